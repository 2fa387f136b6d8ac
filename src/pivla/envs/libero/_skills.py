"""Skills of the scripted LIBERO experts, each a small phase machine for one BDDL subgoal: the shared config
and command types, and the articulated-object skills (drawers, the stove's knob, the microwave's door).

A skill is stepped once per control step with the eef pose and returns a :class:`Command` (an eef goal and
orientation, and the gripper), or None when it has finished. Goals are recomputed from the live simulator
state every step, so the control is closed-loop proportional control towards moving waypoints.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pivla.envs.libero._geometry import (
    FINGER_TIP,
    HAND_ABOVE_TIP,
    TIP_BELOW_EEF,
    Scene,
    closing_yaw,
    gripper_rotation,
    rotation_error,
    within_reach,
    wrap,
)


@dataclass(frozen=True)
class ExpertConfig:
    """Gains, margins and variety of the scripted experts (one set for every task; nothing is tuned per task)."""

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
    chord_close_below: float = 0.006  # a plate's chord grasp holds the eef this far (m) below the grasp while the
    # fingers close: unpressed, they ride up the sloping lip onto its top and close on nothing
    min_pinch: float = 0.01  # a top grasp holds at least this much of the object between the fingers (m)
    floor_clearance: float = 0.006  # fingertips never lower than this above the surface under the object (m)
    lift_clearance: float = 0.06  # object bottom above the highest body on the way (m)
    hand_clearance: float = 0.02  # the hand's underside above the highest body it passes over carrying (m)
    place_above: float = 0.015  # object bottom above the target's top at release, "on" goals (m)
    drop_above: float = 0.01  # object bottom above the container's rim at release, "in" goals (m)
    press_depth: float = 0.03  # below the release height, lowered further until a region goal holds (m)
    travel_clearance: float = 0.07  # eef above the highest body on the way to the pre-grasp (m)
    region_margin: float = 0.012  # a placed origin stays this far inside a region's sides (m)
    insert_standoff: float = 0.06  # held object this far outside an enclosure's opening before going in (m)
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
    max_skill_attempts: int = 2  # a subgoal still unmet after its skill ran is tried this often in all
    # Variety for demonstrations (see ``pivla.envs.libero.expert``): DART noise on executed actions, a
    # deliberately missed first grasp, and per-episode jitter of heights and speed. Labels stay clean.
    noise: float = 0.0  # std of Gaussian noise on executed action dims 0..5 (action units), outside precise phases
    miss: float = 0.0  # share of episodes whose first grasp is executed off the object
    miss_offset: tuple[float, float] = (0.02, 0.04)  # m, horizontal distance of a missed grasp from the right one

    def __post_init__(self) -> None:
        if not 0.0 <= self.miss <= 1.0:
            raise ValueError(f"miss must be a share in [0, 1], got {self.miss}")
        if self.miss > 0 and self.max_attempts < 2:
            raise ValueError("a deliberate miss needs max_attempts >= 2 to recover from")
        if self.noise < 0:
            raise ValueError(f"noise must be >= 0, got {self.noise}")


class PlanningError(RuntimeError):
    """A skill found no way to do its subgoal in the current scene (no grasp, no spot); the expert moves on."""


@dataclass
class Command:
    """What a skill asks for this step. ``goal`` None holds the arm still; ``aim`` / ``aim_grip``, when set, are
    what is executed instead (a deliberate miss), while ``goal`` / ``grip`` are the recorded label."""

    goal: np.ndarray | None
    rot: np.ndarray | None
    grip: float
    aim: np.ndarray | None = None
    aim_grip: float | None = None


class Skill:
    """One subgoal's phase machine. Subclasses define ``PHASES`` (in order), the ``PRECISE`` ones (run
    without DART noise) and ``_goal(phase, ee, rot) -> (command, finished)``."""

    PHASES: tuple[str, ...] = ()
    PRECISE: frozenset[str] = frozenset()

    def __init__(self, scene: Scene, config: ExpertConfig) -> None:
        self.scene = scene
        self.config = config
        self.phase = 0
        self.phase_steps = 0

    @property
    def phase_name(self) -> str:
        return self.PHASES[self.phase] if self.phase < len(self.PHASES) else "done"

    @property
    def precise(self) -> bool:
        return self.phase_name in self.PRECISE

    def _next_phase(self) -> None:
        self.phase += 1
        self.phase_steps = 0

    def reach(self, goal: np.ndarray) -> np.ndarray:
        return within_reach(self.scene.shoulder, goal)

    def step(self, ee: np.ndarray, rot: np.ndarray) -> Command | None:
        while self.phase < len(self.PHASES):
            command, finished = self._goal(self.PHASES[self.phase], ee, rot)
            if not finished:
                self.phase_steps += 1
                return command
            self._next_phase()
        return None

    def _goal(self, phase: str, ee: np.ndarray, rot: np.ndarray) -> tuple[Command, bool]:
        raise NotImplementedError

    def _reached(self, goal: np.ndarray, ee: np.ndarray, rot: np.ndarray, target_rot: np.ndarray | None,
                 tol: float) -> bool:
        oriented = target_rot is None or np.linalg.norm(rotation_error(target_rot, rot)) < self.config.ori_tol
        return bool(np.linalg.norm(goal - ee) < tol and oriented) or self.phase_steps >= self.config.waypoint_timeout


class Drawer(Skill):
    """Open or close a drawer (a slide joint of a cabinet).

    Opening grasps the handle bar from the front, the gripper pointing horizontally at the drawer and the
    fingers closing vertically around the bar (the gap between bar and drawer front, 1.6 cm, is barely wider
    than a finger, so a top-down hook would need sub-millimetre precision), then pulls along the slide until
    the joint is past LIBERO's "open" threshold. Closing pushes the bar with the closed fingertips, the
    gripper pointing down and pitched 45 degrees towards the cabinet: straight down, the hand (3.7 cm above the
    fingertips, 20 cm across and reaching 2-3 cm further than the fingers) hits the handle of the drawer
    above before a bottom drawer is shut; pointing horizontally, the hand (20 cm tall along its closing
    axis) cannot get down to a bottom drawer, or the wrist behind it hits what stands beside the cabinet.
    """

    OPEN_TARGET = -0.155  # slide position pulled to (LIBERO's open range is [-0.16, -0.14])
    PUSH_PITCH = np.pi / 4

    def __init__(self, scene: Scene, config: ExpertConfig, joint_name: str, opening: bool) -> None:
        super().__init__(scene, config)
        self.joint = scene.joint(joint_name)
        self.body = int(scene.m.jnt_bodyid[self.joint])
        self.opening = opening
        # The slide moves the drawer by qpos * axis; LIBERO's cabinets open at negative qpos, so the drawer
        # comes out along -axis.
        axis = scene.d.xaxis[self.joint].copy()
        self.out = -axis / np.linalg.norm(axis)
        geoms = scene.body_geoms(self.body)
        bar = max(geoms, key=lambda g: (scene.corners(np.array([g])) @ self.out).max())  # the outermost geom
        self.bar_pts = scene.corners(np.array([bar]))
        self.start_q = scene.qpos(self.joint)
        if opening:
            self.PHASES = ("clear", "reach", "enter", "close", "pull", "release", "back")
            self.PRECISE = frozenset({"enter", "close", "pull", "release"})
            self.grip_rot = gripper_rotation(0.0, pointing=-self.out)
        else:
            self.PHASES = ("clear", "turn", "above", "lower", "push", "back")
            self.PRECISE = frozenset({"lower", "push"})
            pointing = -self.out * np.sin(self.PUSH_PITCH) + np.array([0.0, 0.0, -np.cos(self.PUSH_PITCH)])
            lateral = np.cross([0.0, 0.0, 1.0], self.out)
            lateral /= np.linalg.norm(lateral)
            # Of the two closing directions, the one that turns the hand's shallower side (3.0 cm from the
            # axis, against 3.85 cm) towards the cabinet.
            y = lateral if np.cross(lateral, pointing) @ self.out > 0 else -lateral
            self.grip_rot = np.stack([np.cross(y, pointing), y, pointing], axis=1)
            # How far the closed fingertips reach past the eef towards the cabinet, and below it.
            corners = [np.array([xe, 0.0, ze]) for xe in (-0.0116, 0.0135) for ze in (0.013, -0.024)]
            world = [self.grip_rot @ c for c in corners]
            self.lead = max(float(w @ -self.out) for w in world)
            self.tip_below = -min(float(w[2]) for w in world)

    def open_footprint(self, margin: float) -> tuple[np.ndarray, np.ndarray]:
        """The drawer's xy box once pulled to ``OPEN_TARGET``, grown by ``margin``."""
        pts = self.scene.corners(self.scene.body_geoms(self.body))
        pts = pts + (self.OPEN_TARGET - self.scene.qpos(self.joint)) * -self.out
        return pts[:, :2].min(0) - margin, pts[:, :2].max(0) + margin

    def _bar(self) -> tuple[np.ndarray, float]:
        """The bar's centre and outer face (along ``out``) now: the drawer has moved with the joint."""
        pts = self.bar_pts + (self.scene.qpos(self.joint) - self.start_q) * -self.out
        return (pts.min(0) + pts.max(0)) / 2, float(np.max(pts @ self.out))

    def done(self) -> bool:
        q = self.scene.qpos(self.joint)
        return q <= self.OPEN_TARGET + 0.004 if self.opening else q > 0.0

    def _goal(self, phase: str, ee: np.ndarray, rot: np.ndarray) -> tuple[Command, bool]:
        centre, outer = self._bar()
        if self.opening:
            # The grip site 1.2 cm inside the bar's outer face: the finger pads (1.3 cm past the site) hold it.
            grasp = centre + self.out * (outer - centre @ self.out - 0.012)
            start = grasp + self.out * 0.09
        else:
            # The fingertips 2 mm off the bar's outer face, level with its middle.
            grasp = centre + self.out * (outer - centre @ self.out + self.lead + 0.002)
            grasp[2] = centre[2] + self.tip_below - 0.004
            start = grasp + self.out * 0.02
        if phase == "clear":  # from over or behind the drawer's front (it was just loaded): up and out first
            if self.phase_steps == 0 and (ee - start) @ self.out > -0.03:
                return Command(None, None, self._grip(phase)), True
            top = float(self.scene.corners(self.scene.body_geoms(self.body))[:, 2].max())
            self.safe = self.reach(np.array([*start[:2], max(ee[2], top + 0.08)]))
            return Command(self.safe, None, self._grip(phase)), self._reached(self.safe, ee, rot, None, 0.02)
        return self._open_goal(phase, ee, rot, grasp, start) if self.opening else \
            self._close_goal(phase, ee, rot, start)

    def _grip(self, phase: str) -> float:
        if self.opening:
            return 1.0 if phase in ("close", "pull") else -1.0
        return 1.0

    def _open_goal(self, phase: str, ee: np.ndarray, rot: np.ndarray, grasp: np.ndarray,
                   start: np.ndarray) -> tuple[Command, bool]:
        cfg, r, grip = self.config, self.grip_rot, self._grip(phase)
        # The hand, 20 cm tall along the vertical closing axis, may rest on something on the table below the
        # handle and keep the fingers a few millimetres high: closing still clamps the bar (1.6 cm tall, the
        # fingers open 7.7 cm), so being within a centimetre is enough.
        if phase == "reach":
            goal = self.reach(start)
            return Command(goal, r, grip), self._reached(goal, ee, rot, r, 0.012)
        if phase == "enter":
            goal = self.reach(grasp)
            deep = abs(float((goal - ee) @ self.out)) < 0.004 and np.linalg.norm(goal - ee) < 0.012
            return Command(goal, r, grip), deep or self.phase_steps >= 25
        if phase == "close":
            return Command(None, None, grip), self.phase_steps >= cfg.close_steps
        if phase == "pull":
            goal = self.reach(ee + self.out * 0.05)
            return Command(goal, r, grip), self.done() or self.phase_steps >= 80
        if phase == "release":
            return Command(None, None, grip), self.phase_steps >= cfg.open_steps
        goal = self.reach(grasp + self.out * 0.08)  # back: the fingers off the bar before anything else
        return Command(goal, r, grip), self._reached(goal, ee, rot, None, 0.015)

    def _close_goal(self, phase: str, ee: np.ndarray, rot: np.ndarray, start: np.ndarray) -> tuple[Command, bool]:
        r = self.grip_rot
        if phase == "turn":  # big turns drag the eef off its path: turn on the spot, clear of everything
            if self.phase_steps == 0:
                self.safe = ee.copy()
            return Command(self.safe, r, 1.0), self._reached(self.safe, ee, rot, r, 0.02)
        if phase == "above":
            goal = self.reach(start + [0.0, 0.0, 0.06])
            return Command(goal, r, 1.0), self._reached(goal, ee, rot, r, 0.012)
        if phase == "lower":
            goal = self.reach(start)
            return Command(goal, r, 1.0), self._reached(goal, ee, rot, r, 0.006)
        if phase == "push":
            goal = self.reach(np.array([*(ee - self.out * 0.05)[:2], start[2]]))
            return Command(goal, r, 1.0), self.done() or self.phase_steps >= 80
        goal = self.reach(np.array([*(ee + self.out * 0.04)[:2], ee[2] + 0.06]))  # back off and up
        return Command(goal, r, 1.0), self._reached(goal, ee, rot, None, 0.015)


