"""The NeuroGF networks on tensor cores: fused per-warp MLP kernels for every batch query.

One warp takes 16 rows (points, vertices or pairs) from the point coordinates to the answer in registers:
fp16 x fp16 -> fp32 ``mma.sync`` per layer, BatchNorm-folded bias and ReLU in fp32, the result rounded to fp16
for the next layer. Warps are persistent (the grid is sized to the GPU) and read the packed weights from L1.
The device code is ``native/neurogf_mma.h``; this module packs the weights, groups the kernel arguments into
structs and launches.

Why native code: Warp's tile API (cuBLASDx ``tile_matmul``) stages every operand and result in shared memory and
cannot keep a layer's output in registers as the next layer's input (docs/design.md).

Numerics: coordinates and Fourier features enter the first layer as fp16 high + low parts (fp32-accurate input),
weights and activations are fp16, sums fp32, the last layer an fp32 dot product. Vertex embeddings kept for
repeated queries are fp16 (the same rounding as in the fused kernels, so both give the same answers).

The same kernels run on Warp's CPU device, each warp as 32 cooperative fibers with the warp-wide operations
emulated; that form is slow and exists so the tests can check the GPU code's data movement against float64.
"""

import contextlib
import dataclasses
import functools
import re
from pathlib import Path

import numpy as np
import warp as wp

from . import mlp

# the landmark networks' constants (neurogf_warp/model/network.py; the kernels package does not import the library)
LANDMARK_UNREACHED = 4.0  # a table entry across components: an upper bound at 2x this means no landmark reaches
LANDMARK_WIDTH_MAX = 8.0  # the log-ratio head input stops here

HEADER = (Path(__file__).resolve().parent / "native" / "neurogf_mma.h").read_text()
BUILD = wp.ModuleBuildOptions(extra_cuda_preamble=HEADER, extra_cpu_preamble=HEADER)
MODULE_OPTIONS = {"extra_build_options": BUILD, "enable_backward": False}

SUPPORTED_D = (64, 128, 256)  # D = 512 would need 128 registers per lane for one tile's embeddings
FP16_MAX = 65504.0
BLOCK_THREADS = 128  # 4 warps per block on CUDA


@dataclasses.dataclass(frozen=True)
class Tuning:
    """Tile shapes and grid sizes of the tensor-core kernels: fixed when an engine is built and passed to every
    launch (``benchmarks/queries.py --tune`` times the alternatives; every layout gives the same numbers)."""

    ssad: tuple = (2, False)   # (m-tiles per warp, prefetch) of the single-source kernel on kept embeddings
    source_group: int = 2      # sources that share each weight load in the multi-source kernels
    # registers per thread at most (0: the compiler's choice) of the single-source kernel on kept embeddings and of
    # the multi-source kernels: more resident warps, but on an H200 the spills (or one source per weight load) cost
    # more than the warps gain, so the default leaves the compiler's choice (255 and 254 registers, 8 warps per SM)
    regs_ssad: int = 0
    regs_distance: int = 0
    lift_ssad: tuple = (1, 8)  # (m-tiles per warp, n-tiles per chunk) of the single-source kernel, rows lifted
    sdf_tile: tuple = (2, 4)   # (m-tiles per warp, n-tiles per chunk) of the SDF kernel
    pair_nc: int = 8           # n-tiles per chunk of the pair kernel (two m-tiles: p and q)
    # persistent warps per multiprocessor of each kernel (the register use allows 8-20)
    warps_ssad: int = 16
    warps_lift_ssad: int = 16
    warps_distance: int = 16
    warps_pairs: int = 16
    warps_sdf: int = 16
    warps_other: int = 16      # embeddings and the path head
    cpu_warps: int = 1         # the CPU emulation runs this many warps (32 fibers each) through all tiles
    # (m-tiles per warp, prefetch of the embeddings) and persistent warps per multiprocessor of a landmark network's
    # single-source kernel on kept embeddings (its table rows stream after the embeddings, so it has a tuning of its
    # own; its register cap is regs_ssad)
    landmark_ssad: tuple = (2, False)
    warps_landmark_ssad: int = 16


@wp.struct
class Lifting:
    """Packed lifting F -> D/4 -> D/2 -> D: fragment-ordered fp16 weights (uint32 pairs), lane-ordered biases."""

    w0: wp.array(dtype=wp.uint32)
    b0: wp.array(dtype=wp.float32)
    w1: wp.array(dtype=wp.uint32)
    b1: wp.array(dtype=wp.float32)
    w2: wp.array(dtype=wp.uint32)
    b2: wp.array(dtype=wp.float32)
    octaves: int


