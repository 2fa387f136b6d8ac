"""The LIBERO adapter against the real environment (skipped when the ``libero`` extra is not installed)."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from pivla.envs.libero import _backend

requires_libero = pytest.mark.skipif(
    not _backend.available(), reason=f"LIBERO not importable; {_backend.INSTALL_HINT}"
)

SIZE = 64


def test_missing_extra_names_the_fix(monkeypatch):
    monkeypatch.setattr(_backend, "_modules", None)
    monkeypatch.setitem(sys.modules, "libero.libero", None)
    with pytest.raises(ImportError, match="make setup-libero"):
        _backend.libero()


@pytest.fixture(scope="module")
def env():
    from pivla.envs import make_env

    e = make_env("libero", "libero_spatial", 0, image_size=SIZE, max_steps=4)
    yield e
    e.close()


@requires_libero
def test_tasks_limits_and_instructions():
    from pivla.envs import list_tasks, select_tasks

    spatial = list_tasks("libero", "libero_spatial")
    assert len(spatial) == 10 and {t.max_steps for t in spatial} == {220}
    assert {t.max_steps for t in list_tasks("libero", "libero_10")} == {520}
    lan = list_tasks("libero", "libero_spatial_lan")
    # Same tasks, paraphrased instructions: the instruction must come from the BDDL, not the task name.
    assert [t.name for t in lan] == [t.name for t in spatial]
    assert any(a.instruction != b.instruction for a, b in zip(lan, spatial))
    assert [t.index for t in select_tasks("libero", "libero_object", "0,3")] == [0, 3]
    with pytest.raises(ValueError, match="unknown LIBERO suite"):
        list_tasks("libero", "libero_nonexistent")


@requires_libero
def test_observation_keys_shapes_and_reset(env):
    obs, info = env.reset(options={"init_state": 53})
    assert info["init_state"] == 3 and info["success"] is False
    assert set(obs) == {"agentview_rgb", "eye_in_hand_rgb", "ee_pos", "ee_ori", "gripper_states", "joint_states",
                        "instruction"}
    for key in ("agentview_rgb", "eye_in_hand_rgb"):
        assert obs[key].shape == (SIZE, SIZE, 3) and obs[key].dtype == np.uint8
    assert obs["ee_pos"].shape == (3,) and obs["ee_ori"].shape == (3,)
    assert obs["gripper_states"].shape == (2,) and obs["joint_states"].shape == (7,)
    assert obs["instruction"] == env.instruction and "bowl" in obs["instruction"]
    assert env.observation_space.contains(dict(obs))
    # The same official init state gives the same scene (to the solver's warm start, which the state omits).
    again, _ = env.reset(options={"init_state": 3})
    np.testing.assert_allclose(again["joint_states"], obs["joint_states"], atol=1e-3)
    np.testing.assert_allclose(again["ee_pos"], obs["ee_pos"], atol=1e-3)


@requires_libero
def test_images_are_upright(env):
    """Compare with MuJoCo's own renderer (top row first) on the same state: ours must match it, not its flip."""
    import mujoco

    obs, _ = env.reset(options={"init_state": 0})
    rs = env.robosuite_env
    renderer = mujoco.Renderer(rs.sim.model._model, SIZE, SIZE)
    try:
        for key, cam in (("agentview_rgb", "agentview"), ("eye_in_hand_rgb", "robot0_eye_in_hand")):
            renderer.update_scene(rs.sim.data._data, camera=cam)
            ref = renderer.render().astype(np.float64).mean(-1)
            ours = obs[key].astype(np.float64).mean(-1)
            same = np.corrcoef(ours.ravel(), ref.ravel())[0, 1]
            flipped = np.corrcoef(ours.ravel(), ref[::-1].ravel())[0, 1]
            assert same > 0.8 and same > flipped + 0.2, (key, same, flipped)
    finally:
        renderer.close()


