"""MJCF of one task's scene: the arm (``pivla/arm/arm.xml``), a table, the task's objects, an optional drawer
cabinet, and visual-only distractor slots. Shadows and multisampling are off: on a CPU renderer they cost
~20x the frame time of this primitive scene (docs/twin.md)."""

from __future__ import annotations

import functools

import cv2
import mujoco
import numpy as np

from pivla.arm.constants import ARM_XML
from pivla.envs.tabletop.tasks import CABINET_FRONT_X, OBJECTS, TaskDef

TABLE_RGBA = (0.78, 0.66, 0.52, 1.0)
FLOOR_RGBA = (0.35, 0.37, 0.4, 1.0)
WALL_RGBA = (0.82, 0.84, 0.86, 1.0)
# The agent view faces the robot across the workspace, framed on where objects start and land, so a 3 cm
# object spans ~7 px of a 96-px image (from farther and wider it was ~4 px, too few to localise it).
AGENTVIEW_POS = np.array([0.40, 0.0, 0.30])
AGENTVIEW_TARGET = np.array([0.16, 0.0, 0.02])
AGENTVIEW_FOVY = 50.0
# Distractor slots cycle through these primitives (sizes are maxima; the perturbation scales them down).
DISTRACTOR_SHAPES = (
    ("cylinder", "0.015 0.025"),
    ("box", "0.02 0.012 0.012"),
    ("capsule", "0.01 0.02"),
    ("sphere", "0.017"),
    ("ellipsoid", "0.025 0.012 0.01"),
    ("box", "0.01 0.03 0.008"),
)
# Training-only clutter (``randomized_scene``): flat discs and cards and thin posts, a family of shapes that
# no test distractor slot uses, so that static-distractor tests stay a test of generalisation.
CLUTTER_SHAPES = (
    ("cylinder", "0.03 0.002"),
    ("box", "0.035 0.025 0.002"),
    ("cylinder", "0.007 0.045"),
)
# Cabinet: outer depth (x), half width (y), height (z); the drawer slides towards the robot (-x).
CAB_DEPTH, CAB_HALF_W, CAB_H = 0.12, 0.075, 0.065
# The handle bar stands 6 cm off the drawer front: the closed fingers (2 cm deep) hook behind it with 1.5 cm
# to spare on either side, and the fully open ones (35 mm travel + 10 mm a side) fit around it.
HANDLE_STANDOFF, HANDLE_Z = 0.06, 0.04
HANDLE_HALF_DEPTH = 0.005  # the bar's half thickness along x, the direction the drawer slides
# The scene's MJCF model is named MODEL_PREFIX + task name, so a perturbation given only the compiled model
# can tell which task (objects, instructed direction) it acts on.
MODEL_PREFIX = "pivla_tabletop_"


def look_at_xyaxes(pos: np.ndarray, target: np.ndarray) -> str:
    """MJCF ``xyaxes`` of a camera at ``pos`` looking at ``target`` with world z up."""
    fwd = (target - pos) / np.linalg.norm(target - pos)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    return " ".join(f"{v:.6f}" for v in (*right, *up))


def _fmt(values) -> str:
    return " ".join(f"{v:g}" for v in values)


def _object_xml(name: str) -> str:
    o = OBJECTS[name]
    friction = "1 0.02 0.004" if o.condim == 6 else "1 0.01 0.001"  # rolling friction stops balls rolling on
    return (
        f'<body name="{name}" pos="0.2 0 {o.rest_z}"><freejoint name="{name}"/>'
        f'<geom name="{name}" type="{o.geom}" size="{_fmt(o.size)}" rgba="{_fmt(o.rgba)}" mass="{o.mass}" '
        f'condim="{o.condim}" friction="{friction}" solref="0.005 1"/></body>'
    )


