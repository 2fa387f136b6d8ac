"""A gymnasium env over an SO-101, so that teleoperation, recording, replay and the policy runners drive it like
the pivla arm's ``RobotEnv``.

Actions are LeRobot's: six absolute joint positions (``shoulder_pan.pos`` ... ``gripper.pos``; degrees, the
gripper 0..100). ``step`` sends one through the arm's guard (``SO101.command``: finite, inside the calibrated
range, a bounded step from the previous goal; clipped or refused as the arm is configured), reports the goal
as sent in ``info["command"]`` and waits out the control period. Observations are LeRobot's SO-101 layout
under pivla's keys: the cameras (``front``, ``wrist``) and ``state``, the six present positions. A bus fault
trips the arm (it holds) and ``step`` raises ``ArmHeld`` until ``robot.resume()``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from pivla.data.action_space import POSITION_SUFFIX, infer_action_space
from pivla.robot.robot import Camera, Ticker
from pivla.robot.safety import SafetyError
from pivla.robot.so101 import MOTORS, ROBOT_TYPE, SO101, ArmHeld

JOINT_NAMES = tuple(f"{m}{POSITION_SUFFIX}" for m in MOTORS)  # LeRobot's action and state names
ACTION_SPACE = infer_action_space(JOINT_NAMES)
STATE_KEY = "state"  # the key LeRobot's observation.state reads back as
__all__ = ["ACTION_SPACE", "JOINT_NAMES", "ROBOT_TYPE", "SO101Env", "SO101EnvConfig"]


@dataclass
class SO101EnvConfig:
    """``fps`` paces steps when ``realtime`` (LeRobot records the SO-101 at 30 fps)."""

    fps: float = 30.0
    realtime: bool = True
    max_steps: int = 300


class SO101Env(gym.Env):
    metadata = {"render_modes": []}

    def __init__(self, robot: SO101, cameras: dict[str, Camera], instruction: str,
                 config: SO101EnvConfig | None = None) -> None:
        self.robot = robot
        self.cameras = cameras
        self.instruction = instruction
        self.config = config or SO101EnvConfig()
        lower, upper = robot.calibration.limits()
        self.lower, self.upper = lower, upper
        self.action_space = gym.spaces.Box(lower.astype(np.float32), upper.astype(np.float32), (len(MOTORS),),
                                           np.float32)
        self._steps = 0
        self._ticker = Ticker(self.config.fps)

    @property
    def control_hz(self) -> float:
        return float(self.config.fps)

    def observe(self) -> dict[str, Any]:
        obs: dict[str, Any] = {key: cam.read() for key, cam in self.cameras.items()}
        obs[STATE_KEY] = self.robot.read().astype(np.float32)
        obs["instruction"] = self.instruction
        return obs

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Torque on where the arm stands (the SO-101 has no home pose: an episode starts where it is)."""
        super().reset(seed=seed)
        if self.robot.held:
            raise ArmHeld(f"SO-101 {self.robot.calibration.arm_id!r} holds after: {self.robot.fault}",
                          self.robot.fault)
        self.robot.enable()
        self._steps = 0
        self._ticker.restart()
        return self.observe(), {"success": False}

    def step(self, action):
        a = np.asarray(action, dtype=float)
        if a.shape != (len(MOTORS),):
            raise ValueError(f"action must be the {len(MOTORS)} joint positions {list(JOINT_NAMES)}, got shape "
                             f"{a.shape}")
        if not np.all(np.isfinite(a)):
            self.robot.stop()
            raise SafetyError(f"refusing non-finite action {a}; the arm holds")
        sent = self.robot.command(a)
        if self.config.realtime:
            self._ticker.wait()
        self._steps += 1
        obs = self.observe()
        return obs, 0.0, False, self._steps >= self.config.max_steps, {"success": False, "command": sent}

    def close(self) -> None:
        for cam in self.cameras.values():
            cam.close()
