"""LeRobot dataset format v3.0, read and written with pyarrow and PyAV.

The ``lerobot`` package pins an older torch and torchvision than pivla's, so pivla implements the on-disk
format itself (as lerobot 0.4.4 writes it)::

    meta/info.json                               codebase_version "v3.0", fps, features, path templates, totals
    meta/stats.json                              per-feature min/max/mean/std/count/q01..q99
    meta/tasks.parquet                           task_index + the task string (pandas index __index_level_0__)
    meta/episodes/chunk-XXX/file-XXX.parquet     one row per episode: length, data file and row range,
                                                 per camera the mp4 file and [from_timestamp, to_timestamp)
    data/chunk-XXX/file-XXX.parquet              one row per frame, many episodes per file
    videos/<feature>/chunk-XXX/file-XXX.mp4      many episodes per file, one after the other

Mapping to pivla's :class:`~pivla.data.format.Episode` (docs/dataset.md, "LeRobot v3.0"):
``observation.images.NAME`` <-> image key ``NAME``; ``observation.state`` <-> the proprio keys, concatenated,
with ``names`` ``["ee_pos.0", "ee_pos.1", ...]`` recording the split so reading restores the keys (other
names give one key ``state``); other low-dim keys <-> ``observation.KEY``; ``action`` <-> ``actions``;
``next.reward``/``next.done`` <-> rewards/dones; task strings <-> instructions; the episode's success,
source and meta live in extra ``pivla/*`` columns of ``meta/episodes`` (lerobot ignores them). The action
space is the ``action`` feature's ``names`` and shape (``pivla.data.action_space.infer_action_space``), or
the ``pivla/action_space`` entry pivla adds to that feature.
"""

from __future__ import annotations

import io
import json
import math
import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field, replace
from fractions import Fraction
from pathlib import Path
from typing import Annotated, Literal

import av
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import tyro

from pivla.data.action_space import EE_DELTA, ActionSpace, infer_action_space
from pivla.data.episode import PROPRIO_KEYS, STATE_KEY, DatasetError, DatasetLayout, Episode
from pivla.data.hdf5 import dataset_files, hdf5_action_space, read_env_meta, read_episodes, write_episodes
from pivla.io import atomic_dir

CODEBASE_VERSION = "v3.0"
INFO_PATH = "meta/info.json"
STATS_PATH = "meta/stats.json"
TASKS_PATH = "meta/tasks.parquet"
EPISODES_DIR = "meta/episodes"
CHUNK_FILE = "chunk-{chunk_index:03d}/file-{file_index:03d}"
EPISODES_PATH = EPISODES_DIR + "/" + CHUNK_FILE + ".parquet"
DATA_PATH = "data/" + CHUNK_FILE + ".parquet"
VIDEO_PATH = "videos/{video_key}/" + CHUNK_FILE + ".mp4"

IMAGE_PREFIX = "observation.images."
OBS_PREFIX = "observation."
STATE = "observation.state"
ACTION = "action"
REWARD = "next.reward"
DONE = "next.done"
SUCCESS = "next.success"
INDEX_FEATURES = {
    "timestamp": {"dtype": "float32", "shape": [1], "names": None},
    "frame_index": {"dtype": "int64", "shape": [1], "names": None},
    "episode_index": {"dtype": "int64", "shape": [1], "names": None},
    "index": {"dtype": "int64", "shape": [1], "names": None},
    "task_index": {"dtype": "int64", "shape": [1], "names": None},
}
IMAGE_NAMES = ["height", "width", "channels"]
QUANTILES = {"q01": 0.01, "q10": 0.10, "q50": 0.50, "q90": 0.90, "q99": 0.99}
PIVLA_SUCCESS, PIVLA_SOURCE, PIVLA_META = "pivla/success", "pivla/source", "pivla/meta"
PIVLA_ACTION_SPACE = "pivla/action_space"  # an entry of the action feature in info.json (lerobot ignores it)
CODECS = {"libx264": {}, "libsvtav1": {"preset": "12"}}  # per-codec extra options (lerobot's SVT preset)
MB = 1024 * 1024


# --------------------------------------------------------------------------------------------- writing


@dataclass
class LeRobotWriteConfig:
    """How episodes become a LeRobot v3.0 dataset."""

    fps: int | None = None
    """Frames per second (default: the source's control rate, HDF5 env_args control_hz)."""
    state_keys: tuple[str, ...] | None = None
    """Low-dim keys concatenated, in order, into observation.state (default: those of ee_pos, ee_ori,
    gripper_states present); every other low-dim key gets its own observation.<key> feature."""
    state_names: tuple[str, ...] | None = None
    """Names of observation.state's dimensions (default: KEY.0, KEY.1, ... per state key, which reading splits
    back into the keys; other names, such as LeRobot's SO-101 ``shoulder_pan.pos`` ..., read back as one key
    ``state``)."""
    vcodec: Literal["libx264", "libsvtav1"] = "libx264"
    """Video codec: H.264, or AV1 as lerobot itself writes."""
    crf: int = 18
    """Constant rate factor: lower is closer to the source and bigger (lerobot uses 30)."""
    gop: int = 2
    """Keyframe interval in frames; lerobot's 2 keeps its random access by timestamp cheap."""
    episodes_per_file: int | None = None
    """At most this many episodes per data and video file (default: no cap, the size limits decide)."""
    data_files_size_in_mb: int = 100
    """A data parquet file takes no new episode once it holds this much (uncompressed)."""
    video_files_size_in_mb: int = 200
    """An mp4 file takes no new episode once it holds this much."""
    chunks_size: int = 1000
    """Files per chunk-XXX folder."""
    robot_type: str | None = None
    """Recorded as info.json robot_type."""


def _next_file(chunk: int, file: int, chunks_size: int) -> tuple[int, int]:
    return (chunk + 1, 0) if file == chunks_size - 1 else (chunk, file + 1)


@dataclass
class _FileSeq:
    """Chunk/file indices of a sequence of files, each closed once it reaches a size or episode cap."""

    limit_bytes: float
    per_file: int | None
    chunks_size: int
    chunk: int = 0
    file: int = 0
    size: int = 0
    episodes: int = 0
    units: int = 0  # frames (or rows) already in the current file

    def full(self) -> bool:
        return self.episodes > 0 and (self.size >= self.limit_bytes or
                                      (self.per_file is not None and self.episodes >= self.per_file))

    def advance(self) -> None:
        self.chunk, self.file = _next_file(self.chunk, self.file, self.chunks_size)
        self.size = self.episodes = self.units = 0


