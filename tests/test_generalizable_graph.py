"""The generalizable encoder as a captured graph: ``WarpGenNet.encode`` without ``into`` replays one
graph per point count on CUDA and copies its outputs into the returned state, so conditioned shapes alive at the
same time stay independent. On the CPU the public call launches eagerly (checked as such); the graph machinery
itself is checked on the CPU too through Warp's CPU graphs (``WarpGenNet._graph_cpu``, a test switch), with the
fast float32 kernels. With a GPU the public-call checks run on cuda:0 as well."""
import os
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
import warp as wp

from neurogf_warp.generalizable import encoder as genc
from neurogf_warp.generalizable.encoder import WarpGenNet
from neurogf_warp.generalizable.model import load
from neurogf_warp.generalizable.network import GenNeuroGF

from .conftest import shared_path

# Warp's CPU device needs its CPU backend (warp-clang), which the GPU machines' Warp leaves out: without it every
# CPU kernel build fails (an AttributeError on the missing library), so the CPU cases skip there
CPU = wp.is_cpu_available()
DEVICES = (["cpu"] if CPU else []) + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])
needs_cpu = pytest.mark.skipif(not CPU, reason="Warp's CPU backend (warp-clang) is not available")


def blob(n, seed, axes):
    """n points on a bumpy ellipsoid with the given axes, moved off the origin (user units)."""
    rng = np.random.default_rng(seed)
    g = rng.standard_normal((n, 3))
    u = g / np.linalg.norm(g, axis=1, keepdims=True)
    return u * (1 + 0.1 * np.sin(3 * u[:, :1])) * np.asarray(axes) + np.array([4.0, -2.0, 1.0])


@pytest.fixture(scope="module")
def model():
    """The released network: from $NEUROGF_SHARED when set (the GPU machines' copy), else ../shared."""
    alt = Path(os.environ.get("NEUROGF_SHARED", "/nonexistent"), "checkpoints", "official", "GenNeuroGF.pth")
    return load(alt if alt.exists() else shared_path("checkpoints", "official", "GenNeuroGF.pth"))


@pytest.fixture(scope="module")
def random_net():
    torch.manual_seed(4)
    return GenNeuroGF().double().eval()


def arrays(enc):
    return [enc.cloud, enc.feats, enc.fused, enc.points32, *enc.neighbours]


CASES = ([("cpu", None), ("cpu", "cpu-graph")] if CPU else []) + ([("cuda:0", None)] if "cuda:0" in DEVICES else [])


@pytest.mark.slow
@pytest.mark.parametrize("device,how", CASES)
def test_two_conditioned_clouds_answer_their_own_distances(model, device, how):
    """Two clouds of the same size conditioned one after another (on CUDA: the same captured graph) each answer
    their own distances, queried for the first time after the second was conditioned and again later; each
    holds arrays of its own. ("cpu", None): the CPU's eager launches; "cpu-graph": the fp32 fast encoder through
    the graph path with Warp's CPU graphs."""
    n = 2048 if device != "cpu" else 300
    mode = "fp32" if how == "cpu-graph" else None
    wn = model.warp_net(device, mode)
    wn._graph_cpu = how == "cpu-graph"
    a, b = blob(n, 1, (3.0, 2.0, 1.0)), blob(n, 2, (1.0, 2.5, 2.0))
    rng = np.random.default_rng(3)
    ia, ib = rng.integers(0, n, (2, 64))
    cond = lambda x: model.condition(x, device=device, mode=mode)
    ref_a = cond(a).distance(a[ia], a[ib])  # each alone: nothing alive beside it
    ref_b = cond(b).distance(b[ia], b[ib])
    ca = cond(a)
    cb = cond(b)
    np.testing.assert_array_equal(ca.distance(a[ia], a[ib]), ref_a)  # a's first query: after b's conditioning
    np.testing.assert_array_equal(cb.distance(b[ia], b[ib]), ref_b)
    cc = cond(blob(n, 5, (2.0, 2.0, 2.0)))  # a third replay after both were queried
    np.testing.assert_array_equal(ca.distance(a[ia], a[ib]), ref_a)
    np.testing.assert_array_equal(cb.distance(b[ia], b[ib]), ref_b)
    np.testing.assert_array_equal(ca.ssad(7)[ia], ca.distance(np.repeat(a[7:8], 64, 0), a[ia]))
    ptrs = [{x.ptr for x in arrays(c.enc)} for c in (ca, cb, cc)]
    assert not (ptrs[0] & ptrs[1] or ptrs[0] & ptrs[2] or ptrs[1] & ptrs[2])
    assert not np.allclose(ca.distance(a[ia], a[ib]), cb.distance(a[ia], a[ib]))  # different shapes
    if how == "cpu-graph":
        assert list(wn._graphs) == [n]
    elif device == "cpu":
        assert not wn._graphs  # the CPU launches eagerly, as before
    elif wn.fast:
        assert n in wn._graphs or wn._graph_off, "no graph captured and no reason recorded"


