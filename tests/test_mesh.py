"""Mesh loading: the file's own vertex numbering (OBJ, PLY, STL, arrays), welding with the map kept, bad files."""
import os
import struct

import numpy as np
import pytest
import trimesh

import neurogf_warp as ngf
from neurogf_warp.mesh.files import read_mesh_file
from neurogf_warp.mesh.mesh import mesh_fingerprint
from tests.conftest import shared_path

TET_OBJ = "v 5 5 5\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 2 3 4\nf 2 3 5\nf 2 4 5\nf 3 4 5\n"


def write(path, text):
    path.write_text(text)
    return path


def icosphere_soup(subdivisions=1):
    """A closed sphere and the same triangles with three vertices of their own each (an STL's layout)."""
    s = trimesh.creation.icosphere(subdivisions=subdivisions)
    V, F = np.asarray(s.vertices), np.asarray(s.faces)
    return V, F, V[F.ravel()], np.arange(3 * len(F)).reshape(-1, 3)


def test_obj_keeps_unused_vertices_in_file_numbering(tmp_path):
    """The issue's repro: vertex 0 unused stays in the numbering; vertex 1 is (0, 0, 0)."""
    path = write(tmp_path / "t.obj", TET_OBJ)
    m = ngf.load_mesh(path)
    assert m.n_input == 5 and len(m.internal_vertices) == 4
    np.testing.assert_array_equal(m.internal_vertices[m.vertex(1)], [0, 0, 0])
    np.testing.assert_array_equal(m.input_to_internal, [-1, 0, 1, 2, 3])
    d = ngf.geodesic_distances(path, [1], device="cpu")
    assert d.shape == (1, 5) and np.isnan(d[0, 0])
    np.testing.assert_allclose(d[0, 1:], [0, 1, 1, 1], atol=1e-6)
    with pytest.raises(IndexError, match="not used by any face"):
        m.vertex(0)
    with pytest.raises(IndexError, match="negative"):
        m.vertex(-1)
    with pytest.raises(IndexError, match="out of range"):
        m.vertex(5)


def test_bunny_obj_numbering_and_fingerprint():
    path = shared_path("meshes", "stanford-bunny.obj")
    m = ngf.load_mesh(path)
    assert m.n_input == 35947 and len(m.internal_vertices) == 34834
    assert np.count_nonzero(m.input_to_internal < 0) == 1113
    ref = np.load(shared_path("reference", "exact", "stanford-bunny.npz"))
    np.testing.assert_array_equal(m.index, ref["file_index"])  # the reference's own file numbering
    np.testing.assert_array_equal(m.internal_vertices.astype(np.float32), ref["positions"])
    # the fingerprint is that of the used vertices, the same as when trimesh (which drops unused ones) read it
    tm = trimesh.load(path, process=False, force="mesh")
    assert m.fingerprint == mesh_fingerprint(tm.vertices, tm.faces)


def test_obj_records_parsed_as_the_format_says(tmp_path):
    text = ("# a comment\nmtllib x.mtl\no thing\n"
            "v 0 0 0 1.0\nv 1 0 0  # trailing comment\nvt 0 0\nvn 0 0 1\n"
            "v 1 1 0 0.5 0.5 0.5\nv 0 1 \\\n 0\nv 0.5 0.5 1\ng part\nusemtl m\ns off\n"
            "f 1/1/1 2/1/1 3/1/1 4/1/1\n"        # quad, split along its first diagonal
            "f -5//1 -4//1 -1//1\n"              # relative indices: vertices 1, 2, 5
            "f 2/1 3/1 5/1 4/1 1/1\n"            # pentagon, fanned from its first corner
            "l 1 2\n")
    v, f, kind = read_mesh_file(write(tmp_path / "r.obj", text))
    assert kind == "obj"
    np.testing.assert_array_equal(v, [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 1]])
    np.testing.assert_array_equal(f, [[0, 1, 2], [2, 3, 0], [0, 1, 4], [1, 2, 4], [1, 4, 3], [1, 3, 0]])


