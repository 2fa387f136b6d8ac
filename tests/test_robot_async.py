"""Asynchronous execution on the arms: `pivla robot run --execution async` drives the pivla arm (its firmware on the
simulated board) against a policy served with a delay, and the SO-101 (its simulated servo bus), through the same
loop as `pivla eval` (pivla.control.asynchronous on the wall clock); a link lost mid-episode makes the arm hold."""

from __future__ import annotations

import time

import numpy as np
import pytest

from pivla.control.asynchronous import AsyncConfig, SyncConfig
from pivla.control.executors import executor_config
from pivla.robot.robot import Camera
from pivla.robot.run import run_policy
from pivla.robot.simboard import missing_toolchain

HZ = 10.0


class StillCamera(Camera):
    """A fixed 32-px picture (the served test run's image size)."""

    def read(self) -> np.ndarray:
        img = np.zeros((32, 32, 3), np.uint8)
        img[8:24, 8:24] = 200
        return img


class Commands:
    """The env, recording the joint targets the arm was sent after every step (and cutting the network at
    ``cut_at``, when given)."""

    def __init__(self, env, robot, cut=None, cut_at: int | None = None):
        self.env, self.robot, self.cut, self.cut_at = env, robot, cut, cut_at
        self.unwrapped, self.action_space, self.sent = env.unwrapped, env.action_space, []

    def reset(self, **kw):
        self.t, self.sent = 0, []
        return self.env.reset(**kw)

    def step(self, action):
        self.t += 1
        if self.t == self.cut_at:
            self.cut()
        out = self.env.step(action)
        self.sent.append(np.array(self.robot.last_command.q, float))
        return out

    def close(self):
        self.env.close()


@pytest.fixture(scope="module")
def firmware():
    if missing_toolchain():
        pytest.skip(f"AVR/simavr toolchain missing: {missing_toolchain()}")
    from pivla.robot.simboard import build

    return build()[0]


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    from tests.test_serving import write_run

    return write_run(tmp_path_factory.mktemp("robot-async") / "run")


def pivla_arm(port: str, max_steps: int):
    from pivla.robot.calibration import ArmCalibration
    from pivla.robot.env import RobotEnv, RobotEnvConfig
    from pivla.robot.link import Board
    from pivla.robot.robot import SerialRobot
    from pivla.robot.safety import SafetyLayer

    calib = ArmCalibration.nominal()
    robot = SerialRobot(Board.open(port), calib, SafetyLayer(calib))
    cams = {"agentview_rgb": StillCamera(), "eye_in_hand_rgb": StillCamera()}
    return robot, RobotEnv(robot, cams, "pick up the red block",
                           RobotEnvConfig(control_hz=HZ, realtime=True, max_steps=max_steps))


def test_the_pivla_arm_runs_a_served_policy_asynchronously_and_holds_when_the_link_is_lost(firmware, run_dir,
                                                                                           tmp_path):
    from pivla.robot.simboard import SimBoard
    from pivla.serving import RemotePolicy
    from tests.test_serving import KEY, Relay, running_server

    with SimBoard(firmware) as board, running_server(run_dir, tmp_path, delay_ms=150) as (port, _):
        robot, env = pivla_arm(board.port, max_steps=16)
        try:
            # 150 ms at 10 Hz is 2 control steps: the auto threshold sends with 2 actions left, so the arm waits
            # only for the first chunk, and its loop never waits on the policy (synchronously every query does)
            runs = {}
            for execution in (AsyncConfig(), SyncConfig()):
                with RemotePolicy(f"ws://127.0.0.1:{port}", api_key=KEY) as remote:
                    runs[execution.kind] = run_policy(env, remote, executor_config("fixed", horizon=3), seed=1,
                                                      execution=execution)[0]
                robot.resume()  # the end of a run stops the arm (it holds); clearing that is explicit
            asynchronous, sync = runs["async"], runs["sync"]
            assert asynchronous["steps"] == sync["steps"] == 16, (asynchronous, sync)
            assert asynchronous["failed_queries"] == asynchronous["stale_chunks"] == 0 and asynchronous["queries"] >= 5
            assert asynchronous["delay_steps_mean"] >= 2 and asynchronous["idle_steps"] <= 6, asynchronous
            assert asynchronous["control_ms_mean"] < 20 < 150 / 3 < sync["control_ms_mean"], (asynchronous, sync)

            # the network goes at step 6: the chunk in execution runs out its horizon, then the arm holds
            relay = Relay(port)
            cut = Commands(env, robot, relay.shut, cut_at=6)
            with RemotePolicy(f"127.0.0.1:{relay.port}", api_key=KEY, retries=1) as remote:
                out = run_policy(cut, remote, executor_config("fixed", horizon=3), seed=2, execution=AsyncConfig(),
                                 latency="real")[0]
            assert out["failed_queries"] >= 1 and out["steps"] == 16
            held = cut.sent[6 + 3 + 2:]  # past the horizon of any chunk that can still have arrived
            assert len(held) >= 3 and all(np.allclose(q, held[0], atol=1e-9) for q in held), held
        finally:
            env.close()
            robot.close()


