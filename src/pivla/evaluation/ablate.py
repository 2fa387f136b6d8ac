"""``pivla ablate``: the structure of the paper's Tables 4-7 on the simulator.

Table 4 (action heads): full, discrete-only, continuous-only. Table 5 (loss terms): full, w/o L_SP,
w/o L_RL, IL only. Table 6 (execution): the full model with AURD, AURD in the paper's literal check order,
fixed horizon, ACT temporal ensembling and AdaHorizon. Table 7 (components added one at a time): a
continuous head trained by imitation alone and run at a fixed horizon (the OpenVLA-OFT row), + the discrete
head (IL only), + the unified loss (the full model), + AURD; each row against the one above it. Every variant
goes through the demo's recipe (:mod:`pivla.evaluation.protocol`) with the same data, seed and steps: trained,
run on the same validation seeds, calibrated on its own successful validation rollouts, and evaluated on the
same test seeds.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from pivla.control.calibrate import CalibrationConfig
from pivla.control.executors import ExecutorConfig, executor_config
from pivla.evaluation.protocol import calibrate_on_rollouts, validation_rollouts
from pivla.evaluation.runner import EvalConfig, evaluate, load_rows
from pivla.evaluation.stats import compare, format_difference, paired_successes, percent_interval, wilson_interval
from pivla.io import atomic_write_bytes
from pivla.training.config import TrainConfig, check_target_divides
from pivla.training.trainer import train

log = logging.getLogger(__name__)

# variant -> (table, loss overrides)
TRAIN_VARIANTS: dict[str, tuple[str, dict]] = {
    "full": ("heads+loss", {}),
    "discrete_only": ("heads", {"use_continuous": False}),
    "continuous_only": ("heads", {"use_discrete": False}),
    "no_sp": ("loss", {"use_sp": False}),
    "no_rl": ("loss", {"use_rl": False}),
    "il_only": ("loss", {"use_sp": False, "use_rl": False, "use_recon": False}),
    "continuous_il_only": ("components", {"use_discrete": False, "use_sp": False, "use_rl": False, "use_recon": False}),
}
# Table 7: (row, trained variant, executor whose result counts): each adds one component to the row above
INCREMENTAL: tuple[tuple[str, str, str], ...] = (
    ("continuous head, IL only, fixed H=5 (OpenVLA-OFT)", "continuous_il_only", "fixed"),
    ("+ dual heads (discrete + continuous)", "il_only", "fixed"),
    ("+ unified loss (L_IL + alpha L_RL + beta L_SP)", "full", "fixed"),
    ("+ AURD (full PI-VLA)", "full", "aurd"),
)
# executor variants of the full model
EXEC_VARIANTS: dict[str, ExecutorConfig] = {
    "aurd": executor_config("aurd"),
    "aurd_check_after": executor_config("aurd", check="after"),
    "fixed_h5": executor_config("fixed", horizon=5),
    "fixed_h8": executor_config("fixed", horizon=8),
    "ensemble": executor_config("ensemble"),
    "adahorizon": executor_config("adahorizon"),
}


@dataclass
class AblationConfig:
    """Every variant trained with the recipe on the same data and seed, calibrated on its own validation
    rollouts, evaluated on the same test seeds."""

    data: str
    """Training dataset."""
    val: str
    """Validation demonstrations (calibration falls back to them when a variant's rollouts all fail)."""
    out: str
    """Directory of the ablation (runs/, eval/, ablation.md); an interrupted ablation resumes."""
    train: TrainConfig = field(default_factory=TrainConfig)
    """Training of every variant (the recipe by default; data, out and seed are set per variant)."""
    seed: int = 1000
    """First test seed."""
    train_seed: int = 0
    """Training seed of every variant."""
    val_episodes: int = 5
    """Validation rollouts per task, for calibration."""
    val_seed: int = 1
    """Seed of the validation rollouts (the demo's validation demonstrations use the same)."""
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    """AURD's calibration of every variant."""
    env: Literal["tabletop", "libero"] = "tabletop"
    """Environment family."""
    suite: str = "pick_place"
    """Task suite."""
    tasks: str | None = None
    """Task indices or names, comma-separated (default: all)."""
    episodes: int = 10
    """Test episodes per task."""
    perturb: str | None = None
    """Twin perturbation spec of the test episodes."""
    realism: Literal["ideal", "servo"] = "ideal"
    """Twin actuation."""
    workers: int = 2
    """Worker processes."""
    variants: tuple[str, ...] | None = None
    """Subset of the variants (default: all)."""
    max_steps: int | None = None
    """Step limit per episode (default: the task's own)."""


def _train_and_calibrate(cfg: AblationConfig, name: str, loss_overrides: dict) -> Path:
    run = Path(cfg.out) / "runs" / name
    status = run / "status.json"
    if not (status.exists() and json.loads(status.read_text()).get("done")):
        tc = dataclasses.replace(cfg.train, data=cfg.data, out=str(run), seed=cfg.train_seed, progress=False,
                                 loss=dataclasses.replace(cfg.train.loss, **loss_overrides))
        train(tc, resume=(run / "checkpoints").exists())
    rollouts, rollouts_eval = Path(cfg.out) / "val_rollouts" / name, Path(cfg.out) / "val_rollouts_eval" / name
    if not (rollouts_eval / "results.json").exists():
        validation_rollouts(run, rollouts, rollouts_eval, cfg.val_episodes, cfg.val_seed, cfg.realism, cfg.workers,
                            cfg.env, cfg.suite, cfg.tasks, cfg.max_steps)
    if not (run / "calibration.json").exists():
        calibrate_on_rollouts(run, rollouts, Path(cfg.val), cfg.calibration)
    return run


def _evaluate(cfg: AblationConfig, run: Path, name: str, executor: ExecutorConfig) -> dict:
    """Evaluate (or reuse a finished evaluation: an interrupted ablation continues where it stopped)."""
    out = Path(cfg.out) / "eval" / name
    if (out / "results.json").exists():
        return {**json.loads((out / "results.json").read_text()), "dir": str(out)}
    ec = EvalConfig(policy=str(run), out=str(out), env=cfg.env, suite=cfg.suite, tasks=cfg.tasks, executor=executor,
                    episodes=cfg.episodes, seed=cfg.seed, perturb=cfg.perturb, realism=cfg.realism,
                    workers=cfg.workers, videos=0, max_steps=cfg.max_steps)
    return {**evaluate(ec, progress=False), "dir": str(out)}


def _rate(r: dict) -> str:
    return f"{100 * r['success_rate']:.1f}% {percent_interval(*wilson_interval(r['successes'], r['episodes']))}"


def _diff(r: dict, ref: dict | None) -> str:
    """Difference in points to the reference row, paired over the same test episodes: Newcombe's method 10
    95% interval and the exact McNemar p."""
    if ref is None or r is ref:
        return ""
    return format_difference(compare(*paired_successes(load_rows(Path(r["dir"]) / "episodes.jsonl"),
                                                       load_rows(Path(ref["dir"]) / "episodes.jsonl"))))


def _model_row(name: str, aurd: dict, fixed: dict, ref: dict | None) -> str:
    return (f"| {name} | {_rate(aurd)} | {_rate(fixed)} | {_diff(aurd, ref)} | {aurd['episodes']} | "
            f"{aurd['mean_executed_horizon']:.2f} |")


def _exec_row(name: str, r: dict, ref: dict | None) -> str:
    return (f"| {name} | {_rate(r)} | {_diff(r, ref)} | {r['episodes']} | {r['mean_executed_horizon']:.2f} | "
            f"{r['replans']} | {r['prunes']} | {r['pauses']} |")


def run_ablation(cfg: AblationConfig) -> str:
    wanted = set(cfg.variants or (*TRAIN_VARIANTS, *EXEC_VARIANTS))
    unknown = wanted - set(TRAIN_VARIANTS) - set(EXEC_VARIANTS)
    if unknown:
        raise ValueError(f"unknown ablation variants {sorted(unknown)}; "
                         f"known: {sorted({*TRAIN_VARIANTS, *EXEC_VARIANTS})}")
    check_target_divides(cfg.train.model)
    models: dict[str, tuple[dict, dict]] = {}  # variant -> (AURD, fixed H=5) results
    for name, (_, overrides) in TRAIN_VARIANTS.items():
        if name in wanted or (name == "full" and wanted & set(EXEC_VARIANTS)):
            log.info("[ablate] %s: train + calibrate", name)
            run = _train_and_calibrate(cfg, name, overrides)
            if name in wanted:  # fixed horizon too: the model's quality apart from AURD's signals
                models[name] = (_evaluate(cfg, run, f"model_{name}", EXEC_VARIANTS["aurd"]),
                                _evaluate(cfg, run, f"model_{name}_fixed_h5", EXEC_VARIANTS["fixed_h5"]))
    full_run = Path(cfg.out) / "runs" / "full"
    execs: dict[str, dict] = {}
    for name, executor in EXEC_VARIANTS.items():
        if name in wanted:
            log.info("[ablate] full model with %s", name)
            execs[name] = _evaluate(cfg, full_run, f"exec_{name}", executor)
    lines = [f"# Ablations ({cfg.env}/{cfg.suite}, {cfg.episodes} episodes per task, perturb={cfg.perturb}, "
             f"{cfg.train.steps} training steps of {cfg.train.batch_size}, training seed {cfg.train_seed}, "
             f"test seed {cfg.seed})",
             "", "Success with 95% Wilson intervals; differences in points, paired over the same test episodes "
             "(Newcombe's method 10 95% interval, exact McNemar p).", ""]
    model_header = ["| variant | AURD | fixed H=5 | AURD - full | episodes | AURD mean horizon |",
                    "|---|---|---|---|---|---|"]
    ref = models.get("full", (None, None))[0]
    for title, keys in [("Table 4: action heads", ["full", "discrete_only", "continuous_only"]),
                        ("Table 5: loss terms", ["full", "no_sp", "no_rl", "il_only"])]:
        rows = [_model_row(k, *models[k], ref) for k in keys if k in models]
        if rows:
            lines += [f"## {title}", "", *model_header, *rows, ""]
    steps = [(row, models[v][0 if ex == "aurd" else 1]) for row, v, ex in INCREMENTAL if v in models]
    if len(steps) == len(INCREMENTAL):
        lines += ["## Table 7: components added one at a time", "",
                  "| configuration | success | - row above | episodes | mean horizon |", "|---|---|---|---|---|",
                  *[f"| {row} | {_rate(r)} | {_diff(r, steps[i - 1][1] if i else None)} | {r['episodes']} | "
                    f"{r['mean_executed_horizon']:.2f} |" for i, (row, r) in enumerate(steps)], ""]
    if execs:
        fixed_ref = execs.get("fixed_h5")
        lines += ["## Table 6: execution strategy (full model)", "",
                  "| executor | success | - fixed H=5 | episodes | mean horizon | replans | prunes | pauses |",
                  "|---|---|---|---|---|---|---|---|", *[_exec_row(k, r, fixed_ref) for k, r in execs.items()], ""]
    table = "\n".join(lines)
    atomic_write_bytes(Path(cfg.out) / "ablation.md", table.encode())
    return table
