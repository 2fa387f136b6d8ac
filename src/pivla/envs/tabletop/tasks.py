"""Task suites of the twin: the paper's pick-and-place grid (Table 2), drawer, stack and long-horizon tasks.

A *task* is one goal with one instruction. Suites:

- ``pick_place``: objects block / ball / rock x directions away / left / right (nine tasks, e.g.
  ``block_left``: "move the block left"). "Left" is the robot's left (+y), "away" is away from the robot
  (+x). Success: the object was moved at least ``MIN_DISPLACEMENT`` along the direction (and more along it
  than across it), rests on the table and is out of the gripper.
- ``pick_place_seen`` / ``pick_place_unseen``: the paper's "unseen tasks" split of the same nine tasks.
  The held-out combinations form a Latin square (every object and every direction is seen in training,
  only the pairing is new): ``block_away``, ``ball_left``, ``rock_right``.
- ``drawer``: ``open_drawer`` / ``close_drawer``.
- ``stack``: ``stack_red_on_green``.
- ``long``: two pick-and-place sub-tasks in sequence (LIBERO-Long style); both goals must hold at the end.

Dense stage rewards: every sub-task has four stages (reached, grasped, lifted/moved, placed/done). The first
time a stage is reached the step's reward grows by 0.25 / number of sub-tasks; success completes all
stages, so an episode's return is 1 exactly when it succeeds.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pivla.envs import twin

MIN_DISPLACEMENT = 0.05  # m, along the instructed direction
EXPERT_DISPLACEMENT = 0.09  # m, what the expert aims for
DRAWER_OPEN_SUCCESS = 0.05  # m of travel for "open"
DRAWER_CLOSED_SUCCESS = 0.01  # m of travel left for "close"
DRAWER_TRAVEL = 0.10

DIRECTIONS = {"away": np.array([1.0, 0.0]), "left": np.array([0.0, 1.0]), "right": np.array([0.0, -1.0])}


@dataclass(frozen=True)
class ObjectDef:
    """A graspable object built from one primitive; ``grasp_z`` is the tool-centre height for a grasp."""

    name: str
    geom: str  # MJCF geom type
    size: tuple[float, ...]
    rgba: tuple[float, float, float, float]
    mass: float
    rest_z: float  # centre height when resting on the table
    grasp_z: float
    yaw_symmetry: float  # the grasp repeats every this many radians about z
    condim: int = 4


OBJECTS: dict[str, ObjectDef] = {
    "block": ObjectDef("block", "box", (0.016, 0.016, 0.016), (0.85, 0.12, 0.1, 1), 0.04, 0.016, 0.018, np.pi / 2),
    "ball": ObjectDef("ball", "sphere", (0.019,), (0.1, 0.3, 0.9, 1), 0.03, 0.019, 0.019, np.pi / 2, condim=6),
    "rock": ObjectDef("rock", "ellipsoid", (0.017, 0.022, 0.014), (0.3, 0.28, 0.27, 1), 0.05, 0.014, 0.016, np.pi / 2,
                      condim=6),
    "red_block": ObjectDef(
        "red_block", "box", (0.016, 0.016, 0.016), (0.85, 0.12, 0.1, 1), 0.04, 0.016, 0.018, np.pi / 2
    ),
    "green_block": ObjectDef(
        "green_block", "box", (0.021, 0.021, 0.021), (0.1, 0.7, 0.2, 1), 0.08, 0.021, 0.023, np.pi / 2
    ),
}

PARAPHRASES = {
    "away": ("move the {o} away", "move the {o} away from the robot", "push the {o} further away",
             "pick up the {o} and put it farther away"),
    "left": ("move the {o} left", "move the {o} to the left", "put the {o} on the left side",
             "pick up the {o} and place it to the left"),
    "right": ("move the {o} right", "move the {o} to the right", "put the {o} on the right side",
              "pick up the {o} and place it to the right"),
}


@dataclass(frozen=True)
class Goal:
    """One sub-task: pick ``obj`` and move it along ``direction``; or a drawer / stack goal."""

    kind: str  # "move", "drawer_open", "drawer_close", "stack"
    obj: str = ""
    direction: str = ""
    onto: str = ""


@dataclass(frozen=True)
class TaskDef:
    name: str
    instruction: str
    goals: tuple[Goal, ...]
    objects: tuple[str, ...]
    max_steps: int
    drawer: bool = False
    paraphrases: tuple[str, ...] = field(default=())


def _move_task(obj: str, direction: str) -> TaskDef:
    phr = tuple(p.format(o=obj) for p in PARAPHRASES[direction])
    return TaskDef(f"{obj}_{direction}", phr[0], (Goal("move", obj, direction),), (obj,), 80, paraphrases=phr)


PICK_PLACE = [_move_task(o, d) for o in ("block", "ball", "rock") for d in ("away", "left", "right")]
UNSEEN = ("block_away", "ball_left", "rock_right")

SUITES: dict[str, list[TaskDef]] = {
    "pick_place": PICK_PLACE,
    "pick_place_seen": [t for t in PICK_PLACE if t.name not in UNSEEN],
    "pick_place_unseen": [t for t in PICK_PLACE if t.name in UNSEEN],
    "drawer": [
        TaskDef("open_drawer", "open the drawer", (Goal("drawer_open"),), (), 60, drawer=True,
                paraphrases=("open the drawer", "pull the drawer open", "pull out the drawer")),
        TaskDef("close_drawer", "close the drawer", (Goal("drawer_close"),), (), 60, drawer=True,
                paraphrases=("close the drawer", "push the drawer closed", "shut the drawer")),
    ],
    "stack": [
        TaskDef("stack_red_on_green", "stack the red block on the green block",
                (Goal("stack", "red_block", onto="green_block"),), ("red_block", "green_block"), 80,
                paraphrases=("stack the red block on the green block", "put the red block on top of the green block",
                             "place the red cube onto the green cube")),
    ],
    "long": [
        TaskDef("block_left_then_ball_away", "move the block left and then move the ball away",
                (Goal("move", "block", "left"), Goal("move", "ball", "away")), ("block", "ball"), 160,
                paraphrases=("move the block left and then move the ball away",
                             "first move the block to the left, then push the ball away")),
        TaskDef("rock_right_then_block_away", "move the rock right and then move the block away",
                (Goal("move", "rock", "right"), Goal("move", "block", "away")), ("rock", "block"), 160,
                paraphrases=("move the rock right and then move the block away",
                             "first move the rock to the right, then move the block away")),
    ],
}

# Initial object regions (x range, y range) per task layout; the expert's targets stay inside the reach.
_SINGLE_REGION = {"away": ((0.13, 0.17), (-0.05, 0.05)), "left": ((0.15, 0.21), (-0.08, 0.0)),
                  "right": ((0.15, 0.21), (0.0, 0.08))}
_LONG_REGIONS = {
    "block_left_then_ball_away": {"block": ((0.13, 0.16), (-0.09, -0.07)), "ball": ((0.14, 0.17), (0.07, 0.09))},
    "rock_right_then_block_away": {"rock": ((0.13, 0.16), (0.07, 0.09)), "block": ((0.14, 0.17), (-0.09, -0.07))},
}
CABINET_FRONT_X = 0.24


def get_suite(suite: str) -> list[TaskDef]:
    return twin.get_suite(SUITES, "tabletop", suite)


def get_task(suite: str, task: int | str) -> TaskDef:
    return twin.get_task(SUITES, "tabletop", suite, task)


def _uniform(rng: np.random.Generator, lo_hi: tuple[float, float]) -> float:
    return float(rng.uniform(*lo_hi))


def sample_layout(task: TaskDef, rng: np.random.Generator) -> dict:
    """Initial state of the task's objects: ``{"objects": {name: (x, y, yaw)}, "drawer": opening, "cabinet_y"}``."""
    layout: dict = {"objects": {}}
    goal = task.goals[0]
    if task.name in _LONG_REGIONS:
        for obj, (xr, yr) in _LONG_REGIONS[task.name].items():
            layout["objects"][obj] = (_uniform(rng, xr), _uniform(rng, yr), _uniform(rng, (-np.pi, np.pi)))
    elif goal.kind == "move":
        xr, yr = _SINGLE_REGION[goal.direction]
        layout["objects"][goal.obj] = (_uniform(rng, xr), _uniform(rng, yr), _uniform(rng, (-np.pi, np.pi)))
    elif goal.kind == "stack":
        base = (_uniform(rng, (0.15, 0.2)), _uniform(rng, (-0.09, -0.04)), _uniform(rng, (-np.pi, np.pi)))
        top = (_uniform(rng, (0.15, 0.2)), _uniform(rng, (0.04, 0.09)), _uniform(rng, (-np.pi, np.pi)))
        if rng.random() < 0.5:  # either side, so the image decides where to go
            base, top = (base[0], -base[1], base[2]), (top[0], -top[1], top[2])
        layout["objects"] = {goal.onto: base, goal.obj: top}
    if task.drawer:
        layout["cabinet_y"] = _uniform(rng, (-0.05, 0.05))
        layout["drawer"] = _uniform(rng, (0.0, 0.008)) if goal.kind == "drawer_open" else _uniform(rng, (0.06, 0.08))
    return layout


def move_target(start_xy: np.ndarray, direction: str, distance: float = EXPERT_DISPLACEMENT) -> np.ndarray:
    return np.asarray(start_xy, float) + distance * DIRECTIONS[direction]


def moved_enough(start_xy: np.ndarray, xy: np.ndarray, direction: str) -> bool:
    d = np.asarray(xy, float) - np.asarray(start_xy, float)
    along = float(d @ DIRECTIONS[direction])
    across = float(abs(d @ np.array([-DIRECTIONS[direction][1], DIRECTIONS[direction][0]])))
    return along >= MIN_DISPLACEMENT and along > across