class Actions:
    """The env, recording the actions it was sent."""

    def __init__(self, env):
        self.env, self.robot, self.unwrapped, self.sent = env, env.robot, env.unwrapped, []
        self.action_space = env.action_space

    def reset(self, **kw):
        self.sent = []
        return self.env.reset(**kw)

    def step(self, action):
        self.sent.append(np.array(action, float))
        return self.env.step(action)

    def close(self):
        self.env.close()


class DelayedPolicy:
    """A joint-position policy that answers after ``delay_s`` (a slow server), then loses its link after ``n``
    answers (what RemotePolicy raises when the network is gone)."""

    def __init__(self, delay_s: float, n: int | None = None):
        from pivla.control.contract import PolicySpec
        from pivla.robot.so101_env import ACTION_SPACE

        self.spec = PolicySpec(cameras=("front",), image_size=32, proprio=(("state", 6),), chunk=8, horizon=4,
                               action_space=ACTION_SPACE)
        self.calibration = None
        self.delay_s, self.n, self.answers = delay_s, n, 0

    def infer(self, obs):
        time.sleep(self.delay_s)
        if self.n is not None and self.answers >= self.n:
            raise ConnectionError("pivla server at ws://x: connection lost, 1 reconnection attempt(s) failed")
        self.answers += 1
        a = np.asarray(obs["state"], np.float32)[None] + np.outer(np.arange(1, 9), [2, 0, 0, 0, 0, 0])
        return {"actions": a.astype(np.float32), "actions_normalized": a.astype(np.float32), "u_act": np.zeros(8),
                "latents": np.zeros((8, 1)), "values": np.zeros(4)}

    def encode(self, obs):
        return np.zeros(1)

    def to_actions(self, normalized):
        return normalized


def test_the_so101_runs_asynchronously_on_its_simulated_bus_and_holds_when_the_link_is_lost():
    from pivla.robot import feetech as F
    from pivla.robot.so101 import SO101, SO101Config
    from pivla.robot.so101_env import SO101Env, SO101EnvConfig
    from tests.test_robot_so101 import calibrated_sim, calibration
    from tests.test_robot_workflow import BUS

    with calibrated_sim() as sim:
        arm = SO101.open(F.BusConfig(sim.port, **BUS), calibration(), SO101Config(watchdog_s=0.0))
        env = SO101Env(arm, {"front": StillCamera()}, "grab the cube",
                       SO101EnvConfig(fps=HZ, realtime=True, max_steps=14))
        try:
            start = arm.read()[0]
            out = run_policy(env, DelayedPolicy(0.15), executor_config("fixed", horizon=4), seed=0,
                             execution=AsyncConfig())[0]
            # 150 ms at 10 Hz: 2 steps in flight (more when this machine is slow), the arm idle only at the start
            assert out["steps"] == 14 and out["failed_queries"] == 0 and out["idle_steps"] <= 6, out
            assert out["delay_steps_mean"] >= 2 and out["control_ms_mean"] < 20, out
            assert arm.read()[0] > start + 4  # the chunks' targets walk the first joint

            recorded = Actions(env)
            arm.resume()  # the end of a run stops the arm (it holds); clearing that is explicit
            out = run_policy(recorded, DelayedPolicy(0.15, n=1), executor_config("fixed", horizon=4), seed=1,
                             execution=AsyncConfig())[0]
            assert out["failed_queries"] >= 1
            sent = recorded.sent
            # one chunk answered: it runs its horizon of 4, then every command is the hold of its last target
            moving = [t for t in range(1, len(sent)) if not np.allclose(sent[t], sent[t - 1])]
            assert moving and moving[-1] <= 2 + 4, moving
            assert all(np.allclose(a, sent[-1]) for a in sent[2 + 4:]), sent
        finally:
            env.close()
            arm.close()


def test_robot_run_takes_an_execution_mode():
    import tyro

    from pivla.cli.app import TYRO_CONFIG, _choice_shorthand
    from pivla.cli.robot import RunCommand

    def parse(*argv):
        argv = ["--policy", "ws://127.0.0.1:8000", "--instruction", "pick", *argv]
        return tyro.cli(RunCommand, args=_choice_shorthand(RunCommand, argv), config=TYRO_CONFIG)

    assert parse().execution == SyncConfig()
    assert parse("--execution", "async").execution == AsyncConfig(threshold="auto")
    cmd = parse("--execution", "async", "--execution.threshold", "3", "--executor", "fixed")
    assert cmd.execution == AsyncConfig(threshold=3) and cmd.executor.kind == "fixed"
