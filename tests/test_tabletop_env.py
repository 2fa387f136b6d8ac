"""The gymnasium twin: task lists, observation contract, determinism, perturbations, servo realism."""

import gymnasium
import numpy as np
import pytest

from pivla.bench.sim import measure_repeatability
from pivla.envs import select_tasks
from pivla.envs.rollout import run_episode
from pivla.envs.tabletop import ENV_ID, list_tasks, make_env, parse_perturb
from pivla.envs.tabletop.expert import Expert, ExpertConfig, make_expert
from pivla.envs.tabletop.perturb import CLUTTER_SLOTS, TABLE_MATERIALS, TRAIN_TABLE_MATERIALS, PerturbConfig
from pivla.envs.tabletop.scene import CLUTTER_SHAPES, DISTRACTOR_SHAPES


def test_suites_and_unseen_split():
    names = [t.name for t in list_tasks("pick_place")]
    assert len(names) == 9 and "block_left" in names and "rock_away" in names
    seen = {t.name for t in list_tasks("pick_place_seen")}
    unseen = {t.name for t in list_tasks("pick_place_unseen")}
    assert seen | unseen == set(names) and not seen & unseen and len(unseen) == 3
    # the held-out pairs still show every object and every direction in training
    assert {n.split("_")[0] for n in seen} == {"block", "ball", "rock"}
    assert {n.split("_")[1] for n in seen} == {"away", "left", "right"}
    assert [t.name for t in list_tasks("drawer")] == ["open_drawer", "close_drawer"]
    assert len(list_tasks("stack")) >= 1 and len(list_tasks("long")) >= 1
    assert all(t.max_steps < 100 for t in list_tasks("pick_place"))
    assert [t.name for t in select_tasks("tabletop", "pick_place", "0,ball_right")] == ["block_away", "ball_right"]
    with pytest.raises(ValueError, match="unknown tabletop suite"):
        list_tasks("nope")


def test_observation_contract_and_gym_registration():
    env = gymnasium.make(ENV_ID, suite="pick_place", task="block_left")
    obs, info = env.reset(seed=0)
    assert obs["agentview_rgb"].shape == (96, 96, 3) and obs["agentview_rgb"].dtype == np.uint8
    assert obs["eye_in_hand_rgb"].shape == (96, 96, 3)
    for key, dim in (("ee_pos", 3), ("ee_ori", 3), ("gripper_states", 2), ("joint_states", 6)):
        assert obs[key].shape == (dim,) and obs[key].dtype == np.float32
    assert obs["instruction"] == "move the block left"
    assert env.observation_space.contains(obs)
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert isinstance(reward, float) and "success" in info and not terminated
    assert obs["agentview_rgb"].std() > 5  # the camera sees a scene, not a blank frame
    env.close()


def test_bad_actions_and_arguments_are_rejected():
    env = make_env("pick_place", 0, render=False)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="NaN"):
        env.step(np.array([0, 0, np.nan, 0, 0, 0, 0]))
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(6))
    with pytest.raises(ValueError, match="realism"):
        make_env("pick_place", 0, realism="robot")
    with pytest.raises(ValueError, match="out of range"):
        make_env("drawer", 5)


def _rollout(env, seed, expert=None):
    expert = expert or make_expert()
    obs, _ = env.reset(seed=seed)
    expert.reset(env, seed)
    frames, states, rewards = [obs], [], []
    for _ in range(env.task.max_steps):
        obs, r, term, trunc, info = env.step(expert(obs))
        frames.append(obs)
        states.append(np.concatenate([o["pos"] for o in env.privileged_state()["objects"].values()]
                                     + [env.privileged_state()["ee_pos"]]))
        rewards.append(r)
        if term or trunc:
            break
    return frames, np.array(states), np.array(rewards), info["success"]


@pytest.mark.parametrize("realism", ["ideal", "servo"])
def test_same_seed_same_episode(realism):
    a = _rollout(make_env("pick_place", "rock_left", image_size=32, realism=realism), seed=7)
    b = _rollout(make_env("pick_place", "rock_left", image_size=32, realism=realism), seed=7)
    c = _rollout(make_env("pick_place", "rock_left", image_size=32, realism=realism), seed=8)
    assert len(a[0]) == len(b[0])
    for fa, fb in zip(a[0], b[0]):
        assert all(np.array_equal(fa[k], fb[k]) for k in fa if k != "instruction")
    assert np.array_equal(a[1], b[1]) and np.array_equal(a[2], b[2])
    assert not np.array_equal(a[1][:5], c[1][:5])


