"""Write docs/performance.md from the kept benchmark results (benchmarks/results/*.json), one table per file.

    python benchmarks/make_performance.py            # regenerate docs/performance.md
    python benchmarks/make_performance.py --check    # exit 1 when docs/performance.md differs from a regeneration

A result file is one benchmark's JSON (``{"benchmark": NAME, "provenance": {...}, ...}``, as ``common.write_json``
writes it) or several runs of one benchmark (``{"benchmark": NAME, "runs": [{"provenance": {...}, ...}, ...]}``).
Each table is headed by its command, device, driver / Warp / torch versions, date and commit, taken from the
provenance blocks. A new benchmark adds one function to ``FORMATTERS`` (``@formatter("name", "title")``): it gets the
list of runs and returns the table (Markdown lines). Where a curve says more than the table (``PLOTTERS``), the page
links a figure in docs/performance/, redrawn with matplotlib when it is installed; ``--check`` compares the text only.
The page itself needs only the standard library.
"""
from __future__ import annotations

import argparse
import difflib
import json
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS_DIR = ROOT / "benchmarks" / "results"
PAGE = ROOT / "docs" / "performance.md"

FORMATTERS: dict = {}  # benchmark name -> (title, function(runs) -> list of Markdown lines)
PLOTTERS: dict = {}  # benchmark name -> function(runs, png path): a figure beside the table (matplotlib)
ORDER = ["queries", "landmark_ssad", "between_vertices", "released", "kernel_api", "path_snap", "geodesic_tools", "ground_truth_setup", "geodesics", "time_to_accuracy",
         "bakeoff", "generalizable",
         "generalizable_collection", "generalizable_eval", "generalizable_scaling", "multi_gpu"]


def formatter(name: str, title: str):
    """Register ``fn(runs) -> [Markdown lines]`` as the table of benchmark ``name``."""
    def register(fn):
        FORMATTERS[name] = (title, fn)
        return fn
    return register


# ---- formatting -------------------------------------------------------------------------------------------------

def pct(x, digits=3) -> str:
    return "-" if x is None else f"{100 * x:.{digits}f}%"


def num(x, fmt="{:.3g}") -> str:
    return "-" if x is None else fmt.format(x)


def span(values, fmt="{:.3g}", unit="") -> str:
    """One value, or the range of several (the runs of one row)."""
    vs = sorted(v for v in values if v is not None)
    if not vs:
        return "-"
    lo, hi = fmt.format(vs[0]), fmt.format(vs[-1])
    return f"{lo}{unit}" if lo == hi else f"{lo}–{hi}{unit}"


def table(head: list, rows: list) -> list:
    out = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return out


def runs_of(doc: dict) -> list:
    return doc["runs"] if "runs" in doc else [doc]


# ---- the header of a table: provenance ---------------------------------------------------------------------------

_MACHINE_ARGS = ("--out", "--work", "--shared", "--json", "--table")


def _command(cmd: str | None) -> str | None:
    """A command without the arguments that only name this machine's folders (output, work and data paths)."""
    if not cmd:
        return cmd
    words = cmd.split()
    out, skip = [], False
    for w in words:
        if skip:
            skip = False
            continue
        if w in _MACHINE_ARGS:
            skip = True
            continue
        if w.startswith(tuple(a + "=" for a in _MACHINE_ARGS)):
            continue
        out.append(w)
    return " ".join(out)


def _commands(provs: list) -> list:
    """Distinct commands; one process per row (same options, other mesh or budget) becomes one line with M / B."""
    cmds = list(dict.fromkeys(c for c in (_command(p.get("command")) for p in provs) if c))
    if len(cmds) > 2:
        generic = list(dict.fromkeys(re.sub(r"(--budgets) [\d. ]+", r"\1 B ",
                                            re.sub(r"(--meshes) [\w\- ]+?(?= --|$)", r"\1 M", c)).strip()
                                     for c in cmds))
        if len(generic) < len(cmds):
            return generic
    return cmds


def _distinct(provs: list, key: str) -> str:
    vals = list(dict.fromkeys(p.get(key) for p in provs))
    known = [str(v) for v in vals if v is not None]
    text = ", ".join(known) if known else "not recorded"
    if known and None in vals:
        text += " (not recorded for some runs)"
    return text


