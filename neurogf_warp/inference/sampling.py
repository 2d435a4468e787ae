"""What users build on a geodesic field: farthest point sampling, geodesic Voronoi cells, the nearest seeds of
every vertex, and isolines of a per-vertex field.

Every per-vertex array taken or returned follows the mesh file's vertex numbering (as ``ssad``); vertices no
face uses get label -1 / distance NaN. Distances come from the model's vertex queries (``distance_matrix``), so a
call costs what those rows cost: on a GPU with bound embeddings one row of a 436K-vertex mesh is about 0.1 ms.
The rows are reduced on the device in chunks of seeds, so memory stays at ``chunk x V`` floats.
"""
from __future__ import annotations

import numpy as np
import torch
import warp as wp

from neurogf_warp.common.arrays import resolve_device
from neurogf_warp.common.checks import InputError
from neurogf_warp.inference.backends import backend_of, bind
from neurogf_warp.inference.queries import distance_matrix
from neurogf_warp.inference.state import query_state
from neurogf_warp.model.model import Model

__all__ = ["farthest_point_sampling", "voronoi", "nearest_seeds", "isolines"]

SEED_CHUNK_BYTES = 1 << 28  # device memory for one chunk of seed rows (each row: 4 V bytes)


def _needs_mesh(model: Model, what: str):
    if not isinstance(model, Model):
        raise InputError(f"{what} needs a per-mesh model (ngf.load('x.ngf') or a released .pth with mesh=...), "
                         f"got {type(model).__name__}")
    if model.mesh is None:
        raise InputError(f"{what} works on the model's mesh, and this model has none: load it with its mesh "
                         "(ngf.load(path, mesh='mesh.obj'))")


def _seed_ids(model: Model, seeds, name: str) -> np.ndarray:
    """Seeds as file vertex indices (S,) int64, checked (integers, in range, used by a face, no repeats)."""
    a = seeds.detach().cpu().numpy() if isinstance(seeds, torch.Tensor) else np.asarray(seeds)
    if a.ndim == 0:
        a = a.reshape(1)
    if a.size == 0:
        raise InputError(f"{name} is empty: give one or more vertex indices")
    if a.ndim != 1 or not np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.bool_):
        raise InputError(f"{name} must be a 1-D list or array of vertex indices (integers), got shape {a.shape} "
                         f"and dtype {a.dtype}")
    model.mesh.vertex(a)  # raises for negative, out-of-range and unused vertices, naming the index
    if len(np.unique(a)) != len(a):
        raise InputError(f"{name} repeats a vertex: each seed must be a different vertex")
    return a.astype(np.int64)