def _count_renders(env) -> list[str]:
    """Record the camera of every frame the env's renderer draws from now on (``del sim.render`` undoes it)."""
    sim, calls = env.robosuite_env.sim, []
    real = sim.render
    sim.render = lambda *a, **k: calls.append(k["camera_name"]) or real(*a, **k)
    return calls


@requires_libero
def test_frames_are_robosuite_camera_observables_rendered_when_read():
    """An image is rendered when first read and is, pixel for pixel, what robosuite's camera observable gives
    on the same state (flipped upright); testing for a key does not render, and reading a frame after the env
    stepped on raises."""
    from pivla.envs import make_env
    from pivla.envs.libero._backend import libero
    from pivla.envs.libero.env import _bddl_path, _benchmark

    env = make_env("libero", "libero_spatial", 0, image_size=SIZE, settle_steps=0)
    lib = libero()
    bench = _benchmark("libero_spatial")
    ref = lib.ControlEnv(bddl_file_name=_bddl_path(bench, 0), use_camera_obs=True, has_offscreen_renderer=True,
                         camera_names=["agentview", "robot0_eye_in_hand"], camera_heights=SIZE, camera_widths=SIZE,
                         ignore_done=True, hard_reset=False)
    try:
        ref.reset()
        flags = lib.mujoco.mjtRndFlag
        ref.sim._render_context_offscreen.scn.flags[flags.mjRND_REFLECTION] = 0  # as the adapter renders
        sim, calls = env.robosuite_env.sim, _count_renders(env)
        obs, _ = env.reset(options={"init_state": 0})
        # the same scene: fixtures are placed by the model (sampled at each reset), the rest is the state
        ref.sim.model.body_pos[:] = sim.model.body_pos
        ref.sim.model.body_quat[:] = sim.model.body_quat
        ref.set_init_state(sim.get_state().flatten())
        expected = ref.env._get_observations(force_update=True)
        assert "agentview_rgb" in obs and not calls
        for key, cam in (("agentview_rgb", "agentview"), ("eye_in_hand_rgb", "robot0_eye_in_hand")):
            np.testing.assert_array_equal(obs[key], expected[f"{cam}_image"][::-1])
            obs[key]  # kept: read again without rendering
        assert calls == ["agentview", "robot0_eye_in_hand"]
        unread, *_ = env.step(np.zeros(7))
        unread["joint_states"]
        env.step(np.zeros(7))
        assert len(calls) == 2  # proprio only: nothing rendered
        with pytest.raises(RuntimeError, match="after the env moved on"):
            unread["agentview_rgb"]
        np.testing.assert_array_equal(obs["agentview_rgb"], expected["agentview_image"][::-1])  # read in time
    finally:
        ref.close()
        env.close()


@requires_libero
def test_a_fixed_horizon_without_monitoring_renders_only_its_query_steps(synthetic_data, tmp_path, env):
    """Why LIBERO's fixed-horizon evaluation is ~3x faster with baseline monitoring off: between queries
    nothing reads the cameras, so nothing is rendered."""
    from pivla.control.executors import executor_config, make_executor
    from pivla.control.runner import run_episode
    from pivla.policy import load_policy
    from pivla.training.trainer import train
    from tests.conftest import tiny_train_config

    policy = load_policy(train(tiny_train_config(synthetic_data, tmp_path / "run", steps=2, val_fraction=0.0)))
    calls = _count_renders(env)
    try:
        for monitor in (False, True):
            calls.clear()
            res = run_episode(env, policy, make_executor(executor_config("fixed", monitor=monitor)), seed=0,
                              reset_options={"init_state": 0})
            assert res.steps == 4 and res.queries == 1
            if monitor:  # the trace's U reads the target encoder's camera on every step
                assert calls.count("agentview") == res.steps, calls
            else:
                assert len(calls) == 2 * res.queries, calls
    finally:
        del env.robosuite_env.sim.render