def header(provs: list, files: list) -> list:
    dates = sorted(str(p.get("date_utc") or "")[:10] for p in provs if p.get("date_utc"))
    date = "not recorded" if not dates else dates[0] if dates[0] == dates[-1] else f"{dates[0]} to {dates[-1]}"
    devices = list(dict.fromkeys(f"{p.get('device_name') or 'not recorded'} (`{p.get('device')}`)" for p in provs))
    commits = list(dict.fromkeys(p["commit"] for p in provs if p.get("commit")))
    recorded = list(dict.fromkeys(p["recorded_in_commit"] for p in provs if p.get("recorded_in_commit")))
    if commits:
        commit = ", ".join(f"`{c}`" for c in commits)
        if any(not p.get("commit") for p in provs):
            commit += " (not recorded for some runs)"
    else:
        commit = "not recorded"
    if recorded:
        commit += "; results added in " + ", ".join(f"`{c}`" for c in recorded)
    cores = list(dict.fromkeys(p.get("cpu_cores") for p in provs if p.get("cpu_cores")))
    loads = [p["load_average_1min"] for p in provs if p.get("load_average_1min") is not None]
    load = (f"; load average {span(loads, '{:.1f}')} (1 min, the run's own included, when its results were written)"
            if loads and any(p.get("device") == "cpu" for p in provs) else "")
    lines = ["- command: " + ("; ".join(f"`{c}`" for c in _commands(provs)) or "not recorded"),
             "- device: " + ", ".join(devices) + (f"; {', '.join(map(str, cores))} CPU cores" if cores else "") + load,
             f"- CUDA driver {_distinct(provs, 'driver')}; Warp {_distinct(provs, 'warp')}; "
             f"torch {_distinct(provs, 'torch')}",
             f"- date: {date}; commit: {commit}",
             "- data: " + ", ".join(f"`benchmarks/results/{f}`" for f in files)]
    if any(p.get("reconstructed_from_history") for p in provs):
        lines.append("- provenance recorded after the run, from the repository's history; "
                     "what it does not say is marked not recorded")
    return lines


# ---- one formatter per benchmark ----------------------------------------------------------------------------------

def _warp_default(rows: list, query: str):
    for r in rows:
        if (r["query"] == query and r["variant"].startswith("warp") and "ms" in r and "check=False" not in r["variant"]
                and "precision=fp32" not in r["variant"]):
            return r
    return None


@formatter("queries", "Queries: Warp kernels against PyTorch")
def fmt_queries(runs):
    queries = list(dict.fromkeys(r["query"] for run in runs for r in run["rows"]))
    rows = []
    for q in queries:
        warp, unchecked, torch_best, torch_name, speed, err = [], [], [], set(), [], []
        # the PyTorch columns come from the runs that timed torch.compile too (others ran with --no-compile)
        compiled = any(r["query"] == q and "torch.compile" in r["variant"] for run in runs for r in run["rows"])
        for run in runs:
            w = _warp_default(run["rows"], q)
            if w is None:
                continue
            warp.append(w["ms"])
            err.append(w.get("rel_err"))
            u = [r for r in run["rows"] if r["query"] == q and "check=False" in r["variant"] and "ms" in r]
            unchecked += [r["ms"] for r in u]
            t = [r for r in run["rows"] if r["query"] == q and r["variant"].startswith("torch") and "ms" in r]
            if compiled and not any("torch.compile" in r["variant"] for r in t):
                t = []
            if t:
                best = min(t, key=lambda r: r["ms"])
                torch_best.append(best["ms"])
                torch_name.add(best["variant"])
                speed.append(best["ms"] / w["ms"])
        if not warp:
            continue
        form = "; ".join(sorted(torch_name)) or "-"
        if torch_name and not compiled:  # the runs of this query all ran with --no-compile
            form += " (torch.compile not timed)"
        rows.append((q, span(warp, unit=" ms"), span(unchecked, unit=" ms"), span(torch_best, unit=" ms"),
                     form, span(speed, "{:.1f}", "x"), span(err, "{:.1e}"), len(warp)))
    sizes = runs[0].get("sizes", {})
    mesh = runs[0].get("mesh", {})
    out = [f"Released bunny network (D = 256) on a {mesh.get('vertices', 0):,}-vertex mesh; device arrays in and "
           "out; median per-call time of back-to-back calls (CUDA events). Ranges span the runs that timed the "
           "query. Errors are relative L2 against a float64 evaluation of the network.", ""]
    out += table(["query", "Warp (input checks on)", "Warp, `check=False`", "fastest PyTorch", "its form",
                  "speed-up", "Warp rel. error", "runs"], rows)
    comp = [run.get("compile_s", {}) for run in runs]
    cold = [c.get("warp cold (every query's kernels)") for c in comp]
    cached = [c.get("warp from the kernel cache, new process") for c in comp]
    out += ["", f"Warp kernels of every query: {span(cold, '{:.1f}', ' s')} to compile from an empty kernel cache, "
            f"{span(cached, '{:.2f}', ' s')} to load from the cache in a new process. Sizes: {sizes}."]
    return out


