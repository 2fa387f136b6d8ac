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
the same) and every comparison pools the seeds, pairing each policy's episodes with its own.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import tyro

from pivla.control.calibrate import CalibrationConfig, calibrate
from pivla.control.executors import CUTS, ExecutorConfig, config_to_dict, executor_config, first_cut
from pivla.data.hdf5 import read_env_meta, read_episodes, write_episodes
from pivla.envs import select_tasks
from pivla.envs.backend import BackendConfig
from pivla.envs.collect import CollectConfig, collect_demos
from pivla.envs.tabletop.perturb import EVENT_LEVELS_CM
from pivla.evaluation.ablate import INCREMENTAL, TRAIN_VARIANTS
from pivla.evaluation.protocol import (
    calibrate_on_rollouts,
    calibration_episodes,
    recipe,
)
from pivla.evaluation.report import new_figure, save_figure
from pivla.evaluation.runner import EvalConfig, evaluate, load_rows
from pivla.evaluation.stats import (
    compare,
    format_difference,
    mcnemar_exact,
    paired_rows,
    paired_successes,
    percent_interval,
    wilson_interval,
)
from pivla.evaluation.timing import StageTimes
from pivla.io import atomic_write_bytes, atomic_write_json
from pivla.policy import load_policy
from pivla.training.config import TrainConfig, check_target_divides
from pivla.training.trainer import train

log = logging.getLogger(__name__)

BASELINES = ("fixed", "ensemble", "adahorizon")
EXECUTORS = ("aurd", *BASELINES)
# Table 6: the full model's execution strategies (label -> executor and options)
EXEC_VARIANTS: dict[str, tuple[str, dict]] = {
    "aurd": ("aurd", {}), "aurd_check_after": ("aurd", {"check": "after"}), "fixed": ("fixed", {}),
    "fixed_h8": ("fixed", {"horizon": 8}), "ensemble": ("ensemble", {}), "adahorizon": ("adahorizon", {}),
}
# Fig. 16: each swept one at a time from the calibration's defaults (CalibrationConfig fields)
SENSITIVITY: dict[str, tuple[float, ...]] = {
    "eta": (0.3, 0.5, 0.7, 0.9), "tau_high_pct": (95.0, 97.5, 99.0, 99.7), "v_pct": (0.0, 10.0, 25.0, 50.0),
}
OTHER_SUITES = ("long", "drawer", "stack")


@dataclass(frozen=True)
class Cell:
    """One evaluation condition: its code in the seed families, the perturbation, the suite, the actuation
    (None: the benchmark's headline realism)."""

    name: str
    condition: str
    perturb: str | None = None
    suite: str = "pick_place"
    realism: str | None = None


@dataclass
class BenchmarkConfig:
    """Sizes of the twin benchmark; ``--quick`` shrinks every one for a smoke run that still trains and
    evaluates for real, covering every table."""

    out: str = "runs/benchmark"
    """Directory of the whole benchmark (data/, seed*/, benchmark.md, benchmark.json, figures/)."""
    seeds: int = 2
    """Training seeds; every comparison pools them by pairing episodes."""
    realism: Literal["ideal", "servo"] = "servo"
    """Actuation of the headline numbers (the paper's arm has backlash); the other is a secondary column."""
    train_episodes: int = 90
    """Demonstrations per task (the demo's validated count)."""
    demo_counts: tuple[int, ...] = (10, 30, 60)
    """Fig. 17: smaller demonstration sets (the first N of the full set), besides train_episodes."""
    val_episodes: int = 10
    """Validation episodes per task and condition (calibration rollouts and every decision)."""
    test_episodes: int = 20
    """Test episodes per task, condition and training seed."""
    rollout_episodes: int = 10
    """Failure round: the policy's own rollouts per task and recording condition (train seeds)."""
    levels: tuple[int, ...] = EVENT_LEVELS_CM
    """Displacement and push levels in cm (Fig. 8); 0 runs the same episodes undisturbed."""
    steps: int = TrainConfig.steps
    """Training steps of every policy (the recipe's)."""
    batch_size: int = TrainConfig.batch_size
    """Training batch (the recipe's)."""
    val_fraction: float = TrainConfig.val_fraction
    """Share of demonstrations held out for the training's validation loss (the recipe's)."""
    image_size: int = 80
    """Camera and policy resolution (the demo's)."""
    noise: float = 0.3
    """DART noise of the demonstrations (the demo's)."""
    miss: float = 0.3
    """Share of demonstrations with a missed, recovered first grasp (the demo's)."""
    max_steps: int | None = None
    """Step limit per episode (default: each task's own)."""
    tasks: str | None = None
    """pick_place tasks evaluated, comma-separated indices or names (default: all nine; every policy trains on
    all of them)."""
    workers: int = 2
    """Worker processes for collection and evaluation."""
    dispatch: Annotated[BackendConfig, tyro.conf.arg(name="")] = dataclasses.field(default_factory=BackendConfig)
    """Where the episodes run: --backend local | ray, --ray-address HOST:PORT (docs/cluster.md)."""
    calibration: CalibrationConfig = dataclasses.field(default_factory=CalibrationConfig)
    """AURD's calibration of every policy."""


def quick(base: BenchmarkConfig | None = None) -> BenchmarkConfig:
    """Smoke-run sizes: one seed, a few demonstrations and training steps, one episode per cell, short episodes."""
    return dataclasses.replace(base or BenchmarkConfig(), seeds=1, train_episodes=3, demo_counts=(1,), val_episodes=1,
                               test_episodes=1, rollout_episodes=1, levels=(0, EVENT_LEVELS_CM[-1]), steps=30,
                               batch_size=8, val_fraction=0.0, max_steps=20, tasks="block_away,ball_left,rock_right")


