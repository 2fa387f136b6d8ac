"""LeRobot's workflow on both arms, without hardware: teleoperate, record (LeRobot v3.0, written as it goes),
replay and view, with a scripted key source instead of a terminal. The SO-101 runs on the simulated Feetech
bus, the pivla arm on the fake board; cameras are synthetic."""

from __future__ import annotations

import json
import os
import time

import numpy as np
import pytest

from pivla.cli import main
from pivla.data.action_space import EE_DELTA
from pivla.data.lerobot.reader import lerobot_layout, read_info, read_lerobot
from pivla.robot import feetech as F
from pivla.robot.calibration import CalibrationError
from pivla.robot.keyboard import Event, decode, event
from pivla.robot.recording import record
from pivla.robot.replay import read_episode_actions, replay
from pivla.robot.robot import Camera
from pivla.robot.simbus import SimBus, SimBusConfig
from pivla.robot.so101 import SO101, SO101Calibration, SO101Config
from pivla.robot.so101_env import ACTION_SPACE, JOINT_NAMES, SO101Env, SO101EnvConfig
from pivla.robot.teleoperation import EEJog, JointJog, teleoperate
from tests.test_robot_so101 import calibrated_sim, calibration

H, W = 48, 64


class FakeCamera(Camera):
    """A moving bright square on a gradient, a new position every frame."""

    def __init__(self, h: int = H, w: int = W, flip: bool = False) -> None:
        self.h, self.w, self.flip, self.t = h, w, flip, 0

    def read(self) -> np.ndarray:
        img = np.zeros((self.h, self.w, 3), np.uint8)
        img[..., 0] = np.linspace(20, 220, self.w, dtype=np.uint8)
        x = 2 + (3 * self.t) % (self.w - 14)
        img[self.h // 3: self.h // 3 + 12, x: x + 10] = 240
        self.t += 1
        return img[:, ::-1].copy() if self.flip else img


BUS = {"reply_timeout_ms": 400.0, "retries": 2}  # generous: the simulated bus shares two busy cores


def so101_env(sim: SimBus, cameras: bool = True) -> SO101Env:
    arm = SO101.open(F.BusConfig(sim.port, **BUS), calibration(), SO101Config(watchdog_s=0.0))
    cams = {"front": FakeCamera(), "wrist": FakeCamera(flip=True)} if cameras else {}
    return SO101Env(arm, cams, "grab the cube", SO101EnvConfig(fps=30, realtime=False))


# ep 0 kept; ep 1 redone, then kept with the right arrow; the stop discards the episode in progress
SO101_KEYS = (["d"] * 5 + ["w"] * 3 + [""] * 2 + ["n"]
              + ["a"] * 4 + ["r"]
              + ["t"] * 6 + ["o"] * 3 + ["right"]
              + ["s"] * 2 + ["esc"] + ["d"] * 50)


@pytest.fixture(scope="module")
def so101_dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("so101_rec") / "grab"
    with calibrated_sim() as sim:
        env = so101_env(sim)
        try:
            said = []
            res = record(env, JointJog(env.lower, env.upper), iter(SO101_KEYS), root, "grab the cube", say=said.append)
        finally:
            env.close()
            env.robot.close()
    return root, res, said


def test_keys_decode_arrows_escape_and_enter():
    assert decode("n\x1b[C\x1b[Dq\r ") == (["n", "right", "left", "q", "enter", " "], "")
    assert decode("\x1b") == (["esc"], "") and decode("a\x1b", more=True) == (["a"], "\x1b")
    assert decode("\x1b[", more=True) == ([], "\x1b[") and decode("\x1bOA") == (["up"], "")
    assert [event(k) for k in ("right", "n", "left", "r", "esc", "q", "b", "w")] == [
        Event.KEEP, Event.KEEP, Event.REDO, Event.REDO, Event.STOP, Event.STOP, Event.KEEP_FAILED, None]


def test_so101_record_keeps_two_episodes_in_lerobots_layout(so101_dataset):
    root, res, said = so101_dataset
    assert (res.kept, res.redone, res.episodes, res.frames) == (2, 1, 2, 10 + 9)
    assert any("not kept" in s for s in said)
    info = read_info(root)
    assert info["robot_type"] == "so101_follower" and info["fps"] == 30 and info["total_episodes"] == 2
    assert info["features"]["observation.state"]["names"] == list(JOINT_NAMES)
    assert info["features"]["action"]["names"] == list(JOINT_NAMES)
    layout = lerobot_layout(root)
    assert layout.cameras == ("front", "wrist") and layout.proprio == ("state",)
    assert layout.action_space == ACTION_SPACE
    episodes = read_lerobot(root)
    assert [len(e) for e in episodes] == [10, 9] and all(e.instruction == "grab the cube" for e in episodes)
    ep0, ep1 = episodes
    assert ep0.obs["front"].shape == (10, H, W, 3) and ep0.obs["state"].shape == (10, 6)
    # the goals as sent: shoulder_pan up 5 key presses of 2 degrees, then shoulder_lift 3, then held
    d = np.diff(ep0.actions, axis=0)
    np.testing.assert_allclose(d[:4, 0], 2.0, atol=1e-4)
    np.testing.assert_allclose(d[5:7, 1], 2.0, atol=1e-4)
    np.testing.assert_allclose(d[8], 0.0, atol=1e-5)
    # the redone motions (shoulder_pan down) are not in episode 1, which moves elbow_flex and the gripper
    np.testing.assert_allclose(ep1.actions[:, 0], ep1.actions[0, 0], atol=1e-4)
    assert ep1.actions[-1, 2] - ep1.actions[0, 2] == pytest.approx(10.0, abs=1e-3)
    assert ep1.actions[-1, 5] > ep1.actions[0, 5]
    assert np.abs(ep0.obs["front"][3].astype(int) - FakeCamera().read().astype(int)).mean() < 60


def test_so101_recording_continues_and_survives_a_crash(so101_dataset, tmp_path):
    """A crash mid-episode (the keys raise) and a dropped link (the bus unplugged) leave every kept episode
    readable; recording into the same folder again continues the dataset."""
    import shutil

    root = tmp_path / "grab"
    shutil.copytree(so101_dataset[0], root)

    def crashing():
        yield from ["d"] * 3 + ["n"] + ["w"] * 4
        raise RuntimeError("the laptop's battery died")

    with calibrated_sim() as sim:
        env = so101_env(sim)
        try:
            with pytest.raises(RuntimeError, match="battery"):
                record(env, JointJog(env.lower, env.upper), crashing(), root, "grab the cube", say=lambda s: None)
            assert [len(e) for e in read_lerobot(root)] == [10, 9, 3]

            def unplugged():
                yield from ["w"] * 2
                sim.unplug()
                yield from ["w"] * 5
            with pytest.raises(F.BusError):
                record(env, JointJog(env.lower, env.upper), unplugged(), root, "grab the cube", say=lambda s: None)
            assert env.robot.held  # the arm tripped and holds
        finally:
            env.close()
            env.robot.close()
    assert [len(e) for e in read_lerobot(root)] == [10, 9, 3]
    assert not (root / ".pivla-commit").exists()


def test_so101_replay_sends_the_recorded_goals(so101_dataset):
    root = so101_dataset[0]
    recorded = read_episode_actions(root, 1)
    assert recorded.fps == 30 and recorded.action_space == ACTION_SPACE and len(recorded.actions) == 9
    with calibrated_sim() as sim:
        env = so101_env(sim, cameras=False)
        try:
            sent = replay(env, recorded, say=lambda s: None)
            expected = [env.robot.calibration.to_ticks(a).tolist() for a in recorded.actions]
            time.sleep(0.2)  # sync writes have no reply: let the bus take the last ones
            writes = [[v for _, v in sim.goal_writes[k:k + 6]] for k in range(0, len(sim.goal_writes), 6)]
        finally:
            env.close()
            env.robot.close()
    np.testing.assert_allclose(np.array(sent), recorded.actions, atol=1e-4)
    # the bus carried exactly those goals, one sync write each, after the walk to the first one
    starts = [k for k in range(len(writes)) if writes[k:k + len(expected)] == expected]
    assert starts, (writes, expected)


def test_view_writes_an_mp4_and_a_plot(so101_dataset, tmp_path):
    import av
    import cv2

    from pivla.data.view import view

    out = view(so101_dataset[0], 1, tmp_path / "view", viewer="files")
    with av.open(str(out["video"])) as c:
        frames = [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]
    assert len(frames) == 9 and frames[0].shape == (H, 2 * W, 3)
    png = cv2.imread(str(out["plot"]))
    assert png is not None and png.shape[0] > 300 and png.std() > 5


def test_view_logs_to_rerun_when_installed(so101_dataset, tmp_path):
    pytest.importorskip("rerun")
    from pivla.data.view import view

    out = view(so101_dataset[0], 0, tmp_path, viewer="rerun", spawn=False)
    assert out["rrd"].stat().st_size > 10_000


def test_recorded_so101_dataset_trains(so101_dataset, tmp_path):
    from tests.test_action_space import TINY_FLAGS

    run = tmp_path / "run"
    flags = [f if f != "3" else "1" for f in TINY_FLAGS]
    assert main(["train", "--data", str(so101_dataset[0]), "--out", str(run), *flags]) == 0
    cfg = json.loads((run / "config.json").read_text())["model"]
    assert tuple(cfg["cameras"]) == ("front", "wrist") and tuple(cfg["proprio_keys"]) == ("state",)
    assert cfg["action_dim"] == 6


def test_so101_calibration_is_guided_on_the_bus(tmp_path):
    """LeRobot's procedure: the middle of the range becomes the homing offset (present reads 2047), the
    extremes of a sweep the range; written to the servos and to LeRobot's file, which then opens the arm."""
    from pivla.robot.calibrate import calibrate_so101

    mids = {1: 2300, 2: 1900, 3: 2100, 4: 2000, 5: 2600, 6: 1500}
    sweep = {1: (900, 3100), 2: (800, 3000), 3: (1000, 3200), 4: (700, 3300), 5: (100, 4000), 6: (1900, 3400)}
    with SimBus(SimBusConfig()) as sim:
        def keys():
            for sid, raw in mids.items():
                sim.set_position(sid, raw)
            yield ""
            yield "enter"
            for k in range(3):
                for sid, (lo, hi) in sweep.items():
                    sim.set_position(sid, [lo, hi, 2047][k])
                yield ""
            yield "enter"

        with F.FeetechBus(F.BusConfig(sim.port, **BUS)) as bus:
            calib, path = calibrate_so101(bus, "follower", keys(), tmp_path / "follower.json", say=lambda s: None)
        doc = json.loads(path.read_text())
        assert list(doc) == ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper"]
        assert doc["shoulder_pan"] == {"id": 1, "drive_mode": 0, "homing_offset": 2300 - 2047, "range_min": 900,
                                       "range_max": 3100}
        assert doc["wrist_roll"]["range_min"] == 0 and doc["wrist_roll"]["range_max"] == 4095
        assert sim.register(1, F.HOMING_OFFSET) == 253 and sim.register(1, F.MIN_ANGLE_LIMIT) == 900
        loaded = SO101Calibration.load(path, "follower")
        with SO101.open(F.BusConfig(sim.port, **BUS), loaded, SO101Config(watchdog_s=0)) as arm:
            assert abs(arm.read()[0]) < 90

    with SimBus(SimBusConfig()) as sim, F.FeetechBus(F.BusConfig(sim.port, **BUS)) as bus:
        with pytest.raises(CalibrationError, match="did not move"):
            calibrate_so101(bus, "follower", iter(["enter", "", "enter"]), tmp_path / "follower.json",
                            say=lambda s: None)


def test_pivla_arm_records_replays_and_teleoperates_on_the_board(tmp_path):
    from pivla.robot.calibration import ArmCalibration
    from pivla.robot.env import RobotEnv, RobotEnvConfig
    from pivla.robot.fakeboard import FakeBoard
    from pivla.robot.link import Board
    from pivla.robot.robot import SerialRobot
    from pivla.robot.safety import SafetyLayer

    with FakeBoard() as fake:
        calib = ArmCalibration.nominal()
        robot = SerialRobot(Board.open(fake.port, reply_timeout_s=0.2, retries=2), calib, SafetyLayer(calib))
        sent = []
        send = robot._send
        robot._send = lambda cmd: (sent.append(cmd.q.copy()), send(cmd))[1]
        env = RobotEnv(robot, {"agentview_rgb": FakeCamera(80, 80)}, "move right",
                       RobotEnvConfig(realtime=False, max_steps=10**9))
        try:
            keys = ["d"] * 4 + [" "] + ["n"] + ["w"] * 3 + ["left"] + ["t"] * 3 + ["a"] * 2 + ["b"] + ["q"]
            res = record(env, EEJog(), iter(keys), tmp_path / "real", "move right", say=lambda s: None)
            assert (res.kept, res.redone, res.episodes) == (2, 1, 2)
            recorded = [q for q in sent]
            episodes = read_lerobot(tmp_path / "real")
            assert [len(e) for e in episodes] == [5, 5] and [e.success for e in episodes] == [True, False]
            assert lerobot_layout(tmp_path / "real").action_space == EE_DELTA
            assert {"agentview_rgb", "ee_pos", "ee_ori", "gripper_states", "joint_states"} <= set(episodes[0].obs)
            np.testing.assert_allclose(episodes[0].actions[0], [0, -0.5, 0, 0, 0, 0, -1])
            assert episodes[0].actions[-1, 6] == 1.0  # space closed the gripper
            robot.resume()  # the end of a recording e-stops the pivla arm (it holds); clearing it is explicit
            sent.clear()
            replay(env, read_episode_actions(tmp_path / "real", 0), say=lambda s: None)
            streamed = [q for q in sent if q is not None]
            # recording: home (a point move), 4 + 1 jog steps; replay: home, then the same 5 joint targets
            np.testing.assert_allclose(np.array(streamed[-5:]), np.array(recorded[1:6]), atol=1e-9)
            robot.resume()
            sent.clear()
            assert teleoperate(env, EEJog(), iter(["s"] * 3 + ["esc", "s"])) == 3
        finally:
            env.close()
            robot.close()


def test_so101_runs_a_policy_in_joint_positions():
    from pivla.control.contract import PolicySpec
    from pivla.control.executors import executor_config
    from pivla.robot.run import run_policy

    class Hold:
        spec = PolicySpec(cameras=("front",), image_size=32, proprio=(("state", 6),), chunk=4, horizon=2,
                          action_space=ACTION_SPACE)
        calibration = None

        def infer(self, obs):
            a = np.repeat(np.asarray(obs["state"], np.float32)[None] + [3, 0, 0, 0, 0, 0], 4, axis=0)
            return {"actions": a, "actions_normalized": a, "u_act": np.zeros(4), "latents": np.zeros((4, 1)),
                    "values": np.zeros(2)}

        def encode(self, obs):
            return np.zeros(1)

        def to_actions(self, normalized):
            return normalized

    with calibrated_sim() as sim:
        env = so101_env(sim)
        env.config.max_steps = 8
        try:
            start = env.robot.read()[0]
            out = run_policy(env, Hold(), executor_config("fixed", horizon=4), episodes=1)
            assert out[0]["steps"] == 8 and env.robot.read()[0] > start + 2
        finally:
            env.close()
            env.robot.close()


def test_cli_teleoperate_record_replay_and_view_the_so101(tmp_path, monkeypatch, capsys):
    import pivla.robot.keyboard as keyboard

    calib_root = tmp_path / "calibration"
    calibration("follower").save(calib_root / "robots" / "so101_follower" / "follower.json")
    monkeypatch.setenv("HF_LEROBOT_CALIBRATION", str(calib_root))
    script = []
    monkeypatch.setattr(keyboard, "terminal_keys", lambda period_s=0.1: iter(script))
    monkeypatch.setattr(F.BusConfig.__init__, "__defaults__", (1_000_000, BUS["reply_timeout_ms"], BUS["retries"]))
    arm = ["--robot", "so101", "--arm-id", "follower"]
    with calibrated_sim() as sim:
        script[:] = ["d"] * 3 + ["q"]
        assert main(["robot", "teleoperate", *arm, "--port", sim.port]) == 0
        assert "3 steps" in capsys.readouterr().out
        script[:] = ["w"] * 4 + ["n"] + ["s"] + ["esc"]
        out = tmp_path / "ds"
        assert main(["robot", "record", *arm, "--port", sim.port, "--camera", "none", "--out", str(out),
                     "--instruction", "wave", "--fps", "50"]) == 0
        assert "kept 1 episodes" in capsys.readouterr().out
        assert read_info(out)["fps"] == 50 and len(read_lerobot(out)[0]) == 4
        assert main(["robot", "replay", *arm, "--port", sim.port, "--dataset", str(out), "--episode", "0"]) == 0
        assert "4 actions at 50 fps" in capsys.readouterr().out
    assert main(["data", "view", str(out), "--episode", "0", "--viewer", "files", "--out", str(tmp_path / "v")]) == 0
    assert (tmp_path / "v" / "episode_000000.png").is_file()
    with pytest.raises(SystemExit, match="not an SO-101"):
        main(["robot", "home", "--robot", "so101", "--port", "/dev/null"])
    with pytest.raises(SystemExit, match="simulated bus"):
        main(["robot", "teleoperate", "--robot", "so101", "--sim"])
    assert os.environ["HF_LEROBOT_CALIBRATION"] == str(calib_root)


def test_pivla_arm_holds_when_the_link_drops_while_recording(tmp_path):
    """The board goes away mid-episode: the link is named lost, the arm is stopped, the kept episode stays."""
    from pivla.robot.calibration import ArmCalibration
    from pivla.robot.env import RobotEnv, RobotEnvConfig
    from pivla.robot.fakeboard import FakeBoard
    from pivla.robot.link import Board, LinkLost
    from pivla.robot.robot import SerialRobot
    from pivla.robot.safety import SafetyLayer

    fake = FakeBoard()
    calib = ArmCalibration.nominal()
    robot = SerialRobot(Board.open(fake.port, reply_timeout_s=0.1, retries=1), calib, SafetyLayer(calib))
    stops = []
    stop = robot.stop
    robot.stop = lambda: (stops.append(1), stop())[1]
    env = RobotEnv(robot, {"agentview_rgb": FakeCamera(80, 80)}, "move right",
                   RobotEnvConfig(realtime=False, max_steps=10**9))

    def keys():
        yield from ["d"] * 3 + ["n"] + ["w"] * 2
        fake.close()
        yield from ["w"] * 3
    try:
        with pytest.raises(LinkLost):
            record(env, EEJog(), keys(), tmp_path / "real", "move right", say=lambda s: None)
    finally:
        env.close()
        robot.close()
    assert stops  # the arm was told to hold (the firmware's watchdog holds it when nothing arrives)
    assert [len(e) for e in read_lerobot(tmp_path / "real")] == [3]


def test_cli_on_the_twin_calibrates_records_and_replays(tmp_path, monkeypatch, capsys):
    import pivla.robot.keyboard as keyboard

    script = []
    monkeypatch.setattr(keyboard, "terminal_keys", lambda period_s=0.1: iter(script))
    calib = tmp_path / "arm.json"
    assert main(["robot", "calibrate", "--sim", "--calibration", str(calib)]) == 0
    assert main(["robot", "calibrate-servos", "--sim", "--calibration", str(calib)]) == 0
    assert json.loads(calib.read_text())["version"] == 1
    script[:] = ["a"] * 3 + ["n"] + ["esc"]
    out = tmp_path / "twin"
    assert main(["robot", "record", "--sim", "--image-size", "32", "--out", str(out), "--instruction", "left"]) == 0
    episodes = read_lerobot(out)
    assert [len(e) for e in episodes] == [3] and episodes[0].obs["agentview_rgb"].shape == (3, 32, 32, 3)
    assert main(["robot", "replay", "--sim", "--dataset", str(out)]) == 0
    assert "3 actions at 10 fps" in capsys.readouterr().out
    script[:] = ["a", "q"]
    assert main(["robot", "teleoperate", "--sim"]) == 0
    with pytest.raises(SystemExit, match="give --port"):
        main(["robot", "replay", "--dataset", str(out)])


def test_view_reads_pivla_hdf5_datasets_too(tmp_path):
    from pivla.data.episode import Episode
    from pivla.data.hdf5 import write_episodes
    from pivla.data.view import view

    cam = FakeCamera(32, 32)
    eps = [Episode(np.zeros((t, 7)), {"agentview_rgb": np.stack([cam.read() for _ in range(t)]),
                                      "ee_pos": np.ones((t, 3))}, "push") for t in (4, 6)]
    write_episodes(tmp_path / "d" / "a.hdf5", eps, env_meta={"control_hz": 10})
    out = view(tmp_path / "d", 1, viewer="files")
    assert out["video"] == tmp_path / "d-view" / "episode_000001.mp4" and out["video"].is_file()
    assert out["plot"].is_file()


def test_cli_calibrates_an_so101_on_the_bus(tmp_path, monkeypatch):
    import pivla.robot.keyboard as keyboard

    with SimBus(SimBusConfig()) as sim:
        def keys():
            yield "enter"
            for ticks in (1000, 3000):
                for sid in range(1, 7):
                    sim.set_position(sid, ticks)
                yield ""
            yield "enter"
        monkeypatch.setattr(keyboard, "terminal_keys", lambda period_s=0.1: keys())
        monkeypatch.setattr(F.BusConfig.__init__, "__defaults__", (1_000_000, BUS["reply_timeout_ms"], BUS["retries"]))
        path = tmp_path / "leader.json"
        assert main(["robot", "calibrate", "--robot", "so101", "--port", sim.port, "--arm-id", "leader",
                     "--calibration", str(path)]) == 0
        calib = SO101Calibration.load(path, "leader")
        assert (calib.motors["elbow_flex"].range_min, calib.motors["elbow_flex"].range_max) == (1000, 3000)
        with pytest.raises(SystemExit, match="calibration file by its id"):
            main(["robot", "calibrate", "--robot", "so101", "--port", sim.port, "--arm-id", "leader",
                  "--calibration", str(tmp_path / "other.json")])
