"""Training sources on a QSlim proxy of a large mesh (dataset/proxy.py): rows in the fine mesh's frame and ids,
held-out rows from the mesh itself, the proxy dropped when it is too far off, the automatic size rule."""
import dataclasses

import numpy as np
import pytest
import trimesh

from neurogf_warp.dataset import build as D
from neurogf_warp.dataset.proxy import Surface, proxy_error, proxy_mesh
from neurogf_warp.ground_truth.geodesics import GeodesicSolver
from neurogf_warp.mesh.mesh import load_mesh

SMALL = dict(n_sources=6, n_global=32, n_local1=8, n_local2=16, n_path_sources=2, n_path_global=4,
             n_path_local=3, n_test=4, n_surface=30000, n_spread=200, progress=False, device="cpu")


@pytest.fixture(scope="module")
def fine_blobs():
    """Two icospheres (the second half as large, apart), each midpoint-subdivided twice: 5,124 vertices whose
    surface is that of the two 162-vertex polyhedra, so a proxy of ~700 vertices can be almost exact."""
    a = trimesh.creation.icosphere(subdivisions=2)
    b = trimesh.creation.icosphere(subdivisions=2)
    b.vertices = b.vertices * 0.5 + np.array([3.0, 0.0, 0.0])
    v, f = np.concatenate([a.vertices, b.vertices]), np.concatenate([a.faces, b.faces + len(a.vertices)])
    for _ in range(2):
        v, f = trimesh.remesh.subdivide(v, f)
    return v, f


@pytest.fixture(scope="module")
def proxied(fine_blobs):
    from neurogf_warp.ground_truth.geodesics import load_kernels

    load_kernels("cpu")
    # a seed whose 4 held-out sources keep the proxy: its error on them is 0.25-0.37% over seeds 0-3, against the
    # 0.3% limit (the kept proxy's rows are what these tests check; the limit itself has its own test)
    return D.build_dataset(fine_blobs, proxy=700, seed=2, **SMALL)


@pytest.mark.slow
def test_a_kept_proxy_gives_rows_of_the_fine_mesh(proxied, fine_blobs):
    d = proxied
    m = load_mesh(fine_blobs)
    p = d.meta["proxy"]
    assert p["kept"] and 600 <= p["vertices"] <= 800 and p["error"]["mre"] <= D.PROXY_MAX_MRE
    assert d.fingerprint == m.fingerprint and len(d.vertices) == len(m.vertices)  # the dataset is the fine mesh's
    V = d.vertices.astype(np.float64)
    for k in ("gd_src", "path_global_src", "path_local_src", "test_src"):
        a = getattr(d, k)
        assert a.size and a.min() >= 0 and a.max() < len(V)
    # held-out rows: the mesh's own solver at its default accuracy, from fine vertices, lowered near each source as
    # evaluate()'s truth (a batch as wide as the sources: a CPU solver pays for its whole batch width)
    from neurogf_warp.ground_truth.near_source import refine_near_sources

    solver = GeodesicSolver(m, device="cpu", batch=len(d.test_src))
    want = refine_near_sources(solver, d.test_src, solver.solve(d.test_src))
    np.testing.assert_allclose(d.test_dist, want, rtol=1e-6)
    # rows start at proxy vertices on the fine surface, next to the fine vertex their source id names
    rows = d.gd_global
    edge = np.linalg.norm(V[m.faces[:, 0]] - V[m.faces[:, 1]], axis=1).mean()
    assert np.all(np.linalg.norm(rows[:, 0, :3] - V[d.gd_src], axis=1) < edge)
    where = Surface.of(m, rows[:, :, 3:6].reshape(-1, 3))
    assert np.abs(np.linalg.norm(where.points - rows[:, :, 3:6].reshape(-1, 3), axis=1)).max() < 1e-5
    # never across the two parts; geodesic >= straight line
    part = lambda x: x[..., 0] > 0.4  # noqa: E731  (the second, smaller sphere lies at x > 0.5 normalized)
    assert part(rows[:, :, :3]).any() and not part(rows[:, :, :3]).all()  # sources on both parts
    assert np.all(part(rows[:, :, :3]) == part(rows[:, :, 3:6]))
    assert np.all(rows[:, :, 6] >= np.linalg.norm(rows[:, :, 3:6] - rows[:, :, :3], axis=2) * (1 - 1e-5))
    # and close to the fine mesh's geodesics between the fine vertices nearest to both ends
    tgt = where.nearest_vertex.reshape(rows.shape[:2])
    D_fine = GeodesicSolver(m, device="cpu", batch=len(d.gd_src)).solve(d.gd_src)
    fine = np.take_along_axis(D_fine, tgt, axis=1)
    far = fine > 0.2
    assert np.mean(np.abs(rows[:, :, 6][far] - fine[far]) / fine[far]) < 0.02
    assert len(d.path_global) and np.isfinite(d.path_global).all()