@pytest.mark.parametrize("text, match", [
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 0\n", r"line 4: vertex index 0 is not valid"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n", r"line 4: vertex index 4 is out of range: the file has 3"),
    ("v 0 0 0\nf -1 -2 -3\nv 1 0 0\nv 0 1 0\n", r"line 2: relative index -2 points before the first vertex"),
    ("v 0 0 0\nv 1 0 zero\nv 0 1 0\nf 1 2 3\n", r"line 2: vertex coordinate 'zero' is not a number"),
    ("v 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", r"line 1: a vertex record needs 3 coordinates"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n", r"line 4: a face needs at least 3 vertices"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 x\n", r"line 4: face vertex 'x' is not an index"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\n", r"has no faces"),
    ("hello world\nthis is text\n", r"not a mesh file: it has no vertex records"),
    ("", r"is empty"),
])
def test_bad_obj_files_name_file_and_line(tmp_path, text, match):
    path = write(tmp_path / "bad.obj", text)
    with pytest.raises(ValueError, match=match) as e:
        ngf.load_mesh(path)
    assert str(path) in str(e.value)


def test_random_bytes_are_not_a_mesh_file(tmp_path):
    rng = np.random.default_rng()
    for suffix in (".obj", ".ply", ".stl", ".off"):
        path = tmp_path / f"noise{suffix}"
        path.write_bytes(rng.integers(0, 256, 3000, dtype=np.uint8).tobytes())
        with pytest.raises(ValueError) as e:
            ngf.load_mesh(path)
        msg = str(e.value)
        assert str(path) in msg and "charset" not in msg, msg
        assert "not a mesh file" in msg or "not a valid" in msg, msg


def ply_text(V, F, binary=False):
    head = (f"ply\nformat {'binary_little_endian' if binary else 'ascii'} 1.0\nelement vertex {len(V)}\n"
            "property double x\nproperty double y\nproperty double z\n"
            f"element face {len(F)}\nproperty list uchar int vertex_indices\nend_header\n").encode()
    if not binary:
        body = "".join(f"{float(x)!r} {float(y)!r} {float(z)!r}\n" for x, y, z in V) + "".join(
            f"{len(f)} " + " ".join(map(str, f)) + "\n" for f in F)
        return head + body.encode()
    body = np.asarray(V, "<f8").tobytes() + b"".join(struct.pack(f"<B{len(f)}i", len(f), *f) for f in F)
    return head + body


@pytest.mark.parametrize("binary", [False, True])
def test_ply_keeps_unused_vertices_and_order(tmp_path, binary):
    V = np.array([[9, 9, 9], [0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 1.0], [7, 7, 7]])
    F = [[1, 2, 3, 4], [1, 2, 5], [2, 3, 5], [3, 4, 5], [4, 1, 5]]
    path = tmp_path / "q.ply"
    path.write_bytes(ply_text(V, F, binary))
    m = ngf.load_mesh(path)
    assert m.n_input == 7 and len(m.internal_vertices) == 5
    np.testing.assert_array_equal(m.input_to_internal, [-1, 0, 1, 2, 3, 4, -1])
    np.testing.assert_array_equal(m.internal_vertices, V[1:6])
    assert len(m.internal_faces) == 6 and m.n_components == 1
    np.testing.assert_array_equal(m.index[m.internal_faces], [[1, 2, 3], [3, 4, 1], [1, 2, 5], [2, 3, 5], [3, 4, 5], [4, 1, 5]]
                                  if binary else  # trimesh (ascii) lists triangles before split quads
                                  [[1, 2, 5], [2, 3, 5], [3, 4, 5], [4, 1, 5], [1, 2, 3], [3, 4, 1]])
    # a header that promises more vertices than the file holds is refused before parsing
    data = ply_text(V, F, binary).replace(b"element vertex 7", b"element vertex 70000000")
    path.write_bytes(data)
    with pytest.raises(ValueError, match="truncated or corrupt" if binary else "truncated or damaged"):
        ngf.load_mesh(path)
    if binary:  # a face list running past the end of the file
        path.write_bytes(ply_text(V, F, binary)[:-6])
        with pytest.raises(ValueError, match="past the end of the file"):
            ngf.load_mesh(path)