def _cabinet_xml() -> str:
    x0, w, h, d = CABINET_FRONT_X, CAB_HALF_W, CAB_H, CAB_DEPTH
    t = 0.006  # wall thickness
    shell = [
        ("cab_top", (x0 + d / 2, 0, h - t / 2), (d / 2, w, t / 2)),
        ("cab_bottom", (x0 + d / 2, 0, t / 2), (d / 2, w, t / 2)),
        ("cab_left", (x0 + d / 2, w - t / 2, h / 2), (d / 2, t / 2, h / 2)),
        ("cab_right", (x0 + d / 2, -w + t / 2, h / 2), (d / 2, t / 2, h / 2)),
        ("cab_back", (x0 + d - t / 2, 0, h / 2), (t / 2, w, h / 2)),
    ]
    geoms = "".join(
        f'<geom name="{n}" type="box" pos="{_fmt(p)}" size="{_fmt(s)}" material="cabinet"/>' for n, p, s in shell
    )
    iw, ih = w - t - 0.002, h - 2 * t - 0.004  # drawer inner half width / height
    drawer = [
        ("drawer_front", (x0 - t / 2 + 0.002, 0, t + 0.002 + ih / 2), (t / 2, w - 0.002, ih / 2 + 0.002)),
        ("drawer_floor", (x0 + d / 2, 0, t + 0.004), (d / 2 - t, iw, 0.002)),
        ("drawer_left", (x0 + d / 2, iw - 0.002, t + 0.02), (d / 2 - t, 0.002, 0.014)),
        ("drawer_right", (x0 + d / 2, -iw + 0.002, t + 0.02), (d / 2 - t, 0.002, 0.014)),
        ("drawer_back", (x0 + d - 2 * t, 0, t + 0.02), (0.002, iw, 0.014)),
    ]
    hx = x0 - HANDLE_STANDOFF
    handle = [
        ("handle", (hx, 0, HANDLE_Z), (HANDLE_HALF_DEPTH, 0.04, 0.005)),
        ("handle_post_l", ((hx + x0) / 2, 0.035, HANDLE_Z), ((x0 - hx) / 2, 0.004, 0.004)),
        ("handle_post_r", ((hx + x0) / 2, -0.035, HANDLE_Z), ((x0 - hx) / 2, 0.004, 0.004)),
    ]
    dgeoms = "".join(
        f'<geom name="{n}" type="box" pos="{_fmt(p)}" size="{_fmt(s)}" material="drawer"/>' for n, p, s in drawer
    )
    hgeoms = "".join(
        f'<geom name="{n}" type="box" pos="{_fmt(p)}" size="{_fmt(s)}" material="handle" condim="4" '
        f'friction="1.2 0.02 0.001"/>' for n, p, s in handle
    )
    return (
        f'<body name="cabinet" pos="0 0 0">{geoms}'
        f'<body name="drawer"><joint name="drawer" type="slide" axis="-1 0 0" range="0 {0.10}" damping="3" '
        f'frictionloss="0.3" armature="0.05"/>{dgeoms}{hgeoms}</body></body>'
    )


def _distractor_xml(i: int) -> str:
    shape, size = DISTRACTOR_SHAPES[i % len(DISTRACTOR_SHAPES)]
    return (
        f'<body name="distractor{i}" mocap="true" pos="0 0 -1"><geom name="distractor{i}" type="{shape}" '
        f'size="{size}" contype="0" conaffinity="0" rgba="1 1 1 1"/></body>'
    )


def _clutter_xml(i: int) -> str:
    shape, size = CLUTTER_SHAPES[i % len(CLUTTER_SHAPES)]
    return (
        f'<body name="clutter{i}" mocap="true" pos="0 0 -1"><geom name="clutter{i}" type="{shape}" '
        f'size="{size}" contype="0" conaffinity="0" rgba="1 1 1 1"/></body>'
    )


