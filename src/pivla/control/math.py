"""The control math of PI-VLA and its baselines as pure functions (numpy in, numpy out).

Indices: a plan is a chunk of K actions; ``u[k]`` and ``values[k]`` belong to step k+1 of the plan (the
(k+1)-th action to execute). Actions are in the normalized space [-1, 1].
"""

from __future__ import annotations

from enum import StrEnum

import numpy as np

from pivla.control.contract import DEFAULT_ETA
from pivla.model.tokenizer import dequantize as _dequantize


class Event(StrEnum):
    """How a plan ends, and what AURD did at a step. The values are what traces and plan logs hold on disk
    (``episodes.jsonl``), so a member equals, hashes and serialises as its string: ``Event.REPLAN == "replan"``.

    A plan ends: ``COMPLETE`` (it ran its horizon), ``REPLAN`` (U above tau_high), ``PRUNE`` (U in the band
    (tau_low, tau_high] with a low value), ``PAUSE`` (its first step was untrusted: AURD held pose one step),
    or, asynchronously, ``SWITCH`` (a newer chunk took over before it ran its horizon). A trace row's
    ``event`` is ``PAUSE`` on the step that held, or ``FORCED``: an untrusted first step executed anyway after
    ``max_pauses`` pauses in a row."""

    COMPLETE = "complete"
    REPLAN = "replan"
    PRUNE = "prune"
    PAUSE = "pause"
    SWITCH = "switch"
    FORCED = "forced"


EVENTS = (Event.COMPLETE, Event.REPLAN, Event.PRUNE, Event.PAUSE)  # the ends of a plan in the synchronous loop
CUTS = (Event.REPLAN, Event.PRUNE, Event.PAUSE)  # the ends AURD's test decides: it left its nominal schedule


def dequantize(probs, bin_centers):
    """Eq. 12: a_bar[k, d] = sum_b p[k, d, b] * c_b (expectation over the bin centres); NumPy arrays or
    torch tensors (the policy calls it on the model's output before leaving torch)."""
    return _dequantize(probs, bin_centers)


def action_uncertainty(continuous: np.ndarray, dequantized: np.ndarray) -> np.ndarray:
    """Eq. 13's U_act: mean over action dimensions of |A_c - a_bar| (per chunk step for (K, D) inputs)."""
    return np.abs(np.asarray(continuous, np.float64) - np.asarray(dequantized, np.float64)).mean(-1)


def prediction_uncertainty(observed_latent: np.ndarray | None,
                           predicted_latent: np.ndarray | None) -> np.ndarray | float:
    """U_pred = || Enc(o_{t+k}) - z_hat_{t+k} ||_2; 0 when no observation is available yet."""
    if observed_latent is None or predicted_latent is None:
        return 0.0
    # np.linalg.norm(axis=-1)'s arithmetic without its wrapper: AURD forms this after every observation
    diff = np.subtract(observed_latent, predicted_latent, dtype=np.float64)
    return np.sqrt(np.add.reduce(diff * diff, axis=-1))


def surprise(u_pred: float, episode_min: float | None) -> float:
    """U_pred above the smallest prediction error seen so far in this episode (0 before any).

    A deviation from Eq. 14, optional (AURD's ``pred_baseline="episode"``): in a scene that looks unlike the
    training data (new table, light, camera) the target encoder's latents are off by a roughly constant
    amount at every step, so raw U_pred exceeds thresholds calibrated in distribution all the time and AURD
    replans after every action. Measured against the episode's own floor, U_pred keeps what AURD needs --
    the world changing differently from the prediction -- and drops the constant offset. Only past steps
    of the same episode are used, so it stays an online rule.
    """
    if episode_min is None:
        return float(u_pred)
    return max(0.0, float(u_pred) - episode_min)


def combine_uncertainty(u_act, u_pred, eta: float = DEFAULT_ETA):
    """Eq. 14: U = eta * U_act + (1 - eta) * U_pred, for scalars or arrays of per-step signals."""
    return eta * u_act + (1.0 - eta) * u_pred


