"""Memory and time of loading a training dataset, as ``pivla train`` loads it (``Trainer`` up to its first step).

Run it in a process of its own (``pivla bench data``): the peak resident size is the process's. Resident memory
splits into anonymous pages (what the pictures cost in RAM when held in memory) and file pages (a store on disk,
which the OS writes back and drops under pressure).
"""

from __future__ import annotations

import dataclasses
import resource
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from pivla.training.config import PRESETS, PresetName
from pivla.training.trainer import Trainer


@dataclass
class DataBenchConfig:
    """Loading a dataset for training: peak memory, memory after loading, seconds."""

    data: str
    """Dataset directory (HDF5 files or a LeRobot v3 dataset)."""
    preset: PresetName = "default"
    """Training preset whose cameras, resolution and proprio keys are loaded."""
    image_store: Literal["auto", "memory", "disk"] = "auto"
    """Where the pictures are held (``pivla train --image-store``)."""


def _status_kb(key: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    raise KeyError(key)


def run_data_bench(cfg: DataBenchConfig) -> dict:
    """Figures of one load (JSON-able); Linux, where /proc gives the resident memory's kinds."""
    with tempfile.TemporaryDirectory() as run:
        tc = dataclasses.replace(PRESETS[cfg.preset](), data=cfg.data, out=run, image_store=cfg.image_store,
                                 progress=False)
        t0 = time.perf_counter()
        trainer = Trainer(tc)
        seconds = time.perf_counter() - t0
        sets = [s for s in (trainer.train_set, trainer.val_set) if s is not None]
        frames = sum(len(ep.actions) for s in sets for ep in s.episodes)
        pictures = sum(ep.images.nbytes for s in sets for ep in s.episodes)
        return {
            "episodes": sum(len(s.episodes) for s in sets), "frames": frames,
            "pictures_gb": round(pictures / 1e9, 3), "image_store": cfg.image_store,
            "load_s": round(seconds, 1),
            "peak_rss_gb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6, 3),
            "anon_rss_gb_after": round(_status_kb("RssAnon") / 1e6, 3),
            "file_rss_gb_after": round(_status_kb("RssFile") / 1e6, 3),
        }
