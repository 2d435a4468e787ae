"""Accuracy of a trained NeuroGF (reference §6): distance MRE / max relative error, path Chamfer-L1, SDF L1.

Ground truth for distances is an exact reference file (keys positions, orig_index, sources, dist; see
shared/reference/README.md) when given, else our geodesic solver from a few random sources. Paths are
compared with solver paths, SDF with ``dataset.sdf_truth``. The heat method (potpourri3d) can be run on
the same sources for comparison. All errors are measured in the normalized unit-sphere frame.
"""
from __future__ import annotations

import json
import os
import sys
import time

import numpy as np
import torch

from . import losses as L
from .mesh import Mesh, load_mesh

__all__ = ["evaluate", "eval_main", "load_reference"]


def load_reference(path, mesh: Mesh):
    """Exact distances of a reference .npz on our internal vertices, normalized units.

    Returns (vertex_ids (Vr,), source_ids (S,), dist (S, Vr)), ids are internal vertex indices of ``mesh``.
    """
    with np.load(os.fspath(path), allow_pickle=False) as z:
        missing = [k for k in ("positions", "orig_index", "sources", "dist") if k not in z.files]
        if missing:
            raise ValueError(f"{path} is not a distance reference: missing {missing}")
        pos, orig, src, dist = z["positions"], z["orig_index"], z["sources"], z["dist"]
    ids = mesh.vertex(orig.astype(np.int64))
    off = np.abs(mesh.vertices[ids] - pos).max() if len(ids) else 0.0
    if not off <= 1e-4 * max(1.0, float(np.abs(pos).max())):
        raise ValueError(f"{path} does not match this mesh: vertex positions differ by up to {off:.3g}")
    return ids, ids[src.astype(np.int64)], dist.astype(np.float64) * mesh.scale


def _torch_device(device):
    return torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))


@torch.no_grad()
def _predict_rows(net, xyz, vertex_ids, source_ids, device):
    """Network distances from each source to the given vertices: (S, Vr) float64, normalized units."""
    x = torch.as_tensor(xyz, dtype=torch.float32, device=device)
    xv = x[torch.as_tensor(vertex_ids, device=device)]
    xs = x[torch.as_tensor(source_ids, device=device)]
    ev, es = net.embed(xv), net.embed(xs)
    return np.stack([net.distance_from_embeddings(es[i].expand_as(ev), ev, xs[i].expand_as(xv), xv).double().cpu().numpy()
                     for i in range(len(es))])


def _rel_stats(pred, gt) -> dict:
    per = [L.relative_errors(p, g) for p, g in zip(pred, gt)]
    r = np.concatenate(per) if per else np.zeros(0)
    return {"mre": float(r.mean()), "max_rel": float(r.max()), "median_rel": float(np.median(r)),
            "p99_rel": float(np.percentile(r, 99)), "pairs": int(r.size),
            "per_source_mre": [float(x.mean()) for x in per]}


def _heat(mesh: Mesh, source_ids, vertex_ids):
    try:
        import potpourri3d as pp3d
    except ImportError as e:
        raise ImportError("the heat-method comparison needs potpourri3d: pip install potpourri3d "
                          "(or neurogf-warp[heat])") from e

    solver = pp3d.MeshHeatMethodDistanceSolver(mesh.normalized_vertices, mesh.faces.astype(np.int64))
    return np.stack([solver.compute_distance(int(s))[vertex_ids] for s in source_ids])


