"""The two ways a query runs, behind one interface: ``TensorCores`` (precision "fp16", the fused kernels of
``kernels/inference/tensorcore.py``) and ``PerThread`` (precision "fp32", the per-thread float32 kernels of
``kernels/inference/mlp.py`` and the tile head of ``head_fp32.py``).

A backend is chosen once per (state, precision) by ``choose_backend``; the public queries call only these methods
and never look at the precision:

    bind()                                             keep every vertex's embedding; bytes kept
    vertex_distances(md, pts, ids, comp, out, reduce_min, raw)   sources -> every mesh vertex (internal order)
    target_distances(src, tgt, src_comp, tgt_comp, out, raw)     sources -> given targets, (S, T)
    pairs(p, q, out, raw, frame)                       distances of point pairs
    sdf(x, out, frame, test_domain)                    the SDF head (NaN outside the domain when test_domain)
    paths(p, q, out, frame)                            the path head's points, out (N, m) vec3
    settle(x, starts, ends, steps, scratch, frame)     path refinement: ends pinned, inner points onto the surface
    sweep(x, starts, ends, scratch, frame)             one shortening sweep (midpoints, one Newton step)

A landmark network (``NeuroGFNet(landmarks=K)``): its distance head also reads each point's row of exact distances
to the landmarks (a vertex's own row; a point's row interpolated at its closest surface point). PerThread answers
every distance query of it (``kernels/inference/landmark.py``); TensorCores a single vertex source on a bound model,
handing the others to a PerThread when "auto" chose it and refusing them for "fp16".

Every array is a ``wp.array`` on the state's device; vertex queries take points relative to the mesh centre
(``state.frame``), point queries points in the ``frame`` they pass; distances come back in user units.
"""
from __future__ import annotations


import numpy as np
import warp as wp

from neurogf_warp.common.chunks import CPU_CHUNK_ALIGN, CPU_CHUNK_SECONDS, in_chunks
from neurogf_warp.inference.engine import fp16_refusal
from neurogf_warp.inference.state import PRECISIONS, MeshOnDevice, QueryState, check_memory, query_state
from neurogf_warp.kernels.inference import finish, head_fp32, landmark, mlp
from neurogf_warp.kernels.inference import refine as refine_kernels
from neurogf_warp.model.folded import NetShape

__all__ = ["backend_of", "bind", "fp32_refusal", "TensorCores", "PerThread", "in_chunks", "CPU_CHUNK_SECONDS",
           "CPU_CHUNK_ALIGN"]

_HID = mlp.MAX_D // 2   # the per-thread kernels' hidden vectors (vec_h)
_ACC = mlp.MAX_D // 4   # their float64 accumulators of a head's first layer (vec_acc)


def fp32_refusal(shape: NetShape, options: dict | None = None) -> str | None:
    """Why the per-thread float32 kernels cannot run a network of this shape and these options (``net.options``;
    None: they can). Their weights struct has three lifting layers, three-layer heads and a four-layer point-wise
    path head, and their local vectors bound the widths. A landmark network's distance head reads D + K + 2 inputs
    (``kernels/inference/landmark.py``); its geometric bracket and pair inputs are not written there."""
    D = shape.D
    K = (options or {}).get("landmarks", 0)
    if K and (options.get("landmark_bracket_log") or options.get("landmark_pair_inputs")):
        return ("a landmark network with landmark_bracket_log or landmark_pair_inputs (the per-thread kernels run "
                "landmark networks with the linear bracket or without one, and no pair inputs)")
    if len(shape.lifting) != 4 or D > mlp.MAX_D or max(shape.lifting[1:3]) > _HID or \
            shape.lifting[0] > 3 + 6 * mlp.MAX_FOURIER:
        return (f"lifting widths {shape.lifting} (the per-thread kernels need (F, H1, H2, D): three layers, "
                f"H1, H2 <= {_HID}, D <= {mlp.MAX_D}, F <= {3 + 6 * mlp.MAX_FOURIER})")
    for name, head, width in (("distance", shape.distance, D + K + 2 * bool(K)), ("SDF", shape.sdf, D)):
        if len(head) != 4 or head[0] != width or head[-1] != 1 or head[1] > _ACC or head[2] > _HID:
            return (f"{name} head widths {head} (the per-thread kernels need ({width}, H1, H2, 1): three layers, "
                    f"H1 <= {_ACC}, H2 <= {_HID})")
    if shape.guidance != (2 * D, D):
        return f"guidance widths {shape.guidance} (the per-thread kernels need ({2 * D}, {D}))"
    p = shape.path
    if len(p) != 5 or p[0] != D + 3 or p[-1] != 3 or max(p[1:4]) > _HID:
        return f"path head widths {p} (the per-thread kernels need ({D + 3}, P1, P2, P3, 3), P1..P3 <= {_HID})"
    return None


