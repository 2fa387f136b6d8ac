"""Scripted experts with privileged simulator state for LIBERO-Spatial, -Object, -Goal and -10 (Long).

They exist so that demonstrations can be made offline. An expert reads the task's BDDL goal and turns each
of its predicates into a skill (see ``_skills`` and ``_pick``):

- ``(On X Y)`` / ``(In X Y)`` with a movable X: pick X and put it on / in Y (another object, a container,
  or a region of a fixture or of the table: the stove's cook region, the cabinet's top, a drawer, the
  microwave, the caddy's back compartment, the table right of the plate);
- ``(Open drawer)`` / ``(Close drawer)``: grasp the handle bar and pull, or push the bar;
- ``(Close microwave)``: push the door's outer face round its hinge;
- ``(Turnon stove)``: grasp the knob's fin and turn it.

Subgoals run in a fixed order: drawers that must be open first (also the drawer an "In" goal puts
something into), then knobs, then pick-and-place in the BDDL's order, then closing. Before each one the
expert checks LIBERO's own predicates; a subgoal already met is skipped, one still unmet after its skill ran
is tried again (``max_skill_attempts``), and a met one that comes undone (a pot knocked off the stove) is
done again. Motion is closed-loop proportional control of the end effector towards waypoints in LIBERO's
own action space (OSC_POSE deltas, 0.05 m / 0.5 rad at full scale), so recorded actions are what a policy
has to output. Waypoints are kept within the arm's reach.

Variety for demonstrations, as on the simulated twin (``pivla.envs.tabletop.expert``): ``noise > 0`` adds
Gaussian noise to the *executed* motion outside precise phases (going down to a grasp, closing, placing,
pulling a drawer...), while the recorded label (``actor.label``) stays the clean action for the state
reached, so a policy learns to correct drift (DART, Laskey et al. 2017); it also draws per-episode lift and
approach heights and speed. ``miss > 0`` executes, in that share of episodes, the first grasp a few
centimetres beside the object and closes on nothing, labelled as the clean approach with the gripper open;
the reopening and second grasp that follow are recorded as they are, so the policy sees the recovery.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pivla.envs import select_tasks
from pivla.envs.libero._backend import libero
from pivla.envs.libero._geometry import (
    ARM_REACH,
    POS_SCALE,
    ROT_SCALE,
    Scene,
    rotation_error,
    within_reach,
    wrist_distance,
)
from pivla.envs.libero._pick import PickPlace, Target, miss_direction
from pivla.envs.libero._skills import Command, Door, Drawer, ExpertConfig, Knob, PlanningError, Push, Skill
from pivla.envs.libero.env import list_tasks, make_env
from pivla.io import exclusive_lock, open_log

__all__ = ["ARM_REACH", "ExpertConfig", "ExpertEvalConfig", "RolloutExpert", "TaskExpert", "expert_actor",
           "expert_success", "run_expert_episode", "within_reach", "wrist_distance"]

log = logging.getLogger(__name__)

EXPERT_FAMILIES = ("libero_spatial", "libero_object", "libero_goal", "libero_10")
IDLE = np.array([0, 0, 0, 0, 0, 0, -1], dtype=np.float64)


# An object this close (m) to where a drawer will be once open is moved aside first: the hand, 20 cm long
# across the fingers, and the wrist above it could not get at it under the drawer.
DRAWER_ROOM = 0.07


@dataclass
class _Subgoal:
    holds: Callable[[], bool]  # whether it is done (a BDDL predicate, mostly)
    make: Callable[[], Skill]
    target: str | None = None  # pick-and-place: the target's name
    tries: int = 0
    deferred: bool = False  # its skill ran to the end without meeting it


class TaskExpert:
    """Scripted expert for one LIBERO task; call it as ``expert(env, obs) -> action`` (``env`` from
    ``make_env("libero", ...)``, rendering on or off; ``obs`` is unused: the expert reads privileged state).

    It sets itself up whenever it sees a new episode (``env.episode_id`` changes); ``reset(seed)`` seeds the
    episode's variety (noise, a missed grasp), which is off by default. ``label`` is the clean action of the
    last call (what a demonstration records); the returned action is what is executed.
    """

    source = "expert"

    def __init__(self, config: ExpertConfig = ExpertConfig()) -> None:  # noqa: B008 - frozen dataclass, safe to share
        self.base_config = config
        self.config = config
        self._episode: int | None = None
        self._seed: int | None = None
        self.label: np.ndarray | None = None
        self.skill: Skill | None = None

    def reset(self, seed: int | None) -> None:
        """Seed the next episode's variety (noise, missed grasp, jitter)."""
        self._seed = seed

    @property
    def attempts(self) -> int:
        """Grasp attempts of the current pick-and-place (1 when none is running)."""
        return getattr(self.skill, "attempts", 1) or 1

    def _setup(self, env: Any) -> None:
        rs = env.robosuite_env
        self.scene = Scene(rs)
        self._episode = env.episode_id
        seed = self._seed if self._seed is not None else (env.init_state or env.init_seed or 0)
        self._seed = None
        self.rng = np.random.default_rng(seed)
        cfg = self.base_config
        if cfg.noise > 0:  # per-episode heights and speed, as the twin's expert draws them
            j = self.rng.uniform(-1.0, 1.0, 3)
            cfg = dataclasses.replace(cfg, lift_clearance=cfg.lift_clearance + 0.015 * j[0],
                                      approach_above=cfg.approach_above + 0.01 * j[1],
                                      pos_gain=cfg.pos_gain * (1.0 + 0.1 * j[2]))
        self.config = cfg
        self.missing = cfg.miss > 0 and self.rng.uniform() < cfg.miss
        self.subgoals = self._subgoals(rs)
        self.skill = None
        self.current: _Subgoal | None = None

    def _subgoals(self, rs: Any) -> list[_Subgoal]:
        goal = [[g[0].lower(), *g[1:]] for g in rs.parsed_problem["goal_state"]]
        opens: list[_Subgoal] = []
        knobs: list[_Subgoal] = []
        places: list[_Subgoal] = []
        closes: list[_Subgoal] = []
        targets = [g[2] for g in goal if g[0] in ("on", "in")]
        for g in goal:
            kind, holds = g[0], self._predicate(g)
            if kind in ("on", "in") and g[1] in rs.objects_dict:
                target = g[2]
                share = (sum(1 for p in places if p.target == target), targets.count(target))
                places.append(_Subgoal(holds, self._pick_maker(g, share), target))
                if kind == "in" and self._slide_joint(rs, target) and not any(s.target == target for s in opens):
                    opened = self._predicate(["open", target])
                    drawer = Drawer(self.scene, self.config, self._slide_joint(rs, target), True)
                    lo, hi = drawer.open_footprint(DRAWER_ROOM)
                    o_lo, o_hi = self.scene.aabb(self.scene.entity_root(g[1]))
                    if not opened() and np.all(o_hi[:2] > lo) and np.all(o_lo[:2] < hi):
                        opens.append(_Subgoal(lambda o=opened, n=g[1], lo=lo, hi=hi: o() or self._clear(n, lo, hi),
                                              self._aside_maker(g[1], lo, hi)))
                    opens.append(_Subgoal(opened, self._drawer_maker(target, True), target))
            elif kind == "open" and self._slide_joint(rs, g[1]):
                opens.append(_Subgoal(holds, self._drawer_maker(g[1], True), g[1]))
            elif kind == "close" and self._slide_joint(rs, g[1]):
                closes.append(_Subgoal(holds, self._drawer_maker(g[1], False)))
            elif kind == "close" and self._hinge_joint(rs, g[1]):
                closes.append(_Subgoal(holds, self._door_maker(holds, g[1])))
            elif kind == "turnon" and self._hinge_joint(rs, g[1]):
                knobs.append(_Subgoal(holds, self._knob_maker(g[1])))
            else:
                raise ValueError(f"the scripted expert has no skill for the goal predicate {g}")
        return opens + knobs + places + closes

    def _predicate(self, predicate: list[str]) -> Callable[[], bool]:
        return lambda: self.scene.holds(predicate)

    def _clear(self, name: str, lo: np.ndarray, hi: np.ndarray) -> bool:
        """Whether object ``name``'s footprint misses the xy box ``lo``-``hi``."""
        o_lo, o_hi = self.scene.aabb(self.scene.entity_root(name))
        return bool(np.any(o_hi[:2] <= lo) or np.any(o_lo[:2] >= hi))

    # ---- skill factories (built when their subgoal starts: the scene may have changed by then) ----------

    def _pick_maker(self, goal: list[str], share: tuple[int, int]) -> Callable[[], Skill]:
        def make() -> Skill:
            miss = None
            if self.missing:  # only the episode's first grasp is missed
                self.missing = False
                dist = self.rng.uniform(*self.config.miss_offset)
                miss = miss_direction(self.scene, self.scene.entity_root(goal[1]), self.rng, dist)
            return PickPlace(self.scene, self.config, goal[1], Target(self.scene, goal[2], goal), share, miss)
        return make

    def _aside_maker(self, name: str, lo: np.ndarray, hi: np.ndarray) -> Callable[[], Skill]:
        """Push the object to the nearest free spot on the table out of the box ``lo``-``hi``."""
        def make() -> Skill:
            obj = self.scene.entity_root(name)
            planner = PickPlace(self.scene, self.config, name, Target.clear_of(self.scene, obj, lo, hi))
            spot = planner._plan_spot()
            o_lo, o_hi = self.scene.aabb(obj)
            centre_from_origin = (o_lo[:2] + o_hi[:2]) / 2 - self.scene.d.xpos[obj][:2]
            return Push(self.scene, self.config, obj, spot.origin[:2] + centre_from_origin)
        return make

    def _drawer_maker(self, region: str, opening: bool) -> Callable[[], Skill]:
        joint = self.scene.rs.object_sites_dict[region].joints[0]
        return lambda: Drawer(self.scene, self.config, joint, opening)

    def _door_maker(self, closed: Callable[[], bool], name: str) -> Callable[[], Skill]:
        joint = self._hinge_joint(self.scene.rs, name)
        return lambda: Door(self.scene, self.config, joint, closed)

    def _knob_maker(self, name: str) -> Callable[[], Skill]:
        joint = self._hinge_joint(self.scene.rs, name)
        return lambda: Knob(self.scene, self.config, joint)

    @staticmethod
    def _slide_joint(rs: Any, name: str) -> str | None:
        """The slide joint of a drawer region (a site with joints), or None."""
        site = rs.object_sites_dict.get(name)
        joints = getattr(site, "joints", None) or []
        m = rs.sim.model
        return next((j for j in joints if m.jnt_type[m.joint_name2id(j)] == 2), None)

    @staticmethod
    def _hinge_joint(rs: Any, name: str) -> str | None:
        """The hinge joint of an articulated object (the microwave's door, the stove's knob), or None."""
        entity = rs.objects_dict.get(name) or rs.fixtures_dict.get(name)
        m = rs.sim.model
        for j in getattr(entity, "joints", None) or []:
            if j in m.joint_names and m.jnt_type[m.joint_name2id(j)] == 3:
                return j
        return None

    # ---- acting ----------------------------------------------------------------------------------------

    def __call__(self, env: Any, obs: dict | None = None) -> np.ndarray:
        raw = env.raw_obs
        if self._episode != env.episode_id:
            self._setup(env)
        ee = np.asarray(raw["robot0_eef_pos"], dtype=np.float64)
        rot = libero().T.quat2mat(raw["robot0_eef_quat"])
        command = self._command(ee, rot)
        self._last_cmd = command
        if command is None:
            self.label = IDLE.astype(np.float32)
            return IDLE.copy()
        label = self._action(command.goal, command.rot, command.grip, ee, rot)
        executed = label
        if command.aim is not None or command.aim_grip is not None:
            goal = command.aim if command.aim is not None else command.goal
            grip = command.aim_grip if command.aim_grip is not None else command.grip
            executed = self._action(goal, command.rot, grip, ee, rot)
        if self.config.noise > 0 and not self.skill.precise:
            executed = executed.copy()
            executed[:6] += self.rng.normal(0.0, self.config.noise, 6)
        self.label = np.clip(label, -1.0, 1.0).astype(np.float32)
        return np.clip(executed, -1.0, 1.0)

    def _command(self, ee: np.ndarray, rot: np.ndarray) -> Command | None:
        """The current skill's command, starting the next unmet subgoal whenever a skill has finished."""
        for _ in range(2 * len(self.subgoals) * self.config.max_skill_attempts + 1):
            if self.skill is None:
                # The first unmet subgoal in plan order, except that one whose skill ran to its end without
                # meeting it waits for the others (a door closing may push in the mug left at the microwave's
                # edge); a skill that found no way to start does not hold the others up.
                pending = [s for s in self.subgoals if not s.holds() and s.tries < self.config.max_skill_attempts]
                nxt = next((s for s in pending if not s.deferred), pending[0] if pending else None)
                if nxt is None:
                    return None
                nxt.tries += 1
                try:
                    self.current, self.skill = nxt, nxt.make()
                    command = self.skill.step(ee, rot)
                except PlanningError as e:
                    log.debug("subgoal given up for now: %s", e)
                    command = None
            else:
                try:
                    command = self.skill.step(ee, rot)
                except PlanningError as e:
                    log.debug("subgoal given up for now: %s", e)
                    command = None
            if command is not None:
                return command
            if self.skill is not None and self.skill.phase_name == "done" and not self.current.holds():
                self.current.deferred = True
            self.skill = None
        return None

    def _action(self, goal: np.ndarray | None, target_rot: np.ndarray | None, grip: float, ee: np.ndarray,
                rot: np.ndarray) -> np.ndarray:
        """Proportional control towards ``goal`` (None: hold still), saturated along the line to it (so the
        path is straight), and towards ``target_rot``."""
        cfg = self.config
        if goal is None:
            return np.array([0, 0, 0, 0, 0, 0, grip], dtype=np.float64)
        pos_a = cfg.pos_gain * (goal - ee) / POS_SCALE
        pos_a *= min(1.0, cfg.max_pos_action / max(float(np.abs(pos_a).max()), 1e-9))
        rot_a = np.zeros(3) if target_rot is None else np.clip(cfg.rot_gain * rotation_error(target_rot, rot)
                                                               / ROT_SCALE, -1.0, 1.0)
        return np.array([*pos_a, *rot_a, grip], dtype=np.float64)


