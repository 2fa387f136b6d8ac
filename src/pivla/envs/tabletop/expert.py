"""Scripted experts: a waypoint state machine on privileged simulator state that emits the policy's own
7-D action (so demonstrations are exactly what a policy has to learn).

Every task is a sequence of goals (:mod:`tasks`); each goal expands into phases (approach above, descend,
close, lift, carry, lower, release, retreat; at the drawer, with the fingers closed throughout: approach,
descend, pull or push, retreat). Every gripper command is fully open or closed, the only two a policy's
thresholded gripper executes. A phase drives the tool centre to a target that is
recomputed from the live state every step with a clipped proportional law, and ends when within tolerance
or after a step budget (so a slipped grasp shows up as a failed episode, never as a hang). The loop is
closed on the *measured* pose, so the same script works with servo backlash and deadband.

``noise > 0`` makes demonstrations diverse and teaches recovery (DART, Laskey et al. 2017): Gaussian noise
perturbs the *executed* motion, while the *recorded* label (``expert.label``) stays the expert's clean
action for the state it actually reached, so a policy learns to correct drift instead of imitating the noise.
Phases that end on a millimetre tolerance (``PRECISE_PHASES``: setting an object down, gripping, releasing)
run without noise: with it, lowering took ~11 steps instead of 3, and the demonstrations taught a policy to
hover with the object instead of letting go. A per-episode draw of lift height, approach height and speed
adds variety.

A grasp that does not hold is retried (open, rise, approach again). ``miss > 0`` makes that recovery part
of the demonstrations, in the same DART spirit: in that share of episodes the first grasp is *executed* a few
centimetres off the object and closed on nothing, while the labels stay the clean expert's; the reopening and
the second approach that follow are recorded as they are. Policies trained without it closed the gripper
short of a small object and then hovered with it closed for the rest of the episode
(docs/experiments.md#missed-grasp-recovery-in-the-demonstrations).

A descent that ends up more than ``OFF_TARGET`` beside the object (the arm pushed, the object displaced) is
abandoned, and a low tool that far off rises before it moves over: returning at grasp height, the fingers dragged
the object out of reach. Without the re-approach the expert failed 15 of the twin benchmark's 90 pushed (6 cm)
validation episodes, with it 4.

``place_miss > 0`` does the same for setting an object down on another: in that share of episodes the carry is first
*executed* to a point 2-4 cm beside the object below, then brought back over it. Policies trained without it let the
block go 2-3 cm beside the one below, where the demonstrations had never shown a correction
(docs/experiments.md#a-missed-placement-in-the-demonstrations).
"""

from __future__ import annotations

from collections.abc import Callable, Generator, Iterator
from dataclasses import dataclass

import numpy as np

from pivla import arm
from pivla.arm.rotations import wrap_angle
from pivla.envs.tabletop import tasks
from pivla.envs.tabletop.env import ROT_SCALE, TRANS_SCALE, TabletopEnv
from pivla.envs.tabletop.scene import HANDLE_HALF_DEPTH
from pivla.envs.twin import check_misses, check_share, draw_miss

Target = Callable[[dict], np.ndarray]
STALL = 0.0015  # m over three steps: a phase whose tool moves less than this has stalled
PRECISE_PHASES = frozenset({"lower", "close", "release"})  # no DART noise while these run
# The drawer, worked with closed fingers (half depth along the closing axis, m): they come down HOOK_BEHIND
# behind the handle bar's centre (midway to the drawer front) and pull it DRAWER_PULL towards the robot, or
# PUSH_CLEARANCE in front of the bar and push it closed.
FINGER_HALF_DEPTH, PUSH_CLEARANCE, HOOK_BEHIND, DRAWER_PULL = 0.01, 0.012, 0.03, 0.075
# A grasp approached from the side sweeps the object away (after a push at grasp height, a straight return dragged
# it out of reach): a descent that ends up this far off the object, horizontally, goes back up and over it, and a
# low tool this far off rises before it moves (m). Undisturbed descents stay well inside it.
OFF_TARGET = 0.025
REAPPROACHES = 3  # descents abandoned for being off target, at most, per grasp


@dataclass(frozen=True)
class ExpertConfig:
    noise: float = 0.0  # std of Gaussian noise on executed action dims 0..5 (action units); labels stay clean
    gain: float = 0.9  # proportional gain (fraction of the error corrected per step)
    lift: float = 0.07  # carry height of the tool centre above its grasp height (m)
    approach: float = 0.05  # height above the grasp point before descending (m)
    grip_steps: int = 3  # control steps to close or open the gripper
    # steps recorded after success: the task succeeds on the first opening step, and a demonstration that
    # stops there shows release once, so policies learned to set the object down and keep holding it
    follow_through: int = 5
    retries: int = 2  # further grasps after one that did not hold
    miss: float = 0.0  # share of episodes whose first grasp is executed off the object (labels stay clean)
    miss_offset: tuple[float, float] = (0.02, 0.04)  # m, horizontal distance of a missed grasp from the object
    place_miss: float = 0.0  # share of stacking episodes whose carry first goes to a point beside the block below


