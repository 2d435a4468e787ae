"""Ground-truth geodesic benchmark: sources/second, peak memory, accuracy vs tvb-gdist (exact) and heat method.

GPU (lead's machine):   python benchmarks/geodesics.py --device cuda:0
CPU smoke test (here):  python benchmarks/geodesics.py --device cpu --small

Distances and paths come from the same solver runs (paths for the first --path-sources sources); a progress line
per batch (flushed) shows the rate so far.

Default mesh: a generated bumpy torus of about --vertices (436,000; 660 x 660) vertices, clean triangles.
Prints a table and writes JSON (--json). Compile time is measured apart from run time; every stage reports
errors instead of aborting the whole run.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
import traceback
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ROOT, bumpy_torus, find_shared  # noqa: E402


def make_mesh(small: bool, vertices: int):
    import trimesh

    if small:
        tm = trimesh.load(find_shared("meshes", "fandisk.obj"), process=False, force="mesh")
        return np.asarray(tm.vertices), np.asarray(tm.faces), "fandisk"
    n = int(round(np.sqrt(vertices)))
    v, f = bumpy_torus(n)
    return v, f, f"bumpy-torus-{n}x{n}"


def peak_mem(device) -> float | None:
    import warp as wp

    for name in ("get_mempool_used_mem_high", "get_mempool_used_mem_current"):
        fn = getattr(wp, name, None)
        if fn is not None and device.is_cuda:
            try:
                return float(fn(device))
            except Exception:  # noqa: BLE001
                pass
    return None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--small", action="store_true", help="fandisk, few sources (CPU smoke test)")
    ap.add_argument("--vertices", type=int, default=436_000, help="vertices of the generated torus")
    ap.add_argument("--sources", type=int, default=None, help="default 1024 (8 with --small)")
    ap.add_argument("--path-sources", type=int, default=None, help="default = --sources (2 with --small)")
    ap.add_argument("--paths", type=int, default=32, help="paths per path source")
    ap.add_argument("--check", type=int, default=None, help="sources checked against gdist (3; 2 with --small)")
    ap.add_argument("--k", type=int, default=None)
    ap.add_argument("--batch", type=int, default=None)
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)

    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    from neurogf_warp.ground_truth import geodesics as G
    from neurogf_warp.mesh.mesh import load_mesh

    k = a.k or G.DEFAULT_K
    n_src = a.sources or (8 if a.small else 1024)
    n_psrc = a.path_sources if a.path_sources is not None else (2 if a.small else n_src)
    n_check = a.check if a.check is not None else (2 if a.small else 3)
    res = {"device": a.device, "k": k, "errors": {}}
    dev = wp.get_device(a.device)
    res["device_name"] = dev.name if hasattr(dev, "name") else str(dev)

    t0 = time.perf_counter()
    V, F, name = make_mesh(a.small, a.vertices)
    m = load_mesh((V, F))
    res.update(mesh=name, vertices=len(m.vertices), faces=len(m.faces), mesh_build_s=time.perf_counter() - t0)
    rng = np.random.default_rng(0)
    src = rng.choice(len(m.vertices), n_src, replace=False)

    t0 = time.perf_counter()
    try:
        G.load_kernels(dev)
        res["compile_s"] = time.perf_counter() - t0
    except Exception as e:  # noqa: BLE001
        res["errors"]["compile"] = repr(e)
        traceback.print_exc()

    # distances and paths from the same runs (paths for the first --path-sources sources)
    D = None
    try:
        solver = G.GeodesicSolver(m, k=k, device=dev, batch=a.batch, max_rows=n_src)
        res.update(nodes=solver.n_nodes, batch=solver.batch, setup_s=solver.timings["setup_s"],
                   bytes_per_row=solver.bytes_per_row)
        print(f"nodes {solver.n_nodes}, batch {solver.batch} rows, "
              f"{solver.bytes_per_row / 1e9:.3f} GB per row", flush=True)
        solver.run(src[: solver.batch])  # warm-up: graph capture + first replay
        wp.synchronize_device(dev)
        solver.timings.update(solve_s=0.0, iterations=[], work=[])
        nb = (n_src + solver.batch - 1) // solver.batch
        D = np.empty((min(n_check, n_src), len(m.vertices)), np.float32)
        t_path = 0.0
        npts = 0
        lens_err, stale = [], 0
        visits = relaxed = 0.0
        t0 = time.perf_counter()
        for bi, i in enumerate(range(0, n_src, solver.batch)):
            s = src[i: i + solver.batch]
            solver.run(s)
            ws = solver.work_stats()
            visits += ws["visits_per_source"] * len(s)
            relaxed += (ws["relaxed_per_source"] or 0.0) * len(s)
            dist = solver.vertex_distances()
            if i < len(D):
                D[i: i + len(s)] = dist[: len(D) - i]
            npr = min(len(s), max(0, n_psrc - i))
            if npr:
                tp = time.perf_counter()
                rows = np.repeat(np.arange(npr), a.paths)
                tg = rng.integers(0, len(m.vertices), len(rows))
                pts, offs, st = solver.trace(rows, tg)
                P = G.resample_polyline(pts, offs, 128)
                t_path += time.perf_counter() - tp
                npts += len(pts)
                stale += int(np.sum(st != 0))
                d = dist[rows, tg]
                seg = np.linalg.norm(np.diff(pts.astype(np.float64), axis=0), axis=1)
                cs = np.r_[0, np.cumsum(seg)]
                L = cs[offs[1:] - 1] - cs[offs[:-1]]
                ok = np.isfinite(d) & (d > 0) & (st == 0)  # flagged paths come back as NaN
                lens_err.extend((np.abs(L[ok] - d[ok]) / d[ok]).tolist())
                del P
            el = time.perf_counter() - t0
            done = i + len(s)
            print(f"batch {bi + 1}/{nb}: {done} sources in {el:.1f} s ({done / el:.2f} sources/s), "
                  f"{solver.timings['iterations'][-1]} iterations, {ws['visits_per_source']:.3g} node visits/source",
                  flush=True)
        wp.synchronize_device(dev)
        dt = time.perf_counter() - t0
        res.update(total_s=dt, sources_per_s=n_src / dt, dist_s=dt - t_path, dist_sources_per_s=n_src / (dt - t_path),
                   iterations=solver.timings["iterations"], captured_graph=solver.captured,
                   peak_mem_bytes=peak_mem(dev), state_bytes=solver.batch * solver.bytes_per_row,
                   node_visits_per_source=visits / n_src, relaxed_per_source=relaxed / n_src)
        if n_psrc:
            res.update(path_s=t_path, path_sources_per_s=min(n_psrc, n_src) / max(t_path, 1e-9),
                       paths_total=min(n_psrc, n_src) * a.paths,
                       path_points_mean=npts / max(min(n_psrc, n_src) * a.paths, 1), path_stale=stale,
                       path_len_vs_dist_max_rel=float(np.max(lens_err)) if len(lens_err) else None)
        D = D / m.scale
        del solver
    except Exception as e:  # noqa: BLE001
        res["errors"]["distances"] = repr(e)
        traceback.print_exc()

    # exact (tvb-gdist) and heat (potpourri3d) on the first n_check sources, CPU
    if n_check and D is not None:
        csrc = src[:n_check]
        try:
            import gdist

            t0 = time.perf_counter()
            ex = np.stack([gdist.compute_gdist(m.vertices.astype(np.float64), m.faces.astype(np.int32),
                                               source_indices=np.array([s], np.int32)) for s in csrc])
            res["gdist_s_per_source"] = (time.perf_counter() - t0) / n_check
            mk = np.isfinite(ex) & (ex > 0) & np.isfinite(D)
            rel = (D[mk] - ex[mk]) / ex[mk]
            res.update(ours_mre=float(rel.mean()), ours_max_rel=float(rel.max()), ours_min_rel=float(rel.min()))
            try:
                import potpourri3d as pp3d

                t0 = time.perf_counter()
                hs = pp3d.MeshHeatMethodDistanceSolver(m.vertices, m.faces)
                res["heat_setup_s"] = time.perf_counter() - t0
                t0 = time.perf_counter()
                H = np.stack([hs.compute_distance(int(s)) for s in csrc])
                res["heat_s_per_source"] = (time.perf_counter() - t0) / n_check
                rh = np.abs(H[mk] - ex[mk]) / ex[mk]
                res.update(heat_mre=float(rh.mean()), heat_max_rel=float(rh.max()))
            except Exception as e:  # noqa: BLE001
                res["errors"]["heat"] = repr(e)
        except Exception as e:  # noqa: BLE001
            res["errors"]["gdist"] = repr(e)
            traceback.print_exc()

    def fmt(key, unit="", scale=1.0, prec=3):
        v = res.get(key)
        return "n/a" if v is None else f"{v * scale:.{prec}f}{unit}"

    print(f"\nmesh {res['mesh']}: {res['vertices']} vertices, {res['faces']} faces; device {res['device_name']}; "
          f"k={k}, nodes={res.get('nodes')}, batch={res.get('batch')}")
    rows = [
        ("compile (s)", fmt("compile_s")), ("setup (s)", fmt("setup_s")),
        (f"distances + paths: {n_src} sources (s)", fmt("total_s")), ("sources / s (both)", fmt("sources_per_s", prec=2)),
        ("distance solve (s)", fmt("dist_s")), ("distance sources / s", fmt("dist_sources_per_s", prec=2)),
        (f"paths: {n_psrc} sources x {a.paths}, trace + resample (s)", fmt("path_s")),
        ("node visits / source", fmt("node_visits_per_source", prec=0)),
        ("relaxed nodes / source", fmt("relaxed_per_source", prec=0)),
        ("stale paths", fmt("path_stale", prec=0)),
        ("path length vs distance, max rel", fmt("path_len_vs_dist_max_rel", prec=2 if False else 7)),
        ("peak GPU mempool (GB)", fmt("peak_mem_bytes", scale=1e-9)),
        ("solver state estimate (GB)", fmt("state_bytes", scale=1e-9)),
        (f"ours vs gdist MRE % ({n_check} src)", fmt("ours_mre", scale=100, prec=4)),
        ("ours vs gdist max rel %", fmt("ours_max_rel", scale=100, prec=3)),
        ("ours vs gdist min rel (>= -1e-6)", fmt("ours_min_rel", prec=8)),
        ("gdist exact, s / source (CPU)", fmt("gdist_s_per_source")),
        ("heat (pp3d) MRE % / max %", f"{fmt('heat_mre', scale=100, prec=3)} / {fmt('heat_max_rel', scale=100, prec=1)}"),
        ("heat setup / s per source (CPU)", f"{fmt('heat_setup_s')} / {fmt('heat_s_per_source', prec=4)}"),
    ]
    w = max(len(r[0]) for r in rows)
    for r in rows:
        print(f"  {r[0]:<{w}}  {r[1]}")
    if res["errors"]:
        print("errors:", json.dumps(res["errors"], indent=1))
    out = a.json or str(ROOT / "benchmarks" / f"geodesics_{'small' if a.small else 'full'}_{dev.alias.replace(':', '')}.json")
    with open(out, "w") as f:
        json.dump(res, f, indent=1, default=float)
    print(f"wrote {out}")
    return 1 if res["errors"] else 0


if __name__ == "__main__":
    sys.exit(main())
