"""A decimated stand-in ("proxy") of a large mesh, for training distances the fine mesh's solver cannot afford.

On a 2.2M-vertex mesh the geodesic solver gives ~1.2 sources/s on an H100 (docs/performance.md), so a
10-minute budget gets ~100 training sources. The same surface decimated by QSlim to a few hundred thousand
vertices is solved ~10x faster per source. The proxy lives in the fine mesh's normalized frame (same center and
scale), so its rows [xs, ys, zs, xt, yt, zt, d] are training rows of the fine mesh's model as they are. Its
vertices are QSlim's quadric optima moved to the closest point of the fine surface (not snapped to fine
vertices: on the stanford bunny decimated 4x, proxy vertices snapped to fine vertices gave distances 1.0% off on
average and 0.9% too long in the median, the QSlim positions 0.11% off).

The proxy's distances are not the fine mesh's: decimation changes the surface. :func:`proxy_error` measures by
how much, on rows both meshes solved (the held-out test sources, which are always solved on the fine mesh).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from neurogf_warp.mesh.mesh import Mesh, load_mesh, mesh_fingerprint

__all__ = ["proxy_mesh", "proxy_error", "pin_vertices", "Surface", "PROXY_MIN_PAIR"]

# pairs closer than this (normalized units, the unit sphere) are left out of proxy_error: near the source the
# proxy vertex's offset from its fine vertex, not the surface, decides the relative error
PROXY_MIN_PAIR = 0.05


def proxy_mesh(mesh: Mesh, n_vertices: int, device=None) -> tuple[Mesh, "Surface"]:
    """QSlim-decimate ``mesh`` to about ``n_vertices`` vertices, each moved onto the closest point of ``mesh``.

    Returns (proxy, where): ``proxy`` a Mesh with ``mesh``'s center and scale (its normalized coordinates are in
    ``mesh``'s frame), ``where`` the fine face and barycentric weights of each proxy vertex. Raises ValueError
    where QSlim refuses the mesh.
    """
    import fast_simplification

    x = mesh.internal_normalized_vertices
    try:
        pts, tri = fast_simplification.simplify(x, mesh.internal_faces.astype(np.int32),
                                                target_count=max(2 * int(n_vertices), 4))
    except Exception as e:  # noqa: BLE001 - QSlim's own errors (non-manifold input and the like)
        raise ValueError(f"the mesh could not be decimated to {n_vertices} vertices for a proxy: {e}") from e
    where = Surface.of(mesh, np.asarray(pts), device)
    proxy = load_mesh((where.points / mesh.scale + mesh.center, np.asarray(tri, np.int64)), weld=False)
    # the fine mesh's frame, so that rows and distances need no conversion
    proxy = dataclasses.replace(proxy, center=np.asarray(mesh.center, np.float64), scale=float(mesh.scale))
    if len(proxy.internal_vertices) != len(pts):  # QSlim left vertices no face uses: keep the ones the proxy has
        where = where.take(proxy.index)
    return proxy, where


def pin_vertices(proxy: Mesh, where: "Surface", ids: np.ndarray, mesh: Mesh) -> Mesh:
    """``proxy`` with its vertices ``ids`` moved onto their nearest fine vertices (``where`` updated to match), so
    that a source solved on both meshes starts at the same point: otherwise the offset between them (up to half a
    fine edge) is an error of its own, larger than the proxy's on small meshes."""
    ids = np.asarray(ids, np.int64)
    fine = where.nearest_vertex[ids]
    v = proxy.internal_vertices.copy()
    v[ids] = mesh.internal_vertices[fine]
    where.points[ids] = mesh.internal_normalized_vertices[fine]
    where.corners[ids] = fine[:, None]
    where.weights[ids] = (1.0, 0.0, 0.0)
    return dataclasses.replace(proxy, internal_vertices=v, fingerprint=mesh_fingerprint(v, proxy.internal_faces))


