"""Pure transforms between numpy samples and the model's tensors (kept out of the model itself)."""

from __future__ import annotations

import cv2
import numpy as np
import torch

FLOAT_KEYS_UINT8_IMAGES = ("images", "sp_images")


def images_to_tensor(images: np.ndarray, device: torch.device | str = "cpu") -> torch.Tensor:
    """(..., H, W, 3) uint8 -> (..., 3, H, W) float in [0, 1]."""
    t = torch.from_numpy(np.ascontiguousarray(images)).to(device)
    return t.movedim(-1, -3).float().div_(255.0)


def area_downsample(images: np.ndarray, factor: int, out: np.ndarray | None = None) -> np.ndarray:
    """(..., H, W, 3) uint8 -> (..., 3, H / factor, W / factor) float32 in [0, 1], each pixel the mean of a
    ``factor`` x ``factor`` block: ``images_to_tensor`` then ``avg_pool2d(factor)``, without PyTorch.

    AURD encodes every new observation, and this runs in front of the ONNX target graph on each one. OpenCV's
    area resize at an integer factor is that block mean; for an 80-px picture it takes ~18 us where NumPy's
    two-axis ``sum`` took ~220 us (docs/results.md, session 18). ``out``: a C-contiguous float32 array of the
    result's shape to write into (the graph's bound input), instead of a new array.
    """
    *lead, h, w, c = images.shape
    if h % factor or w % factor:
        raise ValueError(f"area_downsample: factor {factor} must divide the image size {h}x{w}")
    hs, ws = h // factor, w // factor
    shape = (*lead, c, hs, ws)
    if out is None:
        out = np.empty(shape, np.float32)
    elif out.shape != shape or out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ValueError(f"area_downsample: out must be a C-contiguous float32 array of shape {shape}, "
                         f"got {out.dtype} {out.shape}")
    for image, dst in zip(images.reshape(-1, h, w, c), out.reshape(-1, c, hs, ws)):
        pooled = image.astype(np.float32)
        if factor > 1:
            pooled = cv2.resize(pooled, (ws, hs), interpolation=cv2.INTER_AREA).reshape(hs, ws, c)
        np.multiply(pooled.transpose(2, 0, 1), np.float32(1.0 / 255.0), out=dst)
    return out


def batch_to_tensors(batch: dict[str, np.ndarray], device: torch.device | str = "cpu") -> dict[str, torch.Tensor]:
    """Collated numpy batch -> tensors on ``device``; uint8 images become float CHW."""
    out = {}
    for k, v in batch.items():
        if k in FLOAT_KEYS_UINT8_IMAGES:
            out[k] = images_to_tensor(v, device)
        else:
            out[k] = torch.from_numpy(np.ascontiguousarray(v)).to(device)
    return out
