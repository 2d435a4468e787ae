"""Public queries on the GPU, three ways: back-to-back time per call (CUDA events around 20 calls, median of 9
batches: what a user's loop gets), host time per call (no synchronization: where a call is host-bound this is
its time) and each Warp kernel's GPU time (Warp's CUDA activity timer, CUPTI). For A/B runs of two trees: the
script imports whichever ``neurogf_warp`` is first on ``sys.path`` (older trees: ``model.bind``).

    python benchmarks/query_kernels.py --device cuda:0 --json out.json [--tag NAME] [--mesh-cache /tmp/bm.npz]

Mesh: the 436K-vertex benchmark bunny of ``benchmarks/queries.py`` (built once, cached with --mesh-cache), the
released bunny network. Queries: MSAD of 8 bound vertex sources, a 64 x V bound distance matrix (raw), SDF of 1M
points (check False / True), the path head for 10K pairs x 128 points (check False / True, project=None) and 4M
point-pair distances (check=False, raw). CUDA only (the kernel timer needs CUPTI).
"""
from __future__ import annotations

import argparse
import collections
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from queries import benchmark_mesh, shared  # noqa: E402

wp.config.quiet = True
import neurogf_warp as ngf  # noqa: E402


def timed(f, sync, batches: int = 9, calls: int = 20) -> dict:
    for _ in range(3):
        f()
    sync()
    per = []
    for _ in range(batches):
        a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        sync()
        a.record()
        for _ in range(calls):
            f()
        b.record()
        sync()
        per.append(a.elapsed_time(b) / calls)
    sync()
    t = time.perf_counter()
    for _ in range(calls):
        f()
    host = (time.perf_counter() - t) / calls * 1e3
    sync()
    with wp.ScopedTimer("kernels", cuda_filter=wp.TIMING_KERNEL, print=False, synchronize=True) as tm:
        for _ in range(10):
            f()
    agg, cnt = collections.defaultdict(float), collections.Counter()
    for r in tm.timing_results:
        agg[r.name] += r.elapsed
        cnt[r.name] += 1
    kernels = {k: {"launches": cnt[k] / 10, "ms": v / 10} for k, v in sorted(agg.items(), key=lambda kv: -kv[1])}
    return {"median_ms": statistics.median(per), "min_ms": min(per), "host_ms": host,
            "kernel_ms": sum(k["ms"] for k in kernels.values()), "kernels": kernels}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--json", required=True)
    ap.add_argument("--tag", default="")
    ap.add_argument("--mesh-cache", default="", help="npz to keep the benchmark mesh in between runs")
    a = ap.parse_args()
    if not a.device.startswith("cuda"):
        sys.exit("query_kernels.py times GPU kernels: give --device cuda:N")
    if a.mesh_cache and os.path.exists(a.mesh_cache):
        z = np.load(a.mesh_cache)
        v, f = z["v"], z["f"]
    else:
        v, f = benchmark_mesh(436_000)
        if a.mesh_cache:
            np.savez(a.mesh_cache, v=v, f=f)
    dev = a.device
    model = ngf.load(shared("checkpoints", "official", "NeuroGF_Pretrainer__bunny_final.pth"), mesh=(v, f))
    ngf.bind(model, dev) if hasattr(ngf, "bind") else model.bind(dev)
    rng = np.random.default_rng(0)
    V = model.mesh.internal_vertices
    n = len(V)
    lo, hi = V.min(0), V.max(0)
    idx = np.asarray(model.mesh.index)
    srcs8, srcs64 = idx[rng.choice(n, 8, replace=False)], idx[rng.choice(n, 64, replace=False)]
    cuda = lambda x: torch.from_numpy(x.astype(np.float32)).to(dev)  # noqa: E731
    X = cuda(rng.uniform(lo, hi, (1_000_000, 3)))
    P4, Q4 = cuda(rng.uniform(lo, hi, (4_000_000, 3))), cuda(rng.uniform(lo, hi, (4_000_000, 3)))
    vi = rng.integers(0, n, (10_000, 2))
    Pp, Qp = cuda(V[vi[:, 0]]), cuda(V[vi[:, 1]])
    queries = {
        "msad 8 (bound)": lambda: ngf.msad(model, srcs8, device=dev, output="warp", raw=True),
        "distance_matrix 64 x V (bound)": lambda: ngf.distance_matrix(model, srcs64, device=dev, output="warp",
                                                                      raw=True),
        "sdf 1M, check=False": lambda: ngf.sdf(model, X, device=dev, check=False),
        "sdf 1M": lambda: ngf.sdf(model, X, device=dev),
        "path 10K x 128, check=False": lambda: ngf.path(model, Pp, Qp, m=128, device=dev, check=False,
                                                        project=None),
        "path 10K x 128": lambda: ngf.path(model, Pp, Qp, m=128, device=dev, project=None),
        "distance 4M, check=False": lambda: ngf.distance(model, P4, Q4, device=dev, check=False, raw=True),
    }

    def sync():
        torch.cuda.synchronize()
        wp.synchronize()

    res = {"benchmark": "query_kernels", "tag": a.tag, "device_name": torch.cuda.get_device_name(dev),
           "date": time.strftime("%Y-%m-%d"), "warp": wp.config.version, "vertices": int(n), "rows": {}}
    print(f"{'query':32s} {'b2b median':>10s} {'min':>7s} {'host/call':>9s} {'kernels':>8s}  (ms; {a.tag})")
    for name, fn in queries.items():
        r = res["rows"][name] = timed(fn, sync)
        top = ", ".join(f"{k.split(' ')[-1][:28]} {v['ms']:.4f}" for k, v in list(r["kernels"].items())[:3])
        print(f"{name:32s} {r['median_ms']:10.4f} {r['min_ms']:7.4f} {r['host_ms']:9.4f} {r['kernel_ms']:8.4f}  {top}",
              flush=True)
    Path(a.json).write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
