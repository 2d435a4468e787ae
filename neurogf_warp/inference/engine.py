"""One model's networks packed for the tensor-core kernels on one device, and the launches that answer queries.

The backends (``backends.py``) call these; everything here takes and returns ``wp.array``s on the engine's device.
Rows are points in a ``mlp.Frame``'s coordinates (the engine's ``frame``: relative to the mesh centre, unless a
call passes another), distances come back in user units.
"""
from __future__ import annotations

import warp as wp

from neurogf_warp.kernels.inference import mlp, refine
from neurogf_warp.kernels.inference import tensorcore as tc
from neurogf_warp.model.folded import NetShape

from .launches import Recorded

__all__ = ["Engine", "fp16_refusal", "landmark_inputs", "landmark_form"]

_SIZED_LAUNCHES = 16  # recorded launches kept per kind that is keyed by a size (a few sizes recur: single sources,
# path ends, one path)
_PATH_SCRATCH_BYTES = 16 << 20  # path queries up to this much scratch keep it with their recorded launches


def landmark_inputs(options: dict) -> int:
    """Inputs a landmark network's distance head takes besides the embedding: K differences, the two bounds, and
    |p - q| and the bracket's log-width with ``landmark_pair_inputs`` (0 for other networks)."""
    K = options.get("landmarks", 0)
    return K + 2 + 2 * bool(options.get("landmark_pair_inputs")) if K else 0


def landmark_form(options: dict) -> int:
    """``tc.LANDMARK_FORMS`` code of how a landmark network's output is made from its head."""
    if not options.get("landmark_bracket"):
        return tc.LANDMARK_FORMS["plain"]
    return tc.LANDMARK_FORMS["bracket_log" if options.get("landmark_bracket_log") else "bracket"]


