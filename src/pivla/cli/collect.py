"""``pivla collect``: scripted-expert demonstrations into a LIBERO-layout dataset (one HDF5 file per task),
on the simulated twin or on LIBERO itself; ``pivla export-video``: MP4 previews of a dataset's episodes."""

from __future__ import annotations

import argparse
import functools
import logging
from pathlib import Path

log = logging.getLogger("pivla.collect")

DEFAULT_IMAGE_SIZE = {"tabletop": 96, "libero": 128}


def register(command: str, parser: argparse.ArgumentParser) -> None:
    if command == "collect":
        parser.add_argument("--env", default="tabletop", choices=["tabletop", "libero"],
                            help="environment family: the simulated twin, or LIBERO (libero_spatial and "
                                 "libero_object suites and their variants have scripted experts)")
        parser.add_argument("--suite", required=True, help="tabletop: pick_place, pick_place_seen, "
                                                           "pick_place_unseen, drawer, stack, long; "
                                                           "libero: libero_spatial, libero_object, ...")
        parser.add_argument("--tasks", default=None, help="task indices or names, comma-separated (default: all)")
        parser.add_argument("--episodes", type=int, default=50, help="successful episodes per task")
        parser.add_argument("--out", required=True, help="output dataset directory")
        parser.add_argument("--seed", type=int, default=0,
                            help="libero: episodes start from the official init states 0, 1, ... of each task "
                                 "(failed attempts move on to the next); the seed drives the rest")
        parser.add_argument("--perturb", default=None, help="e.g. unseen_env,static_distractors,level=3 "
                                                            "(grammar: docs/twin.md)")
        parser.add_argument("--workers", type=int, default=1, help="worker processes (results do not depend on it)")
        parser.add_argument("--realism", default="ideal", choices=["ideal", "servo"])
        parser.add_argument("--image-size", type=int, default=None, help="camera resolution (default: "
                            f"{', '.join(f'{k} {v}' for k, v in DEFAULT_IMAGE_SIZE.items())})")
        parser.add_argument("--noise", type=float, default=0.0,
                            help="noise on the expert's executed actions (std, action units); labels stay clean (DART)")
        parser.add_argument("--miss", type=float, default=0.0,
                            help="share of episodes whose first grasp is executed off the object, so the "
                                 "demonstrations show reopening and grasping again (labels stay clean)")
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
    if args.policy:  # every rollout is kept (--keep-failures is implied); cameras are the policy's own
        expert_only = [flag for flag, given in (("--noise", args.noise), ("--miss", args.miss),
                                                 ("--paraphrase", args.paraphrase),
                                                 ("--image-size", args.image_size is not None)) if given]
        if expert_only:
            raise SystemExit(f"pivla collect: {', '.join(expert_only)} shape expert demonstrations, not --policy "
                             "rollouts (they see what the policy was trained on)")
        return collect_rollouts(args)
    if args.image_size is None:
        args.image_size = DEFAULT_IMAGE_SIZE[args.env]
    if args.env == "libero":
        return collect_libero(args)
    try:
        perturb = parse_perturb(args.perturb)
        specs = select_tasks(args.env, args.suite, args.tasks)
    except ValueError as e:
        raise SystemExit(f"pivla collect: {e}") from e
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    expert = make_expert(args.noise, args.miss)
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
            "seed": args.seed, "noise": args.noise, "miss": args.miss, "attempts": attempts[spec.name],
        }
        path = write_episodes(out / f"{spec.name}_demo.hdf5", episodes, env_meta)
        log.info("%s: %d episodes (%d steps) -> %s; expert success %.1f%% over %d attempts", spec.name,
                 len(episodes), sum(len(e) for e in episodes), path, 100 * rate, attempts[spec.name])
        if len(episodes) < args.episodes:
            log.error("%s: only %d of %d successful episodes after %d attempts", spec.name, len(episodes),
                      args.episodes, attempts[spec.name])
            status = 1
    return status


