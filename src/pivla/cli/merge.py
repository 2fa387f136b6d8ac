"""``pivla merge-lora``: fold an ``hf`` run's LoRA adapters into its backbone for deployment."""

from __future__ import annotations

import argparse
import logging


def register(command: str, parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", help="run directory trained with --backbone hf and LoRA")
    parser.add_argument("--out", required=True, help="new run directory to write (must not exist)")
    parser.add_argument("--device", default="auto", help="where to merge: auto | cpu | cuda")
    parser.set_defaults(func=merge)


def merge(args: argparse.Namespace) -> int:
    from pivla.model.hf import merge_run

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    out = merge_run(args.run, args.out, device=args.device)
    print(f"merged run saved to {out}")
    return 0
