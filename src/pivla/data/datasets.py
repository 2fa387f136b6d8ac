"""Reading a dataset directory whatever its format: pivla's LIBERO-layout HDF5 files (``pivla.data.format``) or
a LeRobot v3.0 dataset (``pivla.data.lerobot``, detected by its ``meta/`` folder)."""

from __future__ import annotations

from pathlib import Path

from pivla.data.format import Episode, dataset_files, read_episodes
from pivla.data.lerobot import read_lerobot


def read_dataset(root: str | Path, obs_keys: tuple[str, ...] | None = None) -> list[Episode]:
    """All episodes below ``root``: of every HDF5 file in file order then demo order, or of a LeRobot v3.0
    dataset in episode order."""
    if (Path(root) / "meta").is_dir():
        return read_lerobot(root, obs_keys)
    episodes: list[Episode] = []
    for path in dataset_files(root):
        episodes.extend(read_episodes(path, obs_keys))
    return episodes