class Push(Skill):
    """Slide an object along the table to a point by pushing it from behind with the closed fingertips, a third
    of its height up its side, the gripper pointing down with the fingers side by side across the push,
    correcting the line as it goes (half the sideways drift each step): faster than picking up an object that
    only has to make room."""

    PHASES = ("approach", "lower", "push", "rise")
    PRECISE = frozenset({"lower", "push"})

    def __init__(self, scene: Scene, config: ExpertConfig, obj: int, goal_xy: np.ndarray) -> None:
        super().__init__(scene, config)
        self.obj = obj
        self.goal_xy = np.asarray(goal_xy, dtype=np.float64)
        lo, hi = scene.aabb(obj)
        self.top = float(hi[2])
        self.tip_z = lo[2] + max(0.012, 0.35 * (hi[2] - lo[2]))
        self.start = self._centre()
        to_goal = self.goal_xy - self.start
        self.distance = float(np.linalg.norm(to_goal))
        self.u = to_goal / max(self.distance, 1e-9)
        # Of the two yaws with the fingers across the push, the one nearer neutral.
        self.rot = gripper_rotation(wrap(float(np.arctan2(self.u[1], self.u[0])), np.pi))

    def _centre(self) -> np.ndarray:
        lo, hi = self.scene.aabb(self.obj)
        return (lo[:2] + hi[:2]) / 2

    def _contact(self, lead: float) -> np.ndarray:
        """Eef xy with the fingers' front at the object's trailing side (``lead`` further along the push), on
        the line from the start to the goal, steered back by half the object's sideways drift."""
        pts = self.scene.corners(self.scene.geoms(self.obj))
        centre = (pts[:, :2].min(0) + pts[:, :2].max(0)) / 2
        back = float(np.min((pts[:, :2] - centre) @ self.u))
        lateral = np.array([-self.u[1], self.u[0]])
        on_line = self.start + self.u * float((centre - self.start) @ self.u)
        drift = float((centre - on_line) @ lateral)
        return centre + self.u * (back - FINGER_TIP[2] + lead) - lateral * 0.5 * drift

    def _goal(self, phase: str, ee: np.ndarray, rot: np.ndarray) -> tuple[Command, bool]:
        z = self.tip_z + TIP_BELOW_EEF
        if phase == "approach":
            goal = self.reach(np.array([*self._contact(-0.02), max(z, self.top + 0.02 - HAND_ABOVE_TIP + 0.06)]))
            return Command(goal, self.rot, 1.0), self._reached(goal, ee, rot, self.rot, 0.01)
        if phase == "lower":
            goal = self.reach(np.array([*self._contact(-0.02), z]))
            return Command(goal, self.rot, 1.0), self._reached(goal, ee, rot, self.rot, 0.006)
        if phase == "push":
            moved = float((self._centre() - self.start) @ self.u)
            goal = self.reach(np.array([*self._contact(0.03), z]))
            return Command(goal, self.rot, 1.0), moved >= self.distance or self.phase_steps >= 60
        goal = self.reach(np.array([ee[0], ee[1], self.top + 0.06]))
        return Command(goal, self.rot, 1.0), self._reached(goal, ee, rot, None, 0.02)


