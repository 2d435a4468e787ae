"""The in-kernel API (kernels.field, kernels.mlp gradients) and mesh snapping (surface.snap_to_mesh), on Warp's CPU."""
import numpy as np
import pytest
import torch
import warp as wp

import neurogf_warp as ngf
from neurogf_warp.mesh.surface import snap_to_mesh

DEV = "cpu"


def fresh_seed() -> int:
    return int(np.random.SeedSequence().entropy % 2**31)  # fresh inputs each run; the seed goes in failure messages


# ---- closest points on a mesh ---------------------------------------------------------------------

def closest_on_triangles(p, a, b, c):
    """Brute-force float64 closest point of each p (N, 3) on each triangle (F, 3) x 3: (N, F, 3).

    The plane projection when it falls inside the triangle, else the closest of the three edge points."""
    p = p[:, None]
    n = np.cross(b - a, c - a)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    proj = p - ((p - a) * n).sum(-1, keepdims=True) * n
    # barycentric coordinates of the projection
    v0, v1, v2 = b - a, c - a, proj - a
    d00, d01, d11 = (v0 * v0).sum(-1), (v0 * v1).sum(-1), (v1 * v1).sum(-1)
    d20, d21 = (v2 * v0).sum(-1), (v2 * v1).sum(-1)
    den = d00 * d11 - d01 * d01
    w1 = (d11 * d20 - d01 * d21) / den
    w2 = (d00 * d21 - d01 * d20) / den
    inside = (w1 >= 0) & (w2 >= 0) & (w1 + w2 <= 1)

    def seg(s, e):
        t = np.clip(((p - s) * (e - s)).sum(-1, keepdims=True) / ((e - s) ** 2).sum(-1, keepdims=True), 0, 1)
        return s + t * (e - s)

    cands = np.stack([seg(a, b), seg(b, c), seg(c, a)])  # (3, N, F, 3)
    best = np.take_along_axis(cands, np.linalg.norm(cands - p, axis=-1).argmin(0)[None, ..., None], 0)[0]
    return np.where(inside[..., None], proj, best)


def random_meshes(rng):
    """A random triangle soup and a noisy, moved and scaled sphere whose file has unused vertices, so that
    the file's vertex numbering differs from the internal one."""
    import trimesh

    soup_v = rng.uniform(-1, 1, (3 * 40, 3))
    soup_f = np.arange(3 * 40).reshape(-1, 3)
    sph = trimesh.creation.icosphere(subdivisions=2)
    v = sph.vertices * (1 + 0.15 * rng.standard_normal((len(sph.vertices), 1))) * rng.uniform(0.5, 3) + rng.normal(0, 2, 3)
    v = np.concatenate([rng.normal(0, 5, (3, 3)), v])  # 3 unused vertices first
    f = sph.faces + 3
    return [(soup_v, soup_f), (v, f[rng.permutation(len(f))])]


def test_snap_to_mesh_matches_brute_force():
    seed = fresh_seed()
    rng = np.random.default_rng(seed)
    for V, F in random_meshes(rng):
        a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
        # points near the surface (random faces, random barycentrics, random offsets) and a few far away
        k = rng.integers(0, len(F), 250)
        w = rng.dirichlet(np.ones(3), 250)
        near = w[:, :1] * a[k] + w[:, 1:2] * b[k] + w[:, 2:] * c[k] + rng.normal(0, 0.05, (250, 3)) * np.ptp(V, 0)
        x = np.concatenate([near, V.mean(0) + rng.normal(0, 10, (30, 3))])
        ref = closest_on_triangles(x, a, b, c)
        dist = np.linalg.norm(ref - x[:, None], axis=-1)
        best = dist.min(1)
        pts, face, bary = snap_to_mesh((V, F), x, device=DEV)
        assert pts.shape == x.shape and face.shape == (len(x),) and bary.shape == x.shape
        assert pts.dtype == np.float32 and face.dtype == np.int32
        scale = np.abs(V).max()
        msg = f"seed {seed}"
        np.testing.assert_allclose(np.linalg.norm(pts - x, axis=1), best, atol=2e-6 * scale, err_msg=msg)
        # the reported face is a closest one (ties allowed), the point lies on it, the weights rebuild it
        assert np.all(dist[np.arange(len(x)), face] <= best + 2e-6 * scale), msg
        # where the surface is nearly flat across from x, float32 moves the closest point along it by up to
        # sqrt(2 d tol) for a distance tolerance tol (the distance changes by only delta^2 / 2d)
        off = np.linalg.norm(pts - ref[np.arange(len(x)), face], axis=1)
        assert np.all(off <= 2e-5 * scale + np.sqrt(2 * best * 2e-6 * scale)), (msg, off.max())
        assert np.all(bary >= -1e-6) and np.allclose(bary.sum(1), 1, atol=1e-5), msg
        rebuilt = np.einsum("nk,nkc->nc", bary, V[F[face]])
        np.testing.assert_allclose(rebuilt, pts, atol=2e-5 * scale, err_msg=msg)


