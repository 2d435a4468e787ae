"""Where a trained model's error tail lives: every pair of an exact reference, binned by the pair's geodesic distance
over its source's farthest one (d/dmax), with each bin's share of the pairs, its MRE and its share of the top 1%
(the pairs at or above the p99). Prints a table and writes MODEL.tail.json beside the model.

    python benchmarks/experiments/error_tail.py MODEL.ngf REFERENCE.npz [--device cuda:0]

(Eighth session, RESULTS.md: in 60 s GPU models the pairs below a fifth of dmax are 8-12% of the pairs and 40-79% of
the top 1%; this is what ``hard_share`` aims at.)
"""
import argparse
import json

import numpy as np

import neurogf_warp as ngf
from neurogf_warp.evaluation.evaluate import _predict, load_reference

EDGES = (0.0, 0.02, 0.05, 0.1, 0.2, 0.5, 1.01)  # d / dmax bin edges (1.01: the farthest pair itself included)


def tail_table(pred: np.ndarray, gt: np.ndarray) -> dict:
    """pred, gt : (S, V) distances (gt inf across parts, 0 at the source) -> {mre, p99, max, rows: [per bin]}."""
    ok = np.isfinite(gt) & (gt > 0)
    rel = (np.abs(pred - gt) / np.where(ok, gt, 1.0))[ok]
    frac = (gt / np.nanmax(np.where(ok, gt, np.nan), axis=1, keepdims=True))[ok]
    p99 = float(np.quantile(rel, 0.99))
    top = rel >= p99
    rows = []
    for lo, hi in zip(EDGES[:-1], EDGES[1:]):
        m = (frac >= lo) & (frac < hi)
        rows.append(dict(bin=f"{lo}-{hi}", pairs=float(m.mean()), mre=float(rel[m].mean()) if m.any() else None,
                         top1=float(top[m].sum() / top.sum())))
    return dict(mre=float(rel.mean()), p99=p99, max=float(rel.max()), rows=rows)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model")
    ap.add_argument("reference")
    ap.add_argument("--device", default=None)
    a = ap.parse_args()
    model = ngf.load(a.model)
    vids, sids, gt = load_reference(a.reference, model.mesh)
    t = tail_table(_predict(model, model.mesh, vids, sids, a.device, False), gt)
    print(f"MRE {t['mre']:.4%} p99 {t['p99']:.3%} max {t['max']:.2%}")
    for r in t["rows"]:
        print(f"  d/dmax {r['bin']:>9}: {r['pairs']:6.1%} of pairs, MRE {r['mre'] or 0:.3%}, {r['top1']:6.1%} of the top 1%")
    with open(a.model + ".tail.json", "w") as f:
        json.dump(t, f)


if __name__ == "__main__":
    main()
