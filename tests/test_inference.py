"""Warp inference (CPU device) against the released checkpoints, exact geodesics and a float64 torch forward."""
import numpy as np
import pytest
import torch
import warp as wp

import neurogf_warp as ngf
from neurogf_warp.kernels.inference import mlp
from neurogf_warp.model.network import NeuroGFNet
from tests.conftest import shared_path

DEV = "cpu"


@pytest.fixture(scope="session", autouse=True)
def _precompile():
    wp.load_module(mlp, device=DEV)


def released(name, mesh=None):
    ck = {"stanford-bunny": "bunny"}.get(name, name)
    m = shared_path("meshes", f"{name}.obj") if mesh else None
    return ngf.load(shared_path("checkpoints", "official", f"NeuroGF_Pretrainer__{ck}_final.pth"), mesh=m)


def random_net(D, seed, **options):
    """A network with random weights and random BatchNorm statistics, in eval mode (float64)."""
    g = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    net = NeuroGFNet(D, **options).double()
    with torch.no_grad():
        for mod in net.modules():
            if isinstance(mod, torch.nn.modules.batchnorm._BatchNorm):
                mod.running_mean.copy_(0.2 * torch.randn(mod.num_features, generator=g))
                mod.running_var.copy_(0.5 + torch.rand(mod.num_features, generator=g))
                mod.weight.copy_(0.8 + 0.4 * torch.rand(mod.num_features, generator=g))
                mod.bias.copy_(0.1 * torch.randn(mod.num_features, generator=g))
    return net.eval()


@pytest.mark.parametrize("name", ["bunny", "fandisk"])
def test_matches_official_outputs(name):
    ref = np.load(shared_path("reference", "official", f"{name}.npz"))
    model = released(name)
    # raw: the network's own values (the official outputs are not raised to the straight line |p - q|)
    d = ngf.distance(model, ref["p"], ref["q"], device=DEV, raw=True)
    s = ngf.sdf(model, ref["p"], device=DEV)
    paths = ngf.path(model, ref["p"][:32], ref["q"][:32], m=128, device=DEV)
    assert d.dtype == np.float32 and d.shape == (256,)
    np.testing.assert_allclose(d, ref["gdist"], rtol=1e-5, atol=0)
    # SDF values cross zero; near it a relative bound is meaningless in float32, so add a 1e-7 floor
    # (about one float32 ulp at the unit-sphere scale; float32 weight rounding alone gives ~2e-9 there).
    np.testing.assert_allclose(s, ref["sdf_head"], rtol=1e-5, atol=1e-7)
    assert paths.shape == (32, 128, 3)
    assert np.abs(paths - ref["paths"]).max() <= 1e-5


def test_golden_parity_values():
    """Values published with the reference notes (bunny, float64 evaluation)."""
    model = released("bunny")
    p = np.array([[0.1, 0.2, 0.3], [-0.5, 0.0, 0.2]])
    q = np.array([[-0.4, 0.1, -0.2], [0.6, -0.3, 0.1]])
    np.testing.assert_allclose(ngf.distance(model, p, q, device=DEV), [0.7316605, 1.4584210], rtol=1e-6)
    np.testing.assert_allclose(ngf.sdf(model, p, device=DEV), [0.0356501, -0.1443545], rtol=1e-5)
    pts = ngf.path(model, p[:1], q[:1], device=DEV)[0]
    np.testing.assert_allclose(pts[[0, 63, 127]], [[0.116708, 0.157516, 0.297128], [-0.149426, 0.151460, 0.040065],
                                                   [-0.377735, 0.093600, -0.111356]], atol=2e-6)


