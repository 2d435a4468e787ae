"""The ground-truth solver's set-up gives the same tables, bit for bit, as straightforward implementations.

The references below build each table the plain way (indirect stable sorts, a bit loop, ragged numpy loops);
the solver's set-up builds them with value sorts, bit spreading and device kernels.
"""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from neurogf_warp.ground_truth import steiner_graph as sg
from neurogf_warp.ground_truth.near_source import patch_faces, patch_faces_rows
from neurogf_warp.ground_truth.solver import GeodesicSolver, spatial_order
from tests import geodesic_meshes as gm


# ---- references ---------------------------------------------------------------------------------------------------

def ref_topology(faces: np.ndarray, nv: int) -> dict:
    f = np.asarray(faces, dtype=np.int64)
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])]
    half = np.stack([f, np.roll(f, -1, axis=1)], axis=2).reshape(-1, 2)  # (3F, 2): local edge le of each face
    lo, hi = half.min(axis=1), half.max(axis=1)
    order = np.lexsort((np.arange(len(lo)), hi, lo))  # by (lo, hi), ties in (face, local edge) order
    edges, inv = np.unique(np.stack([lo, hi], axis=1), axis=0, return_inverse=True)
    counts = np.bincount(inv.reshape(-1), minlength=len(edges))
    vf_order = np.lexsort((np.arange(3 * len(f)), f.reshape(-1)))
    return {"faces": f.astype(np.int32), "edges": edges.astype(np.int32),
            "face_edges": inv.reshape(-1, 3).astype(np.int32), "edge_faces": (order // 3).astype(np.int32),
            "edge_face_start": np.r_[0, np.cumsum(counts)].astype(np.int32),
            "vertex_faces": (vf_order // 3).astype(np.int32),
            "vertex_face_start": np.r_[0, np.cumsum(np.bincount(f.reshape(-1), minlength=nv))].astype(np.int32)}


def ref_spatial_order(points: np.ndarray, bits: int = 16) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    lo = p.min(axis=0)
    span = float((p.max(axis=0) - lo).max())
    q = np.floor((p - lo) / (span if span > 0 else 1.0) * (2**bits - 1)).astype(np.int64)
    code = np.zeros(len(p), dtype=np.int64)
    for b in range(bits):
        for axis in range(3):
            code |= ((q[:, axis] >> b) & 1) << (3 * b + axis)
    return np.argsort(code, kind="stable")


def ref_node_tables(positions, edges, start, nv):
    """Per Steiner node: edge, t, position (float32, one rounding per operation); every face's slot codes."""
    node_edge, node_t, xyz = [], [], [positions.astype(np.float32)]
    for e in range(len(edges)):
        c = int(start[e + 1] - start[e])
        a, b = positions[edges[e, 0]], positions[edges[e, 1]]
        for j in range(c):
            t = np.float32((j + 1.0) / (c + 1.0))
            node_edge.append(e)
            node_t.append(t)
            xyz.append((a + t * (b - a))[None])
    return np.array(node_edge, np.int32), np.array(node_t, np.float32), np.concatenate(xyz).astype(np.float32)


def ref_face_slots(faces, face_edges, start, nv):
    slot_start, codes = [0], []
    for f in range(len(faces)):
        for i in range(3):
            codes.append((int(faces[f, i]) << 3) | (1 << i) | (1 << ((i + 2) % 3)))
        for le in range(3):
            e = face_edges[f, le]
            codes += [((nv + int(start[e]) + j) << 3) | (1 << le) for j in range(int(start[e + 1] - start[e]))]
        slot_start.append(len(codes))
    return np.array(slot_start, np.int32), np.array(codes, np.int32)


# ---- meshes -------------------------------------------------------------------------------------------------------

def _meshes():
    s = trimesh.creation.icosphere(subdivisions=2)
    V, F = gm.icosphere(2)
    Vs, Fs = gm.split_edges(V, F, 12)
    Vb, Fb, *_ = gm.book()
    Vd, Fd = gm.duplicated_faces()
    rng = np.random.default_rng(3)
    # shuffled faces and vertices, plus faces that repeat a vertex (dropped) and duplicated vertex positions
    perm = rng.permutation(len(V))
    Fr = np.argsort(perm)[F][rng.permutation(len(F))]
    Fr = np.concatenate([Fr, [[0, 0, 1], [2, 3, 3]]])
    Vr = np.concatenate([V[perm], V[perm][:5]])
    Fr = np.concatenate([Fr, [[len(V), len(V) + 1, len(V) + 2]]])
    return {"stretched": (s.vertices * np.array([1.0, 0.01, 0.01]), s.faces), "needles": (Vs, Fs),
            "book": (Vb, Fb), "duplicated": (Vd, Fd), "shuffled": (Vr, Fr), "slivered": gm.slivered(),
            "fan_box": gm.fan_box()}


MESHES = _meshes()


@pytest.mark.parametrize("name", sorted(MESHES))
def test_topology_tables_equal_the_reference(name):
    V, F = MESHES[name]
    topo = sg.Topology(np.asarray(V, np.float32), F)
    ref = ref_topology(F, len(V))
    for key, want in ref.items():
        got = topo.edge_faces if key == "edge_faces" else getattr(topo, key)
        assert got.dtype == want.dtype, key
        np.testing.assert_array_equal(got, want, err_msg=key)


def test_stable_sort_equals_the_indirect_stable_sort_both_ways():
    rng = np.random.default_rng(0)
    keys = rng.integers(0, 50, 5000)  # many ties
    want = np.argsort(keys, kind="stable")
    for bound in (50, 2**62):  # values sort, and the indirect fallback where key * n would overflow
        sk, order = sg.stable_sort(keys, bound)
        np.testing.assert_array_equal(order, want)
        np.testing.assert_array_equal(sk, keys[want])
    sk, order = sg.stable_sort(np.zeros(0, np.int64), 1)
    assert len(sk) == len(order) == 0


@pytest.mark.parametrize("bits", [4, 16, 21])
def test_spatial_order_equals_the_bit_loop(bits):
    rng = np.random.default_rng(bits)
    p = rng.normal(size=(3000, 3))
    p[1000:1100] = p[:100]  # ties: equal cells keep input order
    np.testing.assert_array_equal(spatial_order(p, bits), ref_spatial_order(p, bits))


@pytest.mark.parametrize("name", ["stretched", "needles", "book", "shuffled"])
@pytest.mark.parametrize("k", [1, 3])
def test_device_tables_equal_the_reference(name, k):
    V, F = MESHES[name]
    s = GeodesicSolver((V, F), k=k, device="cpu", batch=1)
    t, g = s.topo, s.graph
    start = s.nodes[0]
    if name == "stretched":
        assert np.diff(start).max() > k  # adaptive counts differ per edge
    node_edge, node_t, xyz = ref_node_tables(s._positions, t.edges, start, s.nv)
    ns = len(node_edge)
    np.testing.assert_array_equal(g.edge_node_start.numpy(), start)
    np.testing.assert_array_equal(g.node_edge.numpy()[:ns], node_edge)
    np.testing.assert_array_equal(g.node_t.numpy()[:ns].view(np.uint32), node_t.view(np.uint32))
    np.testing.assert_array_equal(g.node_xyz.numpy().view(np.uint32), xyz.view(np.uint32))
    np.testing.assert_array_equal(s.nodes[1], node_edge)
    np.testing.assert_array_equal(s.nodes[2].view(np.uint32), node_t.view(np.uint32))
    slot_start, codes = ref_face_slots(t.faces, t.face_edges, start, s.nv)
    np.testing.assert_array_equal(g.face_slot_start.numpy(), slot_start)
    np.testing.assert_array_equal(g.face_slot.numpy(), codes)
    # the module's numpy functions are the same reference
    np.testing.assert_array_equal(sg.node_positions(s._positions, t.edges, node_edge, node_t).view(np.uint32),
                                  xyz.view(np.uint32))
    np.testing.assert_array_equal(sg.face_slot_table(t.faces, t.face_edges, start, s.nv)[1], codes)
    assert s.n_nodes == s.nv + ns


def test_patch_faces_of_all_rows_equal_row_by_row():
    V, F = gm.icosphere(3)
    s = GeodesicSolver((V, F), device="cpu", batch=3)
    src = np.array([0, 5, 77])
    d = s.solve(src)
    d[1, :40] = np.inf  # unreachable vertices are outside every patch
    for limit in (0.0, 4 * s.mean_edge, 0.5, 10.0):
        rows = patch_faces_rows(s, d, limit, rows_per_block=2)
        assert len(rows) == len(src)
        for r in range(len(src)):
            np.testing.assert_array_equal(rows[r], patch_faces(s, d[r], limit))
        if limit == 4 * s.mean_edge:
            assert all(0 < len(x) < len(s.topo.faces) for x in rows)


def test_repeated_public_calls_reuse_the_tables_and_give_the_same_distances():
    import neurogf_warp.ground_truth.solver as S
    from neurogf_warp.ground_truth.geodesics import clear_solver_cache, geodesic_distances, geodesic_paths

    V, F = MESHES["needles"]
    clear_solver_cache()
    plain = GeodesicSolver((V, F), device="cpu", batch=4)
    want = plain.solve(np.array([0, 3, 9, 30]))
    assert len(S._SOLVER_CACHE) == 0  # only cache=True keeps tables
    first = geodesic_distances((V, F), [0, 3, 9, 30], device="cpu", near_source=False)
    assert len(S._SOLVER_CACHE) == 1
    again = geodesic_distances((V, F), [0, 3, 9, 30], device="cpu", near_source=False)
    np.testing.assert_array_equal(again, first)
    m = plain.mesh
    np.testing.assert_array_equal(first, m.to_input(want / np.float32(m.scale)))
    cached = GeodesicSolver((V, F), device="cpu", batch=4, cache=True)
    assert "cached_tables" in cached.timings["setup_phases"] and cached.graph is S._SOLVER_CACHE[
        next(iter(S._SOLVER_CACHE))][-1]
    np.testing.assert_array_equal(cached.solve(np.array([0, 3, 9, 30])), want)
    # near_source and paths through the cache: the same as a fresh solver's
    on = geodesic_distances((V, F), [1, 2], device="cpu")
    clear_solver_cache()
    assert len(S._SOLVER_CACHE) == 0
    np.testing.assert_array_equal(geodesic_distances((V, F), [1, 2], device="cpu"), on)
    p1 = geodesic_paths((V, F), 4, [10, 20, 40], device="cpu")
    p2 = geodesic_paths((V, F), 4, [10, 20, 40], device="cpu")
    for a, b in zip(p1, p2):
        np.testing.assert_array_equal(a, b)
    # other settings or another mesh: other entries, the least recent dropped beyond SOLVER_CACHE_SIZE
    geodesic_distances((V, F), [0], device="cpu", k=2, near_source=False)
    geodesic_distances(MESHES["book"], [0], device="cpu", near_source=False)
    assert len(S._SOLVER_CACHE) == S.SOLVER_CACHE_SIZE
    clear_solver_cache()


def test_gather_rows_gives_mesh_order_rows():
    import warp as wp

    from neurogf_warp.kernels.ground_truth import build

    rng = np.random.default_rng(0)
    dist = rng.random((3, 50)).astype(np.float32)
    dist[0, 7] = np.inf
    ids = rng.permutation(40)
    out = wp.empty((3, 40), dtype=float, device="cpu")
    wp.launch(build.gather_rows, dim=(3, 40), inputs=[wp.array(dist, dtype=float, device="cpu"),
                                                      wp.array(ids.astype(np.int32), dtype=int, device="cpu")],
              outputs=[out], device="cpu")
    np.testing.assert_array_equal(out.numpy(), dist[:, ids])


def test_a_changed_table_setting_builds_new_tables(monkeypatch):
    from neurogf_warp.ground_truth.geodesics import clear_solver_cache

    V, F = MESHES["stretched"]
    clear_solver_cache()
    a = GeodesicSolver((V, F), device="cpu", batch=1, cache=True)
    assert "cached_tables" in GeodesicSolver((V, F), device="cpu", batch=1, cache=True).timings["setup_phases"]
    monkeypatch.setattr(sg, "STEINER_ASPECT", 1e6)
    b = GeodesicSolver((V, F), device="cpu", batch=1, cache=True)
    assert "cached_tables" not in b.timings["setup_phases"]
    assert b.n_nodes < a.n_nodes  # k points on every edge: the thin faces' long edges no longer get more
    clear_solver_cache()
