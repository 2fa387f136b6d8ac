"""LeRobot v3.0 datasets: reading the layout lerobot writes, HDF5 <-> LeRobot round trips, named errors for
bad input, and training straight from a LeRobot folder.

The fixture writer below builds datasets the way lerobot 0.4.4 lays them out, with its own pyarrow and PyAV
code (not pivla's writer), so reader and writer are each checked against the documented layout."""

import json
import shutil

import av
import cv2
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from pivla.data.action_space import EE_DELTA
from pivla.data.convert import ConvertConfig, convert, run_convert
from pivla.data.episode import DatasetError, Episode
from pivla.data.hdf5 import write_episodes
from pivla.data.lerobot.reader import read_lerobot
from pivla.data.lerobot.writer import LeRobotWriteConfig, write_lerobot
from pivla.data.read import detect_format, read_dataset
from pivla.data.synthetic import make_synthetic_dataset
from tests.conftest import tiny_train_config
from tests.lerobot_files import encode_video, fixed_list

FPS = 10
H, W = 32, 48
LEROBOT_CODEC = "libsvtav1" if "libsvtav1" in av.codecs_available else "libx264"
# measured with the command in docs/dataset.md ("LeRobot v3.0"): H.264 crf 18 on 32 px synthetic frames gives a
# mean absolute pixel error of 1.7 (99th percentile 24), most of it from yuv420p's half-resolution colour
MEAN_TOL, P99_TOL = 3.0, 40


def _frames(T: int, seed: int) -> np.ndarray:
    """Smooth frames with a square moving 2 px a step, so neighbouring frames differ clearly."""
    rng = np.random.default_rng(seed)
    base = np.zeros((H, W, 3), np.uint8)
    base[..., 0] = np.linspace(30, 200, W, dtype=np.uint8)[None, :]
    base[..., 1] = np.linspace(60, 160, H, dtype=np.uint8)[:, None]
    base[..., 2] = rng.integers(40, 200)
    out = np.repeat(base[None], T, axis=0)
    for t in range(T):
        x = 2 + 2 * t
        out[t, 10:18, x:x + 8] = (240, 240, 240)
    return out


