"""A command tree whose leaves are (config dataclass, function) pairs, parsed by tyro.

A leaf module exposes, for each command ``NAME``, a function ``NAME(cfg) -> int | None`` whose first
parameter is annotated with its config dataclass, and optionally ``NAME_default() -> cfg`` (the defaults,
e.g. from a preset chosen by a flag it reads first). Help comes from the config's docstrings.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import logging
import os
import sys
import typing
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import tyro

TYRO_CONFIG = (tyro.conf.CascadeSubcommandArgs,)  # a subcommand's options may follow its choice
# What bad input raises (a missing or corrupt file, a wrong shape, NaN, an impossible setting): the message
# names the problem, so a user sees that one line; a traceback is for --debug. Other exceptions are bugs and
# keep theirs.
USER_ERRORS = (ValueError, OSError)
DEBUG_ENV = "PIVLA_DEBUG"


@dataclass(frozen=True)
class Command:
    module: str
    function: str
    help: str


@dataclass(frozen=True)
class Group:
    help: str
    commands: dict[str, Command | Group]


def _usage(tree: dict[str, Command | Group], prog: str, intro: str = "") -> str:
    width = max(len(name) for name in tree)
    lines = [intro] if intro else []
    lines += [f"usage: {prog} COMMAND [--help] ...", "", "commands:"]
    lines += [f"  {name.ljust(width)}  {node.help}" for name, node in tree.items()]
    if not intro:
        return "\n".join(lines)
    return "\n".join(lines + ["", f"{prog} --version prints the version."])


def run(tree: dict[str, Command | Group], argv: list[str], prog: str, intro: str = "") -> int:
    """Find the command named by the leading words of ``argv``, parse the rest into its config, call it."""
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage(tree, prog, intro))
        return 0 if argv else 2
    name, rest = argv[0], argv[1:]
    if name not in tree:
        print(f"{prog}: unknown command {name!r}\n\n{_usage(tree, prog)}", file=sys.stderr)
        return 2
    node = tree[name]
    if isinstance(node, Group):
        return run(node.commands, rest, f"{prog} {name}", node.help)
    fn, cls = command_target(node)
    default_fn = getattr(importlib.import_module(node.module), f"{node.function}_default", None)
    default, rest = default_fn(rest) if default_fn is not None else (None, rest)
    cfg = tyro.cli(cls, args=_choice_shorthand(cls, rest), prog=f"{prog} {name}",
                   description=_description(fn, node), default=default, config=TYRO_CONFIG)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        return int(fn(cfg) or 0)
    except USER_ERRORS as e:
        if debugging():
            raise
        raise SystemExit(f"{prog} {name}: {type(e).__name__}: {e}\n"
                         f"(--debug or {DEBUG_ENV}=1 shows the traceback)") from None


def debugging() -> bool:
    """Whether user errors show their traceback (``pivla --debug ...`` sets the variable)."""
    return os.environ.get(DEBUG_ENV, "") not in ("", "0")


def command_target(node: Command) -> tuple[Callable[[Any], int | None], type]:
    """The function a command calls and the config class its arguments are parsed into (its first
    parameter's type)."""
    fn = getattr(importlib.import_module(node.module), node.function)
    return fn, typing.get_type_hints(fn)[next(iter(inspect.signature(fn).parameters))]


def _choice_fields(cls: type) -> dict[str, set[str]]:
    """Fields typed as a union of config dataclasses (tyro's subcommands), with the names of the choices."""
    out = {}
    for f in dataclasses.fields(cls):
        args = typing.get_args(typing.get_type_hints(cls)[f.name])
        kinds = {getattr(a, "kind", None) for a in args if dataclasses.is_dataclass(a)}
        if len(args) > 1 and None not in kinds and kinds:
            out[f.name] = kinds
    return out


def _choice_shorthand(cls: type, argv: list[str]) -> list[str]:
    """``--executor fixed`` for tyro's ``executor:fixed`` (the choice first, so its options can follow)."""
    choices = _choice_fields(cls) if dataclasses.is_dataclass(cls) else {}
    picked, rest, i = [], [], 0
    while i < len(argv):
        flag = argv[i].removeprefix("--").replace("-", "_")
        if argv[i].startswith("--") and flag in choices and i + 1 < len(argv):
            if argv[i + 1] not in choices[flag]:
                raise SystemExit(f"--{flag}: choose one of {', '.join(sorted(choices[flag]))}, not {argv[i + 1]!r}")
            picked.append(f"{flag}:{argv[i + 1]}")
            i += 2
            continue
        rest.append(argv[i])
        i += 1
    return picked + rest


def _description(fn: Callable, node: Command) -> str:
    doc = inspect.getdoc(fn)
    return f"{node.help}.\n\n{doc}" if doc else node.help
