"""Constructed meshes for the geodesic-solver tests, with their exact distances where these are analytic.

Every builder returns plain arrays (vertices (n, 3) float64, faces (m, 3) int64) in the builder's own units.
The non-manifold cases: flat discs glued at their centres (a vertex whose faces form two fans), spheres touching
at one vertex, a book of flat pages on one spine (edges with three or more faces), a sphere with fins; the
boundary case: an ellipsoid with holes cut and slivers added by splitting edges close to an end.
"""
from __future__ import annotations

import numpy as np


def grid_square(n=10, seed=0):
    """The unit square in z = 0 as an n x n grid, each cell split along a random diagonal."""
    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
    V = np.c_[x.ravel(), y.ravel(), np.zeros(n * n)]
    rng = np.random.default_rng(seed)
    F = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, i * n + j + 1, (i + 1) * n + j, (i + 1) * n + j + 1
            F += [[a, c, b], [b, c, d]] if rng.random() < 0.5 else [[a, c, d], [a, d, b]]
    return V, np.array(F)


def cylinder(nu=24, nv=8, r=1.0, h=2.0):
    """An open prism (nu sides, nv rings) around the z axis."""
    th = np.linspace(0, 2 * np.pi, nu, endpoint=False)
    z = np.linspace(0, h, nv)
    V = np.array([[r * np.cos(t), r * np.sin(t), zz] for zz in z for t in th])
    F = []
    for j in range(nv - 1):
        for i in range(nu):
            a, b = j * nu + i, j * nu + (i + 1) % nu
            F += [[a, b, b + nu], [a, b + nu, a + nu]]
    return V, np.array(F)


def squashed_square(n=16, seed=1, m=60):
    """A flat jittered grid (exact geodesics = straight lines) where m interior vertices are slid onto (t=0:
    coincident), or to 1e-9 / 1e-6 / 1e-4 of, a neighbour: zero-area faces, needles, caps, zero-length edges."""
    V, F = grid_square(n, seed)
    rng = np.random.default_rng(seed)
    interior = [i * n + j for i in range(1, n - 1) for j in range(1, n - 1)]
    moved = set()
    for i in rng.permutation(interior)[:m]:
        nb = [j for j in np.unique(F[(F == i).any(1)]) if j != i and j not in moved]
        if nb:
            j = rng.choice(nb)
            V[i] = V[j] + rng.choice([0.0, 1e-9, 1e-6, 1e-4]) * (V[i] - V[j])
            moved.add(i)
    return V, F


def icosphere(subdivisions=2, axes=(1.0, 1.0, 1.0)):
    """A closed icosphere scaled to an ellipsoid with the given semi-axes."""
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=subdivisions)
    return np.asarray(s.vertices) * np.asarray(axes, dtype=np.float64), np.asarray(s.faces, dtype=np.int64)


def _disc(rings=5, sectors=12, radius=1.0, seed=0):
    """A flat convex polygonal disc in the plane (x, y): centre vertex 0, `rings` rings of `sectors` vertices,
    slightly jittered inside the rings (the outer ring stays on a regular polygon, so the disc is convex)."""
    rng = np.random.default_rng(seed)
    P = [[0.0, 0.0]]
    for r in range(1, rings + 1):
        th = 2 * np.pi * (np.arange(sectors) + 0.5 * (r % 2)) / sectors
        rad = radius * r / rings
        if r < rings:
            th = th + rng.uniform(-0.15, 0.15, sectors) * 2 * np.pi / sectors
            rad = rad * (1 + rng.uniform(-0.08, 0.08, sectors))
        P += list(np.c_[rad * np.cos(th), rad * np.sin(th)])
    import scipy.spatial

    P = np.asarray(P)
    F = scipy.spatial.Delaunay(P).simplices
    # counter-clockwise seen from +z
    a, b, c = P[F[:, 0]], P[F[:, 1]], P[F[:, 2]]
    cw = (b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0] < 0
    F[cw] = F[cw][:, [0, 2, 1]]
    return P, F.astype(np.int64)


def pinched_discs(rings=5, sectors=12):
    """Two flat discs glued at their centres only (vertex 0): disc A in z = 0, disc B in x = 0, unit radius.

    Returns V, F and the disc of each vertex (0 or 1; the shared centre is 0). Exact distances: straight lines
    inside a disc, through the centre between discs (`pinched_discs_distances`)."""
    Pa, Fa = _disc(rings, sectors, seed=0)
    Pb, Fb = _disc(rings, sectors, seed=1)
    Va = np.c_[Pa, np.zeros(len(Pa))]
    Vb = np.c_[np.zeros(len(Pb)), Pb]
    nb = np.arange(len(Pb)) + len(Pa) - 1
    nb[0] = 0
    V = np.concatenate([Va, Vb[1:]])
    F = np.concatenate([Fa, nb[Fb]])
    disc = np.r_[np.zeros(len(Pa), int), np.ones(len(Pb) - 1, int)]
    return V, F, disc


