"""NeuroGF inference as Warp functions and kernels (float32, BatchNorm folded into the weights).

The ``@wp.func`` functions take a ``NeuroGFWeights`` struct and one query, so they can be called from any
user kernel (one thread per query, no tiles, no shared memory). The kernels below batch them.
All coordinates here are in the network's normalized unit-sphere frame.

Gradients with respect to the query point (``distance_and_gradient``, ``signed_distance_and_gradient``) are
backpropagated by hand through the head, the lifting layers and the Fourier features: Warp's autodiff does not
replay these dynamic loops correctly. At a ReLU kink (pre-activation exactly 0) the unit counts as off, and where
e_p = e_q in a channel |e_p - e_q| has slope 0, as in torch's autograd: the result is one subgradient of the
piecewise-smooth network. ``kernels.field`` gathers the functions meant for user kernels.

Local vectors are sized for the largest supported D (512); loops run to the actual widths, which are
read from the weight shapes, so one compiled module serves every D and every network option
(Fourier input octaves from the first layer's width; ``euclid`` and ``residual`` are 0/1 flags).
"""
from typing import Any

import warp as wp

MAX_D = 512
NAN = wp.constant(float("nan"))
vec_d = wp.types.vector(length=MAX_D, dtype=wp.float32)  # an embedding
vec_h = wp.types.vector(length=MAX_D // 2, dtype=wp.float32)  # hidden layers (at most D/2 wide)
vec_acc = wp.types.vector(length=MAX_D // 4, dtype=wp.float64)  # head accumulators (D/4 wide)
MAX_FOURIER = 8
vec_feat = wp.types.vector(length=3 + 6 * MAX_FOURIER, dtype=wp.float64)  # lifting input features
# Sums run in float64: with float32 weights alone the outputs are within ~7e-6 of a float64 evaluation,
# float32 sums would add as much again.


@wp.struct
class NeuroGFWeights:
    """Folded weights: every layer is y = relu(W x + b) except the bias-free output layers."""

    # lifting: 3 -> D/4 -> D/2 -> D
    l0_w: wp.array2d(dtype=wp.float32)
    l0_b: wp.array(dtype=wp.float32)
    l1_w: wp.array2d(dtype=wp.float32)
    l1_b: wp.array(dtype=wp.float32)
    l2_w: wp.array2d(dtype=wp.float32)
    l2_b: wp.array(dtype=wp.float32)
    # distance head on |e_p - e_q|: D -> H -> H -> 1
    g0_w: wp.array2d(dtype=wp.float32)
    g0_b: wp.array(dtype=wp.float32)
    g1_w: wp.array2d(dtype=wp.float32)
    g1_b: wp.array(dtype=wp.float32)
    g2_w: wp.array2d(dtype=wp.float32)
    # SDF head on e_x, same shape
    s0_w: wp.array2d(dtype=wp.float32)
    s0_b: wp.array(dtype=wp.float32)
    s1_w: wp.array2d(dtype=wp.float32)
    s1_b: wp.array(dtype=wp.float32)
    s2_w: wp.array2d(dtype=wp.float32)
    # path guidance on [e_p | e_q]: 2D -> D
    c_w: wp.array2d(dtype=wp.float32)
    c_b: wp.array(dtype=wp.float32)
    # point-wise path head on [xyz | g]: D+3 -> D/2 -> D/4 -> D/8 -> 3
    p0_w: wp.array2d(dtype=wp.float32)
    p0_b: wp.array(dtype=wp.float32)
    p1_w: wp.array2d(dtype=wp.float32)
    p1_b: wp.array(dtype=wp.float32)
    p2_w: wp.array2d(dtype=wp.float32)
    p2_b: wp.array(dtype=wp.float32)
    p3_w: wp.array2d(dtype=wp.float32)
    # options (network.py): distance += euclid * |p - q|; path points += residual * straight-line point, the
    # head's offsets scaled by sin(pi t) where window = 1
    euclid: wp.float32
    residual: wp.float32
    window: wp.float32


@wp.func
def _dense_relu(w: wp.array2d(dtype=wp.float32), b: wp.array(dtype=wp.float32), x: Any) -> vec_h:
    """relu(W x + b) for x a vec_h or a vec_d (float64 sums)."""
    y = vec_h()
    for i in range(w.shape[0]):
        acc = wp.float64(b[i])
        for k in range(w.shape[1]):
            acc += wp.float64(w[i, k]) * wp.float64(x[k])
        y[i] = wp.max(wp.float32(acc), 0.0)
    return y


@wp.func
def _dot_row(w: wp.array2d(dtype=wp.float32), row: int, x: vec_h) -> float:
    acc = wp.float64(0.0)
    for k in range(w.shape[1]):
        acc += wp.float64(w[row, k]) * wp.float64(x[k])
    return wp.float32(acc)


@wp.func
def features(x: wp.vec3, n: int) -> vec_feat:
    """The lifting input: [x, sin(2^k pi x_c), cos(2^k pi x_c)] in network.fourier_features' order (n = 3 + 6L)."""
    f = vec_feat()
    L = (n - 3) // 6
    for c in range(3):
        xc = wp.float64(x[c])
        f[c] = xc
        w = wp.float64(3.141592653589793)
        for k in range(L):
            f[3 + c * L + k] = wp.sin(w * xc)  # float64: arguments reach 2^L pi
            f[3 + 3 * L + c * L + k] = wp.cos(w * xc)
            w = w * wp.float64(2.0)
    return f


@wp.func
def _lift_first(net: NeuroGFWeights, x: wp.vec3) -> vec_h:
    """The first lifting layer (features -> D/4)."""
    n = net.l0_w.shape[1]
    f = features(x, n)
    h0 = vec_h()
    for i in range(net.l0_w.shape[0]):
        acc = wp.float64(net.l0_b[i])
        for k in range(n):
            acc += wp.float64(net.l0_w[i, k]) * f[k]
        h0[i] = wp.max(wp.float32(acc), 0.0)
    return h0


@wp.func
def lift_hidden(net: NeuroGFWeights, x: wp.vec3) -> vec_h:
    """The first two lifting layers (features -> D/4 -> D/2)."""
    return _dense_relu(net.l1_w, net.l1_b, _lift_first(net, x))


@wp.func
def _embed_from_hidden(net: NeuroGFWeights, h1: vec_h) -> vec_d:
    e = vec_d()
    for k in range(net.l2_w.shape[0]):
        e[k] = wp.max(net.l2_b[k] + _dot_row(net.l2_w, k, h1), 0.0)
    return e


@wp.func
def embed(net: NeuroGFWeights, x: wp.vec3) -> vec_d:
    """The point embedding e(x) (first D entries used)."""
    return _embed_from_hidden(net, lift_hidden(net, x))


@wp.func
def _head_tail(w1: wp.array2d(dtype=wp.float32), b1: wp.array(dtype=wp.float32),
               w2: wp.array2d(dtype=wp.float32), h: vec_h) -> float:
    h1 = _dense_relu(w1, b1, h)
    return _dot_row(w2, 0, h1)


@wp.func
def distance_from_embeddings(net: NeuroGFWeights, ep: vec_d, eq: vec_d) -> float:
    """gdf_head(|e_p - e_q|): symmetric in p and q by construction."""
    h = vec_h()
    for j in range(net.g0_w.shape[0]):
        acc = wp.float64(net.g0_b[j])
        for k in range(net.g0_w.shape[1]):
            acc += wp.float64(net.g0_w[j, k]) * wp.float64(wp.abs(ep[k] - eq[k]))
        h[j] = wp.max(wp.float32(acc), 0.0)
    return _head_tail(net.g1_w, net.g1_b, net.g2_w, h)


@wp.func
def distance_to_embedding(net: NeuroGFWeights, es: wp.array2d(dtype=wp.float32), row: int, s: wp.vec3,
                          x: wp.vec3) -> float:
    """Distance from source point s, whose embedding ``es[row]`` is precomputed (e.g. an SSAD source), to x.

    e(x) is streamed one channel at a time into the head's first layer, so it is never stored.
    """
    h1 = lift_hidden(net, x)
    acc = vec_acc()
    for j in range(net.g0_w.shape[0]):
        acc[j] = wp.float64(net.g0_b[j])
    for k in range(net.l2_w.shape[0]):
        d = wp.abs(es[row, k] - wp.max(net.l2_b[k] + _dot_row(net.l2_w, k, h1), 0.0))
        for j in range(net.g0_w.shape[0]):
            acc[j] += wp.float64(net.g0_w[j, k]) * wp.float64(d)
    h = vec_h()
    for j in range(net.g0_w.shape[0]):
        h[j] = wp.max(wp.float32(acc[j]), 0.0)
    return _head_tail(net.g1_w, net.g1_b, net.g2_w, h) + net.euclid * wp.length(x - s)


@wp.func
def geodesic_distance(net: NeuroGFWeights, p: wp.vec3, q: wp.vec3) -> float:
    """Predicted geodesic distance between two points (normalized frame). Callable from user kernels."""
    return distance_from_embeddings(net, embed(net, p), embed(net, q)) + net.euclid * wp.length(p - q)


@wp.func
def signed_distance(net: NeuroGFWeights, x: wp.vec3) -> float:
    """Predicted signed distance at x from the network's SDF head (normalized frame)."""
    h1 = lift_hidden(net, x)
    acc = vec_acc()
    for j in range(net.s0_w.shape[0]):
        acc[j] = wp.float64(net.s0_b[j])
    for k in range(net.l2_w.shape[0]):
        e = wp.max(net.l2_b[k] + _dot_row(net.l2_w, k, h1), 0.0)
        for j in range(net.s0_w.shape[0]):
            acc[j] += wp.float64(net.s0_w[j, k]) * wp.float64(e)
    h = vec_h()
    for j in range(net.s0_w.shape[0]):
        h[j] = wp.max(wp.float32(acc[j]), 0.0)
    return _head_tail(net.s1_w, net.s1_b, net.s2_w, h)


# ---- gradients with respect to the query point -----------------------------------------------------

@wp.func
def _back_relu(w: wp.array2d(dtype=wp.float32), g: Any, h: vec_h) -> vec_h:
    """The gradient at a layer's input h (its ReLU output) from the gradient g at its output: W^T g where
    h > 0, else 0 (float64 sums over a weight column)."""
    out = vec_h()
    for i in range(w.shape[1]):
        if h[i] > 0.0:
            acc = wp.float64(0.0)
            for k in range(w.shape[0]):
                acc += wp.float64(w[k, i]) * wp.float64(g[k])
            out[i] = wp.float32(acc)
    return out


@wp.func
def _lift_backward(net: NeuroGFWeights, x: wp.vec3, h0: vec_h, h1: vec_h, e: vec_d, ge: vec_d) -> wp.vec3:
    """d(out)/dx from d(out)/de = ge, back through the three lifting layers (h0, h1, e: their ReLU outputs at x)
    and the Fourier features. Transposed products run over weight columns with float64 sums."""
    gz = vec_d()  # through the last ReLU
    for k in range(net.l2_w.shape[0]):
        if e[k] > 0.0:
            gz[k] = ge[k]
    g0 = _back_relu(net.l1_w, _back_relu(net.l2_w, gz, h1), h0)
    # features (x, sin(w x_c), cos(w x_c)), w = 2^l pi: d/dx_c = 1, w cos(w x_c), -w sin(w x_c)
    n = net.l0_w.shape[1]
    L = (n - 3) // 6
    dx = wp.vec3()
    for c in range(3):
        xc = wp.float64(x[c])
        acc = wp.float64(0.0)
        for k in range(net.l0_w.shape[0]):
            acc += wp.float64(net.l0_w[k, c]) * wp.float64(g0[k])
        w = wp.float64(3.141592653589793)
        for l in range(L):
            gs = wp.float64(0.0)
            gc = wp.float64(0.0)
            for k in range(net.l0_w.shape[0]):
                gs += wp.float64(net.l0_w[k, 3 + c * L + l]) * wp.float64(g0[k])
                gc += wp.float64(net.l0_w[k, 3 + 3 * L + c * L + l]) * wp.float64(g0[k])
            acc += w * (wp.cos(w * xc) * gs - wp.sin(w * xc) * gc)
            w = w * wp.float64(2.0)
        dx[c] = wp.float32(acc)
    return dx


@wp.func
def _head_and_gradient(w0: wp.array2d(dtype=wp.float32), b0: wp.array(dtype=wp.float32),
                       w1: wp.array2d(dtype=wp.float32), b1: wp.array(dtype=wp.float32),
                       w2: wp.array2d(dtype=wp.float32), a: vec_d):
    """A head (D -> H -> H -> 1) at input a: its output (the same sums as the forward functions) and d(out)/da."""
    h = _dense_relu(w0, b0, a)
    h1 = _dense_relu(w1, b1, h)
    out = _dot_row(w2, 0, h1)
    d1 = vec_h()
    for j in range(w1.shape[0]):
        if h1[j] > 0.0:
            d1[j] = w2[0, j]
    d0 = _back_relu(w1, d1, h)
    da = vec_d()
    for k in range(w0.shape[1]):
        acc = wp.float64(0.0)
        for i in range(w0.shape[0]):
            acc += wp.float64(w0[i, k]) * wp.float64(d0[i])
        da[k] = wp.float32(acc)
    return out, da


@wp.func
def signed_distance_and_gradient(net: NeuroGFWeights, x: wp.vec3):
    """(SDF head value, its gradient) at x: the gradient is the outward surface normal direction near the
    surface (unit length where the head is a true SDF). About the cost of two SDF evaluations."""
    h0 = _lift_first(net, x)
    h1 = _dense_relu(net.l1_w, net.l1_b, h0)
    e = _embed_from_hidden(net, h1)
    s, ge = _head_and_gradient(net.s0_w, net.s0_b, net.s1_w, net.s1_b, net.s2_w, e)
    return s, _lift_backward(net, x, h0, h1, e, ge)


@wp.func
def _distance_and_gradient_to(net: NeuroGFWeights, p: wp.vec3, h0: vec_h, h1: vec_h, ep: vec_d, eq: vec_d,
                              q: wp.vec3):
    """d(p, q) and d/dp from p's lifting activations and q's embedding."""
    a = vec_d()
    for k in range(net.g0_w.shape[1]):
        a[k] = wp.abs(ep[k] - eq[k])
    d, ga = _head_and_gradient(net.g0_w, net.g0_b, net.g1_w, net.g1_b, net.g2_w, a)
    ge = vec_d()
    for k in range(net.g0_w.shape[1]):  # d|u|/du = sign(u), 0 at u = 0
        if ep[k] > eq[k]:
            ge[k] = ga[k]
        elif ep[k] < eq[k]:
            ge[k] = -ga[k]
    g = _lift_backward(net, p, h0, h1, ep, ge)
    r = p - q
    n = wp.length(r)
    if n > 0.0:  # d|p - q|/dp = (p - q)/|p - q|, 0 at p = q
        g = g + (net.euclid / n) * r
    return d + net.euclid * n, g


@wp.func
def distance_and_gradient(net: NeuroGFWeights, p: wp.vec3, q: wp.vec3):
    """(d(p, q), its gradient with respect to p), normalized frame. -gradient points from p along the geodesic
    toward q (plus a normal part off the surface; project it onto the tangent plane). About the cost of
    ``geodesic_distance`` plus one lifting backward pass. Swap p and q for the gradient with respect to q."""
    h0 = _lift_first(net, p)
    h1 = _dense_relu(net.l1_w, net.l1_b, h0)
    return _distance_and_gradient_to(net, p, h0, h1, _embed_from_hidden(net, h1), embed(net, q), q)


@wp.func
def project_to_surface(net: NeuroGFWeights, x: wp.vec3, steps: int) -> wp.vec3:
    """Newton steps onto the SDF head's zero level set, x -= s grad / |grad|^2 with the analytic gradient, each
    step at most 2|s| long (a flat spot in a poorly fitted SDF must not throw the point away). Callable from
    user kernels."""
    y = x
    for _ in range(steps):
        s, g = signed_distance_and_gradient(net, y)
        n = wp.length(g)
        if n > 1.0e-12:
            y = y - (s / (n * wp.max(n, 0.5))) * g
    return y


# ---- batch kernels ---------------------------------------------------------------------------------

@wp.struct
class Frame:
    """User frame -> network frame: x_net = (x - center) * xscale, computed in float64 (the centre is float64, so a
    float32 point far from the origin keeps its own resolution); distances back to user units with * dscale.
    ``limit``: the domain, |x_net| <= limit on every axis (queries give NaN outside it). ``hi`` + ``lo``: the centre
    as a float32 pair (hi = float32(centre), lo = float32(centre - hi)): the tensor-core kernels map points as
    ((x - hi) - lo) * xscale, in float32 (float64 work cost them up to 16% on an H100)."""

    center: wp.vec3d
    xscale: wp.float32
    dscale: wp.float32
    limit: wp.float32
    hi: wp.vec3
    lo: wp.vec3


def make_frame(center, xscale: float, dscale: float | None = None, limit: float = 1.0e30) -> Frame:
    """A Frame from its centre (3 numbers, kept in float64), ``xscale`` and ``dscale`` (default 1 / xscale),
    with the float32 pair ``hi`` + ``lo`` derived from the centre (build Frames here: a Frame whose pair does not
    match its centre tests the domain at the wrong place)."""
    import numpy as np

    c = np.asarray(center, np.float64).reshape(3)
    hi = c.astype(np.float32)
    f = Frame()
    f.center = wp.vec3d(*c)
    f.xscale = float(xscale)
    f.dscale = float(1.0 / xscale if dscale is None else dscale)
    f.limit = float(limit)
    f.hi = wp.vec3(*hi)
    f.lo = wp.vec3(*(c - hi.astype(np.float64)).astype(np.float32))
    return f


@wp.func
def to_net(frame: Frame, x: wp.vec3) -> wp.vec3:
    """A point in mesh coordinates -> the network's frame: (x - centre) * xscale, computed in float64."""
    c = frame.center
    s = wp.float64(frame.xscale)
    return wp.vec3(wp.float32((wp.float64(x[0]) - c[0]) * s), wp.float32((wp.float64(x[1]) - c[1]) * s),
                   wp.float32((wp.float64(x[2]) - c[2]) * s))


@wp.func
def from_net(frame: Frame, y: wp.vec3) -> wp.vec3:
    """A point in the network's frame -> mesh coordinates: y * dscale + centre, computed in float64."""
    c = frame.center
    u = y * frame.dscale
    return wp.vec3(wp.float32(wp.float64(u[0]) + c[0]), wp.float32(wp.float64(u[1]) + c[1]),
                   wp.float32(wp.float64(u[2]) + c[2]))


@wp.func
def in_domain(frame: Frame, y: wp.vec3) -> bool:
    """Whether y (network frame) lies in the domain cube; False for NaN and inf."""
    return wp.abs(y[0]) <= frame.limit and wp.abs(y[1]) <= frame.limit and wp.abs(y[2]) <= frame.limit


@wp.kernel(enable_backward=False)
def embed_points(net: NeuroGFWeights, xs: wp.array(dtype=wp.vec3), frame: Frame, out: wp.array2d(dtype=wp.float32)):
    i = wp.tid()
    e = embed(net, to_net(frame, xs[i]))
    for k in range(out.shape[1]):
        out[i, k] = e[k]


@wp.kernel(enable_backward=False)
def distance_pairs(net: NeuroGFWeights, ps: wp.array(dtype=wp.vec3), qs: wp.array(dtype=wp.vec3),
                   frame: Frame, out: wp.array(dtype=wp.float32)):
    i = wp.tid()
    out[i] = geodesic_distance(net, to_net(frame, ps[i]), to_net(frame, qs[i])) * frame.dscale


@wp.kernel(enable_backward=False)
def signed_distances(net: NeuroGFWeights, xs: wp.array(dtype=wp.vec3), frame: Frame, out: wp.array(dtype=wp.float32)):
    """SDF values in user units; NaN for points outside the domain (as the tensor-core kernel)."""
    i = wp.tid()
    y = to_net(frame, xs[i])
    if in_domain(frame, y):
        out[i] = signed_distance(net, y) * frame.dscale
    else:
        out[i] = NAN


@wp.kernel(enable_backward=False)
def path_guidance(net: NeuroGFWeights, e: wp.array2d(dtype=wp.float32), n: int, g: wp.array2d(dtype=wp.float32)):
    """g[p, j] = relu(cdw_fc([e_p | e_q]))[j], one thread per (path, unit); e holds the p rows, then the q rows."""
    pi, j = wp.tid()
    D = net.c_w.shape[0]
    acc = wp.float64(net.c_b[j])
    for k in range(D):
        acc += wp.float64(net.c_w[j, k]) * wp.float64(e[pi, k]) + wp.float64(net.c_w[j, D + k]) * wp.float64(e[n + pi, k])
    g[pi, j] = wp.max(wp.float32(acc), 0.0)


@wp.kernel(enable_backward=False)
def path_first_layer(net: NeuroGFWeights, g: wp.array2d(dtype=wp.float32), pre: wp.array2d(dtype=wp.float32)):
    """The part of the path head's first layer that is constant along a path: b0 + W0[:, 3:] g."""
    pi, r = wp.tid()
    acc = wp.float64(net.p0_b[r])
    for j in range(g.shape[1]):
        acc += wp.float64(net.p0_w[r, 3 + j]) * wp.float64(g[pi, j])
    pre[pi, r] = wp.float32(acc)


@wp.kernel(enable_backward=False)
def path_points(net: NeuroGFWeights, ps: wp.array(dtype=wp.vec3), qs: wp.array(dtype=wp.vec3),
                pre: wp.array2d(dtype=wp.float32), frame: Frame, out: wp.array2d(dtype=wp.vec3)):
    """Point i of path n: the straight-line sample x = p + t (q - p), t = i/(m-1), through the point-wise head."""
    pi, i = wp.tid()
    m = out.shape[1]
    t = float(i) / float(wp.max(m - 1, 1))
    p = to_net(frame, ps[pi])
    x = p + t * (to_net(frame, qs[pi]) - p)
    h0 = vec_h()
    for r in range(net.p0_w.shape[0]):
        h0[r] = wp.max(pre[pi, r] + net.p0_w[r, 0] * x[0] + net.p0_w[r, 1] * x[1] + net.p0_w[r, 2] * x[2], 0.0)
    h1 = _dense_relu(net.p1_w, net.p1_b, h0)
    h2 = _dense_relu(net.p2_w, net.p2_b, h1)
    y = wp.vec3(_dot_row(net.p3_w, 0, h2), _dot_row(net.p3_w, 1, h2), _dot_row(net.p3_w, 2, h2))
    y = y * (1.0 - net.window + net.window * wp.sin(wp.pi * t)) + net.residual * x
    out[pi, i] = from_net(frame, y)


@wp.kernel(enable_backward=False)
def project_points(net: NeuroGFWeights, xs: wp.array(dtype=wp.vec3), frame: Frame, steps: int,
                   out: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    out[i] = from_net(frame, project_to_surface(net, to_net(frame, xs[i]), steps))


@wp.kernel(enable_backward=False)
def pin_and_project(net: NeuroGFWeights, ps: wp.array(dtype=wp.vec3), qs: wp.array(dtype=wp.vec3), frame: Frame,
                    steps: int, x: wp.array2d(dtype=wp.vec3)):
    """Start of path refinement, in place: end points := the queries, inner points onto the surface."""
    pi, i = wp.tid()
    m = x.shape[1]
    if i == 0:
        x[pi, i] = ps[pi]
    elif i == m - 1:
        x[pi, i] = qs[pi]
    else:
        x[pi, i] = from_net(frame, project_to_surface(net, to_net(frame, x[pi, i]), steps))


@wp.kernel(enable_backward=False)
def relax_paths(net: NeuroGFWeights, x: wp.array2d(dtype=wp.vec3), frame: Frame, steps: int,
                y: wp.array2d(dtype=wp.vec3)):
    """One Jacobi sweep of path shortening on the surface: each inner point moves to the midpoint of its
    neighbours, projected back onto the surface. Its fixed points are discrete geodesics."""
    pi, i = wp.tid()
    m = x.shape[1]
    if i == 0 or i == m - 1:
        y[pi, i] = x[pi, i]
    else:
        mid = 0.5 * (x[pi, i - 1] + x[pi, i + 1])
        y[pi, i] = from_net(frame, project_to_surface(net, to_net(frame, mid), steps))


@wp.func
def _path_length(x: wp.array2d(dtype=wp.vec3), row: int) -> wp.vec2:
    """(length, longest segment) of polyline ``row``."""
    total = float(0.0)
    longest = float(0.0)
    for i in range(x.shape[1] - 1):
        seg = wp.length(x[row, i + 1] - x[row, i])
        total += seg
        longest = wp.max(longest, seg)
    return wp.vec2(total, longest)


@wp.kernel(enable_backward=False)
def pick_shortest(x: wp.array2d(dtype=wp.vec3), n_cand: int, reversed_mask: wp.array(dtype=wp.int32),
                  out: wp.array2d(dtype=wp.vec3)):
    """Refined candidates of path n are rows n, n + N, n + 2N, ... of x (N = out.shape[0]; candidate c runs
    q -> p where reversed_mask[c]). Keep the shortest whose longest segment is at most 3x the mean: a much
    longer segment means the polyline jumps between sheets of the surface instead of following it."""
    pi, i = wp.tid()
    N = out.shape[0]
    m = x.shape[1]
    best = int(0)
    best_len = float(3.0e38)
    for c in range(n_cand):
        lm = _path_length(x, c * N + pi)
        if lm[1] * float(m - 1) <= 3.0 * lm[0] and lm[0] < best_len:
            best = c
            best_len = lm[0]
    j = i
    if reversed_mask[best] != 0:
        j = m - 1 - i
    out[pi, i] = x[best * N + pi, j]


@wp.kernel(enable_backward=False)
def resample_paths(x: wp.array2d(dtype=wp.vec3), out: wp.array2d(dtype=wp.vec3)):
    """Polylines to another point count, by linear interpolation in the point index (the sweeps keep the
    points about evenly spaced, so this is close to arc length)."""
    pi, i = wp.tid()
    u = float(i) * float(x.shape[1] - 1) / float(out.shape[1] - 1)
    k = wp.min(int(u), x.shape[1] - 2)
    f = u - float(k)
    out[pi, i] = (1.0 - f) * x[pi, k] + f * x[pi, k + 1]


@wp.kernel(enable_backward=False)
def straight_paths(ps: wp.array(dtype=wp.vec3), qs: wp.array(dtype=wp.vec3), out: wp.array2d(dtype=wp.vec3)):
    pi, i = wp.tid()
    t = float(i) / float(wp.max(out.shape[1] - 1, 1))
    out[pi, i] = ps[pi] + t * (qs[pi] - ps[pi])
