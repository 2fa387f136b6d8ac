"""The SO-101 arm over the simulated Feetech bus: LeRobot calibration files, goals guarded before the bus, faults
named and held, the watchdog, and the ``check`` / ``find-port`` commands end to end."""

import json
import subprocess
import sys
import time

import numpy as np
import pytest

from pivla.cli import main
from pivla.robot import feetech as F
from pivla.robot.calibration import CalibrationError
from pivla.robot.safety import SafetyError
from pivla.robot.simbus import SimBus, SimBusConfig
from pivla.robot.so101 import (
    MOTORS,
    SO101,
    ArmHeld,
    MotorCalibration,
    SO101Calibration,
    SO101Config,
)

# a calibrated arm: per motor (homing offset, range_min, range_max), as lerobot-calibrate leaves them
CALIBRATION = {"shoulder_pan": (-30, 1000, 3000), "shoulder_lift": (12, 800, 3300), "elbow_flex": (0, 900, 3100),
               "wrist_flex": (-7, 850, 3200), "wrist_roll": (0, 0, 4095), "gripper": (25, 2000, 3400)}


def calibration(arm_id: str = "follower") -> SO101Calibration:
    return SO101Calibration(arm_id,
                            {name: MotorCalibration(i, 0, *CALIBRATION[name]) for i, name in enumerate(MOTORS, 1)})


