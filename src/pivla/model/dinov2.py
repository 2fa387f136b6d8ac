"""The paper's target encoder: a frozen DINOv2 (ViT-S/14 in the paper) read from a local directory.

``pooled`` gives the CLS token after DINOv2's final layer norm for every camera, concatenated, so
d_z = n_cam x hidden (768 for ViT-S with two cameras). Pixels are prepared as the checkpoint's
preprocessor_config.json says (resize the short side, centre crop, ImageNet normalisation), by hand,
because transformers 5 image processors need torchvision.
"""

from __future__ import annotations

import json

import torch
from torch import nn

from pivla.model.hf.common import check_local_dir
from pivla.model.hf.pixels import PixelSpec

IMAGENET_MEAN = [0.485, 0.456, 0.406]
IMAGENET_STD = [0.229, 0.224, 0.225]


class Dinov2Encoder(nn.Module):
    """Frozen ``Dinov2Model`` with pivla's ``pooled(images)`` interface. When the checkpoint has no
    preprocessor config, images are resized to ``image_size`` rounded to a multiple of the patch size
    (DINOv2 interpolates its position embeddings)."""

    def __init__(self, path: str, image_size: int):
        super().__init__()
        from transformers import Dinov2Model

        p = check_local_dir(path, "target encoder dinov2")
        model_type = json.loads((p / "config.json").read_text()).get("model_type")
        if model_type not in ("dinov2", "dinov2_with_registers"):
            raise ValueError(f"{p}: model_type {model_type!r} is not a DINOv2 checkpoint")
        self.model = Dinov2Model.from_pretrained(str(p), local_files_only=True, dtype=torch.float32)
        self.model.requires_grad_(False)
        self.model.eval()
        patch = int(self.model.config.patch_size)
        fallback = max(patch, round(image_size / patch) * patch)
        spec = PixelSpec.from_dir(p, fallback)
        if not (p / "preprocessor_config.json").is_file():
            spec = PixelSpec(fallback, fallback, (tuple(IMAGENET_MEAN),), (tuple(IMAGENET_STD),), "bicubic")
        self.spec = spec
        self.hidden = int(self.model.config.hidden_size)

    def train(self, mode: bool = True) -> Dinov2Encoder:
        """Always in eval mode: it is a fixed target (no dropout, ever)."""
        return super().train(False)

    def pooled(self, images: torch.Tensor) -> torch.Tensor:
        """(B, n_cam, 3, H, W) in [0, 1] -> (B, n_cam * hidden): the normalised CLS token per camera."""
        if images.ndim != 5:
            raise ValueError(f"expected images (B, n_cam, 3, H, W), got {tuple(images.shape)}")
        b, n = images.shape[:2]
        out = self.model(pixel_values=self.spec(images.flatten(0, 1)))
        return out.pooler_output.float().unflatten(0, (b, n)).flatten(1)

    def external_state_keys(self) -> set[str]:
        """All weights come from the checkpoint directory and never change: not saved with runs."""
        return set(self.state_dict().keys())

