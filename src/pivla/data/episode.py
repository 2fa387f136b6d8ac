"""Episodes and what every dataset format shares: the observation keys pivla and LIBERO use, the layout a
dataset offers a policy, and the error a dataset raises. The formats on disk: :mod:`pivla.data.hdf5` (pivla's,
LIBERO's) and :mod:`pivla.data.lerobot` (LeRobot v3.0); :mod:`pivla.data.read` reads either."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pivla.data.action_space import ActionSpace
from pivla.model.config import PROPRIO_LENGTHS

IMAGE_KEYS = ("agentview_rgb", "eye_in_hand_rgb")
LOW_DIM_KEYS = ("ee_pos", "ee_ori", "gripper_states", "joint_states")
# what a policy reads of pivla's and LIBERO's files unless told otherwise
PROPRIO_KEYS = tuple(PROPRIO_LENGTHS)
STATE_KEY = "state"  # the one key of a state vector without pivla's per-key names (LeRobot's observation.state)


class DatasetError(ValueError):
    """A dataset file is unreadable, truncated, or does not follow the layout; the message names both."""


@dataclass(frozen=True)
class DatasetLayout:
    """What a dataset offers a policy, read without its pictures: ``cameras`` (image keys, the agent view
    first) and ``proprio`` (keys) a policy reads unless told otherwise, ``vectors`` (every low-dim key with
    its length) and the ``action_space``."""

    cameras: tuple[str, ...]
    proprio: tuple[str, ...]
    vectors: dict[str, int]
    action_space: ActionSpace


@dataclass
class Episode:
    """One demonstration or rollout, time-major arrays of equal length T."""

    actions: np.ndarray
    obs: dict[str, np.ndarray]
    instruction: str
    rewards: np.ndarray | None = None
    dones: np.ndarray | None = None
    success: bool = True
    source: str = "expert"
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.actions = np.asarray(self.actions, dtype=np.float32)
        T = len(self.actions)
        if self.actions.ndim != 2 or self.actions.shape[1] < 1:
            raise DatasetError(f"actions must have shape (T, D), got {self.actions.shape}")
        if self.rewards is None:
            self.rewards = np.zeros(T, np.float32)
            if self.success and T:
                self.rewards[-1] = 1.0
        if self.dones is None:
            self.dones = np.zeros(T, np.uint8)
            if T:
                self.dones[-1] = 1
        self.rewards = np.asarray(self.rewards, dtype=np.float32)
        self.dones = np.asarray(self.dones, dtype=np.uint8)
        for name, arr in [("rewards", self.rewards), ("dones", self.dones), *self.obs.items()]:
            if len(arr) != T:
                raise DatasetError(f"{name} has {len(arr)} steps but actions have {T}")
        numeric = [("actions", self.actions), ("rewards", self.rewards),
                   *((k, v) for k, v in self.obs.items() if np.issubdtype(np.asarray(v).dtype, np.floating))]
        for name, arr in numeric:  # a NaN here would surface later as a NaN loss, far from the file
            finite = np.isfinite(np.asarray(arr)).reshape(T, -1).all(axis=1)
            if not finite.all():
                raise DatasetError(f"{name} holds NaN or inf (first at step {int(np.argmin(finite))})")

    def __len__(self) -> int:
        return len(self.actions)


def check_destination(dst: Path, overwrite: bool, src: Path | None = None) -> None:
    """Refuse a dataset destination that overlaps the source, or that exists and is not empty (unless
    ``overwrite``)."""
    if src is not None:
        a, b = src.resolve(), dst.resolve()
        if a == b or a in b.parents or b in a.parents:
            raise DatasetError(f"destination {dst} overlaps the source {src}")
    if dst.exists() and not overwrite and (not dst.is_dir() or any(dst.iterdir())):
        raise DatasetError(f"{dst} already exists (pass overwrite to replace it)")
