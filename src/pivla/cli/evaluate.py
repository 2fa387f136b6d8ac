"""``pivla eval``, ``pivla calibrate``, ``pivla ablate`` and ``pivla report``."""

from __future__ import annotations

import argparse
import json
import logging

from pivla.evaluation import protocol


def _add_eval_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--env", default="tabletop", choices=["tabletop", "libero"])
    p.add_argument("--suite", default="pick_place")
    p.add_argument("--tasks", default=None, help="task indices or names, comma-separated (default: all)")
    p.add_argument("--episodes", type=int, default=10, help="episodes per task")
    p.add_argument("--seed", type=int, default=1000, help="base seed of the test episodes")
    p.add_argument("--perturb", default=None, help="perturbation spec (docs/twin.md)")
    p.add_argument("--realism", default="ideal", choices=["ideal", "servo"])
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--max-steps", type=int, default=None)
    p.add_argument("--first-init-state", type=int, default=0,
                   help="LIBERO: episode e uses official init state first+e (mod 50); keep test states apart "
                        "from those the training demos came from")


def register(command: str, parser: argparse.ArgumentParser) -> None:
    if command == "eval":
        parser.add_argument("--policy", required=True, help="run directory")
        parser.add_argument("--executor", default="aurd", choices=["aurd", "fixed", "ensemble", "adahorizon"])
        parser.add_argument("--out", required=True)
        _add_eval_args(parser)
        parser.add_argument("--videos", type=int, default=2)
        parser.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                            help="executor option, e.g. horizon=3 (fixed), check=after (aurd), tau_high=0.2")
        parser.add_argument("--record", default=None, help="also write every rollout into this dataset directory")
        parser.add_argument("--split", default="test", choices=["test", "validation"],
                            help="validation: rollouts to calibrate on (pivla report leaves them out)")
        parser.add_argument("--gripper-head", default=None, choices=["continuous", "discrete"],
                            help="head that drives the gripper (default: discrete when both were trained)")
        parser.set_defaults(func=cmd_eval)
    elif command == "calibrate":
        parser.add_argument("--policy", required=True, help="run directory")
        parser.add_argument("--data", required=True, help="validation dataset (successful episodes are used)")
        from pivla.control.calibrate import CalibrationConfig  # the command needs torch anyway

        d = CalibrationConfig()
        parser.add_argument("--tau-low-pct", type=float, help=f"percentile of U for tau_low (default P{d.tau_low_pct:g})")
        parser.add_argument("--tau-high-pct", type=float,
                            help=f"percentile of U for tau_high, and of U_act for AdaHorizon's act_high "
                                 f"(default P{d.tau_high_pct:g})")
        parser.add_argument("--v-pct", type=float, help=f"percentile of V for V_thresh (default P{d.v_pct:g})")
        parser.add_argument("--eta", type=float, help=f"weight of U_act in U (default {d.eta:g})")
        parser.add_argument("--pred-baseline", choices=["none", "episode"],
                            help="episode: U_pred above the episode's smallest so far, AURD then uses the same "
                                 f"(default {d.pred_baseline})")
        parser.add_argument("--held-out", action="store_true",
                            help="--data is the run's training data: use only the episodes its split.json held out")
        parser.set_defaults(func=cmd_calibrate)
    elif command == "ablate":
        parser.add_argument("--data", required=True, help="training dataset")
        parser.add_argument("--val", required=True,
                            help="validation demonstrations (calibration falls back to them when a variant's "
                                 "validation rollouts all fail)")
        parser.add_argument("--out", required=True)
        parser.add_argument("--steps", type=int, default=protocol.STEPS, help="training steps per variant (the demo's)")
        parser.add_argument("--batch-size", type=int, default=protocol.BATCH_SIZE)
        parser.add_argument("--image-size", type=int, default=None,
                            help="policy resolution in px (default: the demo's, pivla demo --help)")
        parser.add_argument("--train-seed", type=int, default=0)
        parser.add_argument("--val-seed", type=int, default=1, help="seed of the validation rollouts")
        parser.add_argument("--val-episodes", type=int, default=5, help="validation rollouts per task")
        parser.add_argument("--variants", default=None, help="comma-separated subset of the ablation variants")
        _add_eval_args(parser)
        parser.set_defaults(func=cmd_ablate)
    elif command == "report":
        parser.add_argument("dir", help="directory with one or more evaluations (results.json)")
        parser.set_defaults(func=cmd_report)


