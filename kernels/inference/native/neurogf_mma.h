// neurogf_mma.h: the NeuroGF networks on tensor cores, one warp per tile of 16 rows.
//
// Every layer is an fp16 x fp16 -> fp32 matrix product (mma.sync.m16n8k16) with the BatchNorm-folded bias and
// ReLU applied in fp32 before the result is rounded to fp16 for the next layer. A warp keeps its rows'
// activations in registers from the point coordinates to the distance: nothing between layers touches memory.
// Weights are stored by the host in "fragment order" (kernels/tensorcore.py packs them): the 32 lanes of a warp
// read one layer step as one contiguous 256-byte block, which stays in L1.
//
// The same code runs on Warp's CPU device: there a warp is 32 cooperative fibers (wp.config.enable_cpu_blocks)
// and the three warp-wide operations below (mma, shuffle, the barrier) are emulated through a shared scratch
// block. The CPU form exists to check this file's data movement against float64 in the tests; it is slow.
//
// Fragment layout of mma.m16n8k16 (lane = 4 g + t):
//   A (16 x 16, row major): a0 = A[g][2t..2t+1], a1 = A[g+8][2t..2t+1], a2 = A[g][2t+8..9], a3 = A[g+8][2t+8..9]
//   B (16 x 8):             b0 = B[2t..2t+1][g],  b1 = B[2t+8..9][g]
//   C (16 x 8):             c0,c1 = C[g][2t..2t+1], c2,c3 = C[g+8][2t..2t+1]
// so the C fragments of n-tiles 2j and 2j+1 are exactly the A fragment of k-step j of the next layer.

