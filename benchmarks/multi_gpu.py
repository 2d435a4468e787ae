"""One mesh's ground truth on 1, 2, ... GPUs through the public call, and the collection's one-rank baseline repeated.

    python benchmarks/multi_gpu.py --json multi_gpu.json                       # every stage, every GPU present
    python benchmarks/multi_gpu.py --stages gt --gpus 1 2 --json out.json
    python benchmarks/multi_gpu.py --stages collection --collection coll/ --repeats 3
    python benchmarks/multi_gpu.py --stages ddp --gpus 1 2 4 --budgets 20 60 --json ddp.json

Stages:

- ``gt``: ``ngf.geodesic_distances((V, F), sources, devices=[cuda:0 .. cuda:N-1])`` at its defaults, set-up
  included (the solver cache cleared before every call), on the 436K-vertex benchmark bunny (``common
  .subdivided_bunny``) with 256 sources and the bunny midpoint-subdivided three times (2.2M vertices) with 64
  sources: seconds, sources/s, speed-up over one GPU, and whether the rows equal the one-GPU rows bit for bit
  (else the largest relative difference). Kernels are loaded on every GPU first (not timed). ``--determinism``
  also solves the first 32 sources of the 436K mesh twice on one GPU: whether one GPU repeats itself bit for bit.
- ``train``: ``ngf.train(mesh, out, budget_seconds=B, device="cuda:0", devices=[cuda:0 .. cuda:N-1])`` (the
  dataset's ground truth over N GPUs, the steps on cuda:0) for each ``--budgets`` B, then ``ngf.evaluate`` against
  the exact reference (``--train-mesh``, default igea): MRE, p99, distance sources, the dataset's seconds. A first
  run of ``--warmup`` seconds on one GPU warms the compile caches and is not kept.
- ``ddp``: one mesh trained data-parallel: ``torchrun --nproc_per_node N ... neurogf-warp train MESH -o M
  --budget-seconds B --devices cuda:0,..,cuda:N-1`` (N ranks, one GPU each, the gradients averaged; rank 0 builds
  the dataset on the N GPUs; one rank is the plain command) for each ``--budgets`` B and ``--gpus`` N, then
  ``ngf.evaluate`` against the exact reference of ``--train-mesh``: MRE, p99, the steps, the run's seconds (the
  budget counts from each process's start). The same ``--warmup`` run first. Without a GPU the ranks are gloo
  processes on the CPU (a smoke run, not a measurement of the GPU path).
- ``collection``: the generalizable network's ground truth on a generated collection (``--shapes`` shapes) with one
  rank, ``--repeats`` times (the command of ``generalizable_scaling.py``, ``--gt-only``): median and spread of the
  ranks' ground-truth seconds and shapes/s, and each run's process wall time.

Prints a table; writes JSON (``--json``, ``common.write_json``) for ``make_performance.py``.
"""
from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

import _bootstrap  # noqa: F401  (this checkout's neurogf_warp, installed or not)
import common

MESHES = {"bunny-436K": 256, "bunny-2.2M": 64}  # mesh -> sources


def make_mesh(name: str):
    if name == "bunny-436K":
        return common.subdivided_bunny(436_000)
    if name == "bunny-2.2M":
        import trimesh

        tm = trimesh.load(common.find_shared("meshes", "stanford-bunny.obj"), process=False, force="mesh")
        v, f = np.asarray(tm.vertices), np.asarray(tm.faces)
        used = np.unique(f)  # vertices no face uses dropped, as benchmarks/geodesics.py does
        remap = np.full(len(v), -1)
        remap[used] = np.arange(len(used))
        v, f = v[used], remap[f]
        for _ in range(3):
            v, f = trimesh.remesh.subdivide(v, f)
        return np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64)
    raise SystemExit(f"unknown mesh {name!r}: one of {', '.join(MESHES)}")


def _release(devices) -> None:
    """Memory the last call freed handed back to the devices, so that each call sizes its batches from the same
    free memory (Warp's memory pool keeps freed blocks otherwise)."""
    import gc

    import warp as wp

    gc.collect()
    for d in devices:
        try:
            wp.synchronize_device(d)
            wp.set_mempool_release_threshold(d, 0)
            wp.synchronize_device(d)
        except Exception:  # noqa: BLE001 - a device without a memory pool: nothing to hand back
            pass


