"""Shapes per second of ground truth and of training with 1, 2, ... ranks (torchrun, one GPU each).

    python benchmarks/generalizable_scaling.py --collection coll/ --world 1 2 --json scaling.json

For each world size W (fresh ground-truth cache per W):
1. ground truth: ``torchrun --nproc_per_node W -m neurogf_warp.generalizable.train COLL --gt-only``; shapes/s =
   shapes / the rank-0 ground-truth time (process start-up excluded; it is in ``wall_s``);
2. training: ``--steps N --val-every 0`` on that cache; shapes/s = steps x shapes_per_step x W / training time
   (from the written checkpoint; ground truth, start-up and saving excluded). The per-rank batch is fixed, so
   W ranks process W times the shapes per step (data-parallel, weak scaling), as DDP is used.
Prints the table and the W-vs-1 speed-ups (ideal: W x). If the collection folder does
not exist, ``--shapes`` shapes are generated first (``generalizable.shapes``).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import _bootstrap  # noqa: F401  (this checkout's neurogf_warp, installed or not)
from common import ROOT, write_json


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--collection", required=True)
    ap.add_argument("--shapes", type=int, default=64, help="shapes to generate if the collection is missing")
    ap.add_argument("--world", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--device", default=None, help="cpu forces gloo on the CPU")
    ap.add_argument("--sources", type=int, default=256)
    ap.add_argument("--targets", type=int, default=512)
    ap.add_argument("--cloud-points", type=int, default=2048)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--shapes-per-step", type=int, default=16)
    ap.add_argument("--work", default=None, help="scratch folder (default: <collection>.scaling)")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    coll = Path(a.collection)
    if not coll.exists():
        from neurogf_warp.generalizable.shapes import write_collection

        write_collection(coll, n=a.shapes)
    work = Path(a.work or str(coll) + ".scaling")
    work.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    common = ["--sources", str(a.sources), "--targets", str(a.targets), "--cloud-points", str(a.cloud_points)] + (["--device", a.device] if a.device else [])
    results = []
    for w in a.world:
        cache = work / f"gt_w{w}"
        if cache.exists():
            for p in cache.iterdir():
                p.unlink()
        # each rank runs the training module through _bootstrap: this checkout's package, installed or not
        run = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", str(w), "--master_port",
               str(29700 + w), str(ROOT / "benchmarks" / "_bootstrap.py"), "neurogf_warp.generalizable.train",
               str(coll), "-o", str(work / f"m_w{w}.pt"), "--cache", str(cache)] + common
        t0 = time.perf_counter()
        r = subprocess.run(run + ["--gt-only"], check=False, env=env, capture_output=True, text=True)
        wall_gt = time.perf_counter() - t0
        if r.returncode:
            print(r.stdout[-2000:], r.stderr[-2000:])
            return 1
        m = re.search(r"ground truth of (\d+) shapes in ([\d.]+) s", r.stdout)
        n, gt_s = int(m.group(1)), float(m.group(2))
        # each rank's own time for its shard (the last progress line of each): the balance of the split
        per_rank = {}
        for rk, done, total, sec in re.findall(r"\[rank (\d+)\] ground truth (\d+)/(\d+) shapes, ([\d.]+) s",
                                               r.stdout + r.stderr):
            per_rank[int(rk)] = max(per_rank.get(int(rk), 0.0), float(sec))
        out = work / f"m_w{w}.pt"
        if out.exists():
            out.unlink()
        t0 = time.perf_counter()
        r = subprocess.run(run + ["--steps", str(a.steps), "--val-every", "0", "--shapes-per-step",
                                  str(a.shapes_per_step)], check=False, env=env, capture_output=True, text=True)
        wall_tr = time.perf_counter() - t0
        if r.returncode:
            print(r.stdout[-2000:], r.stderr[-2000:])
            return 1
        import torch

        ck = torch.load(out, map_location="cpu", weights_only=True)
        tr_s = float(ck["elapsed_s"])
        row = {"world": w, "shapes": n, "gt_s": gt_s, "gt_wall_s": wall_gt, "gt_shapes_per_s": n / gt_s,
               "gt_rank_s": per_rank,
               "train_steps": int(ck["step"]), "train_s": tr_s, "train_wall_s": wall_tr,
               "train_shapes_per_s": ck["step"] * a.shapes_per_step * w / tr_s,
               "final_loss": ck["loss_history"][-1][1] if ck["loss_history"] else None}
        results.append(row)
        print(json.dumps(row), flush=True)
    base = results[0]
    print(f"\n{'ranks':>6}{'GT shapes/s':>14}{'speed-up':>10}{'train shapes/s':>16}{'speed-up':>10}")
    for r in results:
        r["gt_speedup"] = r["gt_shapes_per_s"] / base["gt_shapes_per_s"]
        r["train_speedup"] = r["train_shapes_per_s"] / base["train_shapes_per_s"]
        print(f"{r['world']:>6}{r['gt_shapes_per_s']:>14.2f}{r['gt_speedup']:>9.2f}x"
              f"{r['train_shapes_per_s']:>16.1f}{r['train_speedup']:>9.2f}x")
    if a.json:
        write_json(a.json, {"results": results, "args": vars(a)}, "generalizable_scaling", a.device)
    return 0


if __name__ == "__main__":
    sys.exit(main())