H200_COPY_GBPS = 4278  # read + write copy bandwidth queries.py measured on an H200 (queries_h200_2026-11-28.json)


@formatter("landmark_ssad", "Landmark networks: a bound SSAD on tensor cores against K")
def fmt_landmark_ssad(runs):
    out = []
    for run in runs:
        mesh, gpu = run.get("mesh", {}), "H200" in str(run.get("provenance", {}).get("device_name"))
        rows = [(r["K"], f"{r['table_mb']:.1f}", r["bytes_per_vertex"], f"{r['kernel_ms']:.4f}",
                 f"{r['public_ms']:.4f}", f"{r['gb_per_s']:,.0f}",
                 f"{r['gb_per_s'] / H200_COPY_GBPS:.0%}" if gpu else "-", f"{r['max_err']:.1e}")
                for r in run["rows"] if "error" not in r]
        out += [f"A random network of width D = {run['D']} with K landmarks (K = 0: today's network) bound to a "
                f"{mesh.get('vertices', 0):,}-vertex mesh; `ngf.ssad(model, vertex)` with precision fp16: GPU time "
                "per call (CUDA events around back-to-back calls of the backend) and the public call's time, the "
                "bytes each vertex costs (fp16 embedding, float32 table row, the point, the answer), the bandwidth "
                f"that makes and its share of the {H200_COPY_GBPS:,} GB/s copy bandwidth `benchmarks/queries.py` "
                "measured on an H200, and the error against a float64 evaluation relative to the largest distance.",
                ""]
        out += table(["K", "table MB", "bytes per vertex", "GPU ms", "public call ms", "GB/s", "of the copy ceiling",
                      "max error"], rows)
        out += [""] + [f"- K = {r['K']}: {r['error']}" for r in run["rows"] if "error" in r]
    return out


@formatter("between_vertices", "Distances between vertices: edge midpoints against exact geodesics")
def fmt_between_vertices(runs):
    rows = [(r["model"], r["design"], where[3:], pct(r[where]["mre"]), pct(r[where]["p99"], 2), pct(r[where]["max"], 1),
             f"{r[where]['pairs']:,}") for run in runs for r in run["rows"] for where in ("at_vertices", "at_midpoints")]
    out = ["Each model's distances from vertex sources to every vertex and to every edge midpoint, against the "
           "ground-truth solver on the mesh subdivided at its edge midpoints (the same surface).", ""]
    out += table(["model", "design", "targets", "MRE", "p99", "max", "pairs"], rows)
    notes = [n for run in runs for n in run.get("notes", [])]
    return out + ([""] + [f"- {n}" for n in notes] if notes else [])


@formatter("released", "Released checkpoints through the Warp kernels")
def fmt_released(runs):
    rows = [(r["mesh"], r["precision"], pct(r["mre"], 4), pct(r["p99"]), pct(r["max"]), f"{r['pairs']:,}",
             f"{r['seconds']:.1f} s") for run in runs for r in run["rows"]]
    return (["The released NeuroGF checkpoints (bunny, fandisk) against exact geodesics, every source of the exact "
             "references to every vertex (`ngf.ssad`). On a CPU, fp16 runs the tensor-core code in emulation.", ""]
            + table(["mesh", "precision", "MRE", "p99", "max", "pairs", "time"], rows))


@formatter("kernel_api", "In-kernel API (`neurogf_warp.kernels.field`): cost per call")
def fmt_kernel_api(runs):
    out = []
    for run in runs:
        rows = [(f"`{name}`", f"{c['flops'] / 1e3:.0f}", f"{c['seconds_per_call'] * 1e6:.0f}")
                for name, c in run["calls"].items()]
        out += [f"One thread per point, {run['points']:,} points near the released bunny's surface (D = {run['D']}); "
                "time per call, compile excluded.", ""]
        out += table(["function", "kFLOP (dense)", "µs per call"], rows)
        errs = []
        for mesh, e in run.get("gradient_errors", {}).items():
            for what, ee in e.items():
                errs.append((mesh, what, num(ee["autograd"]["median"], "{:.1e}"), num(ee["autograd"]["max"], "{:.1e}")))
        if errs:
            out += ["", "Gradient errors against float64 torch autograd (relative):", ""]
            out += table(["network", "gradient", "median", "max"], errs)
    return out


