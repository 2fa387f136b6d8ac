"""An exponential moving average of the trainable weights: the policy a run deploys when ``--ema-decay`` is set.

A closed-loop policy is judged by its last weights, and the last steps of a short run still move them by
more than a rollout tolerates; the average of the last ~1/(1 - decay) steps is the usual remedy (Diffusion
Policy, ACT-style trainers). Only trainable tensors are averaged: a LoRA run's frozen base is not copied,
and the target encoder, an average of its own (``CMSModel.update_target``), stays as trained.
"""

from __future__ import annotations

import torch
from torch import nn


def ema_decay_at(decay: float, updates: int) -> float:
    """The decay of the ``updates``-th update: ``decay``, tempered early on ((1 + n) / (10 + n)) so that the
    random initial weights do not linger in a short run's average."""
    return min(decay, (1 + updates) / (10 + updates))


class WeightAverage:
    """Shadow copies of a model's trainable parameters, pulled toward the live ones after every optimizer step."""

    def __init__(self, model: nn.Module, decay: float):
        if not 0.0 < decay < 1.0:
            raise ValueError(f"--ema-decay must lie in (0, 1), got {decay}")
        self.decay = decay
        self.updates = 0
        # every name of a shared tensor, as the state dict has them, so that each key of the deployed file is averaged
        self.shadow = {n: p.detach().clone().float()
                       for n, p in model.named_parameters(remove_duplicate=False) if p.requires_grad}

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        live = dict(model.named_parameters(remove_duplicate=False))
        weight = 1.0 - ema_decay_at(self.decay, self.updates)
        torch._foreach_lerp_(list(self.shadow.values()), [live[n].detach().float() for n in self.shadow], weight)
        self.updates += 1

    def averaged(self, state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """``state`` (the model's checkpoint state) with the averaged tensors in place of the live ones."""
        return {k: self.shadow[k].to(v.dtype) if k in self.shadow else v for k, v in state.items()}

    def load(self, tensors: dict[str, torch.Tensor], updates: int, source: str) -> None:
        """Restore a checkpoint's average; a missing or extra tensor is a checkpoint of another model or recipe."""
        if set(tensors) != set(self.shadow):
            raise ValueError(f"{source}: its weight average does not match the model "
                             f"(missing {sorted(set(self.shadow) - set(tensors))[:5]}, "
                             f"unexpected {sorted(set(tensors) - set(self.shadow))[:5]})")
        for k, v in tensors.items():
            if v.shape != self.shadow[k].shape:
                raise ValueError(f"{source}: averaged {k} has shape {tuple(v.shape)}, the model "
                                 f"{tuple(self.shadow[k].shape)}")
            self.shadow[k].copy_(v)
        self.updates = updates