def pinched_discs_distances(V, disc, sources):
    """(S, n) exact distances on `pinched_discs`: Euclidean within a disc, via the centre (vertex 0) across."""
    out = []
    for s in np.atleast_1d(sources):
        direct = np.linalg.norm(V - V[s], axis=1)
        via = np.linalg.norm(V[s] - V[0]) + np.linalg.norm(V - V[0], axis=1)
        same = (disc == disc[s]) | (np.arange(len(V)) == 0) | (s == 0)
        out.append(np.where(same, direct, via))
    return np.array(out)


def pinched_spheres(subdivisions=2):
    """Two unit icospheres touching at one vertex p (vertex 0): the second is the first mirrored in the tangent
    plane at p. Geodesics between them pass through p (exact reference: `reference_geodesics.exact_distances`)."""
    V, F = icosphere(subdivisions)
    n = V[0] / np.linalg.norm(V[0])
    W = V - 2.0 * ((V @ n) - 1.0)[:, None] * n  # mirror in the plane x . n = 1 (p stays where it is)
    idx = np.arange(len(V)) + len(V) - 1
    idx[0] = 0
    return np.concatenate([V, W[1:]]), np.concatenate([F, idx[F][:, [0, 2, 1]]])


def book(pages=3, nu=5, nv=7, width=1.0, length=1.4, seed=0):
    """Flat rectangular pages [0, width] x [0, length] sharing their edge u = 0 (the spine, along y).

    Page i lies in the half-plane at angle 2 pi i / (pages + 1) around the y axis, so every spine edge has
    `pages` faces. Returns V, F, uv (n, 2) page coordinates and the page of each vertex (-1 on the spine)."""
    rng = np.random.default_rng(seed)
    u = np.linspace(0, width, nu)
    y = np.linspace(0, length, nv)
    spine = np.arange(nv)  # spine vertices first: (0, y_j)
    V = [np.c_[np.zeros(nv), y, np.zeros(nv)]]
    uv = [np.c_[np.zeros(nv), y]]
    page = [np.full(nv, -1)]
    F = []
    n = nv
    for p in range(pages):
        th = 2 * np.pi * p / (pages + 1)
        ids = np.empty((nu, nv), dtype=np.int64)
        ids[0] = spine
        ids[1:] = n + np.arange((nu - 1) * nv).reshape(nu - 1, nv)
        n += (nu - 1) * nv
        uu, yy = np.meshgrid(u[1:], y, indexing="ij")
        uu = uu.ravel()
        yy = yy.ravel()
        V.append(np.c_[uu * np.cos(th), yy, uu * np.sin(th)])
        uv.append(np.c_[uu, yy])
        page.append(np.full(len(uu), p))
        for i in range(nu - 1):
            for j in range(nv - 1):
                a, b, c, d = ids[i, j], ids[i, j + 1], ids[i + 1, j], ids[i + 1, j + 1]
                F += [[a, c, b], [b, c, d]] if rng.random() < 0.5 else [[a, c, d], [a, d, b]]
    return np.concatenate(V), np.array(F, dtype=np.int64), np.concatenate(uv), np.concatenate(page)


def book_distances(uv, page, sources):
    """(S, n) exact distances on `book`: Euclidean on one page; between pages the two pages unfold into one
    plane around the spine (u -> -u), where the straight line always crosses the spine inside the book."""
    out = []
    for s in np.atleast_1d(sources):
        du = np.abs(uv[:, 0] - uv[s, 0])
        across = (page != page[s]) & (page >= 0) & (page[s] >= 0)
        du = np.where(across, uv[:, 0] + uv[s, 0], du)
        out.append(np.hypot(du, uv[:, 1] - uv[s, 1]))
    return np.array(out)


def finned_sphere(subdivisions=3, fins=4, axes=(1.0, 0.8, 0.6), seed=0):
    """An ellipsoid with `fins` flat fins: each fin is a quad (two triangles) standing on one mesh edge, so that
    edge has three faces. Returns V, F and the number of ellipsoid vertices (fin vertices come after them)."""
    V, F = icosphere(subdivisions, axes)
    rng = np.random.default_rng(seed)
    nv = len(V)
    used = set()
    Vs, Fs = [V], [F]
    n = nv
    for f in rng.permutation(len(F)):
        if len(Fs) - 1 == fins:
            break
        a, b = int(F[f, 0]), int(F[f, 1])
        if a in used or b in used:
            continue
        used.update((a, b))
        out = V[a] + V[b]
        out = 0.15 * out / np.linalg.norm(out)
        Vs.append(np.array([V[b] + out, V[a] + out]))
        Fs.append(np.array([[a, b, n], [a, n, n + 1]]))
        n += 2
    return np.concatenate(Vs), np.concatenate(Fs), nv


