"""``pivla bench ...``: each benchmark is a function of ``pivla.bench`` taking a typed config; this module
prints its figures (one JSON object with --json)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Annotated, Any, Generic, TypeVar

import tyro

from pivla.bench.control import ControlBenchConfig
from pivla.bench.data import DataBenchConfig
from pivla.bench.hf import HFBenchConfig
from pivla.bench.policy import InferBenchConfig, TrainBenchConfig
from pivla.bench.robot import RobotBenchConfig
from pivla.bench.serve import ServeBenchConfig
from pivla.bench.sim import SimBenchConfig

T = TypeVar("T")


@dataclass
class Bench(Generic[T]):
    """A benchmark's settings and how to print its figures."""

    bench: Annotated[T, tyro.conf.arg(name="")]
    json: bool = False
    """Print one JSON object."""


def _emit(result: dict[str, Any], as_json: bool) -> int:
    if as_json:
        print(json.dumps(result))
    else:
        for k, v in result.items():
            print(f"{k}: {v}")
    return 0


def infer(cmd: Bench[InferBenchConfig]) -> int:
    from pivla.bench.policy import run_infer_bench

    return _emit(run_infer_bench(cmd.bench), cmd.json)


def train(cmd: Bench[TrainBenchConfig]) -> int:
    from pivla.bench.policy import run_train_bench

    return _emit(run_train_bench(cmd.bench), cmd.json)


def data(cmd: Bench[DataBenchConfig]) -> int:
    from pivla.bench.data import run_data_bench

    return _emit(run_data_bench(cmd.bench), cmd.json)


def sim(cmd: Bench[SimBenchConfig]) -> int:
    from pivla.bench.sim import run_sim_bench

    return _emit(run_sim_bench(cmd.bench), cmd.json)


def control(cmd: Bench[ControlBenchConfig]) -> int:
    from pivla.bench.control import run_control_bench

    return _emit(run_control_bench(cmd.bench), cmd.json)


def hf(cmd: Bench[HFBenchConfig]) -> int:
    from pivla.bench.hf import run_hf_bench

    return _emit(run_hf_bench(cmd.bench), cmd.json)


def robot(cmd: Bench[RobotBenchConfig]) -> int:
    from pivla.bench.robot import run_robot_bench

    return _emit(run_robot_bench(cmd.bench), cmd.json)


def serve(cmd: Bench[ServeBenchConfig]) -> int:
    from pivla.bench.serve import run_serve_bench

    return _emit(run_serve_bench(cmd.bench), cmd.json)