@formatter("path_snap", "Paths: the path head, snapped to the mesh, refined")
def fmt_path_snap(runs):
    rows = []
    for run in runs:
        for name, m in run["models"].items():
            for v, r in m["variants"].items():
                rows.append((name, f"{m['vertices']:,}", v, r["pairs"], num(r["chamfer_l1"], "{:.2e}"),
                             num(r["surface_length_over_solver_length_median"], "{:.4f}"),
                             num(r["mean_distance_to_mesh"], "{:.1e}"), num(r["ms_per_pair"], "{:.0f}")))
    return (["Chamfer-L1 to the geodesic solver's paths (128 points, unit-sphere frame); length along the surface "
             "over the solver path's length (median); mean distance of the points from the mesh; time per pair.", ""]
            + table(["model", "vertices", "variant", "pairs", "Chamfer-L1", "length / solver", "off mesh",
                     "ms per pair"], rows))


@formatter("geodesic_tools", "Geodesic tools: sampling, Voronoi cells, reconstruction")
def fmt_geodesic_tools(runs):
    out = []
    for run in runs:
        rows = [(r["mesh"], f"{r['vertices']:,}", r["what"], "neurogf_warp" if r["tool"] == "neurogf" else
                 "heat method (potpourri3d)", f"{r['seconds'] * 1e3:.1f} ms") for r in run["rows"]]
        out += ["Whole public calls, each made once before it is timed (compile and binding apart). The heat method "
                "does the same with one heat solve per sample or seed (its set-up apart).", ""]
        out += table(["mesh", "vertices", "task", "tool", "time"], rows)
        rec = [r for r in run["rows"] if "chamfer_l1" in r]
        for r in rec:
            out += ["", f"Reconstruction of the released bunny's SDF head at {r['what'].split()[-1]}: "
                        f"{r['triangles']:,} triangles, Chamfer-L1 {r['chamfer_l1']:.3g} and Hausdorff "
                        f"{r['hausdorff']:.3g} against the mesh (bounding-box diagonal {r['diagonal']:.3g})."]
        agree = run.get("voronoi_label_agreement_vs_heat")
        if agree is not None:
            out += ["", f"Voronoi labels from the released bunny's field and from the heat method agree on "
                        f"{agree:.1%} of the vertices (the heat method's own error is larger than the field's)."]
    return out


DESIGNS = {"default": "today's network", "no_bn": "no BatchNorm outside the path head",
           "hash": "a 12-level hash-grid encoding appended to the lifting's inputs",
           "landmarks": "exact distances of both points to K landmark vertices fed to the distance head, with the "
                        "triangle-inequality bounds; the lower bound under the output",
           "landmarks_nofloor": "the same features, with |p - q| alone under the output",
           "landmarks_bracket": "the same features, the output between the floor and the landmarks' upper bound"}


def _memory(row: dict) -> str:
    """A bake-off row's model memory: the parameters, plus a landmark design's distance table where recorded."""
    mb = row.get("model_mb", 4 * row.get("params", 0) / 2**20)
    if not row.get("settings", {}).get("landmarks"):
        return f"{mb:.2f} MB"
    return f"{mb + row.get('table_mb', 0.0):.1f} MB"


@formatter("bakeoff", "Field designs: accuracy per second")
def fmt_bakeoff(runs):
    rows = []
    for run in runs:
        for r in run["rows"]:
            if "mre" not in r:
                continue
            ms = r.get("ms_per_step", {})
            rows.append((r["mesh"], f"{r['budget_s']:.0f} s", r["variant"] + (" (2nd run)" if r.get("repeat") else ""),
                         f"{r['call_s']:.1f} s", pct(r["mre"]), pct(r["p99"], 2), pct(r["max"], 1),
                         f"{r['steps'].get('joint', 0):,}/{r['steps'].get('refine_dist', 0):,}",
                         f"{ms.get('joint', float('nan')):.2f}/{ms.get('refine_dist', float('nan')):.2f}"
                         if r["steps"].get("joint") else "-",
                         f"{r.get('params', 0):,}", _memory(r)))
    present = {re.sub(r"\d+$", "", r["variant"]) for run in runs for r in run["rows"]}
    designs = "; ".join(f"`{k}`{'K' if k == 'landmarks' else ''} ({v})" for k, v in DESIGNS.items() if k in present)
    fresh = {bool(run.get("meta", {}).get("one_process_per_row")) for run in runs}
    how = {frozenset([True]): "in a fresh process per row", frozenset([False]): "(the rows of one command in one "
           "process)"}.get(frozenset(fresh), "(a fresh process per row, or the rows of one command in one process "
                                            "where a run's notes say so)")
    out = ["Each design trained by `ngf.train(mesh, out, budget_seconds=B)` " + how + " and scored "
           f"against exact geodesics (every exact source to every vertex). Designs: {designs}. A design is kept only "
           "if its MRE is below the default's by more than the spread of two default runs, on every mesh and "
           "budget. Memory: the float32 parameters, plus a landmark design's (V, K) float32 table of distances to its "
           "landmarks, which a query of it would read too (for rows made before that size was recorded: vertices x K x "
           "4 bytes).", ""]
    out += table(["mesh", "budget", "design", "call", "MRE", "p99", "max", "joint/refine steps",
                  "ms per step", "parameters", "memory"], rows)
    from bakeoff import decide  # the benchmark's own rule, applied to the kept rows

    measured = next((run["meta"]["measured_spread"] for run in runs if run.get("meta", {}).get("measured_spread")),
                    None)
    decision = decide([r for run in runs for r in run["rows"]], measured["spread"] if measured else None)
    out += ["", "Decision" + (f" (the default's run-to-run spread from {measured['from']})" if measured else "")
            + ":", ""]
    for v, d in decision.items():
        if v != "spread":
            out.append(f"- `{v}`: {'kept' if d['keep'] else 'not kept'} ({'; '.join(d['why'])})")
    notes = [n for run in runs for n in run.get("meta", {}).get("notes", [])]
    if notes:
        out += [""] + [f"- {n}" for n in dict.fromkeys(notes)]
    return out