namespace ngf {

typedef unsigned int u32;
struct alignas(8) u32x2 { u32 x, y; };
struct alignas(16) u32x4 { u32 x, y, z, w; };
struct alignas(8) f32x2 { float x, y; };

#if defined(__CUDA_ARCH__)

#define NGF_FN __device__ __forceinline__

NGF_FN int lane_id() { return threadIdx.x & 31; }

NGF_FN void mma(float (&c)[4], const u32 (&a)[4], const u32x2 b)
{
    asm("mma.sync.aligned.m16n8k16.row.col.f32.f16.f16.f32 {%0,%1,%2,%3}, {%4,%5,%6,%7}, {%8,%9}, {%0,%1,%2,%3};\n"
        : "+f"(c[0]), "+f"(c[1]), "+f"(c[2]), "+f"(c[3])
        : "r"(a[0]), "r"(a[1]), "r"(a[2]), "r"(a[3]), "r"(b.x), "r"(b.y));
}

NGF_FN float shfl_xor(float v, int mask) { return __shfl_xor_sync(0xffffffffu, v, mask); }

// weights and small tables (source embeddings, biases): read-only path, kept in L1
NGF_FN u32x2 ld_weights(const u32x2* p)
{
    u32x2 r;
    asm("ld.global.nc.v2.u32 {%0,%1}, [%2];" : "=r"(r.x), "=r"(r.y) : "l"(p));
    return r;
}
NGF_FN f32x2 ld_table(const f32x2* p)
{
    f32x2 r;
    asm("ld.global.nc.v2.f32 {%0,%1}, [%2];" : "=f"(r.x), "=f"(r.y) : "l"(p));
    return r;
}
NGF_FN u32x4 ld_table4(const u32x4* p)
{
    u32x4 r;
    asm("ld.global.nc.v4.u32 {%0,%1,%2,%3}, [%4];" : "=r"(r.x), "=r"(r.y), "=r"(r.z), "=r"(r.w) : "l"(p));
    return r;
}
// streamed rows (vertex embeddings): read once, so they bypass L1 and leave it to the weights
NGF_FN u32x4 ld_stream(const u32x4* p)
{
    u32x4 r;
    asm volatile("ld.global.nc.L1::no_allocate.v4.u32 {%0,%1,%2,%3}, [%4];"
                 : "=r"(r.x), "=r"(r.y), "=r"(r.z), "=r"(r.w) : "l"(p));
    return r;
}

NGF_FN u32 pack_half2(float lo, float hi)
{
    u32 r;
    asm("cvt.rn.f16x2.f32 %0, %1, %2;" : "=r"(r) : "f"(hi), "f"(lo));
    return r;
}
NGF_FN u32 habs_diff2(u32 a, u32 b)  // |a - b| per fp16 lane
{
    u32 d;
    asm("sub.rn.f16x2 %0, %1, %2;" : "=r"(d) : "r"(a), "r"(b));
    return d & 0x7fff7fffu;
}
NGF_FN float half_bits_to_float(u32 h)
{
    float f;
    asm("{ .reg .b16 t; cvt.u16.u32 t, %1; cvt.f32.f16 %0, t; }" : "=f"(f) : "r"(h));
    return f;
}
NGF_FN void sincos_pi(float x, float* s, float* c) { sincospif(x, s, c); }
NGF_FN float sinpi_(float x) { return sinpif(x); }

#else  // Warp's CPU device: a warp is 32 fibers of one cooperative block

#define NGF_FN inline

extern "C" int wp_cpu_get_thread_idx();
extern "C" void wp_cpu_tile_sync();

inline int lane_id() { return wp_cpu_get_thread_idx() & 31; }

struct WarpScratch
{
    u32 a[32][4];
    u32 b[32][2];
    float c[32][4];
    float f[32];
};
// CPU blocks run one at a time and each holds one warp, so one scratch block serves every warp.
inline WarpScratch& scratch()
{
    static WarpScratch s;
    return s;
}

inline float half_bits_to_float(u32 h) { wp::half x; x.u = (unsigned short)h; return wp::half_to_float(x); }
inline u32 float_to_half_bits(float f) { return wp::float_to_half(f).u; }

inline void mma(float (&c)[4], const u32 (&a)[4], const u32x2 b)
{
    WarpScratch& s = scratch();
    const int lane = lane_id();
    for (int i = 0; i < 4; ++i) s.a[lane][i] = a[i];
    s.b[lane][0] = b.x;
    s.b[lane][1] = b.y;
    wp_cpu_tile_sync();
    const int g = lane >> 2, t = lane & 3;
    for (int i = 0; i < 4; ++i)
    {
        const int row = g + 8 * (i >> 1), col = 2 * t + (i & 1);
        float acc = c[i];
        for (int k = 0; k < 16; ++k)
        {
            // A[row][k]: held by lane 4 row' + k'/2 in register (row >= 8) + 2 (k >= 8), half k % 2
            const int kk = k & 7;
            const u32 aw = s.a[4 * (row & 7) + kk / 2][(row >> 3) + 2 * (k >> 3)];
            const u32 bw = s.b[4 * col + kk / 2][k >> 3];
            const float av = half_bits_to_float((aw >> (16 * (kk & 1))) & 0xffffu);
            const float bv = half_bits_to_float((bw >> (16 * (kk & 1))) & 0xffffu);
            acc += av * bv;
        }
        c[i] = acc;
    }
    wp_cpu_tile_sync();
}

inline float shfl_xor(float v, int mask)
{
    WarpScratch& s = scratch();
    const int lane = lane_id();
    s.f[lane] = v;
    wp_cpu_tile_sync();
    const float r = s.f[lane ^ mask];
    wp_cpu_tile_sync();
    return r;
}

inline u32x2 ld_weights(const u32x2* p) { return *p; }
inline f32x2 ld_table(const f32x2* p) { return *p; }
inline u32x4 ld_table4(const u32x4* p) { return *p; }
inline u32x4 ld_stream(const u32x4* p) { return *p; }

inline u32 pack_half2(float lo, float hi) { return float_to_half_bits(lo) | (float_to_half_bits(hi) << 16); }
inline u32 habs_diff2(u32 a, u32 b)
{
    // the exact difference of two fp16 numbers is a float; rounding it to fp16 is what sub.rn.f16x2 does
    const float lo = half_bits_to_float(a & 0xffffu) - half_bits_to_float(b & 0xffffu);
    const float hi = half_bits_to_float(a >> 16) - half_bits_to_float(b >> 16);
    return pack_half2(lo, hi) & 0x7fff7fffu;
}
inline float sinpi_(float x) { return (float)wp::sin(3.14159265358979323846 * (double)x); }
inline void sincos_pi(float x, float* s, float* c)
{
    const double a = 3.14159265358979323846 * (double)x;
    *s = (float)wp::sin(a);
    *c = (float)wp::cos(a);
}

#endif

// NaN and +inf from their bits: the C runtime's NAN is (float)(0.0 / 0.0), which CUDA evaluates at run time as a
// call to a float64 division (in the SDF kernel it was 4 calls per lane and tile, and their registers)
NGF_FN float bits_to_float(u32 b)
{
    union
    {
        u32 u;
        float f;
    } v;
    v.u = b;
    return v.f;
}
#define NGF_NAN bits_to_float(0x7fc00000u)
#define NGF_INF bits_to_float(0x7f800000u)

NGF_FN float relu(float x) { return x > 0.0f ? x : 0.0f; }
NGF_FN float min2(float a, float b) { return b < a ? b : a; }

// ---- layers -------------------------------------------------------------------------------------------------
// A layer of K inputs and N outputs is packed as KS = K/16 k-steps x NT = N/8 n-tiles (NT even, padded with a zero
// n-tile), n-tiles in pairs: for k-step k, pair j, lane l the 16 bytes (b0, b1) of n-tile 2j and of n-tile 2j + 1,
// so one load serves two n-tiles.

template <int MT, int NT>
NGF_FN void zero(float (&c)[MT][NT][4])
{
#pragma unroll
    for (int m = 0; m < MT; ++m)
#pragma unroll
        for (int n = 0; n < NT; ++n)
#pragma unroll
            for (int i = 0; i < 4; ++i) c[m][n][i] = 0.0f;
}

// c[m] += a[m] W for k-steps [KS0, KS0 + KS) of the packed layer w (NTW n-tiles per k-step), n-tiles [NT0, NT0 + NT)
// (NT0 even)
template <int MT, int KS, int NT>
NGF_FN void dense(const u32 (&a)[MT][KS][4], const u32x2* w, int ntw, int ks0, int nt0, float (&c)[MT][NT][4])
{
    const int lane = lane_id();
#pragma unroll
    for (int k = 0; k < KS; ++k)
    {
        const u32x2* row = w + (size_t)(ks0 + k) * ntw * 32;
#pragma unroll
        for (int n = 0; n + 1 < NT; n += 2)
        {
            const u32x4 b = ld_table4((const u32x4*)row + ((nt0 + n) / 2) * 32 + lane);
#pragma unroll
            for (int m = 0; m < MT; ++m)
            {
                mma(c[m][n], a[m][k], u32x2{b.x, b.y});
                mma(c[m][n + 1], a[m][k], u32x2{b.z, b.w});
            }
        }
        if (NT & 1)  // a last single n-tile: the even one of its pair
        {
            const u32x2 b = ld_weights(row + (((nt0 + NT - 1) / 2) * 32 + lane) * 2);
#pragma unroll
            for (int m = 0; m < MT; ++m) mma(c[m][NT - 1], a[m][k], b);
        }
    }
}

// bias (lane-packed: n-tile n, lane t holds the bias of columns 8n + 2t, 8n + 2t + 1) and ReLU, in place
template <int MT, int NT>
NGF_FN void bias_relu(float (&c)[MT][NT][4], const f32x2* bias, int nt0)
{
    const int t = lane_id() & 3;
#pragma unroll
    for (int n = 0; n < NT; ++n)
    {
        const f32x2 b = ld_table(bias + (nt0 + n) * 4 + t);
#pragma unroll
        for (int m = 0; m < MT; ++m)
        {
            c[m][n][0] = relu(c[m][n][0] + b.x);
            c[m][n][1] = relu(c[m][n][1] + b.y);
            c[m][n][2] = relu(c[m][n][2] + b.x);
            c[m][n][3] = relu(c[m][n][3] + b.y);
        }
    }
}

// C fragments of NT n-tiles (fp32) -> A fragments of NT/2 k-steps (fp16)
template <int MT, int NT>
NGF_FN void to_a(const float (&c)[MT][NT][4], u32 (&a)[MT][NT / 2][4])
{
#pragma unroll
    for (int m = 0; m < MT; ++m)
#pragma unroll
        for (int n = 0; n < NT; ++n)
        {
            a[m][n / 2][(n & 1) * 2 + 0] = pack_half2(c[m][n][0], c[m][n][1]);
            a[m][n / 2][(n & 1) * 2 + 1] = pack_half2(c[m][n][2], c[m][n][3]);
        }
}

// A whole hidden layer on A fragments: relu(a W + b) as the A fragments of the next layer (NT output n-tiles).
template <int MT, int KS, int NT>
NGF_FN void hidden_layer(const u32 (&a)[MT][KS][4], const u32x2* w, const f32x2* bias, u32 (&out)[MT][NT / 2][4])
{
    float c[MT][NT][4];
    zero<MT, NT>(c);
    dense<MT, KS, NT>(a, w, NT, 0, 0, c);
    bias_relu<MT, NT>(c, bias, 0);
    to_a<MT, NT>(c, out);
}

// Sum over the 4 lanes of a row group: afterwards every lane of group g holds the full sums of rows g and g+8.
NGF_FN void row_sum(float& r0, float& r1)
{
    r0 += shfl_xor(r0, 1);
    r1 += shfl_xor(r1, 1);
    r0 += shfl_xor(r0, 2);
    r1 += shfl_xor(r1, 2);
}

// Last, bias-free layer to one output (fp32 dot product on the C fragments, weights lane-packed like a bias).
template <int MT, int NT>
NGF_FN void dot_rows(const float (&c)[MT][NT][4], const f32x2* w, float (&y)[MT][2])
{
    const int t = lane_id() & 3;
#pragma unroll
    for (int m = 0; m < MT; ++m)
    {
        y[m][0] = 0.0f;
        y[m][1] = 0.0f;
    }
#pragma unroll
    for (int n = 0; n < NT; ++n)
    {
        const f32x2 v = ld_table(w + n * 4 + t);
#pragma unroll
        for (int m = 0; m < MT; ++m)
        {
            y[m][0] += c[m][n][0] * v.x + c[m][n][1] * v.y;
            y[m][1] += c[m][n][2] * v.x + c[m][n][3] * v.y;
        }
    }
#pragma unroll
    for (int m = 0; m < MT; ++m) row_sum(y[m][0], y[m][1]);
}

// ---- the networks ---------------------------------------------------------------------------------------------

// Folded weights of one network, packed by the host (kernels/tensorcore.py). Widths: lifting F -> D/4 -> D/2 -> D
// (F = 3 + 6 L inputs, each split into an fp16 high and low part), heads D -> D/4 -> D/4 -> 1.
struct Lifting
{
    const u32x2* w0;
    const f32x2* b0;
    const u32x2* w1;
    const f32x2* b1;
    const u32x2* w2;
    const f32x2* b2;
    int octaves;
};

struct Head
{
    const u32x2* w0;
    const f32x2* b0;
    const u32x2* w1;
    const f32x2* b1;
    const f32x2* w2;
};

// Input feature j of a point (network.fourier_features' order): x, y, z, then sin(2^k pi x_c) for c, k, then cos.
NGF_FN float feature(const float (&x)[3], int j, int octaves)
{
    if (j < 3)
        return x[j];
    const int nf = 3 * octaves;
    int i = j - 3;
    const bool is_cos = i >= nf;
    if (is_cos)
        i -= nf;
    if (i >= nf)
        return 0.0f;
    float s, c;
    sincos_pi(x[i / octaves] * (float)(1 << (i % octaves)), &s, &c);
    return is_cos ? c : s;
}

// A fragments of the lifting input: column 2j holds fp16(v_j), column 2j+1 the rest v_j - fp16(v_j), so the
// first layer sees the coordinates and features to fp32 accuracy (its packed weights repeat each column twice).
template <int MT, int KS0>
NGF_FN void input_fragments(const float (&x)[MT][2][3], int octaves, u32 (&a)[MT][KS0][4])
{
    const int t = lane_id() & 3;
#pragma unroll
    for (int m = 0; m < MT; ++m)
#pragma unroll
        for (int k = 0; k < KS0; ++k)
#pragma unroll
            for (int r = 0; r < 2; ++r)
#pragma unroll
                for (int h = 0; h < 2; ++h)
                {
                    const float v = feature(x[m][r], 8 * k + 4 * h + t, octaves);
                    const float vhi = half_bits_to_float(pack_half2(v, 0.0f) & 0xffffu);
                    a[m][k][2 * h + r] = pack_half2(vhi, v - vhi);
                }
}

// The first two lifting layers: points -> A fragments of h1 (D/2 wide, D/32 k-steps).
template <int MT, int D, int KS0>
NGF_FN void lift_hidden(const Lifting& L, const float (&x)[MT][2][3], u32 (&h1)[MT][D / 32][4])
{
    u32 a0[MT][KS0][4];
    input_fragments<MT, KS0>(x, L.octaves, a0);
    u32 a1[MT][D / 64][4];  // D/4 outputs = D/32 n-tiles
    hidden_layer<MT, KS0, D / 32>(a0, L.w0, L.b0, a1);
    // D/2 outputs = D/16 n-tiles, computed at most 8 at a time so that few accumulators are live
    constexpr int NC = D / 16 < 8 ? D / 16 : 8;
#pragma unroll
    for (int q = 0; q < D / 16 / NC; ++q)
    {
        float c1[MT][NC][4];
        zero<MT, NC>(c1);
        dense<MT, D / 64, NC>(a1, L.w1, D / 16, 0, NC * q, c1);
        bias_relu<MT, NC>(c1, L.b1, NC * q);
        u32 part[MT][NC / 2][4];
        to_a<MT, NC>(c1, part);
#pragma unroll
        for (int m = 0; m < MT; ++m)
#pragma unroll
            for (int k = 0; k < NC / 2; ++k)
#pragma unroll
                for (int i = 0; i < 4; ++i) h1[m][NC / 2 * q + k][i] = part[m][k][i];
    }
}

// Output chunk q (8 NC embedding channels, NC n-tiles) of the last lifting layer, after bias and ReLU (fp32).
template <int MT, int D, int NC>
NGF_FN void lift_chunk(const Lifting& L, const u32 (&h1)[MT][D / 32][4], int q, float (&e)[MT][NC][4])
{
    zero<MT, NC>(e);
    dense<MT, D / 32, NC>(h1, L.w2, D / 8, 0, NC * q, e);
    bias_relu<MT, NC>(e, L.b2, NC * q);
}

// The tail of a head: first-layer sums (H = D/4 wide, fp32) -> bias, ReLU -> H -> bias, ReLU -> 1.
template <int MT, int NTH>
NGF_FN void head_tail(const Head& W, float (&c0)[MT][NTH][4], float (&y)[MT][2])
{
    bias_relu<MT, NTH>(c0, W.b0, 0);
    u32 a1[MT][NTH / 2][4];
    to_a<MT, NTH>(c0, a1);
    float c1[MT][NTH][4];
    zero<MT, NTH>(c1);
    dense<MT, NTH / 2, NTH>(a1, W.w1, NTH, 0, 0, c1);
    bias_relu<MT, NTH>(c1, W.b1, 0);
    dot_rows<MT, NTH>(c1, W.w2, y);
}

// ---- packed embeddings ----------------------------------------------------------------------------------------
// An embedding row of D fp16 channels is stored in fragment order: block b (channels 32b .. 32b+31) is four 16-byte
// segments, segment t = {pair(16(2b)+2t), pair(16(2b)+8+2t), pair(16(2b+1)+2t), pair(16(2b+1)+8+2t)}, where
// pair(c) is channels c, c+1. Lane t of a row group then loads its A-fragment halves of two k-steps in one load.

// A fragments of k-steps 2b and 2b+1 from block b's segments of rows g (seg0) and g + 8 (seg1).
NGF_FN void segments_to_a(const u32x4& seg0, const u32x4& seg1, u32 (&a)[2][4])
{
    a[0][0] = seg0.x;
    a[0][1] = seg1.x;
    a[0][2] = seg0.y;
    a[0][3] = seg1.y;
    a[1][0] = seg0.z;
    a[1][1] = seg1.z;
    a[1][2] = seg0.w;
    a[1][3] = seg1.w;
}

template <int D>
NGF_FN void load_embeddings(const u32x4* rows, int r0, int r1, u32 (&e)[1][D / 16][4])
{
    const int t = lane_id() & 3;
    const u32x4* p0 = rows + (size_t)r0 * (D / 8) + t;
    const u32x4* p1 = rows + (size_t)r1 * (D / 8) + t;
    u32x4 s0[D / 32], s1[D / 32];
#pragma unroll
    for (int b = 0; b < D / 32; ++b)  // all loads first: 8 x 16 bytes per lane in flight
    {
        s0[b] = ld_stream(p0 + 4 * b);
        s1[b] = ld_stream(p1 + 4 * b);
    }
#pragma unroll
    for (int b = 0; b < D / 32; ++b)
    {
        u32 a[2][4];
        segments_to_a(s0[b], s1[b], a);
#pragma unroll
        for (int i = 0; i < 4; ++i)
        {
            e[0][2 * b][i] = a[0][i];
            e[0][2 * b + 1][i] = a[1][i];
        }
    }
}

// Store k-steps [2 b0, 2 b0 + KS) of e (A fragments of one m-tile) into rows r0 (row g) and r1 (row g + 8).
template <int KS>
NGF_FN void store_embeddings(const u32 (&e)[1][KS][4], int b0, u32x4* rows, int row_len, int r0, int r1,
                             bool ok0, bool ok1)
{
    const int t = lane_id() & 3;
#pragma unroll
    for (int j = 0; j < KS / 2; ++j)
    {
        const int b = b0 + j;
        if (ok0)
            rows[(size_t)r0 * row_len + 4 * b + t] = u32x4{e[0][2 * j][0], e[0][2 * j][2], e[0][2 * j + 1][0], e[0][2 * j + 1][2]};
        if (ok1)
            rows[(size_t)r1 * row_len + 4 * b + t] = u32x4{e[0][2 * j][1], e[0][2 * j][3], e[0][2 * j + 1][1], e[0][2 * j + 1][3]};
    }
}

// |a - s| in place for k-steps [k0, k0 + KS) of A fragments (k0 and KS even), s a source's packed embedding row:
// lane t reads its segment of each block once, pairs x, y for the even k-step and z, w for the odd one.
template <int MT, int KS>
NGF_FN void subtract_source(u32 (&a)[MT][KS][4], const u32x4* s_row, int k0)
{
    static_assert(KS % 2 == 0, "k-steps come in blocks of two");
    const int t = lane_id() & 3;
#pragma unroll
    for (int j = 0; j < KS / 2; ++j)
    {
        const u32x4 s = ld_table4(s_row + 4 * (k0 / 2 + j) + t);
#pragma unroll
        for (int m = 0; m < MT; ++m)
        {
            a[m][2 * j][0] = habs_diff2(a[m][2 * j][0], s.x);
            a[m][2 * j][1] = habs_diff2(a[m][2 * j][1], s.x);
            a[m][2 * j][2] = habs_diff2(a[m][2 * j][2], s.y);
            a[m][2 * j][3] = habs_diff2(a[m][2 * j][3], s.y);
            a[m][2 * j + 1][0] = habs_diff2(a[m][2 * j + 1][0], s.z);
            a[m][2 * j + 1][1] = habs_diff2(a[m][2 * j + 1][1], s.z);
            a[m][2 * j + 1][2] = habs_diff2(a[m][2 * j + 1][2], s.w);
            a[m][2 * j + 1][3] = habs_diff2(a[m][2 * j + 1][3], s.w);
        }
    }
}

// subtract_source one k-step at a time (half of each segment load used): fewer registers live across a chunk,
// which the lifted single-source kernel needs.
template <int MT, int KS>
NGF_FN void subtract_source_ksteps(u32 (&a)[MT][KS][4], const u32x4* s_row, int k0)
{
    const int t = lane_id() & 3;
#pragma unroll
    for (int k = 0; k < KS; ++k)
    {
        const int ks = k0 + k;
        const u32x4 s = ld_table4(s_row + 4 * (ks / 2) + t);
        const u32 lo = (ks & 1) ? s.z : s.x, hi = (ks & 1) ? s.w : s.y;
#pragma unroll
        for (int m = 0; m < MT; ++m)
        {
            a[m][k][0] = habs_diff2(a[m][k][0], lo);
            a[m][k][1] = habs_diff2(a[m][k][1], lo);
            a[m][k][2] = habs_diff2(a[m][k][2], hi);
            a[m][k][3] = habs_diff2(a[m][k][3], hi);
        }
    }
}

// ---- heads ------------------------------------------------------------------------------------------------------

// A distance head fed two k-steps at a time: blocks(b, d) fills d with the A fragments of |e - s| for k-steps 2b and
// 2b + 1 of MT m-tiles (or of MT sources for one m-tile), which share every weight fragment load.
template <int D, int MT, class Blocks>
NGF_FN void head_on_blocks(const Head& W, Blocks&& blocks, float (&y)[MT][2])
{
    float c0[MT][D / 32][4];
    zero<MT, D / 32>(c0);
#pragma unroll
    for (int b = 0; b < D / 32; ++b)
    {
        u32 d[MT][2][4];
        blocks(b, d);
        dense<MT, 2, D / 32>(d, W.w0, D / 32, 2 * b, 0, c0);
    }
    head_tail<MT, D / 32>(W, c0, y);
}

// Distance heads of SP sources on one m-tile: e in A fragments (fp16), each source a packed embedding row;
// y[j] = head(|e - s_j|) for rows g and g+8 (the |x - s| term of euclid networks is added by the caller).
template <int D, int SP>
NGF_FN void distance_heads(const Head& W, const u32 (&e)[1][D / 16][4], const u32x4* const (&s_rows)[SP],
                           float (&y)[SP][2])
{
    head_on_blocks<D, SP>(W, [&](int b, u32 (&d)[SP][2][4]) {
#pragma unroll
        for (int j = 0; j < SP; ++j)
        {
#pragma unroll
            for (int i = 0; i < 4; ++i)
            {
                d[j][0][i] = e[0][2 * b][i];
                d[j][1][i] = e[0][2 * b + 1][i];
            }
            subtract_source<1, 2>(reinterpret_cast<u32(&)[1][2][4]>(d[j]), s_rows[j], 2 * b);
        }
    }, y);
}

// ---- per-row inputs and outputs -----------------------------------------------------------------------------------

// User frame -> network frame: x_net = ((x - hi) - lo) * xscale with the centre c split into float32 pairs
// hi + lo (hi = float32(c), lo = float32(c - hi)), so that points far from the origin lose little beyond their own
// float32 rounding (a point near the centre subtracts hi exactly); distances * dscale are in user units. A point
// outside the cube |x_net| <= limit (or not finite) has no answer: its results are NaN. The float64 centre cx..cz is
// the per-thread Warp kernels' (kernels/inference/mlp.py); float64 arithmetic here cost the SDF kernel 16% and the
// pair kernel 3% on an H100.
struct Frame
{
    double cx, cy, cz;
    float xscale, dscale, limit;
    float hx, hy, hz, lx, ly, lz;
};

// Rows this lane reads: g and g + 8 of m-tile (tile, m), clamped to the last row (their results are not written).
NGF_FN void tile_rows(int tile, int mt, int m, int n, int& r0, int& r1, bool& ok0, bool& ok1)
{
    const int g = lane_id() >> 2;
    const int base = (tile * mt + m) * 16;
    r0 = base + g;
    r1 = base + g + 8;
    ok0 = r0 < n;
    ok1 = r1 < n;
    if (!ok0)
        r0 = n - 1;
    if (!ok1)
        r1 = n - 1;
}

NGF_FN void to_net(const Frame& f, const float* p, float (&x)[3])
{
    x[0] = ((p[0] - f.hx) - f.lx) * f.xscale;
    x[1] = ((p[1] - f.hy) - f.ly) * f.xscale;
    x[2] = ((p[2] - f.hz) - f.lz) * f.xscale;
}

// Whether a point (network frame) is inside the domain: false for NaN and inf too.
NGF_FN bool in_domain(const Frame& f, const float (&x)[3])
{
    return fabsf(x[0]) <= f.limit && fabsf(x[1]) <= f.limit && fabsf(x[2]) <= f.limit;
}

// The same test for a point in the Frame's coordinates.
NGF_FN bool point_in_domain(const Frame& f, const float* p)
{
    float x[3];
    to_net(f, p, x);
    return in_domain(f, x);
}

// The rows of m-tiles (tile, 0 .. MT-1) this lane reads, and their points in the network frame.
template <int MT>
NGF_FN void tile_points(const Frame& f, const float* pts, int tile, int n, int (&r)[MT][2], bool (&ok)[MT][2],
                        float (&x)[MT][2][3])
{
#pragma unroll
    for (int m = 0; m < MT; ++m)
    {
        tile_rows(tile, MT, m, n, r[m][0], r[m][1], ok[m][0], ok[m][1]);
        to_net(f, pts + 3 * r[m][0], x[m][0]);
        to_net(f, pts + 3 * r[m][1], x[m][1]);
    }
}

// The lifting of MT m-tiles with its last layer produced NC n-tiles at a time: use(q, a) receives chunk q
// (embedding channels 8 NC q ..) as A fragments (fp16), to feed a head or to store, so the whole embedding is
// never held at once.
template <int MT, int D, int KS0, int NC, class Use>
NGF_FN void lift_chunks(const Lifting& L, const float (&x)[MT][2][3], Use&& use)
{
    u32 h1[MT][D / 32][4];
    lift_hidden<MT, D, KS0>(L, x, h1);
#pragma unroll
    for (int q = 0; q < D / 8 / NC; ++q)
    {
        float c[MT][NC][4];
        lift_chunk<MT, D, NC>(L, h1, q, c);
        u32 a[MT][NC / 2][4];
        to_a<MT, NC>(c, a);
        use(q, a);
    }
}

// The lifting of MT m-tiles fed chunk by chunk into a head's first layer, then the rest of the head;
// prepare(q, a) may change a chunk before it enters (|e - s| for a distance head).
template <int MT, int D, int KS0, int NC, class Prepare>
NGF_FN void lifted_head(const Lifting& L, const Head& H, const float (&x)[MT][2][3], Prepare&& prepare,
                        float (&y)[MT][2])
{
    float c0[MT][D / 32][4];
    zero<MT, D / 32>(c0);
    lift_chunks<MT, D, KS0, NC>(L, x, [&](int q, u32 (&a)[MT][NC / 2][4]) {
        prepare(q, a);
        dense<MT, NC / 2, D / 32>(a, H.w0, D / 32, NC / 2 * q, 0, c0);
    });
    head_tail<MT, D / 32>(H, c0, y);
}

// Where distance results go and how they are finished.
struct DistanceOut
{
    float* out;           // (S, ld), or (ld,) with reduce_min
    int ld;               // output row length
    int reduce_min;       // 1: one value per row, the nearest source (MSAD); 0: a row per source
    float euclid;         // 1: distance = head + |x - s| (network frame)
    const int* row_comp;  // component label per row (null: one component)
    int raw;              // 1: the network's own value (no clamping at 0, no exact 0 at the source)
};

// Sources are rows of three tables (packed embeddings, points in the Frame's coordinates, component labels):
// rows ids[s], or row0 + s without ids. A bound model's vertex sources are rows of its kept tables; point sources
// are rows of tables computed for the call.
struct Sources
{
    const u32x4* emb;    // (R, D/8) packed fp16 embeddings
    const float* pos;    // (R, 3) in the Frame's coordinates (to_net maps them)
    const int* comp;     // (R,) component labels (null: one component)
    const int* ids;      // (S,) rows (null: row0 + s)
    int row0;
    int count;

