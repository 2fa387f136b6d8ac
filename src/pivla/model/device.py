"""Where a model runs."""

from __future__ import annotations

import torch


def select_device(device: str = "auto") -> torch.device:
    """``auto``: the GPU when there is one, else the CPU; otherwise the device named (cpu, cuda, cuda:N)."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)
