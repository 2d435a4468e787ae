"""Answers that do not depend on where the mesh sits, check=False rows, source forms and the chord bound
on Warp's CPU device."""
import numpy as np
import pytest
import torch
import warp as wp

import neurogf_warp as ngf
from neurogf_warp.model.network import NeuroGFNet

from .conftest import shared_path

DEV = "cpu"
F32 = np.finfo(np.float32)


@pytest.fixture(scope="module")
def fandisk():
    model = ngf.load(shared_path("checkpoints", "official", "NeuroGF_Pretrainer__fandisk_final.pth"),
                     mesh=shared_path("meshes", "fandisk.obj"))
    return model


def moved(model, shift=0.0, factor=1.0):
    """The same network on its mesh moved by ``shift`` and scaled by ``factor`` (normalization from the mesh)."""
    m = model.mesh
    mesh = ngf.load_mesh((m.vertices * factor + shift, m.faces))
    return ngf.Model(net=model.net, mesh=mesh, center=mesh.center, scale=mesh.scale)


def small_model(D=64, seed=0, offset=0.0, **options):
    import trimesh

    torch.manual_seed(seed)
    tm = trimesh.creation.icosphere(subdivisions=2)
    mesh = ngf.load_mesh((tm.vertices * [1.5, 1.0, 0.8] + offset, tm.faces))
    return ngf.Model(net=NeuroGFNet(D, **options).eval(), mesh=mesh, center=mesh.center, scale=mesh.scale)


# ---- item 1: far from the origin ------------------------------------------------------------------------------

@pytest.mark.slow
@pytest.mark.parametrize("shift", [1e3, -3.7e5, 1e6, np.array([1e8, -2e7, 5e7])], ids=str)
def test_moved_mesh_gives_the_same_answers(fandisk, shift):
    """SSAD (from a vertex and from a point), MSAD and point-pair distances of the mesh moved far from the origin
    equal the unmoved answers to float32 resolution (the coordinates are normalized in float64 first); points
    given as float64 host arrays keep their full precision."""
    far = moved(fandisk, shift)
    rng = np.random.default_rng(1)
    V = fandisk.mesh.vertices
    i, j = rng.integers(0, len(V), 16), rng.integers(0, len(V), 16)
    pt = V[7] + 0.01
    kw = dict(device=DEV, precision="fp32")
    scale = float(np.nanmax(ngf.ssad(fandisk, 5, **kw)))
    tol = 4e-6 * scale  # a few float32 steps of the distance range: the inputs agree to float64 resolution
    for name, a, b in (("ssad vertex", ngf.ssad(fandisk, 5, **kw), ngf.ssad(far, 5, **kw)),
                       ("ssad point", ngf.ssad(fandisk, pt, **kw), ngf.ssad(far, pt + shift, **kw)),
                       ("msad", ngf.msad(fandisk, [3, 900], **kw), ngf.msad(far, [3, 900], **kw)),
                       ("distance", ngf.distance(fandisk, V[i], V[j], **kw),
                        ngf.distance(far, V[i] + shift, V[j] + shift, **kw))):
        err = np.nanmax(np.abs(a - b))
        assert err <= tol, f"{name} moved by {shift}: error {err:.3g} (tolerance {tol:.3g})"
    # the mesh's own vertices are inside the domain at any offset
    ngf.distance(far, far.mesh.vertices[:4], far.mesh.vertices[4:8], device=DEV)


@pytest.mark.parametrize("factor", [1e-12, 1e19])
def test_tiny_and_huge_meshes_work_or_are_refused(fandisk, factor):
    """Scaled by 1e19 (float32 still holds the distances): the same SSAD times the factor; 1e-12 likewise."""
    kw = dict(device=DEV, precision="fp32")
    base = ngf.ssad(fandisk, 5, **kw)
    got = ngf.ssad(moved(fandisk, 0.0, factor), 5, **kw)
    assert np.all(np.isfinite(got)) and np.nanmax(got) > 0
    np.testing.assert_allclose(got / factor, base, rtol=1e-5, atol=1e-5 * np.nanmax(base))


def test_mesh_beyond_float32_is_refused(fandisk):
    with pytest.raises(ValueError, match="float32"):
        ngf.ssad(moved(fandisk, 0.0, 1e39), 5, device=DEV)


