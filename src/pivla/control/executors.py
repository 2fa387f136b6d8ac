"""Executors turn a chunking policy into one action per control step. All share one interface:

    executor.reset()                       # at the start of an episode
    action = executor.act(policy, obs)     # physical 7-D action for this control step

and all write a per-step ``trace`` and a per-plan list ``plans`` of (executed horizon, event). ``aurd`` is
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

import time
from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pivla.control.math import DEFAULT_ETA, adahorizon, prediction_uncertainty, step_event, surprise, temporal_ensemble

GRIPPER = 6
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
    def from_output(cls, out: dict[str, np.ndarray]) -> "Plan":
        return cls(
            normalized=out["actions_normalized"],
            actions=out["actions"],
            u_act=out["u_act"],
            values=out["values"],
            latents=out["latents"],
        )


@dataclass
class BaseExecutor:
    name: str = "base"
    monitor: bool = True  # baselines: also compute U_pred and U for the trace (one encoding per new observation)
    trace: list[dict] = field(default_factory=list)
    plans: list[tuple[int, str]] = field(default_factory=list)
    t: int = 0
    last_gripper: float = -1.0
    monitor_s: float = 0.0  # time spent on monitoring only, excluded from control-step timings
    _pred_min: float | None = None

    def reset(self) -> None:
        self.trace, self.plans, self.t, self.last_gripper, self._pred_min = [], [], 0, -1.0, None

    def _emit(self, action: np.ndarray, **row: Any) -> np.ndarray:
        action = np.asarray(action, np.float32)
        self.last_gripper = float(action[GRIPPER])
        self.trace.append({"t": self.t, **{k: _jsonable(v) for k, v in row.items()}})
        self.t += 1
        return action

    def hold_action(self) -> np.ndarray:
        """Hold pose for one control step: zero end-effector delta, gripper unchanged."""
        a = np.zeros(7, np.float32)
        a[GRIPPER] = self.last_gripper
        return a

    def _pred_baseline(self, policy) -> str:
        return getattr(policy.calibration, "pred_baseline", "none") or "none"

    def _eta(self, policy) -> float:
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

    def _monitored(self, policy, obs: dict, predicted: np.ndarray | None, u_act: float) -> dict[str, float]:
        """U_pred and U of this step exactly as AURD would form them (``predicted``: the latent the current
        plan predicted for ``obs``, None on a step that queried the policy), for a baseline's trace."""
        if not self.monitor:
            return {}
        with self._monitoring():
            u_pred = 0.0 if predicted is None else self._u_pred(policy.encode(obs), predicted, self._pred_baseline(policy))
            eta = self._eta(policy)
        return {"u_pred": u_pred, "u": eta * float(u_act) + (1 - eta) * u_pred}

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
    return v


@dataclass
class FixedExecutor(BaseExecutor):
    """Execute the first ``horizon`` actions of every chunk open loop, then replan."""

    name: str = "fixed"
    horizon: int = 5
    _plan: Plan | None = None
    _k: int = 0

    def reset(self) -> None:
        super().reset()
        self._plan, self._k = None, 0

    def act(self, policy, obs: dict) -> np.ndarray:
        replanned = self._plan is None or self._k >= min(self.horizon, len(self._plan.actions))
        ended = None
        if replanned:
            if self._plan is not None:
                ended = "complete"
                self.plans.append((self._k, ended))
            self._plan, self._k = Plan.from_output(policy.infer(obs)), 0
        k, p = self._k, self._plan
        self._k += 1
        signals = self._monitored(policy, obs, None if k == 0 else p.latents[k - 1], p.u_act[k])
        return self._emit(p.actions[k], plan_step=k, replanned=replanned, u_act=p.u_act[k], **signals,
                          v=p.value(k), ended=ended)


@dataclass
class EnsembleExecutor(BaseExecutor):
    """ACT temporal ensembling: query every step, average every live prediction for the current step
    with weights exp(-m * i), oldest first (in normalized space; the gripper is thresholded after)."""

    name: str = "ensemble"
    m: float = 0.01
    _history: deque = field(default_factory=deque)
    _predicted: np.ndarray | None = None  # the previous query's latent for this step's observation

    def reset(self) -> None:
        super().reset()
        self._history, self._predicted = deque(), None

    def act(self, policy, obs: dict) -> np.ndarray:
        out = policy.infer(obs)
        plan = Plan.from_output(out)
        # every step queries, so the newest prediction of this observation is the previous query's first latent
        signals = self._monitored(policy, obs, self._predicted, plan.u_act[0])
        self._predicted = plan.latents[0]
        K = len(plan.normalized)
        self._history.append((self.t, plan.normalized))
        while self._history and self.t - self._history[0][0] >= K:
            self._history.popleft()
        preds = np.stack([chunk[self.t - t0] for t0, chunk in self._history])
        action = policy.to_actions(temporal_ensemble(preds, self.m).astype(np.float32))
        self.plans.append((1, "complete"))
        return self._emit(action, plan_step=0, replanned=True, u_act=plan.u_act[0], **signals, v=plan.values[0],
                          ended="complete" if self.t > 0 else None, n_ensembled=len(preds))


