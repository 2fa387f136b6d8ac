"""Pieces of LeRobot v3 files that the tests write in the exact upstream format."""

from fractions import Fraction
from pathlib import Path

import av
import numpy as np
import pyarrow as pa

from pivla.data.lerobot.writer import open_encoder


def fixed_list(x) -> pa.Array:
    """Rows of a (T, D) array as the fixed_size_list<float>[D] column lerobot writes for state and action."""
    x = np.ascontiguousarray(x, np.float32)
    return pa.FixedSizeListArray.from_arrays(pa.array(x.ravel()), x.shape[1])


def encode_video(path: Path, frames: np.ndarray, fps: int, codec: str) -> None:
    """(T, H, W, 3) frames into one mp4, frame i at i / fps (episodes back to back, as lerobot concatenates them)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(path), "w") as c:
        s = c.add_stream(codec, rate=fps, options={"g": "2", "crf": "20"})
        s.width, s.height, s.pix_fmt = frames.shape[2], frames.shape[1], "yuv420p"
        open_encoder(s)
        for i, im in enumerate(frames):
            f = av.VideoFrame.from_ndarray(np.ascontiguousarray(im), format="rgb24")
            f.pts, f.time_base = i, Fraction(1, fps)
            for p in s.encode(f):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
