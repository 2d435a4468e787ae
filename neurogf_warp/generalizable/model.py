"""The generalizable model and the object it returns once conditioned on a shape.

    import neurogf_warp.generalizable as gen
    model = gen.load("GenNeuroGF.pth")                  # the released network, or a file from gen.train
    cond = model.condition("bunny.obj")                   # or an (N, 3) point cloud in your units
    d = cond.distance(p, q)                               # (M, 3), (M, 3) -> (M,), your units
    row = cond.ssad(0)                                    # vertex 0 to every vertex (a cloud: every point)
    D = cond.distance_matrix([0, 5, 9])                   # (3, n_vertices)

Normalization (the network's frame, as the authors' data): the points are moved so that the centre of their
axis-aligned bounding box is at the origin and scaled so that the largest distance from it is 1. For a mesh the
frame is the mesh's (``ngf.load_mesh(...).center/.scale``: its used vertices' bounding-box centre, largest
vertex norm 1); for a cloud, the cloud's own. Distances come back in the input's units (divided by the scale).

Point sampling on a mesh: ``trimesh.sample.sample_surface(mesh, n_points, seed=seed)`` (area-weighted uniform
sampling, default seed 2024, n_points 2048), the sampler and seed of the authors' reference inputs, so
``condition(mesh)`` of a shared mesh reproduces ``reference/generalizable/<mesh>.npz``'s ``points``.
"""
from __future__ import annotations

import os

import numpy as np
import warp as wp

from neurogf_warp.common.checks import InputError, integer
from neurogf_warp.generalizable.encoder import WarpGenNet, check_precision, default_mode
from neurogf_warp.generalizable.network import GenNeuroGF, load_network

DEFAULT_POINTS = 2048
DEFAULT_SEED = 2024
# Conditioning compares every point with every other (the neighbour searches): its time grows as N^2 (2,048
# points 4.4 s, 16,384 points 236 s on a 2-core CPU). Larger clouds are refused (``max_points`` raises the limit).
MAX_POINTS = {"cpu": 8192, "cuda": 65536}
COLLINEAR = 1e-7  # second singular value / first of the centred cloud at most this: the points lie on a line
NOT_CONDITIONED = ("condition it first: model.condition(points) or ngf.load(path, mesh=...), then query the "
                   "returned object")


def _finite_points(x, name: str, allow_single: bool = False) -> tuple[np.ndarray, bool]:
    """x as an (M, 3) float64 array (and whether it was a single (3,) point); clear errors otherwise. The dtypes
    the per-mesh queries take (integers and floats; not booleans, complex numbers or objects)."""
    from neurogf_warp.inference.inputs import check_tensor

    check_tensor(x, name)  # meta and sparse tensors, as the per-mesh queries refuse them
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    elif isinstance(x, wp.array):
        x = x.numpy()
    try:
        raw = np.asarray(x)
    except (TypeError, ValueError):  # ragged rows
        raise InputError(f"{name} must be an array of 3-D points, got {type(x).__name__} with rows of different "
                         "lengths") from None
    if raw.dtype.kind not in "iuf":
        raise InputError(f"{name} must hold numeric coordinates (integers or floats), got dtype {raw.dtype}")
    a = raw.astype(np.float64)
    single = a.shape == (3,)
    if single and allow_single:
        a = a[None]
    if a.ndim != 2 or a.shape[1] != 3:
        want = "(M, 3) or (3,)" if allow_single else "(N, 3)"
        raise ValueError(f"{name} must have shape {want} (x, y, z per row), got shape {a.shape}")
    if not np.isfinite(a).all():
        bad = int(np.argwhere(~np.isfinite(a).all(axis=1))[0, 0])
        raise InputError(f"{name} holds a non-finite coordinate (NaN or inf), first at row {bad}; remove or fix "
                         f"those points")
    return a, single


