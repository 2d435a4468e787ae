"""How a mesh's pieces hang together: patches that share edges, and patches that meet only at single vertices."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from neurogf_warp.mesh.mesh import Mesh

__all__ = ["VertexJoins", "edge_patches", "vertex_joins"]


def edge_patches(faces: np.ndarray) -> tuple[int, np.ndarray]:
    """Edge-connected patches: faces are in one patch when a chain of shared edges links them.

    Parameters
    ----------
    faces : (F, 3) int

    Returns
    -------
    n : int
        Number of patches.
    labels : (F,) int32
        The patch of each face.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    F = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(F) == 0:
        return 0, np.zeros(0, dtype=np.int32)
    e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    fid = np.tile(np.arange(len(F)), 3)
    key = e[:, 0] * (int(F.max()) + 1) + e[:, 1]
    order = np.argsort(key, kind="stable")
    k, f = key[order], fid[order]
    same = k[1:] == k[:-1]  # consecutive corners of one edge: their faces share it
    g = coo_matrix((np.ones(int(same.sum()), dtype=np.int8), (f[:-1][same], f[1:][same])), shape=(len(F), len(F)))
    n, labels = connected_components(g, directed=False)
    return int(n), labels.astype(np.int32)


@dataclass
class VertexJoins:
    """Pieces of a mesh that touch only at single vertices.

    Attributes
    ----------
    patches : int
        Edge-connected patches in the mesh.
    joined_patches : int
        Patches that share a connected component with another patch (reached from it only through vertices).
    pinch_vertices : int
        Vertices used by faces of two or more patches.
    coincident_vertices : int
        Vertices that lie exactly on another vertex of a different patch (seams stored twice: welding joins them).
    """

    patches: int
    joined_patches: int
    pinch_vertices: int
    coincident_vertices: int

    @property
    def any(self) -> bool:
        return self.joined_patches > 0


def vertex_joins(mesh: Mesh) -> VertexJoins:
    """Find patches joined only at single vertices (geodesics between them must pass through those vertices)."""
    n, labels = edge_patches(mesh.internal_faces)
    comp_of_patch = np.zeros(max(n, 1), dtype=np.int64)
    comp_of_patch[labels] = mesh.internal_components[mesh.internal_faces[:, 0]]
    per_comp = np.bincount(comp_of_patch[:n], minlength=mesh.n_components) if n else np.zeros(0, np.int64)
    joined = int(per_comp[per_comp > 1].sum())
    if joined == 0:
        return VertexJoins(n, 0, 0, 0)
    # a vertex used by faces of several patches
    corner_patch = np.repeat(labels, 3)
    corner_vertex = mesh.internal_faces.reshape(-1)
    pairs = np.unique(np.stack([corner_vertex, corner_patch], 1), axis=0)
    pinch = int(np.count_nonzero(np.bincount(pairs[:, 0], minlength=len(mesh.internal_vertices)) > 1))
    # vertices of one patch lying exactly on a vertex of another: a seam that welding would close
    v_patch = np.full(len(mesh.internal_vertices), -1, dtype=np.int64)
    v_patch[pairs[:, 0]] = pairs[:, 1]
    _, first, inv = np.unique(mesh.internal_vertices + 0.0, axis=0, return_index=True, return_inverse=True)
    inv = inv.reshape(-1)
    group_patches = np.stack([inv, v_patch], 1)
    distinct = np.unique(group_patches, axis=0)
    multi = np.bincount(distinct[:, 0], minlength=len(first)) > 1
    coincident = int(np.count_nonzero(multi[inv]))
    return VertexJoins(n, joined, pinch, coincident)
