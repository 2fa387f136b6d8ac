"""``pivla ablate``: the structure of the paper's Tables 4-7 on the simulator.

Table 4 (action heads): full, discrete-only, continuous-only. Table 5 (loss terms): full, w/o L_SP,
w/o L_RL, IL only. Table 6 (execution): the full model with AURD, AURD in the paper's literal check order,
fixed horizon, ACT temporal ensembling and AdaHorizon. Table 7 (components added one at a time): a
continuous head trained by imitation alone and run at a fixed horizon (the OpenVLA-OFT row), + the discrete
head (IL only), + the unified loss (the full model), + AURD; each row against the one above it. Every variant
goes through the demo's recipe (:mod:`pivla.experiments.stages`) with the same data, seed and steps: trained,
run on the same validation seeds, calibrated on its own successful validation rollouts, and evaluated on the
same test seeds.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from pivla.control.calibrate import CalibrationConfig
from pivla.evaluation.stats import format_difference, percent_interval, wilson_interval
from pivla.experiments.conditions import Cell
from pivla.experiments.layout import AblationLayout
from pivla.experiments.plan import Evaluation, EvaluationPlan, eval_config
from pivla.experiments.recipes import INCREMENTAL, TRAIN_VARIANTS, execution_variant
from pivla.experiments.render import Block, Table, write_markdown
from pivla.experiments.results import ResultsStore
from pivla.experiments.stages import Calibrate, Evaluate, Train, validation_rollouts
from pivla.training.config import TrainConfig, check_target_divides

log = logging.getLogger(__name__)

# Table 6: the full model's execution strategies (labels of pivla.experiments.recipes.EXECUTION_VARIANTS)
EXEC_VARIANTS = ("aurd", "aurd_check_after", "fixed_h5", "fixed_h8", "ensemble", "adahorizon")


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


def _test_cell(cfg: AblationConfig) -> Cell:
    return Cell("test", None, cfg.perturb, suite=cfg.suite, env=cfg.env)


@dataclass(frozen=True)
class AblationPlan:
    """The variants to train, in order, and the test evaluations: ``models``, each trained variant with AURD and
    the fixed horizon H=5 (the model's quality apart from AURD's signals); ``executions``, the full model with
    each execution variant (labelled by it)."""

    trained: tuple[str, ...]
    models: EvaluationPlan
    executions: EvaluationPlan

    @staticmethod
    def model_key(ev: Evaluation) -> tuple[str]:
        return AblationLayout.model_key(ev.policy, fixed=ev.label != "aurd")

    @staticmethod
    def exec_key(ev: Evaluation) -> tuple[str]:
        return AblationLayout.exec_key(ev.label)


def plan(cfg: AblationConfig) -> AblationPlan:
    wanted = set(cfg.variants or (*TRAIN_VARIANTS, *EXEC_VARIANTS))
    unknown = wanted - set(TRAIN_VARIANTS) - set(EXEC_VARIANTS)
    if unknown:
        raise ValueError(f"unknown ablation variants {sorted(unknown)}; "
                         f"known: {sorted({*TRAIN_VARIANTS, *EXEC_VARIANTS})}")
    cell = _test_cell(cfg)
    trained = tuple(v for v in TRAIN_VARIANTS if v in wanted or (v == "full" and wanted & set(EXEC_VARIANTS)))
    models = [Evaluation(v, cell, label, execution_variant(label))
              for v in trained if v in wanted for label in ("aurd", "fixed_h5")]
    executions = [Evaluation("full", cell, label, execution_variant(label)) for label in EXEC_VARIANTS
                  if label in wanted]
    return AblationPlan(trained, EvaluationPlan.of(models, episodes=cfg.episodes),
                        EvaluationPlan.of(executions, episodes=cfg.episodes))


def _train_and_calibrate(cfg: AblationConfig, layout: AblationLayout, variant: str) -> None:
    run = layout.policy(variant)
    Train(dataclasses.replace(cfg.train, data=cfg.data, out=str(run), seed=cfg.train_seed, progress=False,
                              loss=dataclasses.replace(cfg.train.loss, **TRAIN_VARIANTS[variant][1])))()
    validation_rollouts(run, layout.val_rollouts(variant), layout.val_rollouts_eval(variant),
                        Cell("validation", None, suite=cfg.suite, env=cfg.env), episodes=cfg.val_episodes,
                        seed=cfg.val_seed, realism=cfg.realism, workers=cfg.workers, family=False, tasks=cfg.tasks,
                        max_steps=cfg.max_steps)()
    Calibrate(run, layout.val_rollouts(variant), Path(cfg.val), cfg.calibration)()


def run_ablation(cfg: AblationConfig) -> str:
    test = plan(cfg)
    check_target_divides(cfg.train.model)
    layout = AblationLayout(Path(cfg.out))
    # the run order: each variant trained and calibrated, then tested; the execution variants last
    for variant in test.trained:
        log.info("[ablate] %s: train + calibrate", variant)
        _train_and_calibrate(cfg, layout, variant)
        for ev in test.models.of_policies([variant]):
            _evaluate(cfg, layout, ev, test.models, test.model_key(ev))
    for ev in test.executions:
        log.info("[ablate] full model with %s", ev.label)
        _evaluate(cfg, layout, ev, test.executions, test.exec_key(ev))
    return write_markdown(layout.report_md, report(cfg, layout, test))


def _evaluate(cfg: AblationConfig, layout: AblationLayout, ev: Evaluation, plan: EvaluationPlan,
              key: tuple[str]) -> dict:
    """Evaluate (or reuse a finished evaluation: an interrupted ablation continues where it stopped)."""
    return Evaluate(eval_config(ev, plan, policy=layout.policy(ev.policy), out=layout.evaluation(key),
                                realism=cfg.realism, family=False, seed=cfg.seed, tasks=cfg.tasks,
                                workers=cfg.workers, max_steps=cfg.max_steps))()


def report(cfg: AblationConfig, layout: AblationLayout, test: AblationPlan) -> list[Block]:
    """Tables 4 and 5 (trained variants, AURD and fixed H=5), 7 (components added one at a time) and 6 (the full
    model's execution strategies), from the evaluations of the plan."""
    store = ResultsStore(layout)
    keys = [*map(test.model_key, test.models), *map(test.exec_key, test.executions)]
    results = {k: store.results(*k)[0] for k in keys}

    def rate(key: tuple[str]) -> str:
        r = results[key]
        return f"{100 * r['success_rate']:.1f}% {percent_interval(*wilson_interval(r['successes'], r['episodes']))}"

    def diff(key: tuple[str], ref: tuple[str] | None) -> str:
        """Difference in points to the reference row, paired over the same test episodes: Newcombe's method 10
        95% interval and the exact McNemar p."""
        return "" if ref is None or key == ref else format_difference(store.compare(key, ref))

    def counts(key: tuple[str], *fields: str) -> list[str]:
        return [str(results[key]["episodes"]), f"{results[key]['mean_executed_horizon']:.2f}",
                *(str(results[key][f]) for f in fields)]

    models = list(dict.fromkeys(ev.policy for ev in test.models))
    full = AblationLayout.model_key("full") if "full" in models else None
    blocks: list[Block] = [
        f"# Ablations ({cfg.env}/{cfg.suite}, {cfg.episodes} episodes per task, perturb={cfg.perturb}, "
        f"{cfg.train.steps} training steps of {cfg.train.batch_size}, training seed {cfg.train_seed}, "
        f"test seed {cfg.seed})",
        "Success with 95% Wilson intervals; differences in points, paired over the same test episodes "
        "(Newcombe's method 10 95% interval, exact McNemar p)."]
    for title, variants in [("Table 4: action heads", ["full", "discrete_only", "continuous_only"]),
                            ("Table 5: loss terms", ["full", "no_sp", "no_rl", "il_only"])]:
        rows = []
        for v in (v for v in variants if v in models):
            aurd, fixed = AblationLayout.model_key(v), AblationLayout.model_key(v, fixed=True)
            rows.append([v, rate(aurd), rate(fixed), diff(aurd, full), *counts(aurd)])
        if rows:
            blocks.append(Table(["variant", "AURD", "fixed H=5", "AURD - full", "episodes", "AURD mean horizon"], rows,
                                title=title))
    steps = [(row, AblationLayout.model_key(v, fixed=ex != "aurd")) for row, v, ex in INCREMENTAL if v in models]
    if len(steps) == len(INCREMENTAL):
        blocks.append(Table(["configuration", "success", "- row above", "episodes", "mean horizon"],
                            [[row, rate(k), diff(k, steps[i - 1][1] if i else None), *counts(k)]
                             for i, (row, k) in enumerate(steps)],
                            title="Table 7: components added one at a time"))
    if test.executions:
        fixed_ref = next((test.exec_key(ev) for ev in test.executions if ev.label == "fixed_h5"), None)
        blocks.append(Table(
            ["executor", "success", "- fixed H=5", "episodes", "mean horizon", "replans", "prunes", "pauses"],
            [[ev.label, rate(k), diff(k, fixed_ref), *counts(k, "replans", "prunes", "pauses")]
             for ev, k in zip(test.executions, map(test.exec_key, test.executions))],
            title="Table 6: execution strategy (full model)"))
    return blocks
