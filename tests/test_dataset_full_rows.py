"""Whole distance rows of the first distance sources kept in a dataset (``full_rows``): the rows the training
rows come from, saved and loaded, absent from older files, and what a ``landmarks`` network reads."""

import numpy as np
import torch
import trimesh

from neurogf_warp.dataset import build as D
from neurogf_warp.ground_truth.geodesics import geodesic_distances
from neurogf_warp.mesh.mesh import load_mesh

SMALL = dict(n_sources=6, n_global=32, n_local1=8, n_local2=16, n_path_sources=2, n_path_global=4,
             n_path_local=2, n_test=2, n_surface=30000, n_spread=200, proxy=0, progress=False, device="cpu")


def _sphere():
    s = trimesh.creation.icosphere(subdivisions=3)
    return np.asarray(s.vertices), np.asarray(s.faces)


def test_full_rows_are_the_sources_solver_rows_and_survive_a_save(tmp_path):
    mesh = _sphere()
    ds = D.build_dataset(mesh, tmp_path / "d.npz", full_rows=4, **SMALL)
    assert len(ds.full_src) == 4 and ds.full_dist.shape == (4, len(ds.vertices))
    assert np.array_equal(ds.full_src, ds.gd_src[:4])
    # the same rows the solver gives these sources, in the normalized frame (plain solve, as the training rows)
    m = load_mesh(mesh)
    ref = geodesic_distances(mesh, m.index[ds.full_src], device="cpu", near_source=False)[:, m.index] * m.scale
    np.testing.assert_allclose(ds.full_dist, ref, rtol=1e-5, atol=1e-6)
    # every training row of a kept source reads its distance from that whole row
    rows = ds.gd_global[0]
    t = np.argmin(np.linalg.norm(ds.vertices[None] - rows[:, None, 3:6], axis=2), axis=1)
    np.testing.assert_allclose(rows[:, 6], ds.full_dist[0, t], rtol=1e-6)
    back = D.Dataset.load(tmp_path / "d.npz")
    assert np.array_equal(back.full_src, ds.full_src) and np.array_equal(back.full_dist, ds.full_dist)
    assert "full_rows" in ds.meta["requested"]


def test_files_without_full_rows_load_empty_and_the_default_recipe_is_unchanged(tmp_path):
    ds = D.build_dataset(_sphere(), tmp_path / "d.npz", **SMALL)
    assert len(ds.full_src) == 0 and "full_rows" not in ds.meta["requested"]
    raw = dict(np.load(tmp_path / "d.npz"))
    for k in ("full_src", "full_dist"):
        raw.pop(k)
    np.savez(tmp_path / "old.npz", **raw)
    old = D.Dataset.load(tmp_path / "old.npz")
    assert old.full_src.shape == (0,) and old.full_dist.shape == (0, 0)


def test_a_landmark_network_reads_the_kept_rows_without_a_solve(tmp_path, monkeypatch):
    from neurogf_warp.training import trainer as T
    from neurogf_warp.training.data import TrainingData

    ds = D.build_dataset(_sphere(), None, full_rows=3, **SMALL)
    data = TrainingData(ds, "cpu")

    def refuse(*a, **k):
        raise AssertionError("the landmark rows were solved again")

    monkeypatch.setattr("neurogf_warp.ground_truth.geodesics.geodesic_distances", refuse)
    xyz, table = T.landmark_table(data, 5, "cpu")
    V = len(ds.vertices)
    torch.testing.assert_close(table[:V, :3], torch.as_tensor(ds.full_dist.T), rtol=0, atol=0)
    torch.testing.assert_close(table[:V, 3:5], table[:V, :2], rtol=0, atol=0)  # 5 columns from 3 rows


def test_the_kept_rows_come_from_spread_sources():
    rng = np.random.default_rng(3)
    xyz = rng.random((400, 3))
    ids = rng.permutation(400)[:100]
    out = D._spread_first(xyz, ids, 8)
    assert sorted(out) == sorted(ids) and out[0] == ids[0]
    assert np.array_equal(out[8:], [i for i in ids if i not in set(out[:8])])  # the rest keep their order
    # each of the first 8 is the farthest of the candidates from those before it
    for j in range(1, 8):
        d = np.min(np.linalg.norm(xyz[ids][:, None] - xyz[out[:j]][None], axis=2), axis=1)
        assert np.isclose(np.linalg.norm(xyz[out[j]] - xyz[out[:j]], axis=1).min(), d.max())
    assert np.array_equal(D._spread_first(xyz, ids, 0), ids)
