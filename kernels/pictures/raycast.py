"""Ray casting a shaded triangle mesh into an image: a scalar field as colours with isolines, overlays in flat colours.

One thread per image sample: a pinhole-camera ray through ``wp.mesh_query_ray`` (BVH), the hit's per-vertex
normal and value interpolated with its barycentrics, a colour from a piecewise-linear colour map, Lambert +
ambient (+ a weak specular) shading from a light near the camera, lit from both sides (open meshes show their
inside). Faces with an overlay colour (path tubes, markers) skip the colour map. A second pass draws isolines
where a sample's level index (floor of the value in isoline units) differs from a neighbour's.
No display, no OpenGL: runs on any Warp device.
"""
import warp as wp

AMBIENT = 0.36
DIFFUSE = 0.60
SPECULAR = 0.12
SHININESS = 40.0
NO_VALUE = wp.constant(wp.vec3(0.72, 0.72, 0.72))  # surface where the field is undefined (NaN)
LINE_DARKEN = 0.35  # isoline colour = this * the surface colour


@wp.struct
class Camera:
    """Ray through image sample (x, y) of (width, height): forward + sx * right + sy * up, sx, sy in [-1, 1]."""

    eye: wp.vec3
    forward: wp.vec3
    right: wp.vec3  # half the image width at distance 1
    up: wp.vec3  # half the image height at distance 1
    light: wp.vec3  # unit vector toward the light
    width: int
    height: int


@wp.struct
class Scene:
    mesh: wp.uint64
    faces: wp.array(dtype=wp.int32)  # the mesh's corner indices, 3 per face
    normals: wp.array(dtype=wp.vec3)  # per vertex
    values: wp.array(dtype=float)  # per vertex, in colour-map units (0 .. 1 over the value range); NaN: none
    levels: float  # isoline levels per colour-map unit (0: no isolines)
    face_color: wp.array(dtype=wp.int32)  # per face: -1 = coloured by the field, k = palette[k]
    palette: wp.array(dtype=wp.vec3)
    stops: wp.array(dtype=wp.vec3)  # colour map: equally spaced colours from 0 to 1
    background: wp.vec3


@wp.func
def colormap(stops: wp.array(dtype=wp.vec3), t: float) -> wp.vec3:
    n = stops.shape[0]
    u = wp.clamp(t, 0.0, 1.0) * float(n - 1)
    k = wp.min(int(u), n - 2)
    f = u - float(k)
    return (1.0 - f) * stops[k] + f * stops[k + 1]


@wp.kernel(enable_backward=False)
def trace(scene: Scene, cam: Camera, rgb: wp.array2d(dtype=wp.vec3), level: wp.array2d(dtype=wp.int32)):
    """Shaded colour and isoline level of every sample; level -1 where no field value is shown."""
    y, x = wp.tid()
    sx = (2.0 * (float(x) + 0.5) / float(cam.width)) - 1.0
    sy = 1.0 - (2.0 * (float(y) + 0.5) / float(cam.height))
    d = wp.normalize(cam.forward + sx * cam.right + sy * cam.up)
    q = wp.mesh_query_ray(scene.mesh, cam.eye, d, 1.0e30)
    level[y, x] = -1
    if not q.result:
        rgb[y, x] = scene.background
        return
    i0 = scene.faces[3 * q.face]
    i1 = scene.faces[3 * q.face + 1]
    i2 = scene.faces[3 * q.face + 2]
    w = 1.0 - q.u - q.v
    n = q.u * scene.normals[i0] + q.v * scene.normals[i1] + w * scene.normals[i2]
    if wp.length(n) < 1.0e-12:
        n = q.normal
    n = wp.normalize(n)
    if wp.dot(n, d) > 0.0:  # two-sided
        n = -n
    k = scene.face_color[q.face]
    base = NO_VALUE
    if k >= 0:
        base = scene.palette[k]
    else:
        v = q.u * scene.values[i0] + q.v * scene.values[i1] + w * scene.values[i2]
        if wp.isfinite(v):
            base = colormap(scene.stops, v)
            if scene.levels > 0.0:
                level[y, x] = int(wp.floor(wp.clamp(v, 0.0, 1.0) * scene.levels * 0.999999))
    h = wp.normalize(cam.light - d)
    lam = wp.max(wp.dot(n, cam.light), 0.0)
    spec = wp.pow(wp.max(wp.dot(n, h), 0.0), SHININESS)
    c = base * (AMBIENT + DIFFUSE * lam) + wp.vec3(SPECULAR * spec)
    rgb[y, x] = wp.vec3(wp.min(c[0], 1.0), wp.min(c[1], 1.0), wp.min(c[2], 1.0))


@wp.kernel(enable_backward=False)
def isolines(level: wp.array2d(dtype=wp.int32), radius: int, rgb: wp.array2d(dtype=wp.vec3),
             out: wp.array2d(dtype=wp.vec3)):
    """Darken samples within ``radius`` samples (along the axes) of a change of level between field samples."""
    y, x = wp.tid()
    c = rgb[y, x]
    out[y, x] = c
    me = level[y, x]
    if me < 0:
        return
    H = level.shape[0]
    W = level.shape[1]
    for r in range(1, radius + 1):
        for a in range(4):
            yy = y
            xx = x
            if a == 0:
                xx = x + r
            elif a == 1:
                xx = x - r
            elif a == 2:
                yy = y + r
            else:
                yy = y - r
            if yy >= 0 and yy < H and xx >= 0 and xx < W:
                o = level[yy, xx]
                if o >= 0 and o != me:
                    out[y, x] = LINE_DARKEN * c
                    return
