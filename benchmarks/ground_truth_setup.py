"""The ground-truth solver's per-call set-up, phase by phase, and the public call's rate against the solver's own.

    python benchmarks/ground_truth_setup.py --device cuda:0 --vertices 436000 --sources 256 --json out.json
    python benchmarks/ground_truth_setup.py --device cpu --vertices 50000 --sources 1      # a small CPU run

Mesh: the shared Stanford bunny midpoint-subdivided until it has at least ``--vertices`` vertices, then QSlim-ed
back down (the 436K-vertex benchmark mesh at the default; a conforming mesh, no T-junctions). Kernels are compiled
and loaded first (reported apart). Then:

1. set-up: ``GeodesicSolver(mesh, device, max_rows=sources)`` ``--repeat`` times, each phase's median
   (``timings["setup_phases"]``: vertex order, mesh tables, Steiner counts, per-face slot offsets, uploads, tables
   built on the device, solver state), and ``load_mesh`` of the arrays;
2. the solver alone: a warm-up batch (graph capture), then ``solver.solve`` of ``--sources`` sources (every batch,
   distances copied to the host in mesh order): sources/s;
3. ``refine_near_sources`` on those rows (the public call's default second solve near each source);
4. the public call ``ngf.geodesic_distances((V, F), sources, device)`` at its defaults, set-up included, twice
   (a repeated call on the same mesh may reuse the first call's solver set-up): sources/s, and its ratio to (2).

``--check`` also compares the solver's device-built tables with their numpy reference (bit for bit: the set-up's
own check) and the public call's distances with (2) + (3) (equal unless the device's solves vary from run to run). Prints a table; writes JSON (``--json``) with the command, date, commit,
versions and machine load.
"""
from __future__ import annotations

import argparse
import datetime
import gc
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

import _bootstrap  # noqa: E402,F401  (this checkout's neurogf_warp, installed or not)
from common import ROOT, subdivided_bunny as benchmark_mesh, write_json  # noqa: E402


def _sync(device):
    import warp as wp

    wp.synchronize_device(device)


