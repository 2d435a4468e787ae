"""The maintained benchmarks run from a plain checkout, and docs/performance.md matches the kept results.

Each benchmark's ``--help`` runs in a subprocess started outside the checkout, with the package's install hidden
(the editable finder removed) and a decoy ``neurogf_warp`` first on PYTHONPATH: the script must still import
``neurogf_warp`` and ``neurogf_warp.kernels`` from this checkout.
"""
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"

# importing torch and compiling Warp kernel definitions at import make these two slow on a busy 2-core machine
HEAVY = {"queries", "kernel_api"}
SCRIPTS = ["released", "path_snap", "geodesics", "time_to_accuracy", "generalizable", "generalizable_collection",
           "generalizable_eval", "generalizable_scaling", "queries", "kernel_api", "geodesic_tools", "bakeoff",
           "ground_truth_setup", "multi_gpu", "unseen_meshes", "landmark_ssad", "between_vertices"]

PROBE = textwrap.dedent("""
    import json, runpy, sys
    # hide an install of the package: a plain checkout has none
    sys.meta_path[:] = [f for f in sys.meta_path if "editable" not in repr(f).lower()]
    script = sys.argv[1]
    sys.argv = [script, "--help"]
    sys.path.insert(0, str(__import__("pathlib").Path(script).parent))  # as `python script` does
    code = 0
    try:
        runpy.run_path(script, run_name="__main__")
    except SystemExit as e:
        code = e.code or 0
    import neurogf_warp, neurogf_warp.kernels
    from neurogf_warp.kernels.inference import mlp
    print("PROBE " + json.dumps({"code": code, "package": neurogf_warp.__file__,
                                 "kernels": neurogf_warp.kernels.__file__, "mlp": mlp.__file__}))
""")


def _decoy(tmp_path: Path) -> Path:
    """A neurogf_warp package that fails on import, placed first on PYTHONPATH."""
    pkg = tmp_path / "decoy" / "neurogf_warp"
    (pkg / "kernels").mkdir(parents=True)
    (pkg / "__init__.py").write_text("raise ImportError('the decoy copy was imported')\n")
    (pkg / "kernels" / "__init__.py").write_text("raise ImportError('the decoy kernels were imported')\n")
    return tmp_path / "decoy"


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.slow) if n in HEAVY else n for n in SCRIPTS])
def test_help_runs_from_a_plain_checkout_with_this_checkouts_package(name, tmp_path):
    env = dict(os.environ, PYTHONPATH=str(_decoy(tmp_path)))
    r = subprocess.run([sys.executable, "-c", PROBE, str(BENCH / f"{name}.py")], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "usage:" in r.stdout
    probe = json.loads(r.stdout.rsplit("PROBE ", 1)[1])
    assert probe["code"] == 0
    assert Path(probe["package"]).resolve() == ROOT / "neurogf_warp" / "__init__.py"
    assert Path(probe["kernels"]).resolve() == ROOT / "kernels" / "__init__.py"
    assert Path(probe["mlp"]).resolve() == ROOT / "kernels" / "inference" / "mlp.py"


@pytest.mark.slow
def test_landmark_ssad_runs_on_the_cpu(tmp_path):
    """The landmark SSAD benchmark's smoke test: a tiny mesh on the CPU emulation, every K checked against float64."""
    out = tmp_path / "landmark_ssad.json"
    r = subprocess.run([sys.executable, str(BENCH / "landmark_ssad.py"), "--device", "cpu", "--small", "--json",
                        str(out)], cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    res = json.loads(out.read_text())
    assert [row["K"] for row in res["rows"]] == [0, 16, 32] and all("kernel_ms" in row for row in res["rows"])
    assert res["provenance"]["command"].startswith("python benchmarks/landmark_ssad.py --device cpu --small")


def test_between_vertices_scores_a_model(tmp_path, ellipsoid):
    """The between-vertices benchmark on a random network of the ellipsoid: rows at vertices and at midpoints, every
    edge's midpoint counted."""
    import torch

    import neurogf_warp as ngf
    from neurogf_warp.model.network import NeuroGFNet

    torch.manual_seed(0)
    path = tmp_path / "m.ngf"
    ngf.save(ngf.Model(net=NeuroGFNet(64, euclid=True), mesh=ellipsoid, center=ellipsoid.center,
                       scale=ellipsoid.scale), path)
    out = tmp_path / "bv.json"
    r = subprocess.run([sys.executable, str(BENCH / "between_vertices.py"), str(path), "--sources", "2", "--json",
                        str(out)], cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    row = json.loads(out.read_text())["rows"][0]
    edges = 3 * len(ellipsoid.internal_faces) // 2  # a closed mesh: each edge in two faces
    assert row["midpoints"] == edges and row["at_midpoints"]["pairs"] == 2 * edges
    assert row["at_vertices"]["pairs"] == 2 * (len(ellipsoid.internal_vertices) - 1)


def test_every_maintained_benchmark_is_covered():
    """A new benchmark script joins SCRIPTS (its --help is then checked) or is one of the modules they share."""
    shared = {"_bootstrap", "common", "make_performance"}
    assert {p.stem for p in BENCH.glob("*.py")} - shared == set(SCRIPTS)


def test_performance_page_matches_the_kept_results():
    r = subprocess.run([sys.executable, str(BENCH / "make_performance.py"), "--check"], cwd=ROOT,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-2000:]


def test_check_fails_when_the_page_is_stale(tmp_path):
    page = tmp_path / "performance.md"
    page.write_text((ROOT / "docs" / "performance.md").read_text().replace("| fandisk |", "| fandisk? |", 1))
    r = subprocess.run([sys.executable, str(BENCH / "make_performance.py"), "--check", "-o", str(page)],
                       cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 1
    assert "fandisk?" in r.stdout


def test_every_kept_result_names_its_provenance():
    keys = {"command", "device", "device_name", "driver", "warp", "torch", "date_utc", "commit"}
    files = sorted((BENCH / "results").glob("*.json"))
    assert files
    for f in files:
        doc = json.loads(f.read_text())
        for run in doc.get("runs", [doc]):
            assert keys <= set(run["provenance"]), f"{f.name}: provenance lacks {keys - set(run['provenance'])}"
            assert run["provenance"]["date_utc"], f.name
