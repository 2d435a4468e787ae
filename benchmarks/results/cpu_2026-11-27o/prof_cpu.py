import dataclasses, sys, time
import torch
sys.path.insert(0, "/work/main")
from neurogf_warp.mesh.mesh import load_mesh
from neurogf_warp.training.data import TrainingData, make_sdf_pool, obtain_dataset
from neurogf_warp.training.presets import preset
from neurogf_warp.training.trainer import Trainer
from tests.conftest import shared_path
mesh = load_mesh(str(shared_path("meshes", "spot.obj")))
cfg = preset("cpu")
cfg = dataclasses.replace(cfg, batches=cfg.batches.scaled(0.0625, sdf_factor=0.25))
ds = obtain_dataset(mesh, None, "/tmp/s15/spot_ds.npz", cfg.data, cfg.seed, "cpu", False)
data = TrainingData(ds, "cpu")
pool = make_sdf_pool(mesh, data.surface_points, cfg.batches.sdf_pool, cfg.seed, "cpu")
torch.set_num_threads(1)
tr = Trainer(cfg, data, pool, torch.device("cpu"))
tr.set_modes("refine_dist")
for s in range(30): tr.step("refine_dist", s)
t = time.perf_counter()
for s in range(30, 330): tr.step("refine_dist", s)
print("ms/step", (time.perf_counter() - t) / 300 * 1e3)
with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
    for s in range(330, 430): tr.step("refine_dist", s)
print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=25))