def normalization(points: np.ndarray) -> tuple[np.ndarray, float]:
    """(center, scale) of the unit-sphere frame: bounding-box centre, 1 / largest distance from it.

    Computed on a (3, N) copy: numpy's reductions along the short axis of an (N, 3) array are ~10x slower (160 us
    vs 15 us for 2,048 points on a 2-core CPU). The same numbers as ``c = (min + max) / 2``,
    ``r = sqrt(((points - c) ** 2).sum(axis=1)).max()``: min and max are exact, the squares are summed in the
    same order (x + y) + z, and sqrt is monotonic, so the largest sqrt is the sqrt of the largest sum."""
    p = np.asarray(points)
    t = np.array(p.T, dtype=p.dtype if p.dtype.kind == "f" else np.float64, order="C")  # (3, N) rows: a copy
    c = (t.min(axis=1) + t.max(axis=1)) / 2
    t -= c[:, None]
    with np.errstate(over="ignore"):  # an overflowing cloud is refused below, by its (infinite) radius
        t *= t
    r2 = t[0] + t[1]
    r2 += t[2]
    r = float(np.sqrt(r2.max()))
    if not r > 0:
        raise ValueError("all points coincide: a shape needs points spread in space to be normalized")
    check_cloud_scale(c, r)
    return c, 1.0 / r


def check_cloud_scale(center, radius: float, what: str = "the point cloud") -> None:
    """The per-mesh model's size rule (``mesh.check_scale``): a cloud whose bounding radius is outside
    [MIN_RADIUS, MAX_RADIUS], or whose coordinates reach beyond MAX_COORDINATE (estimated as |center| + radius),
    would give distances of 0 or inf in float32; refused with an InputError."""
    from neurogf_warp.mesh.mesh import MAX_COORDINATE, MAX_RADIUS, MIN_RADIUS

    largest = float(np.abs(np.asarray(center, np.float64)).max()) + radius
    if not MIN_RADIUS <= radius <= MAX_RADIUS or not largest <= MAX_COORDINATE:
        raise InputError(f"{what} is outside the supported range: its bounding radius is {radius:.3g} units and its "
                         f"coordinates reach {largest:.3g}; shapes from {MIN_RADIUS:g} to {MAX_RADIUS:g} units, with "
                         f"coordinates up to {MAX_COORDINATE:g}, are supported (the float32 computations would give "
                         "distances of 0 or inf); rescale or move the points, and scale the results back")


def max_points_for(device) -> int:
    """The largest cloud :meth:`GeneralizableModel.condition` takes by default on ``device`` (``MAX_POINTS``)."""
    return MAX_POINTS["cpu" if wp.get_device(device).is_cpu else "cuda"]


def check_cloud_size(n: int, kk: int, limit: int, what: str = "the point cloud"):
    """Refuse a cloud of ``n`` points above ``limit`` (the N^2 cost of conditioning), naming the fix."""
    if n > limit:
        raise InputError(f"{what} has {n:,} points; conditioning costs grow as N^2 and {limit:,} is the limit here "
                         f"(2,048 points as in training take ~4 s on a 2-core CPU). Subsample it, e.g. "
                         f"points[np.random.default_rng(0).choice(len(points), 2048, replace=False)], or "
                         f"pass max_points={n} to condition() to wait for it")


def cloud_spread_refusal(n_distinct: int, singular: np.ndarray, kk: int, what: str = "the point cloud") -> str | None:
    """Why a cloud cannot condition the network (None: it can): fewer than ``kk`` distinct points (repeating points
    adds none), or points on one line (``singular``: the centred cloud's singular values, largest first)."""
    if n_distinct <= 1:
        return f"all points of {what} coincide: a shape needs at least {kk} distinct points spread over a surface"
    if n_distinct < kk:
        return (f"{what} has only {n_distinct} distinct points; conditioning needs at least {kk} (the neighbour "
                f"count), ideally ~2,048 spread over the surface as in training (repeated points do not count)")
    if not singular[0] > 0 or singular[1] <= COLLINEAR * singular[0]:
        return f"{what} lies on a line; conditioning needs points spread over a surface"
    return None


def check_cloud_spread(pts: np.ndarray, kk: int, what: str = "the point cloud"):
    """:func:`cloud_spread_refusal` of an (N, 3) float64 host cloud, raised as an InputError."""
    distinct = len(np.unique(pts, axis=0)) if len(pts) else 0
    c = pts - (pts.min(axis=0) + pts.max(axis=0)) / 2 if len(pts) else np.zeros((1, 3))
    why = cloud_spread_refusal(distinct, np.linalg.svd(c, compute_uv=False), kk, what)
    if why is not None:
        raise InputError(why)