class Expert:
    """Callable actor: ``expert.reset(env, seed)`` once per episode, then ``action = expert(obs)``."""

    source = "expert"

    def __init__(self, config: ExpertConfig | None = None):
        self.config = config or ExpertConfig()
        check_misses(self.config.miss, self.config.retries)
        check_share("place_miss", self.config.place_miss)
        self.env: TabletopEnv | None = None
        self._plan: Iterator[np.ndarray] | None = None
        self.phase = ""

    @property
    def follow_through(self) -> int:
        """Steps the rollout runner records after success (see ``ExpertConfig.follow_through``)."""
        return self.config.follow_through

    def reset(self, env, seed: int | None = None) -> None:
        self.env = env.unwrapped
        if not isinstance(self.env, TabletopEnv):
            raise TypeError("the scripted expert needs a tabletop env (it reads privileged simulator state)")
        self.rng = np.random.default_rng(seed)
        cfg = self.config
        jitter = self.rng.uniform(-1.0, 1.0, 3) if cfg.noise > 0 else np.zeros(3)
        self.lift = cfg.lift + 0.015 * jitter[0]
        self.approach = cfg.approach + 0.01 * jitter[1]
        self.gain = cfg.gain * (1.0 + 0.1 * jitter[2])
        self._miss = draw_miss(self.rng, cfg.miss, cfg.miss_offset)
        # only a goal the cameras see (an object to stack on) can be missed: the target of a move is a point relative to
        # where the object started, which no picture shows once it is lifted, so a correction towards it cannot be
        # learnt. Drawn only then, so that every other demonstration keeps the draws it had.
        stacks = cfg.place_miss > 0 and any(goal.kind == "stack" for goal in self.env.task.goals)
        self._place_miss = draw_miss(self.rng, cfg.place_miss, cfg.miss_offset) if stacks else None
        self._plan = self._task_plan()
        self._executed: np.ndarray | None = None
        self.label: np.ndarray | None = None

    def __call__(self, obs: dict) -> np.ndarray:
        if self._plan is None:
            raise RuntimeError("call expert.reset(env, seed) before asking for actions")
        action = next(self._plan, None)
        if action is None:  # plan finished without success: hold still with the gripper open
            action = np.array([0, 0, 0, 0, 0, 0, -1.0])
        self.label = np.clip(action, -1.0, 1.0).astype(np.float32)
        executed, self._executed = (action if self._executed is None else self._executed), None
        if self.config.noise <= 0 or self.phase in PRECISE_PHASES:
            return np.clip(executed, -1.0, 1.0).astype(np.float32)
        executed = executed.copy()
        executed[:6] += self.rng.normal(0.0, self.config.noise, 6)
        return np.clip(executed, -1.0, 1.0).astype(np.float32)

    # ------------------------------------------------------------------------------------------ primitives
    def _state(self) -> dict:
        return self.env.privileged_state()

    def _action(self, state: dict, target: np.ndarray, yaw: float, grip: float) -> np.ndarray:
        err = target - state["ee_pos"]
        trans = np.clip(self.gain * err / TRANS_SCALE, -1.0, 1.0)
        rot = arm.rotvec_from_mat(arm.euler_to_mat([0.0, 0.0, yaw]) @ state["ee_mat"].T)
        norm = np.linalg.norm(rot)
        if norm > ROT_SCALE:
            rot *= ROT_SCALE / norm
        rot = arm.mat_to_euler(arm.mat_from_rotvec(self.gain * rot)) / ROT_SCALE
        return np.concatenate([trans, np.clip(rot, -1.0, 1.0), [grip]])

    def _move(self, phase: str, target: Target, yaw: float, grip: float, tol: float, budget: int = 30,
              done: Callable[[dict], bool] | None = None, aim: Target | None = None,
              abort: Callable[[dict], bool] | None = None) -> Generator[np.ndarray, None, bool]:
        """Drive the tool centre to ``target(state)``; stop within ``tol`` (and ``done``) or after ``budget``.
        With ``aim`` the arm is driven to ``aim(state)`` instead (a deliberate miss) while the yielded labels
        still head for ``target``. Returns True when it stopped because ``abort(state)`` held."""
        self.phase = phase
        trail = []
        for _ in range(budget):
            state = self._state()
            if abort is not None and abort(state):
                return True
            goal = target(state)
            reach = goal if aim is None else aim(state)
            if np.linalg.norm(reach - state["ee_pos"]) < tol and (done is None or done(state)):
                return False
            trail.append(state["ee_pos"])
            if len(trail) > 4 and np.linalg.norm(trail[-1] - trail[-4]) < STALL:
                return False  # blocked (contact, joint limit or servo deadband): waiting would not help
            if aim is not None:
                self._executed = self._action(state, reach, yaw, grip)
            yield self._action(state, goal, yaw, grip)
        return False

    def _hold(self, phase: str, grip: float, steps: int, yaw: float) -> Iterator[np.ndarray]:
        self.phase = phase
        for _ in range(steps):
            state = self._state()
            yield self._action(state, state["ee_pos"], yaw, grip)

    def _grasp_yaw(self, name: str, state: dict, dest: np.ndarray | None = None) -> float:
        """Yaw closing the fingers across one of the object's symmetric axes, chosen nearest to the arm's
        heading at the object and at the destination ``dest`` (xy) so the wrist stays inside its range."""
        obj = state["objects"][name]
        spec = tasks.OBJECTS[name]
        heading = float(np.arctan2(obj["pos"][1], obj["pos"][0]))
        dest_heading = heading if dest is None else float(np.arctan2(dest[1], dest[0]))
        if spec.geom == "sphere":
            return heading
        first = heading + wrap_angle(obj["yaw"] - heading, spec.yaw_symmetry)
        candidates = first + spec.yaw_symmetry * np.arange(-2, 3)
        cost = np.abs(candidates - heading) + np.abs(candidates - dest_heading)
        return float(candidates[int(np.argmin(cost))])

    # ------------------------------------------------------------------------------------------- skills
    def _pick(self, name: str, dest: np.ndarray | None = None) -> Iterator[np.ndarray]:
        """Approach, descend, close and lift; a grasp that does not hold is retried (``config.retries``),
        and the first one is the deliberate miss of a ``miss`` episode."""
        spec = tasks.OBJECTS[name]

        def above(s: dict) -> np.ndarray:
            p = s["objects"][name]["pos"]
            return rise_first(s["ee_pos"], np.array([p[0], p[1], spec.grasp_z + self.approach]))

        def grasp(s: dict) -> np.ndarray:
            p = s["objects"][name]["pos"]
            return np.array([p[0], p[1], spec.grasp_z])

        def off_target(s: dict) -> bool:
            return bool(np.linalg.norm(s["objects"][name]["pos"][:2] - s["ee_pos"][:2]) > OFF_TARGET)

        for attempt in range(self.config.retries + 1):
            yaw = self._grasp_yaw(name, self._state(), dest)
            if attempt == 0 and self._miss is not None:
                yield from self._missed_grasp(above, grasp, self._miss, yaw)
            else:
                for _ in range(REAPPROACHES + 1):
                    yield from self._move("approach", above, yaw, -1.0, tol=0.012)
                    if not (yield from self._move("descend", grasp, yaw, -1.0, tol=0.006, budget=12,
                                                  abort=off_target)):
                        break
                yield from self._hold("close", 1.0, self.config.grip_steps, yaw)
                lift_z = spec.grasp_z + self.lift
                start = self._state()["ee_pos"].copy()
                yield from self._move(
                    "lift", lambda s, start=start, lift_z=lift_z: np.array([start[0], start[1], lift_z]), yaw, 1.0,
                    tol=0.015)
                if self._state()["objects"][name]["grasped"] or attempt == self.config.retries:
                    return
            yield from self._hold("reopen", -1.0, self.config.grip_steps, yaw)
            rise = self._state()["ee_pos"].copy()
            rise[2] = max(rise[2], spec.grasp_z + self.approach)
            yield from self._move("rise", lambda s, rise=rise: rise, yaw, -1.0, tol=0.012, budget=10)

    def _missed_grasp(self, above: Target, grasp: Target, offset: np.ndarray, yaw: float) -> Iterator[np.ndarray]:
        """Executed: approach, descend and close ``offset`` away from the object. Labelled: the clean
        approach and descent onto it, gripper open (closing there is the mistake, not the lesson)."""
        yield from self._move("approach", above, yaw, -1.0, tol=0.012, aim=lambda s: above(s) + offset)
        yield from self._move("descend", grasp, yaw, -1.0, tol=0.006, budget=12, aim=lambda s: grasp(s) + offset)
        self.phase = "close"
        for _ in range(self.config.grip_steps):
            state = self._state()
            self._executed = self._action(state, state["ee_pos"], yaw, 1.0)
            yield self._action(state, grasp(state), yaw, -1.0)

    def _place(self, name: str, xy: Callable[[dict], np.ndarray], rest_z: float,
               miss: np.ndarray | None = None) -> Iterator[np.ndarray]:
        """Carry the held object above ``xy``, lower it until it rests at ``rest_z``, release, retreat. With ``miss``
        the carry is first executed to ``miss`` (m) beside ``xy`` while labelled towards it, then brought back."""
        yaw = float(arm.mat_to_euler(self._state()["ee_mat"])[2])
        carry_z = self._state()["ee_pos"][2]

        def offset(s: dict) -> np.ndarray:  # tool centre minus object centre (the grasp may have slipped)
            return s["ee_pos"] - s["objects"][name]["pos"]

        def carry(s: dict) -> np.ndarray:
            return np.array([*(xy(s) + offset(s)[:2]), carry_z])

        def lower(s: dict) -> np.ndarray:
            return np.array([*(xy(s) + offset(s)[:2]), rest_z + 0.003 + offset(s)[2]])

        if miss is not None:
            yield from self._move("carry", carry, yaw, 1.0, tol=0.008, aim=lambda s: carry(s) + miss)
        yield from self._move("carry", carry, yaw, 1.0, tol=0.008)
        yield from self._move("lower", lower, yaw, 1.0, tol=0.004, budget=20,
                              done=lambda s: s["objects"][name]["pos"][2] < rest_z + 0.006)
        yield from self._hold("release", -1.0, self.config.grip_steps, yaw)
        top = self._state()["ee_pos"] + [0.0, 0.0, 0.06]
        yield from self._move("retreat", lambda s: top, yaw, -1.0, tol=0.01, budget=15)

    def _drawer(self, kind: str) -> Iterator[np.ndarray]:
        """Both drawer tasks with the fingers closed from the first step: a hook behind the handle bar pulls the
        drawer open, the fingers in front of it push it closed. A grasp of the bar would add a gripper decision
        at one instant of the episode, which policies learnt to skip (they hovered at the bar, open)."""
        start = self._state()["handle_pos"].copy()
        closed_x = start[0] + self._state()["drawer"]
        bar_to_tool = HANDLE_HALF_DEPTH + FINGER_HALF_DEPTH  # tool centre to bar centre in x, at contact
        if kind == "drawer_open":
            offset, phase, goal_x = HOOK_BEHIND, "pull", closed_x - DRAWER_PULL + bar_to_tool
        else:
            offset, phase, goal_x = -(bar_to_tool + PUSH_CLEARANCE), "push", closed_x - bar_to_tool + 0.004

        def beside(s: dict) -> np.ndarray:
            return s["handle_pos"] + [offset, 0.0, 0.0]

        yield from self._move("approach", lambda s: beside(s) + [0.0, 0.0, self.approach], 0.0, 1.0, tol=0.01)
        yield from self._move("descend", beside, 0.0, 1.0, tol=0.004, budget=20)
        yield from self._move(phase, lambda s: np.array([goal_x, start[1], start[2]]), 0.0, 1.0, tol=0.004, budget=40)
        top = self._state()["ee_pos"] + [0.0, 0.0, 0.06]
        yield from self._move("retreat", lambda s: top, 0.0, 1.0, tol=0.01, budget=15)

    def _task_plan(self) -> Iterator[np.ndarray]:
        for goal in self.env.task.goals:
            if goal.kind in ("drawer_open", "drawer_close"):
                yield from self._drawer(goal.kind)
            elif goal.kind == "move":
                start = self._state()["initial"][goal.obj][:2]
                target = tasks.move_target(start, goal.direction)
                yield from self._pick(goal.obj, target)
                yield from self._place(goal.obj, lambda s, t=target: t, tasks.OBJECTS[goal.obj].rest_z)
            else:  # stack
                base = tasks.OBJECTS[goal.onto]
                yield from self._pick(goal.obj, self._state()["objects"][goal.onto]["pos"][:2])
                rest = base.rest_z + base.size[2] + tasks.OBJECTS[goal.obj].size[2]
                miss, self._place_miss = self._place_miss, None
                yield from self._place(goal.obj, lambda s, goal=goal: s["objects"][goal.onto]["pos"][:2].copy(), rest,
                                       miss)


def rise_first(ee: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """``goal``, or straight above the tool while it is below ``goal`` and ``OFF_TARGET`` off it horizontally: a
    low tool moving sideways to an object drags it along."""
    if ee[2] < goal[2] - OFF_TARGET and np.linalg.norm(goal[:2] - ee[:2]) > OFF_TARGET:
        return np.array([ee[0], ee[1], goal[2]])
    return goal


def make_expert(noise: float = 0.0, miss: float = 0.0, place_miss: float = 0.0) -> Expert:
    return Expert(ExpertConfig(noise=noise, miss=miss, place_miss=place_miss))
