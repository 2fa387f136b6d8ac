"""Scripted pick-and-place experts with privileged simulator state, for LIBERO-Spatial and LIBERO-Object.

They exist so that demonstrations can be made offline. Each task of those suites is "pick X, put it on /
in Y" (the BDDL goal ``(On X Y)`` or ``(In X Y_contain_region)``). The expert reads the goal, the objects'
collision geometry and poses from MuJoCo, and plans:

- a grasp: concave objects (bowls: a ray straight down through the centre lands near the bottom) are
  grasped by the rim, with the fingers closing radially; the rim angle (and how far inside the rim the
  gripper axis sits) is chosen from a height map under both fingers, so that nothing (drawer walls, the
  cookie box, the bowl's own walls) stands above the fingertips, and so that the arm can reach the grasp,
  the lift and the release. Convex objects (cans, bottles, boxes) are grasped from the top, across their
  narrowest horizontal side;
- a slide out from under anything overhanging the grasped object, then a lift high enough to clear every
  body between the pick and the place;
- a release with the object's bottom just above the target's top (plate) or its rim (basket).

Motion is closed-loop proportional control of the end effector towards waypoints, in LIBERO's own
action space (OSC_POSE deltas, 0.05 m / 0.5 rad at full scale), so recorded actions are what a policy
has to output. Waypoints are kept within the arm's reach.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Callable

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


@dataclass(frozen=True)
class ExpertConfig:
    """Gains and margins of the scripted expert (one set for every task; nothing is tuned per task)."""

    pos_gain: float = 1.6  # action = gain * error / POS_SCALE, clipped
    rot_gain: float = 1.0
    max_pos_action: float = 1.0
    pos_tol: float = 0.008  # waypoint reached (m)
    grasp_tol: float = 0.003  # grasp reached (m): a rim grasp short of its depth slips
    transfer_tol: float = 0.02  # the transfer above the target may end this far off: placing corrects it
    ori_tol: float = 0.08  # orientation reached (rad)
    approach_above: float = 0.07  # pre-grasp height above the grasp point (m)
    rim_depth: float = 0.02  # fingertips below the rim top for a rim grasp (m); the wall is 2.6 mm thin and tilted
    rim_offsets: tuple[float, ...] = (0.0, 0.008, 0.016, 0.024)  # gripper axis this far inside the rim (m)
    finger_clearance: float = 0.005  # kept sideways between a descending finger and anything else (m)
    overhang_margin: float = 0.01  # a held object slides this far (m) past anything above it before lifting
    drop_distance: float = 0.05  # the held object moved this far (m) from the eef while carried: dropped, retry
    top_depth: float = 0.03  # fingertips below the object's top for a top grasp (m)
    floor_clearance: float = 0.006  # fingertips never lower than this above the surface under the object (m)
    lift_clearance: float = 0.06  # object bottom above the highest body on the way (m)
    place_above: float = 0.015  # object bottom above the target's top at release, "on" goals (m)
    drop_above: float = 0.01  # object bottom above the container's rim at release, "in" goals (m)
    travel_clearance: float = 0.07  # eef above the highest body on the way to the pre-grasp (m)
    max_attempts: int = 3  # grasps retried when the object did not come up
    retry_distance: float = 0.03  # a retried rim grasp keeps this far (m) from the failed ones
    stall_steps: int = 8  # descending this many steps without getting 1 mm closer: blocked, grasp elsewhere
    # (unless it is within pos_tol of the grasp: then the fingers close there)
    max_replans: int = 3  # grasp re-plans above the object before going down anyway
    replan_shift: float = 0.01  # a re-planned grasp this far (m) from the old one is travelled to first
    replan_turn: float = 0.1  # ... or turned this much (rad) from the old yaw
    rest_speed: float = 0.02  # object at rest: linear speed below this (m/s) ...
    rest_spin: float = 0.2  # ... and angular speed below this (rad/s)
    close_steps: int = 12
    open_steps: int = 8
    waypoint_timeout: int = 60  # steps before a waypoint is abandoned and the next one starts


class _Scene:
    """Collision geometry of the MuJoCo model, grouped by top-level body (objects, fixtures, robot)."""

    def __init__(self, rs_env: Any) -> None:
        self.mj = libero().mujoco
        self.m = rs_env.sim.model._model
        self.d = rs_env.sim.data._data
        m = self.m
        self.collide = (m.geom_contype | m.geom_conaffinity) > 0
        self.root_of_geom = m.body_rootid[m.geom_bodyid]
        robot_bodies = [b for b in range(m.nbody) if self._body_name(b).startswith(("robot0", "gripper0", "mount0"))]
        self.robot_roots = {int(m.body_rootid[b]) for b in robot_bodies}
        self.shoulder = self.d.xpos[self.mj.mj_name2id(m, self.mj.mjtObj.mjOBJ_BODY, "robot0_link2")].copy()  # joint 2

    def _body_name(self, b: int) -> str:
        return self.mj.mj_id2name(self.m, self.mj.mjtObj.mjOBJ_BODY, b) or ""

    def root(self, body_name: str) -> int:
        b = self.mj.mj_name2id(self.m, self.mj.mjtObj.mjOBJ_BODY, body_name)
        if b < 0:
            raise KeyError(f"no body {body_name!r} in the LIBERO scene")
        return int(self.m.body_rootid[b])

    def geoms(self, root: int) -> np.ndarray:
        return np.flatnonzero((self.root_of_geom == root) & self.collide)

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

    def body_frame_extent(self, root: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(centre in world, half sizes, world xy axes) of the object's box in its own yaw frame."""
        rot = self.d.xmat[root].reshape(3, 3)
        yaw = np.arctan2(rot[1, 0], rot[0, 0])
        axes = np.array([[np.cos(yaw), np.sin(yaw)], [-np.sin(yaw), np.cos(yaw)]])
        pts = self.corners(self.geoms(root))
        local = pts[:, :2] @ axes.T
        lo, hi = local.min(0), local.max(0)
        centre_xy = ((lo + hi) / 2) @ axes
        z = (pts[:, 2].min() + pts[:, 2].max()) / 2
        half = np.array([*(hi - lo) / 2, (pts[:, 2].max() - pts[:, 2].min()) / 2])
        return np.array([*centre_xy, z]), half, axes

    def ray_down(self, xy: np.ndarray, z_from: float) -> tuple[float, int]:
        """Height and top-level body of the first non-robot collision geom below (x, y, z_from)."""
        pnt = np.array([xy[0], xy[1], z_from], dtype=np.float64)
        vec = np.array([0.0, 0.0, -1.0])
        geomid = np.zeros(1, dtype=np.int32)
        groups = np.array([1, 0, 0, 0, 0, 0], dtype=np.uint8)  # robosuite puts collision geoms in group 0
        while True:
            dist = self.mj.mj_ray(self.m, self.d, pnt, vec, groups, 1, -1, geomid)
            if dist < 0:
                return -np.inf, -1
            root = int(self.root_of_geom[geomid[0]])
            hit = pnt[2] - dist
            if root not in self.robot_roots:
                return hit, root
            pnt[2] = hit - 1e-4


