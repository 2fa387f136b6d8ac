"""The closed loop: a policy and an executor drive an environment (simulated twin, LIBERO or the arm)."""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pivla.control.executors import BaseExecutor
from pivla.data.format import Episode
from pivla.envs.rollout import run_episode as _run_actor_episode


class ExecutorActor:
    """Adapts (policy, executor) to the rollout runner's actor interface and times every control step
    (without a baseline's trace-only monitoring, ``BaseExecutor.monitor_s``: it is not part of its control)."""

    source = "policy"

    def __init__(self, policy: Any, executor: BaseExecutor):
        self.policy, self.executor = policy, executor
        self.step_times: list[float] = []

    def reset(self, env: Any = None, seed: int | None = None) -> None:
        self.executor.reset()
        self.step_times = []

    def __call__(self, obs: dict) -> np.ndarray:
        t, monitoring = time.perf_counter(), self.executor.monitor_s
        action = self.executor.act(self.policy, obs)
        self.step_times.append(time.perf_counter() - t - (self.executor.monitor_s - monitoring))
        return action


@dataclass
class EpisodeResult:
    success: bool
    steps: int
    executor: str
    trace: list[dict]
    plans: list[tuple[int, str]]
    step_times: list[float]
    seed: int | None = None
    stage_progress: float | None = None  # twin: fraction of the task's stages reached; LIBERO: of its goal met
    queries: int = 0  # policy forward passes
    episode: Episode | None = field(default=None, repr=False)

    @property
    def events(self) -> Counter:
        return Counter(event for _, event in self.plans)

    def summary(self) -> dict:
        ev = self.events
        horizons = [h for h, e in self.plans if e != "pause"]
        return {
            "success": self.success, "steps": self.steps, "executor": self.executor, "seed": self.seed,
            "stage_progress": self.stage_progress,
            "plans": len(self.plans), "queries": self.queries, "replans": ev["replan"], "prunes": ev["prune"], "pauses": ev["pause"],
            "mean_executed_horizon": float(np.mean(horizons)) if horizons else 0.0,
            # mean, not median: chunking executors query the policy on a few steps only
            "control_ms_mean": float(np.mean(self.step_times) * 1e3) if self.step_times else 0.0,
        }


def run_episode(env: Any, policy: Any, executor: BaseExecutor, seed: int | None = None,
                max_steps: int | None = None, keep_episode: bool = False,
                reset_options: dict | None = None) -> EpisodeResult:
    """Run one episode of ``env`` with ``policy`` acting through ``executor``; the executor's trace and
    plan events come back with the outcome. ``keep_episode`` also returns the recorded Episode (for
    rollout datasets that teach the value head what failure looks like)."""
    actor = ExecutorActor(policy, executor)
    ep = _run_actor_episode(env, actor, seed, max_steps, reset_options, frames=keep_episode)
    return EpisodeResult(
        success=bool(ep.success), steps=len(ep), executor=executor.name, trace=list(executor.trace),
        plans=list(executor.plans), step_times=list(actor.step_times), seed=seed,
        stage_progress=ep.meta.get("stage_progress"), queries=executor.queries, episode=ep if keep_episode else None,
    )
