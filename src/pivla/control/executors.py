"""Executors turn a chunking policy into one action per control step. All share one interface:

    executor.reset()                       # at the start of an episode
    action = executor.act(policy, obs)     # physical D-dim action for this control step (policy.spec.action_space)

Each executor is built from its typed config (``FixedConfig``, ``EnsembleConfig``, ``AdaHorizonConfig``,
``AURDConfig``; ``make_executor``) and talks to the policy only through the ``ChunkPolicy`` contract. All
write a per-step ``trace`` and a per-plan list ``plans`` of (executed horizon, event). ``aurd`` is
PI-VLA's decider; ``fixed``, ``ensemble`` (ACT temporal ensembling) and ``adahorizon`` (EverydayVLA) are
the baselines.

A trace row has U_act, U_pred, U and V of the executed step, ``replanned`` (the policy was queried at this
step) and ``ended``: on a step that replanned, how the previous plan ended ("complete", "replan", "prune",
"pause"). AURD adds ``event`` ("pause": the step held pose; "forced": executed after ``max_pauses``),
``committed`` (the plan was made right after a cut and runs unchecked) and, where it cut a plan,
``ended_u`` / ``ended_v``: the U and V of the untrusted step it did not execute. The baselines do not
decide on U_pred, but with ``monitor`` (default) they encode each new observation like AURD does so that
their traces carry the same U: what AURD would have seen in their episodes (failure
prediction, "why AURD does not help"). Monitoring never changes an action, and its time is kept apart
(``monitor_s``) so that control rates compare the bare executors.
"""

from __future__ import annotations

import dataclasses
import time
from collections import deque
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from enum import Enum
from typing import Annotated, Any, ClassVar, Literal

import numpy as np
import tyro

from pivla.control.contract import DEFAULT_ETA, ChunkPolicy, PolicySpec
from pivla.control.math import (
    CUTS,
    Event,
    adahorizon,
    combine_uncertainty,
    prediction_uncertainty,
    step_event,
    surprise,
    temporal_ensemble,
)

EVERYDAYVLA_EXTEND_BELOW, EVERYDAYVLA_REPLAN_ABOVE = 0.03, 0.06  # AdaHorizon's constants in its own code


@dataclass
class Plan:
    """One policy query: normalized primary actions, physical actions, and AURD's signals."""

    normalized: np.ndarray  # (K, D)
    actions: np.ndarray  # (K, D) physical
    u_act: np.ndarray  # (K,)
    values: np.ndarray  # (H,)
    latents: np.ndarray  # (K, d_z)

    def value(self, k: int) -> float:
        """V for plan step k (0-based); steps past the value horizon reuse its last entry."""
        return float(self.values[min(k, len(self.values) - 1)])

    @classmethod
    def from_output(cls, out: dict[str, np.ndarray]) -> Plan:
        return cls(
            normalized=out["actions_normalized"],
            actions=out["actions"],
            u_act=out["u_act"],
            values=out["values"],
            latents=out["latents"],
        )


@dataclass
class FixedConfig:
    """Fixed horizon: execute the first ``horizon`` actions of every chunk open loop, then replan."""

    kind: ClassVar[str] = "fixed"
    horizon: int = 5
    """Actions executed per chunk."""
    monitor: bool = True
    """Also encode each new observation for the trace's U_pred and U (never changes an action)."""


@dataclass
class EnsembleConfig:
    """ACT temporal ensembling: query every step, average every live prediction for the current step."""

    kind: ClassVar[str] = "ensemble"
    m: float = 0.01
    """Weights exp(-m * i), i = 0 for the oldest prediction."""
    monitor: bool = True
    """Also encode each new observation for the trace's U_pred and U (never changes an action)."""


@dataclass
class AdaHorizonConfig:
    """EverydayVLA's AdaHorizon: the horizon chosen per chunk from the two heads' disagreement (U_act)."""

    kind: ClassVar[str] = "adahorizon"
    min_exec: int = 4
    """Actions executed at least (unless one of them is untrusted)."""
    extend_below: float | None = None
    """Extend the plan while U_act is below this (default: the calibrated act_low, else EverydayVLA's 0.03)."""
    replan_above: float | None = None
    """Replan at a step whose U_act exceeds this (default: the calibrated act_high, else EverydayVLA's 0.06)."""
    monitor: bool = True
    """Also encode each new observation for the trace's U_pred and U (never changes an action)."""


