"""Fast float32 kernels of the generalizable network (GPU-shaped, and the same code runs on Warp's CPU device).

Why native snippets: the SIMT kernels in ``__init__.py`` keep 128-float vectors per thread, which CUDA puts in
local memory, and re-read the weights from global memory for every pair. Here the hot loops are written as
``wp.func_native`` C++ so that (a) accumulators are fixed-size register arrays indexed only by unrolled
constants, (b) weights and activations are staged once per block in shared memory (a Warp shared tile supplies
the memory, so Warp sets the dynamic shared-memory size), and (c) a block cooperates through explicit barriers.

One body, two devices: every cooperative phase is written as ``for (v = lane; v < V; v += nt)`` over *virtual*
threads, with a barrier between phases. On CUDA ``nt`` is the block size (each thread runs one or a few virtual
threads); on Warp's CPU device blocks have one thread (``nt == 1``), which runs every virtual thread of a phase
in turn. Each virtual thread reads only what the previous phase wrote and writes a disjoint part, so both give
the same numbers. Only the kNN selection uses warp shuffles on CUDA; its CPU branch emulates the 32 lanes with
the same per-lane state and the same (distance, index) order, so the chosen neighbours are identical.

Kernels (float32 storage and accumulation; the ``fp32`` mode):

- ``pair_head``: persistent blocks of 256 threads, P = 96 pairs per tile. |fuse(s) - fuse(t)| is built in
  shared memory from ``G = W_F F + b`` (per cloud point, computed at conditioning) plus ``Wx q`` per query
  point; then 128 -> 128 -> 64 -> 1 as two register-blocked GEMMs (8 x 6 and 4 x 6 outputs per thread) with the
  head's weights (96 KiB) loaded into shared memory once per block.
- ``knn``: one warp per point: 64 candidate distances per lane in registers (features read channel-major, so a
  warp's loads are coalesced), then k rounds of a warp-wide argmin on (distance, index).
- ``edge2``: one block per point: the 40 x 64 edge activations relu(P_i + Q_j) are computed once into shared
  memory, then each of 64 threads applies one row of the second layer to 4 edges at a time and keeps the max.
- ``linear``: a shared-memory tiled y = act(x W^T + b) (32 rows x 64 outputs per block of 256 threads).
- ``to_unit_frame``, ``copy_encoded``: the two ends of the encoder's CUDA graph (``WarpGenNet.encode``): the
  frame read from a device array, and the graph's outputs copied into arrays of the caller's own.
"""
from types import SimpleNamespace

import warp as wp

FUSE = 128  # per-point feature / fuse / head.0 width
HID = 64  # head.1 width
PAIRS = 96  # pairs per tile of pair_head (shared memory: 2 activation buffers of PAIRS x 132 floats)
PAIR_THREADS = 256  # threads per block of pair_head on CUDA (the virtual-thread count of its GEMM phases)
KNN_LANES = 32
KNN_SLOTS = 64  # candidates per lane: the fast kNN handles clouds of up to 32 * 64 = 2,048 points
KNN_MAX_POINTS = KNN_LANES * KNN_SLOTS
KNN_WARPS = 4  # points (warps) per block of knn on CUDA
EDGE_K_MAX = 64  # neighbours per point the edge2 shared buffer holds
LIN_ROWS, LIN_OUTS, LIN_K = 32, 64, 32  # linear: block tile (rows x outputs) and K-chunk

_CACHE: dict = {}

_PRELUDE = r"""
#if defined(__CUDA_ARCH__)
#define NGF_SYNC() __syncthreads()
#else
#define NGF_SYNC()
#endif
#if defined(__CUDA_ARCH__)
struct alignas(16) ngf_f4 { float x, y, z, w; };
#define NGF_LD4(p) (*reinterpret_cast<const ngf_f4*>(p))
#define NGF_ST4(p, v) (*reinterpret_cast<ngf_f4*>(p) = (v))
#else
// the CPU makes no alignment promise for the tile arena: element-wise
struct ngf_f4 { float x, y, z, w; };
#define NGF_LD4(p) (ngf_f4{(p)[0], (p)[1], (p)[2], (p)[3]})
#define NGF_ST4(p, v) do { ngf_f4 v_ = (v); (p)[0] = v_.x; (p)[1] = v_.y; (p)[2] = v_.z; (p)[3] = v_.w; } while (0)
#endif
"""