def gt_stage(a, out: dict) -> None:
    import warp as wp

    import neurogf_warp as ngf
    from neurogf_warp.ground_truth.solver import clear_solver_cache, load_for_capture
    from neurogf_warp.mesh.mesh import load_mesh

    cuda = [str(d) for d in wp.get_cuda_devices()]
    if not cuda:
        raise SystemExit("the gt stage needs CUDA devices: this machine has none")
    gpus = [g for g in a.gpus if g <= len(cuda)]
    out["gpus_present"] = len(cuda)
    out["gpus_skipped"] = [g for g in a.gpus if g > len(cuda)]
    t0 = time.perf_counter()
    for d in cuda[: max(gpus)]:
        load_for_capture(d)
    out["kernel_load_s"] = time.perf_counter() - t0
    rows = out.setdefault("gt", [])
    for name in a.meshes:
        S = MESHES[name] if a.sources is None else a.sources
        t0 = time.perf_counter()
        V, F = make_mesh(name)
        m = load_mesh((V, F))
        made = time.perf_counter() - t0
        src = np.random.default_rng(0).choice(len(m.internal_vertices), S, replace=False)
        ref, base = None, None
        for g in gpus:
            clear_solver_cache()
            _release(cuda)
            t0 = time.perf_counter()
            d = ngf.geodesic_distances(m, src, devices=cuda[:g])
            sec = time.perf_counter() - t0
            row = {"mesh": name, "vertices": len(m.internal_vertices), "sources": S, "gpus": g, "seconds": sec,
                   "sources_per_s": S / sec, "mesh_seconds": made}
            if ref is None:  # the fewest GPUs: the reference of the others
                ref, base = d, sec
                row.update(speedup=1.0, identical=True, max_rel_diff=0.0)
            else:
                row["speedup"] = base / sec
                same = np.array_equal(d, ref, equal_nan=True)
                fin = np.isfinite(ref) & (ref > 0)
                rel = float(np.max(np.abs(d[fin] - ref[fin]) / ref[fin])) if fin.any() else 0.0
                row.update(identical=bool(same), max_rel_diff=rel)
            if g > 1:  # per GPU (start s, end s, sources or chunks) of its solve and of its near-source patches
                from neurogf_warp.ground_truth.devices import LAST_RUN

                row["spans"] = dict(LAST_RUN)
            rows.append(row)
            print(f"{name:>11} {S:>4} sources {g} GPU(s): {sec:7.2f} s  {S / sec:7.2f} sources/s  "
                  f"x{row['speedup']:.2f}  identical={row['identical']} (max rel diff {row['max_rel_diff']:.2e})",
                  flush=True)
            if "spans" in row:
                print(f"            spans: {row['spans']}", flush=True)
            del d
        if a.determinism and name == "bunny-436K":
            twice = [ngf.geodesic_distances(m, src[:32], devices=cuda[:1]) for _ in range(2)]
            fin = np.isfinite(twice[0]) & (twice[0] > 0)
            out["one_gpu_repeat"] = {"mesh": name, "sources": 32,
                                     "identical": bool(np.array_equal(*twice, equal_nan=True)),
                                     "max_rel_diff": float(np.max(np.abs(twice[1][fin] - twice[0][fin])
                                                                  / twice[0][fin]))}
            print(f"one GPU twice, 32 sources: {out['one_gpu_repeat']}", flush=True)
        del ref


def train_stage(a, out: dict) -> None:
    import json
    import tempfile

    import warp as wp

    import neurogf_warp as ngf
    from neurogf_warp.training.checkpoint import RunFiles

    cuda = [str(d) for d in wp.get_cuda_devices()]
    gpus = [g for g in a.gpus if g <= len(cuda)]
    mesh, ref = _train_files(a)
    work = Path(tempfile.mkdtemp(prefix="multi_gpu_train_"))
    rows = out.setdefault("train", [])
    plan = [(a.warmup, gpus[0], False)] if a.warmup > 0 else []
    plan += [(b, g, True) for b in a.budgets for g in gpus]
    for budget, g, keep in plan:
        target = work / f"{a.train_mesh}_{budget:g}s_{g}gpu.ngf"
        t0 = time.perf_counter()
        model = ngf.train(str(mesh), target, budget_seconds=budget, device=cuda[0], devices=cuda[:g], force=True,
                          progress=False)
        call_s = time.perf_counter() - t0
        log = json.loads(Path(RunFiles.for_model(target).log).read_text())
        res = ngf.evaluate(model, reference=ref, heat=False, paths=False, sdf=False, device=cuda[0], progress=False,
                           verbose=False)
        n = res["neurogf"]
        row = {"mesh": a.train_mesh, "vertices": res["vertices"], "budget_s": budget, "gpus": g, "call_s": call_s,
               "mre": n["mre"], "p99": n["p99_rel"], "sources": log["history"].get("sources"),
               "dataset_s": log["timings"].get("dataset_s"), "steps": log["config"].get("steps"),
               "proxy": (log["history"].get("proxy") or {}).get("vertices")}
        print(f"train {a.train_mesh} {budget:g} s on {g} GPU(s) for the ground truth: MRE {100 * row['mre']:.3f}% "
              f"p99 {100 * row['p99']:.2f}%, {row['sources']['distance']} sources in {row['dataset_s']:.1f} s"
              + ("" if keep else " (warm-up, not kept)"), flush=True)
        if keep:
            rows.append(row)