@dataclass
class AdaHorizonExecutor(BaseExecutor):
    """EverydayVLA's AdaHorizon: horizon chosen per chunk from the discrete/continuous disagreement.

    Thresholds: given explicitly, else the policy's calibrated ``act_low`` / ``act_high`` (percentiles of
    U_act on validation data, like AURD's), else EverydayVLA's absolute 0.03 / 0.06."""

    name: str = "adahorizon"
    min_exec: int = 4
    extend_below: float | None = None
    replan_above: float | None = None
    _plan: Plan | None = None
    _k: int = 0
    _h: int = 0
    _event: str | None = None  # how the current plan ends, decided when it was made

    def reset(self) -> None:
        super().reset()
        self._plan, self._k, self._h, self._event = None, 0, 0, None

    def _thresholds(self, policy) -> tuple[float, float]:
        c = policy.calibration
        low = c.act_low if c is not None and c.act_low is not None else EVERYDAYVLA_EXTEND_BELOW
        high = c.act_high if c is not None and c.act_high is not None else EVERYDAYVLA_REPLAN_ABOVE
        return (low if self.extend_below is None else self.extend_below,
                high if self.replan_above is None else self.replan_above)

    def act(self, policy, obs: dict) -> np.ndarray:
        replanned = self._plan is None or self._k >= self._h
        ended = None
        if replanned:
            ended = self._event
            self._plan = Plan.from_output(policy.infer(obs))
            self._h, self._event = adahorizon(self._plan.u_act, self.min_exec, *self._thresholds(policy))
            self._k = 0
            self.plans.append((self._h, self._event))
        k, p = self._k, self._plan
        self._k += 1
        signals = self._monitored(policy, obs, None if k == 0 else p.latents[k - 1], p.u_act[k])
        return self._emit(p.actions[k], plan_step=k, replanned=replanned, u_act=p.u_act[k], **signals,
                          v=p.value(k), ended=ended, h_exec=self._h)


