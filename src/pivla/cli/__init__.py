"""The ``pivla`` command line. Each subcommand lives in its own module exposing ``register(subparsers)``;
modules are imported only when their command is used, so ``pivla robot ...`` never imports torch models
and ``pivla train`` never imports MuJoCo."""

from __future__ import annotations

import argparse
import importlib
import sys

# command -> (module, one-line help). The module's register() adds the parser and sets func.
COMMANDS: dict[str, tuple[str, str]] = {
    "train": ("pivla.cli.train", "train a CMS policy on a dataset directory"),
    "info": ("pivla.cli.train", "print a run's config, parameter counts and training status"),
    "merge-lora": ("pivla.cli.merge", "merge an hf run's LoRA adapters into its backbone for deployment"),
    "convert-openvla": ("pivla.cli.convert", "convert OpenVLA's released checkpoint for --backbone hf (no timm)"),
    "bench": ("pivla.cli.bench", "benchmarks: infer, sim, control"),
    "collect": ("pivla.cli.collect", "collect expert demonstrations or policy rollouts into a dataset"),
    "export-video": ("pivla.cli.collect", "write MP4 previews of a dataset's episodes"),
    "eval": ("pivla.cli.evaluate", "evaluate a policy with an executor on a task suite"),
    "calibrate": ("pivla.cli.evaluate", "calibrate AURD thresholds on validation data"),
    "ablate": ("pivla.cli.evaluate", "run the paper's ablation tables on the simulator"),
    "report": ("pivla.cli.evaluate", "write report.md with plots for an evaluation directory"),
    "demo": ("pivla.cli.demo", "the main job: collect, train, calibrate, evaluate, report"),
    "robot": ("pivla.cli.robot", "the real arm: firmware board, calibration, teleop, recording, control"),
}


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(prog="pivla", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_, help_) in COMMANDS.items():
        sub.add_parser(name, help=help_, add_help=False)
    if not argv or argv[0] in ("-h", "--help") or argv[0] not in COMMANDS:
        parser.parse_args(argv or ["--help"])
        return 2
    command = argv[0]
    module = importlib.import_module(COMMANDS[command][0])
    cmd_parser = argparse.ArgumentParser(prog=f"pivla {command}", description=COMMANDS[command][1])
    module.register(command, cmd_parser)
    args = cmd_parser.parse_args(argv[1:])
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
