"""Distances to points between vertices: models scored at edge midpoints against exact-grade geodesics.

    python benchmarks/between_vertices.py MODEL.ngf [MODEL.ngf ...] --device cpu

A model answers at its mesh's vertices (where training drew its pairs and a landmark network reads its table's own
rows) and at any other surface point (where a landmark network interpolates its table over the closest face). This
scores both: for ``--sources`` vertex sources of the model's mesh, the distances to every vertex and to the
midpoint of every edge, against the ground-truth solver (``ngf.geodesic_distances``, near-source treatment on) on
the mesh subdivided once at its edge midpoints, which is the same surface with the midpoints as vertices. Prints
the MRE, p99 and max relative error at vertices and at midpoints per model, and writes JSON
($OUT/between_vertices.json or --json) with the device, date, commit and command.
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

import _bootstrap  # noqa: F401  (this checkout's neurogf_warp, installed or not)
from common import write_json


def subdivided(v: np.ndarray, f: np.ndarray):
    """(vertices, faces, edges): the mesh split at its edge midpoints (vertices first, then one per edge) and the
    (E, 2) edges in the order of their midpoints."""
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    edges, inv = np.unique(e, axis=0, return_inverse=True)
    inv = inv.reshape(3, -1).T + len(v)  # midpoint ids of each face's edges (01, 12, 20)
    a, b, c = f.T
    m01, m12, m20 = inv.T
    faces = np.concatenate([np.stack([a, m01, m20], 1), np.stack([m01, b, m12], 1), np.stack([m20, m12, c], 1),
                            np.stack([m01, m12, m20], 1)])
    return np.concatenate([v, 0.5 * (v[edges[:, 0]] + v[edges[:, 1]])]), faces, edges


def errors(got: np.ndarray, ref: np.ndarray) -> dict:
    ok = np.isfinite(ref) & (ref > 0)
    rel = np.abs(got[ok] - ref[ok]) / ref[ok]
    return {"mre": float(rel.mean()), "p99": float(np.quantile(rel, 0.99)), "max": float(rel.max()),
            "pairs": int(ok.sum()), "nonfinite": int((~np.isfinite(got[ok])).sum())}


def score(path: str, a) -> dict:
    import neurogf_warp as ngf

    model = ngf.load(path)
    if model.mesh is None:
        raise SystemExit(f"{path}: the model file stores no mesh; this benchmark needs one")
    m = model.mesh
    v, f = np.asarray(m.internal_vertices, np.float64), np.asarray(m.internal_faces, np.int64)
    sv, sf, edges = subdivided(v, f)
    rng = np.random.default_rng(a.seed)
    src = rng.choice(len(v), min(a.sources, len(v)), replace=False)
    t = time.perf_counter()
    exact = ngf.geodesic_distances((sv, sf), src, device=a.device)  # (S, V + E): vertices, then midpoints
    gt_s = time.perf_counter() - t
    internal_to_input = m.index  # each internal vertex's number in the mesh as given
    t = time.perf_counter()
    at_vertices = ngf.distance_matrix(model, internal_to_input[src], internal_to_input, device=a.device)
    at_midpoints = ngf.distance_matrix(model, internal_to_input[src], sv[len(v):], device=a.device)
    query_s = time.perf_counter() - t
    d = model.net.options
    return {"model": os.path.basename(path), "design": (f"landmarks K = {d['landmarks']}" if d.get("landmarks")
                                                        else "default"),
            "vertices": int(len(v)), "midpoints": int(len(edges)), "sources": int(len(src)),
            "at_vertices": errors(at_vertices, exact[:, :len(v)]),
            "at_midpoints": errors(at_midpoints, exact[:, len(v):]),
            "ground_truth_s": gt_s, "query_s": query_s}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("models", nargs="+", help="model files (.ngf) that store their mesh")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--sources", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default=None, help="output JSON (default: $OUT/between_vertices.json, else "
                                                 "benchmarks/results/between_vertices.json)")
    a = ap.parse_args(argv)
    rows = [score(p, a) for p in a.models]
    print(f"{'model':>24} {'design':>18} {'where':>10} {'MRE':>8} {'p99':>8} {'max':>8} {'pairs':>9}")
    for r in rows:
        for where in ("at_vertices", "at_midpoints"):
            e = r[where]
            print(f"{r['model']:>24} {r['design']:>18} {where[3:]:>10} {100 * e['mre']:7.3f}% {100 * e['p99']:7.2f}% "
                  f"{100 * e['max']:7.1f}% {e['pairs']:>9,}")
    out = a.json or os.path.join(os.environ.get("OUT", os.path.join(os.path.dirname(__file__), "results")),
                                 "between_vertices.json")
    print("JSON:", write_json(out, {"device": a.device, "argv": sys.argv[1:], "rows": rows}, "between_vertices",
                              a.device))
    return 0


if __name__ == "__main__":
    sys.exit(main())
