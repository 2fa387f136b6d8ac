"""``pivla collect --env libero``: scripted-expert demonstrations on LIBERO into the dataset layout."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from pivla.cli import main
from pivla.envs.libero import _backend

requires_libero = pytest.mark.skipif(
    not _backend.available(), reason=f"LIBERO not importable; {_backend.INSTALL_HINT}"
)


@pytest.mark.parametrize("flags,message", [(["--perturb", "unseen_env"], "perturb"),
                                           (["--paraphrase"], "paraphrase"),
                                           (["--realism", "servo"], "realism servo"),
                                           (["--place-miss", "0.5"], "place_miss")])
def test_twin_only_options_are_refused(tmp_path, flags, message):
    with pytest.raises(SystemExit, match=message):
        main(["collect", "--env", "libero", "--suite", "libero_spatial", "--tasks", "0", "--episodes", "1",
              "--out", str(tmp_path), *flags])
    assert not list(tmp_path.glob("*.hdf5"))


@requires_libero
def test_suites_without_expert_are_refused(tmp_path):
    with pytest.raises(SystemExit, match="scripted experts exist for the libero_spatial, libero_object"):
        main(["collect", "--env", "libero", "--suite", "libero_90", "--tasks", "0", "--episodes", "1",
              "--out", str(tmp_path)])
    assert not list(tmp_path.glob("*.hdf5"))


@requires_libero
@pytest.mark.slow
def test_collect_one_libero_episode(tmp_path):
    """One rendered expert episode (~20 s): stored frames, actions, success and metadata read back."""
    from pivla.data.read import read_dataset

    code = main(["collect", "--env", "libero", "--suite", "libero_spatial", "--tasks", "5", "--episodes", "1",
                 "--out", str(tmp_path), "--image-size", "32", "--libero-step-factor", "1.5"])
    assert code == 0
    (path,) = tmp_path.glob("*.hdf5")
    assert path.name == "pick_up_the_black_bowl_on_the_ramekin_and_place_it_on_the_plate_demo.hdf5"
    (ep,) = read_dataset(tmp_path)
    T = len(ep)
    assert ep.success and ep.source == "expert" and 30 < T <= 220
    assert ep.instruction == "pick the akita black bowl on the ramekin and place it on the plate"
    assert ep.obs["agentview_rgb"].shape == (T, 32, 32, 3) and ep.obs["eye_in_hand_rgb"].shape == (T, 32, 32, 3)
    assert ep.obs["joint_states"].shape == (T, 7) and ep.obs["ee_pos"].shape == (T, 3)
    assert ep.obs["agentview_rgb"].std() > 5  # real frames, not blank buffers
    assert np.abs(ep.actions).max() <= 1.0 and set(np.unique(ep.actions[:, 6])) <= {-1.0, 1.0}
    assert ep.rewards.sum() == pytest.approx(1.0) and ep.dones[-1]
    assert ep.meta["init_state"] is None and ep.meta["init_seed"] is not None  # a sampled scene, not official
    # The gripper closes (grasp) and opens again (release) in a successful pick-and-place.
    grip = ep.actions[:, 6]
    assert grip[0] == -1 and (grip == 1).any() and grip[-1] == -1
    with h5py.File(path) as f:
        meta = json.loads(f["data"].attrs["env_args"])
    assert meta["env"] == "libero" and meta["task_index"] == 5 and meta["attempts"] == 1
    assert meta["max_steps"] == 220 and meta["collect_max_steps"] == 330  # the policy's limit, the expert's
    assert meta["init"] == "random" and meta["init_states"] == [None] and meta["init_seeds"] == [ep.meta["init_seed"]]


@requires_libero
@pytest.mark.slow
def test_libero_run_end_to_end_on_one_task(tmp_path):
    """`pivla libero run` in miniature: one task, one demonstration from a sampled scene, a few training steps,
    calibration on one validation rollout, fixed and AURD on two official init states each (each visited
    exactly once per executor, paired), and the report."""
    import dataclasses
    import json

    from pivla.data.read import read_dataset
    from pivla.evaluation.runner import load_rows
    from pivla.experiments.studies.libero import LiberoRunConfig, run_libero
    from pivla.training.config import libero_preset

    train = libero_preset()
    model = dataclasses.replace(train.model, image_size=32)
    train = dataclasses.replace(train, model=model, steps=4, batch_size=4, val_fraction=0.0, threads=2)
    cfg = LiberoRunConfig(suite="libero_spatial", out=str(tmp_path / "run"), tasks="0", demos=1, train=train,
                          val_episodes=1, init_states=2, workers=1, max_steps=12)
    report = run_libero(cfg)
    (demo,) = read_dataset(tmp_path / "run" / "data")
    assert demo.meta["init_state"] is None and demo.meta["init_seed"] is not None  # a sampled scene
    for name in ("fixed", "aurd"):
        rows = load_rows(tmp_path / "run" / "eval" / name / "episodes.jsonl")
        assert sorted(r["init_state"] for r in rows) == [0, 1]
    data = json.loads((tmp_path / "run" / "libero.json").read_text())
    assert data["paired"]["aurd_vs_fixed"]["n"] == 2 and "Published figures" in report.read_text()
    assert data["demonstrations"][demo.meta["task"]]["episodes"] == 1  # the task's row says what it learnt from
    assert "Wall time: collect" in report.read_text()
    stages = {"collect", "train", "validation_rollouts", "calibrate", "eval_fixed", "eval_aurd"}
    assert set(data["timings_s"]) == stages and all(t > 0 for t in data["timings_s"].values())
    mtime = (tmp_path / "run" / "policy" / "model.safetensors").stat().st_mtime_ns
    run_libero(cfg)  # every stage done: nothing is redone
    assert (tmp_path / "run" / "policy" / "model.safetensors").stat().st_mtime_ns == mtime

    # a policy trained elsewhere on demonstrations collected elsewhere (one policy for several suites): copied,
    # calibrated on its own, and the same weights play the same official episodes
    other = dataclasses.replace(cfg, out=str(tmp_path / "other"), data=str(tmp_path / "run" / "data"),
                                policy=str(tmp_path / "run" / "policy"), executors=("fixed",))
    run_libero(other)
    assert not (tmp_path / "other" / "data").exists() and (tmp_path / "other" / "policy" / "calibration.json").exists()
    copied = json.loads((tmp_path / "other" / "libero.json").read_text())
    assert copied["policy_copied_from"] == str((tmp_path / "run" / "policy").resolve())
    assert set(copied["timings_s"]) == {"copy_policy", "validation_rollouts", "calibrate", "eval_fixed"}
    assert copied["demonstrations"] == data["demonstrations"]
    played = [[(r["init_state"], r["success"], r["steps"]) for r in load_rows(d / "eval" / "fixed" / "episodes.jsonl")]
              for d in (tmp_path / "run", tmp_path / "other")]
    assert sorted(played[0]) == sorted(played[1])
    with pytest.raises(ValueError, match="has no demonstrations of libero_spatial task"):
        run_libero(dataclasses.replace(other, out=str(tmp_path / "third"), data=str(tmp_path / "empty")))


@requires_libero
@pytest.mark.slow
def test_an_interrupted_libero_task_resumes_at_its_next_attempt(tmp_path, monkeypatch):
    """Kept episodes and the attempt count survive an interruption (~40 s): the rerun plays only the attempts
    not yet made and the task's file holds the episode recorded before the interruption."""
    from pivla.data.read import read_dataset
    from pivla.envs import collect

    played, real = [], collect.run_episode

    def interrupted_after_one(env, actor, seed, **kw):
        if played:
            raise KeyboardInterrupt
        played.append(real(env, actor, seed, **kw))
        return played[-1]

    args = ["collect", "--env", "libero", "--suite", "libero_spatial", "--tasks", "5", "--episodes", "2",
            "--out", str(tmp_path), "--image-size", "32"]
    monkeypatch.setattr(collect, "run_episode", interrupted_after_one)
    with pytest.raises(KeyboardInterrupt):
        main(args)
    assert not list(tmp_path.glob("*.hdf5")) and played[0].success
    replayed = []

    def counted(env, actor, seed, **kw):
        replayed.append(seed)
        return real(env, actor, seed, **kw)

    monkeypatch.setattr(collect, "run_episode", counted)
    assert main(args) == 0
    first, second = read_dataset(tmp_path)
    np.testing.assert_array_equal(first.actions, played[0].actions)
    assert first.meta["init_seed"] == played[0].meta["init_seed"] != second.meta["init_seed"]
    with h5py.File(next(tmp_path.glob("*.hdf5"))) as f:
        attempts = json.loads(f["data"].attrs["env_args"])["attempts"]
    assert len(replayed) == attempts - 1  # attempt 0 was not played again
    assert not (tmp_path / ".partial").exists()


