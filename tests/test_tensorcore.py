"""The tensor-core kernels (precision="fp16") against a float64 evaluation of the same network.

On the CPU the kernels run as a warp emulation (32 fibers per warp, the warp-wide operations emulated), the
same native code as on the GPU; it is slow, so the CPU cases are small (D = 64, tens of points). With a GPU
the same checks run there at every supported width. Fresh random networks and inputs each run; the seed is
in the failure message.
"""
import numpy as np
import pytest
import torch
import warp as wp

import neurogf_warp as ngf
from neurogf_warp.model.network import NeuroGFNet

# the CPU emulation wherever Warp has its CPU backend (the GPU machines' installs may not), every width on a GPU
DEVICES = ([("cpu", 64)] if wp.is_cpu_available() else []) + \
    [("cuda:0", D) for D in (64, 128, 256) if wp.get_cuda_device_count() > 0]
TOL = 2e-3  # fp16 activations against float64: |error| / max |value| (trained networks: ~1e-4)


def random_net(D, seed, **options):
    torch.manual_seed(seed)
    net = NeuroGFNet(D, **options).double()
    for m in net.modules():
        if isinstance(m, (torch.nn.BatchNorm1d, torch.nn.BatchNorm2d)):
            m.running_mean.uniform_(-0.2, 0.2)
            m.running_var.uniform_(0.5, 1.5)
            m.weight.data.uniform_(0.5, 1.5)
            m.bias.data.uniform_(-0.1, 0.1)
    return net.eval()


def icosphere_mesh(rng, offset):
    import trimesh

    tm = trimesh.creation.icosphere(subdivisions=2)
    return ngf.load_mesh((tm.vertices * rng.uniform(0.8, 2.0, 3) + offset, tm.faces))


def close(got, ref, what, tol=TOL):
    err = np.abs(np.asarray(got, np.float64) - ref).max() / np.abs(ref).max()
    assert err <= tol, f"{what}: relative error {err:.2e}"


# ---- the kernels' arithmetic in numpy: fp16 weights and activations at the same places, sums in float64 ----------

def h(x):
    return np.asarray(x, np.float64).astype(np.float16).astype(np.float64)


def emu_layers(net):
    from neurogf_warp.model.folded import folded_layers

    return folded_layers(net)


def to_net32(mesh, x):
    """The kernels' frame mapping in float32: (x - center) * scale."""
    x32 = np.asarray(x, np.float32)
    return ((x32 - mesh.center.astype(np.float32)) * np.float32(mesh.scale)).astype(np.float64)


def emu_embed(layers, fourier, x_net):
    """fp16 embeddings as the kernels compute them from float32 network-frame points."""
    x = x_net.astype(np.float32).astype(np.float64)
    feats = [x]
    if fourier:
        f = x[:, :, None] * (np.pi * 2.0 ** np.arange(fourier))
        feats += [np.sin(f).reshape(len(x), -1), np.cos(f).reshape(len(x), -1)]
    v = np.concatenate(feats, 1).astype(np.float32).astype(np.float64)
    hi = h(v)
    v = hi + h(v - hi)  # the high + low fp16 input of the first layer
    (W0, b0), (W1, b1), (W2, b2) = layers["lifting"]
    a = h(np.maximum(v @ h(W0).T + b0.astype(np.float32), 0))
    a = h(np.maximum(a @ h(W1).T + b1.astype(np.float32), 0))
    return h(np.maximum(a @ h(W2).T + b2.astype(np.float32), 0))


def emu_head(head, z):
    (W0, b0), (W1, b1), (W2, _) = head
    a = h(np.maximum(z @ h(W0).T + b0.astype(np.float32), 0))
    a = np.maximum(a @ h(W1).T + b1.astype(np.float32), 0)  # fp32 into the last (fp32) layer
    return a @ W2.astype(np.float32).astype(np.float64).T[:, 0]