def plot_bakeoff(runs, path):
    from bakeoff import plot

    plot([r for run in runs for r in run["rows"]], path)


PLOTTERS["bakeoff"] = plot_bakeoff


@formatter("ground_truth_setup", "Ground truth: the public call against the solver alone")
def fmt_ground_truth_setup(runs):
    out = []
    for run in runs:
        out += [f"`ngf.geodesic_distances` on the benchmark bunny ({run['vertices']:,} vertices), {run['sources']} "
                "sources, set-up included, against the solver's own solve of the same sources.", ""]
        out += table(["what", "seconds"], [(name.replace(" ", "&nbsp;", 2 if name.startswith("  ") else 0), f"{t:.3f}")
                                           for name, t in run.get("rows", [])])
        if "public_first_sources_per_s" in run:
            out += ["", f"Solver alone {run['solver_sources_per_s']:.1f} sources/s; the public call "
                        f"{run['public_first_sources_per_s']:.1f} sources/s on its first call and "
                        f"{run['public_repeat_sources_per_s']:.1f} on a repeated one (its tables cached): "
                        f"{run['public_first_ratio_to_solver']:.2f}x and {run['public_repeat_ratio_to_solver']:.2f}x "
                        "the solver's time.", ""]
    return out


@formatter("geodesics", "Ground truth: the geodesic solver")
def fmt_geodesics(runs):
    out = []
    for run in runs:
        if run.get("scaling") or run.get("rows"):
            rows = [(r["mesh"], f"{r['vertices']:,}", r.get("batch", "-"), f"{r['sources_per_s']:.3g}",
                     num(r.get("memory_fraction"), "{:.1%}") if r.get("memory_fraction") else "default (25%)")
                    for r in run.get("scaling", []) + run.get("rows", [])]
            out += ["Solver at the defaults, one timed batch of sources after a warm-up batch; distances to every "
                    "vertex copied to the host.", ""]
            out += table(["mesh", "vertices", "rows per batch", "sources / s", "memory budget"], rows)
            extra = []
            for key, label in (("public_call", "plain solve"), ("public_call_near_source", "`near_source=True`")):
                c = run.get(key)
                if c:
                    extra.append(f"`ngf.geodesic_distances` ({label}), {c['sources']} sources on "
                                 f"{c['vertices']:,} vertices: {c['seconds']:.1f} s, {c['sources_per_s']:.3g} sources/s "
                                 "(set-up included)")
            if run.get("cost_exponent_139K_up"):
                extra.append(f"cost per source grows as V^{run['cost_exponent_139K_up']:.2f} from 139K to 2.2M "
                             "vertices")
            if extra:
                out += [""] + [f"- {e}" for e in extra]
            out.append("")
        if run.get("accuracy"):
            rows = [(r["mesh"], f"{r['vertices']:,}", r["sources"], "yes" if r.get("near_source") else "no",
                     pct(r["mre"]), pct(r["max_rel"], 2), pct(r.get("min_rel"), 4))
                    for r in run["accuracy"]]
            out += [f"Accuracy against exact geodesics (MMP), device `{run['device']}`.", ""]
            out += table(["mesh", "vertices", "sources", "near_source", "MRE", "max", "min"], rows)
            out.append("")
    return out[:-1] if out and out[-1] == "" else out


