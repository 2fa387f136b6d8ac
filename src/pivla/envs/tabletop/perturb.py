"""Seeded, composable perturbations (the paper's Table 3 and Figure 8, and mid-episode disturbances).

Spec grammar (``--perturb``), comma-separated, order-free, whitespace ignored::

    spec   := "" | "none" | item ("," item)*
    item   := "unseen_env" | "static_distractors" | "dynamic_distractors" | "camera_jitter"
            | "randomized_scene" | "level=" INT
            | "displace_object=" CM ["@" timing] | "push_arm=" CM ["@" timing]
            | "recovery=" SHARE | "scatter=" SHARE
    timing := "near" | INT "-" INT

- ``unseen_env``: a table texture, table colour, floor and wall colours, light direction and light colour
  that no training scene has. The scene-style space is partitioned component by component (the
  ``TRAIN_*`` and ``UNSEEN_*`` constants): the test's textures (checker, gradient, speckle) are never
  trained on and the plain table never tested; test tables are paler-and-greyer or darker than any training
  table; test floors and walls are saturated colours outside the training colour box; the test light is
  more slanted and tinted. :func:`training_style` says, per component, whether a rendered scene lies in the
  training space.
- ``randomized_scene``: domain randomisation for *training* data: a share ``CLEAN_SCENE_SHARE`` of the
  episodes keep the clean scene, the others get a plain table or a training-only texture (tiles, crosses,
  blotches, stripes) and colours and light from the ``TRAIN_*`` ranges. Independently, 0..``CLUTTER_SLOTS``
  pieces of training-only clutter (flat discs and cards, thin posts: ``scene.CLUTTER_SHAPES``, a family no
  test distractor slot uses) stand on the table, random colour, size and yaw, visual only like the
  distractors.
- ``static_distractors`` / ``dynamic_distractors``: ``level`` extra objects (random primitive, size and
  colour) on the table; dynamic ones slide and spin during the episode. Both flags together: half move.
- ``level=N`` (0..MAX_LEVEL): the distraction level, i.e. the number of distractors. Without a distractor
  flag it implies ``static_distractors``; a distractor flag without a level uses ``DEFAULT_LEVEL``.
- ``camera_jitter``: the agent-view camera moves up to 3 cm and turns up to 4 degrees per episode.
- ``displace_object=CM``: once per episode the first sub-task's object jumps CM centimetres in a seeded
  horizontal direction with no component along the instructed direction (the jump never does part of the
  task), to a reachable spot clear of the other task objects and of the fingers, and lands at rest
  (:class:`DisplaceObject`). ``Perturber.events`` records the step and the shift, so that success can be
  measured from where the object landed. Levels: ``EVENT_LEVELS_CM``.
- ``push_arm=CM``: once per episode the arm is shoved so that its tool centre moves CM centimetres
  horizontally, and it stays shoved: the offset is added to every later joint command, as if a servo horn
  had slipped on its spline, so the policy has to see it and correct (:class:`PushArm`). A push that the
  servos undid within the control period would leave nothing for a policy to react to.
- ``@timing`` of an event: ``@A-B`` (default ``@5-7``) draws the step uniformly from A..B (0-based
  ``env.step`` calls: step 5 is the sixth action, the first of the second chunk under a fixed horizon of 5),
  the same for every executor; ``@near`` fires at the first step at which the tool centre comes within
  ``NEAR_DISTANCE`` of the object (the drawer handle for drawer tasks), as the gripper closes in. A
  displacement waits (to the next step) while the object is held, touched or moving, or no spot is fit to
  land on; a push waits while no direction is reachable. Either fires at most once an episode.

- ``recovery=P`` (training data): in a share P of the episodes, once, the object is displaced or the arm
  pushed, one or the other evenly (only the push where the task has no object), by a distance drawn from
  ``RECOVERY_CM`` at a step drawn from ``RECOVERY_WINDOW``: the mid-episode events the tests apply, with the
  expert's recovery from them recorded (DART for disturbances rather than for noise). It draws from a stream of
  its own; an explicit event of the same kind takes its place.

- ``scatter=P`` (training data): in a share P of the episodes the first sub-task's object starts up to
  ``RECOVERY_CM[1]`` from its drawn spot, in any direction, where a displacement may land it (reachable, its
  goal reachable, clear of the other task objects): the positions ``displace_object`` puts objects in, many
  of them outside every task's region. Its own stream too; nothing changes for a task without an object.

"Unseen tasks" are not a perturbation of the scene but a task split: use the suite ``pick_place_unseen``
(training on ``pick_place_seen``). The visual perturbations (all but the two events) have no collisions
and draw from a random stream of their own, so a visually perturbed episode has exactly the physics and
success of the clean one; each event draws from a further stream, so adding one changes no other draw.

Why one ~700-line module: the spec grammar and the perturbations it names are one contract (a spec's text,
its draws and its stream of random numbers must change together, or recorded episodes stop replaying).
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass, field

import mujoco
import numpy as np

from pivla import arm
from pivla.envs.tabletop import tasks
from pivla.envs.tabletop.scene import task_name

MAX_LEVEL = 6
DEFAULT_LEVEL = 3
FLAGS = ("unseen_env", "static_distractors", "dynamic_distractors", "camera_jitter", "randomized_scene")
EVENTS = ("displace_object", "push_arm")
SHARES = ("recovery", "scatter")  # training-data items: the share of episodes they change
CLEAN_SCENE_SHARE = 0.5
CLUTTER_SLOTS = 3
DISTRACTOR_REGION = ((0.04, 0.34), (-0.22, 0.22))  # x, y ranges on the table
MIN_CLEARANCE = 0.06  # m from task objects, their goals and the robot base

# The scene-style space, partitioned between training (randomized_scene, and the clean scene inside it) and
# the unseen_env test. Colours are HSV (hue, saturation, value) or RGB in [0, 1]; the light's tilt is its
# direction's horizontal components over its downward one.
TRAIN_TABLE_MATERIALS = ("table", "table_tiles", "table_crosses", "table_blotches", "table_stripes")
TABLE_MATERIALS = ("table_checker", "table_grain", "table_dots")  # unseen_env only: checker, gradient, speckle
TRAIN_SATURATION, TRAIN_VALUE = (0.3, 1.0), (0.35, 1.0)  # training table colours (and every distractor's)
UNSEEN_PALE = ((0.0, 0.22), (0.45, 1.0))  # unseen tables, half of them: less saturated than any training one
UNSEEN_DARK = ((0.0, 1.0), (0.12, 0.28))  # ... the other half: darker than any training one
TRAIN_FLOOR_RGB, TRAIN_WALL_RGB = (0.05, 0.9), (0.05, 0.95)  # per channel
UNSEEN_BACKDROP_SATURATION, UNSEEN_BACKDROP_VALUE = (0.97, 1.0), (0.35, 1.0)  # smallest channel <= 0.03
TRAIN_LIGHT_TILT = 0.6  # |tilt| per axis at most
UNSEEN_LIGHT_TILT = (0.7, 1.0)  # |tilt| of one axis, the other anywhere in +-1
TRAIN_LIGHT_LEVEL, TRAIN_LIGHT_TINT = (0.25, 0.85), (0.8, 1.0)  # diffuse = level * per-channel tint
UNSEEN_LIGHT_LEVEL, UNSEEN_LIGHT_TINT = (0.3, 0.9), (0.4, 0.65)  # the weakest channel over the strongest
_EPS = 1e-9

# Mid-episode events
EVENT_LEVELS_CM = (0, 2, 4, 6)  # the graded levels of displace_object and push_arm
MAX_EVENT_CM = 10.0
DEFAULT_WINDOW = (5, 7)
RECOVERY_CM = (2.0, 8.0)  # distance range of a recovery event (training data), around the tested levels
RECOVERY_WINDOW = (3, 25)  # its step range: the tests' window (5-7) and the rest of the approach
NEAR_DISTANCE = 0.06  # m between the tool centre and the object's centre for "@near"
FINGER_CLEARANCE = 0.005  # m kept between a displaced object and the fingers
FINGER_HALF_WIDTH = 0.011  # m: a finger pad's largest horizontal half-size (pivla/arm/arm.xml)
OBJECT_REACH = (0.12, 0.25)  # m from the base: where a displaced object may land (top-down grasps reach 0.12-0.27)
GOAL_REACH = 0.27  # m from the base: the displaced object's goal must stay reachable
OBJECT_SPACING = 0.05  # m between a displaced object and any other task object
PUSH_TOLERANCE, PUSH_ROT_TOLERANCE = 0.002, 0.02  # m, rad: a push direction needs IK to reach its pose this well


@dataclass(frozen=True)
class EventTiming:
    """When a once-per-episode event fires."""

    trigger: str = "step"  # "step": at a seeded step of `window`; "near": as the tool centre closes in on the object
    window: tuple[int, int] = DEFAULT_WINDOW  # inclusive range of 0-based control steps for trigger="step"

    def __post_init__(self) -> None:
        if self.trigger not in ("step", "near"):
            raise ValueError(f"event trigger must be 'step' or 'near', got {self.trigger!r}")
        object.__setattr__(self, "window", tuple(int(s) for s in self.window))
        if len(self.window) != 2 or not 0 <= self.window[0] <= self.window[1]:
            raise ValueError(f"event window must be two steps 0 <= A <= B, got {self.window}")
        if self.trigger == "near" and self.window != DEFAULT_WINDOW:
            raise ValueError("an event window applies to trigger='step' only")

    def spec(self) -> str:
        if self.trigger == "near":
            return "@near"
        return "" if self.window == DEFAULT_WINDOW else f"@{self.window[0]}-{self.window[1]}"


@dataclass(frozen=True)
class DisplaceObject:
    """The first sub-task's object jumps ``distance`` m once per episode, never along the instructed direction."""

    distance: float  # m; EVENT_LEVELS_CM gives the graded levels
    timing: EventTiming = field(default_factory=EventTiming)

    def __post_init__(self) -> None:
        _check_distance("displace_object", self.distance)