def test_stage_rewards_sum_to_one_on_success():
    frames, _, rewards, success = _rollout(make_env("long", 0, render=False), seed=3)
    assert success and rewards.sum() == pytest.approx(1.0) and (rewards >= 0).all()
    assert (rewards > 0).sum() >= 4  # dense: several stages rewarded along the way


def test_a_missed_grasp_is_executed_but_not_labelled_and_then_recovered():
    """miss=1: the arm closes on nothing beside the rock, reopens and grasps again; the recorded labels never
    ask to close there, and the episode still succeeds."""
    env = make_env("pick_place", "rock_left", image_size=32)
    ep = run_episode(env, make_expert(0.0, miss=1.0), seed=3)
    assert ep.success
    observed_closed = np.flatnonzero(ep.obs["gripper_states"][:, 0] < 0.005)  # fingers shut on nothing
    first_close_label = int(np.flatnonzero(ep.actions[:, 6] > 0)[0])
    assert len(observed_closed) and observed_closed[0] < first_close_label
    reopened = ep.obs["gripper_states"][observed_closed[-1] + 1 : first_close_label, 0]
    assert (reopened > 0.03).any()
    clean = run_episode(env, make_expert(0.0), seed=3)
    assert clean.success and len(clean) < len(ep) and (clean.obs["gripper_states"][:, 0] > 0.005).all()
    with pytest.raises(ValueError, match="retries"):
        Expert(ExpertConfig(miss=0.5, retries=0))


def test_a_missed_placement_is_carried_beside_the_goal_then_brought_back():
    """place_miss=1: the first carry is executed towards a point beside the green block while every label heads
    for the block; the second carry starts centimetres away and brings the held block back over it before it is set
    down. Policies that let go 2-3 cm beside the block had never seen that correction."""
    env = make_env("stack", 0, image_size=32)
    for place_miss in (0.0, 1.0):
        expert = make_expert(0.0, place_miss=place_miss)
        obs, _ = env.reset(seed=3)
        expert.reset(env, seed=3)
        carried, lowered = [], []  # (held block's horizontal distance from the green block, executed as labelled)
        for _ in range(env.task.max_steps):
            action = expert(obs)
            if expert.phase in ("carry", "lower"):
                objects = env.privileged_state()["objects"]
                gap = np.linalg.norm(objects["red_block"]["pos"][:2] - objects["green_block"]["pos"][:2])
                (carried if expert.phase == "carry" else lowered).append((gap, np.array_equal(action, expert.label)))
            obs, _, success, truncated, _ = env.step(action)
            if success or truncated:
                break
        assert success
        as_labelled = [same for _, same in carried]
        if place_miss == 0.0:
            assert all(as_labelled)
            continue
        assert not as_labelled[0]
        back = as_labelled.index(True)  # the first step of the second carry
        assert all(as_labelled[back:]) and carried[back][0] >= 0.015 and lowered[0][0] < 0.01
    with pytest.raises(ValueError, match="place_miss"):
        Expert(ExpertConfig(place_miss=1.5))


def test_parse_perturb_grammar():
    assert parse_perturb(None) == PerturbConfig() and parse_perturb("") == PerturbConfig()
    cfg = parse_perturb(" unseen_env , dynamic_distractors,level=4")
    assert cfg.unseen_env and cfg.dynamic_distractors and cfg.n_distractors == 4 and cfg.n_dynamic == 4
    assert parse_perturb(cfg.spec()) == cfg
    assert parse_perturb("level=2").static_distractors and parse_perturb("level=2").n_distractors == 2
    assert parse_perturb("static_distractors").level == 3
    both = parse_perturb("static_distractors,dynamic_distractors,level=4")
    assert both.n_distractors == 4 and both.n_dynamic == 2
    for bad, msg in (("fog", "unknown perturbation"), ("level=x", "integer"), ("level=99", "0.."),
                     ("unseen_tasks", "pick_place_unseen")):
        with pytest.raises(ValueError, match=msg):
            parse_perturb(bad)


