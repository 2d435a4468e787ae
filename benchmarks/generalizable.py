"""Benchmark of the generalizable network's Warp inference: conditioning time and pair-query time.

    python benchmarks/generalizable.py --device cuda:0 --json out.json
    python benchmarks/generalizable.py --device cpu --quick          # < 60 s on a 2-core CPU

What it does, on one device and arithmetic mode (default: fp32 on CUDA, fp64 on the CPU):
1. compile: the first conditioning + query (kernel compilation or cache load; on CUDA the encoder graph's
   capture too), timed apart;
2. check: a fresh random shape (a noise-displaced ellipsoid, 2,048 points, seeded by --seed) and random pairs
   near it: the Warp ratio against the float64 torch network (mean / max relative difference; fails the run
   with exit status 1 above 1e-5 mean or 1e-3 max);
3. conditioning a 2,048-point cloud: (a) ``WarpGenNet.encode(X, into=state)`` of a device-resident cloud into
   reused buffers (steady state, no allocation; Python launches), (b) ``encode`` allocating new buffers (Python
   launches, the graph switched off), (c) the user call ``model.condition(numpy points)`` (host normalization and
   upload included) as it runs by default: on CUDA the encoder's captured graph replayed and its outputs copied
   (``WarpGenNet.encode`` without ``into``), and (c') the same call with the graph off (``use_graph = False``, as
   ``NGF_NO_GRAPH=1``: Python launches, the hash grid built at conditioning), (e) ``encode(X)`` through that graph
   path alone (replay + copies), (d) (a) replayed as a CUDA graph captured here when capture works (measured
   last); median of --repeats runs, each CUDA-synchronized;
4. pairs: 1M (--pairs) random pairs of points near the surface, distances in user units
   (``WarpGenNet.distances``, nearest-cloud-point lookup included), median wall of --repeats synchronized runs and
   the kernel time from Warp's CUDA activity timers (``wp.timing_begin``); then the same through the tiled query
   (``distances_tiled``: tile GEMMs, cuBLASDx on CUDA) with fp32 and fp16 (tensor-core) operands;
5. fp16 pairs (--precision fp16 or both, the default): the same 1M pairs through ``distances(...,
   precision="fp16")`` (the tensor-core pair head, kernels/generalizable/tensorcore.py) for each tile shape of
   --tc-tiles (m-tiles per warp x layer-0 n-tiles per chunk @ warps per SM): wall and Warp kernel timer as in 4,
   and its error against float64 torch on the check pairs of 2 (ratios) and on 512 of the 1M pairs (distances);
6. the nearest-cloud-point lookups of 4 and 5 alone (2 x --pairs points): Warp's hash grid and the dense
   candidate grid (--nearest picks the one the pair timings use, default grid), the grid's build time (it is
   built on a cloud's first query, not at conditioning) and the indices' agreement (grid = hash = brute force);
and prints a table (and writes --json). Exit status 1 when a result disagrees with float64 torch.
"""
from __future__ import annotations

import argparse
import platform
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

import _bootstrap  # noqa: F401  (this checkout's neurogf_warp, installed or not)
from common import find_shared, write_json


def find_weights(arg):
    if arg:
        return Path(arg)
    try:
        return find_shared("checkpoints", "official", "GenNeuroGF.pth")
    except FileNotFoundError:
        return None


def random_shape(n, seed):
    """n points on a noise-displaced ellipsoid, in arbitrary user units (scaled 5x, shifted)."""
    rng = np.random.default_rng(seed)
    g = rng.standard_normal((n, 3))
    u = g / np.linalg.norm(g, axis=1, keepdims=True)
    k = rng.standard_normal((6, 3))
    bump = 0.15 * np.sin(u @ k.T).sum(axis=1, keepdims=True) / 3
    return (u * (1 + bump)) * np.array([1.0, 0.7, 0.5]) * 5.0 + np.array([2.0, -1.0, 3.0])


def near_surface(cloud, m, rng, noise=0.01):
    i = rng.integers(0, len(cloud), m)
    span = np.ptp(cloud, axis=0).max()
    return cloud[i] + rng.standard_normal((m, 3)) * noise * span