@pytest.mark.gpu
def test_graph_matches_eager_launches_on_cuda(model):
    """On cuda:0 the public call with the graph gives the eager launches' encoding and distances."""
    x = blob(2048, 7, (2.0, 1.0, 1.5))
    wn = model.warp_net("cuda:0")
    cg = model.condition(x, device="cuda:0")
    wn.use_graph = False
    try:
        ce = model.condition(x, device="cuda:0")
    finally:
        wn.use_graph = True
    assert 2048 in wn._graphs, wn._graph_off
    for g, e in zip(arrays(cg.enc), arrays(ce.enc)):
        np.testing.assert_array_equal(g.numpy(), e.numpy())
    np.testing.assert_array_equal(cg.ssad(3), ce.ssad(3))


@pytest.mark.slow
@needs_cpu
def test_graph_path_on_cpu_graphs(random_net):
    """The graph path itself (persistent inputs, frame read from the device, capture, replay, copies out, hash
    grid built on first use), with Warp's CPU graphs standing in for CUDA's: the eager fast encoder's bits."""
    rng = np.random.default_rng(6)
    clouds = [rng.uniform(-1, 1, (150, 3)) * s + c for s, c in ((1.0, 0.0), (0.5, 2.0), (2.0, -1.0))]
    frames = [((0.0, 0.0, 0.0), 1.0), ((2.0, 2.0, 2.0), 2.0), ((-1.0, -1.0, -1.0), 0.5)]
    eager = WarpGenNet(random_net, "cpu", mode="fp32", nearest="hash")
    assert eager.fast and not eager._graph_usable(150)  # the CPU: eager launches unless a test says otherwise
    want = [eager.encode(x, c, s) for x, (c, s) in zip(clouds, frames)]
    wg = WarpGenNet(random_net, "cpu", mode="fp32", nearest="hash")
    wg._graph_cpu = True
    got = [wg.encode(x, c, s) for x, (c, s) in zip(clouds, frames)]
    assert list(wg._graphs) == [150] and wg._graph_off is None
    st = wg._graphs[150].state
    for g, e in zip(got, want):  # all three alive, the graph replayed after the first two
        for x, y in zip(arrays(g), arrays(e)):
            np.testing.assert_array_equal(x.numpy(), y.numpy())
        assert not {x.ptr for x in arrays(g)} & {x.ptr for x in arrays(st)}
        assert g.grid is None and g.grid_pending and g.radius == e.radius
    s, t = rng.uniform(-1, 1, (200, 3)), rng.uniform(-1, 1, (200, 3))
    for g, e in zip(got, want):  # the hash-grid lookup (built here, on first use) and the pair head
        np.testing.assert_array_equal(wg.nearest(g, wg._arr(s)).numpy(), eager.nearest(e, eager._arr(s)).numpy())
        assert g.grid is not None and not g.grid_pending
        np.testing.assert_array_equal(wg.ratio(g, s, t).numpy(), eager.ratio(e, s, t).numpy())
    wg.nearest_lookup = "grid"  # the candidate grid (CUDA's default lookup), one per state, over its own cloud
    for g, e in zip(got, want):
        np.testing.assert_array_equal(wg.nearest(g, wg._arr(s)).numpy(), eager.nearest(e, eager._arr(s)).numpy())
    assert len({id(g.nn_grid) for g in got}) == 3
    # a device-resident cloud takes the graph path too; encode(into=) launches eagerly into the given state
    dev_cloud = wg._arr(clouds[1])
    np.testing.assert_array_equal(wg.encode(dev_cloud, *frames[1]).fused.numpy(), want[1].fused.numpy())
    again = wg.encode(clouds[2], *frames[2], into=got[0])
    assert again is got[0] and again.grid is not None and not again.grid_pending
    np.testing.assert_array_equal(again.fused.numpy(), want[2].fused.numpy())


@needs_cpu
def test_graph_cache_and_switches(random_net, monkeypatch):
    """One graph per point count, the least recently used dropped beyond GRAPHS_KEPT; use_graph / NGF_NO_GRAPH
    switch it off; a failed capture warns once and leaves eager launches (same numbers)."""
    monkeypatch.setattr(genc, "GRAPHS_KEPT", 2)
    rng = np.random.default_rng(8)
    wg = WarpGenNet(random_net, "cpu", mode="fp32")
    wg._graph_cpu = True
    for n in (60, 70, 60, 80):
        wg.encode(rng.uniform(-1, 1, (n, 3)))
    assert list(wg._graphs) == [60, 80]
    wg.use_graph = False
    wg.encode(rng.uniform(-1, 1, (90, 3)))
    assert list(wg._graphs) == [60, 80]
    monkeypatch.setenv("NGF_NO_GRAPH", "1")
    assert not genc.graph_default() and not WarpGenNet(random_net, "cpu", mode="fp32").use_graph
    monkeypatch.setenv("NGF_NO_GRAPH", "0")
    assert genc.graph_default()

    class Broken:
        def __init__(self, *a, **k):
            pass

        def __enter__(self):
            raise RuntimeError("no capture here")

        def __exit__(self, *exc):
            return False

    monkeypatch.setattr(wp, "ScopedCapture", Broken)
    wf = WarpGenNet(random_net, "cpu", mode="fp32")
    wf._graph_cpu = True
    x = rng.uniform(-1, 1, (64, 3))
    with pytest.warns(RuntimeWarning, match="no capture here"):
        e1 = wf.encode(x)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        e2 = wf.encode(x)  # remembered: no second warning, no second try
    assert not wf._graphs and "no capture here" in wf._graph_off
    ref = WarpGenNet(random_net, "cpu", mode="fp32").encode(x)
    for e in (e1, e2):
        np.testing.assert_array_equal(e.fused.numpy(), ref.fused.numpy())
        assert e.grid is not None  # the eager path builds the hash grid at conditioning, as before


