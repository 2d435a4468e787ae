"""The generalizable network's tensor-core pair head (precision="fp16", kernels/generalizable/tensorcore.py)
against float64 on fresh random inputs, on Warp's CPU device.

On the CPU the kernel runs as the per-mesh engine's warp emulation (32 fibers per warp, the mma emulated): the
same native code as on a GPU, so these tests check its fragment layout, column permutation and finishing rules.
With a GPU the same checks run there too (cuda:0).

Tolerances come from fp16 rounding: the weights and the activations entering each layer are rounded to fp16
(unit roundoff 2^-11 = 4.9e-4, sums in fp32), so a ratio carries an error of a few 1e-4 of the magnitude of the
last layer's terms (sum_o |w2_o| h_o; random ratios pass near 0, where a relative error means nothing). Measured
(CPU emulation; a GPU's mma sums in another order, same order of error): random weights, |error| / that
magnitude mean 0.6-1.3e-4, max 2.5-4.6e-4 (bounds 5e-4 and 2e-3); the released network on a 256-point cloud,
per-pair relative error of the distance mean 1.4e-4, max 7.5e-4 (bounds 4e-4 and 5e-3); on 2,048-point clouds
(benchmarks/generalizable.py's shapes) mean 3.7e-5, max 2.7e-4. A wrong weight layout (layer 0 packed without
the column permutation) is off by about the ratio itself (1.3 x max |ratio|) and fails.
"""
import numpy as np
import pytest
import torch
import trimesh
import warp as wp

import neurogf_warp as ngf
from neurogf_warp.generalizable.model import load, normalization
from neurogf_warp.kernels.generalizable import tensorcore as gtc

from .conftest import shared_path

DEVICES = (["cpu"] if wp.is_cpu_available() else []) + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])


def random_head(rng):
    return dict(wx=rng.standard_normal((128, 3)), w0=rng.standard_normal((128, 128)) / 11,
                b0=rng.standard_normal(128) / 4, w1=rng.standard_normal((64, 128)) / 11,
                b1=rng.standard_normal(64) / 4, w2=rng.standard_normal((1, 64)) / 8)


def head_ref(w, g, us, ut, si, ti):
    """The same network in float64: |relu(G[si] + Wx us) - relu(G[ti] + Wx ut)| -> 128 -> 64 -> 1; returns the
    ratio and the sum of the last layer's |terms| (the scale its rounding errors are relative to)."""
    fs = np.maximum(g[si] + us @ w["wx"].T, 0)
    ft = np.maximum(g[ti] + ut @ w["wx"].T, 0)
    h = np.maximum(np.abs(fs - ft) @ w["w0"].T + w["b0"], 0)
    h = np.maximum(h @ w["w1"].T + w["b1"], 0)
    return h @ w["w2"][0], h @ np.abs(w["w2"][0])