def emu_distance(net, mesh, p, q):
    L = emu_layers(net)
    ep, eq = emu_embed(L, net.fourier, to_net32(mesh, p)), emu_embed(L, net.fourier, to_net32(mesh, q))
    y = emu_head(L["distance"], h(np.abs(ep - eq)))
    if net.euclid:
        y = y + np.linalg.norm(p - q, axis=1) * mesh.scale
    return y / mesh.scale


def emu_sdf(net, mesh, x):
    L = emu_layers(net)
    return emu_head(L["sdf"], emu_embed(L, net.fourier, to_net32(mesh, x))) / mesh.scale


def close_emu(got, ref, what):
    """Against the emulation the kernels agree to fp32 sums, except where a sum lands on the other side of an fp16
    rounding boundary (a few activations per run): the bulk must agree tightly, the worst point loosely. A wrong
    fragment layout or lane mapping gives O(1) errors on most points."""
    err = np.abs(np.asarray(got, np.float64) - ref) / np.abs(ref).max()
    assert np.percentile(err, 90) <= 3e-5 and err.max() <= 2e-3, \
        f"{what}: 90th percentile {np.percentile(err, 90):.1e}, max {err.max():.1e}"


OPTIONS = [dict(fourier=2, euclid=True, path_residual=True, path_window=True), dict(fourier=0)]


@pytest.mark.slow
@pytest.mark.parametrize("device,D", DEVICES)
@pytest.mark.parametrize("options", OPTIONS, ids=["default", "paper"])
def test_point_queries_match_float64(device, D, options):
    seed = int(np.random.SeedSequence().entropy % 2**31)
    rng = np.random.default_rng(seed)
    mesh = icosphere_mesh(rng, rng.normal(0, 3, 3))
    net = random_net(D, seed, **options)
    model = ngf.Model(net=net, mesh=mesh, center=mesh.center, scale=mesh.scale)
    n = 40 if device == "cpu" else 5000
    p = mesh.vertices[rng.integers(0, len(mesh.vertices), n)] + rng.normal(0, 0.05, (n, 3))
    q = mesh.vertices[rng.integers(0, len(mesh.vertices), n)] + rng.normal(0, 0.05, (n, 3))
    to_net = lambda x: torch.from_numpy(mesh.normalize(x))
    with torch.no_grad():
        d_ref = net.distance(to_net(p), to_net(q)).numpy() / mesh.scale
        s_ref = net.sdf(to_net(p)).numpy() / mesh.scale
        k = 6 if device == "cpu" else 200
        path_ref = net.path(to_net(p[:k]), to_net(q[:k]), 16).numpy() / mesh.scale + mesh.center
    msg = f"seed {seed}, {device}, D={D}, {options}"
    d = ngf.distance(model, p, q, device=device, precision="fp16", raw=True)
    s = ngf.sdf(model, p, device=device, precision="fp16")
    close_emu(d, emu_distance(net, mesh, p, q), "distance (fp16 emulation) " + msg)
    close_emu(s, emu_sdf(net, mesh, p), "sdf (fp16 emulation) " + msg)
    close(d, d_ref, "distance " + msg, 1e-2)  # float64: fp16 rounding of random networks' activations
    close(s, s_ref, "sdf " + msg, 1e-2)
    close(ngf.path(model, p[:k], q[:k], m=16, project=None, device=device, precision="fp16"), path_ref, "path " + msg)
    assert np.array_equal(ngf.distance(model, p, q, device=device, precision="fp16", raw=True),
                          ngf.distance(model, q, p, device=device, precision="fp16", raw=True)), msg


