"""Distances of landmark networks (``NeuroGFNet(landmarks=K, ...)``) as Warp functions and kernels, float32 weights
with float64 sums, as ``mlp``.

The distance head of such a network reads, besides |e_p - e_q| (D), the exact distances T(x) (K, normalized units)
of both points to K landmark vertices: its input is [|e_p - e_q|, |T(p) - T(q)|, lower, upper] with
lower = max_k |T(p)_k - T(q)_k| and upper = min_k (T(p)_k + T(q)_k) (the triangle inequality's bounds), and with
e = |p - q| and floor = max(e, landmark_floor * lower) the distance is

    bracket:  floor + sigmoid(head) * (max(upper, floor) - floor), or e + head where upper >= 2 * UNREACHED
              (every landmark on another component: no bounds);
    plain:    head (+ floor for ``euclid`` networks).

A point's T is given by its *location* (ids: vec3i, w: vec3): the row of the table interpolated over three table
rows with barycentric weights, T = R[ids[0]] + w[1] (R[ids[1]] - R[ids[0]]) + w[2] (R[ids[2]] - R[ids[0]]).
A vertex v is ((v, v, v), (1, 0, 0)): its row, exactly; a point on a face is the face's corners and the
barycentric weights of its closest surface point. (This form keeps an entry exact where the three rows agree, such
as the ``UNREACHED`` entries of another component, where a weighted sum could miss the threshold by one ulp.)
"""
import warp as wp

from . import mlp
from . import tensorcore as tc
from .finish import finish_distance

# pair kernels finish with the native header's rule (kernels.finish), so the header is part of this module
wp.set_module_options({"extra_build_options": tc.BUILD})

UNREACHED = wp.constant(4.0)  # network.LANDMARK_UNREACHED: a table's entry across components
NAN = wp.constant(float("nan"))
_BIG = wp.constant(wp.float64(1.0e300))


@wp.struct
class LandmarkTable:
    """A landmark network's table of exact distances and the surface its rows live on.

    rows : (V, K) float32, distances from every vertex to the K landmarks, normalized units.
    indices : (3 F,) int32, the triangles' corners (rows of ``rows`` and ``points``).
    points : (V,) vec3, the vertices, in the frame of the points the functions get (network frame for user kernels).
    mesh : uint64, a ``wp.Mesh`` of ``points`` and ``indices`` (closest surface points: ``locate``).
    floor : float32, the network's ``landmark_floor`` (0..1).
    bracket : int32, 1: the network's ``landmark_bracket`` form; 0: the plain form.
    euclid : float32, 1: the plain form adds the floor (the network's ``euclid``); 0: it does not.
    """

    rows: wp.array2d(dtype=wp.float32)
    indices: wp.array(dtype=wp.int32)
    points: wp.array(dtype=wp.vec3)
    mesh: wp.uint64
    floor: wp.float32
    bracket: wp.int32
    euclid: wp.float32


# ---- locations ---------------------------------------------------------------------------------------------------

@wp.func
def vertex_location(v: int):
    """The location of vertex ``v``: its own table row, exactly. Returns (vec3i ids, vec3 weights)."""
    return wp.vec3i(v, v, v), wp.vec3(1.0, 0.0, 0.0)


@wp.func
def face_location(lm: LandmarkTable, face: int, bary: wp.vec3):
    """The location of a point on triangle ``face`` with barycentric weights ``bary`` of its three corners (in the
    order of ``lm.indices``; Warp's mesh queries give (u, v, 1 - u - v)). Returns (vec3i ids, vec3 weights)."""
    return wp.vec3i(lm.indices[3 * face], lm.indices[3 * face + 1], lm.indices[3 * face + 2]), bary


@wp.func
def locate(lm: LandmarkTable, x: wp.vec3):
    """The location of the surface point closest to x (``lm.points``' frame): (vec3i ids, vec3 weights). A point
    whose closest surface point is a vertex (a vertex itself, bit for bit, among them) gets that vertex's exact row;
    a non-finite point NaN weights (NaN distances)."""
    if not (wp.isfinite(x[0]) and wp.isfinite(x[1]) and wp.isfinite(x[2])):
        return wp.vec3i(0, 0, 0), wp.vec3(NAN, NAN, NAN)
    q = wp.mesh_query_point_no_sign(lm.mesh, x, 1.0e30)
    if not q.result:
        return wp.vec3i(0, 0, 0), wp.vec3(NAN, NAN, NAN)
    ids, w = face_location(lm, q.face, wp.vec3(q.u, q.v, 1.0 - q.u - q.v))
    for c in range(3):  # the closest point is a vertex (or x is one): that vertex's row itself, not a weighted sum
        if w[c] == 1.0 or lm.points[ids[c]] == x:
            return vertex_location(ids[c])
    return ids, w


