"""A LeRobot v3.0 dataset that grows one episode at a time and is complete after each (what recording needs).

``write_lerobot`` builds a whole dataset in a temporary folder and renames it into place. A recording cannot
wait for its end: ``LeRobotAppender.add`` writes one episode into data and video files of its own, closes
and syncs them, then rewrites the metadata (tasks, stats, the episodes table, info.json last), each file
written beside its place and renamed over it. After every ``add`` the folder reads as a dataset of the
episodes added so far; a crash while an episode is being written leaves files that no metadata names, and
the next appender writes over them. An existing dataset is continued (``resume``): its features, fps and
action space must be those of the new episodes.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from pivla.data.action_space import ActionSpace
from pivla.data.episode import DatasetError, Episode
from pivla.data.lerobot.reader import _read_tasks, _state_split, lerobot_action_space, read_info
from pivla.data.lerobot.spec import (
    DATA_PATH,
    EPISODES_DIR,
    IMAGE_PREFIX,
    INFO_PATH,
    OBS_PREFIX,
    STATE,
    STATS_PATH,
    TASKS_PATH,
    VIDEO_PATH,
)
from pivla.data.lerobot.writer import LeRobotWriteConfig, _VideoSink, _Writer

STAGING = ".pivla-commit"  # where the next metadata is written before it is renamed into meta/


def _fsync(path: Path) -> None:
    with open(path, "rb") as f:
        os.fsync(f.fileno())


class _AppendingWriter(_Writer):
    """``_Writer`` whose episodes each get files of their own, with the metadata written after every one."""

    def commit(self) -> None:
        self.close()
        for path in self._episode_files():
            _fsync(path)
        for sink in self.videos.values():  # the next episode opens new files instead of reopening these
            if sink.seq.episodes:
                sink.seq.advance()
        if self.data.episodes:
            self.data.advance()
        real, staging = self.root, self.root / STAGING
        shutil.rmtree(staging, ignore_errors=True)
        (staging / "meta").mkdir(parents=True)
        self.root = staging
        try:
            self.finish()
        finally:
            self.root = real
        staged = [staging / TASKS_PATH, staging / STATS_PATH,
                  *sorted((staging / EPISODES_DIR).glob("*/*.parquet")), staging / INFO_PATH]
        for path in staged:  # info.json last: until it names the new totals, readers see the old dataset
            _fsync(path)
            target = real / path.relative_to(staging)
            target.parent.mkdir(parents=True, exist_ok=True)
            os.replace(path, target)
        shutil.rmtree(staging, ignore_errors=True)

    def _episode_files(self) -> list[Path]:
        row = self.rows[-1]
        files = [self.root / DATA_PATH.format(chunk_index=row["data/chunk_index"], file_index=row["data/file_index"])]
        for sink in self.videos.values():
            prefix = f"videos/{sink.feature}/"
            files.append(self.root / VIDEO_PATH.format(video_key=sink.feature, chunk_index=row[prefix + "chunk_index"],
                                                       file_index=row[prefix + "file_index"]))
        return files


def _stats_of(row: dict) -> dict[str, dict[str, np.ndarray]]:
    """An episode's statistics from its meta/episodes row (``stats/<feature>/<stat>`` columns)."""
    out: dict[str, dict[str, np.ndarray]] = {}
    for key, value in row.items():
        if key.startswith("stats/"):
            feature, stat = key[len("stats/"):].rsplit("/", 1)
            out.setdefault(feature, {})[stat] = np.asarray(value, np.float64)
    return out


