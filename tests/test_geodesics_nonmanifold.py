"""Ground-truth solver on meshes that are not clean manifolds, against exact references (Warp CPU device).

Vertices whose faces form several fans (pinches), edges with three or more faces (a book, fins), open meshes
with many boundary loops and needles. The bar is the solver's clean-mesh accuracy: MRE <= 0.05%, no distance
more than 0.5% too long, none below exact beyond float32 rounding, and every traced path as long as its
distance within PATH_TOLERANCE (0.1%).
"""
import numpy as np
import pytest
import trimesh

from neurogf_warp.ground_truth import geodesics as G
from neurogf_warp.mesh.mesh import load_mesh
from tests import geodesic_meshes as M
from tests.conftest import shared_path
from tests.reference_geodesics import exact_distances


@pytest.fixture(scope="module", autouse=True)
def compiled():
    G.load_kernels("cpu")


def check_distances(V, F, src, exact, mre=5e-4, worst=5e-3):
    """Solve from vertex ids `src`; relative error against `exact` (S, V) over reachable pairs."""
    d = G.geodesic_distances((V, F), src, device="cpu").astype(np.float64)
    ok = np.isfinite(exact) & (exact > 1e-9)
    assert np.array_equal(np.isfinite(d), np.isfinite(exact))
    rel = (d[ok] - exact[ok]) / exact[ok]
    assert rel.min() > -1e-5, rel.min()  # every value is a real path: never below exact beyond rounding
    assert np.abs(rel).mean() < mre and rel.max() < worst, (np.abs(rel).mean(), rel.max())
    return d


def check_paths(V, F, src):
    """Every vertex traced from each source: no path flagged, each as long as its distance (PATH_TOLERANCE)."""
    msh = load_mesh((V, F))
    solver = G.GeodesicSolver(msh, device="cpu", batch=len(src))
    solver.run(msh.vertex(np.asarray(src)))
    rows = np.repeat(np.arange(len(src)), solver.nv).astype(np.int32)
    tg = np.tile(np.arange(solver.nv), len(src)).astype(np.int32)
    pts, offs, flags = solver.trace(rows, tg)
    assert np.all(flags == 0) and solver.timings["paths_flagged"] == 0
    step = np.linalg.norm(np.diff(pts.astype(np.float64), axis=0), axis=1)
    cum = np.r_[0.0, np.cumsum(step)]
    length = cum[offs[1:] - 1] - cum[offs[:-1]]
    d = solver.vertex_distances()[rows, tg].astype(np.float64)
    far = d > 1e-3
    assert np.max(np.abs(length[far] - d[far]) / d[far]) < G.PATH_TOLERANCE
    return solver, pts, offs


def test_discs_joined_at_their_centres():
    V, F, disc = M.pinched_discs()
    src = np.array([1, 2, 17, 70, 100])
    check_distances(V, F, src, M.pinched_discs_distances(V, disc, src))
    _, pts, offs = check_paths(V, F, src[:2])
    # paths between the discs pass through the shared centre
    tg = np.where(disc == 1)[0][5]
    p = pts[offs[tg]: offs[tg + 1]]
    msh = load_mesh((V, F))
    assert np.min(np.linalg.norm(msh.denormalize(p) - V[0], axis=1)) < 1e-6


def test_spheres_touching_at_a_vertex():
    V, F = M.pinched_spheres()
    src = np.array([1, 60, 200])
    check_distances(V, F, src, exact_distances(V, F, src))
    check_paths(V, F, src[:1])


def test_cow_pinch_vertex():
    # cow.obj vertex 253: two closed fans meet there (shared reference: gdist on a split copy, re-joined)
    ref = np.load(shared_path("reference", "exact", "cow.npz"))
    tm = trimesh.load(shared_path("meshes", "cow.obj"), process=False, force="mesh")
    inv = np.full(len(tm.vertices), -1)
    inv[ref["orig_index"]] = np.arange(len(ref["orig_index"]))
    V, F = ref["positions"].astype(np.float64), inv[np.asarray(tm.faces)]
    src = ref["sources"][[1, 6]]
    exact = ref["dist"][[1, 6]].astype(np.float64)
    d = G.geodesic_distances((V, F), src, device="cpu").astype(np.float64)
    through = np.abs(exact - (exact[:, [253]] + exact_distances(V, F, [253])[0])) < 1e-6 * exact
    assert through.sum() > 50  # pairs whose geodesic passes the pinch
    rel = (d[through] - exact[through]) / exact[through]
    assert rel.min() > -1e-5 and np.abs(rel).mean() < 5e-4 and rel.max() < 5e-3


def test_book_pages_on_one_spine():
    # every spine edge has three faces; the exact distance between pages is a straight line through the spine
    V, F, uv, page = M.book(pages=3)
    src = np.array([10, 33, 52, 80])
    check_distances(V, F, src, M.book_distances(uv, page, src))
    check_paths(V, F, src)
    V, F, uv, page = M.book(pages=4, nu=6, nv=8, seed=1)
    src = np.array([3, 40, 100])
    check_distances(V, F, src, M.book_distances(uv, page, src))
    check_paths(V, F, src)


