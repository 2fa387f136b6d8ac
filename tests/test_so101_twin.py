"""The SO-101 twin: deterministic episodes per seed, the STS3215 model, the scripted expert with servo realism,
actions inside the joint limits, and collection -> training -> evaluation with the SO-101 action space."""

import numpy as np
import pytest

from pivla.cli import main
from pivla.data.action_space import SO101, SO101_JOINT_NAMES, SO101_MOTORS
from pivla.envs import list_tasks, seeds
from pivla.envs.rollout import run_episode
from pivla.envs.so101 import make_env, model, tasks
from pivla.envs.so101.expert import make_expert
from pivla.envs.so101.servo import RAD_PER_STEP, ServoConfig, STS3215Bus

TASKS = [t.name for t in list_tasks("so101", "pick_place")]
TINY_TRAIN = ["--steps", "3", "--batch-size", "4", "--warmup", "1", "--log-every", "1", "--eval-every", "100",
              "--ckpt-every", "100", "--value-refresh-every", "100", "--threads", "2", "--no-progress",
              "--model.image-size", "32", "--model.backbone.d-model", "64", "--model.backbone.n-layers", "1",
              "--model.backbone.vision-channels", "16", "16", "32", "32"]


def test_the_twin_names_its_joints_as_lerobot_and_the_driver_do():
    from pivla.robot.so101 import MOTORS

    assert model.JOINTS == SO101_MOTORS == MOTORS
    assert SO101.names == SO101_JOINT_NAMES and SO101.dim == 6 and SO101.gripper == 5
    env = make_env(render=False)
    assert [env.model.actuator(i).name for i in env._act] == list(SO101_MOTORS)
    lo, hi = model.lerobot_limits()
    assert lo[-1] == 0.0 and hi[-1] == pytest.approx(100.0)
    assert np.allclose(lo[:5], np.degrees(model.joint_limits()[:5, 0]))
    u = np.array([10.0, -20.0, 30.0, 45.0, -90.0, 37.5])
    assert np.allclose(model.to_lerobot(model.from_lerobot(u)), u)
    assert all(t in seeds.TASKS for t in TASKS) and len(TASKS) == 4


def test_reset_and_step_are_deterministic_per_seed():
    def rollout(seed):
        env = make_env("pick_place", "blue_cube_on_pad", realism="servo", image_size=32)
        obs, info = env.reset(seed=seed)
        out = [obs["front"], obs["wrist"], obs["state"]]
        rng = np.random.default_rng(0)
        for _ in range(4):
            action = env.command + rng.normal(0, 3.0, 6)
            obs, reward, term, trunc, info = env.step(action)
            out += [obs["front"], obs["wrist"], obs["state"]]
        return out, env.layout, info

    a, layout_a, info = rollout(5)
    b, layout_b, _ = rollout(5)
    c, layout_c, _ = rollout(6)
    assert all(np.array_equal(x, y) for x, y in zip(a, b)) and layout_a == layout_b
    assert layout_a != layout_c
    assert a[0].shape == (32, 32, 3) and a[2].dtype == np.float32 and a[2].shape == (6,)
    assert set(info) >= {"success", "stages", "stage_progress", "step", "perturb_events"}


def test_servo_model_quantises_caps_speed_and_has_a_dead_zone():
    cfg = ServoConfig()
    assert cfg.stall_torque == pytest.approx(1.912, abs=1e-3) and cfg.max_speed == pytest.approx(4.717, abs=1e-3)
    bus = STS3215Bus(cfg)
    bus.reset(np.zeros(6))
    bus.command(np.full(6, 1.0))
    assert np.allclose(bus.goal / RAD_PER_STEP, np.round(1.0 / RAD_PER_STEP))  # 4096 steps a turn
    speeds = []
    for _ in range(500):  # 1 s at 2 ms: the setpoint ramps at the acceleration, never faster than the cap
        before = bus.setpoint.copy()
        bus.torque(np.zeros(6), 0.002)
        speeds.append(np.abs(bus.setpoint - before).max() / 0.002)
    assert max(speeds) <= cfg.max_speed + 1e-9 and np.allclose(bus.setpoint, bus.goal)
    torque = bus.torque(np.zeros(6), 0.002)  # far from the goal: saturated, the gripper at half the stall torque
    assert np.allclose(torque[:5], cfg.stall_torque) and torque[5] == pytest.approx(cfg.stall_torque / 2)
    near = bus.goal - cfg.deadband_steps * RAD_PER_STEP  # within the dead zone: no torque
    assert np.all(bus.torque(near, 0.002) == 0.0)