@pytest.mark.parametrize("spec", ["unseen_env", "static_distractors,level=4", "dynamic_distractors,level=2",
                                  "camera_jitter", "randomized_scene,level=2",
                                  "unseen_env,static_distractors,dynamic_distractors,camera_jitter,level=6"])
def test_perturbation_changes_pixels_not_success(spec):
    clean = _rollout(make_env("pick_place", "ball_left", image_size=48), seed=11)
    pert = _rollout(make_env("pick_place", "ball_left", image_size=48, perturb=spec), seed=11)
    assert clean[3] and pert[3]
    assert np.array_equal(clean[1], pert[1]), "the perturbation changed the physics"
    assert np.array_equal(clean[2], pert[2])
    diff = np.abs(clean[0][0]["agentview_rgb"].astype(int) - pert[0][0]["agentview_rgb"].astype(int))
    assert (diff.sum(-1) > 30).mean() > 0.002, "the perturbation is invisible"
    if "dynamic" in spec:  # moving distractors: consecutive perturbed frames differ beyond the arm's motion
        env = make_env("pick_place", "ball_left", image_size=48, perturb=spec)
        env.reset(seed=1)
        before = env.render()
        env.step(np.zeros(7))
        env.step(np.zeros(7))
        assert not np.array_equal(before, env.render())


def test_perturbations_differ_between_seeds():
    env = make_env("pick_place", 0, image_size=48, perturb="unseen_env,static_distractors")
    a = env.reset(seed=1)[0]["agentview_rgb"]
    b = env.reset(seed=2)[0]["agentview_rgb"]
    assert not np.array_equal(a, b)
    assert np.array_equal(a, env.reset(seed=1)[0]["agentview_rgb"])


def test_training_randomisation_keeps_the_test_textures_and_distractors_unseen():
    """randomized_scene (training data) shares no texture with unseen_env and no distractor shape with the
    distractor tests; half the training scenes keep the clean table, clutter comes and goes independently,
    and the physics is that of the clean scene."""
    assert parse_perturb("randomized_scene").randomized_scene and parse_perturb("randomized_scene").active
    assert not set(TRAIN_TABLE_MATERIALS) & set(TABLE_MATERIALS)
    assert not set(CLUTTER_SHAPES) & set(DISTRACTOR_SHAPES)
    assert parse_perturb("static_distractors,unseen_env,level=6").n_clutter == 0  # tests never get clutter
    clean = make_env("pick_place", "ball_left", image_size=48)
    env = make_env("pick_place", "ball_left", image_size=48, perturb="randomized_scene")
    table = env.model.geom("table").id
    clutter = [int(env.model.body_mocapid[env.model.body(f"clutter{i}").id]) for i in range(CLUTTER_SLOTS)]
    restyled, used, counts = 0, set(), set()
    for seed in range(16):
        a = env.reset(seed=seed)[0]["agentview_rgb"]
        b = clean.reset(seed=seed)[0]["agentview_rgb"]
        used.add(env.model.material(int(env.model.geom_matid[table])).name)
        restyled += not np.array_equal(env.model.mat_rgba, clean.model.mat_rgba)
        n = int((env.data.mocap_pos[clutter, 2] > 0).sum())
        counts.add(n)
        assert np.array_equal(a, b) == (n == 0 and np.array_equal(env.model.mat_rgba, clean.model.mat_rgba))
        assert np.array_equal(env.privileged_state()["ee_pos"], clean.privileged_state()["ee_pos"])
    assert used <= set(TRAIN_TABLE_MATERIALS) and len(used) > 2
    assert 3 <= restyled <= 13
    assert 0 in counts and len(counts) > 2


def test_servo_repeatability_is_about_ten_mm():
    rp = measure_repeatability(trials=20, seed=0)["rp_mm"]
    assert 5.0 < rp < 15.0
    ideal = make_env("pick_place", 0, render=False)
    ideal.reset(seed=0)
    for _ in range(3):
        ideal.step(np.array([0.5, 0, 0, 0, 0, 0, -1]))
    s = ideal.privileged_state()
    assert np.linalg.norm(s["cmd_pos"] - s["ee_pos"]) < 0.003  # ideal mode tracks the command
