"""Accuracy of a trained NeuroGF (reference §6): distance MRE / max relative error, path Chamfer-L1, SDF L1.

Predictions come from the public queries (``ssad``, ``path``, ``sdf``: what a user gets). Distance ground
truth is an exact reference file (keys positions, orig_index or file_index, sources, dist; see
shared/reference/README.md) when given, else our geodesic solver from a few random vertices; paths are
compared with solver paths, SDF values with ``dataset.sdf_truth``. Pairs in different connected components
(exact distance inf) are reported apart: the model must answer inf there. The heat method (potpourri3d) can
run on the same sources for comparison. Relative errors are unit-free; Chamfer-L1 and SDF L1 are in the
normalized unit-sphere frame, as in the paper.
"""
from __future__ import annotations

import dataclasses
import os
import time
from typing import TYPE_CHECKING

import numpy as np

from neurogf_warp.dataset.heat import HEAT_HINT, heat_distances, require_heat  # noqa: F401 - re-exported
from neurogf_warp.common.checks import InputError
from neurogf_warp.evaluation import metrics
from neurogf_warp.mesh.mesh import Mesh, load_mesh

if TYPE_CHECKING:
    from neurogf_warp.model.model import Model

__all__ = ["evaluate", "load_reference", "format_table", "require_heat", "json_safe"]

REFERENCE_HELP = ("a distance reference is an .npz with arrays sources (S,), dist (S, Vr) and file_index or "
                  "orig_index (Vr,), plus positions (Vr, 3), which may be left out when it covers every vertex of "
                  "the mesh (shared/reference/README.md)")


def load_reference(path: "str | os.PathLike", mesh: Mesh) -> tuple:
    """Exact distances of a reference ``.npz`` on the mesh's internal vertices.

    Parameters
    ----------
    path : str or os.PathLike
        An ``.npz`` with ``sources`` (S,) indexing its vertices, ``dist`` (S, Vr) in mesh units, and
        ``file_index`` (the file's vertex numbering) or ``orig_index`` (trimesh's, unused vertices dropped),
        (Vr,). ``positions`` (Vr, 3) confirm it belongs to ``mesh``; without them the reference must cover
        every vertex that a face uses (Vr = the mesh's used vertices), numbered by ``file_index`` (or by
        ``orig_index`` on a mesh with no unused vertices, where both numberings agree).
    mesh : Mesh
        The mesh evaluated on.

    Returns
    -------
    vertex_ids : (Vr,) int64 internal vertex ids; source_ids : (S,) int64 internal ids;
    dist : (S, Vr) float64 exact distances in mesh units (inf between components).

    Raises
    ------
    InputError (a ValueError)
        The file is not a reference (a mesh file, another ``.npz``) or belongs to another mesh.
    """
    from neurogf_warp.common.files import check_input_file
    from neurogf_warp.dataset.build import read_npz
    from neurogf_warp.mesh.files import MESH_SUFFIXES

    path = check_input_file(path, "reference file")
    with open(path, "rb") as fh:
        head = fh.read(4)
    if head[:2] != b"PK":  # every .npz is a zip archive
        mesh_like = os.path.splitext(path)[1].lower() in MESH_SUFFIXES or head[:3] == b"ply"
        what = "a mesh file" if mesh_like else "not an .npz file"
        raise InputError(f"reference {path} is {what}, not a distance reference: {REFERENCE_HELP}"
                         + ("; the mesh itself goes to mesh= (--mesh)" if mesh_like else ""))
    data = read_npz(path, "reference")
    missing = [k for k in ("sources", "dist") if k not in data]
    if missing or not ({"orig_index", "file_index"} & set(data)):
        raise InputError(f"{path} is not a distance reference (missing {missing or ['file_index/orig_index']}): "
                         f"{REFERENCE_HELP}")
    src, dist = data["sources"].astype(np.int64), data["dist"]
    pos = data.get("positions")
    used = len(mesh.internal_vertices)
    tol = 1e-4 * max(1.0, float(np.abs(pos).max()) if pos is not None and len(pos) else 1.0)
    for key in ("file_index", "orig_index"):  # whichever numbering this mesh's loader uses
        if key not in data:
            continue
        if pos is None and key == "orig_index" and mesh.n_input != used:
            continue  # trimesh's numbering differs from the file's here, and nothing can tell them apart
        idx = data[key].astype(np.int64).reshape(-1)
        if len(idx) and (idx.min() < 0 or idx.max() >= mesh.n_input):
            continue
        inv = mesh.input_to_internal[idx] if len(idx) else idx
        if np.any(inv < 0):
            continue
        if pos is None:
            fits = len(np.unique(inv)) == used
        else:
            fits = len(inv) == 0 or (pos.shape == (len(inv), 3)
                                     and np.abs(mesh.internal_vertices[inv] - pos).max() <= tol)
        if fits:
            if src.size and (src.min() < 0 or src.max() >= len(inv)):
                raise InputError(f"{path}: source ids must index its {len(inv)} vertices")
            if dist.shape != (len(src), len(inv)):
                raise InputError(f"{path}: dist has shape {dist.shape}, expected ({len(src)}, {len(inv)})")
            return inv, inv[src], dist.astype(np.float64)
    if pos is None:
        raise InputError(f"{path} has no positions and its {key} does not cover the {used} vertices this mesh's faces "
                         "use: it is a reference for another mesh, or a part of one (store positions to use a part)")
    raise InputError(f"{path} is a reference for another mesh: its {len(pos)} vertices do not match this mesh "
                     f"({mesh.n_input} vertices as given, {used} used by faces)")


