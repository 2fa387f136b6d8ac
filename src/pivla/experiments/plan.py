"""A study's plan: the evaluations it runs, in order, grouped by the settings they share."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, NamedTuple

from pivla.control.asynchronous import ExecutionConfig, SyncConfig
from pivla.control.executors import ExecutorConfig
from pivla.evaluation.runner import EvalConfig
from pivla.experiments.conditions import Cell

Split = Literal["train", "validation", "test"]


class Evaluation(NamedTuple):
    """One evaluation of a study: a policy (its recipe's name), a cell, the label it is stored under (its
    executor's name, or an execution variant's), and the executor. A study runs it once per training seed."""

    policy: str
    cell: Cell
    label: str
    executor: ExecutorConfig

    @property
    def key(self) -> tuple[str, str, str]:
        """Its coordinates in the study's results (``ResultsStore``): policy, cell name, label."""
        return self.policy, self.cell.name, self.label


@dataclass(frozen=True)
class EvaluationPlan:
    """Evaluations that share their settings: the split their episodes come from, episodes per task (None:
    the study's count for the split), videos, and when queries go out and how late answers come."""

    evaluations: tuple[Evaluation, ...]
    split: Split = "test"
    episodes: int | None = None
    videos: int = 0
    execution: ExecutionConfig = dataclasses.field(default_factory=SyncConfig)
    latency_ms: str = "0"

    @staticmethod
    def of(evaluations: Iterable[Evaluation], **settings: Any) -> EvaluationPlan:
        """A plan of these evaluations, each key once where several tables share an evaluation (in the place
        of its first mention)."""
        unique = {ev.key: ev for ev in evaluations}
        return EvaluationPlan(tuple(unique.values()), **settings)

    def __iter__(self) -> Iterator[Evaluation]:
        return iter(self.evaluations)

    def __len__(self) -> int:
        return len(self.evaluations)

    def of_policies(self, names: Iterable[str]) -> list[Evaluation]:
        wanted = set(names)
        return [ev for ev in self.evaluations if ev.policy in wanted]


def eval_config(ev: Evaluation, plan: EvaluationPlan, *, policy: Path, out: Path, realism: str, family: bool,
                episodes: int | None = None, **settings: Any) -> EvalConfig:
    """The evaluation's ``EvalConfig``: its cell's fields, the plan's settings, and the study's (``settings``).
    With ``family`` the episodes are seeded from the split's seed family and the cell's code, as every twin
    study does; else from the legacy ``seed`` (LIBERO, ``pivla ablate``)."""
    family_fields = {"seed_family": plan.split, "condition": ev.cell.condition} if family else {}
    return EvalConfig(policy=str(policy), out=str(out), executor=ev.executor, split=plan.split,
                      episodes=episodes if episodes is not None else plan.episodes, videos=plan.videos,
                      execution=plan.execution, latency_ms=plan.latency_ms, **ev.cell.eval_fields(realism),
                      **family_fields, **settings)
