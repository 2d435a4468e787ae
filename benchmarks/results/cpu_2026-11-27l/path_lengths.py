import sys, numpy as np
from neurogf_warp.dataset import build as D
from neurogf_warp.ground_truth.solver import GeodesicSolver
mode = sys.argv[1]
D.trace_with_distances = (lambda device: mode == "new")
ds = D.build_dataset("/work/shared/meshes/fandisk.obj", None, n_sources=24, n_path_sources=24, n_path_global=16,
                     n_path_local=8, device="cpu", progress=False, batch=8, workers=1)
V = ds.vertices.astype(np.float64)
solver = GeodesicSolver("/work/shared/meshes/fandisk.obj", device="cpu")
for kind, paths, src in (("global", ds.path_global, ds.path_global_src), ("local", ds.path_local, ds.path_local_src)):
    d2 = ((V[None, :, :] - paths[:, -1].astype(np.float64)[:, None, :]) ** 2).sum(-1)
    end = d2.argmin(1)
    length = np.linalg.norm(np.diff(paths.astype(np.float64), axis=1), axis=2).sum(1)
    us = np.unique(src)
    geo = solver.solve(us)[np.searchsorted(us, src), end].astype(np.float64)
    r = length / geo
    i = r.argmin()
    print(mode, kind, len(r), "min", r.min(), "p1", np.percentile(r, 1), "max", r.max(), "worst geo", geo[i])
