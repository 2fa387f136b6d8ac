"""Run layouts: where each study keeps its files, the one place in pivla where a run directory's paths are
spelled. Stages, the results store and the reports ask a layout for a path; runs already on disk keep these
names, so a layout never renames one.

Every layout answers the results store's two questions: the training seeds it holds (``seeds``) and where the
evaluation of a key lies for each of them (``evaluation_dirs``; ``None`` where it has no place). A key is an
evaluation's coordinates in the study, its executor label last (``(policy, cell, label)`` in the twin
benchmark, ``(condition, executor)`` in a directory of evaluations).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

RESULTS = "results.json"
EPISODES = "episodes.jsonl"
DEMOS_SUFFIX = "_demo.hdf5"


def evaluation_done(target: Path) -> bool:
    return (target / RESULTS).exists()


def read_results(target: Path) -> dict:
    return json.loads((target / RESULTS).read_text())


def rollouts_file(record: Path, task: str) -> Path:
    """A task's recorded rollouts (``pivla eval --record``)."""
    return record / f"{task}_rollouts.hdf5"


def demos_file(data: Path, task: str) -> Path:
    """A task's demonstrations in a collected dataset (``pivla collect``)."""
    return data / f"{task}{DEMOS_SUFFIX}"


def demo_files(data: Path) -> list[Path]:
    """Every task's demonstrations in a collected dataset, by name."""
    return sorted(data.glob(f"*{DEMOS_SUFFIX}"))


def training_done(run: Path) -> bool:
    """Whether ``pivla train`` finished this run (its status says done)."""
    status = run / "status.json"
    return status.exists() and bool(json.loads(status.read_text()).get("done", False))


def checkpointed(run: Path) -> bool:
    """Whether a training of this run left checkpoints to resume from."""
    return (run / "checkpoints").exists()


def calibrated(run: Path) -> bool:
    return (run / "calibration.json").exists()


@dataclass(frozen=True)
class TwinLayout:
    """``pivla benchmark twin``: ``data/`` shared by every seed, ``seed{s}/`` per training seed."""

    root: Path

    CONFIG = "benchmark_config.json"

    @staticmethod
    def holds(root: Path) -> bool:
        """Whether ``root`` is a twin benchmark's directory (its config is written before anything else)."""
        return (Path(root) / TwinLayout.CONFIG).exists()

    @property
    def config(self) -> Path:
        return self.root / self.CONFIG

    @property
    def decisions(self) -> Path:
        return self.root / "decisions.json"

    @property
    def timings(self) -> Path:
        return self.root / "timings.json"

    @property
    def test_plan(self) -> Path:
        return self.root / "test_plan.json"

    @property
    def report_md(self) -> Path:
        return self.root / "benchmark.md"

    @property
    def report_json(self) -> Path:
        return self.root / "benchmark.json"

    def figure(self, name: str) -> str:
        """A figure's path relative to the root (as the report links it)."""
        return f"figures/{name}.png"

    def data(self, suite: str, first: int | None = None) -> Path:
        """Demonstrations of a suite (train seeds); ``first``: the set of each task's first n episodes."""
        return self.root / "data" / (suite if first is None else f"{suite}_{first}")

    def val_data(self, suite: str) -> Path:
        """Validation demonstrations of a suite (calibration's fallback)."""
        return self.root / "data" / "val" / suite

    def _seed(self, seed: int) -> Path:
        return self.root / f"seed{seed}"

    def policy(self, name: str, seed: int) -> Path:
        return self._seed(seed) / "policies" / name

    def val_rollouts(self, name: str, seed: int) -> Path:
        """The policy's recorded validation rollouts (what it is calibrated on)."""
        return self._seed(seed) / "val_rollouts" / name

    def train_rollouts(self, seed: int, cell: str) -> Path:
        """The failure round's recorded rollouts of the headline policy (train seeds)."""
        return self._seed(seed) / "train_rollouts" / cell

    def evaluation(self, seed: int, split: str, policy: str, cell: str, label: str) -> Path:
        return self._seed(seed) / split / policy / cell / label

    def seeds(self) -> list[int]:
        """Training seeds with a directory on disk."""
        return sorted(int(p.name.removeprefix("seed")) for p in self.root.glob("seed*") if p.name[4:].isdigit())

    def evaluation_dirs(self, key: tuple[str, str, str], split: str, seeds: list[int]) -> list[Path | None]:
        return [self.evaluation(s, split, *key) for s in seeds]


