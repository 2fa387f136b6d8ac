"""The main job, end to end on the simulated twin: collect expert demos on pick_place -> train the validated
recipe -> run it on validation seeds and calibrate AURD on its successful rollouts -> evaluate AURD, fixed,
ensemble and AdaHorizon in distribution, under perturbations and with the object displaced mid-chunk -> report.

Every stage writes into ``out`` and is skipped when its output already exists, so an interrupted demo
continues where it stopped. Seeds come from the families of :mod:`pivla.envs.seeds`: demonstrations from
train, calibration from validation, every reported figure from test.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro

from pivla.control.asynchronous import AsyncConfig, ExecutionConfig, SyncConfig
from pivla.control.calibrate import CalibrationConfig
from pivla.control.executors import executor_config
from pivla.envs.backend import BackendConfig
from pivla.envs.collect import CollectConfig, collect_demos
from pivla.evaluation.protocol import calibrate_on_rollouts, recipe, validation_rollouts
from pivla.evaluation.report import write_report
from pivla.evaluation.runner import EvalConfig, evaluate
from pivla.training.config import TrainConfig, check_target_divides
from pivla.training.trainer import train

log = logging.getLogger("pivla.demo")

EXECUTORS = ("aurd", "fixed", "ensemble", "adahorizon")
# condition -> (its code in the seed families, perturbation spec)
CONDITIONS = {"in_distribution": ("in_distribution", None),
              "static_distractors": ("static_distractors", "static_distractors"),
              "unseen_env": ("unseen_env", "unseen_env"),
              "dynamic_distractors": ("dynamic_distractors", "dynamic_distractors"),
              "camera_jitter": ("camera_jitter", "camera_jitter"),
              # the object jumps 4 cm while the second chunk executes: what replanning exists for
              "displace_object_4": ("displace_object", "displace_object=4")}


@dataclass
class DemoConfig:
    """Sizes of the main job: about 17 min on 2 CPU cores (docs/results.md#demo-wall-time); ``--quick`` is a
    few-minute smoke run that still trains and evaluates for real."""

    out: str = "runs/demo"
    """Directory of the whole job (data, policy, evaluations, report.md)."""
    seed: int = 0
    """Training seed (initialisation, batches, augmentation); episodes come from the seed families."""
    realism: Literal["ideal", "servo"] = "ideal"
    """Twin actuation: ideal, or hobby-servo backlash, deadband and noise."""
    train_episodes: int = 90
    """Training demonstrations per task (docs/experiments.md#90-demonstrations-per-task-with-4000-steps)."""
    val_episodes: int = 5
    """Validation demonstrations and rollouts per task, for calibration only."""
    test_episodes: int = 10
    """Test episodes per task and condition."""
    steps: int = TrainConfig.steps
    """Training steps (the recipe's)."""
    batch_size: int = TrainConfig.batch_size
    """Training batch (the recipe's)."""
    image_size: int = 80
    """Camera and policy resolution: 80 px trains 1.6x faster than 96 at the same success
    (docs/experiments.md#80-px-cameras)."""
    noise: float = 0.3
    """DART: noise on executed expert actions, clean labels (recovery data)."""
    miss: float = 0.3
    """Share of training demos whose first grasp misses and is recovered
    (docs/experiments.md#missed-grasp-recovery-in-the-demonstrations)."""
    train_perturb: str | None = "randomized_scene"
    """Training scenes restyled and cluttered with shapes the tests never use
    (docs/experiments.md#training-scene-randomisation)."""
    conditions: tuple[str, ...] = ("in_distribution", "static_distractors", "unseen_env", "displace_object_4")
    """Test conditions, every executor on each (in_distribution, static_distractors, unseen_env,
    dynamic_distractors, camera_jitter, displace_object_4)."""
    levels: tuple[int, ...] = (2, 4, 6)
    """Distraction levels of the Fig. 8 sweep (level 0 is the in-distribution evaluation)."""
    level_executors: tuple[str, ...] = ("aurd", "fixed")
    """Executors of the distraction sweep."""
    level_episodes: int = 5
    """Episodes per task and level."""
    latency_ms: str | None = "200"
    """The latency cell (docs/latency.md): the fixed horizon in distribution with the policy answering this late,
    synchronously and asynchronously (threshold 3, the one that kept its success at 200 ms); None: no cell."""
    workers: int = 2
    """Worker processes for collection and evaluation."""
    dispatch: Annotated[BackendConfig, tyro.conf.arg(name="")] = dataclasses.field(default_factory=BackendConfig)
    """Where the episodes run: --backend local | ray, --ray-address HOST:PORT (docs/cluster.md)."""
    calibration: CalibrationConfig = dataclasses.field(default_factory=CalibrationConfig)
    """AURD's calibration on the validation rollouts."""


def quick(base: DemoConfig | None = None) -> DemoConfig:
    """The smoke-run sizes: a few episodes, 300 training steps."""
    return dataclasses.replace(base or DemoConfig(), train_episodes=6, val_episodes=2, test_episodes=1, steps=300,
                               levels=(4,), level_episodes=1)


def train_config(cfg: DemoConfig, data: Path, run: Path) -> TrainConfig:
    """The recipe at the demo's sizes; an image size the target's downsampling does not divide is refused
    before anything is collected."""
    tc = recipe(str(data), str(run), cfg.seed, steps=cfg.steps, batch_size=cfg.batch_size, image_size=cfg.image_size)
    check_target_divides(tc.model)
    return tc


def _stage(name: str, done: bool) -> bool:
    log.info("[%s] %s", name, "already done, skipping" if done else "...")
    return not done


def run_demo(cfg: DemoConfig) -> Path:
    """Run (or resume) every stage; returns the path of report.md."""
    out = Path(cfg.out)
    train_dir, val_dir, run_dir = out / "data" / "train", out / "data" / "val", out / "policy"
    tc = train_config(cfg, train_dir, run_dir)
    out.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}
    t_all = time.time()

    def timed(name: str, fn: Callable[[], object]) -> None:
        t = time.time()
        fn()
        timings[name] = round(time.time() - t, 1)

    unknown = sorted(set(cfg.conditions) - set(CONDITIONS))
    if unknown:
        raise ValueError(f"unknown conditions {unknown}; known: {', '.join(CONDITIONS)}")
    demos = CollectConfig(out=str(train_dir), suite="pick_place", env="tabletop", episodes=cfg.train_episodes,
                          seed_family="train", perturb=cfg.train_perturb, workers=cfg.workers, realism=cfg.realism,
                          image_size=cfg.image_size, noise=cfg.noise, miss=cfg.miss, dispatch=cfg.dispatch)
    if _stage("collect train demos", (train_dir / "rock_right_demo.hdf5").exists()):
        timed("collect_train", lambda: collect_demos(demos))
    if _stage("collect validation demos", (val_dir / "rock_right_demo.hdf5").exists()):
        val = dataclasses.replace(demos, out=str(val_dir), episodes=cfg.val_episodes, seed_family="validation",
                                  perturb=None, noise=0.0, miss=0.0)
        timed("collect_val", lambda: collect_demos(val))
    status = run_dir / "status.json"
    if _stage("train", status.exists() and json.loads(status.read_text()).get("done", False)):
        timed("train", lambda: train(tc, resume=(run_dir / "checkpoints").exists()))
    rollouts_dir = out / "data" / "val_rollouts"
    if _stage("validation rollouts", (rollouts_dir / "rock_right_rollouts.hdf5").exists()):
        timed("validation_rollouts", lambda: _log_eval(validation_rollouts(
            run_dir, rollouts_dir, out / "data" / "val_rollouts_eval", cfg.val_episodes, cfg.seed, cfg.realism,
            cfg.workers, family=True, dispatch=cfg.dispatch), "validation", "fixed"))
    if _stage("calibrate", (run_dir / "calibration.json").exists()):
        timed("calibrate", lambda: calibrate_on_rollouts(run_dir, rollouts_dir, val_dir, cfg.calibration))
    sync: ExecutionConfig = SyncConfig()
    cells = [(c, e, *CONDITIONS[c], cfg.test_episodes, 2, sync, "0") for c in cfg.conditions for e in EXECUTORS]
    cells += [(f"distraction_level_{lv}", e, "distraction_level", f"level={lv}" if lv else None, cfg.level_episodes, 0,
               sync, "0") for lv in cfg.levels for e in cfg.level_executors]
    if cfg.latency_ms is not None:
        cells += [(f"latency_{cfg.latency_ms}ms_{mode.kind}", "fixed", "in_distribution", None, cfg.test_episodes, 0,
                   mode, cfg.latency_ms) for mode in (sync, AsyncConfig(threshold=3))]
    for condition, executor, code, perturb, episodes, videos, execution, latency in cells:
        target = out / "eval" / condition / executor
        if _stage(f"eval {condition} {executor}", (target / "results.json").exists()):
            ec = EvalConfig(policy=str(run_dir), out=str(target), executor=executor_config(executor),
                            episodes=episodes, seed_family="test", condition=code, perturb=perturb,
                            realism=cfg.realism, workers=cfg.workers, dispatch=cfg.dispatch, videos=videos,
                            execution=execution, latency_ms=latency)
            timed(f"eval_{condition}_{executor}",
                  lambda ec=ec, c=condition, e=executor: _log_eval(evaluate(ec, progress=False), c, e))
    report = write_report(out)
    timings["total_this_invocation"] = round(time.time() - t_all, 1)
    (out / "timings.json").write_text(json.dumps(timings, indent=2) + "\n")
    log.info("timings (s): %s", timings)
    return report


def _log_eval(res: dict, condition: str, executor: str) -> None:
    lo, hi = res["ci95"]
    log.info("  %s / %s: success %.1f%% [%.1f, %.1f] (%d episodes), mean horizon %.2f", condition, executor,
             100 * res["success_rate"], 100 * lo, 100 * hi, res["episodes"], res["mean_executed_horizon"])
