"""``HFBackbone``: CMS on a local vision-language model (see ``pivla.model.hf`` for the layouts it reads).

One forward pass, OpenVLA-OFT style: the language model reads
``[camera patches][prompt tokens][proprio token][N_cog cognitive queries][K x D action queries]``; the query
block attends to the whole prefix and, bidirectionally, to itself, so all K x D action positions are decoded
in parallel. ``h_cog`` is the final hidden state of the cognitive queries; ``h_mot[k]`` is a linear readout
of the D hidden states of chunk step k (OFT's action head input), feeding the same four heads as the small
backbone. Base weights stay frozen: only LoRA adapters on the language model, the queries, the proprio
projector and the readout train (plus the CMS heads).
"""

from __future__ import annotations

import torch
from torch import nn

from pivla.model.config import ModelConfig
from pivla.model.hf.common import check_local_dir
from pivla.model.hf.lora import enable_activation_checkpointing, lora_target_names
from pivla.model.hf.pixels import PixelSpec
from pivla.model.hf.vlm import VisionPooler, VLMParts, load_vlm, resolve_dtype


class HFBackbone(nn.Module):
    """Backbone ``hf`` (see the module docstring). ``cfg.backbone.path`` is a local checkpoint directory."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        bc = cfg.backbone
        path = check_local_dir(bc.path, "backbone hf")
        kind, vlm = load_vlm(path, resolve_dtype(bc.dtype))
        vlm.requires_grad_(False)
        self.lora = bc.lora_rank > 0
        if self.lora:
            from peft import LoraConfig, get_peft_model

            lcfg = LoraConfig(r=bc.lora_rank, lora_alpha=bc.lora_alpha, lora_dropout=bc.lora_dropout,
                              target_modules=lora_target_names(vlm, tuple(bc.lora_target_modules)))
            vlm = get_peft_model(vlm, lcfg)
        self.vlm = vlm
        self.kind = kind
        if bc.gradient_checkpointing:
            enable_activation_checkpointing(self.base_model(), {"use_reentrant": False})
        self.parts = VLMParts(kind, self.base_model())
        self.pixels = PixelSpec.from_dir(path, self.parts.vision_size)
        d = self.parts.hidden
        self.d_model = d
        self.n_cog, self.chunk, self.action_dim = bc.n_cog_tokens, cfg.chunk, cfg.action_dim
        emb_std = float(self.parts.embed.weight.float().std())
        self.queries = nn.Parameter(torch.randn(1, self.n_cog + cfg.chunk * cfg.action_dim, d) * emb_std)
        self.proprio_proj = nn.Sequential(nn.Linear(cfg.proprio_dim, d), nn.GELU(), nn.Linear(d, d))
        self.motor_readout = nn.Linear(cfg.action_dim * d, d)

    def base_model(self) -> nn.Module:
        """The transformers model (inside the peft wrapper when LoRA is on)."""
        return self.vlm.get_base_model() if self.lora else self.vlm

    @property
    def vision(self) -> VisionPooler:
        """The frozen vision tower, for the ``ema``/``frozen`` target encoders (``dinov2`` is the paper's)."""
        return VisionPooler(self.parts, self.pixels)

    def external_state_keys(self) -> set[str]:
        """Frozen checkpoint weights (rebuilt from ``backbone.path``): left out of run checkpoints."""
        trainable = {n for n, p in self.vlm.named_parameters() if p.requires_grad}
        return {f"vlm.{k}" for k in self.vlm.state_dict() if k not in trainable}

    def merge_lora(self) -> None:
        """Fold the adapters into the base weights (deployment); the backbone then has no LoRA."""
        if self.lora:
            self.vlm = self.vlm.merge_and_unload()
            self.lora = False
            self.parts = VLMParts(self.kind, self.vlm)

    def _attention(self, valid: torch.Tensor, n_query: int, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
        """Additive 4-D mask: causal over the prefix, the query block sees the valid prefix and itself
        (bidirectional); padded words are invisible. Position ids skip padding."""
        n = valid.shape[1]
        i = torch.arange(n, device=valid.device)
        causal = i.view(-1, 1) >= i.view(1, -1)
        in_query = i >= n - n_query
        allowed = (causal | (in_query.view(-1, 1) & in_query.view(1, -1))).unsqueeze(0) & valid.unsqueeze(1)
        allowed = allowed | torch.eye(n, dtype=torch.bool, device=valid.device).unsqueeze(0)
        mask = torch.zeros(allowed.shape, dtype=dtype, device=valid.device)
        mask.masked_fill_(~allowed, torch.finfo(dtype).min)
        position = (valid.long().cumsum(-1) - 1).clamp_min(0)
        return mask.unsqueeze(1), position

    def forward(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        images, ids, text_mask = batch["images"], batch["text_ids"], batch["text_mask"]
        b, n_cam = images.shape[:2]
        dtype = self.parts.embed.weight.dtype
        img = self.parts.image_embeddings(self.pixels(images.flatten(0, 1)).to(dtype))
        img = img.unflatten(0, (b, n_cam)).flatten(1, 2)
        text = self.parts.embed(ids)
        prop = self.proprio_proj(batch["proprio"].float()).unsqueeze(1).to(dtype)
        queries = self.queries.expand(b, -1, -1).to(dtype)
        x = torch.cat([img, text, prop, queries], dim=1)
        ones = lambda k: torch.ones(b, k, dtype=torch.bool, device=x.device)  # noqa: E731
        valid = torch.cat([ones(img.shape[1]), text_mask.bool(), ones(1 + queries.shape[1])], dim=1)
        mask, position = self._attention(valid, queries.shape[1], x.dtype)
        h = self.parts.decoder(inputs_embeds=x, attention_mask=mask, position_ids=position,
                               use_cache=False).last_hidden_state
        hq = h[:, -queries.shape[1] :].float()
        h_cog = hq[:, : self.n_cog]
        h_mot = self.motor_readout(hq[:, self.n_cog :].unflatten(1, (self.chunk, self.action_dim)).flatten(2))
        return h_cog, h_mot
