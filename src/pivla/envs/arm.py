"""The low-cost arm's kinematic model: one place for joint names, limits, zero positions and link lengths.

The arm is a ~$300 6-DOF hobby-servo arm (382 mm reach, 0.2 kg payload, 0.7 m/s, repeatability within
10 mm) with a parallel gripper. ``assets/arm.xml`` is its MJCF; the simulated twin includes it in its
scene and the real arm's driver uses the same functions below for kinematics, so nothing here renders.

The kinematics need neither MuJoCo nor torch (a robot laptop's client-only install runs them): this module
reads the MJCF's body tree with ``xml.etree`` and chains the transforms itself. Every step follows the
operation order of MuJoCo's ``mj_kinematics``, ``mj_comPos`` and ``mj_jacSite`` and its quaternion helpers,
so positions, rotations and Jacobians are bit-identical to MuJoCo's: the twin's IK, and with it the twin's
episodes, are the same as when this module called MuJoCo (tests/test_tabletop_arm.py compares the two).
The price is speed: one forward-kinematics pass costs ~50 us of Python against ~10 us in MuJoCo.

Frames and conventions (metres, radians):

- World/base frame: origin at the centre of the base plate on the table top, x forward, y left, z up.
- Zero position: every joint at 0 makes the arm point straight up (tool centre at z = 0.457 m).
  Positive ``shoulder_pitch`` / ``elbow_pitch`` / ``wrist_pitch`` lean the arm forward (towards +x).
- End-effector frame (site ``ee``): the tool centre point between the finger pads. Its x axis is the
  fingers' closing direction and its z axis points *against* the approach direction, so a top-down
  grasp has Euler angles (0, 0, yaw) — far from the Euler singularity and wrap-around.
- Euler angles are (roll, pitch, yaw) with ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (extrinsic x-y-z).

Link lengths (joint axis to joint axis): shoulder height 0.075, upper arm 0.150, forearm 0.132 (elbow to
wrist pitch), wrist pitch to tool centre 0.100; 0.150 + 0.132 + 0.100 = 0.382 m reach from the shoulder.
"""

from __future__ import annotations

import functools
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ARM_XML = Path(__file__).with_name("assets") / "arm.xml"

JOINT_NAMES: tuple[str, ...] = (
    "base_yaw",
    "shoulder_pitch",
    "elbow_pitch",
    "forearm_roll",
    "wrist_pitch",
    "wrist_roll",
)
# Each range spans ~180 degrees like a hobby servo; the servo's centre is the middle of its range.
JOINT_LIMITS: np.ndarray = np.array(
    [
        [-1.5708, 1.5708],
        [-1.5708, 1.5708],
        [-0.6, 2.54],
        [-1.5708, 1.5708],
        [-1.2, 1.94],
        [-1.5708, 1.5708],
    ]
)
ZERO_POSITION: np.ndarray = np.zeros(6)
GRIPPER_JOINTS: tuple[str, str] = ("finger_left", "finger_right")
GRIPPER_OPEN = 0.035  # finger travel per side (m): 70 mm maximum opening
LINK_LENGTHS: dict[str, float] = {
    "shoulder_height": 0.075,
    "upper_arm": 0.150,
    "forearm": 0.132,
    "wrist_to_tool": 0.100,
}
REACH = LINK_LENGTHS["upper_arm"] + LINK_LENGTHS["forearm"] + LINK_LENGTHS["wrist_to_tool"]
EE_SITE = "ee"
# Home: tool centre 0.15 m in front of the base, 0.15 m above the table, pointing down, yaw 0.
HOME_POSE = (np.array([0.15, 0.0, 0.15]), np.zeros(3))

# The 7-D action convention the twin and the real arm share (docs/twin.md): one action per control period
# moves the commanded tool pose by at most TRANS_SCALE metres and ROT_SCALE radians per unit, and is turned
# into joint targets by IK_ITERATIONS joint-limited damped-least-squares steps.
CONTROL_HZ = 10
TRANS_SCALE = 0.02  # m per unit action per control step
ROT_SCALE = 0.15  # rad per unit action per control step
IK_ITERATIONS = 8

Vec3 = tuple[float, ...]  # 3 floats
Quat = tuple[float, ...]  # 4 floats, (w, x, y, z)
Mat9 = tuple[float, ...]  # a 3x3 matrix, row-major

_MINVAL = 1e-15  # MuJoCo's mjMINVAL: its engine's threshold for normalising vectors
_EPS = 1e-14  # MuJoCo's compiler's mjEPS
_UNIT_QUAT: Quat = (1.0, 0.0, 0.0, 0.0)
_IDENTITY: Mat9 = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)


