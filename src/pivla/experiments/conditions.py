"""The registry of evaluation conditions: every cell a study evaluates on, twin and LIBERO, by name.

A cell's name is also the directory its evaluations are stored under, so names never change. Its
``condition`` is the code its episodes' seeds are drawn with (``pivla.envs.seeds.CONDITIONS``, the same as
``EvalConfig.condition``): cells that share a code meet the same episodes, so their results pair (a
displacement level against level 0, one actuation against the other).
"""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Cell:
    """One evaluation condition: its name, its code in the seed families, the twin's perturbation spec, the
    suite, the actuation (None: the study's) and, on LIBERO, where the episodes start (the official init
    states, or scenes sampled from the tasks' placement regions)."""

    name: str
    condition: str | None
    perturb: str | None = None
    suite: str = "pick_place"
    realism: str | None = None
    env: str = "tabletop"
    libero_init: str = "official"

    def eval_fields(self, realism: str) -> dict[str, Any]:
        """The ``EvalConfig`` fields this cell sets (``realism``: the study's actuation, unless the cell has its
        own)."""
        fields: dict[str, Any] = {"env": self.env, "suite": self.suite, "perturb": self.perturb,
                                  "realism": self.realism or realism}
        if self.env == "libero":
            fields["libero_init"] = self.libero_init
        return fields

    def record(self) -> dict[str, Any]:
        """The cell as the twin's test_plan.json lists it."""
        return {"name": self.name, "condition": self.condition, "perturb": self.perturb, "suite": self.suite,
                "realism": self.realism}

    def with_realism(self, realism: str) -> Cell:
        """The same episodes with another actuation, named ``<name>_<realism>``."""
        return dataclasses.replace(self, name=f"{self.name}_{realism}", realism=realism)


# -- the twin -----------------------------------------------------------------------------------------------
IN_DISTRIBUTION = Cell("in_distribution", "in_distribution")
SCENE_CELLS: dict[str, Cell] = {c.name: c for c in (
    IN_DISTRIBUTION,
    Cell("static_distractors", "static_distractors", "static_distractors"),
    Cell("dynamic_distractors", "dynamic_distractors", "dynamic_distractors"),
    Cell("unseen_env", "unseen_env", "unseen_env"),
    Cell("camera_jitter", "camera_jitter", "camera_jitter"),
    # a policy trained on pick_place_seen, tested on the held-out combinations
    Cell("unseen_tasks", "unseen_tasks", suite="pick_place_unseen"),
)}
EVENTS = ("displace_object", "push_arm")  # mid-episode disturbances, by level in cm (Fig. 8)


def event(name: str, level: int, suite: str = "pick_place") -> Cell:
    """The object displaced (``displace_object``) or the arm pushed (``push_arm``) by ``level`` cm while the
    second chunk executes; level 0 plays the same episodes with nothing moved. Off pick_place the name starts
    with the suite (``long_displace_object_6``)."""
    if name not in EVENTS:
        raise ValueError(f"unknown event {name!r}; known: {', '.join(EVENTS)}")
    prefix = "" if suite == "pick_place" else f"{suite}_"
    return Cell(f"{prefix}{name}_{level}", name, f"{name}={level}", suite=suite)


def distraction_level(level: int) -> Cell:
    """``level`` static distractors (the demo's Fig. 8 sweep; level 0 is the in-distribution evaluation)."""
    return Cell(f"distraction_level_{level}", "distraction_level", f"level={level}" if level else None)


def suite_cell(suite: str) -> Cell:
    """A suite in distribution, named by the suite."""
    return Cell(suite, "in_distribution", suite=suite)


def recording(name: str, base: Cell) -> Cell:
    """A cell in the training scenes (randomised, cluttered), for rollouts to train on."""
    perturb = "randomized_scene" + (f",{base.perturb}" if base.perturb else "")
    return Cell(name, base.condition, perturb, suite=base.suite)


_PATTERNS = ((re.compile(rf"({'|'.join(EVENTS)})_(\d+)"), lambda m: event(m.group(1), int(m.group(2)))),
             (re.compile(r"distraction_level_(\d+)"), lambda m: distraction_level(int(m.group(1)))))


def twin(name: str) -> Cell:
    """A twin cell by name: a scene cell (``SCENE_CELLS``), ``displace_object_N``, ``push_arm_N`` or
    ``distraction_level_N``."""
    if name in SCENE_CELLS:
        return SCENE_CELLS[name]
    for pattern, make in _PATTERNS:
        m = pattern.fullmatch(name)
        if m:
            return make(m)
    raise ValueError(f"unknown twin condition {name!r}")


# -- LIBERO -------------------------------------------------------------------------------------------------
def libero(suite: str, init: str = "official") -> Cell:
    """A LIBERO suite from its official init states (the benchmark's protocol), or from scenes sampled with
    each episode's seed (``init="random"``: validation rollouts, which must not reuse the official states).
    LIBERO's episodes take the legacy seeds, so the cell has no seed-family code."""
    name = {"official": "official_init_states", "random": "sampled_scenes"}[init]
    return Cell(name, None, suite=suite, env="libero", libero_init=init)
