"""Milliseconds per CPU training step (cpu preset, short-budget batches x1/16, spot) under AdamW variants.

    python benchmarks/experiments/cpu_step_time.py --variants loop,fused,foreach,loop --threads 2

loop: torch's per-parameter loop (the CPU default when neither flag is given, and the trainer's choice before the
ninth session); foreach: multi-tensor ops; fused: one kernel (the trainer's choice now). 30 warm-up steps, then
100 joint and 300 refine_dist steps per variant, wall time. The dataset is cached in --work.
"""
import argparse
import dataclasses
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from neurogf_warp.mesh.mesh import load_mesh  # noqa: E402
from neurogf_warp.training.data import TrainingData, make_sdf_pool, obtain_dataset  # noqa: E402
from neurogf_warp.training.presets import preset  # noqa: E402
from neurogf_warp.training.trainer import Trainer  # noqa: E402
from tests.conftest import shared_path  # noqa: E402

FLAGS = {"loop": dict(fused=False, foreach=False), "foreach": dict(fused=False, foreach=True),
         "fused": dict(fused=True, foreach=False)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--variants", default="loop,fused,foreach,loop")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--work", default="/tmp/cpu_step_time")
    a = ap.parse_args(argv)
    mesh = load_mesh(str(shared_path("meshes", "spot.obj")))
    cfg = preset("cpu")
    cfg = dataclasses.replace(cfg, batches=cfg.batches.scaled(0.0625, sdf_factor=0.25))
    Path(a.work).mkdir(parents=True, exist_ok=True)
    ds = obtain_dataset(mesh, None, str(Path(a.work) / "spot_ds.npz"), cfg.data, cfg.seed, "cpu", False)
    data = TrainingData(ds, "cpu")
    pool = make_sdf_pool(mesh, data.surface_points, cfg.batches.sdf_pool, cfg.seed, "cpu")
    torch.set_num_threads(a.threads)
    adamw = torch.optim.AdamW
    try:
        for v in a.variants.split(","):
            def make(params, _flags=FLAGS[v], **kw):
                kw.pop("fused", None)
                kw.pop("foreach", None)
                return adamw(params, **kw, **_flags)

            torch.optim.AdamW = make
            tr = Trainer(cfg, data, pool, torch.device("cpu"))
            for stage, n in (("joint", 100), ("refine_dist", 300)):
                tr.set_modes(stage)
                for s in range(30):
                    tr.step(stage, s)
                t = time.perf_counter()
                for s in range(30, 30 + n):
                    tr.step(stage, s)
                print(f"{v:8s} threads {a.threads} {stage:12s} {(time.perf_counter() - t) / n * 1e3:.3f} ms/step",
                      flush=True)
    finally:
        torch.optim.AdamW = adamw


if __name__ == "__main__":
    main()