@pytest.mark.parametrize("kind", ["torch", "warp"])
def test_float32_device_points_far_away_are_exact_to_their_own_resolution(fandisk, kind):
    """float32 points on a device, 1e5 from the origin: the answers are those of the float32 values as given
    (the same points as float64 host arrays), i.e. no further rounding than the input's own."""
    shift = np.array([1.3e5, -2.1e5, 7e4])
    far = moved(fandisk, shift)
    rng = np.random.default_rng(2)
    V = far.mesh.vertices
    p32 = V[rng.integers(0, len(V), 12)].astype(np.float32)
    q32 = V[rng.integers(0, len(V), 12)].astype(np.float32)
    ref = ngf.distance(far, p32.astype(np.float64), q32.astype(np.float64), device=DEV, precision="fp32")
    ref_sdf = ngf.sdf(far, p32.astype(np.float64), device=DEV, precision="fp32")
    conv = (lambda a: torch.from_numpy(a)) if kind == "torch" else (lambda a: wp.array(a, dtype=wp.vec3, device=DEV))
    got = ngf.distance(far, conv(p32), conv(q32), device=DEV, precision="fp32")
    got_sdf = ngf.sdf(far, conv(p32), device=DEV, precision="fp32")
    got, got_sdf = (np.asarray(g.numpy() if hasattr(g, "numpy") else g) for g in (got, got_sdf))
    # both routes round each coordinate once to float32 at the mesh's own scale (the host route after taking the
    # centre off, the device route after scaling): a few float32 steps of the bounding radius apart
    step = float(np.spacing(np.float32(1.0 / far.scale)))
    np.testing.assert_allclose(got, ref, rtol=0, atol=8 * step)
    np.testing.assert_allclose(got_sdf, ref_sdf, rtol=0, atol=8 * step)
    # the same points given to the unmoved mesh (float64, exact): the move costs nothing beyond those steps
    here = ngf.distance(fandisk, p32 - shift, q32 - shift, device=DEV, precision="fp32")
    np.testing.assert_allclose(got, here, rtol=0, atol=8 * step)


def test_paths_of_a_moved_mesh(fandisk):
    """Path points come back in the moved coordinates, equal to the unmoved ones plus the shift to float32
    resolution of the output's magnitude."""
    shift = np.array([2.5e3, -1e3, 4e3])
    far = moved(fandisk, shift)
    V = fandisk.mesh.vertices
    a = ngf.path(fandisk, V[[1, 50]], V[[3000, 6000]], m=8, device=DEV, precision="fp32")
    b = ngf.path(far, V[[1, 50]] + shift, V[[3000, 6000]] + shift, m=8, device=DEV, precision="fp32")
    ulp = np.spacing(np.float32(np.abs(shift).max() * 2))
    assert np.abs((b - shift) - a).max() <= 4 * ulp + 1e-5


# ---- item 3: check=False ------------------------------------------------------------------------------------------------

BAD_ROWS = [[np.nan, 0.0, 0.0], [np.inf, 0.0, 0.0], [0.0, -np.inf, np.nan], "far"]


@pytest.mark.slow
@pytest.mark.parametrize("precision", ["fp32", "fp16"])
def test_check_false_gives_nan_rows_for_bad_points(precision):
    """check=False: a NaN, infinite or far (outside the domain) point gives NaN for distance, sdf and path rows,
    never 0, +inf or a number; the other rows are the checked answers. ssad from such a point is refused."""
    model = small_model(fourier=2, euclid=True, path_residual=True, path_window=True)
    V = model.mesh.vertices
    far = model.mesh.center + 10.0 / model.scale
    bad = np.array([far if r == "far" else r for r in BAD_ROWS], dtype=np.float64)
    good = V[:4]
    p = np.vstack([good, bad, good[:1]])
    q = np.vstack([good[::-1], good, bad[:1]])
    kw = dict(device=DEV, precision=precision)
    d = ngf.distance(model, p, q, check=False, **kw)
    assert np.all(np.isnan(d[4:])), d
    np.testing.assert_array_equal(d[:4], ngf.distance(model, good, good[::-1], **kw))
    s = ngf.sdf(model, p, check=False, **kw)
    assert np.all(np.isnan(s[4:8])) and np.all(np.isfinite(s[:4])), s
    # device input (float32 mesh coordinates, the kernels' own frame): the same rows are NaN
    s_dev = ngf.sdf(model, wp.array(p.astype(np.float32), dtype=wp.vec3, device=DEV), check=False, **kw).numpy()
    assert np.all(np.isnan(s_dev[4:8])) and np.all(np.isfinite(s_dev[:4])), s_dev
    P = ngf.path(model, p, q, m=8, check=False, **kw)
    assert np.all(np.isnan(P[4:])) and np.all(np.isfinite(P[:4]))
    for row in bad:
        with pytest.raises(ValueError, match="non-finite|outside the model's domain"):
            ngf.distance(model, row, V[0], **kw)
        with pytest.raises(ValueError, match="non-finite|outside the model's domain"):
            ngf.ssad(model, row, **kw)


