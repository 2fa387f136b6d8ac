"""Action spaces as data: a LeRobot SO-101 dataset (six absolute joint positions) trains as it is, with its
cameras, state and action space taken from meta/info.json; datasets whose actions differ from the policy's
are refused by name; a 7-D twin run's batches and actions are those recorded before action spaces existed.

The SO-101 dataset is written here with pyarrow and PyAV in the layout lerobot 0.4.4 records for
``so101_follower`` (not with pivla's writer), at 48x64 instead of 480x640."""

import dataclasses
import hashlib
import json
from pathlib import Path

import h5py
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from pivla.cli import main
from pivla.control.contract import ChunkPolicy, PolicySpec
from pivla.control.executors import make_executor
from pivla.data.action_space import (
    EE_DELTA,
    ActionKind,
    ActionSpace,
    infer_action_space,
)
from pivla.data.convert import convert
from pivla.data.episode import DatasetError
from pivla.data.hdf5 import read_action_space, write_episodes
from pivla.data.lerobot.reader import lerobot_action_space
from pivla.data.read import dataset_layout, read_dataset
from pivla.data.synthetic import make_synthetic_dataset
from pivla.policy import load_policy
from pivla.training.config import FROM_DATASET
from pivla.training.trainer import Trainer
from tests.conftest import tiny_train_config
from tests.lerobot_files import encode_video, fixed_list

JOINTS = ["shoulder_pan.pos", "shoulder_lift.pos", "elbow_flex.pos", "wrist_flex.pos", "wrist_roll.pos", "gripper.pos"]
FPS, H, W = 30, 48, 64
FIXTURE = Path(__file__).parent / "fixtures" / "ee_delta_run.npz"
TINY_FLAGS = ["--steps", "3", "--batch-size", "4", "--warmup", "1", "--log-every", "1", "--eval-every", "100",
              "--ckpt-every", "100", "--value-refresh-every", "100", "--threads", "2", "--no-progress",
              "--model.image-size", "32", "--model.backbone.d-model", "64", "--model.backbone.n-layers", "1",
              "--model.backbone.vision-channels", "16", "16", "32", "32"]


