# Thirteenth session: the GPU dataset with the next batch started before the rows are drawn (prefetch) against
# without (can_start forced False), same process, alternating; build_dataset(mesh, time_limit_s=20).
import json, sys, time
sys.path.insert(0, 'benchmarks')
import time_to_accuracy  # maps kernels/ to neurogf_warp.kernels in a checkout
time_to_accuracy._import_from_checkout()
from neurogf_warp.dataset import build as D
from neurogf_warp.ground_truth.solver import GeodesicSolver, load_kernels

dev = "cuda:0"
load_kernels(dev)
M = "/tmp/bt/meshes/"
D.build_dataset(M + "homer.obj", None, n_sources=64, n_path_sources=64, device=dev, progress=False)  # warm-up
can = GeodesicSolver.can_start
out = []
for mesh in ("stanford-bunny.obj", "homer.obj", "igea.ply"):
    for mode in ("off", "on", "off", "on"):
        GeodesicSolver.can_start = can if mode == "on" else property(lambda self: False)
        t0 = time.perf_counter()
        ds = D.build_dataset(M + mesh, None, device=dev, progress=False, time_limit_s=20.0)
        wall = time.perf_counter() - t0
        t = ds.meta["timings"]
        row = dict(mesh=mesh, prefetch=mode, wall=round(wall, 2), distances_s=round(t["distances_s"], 2),
                   sources=len(ds.gd_src), path_sources=ds.meta["settings"]["n_path_sources"],
                   paths=len(ds.path_global) + len(ds.path_local), complete=ds.meta["complete"],
                   proxy=ds.meta.get("proxy", {}).get("vertices") if isinstance(ds.meta.get("proxy"), dict) else None)
        out.append(row)
        print(json.dumps(row), flush=True)
json.dump(out, open(sys.argv[1], "w"), indent=1)
