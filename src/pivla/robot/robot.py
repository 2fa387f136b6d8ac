"""The Robot and Camera interfaces shared by the real arm (serial board) and the simulated twin.

Everything above this layer (teleop, recording, the policy loop, repeatability, automated collection)
talks to a ``Robot`` in joint space plus gripper opening, and to ``Camera`` objects returning RGB
frames; which arm is underneath is a constructor choice. Every motion goes through ``command`` or
``move_to``, which run the safety layer first: a refused command never reaches the hardware.
"""

from __future__ import annotations

import abc
import logging
import time
from dataclasses import dataclass

import cv2
import numpy as np

from pivla import arm
from pivla.robot.calibration import ArmCalibration
from pivla.robot.link import Board, BoardError, LinkLost
from pivla.robot.safety import CheckedCommand, SafetyLayer

log = logging.getLogger(__name__)


class Ticker:
    """Paces a control loop on the wall clock at ``hz``: ``wait`` sleeps until the next tick; a step that ran
    late restarts the schedule from now instead of bursting to catch up."""

    def __init__(self, hz: float) -> None:
        self.period = 1.0 / hz
        self._next = time.monotonic()

    def restart(self) -> None:
        self._next = time.monotonic()

    def wait(self) -> None:
        self._next += self.period
        delay = self._next - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        else:
            self._next = time.monotonic()

@dataclass(frozen=True)
class RobotState:
    q: np.ndarray  # (6,) rad, arm.JOINT_NAMES order
    opening: float  # gripper: 1 open .. 0 closed
    ee_pos: np.ndarray  # (3,) m, base frame
    ee_ori: np.ndarray  # (3,) Euler rad, arm.euler_to_mat convention
    moving: bool


class Robot(abc.ABC):
    """A 6-DOF arm with a gripper. Subclasses implement ``read``, ``_send``, ``stop`` and ``close``."""

    def __init__(self, calibration: ArmCalibration, safety: SafetyLayer, home_q: np.ndarray | None = None) -> None:
        self.calibration = calibration
        self.safety = safety
        self.home_q = np.asarray(arm.home_q() if home_q is None else home_q, dtype=float)
        self.kinematics = arm.Kinematics()
        self.last_command: CheckedCommand | None = None

    def _state(self, q: np.ndarray, opening: float, moving: bool) -> RobotState:
        pos, ori = self.kinematics.forward_kinematics(np.clip(q, *arm.JOINT_LIMITS.T))
        return RobotState(np.asarray(q, float), float(opening), pos, ori, moving)

    @abc.abstractmethod
    def read(self) -> RobotState:
        """The arm's current joint angles (what the servos are commanded to right now)."""

    @abc.abstractmethod
    def _send(self, cmd: CheckedCommand) -> None:
        """Delivers an already checked command."""

    @abc.abstractmethod
    def stop(self) -> None:
        """Holds the arm where it is (emergency stop); must not raise."""

    @abc.abstractmethod
    def close(self) -> None: ...

    def command(self, q: np.ndarray, opening: float, max_step_rad: float | None = ...) -> CheckedCommand:
        """Checks and sends one joint target (streaming: the step from the last command is bounded)."""
        q_now = self.last_command.q if self.last_command is not None else self.read().q
        cmd = self.safety.check(q, opening, q_now, max_step_rad)
        self._send(cmd)
        self.last_command = cmd
        return cmd

    def move_to(self, q: np.ndarray, opening: float, timeout_s: float = 15.0, settle_s: float = 0.0) -> RobotState:
        """Point-to-point move, executed at the firmware's rate limit; blocks until the arm is still."""
        self.command(q, opening, max_step_rad=None)
        deadline = time.monotonic() + timeout_s
        while True:
            time.sleep(0.02)
            st = self.read()
            if not st.moving:
                break
            if time.monotonic() > deadline:
                self.stop()
                raise TimeoutError(f"arm did not reach its target within {timeout_s:.1f} s; stopped")
        if settle_s:
            time.sleep(settle_s)
        return self.read()

    def home(self, timeout_s: float = 15.0) -> RobotState:
        return self.move_to(self.home_q, 1.0, timeout_s)

    def __enter__(self) -> Robot:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class SerialRobot(Robot):
    """The real arm behind the pivla firmware. On a lost link the arm is stopped and ``LinkLost`` raised."""

    def __init__(self, board: Board, calibration: ArmCalibration, safety: SafetyLayer,
                 home_q: np.ndarray | None = None, program_limits: bool = True) -> None:
        super().__init__(calibration, safety, home_q)
        self.board = board
        self.info = board.ping()
        if program_limits:
            self.program_limits()
        self._last_state = board.state()

    def program_limits(self) -> None:
        """Copies the calibrated limits and home pose into the firmware (both ends enforce them)."""
        for lim in self.calibration.board_limits(self.home_q):
            if self.board.limits(lim.channel) == lim:
                continue
            try:
                self.board.set_limits(lim)
            except BoardError as exc:
                raise RuntimeError(f"channel {lim.channel}: cannot program limits {lim.min_us}..{lim.max_us} us "
                                   f"({exc}); if the servo sits outside that range, jog it inside with "
                                   f"`pivla robot calibrate` first") from exc

    def read(self) -> RobotState:
        st = self._guard(self.board.state)
        self._last_state = st
        q, opening = self.calibration.from_pulses(st.pulses_us)
        return self._state(q, opening, st.moving)

    def _send(self, cmd: CheckedCommand) -> None:
        pulses = self.calibration.to_pulses(cmd.q, cmd.opening)
        self._last_state = self._guard(self.board.set_targets, pulses, cmd.speed_us_s)

    def _guard(self, fn, *args):
        try:
            return fn(*args)
        except LinkLost:
            log.error("serial link lost: stopping the arm")
            self.stop()
            raise

    def stop(self) -> None:
        try:
            if self.board.link.alive:
                self.board.estop()
        except (LinkLost, BoardError) as exc:
            log.error("could not send e-stop (%s); the firmware watchdog holds the arm", exc)

    def resume(self) -> None:
        self.board.clear_estop()
        self.last_command = None

    def close(self) -> None:
        self.board.close()


class Camera(abc.ABC):
    @abc.abstractmethod
    def read(self) -> np.ndarray:
        """One RGB frame, (H, W, 3) uint8."""

    def close(self) -> None:
        return None


def square_resize(frame: np.ndarray, size: int) -> np.ndarray:
    """Centre-crops to a square and resizes (the dataset's images are square)."""
    h, w = frame.shape[:2]
    s = min(h, w)
    y, x = (h - s) // 2, (w - s) // 2
    return cv2.resize(frame[y : y + s, x : x + s], (size, size), interpolation=cv2.INTER_AREA)


class OpenCVCamera(Camera):
    """A USB camera through OpenCV; frames are centre-cropped and resized to ``size`` x ``size`` RGB (``size``
    None: the camera's own frames, as LeRobot records them)."""

    def __init__(self, device: int | str = 0, size: int | None = 128) -> None:
        self.device, self.size = device, size
        self._cap = cv2.VideoCapture(device)
        if not self._cap.isOpened():
            raise RuntimeError(f"cannot open camera {device!r}")

    def read(self) -> np.ndarray:
        ok, frame = self._cap.read()
        if not ok or frame is None:
            raise RuntimeError(f"camera {self.device!r} returned no frame")
        rgb = cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)
        return rgb if self.size is None else square_resize(rgb, self.size)

    def close(self) -> None:
        self._cap.release()