@requires_libero
def test_action_conversion_moves_the_arm_and_gripper(env):
    with pytest.raises(ValueError, match="shape"):
        env.to_env_action(np.zeros(6))
    with pytest.raises(ValueError, match="non-finite"):
        env.to_env_action([0, 0, np.nan, 0, 0, 0, 1])
    np.testing.assert_array_equal(env.to_env_action([2, -3, 0.5, 0, 0, 0, 0.2]), [1, -1, 0.5, 0, 0, 0, 1])
    assert env.to_env_action([0, 0, 0, 0, 0, 0, 0])[6] == -1  # no close command: open
    for axis in range(3):
        obs, _ = env.reset(options={"init_state": 0})
        start = obs["ee_pos"].copy()
        action = np.zeros(7)
        action[axis], action[6] = 1.0, -1.0
        for _ in range(3):
            obs, *_ = env.step(action)
        moved = obs["ee_pos"] - start
        assert moved[axis] > 0.01 and moved[axis] > 2 * np.abs(np.delete(moved, axis)).max(), (axis, moved)
    opened = obs["gripper_states"][0] - obs["gripper_states"][1]
    obs, _, terminated, truncated, info = env.step([0, 0, 0, 0, 0, 0, 1])
    assert obs["gripper_states"][0] - obs["gripper_states"][1] < opened  # +1 closes
    assert terminated is False and truncated is True and info["success"] is False  # max_steps=4 reached


@requires_libero
def test_smoke_episode_into_dataset(env, tmp_path):
    """One short rendered episode through the env contract, stored in the dataset layout and read back."""
    from pivla.data.episode import Episode
    from pivla.data.hdf5 import read_episodes, write_episodes

    obs, _ = env.reset(options={"init_state": 1})
    frames, actions = [], []
    rng = np.random.default_rng(0)
    while True:
        action = np.clip(rng.normal(0, 0.3, 7), -1, 1)
        frames.append({k: v for k, v in obs.items() if k != "instruction"})
        actions.append(action)
        obs, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            break
    ep = Episode(actions=np.array(actions), obs={k: np.stack([f[k] for f in frames]) for k in frames[0]},
                 instruction=env.instruction, success=info["success"], source="random")
    path = write_episodes(tmp_path / "smoke.hdf5", [ep])
    back = read_episodes(path)
    assert len(back) == 1 and len(back[0]) == 4 and back[0].instruction == env.instruction
    assert back[0].obs["agentview_rgb"].shape == (4, SIZE, SIZE, 3)


@requires_libero
def test_an_official_episode_does_not_depend_on_the_one_before():
    """robosuite keeps the gripper's integrated command across resets: after an episode that ended with the
    gripper closed, the same official state must still start exactly as in a fresh env."""
    from pivla.envs import make_env

    fresh, used = (make_env("libero", "libero_10", 3, render=False) for _ in range(2))
    try:
        start, _ = fresh.reset(seed=12, options={"init_state": 12})
        used.reset(seed=3, options={"init_state": 3})
        for _ in range(5):
            used.step(np.array([0, 0, 0, 0, 0, 0, 1.0]))  # close the gripper
        again, _ = used.reset(seed=12, options={"init_state": 12})
        for key in ("ee_pos", "gripper_states", "joint_states"):
            np.testing.assert_array_equal(again[key], start[key], err_msg=key)
    finally:
        fresh.close()
        used.close()


@requires_libero
def test_a_failed_episode_reports_how_much_of_its_goal_holds():
    """LIBERO-10 task 0 wants two objects in the basket: with one put there, the episode that runs out of
    steps ends with half of its goal met."""
    from pivla.envs import make_env

    env = make_env("libero", "libero_10", 0, render=False, max_steps=5)
    try:
        env.reset(seed=0, options={"init_state": 0})
        sim, objects = env._env.env.sim, env._env.env.objects_dict
        basket = sim.data.body_xpos[sim.model.body_name2id(objects["basket_1"].root_body)]
        joint = objects["alphabet_soup_1"].joints[-1]
        qpos = sim.data.get_joint_qpos(joint).copy()
        qpos[:3] = basket + [0.0, 0.0, 0.08]  # dropped into the basket
        sim.data.set_joint_qpos(joint, qpos)
        sim.forward()
        infos = [env.step(np.zeros(7))[-1] for _ in range(5)]
    finally:
        env.close()
    assert all("stage_progress" not in info for info in infos[:-1])
    assert not infos[-1]["success"] and infos[-1]["stage_progress"] == 0.5


