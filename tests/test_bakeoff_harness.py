"""benchmarks/bakeoff.py's scheduling: rows side by side on several GPUs, each process pinned to one GPU with its
share of the CPU cores, rows kept in their order; the landmarks design sized to the mesh."""
import importlib
import json
import sys
import types
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def bakeoff(monkeypatch):
    monkeypatch.setenv("NEUROGF_BAKEOFF_DESIGNS", "1")  # the module sets it; restored after the test
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    return importlib.import_module("bakeoff")


def test_the_landmarks_design_is_sized_to_the_mesh(bakeoff):
    assert bakeoff.row_settings("spot", "landmarks", 2930)["landmarks"] == 128
    assert bakeoff.row_settings("igea", "landmarks", 134345)["landmarks"] == 256
    assert bakeoff.row_settings("spot", "landmarks128", 134345)["landmarks"] == 128  # a fixed K stays
    assert bakeoff.row_settings("joined", "default", 100)["allow_vertex_joins"] is True
    assert bakeoff.row_settings("spot", "landmarks_bracket256", 2930) == {"compile": False, "landmarks": 256,
                                                                          "landmark_bracket": True}


def test_a_landmark_design_counts_its_table_in_the_model_memory(bakeoff):
    mp = importlib.import_module("make_performance")
    plain = {"params": 259936, "model_mb": 0.99, "settings": {"compile": False}}
    assert mp._memory(plain) == "0.99 MB"
    lm = {"params": 276448, "model_mb": 1.05, "table_mb": 34.0, "settings": {"landmarks": 256}}
    assert mp._memory(lm) == "35.0 MB"


def test_errors_by_distance_bin_against_a_direct_count(bakeoff):
    """by_distance: each pair in the bin of its exact distance in mean edges; MRE, max and error shares of the
    bins as counted directly; the source itself and unreached pairs are left out."""
    import numpy as np

    rng = np.random.default_rng(3)
    gt = rng.uniform(0.0, 30.0, (4, 500))
    gt[:, 0], gt[0, 1] = 0.0, np.inf
    pred = gt * (1 + rng.normal(0, 0.01, gt.shape))
    bins = bakeoff.by_distance(pred, gt, edge=1.2)
    ok = np.isfinite(gt) & (gt > 0)
    rel, hops = np.abs(pred - gt)[ok] / gt[ok], gt[ok] / 1.2
    assert sum(b["pairs"] for b in bins) == ok.sum() == 4 * 499 - 1
    for b in bins:
        lo, hi = b["edges"][0], b["edges"][1] or np.inf
        r = rel[(hops >= lo) & (hops < hi)]
        assert b["pairs"] == r.size and b["mre"] == pytest.approx(r.mean()) and b["max"] == pytest.approx(r.max())
    assert sum(b["error_share"] for b in bins) == pytest.approx(1.0)
    far = bakeoff.by_distance(pred, gt, edge=100.0)  # every pair within 2 edges: the other bins empty
    assert far[0]["pairs"] == ok.sum() and all(b == {"edges": b["edges"], "pairs": 0} for b in far[1:])


def test_rows_side_by_side_each_on_one_gpu(bakeoff, monkeypatch, tmp_path):
    seen = []

    def fake_run(cmd, capture_output, text, env):
        spec = cmd[cmd.index("--row") + 1]
        out = Path(cmd[cmd.index("--out") + 1])
        seen.append((spec, env["CUDA_VISIBLE_DEVICES"], env["OMP_NUM_THREADS"], cmd[cmd.index("--work") + 1]))
        name, budget, variant, k = spec.split(":")
        (out / "row.json").write_text(json.dumps({"mesh": name, "budget_s": float(budget), "variant": variant,
                                                  "repeat": int(k), "mre": 0.01, "p99": 0.05, "max": 0.1}))
        return types.SimpleNamespace(returncode=0, stdout="", stderr="")

    monkeypatch.setattr("subprocess.run", fake_run)
    monkeypatch.setattr("os.cpu_count", lambda: 64)
    a = types.SimpleNamespace(device="cuda:0", shared=str(tmp_path), unseen=None, check_engine=True, gpus=4, share=1)
    specs = [f"spot:{b}:{v}:0" for b in (20, 60) for v in ("default", "landmarks")]
    rows = [bakeoff._in_fresh_process(a, s, tmp_path, g) for g, s in enumerate(specs)]
    assert [f"{r['mesh']}:{r['budget_s']:g}:{r['variant']}:{r['repeat']}" for r in rows] == specs
    assert [s[1] for s in seen] == ["0", "1", "2", "3"] and {s[2] for s in seen} == {"16"}
    assert len({s[3] for s in seen}) == 4  # each GPU's runs in a folder of its own
    # two rows at once on each of two GPUs: slots 0..3 on GPUs 0, 1, 0, 1, a quarter of the cores and a folder each
    seen.clear()
    a.gpus, a.share = 2, 2
    for slot, s in enumerate(specs):
        bakeoff._in_fresh_process(a, s, tmp_path, slot)
    assert [s[1] for s in seen] == ["0", "1", "0", "1"] and {s[2] for s in seen} == {"16"}
    assert len({s[3] for s in seen}) == 4


def test_same_process_and_several_gpus_do_not_mix(bakeoff, capsys):
    with pytest.raises(SystemExit):
        bakeoff.main(["--gpus", "2", "--same-process", "--device", "cpu"])
    assert "--gpus" in capsys.readouterr().err


def test_main_keeps_every_row_of_a_side_by_side_run(bakeoff, monkeypatch, tmp_path):
    gpus = []

    def fake_run(cmd, capture_output, text, env):
        spec = cmd[cmd.index("--row") + 1]
        gpus.append(env["CUDA_VISIBLE_DEVICES"])
        name, budget, variant, k = spec.split(":")
        Path(cmd[cmd.index("--out") + 1], "row.json").write_text(json.dumps(
            {"mesh": name, "budget_s": float(budget), "variant": variant, "repeat": int(k), "call_s": 1.0,
             "mre": 0.01 if variant == "default" else 0.005, "p99": 0.05, "max": 0.1, "steps": {},
             "ms_per_step": {}, "peak_gpu_mb": 0.0, "params": 1, "sources": {}}))
        return types.SimpleNamespace(returncode=0, stdout="", stderr="")

    monkeypatch.setattr("subprocess.run", fake_run)
    out = tmp_path / "out"
    assert bakeoff.main(["--device", "cpu", "--gpus", "2", "--meshes", "spot", "cow", "--budgets", "20",
                         "--variants", "default", "landmarks", "--repeat", "--warmup", "0", "--out", str(out),
                         "--work", str(tmp_path / "work")]) == 0
    doc = json.loads((out / "bakeoff.json").read_text())
    rows = doc["runs"][0]["rows"]
    assert [(r["mesh"], r["variant"]) for r in rows] == [("spot", "default"), ("spot", "landmarks"),
                                                          ("cow", "default"), ("cow", "landmarks")]
    assert sorted(set(gpus)) == ["0", "1"] and doc["runs"][0]["meta"]["gpus_side_by_side"] == 2
