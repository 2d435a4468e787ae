"""Exact nearest cloud point through a dense candidate grid (an alternative to the hash-grid lookup).

The unit-frame box [-BOX, BOX]^3 is cut into G^3 cubic cells. Each cell lists the cloud points that can be the
nearest point of some query inside it: with U = min over points p of the largest distance from p to the cell
(so every query in the cell has a point within sqrt(U)), a point p is a candidate when its smallest distance to
the cell is at most sqrt(U) (squared, with a relative margin of MARGIN for rounding). The cells are inflated by
PAD on every side, so a query whose float32 cell index is off by one at a boundary is still inside its cell.

A query then scans only its cell's list (float32 storage: entries (x, y, z, index), one 16-byte load each;
float64: indices) with the exact distance formula and tie rule of ``nearest_point``
(``kernels/generalizable/__init__.py``: squared distance in the mode's accumulation type, ties -> the smaller
index), so it returns the same index as the brute-force scan: every point whose distance is (within rounding)
the smallest is in the list. Queries outside the box, or in a cell whose list did not fit the candidate
buffer, fall back to the brute-force scan.

Build (``build``): three fills, four launches and a prefix sum, no host synchronisation: (1) U per cell (threads
over cells x point chunks, atomic min), (2) candidate counts of the cells near the cloud (LIST_CELLS), (3) caps
(MAX_LIST), (4) exclusive scan -> list starts, (5) the lists (each thread reserves its range with one atomic
add; the order inside a list does not matter for the (distance, index) rule). Cost: G^3 N box-distance tests
plus twice those of the kept cells (G = 23, N = 2,048: 25 M + 2 x ~7 M); it is built lazily, on the first query.
"""
from types import SimpleNamespace

import numpy as np
import warp as wp

from . import kernels as base_kernels

BOX = 1.1  # half-width of the gridded unit-frame box (the cloud lies in the unit sphere; queries near it)
PAD = 1.0e-4  # cells are inflated by this much on every side (unit frame)
MARGIN = 1.0e-4  # relative margin of the candidate test on squared distances
CHUNK = 128  # cloud points per build thread
LIST_CELLS = 3.0  # a cell keeps a list only when every query in it has a point within LIST_CELLS cell widths
# (sqrt(U) <= LIST_CELLS h); other cells are far from the cloud (> ~2 h) and their queries scan every point, as
# the hash-grid lookup does beyond its radius. Measured on benchmarks/generalizable.py's shapes (256 - 4,096
# points, 20,000 queries at 1% noise): the queried cells have sqrt(U) <= 2.4 h; their lists hold 32-35
# candidates on average (at most ~110), and the kept lists 5-14 entries per grid cell in all.
MAX_LIST = 160  # a cell with more candidates keeps no list either
CAND_PER_CELL, CAND_PER_POINT = 24, 128  # candidate buffer: max(24 G^3, 128 N) entries (lists past its end fall
# back; measured totals: 67-81 N)

_CACHE: dict = {}


def grid_cells(n_points: int) -> int:
    """Cells per axis for a cloud of n points: about half a point spacing of a surface cloud, 8 .. 32."""
    return int(min(32, max(8, round(0.5 * np.sqrt(n_points)))))


def kernels(mode: str) -> SimpleNamespace:
    """Build and query kernels for the storage/accumulation types of one arithmetic mode (as ``kernels(mode)``)."""
    if mode not in _CACHE:
        _CACHE[mode] = _build(mode)
    return _CACHE[mode]


