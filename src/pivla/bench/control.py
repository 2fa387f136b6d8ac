"""AURD's per-step overhead against the fixed-horizon executor, measured in the same run.

Two figures, both with the thresholds lifted so that AURD makes exactly fixed horizon's policy queries:

- *controller only*: both executors drive the same policy over the same recorded observations, no
  simulator, so only control cost is timed. Fixed horizon pays one policy query every H steps; AURD pays
  the same queries plus encoding each new observation a decision reads (not the one after a completed
  plan: the replan starts at k = 0 with U_pred = 0), and the decision.
- *closed loop* (``loop_*``): whole episodes in the tabletop twin (physics, cameras, executor), same
  seeds for both, as the paper times its controller (+1.2 ms at 105 Hz). With the same plans the two
  executors act identically, so the trajectories match and the gap is again AURD's alone.

Rounds alternate between the two executors so that machine noise hits both alike; each figure is a
ratio of medians.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from pivla.bench.policy import default_policy, random_obs
from pivla.control.contract import Calibration
from pivla.control.executors import executor_config, make_executor
from pivla.control.runner import run_episode
from pivla.envs import make_env
from pivla.envs.rollout import episode_seed
from pivla.policy import Policy


@dataclass
class ControlBenchConfig:
    """AURD's per-step overhead against fixed horizon."""

    policy: str | None = None
    """A trained run directory (default: the default config, random weights)."""
    steps: int = 200
    """Controller-only steps per repeat."""
    repeats: int = 5
    """Rounds, alternating the two executors."""
    loop_episodes: int = 5
    """Also time whole episodes in the tabletop twin (0: controller only)."""
    encoder_runtime: Literal["auto", "torch", "onnx"] = "auto"
    """Where the target encoder runs (auto: ONNX Runtime on a CPU when installed); with ONNX Runtime, one
    PyTorch encoding is timed too, for comparison."""
    threads: int = 2
    """Torch intra-op threads."""


def _executor(name: str, policy: Policy):
    """Fixed horizon at the policy's nominal horizon (AURD's own default), so both plan alike, and without
    the trace-only monitoring (it would encode like AURD and hide AURD's cost)."""
    if name == "fixed":
        return make_executor(executor_config("fixed", horizon=policy.spec.horizon, monitor=False))
    return make_executor(executor_config(name))


def run_control_bench(cfg: ControlBenchConfig) -> dict:
    torch.set_num_threads(cfg.threads)
    policy = default_policy(cfg.policy, encoder_runtime=cfg.encoder_runtime)
    # thresholds high enough that AURD completes every nominal horizon, also for a calibrated run (random
    # observations would make it replan): same queries as fixed, so the difference is exactly the per-step
    # encoding + decision overhead
    policy.calibration = Calibration(tau_low=1e9, tau_high=1e9, v_thresh=-1e9)
    rng = np.random.default_rng(0)
    observations = [random_obs(policy, rng) for _ in range(16)]
    steps, repeats = cfg.steps, cfg.repeats
    per_step = {"fixed": [], "aurd": []}
    queries = {}
    for _ in range(repeats):
        for name in ("fixed", "aurd"):
            ex = _executor(name, policy)
            ex.reset()
            ex.act(policy, observations[0])  # warm-up
            ex.reset()
            t0 = time.perf_counter()
            for t in range(steps):
                ex.act(policy, observations[t % len(observations)])
            per_step[name].append((time.perf_counter() - t0) / steps)
            queries[name] = len(ex.plans) + 1
    fixed, aurd = float(np.median(per_step["fixed"])), float(np.median(per_step["aurd"]))
    encode, query = [], []
    for t in range(steps):
        obs = observations[t % len(observations)]
        t0 = time.perf_counter()
        policy.encode(obs)
        t1 = time.perf_counter()
        if t % policy.spec.horizon == 0:
            policy.infer(obs)
            query.append(time.perf_counter() - t1)
        encode.append(t1 - t0)
    other = _torch_encode_ms(policy, observations, steps)
    loop = closed_loop(policy, cfg.loop_episodes, repeats) if cfg.loop_episodes > 0 else {}
    return {
        "fixed_ms_per_step": round(fixed * 1e3, 3),
        "aurd_ms_per_step": round(aurd * 1e3, 3),
        "aurd_overhead_pct": round(100 * (aurd / fixed - 1), 1),
        "aurd_overhead_ms_per_step": round((aurd - fixed) * 1e3, 3),
        "encode_ms_median": round(float(np.median(encode)) * 1e3, 3),
        "query_ms_median": round(float(np.median(query)) * 1e3, 3),
        "target_encoder": policy.cfg.target_encoder.name,
        "encoder_runtime": policy.encoder_runtime,
        **other,
        "policy_queries": queries,
        "steps": steps, "repeats": repeats,
        **loop,
    }


