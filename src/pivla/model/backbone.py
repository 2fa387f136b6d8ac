"""Backbones: (images, instruction, proprio) -> (h_cog, h_mot), paper Eq. 3.

The interface is deliberately small: a backbone is an ``nn.Module`` whose ``forward(batch)`` returns
``h_cog`` (B, N_cog, d) and ``h_mot`` (B, K, d), with ``d_model`` giving d. A backbone that can serve as
its own target encoder (the default) also exposes ``vision`` with ``pooled(images) -> (B, d_z)``.

``batch`` holds tensors already normalised outside the model:
  images (B, n_cam, 3, H, W) float in [0, 1], text_ids (B, L) int64, text_mask (B, L) bool (True = word),
  proprio (B, P) float; with ``ModelConfig.action_prefix``, optionally action_prefix (B, K, D) normalised actions
  in flight and prefix_mask (B, K) (1 where given).
"""

from __future__ import annotations

import torch
from torch import nn

from pivla.model.config import ModelConfig
from pivla.model.hf.backbone import HFBackbone
from pivla.model.pixels import centre


class ConvEncoder(nn.Module):
    """A small strided CNN shared by all cameras: image -> grid of feature tokens.

    Four stride-2 stages take a 96-px image to a 6x6 grid; GroupNorm (not BatchNorm) keeps train and
    inference identical at batch 1 and makes an EMA copy a valid target encoder. ``res_blocks[i]`` residual
    3x3 convolutions at stage i's resolution add depth without losing resolution.
    """

    def __init__(self, channels: tuple[int, ...], image_size: int, res_blocks: tuple[int, ...] = ()):
        super().__init__()
        if len(res_blocks) not in (0, len(channels)):
            raise ValueError(f"res_blocks {res_blocks} must give one count per stage of {channels}")
        layers: list[nn.Module] = []
        c_in = 3
        for i, c in enumerate(channels):
            k = 5 if i == 0 else 3
            layers += [nn.Conv2d(c_in, c, k, stride=2, padding=k // 2), nn.GroupNorm(8, c), nn.GELU()]
            c_in = c
        self.net = nn.Sequential(*layers)
        counts = res_blocks or (0,) * len(channels)
        self.res = nn.ModuleList(
            nn.ModuleList(_ResBlock(c) for _ in range(n)) for c, n in zip(channels, counts, strict=True)
        )
        self.out_channels = c_in
        self.image_size = image_size
        self.grid = self._grid(len(channels))

    def _grid(self, stages: int) -> int:
        """Side of the feature grid after ``stages`` stride-2 stages."""
        grid = self.image_size
        for _ in range(stages):
            grid = (grid + 1) // 2
        return grid

    def truncate(self, stages: int) -> ConvEncoder:
        """Keep only the first ``stages`` stages (in place): a target encoder that reads an earlier stage."""
        if not 1 <= stages <= len(self.res):
            raise ValueError(f"a CNN of {len(self.res)} stages cannot keep {stages}")
        self.net = self.net[: 3 * stages]
        self.res = self.res[:stages]
        self.out_channels = self.net[3 * stages - 3].out_channels
        self.grid = self._grid(stages)
        return self

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """(B, n_cam, 3, H, W) -> (B, n_cam, C, h, w)."""
        return self.stages(images)[-1]

    def stages(
        self, images: torch.Tensor, centred: bool = False, film: list[torch.Tensor] | None = None
    ) -> list[torch.Tensor]:
        """The output of every stage, each (B, n_cam, C_i, h_i, w_i), of images in [0, 1] (or already
        ``centre``d). ``film`` holds one (B, 2 * C_i) scale-and-shift per stage, shared by the cameras."""
        b, n = images.shape[:2]
        x = images.flatten(0, 1)
        if not centred:
            x = centre(x)
        outs = []
        for i, layer in enumerate(self.net):
            x = layer(x)
            if i % 3 == 2:  # conv, norm, activation
                for block in self.res[i // 3]:
                    x = block(x)
                if film is not None:
                    x = modulate(x, film[i // 3].repeat_interleave(n, dim=0))
                outs.append(x.unflatten(0, (b, n)))
        return outs

    def pooled(self, images: torch.Tensor, centred: bool = False, grid: int = 1) -> torch.Tensor:
        """The last stage's features of every camera averaged over the picture (``grid`` 1) or over each cell of
        a grid x grid partition, which keeps where things are, concatenated: (B, n_cam * C * grid**2)."""
        feats = self.stages(images, centred)[-1]
        if grid == 1:
            return feats.mean(dim=(-1, -2)).flatten(1)
        return nn.functional.adaptive_avg_pool2d(feats.flatten(0, 1), grid).reshape(feats.shape[0], -1)


def modulate(x: torch.Tensor, film: torch.Tensor) -> torch.Tensor:
    """FiLM: (N, C, h, w) features times (1 + gamma) plus beta, per channel, from ``film`` = (N, 2C) [gamma, beta].
    A zero ``film`` is the identity, so a FiLM layer initialised at zero starts as the unconditioned CNN."""
    gamma, beta = film[:, :, None, None].chunk(2, dim=1)
    return x * (1 + gamma) + beta


class _ResBlock(nn.Module):
    """x + GELU(GN(conv3x3(x))): one more layer of context at the same resolution."""

    def __init__(self, channels: int):
        super().__init__()
        self.body = nn.Sequential(nn.Conv2d(channels, channels, 3, padding=1), nn.GroupNorm(8, channels), nn.GELU())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.body(x)


class SpatialSoftmax(nn.Module):
    """Feature map -> K keypoints: the softmax-weighted mean image coordinates (x, y in [-1, 1]) of K
    learned 1x1 feature detectors (Levine et al. 2016). Coordinates are what a controller needs, and
    they come out exactly instead of being re-learned from patch positions."""

    def __init__(self, channels: int, keypoints: int):
        super().__init__()
        self.detect = nn.Conv2d(channels, keypoints, 1)
        self.log_temperature = nn.Parameter(torch.zeros(1))  # shape (1,), not (): FSDP cannot shard 0-d tensors

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        key = prefix + "log_temperature"
        if key in state_dict and state_dict[key].dim() == 0:  # checkpoints written before it had shape (1,)
            state_dict[key] = state_dict[key].reshape(1)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def forward(self, feats: torch.Tensor) -> torch.Tensor:
        """(N, C, h, w) -> (N, K, 2)."""
        logits = self.detect(feats)
        h, w = logits.shape[-2:]
        attn = torch.softmax(logits.flatten(2) / self.log_temperature.exp(), dim=-1).unflatten(2, (h, w))
        ys = torch.linspace(-1.0, 1.0, h, device=feats.device, dtype=attn.dtype)
        xs = torch.linspace(-1.0, 1.0, w, device=feats.device, dtype=attn.dtype)
        return torch.stack([(attn.sum(-2) * xs).sum(-1), (attn.sum(-1) * ys).sum(-1)], dim=-1)


class SmallBackbone(nn.Module):
    """CPU-friendly default: CNN image tokens + word tokens + a proprio token + learned query tokens,
    fused by a small pre-norm transformer. The N_cog cognitive queries read out h_cog, the K motor
    queries (one per chunk step) read out h_mot."""

    def __init__(self, cfg: ModelConfig, vocab_size: int):
        super().__init__()
        bc = cfg.backbone
        d = bc.d_model
        self.d_model = d
        self.n_cog = bc.n_cog_tokens
        self.chunk = cfg.chunk
        n_cam = len(cfg.cameras)
        self.vision = ConvEncoder(bc.vision_channels, cfg.image_size, bc.res_blocks)
        self.grid_tokens = bc.grid_tokens
        n_patch = self.vision.grid**2 if bc.grid_tokens else 1
        self.img_proj = nn.Linear(self.vision.out_channels, d)
        self.img_pos = nn.Parameter(torch.randn(1, n_cam, n_patch, d) * 0.02)
        self.keypoints = None
        if bc.keypoints > 0:
            self.keypoint_stage = bc.keypoint_stage
            self.keypoints = SpatialSoftmax(bc.vision_channels[bc.keypoint_stage], bc.keypoints)
            self.kp_proj = nn.Sequential(nn.Linear(2 * bc.keypoints, d), nn.GELU(), nn.Linear(d, d))
            self.kp_cam = nn.Parameter(torch.randn(1, n_cam, d) * 0.02)
        self.word_emb = nn.Embedding(vocab_size, d, padding_idx=0)
        self.film = None
        if bc.film:
            self.film = nn.ModuleList(nn.Linear(d, 2 * c) for c in bc.vision_channels)
            for lin in self.film:
                nn.init.zeros_(lin.weight)
                nn.init.zeros_(lin.bias)
        self.text_pos = nn.Parameter(torch.randn(1, cfg.max_text_len, d) * 0.02)
        self.proprio_proj = nn.Sequential(nn.Linear(cfg.proprio_dim, d), nn.GELU(), nn.Linear(d, d))
        self.queries = nn.Parameter(torch.randn(1, self.n_cog + cfg.chunk, d) * 0.02)
        self.prefix_proj = None
        if cfg.action_prefix > 0:
            # the k-th motor query is told "action k is already decided" by adding its embedding (and a flag)
            self.prefix_proj = nn.Linear(cfg.action_dim, d)
            self.prefix_flag = nn.Parameter(torch.randn(d) * 0.02)
        layer = nn.TransformerEncoderLayer(
            d, bc.n_heads, d * bc.ff_mult, dropout=bc.dropout, activation="gelu", batch_first=True, norm_first=True
        )
        self.fusion = nn.TransformerEncoder(layer, bc.n_layers, enable_nested_tensor=False)
        self.norm = nn.LayerNorm(d)

    def forward(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        stages = self.vision.stages(batch["images"], film=self._film(batch))
        feats = stages[-1]  # (B, n_cam, C, h, w)
        b, n_cam = feats.shape[:2]
        cells = feats.flatten(3).transpose(2, 3) if self.grid_tokens else feats.mean(dim=(-1, -2)).unsqueeze(2)
        img = self.img_proj(cells) + self.img_pos  # (B, n_cam, hw or 1, d)
        img = img.flatten(1, 2)
        if self.keypoints is not None:
            kp = self.keypoints(stages[self.keypoint_stage].flatten(0, 1))  # (B * n_cam, K, 2)
            kp = kp.flatten(1).unflatten(0, (b, n_cam))  # (B, n_cam, 2K)
            img = torch.cat([img, self.kp_proj(kp) + self.kp_cam], dim=1)
        text = self.word_emb(batch["text_ids"]) + self.text_pos[:, : batch["text_ids"].shape[1]]
        prop = self.proprio_proj(batch["proprio"]).unsqueeze(1)
        queries = self._told_prefix(self.queries.expand(b, -1, -1), batch)
        tokens = torch.cat([img, text, prop, queries], dim=1)
        pad = torch.zeros(b, tokens.shape[1], dtype=torch.bool, device=tokens.device)
        n_img = img.shape[1]
        pad[:, n_img : n_img + text.shape[1]] = ~batch["text_mask"]
        out = self.norm(self.fusion(tokens, src_key_padding_mask=pad))
        q = out[:, -(self.n_cog + self.chunk) :]
        return q[:, : self.n_cog], q[:, self.n_cog :]

    def _told_prefix(self, queries: torch.Tensor, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """The motor queries of the actions in flight (``action_prefix`` (B, K, D) normalised, ``prefix_mask`` (B, K),
        1 where given) carry those actions; a batch without them, or a mask of zeros, leaves them as they are."""
        if self.prefix_proj is None or "action_prefix" not in batch:
            return queries
        given = batch["prefix_mask"].to(queries.dtype).unsqueeze(-1)
        told = given * (self.prefix_proj(batch["action_prefix"].to(queries.dtype)) + self.prefix_flag)
        return torch.cat([queries[:, : self.n_cog], queries[:, self.n_cog :] + told], dim=1)

    def _film(self, batch: dict[str, torch.Tensor]) -> list[torch.Tensor] | None:
        """Each CNN stage's (B, 2C) FiLM parameters from the mean of the instruction's word embeddings."""
        if self.film is None:
            return None
        mask = batch["text_mask"].unsqueeze(-1).to(self.word_emb.weight.dtype)
        words = (self.word_emb(batch["text_ids"]) * mask).sum(1) / mask.sum(1).clamp(min=1)
        return [lin(words) for lin in self.film]


def build_backbone(cfg: ModelConfig, vocab_size: int) -> nn.Module:
    """The backbone named by ``cfg.backbone.name``."""
    if cfg.backbone.name == "small":
        return SmallBackbone(cfg, vocab_size)
    if cfg.backbone.name == "hf":
        return HFBackbone(cfg)
    raise ValueError(f"unknown backbone {cfg.backbone.name!r}; choose 'small' or 'hf'")
