"""Bake-off of field designs for accuracy per second: each design trained under the same time budget as the
default, scored against exact geodesics.

    python benchmarks/bakeoff.py --device cuda:0 --shared /path/to/shared --meshes bunny spot --budgets 20 60

A design is a set of training settings (``VARIANTS``: the default, ``norm=none``, ``hash_levels=12``,
``landmarks=K`` for K in 32..256). Per
(mesh, budget, design): ``ngf.train(mesh, out, budget_seconds=B, device=..., force=True, **design)``, timed
whole, in one process after an untimed warm-up call (Warp's kernels compiled, CUDA initialized), the designs of
one (mesh, budget) back to back so that a drift of the machine touches each alike. Every design runs with
``compile=False``: on a machine that has not compiled these shapes before, the 20-60 s default rows run eagerly
anyway (the budget planner's choice), and a design must not win or lose through a compile cache.

Accuracy: the trained network's distances from each source of the exact reference to every reference vertex,
computed with torch (eval mode, fp32, raised to the straight-line distance as the public queries do), MRE, p99
and max relative error, source excluded (``evaluation.evaluate._rel_stats``). The Warp inference engine reads
only the default design, so torch scores every design alike; on the first default row the engine's own
``ngf.evaluate`` runs too, as a check of that scoring.

Decision rule, fixed before any run: a design is kept only if, on every mesh and at every budget tried, its MRE is
lower than the default's by more than the run-to-run spread: MRE_design < MRE_default - spread_B, where
MRE_default is the mean of the default's runs on that mesh and budget and spread_B is the largest difference
between two default runs of the same mesh at budget B (the default runs twice on ``--repeat`` meshes). Otherwise
it is not kept.

Writes ``<out>/bakeoff.json`` (every row: errors, steps, step times, peak GPU memory, model size) and
``<out>/bakeoff.png`` (MRE against the budget, one panel per mesh).
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
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
}
COMMON = {"compile": False}
os.environ["NEUROGF_BAKEOFF_DESIGNS"] = "1"  # the designs the package refuses for users (no inference backend reads them)
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
    x = torch.as_tensor((mesh.internal_vertices - np.asarray(model.center)) * scale, dtype=torch.float32,
                        device=device)
    if getattr(net, "landmarks", 0):  # its table is looked up by the training's own float32 vertex array
        x = net.landmark_table.xyz.to(device)
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
    return _rel_stats(pred, gt)


def run_row(ngf, shared: Path, name: str, budget: float, variant: str, a, work: Path, repeat: int) -> dict:
    """Train one design on one mesh at one budget and score it: one row."""
    import torch

    from neurogf_warp.training.checkpoint import RunFiles

    out = work / f"{name}_{budget:g}s_{variant}_{repeat}.ngf"
    settings = {**COMMON, **VARIANTS[variant]}
    row = {"mesh": name, "budget_s": budget, "variant": variant, "repeat": repeat, "settings": settings}
    cuda = str(a.device).startswith("cuda")
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            t0 = time.perf_counter()
            model = ngf.train(str(shared / "meshes" / MESHES[name]), out, budget_seconds=budget, device=a.device,
                              force=True, progress=False, **settings)
            row["call_s"] = time.perf_counter() - t0
        row["peak_gpu_mb"] = torch.cuda.max_memory_allocated() / 2**20 if cuda else 0.0
        log = json.loads(Path(RunFiles.for_model(out).log).read_text())
        t0 = time.perf_counter()
        err = torch_errors(model, _reference(shared, name), a.device)
        row["eval_s"] = time.perf_counter() - t0
        params = sum(p.numel() for p in model.net.parameters())
        t, cfg = log["timings"], log["config"]
        steps = cfg.get("steps") or {}
        per = t.get("calibrated_s_per_step") or {}
        row.update(mre=err.get("mre"), p99=err.get("p99_rel"), max=err.get("max_rel"), median=err.get("median_rel"),
                   pairs=err.get("pairs"), nonfinite=err.get("nonfinite"), steps=steps,
                   ms_per_step={k: 1e3 * v for k, v in per.items()}, steps_s=t.get("steps_s"),
                   dataset_s=t.get("dataset_s"), calibrate_s=t.get("calibrate_s"), sources=log["history"].get("sources"),
                   batch_scale=log["history"].get("batch_scale"), validation_mre=cfg.get("validation_mre"),
                   validation_heat_mre=cfg.get("heat_mre"), params=params, model_mb=4 * params / 2**20,
                   compile=t.get("compile"), warnings=sorted({f"{w.category.__name__}: {w.message}" for w in caught}))
        if a.check_engine and variant == "default" and not getattr(a, "_checked", False):
            a._checked = True
            res = ngf.evaluate(model, reference=_reference(shared, name), paths=False, sdf=False, device=a.device,
                               verbose=False)
            row["engine_check"] = {k: res["neurogf"].get(k) for k in ("mre", "p99_rel", "max_rel")}
    except Exception as e:  # one design failing must not lose the other rows
        row["error"] = f"{type(e).__name__}: {e}"
        row["traceback"] = traceback.format_exc()[-3000:]
    return row


def decide(rows: list) -> dict:
    """The decision rule of the module docstring, applied to ``rows``: {variant: {"keep": bool, "why": [...]}}."""
    import numpy as np

    ok = [r for r in rows if r.get("mre") is not None and np.isfinite(r["mre"])]
    spread = {}
    for r in ok:
        if r["variant"] != "default":
            continue
        same = [x["mre"] for x in ok if x["variant"] == "default" and x["mesh"] == r["mesh"]
                and x["budget_s"] == r["budget_s"]]
        if len(same) > 1:
            spread[r["budget_s"]] = max(spread.get(r["budget_s"], 0.0), max(same) - min(same))
    cells = sorted({(r["mesh"], r["budget_s"]) for r in rows})
    out = {"spread": spread}
    for v in VARIANTS:
        if v == "default":
            continue
        why, keep = [], True
        for mesh, b in cells:
            base = [x["mre"] for x in ok if x["variant"] == "default" and x["mesh"] == mesh and x["budget_s"] == b]
            cand = [x["mre"] for x in ok if x["variant"] == v and x["mesh"] == mesh and x["budget_s"] == b]
            if not base or not cand or b not in spread:
                keep = False
                why.append(f"{mesh} {b:g} s: no comparison (a row failed or no spread)")
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
    except ImportError:
        return False
    ok = [r for r in rows if r.get("mre") is not None]
    names = list(dict.fromkeys(r["mesh"] for r in ok))
    if not names:
        return False
    fig, axes = plt.subplots(1, len(names), figsize=(4.4 * len(names), 3.8), squeeze=False)
    for ax, name in zip(axes[0], names):
        for v in VARIANTS:
            rs = sorted((r for r in ok if r["mesh"] == name and r["variant"] == v), key=lambda r: r["budget_s"])
            if rs:
                ax.semilogy([r["call_s"] for r in rs], [100 * r["mre"] for r in rs], "o--", label=v, alpha=0.8)
        ax.set_title(name)
        ax.set_xlabel("seconds, whole train() call")
        ax.set_ylabel("MRE vs exact (%)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return True


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda:0")
    p.add_argument("--shared", default=str(ROOT.parent / "shared"), help="folder with meshes/ and reference/exact/")
    p.add_argument("--meshes", nargs="+", default=["bunny", "spot"], choices=list(MESHES))
    p.add_argument("--budgets", nargs="+", type=float, default=[20, 60])
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    p.add_argument("--repeat", nargs="*", default=["bunny"], help="meshes on which the default runs twice")
    p.add_argument("--warmup", type=float, default=10.0, help="budget of the untimed first call (0: none)")
    p.add_argument("--no-engine-check", dest="check_engine", action="store_false")
    p.add_argument("--commit", default=None, help="commit of the code measured (recorded)")
    p.add_argument("--out", default=os.environ.get("OUT", str(ROOT / "benchmarks" / "results")))
    p.add_argument("--work", default="/tmp/neurogf-bakeoff")
    p.add_argument("--merge", nargs="+", default=None, metavar="JSON",
                   help="no runs: join the rows of earlier bakeoff.json files, decide, write --out")
    a = p.parse_args(argv)
    if a.merge:
        parts = [json.loads(Path(f).read_text()) for f in a.merge]
        runs = [run for d in parts for run in (d["runs"] if "runs" in d else [_run_doc(d["meta"], d["rows"])])]
        rows = [r for run in runs for r in run["rows"]]
        out = Path(a.out)
        out.mkdir(parents=True, exist_ok=True)
        decision = decide(rows)
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
    shared, work, out = Path(a.shared), Path(a.work), Path(a.out)
    work.mkdir(parents=True, exist_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    warm_s = None
    if a.warmup > 0:
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ngf.train(str(shared / "meshes" / MESHES[a.meshes[-1]]), work / "warmup.ngf", budget_seconds=a.warmup,
                      device=a.device, force=True, progress=False, **COMMON)
        warm_s = time.perf_counter() - t0
        print(f"warm-up call {warm_s:.1f} s", flush=True)
    rows = []
    meta = {"device": a.device, "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
            "host": platform.node(),
            "cpu_cores": os.cpu_count(), "torch": torch.__version__, "warp": warp.config.version,
            "python": platform.python_version(), "argv": sys.argv[1:], "commit": a.commit, "variants": VARIANTS,
            "common_settings": COMMON, "warmup_s": warm_s,
            "date_utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime())}
    for name in a.meshes:
        for budget in a.budgets:
            order = [(v, 0) for v in a.variants] + ([("default", 1)] if name in a.repeat else [])
            for v, k in order:
                r = run_row(ngf, shared, name, budget, v, a, work, k)
                rows.append(r)
                print(table([r]).splitlines()[-1], flush=True)
                (out / "bakeoff.json").write_text(json.dumps({"benchmark": "bakeoff", "runs": [_run_doc(meta, rows)]},
                                                             indent=1))
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