class GeneralizableModel:
    """A generalizable NeuroGF network (released or trained); :meth:`condition` returns a :class:`Conditioned`.

    ``meta``: what a trained file says about its training (collection, steps, validation MRE); empty for the
    released network.

    Every query of a conditioned shape takes ``precision``: ``"fp32"`` (default; the float32 kernels on CUDA,
    float64 on the CPU: the released network's references within 1e-5) or ``"fp16"`` (the pair head on tensor
    cores: fp16 weights and activations, fp32 sums; on the CPU a slow emulation of the same code). fp16 against
    float64, measured: relative error of the distance, released network, 2,048-point clouds and 4,096 pairs near the
    surface (CPU emulation of the kernel): mean 3.7e-5, max 2.7e-4; 256-point clouds: mean 1.2-1.4e-4, max 1.4e-3.
    """

    def __init__(self, net: GenNeuroGF, meta: dict | None = None, path: str | None = None):
        self.net = net.double().eval()
        self.meta = dict(meta or {})
        self.path = path
        self._warp: dict = {}

    def __repr__(self):
        what = self.meta.get("trained_on", {}).get("folder") if self.meta else None
        return f"GeneralizableModel(path={self.path!r}, trained_on={what!r})"

    def warp_net(self, device=None, mode: str | None = None) -> WarpGenNet:
        """The Warp weights on ``device`` in ``mode`` (cached; it also keeps the encoder's CUDA graphs)."""
        from neurogf_warp.common.arrays import resolve_device

        dev = resolve_device(device)  # an unknown device named as the per-mesh queries name it
        mode = mode or default_mode(dev)
        key = (str(dev), mode)
        if key not in self._warp:
            self._warp[key] = WarpGenNet(self.net, dev, mode)
        return self._warp[key]

    @property
    def cloud_points(self) -> int:
        """Points per cloud the network was trained with (2,048 for the released one; a trained file's config)."""
        return int((self.meta.get("config") or {}).get("cloud_points", DEFAULT_POINTS))

    # ---- queries need a shape: say so, and how ---------------------------------------------------------------
    @property
    def _states(self):
        # reached when a per-mesh query (ngf.path, ngf.sdf, ...) is given this model
        raise InputError(f"this is a generalizable NeuroGF network, not conditioned on a shape: {NOT_CONDITIONED}")

    @property
    def mesh(self):
        # per-mesh code asks a model for its mesh first (ngf.path, the command line's vertex queries)
        raise InputError(f"this is a generalizable NeuroGF network, not conditioned on a shape: {NOT_CONDITIONED}; "
                         f"on the command line pass --mesh MESHFILE")

    def _not_conditioned(self, name: str):
        raise InputError(f"{name}() needs a shape: this generalizable network is not conditioned yet; "
                         f"{NOT_CONDITIONED} (e.g. model.condition(points).{name}(...))")

    def distance(self, *args, **kwargs):
        """Refused: a generalizable network answers once conditioned on a shape (:meth:`condition`)."""
        self._not_conditioned("distance")

    def ssad(self, *args, **kwargs):
        """Refused: a generalizable network answers once conditioned on a shape (:meth:`condition`)."""
        self._not_conditioned("ssad")

    def msad(self, *args, **kwargs):
        """Refused: a generalizable network answers once conditioned on a shape (:meth:`condition`)."""
        self._not_conditioned("msad")

    def distance_matrix(self, *args, **kwargs):
        """Refused: a generalizable network answers once conditioned on a shape (:meth:`condition`)."""
        self._not_conditioned("distance_matrix")

    def condition(self, shape, n_points: int | None = None, seed: int = DEFAULT_SEED, device=None,
                  mode: str | None = None, max_points: int | None = None) -> Conditioned:
        """Encode a shape once; the result answers distance queries on it.

        shape: an (N, 3) point cloud in your units (at least 40 distinct points, not all on one line; the
        released network was trained on 2,048-point clouds), or a mesh (path, ``ngf.Mesh``, trimesh, (V, F) pair): ``n_points`` points (default: as many as
        the network was trained with, :attr:`cloud_points`) are sampled on it with ``seed`` (see the module
        docstring), and results are per mesh vertex with +inf across connected
        components. device: "cpu" / "cuda:N" (default: Warp's). mode: "fp64" / "fp32" / "mixed" (default
        fp64 on the CPU, fp32 on CUDA). On CUDA (fp32) the encoder replays a CUDA graph captured on the first
        cloud of each size (``NGF_NO_GRAPH=1`` or ``model.warp_net(device).use_graph = False``: launches from
        Python, same numbers); every conditioned shape holds arrays of its own. max_points: the largest cloud
        (or ``n_points``) taken (default ``MAX_POINTS``: 8,192 on the CPU, 65,536 on CUDA), since conditioning
        time grows as N^2; larger ones are refused with an InputError.

        A cloud already on the GPU (a CUDA torch tensor, or a CUDA ``wp.array`` of shape (N, 3), on the device
        conditioned on) stays there: the checks and the normalization run on the device (the same numbers as for
        the same points from numpy) and only (center, scale) come back to the host; ``points`` is fetched on first
        use. The tensor's stream is waited for, and it waits for the copy, so it may be changed right after the
        call. Anything else (numpy, lists, CPU tensors, another device's tensors) goes through the host. This
        path saves the download, not time: on an H100 it took 1.48 ms for a 2,048-point cloud against 1.08 ms from
        numpy (its checks and frame are small separate launches and a synchronization).
        """
        mesh = None
        if isinstance(shape, (str, os.PathLike)) or hasattr(shape, "faces") or (
                isinstance(shape, (tuple, list)) and len(shape) == 2 and np.ndim(shape[1]) == 2):
            mesh = _load_mesh(shape)
        wn = self.warp_net(device, mode)
        limit = max_points_for(wn.device) if max_points is None else integer("max_points", max_points, minimum=1)
        if mesh is None:
            on_dev = _device_cloud(shape, wn)
            if on_dev is not None:
                check_cloud_size(on_dev[0].shape[0], wn.kk, limit)
                return _condition_on_device(self, wn, *on_dev)
            pts, _ = _finite_points(shape, "points")
            if len(pts) < wn.kk:
                raise InputError(f"the point cloud has {len(pts)} points; conditioning needs at least "
                                 f"{wn.kk} (the neighbour count), ideally ~2,048 as in training")
            check_cloud_size(len(pts), wn.kk, limit)
            check_cloud_spread(pts, wn.kk)
            center, scale = normalization(pts)
            return Conditioned(self, wn, pts, center, scale, None, None)
        n_points = self.cloud_points if n_points is None else integer("n_points", n_points, minimum=1)
        if n_points < wn.kk:
            raise InputError(f"n_points={n_points} is too small; use at least {wn.kk} (2,048 as in training)")
        check_cloud_size(n_points, wn.kk, limit, what=f"n_points={n_points}: the sampled cloud")
        pts, _ = sample_surface(mesh, n_points, integer("seed", seed, minimum=0))
        check_cloud_spread(pts, wn.kk, what="the cloud sampled on the mesh")
        fcomp = mesh.internal_components[mesh.internal_faces[:, 0]].astype(np.int32)
        return Conditioned(self, wn, pts, np.asarray(mesh.center, np.float64), float(mesh.scale), mesh, fcomp)


