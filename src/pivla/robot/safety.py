"""The safety layer every arm command passes before it reaches the board (or the twin).

Checks, in order: shape and finiteness (NaN/inf are refused, never clipped), joint limits, the tool
centre staying inside a workspace box above the table (forward kinematics of the target), and the size
of one step. Speed is not refused but bounded: the layer returns the pulse rate the firmware must not
exceed. A refusal raises ``SafetyError`` naming the violated limit; the caller decides what to do (the
env adapter stops the episode, the CLI prints the error).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pivla.envs import arm
from pivla.robot.calibration import ArmCalibration


class SafetyError(ValueError):
    """A command was refused; nothing was sent to the arm."""


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
        q = np.asarray(q, dtype=float)
        if q.shape != (len(arm.JOINT_NAMES),):
            raise SafetyError(f"joint target must have shape ({len(arm.JOINT_NAMES)},), got {q.shape}")
        if not np.all(np.isfinite(q)) or not np.isfinite(opening):
            raise SafetyError(f"refusing non-finite command q={q}, gripper={opening}")
        if not 0.0 <= opening <= 1.0:
            raise SafetyError(f"gripper opening {opening} outside [0, 1]")
        lim = self.calibration.limits_rad
        tol = self.config.limit_tolerance_rad
        bad = np.flatnonzero((q < lim[:, 0] - tol) | (q > lim[:, 1] + tol))
        if bad.size:
            i = int(bad[0])
            raise SafetyError(f"joint {arm.JOINT_NAMES[i]} target {q[i]:.3f} rad outside its limits "
                              f"[{lim[i, 0]:.3f}, {lim[i, 1]:.3f}]")
        q = np.clip(q, lim[:, 0], lim[:, 1])
        pos, _ = self._kin.forward_kinematics(q)
        if not self.in_workspace(pos):
            lo, hi = self._box
            raise SafetyError(f"tool centre {np.round(pos, 3).tolist()} m would leave the workspace box "
                              f"{lo.tolist()}..{hi.tolist()}")
        step_bound = self.config.max_step_rad if max_step_rad is ... else max_step_rad
        if q_now is not None and step_bound is not None:
            step = np.abs(q - np.asarray(q_now, float))
            if np.max(step) > step_bound:
                i = int(np.argmax(step))
                raise SafetyError(f"joint {arm.JOINT_NAMES[i]} would jump {step[i]:.3f} rad in one command "
                                  f"(max {step_bound:.3f})")
        gains = [j.us_per_rad for j in self.calibration.joints]
        speed = int(self.config.max_joint_speed * min(gains))
        return CheckedCommand(q, float(opening), max(1, speed))