@dataclass(frozen=True)
class PushArm:
    """The arm is shoved once per episode so that its tool centre moves ``distance`` m horizontally, and the
    offset persists in every later joint command."""

    distance: float  # m; EVENT_LEVELS_CM gives the graded levels
    timing: EventTiming = field(default_factory=EventTiming)

    def __post_init__(self) -> None:
        _check_distance("push_arm", self.distance)


def _check_distance(name: str, distance: float) -> None:
    if not (np.isfinite(distance) and 0.0 <= distance <= MAX_EVENT_CM / 100):
        raise ValueError(f"{name}: distance must be 0..{MAX_EVENT_CM / 100:g} m, got {distance}")


@dataclass(frozen=True)
class PerturbConfig:
    unseen_env: bool = False
    static_distractors: bool = False
    dynamic_distractors: bool = False
    camera_jitter: bool = False
    randomized_scene: bool = False
    level: int = 0
    displace_object: DisplaceObject | None = None
    push_arm: PushArm | None = None
    recovery: float = 0.0
    scatter: float = 0.0

    def __post_init__(self) -> None:
        for name in SHARES:
            share = getattr(self, name)
            if not (np.isfinite(share) and 0.0 <= share <= 1.0):
                raise ValueError(f"{name}: the share of episodes must be in 0..1, got {share}")

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
        for name in EVENTS:
            event = getattr(self, name)
            if event is not None:
                items.append(f"{name}={event.distance * 100:g}{event.timing.spec()}")
        items += [f"{name}={getattr(self, name):g}" for name in SHARES if getattr(self, name)]
        return ",".join(items) or "none"

    @property
    def active(self) -> bool:
        events = any(e is not None and e.distance > 0 for e in (self.displace_object, self.push_arm))
        events = events or self.recovery > 0 or self.scatter > 0
        return self.unseen_env or self.camera_jitter or self.randomized_scene or self.n_distractors > 0 or events