@dataclass(frozen=True)
class PolicySpec:
    """A policy of the benchmark: its training data (directories under data/), loss overrides, and the suites
    of its validation rollouts."""

    data: tuple[str, ...]
    suites: tuple[str, ...] = ("pick_place",)
    loss: tuple[tuple[str, Any], ...] = ()
    rollouts: bool = False  # also trains on the main policy's recorded rollouts (the failure round)


def policies(cfg: BenchmarkConfig) -> dict[str, PolicySpec]:
    out = {"main": PolicySpec(("pick_place",)), "round2": PolicySpec(("pick_place",), rollouts=True),
           "seen": PolicySpec(("pick_place_seen",), ("pick_place_seen",)),
           "others": PolicySpec(OTHER_SUITES, OTHER_SUITES)}
    out |= {f"abl_{v}": PolicySpec(("pick_place",), loss=tuple(o.items())) for v, (_, o) in TRAIN_VARIANTS.items()
            if v != "full"}
    out |= {f"demos_{n}": PolicySpec((f"pick_place_{n}",)) for n in cfg.demo_counts}
    return out


def headline_cells(cfg: BenchmarkConfig) -> dict[str, Cell]:
    cells = {name: Cell(name, name, None if name == "in_distribution" else name)
             for name in ("in_distribution", "static_distractors", "dynamic_distractors", "unseen_env")}
    for event in ("displace_object", "push_arm"):
        cells |= {f"{event}_{lv}": Cell(f"{event}_{lv}", event, f"{event}={lv}") for lv in cfg.levels}
    return cells


def candidate_cells(cfg: BenchmarkConfig) -> list[str]:
    """Conditions the ablations may run on: every perturbation at its strongest."""
    top = max(cfg.levels)
    return ["static_distractors", "dynamic_distractors", "unseen_env", f"displace_object_{top}", f"push_arm_{top}"]


# Failure round: the main policy's rollouts (train seeds, fixed horizon) in the training scenes and under the
# disturbances; distractors and unseen environments stay out of training
ROLLOUT_CELLS = (Cell("scenes", "in_distribution", "randomized_scene"),
                 Cell("displaced", "displace_object", "randomized_scene,displace_object=4"),
                 Cell("pushed", "push_arm", "randomized_scene,push_arm=4"))


