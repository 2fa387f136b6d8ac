"""The SO-101 in MuJoCo: TheRobotStudio's arm (``pivla/envs/assets/so101``, Apache-2.0, see its NOTICE), LeRobot's
units, and the kinematics the scripted expert plans with.

Joints and actuators of the MJCF are named as LeRobot's motors (``pivla.data.action_space.SO101_MOTORS``). The
MJCF is the "new calibration" model: every joint's zero is the middle of its range, which is where LeRobot's
degree mode puts zero after calibration, so a body joint's LeRobot position is its MJCF angle in degrees. The
gripper is 0..100 over the MJCF joint's range, 0 closed (the joint's lower limit) and 100 open, as LeRobot's
RANGE_0_100 mode reads it. Signs and offsets of a calibrated real arm may differ per joint (its calibration
decides them); the twin's are the MJCF's.

:class:`Kinematics` solves joint-limited damped-least-squares IK with MuJoCo's Jacobians on a private
``MjData`` of the scene's model, for a tool point between the fingertip pads (``TCP_FROM_FIXED_PAD``), the
jaws pointing down and the jaw axis at a given yaw (top-down grasps).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from pivla.arm.rotations import wrap_angle
from pivla.data.action_space import SO101, SO101_MOTORS

ASSET_DIR = Path(__file__).resolve().parents[1] / "assets" / "so101"
ARM_XML = ASSET_DIR / "so101_new_calib.xml"
MESH_DIR = ASSET_DIR / "assets"
JOINTS: tuple[str, ...] = SO101_MOTORS  # MJCF joint and actuator names, LeRobot's motor order
BODY_JOINTS = JOINTS[:5]
ACTION_SPACE = SO101
GRIPPER_BODY = "gripper"  # the wrist-roll link, which carries the fixed jaw
MOVING_JAW_BODY = "moving_jaw_so101_v1"
PADS = ("fixed_jaw_pad", "moving_jaw_pad")
EE_SITE = "gripperframe"
# The tool point: on the fixed jaw's pad axis, this far from its inner face towards the moving jaw. The fixed jaw
# does not move, so a cube centred here (25 mm wide) clears that pad by 6 mm when the jaws close round it.
TCP_FROM_FIXED_PAD = 0.0185  # m
DOWN = np.array([0.0, 0.0, -1.0])
_APPROACH_AXIS, _JAW_AXIS = 0, 2  # gripperframe: x runs out along the jaws, z from the fixed to the moving jaw


@functools.cache
def asset_files() -> dict[str, bytes]:
    """The arm's MJCF and meshes, keyed as the MJCF includes them (``so101_new_calib.xml``, ``assets/<mesh>.stl``)."""
    files = {ARM_XML.name: ARM_XML.read_bytes()}
    files.update({f"{MESH_DIR.name}/{p.name}": p.read_bytes() for p in sorted(MESH_DIR.glob("*.stl"))})
    return files


@functools.cache
def joint_limits() -> np.ndarray:
    """(6, 2) joint ranges of the MJCF in radians, ``JOINTS`` order."""
    xml = f'<mujoco><include file="{ARM_XML.name}"/></mujoco>'
    m = mujoco.MjModel.from_xml_string(xml, asset_files())
    return np.array([m.jnt_range[m.joint(n).id] for n in JOINTS])


def to_lerobot(q: np.ndarray) -> np.ndarray:
    """MJCF joint angles (rad, ``JOINTS`` order) -> LeRobot positions (degrees, the gripper 0..100)."""
    q = np.asarray(q, float)
    lo, hi = joint_limits()[-1]
    out = np.degrees(q)
    out[..., -1] = 100.0 * (q[..., -1] - lo) / (hi - lo)
    return out


def from_lerobot(u: np.ndarray) -> np.ndarray:
    """LeRobot positions (degrees, the gripper 0..100) -> MJCF joint angles (rad)."""
    u = np.asarray(u, float)
    lo, hi = joint_limits()[-1]
    out = np.radians(u)
    out[..., -1] = lo + u[..., -1] / 100.0 * (hi - lo)
    return out


