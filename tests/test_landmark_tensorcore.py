"""A landmark network's single-source query on tensor cores (precision="fp16") against float64.

The network's distance head also reads exact distances to K landmarks (network.NeuroGFNet, ``landmarks=K``); the
native kernel feeds |T(s) - T(q)| to the first layer in fp16 and makes the bounds and the bracket in fp32. On the
CPU it runs as the warp emulation (tests/test_tensorcore.py), so the meshes are small; fresh random networks and
tables each run, the seed in the failure message.
"""
import numpy as np
import pytest
import torch
import warp as wp

import neurogf_warp as ngf
from neurogf_warp.model import network
from neurogf_warp.model.network import NeuroGFNet
from tests.test_tensorcore import close, icosphere_mesh, random_net

# the CPU emulation wherever Warp has its CPU backend, and a GPU when there is one
DEVICES = (["cpu"] if wp.is_cpu_available() else []) + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])
DEVICE = DEVICES[0]
SOURCES = 12  # the test sources are among the first vertices, never landmarks (from a landmark lower = upper)
TOL = 2e-3  # as tests/test_tensorcore.py: fp16 activations against float64, relative to the largest distance


class TableLookup(torch.nn.Module):
    """Stands in for ``network.Landmarks`` in a float64 network: the table row of the vertex nearest each point
    (the points are the mesh's vertices, so the nearest is the vertex itself)."""

    def __init__(self, xyz: np.ndarray, table: np.ndarray):
        super().__init__()
        self.xyz, self.table = torch.from_numpy(xyz).double(), torch.from_numpy(table).double()

    def forward(self, x):
        return self.table[torch.cdist(x, self.xyz).argmin(1)]


def landmark_model(D, K, seed, tie_rows=True, **options):
    """A random landmark network, its mesh (an icosphere, a few hundred vertices) and a table of positive distances
    (chords to K vertices, scaled); the network with a float64 table lookup is the reference."""
    rng = np.random.default_rng(seed)
    mesh = icosphere_mesh(rng, rng.normal(0, 3, 3))
    opts = dict(euclid=True, landmarks=K, landmark_bracket=True)
    opts.update(options)
    net = random_net(D, seed, **opts)
    xn = mesh.normalize(mesh.vertices)
    marks = rng.choice(np.arange(SOURCES, len(xn)), K, replace=K > len(xn) - SOURCES)  # K = 256: some twice
    # a metric (the chord, scaled): lower <= it <= upper for every pair, so the bracket has room
    table = (np.linalg.norm(xn[:, None] - xn[marks][None], axis=-1) * rng.uniform(1.05, 1.4)).astype(np.float32)
    model = ngf.Model(net=net, mesh=mesh, center=mesh.center, scale=mesh.scale, landmarks=table)
    net.landmark_table = TableLookup(xn, table)  # the float64 reference's lookup (the kernels read model.landmarks)
    # a random head's output is far from 0, where the bracket's sigmoid saturates and hides the head: scale the last
    # layer to outputs of about unit spread around 0, so every input column shows in the answer
    x = torch.from_numpy(xn).double()
    i, j = torch.from_numpy(rng.integers(0, len(xn), (2, 512)))
    with torch.no_grad():
        e, tp, tq = net.embed(x), net.landmark_table(x[i]), net.landmark_table(x[j])
        diff = (tp - tq).abs()
        parts = [(e[i] - e[j]).abs(), diff, diff.max(-1).values[:, None], (tp + tq).min(-1).values[:, None]]
        if net.landmark_pair_inputs:
            parts += [torch.linalg.vector_norm(x[i] - x[j], dim=-1)[:, None], torch.ones(len(i), 1)]
        hidden = net.gdf_head[:-1](torch.cat(parts, -1))
        last = net.gdf_head[-1].linear.weight
        y = hidden @ last[0]
        last.mul_(2.0 / y.std()).sub_(((y.mean() / y.std()) * 2.0) * hidden.mean(0) / hidden.mean(0).square().sum())
    return model, net, mesh, rng


def reference_ssad(net, mesh, src: int) -> np.ndarray:
    """The network's own distances (no finishing) from vertex ``src`` to every vertex, float64, mesh units."""
    x = torch.from_numpy(mesh.normalize(mesh.vertices)).double()
    with torch.no_grad():
        e = net.embed(x)
        d = net.distance_from_embeddings(e[[src]].expand(len(x), -1), e, x[[src]].expand(len(x), 3), x)
    return d.numpy() / mesh.scale