@pytest.mark.parametrize("task", TASKS)
def test_the_expert_succeeds_with_servo_realism_inside_the_joint_limits(task):
    env = make_env("pick_place", task, realism="servo", render=False)
    lo, hi = env.action_space.low, env.action_space.high
    for k, (noise, miss) in enumerate([(0.0, 0.0), (1.0, 1.0)]):  # clean, then DART noise and a missed grasp
        seed = seeds.seed_for("train", "in_distribution", task, k)
        expert = make_expert(noise, miss)
        ep = run_episode(env, expert, seed, frames=False)
        assert ep.success, (task, seed, expert.phase)
        assert ep.actions.shape == (len(ep), 6) and len(ep) < env.task.max_steps
        assert np.all(ep.actions >= lo) and np.all(ep.actions <= hi)
        assert ep.rewards.sum() == pytest.approx(1.0)


def test_out_of_range_and_malformed_actions():
    env = make_env(realism="servo", render=False)
    env.reset(seed=1)
    lo, hi = model.lerobot_limits()
    _, _, _, _, info = env.step(np.array([500.0, -500.0, 0.0, 0.0, 0.0, 150.0]))
    assert np.allclose(info["command"], np.clip([500.0, -500.0, 0.0, 0.0, 0.0, 150.0], lo, hi))
    assert np.all(env.joint_positions() >= lo - 1.0) and np.all(env.joint_positions() <= hi + 1.0)
    with pytest.raises(ValueError, match="6 joint positions"):
        env.step(np.zeros(7))
    with pytest.raises(ValueError, match="NaN"):
        env.step(np.full(6, np.nan))
    with pytest.raises(ValueError, match="no perturbations"):
        make_env(perturb="static_distractors")


def test_a_placed_cube_counts_only_in_its_target():
    assert tasks.placed("pad", np.zeros(2), np.array([0.03, -0.03, tasks.CUBE_HALF]))
    assert not tasks.placed("pad", np.zeros(2), np.array([0.05, 0.0, tasks.CUBE_HALF]))
    assert tasks.placed("bowl", np.zeros(2), np.array([0.02, 0.02, tasks.place_height("bowl")]))
    assert not tasks.placed("bowl", np.zeros(2), np.array([0.06, 0.0, tasks.CUBE_HALF]))


@pytest.fixture(scope="module")
def so101_data(tmp_path_factory):
    out = tmp_path_factory.mktemp("so101_twin") / "data"
    code = main(["collect", "--env", "so101", "--suite", "pick_place", "--tasks", "red_cube_on_pad,blue_cube_in_bowl",
                 "--episodes", "1", "--seed-family", "train", "--realism", "servo", "--image-size", "32",
                 "--noise", "1.0", "--out", str(out)])
    assert code == 0
    return out


def test_a_placement_miss_is_refused_for_so101(tmp_path):
    """Only the tabletop expert misses a placement on purpose: so101's collection names the option, writes nothing."""
    with pytest.raises(SystemExit, match="place_miss"):
        main(["collect", "--env", "so101", "--suite", "pick_place", "--tasks", "red_cube_on_pad", "--episodes", "1",
              "--place-miss", "0.5", "--out", str(tmp_path / "data")])
    assert not (tmp_path / "data").exists()


