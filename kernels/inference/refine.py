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
