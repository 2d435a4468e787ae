"""Files that could lose data or be misread: the one output rule (regular files replaced atomically, links written
through, devices/FIFOs/sockets/folders refused, an input never overwritten), and mesh inputs that are archives,
PLY files with extra per-face lists, or not regular files."""
from __future__ import annotations

import gzip
import io
import os
import socket
import stat
import tarfile
import zipfile

import numpy as np
import pytest

import neurogf_warp as ngf
from neurogf_warp.common.checks import InputError
from neurogf_warp.common.files import atomic_write_bytes, input_guard, note_input, output_target

# a tetrahedron whose file has two vertex records no face uses (the first and the fourth)
OBJ = """v 9 9 9
v 0 0 0
v 1 0 0
v 5 5 5
v 0 1 0
v 0 0 1
f 2 3 5
f 2 3 6
f 2 5 6
f 3 5 6
"""


def _write(path, text):
    path.write_text(text)
    return str(path)


def _fifo(path):
    os.mkfifo(path)
    return str(path)


# ---- the output rule -----------------------------------------------------------------------------------------

def test_regular_file_is_replaced_and_new_path_written(tmp_path):
    p = tmp_path / "out.bin"
    atomic_write_bytes(p, b"one")
    atomic_write_bytes(p, b"two")
    assert p.read_bytes() == b"two"


def test_fifo_and_socket_are_refused_and_stay(tmp_path):
    fifo = _fifo(tmp_path / "pipe.npy")
    with pytest.raises(InputError, match="FIFO.*not a regular file.*pass a regular file path"):
        atomic_write_bytes(fifo, b"x")
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)
    s = socket.socket(socket.AF_UNIX)
    try:
        s.bind(str(tmp_path / "sock.ngf"))
        with pytest.raises(InputError, match="socket"):
            atomic_write_bytes(tmp_path / "sock.ngf", b"x")
        assert stat.S_ISSOCK(os.lstat(tmp_path / "sock.ngf").st_mode)
    finally:
        s.close()


def test_device_node_is_refused_without_writing():
    # output_target decides before anything is written, so this is safe to ask of the real /dev/null
    with pytest.raises(InputError, match="device"):
        output_target("/dev/null")
    with pytest.raises(InputError, match="device"):
        output_target("/dev/zero", what="model file")


def test_folder_is_refused(tmp_path):
    with pytest.raises(IsADirectoryError, match="it is a folder"):
        atomic_write_bytes(tmp_path, b"x")


def test_symlink_is_written_through_and_stays_a_link(tmp_path):
    target = tmp_path / "real.ngf"
    target.write_bytes(b"old")
    link = tmp_path / "link.ngf"
    link.symlink_to(target)
    atomic_write_bytes(link, b"new")
    assert link.is_symlink() and os.readlink(link) == str(target)
    assert target.read_bytes() == b"new"
    # a chain of links, and a link whose target does not exist yet (it is created)
    chain = tmp_path / "chain.ngf"
    chain.symlink_to(link)
    atomic_write_bytes(chain, b"newer")
    assert chain.is_symlink() and target.read_bytes() == b"newer"
    dangling = tmp_path / "dangling.npy"
    dangling.symlink_to(tmp_path / "later.npy")
    atomic_write_bytes(dangling, b"made")
    assert dangling.is_symlink() and (tmp_path / "later.npy").read_bytes() == b"made"


def test_symlink_to_a_fifo_is_refused(tmp_path):
    fifo = _fifo(tmp_path / "pipe")
    link = tmp_path / "out.npy"
    link.symlink_to(fifo)
    with pytest.raises(InputError, match="FIFO"):
        atomic_write_bytes(link, b"x")
    assert link.is_symlink() and stat.S_ISFIFO(os.stat(link).st_mode)


def test_inputs_are_never_targets(tmp_path):
    mesh = _write(tmp_path / "m.obj", OBJ)
    with pytest.raises(InputError, match="input file .*m.obj.*choose another output path"):
        atomic_write_bytes(mesh, b"x", inputs=[mesh])
    hard = tmp_path / "hard.obj"
    os.link(mesh, hard)  # the same file under another name
    with pytest.raises(InputError, match="input file"):
        atomic_write_bytes(hard, b"x", inputs=[mesh])
    soft = tmp_path / "soft.obj"
    soft.symlink_to(mesh)
    with pytest.raises(InputError, match="input file"):
        atomic_write_bytes(soft, b"x", inputs=[mesh])
    with pytest.raises(InputError, match="input file"):  # a relative spelling of the same path
        atomic_write_bytes(os.path.relpath(mesh), b"x", inputs=[os.path.abspath(mesh)])
    assert open(mesh).read() == OBJ
    atomic_write_bytes(tmp_path / "other.obj", b"x", inputs=[mesh, object()])  # others are fine


