"""Ground-truth geodesic distances and shortest paths on triangle meshes (Warp): the public front.

`geodesic_distances` and `geodesic_paths` are the one-call functions; `GeodesicSolver` (geodesic_solver.py) is the
reusable solver behind them. Every distance is the length of a real surface path (an upper bound of the exact
geodesic distance, within 0.02% of it on average at the defaults; docs/design.md).
"""
from __future__ import annotations

import numpy as np
import warp as wp

from neurogf_warp.common.arrays import resolve_device
from neurogf_warp.ground_truth.solver import (
    DEFAULT_DELTA,
    DEFAULT_K,
    PATH_ABS_TOLERANCE,
    PATH_DELTA,
    PATH_TOLERANCE,
    SOLVER_CACHE_SIZE,
    GeodesicSolver,
    clear_solver_cache,
    load_kernels,
    points_per_path,
)
from neurogf_warp.mesh.mesh import Mesh, load_mesh

__all__ = ["geodesic_distances", "geodesic_paths", "GeodesicSolver", "resample_polyline", "load_kernels",
           "clear_solver_cache", "SOLVER_CACHE_SIZE",
           "DEFAULT_K", "DEFAULT_DELTA", "PATH_DELTA", "PATH_TOLERANCE"]


def _vertices(mesh: Mesh, indices, name: str) -> np.ndarray:
    """Internal ids of user vertex indices (an int or a 1-D sequence); an empty sequence gives an empty array."""
    s = np.asarray(indices)
    if s.ndim > 1:
        raise ValueError(f"{name} must be an int or a 1-D sequence of vertex indices, got shape {s.shape}")
    if s.size == 0:
        return np.zeros(0, dtype=np.int64)
    return np.atleast_1d(mesh.vertex(s)).astype(np.int64)


def geodesic_distances(mesh, sources, device=None, k: int = DEFAULT_K, windows: bool = True,
                       batch: int | None = None, delta: float = DEFAULT_DELTA,
                       near_source: bool | None = None, devices=None, distributed=False) -> np.ndarray:
    """Geodesic distances from mesh vertices to every vertex, on one device or spread over several.

    Parameters
    ----------
    mesh : path, (V, F) pair, trimesh.Trimesh or Mesh
    sources : int or (S,) int, vertex indices in the mesh's own numbering
    device : str or warp.Device, optional
    k : int, Steiner points per edge (accuracy)
    windows : bool, exact unfolding windows (on: default accuracy)
    batch : int, optional, source rows solved together (default: from free memory)
    delta : float, delta-stepping bucket in mean edge lengths (speed only; 0 = plain Bellman-Ford)
    near_source : bool, also solve the faces within 14 mean edges of each source at k = 6 and keep the shorter
        value (``near_source.refine_near_sources``): the worst pairs, which lie near their source, go from up to
        1.4% too long to at most 0.45% on the shared meshes (24 sources each; docs/design.md), for
        about 12K more nodes of work per source. On by default: on an H100 the 256-source call on the 436K-vertex
        benchmark mesh took 34.0 s with it and 34.4 s without; on a 2-core CPU +3% on the bunny, 1.3-2x on meshes of
        a few thousand vertices (docs/performance.md). None (the default) means on with
        ``windows`` and off for the plain Steiner graph (``windows=False``, which stays exactly that graph's
        shortest paths); False gives the plain solve at ``k``, which is what the training datasets use.
    devices : "all", a list such as ["cuda:0", "cuda:1"] (or "cuda:0,cuda:1"), or None: the sources are split in
        balanced contiguous blocks, one per device, solved at the same time (one thread and one solver per device;
        ``ground_truth/devices.py``). None means the environment variable ``NEUROGF_DEVICES`` (same forms) where
        it is set and ``device`` is not the CPU, else ``device`` alone. ``device``, if given, must be one of them.
        Unknown devices, a device given twice and the CPU mixed with GPUs are refused (InputError).
    distributed : bool or torch.distributed ProcessGroup, every rank of the process group (True: the default one)
        calls with the same mesh and sources; each solves its block of the sources on its own ``device`` /
        ``devices`` (under torchrun, typically ``device=f"cuda:{LOCAL_RANK}"``), and every rank returns all rows
        (all-gathered). False (default): no collective, as ranks that work on different meshes need.

    Returns
    -------
    (S, V_input) float32, mesh units: inf between parts no surface path joins, NaN at vertices no face uses.
    Every value is the length of a real surface path (an upper bound of the exact distance). An empty
    `sources` gives a (0, V_input) array. Each row is solved on its own, so the rows do not depend on ``devices``
    or the number of ranks (bit for bit on the CPU; docs/guides/multi-gpu.md for GPUs).

    Notes
    -----
    The solver's mesh tables (vertex order and topology on the host, the Steiner graph on the device: by their
    sizes about 45 bytes per graph node on the device, 0.21 GB and 0.12 GB on the host for the 436K-vertex
    benchmark bunny at k = 3) are kept for the last ``SOLVER_CACHE_SIZE`` (2) meshes, so that another call on
    the same mesh, device, ``k`` and ``windows`` skips that set-up (``GeodesicSolver(cache=True)``);
    ``clear_solver_cache()`` frees them. The per-source solver state is freed when the call returns.
    """
    from neurogf_warp.ground_truth.devices import process_group, resolve_devices

    m = load_mesh(mesh)
    src = _vertices(m, sources, "sources")
    devs = resolve_devices(devices, device)
    group = process_group(distributed)
    if len(src) == 0:
        return np.zeros((0, m.n_input), dtype=np.float32)
    near = windows if near_source is None else near_source
    if len(devs) > 1 or group is not None:
        d = _spread_distances(m, src, devs, group, k=k, windows=windows, batch=batch, delta=delta, near=near)
        return _to_output(m, d)
    device = devs[0]
    solver = GeodesicSolver(m, k=k, windows=windows, device=device, batch=batch, max_rows=len(src),
                            delta=delta, cache=True)
    d = solver.solve(src)
    if near:
        from neurogf_warp.ground_truth.near_source import refine_near_sources

        d = refine_near_sources(solver, src, d, copy=False)
    del solver  # its per-source state, before the output rows are made
    return _to_output(m, d)


