"""Ground-truth solver on hard mesh classes against exact MMP (tvb-gdist, float64), Warp CPU device.

Stretched icospheres (triangle aspect ~70 to ~7,000), needles, slivers, duplicated faces and coarse CAD-like fans
(`tests/geodesic_meshes.mesh_classes`). The bar: MRE <= 0.05%, no distance more than 0.5% too long, none below
exact beyond the rounding of the float32 positions the solver works on. Measured values per class and the method
are in docs/design.md.
"""
import numpy as np
import pytest

from neurogf_warp.ground_truth import geodesics as G
from neurogf_warp.ground_truth.steiner_graph import Topology, steiner_counts
from tests import geodesic_meshes as M
from tests.reference_geodesics import gdist_distances

CLASSES = M.mesh_classes()
# the coarse needle mesh keeps a tail of a few pairs above 0.5% at k=3 (rays passing close to a flat or convex
# vertex are lost: one window per node; docs/design.md); bounded, not met
WORST = {"needles": 1e-2}


@pytest.fixture(scope="module", autouse=True)
def compiled():
    G.load_kernels("cpu")


def relative_errors(name, sources=4, seed=0, **solver):
    V, F, R = CLASSES[name]
    src = np.random.default_rng(seed).choice(len(V), sources, replace=False)
    exact = gdist_distances(V, R, src)
    d = G.geodesic_distances((V, F), src, device="cpu", **solver).astype(np.float64)
    assert np.array_equal(np.isfinite(d), np.isfinite(exact))
    ok = np.isfinite(exact) & (exact > 0)
    return (d[ok] - exact[ok]) / exact[ok], exact[ok]


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(CLASSES))
def test_accuracy_against_exact(name):
    rel, exact = relative_errors(name)
    assert np.abs(rel).mean() <= 5e-4, np.abs(rel).mean()
    assert rel.max() <= WORST.get(name, 5e-3), rel.max()
    # never below exact beyond rounding: the solver sees float32 positions (relative 6e-8 of the coordinates,
    # about 1e-7 of the mesh's radius after normalization), which can shorten a short path by that much
    V = CLASSES[name][0]
    radius = np.linalg.norm(V - V.mean(0), axis=1).max()
    assert np.all(rel * exact >= -1e-5 * exact - 4e-7 * radius), rel.min()


def test_needles_meet_the_bar_at_k5():
    # the trade-off setting for exact-grade data: k=5 (2.1x the CPU time of k=3) has no pair above 0.5% on the
    # needle mesh, with sources where k=3 leaves 0.82% (these 12 sources; 5.3K pairs: k=5 0.30%)
    rel, _ = relative_errors("needles", sources=12, k=5, near_source=False)
    assert np.abs(rel).mean() <= 5e-4 and rel.max() <= 5e-3, (np.abs(rel).mean(), rel.max())


def test_graph_only_faces_get_closer_nodes(monkeypatch):
    # the needle mesh's degenerate faces (no window crosses them: paths bend at their nodes) get 2k points per edge:
    # with 24 sources its worst pair goes 1.26% -> 0.64% (the 12 sources above keep their 0.82% pair: a beam tail)
    from neurogf_warp.ground_truth import steiner_graph as SG

    rel, _ = relative_errors("needles", sources=24, near_source=False)  # the plain solve: what the graph does
    assert rel.max() <= 7e-3, rel.max()
    monkeypatch.setattr(SG, "GRAPH_ONLY_FACTOR", 1)
    old, _ = relative_errors("needles", sources=24, near_source=False)
    assert old.max() > 1e-2 and np.abs(rel).mean() < np.abs(old).mean()


def test_thin_faces_get_more_steiner_points():
    # well-shaped faces keep k points per edge; an edge whose every face is thin gets more
    for name, expect_more in (("stretched-0.01", True), ("stretched-1e-4", True), ("duplicated-faces", False)):
        V, F, _ = CLASSES[name]
        topo = Topology(V, F)
        c = steiner_counts(V, topo.faces, topo.face_edges, len(topo.edges), 3, topo.face_ok)
        assert c.min() == 3 and (c.max() > 3) == expect_more