def test_an_unfinished_task_with_other_settings_is_refused(tmp_path):
    from pivla.envs.collect import CollectConfig, _PartialTask
    from pivla.io import atomic_write_json

    cfg = CollectConfig(out=str(tmp_path), env="libero", suite="libero_spatial", noise=0.1)
    partial = _PartialTask(cfg, 5, "task5")
    atomic_write_json(partial.dir / "progress.json", {"settings": {**partial.settings, "noise": 0.0}, "attempts": 3,
                                                      "kept": [0]})
    with pytest.raises(ValueError, match="unfinished collection with other settings"):
        partial.load()
    assert (partial.dir / "progress.json").exists()


def test_demonstrations_get_the_step_factor_times_the_suite_limit(tmp_path, monkeypatch):
    """The expert collects under ``libero_step_factor`` times the suite's limit; a task begun at another limit is
    not continued under this one (its attempts would have ended elsewhere)."""
    from pivla.envs import TaskSpec, collect
    from pivla.io import atomic_write_json

    seen: dict = {}

    def env_seen(*args, **kwargs):
        seen.update(kwargs)
        raise RuntimeError("env made")

    monkeypatch.setattr(collect, "make_env", env_seen)
    spec = TaskSpec(suite="libero_goal", index=3, name="task3", instruction="put it inside", max_steps=300)
    cfg = collect.CollectConfig(out=str(tmp_path), env="libero", suite="libero_goal", episodes=2,
                                libero_step_factor=1.5)
    with pytest.raises(RuntimeError, match="env made"):
        collect._collect_libero_task((cfg, spec))
    assert seen["max_steps"] == 450
    at_limit = collect._PartialTask(collect.CollectConfig(out=str(tmp_path), env="libero", suite="libero_goal"), 3,
                                    spec.name)
    atomic_write_json(at_limit.dir / "progress.json", {"settings": at_limit.settings, "attempts": 3, "kept": []})
    with pytest.raises(ValueError, match="unfinished collection with other settings"):
        collect._collect_libero_task((cfg, spec))
    with pytest.raises(ValueError, match="libero_step_factor must be >= 1"):
        collect.collect_demos(collect.CollectConfig(out=str(tmp_path), env="libero", suite="libero_goal",
                                                    libero_step_factor=0.5))


