"""Rotations: Euler angles, rotation matrices, axis-angle vectors and unit quaternions (w, x, y, z).

The float helpers (``mul_quat`` ... ``quat_to_rotvec``) repeat MuJoCo's arithmetic operation by operation on
Python floats, including how its build groups the sums it vectorises (pairwise in quaternion products, norms
and quat -> matrix: as measured against mujoco 4.0.0): the same IEEE double operations in the same order give
the same bits, so nothing downstream of the kinematics (the twin's IK, its episodes) depends on which
implementation ran.
"""

from __future__ import annotations

import math

import numpy as np

Vec3 = tuple[float, ...]  # 3 floats
Quat = tuple[float, ...]  # 4 floats, (w, x, y, z)
Mat9 = tuple[float, ...]  # a 3x3 matrix, row-major

MINVAL = 1e-15  # MuJoCo's mjMINVAL: its engine's threshold for normalising vectors
UNIT_QUAT: Quat = (1.0, 0.0, 0.0, 0.0)
IDENTITY: Mat9 = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)


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


def mul_quat(a: Quat, b: Quat) -> Quat:
    a0, a1, a2, a3 = a
    b0, b1, b2, b3 = b
    return (
        (a0 * b0 - a1 * b1) + (-(a2 * b2) - a3 * b3),
        (a0 * b1 + a1 * b0) + (a2 * b3 - a3 * b2),
        (a0 * b2 - a1 * b3) + (a2 * b0 + a3 * b1),
        (a0 * b3 + a1 * b2) + (a3 * b0 - a2 * b1),
    )


def rot_vec_quat(v: Vec3, q: Quat) -> Vec3:
    if q[0] == 1 and q[1] == 0 and q[2] == 0 and q[3] == 0:
        return v
    q0, q1, q2, q3 = q
    v0, v1, v2 = v
    t0 = q0 * v0 + q2 * v2 - q3 * v1
    t1 = q0 * v1 + q3 * v0 - q1 * v2
    t2 = q0 * v2 + q1 * v1 - q2 * v0
    return (
        v0 + 2 * (q2 * t2 - q3 * t1),
        v1 + 2 * (q3 * t0 - q1 * t2),
        v2 + 2 * (q1 * t1 - q2 * t0),
    )


def mat_vec(m: Mat9, v: Vec3) -> Vec3:
    v0, v1, v2 = v
    return (
        m[0] * v0 + m[1] * v1 + m[2] * v2,
        m[3] * v0 + m[4] * v1 + m[5] * v2,
        m[6] * v0 + m[7] * v1 + m[8] * v2,
    )


def add(a: Vec3, b: Vec3) -> Vec3:
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


def sub(a: Vec3, b: Vec3) -> Vec3:
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def cross(a: Vec3, b: Vec3) -> Vec3:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def normalize4(q: Quat) -> Quat:
    norm = math.sqrt((q[0] * q[0] + q[1] * q[1]) + (q[2] * q[2] + q[3] * q[3]))
    if norm < MINVAL:
        return UNIT_QUAT
    if abs(norm - 1) > MINVAL:
        inv = 1 / norm
        return (q[0] * inv, q[1] * inv, q[2] * inv, q[3] * inv)
    return q


def axis_angle_quat(axis: Vec3, angle: float) -> Quat:
    if angle == 0:
        return UNIT_QUAT
    s = math.sin(angle * 0.5)
    return (math.cos(angle * 0.5), axis[0] * s, axis[1] * s, axis[2] * s)


def quat_to_mat(q: Quat) -> Mat9:
    if q[0] == 1 and q[1] == 0 and q[2] == 0 and q[3] == 0:
        return IDENTITY
    q00, q01, q02, q03 = q[0] * q[0], q[0] * q[1], q[0] * q[2], q[0] * q[3]
    q11, q12, q13 = q[1] * q[1], q[1] * q[2], q[1] * q[3]
    q22, q23, q33 = q[2] * q[2], q[2] * q[3], q[3] * q[3]
    return (
        (q00 - q22) + (q11 - q33), 2 * (q12 - q03), 2 * (q13 + q02),
        2 * (q12 + q03), (q00 + q22) - (q11 + q33), 2 * (q23 - q01),
        2 * (q13 - q02), 2 * (q23 + q01), (q00 - q22) - (q11 - q33),
    )  # fmt: skip


def mat_to_quat(m: Mat9) -> Quat:
    if m[0] + m[4] + m[8] > 0:
        w = 0.5 * math.sqrt(1 + m[0] + m[4] + m[8])
        q = (w, 0.25 * (m[7] - m[5]) / w, 0.25 * (m[2] - m[6]) / w, 0.25 * (m[3] - m[1]) / w)
    elif m[0] > m[4] and m[0] > m[8]:
        x = 0.5 * math.sqrt(1 + m[0] - m[4] - m[8])
        q = (0.25 * (m[7] - m[5]) / x, x, 0.25 * (m[1] + m[3]) / x, 0.25 * (m[2] + m[6]) / x)
    elif m[4] > m[8]:
        y = 0.5 * math.sqrt(1 - m[0] + m[4] - m[8])
        q = (0.25 * (m[2] - m[6]) / y, 0.25 * (m[1] + m[3]) / y, y, 0.25 * (m[5] + m[7]) / y)
    else:
        z = 0.5 * math.sqrt(1 - m[0] - m[4] + m[8])
        q = (0.25 * (m[3] - m[1]) / z, 0.25 * (m[2] + m[6]) / z, 0.25 * (m[5] + m[7]) / z, z)
    return normalize4(q)


def quat_to_rotvec(q: Quat) -> Vec3:
    """Axis * angle of a unit quaternion, the shorter way round (MuJoCo's ``mju_quat2Vel`` at dt = 1)."""
    x, y, z = q[1], q[2], q[3]
    sin_half = math.sqrt(x * x + y * y + z * z)
    if sin_half < MINVAL:
        x, y, z = 1.0, 0.0, 0.0
    else:
        inv = 1 / sin_half
        x, y, z = x * inv, y * inv, z * inv
    angle = 2 * math.atan2(sin_half, q[0])
    if angle > math.pi:
        angle -= 2 * math.pi
    return (x * angle, y * angle, z * angle)


def flat_mat(mat: np.ndarray) -> Mat9:
    flat = np.asarray(mat, dtype=float).reshape(9)
    return tuple(flat.tolist())


def rotvec_from_mat(mat: np.ndarray) -> np.ndarray:
    """Axis * angle (3,) of a rotation matrix, angle in [-pi, pi]."""
    return np.array(quat_to_rotvec(mat_to_quat(flat_mat(mat))))


def mat_from_rotvec(vec: np.ndarray) -> np.ndarray:
    """Rotation matrix of an axis * angle vector (Rodrigues' rotation, through the unit quaternion)."""
    vec = np.asarray(vec, dtype=float)
    angle = float(np.linalg.norm(vec))
    quat = UNIT_QUAT
    if angle > 1e-12:
        quat = axis_angle_quat(tuple((vec / angle).tolist()), angle)
    return np.array(quat_to_mat(quat)).reshape(3, 3)


def yaw_of_quat(quat: np.ndarray) -> float:
    """The rotation about z (rad) of a unit quaternion (w, x, y, z): a body's heading on the table."""
    w, x, y, z = quat
    return float(np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))


def wrap_angle(angle: float, period: float = 2 * math.pi) -> float:
    """``angle`` taken to [-period / 2, period / 2): the same direction for a shape that repeats every ``period``."""
    return float((angle + period / 2) % period - period / 2)

