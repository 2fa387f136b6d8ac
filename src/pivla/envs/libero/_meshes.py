"""Simplified visual meshes for LIBERO's renderer: the same scenes drawn with a fraction of the triangles.

LIBERO's objects and the Panda carry visual meshes of 5-43 k triangles each (about 290 k in a LIBERO-Spatial
scene), and that is what Mesa's software renderer spends a frame on: at 128 px a frame costs about what it
costs at 256 px. Drawn with at most N triangles per mesh (quadric edge collapse of the welded mesh, flat
normals, texture coordinates from the nearest original face), the frames barely change at a policy's
resolution and a step that reads both cameras runs about twice as fast (docs/libero.md, "Speed").

Only the renderer's copy changes: the simplified mesh is written into the model's arrays just long enough to
upload it to the rendering context, then the original is put back, so physics, contacts, the expert's rays
and LIBERO's success check run on the full meshes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pivla.envs.libero._backend import libero

# Every array of a mesh the renderer reads, with the count that sizes it.
_ARRAYS = (("mesh_vert", "mesh_vertadr", "mesh_vertnum"), ("mesh_normal", "mesh_normaladr", "mesh_normalnum"),
           ("mesh_texcoord", "mesh_texcoordadr", "mesh_texcoordnum"))
_FACE_ARRAYS = ("mesh_face", "mesh_facenormal", "mesh_facetexcoord")


@dataclass
class DrawnMesh:
    """A mesh as the renderer draws it: one vertex per face corner (``3 n``), flat normals, texture coordinates
    when the original has them; ``faces[i] = (3i, 3i + 1, 3i + 2)``."""

    verts: np.ndarray
    normals: np.ndarray
    texcoords: np.ndarray | None

    @property
    def n_faces(self) -> int:
        return len(self.verts) // 3


def simplify_mesh(verts: np.ndarray, faces: np.ndarray, texcoords: np.ndarray | None, facetex: np.ndarray | None,
                  max_faces: int) -> DrawnMesh:
    """A mesh of at most about ``max_faces`` triangles that looks like ``(verts, faces)``.

    MuJoCo stores many meshes as triangle soups (three vertices of their own per face), which an edge collapse
    cannot simplify, so corners at the same position are welded first. Each corner of the result takes the
    texture coordinate of the nearest corner of the nearest original face (by centre), which keeps a
    texture's seams where they were."""
    spatial = libero().scipy_spatial
    verts = np.asarray(verts, np.float64)
    faces = np.asarray(faces, np.int64)
    _, weld = np.unique(np.round(verts / 1e-7).astype(np.int64), axis=0, return_inverse=True)
    weld = weld.ravel()
    welded = np.zeros((weld.max() + 1, 3))
    welded[weld] = verts
    wf = weld[faces]
    wf = wf[(wf[:, 0] != wf[:, 1]) & (wf[:, 1] != wf[:, 2]) & (wf[:, 0] != wf[:, 2])]
    v2, f2 = libero().fast_simplification.simplify(welded, wf.astype(np.int32), target_count=int(max_faces))
    corners = v2[f2]  # (n, 3 corners, 3)
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    tex = None
    if texcoords is not None and facetex is not None:
        nearest = spatial.cKDTree(verts[faces].mean(axis=1)).query(corners.mean(axis=1))[1]
        candidates = verts[faces[nearest]]  # (n, 3 original corners, 3)
        tex = np.empty((len(f2), 3, 2))
        for k in range(3):
            pick = np.linalg.norm(candidates - corners[:, k, None, :], axis=2).argmin(axis=1)
            tex[:, k] = texcoords[facetex[nearest, pick]]
        tex = tex.reshape(-1, 2)
    return DrawnMesh(corners.reshape(-1, 3), np.repeat(normals, 3, axis=0), tex)


def _mesh(model: Any, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    va, nv = model.mesh_vertadr[i], model.mesh_vertnum[i]
    fa, nf = model.mesh_faceadr[i], model.mesh_facenum[i]
    verts, faces = model.mesh_vert[va:va + nv], model.mesh_face[fa:fa + nf]
    if not model.mesh_texcoordnum[i]:
        return verts, faces, None, None
    ta, nt = model.mesh_texcoordadr[i], model.mesh_texcoordnum[i]
    return verts, faces, model.mesh_texcoord[ta:ta + nt], model.mesh_facetexcoord[fa:fa + nf]


def simplified_meshes(model: Any, max_faces: int) -> dict[int, DrawnMesh]:
    """The drawn replacement of every mesh with more than ``max_faces`` triangles that fits in the original's
    storage (a mesh that would not, none so far, is drawn in full)."""
    out = {}
    for i in np.flatnonzero(model.mesh_facenum > max_faces):
        drawn = simplify_mesh(*_mesh(model, int(i)), max_faces=max_faces)
        fits = (len(drawn.verts) <= model.mesh_vertnum[i] and len(drawn.verts) <= model.mesh_normalnum[i]
                and (drawn.texcoords is None or len(drawn.texcoords) <= model.mesh_texcoordnum[i]))
        if fits:
            out[int(i)] = drawn
    return out


def upload(model: Any, context: Any, meshes: dict[int, DrawnMesh]) -> None:
    """Put ``meshes`` into the rendering ``context`` (an ``MjrContext`` whose GL context is current), leaving
    ``model``'s own arrays as they were."""
    mujoco = libero().mujoco
    for i, drawn in meshes.items():
        n, nc = drawn.n_faces, len(drawn.verts)
        fa = model.mesh_faceadr[i]
        saved_counts = {count: int(getattr(model, count)[i]) for _, _, count in _ARRAYS}
        saved_counts["mesh_facenum"] = int(model.mesh_facenum[i])
        saved_faces = {name: getattr(model, name)[fa:fa + n].copy() for name in _FACE_ARRAYS}
        values = {"mesh_vert": drawn.verts, "mesh_normal": drawn.normals, "mesh_texcoord": drawn.texcoords}
        saved = {}
        try:
            for name, adr, count in _ARRAYS:
                if values[name] is None:
                    continue
                start = getattr(model, adr)[i]
                saved[name] = getattr(model, name)[start:start + nc].copy()
                getattr(model, name)[start:start + nc] = values[name]
                getattr(model, count)[i] = nc
            corners = np.arange(nc, dtype=np.int32).reshape(n, 3)
            for name in _FACE_ARRAYS:
                if name != "mesh_facetexcoord" or drawn.texcoords is not None:
                    getattr(model, name)[fa:fa + n] = corners
            model.mesh_facenum[i] = n
            mujoco.mjr_uploadMesh(model, context, i)
        finally:
            for name, adr, _ in _ARRAYS:
                if name in saved:
                    start = getattr(model, adr)[i]
                    getattr(model, name)[start:start + nc] = saved[name]
            for name, arr in saved_faces.items():
                getattr(model, name)[fa:fa + n] = arr
            for count, value in saved_counts.items():
                getattr(model, count)[i] = value
