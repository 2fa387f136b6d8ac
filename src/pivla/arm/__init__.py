"""The low-cost arm that the simulated twin (:mod:`pivla.envs.tabletop`) and the real arm (:mod:`pivla.robot`)
share, without MuJoCo or torch (a robot laptop's client-only install runs it):

- :mod:`pivla.arm.constants`: the specification: joint names, limits, zero and home positions, link lengths,
  the 7-D action convention, and ``arm.xml`` (the arm's MJCF);
- :mod:`pivla.arm.rotations`: Euler angles, rotation matrices, axis-angle vectors and quaternions;
- :mod:`pivla.arm.mjcf`: reading an MJCF's body tree (:func:`read_mjcf`) and the arm's (:func:`load_model`);
- :mod:`pivla.arm.kinematics`: forward kinematics, the site Jacobian and IK, bit-identical to MuJoCo's.
"""

from pivla.arm.constants import (
    ARM_XML,
    CONTROL_HZ,
    EE_SITE,
    GRIPPER_JOINTS,
    GRIPPER_OPEN,
    HOME_POSE,
    IK_ITERATIONS,
    JOINT_LIMITS,
    JOINT_NAMES,
    LINK_LENGTHS,
    REACH,
    ROT_SCALE,
    TRANS_SCALE,
    ZERO_POSITION,
)
from pivla.arm.kinematics import IKConfig, Kinematics, clip_to_limits, forward_kinematics, home_q, solve_ik
from pivla.arm.mjcf import ArmModel, Body, Joint, MjcfError, Site, load_model, read_mjcf
from pivla.arm.rotations import euler_to_mat, mat_from_rotvec, mat_to_euler, rotvec_from_mat

__all__ = [
    "ARM_XML", "CONTROL_HZ", "EE_SITE", "GRIPPER_JOINTS", "GRIPPER_OPEN", "HOME_POSE", "IK_ITERATIONS", "JOINT_LIMITS",
    "JOINT_NAMES", "LINK_LENGTHS", "REACH", "ROT_SCALE", "TRANS_SCALE", "ZERO_POSITION", "ArmModel", "Body",
    "IKConfig", "Joint", "Kinematics", "MjcfError", "Site", "clip_to_limits", "euler_to_mat", "forward_kinematics",
    "home_q", "load_model", "mat_from_rotvec", "mat_to_euler", "read_mjcf", "rotvec_from_mat", "solve_ik",
]
