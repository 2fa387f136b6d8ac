"""Reading a dataset directory whatever its format, and telling which it is: pivla's LIBERO-layout HDF5 files
(``pivla.data.hdf5``) or a LeRobot v3.0 dataset (``pivla.data.lerobot``, detected by its ``meta/`` folder)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Literal

from pivla.data.episode import DatasetError, DatasetLayout, Episode
from pivla.data.hdf5 import dataset_files, hdf5_layout, iter_episodes
from pivla.data.lerobot.reader import is_lerobot, iter_lerobot, lerobot_layout


def dataset_layout(root: str | Path) -> DatasetLayout:
    """The cameras, proprioception and action space a dataset offers, read without its pictures."""
    return lerobot_layout(root) if is_lerobot(root) else hdf5_layout(root)


def iter_dataset(root: str | Path, obs_keys: tuple[str, ...] | None = None) -> Iterator[Episode]:
    """The episodes below ``root`` one at a time: of every HDF5 file in file order then demo order, or of a
    LeRobot v3.0 dataset in episode order. ``obs_keys`` limits (and requires) the observation keys loaded."""
    if is_lerobot(root):
        yield from iter_lerobot(root, obs_keys)
        return
    for path in dataset_files(root):
        yield from iter_episodes(path, obs_keys)


def read_dataset(root: str | Path, obs_keys: tuple[str, ...] | None = None) -> list[Episode]:
    """Every episode of ``iter_dataset``, in memory."""
    return list(iter_dataset(root, obs_keys))


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
