"""Simulation speed: environment steps per second with the policy's cameras (and, for LIBERO, without any),
collection episodes per minute, and the twin's servo repeatability and experts' success."""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from pivla.envs.libero.env import make_env as make_libero
from pivla.envs.libero.expert import RolloutExpert
from pivla.envs.rollout import collect_episodes, run_episode
from pivla.envs.tabletop import make_env
from pivla.envs.tabletop.env import TRANS_SCALE
from pivla.envs.tabletop.expert import make_expert
from pivla.envs.tabletop.servo import ServoConfig
from pivla.envs.tabletop.tasks import get_suite


@dataclass
class SimBenchConfig:
    """What to time."""

    env: Literal["tabletop", "libero"] = "tabletop"
    """The twin or LIBERO."""
    suite: str | None = None
    """Task suite (default: pick_place / libero_spatial)."""
    task: int = 0
    """LIBERO: the task whose scene is stepped."""
    image_size: int | None = None
    """Camera resolution (default: the recipe's 80 px on the twin, 128 on LIBERO)."""
    cameras: tuple[str, ...] = ("agentview_rgb", "eye_in_hand_rgb")
    """LIBERO: the cameras rendered."""
    reflections: bool = False
    """LIBERO: render reflections (robosuite's default; the policy's envs switch them off)."""
    mesh_faces: int = 0
    """LIBERO: draw visual meshes simplified to about this many triangles (0: full meshes); with N > 0 the full
    meshes are timed too, in the same run, and the speed-up reported."""
    steps: int = 200
    """Environment steps per repeat."""
    repeats: int = 5
    """Repeats (the median is reported)."""
    episodes: int = 10
    """Expert episodes timed (the cost of collection; 0: none)."""
    realism: Literal["ideal", "servo"] = "ideal"
    """Twin actuation."""
    seed: int = 0
    """Seed of the scenes and actions."""
    repeatability: bool = False
    """Twin: also measure servo repeatability."""
    expert_episodes: int = 0
    """Twin: also measure the experts' success per suite and realism with this many episodes per task."""


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
    out: dict[str, dict[str, Any]] = {}
    for realism in realisms:
        for suite in suites:
            results, steps = [], []
            for i, _task in enumerate(get_suite(suite)):
                env = make_env(suite, i, realism=realism, render=False)
                eps = collect_episodes(lambda env=env: env, make_expert(0.0), episodes, seed=seed + i)
                results += [e.success for e in eps]
                steps += [len(e) for e in eps]
            out[f"{suite}/{realism}"] = {"success": float(np.mean(results)), "episodes": len(results),
                                         "mean_steps": float(np.mean(steps))}
    return out


def run_sim_bench(cfg: SimBenchConfig) -> dict[str, Any]:
    return _libero(cfg) if cfg.env == "libero" else _tabletop(cfg)


def _tabletop(cfg: SimBenchConfig) -> dict[str, Any]:
    image_size, suite = cfg.image_size or 80, cfg.suite or "pick_place"
    rates = _steps_per_s(image_size, cfg.steps, cfg.repeats, cfg.seed)
    per_min, success = _episodes_per_min(suite, cfg.episodes, image_size, cfg.realism, cfg.seed)
    result: dict[str, Any] = {
        "steps_per_s": statistics.median(rates),
        "steps_per_s_runs": [round(r, 1) for r in rates],
        "episodes_per_min": per_min,
        "expert_success": success,
        "image_size": image_size,
        "cameras": 2,
        "suite": suite,
        "realism": cfg.realism,
    }
    if cfg.repeatability:
        result["servo_repeatability"] = measure_repeatability(seed=cfg.seed)
    if cfg.expert_episodes:
        result["expert_success_by_suite"] = expert_success(cfg.expert_episodes, seed=cfg.seed)
    return result