def composite_uncertainty(continuous: np.ndarray, dequantized: np.ndarray, observed_latent: np.ndarray | None,
                          predicted_latent: np.ndarray | None, eta: float = DEFAULT_ETA) -> np.ndarray | float:
    """Eqs. 13-14: U = eta * U_act + (1 - eta) * U_pred.

    Works on one step ((D,) actions, (d_z,) latents) or a whole chunk ((K, D), (K, d_z)); latents may be
    None (no observation yet), which means U_pred = 0.
    """
    u_act = action_uncertainty(continuous, dequantized)
    u_pred = prediction_uncertainty(observed_latent, predicted_latent)
    out = combine_uncertainty(u_act, np.asarray(u_pred), eta)
    return float(out) if np.ndim(out) == 0 else out


def step_event(u: float, value: float, tau_low: float, tau_high: float, v_thresh: float) -> Event | None:
    """AURD's test of one plan step (Algorithm 1, lines 8-14): ``Event.REPLAN`` above tau_high,
    ``Event.PRUNE`` in the band (tau_low, tau_high] when the value is low, else None (the step is trusted)."""
    if u > tau_high:
        return Event.REPLAN
    if u > tau_low and value < v_thresh:
        return Event.PRUNE
    return None


def decide_horizon(u: np.ndarray, values: np.ndarray, tau_low: float, tau_high: float, v_thresh: float,
                   check: str = "before") -> tuple[int, Event]:
    """AURD's executed horizon for a plan whose uncertainties ``u`` and values are known for each step.

    ``check="before"`` (default, docs/method.md "AURD"): step k is tested before it is executed; a triggered test
    stops the plan with H_exec = k ("replan" or "prune"), and H_exec = 0 becomes "pause" (hold pose one
    control step, then replan). ``check="after"`` is the paper's literal order: execute step k, then test
    it, so H_exec >= 1 and nothing is ever paused. All steps trusted: (len(u), "complete").
    """
    if check not in ("before", "after"):
        raise ValueError(f"check must be 'before' or 'after', got {check!r}")
    n = min(len(u), len(values))
    for k in range(n):
        event = step_event(float(u[k]), float(values[k]), tau_low, tau_high, v_thresh)
        if event is None:
            continue
        if check == "after":
            return k + 1, event
        return (k, event) if k > 0 else (0, Event.PAUSE)
    return n, Event.COMPLETE


def ensemble_weights(n: int, m: float = 0.01) -> np.ndarray:
    """ACT temporal ensembling weights w_i = exp(-m * i), i = 0 for the oldest prediction, normalised."""
    w = np.exp(-m * np.arange(n))
    return w / w.sum()


def temporal_ensemble(predictions: np.ndarray, m: float = 0.01) -> np.ndarray:
    """Weighted average of all predictions for the current step, ``predictions`` (n, D) oldest first."""
    predictions = np.asarray(predictions, np.float64)
    return (ensemble_weights(len(predictions), m)[:, None] * predictions).sum(0)


def adahorizon(mad: np.ndarray, min_exec: int = 4, extend_below: float = 0.03,
               replan_above: float = 0.06) -> tuple[int, Event]:
    """EverydayVLA's AdaHorizon on MAD_k = mean_d |A_c[k] - a_bar[k]|.

    Execute at least ``min_exec`` actions, but if any MAD among them exceeds ``replan_above`` replan at
    that step (never fewer than one action); beyond ``min_exec`` keep extending while MAD < ``extend_below``.
    """
    mad = np.asarray(mad)
    for k in range(min(min_exec, len(mad))):
        if mad[k] > replan_above:
            return max(k, 1), Event.REPLAN
    h = min(min_exec, len(mad))
    while h < len(mad) and mad[h] < extend_below:
        h += 1
    return h, Event.COMPLETE