def _to_output(m: Mesh, d: np.ndarray) -> np.ndarray:
    """Normalized internal rows (S, V) -> mesh units, the input's numbering (in place where it can)."""
    d /= np.float32(m.scale)
    if m.n_input == len(m.index) and np.array_equal(m.index, np.arange(m.n_input)):
        return d  # every input vertex is its own internal vertex: to_input would copy the rows unchanged
    return m.to_input(d)


def _share_tables(m: Mesh, k: int, windows: bool, devs: list) -> None:
    """The solver cache's host tables of ``devs[0]`` (built by its solver just now) entered for the other devices
    as well, without the device graph (each of their solvers builds its own from them). Where the cache's entries
    are not what this expects, nothing is shared (each device then builds its own tables)."""
    from neurogf_warp.ground_truth import solver as sv

    try:
        tables = sv._SOLVER_CACHE.get(sv._cache_key(m, k, windows, devs[0]))
        if tables is None or len(tables) != 7:
            return
        for d in devs[1:]:
            sv._SOLVER_CACHE[sv._cache_key(m, k, windows, d)] = tuple(tables[:6]) + (None,)
    except (AttributeError, TypeError):
        return


def _spread_distances(m: Mesh, src: np.ndarray, devs: list, group, k: int, windows: bool, batch, delta: float,
                      near: bool) -> np.ndarray:
    """``geodesic_distances``' rows (normalized, internal numbering) over ``devs`` (one thread each) and, with
    ``group`` = (process group, rank, world), over the ranks: this rank's block of ``src`` solved in balanced
    contiguous blocks per device, the rows all-gathered; then the near-source patches of all rows planned alike on
    every rank and their union solves split the same way (their updates all-gathered), so that every solve is one
    that a single device would have made."""
    import time

    from neurogf_warp.ground_truth import devices as dv
    from neurogf_warp.ground_truth import near_source as ns

    t0 = time.perf_counter()
    spans = dv.LAST_RUN
    spans.clear()
    spans.update(devices=[str(d) for d in devs], solve=[None] * len(devs), refine=[None] * len(devs))
    S = len(src)
    mine = dv.split_blocks(S, group[2])[group[1]] if group is not None else slice(0, S)
    own = src[mine]
    parts = dv.split_blocks(len(own), len(devs))
    rows = np.empty((len(own), len(m.internal_vertices)), dtype=np.float32)
    solvers = [None] * len(devs)
    # the tables of every device fit in the solver cache, or no device uses it (threads evicting each other's
    # entries would race)
    cache = len(devs) <= SOLVER_CACHE_SIZE
    patches = [[] for _ in devs]
    if len(devs) > 1:  # every module loaded on each device before the threads (no two compile the same module)
        from neurogf_warp.ground_truth.solver import load_for_capture

        for d in devs:
            load_for_capture(d)

    first = None
    if len(devs) > 1 and cache and len(own[parts[0]]):
        # the host tables (vertex order, topology, Steiner counts) built once for every device: one copy in host
        # memory (0.33 GB at 436K vertices), and each other device builds only its device graph from them
        first = GeodesicSolver(m, k=k, windows=windows, device=devs[0], batch=batch, max_rows=len(own[parts[0]]),
                               delta=delta, cache=True)
        _share_tables(m, k, windows, devs)
    spans["first_s"] = time.perf_counter() - t0

    def solve(j):
        block = own[parts[j]]
        if len(block):
            t1 = time.perf_counter()
            with dv.capture_lock():  # its uploads and allocations never during another device's graph capture
                sol = first if j == 0 and first is not None else \
                    GeodesicSolver(m, k=k, windows=windows, device=devs[j], batch=batch, max_rows=len(block),
                                   delta=delta, cache=cache)
                n_batches = -(-len(block) // sol.batch)
                even = -(-len(block) // n_batches)
                if batch is None and even < sol.batch:
                    # equal batches: a short last batch is padded to the full batch and costs as much (2.2M
                    # vertices, 32 sources in batches of 14: 42 rows of work, in batches of 11: 33); tables cached
                    sol = None
                    sol = GeodesicSolver(m, k=k, windows=windows, device=devs[j], batch=even, delta=delta,
                                         cache=cache)
            if len(devs) > 1:
                dv.lock_captures(sol)
            solvers[j] = sol
            t2 = time.perf_counter()
            rows[parts[j]] = sol.solve(block)
            if near and group is None:  # its rows' patches, while the other devices may still solve
                patches[j] = ns.patch_faces_rows(sol, rows[parts[j]], ns.patch_limit(sol))
            spans["solve"][j] = (t1 - t0, t2 - t0, time.perf_counter() - t0, len(block), sol.batch, sol.captured)

    spans["load_s"] = time.perf_counter() - t0
    dv.run_on_devices(solve, len(devs))
    t1 = time.perf_counter()
    d = dv.all_gather_rows(rows, S, group[0]) if group is not None else rows
    spans["gather_s"] = time.perf_counter() - t1
    rows = None  # this rank's block: a copy of it is in d
    if not near:
        return d
    ref = next((s for s in solvers if s is not None), None)
    if ref is None:  # this rank had no sources: its host tables still plan the chunks (one row of state)
        ref = GeodesicSolver(m, k=k, windows=windows, device=devs[0], batch=1, delta=delta, cache=cache)
    for j in range(1, len(solvers)):
        solvers[j] = None  # their per-source state: the patch solves need the room
    t1 = time.perf_counter()
    chunks = ns.plan_chunks(ref, src, d, patches=None if group is not None else [p for ps in patches for p in ps])
    mine = dv.split_blocks(len(chunks), group[2])[group[1]] if group is not None else slice(0, len(chunks))
    own = chunks[mine]
    parts = dv.split_blocks(len(own), len(devs))
    updates = [[] for _ in devs]

    def refine(j):
        t1 = time.perf_counter()
        for chunk in own[parts[j]]:
            updates[j] += ns.solve_chunk(ref, src, chunk, ns.PATCH_K, devs[j],
                                         prepare=dv.lock_captures if len(devs) > 1 else None)
        spans["refine"][j] = (t1 - t0, time.perf_counter() - t0, len(own[parts[j]]))

    spans["plan_s"] = time.perf_counter() - t1
    dv.run_on_devices(refine, len(devs))
    mine_updates = [u for part in updates for u in part]
    every = dv.all_gather_objects(mine_updates, group[0]) if group is not None else [mine_updates]
    for part in every:
        ns.apply_updates(d, part)
    spans["total_s"] = time.perf_counter() - t0
    return d


def resample_polyline(points: np.ndarray, offsets: np.ndarray, m: int, device=None) -> np.ndarray:
    """Resample polylines to m points each, equally spaced by arc length.

    Parameters
    ----------
    points : (P, 3) float, the polylines one after the other (computed from their float32 values)
    offsets : (T + 1,) int, polyline i is points[offsets[i]:offsets[i+1]]
    m : int >= 2, points per resampled polyline
    device : Warp device of the launch (default: Warp's preferred device)

    Returns
    -------
    (T, m, 3) float32: a polyline of one point is repeated; an empty one (or one with NaN points) gives NaN.
    """
    offsets = np.asarray(offsets, dtype=np.int64)
    return resample_polylines(points, offsets[:-1], offsets[1:], m, device)


def resample_polylines(points: np.ndarray, starts: np.ndarray, ends: np.ndarray, m: int,
                       device=None) -> np.ndarray:
    """``resample_polyline`` for polylines anywhere in ``points``: polyline i is points[starts[i]:ends[i]]; one
    Warp launch on ``device`` (one thread per polyline) for all of them.

    A dataset batch on a GPU resamples ~80K paths of ~100-200 points: the loop over them in numpy this replaces
    took ~13 ms per path source, most of a small mesh's ground-truth time.
    """
    from neurogf_warp.kernels.ground_truth import paths as kp

    device = resolve_device(device)
    m = points_per_path(m)
    starts, ends = np.asarray(starts, dtype=np.int64), np.asarray(ends, dtype=np.int64)
    T = len(starts)
    if T == 0:
        return np.zeros((0, m, 3), dtype=np.float32)
    lo, hi = int(starts.min()), int(max(ends.max(), starts.min()))
    if hi - lo >= 2**31:
        raise MemoryError("too many polyline points in one call: resample fewer polylines at a time")
    pts = wp.array(np.ascontiguousarray(points[lo:hi], dtype=np.float32).reshape(-1, 3), dtype=wp.vec3,
                   device=device)
    out = wp.empty((T, m), dtype=wp.vec3, device=device)
    wp.launch(kp.resample_by_length, T, inputs=[pts, wp.array((starts - lo).astype(np.int32), dtype=int,
                                                               device=device),
                                                 wp.array((np.maximum(ends, starts) - lo).astype(np.int32),
                                                          dtype=int, device=device)],
              outputs=[out], device=device)
    return out.numpy().reshape(T, m, 3)


def geodesic_paths(mesh, source, targets, m: int | None = None, device=None, k: int = DEFAULT_K,
                   windows: bool = True, delta: float = PATH_DELTA, near_source: bool | None = None):
    """Shortest surface paths from one vertex to others.

    Parameters
    ----------
    mesh : path, (V, F) pair, trimesh.Trimesh or Mesh
    source : int, vertex index in the mesh's own numbering
    targets : int or (T,) int, vertex indices
    m : int >= 2, optional: resample every path to m points equally spaced by arc length
    device, k, windows, delta : as in `geodesic_distances`
    near_source : bool, optional: a target whose distance the near-source patch of `geodesic_distances` lowers
        gets its path from that patch's solve (k = 6 on the faces within 14 mean edges of the source), so that
        every path is within PATH_TOLERANCE of ``geodesic_distances(mesh, [source], ...)`` for its target (with
        the same `k`, `windows`, `delta` and `near_source`). None (the default): on with `windows`, as in
        `geodesic_distances`; False traces every path from the one solve at `k`.

    Returns
    -------
    A list of T (n_i, 3) float32 polylines in mesh units, ordered from the source, or with m a (T, m, 3)
    float32 array (float32 like every result of the library). A target no surface path reaches gives an empty
    (0, 3) polyline (NaN row with m); a path the
    solver could not trace to within PATH_TOLERANCE of its distance gives a polyline of NaN (NaN row with m)
    and is counted in the warning it raises. An empty `targets` gives [] (a (0, m, 3) array with m).
    """
    if m is not None:
        m = points_per_path(m)
    msh = load_mesh(mesh)
    s = _vertices(msh, source, "source")
    if len(s) != 1:
        raise ValueError(f"geodesic_paths takes one source vertex, got {len(s)}")
    tg = _vertices(msh, targets, "targets")
    if len(tg) == 0:
        return [] if m is None else np.zeros((0, m, 3), dtype=np.float32)
    solver = GeodesicSolver(msh, k=k, windows=windows, device=device, batch=1, delta=delta, cache=True)
    solver.run(s)
    pts, offs, flags = solver.trace(np.zeros(len(tg), np.int32), tg)
    if windows if near_source is None else near_source:
        pts, offs, flags = _near_source_paths(solver, s[0], tg, pts, offs, flags)
    if np.any(flags != 0):
        import warnings

        warnings.warn(f"{int(np.sum(flags != 0))} of {len(tg)} paths could not be traced to within "
                      f"{PATH_TOLERANCE:.1%} of their distance; they are returned as NaN", RuntimeWarning,
                      stacklevel=2)
    pts = msh.denormalize(pts)
    if m is not None:
        return resample_polyline(pts, offs, m, solver.device).astype(np.float32)
    return [pts[offs[i]: offs[i + 1]].astype(np.float32) for i in range(len(tg))]


def _near_source_paths(solver: GeodesicSolver, source: int, tg: np.ndarray, pts: np.ndarray, offs: np.ndarray,
                       flags: np.ndarray):
    """``solver.trace``'s paths (normalized frame) with those to targets whose near-source patch distance is
    shorter (``near_source.refine_near_sources``'s rule) traced on the patch instead. Where the patch path is
    flagged, the first path stays if it is within PATH_TOLERANCE of the patch distance, else the path is NaN."""
    from neurogf_warp.ground_truth import near_source as ns

    d = solver.vertex_distances()[0]
    near = np.flatnonzero(d[tg] <= ns.patch_limit(solver))  # only these can lie in the patch
    if len(near) == 0:
        return pts, offs, flags
    dp, ppts, poffs, pflags = ns.trace_patch(solver, source, d, tg[near])
    lower = np.flatnonzero(dp < d[tg[near]])
    if len(lower) == 0:
        return pts, offs, flags
    paths = [pts[offs[i]: offs[i + 1]] for i in range(len(tg))]
    flags = flags.copy()
    for j in lower:
        t = near[j]
        if pflags[j] == 0:
            paths[t], flags[t] = ppts[poffs[j]: poffs[j + 1]], 0
            continue
        # the patch could not trace it: the first path only if it is no longer than the patch distance allows
        first = paths[t].astype(np.float64)
        length = np.linalg.norm(np.diff(first, axis=0), axis=1).sum()
        if not (flags[t] == 0 and length <= dp[j] * (1.0 + PATH_TOLERANCE) + PATH_ABS_TOLERANCE):
            paths[t], flags[t] = np.full((max(len(ppts[poffs[j]: poffs[j + 1]]), 1), 3), np.nan), 1
    counts = np.array([len(p) for p in paths], dtype=np.int64)
    offs = np.zeros(len(paths) + 1, dtype=np.int64)
    np.cumsum(counts, out=offs[1:])
    return np.concatenate([np.asarray(p, dtype=np.float64) for p in paths]), offs, flags