def _rows(model: Model, ids: np.ndarray, dev, precision: str):
    """Distance rows of ``ids`` in chunks that fit SEED_CHUNK_BYTES: yields (offset, (s, n_input) torch rows)."""
    n = model.mesh.n_input
    step = max(1, min(len(ids), SEED_CHUNK_BYTES // (4 * max(n, 1))))
    for k in range(0, len(ids), step):
        yield k, distance_matrix(model, ids[k:k + step], device=dev, output="torch", precision=precision)


def farthest_point_sampling(model: Model, k: int, start: int = 0, device=None, precision: str = "auto",
                            return_distances: bool = False):
    """Farthest point sampling of ``k`` mesh vertices by the field's geodesic distance.

    Starts at vertex ``start``; each next sample is the vertex farthest (geodesically) from the samples so far.
    On a mesh of several parts a part no sample has reached is infinitely far, so every part gets a sample before
    any part gets a second one.

    Parameters
    ----------
    model : Model
        A per-mesh model with its mesh.
    k : int
        Number of samples, 1 .. number of vertices that faces use.
    start : int
        The first sample, a vertex index in the mesh file's numbering.
    device, precision
        As for ``ssad``.
    return_distances : bool
        Also return the final distance of every vertex to its nearest sample.

    Returns
    -------
    (k,) int64
        Vertex indices in the file's numbering, in the order they were chosen.
    (n_input,) float32, mesh units, only with ``return_distances``
        Distance of each vertex to the nearest sample (NaN where no face uses the vertex).
    """
    _needs_mesh(model, "farthest_point_sampling")
    m = model.mesh
    n_used = len(m.internal_vertices)
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not 1 <= int(k) <= n_used:
        raise InputError(f"k must be an integer from 1 to {n_used} (the vertices that faces use), got {k!r}")
    start = int(_seed_ids(model, start, "start")[0])
    dev = resolve_device(device)
    # the search runs over internal vertices (one per welded group) through the backend's vertex rows, the
    # values ssad gathers into the file's numbering; answers map back to file indices
    st = query_state(model, dev)
    be = backend_of(st, precision)
    md = st.mesh("start")
    bind(model, dev, be.precision)
    multi = m.n_components > 1
    row = wp.empty(md.V, dtype=wp.float32, device=dev)
    row_t = wp.to_torch(row)
    j = int(m.input_to_internal[start])
    chosen = [j]
    best = None
    for i in range(int(k)):
        be.vertex_distances(md, md.rel64[j:j + 1], np.array([j]), m.internal_components[j:j + 1] if multi else None, row,
                            False, False)
        best = row_t.clone() if best is None else torch.minimum(best, row_t, out=best)
        if i + 1 < int(k):
            j = int(torch.argmax(best))  # inf (an unreached part) wins over every finite distance
            chosen.append(j)
    chosen = np.array(chosen)
    samples = m.index[chosen].astype(np.int64)
    if not return_distances:
        return samples
    return samples, m.to_input(best.cpu().numpy().astype(np.float32))


def voronoi(model: Model, seeds, device=None, precision: str = "auto", return_distances: bool = False):
    """Geodesic Voronoi cells: the nearest seed of every vertex.

    Parameters
    ----------
    seeds : (S,) int
        Seed vertices in the mesh file's numbering, all different.

    Returns
    -------
    (n_input,) int64
        For each vertex the position in ``seeds`` of its nearest seed; -1 for vertices no face uses and for
        vertices on a part of the mesh that holds no seed. Ties go to the earlier seed.
    (n_input,) float32, mesh units, only with ``return_distances``
        The distance to that seed (+inf on a part without a seed, NaN for unused vertices).
    """
    labels, dist = nearest_seeds(model, seeds, k=1, device=device, precision=precision)
    labels, dist = labels[:, 0], dist[:, 0]
    return (labels, dist) if return_distances else labels


def nearest_seeds(model: Model, seeds, k: int = 1, device=None, precision: str = "auto"):
    """The ``k`` nearest seeds of every vertex, by geodesic distance.

    Parameters
    ----------
    seeds : (S,) int
        Seed vertices in the mesh file's numbering, all different.
    k : int
        How many seeds per vertex, 1 .. S.

    Returns
    -------
    labels : (n_input, k) int64
        Positions in ``seeds``, nearest first; -1 where no face uses the vertex or fewer than k seeds share its
        part of the mesh.
    distances : (n_input, k) float32, mesh units
        The matching distances (+inf where the label is -1 for lack of a seed, NaN for unused vertices).
    """
    _needs_mesh(model, "nearest_seeds")
    ids = _seed_ids(model, seeds, "seeds")
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not 1 <= int(k) <= len(ids):
        raise InputError(f"k must be an integer from 1 to the number of seeds ({len(ids)}), got {k!r}")
    k = int(k)
    dev = resolve_device(device)
    best_d = best_l = None
    for off, rows in _rows(model, ids, dev, precision):
        rows = torch.nan_to_num(rows, nan=float("inf"))  # (s, n_input); unused vertices sort last
        if k == 1:  # a running minimum: no sort, no transposed copy
            d, lab = torch.min(rows, dim=0)
            d, lab = d[:, None], lab[:, None] + off
            if best_d is not None:
                better = d < best_d  # strict: a tie keeps the earlier seed
                d, lab = torch.where(better, d, best_d), torch.where(better, lab, best_l)
            best_d, best_l = d, lab
            continue
        d = rows.T
        lab = torch.arange(off, off + rows.shape[0], device=d.device).expand_as(d)
        if best_d is not None:  # earlier seeds first, so a stable sort keeps ties with the earlier seed
            d, lab = torch.cat([best_d, d], 1), torch.cat([best_l, lab], 1)
        kk = min(k, d.shape[1])
        order = torch.sort(d, dim=1, stable=True).indices[:, :kk]
        best_d, best_l = torch.gather(d, 1, order), torch.gather(lab, 1, order)
    labels = best_l.cpu().numpy().astype(np.int64)
    dist = best_d.cpu().numpy().astype(np.float32)
    labels[~np.isfinite(dist)] = -1
    unused = model.mesh.input_to_internal < 0
    dist[unused] = np.nan
    return labels, dist


def isolines(model: Model, values, levels):
    """Isolines of a per-vertex field on the mesh, as polylines.

    Parameters
    ----------
    values : (n_input,) float
        One value per vertex in the mesh file's numbering (e.g. ``ssad(model, 0)``); the field is linear on each
        triangle. NaN and infinite values mark vertices the lines avoid.
    levels : float or (L,) float, or int
        The values to trace; an int ``n`` asks for ``n`` levels evenly inside the finite range (ends excluded).

    Returns
    -------
    list of L lists of (n_i, 3) float64 arrays, mesh coordinates
        For each level, its polylines; a closed line ends with its first point repeated.
    """
    _needs_mesh(model, "isolines")
    m = model.mesh
    f = values.detach().cpu().numpy() if isinstance(values, torch.Tensor) else np.asarray(values)
    if f.shape != (m.n_input,):
        raise InputError(f"values must have one entry per vertex of the mesh file, shape ({m.n_input},), "
                         f"got shape {f.shape}")
    f = f.astype(np.float64)[m.index]
    fin = np.isfinite(f)
    if isinstance(levels, (int, np.integer)) and not isinstance(levels, bool):
        if levels < 1 or not fin.any():
            raise InputError(f"levels={levels}: give at least 1 level, and values with finite entries")
        lo, hi = f[fin].min(), f[fin].max()
        levels = lo + (hi - lo) * np.arange(1, levels + 1) / (levels + 1)
    lv = np.atleast_1d(np.asarray(levels, dtype=np.float64))
    if lv.ndim != 1 or not np.all(np.isfinite(lv)):
        raise InputError(f"levels must be finite numbers (a float or a 1-D list), got {levels!r}")
    tri = m.internal_faces[np.all(fin[m.internal_faces], axis=1)]
    return [_trace_level(m.internal_vertices, tri, f, float(c)) for c in lv]


def _trace_level(V: np.ndarray, F: np.ndarray, f: np.ndarray, c: float) -> list[np.ndarray]:
    """Marching triangles at level ``c``, then the segments chained into polylines through shared edges."""
    # a vertex exactly at the level counts as above it, so every crossing lies strictly inside an edge
    above = f[F] >= c
    n_above = above.sum(1)
    cut = F[(n_above == 1) | (n_above == 2)]
    if len(cut) == 0:
        return []
    ab = f[cut] >= c
    segs = []
    for a, b in ((0, 1), (1, 2), (2, 0)):
        segs.append(ab[:, a] != ab[:, b])
    edge_pairs = []  # per face, its two cut edges as (min vertex, max vertex)
    for fi in range(len(cut)):
        es = [(cut[fi, a], cut[fi, b]) for (a, b), s in zip(((0, 1), (1, 2), (2, 0)), segs) if s[fi]]
        edge_pairs.append([tuple(sorted(e)) for e in es])
    # graph: edge -> neighbouring edges through faces
    nbr: dict[tuple, list] = {}
    for e1, e2 in edge_pairs:
        nbr.setdefault(e1, []).append(e2)
        nbr.setdefault(e2, []).append(e1)

    def point(e):
        i, j = e
        t = (c - f[i]) / (f[j] - f[i])
        return V[i] + t * (V[j] - V[i])

    seen_faces: set = set()
    lines = []

    def walk(start):
        line = [start]
        prev, cur = None, start
        while True:
            nxt = [e for e in nbr[cur] if e != prev and frozenset((cur, e)) not in seen_faces]
            if not nxt:
                break
            seen_faces.add(frozenset((cur, nxt[0])))
            prev, cur = cur, nxt[0]
            line.append(cur)
            if cur == start:
                break
        return line

    # open lines start at an end (an edge on one cut face); closed loops anywhere
    for e in [e for e, ns in nbr.items() if len(ns) == 1] + list(nbr):
        if any(frozenset((e, x)) not in seen_faces for x in nbr[e]):
            line = walk(e)
            if len(line) > 1:
                lines.append(np.array([point(x) for x in line]))
    return lines