class _VideoSink:
    """One camera's mp4 files: frames of consecutive episodes encoded back to back in one stream, so an
    episode starts at ``frames before it / fps`` seconds, the ``from_timestamp`` lerobot seeks to."""

    def __init__(self, root: Path, feature: str, cfg: LeRobotWriteConfig, shape: tuple[int, int, int]):
        self.root, self.feature, self.cfg, self.shape = root, feature, cfg, shape
        self.seq = _FileSeq(cfg.video_files_size_in_mb * MB, cfg.episodes_per_file, cfg.chunks_size)
        self.container = self.stream = None
        self.first_path: Path | None = None

    def _open(self) -> None:
        path = self.root / VIDEO_PATH.format(video_key=self.feature, chunk_index=self.seq.chunk,
                                             file_index=self.seq.file)
        path.parent.mkdir(parents=True, exist_ok=True)
        self.first_path = self.first_path or path
        self.container = av.open(str(path), mode="w", format="mp4")
        options = {"g": str(self.cfg.gop), "crf": str(self.cfg.crf), **CODECS[self.cfg.vcodec]}
        self.stream = self.container.add_stream(self.cfg.vcodec, rate=self.cfg.fps, options=options)
        self.stream.height, self.stream.width = self.shape[0], self.shape[1]
        self.stream.pix_fmt = "yuv420p"

    def _mux(self, packets) -> None:
        for packet in packets:
            self.seq.size += packet.size
            self.container.mux(packet)

    def close(self) -> None:
        if self.container is not None:
            self._mux(self.stream.encode())
            self.container.close()
            self.container = self.stream = None

    def add(self, frames: np.ndarray) -> dict:
        if self.seq.full():
            self.close()
            self.seq.advance()
        if self.container is None:
            self._open()
        start = self.seq.units
        time_base = Fraction(1, self.cfg.fps)
        for i, image in enumerate(frames):
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format="rgb24")
            frame.pts, frame.time_base = start + i, time_base
            self._mux(self.stream.encode(frame))
        self.seq.units += len(frames)
        self.seq.episodes += 1
        prefix = f"videos/{self.feature}/"
        return {prefix + "chunk_index": self.seq.chunk, prefix + "file_index": self.seq.file,
                prefix + "from_timestamp": start / self.cfg.fps,
                prefix + "to_timestamp": (start + len(frames)) / self.cfg.fps}


def _video_info(path: Path) -> dict:
    """The ``info`` block lerobot records for a video feature, read back from the written file."""
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        return {"video.height": stream.height, "video.width": stream.width,
                "video.codec": stream.codec_context.codec.canonical_name, "video.pix_fmt": stream.pix_fmt,
                "video.is_depth_map": False, "video.fps": int(stream.base_rate), "video.channels": 3,
                "has_audio": len(container.streams.audio) > 0}


def _vector_stats(x: np.ndarray) -> dict[str, np.ndarray]:
    """lerobot's per-episode statistics of a (T,) or (T, D) feature; scalars keep a length-1 axis."""
    x = np.asarray(x, np.float64).reshape(len(x), -1)
    stats = {"min": x.min(0), "max": x.max(0), "mean": x.mean(0), "std": x.std(0),
             "count": np.array([len(x)])}
    stats.update({k: np.quantile(x, q, axis=0) for k, q in QUANTILES.items()})
    return stats


def _image_stats(frames: np.ndarray) -> dict[str, np.ndarray]:
    """Per-channel statistics in [0, 1], shaped (3, 1, 1) as lerobot stores them; exact, from the 256-bin
    histogram of the uint8 pixels."""
    values = np.arange(256, dtype=np.float64)
    out: dict[str, list] = {k: [] for k in ("min", "max", "mean", "std", *QUANTILES)}
    for c in range(3):
        hist = np.bincount(frames[..., c].ravel(), minlength=256).astype(np.float64)
        n = hist.sum()
        mean = (hist * values).sum() / n
        cum = np.cumsum(hist)
        nonzero = np.flatnonzero(hist)
        out["min"].append(nonzero[0])
        out["max"].append(nonzero[-1])
        out["mean"].append(mean)
        out["std"].append(math.sqrt((hist * (values - mean) ** 2).sum() / n))
        for k, q in QUANTILES.items():
            out[k].append(int(np.searchsorted(cum, q * n)))
    stats = {k: np.asarray(v, np.float64).reshape(3, 1, 1) / 255.0 for k, v in out.items()}
    stats["count"] = np.array([len(frames)])
    return stats


def _aggregate_stats(per_episode: list[dict[str, dict[str, np.ndarray]]]) -> dict:
    """Dataset statistics from per-episode ones, as lerobot aggregates them: exact min/max/mean/std (parallel
    variance), count-weighted quantiles."""
    out = {}
    for key in per_episode[0]:
        stats = [s[key] for s in per_episode]
        counts = np.array([s["count"][0] for s in stats], np.float64)
        w = counts.reshape(-1, *([1] * stats[0]["mean"].ndim))
        means = np.stack([s["mean"] for s in stats])
        mean = (means * w).sum(0) / counts.sum()
        var = ((np.stack([s["std"] for s in stats]) ** 2 + (means - mean) ** 2) * w).sum(0) / counts.sum()
        agg = {"min": np.min([s["min"] for s in stats], 0), "max": np.max([s["max"] for s in stats], 0),
               "mean": mean, "std": np.sqrt(var), "count": np.array([int(counts.sum())])}
        agg.update({k: (np.stack([s[k] for s in stats]) * w).sum(0) / counts.sum() for k in QUANTILES})
        out[key] = {k: v.tolist() for k, v in agg.items()}
    return out


def _fixed_list(x: np.ndarray) -> pa.Array:
    x = np.ascontiguousarray(x, np.float32)
    return pa.FixedSizeListArray.from_arrays(pa.array(x.reshape(-1)), x.shape[1])