@wp.func
def _entry(lm: LandmarkTable, ids: wp.vec3i, w: wp.vec3, k: int) -> wp.float64:
    """T_k at a location, in float64."""
    r0 = wp.float64(lm.rows[ids[0], k])
    return (r0 + wp.float64(w[1]) * (wp.float64(lm.rows[ids[1], k]) - r0)
            + wp.float64(w[2]) * (wp.float64(lm.rows[ids[2], k]) - r0))


# ---- the distance ------------------------------------------------------------------------------------------------

@wp.func
def _first_layer(net: mlp.NeuroGFWeights, lm: LandmarkTable, ep: mlp.vec_d, eq: mlp.vec_d, ip: wp.vec3i,
                 wp_: wp.vec3, iq: wp.vec3i, wq: wp.vec3):
    """The head's first layer (ReLU applied) on [|e_p - e_q|, |T(p) - T(q)|, lower, upper], with lower, upper and
    the landmarks that give them (kl, ku). The K features are streamed, never stored."""
    D = net.l2_w.shape[0]
    K = lm.rows.shape[1]
    H = net.g0_w.shape[0]
    acc = mlp.vec_acc()
    for j in range(H):
        acc[j] = wp.float64(net.g0_b[j])
    for k in range(D):
        a = wp.float64(wp.abs(ep[k] - eq[k]))
        for j in range(H):
            acc[j] += wp.float64(net.g0_w[j, k]) * a
    lower = wp.float64(-1.0)
    upper = _BIG
    kl = int(0)
    ku = int(0)
    for k in range(K):
        tp = _entry(lm, ip, wp_, k)
        tq = _entry(lm, iq, wq, k)
        diff = wp.abs(tp - tq)
        for j in range(H):
            acc[j] += wp.float64(net.g0_w[j, D + k]) * diff
        if diff > lower:  # the first of equal ones, as torch's max
            lower = diff
            kl = k
        if tp + tq < upper:
            upper = tp + tq
            ku = k
    h = mlp.vec_h()
    for j in range(H):
        a = acc[j] + wp.float64(net.g0_w[j, D + K]) * lower + wp.float64(net.g0_w[j, D + K + 1]) * upper
        h[j] = wp.max(wp.float32(a), 0.0)
    return h, lower, upper, kl, ku


@wp.func
def _output(lm: LandmarkTable, y: wp.float64, lower: wp.float64, upper: wp.float64, e: wp.float64) -> wp.float64:
    """The distance from the head's value y (see the module docstring)."""
    floor = wp.max(e, wp.float64(lm.floor) * lower)
    if lm.bracket == 0:
        return y + wp.float64(lm.euclid) * floor
    if upper >= wp.float64(2.0) * wp.float64(UNREACHED):
        return e + y
    s = wp.float64(1.0) / (wp.float64(1.0) + wp.exp(-y))
    return floor + s * (wp.max(upper, floor) - floor)


@wp.func
def _chord(p: wp.vec3, q: wp.vec3) -> wp.float64:
    dx = wp.float64(p[0]) - wp.float64(q[0])
    dy = wp.float64(p[1]) - wp.float64(q[1])
    dz = wp.float64(p[2]) - wp.float64(q[2])
    return wp.sqrt(dx * dx + dy * dy + dz * dz)


@wp.func
def distance_from_embeddings(net: mlp.NeuroGFWeights, lm: LandmarkTable, p: wp.vec3, ep: mlp.vec_d, ip: wp.vec3i,
                             wp_: wp.vec3, q: wp.vec3, eq: mlp.vec_d, iq: wp.vec3i, wq: wp.vec3) -> float:
    """The landmark network's distance of p and q (network frame) from their embeddings and locations."""
    h, lower, upper, kl, ku = _first_layer(net, lm, ep, eq, ip, wp_, iq, wq)
    y = mlp._head_tail(net.g1_w, net.g1_b, net.g2_w, h)
    return wp.float32(_output(lm, wp.float64(y), lower, upper, _chord(p, q)))


@wp.func
def landmark_distance(net: mlp.NeuroGFWeights, lm: LandmarkTable, p: wp.vec3, ip: wp.vec3i, wp_: wp.vec3,
                      q: wp.vec3, iq: wp.vec3i, wq: wp.vec3) -> float:
    """Predicted geodesic distance of a landmark network between p and q (network frame), whose table rows are
    given by their locations (``vertex_location``, ``face_location``, ``locate``). Normalized units."""
    return distance_from_embeddings(net, lm, p, mlp.embed(net, p), ip, wp_, q, mlp.embed(net, q), iq, wq)


