"""Model files and meshes: round trips, released checkpoints, atomic saves and clear errors."""
import os

import numpy as np
import pytest
import torch
import trimesh

import neurogf_warp as ngf
from neurogf_warp import files
from tests.conftest import shared_path

DEV = "cpu"


def bunny_ckpt():
    return shared_path("checkpoints", "official", "NeuroGF_Pretrainer__bunny_final.pth")


def fandisk():
    return (shared_path("checkpoints", "official", "NeuroGF_Pretrainer__fandisk_final.pth"),
            shared_path("meshes", "fandisk.obj"))


def test_load_mesh_normalization_and_index_map(tmp_path):
    v = np.array([[9, 9, 9], [0, 0, 0], [2, 0, 0], [0, 4, 0], [0, 0, 1]], float)  # vertex 0 unused
    f = np.array([[1, 2, 3], [1, 3, 4], [1, 4, 2], [2, 4, 3]])
    path = tmp_path / "tet.obj"
    trimesh.Trimesh(v, f, process=False).export(path)
    m = ngf.load_mesh(path)
    assert m.n_input in (4, 5)  # trimesh's OBJ reader may drop the unused vertex itself
    m = ngf.load_mesh((v, f))
    assert m.n_input == 5 and list(m.index) == [1, 2, 3, 4]
    np.testing.assert_allclose(m.center, [1, 2, 0.5])
    assert np.isclose(np.linalg.norm(m.normalized_vertices, axis=1).max(), 1.0)
    np.testing.assert_allclose(m.denormalize(m.normalize(v[1:])), v[1:])
    assert np.isnan(m.to_input(np.ones(4))[0])


def test_released_checkpoint_normalization_matches_reference():
    """Bounding-box centre + unit max norm, as measured for the released bunny (reference/README.md)."""
    model = ngf.load(bunny_ckpt(), mesh=shared_path("meshes", "stanford-bunny.obj"))
    np.testing.assert_allclose(model.center, [-0.0168405, 0.110154, -0.001537], atol=1e-6)
    assert abs(model.scale - 9.543826404254942) < 1e-6
    # the mesh lies on the SDF head's zero level set
    s = ngf.sdf(model, model.mesh.vertices[::50], device=DEV) * model.scale
    assert np.abs(s).mean() < 2e-3


def test_save_load_round_trip(tmp_path):
    ck, mesh = fandisk()
    model = ngf.load(ck, mesh=mesh, querier=shared_path("checkpoints", "official",
                                                        "SDist_Querier_Offline_Pretrainer__fandisk.pth"))
    out = tmp_path / "fandisk.ngf"
    ngf.save(model, out)
    back = ngf.load(out)  # the file carries its mesh and normalization
    assert back.mesh is not None and back.mesh.fingerprint == model.mesh.fingerprint
    assert back.querier is not None
    for k, v in model.net.state_dict().items():
        assert torch.equal(v, back.net.state_dict()[k]), k
    np.testing.assert_array_equal(ngf.ssad(back, 7, device=DEV), ngf.ssad(model, 7, device=DEV))
    again = ngf.load(out, mesh=mesh)  # with the right mesh given explicitly
    np.testing.assert_array_equal(again.center, model.center)


def test_mesh_fingerprint_mismatch_is_an_error(tmp_path):
    ck, mesh = fandisk()
    out = tmp_path / "m.ngf"
    ngf.save(ngf.load(ck, mesh=mesh), out)
    with pytest.raises(ValueError, match="different mesh"):
        ngf.load(out, mesh=shared_path("meshes", "spot.obj"))
    m = ngf.load(out, mesh=shared_path("meshes", "spot.obj"), check_mesh=False)
    assert m.mesh.n_input == 2930


def test_failed_save_keeps_previous_file(tmp_path, monkeypatch):
    ck, mesh = fandisk()
    model = ngf.load(ck, mesh=mesh)
    out = tmp_path / "m.ngf"
    ngf.save(model, out)
    before = out.read_bytes()

    def broken_fsync(fd):
        raise OSError("disk full (simulated)")

    monkeypatch.setattr(files.os, "fsync", broken_fsync)
    with pytest.raises(OSError, match="disk full"):
        ngf.save(model, out)
    assert out.read_bytes() == before
    assert os.listdir(tmp_path) == ["m.ngf"]  # no temporary file left behind


def test_saved_files_get_normal_permissions(tmp_path):
    ck, mesh = fandisk()
    out = tmp_path / "m.ngf"
    umask = os.umask(0o022)
    try:
        ngf.save(ngf.load(ck, mesh=mesh), out)
        assert out.stat().st_mode & 0o777 == 0o644
        out.chmod(0o640)
        ngf.save(ngf.load(ck, mesh=mesh), out)  # overwriting keeps the file's own permissions
        assert out.stat().st_mode & 0o777 == 0o640
    finally:
        os.umask(umask)


def test_bad_model_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        ngf.load(tmp_path / "missing.pth")
    junk = tmp_path / "junk.ngf"
    junk.write_bytes(b"not a model at all")
    with pytest.raises(ValueError, match="could not read"):
        ngf.load(junk)
    state = torch.load(bunny_ckpt(), weights_only=True)
    state.pop("gdf_head.1.linear.weight")
    state["extra.weight"] = torch.zeros(3)
    state["sdf_head.0.linear.weight"] = torch.zeros(64, 200)
    bad = tmp_path / "bad.pth"
    torch.save(state, bad)
    with pytest.raises(ValueError) as e:
        ngf.load(bad)
    msg = str(e.value)
    assert "missing keys (1): gdf_head.1.linear.weight" in msg
    assert "unexpected keys (1): extra.weight" in msg
    assert "sdf_head.0.linear.weight: file (64, 200) vs model (64, 256)" in msg
    with pytest.raises(ValueError, match="SDF-querier checkpoint"):
        ngf.load(shared_path("checkpoints", "official", "SDist_Querier_Offline_Pretrainer__bunny.pth"))


def test_bad_meshes(tmp_path):
    with pytest.raises(FileNotFoundError, match="mesh file not found"):
        ngf.load_mesh(tmp_path / "nope.obj")
    with pytest.raises(ValueError, match="no faces"):
        ngf.load_mesh((np.zeros((3, 3)), np.zeros((0, 3), int)))
    with pytest.raises(ValueError, match="non-finite"):
        ngf.load_mesh((np.array([[0, 0, 0], [1, 0, 0], [0, np.nan, 0]]), np.array([[0, 1, 2]])))
    with pytest.raises(ValueError, match="face indices"):
        ngf.load_mesh((np.eye(3), np.array([[0, 1, 5]])))
    with pytest.raises(ValueError, match=r"shape \(V, 3\)"):
        ngf.load_mesh((np.zeros((3, 2)), np.array([[0, 1, 2]])))
    empty = tmp_path / "empty.obj"
    empty.write_text("# nothing here\n")
    with pytest.raises(ValueError):
        ngf.load_mesh(empty)


def test_cli_writes_ssad(tmp_path):
    from neurogf_warp.cli import main

    ck, mesh = fandisk()
    out = tmp_path / "d.npy"
    assert main(["ssad", str(ck), "--mesh", str(mesh), "--source", "3", "-o", str(out), "--device", DEV]) == 0
    d = np.load(out)
    model = ngf.load(ck, mesh=mesh)
    np.testing.assert_array_equal(d, ngf.ssad(model, 3, device=DEV))
    assert main(["ssad", str(ck), "--mesh", str(mesh), "--source", "999999", "-o", str(out)]) == 2  # bad input: exit 2