@pytest.mark.slow
@pytest.mark.parametrize("device,D", DEVICES)
def test_vertex_queries_match_float64_bound_and_cold(device, D):
    """SSAD / MSAD / distance matrices from vertices and points, with kept embeddings and without; both paths
    round the embeddings the same way, so they agree exactly."""
    seed = int(np.random.SeedSequence().entropy % 2**31)
    rng = np.random.default_rng(seed)
    mesh = icosphere_mesh(rng, 0.0)
    net = random_net(D, seed, fourier=2, euclid=True)
    model = ngf.Model(net=net, mesh=mesh, center=mesh.center, scale=mesh.scale)
    x = torch.from_numpy(mesh.normalize(mesh.vertices))
    srcs = rng.choice(len(mesh.vertices), 3, replace=False)
    with torch.no_grad():
        ref = np.stack([net.distance(x[[s]].expand(len(x), 3), x).numpy() for s in srcs]) / mesh.scale
    msg = f"seed {seed}, {device}, D={D}"
    kw = dict(device=device, precision="fp16", raw=True)
    cold = ngf.ssad(model, int(srcs[0]), cache=False, **kw)
    close(cold, ref[0], "ssad cold " + msg)
    close(ngf.msad(model, srcs, cache=False, **kw), ref.min(0), "msad cold " + msg)
    bound = ngf.ssad(model, int(srcs[0]), **kw)
    from neurogf_warp.inference.state import query_state

    assert "fp16" in query_state(model, device).bound, msg
    np.testing.assert_array_equal(bound, cold, err_msg=msg)
    close(ngf.msad(model, srcs, **kw), ref.min(0), "msad bound " + msg)
    close(ngf.distance_matrix(model, srcs, **kw), ref, "matrix " + msg)
    close(ngf.distance_matrix(model, srcs, srcs[::-1], **kw), ref[:, srcs[::-1]], "matrix to targets " + msg)
    pt = mesh.vertices[srcs[1]]
    close(ngf.ssad(model, pt, **kw), ref[1], "ssad from a point " + msg)
    # finished answers: exactly 0 at the source, never negative
    d = ngf.ssad(model, int(srcs[2]), device=device, precision="fp16")
    assert d[srcs[2]] == 0.0 and np.all(d >= 0), msg


@pytest.mark.parametrize("device,D", DEVICES[:2])
def test_components_and_numbering(device, D):
    """Two separate parts and an unused vertex: +inf across parts, NaN for the unused vertex, in the file's
    numbering, from both engines."""
    import trimesh

    a = trimesh.creation.icosphere(subdivisions=1)
    V = np.vstack([[[9.0, 9.0, 9.0]], a.vertices, a.vertices + [3.0, 0, 0]])
    F = np.vstack([a.faces + 1, a.faces + 1 + len(a.vertices)])
    mesh = ngf.load_mesh((V, F))
    net = random_net(D, 1, fourier=2, euclid=True)
    model = ngf.Model(net=net, mesh=mesh, center=mesh.center, scale=mesh.scale)
    for prec in ("fp16", "fp32"):
        d = ngf.ssad(model, 1, device=device, precision=prec)
        assert np.isnan(d[0]) and len(d) == len(V)
        first = slice(1, 1 + len(a.vertices))
        assert np.all(np.isfinite(d[first])) and np.all(np.isinf(d[1 + len(a.vertices):])), prec
        pair = ngf.distance(model, V[[1, 1]], V[[2, 1 + len(a.vertices)]], device=device, precision=prec)
        assert np.isfinite(pair[0]) and np.isinf(pair[1]), prec
        paths = ngf.path(model, V[[1, 1]], V[[2, 1 + len(a.vertices)]], m=8, device=device, precision=prec)
        assert np.all(np.isfinite(paths[0])) and np.all(np.isnan(paths[1])), prec
        m = ngf.msad(model, [1, 1 + len(a.vertices)], device=device, precision=prec)
        assert np.all(np.isfinite(m[1:])), prec


