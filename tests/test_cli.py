"""The command line: help for every option, exit codes, outputs by extension, quiet Warp, the demo twice."""
import importlib.util
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from neurogf_warp.cli import main as cli


def run(argv, capsys):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_every_option_has_help_and_version(capsys):
    parser = cli.build_parser()
    subs = next(a for a in parser._actions if a.dest == "command").choices
    assert set(subs) == {"demo", "data", "train", "eval", "ssad", "msad", "distance", "path", "info", "render",
                         "sample", "voronoi", "isolines", "reconstruct", "gen-shapes", "gen-train", "gen-per-mesh"}
    for name, sub in subs.items():
        if name.startswith("gen-"):  # listed only: their own parsers are checked in test_cli_help.py
            continue
        for action in sub._actions:
            assert action.help, f"{name} {action.option_strings or action.dest} has no help text"
        assert {"--device", "--quiet", "--verbose"} <= {o for a in sub._actions for o in a.option_strings}, name
    with pytest.raises(SystemExit) as e:
        cli.main(["--version"])
    assert e.value.code == 0 and "neurogf-warp 0." in capsys.readouterr().out
    assert cli.main([]) == 2  # no command: usage on stderr


def test_help_imports_neither_torch_nor_warp():
    code = ("import sys; from neurogf_warp.cli import main as cli; p = cli.build_parser(); "
            "print('torch' in sys.modules, 'warp' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "False"]


@pytest.mark.slow
def test_query_commands_write_what_the_api_returns(trained, tmp_path, capsys):
    import neurogf_warp as ngf

    model, path = trained
    want = ngf.ssad(model, 5, device="cpu")
    code, _, err = run(["ssad", path, "--source", 5, "-o", tmp_path / "d.npy"], capsys)
    assert code == 0 and "kernel" in err
    np.testing.assert_array_equal(np.load(tmp_path / "d.npy"), want)
    assert run(["ssad", path, "--source", 5, "-o", tmp_path / "d.csv", "-q"], capsys)[0] == 0
    rows = np.loadtxt(tmp_path / "d.csv", delimiter=",", skiprows=1)
    assert rows.shape == (len(want), 2) and np.allclose(rows[:, 1], want, rtol=1e-6)

    code, _, _ = run(["msad", path, "--sources", 1, 7, "-o", tmp_path / "m.npy", "-q"], capsys)
    np.testing.assert_array_equal(np.load(tmp_path / "m.npy"), ngf.msad(model, [1, 7], device="cpu"))

    v = model.mesh.vertices
    np.save(tmp_path / "p.npy", v[:3])
    np.savetxt(tmp_path / "q.csv", v[10:13], delimiter=",")
    code, out, _ = run(["distance", path, "--p", tmp_path / "p.npy", "--q", tmp_path / "q.csv"], capsys)
    assert code == 0
    np.testing.assert_allclose([float(x) for x in out.split()], ngf.distance(model, v[:3], v[10:13]), rtol=1e-6)
    code, out, _ = run(["distance", path, "--p", *v[0], "--q", *v[10]], capsys)
    assert code == 0 and len(out.split()) == 1

    code, _, _ = run(["path", path, "--p", tmp_path / "p.npy", "--q", tmp_path / "q.csv", "--m", 16, "-o",
                      tmp_path / "paths.npy", "-q"], capsys)
    assert code == 0 and np.load(tmp_path / "paths.npy").shape == (3, 16, 3)
    assert run(["path", path, "--p", *v[0], "--q", *v[10], "--m", 8, "-o", tmp_path / "one.csv", "-q"], capsys)[0] == 0
    assert np.loadtxt(tmp_path / "one.csv", delimiter=",", skiprows=1).shape == (8, 5)


def test_info(trained, capsys):
    code, out, _ = run(["info", trained[1]], capsys)
    assert code == 0 and "D=64" in out and "642 vertices" in out and "1 connected component" in out
    code, out, _ = run(["info", trained[1], "--json"], capsys)
    info = json.loads(out)
    assert info["mesh"]["components"] == 1 and info["training"]["steps"]["joint"] == 300


@pytest.mark.parametrize("argv,match", [
    (["ssad", "{model}", "--source", "-1"], "--source must be a vertex index >= 0"),
    (["ssad", "{model}", "--source", "642"], "out of range: the mesh has 642 vertices"),
    (["ssad", "{model}", "-o", "{tmp}/d.txt"], "the file extension chooses the format"),
    (["ssad", "{model}", "-o", "{tmp}/missing/d.npy"], "does not exist"),
    (["ssad", "{tmp}/none.ngf"], "model file not found"),
    (["msad", "{model}", "--sources", "3", "-5"], "out of range"),
    (["distance", "{model}", "--p", "0", "0", "--q", "1", "1", "1"], "three numbers X Y Z or one file"),
    (["distance", "{model}", "--p", "0", "0", "0", "--q", "{tmp}/none.npy"], "no such file"),
    (["path", "{model}", "--p", "0", "0", "0", "--q", "1", "1", "1", "--m", "1"], "--m .* must be >= 2"),
    (["train", "{mesh}", "-o", "{tmp}/m.ngf", "--set", "lr=abc"], "lr must be a number"),
    (["train", "{mesh}", "-o", "{tmp}/m.ngf", "--set", "nonsense=1"], "unknown setting"),
    (["train", "{mesh}", "-o", "{tmp}/missing/m.ngf"], "does not exist"),
    (["train", "{mesh}", "-o", "{tmp}/m.pt"], "use the .ngf extension"),
    (["train", "{tmp}/none.obj", "-o", "{tmp}/m.ngf"], "mesh file not found"),
    (["data", "{mesh}", "-o", "{tmp}/d.npz", "--set", "lr=1"], "not a dataset setting"),
    (["data", "{mesh}", "-o", "{tmp}/d.txt"], "use one of .npz"),
    (["eval", "{model}", "--path-refine", "-2"], "--path-refine must be >= 0"),
])
def test_bad_input_exits_2_with_one_line(argv, match, trained, tmp_path, capsys):
    mesh = tmp_path / "ico.obj"
    import trimesh

    trimesh.creation.icosphere(subdivisions=2).export(mesh)
    argv = [a.format(model=trained[1], tmp=tmp_path, mesh=mesh) for a in argv]
    code, _, err = run(argv, capsys)
    assert code == 2, err
    import re

    assert re.search(match, err), err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "m.ngf").exists() and not (tmp_path / "d.npz").exists()