def _build(mode: str) -> SimpleNamespace:
    base = base_kernels(mode)  # the mode's storage and accumulation types, and its brute-force scan
    T, A = base.dtype, base.acc
    opts = dict(enable_backward=False, module=f"neurogf_generalizable_nngrid_{mode}")
    # float32 storage: a list entry is the point itself (x, y, z, index), one 16-byte load per candidate instead
    # of an index and three gathers; the coordinates are the cloud's float32 values, so distances are the same
    INLINE = T == wp.float32
    C = wp.vec4 if INLINE else wp.int32
    INF = float("inf")

    @wp.func
    def cell_box(c: int, G: int, h: float):
        iz = c % G
        iy = (c / G) % G
        ix = c / (G * G)
        lo = wp.vec3(-BOX + float(ix) * h - PAD, -BOX + float(iy) * h - PAD, -BOX + float(iz) * h - PAD)
        hi = wp.vec3(-BOX + float(ix + 1) * h + PAD, -BOX + float(iy + 1) * h + PAD, -BOX + float(iz + 1) * h + PAD)
        return lo, hi

    @wp.func
    def point(cloud: wp.array2d(dtype=T), j: int):
        return wp.vec3(float(cloud[j, 0]), float(cloud[j, 1]), float(cloud[j, 2]))

    @wp.func
    def far2(p: wp.vec3, lo: wp.vec3, hi: wp.vec3):
        d = wp.max(wp.abs(p - lo), wp.abs(p - hi))
        return wp.dot(d, d)

    @wp.func
    def near2(p: wp.vec3, lo: wp.vec3, hi: wp.vec3):
        d = wp.max(wp.max(lo - p, wp.vec3(0.0)), p - hi)
        return wp.dot(d, d)

    @wp.kernel(**opts)
    def cell_bound(cloud: wp.array2d(dtype=T), G: int, h: float, U: wp.array(dtype=float)):
        """Thread (cell, chunk): U[cell] = min over the chunk's points of the squared distance to the cell's
        farthest corner (atomic min; U starts at +inf)."""
        c, k = wp.tid()
        lo, hi = cell_box(c, G, h)
        j1 = wp.min((k + 1) * CHUNK, cloud.shape[0])
        best = float(INF)
        for j in range(k * CHUNK, j1):
            best = wp.min(best, far2(point(cloud, j), lo, hi))
        wp.atomic_min(U, c, best)

    @wp.func
    def is_candidate(d2: float, u: float):
        return d2 <= u * (1.0 + MARGIN) + 1.0e-12

    @wp.func
    def chunk_candidates(cloud: wp.array2d(dtype=T), j0: int, j1: int, lo: wp.vec3, hi: wp.vec3, u: float):
        """How many of the points j0 .. j1 - 1 can be nearest to some point of the box [lo, hi]."""
        n = int(0)
        for j in range(j0, j1):
            if is_candidate(near2(point(cloud, j), lo, hi), u):
                n += 1
        return n

    @wp.kernel(**opts)
    def cell_count(cloud: wp.array2d(dtype=T), G: int, h: float, U: wp.array(dtype=float),
                   count: wp.array(dtype=wp.int32)):
        """Thread (cell, chunk): count[cell] += the chunk's candidates (count starts at 0)."""
        c, k = wp.tid()
        u = U[c]
        if u > (LIST_CELLS * h) * (LIST_CELLS * h):
            return
        lo, hi = cell_box(c, G, h)
        j1 = wp.min((k + 1) * CHUNK, cloud.shape[0])
        n = chunk_candidates(cloud, k * CHUNK, j1, lo, hi, u)
        if n > 0:
            wp.atomic_add(count, c, n)

    @wp.kernel(**opts)
    def cell_cap(U: wp.array(dtype=float), count: wp.array(dtype=wp.int32)):
        """Thread c: a cell with more than MAX_LIST candidates keeps no list (count 0, no candidate passes)."""
        c = wp.tid()
        if count[c] > MAX_LIST:
            count[c] = 0
            U[c] = -1.0

    @wp.kernel(**opts)
    def cell_fill(cloud: wp.array2d(dtype=T), G: int, h: float, U: wp.array(dtype=float),
                  start: wp.array(dtype=wp.int32), fill: wp.array(dtype=wp.int32), cand: wp.array(dtype=C)):
        """Thread (cell, chunk): writes the chunk's candidates into cand[start[cell] ...] (fill starts at 0);
        entries past the buffer are dropped (the query then scans every point for that cell)."""
        c, k = wp.tid()
        u = U[c]
        if u < 0.0 or u > (LIST_CELLS * h) * (LIST_CELLS * h):
            return
        lo, hi = cell_box(c, G, h)
        j1 = wp.min((k + 1) * CHUNK, cloud.shape[0])
        n = chunk_candidates(cloud, k * CHUNK, j1, lo, hi, u)
        if n == 0:
            return
        s = start[c] + wp.atomic_add(fill, c, n)
        for j in range(k * CHUNK, j1):
            if is_candidate(near2(point(cloud, j), lo, hi), u):
                if s < cand.shape[0]:
                    if wp.static(INLINE):
                        cand[s] = wp.vec4(float(cloud[j, 0]), float(cloud[j, 1]), float(cloud[j, 2]), float(j))
                    else:
                        cand[s] = j
                s += 1

    # the scan the hash-grid lookup falls back to, the same function: the same index on every input
    nearest_brute = base.nearest_brute_func

    @wp.func
    def nearest_point(cloud: wp.array2d(dtype=T), G: int, h: float, start: wp.array(dtype=wp.int32),
                      count: wp.array(dtype=wp.int32), cand: wp.array(dtype=C), x: A, y: A, z: A):
        """Index of the cloud point nearest to (x, y, z) (unit frame), ties -> the smaller index."""
        inv = 1.0 / h
        fx = (float(x) + BOX) * inv
        fy = (float(y) + BOX) * inv
        fz = (float(z) + BOX) * inv
        g = float(G)
        if not (fx >= 0.0 and fx < g and fy >= 0.0 and fy < g and fz >= 0.0 and fz < g):  # NaN too
            return nearest_brute(cloud, x, y, z)
        c = (int(fx) * G + int(fy)) * G + int(fz)
        s = start[c]
        e = s + count[c]
        if e > cand.shape[0]:
            return nearest_brute(cloud, x, y, z)
        best = A(INF)
        bi = int(-1)
        for q in range(s, e):
            j = int(0)
            d = A(0.0)
            if wp.static(INLINE):
                v = cand[q]
                j = int(v[3])
                dx = A(v[0]) - x
                dy = A(v[1]) - y
                dz = A(v[2]) - z
                d = dx * dx + dy * dy + dz * dz
            else:
                j = cand[q]
                dx = A(cloud[j, 0]) - x
                dy = A(cloud[j, 1]) - y
                dz = A(cloud[j, 2]) - z
                d = dx * dx + dy * dy + dz * dz
            if d < best or (d == best and j < bi):
                best = d
                bi = j
        if bi < 0:  # no list (MAX_LIST; a cell always has a candidate: the point that gives U)
            return nearest_brute(cloud, x, y, z)
        return bi

    @wp.kernel(**opts)
    def nearest_user(cloud: wp.array2d(dtype=T), G: int, h: float, start: wp.array(dtype=wp.int32),
                     count: wp.array(dtype=wp.int32), cand: wp.array(dtype=C), pts: wp.array2d(dtype=T),
                     cx: wp.float64, cy: wp.float64, cz: wp.float64, scale: wp.float64, out: wp.array(dtype=wp.int32)):
        """Thread m: the nearest cloud point of pts[m] given in user units, the unit-frame coordinates rounded as
        ``kernels(mode).nearest_user`` rounds them."""
        m = wp.tid()
        sc_ = A(scale)
        out[m] = nearest_point(cloud, G, h, start, count, cand, (A(pts[m, 0]) - A(cx)) * sc_,
                               (A(pts[m, 1]) - A(cy)) * sc_, (A(pts[m, 2]) - A(cz)) * sc_)

    @wp.kernel(**opts)
    def nearest(cloud: wp.array2d(dtype=T), G: int, h: float, start: wp.array(dtype=wp.int32),
                count: wp.array(dtype=wp.int32), cand: wp.array(dtype=C), pts: wp.array2d(dtype=T),
                out: wp.array(dtype=wp.int32)):
        """Thread m: the nearest cloud point of pts[m] (unit frame)."""
        m = wp.tid()
        out[m] = nearest_point(cloud, G, h, start, count, cand, A(pts[m, 0]), A(pts[m, 1]), A(pts[m, 2]))

    return SimpleNamespace(entry=C, cell_bound=cell_bound, cell_count=cell_count, cell_cap=cell_cap,
                           cell_fill=cell_fill,
                           nearest_user=nearest_user, nearest=nearest)


