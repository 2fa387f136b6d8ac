"""The Robot/Camera interfaces on the twin: env adapter, safety on the way in, repeatability, autocollect."""

import numpy as np
import pytest

from pivla.cli import main
from pivla.robot.env import RobotEnv, RobotEnvConfig
from pivla.robot.safety import SafetyError
from pivla.robot.sim import SimCamera, SimRobot


@pytest.fixture(scope="module")
def robot():
    r = SimRobot("pick_place", 0, seed=5)
    yield r
    r.close()


def test_env_adapter_moves_the_tool_and_observes_dataset_keys(robot):
    env = RobotEnv(robot, {"agentview_rgb": SimCamera(robot, "agentview_rgb", 64)}, "move the block left",
                   RobotEnvConfig(realtime=False))
    obs, _ = env.reset()
    start = obs["ee_pos"].copy()
    for _ in range(5):
        obs, *_ = env.step(np.array([0, 1.0, 0, 0, 0, 0, -1.0]))
    assert obs["agentview_rgb"].shape == (64, 64, 3)
    assert set(obs) >= {"ee_pos", "ee_ori", "gripper_states", "joint_states", "instruction"}
    assert obs["ee_pos"][1] - start[1] == pytest.approx(5 * env.config.pos_scale, abs=0.01)
    with pytest.raises(SafetyError, match="non-finite"):
        env.step(np.array([np.nan, 0, 0, 0, 0, 0, 0]))
    robot.resume()


def test_point_moves_pass_the_safety_layer(robot):
    q = robot.home_q.copy()
    q[0] = robot.calibration.limits_rad[0, 1] + 0.2
    with pytest.raises(SafetyError, match="base_yaw"):
        robot.move_to(q, 1.0)


def test_repeatability_and_autocollect_commands(tmp_path, capsys):
    assert main(["robot", "repeatability", "--sim", "--targets", "2", "--repeats", "2"]) == 0
    assert '"scatter_mm_max"' in capsys.readouterr().out
    assert main(["robot", "autocollect", "--sim", "--attempts", "2", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert '"vision_success_rate"' in out
    from pivla.data.read import read_dataset

    eps = read_dataset(tmp_path)
    assert len(eps) == 2 and all(e.source == "autocollect" for e in eps)