def _split_obs(ep: Episode) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """(images, low-dim) observation keys: images are (T, H, W, 3) uint8, everything else is a vector."""
    images, low = {}, {}
    for key, arr in ep.obs.items():
        arr = np.asarray(arr)
        if arr.ndim == 4 and arr.shape[-1] == 3 and arr.dtype == np.uint8:
            images[key] = arr
        elif arr.ndim in (1, 2):
            low[key] = arr.reshape(len(arr), -1)
        else:
            raise DatasetError(f"observation {key!r} has shape {arr.shape}: neither an image nor a vector")
    return images, low


class _Writer:
    """Writes episodes one by one into ``root`` (a fresh folder) and the metadata on ``finish``."""

    def __init__(self, root: Path, cfg: LeRobotWriteConfig, action_space: ActionSpace):
        if cfg.fps is None or cfg.fps <= 0:
            raise DatasetError(f"fps must be a positive number of frames per second, got {cfg.fps}")
        if cfg.vcodec not in CODECS:
            raise DatasetError(f"vcodec must be one of {sorted(CODECS)}, got {cfg.vcodec!r}")
        if (cfg.episodes_per_file is not None and cfg.episodes_per_file < 1) or cfg.chunks_size < 1:
            raise DatasetError(f"episodes_per_file ({cfg.episodes_per_file}) and chunks_size ({cfg.chunks_size}) "
                               "must be at least 1")
        self.root, self.cfg, self.action_space = root, cfg, action_space
        self.features: dict[str, dict] | None = None
        self.state_keys: tuple[str, ...] = ()
        self.extra_keys: tuple[str, ...] = ()
        self.dims: dict[str, int] = {}  # low-dim key -> its dimension, fixed by the first episode
        self.videos: dict[str, _VideoSink] = {}
        self.data = _FileSeq(cfg.data_files_size_in_mb * MB, cfg.episodes_per_file, cfg.chunks_size)
        self.data_writer: pq.ParquetWriter | None = None
        self.tasks: dict[str, int] = {}
        self.rows: list[dict] = []
        self.stats: list[dict] = []
        self.frames = 0

    def _layout(self, images: dict, low: dict) -> None:
        """Fix the features from the first episode; every later one must match them."""
        wanted = self.cfg.state_keys
        if wanted is None:
            wanted = tuple(k for k in PROPRIO_KEYS if k in low)
        missing = [k for k in wanted if k not in low]
        if missing:
            raise DatasetError(f"state keys {missing} are not low-dim observations of the episodes "
                               f"(they have {sorted(low)})")
        self.state_keys = tuple(wanted)
        self.extra_keys = tuple(k for k in low if k not in self.state_keys)
        features: dict[str, dict] = {}
        for key, arr in images.items():
            if arr.shape[1] % 2 or arr.shape[2] % 2:
                raise DatasetError(f"image {key!r} is {arr.shape[1]}x{arr.shape[2]}: yuv420p video needs even "
                                   "height and width")
            features[IMAGE_PREFIX + key] = {"dtype": "video", "shape": list(arr.shape[1:]), "names": IMAGE_NAMES}
            self.videos[key] = _VideoSink(self.root, IMAGE_PREFIX + key, self.cfg, arr.shape[1:])
        self.dims = {key: arr.shape[1] for key, arr in low.items()}
        if self.state_keys:
            names = [f"{k}.{i}" for k in self.state_keys for i in range(low[k].shape[1])]
            if self.cfg.state_names is not None:
                if len(self.cfg.state_names) != len(names):
                    raise DatasetError(f"{len(self.cfg.state_names)} state names for the {len(names)} dimensions of "
                                       f"the state keys {list(self.state_keys)}")
                names = list(self.cfg.state_names)
            features[STATE] = {"dtype": "float32", "shape": [len(names)], "names": names}
        for key in self.extra_keys:
            dim = low[key].shape[1]
            features[OBS_PREFIX + key] = {"dtype": "float32", "shape": [dim],
                                          "names": [f"{key}.{i}" for i in range(dim)]}
        space = self.action_space
        features[ACTION] = {"dtype": "float32", "shape": [space.dim], "names": list(space.names),
                            PIVLA_ACTION_SPACE: space.to_dict()}
        features[REWARD] = {"dtype": "float32", "shape": [1], "names": None}
        features[DONE] = {"dtype": "bool", "shape": [1], "names": None}
        self.features = {**features, **INDEX_FEATURES}

    def _check(self, images: dict, low: dict) -> None:
        expected = set(self.videos) | set(self.state_keys) | set(self.extra_keys)
        if set(images) | set(low) != expected:
            raise DatasetError(f"episode observation keys {sorted(set(images) | set(low))} differ from the first "
                               f"episode's {sorted(expected)}: a LeRobot dataset has one set of features")
        for key, arr in images.items():
            if tuple(arr.shape[1:]) != self.videos[key].shape:
                raise DatasetError(f"image {key!r} is {arr.shape[1:]}, the first episode's is "
                                   f"{self.videos[key].shape}")
        for key, arr in low.items():
            if arr.shape[1] != self.dims[key]:
                raise DatasetError(f"observation {key!r} has {arr.shape[1]} dims, the first episode's has "
                                   f"{self.dims[key]}")

    def add(self, ep: Episode) -> None:
        if len(ep) == 0:
            raise DatasetError(f"episode {ep.instruction!r} has no steps")
        if ep.actions.shape[1] != self.action_space.dim:
            raise DatasetError(f"episode {ep.instruction!r} has {ep.actions.shape[1]}-D actions, the action space "
                               f"is {self.action_space.describe()}")
        images, low = _split_obs(ep)
        if self.features is None:
            self._layout(images, low)
        self._check(images, low)
        T, e = len(ep), len(self.rows)
        task_index = self.tasks.setdefault(ep.instruction, len(self.tasks))
        frame_index = np.arange(T, dtype=np.int64)
        columns: dict[str, np.ndarray] = {}
        if self.state_keys:
            columns[STATE] = np.concatenate([low[k] for k in self.state_keys], axis=1).astype(np.float32)
        for key in self.extra_keys:
            columns[OBS_PREFIX + key] = low[key].astype(np.float32)
        columns[ACTION] = ep.actions
        columns[REWARD] = ep.rewards.astype(np.float32)
        columns[DONE] = ep.dones.astype(bool)
        columns["timestamp"] = (frame_index / self.cfg.fps).astype(np.float32)
        columns["frame_index"] = frame_index
        columns["episode_index"] = np.full(T, e, np.int64)
        columns["index"] = np.arange(self.frames, self.frames + T, dtype=np.int64)
        columns["task_index"] = np.full(T, task_index, np.int64)
        table = pa.table({k: _fixed_list(v) if v.ndim == 2 else pa.array(v) for k, v in columns.items()})

        if self.data.full():
            self.data_writer.close()
            self.data_writer = None
            self.data.advance()
        if self.data_writer is None:
            path = self.root / DATA_PATH.format(chunk_index=self.data.chunk, file_index=self.data.file)
            path.parent.mkdir(parents=True, exist_ok=True)
            self.data_writer = pq.ParquetWriter(path, table.schema, compression="snappy")
        self.data_writer.write_table(table)
        self.data.size += table.nbytes
        self.data.episodes += 1

        row = {"episode_index": e, "tasks": [ep.instruction], "length": T,
               "data/chunk_index": self.data.chunk, "data/file_index": self.data.file,
               "dataset_from_index": self.frames, "dataset_to_index": self.frames + T}
        stats = {k: _vector_stats(v) for k, v in columns.items()}
        for key, frames in images.items():
            row.update(self.videos[key].add(frames))
            stats[IMAGE_PREFIX + key] = _image_stats(frames)
        row.update({f"stats/{k}/{s}": v.tolist() for k, st in stats.items() for s, v in st.items()})
        row.update({PIVLA_SUCCESS: bool(ep.success), PIVLA_SOURCE: ep.source, PIVLA_META: json.dumps(ep.meta)})
        self.rows.append(row)
        self.stats.append(stats)
        self.frames += T

    def close(self) -> None:
        """Close open files (also on error, before the temporary folder is removed)."""
        for sink in self.videos.values():
            sink.close()
        if self.data_writer is not None:
            self.data_writer.close()
            self.data_writer = None

    def finish(self) -> None:
        if not self.rows:
            raise DatasetError("refusing to write a LeRobot dataset with no episodes")
        self.close()
        for key, sink in self.videos.items():
            self.features[IMAGE_PREFIX + key]["info"] = _video_info(sink.first_path)
        self._write_episodes()
        tasks = pa.table({"task_index": pa.array(list(self.tasks.values()), pa.int64()),
                          "__index_level_0__": pa.array(list(self.tasks), pa.string())})
        pq.write_table(tasks.replace_schema_metadata({"pandas": json.dumps(_pandas_index_metadata())}),
                       self.root / TASKS_PATH)
        (self.root / STATS_PATH).write_text(json.dumps(_aggregate_stats(self.stats), indent=4))
        n = len(self.rows)
        info = {
            "codebase_version": CODEBASE_VERSION, "robot_type": self.cfg.robot_type,
            "total_episodes": n, "total_frames": self.frames, "total_tasks": len(self.tasks),
            "chunks_size": self.cfg.chunks_size, "data_files_size_in_mb": self.cfg.data_files_size_in_mb,
            "video_files_size_in_mb": self.cfg.video_files_size_in_mb, "fps": self.cfg.fps,
            "splits": {"train": f"0:{n}"}, "data_path": DATA_PATH,
            "video_path": VIDEO_PATH if self.videos else None, "features": self.features,
        }
        (self.root / INFO_PATH).write_text(json.dumps(info, indent=4, ensure_ascii=False))

    def _write_episodes(self) -> None:
        """meta/episodes files, split like the data files once one would exceed the data size limit."""
        seq = _FileSeq(self.cfg.data_files_size_in_mb * MB, None, self.cfg.chunks_size)
        groups: list[list[dict]] = []
        for row in self.rows:
            size = len(json.dumps(row))
            if not groups or seq.full():
                if groups:
                    seq.advance()
                groups.append([])
            row["meta/episodes/chunk_index"], row["meta/episodes/file_index"] = seq.chunk, seq.file
            groups[-1].append(row)
            seq.size += size
            seq.episodes += 1
        for group in groups:
            first = group[0]
            path = self.root / EPISODES_PATH.format(chunk_index=first["meta/episodes/chunk_index"],
                                                    file_index=first["meta/episodes/file_index"])
            path.parent.mkdir(parents=True, exist_ok=True)
            pq.write_table(pa.Table.from_pylist(group), path, compression="snappy")