class Benchmark:
    """The benchmark's stages over one output directory."""

    def __init__(self, cfg: BenchmarkConfig):
        self.cfg, self.out = cfg, Path(cfg.out)
        self.specs = policies(cfg)
        self.cells = headline_cells(cfg)
        self.decisions: dict[str, Any] = {}

    # -- stages ----------------------------------------------------------------------------------------
    def run(self) -> Path:
        cfg = self.cfg
        check_target_divides(self._train_config("main", 0).model)
        if any(n >= cfg.train_episodes for n in cfg.demo_counts):
            raise ValueError(f"demo_counts {cfg.demo_counts} must be below train_episodes {cfg.train_episodes}: "
                             "each is the first n demonstrations of the full set")
        self.out.mkdir(parents=True, exist_ok=True)
        atomic_write_json(self.out / "benchmark_config.json", dataclasses.asdict(cfg))
        path = self.out / "decisions.json"
        self.decisions = json.loads(path.read_text()) if path.exists() else {}
        self._ready("main")
        self._decide("hardest", self.choose_hardest)
        hardest = self.decisions["hardest"]["cell"]
        for s in range(cfg.seeds):
            self._timed("failure_rollouts", lambda s=s: self.record_rollouts(s))
        self._ready("round2")
        self._decide("failure_round", lambda: self.choose_round(hardest))
        # Most important first, with the report rewritten after each group, so a long run that is stopped
        # already reports the headline: main and round2 (the disturbances), then the other suites' policy (the
        # long horizon), then unseen tasks, then the ablations (Tables 4-7), then the demonstration counts (Fig. 17).
        groups = [("main", "round2"), ("others",), ("seen",), tuple(n for n in self.specs if n.startswith("abl_")),
                  tuple(n for n in self.specs if n.startswith("demos_"))]
        for group in groups:
            for name in group:
                self._ready(name)
            self._timed("test", lambda group=group: self.test(hardest, group))
            if group == ("seen",):
                self._timed("sensitivity", lambda: self.sensitivity(hardest))
            write_benchmark_report(self.out)
        return self.out / "benchmark.md"

    def _timed(self, name: str, fn: Callable[[], object]) -> None:
        """Run a stage, its wall time added to timings.json (``StageTimes``)."""
        StageTimes(self.out / "timings.json").run(name, fn)

    def _decide(self, name: str, fn: Callable[[], dict]) -> None:
        if name not in self.decisions:
            self.decisions[name] = fn()
            atomic_write_json(self.out / "decisions.json", self.decisions)
        log.info("[decision] %s: %s", name, {k: v for k, v in self.decisions[name].items() if k != "validation"})

    def collect(self, name: str) -> None:
        """A policy's demonstrations (train seeds) and the validation demonstrations of its first suite
        (calibration's fallback for a policy that never succeeds), collected when the policy is first needed so
        the headline trains before the other suites are collected. A task's file holds its first N successful
        seeds, so each smaller set of Fig. 17 is the first n episodes of the full set's files."""
        cfg, data, spec = self.cfg, self.out / "data", self.specs[name]
        base = CollectConfig(out="", episodes=cfg.train_episodes, seed_family="train", perturb="randomized_scene",
                             workers=cfg.workers, realism=cfg.realism, image_size=cfg.image_size, noise=cfg.noise,
                             miss=cfg.miss, dispatch=cfg.dispatch)
        for suite in spec.data:
            if suite in {f"pick_place_{n}" for n in cfg.demo_counts}:
                self._collect(dataclasses.replace(base, out=str(data / "pick_place"), suite="pick_place"))
                self._smaller_sets()
            else:
                self._collect(dataclasses.replace(base, out=str(data / suite), suite=suite))
        val = dataclasses.replace(base, episodes=max(1, cfg.val_episodes // 2), seed_family="validation", perturb=None,
                                  noise=0.0, miss=0.0)
        self._collect(dataclasses.replace(val, out=str(data / "val" / spec.suites[0]), suite=spec.suites[0]))

    def _smaller_sets(self) -> None:
        """Fig. 17's sets: the first n episodes of each full pick_place file, one read per file for every n."""
        data = self.out / "data"
        for src in sorted((data / "pick_place").glob("*_demo.hdf5")):
            todo = [n for n in self.cfg.demo_counts if not (data / f"pick_place_{n}" / src.name).exists()]
            if todo:
                episodes, meta = read_episodes(src), {**read_env_meta(src), "first_of": str(src)}
                for n in todo:
                    write_episodes(data / f"pick_place_{n}" / src.name, episodes[:n], meta)

    @staticmethod
    def _collect(cc: CollectConfig) -> None:
        """Collect the tasks whose file is missing (a task's file is written once it is complete)."""
        out = Path(cc.out)
        missing = [str(s.index) for s in select_tasks("tabletop", cc.suite, None)
                   if not (out / f"{s.name}_demo.hdf5").exists()]
        if missing:
            log.info("[collect] %s: %d per task, tasks %s -> %s", cc.suite, cc.episodes, ",".join(missing), out)
            if collect_demos(dataclasses.replace(cc, tasks=",".join(missing))) != 0:
                raise RuntimeError(f"collection of {cc.suite} into {out} fell short of {cc.episodes} per task")

    def run_dir(self, name: str, seed: int) -> Path:
        return self.out / f"seed{seed}" / "policies" / name

    def _train_config(self, name: str, seed: int) -> TrainConfig:
        spec, cfg = self.specs[name], self.cfg
        tc = recipe("", str(self.run_dir(name, seed)), seed, steps=cfg.steps, batch_size=cfg.batch_size,
                    image_size=cfg.image_size, loss_overrides=dict(spec.loss), progress=False)
        dirs = [str(self.out / "data" / d) for d in spec.data]
        if spec.rollouts:
            dirs += [str(self._rollouts_dir(seed, c.name)) for c in ROLLOUT_CELLS]
        return dataclasses.replace(tc, data=dirs[0], extra_data=tuple(dirs[1:]), val_fraction=cfg.val_fraction)

    def _ready(self, name: str) -> None:
        """Train every seed of a policy, run it on validation seeds and calibrate it on its own rollouts."""
        self._timed("collect", lambda: self.collect(name))
        for seed in range(self.cfg.seeds):
            run = self.run_dir(name, seed)
            status = run / "status.json"
            if not (status.exists() and json.loads(status.read_text()).get("done")):
                log.info("[train] %s seed %d", name, seed)
                tc, resume = self._train_config(name, seed), (run / "checkpoints").exists()
                self._timed("train", lambda tc=tc, resume=resume: train(tc, resume=resume))
            if not (run / "calibration.json").exists():
                self._timed("calibrate", lambda seed=seed: self._calibrate(name, seed))

    def _calibrate(self, name: str, seed: int) -> None:
        run, rollouts = self.run_dir(name, seed), self._val_rollouts(name, seed)
        for suite in self.specs[name].suites:
            cell = Cell(suite, "in_distribution", suite=suite)
            self.evaluate(seed, "validation", name, cell, "fixed", executor_config("fixed"), record=rollouts)
        # calibration's fallback: the validation demonstrations of the policy's first suite
        calibrate_on_rollouts(run, rollouts, self.out / "data" / "val" / self.specs[name].suites[0],
                              self.cfg.calibration)

    def _val_rollouts(self, name: str, seed: int) -> Path:
        return self.out / f"seed{seed}" / "val_rollouts" / name

    def _rollouts_dir(self, seed: int, cell: str) -> Path:
        return self.out / f"seed{seed}" / "train_rollouts" / cell

    def evaluate(self, seed: int, split: Literal["train", "validation", "test"], policy: str, cell: Cell, label: str,
                 executor: ExecutorConfig, record: Path | None = None) -> dict:
        """One evaluation (resumed if interrupted, reused if finished) in ``seed*/split/policy/cell/label``."""
        cfg = self.cfg
        episodes = {"test": cfg.test_episodes, "validation": cfg.val_episodes, "train": cfg.rollout_episodes}[split]
        target = self.eval_dir(seed, split, policy, cell.name, label)
        tasks = cfg.tasks if cell.suite == "pick_place" else None
        if (target / "results.json").exists():
            done = json.loads((target / "results.json").read_text())
            if done["episodes"] >= episodes * len(select_tasks("tabletop", cell.suite, tasks)):
                return done
        ec = EvalConfig(policy=str(self.run_dir(policy, seed)), out=str(target), suite=cell.suite, tasks=tasks,
                        executor=executor,
                        episodes=episodes, seed_family=split, condition=cell.condition,
                        perturb=cell.perturb, realism=cell.realism or cfg.realism, workers=cfg.workers,
                        dispatch=cfg.dispatch, videos=0,
                        max_steps=cfg.max_steps, record=str(record) if record else None, split=split)
        res = evaluate(ec, progress=False)
        lo, hi = res["ci95"]
        log.info("  seed %d %s %s %s %s: %.1f%% [%.1f, %.1f] of %d", seed, split, policy, cell.name, label,
                 100 * res["success_rate"], 100 * lo, 100 * hi, res["episodes"])
        return res

    def eval_dir(self, seed: int, split: str, policy: str, cell: str, label: str) -> Path:
        return self.out / f"seed{seed}" / split / policy / cell / label

    def record_rollouts(self, seed: int) -> None:
        for cell in ROLLOUT_CELLS:
            self.evaluate(seed, "train", "main", cell, "fixed", executor_config("fixed"),
                          record=self._rollouts_dir(seed, cell.name))

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
        success = self._val_success("main", [self.cells[n] for n in names], BASELINES)
        mean = {n: float(np.mean([success[f"{n}/{b}"] for b in BASELINES])) for n in names}
        return {"cell": min(names, key=lambda n: mean[n]), "baseline_mean_success": mean, "validation": success}

    def choose_round(self, hardest: str) -> dict:
        """Keep the failure round when, on validation seeds, the retrained policy does at least as well with AURD
        in distribution and on the hardest condition together."""
        cells = [self.cells["in_distribution"], self.cells[hardest]]
        before = self._val_success("main", cells, ("aurd",))
        after = self._val_success("round2", cells, ("aurd",))
        keep = float(np.mean(list(after.values()))) >= float(np.mean(list(before.values())))
        return {"headline": "round2" if keep else "main", "validation": {"main": before, "round2": after}}

    def sensitivity(self, hardest: str) -> None:
        """Fig. 16: AURD with thresholds calibrated at other settings, one at a time, on validation seeds."""
        policy = self.decisions["failure_round"]["headline"]
        for seed in range(self.cfg.seeds):
            run = self.run_dir(policy, seed)
            episodes, _ = calibration_episodes(self._val_rollouts(policy, seed),
                                               self.out / "data" / "val" / "pick_place")
            loaded = None
            for key, values in SENSITIVITY.items():
                for value in values:
                    label = f"{key}={value:g}"
                    if (self.eval_dir(seed, "validation", policy, hardest, label) / "results.json").exists():
                        continue
                    loaded = loaded or load_policy(run, device="cpu")
                    calib, _ = calibrate(loaded, episodes, dataclasses.replace(self.cfg.calibration, **{key: value}))
                    executor = executor_config("aurd", tau_low=calib.tau_low, tau_high=calib.tau_high,
                                               v_thresh=calib.v_thresh, eta=calib.eta)
                    self.evaluate(seed, "validation", policy, self.cells[hardest], label, executor)

    def test_plan(self, hardest: str) -> list[tuple[str, Cell, str, ExecutorConfig]]:
        """Every test evaluation: (policy, cell, label, executor)."""
        cfg, headline = self.cfg, self.decisions["failure_round"]["headline"]
        other = "main" if headline == "round2" else "round2"
        secondary = "ideal" if cfg.realism == "servo" else "servo"
        plan = [(headline, cell, e, executor_config(e)) for cell in self.cells.values() for e in EXECUTORS]
        plan += [(headline, dataclasses.replace(self.cells[c], name=f"{c}_{secondary}", realism=secondary), e,
                  executor_config(e)) for c in ("in_distribution", hardest) for e in EXECUTORS]
        top = f"displace_object_{max(cfg.levels)}"
        plan += [(other, self.cells[c], e, executor_config(e)) for c in dict.fromkeys(("in_distribution", hardest, top))
                 for e in ("aurd", "fixed")]
        plan += [("seen", Cell("unseen_tasks", "unseen_tasks", suite="pick_place_unseen"), e, executor_config(e))
                 for e in EXECUTORS]
        plan += [("others", Cell(s, "in_distribution", suite=s), e, executor_config(e)) for s in OTHER_SUITES
                 for e in EXECUTORS]
        plan += [("others", Cell(f"long_{top}", "displace_object", f"displace_object={max(cfg.levels)}", suite="long"),
                  e, executor_config(e)) for e in EXECUTORS]
        # Tables 4-7 on the hardest condition; the main policy is the full model of the ablations
        plan += [(p, self.cells[hardest], e, executor_config(e))
                 for p in ["main", *(n for n in self.specs if n.startswith("abl_"))] for e in ("aurd", "fixed")]
        plan += [("main", self.cells[hardest], label, executor_config(name, **opts))
                 for label, (name, opts) in EXEC_VARIANTS.items()]
        plan += [(f"demos_{n}", self.cells[c], e, executor_config(e)) for n in cfg.demo_counts
                 for c in ("in_distribution", hardest) for e in ("aurd", "fixed")]
        plan += [("main", self.cells[c], e, executor_config(e))
                 for c in ("in_distribution", hardest) for e in ("aurd", "fixed")]
        unique = {(p, c.name, label): (p, c, label, e) for p, c, label, e in plan}  # tables share evaluations
        return list(unique.values())

    def test(self, hardest: str, policies: Iterable[str]) -> None:
        """The test plan's evaluations of these policies (test_plan.json lists the whole plan)."""
        plan = self.test_plan(hardest)
        atomic_write_json(self.out / "test_plan.json", [
            {"policy": p, "cell": dataclasses.asdict(c), "label": lb, "executor": config_to_dict(e)}
            for p, c, lb, e in plan])
        wanted = set(policies)
        for seed in range(self.cfg.seeds):
            for policy, cell, label, executor in plan:
                if policy in wanted:
                    self.evaluate(seed, "test", policy, cell, label, executor)


def run_benchmark(cfg: BenchmarkConfig) -> Path:
    """Run (or resume) the benchmark; returns the path of benchmark.md."""
    return Benchmark(cfg).run()


# -- report ---------------------------------------------------------------------------------------------
class Results:
    """Finished evaluations of a benchmark directory, pooled over training seeds."""

    def __init__(self, out: Path):
        self.out = out
        self.seeds = sorted(int(p.name.removeprefix("seed")) for p in out.glob("seed*") if p.name[4:].isdigit())

    def _dirs(self, split: str, policy: str, cell: str, label: str) -> list[Path]:
        dirs = [self.out / f"seed{s}" / split / policy / cell / label for s in self.seeds]
        return [d for d in dirs if (d / "results.json").exists()]

    def has(self, policy: str, cell: str, label: str, split: str = "test") -> bool:
        return len(self._dirs(split, policy, cell, label)) == len(self.seeds) > 0

    def results(self, policy: str, cell: str, label: str, split: str = "test") -> list[dict]:
        return [json.loads((d / "results.json").read_text()) for d in self._dirs(split, policy, cell, label)]

    def rate(self, policy: str, cell: str, label: str, split: str = "test") -> dict | None:
        res = self.results(policy, cell, label, split)
        if not res or len(res) != len(self.seeds):
            return None
        k, n = sum(r["successes"] for r in res), sum(r["episodes"] for r in res)
        return {"successes": k, "episodes": n, "rate": k / n if n else 0.0, "ci95": list(wilson_interval(k, n))}

    def rows(self, policy: str, cell: str, label: str, split: str = "test") -> list[tuple[int, list[dict]]]:
        return [(s, load_rows(self.out / f"seed{s}" / split / policy / cell / label / "episodes.jsonl"))
                for s in self.seeds]

    def compare(self, a: tuple[str, str, str], b: tuple[str, str, str], split: str = "test") -> dict | None:
        """A against B (policy, cell, label each), paired episode by episode within each seed, pooled. Cells that
        share seed codes pair too (a displacement level against level 0, servo against ideal actuation)."""
        if not (self.has(*a, split=split) and self.has(*b, split=split)):
            return None
        pairs = [paired_successes(ra, rb)
                 for (_, ra), (_, rb) in zip(self.rows(*a, split=split), self.rows(*b, split=split))]
        return compare(np.concatenate([x for x, _ in pairs]), np.concatenate([y for _, y in pairs]))

    def departures(self, policy: str, cell: str) -> dict[str, dict] | None:
        """AURD's test episodes against the fixed horizon's, grouped by AURD's first cut (``first_cut``; "none":
        it never cut, so both ran the same actions): per group the episodes and those only AURD / only the fixed
        horizon solved. Says which of AURD's decisions its wins and losses start at."""
        if not (self.has(policy, cell, "aurd") and self.has(policy, cell, "fixed")):
            return None
        groups = {g: [0, 0, 0] for g in ("none", *CUTS)}
        for (_, rows_a), (_, rows_b) in zip(self.rows(policy, cell, "aurd"), self.rows(policy, cell, "fixed")):
            for ra, rb in paired_rows(rows_a, rows_b):
                sa, sb = bool(ra["success"]), bool(rb["success"])
                group = groups[first_cut(ra["trace"]) or "none"]
                group[0] += 1
                group[1] += sa and not sb
                group[2] += sb and not sa
        return {g: {"episodes": n, "only_aurd": ia, "only_fixed": ib} for g, (n, ia, ib) in groups.items()}

    def task_rates(self, policy: str, cell: str, label: str) -> dict[str, dict]:
        per: dict[str, list[bool]] = {}
        for _, rows in self.rows(policy, cell, label):
            for r in rows:
                per.setdefault(r["task"], []).append(bool(r["success"]))
        return {t: {"successes": int(sum(v)), "episodes": len(v), "rate": float(np.mean(v)),
                    "ci95": list(wilson_interval(int(sum(v)), len(v)))} for t, v in per.items()}


def _fired(row: dict) -> bool:
    """Whether an episode's displacement or push moved something (level 0 records its step, moving nothing)."""
    return any(np.linalg.norm(ev.get("shift", ev.get("tool_shift", [0.0]))) > 0 for ev in row.get("perturb_events", []))


def _pct(r: dict | None) -> str:
    if r is None:
        return "not run"
    return f"{100 * r['rate']:.1f} {percent_interval(*r['ci95'])}"


def _diff(c: dict | None) -> str:
    return "-" if c is None else format_difference(c)


def write_benchmark_report(out: str | Path) -> Path:
    """benchmark.md, benchmark.json and figures/*.png from the finished evaluations (``pivla report --dir`` on a
    benchmark directory calls this too, so both print the same figures)."""
    out = Path(out)
    stored = json.loads((out / "benchmark_config.json").read_text())
    cfg = BenchmarkConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in stored.items()
                             if k not in ("calibration", "dispatch")})
    decisions = json.loads((out / "decisions.json").read_text()) if (out / "decisions.json").exists() else {}
    res = Results(out)
    hardest = decisions.get("hardest", {}).get("cell")
    headline = decisions.get("failure_round", {}).get("headline", "main")
    cells = headline_cells(cfg)
    data: dict[str, Any] = {"config": stored, "decisions": decisions,
                            "seeds": res.seeds, "headline_policy": headline, "hardest_condition": hardest,
                            "tables": {}, "comparisons": []}
    data["timings_s"] = json.loads((out / "timings.json").read_text()) if (out / "timings.json").exists() else {}
    n_seeds = len(res.seeds)
    md = [f"# Twin benchmark ({cfg.realism} actuation; {n_seeds} training seed{'s' * (n_seeds != 1)} pooled)", "",
          ("Success in % with Wilson 95% intervals, pooled over training seeds; differences in points, paired episode "
           "by episode within each seed (Newcombe's method 10 95% interval, exact McNemar p). Test seeds only; every "
           "decision was taken on validation seeds (decisions.json)."), "",
          f"Headline policy: `{headline}`; hardest condition (lowest mean baseline success on validation): "
          f"`{hardest}`.", ""]

    def table(key: str, title: str, header: list[str], rows: list[list[str]], records: list[dict]) -> None:
        data["tables"][key] = records
        if rows:
            md.extend([f"## {title}", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header), *[
                "| " + " | ".join(r) + " |" for r in rows], ""])

    def versus(policy: str, cell: str, label: str, table_key: str, ref: tuple[str, str, str]) -> dict | None:
        c = res.compare((policy, cell, label), ref)
        if c is not None:
            data["comparisons"].append({"table": table_key, "a": [policy, cell, label], "b": list(ref), **c})
        return c

    def executor_rows(key: str, policy: str, names: Iterable[str]) -> tuple[list[list[str]], list[dict]]:
        rows, recs = [], []
        for name in names:
            rates = {e: res.rate(policy, name, e) for e in EXECUTORS}
            if not any(rates.values()):
                continue
            diffs = {e: versus(policy, name, "aurd", key, (policy, name, e)) for e in BASELINES}
            rows.append([name, *(_pct(rates[e]) for e in EXECUTORS), *(_diff(diffs[e]) for e in BASELINES)])
            recs.append({"cell": name, "policy": policy, "success": rates, "aurd_minus": diffs})
        return rows, recs

    header = ["condition", *EXECUTORS, *(f"AURD - {b}" for b in BASELINES)]
    rows, recs = executor_rows("headline", headline, cells)
    table("headline", "Every condition, every executor (pick_place)", header, rows, recs)
    grid = {e: res.task_rates(headline, "in_distribution", e) for e in EXECUTORS}
    tasks = sorted({t for g in grid.values() for t in g})
    table("table2", "Table 2: object x direction, in distribution", ["task", *EXECUTORS],
          [[t, *(_pct(grid[e].get(t)) for e in EXECUTORS)] for t in tasks],
          [{"task": t, **{e: grid[e].get(t) for e in EXECUTORS}} for t in tasks])
    rows, recs = executor_rows("table3", headline, ["static_distractors", "dynamic_distractors", "unseen_env"])
    r2, c2 = executor_rows("table3", "seen", ["unseen_tasks"])
    table("table3", "Table 3: generalisation (unseen tasks: trained on pick_place_seen)", header, r2 + rows, c2 + recs)
    top = max(cfg.levels)
    rows, recs = executor_rows("suites", "others", [*OTHER_SUITES, f"long_displace_object_{top}"])
    table("suites", "Long-horizon and the other suites (one policy for long, drawer and stack)", header, rows, recs)
    levels: dict[str, dict[str, list]] = {}
    for event in ("displace_object", "push_arm"):
        names = [f"{event}_{lv}" for lv in cfg.levels]
        rows, recs = executor_rows(event, headline, names)
        for row, rec in zip(rows, recs):  # an event waits while it cannot land, and may come too late to fire
            fired = [sum(_fired(r) for _, rows in res.rows(headline, rec["cell"], e) for r in rows) for e in EXECUTORS]
            rec["fired"] = dict(zip(EXECUTORS, fired))
            row.append(" / ".join(map(str, fired)))
        table(event, f"Fig. 8: {event.replace('_', ' ')} mid-chunk, by level (cm)",
              [*header, "fired (" + " / ".join(EXECUTORS) + ")"], rows, recs)
        levels[event] = {e: [res.rate(headline, n, e) for n in names] for e in EXECUTORS}
    secondary = "ideal" if cfg.realism == "servo" else "servo"
    realism_rows, realism_recs = [], []
    for c in ("in_distribution", hardest):
        if c is None:
            continue
        for e in EXECUTORS:
            a, b = res.rate(headline, c, e), res.rate(headline, f"{c}_{secondary}", e)
            cmp = versus(headline, c, e, "realism", (headline, f"{c}_{secondary}", e))
            realism_rows.append([c, e, _pct(a), _pct(b), _diff(cmp)])
            realism_recs.append({"cell": c, "executor": e, cfg.realism: a, secondary: b, "difference": cmp})
    table("realism", f"Actuation: {cfg.realism} (headline) against {secondary}",
          ["condition", "executor", cfg.realism, secondary, f"{cfg.realism} - {secondary}"], realism_rows, realism_recs)
    if hardest:
        _ablation_tables(res, hardest, table, versus)
        _failure_round(res, hardest, top, table, versus)
        sens = _sensitivity(res, headline, hardest, table)
        counts = _demo_counts(res, cfg, hardest, table)
    else:
        sens, counts = {}, {}
    _departures(res, headline, cells, table)
    comp_rows, comp_recs = [], []
    for e in EXECUTORS:
        rs = res.results(headline, "in_distribution", e)
        q = [r.get("queries_per_100_steps") for r in rs if r.get("queries_per_100_steps") is not None]
        ms = [r.get("control_ms_per_step") for r in rs if r.get("control_ms_per_step") is not None]
        if rs:
            comp_rows.append([e, f"{np.mean(q):.1f}" if q else "-", f"{np.median(ms):.2f}" if ms else "-"])
            comp_recs.append({"executor": e, "queries_per_100_steps": float(np.mean(q)) if q else None,
                              "control_ms_per_step": float(np.median(ms)) if ms else None})
    table("compute", "Compute (in distribution): policy queries per 100 control steps, control time per step",
          ["executor", "queries / 100 steps", "ms / step (median over seeds)"], comp_rows, comp_recs)
    md += ["## Seeds", "", ("Demonstrations and the failure round's rollouts: the train family; validation rollouts, "
                            "calibration, the hardest condition, the failure round's adoption and Fig. 16: the "
                            "validation family; every figure above: the test family (pivla.envs.seeds)."), ""]
    if data["timings_s"]:
        md += ["## Wall time (s)", "", ", ".join(f"{k} {v:.0f}" for k, v in data["timings_s"].items()), ""]
    figures = _figures(out, cfg.levels, levels, sens, counts)
    data["figures"] = figures
    md += [f"![{Path(f).stem}]({f})" for f in figures]
    atomic_write_json(out / "benchmark.json", data)
    atomic_write_bytes(out / "benchmark.md", ("\n".join(md) + "\n").encode())
    return out / "benchmark.md"