def test_eval_heat_without_potpourri3d_names_the_extra(trained, monkeypatch, capsys):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "potpourri3d" else real(name, *a))
    code, _, err = run(["eval", trained[1], "--heat"], capsys)
    assert code == 2 and 'pip install "neurogf-warp[heat]"' in err and "Traceback" not in err


def test_ply_and_render(trained, tmp_path, capsys):
    """A coloured .ply with one vertex per mesh vertex, and a picture with two paths."""
    import trimesh

    assert run(["ssad", trained[1], "--source", 3, "-o", tmp_path / "d.ply", "-q"], capsys)[0] == 0
    assert len(trimesh.load(tmp_path / "d.ply", process=False).vertices) == 642
    code, _, err = run(["render", trained[1], "--source", 0, "--paths", 5, 9, "--size", 64, 64, "-o",
                        tmp_path / "p.png", "-q"], capsys)
    assert code == 0, err
    assert (tmp_path / "p.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_render_exact_and_heat_fields(trained, tmp_path, capsys):
    """The pictures of the README: the exact field of a reference file and the heat method's, on a fixed colour
    scale and view; a source the reference does not have is bad input."""
    import neurogf_warp as ngf

    model = ngf.load(trained[1])
    m = model.mesh
    src = [3, 40]
    dist = ngf.geodesic_distances(m, src, device="cpu")
    ref = tmp_path / "ref.npz"
    np.savez(ref, positions=m.vertices.astype(np.float32), file_index=m.index.astype(np.int32),
             sources=m.vertex(np.array(src)).astype(np.int32), dist=dist[:, m.index])
    base = ["render", trained[1], "--size", 48, 48, "--vrange", 0, 1, "--view", 10, 40, "-q"]
    for extra in (["--source", 3, "--exact", ref, "--paths", 7, 9], ["--source", 3, 40, "--exact", ref],
                  ["--source", 3, 40, "--heat", "--paths", 7]):
        out = tmp_path / "p.png"
        code, _, err = run(base + extra + ["-o", out], capsys)
        assert code == 0, err
        assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    code, _, err = run(base + ["--source", 5, "--exact", ref, "-o", tmp_path / "x.png"], capsys)
    assert code == 2 and "not one of" in err


@pytest.mark.slow
def test_warp_stays_quiet_unless_verbose(trained):
    env = dict(os.environ, NEUROGF_DEBUG="")
    cmd = [sys.executable, "-m", "neurogf_warp.cli.main", "info", str(trained[1])]
    quiet = subprocess.run(cmd, capture_output=True, text=True, env=env)
    assert quiet.returncode == 0 and quiet.stderr == "", quiet.stderr
    loud = subprocess.run(cmd + ["--verbose"], capture_output=True, text=True, env=env)
    assert loud.returncode == 0 and "Warp" in loud.stderr  # the banner (and, without a GPU, the driver warning)


@pytest.mark.slow
def test_demo_twice_in_the_same_folder(tmp_path, capsys, ellipsoid):
    """The main job run twice: the second run answers from the finished model; nothing lands outside the folder."""
    import trimesh

    mesh = tmp_path / "blob.obj"
    trimesh.Trimesh(ellipsoid.vertices, ellipsoid.faces, process=False).export(mesh)
    out = tmp_path / "demo"
    argv = ["demo", "-o", out, "--mesh", mesh, "--device", "cpu", "--budget-seconds", "6"]
    code, first, _ = run(argv, capsys)
    assert code == 0 and "SSAD from vertex 0" in first
    code, second, err = run(argv, capsys)
    assert code == 0 and "already trained" in err and "SSAD from vertex 0" in second
    assert sorted(os.listdir(tmp_path)) == ["blob.obj", "demo"]
    assert sorted(os.listdir(out)) == ["evaluation.json", "model.ngf", "model.train", "ssad_vertex0.npy"]


def test_compile_note_follows_the_kernel_cache(tmp_path, monkeypatch):
    """The ssad/msad timing line says 'includes kernel compilation' only when a module was built into the cache."""
    import warp as wp

    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(tmp_path))
    built = []

    def compiling():  # a first call that builds a module: a new folder in the kernel cache
        if not built:
            (tmp_path / "module_abc").mkdir()
            built.append(1)
        return 1

    assert cli._timed_twice(compiling)[3] is True
    assert cli._timed_twice(compiling)[3] is False  # now cached
