"""The arm stack runs on a robot laptop's client-only install: neither MuJoCo nor torch is imported by the
serial link, protocol, safety layer, calibration, the arm driver, RobotEnv, the repeatability measurement or
the SO-101's bus, driver and port finder, nor by the workflow on top (the factory, keys, teleoperation,
recording, replay, calibration, the run loop), and with both made unimportable the whole stack drives a (fake)
board end to end. Only the twin-backed modules (``pivla.robot.sim``, ``pivla.robot.autocollect``) need
MuJoCo."""

from __future__ import annotations

import subprocess
import sys

CLIENT_MODULES = ("link", "protocol", "safety", "calibration", "robot", "env", "repeatability", "feetech", "simbus",
                  "so101", "ports", "so101_env", "factory", "keyboard", "teleoperation", "recording", "replay",
                  "calibrate", "run")
HEAVY = ("mujoco", "torch")


def run(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=180)


def test_arm_stack_imports_neither_mujoco_nor_torch():
    for module in CLIENT_MODULES:  # one process each: a module must not lean on another's imports
        code = f"""
import sys
import pivla.robot.{module}
heavy = sorted(m for m in sys.modules if m.split(".")[0] in {HEAVY!r})
assert not heavy, f"pivla.robot.{module} imported {{heavy}}"
"""
        proc = run(code)
        assert proc.returncode == 0, proc.stderr[-2000:]


def test_arm_stack_drives_a_board_without_mujoco_or_torch_installed():
    code = f"""
import importlib.abc
import sys


class NotInstalled(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {HEAVY!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}} (client-only install)")
        return None


sys.meta_path.insert(0, NotInstalled())

import numpy as np

from pivla import arm
from pivla.robot import {", ".join(CLIENT_MODULES)}  # noqa: F401
from pivla.robot.calibration import ArmCalibration
from pivla.robot.env import RobotEnv, RobotEnvConfig
from pivla.robot.fakeboard import FakeBoard
from pivla.robot.link import Board
from pivla.robot.robot import SerialRobot
from pivla.robot.safety import SafetyLayer

try:
    import mujoco  # noqa: F401
except ModuleNotFoundError:
    pass
else:
    raise AssertionError("the import blocker did not work")

with FakeBoard() as fake:
    calib = ArmCalibration.nominal()
    board = Board.open(fake.port, reply_timeout_s=0.2, retries=2)
    robot = SerialRobot(board, calib, SafetyLayer(calib))
    env = RobotEnv(robot, {{}}, "move right", RobotEnvConfig(realtime=False, max_steps=5))
    obs, _ = env.reset()
    assert np.allclose(obs["ee_pos"], arm.HOME_POSE[0], atol=2e-3), obs["ee_pos"]
    for _ in range(3):
        obs, *_ = env.step(np.array([0.0, -1.0, 0.0, 0.0, 0.0, 0.0, -1.0]))
    commanded, _ = arm.forward_kinematics(robot.last_command.q)
    assert abs(commanded[1] + 3 * env.config.pos_scale) < 5e-3, commanded  # three steps of 2 cm to the right
    robot.close()
heavy = sorted(m for m in sys.modules if m.split(".")[0] in {HEAVY!r})
assert not heavy, heavy
"""
    proc = run(code)
    assert proc.returncode == 0, proc.stderr[-3000:]
