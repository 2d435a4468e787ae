"""The ground-truth solver's mesh tables: unique edges, face/edge incidence, and which faces windows may cross.

Built once per solver on the host (numpy), then uploaded as one `SteinerGraph` struct (kernels/geodesic/graph.py).
"""
from __future__ import annotations

import numpy as np

__all__ = ["Topology", "window_faces"]

WINDOW_FACE_MIN_RELATIVE_HEIGHT = 1e-6  # smallest height / longest edge of a face windows may cross
WINDOW_FACE_MIN_HEIGHT = 1e-7  # and smallest height in the normalized frame (float32 positions)


class Topology:
    """Unique edges, face->edge and edge->face tables (numpy), with degenerate faces removed.

    Attributes: faces (F, 3) int32 (faces that repeat a vertex dropped); edges (E, 2) int32, lower vertex first;
    face_edges (F, 3) int32, the edge of local edge le (vertices le, (le + 1) % 3); vertex_face_start /
    vertex_faces and edge_face_start / edge_faces: CSR lists of the faces around each vertex and of every face of
    each edge (in face order); nonmanifold_edges, boundary_edges: counts of edges with three or more faces and
    with one; face_ok (F,) int8: window faces (`window_faces`).
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        f = np.asarray(faces, dtype=np.int64)
        # faces repeating a vertex carry no area and would create zero-length edges
        keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])
        f = f[keep]
        half = np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], axis=1).reshape(-1, 2)
        half = np.sort(half, axis=1)
        edges, inv = np.unique(half, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        self.faces = f.astype(np.int32)
        self.edges = edges.astype(np.int32)
        self.face_edges = inv.reshape(-1, 3).astype(np.int32)
        ne = len(edges)
        counts = np.bincount(inv, minlength=ne)
        self.nonmanifold_edges = int(np.sum(counts > 2))  # edges with three or more faces
        self.boundary_edges = int(np.sum(counts == 1))
        nvtx = len(vertices)
        fo = np.argsort(f.reshape(-1), kind="stable")
        self.vertex_faces = (fo // 3).astype(np.int32)
        self.vertex_face_start = np.r_[0, np.cumsum(np.bincount(f.reshape(-1), minlength=nvtx))].astype(np.int32)
        self.edge_faces = np.argsort(inv, kind="stable").astype(np.int32) // 3
        self.edge_face_start = np.r_[0, np.cumsum(counts)].astype(np.int32)
        self.face_ok = window_faces(vertices, f)

    def to_warp(self, positions: np.ndarray, k: int, windows: bool, device):
        """The `SteinerGraph` struct of these tables on `device`; positions (V, 3) float32, normalized frame."""
        import warp as wp

        from neurogf_warp.kernels.ground_truth.graph import SteinerGraph

        g = SteinerGraph()
        g.nv = len(positions)
        g.k = int(k)
        g.windows = int(bool(windows))
        g.pos = wp.array(np.asarray(positions, dtype=np.float32), dtype=wp.vec3, device=device)
        g.faces = wp.array(self.faces, dtype=int, device=device)
        g.edges = wp.array(self.edges, dtype=int, device=device)
        g.face_edges = wp.array(self.face_edges, dtype=int, device=device)
        g.window_face = wp.array(self.face_ok, dtype=wp.int8, device=device)
        g.vertex_face_start = wp.array(self.vertex_face_start, dtype=int, device=device)
        g.vertex_faces = wp.array(self.vertex_faces, dtype=int, device=device)
        g.edge_face_start = wp.array(self.edge_face_start, dtype=int, device=device)
        g.edge_face_list = wp.array(self.edge_faces, dtype=int, device=device)
        return g


def window_faces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,) int8: 1 where unfolding windows may cross the face, 0 for graph-only faces.

    Unfolding a virtual source across an edge needs the in-plane direction towards the face's third vertex. The
    kernels compute it in float64 from the float32 positions, which define it exactly for any face whose third
    vertex is off the edge's line by more than the positions' rounding; thin faces (needles from split edges,
    slivers) are crossed like any other. Faces at the rounding level (zero area, coincident or collinear vertices)
    keep only their graph edges (always real segments): there the direction is noise, and the unfolded source
    would land anywhere. A face is kept for windows when its smallest height (2 area / longest edge) is at least
    1e-6 of its longest edge and 1e-7 absolute (pass the float32 positions the kernels use, in the normalized
    unit-sphere frame, where 1e-7 is about two float32 steps)."""
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0:
        return np.zeros(0, np.int8)
    p = np.asarray(vertices, dtype=np.float64)[f]
    area2 = np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    elen = np.linalg.norm(p - p[:, [1, 2, 0]], axis=2)
    lmax = elen.max(axis=1)
    hmin = area2 / np.maximum(lmax, 1e-300)
    ok = (hmin >= WINDOW_FACE_MIN_RELATIVE_HEIGHT * lmax) & (hmin >= WINDOW_FACE_MIN_HEIGHT) & np.isfinite(hmin)
    return ok.astype(np.int8)
