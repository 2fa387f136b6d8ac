"""Pictures as the models read them, without torch: resizing, checking, area pooling and the small CNN's
[-1, 1] convention. Training (``pivla.data.transforms``), the policy and a robot laptop preparing pictures
for the exported target encoder (``pivla.model.onnx_encoder``) all use these functions."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np


def centre(images, inplace: bool = False):
    """[0, 1] pixels -> [-1, 1] (tensors or arrays; ``inplace`` writes into ``images``, e.g. the ONNX graph's
    bound input)."""
    if inplace:
        images *= 2.0
        images -= 1.0
        return images
    return images * 2.0 - 1.0


def resize_images(images: np.ndarray, size: int) -> np.ndarray:
    """(..., H, W, 3) uint8 -> (..., size, size, 3) uint8 with area interpolation (a no-op when equal)."""
    if images.shape[-3] == size and images.shape[-2] == size:
        return images
    flat = images.reshape(-1, *images.shape[-3:])
    out = np.stack([cv2.resize(im, (size, size), interpolation=cv2.INTER_AREA) for im in flat])
    return out.reshape(*images.shape[:-3], size, size, 3)


def area_downsample(images: np.ndarray, factor: int, out: np.ndarray | None = None) -> np.ndarray:
    """(..., H, W, 3) uint8 -> (..., 3, H / factor, W / factor) float32 in [0, 1], each pixel the mean of a
    ``factor`` x ``factor`` block: ``images_to_tensor`` then ``avg_pool2d(factor)``, without PyTorch.

    AURD encodes every new observation, and this runs in front of the ONNX target graph on each one. OpenCV's
    area resize at an integer factor is that block mean; for an 80-px picture it takes ~18 us where NumPy's
    two-axis ``sum`` took ~220 us (docs/experiments.md#the-encoding-path-in-the-control-loop). ``out``: a
    C-contiguous float32 array of the result's shape to write into (the graph's bound input).
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


def check_image(image: Any, key: str) -> np.ndarray:
    """An (H, W, 3) uint8 picture (or a time-major stack of them), refused by name otherwise."""
    im = np.asarray(image)
    if im.ndim < 3 or im.shape[-1] != 3 or im.dtype != np.uint8:
        raise ValueError(f"observation {key!r} must be an HxWx3 uint8 image, got {im.shape} {im.dtype}")
    return im
