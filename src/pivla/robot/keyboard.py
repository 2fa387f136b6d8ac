"""Key presses for the interactive commands, from a terminal or from a script.

A key source is any iterable of key names, one per control tick: ``""`` when no key arrived, a printable
character as itself (``"n"``, ``" "``), and ``"enter"``, ``"esc"``, ``"right"``, ``"left"``, ``"up"``,
``"down"``, ``"backspace"`` for the others. ``terminal_keys`` reads them from the terminal in cbreak mode
(arrows arrive as escape sequences and are decoded); tests pass a list instead.

The recording keys are LeRobot's, with letters beside the arrows for terminals that eat them:
right arrow or ``n`` keeps the episode, left arrow or ``r`` redoes it, Esc or ``q`` stops.
"""

from __future__ import annotations

import os
import select
import sys
from collections.abc import Iterator
from enum import StrEnum


class Event(StrEnum):
    """What a control key asks the recording loop to do."""

    KEEP = "keep"  # the episode is done: keep it (as a success)
    KEEP_FAILED = "keep_failed"  # keep it as a failure (a rollout that teaches a value head what failure is)
    REDO = "redo"  # discard the episode and record it again
    STOP = "stop"  # stop; an episode not kept is discarded


CONTROL_KEYS = {"right": Event.KEEP, "n": Event.KEEP, "b": Event.KEEP_FAILED, "left": Event.REDO, "r": Event.REDO,
                "esc": Event.STOP, "q": Event.STOP}
CONTROL_HELP = "right/n: keep the episode  b: keep it as a failure  left/r: redo it  esc/q: stop"

_SEQUENCES = {"[A": "up", "[B": "down", "[C": "right", "[D": "left", "OA": "up", "OB": "down", "OC": "right",
              "OD": "left"}
_NAMED = {"\r": "enter", "\n": "enter", "\x7f": "backspace", "\x08": "backspace", "\t": "tab"}


def event(key: str) -> Event | None:
    """The control event of a key, None for any other key."""
    return CONTROL_KEYS.get(key)


def decode(data: str, more: bool = False) -> tuple[list[str], str]:
    """Key names in ``data`` (what a terminal sent), and what is left of an escape sequence cut off at its end.
    ``more``: bytes may still follow (a lone Esc at the end waits for them instead of counting as Esc)."""
    keys, i = [], 0
    while i < len(data):
        ch = data[i]
        if ch != "\x1b":
            keys.append(_NAMED.get(ch, ch))
            i += 1
            continue
        rest = data[i + 1:]
        if not rest:
            if more:
                return keys, data[i:]
            keys.append("esc")
            i += 1
            continue
        if rest[0] in "[O":
            if len(rest) < 2:
                if more:
                    return keys, data[i:]
                keys.append("esc")
                i += 1
                continue
            j = 1  # CSI: parameters, then one final byte in @..~
            while j < len(rest) and not ("@" <= rest[j] <= "~"):
                j += 1
            if j == len(rest):
                if more:
                    return keys, data[i:]
                keys.append("esc")
                i += 1
                continue
            keys.append(_SEQUENCES.get(rest[0] + rest[j], "esc"))
            i += 2 + j
            continue
        keys.append("esc")
        i += 1
    return keys, ""


def terminal_keys(period_s: float = 0.1, stream=None) -> Iterator[str]:
    """Keys from the terminal, one a tick: waits up to ``period_s`` for a key and yields ``""`` when none came.
    The terminal is in cbreak mode while iterating and restored after (also on Ctrl-C)."""
    import termios
    import tty

    stream = stream or sys.stdin
    if not stream.isatty():
        raise OSError("this command reads single key presses: run it in an interactive terminal")
    fd = stream.fileno()
    old = termios.tcgetattr(fd)
    tty.setcbreak(fd)
    pending: list[str] = []
    partial = ""
    try:
        while True:
            if pending:
                yield pending.pop(0)
                continue
            ready, _, _ = select.select([fd], [], [], period_s)
            if not ready:
                if partial:  # a lone Esc: nothing followed it
                    keys, partial = decode(partial)
                    pending += keys
                    continue
                yield ""
                continue
            data = partial + os.read(fd, 64).decode(errors="replace")
            more = bool(select.select([fd], [], [], 0.03)[0]) or data.endswith("\x1b")
            keys, partial = decode(data, more=more)
            pending += keys
            if not pending and not partial:
                yield ""
    finally:
        termios.tcsetattr(fd, termios.TCSADRAIN, old)