def _ablation_tables(res: Results, hardest: str, table: Callable, versus: Callable) -> None:
    """Tables 4, 5 (trained variants, AURD and fixed), 6 (execution strategies) and 7 (incremental)."""
    policy = {v: ("main" if v == "full" else f"abl_{v}") for v in TRAIN_VARIANTS}
    for key, title, variants in (("table4", "Table 4: action heads", ("full", "discrete_only", "continuous_only")),
                                 ("table5", "Table 5: loss terms", ("full", "no_sp", "no_rl", "il_only"))):
        rows, recs = [], []
        for v in variants:
            a, f = res.rate(policy[v], hardest, "aurd"), res.rate(policy[v], hardest, "fixed")
            d = None if v == "full" else versus(policy[v], hardest, "aurd", key, ("main", hardest, "aurd"))
            rows.append([v, _pct(a), _pct(f), _diff(d)])
            recs.append({"variant": v, "aurd": a, "fixed": f, "aurd_minus_full": d})
        table(key, f"{title} ({hardest})", ["variant", "AURD", "fixed", "AURD - full"], rows, recs)
    rows, recs = [], []
    for label in EXEC_VARIANTS:
        r = res.rate("main", hardest, label)
        d = None if label == "fixed" else versus("main", hardest, label, "table6", ("main", hardest, "fixed"))
        rows.append([label, _pct(r), _diff(d)])
        recs.append({"executor": label, "success": r, "minus_fixed": d})
    table("table6", f"Table 6: execution strategies of the full model ({hardest})", ["executor", "success", "- fixed"],
          rows, recs)
    rows, recs, above = [], [], None
    for row, variant, executor in INCREMENTAL:
        key = (policy[variant], hardest, "fixed" if executor == "fixed" else "aurd")
        d = versus(*key, "table7", above) if above else None
        rows.append([row, _pct(res.rate(*key)), _diff(d)])
        recs.append({"row": row, "success": res.rate(*key), "minus_row_above": d})
        above = key
    table("table7", f"Table 7: components added one at a time ({hardest})", ["configuration", "success", "- row above"],
          rows, recs)


