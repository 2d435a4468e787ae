"""The in-kernel API (kernels.field, kernels.mlp gradients) and mesh snapping (surface.snap_to_mesh), on Warp's CPU."""
import numpy as np
import pytest
import torch
import warp as wp

import neurogf_warp as ngf
from neurogf_warp.surface import snap_to_mesh

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
        np.testing.assert_allclose(pts, ref[np.arange(len(x)), face], atol=2e-5 * scale, err_msg=msg)
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
        snap_to_mesh(ngf.Model(net=ngf.network.NeuroGFNet(64)), paths, device=DEV)
