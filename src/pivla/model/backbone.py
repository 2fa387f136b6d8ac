"""Backbones: (images, instruction, proprio) -> (h_cog, h_mot), paper Eq. 3.

The interface is deliberately small: a backbone is an ``nn.Module`` whose ``forward(batch)`` returns
``h_cog`` (B, N_cog, d) and ``h_mot`` (B, K, d), with ``d_model`` giving d. A backbone that can serve as
its own target encoder (the default) also exposes ``vision`` with ``pooled(images) -> (B, d_z)``.

``batch`` holds tensors already normalised outside the model:
  images (B, n_cam, 3, H, W) float in [0, 1], text_ids (B, L) int64, text_mask (B, L) bool (True = word),
  proprio (B, P) float.
"""

from __future__ import annotations

import torch
from torch import nn

from pivla.model.config import ModelConfig


class ConvEncoder(nn.Module):
    """A small strided CNN shared by all cameras: image -> grid of feature tokens.

    Four stride-2 stages take a 96-px image to a 6x6 grid; GroupNorm (not BatchNorm) keeps train and
    inference identical at batch 1 and makes an EMA copy a valid target encoder.
    """

    def __init__(self, channels: tuple[int, ...], image_size: int):
        super().__init__()
        layers: list[nn.Module] = []
        c_in = 3
        for i, c in enumerate(channels):
            k = 5 if i == 0 else 3
            layers += [nn.Conv2d(c_in, c, k, stride=2, padding=k // 2), nn.GroupNorm(8, c), nn.GELU()]
            c_in = c
        self.net = nn.Sequential(*layers)
        self.out_channels = c_in
        self.grid = image_size
        for _ in channels:
            self.grid = (self.grid + 1) // 2

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """(B, n_cam, 3, H, W) -> (B, n_cam, C, h, w)."""
        b, n = images.shape[:2]
        feats = self.net(images.flatten(0, 1) * 2.0 - 1.0)
        return feats.unflatten(0, (b, n))

    def pooled(self, images: torch.Tensor) -> torch.Tensor:
        """Global-average-pooled features of every camera, concatenated: (B, n_cam * C)."""
        return self.forward(images).mean(dim=(-1, -2)).flatten(1)


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
        self.vision = ConvEncoder(bc.vision_channels, cfg.image_size)
        n_patch = self.vision.grid**2
        self.img_proj = nn.Linear(self.vision.out_channels, d)
        self.img_pos = nn.Parameter(torch.randn(1, n_cam, n_patch, d) * 0.02)
        self.word_emb = nn.Embedding(vocab_size, d, padding_idx=0)
        self.text_pos = nn.Parameter(torch.randn(1, cfg.max_text_len, d) * 0.02)
        self.proprio_proj = nn.Sequential(nn.Linear(cfg.proprio_dim, d), nn.GELU(), nn.Linear(d, d))
        self.queries = nn.Parameter(torch.randn(1, self.n_cog + cfg.chunk, d) * 0.02)
        layer = nn.TransformerEncoderLayer(
            d, bc.n_heads, d * bc.ff_mult, dropout=bc.dropout, activation="gelu", batch_first=True, norm_first=True
        )
        self.fusion = nn.TransformerEncoder(layer, bc.n_layers, enable_nested_tensor=False)
        self.norm = nn.LayerNorm(d)

    def forward(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        feats = self.vision(batch["images"])  # (B, n_cam, C, h, w)
        b = feats.shape[0]
        img = self.img_proj(feats.flatten(3).transpose(2, 3)) + self.img_pos  # (B, n_cam, hw, d)
        img = img.flatten(1, 2)
        text = self.word_emb(batch["text_ids"]) + self.text_pos[:, : batch["text_ids"].shape[1]]
        prop = self.proprio_proj(batch["proprio"]).unsqueeze(1)
        queries = self.queries.expand(b, -1, -1)
        tokens = torch.cat([img, text, prop, queries], dim=1)
        pad = torch.zeros(b, tokens.shape[1], dtype=torch.bool, device=tokens.device)
        n_img = img.shape[1]
        pad[:, n_img : n_img + text.shape[1]] = ~batch["text_mask"]
        out = self.norm(self.fusion(tokens, src_key_padding_mask=pad))
        q = out[:, -(self.n_cog + self.chunk) :]
        return q[:, : self.n_cog], q[:, self.n_cog :]


def build_backbone(cfg: ModelConfig, vocab_size: int) -> nn.Module:
    """The backbone named by ``cfg.backbone.name``."""
    if cfg.backbone.name == "small":
        return SmallBackbone(cfg, vocab_size)
    if cfg.backbone.name == "hf":
        from pivla.model.hf import HFBackbone

        return HFBackbone(cfg)
    raise ValueError(f"unknown backbone {cfg.backbone.name!r}; choose 'small' or 'hf'")
