"""Shared benchmark helpers: where the test data is, and the ~436K-vertex benchmark mesh."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("NEUROGF_SHARED", ROOT.parent / "shared"))


def find_shared(*parts) -> Path:
    """A file of ../shared, or of ./.bench (the copy carried to the GPU machine, where ../shared is absent)."""
    for base in (SHARED, ROOT / "shared", ROOT / ".bench"):
        p = base.joinpath(*parts)
        if p.exists():
            return p
    raise FileNotFoundError(f"{Path(*parts)} not found under {SHARED}, ./shared or ./.bench")


def subdivided_bunny(target: int = 436_000):
    """A conforming ~``target``-vertex bunny: midpoint-subdivide until above it, then QSlim back down.

    (Subdividing only some faces would leave T-junctions, i.e. cracks that change geodesics.)
    """
    import fast_simplification
    import trimesh

    tm = trimesh.load(find_shared("meshes", "stanford-bunny.obj"), process=False, force="mesh")
    v, f = np.asarray(tm.vertices), np.asarray(tm.faces)
    while len(v) < target:
        v, f = trimesh.remesh.subdivide(v, f)
    if len(v) > 1.02 * target:
        v, f = fast_simplification.simplify(v.astype(np.float32), f.astype(np.int32), 1.0 - target / len(v))
    return np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64)