@wp.struct
class Head:
    """Packed head D -> D/4 -> D/4 -> 1 (the last layer as lane-ordered fp32 weights)."""

    w0: wp.array(dtype=wp.uint32)
    b0: wp.array(dtype=wp.float32)
    w1: wp.array(dtype=wp.uint32)
    b1: wp.array(dtype=wp.float32)
    w2: wp.array(dtype=wp.float32)


@wp.struct
class Rows:
    """The rows of a distance query: points (in the frame the kernel is given), their kept packed embeddings
    (empty: computed in the kernel), component labels (empty: one component)."""

    pts: wp.array(dtype=wp.vec3)
    cached: wp.array(dtype=wp.uint32)
    comp: wp.array(dtype=wp.int32)
    n: int


@wp.struct
class Sources:
    """Tables the sources of a distance query are rows of: packed fp16 embeddings (R * D/2 uint32), frame-coordinate
    points (R,), component labels (R,) or empty. A call names its rows (``src_ids``, or ``src_row`` + s)."""

    emb: wp.array(dtype=wp.uint32)
    pos: wp.array(dtype=wp.vec3)
    comp: wp.array(dtype=wp.int32)


REDUCE_MIN = 1  # flags of a distance launch: one value per row, the nearest source
RAW = 2         # the network's own value (no clamping, no exact 0 at the source)
# (the native code reads these bits through _DISTANCE_CPP, which is written from these two names)


# ---- host-side packing -------------------------------------------------------------------------------------------

def _to_fp16(a: np.ndarray, what: str) -> np.ndarray:
    if not np.all(np.isfinite(a)) or np.abs(a).max(initial=0.0) > FP16_MAX:
        raise ValueError(f"{what} has values beyond the fp16 range (|w| <= {FP16_MAX:g}); use precision='fp32'")
    return a.astype(np.float16)


