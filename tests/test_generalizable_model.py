"""The conditioned object: frame, units, queries, components, errors (Warp on the CPU)."""
import numpy as np
import pytest
import trimesh

import neurogf_warp as ngf
from neurogf_warp.generalizable.model import load, normalization

from .conftest import shared_path


@pytest.fixture(scope="module")
def model():
    return load(shared_path("checkpoints", "official", "GenNeuroGF.pth"))


@pytest.fixture(scope="module")
def cloud_cond(model):
    rng = np.random.default_rng(4)
    g = rng.standard_normal((300, 3))
    pts = g / np.linalg.norm(g, axis=1, keepdims=True) * np.array([3.0, 2.0, 1.0]) + np.array([10.0, -5.0, 2.0])
    return model.condition(pts)


@pytest.mark.slow
def test_mesh_conditioning_reproduces_reference(model):
    """condition(mesh) samples the authors' reference cloud (same sampler, seed and frame) and its distances are
    max(ratio, 1) * |s - t| in mesh units with the reference ratios."""
    z = np.load(shared_path("reference", "generalizable", "spot.npz"))
    cond = model.condition(shared_path("meshes", "spot.obj"))
    assert cond.mesh is not None and cond.points.shape == (2048, 3)
    np.testing.assert_allclose((cond.points - cond.center) * cond.scale, z["points"], atol=1e-6)
    np.testing.assert_allclose(cond.center, z["center"], rtol=1e-12, atol=1e-12)
    assert cond.scale == pytest.approx(float(z["scale"]), rel=1e-12)
    sel = np.arange(0, len(z["ratio"]), 16)
    S = z["S"][sel].astype(np.float64) / z["scale"] + z["center"]
    T = z["T"][sel].astype(np.float64) / z["scale"] + z["center"]
    want = np.maximum(z["ratio"][sel], 1.0) * np.linalg.norm(S - T, axis=1)
    got = cond.distance(S, T)
    ok = want > 0
    assert (np.abs(got - want)[ok] / want[ok]).max() <= 1e-5
    assert (got[~ok] == 0).all()
    # ssad by vertex index: one row per input vertex, 0 at the source, and equal to the pairwise call
    row = cond.ssad(7)
    assert row.shape == (cond.mesh.n_input,) and row[7] == 0
    v = np.asarray(cond.mesh.vertices)
    np.testing.assert_allclose(row[:50], cond.distance(np.repeat(v[7:8], 50, 0), v[:50]), rtol=1e-6)


def test_cloud_queries_and_units(model, cloud_cond):
    c = cloud_cond
    pts = c.points
    # frame: bounding-box centre, largest norm 1
    center, scale = normalization(pts)
    assert np.allclose(c.center, center) and c.scale == pytest.approx(scale)
    d = c.distance(pts[:40], pts[40:80])
    assert (d > 0).all() and np.isfinite(d).all()
    assert (d >= np.linalg.norm(pts[:40] - pts[40:80], axis=1) * (1 - 1e-6)).all()  # ratio floored at 1
    assert (c.distance(pts[:40], pts[:40]) == 0).all()
    np.testing.assert_array_equal(c.distance(pts[40:80], pts[:40]), d)  # exactly symmetric (|fs - ft|)
    assert isinstance(c.distance(pts[0], pts[1]), float)
    D = c.distance_matrix([0, 3, 5])
    assert D.shape == (3, len(pts)) and D[1, 3] == 0
    np.testing.assert_array_equal(D[1], c.ssad(3))
    np.testing.assert_allclose(D[2], c.distance(np.repeat(pts[5:6], len(pts), 0), pts), rtol=1e-6)
    np.testing.assert_array_equal(c.msad([0, 3, 5]), D.min(axis=0))
    Dt = c.distance_matrix(pts[:4], pts[10:13])
    np.testing.assert_allclose(Dt[0], c.distance(np.repeat(pts[:1], 3, 0), pts[10:13]), rtol=1e-6)
    # units: the same shape scaled by 10 (and moved) answers 10x the distances
    c10 = model.condition(pts * 10.0 + 1.0)
    np.testing.assert_allclose(c10.distance(pts[:40] * 10 + 1, pts[40:80] * 10 + 1), 10 * d, rtol=1e-5)


def test_components_give_inf(model):
    a = trimesh.creation.icosphere(subdivisions=2)
    b = trimesh.creation.icosphere(subdivisions=2)
    b.vertices += np.array([3.0, 0.0, 0.0])
    mesh = ngf.load_mesh((np.vstack([a.vertices, b.vertices]), np.vstack([a.faces, b.faces + len(a.vertices)])))
    assert mesh.n_components == 2
    c = model.condition(mesh, n_points=400, seed=1)
    na = len(a.vertices)
    row = c.ssad(0)
    assert np.isinf(row[na:]).all() and np.isfinite(row[:na]).all() and row[0] == 0
    # points (not indices) take the component of the closest triangle
    p = np.array([[1.02, 0.0, 0.0], [3.0, 0.0, 1.01], [0.0, 0.99, 0.0]])
    q = np.array([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])
    d = c.distance(p, q)
    assert np.isfinite(d[0]) and np.isinf(d[1]) and np.isfinite(d[2])
    np.testing.assert_array_equal(np.isinf(c.ssad(p[1])), np.arange(mesh.n_input) < na)
    np.testing.assert_array_equal(c.msad([0, na]), np.fmin(c.ssad(0), c.ssad(na)))
    assert np.isfinite(c.msad([0, na])).all()


def test_bad_input_is_refused(model, cloud_cond):
    c = cloud_cond
    with pytest.raises(ValueError, match="shape"):
        model.condition(np.zeros((100, 2)))
    with pytest.raises(ValueError, match="non-finite"):
        model.condition(np.where(np.arange(300)[:, None] == 5, np.nan, c.points))
    with pytest.raises(ValueError, match="at least"):
        model.condition(c.points[:10])
    with pytest.raises(ValueError, match="coincide"):
        model.condition(np.ones((50, 3)))
    with pytest.raises(ValueError, match="same number"):
        c.distance(c.points[:3], c.points[:4])
    with pytest.raises(ValueError, match="non-finite"):
        c.distance([[0, 0, np.inf]], c.points[:1].tolist())
    with pytest.raises(ValueError, match="empty"):
        c.msad([])
    with pytest.raises(IndexError):
        c.ssad(10_000)
    with pytest.raises(ValueError, match="one source"):
        c.ssad([1, 2])
    with pytest.raises(ValueError, match="one source"):
        c.ssad([1, 2, 3])


def test_load_errors(tmp_path):
    with pytest.raises(ValueError, match="no such file"):
        load(tmp_path / "missing.pth")
    with pytest.raises(ValueError, match="does not match"):
        load(shared_path("checkpoints", "official", "NeuroGF_Pretrainer__bunny_final.pth"))
