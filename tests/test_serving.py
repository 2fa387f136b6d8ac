"""pivla.serving against a real server process on a free loopback port: openpi's protocol, every kind of bad
input (the server answers it and keeps serving), API keys, /healthz, concurrent clients, RemotePolicy as a
drop-in for a local policy (same actions step for step in the twin, same target latents), reconnection,
openpi's published client, and a client import without PyTorch."""

import contextlib
import copy
import dataclasses
import hashlib
import json
import os
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import msgpack
import numpy as np
import pytest
import torch
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import connect

import pivla
from pivla import config as cfgmod
from pivla.control.contract import BatchPolicy
from pivla.control.executors import make_executor
from pivla.control.runner import run_episode
from pivla.data.normalize import ActionStats, NormStats, StandardStats
from pivla.data.text import WordTokenizer
from pivla.model.cms import CMSModel
from pivla.model.config import BackboneConfig, ModelConfig, TargetEncoderConfig
from pivla.policy import load_policy
from pivla.serving import RemotePolicy, ServerError, ServerRefused
from pivla.serving.msgpack_numpy import DecodeError, packb, unpackb
from pivla.serving.protocol import CONTROL_OUTPUTS
from pivla.serving.server import ServeConfig, serve, spec_of
from pivla.training import checkpoint as ck
from pivla.training.config import TrainConfig

ROOT = Path(__file__).resolve().parents[1]
OPENPI_PYTHON = ROOT / ".venv-openpi" / "bin" / "python"
KEY = "test-key-5f1c"
MAX_MESSAGE = 2**20
MAX_BATCH = 4
TEXT = "pick up the red block"


def write_run(run: Path, target_proprio: float = 0.0, action_prefix: int = 0) -> Path:
    """An untrained tiny policy as ``pivla train`` lays out a run (32 px, target encoder downsampled 2x)."""
    model_cfg = ModelConfig(image_size=32,
                            backbone=BackboneConfig(d_model=64, n_layers=2, vision_channels=(16, 32, 32, 32)),
                            target_encoder=TargetEncoderConfig(downsample=2, proprio=target_proprio),
                            action_prefix=action_prefix)
    torch.manual_seed(0)
    text = WordTokenizer.build([TEXT, "put the block in the drawer"], model_cfg.max_text_len)
    model = CMSModel(model_cfg, len(text.vocab))
    stats = NormStats(ActionStats([-0.5] * 6 + [-1.0], [0.5] * 6 + [1.0]), StandardStats([0.0] * 8, [1.0] * 8),
                      proprio_layout=[("ee_pos", 3), ("ee_ori", 3), ("gripper_states", 2)])
    run.mkdir(parents=True)
    ck.save_tensors(run / ck.MODEL_FILE, model.state_dict_for_checkpoint())
    ck.atomic_write_json(run / ck.CONFIG_FILE, cfgmod.to_dict(TrainConfig(out=str(run), model=model_cfg)))
    ck.atomic_write_json(run / ck.STATS_FILE, stats.to_dict())
    ck.atomic_write_json(run / ck.TOKENIZER_FILE, text.to_dict())
    ck.atomic_write_json(run / ck.CALIBRATION_FILE,
                         {"tau_low": 0.3, "tau_high": 0.6, "v_thresh": 0.0, "source": "test"})
    return run


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def observation(seed: int, size: int = 32, prompt_key: str = "instruction") -> dict:
    rng = np.random.default_rng(seed)
    obs = {c: rng.integers(0, 256, (size, size, 3), dtype=np.uint8) for c in ("agentview_rgb", "eye_in_hand_rgb")}
    obs.update(ee_pos=rng.normal(size=3).astype(np.float32), ee_ori=rng.normal(size=3).astype(np.float32),
               gripper_states=np.zeros(2, np.float32), joint_states=np.zeros(6, np.float32))
    obs[prompt_key] = TEXT
    return obs


def local_obs(obs: dict) -> dict:
    return {("instruction" if k == "prompt" else k): v for k, v in obs.items()}


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    return write_run(tmp_path_factory.mktemp("serving") / "run")


@pytest.fixture(scope="module")
def local(run_dir):
    """The same run in this process, one torch thread like the server, so both compute the same bits."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield load_policy(run_dir, device="cpu")  # exports and caches the target graph the server then reuses
    torch.set_num_threads(threads)


def load_one_thread(run: Path, **options):
    """``load_policy`` with one torch thread, as the server loads it, so that both export the same target graph."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return load_policy(run, device="cpu", **options)
    finally:
        torch.set_num_threads(threads)