def _torch_encode_ms(policy, observations: list[dict], steps: int) -> dict:
    """Median ms of one encoding with PyTorch when the policy encodes on ONNX Runtime (same weights, same
    observations): what the runtime saves, measured in the same run. A second ``Policy`` on the same model
    keeps PyTorch, so the ONNX graph is neither rebuilt nor reloaded."""
    if policy.encoder_runtime != "onnx":
        return {}
    torch_policy = Policy(policy.model, policy.stats, policy.text, device=policy.device, encoder_runtime="torch")
    times = []
    for t in range(steps):
        t0 = time.perf_counter()
        torch_policy.encode(observations[t % len(observations)])
        times.append(time.perf_counter() - t0)
    return {"encode_ms_median_torch": round(float(np.median(times)) * 1e3, 3)}


def closed_loop(policy, episodes: int, repeats: int) -> dict:
    """Median ms per control step of whole twin episodes (``pick_place`` task 0, fixed seeds) under each
    executor; the policy's thresholds must already be lifted so that both execute the same plans.

    ``loop_*_executor_ms`` is the executor's own share of a step (its ``act`` calls: policy queries,
    encodings, decisions), timed inside the same episodes. Their difference is AURD's cost where it runs,
    with caches shared with the renderer, but without the simulator's run-to-run noise that the whole-step
    difference carries; ``loop_executor_overhead_pct`` relates it to fixed horizon's whole step."""
    env = make_env("tabletop", "pick_place", 0, image_size=policy.cfg.image_size, cameras=tuple(policy.cfg.cameras))
    seeds = [episode_seed(0, i) for i in range(episodes)]
    per_step: dict[str, list[float]] = {"fixed": [], "aurd": []}
    executor: dict[str, list[float]] = {"fixed": [], "aurd": []}
    outcomes: dict[str, list[tuple[int, bool, int]]] = {}
    run_episode(env, policy, _executor("fixed", policy), seed=seeds[0], max_steps=5)  # warm-up
    for _ in range(repeats):
        for name in ("fixed", "aurd"):
            t0, n, acting, outcome = time.perf_counter(), 0, 0.0, []
            for seed in seeds:
                res = run_episode(env, policy, _executor(name, policy), seed=seed)
                n += res.steps
                acting += sum(res.step_times)
                outcome.append((res.steps, res.success, len(res.plans)))
            per_step[name].append((time.perf_counter() - t0) / n)
            executor[name].append(acting / n)
            outcomes[name] = outcome
    env.close()
    fixed, aurd = float(np.median(per_step["fixed"])), float(np.median(per_step["aurd"]))
    fixed_ex, aurd_ex = float(np.median(executor["fixed"])), float(np.median(executor["aurd"]))
    return {
        "loop_fixed_executor_ms": round(fixed_ex * 1e3, 3),
        "loop_aurd_executor_ms": round(aurd_ex * 1e3, 3),
        "loop_executor_overhead_pct": round(100 * (aurd_ex - fixed_ex) / fixed, 1),
        "loop_fixed_ms_per_step": round(fixed * 1e3, 3),
        "loop_aurd_ms_per_step": round(aurd * 1e3, 3),
        "loop_overhead_pct": round(100 * (aurd / fixed - 1), 1),
        "loop_overhead_ms_per_step": round((aurd - fixed) * 1e3, 3),
        "loop_control_hz_fixed": round(1.0 / fixed, 1),
        "loop_episodes": episodes,
        "loop_steps": sum(o[0] for o in outcomes["fixed"]),
        # same plans -> same actions -> same episodes (length, outcome, queries); False: not like for like
        "loop_same_episodes": outcomes["fixed"] == outcomes["aurd"],
    }