def _device_cloud(x, wn: WarpGenNet):
    """(torch tensor, from torch?) when x is an (N >= k, 3) real-valued CUDA torch tensor or CUDA wp.array on wn's
    device, else None (the host path: also for every input that is refused, so its errors stay those of the host
    path)."""
    dev = wn.device
    if not dev.is_cuda:
        return None
    if isinstance(x, wp.array):
        if x.device != dev or x.ndim > 2 or x.dtype not in (wp.float32, wp.float64, wp.vec3, wp.vec3d):
            return None
        t, from_torch = wp.to_torch(x), False  # vec3 arrays come as (N, 3)
    elif type(x).__module__.partition(".")[0] == "torch" and getattr(x, "is_cuda", False):
        if x.device.index != dev.ordinal:
            return None
        t, from_torch = x.detach(), True
    else:
        return None
    if t.ndim != 2 or t.shape[1] != 3 or t.shape[0] < wn.kk or t.is_complex() or str(t.dtype) == "torch.bool":
        return None
    return t, from_torch


def _frame_stats(x64):
    """(cx, cy, cz, largest squared distance from c) of a float64 (N, 3) torch tensor on any device, with
    :func:`normalization`'s arithmetic (the same bits): min and max exact, c = (min + max) / 2, squares summed
    (x + y) + z, one operation per kernel (no contraction). Non-finite in c where a coordinate is NaN or inf (NaN
    propagates through min and max; an inf makes one of them infinite)."""
    import torch

    mn, mx = torch.aminmax(x64, dim=0)
    c = (mn + mx) / 2
    d = x64 - c
    d = d * d
    r2 = d[:, 0] + d[:, 1]
    r2 = r2 + d[:, 2]
    return torch.cat([c, r2.max().reshape(1)])