def _parse_event(item: str) -> tuple[str, DisplaceObject | PushArm]:
    name, value = (s.strip() for s in item.split("=", 1))
    amount, _, timing_text = value.partition("@")
    try:
        cm = float(amount)
    except ValueError:
        raise ValueError(f"perturbation {item!r}: the distance must be a number of cm (0..{MAX_EVENT_CM:g})") from None
    if not 0.0 <= cm <= MAX_EVENT_CM:
        raise ValueError(f"perturbation {item!r}: the distance must be in 0..{MAX_EVENT_CM:g} cm")
    timing_text = timing_text.strip()
    if not timing_text:
        timing = EventTiming()
    elif timing_text == "near":
        timing = EventTiming("near")
    else:
        a, sep, b = timing_text.partition("-")
        if not (sep and a.strip().isdigit() and b.strip().isdigit()):
            raise ValueError(f"perturbation {item!r}: timing must be '@near' or '@A-B' (control steps)")
        timing = EventTiming("step", (int(a), int(b)))
    cls = DisplaceObject if name == "displace_object" else PushArm
    return name, cls(cm / 100, timing)


def parse_perturb(spec: str | None) -> PerturbConfig:
    """Parse a perturbation spec (grammar in the module docstring); raises ValueError naming the bad item."""
    if spec is None:
        return PerturbConfig()
    flags = dict.fromkeys(FLAGS, False)
    events: dict[str, DisplaceObject | PushArm] = {}
    level: int | None = None
    shares: dict[str, float] = {}
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
        elif item.split("=", 1)[0].strip() in SHARES and "=" in item:
            name, value = (v.strip() for v in item.split("=", 1))
            if name in shares:
                raise ValueError(f"perturbation {item!r}: {name} given twice")
            try:
                shares[name] = float(value)
            except ValueError:
                shares[name] = float("nan")
            if not 0.0 < shares[name] <= 1.0:  # NaN fails too
                raise ValueError(f"perturbation {item!r}: {name} must be a share of episodes in (0, 1]")
        elif item.split("=", 1)[0].strip() in EVENTS and "=" in item:
            name, event = _parse_event(item)
            if name in events:
                raise ValueError(f"perturbation {item!r}: {name} given twice")
            events[name] = event
        elif item in flags:
            flags[item] = True
        elif item in ("unseen_tasks", "unseen_task"):
            raise ValueError("unseen tasks are a task split, not a scene perturbation: use --suite pick_place_unseen")
        else:
            raise ValueError(f"unknown perturbation {item!r}; known: {', '.join(FLAGS)}, level=N, "
                             "displace_object=CM[@timing], push_arm=CM[@timing], recovery=SHARE, scatter=SHARE")
    distract = flags["static_distractors"] or flags["dynamic_distractors"]
    if level is None:
        level = DEFAULT_LEVEL if distract else 0
    elif level > 0 and not distract:
        flags["static_distractors"] = True
    return PerturbConfig(**flags, level=level, **events, **shares)