class NearestGrid:
    """The candidate grid of one cloud (device arrays; rebuilt in place by :meth:`build`)."""

    def __init__(self, mode: str, n_points: int, device, cells: int | None = None):
        self.k = kernels(mode)
        self.device = wp.get_device(device)
        self.n_points = int(n_points)
        self.G = int(cells or grid_cells(n_points))
        self.h = 2.0 * BOX / self.G
        nc = self.G ** 3
        dev = self.device
        self.U = wp.empty(nc, dtype=wp.float32, device=dev)
        self.count = wp.empty(nc, dtype=wp.int32, device=dev)
        self.start = wp.empty(nc, dtype=wp.int32, device=dev)
        self.fill = wp.empty(nc, dtype=wp.int32, device=dev)
        if n_points >= 1 << 24:
            raise ValueError("the candidate grid stores point indices as float32: at most 2^24 points")
        self.cand = wp.empty(max(nc * CAND_PER_CELL, n_points * CAND_PER_POINT), dtype=self.k.entry, device=dev)

    def build(self, cloud: wp.array):
        """The lists of ``cloud`` ((N, 3) storage dtype, unit frame): no host synchronisation."""
        dev, G, h = self.device, self.G, self.h
        nc, chunks = G ** 3, (cloud.shape[0] + CHUNK - 1) // CHUNK
        self.U.fill_(float("inf"))
        self.count.zero_()
        self.fill.zero_()
        wp.launch(self.k.cell_bound, (nc, chunks), inputs=[cloud, G, h, self.U], device=dev)
        wp.launch(self.k.cell_count, (nc, chunks), inputs=[cloud, G, h, self.U, self.count], device=dev)
        wp.launch(self.k.cell_cap, nc, inputs=[self.U, self.count], device=dev)
        wp.utils.array_scan(self.count, self.start, inclusive=False)
        wp.launch(self.k.cell_fill, (nc, chunks), inputs=[cloud, G, h, self.U, self.start, self.fill, self.cand],
                  device=dev)
        return self

    def args(self) -> list:
        return [self.G, self.h, self.start, self.count, self.cand]
