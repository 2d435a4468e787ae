"""The command line a new user meets: results only where asked (stdout without -o), refusing another mesh unless
told, paths on the surface by default, messages in the command line's terms, exit codes that tell bad input (2)
from failures and bugs (1), a closed stdout or stderr handled, the generalizable commands' messages, and quiet
library calls."""
import errno
import os
import subprocess
import sys

import numpy as np
import pytest

from neurogf_warp.cli import main as cli
from tests.conftest import shared_path

DEV = "cpu"


def run(argv, capsys):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def fandisk():
    return (shared_path("checkpoints", "official", "NeuroGF_Pretrainer__fandisk_final.pth"),
            shared_path("meshes", "fandisk.obj"))


# --- nothing written that nobody named -----------------------------------------------------------------------------

def test_queries_without_output_print_and_write_nothing(trained, tmp_path, capsys, monkeypatch):
    import neurogf_warp as ngf

    model, path = trained
    monkeypatch.chdir(tmp_path)
    code, out, err = run(["ssad", path, "--source", 5, "--device", DEV], capsys)
    assert code == 0, err
    np.testing.assert_array_equal(np.array(out.split(), dtype=np.float32), ngf.ssad(model, 5, device=DEV))
    assert "printed" in err
    code, out, _ = run(["msad", path, "--sources", 1, 7, "-q"], capsys)
    np.testing.assert_array_equal(np.array(out.split(), dtype=np.float32), ngf.msad(model, [1, 7], device=DEV))
    v = model.mesh.vertices
    code, out, err = run(["path", path, "--p", *v[0], "--q", *v[10], "--m", 8], capsys)
    assert code == 0, err
    rows = np.loadtxt(out.splitlines(), delimiter=",", skiprows=1)
    assert rows.shape == (8, 5) and np.array_equal(rows[:, 1], np.arange(8))
    assert "1 path of 8 points printed" in err  # one path, not "1 paths"
    assert os.listdir(tmp_path) == []


def test_render_needs_an_output_file(trained, capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["render", str(trained[1])])
    assert e.value.code == 2 and "-o/--output" in capsys.readouterr().err


# --- paths on the surface --------------------------------------------------------------------------------------------

def test_path_project_matches_the_api_and_defaults_to_the_mesh(trained, tmp_path, capsys):
    import neurogf_warp as ngf

    model, path = trained
    v = model.mesh.vertices
    rng = np.random.default_rng(1)
    p, q = v[rng.choice(len(v), 5)], v[rng.choice(len(v), 5)]
    np.save(tmp_path / "p.npy", p)
    np.save(tmp_path / "q.npy", q)
    base = ["path", path, "--p", tmp_path / "p.npy", "--q", tmp_path / "q.npy", "--m", 16, "--device", DEV]
    for flag, api in (("none", None), ("sdf", "sdf"), ("mesh", "mesh"), (None, "mesh")):
        out = tmp_path / f"{flag}.npy"
        code, _, err = run(base + (["--project", flag] if flag else []) + ["-o", out], capsys)
        assert code == 0, err
        np.testing.assert_array_equal(np.load(out), ngf.path(model, p, q, m=16, project=api, device=DEV), err_msg=flag)
        if api == "mesh":
            assert "every point on the mesh (the network's points were up to" in err
        if api is None:
            assert "not projected onto the surface" in err
    from neurogf_warp.mesh.surface import snap_to_mesh

    pts = np.load(tmp_path / "None.npy").reshape(-1, 3)
    on = np.asarray(snap_to_mesh(model, pts, device=DEV)[0])
    assert np.abs(on - pts).max() < 1e-5  # the default output lies on the mesh


def test_path_and_eval_help_say_what_refinement_costs(capsys):
    for cmd in ("path", "render", "eval"):
        with pytest.raises(SystemExit):
            cli.main([cmd, "-h"])
        text = " ".join(capsys.readouterr().out.split())
        assert "slower on a CPU" in text and "fast on a GPU" in text and "per pair" not in text, cmd


# --- another mesh -----------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("command", [["ssad", "--source", "3"], ["eval", "--no-paths", "--no-sdf", "--sources", "1"],
                                     ["info"]])
