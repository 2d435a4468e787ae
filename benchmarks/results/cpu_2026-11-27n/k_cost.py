import time, numpy as np, warp as wp
wp.config.quiet = True
from neurogf_warp.ground_truth.solver import GeodesicSolver
from neurogf_warp.mesh.mesh import load_mesh
for name in ["fandisk", "homer", "alligator"]:
    m = load_mesh(f"/work/shared/meshes/{name}.obj")
    src = np.linspace(0, len(m.vertices) - 1, 16).astype(int)
    for k in (1, 2, 3):
        s = GeodesicSolver(m, k=k, device="cpu", batch=16, max_rows=16)
        s.run(src[:2])
        t = time.perf_counter(); s.run(src); dt = time.perf_counter() - t
        print(name, len(m.vertices), "k", k, "%.3f s/source" % (dt / 16), flush=True)