def test_stl_of_closed_mesh_is_welded_with_the_map_kept(tmp_path):
    """An STL stores three corners per triangle: welding makes one closed surface, results per file corner."""
    V, F, soup_v, soup_f = icosphere_soup(1)
    path = tmp_path / "sphere.stl"
    trimesh.Trimesh(V, F, process=False).export(path)
    m = ngf.load_mesh(path)
    assert m.n_input == 3 * len(F) and len(m.internal_vertices) == len(V) and m.welded and m.n_components == 1
    corners = read_mesh_file(path)[0]  # the file's own corners (float32 in the file)
    np.testing.assert_array_equal(m.internal_vertices[m.input_to_internal], corners)
    d = ngf.geodesic_distances(path, [0], device="cpu")[0]
    assert d.shape == (3 * len(F),) and np.all(np.isfinite(d))
    # the same as on the indexed sphere, corner by corner
    ref = ngf.geodesic_distances((V, F), [F[0, 0]], device="cpu")[0]
    np.testing.assert_allclose(d, ref[F.ravel()], rtol=1e-5, atol=1e-5)
    # without welding every triangle is its own component: what the issue saw
    raw = ngf.load_mesh(path, weld=False)
    assert raw.n_components == len(F)


def test_welding_rules(tmp_path):
    """Triangle soups are welded automatically; other input keeps its topology unless weld=True."""
    V, F, soup_v, soup_f = icosphere_soup(0)
    soup = ngf.load_mesh((soup_v, soup_f))
    assert soup.welded and len(soup.internal_vertices) == len(V) and soup.n_components == 1
    assert soup.n_input == len(soup_v)
    np.testing.assert_array_equal(soup.internal_vertices[soup.input_to_internal], soup_v)
    # representatives are first occurrences, in input order
    assert np.all(np.diff(soup.index) > 0)
    np.testing.assert_array_equal(soup.vertex(soup.index), np.arange(len(soup.internal_vertices)))
    # two tetrahedra sharing a coordinate but not a vertex record: kept apart unless asked
    tet = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    tf = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    v2 = np.vstack([tet, tet + [1, 0, 0]])  # vertex 1 of the first equals vertex 0 of the second
    f2 = np.vstack([tf, tf + 4])
    assert ngf.load_mesh((v2, f2)).n_components == 2
    welded = ngf.load_mesh((v2, f2), weld=True)
    assert welded.n_components == 1 and len(welded.internal_vertices) == 7
    assert welded.vertex(1) == welded.vertex(4)
    np.testing.assert_array_equal(welded.to_input(np.arange(7.0))[[1, 4]], [1, 1])
    # -0.0 and 0.0 are the same coordinate
    v3 = v2.copy()
    v3[4, 1:] = -0.0
    assert len(ngf.load_mesh((v3, f2), weld=True).internal_vertices) == 7
    # the same holds for files
    path = tmp_path / "two.obj"
    trimesh.Trimesh(v2, f2, process=False).export(path)
    assert ngf.load_mesh(path).n_components == 2 and ngf.load_mesh(path, weld=True).n_components == 1
    with pytest.raises(ValueError, match="weld must be"):
        ngf.load_mesh((v2, f2), weld="yes")


def test_bad_meshes(tmp_path):
    with pytest.raises(FileNotFoundError, match="mesh file not found"):
        ngf.load_mesh(tmp_path / "nope.obj")
    with pytest.raises(ValueError, match="is a folder"):
        ngf.load_mesh(tmp_path)
    with pytest.raises(ValueError, match="no faces"):
        ngf.load_mesh((np.zeros((3, 3)), np.zeros((0, 3), int)))
    with pytest.raises(ValueError, match="non-finite"):
        ngf.load_mesh((np.array([[0, 0, 0], [1, 0, 0], [0, np.nan, 0]]), np.array([[0, 1, 2]])))
    with pytest.raises(ValueError, match="face indices"):
        ngf.load_mesh((np.eye(3), np.array([[0, 1, 5]])))
    with pytest.raises(ValueError, match=r"shape \(V, 3\)"):
        ngf.load_mesh((np.zeros((3, 2)), np.array([[0, 1, 2]])))
    with pytest.raises(TypeError, match="integer"):
        ngf.load_mesh((np.eye(3), np.array([[0, 1, 2.0]])))
    with pytest.raises(ValueError, match="degenerate"):
        ngf.load_mesh((np.ones((3, 3)), np.array([[0, 1, 2]])))
    # a NaN in a vertex no face uses is harmless: that vertex gets NaN anyway
    m = ngf.load_mesh((np.array([[np.nan] * 3, [0, 0, 0], [1, 0, 0], [0, 1, 0]]), np.array([[1, 2, 3]])))
    assert m.n_input == 4 and len(m.internal_vertices) == 3
    # STL whose triangle count disagrees with its size
    stl = tmp_path / "short.stl"
    stl.write_bytes(b"\0" * 80 + struct.pack("<I", 1000) + b"\0" * 100)
    with pytest.raises(ValueError, match="declares 1000 triangles"):
        ngf.load_mesh(stl)
    ply = tmp_path / "x.ply"
    ply.write_bytes(b"PK\x03\x04 zip data")
    with pytest.raises(ValueError, match="not a mesh file"):
        ngf.load_mesh(ply)
    with pytest.raises(TypeError, match="cannot make a mesh"):
        ngf.load_mesh(42)
    with pytest.raises(ValueError, match="unsupported mesh format .abc"):
        ngf.load_mesh(write(tmp_path / "m.abc", TET_OBJ))
    if os.getuid() != 0:  # root reads anything
        unreadable = write(tmp_path / "locked.obj", TET_OBJ)
        unreadable.chmod(0)
        with pytest.raises(PermissionError):
            ngf.load_mesh(unreadable)


