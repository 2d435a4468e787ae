"""Small kernels shared by every query: finishing raw distances, per-component answers, numbering, input checks.

A distance is finished the same way on every path (``ngf::finish_distance`` of the native header, called here
too): the network's head value plus the |x - s| term of ``euclid`` networks, scaled to user units, never below
the straight line |x - s|, exactly 0 where the query point is the source itself, +inf between points of
different connected components (no surface path joins them), and NaN where a point is outside the domain or
not finite.
"""
import warp as wp

from . import mlp
from . import tensorcore as tc

# the finishing rule is the native header's ngf::finish_distance, for the per-thread kernels too
wp.set_module_options({"extra_build_options": tc.BUILD})

INF = wp.constant(float("inf"))
NAN = wp.constant(float("nan"))


def _finish_distance(head: float, x: wp.vec3, s: wp.vec3, frame: mlp.Frame, euclid: float, other_part: bool,
                     raw: int) -> float:
    return float(0.0)  # a stub: the body is the native snippet below (the return statement types its result)


_finish_distance.__name__ = _finish_distance.__qualname__ = "ngf_finish_distance"
finish_distance = wp.func_native(tc._frame_cpp("frame") + """
    const float xp[3] = {x[0], x[1], x[2]};
    const float sp[3] = {s[0], s[1], s[2]};
    return ngf::finish_distance(head, F, xp, sp, euclid, other_part, raw);
""")(_finish_distance)
finish_distance.__doc__ = """User-unit distance from a head value (network frame): ``ngf::finish_distance`` of the native
header, the one definition of the rule for both backends."""


@wp.kernel(enable_backward=False)
def finish_rows(head: wp.array2d(dtype=wp.float32), rows: wp.array(dtype=wp.vec3), row_comp: wp.array(dtype=wp.int32),
                src: wp.array(dtype=wp.vec3), src_comp: wp.array(dtype=wp.int32), frame: mlp.Frame, euclid: float,
                raw: int, out: wp.array2d(dtype=wp.float32)):
    """out[s, i] from head values head[s, i] of source s and row i (component arrays empty: one component)."""
    s, i = wp.tid()
    other = False
    if row_comp.shape[0] > 0:
        other = row_comp[i] != src_comp[s]
    out[s, i] = finish_distance(head[s, i], rows[i], src[s], frame, euclid, other, raw)


@wp.kernel(enable_backward=False)
def finish_pairs(net: mlp.NeuroGFWeights, ps: wp.array(dtype=wp.vec3), qs: wp.array(dtype=wp.vec3), frame: mlp.Frame,
                 euclid: float, raw: int, out: wp.array(dtype=wp.float32)):
    """Pair distances from the per-thread network: ``net`` with euclid = 0 gives the head value, finished here."""
    i = wp.tid()
    p = ps[i]
    q = qs[i]
    head = mlp.geodesic_distance(net, mlp.to_net(frame, p), mlp.to_net(frame, q))
    out[i] = finish_distance(head, p, q, frame, euclid, False, raw)


@wp.kernel(enable_backward=False)
def split_pairs(comp_p: wp.array(dtype=wp.int32), comp_q: wp.array(dtype=wp.int32), d: wp.array(dtype=wp.float32)):
    """+inf where the two points of a pair lie on different connected components."""
    i = wp.tid()
    if comp_p[i] != comp_q[i] and not wp.isnan(d[i]):  # a point without an answer stays NaN
        d[i] = INF


@wp.kernel(enable_backward=False)
def split_paths(comp_p: wp.array(dtype=wp.int32), comp_q: wp.array(dtype=wp.int32), x: wp.array2d(dtype=wp.vec3)):
    """NaN rows for paths between different connected components."""
    i, j = wp.tid()
    if comp_p[i] != comp_q[i]:
        x[i, j] = wp.vec3(NAN, NAN, NAN)


@wp.kernel(enable_backward=False)
def min_rows(d: wp.array2d(dtype=wp.float32), out: wp.array(dtype=wp.float32)):
    i = wp.tid()
    best = INF
    for s in range(d.shape[0]):
        best = wp.min(best, d[s, i])
    out[i] = best


