"""The main job: train a NeuroGF on the bundled default mesh (or yours), report its accuracy, answer SSAD."""
from __future__ import annotations

import argparse
import importlib.util
import time

import numpy as np


def demo_main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="neurogf-warp demo", description=__doc__)
    ap.add_argument("--mesh", default=None, help="a mesh file (default: the bundled generated blob)")
    ap.add_argument("-o", "--output", default="neurogf-demo.ngf", help="model file to write")
    ap.add_argument("--device", default=None, help="cpu or cuda:N (default: the GPU if there is one)")
    ap.add_argument("--budget-seconds", type=float, default=None,
                    help="training time (default 200 on CPU, 300 on a GPU)")
    ap.add_argument("--D", type=int, default=None, choices=(64, 128, 256, 512),
                    help="network width (default 256 on a GPU, 64 on CPU)")
    ap.add_argument("--sources", type=int, default=None, help="training sources (default 64 on CPU, 1024 on GPU)")
    a = ap.parse_args(argv)

    import torch
    import warp as wp

    import neurogf_warp as ngf
    from neurogf_warp.default_mesh import default_mesh
    from neurogf_warp.files import atomic_write

    gpu = (a.device or ("cuda:0" if torch.cuda.is_available() else "cpu")).startswith("cuda")
    device = a.device or ("cuda:0" if gpu else "cpu")
    mesh = ngf.load_mesh(a.mesh if a.mesh else default_mesh())
    name = a.mesh or "bundled blob (generated)"
    print(f"mesh: {name}, {mesh.n_input} vertices, {len(mesh.faces)} faces; device {device}")
    budget = a.budget_seconds or (300.0 if gpu else 200.0)
    n_src = a.sources or (1024 if gpu else 64)
    data = dict(n_sources=n_src, n_path_sources=min(128, n_src // 4), n_path_global=64, n_path_local=32,
                n_global=min(4096, mesh.n_input), n_local2=512, n_surface=30000)
    # The paper's batches (65K pairs, 8K paths per step) suit a GPU; a CPU gets small ones so that a
    # couple of minutes buy thousands of steps rather than a few dozen.
    opts = {} if gpu else dict(batch_sdf=2048, batch_g=4096, batch_l1=512, batch_l2=1024, batch_paths_g=128,
                                batch_paths_l=128, batch_surf=32, batch_querier=4096, sdf_pool=100000, val_every=500)
    if not gpu:
        torch.set_num_threads(1)  # tiny batches: threads only add synchronization
    opts["D"] = a.D or (256 if gpu else 64)
    t0 = time.perf_counter()
    model = ngf.train(mesh, a.output, device=device, budget_seconds=budget, dataset_options=data, resume=True,
                      **opts)
    print(f"trained in {time.perf_counter() - t0:.0f} s (dataset, querier, joint training, refinement): {a.output}")

    print("\naccuracy on held-out sources (ground truth: our geodesic solver):")
    heat = importlib.util.find_spec("potpourri3d") is not None  # the heat method beside it, when installed
    ngf.evaluate(model, heat=heat, n_sources=4, n_path_sources=4, n_path_targets=8, n_sdf=20000, device=device,
                 seed=123)

    wdev = device if wp.get_cuda_device_count() else "cpu"
    d = ngf.ssad(model, 0, device=wdev)
    t = time.perf_counter()
    d = ngf.ssad(model, 0, device=wdev)
    ms = (time.perf_counter() - t) * 1e3
    atomic_write("ssad_vertex0.npy", lambda f: np.save(f, d))
    far = int(np.nanargmax(d))
    print(f"\nSSAD from vertex 0 ({wdev}): {ms:.1f} ms for {mesh.n_input} vertices; farthest vertex {far} at "
          f"{d[far]:.4f} (mesh units); written to ssad_vertex0.npy")
    return 0