# ---- pair head ---------------------------------------------------------------------------------------------
# shared layout (floats): W0 (128x128) | W1 (64x128) | b0 128 | b1 64 | w2 64 | Wx (128x3) | A (P x LD) | B (P x LD)
# | unit coords (P x 6). Row stride LD = 132 (16-byte rows, and 132 = 4 mod 32 banks: the 8 lanes of a 128-bit
# load phase, reading 8 consecutive pair rows, hit disjoint banks).
_LD = 132
_PAIR_SMEM = FUSE * FUSE + HID * FUSE + FUSE + HID + HID + 3 * FUSE + 2 * PAIRS * _LD + 6 * PAIRS

_PAIR_SNIPPET = _PRELUDE + r"""
const int P = @P@, LD = @LD@;
float* sW0 = smem.data.ptr;
float* sW1 = sW0 + 128 * 128;
float* sB0 = sW1 + 64 * 128;
float* sB1 = sB0 + 128;
float* sW2 = sB1 + 64;
float* sWX = sW2 + 64;
float* sA = sWX + 384;
float* sB = sA + P * LD;
float* sU = sB + P * LD;
int* sI = ism.data.ptr;
// weights: once per block (the block then loops over pair tiles)
for (int i = lane; i < 128 * 128; i += nt) sW0[i] = w0.data[i];
for (int i = lane; i < 64 * 128; i += nt) sW1[i] = w1.data[i];
for (int i = lane; i < 128; i += nt) sB0[i] = b0.data[i];
for (int i = lane; i < 64; i += nt) { sB1[i] = b1.data[i]; sW2[i] = w2.data[i]; }
for (int i = lane; i < 384; i += nt) sWX[i] = wx.data[i];
NGF_SYNC();
const float fcx = (float)cx, fcy = (float)cy, fcz = (float)cz, fsc = (float)scale;
const long long ntile = (M + P - 1) / P;
for (long long tile = blk; tile < ntile; tile += nblk) {
    const long long base = tile * P;
    // phase 0: unit-frame coordinates and nearest cloud points of the tile's endpoints
    for (int p = lane; p < P; p += nt) {
        const long long m = base + p < M ? base + p : M - 1;  // a tail tile repeats the last pair (never stored)
        long long a = m, b = m;
        if (n_t > 0) { a = m / n_t; b = m - a * n_t; }
        const float* s_ = S.data + 3 * a;
        const float* t_ = T.data + 3 * b;
        sU[6 * p + 0] = (s_[0] - fcx) * fsc; sU[6 * p + 1] = (s_[1] - fcy) * fsc; sU[6 * p + 2] = (s_[2] - fcz) * fsc;
        sU[6 * p + 3] = (t_[0] - fcx) * fsc; sU[6 * p + 4] = (t_[1] - fcy) * fsc; sU[6 * p + 5] = (t_[2] - fcz) * fsc;
        sI[2 * p] = si.data[a];
        sI[2 * p + 1] = ti.data[b];
    }
    NGF_SYNC();
    // phase 1: A[p][c] = |relu(G[i_s][c] + Wx[c] . s) - relu(G[i_t][c] + Wx[c] . t)|; a warp reads whole G rows
    for (int e = lane; e < P * 32; e += nt) {
        const int p = e >> 5, c0 = (e & 31) * 4;
        const ngf_f4 gs = NGF_LD4(g.data + (long long)sI[2 * p] * 128 + c0);
        const ngf_f4 gt = NGF_LD4(g.data + (long long)sI[2 * p + 1] * 128 + c0);
        const float vs[4] = {gs.x, gs.y, gs.z, gs.w};
        const float vt[4] = {gt.x, gt.y, gt.z, gt.w};
        const float* u = sU + 6 * p;
        float r[4];
#pragma unroll
        for (int q = 0; q < 4; ++q) {
            const float* w = sWX + 3 * (c0 + q);
            const float a_ = vs[q] + w[0] * u[0] + w[1] * u[1] + w[2] * u[2];
            const float b_ = vt[q] + w[0] * u[3] + w[1] * u[4] + w[2] * u[5];
            r[q] = wp::abs(wp::max(a_, 0.0f) - wp::max(b_, 0.0f));
        }
        ngf_f4 o; o.x = r[0]; o.y = r[1]; o.z = r[2]; o.w = r[3];
        NGF_ST4(sA + p * LD + c0, o);
    }
    NGF_SYNC();
    // phase 2: B = relu(W0 A + b0); virtual thread v: outputs 8*(v/16) .. +7, pairs v%16 + 16 j (j < 6)
    for (int v = lane; v < 256; v += nt) {
        const int tp = v & 15, to = v >> 4;
        float acc[8][6];
#pragma unroll
        for (int i = 0; i < 8; ++i) {
            const float bb = sB0[8 * to + i];
#pragma unroll
            for (int j = 0; j < 6; ++j) acc[i][j] = bb;
        }
#pragma unroll 2
        for (int k = 0; k < 128; k += 4) {
            ngf_f4 w[8], d[6];
#pragma unroll
            for (int i = 0; i < 8; ++i) w[i] = NGF_LD4(sW0 + (8 * to + i) * 128 + k);
#pragma unroll
            for (int j = 0; j < 6; ++j) d[j] = NGF_LD4(sA + (tp + 16 * j) * LD + k);
#pragma unroll
            for (int i = 0; i < 8; ++i) {
#pragma unroll
                for (int j = 0; j < 6; ++j) {
                    float s0 = acc[i][j];
                    s0 += w[i].x * d[j].x; s0 += w[i].y * d[j].y; s0 += w[i].z * d[j].z; s0 += w[i].w * d[j].w;
                    acc[i][j] = s0;
                }
            }
        }
#pragma unroll
        for (int i = 0; i < 8; ++i) {
#pragma unroll
            for (int j = 0; j < 6; ++j) sB[(tp + 16 * j) * LD + 8 * to + i] = wp::max(acc[i][j], 0.0f);
        }
    }
    NGF_SYNC();
    // phase 3: relu(W1 B + b1) (outputs 4*(v/16) .. +3) and its partial dot with w2 -> A[to][p] (A is free now)
    for (int v = lane; v < 256; v += nt) {
        const int tp = v & 15, to = v >> 4;
        float acc[4][6];
#pragma unroll
        for (int i = 0; i < 4; ++i) {
            const float bb = sB1[4 * to + i];
#pragma unroll
            for (int j = 0; j < 6; ++j) acc[i][j] = bb;
        }
#pragma unroll 2
        for (int k = 0; k < 128; k += 4) {
            ngf_f4 w[4], d[6];
#pragma unroll
            for (int i = 0; i < 4; ++i) w[i] = NGF_LD4(sW1 + (4 * to + i) * 128 + k);
#pragma unroll
            for (int j = 0; j < 6; ++j) d[j] = NGF_LD4(sB + (tp + 16 * j) * LD + k);
#pragma unroll
            for (int i = 0; i < 4; ++i) {
#pragma unroll
                for (int j = 0; j < 6; ++j) {
                    float s0 = acc[i][j];
                    s0 += w[i].x * d[j].x; s0 += w[i].y * d[j].y; s0 += w[i].z * d[j].z; s0 += w[i].w * d[j].w;
                    acc[i][j] = s0;
                }
            }
        }
#pragma unroll
        for (int j = 0; j < 6; ++j) {
            float r = 0.0f;
#pragma unroll
            for (int i = 0; i < 4; ++i) r += sW2[4 * to + i] * wp::max(acc[i][j], 0.0f);
            sA[to * P + tp + 16 * j] = r;
        }
    }
    NGF_SYNC();
    // phase 4: ratio = sum of the 16 partial dots (fixed order); distance or raw ratio out
    for (int p = lane; p < P; p += nt) {
        const long long m = base + p;
        if (m >= M) continue;
        float r = 0.0f;
        for (int q = 0; q < 16; ++q) r += sA[q * P + p];
        if (raw != 0) { out.data[m] = r; continue; }
        long long a = m, b = m;
        if (n_t > 0) { a = m / n_t; b = m - a * n_t; }
        if (sc.shape[0] > 0 && sc.data[a] != tc.data[b]) { out.data[m] = inf_val; continue; }
        const float* s_ = S.data + 3 * a;
        const float* t_ = T.data + 3 * b;
        const float ex = s_[0] - t_[0], ey = s_[1] - t_[1], ez = s_[2] - t_[2];
        const float e2 = ex * ex + ey * ey + ez * ez;
        out.data[m] = e2 == 0.0f ? 0.0f : wp::max(r, 1.0f) * wp::sqrt(e2);
    }
    NGF_SYNC();
}
""".replace("@P@", str(PAIRS)).replace("@LD@", str(_LD))

