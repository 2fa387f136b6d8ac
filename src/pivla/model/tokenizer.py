"""Action tokenizer: 256 uniform bins on [-1, 1] (paper Eq. 4) and the de-quantization of Eq. 12.

All functions are pure and work on numpy arrays or torch tensors alike, so the same code serves training,
inference and the control math. Torch is not imported here: a tensor can only exist once something else
imported it, so numpy-only users (``pivla.control``'s math, analysis scripts) do not pay its import.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

import numpy as np


def _torch_of(x):
    """The torch module when ``x`` is a tensor, else None."""
    torch = sys.modules.get("torch")
    return torch if torch is not None and isinstance(x, torch.Tensor) else None


def bin_centers(n_bins: int = 256, low: float = -1.0, high: float = 1.0) -> np.ndarray:
    """Centres c_b of ``n_bins`` equal-width bins covering [low, high]."""
    width = (high - low) / n_bins
    return (low + width * (np.arange(n_bins) + 0.5)).astype(np.float32)


def encode(actions, n_bins: int = 256, low: float = -1.0, high: float = 1.0):
    """Bin index of each normalized action value; values outside [low, high] go to the edge bins."""
    width = (high - low) / n_bins
    if _torch_of(actions) is not None:
        return ((actions - low) / width).floor().long().clamp(0, n_bins - 1)
    return np.clip(np.floor((np.asarray(actions) - low) / width), 0, n_bins - 1).astype(np.int64)


def decode(bins, centers):
    """Bin indices back to their centres (the argmax reading of a discrete prediction)."""
    torch = _torch_of(bins)
    if torch is not None:
        return torch.as_tensor(centers, device=bins.device)[bins]
    return np.asarray(centers)[np.asarray(bins)]


def dequantize(probs, centers):
    """Eq. 12: a_bar[..., d] = sum_b p[..., d, b] * c_b, the expected action under the bin distribution."""
    torch = _torch_of(probs)
    if torch is not None:
        return probs @ torch.as_tensor(centers, dtype=probs.dtype, device=probs.device)
    return np.asarray(probs) @ np.asarray(centers,
                                          dtype=np.float64 if np.asarray(probs).dtype == np.float64 else np.float32)


@dataclass(frozen=True)
class ActionTokenizer:
    """Uniform binning of normalized actions; a thin holder of ``n_bins`` for the pure functions above."""

    n_bins: int = 256
    low: float = -1.0
    high: float = 1.0

    @property
    def centers(self) -> np.ndarray:
        return bin_centers(self.n_bins, self.low, self.high)

    def encode(self, actions):
        return encode(actions, self.n_bins, self.low, self.high)

    def decode(self, bins):
        return decode(bins, self.centers)

    def dequantize(self, probs):
        return dequantize(probs, self.centers)