def _random_colour(rng: np.random.Generator, avoid: list[np.ndarray]) -> np.ndarray:
    """A saturated random colour at least a little different from every colour in ``avoid``."""
    for _ in range(50):
        rgb = np.array(colorsys.hsv_to_rgb(rng.uniform(), rng.uniform(*TRAIN_SATURATION), rng.uniform(*TRAIN_VALUE)))
        if all(np.linalg.norm(rgb - a[:3]) > 0.3 for a in avoid):
            return rgb
    return rgb


def _unseen_table_colour(rng: np.random.Generator, avoid: list[np.ndarray]) -> np.ndarray:
    """A table colour outside the training range (pale and greyish, or dark), unlike every colour in ``avoid``."""
    for _ in range(50):
        sat, val = UNSEEN_PALE if rng.uniform() < 0.5 else UNSEEN_DARK
        rgb = np.array(colorsys.hsv_to_rgb(rng.uniform(), rng.uniform(*sat), rng.uniform(*val)))
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


# -- the scene-style space --------------------------------------------------------------------------------
@dataclass(frozen=True)
class SceneStyle:
    """What a scene looks like, as rendered: the table's material and colour, floor, wall and key light."""

    table_material: str
    table_rgb: tuple[float, float, float]
    floor_rgb: tuple[float, float, float]
    wall_rgb: tuple[float, float, float]
    light_dir: tuple[float, float, float]
    light_diffuse: tuple[float, float, float]