def _pandas_index_metadata() -> dict:
    """The pandas schema metadata that makes ``pd.read_parquet`` (how lerobot loads meta/tasks.parquet)
    restore the task strings as the DataFrame index."""
    return {
        "index_columns": ["__index_level_0__"],
        "column_indexes": [{"name": None, "field_name": None, "pandas_type": "unicode", "numpy_type": "object",
                            "metadata": {"encoding": "UTF-8"}}],
        "columns": [
            {"name": "task_index", "field_name": "task_index", "pandas_type": "int64", "numpy_type": "int64",
             "metadata": None},
            {"name": None, "field_name": "__index_level_0__", "pandas_type": "unicode", "numpy_type": "object",
             "metadata": None},
        ],
        "creator": {"library": "pyarrow", "version": pa.__version__},
        "pandas_version": "2.2.3",
    }


def write_lerobot(root: str | Path, episodes: Iterable[Episode], cfg: LeRobotWriteConfig,
                  overwrite: bool = False, action_space: ActionSpace = EE_DELTA) -> Path:
    """Write ``episodes`` (consumed one at a time, so a generator streams) as a LeRobot v3.0 dataset at
    ``root``, their actions meaning ``action_space``. The dataset is built in a temporary folder and renamed
    into place: never half a dataset."""
    root = Path(root)
    _check_destination(root, overwrite)
    with atomic_dir(root) as tmp:
        writer = _Writer(tmp, cfg, action_space)
        try:
            for ep in episodes:
                writer.add(ep)
            writer.finish()
        finally:
            writer.close()
    return root


# --------------------------------------------------------------------------------------------- reading


def _read_json(root: Path, rel: str) -> dict:
    path = root / rel
    if not path.is_file():
        raise DatasetError(f"{root}: missing {rel}")
    try:
        value = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DatasetError(f"{path}: not valid JSON ({e})") from e
    if not isinstance(value, dict):
        raise DatasetError(f"{path}: expected a JSON object, got {type(value).__name__}")
    return value