@formatter("time_to_accuracy", "Training under a time budget: accuracy against the call's seconds")
def fmt_time_to_accuracy(runs):
    rows = []
    for run in runs:
        for r in run["rows"]:
            st = r.get("steps") or {}
            rows.append((r["budget_s"], r["mre"], (
                r["mesh"], f"{r['vertices']:,}", f"{r['budget_s']:g} s", f"{r['call_s']:.1f} s", pct(r["mre"]),
                pct(r["p99"], 2), pct(r["max"], 1), pct(r.get("heat_mre")),
                f"{st.get('joint', '-'):,} / {st.get('refine_dist', '-'):,}" if st else "-",
                str(run["provenance"].get("date_utc", ""))[:10])))
    rows.sort(key=lambda x: (x[0], x[1]))
    return (["Each row is one `ngf.train(mesh, out, budget_seconds=B)` call in a fresh process (ground truth, "
             "training and saving included), then `ngf.evaluate` against exact geodesics (8 sources, every vertex); "
             "the heat method (potpourri3d) on the same pairs. One run per row.", ""]
            + table(["mesh", "vertices", "budget", "call", "MRE", "p99", "max", "heat method MRE",
                     "steps joint / refine_dist", "date"], [r[2] for r in rows]))


@formatter("generalizable", "Generalizable network: conditioning and pair queries")
def fmt_generalizable(runs):
    rows = []
    for run in runs:
        rows.append(("conditioning a 2,048-point cloud, into kept buffers", f"{run['encode_ms_median']:.3f} ms"))
        if run.get("encode_graph_ms_median"):
            rows.append(("the same, replayed as a CUDA graph", f"{run['encode_graph_ms_median']:.3f} ms"))
        rows.append(("`model.condition(numpy points)`", f"{run['condition_numpy_ms_median']:.3f} ms"))
        rows.append((f"{run['pairs']:,} pairs, fp32 ({run.get('nearest_lookup', '')} lookup)",
                     f"{run['pairs_ms_median']:.3f} ms, max rel. error vs float64 torch "
                     f"{run['pairs_max_rel_vs_torch_fp64']:.1e}"))
        for tiles, r in (run.get("fp16") or {}).items():
            if "ms_median" in r:
                rows.append((f"{run['pairs']:,} pairs, fp16 tensor cores, tiles {tiles}", f"{r['ms_median']:.3f} ms"))
    return (["The released generalizable network (GenNeuroGF.pth) in Warp; median wall time of synchronized calls.",
             ""] + table(["what", "time"], rows))


def _gen_eval_table(summary: dict) -> list:
    cols = [c for c in ("trained", "released", "heat", "per_mesh") if any(c in v for v in summary.values())]
    names = {"trained": "trained on the collection", "released": "released GenNeuroGF", "heat": "heat method",
             "per_mesh": "per-mesh NeuroGF"}
    rows = [(g, v.get("shapes", "-"), *(pct(v.get(c), 2) for c in cols)) for g, v in summary.items()]
    return table(["shapes", "count", *(names[c] for c in cols)], rows)


@formatter("generalizable_collection", "Generalizable network trained on a generated collection")
def fmt_generalizable_collection(runs):
    out = []
    for run in runs:
        ph = run["summary"]["phases"]
        tr = ph.get("training", {})
        out += [f"{ph['collection']['shapes']} generated shapes in 6 families; ground truth "
                f"{ph['ground_truth']['seconds']:.0f} s ({ph['ground_truth']['per_shape_s']:.2f} s a shape), "
                f"{tr.get('steps', 0):,} training steps in {tr.get('train_seconds', 0):.0f} s, the whole call "
                f"{run['summary'].get('total_seconds', 0):.0f} s. MRE on the same pairs (8 sources x 512 targets a "
                "shape); unseen shapes are of the training families, the shared meshes are not.", ""]
        out += _gen_eval_table(run["eval"]["summary"])
    return out


@formatter("generalizable_eval", "Generalizable network: accuracy on unseen shapes")
def fmt_generalizable_eval(runs):
    out = []
    for run in runs:
        out += _gen_eval_table(run["summary"])
    return out


@formatter("generalizable_scaling", "Generalizable network: ground truth and training on several GPUs")
def fmt_generalizable_scaling(runs):
    rows = []
    for run in runs:
        for r in run["results"]:
            rows.append((r["world"], r["shapes"], f"{r['gt_shapes_per_s']:.2f}", f"{r['gt_speedup']:.2f}x",
                         f"{r['train_shapes_per_s']:.0f}", f"{r['train_speedup']:.2f}x"))
    return (["Ground truth sharded over the ranks (torchrun, one GPU each), then DDP training at a fixed batch per "
             "rank (weak scaling); times exclude process start-up.", ""]
            + table(["ranks", "shapes", "ground truth shapes / s", "speed-up", "training shapes / s", "speed-up"],
                    rows))


