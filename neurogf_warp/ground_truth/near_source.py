"""A second, finer solve near each source: the solver's worst pairs are short ones.

With one window per Steiner node, a beam of rays is lost where it passes close to a vertex; that costs a similar
length anywhere (1-11% of a mean edge on the shared meshes), so the relative error is largest for targets close
to the source: every pair above 0.5% at k = 3 lies within 13.4 mean edge lengths of its source (24 sources on six
meshes; docs/design.md). ``refine_near_sources`` re-solves, for each source, only the faces within
``radius + 2`` mean edges of it, at a higher k, and keeps the shorter value per vertex. Both values are lengths of
real surface paths, so the result is still an upper bound of the exact distance; a geodesic to a vertex at
distance r stays within r of the source, so the patch holds it.

The patches of many sources are copied into one mesh of disjoint components and solved as one row with one seed
per component (``GeodesicSolver.run_seeds``): one solver set-up per chunk of sources, not per source.
``trace_patch`` makes one source's patch solve the same way and traces paths on it (``geodesic_paths``).
"""
from __future__ import annotations

import numpy as np

from neurogf_warp.ground_truth.solver import GeodesicSolver
from neurogf_warp.mesh.mesh import load_mesh

__all__ = ["refine_near_sources", "plan_chunks", "patch_limit", "solve_chunk", "apply_updates", "patch_faces",
           "patch_faces_rows", "patch_union", "trace_patch", "PATCH_RADIUS", "PATCH_K"]

PATCH_RADIUS = 12.0  # mean edge lengths: beyond it the k = 3 worst pair was 0.38-0.44% on the tail meshes
PATCH_K = 6  # k = 5 left the needle mesh's degenerate-face pair at 0.64%; k = 6 took every mesh to <= 0.45%
NODE_CAP = 4_000_000  # nodes of one union solve (109 B each: ~0.44 GB of solver state)


def patch_faces(solver: GeodesicSolver, dist_row: np.ndarray, limit: float) -> np.ndarray:
    """Rows of ``solver.topo.faces`` whose three vertices all lie within ``limit`` (same units as ``dist_row``,
    (V,) in the mesh's internal numbering); gathered through the solver's vertex -> face table, in time
    proportional to the patch."""
    t = solver.topo
    inside = np.isfinite(dist_row) & (dist_row <= limit)
    v = solver._solver_id[np.flatnonzero(inside)]
    n = t.vertex_face_start[v + 1] - t.vertex_face_start[v]
    at = np.repeat(t.vertex_face_start[v] - np.cumsum(n) + n, n) + np.arange(int(n.sum()))
    near = np.unique(t.vertex_faces[at])
    inside_s = inside[solver._order]  # solver numbering
    return near[inside_s[t.faces[near]].all(axis=1)]


def patch_faces_rows(solver: GeodesicSolver, dist: np.ndarray, limit: float, rows_per_block: int = 64) -> list:
    """``patch_faces`` of every row of ``dist`` (S, V): a list of S sorted face-row arrays, the same as row by row,
    gathered a block of rows at a time (one pass over the block, one sort of (row, face) keys)."""
    t = solver.topo
    nf = len(t.faces)
    faces_mesh = solver._order[t.faces]  # mesh numbering of each face's vertices
    out = []
    for r0 in range(0, len(dist), rows_per_block):
        block = dist[r0: r0 + rows_per_block]
        with np.errstate(invalid="ignore"):
            inside = np.isfinite(block) & (block <= limit)
        rows, vm = np.nonzero(inside)
        v = solver._solver_id[vm]
        n = (t.vertex_face_start[v + 1] - t.vertex_face_start[v]).astype(np.int64)
        at = np.repeat(t.vertex_face_start[v] - np.cumsum(n) + n, n) + np.arange(int(n.sum()))
        key = np.unique(np.repeat(rows.astype(np.int64), n) * nf + t.vertex_faces[at])
        row, face = np.divmod(key, nf)
        keep = inside[row[:, None], faces_mesh[face]].all(axis=1)
        row, face = row[keep], face[keep]
        bounds = np.searchsorted(row, np.arange(len(block) + 1))
        out += [face[bounds[i]: bounds[i + 1]] for i in range(len(block))]
    return out


