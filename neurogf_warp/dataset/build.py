"""Training data for a NeuroGF (layout of neurogf-reference.md §3-4), all in the normalized unit-sphere frame.

A :class:`Dataset` holds the mesh, area-weighted surface points, distance rows [xs,ys,zs,xt,yt,zt,d] for
global / local_1 / local_2 targets, resampled ground-truth paths and full distance fields from held-out test
sources; :func:`build_dataset` computes one with the Warp geodesic solver, ``Dataset.save`` / ``Dataset.load``
write and read it as one ``.npz`` (written atomically). Definitions used here (the original repo does not say
how "local" was chosen):
- spread vertices: QSlim (fast-simplification) decimation to ~n_spread vertices, each mapped to the nearest
  mesh vertex; sources, test sources and global targets are drawn from them;
- every target is reachable from its source (same connected component): no pair ever crosses between parts;
  a source whose component holds no spread target draws its global targets from all its component's vertices;
- global targets (distances and paths): random spread vertices, or with ``target_pool="all"`` random vertices
  of the whole mesh, the measure that evaluation over all vertices uses (QSlim keeps detailed regions, so the
  spread set under-samples flat ones);
- local_1: the n_local1 vertices nearest to the source by geodesic distance;
- local_2 and local path targets: random vertices among the `local_ball` (default 5% of V, at least
  4*n_local2) nearest to the source by geodesic distance;
- a ground-truth path with a non-finite point (the solver could not trace it) is left out and counted.
"""
from __future__ import annotations

import dataclasses
import json
import os
import time
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from neurogf_warp.common.arrays import resolve_device
from neurogf_warp.common.files import atomic_write
from neurogf_warp.ground_truth.geodesics import DEFAULT_K, PATH_DELTA, GeodesicSolver, resample_polyline
from neurogf_warp.ground_truth.workers import DistanceRows
from neurogf_warp.mesh.mesh import Mesh, load_mesh

__all__ = ["Dataset", "DatasetSettings", "build_dataset", "load_dataset", "check_trainable", "sdf_truth",
           "sample_sdf_points", "surface_samples", "spread_vertices", "MIN_VERTICES"]

FORMAT_VERSION = 2  # 2: paths stored flat (K, M, 3) with their source per path; 1: (sources, targets, M, 3)
MIN_VERTICES = 16  # below this there is nothing to hold out or sample paths from
GLOBAL_PATH_POINTS = 128  # points per resampled ground-truth path (the official num_pp_g / num_pp_l)
LOCAL_PATH_POINTS = 32
# sources per solver launch on the CPU, where one launch cannot be interrupted: small enough that Ctrl-C is
# honoured within about a second (each source is solved on its own, so results do not depend on it)
CPU_SOLVER_BATCH = 8


def solver_batch(batch: int | None, device) -> int | None:
    """Sources per solver launch: ``batch`` if given, else ``CPU_SOLVER_BATCH`` on the CPU and the solver's own
    choice (a memory budget) on a GPU."""
    if batch is not None:
        return batch
    return CPU_SOLVER_BATCH if resolve_device(device).is_cpu else None


