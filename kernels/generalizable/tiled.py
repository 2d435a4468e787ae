"""Tile (block-cooperative) version of the pair query network, for tensor cores on CUDA.

The SIMT ``pair_distance`` kernel keeps one pair per thread and its 128-wide vectors in local memory: about two
loads per multiply-add, far from the GPU's arithmetic peak. Here a block handles ``B`` pairs at once and every
layer is a ``tile_matmul`` (cuBLASDx on CUDA: HMMA tensor cores with float16 operands; a scalar GEMM on the CPU
and with ``mathdx=False``):

    gs = G[nn(s)] (B, 128, gathered rows) + s (B, 3) @ Wx^T (3, 128);  likewise gt
    d  = |relu(gs) - relu(gt)|                       (B, 128)
    h0 = relu(d @ W0^T + b0)                         (B, 128)
    h1 = relu(h0 @ W1^T + b1)                        (B, 64)
    r  = h1 @ w2^T                                   (B, 1)

Inputs come from two SIMT kernels of the same module (``pair_prep``: unit-frame coordinates and nearest cloud
points; ``pair_finish``: ratio -> distance in user units, exact 0 for equal points, +inf across components).
"""
import warp as wp

from . import kernels

_CACHE: dict = {}


def tiled_kernels(mode: str = "fp32", block_pairs: int = 32, operand: str = "fp32", mathdx: bool = True):
    """Kernels for one (arithmetic mode, B pairs per block, GEMM operand precision, cuBLASDx on/off).

    operand: "fp32"/"fp64" (the mode's storage type) or "fp16" (tensor cores on CUDA; about 1e-3 relative
    error). Accumulation is always in the mode's accumulation type.
    """
    key = (mode, block_pairs, operand, mathdx)
    if key not in _CACHE:
        _CACHE[key] = _build(*key)
    return _CACHE[key]


