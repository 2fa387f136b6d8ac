"""Which arm and which cameras: the pivla arm on its serial board, its simulated twin, or an SO-101 on its servo
bus, opened from the few settings a command line gives, and an env over them for the loops above.

``open_rig`` is what every ``pivla robot`` command that moves an arm starts with: the arm (``kind``
``"pivla-arm"`` or ``"so101"``), its cameras under the keys its datasets use (the pivla arm:
``agentview_rgb`` and ``eye_in_hand_rgb``; the SO-101: LeRobot's ``front`` and ``wrist``) and the env that
turns actions into checked commands (``pivla.robot.env.RobotEnv``: 7-D end-effector deltas;
``pivla.robot.so101_env.SO101Env``: six absolute joint positions). Closing the rig closes all three.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from pivla.robot.robot import Camera, OpenCVCamera

ArmKind = Literal["pivla-arm", "so101"]
ARM_KINDS = ("pivla-arm", "so101")
PIVLA_CAMERAS = ("agentview_rgb", "eye_in_hand_rgb")  # the main camera first, then the wrist's
SO101_CAMERAS = ("front", "wrist")  # LeRobot's SO-101 datasets
PIVLA_IMAGE_SIZE = 80  # the policy's picture side on the pivla arm
SO101_FPS = 30  # LeRobot's recording rate for the SO-101


class ArmError(ValueError):
    """The arm cannot be opened as asked (a missing port, an impossible combination); the message says what to
    give instead."""


def camera_keys(kind: ArmKind) -> tuple[str, str]:
    """The dataset keys of an arm's (main, wrist) cameras."""
    return SO101_CAMERAS if kind == "so101" else PIVLA_CAMERAS


def _device(spec: str | int) -> int | str:
    return int(spec) if str(spec).isdigit() else str(spec)


def so101_calibration(calibration: str | None, arm_id: str | None):
    """An SO-101's LeRobot calibration: the file given, else ``<arm id>.json`` in LeRobot's folder."""
    from pivla.robot import so101

    if calibration is None and arm_id is None:
        raise ArmError("the SO-101 needs its calibration: give --arm-id ID (LeRobot's calibration folder) or "
                       "--calibration FILE (make one with `pivla robot calibrate --robot so101`)")
    path = Path(calibration) if calibration else so101.default_calibration_path(arm_id)
    return so101.SO101Calibration.load(path, arm_id)


def open_robot(kind: ArmKind = "pivla-arm", *, port: str | None = None, sim: bool = False,
               calibration: str | None = None, arm_id: str | None = None, suite: str = "pick_place",
               task: str | int = "0", seed: int = 0, so101_config: Any = None):
    """The pivla arm (``SerialRobot`` on ``port``, or the twin's ``SimRobot`` with ``sim``) or an SO-101
    (``pivla.robot.so101.SO101`` on ``port``, its calibration from ``calibration`` or ``arm_id``)."""
    if kind not in ARM_KINDS:
        raise ArmError(f"unknown arm {kind!r}; choose one of {', '.join(ARM_KINDS)}")
    if kind == "so101":
        if sim:
            raise ArmError("--sim drives the pivla arm's twin; for an SO-101 without an arm, serve a simulated "
                           "bus with `pivla robot simbus` and give its --port")
        if not port:
            raise ArmError("give --port PORT of the SO-101's servo bus (`pivla robot find-port` finds it)")
        from pivla.robot.feetech import BusConfig
        from pivla.robot.so101 import SO101

        return SO101.open(BusConfig(port), so101_calibration(calibration, arm_id), so101_config)
    if sim:
        from pivla.robot.sim import SimRobot

        return SimRobot(suite, int(task) if str(task).isdigit() else task, seed=seed)
    if not port:
        raise ArmError("give --port PORT for the serial arm, or --sim for the twin")
    from pivla.robot.calibration import ArmCalibration
    from pivla.robot.link import Board
    from pivla.robot.robot import SerialRobot
    from pivla.robot.safety import SafetyLayer

    calib = ArmCalibration.load(calibration or "arm_calibration.json")
    board = Board.open(port)
    try:
        return SerialRobot(board, calib, SafetyLayer(calib))
    except BaseException:
        board.close()
        raise