def test_released_checkpoint_with_another_mesh_is_refused_unless_allowed(command, tmp_path, capsys):
    ck, _ = fandisk()
    argv = [command[0], ck, "--mesh", shared_path("meshes", "spot.obj"), *command[1:], "--device", DEV]
    code, out, err = run(argv, capsys)
    assert code == 2 and "does not lie on this checkpoint's surface" in err and "--allow-mesh-mismatch" in err, err
    assert out == "" and len(err.strip().splitlines()) == 1
    if command[0] == "ssad":
        code, out, err = run(argv + ["--allow-mesh-mismatch", "-o", tmp_path / "d.npy"], capsys)
        assert code == 0 and (tmp_path / "d.npy").exists()
        warning = [ln for ln in err.splitlines() if "warning" in ln]
        assert len(warning) == 1 and warning[0].startswith("neurogf-warp ssad: warning: ") and "warn(" not in err
        code, out, err = run(argv + ["--allow-mesh-mismatch", "-q", "-o", tmp_path / "d.npy"], capsys)
        assert code == 0 and err == ""


def test_ngf_with_another_mesh_names_the_flag_not_the_python_argument(tmp_path, capsys):
    import neurogf_warp as ngf

    ck, mesh = fandisk()
    path = tmp_path / "f.ngf"
    ngf.save(ngf.load(ck, mesh=mesh), path)
    argv = ["ssad", path, "--mesh", shared_path("meshes", "spot.obj"), "--source", 1, "--device", DEV]
    code, _, err = run(argv, capsys)
    assert code == 2 and "--allow-mesh-mismatch" in err and "check_mesh" not in err, err
    code, out, err = run(argv + ["--allow-mesh-mismatch", "-q"], capsys)
    assert code == 0 and len(out.split()) == ngf.load_mesh(shared_path("meshes", "spot.obj")).n_input


# --- exit codes and messages ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("error, code, words", [
    (lambda: __import__("neurogf_warp").common.checks.InputError("bad thing"), 2, "error: bad thing"),
    (lambda: ValueError("a stage's bad argument"), 2, "error: a stage's bad argument"),
    (lambda: FileNotFoundError("mesh file not found: x.obj"), 2, "error: mesh file not found"),
    (lambda: TypeError("unsupported operand"), 1, "internal error: TypeError: unsupported operand"),
    (lambda: IndexError("index 9 is out of bounds"), 1, "This is a bug in neurogf-warp"),
    (lambda: KeyError("w0"), 1, "with --verbose"),
    (lambda: OSError(errno.EIO, "Input/output error"), 1, "failed: [Errno 5] Input/output error"),
])
def test_exit_codes_tell_bad_input_from_failures_and_bugs(error, code, words, trained, capsys, monkeypatch):
    import neurogf_warp
    import neurogf_warp.common.checks  # noqa: F401 - for the InputError lambda

    def boom(args):
        raise error()

    monkeypatch.setattr(cli, "_cmd_info", boom)
    monkeypatch.setenv("NEUROGF_DEBUG", "")
    got, _, err = run(["info", trained[1]], capsys)
    assert got == code and words in err and "Traceback" not in err, err
    if code == 1 and "failed" not in words:
        assert "internal error" in err and "report it" in err
        # what to report: the command line, the versions (quoted), the traceback; no address made up
        assert "command line" in err and f"neurogf-warp {neurogf_warp.__version__}" in err and "Python 3." in err
        assert "traceback" in err and "tracker" not in err and "http" not in err


def test_full_disk_during_output_says_so_and_keeps_the_old_file(trained, tmp_path, capsys, monkeypatch):
    out = tmp_path / "d.npy"
    out.write_bytes(b"old")
    real = os.fsync

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    code, _, err = run(["ssad", trained[1], "--source", 2, "-o", out, "-q"], capsys)
    monkeypatch.setattr(os, "fsync", real)
    assert code == 1 and "no space left on the device" in err and "requested" not in err, err
    assert out.read_bytes() == b"old" and sorted(os.listdir(tmp_path)) == ["d.npy"]


def test_train_messages_name_flags(ellipsoid, tmp_path, capsys):
    import trimesh

    mesh = tmp_path / "e.obj"
    trimesh.Trimesh(ellipsoid.vertices, ellipsoid.faces, process=False).export(mesh)
    (tmp_path / "m.ngf").write_bytes(b"someone else's file")
    code, _, err = run(["train", mesh, "-o", tmp_path / "m.ngf", "--device", DEV], capsys)
    assert code == 2 and "--force" in err and "force=True" not in err, err


