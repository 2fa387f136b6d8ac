"""Dataclass configs <-> command-line flags and JSON, without magic.

Every field of a (nested) config dataclass becomes a flag ``--section.field`` (``--lr`` for top-level
fields; ``-`` and ``_`` are interchangeable). A nested section with a ``name`` field can also be chosen with
the short form ``--section VALUE`` (``--backbone hf`` == ``--backbone.name hf``), and such a section nested
one level down is also reachable without its parent's prefix (``--backbone.path`` == ``--model.backbone.path``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import types
import typing
from typing import Any, TypeVar

T = TypeVar("T")


def _is_dataclass_type(tp: Any) -> bool:
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


def _field_types(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _parse_scalar(tp: Any, text: str) -> Any:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if text.lower() in ("none", "null", ""):
            return None
        return _parse_scalar(args[0], text)
    if origin in (tuple, list):
        inner = typing.get_args(tp)[0] if typing.get_args(tp) else str
        items = [_parse_scalar(inner, s) for s in text.split(",") if s.strip()]
        return tuple(items) if origin is tuple else items
    if tp is bool:
        if text.lower() in ("1", "true", "yes", "on"):
            return True
        if text.lower() in ("0", "false", "no", "off"):
            return False
        raise argparse.ArgumentTypeError(f"expected a boolean, got {text!r}")
    if tp in (int, float, str):
        return tp(text)
    if typing.get_origin(tp) is typing.Literal:
        if text not in typing.get_args(tp):
            raise argparse.ArgumentTypeError(f"expected one of {typing.get_args(tp)}, got {text!r}")
        return text
    raise TypeError(f"unsupported config field type {tp}")


def add_config_args(parser: argparse.ArgumentParser, cls: type, prefix: str = "", alias: str = "") -> None:
    """Add one flag per (nested) field of ``cls``; values are kept as strings until ``build_config``.
    ``alias`` is the short spelling of ``prefix`` for named sections (see the module docstring)."""
    for f in dataclasses.fields(cls):
        tp = _field_types(cls)[f.name]
        key = f"{prefix}{f.name}"
        short = f"{alias}{f.name}" if alias else ""
        if _is_dataclass_type(tp):
            named = "name" in {g.name for g in dataclasses.fields(tp)}
            if named:
                short = short or (f.name if prefix.count(".") == 1 else "")
                _add_flag(parser, key, f"choose {key}.name", short)
            add_config_args(parser, tp, key + ".", short + "." if short else "")
        else:
            _add_flag(parser, key, f"{tp} (default: {_default_repr(f)})".replace("typing.", ""), short)


def _default_repr(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
        return f.default_factory()  # type: ignore[misc]
    return "required"


def _add_flag(parser: argparse.ArgumentParser, key: str, help_: str, alias: str = "") -> None:
    flags = {f"--{key}", f"--{key.replace('_', '-')}"}
    if alias:
        flags |= {f"--{alias}", f"--{alias.replace('_', '-')}"}
    parser.add_argument(*sorted(flags), dest=f"cfg:{key}", default=None, help=help_)


def build_config(cls: type[T], args: argparse.Namespace, base: T | None = None) -> T:
    """Config from parsed flags, starting from ``base`` (e.g. a saved run's config) or the defaults."""
    overrides = {k[4:]: v for k, v in vars(args).items() if k.startswith("cfg:") and v is not None}
    cfg = base if base is not None else cls()
    return _apply(cfg, overrides, "")


def _apply(cfg: Any, overrides: dict[str, str], prefix: str) -> Any:
    changes = {}
    hints = _field_types(type(cfg))
    for f in dataclasses.fields(cfg):
        key = f"{prefix}{f.name}"
        tp = hints[f.name]
        if _is_dataclass_type(tp):
            sub = getattr(cfg, f.name)
            if key in overrides:
                sub = dataclasses.replace(sub, name=overrides[key])
            changes[f.name] = _apply(sub, overrides, key + ".")
        elif key in overrides:
            try:
                changes[f.name] = _parse_scalar(tp, overrides[key])
            except (ValueError, argparse.ArgumentTypeError) as e:
                raise SystemExit(f"--{key}: {e}") from e
    return dataclasses.replace(cfg, **changes)


def to_dict(cfg: Any) -> dict:
    return dataclasses.asdict(cfg)


def from_dict(cls: type[T], data: dict) -> T:
    """Inverse of ``to_dict``; unknown keys are an error so that a typo in a config file is not ignored."""
    hints = _field_types(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - names
    if unknown:
        raise ValueError(f"{cls.__name__}: unknown config keys {sorted(unknown)}")
    kwargs = {}
    for name, value in data.items():
        tp = hints[name]
        if _is_dataclass_type(tp):
            kwargs[name] = from_dict(tp, value)
        elif isinstance(value, list) and typing.get_origin(tp) is tuple:
            kwargs[name] = tuple(value)
        else:
            kwargs[name] = value
    return cls(**kwargs)


def dumps(cfg: Any) -> str:
    return json.dumps(to_dict(cfg), indent=2, sort_keys=True)
