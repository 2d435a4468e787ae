"""Unfolding windows: straight rays continued across faces (exact triangle unfolding) and their bookkeeping.

Every node on an edge may carry one window: a virtual source S (the source of straight rays, unfolded into the
plane of the face the window lies in) given in the edge's frame (`along` the edge from its lower vertex, `height`
away from the edge on the far side from that face), the distance `sigma` at S, and the interval [lo, hi] (edge
parameters) of the edge through which rays from S are known to be real surface paths. Crossing into the next
face the ray from S goes on straight as long as it crosses the edge inside [lo, hi].
"""
import warp as wp

from .graph import INF, SteinerGraph, edge_frame, face_normal_in_plane

wp.set_module_options({"enable_backward": False, "fuse_fp": False})

TINY = wp.constant(1.0e-12)
SAME_SOURCE_TOLERANCE = wp.constant(1.0e-6)


@wp.struct
class Windows:
    """One window per (source row, node); (S, N) arrays."""

    face: wp.array2d(dtype=int)  # the face the window lies in (rays come from there); -1: no window
    along: wp.array2d(dtype=float)  # virtual source, along the edge from its lower vertex
    height: wp.array2d(dtype=float)  # virtual source, distance from the edge's line (beyond the edge from `face`)
    sigma: wp.array2d(dtype=float)  # distance at the virtual source
    lo: wp.array2d(dtype=float)  # edge interval [lo, hi] of valid rays
    hi: wp.array2d(dtype=float)


@wp.func
def edge_coords(p: wp.vec3, A: wp.vec3, eh: wp.vec3) -> wp.vec2:
    """Point p in an edge's 2-D frame: (along the edge from A, distance from the edge's line)."""
    r = p - A
    return wp.vec2(wp.dot(r, eh), wp.length(wp.cross(r, eh)))


@wp.func
def ray_length(along: float, height: float, sigma: float, lo: float, hi: float, A: wp.vec3, eh: wp.vec3,
               elen: float, p: wp.vec3) -> float:
    """sigma + length of the straight unfolded ray from the virtual source (along, -height) to p (on the other
    side of the edge), or inf when the ray does not cross the edge inside the window [lo, hi]."""
    r = p - A
    ax = wp.dot(r, eh)
    hx = wp.length(wp.cross(r, eh))
    if hx <= TINY * elen:
        return INF
    c = (along + (ax - along) * height / (height + hx)) / elen
    if c < lo or c > hi:
        return INF
    dx = ax - along
    dy = hx + height
    return sigma + wp.sqrt(dx * dx + dy * dy)


@wp.func
def same_source(win: Windows, s: int, u: int, w: int, elen: float) -> bool:
    """Whether nodes u and w (on one edge) hold windows in the same face with the same virtual source, up to
    float32 rounding (SAME_SOURCE_TOLERANCE of the window's size)."""
    if win.face[s, w] != win.face[s, u]:
        return False
    size = win.height[s, u] + win.sigma[s, u] + elen
    tol = SAME_SOURCE_TOLERANCE * size
    return (wp.abs(win.along[s, w] - win.along[s, u]) <= tol and wp.abs(win.height[s, w] - win.height[s, u]) <= tol
            and wp.abs(win.sigma[s, w] - win.sigma[s, u]) <= tol)


@wp.func
def window_interval(graph: SteinerGraph, win: Windows, s: int, u: int, elen: float):
    """The edge interval of u's window, widened by the windows of the other nodes on u's edge that hold the same
    source in the same face where their intervals overlap (every ray in the union is a real path through one of
    them). Returns (lo, hi)."""
    lo = win.lo[s, u]
    hi = win.hi[s, u]
    e = graph.node_edge[u - graph.nv]
    first = graph.nv + graph.edge_node_start[e]
    count = graph.edge_node_start[e + 1] - graph.edge_node_start[e]
    # merging can chain through neighbours: repeat while an interval grew (at most count - 1 rounds)
    for _round in range(count - 1):
        grew = bool(False)
        for j in range(count):
            w = first + j
            if w != u and same_source(win, s, u, w, elen):
                if win.lo[s, w] <= hi and win.hi[s, w] >= lo:
                    if win.lo[s, w] < lo or win.hi[s, w] > hi:
                        grew = True
                    lo = wp.min(lo, win.lo[s, w])
                    hi = wp.max(hi, win.hi[s, w])
        if not grew:
            break
    return lo, hi


@wp.func
def crossing_param(edge_param: float, c_start: float, c_end: float, source: wp.vec2, elen: float, P0: wp.vec2,
                   P1: wp.vec2) -> float:
    """Parameter t on segment P0P1 (another edge of the face, in the window edge's 2-D frame) whose ray from
    `source` crosses the window edge at `edge_param`; c_start, c_end: the window-edge parameters of the rays to
    P0 and P1. Clamped to [0, 1], monotone in edge_param."""
    if c_start <= c_end:
        if edge_param <= c_start:
            return 0.0
        if edge_param >= c_end:
            return 1.0
    else:
        if edge_param >= c_start:
            return 0.0
        if edge_param <= c_end:
            return 1.0
    d = wp.vec2(edge_param * elen, 0.0) - source
    e = P1 - P0
    w = P0 - source
    den = d[0] * e[1] - d[1] * e[0]
    if wp.abs(den) <= 0.0:
        return 0.5
    t = (w[0] * d[1] - w[1] * d[0]) / den
    return wp.clamp(t, 0.0, 1.0)


@wp.func
def unfold_source(graph: SteinerGraph, e: int, face: int, along: float, height: float) -> wp.vec3:
    """The virtual source (along, height) of a window on edge e, unfolded into the plane of `face` (3-D)."""
    A, eh, elen = edge_frame(graph, e)
    return A + along * eh - height * face_normal_in_plane(graph, e, face)
