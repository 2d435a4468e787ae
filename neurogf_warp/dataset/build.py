"""Training data for a NeuroGF (the layout of the official NeuroGF implementation), all in the normalized
unit-sphere frame.

A :class:`Dataset` holds the mesh, area-weighted surface points, distance rows [xs,ys,zs,xt,yt,zt,d] for
global / local_1 / local_2 targets, resampled ground-truth paths and full distance fields from held-out test
sources; :func:`build_dataset` computes one with the Warp geodesic solver, ``Dataset.save`` / ``Dataset.load``
write and read it as one ``.npz`` (written atomically). Definitions used here (the original repo does not say
how "local" was chosen):
- spread vertices: QSlim (fast-simplification) decimation to ~n_spread vertices, each mapped to the nearest
  mesh vertex; sources and global targets are drawn from them;
- held-out (test) sources: uniformly random vertices of the mesh (of the proxy, with one), never distance
  sources, with full rows at the solver's default accuracy lowered near the source (``refine_near_sources``):
  the sources and the truth of ``evaluate`` without a reference, so that validation measures what it measures
  (drawn from the spread vertices, whose QSlim placement under-samples detailed regions, a teapot model scored
  8.9% on validation against 14.1% in ``evaluate``);
- every target is reachable from its source (same connected component): no pair ever crosses between parts;
  a source whose component holds no spread target draws its global targets from all its component's vertices;
- global targets (distances and paths): random spread vertices, or with ``target_pool="all"`` random vertices
  of the whole mesh, the measure that evaluation over all vertices uses (QSlim keeps detailed regions, so the
  spread set under-samples flat ones);
- local_1: the n_local1 vertices nearest to the source by geodesic distance;
- local_2 and local path targets: random vertices among the `local_ball` (default 5% of V, at least
  4*n_local2) nearest to the source by geodesic distance;
- a ground-truth path with a non-finite point (the solver could not trace it) is left out and counted.
- a proxy (``proxy`` setting, or a mesh too large for its time limit): spread vertices, distance and path
  sources, targets and paths come from a QSlim proxy in the mesh's frame (``dataset/proxy.py``), stored ids are
  the fine vertices nearest to the proxy's; surface points and held-out rows are the mesh's own.
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
from neurogf_warp.common.checks import InputError, integer, number
from neurogf_warp.common.files import atomic_write
from neurogf_warp.dataset.proxy import pin_vertices, proxy_error, proxy_mesh, row_error
from neurogf_warp.ground_truth.geodesics import DEFAULT_K, PATH_DELTA, GeodesicSolver
from neurogf_warp.ground_truth.workers import MAX_WORKERS, DistanceRows, cpu_cores
from neurogf_warp.mesh.mesh import Mesh, load_mesh

__all__ = ["Dataset", "DatasetSettings", "build_dataset", "load_dataset", "check_trainable", "sdf_truth",
           "sample_sdf_points", "surface_samples", "spread_vertices", "MIN_VERTICES"]

HELD_OUT_RULE = "uniform vertices, refined near the source"  # part of the recipe: older held-out rows are not reused
FORMAT_VERSION = 2  # 2: paths stored flat (K, M, 3) with their source per path; 1: (sources, targets, M, 3)
OPTIONAL_ARRAYS = ("full_src", "full_dist")  # absent from files written before them: empty
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

    The defaults are the GPU recipe's (docs/performance.md): distances from 2,048 sources and paths from all
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
    proxy: int | None = None       # training sources on a QSlim proxy of this many vertices (dataset/proxy.py);
                                   # None: sized to the time limit on a GPU (auto_proxy), 0: never
    full_rows: int = 0             # distance sources whose whole rows are kept (landmark features; not on a proxy)

    def recipe(self, seed: int) -> dict:
        """What a dataset built with these settings and ``seed`` holds (every setting but the solver's batch and
        workers, which change only speed): recorded in its meta as ``requested``, compared before a cached dataset
        is reused."""
        # (an automatic proxy is left out: files written before it existed are still reused)
        return {"seed": int(seed), "held_out": HELD_OUT_RULE,
                **{k: v for k, v in dataclasses.asdict(self).items()
                   if k not in ("batch", "workers") and not (k == "proxy" and v is None)
                   and not (k == "full_rows" and v == 0)}}  # files from before the setting stay reusable

    def validate(self) -> "DatasetSettings":
        """Raise ValueError naming the first setting out of range; returns self."""
        counts = {"n_sources": 1, "n_global": 1, "n_local1": 1, "n_local2": 1, "n_path_sources": 0,
                  "n_path_global": 1, "n_path_local": 1, "n_test": 0, "n_surface": 1, "n_spread": 1, "k": 1,
                  "full_rows": 0}
        for name, lo in counts.items():
            integer(name, getattr(self, name), minimum=lo)
        for name in ("batch", "workers"):
            if getattr(self, name) is not None:
                integer(name, getattr(self, name), minimum=1)
        if self.proxy is not None:
            integer("proxy", self.proxy, minimum=0)
        number("local_ball", self.local_ball, above=0, maximum=1)
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
    full_src : (K,) int64, full_dist : (K, V) float32 -- the first distance sources' whole rows, normalized
        (``DatasetSettings.full_rows``; empty when not asked for or solved on a proxy)
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
    full_src: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    full_dist: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.float32))
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
        missing = [k for k in cls.array_names() if k not in raw and k not in OPTIONAL_ARRAYS]
        if missing:
            raise ValueError(f"{path} is not a NeuroGF dataset: missing keys {missing}")
        ds = cls(**{k: raw[k] for k in cls.array_names() if k in raw}, meta=meta)
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
        if len(self.full_src):
            expect["full_dist"] = (len(self.full_src), V)
        for k, shape in expect.items():
            a = np.asarray(getattr(self, k))
            if a.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, a.shape)):
                want = "(" + ", ".join("n" if s is None else str(s) for s in shape) + ")"
                raise ValueError(f"{name}: {k} has shape {a.shape}, expected {want}")
        for k in ("gd_src", "path_global_src", "path_local_src", "test_src", "full_src"):
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


def check_trainable(mesh: Mesh, allow_vertex_joins: bool = False) -> None:
    """Raise ValueError unless ``mesh`` has a connected part large enough to sample training data from, and (unless
    ``allow_vertex_joins``) no patches that meet only at single vertices."""
    V = len(mesh.internal_vertices)
    if len(mesh.internal_faces) == 0:
        raise ValueError("the mesh has no faces: NeuroGF needs a triangle surface")
    if V < MIN_VERTICES:
        raise ValueError(f"the mesh has only {V} vertices; training needs at least {MIN_VERTICES} "
                         "to sample sources, targets and held-out test sources")
    v = mesh.internal_normalized_vertices[mesh.internal_faces]
    area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1).sum()
    if not area > 1e-8:
        raise ValueError("the mesh has zero surface area (all faces degenerate); nothing to sample from")
    largest = int(np.bincount(mesh.internal_components).max())
    if largest < MIN_VERTICES:
        raise ValueError(f"the mesh falls apart into {mesh.n_components} separate pieces of at most {largest} "
                         f"vertices each (a triangle soup?): geodesics cannot leave a piece, so there is nothing to "
                         f"learn. Weld coincident vertices first (e.g. trimesh's merge_vertices()); a piece needs "
                         f"at least {MIN_VERTICES} vertices")
    if not allow_vertex_joins:
        _refuse_vertex_joins(mesh)


def _refuse_vertex_joins(mesh: Mesh) -> None:
    """Patches joined only at single vertices: every geodesic between them passes through one of those vertices,
    a kink the network's smooth field fits badly (a teapot of 19 such patches trained to 4-17% MRE, no better than
    the heat method), so the run is refused before any work, with the fix."""
    from neurogf_warp.mesh.topology import vertex_joins

    j = vertex_joins(mesh)
    if not j.any:
        return
    msg = (f"{j.joined_patches} of the mesh's {j.patches} patches meet other patches only at single vertices "
           f"({j.pinch_vertices} such vertices): geodesics between them must pass through those vertices, which a "
           "NeuroGF fits poorly (errors of several percent, no better than the heat method). ")
    if j.coincident_vertices:
        msg += (f"{j.coincident_vertices} vertices lie exactly on a vertex of another patch: the seams are stored "
                "twice. Weld them: ngf.load_mesh(path, weld=True) (command line: --weld), then train on that mesh. ")
    msg += ("To train on the mesh as it is anyway, pass allow_vertex_joins=True (--allow-vertex-joins); the run "
            "then says whether the model beats the heat method.")
    raise InputError(msg)


# ---- sampling ---------------------------------------------------------------------------------------
def spread_vertices(mesh: Mesh, n: int) -> np.ndarray:
    """About ``n`` well-spread internal vertex ids, sorted: QSlim-decimated vertices snapped to the nearest
    mesh vertex (random vertices where QSlim refuses the mesh)."""
    from scipy.spatial import cKDTree

    V = len(mesh.internal_vertices)
    if n >= V:
        return np.arange(V)
    pts = mesh.internal_normalized_vertices.astype(np.float32)
    try:
        import fast_simplification

        vs, _ = fast_simplification.simplify(pts, mesh.internal_faces.astype(np.int32), target_reduction=1.0 - n / V)
    except Exception:  # noqa: BLE001 - QSlim refuses some inputs (e.g. tiny or non-manifold meshes)
        vs = pts[np.random.default_rng(0).choice(V, n, replace=False)]
    _, idx = cKDTree(pts).query(vs)
    return np.unique(idx)


def surface_samples(mesh: Mesh, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) float32 points uniformly by area on the normalized surface."""
    p = mesh.internal_normalized_vertices[mesh.internal_faces]
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
            watertight = _is_watertight(m.internal_faces)
        winding = not watertight
        wm = wp.Mesh(wp.array(m.internal_normalized_vertices.astype(np.float32), dtype=wp.vec3, device=device),
                     wp.array(m.internal_faces.reshape(-1).astype(np.int32), dtype=wp.int32, device=device),
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
        self.local = nearest_first(d, s, nball)


def nearest_first(d: np.ndarray, s: int, n: int) -> np.ndarray:
    """The ``n`` vertices nearest by ``d`` (finite, other than ``s``), nearest first, ties in index order: the head
    of a stable argsort, from a partition and a sort of the candidates only (a full argsort of every source's row
    was most of a GPU dataset's host time on 35K+ vertices)."""
    idx = np.flatnonzero(np.isfinite(d))
    idx = idx[idx != s]
    if n <= 0:
        return idx[:0]
    if len(idx) > n:
        kth = np.partition(d[idx], n - 1)[n - 1]
        idx = idx[d[idx] <= kth]  # every candidate, ties at the boundary included, still in index order
    return idx[np.argsort(d[idx], kind="stable")][:n]


# Under a time limit on the CPU the paths get its last PATH_SHARE: the distance sources stop when their next batch
# would end past the rest, and the path sources stop at the limit (on a GPU the paths come with the distances).
# (Estimating the paths' cost from the distance batches was tried first: on a loaded 2-core machine the first
# batch's start-up made it stop spot's distances after 8 sources)
PATH_SHARE = 0.25

# Under a time limit on a GPU, one solver batch must fit well inside its share of the limit: the solver's own batch
# (a memory budget: 512 sources on the bunny) took ~4 s for distances and ~12 s for paths on an H100, a 20 s
# budget's whole dataset share and more. The batch is sized from an estimate (an H100's seconds per distance source
# measured on meshes of four sizes, interpolated log-log; the paths traced in the same pass cost ~0.7x more). A
# batch smaller than the GPU can hold costs little per source on meshes of 30K+ vertices (each row is one
# mesh-sized sweep), but much below ~64 rows the sweeps stop filling the GPU (igea: 31 sources/s in batches of 16,
# 54 in batches of 64).
DISTANCE_BATCH_SHARE = 0.12  # of the limit, per distance batch
# (vertices, seconds per distance source) on an H100, batches of 64+ (2026-11-24; docs/performance.md): the
# bunny, igea, and the bunny subdivided twice and three times
GPU_S_PER_SOURCE = ((34_834, 5.0e-3), (134_345, 1.86e-2), (556_051, 0.100), (2_223_321, 0.833))
MIN_LIMITED_BATCH = 16


# (vertices, seconds per distance source at k = 3) of one process on a 2-core CPU (the bunny, subdivided once and
# twice; 2026-11-27, a machine about half as fast per training step as the one of 2026-11-25)
CPU_S_PER_SOURCE = ((34_834, 1.0), (139_122, 4.06), (556_051, 19.9))
CPU_S_PER_SOURCE_K1 = ((34_834, 0.26), (139_122, 1.00), (556_051, 4.94))  # the same runs at k = 1
# The held-out sources are solved before anything else, at k = 3 on the mesh itself, in one solver batch (one
# process). A time limit that their estimated time exceeds by more than HELD_OUT_MARGIN x itself and by more than
# HELD_OUT_SLACK_S cannot be kept: refused (the estimate may be 2x off on another machine; a limit of 0, "as little
# as possible", is kept on every mesh whose held-out rows take seconds)
HELD_OUT_MARGIN = 1.5
HELD_OUT_SLACK_S = 10.0


def gpu_seconds_per_source(n_vertices: int) -> float:
    """Estimated GPU seconds per distance source on a mesh of ``n_vertices`` (an H100's measured rates)."""
    return seconds_per_source(n_vertices, GPU_S_PER_SOURCE)


def seconds_per_source(n_vertices: int, table) -> float:
    """Seconds per distance source on a mesh of ``n_vertices`` from a rate ``table`` of (vertices, seconds)
    (``GPU_S_PER_SOURCE``, ``CPU_S_PER_SOURCE``): interpolated log-log, extrapolated with the slope of the
    nearest two."""
    v, t = np.log([p[0] for p in table]), np.log([p[1] for p in table])
    x = np.log(max(n_vertices, 1))
    i = int(np.clip(np.searchsorted(v, x) - 1, 0, len(v) - 2))
    return float(np.exp(t[i] + (t[i + 1] - t[i]) * (x - v[i]) / (v[i + 1] - v[i])))


def cpu_seconds_per_source(n_vertices: int, k: int) -> float:
    """Estimated seconds per distance source of one CPU process at ``k`` Steiner points per edge (the tables at
    k = 1 and k = 3; linear in k between and beyond them, as the graph's size is)."""
    t1 = seconds_per_source(n_vertices, CPU_S_PER_SOURCE_K1)
    t3 = seconds_per_source(n_vertices, CPU_S_PER_SOURCE)
    return t1 + (k - 1) * (t3 - t1) / 2


def limited_batch(seconds: float, per_source: float) -> int:
    """The largest power of two of sources solved in ``seconds`` at ``per_source`` seconds each (at least
    ``MIN_LIMITED_BATCH``)."""
    n = max(seconds, 0.0) / max(per_source, 1e-9)
    return max(MIN_LIMITED_BATCH, 1 << max(0, int(np.floor(np.log2(max(n, 1.0))))))


# A mesh too large for its time limit trains on a proxy (dataset/proxy.py): when fewer than PROXY_SOURCES sources
# of the fine mesh fit in PROXY_SHARE of the limit, the proxy is sized so that PROXY_SOURCES do, never below
# PROXY_MIN_VERTICES nor above half the mesh. The proxy is kept only if its distances from the held-out sources are
# within PROXY_MAX_MRE of the fine mesh's (measured before any training source).
# Why 1,024 sources: at 60 s on an H100, igea (134K vertices) trained on its own mesh got 384 sources, 0.388% MRE /
# 1.85% p99; on a 34K proxy 768-1,024 sources, 0.306% / 1.36% and 0.309% / 1.43%; on a 67K proxy 512 sources,
# 0.379% / 1.89%. The bunny (35K) on a 17K proxy: 2,048 sources instead
# of 1,280 and no gain (0.487% against 0.505%), so meshes below 2 x PROXY_MIN_VERTICES keep their own.
# DATASET_SLOWDOWN: a dataset's distance phase solves at about half the rate of the table above (its batches are
# cut by the clock, the rows are processed on the host; the same runs: bunny 9.0 ms a source against the table's
# 5.0, igea 29.6 against 18.6, the 34K and 67K proxies 11.1 and 20.3 against ~5 and ~9.6)
PROXY_SOURCES = 1024
PROXY_SHARE = 0.5
PROXY_MIN_VERTICES = 30_000
PROXY_MAX_MRE = 0.003
DATASET_SLOWDOWN = 2.0


def auto_proxy(n_vertices: int, n_sources: int, time_limit_s: float | None, rate=gpu_seconds_per_source) -> int:
    """Vertices of the proxy a build under ``time_limit_s`` uses for ``n_sources`` asked on a mesh of
    ``n_vertices`` (0: none, the fine mesh is affordable or no limit is set). ``rate(v)``: the estimated seconds a
    distance source of a v-vertex mesh takes (default: an H100's; on the CPU, one process's over the processes)."""
    if time_limit_s is None or n_vertices < 2 * PROXY_MIN_VERTICES:
        return 0
    want = min(n_sources, PROXY_SOURCES)
    per = PROXY_SHARE * time_limit_s / (want * DATASET_SLOWDOWN)  # table seconds a source may take
    if rate(n_vertices) <= per:
        return 0
    lo, hi = PROXY_MIN_VERTICES, n_vertices // 2  # the largest size whose estimated rate fits: bisection
    if rate(lo) > per:
        return lo
    while hi - lo > 1000:
        mid = (lo + hi) // 2
        lo, hi = (mid, hi) if rate(mid) <= per else (lo, mid)
    return lo


class _Clock:
    """The dataset's time limit: seconds since the call started, and what is left of ``limit`` (None: no limit)."""

    def __init__(self, t_start: float, limit: float | None):
        self.t_start, self.limit = t_start, limit

    def left(self) -> float:
        return float("inf") if self.limit is None else self.limit - (time.perf_counter() - self.t_start)


@dataclass
class _Plan:
    """Phase 1's draws: spread vertices, the held-out test sources, the distance sources in solve order, the path
    sources (the first distance sources), the surface points and the local-ball size."""

    spread: np.ndarray
    test_src: np.ndarray
    gd_src: np.ndarray
    n_path_sources: int
    surface: np.ndarray
    nball: int
    target_set: np.ndarray


@dataclass
class _Made:
    """Phases 2-3's results, as ``_assemble`` stores them.

    kept : (n,) ids of the distance sources with targets; rows : {"global", "local1", "local2": [(m, 7) float32]}
    distance rows (p, q, d); gd_src : the distance sources solved; n_path_sources : path sources traced;
    out_paths : {"global", "local": ((K, M, 3) points, (K,) source ids)}; test_dist : (T, V) held-out distances
    (normalized units) and test_k their solver's k; complete : every source asked for was solved; stale, dropped :
    path counts; timings : seconds per phase; proxy_meta, coarse : the proxy's and the coarse rows' records or None.
    """

    kept: object
    rows: dict
    gd_src: np.ndarray
    n_path_sources: int
    out_paths: dict
    test_dist: np.ndarray
    test_k: int
    complete: bool
    stale: int
    dropped: int
    timings: dict
    proxy_meta: dict | None = None
    coarse: dict | None = None


def _spread_first(xyz: np.ndarray, ids: np.ndarray, k: int) -> np.ndarray:
    """``ids`` reordered so that its first ``k`` are spread by farthest-point sampling in space (starting at
    ``ids[0]``); the rest keep their order."""
    k = min(k, len(ids))
    if k <= 1:
        return ids
    p = xyz[ids]
    far = np.full(len(ids), np.inf)
    order = [0]
    for _ in range(k - 1):
        far = np.minimum(far, ((p - p[order[-1]]) ** 2).sum(1))
        far[order[-1]] = -1.0  # chosen already
        order.append(int(far.argmax()))
    rest = np.ones(len(ids), bool)
    rest[order] = False
    return np.concatenate([ids[order], ids[rest]])


def _sample(m: Mesh, st: DatasetSettings, rng, surface_mesh: Mesh | None = None,
            test_src: np.ndarray | None = None) -> _Plan:
    """Phase 1: spread vertices (QSlim), test / distance / path sources, area-weighted surface points (on
    ``surface_mesh``, default ``m``). ``test_src``: held-out sources already chosen (left out of the others)."""
    V = len(m.internal_vertices)
    spread = spread_vertices(m, min(st.n_spread, max(V // 2, 1)))
    n_sources = min(st.n_sources, max(len(spread) - st.n_test, 1))
    perm = rng.permutation(spread)
    if test_src is None:  # uniform over the vertices, as evaluate() draws its sources (module docstring)
        n_test = min(st.n_test, V) if len(perm) > n_sources else 0
        test_src = np.sort(rng.choice(V, n_test, replace=False)).astype(perm.dtype)
    gd_src = perm[~np.isin(perm, test_src)][:n_sources]
    if st.full_rows:  # the whole rows kept are landmarks: solve a spread set of them first
        gd_src = _spread_first(np.asarray(m.internal_vertices, np.float64), gd_src, st.full_rows)
    surface = surface_samples(m if surface_mesh is None else surface_mesh, max(st.n_surface, 30000), rng)
    nball = int(min(V - 1, max(st.local_ball * V, 4 * st.n_local2, st.n_local1)))
    target_set = np.asarray(spread) if st.target_pool == "spread" else np.arange(V)
    return _Plan(spread, test_src, gd_src, min(st.n_path_sources, len(gd_src)), surface, nball, target_set)


def _distances(m: Mesh, st: DatasetSettings, plan: _Plan, rng, solver, clock: _Clock, bar,
               test_dist: np.ndarray | None = None, found: _PathSet | None = None, devices=(),
               full: dict | None = None) -> tuple:
    """Phase 2: the test sources' full rows (unless given as ``test_dist``), then distance sources in order, as
    many as the time limit allows (at least one batch) while keeping its last ``PATH_SHARE`` for phase 3's paths.
    With ``found`` (``trace_with_distances``) the paths of the first ``plan.n_path_sources`` sources are traced
    from the same runs into it, and no time is kept for phase 3. ``devices``: further GPUs that share the batches
    (``DistanceRows``), their rows and paths the same as ``solver``'s. ``full``: a dict that receives the whole rows
    of the first ``st.full_rows`` kept sources ("ids", "rows").

    Returns (kept source ids, {"global"|"local1"|"local2": [(n, 7) rows per kept source]}, sources solved,
    (T, V) test distances, worker batches, path sources traced).
    """
    xyz = m.internal_normalized_vertices.astype(np.float32)
    step = solver.batch
    split = lambda ids: [ids[i: i + step] for i in range(0, len(ids), step)]  # noqa: E731
    tests, sources = split(plan.test_src) if test_dist is None else [], split(plan.gd_src)
    batches = tests + sources
    kept, rows = [], {"global": [], "local1": [], "local2": []}
    if test_dist is None:
        test_dist = np.zeros((len(plan.test_src), len(m.internal_vertices)), np.float32)
    # marks: (time, sources back) per batch back; started: batch start times (batch 0 starts now, unasked)
    solved, marks, started = [0], [], [time.perf_counter()]
    traced = 0
    keep = 0.0 if found is not None else PATH_SHARE  # of the limit, for phase 3
    # the batches whose paths are traced: their solver (on whichever device) keeps its path records until then
    n_traced = len(tests) + (-(-plan.n_path_sources // step) if found is not None else 0)
    hold = lambda i: len(tests) <= i < n_traced  # noqa: E731
    with DistanceRows(solver, st.workers, devices=devices) as rows_of:
        if found is not None and rows_of.workers != 1:  # a worker's rows would be traced on this solver's run
            raise RuntimeError("paths are traced in the distance pass only when this process solves every row")

        def more(i):  # asked before batch i > 0 starts: tests and one distance batch always, then by the clock
            now = time.perf_counter()
            if i <= len(tests) or clock.limit is None:
                started.append(now)
                return True
            if len(marks) >= 2:  # wall seconds per source since the first batch, which carries the solver's set-up
                per = (now - marks[0][0]) / max(marks[-1][1] - marks[0][1], 1)
            else:  # asked (by a worker's feeder) before the second batch came back: since that batch started
                per = (now - started[-1]) / step
            if clock.left() - keep * clock.limit < step * per:
                return False
            started.append(now)
            return True

        for b, D in rows_of.rows(batches, more, hold):
            marks.append((time.perf_counter(), (marks[-1][1] if marks else 0) + len(D)))
            if b < len(tests):
                test_dist[b * step: b * step + len(D)] = D
                rows_of.prefetch()
                bar.update(len(D))
                continue
            src = batches[b]
            first = solved[0]  # the batch's place among the distance sources
            solved[0] += len(src)
            targets = {}
            n_trace = min(len(src), plan.n_path_sources - first) if found is not None else 0
            if n_trace > 0:  # the solver still holds this batch's path records (DistanceRows yields before the next)
                targets = {j: _Targets(D[j], src[j], plan.target_set, plan.nball) for j in range(n_trace)}
                found.trace(rows_of.solver_of(b), D[:n_trace], src[:n_trace], plan, st, rng,
                            [targets[j] for j in range(n_trace)])
                traced += n_trace
                bar.update(n_trace)
            # the next batch solves on the GPU while this one's rows are drawn here (the host's share of a GPU
            # dataset: 0.55 s per 256 bunny sources on a 2-core CPU, against ~0.8 s of solving)
            rows_of.prefetch()
            for j, s in enumerate(src):
                tg = targets.get(j) or _Targets(D[j], s, plan.target_set, plan.nball)
                if len(tg.reach) == 0:  # nothing reachable (a vertex of degenerate faces only)
                    continue
                kept.append(s)
                if full is not None and len(full.setdefault("ids", [])) < st.full_rows:
                    full["ids"].append(s)
                    full.setdefault("rows", []).append(np.asarray(D[j], np.float32).copy())
                pool = tg.local
                rows["global"].append(_rows(xyz, s, _pick(rng, tg.reach, st.n_global), tg.d))
                near = _pick(rng, pool[:st.n_local1], st.n_local1) if len(pool) >= st.n_local1 \
                    else _pick(rng, pool, st.n_local1)
                rows["local1"].append(_rows(xyz, s, near, tg.d))
                rows["local2"].append(_rows(xyz, s, _pick(rng, pool, st.n_local2), tg.d))
            bar.update(len(src))
        worker_batches = rows_of.worker_batches + rows_of.device_batches
    if not kept:
        raise ValueError("no training source reaches any other vertex: the mesh has no usable connected part")
    return kept, rows, solved[0], test_dist, worker_batches, traced


class _PathSet:
    """Traced ground-truth paths as they come, per kind ("global": GLOBAL_PATH_POINTS points, "local":
    LOCAL_PATH_POINTS), with their source ids and the count of paths the solver flagged."""

    def __init__(self):
        self.paths = {"global": [], "local": []}
        self.src_of = {"global": [], "local": []}
        self.stale = 0

    def trace(self, solver, D: np.ndarray, src: np.ndarray, plan: _Plan, st: DatasetSettings, rng,
              targets_of: list | None = None) -> None:
        """Paths from the sources ``src`` of ``solver``'s last run (rows 0..len(src)-1, distances ``D``) to
        ``st.n_path_global`` random reachable targets and ``st.n_path_local`` in the local ball of each
        (``targets_of``: their ``_Targets``, when already made)."""
        picked = {"global": ([], [], []), "local": ([], [], [])}  # kind -> (rows, targets, source ids)
        for j, s in enumerate(src):
            tg = targets_of[j] if targets_of is not None else _Targets(D[j], s, plan.target_set, plan.nball)
            for kind, pool, n in (("global", tg.reach, st.n_path_global), ("local", tg.local, st.n_path_local)):
                t = _pick(rng, pool, n)
                picked[kind][0].append(np.full(len(t), j))
                picked[kind][1].append(t)
                picked[kind][2].append(np.full(len(t), s, dtype=np.int64))
        for kind, m_pts in (("global", GLOBAL_PATH_POINTS), ("local", LOCAL_PATH_POINTS)):
            rows, targets, src_of = (np.concatenate(a) for a in picked[kind])
            if len(targets):  # the batch's paths of one kind: walked and resampled on the solver's device
                paths, flags = solver.trace_resampled(rows, targets, m_pts)
                self.stale += int(np.sum(flags != 0))
                self.paths[kind].append(paths)
                self.src_of[kind].append(src_of)

    def arrays(self) -> tuple:
        """({kind: ((K, M, 3) float32 paths, (K,) source ids)}, paths dropped): a path with a non-finite point
        (one the solver flagged) is left out and counted."""
        dropped, out = 0, {}
        for kind, m_pts in (("global", GLOBAL_PATH_POINTS), ("local", LOCAL_PATH_POINTS)):
            p = np.concatenate(self.paths[kind]) if self.paths[kind] else np.zeros((0, m_pts, 3), np.float32)
            src_of = np.concatenate(self.src_of[kind]) if self.src_of[kind] else np.zeros(0, np.int64)
            ok = np.isfinite(p).all(axis=(1, 2))
            dropped += int(np.sum(~ok))
            out[kind] = (p[ok].astype(np.float32), src_of[ok])
        return out, dropped


def _paths(m: Mesh, st: DatasetSettings, plan: _Plan, path_src: np.ndarray, rng, batch, device, clock: _Clock,
           bar, found: _PathSet) -> tuple:
    """Phase 3 (where phase 2 did not trace them): ground-truth paths from ``path_src`` (near-Dijkstra order, so
    every traced polyline is as long as its distance) into ``found``, batch by batch while the time limit allows
    (at least one batch).

    Returns (solver iterations, path sources done).
    """
    iterations, done = [], 0
    if len(path_src):
        ps = GeodesicSolver(m, k=st.k, device=device, batch=batch, delta=PATH_DELTA, max_rows=len(path_src))
        for i in range(0, len(path_src), ps.batch):
            t_batch = time.perf_counter()
            src = path_src[i: i + ps.batch]
            ps.run(src)
            found.trace(ps, ps.vertex_distances(), src, plan, st, rng)
            bar.update(len(src))
            done += len(src)
            if clock.left() < time.perf_counter() - t_batch:  # the next batch would end past the limit
                break
        iterations = ps.timings["iterations"]
    return iterations, done


def trace_with_distances(device) -> bool:
    """Whether the distance pass traces the paths of its own runs (phase 2), instead of solving the path sources
    again in phase 3: on a GPU, where one in-process solver makes every distance row. On the CPU the rows may come
    from worker processes (``DistanceRows``), which return distances only; phase 3 keeps the dataset the same
    with any number of workers."""
    return not resolve_device(device).is_cpu


def build_dataset(mesh, out_path=None, settings: DatasetSettings | None = None, *, seed: int = 0, device=None,
                  progress: bool = True, time_limit_s: float | None = None, devices=None, **overrides) -> Dataset:
    """Compute the NeuroGF training data for one mesh with the Warp geodesic solver.

    Parameters
    ----------
    mesh : path, trimesh.Trimesh, (vertices, faces) or Mesh
    out_path : also save it there (``.npz``, atomic write); None keeps it in memory only
    settings : DatasetSettings (default: the GPU recipe's); ``**overrides`` replace single fields of it,
        e.g. ``n_sources=256``
    seed : random seed of every draw (sources, targets, surface points)
    device : Warp device of the solver (on the CPU, the distance sources are solved by ``settings.workers``
        processes, one per core by default; the result does not depend on how many: ``ground_truth/workers.py``)
    progress : a progress bar on stderr
    devices : GPUs that share the distance sources ("all", a list such as ["cuda:0", "cuda:1"], or None: the
        environment variable ``NEUROGF_DEVICES`` where set and ``device`` is a GPU, else ``device`` alone; checked
        as in ``geodesic_distances``): ``device`` (else the first of them) does the single-device work, and
        every GPU takes distance batches with a solver of the same settings (a batch's paths are traced on the
        GPU that solved it; the rows come back in order), so the dataset is the one ``device`` alone builds
        (under a time limit, with more sources)
    time_limit_s : seconds (from the start of the call) that the whole build may take: distance sources stop
        between solver batches when the next batch would end past it (on the CPU: in its last ``PATH_SHARE``, and
        the path sources stop between batches at the limit); at least one batch of each is solved. The dataset
        then has fewer than ``n_sources`` distance sources or fewer path sources, and its meta says
        ``"complete": False``. The test sources are always solved (first). None (default) solves them all.

    Notes
    -----
    A mesh too large for ``time_limit_s`` (``auto_proxy``, from the GPU's or the CPU's rates), or any mesh with
    ``proxy=N`` set, has its
    distance and path sources solved on a QSlim proxy of about N vertices (``dataset/proxy.py``); the held-out
    test sources are still solved on the mesh itself, on both, and the proxy is dropped (back to the mesh) when
    its distances from them are more than ``PROXY_MAX_MRE`` off. ``meta["proxy"]`` says what happened.

    Returns
    -------
    Dataset

    Phases (one function each): ``_sample`` (sources, targets' pools, surface points), ``_distances`` (test and
    distance sources with the solver, on every core; on a GPU also the paths, traced from the same runs),
    ``_paths`` (on the CPU: the path sources solved again and traced), ``_assemble``.
    """
    settings = dataclasses.replace(settings or DatasetSettings(), **overrides).validate()
    if time_limit_s is not None:
        number("time_limit_s", time_limit_s, minimum=0)
    from neurogf_warp.common.progress import Progress

    t_start = time.perf_counter()
    clock = _Clock(t_start, time_limit_s)
    m = load_mesh(mesh)
    check_trainable(m, allow_vertex_joins=True)  # the data is right on any mesh; training decides what it fits
    st = settings
    rng = np.random.default_rng(seed)
    timings = {}

    from neurogf_warp.ground_truth.devices import resolve_devices

    devs = resolve_devices(devices, device)
    if len(devs) > 1:
        device = str(devs[0])
        timings["devices"] = [str(d) for d in devs]
    batch = solver_batch(st.batch, device)
    _check_held_out_time(m, st, device, time_limit_s)
    n_proxy = st.proxy if st.proxy is not None else _auto_proxy(m, st, device, time_limit_s)
    g, fine_of, proxy_meta = m, None, None  # g: the mesh the training sources are solved on
    if n_proxy and 2 * n_proxy <= len(m.internal_vertices):
        t0 = time.perf_counter()
        g, where = proxy_mesh(m, n_proxy, device)
        fine_of = where.nearest_vertex
        timings["proxy_s"] = time.perf_counter() - t0
        proxy_meta = {"asked": int(n_proxy), "vertices": int(len(g.internal_vertices)),
                      "faces": int(len(g.internal_faces))}

    t0 = time.perf_counter()
    plan = _sample(g, st, rng, surface_mesh=m)
    timings["sampling_s"] = time.perf_counter() - t0
    test_src = proxy_test = plan.test_src
    if fine_of is not None:  # the held-out sources: fine vertices (one proxy vertex each), pinned on the proxy
        test_src, first = np.unique(fine_of[plan.test_src], return_index=True)
        proxy_test = plan.test_src[first]
        g = pin_vertices(g, where, proxy_test, m)

    def solver_for(mesh_):
        rows_cap = max(len(plan.gd_src), len(plan.test_src), 1)
        if batch is None and time_limit_s is not None:  # a GPU under a time limit: batches that fit inside it
            per = gpu_seconds_per_source(len(mesh_.internal_vertices))
            rows_cap = min(rows_cap, limited_batch(DISTANCE_BATCH_SHARE * time_limit_s, per))
        return GeodesicSolver(mesh_, k=st.k, device=device, batch=batch, max_rows=rows_cap)

    solver = solver_for(g)
    bar = Progress(len(plan.gd_src) + len(plan.test_src) + plan.n_path_sources, "ground truth", unit="source",
                   on=progress)
    t0 = time.perf_counter()
    test_dist, test_k = None, st.k
    if (st.k < DEFAULT_K or fine_of is not None) and len(test_src):
        # The held-out rows judge the model, and the heat method against it (training.quality): they come from the
        # solver at its default accuracy on the mesh itself, even when the training sources use a coarser solver
        # or a proxy. With k=1 rows (~0.2% MRE) a 120 s CPU bunny model scored 0.91% against the heat method's
        # 1.14% on them, but 1.01% against 0.95% on exact geodesics.
        exact = GeodesicSolver(m, k=DEFAULT_K, device=device, batch=batch, max_rows=len(test_src))
        test_dist, test_k = exact.solve(test_src), DEFAULT_K
        held_out = _near_source_rows(exact, test_src, test_dist)
        del exact
        bar.update(len(test_src))
        timings["test_rows_s"] = time.perf_counter() - t0
    if fine_of is not None:
        t1 = time.perf_counter()
        proxy_meta["error"] = proxy_error(solver.solve(proxy_test), test_dist, where) if len(test_src) else None
        timings["proxy_check_s"] = time.perf_counter() - t1
        err = (proxy_meta["error"] or {}).get("mre")
        proxy_meta["kept"] = err is not None and err <= PROXY_MAX_MRE
        if not proxy_meta["kept"]:  # too far from the mesh's own geodesics (or nothing to tell): the fine mesh
            del solver
            g, fine_of = m, None
            t1 = time.perf_counter()
            plan = _sample(m, st, rng, test_src=test_src)
            timings["sampling_s"] += time.perf_counter() - t1
            solver = solver_for(m)
    coarse = None
    if st.k < DEFAULT_K and test_k == DEFAULT_K:
        t1 = time.perf_counter()
        coarse = _coarse_correction(solver, test_src, test_dist, proxy_meta if fine_of is not None else None)
        timings["coarse_check_s"] = time.perf_counter() - t1
    found = _PathSet()
    here = trace_with_distances(device)
    given = test_dist is not None
    full = {} if st.full_rows and fine_of is None else None  # a proxy's rows are not the mesh's
    kept, rows, solved, test_dist, timings["worker_batches"], n_path_done = _distances(
        g, st, plan, rng, solver, clock, bar, test_dist, found if here else None, devs[1:], full)
    if not given:  # the rows came from the training solver, on the mesh itself at the default accuracy or finer
        held_out = _near_source_rows(solver, test_src, test_dist)
    if solved < len(plan.gd_src):  # the time limit cut the sources short
        bar.set_total(solved + len(plan.test_src) + min(plan.n_path_sources, solved))
    timings["distances_s"] = time.perf_counter() - t0  # with the paths traced in the pass, when ``here``
    if coarse is not None and coarse["scale"] != 1.0:
        for part in rows.values():
            for r in part:
                r[:, 6] *= np.float32(coarse["scale"])
        for r in (full or {}).get("rows", []):
            r *= np.float32(coarse["scale"])
    timings["distance_iterations"] = solver.timings["iterations"]
    timings["paths_traced_with_distances"] = here
    del solver

    t0 = time.perf_counter()
    gd_src = plan.gd_src[:solved]
    timings["path_iterations"] = []
    if not here:  # the CPU: the path sources solved again, in the CPU's batches
        path_src = gd_src[:min(plan.n_path_sources, len(gd_src))]
        timings["path_iterations"], n_path_done = _paths(g, st, plan, path_src, rng, batch, device, clock, bar,
                                                         found)
    out_paths, dropped = found.arrays()
    stale = found.stale
    if fine_of is not None:  # every id the dataset stores is the fine mesh's (rows and paths carry coordinates)
        kept, gd_src = fine_of[np.asarray(kept, np.int64)], fine_of[gd_src]
        out_paths = {k: (p, fine_of[src]) for k, (p, src) in out_paths.items()}
    plan.test_src = np.asarray(test_src, np.int64)
    bar.close()
    timings["paths_s"] = time.perf_counter() - t0
    timings["total_s"] = time.perf_counter() - t_start
    complete = solved == len(plan.gd_src) and n_path_done == plan.n_path_sources
    made = _Made(kept, rows, gd_src, n_path_done, out_paths, held_out, test_k, complete, stale, dropped, timings,
                 proxy_meta, coarse)
    ds = _assemble(m, st, seed, plan, made, time_limit_s)
    if full and full.get("ids"):
        ds.full_src = np.asarray(full["ids"], np.int64)
        ds.full_dist = np.stack(full["rows"])
        ds.check()
    if out_path is not None:
        ds.save(out_path)
    return ds


def _near_source_rows(solver: GeodesicSolver, sources: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """The held-out rows lowered near their sources, as ``evaluate``'s truth (``refine_near_sources``; the
    solver's short pairs are up to 1.4% too long, and a model trained on such rows looks better against them);
    ``rows`` stay as solved for the comparisons with the training solver."""
    from neurogf_warp.ground_truth.near_source import refine_near_sources

    return refine_near_sources(solver, sources, rows) if len(sources) else np.array(rows, np.float32)


# Rows of a coarser solver (k < DEFAULT_K) are longer than exact-grade ones by a near-constant factor: at k = 1
# the median pair is 0.11-0.23% too long on seven shared meshes (MRE 0.12-0.25%). The held-out sources, solved at
# both accuracies, measure it; the training distances are divided by (1 + the median bias), which halves their
# error (0.05-0.12% on the other half of the sources). Paths keep
# their points. A bias from fewer than COARSE_MIN_PAIRS pairs, or larger than COARSE_MAX_BIAS, is not applied.
COARSE_MIN_PAIRS = 1000
COARSE_MAX_BIAS = 0.02


def _coarse_correction(solver, test_src: np.ndarray, test_dist: np.ndarray, proxy_meta: dict | None) -> dict:
    """{"k", "pairs", "mre", "p99", "max", "bias", "scale"} of the training solver's rows against the held-out rows
    (``proxy.row_error``); on a kept proxy its check's numbers (the proxy's solver is the training one)."""
    if proxy_meta is not None:
        err = dict(proxy_meta.get("error") or {})
    else:
        err = row_error(solver.solve(test_src), test_dist)
    bias = err.get("bias")
    usable = bias is not None and err.get("pairs", 0) >= COARSE_MIN_PAIRS and abs(bias) <= COARSE_MAX_BIAS
    return {"k": int(solver.k), **err, "scale": float(1.0 / (1.0 + bias)) if usable else 1.0}


def _auto_proxy(m: Mesh, st: DatasetSettings, device, time_limit_s: float | None) -> int:
    """``auto_proxy`` for this build: none where the solver's batch is set by hand; on a GPU from the H100 table;
    on the CPU from the CPU tables at the build's k over its processes (a 134K-vertex mesh at 300 s had 8 training
    sources on its own mesh, 768 asked)."""
    if st.batch is not None:
        return 0
    if not resolve_device(device).is_cpu:
        return auto_proxy(len(m.internal_vertices), st.n_sources, time_limit_s)
    procs = min(MAX_WORKERS, cpu_cores() if st.workers is None else st.workers)
    return auto_proxy(len(m.internal_vertices), st.n_sources, time_limit_s,
                      rate=lambda v: cpu_seconds_per_source(v, st.k) / procs)


def _check_held_out_time(m: Mesh, st: DatasetSettings, device, time_limit_s: float | None) -> None:
    """InputError, before any solve, when the held-out sources alone are estimated far over ``time_limit_s``
    (HELD_OUT_MARGIN, HELD_OUT_SLACK_S; a 2.2M-vertex mesh on a 2-core CPU: ~13 minutes for 8 rows, against
    25-40 s of a 120 s training budget)."""
    if time_limit_s is None or st.n_test == 0:
        return
    cpu = resolve_device(device).is_cpu
    n = len(m.internal_vertices)
    est = st.n_test * seconds_per_source(n, CPU_S_PER_SOURCE if cpu else GPU_S_PER_SOURCE)
    if est <= time_limit_s + max(HELD_OUT_MARGIN * time_limit_s, HELD_OUT_SLACK_S):
        return
    from neurogf_warp.common.checks import InputError

    where = "one CPU process" if cpu else "a GPU"
    raise InputError(
        f"this time limit cannot be kept: the {st.n_test} held-out sources that judge the model need about "
        f"{est:.0f} s of ground truth on {where} for this {n:,}-vertex mesh, against {time_limit_s:.0f} s left for "
        f"all of the ground truth (a training call gives it a third of the budget, less what loading the mesh "
        f"took). Give at least ~{3 * est:.0f} s (budget_seconds / "
        f"--budget-seconds){', train on a GPU' if cpu else ''}, or decimate the mesh (e.g. with "
        "fast_simplification) to a size this budget can train")


def _assemble(m: Mesh, st: DatasetSettings, seed: int, plan: _Plan, made: _Made, time_limit_s) -> Dataset:
    """Phase 4: the Dataset and its meta (what was asked for, what was made, how long it took)."""
    kept, rows, gd_src, out_paths = made.kept, made.rows, made.gd_src, made.out_paths
    meta = {
        "format_version": FORMAT_VERSION, "fingerprint": m.fingerprint, "n_input_vertices": m.n_input, "seed": seed,
        # what was asked for (before capping to the mesh): a cached dataset is reused only for the same request
        "requested": st.recipe(seed),
        "settings": dict(dataclasses.asdict(st), n_sources=len(gd_src), n_path_sources=int(made.n_path_sources),
                         n_test=int(len(plan.test_src)), test_k=int(made.test_k), n_spread=int(len(plan.spread)),
                         local_ball_vertices=plan.nball, path_delta=PATH_DELTA),
        # how sources, targets and paths are drawn: this module's docstring (format FORMAT_VERSION)
        "definitions": f"neurogf_warp.dataset.build, dataset format {FORMAT_VERSION}",
        "complete": bool(made.complete), "time_limit_s": time_limit_s,
        "sources_without_targets": int(len(gd_src) - len(kept)), "stale_paths": made.stale,
        "dropped_paths": made.dropped,
        "components": int(m.n_components), "units": "normalized (unit sphere)",
        # the training sources' mesh when it was a proxy (dataset/proxy.py): its size, its measured error, kept
        "proxy": made.proxy_meta,
        # training rows from a coarser solver than the held-out rows: their measured bias and the scale applied
        "coarse_rows": made.coarse,
        "versions": {"warp": wp.config.version, "numpy": np.__version__},
        "timings": made.timings,
    }
    return Dataset(
        vertices=m.internal_normalized_vertices.astype(np.float32), faces=m.internal_faces.astype(np.int32),
        center=np.asarray(m.center, np.float64), scale=float(m.scale),
        surface_points=plan.surface, gd_src=np.asarray(kept, dtype=np.int64),
        gd_global=np.stack(rows["global"]), gd_local1=np.stack(rows["local1"]), gd_local2=np.stack(rows["local2"]),
        path_global=out_paths["global"][0], path_global_src=out_paths["global"][1],
        path_local=out_paths["local"][0], path_local_src=out_paths["local"][1],
        test_src=plan.test_src.astype(np.int64), test_dist=made.test_dist, meta=meta,
    ).check()