_TORCH_STREAMS: dict = {}  # Warp stream handle -> its torch.cuda.ExternalStream


def _condition_on_device(model, wn: WarpGenNet, t, from_torch: bool) -> Conditioned:
    """condition() of a cloud on wn's CUDA device: the checks and (center, scale) computed there with the host
    path's arithmetic (min and max exact, (min + max) / 2, squares summed (x + y) + z, largest sum; sqrt and the
    reciprocal on the host), so the same numbers; one synchronization (the frame's 4 values). The torch work runs on
    Warp's stream, which first waits for the tensor's stream; that stream then waits for Warp's (the copy)."""
    import torch

    ws = wn.device.stream
    ts = _TORCH_STREAMS.get(ws.cuda_stream)
    if ts is None:
        ts = _TORCH_STREAMS[ws.cuda_stream] = wp.stream_to_torch(ws)
    cur = torch.cuda.current_stream(t.device) if from_torch else None
    if cur is not None and cur.cuda_stream != ts.cuda_stream:
        ts.wait_stream(cur)  # the tensor's producers first
    with torch.cuda.stream(ts):
        x64 = t.to(torch.float64, copy=True)  # a snapshot: ``points`` as the host path would keep it
        store = x64 if wn.np_dtype == np.float64 else (t if t.dtype == torch.float32 else x64.to(torch.float32))
        store = store.contiguous()
        stats = _frame_stats(x64).cpu().numpy()  # waits for all of the above
        if not np.isfinite(stats[:3]).all():
            bad = (~torch.isfinite(x64).all(dim=1)).nonzero()
            if bad.numel():
                raise InputError(f"points holds a non-finite coordinate (NaN or inf), first at row {int(bad[0, 0])}; "
                                 f"remove or fix those points")
    r = float(np.sqrt(stats[3]))
    if not r > 0:  # the host path's refusal, word for word
        raise InputError(cloud_spread_refusal(1, np.zeros(3), wn.kk))
    check_cloud_scale(stats[:3], r)
    with torch.cuda.stream(ts):  # distinct points and the spread, as check_cloud_spread on the host
        d = x64 - torch.from_numpy(stats[:3].copy()).to(x64.device)
        sv = torch.linalg.svdvals(d).cpu().numpy()
        why = cloud_spread_refusal(int(torch.unique(x64, dim=0).shape[0]), sv, wn.kk)
    if why is not None:
        raise InputError(why)
    cloud = wp.from_torch(store, dtype=wn.k.dtype)
    cond = Conditioned(model, wn, x64, stats[:3].copy(), 1.0 / r, None, None, cloud=cloud)
    if cur is not None and cur.cuda_stream != ts.cuda_stream:
        cur.wait_stream(ts)  # the tensor may change (or its memory be reused) only after Warp's copy of it
    return cond


def _load_mesh(shape):
    import neurogf_warp as ngf

    return ngf.load_mesh(shape)


