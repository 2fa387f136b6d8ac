"""``pivla collect``, ``pivla export-video``, ``pivla data convert`` and ``pivla data view``."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import tyro

from pivla.control.executors import ExecutorConfig, FixedConfig
from pivla.data.convert import ConvertConfig
from pivla.envs.collect import CollectConfig

log = logging.getLogger("pivla.collect")


@dataclass
class CollectCommand:
    """Expert demonstrations; or, with --policy, rollouts of a trained policy, every one kept with its success
    and rewards (failures teach the value head: ``pivla train --extra-data``)."""

    demos: Annotated[CollectConfig, tyro.conf.arg(name="")]
    policy: str | None = None
    """Record rollouts of this run (or ws://HOST:PORT) instead of expert demonstrations."""
    executor: ExecutorConfig = field(default_factory=FixedConfig)
    """Executor of the policy rollouts (with --policy)."""


def collect(cmd: CollectCommand) -> int:
    cfg = cmd.demos
    if cmd.policy is None:
        from pivla.envs.collect import collect_demos

        try:
            return collect_demos(cfg)
        except ValueError as e:
            raise SystemExit(f"pivla collect: {e}") from e
    expert_only = [flag for flag, given in (("--noise", cfg.noise), ("--miss", cfg.miss),
                                             ("--paraphrase", cfg.paraphrase),
                                             ("--image-size", cfg.image_size is not None)) if given]
    if expert_only:
        raise SystemExit(f"pivla collect: {', '.join(expert_only)} shape expert demonstrations, not --policy "
                         "rollouts (they see what the policy was trained on)")
    from pivla.evaluation.runner import EvalConfig, evaluate

    ec = EvalConfig(policy=cmd.policy, out=str(Path(cfg.out) / "rollout_eval"), env=cfg.env, suite=cfg.suite,
                    tasks=cfg.tasks, executor=cmd.executor, episodes=cfg.episodes, seed=cfg.seed,
                    perturb=cfg.perturb, realism=cfg.realism, workers=cfg.workers, dispatch=cfg.dispatch, videos=0,
                    record=cfg.out, split="train")
    res = evaluate(ec)
    log.info("recorded %d rollouts (%d successes) -> %s", res["episodes"], res["successes"], cfg.out)
    return 0


@dataclass
class ExportVideoConfig:
    """MP4 previews of a dataset's episodes, both cameras side by side."""

    dataset: tyro.conf.Positional[str]
    """Dataset directory (or one .hdf5 file)."""
    out: str | None = None
    """Output directory (default: <dataset>/videos)."""
    max_episodes: int = 3
    """Episodes per file."""
    fps: int = 10
    """Frames per second."""
    scale: int = 3
    """Integer upscaling of the frames."""


def export_video(cfg: ExportVideoConfig) -> int:
    from pivla.data.episode import DatasetError
    from pivla.data.hdf5 import dataset_files, read_episodes
    from pivla.io import write_mp4

    try:
        files = dataset_files(cfg.dataset)
    except DatasetError as e:
        raise SystemExit(f"pivla export-video: {e}") from e
    root = Path(cfg.dataset)
    out = Path(cfg.out) if cfg.out else (root if root.is_dir() else root.parent) / "videos"
    out.mkdir(parents=True, exist_ok=True)
    written = 0
    for path in files:
        for i, ep in enumerate(read_episodes(path)[: cfg.max_episodes]):
            views = [ep.obs[k] for k in ("agentview_rgb", "eye_in_hand_rgb") if k in ep.obs]
            height = max(v.shape[1] for v in views)
            views = [np.pad(v, ((0, 0), (0, height - v.shape[1]), (0, 0), (0, 0))) for v in views]
            frames = np.concatenate(views, axis=2)
            frames = frames.repeat(cfg.scale, axis=1).repeat(cfg.scale, axis=2)
            frames = frames[:, : frames.shape[1] // 2 * 2, : frames.shape[2] // 2 * 2]
            target = out / f"{path.stem}_{i}.mp4"
            write_mp4(target, frames, cfg.fps)
            written += 1
            log.info("%s (%s, %d steps, success=%s)", target, ep.instruction, len(ep), ep.success)
    log.info("wrote %d videos to %s", written, out)
    return 0


def convert(cfg: ConvertConfig) -> int:
    from pivla.data.convert import run_convert
    from pivla.data.episode import DatasetError

    try:
        res = run_convert(cfg)
    except DatasetError as e:
        raise SystemExit(f"pivla data convert: {e}") from e
    print(f"{res.source_format} -> {cfg.to}: {res.episodes} episodes, {res.frames} frames at {res.fps} fps "
          f"-> {res.dst}")
    return 0


@dataclass
class ViewConfig:
    """One episode of a dataset: logged to Rerun when rerun-sdk is installed (pip install 'pivla[viz]'), else an
    MP4 of its cameras and a PNG plot of its actions and state."""

    dataset: tyro.conf.Positional[str]
    """Dataset directory (LeRobot v3.0, or pivla's HDF5 files)."""
    episode: int = 0
    """Index of the episode."""
    viewer: Literal["auto", "rerun", "files"] = "auto"
    """rerun: log to Rerun; files: the MP4 and the PNG; auto: Rerun when installed."""
    out: str | None = None
    """Folder of the MP4 and PNG (or the .rrd with --no-spawn) (default: <dataset>-view beside the dataset)."""
    spawn: bool = True
    """Rerun: show the episode in a spawned viewer; --no-spawn saves an .rrd recording instead."""


def view(cfg: ViewConfig) -> int:
    from pivla.data.view import view as view_episode

    written = view_episode(cfg.dataset, cfg.episode, cfg.out, cfg.viewer, cfg.spawn)
    for kind, path in written.items():
        if path is not None:
            print(f"{kind}: {path}")
    return 0
