import numpy as np, warp as wp
wp.config.quiet = True
from neurogf_warp.ground_truth.geodesics import geodesic_distances
for name in ["fandisk", "spot", "cow", "rocker-arm"]:
    z = np.load(f"/work/shared/reference/exact/{name}.npz")
    mesh = f"/work/shared/meshes/{name}.obj"
    src = z["file_index"][z["sources"]]
    ex = z["dist"]
    for k in (1, 2, 3):
        d = geodesic_distances(mesh, src, device="cpu", k=k)
        d = d[:, z["file_index"]]
        ok = np.isfinite(ex) & (ex > 0)
        r = (d[ok] - ex[ok]) / ex[ok]
        print(name, "k", k, "MRE %.3f%% median %.3f%% p99 %.3f%% max %.2f%%" % (100*np.abs(r).mean(), 100*np.median(r), 100*np.quantile(np.abs(r), .99), 100*np.abs(r).max()), flush=True)