def sample_surface(mesh, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """n points on the mesh surface (area-weighted, trimesh's sampler, ``seed``) -> (points (n, 3), face (n,))."""
    import trimesh

    tm = trimesh.Trimesh(np.asarray(mesh.internal_vertices, np.float64), np.asarray(mesh.internal_faces), process=False)
    pts, face = trimesh.sample.sample_surface(tm, n, seed=seed)
    return np.asarray(pts, np.float64), np.asarray(face, np.int64)


def _host_array(x, name: str) -> np.ndarray:
    """``x`` (a list, numpy array or tensor) as a numpy array; meta tensors and ragged lists refused naming it."""
    from neurogf_warp.inference.inputs import check_tensor

    check_tensor(x, name)
    try:
        return np.asarray(x.detach().cpu().numpy() if hasattr(x, "detach") else x)
    except ValueError:
        raise InputError(f"{name} has rows of different lengths: give integer indices (one, or a 1-D list) or "
                         "(M, 3) points") from None


def _no_2d_integers(a: np.ndarray, name: str) -> None:
    """The per-mesh rule: indices are one integer or 1-D, points are floats; a 2-D integer array is not guessed at."""
    if a.dtype.kind in "iu" and a.ndim >= 2:
        raise InputError(f"{name} is an integer array of shape {a.shape}: vertex or point indices are one integer or "
                         "a 1-D list; points are floats of shape (M, 3) (e.g. np.asarray(x, dtype=float))")


class Conditioned:
    """A generalizable model conditioned on one shape: queries in the shape's own units.

    Attributes: ``points`` (N, 3) the cloud in user units; ``center``, ``scale`` (unit frame =
    (x - center) * scale); ``mesh`` (an ``ngf.Mesh`` or None). Distances are float32 numpy arrays in user units,
    symmetric in (p, q) up to rounding, exactly 0 for p == q, never negative (the ratio is floored at 1: a
    geodesic is never shorter than the straight segment), +inf between points on different connected
    components of the mesh (a point takes the component of the mesh triangle closest to it).
    """

    def __init__(self, model, wn: WarpGenNet, points, center, scale, mesh, face_comp, cloud=None):
        """points: (N, 3) float64 numpy, or a float64 torch tensor on the device (fetched on first use of
        ``points``); cloud: the points on the device in the encoder's storage dtype (then encoded from there)."""
        self.model, self.wn, self.device = model, wn, wn.device
        self._user_points = points
        self.center = np.asarray(center, np.float64)
        self.scale = float(scale)
        self.mesh = mesh
        self.enc = wn.encode(points if cloud is None else cloud, self.center, self.scale)
        self._wpmesh = None
        self._multi = mesh is not None and mesh.n_components > 1
        if self._multi:
            v = ((np.asarray(mesh.internal_vertices) - self.center) * self.scale).astype(np.float32)
            self._wpmesh = wp.Mesh(wp.array(v, dtype=wp.vec3, device=self.device),
                                   wp.array(np.asarray(mesh.internal_faces, np.int32).ravel(), dtype=wp.int32,
                                            device=self.device))
            self._face_comp = wp.array(face_comp, dtype=wp.int32, device=self.device)
        self._targets = None

    @property
    def _states(self):
        # reached when a per-mesh query without a generalizable counterpart (ngf.sdf, ngf.path, ...) is given this
        raise InputError("a conditioned generalizable model answers distance, ssad, msad and distance_matrix (its "
                         "methods, or ngf.distance(...) etc.); it has no SDF or path head: for sdf, path and "
                         "project train a per-mesh model (ngf.train)")

    @property
    def points(self) -> np.ndarray:
        """The cloud (N, 3) float64 in user units (a cloud given on the GPU is copied to the host here, once)."""
        if not isinstance(self._user_points, np.ndarray):
            self._user_points = self._user_points.cpu().numpy()
        return self._user_points

    @property
    def frame(self):
        return (*self.center.tolist(), self.scale)

    # ---- inputs --------------------------------------------------------------------------------------------
    def _points(self, x, name, single_ok=True, allow_index=True):
        """(user-unit points (M, 3) float64, components (M,) or None, single?) from indices or points."""
        from neurogf_warp.inference.inputs import check_tensor

        check_tensor(x, name)
        arr = x.detach().cpu().numpy() if hasattr(x, "detach") else x
        try:
            a = np.asarray(arr)
        except ValueError:  # ragged: indices mixed with points, rows of different lengths
            raise InputError(f"{name} has rows of different lengths: give integer indices (one, or a 1-D list) or "
                             "(M, 3) points") from None
        if a.dtype.kind == "b":
            raise InputError(f"{name} must be integer indices or float points, got booleans")
        if allow_index:
            _no_2d_integers(a, name)
        if allow_index and a.dtype.kind in "iu":  # indices
            single = a.ndim == 0
            idx = a.reshape(-1).astype(np.int64)
            if self.mesh is not None:
                j = self.mesh.vertex(idx)  # input numbering -> internal (clear IndexError otherwise)
                comp = self.mesh.internal_components[j].astype(np.int32) if self._multi else None
                return self.mesh.internal_vertices[j], comp, single
            if idx.size and (idx.min() < 0 or idx.max() >= len(self.points)):
                raise IndexError(f"{name}: point index out of range 0 .. {len(self.points) - 1}")
            return self.points[idx], None, single
        if allow_index and a.dtype.kind == "f" and a.ndim <= 1 and a.shape != (3,):
            raise ValueError(f"{name}: give integer indices or (M, 3) points, got a float array of shape {a.shape}")
        pts, single = _finite_points(arr, name, allow_single=single_ok)
        from neurogf_warp.inference.inputs import check_points_in_frame

        check_points_in_frame(pts, self.center, self.scale, name, "mesh" if self.mesh is not None else "cloud")
        comp = self._components_of(pts) if self._multi else None
        return pts, comp, single

    def _components_of(self, pts):
        X = self._dev(pts)
        out = wp.empty(len(pts), dtype=wp.int32, device=self.device)
        if len(pts):
            wp.launch(self.wn.k.point_component, len(pts),
                      inputs=[self._wpmesh.id, X, *self.frame, self._face_comp, out], device=self.device)
        return out.numpy()

    def _dev(self, pts):
        return wp.array(np.ascontiguousarray(pts, dtype=self.wn.np_dtype), dtype=self.wn.k.dtype, device=self.device)

    def _target_set(self):
        """Every mesh vertex (internal numbering) or every cloud point, on the device, with nearest cloud points
        and components precomputed once (reused by every ssad/msad/distance_matrix call)."""
        if self._targets is None:
            if self.mesh is not None:
                pts = np.asarray(self.mesh.internal_vertices, np.float64)
                comp = self.mesh.internal_components.astype(np.int32) if self._multi else None
            else:
                pts, comp = self.points, None
            T = self._dev(pts)
            unit = wp.empty((len(pts), 3), dtype=self.wn.k.dtype, device=self.device)
            v = wp.empty(len(pts), dtype=wp.vec3, device=self.device)
            wp.launch(self.wn.k.to_unit, len(pts), inputs=[T, *self.frame, unit, v], device=self.device)
            nn = self.wn.nearest(self.enc, unit)
            c = wp.array(comp, dtype=wp.int32, device=self.device) if comp is not None else None
            self._targets = (T, nn, c)
        return self._targets

    def _out(self, values: np.ndarray) -> np.ndarray:
        """Per-target values in the input numbering (mesh: NaN for vertices no face uses)."""
        return self.mesh.to_input(values) if self.mesh is not None else values

    # ---- queries -------------------------------------------------------------------------------------------
    def distance(self, p, q, precision: str = "fp32"):
        """Geodesic distance of each pair: p, q (M, 3) points -> (M,) float32; (3,), (3,) -> a float.

        p and q are coordinates of any real dtype, as in the per-mesh ``ngf.distance`` (integers are never read as
        point indices here: ``ssad``, ``msad`` and ``distance_matrix`` take indices). precision: "fp32" or "fp16"
        (tensor cores; see :class:`GeneralizableModel`)."""
        check_precision(precision)
        P, pc, sp = self._points(p, "p", allow_index=False)
        Q, qc, sq = self._points(q, "q", allow_index=False)
        if len(P) != len(Q):
            raise ValueError(f"p and q must hold the same number of points, got {len(P)} and {len(Q)}")
        out = self.wn.distances(self.enc, self._dev(P), self._dev(Q), self.center, self.scale, False,
                                s_comp=None if pc is None else wp.array(pc, dtype=wp.int32, device=self.device),
                                t_comp=None if qc is None else wp.array(qc, dtype=wp.int32, device=self.device),
                                precision=precision)
        r = out.numpy()
        return float(r[0]) if (sp and sq) else r

    def distance_matrix(self, sources, targets=None, precision: str = "fp32"):
        """(S, n) distances from each source to every target: every mesh vertex (input numbering, NaN columns
        for unused vertices) or every cloud point when ``targets`` is None, else (S, T) to the given targets.
        sources/targets: integer indices (mesh vertices in the input numbering, or cloud points) or points.
        precision: "fp32" or "fp16" (tensor cores; see :class:`GeneralizableModel`)."""
        check_precision(precision)
        S, sc, _ = self._points(sources, "sources")
        if len(S) == 0:
            raise ValueError("sources is empty: give at least one source")
        dev = self.device
        s_comp = None if sc is None else wp.array(sc, dtype=wp.int32, device=dev)
        if targets is None:
            T, t_nn, t_comp = self._target_set()
            if s_comp is None and t_comp is not None:  # points given for a multi-component mesh
                s_comp = wp.array(self._components_of(S), dtype=wp.int32, device=dev)
            out = self.wn.distances(self.enc, self._dev(S), T, self.center, self.scale, True, t_nn=t_nn,
                                    s_comp=s_comp, t_comp=t_comp, precision=precision)
            return self._out(out.numpy().reshape(len(S), T.shape[0]))
        Tp, tc, _ = self._points(targets, "targets")
        out = self.wn.distances(self.enc, self._dev(S), self._dev(Tp), self.center, self.scale, True,
                                s_comp=s_comp, t_comp=None if tc is None else wp.array(tc, dtype=wp.int32, device=dev),
                                precision=precision)
        return out.numpy().reshape(len(S), len(Tp))

    def ssad(self, source, precision: str = "fp32"):
        """Single source, all destinations: one index or one (3,) point -> (n,) float32 (see distance_matrix)."""
        check_precision(precision)
        a = _host_array(source, "source")
        if not (a.ndim == 0 or (a.shape == (3,) and a.dtype.kind == "f")):
            raise ValueError(f"ssad takes one source (an integer index or a (3,) float point), got {a.dtype} "
                             f"shape {a.shape}; "
                             f"use msad or distance_matrix for several")
        return self.distance_matrix(a.reshape(1, 3) if a.ndim == 1 else a.reshape(1), precision=precision)[0]

    def msad(self, sources, chunk: int = 64, precision: str = "fp32"):
        """Multiple sources, all destinations: the distance from every target to its nearest source -> (n,)."""
        check_precision(precision)
        chunk = integer("chunk", chunk, minimum=1)
        a = _host_array(sources, "sources")
        if a.size == 0:
            raise ValueError("sources is empty: give at least one source")
        if a.dtype.kind not in "iuf":
            raise ValueError(f"sources must be integer indices or (S, 3) float points, got dtype {a.dtype}")
        _no_2d_integers(a, "sources")
        a = a.reshape(-1, 3) if a.dtype.kind == "f" else a.reshape(-1)
        best = None
        for i in range(0, len(a), chunk):
            m = self.distance_matrix(a[i:i + chunk], precision=precision).min(axis=0)
            best = m if best is None else np.fmin(best, m)
        return best


def load(path) -> GeneralizableModel:
    """Load the released ``GenNeuroGF.pth`` (a plain state_dict) or a file written by ``generalizable.train``
    (the state_dict plus what it was trained on, kept in ``model.meta``). Raises ValueError for a missing file or
    one that does not hold this network."""
    import torch

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise ValueError(f"no such file: {path!r}; pass the path of GenNeuroGF.pth or a trained model file")
    obj = torch.load(path, map_location="cpu", weights_only=True)
    meta = {}
    if isinstance(obj, dict) and isinstance(obj.get("state_dict"), dict):
        meta = {k: v for k, v in obj.items() if k not in ("state_dict", "optimizer")}
        obj = obj["state_dict"]
    if not isinstance(obj, dict):
        raise ValueError(f"{path!r} does not hold a state_dict (found {type(obj).__name__})")
    return GeneralizableModel(load_network(obj), meta, path)
