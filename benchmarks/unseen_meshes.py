"""Four test meshes of kinds the shared set lacks, with exact geodesic references in the shared format.

    python benchmarks/unseen_meshes.py                      # ./unseen: scan.ply ... joined.ply, reference/, manifest.json
    python benchmarks/unseen_meshes.py --out /tmp/u --scale 0.05     # small copies (a test's size)

The meshes (built with numpy from a fixed seed; a re-run writes the same arrays and the same PLY bytes):

- ``scan.ply``: a scanned-statue-like closed surface (~36K vertices): a geodesic icosphere with its vertices
  jittered along the surface (irregular triangles), stretched into an ellipsoid, with bumps, dents, a sharp ridge
  and a pinched neck, plus per-vertex noise along the normal. One component, genus 0.
- ``parts.ply``: a toy figure of 12 closed parts that share no vertex (~25K vertices): torso, head, nose, eyes,
  arms and legs (ellipsoids), hat and feet (boxes). Parts touch or pass through each other in space but are
  separate surfaces, so distances between parts are unreachable (inf).
- ``cad.ply``: an L-bracket (~6K vertices) with three rectangular through-holes (genus 3): flat faces on a
  rectilinear grid with strongly anisotropic spacing (triangles up to ~16:1), sharp 90-degree edges.
- ``joined.ply``: four bumpy open square patches (~12K vertices) tiling a square like a tessellated teapot's
  patches: neighbours lie along one seam in space but share only the seam's end points (other grid resolutions),
  so every geodesic between patches passes the centre or a tip, and points a hair apart across a seam are far
  apart on the surface. ``ngf.train`` refuses such a mesh unless ``allow_vertex_joins=True``.

Every closed mesh is checked before it is written: closed (every edge in two faces, consistently oriented), every
vertex a single fan (no pinch), no degenerate triangle, the promised number of components and Euler
characteristic, and no patches joined at single vertices (``neurogf_warp.mesh.topology.vertex_joins``); the joined
mesh has open boundaries, five pinch vertices (centre and tips), and ``vertex_joins`` finds its four patches.

References (``reference/<stem>.npz``, the keys of the shared ``reference/exact/*.npz``): ``positions`` float32
(V, 3) (the file's vertices), ``orig_index`` and ``file_index`` int32 (both the identity: every vertex is used and
in file order), ``sources`` int32 (8,), ``dist`` float32 (8, V) with inf where unreachable, ``how``. Sources: six
from ``np.random.default_rng(1234).choice(V, 6, replace=False)``, then the vertex farthest from vertex 0, then the
vertex farthest from that one. Distances: tvb-gdist (exact MMP) in float64, one solve per source on the source's
connected component (inf elsewhere); on the joined mesh per patch, pairs on two patches through the joints
(``JoinedSolver``). Each reference is checked: every value at most the shortest edge path
(Dijkstra) and at least the straight-line distance, finite exactly on the source's component, and
``dist[i, sources[j]] == dist[j, sources[i]]`` to 1e-9 relative. The table and ``manifest.json`` report the counts,
the checks and the gdist time.
"""
from __future__ import annotations

import argparse
import hashlib
import importlib.util
import sys
import time
from pathlib import Path

import numpy as np

import _bootstrap  # noqa: E402,F401  (this checkout's neurogf_warp, installed or not)

MESHES = ("scan", "parts", "cad", "joined")
JOINED_PATCHES = 4
SOURCE_SEED = 1234  # the shared references' source draw
N_RANDOM_SOURCES = 6


# ----------------------------------------------------------------------------------------------- building blocks