@pytest.mark.slow
@pytest.mark.parametrize("name,bound", [("fandisk", 0.0028), ("stanford-bunny", 0.0045)])
def test_mre_against_exact_geodesics(name, bound):
    """SSAD of the released checkpoint on its mesh, over the 8 exact-reference sources."""
    model = released(name, mesh=True)
    ref = np.load(shared_path("reference", "exact", f"{name}.npz"))
    oi = ref["file_index"]  # vertex numbering = the file's own vertex records
    used = model.mesh.input_to_internal >= 0
    rel = []
    for i, s in enumerate(ref["sources"]):
        d = ngf.ssad(model, int(oi[s]), device=DEV)
        assert d.shape == (model.mesh.n_input,) and np.all(np.isfinite(d[used])) and np.all(np.isnan(d[~used]))
        ex = ref["dist"][i].astype(np.float64)
        ok = np.isfinite(ex) & (ex > 0)
        rel.append(np.abs(d[oi][ok] - ex[ok]) / ex[ok])
    mre = np.concatenate(rel).mean()
    print(f"{name}: MRE {100 * mre:.4f}%")
    assert mre <= bound


@pytest.mark.parametrize("D", [64, 256, 512])
def test_warp_matches_torch_float64_on_random_points(D):
    seed = int(np.random.SeedSequence().entropy % 2**31)  # fresh inputs each run; the seed is in the failure message
    rng = np.random.default_rng(seed)
    net = random_net(D, seed)
    model = ngf.Model(net=net)
    p = rng.uniform(-1, 1, (64, 3))
    q = rng.uniform(-1, 1, (64, 3))
    with torch.no_grad():
        P, Q = torch.from_numpy(p), torch.from_numpy(q)
        d_ref = net.distance(P, Q).numpy()
        s_ref = net.sdf(P).numpy()
        path_ref = net.path(P[:8], Q[:8], 16).numpy()
    scale_d = np.abs(d_ref).max()
    assert np.abs(ngf.distance(model, p, q, device=DEV, raw=True) - d_ref).max() <= 1e-5 * scale_d, f"seed {seed}"
    assert np.abs(ngf.sdf(model, p, device=DEV) - s_ref).max() <= 1e-5 * np.abs(s_ref).max(), f"seed {seed}"
    assert np.abs(ngf.path(model, p[:8], q[:8], m=16, device=DEV) - path_ref).max() <= 1e-5 * np.abs(path_ref).max(), \
        f"seed {seed}"


@pytest.mark.parametrize("D", [256, 512])
def test_ssad_matches_float64_with_cached_embeddings(D):
    """SSAD (tile head on cached vertex embeddings for D <= 256, the per-thread kernel above) against float64,
    for two sources in a row: the second call reuses the first one's cache."""
    import trimesh

    seed = int(np.random.SeedSequence().entropy % 2**31)
    rng = np.random.default_rng(seed)
    tm = trimesh.creation.icosphere(subdivisions=2)
    V = tm.vertices * np.array([2.0, 1.6, 1.2]) - 1.0
    mesh = ngf.load_mesh((V, tm.faces))
    net = random_net(D, seed, euclid=True)
    model = ngf.Model(net=net, mesh=mesh, center=mesh.center, scale=mesh.scale)
    x = torch.from_numpy(mesh.normalize(V))
    for src in rng.choice(len(V), 2, replace=False):
        with torch.no_grad():
            ref = net.distance(x[[src]].expand(len(V), 3), x).numpy() / mesh.scale
        got = ngf.ssad(model, int(src), device=DEV, raw=True)
        assert np.abs(got - ref).max() <= 1e-5 * np.abs(ref).max(), f"seed {seed}, source {src}"
    from neurogf_warp.inference.state import query_state

    assert (query_state(model, DEV).tile_head is not None) == (D <= 256)


@pytest.mark.parametrize("options", [dict(fourier=2, euclid=True, path_residual=True, path_window=True),
                                     dict(fourier=8, path_width=2), dict(euclid=True)])