@dataclasses.dataclass
class Surface:
    """Points on a mesh: ``points`` (n, 3) normalized frame, ``corners`` (n, 3) the vertex ids of the face each
    lies on, ``weights`` (n, 3) their barycentric weights (``points`` = weights @ vertices[corners])."""

    points: np.ndarray
    corners: np.ndarray
    weights: np.ndarray

    @classmethod
    def of(cls, mesh: Mesh, points: np.ndarray, device=None) -> "Surface":
        """The closest points of ``mesh`` to ``points`` (normalized frame), by Warp's BVH query."""
        import warp as wp

        from neurogf_warp.common.arrays import resolve_device
        from neurogf_warp.kernels.mesh import surface as kernels

        dev = resolve_device(device)
        x = mesh.internal_normalized_vertices.astype(np.float32)
        wm = wp.Mesh(wp.array(x, dtype=wp.vec3, device=dev),
                     wp.array(mesh.internal_faces.reshape(-1).astype(np.int32), dtype=wp.int32, device=dev))
        q = wp.array(np.asarray(points, np.float32), dtype=wp.vec3, device=dev)
        p, f, b = (wp.empty(len(q), dtype=t, device=dev) for t in (wp.vec3, wp.int32, wp.vec3))
        if len(q):
            wp.launch(kernels.snap_points, len(q), inputs=[wm.id, q, 1.0e18], outputs=[p, f, b], device=dev)
        face = f.numpy()
        return cls(p.numpy().astype(np.float64), mesh.internal_faces[face].astype(np.int64),
                   b.numpy().astype(np.float64))

    def take(self, idx) -> "Surface":
        return Surface(self.points[idx], self.corners[idx], self.weights[idx])

    @property
    def nearest_vertex(self) -> np.ndarray:
        """(n,) int64 the face corner of largest weight: the mesh vertex standing for each point."""
        return np.take_along_axis(self.corners, np.argmax(self.weights, axis=1)[:, None], 1)[:, 0]

    def values(self, rows: np.ndarray) -> np.ndarray:
        """(T, n) ``rows`` (T, V) per-vertex values interpolated at the points (linear on each face)."""
        r = np.asarray(rows, np.float64)
        return np.einsum("tnk,nk->tn", r[:, self.corners], self.weights)


def proxy_error(proxy_rows: np.ndarray, fine_rows: np.ndarray, where: Surface) -> dict:
    """How far the proxy's distances are from the fine mesh's, on the same sources.

    proxy_rows : (T, Vp) distances on the proxy; fine_rows : (T, V) on the fine mesh, normalized units, read at
    each proxy vertex by linear interpolation on its fine face. Pairs nearer than ``PROXY_MIN_PAIR`` or unreachable
    on either mesh are left out.

    Returns ``row_error`` of the two.
    """
    return row_error(proxy_rows, where.values(fine_rows))


def row_error(rows: np.ndarray, reference: np.ndarray) -> dict:
    """Relative errors of distance rows against reference rows of the same shape, over the pairs both reach and
    the reference puts at least ``PROXY_MIN_PAIR`` apart.

    Returns {"pairs", "mre", "p99", "max", "bias"}: |rows - reference| / reference (fractions, not %), ``bias``
    the median of rows / reference - 1 (negative: ``rows`` are shorter); Nones when no pair counts.
    """
    a = np.asarray(rows, np.float64)
    b = np.asarray(reference, np.float64)
    ok = np.isfinite(a) & np.isfinite(b) & (b > PROXY_MIN_PAIR)
    if not ok.any():
        return {"pairs": 0, "mre": None, "p99": None, "max": None, "bias": None}
    r = (a[ok] - b[ok]) / b[ok]
    e = np.abs(r)
    return {"pairs": int(ok.sum()), "mre": float(e.mean()), "p99": float(np.percentile(e, 99)),
            "max": float(e.max()), "bias": float(np.median(r))}
