"""The paper's target encoder: a frozen DINOv2 (ViT-S/14 in the paper) read from a local directory.

``pooled`` gives the CLS token after DINOv2's final layer norm for every camera, concatenated, so
d_z = n_cam x hidden (768 for ViT-S with two cameras). Pixels are prepared as the checkpoint's
preprocessor_config.json says (resize the short side, centre crop, ImageNet normalisation), by hand,
because transformers 5 image processors need torchvision.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch
from torch import nn

from pivla.model.hf import PixelSpec, check_local_dir

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

    def train(self, mode: bool = True) -> "Dinov2Encoder":
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


def make_tiny_dinov2(out: str | Path, image_size: int = 32, hidden: int = 32, seed: int = 0) -> Path:
    """A random tiny DINOv2 with a preprocessor config in the official layout, for tests and smoke runs."""
    from transformers import Dinov2Config, Dinov2Model

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    patch = max(image_size // 4, 1)
    cfg = Dinov2Config(hidden_size=hidden, num_hidden_layers=2, num_attention_heads=2, intermediate_size=2 * hidden,
                       patch_size=patch, image_size=image_size)
    torch.manual_seed(seed)
    Dinov2Model(cfg).save_pretrained(str(out))
    pre = {"image_processor_type": "BitImageProcessor", "do_resize": True, "size": {"shortest_edge": image_size},
           "resample": 3, "do_center_crop": True, "crop_size": {"height": image_size, "width": image_size},
           "do_rescale": True, "rescale_factor": 1 / 255, "do_normalize": True,
           "image_mean": IMAGENET_MEAN, "image_std": IMAGENET_STD}
    (out / "preprocessor_config.json").write_text(json.dumps(pre, indent=2))
    return out
