"""Reading a LeRobot v3.0 dataset with pyarrow and PyAV: its metadata, action space and layout, and its
episodes one at a time (the layout and how it maps to pivla's episodes: :mod:`pivla.data.lerobot`)."""

from __future__ import annotations

import io
import json
import math
import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import av
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from pivla.data.action_space import ActionSpace, infer_action_space
from pivla.data.episode import STATE_KEY, DatasetError, DatasetLayout, Episode
from pivla.data.lerobot.spec import (
    ACTION,
    CODEBASE_VERSION,
    DONE,
    EPISODES_DIR,
    IMAGE_PREFIX,
    INFO_PATH,
    OBS_PREFIX,
    PIVLA_ACTION_SPACE,
    PIVLA_META,
    PIVLA_SOURCE,
    PIVLA_SUCCESS,
    REWARD,
    STATE,
    SUCCESS,
    TASKS_PATH,
)


def is_lerobot(path: str | Path) -> bool:
    """A folder with ``meta/`` is a LeRobot dataset (LeRobot keeps its metadata there)."""
    return (Path(path) / "meta").is_dir()


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
class _FeatureMap:
    """Which features feed which pivla observation keys."""

    videos: dict[str, str] = field(default_factory=dict)  # key -> video feature
    images: dict[str, str] = field(default_factory=dict)  # key -> image feature (encoded bytes in parquet)
    vectors: dict[str, tuple[str, int, int]] = field(default_factory=dict)  # key -> (feature, start, stop)


def _plan(root: Path, features: dict[str, dict], obs_keys: tuple[str, ...] | None) -> _FeatureMap:
    plan = _FeatureMap()
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
        plan = _FeatureMap({k: v for k, v in plan.videos.items() if k in obs_keys},
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


def _episode(root: Path, row: dict, data: _DataFiles, videos: dict[str, _VideoReader], plan: _FeatureMap,
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
