"""Bake-off of field designs for accuracy per second: each design trained under the same time budget as the
default, scored against exact geodesics.

    python benchmarks/bakeoff.py --device cuda:0 --shared /path/to/shared --meshes bunny spot --budgets 20 60

A design is a set of training settings (``VARIANTS``: the default, ``norm=none``, ``hash_levels=12``,
``landmarks=K`` for K in 32..256). Per (mesh, budget, design): ``ngf.train(mesh, out, budget_seconds=B,
device=..., force=True, **design)``, timed whole, each row in a fresh process (``--same-process``: all in this
one) after an untimed warm-up call (Warp's kernels compiled and cached on disk), the designs of one (mesh,
budget) back to back so that a drift of the machine touches each alike (``--gpus N``: side by side, one row per
GPU, each process with 1/N of the CPU cores). Every design runs with
``compile=False``: on a machine that has not compiled these shapes before, the 20-60 s default rows run eagerly
anyway (the budget planner's choice), and a design must not win or lose through a compile cache. Meshes: the
shared ones (``--shared``) and ``scan``, ``parts``, ``cad``, ``joined`` from ``benchmarks/unseen_meshes.py``
(``--unseen``); ``joined`` trains with ``allow_vertex_joins=True`` (a default call refuses it).

Accuracy: the trained network's distances from each source of the exact reference to every reference vertex,
computed with torch (eval mode, fp32, raised to the straight-line distance as the public queries do), MRE, p99
and max relative error, source excluded (``evaluation.evaluate._rel_stats``). The Warp inference engine reads
only the default design, so torch scores every design alike; on default rows the engine's own
``ngf.evaluate`` runs too, as a check of that scoring.

Decision rule, fixed before any run: a design is kept only if, on every mesh and at every budget tried, its MRE is
lower than the default's by more than the run-to-run spread: MRE_design < MRE_default - spread_B, where
MRE_default is the mean of the default's runs on that mesh and budget and spread_B is the largest difference
between two default runs of the same mesh at budget B (the default runs twice on ``--repeat`` meshes). Otherwise
it is not kept.

Writes ``<out>/bakeoff.json`` (every row: errors, steps, step times, peak GPU memory, model size: the
parameters' ``model_mb`` and a landmark design's (V, K) float32 distance table, ``table_mb``) and
``<out>/bakeoff.png`` (MRE against the budget, one panel per mesh).
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import shutil
import sys
import time
import traceback
import warnings
from pathlib import Path

import _bootstrap  # noqa: E402,F401  (this checkout's neurogf_warp, installed or not)

ROOT = Path(__file__).resolve().parents[1]

VARIANTS = {
    "default": {},
    "no_bn": {"norm": "none"},
    "hash": {"hash_levels": 12},
    "landmarks32": {"landmarks": 32},
    "landmarks64": {"landmarks": 64},
    "landmarks128": {"landmarks": 128},
    "landmarks256": {"landmarks": 256},
    "landmarks": {"landmarks": "scaled"},  # K by the mesh's size: scaled_landmarks()
    "landmarks_nofloor": {"landmarks": "scaled", "landmark_floor": 0.0},  # the landmarks only as the head's inputs
    "landmarks_bracket": {"landmarks": "scaled", "landmark_bracket": True},  # between the landmarks' two bounds
    "landmarks_bracket256": {"landmarks": 256, "landmark_bracket": True},  # the same, twice the landmarks below 100K
    "landmarks_bracket256_log": {"landmarks": 256, "landmark_bracket": True, "landmark_bracket_log": True},  # geometric
    "landmarks_bracket256_pair": {"landmarks": 256, "landmark_bracket": True, "landmark_pair_inputs": True},
    "landmarks_bracket256_hard": {"landmarks": 256, "landmark_bracket": True, "hard_share": 0.25},  # + hard pairs
    "no_graphs": {"cuda_graph": False},  # today's network with eager CUDA steps: no graph captures in the set-up
    "plain_adamw": {"optimizer": "plain"},  # today's network, AdamW without torch.optim (training/adamw.py)
}
COMMON = {"compile": False}
os.environ["NEUROGF_BAKEOFF_DESIGNS"] = "1"  # the designs the package refuses for users (no inference backend runs them)
UNSEEN = ("scan", "parts", "cad", "joined")  # benchmarks/unseen_meshes.py's meshes, read from --unseen DIR
JOINED = {"joined"}  # patches that meet at single vertices: trained with allow_vertex_joins=True
MESHES = {"spot": "spot.obj", "cow": "cow.obj", "alligator": "alligator.obj", "homer": "homer.obj",
          "fandisk": "fandisk.obj", "cheburashka": "cheburashka.obj", "rocker-arm": "rocker-arm.obj",
          "bunny": "stanford-bunny.obj", "igea": "igea.ply"}


def _run_doc(meta: dict, rows: list) -> dict:
    """One process's rows with the provenance block that benchmarks/make_performance.py reads."""
    prov = {"command": "python benchmarks/bakeoff.py " + " ".join(meta["argv"]), "device": meta["device"],
            "device_name": meta["gpu"], "driver": None, "warp": meta["warp"], "torch": meta["torch"],
            "python": meta["python"], "date_utc": meta["date_utc"], "commit": meta["commit"], "dirty": False,
            "cpu_cores": meta["cpu_cores"]}
    return {"provenance": prov, "meta": meta, "rows": rows}


