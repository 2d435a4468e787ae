# Fourteenth session: GPU dataset builds with the paths walked, checked and resampled on the device (new) or
# copied back and resampled from the host's copy (old = f779dde tree); build_dataset(mesh, time_limit_s=20).
# usage: python ds_trace.py ROOT OUT.json MESH... (run from ROOT's parent or anywhere; imports from ROOT)
import json, sys, time
root = sys.argv[1]
sys.path.insert(0, root + '/benchmarks')
import time_to_accuracy
time_to_accuracy._import_from_checkout()
import numpy as np
from neurogf_warp.dataset import build as D
from neurogf_warp.ground_truth.solver import GeodesicSolver, load_kernels
from neurogf_warp.ground_truth import geodesics as G
import neurogf_warp
dev = "cuda:0"
load_kernels(dev)
print("root", neurogf_warp.__file__, flush=True)
M = "/tmp/bt/meshes/"
spent = [0.0, 0]
real = D._PathSet.trace
def timed(self, solver, *a, **k):
    t = time.perf_counter(); real(self, solver, *a, **k); spent[0] += time.perf_counter() - t; spent[1] += 1
D._PathSet.trace = timed
D.build_dataset(M + "homer.obj", None, n_sources=64, n_path_sources=64, device=dev, progress=False)  # warm-up
out = []
if hasattr(GeodesicSolver, "trace_resampled"):  # the device resampling against the host's, on this GPU
    from neurogf_warp.mesh.mesh import load_mesh
    m = load_mesh(M + "stanford-bunny.obj")
    s = GeodesicSolver(m, device=dev, batch=64, max_rows=64)
    s.run(np.arange(0, 64 * 500, 500))
    rng = np.random.default_rng(0)
    rows, tg = rng.integers(0, 64, 20000), rng.integers(0, len(m.vertices), 20000)
    for mm in (128, 32):
        pts, offs, flags = s.trace(rows, tg)
        want = G.resample_polylines(pts, offs[:-1], offs[1:], mm, dev)
        got, gf = s.trace_resampled(rows, tg, mm)
        row = dict(check=f"bunny 64 rows, 20000 paths, m={mm}", flags_equal=bool(np.array_equal(gf, flags)),
                   flagged=int(np.sum(flags != 0)), bit_equal=bool(np.array_equal(got, want, equal_nan=True)),
                   max_abs=float(np.nanmax(np.abs(got - want))))
        print(json.dumps(row), flush=True); out.append(row)
for mesh in sys.argv[3:]:
    spent[:] = [0.0, 0]
    t0 = time.perf_counter()
    ds = D.build_dataset(M + mesh, None, device=dev, progress=False, time_limit_s=20.0)
    wall = time.perf_counter() - t0
    t = ds.meta["timings"]
    row = dict(root=root, mesh=mesh, wall=round(wall, 2), distances_s=round(t["distances_s"], 2),
               trace_s=round(spent[0], 2), trace_calls=spent[1], sources=len(ds.gd_src),
               paths=len(ds.path_global) + len(ds.path_local), complete=ds.meta["complete"])
    out.append(row)
    print(json.dumps(row), flush=True)
json.dump(out, open(sys.argv[2], "w"), indent=1)