def lerobot_limits() -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper limits of an action in LeRobot units (the MJCF's ranges; the gripper 0..100)."""
    lim = joint_limits()
    return to_lerobot(lim[:, 0]), to_lerobot(lim[:, 1])


@dataclass(frozen=True)
class IKConfig:
    iterations: int = 40
    damping: float = 1e-4  # m^2 (lambda^2 of the damped least squares)
    tilt_weight: float = 0.05  # m of position error worth one radian of jaw tilt away from straight down
    yaw_weight: float = 0.03  # m per radian of jaw-axis yaw error
    tolerance: float = 2e-4  # m (and weighted rad)


class Kinematics:
    """Forward kinematics and top-down IK of the tool point on a private copy of a compiled scene's state."""

    def __init__(self, model: mujoco.MjModel, config: IKConfig | None = None):
        self.model = model
        self.config = config or IKConfig()
        self.data = mujoco.MjData(model)
        self.qadr = np.array([model.jnt_qposadr[model.joint(n).id] for n in JOINTS])
        self.dofadr = np.array([model.jnt_dofadr[model.joint(n).id] for n in JOINTS])
        self.site = model.site(EE_SITE).id
        self.body = model.body(GRIPPER_BODY).id
        lim = np.array([model.jnt_range[model.joint(n).id] for n in JOINTS])
        self.lower, self.upper = lim[:, 0], lim[:, 1]
        # the tool point, fixed in the gripper body's frame: out from the fixed pad's inner face along the jaw axis
        pad = model.geom(PADS[0]).id
        if model.geom_bodyid[pad] != self.body or np.any(model.geom_quat[pad] != [1.0, 0.0, 0.0, 0.0]):
            raise RuntimeError(f"{PADS[0]} is expected as an unrotated box of the {GRIPPER_BODY} body")
        self._set(np.zeros(len(JOINTS)))
        rot = self.data.xmat[self.body].reshape(3, 3)
        jaw = rot.T @ self.data.site_xmat[self.site].reshape(3, 3)[:, _JAW_AXIS]  # the jaw axis in the body frame
        if abs(abs(jaw[0]) - 1.0) > 1e-6:
            raise RuntimeError(f"the jaw axis of {EE_SITE} is expected along the {GRIPPER_BODY} body's x axis")
        self.tcp_offset = model.geom_pos[pad] + jaw * (model.geom_size[pad][0] + TCP_FROM_FIXED_PAD)
        self.pan_axis = self.data.xanchor[model.joint(JOINTS[0]).id][:2].copy()  # where shoulder_pan turns (x, y)

    def heading(self, point: np.ndarray) -> float:
        """Bearing (rad) of a point from the shoulder_pan axis: where the arm turns to reach it."""
        return float(np.arctan2(point[1] - self.pan_axis[1], point[0] - self.pan_axis[0]))

    def _set(self, q: np.ndarray) -> None:
        d = self.data
        d.qpos[self.qadr[: len(q)]] = q
        mujoco.mj_kinematics(self.model, d)
        mujoco.mj_comPos(self.model, d)

    def tcp(self, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
        """(tool point position, gripperframe rotation) of a live ``data``."""
        rot = data.xmat[self.body].reshape(3, 3)
        return data.xpos[self.body] + rot @ self.tcp_offset, data.site_xmat[self.site].reshape(3, 3).copy()

    def fk(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(tool point, gripperframe rotation) at body-joint angles ``q`` (5 or 6 values, rad)."""
        self._set(np.asarray(q, float))
        return self.tcp(self.data)

    def gravity(self, q: np.ndarray) -> np.ndarray:
        """Joint torques (N m, ``JOINTS`` order) that hold the arm still at ``q`` against gravity."""
        d = self.data
        self._set(np.asarray(q, float))
        d.qvel[:] = 0.0
        mujoco.mj_comVel(self.model, d)
        out = np.zeros(self.model.nv)
        mujoco.mj_rne(self.model, d, 0, out)
        return out[self.dofadr]

    def errors(self, q: np.ndarray, target: np.ndarray, yaw: float | None) -> tuple[float, float]:
        """(position error in m, tilt of the jaws from straight down in rad) of the tool point at ``q``."""
        pos, rot = self.fk(q)
        tilt = float(np.arccos(np.clip(rot[:, _APPROACH_AXIS] @ DOWN, -1.0, 1.0)))
        return float(np.linalg.norm(target - pos)), tilt

    def solve(self, target: np.ndarray, yaw: float | None, q0: np.ndarray) -> np.ndarray:
        """Body-joint angles (5, rad) that put the tool point at ``target`` with the jaws pointing down and the
        jaw axis (fixed to moving jaw) along world yaw ``yaw`` (None: free), from ``q0``; joint-limited damped
        least squares with weighted orientation rows, so an orientation the arm cannot reach is traded for
        position accuracy."""
        cfg, m, d = self.config, self.model, self.data
        q = np.clip(np.asarray(q0, float)[:5], self.lower[:5], self.upper[:5])
        jp, jr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
        cols = self.dofadr[:5]
        for _ in range(cfg.iterations):
            pos, rot = self.fk(q)
            approach = rot[:, _APPROACH_AXIS]
            tilt = np.cross(approach, DOWN)  # rotation (small angle) taking the jaws to straight down
            rows_e = [target - pos, cfg.tilt_weight * tilt]
            mujoco.mj_jac(m, d, jp, jr, pos, self.body)
            rows_j = [jp[:, cols], cfg.tilt_weight * jr[:, cols]]
            if yaw is not None:
                jaw = rot[:, _JAW_AXIS]
                err = wrap_angle(yaw - float(np.arctan2(jaw[1], jaw[0])))
                rows_e.append(np.array([cfg.yaw_weight * err]))
                rows_j.append(cfg.yaw_weight * jr[2:3, cols])
            e, jac = np.concatenate(rows_e), np.vstack(rows_j)
            if np.linalg.norm(e) < cfg.tolerance:
                break
            dq = jac.T @ np.linalg.solve(jac @ jac.T + cfg.damping * np.eye(len(e)), e)
            q = np.clip(q + dq, self.lower[:5], self.upper[:5])
        return q