# ------------------------------------------------------------------------------------------ rotations
def euler_to_mat(euler: np.ndarray) -> np.ndarray:
    """Rotation matrix of (roll, pitch, yaw), ``R = Rz(yaw) Ry(pitch) Rx(roll)``."""
    r, p, y = np.asarray(euler, dtype=float)
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def mat_to_euler(mat: np.ndarray) -> np.ndarray:
    """Inverse of :func:`euler_to_mat` (pitch in [-pi/2, pi/2])."""
    m = np.asarray(mat, dtype=float).reshape(3, 3)
    pitch = np.arcsin(np.clip(-m[2, 0], -1.0, 1.0))
    return np.array([np.arctan2(m[2, 1], m[2, 2]), pitch, np.arctan2(m[1, 0], m[0, 0])])


# The helpers below repeat MuJoCo's arithmetic operation by operation on Python floats, including how its
# build groups the sums it vectorises (pairwise in quaternion products, norms and quat -> matrix: as measured
# against mujoco 4.0.0): the same IEEE double operations in the same order give the same bits, so nothing
# downstream of the kinematics (the twin's IK, its episodes) depends on which implementation ran.
def _mul_quat(a: Quat, b: Quat) -> Quat:
    a0, a1, a2, a3 = a
    b0, b1, b2, b3 = b
    return (
        (a0 * b0 - a1 * b1) + (-(a2 * b2) - a3 * b3),
        (a0 * b1 + a1 * b0) + (a2 * b3 - a3 * b2),
        (a0 * b2 - a1 * b3) + (a2 * b0 + a3 * b1),
        (a0 * b3 + a1 * b2) + (a3 * b0 - a2 * b1),
    )


def _rot_vec_quat(v: Vec3, q: Quat) -> Vec3:
    if q[0] == 1 and q[1] == 0 and q[2] == 0 and q[3] == 0:
        return v
    q0, q1, q2, q3 = q
    v0, v1, v2 = v
    t0 = q0 * v0 + q2 * v2 - q3 * v1
    t1 = q0 * v1 + q3 * v0 - q1 * v2
    t2 = q0 * v2 + q1 * v1 - q2 * v0
    return (
        v0 + 2 * (q2 * t2 - q3 * t1),
        v1 + 2 * (q3 * t0 - q1 * t2),
        v2 + 2 * (q1 * t1 - q2 * t0),
    )


def _mat_vec(m: Mat9, v: Vec3) -> Vec3:
    v0, v1, v2 = v
    return (
        m[0] * v0 + m[1] * v1 + m[2] * v2,
        m[3] * v0 + m[4] * v1 + m[5] * v2,
        m[6] * v0 + m[7] * v1 + m[8] * v2,
    )


def _add(a: Vec3, b: Vec3) -> Vec3:
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


def _sub(a: Vec3, b: Vec3) -> Vec3:
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def _cross(a: Vec3, b: Vec3) -> Vec3:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _normalize4(q: Quat) -> Quat:
    norm = math.sqrt((q[0] * q[0] + q[1] * q[1]) + (q[2] * q[2] + q[3] * q[3]))
    if norm < _MINVAL:
        return _UNIT_QUAT
    if abs(norm - 1) > _MINVAL:
        inv = 1 / norm
        return (q[0] * inv, q[1] * inv, q[2] * inv, q[3] * inv)
    return q


def _axis_angle_quat(axis: Vec3, angle: float) -> Quat:
    if angle == 0:
        return _UNIT_QUAT
    s = math.sin(angle * 0.5)
    return (math.cos(angle * 0.5), axis[0] * s, axis[1] * s, axis[2] * s)


def _quat_to_mat(q: Quat) -> Mat9:
    if q[0] == 1 and q[1] == 0 and q[2] == 0 and q[3] == 0:
        return _IDENTITY
    q00, q01, q02, q03 = q[0] * q[0], q[0] * q[1], q[0] * q[2], q[0] * q[3]
    q11, q12, q13 = q[1] * q[1], q[1] * q[2], q[1] * q[3]
    q22, q23, q33 = q[2] * q[2], q[2] * q[3], q[3] * q[3]
    return (
        (q00 - q22) + (q11 - q33), 2 * (q12 - q03), 2 * (q13 + q02),
        2 * (q12 + q03), (q00 + q22) - (q11 + q33), 2 * (q23 - q01),
        2 * (q13 - q02), 2 * (q23 + q01), (q00 - q22) - (q11 - q33),
    )  # fmt: skip