def _read_table(path: Path, columns: list[str] | None = None) -> pa.Table:
    try:
        return pq.read_table(path, columns=columns)
    except (pa.ArrowException, OSError) as e:
        raise DatasetError(f"{path}: truncated or corrupt parquet file ({e})") from e


def read_info(root: str | Path) -> dict:
    """meta/info.json, checked for the fields pivla relies on and for codebase_version v3.0."""
    root = Path(root)
    info = _read_json(root, INFO_PATH)
    version = info.get("codebase_version")
    if version != CODEBASE_VERSION:
        raise DatasetError(f"{root}: unsupported LeRobot codebase_version {version!r}; pivla reads "
                           f"{CODEBASE_VERSION} (convert older datasets with lerobot's convert_dataset_v21_to_v30)")
    for key in ("fps", "features", "data_path"):
        if key not in info:
            raise DatasetError(f"{root}/{INFO_PATH}: missing key {key!r}")
    for name, ft in info["features"].items():
        if not isinstance(ft, dict) or "dtype" not in ft or "shape" not in ft:
            raise DatasetError(f"{root}/{INFO_PATH}: feature {name!r} lacks dtype or shape")
    if any(ft["dtype"] == "video" for ft in info["features"].values()) and not info.get("video_path"):
        raise DatasetError(f"{root}/{INFO_PATH}: video features but no video_path")
    return info


def _read_tasks(root: Path) -> dict[int, str]:
    if not (root / TASKS_PATH).is_file():
        raise DatasetError(f"{root}: missing {TASKS_PATH}")
    table = _read_table(root / TASKS_PATH)
    text = next((c for c in ("__index_level_0__", "task") if c in table.column_names), None)
    if "task_index" not in table.column_names or text is None:
        raise DatasetError(f"{root / TASKS_PATH}: needs columns task_index and the task string "
                           f"(__index_level_0__), has {table.column_names}")
    return dict(zip(table["task_index"].to_pylist(), table[text].to_pylist()))


def _read_episode_rows(root: Path) -> list[dict]:
    files = sorted((root / EPISODES_DIR).glob("*/*.parquet"))
    if not files:
        raise DatasetError(f"{root}: missing {EPISODES_DIR}/chunk-XXX/file-XXX.parquet")
    rows = []
    for path in files:
        try:
            names = pq.read_schema(path).names
        except (pa.ArrowException, OSError) as e:
            raise DatasetError(f"{path}: truncated or corrupt parquet file ({e})") from e
        rows += _read_table(path, [n for n in names if not n.startswith("stats/")]).to_pylist()
    rows.sort(key=lambda r: r.get("episode_index", -1))
    for i, row in enumerate(rows):
        if row.get("episode_index") != i:
            raise DatasetError(f"{root}/{EPISODES_DIR}: episode indices are not 0..{len(rows) - 1} "
                               f"(found {row.get('episode_index')} at position {i})")
    return rows


def _state_split(names, dim: int) -> list[tuple[str, int, int]] | None:
    """[(key, start, stop)] when the state's names are ``KEY.0, KEY.1, ...`` runs (as pivla writes them)."""
    if not isinstance(names, list) or len(names) != dim:
        return None
    parts = []
    for i, name in enumerate(names):
        m = re.fullmatch(r"(.+)\.(\d+)", str(name))
        if m is None:
            return None
        key, j = m.group(1), int(m.group(2))
        if j == 0:
            if any(p[0] == key for p in parts):
                return None
            parts.append([key, i, i + 1])
        elif parts and parts[-1][0] == key and j == parts[-1][2] - parts[-1][1]:
            parts[-1][2] = i + 1
        else:
            return None
    return [tuple(p) for p in parts]


def lerobot_action_space(root: str | Path, info: dict | None = None) -> ActionSpace:
    """What a LeRobot dataset's actions mean: the action space pivla recorded in the ``action`` feature, else
    one inferred from the feature's ``names`` (a list, or lerobot's older ``{"motors": [...]}``) and shape."""
    info = read_info(root) if info is None else info
    ft = info["features"].get(ACTION)
    if ft is None:
        raise DatasetError(f"{root}/{INFO_PATH}: missing feature {ACTION!r}")
    shape = [int(s) for s in ft["shape"]]
    if len(shape) != 1 or shape[0] < 1:
        raise DatasetError(f"{root}: feature 'action' has shape {shape}; pivla needs one row of D numbers")
    names = ft.get("names")
    if isinstance(names, dict) and len(names) == 1:
        names = next(iter(names.values()))
    if names is None:
        names = [f"{ACTION}.{i}" for i in range(shape[0])]
    if not isinstance(names, list) or len(names) != shape[0]:
        raise DatasetError(f"{root}: feature 'action' names {names} do not name its {shape[0]} dimensions")
    try:
        space = (ActionSpace.from_dict(ft[PIVLA_ACTION_SPACE]) if PIVLA_ACTION_SPACE in ft
                 else infer_action_space(names))
    except ValueError as e:
        raise DatasetError(f"{root}: feature 'action': {e}") from None
    if list(space.names) != [str(n) for n in names]:
        raise DatasetError(f"{root}: feature 'action' {PIVLA_ACTION_SPACE} names {list(space.names)} differ from "
                           f"its names {names}")
    return space


def lerobot_layout(root: str | Path) -> DatasetLayout:
    """A LeRobot dataset's cameras (its image and video features, in info.json's order), proprioception
    (``observation.state``, split as pivla wrote it) and action space, from meta/info.json alone."""
    info = read_info(root)
    plan = _plan(Path(root), info["features"], None)
    vectors = {key: stop - start for key, (_, start, stop) in plan.vectors.items()}
    state = [k for k, (feature, _, _) in plan.vectors.items() if feature == STATE]
    return DatasetLayout(cameras=(*plan.videos, *plan.images), proprio=tuple(state), vectors=vectors,
                         action_space=lerobot_action_space(root, info))


def _obs_name(feature: str) -> str:
    for prefix in (IMAGE_PREFIX, OBS_PREFIX):
        if feature.startswith(prefix):
            return feature[len(prefix):]
    return feature


