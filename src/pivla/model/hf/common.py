"""Local checkpoint directories: pivla reads Hugging Face checkpoints from disk and never downloads."""

from __future__ import annotations

import os
from pathlib import Path


def check_local_dir(path: str | os.PathLike, what: str) -> Path:
    """A local checkpoint directory with a config.json; a clear error otherwise (we never download)."""
    if not path:
        raise ValueError(f"{what}: no local checkpoint directory given")
    p = Path(path).expanduser()
    if not p.is_dir():
        raise FileNotFoundError(f"{what}: {p} is not a directory (give a local checkpoint; nothing is downloaded)")
    if not (p / "config.json").is_file():
        raise FileNotFoundError(f"{what}: {p} has no config.json (not a Hugging Face checkpoint directory)")
    return p