@pytest.mark.parametrize("value", ["-1", "0", "inf", "nan", "1e400", "abc"])
@pytest.mark.parametrize("command", ["demo", "train"])
def test_budgets_are_checked_before_any_work(command, value, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    argv = ["demo", "-o", tmp_path / "d"] if command == "demo" else ["train", "x.obj", "-o", tmp_path / "m.ngf"]
    with pytest.raises(SystemExit) as e:
        cli.main([str(a) for a in argv] + [f"--budget-seconds={value}"])
    assert e.value.code == 2 and "--budget-seconds" in capsys.readouterr().err
    assert os.listdir(tmp_path) == []


@pytest.mark.slow
def test_a_closed_stdout_ends_quietly(trained, tmp_path):
    """`neurogf-warp path ... | head -2` (and `info --json | head`): exit 0, nothing on stderr."""
    v = trained[0].mesh.vertices
    np.save(tmp_path / "p.npy", np.repeat(v[:1], 10, axis=0))  # 4,000 CSV rows: more than a pipe holds
    np.save(tmp_path / "q.npy", v[10:20])
    env = dict(os.environ, NEUROGF_DEBUG="")
    for argv in (["path", str(trained[1]), "--p", str(tmp_path / "p.npy"), "--q", str(tmp_path / "q.npy"), "--m", "400",
                  "--project", "none", "-q"], ["info", str(trained[1]), "--json"]):
        proc = subprocess.Popen([sys.executable, "-m", "neurogf_warp.cli.main", *argv], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, env=env)
        proc.stdout.readline()
        proc.stdout.close()  # what head does after its lines
        err = proc.stderr.read().decode()
        assert proc.wait(timeout=300) == 0 and err == "", (argv[0], err)


def _closing(fd):
    return lambda: os.close(fd)


@pytest.mark.parametrize("closed", [1, 2])
def test_a_command_started_with_stdout_or_stderr_closed(closed, trained, tmp_path):
    """`neurogf-warp info M >&-`: a failure said on stderr (exit 1), no "internal error"; `2>&-`: the results as
    usual on stdout and the exit code of the command; `ssad -o FILE >&-` works, and the file gets no stray text."""
    env = dict(os.environ, NEUROGF_DEBUG="")
    cmd = [sys.executable, "-m", "neurogf_warp.cli.main"]
    res = subprocess.run([*cmd, "info", str(trained[1])], capture_output=True, text=True, env=env, timeout=300,
                         preexec_fn=_closing(closed))
    if closed == 1:
        assert res.returncode == 1 and "standard output is closed" in res.stderr, res.stderr
        assert "internal error" not in res.stderr and "Traceback" not in res.stderr
    else:
        assert res.returncode == 0 and "NeuroGF, D=" in res.stdout
    res = subprocess.run([*cmd, "ssad", str(trained[1]), "--source", "3", "-o", str(tmp_path / "d.csv")],
                         capture_output=True, text=True, env=env, timeout=300, preexec_fn=_closing(closed))
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "d.csv").read_text().startswith("vertex,distance\n0,")
    res = subprocess.run([*cmd, "info", str(tmp_path / "missing.ngf")], capture_output=True, text=True, env=env,
                         timeout=300, preexec_fn=_closing(closed))
    assert res.returncode == 2 and "internal error" not in res.stdout + res.stderr


def test_source_messages_say_what_is_wrong(trained):
    import neurogf_warp as ngf

    model = trained[0]
    for bad, words in ((2 ** 70, r"integer below 2\*\*63"), (None, "got .None."), ([], "is empty")):
        with pytest.raises(ValueError, match=words):
            ngf.ssad(model, bad, device=DEV)


# --- quiet library ---------------------------------------------------------------------------------------------------

QUIET = """
import neurogf_warp as ngf
m = ngf.load_mesh(({v!r}, {f!r}))
d = ngf.geodesic_distances(m, [0], device="cpu")
print("ok", d.shape)
"""


