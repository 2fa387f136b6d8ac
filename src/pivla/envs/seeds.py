"""Episode seeds of the benchmark: families fixed here, disjoint by construction.

An episode seed fixes everything about a twin episode (layout, perturbation draws, servo noise, paraphrase);
``TabletopEnv.reset`` (and the SO-101 twin's) hashes it through numpy's ``SeedSequence``, so neighbouring
integers give independent episodes. Four families, one use each:

- ``train``: demonstrations (and policy rollouts recorded to train on);
- ``validation``: calibration and every recipe decision (checkpoints, thresholds, settings);
- ``test``: evaluated once per recipe; its numbers are reported, never tuned on;
- ``holdout``: no decision ever looks at it; evaluated once, for the final benchmark.

A seed packs (family, condition, task, episode) into bit fields above 2**31::

    seed = 2**31 + family << 29 + condition << 22 + task << 16 + episode

so two different keys never share a seed, and no family meets any seed used before the families existed:
``pivla.envs.rollout.episode_seed`` (demonstrations, validation rollouts, and the old test family
``job_seed(1000, ...)``, kept here as :func:`legacy_test_seed`) makes 31-bit seeds, all below 2**31. Every
seed is below 2**32, so it also suits 32-bit seeding APIs (``np.random.seed``, LIBERO).

The realism and a perturbation's level are not part of the key: the same episodes under ideal and servo
realism, or at every level of a sweep, are paired comparisons. Conditions and tasks have fixed codes
(``CONDITIONS``, ``TASKS``); a new one gets a new code and no code is ever reused.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from pivla.envs.rollout import episode_seed

FAMILIES = ("train", "validation", "test", "holdout")  # the code of a family is its index
CONDITIONS: dict[str, int] = {
    "in_distribution": 0,
    "static_distractors": 1,
    "dynamic_distractors": 2,
    "unseen_env": 3,
    "camera_jitter": 4,
    "distraction_level": 5,  # the Figure 8 sweep (level=N): every level shares these seeds
    "displace_object": 6,  # every displacement level shares these seeds
    "push_arm": 7,  # every push level shares these seeds
    "unseen_tasks": 8,  # the pick_place_unseen split
}
TASKS: dict[str, int] = {
    "block_away": 0, "block_left": 1, "block_right": 2,
    "ball_away": 3, "ball_left": 4, "ball_right": 5,
    "rock_away": 6, "rock_left": 7, "rock_right": 8,
    "open_drawer": 9, "close_drawer": 10, "stack_red_on_green": 11,
    "block_left_then_ball_away": 12, "rock_right_then_block_away": 13,
    # the SO-101 twin's pick_place (pivla.envs.so101)
    "red_cube_in_bowl": 14, "blue_cube_in_bowl": 15, "red_cube_on_pad": 16, "blue_cube_on_pad": 17,
}
BASE = 2**31  # every seed below this is a legacy one
FAMILY_SHIFT, CONDITION_SHIFT, TASK_SHIFT = 29, 22, 16
MAX_FAMILIES = 1 << (31 - FAMILY_SHIFT)  # 4
MAX_CONDITIONS = 1 << (FAMILY_SHIFT - CONDITION_SHIFT)  # 128
MAX_TASKS = 1 << (CONDITION_SHIFT - TASK_SHIFT)  # 64
MAX_EPISODES = 1 << TASK_SHIFT  # 65536 per (family, condition, task)
LEGACY_TEST_BASE = 1000  # the test seed every evaluation before the families used (pivla demo's --seed 0 + 1000)


@dataclass(frozen=True)
class SeedKey:
    family: str
    condition: str
    task: str
    episode: int


def _code(table: Mapping[str, int] | Sequence[str], name: str, what: str) -> int:
    codes = table if isinstance(table, Mapping) else {n: i for i, n in enumerate(table)}
    if name not in codes:
        raise ValueError(f"unknown {what} {name!r}; known: {', '.join(codes)}")
    return codes[name]


def seed_for(family: str, condition: str, task: str, episode: int) -> int:
    """The seed of episode ``episode`` (0-based) of ``task`` under ``condition`` in ``family``."""
    if not 0 <= int(episode) < MAX_EPISODES:
        raise ValueError(f"episode must be in 0..{MAX_EPISODES - 1}, got {episode}")
    f = _code(FAMILIES, family, "seed family")
    c = _code(CONDITIONS, condition, "condition")
    t = _code(TASKS, task, "task")
    return BASE + (f << FAMILY_SHIFT) + (c << CONDITION_SHIFT) + (t << TASK_SHIFT) + int(episode)


def seeds_for(family: str, condition: str, task: str, episodes: int | Iterable[int]) -> list[int]:
    """Seeds of episodes ``range(episodes)`` (or of the given episode indices)."""
    indices = range(episodes) if isinstance(episodes, int) else episodes
    return [seed_for(family, condition, task, e) for e in indices]


def decode(value: int) -> SeedKey | None:
    """The key a family seed was made from; None for a legacy seed (below ``BASE``)."""
    value = int(value)
    if value < 0 or value >= 2 * BASE:
        raise ValueError(f"{value} is not an episode seed (0 <= seed < 2**32)")
    if value < BASE:
        return None
    rest = value - BASE
    f, c, t = rest >> FAMILY_SHIFT, (rest >> CONDITION_SHIFT) % MAX_CONDITIONS, (rest >> TASK_SHIFT) % MAX_TASKS
    condition = next((k for k, v in CONDITIONS.items() if v == c), None)
    task = next((k for k, v in TASKS.items() if v == t), None)
    if condition is None or task is None:
        raise ValueError(f"seed {value} has an unassigned condition ({c}) or task ({t}) code")
    return SeedKey(FAMILIES[f], condition, task, rest % MAX_EPISODES)


def family_of(value: int) -> str:
    """``train``, ``validation``, ``test``, ``holdout`` or ``legacy``."""
    key = decode(value)
    return "legacy" if key is None else key.family


def require_family(values: Iterable[int], allowed: Iterable[str], what: str) -> None:
    """Raise unless every seed belongs to one of the ``allowed`` families (``legacy`` included if listed), e.g.
    so that calibration refuses test or holdout episodes. ``what`` names the episodes in the message."""
    allowed = set(allowed)
    bad = [(v, family_of(v)) for v in values if family_of(v) not in allowed]
    if bad:
        shown = ", ".join(f"{v} ({f})" for v, f in bad[:5])
        raise ValueError(f"{what}: {len(bad)} episode seeds outside the {sorted(allowed)} families, e.g. {shown}")


def family_seeds(family: str, conditions: Iterable[str] | None = None, tasks: Iterable[str] | None = None,
                 episodes: int = 1000) -> np.ndarray:
    """All seeds of a family over the given conditions and tasks (default: all) and episodes 0..episodes-1."""
    f = _code(FAMILIES, family, "seed family")
    c = np.array([_code(CONDITIONS, x, "condition") for x in (CONDITIONS if conditions is None else conditions)])
    t = np.array([_code(TASKS, x, "task") for x in (TASKS if tasks is None else tasks)])
    if not 0 < episodes <= MAX_EPISODES:
        raise ValueError(f"episodes must be in 1..{MAX_EPISODES}, got {episodes}")
    e = np.arange(episodes, dtype=np.int64)
    grid = (c[:, None, None].astype(np.int64) << CONDITION_SHIFT) + (t[None, :, None].astype(np.int64) << TASK_SHIFT)
    return (BASE + (f << FAMILY_SHIFT) + grid + e[None, None, :]).ravel()


def legacy_test_seed(task_index: int, episode: int, base: int = LEGACY_TEST_BASE) -> int:
    """A seed of the old test family (``runner.job_seed(1000, task_index, episode)``), used by many recipe
    decisions: for reproducing old numbers only."""
    return episode_seed(base, task_index * 100_003 + episode)


def _sorted_unique(values: Iterable[int]) -> np.ndarray:
    arr = np.sort(np.asarray(values if isinstance(values, np.ndarray) else list(values), dtype=np.int64))
    return arr[np.concatenate(([True], arr[1:] != arr[:-1]))] if len(arr) else arr


def check_disjoint(named: Mapping[str, Iterable[int]]) -> dict[str, int]:
    """Raise ValueError naming two sets of seeds that share a seed; returns each set's number of seeds.

    Pass the families to check (e.g. ``{f: family_seeds(f) for f in FAMILIES}``) and any legacy seeds in use."""
    sets = {name: _sorted_unique(values) for name, values in named.items()}
    names = list(sets)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            x, y = sets[a], sets[b]
            at = np.minimum(np.searchsorted(y, x), max(len(y) - 1, 0))
            shared = x[y[at] == x] if len(y) else x[:0]
            if len(shared):
                raise ValueError(f"seed sets {a!r} and {b!r} share {len(shared)} seeds, e.g. {shared[:3].tolist()}")
    return {name: len(arr) for name, arr in sets.items()}