def _train_files(a) -> tuple:
    """(mesh file, exact reference .npz) of ``--train-mesh``."""
    files = {"igea": "igea.ply", "bunny": "stanford-bunny.obj", "spot": "spot.obj"}
    mesh = common.find_shared("meshes", files[a.train_mesh])
    return mesh, common.find_shared("reference", "exact", Path(files[a.train_mesh]).stem + ".npz")


def ddp_stage(a, out: dict) -> None:
    import json
    import tempfile

    import warp as wp

    import neurogf_warp as ngf
    from neurogf_warp.training.checkpoint import RunFiles

    cuda = [str(d) for d in wp.get_cuda_devices()]
    counts = [g for g in a.gpus if g <= len(cuda)] if cuda else a.gpus
    mesh, ref = _train_files(a)
    work = Path(tempfile.mkdtemp(prefix="multi_gpu_ddp_"))
    rows = out.setdefault("ddp", [])
    plan = [(a.warmup, counts[0], False)] if a.warmup > 0 else []
    plan += [(b, g, True) for b in a.budgets for g in counts]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    for i, (budget, g, keep) in enumerate(plan):
        target = work / f"{a.train_mesh}_{budget:g}s_{g}ranks.ngf"
        args = ["neurogf_warp.cli.main", "train", str(mesh), "-o", str(target), "--budget-seconds", f"{budget:g}",
                "--force", "-q"] + (["--devices", ",".join(cuda[:g])] if cuda else ["--device", "cpu"])
        _, wall = _torchrun(g, 29850 + i, args, env)
        log = json.loads(Path(RunFiles.for_model(target).log).read_text())
        dev = cuda[0] if cuda else "cpu"
        res = ngf.evaluate(ngf.load(target), reference=ref, heat=False, paths=False, sdf=False, device=dev,
                           progress=False, verbose=False)
        n = res["neurogf"]
        row = {"mesh": a.train_mesh, "vertices": res["vertices"], "budget_s": budget, "ranks": g,
               "device": "cuda" if cuda else "cpu", "wall_s": wall, "call_s": log["timings"].get("call_s"),
               "mre": n["mre"], "p99": n["p99_rel"], "steps": log["config"].get("steps"),
               "batch_scale": log["history"].get("batch_scale"), "sources": log["history"].get("sources")}
        print(f"ddp {a.train_mesh} {budget:g} s on {g} rank(s): MRE {100 * row['mre']:.3f}% p99 "
              f"{100 * row['p99']:.2f}%, {row['steps']['joint']} joint steps, process {wall:.1f} s"
              + ("" if keep else " (warm-up, not kept)"), flush=True)
        if keep:
            rows.append(row)


