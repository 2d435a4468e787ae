"""Time to accuracy: train meshes at several budgets, each call timed whole, and score every model.

The package is imported from this checkout (installed or not); the meshes and exact references come from
``--shared`` (a folder with ``meshes/`` and ``reference/exact/``; default ../shared):

    python benchmarks/time_to_accuracy.py --device cuda:0 --shared /path/to/shared          # 20, 60, 120, 300 s
    python benchmarks/time_to_accuracy.py --device cpu --meshes spot fandisk                 # 60, 180 s

Per (mesh, budget): ``ngf.train(mesh, out, budget_seconds=B, device=..., force=True)`` (the preset the device and
mesh size choose, ground truth included in the call), its real duration, then ``ngf.evaluate`` against the exact
reference: MRE, p99 and max relative error over the reference's sources, the heat method (potpourri3d) on the same
pairs, path Chamfer-L1 against solver paths raw and after ``--path-refine`` sweeps, SDF L1. The training log's
timings say where the call went (dataset, set-up, steps). Writes ``<out>/time_to_accuracy.json`` and
``<out>/time_to_accuracy.png`` (MRE against the call's seconds, one panel per mesh, the heat method dashed).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
import warnings
from pathlib import Path

import _bootstrap  # noqa: F401  (this checkout's neurogf_warp, installed or not)
from common import ROOT, write_json

MESHES = {"spot": "spot.obj", "cow": "cow.obj", "alligator": "alligator.obj", "homer": "homer.obj",
          "fandisk": "fandisk.obj", "cheburashka": "cheburashka.obj", "rocker-arm": "rocker-arm.obj",
          "bunny": "stanford-bunny.obj", "igea": "igea.ply"}


def _reference(shared: Path, name: str) -> Path:
    return shared / "reference" / "exact" / (Path(MESHES[name]).stem + ".npz")


def run_one(ngf, shared: Path, name: str, budget: float, a, work: Path) -> dict:
    """Train ``name`` at ``budget`` seconds and evaluate the model: one row of the table."""
    from neurogf_warp.training.checkpoint import RunFiles

    out = work / f"{name}_{budget:g}s.ngf"
    cached = Path(RunFiles.for_model(out).dataset)
    if cached.exists():  # force=True would reuse an earlier row's complete dataset: every row builds its own
        cached.unlink()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        t0 = time.perf_counter()
        model = ngf.train(str(shared / "meshes" / MESHES[name]), out, budget_seconds=budget, device=a.device,
                          force=True, progress=not a.quiet, **dict(a.settings))
        call_s = time.perf_counter() - t0
    log = json.loads(Path(RunFiles.for_model(out).log).read_text())
    res = ngf.evaluate(model, reference=_reference(shared, name), heat=a.heat, n_path_sources=a.path_sources,
                       n_path_targets=a.path_targets, path_refine=a.path_refine, device=a.device, progress=False,
                       verbose=False)
    n, h = res["neurogf"], res.get("heat", {})
    cfg = log["config"]
    return {"mesh": name, "vertices": res["vertices"], "budget_s": budget, "call_s": call_s,
            "mre": n["mre"], "p99": n["p99_rel"], "max": n["max_rel"],
            "heat_mre": h.get("mre"), "heat_p99": h.get("p99_rel"), "heat_max": h.get("max_rel"),
            "chamfer": res.get("chamfer_l1"), "chamfer_refined": res.get("chamfer_l1_refined"),
            "sdf_l1": res.get("sdf_l1"), "validation_mre": cfg.get("validation_mre"),
            "validation_heat_mre": cfg.get("heat_mre"), "worse_than_heat": cfg.get("worse_than_heat"),
            "budget_warning": cfg.get("budget_warning"), "preset": cfg.get("preset"), "steps": cfg.get("steps"),
            "sources": log["history"].get("sources"), "timings": log["timings"],
            "threads": log["history"].get("threads"), "batch_scale": log["history"].get("batch_scale"),
            "batches": cfg.get("batches"),
            "warnings": sorted({f"{w.category.__name__}: {w.message}" for w in caught})}


def _plot(rows: list, path: Path) -> bool:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    names = list(dict.fromkeys(r["mesh"] for r in rows))
    fig, axes = plt.subplots(1, len(names), figsize=(4.2 * len(names), 3.8), squeeze=False)
    for ax, name in zip(axes[0], names):
        rs = sorted((r for r in rows if r["mesh"] == name), key=lambda r: r["call_s"])
        ax.semilogy([r["call_s"] for r in rs], [100 * r["mre"] for r in rs], "o-", label="NeuroGF")
        heat = [r["heat_mre"] for r in rs if r["heat_mre"] is not None]
        if heat:
            ax.axhline(100 * heat[0], ls="--", color="0.4", label="heat method")
        ax.set_title(f"{name} ({rs[0]['vertices']:,} vertices)")
        ax.set_xlabel("seconds, whole train() call")
        ax.set_ylabel("MRE vs exact (%)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return True


def _phases(r: dict) -> str:
    """The dataset's distance and path phases (seconds) from the training log, with the sources each solved."""
    ph = r["timings"].get("dataset_phases") or {}
    if "distances_s" not in ph:
        return "-"
    src = r.get("sources") or {}
    return f"{ph['distances_s']:.1f} s ({src.get('distance', '?')}) / {ph.get('paths_s', 0):.1f} s"


