"""Per-arm calibration: how joint angles map to servo pulses, and the limits the arm may use.

A hobby servo's pulse is linear in its angle, but every arm differs in how each horn was mounted (the
pulse at the model's zero angle), which way the servo turns (direction), and its gain (microseconds per
radian, nominally 2000 us / pi for a 180-degree servo). The file is JSON::

    {"version": 1, "name": "my-arm",
     "joints": [{"name": "base_yaw", "zero_us": 1500, "direction": 1, "us_per_rad": 636.6,
                 "min_rad": -1.4, "max_rad": 1.4}, ...six joints in arm.JOINT_NAMES order],
     "gripper": {"open_us": 1200, "closed_us": 1800}}

Joint limits are in radians of the kinematic model and must lie inside the model's own limits; the
firmware gets the same limits converted to pulses (``board_limits``) so both ends enforce them.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from pivla import arm
from pivla.io import atomic_write_bytes
from pivla.robot import protocol as P

NOMINAL_US_PER_RAD = 2000.0 / np.pi
CALIBRATION_VERSION = 1


class CalibrationError(ValueError):
    """A calibration file is missing, malformed or unsafe; the message names the field."""


def read_calibration_json(path: Path, how_to_make: str) -> object:
    """A calibration file's JSON, or a CalibrationError naming the file: missing (with how to make one) or corrupt."""
    try:
        return json.loads(path.read_text())
    except FileNotFoundError as exc:
        raise CalibrationError(f"calibration file not found: {path} ({how_to_make})") from exc
    except json.JSONDecodeError as exc:
        raise CalibrationError(f"{path} is not valid JSON: {exc}") from exc


@dataclass
class JointCalibration:
    name: str
    zero_us: float
    direction: int
    us_per_rad: float
    min_rad: float
    max_rad: float


@dataclass
class GripperCalibration:
    open_us: float = 1250.0
    closed_us: float = 1750.0


