"""The ground-truth geodesic solver: device state, the captured relaxation loop, distances and traced paths.

Method (kernels/geodesic): a Steiner-point graph with k points per edge, relaxed by a frontier worklist in
delta-stepping order (uint64 atomic_min on (distance, parent)), where every node also carries one unfolding
window so rays continue straight across faces (exact triangle unfolding). Every value is the length of a real
surface path, so distances are upper bounds of the exact geodesic distance. With ``windows=False`` it is the
plain Steiner graph. All solving happens in the mesh's normalized frame (float32).
"""
from __future__ import annotations

import hashlib
import time
from collections import OrderedDict

import numpy as np
import warp as wp

from neurogf_warp.common.arrays import resolve_device
from neurogf_warp.ground_truth.steiner_graph import Topology, stable_sort
from neurogf_warp.mesh.mesh import load_mesh

__all__ = ["GeodesicSolver", "load_kernels", "clear_solver_cache", "SOLVER_CACHE_SIZE", "DEFAULT_K", "DEFAULT_DELTA",
           "PATH_DELTA", "PATH_TOLERANCE", "BYTES_PER_NODE"]

DEFAULT_K = 3  # Steiner points per edge at default accuracy (windows on); accuracy per k: docs/design.md
DEFAULT_DELTA = 2.0  # delta-stepping bucket (mean edge lengths): few iterations, ~2.4 improvements per node
PATH_DELTA = DEFAULT_DELTA  # paths come from the same run as distances (every node keeps a path record)
BYTES_PER_NODE = 109  # solver state per (source row, node): see GeodesicSolver._alloc
PATH_TOLERANCE = 1e-3  # a traced path longer than its distance by more than this (relative) is not returned
PATH_ABS_TOLERANCE = 1e-6  # and by more than this (normalized units: float32 rounding of short paths)
MAX_BATCH = 512
REORDER = True  # number the solver's vertices along a Morton curve (memory locality; results in mesh order)
ROW_THREADS = (32, 16384, 1 << 20)  # CUDA list launches: entries per row, at least, at most, over all rows
RELAX_LANES = 4  # CUDA threads per list entry in relax_frontier (kernels/ground_truth/relax.py)
CPU_CHUNK_SECONDS = 0.25  # one CPU launch of the relaxation loop; Ctrl-C is seen between launches
LOAD_WORKERS = 16  # threads compiling Warp modules before the first capture (load_for_capture)
CPU_MEMORY_SHARE = 0.4  # of the available memory, at most, for one CPU solver's state (worker processes each
# build their own solver, which sees what the others left)


def points_per_path(m) -> int:
    """``m`` (points per resampled path) as an int; TypeError / ValueError unless an integer >= 2."""
    if isinstance(m, bool) or not isinstance(m, (int, np.integer)):
        raise TypeError(f"m (points per resampled path) must be an integer, got {m!r}")
    if m < 2:
        raise ValueError(f"m (points per resampled path) must be >= 2 (both ends), got {m}")
    return int(m)


def _spread_bits(x: np.ndarray) -> np.ndarray:
    """uint64 values below 2^21 with bit b moved to bit 3 b (the other bits 0)."""
    x = x & np.uint64(0x1FFFFF)
    for shift, mask in ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F),
                        (4, 0x10C30C30C30C30C3), (2, 0x1249249249249249)):
        x = (x | (x << np.uint64(shift))) & np.uint64(mask)
    return x


def spatial_order(points: np.ndarray, bits: int = 16) -> np.ndarray:
    """(n,) int64: the points sorted along a Morton (Z-order) curve of 2^bits cells per axis, ties in input
    order. Nearby points get nearby ranks, so per-node state of neighbouring nodes shares cache lines."""
    p = np.asarray(points, dtype=np.float64)
    if len(p) == 0:
        return np.zeros(0, dtype=np.int64)
    lo = p.min(axis=0)
    span = float((p.max(axis=0) - lo).max())
    q = np.floor((p - lo) / (span if span > 0 else 1.0) * (2**bits - 1)).astype(np.uint64)
    if bits <= 21:  # bit b of axis a goes to bit 3 b + a: five shift-and-mask steps per axis
        code = _spread_bits(q[:, 0]) | (_spread_bits(q[:, 1]) << np.uint64(1)) | \
            (_spread_bits(q[:, 2]) << np.uint64(2))
    else:
        code = np.zeros(len(p), dtype=np.uint64)
        for b in range(bits):
            for axis in range(3):
                code |= ((q[:, axis] >> np.uint64(b)) & np.uint64(1)) << np.uint64(3 * b + axis)
    return np.argsort(code, kind="stable")


