"""The distance head alone in float32 (precision="fp32"): head(|e_s - e_x|) for sources s and rows x.

With the rows' embeddings kept on the device (a bound model) the head runs as tile GEMMs on (features, rows)
tiles, a third of the network's work; otherwise one thread per (source, row) embeds its row with the
per-thread functions of ``mlp``. Both return raw head values in the network frame: ``kernels.finish`` adds the
|x - s| term, the units and the rules every distance follows.
"""
import functools

import warp as wp

from . import mlp

BLOCK = 64  # vertices per tile (columns)
CHUNK = 32  # embedding channels per step of the first layer
THREADS = 128  # block_dim on CUDA (B=32..128 with 64..256 threads measured within 10% of each other)


@wp.func
def _relu(x: float):
    return wp.max(x, 0.0)


MAX_D = 256  # D = 512 would need a chunked second layer too (its H = 128)


@functools.lru_cache(maxsize=None)
def head_kernel(D: int, H: int, block: int = BLOCK, chunk: int = CHUNK):
    """Kernel for embedding width D and head width H: out[0, x] = W2 relu(W1 relu(W0 |e_s - e_x| + b0) + b1).

    The first layer runs over D in chunks (a rolled loop: its trip count is an argument), so neither W0 nor
    the (D, block) input tile is ever whole in shared memory, which keeps several blocks resident per SM.
    Warp's scalar tile GEMM, not cuBLASDx: it compiles in seconds instead of about a minute.
    """
    B, K = block, chunk

    @wp.kernel(enable_backward=False, module="unique", module_options={"enable_mathdx_gemm": False})
    def head(es: wp.array2d(dtype=wp.float32), ex: wp.array2d(dtype=wp.float32),
             w0: wp.array2d(dtype=wp.float32), b0: wp.array2d(dtype=wp.float32),
             w1: wp.array2d(dtype=wp.float32), b1: wp.array2d(dtype=wp.float32),
             w2: wp.array2d(dtype=wp.float32), n_chunks: int, out: wp.array2d(dtype=wp.float32)):
        blk = wp.tid()
        h = wp.tile_zeros(shape=(H, B), dtype=wp.float32)
        for c in range(n_chunks):
            e = wp.tile_transpose(wp.tile_load(ex, shape=(B, K), offset=(blk * B, c * K)))  # (K, B)
            s = wp.tile_broadcast(wp.tile_transpose(wp.tile_load(es, shape=(1, K), offset=(0, c * K))), shape=(K, B))
            wp.tile_matmul(wp.tile_load(w0, shape=(H, K), offset=(0, c * K)), wp.tile_map(wp.abs, e - s), h)
        h = wp.tile_map(_relu, h + wp.tile_broadcast(wp.tile_load(b0, shape=(H, 1)), shape=(H, B)))
        h1 = wp.tile_matmul(wp.tile_load(w1, shape=(H, H)), h)
        h1 = wp.tile_map(_relu, h1 + wp.tile_broadcast(wp.tile_load(b1, shape=(H, 1)), shape=(H, B)))
        y = wp.tile_matmul(wp.tile_load(w2, shape=(1, H)), h1)  # (1, B)
        wp.tile_store(out, y, offset=(0, blk * B))

    return head


@wp.kernel(enable_backward=False)
def head_rows(net: mlp.NeuroGFWeights, es: wp.array2d(dtype=wp.float32), src: wp.array(dtype=wp.vec3),
              xs: wp.array(dtype=wp.vec3), frame: mlp.Frame, out: wp.array2d(dtype=wp.float32)):
    """out[s, i] = head(|e(src[s]) - e(xs[i])|), one thread per pair; ``net`` must have euclid = 0 (the |x - s|
    term is added by kernels.finish)."""
    s, i = wp.tid()
    out[s, i] = mlp.distance_to_embedding(net, es, s, mlp.to_net(frame, src[s]), mlp.to_net(frame, xs[i]))
