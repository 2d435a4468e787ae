"""Per-mesh NeuroGF models for a whole folder, the meshes spread over torch.distributed ranks.

    python -m neurogf_warp.generalizable.per_mesh FOLDER -o OUTDIR --budget-seconds 60
    torchrun --nproc_per_node 8 -m neurogf_warp.generalizable.per_mesh FOLDER -o OUTDIR --budget-seconds 60

The meshes (files sorted by path) are split over the ranks (``common/shards.py``: equal counts under
``--budget-seconds``, else balanced by file size) and trained on each rank's device (``cuda:LOCAL_RANK`` when
there is a GPU) with ``ngf.train`` (one model each, ``OUTDIR/<relative path>.ngf``; the run folder beside it).
Re-running the same command continues interrupted runs and skips finished ones (``ngf.train``'s own resume
rules), so it can also be run again with another world size. A mesh that fails is recorded and does not stop the
others. Rank 0 writes ``OUTDIR/summary.json`` (per mesh: rank, seconds, model file or error) at the end.
No collective runs during training (each rank works alone); the ranks meet only to gather the summary.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from neurogf_warp.common.clock import process_clock
from neurogf_warp.common.shards import balanced_shard, file_sizes
from neurogf_warp.generalizable.train import MESH_EXTENSIONS, _finite, torchrun_command


def _value(text: str):
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return {"true": True, "false": False}.get(text.lower(), text)


def train_folder(folder, outdir, budget_seconds=None, config=None, device=None, settings=None, log=print) -> dict:
    """Train one per-mesh model for each mesh file under ``folder`` (this rank's share); returns the summary
    (complete on rank 0, this rank's rows elsewhere)."""
    import torch
    import torch.distributed as dist

    import neurogf_warp as ngf

    from neurogf_warp.generalizable.train import _dist_setup

    from neurogf_warp.training.api import check_budget

    budget_seconds = check_budget(budget_seconds)  # once, before any work (not once per mesh)
    rank, world, dev, distributed = _dist_setup(device)
    folder, outdir = Path(folder), Path(outdir)
    if not folder.is_dir():
        raise ValueError(f"{folder} is not a folder of meshes")
    files = sorted(p for p in folder.rglob("*") if p.suffix.lower() in MESH_EXTENSIONS and ".tmp" not in p.name)
    if not files:
        raise ValueError(f"no mesh files ({', '.join(MESH_EXTENSIONS)}) under {folder}")
    if dev.type == "cpu" and distributed:
        torch.set_num_threads(max(1, (os.cpu_count() or 1) // world))
    rows = []
    t_all = time.perf_counter()
    # under a budget every mesh costs about that long; without one, about its size (common/shards.py)
    cost = np.ones(len(files)) if budget_seconds else file_sizes(files)
    for i in balanced_shard(cost, world, rank):
        f = files[i]
        rel = f.relative_to(folder)
        out = (outdir / rel).with_suffix(".ngf")
        out.parent.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        row = {"mesh": str(rel), "rank": rank, "device": str(dev)}
        try:
            with process_clock(False):  # the budget is each mesh's, from its own call
                ngf.train(str(f), out, config=config, device=str(dev), budget_seconds=budget_seconds, progress=False,
                          **(settings or {}))
            row["model"] = str(out.relative_to(outdir))
        except Exception as e:  # noqa: BLE001  (one bad mesh must not stop the folder)
            row["error"] = f"{type(e).__name__}: {e}"
        row["seconds"] = time.perf_counter() - t0
        rows.append(row)
        log(f"[rank {rank}] {rel}: {'error: ' + row['error'] if 'error' in row else 'ok'} ({row['seconds']:.1f} s)")
    if distributed:
        gathered = [None] * world
        dist.all_gather_object(gathered, rows)
        rows = sorted((r for part in gathered for r in part), key=lambda r: r["mesh"])
    summary = {"folder": str(folder.resolve()), "world_size": world, "budget_seconds": budget_seconds,
               "wall_seconds": time.perf_counter() - t_all, "meshes": rows,
               "failed": sum("error" in r for r in rows)}
    if rank == 0:
        outdir.mkdir(parents=True, exist_ok=True)
        tmp = outdir / f"summary.json.tmp{os.getpid()}"
        tmp.write_text(json.dumps(summary, indent=1))
        os.replace(tmp, outdir / "summary.json")
    if distributed:
        dist.barrier()
        dist.destroy_process_group()
    return summary


def main(argv=None, prog: str = "python -m neurogf_warp.generalizable.per_mesh"):
    ap = argparse.ArgumentParser(prog=prog,
                                 description="one per-mesh NeuroGF per mesh file, spread over torchrun ranks",
                                 epilog="on N GPUs of one machine: " + torchrun_command(prog, "FOLDER -o OUTDIR"))
    ap.add_argument("folder", help="folder of mesh files (searched recursively)")
    ap.add_argument("-o", "--outdir", required=True, help="output folder: one model per mesh and summary.json")
    ap.add_argument("--budget-seconds", type=_finite, default=None, help="per mesh (ngf.train's budget)")
    ap.add_argument("--preset", default=None, help="ngf.train config preset (default: by device and mesh)")
    ap.add_argument("--device", default=None, help="cpu, cuda (this rank's GPU) or cuda:N (default: auto)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a TrainConfig setting for every mesh (repeatable), e.g. --set epochs=2")
    a = ap.parse_args(argv)
    settings = {}
    for item in a.set:
        if "=" not in item:
            print(f"error: --set {item!r}: use KEY=VALUE", file=sys.stderr)
            return 2
        k, v = item.split("=", 1)
        settings[k.strip()] = _value(v.strip())
    try:
        s = train_folder(a.folder, a.outdir, a.budget_seconds, a.preset, a.device, settings)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 1 if s["failed"] else 0


if __name__ == "__main__":
    sys.exit(main())