@needs_cpu
def test_outputs_outlive_the_encoding(model):
    """A conditioned shape's arrays are views into one allocation; each keeps it alive on its own."""
    wn = model.warp_net("cpu", "fp32")
    wn._graph_cpu = True
    x = blob(256, 11, (1.0, 2.0, 3.0))
    c = model.condition(x, device="cpu", mode="fp32")
    feats, nbr, want_f, want_n = c.enc.feats, c.enc.neighbours[2], c.enc.feats.numpy().copy(), c.enc.neighbours[2].numpy().copy()
    del c
    for i in range(3):  # replays and fresh allocations in between
        model.condition(blob(256, 20 + i, (1.0, 1.0, 1.0)), device="cpu", mode="fp32")
    np.testing.assert_array_equal(feats.numpy(), want_f)
    np.testing.assert_array_equal(nbr.numpy(), want_n)


@pytest.mark.slow
def test_normalization_matches_the_plain_formula():
    """normalization() (reductions on a (3, N) copy) and its torch twin give the plain formula's bits; the input is
    left alone."""
    from neurogf_warp.generalizable.model import _frame_stats, normalization

    rng = np.random.default_rng(12)
    for i in range(200):
        n = int(rng.integers(2, 3000))
        size = 10 ** rng.uniform(-8, 8)
        x = (rng.standard_normal((n, 3)) + rng.standard_normal(3) * 10 ** rng.uniform(-2, 3)) * size
        if i % 4 == 1:
            x = x.astype(np.float32)
        if i % 4 == 2:
            x = np.asfortranarray(x)
        x0 = x.copy()
        c = (x.min(axis=0) + x.max(axis=0)) / 2
        r = float(np.sqrt(((x - c) ** 2).sum(axis=1)).max())
        got_c, got_s = normalization(x)
        np.testing.assert_array_equal(got_c, c)
        assert got_s == 1.0 / r
        np.testing.assert_array_equal(x, x0)
        if x.dtype == np.float64:
            st = _frame_stats(torch.from_numpy(np.ascontiguousarray(x))).numpy()
            np.testing.assert_array_equal(st[:3], c)
            assert 1.0 / float(np.sqrt(st[3])) == got_s


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs torch on CUDA")
def test_cloud_on_the_gpu_conditions_as_numpy(model):
    """A CUDA torch tensor (float32 or float64) or a CUDA wp.array conditions as the same points from numpy: the
    same frame and encoding bits, the same distances; clear errors for non-finite and too few points."""
    x = blob(2048, 13, (2.0, 1.0, 1.5))
    ref = model.condition(x, device="cuda:0")
    rng = np.random.default_rng(14)
    i, j = rng.integers(0, 2048, (2, 256))
    want = ref.distance(x[i], x[j])
    for given in (torch.tensor(x, device="cuda:0"), torch.tensor(x, device="cuda:0").float(),
                  wp.array(x, dtype=wp.float64, device="cuda:0"), wp.array(x.astype(np.float32), dtype=wp.vec3,
                                                                           device="cuda:0")):
        c = model.condition(given, device="cuda:0")
        x_in = x if (getattr(given, "dtype", None) in (torch.float64, wp.float64)) else x.astype(np.float32)
        c_ref = ref if x_in is x else model.condition(x_in.astype(np.float64), device="cuda:0")
        np.testing.assert_array_equal(c.center, c_ref.center)
        assert c.scale == c_ref.scale
        np.testing.assert_array_equal(c.points, c_ref.points)
        for g, e in zip(arrays(c.enc), arrays(c_ref.enc)):
            np.testing.assert_array_equal(g.numpy(), e.numpy())
        if x_in is x:
            np.testing.assert_array_equal(c.distance(x[i], x[j]), want)
    bad = torch.tensor(x, device="cuda:0")
    bad[17, 2] = float("nan")
    with pytest.raises(ValueError, match="non-finite.*row 17"):
        model.condition(bad, device="cuda:0")
    with pytest.raises(ValueError, match="at least"):
        model.condition(torch.zeros((5, 3), device="cuda:0"), device="cuda:0")
    with pytest.raises(ValueError, match="coincide"):
        model.condition(torch.ones((100, 3), device="cuda:0"), device="cuda:0")