@contextlib.contextmanager
def running_server(run_dir: Path, directory: Path, **options: float) -> Iterator[tuple[int, subprocess.Popen]]:
    """(port, process) of a server with the API key KEY, serving ``run_dir`` with ``options`` of ServeConfig and
    logging to ``directory/server.log``; on exit it must stop cleanly on SIGTERM, with no error in its log (every
    bad request and vanished client handled, none escaped as an error)."""
    (directory / "key").write_text(KEY + "\n")
    log = directory / "server.log"
    port = free_port()
    extra = "".join(f", {k}={v!r}" for k, v in options.items())
    code = ("import logging, sys; logging.basicConfig(level=logging.INFO); "
            "from pivla.serving.server import ServeConfig, serve; "
            f"serve(ServeConfig(policy=sys.argv[1], port={port}, api_key_file=sys.argv[2], threads=1, "
            f"max_message_bytes={MAX_MESSAGE}, max_batch={MAX_BATCH}{extra}))")
    with log.open("wb") as out:
        proc = subprocess.Popen([sys.executable, "-c", code, str(run_dir), str(directory / "key")], stdout=out,
                                stderr=subprocess.STDOUT, env={**os.environ, "OMP_NUM_THREADS": "1"})
    try:
        deadline = time.monotonic() + 120
        while True:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=5):
                    break
            except OSError:
                assert proc.poll() is None, f"server exited:\n{log.read_text()[-3000:]}"
                assert time.monotonic() < deadline, f"server not up:\n{log.read_text()[-3000:]}"
                time.sleep(0.2)
        yield port, proc
    finally:
        proc.terminate()
        returncode = proc.wait(30)
    text = log.read_text()
    assert returncode == 0, text[-3000:]
    assert "ERROR" not in text and "Traceback" not in text, text[-3000:]


@pytest.fixture(scope="module")
def server(run_dir, local, tmp_path_factory):
    """(port, process) of a server with an API key, serving the run (``running_server``)."""
    with running_server(run_dir, tmp_path_factory.mktemp("server")) as served:
        yield served


@pytest.fixture
def remote(server):
    with RemotePolicy(f"ws://127.0.0.1:{server[0]}", api_key=KEY) as policy:
        yield policy


def raw(server):
    """A bare WebSocket connection with the key, after the metadata frame."""
    ws = connect(f"ws://127.0.0.1:{server[0]}", additional_headers={"Authorization": f"Api-Key {KEY}"},
                 compression=None, max_size=None, legacy=True)
    unpackb(ws.recv(timeout=30))
    return ws


def assert_serves(server, ws=None):
    """The server process is alive and answers a valid request (on ``ws`` when given: the same connection)."""
    assert server[1].poll() is None
    own = ws is None
    ws = raw(server) if own else ws
    ws.send(packb(observation(0)))
    reply = ws.recv(timeout=30)
    assert isinstance(reply, bytes), reply
    assert unpackb(reply)["actions"].shape == (8, 7)
    if own:
        ws.close()


# -- msgpack-numpy --------------------------------------------------------------------------------------
def test_msgpack_numpy_round_trip_and_refusals():
    data = {"a": np.arange(12, dtype=np.float32).reshape(3, 4)[:, ::2], "b": np.array([True, False]),
            "c": np.float32(1.5), "d": np.int64(-3), "e": ">f8 big endian", "f": np.zeros((0, 3), np.uint8),
            "g": np.arange(3, dtype=">f8")}
    back = unpackb(packb(data))
    for k in ("a", "b", "f", "g"):
        assert back[k].dtype == data[k].dtype and np.array_equal(back[k], data[k])
    assert back["c"] == np.float32(1.5) and isinstance(back["c"], np.float32) and back["d"] == -3
    with pytest.raises(TypeError, match="only bool, integer and float"):
        packb({"x": np.array([object()])})
    with pytest.raises(TypeError, match="only bool, integer and float"):
        packb({"x": np.array(["text"])})

    def header(changes=None):
        return msgpack.packb({b"__ndarray__": True, b"data": b"\0" * 8, b"dtype": "<f4", b"shape": [2],
                              **(changes or {})})

    assert unpackb(header()).tolist() == [0.0, 0.0]
    for changes, message in [({b"dtype": "|O"}, "refused"), ({b"dtype": "i4,O"}, "refused"),
                        ({b"dtype": "|V8"}, "refused"), ({b"dtype": "<c8"}, "refused"),
                        ({b"dtype": "nonsense"}, "unknown dtype"),
                        ({b"shape": [3]}, "needs 12 bytes"), ({b"shape": [2**40, 2**40]}, "bytes of data"),
                        ({b"shape": [-2]}, "non-negative"), ({b"data": "text"}, "must be bytes")]:
        with pytest.raises(DecodeError, match=message):
            unpackb(header(changes))
    with pytest.raises(DecodeError, match="too many maps and lists"):
        unpackb(msgpack.packb([[]] * 1000), max_containers=100)
    with pytest.raises(DecodeError, match="not a valid msgpack"):
        unpackb(b"\xc1\x00")
    with pytest.raises(DecodeError, match="extension"):
        unpackb(msgpack.packb(msgpack.ExtType(5, b"x")))