def _reference(shared: Path, name: str) -> Path:
    return shared / "reference" / "exact" / (Path(MESHES[name]).stem + ".npz")


def mesh_files(a, name: str) -> tuple:
    """(mesh file, exact reference .npz) of a shared mesh or of one of ``unseen_meshes.py``'s (``--unseen``)."""
    if name in UNSEEN:
        if not a.unseen:
            raise SystemExit(f"mesh {name!r} is one of benchmarks/unseen_meshes.py's: pass --unseen DIR (its --out)")
        return Path(a.unseen) / f"{name}.ply", Path(a.unseen) / "reference" / f"{name}.npz"
    shared = Path(a.shared)
    return shared / "meshes" / MESHES[name], _reference(shared, name)


def torch_errors(model, reference, device) -> dict:
    """Relative errors of ``model``'s distances from the reference's sources to its vertices (torch, fp32)."""
    import numpy as np
    import torch

    from neurogf_warp.evaluation.evaluate import _rel_stats, load_reference

    mesh = model.mesh
    vids, sids, gt = load_reference(reference, mesh)
    net = model.net.to(device).eval()
    scale = float(model.scale)
    # internal numbering, as load_reference's ids (mesh.vertices is the file's numbering, unused vertices NaN)
    if getattr(net, "landmarks", 0):  # its table is looked up by the training's own float32 vertex array
        x = net.landmark_table.xyz.to(device)
    else:
        x = torch.as_tensor((mesh.internal_vertices - np.asarray(model.center)) * scale, dtype=torch.float32,
                            device=device)
    prev = torch.backends.cuda.matmul.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = False
    try:
        with torch.no_grad():
            e = torch.cat([net.embed(c) for c in x.split(65536)])
            v = torch.as_tensor(vids, device=device)
            ev, xv = e[v], x[v]
            pred = []
            for s in sids:
                xs = x[int(s)].expand_as(xv)
                d = net.distance_from_embeddings(e[int(s)].expand_as(ev), ev, xs, xv)
                d = torch.maximum(d, torch.linalg.vector_norm(xs - xv, dim=-1))  # as the public queries answer
                pred.append(d / scale)
            pred = torch.stack(pred).double().cpu().numpy()
    finally:
        torch.backends.cuda.matmul.allow_tf32 = prev
        net.cpu()
    out = _rel_stats(pred, gt)
    out["by_distance"] = by_distance(pred, gt, mean_edge(mesh))
    return out


