"""Warp inference of the generalizable network: encoder (conditioning) and query network (pairs).

:class:`WarpGenNet` holds the folded weights on one device in one arithmetic mode; :meth:`WarpGenNet.encode`
turns a point cloud (unit-sphere frame) into a :class:`Encoded` state (per-point features F, the precomputed
``G = W_F F + b`` of ``fuse``, a hash grid for the nearest-point lookup) and :meth:`WarpGenNet.ratio` evaluates
pairs against it. Everything stays on the device; nothing synchronizes with the host except the hash-grid build.

On CUDA, ``encode`` of a new state with the fast kernels replays a CUDA graph of the whole encoder (captured on
the first cloud of each point count, kept by the :class:`WarpGenNet`) and copies its outputs into arrays of the
returned state's own; ``NGF_NO_GRAPH=1`` in the environment (or ``WarpGenNet.use_graph = False``) launches the
kernels from Python instead (same numbers).
"""
from __future__ import annotations

import math
import os
import warnings
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from neurogf_warp.common.warp_setup import init_warp
from neurogf_warp.generalizable.network import GenNeuroGF, folded_layers
from neurogf_warp.kernels.generalizable import kernels

init_warp()  # quietly: library calls print nothing unless asked (NEUROGF_WARP_VERBOSE=1)

GRAPHS_KEPT = 4  # point counts whose captured encoder a WarpGenNet keeps (the least recently used one is dropped)


def graph_default() -> bool:
    """Whether a new :class:`WarpGenNet` replays its encoder as a CUDA graph: yes unless ``NGF_NO_GRAPH`` is set to
    something other than "", "0", "false" or "no"."""
    return os.environ.get("NGF_NO_GRAPH", "").strip().lower() in ("", "0", "false", "no")


def default_mode(device) -> str:
    """float64 on the CPU (exact parity, cheap there), float32 on CUDA (speed; 1e-5-level agreement)."""
    return "fp64" if wp.get_device(device).is_cpu else "fp32"


@dataclass
class Encoded:
    """A conditioned point cloud on the device (unit-sphere frame)."""

    cloud: wp.array  # (N, 3) storage dtype
    feats: wp.array  # (N, 128) per-point features F
    fused: wp.array  # (N, 128) G = W_F F + b_fuse (fuse before the coordinate term and ReLU)
    grid: wp.HashGrid | None
    radius: float  # hash-grid query radius (unit frame); the lookup is exact regardless (brute-force fallback)
    neighbours: list  # the three (N, k) kNN index arrays (for tests)
    points32: wp.array | None = None  # (N,) vec3 float32 copy of ``cloud`` (the hash grid's points)
    scratch: dict = field(default_factory=dict)  # every device array of the encoder, reused by encode(into=)
    nn_grid: object = None  # the candidate grid of WarpGenNet(nearest="grid"), built on the first query
    nn_grid_built: bool = False  # False after encode(into=) until the next query rebuilds it
    grid_pending: bool = False  # True: ``grid`` is built on the first query that needs it (the graph path)


@dataclass
class _EncodeGraph:
    """The captured encoder of one point count: the inputs it reads, the state it writes, the graph.

    ``cloud`` and ``frame`` are views into one device block (``inputs``) that one copy fills from a host block of
    the same layout (``host``: pinned on CUDA, so the copy is a plain DMA; on the CPU the device block itself);
    ``host_cloud`` / ``host_frame`` are numpy views of the host block. ``staged``: an event recorded after the
    last copy out of the pinned block (CUDA), waited for before the block is written again."""

    cloud: wp.array  # (N, 3) float32: each call copies its cloud here
    frame: wp.array  # (4,) float64: center x, y, z and scale, copied here by each call
    inputs: wp.array  # (words,) float64: the device block holding cloud and frame
    host: wp.array  # the host block (the device block itself on the CPU)
    host_cloud: np.ndarray  # (N, 3) float32 numpy view of the host block
    host_frame: np.ndarray  # (4,) float64 numpy view of the host block
    frame_word: int  # the frame's offset in the blocks, in float64 words
    staged: object = None  # wp.Event (CUDA) recorded after the last copy from the pinned block
    state: Encoded | None = None  # the arrays the graph writes; never handed out (copied into each result)
    graph: object = None


_ALIGN = 256  # byte alignment of the arrays carved out of one allocation (cudaMalloc's own)