@requires_libero
def test_a_goal_predicate_that_holds_at_the_reset_is_no_progress():
    """LIBERO-10 task 8's goal is both moka pots on the stove and the stove on, and the stove starts on:
    an episode that moves nothing has met none of its goal, one with a pot on the stove half of it."""
    from pivla.envs import make_env

    env = make_env("libero", "libero_10", 8, render=False, max_steps=30)
    try:
        progress = []
        for moved in (False, True):
            env.reset(seed=0, options={"init_state": 0})
            if moved:
                sim, objects = env._env.env.sim, env._env.env.objects_dict
                region = env._env.env.object_sites_dict["flat_stove_1_cook_region"]
                joint = objects["moka_pot_1"].joints[-1]
                qpos = sim.data.get_joint_qpos(joint).copy()
                qpos[:3] = sim.data.get_site_xpos(region.name) + [0.0, 0.0, 0.1]  # settles on the burner
                sim.data.set_joint_qpos(joint, qpos)
                sim.forward()
            infos = [env.step(np.zeros(7))[-1] for _ in range(30)]
            progress.append(infos[-1]["stage_progress"])
    finally:
        env.close()
    assert progress == [0.0, 0.5]


@requires_libero
def test_render_false_has_no_images():
    from pivla.envs import make_env

    env = make_env("libero", "libero_object", 0, render=False)
    try:
        obs, _ = env.reset()
        assert "agentview_rgb" not in obs and "eye_in_hand_rgb" not in obs
        assert obs["ee_pos"].shape == (3,) and "basket" in obs["instruction"]
    finally:
        env.close()


@requires_libero
def test_tiny_policy_evaluates_on_libero_from_given_init_states(synthetic_data, tmp_path):
    """A smoke test in the default set: one task, short episodes, a tiny policy, the same runner and
    results.json as the twin; episode e starts from official init state first_init_state + e."""
    import json

    from pivla.control.executors import executor_config
    from pivla.evaluation.runner import EvalConfig, evaluate
    from pivla.training.trainer import train
    from tests.conftest import tiny_train_config

    run = train(tiny_train_config(synthetic_data, tmp_path / "run", steps=4, val_fraction=0.0))
    cfg = EvalConfig(policy=str(run), out=str(tmp_path / "eval"), env="libero", suite="libero_spatial", tasks="0",
                     executor=executor_config("fixed"), episodes=2, max_steps=3, videos=0, first_init_state=40)
    res = evaluate(cfg, progress=False)
    assert res["episodes"] == 2 and res["executor"] == "fixed" and 0 <= res["ci95"][0] <= res["ci95"][1] <= 1
    rows = [json.loads(line) for line in (tmp_path / "eval" / "episodes.jsonl").read_text().splitlines()]
    assert sorted(r["init_state"] for r in rows) == [40, 41] and all(r["steps"] == 3 for r in rows)


@requires_libero
def test_sampled_scenes_are_seeded_and_never_official():
    """``{"init": "random", "seed": s}``: the same scene for the same seed (every qpos and qvel, and the fixture
    placements), another for another seed, none equal to an official init state; official states are found."""
    from pivla.envs import make_env

    env = make_env("libero", "libero_goal", 8, render=False, settle_steps=0)
    try:
        model = env.robosuite_env.sim.model._model
        _, info = env.reset(options={"init": "random", "seed": 7})
        first, fixtures = env._env.get_sim_state(), model.body_pos.copy()
        assert info["init_state"] is None and info["init_seed"] == 7 and info["redraws"] == 0
        assert env.init_state is None and env.init_seed == 7
        env.reset(options={"init": "random", "seed": 8})
        other = env._env.get_sim_state()
        env.reset(options={"init_state": 3})  # in between: an official state must not leak into the next sample
        env.reset(options={"init": "random", "seed": 7})
        np.testing.assert_array_equal(env._env.get_sim_state(), first)
        np.testing.assert_array_equal(model.body_pos, fixtures)
        assert np.abs(other[1:] - first[1:]).max() > 1e-3
        for state in (first, other):
            assert env.official_match(state) is None
        assert env.official_match(env.init_states[11]) == 11
    finally:
        env.close()


