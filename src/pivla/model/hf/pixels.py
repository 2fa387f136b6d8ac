"""A checkpoint's pixel preprocessing (``PixelSpec``), shared by the VLM backbone and the DINOv2 target encoder."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F

_RESAMPLE = {0: "nearest", 2: "bilinear", 3: "bicubic", "bilinear": "bilinear", "bicubic": "bicubic"}


@dataclass(frozen=True)
class PixelSpec:
    """How a checkpoint wants its pixels: resize, optional centre crop, then one normalisation per stacked
    view (OpenVLA's fused backbone takes the same image twice, channel-stacked, normalised for each tower).
    Read from preprocessor_config.json because transformers 5 image processors need torchvision."""

    resize: int
    crop: int
    means: tuple[tuple[float, ...], ...]
    stds: tuple[tuple[float, ...], ...]
    mode: str = "bicubic"

    @classmethod
    def from_dir(cls, path: Path, image_size: int) -> PixelSpec:
        """``image_size`` is the vision tower's input size (from config.json), used when the preprocessor
        config is absent or does not say."""
        f = path / "preprocessor_config.json"
        pc = json.loads(f.read_text()) if f.is_file() else {}
        if "means" in pc:  # Prismatic / OpenVLA
            sizes = [int(s[-1]) for s in pc.get("input_sizes", [[3, image_size, image_size]])]
            interp = (pc.get("interpolations") or ["bicubic"])[0]
            return cls(sizes[0], sizes[0], tuple(map(tuple, pc["means"])), tuple(map(tuple, pc["stds"])),
                       _RESAMPLE.get(interp, "bicubic"))
        size = pc.get("size", image_size)
        if isinstance(size, dict):
            size = size.get("shortest_edge") or size.get("height") or image_size
        crop = pc.get("crop_size", size) if pc.get("do_center_crop", False) else size
        if isinstance(crop, dict):
            crop = crop.get("height") or crop.get("shortest_edge") or size
        mean = tuple(pc.get("image_mean", (0.5, 0.5, 0.5)))
        std = tuple(pc.get("image_std", (0.5, 0.5, 0.5)))
        return cls(int(size), int(crop), (mean,), (std,), _RESAMPLE.get(pc.get("resample", 3), "bicubic"))

    @property
    def channels(self) -> int:
        return 3 * len(self.means)

    def __call__(self, images: torch.Tensor) -> torch.Tensor:
        """(N, 3, H, W) in [0, 1] -> (N, 3 * views, crop, crop), normalised."""
        if images.ndim != 4 or images.shape[1] != 3:
            raise ValueError(f"expected images (N, 3, H, W), got {tuple(images.shape)}")
        x = images.float()
        if x.shape[-1] != self.resize or x.shape[-2] != self.resize:
            smooth = self.mode in ("bilinear", "bicubic")
            x = F.interpolate(x, size=(self.resize, self.resize), mode=self.mode,
                              align_corners=False if smooth else None, antialias=smooth).clamp_(0.0, 1.0)
        if self.crop < self.resize:
            top = (self.resize - self.crop) // 2
            x = x[..., top : top + self.crop, top : top + self.crop]
        views = []
        for mean, std in zip(self.means, self.stds):
            m = torch.tensor(mean, device=x.device).view(1, 3, 1, 1)
            s = torch.tensor(std, device=x.device).view(1, 3, 1, 1)
            views.append((x - m) / s)
        return torch.cat(views, dim=1)
