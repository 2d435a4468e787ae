"""Path Chamfer-L1 before and after projecting predicted paths onto the surface, released bunny and fandisk.

    python benchmarks/path_snap.py --device cpu --pairs 128 --refine-pairs 32     # this machine (slow part: refine)

For random vertex pairs (``--sources`` sources x targets, seed 0) our geodesic solver's paths (128 points,
``neurogf_warp.geodesic_paths``) are the reference. Predicted paths, 128 points: the path head (raw), the same
with the SDF projection (``ngf.project``, 2 Newton steps: ``path(..., project="sdf")``), with the exact closest
mesh point (``surface.snap_to_mesh``: ``path(..., project="mesh")``), and ``refine=50`` (already on the SDF
surface) before and after snapping. Chamfer-L1 as ``evaluate`` computes it (normalized unit-sphere frame).
Path length / predicted distance and path length / solver path length show that lengths still match.
"""
from __future__ import annotations

import argparse
import datetime
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import find_shared  # noqa: E402


def lengths(x):
    return np.linalg.norm(np.diff(x, axis=1), axis=2).sum(1)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--pairs", type=int, default=128)
    ap.add_argument("--sources", type=int, default=8)
    ap.add_argument("--refine-pairs", type=int, default=32, help="pairs also refined (spread over all); 0: none")
    ap.add_argument("--refine", type=int, default=50)
    ap.add_argument("--meshes", nargs="+", default=["bunny", "fandisk"])
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    import neurogf_warp as ngf
    from neurogf_warp.evaluation import metrics as L
    from neurogf_warp.mesh.surface import snap_to_mesh

    files = {"bunny": ("stanford-bunny.obj", "bunny"), "fandisk": ("fandisk.obj", "fandisk")}
    res = {"date": datetime.date.today().isoformat(), "device": a.device, "meshes": {}}
    for name in a.meshes:
        mesh_file, ck = files[name]
        model = ngf.load(find_shared("checkpoints", "official", f"NeuroGF_Pretrainer__{ck}_final.pth"),
                         mesh=find_shared("meshes", mesh_file))
        mesh = model.mesh
        rng = np.random.default_rng(0)
        per = -(-a.pairs // a.sources)
        t0 = time.perf_counter()
        gts = []
        for s in rng.choice(len(mesh.vertices), a.sources, replace=False):
            tg = rng.choice(len(mesh.vertices), per + 1, replace=False)
            tg = tg[tg != s][:per]
            g = ngf.geodesic_paths(mesh, mesh.index[s], mesh.index[tg], m=128, device=a.device)
            gts.append(g[np.isfinite(g).all(axis=(1, 2))])
        gt = np.concatenate(gts)[:a.pairs]
        t_solver = time.perf_counter() - t0
        p, q = gt[:, 0], gt[:, -1]
        norm = lambda x: mesh.normalize(x.reshape(-1, 3)).reshape(x.shape)
        gtn = norm(gt)
        pred_d = ngf.distance(model, p, q, device=a.device) * mesh.scale  # normalized units
        raw = ngf.path(model, p, q, m=128, device=a.device)
        variants = {"raw": raw,
                    "raw + sdf projection": ngf.project(model, raw.reshape(-1, 3), device=a.device).reshape(raw.shape),
                    "raw + mesh snap": snap_to_mesh(mesh, raw, device=a.device)[0]}
        # the refined subset: every (len / k)-th pair, so that it spans all sources
        sub = np.unique(np.linspace(0, len(gt) - 1, min(a.refine_pairs, len(gt))).round().astype(int))
        t_ref = None
        if len(sub):
            t0 = time.perf_counter()
            ref = ngf.path(model, p[sub], q[sub], m=128, refine=a.refine, device=a.device)
            t_ref = time.perf_counter() - t0
            variants[f"refine={a.refine}"] = ref
            variants[f"refine={a.refine} + mesh snap"] = snap_to_mesh(mesh, ref, device=a.device)[0]
        rows = {}
        print(f"\n{name}: {len(gt)} solver paths ({t_solver:.0f} s), refined: {len(sub)} of them ({t_ref or 0:.0f} s)")
        print(f"{'variant':28s} {'pairs':>5s} {'Chamfer-L1':>11s} {'same pairs raw':>14s} {'len/pred d':>16s} "
              f"{'len/solver len':>16s} {'off mesh':>9s}")
        for v, x in variants.items():
            x = np.asarray(x, dtype=np.float64)
            n = len(x)
            rows_ = sub if v.startswith("refine") else np.arange(len(gt))
            xn = norm(x)
            cd = L.chamfer_l1(xn, gtn[rows_])
            cd_raw = L.chamfer_l1(norm(raw[rows_]), gtn[rows_])
            lr = lengths(xn) / pred_d[rows_]
            ls = lengths(xn) / lengths(gtn[rows_])
            sp, _, _ = snap_to_mesh(mesh, x, device=a.device)
            off = np.linalg.norm(norm(np.asarray(sp, dtype=np.float64)) - xn, axis=-1).mean()
            rows[v] = {"pairs": n, "chamfer_l1": float(cd.mean()), "chamfer_l1_raw_same_pairs": float(cd_raw.mean()),
                       "length_over_predicted_distance": {"mean": float(lr.mean()), "median": float(np.median(lr)),
                                                          "p90": float(np.quantile(lr, 0.9))},
                       "length_over_solver_length": {"mean": float(ls.mean()), "median": float(np.median(ls))},
                       "mean_distance_to_mesh": float(off)}
            print(f"{v:28s} {n:5d} {cd.mean():11.4e} {cd_raw.mean():14.4e} {lr.mean():7.4f} ({np.median(lr):.4f}) "
                  f"{ls.mean():7.4f} ({np.median(ls):.4f}) {off:9.2e}")
        res["meshes"][name] = {"solver_s": t_solver, "refine_s": t_ref, "variants": rows}
    if a.json:
        Path(a.json).write_text(json.dumps(res, indent=1))
    return res


if __name__ == "__main__":
    main()