def _compiled(r: dict) -> str:
    """The run's torch.compile: "no" (eager), "cold" or "warm" (this machine had compiled its shapes before: such a
    row's speed depends on the machine's history), "-" where no budgeted GPU run decided it."""
    c = r["timings"].get("compile")
    if not c:
        return "-"
    if not c.get("used"):
        return "no"
    return {True: "warm", False: "cold"}.get(c.get("cached"), "yes")


def _table(rows: list) -> str:
    head = ("mesh", "budget", "call", "MRE", "p99", "max", "heat", "Chamfer", "refined", "SDF L1", "dataset",
            "distances/paths", "steps joint/rd", "compile")
    lines = [head]
    pct = lambda x: "-" if x is None else f"{100 * x:.3f}%"  # noqa: E731
    sci = lambda x: "-" if x is None else f"{x:.3e}"  # noqa: E731
    for r in rows:
        st = r["steps"] or {}
        lines.append((r["mesh"], f"{r['budget_s']:g} s", f"{r['call_s']:.1f} s", pct(r["mre"]), pct(r["p99"]),
                      pct(r["max"]), pct(r["heat_mre"]), sci(r["chamfer"]), sci(r["chamfer_refined"]),
                      sci(r["sdf_l1"]), f"{r['timings'].get('dataset_s', 0):.1f} s", _phases(r),
                      f"{st.get('joint', '?')}/{st.get('refine_dist', '?')}", _compiled(r)))
    w = [max(len(x[i]) for x in lines) for i in range(len(head))]
    return "\n".join("  ".join(c.rjust(w[i]) for i, c in enumerate(x)) for x in lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default=None, help="cpu or cuda:N (default: cuda:0 if there is one)")
    p.add_argument("--shared", default=str(ROOT.parent / "shared"),
                   help="folder with meshes/ and reference/exact/ (default ../shared)")
    p.add_argument("--meshes", nargs="+", default=None, choices=list(MESHES),
                   help="default: spot fandisk bunny igea on a GPU, spot fandisk on the CPU")
    p.add_argument("--budgets", nargs="+", type=float, default=None,
                   help="seconds per call (default: 20 60 120 300 on a GPU, 60 180 on the CPU)")
    p.add_argument("--path-sources", type=int, default=None, help="path pairs: sources (default GPU 16, CPU 4)")
    p.add_argument("--path-targets", type=int, default=None, help="path pairs: targets per source (GPU 32, CPU 4)")
    p.add_argument("--path-refine", type=int, default=50, help="shortening sweeps for the refined Chamfer (0: none)")
    p.add_argument("--no-heat", dest="heat", action="store_false", help="skip the heat method")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="a training setting, repeatable")
    p.add_argument("--out", default=os.environ.get("OUT", "time_to_accuracy_out"),
                   help="folder for time_to_accuracy.json and .png (default: $OUT, else ./time_to_accuracy_out)")
    p.add_argument("--work", default="/tmp/neurogf-time-to-accuracy", help="model files and run folders")
    p.add_argument("-q", "--quiet", action="store_true")
    a = p.parse_args(argv)

    import torch

    import neurogf_warp as ngf

    from neurogf_warp.training.config import parse_assignments

    a.device = a.device or ("cuda:0" if torch.cuda.is_available() else "cpu")
    gpu = a.device.startswith("cuda")
    a.meshes = a.meshes or (["spot", "fandisk", "bunny", "igea"] if gpu else ["spot", "fandisk"])
    a.budgets = a.budgets or ([20, 60, 120, 300] if gpu else [60, 180])
    a.path_sources = a.path_sources if a.path_sources is not None else (16 if gpu else 4)
    a.path_targets = a.path_targets if a.path_targets is not None else (32 if gpu else 4)
    a.settings = parse_assignments(a.set)
    shared = Path(a.shared)
    for name in a.meshes:
        for f in (shared / "meshes" / MESHES[name], _reference(shared, name)):
            if not f.exists():
                p.error(f"{f} not found: pass --shared with meshes/ and reference/exact/")
    work, out = Path(a.work), Path(a.out)
    work.mkdir(parents=True, exist_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in a.meshes:
        for budget in a.budgets:
            print(f"== {name}, budget {budget:g} s, {a.device}", flush=True)
            rows.append(run_one(ngf, shared, name, budget, a, work))
            print(_table(rows[-1:]), flush=True)
    text = _table(rows)
    print("\n" + text)
    meta = {"device": a.device, "gpu": torch.cuda.get_device_name(a.device) if gpu else None, "host": platform.node(),
            "cpu_cores": os.cpu_count(), "date_utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()),
            "torch": torch.__version__, "argv": sys.argv[1:], "settings": a.settings,
            "load_average_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None}
    write_json(out / "time_to_accuracy.json", {"meta": meta, "rows": rows}, "time_to_accuracy", a.device)
    plotted = _plot(rows, out / "time_to_accuracy.png")
    print(f"wrote {out / 'time_to_accuracy.json'}" + (f" and {out / 'time_to_accuracy.png'}" if plotted else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