def test_snap_to_mesh_shapes_kinds_and_errors():
    import trimesh

    tm = trimesh.creation.icosphere(subdivisions=1)
    rng = np.random.default_rng(fresh_seed())
    paths = rng.normal(0, 1, (4, 7, 3))
    p, f, b = snap_to_mesh(tm, paths, device=DEV)
    assert p.shape == (4, 7, 3) and f.shape == (4, 7) and b.shape == (4, 7, 3)
    r = np.linalg.norm(p, axis=-1)
    assert np.all((r > 0.9) & (r < 1 + 1e-6))  # on the faces of a unit icosphere (face centres at r = 0.93)
    pt, ft, bt = snap_to_mesh(tm, torch.from_numpy(paths), device=DEV)
    assert isinstance(pt, torch.Tensor) and tuple(pt.shape) == (4, 7, 3) and tuple(ft.shape) == (4, 7)
    np.testing.assert_array_equal(ft.numpy(), f)
    pw, fw, bw = snap_to_mesh(tm, wp.array(paths.astype(np.float32), dtype=wp.vec3, device=DEV))
    assert isinstance(pw, wp.array) and pw.shape == (4, 7) and fw.shape == (4, 7)
    np.testing.assert_allclose(pw.numpy(), p, atol=1e-6)
    p0, f0, b0 = snap_to_mesh(tm, np.zeros((0, 3)), device=DEV)
    assert p0.shape == (0, 3) and f0.shape == (0,)
    with pytest.raises(ValueError, match="points must have shape"):
        snap_to_mesh(tm, np.zeros((5, 2)), device=DEV)
    with pytest.raises(ValueError, match="non-finite"):
        snap_to_mesh(tm, np.full((2, 3), np.nan), device=DEV)
    with pytest.raises(ValueError, match="has no mesh"):
        snap_to_mesh(ngf.Model(net=ngf.model.network.NeuroGFNet(64)), paths, device=DEV)


# ---- gradients inside user kernels ------------------------------------------------------------------

from neurogf_warp.inference.warp_structs import frame, source_set, weights  # noqa: E402
from neurogf_warp.kernels import field  # noqa: E402
from tests.test_inference import random_net, released  # noqa: E402

FD_STEP = 1e-6  # finite differences of the float64 torch forward pass, normalized frame


def _fd_error(got, sided):
    """Relative error of gradients (N, 3) against one-sided differences (2, N, 3): per component the closer of
    the forward and backward difference, so that a ReLU kink within FD_STEP on one side does not count."""
    err = np.abs(got[None] - sided).min(0)
    return np.linalg.norm(err, axis=-1) / np.maximum(np.linalg.norm(got, axis=-1), 1e-12)


@wp.kernel(enable_backward=False)
def _pair_queries(net: field.NeuroGFWeights, p: wp.array(dtype=wp.vec3), q: wp.array(dtype=wp.vec3),
                  d: wp.array(dtype=float), gp: wp.array(dtype=wp.vec3), gq: wp.array(dtype=wp.vec3),
                  s: wp.array(dtype=float), gs: wp.array(dtype=wp.vec3)):
    """What a user kernel does: distance and both gradients, SDF and its gradient."""
    i = wp.tid()
    a, g = field.distance_and_gradient(net, p[i], q[i])
    b, h = field.distance_and_gradient(net, q[i], p[i])
    d[i] = a
    gp[i] = g
    gq[i] = h
    c, n = field.signed_distance_and_gradient(net, p[i])
    s[i] = c
    gs[i] = n


@wp.kernel(enable_backward=False)
def _source_queries(net: field.NeuroGFWeights, src: field.SourceSet, fr: field.Frame, x: wp.array(dtype=wp.vec3),
                    d: wp.array(dtype=float), d2: wp.array(dtype=float), g: wp.array(dtype=wp.vec3),
                    arg: wp.array(dtype=int), d3: wp.array(dtype=float), t: wp.array(dtype=wp.vec3)):
    """Mesh-frame points through the frame; distances back in mesh units."""
    i = wp.tid()
    y = field.to_net(fr, x[i])
    d[i] = field.distance_to_sources(net, src, y) * fr.dscale
    a, b, c = field.distance_to_sources_and_gradient(net, src, y)
    d2[i] = a * fr.dscale
    g[i] = b
    arg[i] = c
    e, f = field.geodesic_direction(net, src, y)
    d3[i] = e * fr.dscale
    t[i] = f