# -- protocol --------------------------------------------------------------------------------------------
def test_metadata_and_round_trip_match_the_local_policy(server, local):
    ws = connect(f"ws://127.0.0.1:{server[0]}", additional_headers={"Authorization": f"Api-Key {KEY}"},
                 compression=None, legacy=True)
    meta = unpackb(ws.recv(timeout=30))
    assert meta["protocol"] == "pivla-serving/1" and meta["pivla_version"] == pivla.__version__
    assert meta["spec"] == spec_of(local).to_dict() and meta["spec"]["proprio"][0] == ["ee_pos", 3]
    assert meta["calibration"] == dataclasses.asdict(local.calibration)
    assert meta["action_stats"] == dataclasses.asdict(local.stats.action)
    assert meta["limits"] == {"max_message_bytes": MAX_MESSAGE, "max_image_side": 1024, "max_batch": MAX_BATCH,
                              "idle_timeout_s": 600.0}
    target = meta["target_encoder"]
    assert target["runtime"] == "onnx" and target["downsample"] == 2 and target["input_shape"] == [1, 1, 3, 16, 16]
    obs = observation(1, prompt_key="prompt")  # openpi's name for the instruction
    ws.send(packb(obs))
    reply = unpackb(ws.recv(timeout=30))
    expected = local.infer(local_obs(obs))
    assert set(reply) == set(expected) | {"server_timing"} and reply["server_timing"]["infer_ms"] > 0
    for k, v in expected.items():
        assert reply[k].shape == np.shape(v) and np.array_equal(reply[k], v), k
    ws.send(packb({"method": "target_encoder"}))
    graph = unpackb(ws.recv(timeout=30))
    assert hashlib.sha256(graph["onnx"]).hexdigest() == target["sha256"] == graph["sha256"]
    ws.close()


def _changed(changes: dict) -> dict:
    """Observation 2 with keys replaced, or removed where the value is None."""
    obs = observation(2)
    for k, v in changes.items():
        if v is None:
            del obs[k]
        else:
            obs[k] = v
    return obs


def _with(**changes):
    return lambda: packb(_changed(changes))


def _lying_header(changes=None):
    header = {b"__ndarray__": True, b"data": b"\0" * 10, b"dtype": "|u1", b"shape": [32, 32, 3], **(changes or {})}
    return lambda: packb({**observation(2), "agentview_rgb": header})


BAD_REQUESTS = {
    "garbage bytes": (lambda: b"\xc1\xff\x00garbage", "not a valid msgpack"),
    "text frame": (lambda: "hello", "text frame"),
    "not a map": (lambda: packb([1, 2, 3]), "a request is a map"),
    "missing camera": (_with(eye_in_hand_rgb=None), "missing camera 'eye_in_hand_rgb'"),
    "float image": (_with(agentview_rgb=np.zeros((32, 32, 3), np.float32)), "uint8 image"),
    "four channels": (_with(agentview_rgb=np.zeros((32, 32, 4), np.uint8)), "HxWx3"),
    "image too large": (_with(agentview_rgb=np.zeros((1025, 4, 3), np.uint8)), "sides of 1 to 1024"),
    "image not an array": (_with(agentview_rgb=[1, 2, 3]), "must be an array"),
    "shape lies about data": (_lying_header(), "needs 3072 bytes"),
    "object dtype": (_lying_header({b"dtype": "|O"}), "refused"),
    "NaN proprio": (_with(ee_pos=np.array([0.0, np.nan, 0.0], np.float32)), "NaN or inf"),
    "inf proprio": (_with(ee_ori=np.array([0.0, 0.0, np.inf])), "NaN or inf"),
    "proprio beyond float32": (_with(ee_pos=np.array([1e300, 0.0, 0.0])), "beyond float32's range"),
    "proprio far out of range": (_with(ee_pos=np.array([1e30, 0.0, 0.0], np.float32)), "non-finite actions"),
    "proprio length": (_with(gripper_states=np.zeros(3, np.float32)), "'gripper_states' must be 2 numbers"),
    "proprio text": (_with(ee_pos="up"), "'ee_pos' must be 3 numbers"),
    "missing proprio": (_with(ee_ori=None), "missing proprio key 'ee_ori'"),
    "missing instruction": (_with(instruction=None), "missing 'instruction'"),
    "instruction not text": (_with(instruction=5), "must be a str"),
    "prompt disagrees": (_with(prompt="open the drawer"), "they differ"),
    "unknown method": (lambda: packb({"method": "train"}), "unknown method 'train'"),
    "unknown output": (lambda: packb({"method": "infer", "observation": observation(0), "outputs": ["torques"]}),
                       "unknown outputs ['torques']"),
    "batch too large": (lambda: packb({"method": "infer_batch", "observations": [observation(0)] * (MAX_BATCH + 1)}),
                        "list of 1 to 4"),
    "empty batch": (lambda: packb({"method": "encode_batch", "observations": []}), "list of 1 to 4"),
    "bad batch item": (lambda: packb({"method": "infer_batch", "observations": [observation(0), 7]}),
                       "an observation is a map"),
    "encode without observation": (lambda: packb({"method": "encode"}), "an observation is a map"),
    "too many containers": (lambda: msgpack.packb({"x": [[]] * 200_000}), "too many maps and lists"),
}


