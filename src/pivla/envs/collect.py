"""Scripted-expert demonstrations into a LIBERO-layout dataset (one HDF5 file per task), on the simulated twin
or on LIBERO itself. ``pivla collect`` and ``pivla demo`` call :func:`collect_demos`.

Failed expert episodes are replaced by the next seeds of the same task, so a task's file holds its first N
successful seeds in seed order: it depends on the seed only, never on the number of worker processes, and the
first n episodes of an N-episode file are the n-episode collection. Each task's file is written as soon as
that task is complete.
"""

from __future__ import annotations

import collections
import contextlib
import functools
import logging
import multiprocessing as mp
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import tyro

from pivla.data.action_space import EE_DELTA, ActionSpace
from pivla.data.episode import Episode
from pivla.data.hdf5 import read_episodes, write_episodes
from pivla.envs import TaskSpec, make_env, seeds, select_tasks
from pivla.envs.backend import BackendConfig, check_backend
from pivla.envs.libero import expert_actor
from pivla.envs.libero.expert import ExpertConfig, RolloutExpert
from pivla.envs.rollout import episode_seed, iter_jobs, run_episode
from pivla.io import atomic_write_json, exclusive_lock, read_json

log = logging.getLogger(__name__)

DEFAULT_IMAGE_SIZE = {"tabletop": 80, "so101": 80, "libero": 128}


@dataclass
class CollectConfig:
    """Expert demonstrations of a task suite."""

    out: str
    """Output dataset directory."""
    suite: str = "pick_place"
    """tabletop: pick_place, pick_place_seen, pick_place_unseen, drawer, stack, long; so101: pick_place; libero:
    libero_spatial, libero_object, libero_goal, libero_10, ..."""
    env: Literal["tabletop", "so101", "libero"] = "tabletop"
    """The simulated twin of the paper's arm, the SO-101 twin, or LIBERO (privileged-state scripted experts)."""
    tasks: str | None = None
    """Task indices or names, comma-separated (default: all)."""
    episodes: int = 50
    """Successful episodes per task."""
    seed: int = 0
    """Seed of the episodes when no seed family is given."""
    seed_family: Literal["train", "validation"] | None = None
    """Seed attempt k of a task from this family (pivla.envs.seeds, condition in_distribution) instead of --seed:
    demonstrations that share no seed with any validation or test episode, by construction."""
    perturb: str | None = None
    """Twin perturbation spec, e.g. randomized_scene or unseen_env,static_distractors,level=3 (docs/twin.md)."""
    workers: int = 1
    """Worker processes, or Ray actors with --backend ray (results do not depend on it)."""
    dispatch: Annotated[BackendConfig, tyro.conf.arg(name="")] = field(default_factory=BackendConfig)
    """Where the episodes run: --backend local | ray, --ray-address HOST:PORT (docs/cluster.md)."""
    realism: Literal["ideal", "servo"] = "ideal"
    """Twin actuation: ideal, or servo realism (tabletop: hobby-servo backlash, deadband and noise; so101: the
    STS3215's resolution, speed profile, position loop, torque cap and dead zone)."""
    image_size: int | None = None
    """Camera resolution in px (default: tabletop and so101 80, the recipe's; libero 128)."""
    noise: float = 0.0
    """Noise on the expert's executed actions (std, action units: tabletop [-1, 1] deltas, so101 degrees of the
    body joints); labels stay clean (DART)."""
    miss: float = 0.0
    """Share of episodes whose first grasp is executed off the object, so the demonstrations show reopening
    and grasping again (labels stay clean)."""
    place_miss: float = 0.0
    """tabletop: share of ``stack`` episodes whose carry is first executed to a point 2-4 cm beside the block below,
    so the demonstrations show the held block brought back over it before it is set down (labels stay clean). Moves
    are never missed: their target is a point no picture shows."""
    paraphrase: bool = False
    """Draw an instruction paraphrase per episode."""
    keep_failures: bool = False
    """Keep failed expert episodes instead of replacing them with new seeds."""
    libero_mesh_faces: int = 0
    """LIBERO: draw visual meshes of more triangles simplified to about this many (0: robosuite's full meshes),
    about twice the steps/s on a software renderer; recorded in the dataset, evaluate with the same setting."""
    libero_init: Literal["official", "random"] = "random"
    """LIBERO: scenes sampled (seeded) from the task's placement regions, or the official init states 0, 1, ...
    (which the benchmark evaluates on: demonstrations from them train on the test states)."""
    libero_step_factor: float = 1.0
    """LIBERO: the expert's step limit per demonstration, as a multiple of the suite's evaluation limit. DART
    noise and a missed grasp slow the executed motion, not the clean labels a policy learns, so the longest
    tasks' noisy demonstrations need more than the limit a policy is evaluated with."""

    @property
    def size(self) -> int:
        return self.image_size or DEFAULT_IMAGE_SIZE[self.env]