DISTANCE_BINS = (0, 2, 5, 10, 20, float("inf"))  # pair distance in mean edge lengths


def mean_edge(mesh) -> float:
    """The mesh's mean edge length (mesh units), over the faces' three edges."""
    import numpy as np

    p, f = mesh.internal_vertices, mesh.internal_faces
    return float(np.mean([np.linalg.norm(p[f[:, a]] - p[f[:, b]], axis=1).mean() for a, b in ((0, 1), (1, 2), (2, 0))]))


def by_distance(pred, gt, edge: float) -> list:
    """Relative errors of the finite-truth pairs (source excluded) by the pair's exact distance in mean edge
    lengths (``DISTANCE_BINS``): per bin its pairs, MRE, p99, max and share of the summed error."""
    import numpy as np

    ok = np.isfinite(gt) & (gt > 0) & np.isfinite(pred)
    rel = np.abs(pred[ok] - gt[ok]) / gt[ok]
    hops, total = gt[ok] / edge, max(float(rel.sum()), 1e-300)
    out = []
    for lo, hi in zip(DISTANCE_BINS[:-1], DISTANCE_BINS[1:]):
        r = rel[(hops >= lo) & (hops < hi)]
        out.append({"edges": [lo, None if hi == float("inf") else hi], "pairs": int(r.size),
                    **({"mre": float(r.mean()), "p99": float(np.percentile(r, 99)), "max": float(r.max()),
                        "error_share": float(r.sum()) / total} if r.size else {})})
    return out


def scaled_landmarks(vertices: int) -> int:
    """K of the ``landmarks`` variant: 128 below 100K vertices, 256 above (on the 134K igea 256 landmarks beat the
    default where 128 tied with it)."""
    return 128 if vertices < 100_000 else 256


def row_settings(name: str, variant: str, vertices: int | None = None) -> dict:
    """The ``ngf.train`` settings of one row (``vertices``: the mesh's, for a design sized to it)."""
    s = {**COMMON, **VARIANTS[variant], **({"allow_vertex_joins": True} if name in JOINED else {})}
    if s.get("landmarks") == "scaled" and vertices is not None:
        s["landmarks"] = scaled_landmarks(vertices)
    return s


