"""Path shortening on the SDF surface with batched SDF evaluations (precision="fp16").

The same method as ``mlp.pin_and_project`` / ``mlp.relax_paths`` (each inner point to its neighbours' midpoint,
then a Newton step onto the SDF head's zero set, x -= s g / (|g| max(|g|, 0.5))), split so that every SDF value
comes from one batched launch of the tensor-core SDF kernel: a kernel writes each point's forward-difference
stencil (the point and three offsets), the SDF kernel evaluates all of them, and a kernel takes the Newton step.

FD_STEP is larger than the per-thread kernels' 1e-4: fp16 activations put about 5e-5 of noise on an SDF value
(network frame), so the difference quotient needs a step well above that.
"""
import warp as wp

FD_STEP = 2.0e-3  # forward-difference step, network frame


@wp.kernel(enable_backward=False)
def stencil(x: wp.array2d(dtype=wp.vec3), mid: int, h: float, out: wp.array(dtype=wp.vec3)):
    """4 points per path point: the point (mid = 1: the midpoint of its neighbours for inner points) and the point
    moved by h (user units) along x, y and z."""
    i, j = wp.tid()
    m = x.shape[1]
    p = x[i, j]
    if mid != 0 and j > 0 and j < m - 1:
        p = 0.5 * (x[i, j - 1] + x[i, j + 1])
    k = 4 * (i * m + j)
    out[k] = p
    out[k + 1] = p + wp.vec3(h, 0.0, 0.0)
    out[k + 2] = p + wp.vec3(0.0, h, 0.0)
    out[k + 3] = p + wp.vec3(0.0, 0.0, h)


@wp.kernel(enable_backward=False)
def newton(pts: wp.array(dtype=wp.vec3), s: wp.array(dtype=wp.float32), h: float, starts: wp.array(dtype=wp.vec3),
           ends: wp.array(dtype=wp.vec3), y: wp.array2d(dtype=wp.vec3)):
    """One Newton step from each stencil's first point (user frame: the SDF and its gradient in user units);
    the path's ends are pinned to starts[i] and ends[i]."""
    i, j = wp.tid()
    m = y.shape[1]
    if j == 0:
        y[i, j] = starts[i]
        return
    if j == m - 1:
        y[i, j] = ends[i]
        return
    k = 4 * (i * m + j)
    s0 = s[k]
    g = wp.vec3(s[k + 1] - s0, s[k + 2] - s0, s[k + 3] - s0) / h
    p = pts[k]
    n = wp.length(g)
    if n > 1.0e-12:
        p = p - (s0 / (n * wp.max(n, 0.5))) * g
    y[i, j] = p


# -- paths on the mesh, and the choice among candidate paths (neurogf_warp.inference.paths) ----------------------
#
# With a mesh attached, paths are shortened on the mesh itself: each inner point goes to the closest mesh point of
# its neighbours' midpoint (a BVH query, no network evaluation: far cheaper than a Newton step on the SDF head,
# and on the exact surface). Then every candidate path of a pair is scored by what can be measured at query time:
# its length, and how far its chords leave the surface (a chord whose midpoint lies far from the surface jumps
# through the solid or across a gap instead of following the surface).

REACH = 1.0e18  # search radius that always finds the closest point (its square stays finite in float32)


@wp.func
def finite3(x: wp.vec3) -> bool:
    return wp.isfinite(x[0]) and wp.isfinite(x[1]) and wp.isfinite(x[2])


@wp.func
def closest_on_mesh(mesh: wp.uint64, x: wp.vec3, bound: float) -> wp.vec3:
    """The closest mesh point of x, searched within ``bound`` first (a known upper bound of the distance prunes
    the BVH), then everywhere; NaN for a non-finite x (a BVH walk on NaN is undefined)."""
    if not finite3(x):
        return wp.vec3(wp.nan, wp.nan, wp.nan)
    q = wp.mesh_query_point_no_sign(mesh, x, bound)
    if not q.result:
        q = wp.mesh_query_point_no_sign(mesh, x, REACH)
    return wp.mesh_eval_position(mesh, q.face, q.u, q.v)


