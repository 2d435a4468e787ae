"""The generalizable network: torch definition vs the authors' float64 outputs, Warp kernels vs float64 torch.

References: ``shared/reference/generalizable/<mesh>.npz`` (the released GenNeuroGF.pth evaluated with the authors'
code in float64). Bounds from the issue: mean relative difference <= 1e-5, max <= 1e-3.
"""
import numpy as np
import pytest
import torch
import warp as wp
from neurogf_warp.kernels.generalizable import kernels

from neurogf_warp.generalizable.encoder import WarpGenNet
from neurogf_warp.generalizable.network import (
    GenNeuroGF,
    folded_layers,
    is_generalizable_state_dict,
    knn_indices,
    load_network,
    load_state_dict_file,
)

from .conftest import shared_path

MESHES = ["stanford-bunny", "fandisk", "spot"]
N_PAIRS = 512  # query pairs per reference checked through Warp (of ~8,192), spread over all sources


def rel(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return np.abs(a - b) / np.abs(b)


@pytest.fixture(scope="module")
def released():
    return load_network(shared_path("checkpoints", "official", "GenNeuroGF.pth"))


@pytest.fixture(scope="module")
def refs():
    return {m: dict(np.load(shared_path("reference", "generalizable", f"{m}.npz"))) for m in MESHES}


@pytest.fixture(scope="module")
def random_net():
    """A network with random weights and random eval-mode BN statistics (so folding is exercised)."""
    torch.manual_seed(3)
    net = GenNeuroGF().double()
    for mod in net.modules():
        if isinstance(mod, torch.nn.BatchNorm2d):
            mod.running_mean.uniform_(-0.2, 0.2)
            mod.running_var.uniform_(0.5, 2.0)
            mod.weight.data.uniform_(0.5, 1.5)
            mod.bias.data.uniform_(-0.1, 0.1)
    return net.eval()


def test_state_dict_loads_strictly(released):
    sd = load_state_dict_file(shared_path("checkpoints", "official", "GenNeuroGF.pth"))
    assert is_generalizable_state_dict(sd)
    assert set(released.state_dict()) == set(sd)
    bad = dict(sd)
    bad.pop("fuse.conv.weight")
    with pytest.raises(ValueError, match="does not match"):
        load_network(bad)


@pytest.mark.slow
@pytest.mark.parametrize("mesh", MESHES)
def test_torch_network_matches_reference(released, refs, mesh):
    z = refs[mesh]
    with torch.no_grad():
        r = released(*(torch.tensor(z[k], dtype=torch.float64)[None] for k in ("points", "S", "T")))[0].numpy()
    e = rel(r, z["ratio"])
    assert e.mean() <= 1e-12 and e.max() <= 1e-9, (e.mean(), e.max())


def test_folding_matches_batchnorm(random_net):
    """Folded (W', b') reproduce conv + eval BN of every layer on random inputs."""
    L = folded_layers(random_net)
    x = torch.randn(7, 131, dtype=torch.float64)
    W, b = L["fuse"]
    ref = random_net.fuse(x.T[None, :, :, None])[0, :, :, 0].T
    assert torch.allclose(torch.relu(x @ W.T + b), ref, rtol=1e-12, atol=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("mode,mesh", [("fp64", "stanford-bunny"),
                                       ("fp32", "fandisk"), ("mixed", "spot")])
def test_warp_matches_reference(released, refs, mode, mesh):
    """The whole Warp path (encoder on the full 2,048-point cloud + query network) against the authors' float64
    ratios on a subsample of pairs covering every source."""
    z = refs[mesh]
    sel = np.linspace(0, len(z["ratio"]) - 1, N_PAIRS).astype(int)
    wn = WarpGenNet(released, "cpu", mode=mode, knn_chunks=1 if mode == "fp64" else 4)
    enc = wn.encode(z["points"])
    r = wn.ratio(enc, z["S"][sel], z["T"][sel]).numpy()
    e = rel(r, z["ratio"][sel])
    assert e.mean() <= 1e-5 and e.max() <= 1e-3, (e.mean(), e.max())
    if mode == "fp64":
        assert e.max() <= 1e-10


# ---- each kernel against float64 torch on fresh random inputs -------------------------------------------------

@pytest.mark.parametrize("chunks", [1, 3])
def test_knn_kernel_exact_with_ties(chunks):
    rng = np.random.default_rng(11)
    f = rng.standard_normal((90, 5))
    f[40:50] = f[0]  # exact duplicates of point 0: distance ties, broken by the smaller index
    f[60:70] = np.round(f[60:70], 1)
    k = kernels("fp64")
    dev = "cpu"
    n, kk = f.shape[0], 12
    g = chunks
    n_per = (n + g - 1) // g
    wide = np.concatenate([rng.standard_normal((n, 2)), f, rng.standard_normal((n, 2))], axis=1)
    F = wp.array(wide, dtype=wp.float64, device=dev)  # the kernel reads columns 2..6 only
    pd = wp.empty((n, g, kk), dtype=wp.float64, device=dev)
    pi = wp.empty((n, g, kk), dtype=wp.int32, device=dev)
    nbr = wp.empty((n, kk), dtype=wp.int32, device=dev)
    wp.launch(k.knn_partial, (n, g), inputs=[F, 2, f.shape[1], n_per, kk, pd, pi], device=dev)
    wp.launch(k.knn_merge, (n, g, kk), inputs=[pd, pi, nbr], device=dev)
    ref = knn_indices(torch.tensor(f)[None], kk, exact=True)[0].numpy()
    np.testing.assert_array_equal(nbr.numpy(), ref)
    assert (nbr.numpy()[:, 0] == np.arange(n))[:40].all()  # self first (no duplicates there)


@pytest.mark.parametrize("mode", ["fp64", "fp32"])
def test_encoder_kernels_random(random_net, mode):
    """Every encoder stage (3 kNN graphs, 3 EdgeConv blocks, pooling, per-point MLP, fuse precompute) on a random
    64-point cloud with random weights, against float64 torch."""
    torch.manual_seed(5)
    pts = torch.rand(1, 64, 3, dtype=torch.float64) * 2 - 1
    bb = random_net.backbone
    with torch.no_grad():
        i1 = knn_indices(pts, 40, exact=True)
        f1 = bb.econv_1(pts, i1)
        i2 = knn_indices(f1, 40, exact=True)
        f2 = bb.econv_2(f1, i2)
        i3 = knn_indices(f2, 40, exact=True)
        F = bb(pts)[0].numpy()  # f1..f3 enter F through the codeword and mlp, so F checks every block
        W, b = folded_layers(random_net)["fuse"]
        G = (F @ W[:, :128].T.numpy() + b.numpy())
    wn = WarpGenNet(random_net, "cpu", mode=mode, knn_chunks=2)
    enc = wn.encode(pts[0].numpy())
    tol = 1e-11 if mode == "fp64" else 2e-5
    if mode == "fp64":
        for got, want in zip(enc.neighbours, (i1, i2, i3)):
            np.testing.assert_array_equal(got.numpy(), want[0].numpy())
    scale = np.abs(F).max()
    assert np.abs(enc.feats.numpy() - F).max() <= tol * scale
    assert np.abs(enc.fused.numpy() - G).max() <= tol * np.abs(G).max()


@pytest.mark.parametrize("use_grid", [True, False])
def test_query_kernels_random(random_net, use_grid):
    """Nearest-point lookup (hash grid with fallback, and brute force) and the pair head on random queries, some
    far from the cloud (fallback path), against float64 torch."""
    torch.manual_seed(8)
    pts = torch.rand(1, 64, 3, dtype=torch.float64) * 2 - 1
    s = torch.randn(1, 200, 3, dtype=torch.float64) * 0.7
    t = torch.randn(1, 200, 3, dtype=torch.float64) * 0.7
    s[0, :20] *= 5  # far away: no cloud point within the grid radius
    t[0, 5] = pts[0, 3]  # a query exactly on a cloud point
    with torch.no_grad():
        want = random_net(pts, s, t)[0].numpy()
        from neurogf_warp.generalizable.network import nearest_indices
        nn_s = nearest_indices(pts, s)[0].numpy()
    wn = WarpGenNet(random_net, "cpu", mode="fp64", use_grid=use_grid)
    enc = wn.encode(pts[0].numpy())
    got_nn = wn.nearest(enc, wn._arr(s[0].numpy())).numpy()
    np.testing.assert_array_equal(got_nn, nn_s)
    got = wn.ratio(enc, s[0].numpy(), t[0].numpy()).numpy()
    assert np.abs(got - want).max() <= 1e-10 * max(1.0, np.abs(want).max())


def test_load_hook_dispatch(tmp_path):
    """hooks.load_if_generalizable: the released file -> a GeneralizableModel; another torch file -> None."""
    from neurogf_warp.generalizable.hooks import load_if_generalizable
    from neurogf_warp.generalizable.model import GeneralizableModel

    m = load_if_generalizable(shared_path("checkpoints", "official", "GenNeuroGF.pth"))
    assert isinstance(m, GeneralizableModel)
    assert load_if_generalizable(shared_path("checkpoints", "official", "NeuroGF_Pretrainer__bunny_final.pth")) is None
    junk = tmp_path / "x.pth"
    junk.write_bytes(b"not a checkpoint")
    assert load_if_generalizable(junk) is None


def test_encode_into_reuses_buffers(random_net):
    """encode(into=state) overwrites an earlier state with the same arrays and gives a fresh encode's result."""
    rng = np.random.default_rng(9)
    a, b = rng.uniform(-1, 1, (64, 3)), rng.uniform(-1, 1, (64, 3))
    wn = WarpGenNet(random_net, "cpu", mode="fp64")
    fresh = wn.encode(b).fused.numpy()
    st = wn.encode(a)
    ids = {k: v.ptr for k, v in st.scratch.items()}
    grid = st.grid
    again = wn.encode(b, into=st)
    assert again is st and st.grid is grid and {k: v.ptr for k, v in st.scratch.items()} == ids
    np.testing.assert_array_equal(st.fused.numpy(), fresh)


@pytest.mark.slow
@pytest.mark.parametrize("operand,tol", [("fp32", 1e-5), ("fp16", 5e-3)])
def test_tiled_query_matches_simt(released, operand, tol):
    """The tile-GEMM query path (tensor cores on CUDA) against the SIMT path on random pairs, fp32 mode; the
    fp16-operand variant within its documented ~1e-3 relative error; 0 for equal points, inf across labels."""
    rng = np.random.default_rng(2)
    wn = WarpGenNet(released, "cpu", mode="fp32")
    enc = wn.encode(rng.uniform(-1, 1, (64, 3)))
    s = rng.uniform(-1, 1, (50, 3)) * 3 + 1
    t = rng.uniform(-1, 1, (50, 3)) * 3 + 1
    t[7] = s[7]
    S, T = wn._arr(s), wn._arr(t)
    comp = np.zeros(50, np.int32)
    comp[3] = 1
    sc = wp.array(comp, dtype=wp.int32, device="cpu")
    tc = wp.zeros(50, dtype=wp.int32, device="cpu")
    want = wn.distances(enc, S, T, (1, 1, 1), 1 / 3, False, s_comp=sc, t_comp=tc).numpy()
    got = wn.distances_tiled(enc, S, T, (1, 1, 1), 1 / 3, s_comp=sc, t_comp=tc, block_pairs=16,
                             operand=operand).numpy()  # 50 pairs: the last block is partial
    assert got[7] == 0 and np.isinf(got[3]) and np.isinf(want[3])
    ok = np.isfinite(want) & (want > 0)
    assert (np.abs(got[ok] - want[ok]) / want[ok]).max() <= tol


@pytest.mark.parametrize("chunks", [1, 7, 32])
def test_column_max_two_passes(chunks):
    """The global max pooling as partial maxima of row chunks then their maximum (the GPU split) == numpy."""
    k = kernels("fp64")
    x = np.random.default_rng(chunks).standard_normal((1000, 320))
    per = (1000 + chunks - 1) // chunks
    chunks = (1000 + per - 1) // per
    part = wp.empty((chunks, 320), dtype=wp.float64, device="cpu")
    y = wp.empty((1, 320), dtype=wp.float64, device="cpu")
    wp.launch(k.column_max, (chunks, 320), inputs=[wp.array(x, dtype=wp.float64, device="cpu"), per, part],
              device="cpu")
    wp.launch(k.column_max, (1, 320), inputs=[part, chunks, y], device="cpu")
    np.testing.assert_array_equal(y.numpy()[0], x.max(axis=0))
