"""Idempotent stages: collect, train, calibrate, evaluate. Calling a stage does its work unless its output
exists (``done``), so a study interrupted anywhere resumes where it stopped by running again; an evaluation
continues from its last logged episode and a training from its last checkpoint. ``perform`` logs a stage and
times it when it runs; ``StageTimes`` keeps those times across invocations.

Calibration follows the recipe of every study: AURD's thresholds from the policy's own successful validation
rollouts (thresholds describe the states *this policy* visits when it succeeds, not the expert's), the
validation demonstrations when it succeeded in none.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from pivla.control.calibrate import CalibrationConfig, calibrate
from pivla.control.executors import FixedConfig
from pivla.data.read import read_dataset
from pivla.envs import select_tasks
from pivla.envs.backend import BackendConfig, ray_session
from pivla.envs.collect import CollectConfig, collect_demos
from pivla.evaluation.runner import EvalConfig, evaluate, evaluation_pool
from pivla.experiments.conditions import Cell
from pivla.experiments.layout import (
    calibrated,
    checkpointed,
    demos_file,
    evaluation_done,
    read_results,
    rollouts_file,
    training_done,
)
from pivla.io import atomic_write_json, read_json
from pivla.policy import load_policy
from pivla.training.checkpoint import copied_from, copy_policy, write_calibration
from pivla.training.config import TrainConfig
from pivla.training.trainer import train

log = logging.getLogger(__name__)
T = TypeVar("T")
Timer = Callable[[str, Callable[[], Any]], Any]


class StageTimes:
    """Seconds per stage in ``path``, summed over the invocations of a resumable run. The running stage's time
    is saved every ``every`` seconds as well, so a run killed mid-stage (a job that outlives no session) loses
    at most that much of it."""

    def __init__(self, path: Path, every: float = 60.0) -> None:
        self.path, self.every = path, every
        self.times: dict[str, float] = read_json(path) if path.exists() else {}
        self._lock = threading.Lock()

    def run(self, name: str, fn: Callable[[], T]) -> T:
        """``fn()``, its wall time added to stage ``name``."""
        before, start, stop = self.times.get(name, 0.0), time.monotonic(), threading.Event()

        def save() -> None:
            with self._lock:
                self.times[name] = round(before + time.monotonic() - start, 1)
                atomic_write_json(self.path, self.times)

        def tick() -> None:
            while not stop.wait(self.every):
                save()

        ticker = threading.Thread(target=tick, name=f"time of {name}", daemon=True)
        ticker.start()
        try:
            return fn()
        finally:
            stop.set()
            ticker.join()
            save()


class Stage:
    """A unit of a study's work with an output on disk: ``done()`` says whether it exists, calling the stage does
    the work unless it does."""

    def done(self) -> bool:
        raise NotImplementedError

    def run(self) -> Any:
        raise NotImplementedError

    def __call__(self) -> Any:
        return None if self.done() else self.run()


def perform(stage: Stage, key: str, label: str | None = None, timed: Timer | None = None) -> Any:
    """Run a stage unless it is done, logging ``[label] ...`` or ``[label] already done, skipping``, its wall time
    kept under ``key`` by ``timed`` (``StageTimes.run``, or a study's own timer) when it runs."""
    done = stage.done()
    log.info("[%s] %s", label or key, "already done, skipping" if done else "...")
    if done:
        return None
    return timed(key, stage.run) if timed is not None else stage.run()


@dataclass(frozen=True)
class Collect(Stage):
    """Demonstrations of the tasks whose file is missing (a task's file is written once it is complete, so a
    rerun collects only the rest). ``strict``: a task that got fewer episodes than asked is an error (a study
    whose figures need the full count), else a logged shortfall (collection writes what it kept)."""

    cfg: CollectConfig
    strict: bool = True

    def missing(self) -> list[str]:
        out = Path(self.cfg.out)
        return [str(s.index) for s in select_tasks(self.cfg.env, self.cfg.suite, self.cfg.tasks)
                if not demos_file(out, s.name).exists()]

    def done(self) -> bool:
        return not self.missing()

    def run(self) -> int:
        cc, missing = self.cfg, self.missing()
        log.info("[collect] %s: %d per task, tasks %s -> %s", cc.suite, cc.episodes, ",".join(missing), cc.out)
        status = collect_demos(dataclasses.replace(cc, tasks=",".join(missing)))
        if status != 0 and self.strict:
            raise RuntimeError(f"collection of {cc.suite} into {cc.out} fell short of {cc.episodes} per task")
        return status


@dataclass(frozen=True)
class Train(Stage):
    """A training run to its last step, resumed from its checkpoints when an earlier one was interrupted; with a
    ray ``dispatch``, a Ray task (``train_all``)."""

    cfg: TrainConfig
    dispatch: BackendConfig | None = None

    def done(self) -> bool:
        return training_done(Path(self.cfg.out))

    @property
    def on_ray(self) -> bool:
        return self.dispatch is not None and self.dispatch.backend == "ray"

    def run(self) -> Any:
        if self.on_ray:
            return _ray_trainings([self], self.dispatch)
        return train(self.cfg, resume=checkpointed(Path(self.cfg.out)))


@dataclass(frozen=True)
class CopyPolicy(Stage):
    """A policy trained elsewhere (``copy_policy``) in the place of a study's own training; a study directory
    that already holds another policy is refused rather than evaluated under the wrong name."""

    source: Path
    dest: Path

    def done(self) -> bool:
        if not self.dest.exists():
            return False
        held = copied_from(self.dest)
        if held != str(self.source.resolve()):
            what = "a policy trained there" if held is None else f"a copy of {held}"
            raise ValueError(f"{self.dest} holds {what}, not a copy of {self.source}: choose another --out")
        return True

    def run(self) -> Path:
        return copy_policy(self.source, self.dest)


def train_all(stages: Sequence[Train]) -> None:
    """Every training not done yet: one after the other in this process (``--backend local``), or each a Ray task
    (``--backend ray``), all submitted at once and running as far as the cluster's resources go."""
    pending = [s for s in stages if not s.done()]
    for stage in (s for s in pending if not s.on_ray):
        stage.run()
    remote = [s for s in pending if s.on_ray]
    if remote:
        _ray_trainings(remote, remote[0].dispatch)


def _ray_trainings(stages: Sequence[Train], dispatch: BackendConfig) -> None:
    """Trainings as Ray tasks that ask for a GPU where the cluster has them, else for their CPUs
    (``training_resources``). A task whose worker is lost runs again (from the run's last checkpoint); a driver
    killed leaves the unfinished runs to the same command, which resumes each from its checkpoints. The run
    directories must be on a filesystem every node sees."""
    with ray_session(dispatch) as ray:
        resources = ray.cluster_resources()
        node_cpus = min((n["Resources"].get("CPU", 0) for n in ray.nodes() if n["Alive"]), default=1)
        refs = {}
        for stage in stages:
            request = training_resources(stage.cfg, resources.get("GPU", 0), int(node_cpus))
            log.info("[train] %s as a Ray task (%s)", stage.cfg.out, ", ".join(f"{k} {v}" for k, v in request.items()))
            refs[ray.remote(max_retries=TRAIN_RETRIES, **request)(_train_task).remote(stage.cfg)] = stage
        errors, waiting = [], list(refs)
        while waiting:
            [ref], waiting = ray.wait(waiting, num_returns=1)
            try:
                ray.get(ref)
                log.info("[train] %s done", refs[ref].cfg.out)
            except ray.exceptions.RayError as e:  # every training is waited for, then the first failure raised
                errors.append(f"{refs[ref].cfg.out}: {e}")
        if errors:
            raise RuntimeError(f"{len(errors)} of {len(refs)} Ray trainings failed; first: {errors[0]}")


TRAIN_RETRIES = 3  # a training task's runs after its worker is lost (each resumes from the last checkpoint)


def training_resources(cfg: TrainConfig, cluster_gpus: float, node_cpus: int) -> dict[str, float]:
    """A training task's resource request: one GPU (and a CPU) where the cluster has GPUs; else its torch
    threads' CPUs, or with ``threads`` 0 (all cores) a whole node's."""
    if cluster_gpus >= 1:
        return {"num_gpus": 1, "num_cpus": 1}
    return {"num_cpus": cfg.threads if cfg.threads > 0 else max(1, node_cpus)}


def _train_task(cfg: TrainConfig) -> None:
    """A Ray task: the training, resumed from its checkpoints when an earlier attempt was interrupted."""
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    Train(cfg)()


@dataclass(frozen=True)
class Evaluate(Stage):
    """An evaluation (``pivla eval``), resumed from its last episode; done when its results hold ``expected``
    episodes (None: when it has results at all) and, if it records its rollouts, every task's recording is
    there. Calling it returns the results either way."""

    cfg: EvalConfig
    expected: int | None = None
    progress: bool = False

    def done(self) -> bool:
        out = Path(self.cfg.out)
        if not evaluation_done(out):
            return False
        if self.expected is not None and read_results(out)["episodes"] < self.expected:
            return False
        record = Path(self.cfg.record) if self.cfg.record else None
        return record is None or all(rollouts_file(record, s.name).exists()
                                     for s in select_tasks(self.cfg.env, self.cfg.suite, self.cfg.tasks))

    def run(self) -> dict:
        return evaluate(self.cfg, progress=self.progress)

    def __call__(self) -> dict:
        return read_results(Path(self.cfg.out)) if self.done() else self.run()


@dataclass(frozen=True)
class Calibrate(Stage):
    """AURD's thresholds written into a run, from ``calibration_episodes``."""

    run_dir: Path
    rollouts: Path
    demos: Path
    cfg: CalibrationConfig = dataclasses.field(default_factory=CalibrationConfig)

    def done(self) -> bool:
        return calibrated(self.run_dir)

    def run(self) -> str:
        return calibrate_on_rollouts(self.run_dir, self.rollouts, self.demos, self.cfg)


@contextlib.contextmanager
def shared_evaluations(workers: int, dispatch: BackendConfig) -> Iterator[None]:
    """One set of evaluation processes for every local evaluation of ``workers`` in the block (Ray runs its own):
    a study opens it around a run of evaluations, not around a training, which needs both cores."""
    with evaluation_pool(workers if dispatch.backend == "local" else 1):
        yield


def validation_rollouts(run: Path, record: Path, results: Path, cell: Cell, *, episodes: int, realism: str,
                        workers: int, family: bool, seed: int = EvalConfig.seed, tasks: str | None = None,
                        max_steps: int | None = None, libero_mesh_faces: int = 0,
                        dispatch: BackendConfig | None = None) -> Evaluate:
    """The evaluation that runs the policy with a fixed horizon on validation seeds and records every rollout
    into ``record``: the validation family's episodes of the cell with ``family`` (twin), else the legacy
    ``seed`` (on LIBERO, a ``libero(suite, "random")`` cell plays sampled scenes, not the official states)."""
    family_fields = {"seed_family": "validation", "condition": cell.condition} if family else {}
    ec = EvalConfig(policy=str(run), out=str(results), tasks=tasks, executor=FixedConfig(), episodes=episodes,
                    seed=seed, workers=workers, videos=0, max_steps=max_steps, record=str(record),
                    split="validation", libero_mesh_faces=libero_mesh_faces, dispatch=dispatch or BackendConfig(),
                    **cell.eval_fields(realism), **family_fields)
    return Evaluate(ec)


def calibration_episodes(rollouts: Path, demos: Path) -> tuple[list, Path]:
    """The successful validation rollouts, or the validation demonstrations when the policy succeeded in none
    (a policy that never succeeds has no in-distribution signals of its own); with the directory used."""
    episodes = read_dataset(rollouts) if rollouts.exists() else []
    if any(ep.success for ep in episodes):
        return episodes, rollouts
    log.warning("no successful validation rollout in %s: calibrating on the validation demonstrations", rollouts)
    return read_dataset(demos), demos


def calibrate_on_rollouts(run: Path, rollouts: Path, demos: Path, cfg: CalibrationConfig | None = None) -> str:
    """Thresholds from ``calibration_episodes``, written into the run; returns the source used."""
    policy = load_policy(run, device="cpu")
    episodes, source = calibration_episodes(rollouts, demos)
    calib, stats = calibrate(policy, episodes, cfg or CalibrationConfig(), source=str(source))
    write_calibration(run, vars(calib), stats)
    return str(source)