def test_input_guard_protects_files_read_inside_it(tmp_path):
    mesh = _write(tmp_path / "m.obj", OBJ)
    with input_guard():
        ngf.load_mesh(mesh)  # the reader notes its file
        with pytest.raises(InputError, match="input file"):
            atomic_write_bytes(mesh, b"x")
        note_input(tmp_path / "data.npz")
        (tmp_path / "data.npz").write_bytes(b"d")
        with pytest.raises(InputError, match="input file"):
            atomic_write_bytes(tmp_path / "data.npz", b"x")
    atomic_write_bytes(tmp_path / "data.npz", b"x")  # outside the guard the caller decides
    assert open(mesh).read() == OBJ


def test_train_refuses_its_own_mesh_as_output_even_with_force(tmp_path):
    mesh = _write(tmp_path / "ico.obj", OBJ)
    for force in (False, True):
        with pytest.raises(InputError, match="input file"):
            ngf.train(mesh, mesh, force=force, progress=False)
    link = tmp_path / "model.ngf"
    link.symlink_to(mesh)
    with pytest.raises(InputError, match="input file"):
        ngf.train(mesh, link, force=True, progress=False)
    assert open(mesh).read() == OBJ
    assert not (tmp_path / "ico.train").exists() or not os.listdir(tmp_path / "ico.train")


def test_train_refuses_a_fifo_output(tmp_path):
    mesh = _write(tmp_path / "ico.obj", OBJ)
    fifo = _fifo(tmp_path / "m.ngf")
    with pytest.raises(InputError, match="FIFO"):
        ngf.train(mesh, fifo, force=True, progress=False)
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)


def _small_model(mesh):
    import torch

    from neurogf_warp.model.model import Model
    from neurogf_warp.model.network import NeuroGFNet

    torch.manual_seed(0)
    m = ngf.load_mesh(mesh)
    return Model(net=NeuroGFNet(64), mesh=m, center=m.center, scale=m.scale)


def test_save_follows_the_rule(tmp_path):
    mesh = _write(tmp_path / "m.obj", OBJ)
    model = _small_model(mesh)
    fifo = _fifo(tmp_path / "f.ngf")
    with pytest.raises(InputError, match="FIFO"):
        ngf.save(model, fifo)
    link = tmp_path / "link.ngf"
    link.symlink_to(tmp_path / "real.ngf")
    ngf.save(model, link)
    assert link.is_symlink() and ngf.load(tmp_path / "real.ngf").mesh.n_input == 6


def test_cli_output_never_replaces_an_input_or_a_fifo(tmp_path):
    from neurogf_warp.cli.main import main

    mesh = _write(tmp_path / "m.obj", OBJ)
    path = str(tmp_path / "m.ngf")
    ngf.save(_small_model(mesh), path)
    before = open(path, "rb").read()
    assert main(["ssad", path, "--source", "1", "-o", path.replace(".ngf", ".npy"), "--device", "cpu"]) == 0
    link = tmp_path / "model_link.npy"
    link.symlink_to(path)  # -o names the model file through a link
    assert main(["ssad", path, "--source", "1", "-o", str(link), "--device", "cpu"]) == 2
    assert open(path, "rb").read() == before
    fifo = _fifo(tmp_path / "pipe.npy")
    assert main(["ssad", path, "--source", "1", "-o", fifo, "--device", "cpu"]) == 2
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)


# ---- mesh inputs -------------------------------------------------------------------------------------------

def _same_mesh(a, b):
    np.testing.assert_array_equal(a.vertices, b.vertices)  # NaN rows where no face uses the vertex
    np.testing.assert_array_equal(a.faces, b.faces)
    assert a.fingerprint == b.fingerprint


def test_archives_keep_the_file_numbering(tmp_path):
    plain = ngf.load_mesh(_write(tmp_path / "t.obj", OBJ))
    assert plain.n_input == 6
    with zipfile.ZipFile(tmp_path / "t.zip", "w") as z:
        z.writestr("inner/t.obj", OBJ)
        z.writestr("inner/t.mtl", "newmtl a\n")  # not a mesh: ignored
    tar_gz = tmp_path / "t.tar.gz"
    with tarfile.open(tar_gz, "w:gz") as t:
        data = OBJ.encode()
        info = tarfile.TarInfo("t.obj")
        info.size = len(data)
        t.addfile(info, io.BytesIO(data))
    (tmp_path / "t.obj.gz").write_bytes(gzip.compress(OBJ.encode()))
    for name in ("t.zip", "t.tar.gz", "t.obj.gz"):
        m = ngf.load_mesh(tmp_path / name)
        _same_mesh(m, plain)
        assert np.isnan(m.vertices[3]).all() and m.vertices[1].tolist() == [0, 0, 0]