@wp.func
def _bary_gradients(lm: LandmarkTable, ids: wp.vec3i):
    """Gradients of the barycentric weights w1, w2 of triangle ``ids`` at a point of its plane (in-plane vectors,
    1 / length); zero for a degenerate triangle (a vertex's location: its row does not move)."""
    a = lm.points[ids[0]]
    b = lm.points[ids[1]]
    c = lm.points[ids[2]]
    n = wp.cross(b - a, c - a)
    nn = wp.dot(n, n)
    if nn <= 0.0 or ids[0] == ids[1]:
        return wp.vec3(), wp.vec3()
    return wp.cross(n, a - c) / nn, wp.cross(n, b - a) / nn


@wp.func
def landmark_distance_and_gradient(net: mlp.NeuroGFWeights, lm: LandmarkTable, p: wp.vec3, ip: wp.vec3i,
                                   wp_: wp.vec3, q: wp.vec3, iq: wp.vec3i, wq: wp.vec3):
    """(``landmark_distance``, its gradient with respect to p), network frame. The gradient flows through the
    embedding, |p - q| and T(p); T(p) moves through its barycentric weights with its triangle held fixed (an
    in-plane gradient; a vertex's row is constant). At a kink (ReLU at 0, equal channels, ties of the max / min)
    one side is taken, as ``mlp.distance_and_gradient``. Swap p and q for the gradient with respect to q."""
    D = net.l2_w.shape[0]
    K = lm.rows.shape[1]
    h0 = mlp._lift_first(net, p)
    h1p = mlp._dense_relu(net.l1_w, net.l1_b, h0)
    ep = mlp._embed_from_hidden(net, h1p)
    eq = mlp.embed(net, q)
    h, lower, upper, kl, ku = _first_layer(net, lm, ep, eq, ip, wp_, iq, wq)
    h1 = mlp._dense_relu(net.g1_w, net.g1_b, h)
    y = wp.float64(mlp._dot_row(net.g2_w, 0, h1))
    e = _chord(p, q)
    out = _output(lm, y, lower, upper, e)
    # d out / d(y, floor, upper, e) of the output rule
    f = wp.float64(lm.floor)
    floor = wp.max(e, f * lower)
    dy = wp.float64(1.0)
    dfloor = wp.float64(0.0)
    dupper = wp.float64(0.0)
    de = wp.float64(0.0)
    if lm.bracket == 0:
        dfloor = wp.float64(lm.euclid)
    elif upper >= wp.float64(2.0) * wp.float64(UNREACHED):
        de = wp.float64(1.0)
    else:
        s = wp.float64(1.0) / (wp.float64(1.0) + wp.exp(-y))
        if upper > floor:
            dy = s * (wp.float64(1.0) - s) * (upper - floor)
            dfloor = wp.float64(1.0) - s
            dupper = s
        else:  # the bracket is empty: the output is the floor
            dy = wp.float64(0.0)
            dfloor = wp.float64(1.0)
    dlower = wp.float64(0.0)
    if e >= f * lower:
        de += dfloor
    else:
        dlower = dfloor * f
    # back through the head to its first layer's pre-activations (ReLU-masked)
    d1 = mlp.vec_h()
    for j in range(net.g1_w.shape[0]):
        if h1[j] > 0.0:
            d1[j] = wp.float32(wp.float64(net.g2_w[0, j]) * dy)
    d0 = mlp._back_relu(net.g1_w, d1, h)
    H = net.g0_w.shape[0]
    ge = mlp.vec_d()
    for k in range(D):  # d|u|/du = sign(u), 0 at u = 0
        acc = wp.float64(0.0)
        for j in range(H):
            acc += wp.float64(net.g0_w[j, k]) * wp.float64(d0[j])
        if ep[k] > eq[k]:
            ge[k] = wp.float32(acc)
        elif ep[k] < eq[k]:
            ge[k] = -wp.float32(acc)
    gl = dlower
    gu = dupper
    for j in range(H):
        gl += wp.float64(net.g0_w[j, D + K]) * wp.float64(d0[j])
        gu += wp.float64(net.g0_w[j, D + K + 1]) * wp.float64(d0[j])
    g = mlp._lift_backward(net, p, h0, h1p, ep, ge)
    # T(p): d out / d T_k, then through the weights w1, w2 (w0 = 1 - w1 - w2)
    gw1, gw2 = _bary_gradients(lm, ip)
    if wp.length_sq(gw1) + wp.length_sq(gw2) > 0.0:
        dw1 = wp.float64(0.0)
        dw2 = wp.float64(0.0)
        for k in range(K):
            tp = _entry(lm, ip, wp_, k)
            tq = _entry(lm, iq, wq, k)
            acc = wp.float64(0.0)
            for j in range(H):
                acc += wp.float64(net.g0_w[j, D + k]) * wp.float64(d0[j])
            sg = wp.float64(0.0)
            if tp > tq:
                sg = wp.float64(1.0)
            elif tp < tq:
                sg = wp.float64(-1.0)
            dt = acc * sg
            if k == kl:
                dt += gl * sg
            if k == ku:
                dt += gu
            r0 = wp.float64(lm.rows[ip[0], k])
            dw1 += dt * (wp.float64(lm.rows[ip[1], k]) - r0)
            dw2 += dt * (wp.float64(lm.rows[ip[2], k]) - r0)
        g = g + wp.float32(dw1) * gw1 + wp.float32(dw2) * gw2
    if e > wp.float64(0.0):  # d|p - q|/dp = (p - q) / |p - q|, 0 at p = q
        g = g + wp.float32(de / e) * (p - q)
    return wp.float32(out), g


