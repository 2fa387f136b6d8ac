"""The SO-101 follower arm: six Feetech STS3215 servos on one bus, in LeRobot's units and calibration files.

Servo ids 1..6 are ``MOTORS`` in order. Positions are LeRobot's (its degree mode): the five body joints in
degrees from the middle of their calibrated range, ``(ticks - mid) * 360 / 4095``, the gripper 0..100 over
its range (``drive_mode`` 1 reverses it). The servos apply the calibration's homing offset themselves
(register 31), so the host only maps present positions with ``range_min`` / ``range_max``; a file that does
not match what the servos hold belongs to another arm and is refused at connect.

Every goal passes the same joint-space guard as the pivla arm (``pivla.robot.safety.JointGuard``: finite,
inside the calibrated limits, a bounded step from the previous goal; clipped or refused per
``SO101Config``) and is clamped to the calibrated tick range, so nothing out of range reaches the bus. A bus
fault (a servo silent, a bad checksum, garbage, the port gone) is named and trips the arm: it holds where
it is (goal := present position) or, if configured, releases torque, and refuses goals until ``resume()``.
A watchdog thread reads the positions whenever the bus has been quiet for ``watchdog_s``, so a dropped link
trips the arm even while nobody is commanding it.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal, Self

import numpy as np

from pivla.io import atomic_write_bytes
from pivla.robot import feetech as F
from pivla.robot.calibration import CalibrationError, read_calibration_json
from pivla.robot.safety import JointGuard, Violation

log = logging.getLogger(__name__)

MOTORS = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper")
MOTOR_IDS = {name: i for i, name in enumerate(MOTORS, 1)}
UNITS = ("deg",) * 5 + ("%",)
ROBOT_TYPE = "so101_follower"  # LeRobot's name for the arm, the folder of its calibration files
MAX_RES = F.STS3215_RESOLUTION - 1


@dataclass
class MotorCalibration:
    """One motor's entry of a LeRobot calibration file (ticks after the servo's homing offset)."""

    id: int
    drive_mode: int
    homing_offset: int
    range_min: int
    range_max: int


def default_calibration_path(arm_id: str) -> Path:
    """Where LeRobot keeps an SO-101 follower's calibration: ``$HF_LEROBOT_CALIBRATION/robots/so101_follower``
    (``so_follower`` in newer LeRobot releases, used when only that file exists)."""
    root = os.environ.get("HF_LEROBOT_CALIBRATION")
    if root is None:
        home = os.environ.get("HF_LEROBOT_HOME") or Path(os.environ.get("HF_HOME", "~/.cache/huggingface")) / "lerobot"
        root = Path(home).expanduser() / "calibration"
    path = Path(root) / "robots" / ROBOT_TYPE / f"{arm_id}.json"
    newer = Path(root) / "robots" / "so_follower" / f"{arm_id}.json"
    return newer if newer.exists() and not path.exists() else path


@dataclass
class SO101Calibration:
    """A LeRobot calibration file: ``{motor name: {"id", "drive_mode", "homing_offset", "range_min",
    "range_max"}}`` for the six motors, named ``<arm id>.json``."""

    arm_id: str
    motors: dict[str, MotorCalibration]

    def __post_init__(self) -> None:
        self.validate()

    @classmethod
    def full_range(cls, arm_id: str) -> SO101Calibration:
        """Every motor over its whole turn with no homing offset: what factory-fresh servos hold."""
        return cls(arm_id, {name: MotorCalibration(sid, 0, 0, 0, MAX_RES) for name, sid in MOTOR_IDS.items()})

    def validate(self) -> None:
        names = list(self.motors)
        if sorted(names) != sorted(MOTORS):
            missing = [m for m in MOTORS if m not in self.motors]
            unknown = [m for m in names if m not in MOTOR_IDS]
            raise CalibrationError(f"calibration of arm {self.arm_id!r} has {len(names)} motors (missing: "
                                   f"{', '.join(missing) or 'none'}; unknown: {', '.join(unknown) or 'none'}); "
                                   f"the SO-101 has {len(MOTORS)}: {', '.join(MOTORS)}")
        for name in MOTORS:
            m = self.motors[name]
            if m.id != MOTOR_IDS[name]:
                raise CalibrationError(f"calibration of arm {self.arm_id!r}: motor {name} has id {m.id}, "
                                       f"the SO-101's {name} is servo {MOTOR_IDS[name]}")
            if m.drive_mode not in (0, 1):
                raise CalibrationError(f"calibration of arm {self.arm_id!r}: motor {name} drive_mode must be 0 or 1, "
                                       f"got {m.drive_mode}")
            if not 0 <= m.range_min < m.range_max <= MAX_RES:
                raise CalibrationError(f"calibration of arm {self.arm_id!r}: motor {name} range "
                                       f"{m.range_min}..{m.range_max} must increase inside 0..{MAX_RES}")
            if abs(m.homing_offset) >= 1 << 11:
                raise CalibrationError(f"calibration of arm {self.arm_id!r}: motor {name} homing_offset "
                                       f"{m.homing_offset} does not fit the servo's 11 bits")

    @classmethod
    def load(cls, path: str | Path, arm_id: str | None = None) -> SO101Calibration:
        """Reads a LeRobot file; the arm id is the file's name, and a file of another arm is refused."""
        path = Path(path)
        if arm_id is not None and path.stem != arm_id:
            raise CalibrationError(f"{path} is the calibration of arm {path.stem!r}, not of arm {arm_id!r}")
        doc = read_calibration_json(path, "calibrate the arm with LeRobot's "
                                    f"lerobot-calibrate --robot.type={ROBOT_TYPE} --robot.id={path.stem}")
        if not isinstance(doc, dict):
            raise CalibrationError(f"{path}: expected an object keyed by motor name")
        try:
            motors = {name: MotorCalibration(**{k: int(v) for k, v in entry.items()}) for name, entry in doc.items()}
        except (TypeError, ValueError, AttributeError) as exc:
            raise CalibrationError(f"{path}: malformed motor entry ({exc})") from exc
        return cls(path.stem, motors)

    def save(self, path: str | Path) -> Path:
        """Writes LeRobot's layout atomically (motors in id order)."""
        path = Path(path)
        atomic_write_bytes(path, json.dumps({name: asdict(self.motors[name]) for name in MOTORS}, indent=4).encode())
        return path

    def _table(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        lo = np.array([self.motors[n].range_min for n in MOTORS], float)
        hi = np.array([self.motors[n].range_max for n in MOTORS], float)
        return lo, hi, np.array([self.motors[n].drive_mode for n in MOTORS])

    def limits(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper limits in arm units (degrees, gripper 0..100)."""
        lo, hi, _ = self._table()
        mid = (lo + hi) / 2
        lower, upper = (lo - mid) * 360 / MAX_RES, (hi - mid) * 360 / MAX_RES
        lower[-1], upper[-1] = 0.0, 100.0
        return lower, upper

    def to_units(self, ticks) -> np.ndarray:
        """Present positions (ticks, ``MOTORS`` order) -> degrees and gripper 0..100."""
        t = np.asarray(ticks, float)
        lo, hi, drive = self._table()
        out = (t - (lo + hi) / 2) * 360 / MAX_RES
        pct = (np.clip(t[-1], lo[-1], hi[-1]) - lo[-1]) / (hi[-1] - lo[-1]) * 100
        out[-1] = 100 - pct if drive[-1] else pct
        return out

    def to_ticks(self, values) -> np.ndarray:
        """Inverse of :meth:`to_units`, rounded and clamped to each motor's calibrated range."""
        v = np.asarray(values, float)
        lo, hi, drive = self._table()
        t = v * MAX_RES / 360 + (lo + hi) / 2
        pct = 100 - v[-1] if drive[-1] else v[-1]
        t[-1] = pct / 100 * (hi[-1] - lo[-1]) + lo[-1]
        return self.clamp(np.round(t))

    def clamp(self, ticks) -> np.ndarray:
        lo, hi, _ = self._table()
        return np.clip(np.asarray(ticks, float), lo, hi).astype(int)


@dataclass
class SO101Config:
    """How the arm guards its goals and what it does on a bus fault."""

    on_limit: Violation = "clip"
    """A goal outside the calibrated range: clip it to the range, or refuse it (SafetyError)."""
    on_step: Violation = "clip"
    """A goal further than the step bound from the previous one: clip the step, or refuse it."""
    max_step_deg: float = 10.0
    """Largest change of a body joint's goal in one command (degrees)."""
    max_gripper_step: float = 25.0
    """Largest change of the gripper's goal in one command (0..100 scale)."""
    watchdog_s: float = 0.1
    """Read the positions when the bus has been quiet this long, so a dropped link is noticed (0: off)."""
    on_fault: Literal["hold", "release"] = "hold"
    """After a fault: hold where the arm is (torque on), or release torque (the arm falls under gravity)."""
    verify_servos: bool = True
    """At connect, refuse a calibration file whose offsets and ranges differ from the servos' registers."""


class ArmHeld(RuntimeError):
    """The arm tripped on a bus fault and refuses goals until ``resume()``."""

    def __init__(self, message: str, fault: F.BusError) -> None:
        super().__init__(message)
        self.fault = fault


class SO101:
    """The arm on an open bus. ``open`` connects; ``enable`` turns torque on where the arm stands."""

    def __init__(self, bus: F.FeetechBus, calibration: SO101Calibration, config: SO101Config | None = None) -> None:
        self.bus, self.calibration = bus, calibration
        self.config = config or SO101Config()
        self.ids = [calibration.motors[n].id for n in MOTORS]
        bus.names.update({sid: name for sid, name in zip(self.ids, MOTORS)})
        lower, upper = calibration.limits()
        self.guard = JointGuard(MOTORS, lower, upper, UNITS, self.config.on_limit, self.config.on_step)
        self._step = np.array([self.config.max_step_deg] * 5 + [self.config.max_gripper_step])
        self.fault: F.BusError | None = None
        self._present: np.ndarray | None = None  # ticks, last good read
        self._goal: np.ndarray | None = None  # arm units, last goal sent
        self._stop = threading.Event()
        self._watchdog: threading.Thread | None = None
        self.connect()

    @classmethod
    def open(cls, bus: F.BusConfig, calibration: SO101Calibration, config: SO101Config | None = None) -> SO101:
        handle = F.FeetechBus(bus, dict(zip(MOTOR_IDS.values(), MOTORS)))
        try:
            return cls(handle, calibration, config)
        except BaseException:
            handle.close()
            raise

    def connect(self) -> None:
        """Pings the six servos, checks they are STS3215s holding this calibration, starts the watchdog."""
        for sid in self.ids:
            model = self.bus.ping(sid)
            if model != F.STS3215_MODEL:
                raise F.BusError(f"{self.bus.servo(sid)} is model {model}, not an STS3215 ({F.STS3215_MODEL})", sid)
        if self.config.verify_servos:
            self._verify()
        self.read()
        if self.config.watchdog_s > 0 and self._watchdog is None:
            self._watchdog = threading.Thread(target=self._watch, name="so101-watchdog", daemon=True)
            self._watchdog.start()

    def _verify(self) -> None:
        held = {reg.name: self.bus.sync_read(reg, self.ids)
                for reg in (F.HOMING_OFFSET, F.MIN_ANGLE_LIMIT, F.MAX_ANGLE_LIMIT)}
        wrong = []
        for name, sid in zip(MOTORS, self.ids):
            m = self.calibration.motors[name]
            servo = (held["homing_offset"][sid], held["min_angle_limit"][sid], held["max_angle_limit"][sid])
            if servo != (m.homing_offset, m.range_min, m.range_max):
                wrong.append(f"{name} (servo: offset {servo[0]}, range {servo[1]}..{servo[2]}; file: offset "
                             f"{m.homing_offset}, range {m.range_min}..{m.range_max})")
        if wrong:
            raise CalibrationError(f"calibration of arm {self.calibration.arm_id!r} does not match the servos on "
                                   f"{self.bus.config.port}: {'; '.join(wrong)}. The file is another arm's, or the "
                                   f"servos were calibrated since")

    # --- state -----------------------------------------------------------------------------------
    def read_ticks(self) -> np.ndarray:
        """Present positions in ticks (``MOTORS`` order), in one sync read; a failure trips the arm."""
        with self.bus.lock:
            try:
                got = self.bus.sync_read(F.PRESENT_POSITION, self.ids)
            except F.BusError as exc:
                self._trip(exc)
                raise
            self._present = np.array([got[sid] for sid in self.ids], float)
            return self._present.copy()

    def read(self) -> np.ndarray:
        """Joint positions: body joints in degrees, gripper 0..100."""
        return self.calibration.to_units(self.read_ticks())

    def observation(self) -> dict[str, float]:
        """The positions under LeRobot's keys (``shoulder_pan.pos`` ...)."""
        return {f"{name}.pos": float(v) for name, v in zip(MOTORS, self.read())}

    @property
    def held(self) -> bool:
        return self.fault is not None

    # --- motion ----------------------------------------------------------------------------------
    def enable(self) -> None:
        """Torque on where the arm stands (its goal first set to its present position, so nothing jumps)."""
        with self.bus.lock:
            ticks = self.calibration.clamp(self.read_ticks())
            self._send(ticks)
            self.bus.torque(self.ids, True)
            self._goal = self.calibration.to_units(ticks)

    def disable(self) -> None:
        """Torque off: the arm can be moved by hand (and falls under gravity)."""
        self.bus.torque(self.ids, False)

    def command(self, goal) -> np.ndarray:
        """Checks and sends one goal (``MOTORS`` order, arm units); returns the goal as sent."""
        with self.bus.lock:
            if self.fault is not None:
                raise ArmHeld(f"SO-101 {self.calibration.arm_id!r} is "
                              f"{'released' if self.config.on_fault == 'release' else 'held'} after: {self.fault}; "
                              f"call resume() once the bus answers", self.fault)
            start = self._goal if self._goal is not None else self.read()
            safe = self.guard.step(self.guard.limits(goal), start, self._step)
            safe = np.clip(safe, self.guard.lower, self.guard.upper)  # a start outside the range stays clipped
            self._send(self.calibration.to_ticks(safe))
            self._goal = safe
            return safe

    def _send(self, ticks: np.ndarray) -> None:
        try:
            self.bus.sync_write(F.GOAL_POSITION, dict(zip(self.ids, (int(t) for t in ticks))))
        except F.BusError as exc:
            self._trip(exc)
            raise

    def _trip(self, fault: F.BusError) -> None:
        """Names the fault and holds (goal := present position, for the servos that still listen) or releases."""
        with self.bus.lock:
            if self.fault is not None:
                return
            self.fault = fault
            action = self.config.on_fault
            log.error("SO-101 %r: %s; %s", self.calibration.arm_id, fault,
                      "releasing torque" if action == "release" else "holding")
            try:
                if action == "release":
                    self.bus.torque(self.ids, False)
                elif self._present is not None:
                    ticks = self._present.copy()
                    for i, sid in enumerate(self.ids):
                        ticks[i] = fault.partial.get(sid, ticks[i])
                    self.bus.sync_write(F.GOAL_POSITION, dict(zip(self.ids, map(int, self.calibration.clamp(ticks)))))
            except F.BusError as exc:
                log.error("SO-101 %r: could not %s the arm (%s)", self.calibration.arm_id, action, exc)

    def stop(self) -> None:
        """Holds the arm where it stands (goal := present position); never raises: a bus that fails here trips the
        arm, which then holds or releases as configured."""
        with self.bus.lock:
            if self.fault is not None:
                return
            try:
                ticks = self.calibration.clamp(self.read_ticks())
                self._send(ticks)
                self._goal = self.calibration.to_units(ticks)
            except F.BusError:
                pass  # read_ticks / _send tripped the arm and logged the fault

    def resume(self) -> None:
        """Clears a fault once the six servos answer again, and re-enables torque where the arm stands."""
        with self.bus.lock:
            self.bus.sync_read(F.PRESENT_POSITION, self.ids)
            self.fault = None
            self.enable()

    def _watch(self) -> None:
        period = self.config.watchdog_s
        while not self._stop.wait(period / 2):
            if self.fault is None and time.monotonic() - self.bus.last_reply >= period:
                try:
                    self.read_ticks()
                except F.BusError:
                    pass  # read_ticks tripped the arm and logged the fault

    def close(self) -> None:
        """Stops the watchdog and closes the bus; torque stays as it is."""
        self._stop.set()
        if self._watchdog is not None:
            self._watchdog.join(2)
        self.bus.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def check(bus: F.BusConfig, calibration: SO101Calibration | None = None) -> list[dict]:
    """What ``pivla robot check --robot so101`` prints: per motor its id, model and present position in ticks,
    and with a calibration in arm units. Reads only; torque is left as it is."""
    if calibration is None:
        with F.FeetechBus(bus, dict(zip(MOTOR_IDS.values(), MOTORS))) as handle:
            models = {sid: handle.ping(sid) for sid in MOTOR_IDS.values()}
            ticks = handle.sync_read(F.PRESENT_POSITION, MOTOR_IDS.values())
        return [{"motor": name, "id": sid, "model": models[sid], "ticks": ticks[sid]}
                for name, sid in MOTOR_IDS.items()]
    with SO101.open(bus, calibration, SO101Config(watchdog_s=0.0)) as arm:
        ticks = arm.read_ticks()
    values = calibration.to_units(ticks)
    return [{"motor": name, "id": sid, "model": F.STS3215_MODEL, "ticks": int(t), "position": round(float(v), 2),
             "unit": unit} for (name, sid), t, v, unit in zip(MOTOR_IDS.items(), ticks, values, UNITS)]

