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

from pivla.control.asynchronous import AsyncConfig, SyncConfig
from pivla.control.calibrate import CalibrationConfig
from pivla.control.executors import executor_config
from pivla.envs.backend import BackendConfig
from pivla.envs.collect import CollectConfig
from pivla.experiments import conditions
from pivla.experiments.layout import DemoLayout
from pivla.experiments.plan import Evaluation, EvaluationPlan, eval_config
from pivla.experiments.recipes import recipe_config
from pivla.experiments.report import write_report
from pivla.experiments.stages import (
    Calibrate,
    Collect,
    Evaluate,
    Train,
    perform,
    shared_evaluations,
    validation_rollouts,
)
from pivla.model.config import BackboneConfig
from pivla.training.config import TrainConfig, check_target_divides

log = logging.getLogger("pivla.demo")

EXECUTORS = ("aurd", "fixed", "ensemble", "adahorizon")
# the conditions --conditions may name (pivla.experiments.conditions); displace_object_4: the object jumps 4 cm
# while the second chunk executes, what replanning exists for
CONDITIONS = ("in_distribution", "static_distractors", "unseen_env", "dynamic_distractors", "camera_jitter",
              "displace_object_4")
POLICY = "policy"  # the demo's one policy


@dataclass
class DemoConfig:
    """Sizes of the main job (its wall time: docs/results.md#demo-wall-time); ``--quick`` is a
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
    vision_channels: tuple[int, ...] = BackboneConfig.vision_channels
    """Widths of the CNN's stages (the recipe's). 16 32 64 128 with --value-refresh-every 2000 took the demo from
    39.5 to 28.6 min on an AVX2-only 2-core box, and 7 points of test success over every cell
    (docs/experiments.md#a-narrower-cnn-and-one-value-refresh)."""
    value_refresh_every: int = TrainConfig.value_refresh_every
    """Training steps between refreshes of the GAE table, each a pass of V over every training frame (the
    recipe's: 0, five a run)."""
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
    synchronously and asynchronously (the auto threshold and the align seam, which keeps the twin's success at
    200 ms); None: no cell."""
    workers: int = 2
    """Worker processes for collection and evaluation."""
    dispatch: Annotated[BackendConfig, tyro.conf.arg(name="")] = dataclasses.field(default_factory=BackendConfig)
    """Where the episodes and the training run: --backend local | ray (the training a Ray task, a GPU where the
    cluster has them), --ray-address HOST:PORT (docs/cluster.md)."""
    calibration: CalibrationConfig = dataclasses.field(default_factory=CalibrationConfig)
    """AURD's calibration on the validation rollouts."""


def quick(base: DemoConfig | None = None) -> DemoConfig:
    """The smoke-run sizes: a few episodes, 300 training steps."""
    return dataclasses.replace(base or DemoConfig(), train_episodes=6, val_episodes=2, test_episodes=1, steps=300,
                               levels=(4,), level_episodes=1)


def train_config(cfg: DemoConfig, data: Path, run: Path) -> TrainConfig:
    """The recipe at the demo's sizes; an image size the target's downsampling does not divide is refused
    before anything is collected."""
    base = TrainConfig().model
    model = dataclasses.replace(base, backbone=dataclasses.replace(base.backbone, vision_channels=cfg.vision_channels))
    tc = recipe_config(str(data), str(run), cfg.seed, steps=cfg.steps, batch_size=cfg.batch_size,
                       image_size=cfg.image_size, model=model)
    check_target_divides(tc.model)
    return dataclasses.replace(tc, value_refresh_every=cfg.value_refresh_every)


def plans(cfg: DemoConfig) -> list[EvaluationPlan]:
    """The test evaluations, in their run order: every executor on every condition (with videos), the
    distraction sweep, then the latency cell synchronously and asynchronously."""
    unknown = sorted(set(cfg.conditions) - set(CONDITIONS))
    if unknown:
        raise ValueError(f"unknown conditions {unknown}; known: {', '.join(CONDITIONS)}")

    def ev(cell: conditions.Cell, executor: str) -> Evaluation:
        return Evaluation(POLICY, cell, executor, executor_config(executor))

    out = [EvaluationPlan.of([ev(conditions.twin(c), e) for c in cfg.conditions for e in EXECUTORS],
                             episodes=cfg.test_episodes, videos=2),
           EvaluationPlan.of([ev(conditions.distraction_level(lv), e) for lv in cfg.levels
                              for e in cfg.level_executors], episodes=cfg.level_episodes)]
    if cfg.latency_ms is not None:
        for mode in (SyncConfig(), AsyncConfig(seam="align")):
            cell = dataclasses.replace(conditions.IN_DISTRIBUTION, name=f"latency_{cfg.latency_ms}ms_{mode.kind}")
            out.append(EvaluationPlan.of([ev(cell, "fixed")], episodes=cfg.test_episodes, execution=mode,
                                         latency_ms=cfg.latency_ms))
    return out


def run_demo(cfg: DemoConfig) -> Path:
    """Run (or resume) every stage; returns the path of report.md."""
    out = DemoLayout(Path(cfg.out))
    tc = train_config(cfg, out.train_data, out.policy)
    out.root.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}
    t_all = time.time()

    def timed(name: str, fn: Callable[[], object]) -> object:
        t = time.time()
        result = fn()
        timings[name] = round(time.time() - t, 1)
        return result

    test_plans = plans(cfg)
    demos = CollectConfig(out=str(out.train_data), suite="pick_place", env="tabletop", episodes=cfg.train_episodes,
                          seed_family="train", perturb=cfg.train_perturb, workers=cfg.workers, realism=cfg.realism,
                          image_size=cfg.image_size, noise=cfg.noise, miss=cfg.miss, dispatch=cfg.dispatch)
    perform(Collect(demos, strict=False), "collect_train", "collect train demos", timed)
    val = dataclasses.replace(demos, out=str(out.val_data), episodes=cfg.val_episodes, seed_family="validation",
                              perturb=None, noise=0.0, miss=0.0)
    perform(Collect(val, strict=False), "collect_val", "collect validation demos", timed)
    perform(Train(tc, cfg.dispatch), "train", timed=timed)
    with shared_evaluations(cfg.workers, cfg.dispatch):
        rollouts = validation_rollouts(out.policy, out.val_rollouts, out.val_rollouts_eval,
                                       conditions.IN_DISTRIBUTION, episodes=cfg.val_episodes, seed=cfg.seed,
                                       realism=cfg.realism, workers=cfg.workers, family=True, dispatch=cfg.dispatch)
        res = perform(rollouts, "validation_rollouts", "validation rollouts", timed)
        if res is not None:
            _log_eval(res, "validation", "fixed")
        perform(Calibrate(out.policy, out.val_rollouts, out.val_data, cfg.calibration), "calibrate", timed=timed)
        for plan in test_plans:
            for ev in plan:
                condition, executor = ev.cell.name, ev.label
                stage = Evaluate(eval_config(ev, plan, policy=out.policy, out=out.evaluation(condition, executor),
                                             realism=cfg.realism, family=True, workers=cfg.workers,
                                             dispatch=cfg.dispatch))
                res = perform(stage, f"eval_{condition}_{executor}", f"eval {condition} {executor}", timed)
                if res is not None:
                    _log_eval(res, condition, executor)
    report = write_report(out.root)
    timings["total_this_invocation"] = round(time.time() - t_all, 1)
    out.timings.write_text(json.dumps(timings, indent=2) + "\n")
    log.info("timings (s): %s", timings)
    return report


def _log_eval(res: dict, condition: str, executor: str) -> None:
    lo, hi = res["ci95"]
    log.info("  %s / %s: success %.1f%% [%.1f, %.1f] (%d episodes), mean horizon %.2f", condition, executor,
             100 * res["success_rate"], 100 * lo, 100 * hi, res["episodes"], res["mean_executed_horizon"])
