"""The fast float32 kernels (kernels/generalizable/fast.py) one by one against float64 numpy on fresh random
inputs, on Warp's CPU device. Their CPU run is the same C++ body as on CUDA (virtual threads; the kNN's CPU
branch emulates the 32 lanes), so these check the GPU form's maths; sizes are small and not multiples of the
tiles, so the tails are exercised too."""
import numpy as np
import pytest
import torch
import warp as wp

from neurogf_warp.generalizable.encoder import WarpGenNet
from neurogf_warp.generalizable.network import GenNeuroGF
from neurogf_warp.kernels.generalizable.fast import PAIRS, kernels

DEV = "cpu"


def f32(a):
    return wp.array(np.ascontiguousarray(a, dtype=np.float32), dtype=wp.float32, device=DEV)


def topk_ref(f, k):
    """Exact k nearest (closest first, ties -> smaller index) by float64 distances of the float32 features."""
    d = ((f[:, None, :].astype(np.float64) - f[None, :, :]) ** 2).sum(-1)
    return np.argsort(d, axis=1, kind="stable")[:, :k]


@pytest.mark.parametrize("n,c,k", [(90, 5, 12), (70, 64, 40), (33, 3, 33)])
def test_knn_kernel(n, c, k):
    rng = np.random.default_rng(n)
    f = rng.standard_normal((n, c)).astype(np.float32)
    f[40 % n: 40 % n + 5] = f[0]  # exact duplicates: ties broken by the smaller index
    ft = np.concatenate([rng.standard_normal((2, n)), f.T], axis=0)  # channel-major; rows 2.. are the features
    nbr = wp.empty((n, k), dtype=wp.int32, device=DEV)
    wp.launch(kernels().knn, (n, 1), inputs=[f32(ft), 2, c, k, nbr], block_dim=1, device=DEV)
    got, want = nbr.numpy(), topk_ref(f, k)
    # float32 distances may order near-equal (not equal) candidates differently: compare where the float64
    # gap to the next candidate is clear
    d = np.sort(((f[:, None, :].astype(np.float64) - f[None]) ** 2).sum(-1), axis=1)
    m = min(k + 1, n)
    gap = np.diff(d[:, :m], axis=1)
    clear = np.all((gap > 1e-5 * (1 + d[:, 1:m])) | (gap == 0), axis=1)
    assert clear.mean() > 0.8
    np.testing.assert_array_equal(got[clear], want[clear])
    assert (got[:, 0] == np.arange(n))[:40 % n].all()


def test_edge2_kernel():
    """max_j relu(b + W relu(P_i + Q_j)) per point, and the channel-major copy."""
    rng = np.random.default_rng(1)
    n, k = 50, 40
    pq = rng.standard_normal((n, 128)).astype(np.float32)
    nbr = np.stack([rng.permutation(n)[:k] for _ in range(n)]).astype(np.int32)
    w = (rng.standard_normal((64, 64)) / 8).astype(np.float32)
    b = (rng.standard_normal(64) / 4).astype(np.float32)
    y = wp.zeros((n, 192), dtype=wp.float32, device=DEV)
    yt = wp.zeros((128, n), dtype=wp.float32, device=DEV)
    wp.launch(kernels().edge2, (n, 1), inputs=[f32(pq), wp.array(nbr, dtype=wp.int32, device=DEV), f32(w), f32(b),
                                                y, yt, 64], block_dim=1, device=DEV)
    P, Q = pq[:, :64].astype(np.float64), pq[:, 64:].astype(np.float64)
    E = np.maximum(P[:, None, :] + Q[nbr], 0)  # (n, k, 64)
    want = np.maximum(E @ w.T.astype(np.float64) + b, 0).max(axis=1)
    assert np.abs(y.numpy()[:, 64:128] - want).max() <= 1e-5 * np.abs(want).max()
    assert (y.numpy()[:, :64] == 0).all() and (y.numpy()[:, 128:] == 0).all()
    np.testing.assert_array_equal(yt.numpy()[64:128], y.numpy()[:, 64:128].T)


@pytest.mark.parametrize("rows,nin,nout,relu", [(70, 192, 320, 1), (1, 320, 128, 0), (33, 3, 128, 0)])
def test_linear_kernel(rows, nin, nout, relu):
    rng = np.random.default_rng(rows + nin)
    x = rng.standard_normal((rows, nin + 7)).astype(np.float32)
    w = (rng.standard_normal((nout, nin)) / np.sqrt(nin)).astype(np.float32)
    b = rng.standard_normal(nout).astype(np.float32)
    y = wp.zeros((rows, nout + 5), dtype=wp.float32, device=DEV)
    nob = (nout + 63) // 64
    nblk = (rows + 31) // 32 * nob
    wp.launch(kernels().linear, (nblk, 1), inputs=[f32(x), 7, f32(w), f32(b), relu, y, 5, nob], block_dim=1,
              device=DEV)
    want = x[:, 7:].astype(np.float64) @ w.T.astype(np.float64) + b
    if relu:
        want = np.maximum(want, 0)
    assert np.abs(y.numpy()[:, 5:] - want).max() <= 1e-5 * np.abs(want).max()
    assert (y.numpy()[:, :5] == 0).all()


def head_ref(g, wx, w0, b0, w1, b1, w2, s, t, i_s, i_t):
    """The query network in float64: |relu(G[i_s] + Wx s) - relu(G[i_t] + Wx t)| -> 128 -> 64 -> 1."""
    G, Wx = g.astype(np.float64), wx.astype(np.float64)
    d = np.abs(np.maximum(G[i_s] + s @ Wx.T, 0) - np.maximum(G[i_t] + t @ Wx.T, 0))
    h = np.maximum(d @ w0.T.astype(np.float64) + b0, 0)
    h = np.maximum(h @ w1.T.astype(np.float64) + b1, 0)
    return h @ w2[0].astype(np.float64)