def test_check_false_nan_on_a_mesh_of_two_parts():
    """Two components: a NaN point is NaN (not +inf, "another component"), and nothing reads out of bounds."""
    import trimesh

    a = trimesh.creation.icosphere(subdivisions=1)
    mesh = ngf.load_mesh((np.vstack([a.vertices, a.vertices + [3.0, 0, 0]]),
                          np.vstack([a.faces, a.faces + len(a.vertices)])))
    torch.manual_seed(0)
    model = ngf.Model(net=NeuroGFNet(64, euclid=True).eval(), mesh=mesh, center=mesh.center, scale=mesh.scale)
    V = mesh.vertices
    p = np.vstack([V[[0, 0]], [[np.nan, 0, 0]], [[0, np.inf, 0]]])
    q = V[[1, len(a.vertices) + 2, 0, len(a.vertices)]]
    d = ngf.distance(model, p, q, check=False, device=DEV, precision="fp32")
    assert np.isfinite(d[0]) and np.isinf(d[1]) and np.all(np.isnan(d[2:])), d


# ---- item 6: three floats are never one point by accident ---------------------------------------------------------------

@pytest.mark.parametrize("n", [1, 2, 3, 4])
def test_a_flat_list_of_floats_is_not_read_as_points(n):
    """msad / distance_matrix take vertex indices (S,) or points (S, 3); a flat list of floats is refused
    whatever its length, with how to pass points; the same values as integers are vertex indices."""
    model = small_model()
    kw = dict(device=DEV, precision="fp32")
    floats = [0.0, 10.0, 20.0, 30.0][:n]
    for fn in (ngf.msad, ngf.distance_matrix):
        with pytest.raises(ValueError, match=r"\(S, 3\)"):
            fn(model, floats, **kw)
        with pytest.raises(ValueError, match=r"\(S, 3\)"):
            fn(model, np.array(floats), **kw)
    ints = [0, 10, 20, 30][:n]
    np.testing.assert_array_equal(ngf.msad(model, ints, **kw),
                                  np.min([ngf.ssad(model, i, **kw) for i in ints], axis=0))
    pts = model.mesh.vertices[ints]
    np.testing.assert_allclose(ngf.msad(model, pts, **kw), ngf.msad(model, ints, **kw), rtol=1e-6, atol=1e-7)
    assert ngf.distance_matrix(model, pts, **kw).shape == (n, model.mesh.n_input)
    if n == 3:  # one point (3,) is a single source for ssad only
        np.testing.assert_array_equal(ngf.ssad(model, pts[0], **kw), ngf.msad(model, pts[:1], **kw))


# ---- item 8: never shorter than the chord -------------------------------------------------------------------------------

@pytest.mark.slow
@pytest.mark.parametrize("precision", ["fp32", "fp16"])
def test_distances_are_never_below_the_chord(precision):
    """A random (untrained) network's head goes negative often; every finished distance is at least the straight
    line |p - q| (pairs, SSAD, distance matrix), raw=True keeps the network's own values."""
    model = small_model(seed=4, fourier=2)
    rng = np.random.default_rng(3)
    V = model.mesh.vertices
    i, j = rng.integers(0, len(V), 64), rng.integers(0, len(V), 64)
    kw = dict(device=DEV, precision=precision)
    chord = np.linalg.norm(V[i] - V[j], axis=1)
    d = ngf.distance(model, V[i], V[j], **kw)
    raw = ngf.distance(model, V[i], V[j], raw=True, **kw)
    assert np.all(d >= chord.astype(np.float32) * (1 - 1e-6)), (d - chord).min()
    assert np.any(raw < chord * (1 - 1e-3)), "the test network should undercut the chord somewhere"
    src = int(i[0])
    row = ngf.ssad(model, src, **kw)
    c = np.linalg.norm(V - V[src], axis=1)
    assert np.all(row >= c.astype(np.float32) * (1 - 1e-6)) and row[src] == 0.0
    M = ngf.distance_matrix(model, [src, int(j[0])], **kw)
    assert np.all(M[0] >= c.astype(np.float32) * (1 - 1e-6))


@pytest.mark.parametrize("precision", ["fp32", "fp16"])
def test_iterated_points_do_not_depend_on_the_input_kind_far_away(precision):
    """Refined paths and projections iterate points; from float32 torch input 3e3 from the origin they equal those
    from the same values as float64 numpy (both iterate relative to the mesh centre: in float32 mesh coordinates
    the steps would be quantized at 2.4e-4, a tenth of the finite-difference step)."""
    model = small_model(seed=5, offset=3e3, fourier=2, euclid=True, path_residual=True, path_window=True)
    V = model.mesh.vertices.astype(np.float32)
    p, q = V[:5], V[20:25]
    kw = dict(device=DEV, precision=precision)
    for extra in (dict(refine=2), dict(project="sdf"), {}):
        a = ngf.path(model, p.astype(np.float64), q.astype(np.float64), m=8, **extra, **kw)
        b = ngf.path(model, torch.from_numpy(p), torch.from_numpy(q), m=8, **extra, **kw).numpy()
        np.testing.assert_array_equal(a, b, err_msg=str(extra))
    x = V[:6] + np.float32(0.05)
    np.testing.assert_array_equal(ngf.project(model, x.astype(np.float64), device=DEV),
                                  ngf.project(model, torch.from_numpy(x), device=DEV).numpy())
