"""A gymnasium env over a Robot and its cameras, so the policy runners drive the arm like a simulator.

``step`` takes the dataset's 7-D action (end-effector position delta, Euler delta, gripper -1 open /
+1 close), integrates it onto the commanded tool pose, keeps that pose inside the safety layer's
workspace box, solves IK from the last joint command and sends the result through the safety layer,
then waits out the control period. Observations use the dataset's key names. The real arm cannot see
task success, so ``info["success"]`` comes from an optional ``success_fn(obs)`` (False without one).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from pivla import arm
from pivla.robot.robot import Camera, Robot, RobotState, Ticker
from pivla.robot.safety import SafetyError


@dataclass
class RobotEnvConfig:
    """Action scaling follows the twin (metres / radians per unit action); ``control_hz`` paces steps."""

    control_hz: float = float(arm.CONTROL_HZ)
    pos_scale: float = arm.TRANS_SCALE
    rot_scale: float = arm.ROT_SCALE
    max_steps: int = 300
    ik_iterations: int = arm.IK_ITERATIONS
    realtime: bool = True


def gripper_states(opening: float) -> np.ndarray:
    """Finger positions (2,) as the twin reports them: each finger's travel from closed."""
    return np.full(2, float(opening) * arm.GRIPPER_OPEN, dtype=np.float32)


class RobotEnv(gym.Env):
    metadata = {"render_modes": []}

    def __init__(self, robot: Robot, cameras: dict[str, Camera], instruction: str,
                 config: RobotEnvConfig | None = None, success_fn: Callable[[dict], bool] | None = None) -> None:
        self.robot = robot
        self.cameras = cameras
        self.instruction = instruction
        self.config = config or RobotEnvConfig()
        self.success_fn = success_fn
        self.action_space = gym.spaces.Box(-1.0, 1.0, (7,), np.float32)
        self._steps = 0
        self._target_pos = np.zeros(3)
        self._target_mat = np.eye(3)
        self._q_cmd = robot.home_q.copy()
        self._opening = 1.0
        self._ticker = Ticker(self.config.control_hz)

    @property
    def control_hz(self) -> float:
        return float(self.config.control_hz)

    def observe(self, state: RobotState | None = None) -> dict[str, Any]:
        st = state or self.robot.read()
        obs: dict[str, Any] = {key: cam.read() for key, cam in self.cameras.items()}
        obs.update(ee_pos=st.ee_pos.astype(np.float32), ee_ori=st.ee_ori.astype(np.float32),
                   gripper_states=gripper_states(st.opening), joint_states=st.q.astype(np.float32),
                   instruction=self.instruction)
        return obs

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        st = self.robot.home()
        self._q_cmd = st.q.copy()
        self._opening = st.opening
        self._target_pos, self._target_mat = self.robot.kinematics.fk_mat(np.clip(st.q, *arm.JOINT_LIMITS.T))
        self._steps = 0
        self._ticker.restart()
        return self.observe(st), {"success": False}

    def step(self, action):
        a = np.asarray(action, dtype=float)
        if a.shape != (7,):
            raise ValueError(f"action must have shape (7,), got {a.shape}")
        if not np.all(np.isfinite(a)):
            self.robot.stop()
            raise SafetyError(f"refusing non-finite action {a}; the arm was stopped")
        a = np.clip(a, -1.0, 1.0)
        cfg = self.config
        target_pos = self.robot.safety.clip_to_workspace(self._target_pos + a[:3] * cfg.pos_scale)
        target_mat = arm.euler_to_mat(a[3:6] * cfg.rot_scale) @ self._target_mat
        q = self._q_cmd
        for _ in range(cfg.ik_iterations):
            q = self.robot.kinematics.ik_step(q, target_pos, target_mat)
        q = np.clip(q, *self.robot.calibration.limits_rad.T)
        opening = float((1.0 - a[6]) / 2.0)
        self.robot.command(q, opening)
        self._q_cmd, self._opening = q, opening
        # Anchor the next delta on what the arm can reach, so unreachable targets do not wind up.
        self._target_pos, _ = self.robot.kinematics.fk_mat(q)
        self._target_mat = target_mat
        if cfg.realtime:
            self._ticker.wait()
        self._steps += 1
        obs = self.observe()
        success = bool(self.success_fn(obs)) if self.success_fn else False
        return obs, float(success), success, self._steps >= cfg.max_steps, {"success": success}

    def close(self) -> None:
        for cam in self.cameras.values():
            cam.close()
