"""``pivla train``, ``pivla ensemble-runs``, ``pivla info``, ``pivla merge-lora`` and ``pivla convert-openvla``."""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro

from pivla.config import from_dict
from pivla.io import read_json
from pivla.training.config import PRESETS, PresetName, TrainConfig
from pivla.training.merge import MergeConfig


@dataclass
class TrainCommand:
    """A training run, with where its defaults come from."""

    run: Annotated[TrainConfig, tyro.conf.arg(name="")] = field(default_factory=TrainConfig)
    preset: PresetName = "default"
    """Named defaults: default is the validated twin recipe; libero: LIBERO's cameras and proprio at 128 px;
    paper: an OpenVLA-style VLM with LoRA 32 and a DINOv2 target (local checkpoints); so101: the SO-101's 80-px
    cameras read for the named cube (FiLM), relative joint targets, 8000 steps."""
    config: str | None = None
    """Start from this JSON config (e.g. a run's config.json) instead of a preset; flags override it."""
    resume: bool = False
    """Continue the run in --out from its last checkpoint, with the config it was started with."""


def train_default(argv: list[str]) -> tuple[TrainCommand, list[str]]:
    """The defaults the flags start from: a preset, a JSON config file, or a resumed run's own config."""
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--preset", choices=sorted(PRESETS), default="default")
    pre.add_argument("--config", default=None)
    pre.add_argument("--resume", action="store_true")
    pre.add_argument("--out", default=None)
    known, _ = pre.parse_known_args(argv)
    base = PRESETS[known.preset]()
    if known.config:
        base = from_dict(TrainConfig, read_json(known.config))
    elif known.resume and known.out and (Path(known.out) / "config.json").exists():
        base = from_dict(TrainConfig, read_json(Path(known.out) / "config.json"))
    return TrainCommand(run=base, preset=known.preset), argv


def train(cmd: TrainCommand) -> int:
    from pivla.training.trainer import train as run_train

    run_dir = run_train(cmd.run, resume=cmd.resume)
    print(f"run saved to {run_dir}")
    return 0


@dataclass
class InfoConfig:
    """Which run to describe."""

    policy: str
    """Run directory."""
    json: bool = False
    """Print one JSON object."""


def info(cfg: InfoConfig) -> int:
    from pivla.policy import load_policy
    from pivla.training import checkpoint as ck

    run = Path(cfg.policy)
    policy = load_policy(run, device="cpu", encoder_runtime="torch")
    members = getattr(policy, "members", [policy])
    lead = getattr(policy, "lead", policy).run_dir  # an ensemble shows its first member's run
    status = read_json(lead / ck.STATUS_FILE) if (lead / ck.STATUS_FILE).exists() else {}
    counts = [m.model.parameter_counts() for m in members]
    data = {
        "run": str(run),
        "members": len(members),
        "config": read_json(lead / ck.CONFIG_FILE),
        "spec": policy.spec.to_dict(),
        "parameters": {k: sum(c[k] for c in counts) for k in counts[0]},
        "vocab_size": len(members[0].text.vocab),
        "status": status,
        "calibration": vars(policy.calibration) if policy.calibration else None,
    }
    if cfg.json:
        print(json.dumps(data, indent=2))
        return 0
    ensemble = f" (an ensemble of {len(members)} runs; the first one's config)" if len(members) > 1 else ""
    print(f"run: {run}{ensemble}")
    print(f"training: step {status.get('step', '?')}/{status.get('steps', '?')} done={status.get('done', '?')} "
          f"elapsed={status.get('elapsed_s', '?')}s")
    if status.get("last"):
        print("last logged: " + ", ".join(f"{k}={v}" for k, v in status["last"].items()))
    print("parameters: " + ", ".join(f"{k}={v:,}" for k, v in data["parameters"].items()))
    print(f"reads: {data['spec']}")
    print(f"calibration: {data['calibration']}")
    print("config:")
    print(json.dumps(data["config"], indent=2))
    return 0


@dataclass
class RunEnsembleConfig:
    """Runs of one recipe (trained with different --seed) to serve, evaluate and calibrate as one policy."""

    runs: list[str]
    """Run directories written by pivla train, two or more; their deployed files are copied."""
    out: str
    """Directory to write (must not exist); give it to --policy like a run. Calibrate it for AURD."""


def ensemble_runs(cfg: RunEnsembleConfig) -> int:
    from pivla.policy import load_policy
    from pivla.training.checkpoint import write_run_ensemble

    def load(directory: Path) -> None:  # refuses members that do not fit together, before anything is written
        load_policy(directory, device="cpu", encoder_runtime="torch")

    out = write_run_ensemble(cfg.runs, cfg.out, check=load)
    print(f"ensemble of {len(cfg.runs)} runs saved to {out}; calibrate it before AURD runs it")
    return 0


def merge_lora(cfg: MergeConfig) -> int:
    from pivla.training.merge import merge_run

    print(f"merged run saved to {merge_run(cfg)}")
    return 0


@dataclass
class ConvertOpenVLAConfig:
    """OpenVLA's released checkpoint as plain transformers parts."""

    src: str
    """OpenVLA checkpoint directory (config.json, model.safetensors.index.json, shards, tokenizer,
    preprocessor_config.json)."""
    out: str
    """Directory to write (must not exist); give it to --model.backbone.path."""


def convert_openvla(cfg: ConvertOpenVLAConfig) -> int:
    from pivla.model.openvla import convert_openvla as convert

    print(f"converted OpenVLA checkpoint saved to {convert(cfg.src, cfg.out)}")
    return 0