def scene_style(model: mujoco.MjModel) -> SceneStyle:
    """The style a scene model renders now."""
    mat = int(model.geom_matid[model.geom("table").id])

    def rgb(material: int) -> tuple[float, float, float]:
        return tuple(float(v) for v in model.mat_rgba[material, :3])

    return SceneStyle(model.material(mat).name, rgb(mat), rgb(model.material("floor").id),
                      rgb(model.material("wall").id), tuple(float(v) for v in model.light_dir[0]),
                      tuple(float(v) for v in model.light_diffuse[0]))


def _within(value: float, lo_hi: tuple[float, float]) -> bool:
    return lo_hi[0] - _EPS <= value <= lo_hi[1] + _EPS


def training_style(style: SceneStyle) -> dict[str, bool]:
    """Per component, whether ``style`` lies in the space training scenes are drawn from (randomized_scene,
    the clean scene included). An unseen_env scene is outside it in every component."""
    _, sat, val = colorsys.rgb_to_hsv(*style.table_rgb)
    direction = np.asarray(style.light_dir)
    tilt = direction[:2] / -direction[2] if direction[2] < 0 else np.full(2, np.inf)
    diffuse = np.asarray(style.light_diffuse)
    tint = diffuse.min() / diffuse.max() if diffuse.max() > 0 else 0.0
    lo, hi = TRAIN_LIGHT_LEVEL[0] * TRAIN_LIGHT_TINT[0], TRAIN_LIGHT_LEVEL[1] * TRAIN_LIGHT_TINT[1]
    return {
        "table_texture": style.table_material in TRAIN_TABLE_MATERIALS,
        "table_colour": _within(sat, TRAIN_SATURATION) and _within(val, TRAIN_VALUE),
        "floor_colour": all(_within(c, TRAIN_FLOOR_RGB) for c in style.floor_rgb),
        "wall_colour": all(_within(c, TRAIN_WALL_RGB) for c in style.wall_rgb),
        "light_direction": bool(np.all(np.abs(tilt) <= TRAIN_LIGHT_TILT + _EPS)),
        "light_colour": _within(tint, TRAIN_LIGHT_TINT) and all(_within(c, (lo, hi)) for c in diffuse),
    }


# -- mid-episode events -----------------------------------------------------------------------------------
@dataclass
class _EventDraw:
    """One episode's draw for an event: the step (trigger "step") and a uniform number choosing among the
    feasible directions when it fires."""

    distance: float
    trigger: str
    step: int
    pick: float
    fired: bool = False


def _footprint_radius(obj: tasks.ObjectDef) -> float:
    """Horizontal radius of the smallest upright cylinder around the object, whatever its yaw."""
    if obj.geom == "box":
        return float(np.hypot(obj.size[0], obj.size[1]))
    return float(max(obj.size[:2]) if obj.geom == "ellipsoid" else obj.size[0])


def _task_def(name: str) -> tasks.TaskDef:
    for suite in tasks.SUITES.values():
        for task in suite:
            if task.name == name:
                return task
    raise ValueError(f"no tabletop task named {name!r}")