@dataclass
class AURDConfig:
    """PI-VLA's Active Uncertainty-Resolving Decider (Algorithm 1). Thresholds default to the policy's
    calibration (``pivla calibrate``)."""

    kind: ClassVar[str] = "aurd"
    tau_low: float | None = None
    """Prune in (tau_low, tau_high] when the value is low (default: calibrated)."""
    tau_high: float | None = None
    """Replan above this U (default: calibrated)."""
    v_thresh: float | None = None
    """A value below this makes a step in the band untrusted (default: calibrated)."""
    eta: float | None = None
    """Weight of U_act in U, Eq. 14 (default: calibrated, else 0.7)."""
    check: Literal["before", "after"] = "before"
    """Test step k before executing it (docs/method.md), or after (the paper's literal order; never pauses)."""
    horizon: int | None = None
    """Nominal horizon (default: the policy's H)."""
    max_pauses: int = 3
    """Pauses in a row before the first action is executed anyway (a static scene cannot stall the robot)."""
    pred_baseline: Literal["none", "episode"] | None = None
    """episode: U_pred above the episode's floor (control.math.surprise); default: as calibrated."""
    commit_after_cut: bool = True
    """The plan made right after a cut runs its nominal horizon unchecked; the plan after it is checked again."""
    monitor: bool = True
    """Encode the observations of committed steps for the trace too (outside the control time)."""


def _choice(cls: type) -> Any:
    """A config as one named choice of ``ExecutorConfig`` (``--executor NAME`` on the command line)."""
    return Annotated[cls, tyro.conf.subcommand(cls.kind)]


ExecutorConfig = _choice(AURDConfig) | _choice(FixedConfig) | _choice(EnsembleConfig) | _choice(AdaHorizonConfig)


class BaseExecutor:
    """State shared by every executor: the trace, the plan log, the step counter and the last action."""

    name = "base"

    def __init__(self, cfg: Any):
        self.cfg = cfg
        self.monitor = cfg.monitor
        self.monitor_s = 0.0  # time spent on monitoring only, excluded from control-step timings
        self.reset()

    def reset(self) -> None:
        self.trace: list[dict] = []
        self.plans: list[tuple[int, Event]] = []
        self.t, self.last_action = 0, None
        self.queries = 0  # policy forward passes, the compute a chunking strategy saves or spends
        self._pred_min: float | None = None

    def act(self, policy: ChunkPolicy, obs: dict) -> np.ndarray:
        raise NotImplementedError

    def _infer(self, policy: ChunkPolicy, obs: dict) -> Any:
        """One policy query, counted."""
        self.queries += 1
        return policy.infer(obs)

    def _emit(self, action: np.ndarray, **row: Any) -> np.ndarray:
        action = np.asarray(action, np.float32)
        self.last_action = action
        self.trace.append({"t": self.t, **{k: _jsonable(v) for k, v in row.items()}})
        self.t += 1
        return action

    def hold_action(self, spec: PolicySpec, obs: Mapping[str, Any]) -> np.ndarray:
        """Hold pose for one control step (``ActionSpace.hold``: zero motion and the gripper as it was for the
        twin's end-effector deltas; the last target for joint positions, or before the first action the present
        pose the observation reports, ``PolicySpec.present_pose``)."""
        last = self.last_action if self.last_action is not None else spec.present_pose(obs)
        return np.asarray(spec.action_space.hold(last), np.float32)

    def can_hold(self, spec: PolicySpec, obs: Mapping[str, Any]) -> bool:
        """Whether ``hold_action`` has a pose to hold: a delta space always does; joint positions after the first
        action, or before it where the observation reports the present pose."""
        return (self.last_action is not None or not spec.action_space.kind.absolute
                or spec.present_pose(obs) is not None)

    def _pred_baseline(self, policy: ChunkPolicy) -> str:
        return getattr(policy.calibration, "pred_baseline", "none") or "none"

    def _eta(self, policy: ChunkPolicy) -> float:
        """Weight of U_act in U: the calibration's, else Eq. 13's default."""
        return policy.calibration.eta if policy.calibration is not None else DEFAULT_ETA

    def _u_pred(self, z_obs: np.ndarray, predicted: np.ndarray, baseline: str) -> float:
        """U_pred of one observation against its prediction, as calibrated (raw, or above the episode's floor)."""
        raw = float(prediction_uncertainty(z_obs, predicted))
        if baseline == "none":
            return raw
        u = surprise(raw, self._pred_min)
        self._pred_min = raw if self._pred_min is None else min(self._pred_min, raw)
        return u

    def _monitored(self, policy: ChunkPolicy, obs: dict, predicted: np.ndarray | None,
                   u_act: float) -> dict[str, float]:
        """U_pred and U of this step exactly as AURD would form them (``predicted``: the latent the current
        plan predicted for ``obs``, None on a step that queried the policy), for a baseline's trace."""
        if not self.monitor:
            return {}
        with self._monitoring():
            u_pred = (0.0 if predicted is None
                      else self._u_pred(policy.encode(obs), predicted, self._pred_baseline(policy)))
            eta = self._eta(policy)
        return {"u_pred": u_pred, "u": combine_uncertainty(float(u_act), u_pred, eta)}

    @contextmanager
    def _monitoring(self) -> Iterator[None]:
        """Count the enclosed work as trace-only monitoring (``monitor_s``), not as control time."""
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.monitor_s += time.perf_counter() - t0