def calibrated_sim(speed: float = 3000.0) -> SimBus:
    """A simulated bus whose servos hold CALIBRATION, each standing in the middle of its range."""
    sim = SimBus(SimBusConfig(speed_ticks_s=speed))
    for sid, (offset, lo, hi) in enumerate(CALIBRATION.values(), 1):
        sim.set_register(sid, F.HOMING_OFFSET, offset)
        sim.set_register(sid, F.MIN_ANGLE_LIMIT, lo)
        sim.set_register(sid, F.MAX_ANGLE_LIMIT, hi)
        sim.set_position(sid, (lo + hi) // 2)
    return sim


@pytest.fixture
def sim():
    with calibrated_sim() as s:
        yield s


def open_arm(sim: SimBus, **config) -> SO101:
    return SO101.open(F.BusConfig(sim.port, reply_timeout_ms=50.0), calibration(), SO101Config(**config))


def goals_received(sim: SimBus) -> list[dict[int, int]]:
    """Every goal-position sync write the bus carried, decoded from the bytes it received."""
    out = []
    for p in F.PacketReader().feed(bytes(sim.received)):
        if p.code == F.Instr.SYNC_WRITE and p.params[0] == F.GOAL_POSITION.address:
            body = p.params[2:]
            out.append({body[i]: int.from_bytes(body[i + 1 : i + 3], "little") for i in range(0, len(body), 3)})
    return out


def wait_for(condition, timeout_s: float = 3.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


# ------------------------------------------------------------------------------------------ calibration
def test_calibration_file_is_lerobots_layout(tmp_path):
    path = calibration().save(tmp_path / "follower.json")
    doc = json.loads(path.read_text())
    assert list(doc) == list(MOTORS)
    assert doc["elbow_flex"] == {"id": 3, "drive_mode": 0, "homing_offset": 0, "range_min": 900, "range_max": 3100}
    again = SO101Calibration.load(path, arm_id="follower")
    assert again == calibration()


def test_units_are_lerobots_degrees_and_gripper_percent():
    calib = calibration()
    ticks = np.array([3000, 2050, 2000, 850, 0, 2700])
    v = calib.to_units(ticks)
    assert v[0] == pytest.approx((3000 - 2000) * 360 / 4095) and v[1] == pytest.approx(0.0)
    assert v[5] == pytest.approx(50.0)
    assert np.array_equal(calib.to_ticks(v), ticks)
    lower, upper = calib.limits()
    assert upper[0] == pytest.approx(-lower[0]) and (lower[5], upper[5]) == (0.0, 100.0)
    calib.motors["gripper"].drive_mode = 1  # a reversed gripper: 0 is range_max
    assert calib.to_units(ticks)[5] == pytest.approx(50.0) and calib.to_ticks([0, 0, 0, 0, 0, 0])[5] == 3400


def test_calibration_of_another_arm_or_servo_count_is_refused(tmp_path):
    path = calibration().save(tmp_path / "follower.json")
    with pytest.raises(CalibrationError, match="calibration of arm 'follower', not of arm 'leader'"):
        SO101Calibration.load(path, arm_id="leader")
    doc = json.loads(path.read_text())
    five = {k: v for k, v in doc.items() if k != "gripper"}
    (tmp_path / "five.json").write_text(json.dumps(five))
    with pytest.raises(CalibrationError, match=r"has 5 motors \(missing: gripper; unknown: none\); the SO-101 has 6"):
        SO101Calibration.load(tmp_path / "five.json")
    (tmp_path / "seven.json").write_text(json.dumps({**doc, "wrist_yaw": doc["wrist_roll"]}))
    with pytest.raises(CalibrationError, match="has 7 motors .*unknown: wrist_yaw"):
        SO101Calibration.load(tmp_path / "seven.json")
    doc["elbow_flex"]["id"] = 7
    (tmp_path / "ids.json").write_text(json.dumps(doc))
    with pytest.raises(CalibrationError, match="motor elbow_flex has id 7, the SO-101's elbow_flex is servo 3"):
        SO101Calibration.load(tmp_path / "ids.json")


def test_a_file_that_differs_from_the_servos_is_refused_at_connect(sim):
    other = calibration("other-arm")
    other.motors["wrist_flex"].homing_offset = 40
    with pytest.raises(CalibrationError, match=r"arm 'other-arm' does not match the servos .*wrist_flex "
                                               r"\(servo: offset -7, range 850..3200; file: offset 40"):
        SO101.open(F.BusConfig(sim.port, reply_timeout_ms=50.0), other)


# ------------------------------------------------------------------------------------------ safety
def test_goals_are_clipped_to_the_calibrated_range_before_the_bus(sim):
    with open_arm(sim, max_step_deg=1e4, max_gripper_step=1e4) as arm:
        arm.enable()
        sent = arm.command([500.0, -500.0, 0.0, 0.0, 0.0, 150.0])
        lower, upper = arm.calibration.limits()
        assert sent[0] == pytest.approx(upper[0]) and sent[1] == pytest.approx(lower[1]) and sent[5] == 100.0
        arm.read()  # a round trip: the simulated bus has taken in the goal
    writes = goals_received(sim)
    assert writes[-1][1] == 3000 and writes[-1][2] == 800 and writes[-1][6] == 3400
    for goals in writes:
        for sid, (_, lo, hi) in enumerate(CALIBRATION.values(), 1):
            assert lo <= goals[sid] <= hi, (sid, goals[sid])
    unclipped = round(500 * 4095 / 360 + 2000)  # what shoulder_pan's goal would have been
    assert bytes([1]) + unclipped.to_bytes(2, "little") not in bytes(sim.received)


def test_refused_goals_never_reach_the_bus(sim):
    with open_arm(sim, on_limit="refuse", on_step="refuse") as arm:
        arm.enable()
        arm.read()
        before = len(goals_received(sim))
        with pytest.raises(SafetyError, match=r"joint shoulder_pan target 500.000 deg outside its limits"):
            arm.command([500.0, 0, 0, 0, 0, 50])
        with pytest.raises(SafetyError, match="non-finite"):
            arm.command([0, np.nan, 0, 0, 0, 50])
        with pytest.raises(SafetyError, match=r"joint elbow_flex would jump 30.000 deg in one command \(max 10.000\)"):
            arm.command(arm.read() + [0, 0, 30, 0, 0, 0])
        arm.read()
        assert len(goals_received(sim)) == before


def test_step_is_capped_per_command(sim):
    with open_arm(sim) as arm:
        arm.enable()
        start = arm.read()
        sent = arm.command(start + [40, 0, -40, 0, 0, 60])
        assert sent - start == pytest.approx([10, 0, -10, 0, 0, 25])
        assert arm.command(start + [40, 0, -40, 0, 0, 60]) - start == pytest.approx([20, 0, -20, 0, 0, 50])


# ------------------------------------------------------------------------------------------ faults
@pytest.mark.parametrize("fault, words", [
    ("mute", "servo 3 (elbow_flex) did not answer"),
    ("corrupt", "servo 3 (elbow_flex): reply to SYNC_READ present_position failed its checksum"),
    ("garbage", "servo 1 (shoulder_pan): 5 bytes of garbage on the bus"),
])
def test_each_fault_is_named_and_the_arm_holds(sim, fault, words):
    with open_arm(sim, watchdog_s=0.0) as arm:
        arm.enable()
        arm.read()  # a round trip: the simulated bus has taken in everything sent before it
        before, sent = sim.positions(), len(goals_received(sim))
        if fault == "garbage":
            sim.inject_garbage()
        else:
            getattr(sim, fault)(3)
        with pytest.raises(F.BusError, match=words.replace("(", r"\(").replace(")", r"\)")):
            arm.read()
        assert arm.held
        wait_for(lambda: len(goals_received(sim)) > sent, 1.0)
        assert goals_received(sim)[sent:] == [before]  # one more goal: where it stands
        with pytest.raises(ArmHeld, match="is held after: " + words.replace("(", r"\(").replace(")", r"\)")):
            arm.command(arm.calibration.to_units(list(before.values())))
        sim.mute(3, False)
        sim.corrupt(3, False)
        arm.resume()
        assert not arm.held
        arm.command(arm.read() + [5, 0, 0, 0, 0, 0])


def test_watchdog_holds_when_a_servo_stops_answering(sim):
    sim.config.speed_ticks_s = 100.0  # 10 degrees (114 ticks) take about 1.1 s
    with open_arm(sim, watchdog_s=0.05) as arm:
        arm.enable()
        start = sim.positions()
        arm.command(arm.read() + [10, 10, 0, 0, 0, 0])
        time.sleep(0.15)
        sim.mute(4)  # nobody commands the arm now: only the watchdog can notice
        wait_for(lambda: arm.held)
        assert isinstance(arm.fault, F.NoReply) and "servo 4 (wrist_flex)" in str(arm.fault)
        time.sleep(0.8)
        stopped = sim.positions()
        assert start[1] < stopped[1] < start[1] + 100  # held part way, not carried on to the goal (+114)
        time.sleep(0.2)
        assert sim.positions() == stopped


def test_watchdog_holds_when_the_link_drops(sim):
    with open_arm(sim, watchdog_s=0.05) as arm:
        arm.enable()
        sim.unplug()
        wait_for(lambda: arm.held)
        assert isinstance(arm.fault, F.PortError)
        with pytest.raises(ArmHeld, match="serial port .* failed"):
            arm.command(np.zeros(6))


def test_watchdog_can_release_torque_instead(sim):
    with open_arm(sim, watchdog_s=0.05, on_fault="release") as arm:
        arm.enable()
        arm.read()
        assert sim.register(1, F.TORQUE_ENABLE) == 1
        sim.mute(6)
        wait_for(lambda: arm.held)
        wait_for(lambda: [sim.register(sid, F.TORQUE_ENABLE) for sid in range(1, 6)] == [0] * 5, 1.0)
        with pytest.raises(ArmHeld, match=r"is released after: servo 6 \(gripper\)"):
            arm.command(np.zeros(6))


# ------------------------------------------------------------------------------------------ commands
def test_check_prints_the_six_joint_positions(sim, tmp_path, capsys):
    path = calibration().save(tmp_path / "follower.json")
    sim.set_position(1, 3000)
    assert main(["robot", "check", "--robot", "so101", "--port", sim.port, "--calibration", str(path)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in lines] == list(MOTORS)
    assert lines[0].split()[-2:] == [f"{1000 * 360 / 4095:.2f}", "deg"] and lines[5].split()[-2:] == ["50.00", "%"]
    assert sim.register(1, F.TORQUE_ENABLE) == 0  # check only reads


def test_check_finds_the_calibration_in_lerobots_folder(sim, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("HF_LEROBOT_CALIBRATION", str(tmp_path))
    calibration().save(tmp_path / "robots" / "so101_follower" / "follower.json")
    assert main(["robot", "check", "--robot", "so101", "--port", sim.port, "--arm-id", "follower"]) == 0
    assert capsys.readouterr().out.splitlines()[5].endswith("50.00 %")
    with pytest.raises(SystemExit, match="calibration file not found: .*leader.json"):
        main(["robot", "check", "--robot", "so101", "--port", sim.port, "--arm-id", "leader"])


def test_check_without_an_arm_exits_with_one_line(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "pivla", "robot", "check", "--robot", "so101", "--port",
                           str(tmp_path / "ttyNone")], capture_output=True, text=True, timeout=60, check=False)
    assert proc.returncode != 0 and proc.stdout == ""
    assert proc.stderr.strip().count("\n") == 0 and proc.stderr.startswith("no SO-101 answers on ")
    with SimBus() as silent:
        for sid in silent.servos:
            silent.mute(sid)
        with pytest.raises(SystemExit, match=r"no SO-101 answers on .*: servo 1 \(shoulder_pan\) did not answer PING"):
            main(["robot", "check", "--robot", "so101", "--port", silent.port])


def test_check_of_the_pivla_arm_is_unchanged(capsys):
    from pivla.robot.fakeboard import FakeBoard

    with FakeBoard() as fake:
        assert main(["robot", "check", "--port", fake.port]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["info"]["channels"] == 7 and len(report["limits"]) == 7


def test_find_port_names_the_port_that_went_away(monkeypatch, capsys):
    from pivla.robot import ports

    listings = iter([["/dev/ttyACM0", "/dev/ttyUSB0"], ["/dev/ttyUSB0"]])
    monkeypatch.setattr(ports, "list_ports", lambda: next(listings))
    monkeypatch.setattr("builtins.input", lambda prompt: "")
    assert main(["robot", "find-port", "--settle-s", "0"]) == 0
    assert "the arm's port is /dev/ttyACM0" in capsys.readouterr().out
    monkeypatch.setattr(ports, "list_ports", lambda: ["/dev/ttyUSB0"])
    with pytest.raises(SystemExit, match="no port went away"):
        main(["robot", "find-port", "--settle-s", "0"])


def test_bench_times_sync_read_and_write_on_the_simulated_bus():
    from pivla.bench.robot import RobotBenchConfig, run_robot_bench

    out = run_robot_bench(RobotBenchConfig(robot="so101", n=30))
    assert 0 < out["sync_read_ms_median"] <= out["round_trip_ms_median"] and out["n"] == 30
