"""Pure transforms between observations and the model's inputs, kept out of the model itself.

Each transform maps a dict to a new dict and works on one time step or on a whole episode alike (arrays
are time-major, transforms only touch the trailing axes). ``input_pipeline`` composes them once; the training
dataset (``pivla.data.samples.prepare_episode``) and the policy (``pivla.policy.Policy``) both call it, so
training and inference cannot drift apart. The policy's output steps (Eq. 12 de-quantization, Eq. 13, head
selection, un-normalization) are in ``pivla.policy``.

Torch is imported only by the two to-tensor functions. The picture functions (resize, check, pool, centre)
are in ``pivla.model.pixels``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from pivla.data.episode import DatasetError
from pivla.data.normalize import ActionStats, StandardStats
from pivla.model.pixels import check_image, resize_images
from pivla.model.tokenizer import encode as bin_actions

if TYPE_CHECKING:
    import torch

    from pivla.model.config import ModelConfig

FLOAT_KEYS_UINT8_IMAGES = ("images", "sp_images")

Sample = dict[str, Any]


class Transform(Protocol):
    def __call__(self, data: Mapping[str, Any]) -> Sample: ...


class TextTokenizer(Protocol):
    def encode(self, text: str) -> tuple[np.ndarray, np.ndarray]: ...


def compose(transforms: Sequence[Transform]) -> Callable[[Mapping[str, Any]], Sample]:
    """Apply ``transforms`` in order."""

    def run(data: Mapping[str, Any]) -> Sample:
        out = dict(data)
        for t in transforms:
            out = t(out)
        return out

    return run


# -- input transforms --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class StackCameras:
    """The cameras' pictures resized to the model's side and stacked: ``images`` (..., n_cam, S, S, 3) uint8."""

    cameras: tuple[str, ...]
    size: int

    def __call__(self, data: Mapping[str, Any]) -> Sample:
        missing = [c for c in self.cameras if c not in data]
        if missing:
            raise DatasetError(f"observation lacks camera(s) {missing} the policy uses (needs {list(self.cameras)})")
        images = [resize_images(check_image(data[c], c), self.size) for c in self.cameras]
        return {**data, "images": np.stack(images, axis=-4)}


@dataclass(frozen=True)
class ProprioVector:
    """The proprioceptive keys concatenated in order: ``proprio`` (..., P), refused if missing or not finite,
    or (given the training data's ``lengths``) if a key has another length than it had there."""

    keys: tuple[str, ...]
    lengths: tuple[int, ...] | None = None

    def __call__(self, data: Mapping[str, Any]) -> Sample:
        return {**data, "proprio": proprio_vector(data, self.keys, self.lengths)}


def proprio_vector(obs: Mapping[str, Any], keys: Sequence[str], lengths: Sequence[int] | None = None) -> np.ndarray:
    """Concatenate the proprioceptive observation keys (time-major or single step); ``lengths``: each key's
    expected last-axis length, checked so that a wrong one is named rather than found in the total."""
    try:
        parts = [np.atleast_1d(np.asarray(obs[k], np.float32)) for k in keys]
    except KeyError as e:
        raise DatasetError(f"observation is missing proprio key {e.args[0]!r} (needed: {list(keys)})") from None
    except (TypeError, ValueError) as e:
        raise DatasetError(f"observation's proprio keys {list(keys)} must hold numbers: {e}") from None
    for key, part, n in zip(keys, parts, lengths or (), strict=False):
        if n >= 0 and part.shape[-1] != n:
            raise DatasetError(f"observation {key!r} has {part.shape[-1]} numbers, the policy was trained on {n}")
    vec = np.concatenate(parts, axis=-1)
    if not np.isfinite(vec).all():  # read as float32: 1e300 is finite before the cast and inf after
        bad = [k for k, part in zip(keys, parts) if not np.isfinite(part).all()]
        raise DatasetError(f"observation {bad[0]!r} contains NaN or inf, or a value beyond float32's range")
    return vec


@dataclass(frozen=True)
class NormalizeProprio:
    """Standardise ``proprio`` with the training set's statistics."""

    stats: StandardStats
    dim: int

    def __call__(self, data: Mapping[str, Any]) -> Sample:
        proprio = data["proprio"]
        if proprio.shape[-1] != self.dim:
            raise DatasetError(f"proprio has {proprio.shape[-1]} dims, the model reads {self.dim}")
        return {**data, "proprio": self.stats.normalize(proprio).astype(np.float32)}


@dataclass(frozen=True)
class TokenizeInstruction:
    """``instruction`` -> ``text_ids`` and ``text_mask`` (``prompt`` is accepted as its other name)."""

    tokenizer: TextTokenizer

    def __call__(self, data: Mapping[str, Any]) -> Sample:
        text = data.get("instruction", data.get("prompt"))
        if text is None:
            raise DatasetError("observation is missing 'instruction'")
        if not isinstance(text, str):
            raise DatasetError(f"observation 'instruction' must be a str, got {type(text).__name__}")
        ids, mask = self.tokenizer.encode(text)
        return {**data, "text_ids": ids, "text_mask": mask}


@dataclass(frozen=True)
class NormalizeActions:
    """Training targets: ``actions`` normalized to [-1, 1] and their discrete ``bins`` (Eq. 4)."""

    stats: ActionStats
    n_bins: int

    def __call__(self, data: Mapping[str, Any]) -> Sample:
        raw = np.asarray(data["actions"])
        if not np.isfinite(raw).all():
            raise DatasetError("non-finite actions")
        actions = self.stats.normalize(raw)
        return {**data, "actions": actions, "bins": bin_actions(actions, self.n_bins)}


def proprio_steps(cfg: ModelConfig, proprio_stats: StandardStats,
                  lengths: Sequence[int] | None = None) -> list[Callable[[Mapping[str, Any]], Sample]]:
    """Observation -> normalised ``proprio``: the model's input, and the proprio part of a target latent;
    ``lengths``: each proprio key's length in the training data, when known (``NormStats.proprio_layout``)."""
    return [ProprioVector(tuple(cfg.proprio_keys), None if lengths is None else tuple(lengths)),
            NormalizeProprio(proprio_stats, cfg.proprio_dim)]


def input_pipeline(cfg: ModelConfig, proprio_stats: StandardStats, text: TextTokenizer,
                   lengths: Sequence[int] | None = None) -> Callable[[Mapping[str, Any]], Sample]:
    """Observation -> model inputs (``images``, ``proprio``, ``text_ids``, ``text_mask``), as NumPy arrays."""
    return compose([
        StackCameras(tuple(cfg.cameras), cfg.image_size),
        *proprio_steps(cfg, proprio_stats, lengths),
        TokenizeInstruction(text),
    ])


# -- to tensors --------------------------------------------------------------------------------------------
def images_to_tensor(images: np.ndarray, device: torch.device | str = "cpu") -> torch.Tensor:
    """(..., H, W, 3) uint8 -> (..., 3, H, W) float in [0, 1]."""
    import torch

    t = torch.from_numpy(np.ascontiguousarray(images)).to(device)
    return t.movedim(-1, -3).float().div_(255.0)


def batch_to_tensors(batch: Mapping[str, np.ndarray], device: torch.device | str = "cpu") -> dict[str, torch.Tensor]:
    """Collated numpy batch -> tensors on ``device``; uint8 images become float CHW."""
    import torch

    out = {}
    for k, v in batch.items():
        if k in FLOAT_KEYS_UINT8_IMAGES:
            out[k] = images_to_tensor(v, device)
        else:
            out[k] = torch.from_numpy(np.ascontiguousarray(v)).to(device)
    return out