def _jsonable(v: Any) -> Any:
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    if isinstance(v, Enum):
        return v.value  # a trace holds plain strings (events, reasons), as episodes.jsonl does
    if isinstance(v, list):
        return [_jsonable(x) for x in v]
    return v


class FixedExecutor(BaseExecutor):
    """Execute the first ``horizon`` actions of every chunk open loop, then replan."""

    name = "fixed"

    def __init__(self, cfg: FixedConfig | None = None):
        super().__init__(cfg or FixedConfig())

    def reset(self) -> None:
        super().reset()
        self._plan: Plan | None = None
        self._k = 0

    def act(self, policy: ChunkPolicy, obs: dict) -> np.ndarray:
        replanned = self._plan is None or self._k >= min(self.cfg.horizon, len(self._plan.actions))
        ended = None
        if replanned:
            if self._plan is not None:
                ended = Event.COMPLETE
                self.plans.append((self._k, ended))
            self._plan, self._k = Plan.from_output(self._infer(policy, obs)), 0
        k, p = self._k, self._plan
        self._k += 1
        signals = self._monitored(policy, obs, None if k == 0 else p.latents[k - 1], p.u_act[k])
        return self._emit(p.actions[k], plan_step=k, replanned=replanned, u_act=p.u_act[k], **signals,
                          v=p.value(k), ended=ended)


class EnsembleExecutor(BaseExecutor):
    """ACT temporal ensembling: query every step, average every live prediction for the current step
    with weights exp(-m * i), oldest first (in normalized space; the gripper is thresholded after)."""

    name = "ensemble"

    def __init__(self, cfg: EnsembleConfig | None = None):
        super().__init__(cfg or EnsembleConfig())

    def reset(self) -> None:
        super().reset()
        self._history: deque = deque()
        self._predicted: np.ndarray | None = None  # the previous query's latent for this step's observation

    def act(self, policy: ChunkPolicy, obs: dict) -> np.ndarray:
        out = self._infer(policy, obs)
        plan = Plan.from_output(out)
        # every step queries, so the newest prediction of this observation is the previous query's first latent
        signals = self._monitored(policy, obs, self._predicted, plan.u_act[0])
        self._predicted = plan.latents[0]
        K = len(plan.normalized)
        self._history.append((self.t, plan.normalized))
        while self._history and self.t - self._history[0][0] >= K:
            self._history.popleft()
        preds = np.stack([chunk[self.t - t0] for t0, chunk in self._history])
        action = policy.to_actions(temporal_ensemble(preds, self.cfg.m).astype(np.float32))
        self.plans.append((1, Event.COMPLETE))
        return self._emit(action, plan_step=0, replanned=True, u_act=plan.u_act[0], **signals, v=plan.values[0],
                          ended=Event.COMPLETE if self.t > 0 else None, n_ensembled=len(preds))


