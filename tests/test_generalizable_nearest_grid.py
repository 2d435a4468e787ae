"""The dense candidate grid of the nearest-cloud-point lookup (kernels/generalizable/nearest_grid.py) against the
brute-force scan: the same index for every query, ties (equal distances) included, on Warp's CPU device and,
with a GPU, on cuda:0."""
import numpy as np
import pytest
import torch
import warp as wp

from neurogf_warp.generalizable.encoder import WarpGenNet
from neurogf_warp.generalizable.network import GenNeuroGF
from neurogf_warp.kernels.generalizable import kernels
from neurogf_warp.kernels.generalizable.nearest_grid import NearestGrid

DEVICES = (["cpu"] if wp.is_cpu_available() else []) + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])


def surface_cloud(n, rng):
    """n points on a bumpy ellipsoid in the unit sphere, with exact duplicates and a tight cluster."""
    u = rng.standard_normal((n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    u *= (1 + 0.1 * np.sin(3 * u[:, :1])) * np.array([1.0, 0.7, 0.5]) * 0.95
    u[n // 2: n // 2 + 4] = u[3]  # duplicates: ties between indices 3 and n/2 ..
    u[10:40] = u[10] + rng.standard_normal((30, 3)) * 1e-3  # a cluster: long candidate lists
    return u


def queries(cloud, rng):
    n = len(cloud)
    near = cloud[rng.integers(0, n, 3000)] + rng.standard_normal((3000, 3)) * 0.02
    mid = (cloud[rng.integers(0, n, 300)] + cloud[rng.integers(0, n, 300)]) / 2  # often equidistant (ties)
    far = rng.uniform(-1.6, 1.6, (1000, 3))  # inside the box far from the cloud, and outside it
    return np.concatenate([near, mid, far, cloud, [[np.nan, 0.0, 0.0]]])


@pytest.mark.parametrize("dev", DEVICES)
@pytest.mark.parametrize("mode,n,seed", [("fp32", 256, 0), ("fp64", 256, 1), ("fp32", 700, 2)])
def test_grid_equals_brute_force(mode, n, seed, dev):
    rng = np.random.default_rng(seed)
    k = kernels(mode)
    npd = np.float32 if k.dtype == wp.float32 else np.float64
    cloud = surface_cloud(n, rng).astype(npd)
    C = wp.array(cloud, dtype=k.dtype, device=dev)
    Q = queries(cloud, rng).astype(npd)
    P = wp.array(Q, dtype=k.dtype, device=dev)
    grid = NearestGrid(mode, n, dev).build(C)
    got = wp.empty(len(Q), dtype=wp.int32, device=dev)
    want = wp.empty(len(Q), dtype=wp.int32, device=dev)
    wp.launch(grid.k.nearest, len(Q), inputs=[C, *grid.args(), P, got], device=dev)
    wp.launch(k.nearest, len(Q), inputs=[C, wp.uint64(0), 0.0, 0, P, want], device=dev)  # brute force
    np.testing.assert_array_equal(got.numpy(), want.numpy())
    # the lists were used (not the fallback) for the queries near the cloud, and ties occurred
    assert (grid.count.numpy() > 0).sum() > 0.1 * grid.G ** 3
    d = ((Q[:3300, None, :].astype(np.float64) - cloud[None].astype(np.float64)) ** 2).sum(-1)
    assert (np.sort(d, axis=1)[:, 1] == d.min(axis=1)).sum() > 10
    # user-unit queries (centre and scale applied in the kernel) agree with the unit-frame ones
    c, s = np.array([3.0, -2.0, 0.5]), 0.25
    user = wp.array((Q / s + c).astype(npd), dtype=k.dtype, device=dev)
    got_u = wp.empty(len(Q), dtype=wp.int32, device=dev)
    want_u = wp.empty(len(Q), dtype=wp.int32, device=dev)
    wp.launch(grid.k.nearest_user, len(Q), inputs=[C, *grid.args(), user, *c, s, got_u], device=dev)
    wp.launch(k.nearest_user, len(Q), inputs=[C, wp.uint64(0), 0.0, 0, user, *c, s, want_u], device=dev)
    np.testing.assert_array_equal(got_u.numpy(), want_u.numpy())


@pytest.mark.slow
@pytest.mark.parametrize("dev", DEVICES)
def test_warp_gen_net_grid_lookup(dev):
    """WarpGenNet(nearest="grid") gives bit for bit the hash-grid distances; encode(into=) rebuilds the lists."""
    torch.manual_seed(2)
    net = GenNeuroGF().double().eval()
    rng = np.random.default_rng(3)
    hashed, gridded = WarpGenNet(net, dev, mode="fp32"), WarpGenNet(net, dev, mode="fp32", nearest="grid")
    a, b = surface_cloud(200, rng), surface_cloud(200, rng) * 0.9
    S, T = hashed._arr(a[rng.integers(0, 200, 150)] * 2 + 1), hashed._arr(b[rng.integers(0, 200, 150)] * 2 + 1)
    state = gridded.encode(a)
    for cloud in (a, b):
        ref = hashed.encode(cloud)
        if cloud is b:
            gridded.encode(cloud, into=state)
        for precision in ("fp32", "fp16"):
            want = hashed.distances(ref, S, T, (1, 1, 1), 0.5, False, precision=precision).numpy()
            got = gridded.distances(state, S, T, (1, 1, 1), 0.5, False, precision=precision).numpy()
            np.testing.assert_array_equal(got, want)
        U = hashed._arr(cloud + rng.standard_normal(cloud.shape) * 0.01)
        np.testing.assert_array_equal(gridded.nearest(state, U).numpy(), hashed.nearest(ref, U).numpy())
    with pytest.raises(ValueError, match="nearest"):
        WarpGenNet(net, dev, mode="fp32", nearest="kd")
