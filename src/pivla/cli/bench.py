"""``pivla bench infer|train|sim|control``: speed measured on this machine, medians after warm-up."""

from __future__ import annotations

import argparse
import json
import time

import numpy as np


def register(command: str, parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="what", required=True)
    p = sub.add_parser("infer", help="batch-1 forward pass of the default (or a trained) policy")
    p.add_argument("--run", help="a trained run directory (default: the default config, random weights)")
    p.add_argument("--runs", type=int, default=100)
    p.add_argument("--warmup", type=int, default=20)
    p.set_defaults(func=bench_infer)
    p = sub.add_parser("train", help="training samples/s of the default policy on synthetic data")
    p.add_argument("--steps", type=int, default=30)
    p.add_argument("--batch-size", type=int, default=64)
    p.add_argument("--grid-tokens", action="store_true",
                   help="the grid-token backbone (the default until session 5) instead of pooled tokens")
    p.set_defaults(func=bench_train)
    p = sub.add_parser("sim", help="environment steps/s with cameras, and collection episodes/min")
    p.add_argument("--env", default="tabletop", choices=["tabletop", "libero"])
    p.add_argument("--suite", default=None)
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--episodes", type=int, default=5)
    p.set_defaults(func=bench_sim)
    p = sub.add_parser("control", help="AURD's per-step overhead against the fixed-horizon executor")
    p.add_argument("--run", help="a trained run directory (default: random weights)")
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--loop-episodes", type=int, default=5,
                   help="also time whole episodes in the tabletop twin (0: controller only)")
    p.add_argument("--encoder-runtime", choices=["auto", "torch", "onnx"], default="auto",
                   help="where the target encoder runs (auto: ONNX Runtime on a CPU when installed); with ONNX "
                        "Runtime, one PyTorch encoding is timed too, for comparison")
    p.set_defaults(func=bench_control)
    p = sub.add_parser("hf", help="CPU cost of the tiny random hf backbone stack (or a local checkpoint)")
    p.add_argument("--path", default="", help="local Llava-style checkpoint (default: a tiny random one)")
    p.add_argument("--target-path", default="", help="local DINOv2 checkpoint (default: a tiny random one)")
    p.add_argument("--image-size", type=int, default=32)
    p.add_argument("--batch", type=int, default=1)
    p.add_argument("--repeats", type=int, default=30)
    p.add_argument("--lora-rank", type=int, default=32)
    p.set_defaults(func=bench_hf)
    p = sub.add_parser("robot", help="serial round trips to the board (a simulated board when --port is absent)")
    p.add_argument("--port", default=None)
    p.add_argument("--n", type=int, default=200)
    p.set_defaults(func=bench_robot)
    for p in sub.choices.values():
        p.add_argument("--json", action="store_true", help="print one JSON object")
        p.add_argument("--threads", type=int, default=2, help="torch intra-op threads")


def emit(result: dict, as_json: bool) -> int:
    if as_json:
        print(json.dumps(result))
    else:
        for k, v in result.items():
            print(f"{k}: {v}")
    return 0


def default_policy(run: str | None, image_size: int | None = None, encoder_runtime: str = "auto"):
    """A trained policy, or the default configuration with random weights (speed does not depend on them)."""
    from pivla import load_policy
    from pivla.data.normalize import ActionStats, NormStats, StandardStats
    from pivla.data.text import WordTokenizer
    from pivla.model.cms import CMSModel
    from pivla.model.config import ModelConfig
    from pivla.policy import Policy

    if run:
        return load_policy(run, device="cpu", encoder_runtime=encoder_runtime)
    cfg = ModelConfig() if image_size is None else ModelConfig(image_size=image_size)
    text = WordTokenizer.build(["pick up the red block and move it to the left of the table"], cfg.max_text_len)
    stats = NormStats(ActionStats([-1.0] * 7, [1.0] * 7), StandardStats([0.0] * cfg.proprio_dim, [1.0] * cfg.proprio_dim))
    return Policy(CMSModel(cfg, len(text.vocab)), stats, text, encoder_runtime=encoder_runtime)


def random_obs(policy, rng: np.random.Generator) -> dict:
    s = policy.cfg.image_size
    obs = {c: rng.integers(0, 255, (s, s, 3), dtype=np.uint8) for c in policy.cfg.cameras}
    obs.update(ee_pos=np.zeros(3, np.float32), ee_ori=np.zeros(3, np.float32), gripper_states=np.zeros(2, np.float32),
               joint_states=np.zeros(6, np.float32), instruction="pick up the red block and move it to the left")
    return obs


def bench_infer(args: argparse.Namespace) -> int:
    import torch

    torch.set_num_threads(args.threads)
    policy = default_policy(args.run)
    obs = random_obs(policy, np.random.default_rng(0))
    inputs = policy.model_inputs([obs])
    times, full = [], []
    with torch.inference_mode():
        for i in range(args.warmup + args.runs):
            t = time.perf_counter()
            policy.model(inputs)
            dt = time.perf_counter() - t
            t = time.perf_counter()
            policy.infer(obs)
            dt_full = time.perf_counter() - t
            if i >= args.warmup:
                times.append(dt)
                full.append(dt_full)
    med, med_full = float(np.median(times)) * 1e3, float(np.median(full)) * 1e3
    counts = policy.model.parameter_counts()
    return emit({
        "forward_ms_median": round(med, 3),
        "forward_ms_p90": round(float(np.percentile(times, 90)) * 1e3, 3),
        "hz": round(1e3 / med, 1),
        "infer_ms_median": round(med_full, 3),
        "infer_hz": round(1e3 / med_full, 1),
        "threads": args.threads, "runs": args.runs, "parameters": counts["total"],
        "image_size": policy.cfg.image_size, "cameras": len(policy.cfg.cameras),
    }, args.json)


def bench_train(args: argparse.Namespace) -> int:
    import tempfile

    import torch

    from pivla.data.synthetic import make_synthetic_dataset
    from pivla.model.config import ModelConfig
    from pivla.training.trainer import TrainConfig, Trainer

    torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as tmp:
        cfg = ModelConfig()
        cfg.backbone.grid_tokens = args.grid_tokens
        make_synthetic_dataset(f"{tmp}/data", episodes_per_goal=4, T=40, size=cfg.image_size)
        tc = TrainConfig(data=f"{tmp}/data", out=f"{tmp}/run", steps=args.steps, batch_size=args.batch_size,
                         model=cfg, progress=False)
        trainer = Trainer(tc)
        trainer._set_values(trainer._state_values(trainer.train_set))
        times = []
        for _ in range(args.steps):
            t = time.perf_counter()
            trainer.train_step()
            times.append(time.perf_counter() - t)
    med = float(np.median(times[3:]))
    return emit({"train_step_s_median": round(med, 4), "samples_per_s": round(args.batch_size / med, 1),
                 "batch_size": args.batch_size, "threads": args.threads, "grid_tokens": args.grid_tokens}, args.json)


def bench_sim(args: argparse.Namespace) -> int:
    if args.env == "tabletop":
        from pivla.envs.tabletop.bench import run_bench
    else:
        from pivla.envs.libero.bench import run_bench
    return emit(run_bench(args), args.json)


def bench_control(args: argparse.Namespace) -> int:
    from pivla.control.bench import run_bench

    return emit(run_bench(args), args.json)


def bench_hf(args: argparse.Namespace) -> int:
    from pivla.model.hf import run_bench

    return emit(run_bench(args), args.json)


def bench_robot(args: argparse.Namespace) -> int:
    from pivla.robot.bench import run_bench

    return emit(run_bench(args), args.json)