@formatter("multi_gpu", "One mesh's ground truth on several GPUs")
def fmt_multi_gpu(runs):
    out = []
    gt = [(run, r) for run in runs for r in run.get("gt", [])]
    if gt:
        present = sorted({run.get("gpus_present") for run, _ in gt if run.get("gpus_present") is not None})
        skipped = sorted({g for run, _ in gt for g in run.get("gpus_skipped") or []})
        out += ["The public call `ngf.geodesic_distances(mesh, sources, devices=[...])` at its defaults, set-up "
                "included (solver cache cleared before each call); the sources split in balanced contiguous blocks, "
                "one thread and one solver per GPU. Same rows: whether the rows equal one GPU's bit for bit, else "
                "the largest relative difference."
                + (f" The machine had {', '.join(map(str, present))} GPUs" if present else "")
                + (f"; no machine of {', '.join(map(str, skipped))} GPUs was lent." if skipped else "."), ""]
        out += table(["mesh", "vertices", "sources", "GPUs", "seconds", "sources / s", "speed-up", "same rows",
                      "commit"],
                     [(r["mesh"], f"{r['vertices']:,}", r["sources"], r["gpus"], f"{r['seconds']:.2f}",
                       f"{r['sources_per_s']:.2f}", f"{r['speedup']:.2f}x",
                       "(reference)" if r["speedup"] == 1.0 and r["max_rel_diff"] == 0.0 and r["identical"]
                       else "yes" if r["identical"] else f"no ({r['max_rel_diff']:.1e})",
                       f"`{run.get('provenance', {}).get('commit')}`") for run, r in gt])
        reps = [run["one_gpu_repeat"] for run in runs if run.get("one_gpu_repeat")]
        if reps:
            same = [r["identical"] for r in reps]
            out += ["", f"One GPU twice on the first {reps[0]['sources']} sources of {reps[0]['mesh']} "
                    f"({len(reps)} runs): " + ("bit-identical every time." if all(same) else
                                               "not bit-identical (largest relative difference "
                                               + span([r["max_rel_diff"] for r in reps], "{:.1e}") + "): the "
                                               "GPU's solve varies from run to run (the order in which threads "
                                               "propose unfolding windows), by about as much as the split over "
                                               "GPUs differs from one GPU.")]
        out.append("")
    for run in runs:
        tr = run.get("train", [])
        if tr:
            out += ["`ngf.train(mesh, out, budget_seconds=B, devices=[...])`: the dataset's ground truth over the GPUs, "
                    "the steps on one; MRE and p99 against the exact reference.", ""]
            out += table(["mesh", "budget", "GPUs (ground truth)", "distance sources", "dataset s", "MRE", "p99"],
                         [(r["mesh"], f"{r['budget_s']:g} s", r["gpus"], r["sources"]["distance"],
                           num(r.get("dataset_s"), "{:.1f}"), pct(r["mre"]), pct(r["p99"], 2)) for r in tr])
            out.append("")
        c = run.get("collection")
        if c:
            out += [f"The generalizable network's ground truth, one rank, {len(c['runs'])} runs "
                    f"(`generalizable_scaling.py`'s `--gt-only` command, commit "
                    f"`{run.get('provenance', {}).get('commit')}`): median {c['median_s']:.1f} s "
                    f"({c['median_shapes_per_s']:.2f} shapes/s), min {c['min_s']:.1f} s, max {c['max_s']:.1f} s "
                    f"(spread {100 * c['spread']:.0f}% of the median).", ""]
            out += table(["run", "shapes", "ground truth s", "shapes / s", "process s"],
                         [(i + 1, r["shapes"], f"{r['gt_s']:.1f}", f"{r['shapes_per_s']:.2f}", f"{r['wall_s']:.1f}")
                          for i, r in enumerate(c["runs"])])
            out.append("")
    return out[:-1] if out and out[-1] == "" else out


