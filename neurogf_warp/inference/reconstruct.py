"""A triangle mesh from the SDF head: the network's zero level set by marching cubes in Warp (CPU or GPU)."""
from __future__ import annotations

import numpy as np
import warp as wp
import warp.geometry

from neurogf_warp.common.arrays import resolve_device
from neurogf_warp.common.checks import InputError
from neurogf_warp.inference.queries import sdf
from neurogf_warp.inference.state import DOMAIN
from neurogf_warp.model.model import Model

__all__ = ["reconstruct", "surface_distances"]

MAX_RESOLUTION = 1024  # 1024^3 float32 samples are 4 GiB: the largest grid one call builds
PAD_CELLS = 2  # grid cells beyond the mesh's box on every side, so the surface closes inside the grid


def reconstruct(model: Model, resolution: int = 256, level: float = 0.0, device=None, precision: str = "auto",
                chunk: int = 1 << 21):
    """Extract the SDF head's zero level set as a triangle mesh (marching cubes, Warp kernels).

    The grid spans the mesh's bounding box (the model's domain cube when no mesh frame is known) plus two cells
    on every side, with ``resolution`` samples along its longest side and cubic cells.

    Parameters
    ----------
    model : Model
        A per-mesh model (with or without its mesh).
    resolution : int
        Samples along the grid's longest side, 8 .. 1024. Memory: 4 bytes per sample.
    level : float
        The iso-value in mesh units (0: the surface; > 0 an offset surface outside it).
    device, precision
        As for ``sdf``.
    chunk : int
        SDF points evaluated per launch.

    Returns
    -------
    vertices : (N, 3) float64, mesh coordinates (the normalized frame for a model without one)
    faces : (M, 3) int64
        Triangles, outward facing. The mesh is closed where the zero level set lies inside the grid.
    """
    if not isinstance(model, Model):
        raise InputError(f"reconstruct needs a per-mesh model, got {type(model).__name__}")
    if isinstance(resolution, bool) or not isinstance(resolution, (int, np.integer)) or not \
            8 <= resolution <= MAX_RESOLUTION:
        raise InputError(f"resolution must be an integer from 8 to {MAX_RESOLUTION}, got {resolution!r}")
    if isinstance(level, (bool, np.bool_)) or not isinstance(level, (int, float, np.integer, np.floating)) or \
            not np.isfinite(level):
        raise InputError(f"level must be a finite number of mesh units, got {level!r}")
    dev = resolve_device(device)
    lo, hi = _box(model)
    step = float((hi - lo).max()) / (int(resolution) - 1 - 2 * PAD_CELLS)
    lo = lo - PAD_CELLS * step
    dims = np.maximum(np.ceil((hi + PAD_CELLS * step - lo) / step).astype(int) + 1, 2)
    # stay inside the model's domain: sdf refuses points beyond it
    if model.in_mesh_frame:
        dom_lo = model.center - DOMAIN / model.scale
    else:
        dom_lo = np.full(3, -DOMAIN)
    dom_hi = 2 * (model.center if model.in_mesh_frame else 0) - dom_lo
    lo = np.maximum(lo, dom_lo)
    dims = np.minimum(dims, np.floor((dom_hi - lo) / step).astype(int) + 1)
    nx, ny, nz = (int(d) for d in dims)
    field = np.empty(nx * ny * nz, dtype=np.float32)
    xs, ys, zs = (lo[a] + step * np.arange(n) for a, n in enumerate((nx, ny, nz)))
    # x-major order, matching the (nx, ny, nz) array marching cubes reads
    for k0 in range(0, nx * ny * nz, chunk):
        idx = np.arange(k0, min(k0 + chunk, nx * ny * nz))
        i, rem = np.divmod(idx, ny * nz)
        j, k = np.divmod(rem, nz)
        pts = np.stack([xs[i], ys[j], zs[k]], 1)
        field[k0:k0 + len(idx)] = sdf(model, pts, device=dev, precision=precision)
    field -= np.float32(level)
    grid = wp.array(field.reshape(nx, ny, nz), dtype=wp.float32, device=dev)
    verts, tris = warp.geometry.IsoSurfaceMarchingCubes.extract(grid, 0.0, lower=tuple(map(float, lo)),
                                           upper=tuple(float(lo[a] + step * (n - 1)) for a, n in
                                                       enumerate((nx, ny, nz))))
    v = verts.numpy().astype(np.float64)
    f = tris.numpy().reshape(-1, 3).astype(np.int64)
    if len(f) and _signed_volume(v, f) < 0:  # outward normals whatever the table's winding
        f = f[:, ::-1].copy()
    return v, f


def _box(model: Model):
    if model.mesh is not None:
        v = model.mesh.internal_vertices
        return v.min(0), v.max(0)
    if model.in_mesh_frame:  # the unit sphere of the normalized frame, in mesh coordinates
        r = 1.0 / model.scale
        return model.center - r, model.center + r
    return np.full(3, -1.0), np.full(3, 1.0)


def _signed_volume(v: np.ndarray, f: np.ndarray) -> float:
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def surface_distances(vertices_a, faces_a, vertices_b, faces_b, samples: int = 100_000, seed: int = 0) -> dict:
    """Chamfer-L1 and Hausdorff distance between two triangle meshes, from area-uniform surface samples.

    Each mesh gets ``samples`` points; each point's distance to the nearest point of the other mesh's samples
    is measured (a k-d tree), which overestimates the true surface distance by at most about the samples'
    spacing.

    Returns
    -------
    dict with ``chamfer_l1`` (the mean of both directions' mean distances), ``hausdorff`` (the larger of both
    directions' largest distances), in the meshes' units, and ``samples``; both None (with a ``note``) when a
    mesh has no triangles.
    """
    import trimesh
    from scipy.spatial import cKDTree

    a = trimesh.Trimesh(np.asarray(vertices_a), np.asarray(faces_a), process=False)
    b = trimesh.Trimesh(np.asarray(vertices_b), np.asarray(faces_b), process=False)
    if len(a.faces) == 0 or len(b.faces) == 0 or a.area <= 0 or b.area <= 0:
        return {"chamfer_l1": None, "hausdorff": None, "samples": 0, "note": "a mesh without triangles of area"}
    pa = trimesh.sample.sample_surface(a, samples, seed=seed)[0]
    pb = trimesh.sample.sample_surface(b, samples, seed=seed + 1)[0]
    dab = cKDTree(pb).query(pa)[0]
    dba = cKDTree(pa).query(pb)[0]
    return {"chamfer_l1": float(0.5 * (dab.mean() + dba.mean())), "hausdorff": float(max(dab.max(), dba.max())),
            "samples": int(samples)}