def _yaw_rotation(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ R_DOWN


def _closing_yaw(direction_xy: np.ndarray) -> float:
    """Gripper yaw whose finger-closing axis is parallel to ``direction_xy``, the smallest rotation from neutral."""
    theta = np.arctan2(direction_xy[1], direction_xy[0])
    yaw = theta + np.pi / 2  # neutral closing axis is world y: yaw by theta - 90 deg, modulo pi
    return float((yaw + np.pi / 2) % np.pi - np.pi / 2)


def _highest_under(z: np.ndarray, along: np.ndarray, across: np.ndarray, finger: tuple[float, float, float],
                   clearance: float) -> float:
    """Highest of the heights ``z`` sampled under both fingers of an open gripper: points ``along`` / ``across``
    the closing direction from the gripper axis, ``finger`` = (inner face, outer face, half-width)."""
    inner, outer, half_width = finger
    under = (along > inner - clearance) & (along < outer + clearance) & (across < half_width + clearance)
    return float(np.max(z, initial=-np.inf, where=under))


def _rotation_error(target: np.ndarray, current: np.ndarray) -> np.ndarray:
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


def _levelling(rot: np.ndarray) -> np.ndarray:
    """The smallest rotation that turns a body with orientation ``rot`` back upright (its z axis up)."""
    z = rot[:, 2]
    axis = np.cross(z, [0.0, 0.0, 1.0])
    s, c = float(np.linalg.norm(axis)), float(z[2])
    if s < 1e-9:
        return np.eye(3)
    k = axis / s
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * kx + (1 - c) * kx @ kx


@dataclass
class _Plan:
    grasp: np.ndarray  # eef position at the grasp
    yaw: float
    lift_z: float  # eef height for the transfer


class PickPlaceExpert:
    """Scripted expert for one "pick X and put it on/in Y" task; call it as ``expert(env, obs) -> action``.

    It plans when it sees a new episode (``env.episode_id`` changes), plans the grasp again once above
    the object (objects may still be settling), and retries the grasp when the object did not come up.
    Each phase is closed-loop proportional control of the eef towards a waypoint.
    """

    def __init__(self, config: ExpertConfig = ExpertConfig()) -> None:
        self.config = config
        self._episode: int | None = None

    def _setup(self, env: Any) -> None:
        rs = env.robosuite_env
        goal = rs.parsed_problem["goal_state"]
        if len(goal) != 1 or goal[0][0].lower() not in ("on", "in"):
            raise ValueError(f"the scripted expert handles one On/In goal; task goal is {goal}")
        _, obj_name, target_name = goal[0]
        self.scene = _Scene(rs)
        self.obj = self.scene.root(rs.objects_dict[obj_name].root_body)
        target_key = target_name.removesuffix("_contain_region")
        target = rs.objects_dict.get(target_key) or rs.fixtures_dict.get(target_key)
        if target is None:
            raise ValueError(f"goal target {target_name!r} is not an object or fixture of the scene")
        self.target = self.scene.root(target.root_body)
        self.into = goal[0][0].lower() == "in"
        self.failed: list[np.ndarray] = []  # xy of grasps that did not lift the object, this episode
        self._episode = env.episode_id

    # ---- planning -------------------------------------------------------------------------------------

    def _plan_grasp(self) -> _Plan:
        sc, cfg = self.scene, self.config
        centre, half, axes = sc.body_frame_extent(self.obj)
        lo, hi = sc.aabb(self.obj)
        z_top = hi[2]
        hit, root = sc.ray_down(centre[:2], z_top + 0.05)
        concave = root == self.obj and hit < z_top - 0.5 * (z_top - lo[2])
        if concave:
            return self._plan_rim(half, hi)
        # Convex object: grasp across the narrow side, fingertips a little below the top.
        narrow = axes[int(np.argmin(half[:2]))]
        floor_z = self._floor_below(lo, hi)
        tip_z = max(z_top - cfg.top_depth, floor_z + cfg.floor_clearance)
        grasp = np.array([centre[0], centre[1], tip_z + TIP_BELOW_EEF])
        return _Plan(grasp, _closing_yaw(narrow), grasp[2] + self._lift_above_grasp())

    def _floor_below(self, lo: np.ndarray, hi: np.ndarray) -> float:
        """Height of the surface the object rests on (rays just outside its footprint, ignoring itself)."""
        sc = self.scene
        zs = []
        for dx, dy in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            xy = (lo[:2] + hi[:2]) / 2 + np.array([dx, dy]) * ((hi[:2] - lo[:2]) / 2 + 0.01)
            z, _ = sc.ray_down(xy, hi[2] + 0.01)
            zs.append(z)
        return max(min(zs), lo[2]) if np.isfinite(min(zs)) else lo[2]

    def _plan_rim(self, half: np.ndarray, hi: np.ndarray) -> _Plan:
        """Pick the rim point where both fingers can go deepest: nothing (the bowl itself included) under them,
        with ``finger_clearance`` to spare sideways.

        The gripper axis may also sit inside the rim (``rim_offsets``): closing then slides the bowl that far
        towards the axis, and the outer finger keeps clear of a wall close to the bowl (a drawer's sides).
        Grasps are also scored by reach: the grasp, the lift above it and the release over the target
        should lie within COMFORT_REACH (a bowl in the drawer is at the edge of the arm's reach). Grasps
        whose fingers cannot get well below the rim rank even below a retry next to a failed grasp."""
        sc, cfg = self.scene, self.config
        radius = float(np.mean(half[:2]))
        origin = sc.d.xpos[self.obj][:2].copy()
        lift_above = self._lift_above_grasp()
        # Where the eef will hold the object over the target, relative to the grasp: it must be reachable too.
        to_place = np.array([*(self._place_xy() - origin), self._release_bottom() - sc.aabb(self.obj)[0][2]])
        grid_xy, grid_z = self._heightmap(origin, radius + FINGER_UPPER[1] + cfg.finger_clearance, hi[2] + 0.1)
        best: tuple[float, float, np.ndarray] | None = None
        for theta in np.linspace(0, 2 * np.pi, 24, endpoint=False):
            radial = np.array([np.cos(theta), np.sin(theta)])
            tangent = np.array([-radial[1], radial[0]])
            # The rim top is the bowl's highest point along this radial line (robust to a tilted bowl).
            rim_top, rim_xy = -np.inf, None
            for r in np.linspace(0.3 * radius, 1.2 * radius, 19):
                xy = origin + radial * r
                z, root = sc.ray_down(xy, hi[2] + 0.05)
                if root == self.obj and z > rim_top:
                    rim_top, rim_xy = z, xy
            if rim_xy is None:
                continue
            yaw = _closing_yaw(radial)
            for offset in cfg.rim_offsets:
                axis_xy = rim_xy - radial * offset
                # Highest surface of anything under either finger (the bowl's own walls count too), as seen
                # by the tip; the wider part above it may pass over what is lower than FINGER_TIP_HEIGHT.
                rel = grid_xy - axis_xy
                along, across = np.abs(rel @ radial), np.abs(rel @ tangent)
                under = max(_highest_under(grid_z, along, across, FINGER_TIP, cfg.finger_clearance),
                            _highest_under(grid_z, along, across, FINGER_UPPER, cfg.finger_clearance)
                            - FINGER_TIP_HEIGHT)
                tip_z = max(rim_top - cfg.rim_depth, under + 0.004)
                depth = rim_top - tip_z
                margin = tip_z - under  # room under the fingers: prefer grasps away from walls and neighbours
                score = min(depth, cfg.rim_depth) + 0.5 * min(margin, 0.03) - 0.004 * abs(yaw) - 0.5 * offset
                grasp = np.array([*axis_xy, tip_z + TIP_BELOW_EEF])
                stretch = max(self._wrist_distance(g) for g in (grasp, grasp + [0, 0, lift_above], grasp + to_place))
                score -= 2.0 * max(stretch - COMFORT_REACH, 0.0)
                if depth < cfg.rim_depth / 2:
                    score -= 1.0
                if any(np.linalg.norm(grasp[:2] - f) < cfg.retry_distance for f in self.failed):
                    score -= 0.5
                if best is None or score > best[0]:
                    best = (score, yaw, grasp)
        if best is None:
            raise RuntimeError("no rim point of the bowl is visible from above")
        _, yaw, grasp = best
        return _Plan(grasp, yaw, grasp[2] + lift_above)

    def _heightmap(self, centre: np.ndarray, half: float, z_from: float) -> tuple[np.ndarray, np.ndarray]:
        """Points (n, 2) of a square grid around ``centre`` and the height of the first surface under each."""
        ticks = np.arange(-half, half + 1e-9, RAY_SPACING)
        grid_xy = centre + np.stack(np.meshgrid(ticks, ticks), -1).reshape(-1, 2)
        return grid_xy, np.array([self.scene.ray_down(xy, z_from)[0] for xy in grid_xy])

    def _lift_above_grasp(self) -> float:
        """How far the eef rises from the grasp so that the held object's bottom clears every body between
        pick and place."""
        lo, hi = self.scene.aabb(self.obj)
        t_lo, t_hi = self.scene.aabb(self.target)
        top = max(t_hi[2], self._clear_height((lo[:2] + hi[:2]) / 2, (t_lo[:2] + t_hi[:2]) / 2, self.obj))
        return top + self.config.lift_clearance - lo[2]

    def _wrist_distance(self, eef: np.ndarray) -> float:
        """Shoulder to wrist distance of the arm with its eef at ``eef`` and the gripper pointing down."""
        rel = eef[:2] - self.scene.shoulder[:2]
        horizontal = max(float(np.linalg.norm(rel)) - WRIST_BEHIND_EEF, 0.0)
        return float(np.hypot(horizontal, eef[2] + WRIST_ABOVE_EEF - self.scene.shoulder[2]))

    def _within_reach(self, goal: np.ndarray) -> np.ndarray:
        """``goal`` brought within the arm's reach: lowered or raised at the same xy when that suffices,
        otherwise also pulled towards the shoulder."""
        shoulder = self.scene.shoulder
        rel = goal[:2] - shoulder[:2]
        dist = float(np.linalg.norm(rel))
        horizontal = dist - WRIST_BEHIND_EEF
        xy = goal[:2]
        if horizontal > ARM_REACH:
            xy, horizontal = shoulder[:2] + rel * (ARM_REACH + WRIST_BEHIND_EEF) / dist, ARM_REACH
        dz = np.sqrt(ARM_REACH**2 - max(horizontal, 0.0) ** 2)
        z = shoulder[2] - WRIST_ABOVE_EEF + np.clip(goal[2] + WRIST_ABOVE_EEF - shoulder[2], -dz, dz)
        return np.array([*xy, z])

    def _clear_height(self, a: np.ndarray, b: np.ndarray, ignore: int) -> float:
        """Highest surface (other than body ``ignore``) within 5 cm of the segment a -> b (xy), sampled densely
        enough along it not to miss a thin wall across it (a drawer's front)."""
        sc = self.scene
        top = -np.inf
        for s in np.linspace(0, 1, max(12, int(np.linalg.norm(b - a) / RAY_SPACING) + 2)):
            xy = a + (b - a) * s
            for off in ((0, 0), (0.05, 0), (-0.05, 0), (0, 0.05), (0, -0.05)):
                z, root = sc.ray_down(xy + np.array(off), 2.0)
                if root != ignore:
                    top = max(top, z)
        return top

    # ---- acting ---------------------------------------------------------------------------------------

    PHASES = ("travel", "descend", "close", "slide", "lift", "transfer", "place", "open", "retreat", "done")

    def _start_attempt(self, ee: np.ndarray) -> None:
        self.plan = self._plan_grasp()
        above = self.plan.grasp[2] + self.config.approach_above
        self.travel_z = max(above, self._clear_height(ee[:2], self.plan.grasp[:2], -1) + self.config.travel_clearance)
        self.start_xy = ee[:2].copy()  # the eef rises here first when it starts low
        self.obj_bottom0 = self.scene.aabb(self.obj)[0][2]
        self.replans = 0
        self.closest, self.stall = np.inf, 0  # progress of the descent
        self.slide: np.ndarray | None = None  # horizontal move of the held object before lifting it
        self.held: np.ndarray | None = None  # object origin relative to the eef when the transfer began
        self.phase = 0
        self.phase_steps = 0

    def _place_xy(self) -> np.ndarray:
        """Where the held object's reference point goes: LIBERO's On test compares body origins (within
        3 cm), so the target's origin for "on" goals; the container's centre for "in" goals."""
        if not self.into:
            return self.scene.d.xpos[self.target][:2].copy()
        t_lo, t_hi = self.scene.aabb(self.target)
        return (t_lo[:2] + t_hi[:2]) / 2

    def _release_bottom(self) -> float:
        """Height of the held object's bottom at release: just above the target's top (or rim)."""
        cfg = self.config
        return float(self.scene.aabb(self.target)[1][2]) + (cfg.drop_above if self.into else cfg.place_above)

    def _held_offset(self, ee: np.ndarray) -> np.ndarray:
        """The held object's reference point (xy) and bottom (z) relative to the eef; the object may have
        shifted or tilted in the hand. For "on" goals the reference point is where the object's origin
        will be once it has tipped upright about its lowest point after release."""
        sc = self.scene
        pts = sc.corners(sc.geoms(self.obj))
        lowest = pts[int(np.argmin(pts[:, 2]))]
        if self.into:
            ref = (pts[:, :2].min(0) + pts[:, :2].max(0)) / 2
        else:
            ref = (lowest + _levelling(sc.d.xmat[self.obj].reshape(3, 3)) @ (sc.d.xpos[self.obj] - lowest))[:2]
        return np.array([*ref, lowest[2]]) - ee

    def __call__(self, env: Any, obs: dict | None = None) -> np.ndarray:
        raw = env.raw_obs
        ee = np.asarray(raw["robot0_eef_pos"], dtype=np.float64)
        if self._episode != env.episode_id:
            self._setup(env)
            self.attempts = 1
            self._start_attempt(ee)
        rot = libero().T.quat2mat(raw["robot0_eef_quat"])
        target_rot = _yaw_rotation(self.plan.yaw)
        ori_err = _rotation_error(target_rot, rot)
        cfg = self.config
        while True:
            goal, grip, done = self._goal(self.PHASES[self.phase], ee, float(np.linalg.norm(ori_err)))
            if not done:
                break
            if self.PHASES[self.phase] == "travel" and self._replan():
                continue
            phase = self.PHASES[self.phase]
            failed = (
                (phase == "lift" and not self._lifted())
                or (phase == "descend" and self.stall >= cfg.stall_steps and self.closest > cfg.pos_tol)
                or (phase in ("transfer", "place") and self._dropped(ee))
            )
            if failed and self.attempts < cfg.max_attempts:
                self.failed.append(self.plan.grasp[:2].copy())
                self.attempts += 1
                self._start_attempt(ee)
                continue
            self.phase += 1
            self.phase_steps = 0
        self.phase_steps += 1
        if goal is None:
            return np.array([0, 0, 0, 0, 0, 0, grip], dtype=np.float64)
        pos_a = cfg.pos_gain * (goal - ee) / POS_SCALE
        pos_a *= min(1.0, cfg.max_pos_action / max(float(np.abs(pos_a).max()), 1e-9))  # saturate along the line
        rot_a = np.clip(cfg.rot_gain * ori_err / ROT_SCALE, -1.0, 1.0)
        return np.array([*pos_a, *rot_a, grip], dtype=np.float64)

    def _replan(self) -> bool:
        """Plan the grasp again just before going down (objects may still be settling when the episode
        starts, e.g. a bowl sliding off a ramekin); True when the new grasp must be travelled to first, so
        that the gripper turns above the object rather than next to it."""
        old, self.plan = self.plan, self._plan_grasp()
        # Yaws pi apart close the fingers along the same line: keep the one nearest the current target, or
        # a grasp across a square-ish object may flip and make the gripper turn half a circle going down.
        turn_by = (self.plan.yaw - old.yaw + np.pi / 2) % np.pi - np.pi / 2
        self.plan.yaw = old.yaw + turn_by
        turn = abs(turn_by)
        shift = float(np.linalg.norm(self.plan.grasp[:2] - old.grasp[:2]))
        if (shift > self.config.replan_shift or turn > self.config.replan_turn) and self.replans < self.config.max_replans:
            self.replans += 1
            self.phase_steps = 0
            return True
        return False

    def _at_rest(self) -> bool:
        vel = self.scene.d.cvel[self.obj]
        return bool(np.linalg.norm(vel[3:]) < self.config.rest_speed and np.linalg.norm(vel[:3]) < self.config.rest_spin)

    def _overhang_escape(self) -> np.ndarray:
        """Horizontal move (xy) that takes the object out from under anything above it, so that it can be
        lifted (a bowl at the back of an open drawer is partly under the cabinet's top); zero when free."""
        sc = self.scene
        lo, hi = sc.aabb(self.obj)
        ticks = [np.arange(lo[k], hi[k] + 1e-9, 0.005) for k in (0, 1)]
        grid = [np.array([x, y]) for x in ticks[0] for y in ticks[1]]
        footprint = np.array([xy for xy in grid if sc.ray_down(xy, hi[2] + 0.001)[1] == self.obj])
        covered = np.array([xy for xy in footprint if sc.ray_down(xy, 2.0)[1] != self.obj])  # something above
        if len(covered) == 0:
            return np.zeros(2)
        centre = footprint.mean(0)
        away = centre - covered.mean(0)
        away /= np.linalg.norm(away)
        # Until the object's rearmost point passes the overhang's frontmost covered point, plus a margin.
        return away * (float(np.max(covered @ away) - np.min(footprint @ away)) + self.config.overhang_margin)

    def _lifted(self) -> bool:
        return self.scene.aabb(self.obj)[0][2] > self.obj_bottom0 + 0.02

    def _dropped(self, ee: np.ndarray) -> bool:
        """Whether the held object has left the hand since the transfer began (it moved that far from the eef)."""
        held = self.scene.d.xpos[self.obj] - ee
        if self.held is None:
            self.held = held
        return bool(np.linalg.norm(held - self.held) > self.config.drop_distance)

    def _goal(self, phase: str, ee: np.ndarray, ori_err: float) -> tuple[np.ndarray | None, float, bool]:
        """(eef goal or None to hold still, gripper command, whether the phase is finished). Every goal is
        within the arm's reach."""
        cfg, p, reach = self.config, self.plan, self._within_reach
        timed_out = self.phase_steps >= cfg.waypoint_timeout
        oriented = ori_err < cfg.ori_tol
        if phase == "travel":
            rise = reach(np.array([*self.start_xy, self.travel_z]))
            if ee[2] < rise[2] - 0.02 and np.linalg.norm(ee[:2] - p.grasp[:2]) > 0.02 and not timed_out:
                return rise, -1.0, False
            goal, grip, need_ori = reach(np.array([*p.grasp[:2], self.travel_z])), -1.0, True
            if not self._at_rest() and not timed_out:
                return goal, grip, False
        elif phase == "descend":
            goal, grip, need_ori = reach(p.grasp), -1.0, True
            dist = float(np.linalg.norm(goal - ee))
            if dist < self.closest - 0.001 or dist < cfg.pos_tol:
                self.closest, self.stall = min(dist, self.closest), 0
            else:
                self.stall += 1
            if self.stall >= cfg.stall_steps:
                return goal, grip, True
        elif phase in ("close", "open"):
            steps, grip = (cfg.close_steps, 1.0) if phase == "close" else (cfg.open_steps, -1.0)
            return None, grip, self.phase_steps >= steps
        elif phase == "slide":
            if self.slide is None:
                self.slide = self._overhang_escape()
            if not self.slide.any():
                return None, 1.0, True
            goal, grip, need_ori = reach(np.array([*(p.grasp[:2] + self.slide), p.grasp[2]])), 1.0, False
        elif phase == "lift":
            goal, grip, need_ori = reach(np.array([*(p.grasp[:2] + self.slide), p.lift_z])), 1.0, False
        elif phase in ("transfer", "place") and self._dropped(ee):
            return None, 1.0, True
        elif phase == "transfer":
            off = self._held_offset(ee)
            goal, grip, need_ori = reach(np.array([*(self._place_xy() - off[:2]), p.lift_z])), 1.0, False
        elif phase == "place":
            off = self._held_offset(ee)
            goal = reach(np.array([*(self._place_xy() - off[:2]), self._release_bottom() - off[2]]))
            grip, need_ori = 1.0, False
        elif phase == "retreat":
            return reach(np.array([ee[0], ee[1], p.lift_z])), -1.0, False
        else:
            return None, -1.0, False
        tol = {"descend": cfg.grasp_tol, "transfer": cfg.transfer_tol}.get(phase, cfg.pos_tol)
        reached = np.linalg.norm(goal - ee) < tol and (oriented or not need_ori)
        return goal, grip, reached or timed_out


def expert_actor(suite: str, task: int | str) -> Callable[[Any, dict | None], np.ndarray]:
    """A scripted expert for one task of LIBERO-Spatial / LIBERO-Object (or their LIBERO-PRO variants).

    Returns ``actor(env, obs) -> action``: ``env`` is the ``LiberoEnv`` from ``make_env("libero", ...)``
    (rendering may be off), ``obs`` its latest observation (unused: the expert reads privileged state).
    """
    if not suite.startswith(("libero_spatial", "libero_object")):
        raise ValueError(f"scripted experts exist for libero_spatial and libero_object suites, not {suite!r}")
    from pivla.envs.libero.env import list_tasks

    names = [t.name for t in list_tasks(suite)]
    if isinstance(task, str) and task not in names:
        raise ValueError(f"unknown task {task!r} in suite {suite!r}")
    if isinstance(task, int) and not 0 <= task < len(names):
        raise ValueError(f"task index {task} out of range: suite {suite!r} has {len(names)} tasks")
    return PickPlaceExpert()


class RolloutExpert:
    """A task's expert behind ``pivla.envs.rollout``'s ``actor(obs)`` interface: ``reset(env, seed)``, called
    after every ``env.reset``, binds the env whose privileged state the expert reads."""

    source = "expert"

    def __init__(self, suite: str, task: int | str) -> None:
        self.expert = expert_actor(suite, task)
        self.env: Any = None

    def reset(self, env: Any, seed: int) -> None:
        self.env = env

    def __call__(self, obs: dict) -> np.ndarray:
        if self.env is None:
            raise RuntimeError("RolloutExpert: call reset(env, seed) after env.reset() first")
        return self.expert(self.env, obs)


def run_expert_episode(env: Any, actor: Callable[[Any, dict | None], np.ndarray], init_state: int) -> dict:
    """Roll out the expert from one official init state; returns success, steps and grasp attempts."""
    obs, info = env.reset(seed=init_state, options={"init_state": init_state})
    success, steps = bool(info["success"]), 0
    while not success:
        obs, _, terminated, truncated, info = env.step(actor(env, obs))
        steps += 1
        success = bool(info["success"])
        if terminated or truncated:
            break
    return {"init_state": init_state, "success": success, "steps": steps, "attempts": getattr(actor, "attempts", 1)}


def measure_experts(suite: str, tasks: list[int] | None = None, episodes: int = 10, first_init: int = 0) -> dict:
    """Per-task expert success over ``episodes`` init states (no rendering), one env at a time."""
    from pivla.envs.libero.env import list_tasks, make_env

    specs = list_tasks(suite)
    results: dict[str, Any] = {"suite": suite, "episodes_per_task": episodes, "tasks": []}
    for index in tasks if tasks is not None else range(len(specs)):
        env = make_env(suite, index, render=False)
        try:
            actor = expert_actor(suite, index)
            eps = [run_expert_episode(env, actor, first_init + e) for e in range(episodes)]
        finally:
            env.close()
        row = {"task": index, "name": specs[index].name, "successes": sum(e["success"] for e in eps),
               "episodes": len(eps), "mean_steps": float(np.mean([e["steps"] for e in eps])),
               "failed_init_states": [e["init_state"] for e in eps if not e["success"]]}
        logging.getLogger(__name__).info("%s task %d: %d/%d", suite, index, row["successes"], row["episodes"])
        results["tasks"].append(row)
    total = sum(r["successes"] for r in results["tasks"])
    results["success_rate"] = total / max(1, sum(r["episodes"] for r in results["tasks"]))
    return results


def main(argv: list[str] | None = None) -> int:
    """``python -m pivla.envs.libero.expert --suite libero_spatial --episodes 10``: per-task expert success."""
    import argparse
    import json

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("--suite", required=True)
    parser.add_argument("--tasks", default=None, help="comma-separated task indices (default: all)")
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--first-init", type=int, default=0, help="first official init state")
    parser.add_argument("--json", default=None, help="also write the results to this file")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    tasks = [int(t) for t in args.tasks.split(",")] if args.tasks else None
    results = measure_experts(args.suite, tasks, args.episodes, args.first_init)
    text = json.dumps(results, indent=1)
    if args.json:
        from pathlib import Path

        Path(args.json).write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
