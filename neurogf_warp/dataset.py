"""Training data for NeuroGF (layout of neurogf-reference.md §3-4), all in the normalized unit-sphere frame.

One .npz (written atomically) holds the mesh, area-weighted surface points, distance rows
[xs,ys,zs,xt,yt,zt,d] for global / local_1 / local_2 targets, resampled ground-truth paths and full distance
fields from held-out test sources. Definitions used here (the original repo does not say how "local" was
chosen):
- spread vertices: QSlim (fast-simplification) decimation to ~n_spread vertices, each mapped to the nearest
  mesh vertex; sources, test sources and global targets are drawn from them;
- global targets (distances and paths): random spread vertices reachable from the source (never another
  component), or with ``target_pool="all"`` random vertices of the whole mesh, the measure that evaluation over
  all vertices uses (QSlim keeps detailed regions, so the spread set under-samples flat ones);
- local_1: the n_local1 vertices nearest to the source by geodesic distance;
- local_2 and local path targets: random vertices among the `local_ball` (default 5% of V, at least
  4*n_local2) nearest to the source by geodesic distance.
"""
from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
import warp as wp

from .files import atomic_write
from .geodesics import DEFAULT_K, PATH_DELTA, GeodesicSolver, resample_polyline
from .arrays import resolve_device
from .mesh import Mesh, load_mesh

__all__ = ["build_dataset", "load_dataset", "sdf_truth", "sample_sdf_points", "spread_vertices", "data_main",
           "DATASET_KEYS"]

DATASET_KEYS = ("vertices", "faces", "center", "scale", "surface_points", "gd_src", "gd_global", "gd_local1",
                "gd_local2", "path_src", "path_global", "path_local", "test_src", "test_dist", "meta")


# ---- sampling helpers ------------------------------------------------------------------------------
def spread_vertices(mesh: Mesh, n: int) -> np.ndarray:
    """About n well-spread internal vertex ids: QSlim-decimated vertices snapped to the nearest mesh vertex."""
    from scipy.spatial import cKDTree

    V = len(mesh.vertices)
    if n >= V:
        return np.arange(V)
    pts = mesh.normalized_vertices.astype(np.float32)
    try:
        import fast_simplification

        vs, _ = fast_simplification.simplify(pts, mesh.faces.astype(np.int32), target_reduction=1.0 - n / V)
    except Exception:  # noqa: BLE001 - QSlim refuses some inputs (e.g. tiny or non-manifold meshes)
        vs = pts[np.random.default_rng(0).choice(V, n, replace=False)]
    _, idx = cKDTree(pts).query(vs)
    return np.unique(idx)


def surface_samples(mesh: Mesh, n: int, rng: np.random.Generator) -> np.ndarray:
    """n points uniformly by area on the normalized surface."""
    p = mesh.normalized_vertices[mesh.faces]
    area = np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    f = rng.choice(len(p), n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], 1)
    return np.einsum("ni,nij->nj", w, p[f]).astype(np.float32)


def sample_sdf_points(rng: np.random.Generator, surface_points: np.ndarray, n: int) -> np.ndarray:
    """§3 SDF queries: thirds of uniform in [-1.01,1.01]^3, surface points, surface + N(0,0.03) clipped to ±0.03."""
    n1 = n // 3
    n2 = n // 3
    n3 = n - n1 - n2
    sp = np.asarray(surface_points, dtype=np.float32)
    uni = rng.uniform(-1.01, 1.01, (n1, 3))
    surf = sp[rng.choice(len(sp), n2, replace=n2 > len(sp))]
    jit = sp[rng.choice(len(sp), n3, replace=n3 > len(sp))] + np.clip(rng.normal(0, 0.03, (n3, 3)), -0.03, 0.03)
    return np.concatenate([uni, surf, jit]).astype(np.float32)


@wp.kernel
def _sdf_kernel(mesh: wp.uint64, pts: wp.array(dtype=wp.vec3), winding: int, out: wp.array(dtype=float)):
    i = wp.tid()
    p = pts[i]
    if winding != 0:
        q = wp.mesh_query_point_sign_winding_number(mesh, p, 1.0e6)
    else:
        q = wp.mesh_query_point_sign_normal(mesh, p, 1.0e6)
    if q.result:
        c = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
        out[i] = q.sign * wp.length(p - c)
    else:
        out[i] = 1.0e6


