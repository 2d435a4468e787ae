"""A fixed-seed CPU training run, recorded before the training package was split and compared after.

    python benchmarks/experiments/fixed_seed_training.py --record results/fixed_seed_before.json
    python benchmarks/experiments/fixed_seed_training.py --compare results/fixed_seed_before.json

642-vertex ellipsoid, a small dataset (seed 0), D=64 with small batches, 2 x 100 joint steps and the other
stages by their ratios, one torch thread. Records the dataset arrays' checksums, every logged loss, the
validation MREs and a checksum of the final weights. The recording was made with the single-module train.py
(commit 5b0b88f, ``T.train(mesh, out, dataset=arrays, epochs=2, iters_per_epoch=100, seed=0, **TRAIN)``).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
import trimesh

DATA = dict(n_sources=64, n_global=256, n_local1=8, n_local2=32, n_path_sources=16, n_path_global=16,
            n_path_local=16, n_test=2, n_surface=30000)
TRAIN = dict(D=64, batch_sdf=2048, batch_g=4096, batch_l1=512, batch_l2=1024, batch_paths_g=128,
             batch_paths_l=128, batch_surf=16, batch_querier=2048, sdf_pool=20000, val_every=100, log_every=20)


def _sha(a) -> str:
    return hashlib.sha256(np.ascontiguousarray(np.asarray(a)).tobytes()).hexdigest()[:16]


def run() -> dict:
    torch.set_num_threads(1)
    tm = trimesh.creation.icosphere(subdivisions=3)
    tm.vertices *= np.array([1.0, 0.8, 0.6])
    mesh = (np.asarray(tm.vertices), np.asarray(tm.faces))
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "m.ngf"
        import neurogf_warp as ngf
        from neurogf_warp.training import preset

        ds = ngf.build_dataset(mesh, device="cpu", progress=False, seed=0, **DATA)
        arrays = ds.arrays()
        cfg = preset("default", **TRAIN, epochs=2, iters_per_epoch=100, seed=0)
        model = ngf.train(mesh, out, config=cfg, dataset=ds, device="cpu", progress=False)
        log = json.loads((Path(tmp) / "m.train" / "log.json").read_text())
    keys = ("vertices", "faces", "surface_points", "gd_global", "gd_local1", "gd_local2", "path_global",
            "path_local", "test_src", "test_dist")
    weights = np.concatenate([v.detach().double().cpu().numpy().ravel() for v in model.net.state_dict().values()])
    return {"dataset": {k: _sha(arrays[k]) for k in keys},
            "loss": [{k: v for k, v in r.items()} for r in log["history"]["loss"]],
            "val": log["history"]["val"], "weights_sha": _sha(weights.astype(np.float32)),
            "weights_sum": float(np.abs(weights).sum())}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--record", help="write the run's numbers to this JSON")
    g.add_argument("--compare", help="compare the run with this recorded JSON")
    a = p.parse_args(argv)
    res = run()
    if a.record:
        Path(a.record).write_text(json.dumps(res, indent=1))
        print(f"recorded {len(res['loss'])} loss rows, val {[round(v['mre'], 6) for v in res['val']]} -> {a.record}")
        return 0
    ref = json.loads(Path(a.compare).read_text())
    same_data = res["dataset"] == ref["dataset"]
    worst = 0.0
    for x, y in zip(res["loss"], ref["loss"]):
        assert (x["stage"], x["step"]) == (y["stage"], y["step"]), (x, y)
        for k, v in y.items():
            if isinstance(v, float):
                worst = max(worst, abs(x[k] - v) / max(abs(v), 1e-12))
    vals = [(x["mre"], y["mre"]) for x, y in zip(res["val"], ref["val"])]
    same = same_data and len(res["loss"]) == len(ref["loss"]) and worst == 0.0 and \
        all(a_ == b_ for a_, b_ in vals) and res["weights_sha"] == ref["weights_sha"]
    print(f"dataset identical: {same_data}; {len(res['loss'])} loss rows (recorded {len(ref['loss'])}), "
          f"largest relative loss difference {worst:.3g}; validation MRE now/recorded {vals}; "
          f"weights identical: {res['weights_sha'] == ref['weights_sha']}")
    print("BIT-IDENTICAL" if same else "DIFFERENT")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