@pytest.mark.parametrize("matrix", [False, True])
def test_pair_head_kernel(matrix):
    """Raw ratios, distances, matrix indexing, zero for equal points and inf across components; 2 tiles + a tail."""
    rng = np.random.default_rng(7 + matrix)
    n = 40
    g = rng.standard_normal((n, 128)).astype(np.float32)
    wx = rng.standard_normal((128, 3)).astype(np.float32)
    w0 = (rng.standard_normal((128, 128)) / 11).astype(np.float32)
    b0 = (rng.standard_normal(128) / 4).astype(np.float32)
    w1 = (rng.standard_normal((64, 128)) / 11).astype(np.float32)
    b1 = (rng.standard_normal(64) / 4).astype(np.float32)
    w2 = (rng.standard_normal((1, 64)) / 8).astype(np.float32)
    c, sc_ = np.array([0.5, -1.0, 2.0]), 0.25
    if matrix:
        S, T = rng.standard_normal((3, 3)) * 4, rng.standard_normal((2 * PAIRS // 3 + 5, 3)) * 4
        T[4] = S[1]
        a, bb = np.divmod(np.arange(len(S) * len(T)), len(T))
        n_t = len(T)
    else:
        S, T = rng.standard_normal((2 * PAIRS + 17, 3)) * 4, rng.standard_normal((2 * PAIRS + 17, 3)) * 4
        T[9] = S[9]
        a = bb = np.arange(len(S))
        n_t = 0
    S, T = S.astype(np.float32), T.astype(np.float32)
    si, ti = rng.integers(0, n, len(S)).astype(np.int32), rng.integers(0, n, len(T)).astype(np.int32)
    scomp, tcomp = np.zeros(len(S), np.int32), np.zeros(len(T), np.int32)
    scomp[2] = 1
    m = len(a)
    iarr = (lambda x: wp.array(x, dtype=wp.int32, device=DEV))
    e = iarr(np.zeros(0, np.int32))
    k = kernels()
    weights = [f32(g), f32(wx), f32(w0), f32(b0), f32(w1), f32(b1), f32(w2)]
    su = ((S.astype(np.float32) - c.astype(np.float32)) * np.float32(sc_)).astype(np.float64)
    tu = ((T.astype(np.float32) - c.astype(np.float32)) * np.float32(sc_)).astype(np.float64)
    r = head_ref(g, wx, w0, b0, w1, b1, w2, su[a], tu[bb], si[a], ti[bb])
    for raw in (1, 0):
        out = wp.empty(m, dtype=wp.float32, device=DEV)
        wp.launch(k.pair_head, (1, 1), inputs=[*weights, f32(S), iarr(si), iarr(scomp) if not raw else e, f32(T),
                                               iarr(ti), iarr(tcomp) if not raw else e, *c.tolist(), sc_, n_t, m,
                                               raw, 1, out], block_dim=1, device=DEV)
        got = out.numpy()
        if raw:
            assert np.abs(got - r).max() <= 1e-5 * np.abs(r).max()
        else:
            dist = np.maximum(r, 1) * np.linalg.norm(S[a].astype(np.float64) - T[bb], axis=1)
            inf = scomp[a] != tcomp[bb]
            zero = (S[a] == T[bb]).all(axis=1)
            assert np.isinf(got[inf]).all() and (got[zero & ~inf] == 0).all() and zero.any() and inf.any()
            ok = ~inf & ~zero
            assert (np.abs(got[ok] - dist[ok]) / dist[ok]).max() <= 1e-5


def test_fast_path_matches_generic_fp32():
    """WarpGenNet(fp32) with the fast kernels == the generic float32 SIMT kernels (fast=False) on a random
    network: features, neighbours, ratios, distances with precomputed nearest points."""
    torch.manual_seed(4)
    net = GenNeuroGF().double().eval()
    rng = np.random.default_rng(6)
    pts = rng.uniform(-1, 1, (150, 3))
    fast, slow = WarpGenNet(net, DEV, mode="fp32"), WarpGenNet(net, DEV, mode="fp32", fast=False)
    assert fast.fast and not slow.fast
    ef, es = fast.encode(pts), slow.encode(pts)
    for a_, b_ in zip(ef.neighbours, es.neighbours):
        assert (a_.numpy() == b_.numpy()).mean() > 0.98  # float32 rounding may swap near ties
    F, Fs = ef.feats.numpy(), es.feats.numpy()
    assert np.abs(F - Fs).max() <= 1e-4 * np.abs(Fs).max()
    s, t = rng.uniform(-1, 1, (300, 3)), rng.uniform(-1, 1, (300, 3))
    rf, rs = fast.ratio(ef, s, t).numpy(), slow.ratio(ef, s, t).numpy()  # same encoding: the query alone
    assert np.abs(rf - rs).max() <= 2e-5 * np.abs(rs).max()
    S, T = fast._arr(s * 2 + 1), fast._arr(t[:7] * 2 + 1)
    nn = fast.nearest(ef, fast._arr(t[:7]))
    df = fast.distances(ef, S, T, (1, 1, 1), 0.5, True, t_nn=nn).numpy()
    ds = slow.distances(ef, S, T, (1, 1, 1), 0.5, True, t_nn=nn).numpy()
    np.testing.assert_allclose(df, ds, rtol=2e-5)