class AdaHorizonExecutor(BaseExecutor):
    """EverydayVLA's AdaHorizon: horizon chosen per chunk from the discrete/continuous disagreement.

    Thresholds: given explicitly, else the policy's calibrated ``act_low`` / ``act_high`` (percentiles of
    U_act on validation data, like AURD's), else EverydayVLA's absolute 0.03 / 0.06."""

    name = "adahorizon"

    def __init__(self, cfg: AdaHorizonConfig | None = None):
        super().__init__(cfg or AdaHorizonConfig())

    def reset(self) -> None:
        super().reset()
        self._plan: Plan | None = None
        self._k, self._h = 0, 0
        self._event: Event | None = None  # how the current plan ends, decided when it was made

    def _thresholds(self, policy: ChunkPolicy) -> tuple[float, float]:
        c = policy.calibration
        low = c.act_low if c is not None and c.act_low is not None else EVERYDAYVLA_EXTEND_BELOW
        high = c.act_high if c is not None and c.act_high is not None else EVERYDAYVLA_REPLAN_ABOVE
        return (low if self.cfg.extend_below is None else self.cfg.extend_below,
                high if self.cfg.replan_above is None else self.cfg.replan_above)

    def act(self, policy: ChunkPolicy, obs: dict) -> np.ndarray:
        replanned = self._plan is None or self._k >= self._h
        ended = None
        if replanned:
            ended = self._event
            self._plan = Plan.from_output(self._infer(policy, obs))
            self._h, self._event = adahorizon(self._plan.u_act, self.cfg.min_exec, *self._thresholds(policy))
            self._k = 0
            self.plans.append((self._h, self._event))
        k, p = self._k, self._plan
        self._k += 1
        signals = self._monitored(policy, obs, None if k == 0 else p.latents[k - 1], p.u_act[k])
        return self._emit(p.actions[k], plan_step=k, replanned=replanned, u_act=p.u_act[k], **signals,
                          v=p.value(k), ended=ended, h_exec=self._h)


@dataclass(frozen=True)
class AURDSettings:
    """What AURD decides with, fixed for an episode: the thresholds (Algorithm 1's tau_low, tau_high, V_thresh),
    eta (Eq. 14), how U_pred is measured, and the nominal horizon H. ``AURDSettings.of``: the config's options
    over the policy's calibration."""

    tau_low: float
    tau_high: float
    v_thresh: float
    eta: float
    pred_baseline: Literal["none", "episode"]  # raw U_pred, or above the episode's floor (control.math.surprise)
    horizon: int

    @classmethod
    def of(cls, cfg: AURDConfig, policy: ChunkPolicy) -> AURDSettings:
        c = policy.calibration
        if any(v is None for v in (cfg.tau_low, cfg.tau_high, cfg.v_thresh)) and c is None:
            raise ValueError("AURD needs thresholds: calibrate the policy (`pivla calibrate --policy RUN --data VAL`) "
                             "or give tau_low, tau_high and v_thresh")

        def option(name: str, calibrated: Any) -> Any:
            mine = getattr(cfg, name)
            return mine if mine is not None else calibrated

        return cls(tau_low=option("tau_low", getattr(c, "tau_low", None)),
                   tau_high=option("tau_high", getattr(c, "tau_high", None)),
                   v_thresh=option("v_thresh", getattr(c, "v_thresh", None)),
                   eta=option("eta", c.eta if c is not None else DEFAULT_ETA),
                   pred_baseline=option("pred_baseline", getattr(c, "pred_baseline", "none") or "none"),
                   horizon=cfg.horizon or policy.spec.horizon)

    def test(self, u: float, v: float) -> Event | None:
        """Algorithm 1, lines 8-14: REPLAN above tau_high, PRUNE in (tau_low, tau_high] with V below V_thresh, else
        None (the step is trusted)."""
        return step_event(u, v, self.tau_low, self.tau_high, self.v_thresh)