def _rate(env: Any, steps: int, repeats: int, rng: np.random.Generator,
          read_every: int = 1) -> tuple[list[float], float]:
    """Steps/s, reading every camera image on one step in ``read_every`` (LIBERO renders what is read: 1 is a
    policy that looks every step, 5 a fixed horizon of 5 that looks on its query steps only)."""
    rates, resets = [], []
    for r in range(repeats):
        t0 = time.perf_counter()
        obs, _ = env.reset(options={"init_state": r})
        resets.append(time.perf_counter() - t0)
        actions = rng.uniform(-0.3, 0.3, size=(steps, 7))
        t0 = time.perf_counter()
        for i, a in enumerate(actions):
            if i % read_every == 0:
                for key in env.config.cameras if env.config.render else ():
                    obs[key]
            obs, *_ = env.step(a)
        rates.append(steps / (time.perf_counter() - t0))
    return rates, statistics.median(resets)


def _expert_rate(env: Any, suite: str, task: int, episodes: int) -> dict:
    """Scripted-expert episodes (official init states 0, 1, ...) per minute, every frame rendered and kept, as
    when collecting."""
    actor = RolloutExpert(suite, task)
    t0 = time.perf_counter()
    results = [run_episode(env, actor, i, reset_options={"init_state": i}) for i in range(episodes)]
    elapsed = time.perf_counter() - t0
    return {"expert_episodes": episodes, "expert_successes": sum(bool(r.success) for r in results),
            "expert_episodes_per_min": round(60 * episodes / elapsed, 2),
            "expert_steps_per_s": round(sum(len(r) for r in results) / elapsed, 2)}


def _libero(cfg: SimBenchConfig) -> dict[str, Any]:
    """Median steps/s over repeats, with cameras read every step (by default the policy's resolution, reflections
    off), read every 5th step, and without cameras; one env
    exists at a time (each LIBERO process holds ~2 GB); actions are small random deltas, so the arm moves."""
    suite, size = cfg.suite or "libero_spatial", cfg.image_size or 128
    out: dict[str, Any] = {"env": "libero", "suite": suite, "task": cfg.task, "steps": cfg.steps,
                           "repeats": cfg.repeats, "image_size": size, "cameras": list(cfg.cameras),
                           "reflections": cfg.reflections}
    configs = [("with_cameras", {"render": True, "mesh_faces": cfg.mesh_faces})]
    if cfg.mesh_faces:
        configs.append(("with_cameras_full_meshes", {"render": True}))
    for label, kwargs in (*configs, ("no_cameras", {"render": False})):
        t0 = time.perf_counter()
        env = make_libero(suite, cfg.task, image_size=size, cameras=cfg.cameras, reflections=cfg.reflections,
                          **kwargs)
        create = time.perf_counter() - t0
        rng = np.random.default_rng(cfg.seed)  # the same actions in every configuration
        try:
            rates, reset = _rate(env, cfg.steps, cfg.repeats, rng)
            if label.startswith("with_cameras"):
                every5, _ = _rate(env, cfg.steps, cfg.repeats, rng, read_every=5)
                out[label.replace("with_cameras", "steps_per_s_reading_every_5th_step")] = round(
                    statistics.median(every5), 2)
                if cfg.episodes > 0:
                    rate = _expert_rate(env, suite, cfg.task, cfg.episodes)
                    suffix = label.removeprefix("with_cameras")
                    out.update({f"{k}{suffix}": v for k, v in rate.items()})
        finally:
            env.close()
        out[f"steps_per_s_{label}"] = round(statistics.median(rates), 2)
        out[f"reset_s_{label}"] = round(reset, 3)
        out[f"create_s_{label}"] = round(create, 2)
    out["mesh_faces"] = cfg.mesh_faces
    if cfg.mesh_faces:
        out["speedup_with_cameras"] = round(out["steps_per_s_with_cameras"]
                                            / out["steps_per_s_with_cameras_full_meshes"], 2)
    return out
