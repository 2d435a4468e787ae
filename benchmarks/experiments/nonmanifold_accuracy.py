"""Solver accuracy on meshes that are not clean manifolds, against exact references (CPU).

    python benchmarks/experiments/nonmanifold_accuracy.py [--json out.json] [--cases a,b]

Cases (tests/geodesic_meshes.py): flat discs glued at their centres and spheres touching at a vertex (analytic /
gdist on a cut copy), cow.obj (its pinch vertex 253; shared exact reference; all pairs, then only the pairs whose
geodesic passes vertex 253), a book of three flat pages on one spine, an ellipsoid with four fins and a coarser
one with one fin (edges with three faces), an ellipsoid with ten holes, and the same with 150 edges split near
an end (needles). Distances: relative error over all vertices except the source; paths:
every vertex traced from two sources, the traced length against the solver's own distance.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
from common import find_shared  # noqa: E402

from tests import geodesic_meshes as M  # noqa: E402
from tests.reference_geodesics import exact_distances  # noqa: E402


def cases():
    rng = np.random.default_rng(0)
    V, F, disc = M.pinched_discs()
    src = np.r_[1, 2, rng.choice(len(V), 4, replace=False)]
    yield "pinched-discs", V, F, src, M.pinched_discs_distances(V, disc, src)
    V, F = M.pinched_spheres()
    src = np.r_[1, rng.choice(len(V), 3, replace=False)]
    yield "pinched-spheres", V, F, src, exact_distances(V, F, src)
    ref = np.load(find_shared("reference", "exact", "cow.npz"))
    import trimesh

    tm = trimesh.load(find_shared("meshes", "cow.obj"), process=False, force="mesh")
    inv = np.full(len(tm.vertices), -1)
    inv[ref["orig_index"]] = np.arange(len(ref["orig_index"]))
    V, F, ex = ref["positions"].astype(np.float64), inv[np.asarray(tm.faces)], ref["dist"].astype(np.float64)
    yield "cow", V, F, ref["sources"], ex
    # only the pairs whose exact geodesic passes the pinch vertex 253
    through = np.abs(ex - (ex[:, [253]] + exact_distances(V, F, [253])[0])) < 1e-6 * ex
    yield "cow-through-pinch", V, F, ref["sources"], np.where(through, ex, np.nan)
    V, F, uv, page = M.book()
    src = np.r_[rng.choice(len(V), 5, replace=False)]
    yield "book-3-pages", V, F, src, M.book_distances(uv, page, src)
    V, F, nv = M.finned_sphere()
    src = np.r_[F[-1, 0], F[-3, 1], rng.choice(nv, 3, replace=False)]
    yield "finned-ellipsoid", V, F, src, exact_distances(V, F, src, samples=256)
    V, F, nv = M.finned_sphere(subdivisions=2, fins=1)
    src = np.array([F[-1, 0], 7, nv])
    yield "finned-ellipsoid-coarse", V, F, src, exact_distances(V, F, src, samples=256)

    V, F = M.holed_ellipsoid()
    src = rng.choice(len(V), 5, replace=False)
    ex = exact_distances(V, F, src)  # cutting holes can leave vertices whose faces form two fans
    yield "holed-ellipsoid", V, F, src, ex
    V2, F2 = M.split_edges(V, F, 150)
    yield "holed-slivered", V2, F2, src, np.c_[ex, np.full((len(src), len(V2) - len(V)), np.nan)]


def measure(name, V, F, src, ex, device="cpu", **kw):
    from neurogf_warp.ground_truth.geodesics import GeodesicSolver
    from neurogf_warp.mesh.mesh import load_mesh

    m = load_mesh((V, F))
    t = time.perf_counter()
    solver = GeodesicSolver(m, device=device, batch=len(src), **kw)
    si = m.vertex(np.asarray(src))
    solver.run(si)
    d = m.to_input(solver.vertex_distances()).astype(np.float64) / m.scale
    dt = time.perf_counter() - t
    ok = np.isfinite(ex) & (ex > 1e-9)
    rel = (d[ok] - ex[ok]) / ex[ok]
    # paths: every vertex from the first two sources, traced length vs the solver's distance
    rows = np.repeat(np.arange(2), solver.nv).astype(np.int32)
    tg = np.tile(np.arange(solver.nv), 2).astype(np.int32)
    out = solver.trace(rows, tg)
    pts, offs, flag = out[0], out[1], out[2]
    seg = np.linalg.norm(np.diff(pts.astype(np.float64), axis=0), axis=1)
    seg = np.where(np.isfinite(seg), seg, 0.0)
    cs = np.r_[0, np.cumsum(seg)]
    L = cs[np.maximum(offs[1:] - 1, 0)] - cs[offs[:-1]]
    dn = solver.vertex_distances()[rows, tg].astype(np.float64)
    traced = (offs[1:] > offs[:-1]) & np.all(np.isfinite(pts[np.minimum(offs[:-1], max(len(pts) - 1, 0))]), axis=-1) \
        if len(pts) else np.zeros(len(tg), bool)
    good = traced & np.isfinite(dn) & (dn > 1e-6)
    excess = (L[good] - dn[good]) / dn[good]
    row = dict(case=name, vertices=len(V), faces=len(F), sources=len(src), solve_s=round(dt, 2),
               mre=float(np.abs(rel).mean()), max_rel=float(rel.max()), min_rel=float(rel.min()),
               over_0p5pct=int((rel > 5e-3).sum()), pairs=int(ok.sum()),
               paths=int(len(tg)), flagged=int(np.sum(flag != 0)), not_returned=int(np.sum(~traced & np.isfinite(dn))),
               path_over_0p1pct=int((excess > 1e-3).sum()), path_max_excess=float(excess.max()) if len(excess) else 0.0)
    return row


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--json", default=None)
    ap.add_argument("--cases", default=None)
    ap.add_argument("--set", action="append", default=[], help="solver option KEY=VALUE (k, delta)")
    a = ap.parse_args(argv)
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    rows = []
    for name, V, F, src, ex in cases():
        if a.cases and name not in a.cases.split(","):
            continue
        kw = {k: float(v) if "." in v else int(v) for k, v in (x.split("=", 1) for x in a.set)}
        r = measure(name, V, F, src, ex, **kw)
        rows.append(r)
        print(json.dumps(r), flush=True)
    print("\n| case | V | MRE | max rel | min rel | > 0.5% | paths | flagged | path > +0.1% | max path excess |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['case']} | {r['vertices']} | {100 * r['mre']:.4f}% | {100 * r['max_rel']:.3f}% "
              f"| {r['min_rel']:.1e} "
              f"| {r['over_0p5pct']} | {r['paths']} | {r['flagged']} | {r['path_over_0p1pct']} | "
              f"{100 * r['path_max_excess']:.3f}% |")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
