"""The generalizable encoder as a captured graph (issue 23): ``WarpGenNet.encode`` without ``into`` replays one
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

DEVICES = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])


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


CASES = [("cpu", None), ("cpu", "cpu-graph")] + ([("cuda:0", None)] if "cuda:0" in DEVICES else [])


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


@pytest.mark.skipif(wp.get_cuda_device_count() == 0, reason="needs a CUDA device")
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
