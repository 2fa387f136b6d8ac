"""``pivla demo``, ``pivla ablate``, ``pivla benchmark twin``, ``pivla libero run`` and ``pivla libero expert``."""

from __future__ import annotations

import argparse
import logging
from dataclasses import dataclass, field
from typing import Annotated

import tyro

from pivla.envs.libero.expert import ExpertEvalConfig, expert_success
from pivla.experiments.studies import twin as benchmark
from pivla.experiments.studies.ablate import AblationConfig, run_ablation
from pivla.experiments.studies.demo import DemoConfig, quick, run_demo
from pivla.experiments.studies.libero import LiberoRunConfig, expert_table, run_libero


@dataclass
class DemoCommand:
    """The main job on the twin."""

    sizes: Annotated[DemoConfig, tyro.conf.arg(name="")] = field(default_factory=DemoConfig)
    quick: bool = False
    """A few-minute smoke run that still trains and evaluates for real (its sizes become the defaults)."""


def demo_default(argv: list[str]) -> tuple[DemoCommand, list[str]]:
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--quick", action="store_true")
    known, _ = pre.parse_known_args(argv)
    return DemoCommand(sizes=quick() if known.quick else DemoConfig(), quick=known.quick), argv


def demo(cmd: DemoCommand) -> int:
    """collect expert demos on pick_place -> train the validated recipe -> run it on validation seeds and
    calibrate AURD on its successful rollouts -> evaluate AURD, fixed, ensemble and AdaHorizon in distribution
    and under perturbations -> report. Every stage is skipped when its output exists, so an interrupted demo
    resumes."""
    try:
        report = run_demo(cmd.sizes)
    except ValueError as e:
        raise SystemExit(f"pivla demo: {e}") from e
    print(f"demo finished: report at {report}")
    return 0


def ablate(cfg: AblationConfig) -> int:
    """Table 4 (action heads), Table 5 (loss terms), Table 6 (execution strategies of the full model) and
    Table 7 (components added one at a time), each variant trained with the recipe."""
    try:
        print(run_ablation(cfg))
    except ValueError as e:
        raise SystemExit(f"pivla ablate: {e}") from e
    return 0


def libero_run(cfg: LiberoRunConfig) -> int:
    """Resumable stage by stage (every stage is skipped when its output exists; an interrupted evaluation
    continues); progress in the log, so it is safe to leave in the background for hours:
    nohup pivla libero run --suite libero_spatial --out runs/libero_spatial > runs/libero_spatial.log 2>&1 &"""
    print(f"report at {run_libero(cfg)}")
    return 0


def libero_expert(cfg: ExpertEvalConfig) -> int:
    """Privileged simulator state, no rendering, one episode per init state (or sampled scene), reset with its
    own seed. With --out, episodes already in the JSONL are skipped, so a finished file just prints its table:
    MUJOCO_GL=egl pivla libero expert --suite libero_10 --init-states 0-49 --out runs/expert_libero_10.jsonl"""
    log = logging.getLogger("pivla.libero.expert")

    def show(row: dict) -> None:
        start = row["init_state"] if row["seed"] is None else f"seed {row['seed']}"
        log.info("%s task %d %s: %s in %d steps (%.0f s)", row["suite"], row["task"], start,
                 "success" if row["success"] else "FAILURE", row["steps"], row["seconds"])

    print(expert_table(expert_success(cfg, show)))
    return 0


@dataclass
class BenchmarkCommand:
    """The paper's experiments on the twin."""

    sizes: Annotated[benchmark.BenchmarkConfig, tyro.conf.arg(name="")] = field(
        default_factory=benchmark.BenchmarkConfig)
    quick: bool = False
    """A smoke run of a few minutes that still trains and evaluates for real, covering every table (its sizes
    become the defaults)."""


def benchmark_twin_default(argv: list[str]) -> tuple[BenchmarkCommand, list[str]]:
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--quick", action="store_true")
    known, _ = pre.parse_known_args(argv)
    sizes = benchmark.quick() if known.quick else benchmark.BenchmarkConfig()
    return BenchmarkCommand(sizes=sizes, quick=known.quick), argv


def benchmark_twin(cmd: BenchmarkCommand) -> int:
    """Resumable (every evaluation continues from its last episode, every other stage is skipped when its output
    exists), so it is safe to leave in the background for hours:
    nohup pivla benchmark twin --out runs/benchmark > runs/benchmark.log 2>&1 &"""
    print(f"benchmark finished: report at {benchmark.run_benchmark(cmd.sizes)}")
    return 0
