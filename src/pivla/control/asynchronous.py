"""Execution modes: how an executor's queries, their latency and its chunks share the control loop.

Every query goes through a link (:mod:`pivla.control.latency`): sent with the observation of step s, its chunk
is usable from step s + d.

- ``sync`` (:class:`SyncConfig`): today's loop. The executor queries when its algorithm says so and nothing
  else happens until the chunk is there: the arm holds pose (zero motion, gripper as it was) for the d steps,
  then the chunk starts at its first action, as if it had come at once (the arm did not move meanwhile).
  The executors run unchanged; at zero latency the episode is today's, step for step.
- ``async`` (:class:`AsyncConfig`): the next query is sent while the current chunk still executes, when
  ``threshold`` actions of the current plan remain (LeRobot's ``chunk_size_threshold``, counted in actions;
  ``auto`` below) and, for AURD, when U and V cut the plan. A chunk sent at step s and arriving at step t
  starts with its action t - s: the actions for the steps that passed are skipped. At most one query is in
  flight.

A chunk's executor horizon counts from the first action it executes (fixed: ``horizon``; AdaHorizon: its
choice on the chunk's remaining U_act; AURD: H) and is never exceeded: a plan that runs out before the next
chunk arrives holds pose (an idle step), so a lost link stops the arm instead of running the old chunk on.

The seam (``seam``): ``switch`` (the default) executes the new chunk's due action at once; ``align`` does too and,
for end-effector deltas, adds to its first ``blend_steps`` actions equal shares of the motion it planned for the
skipped steps minus the motion commanded over them (joint targets need nothing, they are the chunk's path;
actions of unknown kind are left as they are); ``blend`` mixes its first
``blend_steps`` actions linearly with what the old chunk still had for those steps (old weight (b - i) / (b + 1)
at the i-th step after the seam, i = 0..b-1; the gripper always the new chunk's), as far as the old chunk's
horizon reaches.

Chunks that are not executed: one that arrives when the episode has moved past all of its actions is dropped
and counted (``stale``); an answer that is not for the query in flight (another observation) is never
executed and counted (``out_of_order``); a query the link lost is counted (``failed``) and sent again at
the next trigger.

The threshold ``auto`` (the default) is the link's expected delay in control steps (the latency's mean at the
control rate; with ``real`` latency the mean of the measured round trips): at zero latency it is 0 and async
plays the sync episode for every executor; at d steps of delay a query sent with d actions left lands as the
plan runs out.

AURD asynchronously (:class:`AsyncAURDExecutor`) makes the synchronous AURD's decisions with the next plan's
query sent ahead: each step of the current plan is tested as synchronously (U from U_act and U_pred, V,
``tau_low`` / ``tau_high`` / ``v_thresh``; U_pred 0 at the plan's first executed step); an untrusted first step
of a plan made from this very observation is a pause; any other untrusted step is a cut ("replan", "prune")
that sends a query from this observation (unless one is in flight) whose chunk replaces the rest of the plan the
moment it arrives (or takes a newer chunk already waiting); the untrusted steps execute while it is in flight,
none at zero latency. A chunk sent on the threshold instead waits until the current plan completes. The plan
made after a cut runs unchecked (``commit_after_cut``). Only ``check="before"``.

An arm on absolute targets (joint positions) holds the present pose its observation reports until its first
chunk arrives, as a synchronous one does; one whose observation does not report it has no hold command before
its first action, and the loop waits for the episode's first answer instead (the arm has not moved).

ACT ensembling asynchronously: a query whenever none is in flight; each step averages every arrived chunk's
prediction for that step (chunks indexed from the step they were sent), or holds when none reaches it.

Why one ~700-line module: the async fixed horizon, async AURD and the runner share the link's arrival
bookkeeping (pending, ready, stale and out-of-order chunks), which a split would pass across modules.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass
from enum import StrEnum
from typing import Any, ClassVar, Literal

import numpy as np

from pivla.control.contract import ACTION_PREFIX, ChunkPolicy
from pivla.control.executors import (
    AURDSettings,
    BaseExecutor,
    ExecutorConfig,
    Plan,
    _choice,
    make_executor,
)
from pivla.control.latency import Arrival, Latency, make_link
from pivla.control.math import (
    Event,
    adahorizon,
    combine_uncertainty,
    temporal_ensemble,
)
from pivla.data.action_space import ActionKind

MOTION = slice(0, 6)  # the end-effector dims of an action: blended at seams and differenced for jerk


@dataclass
class SyncConfig:
    """Query, wait, execute: the arm holds pose while a query is in flight, then the chunk starts at its first
    action (the executors' own loop; at zero latency exactly today's episodes)."""

    kind: ClassVar[str] = "sync"


AUTO = "auto"


@dataclass
class AsyncConfig:
    """Send the next query while the current chunk executes; a chunk that arrives skips the actions of the
    steps that passed (docs/latency.md)."""

    kind: ClassVar[str] = "async"
    threshold: int | Literal["auto"] = AUTO
    """Send the next query when this many actions of the current plan remain (LeRobot's chunk_size_threshold,
    in actions); auto: the expected delay in control steps (the latency's mean at the control rate; measured
    round trips with --latency-ms real), so that at 0 ms async is sync and the new chunk lands as the old one
    runs out. AURD also sends when its test cuts the plan."""
    seam: Literal["switch", "align", "blend"] = "switch"
    """How a new chunk takes over: switch (its due action at once); align (the same, and with end-effector deltas
    its first blend_steps actions also make up the difference between the motion it planned for the steps it
    skipped and the motion commanded meanwhile, so an arm whose deltas add up to its path follows the path the
    chunk planned from its observation: the twin, not LIBERO's controller; docs/latency.md); or blend (its first
    blend_steps actions mixed linearly with the old chunk's)."""
    blend_steps: int = 2
    """blend: steps over which the old chunk's weight falls linearly to 0; align: steps the difference is spread
    over."""
    prefix: bool = True
    """Tell a policy that reads actions in flight (``PolicySpec.action_prefix`` > 0) the current plan's actions it
    expects to execute before the answer takes over, so that the answer plans what follows them (fixed,
    AdaHorizon and AURD; ensembling averages chunks instead). No effect on other policies."""


ExecutionConfig = _choice(SyncConfig) | _choice(AsyncConfig)


def check_execution(execution: ExecutionConfig, executor: ExecutorConfig) -> None:
    """A ValueError naming the problem with an execution mode for an executor (before any episode runs)."""
    if execution.kind != "async":
        return
    g = execution.threshold
    if g != AUTO and (isinstance(g, bool) or not isinstance(g, int) or g < 0):
        raise ValueError(f"execution.threshold must be 'auto' or a number of actions >= 0, got {g!r}")
    if execution.seam not in ("align", "switch", "blend"):
        raise ValueError(f"execution.seam must be 'align', 'switch' or 'blend', got {execution.seam!r}")
    if execution.blend_steps < 1:
        raise ValueError(f"execution.blend_steps must be >= 1, got {execution.blend_steps}")
    if executor.kind == "aurd" and executor.check != "before":
        raise ValueError("asynchronous AURD tests each step before it executes: use check='before'")


class Sent(StrEnum):
    """Why a query went out (a trace row's ``sent``): the threshold, or the AURD test that cut the plan."""

    THRESHOLD = "threshold"
    REPLAN = Event.REPLAN.value
    PRUNE = Event.PRUNE.value


class Dropped(StrEnum):
    """An answer that was not executed (a trace row's ``dropped``)."""

    STALE = "stale"  # the episode had moved past all its actions
    OUT_OF_ORDER = "out_of_order"  # not the answer to the query in flight
    FAILED = "failed"  # the link lost the query


@dataclass(frozen=True)
class _Cut:
    """AURD's test that did not trust a step: its event (REPLAN or PRUNE), U and V."""

    event: Event
    u: float
    v: float


@dataclass
class _Query:
    id: int
    sent: int  # control step whose observation it carries
    cut: _Cut | None = None  # AURD: the test that sent it or waits for it; its chunk replaces the plan on arrival


@dataclass
class _Chunk:
    """An answer in execution; plan step ``start + k`` is its k-th executed action."""

    plan: Plan
    id: int
    sent: int  # control step whose observation it answers
    start: int  # actions skipped: they were due while it was in flight
    stop: int  # plan steps before this one are executable (its executor horizon)
    event: Event = Event.COMPLETE  # how it ends when it reaches ``stop`` (AdaHorizon's choice)
    committed: bool = False  # AURD: made after a cut, runs unchecked
    k: int = 0

    @property
    def step(self) -> int:
        return self.start + self.k

    @property
    def remaining(self) -> int:
        return self.stop - self.step


@dataclass(frozen=True)
class _Test:
    """AURD's test of the step about to execute: its U_pred, U and V, and the event it raises (None: trusted, or
    the plan is committed)."""

    u_pred: float
    u: float
    v: float
    event: Event | None


class AsyncExecutor(BaseExecutor):
    """fixed or AdaHorizon with the next query in flight while the current chunk executes (module docstring):
    a query goes out when ``threshold`` actions remain, and its chunk takes over the moment it arrives."""

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
        self._ready: tuple[Arrival, _Query] | None = None  # arrived, not executing yet
        self._blend = np.zeros((0, 7), np.float32)
        self._settings: Any = None
        self._prefix_max = 0  # actions in flight the policy reads (set at the episode's first step)
        self.stale = self.out_of_order = 0
        self._row: dict[str, Any] = {}
        # seam="align" on end-effector deltas: the motion commanded over the last K steps (set at the first step;
        # a chunk that skips K actions or more is stale)
        self._moved: deque[np.ndarray] | None = None
        self._align = np.zeros((0, 6), np.float32)

    def _setup(self, policy: ChunkPolicy) -> Any:
        return self.inner._thresholds(policy) if self.cfg.kind == "adahorizon" else ()

    def _start_episode(self, policy: ChunkPolicy) -> None:
        """At an episode's first step: the executor's settings, and the motion record the align seam needs."""
        self._settings = self._setup(policy)
        self._prefix_max = policy.spec.action_prefix if self.execution.prefix else 0
        if self.execution.seam == "align" and policy.spec.action_space.kind is ActionKind.EE_DELTA:
            self._moved = deque(maxlen=policy.spec.chunk)

    def threshold(self) -> int:
        """Actions left in the current plan when the next query goes out (``auto``: the link's expected delay)."""
        g = self.execution.threshold
        return self.link.expected_delay_steps() if g == AUTO else int(g)

    def act(self, policy: ChunkPolicy, obs: dict) -> np.ndarray:
        if self._settings is None:
            self._start_episode(policy)
        t, self._row = self.t, {}
        self._receive(t)
        self._take_over(t)
        if self._due():
            self._send(obs, t, None)
        self._await_first_chunk(policy, obs, t)
        return self._execute(policy, obs, t, self._signals(policy, obs, t))

    # -- queries and arrivals --------------------------------------------------------------------------
    def _remaining(self) -> int:
        return 0 if self._chunk is None else max(self._chunk.remaining, 0)

    def _due(self) -> bool:
        """The threshold's query: none in flight or waiting, and at most ``threshold`` actions left."""
        return self._pending is None and self._ready is None and self._remaining() <= self.threshold()

    def _send(self, obs: dict, t: int, cut: _Cut | None) -> None:
        self._pending = _Query(self.link.send(self._with_prefix(obs, cut), t), t, cut)
        self.queries += 1
        self._row["sent"] = Sent(cut.event.value) if cut else Sent.THRESHOLD
        self._receive(t)  # at zero latency the chunk is here at once
        self._take_over(t)

    def _with_prefix(self, obs: dict, cut: _Cut | None) -> dict:
        """``obs`` with the actions in flight (``ACTION_PREFIX``): the current plan's next actions, as many as are
        expected to execute before the answer takes over (at most the policy's P), when the policy reads them."""
        n = min(self._prefix_max, self._before_takeover(cut))
        if n <= 0:
            return obs
        c = self._chunk
        return {**obs, ACTION_PREFIX: c.plan.actions[c.step: c.step + n]}

    def _before_takeover(self, cut: _Cut | None) -> int:
        """Actions of the current plan expected to execute before the answer to a query sent now takes over: it
        takes over on arrival, after the link's expected delay."""
        return min(self._remaining(), self.link.expected_delay_steps())

    def _receive(self, t: int) -> None:
        for arrival in self.link.arrivals(t):
            self._accept(arrival)

    def _accept(self, arrival: Arrival) -> None:
        query = self._pending
        if query is None or arrival.id != query.id:  # not the observation in flight: never executed
            self.out_of_order += 1
            self._row.setdefault("dropped", []).append(Dropped.OUT_OF_ORDER)
            return
        self._pending = None
        if arrival.output is None:  # the link lost it (counted by the link); the next trigger sends again
            self._row.setdefault("dropped", []).append(Dropped.FAILED)
            return
        self._ready = (arrival, query)

    def _await_first_chunk(self, policy: ChunkPolicy, obs: dict, t: int) -> None:
        """An arm on absolute targets (joint positions) whose observation does not report its present pose has
        no hold command before its first action: until the first chunk is there the loop waits for it instead
        (the arm has not moved), and it starts at its first action. A first answer the link lost leaves nothing
        to hold: ConnectionError."""
        if self.can_hold(policy.spec, obs):
            return
        while self._chunk is None and self._pending is not None:
            self._accept(self.link.wait(self._pending.id))
            self._take_over(t)
        if self._chunk is None:
            raise ConnectionError("the policy's first answer was lost, and an arm on absolute targets has no pose "
                                  "to hold before its first action")

    def _take_over(self, t: int) -> None:
        """fixed and AdaHorizon: an answer takes over the moment it arrives."""
        if self._ready is not None:
            self._switch(t)

    def _switch(self, t: int) -> None:
        """The waiting answer becomes the current chunk, at the action due now (or is dropped as stale)."""
        arrival, query = self._ready
        self._ready = None
        plan = Plan.from_output(arrival.output)
        start = t - query.sent
        if start >= len(plan.actions):
            self.stale += 1
            self._row.setdefault("dropped", []).append(Dropped.STALE)
            return
        old = self._chunk
        ended = None
        if old is not None:
            ended = query.cut.event if query.cut else (old.event if old.remaining <= 0 else Event.SWITCH)
            self.plans.append((old.k, ended))
            if self.execution.seam == "blend":
                self._blend = old.plan.actions[old.step:old.stop][: self.execution.blend_steps]
        if self._moved is not None:
            self._align = self._realign(plan, start)
        stop, event = self._horizon(plan, start)
        self._chunk = _Chunk(plan, query.id, query.sent, start, stop, event, self._commits())
        self._row.update(replanned=True, ended=ended, offset=start)
        if query.cut:
            self._row.update(ended_u=query.cut.u, ended_v=query.cut.v)

    def _emit(self, action: np.ndarray, **row: Any) -> np.ndarray:
        if self._moved is not None:
            self._moved.append(np.asarray(action[MOTION], np.float32))
        return super()._emit(action, **row)

    def _realign(self, plan: Plan, start: int) -> np.ndarray:
        """seam="align": per executed step of the new chunk's first blend_steps, its share of the motion the chunk
        planned for the ``start`` steps it skipped minus the motion commanded over those steps (end-effector
        deltas add up to the path, so the arm ends up where the chunk planned to be after them)."""
        if start == 0:
            return np.zeros((0, 6), np.float32)
        executed = np.sum(list(self._moved)[-start:], axis=0) if self._moved else np.zeros(6, np.float32)
        missing = plan.actions[:start, MOTION].sum(0) - executed
        b = self.execution.blend_steps
        return np.repeat((missing / b)[None].astype(np.float32), b, axis=0)

    def _commits(self) -> bool:
        """Whether the chunk taking over now runs unchecked (AURD's commit after a cut)."""
        return False

    def _horizon(self, plan: Plan, start: int) -> tuple[int, Event]:
        """The plan step this chunk stops before, counted from its first executed action, and how it ends."""
        left = len(plan.actions) - start
        if self.cfg.kind == "adahorizon":
            h, event = adahorizon(plan.u_act[start:], self.cfg.min_exec, *self._settings)
            return start + h, event
        return start + min(self._nominal_horizon(), left), Event.COMPLETE

    def _nominal_horizon(self) -> int:
        return self.cfg.horizon

    # -- the action -------------------------------------------------------------------------------------
    def _signals(self, policy: ChunkPolicy, obs: dict, t: int) -> dict[str, Any]:
        """A baseline's monitored U_pred and U of the step about to execute (trace only)."""
        c = self._chunk
        if c is None or c.remaining <= 0:
            return {}
        j = c.step
        return self._monitored(policy, obs, None if j == 0 else c.plan.latents[j - 1], c.plan.u_act[j])

    def _execute(self, policy: ChunkPolicy, obs: dict, t: int, signals: dict[str, Any]) -> np.ndarray:
        c = self._chunk
        row = self._row
        if c is None or c.remaining <= 0:
            return self._emit(self.hold_action(policy.spec, obs), idle=True, **row)
        j = c.step
        action = c.plan.actions[j].copy()
        if c.k < len(self._blend):
            w = (c.k + 1) / (self.execution.blend_steps + 1)
            action[MOTION] = (1 - w) * self._blend[c.k][MOTION] + w * action[MOTION]
        if c.k < len(self._align):
            action[MOTION] += self._align[c.k]
        c.k += 1
        if c.k >= len(self._blend):
            self._blend = self._blend[:0]
        row.setdefault("replanned", False)
        row.setdefault("ended", None)
        extra = {"h_exec": c.stop - c.start} if self.cfg.kind == "adahorizon" else {}
        return self._emit(action, plan_step=j, u_act=c.plan.u_act[j], **signals, v=c.plan.value(j), chunk=c.id,
                          **extra, **row)


class AsyncAURDExecutor(AsyncExecutor):
    """AURD as the trigger of asynchronous execution: the synchronous AURD's decisions with the query for the next
    plan sent ``threshold`` actions before the current one completes (module docstring). At zero latency with
    ``threshold="auto"`` (0) every decision, action and trace field of the synchronous AURD is reproduced."""

    def reset(self) -> None:
        super().reset()
        self._pauses = 0
        self._z: tuple[int, np.ndarray] | None = None  # this step's observed latent, encoded once
        self._tested: tuple[tuple[int, int, int], _Test] | None = None  # (step, chunk, plan step) -> its test

    def _setup(self, policy: ChunkPolicy) -> AURDSettings:
        return AURDSettings.of(self.cfg, policy)

    def _nominal_horizon(self) -> int:
        return self._settings.horizon

    def act(self, policy: ChunkPolicy, obs: dict) -> np.ndarray:
        """One control step:

        1. an answer that arrived takes over when its query was sent on a cut (the rest of the current plan is
           dropped), or when the current plan has run its horizon; otherwise it waits;
        2. test the current plan's step about to execute, as the synchronous AURD does (U_pred = 0 at the plan's
           first executed step; a committed plan runs unchecked);
        3. trusted: send the threshold's query when it is due (at zero latency it arrives and takes over at once:
           back to 2 for the new plan's step);
        4. untrusted at the first step of a plan made from this very observation: PAUSE, hold pose one step (the
           same query would return the same chunk; the next step queries), or FORCED after ``max_pauses``;
        5. untrusted otherwise, a cut (REPLAN or PRUNE): a newer chunk already waiting takes over now; else the
           query in flight, or a new one from this observation, will replace the rest of the plan on arrival
           (at zero latency at once: back to 2); its untrusted steps execute meanwhile, within its horizon."""
        if self._settings is None:
            self._start_episode(policy)
        t, self._row = self.t, {}
        self._receive(t)
        if self._chunk is None and self._pending is None and self._ready is None:
            self._send(obs, t, None)
        self._await_first_chunk(policy, obs, t)
        while True:
            self._take_over(t)
            test = self._test(policy, obs, t)
            chunk = self._chunk
            if test is None or test.event is None:
                if not self._due():
                    break
                self._send(obs, t, None)
                if self._chunk is chunk:
                    break
                continue
            if chunk.k == 0 and chunk.sent == t:
                if self._pauses < self.cfg.max_pauses and self.can_hold(policy.spec, obs):
                    return self._pause(policy, obs, test)
                break  # FORCED
            cut = _Cut(test.event, test.u, test.v)
            self._row.update(cut=cut.event, cut_u=cut.u, cut_v=cut.v)
            if self._ready is not None:
                self._ready[1].cut = cut
            elif self._pending is not None:
                self._pending.cut = self._pending.cut or cut
                break
            else:
                self._send(obs, t, cut)
                if self._chunk is chunk:
                    break
        return self._execute(policy, obs, t, self._signals(policy, obs, t))

    def _before_takeover(self, cut: _Cut | None) -> int:
        """A threshold's answer waits for the current plan to complete; a cut's takes over on arrival."""
        return self._remaining() if cut is None else super()._before_takeover(cut)

    def _take_over(self, t: int) -> None:
        if self._ready is None:
            return
        if self._ready[1].cut is not None or self._remaining() == 0:
            self._switch(t)

    def _commits(self) -> bool:
        """The plan made right after a cut (the plan log's last entry is not COMPLETE) runs unchecked."""
        return self.cfg.commit_after_cut and bool(self.plans) and self.plans[-1][1] != Event.COMPLETE

    def _pause(self, policy: ChunkPolicy, obs: dict, test: _Test) -> np.ndarray:
        """Hold pose one step instead of a plan's untrusted first step; the plan ends (PAUSE, H_exec = 0)."""
        c = self._chunk
        self._pauses += 1
        self.plans.append((c.k, Event.PAUSE))
        self._chunk = None
        row = self._row
        return self._emit(self.hold_action(policy.spec, obs), plan_step=c.step,
                          replanned=row.pop("replanned", False), u_act=c.plan.u_act[c.step], u_pred=test.u_pred,
                          u=test.u, v=test.v, event=Event.PAUSE, ended=row.pop("ended", None), committed=False,
                          chunk=c.id, **row)

    def _encoded(self, policy: ChunkPolicy, obs: dict, t: int, monitoring: bool) -> np.ndarray:
        if self._z is None or self._z[0] != t:
            if monitoring:
                with self._monitoring():
                    self._z = (t, policy.encode(obs))
            else:
                self._z = (t, policy.encode(obs))
        return self._z[1]

    def _test(self, policy: ChunkPolicy, obs: dict, t: int) -> _Test | None:
        """AURD's test of the current plan's step about to execute (None: no step to execute). U_pred compares
        this observation with the plan's prediction of it, from the plan's second executed step on (before that
        the plan's own actions have had no outcome yet: 0, as the synchronous AURD's step 0)."""
        c = self._chunk
        if c is None or c.remaining <= 0:
            return None
        key = (t, c.id, c.step)
        if self._tested is not None and self._tested[0] == key:
            return self._tested[1]  # tested once: U_pred's episode floor moves with every measurement
        s, j = self._settings, c.step
        u_pred = 0.0
        if c.k > 0 and (not c.committed or self.monitor):
            z = self._encoded(policy, obs, t, monitoring=c.committed)
            u_pred = self._u_pred(z, c.plan.latents[j - 1], s.pred_baseline)
        u, v = combine_uncertainty(float(c.plan.u_act[j]), u_pred, s.eta), c.plan.value(j)
        test = _Test(u_pred, u, v, None if c.committed else s.test(u, v))
        self._tested = (key, test)
        return test

    def _signals(self, policy: ChunkPolicy, obs: dict, t: int) -> dict[str, Any]:
        test = self._test(policy, obs, t)
        if test is None:
            return {}
        c = self._chunk
        forced = test.event is not None and c.k == 0 and c.sent == t  # step 4 after max_pauses
        self._pauses = 0
        return {"u_pred": test.u_pred, "u": test.u, "event": Event.FORCED if forced else None,
                "committed": c.committed}


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
            self._accept(arrival, t)

    def _accept(self, arrival: Arrival, t: int) -> None:
        query = self._pending
        if query is None or arrival.id != query.id:
            self.out_of_order += 1
            self._row.setdefault("dropped", []).append(Dropped.OUT_OF_ORDER)
            return
        self._pending = None
        if arrival.output is None:
            self._row.setdefault("dropped", []).append(Dropped.FAILED)
            return
        plan = Plan.from_output(arrival.output)
        if t - query.sent >= len(plan.actions):
            self.stale += 1
            self._row.setdefault("dropped", []).append(Dropped.STALE)
            return
        self._history.append((query.sent, query.id, plan))
        self.plans.append((1, Event.COMPLETE))
        self._row.update(replanned=True, offset=t - query.sent)

    def act(self, policy: ChunkPolicy, obs: dict) -> np.ndarray:
        t, self._row = self.t, {}
        self._receive(t)
        if self._pending is None:
            self._pending = _Query(self.link.send(obs, t), t)
            self.queries += 1
            self._row["sent"] = Sent.THRESHOLD
            self._receive(t)
        if not self._history and not self.can_hold(policy.spec, obs):
            while not self._history and self._pending is not None:  # nothing to hold yet: wait (see AsyncExecutor)
                self._accept(self.link.wait(self._pending.id), t)
            if not self._history:
                raise ConnectionError("the policy's first answer was lost, and an arm on absolute targets has no "
                                      "pose to hold before its first action")
        self._history = [h for h in self._history if t - h[0] < len(h[2].actions)]
        row = self._row
        if not self._history:
            return self._emit(self.hold_action(policy.spec, obs), idle=True, **row)
        preds = np.stack([plan.normalized[t - sent] for sent, _, plan in self._history])
        action = policy.to_actions(temporal_ensemble(preds, self.cfg.m).astype(np.float32))
        sent, qid, newest = self._history[-1]
        earlier = [(s, p) for s, _, p in self._history if s < t]  # the newest of these predicted this observation
        predicted = earlier[-1][1].latents[t - earlier[-1][0] - 1] if earlier else None
        signals = self._monitored(policy, obs, predicted, newest.u_act[t - sent])
        row.setdefault("replanned", False)
        return self._emit(action, plan_step=t - sent, u_act=newest.u_act[t - sent], **signals,
                          v=newest.value(t - sent), chunk=qid, n_ensembled=len(preds), **row)


_ASYNC_CLASSES: dict[str, type[BaseExecutor]] = {
    "aurd": AsyncAURDExecutor, "fixed": AsyncExecutor, "adahorizon": AsyncExecutor, "ensemble": AsyncEnsembleExecutor,
}


def make_async_executor(cfg: ExecutorConfig, execution: AsyncConfig) -> BaseExecutor:
    check_execution(execution, cfg)
    return _ASYNC_CLASSES[cfg.kind](cfg, execution)


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
                return self._idle(t, obs)
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
            return self._idle(t, obs)
        self.trace.append(row)
        return action

    def _timed(self, step: Any) -> np.ndarray:
        start, monitoring = time.perf_counter(), self.executor.monitor_s
        action = step()
        self.step_times.append(time.perf_counter() - start - (self.executor.monitor_s - monitoring))
        return action

    def _idle(self, t: int, obs: dict) -> np.ndarray:
        """Hold pose while the chunk is in flight, as after the action before the query (``ActionSpace.hold``);
        before an episode's first action an arm on absolute targets holds where it is (``present_pose``)."""
        self.trace.append({"t": t, "idle": True})
        spec = self.policy.spec
        last = self._before if self._before is not None else spec.present_pose(obs)
        return np.asarray(spec.action_space.hold(last), np.float32)

    def rows(self) -> list[dict]:
        return list(self.executor.trace if self.execution.kind == "async" else self.trace)

    def faults(self) -> dict[str, int]:
        return {"stale_chunks": getattr(self.executor, "stale", 0),
                "out_of_order_chunks": getattr(self.executor, "out_of_order", 0),
                "failed_queries": self.link.stats.failed}