def _resume(root: Path, cfg: LeRobotWriteConfig, space: ActionSpace) -> _AppendingWriter:
    """An appending writer positioned after the episodes of the dataset at ``root``."""
    info = read_info(root)
    theirs = lerobot_action_space(root, info)
    if theirs.names != space.names:
        raise DatasetError(f"{root} records actions {theirs.describe()}; the new episodes' are {space.describe()}")
    if cfg.fps is not None and int(cfg.fps) != int(info["fps"]):
        raise DatasetError(f"{root} is recorded at {info['fps']} fps, not {cfg.fps}")
    cfg.fps = int(info["fps"])
    cfg.robot_type = cfg.robot_type or info.get("robot_type")
    writer = _AppendingWriter(root, cfg, space)
    rows = []
    for path in sorted((root / EPISODES_DIR).glob("*/*.parquet")):
        rows += pq.read_table(path).to_pylist()
    rows.sort(key=lambda r: r["episode_index"])
    if [r["episode_index"] for r in rows] != list(range(len(rows))) or not rows:
        raise DatasetError(f"{root}/{EPISODES_DIR}: cannot continue a dataset whose episodes are not 0..N-1")
    features = info["features"]
    writer.features = features
    state = features.get(STATE)
    if state is not None:
        split = _state_split(state.get("names"), int(state["shape"][0]))
        if cfg.state_keys is not None:
            writer.state_keys = tuple(cfg.state_keys)
        elif split is not None:
            writer.state_keys = tuple(k for k, _, _ in split)
        else:
            raise DatasetError(f"{root}: name the observation keys of its observation.state (state_keys) to "
                               "continue it")
        if split is not None and len(split) == len(writer.state_keys):
            writer.dims.update({k: stop - start for k, start, stop in split})
        elif len(writer.state_keys) == 1:
            writer.dims[writer.state_keys[0]] = int(state["shape"][0])
        else:
            raise DatasetError(f"{root}: observation.state does not split into the keys {list(writer.state_keys)}")
    extra = [n for n, ft in features.items() if n.startswith(OBS_PREFIX) and n != STATE
             and not n.startswith(IMAGE_PREFIX) and ft["dtype"] not in ("video", "image", "string")]
    writer.extra_keys = tuple(n[len(OBS_PREFIX):] for n in extra)
    writer.dims.update({n[len(OBS_PREFIX):]: int(features[n]["shape"][0]) for n in extra})
    last = rows[-1]
    for name, ft in features.items():
        if ft["dtype"] != "video":
            continue
        key = name[len(IMAGE_PREFIX):]
        sink = _VideoSink(root, name, cfg, tuple(int(s) for s in ft["shape"]))
        prefix = f"videos/{name}/"
        sink.first_path = root / VIDEO_PATH.format(video_key=name, chunk_index=rows[0][prefix + "chunk_index"],
                                                   file_index=rows[0][prefix + "file_index"])
        sink.seq.chunk, sink.seq.file = int(last[prefix + "chunk_index"]), int(last[prefix + "file_index"])
        sink.seq.advance()
        writer.videos[key] = sink
    writer.data.chunk, writer.data.file = int(last["data/chunk_index"]), int(last["data/file_index"])
    writer.data.advance()
    writer.tasks = {task: index for index, task in sorted(_read_tasks(root).items())}
    writer.rows = rows
    writer.stats = [_stats_of(r) for r in rows]
    writer.frames = int(last["dataset_to_index"])
    return writer


class LeRobotAppender:
    """Episodes appended to the LeRobot dataset at ``root``, each one committed (see the module doc).

    A missing or empty ``root`` starts a new dataset; a LeRobot dataset there is continued when ``resume``
    (its fps, features and action space must match), refused otherwise; anything else there is refused."""

    def __init__(self, root: str | Path, cfg: LeRobotWriteConfig, action_space: ActionSpace,
                 resume: bool = True) -> None:
        self.root = Path(root)
        self._failed = False
        cfg = LeRobotWriteConfig(**{**cfg.__dict__, "episodes_per_file": 1})
        if (self.root / INFO_PATH).is_file():
            if not resume:
                raise DatasetError(f"{self.root} already holds a LeRobot dataset; continue it or choose a new folder")
            self._writer = _resume(self.root, cfg, action_space)
        else:
            leftovers = [p.name for p in self.root.iterdir()] if self.root.is_dir() else []
            if [n for n in leftovers if n not in ("data", "videos", "meta", STAGING)]:
                raise DatasetError(f"{self.root} exists and is not a LeRobot dataset (it holds {sorted(leftovers)}); "
                                   "choose a new folder")
            for name in leftovers:  # an earlier recording that crashed before its first episode was kept
                shutil.rmtree(self.root / name)
            self.root.mkdir(parents=True, exist_ok=True)
            self._writer = _AppendingWriter(self.root, cfg, action_space)

    @property
    def episodes(self) -> int:
        """Episodes the dataset holds."""
        return len(self._writer.rows)

    @property
    def fps(self) -> int:
        return int(self._writer.cfg.fps)

    def add(self, episode: Episode) -> int:
        """Writes and commits one episode; returns its index."""
        if self._failed:
            raise DatasetError(f"{self.root}: an episode failed to be written; open the dataset again to continue it")
        try:
            self._writer.add(episode)
        except BaseException:
            self._failed = True
            self._writer.close()  # what this episode wrote is named by no metadata, and written over next time
            raise
        self._writer.commit()
        return self.episodes - 1

    def close(self) -> None:
        self._writer.close()
        shutil.rmtree(self.root / STAGING, ignore_errors=True)

    def __enter__(self) -> LeRobotAppender:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