def _departures(res: Results, policy: str, names: Iterable[str], table: Callable) -> None:
    """Where AURD's wins and losses against the fixed horizon start, by its first cut, per condition and pooled."""
    groups = ("none", *CUTS)
    rows, recs, total = [], [], {g: [0, 0, 0] for g in groups}
    for name in names:
        dep = res.departures(policy, name)
        if dep is None:
            continue
        for g in groups:
            total[g] = [t + v for t, v in zip(total[g], dep[g].values())]
        rows.append([name, *(f"{dep[g]['episodes']}: {dep[g]['only_aurd']} / {dep[g]['only_fixed']}" for g in groups)])
        recs.append({"cell": name, **dep})
    if rows:
        rows.append(["all, exact McNemar p", *(f"{n}: {ia} / {ib} (p {mcnemar_exact(ia, ib):.2g})"
                                              for n, ia, ib in total.values())])
        recs.append({"cell": "all", **{g: {"episodes": n, "only_aurd": ia, "only_fixed": ib,
                                           "p_mcnemar": mcnemar_exact(ia, ib)} for g, (n, ia, ib) in total.items()}})
    table("departures", "Where AURD parts from the fixed horizon: episodes by AURD's first cut (episodes: only "
          "AURD solved / only fixed solved)", ["condition", "no cut", *(f"first cut: {g}" for g in CUTS)], rows, recs)


