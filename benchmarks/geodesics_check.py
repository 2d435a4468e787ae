"""Solver accuracy on a device against the exact references, delta-stepping and plain Bellman-Ford side by side,
repeated (a GPU race shows as run-to-run change).

    python benchmarks/geodesics_check.py --device cuda:0
    python benchmarks/geodesics_check.py --device cpu --meshes fandisk,spot,cow --repeat 1
"""
from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import find_shared  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--meshes", default="fandisk,stanford-bunny")
    ap.add_argument("--repeat", type=int, default=2, help="runs per variant (a race shows as run-to-run change)")
    a = ap.parse_args(argv)
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    from neurogf_warp.ground_truth import geodesics as G
    from neurogf_warp.mesh.mesh import load_mesh

    out = []
    for name in a.meshes.split(","):
        ref = np.load(find_shared("reference", "exact", f"{name}.npz"))
        m = load_mesh((ref["positions"].astype(np.float64), _faces(name, ref)))
        src = ref["sources"]
        ex = ref["dist"].astype(np.float64)
        for delta, rep in itertools.product((G.DEFAULT_DELTA, 0.0), range(a.repeat)):
            t = time.perf_counter()
            s = G.GeodesicSolver(m, device=a.device, delta=delta, max_rows=len(src))
            d = s.solve(src).astype(np.float64) / m.scale
            dt = time.perf_counter() - t
            ok = np.isfinite(ex) & (ex > 0)
            rel = (d[ok] - ex[ok]) / ex[ok]
            row = dict(mesh=name, delta=delta, rep=rep, s=round(dt, 2), mre=float(np.abs(rel).mean()),
                       max_rel=float(rel.max()), min_rel=float(rel.min()), below_1e5=int((rel < -1e-5).sum()))
            out.append(row)
            print(json.dumps(row), flush=True)
    Path(os.environ.get("OUT", "."), "geodesics_check.json").write_text(json.dumps(out, indent=1))


def _faces(name, ref):
    import trimesh

    ext = "ply" if name == "igea" else "obj"
    tm = trimesh.load(find_shared("meshes", f"{name}.{ext}"), process=False, force="mesh")
    inv = np.full(len(tm.vertices), -1)
    inv[ref["orig_index"]] = np.arange(len(ref["orig_index"]))
    return inv[np.asarray(tm.faces)]


if __name__ == "__main__":
    main()