def test_an_episode_runs_to_the_envs_own_limit():
    """An env made with a longer limit than its task's (LIBERO's collection) runs to its own limit."""
    from types import SimpleNamespace

    from pivla.envs.rollout import run_episode

    class Env:
        task = SimpleNamespace(name="t", max_steps=3)
        max_steps = 7
        unwrapped = property(lambda self: self)

        def reset(self, seed=None, options=None):
            self.t = 0
            return {"state": np.zeros(2)}, {"success": False}

        def step(self, action):
            self.t += 1
            return {"state": np.zeros(2)}, 0.0, False, self.t >= self.max_steps, {"success": False}

    episode = run_episode(Env(), lambda obs: np.zeros(7), seed=0)
    assert len(episode) == 7 and not episode.success


@requires_libero
@pytest.mark.slow
def test_an_unrendered_expert_episode_plays_again_the_same_rendered():
    """What lets a collection play an attempt without frames first: the same env and seed give the same
    episode, action for action, rendered or not (~15 s)."""
    from pivla.envs import make_env
    from pivla.envs.libero.expert import ExpertConfig, RolloutExpert
    from pivla.envs.rollout import run_episode

    env = make_env("libero", "libero_spatial", 5, image_size=32, init_state=0, init="random", mesh_faces=4000)
    actor = RolloutExpert("libero_spatial", 5, ExpertConfig(noise=0.3, miss=1.0))
    try:
        probe, rendered = run_episode(env, actor, 11, frames=False), run_episode(env, actor, 11)
    finally:
        env.close()
    assert not probe.obs and rendered.obs["agentview_rgb"].shape[0] == len(rendered)
    assert probe.success == rendered.success and probe.meta["seed"] == rendered.meta["seed"]
    np.testing.assert_array_equal(probe.actions, rendered.actions)


def test_a_task_that_often_fails_renders_only_its_successes(tmp_path, monkeypatch):
    """Once more than a fifth of a task's attempts have failed, each attempt is first played without frames and
    played again, rendered, only when it succeeds: the kept episodes are the same, every one with frames."""
    from types import SimpleNamespace

    from pivla.data.episode import Episode
    from pivla.envs import TaskSpec, collect
    from pivla.envs.rollout import episode_seed

    attempt_of = {episode_seed(episode_seed(0, 3), k): k for k in range(100)}
    calls: list[tuple[int, bool]] = []

    def play(env, actor, seed, frames=True):
        k = attempt_of[seed]
        calls.append((k, frames))
        obs = {"state": np.zeros((2, 3), np.float32)} if frames else {}
        return Episode(actions=np.zeros((2, 7)), obs=obs, instruction="put it inside", success=k % 2 == 0)

    monkeypatch.setattr(collect, "make_env", lambda *a, **kw: SimpleNamespace(init_state=None, init_seed=1,
                                                                              close=lambda: None))
    monkeypatch.setattr(collect, "RolloutExpert", lambda *a, **kw: None)
    monkeypatch.setattr(collect, "run_episode", play)
    spec = TaskSpec(suite="libero_goal", index=3, name="task3", instruction="put it inside", max_steps=300)
    _, kept, attempts = collect._collect_libero_task(
        (collect.CollectConfig(out=str(tmp_path), env="libero", suite="libero_goal", episodes=10), spec))
    assert attempts == 19 and len(kept) == 10 and all(ep.obs and ep.success for ep in kept)
    assert calls[:5] == [(k, True) for k in range(5)]  # too few attempts yet to tell a hard task
    for k in range(5, 19):
        assert [c for c in calls if c[0] == k] == ([(k, False), (k, True)] if k % 2 == 0 else [(k, False)])


