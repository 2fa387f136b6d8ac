"""``pivla train`` and ``pivla info``."""

from __future__ import annotations

import argparse
import json
import logging


def register(command: str, parser: argparse.ArgumentParser) -> None:
    if command == "info":
        parser.add_argument("run", help="run directory")
        parser.add_argument("--json", action="store_true", help="print one JSON object")
        parser.set_defaults(func=info)
        return
    from pivla.config import add_config_args
    from pivla.training.trainer import TrainConfig

    parser.add_argument("--resume", action="store_true", help="continue from the run's last checkpoint")
    parser.add_argument("--config", help="JSON config file to start from (flags override it)")
    add_config_args(parser, TrainConfig)
    parser.set_defaults(func=train)


def train(args: argparse.Namespace) -> int:
    from pathlib import Path

    from pivla import config as cfgmod
    from pivla.training import checkpoint as ck
    from pivla.training.trainer import TrainConfig, train as run_train

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    base = None
    if args.config:
        base = cfgmod.from_dict(TrainConfig, ck.read_json(Path(args.config)))
    out = vars(args).get("cfg:out")
    if args.resume and base is None and out and (Path(out) / ck.CONFIG_FILE).exists():
        base = ck.read_run_config(Path(out))
    cfg = cfgmod.build_config(TrainConfig, args, base)
    run_dir = run_train(cfg, resume=args.resume)
    print(f"run saved to {run_dir}")
    return 0


def info(args: argparse.Namespace) -> int:
    from pathlib import Path

    from pivla import load_policy
    from pivla.training import checkpoint as ck

    run = Path(args.run)
    policy = load_policy(run, device="cpu", encoder_runtime="torch")
    status = ck.read_json(run / ck.STATUS_FILE) if (run / ck.STATUS_FILE).exists() else {}
    data = {
        "run": str(run),
        "config": ck.read_json(run / ck.CONFIG_FILE),
        "parameters": policy.model.parameter_counts(),
        "latent_dim": policy.model.latent_dim,
        "vocab_size": len(policy.text.vocab),
        "status": status,
        "calibration": vars(policy.calibration) if policy.calibration else None,
    }
    if args.json:
        print(json.dumps(data, indent=2))
        return 0
    print(f"run: {run}")
    st = status or {}
    print(f"training: step {st.get('step', '?')}/{st.get('steps', '?')} done={st.get('done', '?')} "
          f"elapsed={st.get('elapsed_s', '?')}s")
    if st.get("last"):
        print("last logged: " + ", ".join(f"{k}={v}" for k, v in st["last"].items()))
    print("parameters: " + ", ".join(f"{k}={v:,}" for k, v in data["parameters"].items()))
    print(f"calibration: {data['calibration']}")
    print("config:")
    print(json.dumps(data["config"], indent=2))
    return 0