def write_so101(root: Path, lengths=(12, 10, 14), names=JOINTS) -> dict:
    """An SO-101 recording as lerobot writes it: one data file, one mp4 per camera, episodes back to back.
    Joint targets in degrees sweep smoothly; the gripper closes from 80 to 5 percent; the state lags the action
    by one frame. Returns the actions."""
    rng = np.random.default_rng(3)
    video_info = {"video.height": H, "video.width": W, "video.codec": "h264", "video.pix_fmt": "yuv420p",
                  "video.is_depth_map": False, "video.fps": FPS, "video.channels": 3, "has_audio": False}
    image = {"dtype": "video", "shape": [H, W, 3], "names": ["height", "width", "channels"], "info": video_info}
    features = {"action": {"dtype": "float32", "shape": [6], "names": list(names)},
                "observation.state": {"dtype": "float32", "shape": [6], "names": list(names)},
                "observation.images.front": image, "observation.images.wrist": image}
    for name, dtype in [("timestamp", "float32"), ("frame_index", "int64"), ("episode_index", "int64"),
                        ("index", "int64"), ("task_index", "int64")]:
        features[name] = {"dtype": dtype, "shape": [1], "names": None}
    actions, cols, rows, frames, start = [], {k: [] for k in features if "images" not in k}, [], [], 0
    for e, T in enumerate(lengths):
        s = np.linspace(0, 1, T)[:, None]
        a = np.concatenate([-30 + 60 * s + rng.normal(0, 0.5, (T, 1)), 90 - 40 * s, 60 + 20 * np.sin(4 * s),
                            -20 * s, 10 * np.cos(3 * s), 80 - 75 * s], axis=1).astype(np.float32)
        actions.append(a)
        picture = np.zeros((T, H, W, 3), np.uint8)
        picture[..., 0] = np.linspace(20, 220, W, dtype=np.uint8)
        for t in range(T):
            picture[t, 16:28, 2 + 3 * t:12 + 3 * t] = 240
        frames.append(picture)
        cols["action"].append(fixed_list(a))
        cols["observation.state"].append(fixed_list(np.concatenate([a[:1], a[:-1]])))
        cols["timestamp"].append(pa.array((np.arange(T) / FPS).astype(np.float32)))
        cols["frame_index"].append(pa.array(np.arange(T, dtype=np.int64)))
        cols["episode_index"].append(pa.array(np.full(T, e, np.int64)))
        cols["index"].append(pa.array(np.arange(start, start + T, dtype=np.int64)))
        cols["task_index"].append(pa.array(np.zeros(T, np.int64)))
        row = {"episode_index": e, "tasks": ["grab the cube"], "length": T, "data/chunk_index": 0,
               "data/file_index": 0, "dataset_from_index": start, "dataset_to_index": start + T,
               "meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0}
        for cam in ("front", "wrist"):
            row |= {f"videos/observation.images.{cam}/chunk_index": 0, f"videos/observation.images.{cam}/file_index": 0,
                    f"videos/observation.images.{cam}/from_timestamp": start / FPS,
                    f"videos/observation.images.{cam}/to_timestamp": (start + T) / FPS}
        rows.append(row)
        start += T
    (root / "data/chunk-000").mkdir(parents=True)
    pq.write_table(pa.table({k: pa.concat_arrays(v) for k, v in cols.items()}),
                   root / "data/chunk-000/file-000.parquet")
    for cam, flip in (("front", False), ("wrist", True)):
        video = np.concatenate(frames)
        encode_video(root / f"videos/observation.images.{cam}/chunk-000/file-000.mp4",
                     video[:, ::-1] if flip else video, FPS, "libx264")
    (root / "meta/episodes/chunk-000").mkdir(parents=True)
    pq.write_table(pa.Table.from_pylist(rows), root / "meta/episodes/chunk-000/file-000.parquet")
    pq.write_table(pa.table({"task_index": pa.array([0], pa.int64()), "__index_level_0__": ["grab the cube"]}),
                   root / "meta/tasks.parquet")
    info = {"codebase_version": "v3.0", "robot_type": "so101_follower", "total_episodes": len(lengths),
            "total_frames": start, "total_tasks": 1, "chunks_size": 1000, "data_files_size_in_mb": 100,
            "video_files_size_in_mb": 200, "fps": FPS, "splits": {"train": f"0:{len(lengths)}"},
            "data_path": "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet",
            "video_path": "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4", "features": features}
    (root / "meta/info.json").write_text(json.dumps(info, indent=4))
    (root / "meta/stats.json").write_text("{}")
    return {"actions": np.concatenate(actions)}


@pytest.fixture(scope="module")
def so101(tmp_path_factory):
    root = tmp_path_factory.mktemp("so101") / "so101"
    return root, write_so101(root)


@pytest.fixture(scope="module")
def so101_run(so101, tmp_path_factory):
    run = tmp_path_factory.mktemp("so101_run") / "run"
    assert main(["train", "--data", str(so101[0]), "--out", str(run), *TINY_FLAGS]) == 0
    return run


def _obs(so101_root: Path, t: int = 3) -> dict:
    ep = read_dataset(so101_root)[0]
    return {**{k: v[t] for k, v in ep.obs.items()}, "instruction": ep.instruction}


# -- the action space ---------------------------------------------------------------------------------------
def test_names_declare_the_kind_and_the_gripper():
    so = infer_action_space(JOINTS)
    assert (so.kind, so.dim, so.gripper, so.gripper_range, so.gripper_binary) == (
        ActionKind.JOINT_POSITION, 6, 5, (0.0, 100.0), False)
    assert so.units == ("deg",) * 5 + ("percent",)
    assert infer_action_space(list(EE_DELTA.names)) == EE_DELTA and EE_DELTA.binary_gripper == 6
    other = infer_action_space(["a", "b"])
    assert (other.kind, other.gripper) == (ActionKind.UNKNOWN, None)
    for space in (so, EE_DELTA, other):
        assert ActionSpace.from_dict(json.loads(json.dumps(space.to_dict()))) == space
    # holding still: zero motion with the gripper as it was (deltas), the last target itself (positions)
    assert EE_DELTA.hold(None) == [0.0] * 6 + [-1.0] and EE_DELTA.hold([1.0] * 7) == [0.0] * 6 + [1.0]
    assert so.hold([1, 2, 3, 4, 5, 6]) == [1, 2, 3, 4, 5, 6]
    with pytest.raises(ValueError, match="no pose to hold before its first action"):
        so.hold(None)
    with pytest.raises(ValueError, match="distinct dimension names"):
        ActionSpace(("a", "a"))
    # a spec from a server written before action spaces existed is the twin's
    old = {"cameras": [], "image_size": 32, "proprio": [], "chunk": 8, "horizon": 5, "action_dim": 7,
           "action_space": "ee_delta_pos3_rot3_gripper1"}
    assert PolicySpec.from_dict(old).action_space == EE_DELTA


def test_so101_dataset_declares_its_cameras_state_and_joint_positions(so101):
    root, src = so101
    layout = dataset_layout(root)
    assert layout.cameras == ("front", "wrist") and layout.proprio == ("state",) and layout.vectors == {"state": 6}
    assert layout.action_space == infer_action_space(JOINTS)
    episodes = read_dataset(root)
    np.testing.assert_array_equal(np.concatenate([ep.actions for ep in episodes]), src["actions"])
    assert episodes[0].obs["front"].shape == (12, H, W, 3)


def test_action_space_survives_conversion_both_ways(so101, tmp_path):
    root, src = so101
    convert(root, tmp_path / "h5", "hdf5")
    space = infer_action_space(JOINTS)
    assert {read_action_space(p) for p in (tmp_path / "h5").glob("*.hdf5")} == {space}
    assert dataset_layout(tmp_path / "h5").cameras == ("front", "wrist")
    convert(tmp_path / "h5", tmp_path / "lr", "lerobot")
    info = json.loads((tmp_path / "lr/meta/info.json").read_text())
    assert info["features"]["action"]["names"] == JOINTS and lerobot_action_space(tmp_path / "lr") == space
    back = np.concatenate([ep.actions for ep in read_dataset(tmp_path / "lr")])
    np.testing.assert_array_equal(back, src["actions"])


def test_hdf5_without_an_action_space_reads_as_the_twins(tmp_path):
    make_synthetic_dataset(tmp_path / "d", episodes_per_goal=1, T=5, size=16)
    path = next((tmp_path / "d").glob("*.hdf5"))
    with h5py.File(path, "a") as f:
        del f["data"].attrs["action_space"]  # as LIBERO's own files and pivla's older ones are
    assert read_action_space(path) == EE_DELTA
    assert dataset_layout(tmp_path / "d").proprio == ("ee_pos", "ee_ori", "gripper_states")


# -- training on SO-101 data ----------------------------------------------------------------------------------
def test_pivla_train_on_so101_gives_a_joint_position_policy(so101, so101_run):
    root, src = so101
    cfg = json.loads((so101_run / "config.json").read_text())["model"]
    assert (cfg["cameras"], cfg["proprio_keys"], cfg["proprio_dim"], cfg["action_dim"]) == (
        ["front", "wrist"], ["state"], 6, 6)
    stats = json.loads((so101_run / "norm_stats.json").read_text())
    assert stats["action"]["gripper_dim"] is None and stats["action_space"]["names"] == JOINTS
    policy = load_policy(so101_run, device="cpu", encoder_runtime="torch")
    assert isinstance(policy, ChunkPolicy)
    assert policy.spec.action_space == infer_action_space(JOINTS) and policy.spec.action_dim == 6
    assert policy.spec.cameras == ("front", "wrist") and policy.spec.proprio == (("state", 6),)
    out = policy.infer(_obs(root))
    actions = out["actions"]
    assert actions.shape == (8, 6) and out["discrete_probs"].shape == (8, 6, 256)
    # de-normalised into the dataset's units: degrees and gripper percent, within the data's 1st-99th percentiles
    lo, hi = np.quantile(src["actions"], 0.01, axis=0), np.quantile(src["actions"], 0.99, axis=0)
    assert (actions >= lo - 1e-3).all() and (actions <= hi + 1e-3).all()
    assert not np.isin(actions[:, 5], (-1.0, 1.0)).any()  # a position, not a thresholded open/close command
    executor = make_executor("fixed")
    executor.reset()
    first = executor.act(policy, _obs(root))
    assert first.shape == (6,)
    np.testing.assert_array_equal(executor.hold_action(policy.spec, _obs(root)), first)  # holding repeats it


def test_so101_policy_serves_its_action_space(so101, so101_run, tmp_path):
    from pivla.serving import RemotePolicy
    from tests.test_serving import KEY, running_server

    with running_server(so101_run, tmp_path) as (port, _), \
            RemotePolicy(f"ws://127.0.0.1:{port}", api_key=KEY) as remote:
        assert remote.metadata["spec"]["action_space"]["kind"] == "joint_position"
        assert remote.spec.action_space == infer_action_space(JOINTS)
        out = remote.infer(_obs(so101[0]))
    local = load_policy(so101_run, device="cpu", encoder_runtime="torch").infer(_obs(so101[0]))
    np.testing.assert_allclose(out["actions"], local["actions"], atol=1e-4)


def test_a_7d_dataset_in_lerobots_own_layout_trains_with_its_keys(tmp_path):
    """Cameras ``image``, a state named by lerobot (no pivla split) and unnamed 7-D actions: no flags needed."""
    from tests.test_lerobot import write_fixture

    write_fixture(tmp_path / "lr")
    cfg = tiny_train_config(tmp_path / "lr", tmp_path / "run", steps=2, batch_size=4, eval_every=100,
                            ckpt_every=100, value_refresh_every=100)
    t = Trainer(dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, **FROM_DATASET)))
    assert (t.cfg.model.cameras, t.cfg.model.proprio_keys, t.cfg.model.proprio_dim) == (("image",), ("state",), 8)
    assert t.stats.space.kind == ActionKind.UNKNOWN and t.stats.space.dim == 7


