"""The twin's perturbations: unchanged draws for the existing ones, unseen_env outside the training space,
moving distractors, and the mid-episode events (displace_object, push_arm) under both realisms."""

import colorsys
import hashlib

import numpy as np
import pytest

from pivla.envs.rollout import run_episode
from pivla.envs.tabletop import make_env, parse_perturb, tasks
from pivla.envs.tabletop.expert import make_expert
from pivla.envs.tabletop.perturb import (
    DEFAULT_WINDOW,
    NEAR_DISTANCE,
    OBJECT_REACH,
    RECOVERY_CM,
    RECOVERY_WINDOW,
    TABLE_MATERIALS,
    TRAIN_FLOOR_RGB,
    TRAIN_LIGHT_TILT,
    TRAIN_LIGHT_TINT,
    TRAIN_SATURATION,
    TRAIN_TABLE_MATERIALS,
    TRAIN_VALUE,
    TRAIN_WALL_RGB,
    UNSEEN_BACKDROP_SATURATION,
    UNSEEN_DARK,
    UNSEEN_LIGHT_TILT,
    UNSEEN_LIGHT_TINT,
    UNSEEN_PALE,
    DisplaceObject,
    EventTiming,
    PerturbConfig,
    PushArm,
    scene_style,
    training_style,
)

MATERIALS = ("table", "table_checker", "table_grain", "table_dots", "table_tiles", "table_crosses",
             "table_blotches", "table_stripes", "floor", "wall")
ACTIONS = np.array([[0.3, -0.2, 0.1, 0, 0, 0.1, -1], [-0.1, 0.4, -0.3, 0.05, 0, 0, 0.5], [0, 0, 0.2, 0, 0.1, 0, 1]])
OPEN_STILL = np.array([0, 0, 0, 0, 0, 0, -1.0])  # hold the pose, gripper open


def _digests(suite, task, spec, realism, seed) -> tuple[str, str]:
    """(scene, observations): SHA-256 prefixes of what the perturbation drew (materials, colours, light, camera,
    distractor and clutter geoms, mocap poses) and of every observation, over a reset and three steps."""
    env = make_env(suite, task, image_size=32, realism=realism, perturb=spec)
    m, d = env.model, env.data
    scene, observations = hashlib.sha256(), hashlib.sha256()

    def add(obs):
        scene.update(m.material(int(m.geom_matid[m.geom("table").id])).name.encode())
        for name in MATERIALS:
            scene.update(np.ascontiguousarray(m.mat_rgba[m.material(name).id], np.float64).tobytes())
        for arr in (m.light_dir, m.light_diffuse, m.cam_pos, m.cam_quat, d.mocap_pos, d.mocap_quat):
            scene.update(np.ascontiguousarray(arr, np.float64).tobytes())
        for g in range(m.ngeom):
            if m.geom(g).name.startswith(("distractor", "clutter")):
                scene.update(np.ascontiguousarray(m.geom_size[g], np.float64).tobytes())
                scene.update(np.ascontiguousarray(m.geom_rgba[g], np.float64).tobytes())
        for k in sorted(obs):
            if k != "instruction":
                observations.update(k.encode())
                observations.update(np.ascontiguousarray(obs[k]).tobytes())

    add(env.reset(seed=seed)[0])
    for a in ACTIONS:
        add(env.step(a)[0])
    env.close()
    return scene.hexdigest()[:16], observations.hexdigest()[:16]


