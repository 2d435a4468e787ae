"""examples/geodesic_agents.py, short form: agents walking down the predicted geodesic field reach the target."""
import importlib.util
from pathlib import Path

import numpy as np
import pytest

import neurogf_warp as ngf
from neurogf_warp.mesh.surface import snap_to_mesh
from tests.conftest import shared_path

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "geodesic_agents.py"
DEV = "cpu"


def load_example():
    spec = importlib.util.spec_from_file_location("geodesic_agents", EXAMPLE)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.slow
def test_agents_reach_the_target_along_geodesics():
    """Released fandisk model; the target is a source of the exact reference, so each agent's walk can be
    compared with the exact geodesic distance from its start."""
    ex = load_example()
    model = ngf.load(shared_path("checkpoints", "official", "NeuroGF_Pretrainer__fandisk_final.pth"),
                     mesh=shared_path("meshes", "fandisk.obj"))
    mesh = model.mesh
    ref = np.load(shared_path("reference", "exact", "fandisk.npz"))
    assert np.array_equal(ref["orig_index"], ref["file_index"])  # fandisk: one vertex numbering, every vertex used
    seed = int(np.random.SeedSequence().entropy % 2**31)
    rng = np.random.default_rng(seed)
    k = int(rng.integers(len(ref["sources"])))
    target = int(ref["orig_index"][ref["sources"][k]])
    rows = rng.choice(len(ref["orig_index"]), 12, replace=False)
    starts = mesh.internal_vertices[mesh.vertex(ref["orig_index"][rows])]
    exact = ref["dist"][k][rows].astype(np.float64)
    radius = float(np.linalg.norm(mesh.internal_vertices - mesh.internal_vertices.mean(0), axis=1).max())
    speed = 0.025 * radius  # the example's default
    steps = int(np.ceil(exact.max() / speed * 1.3)) + 5
    xs, ds = ex.simulate(model, target, starts, steps, speed, DEV)
    msg = f"seed {seed}, target {target}"
    assert xs.shape == (steps + 1, 12, 3) and ds.shape == (steps + 1, 12)
    # every agent arrives: predicted distance within half a step, and it really is at the target vertex
    assert np.all(ds[-1] <= 0.5 * speed), msg
    tv = mesh.internal_vertices[mesh.vertex([target])][0]
    assert np.linalg.norm(xs[-1] - tv, axis=1).max() <= speed, msg
    # the predicted distance falls monotonically, up to 3/4 of a step: where the geodesic runs along one of the
    # fandisk's sharp creases an agent zigzags across it (both bounds hold with room over 300 random draws of
    # this case)
    assert np.diff(ds, axis=0).max() <= 0.75 * speed, msg
    # the agents stay on the surface (Newton steps on the network's SDF; 1% of the radius)
    p, _, _ = snap_to_mesh(mesh, xs.reshape(-1, 3), device=DEV)
    assert np.linalg.norm(p - xs.reshape(-1, 3), axis=1).max() <= 0.01 * radius, msg
    # they walk (nearly) geodesics: the walked length (plus the last gap) matches the exact geodesic distance
    # from the start within 10% and one step (chords across creases are shorter than the surface, zigzags along
    # them longer)
    walked = np.linalg.norm(np.diff(xs, axis=0), axis=2).sum(0) + np.linalg.norm(xs[-1] - tv, axis=1)
    assert np.all(np.abs(walked - exact) <= 0.10 * exact + speed), f"{msg}: {walked / exact}"


@pytest.mark.slow
def test_example_command_writes_frames_and_gif(tmp_path):
    from PIL import Image

    ex = load_example()
    assert ex.main(["--model", str(shared_path("checkpoints", "official", "NeuroGF_Pretrainer__fandisk_final.pth")),
                    "--mesh", str(shared_path("meshes", "fandisk.obj")), "--agents", "4", "--steps", "6",
                    "--frames", "2", "--size", "40", "--out", str(tmp_path), "--device", DEV]) == 0
    assert sorted(f.name for f in tmp_path.iterdir()) == ["agents.gif", "frame_000.png", "frame_001.png"]
    gif = Image.open(tmp_path / "agents.gif")
    assert gif.size == (40, 40) and gif.n_frames == 2


@pytest.mark.slow
def test_example_reports_agents_that_do_not_arrive(tmp_path, capsys):
    """Two steps are too few to arrive: the summary names the agents that did not, and --require-arrival turns
    that into exit status 1 (the example's stated guarantee: arrival is reported, never assumed)."""
    ex = load_example()
    argv = ["--model", str(shared_path("checkpoints", "official", "NeuroGF_Pretrainer__fandisk_final.pth")),
            "--mesh", str(shared_path("meshes", "fandisk.obj")), "--agents", "3", "--steps", "2", "--frames", "1",
            "--size", "24", "--out", str(tmp_path), "--device", DEV, "--seed", "3"]
    assert ex.main(argv) == 0
    out = capsys.readouterr().out
    assert "0 arrived" in out and "3 did not (agents 0, 1, 2" in out, out
    assert ex.main(argv + ["--require-arrival"]) == 1


def test_readme_pictures_writes_only_where_told(capsys):
    """The README-pictures script needs --out: it has no default folder inside the checkout to write into."""
    spec = importlib.util.spec_from_file_location("readme_pictures", EXAMPLE.parent / "readme_pictures.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    import pytest

    with pytest.raises(SystemExit) as e:
        mod.main([])
    assert e.value.code == 2 and "--out" in capsys.readouterr().err