@dataclass
class DatasetSettings:
    """How much ground truth :func:`build_dataset` computes (counts per source unless stated).

    The defaults are the GPU recipe's (benchmarks/RESULTS.md): distances from 2,048 sources and paths from all
    of them. ``neurogf_warp.training.presets`` sizes them to the device and the mesh.
    """

    n_sources: int = 2048          # distance sources (spread vertices)
    n_global: int = 4096           # global distance targets per source
    n_local1: int = 32             # nearest targets per source
    n_local2: int = 2048           # targets per source inside the local ball
    local_ball: float = 0.05       # local ball: this fraction of the vertices nearest to the source
    n_path_sources: int = 2048     # path sources (the first of the distance sources)
    n_path_global: int = 128       # global path targets per path source
    n_path_local: int = 32         # local path targets per path source
    n_test: int = 8                # held-out sources with full distance fields (validation)
    n_surface: int = 100000        # area-weighted surface points (at least 30,000 are drawn)
    n_spread: int = 20000          # spread vertices (QSlim) that sources and global targets come from
    k: int = DEFAULT_K             # Steiner points per edge of the ground-truth solver
    batch: int | None = None       # sources per solver launch (None: from a memory budget)
    workers: int | None = None     # CPU solver processes, this one included (None: one per core; GPU: 1)
    target_pool: str = "spread"    # "spread" or "all": where global targets come from

    def recipe(self, seed: int) -> dict:
        """What a dataset built with these settings and ``seed`` holds (every setting but the solver's batch and
        workers, which change only speed): recorded in its meta as ``requested``, compared before a cached dataset
        is reused."""
        return {"seed": int(seed), **{k: v for k, v in dataclasses.asdict(self).items()
                                      if k not in ("batch", "workers")}}

    def validate(self) -> "DatasetSettings":
        """Raise ValueError naming the first setting out of range; returns self."""
        counts = {"n_sources": 1, "n_global": 1, "n_local1": 1, "n_local2": 1, "n_path_sources": 0,
                  "n_path_global": 1, "n_path_local": 1, "n_test": 0, "n_surface": 1, "n_spread": 1, "k": 1}
        for name, lo in counts.items():
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                raise ValueError(f"{name} must be an integer >= {lo}, got {v!r}")
        for name in ("batch", "workers"):
            v = getattr(self, name)
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1):
                raise ValueError(f"{name} must be None or an integer >= 1, got {v!r}")
        if isinstance(self.local_ball, bool) or not isinstance(self.local_ball, (int, float)) \
                or not 0 < self.local_ball <= 1:
            raise ValueError(f"local_ball must be a fraction in (0, 1], got {self.local_ball!r}")
        if self.target_pool not in ("spread", "all"):
            raise ValueError(f"target_pool must be 'spread' or 'all', got {self.target_pool!r}")
        return self