def collect_demos(cfg: CollectConfig) -> int:
    """Collect, write one file per task; returns 0, or 1 when a task got fewer successful episodes than asked."""
    if cfg.episodes < 1:
        raise ValueError("episodes must be >= 1")
    if cfg.libero_step_factor < 1.0:
        raise ValueError(f"libero_step_factor must be >= 1 (the evaluation limit at least), "
                         f"got {cfg.libero_step_factor}")
    check_backend(cfg.dispatch)
    if cfg.env == "libero":
        return _collect_libero(cfg)
    twin = _twin(cfg)
    specs = select_tasks(cfg.env, cfg.suite, cfg.tasks)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    expert = twin.expert
    factories = {
        spec.name: functools.partial(twin.make_env, cfg.suite, spec.name, image_size=cfg.size, realism=cfg.realism,
                                     perturb=twin.perturb, paraphrase=cfg.paraphrase)
        for spec in specs
    }
    task_seeds = {spec.name: episode_seed(cfg.seed, spec.index) for spec in specs}

    def attempt_seed(name: str, k: int) -> int:
        if cfg.seed_family is not None:
            return seeds.seed_for(cfg.seed_family, "in_distribution", name, k)
        return episode_seed(task_seeds[name], k)

    kept: dict[str, list] = {spec.name: [] for spec in specs}
    attempts = dict.fromkeys(kept, 0)
    budget = 3 * cfg.episodes + 10
    status = 0

    def settled(name: str) -> bool:
        """A task is done when it has its episodes or has used up its attempts."""
        return len(kept[name]) >= cfg.episodes or attempts[name] >= budget

    def finish(spec: TaskSpec) -> int:
        """Write one complete (or exhausted) task, as soon as its last episode of the round is in."""
        episodes, n = kept[spec.name], attempts[spec.name]
        if not episodes:
            log.error("%s: the expert failed all %d attempts; nothing written", spec.name, n)
            return 1
        env_meta = {
            "env": cfg.env, "suite": cfg.suite, "task": spec.name, "task_index": spec.index,
            "instruction": spec.instruction, "max_steps": spec.max_steps, "realism": cfg.realism,
            "perturb": twin.perturb, "image_size": cfg.size, **twin.meta,
            "seed": cfg.seed, "seed_family": cfg.seed_family, "noise": cfg.noise, "miss": cfg.miss, "attempts": n,
            **({"place_miss": cfg.place_miss} if cfg.place_miss else {}),
        }
        path = write_episodes(out / f"{spec.name}_demo.hdf5", episodes, env_meta, action_space=twin.action_space)
        rate = (sum(e.success for e in episodes) if cfg.keep_failures else len(episodes)) / n
        log.info("%s: %d episodes (%d steps) -> %s; expert success %.1f%% over %d attempts", spec.name,
                 len(episodes), sum(len(e) for e in episodes), path, 100 * rate, n)
        if len(episodes) < cfg.episodes:
            log.error("%s: only %d of %d successful episodes after %d attempts", spec.name, len(episodes),
                      cfg.episodes, n)
            return 1
        return 0

    pending = list(specs)
    while pending:  # rounds over every unfinished task, in one pool per round
        jobs, owners = [], []
        for spec in pending:
            need = cfg.episodes - len(kept[spec.name])
            jobs += [(factories[spec.name], attempt_seed(spec.name, attempts[spec.name] + i)) for i in range(need)]
            owners += [spec] * need
            attempts[spec.name] += need
        left = collections.Counter(spec.name for spec in owners)
        for spec, ep in zip(owners, iter_jobs(jobs, expert, workers=cfg.workers, desc="collect",
                                              backend=cfg.dispatch)):
            if ep.success or cfg.keep_failures:
                kept[spec.name].append(ep)
            left[spec.name] -= 1
            if not left[spec.name] and settled(spec.name):
                status = max(status, finish(spec))
        pending = [spec for spec in pending if not settled(spec.name)]
    return status