def _mat_to_quat(m: Mat9) -> Quat:
    if m[0] + m[4] + m[8] > 0:
        w = 0.5 * math.sqrt(1 + m[0] + m[4] + m[8])
        q = (w, 0.25 * (m[7] - m[5]) / w, 0.25 * (m[2] - m[6]) / w, 0.25 * (m[3] - m[1]) / w)
    elif m[0] > m[4] and m[0] > m[8]:
        x = 0.5 * math.sqrt(1 + m[0] - m[4] - m[8])
        q = (0.25 * (m[7] - m[5]) / x, x, 0.25 * (m[1] + m[3]) / x, 0.25 * (m[2] + m[6]) / x)
    elif m[4] > m[8]:
        y = 0.5 * math.sqrt(1 - m[0] + m[4] - m[8])
        q = (0.25 * (m[2] - m[6]) / y, 0.25 * (m[1] + m[3]) / y, y, 0.25 * (m[5] + m[7]) / y)
    else:
        z = 0.5 * math.sqrt(1 - m[0] - m[4] + m[8])
        q = (0.25 * (m[3] - m[1]) / z, 0.25 * (m[2] + m[6]) / z, 0.25 * (m[5] + m[7]) / z, z)
    return _normalize4(q)


def _quat_to_rotvec(q: Quat) -> Vec3:
    """Axis * angle of a unit quaternion, the shorter way round (MuJoCo's ``mju_quat2Vel`` at dt = 1)."""
    x, y, z = q[1], q[2], q[3]
    sin_half = math.sqrt(x * x + y * y + z * z)
    if sin_half < _MINVAL:
        x, y, z = 1.0, 0.0, 0.0
    else:
        inv = 1 / sin_half
        x, y, z = x * inv, y * inv, z * inv
    angle = 2 * math.atan2(sin_half, q[0])
    if angle > math.pi:
        angle -= 2 * math.pi
    return (x * angle, y * angle, z * angle)


def _flat_mat(mat: np.ndarray) -> Mat9:
    flat = np.asarray(mat, dtype=float).reshape(9)
    return tuple(flat.tolist())


def rotvec_from_mat(mat: np.ndarray) -> np.ndarray:
    """Axis * angle (3,) of a rotation matrix, angle in [-pi, pi]."""
    return np.array(_quat_to_rotvec(_mat_to_quat(_flat_mat(mat))))


def mat_from_rotvec(vec: np.ndarray) -> np.ndarray:
    """Rotation matrix of an axis * angle vector (Rodrigues' rotation, through the unit quaternion)."""
    vec = np.asarray(vec, dtype=float)
    angle = float(np.linalg.norm(vec))
    quat = _UNIT_QUAT
    if angle > 1e-12:
        quat = _axis_angle_quat(tuple((vec / angle).tolist()), angle)
    return np.array(_quat_to_mat(quat)).reshape(3, 3)


# ------------------------------------------------------------------------------------------------ MJCF
@dataclass(frozen=True)
class Joint:
    """A hinge (rotation about ``axis``) or slide joint, in its body's frame as MuJoCo compiles it."""

    name: str
    kind: str  # "hinge" or "slide"
    axis: Vec3  # unit vector
    pos: Vec3  # anchor
    ref: float  # joint value of the zero pose (MuJoCo's qpos0)
    range: tuple[float, float] | None  # radians (hinge) or metres (slide); None when unlimited


@dataclass(frozen=True)
class Body:
    """One rigid body: its frame relative to its parent's, its joints, and its mass and centre of mass
    (needed only because MuJoCo's Jacobian is expressed about the subtree's centre of mass)."""

    name: str
    parent: int  # index in ArmModel.bodies; 0 is the world
    pos: Vec3
    quat: Quat
    joints: tuple[Joint, ...]
    mass: float
    ipos: Vec3  # centre of mass in the body frame


@dataclass(frozen=True)
class Site:
    name: str
    body: int
    pos: Vec3
    quat: Quat


@dataclass(frozen=True)
class ArmModel:
    """The MJCF's kinematic tree, compiled like MuJoCo's compiler does. ``bodies[0]`` is the world."""

    bodies: tuple[Body, ...]
    sites: tuple[Site, ...]
    subtree_mass: tuple[float, ...]

    def joint(self, name: str) -> tuple[int, Joint]:
        """(body index, joint) of a joint by name."""
        for i, body in enumerate(self.bodies):
            for joint in body.joints:
                if joint.name == name:
                    return i, joint
        names = [j.name for b in self.bodies for j in b.joints]
        raise KeyError(f"no joint {name!r} in the arm model; joints: {names}")

    def site(self, name: str) -> Site:
        for site in self.sites:
            if site.name == name:
                return site
        raise KeyError(f"no site {name!r} in the arm model; sites: {[s.name for s in self.sites]}")

    def root(self, body: int) -> int:
        """The body's ancestor that hangs from the world (MuJoCo's ``body_rootid``)."""
        while body > 0 and self.bodies[body].parent > 0:
            body = self.bodies[body].parent
        return body


class MjcfError(ValueError):
    """The MJCF uses something this reader does not model; the message names the element."""


def _normvec(values: list[float]) -> float:
    """MuJoCo compiler's ``mjuu_normvec``: normalise in place unless already within mjEPS of unit length."""
    nrm = 0.0
    for v in values:
        nrm += v * v
    if nrm < _EPS:
        return 0.0
    nrm = math.sqrt(nrm)
    if abs(nrm - 1) > _EPS:
        for i in range(len(values)):
            values[i] /= nrm
    return nrm