def test_archive_with_several_or_no_meshes_is_refused(tmp_path):
    with zipfile.ZipFile(tmp_path / "two.zip", "w") as z:
        z.writestr("a.obj", OBJ)
        z.writestr("b.obj", OBJ)
    with pytest.raises(InputError, match="holds 2 mesh files"):
        ngf.load_mesh(tmp_path / "two.zip")
    with zipfile.ZipFile(tmp_path / "none.zip", "w") as z:
        z.writestr("readme.txt", "hello")
    with pytest.raises(InputError, match="holds no mesh file"):
        ngf.load_mesh(tmp_path / "none.zip")
    (tmp_path / "bad.zip").write_bytes(b"PK\x03\x04 not really")
    with pytest.raises(InputError, match="not a valid .zip archive"):
        ngf.load_mesh(tmp_path / "bad.zip")


def test_unsupported_format_message_lists_only_what_loads(tmp_path):
    with pytest.raises(InputError) as e:
        ngf.load_mesh(_write(tmp_path / "t.mesh3", OBJ))
    msg = str(e.value)
    for suffix in (".tar.gz", ".tgz", ".tar.bz2", ".zip", ".tar"):
        assert suffix in msg
        archive = tmp_path / f"a{suffix}"
        if suffix == ".zip":
            with zipfile.ZipFile(archive, "w") as z:
                z.writestr("t.obj", OBJ)
        else:
            with tarfile.open(archive, "w:" + {".tar.gz": "gz", ".tgz": "gz", ".tar.bz2": "bz2"}.get(suffix, "")) as t:
                t.add(tmp_path / "t.mesh3", arcname="t.obj")
        assert ngf.load_mesh(archive).n_input == 6, suffix


PLY_UV = """ply
format ascii 1.0
element vertex 5
property float x
property float y
property float z
element face 4
property list uchar int vertex_indices
property list uchar float texcoord
end_header
0 0 0
1 0 0
0 1 0
0 0 1
7 7 7
3 0 1 2 6 0 0 1 0 0 1
3 0 1 3 6 0 0 1 0 0 .5
3 0 2 3 6 0 0 .5 0 0 1
3 1 2 3 6 .5 .5 1 0 0 1
"""


def test_ply_with_per_face_texture_lists_keeps_its_vertices(tmp_path):
    m = ngf.load_mesh(_write(tmp_path / "uv.ply", PLY_UV))
    assert m.n_input == 5 and len(m.internal_vertices) == 4
    np.testing.assert_array_equal(m.faces, [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])
    assert np.isnan(m.vertices[4]).all() and m.vertices[3].tolist() == [0, 0, 1]
    # the same in binary, with a per-face int list before the corners
    head = ("ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
            "property float z\nelement face 2\nproperty list uchar int tags\nproperty list uchar int vertex_indices\n"
            "end_header\n").encode()
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], "<f4").tobytes()
    faces = b""
    for tri in ([0, 1, 2], [1, 2, 3]):
        faces += bytes([2]) + np.array([5, 6], "<i4").tobytes() + bytes([3]) + np.array(tri, "<i4").tobytes()
    (tmp_path / "tags.ply").write_bytes(head + v + faces)
    m = ngf.load_mesh(tmp_path / "tags.ply")
    np.testing.assert_array_equal(m.faces, [[0, 1, 2], [1, 2, 3]])


@pytest.mark.parametrize("make", ["dev_null", "fifo", "socket"])
def test_special_files_as_inputs_are_not_regular_files(tmp_path, make):
    if make == "dev_null":
        path = "/dev/null"
    elif make == "fifo":
        path = _fifo(tmp_path / "m.obj")
    else:
        path = str(tmp_path / "m.obj")
        s = socket.socket(socket.AF_UNIX)
        s.bind(path)
    with pytest.raises(InputError, match="not a regular file") as e:
        ngf.load_mesh(path)
    assert "not found" not in str(e.value)
    with pytest.raises(InputError, match="model file .* not a regular file"):
        ngf.load(path)
    with pytest.raises(FileNotFoundError, match="mesh file not found"):
        ngf.load_mesh(tmp_path / "missing.obj")


def test_a_file_that_failed_to_load_is_no_protected_input(tmp_path):
    """``train`` writes a damaged model file again; only files that loaded are a command's inputs."""
    damaged = tmp_path / "m.ngf"
    damaged.write_bytes(b"not a model")
    with input_guard():
        with pytest.raises(ValueError):
            ngf.load(damaged)
        atomic_write_bytes(damaged, b"rewritten")
        mesh = _write(tmp_path / "m.obj", OBJ)
        ngf.load_mesh(mesh)
        with pytest.raises(InputError, match="input file"):
            atomic_write_bytes(mesh, b"x")
    assert damaged.read_bytes() == b"rewritten"
