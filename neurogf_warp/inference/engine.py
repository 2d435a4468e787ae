"""One model's networks packed for the tensor-core kernels on one device, and the launches that answer queries.

The public functions in ``inference`` validate inputs and frames and call these; everything here takes and
returns ``wp.array``s on the engine's device. Rows are points in the user's frame (``frame`` maps them to the
network's), distances come back in user units.
"""
from __future__ import annotations

import numpy as np
import warp as wp

from neurogf_warp.kernels.inference import mlp, refine
from neurogf_warp.kernels.inference import tensorcore as tc
from neurogf_warp.model.folded import folded_layers

__all__ = ["Engine", "supported"]

_UNSET = object()


def supported(net) -> bool:
    """Whether the tensor-core kernels handle this network's widths."""
    return net.D in tc.SUPPORTED_D


class Engine:
    """Packed fp16 weights of one network on one device (a few hundred KB) and its kernels."""

    def __init__(self, net, frame: mlp.Frame, device):
        if not supported(net):
            raise ValueError(f"the tensor-core kernels support D in {tc.SUPPORTED_D}, not {net.D}; use precision='fp32'")
        self.device, self.frame, self.D = device, frame, net.D
        layers = folded_layers(net)
        self.ks0 = tc.input_ksteps(3 + 6 * net.fourier)
        self.euclid = 1.0 if net.euclid else 0.0
        self.lifting = tc.lifting_struct(layers["lifting"], net.fourier, device)
        self.dist_head = tc.head_struct(layers["distance"], device)
        self.sdf_head = tc.head_struct(layers["sdf"], device)
        self.path_head = tc.path_struct(layers["guidance"], layers["path"], net.path_residual, net.path_window, device)
        self.path_widths = tc.path_widths(layers["path"])
        self._none = tc.empty_int(device)
        self._launches, self._last = {}, {}

    # -- kernels, all compiled by warmup() --------------------------------------------------------------------
    def kernels(self) -> dict:
        D, k = self.D, self.ks0
        return {"embed": tc.embed_kernel(D, k), "ssad": tc.ssad_kernel(D, *tc.SSAD),
                "ssad_lifted": tc.lift_ssad_kernel(D, k, *tc.LIFT_SSAD),
                "distance_cached": tc.distance_kernel(D, k, False, tc.SOURCE_GROUP),
                "distance_lifted": tc.distance_kernel(D, k, True, tc.SOURCE_GROUP), "pairs": tc.pair_kernel(D, k, tc.PAIR_NC),
                "sdf": tc.sdf_kernel(D, k, *tc.SDF_TILE), "path_pre": tc.path_pre_kernel(D, self.path_widths[0]),
                "path_points": tc.path_points_kernel(*self.path_widths)}

    def row_bytes(self) -> int:
        """Bytes of one packed fp16 embedding."""
        return 2 * self.D

    # -- queries ------------------------------------------------------------------------------------------------
    def embed(self, pts: wp.array, out: wp.array | None = None) -> wp.array:
        """Packed fp16 embeddings of N points: uint32 (N * D/2,) in the kernels' fragment order."""
        n = pts.shape[0]
        if out is None:
            out = wp.empty(n * self.D // 2, dtype=wp.uint32, device=self.device)
        if n:
            kernel = tc.embed_kernel(self.D, self.ks0)
            key = ("embed", n)
            if key not in self._launches:
                if len(self._launches) > 16:  # bounded: a few sizes recur (single sources, paths)
                    for k in [k for k in self._launches if isinstance(k, tuple) and k[0] == "embed"]:
                        self._launches.pop(k)
                        self._last.pop(k, None)
                self._launches[key] = tc.launch(kernel, -(-n // 16), [self.lifting, self.dist_head, self.frame, pts,
                                                                       n, out], self.device, record=True)
            self._replay(key, self._launches[key], {3: pts, 5: out})
        return out

    # -- distances from sources to rows ------------------------------------------------------------------------
    def rows(self, pts: wp.array, cached: wp.array | None, comp: wp.array | None) -> tc.Rows:
        """Rows of a distance query: points, with their kept embeddings or None (embedded in the kernel)."""
        r = tc.Rows()
        r.pts, r.n = pts, pts.shape[0]
        r.cached = cached if cached is not None else tc.empty_words(self.device)
        r.comp = comp if comp is not None else self._none
        return r

    def sources(self, emb: wp.array, pos: wp.array, comp: wp.array | None) -> tc.Sources:
        """Tables of source rows: packed embeddings, user-frame points, component labels (or None)."""
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
        cached = rows.cached.shape[0] > 0
        if count == 1 and cached:
            kind, kernel, mt = "ssad", tc.ssad_kernel(self.D, *tc.SSAD), tc.SSAD[0]
        elif count == 1:
            kind, kernel, mt = "lift_ssad", tc.lift_ssad_kernel(self.D, self.ks0, *tc.LIFT_SSAD), tc.LIFT_SSAD[0]
        else:
            kind, kernel, mt = "distance", tc.distance_kernel(self.D, self.ks0, not cached, tc.SOURCE_GROUP), 1
        key = (kernel, tc.WARPS[kind])  # one recorded launch per kernel, re-recorded when the rows change
        cmd = self._launches.get(key)
        if cmd is None or cmd[0] is not rows:
            self._last.pop(key, None)
            tiles = -(-n // (16 * mt))
            cmd = (rows, tc.launch(kernel, tiles, [self.lifting, self.dist_head, self.frame, rows, src, self._none,
                                                   0, 1, out, 0, 0, self.euclid], self.device, record=True,
                                   warps_per_sm=tc.WARPS[kind]))
            self._launches[key] = cmd
        flags = (tc.REDUCE_MIN if reduce_min else 0) | (tc.RAW if raw else 0)
        self._replay(key, cmd[1], {tc.DIST_SRC: src, tc.DIST_IDS: ids if ids is not None else self._none,
                                   tc.DIST_ROW: int(row0), tc.DIST_COUNT: int(count), tc.DIST_OUT: out,
                                   tc.DIST_LD: int(ld), tc.DIST_FLAGS: flags})

    def _replay(self, key, launch, params: dict):
        """Replay a recorded launch, packing only the parameters that differ from its previous call."""
        last = self._last.setdefault(key, {})
        for i, v in params.items():
            if last.get(i, _UNSET) is not v and not (isinstance(v, int) and last.get(i) == v):
                launch.set_param_at_index(i, v)
                last[i] = v
        if self.device.is_cpu:
            with tc._cpu_blocks():
                launch.launch()
        else:
            launch.launch()

    def pairs(self, p: wp.array, q: wp.array, out: wp.array, raw: bool = False):
        n = p.shape[0]
        if n:
            tc.launch(tc.pair_kernel(self.D, self.ks0, tc.PAIR_NC), -(-n // 16),
                      [self.lifting, self.dist_head, self.frame, p, q, n, self.euclid, int(raw), out], self.device,
                      warps_per_sm=tc.WARPS["pairs"])

    def sdf(self, x: wp.array, out: wp.array):
        n = x.shape[0]
        if n:
            tc.launch(tc.sdf_kernel(self.D, self.ks0, *tc.SDF_TILE), -(-n // (16 * tc.SDF_TILE[0])),
                      [self.lifting, self.sdf_head, self.frame, x, n, out], self.device, warps_per_sm=tc.WARPS["sdf"])

    def paths(self, p: wp.array, q: wp.array, out: wp.array):
        """out: (N, m) vec3, the path head's points."""
        n, m = out.shape
        if not n:
            return
        D, P1 = self.D, self.path_widths[0]
        ends = wp.empty(2 * n * D // 2, dtype=wp.uint32, device=self.device)
        self.embed(p, ends[: n * D // 2])
        self.embed(q, ends[n * D // 2:])
        pre = wp.empty(n * P1, dtype=wp.float32, device=self.device)
        tc.launch(tc.path_pre_kernel(D, P1), -(-n // 16),
                  [self.path_head, ends[: n * D // 2], ends[n * D // 2:], n, pre], self.device)
        tc.launch(tc.path_points_kernel(*self.path_widths), -(-(n * m) // 16),
                  [self.path_head, self.frame, p, q, pre, n, m, out], self.device)

    # -- path shortening on the SDF surface ----------------------------------------------------------------------
    def newton_steps(self, x: wp.array, starts: wp.array, ends: wp.array, steps: int, midpoints: bool, h: float,
                     scratch: dict) -> wp.array:
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
            self.sdf(pts, s)
            wp.launch(refine.newton, (n, m), inputs=[pts, s, h, starts, ends], outputs=[y], device=self.device)
            cur = y
        return cur