@dataclass
class ArmCalibration:
    joints: list[JointCalibration]
    gripper: GripperCalibration = field(default_factory=GripperCalibration)
    name: str = "arm"

    def __post_init__(self) -> None:
        self.validate()

    @classmethod
    def nominal(cls, name: str = "arm", margin_rad: float = 0.05) -> ArmCalibration:
        """Servos centred (1500 us) at the middle of each model joint range, nominal gain, direction +1."""
        joints = []
        for jname, (lo, hi) in zip(arm.JOINT_NAMES, arm.JOINT_LIMITS):
            mid = 0.5 * (lo + hi)
            joints.append(JointCalibration(jname, 1500.0 - NOMINAL_US_PER_RAD * mid, 1, NOMINAL_US_PER_RAD,
                                           float(lo + margin_rad), float(hi - margin_rad)))
        return cls(joints, GripperCalibration(), name)

    def validate(self) -> None:
        if len(self.joints) != len(arm.JOINT_NAMES):
            raise CalibrationError(f"calibration has {len(self.joints)} joints, the arm has {len(arm.JOINT_NAMES)}")
        for j, name, (lo, hi) in zip(self.joints, arm.JOINT_NAMES, arm.JOINT_LIMITS):
            if j.name != name:
                raise CalibrationError(f"joint {j.name!r} found where {name!r} was expected")
            values = [j.zero_us, j.us_per_rad, j.min_rad, j.max_rad]
            if not all(np.isfinite(v) for v in values):
                raise CalibrationError(f"joint {name}: non-finite value in {values}")
            if j.direction not in (-1, 1):
                raise CalibrationError(f"joint {name}: direction must be +1 or -1, got {j.direction}")
            if not 300.0 <= j.us_per_rad <= 1500.0:
                raise CalibrationError(f"joint {name}: us_per_rad {j.us_per_rad} is outside 300..1500")
            if not lo - 1e-6 <= j.min_rad < j.max_rad <= hi + 1e-6:
                raise CalibrationError(f"joint {name}: limits [{j.min_rad}, {j.max_rad}] must be an increasing "
                                       f"range inside the model's [{lo}, {hi}]")
            for q in (j.min_rad, j.max_rad):
                us = j.zero_us + j.direction * j.us_per_rad * q
                if not P.PULSE_ABS_MIN_US <= us <= P.PULSE_ABS_MAX_US:
                    raise CalibrationError(f"joint {name}: limit {q:.3f} rad maps to {us:.0f} us, outside the "
                                           f"servo range {P.PULSE_ABS_MIN_US}..{P.PULSE_ABS_MAX_US}")
        g = self.gripper
        for v in (g.open_us, g.closed_us):
            if not (np.isfinite(v) and P.PULSE_ABS_MIN_US <= v <= P.PULSE_ABS_MAX_US):
                raise CalibrationError(f"gripper pulse {v} outside {P.PULSE_ABS_MIN_US}..{P.PULSE_ABS_MAX_US}")
        if abs(g.open_us - g.closed_us) < 20:
            raise CalibrationError("gripper open_us and closed_us must differ by at least 20 us")

    @property
    def limits_rad(self) -> np.ndarray:
        return np.array([[j.min_rad, j.max_rad] for j in self.joints])

    def to_pulses(self, q: np.ndarray, opening: float) -> list[int]:
        """Joint angles (6,) and gripper opening (1 open .. 0 closed) -> 7 pulse widths (us)."""
        q = np.asarray(q, dtype=float)
        us = [j.zero_us + j.direction * j.us_per_rad * qi for j, qi in zip(self.joints, q)]
        g = self.gripper
        us.append(g.closed_us + float(np.clip(opening, 0.0, 1.0)) * (g.open_us - g.closed_us))
        return [int(round(u)) for u in us]

    def from_pulses(self, pulses_us) -> tuple[np.ndarray, float]:
        """Inverse of :meth:`to_pulses`: (q (6,), gripper opening)."""
        q = np.array([(p - j.zero_us) / (j.direction * j.us_per_rad) for j, p in zip(self.joints, pulses_us)])
        g = self.gripper
        opening = float(np.clip((pulses_us[6] - g.closed_us) / (g.open_us - g.closed_us), 0.0, 1.0))
        return q, opening

    def board_limits(self, home_q: np.ndarray, home_opening: float = 1.0) -> list[P.ChannelLimits]:
        """Per-channel firmware limits (pulses) equal to the calibrated joint limits, and the home pulses."""
        lo = self.to_pulses(self.limits_rad[:, 0], 0.0)
        hi = self.to_pulses(self.limits_rad[:, 1], 1.0)
        home = self.to_pulses(home_q, home_opening)
        out = []
        for ch in range(P.N_CHANNELS):
            a, b = sorted((lo[ch], hi[ch]))
            out.append(P.ChannelLimits(ch, a, b, int(np.clip(home[ch], a, b))))
        return out

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        doc = {"version": CALIBRATION_VERSION, "name": self.name, "joints": [asdict(j) for j in self.joints],
               "gripper": asdict(self.gripper)}
        atomic_write_bytes(path, json.dumps(doc, indent=2).encode())
        return path

    @classmethod
    def load(cls, path: str | Path) -> ArmCalibration:
        path = Path(path)
        doc = read_calibration_json(path, "create one with `pivla robot calibrate`")
        if not isinstance(doc, dict) or doc.get("version") != CALIBRATION_VERSION:
            raise CalibrationError(f"{path}: expected a calibration object with version {CALIBRATION_VERSION}")
        try:
            joints = [JointCalibration(**j) for j in doc["joints"]]
            for j in joints:
                j.direction = int(j.direction)
            gripper = GripperCalibration(**doc.get("gripper", {}))
            return cls(joints, gripper, str(doc.get("name", path.stem)))
        except (KeyError, TypeError) as exc:
            raise CalibrationError(f"{path}: malformed calibration ({exc})") from exc