def test_network_options_match_torch_float64(options, tmp_path):
    """Fourier inputs, the |p - q| distance term, residual (windowed) and wider path heads: every Warp query (pairs, SSAD,
    MSAD, SDF, paths) against the float64 torch network, in a moved and scaled mesh frame, after a file round trip."""
    import trimesh

    seed = int(np.random.SeedSequence().entropy % 2**31)
    rng = np.random.default_rng(seed)
    tm = trimesh.creation.icosphere(subdivisions=2)
    V = tm.vertices * np.array([2.0, 1.6, 1.2]) + 3.0
    mesh = ngf.load_mesh((V, tm.faces))
    net = random_net(64, seed, **options)
    ngf.save(ngf.Model(net=net, mesh=mesh, center=mesh.center, scale=mesh.scale), tmp_path / "m.ngf")
    model = ngf.load(tmp_path / "m.ngf")
    assert model.net.options == net.options
    to_net = lambda x: torch.from_numpy((x - mesh.center) * mesh.scale)
    p, q = V[rng.integers(0, len(V), 32)], V[rng.integers(0, len(V), 32)] + rng.normal(0, 0.1, (32, 3))
    with torch.no_grad():
        d_ref = net.distance(to_net(p), to_net(q)).numpy() / mesh.scale
        s_ref = net.sdf(to_net(p)).numpy() / mesh.scale
        path_ref = net.path(to_net(p[:8]), to_net(q[:8]), 16).numpy() / mesh.scale + mesh.center
        srcs = [3, 40]
        all_ref = np.stack([net.distance(to_net(V[[s]]).expand(len(V), 3), to_net(V)).numpy() for s in srcs]) / mesh.scale
    # float32 coordinates are off by ~6e-8 of their size, and a Fourier feature of frequency 2^(L-1) pi multiplies
    # that: the attainable accuracy falls with the top frequency (fourier=8: 16x the bound of fourier <= 4)
    tol = lambda ref: 1e-5 * 2 ** max(0, options.get("fourier", 0) - 4) * np.abs(ref).max()
    msg = f"seed {seed}, {options}"
    assert np.abs(ngf.distance(model, p, q, device=DEV, raw=True) - d_ref).max() <= tol(d_ref), msg
    assert np.abs(ngf.sdf(model, p, device=DEV) - s_ref).max() <= tol(s_ref), msg
    paths = ngf.path(model, p[:8], q[:8], m=16, project=None, device=DEV)
    assert np.abs(paths - path_ref).max() <= tol(path_ref), msg
    if options.get("path_window"):  # exact end points
        assert np.abs(paths[:, 0] - p[:8]).max() <= 1e-5 and np.abs(paths[:, -1] - q[:8]).max() <= 1e-5, msg
    assert np.abs(ngf.ssad(model, srcs[1], device=DEV, raw=True) - all_ref[1]).max() <= tol(all_ref), msg
    assert np.abs(ngf.msad(model, srcs, device=DEV, raw=True) - all_ref.min(0)).max() <= tol(all_ref), msg
    with torch.no_grad():  # p = q: the |p - q| term is 0, the rest is the constant gdf_head(0)
        self_ref = net.distance(to_net(p), to_net(p)).numpy() / mesh.scale
    assert np.ptp(self_ref) <= 1e-12
    assert np.abs(ngf.distance(model, p, p, device=DEV, raw=True) - self_ref).max() <= tol(d_ref), msg
    assert np.all(ngf.distance(model, p, p, device=DEV) == 0.0), msg  # the finished answer: exactly 0


def _project_ref(net, x, steps):
    """float64 reference of mlp.project_to_surface: the SDF head's autograd gradient and the same step limit."""
    for _ in range(steps):
        with torch.enable_grad():
            y = x.detach().requires_grad_(True)
            s = net.sdf(y)
            g, = torch.autograd.grad(s.sum(), y)
        s = s.detach()
        n = torch.linalg.vector_norm(g, dim=-1, keepdim=True)
        x = torch.where(n > 1e-12, x - s.unsqueeze(-1) * g / (n * n.clamp_min(0.5)).clamp_min(1e-30), x)
    return x


def _resample_ref(x, k):
    """Polylines (N, m, 3) to k points by linear interpolation in the point index (mlp.resample_paths)."""
    u = torch.linspace(0, x.shape[1] - 1, k, dtype=x.dtype)
    i0 = u.floor().long().clamp(max=x.shape[1] - 2)
    f = (u - i0)[None, :, None]
    return (1 - f) * x[:, i0] + f * x[:, i0 + 1]