@dataclass(eq=False)
class Dataset:
    """NeuroGF training data for one mesh, normalized frame (unit sphere); ``meta`` says how it was made.

    Attributes
    ----------
    vertices : (V, 3) float32, the mesh's internal vertices, normalized
    faces : (F, 3) int32
    center : (3,) float64, scale : float -- normalized = (x - center) * scale
    surface_points : (n, 3) float32, uniform by area on the surface
    gd_src : (S,) int64 -- the distance sources (internal vertex ids)
    gd_global, gd_local1, gd_local2 : (S, n, 7) float32 rows [xs, ys, zs, xt, yt, zt, d], d normalized
    path_global : (Kg, 128, 3) float32, path_global_src : (Kg,) int64 -- paths from their source, arc-length
        resampled; path_local : (Kl, 32, 3), path_local_src : (Kl,)
    test_src : (T,) int64, test_dist : (T, V) float32 -- held-out sources and their distances (inf: unreachable)
    meta : dict -- fingerprint of the mesh, settings, seed, counts of dropped paths, timings, versions
    """

    vertices: np.ndarray
    faces: np.ndarray
    center: np.ndarray
    scale: float
    surface_points: np.ndarray
    gd_src: np.ndarray
    gd_global: np.ndarray
    gd_local1: np.ndarray
    gd_local2: np.ndarray
    path_global: np.ndarray
    path_global_src: np.ndarray
    path_local: np.ndarray
    path_local_src: np.ndarray
    test_src: np.ndarray
    test_dist: np.ndarray
    meta: dict = field(default_factory=dict)

    @classmethod
    def array_names(cls) -> tuple:
        """The names of the arrays, as stored in the file (besides ``meta``)."""
        return tuple(f.name for f in dataclasses.fields(cls) if f.name != "meta")

    @property
    def fingerprint(self) -> str | None:
        """The mesh fingerprint it was built for (``Mesh.fingerprint``)."""
        return self.meta.get("fingerprint")

    @property
    def nbytes(self) -> int:
        return int(sum(np.asarray(getattr(self, k)).nbytes for k in self.array_names()))

    def arrays(self) -> dict:
        """{name: array} of every stored array (``meta`` excluded)."""
        return {k: getattr(self, k) for k in self.array_names()}

    def __repr__(self):
        return (f"Dataset({len(self.vertices)} vertices, {len(self.gd_src)} sources, {len(self.path_global)} + "
                f"{len(self.path_local)} paths, {len(self.test_src)} test sources, {self.nbytes / 1e6:.1f} MB)")

    def save(self, path) -> str:
        """Write one ``.npz`` atomically (the previous file survives a failed save); returns the path."""
        path = os.fspath(path)
        if not path.endswith(".npz"):
            path += ".npz"
        meta = dict(self.meta, format_version=FORMAT_VERSION)
        arrays = {k: np.asarray(v) for k, v in self.arrays().items()}
        atomic_write(path, lambda f: np.savez(f, **arrays, meta=np.asarray(json.dumps(meta))))
        return path

    @classmethod
    def load(cls, path, mesh=None) -> "Dataset":
        """Read and check a dataset file; with ``mesh`` (anything ``load_mesh`` takes), also check that the
        dataset was built for that mesh (fingerprint). Raises ValueError naming what is wrong."""
        path = os.fspath(path)
        raw = read_npz(path, "dataset")
        if "meta" not in raw:
            raise ValueError(f"{path} is not a NeuroGF dataset: no 'meta' entry")
        try:
            meta = json.loads(str(raw.pop("meta")))
            assert isinstance(meta, dict)
        except Exception as e:  # noqa: BLE001
            raise ValueError(f"{path}: unreadable meta JSON ({e})") from e
        if meta.get("format_version", 1) == 1 and "path_src" in raw:
            raw = _from_format_1(raw)
        if meta.get("format_version", 1) > FORMAT_VERSION:
            raise ValueError(f"{path} was written by a newer neurogf-warp (dataset format {meta['format_version']})")
        missing = [k for k in cls.array_names() if k not in raw]
        if missing:
            raise ValueError(f"{path} is not a NeuroGF dataset: missing keys {missing}")
        ds = cls(**{k: raw[k] for k in cls.array_names()}, meta=meta)
        ds.scale = float(ds.scale)
        ds.check(path)
        if mesh is not None:
            fp = load_mesh(mesh).fingerprint
            if ds.fingerprint != fp:
                raise ValueError(f"{path} was built for a different mesh (fingerprint {ds.fingerprint!r}, "
                                 f"this mesh {fp!r})")
        return ds

    def check(self, name: str = "dataset") -> "Dataset":
        """Raise ValueError if the arrays' shapes do not fit together; returns self."""
        V = len(self.vertices)
        S = len(self.gd_src)
        expect = {"vertices": (V, 3), "faces": (None, 3), "center": (3,), "surface_points": (None, 3),
                  "gd_global": (S, None, 7), "gd_local1": (S, None, 7), "gd_local2": (S, None, 7),
                  "path_global": (len(self.path_global_src), None, 3),
                  "path_local": (len(self.path_local_src), None, 3), "test_dist": (len(self.test_src), V)}
        for k, shape in expect.items():
            a = np.asarray(getattr(self, k))
            if a.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, a.shape)):
                want = "(" + ", ".join("n" if s is None else str(s) for s in shape) + ")"
                raise ValueError(f"{name}: {k} has shape {a.shape}, expected {want}")
        for k in ("gd_src", "path_global_src", "path_local_src", "test_src"):
            a = np.asarray(getattr(self, k))
            if a.ndim != 1 or (a.size and (a.min() < 0 or a.max() >= V)):
                raise ValueError(f"{name}: {k} must be a list of vertex ids in [0, {V})")
        if not (np.isfinite(self.scale) and self.scale > 0):
            raise ValueError(f"{name}: scale must be a positive number, got {self.scale}")
        return self


def _from_format_1(raw: dict) -> dict:
    """Arrays of a format-1 file ((sources, targets, M, 3) paths and one path_src list) in today's layout."""
    out = dict(raw)
    for kind in ("global", "local"):
        p = raw[f"path_{kind}"]
        out[f"path_{kind}"] = p.reshape(-1, p.shape[-2], 3)
        out[f"path_{kind}_src"] = np.repeat(raw["path_src"].astype(np.int64), p.shape[1])
    del out["path_src"]
    return out


