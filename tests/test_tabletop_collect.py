"""Collection end to end: CLI -> LIBERO-layout HDF5 -> training data pipeline; worker-count independence."""

import dataclasses
import functools
import signal
import subprocess
import sys
import time
from pathlib import Path

import av
import numpy as np
import pytest

from pivla.cli import main
from pivla.data.read import read_dataset


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("twin") / "data"
    code = main(["collect", "--env", "tabletop", "--suite", "pick_place", "--tasks", "block_left,ball_away",
                 "--episodes", "2", "--out", str(out), "--seed", "3", "--perturb", "static_distractors,level=2",
                 "--image-size", "64"])
    assert code == 0
    return out


def test_collect_writes_libero_layout(dataset):
    files = sorted(p.name for p in dataset.glob("*.hdf5"))
    assert files == ["ball_away_demo.hdf5", "block_left_demo.hdf5"]
    episodes = read_dataset(dataset)
    assert len(episodes) == 4 and all(e.success for e in episodes)
    for ep in episodes:
        T = len(ep)
        assert 10 < T < 80
        assert ep.obs["agentview_rgb"].shape == (T, 64, 64, 3) and ep.obs["eye_in_hand_rgb"].shape == (T, 64, 64, 3)
        assert ep.obs["joint_states"].shape == (T, 6) and ep.obs["gripper_states"].shape == (T, 2)
        assert np.abs(ep.actions).max() <= 1.0 and ep.rewards.sum() == pytest.approx(1.0) and ep.dones[-1]
        assert ep.instruction in ("move the block left", "move the ball away")
        assert ep.meta["perturb"] == "static_distractors,level=2" and ep.source == "expert"


def test_dataset_loads_through_training_pipeline(dataset):
    from pivla.data.samples import ChunkDataset, fit_norm_stats, prepare_episode
    from pivla.data.text import WordTokenizer
    from pivla.model.config import ModelConfig

    episodes = read_dataset(dataset)
    cfg = ModelConfig(image_size=32)
    stats = fit_norm_stats(episodes, cfg)
    text = WordTokenizer.build([e.instruction for e in episodes])
    ds = ChunkDataset([prepare_episode(e, cfg, stats, text) for e in episodes], cfg, sp_steps=1)
    sample = ds.sample(0, np.random.default_rng(0))
    assert sample["images"].shape == (2, 32, 32, 3) and sample["actions"].shape == (cfg.chunk, 7)
    assert np.isfinite(sample["actions"]).all()


def test_export_video(dataset, tmp_path):
    assert main(["export-video", str(dataset), "--out", str(tmp_path), "--max-episodes", "1"]) == 0
    videos = sorted(tmp_path.glob("*.mp4"))
    assert len(videos) == 2
    n_frames = len(read_dataset(dataset)[0])
    with av.open(str(videos[0])) as container:
        frames = [f for f in container.decode(video=0)]
    assert len(frames) == n_frames and frames[0].width == 2 * 64 * 3


def test_bad_perturb_spec_is_a_clear_error(tmp_path):
    with pytest.raises(SystemExit, match="unknown perturbation"):
        main(["collect", "--suite", "drawer", "--episodes", "1", "--out", str(tmp_path), "--perturb", "fog"])


def test_episodes_do_not_depend_on_worker_count():
    from pivla.envs.rollout import collect_episodes
    from pivla.envs.tabletop import make_env
    from pivla.envs.tabletop.expert import make_expert

    factory = functools.partial(make_env, "drawer", "open_drawer", image_size=32, realism="servo")
    one = collect_episodes(factory, make_expert(0.1), 3, seed=9, workers=1)
    two = collect_episodes(factory, make_expert(0.1), 3, seed=9, workers=2)
    assert len(one) == len(two) == 3
    for a, b in zip(one, two):
        assert np.array_equal(a.actions, b.actions) and np.array_equal(a.obs["agentview_rgb"], b.obs["agentview_rgb"])