# Recorded before the event perturbations and the unseen_env partition were added; the demo's training data
# (randomized_scene) and its distractor tests depend on these draws, so they must never change.
UNCHANGED = [
    ("pick_place", "ball_left", "none", "ideal", 3, "747f313f4120449b", "cc1a901b077b0697"),
    ("pick_place", "ball_left", "randomized_scene", "ideal", 0, "1d58336d07cc0077", "24a37f4f092f8298"),
    ("pick_place", "ball_left", "randomized_scene", "ideal", 3, "18cf480d86db5674", "cc1a901b077b0697"),
    ("pick_place", "ball_left", "randomized_scene", "servo", 11, "a660f43ea313601a", "104fe2fe1ac764d2"),
    ("pick_place", "rock_right", "randomized_scene,level=2", "ideal", 1, "f2cf2506abdd9728", "03d0938ba23ac3a6"),
    ("pick_place", "ball_left", "static_distractors", "ideal", 3, "8bec29cb0b639530", "67cf43fb01509068"),
    ("pick_place", "block_away", "dynamic_distractors,level=2", "servo", 11, "551760a597e32f8d", "438301e25351ffe0"),
    ("pick_place", "ball_left", "static_distractors,dynamic_distractors,level=4", "ideal", 5, "200b69475514b40c",
     "00e583f6b69ac5be"),
    ("pick_place", "ball_left", "camera_jitter", "ideal", 11, "749f838fbcf4394b", "d64e6bb98f502b6d"),
    # the drawer's observations since its handle stands 6 cm off the front (before: 96436d24a86214b3)
    ("drawer", "open_drawer", "randomized_scene,level=2", "ideal", 5, "ded415e2a4c5001f", "cb8a3948a4cf6dbf"),
    ("stack", 0, "static_distractors,level=6", "servo", 2, "77346b9e1e567ed8", "365d1f0ebd6e76f1"),
    # unseen_env since its style space was made disjoint from training's (before: eb1eaf05996e1191 /
    # 3ea854fdfc9bb311 and 3fcd9c384a6e98d6 / 58824ffbab313261)
    ("pick_place", "ball_left", "unseen_env", "ideal", 3, "9c17788a7011b688", "b617be4559aee696"),
    ("pick_place", "ball_left", "unseen_env,static_distractors,dynamic_distractors,camera_jitter,level=6", "ideal", 11,
     "fe46e62787dd5aa1", "11e16d16c666cff3"),
]


@pytest.mark.parametrize("case", UNCHANGED, ids=lambda c: f"{c[1]}-{c[2]}-{c[3]}-{c[4]}")
def test_recorded_perturbations_draw_the_same_scenes_and_observations(case):
    *args, scene, observations = case
    got = _digests(*args)
    assert got[0] == scene, "the perturbation draws changed"
    assert got[1] == observations, "same draws, other observations: the scene or the renderer changed"


def test_unseen_env_lies_outside_the_training_space_in_every_component():
    """The style ranges do not overlap (checked on the constants), every unseen_env scene is outside the
    training space in every component, and every training scene (clean or randomized) is inside it."""
    assert not set(TABLE_MATERIALS) & set(TRAIN_TABLE_MATERIALS)
    assert UNSEEN_PALE[0][1] < TRAIN_SATURATION[0] and UNSEEN_DARK[1][1] < TRAIN_VALUE[0]
    assert 1 - UNSEEN_BACKDROP_SATURATION[0] < min(TRAIN_FLOOR_RGB[0], TRAIN_WALL_RGB[0])  # smallest channel
    assert UNSEEN_LIGHT_TILT[0] > TRAIN_LIGHT_TILT and UNSEEN_LIGHT_TINT[1] < TRAIN_LIGHT_TINT[0]
    for task in ("rock_right", "ball_left", "block_away"):  # the rock's grey and the others' colours are avoided
        unseen = make_env("pick_place", task, render=False, perturb="unseen_env")
        train = make_env("pick_place", task, render=False, perturb="randomized_scene")
        clean = make_env("pick_place", task, render=False)
        clean.reset(seed=0)
        assert all(training_style(scene_style(clean.model)).values())
        used = set()
        for seed in range(60):
            unseen.reset(seed=seed)
            style = scene_style(unseen.model)
            assert not any(training_style(style).values()), (seed, style)
            used.add(style.table_material)
            object_rgb = np.array(tasks.OBJECTS[task.split("_")[0]].rgba[:3])
            assert np.linalg.norm(np.array(style.table_rgb) - object_rgb) > 0.3
            train.reset(seed=seed)
            assert all(training_style(scene_style(train.model)).values()), seed
        assert used == set(TABLE_MATERIALS)


def test_unseen_table_colours_are_pale_or_dark():
    env = make_env("pick_place", "ball_left", render=False, perturb="unseen_env")
    pale = dark = 0
    for seed in range(40):
        env.reset(seed=seed)
        _, s, v = colorsys.rgb_to_hsv(*scene_style(env.model).table_rgb)
        pale += s <= UNSEEN_PALE[0][1] + 1e-9 and v >= UNSEEN_PALE[1][0] - 1e-9
        dark += v <= UNSEEN_DARK[1][1] + 1e-9
    assert pale + dark == 40 and pale > 5 and dark > 5


