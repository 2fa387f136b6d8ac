"""The recipe that turns demonstrations into a policy ready to evaluate, shared by ``pivla demo`` and
``pivla ablate`` so that their numbers mean the same thing: the validated training settings
(``TrainConfig``'s defaults), then the policy's own closed loop on validation seeds, then AURD's thresholds
from its successful validation rollouts (METHOD.md: thresholds describe the states *this policy* visits when
it succeeds, not the expert's).
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

from pivla.control.calibrate import CalibrationConfig, calibrate
from pivla.control.executors import FixedConfig
from pivla.data.read import read_dataset
from pivla.envs.backend import BackendConfig
from pivla.evaluation.runner import EvalConfig, evaluate
from pivla.model.config import ModelConfig
from pivla.policy import load_policy
from pivla.training.checkpoint import write_calibration
from pivla.training.config import LossConfig, TrainConfig

log = logging.getLogger(__name__)


def recipe(data: str, out: str, seed: int = 0, *, steps: int | None = None, batch_size: int | None = None,
           image_size: int | None = None, loss_overrides: dict | None = None, model: ModelConfig | None = None,
           progress: bool = True) -> TrainConfig:
    """The validated training recipe on ``data``, with the sizes a caller may change."""
    base = TrainConfig()
    model = model or base.model
    if image_size is not None:
        model = dataclasses.replace(model, image_size=image_size)
    return dataclasses.replace(
        base, data=data, out=out, seed=seed, steps=steps or base.steps, batch_size=batch_size or base.batch_size,
        model=model, loss=dataclasses.replace(LossConfig(), **(loss_overrides or {})), progress=progress)


def validation_rollouts(run: Path, record: Path, results: Path, episodes: int, seed: int, realism: str,
                        workers: int, env: str = "tabletop", suite: str = "pick_place", tasks: str | None = None,
                        max_steps: int | None = None, libero_init: str = "official",
                        family: bool = False, libero_mesh_faces: int = 0,
                        dispatch: BackendConfig | None = None) -> dict:
    """Run the policy with fixed horizon on validation seeds and record every rollout into ``record``: the
    validation family's in-distribution episodes with ``family`` (twin), else the legacy ``seed`` (LIBERO:
    ``libero_init="random"`` plays sampled scenes, not the official init states)."""
    ec = EvalConfig(policy=str(run), out=str(results), env=env, suite=suite, tasks=tasks, executor=FixedConfig(),
                    episodes=episodes, seed=seed, realism=realism, workers=workers, videos=0, max_steps=max_steps,
                    record=str(record), split="validation", libero_init=libero_init,
                    libero_mesh_faces=libero_mesh_faces, seed_family="validation" if family else None,
                    condition="in_distribution" if family else None, dispatch=dispatch or BackendConfig())
    return evaluate(ec, progress=False)


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
