"""Warp kernels of the generalizable NeuroGF network (encoder and query network), SIMT, CPU and CUDA.

``kernels(mode)`` returns one namespace of kernels per arithmetic mode, all in one Warp module per mode (so a
mode compiles once, about 2-5 s cold on the CPU, and loads from Warp's cache afterwards):

- ``"fp64"``: storage and accumulation in float64 (parity tests, CPU default);
- ``"fp32"``: storage and accumulation in float32 (GPU default; within 1e-5 relative of float64 on the references);
- ``"mixed"``: float32 storage, float64 accumulation (dot products and neighbour distances).

Layout: features are row-major ``(points, channels)`` 2-D arrays; weights are ``(out, in)`` with eval-mode
BatchNorm folded in (see ``neurogf_warp.generalizable.network.folded_layers``).

Why the encoder needs no per-edge matrix for most layers: an EdgeConv first layer acting on ``[f_i, f_j - f_i]``
is ``(Wa - Wb) f_i + Wb f_j + b``, so ``P = (Wa - Wb) f + b`` and ``Q = Wb f`` are computed per point and an edge
only adds ``P_i + Q_j``. For a one-layer block (block 3) ``max_j relu(P_i + Q_j) = relu(P_i + max_j Q_j)`` per
channel (ReLU and rounding are monotonic), so that block costs no per-edge work at all.
"""

from types import SimpleNamespace

import warp as wp

_CACHE: dict = {}
FUSE_WIDTH = 128  # per-point feature width and the width of ``fuse``/``head.0``
HEAD_HIDDEN = 64  # width of ``head.1``
MODES = ("fp64", "fp32", "mixed")


def kernels(mode: str = "fp64") -> SimpleNamespace:
    """The kernels for one arithmetic mode (``"fp64"``, ``"fp32"`` or ``"mixed"``), built once and cached."""
    if mode not in MODES:
        raise ValueError(f"unknown arithmetic mode {mode!r}; use one of {MODES}")
    if mode not in _CACHE:
        _CACHE[mode] = _build(mode)
    return _CACHE[mode]