@pytest.mark.slow
def test_a_proxy_too_far_from_the_mesh_is_dropped(fine_blobs, monkeypatch):
    monkeypatch.setattr(D, "PROXY_MAX_MRE", 0.0)
    d = D.build_dataset(fine_blobs, proxy=700, **SMALL)
    p = d.meta["proxy"]
    assert not p["kept"] and p["error"]["mre"] > 0
    V = d.vertices
    np.testing.assert_array_equal(d.gd_global[:, 0, :3], V[d.gd_src])  # rows start at fine vertices again
    assert not set(d.test_src) & set(d.gd_src)
    m = load_mesh(fine_blobs)
    from neurogf_warp.ground_truth.near_source import refine_near_sources

    solver = GeodesicSolver(m, device="cpu", batch=len(d.test_src))  # lowered near each source, as evaluate()'s
    np.testing.assert_allclose(d.test_dist, refine_near_sources(solver, d.test_src, solver.solve(d.test_src)),
                               rtol=1e-6)


@pytest.mark.slow
def test_no_proxy_unless_asked_or_needed(fine_blobs):
    d = D.build_dataset(fine_blobs, **SMALL)  # CPU, no time limit: the mesh itself
    assert d.meta["proxy"] is None
    d = D.build_dataset(fine_blobs, proxy=4000, **SMALL)  # not worth it: more than half the mesh
    assert d.meta["proxy"] is None


def test_proxy_error_reads_the_fine_rows_on_each_proxy_vertex(fine_blobs):
    m = load_mesh(fine_blobs)
    proxy, where = proxy_mesh(m, 700, "cpu")
    assert np.allclose(proxy.center, m.center) and proxy.scale == m.scale
    # the proxy's vertices are on the fine surface: their interpolated coordinates are themselves
    xyz = np.stack([where.values(m.internal_normalized_vertices[:, k][None])[0] for k in range(3)], 1)
    np.testing.assert_allclose(xyz, proxy.internal_normalized_vertices, atol=1e-5)
    fine = np.abs(m.internal_normalized_vertices[:, :1].T - 0.1) + 0.2  # any smooth field: linear in x away from a kink
    e = proxy_error(where.values(fine) * 1.01, fine, where)
    assert e["pairs"] > 0 and abs(e["mre"] - 0.01) < 1e-6 and abs(e["bias"] - 0.01) < 1e-6


@pytest.mark.parametrize("V,limit,expect", [
    (2_223_321, 170.0, (200_000, 550_000)),  # the 2.2M bunny in a 520 s call: a few hundred thousand vertices
    (2_223_321, 20.0, (30_000, 40_000)),     # 66x smaller, near PROXY_MIN_VERTICES
    (436_076, 100.0, (100_000, 218_038)),    # 1,024 of its own sources do not fit in 50 s: a proxy, at most half
    (436_076, 2000.0, (0, 0)),               # they do: the mesh itself
    (134_345, 15.0, (30_000, 40_000)),       # igea at 60 s: ~4x smaller (a 34K proxy trained best)
    (134_345, 95.0, (0, 0)),                 # igea at 300 s: its own mesh
    (50_000, 15.0, (0, 0)),                  # below 2 x PROXY_MIN_VERTICES: never decimated
    (34_834, 15.0, (0, 0)),
    (2_223_321, None, (0, 0)),               # no time limit: the mesh itself
])
def test_auto_proxy_sizes(V, limit, expect):
    n = D.auto_proxy(V, 2048, limit)
    assert expect[0] <= n <= expect[1]
    def fits(v):  # PROXY_SOURCES of a mesh of v vertices solve in the build's share, at the dataset's rate
        return D.gpu_seconds_per_source(v) * D.DATASET_SLOWDOWN * D.PROXY_SOURCES <= D.PROXY_SHARE * limit

    if n:
        assert not fits(V) and (fits(n) or n == D.PROXY_MIN_VERTICES) and 2 * n <= V
        if n > D.PROXY_MIN_VERTICES + 1000 and 2 * (n + 1000) <= V:
            assert not fits(n + 1000)  # the largest proxy that fits, within the bisection's step
    elif limit is not None and V >= 2 * D.PROXY_MIN_VERTICES:
        assert fits(V)
    fewer = D.auto_proxy(V, 256, limit)  # fewer sources asked: the same mesh, a larger proxy, or none
    assert fewer == 0 or (n and fewer >= n)