def run_row(ngf, name: str, budget: float, variant: str, a, work: Path, repeat: int) -> dict:
    """Train one design on one mesh at one budget and score it: one row."""
    import torch

    from neurogf_warp.training.checkpoint import RunFiles

    out = work / f"{name}_{budget:g}s_{variant}_{repeat}.ngf"
    # an earlier command's run folder would lend this row its dataset (``force`` keeps a matching one): the row
    # times the whole call, ground truth included
    shutil.rmtree(RunFiles.for_model(out).folder, ignore_errors=True)
    mesh_file, reference = mesh_files(a, name)
    sized = VARIANTS[variant].get("landmarks") == "scaled"  # only such a design needs the mesh read first
    settings = row_settings(name, variant, len(ngf.load_mesh(str(mesh_file)).internal_vertices) if sized else None)
    row = {"mesh": name, "budget_s": budget, "variant": variant, "repeat": repeat, "settings": settings}
    cuda = str(a.device).startswith("cuda")
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            t0 = time.perf_counter()
            model = ngf.train(str(mesh_file), out, budget_seconds=budget, device=a.device,
                              force=True, progress=False, **settings)
            row["call_s"] = time.perf_counter() - t0
        row["peak_gpu_mb"] = torch.cuda.max_memory_allocated() / 2**20 if cuda else 0.0
        log = json.loads(Path(RunFiles.for_model(out).log).read_text())
        t0 = time.perf_counter()
        err = torch_errors(model, reference, a.device)
        row["eval_s"] = time.perf_counter() - t0
        params = sum(p.numel() for p in model.net.parameters())
        lm = getattr(model.net, "landmark_table", None)  # (V, K) float32 distances a query would also have to read
        table_mb = 4 * lm.table.numel() / 2**20 if lm is not None else 0.0
        t, cfg = log["timings"], log["config"]
        steps = cfg.get("steps") or {}
        per = t.get("calibrated_s_per_step") or {}
        row.update(mre=err.get("mre"), p99=err.get("p99_rel"), max=err.get("max_rel"), median=err.get("median_rel"),
                   by_distance=err.get("by_distance"),
                   pairs=err.get("pairs"), nonfinite=err.get("nonfinite"), steps=steps,
                   ms_per_step={k: 1e3 * v for k, v in per.items()}, steps_s=t.get("steps_s"),
                   dataset_s=t.get("dataset_s"), calibrate_s=t.get("calibrate_s"),
                   set_up={k: t.get(k) for k in ("dataset_phases", "kernels_load_s", "sdf_pool_s", "calibrate_rounds")},
                   sources=log["history"].get("sources"),
                   batch_scale=log["history"].get("batch_scale"), validation_mre=cfg.get("validation_mre"),
                   validation_heat_mre=cfg.get("heat_mre"), params=params, model_mb=4 * params / 2**20,
                   table_mb=table_mb,
                   compile=t.get("compile"), warnings=sorted({f"{w.category.__name__}: {w.message}" for w in caught}))
        if a.check_engine and variant == "default" and not getattr(a, "_checked", False):
            a._checked = True
            res = ngf.evaluate(model, reference=reference, paths=False, sdf=False, device=a.device,
                               verbose=False)
            row["engine_check"] = {k: res["neurogf"].get(k) for k in ("mre", "p99_rel", "max_rel")}
    except Exception as e:  # one design failing must not lose the other rows
        row["error"] = f"{type(e).__name__}: {e}"
        row["traceback"] = traceback.format_exc()[-3000:]
    return row


def decide(rows: list, measured_spread: dict | None = None) -> dict:
    """The decision rule of the module docstring, applied to ``rows``: {variant: {"keep": bool, "why": [...]}}.

    measured_spread : {budget: spread} from repeated default runs of another result file (``--spread-from``),
        for rows without a repeat of their own; a repeat among ``rows`` takes precedence."""
    import numpy as np

    ok = [r for r in rows if r.get("mre") is not None and np.isfinite(r["mre"])]
    own = {}
    for r in ok:
        if r["variant"] != "default":
            continue
        same = [x["mre"] for x in ok if x["variant"] == "default" and x["mesh"] == r["mesh"]
                and x["budget_s"] == r["budget_s"]]
        if len(same) > 1:
            own[r["budget_s"]] = max(own.get(r["budget_s"], 0.0), max(same) - min(same))
    spread = {**{float(b): float(x) for b, x in (measured_spread or {}).items()}, **own}
    cells = sorted({(r["mesh"], r["budget_s"]) for r in rows})
    out = {"spread": spread}
    for v in VARIANTS:
        if v == "default" or not any(r["variant"] == v for r in rows):
            continue
        why, keep = [], True
        for mesh, b in cells:
            base = [x["mre"] for x in ok if x["variant"] == "default" and x["mesh"] == mesh and x["budget_s"] == b]
            cand = [x["mre"] for x in ok if x["variant"] == v and x["mesh"] == mesh and x["budget_s"] == b]
            if not base or not cand or b not in spread:
                keep = False
                ran = any(x["variant"] == v and x["mesh"] == mesh and x["budget_s"] == b for x in rows)
                why.append(f"{mesh} {b:g} s: " + ("no comparison (a row failed or no spread)" if ran else "not run"))
                continue
            ref, c = float(np.mean(base)), float(np.mean(cand))
            win = c < ref - spread[b]
            keep &= win
            why.append(f"{mesh} {b:g} s: {100 * c:.3f}% vs {100 * ref:.3f}% +- {100 * spread[b]:.3f} "
                       + ("better" if win else "not better"))
        out[v] = {"keep": keep, "why": why}
    return out