def _failure_round(res: Results, hardest: str, top: int, table: Callable, versus: Callable) -> None:
    """Success and the failure signals before (main) and after (round2) training on the policy's own rollouts."""
    rows, recs = [], []
    for cell in dict.fromkeys(("in_distribution", hardest, f"displace_object_{top}")):
        for e in ("aurd", "fixed"):
            before, after = res.rate("main", cell, e), res.rate("round2", cell, e)
            d = versus("round2", cell, e, "failure_round", ("main", cell, e))
            signals = {}
            for p in ("main", "round2"):
                fps = [r.get("failure_prediction", {}) for r in res.results(p, cell, e)]
                signals[p] = {k: _mean([f.get(k) for f in fps])
                              for k in ("auroc_neg_v_min", "auroc_u_max", "v_failure_lead_steps_mean",
                                        "failure_lead_steps_mean")}
            rows.append([cell, e, _pct(before), _pct(after), _diff(d),
                         *(f"{_fmt(signals['main'][k])} -> {_fmt(signals['round2'][k])}"
                           for k in ("auroc_neg_v_min", "v_failure_lead_steps_mean", "auroc_u_max"))])
            recs.append({"cell": cell, "executor": e, "before": before, "after": after, "difference": d,
                         "signals": signals})
    table("failure_round", "Failure round: trained again with the policy's own rollouts (before -> after)",
          ["condition", "executor", "before", "after", "after - before", "V AUROC", "V lead (steps)", "U AUROC"],
          rows, recs)