def icosphere(n: int) -> tuple[np.ndarray, np.ndarray]:
    """A geodesic sphere: every icosahedron face split into n x n triangles, vertices on the unit sphere.

    Parameters
    ----------
    n : int, >= 1
        Subdivision frequency.

    Returns
    -------
    vertices : (10 n^2 + 2, 3) float64, unit length
    faces : (20 n^2, 3) int64, outward (counter-clockwise seen from outside)
    """
    t = (1.0 + 5 ** 0.5) / 2.0
    ico_v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t],
                      [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], dtype=np.float64)
    ico_f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
                      [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
                      [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]], dtype=np.int64)
    ii, jj = [a.ravel() for a in np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")]
    keep = ii + jj <= n
    ii, jj = ii[keep], jj[keep]
    local = -np.ones((n + 1, n + 1), dtype=np.int64)
    local[ii, jj] = np.arange(len(ii))
    # a point is named by its integer barycentric weights on the icosahedron's vertex ids, so the points of an
    # edge or corner shared by several faces get one name (and one vertex) without comparing floats
    weights = np.stack([n - ii - jj, ii, jj], 1)                                    # (P, 3)
    ids = np.where(weights[None] > 0, ico_f[:, None, :], 99)                         # (20, P, 3)
    w = np.broadcast_to(weights[None], ids.shape)
    order = np.argsort(ids, axis=2, kind="stable")
    ids_s, w_s = np.take_along_axis(ids, order, 2), np.take_along_axis(w, order, 2)
    key = np.concatenate([ids_s, w_s], 2).reshape(-1, 6)
    _, first, point_vertex = np.unique(key, axis=0, return_index=True, return_inverse=True)
    point_vertex = point_vertex.reshape(20, -1)
    bary = np.broadcast_to(weights[None], (20,) + weights.shape).reshape(-1, 3)[first] / n
    corners = np.repeat(ico_f[:, None, :], len(ii), 1).reshape(-1, 3)[first]
    verts = np.einsum("pk,pkd->pd", bary, ico_v[corners])
    verts /= np.linalg.norm(verts, axis=1, keepdims=True)
    tri = []
    for i in range(n):
        for j in range(n - i):
            tri.append((local[i, j], local[i + 1, j], local[i, j + 1]))
            if j < n - 1 - i:
                tri.append((local[i + 1, j], local[i + 1, j + 1], local[i, j + 1]))
    tri = np.array(tri, dtype=np.int64)
    faces = np.concatenate([point_vertex[f][tri] for f in range(20)])
    return verts, faces


def lattice_surface(occupied: np.ndarray, xs: np.ndarray, ys: np.ndarray, zs: np.ndarray):
    """The closed boundary of a union of cells of a rectilinear grid, as triangles (two per cell face).

    Parameters
    ----------
    occupied : (nx, ny, nz) bool
        Cells inside the solid. Cells that touch only along an edge or at a corner would make a non-manifold
        surface; the caller's shapes avoid them (the mesh checks catch them).
    xs, ys, zs : (nx + 1,), (ny + 1,), (nz + 1,) float64, increasing
        Grid lines (units are the caller's).

    Returns
    -------
    vertices : (V, 3) float64; faces : (F, 3) int64, outward.
    """
    occ = np.pad(np.asarray(occupied, bool), 1)
    nx, ny, nz = occupied.shape
    quads = []
    for axis in range(3):
        lo = np.take(occ, np.arange(0, occ.shape[axis] - 1), axis)
        hi = np.take(occ, np.arange(1, occ.shape[axis]), axis)
        sl = [slice(1, -1)] * 3
        sl[axis] = slice(None)
        out_pos = (lo & ~hi)[tuple(sl)]  # solid below the plane, empty above: the face looks along +axis
        out_neg = (~lo & hi)[tuple(sl)]
        a1, a2 = (axis + 1) % 3, (axis + 2) % 3  # a1 x a2 = +axis, so (0,0),(1,0),(1,1),(0,1) in (a1, a2) is CCW
        for mask, flip in ((out_pos, False), (out_neg, True)):
            idx = np.argwhere(mask)  # (plane, cell a1, cell a2) in the order of the axes
            corners = []
            for d1, d2 in ((0, 0), (1, 0), (1, 1), (0, 1)):
                c = idx.copy()
                c[:, a1] += d1
                c[:, a2] += d2
                corners.append(c)
            q = np.stack(corners, 1)  # (m, 4, 3) lattice points
            quads.append(q[:, ::-1] if flip else q)
    q = np.concatenate(quads)
    lid = (q[..., 0] * (ny + 1) + q[..., 1]) * (nz + 1) + q[..., 2]
    used, inv = np.unique(lid, return_inverse=True)
    inv = inv.reshape(lid.shape)
    i, rem = np.divmod(used, (ny + 1) * (nz + 1))
    j, k = np.divmod(rem, nz + 1)
    verts = np.stack([xs[i], ys[j], zs[k]], 1)
    faces = np.concatenate([inv[:, [0, 1, 2]], inv[:, [0, 2, 3]]])
    return verts, faces


def grid_lines(features, spacing: float) -> np.ndarray:
    """Grid lines through every feature coordinate, each gap split evenly into steps of at most ``spacing``."""
    f = np.unique(np.asarray(features, dtype=np.float64))
    out = [f[:1]]
    for a, b in zip(f[:-1], f[1:]):
        m = max(1, int(np.ceil((b - a) / spacing - 1e-9)))
        out.append(a + (b - a) * np.arange(1, m + 1) / m)
    return np.concatenate(out)


def vertex_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """(V, 3) unit area-weighted vertex normals."""
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n = np.zeros_like(v)
    for c in range(3):
        np.add.at(n, f[:, c], fn)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def rotation(axis, angle: float) -> np.ndarray:
    """(3, 3) rotation by ``angle`` radians about ``axis``."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)


def mean_edge(v: np.ndarray, f: np.ndarray) -> float:
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    return float(np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1).mean())


# ------------------------------------------------------------------------------------------------------ meshes

def make_scan(rng: np.random.Generator, scale: float = 1.0):
    """A scan-like statue: jittered icosphere, ellipsoid, bumps, ridge, pinched neck, normal noise.

    Returns vertices (V, 3) float64 (about 2.6 units tall) and faces (F, 3) int64; V = 10 n^2 + 2 with
    n = round(60 sqrt(scale)).
    """
    n = max(4, int(round(60 * scale ** 0.5)))
    u, f = icosphere(n)
    h = mean_edge(u, f)
    # tangential jitter: the irregular triangles of a scanner's mesh (a quarter edge keeps every triangle upright)
    t = rng.normal(size=u.shape) * 0.12 * h
    t -= np.sum(t * u, 1, keepdims=True) * u
    u = u + np.clip(t, -0.25 * h, 0.25 * h)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    r = np.ones(len(u))
    centers = rng.normal(size=(8, 3))
    centers /= np.linalg.norm(centers, axis=1, keepdims=True)
    amps = rng.uniform(0.05, 0.16, 8) * np.where(np.arange(8) % 4 == 3, -0.6, 1.0)  # bumps and a few dents
    widths = rng.uniform(0.05, 0.15, 8)
    for c, a, w in zip(centers, amps, widths):
        r += a * np.exp(-(1.0 - u @ c) / w)
    m = rng.normal(size=3)
    m /= np.linalg.norm(m)
    r += 0.07 * np.exp(-(u @ m) ** 2 / 0.003)  # a sharp ridge along a great circle
    v = u * r[:, None] * np.array([0.75, 0.6, 1.3])
    v[:, :2] *= (1.0 - 0.45 * np.exp(-((v[:, 2] - 0.55) / 0.18) ** 2))[:, None]  # the neck
    v += vertex_normals(v, f) * rng.normal(size=(len(v), 1)) * 0.08 * mean_edge(v, f)
    return v, f


PARTS = [  # name, kind, centre, size (ellipsoid semi-axes / box edge lengths), rotation axis, angle (degrees)
    ("torso", "ellipsoid", (0.0, 0.0, 0.0), (0.45, 0.3, 0.65), (0, 0, 1), 0),
    ("head", "ellipsoid", (0.0, 0.0, 0.95), (0.3, 0.3, 0.33), (0, 0, 1), 10),
    ("nose", "ellipsoid", (0.0, -0.33, 0.93), (0.05, 0.1, 0.05), (1, 0, 0), 15),
    ("eye_l", "ellipsoid", (-0.11, -0.26, 1.04), (0.055, 0.055, 0.055), (0, 0, 1), 0),
    ("eye_r", "ellipsoid", (0.11, -0.26, 1.04), (0.055, 0.055, 0.055), (0, 0, 1), 0),
    ("hat", "box", (0.0, 0.0, 1.3), (0.5, 0.45, 0.25), (0, 0, 1), 10),
    ("arm_l", "ellipsoid", (-0.52, 0.0, 0.15), (0.09, 0.09, 0.48), (0, 1, 0), 28),
    ("arm_r", "ellipsoid", (0.52, 0.0, 0.15), (0.09, 0.09, 0.48), (0, 1, 0), -28),
    ("leg_l", "ellipsoid", (-0.2, 0.0, -1.0), (0.13, 0.13, 0.5), (0, 1, 0), 4),
    ("leg_r", "ellipsoid", (0.2, 0.0, -1.0), (0.13, 0.13, 0.5), (0, 1, 0), -4),
    ("foot_l", "box", (-0.22, -0.1, -1.55), (0.22, 0.42, 0.12), (0, 0, 1), 6),
    ("foot_r", "box", (0.22, -0.1, -1.55), (0.22, 0.42, 0.12), (0, 0, 1), -6),
]


def _ellipsoid_area(a: float, b: float, c: float) -> float:
    p = 1.6075  # Knud Thomsen's approximation, within about 1%
    return 4 * np.pi * (((a * b) ** p + (a * c) ** p + (b * c) ** p) / 3) ** (1 / p)


def make_parts(rng: np.random.Generator, scale: float = 1.0):
    """A toy figure of 12 separate closed parts, about 25K vertices at scale 1 (vertices spread by area).

    Returns vertices (V, 3) float64, faces (F, 3) int64 and the part names in vertex order.
    """
    areas = [(_ellipsoid_area(*s) if k == "ellipsoid" else 2 * (s[0] * s[1] + s[1] * s[2] + s[0] * s[2]))
             for _, k, _, s, _, _ in PARTS]
    density = 25_000 * scale / sum(areas)  # vertices per unit area
    vs, fs, names, base = [], [], [], 0
    for (name, kind, centre, size, axis, angle), area in zip(PARTS, areas):
        if kind == "ellipsoid":
            n = max(2, int(round((area * density / 10) ** 0.5)))
            v, f = icosphere(n)
            v = v * np.array(size)
        else:
            h = 1.1 / density ** 0.5
            half = np.array(size) / 2
            lines = [grid_lines([-s, s], h) for s in half]
            v, f = lattice_surface(np.ones([len(x) - 1 for x in lines], bool), *lines)
        # a small seeded tilt: parts that touch meet at generic positions, never at a shared coordinate
        tilt = rotation(rng.normal(size=3), np.radians(rng.uniform(1, 3)))
        v = v @ (rotation(axis, np.radians(angle)) @ tilt).T + np.array(centre)
        vs.append(v)
        fs.append(f + base)
        names += [name] * len(v)
        base += len(v)
    return np.concatenate(vs), np.concatenate(fs), names


def make_cad(rng: np.random.Generator, scale: float = 1.0):
    """An L-bracket (mm) with two rectangular holes in its base and one in its upright: genus 3.

    Grid spacing 8 mm along x, 0.5 mm along y, 2 mm along z (divided by sqrt(scale)): long thin triangles on
    every face. ``rng`` is unused: the part is fully specified.
    """
    s = scale ** 0.5
    xs = grid_lines([0, 6, 30, 42, 56, 68, 80], 8.0 / s)
    ys = grid_lines([0, 12, 14, 26, 28, 40], 0.5 / s)
    zs = grid_lines([0, 6, 22, 36, 50], 2.0 / s)
    cx, cy, cz = [(a[:-1] + a[1:]) / 2 for a in (xs, ys, zs)]
    X, Y, Z = np.meshgrid(cx, cy, cz, indexing="ij")
    solid = ((Z < 6) | (X < 6)) & (Z < 50)
    holes = (((X > 30) & (X < 42)) | ((X > 56) & (X < 68))) & (Y > 12) & (Y < 28) & (Z < 6)
    holes |= (X < 6) & (Y > 14) & (Y < 26) & (Z > 22) & (Z < 36)
    return lattice_surface(solid & ~holes, xs, ys, zs)


def make_joined(rng: np.random.Generator, scale: float = 1.0):
    """Four bumpy open unit squares tiling [-1, 1]^2 around the z axis, as a tessellated teapot's patches: along
    each seam the two patches lie on one line in space but their vertices differ (other grid resolutions), so
    they share only the seam's two end points, the centre (vertex 0) and a tip (vertices 1-4); the bumps vanish
    on every patch edge, so the seams meet in space.

    Returns (vertices (V, 3), faces (F, 3), list of JOINED_PATCHES (F_p,) face index arrays, one per patch)."""
    base = max(6, int(round(48 * scale ** 0.5)))
    tips = [np.array([np.cos(a), np.sin(a), 0.0]) for a in np.arange(JOINED_PATCHES) * 2 * np.pi / JOINED_PATCHES]
    verts = [np.zeros((1, 3))] + [t[None] for t in tips]
    faces, patches, start, nf = [], [], 1 + JOINED_PATCHES, 0
    for i in range(JOINED_PATCHES):
        n = base + 7 * i  # a resolution of its own: seam vertices of neighbours do not coincide
        a = 2 * np.pi * i / JOINED_PATCHES
        u, w = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
        amp, fu, fw = rng.uniform(0.08, 0.2), rng.integers(1, 4), rng.integers(1, 4)
        z = amp * np.sin(np.pi * fu * u) * np.sin(np.pi * fw * w)  # zero on every edge: seams meet in space
        x, y = u * np.cos(a) - w * np.sin(a), u * np.sin(a) + w * np.cos(a)
        pts = np.stack([x, y, z], -1).reshape(-1, 3)
        grid = np.arange(n * n).reshape(n, n)
        quads = np.stack([grid[:-1, :-1], grid[1:, :-1], grid[1:, 1:], grid[:-1, 1:]], -1).reshape(-1, 4)
        tri = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
        shared = {0: 0, grid[-1, 0]: 1 + i, grid[0, -1]: 1 + (i + 1) % JOINED_PATCHES}  # centre, its two tips
        own = np.setdiff1d(np.arange(n * n), list(shared))
        idx = np.empty(n * n, np.int64)
        idx[own] = start + np.arange(len(own))
        for local, glob in shared.items():
            idx[local] = glob
        verts.append(pts[own])
        faces.append(idx[tri])
        patches.append(nf + np.arange(len(tri)))
        start, nf = start + len(own), nf + len(tri)
    return np.concatenate(verts), np.concatenate(faces), patches


# ------------------------------------------------------------------------------------------------------ checks

def topology(v: np.ndarray, f: np.ndarray) -> dict:
    """Counts that say whether a mesh is a closed, oriented 2-manifold, and its per-component Euler characteristic.

    Returns a dict: vertices, faces, edges, components, boundary_edges (edges in one face), nonmanifold_edges
    (in three or more), misoriented_edges (two faces traversing an edge the same way), pinch_vertices (vertices
    whose faces form several fans), min_area and min_angle_deg (the smallest triangle area, input units^2, and
    angle), euler (list, per component, in component order), genus (list; None where not closed).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from neurogf_warp.mesh.mesh import component_labels

    f = np.asarray(f, dtype=np.int64)
    nv = len(v)
    d = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])  # directed half-edges
    und = np.sort(d, 1)
    key = und[:, 0] * nv + und[:, 1]
    ukey, inv, count = np.unique(key, return_inverse=True, return_counts=True)
    dkey = d[:, 0] * nv + d[:, 1]
    misoriented = len(dkey) - len(np.unique(dkey))
    # fans: corners (vertex, face) joined when the two faces share an edge at that vertex
    fid = np.tile(np.arange(len(f)), 3)
    order = np.argsort(inv, kind="stable")
    pairs = order.reshape(-1, 2) if np.all(count == 2) else None
    pinch = None
    if pairs is not None:
        rows, cols = [], []
        for p in (0, 1):  # both ends of the shared edge
            ends = und[pairs[:, 0], p]
            fa, fb = fid[pairs[:, 0]], fid[pairs[:, 1]]
            ca = fa * 3 + np.argmax(f[fa] == ends[:, None], 1)
            cb = fb * 3 + np.argmax(f[fb] == ends[:, None], 1)
            rows.append(ca)
            cols.append(cb)
        g = coo_matrix((np.ones(2 * len(pairs), np.int8), (np.concatenate(rows), np.concatenate(cols))),
                       shape=(3 * len(f), 3 * len(f)))
        n_fans, _ = connected_components(g, directed=False)
        pinch = int(n_fans - len(np.unique(f)))  # corner (face, slot) is node 3 face + slot
    labels = component_labels(nv, f)
    ncomp = int(labels.max()) + 1
    fl = labels[f[:, 0]]
    ev = labels[ukey // nv]
    euler = (np.bincount(labels, minlength=ncomp) - np.bincount(ev, minlength=ncomp)
             + np.bincount(fl, minlength=ncomp)).astype(int).tolist()
    closed = bool(np.all(count == 2) and misoriented == 0 and pinch == 0)
    e1, e2 = v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]
    area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)
    ang = []
    for a, b, c in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
        x, y = v[f[:, b]] - v[f[:, a]], v[f[:, c]] - v[f[:, a]]
        cosv = np.sum(x * y, 1) / (np.linalg.norm(x, axis=1) * np.linalg.norm(y, axis=1))
        ang.append(np.degrees(np.arccos(np.clip(cosv, -1, 1))))
    return {"vertices": nv, "faces": len(f), "edges": len(ukey), "components": ncomp,
            "boundary_edges": int(np.sum(count == 1)), "nonmanifold_edges": int(np.sum(count > 2)),
            "misoriented_edges": int(misoriented), "pinch_vertices": pinch, "closed": closed,
            "min_area": float(area.min()), "min_angle_deg": float(np.min(ang)),
            "euler": euler, "genus": [(2 - e) // 2 for e in euler] if closed else None}


def check_mesh(name: str, v: np.ndarray, f: np.ndarray, components: int, genus: int) -> dict:
    """``topology`` plus the promises of each mesh; raises RuntimeError naming the broken one."""
    topo = topology(v, f)
    scale = float(np.ptp(v, 0).max())
    problems = []
    if not topo["closed"]:
        problems.append(f"not closed ({topo['boundary_edges']} boundary, {topo['nonmanifold_edges']} non-manifold, "
                        f"{topo['misoriented_edges']} misoriented edges, {topo['pinch_vertices']} pinch vertices)")
    if topo["components"] != components:
        problems.append(f"{topo['components']} components, expected {components}")
    if topo["genus"] is not None and any(g != genus for g in topo["genus"]):
        problems.append(f"genus {topo['genus']}, expected {genus}")
    if not topo["min_area"] > 1e-10 * scale ** 2 or not topo["min_angle_deg"] > 0.5:
        problems.append(f"degenerate triangles (area {topo['min_area']:.3g}, angle {topo['min_angle_deg']:.3g} deg)")
    if problems:
        raise RuntimeError(f"{name}: " + "; ".join(problems))
    return topo


# -------------------------------------------------------------------------------------------------- references

def edge_graph(v: np.ndarray, f: np.ndarray):
    """(V, V) scipy CSR of the mesh edges, weighted by Euclidean length (float64)."""
    from scipy.sparse import coo_matrix

    e = np.unique(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), 1), axis=0)
    w = np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1)
    return coo_matrix((np.r_[w, w], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(len(v),) * 2).tocsr()


class ComponentSolver:
    """Exact distances (tvb-gdist) from one vertex, solved on that vertex's connected component only.

    Parameters
    ----------
    v : (V, 3) float64; f : (F, 3) int
    """

    def __init__(self, v: np.ndarray, f: np.ndarray):
        from neurogf_warp.mesh.mesh import component_labels

        self.v, self.f = v, np.asarray(f, np.int64)
        self.labels = component_labels(len(v), self.f)
        self._sub = {}
        self.seconds = 0.0
        self.solves = 0

    def _component(self, c: int):
        if c not in self._sub:
            verts = np.flatnonzero(self.labels == c)
            local = np.full(len(self.v), -1, np.int64)
            local[verts] = np.arange(len(verts))
            faces = local[self.f[self.labels[self.f[:, 0]] == c]].astype(np.int32)
            self._sub[c] = (verts, local, np.ascontiguousarray(self.v[verts]), np.ascontiguousarray(faces))
        return self._sub[c]

    def __call__(self, s: int) -> np.ndarray:
        """(V,) float64 distances from vertex ``s``, inf on other components."""
        import gdist

        verts, local, pos, faces = self._component(int(self.labels[s]))
        t0 = time.perf_counter()
        d = gdist.compute_gdist(pos, faces, source_indices=np.array([local[s]], np.int32))
        self.seconds += time.perf_counter() - t0
        self.solves += 1
        d = np.asarray(d, np.float64)
        if not np.all(np.isfinite(d)):  # gdist marks vertices it cannot reach with inf; on one component: none
            raise RuntimeError(f"gdist left {int(np.sum(~np.isfinite(d)))} vertices of the source's component "
                               "unreached")
        out = np.full(len(self.v), np.inf)
        out[verts] = d
        return out


class JoinedSolver:
    """Exact distances on patches that meet only at joint vertices (tvb-gdist per patch).

    A path from one patch to another passes joints, and between joints it runs inside one patch; so
    d(s, v) = min(d_P(s, v) for a patch P holding both, d_P(s, a) + D(a, b) + d_Q(b, v) over joints a of s's patch
    P and b of v's patch Q), with D the joints' distances through the patches (Floyd-Warshall over the few joints).

    Parameters
    ----------
    v : (V, 3) float64; f : (F, 3) int; patches : list of face index arrays, one per patch
    """

    def __init__(self, v: np.ndarray, f: np.ndarray, patches: list):
        f = np.asarray(f, np.int64)
        self.v = v
        self.solvers = [ComponentSolver(v, f[p]) for p in patches]
        self.holds = np.zeros((len(patches), len(v)), bool)  # holds[p, i]: vertex i is on patch p
        for p, faces in enumerate(patches):
            self.holds[p, f[faces]] = True
        self.joints = np.flatnonzero(self.holds.sum(0) > 1)
        self.labels = np.zeros(len(v), np.int64)  # one vertex-connected piece
        self.seconds, self.solves = 0.0, 0
        self._from = {}  # (patch, joint) -> (V,) distances on that patch
        J = len(self.joints)
        D = np.full((J, J), np.inf)
        np.fill_diagonal(D, 0.0)
        for p in range(len(patches)):
            here = np.flatnonzero(self.holds[p, self.joints])
            for a in here:
                d = self._row(p, int(self.joints[a]))
                for b in here:
                    D[a, b] = min(D[a, b], d[self.joints[b]])
        for k in range(J):
            D = np.minimum(D, D[:, [k]] + D[[k], :])
        self.D = D

    def _row(self, p: int, s: int) -> np.ndarray:
        if (p, s) not in self._from:
            cs = self.solvers[p]
            self._from[p, s] = cs(s)
            self.seconds, self.solves = self.seconds + cs.seconds, self.solves + 1
            cs.seconds = 0.0
        return self._from[p, s]

    def __call__(self, s: int) -> np.ndarray:
        """(V,) float64 distances from vertex ``s``."""
        own = np.flatnonzero(self.holds[:, s])
        out = np.full(len(self.v), np.inf)
        to_joint = np.full(len(self.joints), np.inf)
        for p in own:
            d = self._row(p, s)
            out = np.fmin(out, d)
            to_joint = np.fmin(to_joint, d[self.joints])
        via = np.min(to_joint[:, None] + self.D, axis=0)  # s to every joint through the patches
        for p in range(len(self.holds)):
            for a, j in enumerate(self.joints):
                if np.isfinite(via[a]) and self.holds[p, j]:
                    out = np.fmin(out, via[a] + self._row(p, int(j)))
        return out


def exact_reference(v32: np.ndarray, f: np.ndarray, label: list | None = None) -> tuple[dict, dict]:
    """The shared-format reference of a mesh and its checks.

    Parameters
    ----------
    v32 : (V, 3) float32, mesh units
        The vertices as stored in the file (distances are computed on their float64 values).
    f : (F, 3) int
    label : list of (F_p,) face index arrays, optional
        The patches of a mesh whose patches meet only at joint vertices (``make_joined``): solved per patch.

    Returns
    -------
    ref : dict of the .npz arrays (positions, orig_index, file_index, sources, dist, how)
    info : dict with the gdist time and the check results (max values and pass flags)
    """
    from scipy.sparse.csgraph import dijkstra

    v = v32.astype(np.float64)
    nv = len(v)
    solve = ComponentSolver(v, f) if label is None else JoinedSolver(v, f, label)
    src = [int(s) for s in np.random.default_rng(SOURCE_SEED).choice(nv, N_RANDOM_SOURCES, replace=False)]
    rows = [solve(s) for s in src]
    d0 = rows[src.index(0)] if 0 in src else solve(0)
    reach0 = np.where(np.isfinite(d0), d0, -np.inf)
    src.append(int(np.argmax(reach0)))
    rows.append(solve(src[-1]))
    src.append(int(np.argmax(np.where(np.isfinite(rows[-1]), rows[-1], -np.inf))))
    rows.append(solve(src[-1]))
    dist = np.stack(rows)
    sources = np.array(src, np.int64)

    dj = dijkstra(edge_graph(v, np.asarray(f, np.int64)), directed=False, indices=sources)
    fin = np.isfinite(dist)
    reach_ok = bool(np.array_equal(fin, np.isfinite(dj))
                    and np.array_equal(fin, solve.labels[None, :] == solve.labels[sources][:, None]))
    with np.errstate(invalid="ignore"):  # inf - inf off the source's component, masked out
        above_path = float(np.max(np.where(fin, dist - dj, -np.inf)))  # <= 0 up to rounding
    straight = np.linalg.norm(v[None, :, :] - v[sources][:, None, :], axis=2)
    below_line = float(np.max(np.where(fin, straight - dist, -np.inf)))  # <= 0 up to rounding
    a, b = dist[:, sources], dist[:, sources].T
    both = np.isfinite(a) & np.isfinite(b)
    if not np.array_equal(np.isfinite(a), np.isfinite(b)):
        sym = np.inf
    else:
        sym = float(np.max(np.abs(a[both] - b[both]) / np.maximum(np.abs(a[both]), 1e-300), initial=0.0))
    diam = float(dist[fin].max())
    tol = 1e-12 * diam
    checks = {"reachable_equals_component": reach_ok,
              "max_exact_minus_dijkstra": above_path, "exact_le_dijkstra": above_path <= tol,
              "max_straight_minus_exact": below_line, "exact_ge_straight_line": below_line <= tol,
              "max_symmetry_rel": sym, "symmetric": sym <= 1e-9}
    how = (f"tvb-gdist {_version('tvb-gdist')} (Kirsanov's exact MMP) gdist.compute_gdist(positions, faces, "
           "source_indices=[s]) in float64 on the file's float32 vertices, one solve per source on the source's "
           + ("connected component (inf on the others)" if label is None else
              "patch and from every joint vertex on each of its patches; across patches the shortest way through "
              "the joints (d_P(s, a) + D(a, b) + d_Q(b, v), D by Floyd-Warshall over the joints)")
           + "; sources[0:6] = np.random.default_rng(1234).choice(V, 6, "
           "replace=False), sources[6] = farthest from vertex 0, sources[7] = farthest from sources[6]; every "
           "vertex is used and in file order, so orig_index = file_index = arange(V); stored as float32")
    ref = {"positions": v32.astype(np.float32), "orig_index": np.arange(nv, dtype=np.int32),
           "file_index": np.arange(nv, dtype=np.int32), "sources": sources.astype(np.int32),
           "dist": dist.astype(np.float32), "how": np.array(how)}
    info = {"gdist_seconds": round(solve.seconds, 3), "gdist_solves": solve.solves,
            "diameter": float(dist[7, src[6]]), "unreachable_fraction": float(1 - fin.mean()), "checks": checks,
            "dist_float64_sha256": hashlib.sha256(np.ascontiguousarray(dist).tobytes()).hexdigest()}
    return ref, info


def _version(dist_name: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(dist_name)
    except PackageNotFoundError:
        return "unknown"


# ------------------------------------------------------------------------------------------------------ output

def write_ply(path: Path, v32: np.ndarray, f: np.ndarray) -> None:
    """Binary little-endian PLY: float32 x, y, z; faces as uchar count + int32 indices."""
    header = ("ply\nformat binary_little_endian 1.0\ncomment benchmarks/unseen_meshes.py\n"
              f"element vertex {len(v32)}\nproperty float x\nproperty float y\nproperty float z\n"
              f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n").encode("ascii")
    rec = np.empty(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    rec["n"] = 3
    rec["i"] = f
    with open(path, "wb") as fh:
        fh.write(header)
        fh.write(np.ascontiguousarray(v32, dtype="<f4").tobytes())
        fh.write(rec.tobytes())


def check_loading(ply: Path, npz: Path, v32: np.ndarray, f: np.ndarray, joined: int = 0) -> dict:
    """The project's loaders accept the files and agree with the arrays; ``vertex_joins`` finds no joined patches,
    or with ``joined`` that many patches on one pinch vertex."""
    import trimesh

    from neurogf_warp.evaluation.evaluate import load_reference
    from neurogf_warp.mesh.mesh import load_mesh
    from neurogf_warp.mesh.topology import vertex_joins

    m = load_mesh(ply)
    same = (m.n_input == len(v32) and np.array_equal(m.internal_vertices, v32.astype(np.float64))
            and np.array_equal(m.internal_faces, f))
    tm = trimesh.load(ply, process=False, force="mesh")
    same_tm = np.array_equal(np.asarray(tm.vertices), v32.astype(np.float64)) and np.array_equal(tm.faces, f)
    vid, sid, dist = load_reference(npz, m)
    ref_ok = bool(np.array_equal(vid, np.arange(len(v32))) and dist.shape == (8, len(v32)))
    vj = vertex_joins(m)
    out = {"load_mesh_matches": bool(same), "trimesh_matches": bool(same_tm), "load_reference_ok": ref_ok,
           "vertex_joins": {"patches": vj.patches, "joined_patches": vj.joined_patches,
                            "pinch_vertices": vj.pinch_vertices, "coincident_vertices": vj.coincident_vertices}}
    joins_ok = (not vj.any) if not joined else (vj.joined_patches == joined and vj.pinch_vertices == joined + 1)
    if not (same and same_tm and ref_ok and joins_ok and vj.coincident_vertices == 0):
        raise RuntimeError(f"{ply.name}: the loaders disagree with the written arrays or find vertex joins: {out}")
    return out


def build(name: str, seed: int, scale: float):
    """(vertices float32 (V, 3), faces int64 (F, 3), expected components, expected genus, notes, the patches' face
    index arrays of a joined mesh or None) of one mesh."""
    # one stream per mesh, so that one mesh's arrays do not depend on which others are built
    rng = np.random.default_rng([seed, MESHES.index(name)])
    if name == "joined":
        v, f, label = make_joined(rng, scale)
        return (v.astype(np.float32), f.astype(np.int64), 1, None,
                f"{JOINED_PATCHES} bumpy open patches tiling a square, joined at the centre and the seams' tips", label)
    if name == "scan":
        v, f = make_scan(rng, scale)
        comps, genus, notes = 1, 0, "jittered icosphere, ellipsoid, bumps, ridge, pinched neck, normal noise"
    elif name == "parts":
        v, f, names = make_parts(rng, scale)
        comps, genus, notes = len(PARTS), 0, "parts: " + ", ".join(p[0] for p in PARTS)
    else:
        v, f = make_cad(rng, scale)
        comps, genus, notes = 1, 3, "L-bracket, 3 rectangular through-holes, anisotropic grid faces"
    return v.astype(np.float32), f.astype(np.int64), comps, genus, notes, None


def check_joined(v: np.ndarray, f: np.ndarray) -> dict:
    """``topology`` of the joined mesh: one component, open boundaries, no edge in three faces, consistent
    orientation, no degenerate triangle (its joints are counted by ``check_loading``); raises RuntimeError
    otherwise."""
    topo = topology(v, f)
    ok = (topo["components"] == 1 and topo["boundary_edges"] > 0 and topo["nonmanifold_edges"] == 0
          and topo["misoriented_edges"] == 0 and topo["min_angle_deg"] > 0.5)
    if not ok:
        raise RuntimeError(f"joined: not open patches joined at vertices ({topo})")
    topo["genus"] = []  # open patches: no genus
    return topo


def generate(out: Path, seed: int = 0, scale: float = 1.0, meshes=MESHES, quiet: bool = False) -> dict:
    """Write ``<out>/<mesh>.ply``, ``<out>/reference/<mesh>.npz`` and return the per-mesh manifest entries."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "reference").mkdir(exist_ok=True)
    entries = {}
    for name in meshes:
        t0 = time.perf_counter()
        v32, f, comps, genus, notes, label = build(name, seed, scale)
        # the checks run on the float32 vertices the file stores, which every reader sees
        topo = check_mesh(name, v32.astype(np.float64), f, comps, genus) if label is None else \
            check_joined(v32.astype(np.float64), f)
        ply = out / f"{name}.ply"
        write_ply(ply, v32, f)
        ref, info = exact_reference(v32, f, label)
        failed = [k for k, ok in info["checks"].items() if isinstance(ok, bool) and not ok]
        if failed:
            raise RuntimeError(f"{name}: reference checks failed: {failed} ({info['checks']})")
        npz = out / "reference" / f"{name}.npz"
        np.savez_compressed(npz, **ref)
        loading = check_loading(ply, npz, v32, f, JOINED_PATCHES if label is not None else 0)
        entries[name] = {"file": ply.name, "reference": f"reference/{npz.name}", "description": notes,
                         "sha256": hashlib.sha256(ply.read_bytes()).hexdigest(), **topo,
                         "sources": ref["sources"].tolist(), **info, "loading": loading,
                         "seconds": round(time.perf_counter() - t0, 2)}
        if not quiet:
            print(f"  {name}: {len(v32):,} vertices, gdist {info['gdist_seconds']:.1f} s", flush=True)
    return entries


def table(entries: dict) -> str:
    rows = ["| mesh | vertices | faces | components | genus | min angle | diameter | unreachable | gdist s | checks |",
            "|---|---|---|---|---|---|---|---|---|---|"]
    for name, e in entries.items():
        g = sorted(set(e["genus"])) or ["-"]
        rows.append(f"| {e['file']} | {e['vertices']:,} | {e['faces']:,} | {e['components']} | "
                    f"{'/'.join(map(str, g))} | {e['min_angle_deg']:.2f} deg | {e['diameter']:.4g} | "
                    f"{100 * e['unreachable_fraction']:.1f}% | {e['gdist_seconds']:.2f} | "
                    f"{'pass' if all(v for v in e['checks'].values() if isinstance(v, bool)) else 'FAIL'} |")
    return "\n".join(rows)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="unseen", help="output folder (default: ./unseen)")
    p.add_argument("--seed", type=int, default=0, help="seed of the meshes' random shapes (default 0); the "
                   "reference sources always use np.random.default_rng(1234), as the shared references do")
    p.add_argument("--scale", type=float, default=1.0,
                   help="vertex counts times about this (default 1: ~36K, ~25K, ~6K vertices; 0.05 for a quick test)")
    p.add_argument("--meshes", nargs="+", default=list(MESHES), choices=MESHES, help="which meshes (default all)")
    p.add_argument("-q", "--quiet", action="store_true", help="print only the table")
    a = p.parse_args(argv)
    if not 0.01 <= a.scale <= 4:
        p.error(f"--scale must be between 0.01 and 4 (got {a.scale}): below, the parts are too coarse to be "
                "closed solids; above, the exact solves take many minutes")
    if a.seed < 0:
        p.error(f"--seed must be a non-negative integer (got {a.seed})")
    out = Path(a.out)
    if out.exists() and not out.is_dir():
        p.error(f"--out {out} is a file, not a folder: name a folder (it is created if missing)")
    if importlib.util.find_spec("gdist") is None:
        p.error("the exact references need tvb-gdist: pip install tvb-gdist (or pip install -e \".[bench]\")")
    from common import write_json

    t0 = time.perf_counter()
    entries = generate(out, a.seed, a.scale, a.meshes, a.quiet)
    total = time.perf_counter() - t0
    print(table(entries))
    print(f"total {total:.1f} s; gdist {sum(e['gdist_seconds'] for e in entries.values()):.1f} s; "
          f"written to {out}/")
    write_json(out / "manifest.json", {"seed": a.seed, "scale": a.scale, "seconds": round(total, 2),
                                       "numpy": np.__version__, "tvb_gdist": _version("tvb-gdist"),
                                       "meshes": entries}, "unseen_meshes", device="cpu")
    return 0


if __name__ == "__main__":
    sys.exit(main())
