"""Measurements of the twin: simulation speed (``pivla bench sim``) and servo repeatability.

``run_bench(args)`` reads these attributes of ``args`` (all optional): ``image_size`` (96), ``steps`` (200
env steps per repeat), ``repeats`` (5), ``episodes`` (10 collection episodes), ``suite`` ("pick_place"),
``realism`` ("ideal"), ``seed`` (0), ``repeatability`` (bool: also measure servo repeatability),
``expert_episodes`` (0: when > 0, also measure the scripted experts' success per suite and realism with
that many episodes per task, cameras off).
"""

from __future__ import annotations

import statistics
import time
from typing import Any

import numpy as np

from pivla.envs.tabletop import make_env
from pivla.envs.tabletop.env import TRANS_SCALE
from pivla.envs.tabletop.expert import make_expert
from pivla.envs.tabletop.servo import ServoConfig
from pivla.envs.tabletop.tasks import get_suite


def _steps_per_s(image_size: int, steps: int, repeats: int, seed: int) -> list[float]:
    """Env steps per second with both cameras rendered, random actions (episodes reset on termination)."""
    env = make_env("pick_place", 0, image_size=image_size, seed=seed)
    rng = np.random.default_rng(seed)
    rates = []
    env.reset(seed=seed)
    env.step(np.zeros(7))  # create the GL context outside the timed region
    for r in range(repeats):
        env.reset(seed=seed + r)
        start = time.perf_counter()
        for _ in range(steps):
            _, _, term, trunc, _ = env.step(rng.uniform(-1, 1, 7).astype(np.float32))
            if term or trunc:
                env.reset()
        rates.append(steps / (time.perf_counter() - start))
    env.close()
    return rates


def _episodes_per_min(suite: str, episodes: int, image_size: int, realism: str, seed: int) -> tuple[float, float]:
    """Scripted-expert collection rate (both cameras rendered, one process) and its success rate."""
    from pivla.envs.rollout import run_episode

    tasks = get_suite(suite)
    envs = [make_env(suite, i, image_size=image_size, realism=realism) for i in range(len(tasks))]
    expert = make_expert(0.0)
    run_episode(envs[0], expert, seed)  # warm-up: GL context
    successes = 0
    start = time.perf_counter()
    for i in range(episodes):
        successes += run_episode(envs[i % len(envs)], expert, seed + i).success
    elapsed = time.perf_counter() - start
    for env in envs:
        env.close()
    return episodes / elapsed * 60.0, successes / episodes


def measure_repeatability(trials: int = 30, seed: int = 0, servo: ServoConfig | None = None) -> dict[str, float]:
    """ISO 9283-style pose repeatability of the servo twin, in mm.

    Each trial starts from a random pose 4-8 cm away, drives the *commanded* pose (open loop, as the real
    arm has no feedback) to one fixed target, holds, and records where the tool centre really is.
    RP = mean distance to the barycentre + 3 standard deviations.
    """
    env = make_env("pick_place", 0, realism="servo", render=False, servo=servo)
    target = np.array([0.2, 0.0, 0.08])
    rng = np.random.default_rng(seed)
    points = []
    for t in range(trials):
        env.reset(seed=seed + t)
        direction = rng.normal(size=3) * [1.0, 1.0, 0.3]
        detour = target + rng.uniform(0.04, 0.08) * direction / np.linalg.norm(direction)
        for goal in (detour, target):
            for _ in range(20):
                err = goal - env.privileged_state()["cmd_pos"]
                if np.linalg.norm(err) < 1e-4:
                    break
                env.step(np.concatenate([np.clip(err / TRANS_SCALE, -1, 1), np.zeros(3), [-1.0]]))
        for _ in range(3):
            env.step(np.array([0, 0, 0, 0, 0, 0, -1.0]))
        points.append(env.privileged_state()["ee_pos"])
    points = np.array(points)
    dist = np.linalg.norm(points - points.mean(axis=0), axis=1) * 1000
    return {"rp_mm": float(dist.mean() + 3 * dist.std()), "mean_mm": float(dist.mean()), "max_mm": float(dist.max())}


def expert_success(episodes: int, seed: int = 0, suites: tuple[str, ...] = ("pick_place", "drawer", "stack", "long"),
                   realisms: tuple[str, ...] = ("ideal", "servo")) -> dict[str, dict[str, Any]]:
    """Success rate of the noise-free expert per suite and realism (``episodes`` per task, no rendering)."""
    from pivla.envs.rollout import collect_episodes

    out: dict[str, dict[str, Any]] = {}
    for realism in realisms:
        for suite in suites:
            results, steps = [], []
            for i, task in enumerate(get_suite(suite)):
                env = make_env(suite, i, realism=realism, render=False)
                eps = collect_episodes(lambda env=env: env, make_expert(0.0), episodes, seed=seed + i)
                results += [e.success for e in eps]
                steps += [len(e) for e in eps]
            out[f"{suite}/{realism}"] = {"success": float(np.mean(results)), "episodes": len(results),
                                         "mean_steps": float(np.mean(steps))}
    return out


def run_bench(args: Any) -> dict[str, Any]:
    image_size = int(getattr(args, "image_size", None) or 96)
    steps = int(getattr(args, "steps", None) or 200)
    repeats = int(getattr(args, "repeats", None) or 5)
    episodes = int(getattr(args, "episodes", None) or 10)
    suite = getattr(args, "suite", None) or "pick_place"
    realism = getattr(args, "realism", None) or "ideal"
    seed = int(getattr(args, "seed", None) or 0)
    rates = _steps_per_s(image_size, steps, repeats, seed)
    per_min, success = _episodes_per_min(suite, episodes, image_size, realism, seed)
    result: dict[str, Any] = {
        "steps_per_s": statistics.median(rates),
        "steps_per_s_runs": [round(r, 1) for r in rates],
        "episodes_per_min": per_min,
        "expert_success": success,
        "image_size": image_size,
        "cameras": 2,
        "suite": suite,
        "realism": realism,
    }
    if getattr(args, "repeatability", False):
        result["servo_repeatability"] = measure_repeatability(seed=seed)
    if getattr(args, "expert_episodes", 0):
        result["expert_success_by_suite"] = expert_success(int(args.expert_episodes), seed=seed)
    return result