def test_a_task_being_collected_by_another_process_is_refused(tmp_path):
    """Two collections of one task (a rerun beside a worker left by a killed run) would interleave their attempt
    files: the second is refused, naming the task, and the first one's progress is untouched."""
    from pivla.envs import TaskSpec
    from pivla.envs.collect import CollectConfig, _collect_libero_task, _PartialTask
    from pivla.io import atomic_write_json, exclusive_lock

    cfg = CollectConfig(out=str(tmp_path), env="libero", suite="libero_spatial", episodes=2)
    spec = TaskSpec(suite="libero_spatial", index=5, name="task5", instruction="put it there", max_steps=220)
    partial = _PartialTask(cfg, 5, spec.name)
    atomic_write_json(partial.dir / "progress.json", {"settings": partial.settings, "attempts": 3, "kept": []})
    with exclusive_lock(partial.dir / ".lock", "test"), pytest.raises(RuntimeError, match="collection of task5"):
        _collect_libero_task((cfg, spec))
    assert json.loads((partial.dir / "progress.json").read_text())["attempts"] == 3


def test_a_worker_whose_run_was_killed_stops(monkeypatch):
    from pivla.envs import collect

    class Gone:
        def is_alive(self):
            return False

    monkeypatch.setattr(collect.mp, "parent_process", lambda: Gone())
    with pytest.raises(SystemExit, match="has ended"):
        collect._stop_if_orphaned()
    monkeypatch.setattr(collect.mp, "parent_process", lambda: None)  # no pool: the run itself
    collect._stop_if_orphaned()


def test_a_run_refuses_demonstrations_drawn_with_other_meshes(tmp_path):
    """Demonstrations drawn with full meshes (or before the setting existed) and a run that would validate and
    evaluate on simplified ones: refused, naming the file and both settings."""
    from pivla.data.hdf5 import write_episodes
    from pivla.data.synthetic import synthetic_episode
    from pivla.experiments.studies.libero import check_rendering

    episode = synthetic_episode(np.random.default_rng(0), "left", T=3, size=8)
    write_episodes(tmp_path / "a_demo.hdf5", [episode], {"env": "libero", "mesh_faces": 4000})
    check_rendering(tmp_path, 4000)
    write_episodes(tmp_path / "b_demo.hdf5", [episode], {"env": "libero"})
    with pytest.raises(ValueError, match="b_demo.hdf5 was rendered with mesh_faces=0 and this run asks for 4000"):
        check_rendering(tmp_path, 4000)


def test_the_report_counts_failures_that_met_part_of_their_goal(tmp_path):
    """libero.md says which failed episodes ended with some of the goal's predicates true (one of two objects
    in the basket), per task; a failure that met none of its goal is not counted."""
    from pivla.evaluation.runner import EvalConfig, aggregate
    from pivla.experiments.studies.libero import write_libero_report
    from pivla.io import atomic_write_json

    def row(task: str, episode: int, success: bool, progress: float) -> dict:
        return {"task": task, "task_index": int(task[-1]), "episode": episode, "init_state": episode, "seed": episode,
                "success": success, "stage_progress": progress, "steps": 10, "plan_events": [[5, "complete"]] * 2,
                "queries": 2, "control_ms_mean": 1.0, "wall_s": 1.0, "trace": [{"u_act": 0.1, "v": 0.5}] * 10}

    rows = [row("task_0", 0, True, 1.0), row("task_0", 1, False, 0.5), row("task_1", 0, False, 0.0),
            row("task_1", 1, False, 0.5), row("task_1", 2, False, 0.5)]
    target = tmp_path / "eval" / "fixed"
    target.mkdir(parents=True)
    (target / "episodes.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    atomic_write_json(target / "results.json", aggregate(rows, EvalConfig(policy="p", out=str(target)), tau_high=None))
    report = write_libero_report(tmp_path, "libero_10").read_text()
    assert "- fixed: 3 of 4 failures ended with part of the goal met (task_0 1, task_1 2)" in report
