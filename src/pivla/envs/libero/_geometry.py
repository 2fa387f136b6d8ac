"""What the scripted experts know of a LIBERO scene: collision geometry, ray casts, BDDL regions, joints, the
Panda's gripper shape and reach, and rotations of a gripper pointing down (or sideways).

All of it reads MuJoCo's model and data directly (privileged state); nothing here is visible to a policy.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pivla.envs.libero._backend import libero

POS_SCALE = 0.05  # metres per unit of position action (OSC_POSE output_max)
ROT_SCALE = 0.5  # radians per unit of rotation action
TIP_BELOW_EEF = 0.013  # the fingers' lowest point below robosuite's eef site (measured on the Panda gripper)
# An open Panda finger, from its collision mesh: (inner face, outer face) from the gripper axis and half-width
# across, for its lowest FINGER_TIP_HEIGHT (the narrow tip) and above it.
FINGER_TIP = (0.0386, 0.053, 0.0088)
FINGER_UPPER = (0.0386, 0.065, 0.0105)
FINGER_TIP_HEIGHT = 0.033
HAND_ABOVE_TIP = 0.037  # the hand's lowest point above the fingertips (its collision box, measured)
HAND_HALF_LENGTH = 0.103  # the hand's half extent along the finger-closing axis
HAND_HALF_WIDTH = 0.039  # ... and across it, along the eef's +x axis (0.0385)
HAND_BACK = 0.031  # ... and along its -x axis (0.030)
RAY_SPACING = 0.0035  # vertical rays sampling surfaces: closer than the thinnest wall (a drawer's sides, 4 mm)
# Reach of the Panda with the gripper pointing down, measured: the wrist (joint 6) sits this far above the eef
# site and this far from it towards the robot, and the shoulder (joint 2) to wrist distance peaks at 0.719 m
# with the elbow at -0.47 rad. A target beyond that takes the elbow through the singularity towards straight,
# where OSC keeps it against its joint limit and the arm can hardly come back: goals are kept within
# ARM_REACH, and grasps are preferred within COMFORT_REACH (near the limit the arm is slow and overshoots).
WRIST_ABOVE_EEF = 0.205
WRIST_BEHIND_EEF = 0.08
ARM_REACH = 0.70
COMFORT_REACH = 0.67

# Gripper pointing down (robosuite's neutral Panda pose): x forward, fingers closing along world y.
R_DOWN = np.diag([1.0, -1.0, -1.0])


class Scene:
    """Collision geometry of the MuJoCo model, grouped by top-level body (objects, fixtures, robot)."""

    def __init__(self, rs_env: Any) -> None:
        self.rs = rs_env
        self.mj = libero().mujoco
        self.m = rs_env.sim.model._model
        self.d = rs_env.sim.data._data
        m = self.m
        self.collide = (m.geom_contype | m.geom_conaffinity) > 0
        self.root_of_geom = m.body_rootid[m.geom_bodyid]
        robot_bodies = [b for b in range(m.nbody) if self.body_name(b).startswith(("robot0", "gripper0", "mount0"))]
        self.robot_roots = {int(m.body_rootid[b]) for b in robot_bodies}
        self.shoulder = self.d.xpos[self.body_id("robot0_link2")].copy()  # joint 2

    def body_name(self, b: int) -> str:
        return self.mj.mj_id2name(self.m, self.mj.mjtObj.mjOBJ_BODY, b) or ""

    def body_id(self, name: str) -> int:
        b = self.mj.mj_name2id(self.m, self.mj.mjtObj.mjOBJ_BODY, name)
        if b < 0:
            raise KeyError(f"no body {name!r} in the LIBERO scene")
        return int(b)

    def root(self, body_name: str) -> int:
        return int(self.m.body_rootid[self.body_id(body_name)])

    def entity_root(self, name: str) -> int:
        """Top-level body of a BDDL object or fixture."""
        entity = self.rs.objects_dict.get(name) or self.rs.fixtures_dict.get(name)
        if entity is None:
            raise KeyError(f"{name!r} is not an object or fixture of the scene")
        return self.root(entity.root_body)

    def geoms(self, root: int) -> np.ndarray:
        return np.flatnonzero((self.root_of_geom == root) & self.collide)

    def body_geoms(self, body: int) -> np.ndarray:
        """Collision geoms of one body (not its children)."""
        return np.flatnonzero((self.m.geom_bodyid == body) & self.collide)

    def corners(self, geoms: np.ndarray) -> np.ndarray:
        """World coordinates of the corners of each geom's local bounding box, (8 * n, 3)."""
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
        pts = []
        for g in geoms:
            local = self.m.geom_aabb[g, :3] + self.m.geom_aabb[g, 3:] * signs
            pts.append(self.d.geom_xpos[g] + local @ self.d.geom_xmat[g].reshape(3, 3).T)
        return np.concatenate(pts)

    def aabb(self, root: int) -> tuple[np.ndarray, np.ndarray]:
        pts = self.corners(self.geoms(root))
        return pts.min(0), pts.max(0)

    def yaw(self, root: int) -> float:
        rot = self.d.xmat[root].reshape(3, 3)
        return float(np.arctan2(rot[1, 0], rot[0, 0]))

    def body_frame_extent(self, root: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(centre in world, half sizes, world xy axes) of the object's box in its own yaw frame."""
        yaw = self.yaw(root)
        axes = np.array([[np.cos(yaw), np.sin(yaw)], [-np.sin(yaw), np.cos(yaw)]])
        pts = self.corners(self.geoms(root))
        local = pts[:, :2] @ axes.T
        lo, hi = local.min(0), local.max(0)
        centre_xy = ((lo + hi) / 2) @ axes
        z = (pts[:, 2].min() + pts[:, 2].max()) / 2
        half = np.array([*(hi - lo) / 2, (pts[:, 2].max() - pts[:, 2].min()) / 2])
        return np.array([*centre_xy, z]), half, axes

    def ray(self, pnt: np.ndarray, vec: np.ndarray, skip: set[int] | None = None) -> tuple[float, int]:
        """Distance along unit ``vec`` from ``pnt`` to the first collision geom not of the robot (nor of the
        top-level bodies in ``skip``), and its top-level body; (inf, -1) when nothing is hit."""
        pnt = np.array(pnt, dtype=np.float64)
        vec = np.asarray(vec, dtype=np.float64)
        geomid = np.zeros(1, dtype=np.int32)
        groups = np.array([1, 0, 0, 0, 0, 0], dtype=np.uint8)  # robosuite puts collision geoms in group 0
        skip = self.robot_roots if skip is None else self.robot_roots | skip
        travelled = 0.0
        while True:
            dist = self.mj.mj_ray(self.m, self.d, pnt, vec, groups, 1, -1, geomid)
            if dist < 0:
                return np.inf, -1
            root = int(self.root_of_geom[geomid[0]])
            travelled += dist
            if root not in skip:
                return travelled, root
            pnt = pnt + vec * (dist + 1e-4)
            travelled += 1e-4

    def ray_down(self, xy: np.ndarray, z_from: float, skip: set[int] | None = None) -> tuple[float, int]:
        """Height and top-level body of the first collision geom below (x, y, z_from), robot excluded."""
        dist, root = self.ray(np.array([xy[0], xy[1], z_from]), np.array([0.0, 0.0, -1.0]), skip)
        return (z_from - dist if np.isfinite(dist) else -np.inf), root

    # ---- BDDL regions and joints --------------------------------------------------------------------------

    def site(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """World position and rotation matrix of a MuJoCo site."""
        s = self.mj.mj_name2id(self.m, self.mj.mjtObj.mjOBJ_SITE, name)
        if s < 0:
            raise KeyError(f"no site {name!r} in the LIBERO scene")
        return self.d.site_xpos[s].copy(), self.d.site_xmat[s].reshape(3, 3).copy()

    def joint(self, name: str) -> int:
        j = self.mj.mj_name2id(self.m, self.mj.mjtObj.mjOBJ_JOINT, name)
        if j < 0:
            raise KeyError(f"no joint {name!r} in the LIBERO scene")
        return int(j)

    def qpos(self, joint: int) -> float:
        return float(self.d.qpos[self.m.jnt_qposadr[joint]])

    def holds(self, predicate: list[str]) -> bool:
        """Whether one BDDL predicate (e.g. ``["open", "wooden_cabinet_1_top_region"]``) holds now."""
        return bool(self.rs._eval_predicate(predicate))

    def speed(self, root: int) -> tuple[float, float]:
        """Linear (m/s) and angular (rad/s) speed of a body."""
        vel = self.d.cvel[root]
        return float(np.linalg.norm(vel[3:])), float(np.linalg.norm(vel[:3]))


def region_test(kind: str, pos: np.ndarray, mat: np.ndarray, size: np.ndarray, point: np.ndarray,
                margin: float = 0.0, z_margin: float = 0.0) -> bool:
    """LIBERO's geometric test of a BDDL region on a body origin, shrunk by ``margin`` (xy) and ``z_margin``.

    ``kind`` "in" is ``SiteObject.in_box`` (the world box ``pos -+ |mat @ size|``, 1 cm lower at the bottom);
    "on" is ``SiteObject.under`` (``mat @ (point - pos)`` within the site's xy half sizes, and from 5 mm below
    to 10 cm above its top face). LIBERO multiplies by ``mat``, not its transpose; so does this test.
    """
    size = np.asarray(size, dtype=np.float64)
    if kind == "in":
        half = np.abs(mat @ size)
        lo, hi = pos - half, pos + half
        lo[2] -= 0.01
        lo = lo + [margin, margin, z_margin]
        hi = hi - [margin, margin, z_margin]
        return bool(np.all(point > lo) and np.all(point < hi))
    delta = mat @ (np.asarray(point) - pos)
    return bool(size[2] - 0.005 + z_margin < delta[2] < size[2] + 0.10 - z_margin
                and np.all(np.abs(delta[:2]) < size[:2] - margin))


def gripper_rotation(yaw: float, pointing: np.ndarray | None = None) -> np.ndarray:
    """Eef orientation: pointing down (default) with the fingers closing along ``yaw`` + 90 degrees, or pointing
    horizontally along ``pointing`` with the fingers closing vertically."""
    if pointing is None:
        c, s = np.cos(yaw), np.sin(yaw)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ R_DOWN
    z = np.asarray(pointing, dtype=np.float64)
    z = z / np.linalg.norm(z)
    # Of the two vertical closing axes, the one keeping the hand's x axis forward (as when pointing down):
    # the other rolls the wrist half a turn, against joint 7's limit.
    y = np.array([0.0, 0.0, 1.0])
    if np.cross(y, z)[0] < 0:
        y = -y
    return np.stack([np.cross(y, z), y, z], axis=1)


def closing_yaw(direction_xy: np.ndarray) -> float:
    """Gripper yaw whose finger-closing axis is parallel to ``direction_xy``, the smallest rotation from neutral."""
    theta = np.arctan2(direction_xy[1], direction_xy[0])
    yaw = theta + np.pi / 2  # neutral closing axis is world y: yaw by theta - 90 deg, modulo pi
    return float((yaw + np.pi / 2) % np.pi - np.pi / 2)


def wrap(angle: float, period: float = 2 * np.pi) -> float:
    return float((angle + period / 2) % period - period / 2)


def highest_under(z: np.ndarray, along: np.ndarray, across: np.ndarray, finger: tuple[float, float, float],
                  clearance: float) -> float:
    """Highest of the heights ``z`` sampled under both fingers of an open gripper: points ``along`` / ``across``
    the closing direction from the gripper axis, ``finger`` = (inner face, outer face, half-width)."""
    inner, outer, half_width = finger
    under = (along > inner - clearance) & (along < outer + clearance) & (across < half_width + clearance)
    return float(np.max(z, initial=-np.inf, where=under))


def rotation_error(target: np.ndarray, current: np.ndarray) -> np.ndarray:
    """Axis-angle (world frame) taking ``current`` to ``target``."""
    r = target @ current.T
    angle = np.arccos(np.clip((np.trace(r) - 1) / 2, -1.0, 1.0))
    if angle < 1e-6:
        return np.zeros(3)
    axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    norm = np.linalg.norm(axis)
    if norm < 1e-6:  # angle ~ pi: take the axis from the symmetric part
        axis = np.sqrt(np.clip((np.diag(r) + 1) / 2, 0, None))
        norm = np.linalg.norm(axis)
    return axis / norm * angle


def levelling(rot: np.ndarray) -> np.ndarray:
    """The smallest rotation that turns a body with orientation ``rot`` back upright (its z axis up)."""
    z = rot[:, 2]
    axis = np.cross(z, [0.0, 0.0, 1.0])
    s, c = float(np.linalg.norm(axis)), float(z[2])
    if s < 1e-9:
        return np.eye(3)
    k = axis / s
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * kx + (1 - c) * kx @ kx


def wrist_distance(shoulder: np.ndarray, eef: np.ndarray) -> float:
    """Shoulder to wrist distance of the arm with its eef at ``eef`` and the gripper pointing down."""
    rel = eef[:2] - shoulder[:2]
    horizontal = max(float(np.linalg.norm(rel)) - WRIST_BEHIND_EEF, 0.0)
    return float(np.hypot(horizontal, eef[2] + WRIST_ABOVE_EEF - shoulder[2]))


def within_reach(shoulder: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """``goal`` brought within the arm's reach: lowered or raised at the same xy when that suffices,
    otherwise also pulled towards the shoulder."""
    rel = goal[:2] - shoulder[:2]
    dist = float(np.linalg.norm(rel))
    horizontal = dist - WRIST_BEHIND_EEF
    xy = goal[:2]
    if horizontal > ARM_REACH:
        xy, horizontal = shoulder[:2] + rel * (ARM_REACH + WRIST_BEHIND_EEF) / dist, ARM_REACH
    dz = np.sqrt(ARM_REACH**2 - max(horizontal, 0.0) ** 2)
    z = shoulder[2] - WRIST_ABOVE_EEF + np.clip(goal[2] + WRIST_ABOVE_EEF - shoulder[2], -dz, dz)
    return np.array([*xy, z])
