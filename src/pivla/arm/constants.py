"""The low-cost arm's specification: one place for joint names, limits, zero positions and link lengths.

The arm is a ~$300 6-DOF hobby-servo arm (382 mm reach, 0.2 kg payload, 0.7 m/s, repeatability within
10 mm) with a parallel gripper. ``arm.xml`` next to this module is its MJCF; the simulated twin includes it
in its scene and the real arm's driver computes its kinematics from it (:mod:`pivla.arm.kinematics`).

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

from pathlib import Path

import numpy as np

ARM_XML = Path(__file__).with_name("arm.xml")

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

# The 7-D action convention the twin and the real arm share (docs/twin.md): one action per control period
# moves the commanded tool pose by at most TRANS_SCALE metres and ROT_SCALE radians per unit, and is turned
# into joint targets by IK_ITERATIONS joint-limited damped-least-squares steps.
CONTROL_HZ = 10
TRANS_SCALE = 0.02  # m per unit action per control step
ROT_SCALE = 0.15  # rad per unit action per control step
IK_ITERATIONS = 8
