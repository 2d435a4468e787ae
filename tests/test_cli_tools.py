"""The geodesic-tool commands (sample, voronoi, isolines, reconstruct) write what the API returns."""
import numpy as np
import pytest

from neurogf_warp.cli import main as cli

pytestmark = pytest.mark.slow  # uses the trained fixture (one training per test run)


def run(argv, capsys):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_sample_and_voronoi(trained, tmp_path, capsys):
    import neurogf_warp as ngf

    model, path = trained
    code, out, _ = run(["sample", path, "-k", 6, "--start", 3, "-q", "--device", "cpu"], capsys)
    want = ngf.farthest_point_sampling(model, 6, start=3, device="cpu")
    assert code == 0 and [int(x) for x in out.split()] == want.tolist()
    code, _, _ = run(["voronoi", path, "--seeds", *want[:4], "-o", tmp_path / "l.npy", "-q", "--device", "cpu"],
                     capsys)
    assert code == 0
    np.testing.assert_array_equal(np.load(tmp_path / "l.npy"), ngf.voronoi(model, want[:4], device="cpu"))
    code, _, _ = run(["voronoi", path, "--fps", 3, "-o", tmp_path / "l.csv", "-q", "--device", "cpu"], capsys)
    rows = np.loadtxt(tmp_path / "l.csv", delimiter=",", skiprows=1)
    assert code == 0 and rows.shape == (model.mesh.n_input, 2) and set(rows[:, 1]) <= {-1, 0, 1, 2}
    code, _, err = run(["voronoi", path, "--seeds", 1, 1, "-q"], capsys)
    assert code == 2 and "repeats a vertex" in err


def test_isolines_and_reconstruct(trained, tmp_path, capsys):
    model, path = trained
    code, _, _ = run(["isolines", path, "--source", 0, "--levels", 3, "-o", tmp_path / "iso.obj", "-q",
                      "--device", "cpu"], capsys)
    text = (tmp_path / "iso.obj").read_text().split("\n")
    assert code == 0 and any(t.startswith("l ") for t in text) and any(t.startswith("v ") for t in text)
    code, _, _ = run(["isolines", path, "--values", 0.5, "-o", tmp_path / "iso.csv", "-q", "--device", "cpu"],
                     capsys)
    a = np.loadtxt(tmp_path / "iso.csv", delimiter=",", skiprows=1).reshape(-1, 6)
    assert code == 0 and len(a) > 3 and set(a[:, 0]) == {0}
    code, _, err = run(["reconstruct", path, "--resolution", 24, "-o", tmp_path / "r.ply", "--device", "cpu"],
                       capsys)
    import trimesh

    r = trimesh.load(tmp_path / "r.ply", process=False)
    assert code == 0 and len(r.faces) > 100 and "Chamfer-L1" in err
    code, _, err = run(["reconstruct", path, "--resolution", 24, "-o", tmp_path / "r.xyz"], capsys)
    assert code == 2 and ".obj" in err
