"""Execution modes: how an executor's queries, their latency and its chunks share the control loop.

Every query goes through a link (:mod:`pivla.control.latency`): sent with the observation of step s, its chunk
is usable from step s + d.

- ``sync`` (:class:`SyncConfig`): today's loop. The executor queries when its algorithm says so and nothing
  else happens until the chunk is there: the arm holds pose (zero motion, gripper as it was) for the d steps,
  then the chunk starts at its first action, as if it had come at once (the arm did not move meanwhile).
  The executors run unchanged; at zero latency the episode is today's, step for step.
- ``async`` (:class:`AsyncConfig`): the next query is sent while the current chunk still executes, when
  ``threshold`` actions of the current plan remain (LeRobot's ``chunk_size_threshold``, counted in actions)
  and, for AURD, when U and V cut the plan. A chunk sent at step s and arriving at step t starts with its
  action t - s: the actions for the steps that passed are skipped. At most one query is in flight.

A chunk's executor horizon counts from the first action it executes (fixed: ``horizon``; AdaHorizon: its
choice on the chunk's remaining U_act; AURD: H) and is never exceeded: a plan that runs out before the next
chunk arrives holds pose (an idle step), so a lost link stops the arm instead of running the old chunk on.

The seam (``seam``): ``switch`` executes the new chunk's due action at once; ``blend`` mixes its first
``blend_steps`` actions linearly with what the old chunk still had for those steps (old weight
(b - i) / (b + 1) at the i-th step after the seam, i = 0..b-1; the gripper always the new chunk's), as far as
the old chunk's horizon reaches.

Chunks that are not executed: one that arrives when the episode has moved past all of its actions is dropped
and counted (``stale``); an answer that is not for the query in flight (another observation) is never
executed and counted (``out_of_order``); a query the link lost is counted (``failed``) and sent again at
the next trigger.

AURD asynchronously: each step of the current plan is tested as in the synchronous AURD (U from U_act and
U_pred, V, ``tau_low`` / ``tau_high`` / ``v_thresh``), except a chunk's first step when it answers this very
step's observation (U_pred is 0 and the same query would return the same chunk). A test that cuts the plan
("replan", "prune") sends a query from this observation and marks it to replace the rest of the plan the
moment it arrives (or takes a newer chunk already waiting); the untrusted steps execute while it is in
flight, none at zero latency. A chunk sent on the threshold instead waits until the current plan completes.
The plan made after a cut runs unchecked (``commit_after_cut``). There are no pauses and only
``check="before"``.

ACT ensembling asynchronously: a query whenever none is in flight; each step averages every arrived chunk's
prediction for that step (chunks indexed from the step they were sent), or holds when none reaches it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import numpy as np

from pivla.control.contract import ChunkPolicy
from pivla.control.executors import (
    BaseExecutor,
    ExecutorConfig,
    Plan,
    _choice,
    make_executor,
)
from pivla.control.latency import Arrival, Latency, make_link
from pivla.control.math import (
    adahorizon,
    combine_uncertainty,
    step_event,
    temporal_ensemble,
)

MOTION = slice(0, 6)  # the end-effector dims of an action: blended at seams and differenced for jerk


@dataclass
class SyncConfig:
    """Query, wait, execute: the arm holds pose while a query is in flight, then the chunk starts at its first
    action (the executors' own loop; at zero latency exactly today's episodes)."""

    kind: ClassVar[str] = "sync"


@dataclass
class AsyncConfig:
    """Send the next query while the current chunk executes; a chunk that arrives skips the actions of the
    steps that passed (docs/latency.md)."""

    kind: ClassVar[str] = "async"
    threshold: int = 2
    """Send the next query when this many actions of the current plan remain (LeRobot's chunk_size_threshold,
    in actions); AURD also sends when U and V cut its plan."""
    seam: Literal["switch", "blend"] = "switch"
    """How a new chunk takes over: switch (its due action at once), or blend (its first blend_steps actions
    mixed linearly with the old chunk's)."""
    blend_steps: int = 2
    """blend: steps over which the old chunk's weight falls linearly to 0."""


ExecutionConfig = _choice(SyncConfig) | _choice(AsyncConfig)


def check_execution(execution: ExecutionConfig, executor: ExecutorConfig) -> None:
    """A ValueError naming the problem with an execution mode for an executor (before any episode runs)."""
    if execution.kind != "async":
        return
    if execution.threshold < 0:
        raise ValueError(f"execution.threshold must be >= 0 actions, got {execution.threshold}")
    if execution.seam not in ("switch", "blend"):
        raise ValueError(f"execution.seam must be 'switch' or 'blend', got {execution.seam!r}")
    if execution.blend_steps < 1:
        raise ValueError(f"execution.blend_steps must be >= 1, got {execution.blend_steps}")
    if executor.kind == "aurd" and executor.check != "before":
        raise ValueError("asynchronous AURD tests each step before it executes: use check='before'")


@dataclass
class _Query:
    id: int
    sent: int  # control step whose observation it carries
    cut: str | None = None  # AURD: the test that sent it or waits for it; its chunk replaces the plan on arrival


@dataclass
class _Chunk:
    """An answer in execution; plan step ``start + k`` is its k-th executed action."""

    plan: Plan
    id: int
    start: int  # actions skipped: they were due while it was in flight
    stop: int  # plan steps before this one are executable (its executor horizon)
    event: str = "complete"  # how it ends when it reaches ``stop`` (AdaHorizon's choice)
    committed: bool = False  # AURD: made after a cut, runs unchecked
    k: int = 0

    @property
    def step(self) -> int:
        return self.start + self.k

    @property
    def remaining(self) -> int:
        return self.stop - self.step


class AsyncExecutor(BaseExecutor):
    """fixed, AdaHorizon or AURD with the next query in flight while the current chunk executes (module
    docstring). The synchronous executor of the same config supplies the thresholds and U_pred (with its
    episode floor) exactly as it forms them."""

    def __init__(self, cfg: ExecutorConfig, execution: AsyncConfig):
        self.inner = make_executor(cfg)
        self.execution = execution
        self.name = cfg.kind
        self.link: Any = None  # set by the actor for each episode
        super().__init__(cfg)

    def reset(self) -> None:
        super().reset()
        self.inner.reset()
        self._chunk: _Chunk | None = None
        self._pending: _Query | None = None
        self._ready: tuple[Arrival, _Query] | None = None  # AURD: arrived, waiting for the plan to complete
        self._blend = np.zeros((0, 7), np.float32)
        self._settings: tuple | None = None
        self._z: tuple[int, np.ndarray] | None = None  # this step's observed latent, encoded once
        self._tested: tuple[tuple[int, int, int], dict] | None = None  # (step, chunk, plan step) -> its test
        self.stale = self.out_of_order = 0
        self._row: dict[str, Any] = {}

    def _setup(self, policy: ChunkPolicy) -> tuple:
        if self.cfg.kind == "aurd":
            return (*self.inner._thresholds(policy), self.inner._pred_baseline(policy),
                    self.cfg.horizon or policy.spec.horizon)
        if self.cfg.kind == "adahorizon":
            return self.inner._thresholds(policy)
        return ()

    def act(self, policy: ChunkPolicy, obs: dict) -> np.ndarray:
        if self._settings is None:
            self._settings = self._setup(policy)
        t, self._row = self.t, {}
        self._receive(t)
        test = self._test(policy, obs, t)
        cut = test.get("event")
        if cut is not None:
            self._row.update(cut=cut, cut_u=test["u"], cut_v=test["v"])
            if self._ready is not None:  # a newer chunk is already here: it replaces the rest now
                self._switch(t, cut)
            elif self._pending is not None:
                self._pending.cut = self._pending.cut or cut
            else:
                self._send(obs, t, cut)
        elif self._pending is None and self._ready is None and self._remaining() <= self.execution.threshold:
            self._send(obs, t, None)
        return self._execute(policy, obs, t)

    # -- queries and arrivals --------------------------------------------------------------------------
    def _remaining(self) -> int:
        return 0 if self._chunk is None else max(self._chunk.remaining, 0)

    def _send(self, obs: dict, t: int, cut: str | None) -> None:
        self._pending = _Query(self.link.send(obs, t), t, cut)
        self.queries += 1
        self._row["sent"] = cut or "threshold"
        self._receive(t)  # at zero latency the chunk is here at once

    def _receive(self, t: int) -> None:
        for arrival in self.link.arrivals(t):
            query = self._pending
            if query is None or arrival.id != query.id:  # not the observation in flight: never executed
                self.out_of_order += 1
                self._row.setdefault("dropped", []).append("out_of_order")
                continue
            self._pending = None
            if arrival.output is None:  # the link lost it (counted by the link); the next trigger sends again
                self._row.setdefault("dropped", []).append("failed")
                continue
            self._ready = (arrival, query)
        if self._ready is None:
            return
        query = self._ready[1]
        if query.cut is not None or self.cfg.kind != "aurd" or self._remaining() == 0:
            self._switch(t, query.cut)

    def _switch(self, t: int, cut: str | None) -> None:
        """The waiting answer becomes the current chunk, at the action due now (or is dropped as stale)."""
        arrival, query = self._ready
        self._ready = None
        plan = Plan.from_output(arrival.output)
        start = t - query.sent
        if start >= len(plan.actions):
            self.stale += 1
            self._row.setdefault("dropped", []).append("stale")
            return
        old = self._chunk
        ended = None
        if old is not None:
            ended = cut or (old.event if old.remaining <= 0 else "switch")
            self.plans.append((old.k, ended))
            if self.execution.seam == "blend":
                self._blend = old.plan.actions[old.step:old.stop][: self.execution.blend_steps]
        stop, event = self._horizon(plan, start)
        committed = cut is not None and self.cfg.kind == "aurd" and self.cfg.commit_after_cut
        self._chunk = _Chunk(plan, query.id, start, stop, event, committed)
        self._row.update(replanned=True, ended=ended, offset=start)

    def _horizon(self, plan: Plan, start: int) -> tuple[int, str]:
        """The plan step this chunk stops before, counted from its first executed action, and how it ends."""
        left = len(plan.actions) - start
        if self.cfg.kind == "adahorizon":
            h, event = adahorizon(plan.u_act[start:], self.cfg.min_exec, *self._settings)
            return start + h, event
        h = self.cfg.horizon if self.cfg.kind == "fixed" else self._settings[-1]
        return start + min(h, left), "complete"

    # -- AURD's test ------------------------------------------------------------------------------------
    def _encoded(self, policy: ChunkPolicy, obs: dict, t: int, monitoring: bool) -> np.ndarray:
        if self._z is None or self._z[0] != t:
            if monitoring:
                with self._monitoring():
                    self._z = (t, policy.encode(obs))
            else:
                self._z = (t, policy.encode(obs))
        return self._z[1]

    def _test(self, policy: ChunkPolicy, obs: dict, t: int) -> dict[str, Any]:
        """AURD: U_pred, U and V of the step about to execute and, unless its plan is committed or it is the
        first step of an answer to this very observation, the event its test raises."""
        c = self._chunk
        if self.cfg.kind != "aurd" or c is None or c.remaining <= 0:
            return {}
        if self._tested is not None and self._tested[0] == (t, c.id, c.step):
            return self._tested[1]  # tested once: U_pred's episode floor moves with every measurement
        tau_low, tau_high, v_thresh, eta, baseline, _ = self._settings
        j = c.step
        tested = not c.committed and j > 0
        u_pred = 0.0
        if j > 0 and (tested or self.monitor):
            z = self._encoded(policy, obs, t, monitoring=not tested)
            u_pred = self.inner._u_pred(z, c.plan.latents[j - 1], baseline)
        u = combine_uncertainty(float(c.plan.u_act[j]), u_pred, eta)
        v = c.plan.value(j)
        event = step_event(u, v, tau_low, tau_high, v_thresh) if tested else None
        result = {"u_pred": u_pred, "u": u, "v": v, "event": event}
        self._tested = ((t, c.id, j), result)
        return result

    # -- the action -------------------------------------------------------------------------------------
    def _execute(self, policy: ChunkPolicy, obs: dict, t: int) -> np.ndarray:
        c = self._chunk
        row = self._row
        if c is None or c.remaining <= 0:
            return self._emit(self.hold_action(policy.spec.action_space), idle=True, **row)
        j = c.step
        action = c.plan.actions[j].copy()
        if c.k < len(self._blend):
            w = (c.k + 1) / (self.execution.blend_steps + 1)
            action[MOTION] = (1 - w) * self._blend[c.k][MOTION] + w * action[MOTION]
        if self.cfg.kind == "aurd":
            test = self._test(policy, obs, t)  # the executed step's signals (after a switch: the new chunk's)
            signals = {"u_pred": test["u_pred"], "u": test["u"], "committed": c.committed}
        else:
            signals = self._monitored(policy, obs, None if j == 0 else c.plan.latents[j - 1], c.plan.u_act[j])
        c.k += 1
        if c.k >= len(self._blend):
            self._blend = self._blend[:0]
        row.setdefault("replanned", False)
        row.setdefault("ended", None)
        extra = {"h_exec": c.stop - c.start} if self.cfg.kind == "adahorizon" else {}
        return self._emit(action, plan_step=j, u_act=c.plan.u_act[j], **signals, v=c.plan.value(j), chunk=c.id,
                          **extra, **row)


class AsyncEnsembleExecutor(BaseExecutor):
    """ACT temporal ensembling with latency: a query whenever none is in flight; each step averages every
    arrived chunk's prediction for it, chunks indexed from the step they were sent (module docstring)."""

    name = "ensemble"

    def __init__(self, cfg: ExecutorConfig, execution: AsyncConfig):
        self.execution = execution
        self.link: Any = None
        super().__init__(cfg)

    def reset(self) -> None:
        super().reset()
        self._pending: _Query | None = None
        self._history: list[tuple[int, int, Plan]] = []  # (sent step, query id, plan), oldest first
        self.stale = self.out_of_order = 0
        self._row: dict[str, Any] = {}

    def _receive(self, t: int) -> None:
        for arrival in self.link.arrivals(t):
            query = self._pending
            if query is None or arrival.id != query.id:
                self.out_of_order += 1
                self._row.setdefault("dropped", []).append("out_of_order")
                continue
            self._pending = None
            if arrival.output is None:
                self._row.setdefault("dropped", []).append("failed")
                continue
            plan = Plan.from_output(arrival.output)
            if t - query.sent >= len(plan.actions):
                self.stale += 1
                self._row.setdefault("dropped", []).append("stale")
                continue
            self._history.append((query.sent, query.id, plan))
            self.plans.append((1, "complete"))
            self._row.update(replanned=True, offset=t - query.sent)

    def act(self, policy: ChunkPolicy, obs: dict) -> np.ndarray:
        t, self._row = self.t, {}
        self._receive(t)
        if self._pending is None:
            self._pending = _Query(self.link.send(obs, t), t)
            self.queries += 1
            self._row["sent"] = "threshold"
            self._receive(t)
        self._history = [h for h in self._history if t - h[0] < len(h[2].actions)]
        row = self._row
        if not self._history:
            return self._emit(self.hold_action(policy.spec.action_space), idle=True, **row)
        preds = np.stack([plan.normalized[t - sent] for sent, _, plan in self._history])
        action = policy.to_actions(temporal_ensemble(preds, self.cfg.m).astype(np.float32))
        sent, qid, newest = self._history[-1]
        earlier = [(s, p) for s, _, p in self._history if s < t]  # the newest of these predicted this observation
        predicted = earlier[-1][1].latents[t - earlier[-1][0] - 1] if earlier else None
        signals = self._monitored(policy, obs, predicted, newest.u_act[t - sent])
        row.setdefault("replanned", False)
        return self._emit(action, plan_step=t - sent, u_act=newest.u_act[t - sent], **signals,
                          v=newest.value(t - sent), chunk=qid, n_ensembled=len(preds), **row)


def make_async_executor(cfg: ExecutorConfig, execution: AsyncConfig) -> BaseExecutor:
    check_execution(execution, cfg)
    return (AsyncEnsembleExecutor if cfg.kind == "ensemble" else AsyncExecutor)(cfg, execution)


# -- the actors the episode runner calls, one control step per call ------------------------------------------
class _LinkedPolicy:
    """The policy as a synchronous executor sees it: ``infer`` sends through the link and waits for the answer
    (``answer`` says when it came); everything else is the policy's own."""

    def __init__(self, policy: ChunkPolicy, link: Any):
        self.policy, self.link = policy, link
        self.spec, self.calibration = policy.spec, policy.calibration
        self.step = 0
        self.answer: Arrival | None = None

    def infer(self, obs: dict) -> dict[str, np.ndarray]:
        self.answer = self.link.wait(self.link.send(obs, self.step))
        if self.answer.output is None:
            raise ConnectionError(f"policy query lost: {self.answer.error}")
        return self.answer.output

    def encode(self, obs: dict) -> np.ndarray:
        return self.policy.encode(obs)

    def to_actions(self, normalized: np.ndarray) -> np.ndarray:
        return self.policy.to_actions(normalized)


class LinkActor:
    """Runs an executor in an execution mode over a link (simulated or wall-clock latency) for the rollout
    runner: one call per control step, a trace row per control step (``idle`` rows where the arm held pose
    waiting for a chunk), and the control time of each step the executor acted (without trace-only monitoring)."""

    source = "policy"

    def __init__(self, policy: ChunkPolicy, executor: BaseExecutor, execution: ExecutionConfig, latency: Latency,
                 hz: float):
        self.policy, self.execution, self.latency, self.hz = policy, execution, latency, hz
        self.executor = executor if execution.kind == "sync" else make_async_executor(executor.cfg, execution)
        self.link: Any = None  # one per episode, seeded with it (reset)
        self.step, self.step_times, self.trace = 0, [], []

    def reset(self, env: Any = None, seed: int | None = None) -> None:
        self.close()
        self.link = make_link(self.policy, self.latency, self.hz, seed)
        self.executor.reset()
        if self.execution.kind == "async":
            self.executor.link = self.link
        self.linked = _LinkedPolicy(self.policy, self.link)
        self.step, self.step_times, self.trace = 0, [], []
        self._held: tuple[np.ndarray, dict, int] | None = None  # sync: the action due when its chunk arrives
        self._before: np.ndarray | None = None  # sync: the last action before the query in flight

    def close(self) -> None:
        if self.link is not None:
            self.link.close()

    def __call__(self, obs: dict) -> np.ndarray:
        t = self.step
        self.step += 1
        self.link.pace(t)
        if self.execution.kind == "async":
            return self._timed(lambda: self.executor.act(self.policy, obs))
        if self._held is not None:
            action, row, due = self._held
            if t < due:
                return self._idle(t)
            self._held = None
            self.trace.append({**row, "t": t})
            return action
        before = self.executor.last_action
        self.linked.step, self.linked.answer = t, None
        action = self._timed(lambda: self.executor.act(self.linked, obs))
        row = {**self.executor.trace[-1], "t": t}
        answer = self.linked.answer
        if answer is not None and answer.step > t:
            self._held, self._before = (action, row, answer.step), before
            return self._idle(t)
        self.trace.append(row)
        return action

    def _timed(self, step: Any) -> np.ndarray:
        start, monitoring = time.perf_counter(), self.executor.monitor_s
        action = step()
        self.step_times.append(time.perf_counter() - start - (self.executor.monitor_s - monitoring))
        return action

    def _idle(self, t: int) -> np.ndarray:
        """Hold pose while the chunk is in flight, as after the action before the query (``ActionSpace.hold``)."""
        self.trace.append({"t": t, "idle": True})
        return np.asarray(self.policy.spec.action_space.hold(self._before), np.float32)

    def rows(self) -> list[dict]:
        return list(self.executor.trace if self.execution.kind == "async" else self.trace)

    def faults(self) -> dict[str, int]:
        return {"stale_chunks": getattr(self.executor, "stale", 0),
                "out_of_order_chunks": getattr(self.executor, "out_of_order", 0),
                "failed_queries": self.link.stats.failed}
