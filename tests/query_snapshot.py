"""Fixed-input answers of every public query, for the refactoring check in test_query_snapshot.py.

``python tests/query_snapshot.py OUT.npz`` writes them; the stored ``tests/data/query_snapshot.npz`` was made at
commit faff3ec (before the inference core and layout change) on Warp's CPU device. A refactoring must reproduce it
bit for bit; a change that is meant to move answers regenerates it and says why in its commit. path_refined_* were
regenerated on branch path (refinement on the mesh and the choice among five candidates, issues 21 and 24), every
other array kept as stored; path_* asks for the head's points (project=None), what the default was at faff3ec.
"""
from __future__ import annotations

import sys

import numpy as np


def answers(shared) -> dict:
    """{name: array} of the released fandisk model's answers on fixed inputs, fp32 kernels and the fp16 engine."""
    import neurogf_warp as ngf

    model = ngf.load(shared / "checkpoints" / "official" / "NeuroGF_Pretrainer__fandisk_final.pth",
                     mesh=shared / "meshes" / "fandisk.obj")
    rng = np.random.default_rng(20261124)
    V = model.mesh.vertices
    lo, hi = V.min(0), V.max(0)
    p = V[rng.choice(len(V), 24)] + 0.01 * (hi - lo) * rng.standard_normal((24, 3))
    q = V[rng.choice(len(V), 24)]
    srcs = [0, 17, 4000]
    out = {}
    for prec in ("fp32", "fp16"):
        kw = dict(device="cpu", precision=prec)
        out[f"ssad_vertex_{prec}"] = ngf.ssad(model, 5, **kw)
        out[f"ssad_point_{prec}"] = ngf.ssad(model, p[0], **kw)
        out[f"ssad_raw_{prec}"] = ngf.ssad(model, 5, raw=True, **kw)
        out[f"msad_{prec}"] = ngf.msad(model, srcs, **kw)
        out[f"matrix_{prec}"] = ngf.distance_matrix(model, srcs, **kw)
        out[f"matrix_targets_{prec}"] = ngf.distance_matrix(model, srcs, targets=[1, 2, 3, 900], **kw)
        out[f"distance_{prec}"] = ngf.distance(model, p, q, **kw)
        out[f"distance_raw_{prec}"] = ngf.distance(model, p, q, raw=True, **kw)
        out[f"sdf_{prec}"] = ngf.sdf(model, p, **kw)
        out[f"path_{prec}"] = ngf.path(model, p[:6], q[:6], m=16, project=None, **kw)  # the head, as before
        out[f"path_refined_{prec}"] = ngf.path(model, p[:3], q[:3], m=16, refine=3, **kw)
        model.unbind()
    out["project"] = ngf.project(model, p, device="cpu")
    out["path_mesh"] = ngf.path(model, p[:3], q[:3], m=16, project="mesh", device="cpu")
    return {k: np.asarray(v) for k, v in out.items()}


if __name__ == "__main__":
    from pathlib import Path

    import warp as wp

    wp.config.quiet = True
    shared = Path(__file__).resolve().parents[1].parent / "shared"
    np.savez_compressed(sys.argv[1], **answers(shared))