# ---- kNN in feature space ------------------------------------------------------------------------------------
_KNN_SNIPPET = _PRELUDE + r"""
const int N = ft.shape[1];
const float* F = ft.data;
const float INFV = inf_val;
#if defined(__CUDA_ARCH__)
if (row >= N) return;  // warp-uniform: a warp owns one row
float d[@SLOTS@];
#pragma unroll
for (int t = 0; t < @SLOTS@; ++t) d[t] = 0.0f;
for (int c = c_off; c < c_off + nc; ++c) {
    const float* Fc = F + (long long)c * N;
    const float qc = Fc[row];
#pragma unroll
    for (int t = 0; t < @SLOTS@; ++t) {
        const int j = lane + 32 * t;
        const float e = qc - (j < N ? Fc[j] : 0.0f);
        d[t] += e * e;
    }
}
#pragma unroll
for (int t = 0; t < @SLOTS@; ++t) if (lane + 32 * t >= N) d[t] = INFV;
float bv = INFV; int bt = 0;
#pragma unroll
for (int t = 0; t < @SLOTS@; ++t) if (d[t] < bv) { bv = d[t]; bt = t; }  // strict: smaller slot = smaller index
for (int r = 0; r < kk; ++r) {
    float v = bv; int j = lane + 32 * bt;
#pragma unroll
    for (int off = 16; off > 0; off >>= 1) {
        const float v2 = __shfl_xor_sync(0xffffffffu, v, off);
        const int j2 = __shfl_xor_sync(0xffffffffu, j, off);
        if (v2 < v || (v2 == v && j2 < j)) { v = v2; j = j2; }
    }
    if (lane == 0) nbr.data[(long long)row * kk + r] = j;
    if ((j & 31) == lane) {  // the winner's lane drops that candidate and finds its next best
        const int tw = j >> 5;
        bv = INFV; bt = 0;
#pragma unroll
        for (int t = 0; t < @SLOTS@; ++t) {
            if (t == tw) d[t] = INFV;
            if (d[t] < bv) { bv = d[t]; bt = t; }
        }
    }
}
#else
// the CPU emulates the 32 lanes: the same per-lane distances, per-lane best and (distance, index) argmin
if (row >= N) return;
float d[32][@SLOTS@];
float bv[32]; int bt[32];
for (int l = 0; l < 32; ++l) for (int t = 0; t < @SLOTS@; ++t) d[l][t] = 0.0f;
for (int c = c_off; c < c_off + nc; ++c) {
    const float* Fc = F + (long long)c * N;
    const float qc = Fc[row];
    for (int l = 0; l < 32; ++l) for (int t = 0; t < @SLOTS@; ++t) {
        const int j = l + 32 * t;
        const float e = qc - (j < N ? Fc[j] : 0.0f);
        d[l][t] += e * e;
    }
}
for (int l = 0; l < 32; ++l) {
    bv[l] = INFV; bt[l] = 0;
    for (int t = 0; t < @SLOTS@; ++t) {
        if (l + 32 * t >= N) d[l][t] = INFV;
        if (d[l][t] < bv[l]) { bv[l] = d[l][t]; bt[l] = t; }
    }
}
for (int r = 0; r < kk; ++r) {
    float v = bv[0]; int j = 32 * bt[0];
    for (int l = 1; l < 32; ++l) {
        const float v2 = bv[l]; const int j2 = l + 32 * bt[l];
        if (v2 < v || (v2 == v && j2 < j)) { v = v2; j = j2; }
    }
    nbr.data[(long long)row * kk + r] = j;
    const int l = j & 31, tw = j >> 5;
    d[l][tw] = INFV; bv[l] = INFV; bt[l] = 0;
    for (int t = 0; t < @SLOTS@; ++t) if (d[l][t] < bv[l]) { bv[l] = d[l][t]; bt[l] = t; }
}
#endif
""".replace("@SLOTS@", str(KNN_SLOTS))

