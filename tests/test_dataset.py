"""Dataset builder: layout contract, component handling, atomic save/load checks, SDF truth."""
import json
import os
import sys

import numpy as np
import pytest
import trimesh

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from neurogf_warp import dataset as D  # noqa: E402
from neurogf_warp.mesh import load_mesh  # noqa: E402

SMALL = dict(n_sources=6, n_global=32, n_local1=8, n_local2=16, n_path_sources=2, n_path_global=4,
             n_path_local=3, n_test=2, n_surface=30000, n_spread=200, progress=False, device="cpu")


@pytest.fixture(scope="module")
def two_blobs():
    a = trimesh.creation.icosphere(subdivisions=2)
    b = trimesh.creation.icosphere(subdivisions=2)
    b.vertices = b.vertices * 0.5 + np.array([3.0, 0.0, 0.0])
    return np.concatenate([a.vertices, b.vertices]), np.concatenate([a.faces, b.faces + len(a.vertices)])


@pytest.fixture(scope="module")
def built(two_blobs, tmp_path_factory):
    from neurogf_warp.geodesics import load_kernels

    load_kernels("cpu")
    path = tmp_path_factory.mktemp("ds") / "blobs.npz"
    data = D.build_dataset(two_blobs, path, **SMALL)
    return path, data


def test_layout(built, two_blobs):
    path, _ = built
    d = D.load_dataset(path, two_blobs)
    assert set(D.DATASET_KEYS) <= set(d)
    S = len(d["gd_src"])
    assert d["vertices"].dtype == np.float32 and d["faces"].dtype == np.int32
    assert d["gd_global"].shape == (S, 32, 7) and d["gd_local1"].shape == (S, 8, 7)
    assert d["gd_local2"].shape == (S, 16, 7)
    assert d["path_global"].shape == (2, 4, 128, 3) and d["path_local"].shape == (2, 3, 32, 3)
    assert d["surface_points"].shape[0] >= 30000
    assert d["test_dist"].shape == (2, len(d["vertices"]))
    assert not set(d["test_src"]) & set(d["gd_src"])
    assert np.abs(np.linalg.norm(d["vertices"], axis=1).max() - 1) < 1e-6  # normalized frame
    m = load_mesh(two_blobs)
    np.testing.assert_allclose(d["center"], m.center) and np.testing.assert_allclose(d["scale"], m.scale)
    assert json.dumps(d["meta"])  # JSON round trip


def test_rows_consistent_and_same_component(built):
    _, d = built
    V = d["vertices"]
    na = 642  # icosphere(2) vertex count: the first blob
    for s, rows in zip(d["gd_src"], d["gd_global"]):
        np.testing.assert_allclose(rows[:, :3], np.repeat(V[[s]], len(rows), 0))
        assert np.all(np.isfinite(rows[:, 6]))
        tgt = np.argmin(np.linalg.norm(V[None] - rows[:, None, 3:6], axis=2), axis=1)
        assert np.all((tgt < na) == (s < na))  # never paired across components
        eu = np.linalg.norm(rows[:, 3:6] - rows[:, :3], axis=1)
        assert np.all(rows[:, 6] >= eu * (1 - 1e-5))  # geodesic >= Euclidean
    # local_1 = the nearest targets: no further than any global target
    assert np.all(d["gd_local1"][:, :, 6].max(1) <= d["gd_global"][:, :, 6].max(1) + 1e-6)
    for s, P in zip(d["path_src"], d["path_global"]):
        np.testing.assert_allclose(P[:, 0], np.repeat(V[[s]], len(P), 0), atol=1e-5)


def test_bad_files(built, tmp_path):
    path, data = built
    bad = tmp_path / "trunc.npz"
    bad.write_bytes(path.read_bytes()[:1000])
    with pytest.raises(ValueError):
        D.load_dataset(bad)
    other = trimesh.creation.icosphere(subdivisions=1)
    with pytest.raises(ValueError, match="different mesh"):
        D.load_dataset(path, (other.vertices, other.faces))
    part = tmp_path / "part.npz"
    np.savez(part, vertices=data["vertices"])
    with pytest.raises(ValueError, match="missing keys"):
        D.load_dataset(part)
    assert not [f for f in os.listdir(path.parent) if f.endswith(".tmp")]


def test_sdf_truth_and_sampling():
    s = trimesh.creation.icosphere(subdivisions=3)
    rng = np.random.default_rng(0)
    surf = D.surface_samples(load_mesh((s.vertices, s.faces)), 3000, rng)
    q = D.sample_sdf_points(rng, surf, 900)
    assert q.shape == (900, 3) and np.abs(q[:300]).max() <= 1.01
    assert np.abs(np.linalg.norm(q[600:] - q[600:], axis=1)).max() == 0
    sdf = D.sdf_truth((s.vertices, s.faces), q, device="cpu")
    r = np.linalg.norm(q, axis=1)
    np.testing.assert_allclose(sdf, r - 1, atol=0.01)  # unit sphere up to chord error
    assert np.all(np.sign(sdf[np.abs(r - 1) > 0.02]) == np.sign(r - 1)[np.abs(r - 1) > 0.02])
    # an open mesh (hemisphere) uses the winding number: sign still right well inside/outside
    keep = s.vertices[s.faces].mean(1)[:, 2] > -0.3
    p = np.array([[0, 0, 0.2], [0, 0, 2.0]])
    sd = D.sdf_truth((s.vertices, s.faces[keep]), p, device="cpu")
    assert sd[0] < 0 < sd[1]


def test_target_pool_all_reaches_vertices_outside_the_spread_set(two_blobs):
    """target_pool="all": global distance and path targets come from every vertex, not only the spread ones."""
    m = load_mesh(two_blobs)
    opts = dict(SMALL, n_spread=100, n_global=64, n_path_global=16)
    spread = set(D.spread_vertices(m, min(100, len(m.vertices) // 2)).tolist())
    V = m.normalized_vertices.astype(np.float32)
    for pool, want_outside in (("spread", False), ("all", True)):
        d = D.build_dataset(two_blobs, None, target_pool=pool, **opts)
        tgt = np.argmin(np.linalg.norm(V[None] - d["gd_global"][:, :, 3:6].reshape(-1, 1, 3), axis=2), axis=1)
        ends = np.argmin(np.linalg.norm(V[None] - d["path_global"][:, :, -1].reshape(-1, 1, 3), axis=2), axis=1)
        outside = [t for t in np.concatenate([tgt, ends]) if t not in spread]
        assert bool(outside) == want_outside, pool
        assert np.all(np.isfinite(d["gd_global"][:, :, 6]))
    with pytest.raises(ValueError, match="target_pool"):
        D.build_dataset(two_blobs, None, target_pool="everything", **opts)
