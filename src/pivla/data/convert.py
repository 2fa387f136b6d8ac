"""``pivla data convert``: a dataset from pivla's HDF5 layout to LeRobot v3.0 or back, streamed one source
file (HDF5) or one episode (LeRobot) at a time."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Annotated, Literal

import tyro

from pivla.data.episode import DatasetError, Episode, check_destination
from pivla.data.hdf5 import dataset_files, hdf5_action_space, hdf5_fps, read_episodes, write_hdf5
from pivla.data.lerobot.reader import iter_lerobot, lerobot_action_space, read_info
from pivla.data.lerobot.writer import LeRobotWriteConfig, write_lerobot
from pivla.data.read import detect_format


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
    check_destination(dst, cfg.overwrite, src)
    count = {"episodes": 0, "frames": 0}

    def counted(episodes: Iterable[Episode]) -> Iterator[Episode]:
        for ep in episodes:
            count["episodes"] += 1
            count["frames"] += len(ep)
            yield ep

    if cfg.to == "lerobot":
        files = dataset_files(src)
        fps = cfg.lerobot.fps or hdf5_fps(files)
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