# ---- batch kernels (the per-thread backend, precision="fp32") -------------------------------------------------------

@wp.func
def _relative(frame: mlp.Frame, x: wp.vec3) -> wp.vec3:
    """A point in ``frame``'s coordinates -> relative to the mesh centre (x - centre, in float64)."""
    c = frame.center
    return wp.vec3(wp.float32(wp.float64(x[0]) - c[0]), wp.float32(wp.float64(x[1]) - c[1]),
                   wp.float32(wp.float64(x[2]) - c[2]))


@wp.kernel(enable_backward=False)
def locate_points(lm: LandmarkTable, xs: wp.array(dtype=wp.vec3), frame: mlp.Frame, ids: wp.array(dtype=wp.vec3i),
                  w: wp.array(dtype=wp.vec3)):
    """Locations of points in ``frame``'s coordinates (``lm`` relative to the mesh centre)."""
    i = wp.tid()
    a, b = locate(lm, _relative(frame, xs[i]))
    ids[i] = a
    w[i] = b


@wp.func
def _row(a: wp.array2d(dtype=wp.float32), r: int) -> mlp.vec_d:
    v = mlp.vec_d()
    for k in range(a.shape[1]):
        v[k] = a[r, k]
    return v


@wp.kernel(enable_backward=False)
def head_table(net: mlp.NeuroGFWeights, lm: LandmarkTable, es: wp.array2d(dtype=wp.float32),
               src: wp.array(dtype=wp.vec3), src_ids: wp.array(dtype=wp.vec3i), src_w: wp.array(dtype=wp.vec3),
               ex: wp.array2d(dtype=wp.float32), xs: wp.array(dtype=wp.vec3), x_ids: wp.array(dtype=wp.vec3i),
               x_w: wp.array(dtype=wp.vec3), frame: mlp.Frame, x0: int, out: wp.array2d(dtype=wp.float32)):
    """out[s, i]: the distance (network frame, to be finished by ``finish.finish_rows`` with euclid = 0) from source
    s to row x0 + i, from their embeddings es, ex and locations; without row locations (x_ids empty) row r is
    vertex r."""
    s, i = wp.tid()
    r = x0 + i
    ir, wr = vertex_location(r)
    if x_ids.shape[0] > 0:
        ir = x_ids[r]
        wr = x_w[r]
    out[s, i] = distance_from_embeddings(net, lm, mlp.to_net(frame, src[s]), _row(es, s), src_ids[s], src_w[s],
                                         mlp.to_net(frame, xs[r]), _row(ex, r), ir, wr)


@wp.kernel(enable_backward=False)
def pair_distances(net: mlp.NeuroGFWeights, lm: LandmarkTable, ps: wp.array(dtype=wp.vec3),
                   qs: wp.array(dtype=wp.vec3), p_ids: wp.array(dtype=wp.vec3i), p_w: wp.array(dtype=wp.vec3),
                   q_ids: wp.array(dtype=wp.vec3i), q_w: wp.array(dtype=wp.vec3), frame: mlp.Frame, raw: int,
                   out: wp.array(dtype=wp.float32)):
    """Finished pair distances (user units) of points in ``frame``'s coordinates and their locations."""
    i = wp.tid()
    p = ps[i]
    q = qs[i]
    d = landmark_distance(net, lm, mlp.to_net(frame, p), p_ids[i], p_w[i], mlp.to_net(frame, q), q_ids[i], q_w[i])
    out[i] = finish_distance(d, p, q, frame, 0.0, False, raw)