def _sweep_ref(net, x):
    """One shortening sweep (mlp.relax_paths): inner points to their neighbours' midpoint, one Newton step."""
    mid = 0.5 * (x[:, :-2] + x[:, 2:])
    return torch.cat([x[:, :1], _project_ref(net, mid.reshape(-1, 3), 1).view_as(mid), x[:, -1:]], 1)


def test_projection_and_refinement_match_float64():
    """project() and the SDF refinement kernels against float64 references of the same method, on
    the released fandisk model (a trained SDF head: random weights have flat spots where Newton steps stall) and
    fresh random points near its surface and vertex pairs."""
    model = released("fandisk", mesh=True)
    mesh, net = model.mesh, model.net.double().eval()
    seed = int(np.random.SeedSequence().entropy % 2**31)
    rng = np.random.default_rng(seed)
    v = mesh.internal_normalized_vertices
    x = v[rng.integers(0, len(v), 64)] + rng.normal(0, 0.01, (64, 3))
    with torch.no_grad():
        x_ref = _project_ref(net, torch.from_numpy(x), 2).numpy()
    x_w = mesh.normalize(ngf.project(model, mesh.denormalize(x), device=DEV))
    # at a crease of the ReLU head, float32 rounding can put a Newton iterate on the other side of a kink: a few
    # points may differ by more than float32 noise
    err = np.abs(x_w - x_ref).max(-1)
    assert np.quantile(err, 0.95) <= 2e-5 and err.max() <= 1e-3, f"seed {seed}: {np.quantile(err, 0.95)}, {err.max()}"

    # the kernels, each from the same float32 input: resampling, then one sweep from head paths on the surface
    polys = rng.normal(size=(5, 9, 3)).astype(np.float32)
    fine = wp.empty((5, 33), dtype=wp.vec3, device=DEV)
    wp.launch(mlp.resample_paths, fine.shape, inputs=[wp.array(polys, dtype=wp.vec3, device=DEV)], outputs=[fine],
              device=DEV)
    assert np.abs(fine.numpy() - _resample_ref(torch.from_numpy(polys).double(), 33).numpy()).max() <= 1e-6
    i, j = rng.integers(0, len(v), 12), rng.integers(0, len(v), 12)
    p, q = torch.from_numpy(v[i]), torch.from_numpy(v[j])
    with torch.no_grad():
        x0 = torch.cat([p[:, None], _project_ref(net, net.path(p, q, 32)[:, 1:-1].reshape(-1, 3), 2).view(12, -1, 3),
                        q[:, None]], 1).float().double()
        ref = _sweep_ref(net, x0).numpy()
    ident = mlp.make_frame((0.0, 0.0, 0.0), 1.0)  # unit scale, no shift: normalized coordinates as they are
    got = wp.empty((12, 32), dtype=wp.vec3, device=DEV)
    wp.launch(mlp.relax_paths, got.shape, inputs=[ngf.warp_weights(model, DEV),
              wp.array(x0.numpy().astype(np.float32), dtype=wp.vec3, device=DEV), ident, 1], outputs=[got], device=DEV)
    err = np.abs(got.numpy() - ref).max(-1)
    assert np.quantile(err, 0.95) <= 2e-5 and err.max() <= 1e-3, f"seed {seed}: {np.quantile(err, 0.95)}, {err.max()}"


@pytest.mark.slow
def test_symmetry_and_ssad_equals_distance():
    model = released("fandisk", mesh=True)
    rng = np.random.default_rng()
    v = model.mesh.vertices
    p, q = v[rng.integers(0, len(v), 100)], v[rng.integers(0, len(v), 100)]
    np.testing.assert_array_equal(ngf.distance(model, p, q, device=DEV), ngf.distance(model, q, p, device=DEV))
    src = int(rng.integers(0, len(v)))
    d_all = ngf.ssad(model, src, device=DEV)
    d_pair = ngf.distance(model, np.repeat(v[src:src + 1], len(v), 0), v, device=DEV)
    np.testing.assert_allclose(d_all, d_pair, rtol=2e-6, atol=1e-6 * np.nanmax(d_all))
    # a source given as a point equals the source given as its vertex
    np.testing.assert_allclose(ngf.ssad(model, v[src], device=DEV), d_all, rtol=1e-6, atol=1e-7)