# ---- EdgeConv block with two layers --------------------------------------------------------------------------
# pq (N, 128): P = pq[:, :64] = (Wa - Wb) f + b and Q = pq[:, 64:] = Wb f of the block's first layer.
_EDGE_SMEM = EDGE_K_MAX * 64 + 64 * 68
_EDGE_SNIPPET = _PRELUDE + r"""
float* sE = smem.data.ptr;          // kk x 64: relu(P_i + Q_j), computed once per edge
float* sW = sE + @KMAX@ * 64;       // 64 x 68: the second layer, rows padded for conflict-free 128-bit loads
const int N = pq.shape[0];
const int kk = nbr.shape[1];
for (int e = lane; e < 64 * 64; e += nt) sW[(e >> 6) * 68 + (e & 63)] = w.data[e];
for (int e = lane; e < kk * 64; e += nt) {
    const int j = e >> 6, h = e & 63;
    const int nb = nbr.data[(long long)i * kk + j];
    sE[e] = wp::max(pq.data[(long long)i * 128 + h] + pq.data[(long long)nb * 128 + 64 + h], 0.0f);
}
NGF_SYNC();
const int ystride = y.shape[1];
for (int o = lane; o < 64; o += nt) {
    const float bo = b.data[o];
    float best = 0.0f;  // every candidate is a ReLU output (>= 0)
    int j0 = 0;
    for (; j0 + 4 <= kk; j0 += 4) {
        float a0 = bo, a1 = bo, a2 = bo, a3 = bo;
#pragma unroll 4
        for (int h = 0; h < 64; h += 4) {
            const ngf_f4 wv = NGF_LD4(sW + o * 68 + h);
            const ngf_f4 e0 = NGF_LD4(sE + (j0 + 0) * 64 + h);
            const ngf_f4 e1 = NGF_LD4(sE + (j0 + 1) * 64 + h);
            const ngf_f4 e2 = NGF_LD4(sE + (j0 + 2) * 64 + h);
            const ngf_f4 e3 = NGF_LD4(sE + (j0 + 3) * 64 + h);
            a0 += wv.x * e0.x; a0 += wv.y * e0.y; a0 += wv.z * e0.z; a0 += wv.w * e0.w;
            a1 += wv.x * e1.x; a1 += wv.y * e1.y; a1 += wv.z * e1.z; a1 += wv.w * e1.w;
            a2 += wv.x * e2.x; a2 += wv.y * e2.y; a2 += wv.z * e2.z; a2 += wv.w * e2.w;
            a3 += wv.x * e3.x; a3 += wv.y * e3.y; a3 += wv.z * e3.z; a3 += wv.w * e3.w;
        }
        best = wp::max(best, wp::max(wp::max(a0, a1), wp::max(a2, a3)));
    }
    for (; j0 < kk; ++j0) {
        float a0 = bo;
        for (int h = 0; h < 64; ++h) a0 += sW[o * 68 + h] * sE[j0 * 64 + h];
        best = wp::max(best, a0);
    }
    y.data[(long long)i * ystride + y_off + o] = best;
    yt.data[(long long)(y_off + o) * N + i] = best;  // channel-major copy: the next kNN reads it coalesced
}
""".replace("@KMAX@", str(EDGE_K_MAX))

