"""MJCF of one SO-101 task's scene: the arm (``assets/so101``, with a wrist camera added to its gripper link), a
table, the two cubes and the task's target (bowl or pad), a front camera. Shadows and multisampling are off, as
on the tabletop twin: a CPU renderer spends most of a frame on them (docs/twin.md)."""

from __future__ import annotations

import functools

import numpy as np

from pivla.envs.so101 import model as arm
from pivla.envs.so101.tasks import (
    BOWL_FLOOR,
    BOWL_HEIGHT,
    BOWL_INNER,
    BOWL_WALL,
    CUBE_HALF,
    CUBE_MASS,
    CUBES,
    PAD_HALF,
    TARGET_RGBA,
    TaskDef,
)

MODEL_PREFIX = "pivla_so101_"
PHYSICS_DT = 0.002
TABLE_RGBA = (0.78, 0.66, 0.52, 1.0)
# The front camera faces the arm from above the far side of the workspace (as LeRobot's SO-101 recordings place
# "front"), framed on where cubes and targets lie: a 25 mm cube spans ~6 px of a 96 px picture. The wrist camera
# sits behind the fixed jaw and looks down the jaws.
FRONT_POS, FRONT_TARGET, FRONT_FOVY = np.array([0.40, 0.0, 0.45]), np.array([0.16, 0.0, 0.0]), 48.0
WRIST_POS, WRIST_TARGET, WRIST_FOVY = np.array([-0.06, 0.0, -0.05]), np.array([0.005, 0.0, -0.14]), 75.0
BOWL_SEGMENTS = 16
_WRIST_ANCHOR = '<joint axis="0 0 1" name="wrist_roll"'


def look_at_xyaxes(pos: np.ndarray, target: np.ndarray, up: tuple[float, float, float] = (0.0, 0.0, 1.0)) -> str:
    """MJCF ``xyaxes`` of a camera at ``pos`` looking at ``target``, ``up`` roughly up in the image."""
    fwd = (target - pos) / np.linalg.norm(target - pos)
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    cam_up = np.cross(right, fwd)
    return " ".join(f"{v:.6f}" for v in (*right, *cam_up))


def _fmt(values) -> str:
    return " ".join(f"{v:g}" for v in values)


@functools.cache
def arm_xml() -> bytes:
    """The arm's MJCF with the wrist camera in its gripper link (inserted in memory; the file is upstream's)."""
    text = arm.ARM_XML.read_text()
    if text.count(_WRIST_ANCHOR) != 1:
        raise RuntimeError(f"{arm.ARM_XML}: no unique wrist_roll joint to attach the wrist camera to")
    axes = look_at_xyaxes(WRIST_POS, WRIST_TARGET, up=(1.0, 0.0, 0.0))
    camera = f'<camera name="wrist" pos="{_fmt(WRIST_POS)}" xyaxes="{axes}" fovy="{WRIST_FOVY:g}"/>\n                '
    return text.replace(_WRIST_ANCHOR, camera + _WRIST_ANCHOR).encode()


def asset_files() -> dict[str, bytes]:
    """Files the scene XML includes, for ``MjModel.from_xml_string(xml, assets)``."""
    return {**arm.asset_files(), arm.ARM_XML.name: arm_xml()}


def _cube_xml(name: str) -> str:
    return (f'<body name="{name}" pos="0.2 0 {CUBE_HALF}"><freejoint name="{name}"/>'
            f'<geom name="{name}" type="box" size="{CUBE_HALF} {CUBE_HALF} {CUBE_HALF}" rgba="{_fmt(CUBES[name])}" '
            f'mass="{CUBE_MASS}" condim="4" friction="1 0.005 0.0001" solref="0.004 1"/></body>')


def _bowl_xml() -> str:
    r = BOWL_INNER + BOWL_WALL / 2
    half_len = np.pi * (BOWL_INNER + BOWL_WALL) / BOWL_SEGMENTS * 1.02
    walls = "".join(
        f'<geom name="bowl_wall{i}" type="box" pos="{r * np.cos(a):.5f} {r * np.sin(a):.5f} {BOWL_HEIGHT / 2:g}" '
        f'euler="0 0 {a:.5f}" size="{BOWL_WALL / 2:g} {half_len:.5f} {BOWL_HEIGHT / 2:g}" material="bowl"/>'
        for i, a in enumerate(np.linspace(0, 2 * np.pi, BOWL_SEGMENTS, endpoint=False)))
    floor = (f'<geom name="bowl_floor" type="cylinder" pos="0 0 {BOWL_FLOOR / 2:g}" '
             f'size="{BOWL_INNER + BOWL_WALL:g} {BOWL_FLOOR / 2:g}" material="bowl"/>')
    return f'<body name="bowl" mocap="true" pos="0.2 0 0">{floor}{walls}</body>'


def _pad_xml() -> str:
    return (f'<body name="pad" mocap="true" pos="0.2 0 0"><geom name="pad" type="box" pos="0 0 0.0006" '
            f'size="{PAD_HALF} {PAD_HALF} 0.0005" rgba="{_fmt(TARGET_RGBA["pad"])}" contype="0" conaffinity="0"/>'
            f'</body>')


def scene_xml(task: TaskDef) -> str:
    front = look_at_xyaxes(FRONT_POS, FRONT_TARGET)
    cubes = "".join(_cube_xml(n) for n in task.objects)
    target = _bowl_xml() if task.target == "bowl" else _pad_xml()
    return f"""<mujoco model="{MODEL_PREFIX}{task.name}">
  <include file="{arm.ARM_XML.name}"/>
  <option timestep="{PHYSICS_DT}" cone="elliptic" impratio="10"/>
  <visual>
    <quality shadowsize="0" offsamples="0"/>
    <headlight ambient="0.4 0.4 0.4" diffuse="0.45 0.45 0.45" specular="0 0 0"/>
    <map znear="0.005" zfar="5"/>
  </visual>
  <asset>
    <material name="table" rgba="{_fmt(TABLE_RGBA)}" specular="0" shininess="0"/>
    <material name="bowl" rgba="{_fmt(TARGET_RGBA["bowl"])}" specular="0.1"/>
  </asset>
  <worldbody>
    <light name="key" pos="0.3 -0.3 1.2" dir="-0.2 0.25 -1" directional="true" diffuse="0.5 0.5 0.5"
           specular="0 0 0" castshadow="false"/>
    <geom name="floor" type="plane" pos="0 0 -0.04" size="3 3 0.1" rgba="0.35 0.37 0.4 1" contype="0"
          conaffinity="0"/>
    <geom name="table" type="box" pos="0.15 0 -0.02" size="0.4 0.45 0.02" material="table" condim="4"
          friction="1 0.005 0.0001"/>
    <geom name="backdrop" type="box" pos="-0.35 0 0.4" size="0.01 2 0.6" rgba="0.82 0.84 0.86 1" contype="0"
          conaffinity="0"/>
    <camera name="front" pos="{_fmt(FRONT_POS)}" xyaxes="{front}" fovy="{FRONT_FOVY:g}"/>
    {cubes}{target}
  </worldbody>
</mujoco>"""