def test_a_smaller_collection_is_the_first_episodes_of_a_larger_one(tmp_path):
    """Why the benchmark's Fig. 17 sets are slices of the full set: a task's file holds its first successful
    seeds in order (the expert misses its first grasp half the time, so failures are replaced too)."""
    from pivla.data.hdf5 import read_episodes
    from pivla.envs.collect import CollectConfig, collect_demos

    base = CollectConfig(out="", suite="pick_place", tasks="ball_left", seed_family="train", image_size=32, miss=0.5,
                         noise=0.3)
    for n in (2, 4):
        assert collect_demos(dataclasses.replace(base, out=str(tmp_path / str(n)), episodes=n)) == 0
    small, large = (read_episodes(tmp_path / str(n) / "ball_left_demo.hdf5") for n in (2, 4))
    assert len(small) == 2 and len(large) == 4
    for a, b in zip(small, large[:2]):
        assert np.array_equal(a.actions, b.actions) and np.array_equal(a.obs["agentview_rgb"], b.obs["agentview_rgb"])


def test_an_interrupted_collection_keeps_every_finished_task(tmp_path, monkeypatch):
    """Each task's file is written once it is complete; the benchmark's rerun collects only the missing tasks."""
    from pivla.envs import collect
    from pivla.experiments.stages import Collect

    real, calls = collect.iter_jobs, []

    def interrupted(jobs, *args, **kwargs):
        calls.append(len(jobs))
        for i, ep in enumerate(real(jobs, *args, **kwargs)):
            if i == 1 and len(calls) == 1:
                raise KeyboardInterrupt
            yield ep

    monkeypatch.setattr(collect, "iter_jobs", interrupted)
    cfg = collect.CollectConfig(out=str(tmp_path), suite="drawer", episodes=1, image_size=32, keep_failures=True)
    with pytest.raises(KeyboardInterrupt):
        collect.collect_demos(cfg)
    assert sorted(p.name for p in tmp_path.glob("*.hdf5")) == ["open_drawer_demo.hdf5"]
    written = (tmp_path / "open_drawer_demo.hdf5").stat().st_mtime_ns
    Collect(cfg)()
    assert calls[1:] == [1]  # the second run collected the one missing task
    assert sorted(p.name for p in tmp_path.glob("*.hdf5")) == ["close_drawer_demo.hdf5", "open_drawer_demo.hdf5"]
    assert (tmp_path / "open_drawer_demo.hdf5").stat().st_mtime_ns == written


def _children(pid: int) -> set[int]:
    try:
        return {int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()}
    except FileNotFoundError:
        return set()


def test_kill_ends_a_collection_with_its_workers(tmp_path):
    """``kill`` on a running ``pivla collect --workers 2`` ends its worker processes too: left running, they
    would go on playing episodes for nobody (on LIBERO, a whole task each) beside the rerun that resumes it."""
    # 9 x 2000 episodes: hours of work, so the run is still going when it is killed (450 took 21 s here)
    proc = subprocess.Popen([sys.executable, "-m", "pivla", "collect", "--suite", "pick_place", "--episodes", "2000",
                             "--workers", "2", "--out", str(tmp_path / "data")],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 120
        while len(workers := _children(proc.pid)) < 3 and time.monotonic() < deadline:  # 2 workers + tracker
            time.sleep(0.5)
        assert len(workers) >= 3, proc.stderr.read().decode()[-2000:] if proc.poll() is not None else workers
        time.sleep(3)  # the workers are playing episodes
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=60) == 128 + signal.SIGTERM
    finally:
        if proc.poll() is None:
            proc.kill()
    deadline = time.monotonic() + 20
    while any(Path(f"/proc/{w}").exists() for w in workers) and time.monotonic() < deadline:
        time.sleep(0.2)
    alive = [w for w in workers if Path(f"/proc/{w}").exists()
             and Path(f"/proc/{w}/stat").read_text().split()[2] != "Z"]
    assert not alive