def refine_near_sources(solver: GeodesicSolver, sources: np.ndarray, dist: np.ndarray, k: int = PATCH_K,
                        radius: float = PATCH_RADIUS, copy: bool = True) -> np.ndarray:
    """Distances ``dist`` lowered near their sources by a solve at ``k`` of each source's patch.

    Parameters
    ----------
    solver : the GeodesicSolver that computed ``dist`` (its mesh, vertex -> face table and mean edge length are
        used; the patch solves run on its device)
    sources : (S,) int, internal vertex ids
    dist : (S, V) float, distances from ``sources`` in the normalized frame (``GeodesicSolver.solve``)
    k : Steiner points per edge in the patches
    radius : patch radius in mean edge lengths (faces within radius + 2 of the source, by ``dist``)
    copy : False to lower ``dist`` in place where it is a float32 array (saves a copy of all rows)

    Returns
    -------
    (S, V) float32, normalized frame: min(dist, patch distance) per vertex of each patch, ``dist`` elsewhere.
    """
    src = np.asarray(sources, dtype=np.int64).reshape(-1)
    out = np.array(dist, dtype=np.float32, copy=True) if copy else np.asarray(dist, dtype=np.float32)
    if len(src) == 0:
        return out
    for chunk in plan_chunks(solver, src, out, k, radius):
        apply_updates(out, solve_chunk(solver, src, chunk, k, solver.device))
    return out


def patch_limit(solver: GeodesicSolver, radius: float = PATCH_RADIUS) -> float:
    """The distance (normalized frame) within which a source's patch takes faces: radius + 2 mean edges."""
    return (radius + 2.0) * solver.mean_edge


def plan_chunks(solver: GeodesicSolver, sources: np.ndarray, dist: np.ndarray | None, k: int = PATCH_K,
                radius: float = PATCH_RADIUS, patches: list | None = None) -> list:
    """The union solves of ``refine_near_sources``: a list of chunks, each a list of (row, (n,) face rows of
    ``solver.topo.faces``), the rows in order, each chunk's patches together under NODE_CAP nodes. The chunks
    depend only on the mesh and ``dist``, so devices that split them between them reproduce one device's solves.
    ``patches``: the rows' ``patch_faces_rows`` at ``patch_limit``, where already made (``dist`` is then unused)."""
    src = np.asarray(sources, dtype=np.int64).reshape(-1)
    if len(src) == 0:
        return []
    # every patch from the rows as given (a chunk's solve changes only its own rows)
    if patches is None:
        patches = patch_faces_rows(solver, np.asarray(dist, dtype=np.float32), patch_limit(solver, radius))
    # chunks of sources whose patches together stay under NODE_CAP nodes (about V + 1.5 k F per patch)
    chunks, chunk, size = [], [], 0
    for r in range(len(src)):
        faces = patches[r]
        n = int(len(faces) * (0.5 + 1.5 * k))
        if chunk and size + n > NODE_CAP:
            chunks.append(chunk)
            chunk, size = [], 0
        chunk.append((r, faces))
        size += n
    chunks.append(chunk)
    return chunks


def apply_updates(out: np.ndarray, updates: list) -> None:
    """Lower ``out`` (S, V) by ``solve_chunk``'s updates: min in place."""
    for r, used, d in updates:
        out[r, used] = np.minimum(out[r, used], d)


def patch_union(solver: GeodesicSolver, src: np.ndarray, chunk: list):
    """The union of a chunk's patches as one mesh: disjoint copies, numbered one after the other.

    Parameters
    ----------
    solver : the GeodesicSolver whose ``topo.faces`` the chunk's face rows index
    src : (S,) int, internal source vertex ids of the rows
    chunk : list of (row, (n,) face rows), as ``plan_chunks`` makes

    Returns
    -------
    (union Mesh in the normalized frame of ``solver.mesh`` (not welded), (C,) int seeds (one vertex of the union
    per copy), list of C (row, (n,) sorted internal vertex ids of the copy, its first vertex in the union)), or
    None where no patch holds its source (an isolated source vertex: nothing to refine).
    """
    P = solver.mesh.internal_normalized_vertices
    F = solver._order[solver.topo.faces]  # mesh numbering, in the solver's face order
    verts, faces, seeds, owners = [], [], [], []
    base = 0
    for r, fi in chunk:
        used = np.unique(F[fi])  # sorted: a patch vertex's number in the copy is its rank here
        if len(fi) == 0 or not np.isin(src[r], used):
            continue  # an isolated source vertex: nothing to refine
        verts.append(P[used])
        faces.append(np.searchsorted(used, F[fi]) + base)
        seeds.append(np.searchsorted(used, src[r]) + base)
        owners.append((r, used, base))
        base += len(used)
    if not owners:
        return None
    union = load_mesh((np.concatenate(verts), np.concatenate(faces)), weld=False)
    return union, np.asarray(seeds), owners


