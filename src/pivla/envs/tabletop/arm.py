"""The low-cost arm's kinematic model: one place for joint names, limits, zero positions and link lengths.

The arm is a ~$300 6-DOF hobby-servo arm (382 mm reach, 0.2 kg payload, 0.7 m/s, repeatability within
10 mm) with a parallel gripper. ``assets/arm.xml`` is its MJCF; the simulated twin includes it in its
scene and the real arm's driver uses the same functions below for kinematics, so nothing here renders.

Frames and conventions (metres, radians):

- World/base frame: origin at the centre of the base plate on the table top, x forward, y left, z up.
- Zero position: every joint at 0 makes the arm point straight up (tool centre at z = 0.457 m).
  Positive ``shoulder_pitch`` / ``elbow_pitch`` / ``wrist_pitch`` lean the arm forward (towards +x).
- End-effector frame (site ``ee``): the tool centre point between the finger pads. Its x axis is the
  fingers' closing direction and its z axis points *against* the approach direction, so a top-down
  grasp has Euler angles (0, 0, yaw) — far from the Euler singularity and wrap-around.
- Euler angles are (roll, pitch, yaw) with ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (extrinsic x-y-z).

Link lengths (joint axis to joint axis): shoulder height 0.075, upper arm 0.150, forearm 0.132 (elbow to
wrist pitch), wrist pitch to tool centre 0.100; 0.150 + 0.132 + 0.100 = 0.382 m reach from the shoulder.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

ARM_XML = Path(__file__).with_name("assets") / "arm.xml"

JOINT_NAMES: tuple[str, ...] = (
    "base_yaw",
    "shoulder_pitch",
    "elbow_pitch",
    "forearm_roll",
    "wrist_pitch",
    "wrist_roll",
)
# Each range spans ~180 degrees like a hobby servo; the servo's centre is the middle of its range.
JOINT_LIMITS: np.ndarray = np.array(
    [
        [-1.5708, 1.5708],
        [-1.5708, 1.5708],
        [-0.6, 2.54],
        [-1.5708, 1.5708],
        [-1.2, 1.94],
        [-1.5708, 1.5708],
    ]
)
ZERO_POSITION: np.ndarray = np.zeros(6)
GRIPPER_JOINTS: tuple[str, str] = ("finger_left", "finger_right")
GRIPPER_OPEN = 0.035  # finger travel per side (m): 70 mm maximum opening
LINK_LENGTHS: dict[str, float] = {
    "shoulder_height": 0.075,
    "upper_arm": 0.150,
    "forearm": 0.132,
    "wrist_to_tool": 0.100,
}
REACH = LINK_LENGTHS["upper_arm"] + LINK_LENGTHS["forearm"] + LINK_LENGTHS["wrist_to_tool"]
EE_SITE = "ee"
# Home: tool centre 0.15 m in front of the base, 0.15 m above the table, pointing down, yaw 0.
HOME_POSE = (np.array([0.15, 0.0, 0.15]), np.zeros(3))


def euler_to_mat(euler: np.ndarray) -> np.ndarray:
    """Rotation matrix of (roll, pitch, yaw), ``R = Rz(yaw) Ry(pitch) Rx(roll)``."""
    r, p, y = np.asarray(euler, dtype=float)
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def mat_to_euler(mat: np.ndarray) -> np.ndarray:
    """Inverse of :func:`euler_to_mat` (pitch in [-pi/2, pi/2])."""
    m = np.asarray(mat, dtype=float).reshape(3, 3)
    pitch = np.arcsin(np.clip(-m[2, 0], -1.0, 1.0))
    return np.array([np.arctan2(m[2, 1], m[2, 2]), pitch, np.arctan2(m[1, 0], m[0, 0])])


def rotvec_from_mat(mat: np.ndarray) -> np.ndarray:
    """Axis * angle of a rotation matrix (via MuJoCo's quaternion helpers)."""
    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, np.ascontiguousarray(mat, dtype=float).reshape(9))
    vel = np.empty(3)
    mujoco.mju_quat2Vel(vel, quat, 1.0)
    return vel


