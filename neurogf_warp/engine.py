"""One model's networks packed for the tensor-core kernels on one device, and the launches that answer queries.

The public functions in ``inference`` validate inputs and frames and call these; everything here takes and
returns ``wp.array``s on the engine's device. Rows are points in the user's frame (``frame`` maps them to the
network's), distances come back in user units.
"""
from __future__ import annotations

import numpy as np
import warp as wp

from .folded import folded_layers
from .kernels import mlp
from .kernels import tensorcore as tc

__all__ = ["Engine", "supported"]


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

    # -- kernels, all compiled by warmup() --------------------------------------------------------------------
    def kernels(self) -> dict:
        D, k = self.D, self.ks0
        return {"embed": tc.embed_kernel(D, k), "distance_cached": tc.distance_kernel(D, k, False),
                "distance_lifted": tc.distance_kernel(D, k, True), "pairs": tc.pair_kernel(D, k),
                "sdf": tc.sdf_kernel(D, k), "path_pre": tc.path_pre_kernel(D, self.path_widths[0]),
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
            tc.launch(tc.embed_kernel(self.D, self.ks0), -(-n // 16),
                      [self.lifting, self.dist_head, self.frame, pts, n, out], self.device)
        return out

    def sources(self, emb: wp.array, pos: wp.array, comp: wp.array | None) -> tc.Sources:
        s = tc.Sources()
        s.emb, s.pos = emb, pos
        s.comp = comp if comp is not None else self._none
        s.count = pos.shape[0]
        return s

    def distances(self, rows: wp.array, cached: wp.array | None, src: tc.Sources, out: wp.array, ld: int,
                  reduce_min: bool, row_comp: wp.array | None, raw: bool = False):
        """Distances from the sources to the rows (points; with ``cached``, their packed embeddings).

        out: (S * ld,) float32 with reduce_min False (row s of the matrix at s * ld), else (ld,) the nearest.
        """
        n = rows.shape[0]
        if not n or not src.count:
            return
        o = tc.DistanceOut()
        o.out, o.ld, o.reduce_min, o.euclid = out, int(ld), int(reduce_min), self.euclid
        o.row_comp = row_comp if row_comp is not None else self._none
        o.raw = int(raw)
        kernel = tc.distance_kernel(self.D, self.ks0, cached is None)
        tc.launch(kernel, -(-n // 16), [self.lifting, self.dist_head, self.frame, rows,
                                        cached if cached is not None else tc.empty_words(self.device), n, src, o],
                  self.device)

    def pairs(self, p: wp.array, q: wp.array, out: wp.array, raw: bool = False):
        n = p.shape[0]
        if n:
            tc.launch(tc.pair_kernel(self.D, self.ks0), -(-n // 16),
                      [self.lifting, self.dist_head, self.frame, p, q, n, self.euclid, int(raw), out], self.device)

    def sdf(self, x: wp.array, out: wp.array):
        n = x.shape[0]
        if n:
            tc.launch(tc.sdf_kernel(self.D, self.ks0), -(-n // 16),
                      [self.lifting, self.sdf_head, self.frame, x, n, out], self.device)

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
