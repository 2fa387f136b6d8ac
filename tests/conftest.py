import os

import pytest

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])


def _scheduling() -> tuple | None:
    return (os.sched_getscheduler(0), os.sched_getparam(0)) if hasattr(os, "sched_getscheduler") else None


SCHEDULING = _scheduling()


@pytest.fixture(autouse=True)
def _scheduling_unchanged():
    """The thread running the tests stays scheduled as the session started: a real-time policy left behind by a
    test or its fixtures (SVT-AV1 run as root sets SCHED_FIFO 99) is inherited by every process a later test
    starts, and one busy at that priority starves the others on its core, so that a later test fails for no
    reason of its own."""
    yield
    assert _scheduling() == SCHEDULING, f"scheduling left at {_scheduling()}, from {SCHEDULING} at the start"


@pytest.fixture(scope="session")
def synthetic_data(tmp_path_factory):
    """A tiny LIBERO-layout dataset (4 goals x 4 episodes x 20 steps, 32 px) shared by core tests."""
    from pivla.data.synthetic import make_synthetic_dataset

    return make_synthetic_dataset(tmp_path_factory.mktemp("syn") / "data", episodes_per_goal=4, T=20, size=32,
                                  failures=1)


def twin_pick_place_data(out, episodes: int):
    """Expert demonstrations of the twin's first two ``pick_place`` tasks at 32 px, a file per task in ``out``."""
    import functools

    from pivla.data.hdf5 import write_episodes
    from pivla.envs.rollout import collect_episodes
    from pivla.envs.tabletop import make_env
    from pivla.envs.tabletop.expert import make_expert

    for task in (0, 1):
        eps = collect_episodes(functools.partial(make_env, "pick_place", task, image_size=32), make_expert(0.1),
                               episodes, seed=task)
        write_episodes(out / f"task{task}.hdf5", eps)
    return out


def tiny_train_config(data, out, **overrides):
    from pivla.model.config import BackboneConfig, ModelConfig
    from pivla.training.config import TrainConfig

    model = ModelConfig(image_size=32,
                        backbone=BackboneConfig(d_model=64, n_layers=2, vision_channels=(16, 32, 32, 32)))
    kw = dict(data=str(data), out=str(out), steps=20, batch_size=8, warmup=5, log_every=5, eval_every=10,
              ckpt_every=10, value_refresh_every=10, progress=False, model=model, threads=2)
    kw.update(overrides)
    return TrainConfig(**kw)


def run_two_process(tmp_path, worker_source: str, cfg) -> dict:
    """Run ``worker_source`` under ``torchrun --standalone --nproc_per_node 2`` (gloo, one thread each) with
    the config as ``argv[1]``; the worker writes its findings as JSON to ``argv[2]``, returned here."""
    import json
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    from pivla import config as cfgmod

    torchrun = shutil.which("torchrun", path=str(Path(sys.executable).parent)) or shutil.which("torchrun")
    if torchrun is None:
        pytest.skip("torchrun not found")
    (tmp_path / "cfg.json").write_text(json.dumps(cfgmod.to_dict(cfg)))
    (tmp_path / "worker.py").write_text(worker_source)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([torchrun, "--standalone", "--nproc_per_node", "2", str(tmp_path / "worker.py"),
                           str(tmp_path / "cfg.json"), str(tmp_path / "result.json")],
                          capture_output=True, text=True, timeout=300, env=env, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads((tmp_path / "result.json").read_text())
