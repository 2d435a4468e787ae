"""benchmarks/unseen_meshes.py at a small size: closed meshes with the promised topology, patches joined at one
vertex, exact references that pass their checks (recomputed here), the project's loaders accept the files, and a
re-run gives the same arrays."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import unseen_meshes as um  # noqa: E402

from neurogf_warp.evaluation.evaluate import load_reference  # noqa: E402
from neurogf_warp.mesh.mesh import load_mesh  # noqa: E402
from neurogf_warp.mesh.topology import vertex_joins  # noqa: E402

SCALE = 0.05
EXPECTED = {"scan": (1, 0), "parts": (len(um.PARTS), 0), "cad": (1, 3)}  # components, genus of each closed mesh


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    a, b = tmp_path_factory.mktemp("a"), tmp_path_factory.mktemp("b")
    return a, um.generate(a, seed=3, scale=SCALE, quiet=True), b, um.generate(b, seed=3, scale=SCALE, quiet=True)


def _edges(f):
    return np.unique(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), 1), axis=0)


@pytest.mark.parametrize("name", list(EXPECTED))
def test_mesh_is_closed_with_the_promised_components_and_genus(runs, name):
    import trimesh

    out = runs[0]
    m = load_mesh(out / f"{name}.ply")
    tm = trimesh.load(out / f"{name}.ply", process=False, force="mesh")
    assert tm.is_watertight and tm.is_winding_consistent
    assert len(tm.split(only_watertight=True)) == EXPECTED[name][0]
    comps, genus = EXPECTED[name]
    assert m.n_components == comps
    f = m.internal_faces.astype(np.int64)
    labels = m.internal_components
    e = _edges(f)
    euler = (np.bincount(labels, minlength=comps) - np.bincount(labels[e[:, 0]], minlength=comps)
             + np.bincount(labels[f[:, 0]], minlength=comps))
    assert np.all(euler == 2 - 2 * genus), euler
    vj = vertex_joins(m)
    assert not vj.any and vj.pinch_vertices == 0 and vj.coincident_vertices == 0
    v = m.internal_vertices
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    assert area.min() > 1e-8 * np.ptp(v, 0).max() ** 2


@pytest.mark.parametrize("name", um.MESHES)
def test_reference_is_exact_geodesics_in_the_shared_format(runs, name):
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    out = runs[0]
    m = load_mesh(out / f"{name}.ply")
    ref = np.load(out / "reference" / f"{name}.npz")
    assert {k: ref[k].dtype.kind for k in ref.files} == {"positions": "f", "orig_index": "i", "file_index": "i",
                                                        "sources": "i", "dist": "f", "how": "U"}
    assert ref["dist"].dtype == np.float32 and ref["positions"].dtype == np.float32
    assert ref["sources"].shape == (8,) and ref["dist"].shape == (8, len(m.internal_vertices))
    vid, sid, dist = load_reference(out / "reference" / f"{name}.npz", m)
    src = ref["sources"].astype(np.int64)
    v = m.internal_vertices
    # sources 6 and 7: the farthest vertices from vertex 0 and from source 6
    assert src[7] == np.argmax(np.where(np.isfinite(dist[6]), dist[6], -1))
    e = _edges(m.internal_faces.astype(np.int64))
    w = np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1)
    g = coo_matrix((w, (e[:, 0], e[:, 1])), shape=(len(v),) * 2)
    dj = dijkstra(g, directed=False, indices=src)
    fin = np.isfinite(dist)
    assert np.array_equal(fin, m.internal_components[None, :] == m.internal_components[src][:, None])
    assert np.array_equal(fin, np.isfinite(dj))
    rel = 2e-7  # float32 storage
    assert np.all(dist[fin] <= dj[fin] * (1 + rel) + 1e-30)
    straight = np.linalg.norm(v[None] - v[src][:, None], axis=2)
    assert np.all(dist[fin] >= straight[fin] * (1 - rel))
    assert np.any(dist[fin] < dj[fin] * (1 - 1e-3))  # shorter than edge paths: not a graph distance
    a = dist[:, src]
    assert np.array_equal(np.isfinite(a), np.isfinite(a.T))
    both = np.isfinite(a) & (a > 0)
    np.testing.assert_allclose(a[both], a.T[both], rtol=1e-6)
    if name == "parts":
        assert 0 < np.mean(~fin) < 1  # other parts are unreachable


def test_joined_patches_meet_at_vertices_only_and_the_reference_crosses_them(runs):
    from neurogf_warp.ground_truth.geodesics import geodesic_distances

    out = runs[0]
    m = load_mesh(out / "joined.ply")
    vj = vertex_joins(m)
    assert vj.joined_patches == um.JOINED_PATCHES and vj.pinch_vertices == um.JOINED_PATCHES + 1
    assert vj.coincident_vertices == 0
    vid, sid, dist = load_reference(out / "reference" / "joined.npz", m)
    # the project's solver treats pinch vertices on its own (point sources): both agree to its accuracy
    ours = geodesic_distances(out / "joined.ply", sid, device="cpu")
    fin = dist > 0
    assert np.max(np.abs(ours[fin] - dist[fin]) / dist[fin]) < 0.01
    # across a seam, points close in space are far apart on the surface
    v = m.internal_vertices
    straight = np.linalg.norm(v[None] - v[sid][:, None], axis=2)
    assert np.max(dist[fin] / straight[fin]) > 5


def test_a_rerun_writes_the_same_arrays(runs):
    a, ea, b, eb = runs
    for name in um.MESHES:
        assert (a / f"{name}.ply").read_bytes() == (b / f"{name}.ply").read_bytes()
        ra, rb = np.load(a / "reference" / f"{name}.npz"), np.load(b / "reference" / f"{name}.npz")
        for k in ra.files:
            assert np.array_equal(ra[k], rb[k]), (name, k)
        assert ea[name]["dist_float64_sha256"] == eb[name]["dist_float64_sha256"]


def test_another_seed_gives_another_scan(runs, tmp_path):
    other = um.generate(tmp_path, seed=4, scale=SCALE, meshes=("scan",), quiet=True)
    assert other["scan"]["sha256"] != runs[1]["scan"]["sha256"]


def test_topology_finds_a_pinch_and_a_hole():
    v, f = um.icosphere(2)
    # a second sphere, moved so that its vertex 0 lands on vertex 3 of the first, then given that vertex's index
    w = np.concatenate([v, v - v[0] + v[3]])
    g = np.concatenate([f, f + len(v)])
    g[g == len(v)] = 3
    t = um.topology(w, g)
    assert t["pinch_vertices"] == 1 and not t["closed"]
    t = um.topology(v, f[1:])
    assert t["boundary_edges"] == 3 and not t["closed"]
    with pytest.raises(RuntimeError, match="not closed"):
        um.check_mesh("scan", v, f[1:], 1, 0)


@pytest.mark.parametrize("args, word", [(["--scale", "0"], "--scale"), (["--seed", "-1"], "--seed")])
def test_bad_arguments_name_the_argument(args, word, tmp_path):
    r = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "unseen_meshes.py"), "--out", str(tmp_path / "o"),
                        *args], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and word in r.stderr
    assert not (tmp_path / "o").exists()


def test_help_runs_from_a_plain_checkout(tmp_path):
    r = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "unseen_meshes.py"), "--help"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "usage:" in r.stdout and "--scale" in r.stdout