@pytest.mark.parametrize("name", list(BAD_REQUESTS))
def test_bad_request_gets_an_error_frame_and_the_connection_stays_usable(server, name):
    make, expected = BAD_REQUESTS[name]
    ws = raw(server)
    ws.send(make())
    reply = ws.recv(timeout=30)
    assert isinstance(reply, str) and expected in reply, reply
    assert_serves(server, ws)
    ws.close()


LOCAL_REFUSALS = {
    "missing camera": ({"eye_in_hand_rgb": None}, r"lacks camera\(s\) \['eye_in_hand_rgb'\]"),
    "float image": ({"agentview_rgb": np.zeros((32, 32, 3), np.float32)}, "'agentview_rgb' must be an HxWx3 uint8"),
    "NaN proprio": ({"ee_pos": np.array([0.0, np.nan, 0.0], np.float32)}, "'ee_pos' contains NaN or inf"),
    "proprio length": ({"gripper_states": np.zeros(3, np.float32)},
                       "'gripper_states' has 3 numbers, the policy was trained on 2"),
    "proprio text": ({"ee_pos": "up"}, "must hold numbers"),
    "missing proprio": ({"ee_ori": None}, "missing proprio key 'ee_ori'"),
    "missing instruction": ({"instruction": None}, "missing 'instruction'"),
    "instruction not text": ({"instruction": 5}, "'instruction' must be a str, got int"),
}


@pytest.mark.parametrize("name", list(LOCAL_REFUSALS))
def test_a_local_policy_names_what_is_wrong_with_an_observation(local, name):
    """In process, without the server's checks, a malformed observation is refused by the input pipeline."""
    changes, expected = LOCAL_REFUSALS[name]
    with pytest.raises(ValueError, match=expected):
        local.infer(_changed(changes))


def test_oversized_message_closes_only_that_connection(server):
    ws = raw(server)
    ws.send(b"\0" * (MAX_MESSAGE + 1))
    with pytest.raises(ConnectionClosed) as e:
        ws.recv(timeout=30)
    assert e.value.rcvd.code == 1009
    assert_serves(server)


def test_a_client_vanishing_mid_request_does_not_hurt_the_server(server, tmp_path):
    """A process sends a batch request and dies before the reply (its socket closed by the OS)."""
    script = tmp_path / "vanish.py"
    script.write_text(
        "import os, sys, numpy as np\n"
        "from websockets.sync.client import connect\n"
        "from pivla.serving.msgpack_numpy import packb\n"
        f"ws = connect('ws://127.0.0.1:{server[0]}', additional_headers={{'Authorization': 'Api-Key {KEY}'}})\n"
        "ws.recv()\n"
        "img = np.zeros((32, 32, 3), np.uint8)\n"
        "obs = dict(agentview_rgb=img, eye_in_hand_rgb=img, ee_pos=np.zeros(3), ee_ori=np.zeros(3),\n"
        "           gripper_states=np.zeros(2), instruction='x')\n"
        f"ws.send(packb({{'method': 'infer_batch', 'observations': [obs] * {MAX_BATCH}}}))\n"
        "os._exit(0)\n")
    subprocess.run([sys.executable, str(script)], check=True, timeout=60)
    assert_serves(server)


