"""For one (source, target) pair: follow the exact geodesic (potpourri3d edge-flip, checked against tvb-gdist)
edge by edge and show, on every edge it crosses, whether some Steiner node of that edge holds a window that
carries the geodesic's ray there (crossing inside [lo, hi] with the exact length). The first edge where none does
is where the beam was lost.

    python benchmarks/experiments/lost_beams.py --mesh cheburashka --row 0 --target 2440
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "benchmarks" / "experiments"))


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--mesh", default="cheburashka")
    ap.add_argument("--sources", type=int, default=8)
    ap.add_argument("--pairs", default="", help="row:target,... (default: the 3 worst)")
    ap.add_argument("--k", type=int, default=3)
    a = ap.parse_args(argv)
    import potpourri3d as pp
    import warp as wp

    wp.config.quiet = True
    from neurogf_warp.ground_truth.solver import GeodesicSolver
    from worst_pairs import load, vertex_geometry

    V, F, src, ex = load(a.mesh, a.sources)
    s = GeodesicSolver((V, F), device="cpu", k=a.k, max_rows=len(src))
    d = s.solve(src).astype(np.float64) / s.mesh.scale
    rel = np.where(np.isfinite(ex) & (ex > 0), (d - ex) / np.where(ex > 0, ex, 1), 0)
    if a.pairs:
        pairs = [tuple(int(x) for x in p.split(":")) for p in a.pairs.split(",")]
    else:
        pairs = [divmod(int(i), len(V)) for i in np.argsort(rel.ravel())[::-1][:3]]
    Vn = s.mesh.internal_normalized_vertices
    P, tf, asum, val = vertex_geometry(s)
    edges = s.topo.edges
    ekey = {(int(u), int(v)): i for i, (u, v) in enumerate(edges)}
    start, node_edge, node_t = s.nodes
    st = s.state
    W = {n: getattr(st.win, n).numpy() for n in ("face", "along", "height", "sigma", "lo", "hi")}
    dist = st.dist.numpy()
    mel = np.linalg.norm(P[edges[:, 0]] - P[edges[:, 1]], axis=1).mean()
    solver = pp.EdgeFlipGeodesicSolver(Vn, np.asarray(s.mesh.internal_faces))
    for r, tgt in pairs:
        pts = solver.find_geodesic_path(v_start=int(src[r]), v_end=int(tgt))
        L = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        print(f"== {a.mesh} row {r} (src {src[r]}) -> {tgt}: ours {d[r, tgt]:.6g} exact {ex[r, tgt]:.6g} "
              f"({rel[r, tgt] * 100:.3f}%), edge-flip path {L.sum() / s.mesh.scale:.6g}, {len(pts) - 2} crossings, "
              f"length {L.sum() / mel:.1f} mean edges")
        pref = np.r_[0, np.cumsum(L)]
        sid = s._solver_id
        for i in range(1, len(pts) - 1):
            p = pts[i]
            # the edge this point lies on: the closest segment among edges of faces near the point
            near = np.argsort(np.linalg.norm(Vn - p, axis=1))[:12]
            best = None
            for u in near:
                for v in near:
                    e = ekey.get((int(min(sid[u], sid[v])), int(max(sid[u], sid[v]))))
                    if e is None:
                        continue
                    A, B = P[edges[e, 0]], P[edges[e, 1]]
                    t = np.clip(np.dot(p - A, B - A) / np.dot(B - A, B - A), 0, 1)
                    dd = np.linalg.norm(A + t * (B - A) - p)
                    if best is None or dd < best[0]:
                        best = (dd, e, t)
            _, e, t = best
            A, B = P[edges[e, 0]], P[edges[e, 1]]
            el = np.linalg.norm(B - A)
            ids = np.arange(start[e], start[e + 1]) + s.nv
            carried = []
            for n in ids:
                f, al, h, sg, lo, hi = (W[k][r, n] for k in ("face", "along", "height", "sigma", "lo", "hi"))
                if f < 0:
                    carried.append(f"{node_t[n - s.nv]:.2f}:pt d{dist[r, n] / mel:.3f}")
                    continue
                ray = sg + np.hypot(t * el - al, h)
                ok = lo - 1e-6 <= t <= hi + 1e-6
                err = (ray - pref[i]) / pref[i]
                carried.append(f"{node_t[n - s.nv]:.2f}:[{lo:.2f},{hi:.2f}]{'in' if ok else 'out'} "
                               f"ray{err * 100:+.3f}%")
            va, vb = edges[e]
            print(f"  {i:2d} at {pref[i] / pref[-1]:.2f} e{e} t={t:.3f} (v{va} val {val[va]} "
                  f"{np.degrees(asum[va]):.0f}, v{vb} val {val[vb]} {np.degrees(asum[vb]):.0f}) | " + " ; ".join(carried))


if __name__ == "__main__":
    main()
