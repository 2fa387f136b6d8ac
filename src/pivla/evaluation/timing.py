"""Wall time per stage of a resumable run, kept in the run's ``timings.json`` across interruptions."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

from pivla.io import atomic_write_json, read_json

T = TypeVar("T")


class StageTimes:
    """Seconds per stage in ``path``, summed over the invocations of a resumable run. The running stage's time
    is saved every ``every`` seconds as well, so a run killed mid-stage (a job that outlives no session) loses
    at most that much of it."""

    def __init__(self, path: Path, every: float = 60.0) -> None:
        self.path, self.every = path, every
        self.times: dict[str, float] = read_json(path) if path.exists() else {}
        self._lock = threading.Lock()

    def run(self, name: str, fn: Callable[[], T]) -> T:
        """``fn()``, its wall time added to stage ``name``."""
        before, start, stop = self.times.get(name, 0.0), time.monotonic(), threading.Event()

        def save() -> None:
            with self._lock:
                self.times[name] = round(before + time.monotonic() - start, 1)
                atomic_write_json(self.path, self.times)

        def tick() -> None:
            while not stop.wait(self.every):
                save()

        ticker = threading.Thread(target=tick, name=f"time of {name}", daemon=True)
        ticker.start()
        try:
            return fn()
        finally:
            stop.set()
            ticker.join()
            save()