def split_edges(V, F, count, ts=(1e-4, 1e-3, 1e-2, 3e-2), seed=0):
    """Split `count` random edges at a parameter t from one end (t drawn from ts): every split face becomes a
    needle and a fat triangle. The surface is unchanged (the new vertex lies on the edge); the first len(V)
    vertices keep their numbering."""
    rng = np.random.default_rng(seed)
    V = [np.asarray(V, dtype=np.float64)]
    F = np.asarray(F, dtype=np.int64).copy()
    n = len(V[0])
    P = V[0]
    for _ in range(count):
        f = rng.integers(len(F))
        le = rng.integers(3)
        a, b = F[f, le], F[f, (le + 1) % 3]
        t = rng.choice(ts)
        p = P[a] + t * (P[b] - P[a])
        new = []
        for g in np.where((F == a).any(1) & (F == b).any(1))[0]:
            row = F[g]
            i = int(np.where(row == a)[0][0])
            j = int(np.where(row == b)[0][0])
            c = row[3 - i - j]
            if (j - i) % 3 == 1:  # a -> b in this face's order
                new += [[a, n, c], [n, b, c]]
            else:
                new += [[b, n, c], [n, a, c]]
        keep = ~((F == a).any(1) & (F == b).any(1))
        F = np.concatenate([F[keep], np.array(new, dtype=np.int64)])
        P = np.concatenate([P, p[None]])
        n += 1
    return P, F


def holed_ellipsoid(subdivisions=3, holes=10, radius=0.25, axes=(1.0, 0.8, 0.6), seed=0):
    """An ellipsoid with `holes` round holes cut out (faces whose centroid is near a random centre): an open
    mesh with many boundary loops. Unreferenced vertices are dropped, so vertices are renumbered 0..n-1."""
    V, F = icosphere(subdivisions)
    rng = np.random.default_rng(seed)
    c = rng.standard_normal((holes, 3))
    c /= np.linalg.norm(c, axis=1, keepdims=True)
    cen = V[F].mean(1)
    cen /= np.linalg.norm(cen, axis=1, keepdims=True)
    keep = np.min(np.linalg.norm(cen[:, None] - c[None], axis=2), axis=1) > radius
    F = F[keep]
    used = np.unique(F)
    remap = np.full(len(V), -1)
    remap[used] = np.arange(len(used))
    return V[used] * np.asarray(axes), remap[F]


