"""Geodesic tools built on the field, side by side with potpourri3d's heat method in the same run.

Times whole public calls (compile apart: every call is made once first): farthest point sampling, Voronoi
labels, the 3 nearest seeds of every vertex, SDF reconstruction; on the benchmark bunny (default 436K vertices)
and the shared 35K bunny, where the heat method does the same (one heat solve per sample or seed).

    python benchmarks/geodesic_tools.py --device cuda:0 [--json out.json] [--quick]
"""
from __future__ import annotations

import argparse
import time

import _bootstrap  # noqa: F401  (this checkout's neurogf_warp, installed or not)

import numpy as np  # noqa: E402


def timed(fn, sync):
    fn()  # compiles and binds; not counted
    sync()
    t = time.perf_counter()
    out = fn()
    sync()
    return time.perf_counter() - t, out


def heat_fps(solver, start: int, k: int):
    best = solver.compute_distance(start)
    chosen = [start]
    for _ in range(k - 1):
        j = int(np.argmax(best))
        chosen.append(j)
        best = np.minimum(best, solver.compute_distance(j))
    return np.array(chosen)


def heat_voronoi(solver, seeds):
    D = np.stack([solver.compute_distance(int(s)) for s in seeds])
    return np.argmin(D, 0)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda:0", help="cpu or cuda:N")
    ap.add_argument("--vertices", type=int, default=436_000, help="size of the benchmark bunny")
    ap.add_argument("--samples", type=int, default=1024, help="farthest point samples and Voronoi seeds")
    ap.add_argument("--heat-samples", type=int, default=256, help="samples and seeds for the heat method's rows")
    ap.add_argument("--resolution", type=int, default=256, help="grid of the SDF reconstruction")
    ap.add_argument("--quick", action="store_true", help="small sizes (a CPU smoke run)")
    ap.add_argument("--json", help="write the results here")
    a = ap.parse_args(argv)
    if a.quick:
        a.vertices, a.samples, a.heat_samples, a.resolution = 6_000, 16, 16, 32

    import warp as wp

    import neurogf_warp as ngf
    from neurogf_warp.inference.reconstruct import surface_distances
    from common import find_shared as shared, subdivided_bunny as benchmark_mesh, write_json

    dev = a.device
    cuda = dev.startswith("cuda")

    def sync():
        if cuda:
            wp.synchronize_device(dev)

    ckpt = shared("checkpoints", "official", "NeuroGF_Pretrainer__bunny_final.pth")
    res = {"rows": []}

    def row(mesh, V, what, tool, seconds, **kw):
        r = {"mesh": mesh, "vertices": V, "what": what, "tool": tool, "seconds": seconds, **kw}
        res["rows"].append(r)
        print(f"{mesh:>12} {V:>8,} {what:<28} {tool:<12} {seconds * 1e3:10.1f} ms", flush=True)

    v, f = benchmark_mesh(a.vertices)
    big = ngf.load(ckpt, mesh=(v, f))
    n = big.mesh.n_input
    s, fps = timed(lambda: ngf.farthest_point_sampling(big, a.samples, device=dev), sync)
    row("bench bunny", n, f"fps {a.samples}", "neurogf", s)
    s, _ = timed(lambda: ngf.voronoi(big, fps, device=dev), sync)
    row("bench bunny", n, f"voronoi {a.samples} seeds", "neurogf", s)
    s, _ = timed(lambda: ngf.nearest_seeds(big, fps, k=3, device=dev), sync)
    row("bench bunny", n, f"3 nearest of {a.samples}", "neurogf", s)

    small = ngf.load(ckpt, mesh=str(shared("meshes", "stanford-bunny.obj")))
    ms = small.mesh
    k = a.heat_samples
    s, fps_s = timed(lambda: ngf.farthest_point_sampling(small, k, device=dev), sync)
    row("bunny", len(ms.internal_vertices), f"fps {k}", "neurogf", s)
    s, _ = timed(lambda: ngf.voronoi(small, fps_s, device=dev), sync)
    row("bunny", len(ms.internal_vertices), f"voronoi {k} seeds", "neurogf", s)
    try:
        import potpourri3d as pp3d

        t = time.perf_counter()
        solver = pp3d.MeshHeatMethodDistanceSolver(ms.internal_vertices, ms.internal_faces)
        setup = time.perf_counter() - t
        start = int(ms.input_to_internal[0])
        t = time.perf_counter()
        hf = heat_fps(solver, start, k)
        row("bunny", len(ms.internal_vertices), f"fps {k}", "heat", time.perf_counter() - t, setup_s=setup)
        t = time.perf_counter()
        hv = heat_voronoi(solver, hf)
        row("bunny", len(ms.internal_vertices), f"voronoi {k} seeds", "heat", time.perf_counter() - t, setup_s=setup)
        lab = ngf.voronoi(small, ms.index[hf], device=dev)[ms.index]
        res["voronoi_label_agreement_vs_heat"] = float(np.mean(lab == hv))
    except ImportError:
        res["heat"] = "potpourri3d not installed"

    s, (rv, rf) = timed(lambda: ngf.reconstruct(small, resolution=a.resolution, device=dev), sync)
    m = surface_distances(rv, rf, ms.internal_vertices, ms.internal_faces)
    extent = float(np.linalg.norm(ms.internal_vertices.max(0) - ms.internal_vertices.min(0)))
    row("bunny", len(ms.internal_vertices), f"reconstruct {a.resolution}^3", "neurogf", s, triangles=int(len(rf)),
        chamfer_l1=m["chamfer_l1"], hausdorff=m["hausdorff"], diagonal=extent)
    print(f"reconstruction: Chamfer-L1 {m['chamfer_l1']:.3g}, Hausdorff {m['hausdorff']:.3g} "
          f"(bounding-box diagonal {extent:.3g})")
    if a.json:
        write_json(a.json, res, "geodesic_tools", dev)
    return res


if __name__ == "__main__":
    main()
