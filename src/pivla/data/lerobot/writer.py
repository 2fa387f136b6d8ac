"""Writing episodes as a LeRobot v3.0 dataset with pyarrow and PyAV (the layout: :mod:`pivla.data.lerobot`)."""

from __future__ import annotations

import contextlib
import json
import math
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Literal

import av
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from pivla.data.action_space import EE_DELTA, ActionSpace
from pivla.data.episode import PROPRIO_KEYS, DatasetError, Episode, check_destination
from pivla.data.lerobot.spec import (
    ACTION,
    CODEBASE_VERSION,
    DATA_PATH,
    DONE,
    EPISODES_PATH,
    IMAGE_NAMES,
    IMAGE_PREFIX,
    INDEX_FEATURES,
    INFO_PATH,
    OBS_PREFIX,
    PIVLA_ACTION_SPACE,
    PIVLA_META,
    PIVLA_SOURCE,
    PIVLA_SUCCESS,
    QUANTILES,
    REWARD,
    STATE,
    STATS_PATH,
    TASKS_PATH,
    VIDEO_PATH,
)
from pivla.io import atomic_dir

CODECS = {"libx264": {}, "libsvtav1": {"preset": "12"}}  # per-codec extra options (lerobot's SVT preset)
MB = 1024 * 1024


def _threads() -> set[int]:
    """This process's thread ids (Linux; elsewhere none are listed)."""
    tasks = Path("/proc/self/task")
    return {int(t.name) for t in tasks.iterdir()} if tasks.is_dir() else set()


@contextlib.contextmanager
def _scheduling_kept() -> Iterator[None]:
    """On exit, the calling thread and every thread started in the block scheduled as the caller was on entry."""
    if not hasattr(os, "sched_getscheduler"):  # macOS: no per-thread policy to lose
        yield
        return
    policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    before = _threads()
    try:
        yield
    finally:
        for tid in (0, *(_threads() - before)):
            try:
                if (os.sched_getscheduler(tid), os.sched_getparam(tid)) != (policy, param):
                    os.sched_setscheduler(tid, policy, param)
            except ProcessLookupError:  # a thread that has ended since
                pass


def open_encoder(stream: av.video.stream.VideoStream) -> None:
    """Open ``stream``'s encoder, every thread scheduled as the caller is. SVT-AV1 (libsvtav1), run as root, moves
    the thread that opens it and the threads it starts (37 for one 64-px stream on 2 cores) to SCHED_FIFO priority
    99: every process started from the caller later would inherit it, and a thread or process busy at that priority
    starves the others on its core (a robot's control loop, a policy server) for as long as it runs."""
    with _scheduling_kept():
        stream.codec_context.open()


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
        open_encoder(self.stream)

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
    check_destination(root, overwrite)
    with atomic_dir(root) as tmp:
        writer = _Writer(tmp, cfg, action_space)
        try:
            for ep in episodes:
                writer.add(ep)
            writer.finish()
        finally:
            writer.close()
    return root