def _with_mesh(model, mesh):
    """The model with the mesh to evaluate on attached (a model without one answers in the mesh's frame)."""
    if mesh is None:
        if model.mesh is None:
            raise ValueError("evaluation needs the mesh: the model file has none, pass mesh=")
        return model, model.mesh
    m = load_mesh(mesh)
    if model.mesh is None:
        return dataclasses.replace(model, mesh=m, center=m.center, scale=m.scale, _states={}), m
    if model.mesh.fingerprint != m.fingerprint:
        raise ValueError("the model was trained on another mesh than the one given (fingerprints differ); "
                         "evaluate it on its own mesh")
    return model, model.mesh


def _bar(total: int, desc: str, on: bool, unit: str = "source"):
    from neurogf_warp.common.progress import Progress

    return Progress(total, desc, unit=unit, on=on, leave=False)


def _solver_truth(mesh: Mesh, sids, k, device, progress):
    from neurogf_warp.dataset.build import solver_batch
    from neurogf_warp.ground_truth.geodesics import GeodesicSolver
    from neurogf_warp.ground_truth.near_source import refine_near_sources

    kw = {} if k is None else {"k": k}
    solver = GeodesicSolver(mesh, device=device, max_rows=len(sids), batch=solver_batch(None, device), **kw)
    out = np.empty((len(sids), len(mesh.internal_vertices)), np.float64)
    with _bar(len(sids), "ground truth", progress) as bar:
        for i in range(0, len(sids), solver.batch):
            s = sids[i: i + solver.batch]
            # at the default accuracy, as ngf.geodesic_distances: the near-source patches take the solver's worst
            # pairs (short ones, up to 1.4% too long) under 0.5%, so they do not count as the model's error
            d = solver.solve(s)
            out[i: i + solver.batch] = d if k is not None else refine_near_sources(solver, s, d)
            bar.update(len(s))
    return out / mesh.scale


def _predict(model, mesh: Mesh, vids, sids, device, progress):
    """The model's SSAD from each source to the given vertices: (S, Vr) float64, mesh units."""
    from neurogf_warp.inference.queries import ssad

    out = np.empty((len(sids), len(vids)), np.float64)
    cols = mesh.index[vids]
    with _bar(len(sids), "predictions", progress) as bar:
        for i, s in enumerate(sids):
            out[i] = np.asarray(ssad(model, int(mesh.index[s]), device=device), dtype=np.float64)[cols]
            bar.update(1)
    return out