CASES = [(d, D, K) for d in DEVICES for D, K in ([(64, 16), (64, 32)] if d == "cpu" else
                                                  [(64, 16), (128, 64), (256, 256)])]


@pytest.mark.parametrize("device,D,K", CASES)
def test_bound_ssad_matches_float64(device, D, K):
    seed = int(np.random.SeedSequence().entropy % 2**31)
    model, net, mesh, rng = landmark_model(D, K, seed)
    msg = f"seed {seed}, {device}, D={D}, K={K}"
    srcs = rng.choice(SOURCES, 2, replace=False)
    for s in srcs:
        got = ngf.ssad(model, int(s), device=device, precision="fp16", raw=True)
        close(got, reference_ssad(net, mesh, int(s)), f"ssad from {s}, " + msg, TOL)
    # finished answers: exactly 0 at the source, never below the straight line
    d = ngf.ssad(model, int(srcs[0]), device=device, precision="fp16")
    chord = np.linalg.norm(mesh.vertices - mesh.vertices[srcs[0]], axis=1)
    assert d[srcs[0]] == 0.0 and np.all(d >= chord * (1 - 1e-6)), msg


@pytest.mark.slow
@pytest.mark.parametrize("options", [dict(landmark_bracket_log=True), dict(landmark_bracket=False),
                                     dict(landmark_pair_inputs=True, landmark_floor=0.5),
                                     dict(fourier=2, landmark_bracket=False, euclid=False)],
                         ids=["log", "plain", "pair-inputs", "plain-no-euclid"])
@pytest.mark.parametrize("device", DEVICES)
def test_other_landmark_forms_match_float64(device, options):
    seed = int(np.random.SeedSequence().entropy % 2**31)
    model, net, mesh, rng = landmark_model(64, 16, seed, **options)
    s = int(rng.integers(SOURCES))
    got = ngf.ssad(model, s, device=device, precision="fp16", raw=True)
    # the plain forms add the whole head to the floor, not a sigmoid of it: fp16 shows more (as point queries do)
    tol = TOL if options.get("landmark_bracket", True) else 5e-3
    close(got, reference_ssad(net, mesh, s), f"seed {seed}, {device}, {options}", tol)


@pytest.mark.slow
def test_tile_variants_agree():
    """Every tile layout of the landmark kernel gives the same numbers (the same sums per row)."""
    from neurogf_warp.inference.state import query_state
    from neurogf_warp.kernels.inference import tensorcore as tc

    model, net, mesh, rng = landmark_model(64, 32, 11)
    base = ngf.ssad(model, 9, device=DEVICE, precision="fp16")
    for setting in ({"landmark_ssad": (1, False)}, {"landmark_ssad": (1, True)}, {"landmark_ssad": (2, True)}):
        query_state(model, DEVICE).retune(tc.Tuning(**setting))
        np.testing.assert_array_equal(ngf.ssad(model, 9, device=DEVICE, precision="fp16"), base, err_msg=str(setting))


@pytest.mark.parametrize("device", DEVICES)
def test_unreached_landmarks_and_components(device):
    """Two separate parts: landmarks only on the first, so the second part's table rows are all unreached; +inf
    across the parts, and from a source on the second part the head on |s - q| (no bracket)."""
    import trimesh

    a = trimesh.creation.icosphere(subdivisions=1)
    n = len(a.vertices)
    mesh = ngf.load_mesh((np.vstack([a.vertices, a.vertices + [3.0, 0, 0]]), np.vstack([a.faces, a.faces + n])))
    K = 16
    xn = mesh.normalize(mesh.vertices)
    table = np.full((2 * n, K), network.LANDMARK_UNREACHED, np.float32)
    table[:n] = np.linalg.norm(xn[:n, None] - xn[:K][None], axis=-1) * 1.2
    net = random_net(64, 4, euclid=True, landmarks=K, landmark_bracket=True)
    model = ngf.Model(net=net, mesh=mesh, center=mesh.center, scale=mesh.scale, landmarks=table)
    net.landmark_table = TableLookup(xn, table)
    for s, here in ((2, slice(0, n)), (n + 3, slice(n, 2 * n))):
        d = ngf.ssad(model, s, device=device, precision="fp16", raw=True)
        other = slice(n, 2 * n) if s < n else slice(0, n)
        assert np.all(np.isinf(d[other])), s
        close(d[here], reference_ssad(net, mesh, s)[here], f"source {s}", TOL)