@pytest.mark.slow
@pytest.mark.parametrize("verbose", ["", "1"])
def test_library_calls_are_quiet_unless_asked(verbose, tmp_path):
    """No Warp banner, no "Module ... load" lines, no CUDA-driver warning; NEUROGF_WARP_VERBOSE=1 brings them back."""
    v = [[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]
    f = [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]
    env = dict(os.environ, NEUROGF_WARP_VERBOSE=verbose, WARP_CACHE_PATH=os.environ.get("WARP_CACHE_PATH", ""))
    if not env["WARP_CACHE_PATH"]:
        env.pop("WARP_CACHE_PATH")
    res = subprocess.run([sys.executable, "-c", QUIET.format(v=v, f=f)], capture_output=True, text=True, env=env,
                         cwd=tmp_path, timeout=300)
    assert res.returncode == 0 and res.stdout.endswith("ok (1, 4)\n"), res.stderr
    if verbose:  # Warp prints its banner and module lines to stdout
        assert "Warp 1." in res.stdout and "Module " in res.stdout
    else:
        assert res.stdout == "ok (1, 4)\n" and res.stderr == "", res.stdout + res.stderr


@pytest.mark.parametrize("quiet", [False, True])
def test_warnings_are_one_line_and_silent_with_quiet(quiet, capsys):
    """A warning (a failing ground-truth worker's, say, raised in a feeding thread) is one line in the command's
    name, without Python source, and -q silences it."""
    import argparse
    import threading
    import warnings

    args = argparse.Namespace(quiet=quiet, command="data")
    with cli._one_line_warnings(args):
        t = threading.Thread(target=lambda: warnings.warn("a ground-truth worker process failed: ImportError: x",
                                                          RuntimeWarning))
        t.start()
        t.join()
    err = capsys.readouterr().err
    if quiet:
        assert err == ""
    else:
        assert err == "neurogf-warp data: warning: a ground-truth worker process failed: ImportError: x\n"


# --- gen-shapes ---------------------------------------------------------------------------------------------------

def test_gen_shapes_refuses_no_shapes_and_a_file(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["gen-shapes", str(tmp_path / "coll"), "-n", "0"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "-n" in err and "at least 1" in err and "Traceback" not in err
    assert not (tmp_path / "coll").exists()
    (tmp_path / "f").write_text("x")
    code, _, err = run(["gen-shapes", tmp_path / "f", "-n", "2"], capsys)
    assert code == 2 and "is a file" in err and (tmp_path / "f").read_text() == "x"


def test_gen_shapes_says_what_it_made_and_why_there_is_no_test_split(tmp_path, capsys):
    from neurogf_warp.generalizable.shapes import FAMILIES

    code, out, err = run(["gen-shapes", tmp_path / "a", "-n", 12], capsys)
    assert code == 0 and "12 shapes" in err and "12 in train/, 0 in test/" in err, err
    first = 9 * len(FAMILIES)  # the 10th instance of the first family
    assert "no test split" in err and f"first is shape {first}" in err and f"-n {first + 1}" in err
    assert len(os.listdir(tmp_path / "a" / "train")) == 12 and not (tmp_path / "a" / "test").exists()
    code, out, err = run(["gen-shapes", tmp_path / "b", "-n", 12, "--test-every", 2], capsys)
    n_test = len(os.listdir(tmp_path / "b" / "test"))
    assert code == 0 and n_test > 0 and f"{12 - n_test} in train/, {n_test} in test/" in err, err
    assert "no test split" not in err


# --- heat field ---------------------------------------------------------------------------------------------------

def test_heat_field_leaves_parts_without_a_source_unreached():
    """`render --heat`: the heat method's numbers on a part that no source reaches are not distances; they are
    inf, drawn in the no-value colour as the model's and the solver's fields are."""
    pytest.importorskip("potpourri3d")
    import trimesh

    import neurogf_warp as ngf
    from neurogf_warp.evaluation.fields import heat_field
    from neurogf_warp.pictures.render import colorize

    a = trimesh.creation.icosphere(subdivisions=2)
    b = trimesh.creation.icosphere(subdivisions=2)
    b.apply_translation([3.0, 0, 0])
    mesh = ngf.load_mesh(trimesh.util.concatenate([a, b]))
    n = len(a.vertices)
    d = heat_field(mesh, [0])
    assert np.isfinite(d[:n]).all() and d[0] == pytest.approx(0, abs=1e-6) and d[1:n].max() > 1.0
    assert np.isinf(d[n:]).all()
    grey = colorize(np.array([np.nan]))[0]
    assert (colorize(d)[n:] == grey).all()
    d2 = heat_field(mesh, [0, n + 5])  # a source on each part: every vertex reached
    assert np.isfinite(d2).all()
