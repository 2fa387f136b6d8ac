"""``pivla convert-openvla``: OpenVLA's released checkpoint as plain transformers parts (no timm)."""

from __future__ import annotations

import argparse
import logging


def register(command: str, parser: argparse.ArgumentParser) -> None:
    parser.add_argument("src", help="OpenVLA checkpoint directory (config.json, model.safetensors.index.json, "
                                    "shards, tokenizer, preprocessor_config.json)")
    parser.add_argument("--out", required=True, help="directory to write (must not exist); give it to "
                                                     "--backbone.path")
    parser.set_defaults(func=convert)


def convert(args: argparse.Namespace) -> int:
    from pivla.model.openvla import convert_openvla

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    out = convert_openvla(args.src, args.out)
    print(f"converted OpenVLA checkpoint saved to {out}")
    return 0