@dataclass(frozen=True)
class _Twin:
    """What collecting on one simulated twin needs: its env factory, its expert, the perturbation spec its envs
    get (canonical), what its datasets record of its control (``control_hz``, the action convention) and the
    action space of its episodes."""

    make_env: Callable[..., Any]
    expert: Any
    perturb: str
    meta: dict
    action_space: ActionSpace


def _twin(cfg: CollectConfig) -> _Twin:
    """The twin's pieces for ``cfg.env`` (tabletop or so101), imported only when it collects: a twin's import sets
    the process's MuJoCo rendering variables."""
    if cfg.env == "so101":
        if cfg.place_miss:
            raise ValueError("place_miss: only the tabletop expert misses a placement on purpose, not so101's")
        from pivla.envs import so101
        from pivla.envs.so101.expert import make_expert as so101_expert

        so101.parse_perturb(cfg.perturb)
        meta = {"control_hz": so101.CONTROL_HZ,
                "action": {"kind": "absolute joint positions", "names": list(so101.ACTION_SPACE.names),
                           "units": "degrees, the gripper 0 (closed) .. 100 (open)"},
                "noise_units": "degrees on the five body joints"}
        return _Twin(so101.make_env, so101_expert(cfg.noise, cfg.miss), "none", meta, so101.ACTION_SPACE)
    from pivla.envs.tabletop import make_env as make_tabletop
    from pivla.envs.tabletop import parse_perturb
    from pivla.envs.tabletop.env import CONTROL_HZ, ROT_SCALE, TRANS_SCALE
    from pivla.envs.tabletop.expert import make_expert

    meta = {"control_hz": CONTROL_HZ, "action": {"translation_m_per_unit": TRANS_SCALE,
                                                 "rotation_rad_per_unit": ROT_SCALE, "gripper": "-1 open, +1 closed"}}
    expert = make_expert(cfg.noise, cfg.miss, cfg.place_miss)
    return _Twin(make_tabletop, expert, parse_perturb(cfg.perturb).spec(), meta, EE_DELTA)


def _collect_libero(cfg: CollectConfig) -> int:
    """LIBERO demonstrations by the privileged-state scripted experts, one file per task; ``workers`` spreads
    whole tasks over processes (each LIBERO process holds ~2 GB)."""
    unsupported = {"perturb (use a LIBERO-PRO suite)": cfg.perturb, "paraphrase (use a *_lan suite)": cfg.paraphrase,
                   "realism servo": cfg.realism != "ideal", "place_miss (the tabletop expert's)": cfg.place_miss,
                   "backend ray (whole tasks run in local processes, --workers)": cfg.dispatch.backend == "ray"}
    given = [flag for flag, value in unsupported.items() if value]
    if given:
        raise ValueError(f"not supported with env libero: {', '.join(given)}")
    specs = select_tasks("libero", cfg.suite, cfg.tasks)
    for spec in specs:
        expert_actor(cfg.suite, spec.index)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    jobs = [(cfg, spec) for spec in specs]
    if cfg.workers > 1 and len(jobs) > 1:
        with mp.get_context("spawn").Pool(min(cfg.workers, len(jobs))) as pool:
            # Each task's file is written as soon as that task finishes, so an interruption keeps it.
            return max([_write_libero_task(cfg, spec, episodes, attempts)
                        for spec, episodes, attempts in pool.imap_unordered(_collect_libero_task, jobs)])
    return max([_write_libero_task(cfg, *_collect_libero_task(job)) for job in jobs])