@wp.kernel(enable_backward=False)
def snap_inner(mesh: wp.uint64, starts: wp.array(dtype=wp.vec3), ends: wp.array(dtype=wp.vec3),
               x: wp.array2d(dtype=wp.vec3)):
    """In place: path i's ends := starts[i], ends[i]; its inner points := their closest mesh points."""
    i, j = wp.tid()
    m = x.shape[1]
    if j == 0:
        x[i, j] = starts[i]
    elif j == m - 1:
        x[i, j] = ends[i]
    else:
        x[i, j] = closest_on_mesh(mesh, x[i, j], REACH)


@wp.kernel(enable_backward=False)
def relax_on_mesh(mesh: wp.uint64, x: wp.array2d(dtype=wp.vec3), y: wp.array2d(dtype=wp.vec3)):
    """One Jacobi shortening sweep on the mesh: each inner point to the closest mesh point of its neighbours'
    midpoint (ends kept). x's inner points lie on the mesh, so the midpoint's closest point is no farther than
    x[i, j] is from it: that distance bounds the search."""
    i, j = wp.tid()
    m = x.shape[1]
    if j == 0 or j == m - 1:
        y[i, j] = x[i, j]
    else:
        mid = 0.5 * (x[i, j - 1] + x[i, j + 1])
        y[i, j] = closest_on_mesh(mesh, mid, 1.001 * wp.length(mid - x[i, j]) + 1.0e-30)


@wp.kernel(enable_backward=False)
def gaps_on_mesh(mesh: wp.uint64, x: wp.array2d(dtype=wp.vec3), off: wp.array2d(dtype=wp.float32),
                 gap: wp.array2d(dtype=wp.float32)):
    """Per point x[i, j]: off[i, j], its distance from the mesh; per chord (x[i, j], x[i, j + 1]), j < m - 1:
    gap[i, j], its midpoint's distance from the mesh (mesh units). off and gap have x's shape (N, m); gap's last
    column is not written."""
    i, j = wp.tid()
    m = x.shape[1]
    a = x[i, j]
    ca = closest_on_mesh(mesh, a, REACH)
    off[i, j] = wp.length(a - ca)
    if j < m - 1:
        mid = 0.5 * (a + x[i, j + 1])
        # the midpoint's closest point is no farther than a's closest point
        c = closest_on_mesh(mesh, mid, 1.001 * wp.length(mid - ca) + 1.0e-30)
        gap[i, j] = wp.length(mid - c)


@wp.kernel(enable_backward=False)
def midpoints(x: wp.array2d(dtype=wp.vec3), out: wp.array2d(dtype=wp.vec3)):
    """out[i, j] = the midpoint of chord j of path i (j < m - 1); out[i, m - 1] = the path's last point, so that
    out has x's shape (N, m)."""
    i, j = wp.tid()
    k = wp.min(j + 1, x.shape[1] - 1)
    out[i, j] = 0.5 * (x[i, j] + x[i, k])


@wp.kernel(enable_backward=False)
def score_paths(x: wp.array2d(dtype=wp.vec3), off: wp.array2d(dtype=wp.float32), gap: wp.array2d(dtype=wp.float32),
                length: wp.array(dtype=wp.float32), excess: wp.array(dtype=wp.float32)):
    """Per path: its length along the surface, and its chords' largest excess distance from the surface.

    A chord's excess e is its midpoint's distance from the surface less the mean of its ends' distances (ends
    given off the surface do not count). The chord of length s stands for a path on the surface through the
    point e below (or above) its midpoint: 2 sqrt((s / 2)^2 + e^2) long. So a chord that cuts a convex crease
    or a bump counts the detour the surface makes, and a path zigzagging along a crease is not mistaken for a
    short one. off/gap may hold signed SDF values: their magnitudes are used."""
    i = wp.tid()
    m = x.shape[1]
    total = float(0.0)
    worst = float(0.0)
    for j in range(m - 1):
        e = wp.abs(gap[i, j]) - 0.5 * (wp.abs(off[i, j]) + wp.abs(off[i, j + 1]))
        half = 0.5 * wp.length(x[i, j + 1] - x[i, j])
        ep = wp.max(e, 0.0)
        total += 2.0 * wp.sqrt(half * half + ep * ep)
        if not (e <= worst):  # NaN counts as the worst
            worst = e
    length[i] = total
    excess[i] = worst