# --- property tests: the numbering survives every way in ------------------------------------------------------

from hypothesis import HealthCheck, assume, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

PROPERTY = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@st.composite
def numbered_meshes(draw):
    """Vertex records in random order with unused ones among them, and random triangles over the used ones."""
    n_used = draw(st.integers(3, 12))
    n_unused = draw(st.integers(0, 4))
    coord = st.one_of(st.integers(-5, 5).map(float), st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False))
    pts = np.array(draw(st.lists(st.tuples(coord, coord, coord), min_size=n_used + n_unused,
                                 max_size=n_used + n_unused)), dtype=np.float64).reshape(-1, 3)
    order = np.array(draw(st.permutations(range(len(pts)))))
    used_ids = order[:n_used]  # input positions of the used vertices, in random order
    tri = st.lists(st.sampled_from(range(n_used)), min_size=3, max_size=3, unique=True)
    faces = np.array(draw(st.lists(tri, min_size=1, max_size=2 * n_used)), dtype=np.int64)
    faces = used_ids[faces]
    referenced = np.unique(faces)
    assume(np.ptp(pts[referenced], axis=0).max() > 0)  # not all referenced vertices at one point
    return pts, faces


def write_obj(path, v, f, style):
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in v.tolist()]
    n = len(v)
    for a, b, c in f.tolist():
        if style == "relative":
            idx = [str(k - n) for k in (a, b, c)]
        elif style == "slashes":
            idx = [f"{k + 1}/1/{k + 1}" for k in (a, b, c)]
        else:
            idx = [str(k + 1) for k in (a, b, c)]
        lines.append("f " + " ".join(idx))
    path.write_text("\n".join(["# generated", "vt 0 0"] + lines) + "\n")


def check_numbering(m, v, f, welded_ok):
    """Every input vertex lands on an internal vertex with its own coordinates; faces are the input's."""
    inv = m.input_to_internal
    used = np.zeros(len(v), bool)
    used[f.ravel()] = True
    assert m.n_input == len(v)
    assert np.all((inv >= 0) == used)
    np.testing.assert_array_equal(m.internal_vertices[inv[used]], v[used])
    np.testing.assert_array_equal(m.internal_faces, inv[f])
    if not welded_ok:
        assert len(np.unique(inv[used])) == used.sum()
    # a per-vertex value computed on the internal mesh comes back on the right input vertices
    val = m.internal_vertices @ np.array([1.0, 1e-3, 1e-6])
    back = m.to_input(val)
    np.testing.assert_array_equal(back[used], v[used] @ np.array([1.0, 1e-3, 1e-6]))
    assert np.all(np.isnan(back[~used]))


@PROPERTY
@given(mesh=numbered_meshes(), style=st.sampled_from(["plain", "relative", "slashes"]))
def test_property_obj_numbering(tmp_path, mesh, style):
    v, f = mesh
    path = tmp_path / "r.obj"
    write_obj(path, v, f, style)
    m = ngf.load_mesh(path)
    check_numbering(m, v, f, welded_ok=m.welded)
    arrays = ngf.load_mesh((v, f))
    np.testing.assert_array_equal(arrays.input_to_internal, m.input_to_internal)
    assert arrays.fingerprint == m.fingerprint