def _check_suite(suite: str) -> None:
    if not suite.startswith(EXPERT_FAMILIES):
        raise ValueError(f"scripted experts exist for the {', '.join(EXPERT_FAMILIES)} suites (and their "
                         f"LIBERO-PRO variants with the same goals), not {suite!r}")


def expert_actor(suite: str, task: int | str,
                 config: ExpertConfig = ExpertConfig()) -> TaskExpert:  # noqa: B008 - frozen dataclass, safe to share
    """A scripted expert for one task of LIBERO-Spatial / -Object / -Goal / -10 (or their LIBERO-PRO variants).

    Returns ``actor(env, obs) -> action`` (a :class:`TaskExpert`); ``env`` is the ``LiberoEnv`` from
    ``make_env("libero", ...)`` (rendering may be off).
    """
    _check_suite(suite)
    names = [t.name for t in list_tasks(suite)]
    if isinstance(task, str) and task not in names:
        raise ValueError(f"unknown task {task!r} in suite {suite!r}")
    if isinstance(task, int) and not 0 <= task < len(names):
        raise ValueError(f"task index {task} out of range: suite {suite!r} has {len(names)} tasks")
    return TaskExpert(config)


class RolloutExpert:
    """A task's expert behind ``pivla.envs.rollout``'s ``actor(obs)`` interface: ``reset(env, seed)``, called
    after every ``env.reset``, binds the env whose privileged state the expert reads and seeds the episode's
    variety; ``label`` is the clean action to record (it differs from the executed one with noise or a miss)."""

    source = "expert"

    def __init__(self, suite: str, task: int | str,
                 config: ExpertConfig = ExpertConfig()) -> None:  # noqa: B008 - frozen dataclass, safe to share
        self.expert = expert_actor(suite, task, config)
        self.env: Any = None

    def reset(self, env: Any, seed: int) -> None:
        self.env = env
        self.expert.reset(seed)

    @property
    def label(self) -> np.ndarray | None:
        return self.expert.label

    def __call__(self, obs: dict) -> np.ndarray:
        if self.env is None:
            raise RuntimeError("RolloutExpert: call reset(env, seed) after env.reset() first")
        return self.expert(self.env, obs)


