"""``pivla collect``: scripted-expert demonstrations into a LIBERO-layout dataset (one HDF5 file per task);
``pivla export-video``: MP4 previews of a dataset's episodes (PyAV, H.264)."""

from __future__ import annotations

import argparse
import functools
import logging
import os
import tempfile
from pathlib import Path

log = logging.getLogger("pivla.collect")


def register(command: str, parser: argparse.ArgumentParser) -> None:
    if command == "collect":
        parser.add_argument("--env", default="tabletop", choices=["tabletop"],
                            help="environment family (the scripted expert needs the simulated twin)")
        parser.add_argument("--suite", required=True, help="pick_place, pick_place_seen, pick_place_unseen, "
                                                           "drawer, stack, long")
        parser.add_argument("--tasks", default=None, help="task indices or names, comma-separated (default: all)")
        parser.add_argument("--episodes", type=int, default=50, help="successful episodes per task")
        parser.add_argument("--out", required=True, help="output dataset directory")
        parser.add_argument("--seed", type=int, default=0)
        parser.add_argument("--perturb", default=None, help="e.g. unseen_env,static_distractors,level=3 "
                                                            "(grammar: docs/twin.md)")
        parser.add_argument("--workers", type=int, default=1, help="worker processes (results do not depend on it)")
        parser.add_argument("--realism", default="ideal", choices=["ideal", "servo"])
        parser.add_argument("--image-size", type=int, default=96)
        parser.add_argument("--noise", type=float, default=0.0, help="expert action noise (std, action units)")
        parser.add_argument("--paraphrase", action="store_true", help="draw an instruction paraphrase per episode")
        parser.add_argument("--keep-failures", action="store_true",
                            help="keep failed expert episodes instead of replacing them with new seeds")
        parser.add_argument("--policy", default=None,
                            help="record rollouts of this trained run instead of expert demos: successes and "
                                 "failures with rewards, for the RL and value terms (`pivla train --extra-data`)")
        parser.add_argument("--executor", default="fixed", choices=["aurd", "fixed", "ensemble", "adahorizon"],
                            help="executor of the policy rollouts (with --policy)")
        parser.set_defaults(func=collect)
    elif command == "export-video":
        parser.add_argument("dataset", help="dataset directory (or one .hdf5 file)")
        parser.add_argument("--out", default=None, help="output directory (default: <dataset>/videos)")
        parser.add_argument("--max-episodes", type=int, default=3, help="episodes per file")
        parser.add_argument("--fps", type=int, default=10)
        parser.add_argument("--scale", type=int, default=3, help="integer upscaling of the frames")
        parser.set_defaults(func=export_video)
    else:
        raise ValueError(f"pivla.cli.collect does not provide command {command!r}")


def collect(args: argparse.Namespace) -> int:
    from pivla.data.format import write_episodes
    from pivla.envs import select_tasks
    from pivla.envs.rollout import episode_seed, run_jobs
    from pivla.envs.tabletop import make_env, parse_perturb
    from pivla.envs.tabletop.env import CONTROL_HZ, ROT_SCALE, TRANS_SCALE
    from pivla.envs.tabletop.expert import make_expert

    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.episodes < 1:
        raise SystemExit("--episodes must be >= 1")
    if args.policy:
        return collect_rollouts(args)
    try:
        perturb = parse_perturb(args.perturb)
        specs = select_tasks(args.env, args.suite, args.tasks)
    except ValueError as e:
        raise SystemExit(f"pivla collect: {e}") from e
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    expert = make_expert(args.noise)
    factories = {
        spec.name: functools.partial(make_env, args.suite, spec.name, image_size=args.image_size,
                                     realism=args.realism, perturb=perturb.spec(), paraphrase=args.paraphrase)
        for spec in specs
    }
    task_seeds = {spec.name: episode_seed(args.seed, spec.index) for spec in specs}
    kept: dict[str, list] = {spec.name: [] for spec in specs}
    attempts = dict.fromkeys(task_seeds, 0)
    budget = 3 * args.episodes + 10
    # Rounds over all tasks at once (one worker pool per round); failed expert episodes are replaced by
    # the next seeds of the same task, so the dataset does not depend on the number of workers.
    while True:
        jobs, owners = [], []
        for name in kept:
            need = args.episodes - len(kept[name])
            if need <= 0 or attempts[name] >= budget:
                continue
            for i in range(need):
                jobs.append((factories[name], episode_seed(task_seeds[name], attempts[name] + i)))
                owners.append(name)
            attempts[name] += need
        if not jobs:
            break
        for name, ep in zip(owners, run_jobs(jobs, expert, workers=args.workers, desc="collect")):
            if ep.success or args.keep_failures:
                kept[name].append(ep)
    status = 0
    for spec in specs:
        episodes = kept[spec.name]
        n_success = sum(e.success for e in episodes)
        rate = (n_success if args.keep_failures else len(episodes)) / attempts[spec.name]
        if not episodes:
            log.error("%s: the expert failed all %d attempts; nothing written", spec.name, attempts[spec.name])
            status = 1
            continue
        env_meta = {
            "env": args.env, "suite": args.suite, "task": spec.name, "task_index": spec.index,
            "instruction": spec.instruction, "max_steps": spec.max_steps, "realism": args.realism,
            "perturb": perturb.spec(), "image_size": args.image_size, "control_hz": CONTROL_HZ,
            "action": {"translation_m_per_unit": TRANS_SCALE, "rotation_rad_per_unit": ROT_SCALE,
                       "gripper": "-1 open, +1 closed"},
            "seed": args.seed, "noise": args.noise, "attempts": attempts[spec.name],
        }
        path = write_episodes(out / f"{spec.name}_demo.hdf5", episodes, env_meta)
        log.info("%s: %d episodes (%d steps) -> %s; expert success %.1f%% over %d attempts", spec.name,
                 len(episodes), sum(len(e) for e in episodes), path, 100 * rate, attempts[spec.name])
        if len(episodes) < args.episodes:
            log.error("%s: only %d of %d successful episodes after %d attempts", spec.name, len(episodes),
                      args.episodes, attempts[spec.name])
            status = 1
    return status