def plot_time_to_accuracy(runs, path: Path) -> None:
    """MRE against the budget, one line per mesh (log scale), the heat method's MRE as a dotted line of its colour."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for run in runs for r in run["rows"]]
    meshes = sorted({r["mesh"] for r in rows}, key=lambda m: min(r["mre"] for r in rows if r["mesh"] == m))
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for i, m in enumerate(meshes):
        rs = sorted((r for r in rows if r["mesh"] == m), key=lambda r: r["budget_s"])
        color = f"C{i % 10}"
        ax.plot([r["budget_s"] for r in rs], [100 * r["mre"] for r in rs], "o-", color=color, label=m)
        if rs[0].get("heat_mre"):
            ax.axhline(100 * rs[0]["heat_mre"], color=color, ls=":", lw=0.8)
    ax.set_xscale("log")
    ax.set_yscale("log")
    budgets = sorted({r["budget_s"] for r in rows})
    ax.set_xticks(budgets, [f"{b:g} s" for b in budgets])
    ax.set_xticks([], minor=True)
    ax.set_xlabel("budget of the whole train() call")
    ax.set_ylabel("MRE against exact geodesics (%)")
    ax.set_title("dotted: the heat method on the same pairs", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=90, metadata={"Software": None})
    plt.close(fig)


PLOTTERS["time_to_accuracy"] = plot_time_to_accuracy


# ---- the page ---------------------------------------------------------------------------------------------------

def build(results: Path = RESULTS_DIR, plots: list | None = None) -> str:
    """The page's text; the figures it links are appended to ``plots`` as (function, runs, file name)."""
    plots = [] if plots is None else plots
    files = sorted(results.glob("*.json"))
    docs = []
    for f in files:
        doc = json.loads(f.read_text())
        name = doc.get("benchmark")
        if name not in FORMATTERS:
            raise SystemExit(f"{f}: benchmark {name!r} has no formatter in make_performance.FORMATTERS")
        docs.append((ORDER.index(name) if name in ORDER else len(ORDER), name, f.name, doc))
    docs.sort(key=lambda d: (d[0], d[2]))
    lines = ["# Performance", "",
             "<!-- generated by `python benchmarks/make_performance.py` from benchmarks/results/*.json; "
             "do not edit -->", "",
             "Every table below is made from one result file of `benchmarks/results/`; its header names the command "
             "that produced it, the device, the software versions, the date and the commit. `benchmarks/README.md` "
             "describes each benchmark and how to run it.", ""]
    toc = []
    body = []
    for _, name, fname, doc in docs:
        title, fn = FORMATTERS[name]
        title = doc.get("title") or title  # two files of one benchmark need two headings (and anchors)
        runs = runs_of(doc)
        provs = [r.get("provenance", {}) for r in runs]
        dev = ", ".join(dict.fromkeys(p.get("device_name") or p.get("device") or "?" for p in provs))
        heading = f"{title} — {dev}"
        # the anchor the docs builder (Markdown's toc) gives the heading: runs of hyphens collapse to one
        anchor = re.sub(r"[-\s]+", "-", re.sub(r"[^\w\s-]", "", heading).strip().lower())
        toc.append(f"- [{heading}](#{anchor})")
        body += [f"## {heading}", ""] + header(provs, [fname]) + [""] + fn(runs) + [""]
        if name in PLOTTERS and len({r["budget_s"] for run in runs for r in run.get("rows", [])}) > 1:
            png = Path(fname).with_suffix(".png").name
            body += [f"![{title}, {dev}](performance/{png})", ""]
            plots.append((PLOTTERS[name], runs, png))
    return "\n".join(lines + toc + [""] + body).rstrip() + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--check", action="store_true",
                    help="compare docs/performance.md with a regeneration; exit 1 (with a diff) when they differ")
    ap.add_argument("--results", default=str(RESULTS_DIR), help="folder of result JSON files (default: benchmarks/results)")
    ap.add_argument("-o", "--output", default=str(PAGE), help="the page (default: docs/performance.md)")
    ap.add_argument("--no-plots", action="store_true", help="write the page only, not its figures")
    a = ap.parse_args(argv)
    plots = []
    text = build(Path(a.results), plots)
    out = Path(a.output)
    if a.check:
        old = out.read_text() if out.exists() else ""
        if old == text:
            print(f"{out} is up to date")
            return 0
        sys.stdout.writelines(difflib.unified_diff(old.splitlines(True), text.splitlines(True), str(out),
                                                   "regenerated", n=1))
        print(f"\n{out} differs from its regeneration: run python benchmarks/make_performance.py", file=sys.stderr)
        return 1
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    print(f"wrote {out}")
    if plots and not a.no_plots:
        try:
            import matplotlib  # noqa: F401
        except ImportError:
            print("matplotlib is not installed: the figures were not redrawn")
            return 0
        folder = out.parent / "performance"
        folder.mkdir(exist_ok=True)
        for fn, runs, png in plots:
            fn(runs, folder / png)
            print(f"wrote {folder / png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