def scene_xml(task: TaskDef, n_distractors: int = 0, n_clutter: int = 0) -> str:
    """The scene for ``task`` with ``n_distractors`` test-distractor slots and ``n_clutter`` training-clutter
    slots (all hidden below the floor until used)."""
    cam_axes = look_at_xyaxes(AGENTVIEW_POS, AGENTVIEW_TARGET)
    objects = "".join(_object_xml(n) for n in task.objects)
    cabinet = _cabinet_xml() if task.drawer else ""
    distractors = "".join(_distractor_xml(i) for i in range(n_distractors))
    distractors += "".join(_clutter_xml(i) for i in range(n_clutter))
    return f"""<mujoco model="{MODEL_PREFIX}{task.name}">
  <include file="{ARM_XML.name}"/>
  <visual>
    <quality shadowsize="0" offsamples="0"/>
    <headlight ambient="0.35 0.35 0.35" diffuse="0.4 0.4 0.4" specular="0 0 0"/>
    <map znear="0.01" zfar="5"/>
  </visual>
  <asset>
    <texture name="checker" type="2d" builtin="checker" rgb1="1 1 1" rgb2="0.55 0.55 0.55" width="64" height="64"/>
    <texture name="grain" type="2d" builtin="gradient" rgb1="1 1 1" rgb2="0.6 0.6 0.6" width="64" height="64"/>
    <texture name="dots" type="2d" builtin="flat" mark="random" random="0.08" markrgb="0.4 0.4 0.4" rgb1="1 1 1"
             width="128" height="128"/>
    <material name="table" rgba="{_fmt(TABLE_RGBA)}" specular="0" shininess="0"/>
    <material name="table_checker" texture="checker" texrepeat="8 8" rgba="1 1 1 1" specular="0"/>
    <material name="table_grain" texture="grain" texrepeat="3 1" rgba="1 1 1 1" specular="0"/>
    <material name="table_dots" texture="dots" texrepeat="2 2" rgba="1 1 1 1" specular="0"/>
    <texture name="tiles" type="2d" builtin="flat" mark="edge" markrgb="0.45 0.45 0.45" rgb1="1 1 1" width="64"
             height="64"/>
    <texture name="crosses" type="2d" builtin="flat" mark="cross" markrgb="0.5 0.5 0.5" rgb1="1 1 1" width="64"
             height="64"/>
    <material name="table_tiles" texture="tiles" texrepeat="6 6" rgba="1 1 1 1" specular="0"/>
    <material name="table_crosses" texture="crosses" texrepeat="5 5" rgba="1 1 1 1" specular="0"/>
    <texture name="blotches" type="2d" file="blotches.png"/>
    <texture name="stripes" type="2d" file="stripes.png"/>
    <material name="table_blotches" texture="blotches" texrepeat="1 1" rgba="1 1 1 1" specular="0"/>
    <material name="table_stripes" texture="stripes" texrepeat="2 2" rgba="1 1 1 1" specular="0"/>
    <material name="floor" rgba="{_fmt(FLOOR_RGBA)}" specular="0"/>
    <material name="wall" rgba="{_fmt(WALL_RGBA)}" specular="0"/>
    <material name="cabinet" rgba="0.55 0.4 0.25 1" specular="0"/>
    <material name="drawer" rgba="0.85 0.75 0.45 1" specular="0"/>
    <material name="handle" rgba="0.1 0.1 0.1 1" specular="0"/>
  </asset>
  <worldbody>
    <light name="key" pos="0.3 -0.3 1.2" dir="-0.2 0.25 -1" directional="true" diffuse="0.55 0.55 0.55"
           specular="0 0 0" castshadow="false"/>
    <geom name="floor" type="plane" pos="0 0 -0.04" size="3 3 0.1" material="floor" contype="0" conaffinity="0"/>
    <geom name="table" type="box" pos="0.17 0 -0.02" size="0.38 0.5 0.02" material="table" condim="4"
          friction="1 0.01 0.001"/>
    <geom name="wall" type="box" pos="-0.45 0 0.4" size="0.01 2 0.6" material="wall" contype="0" conaffinity="0"/>
    <camera name="agentview" pos="{_fmt(AGENTVIEW_POS)}" xyaxes="{cam_axes}" fovy="{AGENTVIEW_FOVY:g}"/>
    {objects}{cabinet}{distractors}
  </worldbody>
  <contact><exclude body1="finger_left" body2="finger_right"/></contact>
</mujoco>"""


def task_name(model: mujoco.MjModel) -> str:
    """The task a compiled scene model was built for (from its model name, see ``MODEL_PREFIX``)."""
    name = bytes(model.names).split(b"\0", 1)[0].decode()
    if not name.startswith(MODEL_PREFIX):
        raise ValueError(f"model {name!r} is not a tabletop scene (its name must start with {MODEL_PREFIX!r})")
    return name[len(MODEL_PREFIX):]


def _png(gray: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", np.repeat(np.round(gray * 255).astype(np.uint8)[..., None], 3, axis=-1))
    if not ok:
        raise RuntimeError("OpenCV could not encode a training texture as PNG")
    return buf.tobytes()


@functools.cache
def _training_textures() -> dict[str, bytes]:
    """Grey training-only table textures (the material colour tints them), drawn once from a fixed seed:
    ``blotches`` (large soft light and dark patches, ~15 cm on the table) and ``stripes`` (planks of random
    width). Neither is a pattern of the test's textures (checker, gradient, speckle)."""
    rng = np.random.default_rng(20261123)
    noise = cv2.resize(rng.normal(size=(6, 6)), (128, 128), interpolation=cv2.INTER_CUBIC)
    noise = (noise - noise.min()) / (noise.max() - noise.min())
    widths = rng.integers(4, 17, 40)
    bands = np.repeat(rng.uniform(0.55, 1.0, len(widths)), widths)[:128]
    return {"blotches.png": _png(0.5 + 0.5 * noise), "stripes.png": _png(np.tile(bands[:, None], (1, 128)))}


def asset_files() -> dict[str, bytes]:
    """Files the scene XML includes, for ``MjModel.from_xml_string(xml, assets)``."""
    return {ARM_XML.name: ARM_XML.read_bytes(), **_training_textures()}