def _is_watertight(faces: np.ndarray) -> bool:
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, c = np.unique(e, axis=0, return_counts=True)
    return bool(np.all(c == 2))


def sdf_truth(mesh_or_wp_mesh, points, device=None, watertight: bool | None = None) -> np.ndarray:
    """Signed distance (negative inside) of normalized-frame points to the mesh surface.

    Accepts anything load_mesh takes (then the normalized mesh is used) or a wp.Mesh (points in its frame;
    pass watertight=False for a wp.Mesh built with support_winding_number=True to use the winding number).
    Watertight meshes use the pseudo-normal sign; meshes with holes the generalized winding number.
    """
    device = resolve_device(device)
    if isinstance(mesh_or_wp_mesh, wp.Mesh):
        wm = mesh_or_wp_mesh
        winding = watertight is False
    else:
        m = load_mesh(mesh_or_wp_mesh)
        if watertight is None:
            watertight = _is_watertight(m.faces)
        winding = not watertight
        wm = wp.Mesh(wp.array(m.normalized_vertices.astype(np.float32), dtype=wp.vec3, device=device),
                     wp.array(m.faces.reshape(-1).astype(np.int32), dtype=wp.int32, device=device),
                     support_winding_number=winding)
    pts = wp.array(np.asarray(points, dtype=np.float32).reshape(-1, 3), dtype=wp.vec3, device=wm.device)
    out = wp.zeros(len(pts), dtype=float, device=wm.device)
    wp.launch(_sdf_kernel, dim=len(pts), inputs=[wm.id, pts, int(winding), out], device=wm.device)
    return out.numpy()


# ---- builder ---------------------------------------------------------------------------------------
def _pick(rng, pool: np.ndarray, n: int) -> np.ndarray:
    if len(pool) == 0:
        return pool
    return rng.choice(pool, n, replace=len(pool) < n)


def _rows(xyz: np.ndarray, s: int, t: np.ndarray, d: np.ndarray) -> np.ndarray:
    out = np.empty((len(t), 7), dtype=np.float32)
    out[:, :3] = xyz[s]
    out[:, 3:6] = xyz[t]
    out[:, 6] = d[t]
    return out