@PROPERTY
@given(mesh=numbered_meshes(), binary=st.booleans())
def test_property_ply_numbering(tmp_path, mesh, binary):
    v, f = mesh
    path = tmp_path / "r.ply"
    path.write_bytes(ply_text(v, f.tolist(), binary))
    m = ngf.load_mesh(path)
    check_numbering(m, v, f, welded_ok=m.welded)


@PROPERTY
@given(mesh=numbered_meshes())
def test_property_stl_numbering(tmp_path, mesh):
    """STL numbers the corners of its triangles; welded vertices give every corner its vertex's value."""
    v, f = mesh
    path = tmp_path / "r.stl"
    trimesh.Trimesh(v, f, process=False).export(path)
    corners = v[f.ravel()].astype(np.float32).astype(np.float64)  # STL stores float32
    assume(np.ptp(corners, axis=0).max() > 0)
    m = ngf.load_mesh(path)
    soup_f = np.arange(len(corners)).reshape(-1, 3)
    check_numbering(m, corners, soup_f, welded_ok=True)
    # exactly the corners with equal coordinates share a vertex
    _, groups = np.unique(corners + 0.0, axis=0, return_inverse=True)
    inv = m.input_to_internal
    same = inv[:, None] == inv[None, :]
    np.testing.assert_array_equal(same, groups.reshape(-1)[:, None] == groups.reshape(-1)[None, :])


# --- encodings, line ends and truncations ----------------------------------------------------------------------

TRAILING_UNUSED = TET_OBJ + "v 8 8 8\n"  # an unused last vertex: a dropped first record would still load


@pytest.mark.parametrize("name, encode", [
    ("utf-8 BOM", lambda t: b"\xef\xbb\xbf" + t.encode()),
    ("CRLF", lambda t: t.replace("\n", "\r\n").encode()),
    ("BOM + CRLF", lambda t: b"\xef\xbb\xbf" + t.replace("\n", "\r\n").encode()),
    ("CR only", lambda t: t.replace("\n", "\r").encode()),
    ("UTF-16 LE with BOM", lambda t: t.encode("utf-16")),
    ("UTF-16 BE with BOM", lambda t: b"\xfe\xff" + t.encode("utf-16-be")),
    ("UTF-32 with BOM", lambda t: t.encode("utf-32")),
    ("Latin-1 byte in a comment", lambda t: ("# caf\xe9, r\xe9sum\xe9\n" + t).encode("latin-1")),
    ("Latin-1 byte in an object name", lambda t: ("o pi\xe8ce\n" + t).encode("latin-1")),
])
@pytest.mark.parametrize("text", [TET_OBJ, TRAILING_UNUSED])
def test_obj_encodings_read_the_same_mesh(tmp_path, name, encode, text):
    want_v, want_f, _ = read_mesh_file(write(tmp_path / "plain.obj", text))
    path = tmp_path / "enc.obj"
    path.write_bytes(encode(text))
    v, f, _ = read_mesh_file(path)
    np.testing.assert_array_equal(v, want_v, err_msg=name)
    np.testing.assert_array_equal(f, want_f, err_msg=name)


def test_obj_that_is_not_text_or_misencoded_is_refused_clearly(tmp_path):
    path = tmp_path / "u16.obj"
    path.write_bytes(TET_OBJ.encode("utf-16-le"))  # no byte-order mark: NUL bytes between the characters
    with pytest.raises(ValueError, match="UTF-16 text without a byte-order mark, save it as UTF-8"):
        read_mesh_file(path)
    path.write_bytes(b"\xff\xfe" + b"v\x00 \x00" + b"\x00\xd8")  # a UTF-16 BOM, then a lone surrogate
    with pytest.raises(ValueError, match="UTF-16-LE byte-order mark but is not UTF-16-LE text"):
        read_mesh_file(path)
    # a non-UTF-8 byte inside a coordinate is still an error naming the line
    path.write_bytes(TET_OBJ.replace("v 1 0 0", "v 1 0 \xe9").encode("latin-1"))
    with pytest.raises(ValueError, match="line 3: vertex coordinate"):
        read_mesh_file(path)


