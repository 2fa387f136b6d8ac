"""Calibration mapping and the safety layer every command passes."""

import json

import numpy as np
import pytest

from pivla import arm
from pivla.robot.calibration import ArmCalibration, CalibrationError
from pivla.robot.safety import SafetyConfig, SafetyError, SafetyLayer


@pytest.fixture(scope="module")
def calib():
    c = ArmCalibration.nominal()
    c.joints[2].direction = -1  # a reversed servo
    c.joints[2].zero_us = 1500 + c.joints[2].us_per_rad * 0.97
    c.validate()
    return c


@pytest.fixture(scope="module")
def safety(calib):
    return SafetyLayer(calib)


def test_pulse_mapping_round_trips(calib):
    rng = np.random.default_rng(0)
    lim = calib.limits_rad
    for _ in range(50):
        q = rng.uniform(lim[:, 0], lim[:, 1])
        opening = float(rng.uniform(0, 1))
        q2, o2 = calib.from_pulses(calib.to_pulses(q, opening))
        assert np.max(np.abs(q2 - q)) < 1.0 / calib.joints[0].us_per_rad
        assert abs(o2 - opening) < 0.01


def test_board_limits_bracket_the_joint_range(calib):
    """The board accepts every joint at either end of its calibrated range, refuses a pulse 0.02 rad beyond
    it, and spans the gripper from closed to open; home lies inside."""
    limits = calib.board_limits(arm.home_q())
    assert [lim.channel for lim in limits] == list(range(7))
    home = arm.home_q()
    for ch, (lo, hi) in enumerate(calib.limits_rad):
        lim = limits[ch]
        for angle, inside in ((lo, True), (hi, True), (lo - 0.02, False), (hi + 0.02, False)):
            pulse = calib.to_pulses(np.where(np.arange(6) == ch, angle, home), 1.0)[ch]
            assert (lim.min_us <= pulse <= lim.max_us) == inside, (ch, angle, pulse, lim)
        assert lim.min_us < lim.home_us < lim.max_us
    gripper = limits[6]
    assert (gripper.min_us, gripper.max_us) == tuple(sorted(calib.to_pulses(home, o)[6] for o in (0.0, 1.0)))
    assert gripper.min_us <= gripper.home_us <= gripper.max_us
    # reversed joint: its max angle maps to the lower pulse
    assert calib.to_pulses(calib.limits_rad[:, 1], 1.0)[2] < calib.to_pulses(calib.limits_rad[:, 0], 1.0)[2]


def test_calibration_file_round_trip_and_errors(calib, tmp_path):
    path = calib.save(tmp_path / "arm.json")
    again = ArmCalibration.load(path)
    assert again.joints == calib.joints and again.gripper == calib.gripper
    doc = json.loads(path.read_text())
    doc["joints"][1]["max_rad"] = 3.0  # beyond the model's limit
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    with pytest.raises(CalibrationError, match="shoulder_pitch"):
        ArmCalibration.load(tmp_path / "bad.json")
    (tmp_path / "broken.json").write_text("{not json")
    with pytest.raises(CalibrationError, match="not valid JSON"):
        ArmCalibration.load(tmp_path / "broken.json")
    with pytest.raises(CalibrationError, match="not found"):
        ArmCalibration.load(tmp_path / "missing.json")


def test_safety_accepts_home_and_reports_speed(safety, calib):
    cmd = safety.check(arm.home_q(), 1.0, arm.home_q())
    assert np.allclose(cmd.q, arm.home_q())
    assert cmd.speed_us_s == int(safety.config.max_joint_speed * calib.joints[0].us_per_rad)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_safety_refuses_non_finite(safety, bad):
    q = arm.home_q()
    q[3] = bad
    with pytest.raises(SafetyError, match="non-finite"):
        safety.check(q, 1.0)
    with pytest.raises(SafetyError, match="non-finite"):
        safety.check(arm.home_q(), bad)


def test_safety_refuses_joint_limits_and_shape(safety, calib):
    q = arm.home_q()
    q[0] = calib.limits_rad[0, 1] + 0.1
    with pytest.raises(SafetyError, match="base_yaw"):
        safety.check(q, 1.0)
    with pytest.raises(SafetyError, match="shape"):
        safety.check(np.zeros(5), 1.0)
    with pytest.raises(SafetyError, match="gripper"):
        safety.check(arm.home_q(), 1.5)


def test_safety_refuses_leaving_the_workspace(calib):
    layer = SafetyLayer(calib, SafetyConfig(workspace_max=(0.40, 0.35, 0.30)))
    q_up = np.zeros(6)
    q_up[2] = 0.05  # nearly straight up: tool centre ~0.45 m high
    with pytest.raises(SafetyError, match="workspace"):
        layer.check(q_up, 1.0)
    # into the table
    pos, ori = arm.forward_kinematics(arm.home_q())
    q_low, _, _ = arm.solve_ik(pos - np.array([0, 0, 0.16]), ori, arm.home_q())
    with pytest.raises(SafetyError, match="workspace"):
        layer.check(q_low, 1.0)


def test_safety_bounds_single_step(safety):
    q = arm.home_q()
    far = q.copy()
    far[0] += 0.8
    with pytest.raises(SafetyError, match="jump"):
        safety.check(far, 1.0, q)
    assert safety.check(far, 1.0, q, max_step_rad=None).q[0] == pytest.approx(far[0])


def test_kinematics_round_trip_through_calibrated_pulses(calib):
    """EE pose -> IK -> pulses -> joints -> FK returns the pose within a pulse's resolution."""
    kin = arm.Kinematics()
    rng = np.random.default_rng(1)
    for _ in range(10):
        q_true = np.clip(arm.home_q() + rng.uniform(-0.3, 0.3, 6), *(calib.limits_rad - [-0.1, 0.1]).T)
        target, ori = kin.forward_kinematics(q_true)
        # differential IK from a nearby configuration, as the env adapter uses it
        q, pos_err, _ = kin.solve_ik(target, ori, q_true + rng.uniform(-0.05, 0.05, 6), iterations=100)
        assert pos_err < 1e-3
        q2, _ = calib.from_pulses(calib.to_pulses(q, 1.0))
        pos2, _ = kin.forward_kinematics(q2)
        assert np.linalg.norm(pos2 - target) < 4e-3