def run_expert_episode(env: Any, actor: Callable[[Any, dict | None], np.ndarray], init_state: int | None = None,
                       seed: int | None = None) -> dict:
    """Roll out the expert from official init state ``init_state``, or (``init_state`` None) from the scene
    sampled with ``seed``; returns success, steps and grasp attempts."""
    if init_state is not None:
        obs, info = env.reset(seed=init_state, options={"init_state": init_state})
    elif seed is not None:
        obs, info = env.reset(seed=seed, options={"init": "random", "seed": seed})
    else:
        raise ValueError("run_expert_episode needs an init_state or a seed")
    if hasattr(actor, "reset"):
        actor.reset(seed if init_state is None else init_state)
    success, steps = bool(info["success"]), 0
    while not success:
        obs, _, terminated, truncated, info = env.step(actor(env, obs))
        steps += 1
        success = bool(info["success"])
        if terminated or truncated:
            break
    return {"init_state": init_state, "seed": seed, "success": success, "steps": steps,
            "attempts": getattr(actor, "attempts", 1)}


def _parse_indices(text: str) -> list[int]:
    """"0-49" / "0,5,7" / "3" -> indices."""
    out: list[int] = []
    for part in (p.strip() for p in text.split(",") if p.strip()):
        lo, _, hi = part.partition("-")
        if not lo.isdigit() or (hi and not hi.isdigit()):
            raise ValueError(f"bad index list {text!r}: use e.g. '0-49' or '0,5,7'")
        out.extend(range(int(lo), int(hi) + 1) if hi else [int(lo)])
    return out


