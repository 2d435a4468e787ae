"""The generalizable network's pair head on tensor cores (the ``precision="fp16"`` queries).

What it computes, per pair (s, t) with nearest cloud points i_s, i_t (given, int32, as for the fast float32
kernel ``fast.pair_head``): fuse(q) = relu(G[i_q] + Wx u_q) (u_q: the point in the unit frame, G = W_F F + b
precomputed at conditioning), d = |fuse(s) - fuse(t)| (128), ratio = w2 . relu(W1 relu(W0 d + b0) + b1)
(128 -> 128 -> 64 -> 1), and the distance in user units with the fast kernel's finishing rules: +inf across
components, exactly 0 for s == t, else max(ratio, 1) |s - t|.

How: one warp takes MT tiles of 16 pairs through the head in registers with the per-mesh engine's building
blocks (``kernels/inference/native/neurogf_mma.h``: ``dense``, ``bias_relu``, ``to_a``, ``dot_rows``,
``pack_half2``): fp16 x fp16 -> fp32 ``mma.sync.m16n8k16``. Each lane builds its own A fragments of d in fp32
(G rows, Wx u, ReLU, |difference|) and rounds them to fp16 once; the hidden layers add the folded bias and apply
ReLU in fp32 and round to fp16 for the next layer; the last layer is an fp32 dot product. Layer 0's outputs are
produced NC n-tiles at a time and fed straight into layer 1's accumulators, so only a chunk of them is live.

Column order: inside k-step k the mma's A columns 2t, 2t+1, 2t+8, 2t+9 of lane t (lane = 4g + t) are taken to be
the channels 16k + 4t .. 16k + 4t + 3, so a lane reads its four G values of a row as one 16-byte load; layer 0's
weights are packed with their columns permuted the same way (``W0_COLUMN_ORDER``). Layer 1 reads layer 0's C
fragments in the natural order (the engine's to_a), so it needs no permutation.

The same code runs on Warp's CPU device (each warp as 32 cooperative fibers with the mma emulated, see the
header's top comment): slow, and there to test the GPU code's data movement against float64.
"""
import functools

import numpy as np
import warp as wp

from neurogf_warp.kernels.inference import tensorcore as tc

FUSE = 128  # fuse / head.0 width (the A fragments: 8 k-steps)
HID = 64  # head.1 width (8 n-tiles)
MT = 1  # m-tiles (16 pairs each) per warp and tile step; MT = 2 shares each weight load by two tiles
NC = 8  # layer-0 n-tiles per chunk (16 = the whole layer at once)
WARPS_PER_SM = 12  # persistent warps per multiprocessor on CUDA (MT = 1; 8 for MT >= 2)
# The kernel is compiled for that occupancy (__launch_bounds__(128, WARPS_PER_SM / 4)): without the bound NVRTC
# (Warp 1.19, sm_90) gave the 1 x 8 kernel 143 registers, so only 12 of 16 persistent warps would be resident. For
# 12 warps it keeps 168 registers and no local frame, for 16 it gets 128 and a 64-byte frame: 1M pairs on an H100
# took 0.312 vs 0.385 ms of kernel time (2026-11-24).
CPU_WARPS = 1  # the CPU emulation runs one warp (32 fibers) through every tile

