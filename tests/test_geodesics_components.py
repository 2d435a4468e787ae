"""Ground-truth solver on meshes made of several parts: inf exactly between parts, no path across (Warp CPU)."""
import numpy as np
import pytest

from neurogf_warp.ground_truth import geodesics as G
from neurogf_warp.mesh.mesh import load_mesh
from tests import geodesic_meshes as M


@pytest.fixture(scope="module", autouse=True)
def compiled():
    G.load_kernels("cpu")


def test_two_spheres():
    Va, Fa = M.icosphere(2)
    Vb, Fb = M.icosphere(2, axes=(0.5, 0.5, 0.5))
    V = np.concatenate([Va, Vb + np.array([3.0, 0.0, 0.0])])
    F = np.concatenate([Fa, Fb + len(Va)])
    na = len(Va)
    d = G.geodesic_distances((V, F), [0, na + 5], device="cpu")
    assert np.isfinite(d[0, :na]).all() and np.isinf(d[0, na:]).all()
    assert np.isinf(d[1, :na]).all() and np.isfinite(d[1, na:]).all()
    assert d[0, 0] == 0.0 and d[1, na + 5] == 0.0
    # within a sphere: the great-circle distance up to the polyhedral chord error
    ang = np.arccos(np.clip(Va @ Va[0], -1.0, 1.0))
    assert np.all(np.abs(d[0, :na] - ang) <= 0.03 * ang + 1e-6)
    paths = G.geodesic_paths((V, F), 0, [10, na + 1], device="cpu")
    assert len(paths[0]) >= 2 and np.isfinite(paths[0]).all()
    assert paths[1].shape == (0, 3)  # no surface path reaches the other sphere
    r = G.geodesic_paths((V, F), 0, [10, na + 1], m=16, device="cpu")
    assert np.isfinite(r[0]).all() and np.isnan(r[1]).all()


def test_44_parts():
    V, F, part = M.scattered_parts(44)
    msh = load_mesh((V, F))
    assert msh.n_components == 44 and np.array_equal(msh.internal_components, part)
    src = np.array([0, 14, 200, len(V) - 1])
    d = G.geodesic_distances((V, F), src, device="cpu")
    same = part[None, :] == part[src][:, None]
    assert np.array_equal(np.isfinite(d), same)
    assert np.all(d[same] >= 0) and np.all(d[np.arange(len(src)), src] == 0)
    solver = G.GeodesicSolver(msh, device="cpu", batch=len(src))
    solver.run(msh.vertex(src))
    rows = np.repeat(np.arange(len(src)), 30).astype(np.int32)
    tg = np.tile(np.arange(0, len(V), len(V) // 30)[:30], len(src)).astype(np.int32)
    pts, offs, flags = solver.trace(rows, tg)
    assert np.all(flags == 0)
    n = np.diff(offs)
    assert np.array_equal(n > 0, part[tg] == part[src[rows]])  # paths only within a part