def _column(table: pa.Table, name: str, ft: dict, path: Path) -> np.ndarray:
    """A data column as a (rows,) or (rows, D) array, checked against its declared shape."""
    if name not in table.column_names:
        raise DatasetError(f"{path}: missing column {name!r} declared in {INFO_PATH}")
    col = table[name].combine_chunks()
    shape = [int(s) for s in ft["shape"]]
    if pa.types.is_list(col.type) or pa.types.is_fixed_size_list(col.type) or pa.types.is_large_list(col.type):
        flat = col.flatten().to_numpy(zero_copy_only=False)
        width = len(flat) // max(len(col), 1)
        if len(flat) != width * len(col) or [width] != shape:
            raise DatasetError(f"{path}: column {name!r} has {width if len(flat) == width * len(col) else 'ragged'}"
                               f" values per row, {INFO_PATH} declares shape {shape}")
        return flat.reshape(len(col), width)
    if shape != [1]:
        raise DatasetError(f"{path}: column {name!r} holds scalars, {INFO_PATH} declares shape {shape}")
    return col.to_numpy(zero_copy_only=False)


class _VideoReader:
    """Sequential decoding of one camera's mp4 files: episodes come in file order, so every file is decoded
    once, one episode in memory at a time."""

    def __init__(self, root: Path, template: str, feature: str, ft: dict, fps: int):
        self.root, self.template, self.feature, self.fps = root, template, feature, fps
        self.shape = tuple(int(s) for s in ft["shape"])
        self.path: Path | None = None
        self.container = self.frames = self.pending = None
        self.position = -math.inf  # seconds of the last frame handed out

    def close(self) -> None:
        if self.container is not None:
            self.container.close()
            self.container = self.frames = self.pending = None

    def _open(self, path: Path) -> None:
        self.close()
        if not path.is_file():
            raise DatasetError(f"missing video file {path}")
        try:
            self.container = av.open(str(path))
            stream = self.container.streams.video[0]
        except (av.FFmpegError, IndexError) as e:
            raise DatasetError(f"{path}: unreadable video ({e})") from e
        stream.thread_type = "AUTO"
        self.path, self.frames, self.position = path, self.container.decode(stream), -math.inf

    def episode(self, e: int, chunk: int, file: int, start_s: float, length: int) -> np.ndarray:
        path = self.root / self.template.format(video_key=self.feature, chunk_index=chunk, file_index=file)
        if path != self.path or start_s < self.position or self.container is None:
            self._open(path)
        out = np.empty((length, *self.shape), np.uint8)
        found = np.zeros(length, bool)
        while True:
            frame, self.pending = self.pending, None
            if frame is None:
                try:
                    frame = next(self.frames, None)
                except av.FFmpegError as err:
                    raise DatasetError(f"{path}: unreadable video ({err})") from err
            if frame is None:
                break
            if frame.time is None:
                raise DatasetError(f"{path}: video frame without a timestamp")
            i = round((frame.time - start_s) * self.fps)
            if i >= length:
                self.pending = frame
                break
            self.position = frame.time
            if i < 0:
                continue
            image = frame.to_ndarray(format="rgb24")
            if image.shape != self.shape:
                raise DatasetError(f"{path}: frames are {image.shape}, {INFO_PATH} declares {self.shape}")
            out[i], found[i] = image, True
        if not found.all():
            raise DatasetError(f"{path}: episode {e} needs {length} frames from {start_s:.3f} s, the video has "
                               f"{int(found.sum())} of them")
        return out


def _video_location(row: dict, feature: str) -> tuple[int, int, float]:
    prefix = f"videos/{feature}/"
    try:
        return (int(row[prefix + "chunk_index"]), int(row[prefix + "file_index"]),
                float(row[prefix + "from_timestamp"]))
    except (KeyError, TypeError) as err:
        raise DatasetError(f"meta/episodes row of episode {row['episode_index']} lacks {err.args[0]!r}") from None


def _decode_image(value: dict | None, feature: str, shape: tuple) -> np.ndarray:
    """One image of an ``image``-dtype feature (encoded bytes in the parquet row)."""
    data = value.get("bytes") if isinstance(value, dict) else None
    if not data:
        raise DatasetError(f"feature {feature!r}: a row holds no image bytes")
    try:
        with av.open(io.BytesIO(data)) as container:
            image = next(container.decode(video=0)).to_ndarray(format="rgb24")
    except (av.FFmpegError, StopIteration) as err:
        raise DatasetError(f"feature {feature!r}: undecodable image ({err})") from err
    if image.shape != shape:
        raise DatasetError(f"feature {feature!r}: image is {image.shape}, {INFO_PATH} declares {shape}")
    return image


@dataclass
class _Plan:
    """Which features feed which pivla observation keys."""

    videos: dict[str, str] = field(default_factory=dict)  # key -> video feature
    images: dict[str, str] = field(default_factory=dict)  # key -> image feature (encoded bytes in parquet)
    vectors: dict[str, tuple[str, int, int]] = field(default_factory=dict)  # key -> (feature, start, stop)


def _plan(root: Path, features: dict[str, dict], obs_keys: tuple[str, ...] | None) -> _Plan:
    plan = _Plan()
    for name, ft in features.items():
        shape = [int(s) for s in ft["shape"]]
        if ft["dtype"] == "video":
            plan.videos[_obs_name(name)] = name
        elif ft["dtype"] == "image":
            plan.images[_obs_name(name)] = name
        elif name == STATE:
            split = _state_split(ft.get("names"), shape[0])
            for key, start, stop in split or [(STATE_KEY, 0, shape[0])]:
                plan.vectors[key] = (name, start, stop)
        elif name.startswith(OBS_PREFIX) and ft["dtype"] != "string" and len(shape) == 1:
            plan.vectors[_obs_name(name)] = (name, 0, shape[0])
    if obs_keys is not None:
        available = [*plan.videos, *plan.images, *plan.vectors]
        missing = [k for k in obs_keys if k not in available]
        if missing:
            raise DatasetError(f"{root}: missing feature for observation key(s) {missing} (the dataset has "
                               f"{available})")
        plan = _Plan({k: v for k, v in plan.videos.items() if k in obs_keys},
                     {k: v for k, v in plan.images.items() if k in obs_keys},
                     {k: v for k, v in plan.vectors.items() if k in obs_keys})
    return plan


