"""Files that cannot destroy data and paths of every shape: model files never take a mesh's name, a folder, None or
an input (by any path: hard links, symbolic links, '..'); names with newlines and non-ASCII letters round-trip;
damaged or foreign model files are refused; the command line maps resource failures to exit code 1 without
calling them bugs."""
import hashlib
import os

import numpy as np
import pytest
import torch
import trimesh

import neurogf_warp as ngf
from neurogf_warp.common.checks import InputError
from neurogf_warp.common.files import output_target


@pytest.fixture(scope="module")
def model():
    from neurogf_warp.model.model import Model
    from neurogf_warp.model.network import NeuroGFNet

    tm = trimesh.creation.icosphere(subdivisions=2)
    m = ngf.load_mesh((np.asarray(tm.vertices), np.asarray(tm.faces)))
    torch.manual_seed(0)
    return Model(net=NeuroGFNet(64), mesh=m, center=m.center, scale=m.scale)


def _digest(path):
    return hashlib.sha256(open(path, "rb").read()).hexdigest()


@pytest.mark.parametrize("name", ["bunny.obj", "BUNNY.PLY", "part.stl", "mesh.zip", "mesh.tar.gz", "mesh.obj.gz"])
def test_a_model_is_never_saved_under_a_mesh_name(model, tmp_path, name):
    target = tmp_path / name
    target.write_bytes(b"v 0 0 0\n")
    before = _digest(target)
    with pytest.raises(InputError, match=r"mesh file's.*save to a \.ngf path"):
        ngf.save(model, target)
    assert _digest(target) == before


def test_train_refuses_a_mesh_name_before_any_work(tmp_path):
    tm = trimesh.creation.icosphere(subdivisions=1)
    mesh = tmp_path / "ico.obj"
    tm.export(mesh)
    other = tmp_path / "other.obj"
    other.write_text("v 0 0 0\n")
    with pytest.raises(InputError, match="mesh file's"):
        ngf.train(mesh, other, budget_seconds=5, device="cpu", progress=False)
    assert other.read_text() == "v 0 0 0\n" and sorted(os.listdir(tmp_path)) == ["ico.obj", "other.obj"]


@pytest.mark.parametrize("path", [None, 3, b"", ""])
def test_a_path_that_is_not_a_file_name_is_named(model, path):
    with pytest.raises(InputError, match="model file path"):
        ngf.save(model, path)


@pytest.mark.parametrize("name", ["new\nline.ngf", "模型 é.ngf", " lead and trail .ngf", "-dash.ngf"])
def test_odd_names_round_trip(model, tmp_path, name):
    path = tmp_path / name
    ngf.save(model, path)
    assert os.listdir(tmp_path) == [name]
    np.testing.assert_array_equal(ngf.ssad(ngf.load(path), 0), ngf.ssad(model, 0))


def test_a_symlinked_folder_is_written_through(model, tmp_path):
    (tmp_path / "real").mkdir()
    os.symlink(tmp_path / "real", tmp_path / "link")
    ngf.save(model, tmp_path / "link" / "m.ngf")
    assert os.listdir(tmp_path / "real") == ["m.ngf"] and os.path.islink(tmp_path / "link")


@pytest.mark.parametrize("how", ["hard link", "symlink", "dot-dot", "absolute", "dot"])
def test_an_input_is_refused_by_any_path(tmp_path, monkeypatch, how):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "ico.obj").write_text("v 0 0 0\n")
    (tmp_path / "sub").mkdir()
    target = {"hard link": "hard.obj", "symlink": "soft.obj", "dot-dot": "sub/../ico.obj",
              "absolute": str(tmp_path / "ico.obj"), "dot": "./ico.obj"}[how]
    if how == "hard link":
        os.link("ico.obj", "hard.obj")
    if how == "symlink":
        os.symlink("ico.obj", "soft.obj")
    with pytest.raises(InputError, match="it is the input file"):
        output_target(target, inputs=["ico.obj"])
    with pytest.raises(InputError, match="it is the input file"):  # the input named through the other path
        output_target("ico.obj", inputs=[target])


@pytest.mark.parametrize("damage", ["empty", "one byte", "half", "all but one byte", "reversed", "text"])
def test_damaged_model_files_are_refused(model, tmp_path, damage):
    good = tmp_path / "good.ngf"
    ngf.save(model, good)
    data = good.read_bytes()
    bad = {"empty": b"", "one byte": data[:1], "half": data[: len(data) // 2], "all but one byte": data[:-1],
           "reversed": data[::-1], "text": b"hello"}[damage]
    path = tmp_path / "bad.ngf"
    path.write_bytes(bad)
    with pytest.raises(InputError, match=r"bad\.ngf.*damaged"):
        ngf.load(path)


def test_a_model_with_another_mesh_is_refused(model, tmp_path):
    path = tmp_path / "m.ngf"
    ngf.save(model, path)
    moved = tmp_path / "moved.obj"
    trimesh.Trimesh(model.mesh.vertices * 1.0001, model.mesh.faces, process=False).export(moved)
    with pytest.raises(ValueError, match="trained on a different mesh.*check_mesh=False"):
        ngf.load(path, mesh=moved)


def test_cli_resource_failures_are_no_bugs(model, tmp_path, capsys):
    from neurogf_warp.cli.main import main

    path = tmp_path / "m.ngf"
    ngf.save(model, path)
    rc = main(["path", str(path), "--p", "1", "0", "0", "--q", "0", "1", "0", "--m", str(10 ** 12), "-q"])
    err = capsys.readouterr().err
    assert rc == 1 and "failed:" in err and "m=1,000,000,000,000 points" in err
    assert "internal error" not in err and "bug" not in err


def test_cli_train_refuses_a_mesh_name_for_its_model(tmp_path, capsys):
    from neurogf_warp.cli.main import main

    tm = trimesh.creation.icosphere(subdivisions=1)
    tm.export(tmp_path / "ico.obj")
    assert main(["train", str(tmp_path / "ico.obj"), "-o", str(tmp_path / "m.ply"), "-q"]) == 2
    assert ".ngf" in capsys.readouterr().err and sorted(os.listdir(tmp_path)) == ["ico.obj"]


def test_generalizable_training_never_writes_over_a_mesh(tmp_path):
    """The collection's own meshes sit beside a typo'd output: refused before any ground truth is computed."""
    from neurogf_warp.generalizable.train import train_generalizable

    trimesh.creation.icosphere(subdivisions=1).export(tmp_path / "shape.obj")
    before = _digest(tmp_path / "shape.obj")
    with pytest.raises(InputError, match=r"mesh file's.*save to a \.pt path"):
        train_generalizable(tmp_path, tmp_path / "shape.obj", device="cpu")
    with pytest.raises(InputError, match="must be a file name"):
        train_generalizable(tmp_path, None, device="cpu")
    assert _digest(tmp_path / "shape.obj") == before and os.listdir(tmp_path) == ["shape.obj"]
