"""The SO-101 twin's scripted expert: Cartesian waypoints from privileged state, turned into the policy's own
action (six absolute joint positions, LeRobot units) by damped-least-squares IK on MuJoCo's Jacobians.

A task is a sequence of phases (approach above the cube, descend, close, lift, carry above the target, lower,
release, retreat). Every step a phase recomputes its goal for the tool point (between the fingertip pads) from
the live state, moves a waypoint from the *measured* tool point towards it at a capped speed, solves the IK for
the waypoint with the jaws pointing down and across the cube's faces, and raises each joint's goal by its
gravity sag (``SO101TwinEnv.hold_command``), so that the arm comes to rest where the IK put it on the twin's
compliant servos. A phase ends within tolerance or after a step budget, and ends early when the tool stalls, so
a slipped grasp shows up as a failed episode, never as a hang; a grasp that does not hold is retried.

``noise > 0`` (DART, as the tabletop expert): Gaussian noise of that many degrees perturbs the *executed* body-
joint goals while the recorded label (``expert.label``) stays the clean command for the state reached; phases
that end on a millimetre tolerance (lower, close, release) run without it. ``miss > 0``: in that share of
episodes the first grasp is executed a few centimetres off the cube and closed on nothing, with clean labels,
and the reopening and second approach are recorded as they are. A per-episode draw of carry height, approach
height and speed adds variety when ``noise > 0``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from pivla.arm.rotations import wrap_angle
from pivla.envs.so101 import tasks
from pivla.envs.so101.env import CONTROL_HZ, SO101TwinEnv
from pivla.envs.so101.model import BODY_JOINTS
from pivla.envs.twin import check_misses, draw_miss

Target = Callable[[dict], np.ndarray]
STALL = 0.0015  # m over three steps: a phase whose tool point moves less than this has stalled
LEASH = 0.03  # m: how far the reference tool point may run ahead of the measured one
ROLL_MARGIN = np.radians(10.0)  # a grasp keeps wrist_roll this far inside its range
PRECISE_PHASES = frozenset({"lower", "close", "release"})  # no DART noise while these run
GRASP_Z = tasks.CUBE_HALF + 0.002  # tool point height of a grasp: the pads just above the cube's middle


@dataclass(frozen=True)
class ExpertConfig:
    noise: float = 0.0  # std (deg) of Gaussian noise on the executed body-joint goals; labels stay clean
    speed: float = 0.15  # m/s of the tool point in free moves
    slow: float = 0.06  # m/s while descending onto, lifting and lowering the cube
    gain: float = 0.8  # share of the remaining distance a waypoint covers (below the speed cap)
    carry: float = 0.07  # tool point height while carrying (m)
    approach: float = 0.045  # height above the grasp point before descending (m)
    grip_open: float = 40.0  # gripper.pos with the jaws open around a 25 mm cube (pads ~48 mm apart)
    grip_closed: float = 0.0  # gripper.pos commanded to hold (the servo squeezes the cube at its torque cap)
    grip_steps: int = 4  # control steps to close or open the gripper
    # steps recorded after success, so that a demonstration shows the arm letting go and moving off
    follow_through: int = 5
    retries: int = 2  # further grasps after one that did not hold
    miss: float = 0.0  # share of episodes whose first grasp is executed off the cube (labels stay clean)
    miss_offset: tuple[float, float] = (0.025, 0.04)  # m, horizontal distance of a missed grasp from the cube


class Expert:
    """Callable actor: ``expert.reset(env, seed)`` once per episode, then ``action = expert(obs)``."""

    source = "expert"

    def __init__(self, config: ExpertConfig | None = None):
        self.config = config or ExpertConfig()
        check_misses(self.config.miss, self.config.retries)
        if self.config.noise < 0:
            raise ValueError(f"noise must be >= 0 (degrees), got {self.config.noise}")
        self.env: SO101TwinEnv | None = None
        self._plan: Iterator[np.ndarray] | None = None
        self.phase = ""

    @property
    def follow_through(self) -> int:
        """Steps the rollout runner records after success (see ``ExpertConfig.follow_through``)."""
        return self.config.follow_through

    def reset(self, env, seed: int | None = None) -> None:
        self.env = env.unwrapped
        if not isinstance(self.env, SO101TwinEnv):
            raise TypeError("the SO-101 expert needs an so101 twin env (it reads privileged simulator state)")
        self.rng = np.random.default_rng(seed)
        cfg = self.config
        jitter = self.rng.uniform(-1.0, 1.0, 3) if cfg.noise > 0 else np.zeros(3)
        self.carry = cfg.carry + 0.008 * jitter[0]
        self.approach = cfg.approach + 0.01 * jitter[1]
        self.speed = cfg.speed * (1.0 + 0.15 * jitter[2])
        self._miss = draw_miss(self.rng, cfg.miss, cfg.miss_offset)
        state = self._state()
        self._q = state["q"][:5].copy()  # IK seed: the last solution
        self._ref = state["tcp"].copy()  # the reference tool point (see _command)
        self._grip = float(self.env.command[-1])
        self._yaw: float | None = None  # jaw-axis yaw relative to the arm's heading (see _command); None: free
        self._plan = self._task_plan()
        self._executed: np.ndarray | None = None
        self.label: np.ndarray | None = None

    def __call__(self, obs: dict) -> np.ndarray:
        if self._plan is None:
            raise RuntimeError("call expert.reset(env, seed) before asking for actions")
        action = next(self._plan, None)
        if action is None:  # plan finished without success: hold still
            action = self._command(self._state(), self._ref, self._grip)
        env = self.env
        self.label = np.clip(action, env.lower, env.upper).astype(np.float32)
        executed, self._executed = (action if self._executed is None else self._executed), None
        executed = np.array(executed, dtype=np.float64)
        if self.config.noise > 0 and self.phase not in PRECISE_PHASES:
            executed[: len(BODY_JOINTS)] += self.rng.normal(0.0, self.config.noise, len(BODY_JOINTS))
        return np.clip(executed, env.lower, env.upper).astype(np.float32)

    # ------------------------------------------------------------------------------------------ primitives
    def _state(self) -> dict:
        return self.env.privileged_state()

    def _command(self, state: dict, goal: np.ndarray, grip: float, speed: float | None = None) -> np.ndarray:
        """The joint command that moves the reference tool point one control step towards ``goal``.

        The jaws keep their yaw relative to the arm's heading (``self._yaw``), so the wrist does not counter-turn
        while the arm pans towards the cube. The reference is where the expert wants the tool point now, not
        where it is: the compliant servos trail a
        moving goal by one to three control steps, and stepping from the measured point each step would chase
        that lag into an oscillation. A reference left more than ``LEASH`` behind by a blocked or pushed arm is
        pulled back towards the measured tool point."""
        ref = self._ref
        lag = ref - state["tcp"]
        if np.linalg.norm(lag) > LEASH:
            ref = state["tcp"] + lag * (LEASH / np.linalg.norm(lag))
        step = self.config.gain * (np.asarray(goal, float) - ref)
        cap = (self.speed if speed is None else speed) / CONTROL_HZ
        norm = np.linalg.norm(step)
        if norm > cap:
            step *= cap / norm
        self._ref = ref + step
        kin = self.env.kin
        yaw = None if self._yaw is None else kin.heading(self._ref) + self._yaw
        q = kin.solve(self._ref, yaw, self._q)
        self._q = q
        self._grip = grip
        return self.env.hold_command(np.array([*np.degrees(q), grip]))

    def _move(self, phase: str, target: Target, grip: float, tol: float, budget: int = 40, slow: bool = False,
              done: Callable[[dict], bool] | None = None, aim: Target | None = None) -> Iterator[np.ndarray]:
        """Drive the tool point to ``target(state)``; stop within ``tol`` (and ``done``) or after ``budget``, or
        when the tool point has come to rest short of it (blocked by a contact, a joint limit or the servos'
        dead zone: waiting would not help). With ``aim`` the arm is driven to ``aim(state)`` instead (a
        deliberate miss) while the yielded labels still head for ``target``."""
        self.phase = phase
        speed = self.config.slow if slow else None
        trail = []
        for _ in range(budget):
            state = self._state()
            goal = target(state)
            reach = goal if aim is None else aim(state)
            if np.linalg.norm(reach - state["tcp"]) < tol and (done is None or done(state)):
                return
            trail.append(state["tcp"])
            if (len(trail) > 4 and np.linalg.norm(trail[-1] - trail[-4]) < STALL
                    and np.linalg.norm(self._ref - reach) < tol):
                return
            if aim is not None:
                saved = self._q.copy(), self._ref.copy()
                self._executed = self._command(state, reach, grip, speed)
                executed_ref = self._ref
                self._q, self._ref = saved
                label = self._command(state, goal, grip, speed)
                self._ref = executed_ref  # the arm follows the executed reference
                yield label
            else:
                yield self._command(state, goal, grip, speed)

    def _hold(self, phase: str, grip: float, steps: int) -> Iterator[np.ndarray]:
        self.phase = phase
        for _ in range(steps):
            yield self._command(self._state(), self._ref, grip)

    def _grasp_yaw(self, name: str, state: dict) -> float:
        """Jaw-axis yaw, relative to the arm's heading at the cube, that closes the jaws across two faces of the
        cube: of the four, the one whose IK solution above the cube turns the wrist least from where it is, among
        those the arm reaches with the jaws down and the wrist clear of its roll limits."""
        cube = state["objects"][name]
        above = np.array([cube["pos"][0], cube["pos"][1], GRASP_Z + self.approach])
        kin = self.env.kin
        heading = kin.heading(above)
        roll_lo, roll_hi = kin.lower[4] + ROLL_MARGIN, kin.upper[4] - ROLL_MARGIN
        options = []
        for k in range(4):
            yaw = wrap_angle(cube["yaw"] + k * np.pi / 2, 2 * np.pi)
            q = kin.solve(above, yaw, self._q)
            pos_err, tilt = kin.errors(q, above, yaw)
            reached = pos_err < 0.003 and tilt < 0.1 and roll_lo <= q[4] <= roll_hi
            options.append((not reached, abs(q[4] - self._q[4]), wrap_angle(yaw - heading, 2 * np.pi)))
        return min(options)[2]

    # ------------------------------------------------------------------------------------------- skills
    def _pick(self, name: str) -> Iterator[np.ndarray]:
        """Approach, descend, close and lift; a grasp that does not hold is retried (``config.retries``), and
        the first one is the deliberate miss of a ``miss`` episode."""
        cfg = self.config

        def above(s: dict) -> np.ndarray:
            p = s["objects"][name]["pos"]
            return np.array([p[0], p[1], GRASP_Z + self.approach])

        def grasp(s: dict) -> np.ndarray:
            p = s["objects"][name]["pos"]
            return np.array([p[0], p[1], GRASP_Z])

        for attempt in range(cfg.retries + 1):
            self._yaw = self._grasp_yaw(name, self._state())
            if attempt == 0 and self._miss is not None:
                yield from self._missed_grasp(above, grasp, self._miss)
            else:
                yield from self._move("approach", above, cfg.grip_open, tol=0.008)
                yield from self._move("descend", grasp, cfg.grip_open, tol=0.004, budget=15, slow=True)
                yield from self._hold("close", cfg.grip_closed, cfg.grip_steps)
                start = self._state()["tcp"].copy()
                yield from self._move("lift", lambda s, start=start: np.array([start[0], start[1], self.carry]),
                                      cfg.grip_closed, tol=0.01, budget=15, slow=True)
                if self._state()["objects"][name]["grasped"] or attempt == cfg.retries:
                    return
            yield from self._hold("reopen", cfg.grip_open, cfg.grip_steps)
            rise = self._state()["tcp"].copy()
            rise[2] = max(rise[2], GRASP_Z + self.approach)
            yield from self._move("rise", lambda s, rise=rise: rise, cfg.grip_open, tol=0.01, budget=10)

    def _missed_grasp(self, above: Target, grasp: Target, offset: np.ndarray) -> Iterator[np.ndarray]:
        """Executed: approach, descend and close ``offset`` away from the cube. Labelled: the clean approach
        and descent onto it, gripper open (closing there is the mistake, not the lesson)."""
        cfg = self.config
        yield from self._move("approach", above, cfg.grip_open, tol=0.008, aim=lambda s: above(s) + offset)
        yield from self._move("descend", grasp, cfg.grip_open, tol=0.004, budget=15, slow=True,
                              aim=lambda s: grasp(s) + offset)
        self.phase = "close"
        for _ in range(cfg.grip_steps):
            state = self._state()
            saved = self._q.copy(), self._ref.copy()
            self._executed = self._command(state, self._ref, cfg.grip_closed)
            executed_ref = self._ref
            self._q, self._ref = saved
            label = self._command(state, grasp(state), cfg.grip_open)
            self._ref = executed_ref
            yield label

    def _place(self, name: str) -> Iterator[np.ndarray]:
        """Carry the held cube above the target, lower it until it rests there, release, retreat."""
        cfg, env = self.config, self.env
        target_xy = np.array(env.layout["target"])
        rest = tasks.place_height(env.task.target)

        def offset(s: dict) -> np.ndarray:  # tool point minus cube centre (the grasp may have slipped)
            return s["tcp"] - s["objects"][name]["pos"]

        def carry(s: dict) -> np.ndarray:
            return np.array([*(target_xy + offset(s)[:2]), self.carry])

        def lower(s: dict) -> np.ndarray:
            return np.array([*(target_xy + offset(s)[:2]), rest + 0.004 + offset(s)[2]])

        yield from self._move("carry", carry, cfg.grip_closed, tol=0.008, budget=40)
        yield from self._move("lower", lower, cfg.grip_closed, tol=0.004, budget=20, slow=True,
                              done=lambda s: s["objects"][name]["pos"][2] < rest + 0.006)
        yield from self._hold("release", cfg.grip_open, cfg.grip_steps)
        top = self._state()["tcp"] + [0.0, 0.0, 0.04]
        yield from self._move("retreat", lambda s: top, cfg.grip_open, tol=0.01, budget=15)

    def _task_plan(self) -> Iterator[np.ndarray]:
        yield from self._pick(self.env.task.cube)
        yield from self._place(self.env.task.cube)


def make_expert(noise: float = 0.0, miss: float = 0.0) -> Expert:
    return Expert(ExpertConfig(noise=noise, miss=miss))