def test_msad_is_min_over_sources():
    model = released("fandisk", mesh=True)
    srcs = [5, 1000, 4000]
    per = np.stack([ngf.ssad(model, s, device=DEV) for s in srcs])
    np.testing.assert_allclose(ngf.msad(model, srcs, device=DEV), per.min(0), rtol=2e-6, atol=1e-7)


def test_mesh_units_and_numbering():
    """A mesh with an unused vertex, moved and scaled: outputs follow its numbering and its units."""
    base = released("fandisk", mesh=True)
    v, f = base.mesh.vertices, base.mesh.faces.astype(np.int64)
    v2 = np.vstack([[1e3, 1e3, 1e3], v * 2.0 + 5.0])  # an unreferenced vertex first, then the mesh
    moved = ngf.load(shared_path("checkpoints", "official", "NeuroGF_Pretrainer__fandisk_final.pth"), mesh=(v2, f + 1))
    d = ngf.ssad(moved, 1, device=DEV)
    assert d.shape == (len(v2),) and np.isnan(d[0])
    d_base = 2.0 * ngf.ssad(base, 0, device=DEV)
    # the moved copy's float32 coordinates round differently: allow 1e-6 of the largest distance
    np.testing.assert_allclose(d[1:], d_base, rtol=0, atol=1e-6 * d_base.max())
    with pytest.raises(IndexError, match="not used by any face"):
        ngf.ssad(moved, 0, device=DEV)


def test_torch_and_warp_arrays_in_and_out():
    model = released("bunny")
    rng = np.random.default_rng(0)
    p = rng.uniform(-0.5, 0.5, (10, 3)).astype(np.float32)
    q = rng.uniform(-0.5, 0.5, (10, 3)).astype(np.float32)
    ref = ngf.distance(model, p, q, device=DEV)
    dt = ngf.distance(model, torch.from_numpy(p), torch.from_numpy(q))
    assert isinstance(dt, torch.Tensor) and dt.dtype == torch.float32
    np.testing.assert_array_equal(dt.numpy(), ref)
    dw = ngf.distance(model, wp.array(p, dtype=wp.vec3, device=DEV), wp.array(q, dtype=wp.float32, device=DEV))
    assert isinstance(dw, wp.array)
    np.testing.assert_array_equal(dw.numpy(), ref)
    st = ngf.sdf(model, torch.from_numpy(p))
    assert isinstance(st, torch.Tensor) and st.shape == (10,)
    pt = ngf.path(model, torch.from_numpy(p), torch.from_numpy(q), m=8)
    assert isinstance(pt, torch.Tensor) and pt.shape == (10, 8, 3)
    # float32 torch input on the device is used in place (zero-copy)
    from neurogf_warp.common.arrays import as_points

    t = torch.from_numpy(p)
    arr, kind = as_points(t, "p", wp.get_device(DEV))
    assert kind == "torch" and arr.ptr == t.data_ptr()


@pytest.mark.slow
def test_user_kernel_can_call_distance():
    """The SIMT functions are usable inside a user's own Warp kernel."""
    model = released("bunny")

    @wp.kernel(enable_backward=False)
    def user_kernel(net: mlp.NeuroGFWeights, xs: wp.array(dtype=wp.vec3), goal: wp.vec3, out: wp.array(dtype=float)):
        i = wp.tid()
        out[i] = mlp.geodesic_distance(net, xs[i], goal) + 0.0 * mlp.signed_distance(net, xs[i])

    xs = np.random.default_rng(1).uniform(-0.5, 0.5, (8, 3)).astype(np.float32)
    goal = np.array([0.1, 0.2, 0.3], dtype=np.float32)
    out = wp.zeros(8, dtype=float, device=DEV)
    wp.launch(user_kernel, 8, inputs=[ngf.warp_weights(model, DEV), wp.array(xs, dtype=wp.vec3, device=DEV),
                                      wp.vec3(*goal), out], device=DEV)
    np.testing.assert_allclose(out.numpy(), ngf.distance(model, xs, np.repeat(goal[None], 8, 0), device=DEV), rtol=1e-6)