def _commit() -> str:
    try:
        return subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, timeout=10).stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def check_tables(solver) -> dict:
    """The device-built tables against their numpy reference (steiner_graph): equal bit for bit?"""
    from neurogf_warp.ground_truth import steiner_graph as sg

    start, node_edge, node_t = solver.topo.steiner_nodes(solver.k)
    g = solver.graph
    ns = len(node_edge)
    xyz = sg.node_positions(solver._positions, solver.topo.edges, node_edge, node_t)
    slot_start, codes = sg.face_slot_table(solver.topo.faces, solver.topo.face_edges, start, solver.nv)
    same = {
        "edge_node_start": np.array_equal(g.edge_node_start.numpy(), start),
        "node_edge": np.array_equal(g.node_edge.numpy()[:ns], node_edge),
        "node_t": np.array_equal(g.node_t.numpy()[:ns].view(np.uint32), node_t.view(np.uint32)),
        "node_xyz": np.array_equal(g.node_xyz.numpy().view(np.uint32), xyz.view(np.uint32)),
        "face_slot_start": np.array_equal(g.face_slot_start.numpy(), slot_start),
        "face_slot": np.array_equal(g.face_slot.numpy(), codes),
    }
    return same


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--vertices", type=int, default=436_000, help="mesh size (the bunny subdivided, then QSlim-ed)")
    ap.add_argument("--sources", type=int, default=None, help="sources of the timed solves (default: 256 on CUDA, "
                                                             "1 on the CPU)")
    ap.add_argument("--repeat", type=int, default=3, help="set-up repetitions (median per phase)")
    ap.add_argument("--setup-only", action="store_true", help="only the set-up phases (no solves)")
    ap.add_argument("--check", action="store_true", help="compare device tables and public-call distances")
    ap.add_argument("--mesh-cache", default=None, help="an .npz file: the built mesh is read from it when it exists, "
                                                       "else written to it")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)

    import neurogf_warp as ngf
    import warp as wp

    from neurogf_warp.ground_truth.near_source import refine_near_sources
    from neurogf_warp.ground_truth.solver import GeodesicSolver, load_kernels
    from neurogf_warp.mesh.mesh import load_mesh

    wp.config.quiet = True
    wp.init()
    device = wp.get_device(a.device)
    S = a.sources if a.sources is not None else (256 if device.is_cuda else 1)
    out = {"command": "python " + " ".join([sys.argv[0]] + (argv if argv is not None else sys.argv[1:])),
           "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
           "commit": _commit(), "device": str(device), "device_name": getattr(device, "name", str(device)),
           "versions": {"python": platform.python_version(), "numpy": np.__version__, "warp": wp.config.version},
           "cpu_count": os.cpu_count(), "load_average_start": list(os.getloadavg()), "sources": S}

    t0 = time.perf_counter()
    if a.mesh_cache and Path(a.mesh_cache).exists():
        z = np.load(a.mesh_cache)
        V, F = z["vertices"], z["faces"]
    else:
        V, F = benchmark_mesh(a.vertices)
        if a.mesh_cache:
            np.savez(a.mesh_cache, vertices=V, faces=F)
    out["mesh_build_s"] = time.perf_counter() - t0
    out["vertices"], out["faces"] = len(V), len(F)
    print(f"mesh: {len(V):,} vertices, {len(F):,} faces (built in {out['mesh_build_s']:.1f} s); device {device}; "
          f"{S} sources", flush=True)

    # compile / load every kernel and capture once on a tiny mesh, so that no timing below includes it
    t0 = time.perf_counter()
    load_kernels(device)
    ico_v, ico_f = benchmark_ico()
    warm = GeodesicSolver((ico_v, ico_f), device=device, max_rows=2)
    warm.run(np.arange(2))
    _sync(device)
    ngf.geodesic_distances((ico_v, ico_f), [0, 1], device=device)
    del warm
    out["compile_s"] = time.perf_counter() - t0

    # 1. set-up phases
    t0 = time.perf_counter()
    m = load_mesh((V, F))
    out["load_mesh_s"] = time.perf_counter() - t0
    runs = []
    solver = None
    for r in range(max(1, a.repeat)):
        solver = None
        gc.collect()
        t0 = time.perf_counter()
        solver = GeodesicSolver(m, device=device, max_rows=S)
        _sync(device)
        total = time.perf_counter() - t0
        runs.append(dict(solver.timings.get("setup_phases", {}), total=total))
    phases = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
    out["setup_phases_s"] = phases
    out["setup_runs"] = runs
    out["nodes"], out["batch"] = solver.n_nodes, solver.batch
    if a.check:
        out["tables_identical"] = check_tables(solver)

    rows = [("load_mesh (arrays)", out["load_mesh_s"])] + [(f"  {k}", v) for k, v in phases.items() if k != "total"]
    rows.append(("GeodesicSolver(...) total", phases["total"]))

    if not a.setup_only:
        rng = np.random.default_rng(1)
        src = rng.choice(len(V), S, replace=S > len(V))
        msrc = m.vertex(src)
        # 2. the solver alone
        n = min(solver.batch, S)
        t0 = time.perf_counter()
        solver.run(rng.choice(solver.nv, n, replace=n > solver.nv))
        solver.vertex_distances()
        _sync(device)
        out["warmup_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        d = solver.solve(msrc)
        _sync(device)
        out["solver_s"] = time.perf_counter() - t0
        out["solver_sources_per_s"] = S / out["solver_s"]
        # 3. near-source patches
        t0 = time.perf_counter()
        d2 = refine_near_sources(solver, msrc, d)
        _sync(device)
        out["near_source_s"] = time.perf_counter() - t0
        ref = m.to_input((d2 / np.float32(m.scale)).astype(np.float32)) if a.check else None
        del d, d2
        solver = None
        gc.collect()
        rows += [("solver.solve (warm)", out["solver_s"]), ("refine_near_sources", out["near_source_s"])]
        # 4. the public call, twice
        for i in range(2):
            t0 = time.perf_counter()
            got = ngf.geodesic_distances((V, F), src, device=device)
            _sync(device)
            dt = time.perf_counter() - t0
            key = "public_first" if i == 0 else "public_repeat"
            out[key + "_s"] = dt
            out[key + "_sources_per_s"] = S / dt
            out[key + "_ratio_to_solver"] = out["solver_sources_per_s"] / (S / dt)
            if a.check and ref is not None:
                out[key + "_identical_to_solver"] = bool(np.array_equal(got, ref, equal_nan=True))
                both = np.isfinite(got) & np.isfinite(ref) & (ref > 0)
                out[key + "_max_rel_diff_to_solver"] = float(np.max(np.abs(got[both] - ref[both]) / ref[both],
                                                                    initial=0.0))
            del got
            gc.collect()
            rows.append((f"ngf.geodesic_distances ({'first' if i == 0 else 'repeat'} call)", dt))
    out["load_average_end"] = list(os.getloadavg())
    out["rows"] = rows

    print(f"\n{'phase':44s} {'seconds':>9s}")
    for name, v in rows:
        print(f"{name:44s} {v:9.3f}")
    if not a.setup_only:
        print(f"\nsolver alone {out['solver_sources_per_s']:.2f} sources/s; public call "
              f"{out['public_first_sources_per_s']:.2f} sources/s first, {out['public_repeat_sources_per_s']:.2f} "
              "repeated (ratio "
              f"{out['public_first_ratio_to_solver']:.2f}x / {out['public_repeat_ratio_to_solver']:.2f}x)")
    if a.check:
        print("device tables equal to the numpy reference:", out["tables_identical"])
        for key in ("public_first", "public_repeat"):
            if key + "_identical_to_solver" in out:
                print(f"{key} distances equal to solve + refine_near_sources: {out[key + '_identical_to_solver']} "
                      f"(largest relative difference {out[key + '_max_rel_diff_to_solver']:.2e})")
    print(f"load average {out['load_average_start']} -> {out['load_average_end']} on {os.cpu_count()} cores")
    if a.json:
        write_json(a.json, out, "ground_truth_setup", str(device))
    return 0


def benchmark_ico():
    """A small closed mesh (an icosphere) for the compile / capture warm-up."""
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=2)
    return np.asarray(s.vertices, dtype=np.float64), np.asarray(s.faces, dtype=np.int64)


if __name__ == "__main__":
    sys.exit(main())