def test_dynamic_distractors_move_every_step_and_static_ones_stay():
    env = make_env("pick_place", "block_left", render=False, perturb="static_distractors,dynamic_distractors,level=4")
    env.reset(seed=2)
    ids = [int(env.model.body_mocapid[env.model.body(f"distractor{i}").id]) for i in range(4)]
    track = [env.data.mocap_pos[ids].copy()]
    for _ in range(10):
        env.step(OPEN_STILL)
        track.append(env.data.mocap_pos[ids].copy())
    steps = np.linalg.norm(np.diff(np.array(track), axis=0)[..., :2], axis=-1)  # (10, 4)
    assert (steps[:, :2] == 0).all()  # the first half stand still
    assert (steps[:, 2:] > 0.002).all() and (steps[:, 2:] < 0.0071).all()  # 3-7 cm/s at 10 Hz


def _track(env, seed, actor=None, steps=14):
    """Object and tool-centre positions in the observation after reset and after each step."""
    obs, _ = env.reset(seed=seed)
    if actor is not None:
        actor.reset(env, seed)
    name = env.task.goals[0].obj
    objs, tools = [], []
    for t in range(steps + 1):
        s = env.privileged_state()
        objs.append(s["objects"][name]["pos"].copy() if name else np.zeros(3))
        tools.append(s["ee_pos"].copy())
        if t < steps:
            obs, *_ = env.step(actor(obs) if actor is not None else OPEN_STILL)
    return np.array(objs), np.array(tools)


@pytest.mark.parametrize("realism", ["ideal", "servo"])
@pytest.mark.parametrize("cm", [2, 4, 6])
def test_displace_object_jumps_once_at_its_step_by_its_level(realism, cm):
    env = make_env("pick_place", "block_left", render=False, realism=realism, perturb=f"displace_object={cm}")
    objs, _ = _track(env, seed=4)
    [event] = env.perturber.events
    t0 = event["step"]
    assert DEFAULT_WINDOW[0] <= t0 <= DEFAULT_WINDOW[1] and event["object"] == "block"
    moves = np.linalg.norm(np.diff(objs, axis=0), axis=1)
    assert moves[t0] == pytest.approx(cm / 100, abs=1e-3)  # in the observation after step t0
    assert np.delete(moves, t0).max() < 1e-4  # at rest before and after
    shift = np.array(event["shift"])
    assert np.linalg.norm(shift) == pytest.approx(cm / 100) and shift @ [0, 1, 0] <= 1e-9  # never along "left"


def test_perturber_step_returns_the_events_it_fired():
    """What the env needs to measure success from where a displaced object landed."""
    env = make_env("pick_place", "ball_right", render=False, perturb="displace_object=4,push_arm=2")
    returned = []
    step = env.perturber.step
    env.perturber.step = lambda data, dt: returned.append(step(data, dt)) or returned[-1]
    _track(env, seed=9, steps=10)
    fired = [(t, e["kind"]) for t, events in enumerate(returned) for e in events]
    assert sorted(fired) == sorted((e["step"], e["kind"]) for e in env.perturber.events) and len(fired) == 2


def test_an_event_at_level_zero_is_the_clean_episode():
    clean = _digests("pick_place", "rock_left", "none", "servo", 6)
    assert _digests("pick_place", "rock_left", "displace_object=0,push_arm=0", "servo", 6) == clean
    env = make_env("pick_place", "rock_left", render=False, perturb="displace_object=0,push_arm=0")
    _track(env, seed=6)
    assert [e["kind"] for e in env.perturber.events] == ["displace_object", "push_arm"]
    assert not parse_perturb("displace_object=0").active and parse_perturb("displace_object=2").active


def test_displace_object_near_fires_as_the_gripper_closes_in_and_the_expert_recovers():
    env = make_env("pick_place", "ball_away", render=False, perturb="displace_object=4@near")
    objs, tools = _track(env, seed=1, actor=make_expert(), steps=40)
    [event] = env.perturber.events
    t0 = event["step"]
    gaps = np.linalg.norm(tools - objs, axis=1)
    assert gaps[t0] <= NEAR_DISTANCE < gaps[:t0].min()  # the first observation that close
    moves = np.linalg.norm(np.diff(objs, axis=0), axis=1)
    assert moves[t0] == pytest.approx(0.04, abs=1e-3) and moves[:t0].max() < 1e-4
    assert env.privileged_state()["objects"]["ball"]["pos"][0] > objs[t0 + 1][0] + 0.05  # then moved away (+x)