class Knob(Skill):
    """Turn a stove's knob on: grasp its fin across its narrow side (the fingers straddle the hinge) and turn
    the wrist about the knob's vertical axis until LIBERO counts it on (joint >= 0.5 rad; turned to 1.0)."""

    PHASES = ("approach", "descend", "close", "turn", "release", "rise")
    PRECISE = frozenset({"descend", "close", "turn", "release"})
    TURN_TO = 1.0  # knob joint angle (rad) turned to; LIBERO's "on" range starts at 0.5

    def __init__(self, scene: Scene, config: ExpertConfig, joint_name: str) -> None:
        super().__init__(scene, config)
        self.joint = scene.joint(joint_name)
        self.body = int(scene.m.jnt_bodyid[self.joint])
        pts = scene.corners(scene.body_geoms(self.body))
        # The fin is the knob's raised part: its geoms above the disc.
        top = pts[:, 2].max()
        fin = np.concatenate([scene.corners(np.array([g])) for g in scene.body_geoms(self.body)
                              if scene.corners(np.array([g]))[:, 2].max() > top - 0.005])
        self.axis_xy = scene.d.xanchor[self.joint][:2].copy()
        self.top = float(top)
        self.fin_bottom = float(fin[:, 2].min())
        # The fin's long direction: the larger of its extents in the knob's frame; the fingers close across it.
        rot = scene.d.xmat[self.body].reshape(3, 3)
        local = (fin[:, :2] - self.axis_xy) @ rot[:2, :2]
        long_axis = rot[:2, 0] if np.ptp(local[:, 0]) > np.ptp(local[:, 1]) else rot[:2, 1]
        self.sign = float(np.sign(scene.d.xaxis[self.joint][2]) or 1.0)  # world yaw direction of turning on
        # Of the two yaws closing across the fin, the one leaving the wrist nearest its middle after the turn.
        yaw = closing_yaw(np.array([-long_axis[1], long_axis[0]]))
        self.yaw0 = min((yaw, yaw - np.pi, yaw + np.pi), key=lambda y: abs(y + self.sign * 0.7))
        self.q0 = scene.qpos(self.joint)

    def done(self) -> bool:
        return self.scene.qpos(self.joint) >= self.TURN_TO - 0.05

    def _goal(self, phase: str, ee: np.ndarray, rot: np.ndarray) -> tuple[Command, bool]:
        cfg = self.config
        # Fingertips a third of the way down the fin (deeper would touch the disc).
        tip_z = self.top - 0.6 * (self.top - self.fin_bottom)
        grasp = np.array([*self.axis_xy, tip_z + TIP_BELOW_EEF])
        turned = self.scene.qpos(self.joint) - self.q0  # in the joint's sense: positive turns it on
        r = gripper_rotation(self.yaw0)
        if phase == "approach":
            goal = self.reach(grasp + [0, 0, 0.07])
            return Command(goal, r, -1.0), self._reached(goal, ee, rot, r, 0.01)
        if phase == "descend":
            goal = self.reach(grasp)
            return Command(goal, r, -1.0), self._reached(goal, ee, rot, r, 0.004)
        if phase == "close":
            return Command(None, None, 1.0), self.phase_steps >= cfg.close_steps
        if phase == "turn":
            # Lead the knob by 0.4 rad: the joint follows the fingers, which the fin lags behind a little.
            r = gripper_rotation(self.yaw0 + self.sign * (turned + 0.4))
            return Command(grasp, r, 1.0), self.done() or self.phase_steps >= 60
        if phase == "release":
            return Command(None, None, -1.0), self.phase_steps >= cfg.open_steps
        goal = self.reach(np.array([ee[0], ee[1], self.top + 0.1]))
        return Command(goal, None, -1.0), self._reached(goal, ee, rot, None, 0.02)


