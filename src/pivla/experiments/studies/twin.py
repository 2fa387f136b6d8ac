"""``pivla benchmark twin``: the paper's experiments on the simulated twin, where they can tell the methods apart.

One resumable command (every evaluation continues from its last episode, every other stage is skipped when
its output exists) that collects, trains, calibrates, decides on validation seeds, evaluates on test seeds
and writes ``benchmark.md``, ``benchmark.json`` and PNG figures. What it covers:

- the headline grid on ``pick_place`` (Table 2 per object x direction, Table 3's static and dynamic
  distractors and unseen environments), mid-episode displacement of the object and pushes of the arm at
  graded levels (Fig. 8), all four executors, with the twin's servo realism (backlash, deadband, noise) and,
  as a secondary column, ideal actuation;
- unseen tasks: a policy trained on ``pick_place_seen`` tested on the held-out combinations;
- the other suites (``long``, ``drawer``, ``stack``): one multi-task policy trained on the three together;
- Tables 4-7 and the failure round on the condition where the baselines are furthest from the ceiling (chosen
  on validation seeds), Fig. 16 (sensitivity to eta, tau_high and V_thresh, on validation seeds) and Fig. 17
  (success against the number of demonstrations);
- compute: policy queries per 100 control steps and control time per step, per executor.

Seeds (``pivla.envs.seeds``): demonstrations and the policy rollouts of the failure round come from the train
family; calibration and every decision (the hardest condition, whether the failure round is kept, Fig. 16)
from the validation family; reported figures from the test family only, each policy's episodes run once.
``--seeds N`` trains every policy N times (initialisation, batch order, augmentation; the demonstrations are
the same) and every comparison pools the seeds, pairing each policy's episode with its own.

The study is its plan (``Benchmark.test_plan``) and its run order (``Benchmark.run``); what it is made of is in
:mod:`.twin_config`, its tables in :mod:`.twin_report`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np

from pivla.control.calibrate import calibrate
from pivla.control.executors import ExecutorConfig, config_to_dict, executor_config
from pivla.data.hdf5 import read_env_meta, read_episodes, write_episodes
from pivla.envs import select_tasks
from pivla.envs.collect import CollectConfig
from pivla.experiments import conditions
from pivla.experiments.conditions import Cell
from pivla.experiments.layout import TwinLayout, calibrated, demo_files, evaluation_done
from pivla.experiments.plan import Evaluation, EvaluationPlan, Split, eval_config
from pivla.experiments.recipes import Kind, execution_variant, recipe_config
from pivla.experiments.stages import (
    Collect,
    Evaluate,
    StageTimes,
    Train,
    calibrate_on_rollouts,
    calibration_episodes,
    shared_evaluations,
    train_all,
)
from pivla.experiments.studies.twin_config import (
    BASELINES,
    EXECUTORS,
    GROUPS,
    OTHER_SUITES,
    ROLLOUT_CELLS,
    SENSITIVITY,
    TABLE6_VARIANTS,
    BenchmarkConfig,
    by_variant,
    candidate_cells,
    headline_cells,
    of_kind,
    one,
    quick,
    recipes,
    sensitivity_label,
)
from pivla.experiments.studies.twin_report import write_benchmark_report
from pivla.io import atomic_write_json
from pivla.policy import load_policy
from pivla.training.config import TrainConfig, check_target_divides

__all__ = ["BASELINES", "EXECUTORS", "ROLLOUT_CELLS", "Benchmark", "BenchmarkConfig", "candidate_cells",
           "headline_cells", "quick", "run_benchmark", "write_benchmark_report"]

log = logging.getLogger(__name__)


class Benchmark:
    """The benchmark's stages over one output directory."""

    def __init__(self, cfg: BenchmarkConfig):
        self.cfg, self.layout = cfg, TwinLayout(Path(cfg.out))
        self.recipes = recipes(cfg)
        self.cells = headline_cells(cfg)
        self.decisions: dict[str, Any] = {}

    # -- the run order ---------------------------------------------------------------------------------
    def run(self) -> Path:
        cfg, layout = self.cfg, self.layout
        headline, round2 = one(self.recipes, Kind.HEADLINE), one(self.recipes, Kind.FAILURE_ROUND)
        check_target_divides(self._train_config(headline, 0).model)
        if any(n >= cfg.train_episodes for n in cfg.demo_counts):
            raise ValueError(f"demo_counts {cfg.demo_counts} must be below train_episodes {cfg.train_episodes}: "
                             "each is the first n demonstrations of the full set")
        layout.root.mkdir(parents=True, exist_ok=True)
        atomic_write_json(layout.config, dataclasses.asdict(cfg))
        self.decisions = json.loads(layout.decisions.read_text()) if layout.decisions.exists() else {}
        self._ready(headline)
        with self._evaluations():
            self._decide("hardest", self.choose_hardest)
            hardest = self.decisions["hardest"]["cell"]
            for s in range(cfg.seeds):
                self._timed("failure_rollouts", lambda s=s: self.record_rollouts(s))
        self._ready(round2)
        with self._evaluations():
            self._decide("failure_round", lambda: self.choose_round(hardest))
        for kinds in GROUPS:
            group = of_kind(self.recipes, *kinds)
            self._ready(*group)
            with self._evaluations():
                self._timed("test", lambda group=group: self.test(hardest, group))
                if kinds == (Kind.SEEN_TASKS,):
                    self._timed("sensitivity", lambda: self.sensitivity(hardest))
            write_benchmark_report(layout.root)
        return layout.report_md

    def _evaluations(self) -> contextlib.AbstractContextManager[None]:
        """One set of evaluation processes for the evaluations of a stretch between trainings."""
        return shared_evaluations(self.cfg.workers, self.cfg.dispatch)

    def _timed(self, name: str, fn: Callable[[], object]) -> None:
        """Run a stage, its wall time added to timings.json (``StageTimes``)."""
        StageTimes(self.layout.timings).run(name, fn)

    def _decide(self, name: str, fn: Callable[[], dict]) -> None:
        if name not in self.decisions:
            self.decisions[name] = fn()
            atomic_write_json(self.layout.decisions, self.decisions)
        log.info("[decision] %s: %s", name, {k: v for k, v in self.decisions[name].items() if k != "validation"})

    # -- collect, train, calibrate -----------------------------------------------------------------------
    def collect(self, name: str) -> None:
        """A policy's demonstrations (train seeds) and the validation demonstrations of its first suite
        (calibration's fallback for a policy that never succeeds), collected when the policy is first needed so
        the headline trains before the other suites are collected. A task's file holds its first N successful
        seeds, so each smaller set of Fig. 17 is the first n episodes of the full set's files."""
        cfg, layout, recipe = self.cfg, self.layout, self.recipes[name]
        base = CollectConfig(out="", episodes=cfg.train_episodes, seed_family="train", perturb=cfg.train_perturb,
                             workers=cfg.workers, realism=cfg.realism, image_size=cfg.image_size, noise=cfg.noise,
                             miss=cfg.miss, place_miss=cfg.place_miss, dispatch=cfg.dispatch)
        for suite in recipe.data:
            Collect(dataclasses.replace(base, out=str(layout.data(suite)), suite=suite))()
            if recipe.kind is Kind.DEMO_COUNT:
                self._smaller_sets(suite)
        val = dataclasses.replace(base, episodes=max(1, cfg.val_episodes // 2), seed_family="validation", perturb=None,
                                  noise=0.0, miss=0.0, place_miss=0.0)
        Collect(dataclasses.replace(val, out=str(layout.val_data(recipe.suites[0])), suite=recipe.suites[0]))()

    def _smaller_sets(self, suite: str) -> None:
        """Fig. 17's sets: the first n episodes of each full file, one read per file for every n."""
        layout = self.layout
        for src in demo_files(layout.data(suite)):
            todo = [n for n in self.cfg.demo_counts if not (layout.data(suite, first=n) / src.name).exists()]
            if todo:
                episodes, meta = read_episodes(src), {**read_env_meta(src), "first_of": str(src)}
                for n in todo:
                    write_episodes(layout.data(suite, first=n) / src.name, episodes[:n], meta)

    def _train_config(self, name: str, seed: int) -> TrainConfig:
        recipe, cfg, layout = self.recipes[name], self.cfg, self.layout
        tc = recipe_config("", str(layout.policy(name, seed)), seed, steps=cfg.steps, batch_size=cfg.batch_size,
                           image_size=cfg.image_size, loss_overrides=recipe.loss, progress=False)
        dirs = [str(layout.data(d, first=recipe.demos)) for d in recipe.data]
        if recipe.rollouts:
            dirs += [str(layout.train_rollouts(seed, c.name)) for c in ROLLOUT_CELLS]
        return dataclasses.replace(tc, data=dirs[0], extra_data=tuple(dirs[1:]), val_fraction=cfg.val_fraction,
                                   task_balance=recipe.task_balance,
                                   augment_shift_cameras=recipe.augment_shift_cameras, ema_decay=recipe.ema_decay)

    def _ready(self, *names: str) -> None:
        """Collect, then train every seed of these policies (each a Ray task, all at once, with --backend ray),
        then run each on validation seeds and calibrate it on its own rollouts."""
        for name in names:
            self._timed("collect", lambda name=name: self.collect(name))
        trainings = [Train(self._train_config(name, seed), self.cfg.dispatch) for name in names
                     for seed in range(self.cfg.seeds)]
        pending = [t for t in trainings if not t.done()]
        if pending:
            log.info("[train] %s", ", ".join(t.cfg.out for t in pending))
            self._timed("train", lambda: train_all(pending))
        with self._evaluations():
            for name in names:
                for seed in range(self.cfg.seeds):
                    if not calibrated(self.layout.policy(name, seed)):
                        self._timed("calibrate", lambda name=name, seed=seed: self._calibrate(name, seed))

    def _calibrate(self, name: str, seed: int) -> None:
        layout, recipe = self.layout, self.recipes[name]
        rollouts = layout.val_rollouts(name, seed)
        for suite in recipe.suites:
            self.evaluate(seed, "validation", name, conditions.suite_cell(suite), "fixed", executor_config("fixed"),
                          record=rollouts)
        # calibration's fallback: the validation demonstrations of the policy's first suite
        calibrate_on_rollouts(layout.policy(name, seed), rollouts, layout.val_data(recipe.suites[0]),
                              self.cfg.calibration)

    # -- evaluations -------------------------------------------------------------------------------------
    def evaluate(self, seed: int, split: Split, policy: str, cell: Cell, label: str, executor: ExecutorConfig,
                 record: Path | None = None) -> dict:
        """One evaluation (resumed if interrupted, reused if finished) in ``seed*/split/policy/cell/label``."""
        cfg = self.cfg
        episodes = {"test": cfg.test_episodes, "validation": cfg.val_episodes, "train": cfg.rollout_episodes}[split]
        tasks = cfg.tasks if cell.suite == "pick_place" else None
        ev = Evaluation(policy, cell, label, executor)
        stage = Evaluate(eval_config(ev, EvaluationPlan((ev,), split=split, episodes=episodes),
                                     policy=self.layout.policy(policy, seed),
                                     out=self.layout.evaluation(seed, split, policy, cell.name, label),
                                     realism=cfg.realism, family=True, tasks=tasks, workers=cfg.workers,
                                     dispatch=cfg.dispatch, max_steps=cfg.max_steps,
                                     record=str(record) if record else None),
                         expected=episodes * len(select_tasks("tabletop", cell.suite, tasks)))
        if stage.done():
            return stage()
        res = stage.run()
        lo, hi = res["ci95"]
        log.info("  seed %d %s %s %s %s: %.1f%% [%.1f, %.1f] of %d", seed, split, policy, cell.name, label,
                 100 * res["success_rate"], 100 * lo, 100 * hi, res["episodes"])
        return res

    def record_rollouts(self, seed: int) -> None:
        for cell in ROLLOUT_CELLS:
            self.evaluate(seed, "train", one(self.recipes, Kind.HEADLINE), cell, "fixed", executor_config("fixed"),
                          record=self.layout.train_rollouts(seed, cell.name))

    # -- decisions, on validation seeds ------------------------------------------------------------------
    def _val_success(self, policy: str, cells: Iterable[Cell], labels: Iterable[str]) -> dict[str, float]:
        """Validation success per (cell, executor), pooled over seeds; runs what is missing (fixed options)."""
        out = {}
        for cell in cells:
            for label in labels:
                res = [self.evaluate(s, "validation", policy, cell, label, executor_config(label))
                       for s in range(self.cfg.seeds)]
                out[f"{cell.name}/{label}"] = sum(r["successes"] for r in res) / max(sum(r["episodes"] for r in res), 1)
        return out

    def choose_hardest(self) -> dict:
        """The condition where the baselines are furthest from the ceiling, on validation seeds."""
        names = candidate_cells(self.cfg)
        success = self._val_success(one(self.recipes, Kind.HEADLINE), [self.cells[n] for n in names], BASELINES)
        mean = {n: float(np.mean([success[f"{n}/{b}"] for b in BASELINES])) for n in names}
        return {"cell": min(names, key=lambda n: mean[n]), "baseline_mean_success": mean, "validation": success}

    def choose_round(self, hardest: str) -> dict:
        """Keep the failure round when, on validation seeds, the retrained policy does at least as well with AURD
        in distribution and on the hardest condition together."""
        before_name, after_name = one(self.recipes, Kind.HEADLINE), one(self.recipes, Kind.FAILURE_ROUND)
        cells = [self.cells["in_distribution"], self.cells[hardest]]
        before = self._val_success(before_name, cells, ("aurd",))
        after = self._val_success(after_name, cells, ("aurd",))
        keep = float(np.mean(list(after.values()))) >= float(np.mean(list(before.values())))
        return {"headline": after_name if keep else before_name,
                "validation": {before_name: before, after_name: after}}

    def sensitivity(self, hardest: str) -> None:
        """Fig. 16: AURD with thresholds calibrated at other settings, one at a time, on validation seeds."""
        layout, policy = self.layout, self.decisions["failure_round"]["headline"]
        for seed in range(self.cfg.seeds):
            episodes, _ = calibration_episodes(layout.val_rollouts(policy, seed), layout.val_data("pick_place"))
            loaded = None
            for key, values in SENSITIVITY.items():
                for value in values:
                    label = sensitivity_label(key, value)
                    if evaluation_done(layout.evaluation(seed, "validation", policy, hardest, label)):
                        continue
                    loaded = loaded or load_policy(layout.policy(policy, seed), device="cpu")
                    calib, _ = calibrate(loaded, episodes, dataclasses.replace(self.cfg.calibration, **{key: value}))
                    executor = executor_config("aurd", tau_low=calib.tau_low, tau_high=calib.tau_high,
                                               v_thresh=calib.v_thresh, eta=calib.eta)
                    self.evaluate(seed, "validation", policy, self.cells[hardest], label, executor)

    # -- the plan ------------------------------------------------------------------------------------------
    def test_plan(self, hardest: str) -> EvaluationPlan:
        """Every test evaluation, each once where tables share it."""
        cfg, rs = self.cfg, self.recipes
        headline = self.decisions["failure_round"]["headline"]
        main, round2 = one(rs, Kind.HEADLINE), one(rs, Kind.FAILURE_ROUND)
        other = main if headline == round2 else round2
        seen, others = one(rs, Kind.SEEN_TASKS), one(rs, Kind.OTHER_SUITES)
        secondary = "ideal" if cfg.realism == "servo" else "servo"
        top = max(cfg.levels)
        hard = self.cells[hardest]

        def each(policy: str, cells: Iterable[Cell], executors: Iterable[str]) -> list[Evaluation]:
            return [Evaluation(policy, c, e, executor_config(e)) for c in cells for e in executors]

        near = [self.cells[c] for c in dict.fromkeys(("in_distribution", hardest, f"displace_object_{top}"))]
        in_and_hard = [self.cells["in_distribution"], hard]
        plan = each(headline, self.cells.values(), EXECUTORS)
        plan += each(headline, [c.with_realism(secondary) for c in in_and_hard], EXECUTORS)
        plan += each(other, near, ("aurd", "fixed"))  # the failure round, before and after
        plan += each(seen, [conditions.SCENE_CELLS["unseen_tasks"]], EXECUTORS)
        plan += each(others, [conditions.suite_cell(s) for s in OTHER_SUITES], EXECUTORS)
        plan += each(others, [conditions.event("displace_object", top, suite="long")], EXECUTORS)
        # Tables 4-7 on the hardest condition; the headline recipe is the full model of the ablations
        for policy in by_variant(rs).values():
            plan += each(policy, [hard], ("aurd", "fixed"))
        plan += [Evaluation(main, hard, label, execution_variant(label)) for label in TABLE6_VARIANTS]
        for policy in of_kind(rs, Kind.DEMO_COUNT):
            plan += each(policy, in_and_hard, ("aurd", "fixed"))
        plan += each(main, in_and_hard, ("aurd", "fixed"))
        return EvaluationPlan.of(plan, split="test", episodes=cfg.test_episodes)

    def test(self, hardest: str, policies: Iterable[str]) -> None:
        """The test plan's evaluations of these policies (test_plan.json lists the whole plan)."""
        plan = self.test_plan(hardest)
        atomic_write_json(self.layout.test_plan, [
            {"policy": ev.policy, "cell": ev.cell.record(), "label": ev.label, "executor": config_to_dict(ev.executor)}
            for ev in plan])
        wanted = plan.of_policies(policies)
        for seed in range(self.cfg.seeds):
            for ev in wanted:
                self.evaluate(seed, plan.split, *ev)


def run_benchmark(cfg: BenchmarkConfig) -> Path:
    """Run (or resume) the benchmark; returns the path of benchmark.md."""
    return Benchmark(cfg).run()