@wp.kernel(enable_backward=False)
def to_input(internal: wp.array2d(dtype=wp.float32), inv: wp.array(dtype=wp.int32), out: wp.array2d(dtype=wp.float32)):
    """Per-vertex results in the user's numbering: out[s, j] = internal[s, inv[j]], NaN where inv[j] < 0."""
    s, j = wp.tid()
    k = inv[j]
    if k < 0:
        out[s, j] = NAN
    else:
        out[s, j] = internal[s, k]


@wp.kernel(enable_backward=False)
def point_components(mesh: wp.uint64, pts: wp.array(dtype=wp.vec3), face_comp: wp.array(dtype=wp.int32),
                     out: wp.array(dtype=wp.int32)):
    """Component of the surface point closest to each point (points and mesh in the same frame); -1 for none."""
    i = wp.tid()
    p = pts[i]
    out[i] = -1  # a non-finite point belongs to no component (its answers are NaN)
    if wp.isfinite(p[0]) and wp.isfinite(p[1]) and wp.isfinite(p[2]):
        q = wp.mesh_query_point_no_sign(mesh, p, 1.0e30)
        if q.result:
            out[i] = face_comp[q.face]


@wp.func
def in_domain(p: wp.vec3, frame: mlp.Frame, limit: float) -> bool:
    x = mlp.to_net(frame, p)
    ok = wp.isfinite(x[0]) and wp.isfinite(x[1]) and wp.isfinite(x[2])
    if ok:
        ok = wp.abs(x[0]) <= limit and wp.abs(x[1]) <= limit and wp.abs(x[2]) <= limit
    return ok


@wp.kernel(enable_backward=False)
def nan_outside(xs: wp.array(dtype=wp.vec3), frame: mlp.Frame, out: wp.array(dtype=wp.float32)):
    """NaN for points outside the domain or not finite."""
    i = wp.tid()
    if not mlp.in_domain(frame, mlp.to_net(frame, xs[i])):
        out[i] = NAN


@wp.kernel(enable_backward=False)
def finish_paths(ps: wp.array(dtype=wp.vec3), qs: wp.array(dtype=wp.vec3), frame: mlp.Frame, test_domain: int,
                 x: wp.array2d(dtype=wp.vec3)):
    """Per path (one thread; most rows are left as they are): NaN rows where an end is outside the domain or not
    finite (their points have no meaning; tested with ``test_domain``, i.e. for unchecked input), and a path from a
    point to itself is that point repeated."""
    i = wp.tid()
    p = ps[i]
    q = qs[i]
    if test_domain != 0:
        if not (mlp.in_domain(frame, mlp.to_net(frame, p)) and mlp.in_domain(frame, mlp.to_net(frame, q))):
            for j in range(x.shape[1]):
                x[i, j] = wp.vec3(NAN, NAN, NAN)
            return
    if p == q:
        for j in range(x.shape[1]):
            x[i, j] = p


@wp.kernel(enable_backward=False)
def shift_points(x: wp.array(dtype=wp.vec3), center: wp.vec3d, out: wp.array(dtype=wp.vec3)):
    """out = x + center in float64: points relative to the mesh centre back to mesh coordinates."""
    i = wp.tid()
    p = x[i]
    out[i] = wp.vec3(wp.float32(wp.float64(p[0]) + center[0]), wp.float32(wp.float64(p[1]) + center[1]),
                     wp.float32(wp.float64(p[2]) + center[2]))


@wp.kernel(enable_backward=False)
def check_points(a: wp.array(dtype=wp.vec3), b: wp.array(dtype=wp.vec3), frame: mlp.Frame, limit: float,
                 bad: wp.array(dtype=wp.int32)):
    """bad[k] = 1 + the smallest index of a non-finite point, or one outside the domain cube (normalized frame),
    of array k (a, then b; b may be empty)."""
    i = wp.tid()
    if not in_domain(a[i], frame, limit):
        wp.atomic_min(bad, 0, i + 1)
    if b.shape[0] > 0:
        if not in_domain(b[i], frame, limit):
            wp.atomic_min(bad, 1, i + 1)
