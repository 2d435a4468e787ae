"""Accuracy of generalizable models on unseen shapes: trained model, released network, heat method, same pairs.

    python benchmarks/generalizable_eval.py --collection coll/ --model model.pt --device cuda:0 --json acc.json

Shape groups:
- the collection's held-out shapes (``test/`` of ``shapes.write_collection``; --max-shapes of them, by family):
  ground truth from the project's solver (``ngf.geodesic_distances``) for --sources random sources; the
  pairs are each source x --targets random vertices;
- the shared meshes stanford-bunny, fandisk and spot (never in the collection): the exact MMP distances of
  ``shared/reference/exact/<mesh>.npz`` (8 sources x --targets random vertices).
Methods on the same pairs (MRE = mean |d - d_gt| / d_gt, the source vertex itself excluded):
- ``trained``: --model (a file from ``generalizable.train``), conditioned on the mesh (2,048 points, seed 2024);
- ``released``: GenNeuroGF.pth, likewise;
- ``heat``: potpourri3d's heat method (defaults) on the mesh;
- ``per_mesh``: with --per-mesh-seconds S, a per-mesh NeuroGF trained for about S seconds on each shape
  (``ngf.train(mesh, out, budget_seconds=S)``, default preset for the device), queried with ``ngf.distance``;
  with --per-mesh-shapes K only on the first K collection shapes (and every shared mesh).
Times: conditioning (median over the shapes) and the pair query, per method, on --device.

The sources and pairs of a shape depend on its file name only (a seed from its CRC-32), not on which other
shapes are evaluated, so runs on different subsets (e.g. the per-mesh models in a second call) score the same
pairs and their rows can be merged (benchmarks/generalizable_collection.py merge).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
import zlib
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

import _bootstrap  # noqa: F401  (this checkout's neurogf_warp, installed or not)
from common import ROOT, write_json

SHARED_EVAL = ("stanford-bunny.obj", "fandisk.obj", "spot.obj")


def find_shared():
    env = os.environ.get("NEUROGF_SHARED")
    for base in ([Path(env)] if env else []) + [ROOT.parent / "shared", ROOT / "shared"]:
        if (base / "meshes").is_dir():
            return base
    return None


def shape_rng(name: str) -> np.random.Generator:
    """The random numbers of one shape's sources and pairs (independent of the other shapes evaluated)."""
    return np.random.default_rng([0, zlib.crc32(name.encode())])


def pairs_for(nv, sources, targets, rng):
    return [(s, rng.choice(np.setdiff1d(np.arange(nv), [s]), targets, replace=False)) for s in sources]


