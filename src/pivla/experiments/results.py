"""The results store: a study's finished evaluations by key, pooled over its training seeds, with the success
rates and paired comparisons every report prints.

A key is an evaluation's coordinates in its study's layout, the executor label last (``pivla.experiments.
layout``). A rate or a comparison needs every seed's evaluation; a comparison pairs the two sides' episodes
within each seed (same task, same episode, same seed) and pools the pairs.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Protocol

import numpy as np

from pivla.control.executors import CUTS, first_cut
from pivla.evaluation.runner import load_rows
from pivla.evaluation.stats import compare, paired_rows, paired_successes, wilson_interval
from pivla.experiments.layout import EPISODES, RESULTS

Key = tuple[str, ...]


class Layout(Protocol):
    def seeds(self) -> list[int]: ...

    def evaluation_dirs(self, key: Key, split: str, seeds: list[int]) -> list[Path | None]: ...


def pooled_rate(successes: int, episodes: int) -> dict:
    """Successes of ``episodes`` as the reports hold a rate: the counts, the rate and its Wilson 95% interval."""
    return {"successes": successes, "episodes": episodes, "rate": successes / episodes if episodes else 0.0,
            "ci95": list(wilson_interval(successes, episodes))}


class ResultsStore:
    """Finished evaluations of one study directory (its ``layout``), pooled over the training seeds found when
    the store is made."""

    def __init__(self, layout: Layout):
        self.layout = layout
        self.seeds = layout.seeds()

    def _dirs(self, key: Key, split: str) -> list[Path]:
        return [d for d in self.layout.evaluation_dirs(key, split, self.seeds)
                if d is not None and (d / RESULTS).exists()]

    def has(self, *key: str, split: str = "test") -> bool:
        """Whether every seed's evaluation of ``key`` has finished."""
        return len(self._dirs(key, split)) == len(self.seeds) > 0

    def results(self, *key: str, split: str = "test") -> list[dict]:
        """The results.json of every seed's finished evaluation of ``key``."""
        return [json.loads((d / RESULTS).read_text()) for d in self._dirs(key, split)]

    def rate(self, *key: str, split: str = "test") -> dict | None:
        """Successes pooled over the seeds (``pooled_rate``); None unless every seed's evaluation has finished."""
        res = self.results(*key, split=split)
        if not res or len(res) != len(self.seeds):
            return None
        return pooled_rate(sum(r["successes"] for r in res), sum(r["episodes"] for r in res))

    def rows(self, *key: str, split: str = "test") -> list[tuple[int, list[dict]]]:
        """Each seed's episode rows of ``key`` (none where it has not run)."""
        return [(s, load_rows(d / EPISODES) if d is not None else [])
                for s, d in zip(self.seeds, self.layout.evaluation_dirs(key, split, self.seeds))]

    def compare(self, a: Key, b: Key, split: str = "test") -> dict | None:
        """A against B, paired episode by episode within each seed, pooled (``pivla.evaluation.stats.compare``);
        None unless both have finished. Cells that share seed codes pair too (a displacement level against level
        0, servo against ideal actuation)."""
        if not (self.has(*a, split=split) and self.has(*b, split=split)):
            return None
        pairs = [paired_successes(ra, rb)
                 for (_, ra), (_, rb) in zip(self.rows(*a, split=split), self.rows(*b, split=split))]
        return compare(np.concatenate([x for x, _ in pairs]), np.concatenate([y for _, y in pairs]))

    def departures(self, *cell: str) -> dict[str, dict] | None:
        """AURD's test episodes of a cell (its key without the label) against the fixed horizon's, grouped by
        AURD's first cut (``first_cut``; "none": it never cut, so both ran the same actions): per group the
        episodes and those only AURD / only the fixed horizon solved. Says which of AURD's decisions its wins and
        losses start at."""
        aurd, fixed = (*cell, "aurd"), (*cell, "fixed")
        if not (self.has(*aurd) and self.has(*fixed)):
            return None
        groups = {g: [0, 0, 0] for g in ("none", *CUTS)}
        for (_, rows_a), (_, rows_b) in zip(self.rows(*aurd), self.rows(*fixed)):
            for ra, rb in paired_rows(rows_a, rows_b):
                sa, sb = bool(ra["success"]), bool(rb["success"])
                group = groups[first_cut(ra["trace"]) or "none"]
                group[0] += 1
                group[1] += sa and not sb
                group[2] += sb and not sa
        return {g: {"episodes": n, "only_aurd": ia, "only_fixed": ib} for g, (n, ia, ib) in groups.items()}

    def task_rates(self, *key: str) -> dict[str, dict]:
        """Per task, successes pooled over the seeds (``pooled_rate``)."""
        per: dict[str, list[bool]] = {}
        for _, rows in self.rows(*key):
            for r in rows:
                per.setdefault(r["task"], []).append(bool(r["success"]))
        return {t: {"successes": int(sum(v)), "episodes": len(v), "rate": float(np.mean(v)),
                    "ci95": list(wilson_interval(int(sum(v)), len(v)))} for t, v in per.items()}
