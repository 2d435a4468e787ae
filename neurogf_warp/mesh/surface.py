"""Points snapped onto a triangle mesh: the exact closest surface point, its face and barycentric coordinates.

``snap_to_mesh`` answers "where on the mesh is this point" for predicted path points (a surface location a
mesh-processing code can use: face + barycentrics) and for anything else near the surface. The ``wp.Mesh``
(BVH) of a mesh is built once per device and kept while the mesh object lives.
"""
from __future__ import annotations

import weakref

import numpy as np
import warp as wp

from neurogf_warp.common.arrays import Output, _is_torch, as_points, resolve_device
from neurogf_warp.kernels.mesh import surface as kernels
from neurogf_warp.mesh.mesh import Mesh, load_mesh

__all__ = ["snap_to_mesh", "warp_mesh", "as_mesh", "points_of"]

REACH = 1.0e18  # search radius: every point has its closest point within it (its square stays finite in float32)
_BVH: "weakref.WeakKeyDictionary[Mesh, dict]" = weakref.WeakKeyDictionary()


def as_mesh(mesh) -> Mesh:
    """A ``Mesh`` from a Model (its mesh), a Mesh, a trimesh.Trimesh, a (vertices, faces) pair or a file path."""
    if hasattr(mesh, "net") and hasattr(mesh, "mesh"):  # a Model
        if mesh.mesh is None:
            raise ValueError("this model has no mesh: load it with neurogf_warp.load(path, mesh=...) "
                             "or pass the mesh itself")
        return mesh.mesh
    return load_mesh(mesh)


def as_numpy(a) -> np.ndarray:
    """numpy view or copy of a numpy, torch or Warp array (or anything np.asarray takes)."""
    if isinstance(a, wp.array):
        return a.numpy()
    if _is_torch(a):
        return a.detach().cpu().numpy()
    return np.asarray(a)


def points_of(mesh: Mesh | None, x, name: str) -> np.ndarray:
    """Vertex indices (the mesh's numbering) or (S, 3) float points, mesh units -> (S, 3) float64 points."""
    a = as_numpy(x)
    if np.issubdtype(a.dtype, np.integer):
        if mesh is None:
            raise ValueError(f"{name} given as vertex indices, but there is no mesh: pass points instead")
        return mesh.internal_vertices[mesh.vertex(a.reshape(-1))]
    if not np.issubdtype(a.dtype, np.floating):
        raise TypeError(f"{name} must be vertex indices (integers) or points (floats), got dtype {a.dtype}")
    a = a.reshape(1, 3) if a.shape == (3,) else a
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must be vertex indices or points of shape (S, 3), got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains non-finite coordinates (NaN or inf)")
    return a.astype(np.float64)


def warp_mesh(mesh, device=None) -> wp.Mesh:
    """The mesh's ``wp.Mesh`` (vertices in its own coordinates, faces in file order) on ``device``, cached."""
    m = as_mesh(mesh)
    dev = resolve_device(device)
    per_device = _BVH.setdefault(m, {})
    key = str(dev)
    if key not in per_device:
        per_device[key] = wp.Mesh(points=wp.array(m.internal_vertices.astype(np.float32), dtype=wp.vec3, device=dev),
                                  indices=wp.array(m.internal_faces.reshape(-1).astype(np.int32), dtype=wp.int32,
                                                   device=dev))
    return per_device[key]


def _flat_points(x, name: str, dev, check: bool = True):
    """(N, 3) or (N, m, 3) points of any kind -> (wp.array of vec3 (K,), kind, leading shape)."""
    if isinstance(x, wp.array):
        if x.dtype == wp.vec3:
            lead = tuple(x.shape)
            flat = x.contiguous().flatten()
        elif x.dtype == wp.float32 and x.ndim >= 2 and x.shape[-1] == 3:
            lead = tuple(x.shape[:-1])
            flat = x.contiguous().reshape((-1, 3))
        else:
            raise TypeError(f"{name} must be a wp.array of vec3 or of float32 with last dimension 3, got dtype "
                            f"{wp.types.type_repr(x.dtype)} with shape {x.shape}")
    elif _is_torch(x):
        if x.ndim < 2 or x.shape[-1] != 3:
            raise ValueError(f"{name} must have shape (N, 3) or (N, m, 3), got {tuple(x.shape)}")
        lead, flat = tuple(x.shape[:-1]), x.reshape(-1, 3)
    else:
        a = np.asarray(x)
        if a.ndim < 2 or a.shape[-1] != 3:
            raise ValueError(f"{name} must have shape (N, 3) or (N, m, 3), got {a.shape}")
        lead, flat = a.shape[:-1], a.reshape(-1, 3)
    if len(lead) > 2:
        raise ValueError(f"{name} must have shape (N, 3) or (N, m, 3), got {lead + (3,)}")
    pts, kind = as_points(flat, name, dev, check=check)
    return pts, kind, tuple(lead)


def snap_to_mesh(mesh, points, device=None, check: bool = True):
    """Closest points on the mesh, with the face each lies on and its barycentric coordinates.

    Parameters
    ----------
    mesh : Model (its mesh), Mesh, trimesh.Trimesh, (vertices, faces) or a mesh file path
    points : (N, 3) or (N, m, 3) float, mesh units (e.g. paths from ``neurogf_warp.path``); numpy, torch or
        wp.array
    device : Warp device (default: the points' device, else Warp's preferred one)
    check : refuse non-finite points (True); with False a non-finite point gives a NaN point, face -1 and NaN
        weights

    Returns
    -------
    points : (..., 3) float32, mesh units: the exact closest point of the triangle mesh
    face : (...) int32, the face it lies on: a row of the mesh's face list as given (file order)
    bary : (..., 3) float32, weights of that face's three corners, in their order in the face list
        (non-negative, summing to 1): point = sum_k bary[k] * vertices[faces[face, k]]

    The same kind of array as ``points`` comes back, on its device. Ties (a point equally close to two faces,
    e.g. on an edge) pick either face; the point is the same.
    """
    m = as_mesh(mesh)
    dev = resolve_device(device, like=points)
    pts, kind, lead = _flat_points(points, "points", dev, check)
    n = pts.shape[0]
    out = Output(kind, dev)
    res_p, res_f, res_b = out.empty(n, dtype=wp.vec3), out.empty(n, dtype=wp.int32), out.empty(n, dtype=wp.vec3)
    if n:
        from neurogf_warp.common.chunks import in_chunks  # chunks on the CPU: Ctrl-C within about a second

        mid = warp_mesh(m, dev).id
        in_chunks(dev, n, lambda lo, hi: wp.launch(kernels.snap_points, hi - lo, inputs=[mid, pts[lo:hi], REACH],
                                                   outputs=[res_p[lo:hi], res_f[lo:hi], res_b[lo:hi]], device=dev),
                  first=1 << 14, align=1)
    return tuple(_shaped(out.result(a), lead, last) for a, last in ((res_p, (3,)), (res_f, ()), (res_b, (3,))))


def _shaped(a, lead, last):
    shape = tuple(lead) + last
    if isinstance(a, wp.array):
        return a.reshape(tuple(lead)) if a.dtype == wp.vec3 else a.reshape(shape)
    return a.reshape(shape)
