"""Episode runner shared by demonstration collection and policy rollouts: (env, actor, seed) -> Episode.

An *actor* is any callable ``actor(obs) -> action (D,)`` (D the env's action dimension); if it has
``reset(env, seed)`` that is called after every ``env.reset``, and its ``source`` attribute ("expert",
"policy", ...) is recorded. Every episode records its actions, observations (before each action), rewards,
dones and success, so failed rollouts are as usable (for the value head) as successful demonstrations. An
actor that executes a perturbed action but wants a different one recorded (a DART expert) exposes it as
``actor.label``; one whose demonstration should go on past the moment of success (to let go and move away,
not just the first step of opening) sets ``actor.follow_through`` to the number of extra steps to record.

Episode seeds depend only on (base seed, episode index), never on the number of worker processes, so
``--workers 1`` and ``--workers 4`` produce identical datasets.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import pickle
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np
from tqdm import tqdm

from pivla.data.episode import Episode
from pivla.envs.backend import BackendConfig, ray_map

log = logging.getLogger(__name__)

EnvFactory = Callable[[], Any]
Actor = Callable[[dict], np.ndarray]


def episode_seed(seed: int, index: int) -> int:
    """A well-mixed 31-bit seed for episode ``index`` of a run seeded ``seed``."""
    return int(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, int(index)]).generate_state(1)[0] & 0x7FFFFFFF)


def run_episode(env: Any, actor: Actor, seed: int, max_steps: int | None = None,
                reset_options: dict | None = None, frames: bool = True) -> Episode:
    """Run one episode until success (terminated), the env's step limit (truncated) or ``max_steps``;
    ``reset_options`` go to ``env.reset`` (e.g. LIBERO's ``{"init_state": i}``). ``frames=False`` keeps no
    observations in the Episode (its actions, rewards and outcome only), so an env that renders only what
    is read (LIBERO) renders only what the actor reads."""
    obs, info = env.reset(seed=seed, options=reset_options)
    if hasattr(actor, "reset"):
        actor.reset(env, seed)
    task = getattr(env.unwrapped, "task", None)
    # The env's own limit when it has one (a LIBERO env made with another limit than its task's), else the task's.
    limit = max_steps or getattr(env.unwrapped, "max_steps", None) or getattr(task, "max_steps", None) or 1000
    kept: dict[str, list[np.ndarray]] = {k: [] for k in obs if k != "instruction"} if frames else {}
    actions, rewards, dones = [], [], []
    instruction = obs.get("instruction", "")
    success = bool(info.get("success", False))
    extra = int(getattr(actor, "follow_through", 0))
    for _ in range(limit):
        action = np.asarray(actor(obs), dtype=np.float32)
        for key, values in kept.items():
            values.append(obs[key])
        label = getattr(actor, "label", None)
        obs, reward, terminated, truncated, info = env.step(action)
        actions.append(action if label is None else np.asarray(label, dtype=np.float32))
        rewards.append(reward)
        dones.append(terminated or truncated)
        success = bool(info.get("success", False))
        if terminated and success and extra > 0 and not truncated:
            extra -= 1
            dones[-1] = False  # the episode goes on: only its last step is terminal
            continue
        if terminated or truncated:
            break
    if dones:
        dones[-1] = True
    unwrapped = env.unwrapped
    meta = {
        "seed": None if seed is None else int(seed),
        "steps": len(actions),
        "return": float(np.sum(rewards)),
        "suite": getattr(unwrapped, "suite", None),
        "task": getattr(task, "name", None),
        "realism": getattr(unwrapped, "realism", None),
        "perturb": unwrapped.perturb.spec() if hasattr(unwrapped, "perturb") else None,
        "stage_progress": info.get("stage_progress"),
    }
    return Episode(
        actions=np.array(actions, np.float32).reshape(len(actions), _action_dim(env)),
        obs={k: np.stack(v) for k, v in kept.items()},
        instruction=instruction,
        rewards=np.array(rewards, np.float32),
        dones=np.array(dones, np.uint8),
        success=success,
        source=getattr(actor, "source", "rollout"),
        meta=meta,
    )


def _action_dim(env: Any) -> int:
    """The env's action dimension (7 for the twin's and LIBERO's end-effector deltas, 6 for the SO-101's joints)."""
    shape = getattr(getattr(env, "action_space", None), "shape", None)
    return int(shape[0]) if shape else 7


_WORKER_ENVS: dict[bytes, Any] = {}


def _worker(job: tuple[EnvFactory, Actor, int]) -> Episode:
    """Runs in a worker process; reuses one env per distinct factory (model building costs ~50 ms)."""
    env_factory, actor, seed = job
    key = pickle.dumps(env_factory)
    if key not in _WORKER_ENVS:
        _WORKER_ENVS[key] = env_factory()
    return run_episode(_WORKER_ENVS[key], actor, seed)


def iter_jobs(jobs: Sequence[tuple[EnvFactory, int]], actor: Actor, *, workers: int = 1,
              desc: str | None = None, backend: BackendConfig | None = None) -> Iterator[Episode]:
    """One episode per (env factory, seed) job, yielded in job order as each finishes. ``workers > 1`` uses
    spawned processes, ``backend`` ray that many Ray actors (factories and actor must then be picklable, e.g.
    ``functools.partial(make_env, ...)`` and an un-reset expert); each worker builds one env per distinct
    factory and reuses it."""
    if backend is not None and backend.backend == "ray":
        yield from ray_map(_worker, [(factory, actor, seed) for factory, seed in jobs], backend, workers=workers,
                           desc=desc)
        return
    progress = tqdm(total=len(jobs), desc=desc, unit="ep", disable=desc is None, leave=False)
    try:
        if workers <= 1 or len(jobs) <= 1:
            envs: dict[int, Any] = {}  # by identity: in-process factories need not be picklable
            try:
                for factory, seed in jobs:
                    key = id(factory)
                    if key not in envs:
                        envs[key] = factory()
                    yield run_episode(envs[key], actor, seed)
                    progress.update()
            finally:
                for env in envs.values():
                    env.close()
            return
        ctx = mp.get_context("spawn")
        with ctx.Pool(min(workers, len(jobs))) as pool:
            for ep in pool.imap(_worker, [(factory, actor, seed) for factory, seed in jobs]):
                yield ep
                progress.update()
    finally:
        progress.close()


def run_jobs(jobs: Sequence[tuple[EnvFactory, int]], actor: Actor, *, workers: int = 1,
             desc: str | None = None) -> list[Episode]:
    """Every episode of :func:`iter_jobs`, in job order."""
    return list(iter_jobs(jobs, actor, workers=workers, desc=desc))


def run_episodes(env_factory: EnvFactory, actor: Actor, seeds: Sequence[int], *, workers: int = 1,
                 desc: str | None = None) -> list[Episode]:
    """One episode of ``env_factory``'s env per seed, in seed order (see :func:`run_jobs`)."""
    return run_jobs([(env_factory, s) for s in seeds], actor, workers=workers, desc=desc)


def collect_episodes(
    env_factory: EnvFactory, actor: Actor, n: int, seed: int = 0, *, workers: int = 1, desc: str | None = None
) -> list[Episode]:
    """``n`` episodes with seeds ``episode_seed(seed, 0..n-1)`` (identical for any ``workers``)."""
    return run_episodes(env_factory, actor, [episode_seed(seed, i) for i in range(n)], workers=workers, desc=desc)