@pytest.mark.parametrize("realism", ["ideal", "servo"])
def test_push_arm_moves_the_tool_once_by_its_level_and_the_offset_stays(realism):
    env = make_env("pick_place", "rock_right", render=False, realism=realism, perturb="push_arm=4")
    objs, tools = _track(env, seed=3)
    [event] = env.perturber.events
    t0 = event["step"]
    assert DEFAULT_WINDOW[0] <= t0 <= DEFAULT_WINDOW[1]
    moves = tools[1:] - tools[:-1]
    assert np.linalg.norm(moves[t0]) == pytest.approx(0.04, rel=0.05)
    assert moves[t0] @ np.array(event["tool_shift"]) / 0.04 ** 2 > 0.95  # in the drawn direction
    assert abs(moves[t0][2]) < 0.002  # horizontally
    assert np.linalg.norm(moves[t0 + 1]) < 0.002  # settles within the next step
    assert np.linalg.norm(np.delete(moves, [t0, t0 + 1], axis=0), axis=1).max() < 1e-3
    assert np.linalg.norm(tools[-1] - tools[t0 + 1]) < 0.002  # the offset stays
    assert np.abs(np.diff(objs, axis=0)).max() < 1e-4


def test_event_draws_depend_on_the_seed_only():
    """The step and direction come from the episode seed, not from what the policy does or which other
    perturbations run, so every executor meets the same event."""
    a = make_env("pick_place", "block_right", render=False, perturb="displace_object=4")
    b = make_env("pick_place", "block_right", render=False, perturb="unseen_env,level=3,displace_object=4,push_arm=2")
    for seed in range(5):
        a.reset(seed=seed)
        b.reset(seed=seed)
        assert a.perturber._plans["displace_object"] == b.perturber._plans["displace_object"]
    steps = {seed: (a.reset(seed=seed), a.perturber._plans["displace_object"].step)[1] for seed in range(30)}
    assert set(steps.values()) == set(range(DEFAULT_WINDOW[0], DEFAULT_WINDOW[1] + 1))


def test_event_spec_grammar():
    cfg = parse_perturb("displace_object=4, push_arm=2@near, static_distractors")
    assert cfg.displace_object == DisplaceObject(0.04) and cfg.push_arm == PushArm(0.02, EventTiming("near"))
    assert cfg.static_distractors and cfg.level == 3
    for spec in ("displace_object=6@3-9", "push_arm=2.5", "unseen_env,displace_object=0,push_arm=6@near"):
        assert parse_perturb(parse_perturb(spec).spec()) == parse_perturb(spec)
    assert parse_perturb("displace_object=6@3-9").displace_object.timing == EventTiming("step", (3, 9))
    assert PerturbConfig(push_arm=PushArm(0.04)).spec() == "push_arm=4"
    for bad, msg in (("displace_object=-1", "0..10"), ("push_arm=11", "0..10"), ("push_arm=x", "number of cm"),
                     ("displace_object=2@soon", "timing"), ("push_arm=1,push_arm=2", "twice"),
                     ("displace_object", "unknown perturbation")):
        with pytest.raises(ValueError, match=msg):
            parse_perturb(bad)
    assert EventTiming("step", [3, 9]) == EventTiming("step", (3, 9))
    for bad in (("step", (7, 3)), ("step", (1, 2, 3)), ("near", (3, 9))):
        with pytest.raises(ValueError, match="window"):
            EventTiming(*bad)
    with pytest.raises(ValueError, match="trigger"):
        EventTiming("soon")
    with pytest.raises(ValueError, match="no object to displace"):
        make_env("drawer", "open_drawer", render=False, perturb="displace_object=2")


def test_servo_realism_runs_every_perturbation_at_once():
    spec = "unseen_env,static_distractors,dynamic_distractors,camera_jitter,level=4,displace_object=4,push_arm=4"
    env = make_env("pick_place", "ball_left", image_size=32, realism="servo", perturb=spec)
    expert = make_expert()
    obs, _ = env.reset(seed=5)
    expert.reset(env, 5)
    frames = [obs["agentview_rgb"]]
    for _ in range(12):
        obs, *_ = env.step(expert(obs))
        frames.append(obs["agentview_rgb"])
    assert sorted(e["kind"] for e in env.perturber.events) == ["displace_object", "push_arm"]
    assert all(not np.array_equal(a, b) for a, b in zip(frames, frames[1:]))
    drawer = make_env("drawer", "close_drawer", render=False, realism="servo", perturb="push_arm=3@near")
    _track(drawer, seed=0, actor=make_expert(), steps=20)
    assert [e["kind"] for e in drawer.perturber.events] == ["push_arm"]