# -- refusals -------------------------------------------------------------------------------------------------
def test_datasets_whose_actions_differ_are_refused_by_name(so101, so101_run, tmp_path):
    root, _ = so101
    twin = make_synthetic_dataset(tmp_path / "twin", episodes_per_goal=1, T=6, size=16)
    so = dataclasses.replace(tiny_train_config(root, tmp_path / "r1"), model=dataclasses.replace(
        tiny_train_config(root, tmp_path / "r1").model, **FROM_DATASET))
    with pytest.raises(ValueError, match=rf"--extra-data {twin} has actions ee_delta \(7-D: x, y, z.*the policy's are "
                                         r"joint_position \(6-D: shoulder_pan.pos"):
        Trainer(dataclasses.replace(so, extra_data=(str(twin),)))
    # resuming the SO-101 run on a dataset of six other joints (same dimension, other names)
    renamed = tmp_path / "renamed"
    write_so101(renamed, lengths=(6, 6), names=[f"j{i}.pos" for i in range(6)])
    with pytest.raises(ValueError, match=r"--data .*renamed has actions joint_position \(6-D: j0.pos.*the policy's are "
                                         r"joint_position \(6-D: shoulder_pan.pos"):
        main(["train", "--data", str(renamed), "--out", str(so101_run), "--resume", "--debug"])
    # a config that names another dimension than the dataset's
    with pytest.raises(DatasetError, match=r"the dataset's actions are joint_position \(6-D.*action_dim is 7"):
        Trainer(tiny_train_config(root, tmp_path / "r2"))
    # one dataset, two action spaces
    mixed = tmp_path / "mixed"
    make_synthetic_dataset(mixed, episodes_per_goal=1, T=6, size=16)
    ep = read_dataset(mixed)[0]
    write_episodes(mixed / "z_six.hdf5", [dataclasses.replace(ep, actions=ep.actions[:, :6])],
                   action_space=infer_action_space(JOINTS))
    with pytest.raises(DatasetError, match="one dataset holds one action space"):
        dataset_layout(mixed)


