"""Snapshot of the ground-truth solver's outputs, to prove a refactor changes nothing (byte-identical arrays).

    python benchmarks/experiments/solver_snapshot.py save /tmp/solver-before
    python benchmarks/experiments/solver_snapshot.py compare /tmp/solver-before /tmp/solver-after

Cases: the exact-reference sources of fandisk, spot, cow and stanford-bunny (bunny: the first 3) at the default
settings on the CPU, 64 traced paths from two sources of each, a windows-off run and two constructed meshes with
slivers and a non-manifold fin. Each case is one .npz of distances (S, V) float32 and the trace arrays.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
from common import find_shared  # noqa: E402

from tests.geodesic_meshes import squashed_square  # noqa: E402


def finned_sphere():
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=2)
    V, F = np.asarray(s.vertices), np.asarray(s.faces)
    a, b = F[0, 0], F[0, 1]
    tip = (V[a] + V[b]) / 2 + 0.4 * (V[a] + V[b])
    return np.concatenate([V, [tip]]), np.concatenate([F, [[a, b, len(V)]]])


def cases():
    import trimesh

    from neurogf_warp.mesh.mesh import load_mesh

    for name, nsrc in (("fandisk", 8), ("spot", 8), ("cow", 8), ("stanford-bunny", 3)):
        ref = np.load(find_shared("reference", "exact", f"{name}.npz"))
        tm = trimesh.load(find_shared("meshes", f"{name}.obj"), process=False, force="mesh")
        m = load_mesh((np.asarray(tm.vertices), np.asarray(tm.faces)))
        yield name, m, m.vertex(ref["orig_index"][ref["sources"][:nsrc]]), {}
    yield "squashed-square", load_mesh(squashed_square()), np.array([0, 30, 200]), {}
    yield "finned-sphere", load_mesh(finned_sphere()), np.array([0, 5]), {}
    yield "fandisk-k2-nowindows", load_mesh(find_shared("meshes", "fandisk.obj")), np.array([0, 100]), \
        dict(k=2, windows=False)


def save(out: Path):
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    from neurogf_warp.ground_truth.geodesics import GeodesicSolver

    out.mkdir(parents=True, exist_ok=True)
    for name, m, src, kw in cases():
        solver = GeodesicSolver(m, device="cpu", batch=len(src), **kw)
        dist = solver.solve(src)
        solver.run(src[:2])
        rng = np.random.default_rng(0)
        rows = np.repeat([0, 1], 32).astype(np.int32)
        tg = rng.integers(0, solver.nv, len(rows)).astype(np.int32)
        pts, offs, stale = solver.trace(rows, tg)
        np.savez(out / f"{name}.npz", dist=dist, pts=pts, offs=offs, stale=stale, rows=rows, targets=tg)
        print(f"{name}: {dist.shape} distances, {len(tg)} paths, {len(pts)} points", flush=True)


def compare(a: Path, b: Path) -> int:
    bad = 0
    for fa in sorted(a.glob("*.npz")):
        x, y = np.load(fa), np.load(b / fa.name)
        for key in x.files:
            same = x[key].shape == y[key].shape and np.array_equal(x[key], y[key])
            bad += not same
            print(f"{fa.stem:22s} {key:8s} {'identical' if same else 'DIFFERENT'} {x[key].shape}")
    print("all identical" if bad == 0 else f"{bad} arrays differ")
    return 1 if bad else 0


if __name__ == "__main__":
    if sys.argv[1:2] == ["save"]:
        save(Path(sys.argv[2]))
    elif sys.argv[1:2] == ["compare"]:
        sys.exit(compare(Path(sys.argv[2]), Path(sys.argv[3])))
    else:
        sys.exit(__doc__)
