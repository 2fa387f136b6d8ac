"""Pure transforms between numpy samples and the model's tensors (kept out of the model itself)."""

from __future__ import annotations

import numpy as np
import torch

FLOAT_KEYS_UINT8_IMAGES = ("images", "sp_images")


def images_to_tensor(images: np.ndarray, device: torch.device | str = "cpu") -> torch.Tensor:
    """(..., H, W, 3) uint8 -> (..., 3, H, W) float in [0, 1]."""
    t = torch.from_numpy(np.ascontiguousarray(images)).to(device)
    return t.movedim(-1, -3).float().div_(255.0)


def batch_to_tensors(batch: dict[str, np.ndarray], device: torch.device | str = "cpu") -> dict[str, torch.Tensor]:
    """Collated numpy batch -> tensors on ``device``; uint8 images become float CHW."""
    out = {}
    for k, v in batch.items():
        if k in FLOAT_KEYS_UINT8_IMAGES:
            out[k] = images_to_tensor(v, device)
        else:
            out[k] = torch.from_numpy(np.ascontiguousarray(v)).to(device)
    return out
