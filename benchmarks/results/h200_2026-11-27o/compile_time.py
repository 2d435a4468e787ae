# torch.compile cost per stage in this process (cold or warm inductor/Triton caches): seconds of the first 4 steps
# (compile + graph capture) and ms per step after, default preset, quarter batches
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
from neurogf_warp.training.config import STAGES

dev = torch.device("cuda:0")
mesh = load_mesh(sys.argv[1])
compile_on = sys.argv[2] == "1"
t00 = time.perf_counter()
cfg = preset("default", compile=compile_on)
cfg = dataclasses.replace(cfg, batches=cfg.batches.scaled(0.25))
ds = build_dataset(mesh, None, cfg.data, seed=cfg.seed, device="cuda:0", progress=False, time_limit_s=10.0)
data = TrainingData(ds, dev)
pool = make_sdf_pool(mesh, data.surface_points, cfg.batches.sdf_pool, cfg.seed, dev)
set_tf32(True)
tr = Trainer(cfg, data, pool, dev)
out = {"compile": compile_on}
for stage in STAGES:
    tr.set_modes(stage)
    torch.cuda.synchronize(); t = time.perf_counter()
    for s in range(4): tr.step(stage, s)
    torch.cuda.synchronize(); first = time.perf_counter() - t
    t = time.perf_counter()
    for s in range(4, 204): tr.step(stage, s)
    torch.cuda.synchronize()
    out[stage] = (round(first, 2), round((time.perf_counter() - t) / 200 * 1e3, 3))
print(json.dumps(out), flush=True)