def _mean(values: list) -> float | None:
    vals = [v for v in values if v is not None]
    return float(np.mean(vals)) if vals else None


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f}"


def _sensitivity(res: Results, policy: str, hardest: str, table: Callable) -> dict[str, list]:
    """Fig. 16 (validation seeds): AURD's success with thresholds calibrated at each swept setting."""
    out, rows = {}, []
    for key, values in SENSITIVITY.items():
        rates = [res.rate(policy, hardest, f"{key}={v:g}", split="validation") for v in values]
        out[key] = [{"value": v, "success": r} for v, r in zip(values, rates)]
        rows += [[key, f"{v:g}", _pct(r)] for v, r in zip(values, rates)]
    table("sensitivity", f"Fig. 16: sensitivity of AURD (validation seeds, {hardest})", ["setting", "value", "success"],
          rows, [out])
    return out


def _demo_counts(res: Results, cfg: BenchmarkConfig, hardest: str, table: Callable) -> dict[str, list]:
    """Fig. 17: success against the number of demonstrations per task."""
    policies_by_n = {n: f"demos_{n}" for n in cfg.demo_counts} | {cfg.train_episodes: "main"}
    out, rows = {}, []
    for cell in dict.fromkeys(("in_distribution", hardest)):
        for e in ("aurd", "fixed"):
            pts = [{"demos": n, "success": res.rate(p, cell, e)} for n, p in sorted(policies_by_n.items())]
            out[f"{cell}/{e}"] = pts
            rows += [[cell, e, str(p["demos"]), _pct(p["success"])] for p in pts]
    table("demo_counts", "Fig. 17: success against demonstrations per task",
          ["condition", "executor", "demos", "success"], rows, [out])
    return out


