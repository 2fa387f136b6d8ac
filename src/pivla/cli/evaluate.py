"""``pivla eval``, ``pivla calibrate`` and ``pivla report``."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from pivla.control.calibrate import CalibrationConfig
from pivla.evaluation.runner import EvalConfig


def evaluate(cfg: EvalConfig) -> int:
    from pivla.evaluation.runner import evaluate as run

    res = run(cfg)
    lo, hi = res["ci95"]
    print(f"{cfg.executor.kind}: success {res['success_rate']:.1%} [{lo:.1%}, {hi:.1%}] over {res['episodes']} "
          f"episodes; mean horizon {res['mean_executed_horizon']:.2f}, replans {res['replans']}, prunes "
          f"{res['prunes']}, pauses {res['pauses']}, control {res['control_hz']:.0f} Hz -> {cfg.out}/results.json")
    if cfg.execution.kind != "sync" or cfg.latency_ms.strip() != "0":
        qpm = res["queries_per_minute"]
        latency = "measured" if cfg.latency_ms.strip() == "real" else f"{cfg.latency_ms} ms"
        print(f"  {cfg.execution.kind}, latency {latency}: idle {res['idle_fraction']:.1%} of the steps, "
              f"{'-' if qpm is None else f'{qpm:.0f}'} queries per minute, {res['stale_chunks']} stale chunks, "
              f"{res['failed_queries']} queries lost")
    return 0


@dataclass
class CalibrateCommand:
    """AURD's thresholds from validation episodes: the policy's own successful validation rollouts
    (``pivla eval --split validation --record DIR``), validation demonstrations, or the episodes a run held out."""

    policy: str
    """Run directory; calibration.json is written into it."""
    data: str
    """Validation dataset (its successful episodes are used)."""
    held_out: bool = False
    """--data is the run's training data: use only the episodes its split.json held out."""
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    """Percentiles and the U_pred baseline."""


def held_out_episodes(run_dir: str, episodes: list) -> list:
    """The episodes of a run's training data that its ``split.json`` kept out of training."""
    path = Path(run_dir) / "split.json"
    if not path.exists():
        raise SystemExit(f"--held-out: {path} not found (written by `pivla train`); give --data without --held-out")
    split = json.loads(path.read_text())
    n = len(split["train_episodes"]) + len(split["val_episodes"])
    if n != len(episodes):
        raise SystemExit(f"--held-out: the run was trained on {n} episodes, --data has {len(episodes)}; "
                         "give the run's training data (without --extra-data)")
    if not split["val_episodes"]:
        raise SystemExit("--held-out: the run held out no episodes (trained with --val-fraction 0)")
    return [episodes[i] for i in split["val_episodes"]]


def calibrate(cmd: CalibrateCommand) -> int:
    from pivla.control.calibrate import calibrate as run
    from pivla.data.read import read_dataset
    from pivla.policy import load_policy
    from pivla.training.checkpoint import write_calibration

    policy = load_policy(cmd.policy, device="cpu")
    episodes = read_dataset(cmd.data)
    source = cmd.data
    if cmd.held_out:
        episodes = held_out_episodes(cmd.policy, episodes)
        source += " (held-out split)"
    try:
        calib, stats = run(policy, episodes, cmd.calibration, source=source)
    except ValueError as e:  # test rollouts, or no successful episode to calibrate on
        raise SystemExit(f"pivla calibrate: {e}") from e
    write_calibration(cmd.policy, vars(calib), stats)
    print(json.dumps({"calibration": vars(calib), **stats}, indent=2))
    return 0


@dataclass
class ReportConfig:
    """Which evaluations to report on."""

    dir: str
    """Directory of evaluations (DIR/<condition>/<executor>/results.json), or of a twin benchmark."""


def report(cfg: ReportConfig) -> int:
    from pivla.experiments.studies import write_report

    try:  # a benchmark directory gets the benchmark's tables, the same ones pivla benchmark writes
        path = write_report(cfg.dir)
    except ValueError as e:  # an evaluation layout the report cannot read; said in the message
        raise SystemExit(f"pivla report: {e}") from e
    print(f"report written to {path}")
    return 0
