"""Where a graph-replayed GPU training step's time goes: the whole ``Trainer.step`` against its CUDA graph alone.

    python benchmarks/experiments/gpu_step_overhead.py --mesh PATH [--scale 0.25] [--steps 400]

Default preset, batches scaled by --scale (0.25 = what a 60 s budget trains on). Per stage (joint, refine_dist),
after 30 warm-up steps, milliseconds per step, wall, synchronized at the end of each timed block:
  step      ``Trainer.step`` plus the loop's per-step bookkeeping (the loss terms stacked and summed)
  replay    the stage's captured graph replayed alone (no index draws, learning rate or bookkeeping)
  kernels   GPU kernel time per replay (torch.profiler, summed over the graph's kernels) and kernel count
If step >> replay the host (index draws, copies, Python) limits the step; if replay >> kernels the GPU idles between
the graph's small kernels. Prints one JSON line per stage (with ``--top N``, then its N costliest kernels by name).
"""
import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import time_to_accuracy  # noqa: E402  (imports this checkout's neurogf_warp)

time_to_accuracy._import_from_checkout()
from neurogf_warp.mesh.mesh import load_mesh  # noqa: E402
from neurogf_warp.training.acceleration import set_tf32  # noqa: E402
from neurogf_warp.training.budget import MIN_SDF_SCALE  # noqa: E402
from neurogf_warp.training.data import TrainingData, make_sdf_pool  # noqa: E402
from neurogf_warp.dataset.build import build_dataset  # noqa: E402
from neurogf_warp.training.presets import preset  # noqa: E402
from neurogf_warp.training.trainer import Trainer  # noqa: E402


def timed(fn, n, dev):
    torch.cuda.synchronize(dev)
    t = time.perf_counter()
    for i in range(n):
        fn(i)
    torch.cuda.synchronize(dev)
    return (time.perf_counter() - t) / n * 1e3


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--mesh", required=True)
    ap.add_argument("--scale", type=float, default=0.25)
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--eager", action="store_true", help="no torch.compile (what a budget too short to compile runs)")
    ap.add_argument("--top", type=int, default=0, help="also print the N kernels (by name) taking most time per replay")
    a = ap.parse_args(argv)
    dev = torch.device("cuda:0")
    mesh = load_mesh(a.mesh)
    cfg = preset("default", compile=not a.eager)
    cfg = dataclasses.replace(cfg, batches=cfg.batches.scaled(a.scale, sdf_factor=max(a.scale, MIN_SDF_SCALE)))
    ds = build_dataset(mesh, None, cfg.data, seed=cfg.seed, device="cuda:0", progress=False, time_limit_s=10.0)
    data = TrainingData(ds, dev)
    pool = make_sdf_pool(mesh, data.surface_points, cfg.batches.sdf_pool, cfg.seed, dev)
    tr = Trainer(cfg, data, pool, dev)
    set_tf32(cfg.runtime.tf32)
    for stage in ("joint", "refine_dist"):
        tr.set_modes(stage)
        for s in range(30):
            tr.step(stage, s)
        acc = [None]

        def step(i, stage=stage):
            terms = tr.step(stage, 30 + i)
            vals = torch.stack([v.detach().float() for v in terms.values()])
            acc[0] = vals if acc[0] is None else acc[0] + vals

        graph = tr._graph.graph[0]
        ms_step = timed(step, a.steps, dev)
        ms_replay = timed(lambda i: graph.replay(), a.steps, dev)
        ms_step2 = timed(step, a.steps, dev)
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA]) as prof:
            for _ in range(50):
                graph.replay()
            torch.cuda.synchronize(dev)
        ev = [e for e in prof.events() if e.device_type == torch.autograd.DeviceType.CUDA]
        gpu_us = sum(e.device_time for e in ev) / 50
        row = dict(stage=stage, scale=a.scale, step_ms=round(ms_step, 4), step_ms_again=round(ms_step2, 4),
                   replay_ms=round(ms_replay, 4), kernels_ms=round(gpu_us / 1e3, 4), kernels=len(ev) // 50,
                   device=torch.cuda.get_device_name(dev))
        print(json.dumps(row), flush=True)
        if a.top:
            by = {}
            for e in ev:
                t, n = by.get(e.name, (0.0, 0))
                by[e.name] = (t + e.device_time / 50, n + 1)
            for name, (us, n) in sorted(by.items(), key=lambda kv: -kv[1][0])[: a.top]:
                print(f"  {us:8.1f} us {100 * us / gpu_us:5.1f}%  x{n // 50:<3d} {name[:110]}", flush=True)


if __name__ == "__main__":
    main()
