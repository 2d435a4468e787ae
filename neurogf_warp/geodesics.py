"""Ground-truth geodesic distances and shortest paths on triangle meshes (Warp).

Method (see kernels/geodesic.py): a Steiner-point graph with k points per edge, relaxed face by face by a
parallel Bellman-Ford (uint64 atomic_min on (distance, parent)), where every node also carries one
unfolding window so rays continue straight across faces (exact triangle unfolding). Every value is the
length of a real surface path, so distances are upper bounds of the exact geodesic distance.
With ``windows=False`` it is the plain Steiner graph, the same graph as :func:`steiner_dijkstra`.

All solving happens in the mesh's normalized frame (float32); public results are in the mesh's units.
"""
from __future__ import annotations

import time

import numpy as np
import warp as wp

from .arrays import resolve_device
from .mesh import Mesh, load_mesh

__all__ = ["geodesic_distances", "geodesic_paths", "GeodesicSolver", "steiner_dijkstra", "DEFAULT_K",
           "resample_polyline"]

DEFAULT_K = 3  # Steiner points per edge at default accuracy (windows on); see benchmarks/geodesics_notes.md
DEFAULT_DELTA = 2.0  # delta-stepping bucket (mean edge lengths): few iterations, ~2.4 improvements per node
PATH_DELTA = DEFAULT_DELTA  # paths come from the same run as distances: every node keeps a path record that never
#                             goes stale, and distances are made equal to the traced lengths (GeodesicSolver.trace)
BYTES_PER_NODE = 110  # solver state per (source row, node): see GeodesicSolver._alloc
MAX_BATCH = 512


def _kernels():
    from neurogf_warp.kernels import geodesic as kg  # imported lazily so `import neurogf_warp` stays light

    return kg


