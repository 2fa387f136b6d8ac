"""Calibration of AURD's thresholds on validation data (never on test episodes).

For every sampled time t of every successful validation episode, the policy's plan gives U_act[k] and
V[k]; the episode's real next observations give U_pred[k] = ||Enc(o_{t+k}) - z_hat_{t+k}|| exactly as
AURD sees it online (the newest prediction error before step k; 0 for k = 0). Thresholds are percentiles
of these in-distribution signals: tau_low = P50(U), tau_high = P99(U), V_thresh = P10(V) by default, so
that on data like the validation set AURD rarely intervenes, and it intervenes when signals leave that
range. P99, not P95: with P95 the demo's 80-px policy replanned ~3x as often as at 96 px and lost to a fixed
horizon on validation episodes; P99 took it level with fixed (docs/experiments.md#replan-threshold-at-p99). The same
percentiles of U_act alone give AdaHorizon its thresholds (``act_low``, ``act_high``): EverydayVLA's
absolute 0.03 / 0.06 belong to its model's action scale, and on ours they made it replan after every
action (docs/experiments.md#adahorizon-thresholds-from-calibration).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from pivla.control.contract import DEFAULT_ETA, BatchPolicy, Calibration
from pivla.control.math import combine_uncertainty, prediction_uncertainty, surprise
from pivla.data.episode import Episode


@dataclass
class CalibrationConfig:
    """Which percentiles of the policy's own in-distribution signals become AURD's thresholds."""

    tau_low_pct: float = 50.0
    """Percentile of U for tau_low."""
    tau_high_pct: float = 99.0
    """Percentile of U for tau_high, and of U_act for AdaHorizon's act_high."""
    v_pct: float = 10.0
    """Percentile of V for V_thresh."""
    eta: float = DEFAULT_ETA
    """Weight of U_act in U (Eq. 14)."""
    stride: int = 2
    """Every stride-th time step of each episode is sampled."""
    batch: int = 64
    """Observations per forward pass."""
    pred_baseline: Literal["none", "episode"] = "episode"
    """episode: U_pred above the episode's smallest so far (AURD then measures it the same way); without it
    AURD replanned after every action in unseen environments (docs/experiments.md#prediction-error-above-the-episode-floor)."""  # noqa: E501 - tyro --help keeps its line breaks


def _obs_at(ep: Episode, t: int) -> dict:
    obs = {k: v[t] for k, v in ep.obs.items()}
    obs["instruction"] = ep.instruction
    return obs


def calibration_signals(policy: BatchPolicy, episodes: list[Episode], cfg: CalibrationConfig) -> dict[str, np.ndarray]:
    """U (N, H), U_act, U_pred and V (N, H) for sampled steps of successful episodes (NaN where o_{t+k}
    lies past the episode end)."""
    H = policy.spec.horizon
    us, uas, ups, vs = [], [], [], []
    for ep in episodes:
        if not ep.success:
            continue
        T = len(ep)
        z = np.concatenate([policy.encode_batch([_obs_at(ep, t) for t in range(s, min(s + cfg.batch, T))])
                            for s in range(0, T, cfg.batch)])
        ts = list(range(0, T, cfg.stride))
        floor: float | None = None  # smallest raw U_pred of the earlier samples (pred_baseline="episode")
        for s in range(0, len(ts), cfg.batch):
            chunk = ts[s : s + cfg.batch]
            out = policy.infer_batch([_obs_at(ep, t) for t in chunk])
            u_act = out["u_act"][:, :H]
            for i, t in enumerate(chunk):
                u_pred = np.full(H, np.nan)
                u_pred[0] = 0.0
                for k in range(1, H):
                    if t + k < T:
                        u_pred[k] = prediction_uncertainty(z[t + k], out["latents"][i, k - 1])
                if cfg.pred_baseline == "episode":
                    raw = u_pred.copy()
                    for k in range(1, H):
                        if np.isfinite(raw[k]):
                            u_pred[k] = surprise(raw[k], floor)
                            floor = raw[k] if floor is None else min(floor, raw[k])
                uas.append(u_act[i])
                ups.append(u_pred)
                us.append(combine_uncertainty(u_act[i], u_pred, cfg.eta))
                vs.append(out["values"][i, :H])
    if not us:
        raise ValueError("no successful validation episodes to calibrate on")
    return {"u": np.array(us), "u_act": np.array(uas), "u_pred": np.array(ups), "v": np.array(vs)}


def thresholds(signals: dict[str, np.ndarray], cfg: CalibrationConfig, source: str = "") -> Calibration:
    u = signals["u"][np.isfinite(signals["u"])]
    v = signals["v"].ravel()
    tau_low = float(np.percentile(u, cfg.tau_low_pct))
    tau_high = float(np.percentile(u, cfg.tau_high_pct))
    u_act = signals["u_act"][np.isfinite(signals["u_act"])]
    act_low, act_high = (float(np.percentile(u_act, q)) for q in (cfg.tau_low_pct, cfg.tau_high_pct))
    return Calibration(tau_low=tau_low, tau_high=max(tau_high, tau_low), v_thresh=float(np.percentile(v, cfg.v_pct)),
                       eta=cfg.eta, source=source, act_low=act_low, act_high=max(act_high, act_low),
                       pred_baseline=cfg.pred_baseline)


def calibrate(policy: BatchPolicy, episodes: list[Episode], cfg: CalibrationConfig | None = None,
              source: str = "") -> tuple[Calibration, dict]:
    """Compute thresholds, set them on the policy and return them with statistics (a run directory stores
    them with ``pivla.training.checkpoint.write_calibration``)."""
    cfg = cfg or CalibrationConfig()
    test = sum(ep.meta.get("split") == "test" for ep in episodes)
    if test:
        raise ValueError(f"{test} of the {len(episodes)} episodes are recorded test rollouts (pivla eval --record "
                         "without --split validation): thresholds are calibrated on validation data only")
    sig = calibration_signals(policy, episodes, cfg)
    calib = thresholds(sig, cfg, source)
    stats = {
        "samples": int(len(sig["u"])),
        "u_mean_by_step": np.nanmean(sig["u"], axis=0).round(5).tolist(),
        "u_act_mean_by_step": np.nanmean(sig["u_act"], axis=0).round(5).tolist(),
        "u_pred_mean_by_step": np.nanmean(sig["u_pred"], axis=0).round(5).tolist(),
        "v_mean_by_step": sig["v"].mean(0).round(5).tolist(),
        "percentiles": {"tau_low": cfg.tau_low_pct, "tau_high": cfg.tau_high_pct, "v_thresh": cfg.v_pct},
    }
    policy.calibration = calib
    return calib, stats