def _torchrun(nproc: int, port: int, args: list, env: dict) -> tuple:
    """(stdout, wall seconds) of ``torchrun --nproc_per_node nproc`` running this checkout's module ``args[0]``
    with ``args[1:]``; exits with its output when it fails."""
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", str(nproc), "--master_port", str(port),
           str(common.ROOT / "benchmarks" / "_bootstrap.py")] + list(args)
    t0 = time.perf_counter()
    r = subprocess.run(cmd, check=False, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if r.returncode:
        print(r.stdout[-2000:], r.stderr[-2000:])
        raise SystemExit(1)
    return r.stdout, wall


def collection_stage(a, out: dict) -> None:
    coll = Path(a.collection)
    if not coll.exists():
        from neurogf_warp.generalizable.shapes import write_collection

        write_collection(coll, n=a.shapes)
    work = Path(str(coll) + ".multi_gpu")
    work.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    runs = []
    for i in range(a.repeats):
        cache = work / f"gt_{i}"
        if cache.exists():
            for p in cache.iterdir():
                p.unlink()
        stdout, wall = _torchrun(1, 29811, ["neurogf_warp.generalizable.train", str(coll), "-o", str(work / "m.pt"),
                                            "--cache", str(cache), "--sources", "256", "--targets", "512",
                                            "--cloud-points", "2048", "--gt-only"], env)
        mt = re.search(r"ground truth of (\d+) shapes in ([\d.]+) s", stdout)
        n, sec = int(mt.group(1)), float(mt.group(2))
        runs.append({"shapes": n, "gt_s": sec, "shapes_per_s": n / sec, "wall_s": wall})
        print(f"collection one rank, run {i + 1}: {n} shapes in {sec:.1f} s ({n / sec:.2f} shapes/s), "
              f"process {wall:.1f} s", flush=True)
    secs = [r["gt_s"] for r in runs]
    med = statistics.median(secs)
    out["collection"] = {"runs": runs, "median_s": med, "min_s": min(secs), "max_s": max(secs),
                         "spread": (max(secs) - min(secs)) / med,
                         "median_shapes_per_s": statistics.median(r["shapes_per_s"] for r in runs)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--stages", nargs="+", default=["gt", "train", "collection"],
                    choices=["gt", "train", "ddp", "collection"])
    ap.add_argument("--gpus", type=int, nargs="+", default=[1, 2, 4],
                    help="GPU counts (those present); the ddp stage's ranks")
    ap.add_argument("--meshes", nargs="+", default=list(MESHES), choices=list(MESHES))
    ap.add_argument("--sources", type=int, default=None, help="sources per mesh (default: 256 at 436K, 64 at 2.2M)")
    ap.add_argument("--determinism", action="store_true", help="also one GPU twice on 32 sources of the 436K mesh")
    ap.add_argument("--budgets", type=float, nargs="+", default=[20.0, 60.0], help="train stage budgets (s)")
    ap.add_argument("--warmup", type=float, default=20.0, help="train stage: a first run of this budget, not kept "
                    "(compiles every kernel; 0: none)")
    ap.add_argument("--train-mesh", default="igea", choices=["igea", "bunny", "spot"], help="train and ddp stages")
    ap.add_argument("--collection", default="multi_gpu_collection", help="collection folder (made if missing)")
    ap.add_argument("--shapes", type=int, default=128)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    a.gpus = sorted(set(a.gpus))
    out: dict = {"args": vars(a)}
    if "gt" in a.stages:
        gt_stage(a, out)
    if "train" in a.stages:
        train_stage(a, out)
    if "ddp" in a.stages:
        ddp_stage(a, out)
    if "collection" in a.stages:
        collection_stage(a, out)
    print(f"\n{'mesh':>11}{'sources':>8}{'GPUs':>6}{'seconds':>9}{'sources/s':>11}{'speed-up':>10}  identical")
    for r in out.get("gt", []):
        print(f"{r['mesh']:>11}{r['sources']:>8}{r['gpus']:>6}{r['seconds']:>9.2f}{r['sources_per_s']:>11.2f}"
              f"{r['speedup']:>9.2f}x  {r['identical']}")
    for r in out.get("train", []):
        print(f"train {r['mesh']} {r['budget_s']:g} s, ground truth on {r['gpus']} GPU(s): MRE {100 * r['mre']:.3f}%, "
              f"{r['sources']['distance']} sources")
    for r in out.get("ddp", []):
        print(f"ddp {r['mesh']} {r['budget_s']:g} s on {r['ranks']} rank(s) ({r['device']}): MRE "
              f"{100 * r['mre']:.3f}%, p99 {100 * r['p99']:.2f}%, {r['steps']['joint']} joint steps")
    if "collection" in out:
        c = out["collection"]
        print(f"collection, one rank x{len(c['runs'])}: median {c['median_s']:.1f} s "
              f"(min {c['min_s']:.1f}, max {c['max_s']:.1f}; spread {100 * c['spread']:.0f}%)")
    if a.json:
        common.write_json(a.json, out, "multi_gpu", None)
    return 0


if __name__ == "__main__":
    sys.exit(main())