def table(rows: list) -> str:
    head = ("mesh", "budget", "variant", "call", "MRE", "p99", "max", "joint/rd steps", "ms joint/rd", "peak GPU",
            "params", "sources")
    lines = [head]
    pct = lambda x: "-" if x is None else f"{100 * x:.3f}%"  # noqa: E731
    for r in rows:
        if "error" in r:
            lines.append((r["mesh"], f"{r['budget_s']:g} s", r["variant"], "-", r["error"][:60], "", "", "", "", "",
                          "", ""))
            continue
        st, ms = r["steps"], r["ms_per_step"]
        lines.append((r["mesh"], f"{r['budget_s']:g} s", r["variant"], f"{r['call_s']:.1f} s", pct(r["mre"]),
                      pct(r["p99"]), pct(r["max"]), f"{st.get('joint', '?')}/{st.get('refine_dist', '?')}",
                      f"{ms.get('joint', 0):.2f}/{ms.get('refine_dist', 0):.2f}", f"{r['peak_gpu_mb']:.0f} MB",
                      f"{r['params']:,}", str((r.get("sources") or {}).get("distance", "?"))))
    w = [max(len(x[i]) for x in lines) for i in range(len(head))]
    return "\n".join("  ".join(c.rjust(w[i]) for i, c in enumerate(x)) for x in lines)


