"""The main job: train a NeuroGF on the bundled default mesh (or yours), measure it, answer an SSAD query.

Everything goes to one output folder (the model, its run folder, ``evaluation.json``, ``ssad_vertex0.npy``).
Run again on the same folder, it finds the finished model and answers from it (``force`` trains again); an
interrupted run continues where it stopped.
"""
from __future__ import annotations

import importlib.util
import json
import os
import sys
import time

from neurogf_warp.common.checks import say

__all__ = ["run_demo"]

CPU_BUDGET_S = 180.0
GPU_BUDGET_S = 300.0


def _say(on: bool, msg: str):
    say(on, msg, sys.stdout)  # the demo's report is its output: stdout


def run_demo(out_dir="neurogf-demo", *, mesh=None, device=None, budget_seconds: float | None = None,
             force: bool = False, progress: bool = True) -> dict:
    """Train (or reuse), evaluate and query a model in ``out_dir``; returns the evaluation results.

    Parameters
    ----------
    out_dir : output folder (created if missing)
    mesh : a mesh (path, trimesh, (V, F) or Mesh); default: the bundled generated blob (2,562 vertices)
    device : "cpu" or "cuda:N" (default: the GPU if there is one)
    budget_seconds : seconds for the training call, dataset included (default 180 on a CPU, 300 on a GPU)
    force : train again even when ``out_dir`` holds a finished run
    progress : progress bars and messages
    """
    import numpy as np

    from neurogf_warp.common.files import atomic_write
    from neurogf_warp.evaluation.evaluate import evaluate
    from neurogf_warp.inference.queries import ssad
    from neurogf_warp.mesh.default import default_mesh
    from neurogf_warp.mesh.mesh import load_mesh
    from neurogf_warp.training import train
    from neurogf_warp.training.api import torch_device
    from neurogf_warp.training.checkpoint import RunFiles

    folder = os.path.abspath(os.fspath(out_dir))
    if os.path.exists(folder) and not os.path.isdir(folder):
        raise FileExistsError(f"output folder {folder} exists and is not a folder")
    os.makedirs(folder, exist_ok=True)
    files = RunFiles.for_model(os.path.join(folder, "model.ngf"))
    files.check_writable()
    dev = torch_device(device)
    m = load_mesh(mesh if mesh is not None else default_mesh())
    name = mesh if isinstance(mesh, (str, os.PathLike)) else "bundled blob (generated)" if mesh is None else "given mesh"
    budget = budget_seconds or (GPU_BUDGET_S if dev.type == "cuda" else CPU_BUDGET_S)
    _say(progress, f"mesh: {name}, {m.n_input} vertices, {len(m.faces)} faces; device {dev}; output folder {folder}")

    reuse = not force and os.path.exists(files.model) and os.path.exists(files.checkpoint)
    t0 = time.perf_counter()
    model = train(m, files.model, device=dev, budget_seconds=budget, force=force, progress=progress)
    took = time.perf_counter() - t0
    _say(progress, f"model: {files.model} " + ("(the finished run's; --force trains again)" if reuse and took < 30 else
                                               f"({took:.0f} s: dataset, querier, joint training, refinement)"))

    heat = importlib.util.find_spec("potpourri3d") is not None  # the heat method beside it, when installed
    _say(progress, "\naccuracy on random vertices (ground truth: the Warp geodesic solver"
                   + (", beside the heat method):" if heat else "):"))
    res = evaluate(model, heat=heat, n_sources=4, n_path_sources=4, n_path_targets=8, n_sdf=20000, device=str(dev),
                   seed=123, progress=progress, verbose=progress)
    text = json.dumps(res, indent=1).encode()
    atomic_write(os.path.join(folder, "evaluation.json"), lambda f: f.write(text))

    d = ssad(model, 0, device=str(dev))
    t = time.perf_counter()
    d = ssad(model, 0, device=str(dev))
    ms = (time.perf_counter() - t) * 1e3
    out = os.path.join(folder, "ssad_vertex0.npy")
    atomic_write(out, lambda f: np.save(f, d))
    far = int(np.nanargmax(np.where(np.isfinite(d), d, np.nan)))
    _say(progress, f"\nSSAD from vertex 0 ({dev}): {ms:.1f} ms for {m.n_input} vertices; farthest vertex {far} at "
                   f"{d[far]:.4f} (mesh units); written to {out}")
    sys.stdout.flush()
    return res