def _run_pairs(model, p, q):
    n = len(p)
    P, Q = (wp.array(a.astype(np.float32), dtype=wp.vec3, device=DEV) for a in (p, q))
    outs = [wp.zeros(n, dtype=float, device=DEV), wp.zeros(n, dtype=wp.vec3, device=DEV),
            wp.zeros(n, dtype=wp.vec3, device=DEV), wp.zeros(n, dtype=float, device=DEV),
            wp.zeros(n, dtype=wp.vec3, device=DEV)]
    wp.launch(_pair_queries, n, inputs=[weights(model, DEV), P, Q], outputs=outs, device=DEV)
    return [o.numpy() for o in outs]


def _torch_grads(net, p, q):
    """float64 torch autograd at the float32-rounded points: d, d/dp, d/dq, sdf, d sdf/dp."""
    P = torch.from_numpy(p.astype(np.float32).astype(np.float64)).requires_grad_(True)
    Q = torch.from_numpy(q.astype(np.float32).astype(np.float64)).requires_grad_(True)
    d = net.distance(P, Q)
    gp, gq = torch.autograd.grad(d.sum(), (P, Q))
    X = P.detach().clone().requires_grad_(True)
    s = net.sdf(X)
    gs, = torch.autograd.grad(s.sum(), X)
    with torch.no_grad():  # one-sided differences, independent of autograd: (forward, backward), (2, N, 3)
        eye = FD_STEP * torch.eye(3, dtype=torch.float64)
        P0, Q0 = P.detach(), Q.detach()
        sided = lambda f: torch.stack([torch.stack([(f(P0 + h * eye[c]) - f(P0)) / (h * FD_STEP) for c in range(3)], -1)
                                       for h in (1.0, -1.0)])
        fd = sided(lambda x: net.distance(x, Q0))
        fds = sided(net.sdf)
    return d.detach().numpy(), gp.numpy(), gq.numpy(), s.detach().numpy(), gs.numpy(), fd.numpy(), fds.numpy()


def _rel(a, b):
    return np.linalg.norm(a - b, axis=-1) / np.maximum(np.linalg.norm(b, axis=-1), 1e-12)


def _check_gradients(model, p, q, msg):
    d, gp, gq, s, gs = _run_pairs(model, p, q)
    rd, rgp, rgq, rs, rgs, fd, fds = _torch_grads(model.net.double().eval(), p, q)
    assert np.abs(d - rd).max() <= 1e-5 * np.abs(rd).max(), msg
    assert np.abs(s - rs).max() <= 1e-5 * np.abs(rs).max() + 1e-7, msg
    # against float64 autograd and float64 finite differences: float32 weights and activations give ~1e-6; a
    # point whose float32 pre-activation falls on the other side of a ReLU kink than in float64 may differ more,
    # so allow 1% of such points, and at least one (random nets, 96 points: one such point in 7 of 451 draws at
    # D = 128 and 512, never two)
    for r, what in ((_rel(gp, rgp), "d/dp"), (_rel(gq, rgq), "d/dq"), (_rel(gs, rgs), "d sdf/dx"),
                    (_fd_error(gp, fd), "d/dp vs FD"), (_fd_error(gs, fds), "d sdf/dx vs FD")):
        assert np.median(r) <= 1e-5 and np.sum(r > 1e-4) <= max(1, 0.01 * len(r)), \
            f"{msg}, {what}: {np.quantile(r, [0.5, 0.99, 1])}"
    return _rel(gp, rgp), _fd_error(gp, fd)


@pytest.mark.parametrize("D,options", [(64, {}), (128, dict(fourier=3, euclid=True)), (512, dict(euclid=True))])
def test_gradients_match_autograd_and_differences_random_nets(D, options):
    seed = fresh_seed()
    rng = np.random.default_rng(seed)
    model = ngf.Model(net=random_net(D, seed, **options))
    p, q = rng.uniform(-1, 1, (96, 3)), rng.uniform(-1, 1, (96, 3))
    _check_gradients(model, p, q, f"seed {seed}, D={D}, {options}")