class AURDExecutor(BaseExecutor):
    """PI-VLA's Active Uncertainty-Resolving Decider (Algorithm 1; the paper's reading in docs/method.md, "AURD").

    ``check="before"`` (default): before executing plan step k it forms U = eta * U_act[k] + (1 - eta) * U_pred,
    U_pred being the newest prediction error ||Enc(o_{t+k}) - z_hat_{t+k}|| (0 for k = 0), and replans above
    tau_high, prunes in (tau_low, tau_high] when V[k] < V_thresh, and after a full nominal horizon completes. A
    stop before the first action is a pause: hold pose one step, then replan; after ``max_pauses`` pauses in a
    row the first action is executed anyway, so a static scene cannot stall the robot forever.
    ``check="after"`` is the paper's literal order (execute, observe, then test). One method each:
    ``_act_checking_before`` and ``_act_checking_after``.

    ``commit_after_cut`` (default): the plan made right after a cut (replan, prune or pause) runs its nominal
    horizon unchecked, and the plan after it is checked again. Without it a policy whose U stays above
    tau_high in some state cut every new plan after one action or paused again and again until the step
    limit (docs/experiments.md#commit-after-a-cut). A committed step needs no observed latent for a decision;
    it is still encoded for the trace as monitoring (``monitor``), outside the control time.
    """

    name = "aurd"

    def __init__(self, cfg: AURDConfig | None = None):
        super().__init__(cfg or AURDConfig())

    def reset(self) -> None:
        super().reset()
        self._plan: Plan | None = None
        self._k, self._pauses = 0, 0
        self.settings: AURDSettings | None = None  # resolved at the episode's first step

    def act(self, policy: ChunkPolicy, obs: dict) -> np.ndarray:
        if self.settings is None:
            self.settings = AURDSettings.of(self.cfg, policy)
        if self.cfg.check == "before":
            return self._act_checking_before(policy, obs)
        return self._act_checking_after(policy, obs)

    def _act_checking_before(self, policy: ChunkPolicy, obs: dict) -> np.ndarray:
        """One control step, step k tested before it executes (docs/method.md):

        1. observe o_t, the outcome of the plan's step k - 1;
        2. after H steps the plan is complete (COMPLETE);
        3. without a plan, query the policy (its step 0 has U_pred = 0);
        4. test step k: trusted (or the plan is committed) -> execute it; untrusted at k > 0 -> the plan ends
           before it (REPLAN or PRUNE, H_exec = k) and a new one is made from this observation (back to 3);
           untrusted at k = 0 -> PAUSE: hold pose one step (after ``max_pauses`` pauses in a row execute it
           anyway, FORCED)."""
        s = self.settings
        z = self._observe(policy, obs)
        ended, cut = None, {}  # how the previous plan ended at this step; U and V of a step a cut did not trust
        if self._plan is not None and self._k >= self._horizon():
            ended = self._end_plan(Event.COMPLETE)
        replanned = False
        while True:
            if self._plan is None:
                self._new_plan(policy, obs)
                replanned, z = True, None
            p, k = self._plan, self._k
            u_pred = 0.0 if k == 0 or z is None else self._u_pred(z, p.latents[k - 1], s.pred_baseline)
            u, v = combine_uncertainty(float(p.u_act[k]), u_pred, s.eta), p.value(k)
            committed = self._committed()
            event = None if committed else s.test(u, v)
            if event is None or k == 0:
                break
            ended, cut = self._end_plan(event), {"ended_u": u, "ended_v": v}  # replan from this observation
        if event is not None and self._pauses < self.cfg.max_pauses and self.can_hold(policy.spec, obs):
            self._pauses += 1
            self._end_plan(Event.PAUSE)
            return self._emit(self.hold_action(policy.spec, obs), plan_step=0, replanned=replanned,
                              u_act=p.u_act[0], u_pred=u_pred, u=u, v=v, event=Event.PAUSE, ended=ended,
                              committed=False, **cut)
        self._pauses = 0
        self._k += 1
        return self._emit(p.actions[k], plan_step=k, replanned=replanned, u_act=p.u_act[k], u_pred=u_pred, u=u,
                          v=v, event=Event.FORCED if event else None, ended=ended, committed=committed, **cut)

    def _act_checking_after(self, policy: ChunkPolicy, obs: dict) -> np.ndarray:
        """One control step in the paper's literal order, never a pause:

        1. observe o_t, the outcome of the plan's step k - 1, and (unless the plan is committed) test that step
           with it: untrusted -> the plan ends after it (REPLAN or PRUNE, H_exec = k);
        2. after H steps the plan is complete (COMPLETE);
        3. without a plan, query the policy; execute step k."""
        s = self.settings
        z = self._observe(policy, obs)
        ended, cut = None, {}
        if self._plan is not None and self._k > 0 and not self._committed():
            p, k = self._plan, self._k - 1
            u_pred = self._u_pred(z, p.latents[k], s.pred_baseline)
            u = combine_uncertainty(p.u_act[k], u_pred, s.eta)  # U_act's own dtype here, as the episodes on disk
            event = s.test(u, p.value(k))
            if event is not None:
                ended, cut = self._end_plan(event), {"ended_u": u, "ended_v": p.value(k)}
        if self._plan is not None and self._k >= self._horizon():
            ended = self._end_plan(Event.COMPLETE)
        replanned = False
        if self._plan is None:
            self._new_plan(policy, obs)
            replanned, z = True, None
        p, k = self._plan, self._k
        # the trace's U_pred of step k; after a test above, the episode floor has moved by that measurement
        u_pred = 0.0 if k == 0 or z is None else self._u_pred(z, p.latents[k - 1], s.pred_baseline)
        u = combine_uncertainty(float(p.u_act[k]), u_pred, s.eta)
        committed = self._committed()
        self._pauses = 0
        self._k += 1
        return self._emit(p.actions[k], plan_step=k, replanned=replanned, u_act=p.u_act[k], u_pred=u_pred, u=u,
                          v=p.value(k), event=None, ended=ended, committed=committed, **cut)

    # -- the pieces of a step --------------------------------------------------------------------------------
    def _horizon(self) -> int:
        return min(self.settings.horizon, len(self._plan.actions))

    def _observe(self, policy: ChunkPolicy, obs: dict) -> np.ndarray | None:
        """Enc(o_t) where a test reads it: o_t is the outcome of the plan's step k - 1, read by the test of step k
        (before) or of step k - 1 (after). Not after a plan's last step when testing before (the plan completes,
        and a new plan's step 0 has U_pred = 0). A committed plan's steps are read by no test: encoded for the
        trace only (``monitor``, outside the control time)."""
        if self._plan is None or self._k == 0:
            return None
        if self.cfg.check == "before" and self._k >= self._horizon():
            return None
        if not self._committed():
            return policy.encode(obs)
        if not self.monitor:
            return None
        with self._monitoring():
            return policy.encode(obs)

    def _committed(self) -> bool:
        """The current plan was made right after a cut (the plan log's last entry) and runs unchecked."""
        return self.cfg.commit_after_cut and bool(self.plans) and self.plans[-1][1] != Event.COMPLETE

    def _new_plan(self, policy: ChunkPolicy, obs: dict) -> None:
        self._plan, self._k = Plan.from_output(self._infer(policy, obs)), 0

    def _end_plan(self, event: Event) -> Event:
        """The current plan ends after its ``_k`` executed steps; returns the event (the next row's ``ended``)."""
        self.plans.append((self._k, event))
        self._plan, self._k = None, 0
        return event