def read_npz(path, what: str) -> dict:
    """All arrays of an ``.npz`` (no pickles); FileNotFoundError / ValueError naming ``what`` it should be."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{what} file not found: {path}")
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except Exception as e:  # noqa: BLE001 - zip/npy errors of a truncated or foreign file
        raise ValueError(f"{path} is not a readable {what} .npz (corrupt or truncated?): {e}") from e


def load_dataset(path, mesh=None) -> Dataset:
    """``Dataset.load(path, mesh)``: read and check a dataset file."""
    return Dataset.load(path, mesh)


def check_trainable(mesh: Mesh) -> None:
    """Raise ValueError unless ``mesh`` has a connected part large enough to sample training data from."""
    V = len(mesh.vertices)
    if len(mesh.faces) == 0:
        raise ValueError("the mesh has no faces: NeuroGF needs a triangle surface")
    if V < MIN_VERTICES:
        raise ValueError(f"the mesh has only {V} vertices; training needs at least {MIN_VERTICES} "
                         "to sample sources, targets and held-out test sources")
    v = mesh.normalized_vertices[mesh.faces]
    area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1).sum()
    if not area > 1e-8:
        raise ValueError("the mesh has zero surface area (all faces degenerate); nothing to sample from")
    largest = int(np.bincount(mesh.components).max())
    if largest < MIN_VERTICES:
        raise ValueError(f"the mesh falls apart into {mesh.n_components} separate pieces of at most {largest} "
                         f"vertices each (a triangle soup?): geodesics cannot leave a piece, so there is nothing to "
                         f"learn. Weld coincident vertices first (e.g. trimesh's merge_vertices()); a piece needs "
                         f"at least {MIN_VERTICES} vertices")


# ---- sampling helpers ------------------------------------------------------------------------------
def spread_vertices(mesh: Mesh, n: int) -> np.ndarray:
    """About ``n`` well-spread internal vertex ids, sorted: QSlim-decimated vertices snapped to the nearest
    mesh vertex (random vertices where QSlim refuses the mesh)."""
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
    """(n, 3) float32 points uniformly by area on the normalized surface."""
    p = mesh.normalized_vertices[mesh.faces]
    area = np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    f = rng.choice(len(p), n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], 1)
    return np.einsum("ni,nij->nj", w, p[f]).astype(np.float32)


def sample_sdf_points(rng: np.random.Generator, surface_points: np.ndarray, n: int) -> np.ndarray:
    """(n, 3) float32 SDF queries (§3): thirds of uniform in [-1.01, 1.01]^3, surface points, and surface points
    + N(0, 0.03) clipped to +-0.03; normalized frame."""
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

    Parameters
    ----------
    mesh_or_wp_mesh : anything ``load_mesh`` takes (its normalized copy is used), or a ``wp.Mesh`` (points in its
        frame; pass ``watertight=False`` for one built with ``support_winding_number=True``)
    points : (N, 3) float, normalized frame
    device : Warp device (default: Warp's preferred one)
    watertight : sign from pseudo-normals (True) or the generalized winding number (False, for meshes with
        holes); None: decided from the mesh

    Returns
    -------
    (N,) float32 signed distances, normalized units.
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


class _Targets:
    """Target pools of one source's distance row ``d`` (internal ids; inf = another component)."""

    def __init__(self, d: np.ndarray, s: int, target_set: np.ndarray, nball: int):
        self.d, self.s = d, s
        reach = target_set[np.isfinite(d[target_set]) & (target_set != s)]
        if len(reach) == 0:  # no spread target in this source's component: all of its vertices
            everything = np.arange(len(d))
            reach = everything[np.isfinite(d) & (everything != s)]
        self.reach = reach
        order = np.argsort(d, kind="stable")
        self.local = order[np.isfinite(d[order]) & (order != s)][:nball]