def _write_libero_task(cfg: CollectConfig, spec: TaskSpec, episodes: list, attempts: int) -> int:
    """Write one task's demonstrations; 0, or 1 when the expert fell short of ``cfg.episodes``."""
    out = Path(cfg.out)
    n_success = sum(e.success for e in episodes)
    if not episodes:
        log.error("%s: the expert failed all %d attempts; nothing written", spec.name, attempts)
        return 1
    env_meta = {
        "env": "libero", "suite": cfg.suite, "task": spec.name, "task_index": spec.index,
        "instruction": spec.instruction, "max_steps": spec.max_steps, "image_size": cfg.size,
        "control_hz": 20, "action": {"space": "OSC_POSE deltas", "translation_m_per_unit": 0.05,
                                     "rotation_rad_per_unit": 0.5, "gripper": "-1 open, +1 closed"},
        "seed": cfg.seed, "attempts": attempts, "expert": "scripted, privileged simulator state",
        "init": cfg.libero_init, "noise": cfg.noise, "miss": cfg.miss, "mesh_faces": cfg.libero_mesh_faces,
        "collect_max_steps": _collect_limit(cfg, spec),
        "init_states": [e.meta["init_state"] for e in episodes],
        "init_seeds": [e.meta["init_seed"] for e in episodes],
    }
    path = write_episodes(out / f"{spec.name}_demo.hdf5", episodes, env_meta)
    partial = _partial_dir(cfg, spec.name)
    shutil.rmtree(partial, ignore_errors=True)
    with contextlib.suppress(OSError):  # gone with the last unfinished task
        partial.parent.rmdir()
    log.info("%s: %d episodes (%d steps) -> %s; expert success %d/%d attempts", spec.name, len(episodes),
             sum(len(e) for e in episodes), path, n_success, attempts)
    if not cfg.keep_failures and len(episodes) < cfg.episodes:
        log.error("%s: only %d of %d successful episodes after %d attempts", spec.name, len(episodes),
                  cfg.episodes, attempts)
        return 1
    return 0


def _partial_dir(cfg: CollectConfig, task_name: str) -> Path:
    """Where an unfinished LIBERO task keeps its episodes (hidden: not part of the dataset)."""
    return Path(cfg.out) / ".partial" / task_name


class _PartialTask:
    """An unfinished LIBERO task's progress on disk: one file per kept episode and the attempt count, so an
    interrupted collection continues from its next attempt (a task takes ~40 min of rendered episodes). Attempt
    k's episode depends only on (seed, task, k), so a resumed task's file equals an uninterrupted one's."""

    def __init__(self, cfg: CollectConfig, task: int, task_name: str):
        self.dir = _partial_dir(cfg, task_name)
        self.settings = {"suite": cfg.suite, "task": task, "seed": cfg.seed, "image_size": cfg.size,
                         "init": cfg.libero_init, "noise": cfg.noise, "miss": cfg.miss,
                         "keep_failures": cfg.keep_failures}
        if cfg.libero_mesh_faces:  # absent from full-mesh progress, which older collections wrote without it
            self.settings["mesh_faces"] = cfg.libero_mesh_faces
        if cfg.libero_step_factor != 1.0:  # likewise absent from collections at the evaluation limit
            self.settings["step_factor"] = cfg.libero_step_factor

    def load(self) -> tuple[list[Episode], list[int], int]:
        """(episodes kept, their attempt numbers, attempts made) so far; nothing when the task has not started."""
        path = self.dir / "progress.json"
        if not path.exists():
            return [], [], 0
        progress = read_json(path)
        if progress.get("settings") != self.settings:
            raise ValueError(f"{self.dir}: an unfinished collection with other settings ({progress.get('settings')}, "
                             f"now {self.settings}); delete that directory to start this task afresh")
        kept = [read_episodes(self.dir / f"attempt_{k}.hdf5")[0] for k in progress["kept"]]
        log.info("%s: resuming after %d attempts with %d episodes kept", self.dir.name, progress["attempts"], len(kept))
        return kept, progress["kept"], progress["attempts"]

    def record(self, attempt: int, episode: Episode | None, kept: list[int]) -> None:
        """After attempt ``attempt``: its episode when kept (written first), then the progress that names it."""
        if episode is not None:
            write_episodes(self.dir / f"attempt_{attempt}.hdf5", [episode])
        atomic_write_json(self.dir / "progress.json",
                          {"settings": self.settings, "attempts": attempt + 1, "kept": kept})