def collect_rollouts(args: argparse.Namespace) -> int:
    """Policy rollouts, every one kept with its success, through the evaluation runner (same seeds logic,
    workers, traces); the dataset goes to ``--out``, the evaluation record to ``--out/rollout_eval``."""
    from pivla.evaluation.runner import EvalConfig, evaluate

    cfg = EvalConfig(policy=args.policy, out=str(Path(args.out) / "rollout_eval"), env=args.env, suite=args.suite,
                     tasks=args.tasks, executor=args.executor, episodes=args.episodes, seed=args.seed,
                     perturb=args.perturb, realism=args.realism, workers=args.workers, videos=0, record=args.out)
    res = evaluate(cfg)
    log.info("recorded %d rollouts (%d successes) -> %s", res["episodes"], res["successes"], args.out)
    return 0


def _write_mp4(path: Path, frames, fps: int) -> None:
    """Encode (T, H, W, 3) uint8 frames as H.264 MP4, atomically."""
    import av

    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".mp4")
    os.close(fd)
    try:
        with av.open(tmp, mode="w", format="mp4") as container:
            stream = container.add_stream("libx264", rate=fps)
            stream.height, stream.width = frames.shape[1], frames.shape[2]
            stream.pix_fmt = "yuv420p"
            for frame in frames:
                container.mux(stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")))
            container.mux(stream.encode())
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def export_video(args: argparse.Namespace) -> int:
    import numpy as np

    from pivla.data.format import DatasetError, dataset_files, read_episodes

    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        files = dataset_files(args.dataset)
    except DatasetError as e:
        raise SystemExit(f"pivla export-video: {e}") from e
    root = Path(args.dataset)
    out = Path(args.out) if args.out else (root if root.is_dir() else root.parent) / "videos"
    out.mkdir(parents=True, exist_ok=True)
    written = 0
    for path in files:
        for i, ep in enumerate(read_episodes(path)[: args.max_episodes]):
            views = [ep.obs[k] for k in ("agentview_rgb", "eye_in_hand_rgb") if k in ep.obs]
            height = max(v.shape[1] for v in views)
            views = [np.pad(v, ((0, 0), (0, height - v.shape[1]), (0, 0), (0, 0))) for v in views]
            frames = np.concatenate(views, axis=2)
            frames = frames.repeat(args.scale, axis=1).repeat(args.scale, axis=2)
            frames = frames[:, : frames.shape[1] // 2 * 2, : frames.shape[2] // 2 * 2]
            target = out / f"{path.stem}_{i}.mp4"
            _write_mp4(target, frames, args.fps)
            written += 1
            log.info("%s (%s, %d steps, success=%s)", target, ep.instruction, len(ep), ep.success)
    log.info("wrote %d videos to %s", written, out)
    return 0