def _build(mode, B, operand, mathdx):
    if mode not in ("fp32", "fp64"):
        raise ValueError(f"the tiled query supports modes fp32 and fp64, not {mode!r}")
    base = kernels(mode)
    T, A = base.dtype, base.acc
    O = wp.float16 if operand == "fp16" else T  # GEMM operand type
    W = 128
    H = 64
    name = f"neurogf_generalizable_tiled_{mode}_{B}_{operand}_{int(mathdx)}"
    opts = dict(enable_backward=False, module=name)

    @wp.func
    def relu_diff(a: A, b: A):
        return wp.abs(wp.max(a, A(0.0)) - wp.max(b, A(0.0)))

    @wp.func
    def relu_add(a: A, b: A):
        return wp.max(a + b, A(0.0))

    @wp.kernel(**opts)
    def pair_prep(cloud: wp.array2d(dtype=T), grid: wp.uint64, radius: float, use_grid: int,
                  s: wp.array2d(dtype=T), t: wp.array2d(dtype=T),
                  cx: wp.float64, cy: wp.float64, cz: wp.float64, scale: wp.float64,
                  su: wp.array2d(dtype=A), tu: wp.array2d(dtype=A),
                  si: wp.array(dtype=wp.int32), ti: wp.array(dtype=wp.int32)):
        """Thread m: unit-frame coordinates of s[m], t[m] and their nearest cloud points."""
        m = wp.tid()
        sx = A((wp.float64(s[m, 0]) - cx) * scale)
        sy = A((wp.float64(s[m, 1]) - cy) * scale)
        sz = A((wp.float64(s[m, 2]) - cz) * scale)
        tx = A((wp.float64(t[m, 0]) - cx) * scale)
        ty = A((wp.float64(t[m, 1]) - cy) * scale)
        tz = A((wp.float64(t[m, 2]) - cz) * scale)
        su[m, 0] = sx
        su[m, 1] = sy
        su[m, 2] = sz
        tu[m, 0] = tx
        tu[m, 1] = ty
        tu[m, 2] = tz
        si[m] = base.nearest_point_func(cloud, grid, radius, use_grid, sx, sy, sz)
        ti[m] = base.nearest_point_func(cloud, grid, radius, use_grid, tx, ty, tz)

    @wp.kernel(**opts)
    def pair_head(g: wp.array2d(dtype=A), si: wp.array(dtype=wp.int32), ti: wp.array(dtype=wp.int32),
                  su: wp.array2d(dtype=A), tu: wp.array2d(dtype=A), wxt: wp.array2d(dtype=A),
                  w0t: wp.array2d(dtype=O), b0: wp.array2d(dtype=A), w1t: wp.array2d(dtype=O),
                  b1: wp.array2d(dtype=A), w2t: wp.array2d(dtype=O), ratio: wp.array2d(dtype=A)):
        """Block i: the ratio of pairs [i B, (i + 1) B) (rows past the end are computed on zeros and not
        stored)."""
        i = wp.tid()
        o = i * B
        js = wp.tile_load(si, shape=B, offset=o, storage="shared")
        jt = wp.tile_load(ti, shape=B, offset=o, storage="shared")
        gs = wp.tile_load_indexed(g, js, shape=(B, W), offset=(0, 0), axis=0, storage="shared")
        gt = wp.tile_load_indexed(g, jt, shape=(B, W), offset=(0, 0), axis=0, storage="shared")
        xs = wp.tile_load(su, shape=(B, 3), offset=(o, 0), storage="shared")
        xt = wp.tile_load(tu, shape=(B, 3), offset=(o, 0), storage="shared")
        wx = wp.tile_load(wxt, shape=(3, W), storage="shared")
        wp.tile_matmul(xs, wx, gs)  # gs += s Wx^T: fuse before its ReLU
        wp.tile_matmul(xt, wx, gt)
        d = wp.tile_astype(wp.tile_map(relu_diff, gs, gt), O)
        w0 = wp.tile_load(w0t, shape=(W, W), storage="shared")
        h0 = wp.tile_zeros(shape=(B, W), dtype=A, storage="shared")
        wp.tile_matmul(d, w0, h0)
        bb0 = wp.tile_load(b0, shape=(1, W), storage="shared")
        h0r = wp.tile_astype(wp.tile_map(relu_add, h0, wp.tile_broadcast(bb0, shape=(B, W))), O)
        w1 = wp.tile_load(w1t, shape=(W, H), storage="shared")
        h1 = wp.tile_zeros(shape=(B, H), dtype=A, storage="shared")
        wp.tile_matmul(h0r, w1, h1)
        bb1 = wp.tile_load(b1, shape=(1, H), storage="shared")
        h1r = wp.tile_astype(wp.tile_map(relu_add, h1, wp.tile_broadcast(bb1, shape=(B, H))), O)
        w2 = wp.tile_load(w2t, shape=(H, 1), storage="shared")
        r = wp.tile_zeros(shape=(B, 1), dtype=A, storage="shared")
        wp.tile_matmul(h1r, w2, r)
        wp.tile_store(ratio, r, offset=(o, 0))

    @wp.kernel(**opts)
    def pair_finish(s: wp.array2d(dtype=T), t: wp.array2d(dtype=T), ratio: wp.array2d(dtype=A),
                    sc: wp.array(dtype=wp.int32), tc: wp.array(dtype=wp.int32), out: wp.array(dtype=wp.float32)):
        """Thread m: max(ratio, 1) |s - t| in user units; 0 for s == t; +inf across components."""
        m = wp.tid()
        if sc.shape[0] > 0:
            if sc[m] != tc[m]:
                out[m] = wp.inf
                return
        ex = A(s[m, 0]) - A(t[m, 0])
        ey = A(s[m, 1]) - A(t[m, 1])
        ez = A(s[m, 2]) - A(t[m, 2])
        e2 = ex * ex + ey * ey + ez * ez
        if e2 == A(0.0):
            out[m] = 0.0
            return
        out[m] = float(wp.max(ratio[m, 0], A(1.0)) * wp.sqrt(e2))

    for k in (pair_prep, pair_head, pair_finish):
        k.module.options["enable_mathdx_gemm"] = bool(mathdx)
    from types import SimpleNamespace

    return SimpleNamespace(pair_prep=pair_prep, pair_head=pair_head, pair_finish=pair_finish, block_pairs=B,
                           operand=O, acc=A, dtype=T, module=name)
