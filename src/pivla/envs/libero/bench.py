"""``pivla bench sim --env libero``: LIBERO steps per second with the policy's cameras and without any.

Flags read from ``args`` (all optional): ``suite`` (libero_spatial), ``task`` (0), ``steps`` (50 per
repeat), ``repeats`` (3), ``image_size`` (128), ``cameras`` ("agentview_rgb,eye_in_hand_rgb").
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


def run_bench(args: Any) -> dict:
    """Median steps/s over repeats, with cameras (policy resolution, reflections off) and without."""
    from pivla.envs.libero.env import make_env

    suite = getattr(args, "suite", None) or "libero_spatial"
    task = int(getattr(args, "task", None) or 0)
    steps = int(getattr(args, "steps", None) or 50)
    repeats = int(getattr(args, "repeats", None) or 3)
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
        finally:
            env.close()
        out[f"steps_per_s_{label}"] = round(statistics.median(rates), 2)
        out[f"reset_s_{label}"] = round(reset, 3)
        out[f"create_s_{label}"] = round(create, 2)
    return out
