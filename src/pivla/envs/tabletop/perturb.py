"""Seeded, composable visual perturbations (the paper's Table 3 and Figure 8).

Spec grammar (``--perturb``), comma-separated, order-free, whitespace ignored::

    spec   := "" | "none" | item ("," item)*
    item   := "unseen_env" | "static_distractors" | "dynamic_distractors" | "camera_jitter"
            | "randomized_scene" | "level=" INT

- ``unseen_env``: table colour and texture, floor and wall colours, light direction and intensity.
- ``randomized_scene``: domain randomisation for *training* data, kept apart from the tests: the table is
  plain or carries a training-only texture (tiles, crosses, blotches, stripes) that no test scene uses,
  while the test's textures (checker, gradient, speckle) never appear in training; colours, floor, wall and
  light vary over the same ranges. A share ``CLEAN_SCENE_SHARE`` of the episodes keeps the clean scene.
  Independently, 0..``CLUTTER_SLOTS`` pieces of training-only clutter (flat discs and cards, thin posts:
  ``scene.CLUTTER_SHAPES``, a family no test distractor slot uses) stand on the table, random colour, size
  and yaw, visual only like the distractors.
- ``static_distractors`` / ``dynamic_distractors``: ``level`` extra objects (random primitive, size and
  colour) on the table; dynamic ones slide and spin during the episode. Both flags together: half move.
- ``level=N`` (0..MAX_LEVEL): the distraction level, i.e. the number of distractors. Without a distractor
  flag it implies ``static_distractors``; a distractor flag without a level uses ``DEFAULT_LEVEL``.
- ``camera_jitter``: the agent-view camera moves up to 3 cm and turns up to 4 degrees per episode.

"Unseen tasks" are not a perturbation of the scene but a task split: use the suite ``pick_place_unseen``
(training on ``pick_place_seen``). Distractors are visual only (no collisions) and the perturbation draws
from its own random stream, so a perturbed episode has exactly the physics and success of the clean one.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass

import mujoco
import numpy as np

MAX_LEVEL = 6
DEFAULT_LEVEL = 3
FLAGS = ("unseen_env", "static_distractors", "dynamic_distractors", "camera_jitter", "randomized_scene")
TABLE_MATERIALS = ("table", "table_checker", "table_grain", "table_dots")  # unseen_env (test)
TRAIN_TABLE_MATERIALS = ("table", "table_tiles", "table_crosses", "table_blotches", "table_stripes")  # training
CLEAN_SCENE_SHARE = 0.5
CLUTTER_SLOTS = 3
DISTRACTOR_REGION = ((0.04, 0.34), (-0.22, 0.22))  # x, y ranges on the table
MIN_CLEARANCE = 0.06  # m from task objects, their goals and the robot base


@dataclass(frozen=True)
class PerturbConfig:
    unseen_env: bool = False
    static_distractors: bool = False
    dynamic_distractors: bool = False
    camera_jitter: bool = False
    randomized_scene: bool = False
    level: int = 0

    @property
    def n_distractors(self) -> int:
        return self.level if (self.static_distractors or self.dynamic_distractors) else 0

    @property
    def n_clutter(self) -> int:
        """Training-clutter slots in the scene (each episode uses 0..all of them)."""
        return CLUTTER_SLOTS if self.randomized_scene else 0

    @property
    def n_dynamic(self) -> int:
        if not self.dynamic_distractors:
            return 0
        return self.level // 2 if self.static_distractors else self.level

    def spec(self) -> str:
        """The canonical spec string (``parse_perturb(c.spec()) == c``)."""
        items = [f for f in FLAGS if getattr(self, f)]
        if self.n_distractors:
            items.append(f"level={self.level}")
        return ",".join(items) or "none"

    @property
    def active(self) -> bool:
        return self.unseen_env or self.camera_jitter or self.randomized_scene or self.n_distractors > 0


def parse_perturb(spec: str | None) -> PerturbConfig:
    """Parse a perturbation spec (grammar in the module docstring); raises ValueError naming the bad item."""
    if spec is None:
        return PerturbConfig()
    flags = dict.fromkeys(FLAGS, False)
    level: int | None = None
    for raw in spec.split(","):
        item = raw.strip()
        if not item or item == "none":
            continue
        if item.startswith("level="):
            value = item.split("=", 1)[1].strip()
            if not value.lstrip("-").isdigit():
                raise ValueError(f"perturbation {item!r}: level must be an integer 0..{MAX_LEVEL}")
            level = int(value)
            if not 0 <= level <= MAX_LEVEL:
                raise ValueError(f"perturbation {item!r}: level must be in 0..{MAX_LEVEL}")
        elif item in flags:
            flags[item] = True
        elif item in ("unseen_tasks", "unseen_task"):
            raise ValueError("unseen tasks are a task split, not a scene perturbation: use --suite pick_place_unseen")
        else:
            raise ValueError(f"unknown perturbation {item!r}; known: {', '.join(FLAGS)}, level=N")
    distract = flags["static_distractors"] or flags["dynamic_distractors"]
    if level is None:
        level = DEFAULT_LEVEL if distract else 0
    elif level > 0 and not distract:
        flags["static_distractors"] = True
    return PerturbConfig(**flags, level=level)


def _random_colour(rng: np.random.Generator, avoid: list[np.ndarray]) -> np.ndarray:
    """A saturated random colour at least a little different from every colour in ``avoid``."""
    for _ in range(50):
        rgb = np.array(colorsys.hsv_to_rgb(rng.uniform(), rng.uniform(0.3, 1.0), rng.uniform(0.35, 1.0)))
        if all(np.linalg.norm(rgb - a[:3]) > 0.3 for a in avoid):
            return rgb
    return rgb


def _rest_height(geom_type: int, size: np.ndarray) -> float:
    """Centre height of an upright primitive resting on the table."""
    if geom_type == mujoco.mjtGeom.mjGEOM_SPHERE:
        return float(size[0])
    if geom_type == mujoco.mjtGeom.mjGEOM_CYLINDER:
        return float(size[1])
    if geom_type == mujoco.mjtGeom.mjGEOM_CAPSULE:
        return float(size[0] + size[1])
    return float(size[2])


class Perturber:
    """Applies a :class:`PerturbConfig` to one scene model; remembers the clean values to restore them."""

    def __init__(self, model: mujoco.MjModel, config: PerturbConfig, protected_rgba: list[np.ndarray]):
        self.model = model
        self.config = config
        self.protected = protected_rgba
        self.cam = model.camera("agentview").id
        self.table_geom = model.geom("table").id
        self.test_materials = [model.material(m).id for m in TABLE_MATERIALS]
        self.train_materials = [model.material(m).id for m in TRAIN_TABLE_MATERIALS]
        self.clean = {
            "cam_pos": model.cam_pos[self.cam].copy(),
            "cam_quat": model.cam_quat[self.cam].copy(),
            "mat_rgba": model.mat_rgba.copy(),
            "light_dir": model.light_dir.copy(),
            "light_diffuse": model.light_diffuse.copy(),
            "table_mat": int(model.geom_matid[self.table_geom]),
        }
        self.mocap = [int(model.body_mocapid[model.body(f"distractor{i}").id]) for i in range(config.n_distractors)]
        self.dgeoms = [model.geom(f"distractor{i}").id for i in range(config.n_distractors)]
        self.dsize = model.geom_size[self.dgeoms].copy()
        self.clutter_mocap = [int(model.body_mocapid[model.body(f"clutter{i}").id]) for i in range(config.n_clutter)]
        self.cgeoms = [model.geom(f"clutter{i}").id for i in range(config.n_clutter)]
        self.csize = model.geom_size[self.cgeoms].copy()
        self.velocity = np.zeros((config.n_distractors, 2))
        self.spin = np.zeros(config.n_distractors)

    def reset(self, data: mujoco.MjData, rng: np.random.Generator, keep_out: list[np.ndarray]) -> None:
        """Draw this episode's perturbation. ``keep_out``: xy points distractors must not cover."""
        m, c = self.model, self.clean
        m.cam_pos[self.cam], m.cam_quat[self.cam] = c["cam_pos"], c["cam_quat"]
        m.mat_rgba[:] = c["mat_rgba"]
        m.light_dir[:], m.light_diffuse[:] = c["light_dir"], c["light_diffuse"]
        m.geom_matid[self.table_geom] = c["table_mat"]
        if self.config.unseen_env:
            self._restyle_scene(rng, self.test_materials)
        elif self.config.randomized_scene and rng.uniform() >= CLEAN_SCENE_SHARE:
            self._restyle_scene(rng, self.train_materials)
        if self.config.camera_jitter:
            self._jitter_camera(rng)
        points = [np.zeros(2), *keep_out]
        self._place_distractors(data, rng, points)
        if self.clutter_mocap:
            n = int(rng.integers(len(self.clutter_mocap) + 1))
            for mocap in self.clutter_mocap[n:]:
                data.mocap_pos[mocap] = [0.0, 0.0, -1.0]
            self._place(data, rng, points, self.clutter_mocap[:n], self.cgeoms[:n], self.csize[:n])

    def _restyle_scene(self, rng: np.random.Generator, materials: list[int]) -> None:
        """A new table (one of ``materials``, random colour), floor, wall and key light."""
        m = self.model
        mat = materials[int(rng.integers(len(materials)))]
        m.geom_matid[self.table_geom] = mat
        m.mat_rgba[mat, :3] = _random_colour(rng, self.protected)
        m.mat_rgba[m.material("floor").id, :3] = rng.uniform(0.05, 0.9, 3)
        m.mat_rgba[m.material("wall").id, :3] = rng.uniform(0.05, 0.95, 3)
        tilt = rng.uniform(-0.6, 0.6, 2)
        direction = np.array([tilt[0], tilt[1], -1.0])
        m.light_dir[0] = direction / np.linalg.norm(direction)
        m.light_diffuse[0] = rng.uniform(0.25, 0.85) * rng.uniform(0.8, 1.0, 3)

    def _jitter_camera(self, rng: np.random.Generator) -> None:
        m = self.model
        m.cam_pos[self.cam] = self.clean["cam_pos"] + rng.uniform(-0.03, 0.03, 3)
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        turn = np.empty(4)
        mujoco.mju_axisAngle2Quat(turn, axis, np.deg2rad(rng.uniform(0.0, 4.0)))
        quat = np.empty(4)
        mujoco.mju_mulQuat(quat, self.clean["cam_quat"], turn)
        m.cam_quat[self.cam] = quat

    def _place(self, data: mujoco.MjData, rng: np.random.Generator, points: list[np.ndarray], mocaps: list[int],
               geoms: list[int], sizes: np.ndarray) -> None:
        """Stand each geom upright at a random free spot (``MIN_CLEARANCE`` from ``points``, which grows),
        scaled down by up to 40%, in a random colour and yaw."""
        (x0, x1), (y0, y1) = DISTRACTOR_REGION
        for mocap, geom, size in zip(mocaps, geoms, sizes):
            for _ in range(200):
                xy = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)])
                if all(np.linalg.norm(xy - p) >= MIN_CLEARANCE for p in points):
                    break
            points.append(xy)
            self.model.geom_size[geom] = size * rng.uniform(0.6, 1.0)
            self.model.geom_rgba[geom, :3] = _random_colour(rng, self.protected)
            height = _rest_height(int(self.model.geom_type[geom]), self.model.geom_size[geom])
            data.mocap_pos[mocap] = [xy[0], xy[1], height]
            yaw = rng.uniform(-np.pi, np.pi)
            data.mocap_quat[mocap] = [np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)]

    def _place_distractors(self, data: mujoco.MjData, rng: np.random.Generator, points: list[np.ndarray]) -> None:
        n_static = len(self.mocap) - self.config.n_dynamic
        for i in range(len(self.mocap)):
            self._place(data, rng, points, self.mocap[i : i + 1], self.dgeoms[i : i + 1], self.dsize[i : i + 1])
            if i >= n_static:
                angle = rng.uniform(-np.pi, np.pi)
                self.velocity[i] = rng.uniform(0.03, 0.07) * np.array([np.cos(angle), np.sin(angle)])
                self.spin[i] = rng.uniform(-1.5, 1.5)
            else:
                self.velocity[i], self.spin[i] = 0.0, 0.0

    def step(self, data: mujoco.MjData, dt: float) -> None:
        """Advance the moving distractors by ``dt`` seconds (bouncing off the region's edges)."""
        (x0, x1), (y0, y1) = DISTRACTOR_REGION
        for i, mocap in enumerate(self.mocap):
            if not self.spin[i] and not self.velocity[i].any():
                continue
            pos = data.mocap_pos[mocap]
            pos[:2] += self.velocity[i] * dt
            for axis, (lo, hi) in enumerate(((x0, x1), (y0, y1))):
                if not lo <= pos[axis] <= hi:
                    pos[axis] = np.clip(pos[axis], lo, hi)
                    self.velocity[i, axis] *= -1
            quat = data.mocap_quat[mocap].copy()
            mujoco.mju_quatIntegrate(quat, np.array([0.0, 0.0, self.spin[i]]), dt)
            data.mocap_quat[mocap] = quat