def median_ms(fn, repeats, sync):
    ts = []
    for _ in range(repeats):
        sync()
        t0 = time.perf_counter()
        fn()
        sync()
        ts.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(ts)), float(np.min(ts))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--mode", default=None, choices=[None, "fp64", "fp32", "mixed"])
    ap.add_argument("--weights", default=None, help="GenNeuroGF.pth (default: ../shared/checkpoints/official)")
    ap.add_argument("--points", type=int, default=2048)
    ap.add_argument("--pairs", type=int, default=1 << 20)
    ap.add_argument("--repeats", type=int, default=50)
    ap.add_argument("--knn-chunks", type=int, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--block-pairs", type=int, default=32, help="pairs per block of the tiled query")
    ap.add_argument("--no-tiled", action="store_true", help="skip the tiled query (its first CUDA compile with "
                    "cuBLASDx takes about a minute)")
    ap.add_argument("--generic", action="store_true", help="time the generic SIMT kernels instead of the fast "
                    "float32 ones (kernels/generalizable/fast.py, the fp32 default)")
    ap.add_argument("--nearest", default="grid", choices=["hash", "grid"],
                    help="nearest-cloud-point lookup of the timed pair queries (default grid: the dense candidate "
                    "grid, kernels/generalizable/nearest_grid.py; hash: Warp's hash grid); both lookups are timed "
                    "on their own in any case")
    ap.add_argument("--precision", default="both", choices=["fp32", "fp16", "both"],
                    help="pair queries timed: the fp32 kernels, the fp16 tensor-core head, or both (default)")
    ap.add_argument("--tc-tiles", default="1x8@16,1x8@12,2x4@8", help="shapes of the fp16 pair kernel to time, "
                    "MTxNC@W (m-tiles of 16 pairs per warp x layer-0 n-tiles per chunk @ persistent warps per SM, "
                    "which the kernel is compiled for: 16 -> 128 registers, 12 -> 168, 8 -> 255), comma-separated")
    ap.add_argument("--quick", action="store_true", help="CPU smoke run: 20K pairs, 1 repeat")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    if a.quick:
        a.pairs, a.repeats = min(a.pairs, 20_000), 1
    few = 1 if a.quick else max(3, a.repeats // 5)  # repeats of the slower conditioning variants

    import torch
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    from neurogf_warp.generalizable.encoder import WarpGenNet, default_mode
    from neurogf_warp.generalizable.model import GeneralizableModel, normalization
    from neurogf_warp.generalizable.network import GenNeuroGF, load_network

    dev = wp.get_device(a.device)
    mode = a.mode or default_mode(dev)
    sync = (lambda: wp.synchronize_device(dev))
    wpath = find_weights(a.weights)
    if wpath is not None:
        net = load_network(wpath)
        weights = str(wpath)
    else:
        torch.manual_seed(0)
        net = GenNeuroGF().double().eval()
        weights = "random (GenNeuroGF.pth not found)"
    model = GeneralizableModel(net)
    rng = np.random.default_rng(a.seed)
    cloud = random_shape(a.points, a.seed)
    center, scale = normalization(cloud)
    unit = (cloud - center) * scale

    # 1. compile / first call
    t0 = time.perf_counter()
    wn = WarpGenNet(net, dev, mode, knn_chunks=a.knn_chunks, fast=not a.generic, nearest=a.nearest)
    enc = wn.encode(unit)
    wn.ratio(enc, unit[:4], unit[4:8]).numpy()
    compile_s = time.perf_counter() - t0

    # 2. check against float64 torch on fresh random inputs
    m_chk = 4096 if not a.quick else 1024
    S = (near_surface(cloud, m_chk, rng) - center) * scale
    T = (near_surface(cloud, m_chk, rng) - center) * scale
    got = wn.ratio(enc, S, T).numpy().astype(np.float64)
    with torch.no_grad():
        want = net(*(torch.tensor(x, dtype=torch.float64)[None] for x in (unit, S, T)))[0].numpy()
    rel = np.abs(got - want) / np.abs(want)
    check = {"pairs": m_chk, "mean_rel": float(rel.mean()), "max_rel": float(rel.max())}
    check["ok"] = bool(check["mean_rel"] <= 1e-5 and check["max_rel"] <= 1e-3)

    # 3. conditioning
    X = wn._arr(unit)  # device-resident input, storage dtype
    wn.use_graph = False  # (a), (b): the Python launches, as measured before the graph path
    enc_new_ms, _ = median_ms(lambda: wn.encode(X), few, sync)  # allocates every call
    state = wn.encode(X)
    wn.use_graph = True
    enc_ms, enc_min = median_ms(lambda: wn.encode(X, into=state), a.repeats, sync)  # steady state: no allocation
    # the public call: by default (on CUDA: the encoder's graph, captured on the first call), then the graph off
    cwn = model.warp_net(dev, mode)
    model.condition(cloud, device=dev, mode=mode)
    reps = a.repeats if dev.is_cuda else few
    cond_ms, _ = median_ms(lambda: model.condition(cloud, device=dev, mode=mode), reps, sync)
    cond_graph = bool(cwn._graphs)
    cwn.use_graph = False
    cond_eager_ms, _ = median_ms(lambda: model.condition(cloud, device=dev, mode=mode), reps, sync)
    cwn.use_graph = True
    enc_graph_path_ms = None
    if dev.is_cuda:
        wn.encode(X)
        if wn._graphs:
            enc_graph_path_ms, _ = median_ms(lambda: wn.encode(X), a.repeats, sync)
    enc_kernel_ms = None
    enc_kernels = []
    if dev.is_cuda:
        wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)
        wn.encode(X, into=state)
        res = wp.timing_end()
        enc_kernel_ms = float(sum(r.elapsed for r in res))
        enc_kernels = [(r.name.split("_cuda_kernel")[0].replace("_build__locals__", ""), float(r.elapsed))
                       for r in res]

    # 4. pairs
    P = near_surface(cloud, a.pairs, rng)
    Q = near_surface(cloud, a.pairs, rng)
    Pd, Qd = wn._arr(P), wn._arr(Q)
    out = wp.empty(a.pairs, dtype=wp.float32, device=dev)
    def kernel_times(run):
        """{kernel: [ms] of its launches in 5 runs} from Warp's CUDA timers, and the time per run: the sum of the
        per-kernel medians, each times its launches per run."""
        if not dev.is_cuda:
            return {}, None
        wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)
        for _ in range(5):
            run()
        res = wp.timing_end()
        ks = {}
        for r in res:
            ks.setdefault(r.name.split("_cuda_kernel")[0].replace("_build__locals__", ""), []).append(
                float(r.elapsed))
        # a kernel launched twice per run (the nearest-point lookups of S and T) counts twice
        return ks, float(sum(np.median(v) * (len(v) // 5) for v in ks.values()))

    sel = rng.integers(0, a.pairs, 512)
    with torch.no_grad():
        w = net(torch.tensor(unit)[None], torch.tensor((P[sel] - center) * scale)[None],
                torch.tensor((Q[sel] - center) * scale)[None])[0].numpy()
    want_d = np.maximum(w, 1.0) * np.linalg.norm(P[sel] - Q[sel], axis=1)
    pair_ms = pair_min = pair_kernel_ms = pair_check = None
    pair_kernels = {}
    pair_kernel_note = ""

    def kernel_note(ks):
        return ", ".join(f"{k} {np.median(v):.3f}" + (f" x{len(v) // 5}" if len(v) // 5 > 1 else "")
                         for k, v in ks.items())

    if a.precision in ("fp32", "both"):
        run = (lambda: wn.distances(enc, Pd, Qd, center, scale, False, out=out))
        run()
        pair_ms, pair_min = median_ms(run, a.repeats, sync)
        pair_kernels, pair_kernel_ms = kernel_times(run)
        pair_kernel_note = kernel_note(pair_kernels)
        d = out.numpy()
        pair_check = float((np.abs(d[sel] - want_d) / want_d).max())

    # 5. fp16: the tensor-core pair head, each tile shape of --tc-tiles
    fp16 = {}
    if a.precision in ("fp16", "both"):
        for shape in [x.strip() for x in a.tc_tiles.split(",") if x.strip()]:
            tiles, _, warps = shape.lower().partition("@")
            mt, nc = (int(v) for v in tiles.split("x"))
            try:
                wn.tc_tiles = (mt, nc, int(warps) if warps else None)
                t0 = time.perf_counter()
                wn.distances(enc, Pd[:64], Qd[:64], center, scale, False, precision="fp16")
                sync()
                comp_s = time.perf_counter() - t0
                out16 = wp.empty(a.pairs, dtype=wp.float32, device=dev)
                def run16(out16=out16):
                    return wn.distances(enc, Pd, Qd, center, scale, False, out=out16, precision="fp16")
                run16()
                ms, mn = median_ms(run16, a.repeats, sync)
                ks, kms = kernel_times(run16)
                d16 = out16.numpy()
                r16 = wn.ratio(enc, S, T, precision="fp16").numpy().astype(np.float64)
                rr = np.abs(r16 - want) / np.abs(want)
                rd = np.abs(d16[sel] - want_d) / want_d
                fp16[shape] = {"compile_s": comp_s, "ms_median": ms, "ms_min": mn, "kernels_ms_sum": kms,
                               "kernels_ms_median": {k: float(np.median(v)) for k, v in ks.items()},
                               "kernel_launches_per_run": {k: len(v) // 5 for k, v in ks.items()},
                               "kernels_note": kernel_note(ks),
                               "ratio_vs_torch_fp64": {"pairs": m_chk, "mean_rel": float(rr.mean()),
                                                       "max_rel": float(rr.max())},
                               "distance_vs_torch_fp64": {"pairs": len(sel), "mean_rel": float(rd.mean()),
                                                          "max_rel": float(rd.max())},
                               "ok": bool(rr.mean() <= 5e-4 and rr.max() <= 1e-2 and rd.max() <= 1e-2)}
            except Exception as e:  # noqa: BLE001
                fp16[shape] = {"error": f"{type(e).__name__}: {str(e)[:300]}"}
            finally:
                wn.tc_tiles = None

    # 6. the nearest-cloud-point lookups alone: the hash grid and the dense candidate grid on the 2 x pairs query
    # points (as a pair query runs them), the candidate grid's build (done on a cloud's first query), and whether
    # both give the brute-force scan's indices
    nearest = {}
    idx = {}
    for look in ("hash", "grid"):
        wn.nearest_lookup = look
        r = {}
        if look == "grid":
            def rebuild():
                enc.nn_grid_built = False
                wn._nn_grid(enc)
            rebuild()
            r["build_ms_median"], r["build_ms_min"] = median_ms(rebuild, a.repeats, sync)
            _, r["build_kernels_ms_sum"] = kernel_times(rebuild)
            g = enc.nn_grid
            cnt = g.count.numpy()
            r["cells_per_axis"], r["lists"], r["list_entries"] = g.G, int((cnt > 0).sum()), int(cnt.sum())
        def look_up():
            return wn._nearest_user(enc, Pd, center, scale), wn._nearest_user(enc, Qd, center, scale)
        look_up()
        r["ms_median"], r["ms_min"] = median_ms(look_up, a.repeats, sync)
        ks, r["kernels_ms_sum"] = kernel_times(look_up)
        r["kernels_note"] = kernel_note(ks)
        idx[look] = np.concatenate([x.numpy() for x in look_up()])
        nearest[look] = r
    wn.nearest_lookup = a.nearest
    sub = rng.integers(0, a.pairs, 4096)
    brute = wp.empty(len(sub), dtype=wp.int32, device=dev)
    wp.launch(wn.k.nearest_user, len(sub), inputs=[enc.cloud, wp.uint64(0), 0.0, 0, wn._arr(P[sub]),
                                                    *(float(c) for c in center), float(scale), brute], device=dev)
    nearest["grid_vs_hash_mismatches"] = int((idx["grid"] != idx["hash"]).sum())
    nearest["vs_brute_force_mismatches"] = {k: int((v[sub] != brute.numpy()).sum()) for k, v in idx.items()}
    nearest["brute_force_queries"] = len(sub)

    # 4b. the tiled (tile-GEMM) query: operand fp32 and fp16 (tensor cores on CUDA); compile timed apart
    tiled = {}
    if mode in ("fp32", "fp64") and not a.no_tiled:
        for op in (["fp32", "fp16"] if mode == "fp32" else ["fp64"]):
            bp = a.block_pairs if dev.is_cuda else min(a.block_pairs, 16)
            if dev.is_cpu and op == "fp64":
                continue  # the fp64 tiles exceed the CPU tile arena
            try:
                t0 = time.perf_counter()
                wn.distances_tiled(enc, Pd[:bp], Qd[:bp], center, scale, block_pairs=bp, operand=op)
                sync()
                comp_s = time.perf_counter() - t0
                sc_ = {}
                out_t = wp.empty(a.pairs, dtype=wp.float32, device=dev)
                def runt(out_t=out_t, bp=bp, op=op, sc_=sc_):
                    return wn.distances_tiled(enc, Pd, Qd, center, scale, out=out_t, block_pairs=bp, operand=op,
                                              scratch=sc_)
                runt()
                ms, mn = median_ms(runt, a.repeats, sync)
                kms = None
                if dev.is_cuda:
                    wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)
                    runt()
                    kms = float(sum(r.elapsed for r in wp.timing_end()))
                dt = out_t.numpy()
                tiled[op] = {"block_pairs": bp, "compile_s": comp_s, "ms_median": ms, "ms_min": mn,
                             "kernels_ms_sum": kms, "max_rel_vs_torch_fp64":
                             float((np.abs(dt[sel] - want_d) / want_d).max())}
            except Exception as e:  # noqa: BLE001
                tiled[op] = {"error": f"{type(e).__name__}: {str(e)[:200]}"}

    # 5. conditioning under a CUDA graph (last: a failed capture must not disturb the other measurements)
    graph_ms = graph_note = None
    if dev.is_cuda:
        try:
            with wp.ScopedCapture(dev) as cap:
                wn.encode(X, into=state)
            graph_ms, _ = median_ms(lambda: wp.capture_launch(cap.graph), a.repeats, sync)
        except Exception as e:  # noqa: BLE001  (report, do not fail the benchmark)
            graph_note = f"capture failed: {type(e).__name__}: {str(e)[:120]}"

    result = {
        "date_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"), "device": str(dev),
        "device_name": dev.name, "host": platform.node(), "mode": mode, "weights": weights,
        "points": a.points, "pairs": a.pairs, "repeats": a.repeats, "knn_chunks": wn.knn_chunks,
        "compile_first_call_s": compile_s, "check_vs_torch_fp64": check,
        "encode_ms_median": enc_ms, "encode_ms_min": enc_min, "encode_new_buffers_ms_median": enc_new_ms, "encode_graph_ms_median": graph_ms,
        "kernels": "generic" if not wn.fast else "fast", "encode_kernels": enc_kernels,
        "pair_kernels_ms_median": {k: float(np.median(v)) for k, v in pair_kernels.items()},
        "encode_graph_note": graph_note, "encode_kernels_ms_sum": enc_kernel_ms, "condition_numpy_ms_median": cond_ms,
        "condition_numpy_graph": cond_graph, "condition_numpy_no_graph_ms_median": cond_eager_ms,
        "encode_graph_path_ms_median": enc_graph_path_ms, "graph_off_reason": cwn._graph_off,
        "pairs_ms_median": pair_ms, "pairs_ms_min": pair_min, "pairs_kernel_ms_median": pair_kernel_ms,
        "pairs_per_s": a.pairs / (pair_ms / 1e3) if pair_ms else None, "pairs_max_rel_vs_torch_fp64": pair_check,
        "tiled": tiled, "fp16": fp16, "nearest_lookup": a.nearest, "nearest": nearest,
    }
    f = (lambda v: "-" if v is None else f"{v:.3f}")
    rows = [
        ("device / mode", f"{dev} ({dev.name}) / {mode}, {'fast' if wn.fast else 'generic'} kernels"),
        ("weights", weights),
        ("compile + first call", f"{compile_s:.2f} s"),
        ("check vs float64 torch", (f"mean {check['mean_rel']:.2e}, max {check['max_rel']:.2e} "
                                    f"({'ok' if check['ok'] else 'FAIL'})")),
        (f"encode {a.points} pts (device input)", f"{f(enc_ms)} ms median, {f(enc_min)} min (reused buffers)"),
        ("encode, new buffers each call", f"{f(enc_new_ms)} ms median"),
        ("encode under a CUDA graph", f"{f(graph_ms)} ms" + (f" ({graph_note})" if graph_note else "")),
        ("encode kernels (Warp timers, sum)", f"{f(enc_kernel_ms)} ms"),
        ("model.condition(numpy)", f"{f(cond_ms)} ms median"
         + (" (encoder graph replayed)" if cond_graph else " (Python launches" + (f": {cwn._graph_off}"
                                                                                   if cwn._graph_off else "") + ")")),
        ("model.condition(numpy), graph off", f"{f(cond_eager_ms)} ms median (use_graph=False / NGF_NO_GRAPH=1)"),
        ("encode(X), graph path (replay + copies)", f"{f(enc_graph_path_ms)} ms median"),
        (f"{a.pairs:,} pairs (wall, sync)", f"{f(pair_ms)} ms median, {f(pair_min)} min"),
        (f"{a.pairs:,} pairs (Warp kernel timer)", f"{f(pair_kernel_ms)} ms ({pair_kernel_note})"),
        ("pair distances vs float64 torch", f"max rel {f(pair_check) if pair_check is None else f'{pair_check:.2e}'}"),
    ]
    for shape, r in fp16.items():
        if "error" in r:
            rows.append((f"fp16 pairs, tiles {shape}", r["error"]))
            continue
        rows.append((f"{a.pairs:,} pairs fp16 {shape} (wall, sync)",
                     f"{f(r['ms_median'])} ms median, {f(r['ms_min'])} min, compile {r['compile_s']:.1f} s"))
        rows.append((f"{a.pairs:,} pairs fp16 {shape} (Warp kernel timer)",
                     f"{f(r['kernels_ms_sum'])} ms ({r['kernels_note']})"))
        rc, dc = r["ratio_vs_torch_fp64"], r["distance_vs_torch_fp64"]
        rows.append((f"fp16 {shape} vs float64 torch", f"ratio mean {rc['mean_rel']:.2e} max {rc['max_rel']:.2e} "
                     f"({rc['pairs']} pairs); distance mean {dc['mean_rel']:.2e} max {dc['max_rel']:.2e} "
                     f"({dc['pairs']} pairs) ({'ok' if r['ok'] else 'FAIL'})"))
    for look in ("hash", "grid"):
        r = nearest[look]
        rows.append((f"nearest, {look}, 2 x {a.pairs:,} pts (wall)",
                     f"{f(r['ms_median'])} ms median, {f(r['ms_min'])} min; kernels {f(r['kernels_ms_sum'])} ms "
                     f"({r['kernels_note']})"))
    g = nearest["grid"]
    rows.append(("nearest grid build (first query)", f"{f(g['build_ms_median'])} ms median, kernels "
                 f"{f(g['build_kernels_ms_sum'])} ms; {g['cells_per_axis']}^3 cells, {g['lists']} lists, "
                 f"{g['list_entries']} entries"))
    rows.append(("nearest: grid vs hash / vs brute", f"{nearest['grid_vs_hash_mismatches']} different of "
                 f"{2 * a.pairs:,}; vs brute force on {len(sub)}: {nearest['vs_brute_force_mismatches']}"))
    for op, r in tiled.items():
        if "error" in r:
            rows.append((f"tiled query ({op} operands)", r["error"]))
        else:
            rows.append((f"tiled query ({op}, B={r['block_pairs']})", (f"{f(r['ms_median'])} ms median, "
                         f"kernels {f(r['kernels_ms_sum'])} ms, compile {r['compile_s']:.1f} s, "
                         f"max rel {r['max_rel_vs_torch_fp64']:.1e}")))
    if enc_kernels:
        rows.append(("encode kernels, one by one (ms)", ", ".join(f"{k} {v:.3f}" for k, v in enc_kernels)))
    wd = max(len(r[0]) for r in rows)
    print(f"generalizable NeuroGF, Warp inference ({result['date_utc']})")
    for k, v in rows:
        print(f"  {k:<{wd}}  {v}")
    if a.json:
        write_json(a.json, result, "generalizable", a.device)
    ok16 = all(r.get("ok", False) for r in fp16.values()) and nearest["grid_vs_hash_mismatches"] == 0 and \
        not any(nearest["vs_brute_force_mismatches"].values())
    return 0 if check["ok"] and (pair_check is None or pair_check <= 1e-3) and ok16 else 1


if __name__ == "__main__":
    sys.exit(main())