@dataclass
class ExpertEvalConfig:
    """Success of the scripted experts, per task, without rendering."""

    suite: str
    """libero_spatial, libero_object, libero_goal, libero_10 (or a LIBERO-PRO variant of them)."""
    tasks: str | None = None
    """Task indices or names, comma-separated (default: all)."""
    init_states: str = "0-49"
    """Official init states, e.g. "0-49" or "0,7,9"."""
    seeds: str | None = None
    """Sampled scenes with these seeds (e.g. "0-9") instead of official init states."""
    out: str | None = None
    """JSONL file of per-episode results: appended as episodes finish; episodes already in it are skipped."""
    noise: float = 0.0
    """DART noise on executed actions (the expert's config)."""
    miss: float = 0.0
    """Share of episodes whose first grasp is missed on purpose."""
    max_steps: int | None = None
    """Step limit per episode (default: the suite's; `pivla libero run` collects at 1.5 times it)."""


def _episode_key(suite: str, task: int, seed: int | None, init_state: int | None, noise: float,
                 miss: float, max_steps: int | None) -> tuple:
    """What identifies an episode of ``expert_success`` (a sampled scene's seed, or an official init state)."""
    start = ("seed", int(seed)) if seed is not None else ("init", int(init_state))
    return suite, int(task), *start, float(noise), float(miss), max_steps