def open_cameras(robot: Any, kind: ArmKind = "pivla-arm", *, sim: bool = False, camera: str | None = "0",
                 wrist_camera: str | None = None, image_size: int | None = None) -> dict[str, Camera]:
    """The arm's cameras under its dataset keys: the twin's two rendered ones with ``sim``, else OpenCV devices
    (``camera``: the main one, None for none; ``wrist_camera``: optional). ``image_size``: square pictures of
    that side (default: 80 px on the pivla arm, the camera's own frame on the SO-101)."""
    main, wrist = camera_keys(kind)
    size = image_size if image_size is not None else (None if kind == "so101" else PIVLA_IMAGE_SIZE)
    if sim:
        from pivla.robot.sim import SimCamera

        return {k: SimCamera(robot, k, size or PIVLA_IMAGE_SIZE) for k in PIVLA_CAMERAS}
    out: dict[str, Camera] = {}
    try:
        if camera is not None and str(camera) != "":
            out[main] = OpenCVCamera(_device(camera), size)
        if wrist_camera is not None:
            out[wrist] = OpenCVCamera(_device(wrist_camera), size)
    except BaseException:
        for cam in out.values():
            cam.close()
        raise
    return out


def open_env(robot: Any, cameras: dict[str, Camera], instruction: str, *, realtime: bool = True,
             max_steps: int = 300, fps: float | None = None):
    """The env over ``robot``: ``SO101Env`` (joint positions, ``fps`` default 30) for an SO-101, ``RobotEnv``
    (end-effector deltas at the arm's control rate unless ``fps``) for the pivla arm or its twin."""
    from pivla.robot.so101 import SO101

    if isinstance(robot, SO101):
        from pivla.robot.so101_env import SO101Env, SO101EnvConfig

        return SO101Env(robot, cameras, instruction,
                        SO101EnvConfig(fps=fps or SO101_FPS, realtime=realtime, max_steps=max_steps))
    from pivla.robot.env import RobotEnv, RobotEnvConfig

    cfg = RobotEnvConfig(realtime=realtime, max_steps=max_steps)
    if fps:
        cfg.control_hz = float(fps)
    return RobotEnv(robot, cameras, instruction, cfg)


@dataclass
class Rig:
    """An opened arm, its cameras and the env over them; ``close`` (or leaving ``with``) stops the arm and closes
    all three, whatever happened."""

    kind: ArmKind
    robot: Any
    cameras: dict[str, Camera] = field(default_factory=dict)
    env: Any = None
    sim: bool = False

    def close(self) -> None:
        try:
            stop_arm(self.robot)
        finally:
            if self.env is not None:
                self.env.close()  # closes the cameras
            else:
                for cam in self.cameras.values():
                    cam.close()
            self.robot.close()

    def __enter__(self) -> Rig:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def stop_arm(robot: Any) -> None:
    """Holds the arm where it is (never raises)."""
    stop = getattr(robot, "stop", None)
    if stop is not None:
        stop()


def open_rig(kind: ArmKind = "pivla-arm", *, port: str | None = None, sim: bool = False,
             calibration: str | None = None, arm_id: str | None = None, suite: str = "pick_place",
             task: str | int = "0", seed: int = 0, cameras: bool = True, camera: str | None = "0",
             wrist_camera: str | None = None, image_size: int | None = None, instruction: str = "",
             max_steps: int = 300, fps: float | None = None, realtime: bool | None = None,
             so101_config: Any = None) -> Rig:
    """The arm, its cameras (none unless ``cameras``) and its env, as one closable rig (see the module doc).
    ``realtime`` paces the env's steps (default: on a real arm, not on the twin)."""
    robot = open_robot(kind, port=port, sim=sim, calibration=calibration, arm_id=arm_id, suite=suite, task=task,
                       seed=seed, so101_config=so101_config)
    rig = Rig(kind, robot, sim=sim)
    try:
        if cameras:
            rig.cameras = open_cameras(robot, kind, sim=sim, camera=camera, wrist_camera=wrist_camera,
                                       image_size=image_size)
        rig.env = open_env(robot, rig.cameras, instruction, realtime=not sim if realtime is None else realtime,
                           max_steps=max_steps, fps=fps)
    except BaseException:
        rig.close()
        raise
    return rig