SOLVER_CACHE_SIZE = 2  # meshes whose solver tables GeodesicSolver(cache=True) keeps (clear_solver_cache frees them)
_SOLVER_CACHE: OrderedDict = OrderedDict()  # (mesh content, k, windows, device) -> tables, least recent first


def clear_solver_cache() -> None:
    """Free the mesh tables that ``GeodesicSolver(cache=True)`` (the public calls) keeps between calls."""
    _SOLVER_CACHE.clear()


def _cache_key(mesh, k: int, windows: bool, device) -> tuple:
    """The solver tables' key: a hash of the mesh's exact vertices (float64), faces and normalization, with the
    settings the tables depend on (the module-level ones included, read now: a changed constant builds anew)."""
    from neurogf_warp.ground_truth import steiner_graph as sg

    h = hashlib.blake2b(digest_size=20)
    for a in (mesh.internal_vertices, mesh.internal_faces, mesh.center, np.float64(mesh.scale)):
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.data if a.ndim else a.tobytes())
    tunables = (REORDER, sg.STEINER_ASPECT, sg.MAX_STEINER, sg.GRAPH_ONLY_FACTOR, sg.WINDOW_FACE_MIN_RELATIVE_HEIGHT,
                sg.WINDOW_FACE_MIN_HEIGHT, sg.SLOT_EDGE_BITS)
    return h.hexdigest(), int(k), bool(windows), str(device), repr(tunables)


def _count(name: str, value) -> int:
    """An integer setting >= 1, or a clear error naming it."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be an integer, got {value!r}")
    if value < 1:
        raise ValueError(f"{name} must be >= 1, got {value}")
    return int(value)


def _kernels():
    from neurogf_warp.kernels import ground_truth as kg  # imported lazily so `import neurogf_warp` stays light

    return kg


def available_memory(device) -> float | None:
    """Bytes free on a CUDA ``device``, or the system's available memory for the CPU (``MemAvailable`` in
    /proc/meminfo, else free pages); None where it cannot be told."""
    if device.is_cuda:
        free = getattr(device, "free_memory", None)
        return float(free) if free else None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024.0
    except OSError:
        pass
    try:
        import os

        return float(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def load_kernels(device=None) -> None:
    """Compile (or load from Warp's kernel cache) the solver's kernels for `device` ahead of the first solve."""
    _kernels().load(resolve_device(device))


_LOAD_S = [0.0]  # seconds this process has spent in load_for_capture


def load_seconds() -> float:
    """Seconds this process has spent loading Warp modules for the solver (``load_for_capture``): a caller that
    reads it before and after a piece of work knows what compiling cost that work."""
    return _LOAD_S[0]


def load_for_capture(device) -> None:
    """Every imported module with Warp code, loaded on ``device`` in parallel threads (one per core, at most
    ``LOAD_WORKERS``), ahead of the solver's first graph capture. The capture force-loads all of them itself, one
    after another: on a fresh 2-core CPU that was ~7 s after the solver's own two modules (warp.utils 4.0 s, the
    dataset's SDF kernel 2.8 s, Warp's coloring and math), all inside a 20 s budget's ground-truth share
    (docs/performance.md). NVRTC and Warp's CPU compiler run outside the GIL."""
    import os

    _kernels()  # the solver's modules are among them
    t0 = time.perf_counter()
    wp.force_load(device, max_workers=max(1, min(os.cpu_count() or 1, LOAD_WORKERS)))
    _LOAD_S[0] += time.perf_counter() - t0


