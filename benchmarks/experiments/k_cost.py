"""CPU cost of the Steiner count k (issue 24.4): sources/s after set-up and capture (one warm-up batch first),
nodes, on shared meshes.

    python benchmarks/experiments/k_cost.py --runs fandisk:8,stanford-bunny:4,igea:1 --ks 3,4,5
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", default="fandisk:8,stanford-bunny:4")
    ap.add_argument("--ks", default="3,4,5")
    a = ap.parse_args(argv)
    import warp as wp

    wp.config.quiet = True
    from geodesics import shared_reference
    from neurogf_warp.ground_truth.solver import GeodesicSolver

    for run in a.runs.split(","):
        name, n = run.split(":")
        V, F, src, _ = shared_reference(name)
        src = src[: int(n)]
        for k in (int(x) for x in a.ks.split(",")):
            s = GeodesicSolver((V, F), device="cpu", k=k, max_rows=len(src))
            s.run(src[:1] if len(src) > 1 else src)  # warm-up: capture and first launch
            t0 = time.perf_counter()
            s.run(src)
            dt = time.perf_counter() - t0
            print(f"{name:15s} V={len(V):>7,d} k={k} nodes={s.n_nodes:>9,d} sources={len(src)} {dt:6.2f} s "
                  f"{len(src) / dt:6.2f} sources/s", flush=True)


if __name__ == "__main__":
    main()
