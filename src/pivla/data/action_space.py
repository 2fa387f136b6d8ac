"""What an action row means: a dataset declares it, a policy trained on it advertises it.

The dimension D of everything downstream (the model's heads, the bins, the normalisation, the losses, the
served metadata) is the length of the action space a dataset declares, never a constant. The twin and
LIBERO command 7-D end-effector deltas (``EE_DELTA``); a LeRobot SO-101 dataset records six absolute joint
positions (``*.pos`` names, degrees, gripper 0..100).

NumPy-free and torch-free, so a robot laptop's client reads a served policy's action space.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from enum import StrEnum
from typing import Any


class ActionKind(StrEnum):
    """How an action row moves the robot."""

    EE_DELTA = "ee_delta"  # end-effector position and orientation deltas per step, then the gripper command
    JOINT_POSITION = "joint_position"  # absolute joint positions (LeRobot's ``*.pos`` features)
    UNKNOWN = "unknown"  # not recorded; trained on as numbers, per dimension

    @property
    def absolute(self) -> bool:
        """Whether a row is a target pose (holding still repeats it) rather than a motion (holding is zero)."""
        return self is ActionKind.JOINT_POSITION


@dataclass(frozen=True)
class ActionSpace:
    """The meaning of each action dimension.

    ``gripper``: the gripper's index, None for none; ``gripper_range``: its (low, high) values when known;
    ``gripper_binary``: the gripper is a command, low open and high closed (thresholded at zero, as the twin
    and LIBERO have it), not a position; ``units``: per dimension, when known.
    """

    names: tuple[str, ...]
    kind: ActionKind = ActionKind.UNKNOWN
    gripper: int | None = None
    gripper_range: tuple[float, float] | None = None
    gripper_binary: bool = False
    units: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "names", tuple(str(n) for n in self.names))
        object.__setattr__(self, "kind", ActionKind(self.kind))
        if not self.names or len(set(self.names)) != len(self.names):
            raise ValueError(f"an action space needs distinct dimension names, got {list(self.names)}")
        if self.gripper is not None and not 0 <= self.gripper < self.dim:
            raise ValueError(f"gripper index {self.gripper} is outside the {self.dim} action dimensions")
        if self.gripper_range is not None:
            object.__setattr__(self, "gripper_range", tuple(float(v) for v in self.gripper_range))
        if self.gripper_binary and (self.gripper is None or self.gripper_range is None):
            raise ValueError("a binary gripper needs its index and (open, closed) range")
        if self.units is not None:
            object.__setattr__(self, "units", tuple(str(u) for u in self.units))
            if len(self.units) != self.dim:
                raise ValueError(f"{len(self.units)} units for {self.dim} action dimensions")

    @property
    def dim(self) -> int:
        return len(self.names)

    @property
    def binary_gripper(self) -> int | None:
        """The index of a gripper that is an open/close command, else None (what normalisation thresholds)."""
        return self.gripper if self.gripper_binary else None

    def describe(self) -> str:
        """One line for error messages: kind, dimension and names."""
        return f"{self.kind.value} ({self.dim}-D: {', '.join(self.names)})"

    def check_same(self, other: ActionSpace, what: str) -> None:
        """Refuse ``other`` (a dataset's) unless its names and dimension are this one's (a policy's)."""
        if other.names != self.names:
            raise ValueError(f"{what} has actions {other.describe()}, the policy's are {self.describe()}")

    def hold(self, last: Sequence[float] | None) -> list[float]:
        """The action that keeps the robot where it is after ``last``: zero motion with the gripper as it was
        for a delta space, ``last`` itself for an absolute one (which cannot hold before its first action)."""
        if self.kind.absolute:
            if last is None:
                raise ValueError(f"a {self.kind.value} arm has no pose to hold before its first action")
            return [float(v) for v in last]
        out = [0.0] * self.dim
        if self.gripper is not None:
            opened = self.gripper_range[0] if self.gripper_range is not None else 0.0
            out[self.gripper] = float(last[self.gripper]) if last is not None else opened
        return out

    def to_dict(self) -> dict[str, Any]:
        return {"names": list(self.names), "kind": self.kind.value, "gripper": self.gripper,
                "gripper_range": None if self.gripper_range is None else list(self.gripper_range),
                "gripper_binary": self.gripper_binary, "units": None if self.units is None else list(self.units)}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> ActionSpace:
        try:
            rng = d.get("gripper_range")
            return cls(names=tuple(d["names"]), kind=ActionKind(d.get("kind", ActionKind.UNKNOWN.value)),
                       gripper=None if d.get("gripper") is None else int(d["gripper"]),
                       gripper_range=None if rng is None else (float(rng[0]), float(rng[1])),
                       gripper_binary=bool(d.get("gripper_binary", False)),
                       units=None if d.get("units") is None else tuple(d["units"]))
        except (KeyError, TypeError, IndexError) as e:
            raise ValueError(f"not an action space: {dict(d)} ({e!r})") from None


# The twin's and LIBERO's actions: end-effector position (m) and Euler orientation (rad) deltas, scaled by the
# environment to [-1, 1], then the gripper command (-1 open, +1 closed).
EE_DELTA = ActionSpace(names=("x", "y", "z", "roll", "pitch", "yaw", "gripper"), kind=ActionKind.EE_DELTA,
                       gripper=6, gripper_range=(-1.0, 1.0), gripper_binary=True)

POSITION_SUFFIX = ".pos"  # LeRobot's name for a joint's absolute position feature, e.g. "shoulder_pan.pos"
# LeRobot's Feetech arms (SO-100/101) record joints in degrees and the gripper in percent of its range, 0..100
_DEGREES, _GRIPPER_PERCENT = "deg", "percent"


def pose_key(proprio: Sequence[tuple[str, int]], space: ActionSpace) -> str | None:
    """The proprio key that reports the present pose of an arm on absolute targets: the first of the action's
    dimension (LeRobot's ``observation.state`` beside ``action``); None for a delta space or when none has it."""
    if not space.kind.absolute:
        return None
    return next((key for key, n in proprio if n == space.dim), None)


def infer_action_space(names: Sequence[str]) -> ActionSpace:
    """An action space from a dataset's dimension names alone: the twin's names are ``EE_DELTA``; all names
    ``<joint>.pos`` are absolute joint positions (LeRobot's arms: degrees, a ``gripper`` joint 0..100);
    anything else is of unknown kind, with a dimension named ``gripper`` as its (continuous) gripper."""
    names = tuple(str(n) for n in names)
    if names == EE_DELTA.names:
        return EE_DELTA
    gripper = next((i for i, n in enumerate(names) if re.fullmatch(r"gripper(\.pos)?", n)), None)
    if names and all(n.endswith(POSITION_SUFFIX) for n in names):
        units = tuple(_GRIPPER_PERCENT if i == gripper else _DEGREES for i in range(len(names)))
        return ActionSpace(names, ActionKind.JOINT_POSITION, gripper,
                           None if gripper is None else (0.0, 100.0), units=units)
    return ActionSpace(names, ActionKind.UNKNOWN, gripper)


# The SO-101 (LeRobot's so101_follower): servo ids 1..6 in this order, and the six absolute joint positions of its
# actions and state as LeRobot names them. The driver (pivla.robot.so101) and the MuJoCo twin (pivla.envs.so101)
# both read these, so a policy trained in the twin and a dataset recorded on the arm name their actions alike.
SO101_MOTORS = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper")
SO101_JOINT_NAMES = tuple(f"{m}{POSITION_SUFFIX}" for m in SO101_MOTORS)
SO101 = infer_action_space(SO101_JOINT_NAMES)  # degrees for the five body joints, the gripper 0 (closed)..100 (open)