def pack_weights(W: np.ndarray, what: str = "weights", n_multiple: int = 8) -> np.ndarray:
    """(N, K) weights -> uint32 (KS, NT/2, 32, 4): the B fragments of every (k-step, n-tile), lane by lane.

    Lane 4g + t of n-tile n holds b0 = (W[8n+g, 16k+2t], W[8n+g, 16k+2t+1]) and b1 = the same 8 columns further,
    fp16 pairs with the lower column in the low half; n-tiles 2j and 2j + 1 sit side by side, so a lane reads
    both with one 16-byte load. N is padded with zero rows to a multiple of ``n_multiple`` (16 where the output
    feeds another layer, whose k-steps are 16 wide) and to an even number of n-tiles; K to a multiple of 16.
    """
    N, K = W.shape
    NT = -(-N // n_multiple) * n_multiple // 8
    KS, NT = -(-K // 16), NT + (NT & 1)
    Wp = np.zeros((NT * 8, KS * 16))
    Wp[:N, :K] = W
    h = _to_fp16(Wp, what).view(np.uint16).astype(np.uint32)
    lane = np.arange(32)
    g, t = lane >> 2, lane & 3
    rows = (np.arange(NT)[:, None] * 8 + g[None, :])[None, :, :]           # (1, NT, 32)
    col = (np.arange(KS)[:, None, None] * 16 + 2 * t[None, None, :])       # (KS, 1, 32)
    b0 = h[rows, col] | (h[rows, col + 1] << 16)
    b1 = h[rows, col + 8] | (h[rows, col + 9] << 16)
    frag = np.stack([b0, b1], axis=-1)                                      # (KS, NT, 32, 2)
    pairs = frag.reshape(KS, NT // 2, 2, 32, 2).transpose(0, 1, 3, 2, 4)   # (KS, NT/2, 32, n-tile, word)
    return np.ascontiguousarray(pairs.reshape(KS, NT // 2, 32, 4), dtype=np.uint32)


def pack_lanes(v: np.ndarray, n_multiple: int = 8) -> np.ndarray:
    """(N, ...) per-column values -> float32 (NT, 4, 2, ...): lane t of n-tile n holds columns 8n + 2t and 8n + 2t + 1
    (the trailing axes, e.g. xyz, go last: (NT, 4, 3, 2) for (N, 3) input)."""
    v = np.asarray(v, dtype=np.float64)
    NT = -(-len(v) // n_multiple) * n_multiple // 8
    p = np.zeros((NT * 8,) + v.shape[1:])
    p[: len(v)] = v
    p = p.reshape((NT, 4, 2) + v.shape[1:])
    if v.ndim == 2:
        p = p.transpose(0, 1, 3, 2)
    return np.ascontiguousarray(p, dtype=np.float32)


def split_input_columns(W0: np.ndarray) -> np.ndarray:
    """First lifting layer for high/low fp16 input pairs: every input column twice (columns 2j and 2j+1)."""
    return np.repeat(W0, 2, axis=1)


def input_ksteps(n_features: int) -> int:
    return -(-2 * n_features // 16)


def _arr(a, dtype, device):
    return wp.array(np.ascontiguousarray(a).reshape(-1), dtype=dtype, device=device)


def lifting_struct(layers, octaves: int, device) -> Lifting:
    """layers: [(W, b)] x 3 folded float64 lifting layers."""
    (W0, b0), (W1, b1), (W2, b2) = layers
    L = Lifting()
    L.w0 = _arr(pack_weights(split_input_columns(W0), "lifting layer 0"), wp.uint32, device)
    L.b0 = _arr(pack_lanes(b0), wp.float32, device)
    L.w1 = _arr(pack_weights(W1, "lifting layer 1"), wp.uint32, device)
    L.b1 = _arr(pack_lanes(b1), wp.float32, device)
    L.w2 = _arr(pack_weights(W2, "lifting layer 2"), wp.uint32, device)
    L.b2 = _arr(pack_lanes(b2), wp.float32, device)
    L.octaves = int(octaves)
    return L


def head_struct(layers, device) -> Head:
    """layers: [(W0, b0), (W1, b1), (W2, None)] folded float64 head layers."""
    (W0, b0), (W1, b1), (W2, _) = layers
    H = Head()
    H.w0 = _arr(pack_weights(W0, "head layer 0"), wp.uint32, device)
    H.b0 = _arr(pack_lanes(b0), wp.float32, device)
    H.w1 = _arr(pack_weights(W1, "head layer 1"), wp.uint32, device)
    H.b1 = _arr(pack_lanes(b1), wp.float32, device)
    H.w2 = _arr(pack_lanes(W2.reshape(-1)), wp.float32, device)
    return H


# ---- landmark networks ----------------------------------------------------------------------------------------------

LANDMARK_K = tuple(range(16, 257, 16))  # landmark counts of the native kernels: whole k-steps, up to MAX_LANDMARKS
LANDMARK_FORMS = {"plain": 0, "bracket": 1, "bracket_log": 2}


def landmark_columns() -> np.ndarray:
    """The table column that mma column c (0..15) of a landmark k-step carries: lane t loads floats 4t .. 4t+3 of a
    16-column block and puts the first two in columns 2t, 2t+1 of the A fragment, the other two in 2t+8, 2t+9."""
    c = np.arange(16)
    t, lane_half = (c % 8) // 2, c // 8
    return 4 * t + 2 * lane_half + c % 2


def landmark_first_layer(W0: np.ndarray, D: int, K: int) -> np.ndarray:
    """A landmark head's first layer (H, D + K + 2 [+ 2]) as the kernel's k-steps see it (H, D + K + 16): the
    embedding columns as they are, each 16 landmark columns permuted to the lanes' loads (``landmark_columns``), then
    every scalar input (lower, upper [, |s - q|, log-ratio]) twice, for its fp16 high and low parts."""
    H, n_in = W0.shape
    scalars = n_in - D - K
    if K % 16 or scalars not in (2, 4):
        raise ValueError(f"a landmark head's first layer must be (H, D + K + 2 or 4) with K in {LANDMARK_K}, "
                         f"got {W0.shape} for D={D}, K={K}")
    out = np.zeros((H, D + K + 16))
    out[:, :D] = W0[:, :D]
    perm = landmark_columns()
    for j in range(K // 16):
        out[:, D + 16 * j: D + 16 * j + 16] = W0[:, D + 16 * j + perm]
    out[:, D + K: D + K + 2 * scalars] = np.repeat(W0[:, D + K:], 2, axis=1)
    return out


def landmark_head_struct(layers, D: int, K: int, device) -> Head:
    """``head_struct`` of a landmark network's distance head: its first layer packed by ``landmark_first_layer``
    (D/16 + K/16 + 1 k-steps), the rest as in every head."""
    (W0, b0), *rest = layers
    return head_struct([(landmark_first_layer(W0, D, K), b0), *rest], device)


@wp.struct
class PathHead:
    """Packed path head: guidance 2D -> D, the point layer split into guidance (D -> P1) and xyz (3 -> P1) columns,
    then P1 -> P2 -> P3 -> 3; ``residual`` / ``window`` as in network.NeuroGFNet."""

    wc: wp.array(dtype=wp.uint32)
    bc: wp.array(dtype=wp.float32)
    wg: wp.array(dtype=wp.uint32)
    b0: wp.array(dtype=wp.float32)
    wx: wp.array(dtype=wp.float32)
    w1: wp.array(dtype=wp.uint32)
    b1: wp.array(dtype=wp.float32)
    w2: wp.array(dtype=wp.uint32)
    b2: wp.array(dtype=wp.float32)
    w3: wp.array(dtype=wp.uint32)
    residual: float
    window: float


def path_widths(layers) -> tuple:
    """(P1, P2, P3) of a path head as the kernels see them (P3 padded to 16)."""
    P1, P2, P3 = (layers[i][0].shape[0] for i in range(3))
    return P1, P2, -(-P3 // 16) * 16


def path_struct(guidance, layers, residual: bool, window: bool, device) -> PathHead:
    """guidance: folded (Wc, bc); layers: folded point-wise layers [(W0, b0), (W1, b1), (W2, b2), (W3, None)]."""
    (Wc, bc), (W0, b0), (W1, b1), (W2, b2), (W3, _) = guidance, *layers
    P = PathHead()
    P.wc = _arr(pack_weights(Wc, "path guidance"), wp.uint32, device)
    P.bc = _arr(pack_lanes(bc), wp.float32, device)
    P.wg = _arr(pack_weights(W0[:, 3:], "path layer 0"), wp.uint32, device)
    P.b0 = _arr(pack_lanes(b0), wp.float32, device)  # also the natural order: column c at 8n + 2t + j = c
    P.wx = _arr(pack_lanes(W0[:, :3]), wp.float32, device)
    P.w1 = _arr(pack_weights(W1, "path layer 1", 16), wp.uint32, device)
    P.b1 = _arr(pack_lanes(b1, 16), wp.float32, device)
    P.w2 = _arr(pack_weights(W2, "path layer 2", 16), wp.uint32, device)
    P.b2 = _arr(pack_lanes(b2, 16), wp.float32, device)
    W3p = np.zeros((W3.shape[0], -(-W3.shape[1] // 16) * 16))
    W3p[:, : W3.shape[1]] = W3
    P.w3 = _arr(pack_weights(W3p, "path layer 3"), wp.uint32, device)
    P.residual = 1.0 if residual else 0.0
    P.window = 1.0 if window else 0.0
    return P


def empty_int(device) -> wp.array:
    return wp.empty(0, dtype=wp.int32, device=device)


def empty_words(device) -> wp.array:
    return wp.empty(0, dtype=wp.uint32, device=device)


# ---- the native structs, read from the header -----------------------------------------------------------------------
# A packed-weight struct is declared twice, as a @wp.struct here and as a C++ struct in the header; the C++
# initializer that turns one into the other is written from both declarations, which must name the same fields
# in the same order (checked when this module is imported, and by tests/test_inference_contracts.py).

def native_fields(struct: str) -> list:
    """[(C++ type, field name)] of ``struct NAME { ... };`` in the header, in declaration order."""
    m = re.search(r"^struct\s+(?:alignas\(\d+\)\s+)?" + struct + r"\s*\{(.*?)^\};", HEADER, re.S | re.M)
    if m is None:
        raise RuntimeError(f"native/neurogf_mma.h declares no struct {struct}")
    out = []
    body = re.sub(r"\{[^{}]*\}", ";", re.sub(r"//[^\n]*", "", m.group(1)))  # comments and function bodies out
    for decl in body.split(";"):
        decl = decl.strip()
        if not decl or "(" in decl:  # member functions are not fields
            continue
        head, names = re.match(r"((?:const\s+)?[\w:]+\s*\**)\s*(.*)", decl, re.S).groups()
        out += [(" ".join(head.replace("*", " *").split()), n.strip()) for n in names.split(",")]
    return out


def native_initializer(py_struct, native: str, var: str, name: str) -> str:
    """C++ ``ngf::NATIVE NAME = {...};`` from the wp.struct value ``var``: arrays pass their data pointers cast to the
    header's field types, scalars their values. Refuses structs whose fields differ."""
    fields = native_fields(native)
    py = list(py_struct.vars)
    if [f for _, f in fields] != py:
        raise RuntimeError(f"the fields of ngf::{native} {[f for _, f in fields]} differ from those of "
                           f"{py_struct.__name__} {py}: change both together")
    parts = []
    for ctype, f in fields:
        if ctype.endswith("*"):  # e.g. "const u32x2 *": a pointer to one of the header's types
            *const, base, _ = ctype.split()
            parts.append(f"({' '.join(const + ['ngf::' + base])}*){var}.{f}.data")
        else:
            parts.append(f"{var}.{f}")
    return f"    ngf::{native} {name} = {{{', '.join(parts)}}};\n"


# ---- kernels -------------------------------------------------------------------------------------------------------

def native_init(native: str, name: str, values: dict) -> str:
    """C++ ``ngf::NATIVE NAME = {...};`` from {field name: C++ expression}, in the header's field order; refuses a
    missing or unknown field (for native structs assembled from several kernel arguments)."""
    fields = [f for _, f in native_fields(native)]
    if sorted(fields) != sorted(values):
        raise RuntimeError(f"ngf::{native} has fields {fields}, the kernel gives {list(values)}: change both together")
    return f"    ngf::{native} {name} = {{{', '.join(values[f] for f in fields)}}};\n"


def _frame_cpp(name: str) -> str:
    """ngf::Frame F from an ``mlp.Frame`` argument."""
    return native_init("Frame", "F", {"cx": f"{name}.center[0]", "cy": f"{name}.center[1]", "cz": f"{name}.center[2]",
                                      "xscale": f"{name}.xscale", "dscale": f"{name}.dscale", "limit": f"{name}.limit",
                                      **{f"h{x}": f"{name}.hi[{i}]" for i, x in enumerate("xyz")},
                                      **{f"l{x}": f"{name}.lo[{i}]" for i, x in enumerate("xyz")}})


_STRUCTS_CPP = native_initializer(Lifting, "Lifting", "lift", "L") + native_initializer(Head, "Head", "head", "H")
_PATH_CPP = native_initializer(PathHead, "PathWeights", "ph", "W")


def _unique(fn, name):
    fn.__name__ = fn.__qualname__ = name
    return fn


_DISTANCE_CPP = native_init("Sources", "S", {
    "emb": "(const ngf::u32x4*)src.emb.data", "pos": "(const float*)src.pos.data",
    "comp": "src.comp.shape[0] ? (const int*)src.comp.data : nullptr",
    "ids": "src_ids.shape[0] ? (const int*)src_ids.data : nullptr", "row0": "src_row", "count": "n_src"}) + \
    native_init("DistanceOut", "O", {
        "out": "(float*)out.data", "ld": "ld", "reduce_min": f"(flags & {REDUCE_MIN}) ? 1 : 0", "euclid": "euclid",
        "row_comp": "rows.comp.shape[0] ? (const int*)rows.comp.data : nullptr", "raw": f"(flags & {RAW}) ? 1 : 0"})


def _distance_kernel(call: str, name: str, max_regs: int = 0):
    """A distance kernel around the native call ``call`` (uses L, H, F, S, O and rows); ``max_regs``: registers per
    thread at most (0: the compiler's choice), spilling to shared memory, for more resident warps."""
    snippet = _STRUCTS_CPP + _frame_cpp("frame") + _DISTANCE_CPP + call

    def body(lift: Lifting, head: Head, frame: mlp.Frame, rows: Rows, src: Sources, src_ids: wp.array(dtype=wp.int32),
             src_row: int, n_src: int, out: wp.array(dtype=wp.float32), ld: int, flags: int, euclid: float, tid: int,
             n_warps: int): ...

    native = wp.func_native(snippet)(_unique(body, name + (f"_r{max_regs}" if max_regs else "")))
    regs = dict(cuda_max_registers=max_regs, enable_cuda_smem_spilling=True) if max_regs else {}

    @wp.kernel(module="unique", module_options=MODULE_OPTIONS, **regs)
    def distance_rows(lift: Lifting, head: Head, frame: mlp.Frame, rows: Rows, src: Sources,
                      src_ids: wp.array(dtype=wp.int32), src_row: int, n_src: int, out: wp.array(dtype=wp.float32),
                      ld: int, flags: int, euclid: float, n_warps: int):
        native(lift, head, frame, rows, src, src_ids, src_row, n_src, out, ld, flags, euclid, wp.tid(), n_warps)

    return distance_rows


def param_index(kernel) -> dict:
    """{parameter name: position} of a kernel, for updating a recorded launch (``wp.Launch.set_param_at_index``)
    by name; the warp count that ``launch`` appends is the last parameter."""
    return {a.label: i for i, a in enumerate(kernel.adj.args)}


@functools.lru_cache(maxsize=None)
def distance_kernel(D: int, ks0: int, lift: bool, sp: int = 1, max_regs: int = 0):
    """Distances from S sources to N rows: lifted points (``lift``) or kept packed vertex embeddings; ``sp``
    sources share each weight load; ``max_regs`` as in ``_distance_kernel``."""
    call = f"""
    ngf::distance_rows<{D}, {ks0}, {'true' if lift else 'false'}, {sp}>(L, H, F, (const float*)rows.pts.data,
        (const ngf::u32x4*)rows.cached.data, rows.n, S, O, tid >> 5, n_warps);
"""
    return _distance_kernel(call, f"ngf_distance_rows_{D}_{ks0}_{int(lift)}_{sp}", max_regs)


@functools.lru_cache(maxsize=None)
def ssad_kernel(D: int, mt: int = 1, prefetch: bool = False, max_regs: int = 0):
    """One source to every row of kept packed embeddings, mt m-tiles per warp, optionally loading the next tile
    during this one (same arguments as distance_kernel)."""
    call = f"""
    ngf::ssad_rows<{D}, {mt}, {'true' if prefetch else 'false'}>(H, F, (const float*)rows.pts.data,
        (const ngf::u32x4*)rows.cached.data, rows.n, S, O, tid >> 5, n_warps);
"""
    return _distance_kernel(call, f"ngf_ssad_rows_{D}_{mt}_{int(prefetch)}", max_regs)


@functools.lru_cache(maxsize=None)
def lift_ssad_kernel(D: int, ks0: int, mt: int = 1, nc: int = 8):
    """One source to N points embedded in the kernel, chunk by chunk (same arguments as distance_kernel)."""
    call = f"""
    ngf::lift_ssad_rows<{D}, {ks0}, {mt}, {nc}>(L, H, F, (const float*)rows.pts.data, rows.n, S, O, tid >> 5, n_warps);
"""
    return _distance_kernel(call, f"ngf_lift_ssad_rows_{D}_{ks0}_{mt}_{nc}")


@functools.lru_cache(maxsize=None)
def landmark_ssad_kernel(D: int, K: int, mt: int = 2, prefetch: bool = False, max_regs: int = 0):
    """One source to every row of kept packed embeddings for a landmark network with K landmarks: ``table`` (V, K)
    float32 rows of the bound vertices, the source its row ``src_row``; ``form`` (``LANDMARK_FORMS``), ``floor``,
    ``pair_inputs`` as in network.NeuroGFNet; ``flags`` takes ``RAW`` only."""
    if K not in LANDMARK_K:
        raise ValueError(f"K = {K} landmarks: the tensor-core kernels support K in {LANDMARK_K} (multiples of 16 up "
                         "to 256)")
    snippet = native_initializer(Head, "Head", "head", "H") + _frame_cpp("frame") + native_init("Sources", "S", {
        "emb": "(const ngf::u32x4*)src.emb.data", "pos": "(const float*)src.pos.data",
        "comp": "src.comp.shape[0] ? (const int*)src.comp.data : nullptr", "ids": "nullptr", "row0": "src_row",
        "count": "1"}) + native_init("DistanceOut", "O", {
        "out": "(float*)out.data", "ld": "rows.n", "reduce_min": "0", "euclid": "0.0f",
        "row_comp": "rows.comp.shape[0] ? (const int*)rows.comp.data : nullptr", "raw": f"(flags & {RAW}) ? 1 : 0"}) + \
        native_init("LandmarkNet", "M", {
            "table": "(const float*)table.data", "floor_scale": "lm_floor", "euclid": "euclid",
            "unreached": f"{2.0 * LANDMARK_UNREACHED!r}f", "form": "form", "pair_inputs": "pair_inputs",
            "width_max": f"{LANDMARK_WIDTH_MAX!r}f"}) + f"""
    ngf::landmark_ssad_rows<{D}, {K}, {mt}, {'true' if prefetch else 'false'}>(H, F, (const float*)rows.pts.data,
        (const ngf::u32x4*)rows.cached.data, rows.n, S, M, O, tid >> 5, n_warps);
"""

    def body(head: Head, frame: mlp.Frame, rows: Rows, src: Sources, src_row: int, table: wp.array(dtype=wp.float32),
             lm_floor: float, euclid: float, form: int, pair_inputs: int, out: wp.array(dtype=wp.float32), flags: int,
             tid: int, n_warps: int): ...

    name = f"ngf_landmark_ssad_rows_{D}_{K}_{mt}_{int(prefetch)}" + (f"_r{max_regs}" if max_regs else "")
    native = wp.func_native(snippet)(_unique(body, name))
    regs = dict(cuda_max_registers=max_regs, enable_cuda_smem_spilling=True) if max_regs else {}

    @wp.kernel(module="unique", module_options=MODULE_OPTIONS, **regs)
    def landmark_ssad_rows(head: Head, frame: mlp.Frame, rows: Rows, src: Sources, src_row: int,
                           table: wp.array(dtype=wp.float32), lm_floor: float, euclid: float, form: int,
                           pair_inputs: int, out: wp.array(dtype=wp.float32), flags: int, n_warps: int):
        native(head, frame, rows, src, src_row, table, lm_floor, euclid, form, pair_inputs, out, flags, wp.tid(),
               n_warps)

    return landmark_ssad_rows


def _points_kernel(call: str, name: str, out_dtype):
    """A kernel (lift, head, frame, pts, n, out, n_warps) around the native call ``call`` over N points."""
    snippet = _STRUCTS_CPP + _frame_cpp("frame") + call

    def body(lift: Lifting, head: Head, frame: mlp.Frame, pts: wp.array(dtype=wp.vec3), n: int,
             out: wp.array(dtype=out_dtype), tid: int, n_warps: int): ...

    native = wp.func_native(snippet)(_unique(body, name))

    @wp.kernel(module="unique", module_options=MODULE_OPTIONS)
    def point_rows(lift: Lifting, head: Head, frame: mlp.Frame, pts: wp.array(dtype=wp.vec3), n: int,
                   out: wp.array(dtype=out_dtype), n_warps: int):
        native(lift, head, frame, pts, n, out, wp.tid(), n_warps)

    return point_rows


@functools.lru_cache(maxsize=None)
def embed_kernel(D: int, ks0: int):
    """Packed fp16 embeddings (N, D/2 uint32) of N points."""
    return _points_kernel(f"""
    ngf::embed_rows<{D}, {ks0}>(L, F, (const float*)pts.data, n, (ngf::u32x4*)out.data, tid >> 5, n_warps);
""", f"ngf_embed_rows_{D}_{ks0}", wp.uint32)


@functools.lru_cache(maxsize=None)
def embed_point_kernel(D: int, ks0: int):
    """Packed fp16 embedding (D/2 uint32) of one point given as a launch parameter, which is also written to
    pos[0] (and the label c to comp[0] when comp is not empty): a single source's tables, made without a copy from
    the host (which would wait for the stream's earlier work) in one launch."""
    snippet = _STRUCTS_CPP + _frame_cpp("frame") + f"""
    const float p[3] = {{pt[0], pt[1], pt[2]}};
    if (tid == 0)
    {{
        pos.data[0] = pt;
        if (comp.shape[0] > 0)
            comp.data[0] = c;
    }}
    ngf::embed_rows<{D}, {ks0}>(L, F, p, 1, (ngf::u32x4*)out.data, tid >> 5, n_warps);
"""

    def body(lift: Lifting, head: Head, frame: mlp.Frame, pt: wp.vec3, c: int, pos: wp.array(dtype=wp.vec3),
             comp: wp.array(dtype=wp.int32), out: wp.array(dtype=wp.uint32), tid: int, n_warps: int): ...

    native = wp.func_native(snippet)(_unique(body, f"ngf_embed_point_{D}_{ks0}"))

    @wp.kernel(module="unique", module_options=MODULE_OPTIONS)
    def embed_point(lift: Lifting, head: Head, frame: mlp.Frame, pt: wp.vec3, c: int, pos: wp.array(dtype=wp.vec3),
                    comp: wp.array(dtype=wp.int32), out: wp.array(dtype=wp.uint32), n_warps: int):
        native(lift, head, frame, pt, c, pos, comp, out, wp.tid(), n_warps)

    return embed_point


@functools.lru_cache(maxsize=None)
def pair_kernel(D: int, ks0: int, nc: int = 4):
    """Distances between point pairs (p_i, q_i), both lifted in the same warp."""
    snippet = _STRUCTS_CPP + _frame_cpp("frame") + f"""
    ngf::pair_rows<{D}, {ks0}, {nc}>(L, H, F, (const float*)ps.data, (const float*)qs.data, n, euclid, raw,
                                     (float*)out.data, tid >> 5, n_warps);
"""

    def body(lift: Lifting, head: Head, frame: mlp.Frame, ps: wp.array(dtype=wp.vec3), qs: wp.array(dtype=wp.vec3),
             n: int, euclid: float, raw: int, out: wp.array(dtype=wp.float32), tid: int, n_warps: int): ...

    native = wp.func_native(snippet)(_unique(body, f"ngf_pair_rows_{D}_{ks0}_{nc}"))

    @wp.kernel(module="unique", module_options=MODULE_OPTIONS)
    def pair_rows(lift: Lifting, head: Head, frame: mlp.Frame, ps: wp.array(dtype=wp.vec3),
                  qs: wp.array(dtype=wp.vec3), n: int, euclid: float, raw: int, out: wp.array(dtype=wp.float32),
                  n_warps: int):
        native(lift, head, frame, ps, qs, n, euclid, raw, out, wp.tid(), n_warps)

    return pair_rows


@functools.lru_cache(maxsize=None)
def sdf_kernel(D: int, ks0: int, mt: int = 1, nc: int = 8):
    """Signed distances of N points from the SDF head."""
    return _points_kernel(f"""
    ngf::sdf_rows<{D}, {ks0}, {mt}, {nc}>(L, H, F, (const float*)pts.data, n, (float*)out.data, tid >> 5, n_warps);
""", f"ngf_sdf_rows_{D}_{ks0}_{mt}_{nc}", wp.float32)


@functools.lru_cache(maxsize=None)
def path_pre_kernel(D: int, P1: int):
    """Per path: the guidance vector and the path-constant part of the point layer (N, P1) float32."""
    snippet = _PATH_CPP + f"""
    ngf::path_pre_rows<{D}, {P1}>(W, (const ngf::u32x4*)ep.data, (const ngf::u32x4*)eq.data, n, (float*)pre.data,
                                   tid >> 5, n_warps);
"""

    def body(ph: PathHead, ep: wp.array(dtype=wp.uint32), eq: wp.array(dtype=wp.uint32), n: int,
             pre: wp.array(dtype=wp.float32), tid: int, n_warps: int): ...

    native = wp.func_native(snippet)(_unique(body, f"ngf_path_pre_rows_{D}_{P1}"))

    @wp.kernel(module="unique", module_options=MODULE_OPTIONS)
    def path_pre_rows(ph: PathHead, ep: wp.array(dtype=wp.uint32), eq: wp.array(dtype=wp.uint32), n: int,
                      pre: wp.array(dtype=wp.float32), n_warps: int):
        native(ph, ep, eq, n, pre, wp.tid(), n_warps)

    return path_pre_rows


@functools.lru_cache(maxsize=None)
def path_points_kernel(P1: int, P2: int, P3: int):
    """m points of each of N paths (N, m, 3), mapped back by the frame (from_net)."""
    snippet = _PATH_CPP + _frame_cpp("frame") + f"""
    ngf::path_point_rows<{P1}, {P2}, {P3}>(W, F, (const float*)ps.data, (const float*)qs.data, (const float*)pre.data,
                                            n, m, (float*)out.data, tid >> 5, n_warps);
"""

    def body(ph: PathHead, frame: mlp.Frame, ps: wp.array(dtype=wp.vec3), qs: wp.array(dtype=wp.vec3),
             pre: wp.array(dtype=wp.float32), n: int, m: int, out: wp.array2d(dtype=wp.vec3), tid: int,
             n_warps: int): ...

    native = wp.func_native(snippet)(_unique(body, f"ngf_path_point_rows_{P1}_{P2}_{P3}"))

    @wp.kernel(module="unique", module_options=MODULE_OPTIONS)
    def path_point_rows(ph: PathHead, frame: mlp.Frame, ps: wp.array(dtype=wp.vec3), qs: wp.array(dtype=wp.vec3),
                        pre: wp.array(dtype=wp.float32), n: int, m: int, out: wp.array2d(dtype=wp.vec3),
                        n_warps: int):
        native(ph, frame, ps, qs, pre, n, m, out, wp.tid(), n_warps)

    return path_point_rows


# ---- launching -------------------------------------------------------------------------------------------------

@contextlib.contextmanager
def _cpu_blocks():
    """Warp runs a CPU block's lanes as cooperative fibers only while this flag is set."""
    old = wp.config.enable_cpu_blocks
    wp.config.enable_cpu_blocks = True
    try:
        yield
    finally:
        wp.config.enable_cpu_blocks = old


def warps_for(device, n_tiles: int, warps_per_sm: int, cpu_warps: int = 1) -> int:
    """Persistent warps for a launch over n_tiles tiles."""
    if device.is_cpu:
        return max(1, min(cpu_warps, n_tiles))
    cap = device.sm_count * warps_per_sm
    return max(1, min(cap, n_tiles))


def launch(kernel, n_tiles: int, inputs: list, device, warps_per_sm: int, cpu_warps: int = 1, record: bool = False):
    """Launch a per-warp kernel over n_tiles tiles; its last input is the warp count, appended here.

    record: return a ``wp.Launch`` to replay (parameters updated by position, ``param_index``) instead of
    launching; its warp count stays the one for n_tiles.
    """
    n_warps = warps_for(device, n_tiles, warps_per_sm, cpu_warps)
    kw = dict(dim=32 * n_warps, inputs=[*inputs, n_warps], device=device, record_cmd=record)
    if device.is_cpu:
        with _cpu_blocks():
            return wp.launch(kernel, block_dim=32, **kw)
    return wp.launch(kernel, block_dim=BLOCK_THREADS, **kw)