@pytest.mark.parametrize("index", ["99999999999999999999999", "-99999999999999999999999", str(2**63), str(-2**63 - 1)])
def test_obj_face_index_beyond_int64_is_a_clear_error(tmp_path, index):
    path = write(tmp_path / "big.obj", TET_OBJ + f"f 2 3 {index}\n")
    with pytest.raises(ValueError, match=rf"line 10: vertex index {index} is out of range: the file has 5 vertex"):
        read_mesh_file(path)


PLY_V = np.array([[9, 9, 9], [0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 1.0], [7, 7, 7]])
PLY_F = [[1, 2, 3, 4], [1, 2, 5], [2, 3, 5], [3, 4, 5], [4, 1, 5]]


@pytest.mark.parametrize("faces", [PLY_F, PLY_F[1:]])  # mixed polygons, and triangles only (the fast path)
def test_truncated_ascii_ply_is_refused_at_every_cut(tmp_path, faces):
    full = ply_text(PLY_V, faces)
    path = tmp_path / "cut.ply"
    path.write_bytes(full)
    assert len(read_mesh_file(path)[0]) == len(PLY_V)
    body = full.index(b"end_header\n") + len(b"end_header\n")
    # every record boundary (line end) and every cut inside a record (after each space) before the last value
    cuts = [i + 1 for i in range(body, len(full) - 1) if full[i:i + 1] in (b"\n", b" ")]
    assert len(cuts) > 20
    for c in cuts:
        path.write_bytes(full[:c])
        with pytest.raises(ValueError, match="truncated") as e:
            read_mesh_file(path)
        assert str(path) in str(e.value)


def test_ascii_ply_header_counts_must_match_the_body(tmp_path):
    full = ply_text(PLY_V, PLY_F)
    path = tmp_path / "h.ply"
    for declared, match in ((2_000_000_000, "declares 2000000000 face records but the file ends after 5"),
                            (6, "declares 6 face records but the file ends after 5"),
                            (4, "values follow the last record the PLY header declares")):
        path.write_bytes(full.replace(b"element face 5", f"element face {declared}".encode()))
        with pytest.raises(ValueError, match=match):
            read_mesh_file(path)
    path.write_bytes(full.replace(b"element vertex 7", b"element vertex 9"))
    with pytest.raises(ValueError, match="the header's counts are wrong|truncated|not a mesh file|index"):
        read_mesh_file(path)
    # CRLF line ends read the same mesh
    path.write_bytes(full.replace(b"\n", b"\r\n"))
    v, f, _ = read_mesh_file(path)
    path.write_bytes(full)
    v0, f0, _ = read_mesh_file(path)
    np.testing.assert_array_equal(v, v0)
    np.testing.assert_array_equal(f, f0)


def test_truncated_binary_ply_and_stl_stay_refused(tmp_path):
    full = ply_text(PLY_V, PLY_F, binary=True)
    path = tmp_path / "b.ply"
    body = full.index(b"end_header\n") + len(b"end_header\n")
    for c in range(body, len(full)):
        path.write_bytes(full[:c])
        with pytest.raises(ValueError, match="truncated|runs past the end"):
            read_mesh_file(path)
    V, F, _, _ = icosphere_soup(0)
    stl = tmp_path / "s.stl"
    trimesh.Trimesh(V, F, process=False).export(stl)
    data = stl.read_bytes()
    for c in list(range(84, len(data), 50)) + [len(data) - 1]:
        stl.write_bytes(data[:c])
        with pytest.raises(ValueError, match="declares 20 triangles"):
            read_mesh_file(stl)


def test_welded_input_keeps_every_record_in_the_public_arrays():
    """Mesh.vertices and Mesh.faces stay in the numbering as given when the mesh is welded."""
    V, F, soup_v, soup_f = icosphere_soup(0)
    soup = ngf.load_mesh((soup_v, soup_f))
    np.testing.assert_array_equal(soup.vertices, soup_v)  # every corner record keeps its own position
    assert soup.faces.shape == soup_f.shape and soup.faces.max() < len(soup_v)
    np.testing.assert_array_equal(soup.vertices[soup.faces], soup_v[soup_f])
    np.testing.assert_array_equal(soup.components, np.zeros(len(soup_v), np.int32))