def test_the_cpu_rate_goes_through_its_tables_and_grows_with_k():
    rate = D.cpu_seconds_per_source
    for (v, t1), (_, t3) in zip(D.CPU_S_PER_SOURCE_K1, D.CPU_S_PER_SOURCE):
        assert abs(rate(v, 1) / t1 - 1) < 1e-9 and abs(rate(v, 3) / t3 - 1) < 1e-9
    assert rate(80_000, 1) < rate(80_000, 2) < rate(80_000, 3)


@pytest.mark.parametrize("V,k,limit,workers,expect", [
    (134_345, 1, 40.0, 2, (30_000, 30_000)),      # igea at 120 s (cpu_large): its own sources take ~1 s a process
    (134_345, 1, 100.0, 2, (30_000, 30_000)),     # at 300 s still far from 768 of its own: the smallest proxy
    (556_051, 1, 4000.0, 2, (100_000, 278_025)),  # a long budget: a larger proxy, at most half the mesh
    (134_345, 1, 1e6, 2, (0, 0)),                 # a budget that fits its own sources: the mesh itself
    (50_000, 1, 40.0, 2, (0, 0)),                 # below 2 x PROXY_MIN_VERTICES: never decimated
    (134_345, 1, None, 2, (0, 0)),                # no time limit
])
def test_cpu_builds_get_a_proxy_from_the_cpu_rates(V, k, limit, workers, expect):
    """On the CPU the proxy rule reads the CPU's rate tables at the build's k, shared by its processes; a batch
    set by hand (the caller sizes the solves) or a GPU with a batch set by hand keeps the mesh."""
    mesh = load_mesh(trimesh.creation.icosphere(subdivisions=1))
    mesh = dataclasses.replace(mesh, internal_vertices=np.zeros((V, 3)))  # only its size is read
    st = D.DatasetSettings(k=k, n_sources=768, workers=workers)
    n = D._auto_proxy(mesh, st, "cpu", limit)
    assert expect[0] <= n <= expect[1]
    if n:
        per = D.PROXY_SHARE * limit / (768 * D.DATASET_SLOWDOWN)
        assert D.cpu_seconds_per_source(V, k) / workers > per  # its own sources would not fit
    assert D._auto_proxy(mesh, dataclasses.replace(st, batch=8), "cpu", limit) == 0


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::neurogf_warp.training.quality.ModelQualityWarning")  # 10 steps: of course
def test_a_training_run_says_it_used_a_proxy(fine_blobs, tmp_path, capsys):
    """The run's history (log.json) and its progress lines say which ground truth it trained on."""
    import json

    from neurogf_warp.training.api import train
    from neurogf_warp.training.presets import preset

    cfg = preset("cpu_small", querier_steps=5, epochs=1, iters_per_epoch=10, refine_dist_steps=0,
                 refine_sdf_steps=0, refine_path_steps=0).set(proxy=700, n_sources=6, n_path_sources=2, n_test=4,
                                                               n_spread=200, seed=2)  # kept: see ``proxied``
    train(fine_blobs, tmp_path / "m.ngf", config=cfg, device="cpu", progress=True)
    log = json.loads((tmp_path / "m.train" / "log.json").read_text())
    assert log["history"]["proxy"]["kept"] and log["history"]["proxy"]["vertices"] > 600
    assert "-vertex proxy of the mesh (" in capsys.readouterr().err
