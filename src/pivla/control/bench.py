"""AURD's per-step overhead against the fixed-horizon executor, measured in the same run.

Both executors drive the same policy over the same recorded observations (no simulator in the loop, so
only control cost is timed): fixed horizon pays one policy query every H steps; AURD pays the same
queries (or more, when it replans) plus encoding every new observation and the decision. Rounds
alternate between the two so that machine noise hits both alike; the figure is the ratio of medians.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from pivla.control.executors import make_executor
from pivla.policy import Calibration


def run_bench(args: argparse.Namespace) -> dict:
    from pivla.cli.bench import default_policy, random_obs

    torch.set_num_threads(getattr(args, "threads", 2))
    policy = default_policy(getattr(args, "run", None))
    # thresholds high enough that AURD completes every nominal horizon, also for a calibrated run (random
    # observations would make it replan): same queries as fixed, so the difference is exactly the per-step
    # encoding + decision overhead
    policy.calibration = Calibration(tau_low=1e9, tau_high=1e9, v_thresh=-1e9)
    rng = np.random.default_rng(0)
    observations = [random_obs(policy, rng) for _ in range(16)]
    steps, repeats = args.steps, args.repeats
    per_step = {"fixed": [], "aurd": []}
    queries = {}
    for _ in range(repeats):
        for name in ("fixed", "aurd"):
            ex = make_executor(name, horizon=policy.horizon) if name == "fixed" else make_executor(name)
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
        if t % policy.horizon == 0:
            policy.infer(obs)
            query.append(time.perf_counter() - t1)
        encode.append(t1 - t0)
    return {
        "fixed_ms_per_step": round(fixed * 1e3, 3),
        "aurd_ms_per_step": round(aurd * 1e3, 3),
        "aurd_overhead_pct": round(100 * (aurd / fixed - 1), 1),
        "aurd_overhead_ms_per_step": round((aurd - fixed) * 1e3, 3),
        "encode_ms_median": round(float(np.median(encode)) * 1e3, 3),
        "query_ms_median": round(float(np.median(query)) * 1e3, 3),
        "target_encoder": policy.cfg.target_encoder.name,
        "policy_queries": queries,
        "steps": steps, "repeats": repeats,
    }
