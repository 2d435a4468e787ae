"""Ground-truth solver on the GPU: where an iteration's time goes, and variants of the relax launch.
usage: python .bm/gt_lanes.py OUT.json [stages: acc,rate,prof,big]"""
import json
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import time_to_accuracy as tta  # noqa: E402

tta._import_from_checkout()
import numpy as np  # noqa: E402
import trimesh  # noqa: E402
import warp as wp  # noqa: E402

import neurogf_warp.ground_truth.solver as S  # noqa: E402
from neurogf_warp.mesh.mesh import load_mesh  # noqa: E402

BM = Path(os.environ.get("BM_DIR", Path(__file__).resolve().parent))
OUT = {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "rows": [], "acc": [], "prof": []}
out_path = sys.argv[1] if len(sys.argv) > 1 else "/dev/null"
stages = sys.argv[2].split(",") if len(sys.argv) > 2 else []
OLD = "old" in stages
import os
DEV = os.environ.get("DEV", "cuda:0")
dev = wp.get_device(DEV)
OUT["device"] = dev.name


def save():
    json.dump(OUT, open(out_path, "w"), indent=1)


def bunny(sub):
    tm = trimesh.load(BM / "meshes" / "stanford-bunny.obj", process=False, force="mesh")
    v, f = np.asarray(tm.vertices), np.asarray(tm.faces)
    used = np.unique(f)
    remap = np.full(len(v), -1)
    remap[used] = np.arange(len(used))
    v, f = v[used], remap[f]
    for _ in range(sub):
        v, f = trimesh.remesh.subdivide(v, f)
    return np.asarray(v, np.float64), np.asarray(f, np.int64)


def qslim436():
    import fast_simplification

    v, f = bunny(2)
    v, f = fast_simplification.simplify(v.astype(np.float32), f.astype(np.int32), 1.0 - 436_000 / len(v))
    return np.asarray(v, np.float64), np.asarray(f, np.int64)


def make(mesh, lanes=4, threads=(32, 16384, 1 << 20), frac=None, delta=2.0, max_rows=None, batch=None, regs=None):
    S.RELAX_LANES = lanes
    S.ROW_THREADS = threads
    budget = frac * float(dev.free_memory) if frac and dev.is_cuda else None
    return S.GeodesicSolver(mesh, device=DEV, memory_budget=budget, delta=delta, max_rows=max_rows,
                            batch=batch)


def timed(sol, src):
    wp.synchronize_device(dev)
    t0 = time.perf_counter()
    sol.run(src)
    d = sol.vertex_distances()
    return time.perf_counter() - t0, d


def rate(name, mesh, **kw):
    if OLD and kw.get("lanes", 1) != 1:
        return
    try:
        t0 = time.perf_counter()
        sol = make(mesh, **{k: v for k, v in kw.items()})
        setup = time.perf_counter() - t0
        rng = np.random.default_rng(0)
        n = sol.batch
        src = rng.choice(sol.nv, 2 * n, replace=sol.nv < 2 * n)
        warm, _ = timed(sol, src[:n])
        dt, d = timed(sol, src[n:])
        it = sol.timings["iterations"][-1]
        ws = sol.work_stats()
        row = dict(mesh=name, V=sol.nv, nodes=sol.n_nodes, batch=n, setup_s=setup, warm_s=warm, solve_s=dt,
                   sources_per_s=n / dt, iterations=it, ms_per_iter=1e3 * dt / it, threads=sol.row_threads,
                   lanes=getattr(sol, 'lanes', 1), relaxed_per_source=ws["relaxed_per_source"],
                   visits_per_source=ws["visits_per_source"], finite=float(np.isfinite(d).mean()), cfg=str(kw))
        OUT["rows"].append(row)
        print(f"{name:10s} {str(kw):60s} batch {n:3d} {n / dt:8.2f} src/s  it {it:5d}  {1e3 * dt / it:.3f} ms/it  "
              f"relaxed/src {ws['relaxed_per_source']:.3g}", flush=True)
        del sol
    except Exception as e:  # noqa: BLE001
        print(name, kw, "ERROR", type(e).__name__, str(e)[:300], flush=True)
        OUT["rows"].append(dict(mesh=name, error=str(e)[:300], **{k: str(v) for k, v in kw.items()}))
    save()


def shared_ref(name, ext="obj"):
    ref = np.load(BM / "reference" / "exact" / f"{name}.npz")
    tm = trimesh.load(BM / "meshes" / f"{name}.{ext}", process=False, force="mesh")
    inv = np.full(len(tm.vertices), -1)
    inv[ref["orig_index"]] = np.arange(len(ref["orig_index"]))
    return (ref["positions"].astype(np.float64), inv[np.asarray(tm.faces)]), ref["sources"], \
        ref["dist"].astype(np.float64)