def _collect_limit(cfg: CollectConfig, spec: TaskSpec) -> int:
    """The expert's step limit for one LIBERO task's demonstrations."""
    return round(cfg.libero_step_factor * spec.max_steps)


def _probe_first(attempts: int, kept: int) -> bool:
    """Whether a task's next attempt is first played without rendering: once more than a fifth of its attempts
    have failed, skipping the frames of the failures saves more than the unrendered pass costs the successes."""
    return attempts >= 5 and attempts - kept > attempts / 5


def _collect_libero_task(job: tuple[CollectConfig, TaskSpec]) -> tuple[TaskSpec, list, int]:
    """(task, episodes kept, attempts) for one LIBERO task; runs in a worker process when ``workers > 1``. Attempt
    ``k`` plays the scene sampled with seed (seed, task, k), or official init state ``k`` (mod 50). Progress is
    kept per episode, so an interrupted task resumes at its next attempt."""
    cfg, spec = job
    task = spec.index
    if not logging.getLogger().handlers:  # a spawned worker: its per-episode progress goes to the caller's log too
        logging.basicConfig(level=logging.INFO, format="%(message)s")
    partial = _PartialTask(cfg, task, spec.name)
    with exclusive_lock(partial.dir / ".lock", f"collection of {spec.name}"):
        kept, kept_attempts, attempts = partial.load()
        wanted = cfg.episodes
        budget = wanted if cfg.keep_failures else 3 * wanted + 10
        if len(kept) >= wanted or attempts >= budget:
            return spec, kept, attempts
        env = make_env("libero", cfg.suite, task, image_size=cfg.size, render=True, init_state=0,
                       init=cfg.libero_init, mesh_faces=cfg.libero_mesh_faces, max_steps=_collect_limit(cfg, spec))
        actor = RolloutExpert(cfg.suite, task, ExpertConfig(noise=cfg.noise, miss=cfg.miss))
        try:
            while len(kept) < wanted and attempts < budget:
                _stop_if_orphaned()
                seed = episode_seed(episode_seed(cfg.seed, task), attempts)
                ep = None
                if not cfg.keep_failures and _probe_first(attempts, len(kept)):
                    # The expert reads privileged state, so without frames nothing is rendered (a fifth of the
                    # time or less); the same seed plays the same episode again, rendered, only when it succeeds.
                    probe = run_episode(env, actor, seed, frames=False)
                    ep = None if probe.success else probe
                if ep is None:
                    ep = run_episode(env, actor, seed)
                ep.meta["init_state"] = env.init_state
                ep.meta["init_seed"] = env.init_seed
                keep = ep.success or cfg.keep_failures
                if keep:
                    kept.append(ep)
                    kept_attempts.append(attempts)
                partial.record(attempts, ep if keep else None, kept_attempts)
                attempts += 1
                log.info("%s task %d %s: %s in %d steps", cfg.suite, task,
                         f"init state {env.init_state}" if env.init_state is not None
                         else f"scene seed {env.init_seed}", "success" if ep.success else "failure", len(ep))
        finally:
            env.close()
    return spec, kept, attempts


def _stop_if_orphaned() -> None:
    """End a worker whose run was killed: it would otherwise collect its whole task (tens of minutes) for nobody,
    holding the task against the rerun that resumes it. Its kept episodes are on disk already."""
    parent = mp.parent_process()
    if parent is not None and not parent.is_alive():
        raise SystemExit("the collection run that started this worker has ended")
