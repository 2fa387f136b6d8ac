"""The arm's kinematic model: the MJCF agrees with the documented spec, IK reaches and respects limits."""

import numpy as np
import pytest

from pivla.envs.tabletop import arm


def test_mjcf_matches_documented_spec():
    model = arm.load_model()
    for name, (lo, hi) in zip(arm.JOINT_NAMES, arm.JOINT_LIMITS):
        assert np.allclose(model.jnt_range[model.joint(name).id], [lo, hi], atol=1e-4), name
        assert np.allclose(model.actuator_ctrlrange[model.actuator(name).id], [lo, hi], atol=1e-4), name
    pos, _ = arm.forward_kinematics(arm.ZERO_POSITION)
    assert np.allclose(pos, [0, 0, arm.LINK_LENGTHS["shoulder_height"] + arm.REACH], atol=1e-6)
    assert arm.REACH == pytest.approx(0.382)


def test_euler_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(50):
        e = rng.uniform([-3, -1.5, -3], [3, 1.5, 3])
        assert np.allclose(arm.mat_to_euler(arm.euler_to_mat(e)), e, atol=1e-9)
        assert np.allclose(arm.mat_from_rotvec(arm.rotvec_from_mat(arm.euler_to_mat(e))), arm.euler_to_mat(e), atol=1e-9)


def test_home_pose_is_top_down():
    pos, euler = arm.forward_kinematics(arm.home_q())
    assert np.allclose(pos, arm.HOME_POSE[0], atol=1e-3)
    assert np.allclose(euler, 0, atol=1e-2)


def test_ik_reaches_reachable_targets_within_limits():
    rng = np.random.default_rng(1)
    kin = arm.Kinematics()
    home = arm.home_q()
    for _ in range(40):
        q_true = arm.clip_to_limits(home + rng.uniform(-0.5, 0.5, 6))
        pos, euler = kin.forward_kinematics(q_true)
        q, pos_err, rot_err = kin.solve_ik(pos, euler, home, iterations=100)
        assert pos_err < 1e-3 and rot_err < 1e-2, (q_true, q, pos_err, rot_err)
        assert np.all(q >= arm.JOINT_LIMITS[:, 0]) and np.all(q <= arm.JOINT_LIMITS[:, 1])
        assert np.allclose(kin.forward_kinematics(q)[0], pos, atol=1e-3)


def test_ik_covers_the_tabletop_workspace_top_down():
    """Every grasp point of the task layouts (tool-centre radius 0.12-0.27 m) is reachable pointing down."""
    for x in (0.12, 0.18, 0.24, 0.27):
        for y in (-0.12, 0.0, 0.12):
            if np.hypot(x, y) > 0.27:
                continue
            yaw = np.arctan2(y, x)
            _, pos_err, rot_err = arm.solve_ik(np.array([x, y, 0.016]), np.array([0, 0, yaw]))
            assert pos_err < 1e-3 and rot_err < 1e-2, (x, y)


def test_ik_respects_joint_limits_on_unreachable_targets():
    rng = np.random.default_rng(2)
    q, pos_err, _ = arm.solve_ik(np.array([1.0, 0.0, 0.0]), np.zeros(3))
    assert pos_err > 0.4
    assert np.all(q >= arm.JOINT_LIMITS[:, 0] - 1e-12) and np.all(q <= arm.JOINT_LIMITS[:, 1] + 1e-12)
    for _ in range(30):
        q0 = rng.uniform(arm.JOINT_LIMITS[:, 0], arm.JOINT_LIMITS[:, 1])
        q1 = arm.ik_step(q0, rng.uniform(-0.5, 0.5, 3), rng.uniform(-3, 3, 3))
        assert np.all(q1 >= arm.JOINT_LIMITS[:, 0] - 1e-12) and np.all(q1 <= arm.JOINT_LIMITS[:, 1] + 1e-12)


def test_bad_joint_vectors_are_rejected():
    with pytest.raises(ValueError, match="shape"):
        arm.forward_kinematics(np.zeros(5))
    with pytest.raises(ValueError, match="NaN"):
        arm.forward_kinematics(np.array([0, 0, np.nan, 0, 0, 0]))
    with pytest.raises(ValueError, match="finite"):
        arm.solve_ik(np.array([np.nan, 0, 0]), np.zeros(3))