def test_refusals():
    """Landmark queries other than a bound single vertex source say to use precision='fp32'; a K that is not a
    multiple of 16 is refused with the allowed values; a model without its table says how to load one."""
    model, net, mesh, rng = landmark_model(64, 16, 7)
    kw = dict(device=DEVICE, precision="fp16")
    p = mesh.vertices[:2]
    # (cache=False first: a query without kept embeddings; later calls bind the model)
    for call in (lambda: ngf.ssad(model, 1, cache=False, **kw), lambda: ngf.distance(model, p[:1], p[1:], **kw),
                 lambda: ngf.msad(model, [1, 2], **kw), lambda: ngf.ssad(model, p[0], **kw),
                 lambda: ngf.distance_matrix(model, [1, 2], [3, 4], **kw)):
        with pytest.raises(ValueError, match="needs precision='fp32'"):
            call()
    # the heads a landmark network shares with every network still run
    assert np.all(np.isfinite(ngf.sdf(model, p, **kw)))
    net20 = NeuroGFNet(64, euclid=True, landmarks=20, landmark_bracket=True)
    m20 = ngf.Model(net=net20, mesh=mesh, center=mesh.center, scale=mesh.scale,
                    landmarks=np.ones((len(mesh.vertices), 20), np.float32))
    with pytest.raises(ValueError, match=r"K = 20 landmarks .*multiples of 16 up to 256"):
        ngf.ssad(m20, 1, **kw)
    bare = ngf.Model(net=random_net(64, 7, euclid=True, landmarks=16, landmark_bracket=True), mesh=mesh,
                     center=mesh.center, scale=mesh.scale)
    with pytest.raises(ValueError, match="stores the table"):
        ngf.ssad(bare, 1, **kw)


def test_auto_sends_other_queries_to_the_per_thread_kernels():
    """precision "auto" on a GPU: a bound vertex source runs on the tensor cores, every other landmark query on the
    per-thread kernels, with their answers (the backend "auto" makes on a CUDA device, built here by hand: on the
    CPU "auto" is fp32)."""
    from neurogf_warp.inference.backends import PerThread, TensorCores
    from neurogf_warp.inference.state import query_state

    model, net, mesh, rng = landmark_model(64, 16, 11)
    st = query_state(model, DEVICE)
    st.backends["auto"] = TensorCores(st, PerThread(st))
    p, q = mesh.vertices[:3], mesh.vertices[5:8]
    for call in (lambda **kw: ngf.distance(model, p, q, device=DEVICE, **kw),
                 lambda **kw: ngf.msad(model, [1, 2], device=DEVICE, **kw),
                 lambda **kw: ngf.ssad(model, p[0] + 1e-3, device=DEVICE, **kw),
                 lambda **kw: ngf.distance_matrix(model, [1, 2], [3, 4], device=DEVICE, **kw)):
        np.testing.assert_array_equal(call(), call(precision="fp32"))
    ngf.bind(model, device=DEVICE)  # kept fp16 embeddings: the tensor-core kernel answers
    np.testing.assert_array_equal(ngf.ssad(model, 1, device=DEVICE), ngf.ssad(model, 1, device=DEVICE,
                                                                             precision="fp16"))


def test_packing_of_the_landmark_columns():
    """The first layer's landmark columns follow the lanes' loads; scalars come twice (high and low parts); the
    kernels' copies of the network's constants agree."""
    from neurogf_warp.kernels.inference import tensorcore as tc

    assert tc.LANDMARK_UNREACHED == network.LANDMARK_UNREACHED
    assert tc.LANDMARK_WIDTH_MAX == network.LANDMARK_WIDTH_MAX
    assert tc.LANDMARK_K[-1] == network.MAX_LANDMARKS
    D, K = 64, 32
    W = np.random.default_rng(0).normal(size=(16, D + K + 2))
    P = tc.landmark_first_layer(W, D, K)
    assert P.shape == (16, D + K + 16)
    np.testing.assert_array_equal(P[:, :D], W[:, :D])
    perm = tc.landmark_columns()
    assert sorted(perm) == list(range(16))
    for c in range(16):  # lane t = (c % 8) // 2 holds floats 4t .. 4t+3: the first two in columns 2t, 2t+1
        t = (c % 8) // 2
        assert perm[c] == 4 * t + (2 if c >= 8 else 0) + c % 2
        np.testing.assert_array_equal(P[:, D + 16 + c], W[:, D + 16 + perm[c]])
    np.testing.assert_array_equal(P[:, D + K: D + K + 4], W[:, [D + K, D + K, D + K + 1, D + K + 1]])
    assert not P[:, D + K + 4:].any()
