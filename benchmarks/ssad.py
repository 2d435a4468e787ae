"""SSAD benchmark: the released bunny model on a ~436K-vertex subdivided bunny, Warp vs PyTorch in one run.

    python benchmarks/ssad.py --device cuda:0            # GPU machine
    python benchmarks/ssad.py --device cpu --vertices 40000 --repeats 2   # quick look here

Prints a table and writes JSON. Roofline (D=256, per vertex): lifting 41,152 MACs + distance head 20,544
MACs = 123 kFLOP; for 436K vertices 53.8 GFLOP, i.e. 1.05 ms at the ~51 TFLOP/s FP32 (FFMA) ceiling, 0.07 ms
at the ~780 TFLOP/s fp16 tensor-core ceiling. Bytes: 12 B in + 4 B out per vertex = 7 MB, ~2 us at 4 TB/s.
So SSAD is compute-bound; the float64-accumulating SIMT kernel here is the correctness baseline, not the
fast path.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ROOT, find_shared, subdivided_bunny  # noqa: E402


def time_it(fn, sync, repeats):
    fn()
    sync()
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        sync()
        ts.append(time.perf_counter() - t)
    return statistics.median(ts)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--vertices", type=int, default=436_000)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--source", type=int, default=0)
    ap.add_argument("--json", default=None, help="output JSON (default: $OUT/ssad.json or benchmarks/ssad.json)")
    ap.add_argument("--save-ref", default=None, help="also save the SSAD result (.npy) to compare across devices")
    ap.add_argument("--ref", default=None, help="a saved SSAD result (.npy) from another device to compare with")
    a = ap.parse_args(argv)

    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    import neurogf_warp as ngf
    from neurogf_warp.kernels import mlp

    dev = wp.get_device(a.device)
    v, f = subdivided_bunny(a.vertices)
    model = ngf.load(find_shared("checkpoints", "official", "NeuroGF_Pretrainer__bunny_final.pth"), mesh=(v, f))
    V = model.mesh.n_input
    print(f"mesh: {V} vertices, {len(f)} faces; device {dev} ({dev.name if hasattr(dev, 'name') else ''})")

    from neurogf_warp.inference import _ssad_tile, _to_vertices

    t = time.perf_counter()
    wp.load_module(mlp, device=dev)
    compile_s = time.perf_counter() - t
    sync = (lambda: wp.synchronize_device(dev))
    simt = lambda: _to_vertices(model, a.source, "ssad", "src", mlp.distance_to_source, dev, "warp")
    t = time.perf_counter()
    d_warp = simt().numpy()
    first_s = time.perf_counter() - t
    rows, outputs, setup = [], {}, {}
    rows.append(("warp SIMT, whole MLP per thread", time_it(simt, sync, a.repeats)))
    outputs[rows[-1][0]] = d_warp
    # tile head on cached vertex embeddings: the first call compiles the kernel and builds the cache
    configs = [(False, 32, 64), (False, 64, 128), (False, 64, 256), (False, 128, 256)]  # (cuBLASDx, block, threads)
    configs += [(True, 64, 128)] if dev.is_cuda else []
    for mathdx, block, threads in configs:
        name = f"warp tile head, cached e(x), {'cuBLASDx' if mathdx else 'scalar GEMM'} B={block} T={threads}"
        kw = dict(mathdx=mathdx, block=block, threads=threads)
        model.invalidate()
        t = time.perf_counter()
        outputs[name] = _ssad_tile(model, a.source, dev, "numpy", **kw)
        setup[name] = time.perf_counter() - t  # compile + embedding cache + one query
        rows.append((name, time_it(lambda: _ssad_tile(model, a.source, dev, "warp", **kw), sync, a.repeats)))

    # PyTorch on the same device: lift every vertex + distance head on |e_s - e_v|, and the head alone on
    # cached embeddings (the same saving the tile path makes)
    tdev = torch.device("cuda", dev.ordinal) if dev.is_cuda else torch.device("cpu")
    x = torch.from_numpy(model.mesh.normalize(model.mesh.vertices)).to(tdev)
    src = x[model.mesh.vertex(a.source)].view(1, 3)
    net = model.net

    def torch_ssad(dtype, cached=False):
        n = net.to(tdev, dtype)
        xx, ss = x.to(dtype), src.to(dtype)
        with torch.no_grad():
            ex = n.embed(xx)
        def run():
            with torch.no_grad():
                return n.distance_from_embeddings(n.embed(ss), ex if cached else n.embed(xx), ss, xx) / model.scale
        return run

    tsync = (lambda: torch.cuda.synchronize(tdev)) if tdev.type == "cuda" else (lambda: None)
    ref64 = torch_ssad(torch.float64)().cpu().numpy()
    for name, dt, cached in (("torch eager fp32", torch.float32, False), ("torch eager fp16", torch.float16, False),
                             ("torch fp32 head, cached e(x)", torch.float32, True),
                             ("torch fp16 head, cached e(x)", torch.float16, True)):
        if dt == torch.float16 and tdev.type != "cuda":
            continue
        rows.append((name, time_it(torch_ssad(dt, cached), tsync, a.repeats)))
    net.to("cpu", torch.float32)
    errs = {n: float(np.max(np.abs(o[model.mesh.index] - ref64)) / np.max(np.abs(ref64))) for n, o in outputs.items()}

    err = max(errs.values())
    result = {
        "benchmark": "ssad", "date": datetime.date.today().isoformat(), "device": str(dev),
        "device_name": getattr(dev, "name", platform.processor()), "vertices": V,
        "warp_module_compile_s": compile_s, "warp_first_call_s": first_s,
        "tile_first_call_s": setup,  # kernel compile + embedding cache + one query
        "times_ms": {n: s * 1e3 for n, s in rows},
        "max_err_vs_torch_float64_rel_to_max": errs,
        "roofline_fp32_ms": {"whole MLP": 2 * 61696 * V / 51e12 * 1e3, "head only": 2 * 20544 * V / 51e12 * 1e3},
        "warp": wp.config.version, "torch": torch.__version__,
    }
    if a.ref:
        other = np.load(a.ref)
        result["max_abs_diff_vs_ref"] = float(np.nanmax(np.abs(other - d_warp)))
        result["ref_file"] = a.ref
    if a.save_ref:
        np.save(a.save_ref, d_warp)
    out = a.json or os.path.join(os.environ.get("OUT", str(ROOT / "benchmarks")), "ssad.json")
    Path(out).write_text(json.dumps(result, indent=1))

    print(f"\nSSAD, {V} vertices, {dev}: compile {compile_s:.2f} s, first call {first_s:.2f} s")
    for n, t in setup.items():
        print(f"{n}: first call (kernel compile + embedding cache) {t:.2f} s")
    print(f"{'variant':60s} {'ms':>10s} {'vs torch fp32':>14s}")
    base = dict(rows).get("torch eager fp32")
    for n, s in rows:
        print(f"{n:60s} {s * 1e3:10.3f} {base / s if base else float('nan'):13.2f}x")
    for n, e in errs.items():
        print(f"{n}: max |warp - torch float64| / max distance = {e:.2e}")
    if "max_abs_diff_vs_ref" in result:
        print(f"max |warp here - warp on {a.ref}| = {result['max_abs_diff_vs_ref']:.3e} (mesh units)")
    print(f"JSON: {out}")
    return 0 if err < 1e-4 else 1


if __name__ == "__main__":
    sys.exit(main())