@torch.no_grad()
def _paths(model, mesh: Mesh, rng, n_sources, n_targets, device, solver_device, k, refine):
    """Chamfer-L1 of predicted 128-point paths against solver paths between random vertex pairs; with
    refine > 0 also of the same paths after that many shortening sweeps (the Warp kernels of ``path``)."""
    from .geodesics import geodesic_paths
    from .inference import path

    net = model.net

    V = len(mesh.vertices)
    gts, ps, qs = [], [], []
    for s in rng.choice(V, min(n_sources, V), replace=False):
        tg = rng.choice(V, min(n_targets, V), replace=False)
        tg = tg[tg != s]
        kw = {} if k is None else {"k": k}
        g = geodesic_paths(mesh, mesh.index[s], mesh.index[tg], m=128, device=solver_device, **kw)
        g = mesh.normalize(g.reshape(-1, 3)).reshape(g.shape)
        ok = np.isfinite(g).all(axis=(1, 2))
        gts.append(g[ok])
    gt = np.concatenate(gts)
    p = torch.as_tensor(gt[:, 0], dtype=torch.float32, device=device)
    q = torch.as_tensor(gt[:, -1], dtype=torch.float32, device=device)
    pred = net.path(p, q, 128).double().cpu().numpy()
    cd = L.chamfer_l1(pred, gt)
    res = {"chamfer_l1": float(cd.mean()), "chamfer_l1_median": float(np.median(cd)), "paths": int(len(cd))}
    if refine:
        t0 = time.perf_counter()
        ends = [mesh.denormalize(e) if model.in_mesh_frame else e for e in (gt[:, 0], gt[:, -1])]
        r = path(model, *ends, m=128, refine=refine, device=solver_device)
        r = mesh.normalize(r.reshape(-1, 3)).reshape(r.shape) if model.in_mesh_frame else r
        cd = L.chamfer_l1(r, gt)
        res.update(chamfer_l1_refined=float(cd.mean()), chamfer_l1_refined_median=float(np.median(cd)),
                   refine_sweeps=int(refine), refine_s=time.perf_counter() - t0)
    return res


@torch.no_grad()
def _sdf(model, mesh: Mesh, rng, n, device, solver_device):
    from .dataset import sample_sdf_points, sdf_truth, surface_samples

    pts = sample_sdf_points(rng, surface_samples(mesh, max(n, 30000), rng), n)
    gt = np.asarray(sdf_truth(mesh, pts, device=solver_device), dtype=np.float64)
    x = torch.as_tensor(pts, device=device)
    out = {"sdf_l1": float(np.abs(model.net.sdf(x).double().cpu().numpy() - gt).mean())}
    if model.querier is not None:
        q = model.querier.to(device).eval()
        out["querier_l1"] = float(np.abs(q(x).double().cpu().numpy() - gt).mean())
    return out


def _warp_device(device: torch.device) -> str:
    return "cpu" if device.type == "cpu" else f"cuda:{device.index or 0}"


