"""Per-thread NeuroGF queries for users' own Warp kernels: distances, their gradients, the SDF, projection.

Every function takes the model's folded weights, ``mlp.NeuroGFWeights`` (``warp_structs.weights(model, device)``), and
points in the network's normalized frame (``mlp.to_net(frame, x)`` with ``neurogf_warp.inference.warp_structs.frame``;
multiply distances by ``frame.dscale`` for mesh units). The frame's centre is float64 and ``to_net`` / ``from_net``
subtract / add it in float64, so float32 mesh coordinates far from the origin lose nothing beyond their own
rounding; ``frame.limit`` is the domain (|to_net(x)| <= limit per axis; the functions themselves do not check it).
One thread, one query; no tiles, no shared memory.

    geodesic_distance(net, p, q) -> float                    predicted geodesic distance
    distance_and_gradient(net, p, q) -> (float, vec3)        ... and d/dp (the geodesic leaves p along -d/dp)
    distance_to_sources(net, src, x) -> float                distance to the nearest source of a SourceSet (MSAD)
    distance_to_sources_and_gradient(net, src, x)            -> (float, vec3 d/dx, int nearest source)
    geodesic_direction(net, src, x) -> (float, vec3)         distance and the unit tangent direction at x of the
                                                             geodesic toward the nearest source
    signed_distance(net, x) -> float                         the SDF head (negative inside)
    signed_distance_and_gradient(net, x) -> (float, vec3)    ... and its gradient (surface normal direction)
    project_to_surface(net, x, steps) -> vec3                Newton steps onto the SDF head's zero level set

Landmark networks (``NeuroGFNet(landmarks=K, ...)``): their distance head also reads each point's exact distances
to K landmark vertices, looked up in a ``LandmarkTable`` (``warp_structs.landmarks(model, device)``: the table and
a ``wp.Mesh`` of the vertices, network frame). A point's row is named by its *location* (vec3i ids, vec3 weights):

    locate(lm, x) -> (vec3i, vec3)                           location of x's closest surface point (a vertex's own row)
    vertex_location(v) -> (vec3i, vec3)                      location of vertex v (its row, exactly)
    face_location(lm, face, bary) -> (vec3i, vec3)           location of a point of a triangle (barycentric weights)
    landmark_distance(net, lm, p, ip, wp, q, iq, wq) -> float       predicted geodesic distance
    landmark_distance_and_gradient(net, lm, p, ip, wp, q, iq, wq)   -> (float, vec3 d/dp); T(p) moves with its
                                                             weights on a fixed triangle (the in-plane gradient)

``geodesic_distance`` and the other distance functions above do not read landmarks: use these for such networks.

Cost per call (D=256 released layout; ``benchmarks/kernel_api.py`` prints them for any model): one lifting
(3 -> 64 -> 128 -> 256) is 82K FLOPs, a head (256 -> 64 -> 64 -> 1) 41K; a backward pass through either costs
about what its forward does. Gradients are exact for the piecewise-linear ReLU network away from kinks; at a
kink the unit counts as off (see ``kernels/mlp.py``).
"""
import warp as wp

from .inference.landmark import (
    LandmarkTable,
    face_location,
    landmark_distance,
    landmark_distance_and_gradient,
    locate,
    vertex_location,
)
from .inference.mlp import (
    MAX_D,
    Frame,
    NeuroGFWeights,
    _dense_relu,
    _distance_and_gradient_to,
    _embed_from_hidden,
    _head_and_gradient,
    _lift_backward,
    _lift_first,
    distance_and_gradient,
    distance_from_embeddings,
    embed,
    from_net,
    geodesic_distance,
    project_to_surface,
    signed_distance,
    signed_distance_and_gradient,
    to_net,
    vec_d,
)

__all__ = ["NeuroGFWeights", "Frame", "SourceSet", "to_net", "from_net", "embed", "geodesic_distance",
           "distance_and_gradient", "distance_to_sources", "distance_to_sources_and_gradient", "geodesic_direction",
           "signed_distance", "signed_distance_and_gradient", "project_to_surface", "MAX_D", "LandmarkTable", "locate",
           "vertex_location", "face_location", "landmark_distance", "landmark_distance_and_gradient"]


@wp.struct
class SourceSet:
    """A bound set of sources for MSAD queries: their embeddings (S, D) and points (S,), normalized frame.
    Build one with ``neurogf_warp.inference.warp_structs.source_set(model, sources, device)``."""

    emb: wp.array2d(dtype=wp.float32)
    points: wp.array(dtype=wp.vec3)


@wp.func
def _row(a: wp.array2d(dtype=wp.float32), r: int) -> vec_d:
    v = vec_d()
    for k in range(a.shape[1]):
        v[k] = a[r, k]
    return v


@wp.func
def _nearest(net: NeuroGFWeights, src: SourceSet, x: wp.vec3, ex: vec_d):
    """(distance, index) of the nearest source to x, whose embedding is ex."""
    best = float(3.0e38)
    arg = int(-1)
    for s in range(src.emb.shape[0]):
        d = distance_from_embeddings(net, _row(src.emb, s), ex) + net.euclid * wp.length(x - src.points[s])
        if d < best:
            best = d
            arg = s
    return best, arg


@wp.func
def distance_to_sources(net: NeuroGFWeights, src: SourceSet, x: wp.vec3) -> float:
    """Predicted geodesic distance from x to the nearest source of ``src`` (3e38 for an empty set). e(x) is
    computed once; each source adds one head evaluation."""
    d, s = _nearest(net, src, x, embed(net, x))
    return d


@wp.func
def distance_to_sources_and_gradient(net: NeuroGFWeights, src: SourceSet, x: wp.vec3):
    """(distance to the nearest source, its gradient with respect to x, that source's index); the gradient is
    the nearest source's (0 and index -1 for an empty set). Where two sources are equally near the field has a
    ridge and this is the gradient of the first of them."""
    h0 = _lift_first(net, x)
    h1 = _dense_relu(net.l1_w, net.l1_b, h0)
    ex = _embed_from_hidden(net, h1)
    d, s = _nearest(net, src, x, ex)
    if s < 0:
        return d, wp.vec3(), s
    d2, g = _distance_and_gradient_to(net, x, h0, h1, ex, _row(src.emb, s), src.points[s])
    return d2, g, s


@wp.func
def geodesic_direction(net: NeuroGFWeights, src: SourceSet, x: wp.vec3):
    """(distance to the nearest source, unit direction of steepest descent of that distance in the tangent plane
    of the SDF head's level set through x): the way a geodesic from x toward the nearest source sets off. The
    direction is 0 where it is undefined (at a source, a zero gradient, or no sources)."""
    h0 = _lift_first(net, x)
    h1 = _dense_relu(net.l1_w, net.l1_b, h0)
    ex = _embed_from_hidden(net, h1)
    d, s = _nearest(net, src, x, ex)
    if s < 0:
        return d, wp.vec3()
    d2, g = _distance_and_gradient_to(net, x, h0, h1, ex, _row(src.emb, s), src.points[s])
    sv, gs = _head_and_gradient(net.s0_w, net.s0_b, net.s1_w, net.s1_b, net.s2_w, ex)
    n = _lift_backward(net, x, h0, h1, ex, gs)
    nn = wp.length(n)
    t = -g
    if nn > 1.0e-12:
        n = n / nn
        t = t - wp.dot(t, n) * n
    tl = wp.length(t)
    if tl > 1.0e-12:
        return d2, t / tl
    return d2, wp.vec3()