@wp.kernel(enable_backward=False)
def pick_best(length: wp.array(dtype=wp.float32), excess: wp.array(dtype=wp.float32), n_cand: int, m: int,
              tol: float, best: wp.array(dtype=wp.int32), best_excess: wp.array(dtype=wp.float32)):
    """Candidates of path i are rows i, i + N, i + 2N, ... (N = best.shape[0]). A candidate stays on the surface
    when its chords' excess is at most ``tol`` times its mean point spacing; keep the shortest of those, else
    (none stays on) the one that leaves the least. best_excess[i]: 0 when a candidate stayed on, else the chosen
    one's excess (mesh units). Ties keep the lower candidate index."""
    i = wp.tid()
    N = best.shape[0]
    b = int(-1)
    bl = float(0.0)
    for c in range(n_cand):
        r = c * N + i
        if excess[r] <= tol * length[r] / float(m - 1) and (b < 0 or length[r] < bl):
            b = c
            bl = length[r]
    best_excess[i] = 0.0
    if b < 0:
        be = float(0.0)
        for c in range(n_cand):
            r = c * N + i
            if b < 0 or excess[r] < be:
                b = c
                be = excess[r]
        if b < 0:
            b = 0
        best_excess[i] = excess[b * N + i]
    best[i] = b


@wp.kernel(enable_backward=False)
def span_ends(x: wp.array2d(dtype=wp.vec3), stride: int, a: wp.array2d(dtype=wp.vec3), b: wp.array2d(dtype=wp.vec3)):
    """The spans of ``stride`` chords of each path: a[i, k] = x[i, k * stride], b[i, k] = the point ``stride``
    further on (the last point for the last span). a and b are (N, ceil((m - 1) / stride))."""
    i, k = wp.tid()
    j = k * stride
    a[i, k] = x[i, j]
    b[i, k] = x[i, wp.min(j + stride, x.shape[1] - 1)]


@wp.kernel(enable_backward=False)
def fold_jumps(a: wp.array2d(dtype=wp.vec3), b: wp.array2d(dtype=wp.vec3), d: wp.array2d(dtype=wp.float32),
               length: wp.array(dtype=wp.float32), d_ends: wp.array(dtype=wp.float32), short_of: float,
               scale: float, excess: wp.array(dtype=wp.float32)):
    """excess[i] := max(excess[i], scale * (d - |b - a|) over the spans of path i,
    scale * (short_of * d_ends - length)):
    a span whose ends are much farther apart along the surface (d, the network's geodesic distance) than in space
    jumps a gap, and so does a path shorter than ``short_of`` times the network's distance between its ends (path i
    joins the ends of pair i % N, N = d_ends.shape[0]). NaN stays."""
    i = wp.tid()
    worst = excess[i]
    for k in range(a.shape[1]):
        e = scale * (d[i, k] - wp.length(b[i, k] - a[i, k]))
        if not (e <= worst):
            worst = e
    g = scale * (short_of * d_ends[i % d_ends.shape[0]] - length[i])
    if g > worst:
        worst = g
    excess[i] = worst


@wp.kernel(enable_backward=False)
def take_best(x: wp.array2d(dtype=wp.vec3), best: wp.array(dtype=wp.int32), reversed_mask: wp.array(dtype=wp.int32),
              out: wp.array2d(dtype=wp.vec3)):
    """out[i] := candidate best[i] of path i (rows i + c N of x), turned around where reversed_mask[c]."""
    i, j = wp.tid()
    N = out.shape[0]
    m = out.shape[1]
    c = best[i]
    k = j
    if reversed_mask[c] != 0:
        k = m - 1 - j
    out[i, j] = x[c * N + i, k]


@wp.kernel(enable_backward=False)
def end_offsets(s_start: wp.array(dtype=wp.float32), s_end: wp.array(dtype=wp.float32),
                off: wp.array2d(dtype=wp.float32)):
    """off[i, 0] := s_start[i], off[i, m - 1] := s_end[i] (the path ends' SDF values; inner points lie on the
    SDF surface after projection and keep the zeros they were given)."""
    i = wp.tid()
    off[i, 0] = s_start[i]
    off[i, off.shape[1] - 1] = s_end[i]