def test_lerobot_action_names_must_name_every_dimension(so101, tmp_path):
    import shutil

    shutil.copytree(so101[0], tmp_path / "ds")
    info = json.loads((tmp_path / "ds/meta/info.json").read_text())
    info["features"]["action"]["names"] = JOINTS[:5]
    (tmp_path / "ds/meta/info.json").write_text(json.dumps(info))
    with pytest.raises(DatasetError, match=r"feature 'action' names .* do not name its 6 dimensions"):
        read_dataset(tmp_path / "ds")


# -- the twin's figures ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("inputs", ["named", "from the dataset"])
def test_a_7d_run_trains_and_acts_as_before_action_spaces(tmp_path, inputs):
    """The first training batch and the actions on a fixed input of a tiny twin-layout run, recorded on the code
    before action spaces (tests/fixtures/ee_delta_run.npz): the batch exactly, the outputs to float noise."""
    data = make_synthetic_dataset(tmp_path / "data", episodes_per_goal=2, T=12, size=32, failures=1)
    cfg = tiny_train_config(data, tmp_path / "run", steps=4, eval_every=2, ckpt_every=4, value_refresh_every=2,
                            threads=1)
    if inputs == "from the dataset":
        cfg = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, **FROM_DATASET))
    t = Trainer(cfg)
    batch = {k: v.numpy() for k, v in t._batch(t.train_set, 0, 0, 1, augment=True).items()}
    t.run()
    policy = load_policy(tmp_path / "run", device="cpu", encoder_runtime="torch")
    rng = np.random.default_rng(5)
    obs = {c: rng.integers(0, 255, (32, 32, 3), dtype=np.uint8) for c in policy.spec.cameras}
    obs.update(ee_pos=np.array([.4, .5, .1], np.float32), ee_ori=np.zeros(3, np.float32),
               gripper_states=np.array([.02, .02], np.float32), instruction="move the square left")
    out = policy.infer(obs)
    want = np.load(FIXTURE)
    assert (hashlib.sha256(np.ascontiguousarray(batch["images"]).tobytes()).hexdigest()
            == str(want["batch_images_sha256"]))
    for key in want.files:
        if key.startswith("batch_") and key != "batch_images_sha256":
            np.testing.assert_array_equal(batch[key[6:]], want[key], err_msg=key)
        elif key.startswith("out_"):
            np.testing.assert_allclose(out[key[4:]], want[key], rtol=1e-5, atol=1e-6, err_msg=key)
    assert policy.spec.action_space == EE_DELTA and json.loads((tmp_path / "run/config.json").read_text())[
        "model"]["cameras"] == ["agentview_rgb", "eye_in_hand_rgb"]