@dataclass(frozen=True)
class ExecutorKind:
    """One executor in the registry: its config (the command line's ``--executor NAME``) and its class."""

    config: type
    executor: type[BaseExecutor]


EXECUTOR_REGISTRY: dict[str, ExecutorKind] = {
    "aurd": ExecutorKind(AURDConfig, AURDExecutor), "fixed": ExecutorKind(FixedConfig, FixedExecutor),
    "ensemble": ExecutorKind(EnsembleConfig, EnsembleExecutor),
    "adahorizon": ExecutorKind(AdaHorizonConfig, AdaHorizonExecutor),
}
"""Every executor by name (``make_executor``, ``executor_config``)."""


def first_cut(trace: list[dict]) -> Event | None:
    """How AURD first left its nominal schedule in an episode's trace: REPLAN, PRUNE or PAUSE; None if it never
    did. Until that step AURD executes what a fixed horizon of the same H would, so in a paired episode the
    first cut is where the two can part (the benchmark groups its discordant pairs by it)."""
    for row in trace:
        if row.get("ended") in CUTS:  # a plan cut at this step (a pause here too comes after that cut)
            return Event(row["ended"])
        if row.get("event") == Event.PAUSE:
            return Event.PAUSE
    return None


def executor_config(name: str, **options: Any) -> ExecutorConfig:
    """The config of an executor by name, with options replacing its defaults (unknown options are an error)."""
    if name not in EXECUTOR_REGISTRY:
        raise ValueError(f"unknown executor {name!r}; choose from {sorted(EXECUTOR_REGISTRY)}")
    cls = EXECUTOR_REGISTRY[name].config
    fields = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(options) - fields)
    if unknown:
        raise ValueError(f"executor {name!r} has no option {', '.join(unknown)} (options: {', '.join(sorted(fields))})")
    return cls(**options)


def make_executor(cfg: ExecutorConfig | str, **options: Any) -> BaseExecutor:
    """An executor from its config, or by name with options (``make_executor("fixed", horizon=3)``)."""
    if isinstance(cfg, str):
        cfg = executor_config(cfg, **options)
    elif options:
        cfg = dataclasses.replace(cfg, **options)
    if cfg.kind == "aurd" and cfg.pred_baseline not in (None, "none", "episode"):
        raise ValueError(f"pred_baseline must be 'none' or 'episode', got {cfg.pred_baseline!r}")
    return EXECUTOR_REGISTRY[cfg.kind].executor(cfg)


def config_to_dict(cfg: ExecutorConfig) -> dict[str, Any]:
    """An executor config as JSON: its name and options (the inverse of ``executor_config(**d)``)."""
    return {"name": cfg.kind, **dataclasses.asdict(cfg)}