    NGF_FN int row(int s) const { return ids ? ids[s] : row0 + s; }
};

// The one finishing rule of a distance (the per-thread kernels call it too, kernels/inference/finish.py):
// NaN where either point is outside the domain or not finite; +inf across components; exactly 0 where the row is
// the source point itself; d = (head + euclid |x - s|) in user units, never below the straight line |x - s|
// (a geodesic is never shorter than the chord; NaN stays NaN). raw: the network's value (NaN and +inf as above).
// inside: both points are in the domain. The vertex-query kernels below (distance_rows, ssad_rows, lift_ssad_rows)
// pass true: their rows are mesh vertices or targets and their sources points that the host refused unless inside
// (inference/inputs.py, sources_in); a test per distance there cost a bound MSAD 50%, and one per row and source
// still 15%, on an H100. The pair kernel tests its points (check=False gives NaN rows).
NGF_FN float finish_inside(float y, const Frame& f, const float* p, const float* sp, float euclid, bool other_part,
                           int raw, bool inside)
{
    if (!inside)
        return NGF_NAN;
    if (other_part)
        return NGF_INF;
    if (!raw && p[0] == sp[0] && p[1] == sp[1] && p[2] == sp[2])
        return 0.0f;
    // |x - s| from the input points' float32 difference: correctly rounded to the difference itself however far the
    // points lie from the origin, and symmetric in x and s (float64 and a float64 sqrt here cost 50% of a bound
    // MSAD's time on an H100), scaled to the network frame before squaring (no overflow for huge meshes)
    const float dx = (p[0] - sp[0]) * f.xscale, dy = (p[1] - sp[1]) * f.xscale, dz = (p[2] - sp[2]) * f.xscale;
    const float chord = sqrtf(dx * dx + dy * dy + dz * dz);  // network frame
    const float d = (y + euclid * chord) * f.dscale;
    if (raw)
        return d;
    const float c = chord * f.dscale;
    return d < c ? c : d;
}

NGF_FN float finish_distance(float y, const Frame& f, const float* p, const float* sp, float euclid, bool other_part,
                             int raw)
{
    return finish_inside(y, f, p, sp, euclid, other_part, raw, point_in_domain(f, p) && point_in_domain(f, sp));
}

// Finishes and writes one source's distances to the rows of MT m-tiles (lane t = 0 writes row g, t = 1 row g + 8).
template <int MT>
NGF_FN void store_distances(const DistanceOut& o, const Frame& f, const float* pts, const float (&y)[MT][2],
                            const int (&r)[MT][2], const bool (&ok)[MT][2], const float* sp, int sc)
{
    const int t = lane_id() & 3;
#pragma unroll
    for (int m = 0; m < MT; ++m)
#pragma unroll
        for (int i = 0; i < 2; ++i)
        {
            const int rc = o.row_comp ? o.row_comp[r[m][i]] : 0;
            const float d = finish_inside(y[m][i], f, pts + 3 * r[m][i], sp, o.euclid, o.row_comp && sc != rc, o.raw,
                                          true);
            if (t == i && ok[m][i])
                o.out[r[m][i]] = d;
        }
}

// ---- kernels (one call per warp; the warp loops over its tiles) ---------------------------------------------------

// Distances from S sources to N rows (points, or vertices with cached embeddings): the persistent loop of the
// SSAD / MSAD / distance-matrix kernels. LIFT: embed the rows here (points); else read packed embeddings `cached`.
// SP sources at a time share each weight fragment load.
template <int D, int KS0, bool LIFT, int SP>
NGF_FN void distance_rows(const Lifting& L, const Head& H, const Frame& f, const float* pts, const u32x4* cached,
                          int n, const Sources& S, const DistanceOut& o, int warp, int n_warps)
{
    const int t = lane_id() & 3;
    const int n_tiles = (n + 15) / 16;
    for (int tile = warp; tile < n_tiles; tile += n_warps)
    {
        int r[1][2];
        bool ok[1][2];
        u32 e[1][D / 16][4];
        if (LIFT)
        {
            float x[1][2][3];
            tile_points<1>(f, pts, tile, n, r, ok, x);
            lift_chunks<1, D, KS0, 8>(L, x, [&](int q, const u32 (&a)[1][4][4]) {
#pragma unroll
                for (int k = 0; k < 4; ++k)
#pragma unroll
                    for (int i = 0; i < 4; ++i) e[0][4 * q + k][i] = a[0][k][i];
            });
        }
        else
        {
            tile_rows(tile, 1, 0, n, r[0][0], r[0][1], ok[0][0], ok[0][1]);
            load_embeddings<D>(cached, r[0][0], r[0][1], e);
        }
        const int r0 = r[0][0], r1 = r[0][1];
        const float* p0 = pts + 3 * r0;
        const float* p1 = pts + 3 * r1;
        const int comp0 = o.row_comp ? o.row_comp[r0] : 0;
        const int comp1 = o.row_comp ? o.row_comp[r1] : 0;
        float best0 = NGF_INF, best1 = NGF_INF;
        for (int s = 0; s < S.count; s += SP)
        {
            const u32x4* rows[SP];
            int src[SP];
#pragma unroll
            for (int j = 0; j < SP; ++j)  // a short last group repeats its last source
            {
                src[j] = S.row(s + j < S.count ? s + j : S.count - 1);
                rows[j] = S.emb + (size_t)src[j] * (D / 8);
            }
            float y[SP][2];
            distance_heads<D, SP>(H, e, rows, y);
#pragma unroll
            for (int j = 0; j < SP; ++j)
            {
                if (s + j >= S.count)
                    break;
                const float* sp = S.pos + 3 * src[j];
                const int sc = S.comp ? S.comp[src[j]] : 0;
                const float d0 = finish_inside(y[j][0], f, p0, sp, o.euclid, o.row_comp && sc != comp0, o.raw, true);
                const float d1 = finish_inside(y[j][1], f, p1, sp, o.euclid, o.row_comp && sc != comp1, o.raw, true);
                if (o.reduce_min)
                {
                    best0 = min2(best0, d0);
                    best1 = min2(best1, d1);
                    continue;
                }
                float* row = o.out + (size_t)(s + j) * o.ld;
                if (t == 0 && ok[0][0])
                    row[r0] = d0;
                if (t == 1 && ok[0][1])
                    row[r1] = d1;
            }
        }
        if (o.reduce_min)
        {
            if (t == 0 && ok[0][0])
                o.out[r0] = best0;
            if (t == 1 && ok[0][1])
                o.out[r1] = best1;
        }
    }
}

// One source to every row of kept embeddings (SSAD on a bound model): MT m-tiles per warp share each weight
// fragment load. PF: two register buffers take turns, the next tile's embeddings loading into one while the
// other's tile computes, so each warp keeps memory busy.
template <int D, int MT>
struct SsadTile
{
    u32x4 seg[MT][2][D / 32];
    int r[MT][2];
    bool ok[MT][2];

