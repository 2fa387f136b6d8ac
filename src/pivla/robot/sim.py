"""The simulated twin behind the same Robot and Camera interfaces as the real arm (``--sim``).

``SimRobot`` drives the twin's joints the way the firmware drives the servos: a joint target is accepted
only after the safety layer, then the commanded angles move towards it at the commanded speed, one
control period (0.1 s of simulated time) per interaction, through the twin's hobby-servo model
(deadband, backlash, noise). Like the board, ``read`` reports the *commanded* angles; the physical
tool position, which a real maker would measure externally, is ``measured_ee_pos``. Simulated time is
advanced by the host's calls (commands and polls), so loops run faster than real time.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from pivla import arm  # noqa: E402
from pivla.envs.tabletop import env as twin  # noqa: E402
from pivla.envs.tabletop import make_env  # noqa: E402
from pivla.robot.calibration import ArmCalibration  # noqa: E402
from pivla.robot.robot import Camera, Robot, RobotState  # noqa: E402
from pivla.robot.safety import CheckedCommand, SafetyConfig, SafetyLayer  # noqa: E402

TWIN_CAMERAS = {"agentview_rgb": "agentview", "eye_in_hand_rgb": "eye_in_hand"}


class SimRobot(Robot):
    def __init__(self, suite: str = "pick_place", task: int | str = 0, seed: int = 0, realism: str = "servo",
                 calibration: ArmCalibration | None = None, safety: SafetyConfig | None = None,
                 env_kwargs: dict | None = None) -> None:
        calibration = calibration or ArmCalibration.nominal("twin")
        super().__init__(calibration, SafetyLayer(calibration, safety))
        self.env = make_env(suite, task, seed=seed, realism=realism, render=False, **(env_kwargs or {}))
        m = self.env.model
        self._arm_act = np.array([m.actuator(n).id for n in arm.JOINT_NAMES])
        self._finger_act = np.array([m.actuator(n).id for n in arm.GRIPPER_JOINTS])
        self._ee_site = m.site(arm.EE_SITE).id
        self.dt = 1.0 / twin.CONTROL_HZ
        self.sim_time = 0.0
        self.reset_scene(seed)

    def reset_scene(self, seed: int | None = None) -> dict:
        """New layout of the task (the twin's automatic reset); the arm starts at the env's start pose."""
        _, info = self.env.reset(seed=seed)
        self.q = self.env.q_cmd.copy()
        self.target_q = self.q.copy()
        self.opening = self.target_opening = 1.0
        self.speed = 1.0
        self.stopped = False
        self.last_command = None
        return info

    def tick(self) -> None:
        """One control period: commanded angles step towards the target, then physics runs."""
        step = self.speed * self.dt
        self.q = self.q + np.clip(self.target_q - self.q, -step, step)
        self.opening = self.target_opening
        self.env.q_cmd = self.q.copy()
        d = self.env.data
        d.ctrl[self._arm_act] = self.env.servo.command(self.q) if self.env.servo is not None else self.q
        d.ctrl[self._finger_act] = arm.GRIPPER_OPEN * self.opening
        mujoco.mj_step(self.env.model, d, nstep=twin.SUBSTEPS)
        self.sim_time += self.dt

    def _moving(self) -> bool:
        return bool(np.max(np.abs(self.target_q - self.q)) > 1e-6)

    def read(self) -> RobotState:
        if self._moving():
            self.tick()
        return self._state(self.q, self.opening, self._moving())

    def _send(self, cmd: CheckedCommand) -> None:
        if self.stopped:
            raise RuntimeError("simulated arm is e-stopped; call resume()")
        self.target_q = cmd.q.copy()
        self.target_opening = cmd.opening
        self.speed = cmd.speed_us_s / min(j.us_per_rad for j in self.calibration.joints)
        self.tick()

    def wait(self, periods: int = 1) -> None:
        """Lets simulated time pass (e.g. for the gripper to close)."""
        for _ in range(periods):
            self.tick()

    def measured_ee_pos(self) -> np.ndarray:
        """Where the tool centre physically is (the twin's truth, for repeatability)."""
        return self.env.data.site_xpos[self._ee_site].copy()

    def evaluate(self) -> bool:
        """The twin's success judgement: one idle control step through the env with the gripper open."""
        _, _, _, _, info = self.env.step(np.array([0, 0, 0, 0, 0, 0, 1.0 - 2.0 * self.opening]))
        return bool(info["success"])

    def stop(self) -> None:
        self.target_q = self.q.copy()
        self.stopped = True

    def resume(self) -> None:
        self.stopped = False
        self.last_command = None

    def close(self) -> None:
        self.env.close()


class SimCamera(Camera):
    """Renders one of the twin's cameras at ``size`` px (independent of the env's own image size)."""

    def __init__(self, robot: SimRobot, key: str = "agentview_rgb", size: int = 128) -> None:
        if key not in TWIN_CAMERAS:
            raise ValueError(f"unknown twin camera {key!r}; choose from {sorted(TWIN_CAMERAS)}")
        self.robot, self.size = robot, size
        self.cam_id = robot.env.model.camera(TWIN_CAMERAS[key]).id
        self._renderer = mujoco.Renderer(robot.env.model, size, size)

    def read(self) -> np.ndarray:
        self._renderer.update_scene(self.robot.env.data, self.cam_id)
        return self._renderer.render().copy()

    def intrinsics(self) -> np.ndarray:
        """Pinhole matrix from the camera's field of view (what a datasheet/checkerboard would give)."""
        fovy = np.deg2rad(self.robot.env.model.cam_fovy[self.cam_id])
        f = 0.5 * self.size / np.tan(fovy / 2)
        return np.array([[f, 0, self.size / 2], [0, f, self.size / 2], [0, 0, 1.0]])

    def close(self) -> None:
        self._renderer.close()
