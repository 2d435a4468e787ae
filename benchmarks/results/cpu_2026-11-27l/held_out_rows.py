import sys, time, numpy as np
from neurogf_warp.dataset import build as D
from neurogf_warp.mesh.mesh import load_mesh
m = load_mesh("/work/shared/meshes/igea.ply")
src = np.random.default_rng(0).choice(len(m.vertices), 8, replace=False)
w = int(sys.argv[1])
st = D.DatasetSettings(workers=w)
t0 = time.perf_counter()
r = D._held_out_rows(m, src, st, "cpu", 8)
print("workers", w, "held-out 8 rows", round(time.perf_counter() - t0, 1), "s", flush=True)