def test_an_idle_connection_is_closed_and_remote_policy_reconnects(run_dir, local, tmp_path):
    """Silence for idle_timeout_s closes a connection (1001); steady requests keep one open past it."""
    with running_server(run_dir, tmp_path, idle_timeout_s=1.5) as served:
        silent, busy = raw(served), raw(served)
        obs = observation(5)
        expected = local.infer(local_obs(obs))["actions"]
        with RemotePolicy(f"127.0.0.1:{served[0]}", api_key=KEY) as policy:
            assert policy.metadata["limits"]["idle_timeout_s"] == 1.5
            assert np.array_equal(policy.infer(obs)["actions"], expected)
            start = time.monotonic()
            while time.monotonic() - start < 3.5:
                assert_serves(served, busy)
                time.sleep(0.3)
            with pytest.raises(ConnectionClosed) as e:
                silent.recv(timeout=30)
            assert e.value.rcvd.code == 1001 and "idle" in e.value.rcvd.reason
            assert np.array_equal(policy.infer(obs)["actions"], expected)
            assert policy.reconnects == 1
        busy.close()
    assert "idle for 1.5 s: closing" in (tmp_path / "server.log").read_text()


# -- access -------------------------------------------------------------------------------------------
def test_api_key_is_required_and_checked(server):
    url = f"ws://127.0.0.1:{server[0]}"
    for headers in (None, {"Authorization": "Api-Key wrong"}, {"Authorization": KEY}):
        with pytest.raises(InvalidStatus) as e:
            connect(url, additional_headers=headers, legacy=True)
        assert e.value.response.status_code == 401 and b"Api-Key" in e.value.response.body
    with pytest.raises(ServerRefused, match="401"):
        RemotePolicy(url)
    with RemotePolicy(url, api_key=KEY) as policy:
        assert policy.spec.chunk == 8


def test_healthz_answers_without_a_key(server):
    with urllib.request.urlopen(f"http://127.0.0.1:{server[0]}/healthz", timeout=10) as r:
        assert r.status == 200 and r.read().strip() == b"OK"
    with pytest.raises(urllib.error.HTTPError) as e:
        urllib.request.urlopen(f"http://127.0.0.1:{server[0]}/", timeout=10)
    assert e.value.code == 401


def test_non_loopback_without_a_key_is_refused_before_loading(tmp_path):
    for host in ("0.0.0.0", "::", "192.168.1.10", "robot-server"):
        with pytest.raises(ValueError, match="without an API key"):
            serve(ServeConfig(policy=str(tmp_path / "no-such-run"), host=host))
    with pytest.raises(ValueError, match="idle_timeout_s: -1"):
        serve(ServeConfig(policy=str(tmp_path / "no-such-run"), idle_timeout_s=-1))
    (tmp_path / "empty").write_text("\n")
    with pytest.raises(ValueError, match="one key"):
        serve(ServeConfig(policy=str(tmp_path), host="0.0.0.0", api_key_file=str(tmp_path / "empty")))


# -- RemotePolicy --------------------------------------------------------------------------------------
def test_remote_policy_matches_the_local_one(remote, local):
    assert isinstance(remote, BatchPolicy) and remote.spec == spec_of(local) == local.spec
    assert remote.calibration == local.calibration
    assert remote.encoder_runtime == "onnx"
    observations = [observation(s) for s in range(3)] + [observation(9, size=64)]  # the last one is resized
    for obs in observations:
        assert np.array_equal(remote.encode(obs), local.encode(obs))  # same graph, same pre-processing
    assert np.allclose(remote.encode_batch(observations), local.encode_batch(observations), atol=1e-5)
    got, expected = remote.infer_batch(observations[:3]), local.infer_batch(observations[:3])
    assert set(got) == set(CONTROL_OUTPUTS)  # what the executors read, not the 256-bin distributions
    for k, v in got.items():
        assert np.allclose(v, expected[k], atol=1e-5), k
    assert np.array_equal(remote.infer(observations[3])["actions"], local.infer(observations[3])["actions"])
    normalized = np.linspace(-1.2, 1.2, 8 * 7, dtype=np.float32).reshape(8, 7)
    assert np.array_equal(remote.to_actions(normalized), local.to_actions(normalized))
    with pytest.raises(ServerError, match="missing camera 'eye_in_hand_rgb'"):
        remote.infer({k: v for k, v in observations[0].items() if k != "eye_in_hand_rgb"})
    assert remote.infer(observations[0])["actions"].shape == (8, 7)  # still usable


def test_all_outputs_when_asked(server, local):
    with RemotePolicy(f"127.0.0.1:{server[0]}", api_key=KEY, outputs=None) as policy:
        obs = observation(7, size=100)  # resized on the client, as the server would
        got, expected = policy.infer(obs), local.infer(obs)
        assert set(got) == set(expected) and policy.last_server_ms > 0
        for k, v in expected.items():
            assert np.array_equal(got[k], v), k


def test_encoding_on_the_server_when_asked(server, local):
    with RemotePolicy(f"127.0.0.1:{server[0]}", api_key=KEY, local_encoder=False) as policy:
        assert policy.encoder_runtime == "server"
        obs = observation(4)
        assert np.array_equal(policy.encode(obs), local.encode(obs))
        assert np.allclose(policy.encode_batch([obs, observation(5)]), local.encode_batch([obs, observation(5)]),
                           atol=1e-6)


