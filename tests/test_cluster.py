"""The Ray backend on a two-node cluster on this machine: every episode equals the local backend's, with an
actor lost mid-run as without, each episode counted once."""

import functools
import logging

import pytest

from pivla.envs.backend import FAULT_ENV, BackendConfig, check_backend
from pivla.evaluation.runner import load_rows
from tests import test_control_eval
from tests.test_control_eval import _episodes, _eval, _same_episodes

tiny_policy = test_control_eval.tiny_policy  # the fixture: a tiny trained, calibrated policy

ray = pytest.importorskip("ray")


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """Two nodes of one CPU each; actors that find the fault file missing create it and exit (FAULT_ENV)."""
    from ray.cluster_utils import Cluster

    fault = tmp_path_factory.mktemp("fault") / "fired"
    fault.touch()  # armed only when a test deletes it
    mp = pytest.MonkeyPatch()
    mp.setenv(FAULT_ENV, str(fault))  # the nodes' processes, and so their actors, inherit it
    nodes = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
    nodes.add_node(num_cpus=1)
    nodes.wait_for_nodes()
    try:
        yield nodes.address, fault
    finally:
        nodes.shutdown()
        mp.undo()


def test_ray_episodes_equal_local_ones_even_when_an_actor_dies(tiny_policy, cluster, tmp_path, caplog):
    address, fault = cluster
    ray_backend = BackendConfig(backend="ray", ray_address=address)
    _eval(tiny_policy, tmp_path / "local")
    _eval(tiny_policy, tmp_path / "ray", workers=2, dispatch=ray_backend)
    local = _episodes(tmp_path / "local")
    _same_episodes(local, _episodes(tmp_path / "ray"))
    # same rows in the same order: job order, as one local process logs them
    keys = [(r["task_index"], r["episode"]) for r in load_rows(tmp_path / "local" / "episodes.jsonl")]
    assert [(r["task_index"], r["episode"]) for r in load_rows(tmp_path / "ray" / "episodes.jsonl")] == keys

    fault.unlink()  # the next actor to finish a job dies before returning it
    with caplog.at_level(logging.WARNING, logger="pivla.envs.backend"):
        res = _eval(tiny_policy, tmp_path / "fault", workers=2, dispatch=ray_backend)
    assert fault.exists() and "Ray worker was lost" in caplog.text
    rows = load_rows(tmp_path / "fault" / "episodes.jsonl")
    assert [(r["task_index"], r["episode"]) for r in rows] == keys and res["episodes"] == len(keys)
    _same_episodes(local, _episodes(tmp_path / "fault"))
    assert not ray.is_initialized()  # the driver left the cluster it joined


def test_ray_collection_equals_local(cluster, tmp_path):
    from pivla.envs.rollout import iter_jobs
    from pivla.envs.tabletop import make_env
    from pivla.envs.tabletop.expert import make_expert

    factory = functools.partial(make_env, "pick_place", 0, image_size=32)
    jobs = [(factory, seed) for seed in (3, 4, 5)]
    local = list(iter_jobs(jobs, make_expert(0.1)))
    remote = list(iter_jobs(jobs, make_expert(0.1), workers=2, backend=BackendConfig("ray", cluster[0])))
    assert [e.meta for e in remote] == [e.meta for e in local]
    for a, b in zip(local, remote, strict=True):
        assert (a.actions == b.actions).all() and (a.obs["agentview_rgb"] == b.obs["agentview_rgb"]).all()


def test_bad_backend_settings_are_one_line_errors(monkeypatch):
    with pytest.raises(ConnectionError, match="no Ray cluster answers there"):
        check_backend(BackendConfig("ray", "127.0.0.1:1"))
    with pytest.raises(ValueError, match="HOST:PORT"):
        check_backend(BackendConfig("ray", "headnode"))
    monkeypatch.setitem(__import__("sys").modules, "ray", None)  # as if not installed
    with pytest.raises(ValueError, match=r"pip install 'pivla\[ray\]'"):
        check_backend(BackendConfig("ray"))


def test_cli_says_in_one_line_that_no_cluster_answers(tiny_policy, tmp_path):
    from pivla.cli import main

    with pytest.raises(SystemExit) as e:
        main(["eval", "--policy", str(tiny_policy), "--out", str(tmp_path / "e"), "--backend", "ray",
              "--ray-address", "127.0.0.1:1"])
    assert "--ray-address 127.0.0.1:1: no Ray cluster answers there" in str(e.value)
    assert not (tmp_path / "e").exists()  # refused before anything is written
