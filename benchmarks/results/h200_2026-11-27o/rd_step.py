# refine_dist step: BN-folded (this tree) vs the module forward (before), alternating in one process.
# GPU: default preset, quarter batches, eager (no compile), CUDA graphs; wall ms per Trainer.step + kernel ms per replay
import dataclasses, sys, time, json
import torch
sys.path.insert(0, "benchmarks")
import time_to_accuracy
time_to_accuracy._import_from_checkout()
from neurogf_warp.mesh.mesh import load_mesh
from neurogf_warp.training.acceleration import set_tf32
from neurogf_warp.training.data import TrainingData, make_sdf_pool
from neurogf_warp.dataset.build import build_dataset
from neurogf_warp.training.presets import preset
from neurogf_warp.training.trainer import Trainer

def old_loss(self, b):
    parts = [x for key in ("global", "local1", "local2") for x in b[key][:2]]
    e = self.net.embed(torch.cat(parts)).split([len(x) for x in parts])
    return self._distance_terms(b, e)

new_loss = Trainer._loss_refine_dist
dev = torch.device("cuda:0")
for mpath in sys.argv[1:]:
    mesh = load_mesh(mpath)
    cfg = preset("default", compile=False)
    cfg = dataclasses.replace(cfg, batches=cfg.batches.scaled(0.25))
    ds = build_dataset(mesh, None, cfg.data, seed=cfg.seed, device="cuda:0", progress=False, time_limit_s=10.0)
    data = TrainingData(ds, dev)
    pool = make_sdf_pool(mesh, data.surface_points, cfg.batches.sdf_pool, cfg.seed, dev)
    set_tf32(True)
    for rep in range(2):
        for name, fn in (("module", old_loss), ("folded", new_loss)):
            Trainer._loss_refine_dist = fn
            tr = Trainer(cfg, data, pool, dev)
            tr.set_modes("joint")
            for s in range(20): tr.step("joint", s)
            tr.set_modes("refine_dist")
            for s in range(30): tr.step("refine_dist", s)
            torch.cuda.synchronize()
            t = time.perf_counter()
            for s in range(30, 1030): tr.step("refine_dist", s)
            torch.cuda.synchronize()
            ms = (time.perf_counter() - t)
            graph = tr._graph.graph[0]
            with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CUDA]) as prof:
                for _ in range(50): graph.replay()
                torch.cuda.synchronize()
            ev = [e for e in prof.events() if e.device_type == torch.autograd.DeviceType.CUDA]
            print(json.dumps(dict(mesh=mpath.split("/")[-1], variant=name, step_ms=round(ms, 4), kernels_ms=round(sum(e.device_time for e in ev) / 50e3, 4),
                                  kernels=len(ev) // 50, val=round(tr.validate(), 6))), flush=True)
