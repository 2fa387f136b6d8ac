"""The closed loop: a policy and an executor drive an environment (simulated twin, LIBERO or the arm)."""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pivla.control.asynchronous import MOTION, ExecutionConfig, LinkActor
from pivla.control.executors import BaseExecutor
from pivla.control.latency import Latency, control_hz, parse_latency
from pivla.control.math import Event
from pivla.data.episode import Episode
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
    plans: list[tuple[int, Event]]
    step_times: list[float]
    seed: int | None = None
    stage_progress: float | None = None  # twin: fraction of the task's stages reached; LIBERO: of its goal met
    queries: int = 0  # policy forward passes
    episode: Episode | None = field(default=None, repr=False)
    control_hz: float | None = None  # the env's control rate
    actions: np.ndarray | None = field(default=None, repr=False)  # (steps, 7) as commanded
    faults: dict[str, int] = field(default_factory=dict)  # chunks not executed, queries lost (control.asynchronous)
    delays: list[int] = field(default_factory=list)  # control steps from each query to its answer

    @property
    def events(self) -> Counter:
        return Counter(event for _, event in self.plans)

    def summary(self) -> dict:
        ev = self.events
        horizons = [h for h, e in self.plans if e != Event.PAUSE]
        return {
            "success": self.success, "steps": self.steps, "executor": self.executor, "seed": self.seed,
            "stage_progress": self.stage_progress,
            "plans": len(self.plans), "queries": self.queries,
            "replans": ev[Event.REPLAN], "prunes": ev[Event.PRUNE], "pauses": ev[Event.PAUSE],
            "mean_executed_horizon": float(np.mean(horizons)) if horizons else 0.0,
            # mean, not median: chunking executors query the policy on a few steps only
            "control_ms_mean": float(np.mean(self.step_times) * 1e3) if self.step_times else 0.0,
            **self.timing_summary(),
        }

    def timing_summary(self) -> dict:
        """What latency and the execution mode cost: steps to success, steps the arm held waiting for a chunk,
        queries per minute of control, the jerk at chunk seams (``seam_jerks``), chunks not executed."""
        jerks = seam_jerks(self.actions, self.trace) if self.actions is not None else []
        minutes = self.steps / self.control_hz / 60 if self.control_hz else 0.0
        return {
            "steps_to_success": self.steps if self.success else None,
            "idle_steps": sum(bool(row.get("idle")) for row in self.trace),
            "queries_per_minute": self.queries / minutes if minutes else None,
            "seams": len(jerks), "seam_jerk": float(np.mean(jerks)) if jerks else None,
            "stale_chunks": 0, "out_of_order_chunks": 0, "failed_queries": 0, **self.faults,
            "delay_steps_mean": float(np.mean(self.delays)) if self.delays else None,
            "env_control_hz": self.control_hz,
        }


def seam_jerks(actions: np.ndarray, trace: list[dict]) -> list[float]:
    """At each step whose action is the first of a new chunk (``replanned``), || a[t+1] - 2 a[t] + a[t-1] || over
    the six end-effector dims of the commanded actions: the jerk the seam puts into the motion, in action units
    per step^2 (an action is a per-step end-effector delta, a velocity; its second difference is the jerk)."""
    a = np.asarray(actions, np.float64)[:, MOTION]
    return [float(np.linalg.norm(a[t + 1] - 2 * a[t] + a[t - 1])) for row in trace
            if row.get("replanned") and not row.get("idle") and 0 < (t := row["t"]) < len(a) - 1]


def _rate(env: Any) -> float | None:
    try:
        return control_hz(env)
    except ValueError:
        return None


def run_episode(env: Any, policy: Any, executor: BaseExecutor, seed: int | None = None,
                max_steps: int | None = None, keep_episode: bool = False,
                reset_options: dict | None = None, execution: ExecutionConfig | None = None,
                latency: Latency | str = "0") -> EpisodeResult:
    """Run one episode of ``env`` with ``policy`` acting through ``executor``; the executor's trace and
    plan events come back with the outcome. ``keep_episode`` also returns the recorded Episode (for
    rollout datasets that teach the value head what failure looks like).

    With ``execution`` (``SyncConfig`` or ``AsyncConfig``) every query crosses a link with ``latency``
    (``MEAN[:JITTER]`` ms drawn from the episode's seed, or ``real``: measured on the wall clock) while the
    env keeps stepping (:mod:`pivla.control.asynchronous`); without it the executor calls the policy directly."""
    hz = _rate(env)
    if execution is None:
        actor: Any = ExecutorActor(policy, executor)
    else:
        latency = parse_latency(latency) if isinstance(latency, str) else latency
        actor = LinkActor(policy, executor, execution, latency, control_hz(env))
    try:
        ep = _run_actor_episode(env, actor, seed, max_steps, reset_options, frames=keep_episode)
    finally:
        if execution is not None:
            actor.close()
    driven = actor.executor
    linked = execution is not None
    return EpisodeResult(
        success=bool(ep.success), steps=len(ep), executor=driven.name,
        trace=actor.rows() if linked else list(driven.trace), plans=list(driven.plans),
        step_times=list(actor.step_times), seed=seed, stage_progress=ep.meta.get("stage_progress"),
        queries=driven.queries, episode=ep if keep_episode else None, control_hz=hz, actions=ep.actions,
        faults=actor.faults() if linked else {}, delays=list(actor.link.stats.delays) if linked else [],
    )