def test_a_collected_dataset_has_the_so101_layout(so101_data):
    from pivla.data.hdf5 import read_env_meta
    from pivla.data.read import dataset_layout, read_dataset

    layout = dataset_layout(so101_data)
    assert layout.action_space == SO101
    assert layout.cameras == ("front", "wrist") and layout.proprio == ("state",) and layout.vectors == {"state": 6}
    episodes = read_dataset(so101_data)
    assert len(episodes) == 2 and all(e.success for e in episodes)
    for ep in episodes:
        assert ep.actions.shape == (len(ep), 6) and ep.obs["state"].shape == (len(ep), 6)
        assert ep.obs["front"].shape == (len(ep), 32, 32, 3)
        lo, hi = model.lerobot_limits()
        assert np.all(ep.actions >= lo) and np.all(ep.actions <= hi) and np.abs(ep.obs["state"]).max() > 30  # deg
    meta = read_env_meta(sorted(so101_data.glob("*.hdf5"))[0])
    assert meta["env"] == "so101" and meta["control_hz"] == 10 and meta["realism"] == "servo"


def test_a_policy_trains_on_it_and_runs_in_the_twin(so101_data, tmp_path):
    from pivla.control import run_episode as run_policy
    from pivla.control.executors import make_executor
    from pivla.policy import load_policy

    run = tmp_path / "run"
    assert main(["train", "--data", str(so101_data), "--out", str(run), *TINY_TRAIN]) == 0
    policy = load_policy(run, device="cpu")
    assert policy.spec.action_space == SO101 and tuple(policy.spec.cameras) == ("front", "wrist")
    env = make_env("pick_place", "red_cube_on_pad", realism="servo", image_size=policy.spec.image_size,
                   cameras=tuple(policy.spec.cameras))
    result = run_policy(env, policy, make_executor("fixed"), seed=seeds.seed_for("test", "in_distribution",
                                                                                 "red_cube_on_pad", 0), max_steps=6)
    assert result.steps == 6 and result.actions.shape == (6, 6)
    lo, hi = model.lerobot_limits()
    assert np.all(np.isfinite(result.actions))
    assert np.all(env.command >= lo) and np.all(env.command <= hi)

    # with latency the arm holds where it is until the first chunk arrives: its present joint positions
    from pivla.control.asynchronous import AsyncConfig, SyncConfig

    obs, _ = env.reset(seed=3)
    start = np.asarray(obs["state"], np.float32)
    result = run_policy(env, policy, make_executor("fixed"), seed=3, max_steps=6, execution=SyncConfig(),
                        latency="300")
    idle = [row for row in result.trace if row.get("idle")]
    assert result.steps == 6 and len(idle) == 3
    np.testing.assert_allclose(result.actions[0], start, atol=1e-4)
    # asynchronously too: the simulation steps on while the first chunk is in flight, the arm held where it is
    never = {"tau_low": 1e9, "tau_high": 1e9, "v_thresh": -1e9}
    for executor in (make_executor("fixed"), make_executor("aurd", **never), make_executor("ensemble")):
        result = run_policy(env, policy, executor, seed=3, max_steps=6, execution=AsyncConfig(), latency="300")
        idle = [row for row in result.trace if row.get("idle")]
        assert result.steps == 6 and len(idle) == 3, executor.name
        np.testing.assert_allclose(result.actions[:3], np.repeat(start[None], 3, 0), atol=1e-4)
    # AURD that distrusts the episode's first step pauses there, holding the present pose
    always = {"tau_low": -1.0, "tau_high": -1.0, "v_thresh": 2.0}
    result = run_policy(env, policy, make_executor("aurd", **always), seed=3, max_steps=2)
    assert result.trace[0]["event"] == "pause"
    np.testing.assert_allclose(result.actions[0], start, atol=1e-4)


def test_the_arm_model_ships_with_its_license_and_notice():
    """The MJCF, meshes, LICENSE and NOTICE of assets/so101 are package data (pyproject's patterns)."""
    import fnmatch
    import tomllib
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    patterns = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["pivla"]
    files = [p for p in model.ASSET_DIR.rglob("*") if p.is_file()]
    assert {p.name for p in files} >= {"LICENSE", "NOTICE", "so101_new_calib.xml", "moving_jaw_so101_v1.stl"}
    package = root / "src" / "pivla"
    unshipped = [p for p in files if not any(fnmatch.fnmatch(str(p.relative_to(package)), pat) for pat in patterns)]
    assert not unshipped
    assert "Apache License" in (model.ASSET_DIR / "LICENSE").read_text()
    assert "TheRobotStudio" in (model.ASSET_DIR / "NOTICE").read_text()