def write_fixture(root, lengths=(5, 7, 4), state_names=None, with_rewards=False, png_wrist=False) -> dict:
    """A v3.0 dataset as lerobot writes it: episodes 0-1 share data file 0 and video file 0, episode 2 is in
    file 1 of both. Returns the source arrays per episode."""
    rng = np.random.default_rng(0)
    tasks = ["pick up the bowl", "open the drawer"]
    ep_tasks = [0, 1, 0]
    state_names = state_names or ["x", "y", "z", "ax", "ay", "az", "g0", "g1"]
    src = []
    for e, T in enumerate(lengths):
        src.append({"actions": rng.normal(size=(T, 7)).astype(np.float32),
                    "state": rng.normal(size=(T, 8)).astype(np.float32),
                    "image": _frames(T, e), "wrist": _frames(T, 10 + e)[:, ::-1].copy(),
                    "reward": rng.random(T).astype(np.float32), "task": tasks[ep_tasks[e]]})
    features = {
        "observation.images.image": {"dtype": "video", "shape": [H, W, 3], "names": ["height", "width", "channels"],
                                     "info": {"video.height": H, "video.width": W, "video.codec": "av1",
                                              "video.pix_fmt": "yuv420p", "video.is_depth_map": False,
                                              "video.fps": FPS, "video.channels": 3, "has_audio": False}},
        "observation.state": {"dtype": "float32", "shape": [8], "names": state_names},
        "action": {"dtype": "float32", "shape": [7], "names": None},
    }
    if png_wrist:
        features["observation.images.wrist"] = {"dtype": "image", "shape": [H, W, 3],
                                                "names": ["height", "width", "channels"]}
    if with_rewards:
        features["next.reward"] = {"dtype": "float32", "shape": [1], "names": None}
        features["next.done"] = {"dtype": "bool", "shape": [1], "names": None}
    for name, dtype in [("timestamp", "float32"), ("frame_index", "int64"), ("episode_index", "int64"),
                        ("index", "int64"), ("task_index", "int64")]:
        features[name] = {"dtype": dtype, "shape": [1], "names": None}
    files = [[0, 1], [2]]
    rows, start = [], 0
    for file_index, eps in enumerate(files):
        cols = {k: [] for k in features if features[k]["dtype"] != "video"}
        video_t = 0
        for e in eps:
            s, T = src[e], lengths[e]
            cols["observation.state"].append(fixed_list(s["state"]))
            cols["action"].append(fixed_list(s["actions"]))
            if png_wrist:
                cols["observation.images.wrist"].append(pa.array(
                    [{"bytes": cv2.imencode(".png", im[..., ::-1])[1].tobytes(), "path": None} for im in s["wrist"]],
                    pa.struct([("bytes", pa.binary()), ("path", pa.string())])))
            if with_rewards:
                cols["next.reward"].append(pa.array(s["reward"]))
                cols["next.done"].append(pa.array(np.arange(T) == T - 1))
            cols["timestamp"].append(pa.array((np.arange(T) / FPS).astype(np.float32)))
            cols["frame_index"].append(pa.array(np.arange(T, dtype=np.int64)))
            cols["episode_index"].append(pa.array(np.full(T, e, np.int64)))
            cols["index"].append(pa.array(np.arange(start, start + T, dtype=np.int64)))
            cols["task_index"].append(pa.array(np.full(T, ep_tasks[e], np.int64)))
            rows.append({"episode_index": e, "tasks": [s["task"]], "length": T,
                         "data/chunk_index": 0, "data/file_index": file_index,
                         "dataset_from_index": start, "dataset_to_index": start + T,
                         "videos/observation.images.image/chunk_index": 0,
                         "videos/observation.images.image/file_index": file_index,
                         "videos/observation.images.image/from_timestamp": video_t / FPS,
                         "videos/observation.images.image/to_timestamp": (video_t + T) / FPS,
                         "stats/action/mean": s["actions"].mean(0).tolist(),
                         "meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0})
            start, video_t = start + T, video_t + T
        table = pa.table({k: pa.concat_arrays(v) for k, v in cols.items()})
        path = root / f"data/chunk-000/file-{file_index:03d}.parquet"
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(table, path)
        encode_video(root / f"videos/observation.images.image/chunk-000/file-{file_index:03d}.mp4",
                     np.concatenate([src[e]["image"] for e in eps]), FPS, LEROBOT_CODEC)
    (root / "meta/episodes/chunk-000").mkdir(parents=True)
    pq.write_table(pa.Table.from_pylist(rows), root / "meta/episodes/chunk-000/file-000.parquet")
    pq.write_table(pa.table({"task_index": pa.array([0, 1], pa.int64()), "__index_level_0__": tasks}),
                   root / "meta/tasks.parquet")
    info = {"codebase_version": "v3.0", "robot_type": "panda", "total_episodes": len(lengths),
            "total_frames": sum(lengths), "total_tasks": 2, "chunks_size": 1000, "data_files_size_in_mb": 100,
            "video_files_size_in_mb": 200, "fps": FPS, "splits": {"train": f"0:{len(lengths)}"},
            "data_path": "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet",
            "video_path": "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4",
            "features": features}
    (root / "meta/info.json").write_text(json.dumps(info, indent=4))
    (root / "meta/stats.json").write_text("{}")
    return {"src": src, "tasks": tasks}


def _err(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.abs(a.astype(np.int16) - b.astype(np.int16))


@pytest.fixture(scope="module")
def fixture_dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("lr") / "ds"
    return root, write_fixture(root)


def test_reads_the_layout_lerobot_writes(fixture_dataset):
    root, made = fixture_dataset
    assert detect_format(root) == "lerobot"
    episodes = read_lerobot(root)
    assert [len(ep) for ep in episodes] == [5, 7, 4]
    for ep, s in zip(episodes, made["src"]):
        np.testing.assert_array_equal(ep.actions, s["actions"])
        np.testing.assert_array_equal(ep.obs["state"], s["state"])  # names are not pivla's split: one key
        assert ep.instruction == s["task"] and ep.success and ep.rewards[-1] == 1 and ep.dones[-1] == 1
        assert ep.obs["image"].shape == (len(ep), H, W, 3) and ep.obs["image"].dtype == np.uint8
        assert _err(ep.obs["image"], s["image"]).mean() < MEAN_TOL
        # frames line up with their own source frame, not a neighbour (the square moves 2 px a step)
        for t in range(1, len(ep)):
            assert _err(ep.obs["image"][t], s["image"][t]).mean() < _err(ep.obs["image"][t], s["image"][t - 1]).mean()
    assert read_dataset(root, obs_keys=("state",))[1].obs.keys() == {"state"}  # the read_dataset hook


def test_reads_pivla_state_split_rewards_and_png_images(tmp_path):
    names = [f"ee_pos.{i}" for i in range(3)] + [f"ee_ori.{i}" for i in range(3)] + ["gripper_states.0",
                                                                                        "gripper_states.1"]
    made = write_fixture(tmp_path / "ds", state_names=names, with_rewards=True, png_wrist=True)
    episodes = read_lerobot(tmp_path / "ds")
    assert len(episodes) == len(made["src"]) > 0
    for ep, s in zip(episodes, made["src"]):
        np.testing.assert_array_equal(ep.obs["ee_pos"], s["state"][:, :3])
        np.testing.assert_array_equal(ep.obs["gripper_states"], s["state"][:, 6:])
        np.testing.assert_array_equal(ep.obs["wrist"], s["wrist"])  # PNG is lossless
        np.testing.assert_array_equal(ep.rewards, s["reward"])
        assert ep.dones.tolist() == [0] * (len(ep) - 1) + [1]


def _compare(a: list[Episode], b: list[Episode]) -> np.ndarray:
    assert len(a) == len(b)
    errors = []
    for x, y in zip(a, b):
        assert (x.instruction, x.success, x.source, x.meta) == (y.instruction, y.success, y.source, y.meta)
        for name in ("actions", "rewards", "dones"):
            np.testing.assert_array_equal(getattr(x, name), getattr(y, name))
        assert x.obs.keys() == y.obs.keys()
        for key, arr in x.obs.items():
            if arr.dtype == np.uint8:
                assert y.obs[key].shape == arr.shape
                errors.append(_err(arr, y.obs[key]).ravel())
            else:
                assert y.obs[key].dtype == arr.dtype
                np.testing.assert_array_equal(y.obs[key], arr)
    return np.concatenate(errors)


@pytest.fixture(scope="module")
def converted(tmp_path_factory):
    root = tmp_path_factory.mktemp("rt")
    src = make_synthetic_dataset(root / "h5", episodes_per_goal=2, T=10, size=32, failures=1)
    eps = read_dataset(src)
    eps[0].meta = {"seed": 3, "task": "x"}
    eps[1].source = "policy"
    write_episodes(min(src.glob("*.hdf5")), eps[:3], env_meta={"control_hz": FPS})
    result = run_convert(ConvertConfig(str(src), str(root / "lr"), "lerobot",
                                       lerobot=LeRobotWriteConfig(episodes_per_file=4)))
    return src, root / "lr", result


def test_writer_output_follows_the_documented_layout(converted):
    src, lr, result = converted
    assert (result.source_format, result.episodes, result.frames, result.fps) == ("hdf5", 12, 120, FPS)
    info = json.loads((lr / "meta/info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["fps"] == FPS
    assert (info["total_episodes"], info["total_frames"], info["total_tasks"]) == (12, 120, 4)
    assert info["data_path"] == "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
    assert info["video_path"] == "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
    assert info["splits"] == {"train": "0:12"} and info["chunks_size"] == 1000
    feats = info["features"]
    assert list(feats)[-5:] == ["timestamp", "frame_index", "episode_index", "index", "task_index"]
    assert feats["observation.state"]["shape"] == [8] and feats["observation.state"]["names"][:2] == ["ee_pos.0",
                                                                                                        "ee_pos.1"]
    assert feats["action"] == {"dtype": "float32", "shape": [7], "names": ["x", "y", "z", "roll", "pitch", "yaw",
                                                                             "gripper"],
                               "pivla/action_space": EE_DELTA.to_dict()}
    video = feats["observation.images.agentview_rgb"]
    assert video["dtype"] == "video" and video["shape"] == [32, 32, 3] and video["names"] == ["height", "width",
                                                                                            "channels"]
    assert video["info"] == {"video.height": 32, "video.width": 32, "video.codec": "h264", "video.pix_fmt": "yuv420p",
                             "video.is_depth_map": False, "video.fps": FPS, "video.channels": 3, "has_audio": False}
    # 12 episodes, at most 4 per file: 3 data files and 3 mp4 files per camera
    assert len(list((lr / "data/chunk-000").glob("file-*.parquet"))) == 3
    assert len(list((lr / "videos/observation.images.eye_in_hand_rgb/chunk-000").glob("file-*.mp4"))) == 3
    schema = pq.read_schema(lr / "data/chunk-000/file-001.parquet")
    assert {f.name: str(f.type) for f in schema} == {
        "observation.state": "fixed_size_list<element: float>[8]",
        "observation.joint_states": "fixed_size_list<element: float>[6]",
        "action": "fixed_size_list<element: float>[7]", "next.reward": "float", "next.done": "bool",
        "timestamp": "float", "frame_index": "int64", "episode_index": "int64", "index": "int64", "task_index": "int64"}
    data = pq.read_table(lr / "data/chunk-000/file-001.parquet").to_pydict()
    assert data["episode_index"][0] == 4 and data["index"][0] == 40
    np.testing.assert_allclose(data["timestamp"][:3], np.float32([0, 0.1, 0.2]))
    tasks = pq.read_table(lr / "meta/tasks.parquet")
    assert tasks.column_names == ["task_index", "__index_level_0__"]
    assert json.loads(tasks.schema.metadata[b"pandas"])["index_columns"] == ["__index_level_0__"]
    rows = pq.read_table(lr / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
    key = "videos/observation.images.agentview_rgb/"
    assert [(r[key + "file_index"], r[key + "from_timestamp"], r[key + "to_timestamp"]) for r in rows[4:6]] == [
        (1, 0.0, 1.0), (1, 1.0, 2.0)]
    assert (rows[5]["dataset_from_index"], rows[5]["dataset_to_index"], rows[5]["data/file_index"]) == (50, 60, 1)
    assert rows[5]["tasks"] == [read_dataset(src)[5].instruction] and rows[5]["length"] == 10
    assert np.asarray(rows[0]["stats/observation.images.agentview_rgb/mean"]).shape == (3, 1, 1)
    stats = json.loads((lr / "meta/stats.json").read_text())
    assert stats["action"]["count"] == [120] and set(stats["action"]) >= {"min", "max", "mean", "std", "q01", "q99"}


def test_hdf5_lerobot_hdf5_round_trip(converted, tmp_path):
    src, lr, _ = converted
    original = read_dataset(src)
    errors = _compare(original, read_dataset(lr))
    assert errors.mean() < MEAN_TOL and np.percentile(errors, 99) < P99_TOL
    result = convert(lr, tmp_path / "back", "hdf5")
    assert (result.source_format, result.episodes) == ("lerobot", 12) and detect_format(tmp_path / "back") == "hdf5"
    back_errors = _compare(original, read_dataset(tmp_path / "back"))
    np.testing.assert_array_equal(back_errors, errors)  # HDF5 keeps the decoded frames as they are
    assert len(list((tmp_path / "back").glob("*.hdf5"))) == 4  # one file per task


def test_size_limits_split_files_and_av1_is_readable(tmp_path):
    eps = read_dataset(make_synthetic_dataset(tmp_path / "h5", episodes_per_goal=1, T=6, size=32))
    cfg = LeRobotWriteConfig(fps=FPS, vcodec=LEROBOT_CODEC, crf=30, data_files_size_in_mb=0,
                             video_files_size_in_mb=0, chunks_size=2)
    write_lerobot(tmp_path / "lr", eps, cfg)
    # a zero limit closes every file after one episode; two files per chunk folder
    assert sorted(str(p.relative_to(tmp_path / "lr")) for p in (tmp_path / "lr/data").rglob("*.parquet")) == [
        "data/chunk-000/file-000.parquet", "data/chunk-000/file-001.parquet",
        "data/chunk-001/file-000.parquet", "data/chunk-001/file-001.parquet"]
    assert _compare(eps, read_lerobot(tmp_path / "lr")).mean() < MEAN_TOL


@pytest.mark.skipif(LEROBOT_CODEC != "libsvtav1", reason="PyAV has no SVT-AV1 encoder")
def test_an_av1_encoder_leaves_every_thread_scheduled_as_its_caller(tmp_path):
    """Run as root, SVT-AV1 sets the thread opening it and the threads it starts to SCHED_FIFO 99 (as another user
    it cannot, and this holds trivially); threads that were running before keep whatever they had."""
    import os

    from pivla.data.lerobot.writer import open_encoder

    caller = (os.sched_getscheduler(0), os.sched_getparam(0))
    with av.open(str(tmp_path / "v.mp4"), "w") as c:
        s = c.add_stream("libsvtav1", rate=FPS)
        s.width, s.height, s.pix_fmt = 32, 32, "yuv420p"
        before = set(os.listdir("/proc/self/task"))
        open_encoder(s)
        threads = [0, *(int(t) for t in set(os.listdir("/proc/self/task")) - before)]
        assert len(threads) > 2  # the encoder's own threads are running
        assert [(os.sched_getscheduler(t), os.sched_getparam(t)) for t in threads] == [caller] * len(threads)
        for p in s.encode(av.VideoFrame.from_ndarray(np.zeros((32, 32, 3), np.uint8), format="rgb24")):
            c.mux(p)
        for p in s.encode():
            c.mux(p)


def test_trains_from_a_lerobot_folder(converted, tmp_path):
    from pivla import load_policy
    from pivla.training.trainer import train

    _, lr, _ = converted
    run = train(tiny_train_config(lr, tmp_path / "run", steps=3, batch_size=4, eval_every=100, ckpt_every=100,
                                  value_refresh_every=100, log_every=1))
    out = load_policy(run, device="cpu").infer({**{k: v[0] for k, v in read_lerobot(lr)[0].obs.items()},
                                                "instruction": "move the square left"})
    assert out["actions"].shape[1] == 7 and np.isfinite(out["actions"]).all()


# ------------------------------------------------------------------------------------------- bad input


def _break(root, case: str) -> None:
    info_path = root / "meta/info.json"
    info = json.loads(info_path.read_text())
    if case == "missing feature":
        del info["features"]["action"]
    elif case == "wrong shape":
        info["features"]["observation.state"]["shape"] = [6]
    elif case == "unsupported codebase_version":
        info["codebase_version"] = "v2.1"
    elif case == "missing meta file":
        (root / "meta/tasks.parquet").unlink()
    elif case == "truncated parquet":
        path = root / "data/chunk-000/file-001.parquet"
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    elif case == "corrupt episodes parquet":
        (root / "meta/episodes/chunk-000/file-000.parquet").write_bytes(b"PAR1 not really parquet")
    elif case == "unreadable video":
        (root / "videos/observation.images.image/chunk-000/file-001.mp4").write_bytes(b"\x00" * 4096)
    elif case == "empty episode":
        rows = pq.read_table(root / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
        rows[1]["length"] = 0
        pq.write_table(pa.Table.from_pylist(rows), root / "meta/episodes/chunk-000/file-000.parquet")
    elif case == "video too short":
        rows = pq.read_table(root / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
        rows[1]["videos/observation.images.image/from_timestamp"] = 0.9  # past the end of the file's 12 frames
        pq.write_table(pa.Table.from_pylist(rows), root / "meta/episodes/chunk-000/file-000.parquet")
    info_path.write_text(json.dumps(info))


@pytest.mark.parametrize("case, message", [
    ("missing feature", "missing feature 'action'"),
    ("wrong shape", r"column 'observation.state' has 8 values per row, meta/info.json declares shape \[6\]"),
    ("unsupported codebase_version", "unsupported LeRobot codebase_version 'v2.1'"),
    ("missing meta file", "missing meta/tasks.parquet"),
    ("truncated parquet", "file-001.parquet: truncated or corrupt parquet"),
    ("corrupt episodes parquet", "meta/episodes/chunk-000/file-000.parquet: truncated or corrupt parquet"),
    ("unreadable video", "file-001.mp4: unreadable video"),
    ("empty episode", "episode 1 has length 0; an episode needs a frame"),
    ("video too short", "episode 1 needs 7 frames from 0.900 s, the video has 3 of them"),
])
def test_bad_input_gets_a_named_error(fixture_dataset, tmp_path, case, message):
    root = tmp_path / "ds"
    shutil.copytree(fixture_dataset[0], root)
    _break(root, case)
    with pytest.raises(DatasetError, match=message):
        read_dataset(root)


def test_bad_requests_get_named_errors(fixture_dataset, tmp_path):
    root, _ = fixture_dataset
    with pytest.raises(DatasetError, match=r"missing feature for observation key\(s\) \['agentview_rgb'\]"):
        read_lerobot(root, obs_keys=("agentview_rgb",))
    with pytest.raises(DatasetError, match="already a lerobot dataset"):
        convert(root, tmp_path / "x", "lerobot")
    with pytest.raises(DatasetError, match="overlaps the source"):
        convert(root, root / "inside", "hdf5")
    (tmp_path / "taken").mkdir()
    (tmp_path / "taken/file").write_text("")
    with pytest.raises(DatasetError, match="already exists"):
        convert(root, tmp_path / "taken", "hdf5")
    with pytest.raises(DatasetError, match="neither a LeRobot dataset"):
        detect_format(tmp_path / "taken")
    ep = Episode(actions=np.zeros((3, 7)), obs={"cam": np.zeros((3, 9, 8, 3), np.uint8)}, instruction="x")
    with pytest.raises(DatasetError, match="9x8: yuv420p video needs even height and width"):
        write_lerobot(tmp_path / "odd", [ep], LeRobotWriteConfig(fps=FPS))
    other = Episode(actions=np.zeros((3, 7)), obs={"cam2": np.zeros((3, 8, 8, 3), np.uint8)}, instruction="x")
    ok = Episode(actions=np.zeros((3, 7)), obs={"cam": np.zeros((3, 8, 8, 3), np.uint8)}, instruction="x")
    with pytest.raises(DatasetError, match="differ from the first episode's"):
        write_lerobot(tmp_path / "mixed", [ok, other], LeRobotWriteConfig(fps=FPS))
    assert not (tmp_path / "mixed").exists()  # nothing half-written
    with pytest.raises(DatasetError, match="record no control rate"):
        convert(make_synthetic_dataset(tmp_path / "h5", episodes_per_goal=1, T=3), tmp_path / "lr", "lerobot")
