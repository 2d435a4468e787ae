# Twelfth session: the dataset with paths traced in the distance pass (new) against the separate path phase (old),
# same GPU, same process order; then a float64 check of the new pass's paths against the solver's distances.
import json, sys, time
import numpy as np
sys.path.insert(0, 'benchmarks')
import time_to_accuracy  # maps kernels/ to neurogf_warp.kernels in a checkout
time_to_accuracy._import_from_checkout()

from neurogf_warp.dataset import build as D
from neurogf_warp.ground_truth.solver import GeodesicSolver, load_kernels

dev = "cuda:0"
load_kernels(dev)
out = {}
# warm-up (solver capture, resample kernels) so that neither mode pays first-use costs
D.build_dataset(".bm/meshes/fandisk.obj", None, n_sources=64, n_path_sources=64, device=dev, progress=False)
for mesh in ("homer", "stanford-bunny"):
    for mode in ("old", "new"):
        D.trace_with_distances = (lambda device: False) if mode == "old" else (lambda device: True)
        t0 = time.perf_counter()
        ds = D.build_dataset(f".bm/meshes/{mesh}.obj", None, device=dev, progress=False, time_limit_s=20.0)
        wall = time.perf_counter() - t0
        t = ds.meta["timings"]
        row = dict(mesh=mesh, mode=mode, wall=round(wall, 2), distances_s=round(t["distances_s"], 2),
                   paths_s=round(t["paths_s"], 2), sources=len(ds.gd_src), path_sources=ds.meta["settings"]["n_path_sources"],
                   paths_g=len(ds.path_global), paths_l=len(ds.path_local), stale=ds.meta["stale_paths"],
                   dropped=ds.meta["dropped_paths"], complete=ds.meta["complete"])
        out.setdefault(mesh, []).append(row)
        print(json.dumps(row), flush=True)
# check: the new pass's paths, float64 lengths against the solver's distance at their end vertex
D.trace_with_distances = lambda device: True
ds = D.build_dataset(".bm/meshes/fandisk.obj", None, n_sources=200, n_path_sources=100, n_path_global=16,
                     n_path_local=8, device=dev, progress=False, batch=64)
V = ds.vertices.astype(np.float64)
solver = GeodesicSolver(".bm/meshes/fandisk.obj", device=dev)
worst = [1.0, 1.0]
for paths, src in ((ds.path_global, ds.path_global_src), (ds.path_local, ds.path_local_src)):
    d2 = ((V[None, :, :] - paths[:, -1].astype(np.float64)[:, None, :]) ** 2).sum(-1)
    end = d2.argmin(1)
    assert np.sqrt(d2.min(1)).max() < 1e-5
    length = np.linalg.norm(np.diff(paths.astype(np.float64), axis=1), axis=2).sum(1)
    us = np.unique(src)
    Dm = solver.solve(us)
    geo = Dm[np.searchsorted(us, src), end].astype(np.float64)
    r = length / geo
    worst = [min(worst[0], r.min()), max(worst[1], r.max())]
print(json.dumps({"check_paths": len(ds.path_global) + len(ds.path_local), "len_over_geo_min": worst[0],
                  "len_over_geo_max": worst[1], "stale": ds.meta["stale_paths"]}), flush=True)
json.dump(out, open(sys.argv[1], "w"), indent=1)