@pytest.mark.slow
@pytest.mark.parametrize("dev", DEVICES)
@pytest.mark.parametrize("storage,mt,nc", [("fp32", 1, 8), ("fp64", 1, 8), ("fp32", 2, 4), ("fp32", 1, 16)])
def test_kernel_random_weights(storage, mt, nc, dev):
    # (the warps-per-SM variants differ only in their CUDA launch bounds: the CPU code is the same)
    """Raw ratios, distances (matrix indexing, zero for equal points, inf across components) against float64;
    pair counts not a multiple of the tile, so the tail is exercised."""
    rng = np.random.default_rng([11, mt, nc, storage == "fp64"])
    n = 256
    w = random_head(rng)
    g = rng.standard_normal((n, 128))
    npd, T = (np.float32, wp.float32) if storage == "fp32" else (np.float64, wp.float64)
    arr = (lambda x: wp.array(np.ascontiguousarray(x, dtype=npd), dtype=T, device=dev))
    iarr = (lambda x: wp.array(np.asarray(x, np.int32), dtype=wp.int32, device=dev))
    e = iarr(np.zeros(0))
    H, wxp = gtc.pack_head(*w.values(), dev)
    k = gtc.pair_kernel(storage, mt, nc)
    c, sc_ = np.array([0.5, -1.0, 2.0]), 0.25
    # a matrix of 5 x 61 pairs (305): one target equals a source, one source in another component
    S, Tq = rng.standard_normal((5, 3)) * 4 + c, rng.standard_normal((61, 3)) * 4 + c
    Tq[7] = S[3]
    S, Tq = S.astype(npd), Tq.astype(npd)
    si, ti = rng.integers(0, n, len(S)), rng.integers(0, n, len(Tq))
    scomp, tcomp = np.zeros(len(S)), np.zeros(len(Tq))
    scomp[1] = 1
    a, b = np.divmod(np.arange(len(S) * len(Tq)), len(Tq))
    m = len(a)
    gs = g.astype(npd).astype(np.float64)
    unit = (lambda x: ((x - c.astype(npd)) * npd(sc_)).astype(np.float32).astype(np.float64))
    r, mag = head_ref(w, gs, unit(S)[a], unit(Tq)[b], si[a], ti[b])
    out = wp.empty(m, dtype=wp.float32, device=dev)
    args = [arr(gs), arr(S), iarr(si), e, arr(Tq), iarr(ti), e, c, sc_, len(Tq), m]
    gtc.launch_pairs(k, H, wxp, *args, True, out, dev, mt=mt)
    got = out.numpy().astype(np.float64)
    err = np.abs(got - r) / mag
    assert err.mean() <= 5e-4 and err.max() <= 2e-3, (err.mean(), err.max())
    # distances with the fast kernel's finishing rules
    args[3], args[6] = iarr(scomp), iarr(tcomp)
    gtc.launch_pairs(k, H, wxp, *args, False, out, dev, mt=mt)
    d = out.numpy()
    chord = np.linalg.norm(S[a].astype(np.float64) - Tq[b], axis=1)
    inf = scomp[a] != tcomp[b]
    zero = (S[a] == Tq[b]).all(axis=1)
    assert inf.sum() == len(Tq) and zero.sum() == 1
    assert np.isinf(d[inf]).all() and (d[zero] == 0).all()
    ok = ~inf & ~zero
    want = np.maximum(got, 1) * chord  # the kernel's own ratio, finished as fast.pair_head finishes
    np.testing.assert_allclose(d[ok], want[ok], rtol=2e-6)
    assert (d[ok] >= chord[ok] * (1 - 1e-6)).all()


@pytest.mark.parametrize("dev", DEVICES)
def test_kernel_pairs_equal_matrix(dev):
    """Pair mode (n_t = 0) on the expanded pairs gives bit for bit the matrix mode's values."""
    rng = np.random.default_rng(5)
    n = 64
    w = random_head(rng)
    H, wxp = gtc.pack_head(*w.values(), dev)
    g = wp.array(rng.standard_normal((n, 128)).astype(np.float32), dtype=wp.float32, device=dev)
    S, Tq = rng.standard_normal((3, 3)).astype(np.float32), rng.standard_normal((23, 3)).astype(np.float32)
    si, ti = rng.integers(0, n, 3).astype(np.int32), rng.integers(0, n, 23).astype(np.int32)
    a, b = np.divmod(np.arange(3 * 23), 23)
    f = (lambda x: wp.array(np.ascontiguousarray(x), dtype=wp.float32, device=dev))
    i = (lambda x: wp.array(np.ascontiguousarray(x), dtype=wp.int32, device=dev))
    e = i(np.zeros(0, np.int32))
    k = gtc.pair_kernel()
    dm = wp.empty(69, dtype=wp.float32, device=dev)
    dp = wp.empty(69, dtype=wp.float32, device=dev)
    gtc.launch_pairs(k, H, wxp, g, f(S), i(si), e, f(Tq), i(ti), e, (0, 0, 0), 1.0, 23, 69, False, dm, dev)
    gtc.launch_pairs(k, H, wxp, g, f(S[a]), i(si[a]), e, f(Tq[b]), i(ti[b]), e, (0, 0, 0), 1.0, 0, 69, False, dp, dev)
    np.testing.assert_array_equal(dm.numpy(), dp.numpy())


@pytest.fixture(scope="module")
def released():
    return load(shared_path("checkpoints", "official", "GenNeuroGF.pth"))