def backend_of(state: QueryState, precision: str):
    """The backend for ``precision`` ("auto", "fp16", "fp32") on the state's device, chosen once and kept in
    ``state.backends``: "auto" is fp16 on CUDA devices where the tensor-core kernels run the network's shape,
    else fp32. A network that the chosen backend cannot run is refused with an error naming its shape."""
    b = state.backends.get(precision)
    if b is None:
        b = state.backends[precision] = _choose(state, precision)
    return b


def bind(model, device=None, precision: str = "auto") -> int:
    """Embed every mesh vertex once and keep the result on ``device`` for later vertex queries; returns bytes kept.

    fp16: packed (V, D/2) uint32, 2 D bytes per vertex; fp32: (V, D) float32, 4 D bytes per vertex.
    ``neurogf_warp.unbind(model)`` (or ``model.unbind()``) frees them and everything made from them.
    """
    return backend_of(query_state(model, device), precision).bind()


def _choose(state: QueryState, precision: str):
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    fp16_no, fp32_no = fp16_refusal(state.shape, state.options), fp32_refusal(state.shape, state.options)
    chosen_by_auto = precision == "auto"
    if precision == "auto":
        precision = "fp16" if state.device.is_cuda and fp16_no is None else "fp32"
    if precision == "fp16" and fp16_no is not None:
        raise ValueError(f"precision='fp16' cannot run this network: {fp16_no}; use precision='fp32'")
    if precision == "fp32" and fp32_no is not None:
        raise ValueError(f"this network's shape ({state.shape}) is not supported by the per-thread kernels: {fp32_no}")
    if precision == "fp32":
        return PerThread(state)
    # "auto" on a landmark network: the tensor cores answer what they run (a vertex source on a bound model), the
    # per-thread kernels the other distance queries
    auto_landmarks = chosen_by_auto and state.options.get("landmarks") and fp32_no is None
    return TensorCores(state, PerThread(state) if auto_landmarks else None)


class _Backend:
    precision = ""
    bytes_per_channel = 0

    def __init__(self, state: QueryState):
        self.state = state
        self.device = state.device

    def bind(self) -> int:
        st = self.state
        md = st.mesh("binding")
        b = st.bound.get(self.precision)
        if b is None:
            need = md.V * st.shape.D * self.bytes_per_channel
            check_memory(self.device, need, f"keeping the embeddings of {md.V:,} vertices ({need / 1e6:.0f} MB)",
                         "query with cache=False (every call then embeds the vertices) or free GPU memory", 0.5)
            b = st.bound[self.precision] = self._embed_vertices(md)
        return int(b.capacity)

    @property
    def kept(self):
        """This backend's kept vertex embeddings, or None."""
        return self.state.bound.get(self.precision)