def build_dataset(mesh, out_path=None, settings: DatasetSettings | None = None, *, seed: int = 0, device=None,
                  progress: bool = True, time_limit_s: float | None = None, **overrides) -> Dataset:
    """Compute the NeuroGF training data for one mesh with the Warp geodesic solver.

    Parameters
    ----------
    mesh : path, trimesh.Trimesh, (vertices, faces) or Mesh
    out_path : also save it there (``.npz``, atomic write); None keeps it in memory only
    settings : DatasetSettings (default: the GPU recipe's); ``**overrides`` replace single fields of it,
        e.g. ``n_sources=256``
    seed : random seed of every draw (sources, targets, surface points)
    device : Warp device of the solver (on the CPU, the distance sources are solved by ``settings.workers``
        processes, one per core by default; the result does not depend on how many: ``solver_workers.py``)
    progress : a progress bar on stderr
    time_limit_s : seconds (from the start of the call) after which no further batch of distance sources is
        solved: the dataset then has fewer than ``n_sources`` sources (at least one solver batch) and its meta says
        ``"complete": False``. None (default) solves them all. The test and path sources come after it.

    Returns
    -------
    Dataset
    """
    settings = dataclasses.replace(settings or DatasetSettings(), **overrides).validate()
    if time_limit_s is not None and not (isinstance(time_limit_s, (int, float)) and time_limit_s >= 0):
        raise ValueError(f"time_limit_s must be a number >= 0 or None, got {time_limit_s!r}")
    from tqdm.auto import tqdm

    t_start = time.perf_counter()
    m = load_mesh(mesh)
    check_trainable(m)
    st = settings
    rng = np.random.default_rng(seed)
    V = len(m.vertices)
    xyz = m.normalized_vertices.astype(np.float32)
    timings = {}

    t0 = time.perf_counter()
    spread = spread_vertices(m, min(st.n_spread, max(V // 2, 1)))
    n_sources = min(st.n_sources, max(len(spread) - st.n_test, 1))
    perm = rng.permutation(spread)
    test_src = np.sort(perm[:st.n_test]) if len(perm) > n_sources else perm[:0]
    gd_src = perm[len(test_src): len(test_src) + n_sources]
    n_path_sources = min(st.n_path_sources, len(gd_src))
    path_src = gd_src[:n_path_sources]
    surface = surface_samples(m, max(st.n_surface, 30000), rng)
    timings["sampling_s"] = time.perf_counter() - t0

    nball = int(min(V - 1, max(st.local_ball * V, 4 * st.n_local2, st.n_local1)))
    target_set = np.asarray(spread) if st.target_pool == "spread" else np.arange(V)
    kept, rows = [], {"global": [], "local1": [], "local2": []}

    batch = solver_batch(st.batch, device)
    solver = GeodesicSolver(m, k=st.k, device=device, batch=batch, max_rows=max(len(gd_src), len(test_src), 1))
    bar = tqdm(total=len(gd_src) + len(test_src) + n_path_sources, desc="ground truth", disable=not progress,
               unit="source", dynamic_ncols=True)
    t0 = time.perf_counter()
    solved = 0

    def more(_):  # asked before each batch of distance sources after the first
        return time_limit_s is None or time.perf_counter() - t_start <= time_limit_s

    def split(ids):
        return [ids[i: i + solver.batch] for i in range(0, len(ids), solver.batch)]

    with DistanceRows(solver, st.workers) as rows_of:
        batches = split(gd_src)
        for b, D in rows_of.rows(batches, more):
            src = batches[b]
            solved += len(src)
            for j, s in enumerate(src):
                tg = _Targets(D[j], s, target_set, nball)
                if len(tg.reach) == 0:  # nothing reachable (a vertex of degenerate faces only)
                    continue
                kept.append(s)
                pool = tg.local
                rows["global"].append(_rows(xyz, s, _pick(rng, tg.reach, st.n_global), tg.d))
                near = _pick(rng, pool[:st.n_local1], st.n_local1) if len(pool) >= st.n_local1 \
                    else _pick(rng, pool, st.n_local1)
                rows["local1"].append(_rows(xyz, s, near, tg.d))
                rows["local2"].append(_rows(xyz, s, _pick(rng, pool, st.n_local2), tg.d))
            bar.update(len(src))
        if not kept:
            raise ValueError("no training source reaches any other vertex: the mesh has no usable connected part")
        if solved < len(gd_src):  # the time limit cut the sources short
            bar.total = solved + len(test_src) + min(n_path_sources, solved)
            bar.refresh()
        gd_src = gd_src[:solved]
        n_path_sources = min(n_path_sources, len(gd_src))
        path_src = gd_src[:n_path_sources]
        test_dist = np.zeros((len(test_src), V), np.float32)
        for b, D in rows_of.rows(split(test_src)):
            test_dist[b * solver.batch: b * solver.batch + len(D)] = D
            bar.update(len(D))
        timings["worker_batches"] = rows_of.worker_batches
    timings["distances_s"] = time.perf_counter() - t0
    timings["distance_iterations"] = solver.timings["iterations"]
    del solver

    # paths: near-Dijkstra order so every traced polyline is as long as its distance
    t0 = time.perf_counter()
    paths = {"global": [], "local": []}
    path_of = {"global": [], "local": []}
    stale = 0
    if n_path_sources:
        ps = GeodesicSolver(m, k=st.k, device=device, batch=batch, delta=PATH_DELTA, max_rows=n_path_sources)
        for i in range(0, n_path_sources, ps.batch):
            src = path_src[i: i + ps.batch]
            ps.run(src)
            D = ps.vertex_distances()
            row_of, targets, count = [], [], []
            for j, s in enumerate(src):
                tg = _Targets(D[j], s, target_set, nball)
                for kind, pool, n in (("global", tg.reach, st.n_path_global), ("local", tg.local, st.n_path_local)):
                    t = _pick(rng, pool, n)
                    targets.append(t)
                    row_of.append(np.full(len(t), j))
                    count.append((kind, s, len(t)))
            pts, offs, st_flags = ps.trace(np.concatenate(row_of), np.concatenate(targets))
            stale += int(np.sum(st_flags != 0))
            c = 0
            for kind, s, n in count:
                if n:
                    m_pts = GLOBAL_PATH_POINTS if kind == "global" else LOCAL_PATH_POINTS
                    paths[kind].append(resample_polyline(pts, offs[c: c + n + 1], m_pts))
                    path_of[kind].append(np.full(n, s, dtype=np.int64))
                c += n
            bar.update(len(src))
        timings["path_iterations"] = ps.timings["iterations"]
    bar.close()
    dropped, out_paths = 0, {}
    for kind, m_pts in (("global", GLOBAL_PATH_POINTS), ("local", LOCAL_PATH_POINTS)):
        p = np.concatenate(paths[kind]) if paths[kind] else np.zeros((0, m_pts, 3), np.float32)
        src_of = np.concatenate(path_of[kind]) if path_of[kind] else np.zeros(0, np.int64)
        ok = np.isfinite(p).all(axis=(1, 2))
        dropped += int(np.sum(~ok))
        out_paths[kind] = (p[ok].astype(np.float32), src_of[ok])
    timings["paths_s"] = time.perf_counter() - t0
    timings["total_s"] = time.perf_counter() - t_start

    meta = {
        "format_version": FORMAT_VERSION, "fingerprint": m.fingerprint, "n_input_vertices": m.n_input, "seed": seed,
        # what was asked for (before capping to the mesh): a cached dataset is reused only for the same request
        "requested": st.recipe(seed),
        "settings": dict(dataclasses.asdict(st), n_sources=len(gd_src), n_path_sources=int(n_path_sources),
                         n_test=int(len(test_src)), n_spread=int(len(spread)), local_ball_vertices=nball,
                         path_delta=PATH_DELTA),
        "definitions": __doc__.split("Definitions used here", 1)[-1].strip(),
        "complete": solved == n_sources, "time_limit_s": time_limit_s,
        "sources_without_targets": int(len(gd_src) - len(kept)), "stale_paths": stale, "dropped_paths": dropped,
        "components": int(m.n_components), "units": "normalized (unit sphere)",
        "versions": {"warp": wp.config.version, "numpy": np.__version__},
        "timings": timings,
    }
    ds = Dataset(
        vertices=xyz, faces=m.faces.astype(np.int32), center=np.asarray(m.center, np.float64), scale=float(m.scale),
        surface_points=surface, gd_src=np.asarray(kept, dtype=np.int64),
        gd_global=np.stack(rows["global"]), gd_local1=np.stack(rows["local1"]), gd_local2=np.stack(rows["local2"]),
        path_global=out_paths["global"][0], path_global_src=out_paths["global"][1],
        path_local=out_paths["local"][0], path_local_src=out_paths["local"][1],
        test_src=test_src.astype(np.int64), test_dist=test_dist, meta=meta,
    ).check()
    if out_path is not None:
        ds.save(out_path)
    return ds