@dataclass(frozen=True)
class DemoLayout:
    """``pivla demo``: one policy, its data and ``eval/<condition>/<executor>``."""

    root: Path

    @property
    def train_data(self) -> Path:
        return self.root / "data" / "train"

    @property
    def val_data(self) -> Path:
        return self.root / "data" / "val"

    @property
    def val_rollouts(self) -> Path:
        return self.root / "data" / "val_rollouts"

    @property
    def val_rollouts_eval(self) -> Path:
        return self.root / "data" / "val_rollouts_eval"

    @property
    def policy(self) -> Path:
        return self.root / "policy"

    def evaluation(self, condition: str, executor: str) -> Path:
        return self.root / "eval" / condition / executor

    @property
    def timings(self) -> Path:
        return self.root / "timings.json"


@dataclass(frozen=True)
class AblationLayout:
    """``pivla ablate``: ``runs/<variant>`` trained, ``eval/<name>`` evaluated, ``ablation.md``. An evaluation's
    name says what it is: ``model_<variant>`` (AURD), ``model_<variant>_fixed_h5``, ``exec_<label>`` (the full
    model with an execution variant)."""

    root: Path

    def policy(self, variant: str) -> Path:
        return self.root / "runs" / variant

    def val_rollouts(self, variant: str) -> Path:
        return self.root / "val_rollouts" / variant

    def val_rollouts_eval(self, variant: str) -> Path:
        return self.root / "val_rollouts_eval" / variant

    @staticmethod
    def model_key(variant: str, fixed: bool = False) -> tuple[str]:
        """A trained variant's evaluation with AURD, or with the fixed horizon H=5."""
        return (f"model_{variant}_fixed_h5" if fixed else f"model_{variant}",)

    @staticmethod
    def exec_key(label: str) -> tuple[str]:
        """The full model's evaluation with an execution variant."""
        return (f"exec_{label}",)

    def evaluation(self, key: tuple[str]) -> Path:
        return self.root / "eval" / key[0]

    @property
    def report_md(self) -> Path:
        return self.root / "ablation.md"

    def seeds(self) -> list[int]:
        return [0]

    def evaluation_dirs(self, key: tuple[str], split: str, seeds: list[int]) -> list[Path | None]:
        return [self.evaluation(key)]


@dataclass(frozen=True)
class LiberoLayout:
    """``pivla libero run``: ``data/``, ``policy/``, ``eval/<executor>``, ``libero.md`` and ``libero.json``."""

    root: Path

    @property
    def data(self) -> Path:
        return self.root / "data"

    @property
    def policy(self) -> Path:
        return self.root / "policy"

    @property
    def val_rollouts(self) -> Path:
        return self.root / "val_rollouts"

    @property
    def val_rollouts_eval(self) -> Path:
        return self.root / "val_rollouts_eval"

    def evaluation(self, executor: str) -> Path:
        return self.root / "eval" / executor

    def evaluated(self) -> list[str]:
        """Executors with a finished evaluation, by name."""
        return [d.name for d in sorted((self.root / "eval").iterdir()) if evaluation_done(d)]

    @property
    def timings(self) -> Path:
        return self.root / "timings.json"

    @property
    def report_md(self) -> Path:
        return self.root / "libero.md"

    @property
    def report_json(self) -> Path:
        return self.root / "libero.json"

    def seeds(self) -> list[int]:
        return [0]

    def evaluation_dirs(self, key: tuple[str], split: str, seeds: list[int]) -> list[Path | None]:
        return [self.evaluation(key[0])]


@dataclass(frozen=True)
class EvaluationsLayout:
    """Any directory of evaluations, as ``pivla report`` reads it: ``DIR/**/<condition>/<evaluation>/`` with
    results.json, the parent directory naming the condition and results.json the executor; test
    evaluations only (validation rollouts that thresholds were calibrated on are not results)."""

    root: Path

    @cached_property
    def found(self) -> dict[tuple[str, str], Path]:
        """(condition, executor) -> evaluation directory, read once."""
        found: dict[tuple[str, str], Path] = {}
        for res in sorted(self.root.rglob(RESULTS)):
            d, meta = res.parent, json.loads(res.read_text())
            if meta.get("split", "test") != "test":
                continue
            key = (d.parent.name, meta["executor"])
            if key in found:
                raise ValueError(f"{found[key]} and {d} are both {key[1]} evaluations of condition {key[0]!r}: pivla "
                                 "report reads DIR/<condition>/<evaluation>/results.json, one evaluation per executor "
                                 "and condition")
            found[key] = d
        return found

    @property
    def figures(self) -> Path:
        return self.root / "figures"

    @property
    def report_md(self) -> Path:
        return self.root / "report.md"

    def seeds(self) -> list[int]:
        return [0]

    def evaluation_dirs(self, key: tuple[str, str], split: str, seeds: list[int]) -> list[Path | None]:
        return [self.found.get(key)] if split == "test" else [None]