def test_a_latent_that_reads_the_proprio(tmp_path):
    """A target latent with the proprio: locally the pictures' part runs on ONNX Runtime and the proprio is
    appended, as in PyTorch; a server hands out no graph, and a client sends the proprio keys to encode."""
    run = write_run(tmp_path / "run", target_proprio=1.0)
    local, eager = load_one_thread(run), load_one_thread(run, encoder_runtime="torch")
    assert local.encoder_runtime == "onnx" and local.spec.target_proprio
    obs = local_obs(observation(3))
    np.testing.assert_allclose(local.encode(obs), eager.encode(obs), atol=1e-5)
    pushed = {**obs, "ee_pos": obs["ee_pos"] + np.array([0.06, 0.0, 0.0], np.float32)}
    moved = local.encode(pushed) - local.encode(obs)  # the run's proprio statistics: mean 0, std 1
    np.testing.assert_allclose(moved,
                               np.eye(1, local.spec.latent_dim, local.spec.latent_dim - 8)[0] * 0.06 / np.sqrt(8),
                               atol=1e-6)
    with running_server(run, tmp_path) as (port, _), RemotePolicy(f"127.0.0.1:{port}", api_key=KEY) as remote:
        assert remote.encoder_runtime == "server" and remote.spec.target_proprio
        assert "ee_pos" in remote.wire_observation(obs, encode=True)
        np.testing.assert_allclose(remote.encode(observation(3)), local.encode(obs), atol=1e-5)
        np.testing.assert_allclose(remote.encode_batch([observation(3), observation(4)]),
                                   local.encode_batch([obs, local_obs(observation(4))]), atol=1e-5)


def test_an_ensemble_of_runs_is_served_with_its_first_members_encoder(tmp_path):
    """An ensemble (``pivla ensemble-runs``) encodes with its first member's target encoder: the server hands that
    graph out, and what it answers equals the local ensemble."""
    runs = [write_run(tmp_path / f"run{i}") for i in (0, 1)]
    ensemble = ck.write_run_ensemble(runs, tmp_path / "ens")
    local = load_one_thread(ensemble)
    with running_server(ensemble, tmp_path) as (port, _), \
            RemotePolicy(f"127.0.0.1:{port}", api_key=KEY, outputs=None) as remote:
        assert remote.encoder_runtime == "onnx" and remote.spec == local.spec
        obs = observation(6)
        got, expected = remote.infer(obs), local.infer(local_obs(obs))
        assert set(got) == set(expected)
        for k, v in expected.items():
            np.testing.assert_allclose(got[k], v, atol=1e-6, err_msg=k)
        np.testing.assert_allclose(remote.encode(obs), local.encode(local_obs(obs)), atol=1e-6)


def test_a_served_policy_reads_the_actions_in_flight_and_names_bad_ones(tmp_path):
    """The spec tells the client how many actions in flight the policy reads; the remote answer to an observation
    with them is the local one, and a prefix the policy cannot read gets an error frame naming it."""
    run = write_run(tmp_path / "run", action_prefix=2)
    local = load_one_thread(run)
    in_flight = local.infer(local_obs(observation(5)))["actions"][:2]
    told = {**observation(5), "action_prefix": in_flight}
    with running_server(run, tmp_path) as (port, _), RemotePolicy(f"127.0.0.1:{port}", api_key=KEY) as remote:
        assert remote.spec.action_prefix == 2
        np.testing.assert_allclose(remote.infer(told)["actions"], local.infer(local_obs(told))["actions"], atol=1e-5)
        with pytest.raises(ServerError, match="reads at most 2"):
            remote.infer({**told, "action_prefix": np.zeros((3, 7), np.float32)})
        assert remote.infer(observation(5))["actions"].shape == (8, 7)