def _figures(out: Path, cm: Iterable[int], levels: dict, sens: dict, counts: dict) -> list[str]:
    """PNG figures (relative paths); curves without results are left out, and figures without any."""
    written: list[str] = []

    def measured(curves: Iterable[list]) -> bool:
        return any(r is not None for rates in curves for r in rates)

    def curve(ax: Any, xs: list, rates: list[dict | None], label: str) -> None:
        pts = [(x, r) for x, r in zip(xs, rates) if r is not None]
        if pts:
            ax.errorbar([x for x, _ in pts], [100 * r["rate"] for _, r in pts],
                        yerr=np.clip([[100 * (r["rate"] - r["ci95"][0]), 100 * (r["ci95"][1] - r["rate"])]
                                      for _, r in pts], 0, None).T,  # Wilson bounds can round past the rate
                        marker="o", capsize=3, label=label)

    for name, per_exec in levels.items():
        if not measured(per_exec.values()):
            continue
        fig, ax = new_figure((5, 3.5))
        for e, rates in per_exec.items():
            curve(ax, list(cm), rates, e)
        ax.set(xlabel=f"{name.replace('_', ' ')} (cm)", ylabel="success (%)", ylim=(0, 102))
        ax.legend()
        written.append(f"figures/{name}.png")
        save_figure(fig, out / written[-1])
    if measured([p["success"] for p in pts] for pts in sens.values()):
        fig, axes = new_figure((4 * len(sens), 3.2), ncols=len(sens))
        for ax, (key, pts) in zip(np.atleast_1d(axes), sens.items()):
            curve(ax, [p["value"] for p in pts], [p["success"] for p in pts], "AURD")
            ax.set(xlabel=key, ylabel="validation success (%)", ylim=(0, 102))
        written.append("figures/sensitivity.png")
        save_figure(fig, out / written[-1])
    if measured([p["success"] for p in pts] for pts in counts.values()):
        fig, ax = new_figure((5, 3.5))
        for key, pts in counts.items():
            curve(ax, [p["demos"] for p in pts], [p["success"] for p in pts], key)
        ax.set(xlabel="demonstrations per task", ylabel="success (%)", ylim=(0, 102))
        ax.legend(fontsize=7)
        written.append("figures/demo_counts.png")
        save_figure(fig, out / written[-1])
    return written