# ---- tiled linear --------------------------------------------------------------------------------------------
# y[r, y_off + o] = act(b[o] + sum_c W[o, c] x[r, x_off + c]); block: 32 rows x 64 outputs, 256 virtual threads
# of 2 rows x 4 outputs; K staged in chunks of 32 (x tile 32 x 33, W tile 64 x 33: odd strides, no bank conflicts).
_LIN_SMEM = LIN_ROWS * (LIN_K + 1) + LIN_OUTS * (LIN_K + 1)
_LIN_SNIPPET = _PRELUDE + r"""
const int R = @R@, O = @O@, KC = @KC@, LS = @KC@ + 1;
float* sX = smem.data.ptr;
float* sWt = sX + R * LS;
const int nrow = x.shape[0], xs = x.shape[1], ys = y.shape[1];
const int nout = w.shape[0], nin = w.shape[1];
const int r0 = rb * R, o0 = ob * O;
// accumulators: 2 rows x 4 outputs per virtual thread. CUDA (block_dim 256): one virtual thread per thread, so
// one register set; a CPU block (nt == 1) runs all 256 virtual threads and needs all their accumulators at once.
#if defined(__CUDA_ARCH__)
const int VPT = 1;
#else
const int VPT = 256;
#endif
float accs[VPT][8];
for (int q = 0; q < VPT; ++q) for (int z = 0; z < 8; ++z) accs[q][z] = 0.0f;
for (int k0 = 0; k0 < nin; k0 += KC) {
    for (int e = lane; e < R * KC; e += nt) {
        const int r = e / KC, c = e % KC;
        sX[r * LS + c] = (r0 + r < nrow && k0 + c < nin) ? x.data[(long long)(r0 + r) * xs + x_off + k0 + c] : 0.0f;
    }
    for (int e = lane; e < O * KC; e += nt) {
        const int o = e / KC, c = e % KC;
        sWt[o * LS + c] = (o0 + o < nout && k0 + c < nin) ? w.data[(long long)(o0 + o) * nin + k0 + c] : 0.0f;
    }
    NGF_SYNC();
    int q = 0;
    for (int v = lane; v < 256; v += nt, ++q) {
        const int tr = v >> 4, tc = v & 15;  // rows 2 tr, 2 tr + 1; outputs tc + 16 i
        float* a = accs[VPT == 1 ? 0 : q];
        const int kn = nin - k0 < KC ? nin - k0 : KC;
        for (int c = 0; c < kn; ++c) {
            const float x0 = sX[(2 * tr) * LS + c], x1 = sX[(2 * tr + 1) * LS + c];
#pragma unroll
            for (int i2 = 0; i2 < 4; ++i2) {
                const float wv = sWt[(tc + 16 * i2) * LS + c];
                a[i2] += wv * x0;
                a[4 + i2] += wv * x1;
            }
        }
    }
    NGF_SYNC();
}
int q = 0;
for (int v = lane; v < 256; v += nt, ++q) {
    const int tr = v >> 4, tc = v & 15;
    for (int rr = 0; rr < 2; ++rr) {
        const int r = r0 + 2 * tr + rr;
        if (r >= nrow) continue;
        for (int i2 = 0; i2 < 4; ++i2) {
            const int o = o0 + tc + 16 * i2;
            if (o >= nout) continue;
            float s0 = b.data[o] + accs[VPT == 1 ? 0 : q][4 * rr + i2];
            if (relu != 0) s0 = wp::max(s0, 0.0f);
            y.data[(long long)r * ys + y_off + o] = s0;
        }
    }
}
""".replace("@R@", str(LIN_ROWS)).replace("@O@", str(LIN_OUTS)).replace("@KC@", str(LIN_K))