@requires_libero
def test_a_sample_equal_to_an_official_state_is_drawn_again(monkeypatch):
    from pivla.envs import make_env

    env = make_env("libero", "libero_goal", 8, render=False, settle_steps=0)
    try:
        env.reset(options={"init": "random", "seed": 5})
        drawn = env._env.get_sim_state()
        official = env.init_states.copy()
        official[20] = drawn  # pretend seed 5's scene were official state 20
        monkeypatch.setattr(env, "init_states", official)
        _, info = env.reset(options={"init": "random", "seed": 5})
        assert info["redraws"] == 1 and env.official_match(env._env.get_sim_state()) is None
        assert np.abs(env._env.get_sim_state()[1:] - drawn[1:]).max() > 1e-3
    finally:
        env.close()


@requires_libero
def test_random_init_config_and_bad_reset_options():
    from pivla.envs import make_env

    env = make_env("libero", "libero_object", 0, render=False, init="random", settle_steps=0)
    try:
        _, info = env.reset(seed=3)
        state = env._env.get_sim_state()
        assert info["init_state"] is None and info["init_seed"] is not None
        _, again = env.reset(seed=3)
        assert again["init_seed"] == info["init_seed"]
        np.testing.assert_array_equal(env._env.get_sim_state(), state)
        _, official = env.reset(options={"init_state": 2})
        assert official["init_state"] == 2 and official["init_seed"] is None
        with pytest.raises(ValueError, match="init"):
            env.reset(options={"init": "sampled"})
        with pytest.raises(ValueError, match="init_state"):
            env.reset(options={"init": "random", "init_state": 1})
        with pytest.raises(ValueError, match="init"):
            env.reset(options={"seeed": 1})
    finally:
        env.close()
    with pytest.raises(ValueError, match="init must be one of"):
        make_env("libero", "libero_object", 0, render=False, init="sampled")


@requires_libero
def test_a_sampled_object_in_a_fixture_starts_in_it():
    """LIBERO-Spatial task 4's bowl starts in the top drawer in sampled scenes as in the official states (placed
    with the drawer counted twice, after a soft reset, it fell a metre onto the cabinet and off the table)."""
    from pivla.envs import make_env

    env = make_env("libero", "libero_spatial", 4, render=False)
    try:
        rs = env.robosuite_env
        bowl = rs.sim.model.body_name2id(rs.objects_dict["akita_black_bowl_1"].root_body)
        env.reset(options={"init_state": 0})
        official = rs.sim.data.body_xpos[bowl].copy()
        for seed in (0, 1):
            env.reset(options={"init": "random", "seed": seed})
            pos = rs.sim.data.body_xpos[bowl]
            assert abs(pos[2] - official[2]) < 0.02 and np.linalg.norm(pos[:2] - official[:2]) < 0.1, (pos, official)
    finally:
        env.close()


def _sphere_soup(n_lat: int = 40, n_lon: int = 80):
    """A unit sphere as MuJoCo often stores meshes: three vertices of its own per face, texture u = longitude."""
    lat, lon = np.linspace(0, np.pi, n_lat + 1), np.linspace(0, 2 * np.pi, n_lon + 1)
    grid = np.stack(np.meshgrid(lat, lon, indexing="ij"), -1)
    xyz = np.stack([np.sin(grid[..., 0]) * np.cos(grid[..., 1]), np.sin(grid[..., 0]) * np.sin(grid[..., 1]),
                    np.cos(grid[..., 0])], -1)
    uv = np.stack([grid[..., 1] / (2 * np.pi), grid[..., 0] / np.pi], -1)
    quads = [((i, j), (i + 1, j), (i + 1, j + 1), (i, j + 1)) for i in range(n_lat) for j in range(n_lon)]
    tris = [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]
    verts = np.array([xyz[p] for t in tris for p in t])
    tex = np.array([uv[p] for t in tris for p in t])
    faces = np.arange(len(verts)).reshape(-1, 3)
    return verts, faces, tex