class GeodesicSolver:
    """Multi-source solver bound to one mesh and device. Reuse it for many sources.

    Parameters
    ----------
    mesh : path, (V, F) pair, trimesh.Trimesh or Mesh
    k : int
        Steiner points per edge (accuracy; memory and time grow about linearly).
    windows : bool
        Exact unfolding windows (on: default accuracy; off: the plain Steiner graph). Upper bounds either way.
    device : str or warp.Device, optional
    batch : int, optional
        Source rows solved together. Default: from a memory budget (25% of the free device memory on CUDA;
        on the CPU 1 GB, or less where less memory is available) at BYTES_PER_NODE per row and node, at most 512
        (and at most `max_rows`). On the CPU a given batch is lowered to the rows that fit in
        ``CPU_MEMORY_SHARE`` of the available memory (the rows are the same; only their grouping changes).
        MemoryError (before anything is allocated) where even one row does not fit.
    max_iter : int
        Safety cap on iterations.
    delta : float
        Delta-stepping bucket width in mean edge lengths (0: plain Bellman-Ford).
    cache : bool
        Keep this solver's mesh tables (vertex order, topology, Steiner graph on the device; not the per-source
        state) for later solvers on the same mesh, k, windows and device, which then skip that set-up: the
        last ``SOLVER_CACHE_SIZE`` meshes are kept, ``clear_solver_cache()`` frees them. The public calls
        (``geodesic_distances``, ``geodesic_paths``) use it; the results are the same either way.
    """

    def __init__(self, mesh, k: int = DEFAULT_K, windows: bool = True, device=None, batch: int | None = None,
                 max_iter: int = 100000, memory_budget: float | None = None, max_rows: int | None = None,
                 delta: float = DEFAULT_DELTA, cache: bool = False):
        self.mesh = load_mesh(mesh)
        self.k = _count("k (Steiner points per edge)", k)
        self.windows = bool(windows)
        self.device = resolve_device(device)
        self.max_iter = _count("max_iter", max_iter)
        if isinstance(delta, bool) or not isinstance(delta, (int, float, np.integer, np.floating)) \
                or not np.isfinite(delta) or delta < 0:
            raise ValueError(f"delta must be a finite number >= 0 (0: plain Bellman-Ford), got {delta!r}")
        t0 = time.perf_counter()
        # The solver numbers vertices along a Morton curve (and faces by their lowest vertex), so that a node's
        # neighbours sit close in memory (Steiner nodes follow their edges, edges their vertices); the mesh's own
        # numbering is restored at run / vertex_distances / trace. Bunny subdivided once (139K vertices), one
        # source on the CPU: 5.4-5.8 s against 6.6-8.2 s in file order, same results up to the order-dependence of
        # the windows.
        phases = {}
        t1 = t0

        def lap(name):
            nonlocal t1
            now = time.perf_counter()
            phases[name] = phases.get(name, 0.0) + now - t1
            t1 = now

        self.nv = len(self.mesh.internal_vertices)
        self.graph = None
        key = _cache_key(self.mesh, self.k, self.windows, self.device) if cache else None
        tables = _SOLVER_CACHE.get(key) if cache else None
        if tables is not None:
            _SOLVER_CACHE.move_to_end(key)
            self._order, self._solver_id, self._positions, self.topo, mean_len, self._edge_node_start, \
                self.graph = tables
            lap("cached_tables")
        else:
            nv64 = self.mesh.internal_normalized_vertices
            x32 = nv64.astype(np.float32)
            self._order = spatial_order(x32) if REORDER else np.arange(self.nv)  # solver id -> mesh id
            self._solver_id = np.empty(self.nv, dtype=np.int64)  # mesh id -> solver id
            self._solver_id[self._order] = np.arange(self.nv)
            faces = self._solver_id[np.asarray(self.mesh.internal_faces, dtype=np.int64)]
            if REORDER:
                lowest = np.minimum(np.minimum(faces[:, 0], faces[:, 1]), faces[:, 2])  # faces.min(axis=1), faster
                faces = faces[stable_sort(lowest, max(self.nv, 1))[1]]
            self._positions = x32[self._order]
            lap("order")
            # window-face test on the float32 normalized positions the kernels use (see window_faces)
            self.topo = Topology(self._positions, faces)
            lap("topology")
            # delta-stepping bucket width, in mean edge lengths (normalized frame)
            e = self.topo.edges
            nvx = nv64[self._order]
            mean_len = float(np.linalg.norm(nvx[e[:, 0]] - nvx[e[:, 1]], axis=1).mean()) if len(e) else 1.0
            # Steiner points: k per edge, more on long edges of thin faces (steiner_graph.steiner_counts)
            self._edge_node_start = self.topo.steiner_start(self.k)
            lap("steiner_counts")
        self.mean_edge = mean_len  # normalized frame
        self.delta = float(delta) * mean_len if delta > 0 else float("inf")
        self._nodes = None
        self.n_nodes = self.nv + int(self._edge_node_start[-1])
        if self.n_nodes >= 2**31 - 1:
            raise ValueError(f"mesh too large for int32 node ids at k={self.k} ({self.n_nodes} nodes); lower k")
        free = available_memory(self.device)
        if memory_budget is None:
            if self.device.is_cuda:
                memory_budget = 0.25 * free if free else 8e9
            else:
                memory_budget = 1e9 if free is None else min(1e9, CPU_MEMORY_SHARE * free)
        if batch is None:
            batch = int(max(1, min(MAX_BATCH, memory_budget // self.bytes_per_row)))
            if max_rows:
                batch = min(batch, int(max_rows))
        batch = _count("batch", batch)
        if self.device.is_cpu and free is not None:
            # the dataset's CPU batch of 8 rows was 19 GB of state on a 2.2M-vertex mesh at k=3: the process was
            # killed by the kernel's out-of-memory killer (24 GB machine), hence the cap by free memory
            batch = min(batch, max(1, int(CPU_MEMORY_SHARE * free // self.bytes_per_row)))
        self.batch = batch
        need = self.batch * self.bytes_per_row
        # (on the CPU a single row may take more than CPU_MEMORY_SHARE, not more than there is)
        if free is not None and need > (free if self.device.is_cuda else 0.9 * free):
            raise MemoryError(f"one batch of {self.batch} source rows needs {need / 1e9:.2f} GB of solver state "
                              f"({self.bytes_per_row / 1e9:.3f} GB per row at k={self.k}, {self.n_nodes:,} graph "
                              f"nodes) but {self.device} has {free / 1e9:.2f} GB available; lower batch or k, "
                              "or use a smaller (decimated) mesh")
        self.timings = {"setup_s": time.perf_counter() - t0, "solve_s": 0.0, "iterations": [],
                        "setup_phases": phases}
        try:
            self._alloc()
        except Exception as e:  # noqa: BLE001 - allocation failures come as several types
            raise MemoryError(f"could not allocate the solver state on {self.device}: {need / 1e9:.2f} GB for "
                              f"{self.batch} source rows ({self.bytes_per_row / 1e9:.3f} GB per row at k={self.k}); "
                              f"lower batch or k ({e})") from e
        if cache and tables is None:
            _SOLVER_CACHE[key] = (self._order, self._solver_id, self._positions, self.topo, self.mean_edge,
                                  self._edge_node_start, self.graph)
            while len(_SOLVER_CACHE) > max(SOLVER_CACHE_SIZE, 0):
                _SOLVER_CACHE.popitem(last=False)
        # what a second solver on the same mesh needs to give the same rows (solver_workers.py)
        self.settings = {"k": self.k, "windows": self.windows, "delta": float(delta), "max_iter": self.max_iter,
                         "batch": self.batch}
        self._graphs = {}
        self._chunk = 16  # loop iterations per CPU launch, adapted to CPU_CHUNK_SECONDS
        self.rows = None
        self._started = None  # (sources, start time) of a batch begun by start()
        self._solver_id_w = None  # device copy of _solver_id, made by the first vertex_distances on CUDA
        self.timings["setup_s"] = time.perf_counter() - t0

    @property
    def nodes(self):
        """The Steiner nodes (``Topology.steiner_nodes``: edge_node_start, node_edge, node_t), host copies made on
        first use (the solver's own tables are built on its device)."""
        if self._nodes is None:
            self._nodes = self.topo.steiner_nodes(self.k, start=self._edge_node_start)
        return self._nodes

    @property
    def captured(self) -> bool:
        """Whether the relaxation loop runs as a captured graph (else from a host loop)."""
        return bool(self._graphs.get("loop"))

    @property
    def bytes_per_row(self) -> int:
        """Device memory of one source row of solver state (bytes)."""
        return self.n_nodes * BYTES_PER_NODE

    # ---- device state -------------------------------------------------------------------------
    def _alloc(self):
        kg = _kernels()
        d, b, n = self.device, self.batch, self.n_nodes
        phases = self.timings["setup_phases"]
        if self.graph is None:
            self.graph = self.topo.to_warp(self._positions, self.k, self.windows, d, self._edge_node_start,
                                           timings=phases)
        t1 = time.perf_counter()
        z = lambda dt: wp.zeros((b, n), dtype=dt, device=d)  # noqa: E731

        def windows():
            w = kg.unfolding.Windows()
            w.face, w.along, w.height, w.sigma, w.lo, w.hi = z(int), z(float), z(float), z(float), z(float), z(float)
            return w

        # per node: committed state 36 B (key, dist, window), path records 20, staging 33, worklists and stamps 20
        rec = kg.relax.PathRecords()
        rec.parent, rec.origin, rec.ray_face, rec.ray_along, rec.ray_height = z(int), z(int), z(int), z(float), \
            z(float)
        self.state = kg.relax.NodeState()
        self.state.key, self.state.dist, self.state.win, self.state.rec = z(wp.uint64), z(float), windows(), rec
        self.staged = kg.relax.Staging()
        self.staged.accept, self.staged.win, self.staged.origin, self.staged.ray_face = z(wp.int8), windows(), \
            z(int), z(int)
        self.src_w = wp.zeros(b, dtype=int, device=d)
        # threads per row of the list launches (a grid-stride loop covers longer lists)
        lo, hi, total = ROW_THREADS
        self.row_threads = max(lo, min(hi, total // b)) if d.is_cuda else 1
        self.lanes = RELAX_LANES if d.is_cuda else 1
        lists = [z(int), z(int)]
        line = lambda: wp.zeros((b, kg.relax.LINE), dtype=int, device=d)  # noqa: E731 - a row's counter per line
        counts = [line(), line()]
        shared = dict(queued=z(int), touched=z(int), touched_count=line(),
                      touched_stamp=z(int), threshold=wp.zeros(b, dtype=float, device=d),
                      min_pending=line(), delta=self.delta,
                      iteration=wp.zeros(1, dtype=int, device=d), go=wp.zeros(1, dtype=int, device=d),
                      iteration_limit=wp.zeros(1, dtype=int, device=d), work=line(),
                      threads=self.row_threads, lanes=self.lanes)
        # two iterations per loop body, ping-pong: the second swaps `active` and `next`
        self.fronts = []
        for c in (0, 1):
            f = kg.relax.Frontier()
            f.active, f.active_count, f.next, f.next_count = lists[c], counts[c], lists[1 - c], counts[1 - c]
            for name, value in shared.items():
                setattr(f, name, value)
            self.fronts.append(f)
        self._front_shared = shared
        phases["state"] = phases.get("state", 0.0) + time.perf_counter() - t1

    def _step(self, front):
        """One worklist iteration: relax front.active, build front.next."""
        kg = _kernels()
        d, b, T = self.device, self.batch, self.row_threads
        wp.launch(kg.relax.start_iteration, dim=b, inputs=[front], device=d)
        wp.launch(kg.relax.relax_frontier, dim=(b, T * self.lanes), inputs=[self.graph, self.state, front], device=d)
        wp.launch(kg.relax.decode_touched, dim=(b, T), inputs=[self.graph, self.state, self.staged, front], device=d)
        wp.launch(kg.relax.commit_touched, dim=(b, T), inputs=[self.state, self.staged, front], device=d)
        wp.launch(kg.relax.finish_iteration, dim=b, inputs=[front], device=d)

    def _loop_body(self):
        # two iterations per body so the ping-pong lists need no copy (the second one is empty once done)
        self._step(self.fronts[0])
        self._step(self.fronts[1])

    def _consistent(self):
        """Lower each distance to the exact length of the path its records describe (pointer jumping)."""
        kg = _kernels()
        d, dims = self.device, (self.batch, self.n_nodes)
        # the staging arrays are free after the solve
        ptr = [self.staged.origin, self.staged.ray_face]
        acc = [self.staged.win.along, self.staged.win.height]
        wp.launch(kg.paths.slack_init, dim=dims, inputs=[self.graph, self.state, ptr[0], acc[0]], device=d)
        rounds = max(1, int(np.ceil(np.log2(max(self.n_nodes, 2)))))
        for r in range(rounds):
            wp.launch(kg.paths.slack_jump, dim=dims, device=d,
                      inputs=[ptr[r % 2], acc[r % 2], ptr[(r + 1) % 2], acc[(r + 1) % 2]])
        wp.launch(kg.paths.slack_apply, dim=dims, inputs=[acc[rounds % 2], self.state.dist], device=d)

    def _start(self):
        kg = _kernels()
        sh = self._front_shared
        wp.launch(kg.relax.init_rows, dim=(self.batch, self.n_nodes), inputs=[self.src_w, self.state],
                  device=self.device)
        sh["iteration"].zero_()
        sh["min_pending"].zero_()  # the sources sit at distance 0 (float bits 0)
        sh["work"].zero_()
        sh["queued"].zero_()
        sh["touched_stamp"].zero_()
        wp.launch(kg.relax.init_frontier, dim=self.batch, inputs=[self.src_w, self.fronts[0]], device=self.device)

    def _loop(self):
        wp.capture_while(self._front_shared["go"], self._loop_body)

    def _launch(self, name: str, program):
        # Each program is captured once and replayed (the loop then runs on the device without host syncs);
        # where capture is not available the same program runs from the host.
        graph = self._graphs.get(name)
        if graph is None:
            # Before this solver's first capture every imported module loads in parallel (serially, at the capture,
            # the solver's own two took 5.3 of 9.5 s of a fresh H100's first solve), so that the capture's own
            # force-load finds them loaded: with force_module_load=False (6.2 s less on a fresh H100) 3 of 17 H100
            # training runs had the "start" capture fail (CUDA error 906, a memset on the legacy stream) and ran
            # the host loop; not understood.
            if not self._graphs:
                load_for_capture(self.device)
            try:
                with wp.ScopedCapture(device=self.device, force_module_load=True) as cap:
                    program()
                graph = cap.graph
            except Exception as e:  # noqa: BLE001 - any capture failure falls back to the host loop
                graph = False
                self.timings.setdefault("capture_failed", []).append(f"{name}: {type(e).__name__}: {e}"[:300])
                import warnings

                warnings.warn(f"the geodesic solver's {name!r} program could not be captured as a graph "
                              f"({type(e).__name__}: {str(e)[:200]}); it runs from the host instead (same results, "
                              "slower)", RuntimeWarning, stacklevel=2)
            self._graphs[name] = graph
        if graph:
            wp.capture_launch(graph)
        else:
            program()

    def run_seeds(self, seeds: np.ndarray) -> None:
        """Solve one row from several internal source vertex ids at once (distance to the nearest); the result is
        row 0 of ``vertex_distances``. The paths of such a run are not traced."""
        seeds = np.unique(np.asarray(seeds, dtype=np.int64).reshape(-1))
        if len(seeds) == 0 or seeds.min() < 0 or seeds.max() >= self.nv:
            raise IndexError("run_seeds takes 1 or more internal source ids in range")
        seeds_w = wp.array(self._solver_id[seeds].astype(np.int32), dtype=int, device=self.device)
        self.src_w.assign(np.full(self.batch, self._solver_id[seeds[0]], dtype=np.int32))
        self._timed_program(seeds_w)
        self.rows = seeds[:1]

    def _timed_program(self, extra_seeds=None):
        """``_run_program`` to the end on the device, its time and iterations added to ``timings``."""
        t0 = time.perf_counter()
        self._run_program(extra_seeds)
        self._end_program(t0)

    def _end_program(self, t0: float) -> None:
        """Wait for the program started at ``t0``; add its time and iterations to ``timings``; raise if it stopped
        at max_iter with work left."""
        wp.synchronize_device(self.device)
        self.timings["solve_s"] += time.perf_counter() - t0
        self.timings["iterations"].append(int(self._front_shared["iteration"].numpy()[0]))
        if self.fronts[0].active_count.numpy()[:, 0].any():
            raise RuntimeError(f"the geodesic solver did not converge in max_iter={self.max_iter} iterations; "
                               "raise max_iter")

    def _run_program(self, extra_seeds=None, block: bool = True):
        """Initialize, relax to convergence, make distances equal to path lengths. On the CPU the relaxation runs
        in chunks of about CPU_CHUNK_SECONDS (between chunks Python sees Ctrl-C); on CUDA in one launch, which
        with ``block=False`` is only queued (``_end_program`` waits and checks it).
        ``extra_seeds``: a device array of node ids that row 0 starts from as well (``run_seeds``)."""
        sh = self._front_shared
        self._launch("start", self._start)
        if extra_seeds is not None:
            wp.launch(_kernels().relax.add_seeds, dim=len(extra_seeds),
                      inputs=[extra_seeds, self.state, self.fronts[0]], device=self.device)
        done = 0
        while True:
            step = self.max_iter if self.device.is_cuda else self._chunk
            sh["iteration_limit"].fill_(min(done + step, self.max_iter))
            sh["go"].fill_(1)
            t0 = time.perf_counter()
            self._launch("loop", self._loop)
            self.timings["loop_launches"] = self.timings.get("loop_launches", 0) + 1
            if not block and self.device.is_cuda:
                break
            done = int(sh["iteration"].numpy()[0])
            if not self.fronts[0].active_count.numpy()[:, 0].any() or done >= self.max_iter:
                break  # done, or stopped at max_iter (_end_program raises)
            # keep each CPU chunk near the target time
            took = time.perf_counter() - t0
            if took < 0.5 * CPU_CHUNK_SECONDS:
                self._chunk = min(self._chunk * 2, 1 << 20)
            elif took > 2.0 * CPU_CHUNK_SECONDS:
                self._chunk = max(self._chunk // 2, 2)
        self._launch("finish", self._consistent)

    def _set_sources(self, sources: np.ndarray) -> np.ndarray:
        src = np.asarray(sources, dtype=np.int64).reshape(-1)
        if len(src) == 0 or len(src) > self.batch:
            raise ValueError(f"run() takes 1..{self.batch} sources, got {len(src)}")
        if src.min() < 0 or src.max() >= self.nv:
            raise IndexError("internal source id out of range")
        padded = np.full(self.batch, self._solver_id[src[-1]], dtype=np.int32)
        padded[: len(src)] = self._solver_id[src]
        self.src_w.assign(padded)
        return src

    def _record_work(self, src: np.ndarray) -> None:
        w = self._front_shared["work"].numpy()[: len(src), :3].sum(axis=0)
        self.timings.setdefault("work", []).append([int(v) for v in w])
        self.rows = src

    def run(self, sources: np.ndarray) -> None:
        """Solve for up to `batch` internal source vertex ids; results stay on the device (rows 0..len-1)."""
        src = self._set_sources(sources)
        self._timed_program()
        self._record_work(src)

    @property
    def can_start(self) -> bool:
        """Whether ``start`` runs a batch without waiting: CUDA, with the programs captured (by a first ``run``)."""
        return self.device.is_cuda and all(self._graphs.get(n) for n in ("start", "loop", "finish"))

    def start(self, sources: np.ndarray) -> None:
        """Begin ``run(sources)`` on the device and return at once (where ``can_start``; elsewhere, as on the CPU,
        the batch is solved before it returns); ``wait`` ends it. Between the two the solver's state is the new
        batch's, half done: read nothing from it."""
        src = self._set_sources(sources)
        self._started = (src, time.perf_counter())
        self._run_program(block=not self.can_start)

    def wait(self) -> None:
        """The end of the batch ``start`` began: as after ``run``."""
        src, t0 = self._started
        self._started = None
        self._end_program(t0)
        self._record_work(src)

    def work_stats(self) -> dict:
        """Work of the last run per source: iterations, relaxed nodes, node visits (list entries read + 2 x
        decoded entries) and the node count."""
        it = self.timings["iterations"][-1]
        rel, read, dec = self.timings["work"][-1]
        n = len(self.rows)
        return {"iterations": it, "relaxed_per_source": rel / n, "visits_per_source": float((read + 2 * dec) / n),
                "nodes": self.n_nodes}

    def vertex_distances(self) -> np.ndarray:
        """(rows, V) float32 distances of the last run, normalized units (inf = unreachable)."""
        rows = len(self.rows)
        if not self.device.is_cuda:  # a view of the host state: one numpy gather
            return self.state.dist.numpy()[:rows, : self.nv][:, self._solver_id]
        # on the device: copying every node of the whole batch to the host took longer than the gather
        if self._solver_id_w is None:
            self._solver_id_w = wp.array(self._solver_id.astype(np.int32), dtype=int, device=self.device)
        out = wp.empty((rows, self.nv), dtype=float, device=self.device)
        wp.launch(_kernels().build.gather_rows, dim=(rows, self.nv), inputs=[self.state.dist, self._solver_id_w],
                  outputs=[out], device=self.device)
        return out.numpy()

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

        Parameters
        ----------
        rows : (T,) int, source rows of the last `run`
        targets : (T,) int, internal vertex ids
        max_steps : int, optional cap on the walk per path

        Returns
        -------
        points : (P, 3) float32, normalized frame; path i is points[offsets[i]:offsets[i+1]], from the source
        offsets : (T + 1,) int64
        flags : (T,) int32, 0 for a path returned; 1 for a path that could not be traced or came out longer
            than its distance by more than PATH_TOLERANCE, -1 for one truncated at max_steps: the points of a
            flagged path are NaN. Unreachable targets have no points (flag 0).

        Paths follow each node's path record (a graph edge, or a straight unfolded ray walked face by face to its
        origin node), so a path's length equals the node's distance up to float rounding. Flagged paths are
        counted in ``timings["paths_flagged"]``.
        """
        q, c, offsets, flags = self._walk(rows, targets, max_steps)
        if q is None:
            return np.zeros((0, 3), np.float32), np.zeros(1, np.int64), np.zeros(0, np.int32)
        T = len(c)
        p = q.points.numpy()[: offsets[-1]]
        # written target->source: reverse each path so it starts at the source
        seg = np.repeat(np.arange(T), c)
        local = np.arange(len(p)) - offsets[seg]
        p = p[offsets[seg] + (c[seg] - 1 - local)]
        flags = flags.numpy()
        self._count_paths(flags)
        p[np.repeat(flags != 0, c)] = np.nan
        return p, offsets, flags

    def trace_resampled(self, rows: np.ndarray, targets: np.ndarray, m: int, max_steps: int | None = None):
        """The paths of ``trace``, resampled to ``m`` points each on the device (only those come back).

        Returns
        -------
        paths : (T, m, 3) float32, normalized frame, from the source, equally spaced by arc length
            (``geodesics.resample_polylines`` of ``trace``'s polylines, bit for bit); a flagged or unreachable
            path is a NaN row
        flags : (T,) int32, as ``trace``'s
        """
        m = points_per_path(m)
        q, c, offsets, flags = self._walk(rows, targets, max_steps)
        if q is None:
            return np.zeros((0, m, 3), np.float32), np.zeros(0, np.int32)
        T = len(c)
        out = wp.empty((T, m), dtype=wp.vec3, device=self.device)
        wp.launch(_kernels().paths.resample_walks, dim=T, inputs=[q, flags], outputs=[out], device=self.device)
        flags = flags.numpy()
        self._count_paths(flags)
        return out.numpy().reshape(T, m, 3), flags

    def _walk(self, rows, targets, max_steps):
        """Walk the paths on the device: (PathQuery with the written points, (T,) int64 point counts, (T + 1,)
        int64 offsets, (T,) device flags as ``trace``'s), or Nones for no paths."""
        kg = _kernels()
        rows = np.asarray(rows, dtype=np.int32).reshape(-1)
        targets = self._solver_id[np.asarray(targets, dtype=np.int64).reshape(-1)].astype(np.int32)
        T = len(targets)
        if T == 0:
            return None, None, None, None
        if max_steps is None:
            max_steps = 4 * (max(self.timings["iterations"][-1], 1) + 16) * (self.graph.kmax + 1)
            max_steps = max(max_steps, int(64 * np.sqrt(len(self.topo.faces))) + 1024)
        d = self.device
        q = kg.paths.PathQuery()
        q.rows = wp.array(rows, dtype=int, device=d)
        q.targets = wp.array(targets, dtype=int, device=d)
        q.counts = wp.zeros(T, dtype=int, device=d)
        q.stale = wp.zeros(T, dtype=int, device=d)
        q.offsets = wp.zeros(T, dtype=int, device=d)
        q.points = wp.zeros(1, dtype=wp.vec3, device=d)
        q.max_steps = int(max_steps)
        q.write = 0
        inputs = [self.graph, self.state.rec, self.state.dist, q]
        wp.launch(kg.paths.walk_paths, dim=T, inputs=inputs, device=d)
        c = q.counts.numpy().astype(np.int64)
        offsets = np.zeros(T + 1, dtype=np.int64)
        np.cumsum(c, out=offsets[1:])
        if offsets[-1] >= 2**31:
            raise MemoryError("too many path points in one trace call; trace fewer targets at a time")
        q.offsets.assign(offsets[:-1].astype(np.int32))
        q.points = wp.zeros(max(int(offsets[-1]), 1), dtype=wp.vec3, device=d)
        q.write = 1
        wp.launch(kg.paths.walk_paths, dim=T, inputs=inputs, device=d)
        # a truncated walk, or a path longer than its distance by more than PATH_TOLERANCE (a ray walk that
        # failed and bent at its parent, or went through the wrong faces)
        flags = wp.empty(T, dtype=int, device=d)
        wp.launch(kg.paths.check_walks, dim=T, inputs=[q, self.state.dist, wp.float64(PATH_TOLERANCE),
                                                       wp.float64(PATH_ABS_TOLERANCE)], outputs=[flags], device=d)
        return q, c, offsets, flags

    def _count_paths(self, flags: np.ndarray) -> None:
        self.timings["paths_traced"] = self.timings.get("paths_traced", 0) + len(flags)
        self.timings["paths_flagged"] = self.timings.get("paths_flagged", 0) + int(np.sum(flags != 0))