class _DataFiles:
    """Data parquet files read one at a time, in the order episodes refer to them."""

    def __init__(self, root: Path, template: str, features: dict[str, dict], names: list[str]):
        self.root, self.template = root, template
        self.columns = {n: features[n] for n in names}
        self.current: tuple[int, int] | None = None
        self.table: dict[str, np.ndarray] = {}
        self.ranges: dict[int, tuple[int, int]] = {}
        self.path: Path | None = None

    def episode(self, e: int, chunk: int, file: int, length: int) -> dict[str, np.ndarray]:
        if self.current != (chunk, file):
            self._load(self.root / self.template.format(chunk_index=chunk, file_index=file))
            self.current = (chunk, file)
        start, stop = self.ranges.get(e, (0, 0))
        if stop - start != length:
            raise DatasetError(f"{self.path}: episode {e} has {stop - start} frames, meta/episodes says {length}")
        return {k: v[start:stop] for k, v in self.table.items()}

    def _load(self, path: Path) -> None:
        if not path.is_file():
            raise DatasetError(f"missing data file {path}")
        table = _read_table(path)
        self.path, self.table = path, {}
        for name, ft in self.columns.items():
            if ft["dtype"] == "image":
                if name not in table.column_names:
                    raise DatasetError(f"{path}: missing column {name!r} declared in {INFO_PATH}")
                values = np.empty(table.num_rows, object)
                values[:] = table[name].to_pylist()
                self.table[name] = values
            else:
                self.table[name] = _column(table, name, ft, path)
        order = np.lexsort((self.table["frame_index"], self.table["episode_index"]))
        self.table = {k: v[order] for k, v in self.table.items()}
        episodes = self.table["episode_index"]
        starts = np.flatnonzero(np.r_[True, episodes[1:] != episodes[:-1]]) if len(episodes) else np.array([], int)
        stops = np.r_[starts[1:], len(episodes)]
        self.ranges = {int(episodes[s]): (int(s), int(t)) for s, t in zip(starts, stops)}


def iter_lerobot(root: str | Path, obs_keys: tuple[str, ...] | None = None,
                 episodes: Iterable[int] | None = None) -> Iterator[Episode]:
    """The episodes of a LeRobot v3.0 dataset in episode order, decoded one at a time (each data and video
    file is read once). ``obs_keys`` limits (and requires) the observation keys, as in ``read_episodes``;
    ``episodes`` limits the episodes to those indices (an index the dataset lacks is an error)."""
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root}: dataset directory does not exist")
    info = read_info(root)
    features, fps = info["features"], int(info["fps"])
    for name in (ACTION, "episode_index", "frame_index", "task_index"):
        if name not in features:
            raise DatasetError(f"{root}/{INFO_PATH}: missing feature {name!r}")
    lerobot_action_space(root, info)
    tasks = _read_tasks(root)
    rows = _read_episode_rows(root)
    if episodes is not None:
        wanted = sorted(set(int(e) for e in episodes))
        missing = [e for e in wanted if not 0 <= e < len(rows)]
        if missing:
            raise DatasetError(f"{root} has episodes 0..{len(rows) - 1}, not {missing}")
        rows = [rows[e] for e in wanted]
    plan = _plan(root, features, obs_keys)
    names = [ACTION, "episode_index", "frame_index", "task_index",
             *(n for n in (REWARD, DONE, SUCCESS) if n in features),
             *dict.fromkeys(f for f, _, _ in plan.vectors.values()), *plan.images.values()]
    data = _DataFiles(root, info["data_path"], features, names)
    videos = {key: _VideoReader(root, info["video_path"], feature, features[feature], fps)
              for key, feature in plan.videos.items()}
    try:
        for row in rows:
            yield _episode(root, row, data, videos, plan, features, tasks)
    finally:
        for reader in videos.values():
            reader.close()


def _episode(root: Path, row: dict, data: _DataFiles, videos: dict[str, _VideoReader], plan: _Plan,
             features: dict, tasks: dict[int, str]) -> Episode:
    e = row["episode_index"]
    try:
        length = int(row["length"])
        if length < 1:
            raise DatasetError(f"{root}/{EPISODES_DIR}: episode {e} has length {length}; an episode needs a frame")
        cols = data.episode(e, int(row["data/chunk_index"]), int(row["data/file_index"]), length)
    except (KeyError, TypeError) as err:
        raise DatasetError(f"{root}/{EPISODES_DIR}: episode {e} lacks {err.args[0]!r}") from None
    obs: dict[str, np.ndarray] = {}
    for key, reader in videos.items():
        chunk, file, start = _video_location(row, reader.feature)
        obs[key] = reader.episode(e, chunk, file, start, length)
    for key, feature in plan.images.items():
        shape = tuple(int(s) for s in features[feature]["shape"])
        obs[key] = np.stack([_decode_image(v, feature, shape) for v in cols[feature]])
    for key, (feature, start, stop) in plan.vectors.items():
        obs[key] = np.ascontiguousarray(cols[feature][:, start:stop], np.float32)
    task = int(cols["task_index"][0])
    if task not in tasks:
        raise DatasetError(f"{root}: episode {e} uses task_index {task}, absent from {TASKS_PATH}")
    if row.get(PIVLA_SUCCESS) is not None:
        success = bool(row[PIVLA_SUCCESS])
    else:
        success = bool(cols[SUCCESS].any()) if SUCCESS in cols else True
    try:
        return Episode(
            actions=cols[ACTION], obs=obs, instruction=tasks[task],
            rewards=cols[REWARD].astype(np.float32) if REWARD in cols else None,
            dones=cols[DONE].astype(np.uint8) if DONE in cols else None,
            success=success, source=row.get(PIVLA_SOURCE) or "expert",
            meta=json.loads(row[PIVLA_META]) if row.get(PIVLA_META) else {},
        )
    except (DatasetError, json.JSONDecodeError) as err:
        raise DatasetError(f"{root}: episode {e}: {err}") from err


def read_lerobot(root: str | Path, obs_keys: tuple[str, ...] | None = None) -> list[Episode]:
    """All episodes of a LeRobot v3.0 dataset, in memory like ``read_dataset`` holds HDF5 episodes."""
    return list(iter_lerobot(root, obs_keys))


# ------------------------------------------------------------------------------------------ conversion


def is_lerobot(path: str | Path) -> bool:
    """A folder with ``meta/`` is a LeRobot dataset (LeRobot keeps its metadata there)."""
    return (Path(path) / "meta").is_dir()