def test_bad_inputs():
    model = released("fandisk", mesh=True)
    nomesh = released("fandisk")
    with pytest.raises(ValueError, match="no mesh|needs the model's mesh"):
        ngf.ssad(nomesh, 0, device=DEV)
    with pytest.raises(IndexError, match="out of range"):
        ngf.ssad(model, 10**6, device=DEV)
    with pytest.raises(ValueError, match="non-finite"):
        ngf.distance(model, np.array([[np.nan, 0, 0]]), np.zeros((1, 3)), device=DEV)
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        ngf.sdf(model, np.zeros((4, 2)), device=DEV)
    with pytest.raises(ValueError, match="same shape"):
        ngf.distance(model, np.zeros((4, 3)), np.zeros((5, 3)), device=DEV)
    with pytest.raises(TypeError, match="numeric|floating"):
        ngf.sdf(model, np.array([["a", "b", "c"]]), device=DEV)
    with pytest.raises(ValueError, match="unknown device"):
        ngf.sdf(model, np.zeros((1, 3)), device="cuda:7")
    with pytest.raises(ValueError, match="unknown device"):
        ngf.geodesic_distances(model.mesh, [0], device="cuda:7")
    with pytest.raises(ValueError, match="m \\(points per path\\)"):
        ngf.path(model, np.zeros((1, 3)), np.ones((1, 3)), m=1, device=DEV)
    with pytest.raises(ValueError, match="refine"):
        ngf.path(model, np.zeros((1, 3)), np.ones((1, 3)), refine=-1, device=DEV)
    with pytest.raises(ValueError, match="steps"):
        ngf.project(model, np.zeros((1, 3)), steps=2.5, device=DEV)
    with pytest.raises(ValueError, match="one source"):
        ngf.ssad(model, [1, 2], device=DEV)


def test_paths_projected_onto_the_mesh_or_the_sdf():
    """project='mesh': every point on the mesh, with the face and barycentric weights that rebuild it;
    project='sdf': every point on the SDF head's surface; both keep the array kind and single-pair shapes."""
    model = released("fandisk", mesh=True)
    rng = np.random.default_rng()
    V = model.mesh.vertices
    i, j = rng.integers(0, len(V), 6), rng.integers(0, len(V), 6)
    pts, faces, bary = ngf.path(model, V[i], V[j], m=12, project="mesh", return_faces=True, device=DEV)
    assert pts.shape == (6, 12, 3) and faces.shape == (6, 12) and bary.shape == (6, 12, 3)
    corners = V[model.mesh.input_to_internal[_file_faces(model)[faces]]]  # (6, 12, 3 corners, 3)
    np.testing.assert_allclose((bary[..., None] * corners).sum(-2), pts, atol=1e-5 * np.abs(V).max())
    assert np.all(bary >= -1e-6) and np.allclose(bary.sum(-1), 1.0, atol=1e-5)
    on_sdf = ngf.path(model, V[i], V[j], m=12, project="sdf", device=DEV)
    raw = ngf.path(model, V[i], V[j], m=12, project=None, device=DEV)
    s = lambda x: np.abs(ngf.sdf(model, x.reshape(-1, 3), device=DEV))
    assert s(on_sdf).mean() < 0.1 * s(raw).mean()
    one = ngf.path(model, V[i[0]], V[j[0]], m=12, project="mesh", return_faces=True, device=DEV)
    assert [a.shape for a in one] == [(12, 3), (12,), (12, 3)]
    with pytest.raises(ValueError, match="project"):
        ngf.path(model, V[i], V[j], project="plane", device=DEV)
    with pytest.raises(ValueError, match="return_faces"):
        ngf.path(model, V[i], V[j], project=None, return_faces=True, device=DEV)


def _file_faces(model):
    """The mesh's faces in the file's vertex numbering (what snap_to_mesh's face indices refer to)."""
    return model.mesh.faces