def test_solver_numbering_is_invisible(monkeypatch):
    # the solver numbers vertices along a Morton curve; sources, rows and paths stay in the mesh's numbering.
    # With windows off (the plain Steiner graph: no order-dependence) both numberings give the same distances.
    from neurogf_warp.ground_truth import solver as S

    V, F = M.icosphere(2, (1.0, 0.8, 0.6))
    order = S.spatial_order(V)
    assert np.array_equal(np.sort(order), np.arange(len(V))) and not np.array_equal(order, np.arange(len(V)))
    src = [0, 5, 100]
    on = G.geodesic_distances((V, F), src, device="cpu", windows=False)
    monkeypatch.setattr(S, "REORDER", False)
    off = G.geodesic_distances((V, F), src, device="cpu", windows=False)
    np.testing.assert_allclose(on, off, rtol=1e-6)
    assert np.all(on[np.arange(3), src] == 0)


def test_near_source_patches_take_the_needles_tail_under_the_bar():
    # the worst pairs lie near their source; a k=6 solve of the faces within 14 mean edges of each source, kept
    # where shorter (near_source=True), takes the 24-source needle tail (0.64% at k=3) under 0.5%
    plain, _ = relative_errors("needles", sources=24, near_source=False)
    rel, exact = relative_errors("needles", sources=24, near_source=True)
    assert plain.max() > 5e-3 and rel.max() <= 5e-3, (plain.max(), rel.max())
    assert np.abs(rel).mean() < np.abs(plain).mean()
    assert np.all(rel * exact <= plain * exact + 1e-7)  # the minimum of two real path lengths: never longer
    V = CLASSES["needles"][0]
    assert np.all(rel * exact >= -1e-5 * exact - 4e-7 * np.linalg.norm(V - V.mean(0), axis=1).max())


def test_near_source_on_a_shared_mesh():
    # cow, three sources whose k=3 rows hold pairs up to 1.44% too long without the near-source solve
    import trimesh

    from tests.conftest import shared_path

    tm = trimesh.load(shared_path("meshes", "cow.obj"), process=False, force="mesh")
    V, F = np.asarray(tm.vertices, np.float64), np.asarray(tm.faces)
    src = [2838, 0, 3]
    exact = gdist_distances(V, F, src)
    ok = np.isfinite(exact) & (exact > 0)
    rel = {}
    for ns in (False, True):
        d = G.geodesic_distances((V, F), src, device="cpu", near_source=ns).astype(np.float64)
        rel[ns] = (d[ok] - exact[ok]) / exact[ok]
    assert rel[False].max() > 5e-3 and rel[True].max() <= 5e-3, (rel[False].max(), rel[True].max())
    assert rel[True].min() >= -2e-5


def test_run_seeds_solves_disjoint_copies_at_once():
    # one row seeded in each of two disjoint copies of a mesh = each copy solved from its own seed
    from neurogf_warp.ground_truth.solver import GeodesicSolver
    from neurogf_warp.mesh.mesh import load_mesh

    V, F = M.icosphere(2, (1.0, 0.8, 0.6))
    one = GeodesicSolver((V, F), device="cpu", max_rows=2)
    single = one.solve(np.array([5, 40])) / np.float32(one.mesh.scale)
    both = load_mesh((np.r_[V, V], np.r_[F, F + len(V)]), weld=False)
    two = GeodesicSolver(both, device="cpu", max_rows=1)
    two.run_seeds(np.array([5, len(V) + 40]))
    d = two.vertex_distances()[0] / np.float32(both.scale)
    np.testing.assert_allclose(d[: len(V)], single[0], rtol=2e-5, atol=1e-6)
    np.testing.assert_allclose(d[len(V):], single[1], rtol=2e-5, atol=1e-6)
