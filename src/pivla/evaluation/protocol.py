"""The recipe that turns demonstrations into a policy ready to evaluate, shared by ``pivla demo`` and
``pivla ablate`` so that their numbers mean the same thing: the same training settings, then the policy's
own closed loop on validation seeds, then AURD's thresholds from its successful validation rollouts
(METHOD.md: thresholds describe the states *this policy* visits when it succeeds, not the expert's).
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from pivla.model.config import ModelConfig
    from pivla.training.trainer import TrainConfig

log = logging.getLogger(__name__)

# The demo's training length and batch, which ablations use too. More, smaller updates: at 1800 x 64 the first
# policy had not learned to localise objects, and twice the steps of the same model added ~11 points
# (docs/results.md, sessions 2 and 5). With 90 demos per task 4000 steps scored as well as 5000 on 1440
# validation episodes and keep the demo under 30 min (session 12).
STEPS = 4000
BATCH_SIZE = 32


def train_config(data: str, out: str, steps: int, batch_size: int, seed: int, loss_overrides: dict | None = None,
                 progress: bool = True, model: ModelConfig | None = None) -> TrainConfig:
    """The demo's training settings: a 5% validation split, five evaluations, checkpoints and value refreshes
    per run, warm-up of at most 200 steps."""
    from pivla.model.config import ModelConfig
    from pivla.training.losses import LossConfig
    from pivla.training.trainer import TrainConfig

    every = max(steps // 5, 1)
    return TrainConfig(data=data, out=out, steps=steps, batch_size=batch_size, seed=seed, val_fraction=0.05,
                       eval_every=every, ckpt_every=every, value_refresh_every=every, warmup=min(200, steps // 10),
                       loss=dataclasses.replace(LossConfig(), **(loss_overrides or {})), progress=progress,
                       model=model or ModelConfig())


def validation_rollouts(run: Path, record: Path, results: Path, episodes: int, seed: int, realism: str,
                        workers: int, env: str = "tabletop", suite: str = "pick_place", tasks: str | None = None,
                        max_steps: int | None = None) -> dict:
    """Run the policy with fixed horizon on validation seeds and record every rollout into ``record``."""
    from pivla.evaluation.runner import EvalConfig, evaluate

    ec = EvalConfig(policy=str(run), out=str(results), env=env, suite=suite, tasks=tasks, executor="fixed",
                    episodes=episodes, seed=seed, realism=realism, workers=workers, videos=0, max_steps=max_steps,
                    record=str(record), split="validation")
    return evaluate(ec, progress=False)


def calibrate_on_rollouts(run: Path, rollouts: Path, demos: Path, pred_baseline: str = "episode") -> str:
    """Thresholds from the successful validation rollouts, or from the validation demonstrations when the
    policy succeeded in none (a policy that never succeeds has no in-distribution signals of its own).
    Returns the source used."""
    from pivla.control.calibrate import CalibrationConfig, calibrate
    from pivla.data.format import read_dataset
    from pivla.policy import load_policy

    policy = load_policy(run, device="cpu")
    cfg = CalibrationConfig(pred_baseline=pred_baseline)
    episodes = read_dataset(rollouts) if rollouts.exists() else []
    source = rollouts
    if not any(ep.success for ep in episodes):
        log.warning("no successful validation rollout of %s: calibrating on the validation demonstrations", run)
        episodes, source = read_dataset(demos), demos
    calibrate(policy, episodes, cfg, source=str(source))
    return str(source)