def build_dataset(mesh, out_path=None, n_sources: int = 2048, seed: int = 0, device=None, progress: bool = True,
                  n_global: int = 4096, n_local1: int = 32, n_local2: int = 2048, local_ball: float = 0.05,
                  n_path_sources: int = 2048, n_path_global: int = 128, n_path_local: int = 32,
                  n_test: int = 8, n_surface: int = 100000, n_spread: int = 20000, k: int = DEFAULT_K,
                  batch: int | None = None, target_pool: str = "spread") -> dict:
    """Build the NeuroGF training data for one mesh; returns the dict of arrays (and saves it if out_path).

    The defaults are the GPU benchmark's (benchmarks/RESULTS.md): distances from 2,048 sources, paths from all
    of them (128 global + 32 local targets each: test-path Chamfer 13% lower on fandisk and 3% on bunny than
    with 64, 20% lower on bunny than with 16).
    """
    if target_pool not in ("spread", "all"):
        raise ValueError(f"target_pool must be 'spread' or 'all', got {target_pool!r}")
    from tqdm.auto import tqdm

    t_start = time.perf_counter()
    m = load_mesh(mesh)
    rng = np.random.default_rng(seed)
    V = len(m.vertices)
    xyz = m.normalized_vertices.astype(np.float32)
    timings = {}

    t0 = time.perf_counter()
    spread = spread_vertices(m, min(n_spread, max(V // 2, 1)))
    n_sources = min(n_sources, max(len(spread) - n_test, 1))
    perm = rng.permutation(spread)
    test_src = np.sort(perm[:n_test]) if len(perm) > n_sources else perm[:0]
    gd_src = perm[len(test_src): len(test_src) + n_sources]
    n_path_sources = min(n_path_sources, len(gd_src))
    path_src = gd_src[:n_path_sources]
    surface = surface_samples(m, max(n_surface, 30000), rng)
    timings["sampling_s"] = time.perf_counter() - t0

    nball = int(min(V - 1, max(local_ball * V, 4 * n_local2, n_local1)))
    S = len(gd_src)
    gd_global = np.zeros((S, n_global, 7), np.float32)
    gd_local1 = np.zeros((S, n_local1, 7), np.float32)
    gd_local2 = np.zeros((S, n_local2, 7), np.float32)
    spread_set = np.asarray(spread)
    target_set = spread_set if target_pool == "spread" else np.arange(V)

    def local_pool(d, s):
        order = np.argsort(d, kind="stable")
        order = order[np.isfinite(d[order]) & (order != s)]
        return order[:nball]

    solver = GeodesicSolver(m, k=k, device=device, batch=batch, max_rows=max(S, len(test_src), 1))
    bar = tqdm(total=S + len(test_src) + n_path_sources, desc="geodesics", disable=not progress, unit="src")
    t0 = time.perf_counter()
    for i in range(0, S, solver.batch):
        src = gd_src[i: i + solver.batch]
        solver.run(src)
        D = solver.vertex_distances()
        for j, s in enumerate(src):
            d = D[j]
            reach = target_set[np.isfinite(d[target_set]) & (target_set != s)]
            pool = local_pool(d, s)
            gd_global[i + j] = _rows(xyz, s, _pick(rng, reach, n_global), d)
            gd_local1[i + j] = _rows(xyz, s, _pick(rng, pool[:n_local1], n_local1) if len(pool) >= n_local1
                                     else _pick(rng, pool, n_local1), d)
            gd_local2[i + j] = _rows(xyz, s, _pick(rng, pool, n_local2), d)
        bar.update(len(src))
    test_dist = np.zeros((len(test_src), V), np.float32)
    if len(test_src):
        test_dist[:] = solver.solve(test_src)
        bar.update(len(test_src))
    timings["distances_s"] = time.perf_counter() - t0
    timings["distance_iterations"] = solver.timings["iterations"]
    del solver

    # paths: near-Dijkstra order so every traced polyline is as long as its distance
    t0 = time.perf_counter()
    path_global = np.zeros((n_path_sources, n_path_global, 128, 3), np.float32)
    path_local = np.zeros((n_path_sources, n_path_local, 32, 3), np.float32)
    stale = 0
    if n_path_sources:
        ps = GeodesicSolver(m, k=k, device=device, batch=batch, delta=PATH_DELTA, max_rows=n_path_sources)
        for i in range(0, n_path_sources, ps.batch):
            src = path_src[i: i + ps.batch]
            ps.run(src)
            D = ps.vertex_distances()
            rows, tg, kinds = [], [], []
            for j, s in enumerate(src):
                d = D[j]
                reach = target_set[np.isfinite(d[target_set]) & (target_set != s)]
                tg.append(_pick(rng, reach, n_path_global))
                tg.append(_pick(rng, local_pool(d, s), n_path_local))
                rows += [np.full(len(tg[-2]), j), np.full(len(tg[-1]), j)]
            pts, offs, st = ps.trace(np.concatenate(rows), np.concatenate(tg))
            stale += int(np.sum(st != 0))
            c = 0
            for j in range(len(src)):
                ng, nl = len(tg[2 * j]), len(tg[2 * j + 1])
                if ng:
                    path_global[i + j] = resample_polyline(pts, offs[c: c + ng + 1], 128)
                c += ng
                if nl:
                    path_local[i + j] = resample_polyline(pts, offs[c: c + nl + 1], 32)
                c += nl
            bar.update(len(src))
        timings["path_iterations"] = ps.timings["iterations"]
    bar.close()
    timings["paths_s"] = time.perf_counter() - t0
    timings["total_s"] = time.perf_counter() - t_start

    meta = {
        "fingerprint": m.fingerprint, "n_input_vertices": m.n_input, "seed": seed,
        "settings": {"k": k, "n_sources": int(S), "n_global": n_global, "n_local1": n_local1, "n_local2": n_local2,
                     "local_ball_vertices": nball, "n_path_sources": int(n_path_sources),
                     "n_path_global": n_path_global, "n_path_local": n_path_local, "n_test": int(len(test_src)),
                     "n_spread": int(len(spread)), "target_pool": target_pool, "path_delta": PATH_DELTA},
        "definitions": __doc__.split("Definitions used here", 1)[-1].strip(),
        "stale_paths": stale, "units": "normalized (unit sphere)",
        "versions": {"warp": wp.config.version, "numpy": np.__version__},
        "timings": timings,
    }
    data = {
        "vertices": xyz, "faces": m.faces.astype(np.int32), "center": np.asarray(m.center, np.float64),
        "scale": np.float64(m.scale), "surface_points": surface, "gd_src": gd_src.astype(np.int64),
        "gd_global": gd_global, "gd_local1": gd_local1, "gd_local2": gd_local2,
        "path_src": path_src.astype(np.int64), "path_global": path_global, "path_local": path_local,
        "test_src": test_src.astype(np.int64), "test_dist": test_dist, "meta": np.asarray(json.dumps(meta)),
    }
    if out_path is not None:
        save_dataset(out_path, data)
    return data


def save_dataset(path, data: dict) -> None:
    """Write atomically: a temporary file in the same directory, then os.replace."""
    path = os.fspath(path)
    if not path.endswith(".npz"):
        path += ".npz"
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    atomic_write(path, lambda f: np.savez(f, **data))


def load_dataset(path, mesh=None) -> dict:
    """Load and check a dataset file; with `mesh`, also check it was built from that mesh (fingerprint)."""
    path = os.fspath(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise
    except Exception as e:  # noqa: BLE001 - zip/npy errors of a truncated or foreign file
        raise ValueError(f"{path} is not a readable dataset .npz (corrupt or truncated?): {e}") from e
    missing = [k for k in DATASET_KEYS if k not in data]
    if missing:
        raise ValueError(f"{path} is not a NeuroGF dataset: missing keys {missing}")
    try:
        meta = json.loads(str(data["meta"]))
    except Exception as e:  # noqa: BLE001
        raise ValueError(f"{path}: unreadable meta JSON: {e}") from e
    data["meta"] = meta
    S = len(data["gd_src"])
    for k_, w in (("gd_global", 7), ("gd_local1", 7), ("gd_local2", 7)):
        a = data[k_]
        if a.ndim != 3 or a.shape[0] != S or a.shape[2] != w:
            raise ValueError(f"{path}: {k_} has shape {a.shape}, expected ({S}, n, {w})")
    if data["test_dist"].shape != (len(data["test_src"]), len(data["vertices"])):
        raise ValueError(f"{path}: test_dist shape {data['test_dist'].shape} does not match test_src/vertices")
    if mesh is not None:
        fp = load_mesh(mesh).fingerprint
        if meta.get("fingerprint") != fp:
            raise ValueError(f"{path} was built for a different mesh (fingerprint {meta.get('fingerprint')!r}, "
                             f"this mesh {fp!r})")
    return data


def data_main(argv=None) -> int:
    """`neurogf-warp data mesh.obj -o data.npz [--sources N] [--device D]`."""
    ap = argparse.ArgumentParser(prog="neurogf-warp data", description="Build NeuroGF training data for a mesh.")
    ap.add_argument("mesh")
    ap.add_argument("-o", "--output", required=True)
    ap.add_argument("--sources", type=int, default=2048)
    ap.add_argument("--device", default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--k", type=int, default=DEFAULT_K, help="Steiner points per edge")
    ap.add_argument("--path-sources", type=int, default=128)
    ap.add_argument("--test-sources", type=int, default=8)
    ap.add_argument("--quiet", action="store_true")
    a = ap.parse_args(argv)
    data = build_dataset(a.mesh, a.output, n_sources=a.sources, seed=a.seed, device=a.device,
                         progress=not a.quiet, k=a.k, n_path_sources=a.path_sources, n_test=a.test_sources)
    if not a.quiet:
        t = json.loads(str(data["meta"]))["timings"]
        print(f"wrote {a.output}: {len(data['gd_src'])} sources, {len(data['path_src'])} path sources, "
              f"{len(data['test_src'])} test sources in {t['total_s']:.1f} s")
    return 0