def plot(rows: list, path: Path) -> bool:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        import matplotlib.ticker
    except ImportError:
        return False
    ok = [r for r in rows if r.get("mre") is not None]
    names = list(dict.fromkeys(r["mesh"] for r in ok))
    if not names:
        return False
    cols = min(len(names), 5)
    nrows = -(-len(names) // cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(4.4 * cols, 3.8 * nrows), squeeze=False)
    for ax in axes.flat[len(names):]:
        ax.set_visible(False)
    for ax, name in zip(axes.flat, names):
        for i, v in enumerate(VARIANTS):  # one colour per design in every panel and file
            rs = sorted((r for r in ok if r["mesh"] == name and r["variant"] == v), key=lambda r: r["budget_s"])
            if rs:
                ax.loglog([r["call_s"] for r in rs], [100 * r["mre"] for r in rs], "o--", label=v, alpha=0.8,
                          color=f"C{i % 10}")
        ax.set_title(name)
        ax.set_xticks(sorted({r["budget_s"] for r in ok if r["mesh"] == name}))  # the budgets, as plain numbers
        ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_xlabel("seconds, whole train() call")
        ax.set_ylabel("MRE vs exact (%)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return True


def _in_fresh_process(a, spec: str, work: Path, slot: int | None = None) -> dict:
    """One row (``--row spec``) in a new Python process: what one run leaves in a process (caches, allocator
    pools, threads) cannot touch the next row. ``gpu``: the process sees only that GPU and its share of the
    CPU cores (rows side by side, ``--gpus``); ``slot``: GPU ``slot % --gpus``, a work folder of its own (rows at once
    must not share a mesh's dataset folder)."""
    import subprocess
    import tempfile

    name, budget, variant, k = spec.split(":")
    env = dict(os.environ)
    gpu = None if slot is None else slot % a.gpus
    if gpu is not None:
        threads = str(max(1, (os.cpu_count() or 1) // (a.gpus * a.share)))
        env.update(CUDA_VISIBLE_DEVICES=str(gpu), OMP_NUM_THREADS=threads, MKL_NUM_THREADS=threads)
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, __file__, "--row", spec, "--device", a.device, "--shared", a.shared, "--work",
               str(work / f"slot{slot}" if slot is not None else work), "--out", tmp] + \
            (["--unseen", a.unseen] if a.unseen else []) + ([] if a.check_engine else ["--no-engine-check"])
        done = subprocess.run(cmd, capture_output=True, text=True, env=env)
        got = Path(tmp, "row.json")
        if done.returncode == 0 and got.exists():
            return json.loads(got.read_text())
    return {"mesh": name, "budget_s": float(budget), "variant": variant, "repeat": int(k),
            "settings": row_settings(name, variant), "error": f"the row's process exited {done.returncode}",
            "traceback": (done.stdout + done.stderr)[-3000:]}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda:0")
    p.add_argument("--shared", default=str(ROOT.parent / "shared"), help="folder with meshes/ and reference/exact/")
    p.add_argument("--meshes", nargs="+", default=["bunny", "spot"], choices=list(MESHES) + list(UNSEEN))
    p.add_argument("--unseen", default=None, metavar="DIR",
                   help="the --out folder of benchmarks/unseen_meshes.py (meshes scan, parts, cad, joined)")
    p.add_argument("--budgets", nargs="+", type=float, default=[20, 60])
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    p.add_argument("--repeat", nargs="*", default=["bunny"], help="meshes on which the default runs twice")
    p.add_argument("--warmup", type=float, default=10.0, help="budget of the untimed first call (0: none)")
    p.add_argument("--no-engine-check", dest="check_engine", action="store_false")
    p.add_argument("--commit", default=None, help="commit of the code measured (recorded)")
    p.add_argument("--out", default=os.environ.get("OUT", str(ROOT / "benchmarks" / "results")))
    p.add_argument("--work", default="/tmp/neurogf-bakeoff")
    p.add_argument("--gpus", type=int, default=1,
                   help="rows side by side, one per GPU (each process sees one GPU and its share of the CPU cores); "
                        "the designs of one mesh and budget run at the same time")
    p.add_argument("--share", type=int, default=1, metavar="N",
                   help="N rows at once on each GPU (time-sliced: each row gets about 1/N of the GPU and of the "
                        "CPU cores, so its errors bound from above those of a row alone)")
    p.add_argument("--same-process", dest="fresh", action="store_false",
                   help="every row in this process (default: each row, and the warm-up, in a fresh process)")
    p.add_argument("--row", default=None, help=argparse.SUPPRESS)  # MESH:BUDGET:VARIANT:REPEAT, one row, JSON out
    p.add_argument("--spread-from", default=None, metavar="JSON",
                   help="with --merge: the run-to-run spread of the default from this result file's repeated runs "
                        "(for runs without a repeat of their own)")
    p.add_argument("--merge", nargs="+", default=None, metavar="JSON",
                   help="no runs: join the rows of earlier bakeoff.json files, decide, write --out")
    a = p.parse_args(argv)
    if (a.gpus > 1 or a.share > 1) and not a.fresh:
        p.error("--gpus and --share run rows in processes of their own: drop --same-process")
    if a.share < 1:
        p.error(f"--share is the number of rows at once on one GPU (1 or more), got {a.share}")
    if a.merge:
        parts = [json.loads(Path(f).read_text()) for f in a.merge]
        runs = [run for d in parts for run in (d["runs"] if "runs" in d else [_run_doc(d["meta"], d["rows"])])]
        rows = [r for run in runs for r in run["rows"]]
        out = Path(a.out)
        out.mkdir(parents=True, exist_ok=True)
        measured = None
        if a.spread_from:
            measured = decide([r for run in json.loads(Path(a.spread_from).read_text())["runs"]
                               for r in run["rows"]])["spread"]
            for run in runs:  # kept with the rows: the results page decides with the same numbers
                run["meta"]["measured_spread"] = {"from": Path(a.spread_from).name, "spread": measured}
        decision = decide(rows, measured)
        (out / "bakeoff.json").write_text(json.dumps({"benchmark": "bakeoff", "runs": runs, "decision": decision},
                                                     indent=1))
        plot(rows, out / "bakeoff.png")
        print(table(rows))
        print(json.dumps(decision, indent=1))
        return 0

    import neurogf_warp as ngf
    import torch
    import warp

    print(f"neurogf_warp from {ngf.__file__}, kernels from {sys.modules['neurogf_warp.kernels'].__file__}"
          if "neurogf_warp.kernels" in sys.modules else f"neurogf_warp from {ngf.__file__}, kernels installed: "
          f"{importlib.util.find_spec('neurogf_warp.kernels').origin}", flush=True)
    work, out = Path(a.work), Path(a.out)
    work.mkdir(parents=True, exist_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    if a.row:
        name, budget, variant, k = a.row.split(":")
        r = run_row(ngf, name, float(budget), variant, a, work, int(k))
        Path(a.out, "row.json").write_text(json.dumps(r))
        return 0
    warm_s = None
    if a.warmup > 0:  # Warp's and torch's caches on disk filled before the timed rows
        t0 = time.perf_counter()
        if a.fresh:
            _in_fresh_process(a, f"{a.meshes[-1]}:{a.warmup:g}:default:-1", work)
        else:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                ngf.train(str(mesh_files(a, a.meshes[-1])[0]), work / "warmup.ngf", budget_seconds=a.warmup,
                          device=a.device, force=True, progress=False, **COMMON)
        warm_s = time.perf_counter() - t0
        print(f"warm-up call {warm_s:.1f} s", flush=True)
    rows = []
    meta = {"device": a.device, "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
            "host": platform.node(),
            "cpu_cores": os.cpu_count(), "torch": torch.__version__, "warp": warp.config.version,
            "python": platform.python_version(), "argv": sys.argv[1:], "commit": a.commit, "variants": VARIANTS,
            "common_settings": COMMON, "warmup_s": warm_s, "one_process_per_row": a.fresh,
            "date_utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime())}
    specs = [f"{name}:{budget:g}:{v}:{k}" for name in a.meshes for budget in a.budgets
             for v, k in [(v, 0) for v in a.variants] + ([("default", 1)] if name in a.repeat else [])]

    def keep(r):
        rows.append(r)
        print(table([r]).splitlines()[-1], flush=True)
        (out / "bakeoff.json").write_text(json.dumps({"benchmark": "bakeoff", "runs": [_run_doc(meta, rows)]},
                                                     indent=1))

    if a.gpus * a.share > 1:
        import queue
        from concurrent.futures import ThreadPoolExecutor

        meta["gpus_side_by_side"] = a.gpus
        if a.share > 1:
            meta["rows_sharing_a_gpu"] = a.share
        free = queue.Queue()
        for slot in range(a.gpus * a.share):
            free.put(slot)

        def on_a_free_gpu(spec):
            g = free.get()
            try:
                return _in_fresh_process(a, spec, work, g)
            finally:
                free.put(g)

        with ThreadPoolExecutor(a.gpus * a.share) as pool:
            for r in pool.map(on_a_free_gpu, specs):
                keep(r)
    else:
        for spec in specs:
            name, budget, v, k = spec.split(":")
            keep(_in_fresh_process(a, spec, work) if a.fresh else run_row(ngf, name, float(budget), v, a, work,
                                                                           int(k)))
    decision = decide(rows)
    meta["end_utc"] = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime())
    (out / "bakeoff.json").write_text(json.dumps({"benchmark": "bakeoff", "runs": [_run_doc(meta, rows)],
                                                 "decision": decision}, indent=1))
    plot(rows, out / "bakeoff.png")
    print("\n" + table(rows))
    print(json.dumps(decision, indent=1))
    for r in rows:
        if "error" in r:
            print(r["traceback"])
        if "engine_check" in r:
            print("engine check (Warp ssad) on", r["mesh"], r["budget_s"], r["engine_check"], "torch:", r["mre"],
                  r["p99"], r["max"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