def fp16_refusal(shape: NetShape, options: dict | None = None) -> str | None:
    """Why the tensor-core kernels cannot run a network of this shape (None: they can).

    The native code is written for the released layout: lifting F -> D/4 -> D/2 -> D with D in SUPPORTED_D,
    distance and SDF heads D -> D/4 -> D/4 -> 1, a guidance layer 2D -> D and a four-layer point-wise path head
    whose widths are template parameters (P1, P2 multiples of 16; P3 is padded to 16 by the packing). A landmark
    network (``options["landmarks"]`` = K) has D + K + 2 (+ 2) distance-head inputs, K in ``tc.LANDMARK_K``.
    """
    D = shape.D
    if D not in tc.SUPPORTED_D:
        return f"D = {D} (the tensor-core kernels support D in {tc.SUPPORTED_D})"
    want_lift = (D // 4, D // 2, D)
    if shape.lifting[1:] != want_lift:
        return f"lifting widths {shape.lifting} (the tensor-core kernels need (F, {', '.join(map(str, want_lift))}))"
    K = (options or {}).get("landmarks", 0)
    if K and K not in tc.LANDMARK_K:
        return f"K = {K} landmarks (the tensor-core kernels support K in {tc.LANDMARK_K}: multiples of 16 up to 256)"
    extra = landmark_inputs(options or {})
    for name, head, n_in in (("distance", shape.distance, D + extra), ("SDF", shape.sdf, D)):
        if head != (n_in, D // 4, D // 4, 1):
            return f"{name} head widths {head} (the tensor-core kernels need ({n_in}, {D // 4}, {D // 4}, 1))"
    if shape.guidance != (2 * D, D):
        return f"guidance widths {shape.guidance} (the tensor-core kernels need ({2 * D}, {D}))"
    path = shape.path
    if len(path) != 5 or path[0] != D + 3 or path[-1] != 3 or any(w % 16 for w in path[1:3]):
        return (f"path head widths {path} (the tensor-core kernels need ({D + 3}, P1, P2, P3, 3), P1 and P2 "
                "multiples of 16)")
    return None


class Engine:
    """Packed fp16 weights of one network on one device (a few hundred KB), its kernels and recorded launches.

    ``layers``: ``folded.folded_layers(net)``; ``shape``: the ``NetShape`` read from them (refused here, with the
    reason, when the native kernels are not written for it); ``tuning``: the frozen tile settings of every launch.
    """

    def __init__(self, layers: dict, shape: NetShape, options: dict, frame: mlp.Frame, device,
                 tuning: tc.Tuning = tc.Tuning()):
        why = fp16_refusal(shape, options)
        if why is not None:
            raise ValueError(f"precision='fp16' cannot run this network: {why}; use precision='fp32'")
        self.device, self.frame, self.D, self.tuning = device, frame, shape.D, tuning
        self.ks0 = tc.input_ksteps(shape.lifting[0])
        self.euclid = 1.0 if options["euclid"] else 0.0
        self.lifting = tc.lifting_struct(layers["lifting"], options["fourier"], device)
        # K > 0: the distance head's first layer also reads landmark distances; only landmark_ssad runs it
        self.K = options.get("landmarks", 0)
        if self.K:
            self.dist_head = tc.landmark_head_struct(layers["distance"], self.D, self.K, device)
            self.landmark_params = {"lm_floor": float(options.get("landmark_floor", 1.0)), "euclid": self.euclid,
                                    "form": landmark_form(options),
                                    "pair_inputs": int(bool(options.get("landmark_pair_inputs")))}
        else:
            self.dist_head = tc.head_struct(layers["distance"], device)
        self.sdf_head = tc.head_struct(layers["sdf"], device)
        self.path_head = tc.path_struct(layers["guidance"], layers["path"], options["path_residual"],
                                        options["path_window"], device)
        self.path_widths = tc.path_widths(layers["path"])
        self._none = tc.empty_int(device)
        self.launches = Recorded(device, tc._cpu_blocks, keep=_SIZED_LAUNCHES)

    def forget_launches(self):
        """Drop every recorded launch: they hold references to the arrays they were recorded with."""
        self.launches.clear()

    def _launch(self, kernel, n_tiles: int, inputs: list, warps: int, record: bool = False):
        t = self.tuning
        return tc.launch(kernel, n_tiles, inputs, self.device, warps, t.cpu_warps, record=record)

    # -- queries ------------------------------------------------------------------------------------------------
    def embed(self, pts: wp.array, out: wp.array | None = None, frame: mlp.Frame | None = None) -> wp.array:
        """Packed fp16 embeddings of N points (in ``frame``, default the engine's): uint32 (N * D/2,) in the
        kernels' fragment order."""
        n = pts.shape[0]
        if out is None:
            out = wp.empty(n * self.D // 2, dtype=wp.uint32, device=self.device)
        if n:
            kernel = tc.embed_kernel(self.D, self.ks0)
            key = ("embed", n)
            if key not in self.launches:
                cmd = self._launch(kernel, -(-n // 16), [self.lifting, self.dist_head, self.frame, pts, n, out],
                                   self.tuning.warps_other, record=True)
                self.launches.record(key, cmd, kernel, group="embed", cpu_blocks=True)
            self.launches.replay(key, {"pts": pts, "out": out, "frame": frame or self.frame})
        return out

    def embed_point(self, p: wp.vec3, c: int, pos: wp.array, comp: wp.array, out: wp.array):
        """The packed embedding of one point p (frame coordinates) into ``out`` (D/2 uint32), p into pos[0] and the
        label c into comp[0] (comp may be empty): one recorded launch, the point a launch parameter."""
        key = ("embed_point",)
        if key not in self.launches:
            kernel = tc.embed_point_kernel(self.D, self.ks0)
            cmd = self._launch(kernel, 1, [self.lifting, self.dist_head, self.frame, p, c, pos, comp, out],
                               self.tuning.warps_other, record=True)
            self.launches.record(key, cmd, kernel, cpu_blocks=True)
        self.launches.replay(key, {"pt": p, "c": int(c), "pos": pos, "comp": comp, "out": out})

    # -- distances from sources to rows ------------------------------------------------------------------------
    def rows(self, pts: wp.array, cached: wp.array | None, comp: wp.array | None) -> tc.Rows:
        """Rows of a distance query: points, with their kept embeddings or None (embedded in the kernel)."""
        r = tc.Rows()
        r.pts, r.n = pts, pts.shape[0]
        r.cached = cached if cached is not None else tc.empty_words(self.device)
        r.comp = comp if comp is not None else self._none
        return r

    def sources(self, emb: wp.array, pos: wp.array, comp: wp.array | None) -> tc.Sources:
        """Tables of source rows: packed embeddings, points (frame coordinates), component labels (or None)."""
        s = tc.Sources()
        s.emb, s.pos = emb, pos
        s.comp = comp if comp is not None else self._none
        return s

    def distances(self, rows: tc.Rows, src: tc.Sources, out: wp.array, ld: int, ids: wp.array | None = None,
                  row0: int = 0, count: int = 1, reduce_min: bool = False, raw: bool = False):
        """Distances from the sources (rows ``ids`` of ``src``, or row0 .. row0 + count - 1) to ``rows``.

        out: (count * ld,) float32, row s of the result at s * ld; with reduce_min (ld,), the nearest source.
        A single source on kept embeddings takes the streaming kernel. Launches are recorded once per rows and
        replayed with the call's parameters, which keeps a query's host time to a few parameter updates.
        """
        n = rows.n
        if not n or not count:
            return
        t = self.tuning
        cached = rows.cached.shape[0] > 0
        if count == 1 and cached:
            kernel, mt, warps = tc.ssad_kernel(self.D, *t.ssad, t.regs_ssad), t.ssad[0], t.warps_ssad
        elif count == 1:
            kernel, mt, warps = tc.lift_ssad_kernel(self.D, self.ks0, *t.lift_ssad), t.lift_ssad[0], t.warps_lift_ssad
        else:
            kernel, mt, warps = (tc.distance_kernel(self.D, self.ks0, not cached, t.source_group, t.regs_distance), 1,
                                 t.warps_distance)
        key = kernel  # one recorded launch per kernel, re-recorded when the rows change
        if key not in self.launches or self.launches.held(key) is not rows:
            tiles = -(-n // (16 * mt))
            cmd = self._launch(kernel, tiles, [self.lifting, self.dist_head, self.frame, rows, src, self._none, 0, 1,
                                               out, 0, 0, self.euclid], warps, record=True)
            self.launches.record(key, cmd, kernel, held=rows, cpu_blocks=True)
        flags = (tc.REDUCE_MIN if reduce_min else 0) | (tc.RAW if raw else 0)
        self.launches.replay(key, {"src": src, "src_ids": ids if ids is not None else self._none,
                                   "src_row": int(row0), "n_src": int(count), "out": out, "ld": int(ld),
                                   "flags": flags})

    def landmark_ssad(self, rows: tc.Rows, src: tc.Sources, table: wp.array, out: wp.array, row0: int,
                      raw: bool = False):
        """A landmark network's distances from source row ``row0`` of ``src`` to every row of ``rows`` (kept
        embeddings), ``table`` the (V * K,) float32 landmark rows of both (the rows' numbering). out: (V,) float32."""
        n = rows.n
        if not n:
            return
        t = self.tuning
        mt, prefetch = t.landmark_ssad
        kernel = tc.landmark_ssad_kernel(self.D, self.K, mt, prefetch, t.regs_ssad)
        key = kernel
        if key not in self.launches or self.launches.held(key) is not rows:
            p = self.landmark_params
            cmd = self._launch(kernel, -(-n // (16 * mt)), [self.dist_head, self.frame, rows, src, 0, table,
                                                             p["lm_floor"], p["euclid"], p["form"], p["pair_inputs"],
                                                             out, 0], t.warps_landmark_ssad, record=True)
            self.launches.record(key, cmd, kernel, held=rows, cpu_blocks=True)
        self.launches.replay(key, {"src": src, "src_row": int(row0), "table": table, "out": out,
                                   "flags": tc.RAW if raw else 0})

    def pairs(self, p: wp.array, q: wp.array, out: wp.array, raw: bool = False, frame: mlp.Frame | None = None):
        n = p.shape[0]
        if n:
            self._launch(tc.pair_kernel(self.D, self.ks0, self.tuning.pair_nc), -(-n // 16),
                         [self.lifting, self.dist_head, frame or self.frame, p, q, n, self.euclid, int(raw), out],
                         self.tuning.warps_pairs)

    def sdf(self, x: wp.array, out: wp.array, frame: mlp.Frame | None = None):
        n = x.shape[0]
        if n:
            mt, nc = self.tuning.sdf_tile
            self._launch(tc.sdf_kernel(self.D, self.ks0, mt, nc), -(-n // (16 * mt)),
                         [self.lifting, self.sdf_head, frame or self.frame, x, n, out], self.tuning.warps_sdf)

    def paths(self, p: wp.array, q: wp.array, out: wp.array, frame: mlp.Frame | None = None):
        """out: (N, m) vec3, the path head's points.

        Small queries (scratch up to ``_PATH_SCRATCH_BYTES``: every host-bound size) keep their scratch and two
        recorded launches per (N, m); larger ones allocate and launch per call."""
        n, m = out.shape
        if not n:
            return
        D, P1 = self.D, self.path_widths[0]
        half = n * D // 2
        pre_k, points_k = tc.path_pre_kernel(D, P1), tc.path_points_kernel(*self.path_widths)
        warps = self.tuning.warps_other
        params = {"frame": frame or self.frame, "ps": p, "qs": q, "out": out}
        key, pre_key = ("path", n, m), ("path_pre", n, m)
        kept = key in self.launches and pre_key in self.launches  # both, or record both again
        if kept:
            ends_p, ends_q, pre = self.launches.held(key)
        else:
            ends = wp.empty(2 * half, dtype=wp.uint32, device=self.device)
            ends_p, ends_q = ends[:half], ends[half:]
            pre = wp.empty(n * P1, dtype=wp.float32, device=self.device)
        self.embed(p, ends_p, frame)
        self.embed(q, ends_q, frame)
        if not kept and (2 * half + n * P1) * 4 > _PATH_SCRATCH_BYTES:
            self._launch(pre_k, -(-n // 16), [self.path_head, ends_p, ends_q, n, pre], warps)
            self._launch(points_k, -(-(n * m) // 16), [self.path_head, params["frame"], p, q, pre, n, m, out], warps)
            return
        if not kept:
            pre_cmd = self._launch(pre_k, -(-n // 16), [self.path_head, ends_p, ends_q, n, pre], warps, record=True)
            points_cmd = self._launch(points_k, -(-(n * m) // 16), [self.path_head, params["frame"], p, q, pre, n, m,
                                                                     out], warps, record=True)
            self.launches.record(pre_key, pre_cmd, pre_k, group="path_pre", cpu_blocks=True)
            self.launches.record(key, points_cmd, points_k, held=(ends_p, ends_q, pre), group="path", cpu_blocks=True)
        self.launches.replay(pre_key, {})
        self.launches.replay(key, params)

    # -- path shortening on the SDF surface ----------------------------------------------------------------------
    def newton_steps(self, x: wp.array, starts: wp.array, ends: wp.array, steps: int, midpoints: bool, h: float,
                     scratch: dict, frame: mlp.Frame | None = None) -> wp.array:
        """``steps`` Newton steps onto the SDF surface for the inner points of paths x (N, m) (ends pinned to
        starts/ends), each from the midpoint of its neighbours when ``midpoints`` (a shortening sweep); every
        SDF value in one batched launch per step. Returns the result (x itself is left unchanged)."""
        n, m = x.shape
        if (n, m) != scratch.get("shape"):
            scratch.update(shape=(n, m), pts=wp.empty(4 * n * m, dtype=wp.vec3, device=self.device),
                           s=wp.empty(4 * n * m, dtype=wp.float32, device=self.device),
                           y=[wp.empty((n, m), dtype=wp.vec3, device=self.device) for _ in range(2)])
        pts, s, ys = scratch["pts"], scratch["s"], scratch["y"]
        cur = x
        for k in range(steps):
            y = ys[k % 2] if ys[k % 2] is not cur else ys[(k + 1) % 2]
            wp.launch(refine.stencil, (n, m), inputs=[cur, int(midpoints and k == 0), h], outputs=[pts],
                      device=self.device)
            self.sdf(pts, s, frame)
            wp.launch(refine.newton, (n, m), inputs=[pts, s, h, starts, ends], outputs=[y], device=self.device)
            cur = y
        return cur
