"""Task suites of the SO-101 twin.

``pick_place`` (four tasks): a red and a blue cube (25 mm, LeRobot's usual pick-and-place cube) lie on the table
with one target, a bowl or a green pad, all at seeded spots in the arm's reach; the instruction names the cube
to move, so the policy has to read it (the other cube is a distractor it must leave alone):

- ``red_cube_in_bowl`` / ``blue_cube_in_bowl``: "put the red cube in the bowl";
- ``red_cube_on_pad`` / ``blue_cube_on_pad``: "put the red cube on the green pad".

Success: the named cube rests (speed < 5 cm/s) inside the bowl (centre within its inner radius, below its
rim) or on the pad (centre over the pad, on the table), and neither jaw touches it. Stages (reached, grasped,
lifted, placed) give the dense reward as on the tabletop twin: 0.25 the first time each is reached, so an
episode's return is 1 exactly when it succeeds.

Layouts are drawn in polar coordinates around the arm's base (x forward, y to the arm's left): radius
``REACH`` and bearing ``BEARING``, where the top-down grasps and the carry height are reachable (the SO-101's
wrist runs out of travel beyond ~0.28 m and above ~0.08 m with the jaws pointing down).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pivla.envs import twin

CUBE_HALF = 0.0125  # m
CUBE_MASS = 0.03  # kg
BOWL_INNER, BOWL_WALL, BOWL_HEIGHT, BOWL_FLOOR = 0.052, 0.004, 0.028, 0.004  # m: inner radius, wall, rim, floor
PAD_HALF = 0.04  # m
REACH = (0.15, 0.26)  # m from the base axis, for every object's centre
BEARING = (-0.75, 0.75)  # rad from straight ahead (+x)
MIN_GAP = {"cube": 0.07, "bowl": 0.11, "pad": 0.09}  # m between a cube's centre and any other object's centre
REST_SPEED = 0.05  # m/s

CUBES = {"red_cube": (0.85, 0.12, 0.1, 1.0), "blue_cube": (0.12, 0.3, 0.9, 1.0)}
TARGET_RGBA = {"bowl": (0.92, 0.92, 0.88, 1.0), "pad": (0.15, 0.7, 0.25, 1.0)}

PARAPHRASES = {
    "bowl": ("put the {c} cube in the bowl", "place the {c} cube into the bowl", "pick up the {c} cube and drop it in "
             "the bowl", "move the {c} cube to the bowl"),
    "pad": ("put the {c} cube on the green pad", "place the {c} cube onto the green square",
            "pick up the {c} cube and set it on the green pad", "move the {c} cube to the green pad"),
}


@dataclass(frozen=True)
class TaskDef:
    name: str
    instruction: str
    cube: str  # the cube to move
    target: str  # "bowl" or "pad"
    max_steps: int = 120
    objects: tuple[str, ...] = tuple(CUBES)
    paraphrases: tuple[str, ...] = field(default=())

    @property
    def distractor(self) -> str:
        return next(c for c in self.objects if c != self.cube)


def _task(cube: str, target: str) -> TaskDef:
    colour = cube.split("_")[0]
    phr = tuple(p.format(c=colour) for p in PARAPHRASES[target])
    return TaskDef(f"{cube}_{'in' if target == 'bowl' else 'on'}_{target}", phr[0], cube, target, paraphrases=phr)


SUITES: dict[str, list[TaskDef]] = {
    "pick_place": [_task(c, t) for t in ("bowl", "pad") for c in CUBES],
}


def get_suite(suite: str) -> list[TaskDef]:
    return twin.get_suite(SUITES, "so101", suite)


def get_task(suite: str, task: int | str) -> TaskDef:
    return twin.get_task(SUITES, "so101", suite, task)


def _polar(rng: np.random.Generator) -> np.ndarray:
    r, b = rng.uniform(*REACH), rng.uniform(*BEARING)
    return np.array([r * np.cos(b), r * np.sin(b)])


def sample_layout(task: TaskDef, rng: np.random.Generator) -> dict:
    """``{"objects": {cube: (x, y, yaw)}, "target": (x, y)}``: the target first, then each cube clear of it and
    of the other cube (rejection sampling from the task's own stream)."""
    gap = MIN_GAP[task.target]
    target = _polar(rng)
    placed: list[np.ndarray] = []
    objects = {}
    for cube in task.objects:
        for _ in range(1000):
            xy = _polar(rng)
            if np.linalg.norm(xy - target) >= gap and all(np.linalg.norm(xy - p) >= MIN_GAP["cube"] for p in placed):
                break
        else:  # pragma: no cover - the regions are far larger than the gaps
            raise RuntimeError("no layout found")
        placed.append(xy)
        objects[cube] = (float(xy[0]), float(xy[1]), float(rng.uniform(-np.pi, np.pi)))
    return {"objects": objects, "target": (float(target[0]), float(target[1]))}


def place_height(target: str) -> float:
    """Height of a cube's centre resting at the target."""
    return CUBE_HALF + (BOWL_FLOOR if target == "bowl" else 0.0)


def placed(target: str, target_xy: np.ndarray, cube_pos: np.ndarray) -> bool:
    """Whether a cube centred at ``cube_pos`` lies in the bowl / on the pad at ``target_xy``."""
    d = np.asarray(cube_pos[:2], float) - np.asarray(target_xy, float)
    if target == "bowl":
        return bool(np.linalg.norm(d) < BOWL_INNER - CUBE_HALF * 0.5 and cube_pos[2] < BOWL_HEIGHT)
    return bool(np.all(np.abs(d) < PAD_HALF) and cube_pos[2] < CUBE_HALF + 0.006)