def solve_chunk(solver: GeodesicSolver, src: np.ndarray, chunk: list, k: int, device, prepare=None) -> list:
    """One union of patches (``patch_union``), one multi-seed solve on ``device``
    (``prepare(solver)``, if given, first: ``devices.lock_captures`` where other threads solve at the same time).

    Returns a list of (row, (n,) vertex ids, (n,) float32 patch distances in the normalized frame), for
    ``apply_updates``."""
    made = patch_union(solver, src, chunk)
    if made is None:
        return []
    union, seeds, owners = made
    ps = GeodesicSolver(union, k=k, device=device, max_rows=1)
    if prepare is not None:
        prepare(ps)
    ps.run_seeds(seeds)
    d = ps.vertex_distances()[0] / np.float32(union.scale)  # units of P: the normalized frame
    return [(r, used, d[b: b + len(used)]) for r, used, b in owners]


def trace_patch(solver: GeodesicSolver, source: int, dist_row: np.ndarray, targets: np.ndarray, k: int = PATCH_K,
                radius: float = PATCH_RADIUS):
    """Paths from ``source`` to ``targets`` traced on the source's patch solved at ``k``: the solve that
    ``refine_near_sources`` makes for that source, so the distances are the ones it compares.

    Parameters
    ----------
    solver : the GeodesicSolver that computed ``dist_row`` (the patch solve runs on its device)
    source : int, internal vertex id
    dist_row : (V,) float, distances from ``source`` in the normalized frame (``GeodesicSolver.solve``'s row)
    targets : (T,) int, internal vertex ids
    k, radius : as in ``refine_near_sources``

    Returns
    -------
    dist : (T,) float32, patch distances in the normalized frame; inf for a target outside the patch
    points : (P, 3) float64, normalized frame of ``solver.mesh``; path i is points[offsets[i]:offsets[i+1]], from
        the source (NaN points for a flagged path; no points for a target outside the patch)
    offsets : (T + 1,) int64
    flags : (T,) int32, as ``GeodesicSolver.trace``'s (0 for a target outside the patch)
    """
    tg = np.asarray(targets, dtype=np.int64).reshape(-1)
    T = len(tg)
    dist = np.full(T, np.inf, dtype=np.float32)
    none = (dist, np.zeros((0, 3)), np.zeros(T + 1, np.int64), np.zeros(T, np.int32))
    faces = patch_faces(solver, dist_row, patch_limit(solver, radius))
    made = patch_union(solver, np.array([source], dtype=np.int64), [(0, faces)])
    if made is None or T == 0:
        return none
    union, seeds, ((_, used, _),) = made
    j = np.minimum(np.searchsorted(used, tg), len(used) - 1)
    inside = np.flatnonzero(used[j] == tg)
    if len(inside) == 0:
        return none
    ps = GeodesicSolver(union, k=k, device=solver.device, max_rows=1)
    ps.run_seeds(seeds)  # as solve_chunk: the same solve, so the same distances
    dist[inside] = ps.vertex_distances()[0][j[inside]] / np.float32(union.scale)
    pts, offs, fl = ps.trace(np.zeros(len(inside), np.int32), j[inside])
    counts = np.zeros(T, np.int64)
    counts[inside] = np.diff(offs)
    offsets = np.zeros(T + 1, np.int64)
    np.cumsum(counts, out=offsets[1:])
    flags = np.zeros(T, np.int32)
    flags[inside] = fl
    return dist, union.denormalize(pts), offsets, flags