def _rel_stats(pred, gt) -> dict:
    """Relative errors over the finite-truth pairs (source excluded), and how the other pairs were answered."""
    ok = np.isfinite(gt) & (gt > 0)
    bad = ok & ~np.isfinite(pred)
    per = [metrics.relative_errors(p[o & np.isfinite(p)], g[o & np.isfinite(p)]) for p, g, o in zip(pred, gt, ok)]
    r = np.concatenate(per) if per else np.zeros(0)
    if not r.size:
        return {"pairs": 0, "nonfinite": int(bad.sum())}
    return {"mre": float(r.mean()), "max_rel": float(r.max()), "median_rel": float(np.median(r)),
            "p99_rel": float(np.percentile(r, 99)), "pairs": int(r.size), "nonfinite": int(bad.sum()),
            "per_source_mre": [float(x.mean()) if x.size else None for x in per]}


def _heat(mesh: Mesh, source_ids, vertex_ids, progress):
    """Heat-method distances (potpourri3d defaults) from each source: (S, Vr) float64, mesh units."""
    require_heat()
    with _bar(len(source_ids), "heat method", progress) as bar:
        d = heat_distances(mesh.internal_normalized_vertices, mesh.internal_faces, source_ids,
                           on_row=lambda: bar.update(1))
    return d[:, vertex_ids] / mesh.scale


def _paths(model, mesh: Mesh, rng, n_sources, n_targets, device, k, refine, progress) -> dict:
    """Chamfer-L1 of ``path(model, p, q, m=128)`` against solver paths between random vertex pairs of one
    component; with ``refine`` > 0 also after that many shortening sweeps per level."""
    from neurogf_warp.ground_truth.geodesics import geodesic_paths
    from neurogf_warp.inference.queries import path

    V, comp = len(mesh.internal_vertices), mesh.internal_components
    gts = []
    with _bar(n_sources, "solver paths", progress) as bar:
        for s in rng.choice(V, min(n_sources, V), replace=False):
            same = np.flatnonzero(comp == comp[s])
            same = same[same != s]
            bar.update(1)
            if not len(same):
                continue
            tg = rng.choice(same, min(n_targets, len(same)), replace=False)
            kw = {} if k is None else {"k": k}
            g = geodesic_paths(mesh, mesh.index[s], mesh.index[tg], m=128, device=device, **kw)
            gts.append(g[np.isfinite(g).all(axis=(1, 2))])
    gt = np.concatenate(gts) if gts else np.zeros((0, 128, 3))
    if not len(gt):
        return {"paths": 0}
    norm = lambda x: mesh.normalize(x.reshape(-1, 3)).reshape(x.shape)  # noqa: E731
    chunk = 64 if str(device).startswith("cuda") else 8

    def predicted(sweeps, desc):
        out = np.empty(gt.shape, np.float64)
        with _bar(len(gt), desc, progress, unit="path") as bar:
            for i in range(0, len(gt), chunk):
                out[i: i + chunk] = path(model, gt[i: i + chunk, 0], gt[i: i + chunk, -1], m=128, refine=sweeps,
                                         device=device)
                bar.update(len(gt[i: i + chunk]))
        return norm(out)

    res = {"paths": int(len(gt))}
    res.update(_chamfer(metrics.chamfer_l1(predicted(0, "paths"), norm(gt)), "chamfer_l1"))
    if refine:
        t0 = time.perf_counter()
        res.update(_chamfer(metrics.chamfer_l1(predicted(int(refine), f"paths, {refine} sweeps"), norm(gt)),
                            "chamfer_l1_refined"))
        res.update(refine_sweeps=int(refine), refine_s=time.perf_counter() - t0)
    return res


def _chamfer(cd: np.ndarray, key: str) -> dict:
    """Mean and median Chamfer-L1 over the predicted paths that are finite; the others counted, with the reason.

    ``path()`` answers a NaN row when it finds the two ends on different connected parts of the mesh, which can
    happen on a mesh of several parts although the solver's path joins them; such a row has no Chamfer distance.
    """
    ok = np.isfinite(cd)
    out = {key: float(cd[ok].mean()) if ok.any() else None,
           f"{key}_median": float(np.median(cd[ok])) if ok.any() else None,
           f"{key}_nonfinite": int((~ok).sum())}
    if not ok.all():
        left = f"the value is over the other {int(ok.sum())}" if ok.any() else "no path is left to score"
        out[f"{key}_note"] = (f"{int((~ok).sum())} of {len(cd)} predicted paths are NaN (path() found their two "
                              f"ends on different parts of the mesh); {left}")
    return out