def test_two_clients_at_once(server, local):
    observations = {c: [observation(10 * c + i) for i in range(6)] for c in (1, 2)}
    results: dict[int, list] = {}

    def client(c):
        with RemotePolicy(f"127.0.0.1:{server[0]}", api_key=KEY) as policy:
            results[c] = [policy.infer(o)["actions"] for o in observations[c]]

    threads = [threading.Thread(target=client, args=(c,)) for c in (1, 2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    for c in (1, 2):
        assert len(results[c]) == 6
        for obs, actions in zip(observations[c], results[c]):
            assert np.array_equal(actions, local.infer(obs)["actions"])


@pytest.mark.parametrize("executor", ["fixed", "aurd"])
def test_remote_twin_episode_equals_the_local_one_step_for_step(remote, local, executor):
    from pivla.envs import make_env

    env = make_env("tabletop", "pick_place", 0, image_size=32)
    options = {"horizon": 3}
    if executor == "aurd":  # thresholds inside this policy's U, so that it cuts plans on the client's latents
        probe = run_episode(env, local, make_executor("aurd", tau_low=1e9, tau_high=1e9, v_thresh=-1e9), seed=3,
                            max_steps=20)
        u = [row["u"] for row in probe.trace]
        options = {"tau_low": float(np.percentile(u, 30)), "tau_high": float(np.percentile(u, 80)), "v_thresh": 0.0}
    a = run_episode(env, local, make_executor(executor, **options), seed=5, max_steps=20, keep_episode=True)
    b = run_episode(env, remote, make_executor(executor, **options), seed=5, max_steps=20, keep_episode=True)
    env.close()
    assert np.array_equal(a.episode.actions, b.episode.actions)
    assert a.plans == b.plans and a.trace == b.trace
    if executor == "aurd":
        assert any(event != "complete" for _, event in a.plans), a.plans  # decisions on U_pred were exercised


def test_remote_episode_with_served_delays_equals_the_simulated_latency_step_for_step(run_dir, local, tmp_path):
    """The server holds back each answer by a seeded delay; the client measures arrival in control steps on the
    wall clock (knowing nothing of the delay) and must play what the simulated latency with the same draws plays."""
    from pivla.control.asynchronous import AsyncConfig, SyncConfig
    from pivla.control.latency import latency_rng, parse_latency
    from pivla.envs import make_env

    seed, delay = 5, "140:10"
    rng = latency_rng(seed)
    draws = [parse_latency(delay).draw_ms(rng) for _ in range(20)]
    # every delay lies well inside (100, 200) ms, 2 steps at 10 Hz, so the loop's own few ms cannot move an arrival
    assert all(110 < ms < 165 for ms in draws), draws
    env = make_env("tabletop", "pick_place", 0, image_size=32)
    runs = {}
    with running_server(run_dir, tmp_path, delay_ms=delay, delay_seed=seed) as (port, _):
        for execution in (AsyncConfig(threshold=2), SyncConfig()):
            with RemotePolicy(f"ws://127.0.0.1:{port}", api_key=KEY) as remote:  # a connection: delays from the start
                real = run_episode(env, remote, make_executor("fixed", horizon=3), seed=seed, max_steps=16,
                                   execution=execution, latency="real")
            simulated = run_episode(env, local, make_executor("fixed", horizon=3), seed=seed, max_steps=16,
                                    execution=execution, latency=delay)
            runs[execution.kind] = real, simulated
    env.close()
    for kind, (real, simulated) in runs.items():
        assert real.delays == simulated.delays and set(real.delays) == {2}, (kind, real.delays)
        assert np.array_equal(real.actions, simulated.actions), kind
        assert real.trace == simulated.trace and real.plans == simulated.plans, kind
    # sent with 2 actions left, each chunk arrives as the last one ends: only the first wait is idle
    assert runs["async"][0].summary()["idle_steps"] == 2 and runs["sync"][0].summary()["idle_steps"] == 7


class Relay:
    """A TCP relay to the server that the test can cut (a dropped network) or shut (the server unreachable)."""

    def __init__(self, port: int):
        self.target, self.sockets = port, []
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self):
        while True:
            try:
                a, _ = self.listener.accept()
            except OSError:
                return
            b = socket.create_connection(("127.0.0.1", self.target))
            self.sockets += [a, b]
            for src, dst in ((a, b), (b, a)):
                threading.Thread(target=self._pipe, args=(src, dst), daemon=True).start()

    @staticmethod
    def _pipe(src, dst):
        try:
            while data := src.recv(65536):
                dst.sendall(data)
        except OSError:
            pass
        for s in (src, dst):
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def cut(self):
        for s in self.sockets:
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        self.sockets = []

    def shut(self):
        self.listener.shutdown(socket.SHUT_RDWR)  # wakes the blocked accept (a bare close would not stop it)
        self.listener.close()
        self.cut()


def test_reconnects_after_a_dropped_connection_and_says_when_it_cannot(server, local):
    relay = Relay(server[0])
    obs = observation(6)
    expected = local.infer(obs)["actions"]
    with RemotePolicy(f"127.0.0.1:{relay.port}", api_key=KEY, retries=2) as policy:
        assert np.array_equal(policy.infer(obs)["actions"], expected)
        relay.cut()
        time.sleep(0.2)
        assert np.array_equal(policy.infer(obs)["actions"], expected)
        assert policy.reconnects == 1
        relay.shut()
        time.sleep(0.2)
        with pytest.raises(ConnectionError, match=f"127.0.0.1:{relay.port}.*2 reconnection attempt"):
            policy.infer(obs)
    with pytest.raises(ConnectionError, match="unreachable"):
        RemotePolicy(f"127.0.0.1:{relay.port}")


class CutAfter:
    """The env, with the network to the server shut after ``step`` control steps."""

    def __init__(self, env, relay: Relay, step: int):
        self.env, self.relay, self.cut_at, self.unwrapped = env, relay, step, env.unwrapped

    def reset(self, **kw):
        self.t = 0
        return self.env.reset(**kw)

    def step(self, action):
        self.t += 1
        if self.t == self.cut_at:
            self.relay.shut()
        return self.env.step(action)


def test_a_link_lost_during_async_execution_makes_the_arm_hold(server):
    from pivla.control.asynchronous import AsyncConfig
    from pivla.envs import make_env

    relay = Relay(server[0])
    env = make_env("tabletop", "pick_place", 0, image_size=32)
    with RemotePolicy(f"127.0.0.1:{relay.port}", api_key=KEY, retries=1) as policy:
        result = run_episode(CutAfter(env, relay, 6), policy, make_executor("fixed", horizon=3), seed=5, max_steps=18,
                             execution=AsyncConfig(threshold=1), latency="real")
    env.close()
    moving = [t for t, a in enumerate(result.actions) if np.any(a[:6] != 0)]
    # the chunk in execution when the link went runs out its horizon at the latest, then the arm holds
    assert moving and moving[-1] < 6 + 3 and len(moving) >= 4, moving
    assert result.summary()["failed_queries"] >= 1 and result.trace[-1].get("idle")


def test_spec_of_a_run_without_stored_proprio_lengths(local):
    old = copy.copy(local)
    old.spec = dataclasses.replace(local.spec, proprio=(("ee_pos", -1), ("ee_ori", -1), ("gripper_states", -1)))
    assert spec_of(old).proprio == (("ee_pos", 3), ("ee_ori", 3), ("gripper_states", 2))


# -- openpi's client and a client-only install --------------------------------------------------------
OPENPI_SCRIPT = """
import json, sys
import numpy as np
from openpi_client.websocket_client_policy import WebsocketClientPolicy

client = WebsocketClientPolicy(host="127.0.0.1", port=int(sys.argv[1]), api_key=sys.argv[2])
meta = client.get_server_metadata()
img = (np.arange(32 * 32 * 3, dtype=np.int64).reshape(32, 32, 3) * 7 % 256).astype(np.uint8)
obs = {"agentview_rgb": img, "eye_in_hand_rgb": img[::-1].copy(), "ee_pos": np.array([0.1, 0.2, 0.3], np.float32),
       "ee_ori": np.zeros(3, np.float32), "gripper_states": np.zeros(2, np.float32), "prompt": "pick up the red block"}
out = client.infer(obs)
try:
    client.infer({"prompt": "pick up the red block"})
    error = None
except RuntimeError as e:
    error = str(e)
again = client.infer(obs)
print(json.dumps({"spec": meta["spec"], "actions": out["actions"].tolist(), "dtype": str(out["actions"].dtype),
                  "keys": sorted(out), "error": error, "same": bool(np.array_equal(out["actions"], again["actions"]))}))
"""


@pytest.mark.skipif(not OPENPI_PYTHON.exists(),
                    reason=".venv-openpi is absent (scripts/setup-openpi-client.sh creates it)")
def test_openpi_published_client_works_unchanged(server, local):
    proc = subprocess.run([str(OPENPI_PYTHON), "-c", OPENPI_SCRIPT, str(server[0]), KEY], capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    img = (np.arange(32 * 32 * 3, dtype=np.int64).reshape(32, 32, 3) * 7 % 256).astype(np.uint8)
    obs = {"agentview_rgb": img, "eye_in_hand_rgb": img[::-1].copy(), "ee_pos": np.array([0.1, 0.2, 0.3], np.float32),
           "ee_ori": np.zeros(3, np.float32), "gripper_states": np.zeros(2, np.float32), "instruction": TEXT}
    assert got["spec"]["cameras"] == ["agentview_rgb", "eye_in_hand_rgb"] and got["dtype"] == "float32"
    assert np.array_equal(np.asarray(got["actions"], np.float32), local.infer(obs)["actions"])
    assert {"actions", "u_act", "latents", "values", "server_timing"} <= set(got["keys"])
    assert "missing camera 'agentview_rgb'" in got["error"] and got["same"]


def test_client_imports_neither_torch_nor_mujoco():
    code = ("import sys; import pivla.serving, pivla.serving.client, pivla.control.executors; "
            "bad = [m for m in ('torch', 'mujoco') if m in sys.modules]; assert not bad, bad")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