@dataclass
class AURDExecutor(BaseExecutor):
    """PI-VLA's Active Uncertainty-Resolving Decider (Algorithm 1, METHOD.md "AURD").

    Before executing plan step k (``check="before"``) it forms U = eta * U_act[k] + (1 - eta) * U_pred,
    U_pred being the newest prediction error ||Enc(o_{t+k}) - z_hat_{t+k}|| (0 for k = 0), and
    replans above tau_high, prunes in (tau_low, tau_high] when V[k] < V_thresh, and after a full nominal
    horizon completes. A stop before the first action is a pause: hold pose one step, then replan; after
    ``max_pauses`` pauses in a row the first action is executed anyway, so a static scene cannot stall the
    robot forever. ``check="after"`` is the paper's literal order (execute, observe, then test).
    Thresholds default to the policy's calibration (``pivla calibrate``).

    ``commit_after_cut`` (default): the plan made right after a cut (replan, prune or pause) runs its nominal
    horizon unchecked, and the plan after it is checked again. Without it a policy whose U stays above
    tau_high in some state cut every new plan after one action or paused again and again until the step
    limit (docs/results.md, "Session 18"). A committed step needs no observed latent for a decision; it is
    still encoded for the trace as monitoring (``monitor``), outside the control time.
    """

    name: str = "aurd"
    tau_low: float | None = None
    tau_high: float | None = None
    v_thresh: float | None = None
    eta: float | None = None
    check: str = "before"
    horizon: int | None = None
    max_pauses: int = 3
    pred_baseline: str | None = None  # "episode": U_pred above the episode's floor (math.surprise); None: as calibrated
    commit_after_cut: bool = True
    _plan: Plan | None = None
    _k: int = 0
    _pauses: int = 0
    _settings: tuple | None = None  # thresholds, eta, U_pred baseline and horizon, fixed for an episode

    def __post_init__(self) -> None:
        if self.pred_baseline not in (None, "none", "episode"):
            raise ValueError(f"pred_baseline must be 'none' or 'episode', got {self.pred_baseline!r}")

    def reset(self) -> None:
        super().reset()
        self._plan, self._k, self._pauses, self._settings = None, 0, 0, None

    def _pred_baseline(self, policy) -> str:
        return self.pred_baseline if self.pred_baseline is not None else super()._pred_baseline(policy)

    def _thresholds(self, policy) -> tuple[float, float, float, float]:
        c = policy.calibration
        vals = [self.tau_low, self.tau_high, self.v_thresh]
        if any(v is None for v in vals) and c is None:
            raise ValueError(f"AURD needs thresholds: run `pivla calibrate --policy {policy.run_dir} --data VAL` "
                             "or pass tau_low/tau_high/v_thresh")
        tl = self.tau_low if self.tau_low is not None else c.tau_low
        th = self.tau_high if self.tau_high is not None else c.tau_high
        vt = self.v_thresh if self.v_thresh is not None else c.v_thresh
        eta = self.eta if self.eta is not None else self._eta(policy)
        return tl, th, vt, eta

    def _committed(self) -> bool:
        """The current plan was made right after a cut (the plan log's last entry) and runs unchecked."""
        return self.commit_after_cut and bool(self.plans) and self.plans[-1][1] != "complete"

    def _end_plan(self, h: int, event: str) -> None:
        self.plans.append((h, event))
        self._plan, self._k = None, 0

    def act(self, policy, obs: dict) -> np.ndarray:
        if self._settings is None:
            self._settings = (*self._thresholds(policy), self._pred_baseline(policy), self.horizon or policy.horizon)
        tau_low, tau_high, v_thresh, eta, baseline, H = self._settings
        ended = None
        cut: dict[str, float] = {}  # U and V of the step a "replan" / "prune" did not trust
        z_obs = None
        observed = self._plan is not None and self._k > 0  # o is the outcome of this plan's step k - 1
        # encode only what a decision reads: not after a plan's last step (it completes, and the new plan's
        # first step has U_pred = 0), unless check="after" tests that step first; a committed plan's steps
        # are read by no decision, only by the trace (monitoring)
        committed = observed and self._committed()
        if observed and (self.check == "after" or self._k < min(H, len(self._plan.actions))):
            if not committed:
                z_obs = policy.encode(obs)
            elif self.monitor:
                with self._monitoring():
                    z_obs = policy.encode(obs)
        if self.check == "after" and observed and not committed:
            k = self._k - 1  # the step just executed, now observed
            u_pred = self._u_pred(z_obs, self._plan.latents[k], baseline)
            u = eta * self._plan.u_act[k] + (1 - eta) * u_pred
            event = step_event(u, self._plan.value(k), tau_low, tau_high, v_thresh)
            if event is not None:
                ended, cut = event, {"ended_u": u, "ended_v": self._plan.value(k)}
                self._end_plan(self._k, event)
        if self._plan is not None and self._k >= min(H, len(self._plan.actions)):
            ended = "complete"
            self._end_plan(self._k, "complete")
        replanned = False
        while True:
            if self._plan is None:
                self._plan, self._k, replanned, z_obs = Plan.from_output(policy.infer(obs)), 0, True, None
            k, p = self._k, self._plan
            u_pred = 0.0 if k == 0 or z_obs is None else self._u_pred(z_obs, p.latents[k - 1], baseline)
            u = eta * float(p.u_act[k]) + (1 - eta) * u_pred
            v = p.value(k)
            committed = self._committed()
            checked = self.check == "before" and not committed
            event = step_event(u, v, tau_low, tau_high, v_thresh) if checked else None
            if event is not None and k > 0:
                ended, cut = event, {"ended_u": u, "ended_v": v}
                self._end_plan(k, event)
                continue  # replan from the same observation
            if event is not None and self._pauses < self.max_pauses:
                self._pauses += 1
                self._end_plan(0, "pause")
                return self._emit(self.hold_action(), plan_step=0, replanned=replanned, u_act=p.u_act[0],
                                  u_pred=u_pred, u=u, v=v, event="pause", ended=ended, committed=False, **cut)
            self._pauses = 0
            self._k += 1
            return self._emit(p.actions[k], plan_step=k, replanned=replanned, u_act=p.u_act[k], u_pred=u_pred,
                              u=u, v=v, event="forced" if event else None, ended=ended, committed=committed,
                              **cut)


EXECUTORS = {"aurd": AURDExecutor, "fixed": FixedExecutor, "ensemble": EnsembleExecutor, "adahorizon": AdaHorizonExecutor}


def make_executor(name: str, **options: Any) -> BaseExecutor:
    """An executor by name with optional overrides (e.g. ``horizon=5`` for fixed, ``check="after"``)."""
    if name not in EXECUTORS:
        raise ValueError(f"unknown executor {name!r}; choose from {sorted(EXECUTORS)}")
    return EXECUTORS[name](**options)