def mat_from_rotvec(vec: np.ndarray) -> np.ndarray:
    vec = np.asarray(vec, dtype=float)
    angle = float(np.linalg.norm(vec))
    quat = np.array([1.0, 0.0, 0.0, 0.0])
    if angle > 1e-12:
        mujoco.mju_axisAngle2Quat(quat, vec / angle, angle)
    mat = np.empty(9)
    mujoco.mju_quat2Mat(mat, quat)
    return mat.reshape(3, 3)


@functools.lru_cache(maxsize=1)
def load_model() -> mujoco.MjModel:
    """The arm alone (no scene), for kinematics. Cached: MjModel is read-only here."""
    return mujoco.MjModel.from_xml_path(str(ARM_XML))


def _check_q(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    if q.shape != (6,):
        raise ValueError(f"joint vector must have shape (6,) for {JOINT_NAMES}, got {q.shape}")
    if not np.all(np.isfinite(q)):
        raise ValueError(f"joint vector contains NaN or inf: {q}")
    return q


def clip_to_limits(q: np.ndarray) -> np.ndarray:
    return np.clip(q, JOINT_LIMITS[:, 0], JOINT_LIMITS[:, 1])


@dataclass
class IKConfig:
    """Damped least squares on MuJoCo's site Jacobian. ``rot_weight`` trades metres against radians."""

    damping: float = 1e-3
    rot_weight: float = 0.2
    max_step: float = 0.3  # rad per joint per iteration, keeps the linearisation valid
    iterations: int = 30
    pos_tol: float = 5e-4
    rot_tol: float = 5e-3


class Kinematics:
    """Forward kinematics and differential IK of the arm on its own MjData (one per thread)."""

    def __init__(self, model: mujoco.MjModel | None = None, config: IKConfig | None = None):
        self.model = model if model is not None else load_model()
        self.data = mujoco.MjData(self.model)
        self.config = config or IKConfig()
        self.qadr = np.array([self.model.jnt_qposadr[self.model.joint(n).id] for n in JOINT_NAMES])
        self.dofadr = np.array([self.model.jnt_dofadr[self.model.joint(n).id] for n in JOINT_NAMES])
        self.site = self.model.site(EE_SITE).id
        self._jacp = np.zeros((3, self.model.nv))
        self._jacr = np.zeros((3, self.model.nv))

    def _set(self, q: np.ndarray) -> None:
        self.data.qpos[self.qadr] = q
        mujoco.mj_kinematics(self.model, self.data)

    def fk_mat(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tool centre position (3,) and rotation matrix (3, 3) at joint angles ``q``."""
        self._set(_check_q(q))
        return self.data.site_xpos[self.site].copy(), self.data.site_xmat[self.site].reshape(3, 3).copy()

    def forward_kinematics(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pos, mat = self.fk_mat(q)
        return pos, mat_to_euler(mat)

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        """(6, 6) Jacobian of [tool velocity; angular velocity] (world frame) w.r.t. the arm joints."""
        self._set(_check_q(q))
        mujoco.mj_comPos(self.model, self.data)
        mujoco.mj_jacSite(self.model, self.data, self._jacp, self._jacr, self.site)
        return np.vstack([self._jacp[:, self.dofadr], self._jacr[:, self.dofadr]])

    def ik_step(self, q: np.ndarray, target_pos: np.ndarray, target_mat: np.ndarray) -> np.ndarray:
        """One damped-least-squares step towards the target pose; the result is inside the joint limits.

        Joints that would cross a limit are clamped and the step is re-solved without them, so the
        remaining joints still reduce the error instead of the clamp silently distorting the motion.
        """
        cfg = self.config
        q = _check_q(q)
        pos, mat = self.fk_mat(q)
        err = np.concatenate([target_pos - pos, cfg.rot_weight * rotvec_from_mat(target_mat @ mat.T)])
        jac = self.jacobian(q)
        jac[3:] *= cfg.rot_weight
        free = np.ones(6, bool)
        for _ in range(3):
            j = jac[:, free]
            dq_free = j.T @ np.linalg.solve(j @ j.T + cfg.damping * np.eye(6), err)
            dq = np.zeros(6)
            dq[free] = dq_free
            scale = np.max(np.abs(dq)) / cfg.max_step
            if scale > 1.0:
                dq /= scale
            q_new = q + dq
            hit = (q_new < JOINT_LIMITS[:, 0]) | (q_new > JOINT_LIMITS[:, 1])
            if not np.any(hit & free):
                return q_new
            free &= ~hit
            if not np.any(free):
                break
        return clip_to_limits(q_new)

    def pose_error(self, q: np.ndarray, target_pos: np.ndarray, target_mat: np.ndarray) -> tuple[float, float]:
        pos, mat = self.fk_mat(q)
        return float(np.linalg.norm(target_pos - pos)), float(np.linalg.norm(rotvec_from_mat(target_mat @ mat.T)))

    def solve_ik(
        self,
        target_pos: np.ndarray,
        target_euler: np.ndarray,
        q0: np.ndarray | None = None,
        iterations: int | None = None,
    ) -> tuple[np.ndarray, float, float]:
        """Iterate :meth:`ik_step` from ``q0``; returns (q, position error m, rotation error rad).

        An unreachable target gives the closest joint-limited configuration found, with its error, so the
        caller decides whether that is good enough (the env moves towards it; the robot refuses it).
        """
        target_pos = np.asarray(target_pos, dtype=float)
        target_mat = euler_to_mat(target_euler)
        if target_pos.shape != (3,) or not np.all(np.isfinite(target_pos)) or not np.all(np.isfinite(target_mat)):
            raise ValueError(f"IK target must be finite position (3,) and Euler (3,), got {target_pos}, {target_euler}")
        q = clip_to_limits(_check_q(q0 if q0 is not None else home_q()))
        cfg = self.config
        for _ in range(iterations or cfg.iterations):
            pos_err, rot_err = self.pose_error(q, target_pos, target_mat)
            if pos_err < cfg.pos_tol and rot_err < cfg.rot_tol:
                break
            q = self.ik_step(q, target_pos, target_mat)
        pos_err, rot_err = self.pose_error(q, target_pos, target_mat)
        return q, pos_err, rot_err


@functools.lru_cache(maxsize=1)
def _default() -> Kinematics:
    return Kinematics()


def forward_kinematics(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tool centre position (m) and Euler angles (rad) at joint angles ``q`` (6,)."""
    return _default().forward_kinematics(q)


def ik_step(q: np.ndarray, target_pos: np.ndarray, target_euler: np.ndarray) -> np.ndarray:
    """One joint-limited damped-least-squares step from ``q`` towards a pose."""
    return _default().ik_step(q, np.asarray(target_pos, float), euler_to_mat(target_euler))


def solve_ik(
    target_pos: np.ndarray, target_euler: np.ndarray, q0: np.ndarray | None = None
) -> tuple[np.ndarray, float, float]:
    """Joint angles reaching a pose from ``q0`` (default home): (q, position error, rotation error)."""
    return _default().solve_ik(target_pos, target_euler, q0)


@functools.lru_cache(maxsize=1)
def _home_q() -> tuple[float, ...]:
    guess = np.array([0.0, 0.4, 1.6, 0.0, 1.1, 0.0])
    q, pos_err, rot_err = _default().solve_ik(*HOME_POSE, q0=guess, iterations=200)
    if pos_err > 1e-3 or rot_err > 1e-2:
        raise RuntimeError(f"home pose unreachable (error {pos_err:.4f} m, {rot_err:.4f} rad): arm.xml changed?")
    return tuple(q)


def home_q() -> np.ndarray:
    """Joint angles of :data:`HOME_POSE` (elbow up, wrist below the elbow)."""
    return np.array(_home_q())
