"""Issue 23: the host side of the public conditioning call ``model.condition(points, device="cuda:0")``.

    python benchmarks/experiments/condition_host.py [GenNeuroGF.pth] [--cloud stanford-bunny.npz] [--json out.json]
    python benchmarks/experiments/condition_host.py --device cpu          # dry run of the logic (~30 s, 2-core CPU)

Defaults: the checkpoint and reference cloud under $NEUROGF_SHARED, ../shared, ./shared, ./.bench or ./.bm (checkpoints/official/GenNeuroGF.pth,
reference/generalizable/stanford-bunny.npz ``points``, 2,048 points); JSON to --json, else $OUT/condition_host.json
when OUT is set. On the CPU (a dry run: its timings mean nothing for the GPU) the fp32 fast encoder runs through
Warp's CPU graphs (the encoder's test switch), 256 points, 3 repeats, 1,024 check pairs.

Checks (exit status 1 if one fails): the graph was captured; graph and Python launches (use_graph=False, as
NGF_NO_GRAPH=1) give bit-identical encodings and distances on the check pairs; the frame equals the plain numpy
formula's bits; a CUDA torch tensor (float64 and float32) and a CUDA wp.array give the numpy input's frame, encoding
and distances bit for bit; distances against the float64 torch network on 8,192 pairs near the surface (fp32
bounds: mean 1e-5, max 1e-3 relative).

Timings, median and min of --repeats calls after warm-up, each CUDA-synchronized: the public call with numpy input
(graph), with a CUDA torch tensor (float32, float64), with the graph off; the host time of the numpy call before the
graph replay is issued and after it (``wp.capture_launch`` wrapped; the time after is overlapped with the GPU);
the replay alone; an empty synchronize; the GPU work of one public call from Warp's activity timers (median of 5
calls, by kind: graph, kernels, memcpy).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))


def shared_file(*parts):
    for base in (os.environ.get("NEUROGF_SHARED"), ROOT.parent / "shared", ROOT / "shared", ROOT / ".bench", ROOT / ".bm"):
        if base and Path(base, *parts).exists():
            return Path(base, *parts)
    return None


def stats_ms(ts):
    a = np.asarray(ts) * 1e3
    return {"median_ms": round(float(np.median(a)), 4), "min_ms": round(float(a.min()), 4), "n": len(a)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("weights", nargs="?", default=None)
    ap.add_argument("--cloud", default=None, help="an .npz with 'points' (default: the reference bunny cloud)")
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--points", type=int, default=None, help="first N points of the cloud (default 2048; CPU 256)")
    ap.add_argument("--repeats", type=int, default=None, help="timed calls (default 50; CPU 3)")
    ap.add_argument("--pairs", type=int, default=None, help="check pairs (default 8192; CPU 1024)")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)

    import torch
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    from neurogf_warp.generalizable.model import load, normalization

    dev = wp.get_device(a.device)
    cpu = dev.is_cpu
    n = a.points or (256 if cpu else 2048)
    repeats = a.repeats or (3 if cpu else 50)
    n_pairs = a.pairs or (1024 if cpu else 8192)
    mode = "fp32"
    wpath = Path(a.weights) if a.weights else shared_file("checkpoints", "official", "GenNeuroGF.pth")
    if wpath is None or not wpath.exists():
        print(f"GenNeuroGF.pth not found ({wpath}); pass its path or set NEUROGF_SHARED", file=sys.stderr)
        return 2
    cpath = Path(a.cloud) if a.cloud else shared_file("reference", "generalizable", "stanford-bunny.npz")
    if cpath is not None and cpath.exists():
        cloud = np.asarray(np.load(cpath)["points"], np.float64)[:n]
        cloud_src = str(cpath)
    else:  # a synthetic bumpy ellipsoid (reported)
        rng0 = np.random.default_rng(0)
        g = rng0.standard_normal((n, 3))
        u = g / np.linalg.norm(g, axis=1, keepdims=True)
        cloud = u * (1 + 0.1 * np.sin(3 * u[:, :1])) * np.array([2.0, 1.0, 1.5]) + np.array([3.0, -1.0, 2.0])
        cloud_src = "synthetic (reference cloud not found)"
    assert cloud.shape == (n, 3), cloud.shape

    t0 = time.perf_counter()
    model = load(wpath)
    wn = model.warp_net(dev, mode)
    wn._graph_cpu = cpu  # the CPU dry run: Warp's CPU graphs stand in for CUDA's
    sync = (lambda: wp.synchronize_device(dev))
    cond = lambda x: model.condition(x, device=dev, mode=mode)
    first = cond(cloud)
    sync()
    first_s = time.perf_counter() - t0
    out = {"device": str(dev), "device_name": dev.name, "mode": mode, "points": n, "cloud": cloud_src,
           "checkpoint": str(wpath), "first_call_s": round(first_s, 2), "checks": {}, "timings": {}}
    checks, ok = out["checks"], True

    def check(name, passed, **info):
        nonlocal ok
        checks[name] = {"ok": bool(passed), **info}
        ok = ok and bool(passed)
        print(f"  check {name}: {'ok' if passed else 'FAILED'} {info if info else ''}")

    arrays = lambda enc: {"cloud": enc.cloud, "feats": enc.feats, "fused": enc.fused, "points32": enc.points32,
                          **{f"nbr{i + 1}": x for i, x in enumerate(enc.neighbours)}}

    def same_encoding(c1, c2):
        diff = [k for (k, x), y in zip(arrays(c1.enc).items(), arrays(c2.enc).values())
                if not np.array_equal(x.numpy(), y.numpy())]
        return not diff and np.array_equal(c1.center, c2.center) and c1.scale == c2.scale, diff

    # ---- checks -----------------------------------------------------------------------------------------------
    print(f"{dev} ({dev.name}), {n} points of {cloud_src}; first call {first_s:.2f} s")
    check("graph_captured", n in wn._graphs, graph_off=wn._graph_off)
    c_old = (cloud.min(axis=0) + cloud.max(axis=0)) / 2  # the plain formula (before the (3, N) rewrite)
    s_old = 1.0 / float(np.sqrt(((cloud - c_old) ** 2).sum(axis=1)).max())
    c_new, s_new = normalization(cloud)
    check("frame_equals_plain_formula", np.array_equal(c_old, c_new) and s_old == s_new)
    rng = np.random.default_rng(1)
    span = float(np.ptp(cloud, axis=0).max())
    P = cloud[rng.integers(0, n, n_pairs)] + rng.standard_normal((n_pairs, 3)) * 0.01 * span
    Q = cloud[rng.integers(0, n, n_pairs)] + rng.standard_normal((n_pairs, 3)) * 0.01 * span
    cg = cond(cloud)
    d_graph = cg.distance(P, Q)
    wn.use_graph = False
    try:
        ce = cond(cloud)
    finally:
        wn.use_graph = True
    same, diff = same_encoding(cg, ce)
    check("graph_vs_eager_encoding_identical", same, differing=diff)
    check("graph_vs_eager_distances_identical", np.array_equal(d_graph, ce.distance(P, Q)), pairs=n_pairs)
    # a shape keeps its answers after other clouds replayed the graph
    for k in range(2):
        cond(cloud[::-1] * (1.5 + k))
    check("kept_after_other_replays", np.array_equal(cg.distance(P, Q), d_graph))
    # against the float64 torch network (the distance rule: max(ratio, 1) * |p - q|)
    with torch.no_grad():
        unit = lambda x: torch.tensor((x - c_new) * s_new, dtype=torch.float64)[None]
        w = model.net(unit(cloud), unit(P), unit(Q))[0].numpy()
    want = np.maximum(w, 1.0) * np.linalg.norm(P - Q, axis=1)
    rel = np.abs(d_graph.astype(np.float64) - want) / want
    check("distances_vs_float64_torch", rel.mean() <= 1e-5 and rel.max() <= 1e-3, pairs=n_pairs,
          mean_rel=float(rel.mean()), max_rel=float(rel.max()))
    gpu_inputs = {}
    if dev.is_cuda and torch.cuda.is_available():
        tdev = f"cuda:{dev.ordinal}"
        gpu_inputs = {"torch_float64": torch.tensor(cloud, device=tdev),
                      "torch_float32": torch.tensor(cloud, device=tdev).float(),
                      "wp_array_float64": wp.array(cloud, dtype=wp.float64, device=dev)}
        for name, x in gpu_inputs.items():
            try:
                ref = cg if "32" not in name else cond(cloud.astype(np.float32).astype(np.float64))
                c = cond(x)
                same, diff = same_encoding(c, ref)
                same = same and np.array_equal(c.points, ref.points)
                dist_same = np.array_equal(c.distance(P, Q), ref.distance(P, Q))
                check(f"{name}_input_identical_to_numpy", same and dist_same, differing=diff,
                      distances_identical=bool(dist_same))
            except Exception as e:  # noqa: BLE001 - report, time the rest
                check(f"{name}_input_identical_to_numpy", False, error=f"{type(e).__name__}: {e}"[:300])
    else:
        print("  (no CUDA torch: the GPU-input checks and timings are skipped)")

    # ---- timings ----------------------------------------------------------------------------------------------
    T = out["timings"]

    def timed(fn, reps=repeats):
        for _ in range(2):
            fn()
        sync()
        ts = []
        for _ in range(reps):
            sync()
            t1 = time.perf_counter()
            fn()
            sync()
            ts.append(time.perf_counter() - t1)
        return stats_ms(ts)

    T["public_numpy_graph"] = timed(lambda: cond(cloud))
    for name, x in gpu_inputs.items():
        if checks.get(f"{name}_input_identical_to_numpy", {}).get("ok"):
            T[f"public_{name}_graph"] = timed(lambda x=x: cond(x))
    wn.use_graph = False
    try:
        T["public_numpy_graph_off"] = timed(lambda: cond(cloud))
    finally:
        wn.use_graph = True
    # host time before / after the replay is issued (the numpy call), wp.capture_launch wrapped
    marks = []
    real = wp.capture_launch

    def stamped(*args, **kw):
        marks.append(time.perf_counter())
        return real(*args, **kw)

    pre, post = [], []
    wp.capture_launch = stamped
    try:
        for _ in range(repeats):
            sync()
            marks.clear()
            t1 = time.perf_counter()
            cond(cloud)
            t2 = time.perf_counter()
            sync()
            if marks:
                pre.append(marks[0] - t1)
                post.append(t2 - marks[0])
    finally:
        wp.capture_launch = real
    if pre:
        T["host_before_replay"] = stats_ms(pre)
        T["host_after_replay_issue"] = stats_ms(post)
        if cpu:
            T["host_after_replay_issue"]["note"] = "includes the CPU graph replay and copy kernel themselves"
    g = wn._graphs.get(n)
    if g is not None:
        T["replay_alone"] = timed(lambda: wp.capture_launch(g.graph))
    T["synchronize_alone"] = timed(lambda: None)
    if dev.is_cuda:
        per_call = []
        for _ in range(5):
            sync()
            wp.timing_begin(cuda_filter=wp.TIMING_ALL)
            cond(cloud)
            sync()
            res = wp.timing_end()
            kinds = {}
            for r in res:
                kind = ("graph" if r.filter == wp.TIMING_GRAPH else "memcpy" if r.filter == wp.TIMING_MEMCPY
                        else "kernels" if r.filter == wp.TIMING_KERNEL else "other")
                kinds[kind] = kinds.get(kind, 0.0) + float(r.elapsed)
            per_call.append((sum(kinds.values()), kinds))
        per_call.sort(key=lambda x: x[0])
        tot, kinds = per_call[len(per_call) // 2]
        T["gpu_work_public_numpy"] = {"total_ms": round(tot, 4), "by_kind_ms": {k: round(v, 4) for k, v in kinds.items()}}

    print(f"{'timing':34s} {'median ms':>10s} {'min ms':>9s}")
    for k, v in T.items():
        if "median_ms" in v:
            print(f"{k:34s} {v['median_ms']:10.4f} {v['min_ms']:9.4f}")
        else:
            print(f"{k:34s} {v['total_ms']:10.4f}   {v['by_kind_ms']}")
    out["ok"] = ok
    path = a.json or (os.path.join(os.environ["OUT"], "condition_host.json") if os.environ.get("OUT") else None)
    if path:
        Path(path).write_text(json.dumps(out, indent=1))
        print(f"wrote {path}")
    print("all checks passed" if ok else "SOME CHECKS FAILED")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