def kernels() -> SimpleNamespace:
    """The float32 fast kernels (one Warp module), built once."""
    if "k" not in _CACHE:
        _CACHE["k"] = _build()
    return _CACHE["k"]


def _build() -> SimpleNamespace:
    # one Warp module per CUDA block size: Warp compiles a module for the block_dim it is launched with, so
    # kernels of different block sizes in one module would compile it several times
    module = "neurogf_generalizable_fast"
    opts = dict(enable_backward=False, module=module + "_256")  # pair_head, linear, plain SIMT kernels
    opts128 = dict(enable_backward=False, module=module + "_128")  # knn: 4 warps
    opts64 = dict(enable_backward=False, module=module + "_64")  # edge2: a thread per output channel
    f32 = wp.float32
    SHAPE_PAIR = (_PAIR_SMEM,)
    SHAPE_EDGE = (_EDGE_SMEM,)
    SHAPE_LIN = (_LIN_SMEM,)
    NPAIR, NEDGE, NLIN, NPI = _PAIR_SMEM, _EDGE_SMEM, _LIN_SMEM, 2 * PAIRS  # ints: kernels may only close over scalars
    # the shared tiles are tile_empty (not tile_zeros): every element a snippet reads it has written first, and
    # zeroing 33 KiB per point-block of edge2 would cost about a fifth of its time

    @wp.func_native(_PAIR_SNIPPET)
    def pair_body(smem: wp.tile(dtype=f32, shape=SHAPE_PAIR, storage="shared"),
                  ism: wp.tile(dtype=wp.int32, shape=(2 * PAIRS,), storage="shared"),
                  g: wp.array2d(dtype=f32), wx: wp.array2d(dtype=f32), w0: wp.array2d(dtype=f32),
                  b0: wp.array(dtype=f32), w1: wp.array2d(dtype=f32), b1: wp.array(dtype=f32),
                  w2: wp.array2d(dtype=f32), S: wp.array2d(dtype=f32), si: wp.array(dtype=wp.int32),
                  sc: wp.array(dtype=wp.int32), T: wp.array2d(dtype=f32), ti: wp.array(dtype=wp.int32),
                  tc: wp.array(dtype=wp.int32), cx: wp.float64, cy: wp.float64, cz: wp.float64,
                  scale: wp.float64, n_t: int, M: int, raw: int, inf_val: float, out: wp.array(dtype=f32),
                  lane: int, nt: int, blk: int, nblk: int): ...

    @wp.kernel(**opts)
    def pair_head(g: wp.array2d(dtype=f32), wx: wp.array2d(dtype=f32), w0: wp.array2d(dtype=f32),
                  b0: wp.array(dtype=f32), w1: wp.array2d(dtype=f32), b1: wp.array(dtype=f32),
                  w2: wp.array2d(dtype=f32), S: wp.array2d(dtype=f32), si: wp.array(dtype=wp.int32),
                  sc: wp.array(dtype=wp.int32), T: wp.array2d(dtype=f32), ti: wp.array(dtype=wp.int32),
                  tc: wp.array(dtype=wp.int32), cx: wp.float64, cy: wp.float64, cz: wp.float64,
                  scale: wp.float64, n_t: int, M: int, raw: int, nblk: int, out: wp.array(dtype=f32)):
        """Block blk (persistent): pair tiles blk, blk + nblk, ... Pair m is (S[m // n_t], T[m % n_t]) when
        n_t > 0, else (S[m], T[m]); si/ti: their nearest cloud points (always given); sc/tc: component labels
        (length 0: none). raw != 0: out = the raw ratio (S, T in the unit frame); else the distance in user
        units: max(ratio, 1) |s - t|, 0 for s == t, inf across components."""
        blk, lane = wp.tid()
        smem = wp.tile_empty(shape=NPAIR, dtype=f32, storage="shared")
        ism = wp.tile_empty(shape=NPI, dtype=wp.int32, storage="shared")
        pair_body(smem, ism, g, wx, w0, b0, w1, b1, w2, S, si, sc, T, ti, tc, cx, cy, cz, scale, n_t, M, raw,
                  wp.inf, out, lane, wp.block_dim(), blk, nblk)

    @wp.func_native(_KNN_SNIPPET)
    def knn_body(ft: wp.array2d(dtype=f32), c_off: int, nc: int, kk: int, inf_val: float,
                 nbr: wp.array2d(dtype=wp.int32), row: int, lane: int): ...

    @wp.kernel(**opts128)
    def knn(ft: wp.array2d(dtype=f32), c_off: int, nc: int, kk: int, nbr: wp.array2d(dtype=wp.int32)):
        """The kk nearest points of each point (closest first, self included, ties -> smaller index) in the
        feature space of rows [c_off, c_off + nc) of the channel-major ft (C, N), N <= 2,048. CUDA: launch
        (ceil(N / 4), 128) with block_dim 128 (a warp per point); CPU: (N, 1) with block_dim 1."""
        blk, t = wp.tid()
        nw = wp.block_dim() / 32
        row = blk
        lane = int(0)
        if nw > 0:
            row = blk * nw + t / 32
            lane = t % 32
        knn_body(ft, c_off, nc, kk, wp.inf, nbr, row, lane)

    @wp.func_native(_EDGE_SNIPPET)
    def edge_body(smem: wp.tile(dtype=f32, shape=SHAPE_EDGE, storage="shared"), pq: wp.array2d(dtype=f32),
                  nbr: wp.array2d(dtype=wp.int32), w: wp.array2d(dtype=f32), b: wp.array(dtype=f32),
                  y: wp.array2d(dtype=f32), yt: wp.array2d(dtype=f32), y_off: int, i: int, lane: int,
                  nt: int): ...

    @wp.kernel(**opts64)
    def edge2(pq: wp.array2d(dtype=f32), nbr: wp.array2d(dtype=wp.int32), w: wp.array2d(dtype=f32),
              b: wp.array(dtype=f32), y: wp.array2d(dtype=f32), yt: wp.array2d(dtype=f32), y_off: int):
        """Block i: y[i, y_off + o] = yt[y_off + o, i] = max over neighbours j of
        relu(b[o] + sum_h w[o, h] relu(P[i, h] + Q[j, h])). CUDA: launch (N, 64), block_dim 64."""
        i, lane = wp.tid()
        smem = wp.tile_empty(shape=NEDGE, dtype=f32, storage="shared")
        edge_body(smem, pq, nbr, w, b, y, yt, y_off, i, lane, wp.block_dim())

    @wp.kernel(**opts)
    def edge1(pq: wp.array2d(dtype=f32), nbr: wp.array2d(dtype=wp.int32), y: wp.array2d(dtype=f32),
              y_off: int):
        """Thread (i, o): a one-layer block: relu(P[i, o] + max_j Q[j, o]) (= max_j relu(P + Q), monotonic)."""
        i, o = wp.tid()
        m = pq[nbr[i, 0], 64 + o]
        for kq in range(1, nbr.shape[1]):
            m = wp.max(m, pq[nbr[i, kq], 64 + o])
        y[i, y_off + o] = wp.max(pq[i, o] + m, 0.0)

    @wp.func_native(_LIN_SNIPPET)
    def linear_body(smem: wp.tile(dtype=f32, shape=SHAPE_LIN, storage="shared"), x: wp.array2d(dtype=f32),
                    x_off: int, w: wp.array2d(dtype=f32), b: wp.array(dtype=f32), relu: int,
                    y: wp.array2d(dtype=f32), y_off: int, rb: int, ob: int, lane: int, nt: int): ...

    @wp.kernel(**opts)
    def linear(x: wp.array2d(dtype=f32), x_off: int, w: wp.array2d(dtype=f32), b: wp.array(dtype=f32),
               relu: int, y: wp.array2d(dtype=f32), y_off: int, nob: int):
        """Block (rb * nob + ob): rows [32 rb, 32 rb + 32) x outputs [64 ob, 64 ob + 64) of
        y[:, y_off + o] = act(b[o] + sum_c w[o, c] x[:, x_off + c]). CUDA: block_dim 256."""
        blk, lane = wp.tid()
        smem = wp.tile_empty(shape=NLIN, dtype=f32, storage="shared")
        linear_body(smem, x, x_off, w, b, relu, y, y_off, blk / nob, blk % nob, lane, wp.block_dim())

    @wp.func
    def unit_row(x: wp.array2d(dtype=f32), i: int, cx: wp.float64, cy: wp.float64, cz: wp.float64,
                 scale: wp.float64, y: wp.array2d(dtype=f32), yt: wp.array2d(dtype=f32), v: wp.array(dtype=wp.vec3)):
        """y[i] = (x[i] - c) * scale (as the generic kernel rounds it), its channel-major copy yt and a vec3 copy
        for the hash grid."""
        a = float((wp.float64(x[i, 0]) - cx) * scale)
        b = float((wp.float64(x[i, 1]) - cy) * scale)
        c = float((wp.float64(x[i, 2]) - cz) * scale)
        y[i, 0] = a
        y[i, 1] = b
        y[i, 2] = c
        yt[0, i] = a
        yt[1, i] = b
        yt[2, i] = c
        v[i] = wp.vec3(a, b, c)

    @wp.kernel(**opts)
    def to_unit(x: wp.array2d(dtype=f32), cx: wp.float64, cy: wp.float64, cz: wp.float64, scale: wp.float64,
                y: wp.array2d(dtype=f32), yt: wp.array2d(dtype=f32), v: wp.array(dtype=wp.vec3)):
        """Thread i: ``unit_row`` with the frame as launch constants."""
        unit_row(x, wp.tid(), cx, cy, cz, scale, y, yt, v)

    # the captured encoder's ends (WarpGenNet.encode on CUDA replays a CUDA graph), in a small module of their own
    opts_io = {"enable_backward": False, "module": module + "_io"}

    @wp.kernel(**opts_io)
    def to_unit_frame(x: wp.array2d(dtype=f32), frame: wp.array(dtype=wp.float64), y: wp.array2d(dtype=f32),
                      yt: wp.array2d(dtype=f32), v: wp.array(dtype=wp.vec3)):
        """to_unit with (cx, cy, cz, scale) read from the device array ``frame`` (not launch constants, which a
        CUDA graph would keep): the same arithmetic, so the same bits."""
        unit_row(x, wp.tid(), frame[0], frame[1], frame[2], frame[3], y, yt, v)

    @wp.kernel(**opts_io)
    def copy_encoded(x: wp.array2d(dtype=f32), v: wp.array(dtype=wp.vec3), f: wp.array2d(dtype=f32),
                     g: wp.array2d(dtype=f32), n1: wp.array2d(dtype=wp.int32), n2: wp.array2d(dtype=wp.int32),
                     n3: wp.array2d(dtype=wp.int32), x2: wp.array2d(dtype=f32), v2: wp.array(dtype=wp.vec3),
                     f2: wp.array2d(dtype=f32), g2: wp.array2d(dtype=f32), m1: wp.array2d(dtype=wp.int32),
                     m2: wp.array2d(dtype=wp.int32), m3: wp.array2d(dtype=wp.int32)):
        """Thread (i, c), c < 128: row i of an encoding (cloud, its vec3 copy, F, G, the three kNN lists of at
        most 128 neighbours) into fresh arrays: one launch instead of seven copies."""
        i, c = wp.tid()
        f2[i, c] = f[i, c]
        g2[i, c] = g[i, c]
        if c < n1.shape[1]:
            m1[i, c] = n1[i, c]
            m2[i, c] = n2[i, c]
            m3[i, c] = n3[i, c]
        if c < 3:
            x2[i, c] = x[i, c]
        if c == 0:
            v2[i] = v[i]

    return SimpleNamespace(modules=[module + '_256', module + '_128', module + '_64', module + '_io'],
                           pair_head=pair_head, knn=knn, edge2=edge2, edge1=edge1, linear=linear, to_unit=to_unit,
                           to_unit_frame=to_unit_frame, copy_encoded=copy_encoded, pair_tile=PAIRS,
                           pair_threads=PAIR_THREADS)
