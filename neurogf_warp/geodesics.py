"""Ground-truth geodesic distances and shortest paths on triangle meshes (Warp): the public front.

`geodesic_distances` and `geodesic_paths` are the one-call functions; `GeodesicSolver` (geodesic_solver.py) is the
reusable solver behind them. Every distance is the length of a real surface path (an upper bound of the exact
geodesic distance, within 0.02% of it on average at the defaults; benchmarks/geodesics_notes.md).
"""
from __future__ import annotations

import numpy as np

from .geodesic_solver import DEFAULT_DELTA, DEFAULT_K, PATH_DELTA, GeodesicSolver, load_kernels
from .mesh import Mesh, load_mesh

__all__ = ["geodesic_distances", "geodesic_paths", "GeodesicSolver", "resample_polyline", "load_kernels",
           "DEFAULT_K", "DEFAULT_DELTA", "PATH_DELTA"]


def _sources(mesh: Mesh, sources) -> np.ndarray:
    s = np.asarray(sources)
    if s.ndim > 1:
        raise ValueError("sources must be an int or a 1-D array of vertex indices")
    return np.atleast_1d(mesh.vertex(s)).astype(np.int64)


def geodesic_distances(mesh, sources, device=None, k: int = DEFAULT_K, windows: bool = True,
                       batch: int | None = None, delta: float = DEFAULT_DELTA) -> np.ndarray:
    """Geodesic distances (S, V_input) float32 in the mesh's units from user vertex indices `sources`.

    Unreferenced vertices are NaN, unreachable ones inf. Accuracy: `k` Steiner points per edge and
    `windows` (exact unfolding); every value is an upper bound of the exact distance. `delta`: bucket
    width of the delta-stepping order (speed only; 0 = plain Bellman-Ford).
    """
    m = load_mesh(mesh)
    src = _sources(m, sources)
    solver = GeodesicSolver(m, k=k, windows=windows, device=device, batch=batch, max_rows=len(src),
                            delta=delta)
    d = solver.solve(src) / np.float32(m.scale)
    return m.to_input(d.astype(np.float32))


def resample_polyline(points: np.ndarray, offsets: np.ndarray, m: int) -> np.ndarray:
    """Resample each polyline points[offsets[i]:offsets[i+1]] to m points equally spaced by arc length."""
    T = len(offsets) - 1
    out = np.empty((T, m, 3), dtype=np.float32)
    u = np.linspace(0.0, 1.0, m)
    for i in range(T):
        p = points[offsets[i]: offsets[i + 1]].astype(np.float64)
        if len(p) == 0:
            out[i] = np.nan
            continue
        if len(p) == 1:
            out[i] = p[0]
            continue
        s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))]
        tq = u * s[-1]
        j = np.clip(np.searchsorted(s, tq, side="right") - 1, 0, len(p) - 2)
        seg = s[j + 1] - s[j]
        w = np.where(seg > 0, (tq - s[j]) / np.where(seg > 0, seg, 1.0), 0.0)
        out[i] = p[j] + w[:, None] * (p[j + 1] - p[j])
    return out


def geodesic_paths(mesh, source, targets, m: int | None = None, device=None, k: int = DEFAULT_K,
                   windows: bool = True, delta: float = PATH_DELTA):
    """Shortest surface paths from user vertex `source` to user vertices `targets`, in mesh units.

    Returns a list of (n_i, 3) float64 polylines ordered from the source (empty (0,3) for unreachable
    targets), or a (T, m, 3) array resampled by arc length when m is given (NaN rows if unreachable).
    """
    msh = load_mesh(mesh)
    s = _sources(msh, source)
    if len(s) != 1:
        raise ValueError("geodesic_paths takes one source vertex")
    tg = _sources(msh, targets)
    solver = GeodesicSolver(msh, k=k, windows=windows, device=device, batch=1, delta=delta)
    solver.run(s)
    pts, offs, _ = solver.trace(np.zeros(len(tg), np.int32), tg)
    pts = msh.denormalize(pts)
    if m is not None:
        return resample_polyline(pts, offs, int(m)).astype(np.float64)
    return [pts[offs[i]: offs[i + 1]] for i in range(len(tg))]