def evaluate(model, mesh=None, reference=None, *, heat: bool = False, n_sources: int = 8,
             n_path_sources: int = 8, n_path_targets: int = 8, n_sdf: int = 30000, paths: bool = True,
             sdf: bool = True, solver_k: int | None = None, path_refine: int = 0, device=None, seed: int = 0,
             verbose: bool = True) -> dict:
    """Accuracy of ``model`` (a Model or a model file) on ``mesh`` (default: the model's own mesh).

    reference: exact-distance .npz (else the solver from ``n_sources`` random vertices).
    solver_k: Steiner points per edge for the solver's distances and paths (None: its default).
    path_refine: also measure the paths after that many shortening sweeps per level (``path(..., refine=)``;
    slow on CPU).
    Returns a dict (errors as fractions, distances normalized); prints a table when ``verbose``.
    """
    if not hasattr(model, "net"):
        from .model_io import load

        model = load(model, mesh=mesh)
    mesh = load_mesh(mesh) if mesh is not None else model.mesh
    if mesh is None:
        raise ValueError("evaluation needs the mesh: the model file has none, pass mesh=")
    dev = _torch_device(device)
    wdev = _warp_device(dev)
    net = model.net.to(dev).eval()
    rng = np.random.default_rng(seed)
    res = {"vertices": int(len(mesh.vertices))}

    t0 = time.perf_counter()
    if reference is not None:
        vids, sids, gt = load_reference(reference, mesh)
        res["reference"] = os.path.basename(os.fspath(reference))
    else:
        from .geodesics import geodesic_distances

        vids = np.arange(len(mesh.vertices))
        sids = np.sort(rng.choice(len(vids), min(n_sources, len(vids)), replace=False))
        kw = {} if solver_k is None else {"k": solver_k}
        gt = geodesic_distances(mesh, mesh.index[sids], device=wdev, **kw)[:, mesh.index].astype(np.float64) * mesh.scale
        res["reference"] = "solver"
    res["ground_truth_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    pred = _predict_rows(net, mesh.normalized_vertices, vids, sids, dev)
    res["predict_s"] = time.perf_counter() - t0
    res["neurogf"] = _rel_stats(pred, gt)
    if heat:
        t0 = time.perf_counter()
        res["heat"] = _rel_stats(_heat(mesh, sids, vids), gt)
        res["heat"]["seconds"] = time.perf_counter() - t0
    if paths:
        res.update(_paths(model, mesh, rng, n_path_sources, n_path_targets, dev, wdev, solver_k, path_refine))
    if sdf:
        res.update(_sdf(model, mesh, rng, n_sdf, dev, wdev))
    if verbose:
        print(format_table(res))
    return res


def format_table(res: dict) -> str:
    rows = [("", "MRE", "max rel", "median", "p99", "pairs")]
    for name in ("neurogf", "heat"):
        if name in res:
            s = res[name]
            rows.append((name, f"{s['mre']:.3%}", f"{s['max_rel']:.2%}", f"{s['median_rel']:.3%}",
                         f"{s['p99_rel']:.2%}", str(s["pairs"])))
    w = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = [f"distances vs {res.get('reference')} ({res['vertices']} vertices)"]
    lines += ["  ".join(c.rjust(w[i]) for i, c in enumerate(r)) for r in rows]
    if "chamfer_l1" in res:
        lines.append(f"path Chamfer-L1 {res['chamfer_l1']:.4e} (median {res['chamfer_l1_median']:.4e}, "
                     f"{res['paths']} solver paths)")
    if "chamfer_l1_refined" in res:
        lines.append(f"path Chamfer-L1 after {res['refine_sweeps']} shortening sweeps {res['chamfer_l1_refined']:.4e} "
                     f"(median {res['chamfer_l1_refined_median']:.4e}, {res['refine_s']:.1f} s)")
    if "sdf_l1" in res:
        q = f", querier {res['querier_l1']:.4e}" if "querier_l1" in res else ""
        lines.append(f"SDF L1 {res['sdf_l1']:.4e}{q}")
    return "\n".join(lines)


def eval_main(argv=None) -> int:
    import argparse

    p = argparse.ArgumentParser(prog="neurogf-warp eval", description="Accuracy of a trained NeuroGF.")
    p.add_argument("model", help="model file (.ngf or a released _final.pth)")
    p.add_argument("--mesh", default=None, help="mesh file (default: the mesh stored in the model)")
    p.add_argument("--reference", default=None, help="exact-distance .npz (positions, orig_index, sources, dist)")
    p.add_argument("--heat", action="store_true", help="also run the heat method on the same sources")
    p.add_argument("--sources", type=int, default=8, help="solver sources when no reference is given")
    p.add_argument("--no-paths", action="store_true")
    p.add_argument("--no-sdf", action="store_true")
    p.add_argument("--path-refine", type=int, default=0, metavar="N",
                   help="also score the paths after N shortening sweeps per level on the SDF surface "
                        "(e.g. 50; slow on CPU)")
    p.add_argument("--device", default=None)
    p.add_argument("--json", default=None, help="also write the results here")
    a = p.parse_args(argv)
    try:
        res = evaluate(a.model, a.mesh, a.reference, heat=a.heat, n_sources=a.sources, paths=not a.no_paths,
                       sdf=not a.no_sdf, path_refine=a.path_refine, device=a.device)
    except (ValueError, OSError, IndexError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if a.json:
        with open(a.json, "w") as f:
            json.dump(res, f, indent=1)
    return 0