def _parse_options(items: list[str]) -> dict:
    out = {}
    for item in items:
        if "=" not in item:
            raise SystemExit(f"--option {item!r}: expected KEY=VALUE")
        k, v = item.split("=", 1)
        try:
            out[k] = json.loads(v)
        except json.JSONDecodeError:
            out[k] = v
    return out


def cmd_eval(args: argparse.Namespace) -> int:
    from pivla.evaluation.runner import EvalConfig, evaluate

    logging.basicConfig(level=logging.INFO, format="%(message)s")
    cfg = EvalConfig(policy=args.policy, out=args.out, env=args.env, suite=args.suite, tasks=args.tasks,
                     executor=args.executor, episodes=args.episodes, seed=args.seed, perturb=args.perturb,
                     realism=args.realism, workers=args.workers, videos=args.videos, max_steps=args.max_steps,
                     executor_options=_parse_options(args.option), record=args.record,
                     first_init_state=args.first_init_state, split=args.split, gripper_head=args.gripper_head)
    res = evaluate(cfg)
    lo, hi = res["ci95"]
    print(f"{args.executor}: success {res['success_rate']:.1%} [{lo:.1%}, {hi:.1%}] over {res['episodes']} episodes; "
          f"mean horizon {res['mean_executed_horizon']:.2f}, replans {res['replans']}, prunes {res['prunes']}, "
          f"pauses {res['pauses']}, control {res['control_hz']:.0f} Hz -> {args.out}/results.json")
    return 0


def held_out_episodes(run_dir: str, episodes: list) -> list:
    """The episodes of a run's training data that its ``split.json`` kept out of training."""
    from pathlib import Path

    path = Path(run_dir) / "split.json"
    if not path.exists():
        raise SystemExit(f"--held-out: {path} not found (written by `pivla train`); give --data without --held-out")
    split = json.loads(path.read_text())
    n = len(split["train_episodes"]) + len(split["val_episodes"])
    if n != len(episodes):
        raise SystemExit(f"--held-out: the run was trained on {n} episodes, --data has {len(episodes)}; "
                         "give the run's training data (without --extra-data)")
    if not split["val_episodes"]:
        raise SystemExit("--held-out: the run held out no episodes (trained with --val-fraction 0)")
    return [episodes[i] for i in split["val_episodes"]]


def cmd_calibrate(args: argparse.Namespace) -> int:
    from pivla import load_policy
    from pivla.control.calibrate import CalibrationConfig, calibrate
    from pivla.data.format import read_dataset

    policy = load_policy(args.policy, device="cpu")
    given = {"tau_low_pct": args.tau_low_pct, "tau_high_pct": args.tau_high_pct, "v_pct": args.v_pct,
             "eta": args.eta, "pred_baseline": args.pred_baseline}
    cfg = CalibrationConfig(**{k: v for k, v in given.items() if v is not None})
    episodes = read_dataset(args.data)
    source = str(args.data)
    if args.held_out:
        episodes = held_out_episodes(args.policy, episodes)
        source += " (held-out split)"
    try:
        calib, stats = calibrate(policy, episodes, cfg, source=source)
    except ValueError as e:  # test rollouts, or no successful episode to calibrate on
        raise SystemExit(f"pivla calibrate: {e}") from e
    print(json.dumps({"calibration": vars(calib), **stats}, indent=2))
    return 0


def cmd_ablate(args: argparse.Namespace) -> int:
    from pivla.cli.demo import DemoConfig, model_config
    from pivla.evaluation.ablate import AblationConfig, run_ablation

    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        model = model_config(DemoConfig(image_size=args.image_size or DemoConfig.image_size))
    except ValueError as e:
        raise SystemExit(f"pivla ablate: {e}") from e
    cfg = AblationConfig(data=args.data, val=args.val, out=args.out, steps=args.steps, batch_size=args.batch_size,
                         env=args.env, suite=args.suite, tasks=args.tasks, episodes=args.episodes, seed=args.seed,
                         train_seed=args.train_seed, val_seed=args.val_seed, val_episodes=args.val_episodes,
                         perturb=args.perturb,
                         realism=args.realism, workers=args.workers,
                         variants=tuple(args.variants.split(",")) if args.variants else None,
                         model=model)
    table = run_ablation(cfg)
    print(table)
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    from pivla.evaluation.report import write_report

    try:
        path = write_report(args.dir)
    except ValueError as e:  # an evaluation layout the report cannot read; said in the message
        raise SystemExit(f"pivla report: {e}") from e
    print(f"report written to {path}")
    return 0
