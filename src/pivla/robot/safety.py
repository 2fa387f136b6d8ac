"""The safety layer every arm command passes before it reaches the board (or the twin, or the servo bus).

Checks, in order: shape and finiteness (NaN/inf are refused, never clipped), joint limits, the tool
centre staying inside a workspace box above the table (forward kinematics of the target), and the size
of one step. Speed is not refused but bounded: the layer returns the pulse rate the firmware must not
exceed. A refusal raises ``SafetyError`` naming the violated limit; the caller decides what to do (the
env adapter stops the episode, the CLI prints the error).

The joint-space part (``JointGuard``: finite values, calibrated limits, the step of one command) is shared
with arms that have no kinematic model here, such as the SO-101 (``pivla.robot.so101``), where a violation
may be clipped instead of refused.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from pivla import arm
from pivla.robot.calibration import ArmCalibration

log = logging.getLogger(__name__)

Violation = Literal["clip", "refuse"]


class SafetyError(ValueError):
    """A command was refused; nothing was sent to the arm."""


class JointGuard:
    """Joint-space checks of every command: shape, finite values, the calibrated limits and a bounded step.

    A target outside the limits (beyond ``tolerance``) or stepping further than the bound from the previous
    command is refused (``SafetyError``) or clipped, per ``on_limit`` / ``on_step``; within the tolerance it
    is always clipped. Non-finite values are always refused: there is nothing sensible to clip them to.
    """

    def __init__(self, names: Sequence[str], lower, upper, units: str | Sequence[str],
                 on_limit: Violation = "refuse", on_step: Violation = "refuse", tolerance: float = 0.0) -> None:
        self.names = tuple(names)
        self.lower, self.upper = np.asarray(lower, float), np.asarray(upper, float)
        n = len(self.names)
        if self.lower.shape != (n,) or self.upper.shape != (n,) or not np.all(self.lower < self.upper):
            raise ValueError(f"limits must be two increasing {n}-vectors, got {self.lower}, {self.upper}")
        self.units = (units,) * n if isinstance(units, str) else tuple(units)
        self.on_limit, self.on_step, self.tolerance = on_limit, on_step, tolerance

    def limits(self, q) -> np.ndarray:
        """``q`` inside the limits (clipped), or SafetyError."""
        q = np.asarray(q, dtype=float)
        n = len(self.names)
        if q.shape != (n,):
            raise SafetyError(f"joint target must have shape ({n},), got {q.shape}")
        if not np.all(np.isfinite(q)):
            raise SafetyError(f"refusing non-finite command {q}")
        tol = self.tolerance
        bad = np.flatnonzero((q < self.lower - tol) | (q > self.upper + tol))
        if bad.size:
            i = int(bad[0])
            msg = (f"joint {self.names[i]} target {q[i]:.3f} {self.units[i]} outside its limits "
                   f"[{self.lower[i]:.3f}, {self.upper[i]:.3f}]")
            if self.on_limit == "refuse":
                raise SafetyError(msg)
            log.debug("%s: clipped", msg)  # the caller gets the clipped target back
        return np.clip(q, self.lower, self.upper)

    def step(self, q: np.ndarray, q_from: np.ndarray | None, bound) -> np.ndarray:
        """``q`` at most ``bound`` (a number or one per joint; None: unbounded) from ``q_from``."""
        if q_from is None or bound is None:
            return q
        delta = q - np.asarray(q_from, float)
        bound = np.broadcast_to(np.asarray(bound, float), delta.shape)
        over = np.abs(delta) / bound
        if np.max(over) <= 1.0:
            return q
        i = int(np.argmax(over))
        msg = (f"joint {self.names[i]} would jump {abs(delta[i]):.3f} {self.units[i]} in one command "
               f"(max {bound[i]:.3f})")
        if self.on_step == "refuse":
            raise SafetyError(msg)
        log.debug("%s: clipped", msg)
        return np.asarray(q_from, float) + np.clip(delta, -bound, bound)


@dataclass
class SafetyConfig:
    """Workspace box in the base frame (metres); speeds in rad/s; ``max_step_rad`` per streamed command."""

    workspace_min: tuple[float, float, float] = (-0.10, -0.35, 0.005)
    workspace_max: tuple[float, float, float] = (0.40, 0.35, 0.45)
    max_joint_speed: float = 1.5
    max_step_rad: float | None = 0.6
    limit_tolerance_rad: float = 1e-3


@dataclass(frozen=True)
class CheckedCommand:
    q: np.ndarray
    opening: float
    speed_us_s: int


class SafetyLayer:
    def __init__(self, calibration: ArmCalibration, config: SafetyConfig | None = None) -> None:
        self.calibration = calibration
        self.config = config or SafetyConfig()
        self._kin = arm.Kinematics()
        lo, hi = np.asarray(self.config.workspace_min, float), np.asarray(self.config.workspace_max, float)
        if lo.shape != (3,) or hi.shape != (3,) or not np.all(lo < hi):
            raise ValueError(f"workspace box must be two increasing 3-vectors, got {lo}, {hi}")
        self._box = (lo, hi)
        lim = calibration.limits_rad
        self._joints = JointGuard(arm.JOINT_NAMES, lim[:, 0], lim[:, 1], "rad",
                                  tolerance=self.config.limit_tolerance_rad)

    def in_workspace(self, pos: np.ndarray) -> bool:
        lo, hi = self._box
        return bool(np.all(pos >= lo) and np.all(pos <= hi))

    def clip_to_workspace(self, pos: np.ndarray) -> np.ndarray:
        lo, hi = self._box
        return np.clip(pos, lo, hi)

    def check(self, q: np.ndarray, opening: float, q_now: np.ndarray | None = None,
              max_step_rad: float | None = ...) -> CheckedCommand:
        """Validates a joint target; returns it with the firmware speed limit to use.

        ``max_step_rad`` overrides the config's per-command step bound (None: unbounded, e.g. for a
        deliberate point-to-point move that the firmware's rate limit then executes slowly).
        """
        if not np.isfinite(opening):
            raise SafetyError(f"refusing non-finite gripper opening {opening}")
        if not 0.0 <= opening <= 1.0:
            raise SafetyError(f"gripper opening {opening} outside [0, 1]")
        q = self._joints.limits(q)
        pos, _ = self._kin.forward_kinematics(q)
        if not self.in_workspace(pos):
            lo, hi = self._box
            raise SafetyError(f"tool centre {np.round(pos, 3).tolist()} m would leave the workspace box "
                              f"{lo.tolist()}..{hi.tolist()}")
        step_bound = self.config.max_step_rad if max_step_rad is ... else max_step_rad
        q = self._joints.step(q, q_now, step_bound)
        gains = [j.us_per_rad for j in self.calibration.joints]
        speed = int(self.config.max_joint_speed * min(gains))
        return CheckedCommand(q, float(opening), max(1, speed))
