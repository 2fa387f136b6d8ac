"""File input and output below every other layer. Writes are atomic: everything pivla saves goes to a temporary
name in the target folder and is renamed into place, so an interrupted write never leaves half a file and never
clobbers the previous version."""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[str]:
    """Yield a temporary path beside ``path``; on success it replaces ``path`` (mode 0644), on error it is removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp" + path.suffix)
    os.close(fd)
    try:
        yield tmp
        os.chmod(tmp, 0o644)  # mkstemp creates 0600; outputs are meant to be shared
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically, synced to disk before the rename (a crash leaves the old file)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def atomic_write_json(path: str | Path, obj: Any) -> None:
    """``obj`` as indented JSON with sorted keys (stable diffs between runs), atomically."""
    atomic_write_bytes(path, (json.dumps(obj, indent=2, sort_keys=True) + "\n").encode())


def read_json(path: str | Path) -> Any:
    """A JSON file, with an error naming the file when it is missing or corrupt."""
    try:
        return json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: missing") from None
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: corrupt JSON ({e})") from e


@contextlib.contextmanager
def atomic_dir(path: str | Path, prefix: str | None = None) -> Iterator[Path]:
    """Yield a new temporary directory beside ``path``; on success it replaces ``path`` (a reader sees the old
    directory or the complete new one), on error it is removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=path.parent, prefix=prefix or f".{path.name}."))
    try:
        yield tmp
        if path.exists():
            shutil.rmtree(path)
        os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


@contextlib.contextmanager
def exclusive_lock(path: str | Path, what: str) -> Iterator[None]:
    """Hold an advisory lock on ``path`` (created when missing) for the duration: one writer per file or folder
    of results, so that two runs on the same output cannot repeat or interleave each other's work. A second
    holder gets an error naming the path and ``what`` it is at once, instead of waiting."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise RuntimeError(f"{path} is being written by another {what}; wait for it to finish, stop it, "
                               "or write elsewhere") from None
        yield


def open_log(path: str | Path) -> IO[str]:
    """A JSON-lines log opened for appending. After an interrupted write its last line is torn; the torn line
    is ended first, so the next row starts on a line of its own (readers skip the torn one) instead of being
    glued to it and lost."""
    path = Path(path)
    torn = False
    if path.exists() and path.stat().st_size > 0:
        with open(path, "rb") as end:  # the last byte only: a log of traces runs to tens of MB
            end.seek(-1, os.SEEK_END)
            torn = end.read(1) != b"\n"
    f = open(path, "a")
    if torn:
        f.write("\n")
        f.flush()
    return f


def write_mp4(path: str | Path, frames, fps: int) -> None:
    """Encode (T, H, W, 3) uint8 frames (even H and W) as an H.264 MP4 with PyAV, atomically."""
    import av

    with atomic_path(path) as tmp:
        with av.open(tmp, mode="w", format="mp4") as container:
            stream = container.add_stream("libx264", rate=fps)
            stream.height, stream.width = frames.shape[1], frames.shape[2]
            stream.pix_fmt = "yuv420p"
            for frame in frames:
                container.mux(stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")))
            container.mux(stream.encode())