def detect_format(path: str | Path) -> Literal["hdf5", "lerobot"]:
    """``lerobot`` for a folder with ``meta/`` (LeRobot keeps its metadata there), ``hdf5`` for a ``.hdf5``
    file or a folder of them."""
    path = Path(path)
    if is_lerobot(path):
        return "lerobot"
    try:
        dataset_files(path)
    except DatasetError:
        raise DatasetError(f"{path}: neither a LeRobot dataset (meta/info.json) nor .hdf5 episode files") from None
    return "hdf5"


def _hdf5_fps(files: list[Path]) -> int | None:
    """The control rate recorded in the files' ``env_args`` (pivla's ``control_hz``, LIBERO's
    ``env_kwargs.control_freq``), if any."""
    rates = set()
    for path in files:
        env = read_env_meta(path)
        rate = env.get("control_hz") or (env.get("env_kwargs") or {}).get("control_freq")
        if rate:
            rates.add(round(float(rate)))
    if len(rates) > 1:
        raise DatasetError(f"the files record different control rates {sorted(rates)} Hz: give fps")
    return rates.pop() if rates else None


def _check_destination(dst: Path, overwrite: bool, src: Path | None = None) -> None:
    if src is not None:
        a, b = src.resolve(), dst.resolve()
        if a == b or a in b.parents or b in a.parents:
            raise DatasetError(f"destination {dst} overlaps the source {src}")
    if dst.exists() and not overwrite and (not dst.is_dir() or any(dst.iterdir())):
        raise DatasetError(f"{dst} already exists (pass overwrite to replace it)")


def _slug(text: str) -> str:
    return re.sub(r"[^a-z0-9]+", "_", text.lower()).strip("_")[:80] or "task"


def write_hdf5(root: str | Path, episodes: Iterable[Episode], env_meta: dict, episodes_per_file: int = 50,
               overwrite: bool = False, action_space: ActionSpace = EE_DELTA) -> Path:
    """Write episodes as LIBERO-layout files, one per run of consecutive episodes of one task (at most
    ``episodes_per_file``), named ``<n>_<task>_demo.hdf5`` so their sorted order is the episode order."""
    root = Path(root)
    _check_destination(root, overwrite)
    if episodes_per_file < 1:
        raise DatasetError(f"episodes_per_file must be at least 1, got {episodes_per_file}")
    with atomic_dir(root) as tmp:
        run: list[Episode] = []
        n = 0
        for ep in episodes:
            if run and (ep.instruction != run[0].instruction or len(run) >= episodes_per_file):
                write_episodes(tmp / f"{n:05d}_{_slug(run[0].instruction)}_demo.hdf5", run, env_meta, action_space)
                run, n = [], n + 1
            run.append(ep)
        if not run:
            raise DatasetError("refusing to write a dataset with no episodes")
        write_episodes(tmp / f"{n:05d}_{_slug(run[0].instruction)}_demo.hdf5", run, env_meta, action_space)
    return root


@dataclass
class ConvertConfig:
    """Convert a dataset between pivla's HDF5 layout and LeRobot v3.0 (the source format is detected)."""

    src: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="SRC")]
    """A LeRobot v3.0 folder, or a .hdf5 file or folder of them (the format is detected)."""
    dst: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="DST")]
    """The folder to create."""
    to: Literal["hdf5", "lerobot"]
    """The format to write."""
    overwrite: bool = False
    """Replace dst if it exists."""
    hdf5_episodes_per_file: int = 50
    """To hdf5: at most this many episodes per file (LIBERO has 50 per task)."""
    lerobot: LeRobotWriteConfig = field(default_factory=LeRobotWriteConfig)
    """To lerobot: how to write it."""


@dataclass
class ConvertResult:
    """What a conversion wrote."""

    dst: Path
    source_format: str
    episodes: int
    frames: int
    fps: int


def run_convert(cfg: ConvertConfig) -> ConvertResult:
    """Stream the episodes of ``cfg.src`` into ``cfg.dst`` in format ``cfg.to``: one source file (HDF5) or one
    episode (LeRobot) in memory at a time."""
    src, dst = Path(cfg.src), Path(cfg.dst)
    if cfg.to not in ("hdf5", "lerobot"):
        raise DatasetError(f"unknown target format {cfg.to!r} (hdf5 or lerobot)")
    source = detect_format(src)
    if source == cfg.to:
        raise DatasetError(f"{src} is already a {cfg.to} dataset")
    _check_destination(dst, cfg.overwrite, src)
    count = {"episodes": 0, "frames": 0}

    def counted(episodes: Iterable[Episode]) -> Iterator[Episode]:
        for ep in episodes:
            count["episodes"] += 1
            count["frames"] += len(ep)
            yield ep

    if cfg.to == "lerobot":
        files = dataset_files(src)
        fps = cfg.lerobot.fps or _hdf5_fps(files)
        if fps is None:
            raise DatasetError(f"{src}: the files record no control rate (env_args control_hz): give fps")
        write_lerobot(dst, counted(ep for path in files for ep in read_episodes(path)),
                      replace(cfg.lerobot, fps=fps), overwrite=cfg.overwrite, action_space=hdf5_action_space(files))
    else:
        info = read_info(src)
        fps = int(info["fps"])
        env_meta = {"control_hz": fps, "robot_type": info.get("robot_type"), "converted_from": "LeRobot v3.0"}
        write_hdf5(dst, counted(iter_lerobot(src)), env_meta, cfg.hdf5_episodes_per_file, overwrite=cfg.overwrite,
                   action_space=lerobot_action_space(src, info))
    return ConvertResult(dst=dst, source_format=source, episodes=count["episodes"], frames=count["frames"], fps=fps)


def convert(src: str | Path, dst: str | Path, to: Literal["hdf5", "lerobot"], **options) -> ConvertResult:
    """``run_convert`` with keyword options: ``overwrite``, ``hdf5_episodes_per_file``, and the fields of
    :class:`LeRobotWriteConfig` (``fps``, ``vcodec``, ``crf``, ``episodes_per_file``...)."""
    top = {k: options.pop(k) for k in ("overwrite", "hdf5_episodes_per_file") if k in options}
    try:
        write = LeRobotWriteConfig(**options)
    except TypeError as e:
        raise DatasetError(f"unknown conversion option: {e}") from None
    return run_convert(ConvertConfig(src=str(src), dst=str(dst), to=to, lerobot=write, **top))