# -- relative actions ---------------------------------------------------------------------------------------
def test_chunk_offsets_start_from_the_pose_at_the_chunks_first_step():
    from pivla.data.samples import chunk_offsets

    actions = np.arange(12, dtype=np.float32).reshape(4, 3) * 10  # T=4, D=3, the last dim a gripper
    pose = actions - 1.0
    out, inside = chunk_offsets(actions, pose, 3, np.array([0, 1]))
    assert out.shape == (4, 3, 3) and inside.tolist() == [[1, 1, 1], [1, 1, 1], [1, 1, 0], [1, 0, 0]]
    np.testing.assert_array_equal(out[1, :, :2], actions[1:4, :2] - pose[1, :2])  # offsets from step 1's pose
    np.testing.assert_array_equal(out[1, :, 2], actions[1:4, 2])  # the gripper stays absolute
    np.testing.assert_array_equal(out[3, 2], np.r_[actions[3, :2] - pose[3, :2], actions[3, 2]])  # past the end


def test_a_relative_policy_learns_offsets_and_acts_in_absolute_targets(so101, tmp_path):
    root, src = so101
    run = tmp_path / "rel"
    assert main(["train", "--data", str(root), "--out", str(run), *TINY_FLAGS, "--model.relative-actions"]) == 0
    policy = load_policy(run, device="cpu")
    stats = policy.stats
    assert stats.reference == "state" and stats.target is not None and stats.relative_dims().tolist() == [0, 1, 2, 3, 4]
    # absolute statistics span the data (a joint's extremes are poses to reach), offsets their percentiles
    train = np.concatenate([read_dataset(root)[e].actions for e in json.loads((run / "split.json").read_text())[
        "train_episodes"]])
    np.testing.assert_allclose(stats.action.q01, train.min(0), atol=1e-4)
    np.testing.assert_allclose(stats.action.q99, train.max(0), atol=1e-4)
    obs = _obs(root)
    out = policy.infer(obs)
    cont = out["continuous_normalized"]  # the heads are offsets: the arm adds the pose it is at
    expected = stats.action.unnormalize(stats.action.normalize(stats.to_absolute(cont, obs["state"])))
    expected[:, 5] = out["actions"][:, 5]  # the gripper from the discrete head
    np.testing.assert_allclose(out["actions"], expected, atol=1e-4)
    np.testing.assert_allclose(policy.to_actions(out["actions_normalized"]), out["actions"], atol=1e-4)
    moved = {**obs, "state": obs["state"] + np.r_[5.0, 0, 0, 0, 0, 0].astype(np.float32)}
    shift = policy.infer(moved)["actions"][:, 0] - out["actions"][:, 0]  # the same offsets from another pose
    assert np.all(np.abs(shift) > 0.5)


def test_relative_actions_are_refused_for_end_effector_deltas(tmp_path):
    data = make_synthetic_dataset(tmp_path / "ee", episodes_per_goal=1, T=6, size=16)
    with pytest.raises(DatasetError, match=r"relative actions are offsets from the present pose: the dataset's "
                                           r"actions are ee_delta"):
        main(["train", "--data", str(data), "--out", str(tmp_path / "run"), *TINY_FLAGS, "--model.relative-actions",
              "--debug"])


def test_the_so101_preset_trains_a_film_relative_policy_on_a_lerobot_recording(so101, tmp_path):
    root, _ = so101
    run = tmp_path / "preset"
    assert main(["train", "--preset", "so101", "--data", str(root), "--out", str(run), *TINY_FLAGS]) == 0
    policy = load_policy(run, device="cpu")
    assert policy.cfg.backbone.film and policy.model.backbone.film is not None
    assert policy.cfg.relative_actions and policy.stats.reference == "state"
    assert policy.infer(_obs(root))["actions"].shape == (8, 6)
