"""Calibrating an arm (``pivla robot calibrate``), guided from a key source.

- **The pivla arm**: start from the nominal calibration (or the existing file), optionally jog each joint to
  the model's zero (``jog_zero_offsets``), program the calibrated limits and home pose into the board and read
  them back, then write the file.
- **The SO-101**, LeRobot's procedure on the bus: torque off, every servo's calibration registers reset; the
  arm is moved by hand to the middle of its range (Enter), which becomes each servo's homing offset (the
  present position then reads 2047, the middle of a turn); then every joint but ``wrist_roll`` is moved
  through its whole range while the positions are read (Enter ends it), whose extremes become the range
  (``wrist_roll`` keeps the whole turn). Offsets and ranges are written to the servos (EEPROM) and to
  LeRobot's calibration file ``<arm id>.json``, which ``lerobot`` reads as its own.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

import numpy as np

from pivla.robot.calibration import ArmCalibration, CalibrationError

SO101_FULL_TURN = ("wrist_roll",)  # joints that turn all the way round: their range is the whole turn


def jog_zero_offsets(board, calib: ArmCalibration, keys: Iterable[str], say: Callable[[str], None] = print):
    """Interactive: for each joint, jog the servo until the joint is at the model's zero, then Enter.

    Keys: '+'/'-' 10 us, ']'/'[' 50 us, 'r' reverse direction, Enter accept, 's' skip. Moves stay inside
    the board's current limits (the firmware refuses anything else).
    """
    from pivla import arm

    keys = iter(keys)
    st = board.state()
    pulses = list(st.targets_us)
    steps = {"+": 10, "-": -10, "]": 50, "[": -50}
    for ch, name in enumerate(arm.JOINT_NAMES):
        say(f"joint {name}: jog to its zero (arm straight up), Enter to accept, s to skip")
        for key in keys:
            if key in steps:
                lim = board.limits(ch)
                pulses[ch] = min(max(pulses[ch] + steps[key], lim.min_us), lim.max_us)
                board.set_targets(pulses, 300)
            elif key == "r":
                calib.joints[ch].direction *= -1
                say(f"  direction now {calib.joints[ch].direction:+d}")
            elif key in ("enter", "\r", "\n"):
                calib.joints[ch].zero_us = float(pulses[ch])
                say(f"  zero_us = {pulses[ch]}")
                break
            elif key == "s":
                break
            board.state()  # keeps the watchdog fed while the user thinks
    calib.validate()
    return calib


def calibrate_pivla_arm(path: str | Path, board=None, jog: bool = False, keys: Iterable[str] = (),
                        say: Callable[[str], None] = print) -> Path:
    """Writes the pivla arm's calibration to ``path`` (see the module doc); ``board`` None: the twin's nominal
    calibration, nothing programmed. The board is closed at the end."""
    from pivla.robot.robot import SerialRobot
    from pivla.robot.safety import SafetyLayer

    path = Path(path)
    calib = ArmCalibration.load(path) if path.exists() else ArmCalibration.nominal(path.stem)
    if board is None:
        calib.save(path)
        say(f"wrote {path} (the twin uses the nominal calibration)")
        return path
    try:
        if jog:
            calib = jog_zero_offsets(board, calib, keys, say)
        robot = SerialRobot(board, calib, SafetyLayer(calib), program_limits=True)
        limits = calib.board_limits(robot.home_q)
        for lim in limits:
            got = board.limits(lim.channel)
            if got != lim:
                raise CalibrationError(f"channel {lim.channel}: board kept {got}, expected {lim}")
        calib.save(path)
    finally:
        board.close()
    say(f"wrote {path}; board limits programmed: "
        + ", ".join(f"ch{lim.channel} {lim.min_us}-{lim.max_us} (home {lim.home_us})" for lim in limits))
    return path


def _until_enter(keys: Iterator[str], tick: Callable[[], None] | None = None) -> None:
    from pivla.robot.keyboard import Event, event

    for key in keys:
        if key in ("enter", "\r", "\n"):
            return
        if event(key) is Event.STOP:
            raise KeyboardInterrupt("calibration stopped; nothing was written")
        if tick is not None:
            tick()
    raise KeyboardInterrupt("the keys ended before the calibration did; nothing was written")


def calibrate_so101(bus, arm_id: str, keys: Iterable[str], path: str | Path | None = None,
                    say: Callable[[str], None] = print):
    """LeRobot's SO-101 calibration on an open ``pivla.robot.feetech.FeetechBus`` (see the module doc); returns
    the calibration, written to ``path`` (default: LeRobot's folder) and to the servos."""
    from pivla.robot import feetech as F
    from pivla.robot import so101

    if path is not None and Path(path).stem != arm_id:
        raise CalibrationError(f"LeRobot names an arm's calibration file by its id: {arm_id}.json, not "
                               f"{Path(path).name}")
    keys = iter(keys)
    ids = [so101.MOTOR_IDS[m] for m in so101.MOTORS]
    bus.names.update({sid: m for m, sid in so101.MOTOR_IDS.items()})
    for sid in ids:
        model = bus.ping(sid)
        if model != F.STS3215_MODEL:
            raise F.BusError(f"{bus.servo(sid)} is model {model}, not an STS3215 ({F.STS3215_MODEL})", sid)
    bus.torque(ids, False)
    for sid in ids:  # unlock the EEPROM, position mode, no calibration: raw positions over the whole turn
        bus.write(sid, F.LOCK, 0)
        bus.write(sid, F.MODE, 0)
        bus.write(sid, F.HOMING_OFFSET, 0)
        bus.write(sid, F.MIN_ANGLE_LIMIT, 0)
        bus.write(sid, F.MAX_ANGLE_LIMIT, so101.MAX_RES)
    say(f"SO-101 {arm_id!r}: torque is off. Move the arm by hand to the middle of its range of motion, then "
        "press Enter")
    _until_enter(keys)
    half = so101.MAX_RES // 2
    present = bus.sync_read(F.PRESENT_POSITION, ids)
    offsets = {sid: present[sid] - half for sid in ids}
    for sid in ids:
        bus.write(sid, F.HOMING_OFFSET, offsets[sid])
    say(f"move every joint but {', '.join(SO101_FULL_TURN)} through its whole range of motion, one after the "
        "other; press Enter when done")
    lo = {sid: np.inf for sid in ids}
    hi = {sid: -np.inf for sid in ids}

    def read() -> None:
        got = bus.sync_read(F.PRESENT_POSITION, ids)
        for sid, value in got.items():
            lo[sid], hi[sid] = min(lo[sid], value), max(hi[sid], value)

    read()
    _until_enter(keys, read)
    read()
    motors = {}
    for name in so101.MOTORS:
        sid = so101.MOTOR_IDS[name]
        if name in SO101_FULL_TURN:
            rmin, rmax = 0, so101.MAX_RES
        else:
            rmin, rmax = int(lo[sid]), int(hi[sid])
            if rmin >= rmax:
                raise CalibrationError(f"SO-101 {arm_id!r}: {name} did not move ({rmin} ticks throughout); move "
                                       "every joint through its range while the positions are read")
        motors[name] = so101.MotorCalibration(sid, 0, int(offsets[sid]), rmin, rmax)
    calib = so101.SO101Calibration(arm_id, motors)
    for m in motors.values():
        bus.write(m.id, F.MIN_ANGLE_LIMIT, m.range_min)
        bus.write(m.id, F.MAX_ANGLE_LIMIT, m.range_max)
        bus.write(m.id, F.LOCK, 1)
    out = calib.save(Path(path) if path else so101.default_calibration_path(arm_id))
    say(f"wrote {out}: " + ", ".join(f"{n} {m.range_min}..{m.range_max} (offset {m.homing_offset})"
                                     for n, m in motors.items()))
    return calib, out
