"""Reading an arm's MJCF: its body tree (bodies, hinge/slide joints, sites, masses) with ``xml.etree``, compiled
the way MuJoCo's compiler does (no MuJoCo needed), and the arm's own model (:func:`load_model`)."""

from __future__ import annotations

import functools
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

from pivla.arm.constants import ARM_XML, EE_SITE, GRIPPER_JOINTS, JOINT_NAMES
from pivla.arm.rotations import UNIT_QUAT, Quat, Vec3, mul_quat

_EPS = 1e-14  # MuJoCo's compiler's mjEPS


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
    out = list(mul_quat(tuple(a), tuple(b)))
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
        self.bodies: list[Body] = [Body("world", -1, (0.0, 0.0, 0.0), UNIT_QUAT, (), 0.0, (0.0, 0.0, 0.0))]
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

