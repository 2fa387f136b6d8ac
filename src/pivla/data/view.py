"""One episode of a dataset, to look at (``pivla data view``).

With rerun-sdk installed (``pip install 'pivla[viz]'``) the episode is logged to Rerun: every camera as an
image stream and every action and state dimension as a scalar series on a ``frame`` timeline (seconds on a
``time`` one), shown in a spawned viewer or saved as an ``.rrd`` recording. Without it (or with
``viewer="files"``) two files: an MP4 of the cameras side by side at the dataset's fps, and a PNG plot of
the actions and the state over time (matplotlib, which comes with the extras that read LeRobot videos).
Both LeRobot v3.0 datasets and pivla's HDF5 ones are read.
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from pivla.data.action_space import ActionSpace
from pivla.data.episode import DatasetError, Episode
from pivla.data.hdf5 import dataset_files, hdf5_action_space, hdf5_fps, iter_episodes

Viewer = Literal["auto", "rerun", "files"]


@dataclass
class EpisodeView:
    episode: Episode
    index: int
    fps: int
    action_space: ActionSpace
    state_names: dict[str, list[str]] = field(default_factory=dict)  # vector key -> its dimension names


def _images(ep: Episode) -> dict[str, np.ndarray]:
    return {k: v for k, v in ep.obs.items() if v.ndim == 4 and v.shape[-1] == 3}


def _vectors(ep: Episode) -> dict[str, np.ndarray]:
    return {k: v.reshape(len(v), -1) for k, v in ep.obs.items() if v.ndim in (1, 2)}


def load_episode(root: str | Path, index: int) -> EpisodeView:
    """Episode ``index`` of the dataset at ``root`` with its fps, action space and state names."""
    from pivla.data.lerobot.reader import is_lerobot, iter_lerobot, lerobot_action_space, read_info
    from pivla.data.lerobot.spec import STATE

    root = Path(root)
    if is_lerobot(root):
        info = read_info(root)
        ep = next(iter_lerobot(root, episodes=[index]))
        names = {}
        state = info["features"].get(STATE, {}).get("names")
        if isinstance(state, list) and "state" in ep.obs and len(state) == ep.obs["state"].shape[-1]:
            names["state"] = [str(n) for n in state]
        return EpisodeView(ep, index, int(info["fps"]), lerobot_action_space(root, info), names)
    files = dataset_files(root)
    i = 0
    for path in files:
        for ep in iter_episodes(path):
            if i == index:
                return EpisodeView(ep, index, hdf5_fps(files) or 10, hdf5_action_space(files))
            i += 1
    raise DatasetError(f"{root} has episodes 0..{i - 1}, not {index}")


def _even(image: np.ndarray) -> np.ndarray:
    h, w = image.shape[:2]
    return np.pad(image, ((0, h % 2), (0, w % 2), (0, 0)))


def side_by_side(frames: list[np.ndarray]) -> np.ndarray:
    """Pictures of one instant next to each other, each scaled to the tallest one's height."""
    import cv2

    height = max(f.shape[0] for f in frames)
    scaled = [f if f.shape[0] == height else
              cv2.resize(f, (round(f.shape[1] * height / f.shape[0]), height), interpolation=cv2.INTER_NEAREST)
              for f in frames]
    return _even(np.concatenate(scaled, axis=1))


def write_video(view: EpisodeView, path: str | Path) -> Path:
    """The episode's cameras side by side as an H.264 MP4 at the dataset's fps."""
    from pivla.io import write_mp4

    images = _images(view.episode)
    if not images:
        raise DatasetError(f"episode {view.index} has no camera to put in a video")
    frames = np.stack([side_by_side([v[t] for v in images.values()]) for t in range(len(view.episode))])
    write_mp4(path, frames, view.fps)
    return Path(path)


def write_plot(view: EpisodeView, path: str | Path) -> Path:
    """A PNG of the actions and each state vector over time (seconds), one panel each, named dimensions."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    ep = view.episode
    t = np.arange(len(ep)) / view.fps
    panels = [("action", ep.actions, list(view.action_space.names))]
    for key, values in _vectors(ep).items():
        panels.append((key, values, view.state_names.get(key) or [f"{key}.{i}" for i in range(values.shape[1])]))
    fig = Figure(figsize=(10, 2.6 * len(panels)), layout="constrained")
    for ax, (title, values, names) in zip(fig.subplots(len(panels), 1, squeeze=False)[:, 0], panels):
        for i in range(values.shape[1]):
            ax.plot(t, values[:, i], label=names[i] if i < len(names) else str(i), linewidth=1.2)
        ax.set_title(title, loc="left", fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncols=min(values.shape[1], 7), loc="upper right")
    ax.set_xlabel("time (s)")
    fig.suptitle(f"episode {view.index}: {ep.instruction} ({len(ep)} frames at {view.fps} fps, "
                 f"{'success' if ep.success else 'failure'})", fontsize=11)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    return path


def rerun_available() -> bool:
    return importlib.util.find_spec("rerun") is not None


def log_rerun(view: EpisodeView, save: str | Path | None = None, spawn: bool = True) -> Path | None:
    """Logs the episode to Rerun: saved to ``save`` (an .rrd file) when given, else shown in a spawned viewer."""
    import rerun as rr

    ep = view.episode
    rr.init(f"pivla/episode_{view.index}", spawn=spawn and save is None)
    if save is not None:
        save = Path(save)
        save.parent.mkdir(parents=True, exist_ok=True)
        rr.save(str(save))
    vectors = {"action": (ep.actions, list(view.action_space.names))}
    for key, values in _vectors(ep).items():
        vectors[f"observation/{key}"] = (values, view.state_names.get(key) or [str(i) for i in range(values.shape[1])])
    images = _images(ep)
    for t in range(len(ep)):
        rr.set_time("frame", sequence=t)
        rr.set_time("time", duration=t / view.fps)
        for key, frames in images.items():
            rr.log(f"observation/images/{key}", rr.Image(frames[t]))
        for entity, (values, names) in vectors.items():
            for i, name in enumerate(names):
                rr.log(f"{entity}/{name}", rr.Scalars(float(values[t, i])))
    if save is not None:
        rr.disconnect()
    return save


def view(root: str | Path, episode: int, out: str | Path | None = None, viewer: Viewer = "auto",
         spawn: bool = True) -> dict[str, Path | None]:
    """Shows episode ``episode`` (see the module doc). ``out``: the folder of the files (default
    ``<root>-view`` beside the dataset). Returns what was written."""
    root = Path(root)
    data = load_episode(root, episode)
    out = Path(out) if out is not None else root.parent / f"{root.name}-view"
    stem = f"episode_{episode:06d}"
    use_rerun = viewer == "rerun" or (viewer == "auto" and rerun_available())
    if use_rerun:
        if not rerun_available():
            raise ModuleNotFoundError("viewing with Rerun needs rerun-sdk: pip install 'pivla[viz]'")
        return {"rrd": log_rerun(data, save=None if spawn else out / f"{stem}.rrd", spawn=spawn)}
    written: dict[str, Path | None] = {"plot": write_plot(data, out / f"{stem}.png")}
    written["video"] = write_video(data, out / f"{stem}.mp4") if _images(data.episode) else None
    return written