def _build(mode: str) -> SimpleNamespace:
    T = wp.float64 if mode == "fp64" else wp.float32  # storage
    A = wp.float32 if mode == "fp32" else wp.float64  # accumulation
    module = f"neurogf_generalizable_{mode}"
    opts = dict(enable_backward=False, module=module)
    VF = wp.types.vector(length=FUSE_WIDTH, dtype=A)
    INF = float("inf")

    @wp.func
    def knn_scan(f: wp.array2d(dtype=T), i: int, r: int, g: int, c_off: int, nc: int, n_per: int, kk: int,
                 pd: wp.array3d(dtype=A), pi: wp.array3d(dtype=wp.int32)):
        """The kk nearest of point i among candidates [g n_per, (g+1) n_per), sorted by (distance, index), in the
        feature space of columns [c_off, c_off + nc) of f, into row r of pd/pi (inf / -1 where the chunk has
        fewer)."""
        n = f.shape[0]
        for m in range(kk):
            pd[r, g, m] = A(INF)
            pi[r, g, m] = -1
        j0 = g * n_per
        j1 = wp.min(j0 + n_per, n)
        cnt = int(0)
        worst = A(INF)
        for j in range(j0, j1):
            d = A(0.0)
            for c in range(c_off, c_off + nc):
                e = A(f[i, c]) - A(f[j, c])
                d += e * e
            # strict comparisons: among equal distances the earlier (smaller) index stays first
            if cnt < kk or d < worst:
                m = wp.min(cnt, kk - 1)
                while m > 0 and pd[r, g, m - 1] > d:
                    pd[r, g, m] = pd[r, g, m - 1]
                    pi[r, g, m] = pi[r, g, m - 1]
                    m -= 1
                pd[r, g, m] = d
                pi[r, g, m] = j
                cnt = wp.min(cnt + 1, kk)
                if cnt == kk:
                    worst = pd[r, g, kk - 1]

    @wp.kernel(**opts)
    def knn_partial(f: wp.array2d(dtype=T), c_off: int, nc: int, n_per: int, kk: int,
                    pd: wp.array3d(dtype=A), pi: wp.array3d(dtype=wp.int32)):
        """Thread (i, g): the kk nearest of point i among candidates [g n_per, (g+1) n_per), sorted by
        (distance, index), in the feature space of columns [c_off, c_off + nc) of f. pd/pi (N, G, kk) hold the
        sorted list (inf / -1 where the chunk has fewer)."""
        i, g = wp.tid()
        knn_scan(f, i, i, g, c_off, nc, n_per, kk, pd, pi)

    @wp.kernel(**opts)
    def knn_rows(f: wp.array2d(dtype=T), i0: int, c_off: int, nc: int, n_per: int, kk: int,
                 pd: wp.array3d(dtype=A), pi: wp.array3d(dtype=wp.int32)):
        """knn_partial of the points i0, i0 + 1, ... only (a chunk of rows, Ctrl-C between chunks on the CPU):
        thread (r, g) writes row r of pd/pi (views of the chunk's rows)."""
        r, g = wp.tid()
        knn_scan(f, r + i0, r, g, c_off, nc, n_per, kk, pd, pi)

    @wp.kernel(**opts)
    def knn_merge(pd: wp.array3d(dtype=A), pi: wp.array3d(dtype=wp.int32), nbr: wp.array2d(dtype=wp.int32)):
        """Thread (i, g, m): the rank of candidate m of chunk g among all chunks' candidates of point i (by
        (distance, index)); it is written to nbr[i, rank] if rank < kk. Each chunk's list is sorted, so the count
        of smaller candidates in another chunk is a binary search."""
        i, g, m = wp.tid()
        idx = pi[i, g, m]
        if idx < 0:
            return
        d = pd[i, g, m]
        kk = pd.shape[2]
        rank = m
        for h in range(pd.shape[1]):
            if h != g:
                lo = int(0)
                hi = kk
                while lo < hi:  # first position whose (d, idx) is not smaller than ours; padding (-1) is larger
                    mid = (lo + hi) // 2
                    dm = pd[i, h, mid]
                    im = pi[i, h, mid]
                    smaller = im >= 0 and (dm < d or (dm == d and im < idx))
                    if smaller:
                        lo = mid + 1
                    else:
                        hi = mid
                rank += lo
        if rank < kk:
            nbr[i, rank] = idx

    @wp.kernel(**opts)
    def linear(x: wp.array2d(dtype=T), x_off: int, w: wp.array2d(dtype=T), b: wp.array(dtype=T), relu: int,
               y: wp.array2d(dtype=T), y_off: int):
        """Thread (i, o): y[i, y_off + o] = act(b[o] + sum_c w[o, c] x[i, x_off + c]), act = ReLU if relu."""
        i, o = wp.tid()
        acc = A(b[o])
        for c in range(w.shape[1]):
            acc += A(w[o, c]) * A(x[i, x_off + c])
        if relu != 0:
            acc = wp.max(acc, A(0.0))
        y[i, y_off + o] = T(acc)

    @wp.kernel(**opts)
    def edge_two_layers(p: wp.array2d(dtype=T), q: wp.array2d(dtype=T), nbr: wp.array2d(dtype=wp.int32),
                        w: wp.array2d(dtype=T), b: wp.array(dtype=T), y: wp.array2d(dtype=T), y_off: int):
        """Thread (i, o): max over neighbours j of relu(b[o] + sum_h w[o, h] relu(p[i, h] + q[j, h]))."""
        i, o = wp.tid()
        best = A(0.0)  # every candidate is a ReLU output (>= 0), so 0 is a neutral start for the max
        for kq in range(nbr.shape[1]):
            j = nbr[i, kq]
            acc = A(b[o])
            for h in range(w.shape[1]):
                acc += A(w[o, h]) * wp.max(A(p[i, h]) + A(q[j, h]), A(0.0))
            best = wp.max(best, acc)
        y[i, y_off + o] = T(best)

    @wp.kernel(**opts)
    def edge_one_layer(p: wp.array2d(dtype=T), q: wp.array2d(dtype=T), nbr: wp.array2d(dtype=wp.int32),
                       y: wp.array2d(dtype=T), y_off: int):
        """Thread (i, o): relu(p[i, o] + max_j q[j, o]) = max_j relu(p[i, o] + q[j, o])."""
        i, o = wp.tid()
        m = A(q[nbr[i, 0], o])
        for kq in range(1, nbr.shape[1]):
            m = wp.max(m, A(q[nbr[i, kq], o]))
        y[i, y_off + o] = T(wp.max(A(p[i, o]) + m, A(0.0)))

    @wp.kernel(**opts)
    def column_max(x: wp.array2d(dtype=T), rows_per: int, y: wp.array2d(dtype=T)):
        """Thread (p, c): y[p, c] = max of x[i, c] over rows i in [p rows_per, (p+1) rows_per) (the global max
        pooling in two passes: partial maxima of row chunks, then the maximum of those, so that a GPU runs
        chunks x channels threads instead of one long loop per channel)."""
        p, c = wp.tid()
        i0 = p * rows_per
        i1 = wp.min(i0 + rows_per, x.shape[0])
        m = x[i0, c]
        for i in range(i0 + 1, i1):
            m = wp.max(m, x[i, c])
        y[p, c] = m

    @wp.func
    def nearest_brute(cloud: wp.array2d(dtype=T), x: A, y: A, z: A):
        best = A(INF)
        bi = int(0)
        for j in range(cloud.shape[0]):
            dx = A(cloud[j, 0]) - x
            dy = A(cloud[j, 1]) - y
            dz = A(cloud[j, 2]) - z
            d = dx * dx + dy * dy + dz * dz
            if d < best:  # strict: ties go to the smaller index
                best = d
                bi = j
        return bi

    @wp.func
    def nearest_point(cloud: wp.array2d(dtype=T), grid: wp.uint64, radius: float, use_grid: int,
                      x: A, y: A, z: A):
        """Index of the nearest cloud point to (x, y, z); ties -> smaller index. With the hash grid, the points of
        the cells within ``radius`` are candidates; the result is exact when the best candidate lies within
        ``radius`` (every closer point was enumerated), otherwise the search falls back to all points."""
        if use_grid == 0:
            return nearest_brute(cloud, x, y, z)
        best = A(INF)
        bi = int(-1)
        qp = wp.vec3(float(x), float(y), float(z))
        query = wp.hash_grid_query(grid, qp, radius)
        j = int(0)
        while wp.hash_grid_query_next(query, j):
            dx = A(cloud[j, 0]) - x
            dy = A(cloud[j, 1]) - y
            dz = A(cloud[j, 2]) - z
            d = dx * dx + dy * dy + dz * dz
            if d < best or (d == best and j < bi):
                best = d
                bi = j
        # 0.999: a margin for the float32 cell arithmetic of the grid
        r = A(radius) * A(0.999)
        if bi < 0 or best > r * r:
            return nearest_brute(cloud, x, y, z)
        return bi

    @wp.kernel(**opts)
    def nearest(cloud: wp.array2d(dtype=T), grid: wp.uint64, radius: float, use_grid: int,
                pts: wp.array2d(dtype=T), out: wp.array(dtype=wp.int32)):
        """Thread m: the index of the cloud point nearest to pts[m]."""
        m = wp.tid()
        out[m] = nearest_point(cloud, grid, radius, use_grid, A(pts[m, 0]), A(pts[m, 1]), A(pts[m, 2]))

    @wp.kernel(**opts)
    def nearest_user(cloud: wp.array2d(dtype=T), grid: wp.uint64, radius: float, use_grid: int,
                     pts: wp.array2d(dtype=T), cx: wp.float64, cy: wp.float64, cz: wp.float64, scale: wp.float64,
                     out: wp.array(dtype=wp.int32)):
        """Thread m: the nearest cloud point of pts[m] given in user units; the unit-frame coordinates are
        rounded exactly as ``pair_distance`` rounds them, so both paths pick the same point."""
        m = wp.tid()
        sc_ = A(scale)
        out[m] = nearest_point(cloud, grid, radius, use_grid, (A(pts[m, 0]) - A(cx)) * sc_,
                               (A(pts[m, 1]) - A(cy)) * sc_, (A(pts[m, 2]) - A(cz)) * sc_)

    @wp.func
    def fuse_diff(g: wp.array2d(dtype=T), wx: wp.array2d(dtype=T), i_s: int, i_t: int,
                  sx: A, sy: A, sz: A, tx: A, ty: A, tz: A):
        """|fuse(s) - fuse(t)| (128) with fuse(q) = relu(G[nn(q)] + Wx q), G = W_F F + b precomputed per point."""
        d = VF()
        for c in range(FUSE_WIDTH):
            a = A(g[i_s, c]) + A(wx[c, 0]) * sx + A(wx[c, 1]) * sy + A(wx[c, 2]) * sz
            e = A(g[i_t, c]) + A(wx[c, 0]) * tx + A(wx[c, 1]) * ty + A(wx[c, 2]) * tz
            d[c] = wp.abs(wp.max(a, A(0.0)) - wp.max(e, A(0.0)))
        return d

    @wp.func
    def head(d: VF, w0: wp.array2d(dtype=T), b0: wp.array(dtype=T), w1: wp.array2d(dtype=T),
             b1: wp.array(dtype=T), w2: wp.array2d(dtype=T)):
        """head: 128 -> 128 (ReLU) -> 64 (ReLU) -> 1 (plain), weights folded."""
        h = VF()
        for o in range(FUSE_WIDTH):
            acc = A(b0[o])
            for c in range(FUSE_WIDTH):
                acc += A(w0[o, c]) * d[c]
            h[o] = wp.max(acc, A(0.0))
        r = A(0.0)
        for o in range(HEAD_HIDDEN):
            acc = A(b1[o])
            for c in range(FUSE_WIDTH):
                acc += A(w1[o, c]) * h[c]
            r += A(w2[0, o]) * wp.max(acc, A(0.0))
        return r

    @wp.kernel(**opts)
    def pair_ratio(cloud: wp.array2d(dtype=T), grid: wp.uint64, radius: float, use_grid: int,
                   g: wp.array2d(dtype=T), wx: wp.array2d(dtype=T),
                   w0: wp.array2d(dtype=T), b0: wp.array(dtype=T), w1: wp.array2d(dtype=T),
                   b1: wp.array(dtype=T), w2: wp.array2d(dtype=T),
                   s: wp.array2d(dtype=T), t: wp.array2d(dtype=T), ratio: wp.array(dtype=T)):
        """Thread m: the network's ratio for the pair (s[m], t[m]) (unit-sphere frame), raw (no clamping)."""
        m = wp.tid()
        sx = A(s[m, 0])
        sy = A(s[m, 1])
        sz = A(s[m, 2])
        tx = A(t[m, 0])
        ty = A(t[m, 1])
        tz = A(t[m, 2])
        i_s = nearest_point(cloud, grid, radius, use_grid, sx, sy, sz)
        i_t = nearest_point(cloud, grid, radius, use_grid, tx, ty, tz)
        d = fuse_diff(g, wx, i_s, i_t, sx, sy, sz, tx, ty, tz)
        ratio[m] = T(head(d, w0, b0, w1, b1, w2))

    @wp.kernel(**opts)
    def pair_distance(cloud: wp.array2d(dtype=T), grid: wp.uint64, radius: float, use_grid: int,
                      g: wp.array2d(dtype=T), wx: wp.array2d(dtype=T),
                      w0: wp.array2d(dtype=T), b0: wp.array(dtype=T), w1: wp.array2d(dtype=T),
                      b1: wp.array(dtype=T), w2: wp.array2d(dtype=T),
                      s: wp.array2d(dtype=T), si: wp.array(dtype=wp.int32), sc: wp.array(dtype=wp.int32),
                      t: wp.array2d(dtype=T), ti: wp.array(dtype=wp.int32), tc: wp.array(dtype=wp.int32),
                      cx: wp.float64, cy: wp.float64, cz: wp.float64, scale: wp.float64, n_t: int,
                      out: wp.array(dtype=wp.float32)):
        """Thread m: pair (s[m // n_t], t[m % n_t]) when n_t > 0 (a source x target matrix), else (s[m], t[m]).

        s, t are in user units; the unit frame is ``(x - c) * scale``. Distance (user units) =
        max(ratio, 1) * |s - t|: a geodesic is never shorter than the straight segment, so ratios below 1
        (network error) are raised to 1; exactly 0 for s == t, never negative. ``si``/``ti``: the nearest cloud
        point of each point if precomputed (length > 0), else found here. ``sc``/``tc``: connected-component
        labels (length 0: one component); different labels give +inf.
        """
        m = wp.tid()
        a = m
        bb = m
        if n_t > 0:
            a = m / n_t
            bb = m - a * n_t
        if sc.shape[0] > 0:
            if sc[a] != tc[bb]:
                out[m] = wp.inf
                return
        ux = A(s[a, 0])
        uy = A(s[a, 1])
        uz = A(s[a, 2])
        vx = A(t[bb, 0])
        vy = A(t[bb, 1])
        vz = A(t[bb, 2])
        ex = ux - vx
        ey = uy - vy
        ez = uz - vz
        e2 = ex * ex + ey * ey + ez * ez
        if e2 == A(0.0):
            out[m] = 0.0
            return
        sc_ = A(scale)
        sx = (ux - A(cx)) * sc_
        sy = (uy - A(cy)) * sc_
        sz = (uz - A(cz)) * sc_
        tx = (vx - A(cx)) * sc_
        ty = (vy - A(cy)) * sc_
        tz = (vz - A(cz)) * sc_
        i_s = int(0)
        i_t = int(0)
        if si.shape[0] > 0:
            i_s = si[a]
        else:
            i_s = nearest_point(cloud, grid, radius, use_grid, sx, sy, sz)
        if ti.shape[0] > 0:
            i_t = ti[bb]
        else:
            i_t = nearest_point(cloud, grid, radius, use_grid, tx, ty, tz)
        d = fuse_diff(g, wx, i_s, i_t, sx, sy, sz, tx, ty, tz)
        r = wp.max(head(d, w0, b0, w1, b1, w2), A(1.0))
        out[m] = float(r * wp.sqrt(e2))

    @wp.kernel(**opts)
    def to_unit(x: wp.array2d(dtype=T), cx: wp.float64, cy: wp.float64, cz: wp.float64, scale: wp.float64,
                y: wp.array2d(dtype=T), v: wp.array(dtype=wp.vec3)):
        """Thread i: y[i] = (x[i] - c) * scale (storage dtype) and its float32 vec3 copy (for the hash grid)."""
        i = wp.tid()
        a = (wp.float64(x[i, 0]) - cx) * scale
        b = (wp.float64(x[i, 1]) - cy) * scale
        c = (wp.float64(x[i, 2]) - cz) * scale
        y[i, 0] = T(a)
        y[i, 1] = T(b)
        y[i, 2] = T(c)
        v[i] = wp.vec3(float(a), float(b), float(c))

    @wp.kernel(**opts)
    def point_component(mesh: wp.uint64, x: wp.array2d(dtype=T), cx: wp.float64, cy: wp.float64,
                        cz: wp.float64, scale: wp.float64, face_comp: wp.array(dtype=wp.int32),
                        out: wp.array(dtype=wp.int32)):
        """Thread i: the connected component of the mesh triangle closest to x[i] (user units; the wp.Mesh is in
        the unit frame)."""
        i = wp.tid()
        p = wp.vec3(float((wp.float64(x[i, 0]) - cx) * scale), float((wp.float64(x[i, 1]) - cy) * scale),
                    float((wp.float64(x[i, 2]) - cz) * scale))
        q = wp.mesh_query_point_no_sign(mesh, p, 1.0e30)
        if q.result:
            out[i] = face_comp[q.face]
        else:
            out[i] = -1

    return SimpleNamespace(mode=mode, dtype=T, acc=A, module=module, knn_partial=knn_partial, knn_rows=knn_rows, knn_merge=knn_merge,
                           linear=linear, edge_two_layers=edge_two_layers, edge_one_layer=edge_one_layer,
                           column_max=column_max, nearest=nearest, nearest_user=nearest_user, nearest_point_func=nearest_point,
                           nearest_brute_func=nearest_brute, pair_ratio=pair_ratio,
                           pair_distance=pair_distance, to_unit=to_unit,
                           point_component=point_component)