def mre_table(rows, cols, title: str) -> tuple[str, dict]:
    """(printed table, summary {group: {method: mean MRE}}): one line per group ("unseen:<family>", "all unseen",
    "shared") and per shared mesh. A method evaluated on only some of a group's shapes (per-mesh models on a
    few) is averaged over those, and the count is shown beside it."""
    groups = sorted({r["group"] for r in rows}, key=lambda g: (g == "shared", g))
    lines = [title, f"{'group':<24}{'shapes':>7}" + "".join(f"{c:>16}" for c in cols)]
    summary = {}

    def cell(rs, c):
        have = [r[c] for r in rs if r.get(c) is not None]
        if not have:
            return None, f"{'-':>16}"
        v = float(np.mean(have))
        tag = "" if len(have) == len(rs) else f" ({len(have)})"
        return v, f"{f'{100 * v:.2f}%{tag}':>16}"

    for g in groups + ["all unseen"]:
        rs = [r for r in rows if (r["group"] == g if not g.startswith("all") else r["group"].startswith("unseen"))]
        if not rs:
            continue
        cells = [cell(rs, c) for c in cols]
        summary[g] = {c: v for c, (v, _) in zip(cols, cells) if v is not None}
        summary[g]["shapes"] = len(rs)
        lines.append(f"{g:<24}{len(rs):>7}" + "".join(t for _, t in cells))
    for r in rows:
        if r["group"] == "shared":
            lines.append(f"{'  ' + r['shape']:<24}{1:>7}" + "".join(cell([r], c)[1] for c in cols))
    return "\n".join(lines), summary


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--collection", default=None)
    ap.add_argument("--model", default=None)
    ap.add_argument("--released", default=None)
    ap.add_argument("--device", default=None)
    ap.add_argument("--sources", type=int, default=8)
    ap.add_argument("--targets", type=int, default=512)
    ap.add_argument("--max-shapes", type=int, default=30)
    ap.add_argument("--no-heat", action="store_true")
    ap.add_argument("--per-mesh-seconds", type=float, default=None,
                    help="also train a per-mesh model for each shape with this budget (e.g. 60)")
    ap.add_argument("--per-mesh-shapes", type=int, default=None,
                    help="per-mesh models only for the first K collection shapes (and every shared mesh)")
    ap.add_argument("--no-shared", action="store_true", help="skip the shared meshes")
    ap.add_argument("--table", default=None, help="also write the printed table to this file")
    ap.add_argument("--work", default=None, help="folder for the per-mesh models (default: a temporary one)")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)

    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    import neurogf_warp as ngf
    from neurogf_warp.generalizable.model import load

    shared = find_shared()
    methods = {}
    if a.model:
        methods["trained"] = load(a.model)
    rel = a.released or (shared / "checkpoints" / "official" / "GenNeuroGF.pth" if shared else None)
    if rel and Path(rel).exists():
        methods["released"] = load(rel)
    dev = wp.get_device(a.device)

    cases = []  # (group, name, mesh, [(src, tgt idx, gt dist)])
    if a.collection:
        coll = Path(a.collection)
        man = json.loads((coll / "manifest.json").read_text()) if (coll / "manifest.json").exists() else None
        files = sorted((coll / "test").glob("*.obj")) if (coll / "test").is_dir() else sorted(coll.glob("*.obj"))
        files = files[: a.max_shapes]
        for f in files:
            mesh = ngf.load_mesh(str(f))
            nv = len(mesh.internal_vertices)
            rng = shape_rng(f.name)
            src = rng.choice(nv, a.sources, replace=False)
            d = ngf.geodesic_distances(mesh, mesh.index[src], device=dev)[:, mesh.index]
            parts = f.stem.split("_", 2)  # shapes.write_collection's names: shape_<number>_<family>
            fam = parts[2] if (man or len(parts) == 3 and parts[0] == "shape") and len(parts) == 3 else "collection"
            cases.append(("unseen:" + fam, f.name, mesh,
                          [(s, t, d[i, t]) for i, (s, t) in enumerate(pairs_for(nv, src, a.targets, rng))]))
    if shared and not a.no_shared:
        for name in SHARED_EVAL:
            z = np.load(shared / "reference" / "exact" / name.replace(".obj", ".npz"))
            mesh = ngf.load_mesh(str(shared / "meshes" / name))
            assert np.abs(mesh.internal_vertices - z["positions"]).max() < 1e-5 * np.abs(z["positions"]).max()
            nv = len(mesh.internal_vertices)
            prs = pairs_for(nv, z["sources"], a.targets, shape_rng(name))
            cases.append(("shared", name, mesh, [(s, t, z["dist"][i, t]) for i, (s, t) in enumerate(prs)]))

    rows = []
    n_coll = 0
    for group, name, mesh, prs in cases:
        V = np.asarray(mesh.internal_vertices)
        S = np.concatenate([np.repeat(V[s][None], len(t), 0) for s, t, _ in prs])
        T = np.concatenate([V[t] for _, t, _ in prs])
        gt = np.concatenate([g for _, _, g in prs]).astype(np.float64)
        ok = np.isfinite(gt) & (gt > 0)
        row = {"group": group, "shape": name, "vertices": len(V), "pairs": int(ok.sum())}
        for mname, model in methods.items():
            wp.synchronize_device(dev)
            t0 = time.perf_counter()
            cond = model.condition(mesh, device=dev)
            wp.synchronize_device(dev)
            t1 = time.perf_counter()
            d = cond.distance(S, T)
            t2 = time.perf_counter()
            row[mname] = float(np.mean(np.abs(d[ok] - gt[ok]) / gt[ok]))
            row[mname + "_condition_ms"] = (t1 - t0) * 1e3
            row[mname + "_query_ms"] = (t2 - t1) * 1e3
        if not a.no_heat:
            import potpourri3d as pp3d

            t0 = time.perf_counter()
            solver = pp3d.MeshHeatMethodDistanceSolver(V, np.asarray(mesh.internal_faces))
            hd = np.concatenate([solver.compute_distance(int(s))[t] for s, t, _ in prs])
            row["heat"] = float(np.mean(np.abs(hd[ok] - gt[ok]) / gt[ok]))
            row["heat_ms"] = (time.perf_counter() - t0) * 1e3
        n_coll += group != "shared"
        if a.per_mesh_seconds and (a.per_mesh_shapes is None or group == "shared" or n_coll <= a.per_mesh_shapes):
            import tempfile

            work = Path(a.work or tempfile.mkdtemp(prefix="gen_eval_"))
            work.mkdir(parents=True, exist_ok=True)  # ngf.train writes into an existing folder only
            out = work / (Path(name).stem + ".ngf")
            t0 = time.perf_counter()
            try:
                pm = ngf.train(mesh, out, device=str(dev), budget_seconds=a.per_mesh_seconds, progress=False)
                row["per_mesh_train_s"] = time.perf_counter() - t0
                d = np.asarray(ngf.distance(pm, S, T), np.float64)
                row["per_mesh"] = float(np.mean(np.abs(d[ok] - gt[ok]) / gt[ok]))
            except Exception as e:  # noqa: BLE001 - one failed model must not lose the other rows
                row["per_mesh_error"] = f"{type(e).__name__}: {e}"
        rows.append(row)
        print(json.dumps(row), flush=True)
        if a.json:  # rows so far (a run stopped by a time limit keeps them); the summary comes at the end
            Path(a.json).write_text(json.dumps({"rows": rows, "partial": True, "device": str(dev),
                                                "args": vars(a)}, indent=1))

    cols = list(methods) + ([] if a.no_heat else ["heat"]) + (["per_mesh"] if a.per_mesh_seconds else [])
    text, summary = mre_table(rows, cols, f"MRE on the same pairs ({datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC, "
                                          f"device {dev})")
    print("\n" + text, flush=True)
    if a.table:
        Path(a.table).write_text(text + "\n")
    if a.json:
        write_json(a.json, {"rows": rows, "summary": summary, "device": str(dev), "args": vars(a)},
                   "generalizable_eval", str(dev))
    return 0


if __name__ == "__main__":
    sys.exit(main())