def _compiler_mul_quat(a: list[float], b: list[float]) -> list[float]:
    out = list(_mul_quat(tuple(a), tuple(b)))
    _normvec(out)
    return out


# Geom volumes (MuJoCo's compiler, solid bodies), from size as compiled: the twin's masses follow from them.
_VOLUME = {
    "sphere": lambda s: 4 * math.pi * s[0] * s[0] * s[0] / 3,
    "capsule": lambda s: math.pi * (s[0] * s[0] * (2 * s[1]) + 4 * s[0] * s[0] * s[0] / 3),
    "cylinder": lambda s: math.pi * s[0] * s[0] * (2 * s[1]),
    "ellipsoid": lambda s: 4 * math.pi * s[0] * s[1] * s[2] / 3,
    "box": lambda s: s[0] * s[1] * s[2] * 8,
    "plane": lambda s: 0.0,
}
_IGNORED = {"camera", "light"}  # body children with no bearing on kinematics or mass


class _MjcfReader:
    """Reads the subset of MJCF the arm uses: nested bodies with hinge/slide joints, primitive geoms,
    sites, <inertial>, default classes (``class`` / ``childclass``) and the compiler's angle settings."""

    def __init__(self, path: Path):
        self.path = path
        try:
            root = ET.parse(path).getroot()
        except (OSError, ET.ParseError) as exc:
            raise MjcfError(f"{path}: cannot read MJCF: {exc}") from exc
        if root.tag != "mujoco":
            raise MjcfError(f"{path}: root element is <{root.tag}>, expected <mujoco>")
        if root.find(".//include") is not None:
            raise MjcfError(f"{path}: <include> is not supported; give the arm as one file")
        compiler = root.find("compiler")
        attrs = compiler.attrib if compiler is not None else {}
        self.degree = attrs.get("angle", "degree") == "degree"
        self.eulerseq = attrs.get("eulerseq", "xyz")
        if len(self.eulerseq) != 3 or any(c not in "xyzXYZ" for c in self.eulerseq):
            raise MjcfError(f"{path}: compiler eulerseq {self.eulerseq!r} must be three of x, y, z, X, Y, Z")
        self.from_geom = attrs.get("inertiafromgeom", "auto")
        lo, hi = (int(v) for v in attrs.get("inertiagrouprange", "0 5").split())
        self.group_range = (lo, hi)
        self.classes: dict[str, dict[str, dict[str, str]]] = {}
        for default in root.findall("default"):
            self._read_defaults(default, {})
        self.bodies: list[Body] = [Body("world", -1, (0.0, 0.0, 0.0), _UNIT_QUAT, (), 0.0, (0.0, 0.0, 0.0))]
        self.sites: list[Site] = []
        world = root.find("worldbody")
        if world is None:
            raise MjcfError(f"{path}: no <worldbody>")
        for child in world:
            self._read_child(child, 0, "main")

    def _read_defaults(self, el: ET.Element, inherited: dict[str, dict[str, str]]) -> None:
        name = el.get("class", "main")
        own = {tag: dict(attrs) for tag, attrs in inherited.items()}
        for child in el:
            if child.tag != "default":
                own.setdefault(child.tag, {}).update(child.attrib)
        self.classes[name] = own
        for child in el.findall("default"):
            self._read_defaults(child, own)

    def _attr(self, el: ET.Element, name: str, cls: str, default: str | None = None) -> str | None:
        if name in el.attrib:
            return el.attrib[name]
        klass = el.get("class", cls)
        if klass not in self.classes and klass != "main":
            raise MjcfError(f"{self.path}: <{el.tag}> uses unknown class {klass!r}")
        return self.classes.get(klass, {}).get(el.tag, {}).get(name, default)

    def _floats(self, el: ET.Element, name: str, cls: str, default: str, n: int | None = None) -> list[float]:
        text = self._attr(el, name, cls, default) or default
        try:
            values = [float(v) for v in text.split()]
        except ValueError as exc:
            raise MjcfError(f"{self.path}: <{el.tag} {name}={text!r}> is not a list of numbers") from exc
        if n is not None and len(values) != n:
            raise MjcfError(f"{self.path}: <{el.tag} {name}={text!r}> needs {n} numbers")
        return values

    def _angle(self, value: float) -> float:
        return value / 180.0 * math.pi if self.degree else value

    def _orientation(self, el: ET.Element, cls: str) -> Quat:
        """The element's quaternion as the compiler resolves ``quat`` / ``euler`` / ``axisangle``."""
        given = [k for k in ("quat", "euler", "axisangle", "xyaxes", "zaxis") if k in el.attrib]
        if len(given) > 1:
            raise MjcfError(f"{self.path}: <{el.tag} name={el.get('name')!r}> gives several orientations {given}")
        kind = given[0] if given else "quat"
        if kind == "quat":
            quat = self._floats(el, "quat", cls, "1 0 0 0", 4)
        elif kind == "euler":
            euler = [self._angle(v) for v in self._floats(el, "euler", cls, "0 0 0", 3)]
            quat = [1.0, 0.0, 0.0, 0.0]
            for angle, axis in zip(euler, self.eulerseq):
                rot = [math.cos(angle / 2), 0.0, 0.0, 0.0]
                rot["xyz".index(axis.lower()) + 1] = math.sin(angle / 2)
                quat = _compiler_mul_quat(quat, rot) if axis.islower() else _compiler_mul_quat(rot, quat)
        elif kind == "axisangle":
            *axis, angle = self._floats(el, "axisangle", cls, "0 0 1 0", 4)
            if _normvec(axis) < _EPS:
                raise MjcfError(f"{self.path}: <{el.tag} name={el.get('name')!r}> axisangle axis too small")
            half = self._angle(angle) / 2
            quat = [math.cos(half), math.sin(half) * axis[0], math.sin(half) * axis[1], math.sin(half) * axis[2]]
        else:
            raise MjcfError(f"{self.path}: <{el.tag} name={el.get('name')!r}> uses {kind}; "
                            "give quat, euler or axisangle")
        if _normvec(quat) == 0.0:
            raise MjcfError(f"{self.path}: <{el.tag} name={el.get('name')!r}> has a zero quaternion")
        return tuple(quat)

    def _read_child(self, el: ET.Element, parent: int, cls: str) -> None:
        if el.tag == "body":
            self._read_body(el, parent, cls)
        elif el.tag == "site":
            pos = tuple(self._floats(el, "pos", cls, "0 0 0", 3))
            self.sites.append(Site(el.get("name", ""), parent, pos, self._orientation(el, cls)))
        elif el.tag in ("joint", "freejoint", "inertial") and parent == 0:
            raise MjcfError(f"{self.path}: <{el.tag}> directly in <worldbody>")
        elif el.tag not in ("geom", "joint", "freejoint", "inertial") and el.tag not in _IGNORED:
            raise MjcfError(f"{self.path}: <{el.tag}> is not supported by the arm's kinematic model")

    def _read_joint(self, el: ET.Element, cls: str) -> Joint:
        name = el.get("name", "")
        kind = self._attr(el, "type", cls, "hinge")
        if kind not in ("hinge", "slide"):
            raise MjcfError(f"{self.path}: joint {name!r} is a {kind} joint; only hinge and slide are modelled")
        axis = self._floats(el, "axis", cls, "0 0 1", 3)
        if _normvec(axis) < _EPS:
            raise MjcfError(f"{self.path}: joint {name!r} has a zero axis")
        ref = self._floats(el, "ref", cls, "0", 1)[0]
        lo, hi = self._floats(el, "range", cls, "0 0", 2)
        if kind == "hinge" and self.degree:
            ref *= math.pi / 180.0
            lo, hi = (v * (math.pi / 180.0) if v else v for v in (lo, hi))
        limited = self._attr(el, "limited", cls, "auto")
        has_range = limited == "true" or (limited == "auto" and (lo != 0 or hi != 0))
        pos = tuple(self._floats(el, "pos", cls, "0 0 0", 3))
        return Joint(name, kind, tuple(axis), pos, ref, (lo, hi) if has_range else None)

    def _geom_mass(self, el: ET.Element, cls: str) -> tuple[float, Vec3] | None:
        """(mass, centre) of a geom that counts towards its body's inertia, else None."""
        group = int(self._attr(el, "group", cls, "0") or 0)
        if not self.group_range[0] <= group <= self.group_range[1]:
            return None
        kind = self._attr(el, "type", cls, "sphere") or "sphere"
        if kind not in _VOLUME:
            raise MjcfError(f"{self.path}: geom {el.get('name')!r} of type {kind} has no volume the model can compute")
        size = self._floats(el, "size", cls, "0 0 0")
        size += [0.0] * (3 - len(size))
        fromto = self._attr(el, "fromto", cls)
        if fromto is not None:
            ends = self._floats(el, "fromto", cls, "", 6)
            vec = [ends[0] - ends[3], ends[1] - ends[4], ends[2] - ends[5]]
            half = _normvec(vec) / 2
            if half < _EPS:
                raise MjcfError(f"{self.path}: geom {el.get('name')!r} fromto points coincide")
            size[1] = half
            if kind in ("ellipsoid", "box"):
                size[1], size[2] = size[0], half
            center = ((ends[0] + ends[3]) / 2, (ends[1] + ends[4]) / 2, (ends[2] + ends[5]) / 2)
        else:
            center = tuple(self._floats(el, "pos", cls, "0 0 0", 3))
        volume = _VOLUME[kind](size)
        mass_attr = self._attr(el, "mass", cls)
        if mass_attr is not None:
            mass = float(mass_attr) if volume > _EPS or float(mass_attr) == 0 else 0.0
        else:
            mass = float(self._attr(el, "density", cls, "1000") or 1000) * volume
        if mass <= _EPS:
            return None
        return mass, center

    def _read_body(self, el: ET.Element, parent: int, cls: str) -> None:
        cls = el.get("childclass", cls)
        name = el.get("name", "")
        if el.find("freejoint") is not None:
            raise MjcfError(f"{self.path}: body {name!r} has a free joint; the arm must hang from the world")
        pos = tuple(self._floats(el, "pos", cls, "0 0 0", 3))
        quat = self._orientation(el, cls)
        joints = tuple(self._read_joint(j, cls) for j in el.findall("joint"))
        inertial = el.find("inertial")
        if inertial is not None and self.from_geom != "true":
            mass = float(inertial.get("mass", "0"))
            ipos: Vec3 = tuple(self._floats(inertial, "pos", cls, "0 0 0", 3))
        else:
            mass, ipos = self._mass_from_geoms([self._geom_mass(g, cls) for g in el.findall("geom")], pos)
        index = len(self.bodies)
        self.bodies.append(Body(name, parent, pos, quat, joints, max(mass, 0.0), ipos))
        for child in el:
            self._read_child(child, index, cls)

    @staticmethod
    def _mass_from_geoms(geoms: list[tuple[float, Vec3] | None], body_pos: Vec3) -> tuple[float, Vec3]:
        """Body mass and centre of mass as the compiler sums them (same order, same operations)."""
        sel = [g for g in geoms if g is not None]
        if not sel:
            return 0.0, body_pos
        if len(sel) == 1:
            return sel[0]
        mass, com = 0.0, [0.0, 0.0, 0.0]
        for m, p in sel:
            mass += m
            com[0] += m * p[0]
            com[1] += m * p[1]
            com[2] += m * p[2]
        return mass, (com[0] / mass, com[1] / mass, com[2] / mass)

    def model(self) -> ArmModel:
        subtree = [b.mass for b in self.bodies]
        for i in range(len(self.bodies) - 1, 0, -1):
            subtree[self.bodies[i].parent] += subtree[i]
        return ArmModel(tuple(self.bodies), tuple(self.sites), tuple(subtree))


