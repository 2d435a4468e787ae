"""benchmarks/generalizable_collection.py and generalizable_eval.py functions: evaluation order, tables with
partial columns, merging two calls' rows, pairs that depend on the shape name only."""
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import generalizable_collection as gc
import generalizable_eval as ge


def test_eval_order_round_robin_over_families():
    names = [f"shape_{i:05d}_{f}.obj" for i, f in [(9, "a"), (10, "b"), (19, "a"), (20, "b"), (29, "a"), (11, "c")]]
    got = [p.name for p in gc.eval_order([Path(n) for n in names])]
    assert got == ["shape_00009_a.obj", "shape_00010_b.obj", "shape_00011_c.obj", "shape_00019_a.obj",
                   "shape_00020_b.obj", "shape_00029_a.obj"]


def test_pairs_depend_on_the_name_only():
    a = ge.shape_rng("shape_00054_blob.obj").choice(1000, 8, replace=False)
    ge.shape_rng("other.obj").random(5)
    b = ge.shape_rng("shape_00054_blob.obj").choice(1000, 8, replace=False)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, ge.shape_rng("shape_00055_torus.obj").choice(1000, 8, replace=False))


def test_table_and_merge(tmp_path, capsys):
    run = {"device": "cuda:0", "rows": [
        {"group": "unseen:blob", "shape": "s1.obj", "trained": 0.02, "released": 0.05, "heat": 0.012},
        {"group": "unseen:torus", "shape": "s2.obj", "trained": 0.04, "released": 0.07, "heat": 0.02},
        {"group": "shared", "shape": "spot.obj", "trained": 0.06, "released": 0.048, "heat": 0.018}]}
    pm = {"rows": [{"group": "unseen:blob", "shape": "s1.obj", "released": 0.05, "heat": 0.012, "per_mesh": 0.01},
                   {"group": "shared", "shape": "spot.obj", "released": 0.048, "heat": 0.018, "per_mesh": 0.009}]}
    (tmp_path / "a.json").write_text(json.dumps(run))
    (tmp_path / "b.json").write_text(json.dumps(pm))
    rc = gc.main(["merge", str(tmp_path / "a.json"), str(tmp_path / "b.json"), "-o", str(tmp_path / "m")])
    assert rc == 0
    merged = json.loads((tmp_path / "m.json").read_text())
    assert merged["summary"]["all unseen"]["trained"] == 0.03
    assert merged["summary"]["all unseen"]["per_mesh"] == 0.01  # over the one shape that has it
    text = (tmp_path / "m.txt").read_text()
    assert "1.00% (1)" in text and "spot.obj" in text
    # different heat values for one shape: not the same pairs -> said, exit 1
    pm["rows"][0]["heat"] = 0.013
    (tmp_path / "b.json").write_text(json.dumps(pm))
    assert gc.main(["merge", str(tmp_path / "a.json"), str(tmp_path / "b.json"), "-o", str(tmp_path / "m")]) == 1
    assert "not the same pairs" in capsys.readouterr().out


def test_pack_shared_archive_and_unpack(tmp_path, monkeypatch):
    src = tmp_path / "shared"
    for rel in ["meshes/a.obj", "meshes/b.ply", "meshes/manifest.json", "reference/exact/stanford-bunny.npz",
                "reference/exact/fandisk.npz", "reference/exact/spot.npz", "reference/exact/cow.npz",
                "checkpoints/official/GenNeuroGF.pth"]:
        (src / rel).parent.mkdir(parents=True, exist_ok=True)
        (src / rel).write_text(rel)
    assert gc.main(["pack-shared", str(src), str(tmp_path / "p.tar.xz")]) == 0
    monkeypatch.setenv("NEUROGF_SHARED", str(tmp_path / "p.tar.xz"))
    got = Path(gc.unpack_shared(None, tmp_path / "work"))
    assert sorted(str(p.relative_to(got)) for p in got.rglob("*") if p.is_file()) == sorted(
        ["meshes/a.obj", "meshes/b.ply", "reference/exact/stanford-bunny.npz", "reference/exact/fandisk.npz",
         "reference/exact/spot.npz", "checkpoints/official/GenNeuroGF.pth"])
    assert (got / "meshes" / "a.obj").read_text() == "meshes/a.obj"
    assert gc.find_shared(str(got)) == got.resolve()
    assert gc.unpack_shared(str(src), tmp_path / "work") == str(src)  # a folder is used as it is