def test_fin_on_a_closed_mesh():
    V, F, nv = M.finned_sphere(subdivisions=2, fins=1)
    src = np.array([F[-1, 0], 7, nv])  # on the fin's edge, on the ellipsoid, the fin's tip
    check_distances(V, F, src, exact_distances(V, F, src, samples=256))
    check_paths(V, F, src)


def test_holes_and_needles():
    # an ellipsoid with 10 holes, then 150 edges split close to one end (needles, 15% of the faces); the surface
    # is unchanged, so the holed mesh's exact distances hold for the original vertices
    V, F = M.holed_ellipsoid()
    src = np.array([0, 200, 400])
    exact = exact_distances(V, F, src)
    check_distances(V, F, src, exact)
    V2, F2 = M.split_edges(V, F, 150)
    d = G.geodesic_distances((V2, F2), src, device="cpu").astype(np.float64)[:, : len(V)]
    ok = np.isfinite(exact) & (exact > 1e-9)
    rel = (d[ok] - exact[ok]) / exact[ok]
    assert rel.min() > -1e-5 and np.abs(rel).mean() < 5e-4 and rel.max() < 5e-3
    solver, _, _ = check_paths(V2, F2, src[:2])
    assert (solver.topo.boundary_edges > 0) and solver.topo.face_ok.mean() > 0.99


def test_untraceable_paths_are_flagged_and_nan():
    # records made inconsistent on purpose: every ray's virtual source moved, so walks miss their origins
    s = trimesh.creation.icosphere(subdivisions=2)
    msh = load_mesh((s.vertices * np.array([1.0, 0.8, 0.6]), s.faces))
    solver = G.GeodesicSolver(msh, device="cpu", batch=1)
    solver.run([0])
    tg = np.arange(solver.nv, dtype=np.int32)
    _, _, flags = solver.trace(np.zeros(len(tg), np.int32), tg)
    assert np.all(flags == 0)
    h = solver.state.rec.ray_height.numpy()
    solver.state.rec.ray_height.assign(h * 1.5)
    pts, offs, flags = solver.trace(np.zeros(len(tg), np.int32), tg)
    bad = flags != 0
    assert bad.sum() > 10 and solver.timings["paths_flagged"] == bad.sum()
    for i in range(len(tg)):
        p = pts[offs[i]: offs[i + 1]]
        assert np.isnan(p).all() if bad[i] else np.isfinite(p).all()
    r = G.resample_polyline(pts, offs, 8)
    assert np.isnan(r[bad]).all() and np.isfinite(r[~bad]).all()


def _resample_reference(p: np.ndarray, m: int) -> np.ndarray:
    """float64, one polyline at a time: arc-length samples at k / (m - 1) of the length."""
    if len(p) == 0 or not np.isfinite(p).all():
        return np.full((m, 3), np.nan)
    if len(p) == 1:
        return np.repeat(p[:1], m, axis=0)
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))]
    t = np.arange(m) / (m - 1) * s[-1]
    j = np.clip(np.searchsorted(s, t, side="right") - 1, 0, len(p) - 2)
    seg = s[j + 1] - s[j]
    w = np.where(seg > 0, (t - s[j]) / np.where(seg > 0, seg, 1.0), 0.0)
    return p[j] + w[:, None] * (p[j + 1] - p[j])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_resample_polylines_against_float64(seed):
    """The one-launch resampling (``resample_polylines``, a thread per polyline) against a float64 loop on fresh
    random polylines anywhere in the point array: empty ones, single points, repeated points (zero-length
    segments), NaN and inf points (NaN rows), and lengths from 1e-3 to 1e3."""
    rng = np.random.default_rng(seed)
    T = 300
    count = rng.integers(0, 40, T)
    count[rng.random(T) < 0.1] = 1
    scale = 10.0 ** rng.uniform(-3, 3)
    pts = (np.cumsum(rng.standard_normal((count.sum() + 7, 3)), axis=0) * scale).astype(np.float32)
    k = rng.integers(1, len(pts), 25)
    pts[k] = pts[k - 1]
    pts[rng.integers(0, len(pts), 3)] = np.nan
    pts[rng.integers(0, len(pts), 2)] = np.inf
    order = rng.permutation(T)  # polylines in any order in the array, with points before and after
    starts = np.empty(T, np.int64)
    starts[order] = 5 + np.r_[0, np.cumsum(count[order])[:-1]]
    m = int(rng.integers(2, 130))
    got = G.resample_polylines(pts, starts, starts + count, m)
    want = np.stack([_resample_reference(pts[a:a + c].astype(np.float64), m) for a, c in zip(starts, count)])
    assert got.shape == (T, m, 3) and got.dtype == np.float32
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    ok = np.isfinite(want)
    assert ok.any() and (~ok).any()
    # float32 output: within two roundings of the largest coordinate
    np.testing.assert_allclose(got[ok], want[ok], rtol=0, atol=2 * np.finfo(np.float32).eps * np.abs(want[ok]).max())
    offsets = np.r_[starts[order], starts[order[-1]] + count[order[-1]]]  # the same polylines as offsets
    np.testing.assert_array_equal(G.resample_polyline(pts, offsets, m), got[order])