def shape(n, seed):
    """n points on a bumpy ellipsoid in arbitrary units (as benchmarks/generalizable.py's random_shape)."""
    rng = np.random.default_rng(seed)
    u = rng.standard_normal((n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    bump = 0.15 * np.sin(u @ rng.standard_normal((6, 3)).T).sum(axis=1, keepdims=True) / 3
    return u * (1 + bump) * np.array([1.0, 0.7, 0.5]) * 5.0 + np.array([2.0, -1.0, 3.0])


@pytest.mark.parametrize("dev,mode", [(d, m) for d in DEVICES for m in (["fp64", "fp32"] if d == "cpu" else ["fp32"])])
def test_released_network_fp16_vs_float64(released, dev, mode):
    """The public queries with precision="fp16" against the float64 torch network on a 256-point cloud; fp32
    (the default) is unchanged; matrix, ssad and msad agree with the pair call."""
    cloud = shape(256, 3)
    c, sc = normalization(cloud)
    rng = np.random.default_rng(8)
    m = 400
    P = cloud[rng.integers(0, 256, m)] + rng.standard_normal((m, 3)) * 0.05
    Q = cloud[rng.integers(0, 256, m)] + rng.standard_normal((m, 3)) * 0.05
    with torch.no_grad():
        ratio = released.net(*(torch.tensor((x - c) * sc)[None]
                               for x in (cloud, P, Q)))[0].numpy()
    want = np.maximum(ratio, 1) * np.linalg.norm(P - Q, axis=1)
    cond = released.condition(cloud, device=dev, mode=mode)
    d16 = cond.distance(P, Q, precision="fp16")
    rel = np.abs(d16 - want) / want
    assert rel.mean() <= 4e-4 and rel.max() <= 5e-3, (rel.mean(), rel.max())
    d32 = cond.distance(P, Q)
    np.testing.assert_array_equal(d32, cond.distance(P, Q, precision="fp32"))
    assert (np.abs(d32 - want) / want).max() <= 1e-3  # the fp32/fp64 path as before
    # s == t: exactly 0; a single pair gives a float
    assert (cond.distance(P[:20], P[:20], precision="fp16") == 0).all()
    assert isinstance(cond.distance(P[0], Q[0], precision="fp16"), float)
    # matrix = pair mode (same nearest points, same arithmetic per pair)
    D = cond.distance_matrix(P[:3], Q[:50], precision="fp16")
    np.testing.assert_array_equal(D[1], cond.distance(np.repeat(P[1:2], 50, 0), Q[:50], precision="fp16"))
    row = cond.ssad(4, precision="fp16")
    assert row[4] == 0
    np.testing.assert_array_equal(row, cond.distance(np.repeat(cloud[4:5], 256, 0), cloud, precision="fp16"))
    np.testing.assert_allclose(row, cond.ssad(4), rtol=5e-3)
    np.testing.assert_array_equal(cond.msad([4, 9], precision="fp16"),
                                  np.fmin(row, cond.ssad(9, precision="fp16")))


@pytest.mark.parametrize("dev", DEVICES)
def test_components_inf_and_bad_precision(released, dev):
    a = trimesh.creation.icosphere(subdivisions=1)
    b = trimesh.creation.icosphere(subdivisions=1)
    b.vertices += np.array([3.0, 0.0, 0.0])
    mesh = ngf.load_mesh((np.vstack([a.vertices, b.vertices]), np.vstack([a.faces, b.faces + len(a.vertices)])))
    cond = released.condition(mesh, n_points=200, seed=1, device=dev)
    na = len(a.vertices)
    row = cond.ssad(0, precision="fp16")
    assert np.isinf(row[na:]).all() and np.isfinite(row[:na]).all() and row[0] == 0
    np.testing.assert_allclose(row[1:na], cond.ssad(0)[1:na], rtol=5e-3)
    d = cond.distance([[1.02, 0.0, 0.0], [3.0, 0.0, 1.01]], [[0.0, 1.0, 0.0], [0.0, 1.0, 0.0]], precision="fp16")
    assert np.isfinite(d[0]) and np.isinf(d[1])
    for call in (lambda: cond.distance([0], [1], precision="fp8"), lambda: cond.ssad(0, precision="half"),
                 lambda: cond.msad([0], precision=None), lambda: cond.distance_matrix([0], precision="FP16"),
                 lambda: cond.wn.ratio(cond.enc, np.zeros((1, 3)), np.zeros((1, 3)), precision="bf16")):
        with pytest.raises(ValueError, match="unknown precision"):
            call()
