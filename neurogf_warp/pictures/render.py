"""Pictures of distance fields and paths on a mesh, ray cast in Warp (headless, CPU or GPU), and coloured meshes.

    ngf.render(model, sources=[0], out="ssad.png")                 # NeuroGF SSAD from vertex 0, 20 isolines
    ngf.render(model, sources=[0, 9, 40, 77, 120], out="msad.png")  # MSAD
    ngf.render(mesh, values=d, paths=P, out="paths.png")          # any per-vertex field, polylines as tubes
    ngf.write_ply("field.ply", mesh, d)                            # vertex colours for MeshLab / Blender

The image is ray cast against one ``wp.Mesh`` holding the surface plus the overlays (path tubes, marker
spheres), shaded by ``kernels/raycast.py``, supersampled and box-filtered down. The colour map
(``COLOR_STOPS``: dark indigo at 0 through blue, teal, green and amber to cream at the top of the range) is
this package's own.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, fields

import numpy as np
import warp as wp

from neurogf_warp.common.arrays import resolve_device
from neurogf_warp.common.checks import InputError, integer, number
from neurogf_warp.common.files import atomic_write
from neurogf_warp.kernels.pictures import raycast
from neurogf_warp.mesh.surface import as_mesh, as_numpy, points_of

__all__ = ["render", "write_ply", "colorize", "View", "Style", "choose_up", "COLOR_STOPS", "UP_CHOICES"]

# equally spaced colours from the low end (a source: distance 0) to the high end of the value range
COLOR_STOPS = np.array([
    [0.10, 0.09, 0.30],  # indigo
    [0.12, 0.30, 0.60],  # blue
    [0.12, 0.55, 0.62],  # teal
    [0.42, 0.73, 0.43],  # green
    [0.92, 0.78, 0.33],  # amber
    [0.99, 0.95, 0.84],  # cream
])
SOURCE_COLOR = (1.00, 0.80, 0.08)  # gold spheres at the sources
POINT_COLOR = (0.96, 0.96, 0.96)  # white spheres at other marked points
TARGET_COLOR = (0.10, 0.10, 0.12)  # dark spheres at the ends of paths
PATH_COLORS = ((0.86, 0.08, 0.20), (0.98, 0.45, 0.05), (0.80, 0.15, 0.75))  # crimson, orange, magenta: cycled
BACKGROUND = (1.0, 1.0, 1.0)


@dataclass
class View:
    """Where the camera looks from. The default: the bounding box's centre seen from azimuth 30 degrees,
    elevation 20 degrees, everything drawn (the mesh, markers and paths) inside a 30-degree vertical field of
    view with a margin, the up axis chosen automatically (``up="auto"``, see ``choose_up``). ``render`` with
    sources and no view looks at the first source instead (``View.toward`` it).

    azimuth : degrees around the up axis; 0 looks from the +front axis (the axis after ``up`` in x, y, z
        order: +z for up y, +x for up z, +y for up x), 90 from the +right axis (up x front)
    elevation : degrees above the plane normal to ``up``
    up : "auto", or the mesh axis drawn upward: "x", "y", "z", "-x", "-y", "-z"
    fov : vertical field of view, degrees
    zoom : > 1 moves the camera closer
    center : the point looked at, mesh units (default: the bounding box's centre)
    """

    azimuth: float = 30.0
    elevation: float = 20.0
    up: str = "auto"
    fov: float = 30.0
    zoom: float = 1.0
    center: tuple | None = None

    @classmethod
    def toward(cls, direction, up: str = "y", vertices=None, max_elevation: float = 90.0, **kw) -> "View":
        """The view from the bounding box's centre out along ``direction`` (a 3-vector, mesh axes), e.g. a
        point's offset from the centre, to look at that side of the mesh. ``up="auto"`` needs ``vertices``
        ((V, 3), to choose it); the elevation is clipped to +-``max_elevation`` degrees."""
        d = np.asarray(direction, dtype=np.float64).reshape(3)
        if not np.linalg.norm(d) > 0:
            raise InputError(f"direction must be a non-zero 3-vector, got {direction!r}")
        if str(up).strip().lower() == "auto":
            if vertices is None:
                raise InputError('View.toward(..., up="auto") needs the mesh vertices (vertices=...) to choose the up axis')
            up = choose_up(vertices)
        u, front, right = _axes(up)
        d = d / np.linalg.norm(d)
        az = math.degrees(math.atan2(d @ right, d @ front))
        el = math.degrees(math.asin(np.clip(d @ u, -1.0, 1.0)))
        el = float(np.clip(el, -max_elevation, max_elevation))
        return cls(azimuth=az, elevation=el, up=up, **kw)

    @classmethod
    def of(cls, view) -> "View":
        """A View from None (the default), a View, a dict of its fields or an (azimuth, elevation) pair."""
        if view is None:
            return cls()
        if isinstance(view, cls):
            return view
        if isinstance(view, dict):
            known = {f.name for f in fields(cls)}
            bad = set(view) - known
            if bad:
                raise InputError(f"view: unknown keys {sorted(bad)}; known: {sorted(known)}")
            return cls(**view)
        if isinstance(view, (tuple, list)) and len(view) == 2:
            return cls(azimuth=float(view[0]), elevation=float(view[1]))
        raise TypeError(f"view must be None, a View, a dict or (azimuth, elevation) in degrees, got {view!r}")


_AXES = {"x": 0, "y": 1, "z": 2}
UP_CHOICES = ("auto", "x", "y", "z", "-x", "-y", "-z")
# up="auto" turns to +z when the mesh is this many times taller along z than along y
Z_UP_RATIO = 1.2
# room left around everything drawn: the bounding sphere is enlarged by this fraction
FRAME_MARGIN = 0.06
# the default view of a source looks at it from at most this far above or below
SOURCE_VIEW_MAX_ELEVATION = 60.0
# several sources are faced when the mean of their unit directions from the centre is at least this long
SOURCES_ON_ONE_SIDE = 0.35


def choose_up(vertices) -> str:
    """The up axis for ``up="auto"``: "z" when the mesh's extent along z is at least ``Z_UP_RATIO`` times its
    extent along y (a z-up scan or CAD part standing upright), else "y" (the OBJ/glTF convention). Extents
    cannot tell every convention apart (a y-up car that is long along z comes out on its nose): pass ``up``
    (``--up``) when the guess is wrong."""
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    ext = v.max(0) - v.min(0)
    return "z" if ext[2] >= Z_UP_RATIO * ext[1] else "y"


def source_side(sources: np.ndarray, vertices: np.ndarray):
    """The direction, from the bounding box's centre, that the default view of ``sources`` ((S, 3), mesh units)
    looks along: toward the one source; for several, the mean of their unit directions, when they lie mostly on
    one side (its length at least ``SOURCES_ON_ONE_SIDE``). None: no side to face (sources all around, or one at
    the centre), and the default ``View`` is used."""
    c = (vertices.min(0) + vertices.max(0)) / 2
    d = np.asarray(sources, dtype=np.float64).reshape(-1, 3) - c
    n = np.linalg.norm(d, axis=1)
    scale = float(np.linalg.norm(vertices - c, axis=1).max())
    d, n = d[n > 1e-9 * scale], n[n > 1e-9 * scale]
    if not len(d):
        return None
    mean = (d / n[:, None]).mean(0)
    return mean if np.linalg.norm(mean) >= (SOURCES_ON_ONE_SIDE if len(d) > 1 else 0.0) else None


def _axes(up: str):
    """(up, front, right) unit vectors for an up-axis name."""
    u = str(up).strip().lower()
    if u.lstrip("+-") not in _AXES or len(u.lstrip("+-")) != 1:
        raise InputError(f"view.up must be one of auto, x, y, z, -x, -y, -z; got {up!r}")
    i = _AXES[u.lstrip("+-")]
    a, front = np.zeros(3), np.zeros(3)
    a[i], front[(i + 1) % 3] = (-1.0 if u.startswith("-") else 1.0), 1.0
    return a, front, np.cross(a, front)


def _camera(vertices: np.ndarray, view: View, width: int, height: int, extent: np.ndarray | None = None
            ) -> raycast.Camera:
    """The camera of ``view``: it looks at the centre of ``vertices``' bounding box (or ``view.center``) from far
    enough that the sphere around that centre holding ``extent`` (every point drawn, default ``vertices``),
    enlarged by ``FRAME_MARGIN``, fits in both the vertical and the horizontal field of view."""
    up, front, right = _axes(choose_up(vertices) if str(view.up).strip().lower() == "auto" else view.up)
    for name in ("azimuth", "elevation", "fov", "zoom"):  # a NaN camera draws an empty picture
        number(f"view.{name}", getattr(view, name))
    if not (0.0 < view.fov < 179.0) or not view.zoom > 0:
        raise InputError(f"view.fov must lie in (0, 179) degrees and view.zoom be > 0, got {view.fov}, {view.zoom}")
    lo, hi = vertices.min(0), vertices.max(0)
    center = (lo + hi) / 2 if view.center is None else np.asarray(view.center, dtype=np.float64).reshape(3)
    if not np.isfinite(center).all():
        raise InputError(f"view.center must be a finite point, got {view.center!r}")
    pts = vertices if extent is None else extent
    radius = max(float(np.linalg.norm(pts - center, axis=1).max()), 1e-12) * (1.0 + FRAME_MARGIN)
    az, el = math.radians(view.azimuth), math.radians(view.elevation)
    back = math.cos(el) * (math.sin(az) * right + math.cos(az) * front) + math.sin(el) * up  # center -> eye
    half = math.tan(math.radians(view.fov) / 2)
    # a sphere of radius r seen from distance d fills a cone of half-angle asin(r / d): that cone must fit in the
    # narrower of the two half-angles of the picture
    narrow = min(half, half * width / height)
    dist = radius / math.sin(math.atan(narrow)) / view.zoom
    fwd = -back
    r = np.cross(fwd, up)
    if np.linalg.norm(r) < 1e-9:  # looking straight along the up axis: the limit of a slightly lower elevation
        r = np.cross(up, math.sin(az) * right + math.cos(az) * front)
    r /= np.linalg.norm(r)
    v = np.cross(r, fwd)
    light = back * 0.8 + 0.45 * v - 0.35 * r  # from above and left of the camera
    cam = raycast.Camera()
    cam.eye = wp.vec3(*(center + dist * back))
    cam.forward = wp.vec3(*fwd)
    cam.right = wp.vec3(*(r * half * width / height))
    cam.up = wp.vec3(*(v * half))
    cam.light = wp.vec3(*(light / np.linalg.norm(light)))
    cam.width, cam.height = int(width), int(height)
    return cam


def _vertex_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])  # area-weighted
    n = np.zeros_like(V)
    for k in range(3):
        np.add.at(n, F[:, k], fn)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


def _tube(P: np.ndarray, radius: float, sides: int = 8):
    """A closed-ring tube (vertices, normals, faces) around polyline P (m, 3), rotation-minimizing frames."""
    P = P[np.isfinite(P).all(1)]
    if len(P) > 1:
        keep = np.concatenate([[True], np.linalg.norm(np.diff(P, axis=0), axis=1) > 1e-12 * radius])
        P = P[keep]
    if len(P) < 2:
        return None
    T = np.gradient(P, axis=0)
    T /= np.maximum(np.linalg.norm(T, axis=1, keepdims=True), 1e-30)
    a = np.eye(3)[np.argmin(np.abs(T[0]))]
    N = np.empty_like(P)
    N[0] = np.cross(T[0], a)
    N[0] /= np.linalg.norm(N[0])
    for i in range(1, len(P)):  # parallel transport: drop the new tangent's component
        n = N[i - 1] - (N[i - 1] @ T[i]) * T[i]
        ln = np.linalg.norm(n)
        N[i] = n / ln if ln > 1e-9 else N[i - 1]
    B = np.cross(T, N)
    ang = 2 * np.pi * np.arange(sides) / sides
    nrm = np.cos(ang)[None, :, None] * N[:, None] + np.sin(ang)[None, :, None] * B[:, None]  # (m, s, 3)
    verts = P[:, None] + radius * nrm
    m = len(P)
    i, k = np.meshgrid(np.arange(m - 1), np.arange(sides), indexing="ij")
    a0, a1 = i * sides + k, i * sides + (k + 1) % sides
    b0, b1 = a0 + sides, a1 + sides
    faces = np.concatenate([np.stack([a0, a1, b1], -1).reshape(-1, 3), np.stack([a0, b1, b0], -1).reshape(-1, 3)])
    return verts.reshape(-1, 3), nrm.reshape(-1, 3), faces


def _spheres(points: np.ndarray, radius: float):
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=2)
    n = np.asarray(s.vertices)
    k = len(points)
    verts = (points[:, None] + radius * n[None]).reshape(-1, 3)
    faces = (np.asarray(s.faces)[None] + len(n) * np.arange(k)[:, None, None]).reshape(-1, 3)
    return verts, np.tile(n, (k, 1)), faces


def _vertex_values(mesh, values) -> np.ndarray:
    """Per-vertex values (the mesh's numbering, or internal order when that is the same length) -> internal."""
    v = as_numpy(values).astype(np.float64).reshape(-1) if np.ndim(as_numpy(values)) else None
    if v is None or len(v) not in (mesh.n_input, len(mesh.internal_vertices)):
        raise InputError(f"values must hold one number per mesh vertex ({mesh.n_input} in the mesh's numbering), "
                         f"got shape {np.shape(as_numpy(values))}")
    return v[mesh.index] if len(v) == mesh.n_input else v


def _polylines(paths) -> list:
    if isinstance(paths, (list, tuple)):
        out = [as_numpy(p).astype(np.float64) for p in paths]
    else:
        a = as_numpy(paths).astype(np.float64)
        out = [a] if a.ndim == 2 else list(a) if a.ndim == 3 else None
        if out is None:
            raise InputError(f"paths must be (N, m, 3), (m, 3) or a list of (m_i, 3) arrays, got shape {a.shape}")
    for p in out:
        if p.ndim != 2 or p.shape[1] != 3:
            raise InputError(f"each path must be an (m, 3) array of points, got shape {p.shape}")
    return out


def colorize(values, vrange=None) -> np.ndarray:
    """Colours of the package's colour map: (N,) values -> (N, 3) uint8; NaN -> grey.

    vrange : (low, high), the values mapped to the two ends (default: the finite values' min and max)."""
    v = as_numpy(values).astype(np.float64).reshape(-1)
    lo, hi = _range(v, vrange)
    t = np.clip((v - lo) / (hi - lo), 0, 1) * (len(COLOR_STOPS) - 1)
    k = np.minimum(np.floor(np.nan_to_num(t)).astype(int), len(COLOR_STOPS) - 2)
    f = (np.nan_to_num(t) - k)[:, None]
    rgb = (1 - f) * COLOR_STOPS[k] + f * COLOR_STOPS[k + 1]
    rgb[~np.isfinite(v)] = 0.72
    return np.round(rgb * 255).astype(np.uint8)


def _range(v: np.ndarray, vrange):
    if vrange is not None:
        lo, hi = (float(x) for x in vrange)
        if not (np.isfinite(lo) and np.isfinite(hi) and hi > lo):
            raise InputError(f"vrange must be (low, high) with low < high, got {vrange!r}")
        return lo, hi
    ok = v[np.isfinite(v)]
    if not len(ok):
        return 0.0, 1.0
    lo, hi = float(ok.min()), float(ok.max())
    return (lo, hi) if hi > lo else (lo, lo + 1.0)


@dataclass
class Style:
    """How a picture is drawn, apart from what (values, markers, paths) and from where (``View``).

    isolines : number of equal steps of the value range between isolines (0: none)
    vrange : (low, high) values at the colour map's ends (default: the field's min and max); share it between
        pictures that are to be compared
    supersample : samples per pixel along each axis (anti-aliasing; 1 = none), 1..8
    path_radius, marker_radius : tube and sphere radii, mesh units (default 0.6% and 2.5% of the bounding
        sphere's radius)
    path_targets : mark each path's last point (its target) with a dark sphere
    """

    isolines: int = 20
    vrange: tuple | None = None
    supersample: int = 2
    path_radius: float | None = None
    marker_radius: float | None = None
    path_targets: bool = True

    @classmethod
    def of(cls, style=None, **changes) -> "Style":
        """A Style from None (the default), a Style or a dict of its fields, with ``changes`` applied; unknown
        names are refused, naming the known ones."""
        known = {f.name for f in fields(cls)}
        if style is None:
            base = {}
        elif isinstance(style, cls):
            base = {f: getattr(style, f) for f in known}
        elif isinstance(style, dict):
            base = dict(style)
        else:
            raise InputError(f"style must be None, a Style or a dict of its fields, got {style!r}")
        base.update(changes)
        bad = sorted(set(base) - known)
        if bad:
            raise InputError(f"unknown picture setting(s) {bad}; known: {sorted(known)} (see neurogf_warp.pictures."
                             "render.Style)")
        out = cls(**base)
        out.isolines = integer("isolines", out.isolines, minimum=0)
        out.supersample = integer("supersample", out.supersample, minimum=1, maximum=8)
        for name in ("path_radius", "marker_radius"):
            if getattr(out, name) is not None:
                setattr(out, name, number(name, getattr(out, name), above=0.0))
        return out


def render(model_or_mesh, values=None, *, sources=None, paths=None, points=None, view=None, style=None,
           size=(1024, 1024), out=None, device=None, **style_fields) -> np.ndarray:
    """Draw the mesh shaded by a per-vertex field with isolines, sources and points marked, paths as tubes.

    Parameters
    ----------
    model_or_mesh : a Model with a mesh, or a mesh (Mesh, trimesh.Trimesh, (vertices, faces), file path)
    values : (V,) float per vertex in the mesh's numbering (NaN: no value, drawn grey). None with a model and
        ``sources``: the model's SSAD (one source) or MSAD (several) from them; None otherwise: plain grey.
    sources : vertex indices (mesh numbering) or (S, 3) points, mesh units; drawn as gold spheres
    paths : (N, m, 3), (m, 3) or a list of (m_i, 3) polylines, mesh units; drawn as tubes, colours cycled, each
        one's last point (its target) marked with a dark sphere unless ``path_targets=False``
    points : (K, 3) further points to mark (white spheres), mesh units
    view : where from: a ``View``, a dict of its fields or (azimuth, elevation) in degrees; None: with
        ``sources``, the view toward them (``source_side``: the one source, or several when they lie mostly on
        one side; elevation within +-60 degrees), else the default ``View``. The up axis is chosen by
        ``choose_up`` unless the view names one. Everything drawn, markers and paths included, fits in the
        picture with a margin at every view.
    style : how: a ``Style`` or a dict of its fields (isolines, vrange, supersample, path_radius,
        marker_radius, path_targets); ``style_fields`` given as keywords (``isolines=0``) override it
    size : (width, height) in pixels
    out : image file to write (.png, or .jpg), atomically; None writes nothing
    device : Warp device (default: Warp's preferred one)

    Returns
    -------
    (height, width, 3) uint8 RGB image
    """
    mesh = as_mesh(model_or_mesh)
    model = model_or_mesh if hasattr(model_or_mesh, "net") else None
    w, h = _size(size)
    st = Style.of(style, **style_fields)
    isolines, vrange, supersample = st.isolines, st.vrange, st.supersample
    path_radius, marker_radius = st.path_radius, st.marker_radius
    dev = resolve_device(device)
    V, F = mesh.internal_vertices, mesh.internal_faces.astype(np.int64)
    r0 = float(np.linalg.norm(V - (V.min(0) + V.max(0)) / 2, axis=1).max())

    if values is None and model is not None and sources is not None:
        from neurogf_warp.inference.queries import msad, ssad

        src = as_numpy(sources)
        one = src.size == 1 or (np.issubdtype(src.dtype, np.floating) and src.size == 3)
        values = (ssad(model, src.reshape(-1)[0] if src.size == 1 else src.reshape(3), device=dev) if one
                  else msad(model, src, device=dev))
    vals = np.full(len(V), np.nan) if values is None else _vertex_values(mesh, values)
    lo, hi = _range(vals, vrange)
    t = (vals - lo) / (hi - lo)

    parts = [(V, _vertex_normals(V, F), F, -1)]
    rm = marker_radius if marker_radius is not None else 0.025 * r0
    rp = path_radius if path_radius is not None else 0.006 * r0
    palette = [SOURCE_COLOR, POINT_COLOR, TARGET_COLOR, *PATH_COLORS]
    src_points = None
    if sources is not None:
        src_points = points_of(mesh, sources, "sources")
        parts.append((*_spheres(src_points, rm), 0))
    if points is not None:
        parts.append((*_spheres(points_of(mesh, np.asarray(as_numpy(points), dtype=np.float64), "points"),
                                0.75 * rm), 1))
    if paths is not None:
        lines = _polylines(paths)
        for i, P in enumerate(lines):
            tube = _tube(P, rp)
            if tube is not None:
                parts.append((*tube, 3 + i % len(PATH_COLORS)))
        ends = np.array([P[np.isfinite(P).all(1)][-1] for P in lines if np.isfinite(P).all(1).any()])
        if len(ends) and st.path_targets:
            parts.append((*_spheres(ends, 0.6 * rm), 2))
    verts, norms, faces, color, vv = [], [], [], [], []
    base = 0
    for pv, pn, pf, c in parts:
        verts.append(pv)
        norms.append(pn)
        faces.append(pf + base)
        color.append(np.full(len(pf), c, dtype=np.int32))
        vv.append(t if c < 0 else np.full(len(pv), np.nan))
        base += len(pv)
    verts = np.concatenate(verts)
    flat = np.concatenate(faces).astype(np.int32).reshape(-1)
    pts = wp.array(verts.astype(np.float32), dtype=wp.vec3, device=dev)
    idx = wp.array(flat, dtype=wp.int32, device=dev)
    bvh = wp.Mesh(points=pts, indices=idx)
    scene = raycast.Scene()
    scene.mesh = bvh.id
    scene.faces = idx
    scene.normals = wp.array(np.concatenate(norms).astype(np.float32), dtype=wp.vec3, device=dev)
    scene.values = wp.array(np.concatenate(vv).astype(np.float32), dtype=wp.float32, device=dev)
    scene.levels = float(isolines)
    scene.face_color = wp.array(np.concatenate(color), dtype=wp.int32, device=dev)
    scene.palette = wp.array(np.array(palette, dtype=np.float32), dtype=wp.vec3, device=dev)
    scene.stops = wp.array(COLOR_STOPS.astype(np.float32), dtype=wp.vec3, device=dev)
    scene.background = wp.vec3(*BACKGROUND)

    s = int(supersample)
    if view is None and src_points is not None and len(src_points):
        direction = source_side(src_points, V)
        if direction is not None:
            view = View.toward(direction, up="auto", vertices=V, max_elevation=SOURCE_VIEW_MAX_ELEVATION)
    cam = _camera(V, View.of(view), w * s, h * s, extent=verts)
    rgb = wp.empty((h * s, w * s), dtype=wp.vec3, device=dev)
    level = wp.empty((h * s, w * s), dtype=wp.int32, device=dev)
    wp.launch(raycast.trace, rgb.shape, inputs=[scene, cam], outputs=[rgb, level], device=dev)
    if isolines:
        lined = wp.empty_like(rgb)
        wp.launch(raycast.isolines, rgb.shape, inputs=[level, max(1, s // 2), rgb], outputs=[lined], device=dev)
        rgb = lined
    img = rgb.numpy().reshape(h, s, w, s, 3).mean(axis=(1, 3))
    img = np.round(np.clip(img, 0, 1) * 255).astype(np.uint8)
    if out is not None:
        write_image(out, img)
    return img


def _size(size):
    try:
        w, h = (int(x) for x in size)
    except (TypeError, ValueError):
        raise InputError(f"size must be (width, height) in pixels, got {size!r}") from None
    if not (1 <= w <= 16384 and 1 <= h <= 16384):
        raise InputError(f"size must be (width, height) with each in 1..16384 pixels, got {size!r}")
    return w, h


def write_image(path, image: np.ndarray) -> str:
    """An (H, W, 3) uint8 image to a .png (or .jpg) file, atomically (Pillow)."""
    ext = os.path.splitext(os.fspath(path))[1].lower()
    fmt = {".png": "PNG", ".jpg": "JPEG", ".jpeg": "JPEG"}.get(ext)
    if fmt is None:
        raise InputError(f"out must name a .png or .jpg file, got {os.fspath(path)!r}")
    try:
        from PIL import Image
    except ImportError as e:
        raise ImportError("writing pictures needs Pillow: pip install pillow") from e
    im = Image.fromarray(np.ascontiguousarray(image))
    opts = {"optimize": True} if fmt == "PNG" else {"quality": 92}
    return atomic_write(path, lambda f: im.save(f, format=fmt, **opts))


def write_ply(path, mesh, values, *, vrange=None) -> str:
    """A binary .ply of the mesh with vertex colours from ``values`` (MeshLab, Blender, trimesh read it).

    Parameters
    ----------
    path : output file, written atomically
    mesh : a Model with a mesh, or a mesh (Mesh, trimesh.Trimesh, (vertices, faces), file path)
    values : (n_input,) per-vertex values in the mesh's numbering (e.g. ``ssad``'s result); NaN is drawn grey
    vrange : (low, high) at the colour map's ends (default: the values' min and max)

    Notes
    -----
    The file holds every vertex of the mesh as given, in its numbering (vertex j of the file is vertex j of the
    mesh file and ``values[j]``), as float32 x, y, z, uchar red, green, blue, alpha and float32 quality (the value
    itself, which MeshLab shows as vertex quality), and the faces in their given order, indexing those vertices.
    Vertices no face uses have no position on the surface (``Mesh.vertices``): they are written with NaN
    coordinates and quality, grey, and no face refers to them.
    """
    m = as_mesh(mesh)
    v = m.to_input(_vertex_values(m, values))  # one value per vertex as given
    rgb = colorize(v, vrange)
    n, f = m.n_input, len(m.internal_faces)
    vert = np.empty(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"),
                              ("blue", "u1"), ("alpha", "u1"), ("quality", "<f4")])
    vert["x"], vert["y"], vert["z"] = m.vertices.T.astype(np.float32)
    vert["red"], vert["green"], vert["blue"] = rgb.T
    vert["alpha"] = 255
    vert["quality"] = v.astype(np.float32)
    face = np.empty(f, dtype=[("n", "u1"), ("i", "<i4", (3,))])
    face["n"], face["i"] = 3, m.faces  # the file's numbering
    header = (f"ply\nformat binary_little_endian 1.0\ncomment neurogf_warp field colours\nelement vertex {n}\n"
              "property float x\nproperty float y\nproperty float z\nproperty uchar red\nproperty uchar green\n"
              "property uchar blue\nproperty uchar alpha\nproperty float quality\n"
              f"element face {f}\nproperty list uchar int vertex_indices\nend_header\n").encode("ascii")

    def write(fh):
        fh.write(header)
        fh.write(vert.tobytes())
        fh.write(face.tobytes())

    return atomic_write(path, write)
