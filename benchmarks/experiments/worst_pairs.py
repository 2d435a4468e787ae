"""Where the solver's worst pairs lose length (issue 24.4): per mesh, error against exact MMP (tvb-gdist), the
worst pairs, and for each the bends of its path record chain (where the straight pieces meet).

    python benchmarks/experiments/worst_pairs.py --meshes cow,needles --sources 8 --top 3

A geodesic bends only at vertices; a bend at a Steiner node (inside an edge) is where a ray was lost and the path
went through the plain graph. For each such bend the script prints the unfolded turning angle and the geometry
there (the angles of the faces at the edge, the valences and angle sums of the edge's vertices).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def load(name, sources):
    from tests import geodesic_meshes as M
    from tests.reference_geodesics import gdist_distances

    classes = M.mesh_classes()
    if name in classes:
        V, F, R = classes[name]
        src = np.random.default_rng(0).choice(len(V), sources, replace=False)
        return V, F, src, gdist_distances(V, R, src)
    from geodesics import shared_reference

    V, F, src, ex = shared_reference(name)
    if sources > len(src):
        # more sources than the shared reference holds: the rest from tvb-gdist on the same mesh
        rest = np.setdiff1d(np.random.default_rng(1).permutation(len(V)), src)[: sources - len(src)]
        src, ex = np.r_[src, rest], np.concatenate([ex, gdist_distances(V, F, rest)])
    return V, F, src[:sources], ex[:sources]


def angles(P):
    """(F, 3) interior angles of triangles P (F, 3, 3)."""
    out = np.zeros(P.shape[:2])
    for i in range(3):
        a = P[:, (i + 1) % 3] - P[:, i]
        b = P[:, (i + 2) % 3] - P[:, i]
        c = (a * b).sum(1) / np.maximum(np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-300)
        out[:, i] = np.arccos(np.clip(c, -1, 1))
    return out


def vertex_geometry(s):
    """(positions (V, 3) float64, faces, angle sum per vertex, valence per vertex) of a solver's mesh."""
    P = s._positions.astype(np.float64)
    tf = s.topo.faces
    asum = np.zeros(len(P))
    np.add.at(asum, tf.ravel(), angles(P[tf]).ravel())
    return P, tf, asum, np.bincount(tf.ravel(), minlength=len(P))


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--meshes", default="needles,cow,cheburashka,rocker-arm")
    ap.add_argument("--sources", type=int, default=8)
    ap.add_argument("--top", type=int, default=3)
    ap.add_argument("--k", type=int, default=3)
    a = ap.parse_args(argv)
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    wp.config.quiet = True
    from neurogf_warp.ground_truth.solver import GeodesicSolver

    for name in a.meshes.split(","):
        V, F, src, ex = load(name, a.sources)
        t0 = time.perf_counter()
        s = GeodesicSolver((V, F), device="cpu", k=a.k, max_rows=len(src))
        d = s.solve(src).astype(np.float64) / s.mesh.scale
        dt = time.perf_counter() - t0
        ok = np.isfinite(ex) & (ex > 0)
        rel = np.where(ok, (d - ex) / np.where(ok, ex, 1), 0)
        print(f"== {name}: V={len(V)} sources={len(src)} MRE {np.abs(rel[ok]).mean() * 100:.4f}% max "
              f"{rel.max() * 100:.3f}% >0.5%: {(rel > 5e-3).sum()} ({dt:.1f} s)")
        # vertex geometry (solver numbering)
        P, tf, asum, val = vertex_geometry(s)
        bnd = np.zeros(len(P), bool)
        eb = s.topo.edges[np.diff(s.topo.edge_face_start) == 1]
        bnd[eb.ravel()] = True
        # the worst pairs: (row, target)
        flat = np.argsort(rel.ravel())[::-1][: a.top]
        origin = s.state.rec.origin.numpy()
        for fi in flat:
            r, tgt = divmod(int(fi), len(V))
            x = int(s._solver_id[tgt])
            print(f"  pair row {r} src {src[r]} -> {tgt}: rel {rel[r, tgt] * 100:.3f}%, exact {ex[r, tgt]:.4g}, "
                  f"valence/angle-sum of target {val[x]}/{np.degrees(asum[x]):.1f}")
            chain = [x]
            while origin[r, chain[-1]] != chain[-1] and len(chain) < 10000:
                chain.append(int(origin[r, chain[-1]]))
            bends = chain[1:-1]
            desc = []
            for b in bends:
                if b < s.nv:
                    desc.append(f"v{b}(val {val[b]}, sum {np.degrees(asum[b]):.0f}{', bnd' if bnd[b] else ''})")
                else:
                    desc.append(f"S{b}")
            print(f"    bends (target->source): {len(bends)}: " + " ".join(desc[:20]))
        sys.stdout.flush()


if __name__ == "__main__":
    main()


def summary(names, sources=24, above=4e-3):
    """Per mesh: how the paths of the pairs above `above` end: the kind of their last bend (a Steiner node, a
    vertex that is not a saddle (angle sum <= 360.5 degrees), a saddle vertex, none) and its hop count."""
    import warp as wp

    wp.config.quiet = True
    from neurogf_warp.ground_truth.solver import GeodesicSolver

    for name in names:
        V, F, src, ex = load(name, sources)
        s = GeodesicSolver((V, F), device="cpu", max_rows=len(src))
        d = s.solve(src).astype(np.float64) / s.mesh.scale
        ok = np.isfinite(ex) & (ex > 0)
        rel = np.where(ok, (d - ex) / np.where(ok, ex, 1), 0)
        P, tf, asum, _ = vertex_geometry(s)
        origin = s.state.rec.origin.numpy()
        kinds = {"steiner": 0, "flat-or-convex vertex": 0, "saddle vertex": 0, "straight": 0}
        nb = []
        rows, tg = np.nonzero(rel > above)
        for r, t in zip(rows, tg):
            x = int(s._solver_id[t])
            chain = [x]
            while origin[r, chain[-1]] != chain[-1] and len(chain) < 10000:
                chain.append(int(origin[r, chain[-1]]))
            nb.append(len(chain) - 2)
            if len(chain) == 2:
                kinds["straight"] += 1
            elif chain[1] >= s.nv:
                kinds["steiner"] += 1
            elif np.degrees(asum[chain[1]]) <= 360.5:
                kinds["flat-or-convex vertex"] += 1
            else:
                kinds["saddle vertex"] += 1
        allv = np.degrees(asum)
        print(f"{name}: {len(rows)} pairs > {above * 100:.1f}% of {ok.sum()}; last bend: {kinds}; bends per path "
              f"median {np.median(nb) if nb else 0}; vertices with angle sum <= 360.5: "
              f"{(allv <= 360.5).mean() * 100:.0f}%")