class TensorCores(_Backend):
    """precision="fp16": the fused tensor-core kernels (``engine.Engine``)."""

    precision = "fp16"
    bytes_per_channel = 2

    def __init__(self, state: QueryState, landmark_fallback: "PerThread | None" = None):
        super().__init__(state)
        self.fallback = landmark_fallback  # a landmark network's queries these kernels do not run (precision "auto")
        state.engine  # built (and the network's shape checked) now

    @property
    def eng(self):
        return self.state.engine

    def _embed_vertices(self, md: MeshOnDevice):
        return self.eng.embed(md.verts)

    def _tables(self, md: MeshOnDevice, bound):
        """(rows, sources) tables of the kept vertex embeddings (made once per binding)."""
        st = self.state
        if st.tables is None or st.tables[0] is not bound:
            eng = self.eng
            st.tables = (bound, eng.rows(md.verts, bound, md.comp), eng.sources(bound, md.verts, md.comp))
        return st.tables[1], st.tables[2]

    def _elsewhere(self, what: str) -> bool:
        """True when a landmark network's query goes to the per-thread kernels (precision "auto"); for "fp16" an
        error: these kernels answer a landmark network's single vertex source on a bound model only."""
        if not self.state.options.get("landmarks"):
            return False
        if self.fallback is not None:
            return True
        raise ValueError(f"precision='fp16' runs a landmark network's single-source query from a vertex on a "
                         f"bound model only (neurogf_warp.ssad(model, vertex) with cache=True); {what} needs "
                         "precision='fp32' (or 'auto')")

    def _landmark_table(self, md: MeshOnDevice) -> wp.array:
        """The landmark table's rows in internal vertex order on the device, (V * K,) float32 (the per-thread
        kernels' copy, made once)."""
        return md.landmark_table(self.state.model).rows.flatten()

    def vertex_distances(self, md: MeshOnDevice, pts: np.ndarray, ids, comp, out: wp.array, reduce_min: bool,
                         raw: bool):
        eng, dev, bound = self.eng, self.device, self.kept
        S, V = len(pts), md.V
        if eng.K:
            what = ("a point source" if ids is None else f"a query from {S} sources" if S != 1 else
                    "a query without kept embeddings (cache=False)" if bound is None else None)
            if what is not None and self._elsewhere(what):
                return self.fallback.vertex_distances(md, pts, ids, comp, out, reduce_min, raw)
            rows, table = self._tables(md, bound)
            eng.landmark_ssad(rows, table, self._landmark_table(md), out, int(ids[0]), raw)
            return
        kw = dict(count=S, reduce_min=reduce_min, raw=raw)
        if bound is not None and ids is not None:  # rows of the kept tables: nothing to embed or copy
            rows, table = self._tables(md, bound)
            if S == 1:
                eng.distances(rows, table, out, V, row0=int(ids[0]), **kw)
            else:
                eng.distances(rows, table, out, V, ids=self.state.ids_on_device(ids), **kw)
            return
        if bound is not None:
            rows = self._tables(md, bound)[0]
        else:
            if md.lifted is None:
                md.lifted = eng.rows(md.verts, None, md.comp)
            rows = md.lifted
        if S == 1:
            eng.distances(rows, self._point_source(pts, comp), out, V, **kw)
            return
        src_pos = wp.array(pts.astype(np.float32), dtype=wp.vec3, device=dev)
        src_comp = wp.array(comp.astype(np.int32), dtype=wp.int32, device=dev) if comp is not None else None
        eng.distances(rows, eng.sources(eng.embed(src_pos), src_pos, src_comp), out, V, **kw)

    def _point_source(self, pts: np.ndarray, comp):
        """The table of one source point: the state's kept (position, label, embedding) buffers, filled by one
        recorded launch (the point travels as a launch parameter), so a single-source query makes no copy from
        the host and no allocation. Later queries on the stream overwrite the buffers after this one's kernels."""
        st, eng = self.state, self.eng
        if st.point_source is None:
            pos = wp.empty(1, dtype=wp.vec3, device=self.device)
            lab = wp.empty(1, dtype=wp.int32, device=self.device)
            emb = wp.empty(eng.D // 2, dtype=wp.uint32, device=self.device)
            st.point_source = (pos, lab, emb, (eng.sources(emb, pos, None), eng.sources(emb, pos, lab)))
        pos, lab, emb, tables = st.point_source
        p = pts.astype(np.float32)[0]
        multi = comp is not None
        eng.embed_point(wp.vec3(p[0], p[1], p[2]), int(comp[0]) if multi else 0, pos, lab if multi else st.no_ints,
                        emb)
        return tables[multi]

    def target_distances(self, src_pos, tgt_pos, src_comp, tgt_comp, out: wp.array, raw: bool):
        if self._elsewhere("a distance matrix to given targets"):
            return self.fallback.target_distances(src_pos, tgt_pos, src_comp, tgt_comp, out, raw)
        eng = self.eng
        eng.distances(eng.rows(tgt_pos, eng.embed(tgt_pos), tgt_comp), eng.sources(eng.embed(src_pos), src_pos,
                                                                                   src_comp),
                      out.reshape(-1), out.shape[1], count=out.shape[0], raw=raw)

    def pairs(self, p, q, out, raw: bool, frame):
        if self._elsewhere("a point-pair distance"):
            return self.fallback.pairs(p, q, out, raw, frame)
        self.eng.pairs(p, q, out, raw, frame)

    def sdf(self, x, out, frame, test_domain: bool = False):
        self.eng.sdf(x, out, frame)
        if test_domain:  # the native SDF kernel does not test the domain (a test there cost it 16%)
            wp.launch(finish.nan_outside, x.shape[0], inputs=[x, frame], outputs=[out], device=self.device)

    def paths(self, p, q, out, frame):
        self.eng.paths(p, q, out, frame)

    def _h(self) -> float:
        m = self.state.model
        return refine_kernels.FD_STEP / (m.scale if m.in_mesh_frame else 1.0)

    def settle(self, x, starts, ends, steps: int, scratch: dict, frame):
        # a copy: the result lives in the scratch buffers that the next steps reuse
        return wp.clone(self.eng.newton_steps(x, starts, ends, steps, False, self._h(), scratch, frame))

    def sweep(self, x, starts, ends, scratch: dict, frame):
        return self.eng.newton_steps(x, starts, ends, 1, True, self._h(), scratch, frame)


class PerThread(_Backend):
    """precision="fp32": per-thread float32 kernels with float64 sums (and the tile head on kept embeddings)."""

    precision = "fp32"
    bytes_per_channel = 4

    def embed(self, pts: wp.array, frame=None) -> wp.array:
        """Embeddings e(x) of (N,) vec3 points (in ``frame``, default ``state.frame``): (N, D) float32."""
        st = self.state
        out = wp.empty((pts.shape[0], st.shape.D), dtype=wp.float32, device=self.device)
        in_chunks(self.device, pts.shape[0], lambda lo, hi: wp.launch(
            mlp.embed_points, hi - lo, inputs=[st.weights, pts[lo:hi], frame or st.frame], outputs=[out[lo:hi]],
            device=self.device))
        return out

    def _embed_vertices(self, md: MeshOnDevice):
        return self.embed(md.verts)

    def _head_values(self, md: MeshOnDevice, src_pos: wp.array) -> wp.array:
        """(S, V) distance-head values (network frame, no |x - s| term) from per-thread or tile kernels."""
        st, dev, bound = self.state, self.device, self.kept
        S, V = src_pos.shape[0], md.V
        es = self.embed(src_pos)
        head = wp.empty((S, V), dtype=wp.float32, device=dev)
        if bound is None or st.shape.D > head_fp32.MAX_D:  # every (source, vertex) its own: chunks of vertices
            in_chunks(dev, V, lambda lo, hi: wp.launch(
                head_fp32.head_rows, (S, hi - lo), outputs=[head[:, lo:hi]], device=dev,
                inputs=[st.head_weights, es, src_pos, md.verts[lo:hi], st.frame]), first=max(1, 2048 // max(S, 1)))
            return head
        if st.tile_head is None:  # the tile kernel takes biases as (H, 1) columns
            w = st.weights
            col = lambda b: wp.array(b.numpy().reshape(-1, 1), dtype=wp.float32, device=dev)
            st.tile_head = (w.g0_w, col(w.g0_b), w.g1_w, col(w.g1_b), w.g2_w)
        weights = st.tile_head
        H, D = weights[0].shape
        kernel = head_fp32.head_kernel(D, H, head_fp32.BLOCK, head_fp32.CHUNK)
        for s in range(S):
            wp.launch_tiled(kernel, dim=[(V + head_fp32.BLOCK - 1) // head_fp32.BLOCK],
                            inputs=[es[s: s + 1], bound, *weights, D // head_fp32.CHUNK], outputs=[head[s: s + 1]],
                            block_dim=head_fp32.THREADS, device=dev)
        return head

    def _finish(self, head, rows, row_comp, src, src_comp, out, raw: bool, euclid: float | None = None):
        """Finished distances from head values (``euclid``: the |x - s| term's factor, default the network's)."""
        st = self.state
        if euclid is None:
            euclid = 1.0 if st.options["euclid"] else 0.0

        def run(lo, hi):  # columns lo..hi (rows of the result: targets)
            wp.launch(finish.finish_rows, (head.shape[0], hi - lo),
                      inputs=[head[:, lo:hi], rows[lo:hi], row_comp[lo:hi] if row_comp is not None else st.no_ints,
                              src, src_comp if src_comp is not None else st.no_ints, st.frame, euclid, int(raw)],
                      outputs=[out[:, lo:hi]], device=self.device)

        in_chunks(self.device, head.shape[1], run, first=1 << 16)

    def vertex_distances(self, md: MeshOnDevice, pts: np.ndarray, ids, comp, out: wp.array, reduce_min: bool,
                         raw: bool):
        dev = self.device
        S, V = len(pts), md.V
        src_pos = wp.array(pts.astype(np.float32), dtype=wp.vec3, device=dev)
        src_comp = wp.array(comp.astype(np.int32), dtype=wp.int32, device=dev) if comp is not None else None
        if self.landmarks:  # the head's values include the floor under them: no |x - s| term when finishing
            lm = self._table()
            ex = self.kept if self.kept is not None else self.embed(md.verts)
            head = self._landmark_head(lm, src_pos, self._locate(lm, src_pos, self.state.frame, ids), md.verts, ex)
        else:
            head = self._head_values(md, src_pos)
        full = out.reshape((S, V)) if not reduce_min else wp.empty((S, V), dtype=wp.float32, device=dev)
        self._finish(head, md.verts, md.comp if md.multi else None, src_pos, src_comp, full, raw,
                     euclid=0.0 if self.landmarks else None)
        if reduce_min:
            wp.launch(finish.min_rows, V, inputs=[full], outputs=[out], device=dev)

    def target_distances(self, src_pos, tgt_pos, src_comp, tgt_comp, out: wp.array, raw: bool):
        st = self.state
        if self.landmarks:
            lm = self._table()
            head = self._landmark_head(lm, src_pos, self._locate(lm, src_pos, st.frame), tgt_pos, self.embed(tgt_pos),
                                       self._locate(lm, tgt_pos, st.frame))
            self._finish(head, tgt_pos, tgt_comp, src_pos, src_comp, out, raw, euclid=0.0)
            return
        es = self.embed(src_pos)
        head = wp.empty(out.shape, dtype=wp.float32, device=self.device)
        wp.launch(head_fp32.head_rows, out.shape, outputs=[head], device=self.device,
                  inputs=[st.head_weights, es, src_pos, tgt_pos, st.frame])
        self._finish(head, tgt_pos, tgt_comp, src_pos, src_comp, out, raw)

    def pairs(self, p, q, out, raw: bool, frame):
        st = self.state
        if self.landmarks:
            lm = self._table()
            (pi, pw), (qi, qw) = self._locate(lm, p, frame), self._locate(lm, q, frame)
            wp.launch(landmark.pair_distances, p.shape[0], inputs=[st.weights, lm, p, q, pi, pw, qi, qw, frame, int(raw)],
                      outputs=[out], device=self.device)
            return
        wp.launch(finish.finish_pairs, p.shape[0], inputs=[st.head_weights, p, q, frame,
                                                           1.0 if st.options["euclid"] else 0.0, int(raw)],
                  outputs=[out], device=self.device)

    # ---- landmark networks: the distance head also reads the table rows of both points (kernels/inference/landmark.py)
    @property
    def landmarks(self) -> int:
        """K, the network's landmark count (0: not a landmark network)."""
        return self.state.options.get("landmarks", 0)

    def _table(self) -> landmark.LandmarkTable:
        st = self.state
        return st.mesh("a landmark network's distance").landmark_table(st.model)

    def _locate(self, lm: landmark.LandmarkTable, pts: wp.array, frame, ids=None):
        """(vec3i ids, vec3 weights) locations of points in ``frame`` (their closest surface points' table rows), or of
        the internal vertices ``ids`` (numpy, their exact rows) given for them."""
        n, dev = pts.shape[0], self.device
        if ids is not None:
            w = np.zeros((n, 3), np.float32)
            w[:, 0] = 1.0
            return (wp.array(np.repeat(np.asarray(ids, np.int32).reshape(-1, 1), 3, 1), dtype=wp.vec3i, device=dev),
                    wp.array(w, dtype=wp.vec3, device=dev))
        loc = (wp.empty(n, dtype=wp.vec3i, device=dev), wp.empty(n, dtype=wp.vec3, device=dev))
        if n:
            wp.launch(landmark.locate_points, n, inputs=[lm, pts, frame], outputs=list(loc), device=dev)
        return loc

    def _landmark_head(self, lm, src_pos, src_loc, xs, ex, x_loc=None) -> wp.array:
        """(S, N) landmark distances (network frame) from sources to rows xs (embeddings ex; locations x_loc, None:
        the rows are the mesh's vertices), in chunks of rows."""
        st, dev = self.state, self.device
        S, N = src_pos.shape[0], xs.shape[0]
        es = self.embed(src_pos)
        head = wp.empty((S, N), dtype=wp.float32, device=dev)
        none = (wp.empty(0, dtype=wp.vec3i, device=dev), wp.empty(0, dtype=wp.vec3, device=dev))
        x_ids, x_w = x_loc if x_loc is not None else none
        in_chunks(dev, N, lambda lo, hi: wp.launch(
            landmark.head_table, (S, hi - lo), device=dev, outputs=[head[:, lo:hi]],
            inputs=[st.weights, lm, es, src_pos, *src_loc, ex, xs, x_ids, x_w, st.frame, lo]),
            first=max(1, 2048 // max(S, 1)))
        return head

    def sdf(self, x, out, frame, test_domain: bool = False):  # the kernel gives NaN outside the domain anyway
        wp.launch(mlp.signed_distances, x.shape[0], inputs=[self.state.weights, x, frame], outputs=[out],
                  device=self.device)

    def paths(self, p, q, out, frame):
        st, dev = self.state, self.device
        n, D = p.shape[0], st.shape.D
        w = st.weights
        e = wp.empty((2 * n, D), dtype=wp.float32, device=dev)
        wp.launch(mlp.embed_points, n, inputs=[w, p, frame], outputs=[e[:n]], device=dev)
        wp.launch(mlp.embed_points, n, inputs=[w, q, frame], outputs=[e[n:]], device=dev)
        g = wp.empty((n, D), dtype=wp.float32, device=dev)
        pre = wp.empty((n, w.p0_w.shape[0]), dtype=wp.float32, device=dev)
        wp.launch(mlp.path_guidance, (n, D), inputs=[w, e, n], outputs=[g], device=dev)
        wp.launch(mlp.path_first_layer, pre.shape, inputs=[w, g], outputs=[pre], device=dev)
        wp.launch(mlp.path_points, out.shape, inputs=[w, p, q, pre, frame], outputs=[out], device=dev)

    def settle(self, x, starts, ends, steps: int, scratch: dict, frame):
        wp.launch(mlp.pin_and_project, x.shape, inputs=[self.state.weights, starts, ends, frame, steps], outputs=[x],
                  device=self.device)
        return x

    def sweep(self, x, starts, ends, scratch: dict, frame):
        if scratch.get("shape") != x.shape:
            scratch.update(shape=x.shape, tmp=wp.empty_like(x))
        y = scratch["tmp"]
        wp.launch(mlp.relax_paths, x.shape, inputs=[self.state.weights, x, frame, 1], outputs=[y], device=self.device)
        scratch["tmp"] = x
        return y
