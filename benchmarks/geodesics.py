"""Ground-truth geodesic benchmark: sources/second as the mesh grows, and accuracy against exact MMP per mesh class.

GPU (under 8 minutes on an H200):
    python benchmarks/geodesics.py --device cuda:0 --shared PATH --json out.json
CPU smoke run (a few minutes on 2 cores):
    python benchmarks/geodesics.py --device cpu --small --json out.json
CPU accuracy only, the shared meshes of the solver's worst-pair tail as well (about two minutes on 2 cores):
    python benchmarks/geodesics.py --device cpu --small --skip scaling --meshes fandisk,spot,cow,rocker-arm,cheburashka

Accuracy runs first (it is quick), then the scaling stages from the smallest mesh up.
1. Scaling: the shared bunny (34,834 vertices) midpoint-subdivided 0..3 times (139K, 556K, 2.2M vertices; the
   surface is unchanged) and the 436K-vertex benchmark mesh (`common.subdivided_bunny`: subdivided, then QSlim).
   Per mesh: one `GeodesicSolver` at the defaults, a warm-up batch (graph capture), then one timed batch of
   sources (distances to every vertex, copied to the host): sources/s, iterations, nodes, batch rows. The cost
   exponent is fitted (log-log) from 139K to 2.2M. On the 436K mesh also the public call
   `ngf.geodesic_distances(mesh, 256 sources)` end to end (solver set-up included: the figure a user gets).
   Also a regular bumpy torus of 660 x 660 = 435,600 vertices (well-shaped triangles, no slivers).
   Rows: the 556K mesh with the solver's memory budget at 12.5% and 50% of the free memory (the default is 25%):
   whether a batch of more source rows costs more per source tells if the iterations are latency-bound.
2. Accuracy: every mesh class of `tests/geodesic_meshes.mesh_classes` (stretched, needles, slivers, duplicated
   faces, CAD-like fans; 6 sources each, exact: tvb-gdist on the CPU) and the shared meshes' exact references
   (`reference/exact/*.npz`, all their sources): MRE, max and min relative error.
Prints a table and writes JSON (--json). Every stage reports errors instead of aborting the run.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
import traceback
from pathlib import Path

import numpy as np

import _bootstrap  # noqa: F401  (this checkout's neurogf_warp, installed or not)
import common


def bunny(subdivisions: int):
    import trimesh

    tm = trimesh.load(common.find_shared("meshes", "stanford-bunny.obj"), process=False, force="mesh")
    v, f = np.asarray(tm.vertices), np.asarray(tm.faces)
    used = np.unique(f)
    remap = np.full(len(v), -1)
    remap[used] = np.arange(len(used))
    v, f = v[used], remap[f]
    for _ in range(subdivisions):
        v, f = trimesh.remesh.subdivide(v, f)
    return np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64)


def rate(name, V, F, device, max_sources: int, out: dict, memory_fraction: float | None = None, key="scaling",
         warmup: bool = True):
    """Warm-up batch, then one timed batch: sources/s of distances to every vertex (copied to the host).
    memory_fraction: the solver's memory budget as a fraction of the free device memory (default: the solver's
    own, 25%). Without warm-up the timed batch includes the graph capture (milliseconds on CUDA)."""
    import warp as wp

    from neurogf_warp.ground_truth.geodesics import GeodesicSolver
    from neurogf_warp.mesh.mesh import load_mesh

    t0 = time.perf_counter()
    m = load_mesh((V, F))
    budget = None
    dev = wp.get_device(device)
    if memory_fraction is not None and dev.is_cuda:
        budget = memory_fraction * float(dev.free_memory)
    solver = GeodesicSolver(m, device=device, max_rows=max_sources, memory_budget=budget)
    setup = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    n = min(solver.batch, max_sources)
    src = rng.choice(solver.nv, 2 * n, replace=len(V) < 2 * n)
    t0 = time.perf_counter()
    if warmup:
        solver.run(src[:n])
        solver.vertex_distances()
        wp.synchronize_device(solver.device)
    warm = time.perf_counter() - t0
    t0 = time.perf_counter()
    solver.run(src[n:])
    solver.vertex_distances()
    wp.synchronize_device(solver.device)
    dt = time.perf_counter() - t0
    row = dict(mesh=name, memory_fraction=memory_fraction, vertices=len(m.internal_vertices), faces=len(m.internal_faces), nodes=solver.n_nodes, batch=solver.batch,
               sources=n, setup_s=setup, warmup_s=warm, solve_s=dt, sources_per_s=n / dt,
               iterations=solver.timings["iterations"][-1], relaxed_per_source=solver.work_stats()["relaxed_per_source"])
    out.setdefault(key, []).append(row)
    print(f"{name:28s} V={row['vertices']:>9,d} nodes={row['nodes']:>10,d} batch={row['batch']:4d} "
          f"{n} sources in {dt:.2f} s: {row['sources_per_s']:.2f} sources/s ({row['iterations']} iterations; "
          f"set-up {setup:.1f} s, warm-up {warm:.1f} s)", flush=True)
    del solver


def public_call(V, F, device, n: int, out: dict):
    import neurogf_warp as ngf

    src = np.random.default_rng(1).choice(len(V), n, replace=False)
    plain = None
    for near in (False, True):  # near_source=True: the k=6 patch solves (ground_truth/near_source.py), side by side
        t0 = time.perf_counter()
        d = ngf.geodesic_distances((V, F), src, device=device, near_source=near)
        dt = time.perf_counter() - t0
        key = "public_call_near_source" if near else "public_call"
        out[key] = dict(vertices=len(V), sources=n, seconds=dt, sources_per_s=n / dt,
                        finite=bool(np.isfinite(d).all()))
        if near:  # never longer than the plain call (the minimum of two real path lengths)
            out[key]["never_longer"] = bool(np.all(d <= plain * (1 + 1e-6)))
        plain = d
        print(f"ngf.geodesic_distances{'(near_source=True)' if near else ''} on {len(V):,d} vertices, {n} sources: "
              f"{dt:.2f} s ({n / dt:.2f} sources/s, set-up included)", flush=True)


def accuracy(name, V, F, src, exact, device, out: dict):
    from neurogf_warp.ground_truth.geodesics import geodesic_distances

    for near in (False, True):
        t0 = time.perf_counter()
        d = geodesic_distances((V, F), src, device=device, near_source=near).astype(np.float64)
        dt = time.perf_counter() - t0
        ok = np.isfinite(exact) & (exact > 0) & np.isfinite(d)
        rel = (d[ok] - exact[ok]) / exact[ok]
        row = dict(mesh=name, near_source=near, vertices=len(V), sources=len(src), mre=float(np.abs(rel).mean()),
                   max_rel=float(rel.max()), min_rel=float(rel.min()),
                   pairs_over_half_percent=int((rel > 5e-3).sum()), seconds=dt,
                   meets=bool(np.abs(rel).mean() <= 5e-4 and rel.max() <= 5e-3))
        out.setdefault("accuracy", []).append(row)
        print(f"{name + (' near_source' if near else ''):36s} V={len(V):>7,d} MRE {row['mre'] * 100:.4f}%  "
              f"max {row['max_rel'] * 100:.3f}%  min {row['min_rel']:.1e}  >0.5%: {row['pairs_over_half_percent']}  "
              f"({dt:.1f} s) {'ok' if row['meets'] else 'MISSED'}", flush=True)


def shared_reference(name):
    import trimesh

    ref = np.load(common.find_shared("reference", "exact", f"{name}.npz"))
    ext = "ply" if name == "igea" else "obj"
    tm = trimesh.load(common.find_shared("meshes", f"{name}.{ext}"), process=False, force="mesh")
    inv = np.full(len(tm.vertices), -1)
    inv[ref["orig_index"]] = np.arange(len(ref["orig_index"]))
    return ref["positions"].astype(np.float64), inv[np.asarray(tm.faces)], ref["sources"], ref["dist"].astype(np.float64)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--shared", default=None, help="the shared data folder (meshes/, reference/)")
    ap.add_argument("--small", action="store_true", help="CPU smoke run: bunny only, few sources, small meshes")
    ap.add_argument("--subdivisions", type=int, default=3, help="bunny midpoint subdivisions: 0..N (3: 2.2M)")
    ap.add_argument("--max-sources", type=int, default=64, help="sources in the timed batch (at most one batch)")
    ap.add_argument("--public-sources", type=int, default=256)
    ap.add_argument("--bench-vertices", type=int, default=436_000, help="the QSlim benchmark mesh's vertices")
    ap.add_argument("--rows-sources", type=int, default=512, help="rows stage: at most this many rows")
    ap.add_argument("--meshes", default=None,
                    help="comma list of shared meshes for the accuracy stage (default: fandisk,spot,cow with --small, "
                         "all nine otherwise)")
    ap.add_argument("--skip", default="", help="comma list of stages to skip: scaling,public,rows,classes,shared")
    ap.add_argument("--time-limit", type=float, default=420.0,
                    help="stages that would start after this many seconds are skipped (listed in the JSON)")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    if a.shared:
        common.SHARED = Path(a.shared).resolve()
    skip = set(filter(None, a.skip.split(",")))

    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    from neurogf_warp.ground_truth import geodesics as G

    dev = wp.get_device(a.device)
    out = {"device": a.device, "device_name": getattr(dev, "name", str(dev)), "k": G.DEFAULT_K,
           "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "errors": {}}
    t0 = time.perf_counter()
    G.load_kernels(dev)
    out["compile_s"] = time.perf_counter() - t0
    print(f"kernels loaded in {out['compile_s']:.1f} s", flush=True)

    t_start = time.perf_counter()

    def stage(key, fn, *args):
        if time.perf_counter() - t_start > a.time_limit:
            out.setdefault("skipped", []).append(key)  # keeps the whole run inside a fixed time slot
            print(f"skipped {key}: past --time-limit {a.time_limit:.0f} s", flush=True)
            return
        try:
            fn(*args)
        except Exception as e:  # noqa: BLE001 - report and go on
            out["errors"][key] = repr(e)
            traceback.print_exc()

    if "classes" not in skip:
        print("== accuracy per mesh class (exact: tvb-gdist, float64, CPU)", flush=True)
        from tests import geodesic_meshes as M
        from tests.reference_geodesics import gdist_distances

        for name, (V, F, R) in M.mesh_classes().items():
            def one(name=name, V=V, F=F, R=R):
                src = np.random.default_rng(0).choice(len(V), 6, replace=False)
                accuracy(name, V, F, src, gdist_distances(V, R, src), dev, out)
            stage(f"class-{name}", one)

    if "shared" not in skip:
        print("== accuracy on the shared meshes (exact references)", flush=True)
        names = ["fandisk", "spot", "cow"] if a.small else ["fandisk", "spot", "cow", "homer", "rocker-arm",
                                                            "cheburashka", "alligator", "stanford-bunny", "igea"]
        if a.meshes:
            names = [n for n in a.meshes.split(",") if n]
        for name in names:
            def one(name=name):
                V, F, src, ex = shared_reference(name)
                accuracy(name, V, F, src, ex, dev, out)
            stage(f"shared-{name}", one)

    if "scaling" not in skip:
        print("== scaling (subdivided bunny; 436K benchmark mesh)", flush=True)
        for s in range((0 if a.small else a.subdivisions) + 1):
            stage(f"scaling-{s}", lambda s=s: rate(f"bunny x{s} subdivided", *bunny(s), dev,
                                                   4 if a.small else a.max_sources, out))
        if not a.small:
            V436, F436 = common.subdivided_bunny(a.bench_vertices)
            stage("scaling-436K", rate, f"benchmark bunny {a.bench_vertices // 1000}K (QSlim)", V436, F436, dev,
                  a.max_sources, out)
            if "public" not in skip:
                stage("public", public_call, V436, F436, dev, a.public_sources, out)
            del V436, F436
            # a regular torus of the same size without slivers: how much the bunny's triangle shapes cost
            n = int(round(np.sqrt(a.bench_vertices)))
            stage("scaling-torus", lambda: rate(f"bumpy torus {n}x{n}", *common.bumpy_torus(n), dev,
                                                a.max_sources, out))
        if not a.small and "rows" not in skip:
            # does a batch of more rows cost more per source? (latency-bound iterations: no; throughput-bound: yes)
            V2, F2 = bunny(min(2, a.subdivisions))
            for frac in (0.125, 0.5):
                stage(f"rows-{frac}", rate, f"bunny x{min(2, a.subdivisions)}, memory {frac:.1%}", V2, F2, dev,
                      a.rows_sources, out, frac, "rows", False)
            del V2, F2
        pts = [(r["vertices"], r["sources_per_s"]) for r in out.get("scaling", []) if "subdivided" in r["mesh"]
               and r["vertices"] > 100_000]
        if len(pts) >= 2:
            x, y = np.log([p[0] for p in pts]), np.log([1.0 / p[1] for p in pts])
            out["cost_exponent_139K_up"] = float(np.polyfit(x, y, 1)[0])
            print(f"cost per source grows like V^{out['cost_exponent_139K_up']:.2f} above 100K vertices", flush=True)

    out["total_s"] = time.perf_counter() - t_start
    if out["errors"]:
        print("errors:", json.dumps(out["errors"], indent=1))
    path = common.write_json(a.json or f"geodesics_{'small' if a.small else 'full'}_{dev.alias.replace(':', '')}.json",
                             out, "geodesics", a.device)
    print(f"wrote {path}")
    return 1 if out["errors"] else 0


if __name__ == "__main__":
    sys.exit(main())
