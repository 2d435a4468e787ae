"""One vertex numbering: every per-vertex array the library takes or gives is in the file's order, positions included
(``Mesh.vertices``, ``faces``, ``components``), on meshes with unused and welded vertices."""
from __future__ import annotations

import numpy as np
import pytest

import neurogf_warp as ngf

from .conftest import shared_path

# two tetrahedra (two components) whose file interleaves three vertex records no face uses
OBJ = """v 50 50 50
v 0 0 0
v 2 0 0
v -7 -7 -7
v 0 3 0
v 0 0 1.5
v 9 9 9
v 10 0 0
v 11 0 0
v 10 1 0
v 10 0 1
f 2 3 5
f 2 3 6
f 2 5 6
f 3 5 6
f 8 9 10
f 8 9 11
f 8 10 11
f 9 10 11
"""
UNUSED = [0, 3, 6]


@pytest.fixture(scope="module")
def mesh_path(tmp_path_factory):
    p = tmp_path_factory.mktemp("numbering") / "two.obj"
    p.write_text(OBJ)
    return str(p)


@pytest.fixture(scope="module")
def model(mesh_path):
    import torch

    from neurogf_warp.model.model import Model
    from neurogf_warp.model.network import NeuroGFNet

    torch.manual_seed(1)
    m = ngf.load_mesh(mesh_path)
    return Model(net=NeuroGFNet(64), mesh=m, center=m.center, scale=m.scale)


def test_positions_faces_and_labels_are_in_file_order(mesh_path):
    m = ngf.load_mesh(mesh_path)
    rows = np.loadtxt([ln[2:] for ln in OBJ.splitlines() if ln.startswith("v ")])
    assert m.vertices.shape == (11, 3) and m.n_input == 11
    used = np.setdiff1d(np.arange(11), UNUSED)
    np.testing.assert_array_equal(m.vertices[used], rows[used])
    assert np.isnan(m.vertices[UNUSED]).all()
    np.testing.assert_array_equal(m.faces, [[1, 2, 4], [1, 2, 5], [1, 4, 5], [2, 4, 5],
                                            [7, 8, 9], [7, 8, 10], [7, 9, 10], [8, 9, 10]])
    np.testing.assert_array_equal(m.vertices[m.faces], m.internal_vertices[m.internal_faces])
    np.testing.assert_array_equal(m.components, [-1, 0, 0, -1, 0, 0, -1, 1, 1, 1, 1])
    with pytest.raises(ValueError):
        m.vertices[1] = 0  # a read-only view: writing to it would change nothing the mesh uses


def test_exact_distances_match_file_positions(mesh_path):
    """On a tetrahedron every vertex pair is an edge: the exact geodesic distance is the straight line."""
    m = ngf.load_mesh(mesh_path)
    d = np.asarray(ngf.geodesic_distances(m, [2, 8], device="cpu"))
    assert d.shape == (2, 11)
    for row, s in zip(d, (2, 8)):
        same = np.flatnonzero(m.components == m.components[s])
        want = np.linalg.norm(m.vertices[same] - m.vertices[s], axis=1)
        np.testing.assert_allclose(row[same], want, rtol=1e-5)
        assert np.isnan(row[UNUSED]).all()
        other = np.flatnonzero((m.components >= 0) & (m.components != m.components[s]))
        assert np.isinf(row[other]).all()


def test_model_answers_line_up_with_mesh_vertices(model):
    V = model.mesh.vertices
    s = 4
    row = np.asarray(ngf.ssad(model, s, raw=True, device="cpu"), np.float64)
    assert row.shape == (11,) and np.isnan(row[UNUSED]).all()
    same = np.flatnonzero(model.mesh.components == model.mesh.components[s])
    pts = np.asarray(ngf.distance(model, np.repeat(V[[s]], len(same), 0), V[same], raw=True, device="cpu"))
    np.testing.assert_allclose(row[same], pts, rtol=1e-3, atol=1e-4)
    m = np.asarray(ngf.msad(model, [s], raw=True, device="cpu"))
    np.testing.assert_allclose(m[same], row[same], rtol=1e-5)
    mat = np.asarray(ngf.distance_matrix(model, [s, 9], device="cpu"))
    assert mat.shape == (2, 11) and np.isnan(mat[:, UNUSED]).all()


def test_model_file_keeps_file_order(model, tmp_path):
    ngf.save(model, tmp_path / "m.ngf")
    back = ngf.load(tmp_path / "m.ngf")
    np.testing.assert_array_equal(back.mesh.vertices, model.mesh.vertices)
    np.testing.assert_array_equal(back.mesh.faces, model.mesh.faces)
    np.testing.assert_array_equal(back.mesh.components, model.mesh.components)


def test_write_ply_writes_the_file_vertices_in_file_order(model, tmp_path):
    from neurogf_warp.mesh.files import read_mesh_file
    from neurogf_warp.pictures.render import write_ply

    values = np.arange(11, dtype=np.float64)
    values[UNUSED] = np.nan
    path = write_ply(tmp_path / "f.ply", model, values)
    v, f, _ = read_mesh_file(path)
    assert len(v) == 11
    np.testing.assert_array_equal(v, model.mesh.vertices.astype(np.float32))  # NaN rows where unused
    np.testing.assert_array_equal(f, model.mesh.faces)
    quality = np.frombuffer(open(path, "rb").read().split(b"end_header\n", 1)[1][:11 * 20], dtype=np.dtype(
        [("xyz", "<f4", 3), ("rgba", "u1", 4), ("q", "<f4")]))["q"]
    np.testing.assert_array_equal(quality, values.astype(np.float32))


def test_welded_stl_gives_every_record_its_position(tmp_path):
    import trimesh

    tm = trimesh.creation.icosphere(subdivisions=1)
    tm.export(tmp_path / "s.stl")
    m = ngf.load_mesh(tmp_path / "s.stl")
    assert m.welded and m.n_input == 3 * len(tm.faces)
    corners = np.asarray(tm.vertices)[np.asarray(tm.faces)].reshape(-1, 3).astype(np.float32)
    np.testing.assert_array_equal(m.vertices, corners.astype(np.float64))
    np.testing.assert_array_equal(m.vertices[m.faces], m.internal_vertices[m.internal_faces])


def test_bunny_positions_match_the_reference_file_numbering():
    ref = np.load(shared_path("reference", "exact", "stanford-bunny.npz"))
    m = ngf.load_mesh(shared_path("meshes", "stanford-bunny.obj"))
    assert m.vertices.shape == (35947, 3)
    np.testing.assert_array_equal(m.vertices[ref["file_index"]].astype(np.float32), ref["positions"])
    assert int(np.isnan(m.vertices[:, 0]).sum()) == 35947 - 34834