def json_safe(value):
    """``value`` with every NaN or infinite float replaced by None, so that ``json.dumps`` writes valid JSON
    (the results keep a ``*_note`` or count beside each value that can be missing, saying why)."""
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if np.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


def _sdf(model, mesh: Mesh, rng, n, device) -> dict:
    import torch

    from neurogf_warp.dataset.build import sample_sdf_points, sdf_truth, surface_samples
    from neurogf_warp.inference.queries import sdf

    pts = sample_sdf_points(rng, surface_samples(mesh, max(n, 30000), rng), n)
    gt = np.asarray(sdf_truth(mesh, pts, device=device), dtype=np.float64)
    pred = np.asarray(sdf(model, mesh.denormalize(pts), device=device), dtype=np.float64) * mesh.scale
    out = {"sdf_l1": float(np.abs(pred - gt).mean())}
    if model.querier is not None:
        with torch.no_grad():
            q = model.querier.cpu().eval()(torch.as_tensor(pts)).double().numpy()
        out["querier_l1"] = float(np.abs(q - gt).mean())
    return out


def evaluate(model: "Model | str | os.PathLike", mesh=None, reference: "str | os.PathLike | None" = None, *,
             heat: bool = False, n_sources: int = 8,
             n_path_sources: int = 8, n_path_targets: int = 8, n_sdf: int = 30000, paths: bool = True,
             sdf: bool = True, solver_k: int | None = None, path_refine: int = 0, surface: int = 0, device=None,
             seed: int = 0, progress: bool = False, verbose: bool = True) -> dict:
    """Accuracy of ``model`` on ``mesh``.

    Parameters
    ----------
    model : a Model or a model file (``.ngf``, or a released ``_final.pth`` with ``mesh``)
    mesh : the mesh (default: the model's own); a model that has one must be evaluated on it
    reference : exact-distance ``.npz`` (else the solver from ``n_sources`` random vertices)
    heat : also run the heat method (needs potpourri3d, the ``heat`` extra) on the same sources
    n_path_sources, n_path_targets : random path pairs, each within one connected component
    solver_k : Steiner points per edge for the solver's distances and paths (None: its default)
    path_refine : also score the paths after that many shortening sweeps per level (``path(..., refine=)``)
    surface : also reconstruct the SDF head's surface on a grid of this many samples along the longest side
        (``reconstruct``; 0: not) and measure its Chamfer-L1 and Hausdorff distance to the mesh, in mesh units
    device : Warp device of every query and of the solver
    progress : progress bars on stderr; verbose : print the table

    Returns
    -------
    dict: ``neurogf`` (and ``heat``) with mre / max_rel / median_rel / p99_rel as fractions over the pairs of
    finite exact distance, ``nonfinite`` predictions among them; ``cross_component`` with the pairs of infinite
    exact distance and how many of them the model answered finite (they must be inf); ``chamfer_l1`` (normalized
    frame) and ``sdf_l1``; with ``surface``, ``surface`` holds ``chamfer_l1`` and ``hausdorff`` (mesh units) of
    the reconstruction; timings in seconds.
    """
    from neurogf_warp.common.arrays import resolve_device

    if heat:
        require_heat()  # before any work
    if not isinstance(path_refine, (int, np.integer)) or path_refine < 0:
        raise ValueError(f"path_refine must be an integer >= 0, got {path_refine!r}")
    from neurogf_warp.model.model import Model

    if isinstance(model, (str, bytes, os.PathLike)):
        from neurogf_warp.model.files import load

        model = load(model, mesh=mesh)
    if not isinstance(model, Model):  # a generalizable network (conditioned or not) has no SDF or path head
        raise InputError(f"evaluate needs a per-mesh model (ngf.load('x.ngf'), or a model file path), got "
                         f"{type(model).__name__}")
    model, mesh = _with_mesh(model, mesh)
    dev = str(resolve_device(device))
    rng = np.random.default_rng(seed)
    res = {"vertices": int(len(mesh.internal_vertices))}

    t0 = time.perf_counter()
    if reference is not None:
        vids, sids, gt = load_reference(reference, mesh)
        res["reference"] = os.path.basename(os.fspath(reference))
    else:
        vids = np.arange(len(mesh.internal_vertices))
        sids = np.sort(rng.choice(len(vids), min(n_sources, len(vids)), replace=False))
        gt = _solver_truth(mesh, sids, solver_k, dev, progress)
        res["reference"] = "solver"
    res["ground_truth_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    pred = _predict(model, mesh, vids, sids, dev, progress)
    res["predict_s"] = time.perf_counter() - t0
    res["neurogf"] = _rel_stats(pred, gt)
    cross = np.isinf(gt)
    res["cross_component"] = {"pairs": int(cross.sum()), "finite": int(np.isfinite(pred[cross]).sum())}
    if heat:
        t0 = time.perf_counter()
        res["heat"] = _rel_stats(_heat(mesh, sids, vids, progress), gt)
        res["heat"]["seconds"] = time.perf_counter() - t0
    if paths:
        res.update(_paths(model, mesh, rng, n_path_sources, n_path_targets, dev, solver_k, path_refine, progress))
    if sdf:
        res.update(_sdf(model, mesh, rng, n_sdf, dev))
    if surface:
        from neurogf_warp.inference.reconstruct import reconstruct, surface_distances

        t0 = time.perf_counter()
        rv, rf = reconstruct(model, resolution=int(surface), device=dev)
        res["surface"] = {"resolution": int(surface), "triangles": int(len(rf)),
                          **surface_distances(rv, rf, mesh.internal_vertices, mesh.internal_faces, seed=seed),
                          "seconds": time.perf_counter() - t0}
    res = json_safe(res)  # valid JSON as it is: a missing value is None, with its reason beside it
    if verbose:
        print(format_table(res))
    return res


def format_table(res: dict) -> str:
    """The results of ``evaluate`` as a few lines of text."""
    rows = [("", "MRE", "max rel", "median", "p99", "pairs")]
    for name in ("neurogf", "heat"):
        s = res.get(name)
        if s and "mre" in s:
            rows.append((name, f"{s['mre']:.3%}", f"{s['max_rel']:.2%}", f"{s['median_rel']:.3%}",
                         f"{s['p99_rel']:.2%}", str(s["pairs"])))
    w = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = [f"distances vs {res.get('reference')} ({res['vertices']} vertices)"]
    lines += ["  ".join(c.rjust(w[i]) for i, c in enumerate(r)) for r in rows]
    if res.get("neurogf", {}).get("nonfinite"):
        lines.append(f"warning: {res['neurogf']['nonfinite']} predictions are not finite where the exact distance is")
    cc = res.get("cross_component", {})
    if cc.get("pairs"):
        lines.append(f"pairs in different components: {cc['pairs']} (exact distance inf); the model answered "
                     f"{cc['finite']} of them with a finite distance" + (" (must be 0)" if cc["finite"] else ""))
    refined = f"path Chamfer-L1 after {res.get('refine_sweeps')} shortening sweeps"
    for key, what in (("chamfer_l1", "path Chamfer-L1"), ("chamfer_l1_refined", refined)):
        if key not in res:
            continue
        if res[key] is None:
            lines.append(f"{what}: none ({res.get(key + '_note', 'no finite predicted path')})")
            continue
        tail = f"{res['paths']} solver paths" if key == "chamfer_l1" else f"{res['refine_s']:.1f} s"
        lines.append(f"{what} {res[key]:.4e} (median {res[key + '_median']:.4e}, {tail})")
        if res.get(key + "_note"):
            lines.append(f"note: {res[key + '_note']}")
    if "sdf_l1" in res:
        q = f", querier {res['querier_l1']:.4e}" if "querier_l1" in res else ""
        lines.append(f"SDF L1 {res['sdf_l1']:.4e}{q}")
    srf = res.get("surface")
    if srf and srf.get("chamfer_l1") is not None:
        lines.append(f"reconstructed surface ({srf['resolution']} samples, {srf['triangles']} triangles): Chamfer-L1 "
                     f"{srf['chamfer_l1']:.4e}, Hausdorff {srf['hausdorff']:.4e} (mesh units)")
    elif srf:
        lines.append(f"reconstructed surface: none ({srf.get('note', 'no triangles')})")
    return "\n".join(lines)
