"""``pivla ablate``: the structure of the paper's Tables 4-6 on the simulator.

Table 4 (action heads): full, discrete-only, continuous-only. Table 5 (loss terms): full, w/o L_SP,
w/o L_RL, IL only. Table 6 (execution): the full model with AURD, AURD in the paper's literal check order,
fixed horizon, ACT temporal ensembling and AdaHorizon. Every variant is trained with the same data, seed
and steps, calibrated on the same validation set, and evaluated on the same test seeds.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from dataclasses import dataclass
from pathlib import Path

from pivla.control.math import wilson_interval
from pivla.training.checkpoint import atomic_write_bytes

log = logging.getLogger(__name__)

# variant -> (table, loss overrides)
TRAIN_VARIANTS: dict[str, tuple[str, dict]] = {
    "full": ("heads+loss", {}),
    "discrete_only": ("heads", {"use_continuous": False}),
    "continuous_only": ("heads", {"use_discrete": False}),
    "no_sp": ("loss", {"use_sp": False}),
    "no_rl": ("loss", {"use_rl": False}),
    "il_only": ("loss", {"use_sp": False, "use_rl": False, "use_recon": False}),
}
# executor variants of the full model: name -> (executor, options)
EXEC_VARIANTS: dict[str, tuple[str, dict]] = {
    "aurd": ("aurd", {}),
    "aurd_check_after": ("aurd", {"check": "after"}),
    "fixed_h5": ("fixed", {"horizon": 5}),
    "fixed_h8": ("fixed", {"horizon": 8}),
    "ensemble": ("ensemble", {}),
    "adahorizon": ("adahorizon", {}),
}


@dataclass
class AblationConfig:
    data: str
    val: str
    out: str
    steps: int = 3000
    batch_size: int = 64
    seed: int = 0
    env: str = "tabletop"
    suite: str = "pick_place"
    tasks: str | None = None
    episodes: int = 10
    perturb: str | None = None
    realism: str = "ideal"
    workers: int = 2
    variants: tuple[str, ...] | None = None


def _train_and_calibrate(cfg: AblationConfig, name: str, loss_overrides: dict) -> Path:
    from pivla.control.calibrate import calibrate
    from pivla.data.format import read_dataset
    from pivla.policy import load_policy
    from pivla.training.losses import LossConfig
    from pivla.training.trainer import TrainConfig, train

    run = Path(cfg.out) / "runs" / name
    status = run / "status.json"
    if not (status.exists() and json.loads(status.read_text()).get("done")):
        tc = TrainConfig(data=cfg.data, out=str(run), steps=cfg.steps, batch_size=cfg.batch_size, seed=cfg.seed,
                         val_fraction=0.05, loss=dataclasses.replace(LossConfig(), **loss_overrides),
                         eval_every=max(cfg.steps // 5, 1), ckpt_every=max(cfg.steps // 5, 1),
                         value_refresh_every=max(cfg.steps // 5, 1), progress=False)
        train(tc, resume=(run / "checkpoints").exists())
    if not (run / "calibration.json").exists():
        calibrate(load_policy(run, device="cpu"), read_dataset(cfg.val), source=cfg.val)
    return run


def _evaluate(cfg: AblationConfig, run: Path, name: str, executor: str, options: dict) -> dict:
    from pivla.evaluation.runner import EvalConfig, evaluate

    ec = EvalConfig(policy=str(run), out=str(Path(cfg.out) / "eval" / name), env=cfg.env, suite=cfg.suite,
                    tasks=cfg.tasks, executor=executor, episodes=cfg.episodes, seed=cfg.seed + 1000,
                    perturb=cfg.perturb, realism=cfg.realism, workers=cfg.workers, videos=0, executor_options=options)
    return evaluate(ec, progress=False)


def _row(label: str, r: dict) -> str:
    lo, hi = wilson_interval(r["successes"], r["episodes"])
    return (f"| {label} | {100 * r['success_rate']:.1f}% | [{100 * lo:.1f}, {100 * hi:.1f}] | {r['episodes']} | "
            f"{r['mean_executed_horizon']:.2f} | {r['replans']} | {r['prunes']} | {r['pauses']} |")


def run_ablation(cfg: AblationConfig) -> str:
    wanted = set(cfg.variants or (*TRAIN_VARIANTS, *EXEC_VARIANTS))
    unknown = wanted - set(TRAIN_VARIANTS) - set(EXEC_VARIANTS)
    if unknown:
        raise SystemExit(f"unknown ablation variants {sorted(unknown)}; known: {sorted({*TRAIN_VARIANTS, *EXEC_VARIANTS})}")
    results: dict[str, dict] = {}
    for name, (_, overrides) in TRAIN_VARIANTS.items():
        if name in wanted or (name == "full" and wanted & set(EXEC_VARIANTS)):
            log.info("[ablate] %s: train + calibrate", name)
            run = _train_and_calibrate(cfg, name, overrides)
            if name in wanted:
                results[name] = _evaluate(cfg, run, f"model_{name}", "aurd", {})
    full_run = Path(cfg.out) / "runs" / "full"
    for name, (executor, options) in EXEC_VARIANTS.items():
        if name in wanted:
            log.info("[ablate] full model with %s", name)
            results[f"exec_{name}"] = _evaluate(cfg, full_run, f"exec_{name}", executor, options)
    header = ["| variant | success | 95% CI | episodes | mean horizon | replans | prunes | pauses |",
              "|---|---|---|---|---|---|---|---|"]
    lines = [f"# Ablations ({cfg.env}/{cfg.suite}, {cfg.episodes} episodes per task, perturb={cfg.perturb}, "
             f"{cfg.steps} training steps, seed {cfg.seed})", ""]
    for title, keys in [
        ("Table 4: action heads (AURD)", ["full", "discrete_only", "continuous_only"]),
        ("Table 5: loss terms (AURD)", ["full", "no_sp", "no_rl", "il_only"]),
        ("Table 6: execution strategy (full model)", [f"exec_{k}" for k in EXEC_VARIANTS]),
    ]:
        rows = [_row(k.removeprefix("exec_"), results[k]) for k in keys if k in results]
        if rows:
            lines += [f"## {title}", "", *header, *rows, ""]
    table = "\n".join(lines)
    atomic_write_bytes(Path(cfg.out) / "ablation.md", table.encode())
    return table