def collect_libero(args: argparse.Namespace) -> int:
    """LIBERO demonstrations by the privileged-state scripted experts, one file per task.

    Attempt ``k`` of a task starts from official init state ``k`` (modulo the task's 50), so the dataset does
    not depend on ``--workers``, which spreads whole tasks over processes (each LIBERO process holds ~2 GB).
    """
    from pivla.data.format import write_episodes
    from pivla.envs import select_tasks

    unsupported = {"--perturb (use a LIBERO-PRO suite)": args.perturb, "--paraphrase (use a *_lan suite)":
                   args.paraphrase, "--noise": args.noise, "--miss": args.miss,
                   "--realism servo": args.realism != "ideal"}
    given = [flag for flag, value in unsupported.items() if value]
    if given:
        raise SystemExit(f"pivla collect --env libero: not supported: {', '.join(given)}")
    try:
        specs = select_tasks("libero", args.suite, args.tasks)
        from pivla.envs.libero import expert_actor

        for spec in specs:
            expert_actor(args.suite, spec.index)
    except (ValueError, ImportError) as e:
        raise SystemExit(f"pivla collect: {e}") from e
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    jobs = [(args.suite, spec.index, args.episodes, args.keep_failures, args.seed, args.image_size) for spec in specs]
    if args.workers > 1 and len(jobs) > 1:
        import multiprocessing as mp

        with mp.get_context("spawn").Pool(min(args.workers, len(jobs))) as pool:
            results = pool.map(_collect_libero_task, jobs)
    else:
        results = [_collect_libero_task(job) for job in jobs]
    status = 0
    for spec, (episodes, attempts) in zip(specs, results):
        n_success = sum(e.success for e in episodes)
        if not episodes:
            log.error("%s: the expert failed all %d attempts; nothing written", spec.name, attempts)
            status = 1
            continue
        env_meta = {
            "env": "libero", "suite": args.suite, "task": spec.name, "task_index": spec.index,
            "instruction": spec.instruction, "max_steps": spec.max_steps, "image_size": args.image_size,
            "control_hz": 20, "action": {"space": "OSC_POSE deltas", "translation_m_per_unit": 0.05,
                                         "rotation_rad_per_unit": 0.5, "gripper": "-1 open, +1 closed"},
            "seed": args.seed, "attempts": attempts, "expert": "scripted, privileged simulator state",
            "init_states": [e.meta["init_state"] for e in episodes],
        }
        path = write_episodes(out / f"{spec.name}_demo.hdf5", episodes, env_meta)
        log.info("%s: %d episodes (%d steps) -> %s; expert success %d/%d attempts", spec.name, len(episodes),
                 sum(len(e) for e in episodes), path, n_success, attempts)
        if not args.keep_failures and len(episodes) < args.episodes:
            log.error("%s: only %d of %d successful episodes after %d attempts", spec.name, len(episodes),
                      args.episodes, attempts)
            status = 1
    return status


def _collect_libero_task(job: tuple[str, int, int, bool, int, int]) -> tuple[list, int]:
    """(episodes kept, attempts) for one LIBERO task; runs in a worker process when ``--workers > 1``."""
    from pivla.envs import make_env
    from pivla.envs.libero.expert import RolloutExpert
    from pivla.envs.rollout import episode_seed, run_episode

    suite, task, wanted, keep_failures, seed, image_size = job
    env = make_env("libero", suite, task, image_size=image_size, render=True, init_state=0)
    actor = RolloutExpert(suite, task)
    budget = wanted if keep_failures else 3 * wanted + 10
    kept, attempts = [], 0
    try:
        while len(kept) < wanted and attempts < budget:
            ep = run_episode(env, actor, episode_seed(episode_seed(seed, task), attempts))
            ep.meta["init_state"] = env.init_state
            attempts += 1
            if ep.success or keep_failures:
                kept.append(ep)
            log.info("%s task %d init state %d: %s in %d steps", suite, task, env.init_state,
                     "success" if ep.success else "failure", len(ep))
    finally:
        env.close()
    return kept, attempts


def collect_rollouts(args: argparse.Namespace) -> int:
    """Policy rollouts, every one kept with its success, through the evaluation runner (same seeds logic,
    workers, traces); the dataset goes to ``--out``, the evaluation record to ``--out/rollout_eval``."""
    from pivla.evaluation.runner import EvalConfig, evaluate

    cfg = EvalConfig(policy=args.policy, out=str(Path(args.out) / "rollout_eval"), env=args.env, suite=args.suite,
                     tasks=args.tasks, executor=args.executor, episodes=args.episodes, seed=args.seed,
                     perturb=args.perturb, realism=args.realism, workers=args.workers, videos=0, record=args.out,
                     split="train")
    res = evaluate(cfg)
    log.info("recorded %d rollouts (%d successes) -> %s", res["episodes"], res["successes"], args.out)
    return 0


def export_video(args: argparse.Namespace) -> int:
    import numpy as np

    from pivla.data.format import DatasetError, dataset_files, read_episodes
    from pivla.io import write_mp4

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
            write_mp4(target, frames, args.fps)
            written += 1
            log.info("%s (%s, %d steps, success=%s)", target, ep.instruction, len(ep), ep.success)
    log.info("wrote %d videos to %s", written, out)
    return 0