def scattered_parts(count=44, seed=0):
    """`count` small closed meshes (icospheres and boxes) placed apart: a mesh with `count` components.
    Returns V, F and the part of each vertex."""
    import trimesh

    rng = np.random.default_rng(seed)
    Vs, Fs, part = [], [], []
    n = 0
    for i in range(count):
        m = trimesh.creation.icosphere(subdivisions=1) if i % 2 == 0 else trimesh.creation.box()
        v = np.asarray(m.vertices) * rng.uniform(0.3, 0.6) + np.array([3.0 * (i % 7), 3.0 * (i // 7), 0.0])
        Vs.append(v)
        Fs.append(np.asarray(m.faces) + n)
        part.append(np.full(len(v), i))
        n += len(v)
    return np.concatenate(Vs), np.concatenate(Fs), np.concatenate(part)


# ---- hard mesh classes (exact reference: tvb-gdist, float64) -------------------------------------------------

STRETCHES = {"stretched-0.01": (1.0, 0.01, 0.01), "stretched-100-1-0.01": (100.0, 1.0, 0.01),
             "stretched-1e-4": (1.0, 1e-4, 1e-4)}


def duplicated_faces(subdivisions=2, count=60, seed=0):
    """An icosphere with `count` of its faces added a second time (same three vertices, same order): every edge
    of a duplicated face has three or more faces and its two copies coincide."""
    V, F = icosphere(subdivisions)
    rng = np.random.default_rng(seed)
    dup = F[rng.choice(len(F), count, replace=False)]
    return V, np.concatenate([F, dup])


def slivered(subdivisions=2, count=40, lift=1e-3, seed=0):
    """An icosphere with `count` near-flat caps (slivers: three almost collinear vertices). Each cap comes from
    splitting an edge ab at its midpoint n, lifting n off the edge by `lift` x |ab| (outwards), and flipping the
    new edge nc of one side, so that the triangle (a, n, b) appears with height lift x |ab|."""
    V, F = icosphere(subdivisions)
    rng = np.random.default_rng(seed)
    V = [p for p in V]
    F = [list(f) for f in F]
    used = set()
    for _ in range(count):
        for _try in range(100):
            f = int(rng.integers(len(F)))
            le = int(rng.integers(3))
            a, b, c = F[f][le], F[f][(le + 1) % 3], F[f][(le + 2) % 3]
            if not ({a, b, c} & used):
                break
        others = [g for g, h in enumerate(F) if g != f and a in h and b in h]
        if len(others) != 1:
            continue
        g = others[0]
        d = [x for x in F[g] if x not in (a, b)][0]
        used.update((a, b, c, d))
        mid = 0.5 * (V[a] + V[b])
        n = len(V)
        V.append(mid + lift * np.linalg.norm(V[b] - V[a]) * mid / np.linalg.norm(mid))
        # face f (a, b, c) split at n into (a, n, c) + (n, b, c), then the edge n-c flipped: (a, n, b) + (a, b, c)
        F[f] = [a, n, b]
        F.append([a, b, c])
        # the other face (b, a, d) is split at n: (b, n, d) + (n, a, d)
        F[g] = [b, n, d]
        F.append([n, a, d])
    return np.asarray(V), np.asarray(F, dtype=np.int64)


def fan_cylinder(sectors=48, radius=0.5, height=2.0):
    """A closed CAD-like cylinder: two rings of `sectors` vertices and nothing between them (long thin side
    triangles, aspect about height / (2 pi radius / sectors)), each cap a fan around its centre vertex."""
    th = 2 * np.pi * np.arange(sectors) / sectors
    ring = np.c_[radius * np.cos(th), radius * np.sin(th)]
    V = np.concatenate([np.c_[ring, np.zeros(sectors)], np.c_[ring, np.full(sectors, height)],
                        [[0.0, 0.0, 0.0], [0.0, 0.0, height]]])
    F = []
    c0, c1 = 2 * sectors, 2 * sectors + 1
    for i in range(sectors):
        j = (i + 1) % sectors
        F += [[i, j, sectors + j], [i, sectors + j, sectors + i], [c0, j, i], [c1, sectors + i, sectors + j]]
    return V, np.asarray(F, dtype=np.int64)


def fan_box(n=4, size=(2.0, 1.0, 0.3)):
    """A closed CAD-like box: every face a fan around its centre over `n` boundary segments per side (few large
    triangles; on the long faces thin ones, aspect up to about size ratio x n)."""
    import trimesh

    g = np.linspace(0.0, 1.0, n + 1)[:-1]
    loop = [(t, 0.0) for t in g] + [(1.0, t) for t in g] + [(1 - t, 1.0) for t in g] + [(0.0, 1 - t) for t in g]
    pts, faces = [], []
    for axis in range(3):
        for side in (0.0, 1.0):
            u, v = (axis + 1) % 3, (axis + 2) % 3
            base = len(pts)
            for a, b in [(0.5, 0.5)] + loop:
                p = np.zeros(3)
                p[axis], p[u], p[v] = side, a, b
                pts.append(p)
            m = len(loop)
            for i in range(m):
                f = [base, base + 1 + i, base + 1 + (i + 1) % m]
                faces.append(f if side == 1.0 else f[::-1])
    tm = trimesh.Trimesh(np.asarray(pts) * np.asarray(size), np.asarray(faces), process=True)  # welds the seams
    trimesh.repair.fix_normals(tm)
    return np.asarray(tm.vertices, dtype=np.float64), np.asarray(tm.faces, dtype=np.int64)


def mesh_classes():
    """name -> (V, F, R): one small mesh of each hard class (stretched, needles, slivers, duplicated faces,
    coarse CAD-like fans) and R, the faces of the same surface that the exact reference (tvb-gdist,
    `reference_geodesics.gdist_distances`) runs on: F itself, except for duplicated faces (gdist needs a manifold;
    the copies add no surface, so the icosphere's own faces give the same distances)."""
    out = {name: icosphere(2, axes) for name, axes in STRETCHES.items()}
    out["needles"] = split_edges(*icosphere(2, (1.0, 0.8, 0.6)), 60)
    out["slivers"] = slivered()
    out["fan-cylinder"] = fan_cylinder()
    out["fan-box"] = fan_box()
    out = {name: (V, F, F) for name, (V, F) in out.items()}
    V, F = duplicated_faces()
    out["duplicated-faces"] = (V, F, F[: len(F) - 60])
    return out
