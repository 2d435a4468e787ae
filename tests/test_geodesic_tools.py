"""Farthest point sampling, Voronoi cells, nearest seeds, isolines and SDF reconstruction, on Warp's CPU device,
checked against the same computations on exact (MMP) or solver distances."""
import numpy as np
import pytest

import neurogf_warp as ngf
from neurogf_warp.common.checks import InputError
from neurogf_warp.inference.reconstruct import surface_distances
from tests.conftest import shared_path

pytestmark = pytest.mark.slow  # the released D=256 fandisk model on the CPU: ~1 min for the module


@pytest.fixture(scope="module")
def fandisk():
    return ngf.load(str(shared_path("checkpoints", "official", "NeuroGF_Pretrainer__fandisk_final.pth")),
                    mesh=str(shared_path("meshes", "fandisk.obj")))


@pytest.fixture(scope="module")
def exact():
    return np.load(shared_path("reference", "exact", "fandisk.npz"))


def _fps_reference(rows_of, start, k):
    """Plain farthest point sampling over distance rows given by ``rows_of(vertex) -> (n,)``."""
    chosen = [start]
    best = rows_of(start).astype(np.float64)
    for _ in range(k - 1):
        nxt = int(np.nanargmax(best))
        chosen.append(nxt)
        best = np.fmin(best, rows_of(nxt))
    return chosen, best


def test_fps_is_farthest_point_sampling_of_the_models_own_distances(fandisk):
    got, dist = ngf.farthest_point_sampling(fandisk, 12, start=5, device="cpu", return_distances=True)
    want, best = _fps_reference(lambda v: ngf.ssad(fandisk, int(v), device="cpu"), 5, 12)
    assert got.tolist() == want
    np.testing.assert_allclose(dist, best, rtol=0, atol=0, equal_nan=True)


def test_fps_against_the_solver_up_to_near_ties(fandisk):
    """Each model sample is, by the solver's distances, within 1% of the farthest vertex's distance at that step
    (the model's error is ~0.3%, so a sample differs only where two candidates nearly tie)."""
    mesh = fandisk.mesh
    k = 8
    got = ngf.farthest_point_sampling(fandisk, k, start=0, device="cpu")
    rows = ngf.geodesic_distances(mesh, got.tolist(), device="cpu")  # (k, n_input), exact-grade
    best = rows[0].astype(np.float64)
    for i in range(1, k):
        far = np.nanmax(best)
        assert best[got[i]] >= 0.99 * far, f"sample {i}: {best[got[i]]:.4f} vs farthest {far:.4f}"
        best = np.fmin(best, rows[i])


def test_voronoi_agrees_with_exact_labels_up_to_near_ties(fandisk, exact):
    seeds = exact["file_index"][exact["sources"]].astype(np.int64)
    labels, dist = ngf.voronoi(fandisk, seeds, device="cpu", return_distances=True)
    D = exact["dist"].astype(np.float64)  # (8, Vc), columns in exact['file_index'] order
    want = np.argmin(D, 0)
    got = labels[exact["file_index"]]
    diff = got != want
    # a label differs only where the exact distances to the two seeds nearly tie
    d_want = D[want, np.arange(D.shape[1])]
    d_got = D[got[diff], np.nonzero(diff)[0]]
    assert np.all(d_got - d_want[diff] <= 0.02 * d_want[diff] + 1e-3 * D.max())
    assert diff.mean() < 0.02, f"{diff.mean():.2%} of the labels differ"
    np.testing.assert_allclose(dist[exact["file_index"]], d_want, rtol=0.05, atol=0.01 * D.max())


def test_nearest_seeds_sorted_and_consistent_with_voronoi(fandisk):
    seeds = np.array([3, 900, 2500, 4000, 6000])
    lab, d = ngf.nearest_seeds(fandisk, seeds, k=3, device="cpu")
    assert lab.shape == d.shape == (fandisk.mesh.n_input, 3)
    used = fandisk.mesh.input_to_internal >= 0
    assert np.all(np.diff(d[used], axis=1) >= 0)
    assert np.array_equal(lab[:, 0], ngf.voronoi(fandisk, seeds, device="cpu"))
    M = ngf.distance_matrix(fandisk, seeds, device="cpu")
    np.testing.assert_array_equal(d[used], np.take_along_axis(M.T[used], lab[used], 1))


def test_isolines_lie_on_their_level(fandisk):
    d = ngf.ssad(fandisk, 0, device="cpu")
    lines = ngf.isolines(fandisk, d, [0.3, 1.0])
    assert len(lines) == 2 and all(len(level) >= 1 for level in lines)
    # a point on a line is on the mesh: its distance to the source, by the model, is the level
    for level, polylines in zip([0.3, 1.0], lines):
        pts = np.concatenate(polylines)
        got = ngf.distance(fandisk, pts, np.repeat(fandisk.mesh.vertices[[0]], len(pts), 0), device="cpu")
        assert np.median(np.abs(got - level)) < 0.02 * level


def test_reconstruct_is_close_to_the_mesh(fandisk):
    v, f = ngf.reconstruct(fandisk, resolution=40, device="cpu")
    mesh = fandisk.mesh
    extent = float(np.linalg.norm(mesh.internal_vertices.max(0) - mesh.internal_vertices.min(0)))
    m = surface_distances(v, f, mesh.internal_vertices, mesh.internal_faces, samples=20_000)
    # a 40-sample grid: cells of ~1/37 of the longest side; the surface lies within about a cell of the mesh
    assert m["chamfer_l1"] < 0.01 * extent
    assert m["hausdorff"] < 0.06 * extent
    import trimesh

    t = trimesh.Trimesh(v, f, process=True)  # merges the copies of a vertex that neighbouring cells share
    boundary = trimesh.grouping.group_rows(t.edges_sorted, require_count=1)
    assert len(boundary) == 0 and t.is_winding_consistent and t.volume > 0


def test_bad_arguments_are_refused(fandisk):
    with pytest.raises(InputError, match="k must be"):
        ngf.farthest_point_sampling(fandisk, 0, device="cpu")
    with pytest.raises(InputError, match="repeats a vertex"):
        ngf.voronoi(fandisk, [1, 1], device="cpu")
    with pytest.raises(InputError, match="1-D list"):
        ngf.voronoi(fandisk, [[1, 2]], device="cpu")
    with pytest.raises(InputError, match="resolution"):
        ngf.reconstruct(fandisk, resolution=4)
    with pytest.raises(InputError, match="one entry per vertex"):
        ngf.isolines(fandisk, np.zeros(3), 2)


def test_evaluate_reports_the_reconstructed_surface(fandisk):
    res = ngf.evaluate(fandisk, n_sources=1, paths=False, sdf=False, surface=24, device="cpu", verbose=False)
    s = res["surface"]
    extent = float(np.linalg.norm(fandisk.mesh.internal_vertices.max(0) - fandisk.mesh.internal_vertices.min(0)))
    assert s["triangles"] > 100 and 0 < s["chamfer_l1"] < 0.02 * extent and s["hausdorff"] < 0.1 * extent