def _row_key(row: dict) -> tuple:
    return _episode_key(row["suite"], row["task"], row.get("seed"), row.get("init_state"), row.get("noise", 0.0),
                        row.get("miss", 0.0), row.get("max_steps"))


def _read_rows(path: Path) -> dict[tuple, dict]:
    rows: dict[tuple, dict] = {}
    if path.exists():
        for line in path.read_text().splitlines():
            try:
                row = json.loads(line)
            except json.JSONDecodeError:
                log.warning("%s: skipping a truncated line (interrupted write)", path)
                continue
            rows[_row_key(row)] = row
    return rows


def expert_success(cfg: ExpertEvalConfig, progress: Callable[[dict], None] | None = None) -> dict:
    """Per-task expert success over the given init states (or sampled scenes), one env at a time and no
    rendering; resumable through ``cfg.out`` (a JSONL file, appended as episodes finish). Returns
    ``{"suite", "tasks": [{task, name, successes, episodes, mean_steps, failed}], "successes", "episodes"}``
    over the episodes asked for; ``progress`` is called with each new row."""
    _check_suite(cfg.suite)
    specs = select_tasks("libero", cfg.suite, cfg.tasks)
    seeds = _parse_indices(cfg.seeds) if cfg.seeds else None
    starts = seeds if seeds is not None else _parse_indices(cfg.init_states)

    def key(task: int, start: int) -> tuple:
        seed, init_state = (start, None) if seeds is not None else (None, start)
        return _episode_key(cfg.suite, task, seed, init_state, cfg.noise, cfg.miss, cfg.max_steps)

    path = Path(cfg.out) if cfg.out else None
    rows = _read_rows(path) if path is not None else {}
    config = ExpertConfig(noise=cfg.noise, miss=cfg.miss)
    todo = {spec.index: [s for s in starts if key(spec.index, s) not in rows] for spec in specs}
    with contextlib.ExitStack() as stack:
        logf = None
        if path is not None and any(todo.values()):
            path.parent.mkdir(parents=True, exist_ok=True)
            # one writer per file: a second run would repeat the first one's episodes
            stack.enter_context(exclusive_lock(path, "expert run"))
            logf = stack.enter_context(open_log(path))
        for spec in specs:
            if not todo[spec.index]:
                continue
            env = make_env(cfg.suite, spec.index, render=False, max_steps=cfg.max_steps)
            try:
                actor = expert_actor(cfg.suite, spec.index, config)
                for start in todo[spec.index]:
                    t0 = time.perf_counter()
                    if seeds is None:
                        result = run_expert_episode(env, actor, init_state=start)
                    else:
                        result = run_expert_episode(env, actor, seed=start)
                    row = {"suite": cfg.suite, "task": spec.index, "name": spec.name, **result,
                           "noise": cfg.noise, "miss": cfg.miss, "max_steps": cfg.max_steps,
                           "seconds": round(time.perf_counter() - t0, 1)}
                    rows[key(spec.index, start)] = row
                    if logf is not None:
                        logf.write(json.dumps(row) + "\n")
                        logf.flush()
                    if progress is not None:
                        progress(row)
            finally:
                env.close()
    table = []
    for spec in specs:
        done = {s: rows[key(spec.index, s)] for s in starts if key(spec.index, s) in rows}
        table.append({"task": spec.index, "name": spec.name, "successes": sum(e["success"] for e in done.values()),
                      "episodes": len(done),
                      "mean_steps": float(np.mean([e["steps"] for e in done.values()])) if done else 0.0,
                      "failed": [s for s, e in done.items() if not e["success"]]})
    return {"suite": cfg.suite, "tasks": table, "successes": sum(t["successes"] for t in table),
            "episodes": sum(t["episodes"] for t in table)}