class Door(Skill):
    """Close a hinged door (the microwave's) by pushing its outer face around the hinge with the closed
    fingertips, the hand just above the door's top edge, until LIBERO counts it closed. The outer face trails
    while the door closes, so the fingers never get between the door and the cabinet; they push part-way
    along the door, clear of its handle."""

    PHASES = ("approach", "lower", "sweep", "rise")
    PRECISE = frozenset({"lower", "sweep"})
    LEAD = 0.3  # the push point runs ahead of the door's face by this angle (rad) about the hinge

    def __init__(self, scene: Scene, config: ExpertConfig, joint_name: str, is_closed: Any) -> None:
        super().__init__(scene, config)
        self.joint = scene.joint(joint_name)
        self.body = int(scene.m.jnt_bodyid[self.joint])
        self.is_closed = is_closed
        lo_q, hi_q = scene.m.jnt_range[self.joint]
        # Closing turns the joint towards the end of its range nearer zero (LIBERO's closed position), i.e.
        # the door turns about the world vertical in the direction ``turn``.
        closing = 1.0 if abs(hi_q) < abs(lo_q) else -1.0
        self.turn = closing * float(np.sign(scene.d.xaxis[self.joint][2]) or 1.0)
        geoms = scene.body_geoms(self.body)
        pts = scene.corners(geoms)
        self.top = float(pts[:, 2].max())
        # In the door's own frame: its long horizontal axis (from the hinge out), its faces across, the handle.
        hinge = scene.d.xanchor[self.joint]
        rot = scene.d.xmat[self.body].reshape(3, 3)
        local = (pts - hinge) @ rot
        long = 0 if np.ptp(local[:, 0]) > np.ptp(local[:, 1]) else 1
        across = 1 - long
        out_sign = 1.0 if abs(local[:, long].max()) > abs(local[:, long].min()) else -1.0
        panel = max(geoms, key=lambda g: np.ptp((scene.corners(np.array([g])) - hinge) @ rot[:, long]))
        panel_local = (scene.corners(np.array([panel])) - hinge) @ rot
        length = float(np.abs(panel_local[:, long]).max())
        # The face that trails while closing: the door's points move along turn * (z x r).
        moving = np.cross([0.0, 0.0, self.turn], rot[:, long] * out_sign)
        trail = -1.0 if moving @ rot[:, across] > 0 else 1.0
        face = panel_local[:, across].max() if trail > 0 else panel_local[:, across].min()
        handles = [g for g in geoms if g != panel]
        reach_out = length * 0.6
        if handles:
            handle_local = (scene.corners(np.array(handles)) - hinge) @ rot
            reach_out = min(reach_out, float(np.abs(handle_local[:, long]).min()) - 0.03)
        point = np.zeros(3)
        point[long] = out_sign * reach_out
        point[across] = face + trail * 0.013  # the closed fingers' half-thickness, plus a millimetre
        self.local_point = point

    def _point(self, lead: float) -> np.ndarray:
        """Push position (xy) on the door's trailing face, turned ``lead`` further about the hinge."""
        hinge = self.scene.d.xanchor[self.joint]
        rot = self.scene.d.xmat[self.body].reshape(3, 3)
        rel = (rot @ self.local_point)[:2]
        a = self.turn * lead
        c, s = np.cos(a), np.sin(a)
        return hinge[:2] + np.array([c * rel[0] - s * rel[1], s * rel[0] + c * rel[1]])

    def _goal(self, phase: str, ee: np.ndarray, rot: np.ndarray) -> tuple[Command, bool]:
        z = self.top + 0.006 - HAND_ABOVE_TIP + TIP_BELOW_EEF  # the hand just above the door's top edge
        r = gripper_rotation(0.0)
        if phase == "approach":
            goal = self.reach(np.array([*self._point(0.0), z + 0.08]))
            return Command(goal, r, 1.0), self._reached(goal, ee, rot, r, 0.012)
        if phase == "lower":
            goal = self.reach(np.array([*self._point(0.0), z]))
            return Command(goal, r, 1.0), self._reached(goal, ee, rot, r, 0.006)
        if phase == "sweep":
            goal = self.reach(np.array([*self._point(self.LEAD), z]))
            return Command(goal, r, 1.0), bool(self.is_closed()) or self.phase_steps >= 100
        goal = self.reach(np.array([ee[0], ee[1], self.top + 0.1]))
        return Command(goal, r, 1.0), self._reached(goal, ee, rot, None, 0.02)
