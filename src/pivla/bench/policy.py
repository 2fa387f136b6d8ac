"""Speed of the policy itself: batch-1 inference and training samples per second, and the default
untrained policy every speed benchmark can run without a trained run (speed does not depend on weights)."""

from __future__ import annotations

import dataclasses
import tempfile
import time
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch

from pivla.data.normalize import ActionStats, NormStats, StandardStats
from pivla.data.synthetic import make_synthetic_dataset
from pivla.data.text import WordTokenizer
from pivla.model.cms import CMSModel
from pivla.policy import Policy, load_policy
from pivla.training.config import PRESETS, LossConfig, TrainConfig, with_twin_inputs
from pivla.training.trainer import Trainer

INSTRUCTION = "pick up the red block and move it to the left of the table"


def default_policy(run: str | None = None, encoder_runtime: str = "auto") -> Policy:
    """A trained policy, or the recipe's model with random weights."""
    if run:
        return load_policy(run, device="cpu", encoder_runtime=encoder_runtime)
    cfg = with_twin_inputs(TrainConfig().model)
    text = WordTokenizer.build([INSTRUCTION], cfg.max_text_len)
    layout = [("ee_pos", 3), ("ee_ori", 3), ("gripper_states", 2)]
    stats = NormStats(ActionStats([-1.0] * 7, [1.0] * 7),
                      StandardStats([0.0] * cfg.proprio_dim, [1.0] * cfg.proprio_dim), proprio_layout=layout)
    return Policy(CMSModel(cfg, len(text.vocab)), stats, text, encoder_runtime=encoder_runtime)


def random_obs(policy: Policy, rng: np.random.Generator) -> dict:
    """An observation of the policy's spec with random pictures and zero proprioception."""
    s = policy.spec.image_size
    obs = {c: rng.integers(0, 255, (s, s, 3), dtype=np.uint8) for c in policy.spec.cameras}
    obs.update({k: np.zeros(max(n, 1), np.float32) for k, n in policy.spec.proprio})
    obs["instruction"] = INSTRUCTION
    return obs


@dataclass
class InferBenchConfig:
    """Batch-1 inference of a policy."""

    policy: str | None = None
    """A trained run directory (default: the recipe's model, random weights)."""
    runs: int = 100
    """Timed calls."""
    warmup: int = 20
    """Untimed calls first."""
    threads: int = 2
    """Torch intra-op threads."""


def run_infer_bench(cfg: InferBenchConfig) -> dict:
    torch.set_num_threads(cfg.threads)
    policy = default_policy(cfg.policy)
    members = getattr(policy, "members", [policy])  # an ensemble of runs runs each member's forward pass
    obs = random_obs(policy, np.random.default_rng(0))
    inputs = [m.model_inputs([obs]) for m in members]
    times, full = [], []
    with torch.inference_mode():
        for i in range(cfg.warmup + cfg.runs):
            t = time.perf_counter()
            for member, x in zip(members, inputs):
                member.model(x)
            dt = time.perf_counter() - t
            t = time.perf_counter()
            policy.infer(obs)
            dt_full = time.perf_counter() - t
            if i >= cfg.warmup:
                times.append(dt)
                full.append(dt_full)
    med, med_full = float(np.median(times)) * 1e3, float(np.median(full)) * 1e3
    return {
        "forward_ms_median": round(med, 3),
        "forward_ms_p90": round(float(np.percentile(times, 90)) * 1e3, 3),
        "hz": round(1e3 / med, 1),
        "infer_ms_median": round(med_full, 3),
        "infer_hz": round(1e3 / med_full, 1),
        "threads": cfg.threads, "runs": cfg.runs, "members": len(members),
        "parameters": sum(m.model.parameter_counts()["total"] for m in members),
        "image_size": policy.spec.image_size, "cameras": len(policy.spec.cameras),
    }


@dataclass
class TrainBenchConfig:
    """Training speed of the recipe's model on synthetic data."""

    steps: int = 30
    """Timed training steps (the first three are left out)."""
    batch_size: int = 32
    """Samples per step (the recipe's)."""
    grid_tokens: bool = False
    """The grid-token backbone instead of pooled tokens."""
    threads: int = 2
    """Torch intra-op threads."""
    preset: Literal["default", "libero"] = "default"
    """The training preset whose model is timed (libero: two cameras at 128 px)."""
    mixed_precision: Literal["no", "bf16", "fp16"] = "no"
    """Autocast precision (bf16 runs on CPUs with AVX-512 BF16 or AMX at speed, emulated elsewhere)."""
    loss: LossConfig = field(default_factory=LossConfig)
    """The objective's terms (e.g. ``--loss.no-use-sp --loss.no-use-rl --loss.no-use-recon`` times IL only)."""
    ema_decay: float | None = None
    """The weight average's decay (None: the preset's; 0: off), to time its update."""


def run_train_bench(cfg: TrainBenchConfig) -> dict:
    torch.set_num_threads(cfg.threads)
    with tempfile.TemporaryDirectory() as tmp:
        tc = dataclasses.replace(PRESETS[cfg.preset](), data=f"{tmp}/data", out=f"{tmp}/run", steps=cfg.steps,
                                 batch_size=cfg.batch_size, progress=False, mixed_precision=cfg.mixed_precision,
                                 loss=cfg.loss)
        if cfg.ema_decay is not None:
            tc = dataclasses.replace(tc, ema_decay=cfg.ema_decay)
        tc.model.backbone.grid_tokens = cfg.grid_tokens
        make_synthetic_dataset(f"{tmp}/data", episodes_per_goal=4, T=40, size=tc.model.image_size)
        trainer = Trainer(tc)
        trainer._set_values(trainer._state_values(trainer.train_set))
        times = []
        for _ in range(cfg.steps):
            t = time.perf_counter()
            trainer.train_step()
            times.append(time.perf_counter() - t)
        t = time.perf_counter()  # the GAE refresh, timed warm: a pass of V over every training frame
        trainer._state_values(trainer.train_set)
        refresh_ms = (time.perf_counter() - t) * 1e3 / sum(len(ep.actions) for ep in trainer.train_set.episodes)
        average_ms = None
        if trainer.average is not None:  # the weight average's update, part of every step above
            t = time.perf_counter()
            for _ in range(20):
                trainer.average.update(trainer.model)
            average_ms = round((time.perf_counter() - t) * 1e3 / 20, 3)
    med = float(np.median(times[3:]))
    return {"train_step_s_median": round(med, 4), "samples_per_s": round(cfg.batch_size / med, 1),
            "value_refresh_ms_per_frame": round(refresh_ms, 3), "weight_average_ms": average_ms,
            "batch_size": cfg.batch_size, "threads": cfg.threads, "grid_tokens": cfg.grid_tokens,
            "preset": cfg.preset, "image_size": tc.model.image_size, "cameras": len(trainer.cfg.model.cameras),
            "mixed_precision": cfg.mixed_precision, "loss": dataclasses.asdict(cfg.loss)}