    NGF_FN void load(const u32x4* cached, int tile, int n)
    {
        const int t = lane_id() & 3;
#pragma unroll
        for (int m = 0; m < MT; ++m)
            tile_rows(tile, MT, m, n, r[m][0], r[m][1], ok[m][0], ok[m][1]);
#pragma unroll
        for (int b = 0; b < D / 32; ++b)
#pragma unroll
            for (int m = 0; m < MT; ++m)
#pragma unroll
                for (int i = 0; i < 2; ++i) seg[m][i][b] = ld_stream(cached + (size_t)r[m][i] * (D / 8) + 4 * b + t);
    }

    NGF_FN void finish(const Head& H, const Frame& f, const float* pts, const u32x4* s_row, const float* sp, int sc,
                       const DistanceOut& o) const
    {
        float y[MT][2];
        head_on_blocks<D, MT>(H, [&](int b, u32 (&d)[MT][2][4]) {
#pragma unroll
            for (int m = 0; m < MT; ++m)
                segments_to_a(seg[m][0][b], seg[m][1][b], d[m]);
            subtract_source<MT, 2>(d, s_row, 2 * b);
        }, y);
        store_distances<MT>(o, f, pts, y, r, ok, sp, sc);
    }
};

// Every tile of kept embeddings a persistent warp owns, loaded and handed to finish(tile); with PF the next tile's
// load is issued before this one's head runs, so its latency hides behind the mma work.
template <int D, int MT, bool PF, class Finish>
NGF_FN void each_kept_tile(const u32x4* cached, int n, int warp, int n_warps, Finish finish)
{
    const int n_tiles = (n + 16 * MT - 1) / (16 * MT);
    if (!PF)
    {
        for (int tile = warp; tile < n_tiles; tile += n_warps)
        {
            SsadTile<D, MT> a;
            a.load(cached, tile, n);
            finish(a);
        }
        return;
    }
    SsadTile<D, MT> a, b;
    if (warp < n_tiles)
        a.load(cached, warp, n);
    for (int tile = warp; tile < n_tiles; tile += 2 * n_warps)
    {
        const int next = tile + n_warps;
        if (next < n_tiles)
            b.load(cached, next, n);
        finish(a);
        if (next >= n_tiles)
            break;
        if (next + n_warps < n_tiles)
            a.load(cached, next + n_warps, n);
        finish(b);
    }
}

template <int D, int MT, bool PF>
NGF_FN void ssad_rows(const Head& H, const Frame& f, const float* pts, const u32x4* cached, int n, const Sources& S,
                      const DistanceOut& o, int warp, int n_warps)
{
    const int srow = S.row(0);
    const u32x4* s_row = S.emb + (size_t)srow * (D / 8);
    const float* sp = S.pos + 3 * srow;
    const int sc = S.comp ? S.comp[srow] : 0;
    each_kept_tile<D, MT, PF>(cached, n, warp, n_warps,
                              [&](const SsadTile<D, MT>& t) { t.finish(H, f, pts, s_row, sp, sc, o); });
}

// ---- landmark networks ------------------------------------------------------------------------------------------
// A landmark network's distance head also reads the exact distances T(s), T(q) of both points to K landmarks: fp32
// rows of a (V, K) table. Its first layer takes [|e_s - e_q| (D), |T(s) - T(q)| (K), lower, upper (, |s - q|,
// log(upper / floor))]: the K differences enter as fp16 k-steps like the embedding channels (they are features),
// the scalars as fp16 high + low pairs in one last k-step (fp32-accurate), and the bounds and the bracket around
// the head's output are computed in fp32 from the fp32 rows, since they set the answer's accuracy.
// Lane t of a row group reads floats 4t .. 4t+3 of each 16-column block of a row in one load; the host permutes the
// layer's landmark columns to match (tensorcore.landmark_head_struct), so the table keeps its natural order.

// How a landmark network turns its head's output y into a distance (network.NeuroGFNet.distance_from_embeddings).
struct LandmarkNet
{
    const float* table;  // (V, K) float32, normalized units; the rows of the bound vertices
    float floor_scale;   // landmark_floor: the floor is max(|s - q|, floor_scale x lower)
    float euclid;        // 1: the plain form adds the floor to the head
    float unreached;     // upper at or beyond this: no landmark reaches the pair (2 x network.LANDMARK_UNREACHED)
    int form;            // 0: y (+ floor); 1: floor + sigmoid(y) (top - floor); 2: floor (top / floor) ** sigmoid(y)
    int pair_inputs;     // 1: the head also reads |s - q| and min(log(upper / floor), width_max)
    float width_max;
};

NGF_FN float max2(float a, float b) { return b > a ? b : a; }
NGF_FN f32x2 row_minmax(float lo, float up)  // the max of lo and the min of up over the 4 lanes of a row group
{
    lo = max2(lo, shfl_xor(lo, 1));
    up = min2(up, shfl_xor(up, 1));
    lo = max2(lo, shfl_xor(lo, 2));
    up = min2(up, shfl_xor(up, 2));
    return f32x2{lo, up};
}
NGF_FN float floats_at(const u32x4& v, int i)
{
    return bits_to_float(i == 0 ? v.x : i == 1 ? v.y : i == 2 ? v.z : v.w);
}

#define NGF_TINY 1e-12f  // network._TINY: distances clamped here before a log (s = q gives a floor of 0)

NGF_FN float log_ratio(float a, float b) { return logf(max2(a, NGF_TINY)) - logf(max2(b, NGF_TINY)); }

// The landmark k-steps of the first layer for MT m-tiles: c0 += |T(q) - T(s)| W, and each row's bounds (every lane
// of a row group holds those of rows g and g + 8). s_marks: the source's table row.
template <int D, int K, int MT>
NGF_FN void landmark_ksteps(const Head& W, const float* table, const int (&r)[MT][2], const float* s_marks,
                            float (&c0)[MT][D / 32][4], float (&lower)[MT][2], float (&upper)[MT][2])
{
    const int t = lane_id() & 3;
#pragma unroll
    for (int m = 0; m < MT; ++m)
#pragma unroll
        for (int i = 0; i < 2; ++i)
        {
            lower[m][i] = 0.0f;
            upper[m][i] = NGF_INF;
        }
#pragma unroll 4
    for (int j = 0; j < K / 16; ++j)
    {
        const u32x4 sb = ld_table4((const u32x4*)(s_marks + 16 * j + 4 * t));
        u32 a[MT][1][4];
#pragma unroll
        for (int m = 0; m < MT; ++m)
#pragma unroll
            for (int i = 0; i < 2; ++i)
            {
                const u32x4 qb = ld_stream((const u32x4*)(table + (size_t)r[m][i] * K + 16 * j + 4 * t));
                float d[4];
#pragma unroll
                for (int c = 0; c < 4; ++c)
                {
                    const float q = floats_at(qb, c), s = floats_at(sb, c);
                    d[c] = fabsf(q - s);
                    lower[m][i] = max2(lower[m][i], d[c]);
                    upper[m][i] = min2(upper[m][i], q + s);
                }
                a[m][0][i] = pack_half2(d[0], d[1]);      // row g (i = 0) or g + 8, columns 2t, 2t + 1
                a[m][0][2 + i] = pack_half2(d[2], d[3]);  // the same rows, columns 2t + 8, 2t + 9
            }
        dense<MT, 1, D / 32>(a, W.w0, D / 32, D / 16 + j, 0, c0);
    }
#pragma unroll
    for (int m = 0; m < MT; ++m)
#pragma unroll
        for (int i = 0; i < 2; ++i)
        {
            const f32x2 b = row_minmax(lower[m][i], upper[m][i]);
            lower[m][i] = b.x;
            upper[m][i] = b.y;
        }
}

// The landmark head on one tile of kept embeddings (SsadTile) and the finished distances of its rows.
template <int D, int K, int MT>
NGF_FN void landmark_tile(const SsadTile<D, MT>& a, const Head& H, const Frame& f, const float* pts,
                          const u32x4* s_row, const float* sp, int sc, const float* s_marks, const LandmarkNet& M,
                          const DistanceOut& o)
{
    const int t = lane_id() & 3;
    float c0[MT][D / 32][4];
    zero<MT, D / 32>(c0);
#pragma unroll
    for (int b = 0; b < D / 32; ++b)
    {
        u32 d[MT][2][4];
#pragma unroll
        for (int m = 0; m < MT; ++m)
            segments_to_a(a.seg[m][0][b], a.seg[m][1][b], d[m]);
        subtract_source<MT, 2>(d, s_row, 2 * b);
        dense<MT, 2, D / 32>(d, H.w0, D / 32, 2 * b, 0, c0);
    }
    float lower[MT][2], upper[MT][2], e[MT][2], floor_[MT][2];
    landmark_ksteps<D, K, MT>(H, M.table, a.r, s_marks, c0, lower, upper);
    // the last k-step: lane t holds columns 2t, 2t + 1 = the high and low fp16 parts of scalar t of the row
    u32 z[MT][1][4];
#pragma unroll
    for (int m = 0; m < MT; ++m)
#pragma unroll
        for (int i = 0; i < 2; ++i)
        {
            const float* p = pts + 3 * a.r[m][i];
            const float dx = (p[0] - sp[0]) * f.xscale, dy = (p[1] - sp[1]) * f.xscale, dz = (p[2] - sp[2]) * f.xscale;
            e[m][i] = sqrtf(dx * dx + dy * dy + dz * dz);  // |s - q|, network frame (as finish_inside's chord)
            floor_[m][i] = max2(e[m][i], M.floor_scale * lower[m][i]);
            float v = t == 0 ? lower[m][i] : upper[m][i];
            if (t >= 2)
                v = M.pair_inputs ? (t == 2 ? e[m][i] : min2(log_ratio(upper[m][i], floor_[m][i]), M.width_max)) : 0.0f;
            const float vhi = half_bits_to_float(pack_half2(v, 0.0f) & 0xffffu);
            z[m][0][i] = pack_half2(vhi, v - vhi);
            z[m][0][2 + i] = 0u;
        }
    dense<MT, 1, D / 32>(z, H.w0, D / 32, D / 16 + K / 16, 0, c0);
    float y[MT][2];
    head_tail<MT, D / 32>(H, c0, y);
#pragma unroll
    for (int m = 0; m < MT; ++m)
#pragma unroll
        for (int i = 0; i < 2; ++i)
        {
            const float fl = floor_[m][i];
            float v;
            if (M.form == 0)
                v = y[m][i] + M.euclid * fl;
            else if (upper[m][i] >= M.unreached)  // a piece without landmarks: the head on |s - q|
                v = e[m][i] + y[m][i];
            else
            {
                const float top = max2(upper[m][i], fl);
                const float sig = 1.0f / (1.0f + expf(-y[m][i]));
                if (M.form == 1)
                    v = fl + sig * (top - fl);
                else
                    v = fl > 0.0f ? max2(fl, NGF_TINY) * expf(sig * log_ratio(top, fl)) : fl;
            }
            const int rc = o.row_comp ? o.row_comp[a.r[m][i]] : 0;
            const float d = finish_inside(v, f, pts + 3 * a.r[m][i], sp, 0.0f, o.row_comp && sc != rc, o.raw, true);
            if (t == i && a.ok[m][i])
                o.out[a.r[m][i]] = d;
        }
}

// One source to every row of kept embeddings for a landmark network (SSAD on a bound model), as ssad_rows.
template <int D, int K, int MT, bool PF>
NGF_FN void landmark_ssad_rows(const Head& H, const Frame& f, const float* pts, const u32x4* cached, int n,
                               const Sources& S, const LandmarkNet& M, const DistanceOut& o, int warp, int n_warps)
{
    const int srow = S.row(0);
    const u32x4* s_row = S.emb + (size_t)srow * (D / 8);
    const float* sp = S.pos + 3 * srow;
    const int sc = S.comp ? S.comp[srow] : 0;
    const float* s_marks = M.table + (size_t)srow * K;
    each_kept_tile<D, MT, PF>(cached, n, warp, n_warps, [&](const SsadTile<D, MT>& t) {
        landmark_tile<D, K, MT>(t, H, f, pts, s_row, sp, sc, s_marks, M, o);
    });
}

// One source to N points embedded here (SSAD without kept embeddings): each chunk of the last lifting layer goes
// straight into the head's first layer as |e - s|, so the embedding is never held whole. MT m-tiles per warp
// share each weight load.
template <int D, int KS0, int MT, int NC>
NGF_FN void lift_ssad_rows(const Lifting& L, const Head& H, const Frame& f, const float* pts, int n, const Sources& S,
                           const DistanceOut& o, int warp, int n_warps)
{
    const int n_tiles = (n + 16 * MT - 1) / (16 * MT);
    const int srow = S.row(0);
    const u32x4* s_row = S.emb + (size_t)srow * (D / 8);
    const float* sp = S.pos + 3 * srow;
    const int sc = S.comp ? S.comp[srow] : 0;
    for (int tile = warp; tile < n_tiles; tile += n_warps)
    {
        int r[MT][2];
        bool ok[MT][2];
        float x[MT][2][3];
        tile_points<MT>(f, pts, tile, n, r, ok, x);
        float y[MT][2];
        lifted_head<MT, D, KS0, NC>(L, H, x, [&](int q, u32 (&a)[MT][NC / 2][4]) {
            subtract_source_ksteps<MT, NC / 2>(a, s_row, NC / 2 * q);
        }, y);
        store_distances<MT>(o, f, pts, y, r, ok, sp, sc);
    }
}

// Embeddings of N points, stored packed (fp16, fragment order): the rows the distance kernels read.
template <int D, int KS0>
NGF_FN void embed_rows(const Lifting& L, const Frame& f, const float* pts, int n, u32x4* out, int warp, int n_warps)
{
    const int n_tiles = (n + 15) / 16;
    for (int tile = warp; tile < n_tiles; tile += n_warps)
    {
        int r[1][2];
        bool ok[1][2];
        float x[1][2][3];
        tile_points<1>(f, pts, tile, n, r, ok, x);
        lift_chunks<1, D, KS0, 8>(L, x, [&](int q, const u32 (&a)[1][4][4]) {
            store_embeddings<4>(a, 2 * q, out, D / 8, r[0][0], r[0][1], ok[0][0], ok[0][1]);
        });
    }
}

// Point-to-point distances: m-tile 0 holds 16 points p, m-tile 1 their partners q; both are lifted together (one
// weight read serves both) and |e_p - e_q| feeds the head chunk by chunk, so no embedding is ever stored.
template <int D, int KS0, int NC>
NGF_FN void pair_rows(const Lifting& L, const Head& H, const Frame& f, const float* ps, const float* qs, int n,
                      float euclid, int raw, float* out, int warp, int n_warps)
{
    const int t = lane_id() & 3;
    const int n_tiles = (n + 15) / 16;
    for (int tile = warp; tile < n_tiles; tile += n_warps)
    {
        int r0, r1;
        bool ok0, ok1;
        tile_rows(tile, 1, 0, n, r0, r1, ok0, ok1);
        float x[2][2][3];
        to_net(f, ps + 3 * r0, x[0][0]);
        to_net(f, ps + 3 * r1, x[0][1]);
        to_net(f, qs + 3 * r0, x[1][0]);
        to_net(f, qs + 3 * r1, x[1][1]);
        const bool in0 = in_domain(f, x[0][0]) && in_domain(f, x[1][0]);  // both ends of row g, of row g + 8
        const bool in1 = in_domain(f, x[0][1]) && in_domain(f, x[1][1]);
        float c0[1][D / 32][4];
        zero<1, D / 32>(c0);
        lift_chunks<2, D, KS0, NC>(L, x, [&](int q, const u32 (&a)[2][NC / 2][4]) {
            u32 d[1][NC / 2][4];
#pragma unroll
            for (int k = 0; k < NC / 2; ++k)
#pragma unroll
                for (int i = 0; i < 4; ++i) d[0][k][i] = habs_diff2(a[0][k][i], a[1][k][i]);
            dense<1, NC / 2, D / 32>(d, H.w0, D / 32, NC / 2 * q, 0, c0);
        });
        float y[1][2];
        head_tail<1, D / 32>(H, c0, y);
        const float d0 = finish_inside(y[0][0], f, ps + 3 * r0, qs + 3 * r0, euclid, false, raw, in0);
        const float d1 = finish_inside(y[0][1], f, ps + 3 * r1, qs + 3 * r1, euclid, false, raw, in1);
        if (t == 0 && ok0)
            out[r0] = d0;
        if (t == 1 && ok1)
            out[r1] = d1;
    }
}

// Signed distances from the SDF head, MT m-tiles per warp (16 MT points). No domain test here: kept to the end of
// the tile, a point's test made this kernel spill registers (16% slower on an H100); rows outside the domain are
// made NaN by the caller (inference/backends.py, TensorCores.sdf: finish.nan_outside, only for unchecked input,
// since checked input is inside).
template <int D, int KS0, int MT, int NC>
NGF_FN void sdf_rows(const Lifting& L, const Head& H, const Frame& f, const float* pts, int n, float* out, int warp,
                     int n_warps)
{
    const int t = lane_id() & 3;
    const int n_tiles = (n + 16 * MT - 1) / (16 * MT);
    for (int tile = warp; tile < n_tiles; tile += n_warps)
    {
        int r[MT][2];
        bool ok[MT][2];
        float x[MT][2][3];
        tile_points<MT>(f, pts, tile, n, r, ok, x);
        float y[MT][2];
        lifted_head<MT, D, KS0, NC>(L, H, x, [](int, u32 (&)[MT][NC / 2][4]) {}, y);
#pragma unroll
        for (int m = 0; m < MT; ++m)
#pragma unroll
            for (int i = 0; i < 2; ++i)
                if (t == i && ok[m][i])
                    out[r[m][i]] = y[m][i] * f.dscale;
    }
}

// ---- the path head --------------------------------------------------------------------------------------------------
// Per path: g = relu(Wc [e_p | e_q] + bc), then the part of the point-wise head's first layer that is the same for
// every point of the path, pre = b0 + W0[:, 3:] g. Per point x on the straight line p -> q:
// relu(pre + W0[:, :3] x) -> P2 -> P3 -> 3, as offsets from x scaled by sin(pi t) where the network says so.

struct PathWeights
{
    const u32x2* wc;   // guidance 2D -> D
    const f32x2* bc;
    const u32x2* wg;   // first point layer, guidance columns: D -> P1
    const f32x2* b0;
    const f32x2* wx;   // first point layer, xyz columns: (P1/8 n-tiles, 4 lanes, 3 coordinates) f32x2
    const u32x2* w1;   // P1 -> P2
    const f32x2* b1;
    const u32x2* w2;   // P2 -> P3
    const f32x2* b2;
    const u32x2* w3;   // P3 -> 3 (one n-tile)
    float residual, window;
};

// pre (P1 floats per path, natural order) for N paths from their endpoints' packed embeddings.
template <int D, int P1>
NGF_FN void path_pre_rows(const PathWeights& W, const u32x4* ep, const u32x4* eq, int n, float* pre, int warp,
                          int n_warps)
{
    const int t = lane_id() & 3;
    const int n_tiles = (n + 15) / 16;
    for (int tile = warp; tile < n_tiles; tile += n_warps)
    {
        int r0, r1;
        bool ok0, ok1;
        tile_rows(tile, 1, 0, n, r0, r1, ok0, ok1);
        float acc[1][P1 / 8][4];
        zero<1, P1 / 8>(acc);
#pragma unroll 1
        for (int q = 0; q < D / 64; ++q)  // guidance in chunks of 64 channels, each fed on to the point layer
        {
            float c[1][8][4];
            zero<1, 8>(c);
#pragma unroll 1
            for (int half = 0; half < 2; ++half)  // [e_p | e_q]: k-steps 0 .. D/16-1 from e_p, the rest from e_q
            {
                const u32x4* rows = half ? eq : ep;
#pragma unroll 2
                for (int b = 0; b < D / 32; ++b)
                {
                    const u32x4 s0 = ld_table4(rows + (size_t)r0 * (D / 8) + 4 * b + t);
                    const u32x4 s1 = ld_table4(rows + (size_t)r1 * (D / 8) + 4 * b + t);
                    u32 a[1][2][4] = {{{s0.x, s1.x, s0.y, s1.y}, {s0.z, s1.z, s0.w, s1.w}}};
                    dense<1, 2, 8>(a, W.wc, D / 8, half * (D / 16) + 2 * b, 8 * q, c);
                }
            }
            bias_relu<1, 8>(c, W.bc, 8 * q);
            u32 a[1][4][4];
            to_a<1, 8>(c, a);
            dense<1, 4, P1 / 8>(a, W.wg, P1 / 8, 4 * q, 0, acc);
        }
#pragma unroll
        for (int n8 = 0; n8 < P1 / 8; ++n8)
        {
            const f32x2 b = ld_table(W.b0 + n8 * 4 + t);
            if (ok0)
                *(f32x2*)(pre + (size_t)r0 * P1 + 8 * n8 + 2 * t) = f32x2{acc[0][n8][0] + b.x, acc[0][n8][1] + b.y};
            if (ok1)
                *(f32x2*)(pre + (size_t)r1 * P1 + 8 * n8 + 2 * t) = f32x2{acc[0][n8][2] + b.x, acc[0][n8][3] + b.y};
        }
    }
}

// m points for each of N paths: out[i, j] (from_net: the Frame's coordinates), straight line p_i -> q_i through the
// point-wise head.
template <int P1, int P2, int P3>
NGF_FN void path_point_rows(const PathWeights& W, const Frame& f, const float* ps, const float* qs, const float* pre,
                            int n_paths, int m, float* out, int warp, int n_warps)
{
    const int t = lane_id() & 3;
    const int n = n_paths * m;
    const int n_tiles = (n + 15) / 16;
    for (int tile = warp; tile < n_tiles; tile += n_warps)
    {
        int r[2];
        bool ok[2];
        tile_rows(tile, 1, 0, n, r[0], r[1], ok[0], ok[1]);
        float x[2][3], u[2];
        int path[2];
#pragma unroll
        for (int i = 0; i < 2; ++i)
        {
            path[i] = r[i] / m;
            u[i] = (float)(r[i] - path[i] * m) / (float)(m > 1 ? m - 1 : 1);
            float p[3], q[3];
            to_net(f, ps + 3 * path[i], p);
            to_net(f, qs + 3 * path[i], q);
#pragma unroll
            for (int c = 0; c < 3; ++c) x[i][c] = p[c] + u[i] * (q[c] - p[c]);
        }
        // first layer on CUDA cores in fp32: pre (per path) + W0[:, :3] x
        float h[1][P1 / 8][4];
#pragma unroll
        for (int n8 = 0; n8 < P1 / 8; ++n8)
        {
            const f32x2 wx = ld_table(W.wx + (n8 * 4 + t) * 3 + 0);
            const f32x2 wy = ld_table(W.wx + (n8 * 4 + t) * 3 + 1);
            const f32x2 wz = ld_table(W.wx + (n8 * 4 + t) * 3 + 2);
#pragma unroll
            for (int i = 0; i < 2; ++i)
            {
                const f32x2 b = ld_table((const f32x2*)(pre + (size_t)path[i] * P1 + 8 * n8 + 2 * t));
                h[0][n8][2 * i + 0] = relu(b.x + wx.x * x[i][0] + wy.x * x[i][1] + wz.x * x[i][2]);
                h[0][n8][2 * i + 1] = relu(b.y + wx.y * x[i][0] + wy.y * x[i][1] + wz.y * x[i][2]);
            }
        }
        u32 a1[1][P1 / 16][4];
        to_a<1, P1 / 8>(h, a1);
        u32 a2[1][P2 / 16][4];
        hidden_layer<1, P1 / 16, P2 / 8>(a1, W.w1, W.b1, a2);
        u32 a3[1][P3 / 16][4];
        hidden_layer<1, P2 / 16, P3 / 8>(a2, W.w2, W.b2, a3);
        float y[1][1][4];
        zero<1, 1>(y);
        dense<1, P3 / 16, 1>(a3, W.w3, 2, 0, 0, y);
        // lane t holds output columns 2t, 2t+1 of rows g and g+8: columns 0, 1 (t = 0) and 2 (t = 1) are xyz
        if (t < 2)
        {
#pragma unroll
            for (int i = 0; i < 2; ++i)
            {
                if (!ok[i])
                    continue;
                const float w = W.window != 0.0f ? sinpi_(u[i]) : 1.0f;
                const float hi[3] = {f.hx, f.hy, f.hz}, lo[3] = {f.lx, f.ly, f.lz};
#pragma unroll
                for (int j = 0; j < 2; ++j)
                {
                    const int col = 2 * t + j;
                    if (col < 3)
                    {
                        const float v = y[0][0][2 * i + j] * w + W.residual * x[i][col];
                        out[(size_t)r[i] * 3 + col] = (v * f.dscale + lo[col]) + hi[col];  // from the network frame
                    }
                }
            }
        }
    }
}

}  // namespace ngf