@requires_libero
def test_a_simplified_mesh_keeps_its_shape_normals_and_texture():
    from pivla.envs.libero._meshes import simplify_mesh

    verts, faces, tex = _sphere_soup()
    drawn = simplify_mesh(verts, faces, tex, faces, max_faces=600)
    assert 500 <= drawn.n_faces <= 600 < len(faces)
    assert len(drawn.verts) == len(drawn.normals) == len(drawn.texcoords) == 3 * drawn.n_faces
    assert np.abs(np.linalg.norm(drawn.verts, axis=1) - 1).max() < 0.05  # still the sphere
    centres = drawn.verts.reshape(-1, 3, 3).mean(1)
    assert np.allclose(np.linalg.norm(drawn.normals, axis=1), 1)
    assert (np.einsum("ij,ij->i", drawn.normals[::3], centres) > 0.9).mean() > 0.95  # facing outwards
    # each corner's texture coordinate is that of an original corner close to it
    ref = tex[np.linalg.norm(verts[None] - drawn.verts[:, None], axis=2).argmin(1)]
    assert np.median(np.abs(drawn.texcoords - ref).sum(1)) < 0.05


def test_mesh_faces_must_be_zero_or_a_real_budget():
    from pivla.envs.libero.env import LiberoEnvConfig

    with pytest.raises(ValueError, match="mesh_faces must be 0"):
        LiberoEnvConfig(mesh_faces=50)


@requires_libero
def test_simplified_meshes_draw_the_same_scene_and_leave_physics_alone():
    """Visual meshes drawn with at most 2000 triangles: the frames of an official state stay within a few grey
    levels of the full meshes' (they are not the same frames), the model's own mesh arrays, which physics and
    the expert's rays read, are untouched, and the arm moves alike."""
    from pivla.envs import make_env

    envs = [make_env("libero", "libero_spatial", 4, image_size=SIZE, mesh_faces=n, seed=0) for n in (0, 2000)]
    try:
        first = [env.reset(options={"init_state": 3})[0] for env in envs]
        for key in ("agentview_rgb", "eye_in_hand_rgb"):
            diff = np.abs(first[0][key].astype(int) - first[1][key].astype(int))
            assert 0 < diff.mean() < 3, key
        full, simplified = (env.robosuite_env.sim.model._model for env in envs)
        for name in ("mesh_vert", "mesh_normal", "mesh_texcoord", "mesh_face", "mesh_facenum", "mesh_vertnum"):
            np.testing.assert_array_equal(getattr(full, name), getattr(simplified, name), err_msg=name)
        action = np.array([0.3, -0.2, 0.1, 0, 0, 0, -1], np.float32)
        after = [env.step(action)[0] for env in envs]
        np.testing.assert_array_equal(after[0]["joint_states"], after[1]["joint_states"])
    finally:
        for env in envs:
            env.close()


@requires_libero
def test_an_evaluation_worker_keeps_one_libero_env(synthetic_data, tmp_path, monkeypatch):
    """Jobs come task after task: moving to the next task closes the env of the one before (each holds ~1 GB)."""
    from pivla.evaluation import runner
    from pivla.training.trainer import train
    from tests.conftest import tiny_train_config

    run = train(tiny_train_config(synthetic_data, tmp_path / "run", steps=2, val_fraction=0.0))
    cfg = runner.EvalConfig(policy=str(run), out=str(tmp_path / "eval"), env="libero", suite="libero_spatial")
    monkeypatch.setattr(runner, "_STATE", {})
    runner._init_worker(cfg, 1)
    first = runner._env(0)
    assert runner._env(0) is first
    second = runner._env(1)
    assert list(runner._STATE["envs"]) == [1] and first._env is None  # closed
    second.close()
