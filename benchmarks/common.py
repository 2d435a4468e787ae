"""Shared benchmark helpers: where the test data is, and the ~436K-vertex benchmark mesh."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("NEUROGF_SHARED", ROOT.parent / "shared"))

# training benchmarks: mesh and exact-reference files, and the accuracy targets
MESHES = {"bunny": ("stanford-bunny.obj", "stanford-bunny.npz"), "fandisk": ("fandisk.obj", "fandisk.npz")}
TARGETS = {"bunny": 0.0040, "fandisk": 0.0027, "chamfer_l1": 1.25e-2}


def parse_data_options(items) -> dict:
    """--data KEY=VALUE items -> {name: text} of dataset settings (DatasetSettings); other names are an error."""
    import dataclasses

    from neurogf_warp import DatasetSettings
    from neurogf_warp.training.config import parse_assignments

    out = parse_assignments(items, flag="--data")
    names = {f.name for f in dataclasses.fields(DatasetSettings)}
    bad = [k for k in out if k.split(".")[-1] not in names]
    if bad:
        raise ValueError(f"--data {bad[0]}: not a dataset setting; known: {', '.join(sorted(names))}")
    return out


def find_shared(*parts) -> Path:
    """A file of ../shared, or of ./.bench (the copy carried to the GPU machine, where ../shared is absent)."""
    for base in (SHARED, ROOT / "shared", ROOT / ".bench", ROOT / ".bench2"):
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


def bumpy_torus(n: int = 660) -> tuple[np.ndarray, np.ndarray]:
    """A clean closed genus-1 mesh of n*n vertices (660 -> 435,600) with smooth bumps: well-shaped triangles,
    no slivers, so exact MMP (gdist) and our solver can be compared on it."""
    u, w = np.meshgrid(np.arange(n) * (2 * np.pi / n), np.arange(n) * (2 * np.pi / n), indexing="ij")
    r = 0.35 * (1 + 0.15 * np.sin(3 * u) * np.cos(2 * w))
    R = 1.0 + 0.1 * np.cos(5 * u)
    x = (R + r * np.cos(w)) * np.cos(u)
    y = (R + r * np.cos(w)) * np.sin(u)
    z = r * np.sin(w) * 1.3
    v = np.stack([x, y, z], -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a, b = i * n + j, ((i + 1) % n) * n + j
    c, d = ((i + 1) % n) * n + (j + 1) % n, i * n + (j + 1) % n
    f = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return v, f
