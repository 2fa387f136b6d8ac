"""``pivla bench sim --env libero``: LIBERO steps per second with the policy's cameras and without any.

Flags read from ``args`` (all optional, as ``pivla bench sim`` passes them): ``suite`` (libero_spatial),
``task`` (0), ``steps`` (50 per repeat), ``repeats`` (3), ``episodes`` (0: when > 0, also time that many
scripted-expert episodes with cameras, i.e. the cost of ``pivla collect --env libero``), ``image_size``
(128), ``cameras`` ("agentview_rgb,eye_in_hand_rgb"). ``threads`` and ``json`` are the CLI's.
One env exists at a time (each LIBERO process holds ~2 GB). Actions are small random deltas, so the
arm moves and the scene is not static.
"""

from __future__ import annotations

import statistics
import time
from typing import Any

import numpy as np


def _rate(env: Any, steps: int, repeats: int, rng: np.random.Generator) -> tuple[list[float], float]:
    rates, resets = [], []
    for r in range(repeats):
        t0 = time.perf_counter()
        env.reset(options={"init_state": r})
        resets.append(time.perf_counter() - t0)
        actions = rng.uniform(-0.3, 0.3, size=(steps, 7))
        t0 = time.perf_counter()
        for a in actions:
            env.step(a)
        rates.append(steps / (time.perf_counter() - t0))
    return rates, statistics.median(resets)


def _expert_rate(env: Any, suite: str, task: int, episodes: int) -> dict:
    """Scripted-expert episodes (official init states 0, 1, ...) per minute, frames rendered as when collecting."""
    from pivla.envs.libero.expert import expert_actor, run_expert_episode

    actor = expert_actor(suite, task)
    t0 = time.perf_counter()
    results = [run_expert_episode(env, actor, i) for i in range(episodes)]
    elapsed = time.perf_counter() - t0
    return {"expert_episodes": episodes, "expert_successes": sum(r["success"] for r in results),
            "expert_episodes_per_min": round(60 * episodes / elapsed, 2),
            "expert_steps_per_s": round(sum(r["steps"] for r in results) / elapsed, 2)}


def run_bench(args: Any) -> dict:
    """Median steps/s over repeats, with cameras (policy resolution, reflections off) and without."""
    from pivla.envs.libero.env import make_env

    suite = getattr(args, "suite", None) or "libero_spatial"
    task = int(getattr(args, "task", None) or 0)
    steps = int(getattr(args, "steps", None) or 50)
    repeats = int(getattr(args, "repeats", None) or 3)
    episodes = int(getattr(args, "episodes", None) or 0)
    size = int(getattr(args, "image_size", None) or 128)
    cameras = tuple(c for c in (getattr(args, "cameras", None) or "agentview_rgb,eye_in_hand_rgb").split(",") if c)
    rng = np.random.default_rng(0)
    out: dict[str, Any] = {"env": "libero", "suite": suite, "task": task, "steps": steps, "repeats": repeats,
                           "image_size": size, "cameras": list(cameras)}
    for label, kwargs in (("with_cameras", {"render": True}), ("no_cameras", {"render": False})):
        t0 = time.perf_counter()
        env = make_env(suite, task, image_size=size, cameras=cameras, **kwargs)
        create = time.perf_counter() - t0
        try:
            rates, reset = _rate(env, steps, repeats, rng)
            if label == "with_cameras" and episodes > 0:
                out.update(_expert_rate(env, suite, task, episodes))
        finally:
            env.close()
        out[f"steps_per_s_{label}"] = round(statistics.median(rates), 2)
        out[f"reset_s_{label}"] = round(reset, 3)
        out[f"create_s_{label}"] = round(create, 2)
    return out