# the mma column position (within a k-step) -> channel offset (within the 16 channels of that k-step)
_POS = np.arange(16)
_T, _HI, _J = (_POS & 7) >> 1, _POS >> 3, _POS & 1  # lane t, upper half (positions 8..15), pair element
KSTEP_CHANNELS = 4 * _T + 2 * _HI + _J
W0_COLUMN_ORDER = (np.arange(FUSE // 16)[:, None] * 16 + KSTEP_CHANNELS[None, :]).reshape(-1)

_GEN_CPP = r"""
namespace ngf_gen {
using namespace ngf;

// four consecutive values of a row (16-byte aligned for float storage) as float32
NGF_FN void load4(const float* p, float (&v)[4])
{
#if defined(__CUDA_ARCH__)
    const float4 q = __ldg(reinterpret_cast<const float4*>(p));
    v[0] = q.x; v[1] = q.y; v[2] = q.z; v[3] = q.w;
#else
    v[0] = p[0]; v[1] = p[1]; v[2] = p[2]; v[3] = p[3];
#endif
}
NGF_FN void load4(const double* p, float (&v)[4])
{
    v[0] = (float)p[0]; v[1] = (float)p[1]; v[2] = (float)p[2]; v[3] = (float)p[3];
}

// Pairs m = tile rows: m -> (a, b) = (m / n_t, m % n_t) for a matrix (n_t > 0), else (m, m). 32-bit: M is a
// Warp int.
NGF_FN void pair_ends(int m, int n_t, int& a, int& b)
{
    a = m; b = m;
    if (n_t > 0) { a = m / n_t; b = m - a * n_t; }
}

// The point in the unit frame, rounded as the fast float32 kernel (float storage) and the generic fp64 kernel
// (double storage) round it.
template <class T>
NGF_FN void unit_point(const T* p, T cx, T cy, T cz, T sc, float (&u)[3])
{
    u[0] = (float)((p[0] - cx) * sc);
    u[1] = (float)((p[1] - cy) * sc);
    u[2] = (float)((p[2] - cz) * sc);
}

// |fuse(s) - fuse(t)| as the A fragments (fp16) of 8 k-steps, rows g (i = 0) and g + 8 (i = 1) of one m-tile.
// wxp: Wx packed per lane group: 12 floats per (k, t): x of channels 16k + 4t .. +3, then y, then z.
template <class T>
NGF_FN void fuse_diff_rows(const T* G, const float* wxp, const T* (&gs)[2], const T* (&gt)[2],
                           const float (&us)[2][3], const float (&ut)[2][3], u32 (&a)[8][4])
{
    const int t = lane_id() & 3;
#pragma unroll
    for (int k = 0; k < 8; ++k)
    {
        float wx[4], wy[4], wz[4];
        load4(wxp + (4 * k + t) * 12 + 0, wx);
        load4(wxp + (4 * k + t) * 12 + 4, wy);
        load4(wxp + (4 * k + t) * 12 + 8, wz);
#pragma unroll
        for (int i = 0; i < 2; ++i)
        {
            float vs[4], vt[4];
            load4(gs[i] + 16 * k + 4 * t, vs);
            load4(gt[i] + 16 * k + 4 * t, vt);
            float d[4];
#pragma unroll
            for (int j = 0; j < 4; ++j)
            {
                const float a_ = vs[j] + wx[j] * us[i][0] + wy[j] * us[i][1] + wz[j] * us[i][2];
                const float b_ = vt[j] + wx[j] * ut[i][0] + wy[j] * ut[i][1] + wz[j] * ut[i][2];
                d[j] = fabsf(relu(a_) - relu(b_));
            }
            a[k][i] = pack_half2(d[0], d[1]);      // columns 2t, 2t + 1    = channels 16k + 4t, +1
            a[k][2 + i] = pack_half2(d[2], d[3]);  // columns 2t + 8, 2t + 9 = channels 16k + 4t + 2, +3
        }
    }
}

// The persistent loop: warp w takes tiles w, w + n_warps, ... of 16 MT pairs.
template <class T, int MT, int NC>
NGF_FN void gen_pair_rows(const Head& H, const T* G, const float* wxp, const T* S, const int* si, const int* sc,
                      const T* Tq, const int* ti, const int* tc, double cx, double cy, double cz, double scale,
                      int n_t, int M, int raw, float* out, int warp, int n_warps)
{
    static_assert(16 % NC == 0 && NC % 2 == 0, "NC: an even divisor of 16");
    const int lane = lane_id();
    const int g = lane >> 2, t = lane & 3;
    const T tcx = (T)cx, tcy = (T)cy, tcz = (T)cz, tsc = (T)scale;
    const int n_tiles = (int)(((long long)M + 16 * MT - 1) / (16 * MT));
    for (int tile = warp; tile < n_tiles; tile += n_warps)
    {
        int rows[MT][2];
        u32 a0[MT][8][4];
#pragma unroll
        for (int m = 0; m < MT; ++m)
        {
            const T* gs[2];
            const T* gt[2];
            float us[2][3], ut[2][3];
#pragma unroll
            for (int i = 0; i < 2; ++i)
            {
                const long long r0 = (long long)tile * 16 * MT + 16 * m + g + 8 * i;
                const int r = r0 < M ? (int)r0 : M;  // M: past the end (the pair is not stored)
                rows[m][i] = r;
                int a, b;
                pair_ends(r < M ? r : M - 1, n_t, a, b);  // a tail tile repeats the last pair (never stored)
                unit_point<T>(S + 3 * a, tcx, tcy, tcz, tsc, us[i]);
                unit_point<T>(Tq + 3 * b, tcx, tcy, tcz, tsc, ut[i]);
                gs[i] = G + (long long)si[a] * 128;
                gt[i] = G + (long long)ti[b] * 128;
            }
            fuse_diff_rows<T>(G, wxp, gs, gt, us, ut, a0[m]);
        }
        // 128 -> 128 (NC n-tiles at a time) -> 64: each chunk of layer 0 enters layer 1 as NC/2 k-steps
        float c1[MT][8][4];
        zero<MT, 8>(c1);
#pragma unroll
        for (int q = 0; q < 16 / NC; ++q)
        {
            float c0[MT][NC][4];
            zero<MT, NC>(c0);
            dense<MT, 8, NC>(a0, H.w0, 16, 0, NC * q, c0);
            bias_relu<MT, NC>(c0, H.b0, NC * q);
            u32 h[MT][NC / 2][4];
            to_a<MT, NC>(c0, h);
            dense<MT, NC / 2, 8>(h, H.w1, 8, NC / 2 * q, 0, c1);
        }
        bias_relu<MT, 8>(c1, H.b1, 0);
        float y[MT][2];
        dot_rows<MT, 8>(c1, H.w2, y);  // every lane of group g: the ratios of rows g, g + 8
#pragma unroll
        for (int m = 0; m < MT; ++m)
#pragma unroll
            for (int i = 0; i < 2; ++i)
            {
                const int r = rows[m][i];
                if (t != i || r >= M)
                    continue;
                const float ratio = y[m][i];
                if (raw) { out[r] = ratio; continue; }
                int a, b;
                pair_ends(r, n_t, a, b);
                if (sc && sc[a] != tc[b]) { out[r] = NGF_INF; continue; }
                const T* s_ = S + 3 * a;
                const T* t_ = Tq + 3 * b;
                const T ex = s_[0] - t_[0], ey = s_[1] - t_[1], ez = s_[2] - t_[2];
                const T e2 = ex * ex + ey * ey + ez * ez;
                out[r] = e2 == (T)0 ? 0.0f : (float)((T)(ratio > 1.0f ? ratio : 1.0f) * wp::sqrt(e2));
            }
    }
}

}  // namespace ngf_gen
"""

BUILD = wp.ModuleBuildOptions(extra_cuda_preamble=tc.HEADER + _GEN_CPP, extra_cpu_preamble=tc.HEADER + _GEN_CPP)
MODULE_OPTIONS = {"extra_build_options": BUILD, "enable_backward": False}


def pack_head(wx: np.ndarray, w0: np.ndarray, b0: np.ndarray, w1: np.ndarray, b1: np.ndarray, w2: np.ndarray,
              device) -> tuple:
    """Folded float64 head weights -> (ngf Head struct, Wx table (FUSE * 3,) float32) for the kernel.

    wx (128, 3): fuse's coordinate columns; w0 (128, 128), b0; w1 (64, 128), b1; w2 (1, 64) or (64,).
    Layer 0 is packed with its input columns in ``W0_COLUMN_ORDER``; Wx as 12 floats per (k-step, lane t):
    x, y, z of channels 16k + 4t .. 16k + 4t + 3."""
    w0 = np.asarray(w0, np.float64)
    H = tc.head_struct([(w0[:, W0_COLUMN_ORDER], b0), (np.asarray(w1, np.float64), b1),
                        (np.asarray(w2, np.float64).reshape(1, -1), None)], device)
    wxp = np.asarray(wx, np.float64).reshape(FUSE // 4, 4, 3).transpose(0, 2, 1)  # (k, t) x xyz x channel
    return H, wp.array(np.ascontiguousarray(wxp, np.float32).reshape(-1), dtype=wp.float32, device=device)


def warps_per_sm(mt: int) -> int:
    """The default occupancy of the kernel with mt m-tiles per warp (persistent warps per multiprocessor)."""
    return WARPS_PER_SM if mt == 1 else 8


@functools.lru_cache(maxsize=None)
def pair_kernel(storage: str = "fp32", mt: int = MT, nc: int = NC, warps: int | None = None):
    """The pair kernel for float32 ("fp32") or float64 ("fp64") storage of G and the points, mt m-tiles per warp,
    layer 0 in chunks of nc n-tiles, compiled for ``warps`` resident warps per multiprocessor (default
    :func:`warps_per_sm`; a multiple of 4). Launch with :func:`launch_pairs` and the same ``warps``."""
    warps = warps or warps_per_sm(mt)
    if storage not in ("fp32", "fp64") or mt not in (1, 2, 3, 4) or nc not in (2, 4, 8, 16) or warps % 4 or \
            not 4 <= warps <= 64:
        raise ValueError(f"pair_kernel: storage {storage!r}, mt {mt}, nc {nc}, warps {warps} not supported")
    T = wp.float32 if storage == "fp32" else wp.float64
    ctype = "float" if storage == "fp32" else "double"
    snippet = tc.native_initializer(tc.Head, "Head", "head", "H") + f"""
    ngf_gen::gen_pair_rows<{ctype}, {mt}, {nc}>(H, ({ctype}*)g.data, (const float*)wxp.data, ({ctype}*)S.data,
        (const int*)si.data, s_comp.shape[0] ? (const int*)s_comp.data : nullptr, ({ctype}*)Tq.data,
        (const int*)ti.data, t_comp.shape[0] ? (const int*)t_comp.data : nullptr, cx, cy, cz, scale, n_t, M, raw,
        (float*)out.data, tid >> 5, n_warps);
"""

    def body(head: tc.Head, g: wp.array2d(dtype=T), wxp: wp.array(dtype=wp.float32), S: wp.array2d(dtype=T),
             si: wp.array(dtype=wp.int32), s_comp: wp.array(dtype=wp.int32), Tq: wp.array2d(dtype=T),
             ti: wp.array(dtype=wp.int32), t_comp: wp.array(dtype=wp.int32), cx: wp.float64, cy: wp.float64,
             cz: wp.float64, scale: wp.float64, n_t: int, M: int, raw: int, out: wp.array(dtype=wp.float32),
             tid: int, n_warps: int): ...

    native = wp.func_native(snippet)(tc._unique(body, f"ngf_gen_pair_rows_{storage}_{mt}_{nc}_{warps}"))

    @wp.kernel(module="unique", module_options=MODULE_OPTIONS,
               launch_bounds=(tc.BLOCK_THREADS, warps * 32 // tc.BLOCK_THREADS))
    def gen_pair_rows(head: tc.Head, g: wp.array2d(dtype=T), wxp: wp.array(dtype=wp.float32),
                      S: wp.array2d(dtype=T), si: wp.array(dtype=wp.int32), s_comp: wp.array(dtype=wp.int32),
                      Tq: wp.array2d(dtype=T), ti: wp.array(dtype=wp.int32), t_comp: wp.array(dtype=wp.int32),
                      cx: wp.float64, cy: wp.float64, cz: wp.float64, scale: wp.float64, n_t: int, M: int, raw: int,
                      out: wp.array(dtype=wp.float32), n_warps: int):
        """Warp w: pair tiles w, w + n_warps, ...; pair m is (S[m // n_t], Tq[m % n_t]) when n_t > 0, else
        (S[m], Tq[m]); si/ti: their nearest cloud points; s_comp/t_comp: component labels (length 0: none). raw != 0:
        out = the ratio; else the distance in user units (module docstring)."""
        native(head, g, wxp, S, si, s_comp, Tq, ti, t_comp, cx, cy, cz, scale, n_t, M, raw, out, wp.tid(), n_warps)

    return gen_pair_rows


def launch_pairs(kernel, head, wxp, G, S, si, s_comp, T, ti, t_comp, center, scale, n_t: int, m: int, raw: bool, out,
                 device, mt: int = MT, warps: int | None = None):
    """Launch ``pair_kernel(storage, mt, nc, warps)`` over m pairs: persistent warps, ``warps`` per multiprocessor
    (default :func:`warps_per_sm`); the CPU emulation: one warp of 32 fibers."""
    n_tiles = (m + 16 * mt - 1) // (16 * mt)
    device = wp.get_device(device)
    tc.launch(kernel, n_tiles, [head, G, wxp, S, si, s_comp, T, ti, t_comp, *(float(c) for c in center), float(scale),
                                int(n_t), int(m), int(raw), out], device, warps or warps_per_sm(mt), CPU_WARPS)
    return out
