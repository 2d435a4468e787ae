# refine_dist step on the CPU: BN-folded (current) vs the module forward (before), alternating, spot, cpu preset x1/16
import dataclasses, sys, time
from pathlib import Path
import torch
sys.path.insert(0, "/work/main")
from neurogf_warp.mesh.mesh import load_mesh
from neurogf_warp.training.data import TrainingData, make_sdf_pool, obtain_dataset
from neurogf_warp.training.presets import preset
from neurogf_warp.training.trainer import Trainer
from tests.conftest import shared_path

def old_loss(self, b):
    parts = [x for key in ("global", "local1", "local2") for x in b[key][:2]]
    e = self.net.embed(torch.cat(parts)).split([len(x) for x in parts])
    return self._distance_terms(b, e)

new_loss = Trainer._loss_refine_dist
mesh = load_mesh(str(shared_path("meshes", sys.argv[1] if len(sys.argv) > 1 else "spot.obj")))
cfg = preset("cpu")
cfg = dataclasses.replace(cfg, batches=cfg.batches.scaled(0.0625, sdf_factor=0.25))
ds = obtain_dataset(mesh, None, "/tmp/s15/spot_ds.npz", cfg.data, cfg.seed, "cpu", False)
data = TrainingData(ds, "cpu")
pool = make_sdf_pool(mesh, data.surface_points, cfg.batches.sdf_pool, cfg.seed, "cpu")
torch.set_num_threads(2)
for rep in range(4):
    for name, fn in (("module", old_loss), ("folded", new_loss)):
        Trainer._loss_refine_dist = fn
        tr = Trainer(cfg, data, pool, torch.device("cpu"))
        tr.set_modes("refine_dist")
        for s in range(30): tr.step("refine_dist", s)
        t = time.perf_counter()
        for s in range(30, 530): tr.step("refine_dist", s)
        print(f"{name} refine_dist {(time.perf_counter() - t) / 500 * 1e3:.3f} ms/step", flush=True)
