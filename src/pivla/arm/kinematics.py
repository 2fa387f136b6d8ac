"""The arm's forward kinematics, site Jacobian and differential IK, on the model :mod:`pivla.arm.mjcf` reads.

The kinematics need neither MuJoCo nor torch (a robot laptop's client-only install runs them): they chain
the MJCF's transforms themselves. Every step follows the operation order of MuJoCo's ``mj_kinematics``,
``mj_comPos`` and ``mj_jacSite`` and its quaternion helpers, so positions, rotations and Jacobians are
bit-identical to MuJoCo's: the twin's IK, and with it the twin's episodes, are the same as when this module
called MuJoCo (tests/test_tabletop_arm.py compares the two). The price is speed: one forward-kinematics pass
costs ~50 us of Python against ~10 us in MuJoCo.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from pivla.arm.constants import EE_SITE, HOME_POSE, JOINT_LIMITS, JOINT_NAMES
from pivla.arm.mjcf import ArmModel, load_model
from pivla.arm.rotations import (
    IDENTITY,
    MINVAL,
    UNIT_QUAT,
    Mat9,
    Quat,
    Vec3,
    add,
    axis_angle_quat,
    cross,
    euler_to_mat,
    mat_to_euler,
    mat_vec,
    mul_quat,
    normalize4,
    quat_to_mat,
    rot_vec_quat,
    rotvec_from_mat,
    sub,
)


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
    """Damped least squares on the site Jacobian. ``rot_weight`` trades metres against radians."""

    damping: float = 1e-3
    rot_weight: float = 0.2
    max_step: float = 0.3  # rad per joint per iteration, keeps the linearisation valid
    iterations: int = 30
    pos_tol: float = 5e-4
    rot_tol: float = 5e-3


@dataclass
class _Pose:
    """One forward-kinematics pass: what the site pose and its Jacobian are computed from."""

    xpos: list[Vec3]
    xquat: list[Quat]
    xmat: list[Mat9]
    axes: dict[str, tuple[Vec3, Vec3]]  # joint name -> (world axis, world anchor)
    site_pos: Vec3
    site_mat: Mat9


class Kinematics:
    """Forward kinematics and differential IK of the arm (one instance per thread: it caches the last pose)."""

    def __init__(self, model: ArmModel | None = None, config: IKConfig | None = None):
        self.model = model if model is not None else load_model()
        self.config = config or IKConfig()
        self.site = self.model.site(EE_SITE)
        self._index = {name: i for i, name in enumerate(JOINT_NAMES)}
        chain, body = set(), self.site.body
        while body > 0:
            chain.add(body)
            body = self.model.bodies[body].parent
        # (column, joint name, hinge?) of the arm joints that move the site; the others' columns stay zero
        self._dofs = [(self._index[name], name, self.model.joint(name)[1].kind == "hinge")
                      for name in JOINT_NAMES if self.model.joint(name)[0] in chain]
        self._root = self.model.root(self.site.body)
        # per body: its joints with their index in q (-1: held at ref) and whether the anchor is the origin
        self._plan = [(body, [(j, self._index.get(j.name, -1), all(math.copysign(1.0, v) > 0 and v == 0 for v in j.pos))
                              for j in body.joints]) for body in self.model.bodies[1:]]
        self._key: bytes | None = None
        self._pose: _Pose | None = None

    def _forward(self, q: np.ndarray) -> _Pose:
        """``mj_kinematics`` on the arm's tree: arm joints at ``q``, every other joint at its ``ref``."""
        key = q.tobytes()
        if key == self._key and self._pose is not None:
            return self._pose
        values = q.tolist()
        xpos: list[Vec3] = [(0.0, 0.0, 0.0)]
        xquat: list[Quat] = [UNIT_QUAT]
        xmat: list[Mat9] = [IDENTITY]
        axes: dict[str, tuple[Vec3, Vec3]] = {}
        for body, joints in self._plan:
            p = body.parent
            if p:
                pos = add(mat_vec(xmat[p], body.pos), xpos[p])
                quat = mul_quat(xquat[p], body.quat)
            else:
                pos, quat = body.pos, body.quat
            for joint, i, centred in joints:
                value = (values[i] if i >= 0 else joint.ref) - joint.ref
                axis = rot_vec_quat(joint.axis, quat)
                if centred:  # an anchor at +0 rotates to +0 (bit for bit), so only the addition is left to do
                    anchor = (pos[0] + 0.0, pos[1] + 0.0, pos[2] + 0.0)
                else:
                    anchor = add(rot_vec_quat(joint.pos, quat), pos)
                if joint.kind == "slide":
                    pos = (pos[0] + axis[0] * value, pos[1] + axis[1] * value, pos[2] + axis[2] * value)
                else:
                    quat = mul_quat(quat, axis_angle_quat(joint.axis, value))
                    pos = anchor if centred else sub(anchor, rot_vec_quat(joint.pos, quat))
                axes[joint.name] = (axis, anchor)
            quat = normalize4(quat)
            xpos.append(pos)
            xquat.append(quat)
            xmat.append(quat_to_mat(quat))
        s = self.site
        site_pos = add(mat_vec(xmat[s.body], s.pos), xpos[s.body])
        site_mat = quat_to_mat(mul_quat(xquat[s.body], s.quat))
        self._key, self._pose = key, _Pose(xpos, xquat, xmat, axes, site_pos, site_mat)
        return self._pose

    def fk_mat(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tool centre position (3,) and rotation matrix (3, 3) at joint angles ``q``."""
        pose = self._forward(_check_q(q))
        return np.array(pose.site_pos), np.array(pose.site_mat).reshape(3, 3)

    def forward_kinematics(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pos, mat = self.fk_mat(q)
        return pos, mat_to_euler(mat)

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        """(6, 6) Jacobian of [tool velocity; angular velocity] (world frame) w.r.t. the arm joints.

        Computed like ``mj_comPos`` + ``mj_jacSite``: each hinge's motion about the root's subtree centre of
        mass, shifted to the site. Mathematically the centre of mass cancels; it is kept so the rounding,
        and so every IK step, matches MuJoCo's."""
        pose = self._forward(_check_q(q))
        bodies = self.model.bodies
        com = [[0.0, 0.0, 0.0]]
        for b in range(1, len(bodies)):
            body, m, x = bodies[b], pose.xmat[b], pose.xpos[b]
            ip, mass = body.ipos, body.mass
            com.append([
                (m[0] * ip[0] + m[1] * ip[1] + m[2] * ip[2] + x[0]) * mass,
                (m[3] * ip[0] + m[4] * ip[1] + m[5] * ip[2] + x[1]) * mass,
                (m[6] * ip[0] + m[7] * ip[1] + m[8] * ip[2] + x[2]) * mass,
            ])
        for b in range(len(bodies) - 1, 0, -1):
            parent, child = com[bodies[b].parent], com[b]
            parent[0] += child[0]
            parent[1] += child[1]
            parent[2] += child[2]
        r = self._root
        if self.model.subtree_mass[r] < MINVAL:
            root_com = add(mat_vec(pose.xmat[r], bodies[r].ipos), pose.xpos[r])
        else:
            inv = 1.0 / self.model.subtree_mass[r]
            root_com = (com[r][0] * inv, com[r][1] * inv, com[r][2] * inv)
        offset = sub(pose.site_pos, root_com)
        cols = [(0.0,) * 6] * 6
        for col, name, hinge in self._dofs:
            axis, anchor = pose.axes[name]
            if hinge:
                lin = cross(axis, sub(root_com, anchor))
                turn = cross(axis, offset)
                cols[col] = (lin[0] + turn[0], lin[1] + turn[1], lin[2] + turn[2], *axis)
            else:
                cols[col] = (*axis, 0.0, 0.0, 0.0)
        return np.array(cols).T.copy()

    def ik_step(self, q: np.ndarray, target_pos: np.ndarray, target_mat: np.ndarray) -> np.ndarray:
        """One damped-least-squares step towards the target pose (a rotation matrix: :func:`euler_to_mat` makes
        one from Euler angles); the result is inside the joint limits.

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