def accuracy():
    for name in ("spot", "cow", "rocker-arm", "stanford-bunny"):
        (V, F), src, exact = shared_ref(name)
        m = load_mesh((V, F))
        for lanes in (1, 4, 8):
            sol = make(m, lanes=lanes, batch=len(src))
            d = sol.solve(src).astype(np.float64) / m.scale
            ok = np.isfinite(exact) & (exact > 0)
            rel = (d[ok] - exact[ok]) / exact[ok]
            row = dict(mesh=name, lanes=lanes, mre=float(np.abs(rel).mean()), max=float(rel.max()),
                       min=float(rel.min()), over_half=int((rel > 5e-3).sum()))
            OUT["acc"].append(row)
            print(f"acc {name:15s} lanes {lanes}  MRE {100 * row['mre']:.4f}%  max {100 * row['max']:.3f}%  "
                  f"min {row['min']:.1e}  >0.5%: {row['over_half']}", flush=True)
    save()


def profile(name, mesh, **kw):
    """One batch from the host loop (no graph) with Warp's kernel timing: time per kernel."""
    if OLD and kw.get("lanes", 1) != 1:
        return
    sol = make(mesh, **kw)
    sol._graphs = {"start": False, "loop": False, "finish": False}
    n = min(sol.batch, 32)
    src = np.random.default_rng(1).choice(sol.nv, n, replace=False)
    sol.run(src[:n])  # loads the kernels
    wp.synchronize_device(dev)
    wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)
    t0 = time.perf_counter()
    sol.run(src[:n])
    wall = time.perf_counter() - t0
    res = wp.timing_end()
    per = {}
    for r in res:
        k = r.name.split("(")[0] if hasattr(r, "name") else str(r)
        per.setdefault(k, [0.0, 0])
        per[k][0] += r.elapsed
        per[k][1] += 1
    it = sol.timings["iterations"][-1]
    row = dict(mesh=name, batch=n, iterations=it, wall_s=wall, kernels={k: v for k, v in per.items()}, cfg=str(kw))
    OUT["prof"].append(row)
    print(f"prof {name} {kw} batch {n} it {it} wall {wall:.2f}s")
    for k, (ms, c) in sorted(per.items(), key=lambda x: -x[1][0])[:8]:
        print(f"   {k:40s} {ms:9.1f} ms  {c:6d} launches  {ms / max(c, 1) * 1e3:8.1f} us each", flush=True)
    save()


if __name__ == "__main__":
    if "acc" in stages:
        accuracy()
    if "rate" in stages or "prof" in stages or "public" in stages:
        t0 = time.perf_counter()
        q = load_mesh(qslim436())
        print(f"436K mesh built in {time.perf_counter() - t0:.1f} s", flush=True)
        if "rate" in stages:
            b34 = load_mesh(bunny(0))
            OLDT = (32, 4096, 1 << 18)
            for kw in (dict(lanes=1, threads=OLDT), dict(lanes=4), dict(lanes=8), dict(lanes=4, threads=OLDT)):
                rate("bunny34K", b34, **kw)
            for kw in (dict(lanes=1, threads=OLDT), dict(lanes=4), dict(lanes=8), dict(lanes=4, threads=OLDT),
                       dict(lanes=2)):
                rate("q436K", q, **kw)
        if "prof" in stages:
            profile("q436K", q, lanes=1, threads=(32, 4096, 1 << 18))
            profile("q436K", q, lanes=4)
        if "public" in stages:
            import neurogf_warp as ngf
            V, F = q.vertices, q.faces
            src = np.random.default_rng(1).choice(len(V), 256, replace=False)
            for near in (False, True):
                t0 = time.perf_counter()
                d = ngf.geodesic_distances((V, F), src, device=DEV, near_source=near)
                dt = time.perf_counter() - t0
                OUT.setdefault("public", []).append(dict(near_source=near, seconds=dt, sources_per_s=256 / dt,
                                                         finite=float(np.isfinite(d).mean())))
                print(f"public geodesic_distances 436K 256 sources near_source={near}: {dt:.2f} s = {256 / dt:.2f} "
                      f"sources/s (set-up included)", flush=True)
            save()
    if "final" in stages:
        q = load_mesh(qslim436())
        rate("bunny34K", load_mesh(bunny(0)))
        rate("q436K", q)
        rate("bunny2.2M", load_mesh(bunny(3)))
    if "big" in stages:
        t0 = time.perf_counter()
        b2m = load_mesh(bunny(3))
        print(f"2.2M mesh built in {time.perf_counter() - t0:.1f} s", flush=True)
        for kw in (dict(lanes=1, threads=(32, 4096, 1 << 18)), dict(lanes=4), dict(lanes=8)):
            rate("bunny2.2M", b2m, **kw)
    print("done", flush=True)
    save()