@pytest.mark.slow
@pytest.mark.parametrize("name", ["fandisk", "bunny"])
def test_gradients_match_autograd_and_differences_released(name):
    seed = fresh_seed()
    rng = np.random.default_rng(seed)
    model = released(name)
    ref = np.load(shared_path_official(name))
    p = ref["p"][rng.permutation(256)[:64]]
    q = ref["q"][rng.permutation(256)[:64]]
    _check_gradients(model, p + rng.normal(0, 0.01, p.shape), q, f"seed {seed}, {name}")


def shared_path_official(name):
    from tests.conftest import shared_path

    return shared_path("reference", "official", f"{name}.npz")


def test_source_set_in_mesh_frame():
    """A bound source set on the released fandisk model: distances in mesh units equal the float64 network's
    MSAD; the gradient is the nearest source's, against float64 autograd; the direction is a unit tangent
    vector going downhill."""
    seed = fresh_seed()
    rng = np.random.default_rng(seed)
    model = released("fandisk", mesh=True)
    mesh = model.mesh
    srcs = rng.choice(mesh.n_input, 3, replace=False)
    # query points other than the sources: at a source the distance has no gradient to compare
    verts = rng.choice(np.setdiff1d(np.arange(len(mesh.vertices)), srcs), 48, replace=False)
    x = mesh.vertices[verts]
    n = len(x)
    outs = [wp.zeros(n, dtype=float, device=DEV), wp.zeros(n, dtype=float, device=DEV),
            wp.zeros(n, dtype=wp.vec3, device=DEV), wp.zeros(n, dtype=int, device=DEV),
            wp.zeros(n, dtype=float, device=DEV), wp.zeros(n, dtype=wp.vec3, device=DEV)]
    wp.launch(_source_queries, n, inputs=[weights(model, DEV), source_set(model, srcs, DEV), frame(model),
                                          wp.array(x.astype(np.float32), dtype=wp.vec3, device=DEV)],
              outputs=outs, device=DEV)
    d, d2, g, arg, d3, t = (o.numpy() for o in outs)
    msg = f"seed {seed}"
    np.testing.assert_array_equal(d, d2)
    np.testing.assert_array_equal(d, d3)
    net = model.net.double().eval()
    X = torch.from_numpy(mesh.normalize(x).astype(np.float32).astype(np.float64)).requires_grad_(True)
    S = torch.from_numpy(mesh.normalize(mesh.internal_vertices[mesh.vertex(srcs)]).astype(np.float32).astype(np.float64))
    all_d = torch.stack([net.distance(X, S[k].expand_as(X)) for k in range(len(S))])  # (3, n)
    ref = all_d.min(0).values.detach().numpy() / mesh.scale  # MSAD in mesh units
    np.testing.assert_allclose(d, ref, rtol=1e-5, atol=1e-5 * ref.max(), err_msg=msg)
    best = all_d.argmin(0)
    gap = (all_d.sort(0).values[1] - all_d.min(0).values).detach().numpy()
    clear = gap > 1e-4  # not on a ridge between two sources
    assert np.all(arg[clear] == best.numpy()[clear]), msg
    gx, = torch.autograd.grad(all_d.min(0).values.sum(), X)
    r = _rel(g, gx.numpy())[clear]
    assert np.median(r) <= 1e-5 and np.mean(r > 1e-4) <= 0.02, f"{msg}: {np.quantile(r, [0.5, 1])}"
    Y = X.detach().clone().requires_grad_(True)
    nrm, = torch.autograd.grad(net.sdf(Y).sum(), Y)
    nn = np.linalg.norm(nrm.numpy(), axis=1, keepdims=True)
    nrm = nrm.numpy() / np.maximum(nn, 1e-30)
    # away from the sources, where the direction is defined, and where the SDF head is not flat (a trained head
    # can have every unit of a layer off at a few points: gradient 0, no tangent plane)
    far = clear & (d > 0.05 * d.max()) & (nn[:, 0] > 1e-3)
    tl = np.linalg.norm(t, axis=1)
    assert np.allclose(tl[far], 1, atol=1e-5), msg
    assert np.abs((t * nrm).sum(1))[far].max() <= 1e-4, msg  # tangent to the SDF level set
    assert np.all((t * gx.numpy()).sum(1)[far] < 0), msg  # downhill


def test_source_set_bad_input():
    model = released("fandisk", mesh=True)
    with pytest.raises(ValueError, match="sources is empty"):
        source_set(model, np.zeros((0, 3)), DEV)
    with pytest.raises(IndexError, match="out of range"):
        source_set(model, [10**7], DEV)