def _packed(device, specs, pinned: bool = False) -> list:
    """Arrays of the given (dtype, shape) as views into one new allocation on ``device`` (each at a 256-byte
    aligned offset): one allocation (and one free) instead of one per array. Each view keeps the block alive."""
    offsets, total = [], 0
    for dtype, shape in specs:
        offsets.append(total)
        nbytes = wp.types.type_size_in_bytes(dtype) * math.prod(shape)
        total += -(-nbytes // _ALIGN) * _ALIGN
    block = wp.empty(max(total, 1), dtype=wp.uint8, device=device, pinned=pinned)
    out = []
    for (dtype, shape), off in zip(specs, offsets):
        a = wp.array(ptr=block.ptr + off, dtype=dtype, shape=shape, device=block.device)
        a._ref = block  # Warp's own link from a view to its owner
        out.append(a)
    return out


class WarpGenNet:
    """The released (or a trained) :class:`GenNeuroGF` as Warp arrays on ``device``.

    mode: ``"fp64"``, ``"fp32"`` or ``"mixed"`` (see ``kernels/generalizable``); default: :func:`default_mode`.
    knn_chunks: candidate chunks per point of the neighbour search (parallelism on a GPU, default 16; 1 on the
    CPU); sweep it with the benchmark's --knn-chunks.
    nearest: the nearest-cloud-point lookup of the queries: ``"hash"`` (Warp's hash grid, built at conditioning;
    the default on the CPU, where building the grid costs ~130 ms) or ``"grid"`` (the default on CUDA: a dense
    grid of candidate lists, ``kernels/generalizable/nearest_grid.py``, 4x faster on an H100, built
    on the first query of a conditioned cloud); both return the brute-force scan's index (ties -> smaller index).
    graph: replay the fast encoder as a CUDA graph in :meth:`encode` (default: :func:`graph_default`, i.e. yes
    unless ``NGF_NO_GRAPH=1``); the attribute ``use_graph`` switches it later. Only CUDA devices capture; where a
    capture fails the encoder launches from Python (one warning, remembered per device).
    """

    def __init__(self, net: GenNeuroGF, device=None, mode: str | None = None, knn_chunks: int | None = None,
                 use_grid: bool = True, fast: bool | None = None, nearest: str | None = None,
                 graph: bool | None = None):
        if nearest not in (None, "hash", "grid"):
            raise ValueError(f"nearest must be 'hash' or 'grid', got {nearest!r}")
        self.device = wp.get_device(device)
        self.nearest_lookup = nearest or ("grid" if self.device.is_cuda else "hash")
        self.mode = mode or default_mode(self.device)
        self.k = kernels(self.mode)
        self.np_dtype = np.float64 if self.mode == "fp64" else np.float32
        self.knn_chunks = knn_chunks or (1 if self.device.is_cpu else 16)
        self.use_grid = use_grid
        self.use_graph = graph_default() if graph is None else bool(graph)
        # per point count, the captured encoder (warp/fem style: the owner of the device state caches it)
        self._graphs: OrderedDict[int, _EncodeGraph] = OrderedDict()
        self._graph_off: str | None = None  # why capture is off on this device for good (a capture failed)
        self._graph_warned: set = set()
        self._graph_cpu = False  # tests only: Warp's CPU graphs stand in for CUDA's (off: the CPU launches eagerly)
        self.kk = net.backbone.econv_1.k
        L = folded_layers(net)
        a = self._arr
        w = {}
        for name, split in (("e1a", 3), ("e2a", 64), ("e3", 64)):  # edge layers on [f_i, f_j - f_i]
            W, b = L[name]
            Wa, Wb = W[:, :split], W[:, split:]
            w[name + "P"] = (a(Wa - Wb), a(b))
            w[name + "Q"] = (a(Wb), a(np.zeros(W.shape[0])))
        for name in ("e1b", "e2b", "pw", "mlp1", "head0", "head1"):
            W, b = L[name]
            w[name] = (a(W), a(b))
        W, b = L["mlp0"]
        w["mlp0cw"] = (a(W[:, :320]), a(b))
        w["mlp0f"] = a(W[:, 320:])
        W, b = L["fuse"]
        w["fuseF"] = (a(W[:, :128]), a(b))
        w["fuseX"] = a(W[:, 128:])
        w["head2"] = a(L["head2"][0])
        self.w = w
        # the tensor-core head (precision="fp16", kernels/generalizable/tensorcore.py): float64 weights kept here,
        # packed on first use; tc_tiles: (m-tiles per warp, layer-0 n-tiles per chunk, warps per multiprocessor)
        # of its kernel (None: the kernel file's defaults; the benchmark's --tc-tiles sweeps them)
        self._head64 = (L["fuse"][0][:, 128:], *L["head0"], *L["head1"], L["head2"][0])
        self._tc = None
        self.tc_tiles = None
        # the fast float32 kernels (kernels/generalizable/fast.py): fp32 mode only (their arithmetic is float32)
        self.fast = (self.mode == "fp32") if fast is None else bool(fast and self.mode == "fp32")
        self.fk = None
        if self.fast:
            from neurogf_warp.kernels.generalizable.fast import kernels as fast_kernels

            self.fk = fast_kernels()
            for name, split in (("e1a", 3), ("e2a", 64), ("e3", 64)):
                # P and Q of an edge layer as one (128, C) map: one GEMM launch gives both
                W, b = L[name]
                Wa, Wb = W[:, :split], W[:, split:]
                w[name + "PQ"] = (a(np.vstack([Wa - Wb, Wb])), a(np.concatenate([b, np.zeros(W.shape[0])])))

    def _arr(self, x):
        x = np.ascontiguousarray(np.asarray(x, dtype=np.float64).astype(self.np_dtype))
        return wp.array(x, dtype=self.k.dtype, device=self.device)

    # ---- encoder -------------------------------------------------------------------------------------------
    def _buf(self, scratch: dict, name: str, shape, dtype):
        """A device array from ``scratch`` (reused when its shape and dtype fit), else a new one stored there:
        re-encoding into an earlier state allocates nothing (and can be captured in a CUDA graph)."""
        a = scratch.get(name)
        if a is None or a.shape != tuple(shape) or a.dtype != dtype:
            a = scratch[name] = wp.empty(shape, dtype=dtype, device=self.device)
        return a

    def knn(self, f: wp.array, c_off: int = 0, nc: int | None = None, kk: int | None = None,
            scratch: dict | None = None, tag: str = "") -> wp.array:
        """Exact kk nearest neighbours of each row of f[:, c_off:c_off + nc] among the rows, closest first, self
        included, ties -> smaller index. Returns (N, kk) int32."""
        kk = kk or self.kk
        nc = f.shape[1] - c_off if nc is None else nc
        scratch = {} if scratch is None else scratch
        n = f.shape[0]
        g = max(1, min(self.knn_chunks, n // kk))
        n_per = (n + g - 1) // g
        pd = self._buf(scratch, "knn_d", (n, g, kk), self.k.acc)
        pi = self._buf(scratch, "knn_i", (n, g, kk), wp.int32)
        nbr = self._buf(scratch, "nbr" + tag, (n, kk), wp.int32)
        if self.device.is_cpu:  # N^2 work: in chunks of rows, so that Ctrl-C stops a large cloud within a second
            self._rows(n, lambda lo, hi: wp.launch(
                self.k.knn_rows, (hi - lo, g), inputs=[f, lo, c_off, nc, n_per, kk, pd[lo:hi], pi[lo:hi]],
                device=self.device), first=max(16, (1 << 24) // max(n * nc, 1)))
        else:
            wp.launch(self.k.knn_partial, (n, g), inputs=[f, c_off, nc, n_per, kk, pd, pi], device=self.device)
        wp.launch(self.k.knn_merge, (n, g, kk), inputs=[pd, pi, nbr], device=self.device)
        return nbr

    def _rows(self, n: int, run, first: int = 1024):
        """``run(lo, hi)`` over the rows [0, n): one call on a GPU, chunks of about half a second on the CPU
        (``common.chunks.in_chunks``; every kernel chunked so computes each row from its own inputs)."""
        from neurogf_warp.common.chunks import in_chunks

        in_chunks(self.device, n, run, first=first, align=1)

    def _linear(self, x, x_off, wb, relu, y, y_off=0):
        W, b = wb
        self._rows(x.shape[0], lambda lo, hi: wp.launch(
            self.k.linear, (hi - lo, W.shape[0]), inputs=[x[lo:hi], x_off, W, b, int(relu), y[lo:hi], y_off],
            device=self.device))

    def _edge(self, kernel, P, Q, nbr, extra, y, y_off):
        """An edge layer over row chunks (``_rows``): rows of P, nbr and y, every row of Q (the neighbours)."""
        self._rows(P.shape[0], lambda lo, hi: wp.launch(
            kernel, (hi - lo, 64), inputs=[P[lo:hi], Q, nbr[lo:hi], *extra, y[lo:hi], y_off], device=self.device),
            first=256)

    def encode(self, cloud, center=(0.0, 0.0, 0.0), scale: float = 1.0, into: Encoded | None = None) -> Encoded:
        """Condition the network on a point cloud.

        cloud: (N, 3), N >= k = 40: numpy (any float dtype) or a wp.array2d of the storage dtype on this device
        (then nothing is copied from the host). ``(cloud - center) * scale`` must be the cloud in the network's
        unit-sphere frame (defaults: the cloud is in that frame already). ``into``: an earlier result whose
        arrays (and hash grid) are overwritten and returned (no allocation when N is unchanged; that earlier
        state is then gone). Returns :class:`Encoded`.

        Without ``into``, on CUDA with the fast kernels (and ``use_graph``), the encoder runs as a CUDA graph
        replay (captured on the first cloud of this N) and the result holds copies of the graph's outputs: every
        result is its own, whatever later calls replay; its hash grid is built on the first query that uses it.
        """
        dev, T = self.device, self.k.dtype
        host = None
        if not (isinstance(cloud, wp.array) and cloud.dtype == T and cloud.ndim == 2 and cloud.device == dev):
            host = np.asarray(cloud.numpy() if isinstance(cloud, wp.array) else cloud)
            if host.dtype != np.float64 and host.dtype != np.float32:
                host = host.astype(np.float64)  # as _arr: through float64 (float32 -> float64 -> float32 is exact)
        shape = (host if host is not None else cloud).shape
        n = shape[0]
        if n < self.kk:
            raise ValueError(f"the point cloud has {n} points; the encoder needs at least k={self.kk}")
        if into is None and shape == (n, 3) and self._graph_usable(n):
            enc = self._encode_graph(cloud if host is None else host, center, scale)
            if enc is not None:
                return enc
        if host is not None:
            cloud = wp.array(np.ascontiguousarray(host.astype(self.np_dtype, copy=False)), dtype=T, device=dev)
        if self._fast_encoder_fits(n):
            return self._encode_fast(cloud, center, scale, into)
        sc = into.scratch if into is not None else {}
        buf = lambda name, c: self._buf(sc, name, (n, c), T)
        X = buf("X", 3)
        V = self._buf(sc, "V", (n,), wp.vec3)
        wp.launch(self.k.to_unit, n, inputs=[cloud, *(float(c) for c in center), float(scale), X, V], device=dev)
        cat = buf("cat", 192)  # [f1, f2, f3]
        P, Q = buf("P", 64), buf("Q", 64)
        w = self.w
        # block 1: neighbours in xyz space
        n1 = self.knn(X, scratch=sc, tag="1")
        self._linear(X, 0, w["e1aP"], False, P)
        self._linear(X, 0, w["e1aQ"], False, Q)
        self._edge(self.k.edge_two_layers, P, Q, n1, w["e1b"], cat, 0)
        # block 2: neighbours in f1 space
        n2 = self.knn(cat, 0, 64, scratch=sc, tag="2")
        self._linear(cat, 0, w["e2aP"], False, P)
        self._linear(cat, 0, w["e2aQ"], False, Q)
        self._edge(self.k.edge_two_layers, P, Q, n2, w["e2b"], cat, 64)
        # block 3: neighbours in f2 space, one layer: no per-edge matrix (see the kernels' docstring)
        n3 = self.knn(cat, 64, 64, scratch=sc, tag="3")
        self._linear(cat, 64, w["e3P"], False, P)
        self._linear(cat, 64, w["e3Q"], False, Q)
        self._edge(self.k.edge_one_layer, P, Q, n3, (), cat, 128)
        return self._heads(self._linear, T, sc, buf, n, cat, X, V, [n1, n2, n3], into)

    def _heads(self, lin, T, sc, buf, n, cat, X, V, nbrs, into, build_grid=True):
        """After the edge blocks (both encoders): the codeword (max over points of the point-wise embedding of
        [f1, f2, f3]), the per-point features F and their fused part G, the query grid (not with ``build_grid``
        False: the captured encoder); ``lin`` is the linear layer of the encoder in use."""
        dev, w = self.device, self.w
        E = buf("E", 320)
        lin(cat, 0, w["pw"], True, E)
        cw = self._buf(sc, "cw", (1, 320), T)
        chunks = max(1, min(32, n // 64)) if not dev.is_cpu else 1
        per = (n + chunks - 1) // chunks
        chunks = (n + per - 1) // per  # every chunk non-empty
        part = self._buf(sc, "cw_part", (chunks, 320), T)
        wp.launch(self.k.column_max, (chunks, 320), inputs=[E, per, part], device=dev)
        wp.launch(self.k.column_max, (1, 320), inputs=[part, chunks, cw], device=dev)
        # mlp.0 on [codeword, f]: the codeword part is the same for every point -> a per-cloud bias
        bias = self._buf(sc, "bias", (1, 128), T)
        lin(cw, 0, w["mlp0cw"], False, bias)
        H = buf("H", 128)
        lin(cat, 0, (w["mlp0f"], bias.reshape((128,))), True, H)
        F = buf("F", 128)
        lin(H, 0, w["mlp1"], True, F)
        G = buf("G", 128)
        lin(F, 0, w["fuseF"], False, G)
        grid, radius = None, 0.0
        if self.use_grid and build_grid:
            grid, radius = self._grid(V, into.grid if into is not None else None)
        if into is not None:
            into.cloud, into.feats, into.fused, into.grid, into.radius = X, F, G, grid, radius
            into.neighbours, into.points32 = nbrs, V
            into.nn_grid_built = False  # the candidate lists are the old cloud's
            into.grid_pending = False
            return into
        return Encoded(X, F, G, grid, radius, nbrs, V, sc)

    def _fast_encoder_fits(self, n: int) -> bool:
        from neurogf_warp.kernels.generalizable.fast import EDGE_K_MAX, KNN_MAX_POINTS

        return self.fast and n <= KNN_MAX_POINTS and self.kk <= EDGE_K_MAX

    def _lin(self, x, x_off, wb, relu, y, y_off=0):
        """y[:, y_off:] = act(x[:, x_off:] W^T + b) with the fast tiled kernel (32 rows x 64 outputs a block)."""
        from neurogf_warp.kernels.generalizable.fast import LIN_OUTS, LIN_ROWS

        W, b = wb
        nob = (W.shape[0] + LIN_OUTS - 1) // LIN_OUTS
        nblk = (x.shape[0] + LIN_ROWS - 1) // LIN_ROWS * nob
        bd = 1 if self.device.is_cpu else 256
        wp.launch(self.fk.linear, (nblk, bd), inputs=[x, x_off, W, b, int(relu), y, y_off, nob],
                  block_dim=bd, device=self.device)

    def _knn_fast(self, ft, c_off, nc, scratch, tag):
        """kk nearest neighbours in rows [c_off, c_off + nc) of the channel-major ft (C, N) -> (N, kk) int32."""
        n = ft.shape[1]
        nbr = self._buf(scratch, "nbr" + tag, (n, self.kk), wp.int32)
        if self.device.is_cpu:
            wp.launch(self.fk.knn, (n, 1), inputs=[ft, c_off, nc, self.kk, nbr], block_dim=1, device=self.device)
        else:
            wp.launch(self.fk.knn, ((n + 3) // 4, 128), inputs=[ft, c_off, nc, self.kk, nbr], block_dim=128,
                      device=self.device)
        return nbr

    def _encode_fast(self, cloud, center, scale, into, frame=None, build_grid=True):
        """encode() with the fast float32 kernels: 16 launches, no host synchronisation (except the hash-grid
        build), every buffer reused through ``into`` (so the whole encoder can be captured in a CUDA graph).
        frame: a (4,) float64 device array (center, scale) read by the first kernel instead of ``center`` and
        ``scale`` (the captured encoder: nothing of a particular cloud is kept in the graph)."""
        dev, fk, w = self.device, self.fk, self.w
        n = cloud.shape[0]
        f32 = wp.float32
        sc = into.scratch if into is not None else {}
        buf = lambda name, c: self._buf(sc, name, (n, c), f32)
        X = buf("X", 3)
        XT = self._buf(sc, "XT", (3, n), f32)
        V = self._buf(sc, "V", (n,), wp.vec3)
        if frame is None:
            wp.launch(fk.to_unit, n, inputs=[cloud, *(float(c) for c in center), float(scale), X, XT, V],
                      device=dev)
        else:
            wp.launch(fk.to_unit_frame, n, inputs=[cloud, frame, X, XT, V], device=dev)
        cat = buf("cat", 192)  # [f1, f2, f3]
        catT = self._buf(sc, "catT", (128, n), f32)  # f1, f2 channel-major (the kNN's coalesced reads)
        PQ = buf("PQ", 128)
        eb = 1 if dev.is_cpu else 64
        n1 = self._knn_fast(XT, 0, 3, sc, "1")
        self._lin(X, 0, w["e1aPQ"], False, PQ)
        wp.launch(fk.edge2, (n, eb), inputs=[PQ, n1, *w["e1b"], cat, catT, 0], block_dim=eb, device=dev)
        n2 = self._knn_fast(catT, 0, 64, sc, "2")
        self._lin(cat, 0, w["e2aPQ"], False, PQ)
        wp.launch(fk.edge2, (n, eb), inputs=[PQ, n2, *w["e2b"], cat, catT, 64], block_dim=eb, device=dev)
        n3 = self._knn_fast(catT, 64, 64, sc, "3")
        self._lin(cat, 64, w["e3PQ"], False, PQ)
        wp.launch(fk.edge1, (n, 64), inputs=[PQ, n3, cat, 128], device=dev)
        return self._heads(self._lin, f32, sc, buf, n, cat, X, V, [n1, n2, n3], into, build_grid)

    # ---- the encoder as a CUDA graph --------------------------------------------------------------------------
    def _graph_usable(self, n: int) -> bool:
        """Whether encode() of n points replays the captured encoder now (else: launches from Python)."""
        if not (self.use_graph and self._fast_encoder_fits(n)):
            return False
        dev = self.device
        if dev.is_capturing:
            return False  # inside the caller's own capture: the launches are recorded there
        if dev.is_cpu:
            return self._graph_cpu  # the CPU launches eagerly (tests may stand Warp's CPU graphs in)
        reason = self._graph_off
        if reason is None and not getattr(dev, "is_capturable", True):
            reason = f"{dev} cannot capture CUDA graphs"
        elif reason is None and not dev.is_mempool_enabled:
            reason = f"the CUDA memory pool is off on {dev} (wp.set_mempool_enabled)"
        elif reason is None and wp.config.verify_cuda:
            reason = "wp.config.verify_cuda is on (no capture with CUDA error checks)"
        if reason is not None:
            self._warn_graph(reason)
            return False
        return True

    def _warn_graph(self, reason: str):
        if reason not in self._graph_warned:
            self._graph_warned.add(reason)
            warnings.warn(f"the generalizable encoder runs without a CUDA graph on {self.device}: {reason}; its "
                          "kernels launch from Python (same results, slower)", RuntimeWarning, stacklevel=4)

    def _graph_inputs(self, n: int) -> _EncodeGraph:
        """The fixed inputs of the captured encoder of n points: cloud (float32) and frame (float64) in one device
        block, filled by one copy from a host block of the same layout (pinned on CUDA)."""
        dev = self.device
        fw = -(-n * 3 // 2)  # float32 cloud, then the frame at the next float64 word
        words = fw + 4
        inputs = wp.empty(words, dtype=wp.float64, device=dev)
        host = inputs if dev.is_cpu else wp.empty(words, dtype=wp.float64, device="cpu", pinned=True)
        view = lambda dtype, shape, word: _view(inputs, dtype, shape, word)
        hb = host.numpy()
        return _EncodeGraph(view(wp.float32, (n, 3), 0), view(wp.float64, (4,), fw), inputs, host,
                            hb.view(np.float32)[:n * 3].reshape(n, 3), hb[fw:fw + 4], fw)

    def _encode_graph(self, cloud, center, scale) -> Encoded | None:
        """encode() by replaying the captured encoder of this point count (captured here on its first cloud, after
        one eager run that loads the modules and allocates its arrays); the result holds copies of the graph's
        outputs. cloud: numpy (N, 3) (float32, or float64: rounded to float32 here) or a device array. None where
        the capture failed (then remembered: this device launches eagerly from now on)."""
        dev, n = self.device, cloud.shape[0]
        g = self._graphs.get(n)
        fresh = g is None
        if fresh:
            g = self._graph_inputs(n)
        if g.staged is not None:
            wp.synchronize_event(g.staged)  # the last copy out of the pinned block is done (it is rewritten here)
        hf = g.host_frame
        hf[0], hf[1], hf[2] = center
        hf[3] = scale
        if isinstance(cloud, wp.array):
            wp.copy(g.cloud, cloud)  # on the device's stream: after every earlier replay's reads
            if g.host is not g.inputs:
                wp.copy(g.inputs, g.host, dest_offset=g.frame_word, src_offset=g.frame_word, count=4)
        else:
            np.copyto(g.host_cloud, cloud)  # float64 -> float32 rounds as astype does
            if g.host is not g.inputs:
                wp.copy(g.inputs, g.host)  # one DMA for cloud and frame, after every earlier replay's reads
        if g.host is not g.inputs:
            if g.staged is None:
                g.staged = wp.Event(dev)
            dev.stream.record_event(g.staged)
        if fresh:
            g.state = self._encode_fast(g.cloud, None, None, None, frame=g.frame, build_grid=False)
            try:
                with wp.ScopedCapture(device=dev, force_module_load=False) as cap:
                    self._encode_fast(g.cloud, None, None, g.state, frame=g.frame, build_grid=False)
                g.graph = cap.graph
            except Exception as e:  # noqa: BLE001 - any capture failure: eager launches from now on
                self._graph_off = f"the capture failed ({type(e).__name__}: {str(e)[:200]})"
                self._warn_graph(self._graph_off)
                return None
            self._graphs[n] = g
            while len(self._graphs) > GRAPHS_KEPT:
                wp.synchronize_device(dev)  # nothing in flight still reads the arrays of the one dropped
                self._graphs.popitem(last=False)
        else:
            self._graphs.move_to_end(n)
        wp.capture_launch(g.graph)
        return self._copy_encoded(g.state)

    def _copy_encoded(self, st: Encoded) -> Encoded:
        """A new Encoded holding device copies of st's cloud, features and neighbour lists (one launch, into views
        of one allocation); its hash grid is built on first use (:meth:`_hash`), its nearest grid on the first
        query, over its own points."""
        dev, n, f32 = self.device, st.cloud.shape[0], wp.float32
        specs = [(f32, (n, 3)), (wp.vec3, (n,)), (f32, st.feats.shape), (f32, st.fused.shape),
                 *((wp.int32, a.shape) for a in st.neighbours)]
        X, V, F, G, *nbrs = _packed(dev, specs)
        wp.launch(self.fk.copy_encoded, (n, F.shape[1]), inputs=[st.cloud, st.points32, st.feats, st.fused,
                                                                  *st.neighbours, X, V, F, G, *nbrs], device=dev)
        sc = {"X": X, "V": V, "F": F, "G": G, "nbr1": nbrs[0], "nbr2": nbrs[1], "nbr3": nbrs[2]}
        return Encoded(X, F, G, None, _grid_radius(n) if self.use_grid else 0.0, nbrs, V, sc,
                       grid_pending=self.use_grid)

    def _hash(self, enc: Encoded):
        """(grid id, radius, has grid) of enc's hash grid for the kernels; built here if encode left it for later."""
        if enc.grid is None and enc.grid_pending:
            enc.grid, enc.radius = self._grid(enc.points32)
            enc.grid_pending = False
        if enc.grid is None:
            return wp.uint64(0), enc.radius, 0
        return enc.grid.id, enc.radius, 1

    def _grid(self, pts: wp.array, grid: wp.HashGrid | None = None):
        """A hash grid over the cloud for the nearest-point lookup of queries.

        radius: 4 / sqrt(N) in the unit frame (about twice the typical spacing of N points on a surface of area
        ~4 pi r^2 / 2); queries farther than that from every point fall back to a brute-force scan (exact)."""
        n = pts.shape[0]
        radius = _grid_radius(n)
        dim = int(max(8, min(128, np.ceil(2.0 / radius))))
        if grid is None:
            grid = wp.HashGrid(dim, dim, dim, device=self.device)
        grid.build(pts, radius)  # the grid refers to pts: Encoded keeps them alive
        return grid, radius

    # ---- queries -------------------------------------------------------------------------------------------
    def ratio(self, enc: Encoded, s, t, precision: str = "fp32") -> wp.array:
        """The network's raw ratio for pairs s[m], t[m] ((M, 3), unit frame) -> (M,) storage dtype (float32 with
        precision "fp16", see :meth:`distances`)."""
        check_precision(precision)
        S, Tt = self._arr(np.asarray(s)), self._arr(np.asarray(t))
        m = S.shape[0]
        if precision == "fp16":
            out = wp.empty(m, dtype=wp.float32, device=self.device)
            if m:
                self._pair_head_tc(enc, S, Tt, None, None, None, None, (0.0, 0.0, 0.0), 1.0, 0, m, True, out)
            return out
        out = wp.empty(m, dtype=self.k.dtype, device=self.device)
        if self.fast:
            if m:
                self._pair_head(enc, S, Tt, None, None, None, None, (0.0, 0.0, 0.0), 1.0, 0, m, True, out)
            return out
        w = self.w
        grid_id, radius, has = self._hash(enc)
        wp.launch(self.k.pair_ratio, m,
                  inputs=[enc.cloud, grid_id, radius, has, enc.fused, w["fuseX"],
                          *w["head0"], *w["head1"], w["head2"], S, Tt, out], device=self.device)
        return out

    def _nn_grid(self, enc: Encoded):
        """The candidate grid of enc (nearest="grid"), built here on first use after encode."""
        from neurogf_warp.kernels.generalizable.nearest_grid import NearestGrid

        if enc.nn_grid is None or enc.nn_grid.n_points != enc.cloud.shape[0]:
            enc.nn_grid = NearestGrid(self.mode, enc.cloud.shape[0], self.device)
            enc.nn_grid_built = False
        if not enc.nn_grid_built:
            enc.nn_grid.build(enc.cloud)
            enc.nn_grid_built = True
        return enc.nn_grid

    def nearest(self, enc: Encoded, pts: wp.array) -> wp.array:
        """Nearest cloud point of each row of pts (M, 3) (storage dtype, unit frame) -> (M,) int32."""
        out = wp.empty(pts.shape[0], dtype=wp.int32, device=self.device)
        if self.nearest_lookup == "grid":
            if pts.shape[0]:
                g = self._nn_grid(enc)
                wp.launch(g.k.nearest, pts.shape[0], inputs=[enc.cloud, *g.args(), pts, out], device=self.device)
            return out
        grid_id, radius, has = self._hash(enc)
        wp.launch(self.k.nearest, pts.shape[0], inputs=[enc.cloud, grid_id, radius, has, pts, out],
                  device=self.device)
        return out

    def distances(self, enc: Encoded, S: wp.array, T: wp.array, center, scale: float, matrix: bool,
                  s_nn=None, t_nn=None, s_comp=None, t_comp=None, out=None, precision: str = "fp32",
                  whole: bool = False) -> wp.array:
        """Distances in user units (float32): pairs (S[m], T[m]) or, with ``matrix``, all S x T (row-major).

        S, T: (., 3) storage dtype, user units, ``(x - center) * scale`` = unit frame; s_nn/t_nn: optional
        precomputed nearest cloud points (int32); s_comp/t_comp: optional component labels (int32), +inf across.
        precision: ``"fp32"`` (default): the kernels of the network's mode (fast float32 on CUDA, float64 on the
        CPU by default), unchanged; ``"fp16"``: the pair head on tensor cores (fp16 operands, fp32 sums;
        ``kernels/generalizable/tensorcore.py``; on the CPU a slow emulation of the same code). Its error against
        float64, measured: relative error of the distance, released network, 2,048-point clouds and 4,096 pairs near
        the surface (CPU emulation of the kernel): mean 3.7e-5, max 2.7e-4; 256-point clouds: mean 1.2-1.4e-4, max
        1.4e-3. whole: one launch also on the CPU (else more than ``PAIR_CHUNK`` pairs run in chunks of S rows).
        """
        check_precision(precision)
        n_t = T.shape[0] if matrix else 0
        m = S.shape[0] * T.shape[0] if matrix else S.shape[0]
        if out is None:
            out = wp.empty(m, dtype=wp.float32, device=self.device)
        if m == 0:
            return out
        if self.device.is_cpu and m > PAIR_CHUNK and not whole:
            # one CPU launch runs to its end before Ctrl-C is seen: rows of S in chunks (every pair's distance
            # depends on its own two points only, so the result is the same bits as one launch)
            from neurogf_warp.common.chunks import in_chunks

            per = max(n_t, 1)
            cut = lambda a, lo, hi: None if a is None else a[lo:hi]  # noqa: E731

            def run(lo, hi):
                self.distances(enc, S[lo:hi], T if matrix else T[lo:hi], center, scale, matrix, cut(s_nn, lo, hi),
                               t_nn if matrix else cut(t_nn, lo, hi), cut(s_comp, lo, hi),
                               t_comp if matrix else cut(t_comp, lo, hi), out[lo * per: hi * per] if matrix
                               else out[lo:hi], precision, whole=True)

            in_chunks(self.device, S.shape[0], run, first=max(1, PAIR_CHUNK // per), align=1)
            return out
        if precision == "fp16":
            return self._pair_head_tc(enc, S, T, s_nn, t_nn, s_comp, t_comp, center, scale, n_t, m, False, out)
        if self.fast:
            return self._pair_head(enc, S, T, s_nn, t_nn, s_comp, t_comp, center, scale, n_t, m, False, out)
        if self.nearest_lookup == "grid":  # else the kernel looks them up in the hash grid
            s_nn = self._nearest_user(enc, S, center, scale) if s_nn is None else s_nn
            t_nn = self._nearest_user(enc, T, center, scale) if t_nn is None else t_nn
        e = wp.empty(0, dtype=wp.int32, device=self.device)
        w = self.w
        grid_id, radius, has = self._hash(enc)
        wp.launch(self.k.pair_distance, m,
                  inputs=[enc.cloud, grid_id, radius, has, enc.fused, w["fuseX"],
                          *w["head0"], *w["head1"], w["head2"],
                          S, s_nn if s_nn is not None else e, s_comp if s_comp is not None else e,
                          T, t_nn if t_nn is not None else e, t_comp if t_comp is not None else e,
                          *(float(c) for c in center), float(scale), n_t, out], device=self.device)
        return out

    def _nearest_user(self, enc: Encoded, pts: wp.array, center, scale) -> wp.array:
        """Nearest cloud point of each row of pts (user units, rounded to the unit frame as the pair kernels do)."""
        out = wp.empty(pts.shape[0], dtype=wp.int32, device=self.device)
        if pts.shape[0] and self.nearest_lookup == "grid":
            g = self._nn_grid(enc)
            wp.launch(g.k.nearest_user, pts.shape[0], inputs=[enc.cloud, *g.args(), pts, *(float(c) for c in center),
                                                             float(scale), out], device=self.device)
        elif pts.shape[0]:
            grid_id, radius, has = self._hash(enc)
            wp.launch(self.k.nearest_user, pts.shape[0],
                      inputs=[enc.cloud, grid_id, radius, has, pts,
                              *(float(c) for c in center), float(scale), out], device=self.device)
        return out

    def _pair_head(self, enc, S, T, s_nn, t_nn, s_comp, t_comp, center, scale, n_t, m, raw, out):
        """The fast pair kernel: nearest cloud points once per S row and per T row (a separate, fully occupied
        launch: in a matrix a row is shared by many pairs), then persistent blocks over tiles of pairs."""
        from neurogf_warp.kernels.generalizable.fast import PAIRS, PAIR_THREADS

        dev, w = self.device, self.w
        if s_nn is None:
            s_nn = self._nearest_user(enc, S, center, scale)
        if t_nn is None:
            t_nn = self._nearest_user(enc, T, center, scale)
        e = wp.empty(0, dtype=wp.int32, device=dev)
        ntiles = (m + PAIRS - 1) // PAIRS
        if dev.is_cpu:
            nblk, bd = 1, 1
        else:
            nblk, bd = max(1, min(ntiles, dev.sm_count)), PAIR_THREADS  # one 200 KiB block per SM
        wp.launch(self.fk.pair_head, (nblk, bd),
                  inputs=[enc.fused, w["fuseX"], *w["head0"], *w["head1"], w["head2"], S, s_nn,
                          s_comp if s_comp is not None else e, T, t_nn, t_comp if t_comp is not None else e,
                          *(float(c) for c in center), float(scale), int(n_t), int(m), int(raw), nblk, out],
                  block_dim=bd, device=dev)
        return out

    def _pair_head_tc(self, enc, S, T, s_nn, t_nn, s_comp, t_comp, center, scale, n_t, m, raw, out):
        """The tensor-core pair kernel (precision "fp16"): nearest cloud points as for the fast kernel, then
        persistent warps over tiles of 16 pairs."""
        from neurogf_warp.kernels.generalizable import tensorcore as gtc

        dev = self.device
        if self._tc is None:
            self._tc = gtc.pack_head(*self._head64, dev)
        mt, nc, warps = self.tc_tiles or (gtc.MT, gtc.NC, None)
        if s_nn is None:
            s_nn = self._nearest_user(enc, S, center, scale)
        if t_nn is None:
            t_nn = self._nearest_user(enc, T, center, scale)
        e = wp.empty(0, dtype=wp.int32, device=dev)
        warps = warps or gtc.warps_per_sm(mt)
        kernel = gtc.pair_kernel("fp32" if enc.fused.dtype == wp.float32 else "fp64", mt, nc, warps)
        head, wxp = self._tc
        return gtc.launch_pairs(kernel, head, wxp, enc.fused, S, s_nn, s_comp if s_comp is not None else e, T, t_nn,
                                t_comp if t_comp is not None else e, center, scale, n_t, m, raw, out, dev, mt=mt,
                                warps=warps)

    # ---- tiled query (tensor cores on CUDA) ------------------------------------------------------------------
    def tiled_weights(self, operand: str):
        """Transposed head weights for the tiled kernel: (WxT (3,128), W0T, b0 (1,128), W1T, b1 (1,64), w2T)."""
        key = ("tiled", operand)
        if key not in self.w:
            O = wp.float16 if operand == "fp16" else self.k.dtype
            npo = np.float16 if operand == "fp16" else self.np_dtype
            arr = (lambda x, dt, npd: wp.array(np.ascontiguousarray(np.asarray(x, np.float64).astype(npd)),
                                               dtype=dt, device=self.device))
            A, npa = self.k.acc, self.np_dtype
            w = self.w
            self.w[key] = (arr(_T(w["fuseX"]), A, npa), arr(_T(w["head0"][0]), O, npo),
                           arr(w["head0"][1].numpy()[None], A, npa), arr(_T(w["head1"][0]), O, npo),
                           arr(w["head1"][1].numpy()[None], A, npa), arr(_T(w["head2"]), O, npo))
        return self.w[key]

    def distances_tiled(self, enc: Encoded, S: wp.array, T: wp.array, center, scale: float, s_comp=None,
                        t_comp=None, out=None, block_pairs: int = 32, operand: str | None = None,
                        mathdx: bool = True, scratch: dict | None = None) -> wp.array:
        """As :meth:`distances` for pairs (S[m], T[m]), with the head as block-wide tile GEMMs (see
        ``kernels/generalizable/tiled.py``). operand "fp16" uses tensor cores on CUDA (~1e-3 relative error);
        default: the mode's own type. block_pairs B: pairs per block (CPU: B <= 16 keeps the tile arena small).
        """
        from ..kernels.generalizable.tiled import tiled_kernels

        operand = operand or ("fp64" if self.mode == "fp64" else "fp32")
        tk = tiled_kernels(self.mode, block_pairs, operand, mathdx)
        m = S.shape[0]
        dev, A = self.device, tk.acc
        sc = {} if scratch is None else scratch
        su = self._buf(sc, "su", (m, 3), A)
        tu = self._buf(sc, "tu", (m, 3), A)
        si = self._buf(sc, "si", (m,), wp.int32)
        ti = self._buf(sc, "ti", (m,), wp.int32)
        r = self._buf(sc, "r", (m, 1), A)
        if out is None:
            out = wp.empty(m, dtype=wp.float32, device=dev)
        if m == 0:
            return out
        grid_id, radius, has = self._hash(enc)
        fr = [*(float(c) for c in center), float(scale)]
        wp.launch(tk.pair_prep, m, inputs=[enc.cloud, grid_id, radius, has, S, T, *fr, su, tu, si, ti], device=dev)
        nblocks = (m + block_pairs - 1) // block_pairs
        wp.launch_tiled(tk.pair_head, dim=[nblocks], inputs=[enc.fused, si, ti, su, tu, *self.tiled_weights(operand), r],
                        block_dim=64 if dev.is_cuda else 1, device=dev)
        e = wp.empty(0, dtype=wp.int32, device=dev)
        wp.launch(tk.pair_finish, m, inputs=[S, T, r, s_comp if s_comp is not None else e,
                                             t_comp if t_comp is not None else e, out], device=dev)
        return out


PRECISIONS = ("fp32", "fp16")
PAIR_CHUNK = 1 << 14  # CPU queries of more pairs run in chunks (the first about this many pairs; see distances)


def _grid_radius(n: int) -> float:
    """The hash grid's query radius for n points (unit frame), see WarpGenNet._grid."""
    return float(4.0 / np.sqrt(n))


def _view(block: wp.array, dtype, shape, word: int) -> wp.array:
    """A view of ``dtype`` and ``shape`` into the float64 block from its word ``word`` on (keeps the block alive)."""
    a = wp.array(ptr=block.ptr + 8 * word, dtype=dtype, shape=shape, device=block.device)
    a._ref = block
    return a


def check_precision(precision) -> None:
    """Refuse a precision other than "fp32" / "fp16" with a clear error."""
    if precision not in PRECISIONS:
        raise ValueError(f"unknown precision {precision!r}; use 'fp32' (default: the network's float32/float64 "
                         f"kernels) or 'fp16' (tensor cores)")


def _T(a: wp.array) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(a.numpy(), np.float64).T)