class Topology:
    """Unique edges, face->edge and edge->face tables (numpy), with degenerate faces removed."""

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
        ef = np.full((ne, 2), -1, dtype=np.int32)
        order = np.argsort(inv, kind="stable")
        e_sorted = inv[order]
        first = np.r_[True, e_sorted[1:] != e_sorted[:-1]]
        rank = np.arange(len(order)) - np.maximum.accumulate(np.where(first, np.arange(len(order)), 0))
        face_of = order // 3
        m = rank < 2  # non-manifold edges keep their first two faces for window bookkeeping
        ef[e_sorted[m], rank[m]] = face_of[m]
        self.edge_faces = ef
        self.nonmanifold_edges = int(np.sum(rank >= 2))
        # node -> faces (CSR): faces around each vertex, and all faces of each edge (non-manifold ones too)
        nvtx = len(vertices)
        fo = np.argsort(f.reshape(-1), kind="stable")
        self.vf_idx = (fo // 3).astype(np.int32)
        self.vf_off = np.r_[0, np.cumsum(np.bincount(f.reshape(-1), minlength=nvtx))].astype(np.int32)
        self.ef_idx = face_of.astype(np.int32)
        self.ef_off = np.r_[0, np.cumsum(np.bincount(inv, minlength=ne))].astype(np.int32)
        self.face_ok = window_faces(vertices, f)


def window_faces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """int8 per face: 1 where unfolding windows may cross the face, 0 for graph-only faces.

    Unfolding a virtual source across an edge uses the in-plane normal towards the face's third vertex; when that
    vertex is (nearly) on the edge's line (zero-area faces, needles, caps, coincident vertices) the normal is float
    noise and the unfolded source lands anywhere: values below the exact distance, paths the tracer cannot walk.
    Such faces keep only their graph edges (always real segments). A face is kept for windows when its smallest
    height (2 area / longest edge) is at least 1% of its longest edge (smallest angle about 0.6 degrees or more)
    and at least 1% of the mean edge length and 1e-5 absolute (pass the float32 positions the kernels use, in the
    normalized unit-sphere frame, for the absolute part to mean anything)."""
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0:
        return np.zeros(0, np.int8)
    p = np.asarray(vertices, dtype=np.float64)[f]
    area2 = np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    elen = np.linalg.norm(p - p[:, [1, 2, 0]], axis=2)
    lmax = elen.max(axis=1)
    hmin = area2 / np.maximum(lmax, 1e-300)
    floor = max(1e-2 * float(elen.mean()), 1e-5)
    ok = (hmin >= 1e-2 * lmax) & (hmin >= floor) & np.isfinite(hmin)
    return ok.astype(np.int8)


class GeodesicSolver:
    """Multi-source solver bound to one mesh and device. Reuse it for many sources.

    k: Steiner points per edge; windows: exact unfolding on (upper bounds either way);
    batch: source rows solved together (default: from a memory budget: 25% of the free device memory on CUDA,
    1 GB on CPU; BYTES_PER_NODE per row and node); max_iter: safety cap on iterations.
    worklist: each iteration touches only the frontier (nodes improved in the previous one) instead of every
    (row, face) and (row, node); False keeps the dense passes (same results, kept as a reference).
    """

    def __init__(self, mesh, k: int = DEFAULT_K, windows: bool = True, device=None, batch: int | None = None,
                 max_iter: int = 100000, memory_budget: float | None = None, max_rows: int | None = None,
                 delta: float = DEFAULT_DELTA, worklist: bool = True):
        self.mesh = load_mesh(mesh)
        if k < 1:
            raise ValueError("k (Steiner points per edge) must be >= 1")
        self.k = int(k)
        self.windows = bool(windows)
        self.device = resolve_device(device)
        self.max_iter = int(max_iter)
        self.worklist = bool(worklist)
        t0 = time.perf_counter()
        # window-face test on the float32 normalized positions the kernels use (see window_faces)
        self.topo = Topology(self.mesh.normalized_vertices.astype(np.float32), self.mesh.faces)
        self.nv = len(self.mesh.vertices)
        # delta-stepping bucket width, in mean edge lengths (normalized frame)
        e = self.topo.edges
        nvx = self.mesh.normalized_vertices
        mean_len = float(np.linalg.norm(nvx[e[:, 0]] - nvx[e[:, 1]], axis=1).mean()) if len(e) else 1.0
        self.delta = float(delta) * mean_len if delta and delta > 0 else float("inf")
        self.n_nodes = self.nv + len(self.topo.edges) * self.k
        if self.n_nodes >= 2**31 - 1:
            raise ValueError("mesh too large for int32 node ids; lower k")
        if memory_budget is None:
            memory_budget = 1e9
            if self.device.is_cuda:
                free = getattr(self.device, "free_memory", None)
                memory_budget = 0.25 * float(free) if free else 8e9
        if batch is None:
            batch = int(max(1, min(MAX_BATCH, memory_budget // (self.n_nodes * BYTES_PER_NODE))))
            if max_rows:
                batch = min(batch, int(max_rows))
        self.batch = int(batch)
        self.timings = {"setup_s": time.perf_counter() - t0, "solve_s": 0.0, "iterations": []}
        self._alloc()
        self._graph = None
        self.rows = None

    # ---- device state -------------------------------------------------------------------------
    def _alloc(self):
        d, b, n = self.device, self.batch, self.n_nodes
        t = self.topo
        self.pos = wp.array(self.mesh.normalized_vertices.astype(np.float32), dtype=wp.vec3, device=d)
        self.faces_w = wp.array(t.faces, dtype=int, device=d)
        self.edges_w = wp.array(t.edges, dtype=int, device=d)
        self.fe_w = wp.array(t.face_edges, dtype=int, device=d)
        self.ef_w = wp.array(t.edge_faces, dtype=int, device=d)
        self.fok_w = wp.array(t.face_ok, dtype=wp.int8, device=d)
        self.src_w = wp.zeros(b, dtype=int, device=d)
        z = lambda dt: wp.zeros((b, n), dtype=dt, device=d)  # noqa: E731
        self.key = z(wp.uint64)
        self.dist, self.parent, self.in_face, self.info = z(float), z(int), z(int), z(int)
        self.w = [z(float) for _ in range(5)]  # a, h, sigma, L, R
        self.nw = [z(float) for _ in range(5)]
        self.n_in_face, self.n_info = z(int), z(int)
        self.changed, self.improved = z(wp.int8), z(wp.int8)
        # path records (never stale; see kernels/geodesic.py) and their staging
        self.origin, self.n_origin = z(int), z(int)
        self.pa, self.ph = z(float), z(float)
        # frontier worklists: two ping-pong lists, the per-iteration improved list, and their stamps
        self.vf_off, self.vf_idx = wp.array(t.vf_off, dtype=int, device=d), wp.array(t.vf_idx, dtype=int, device=d)
        self.ef_off, self.ef_idx = wp.array(t.ef_off, dtype=int, device=d), wp.array(t.ef_idx, dtype=int, device=d)
        self.lists = [z(int), z(int)]
        self.counts = [wp.zeros(b, dtype=int, device=d), wp.zeros(b, dtype=int, device=d)]
        self.tlist, self.tcount = z(int), wp.zeros(b, dtype=int, device=d)
        self.qstamp, self.tstamp = z(int), z(int)
        self.work = wp.zeros((b, 3), dtype=int, device=d)
        # threads per row of the list launches (a grid-stride loop covers longer lists)
        self.row_threads = max(32, min(4096, (1 << 18) // b)) if d.is_cuda else 1
        self.thr = wp.zeros(b, dtype=float, device=d)
        self.minpend = wp.zeros(b, dtype=float, device=d)
        self.cond = wp.zeros(1, dtype=int, device=d)
        self.counter = wp.zeros(1, dtype=int, device=d)

    def _step(self, c, x):
        """One worklist iteration: relax lists[c], build lists[x]."""
        kg = _kernels()
        d, b, T = self.device, self.batch, self.row_threads
        wp.launch(kg.clear_list_kernel, dim=b, device=d,
                  inputs=[self.cond, self.counter, self.thr, self.minpend, self.delta, self.counts[x], self.tcount])
        wp.launch(kg.relax_list_kernel, dim=(b, T), device=d,
                  inputs=[self.nv, self.k, int(self.windows), self.pos, self.faces_w, self.edges_w, self.fe_w,
                          self.fok_w, self.vf_off, self.vf_idx, self.ef_off, self.ef_idx, self.dist, self.in_face,
                          *self.w, self.lists[c], self.counts[c], self.lists[x], self.counts[x], self.qstamp,
                          self.tlist, self.tcount, self.tstamp, self.thr, self.minpend, self.key, self.counter,
                          self.cond, self.max_iter, self.work, T])
        wp.launch(kg.decode_list_kernel, dim=(b, T), device=d,
                  inputs=[self.nv, self.k, int(self.windows), self.pos, self.faces_w, self.edges_w, self.fe_w,
                          self.ef_w, self.fok_w, self.key, self.dist, self.in_face, *self.w, self.improved,
                          self.n_in_face, self.n_info, *self.nw, self.n_origin, self.origin, self.pa, self.ph,
                          self.tlist, self.tcount, self.work, T])
        wp.launch(kg.commit_list_kernel, dim=(b, T), device=d,
                  inputs=[self.key, self.dist, self.parent, self.in_face, self.info, *self.w, self.improved,
                          self.n_in_face, self.n_info, *self.nw, self.n_origin, self.origin, self.tlist,
                          self.tcount, self.lists[x], self.counts[x], self.qstamp, self.cond, self.counter,
                          self.max_iter, self.minpend, T])

    def _list_body(self):
        # two iterations per body so the ping-pong lists need no copy (the second one is empty once done)
        self._step(0, 1)
        self._step(1, 0)

    def _consistent(self):
        """Lower each distance to the exact length of the path its records describe (pointer jumping)."""
        kg = _kernels()
        d, dims = self.device, (self.batch, self.n_nodes)
        ptr, acc = [self.n_origin, self.n_info], [self.nw[0], self.nw[1]]  # staging is free after the solve
        wp.launch(kg.slack_init_kernel, dim=dims, device=d,
                  inputs=[self.nv, self.k, self.pos, self.faces_w, self.edges_w, self.dist, self.parent, self.info,
                          self.origin, self.pa, self.ph, ptr[0], acc[0]])
        rounds = max(1, int(np.ceil(np.log2(max(self.n_nodes, 2)))))
        for r in range(rounds):
            wp.launch(kg.slack_jump_kernel, dim=dims, device=d,
                      inputs=[ptr[r % 2], acc[r % 2], ptr[(r + 1) % 2], acc[(r + 1) % 2]])
        wp.launch(kg.slack_apply_kernel, dim=dims, device=d, inputs=[acc[rounds % 2], self.dist])

    def _body(self):
        kg = _kernels()
        d, b, t = self.device, self.batch, self.topo
        nf, n = len(t.faces), self.n_nodes
        wp.launch(kg.clear_flag_kernel, dim=b, inputs=[self.cond, self.counter, self.thr, self.minpend, self.delta],
                  device=d)
        wp.launch(kg.relax_kernel, dim=(b, nf), device=d,
                  inputs=[self.nv, self.k, int(self.windows), self.pos, self.faces_w, self.edges_w, self.fe_w,
                          self.fok_w, self.dist, self.in_face, *self.w, self.changed, self.thr, self.key])
        wp.launch(kg.decode_kernel, dim=(b, n), device=d,
                  inputs=[self.nv, self.k, int(self.windows), self.pos, self.faces_w, self.edges_w, self.fe_w,
                          self.ef_w, self.fok_w, self.key, self.dist, self.in_face, *self.w, self.improved,
                          self.n_in_face, self.n_info, *self.nw, self.n_origin, self.origin, self.pa, self.ph])
        wp.launch(kg.commit_kernel, dim=(b, n), device=d,
                  inputs=[self.key, self.dist, self.parent, self.in_face, self.info, *self.w, self.improved,
                          self.n_in_face, self.n_info, *self.nw, self.n_origin, self.origin, self.changed, self.cond,
                          self.counter, self.max_iter, self.thr, self.minpend])

    def _program(self):
        kg = _kernels()
        wp.launch(kg.init_kernel, dim=(self.batch, self.n_nodes), device=self.device,
                  inputs=[self.src_w, self.key, self.dist, self.parent, self.in_face, self.info, self.changed,
                          self.origin])
        self.cond.fill_(1)
        self.counter.zero_()
        self.minpend.zero_()  # the sources sit at distance 0
        self.work.zero_()
        if self.worklist:
            self.qstamp.zero_()
            self.tstamp.zero_()
            wp.launch(kg.init_list_kernel, dim=self.batch, device=self.device,
                      inputs=[self.src_w, self.lists[0], self.counts[0], self.minpend])
            wp.capture_while(self.cond, self._list_body)
        else:
            wp.capture_while(self.cond, self._body)
        self._consistent()

    def _run_program(self):
        # One graph replay per batch: the loop runs on the device without host syncs. If capture is not
        # available (old driver, CPU quirks) the same program runs with a host-side loop.
        if self._graph is None and self._graph is not False:
            try:
                with wp.ScopedCapture(device=self.device, force_module_load=True) as cap:
                    self._program()
                self._graph = cap.graph
            except Exception:  # noqa: BLE001 - any capture failure falls back to the host loop
                self._graph = False
        if self._graph:
            wp.capture_launch(self._graph)
        else:
            self._program()

    def run(self, sources: np.ndarray) -> None:
        """Solve for up to `batch` internal source vertex ids; results stay on the device (rows 0..len-1)."""
        src = np.asarray(sources, dtype=np.int64).reshape(-1)
        if len(src) == 0 or len(src) > self.batch:
            raise ValueError(f"run() takes 1..{self.batch} sources, got {len(src)}")
        if src.min() < 0 or src.max() >= self.nv:
            raise IndexError("internal source id out of range")
        padded = np.full(self.batch, src[-1], dtype=np.int32)
        padded[: len(src)] = src
        t0 = time.perf_counter()
        self.src_w.assign(padded)
        self._run_program()
        wp.synchronize_device(self.device)
        self.timings["solve_s"] += time.perf_counter() - t0
        self.timings["iterations"].append(int(self.counter.numpy()[0]))
        w = self.work.numpy()[: len(src)].sum(axis=0)
        self.timings.setdefault("work", []).append([int(v) for v in w])
        self.rows = src

    def work_stats(self) -> dict:
        """Work of the last run per source: relaxed nodes, node visits (list entries or dense (row, node)/(row,
        face) items) and iterations; the dense solver's visits are iterations * (faces + 2 nodes)."""
        it = self.timings["iterations"][-1]
        rel, read, dec = self.timings["work"][-1]
        n = len(self.rows)
        if self.worklist:
            visits = (read + 2 * dec) / n
        else:
            visits = it * (len(self.topo.faces) + 2 * self.n_nodes)
        return {"iterations": it, "relaxed_per_source": rel / n if self.worklist else None,
                "visits_per_source": float(visits), "nodes": self.n_nodes}

    def vertex_distances(self) -> np.ndarray:
        """(rows, V) float32 distances of the last run, normalized units (inf = unreachable)."""
        return self.dist.numpy()[: len(self.rows), : self.nv].copy()

    def solve(self, sources: np.ndarray) -> np.ndarray:
        """(S, V) normalized distances for any number of internal source ids."""
        src = np.asarray(sources, dtype=np.int64).reshape(-1)
        out = np.empty((len(src), self.nv), dtype=np.float32)
        for i in range(0, len(src), self.batch):
            self.run(src[i: i + self.batch])
            out[i: i + self.batch] = self.vertex_distances()
        return out

    def trace(self, rows: np.ndarray, targets: np.ndarray, max_steps: int | None = None):
        """Shortest paths of the last run: row r's source to internal vertex targets[i].

        Returns (points (P,3) float32 normalized, offsets (T+1,), stale (T,)); path i is
        points[offsets[i]:offsets[i+1]] ordered from the source. Paths follow each node's path record (a graph
        edge, or a straight unfolded ray walked face by face to its origin node), so a path's length equals the
        node's distance up to float rounding. stale counts rays whose walk failed numerically (the path then
        jumps to the ray's origin; not seen in the tests); -1 = truncated (max_steps).
        """
        kg = _kernels()
        rows = np.asarray(rows, dtype=np.int32).reshape(-1)
        targets = np.asarray(targets, dtype=np.int32).reshape(-1)
        T = len(targets)
        if T == 0:
            return np.zeros((0, 3), np.float32), np.zeros(1, np.int64), np.zeros(0, np.int32)
        if max_steps is None:
            max_steps = 4 * (max(self.timings["iterations"][-1], 1) + 16) * (self.k + 1)
            max_steps = max(max_steps, int(64 * np.sqrt(len(self.topo.faces))) + 1024)
        d = self.device
        rw = wp.array(rows, dtype=int, device=d)
        tw = wp.array(targets, dtype=int, device=d)
        counts = wp.zeros(T, dtype=int, device=d)
        stale = wp.zeros(T, dtype=int, device=d)
        offs = wp.zeros(T, dtype=int, device=d)
        dummy = wp.zeros(1, dtype=wp.vec3, device=d)
        args = [self.nv, self.k, self.pos, self.faces_w, self.edges_w, self.fe_w, self.ef_w, self.fok_w, rw, tw,
                self.parent,
                self.info, self.origin, self.pa, self.ph, max_steps]
        wp.launch(kg.walk_kernel, dim=T, inputs=args + [0, offs, dummy, counts, stale], device=d)
        c = counts.numpy().astype(np.int64)
        offsets = np.zeros(T + 1, dtype=np.int64)
        np.cumsum(c, out=offsets[1:])
        if offsets[-1] >= 2**31:
            raise MemoryError("too many path points in one trace call; trace fewer targets at a time")
        offs.assign(offsets[:-1].astype(np.int32))
        pts = wp.zeros(max(int(offsets[-1]), 1), dtype=wp.vec3, device=d)
        wp.launch(kg.walk_kernel, dim=T, inputs=args + [1, offs, pts, counts, stale], device=d)
        p = pts.numpy()[: offsets[-1]]
        # written target->source: reverse each path so it starts at the source
        seg = np.repeat(np.arange(T), c)
        local = np.arange(len(p)) - offsets[seg]
        p = p[offsets[seg] + (c[seg] - 1 - local)]
        return p, offsets, stale.numpy()


# ---- public functions -----------------------------------------------------------------------------
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


# ---- CPU reference ---------------------------------------------------------------------------------
def steiner_graph(mesh, k: int):
    """The explicit Steiner graph (scipy CSR, float64 weights in normalized units) used by the solver."""
    import scipy.sparse as sp

    m = load_mesh(mesh)
    topo = Topology(m.vertices, m.faces)
    pos = m.normalized_vertices
    nv, ne = len(pos), len(topo.edges)
    t = (np.arange(k) + 1.0) / (k + 1.0)
    e0, e1 = pos[topo.edges[:, 0]], pos[topo.edges[:, 1]]
    epts = (e0[:, None, :] + t[None, :, None] * (e1 - e0)[:, None, :]).reshape(-1, 3)
    allpos = np.concatenate([pos, epts])
    F = len(topo.faces)
    slots = np.concatenate([topo.faces, (nv + topo.face_edges[:, :, None] * k + np.arange(k)).reshape(F, -1)], 1)
    ii, jj = np.meshgrid(np.arange(slots.shape[1]), np.arange(slots.shape[1]), indexing="ij")
    sel = ii < jj
    a = slots[:, ii[sel]].ravel()
    b = slots[:, jj[sel]].ravel()
    w = np.linalg.norm(allpos[a] - allpos[b], axis=1)
    n = nv + ne * k
    g = sp.coo_matrix((w, (a, b)), shape=(n, n)).tocsr()  # duplicates would sum: dedupe first
    key = np.minimum(a, b).astype(np.int64) * n + np.maximum(a, b)
    uk, first = np.unique(key, return_index=True)
    g = sp.coo_matrix((w[first], (a[first], b[first])), shape=(n, n)).tocsr()
    return g + g.T, nv


def steiner_dijkstra(mesh, sources, k: int = DEFAULT_K) -> np.ndarray:
    """Plain CPU Dijkstra (scipy) on the same Steiner graph: (S, V_input) distances in mesh units."""
    from scipy.sparse.csgraph import dijkstra

    m = load_mesh(mesh)
    src = _sources(m, sources)
    g, nv = steiner_graph(m, k)
    d = dijkstra(g, directed=False, indices=src)[:, :nv] / m.scale
    return m.to_input(d.astype(np.float32))
