"""Normalization kept out of the model: pure functions plus the statistics that travel with a checkpoint.

Actions are mapped per dimension to [-1, 1] with the 1st/99th percentiles of the training set (OpenVLA's
BOUNDS_Q99); a gripper that is an open/close command (the twin's and LIBERO's, -1 open, +1 close) is only
thresholded. Proprioception is standardised. Statistics are plain JSON so a checkpoint never needs pickle.

A policy that predicts absolute joint targets relative to the present pose (``ModelConfig.relative_actions``)
has two action statistics: ``action`` normalises the absolute targets the policy exchanges (``to_actions``, the
served metadata), ``target`` the chunk-relative offsets its heads are trained on.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from pivla.data.action_space import EE_DELTA, ActionSpace


@dataclass
class ActionStats:
    q01: list[float]
    q99: list[float]
    # the dimension thresholded to -1 / +1 (a binary gripper), None for none; files always record it
    gripper_dim: int | None = EE_DELTA.binary_gripper

    @classmethod
    def fit(cls, actions: np.ndarray, space: ActionSpace = EE_DELTA, full_range: bool = False) -> ActionStats:
        """The bounds of ``actions`` (N, D): their 1st and 99th percentiles, or with ``full_range`` their minimum
        and maximum (absolute joint targets: a joint's extreme is a pose the arm has to reach, not an outlier)."""
        actions = np.asarray(actions, dtype=np.float64)
        q01 = actions.min(axis=0) if full_range else np.quantile(actions, 0.01, axis=0)
        q99 = actions.max(axis=0) if full_range else np.quantile(actions, 0.99, axis=0)
        return cls(q01=q01.tolist(), q99=q99.tolist(), gripper_dim=space.binary_gripper)

    def _bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = np.asarray(self.q01, np.float32), np.asarray(self.q99, np.float32)
        return lo, np.maximum(hi, lo + 1e-6)

    def normalize(self, actions: np.ndarray) -> np.ndarray:
        """Physical actions -> [-1, 1]; values beyond the percentiles are clipped."""
        lo, hi = self._bounds()
        out = np.clip(2.0 * (np.asarray(actions, np.float32) - lo) / (hi - lo) - 1.0, -1.0, 1.0)
        if self.gripper_dim is not None:
            out[..., self.gripper_dim] = np.where(np.asarray(actions)[..., self.gripper_dim] > 0, 1.0, -1.0)
        return out.astype(np.float32)

    def renormalize(self, actions: np.ndarray, source: ActionStats) -> np.ndarray:
        """Actions normalised by ``source`` in this normalisation, unclipped. A binary gripper's values pass
        through unthresholded (both map it to -1 / +1), so that an average of several policies' grippers is a
        soft vote."""
        if source.gripper_dim != self.gripper_dim:
            raise ValueError(f"gripper dimension {source.gripper_dim} against {self.gripper_dim}: not the same actions")
        (lo_s, hi_s), (lo, hi) = source._bounds(), self._bounds()
        if lo_s.shape != lo.shape:
            raise ValueError(f"{lo_s.size}-D actions against {lo.size}-D: not the same actions")
        a = np.asarray(actions, np.float32)
        out = 2.0 * ((a + 1.0) / 2.0 * (hi_s - lo_s) + lo_s - lo) / (hi - lo) - 1.0
        if self.gripper_dim is not None:
            out[..., self.gripper_dim] = a[..., self.gripper_dim]
        return out.astype(np.float32)

    def unnormalize(self, actions: np.ndarray) -> np.ndarray:
        """[-1, 1] -> physical actions; a binary gripper is thresholded to exactly -1 or +1."""
        lo, hi = self._bounds()
        a = np.asarray(actions, np.float32)
        out = (np.clip(a, -1.0, 1.0) + 1.0) / 2.0 * (hi - lo) + lo
        if self.gripper_dim is not None:
            out[..., self.gripper_dim] = np.where(a[..., self.gripper_dim] > 0, 1.0, -1.0)
        return out.astype(np.float32)


@dataclass
class StandardStats:
    """Per-dimension mean/std (proprioception, target-encoder latents)."""

    mean: list[float]
    std: list[float]

    @classmethod
    def fit(cls, x: np.ndarray, min_std: float = 1e-3) -> StandardStats:
        x = np.asarray(x, dtype=np.float64)
        return cls(mean=x.mean(0).tolist(), std=np.maximum(x.std(0), min_std).tolist())

    def normalize(self, x):
        return (x - np.asarray(self.mean, np.float32)) / np.asarray(self.std, np.float32)


@dataclass
class NormStats:
    action: ActionStats
    proprio: StandardStats
    # each proprio key with its length, in order (what a client must send); None in runs written before it
    proprio_layout: list[tuple[str, int]] | None = None
    # what the actions mean (the training data's); None in runs written before it, which are EE_DELTA
    action_space: ActionSpace | None = None
    # relative actions: the heads' targets (offsets from the pose under ``reference``, the proprio key of the
    # action's dimension, at the chunk's first step); None when the heads predict the actions themselves
    target: ActionStats | None = None
    reference: str | None = None

    @property
    def space(self) -> ActionSpace:
        """The run's action space."""
        return self.action_space or EE_DELTA

    def to_dict(self) -> dict:
        out = {"action": asdict(self.action), "proprio": asdict(self.proprio),
               "proprio_layout": None if self.proprio_layout is None else [list(x) for x in self.proprio_layout],
               "action_space": None if self.action_space is None else self.action_space.to_dict()}
        if self.target is not None:
            out.update(target=asdict(self.target), reference=self.reference)
        return out

    @classmethod
    def from_dict(cls, d: dict) -> NormStats:
        layout, space = d.get("proprio_layout"), d.get("action_space")
        return cls(action=ActionStats(**d["action"]), proprio=StandardStats(**d["proprio"]),
                   proprio_layout=[(str(k), int(n)) for k, n in layout] if layout is not None else None,
                   action_space=ActionSpace.from_dict(space) if space is not None else None,
                   target=ActionStats(**d["target"]) if d.get("target") is not None else None,
                   reference=d.get("reference"))

    def relative_dims(self) -> np.ndarray:
        """The action dimensions a relative policy predicts as offsets: all but the gripper (whose present
        position lags and stops at a held object, so its command stays absolute)."""
        dims = np.arange(self.space.dim)
        return dims[dims != self.space.gripper] if self.space.gripper is not None else dims

    def to_absolute(self, offsets: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """Physical chunk(s) (..., K, D) from normalised offsets, for the pose(s) ``reference`` (..., D) at the chunk's
        first step (a relative policy's inverse of its training targets)."""
        out = self.target.unnormalize(offsets)
        dims = self.relative_dims()
        out[..., dims] += np.asarray(reference, np.float32)[..., None, dims]
        return out
