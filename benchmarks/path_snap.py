"""Path Chamfer-L1 to the solver's paths: the path head, the default (snapped to the mesh), refinement on the mesh
and on the SDF head's surface, with the time of each call.

    python benchmarks/path_snap.py --device cpu --pairs 128 --sdf-pairs 16            # released bunny, fandisk
    python benchmarks/path_snap.py --device cpu --models torus.ngf spot.ngf --meshes   # your own trained models

For random vertex pairs (``--sources`` sources x targets, seed 0) our geodesic solver's paths (128 points,
``neurogf_warp.geodesic_paths``) are the reference. Variants, 128 points each: ``project=None`` (the path head's
own points), the default (``project="auto"``: snapped to the mesh), ``refine=R`` (shortened on the mesh, the best
of five candidates by ``surface_fit``), and on ``--sdf-pairs`` of the pairs ``refine=R`` on a copy of the model
without its mesh (shortened on the SDF head's surface: the method ``queries.py``'s refine row times on a GPU; slow on a CPU).
Chamfer-L1 as ``evaluate`` computes it (normalized unit-sphere frame); "worse" counts pairs whose refined path has
a Chamfer distance more than 10% above the same pair's head path; "off mesh" is the mean distance of the points
from the mesh (normalized units); "len/solver" the median of the length along the surface (``surface_fit``) over
the solver path's length.
"""
from __future__ import annotations

import argparse
import datetime
import platform
import time
from pathlib import Path

import numpy as np

import _bootstrap  # noqa: F401  (this checkout's neurogf_warp, installed or not)
from common import find_shared, write_json


def lengths(x):
    return np.linalg.norm(np.diff(x, axis=1), axis=2).sum(1)


def timed(f):
    t0 = time.perf_counter()
    r = f()
    return r, time.perf_counter() - t0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--pairs", type=int, default=128)
    ap.add_argument("--sources", type=int, default=8)
    ap.add_argument("--refine", type=int, default=50)
    ap.add_argument("--sdf-pairs", type=int, default=16, help="pairs also refined on the SDF surface; 0: none")
    ap.add_argument("--meshes", nargs="*", default=["bunny", "fandisk"], help="released checkpoints to run")
    ap.add_argument("--models", nargs="*", default=[], help="model files (.ngf with their mesh) to run")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    import neurogf_warp as ngf
    from neurogf_warp.evaluation import metrics as L
    from neurogf_warp.inference.paths import surface_fit
    from neurogf_warp.mesh.surface import snap_to_mesh

    files = {"bunny": ("stanford-bunny.obj", "bunny"), "fandisk": ("fandisk.obj", "fandisk")}
    runs = [(name, lambda name=name: ngf.load(
        find_shared("checkpoints", "official", f"NeuroGF_Pretrainer__{files[name][1]}_final.pth"),
        mesh=find_shared("meshes", files[name][0]))) for name in a.meshes]
    runs += [(Path(f).stem, lambda f=f: ngf.load(f)) for f in a.models]
    res = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="minutes"), "device": a.device,
           "machine": platform.processor() or platform.machine(), "refine": a.refine, "models": {}}
    for name, load in runs:
        model = load()
        mesh = model.mesh
        rng = np.random.default_rng(0)
        per = -(-a.pairs // a.sources)
        gts = []
        for s in rng.choice(len(mesh.internal_vertices), a.sources, replace=False):
            tg = rng.choice(len(mesh.internal_vertices), per + 1, replace=False)
            tg = tg[tg != s][:per]
            g = ngf.geodesic_paths(mesh, mesh.index[s], mesh.index[tg], m=128, device=a.device)
            gts.append(g[np.isfinite(g).all(axis=(1, 2))])
        gt = np.concatenate(gts)[:a.pairs]
        p, q = gt[:, 0], gt[:, -1]
        norm = lambda x: mesh.normalize(np.asarray(x, np.float64).reshape(-1, 3)).reshape(np.shape(x))
        gtn = norm(gt)
        ngf.path(model, p[:2], q[:2], m=128, refine=1, device=a.device)  # compile and build the BVH first
        all_rows = np.arange(len(gt))
        variants = {}
        variants["head (project=None)"] = (all_rows, *timed(lambda: ngf.path(model, p, q, m=128, project=None,
                                                                             device=a.device)))
        variants["default (snapped)"] = (all_rows, *timed(lambda: ngf.path(model, p, q, m=128, device=a.device)))
        variants[f"refine={a.refine}"] = (all_rows, *timed(lambda: ngf.path(model, p, q, m=128, refine=a.refine,
                                                                            device=a.device)))
        if a.sdf_pairs:
            sub = np.unique(np.linspace(0, len(gt) - 1, min(a.sdf_pairs, len(gt))).round().astype(int))
            bare = ngf.Model(net=model.net)  # mesh-free: refines on the SDF surface, in the normalized frame
            pn, qn = mesh.normalize(p[sub]).astype(np.float32), mesh.normalize(q[sub]).astype(np.float32)
            x, t = timed(lambda: ngf.path(bare, pn, qn, m=128, refine=a.refine, device=a.device))
            x = mesh.denormalize(np.asarray(x, np.float64).reshape(-1, 3)).reshape(x.shape)
            variants[f"refine={a.refine} on SDF (no mesh)"] = (sub, x, t)
        head_cd = L.chamfer_l1(norm(variants["head (project=None)"][1]), gtn)
        rows = {}
        print(f"\n{name} ({len(mesh.internal_vertices)} vertices): {len(gt)} solver paths, device {a.device}")
        print(f"{'variant':30s} {'pairs':>5s} {'Chamfer-L1':>11s} {'head, same':>11s} {'worse':>5s} "
              f"{'len/solver':>10s} {'off mesh':>9s} {'seconds':>8s} {'ms/pair':>8s}")
        for v, (sel, x, t) in variants.items():
            x = np.asarray(x, dtype=np.float32)
            cd = L.chamfer_l1(norm(x), gtn[sel])
            fit_len = np.asarray(surface_fit(model, x, device=a.device)[0], np.float64) * mesh.scale
            ls = fit_len / lengths(gtn[sel])
            sp = snap_to_mesh(mesh, x, device=a.device)[0]
            off = np.linalg.norm(norm(sp) - norm(x), axis=-1).mean()
            worse = int((cd > 1.1 * head_cd[sel]).sum())
            rows[v] = {"pairs": len(sel), "chamfer_l1": float(cd.mean()), "chamfer_l1_head_same_pairs":
                       float(head_cd[sel].mean()), "worse_than_head_by_10pct": worse,
                       "surface_length_over_solver_length_median": float(np.median(ls)),
                       "mean_distance_to_mesh": float(off), "seconds": t, "ms_per_pair": 1e3 * t / len(sel)}
            print(f"{v:30s} {len(sel):5d} {cd.mean():11.4e} {head_cd[sel].mean():11.4e} {worse:5d} "
                  f"{np.median(ls):10.4f} {off:9.2e} {t:8.2f} {1e3 * t / len(sel):8.1f}")
        res["models"][name] = {"vertices": len(mesh.internal_vertices), "variants": rows}
    if a.json:
        write_json(a.json, res, "path_snap", a.device)
    return res


if __name__ == "__main__":
    main()
