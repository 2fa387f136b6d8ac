"""Policy recipes: what each policy of a study is trained on and how, its kind a field rather than a name prefix;
the loss and head variants of the ablations (Tables 4, 5, 7), the execution variants (Table 6), and the
validated training recipe every study trains with (``TrainConfig``'s defaults at the study's sizes), so that
the studies' numbers mean the same thing.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from enum import StrEnum
from typing import Any

from pivla.control.executors import ExecutorConfig, executor_config
from pivla.model.config import ModelConfig
from pivla.training.config import LossConfig, TrainConfig

# variant -> (table, loss overrides)
TRAIN_VARIANTS: dict[str, tuple[str, dict]] = {
    "full": ("heads+loss", {}),
    "discrete_only": ("heads", {"use_continuous": False}),
    "continuous_only": ("heads", {"use_discrete": False}),
    "no_sp": ("loss", {"use_sp": False}),
    "no_rl": ("loss", {"use_rl": False}),
    "il_only": ("loss", {"use_sp": False, "use_rl": False, "use_recon": False}),
    "continuous_il_only": ("components", {"use_discrete": False, "use_sp": False, "use_rl": False, "use_recon": False}),
}
# Table 7: (row, trained variant, executor whose result counts): each adds one component to the row above
INCREMENTAL: tuple[tuple[str, str, str], ...] = (
    ("continuous head, IL only, fixed H=5 (OpenVLA-OFT)", "continuous_il_only", "fixed"),
    ("+ dual heads (discrete + continuous)", "il_only", "fixed"),
    ("+ unified loss (L_IL + alpha L_RL + beta L_SP)", "full", "fixed"),
    ("+ AURD (full PI-VLA)", "full", "aurd"),
)
# Table 6: execution variants of the full model, label -> (executor, options); "fixed" and "fixed_h5" are the
# same executor under the labels the twin benchmark and pivla ablate store it under
EXECUTION_VARIANTS: dict[str, tuple[str, dict]] = {
    "aurd": ("aurd", {}), "aurd_check_after": ("aurd", {"check": "after"}), "fixed": ("fixed", {}),
    "fixed_h5": ("fixed", {"horizon": 5}), "fixed_h8": ("fixed", {"horizon": 8}), "ensemble": ("ensemble", {}),
    "adahorizon": ("adahorizon", {}),
}


def execution_variant(label: str) -> ExecutorConfig:
    """The executor of an execution variant's label (a plain executor's name is its own label)."""
    name, options = EXECUTION_VARIANTS[label]
    return executor_config(name, **options)


class Kind(StrEnum):
    """What a policy is in a study, which says where its data comes from and what it is compared against."""

    HEADLINE = "headline"  # the recipe on the full demonstrations (the ablations' full model)
    FAILURE_ROUND = "failure_round"  # the headline data plus the headline policy's own recorded rollouts
    SEEN_TASKS = "seen_tasks"  # trained on some tasks, tested on the held-out ones
    OTHER_SUITES = "other_suites"  # one multi-task policy for the other suites
    ABLATION = "ablation"  # a loss or head variant of the recipe (Tables 4, 5, 7)
    DEMO_COUNT = "demo_count"  # the first n demonstrations per task (Fig. 17)


@dataclass(frozen=True)
class Recipe:
    """A policy of a study: its name (its directory, so runs on disk keep it), its kind, the suites it trains on
    and those of its validation rollouts, its loss and head variant (``TRAIN_VARIANTS``), and for a
    ``DEMO_COUNT`` policy the demonstrations per task it keeps, how evenly its batches draw the tasks
    (``TrainConfig.task_balance``), the cameras its random shift moves (``TrainConfig.augment_shift_cameras``) and
    the decay of the weight average it deploys (``TrainConfig.ema_decay``)."""

    name: str
    kind: Kind
    data: tuple[str, ...] = ("pick_place",)
    suites: tuple[str, ...] = ("pick_place",)
    variant: str = "full"
    demos: int | None = None
    task_balance: float = 0.0
    augment_shift_cameras: tuple[str, ...] = ()
    ema_decay: float = 0.0

    def __post_init__(self) -> None:
        if self.variant not in TRAIN_VARIANTS:
            raise ValueError(f"unknown training variant {self.variant!r}; known: {', '.join(TRAIN_VARIANTS)}")
        if (self.demos is not None) != (self.kind is Kind.DEMO_COUNT):
            raise ValueError(f"{self.name}: demos is the demonstration count of a {Kind.DEMO_COUNT} policy only")

    @property
    def loss(self) -> dict[str, Any]:
        """Loss and head overrides of its variant."""
        return TRAIN_VARIANTS[self.variant][1]

    @property
    def rollouts(self) -> bool:
        """Whether it also trains on the headline policy's recorded rollouts (the failure round)."""
        return self.kind is Kind.FAILURE_ROUND


def recipe_config(data: str, out: str, seed: int = 0, *, steps: int | None = None, batch_size: int | None = None,
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
