"""The solver's worst pairs sit near their source; a second solve of a patch around each source at a higher k, kept
where it is shorter, removes them (prototype for issue 24.4: one solver per patch, CPU, not yet in the product).

    python benchmarks/experiments/source_patch.py --meshes needles,cow,cheburashka,rocker-arm,spot,fandisk --k-patch 6

Per mesh and its 24 sources (as tail_variants.py: the reference sources, then tvb-gdist): the k=3 solve; the
distance of each pair above 0.5% in mean edge lengths; then, per source, the faces whose vertices all lie within
(R + 2) mean edges of it by the k=3 distances, solved alone at --k-patch, and min(k=3, patch) per vertex. Both
solves give lengths of real surface paths (upper bounds), so the minimum is one too; a geodesic to a vertex at
distance r stays within r of the source, so the patch holds every geodesic to a vertex within R.
Prints MRE, the worst pair and the pairs above 0.5% before and after, and the patch nodes per source.
"""
import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "benchmarks" / "experiments"))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--meshes", default="needles,cow,cheburashka,rocker-arm,spot,fandisk")
    ap.add_argument("--sources", type=int, default=24)
    ap.add_argument("--radius", type=float, default=12.0, help="R, mean edge lengths")
    ap.add_argument("--k-patch", type=int, default=6)
    a = ap.parse_args(argv)
    import warp as wp

    wp.config.quiet = True
    from neurogf_warp.ground_truth.solver import GeodesicSolver
    from worst_pairs import load

    for name in a.meshes.split(","):
        V, F, src, ex = load(name, a.sources)
        V, F = np.asarray(V, np.float64), np.asarray(F, np.int64)
        t0 = time.perf_counter()
        s = GeodesicSolver((V, F), device="cpu", k=3, max_rows=len(src))
        d = s.solve(src).astype(np.float64) / s.mesh.scale
        t_full = time.perf_counter() - t0
        E = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
        me = float(np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1).mean())
        ok = np.isfinite(ex) & (ex > 0)
        rel0 = np.where(ok, (d - ex) / np.where(ok, ex, 1.0), 0.0)
        far = [f"{ex[r, v] / me:.1f}" for r, v in np.argwhere(rel0 > 5e-3)]
        print(f"{name}: pairs above 0.5% lie {', '.join(far) or '-'} mean edges from their source")
        patched, nodes, t1 = d.copy(), 0, time.perf_counter()
        for r, sv in enumerate(src):
            keep = F[(d[r] <= (a.radius + 2) * me)[F].all(axis=1)]
            used = np.unique(keep)
            local = np.full(len(V), -1, np.int64)
            local[used] = np.arange(len(used))
            p = GeodesicSolver((V[used], local[keep]), device="cpu", k=a.k_patch, max_rows=1)
            nodes += p.n_nodes
            dp = p.solve(np.array([local[sv]])).astype(np.float64)[0] / p.mesh.scale
            patched[r, used] = np.minimum(patched[r, used], dp)
        t_patch = time.perf_counter() - t1
        for tag, dd in (("k=3", d), (f"k=3 + patches (R={a.radius:g}, k={a.k_patch})", patched)):
            rel = (dd[ok] - ex[ok]) / ex[ok]
            print(f"  {tag:34s} MRE {np.abs(rel).mean() * 100:.4f}%  max {rel.max() * 100:.3f}%  "
                  f">0.5%: {(rel > 5e-3).sum():3d}  min {rel.min():.1e}")
        print(f"  nodes: {s.n_nodes:,} per row, patches {nodes / len(src):,.0f} per source "
              f"({nodes / len(src) / s.n_nodes:.1%}); CPU {t_full:.1f} s for the rows, {t_patch:.1f} s for the "
              f"patches (one solver each)", flush=True)


if __name__ == "__main__":
    main()