def test_packing_layout():
    """The B-fragment packing against the mma.m16n8k16 layout, element by element (odd n-tile count padded)."""
    from neurogf_warp.kernels.inference import tensorcore as tc

    rng = np.random.default_rng()
    W = rng.normal(size=(24, 40))  # 3 n-tiles (padded to 4), 3 k-steps
    pk = tc.pack_weights(W)
    assert pk.shape == (3, 2, 32, 4)
    h = lambda w: np.float16(W[w]) if w[0] < 24 and w[1] < 40 else np.float16(0.0)
    for ks in range(pk.shape[0]):
        for nt in range(2 * pk.shape[1]):
            for lane in range(32):
                g, t = lane >> 2, lane & 3
                for j, k0 in enumerate((16 * ks + 2 * t, 16 * ks + 2 * t + 8)):
                    word = int(pk[ks, nt // 2, lane, 2 * (nt % 2) + j])
                    lo = np.array([word & 0xFFFF], np.uint16).view(np.float16)[0]
                    hi = np.array([word >> 16], np.uint16).view(np.float16)[0]
                    assert lo == h((8 * nt + g, k0)) and hi == h((8 * nt + g, k0 + 1))


def test_fp16_range_is_checked():
    from neurogf_warp.kernels.inference import tensorcore as tc

    with pytest.raises(ValueError, match="fp16 range"):
        tc.pack_weights(np.full((8, 16), 1e6))


@pytest.mark.slow
@pytest.mark.parametrize("setting", [{"ssad": (1, True)}, {"ssad": (1, False)}, {"source_group": 1},
                                     {"lift_ssad": (1, 4)}, {"sdf_tile": (1, 8)}, {"pair_nc": 4}], ids=str)
def test_tile_variants_agree(setting):
    """Every tile layout the benchmarks tune computes the same numbers (same roundings, same sums per row)."""
    from neurogf_warp.inference.state import query_state
    from neurogf_warp.kernels.inference import tensorcore as tc

    device = "cpu" if wp.is_cpu_available() else "cuda:0"
    rng = np.random.default_rng(3)
    mesh = icosphere_mesh(rng, 0.0)
    model = ngf.Model(net=random_net(64, 3, fourier=2, euclid=True), mesh=mesh, center=mesh.center, scale=mesh.scale)
    p = mesh.vertices[rng.integers(0, len(mesh.vertices), 40)]
    kw = dict(device=device, precision="fp16")

    def run():
        return (ngf.ssad(model, 5, **kw), ngf.ssad(model, 7, cache=False, **kw), ngf.msad(model, [1, 2, 3], **kw),
                ngf.distance(model, p, p[::-1], **kw), ngf.sdf(model, p, **kw))

    base = run()
    st = query_state(model, device)
    st.retune(tc.Tuning(**setting))
    assert st.engine.tuning == tc.Tuning(**setting)
    other = run()
    for a, b in zip(base, other):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)


def test_large_requests_are_chunked_or_refused(monkeypatch):
    """A many-source result for the host is computed in chunks of sources (same numbers); a binding that does not
    fit in memory leaves the query to run unbound, with a warning."""
    from neurogf_warp.inference import queries as inference

    device = "cpu" if wp.is_cpu_available() else "cuda:0"
    rng = np.random.default_rng(5)
    mesh = icosphere_mesh(rng, 0.0)
    model = ngf.Model(net=random_net(64, 5, fourier=2, euclid=True), mesh=mesh, center=mesh.center, scale=mesh.scale)
    srcs = [1, 7, 20, 33, 41]
    whole = ngf.distance_matrix(model, srcs, device=device, precision="fp32")
    monkeypatch.setattr(inference, "CHUNK_BYTES", 4 * len(mesh.vertices) * 2)  # two sources per chunk
    np.testing.assert_array_equal(ngf.distance_matrix(model, srcs, device=device, precision="fp32"), whole)

    def no_room(*args, **kwargs):
        raise MemoryError("keeping the embeddings needs more than is free: query with cache=False")

    model.unbind()
    monkeypatch.setattr(inference, "bind", no_room)
    with pytest.warns(RuntimeWarning, match="without kept embeddings"):
        d = ngf.ssad(model, 7, device=device, precision="fp32")
    np.testing.assert_allclose(d, whole[1], rtol=1e-6, atol=1e-7)