class Perturber:
    """Applies a :class:`PerturbConfig` to one scene model; remembers the clean values to restore them.

    ``events`` lists what the mid-episode events did in the current episode (step, object, shift, ...)."""

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
        self._init_events()

    def _init_events(self) -> None:
        m, cfg = self.model, self.config
        self.task = _task_def(task_name(m))
        self.events: list[dict] = []
        self._plans: dict[str, _EventDraw] = {}
        self._push_offset: np.ndarray | None = None
        self._step = 0
        self.ee_site = m.site(arm.EE_SITE).id
        self.arm_qadr = np.array([m.jnt_qposadr[m.joint(n).id] for n in arm.JOINT_NAMES])
        self.arm_act = np.array([m.actuator(n).id for n in arm.JOINT_NAMES])
        self.finger_geoms = {int(m.body(n).geomadr[0]) for n in arm.GRIPPER_JOINTS}
        self.target: str | None = None
        if self.task.objects:
            goal = self.task.goals[0]
            self.target = goal.obj
            body = m.body(goal.obj).id
            joint = m.joint(goal.obj).id
            self._target_ids = (body, int(m.jnt_qposadr[joint]), int(m.jnt_dofadr[joint]), m.geom(goal.obj).id)
            self._others = [m.body(o).id for o in self.task.objects if o != goal.obj]
            self._footprint = _footprint_radius(tasks.OBJECTS[goal.obj]) + FINGER_HALF_WIDTH
        elif cfg.displace_object is not None:
            raise ValueError(f"displace_object: task {self.task.name!r} has no object to displace")
        self.kin = arm.Kinematics() if cfg.push_arm is not None or cfg.recovery > 0 else None

    def reset(self, data: mujoco.MjData, rng: np.random.Generator, keep_out: list[np.ndarray]) -> None:
        """Draw this episode's perturbation. ``keep_out``: xy points distractors must not cover."""
        # own streams: no draw below changes (spawning more children leaves the first ones as they were)
        events_rng = dict(zip((*EVENTS, *SHARES), rng.spawn(len(EVENTS) + len(SHARES))))
        m, c = self.model, self.clean
        m.cam_pos[self.cam], m.cam_quat[self.cam] = c["cam_pos"], c["cam_quat"]
        m.mat_rgba[:] = c["mat_rgba"]
        m.light_dir[:], m.light_diffuse[:] = c["light_dir"], c["light_diffuse"]
        m.geom_matid[self.table_geom] = c["table_mat"]
        if self.config.unseen_env:
            self._unseen_scene(rng)
        elif self.config.randomized_scene and rng.uniform() >= CLEAN_SCENE_SHARE:
            self._training_scene(rng)
        if self.config.camera_jitter:
            self._jitter_camera(rng)
        points = [np.zeros(2), *keep_out]
        if self.config.scatter > 0 and self.target is not None:
            points += self._scatter(data, events_rng["scatter"])
        self._place_distractors(data, rng, points)
        if self.clutter_mocap:
            n = int(rng.integers(len(self.clutter_mocap) + 1))
            for mocap in self.clutter_mocap[n:]:
                data.mocap_pos[mocap] = [0.0, 0.0, -1.0]
            self._place(data, rng, points, self.clutter_mocap[:n], self.cgeoms[:n], self.csize[:n])
        self.events, self._plans, self._push_offset, self._step = [], {}, None, 0
        for name in EVENTS:
            event = getattr(self.config, name)
            if event is not None:
                r = events_rng[name]
                step = int(r.integers(event.timing.window[0], event.timing.window[1] + 1))
                self._plans[name] = _EventDraw(event.distance, event.timing.trigger, step, float(r.uniform()))
        if self.config.recovery > 0:
            self._plan_recovery(events_rng["recovery"])

    def _scatter(self, data: mujoco.MjData, r: np.random.Generator) -> list[np.ndarray]:
        """Start this episode's object at a random landing spot (``scatter=P``); returns the points it and its
        goal now take, for the distractors and clutter to keep clear of."""
        if r.uniform() >= self.config.scatter:
            return []
        mujoco.mj_kinematics(self.model, data)  # the fingers' poses, which the landing test reads
        _, qadr, _, _ = self._target_ids
        start = data.qpos[qadr : qadr + 2].copy()
        for _ in range(100):
            angle = r.uniform(-np.pi, np.pi)
            xy = start + r.uniform(0.0, RECOVERY_CM[1] / 100) * np.array([np.cos(angle), np.sin(angle)])
            if self._landing_ok(xy, data):
                data.qpos[qadr : qadr + 2] = xy
                goal = self.task.goals[0]
                return [xy] + ([tasks.move_target(xy, goal.direction)] if goal.kind == "move" else [])
        return []

    def _plan_recovery(self, r: np.random.Generator) -> None:
        """This episode's recovery event, if it draws one (``recovery=P`` in the module docstring)."""
        if r.uniform() >= self.config.recovery:
            return
        kinds = [k for k in EVENTS if k == "push_arm" or self.target is not None]
        name = kinds[int(r.integers(len(kinds)))]
        distance = float(r.uniform(*RECOVERY_CM)) / 100
        step = int(r.integers(RECOVERY_WINDOW[0], RECOVERY_WINDOW[1] + 1))
        self._plans.setdefault(name, _EventDraw(distance, "step", step, float(r.uniform())))

    def _training_scene(self, rng: np.random.Generator) -> None:
        """A training table (one of ``TRAIN_TABLE_MATERIALS``, random colour), floor, wall and key light."""
        m = self.model
        mat = self.train_materials[int(rng.integers(len(self.train_materials)))]
        m.geom_matid[self.table_geom] = mat
        m.mat_rgba[mat, :3] = _random_colour(rng, self.protected)
        m.mat_rgba[m.material("floor").id, :3] = rng.uniform(*TRAIN_FLOOR_RGB, 3)
        m.mat_rgba[m.material("wall").id, :3] = rng.uniform(*TRAIN_WALL_RGB, 3)
        tilt = rng.uniform(-TRAIN_LIGHT_TILT, TRAIN_LIGHT_TILT, 2)
        direction = np.array([tilt[0], tilt[1], -1.0])
        m.light_dir[0] = direction / np.linalg.norm(direction)
        m.light_diffuse[0] = rng.uniform(*TRAIN_LIGHT_LEVEL) * rng.uniform(*TRAIN_LIGHT_TINT, 3)

    def _unseen_scene(self, rng: np.random.Generator) -> None:
        """A scene outside the training space in every component (module docstring)."""
        m = self.model
        mat = self.test_materials[int(rng.integers(len(self.test_materials)))]
        m.geom_matid[self.table_geom] = mat
        m.mat_rgba[mat, :3] = _unseen_table_colour(rng, self.protected)
        for name in ("floor", "wall"):
            m.mat_rgba[m.material(name).id, :3] = colorsys.hsv_to_rgb(
                rng.uniform(), rng.uniform(*UNSEEN_BACKDROP_SATURATION), rng.uniform(*UNSEEN_BACKDROP_VALUE))
        tilt = rng.uniform(-UNSEEN_LIGHT_TILT[1], UNSEEN_LIGHT_TILT[1], 2)
        tilt[int(rng.integers(2))] = rng.choice([-1.0, 1.0]) * rng.uniform(*UNSEEN_LIGHT_TILT)
        direction = np.array([tilt[0], tilt[1], -1.0])
        m.light_dir[0] = direction / np.linalg.norm(direction)
        tint = np.array([1.0, rng.uniform(UNSEEN_LIGHT_TINT[0], 1.0), rng.uniform(*UNSEEN_LIGHT_TINT)])
        m.light_diffuse[0] = rng.uniform(*UNSEEN_LIGHT_LEVEL) * tint[rng.permutation(3)]

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

    def step(self, data: mujoco.MjData, dt: float) -> list[dict]:
        """Before the physics of one control step: advance the moving distractors by ``dt`` seconds (bouncing
        off the region's edges), fire a due event, and keep a push's offset on the joint commands. Returns
        the events that fired in this step (also appended to ``events``)."""
        self._move_distractors(data, dt)
        fired = len(self.events)
        plan = self._plans.get("displace_object")
        if plan is not None and not plan.fired and self._due(plan, data):
            self._displace(plan, data)
        plan = self._plans.get("push_arm")
        if plan is not None and not plan.fired and self._due(plan, data):
            self._push(plan, data)
        if self._push_offset is not None:
            data.ctrl[self.arm_act] += self._push_offset
        self._step += 1
        return self.events[fired:]

    def _move_distractors(self, data: mujoco.MjData, dt: float) -> None:
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

    def _near_point(self, data: mujoco.MjData) -> np.ndarray:
        """Where "@near" measures from: the target object's centre, or the drawer handle."""
        if self.target is not None:
            return data.xpos[self._target_ids[0]]
        return data.geom_xpos[self.model.geom("handle").id]

    def _due(self, plan: _EventDraw, data: mujoco.MjData) -> bool:
        if plan.trigger == "step":
            return self._step >= plan.step
        return float(np.linalg.norm(data.site_xpos[self.ee_site] - self._near_point(data))) <= NEAR_DISTANCE

    def _object_free(self, data: mujoco.MjData) -> bool:
        """At rest on the table and touched by no finger (open fingers around it are fine: it slides out)."""
        body, _, dof, geom = self._target_ids
        for g1, g2 in data.contact.geom[: data.ncon]:
            if (g1 == geom and g2 in self.finger_geoms) or (g2 == geom and g1 in self.finger_geoms):
                return False
        rest_z = tasks.OBJECTS[self.target].rest_z
        return bool(np.linalg.norm(data.qvel[dof : dof + 3]) < 0.05 and data.xpos[body][2] < rest_z + 0.006)

    def _displace_directions(self, plan: _EventDraw) -> list[np.ndarray]:
        """Candidate unit shifts in the order this episode tries them: eight directions from a random angle,
        for a move only those without a component along the instructed direction (a jump never does part of
        the task)."""
        angles = 2 * np.pi * plan.pick + np.arange(8) * np.pi / 4
        units = [np.array([np.cos(a), np.sin(a)]) for a in angles]
        goal = self.task.goals[0]
        if goal.kind == "move":
            units = [u for u in units if u @ tasks.DIRECTIONS[goal.direction] <= 1e-9]
        return units

    def _landing_ok(self, xy: np.ndarray, data: mujoco.MjData) -> bool:
        """Reachable, its goal reachable, clear of the other task objects and of any finger reaching below
        the object's top."""
        if not OBJECT_REACH[0] <= np.linalg.norm(xy) <= OBJECT_REACH[1]:
            return False
        goal = self.task.goals[0]
        if goal.kind == "move" and np.linalg.norm(tasks.move_target(xy, goal.direction)) > GOAL_REACH:
            return False
        if any(np.linalg.norm(xy - data.xpos[b][:2]) < OBJECT_SPACING for b in self._others):
            return False
        top = 2 * tasks.OBJECTS[self.target].rest_z
        for g in self.finger_geoms:
            low = data.geom_xpos[g][2] - self.model.geom_size[g][2] < top + FINGER_CLEARANCE
            if low and np.linalg.norm(xy - data.geom_xpos[g][:2]) < self._footprint + FINGER_CLEARANCE:
                return False
        return True

    def _displace(self, plan: _EventDraw, data: mujoco.MjData) -> None:
        """Move the object if it is free and one of its candidate spots is fit to land on; else try again at
        the next step."""
        if not self._object_free(data):
            return
        _, qadr, dof, _ = self._target_ids
        start = data.qpos[qadr : qadr + 2].copy()
        shift = next((plan.distance * u for u in self._displace_directions(plan)
                      if self._landing_ok(start + plan.distance * u, data)), None)
        if shift is None:
            return
        plan.fired = True
        data.qpos[qadr : qadr + 2] = start + shift
        data.qvel[dof : dof + 6] = 0.0
        self.events.append({"kind": "displace_object", "step": self._step, "object": self.target,
                            "shift": [float(shift[0]), float(shift[1]), 0.0]})

    def _push(self, plan: _EventDraw, data: mujoco.MjData) -> None:
        """Joint offset that moves the tool centre ``plan.distance`` horizontally at constant orientation, in
        the first of eight directions (from this episode's angle) that the arm can reach; if none is, the push
        waits for the next step."""
        q = data.qpos[self.arm_qadr].copy()
        shift, offset = np.zeros(3), np.zeros(len(q))
        if plan.distance > 0:
            pos, mat = self.kin.fk_mat(q)
            for angle in 2 * np.pi * plan.pick + np.arange(8) * np.pi / 4:
                shift = plan.distance * np.array([np.cos(angle), np.sin(angle), 0.0])
                pushed = q
                for _ in range(self.kin.config.iterations):
                    pushed = self.kin.ik_step(pushed, pos + shift, mat)
                pos_err, rot_err = self.kin.pose_error(pushed, pos + shift, mat)
                if pos_err <= PUSH_TOLERANCE and rot_err <= PUSH_ROT_TOLERANCE:
                    offset = pushed - q
                    break
            else:
                return
        plan.fired = True
        self._push_offset = offset
        self.events.append({"kind": "push_arm", "step": self._step, "tool_shift": shift.tolist(),
                            "joint_offset": offset.tolist()})