def test_recovery_disturbs_its_share_of_episodes_and_the_expert_recovers():
    """Training data with the tests' events in it: about the share asked for is disturbed, by a distance and at a
    step in the recovery ranges, and the expert (closed on the live state) still finishes those episodes."""
    env = make_env("pick_place", "block_left", render=False, realism="servo", perturb="randomized_scene,recovery=0.5")
    expert = make_expert(0.3, 0.3)
    kinds, successes = [], 0
    for seed in range(24):
        ep = run_episode(env, expert, seed, frames=False)
        kinds += [e["kind"] for e in env.perturber.events]
        successes += ep.success
        for plan in env.perturber._plans.values():
            assert RECOVERY_CM[0] / 100 <= plan.distance <= RECOVERY_CM[1] / 100
            assert RECOVERY_WINDOW[0] <= plan.step <= RECOVERY_WINDOW[1]
    assert 6 <= len(kinds) <= 18 and set(kinds) == {"displace_object", "push_arm"}
    assert successes >= 21
    drawer = make_env("drawer", "open_drawer", render=False, perturb="recovery=1")  # no object: pushes only
    for seed in range(4):
        drawer.reset(seed=seed)
        assert list(drawer.perturber._plans) == ["push_arm"]


def test_recovery_leaves_every_other_draw_of_the_episode_as_it_was():
    """Its stream is its own: the scene, the layout and a tested event are drawn the same with or without it."""
    assert _digests("pick_place", "ball_left", "randomized_scene,recovery=0.5", "ideal", 3)[0] == UNCHANGED[2][5]
    a = make_env("pick_place", "block_right", render=False, perturb="displace_object=4")
    b = make_env("pick_place", "block_right", render=False, perturb="displace_object=4,recovery=1")
    for seed in range(5):
        a.reset(seed=seed)
        b.reset(seed=seed)
        assert a.perturber._plans["displace_object"] == b.perturber._plans["displace_object"]


def test_recovery_spec_grammar():
    cfg = parse_perturb("randomized_scene, recovery=0.4")
    assert cfg.recovery == 0.4 and cfg.active and parse_perturb(cfg.spec()) == cfg
    assert not parse_perturb("none").recovery
    for bad in ("recovery=0", "recovery=1.5", "recovery=nan", "recovery=x", "recovery=0.2,recovery=0.3"):
        with pytest.raises(ValueError, match="recovery"):
            parse_perturb(bad)
    with pytest.raises(ValueError, match="recovery"):
        PerturbConfig(recovery=-0.1)


def test_scatter_starts_its_share_of_objects_beside_their_region_and_the_task_still_holds():
    """scatter=P moves the first object's start by up to RECOVERY_CM[1] in a share of the episodes, to spots the
    displacement test may land it on; success is judged from the new start and the other draws stay as they were."""
    plain = make_env("pick_place", "ball_left", render=False, perturb="randomized_scene")
    env = make_env("pick_place", "ball_left", render=False, perturb="randomized_scene,scatter=0.5")
    moved = 0
    for seed in range(30):
        plain.reset(seed=seed)
        env.reset(seed=seed)
        a = plain.privileged_state()["objects"]["ball"]["pos"][:2]
        b = env.privileged_state()["objects"]["ball"]["pos"][:2]
        shift = float(np.linalg.norm(b - a))
        assert shift <= RECOVERY_CM[1] / 100 + 1e-6
        assert OBJECT_REACH[0] <= np.linalg.norm(b) <= OBJECT_REACH[1] or shift < 1e-9
        assert np.allclose(env._initial["ball"][:2], b, atol=2e-3)  # judged from where it starts
        moved += shift > 1e-9
        assert env.layout == plain.layout  # the task's own draw is untouched
    assert 8 <= moved <= 22
    assert parse_perturb("scatter=0.5,recovery=0.5").spec() == "recovery=0.5,scatter=0.5"
    with pytest.raises(ValueError, match="scatter"):
        parse_perturb("scatter=2")