def read_mjcf(path: str | Path) -> ArmModel:
    """The kinematic tree of an MJCF file (bodies, hinge/slide joints, sites, masses)."""
    return _MjcfReader(Path(path)).model()


@functools.lru_cache(maxsize=1)
def load_model() -> ArmModel:
    """The arm alone (no scene), for kinematics. Cached: the model is immutable."""
    model = read_mjcf(ARM_XML)
    for name in (*JOINT_NAMES, *GRIPPER_JOINTS):
        model.joint(name)
    model.site(EE_SITE)
    return model


def _check_q(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    if q.shape != (6,):
        raise ValueError(f"joint vector must have shape (6,) for {JOINT_NAMES}, got {q.shape}")
    if not np.all(np.isfinite(q)):
        raise ValueError(f"joint vector contains NaN or inf: {q}")
    return q


def clip_to_limits(q: np.ndarray) -> np.ndarray:
    return np.clip(q, JOINT_LIMITS[:, 0], JOINT_LIMITS[:, 1])


@dataclass
class IKConfig:
    """Damped least squares on the site Jacobian. ``rot_weight`` trades metres against radians."""

    damping: float = 1e-3
    rot_weight: float = 0.2
    max_step: float = 0.3  # rad per joint per iteration, keeps the linearisation valid
    iterations: int = 30
    pos_tol: float = 5e-4
    rot_tol: float = 5e-3


@dataclass
class _Pose:
    """One forward-kinematics pass: what the site pose and its Jacobian are computed from."""

    xpos: list[Vec3]
    xquat: list[Quat]
    xmat: list[Mat9]
    axes: dict[str, tuple[Vec3, Vec3]]  # joint name -> (world axis, world anchor)
    site_pos: Vec3
    site_mat: Mat9


class Kinematics:
    """Forward kinematics and differential IK of the arm (one instance per thread: it caches the last pose)."""

    def __init__(self, model: ArmModel | None = None, config: IKConfig | None = None):
        self.model = model if model is not None else load_model()
        self.config = config or IKConfig()
        self.site = self.model.site(EE_SITE)
        self._index = {name: i for i, name in enumerate(JOINT_NAMES)}
        chain, body = set(), self.site.body
        while body > 0:
            chain.add(body)
            body = self.model.bodies[body].parent
        # (column, joint name, hinge?) of the arm joints that move the site; the others' columns stay zero
        self._dofs = [(self._index[name], name, self.model.joint(name)[1].kind == "hinge")
                      for name in JOINT_NAMES if self.model.joint(name)[0] in chain]
        self._root = self.model.root(self.site.body)
        # per body: its joints with their index in q (-1: held at ref) and whether the anchor is the origin
        self._plan = [(body, [(j, self._index.get(j.name, -1), all(math.copysign(1.0, v) > 0 and v == 0 for v in j.pos))
                              for j in body.joints]) for body in self.model.bodies[1:]]
        self._key: bytes | None = None
        self._pose: _Pose | None = None

    def _forward(self, q: np.ndarray) -> _Pose:
        """``mj_kinematics`` on the arm's tree: arm joints at ``q``, every other joint at its ``ref``."""
        key = q.tobytes()
        if key == self._key and self._pose is not None:
            return self._pose
        values = q.tolist()
        xpos: list[Vec3] = [(0.0, 0.0, 0.0)]
        xquat: list[Quat] = [_UNIT_QUAT]
        xmat: list[Mat9] = [_IDENTITY]
        axes: dict[str, tuple[Vec3, Vec3]] = {}
        for body, joints in self._plan:
            p = body.parent
            if p:
                pos = _add(_mat_vec(xmat[p], body.pos), xpos[p])
                quat = _mul_quat(xquat[p], body.quat)
            else:
                pos, quat = body.pos, body.quat
            for joint, i, centred in joints:
                value = (values[i] if i >= 0 else joint.ref) - joint.ref
                axis = _rot_vec_quat(joint.axis, quat)
                if centred:  # an anchor at +0 rotates to +0 (bit for bit), so only the addition is left to do
                    anchor = (pos[0] + 0.0, pos[1] + 0.0, pos[2] + 0.0)
                else:
                    anchor = _add(_rot_vec_quat(joint.pos, quat), pos)
                if joint.kind == "slide":
                    pos = (pos[0] + axis[0] * value, pos[1] + axis[1] * value, pos[2] + axis[2] * value)
                else:
                    quat = _mul_quat(quat, _axis_angle_quat(joint.axis, value))
                    pos = anchor if centred else _sub(anchor, _rot_vec_quat(joint.pos, quat))
                axes[joint.name] = (axis, anchor)
            quat = _normalize4(quat)
            xpos.append(pos)
            xquat.append(quat)
            xmat.append(_quat_to_mat(quat))
        s = self.site
        site_pos = _add(_mat_vec(xmat[s.body], s.pos), xpos[s.body])
        site_mat = _quat_to_mat(_mul_quat(xquat[s.body], s.quat))
        self._key, self._pose = key, _Pose(xpos, xquat, xmat, axes, site_pos, site_mat)
        return self._pose

    def fk_mat(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tool centre position (3,) and rotation matrix (3, 3) at joint angles ``q``."""
        pose = self._forward(_check_q(q))
        return np.array(pose.site_pos), np.array(pose.site_mat).reshape(3, 3)

    def forward_kinematics(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pos, mat = self.fk_mat(q)
        return pos, mat_to_euler(mat)

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        """(6, 6) Jacobian of [tool velocity; angular velocity] (world frame) w.r.t. the arm joints.

        Computed like ``mj_comPos`` + ``mj_jacSite``: each hinge's motion about the root's subtree centre of
        mass, shifted to the site. Mathematically the centre of mass cancels; it is kept so the rounding,
        and so every IK step, matches MuJoCo's."""
        pose = self._forward(_check_q(q))
        bodies = self.model.bodies
        com = [[0.0, 0.0, 0.0]]
        for b in range(1, len(bodies)):
            body, m, x = bodies[b], pose.xmat[b], pose.xpos[b]
            ip, mass = body.ipos, body.mass
            com.append([
                (m[0] * ip[0] + m[1] * ip[1] + m[2] * ip[2] + x[0]) * mass,
                (m[3] * ip[0] + m[4] * ip[1] + m[5] * ip[2] + x[1]) * mass,
                (m[6] * ip[0] + m[7] * ip[1] + m[8] * ip[2] + x[2]) * mass,
            ])
        for b in range(len(bodies) - 1, 0, -1):
            parent, child = com[bodies[b].parent], com[b]
            parent[0] += child[0]
            parent[1] += child[1]
            parent[2] += child[2]
        r = self._root
        if self.model.subtree_mass[r] < _MINVAL:
            root_com = _add(_mat_vec(pose.xmat[r], bodies[r].ipos), pose.xpos[r])
        else:
            inv = 1.0 / self.model.subtree_mass[r]
            root_com = (com[r][0] * inv, com[r][1] * inv, com[r][2] * inv)
        offset = _sub(pose.site_pos, root_com)
        cols = [(0.0,) * 6] * 6
        for col, name, hinge in self._dofs:
            axis, anchor = pose.axes[name]
            if hinge:
                lin = _cross(axis, _sub(root_com, anchor))
                turn = _cross(axis, offset)
                cols[col] = (lin[0] + turn[0], lin[1] + turn[1], lin[2] + turn[2], *axis)
            else:
                cols[col] = (*axis, 0.0, 0.0, 0.0)
        return np.array(cols).T.copy()

    def ik_step(self, q: np.ndarray, target_pos: np.ndarray, target_mat: np.ndarray) -> np.ndarray:
        """One damped-least-squares step towards the target pose; the result is inside the joint limits.

        Joints that would cross a limit are clamped and the step is re-solved without them, so the
        remaining joints still reduce the error instead of the clamp silently distorting the motion.
        """
        cfg = self.config
        q = _check_q(q)
        pos, mat = self.fk_mat(q)
        err = np.concatenate([target_pos - pos, cfg.rot_weight * rotvec_from_mat(target_mat @ mat.T)])
        jac = self.jacobian(q)
        jac[3:] *= cfg.rot_weight
        free = np.ones(6, bool)
        for _ in range(3):
            j = jac[:, free]
            dq_free = j.T @ np.linalg.solve(j @ j.T + cfg.damping * np.eye(6), err)
            dq = np.zeros(6)
            dq[free] = dq_free
            scale = np.max(np.abs(dq)) / cfg.max_step
            if scale > 1.0:
                dq /= scale
            q_new = q + dq
            hit = (q_new < JOINT_LIMITS[:, 0]) | (q_new > JOINT_LIMITS[:, 1])
            if not np.any(hit & free):
                return q_new
            free &= ~hit
            if not np.any(free):
                break
        return clip_to_limits(q_new)

    def pose_error(self, q: np.ndarray, target_pos: np.ndarray, target_mat: np.ndarray) -> tuple[float, float]:
        pos, mat = self.fk_mat(q)
        return float(np.linalg.norm(target_pos - pos)), float(np.linalg.norm(rotvec_from_mat(target_mat @ mat.T)))

    def solve_ik(
        self,
        target_pos: np.ndarray,
        target_euler: np.ndarray,
        q0: np.ndarray | None = None,
        iterations: int | None = None,
    ) -> tuple[np.ndarray, float, float]:
        """Iterate :meth:`ik_step` from ``q0``; returns (q, position error m, rotation error rad).

        An unreachable target gives the closest joint-limited configuration found, with its error, so the
        caller decides whether that is good enough (the env moves towards it; the robot refuses it).
        """
        target_pos = np.asarray(target_pos, dtype=float)
        target_mat = euler_to_mat(target_euler)
        if target_pos.shape != (3,) or not np.all(np.isfinite(target_pos)) or not np.all(np.isfinite(target_mat)):
            raise ValueError(f"IK target must be finite position (3,) and Euler (3,), got {target_pos}, {target_euler}")
        q = clip_to_limits(_check_q(q0 if q0 is not None else home_q()))
        cfg = self.config
        for _ in range(iterations or cfg.iterations):
            pos_err, rot_err = self.pose_error(q, target_pos, target_mat)
            if pos_err < cfg.pos_tol and rot_err < cfg.rot_tol:
                break
            q = self.ik_step(q, target_pos, target_mat)
        pos_err, rot_err = self.pose_error(q, target_pos, target_mat)
        return q, pos_err, rot_err


@functools.lru_cache(maxsize=1)
def _default() -> Kinematics:
    return Kinematics()


def forward_kinematics(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tool centre position (m) and Euler angles (rad) at joint angles ``q`` (6,)."""
    return _default().forward_kinematics(q)


def ik_step(q: np.ndarray, target_pos: np.ndarray, target_euler: np.ndarray) -> np.ndarray:
    """One joint-limited damped-least-squares step from ``q`` towards a pose."""
    return _default().ik_step(q, np.asarray(target_pos, float), euler_to_mat(target_euler))


def solve_ik(
    target_pos: np.ndarray, target_euler: np.ndarray, q0: np.ndarray | None = None
) -> tuple[np.ndarray, float, float]:
    """Joint angles reaching a pose from ``q0`` (default home): (q, position error, rotation error)."""
    return _default().solve_ik(target_pos, target_euler, q0)


@functools.lru_cache(maxsize=1)
def _home_q() -> tuple[float, ...]:
    guess = np.array([0.0, 0.4, 1.6, 0.0, 1.1, 0.0])
    q, pos_err, rot_err = _default().solve_ik(*HOME_POSE, q0=guess, iterations=200)
    if pos_err > 1e-3 or rot_err > 1e-2:
        raise RuntimeError(f"home pose unreachable (error {pos_err:.4f} m, {rot_err:.4f} rad): arm.xml changed?")
    return tuple(q)


def home_q() -> np.ndarray:
    """Joint angles of :data:`HOME_POSE` (elbow up, wrist below the elbow)."""
    return np.array(_home_q())
