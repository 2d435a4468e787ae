"""Paths a user can trust: default paths on the surface, refinement that never
returns a path worse than the head's or the straight line's (by the on-surface length it is chosen by, and on
average by Chamfer to the solver's paths), a point's path to itself is the point, NaN across components.

Models: the ``trained`` ellipsoid (conftest) and a torus trained two thirds as long (module fixture, ~20 s on 2
cores), a random network on two spheres (components), and the released fandisk checkpoint.
"""
import warnings

import numpy as np
import pytest
import torch
import warp as wp

import neurogf_warp as ngf
from neurogf_warp.evaluation import metrics as L
from neurogf_warp.inference import paths as paths_mod
from neurogf_warp.inference.paths import PathWarning, surface_fit
from neurogf_warp.mesh.surface import snap_to_mesh
from tests.conftest import shared_path

DEV = "cpu"


@pytest.fixture(scope="module")
def torus(tmp_path_factory):
    """A 512-vertex torus (tube radius 0.35) trained with the ``cpu_small`` preset: a model whose path head
    cuts through the solid and whose SDF is rough, as short CPU runs give."""
    import trimesh

    from neurogf_warp.dataset.build import build_dataset
    from neurogf_warp.mesh.mesh import load_mesh
    from neurogf_warp.training import preset, train

    mesh = load_mesh(trimesh.creation.torus(major_radius=1.0, minor_radius=0.35, major_sections=32,
                                            minor_sections=16))
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        cfg = preset("cpu_small", querier_steps=30, epochs=2, iters_per_epoch=100)
        data = build_dataset(mesh, None, cfg.data, device=DEV, progress=False)
        return train(mesh, tmp_path_factory.mktemp("torus") / "t.ngf", config=cfg, dataset=data, device=DEV,
                     progress=False)
    finally:
        torch.set_num_threads(n)


@pytest.fixture(scope="module")
def ellipsoid_model(trained):
    return trained[0]


def _pairs(model, n, seed):
    """n random vertex pairs (distinct vertices), as points."""
    rng = np.random.default_rng(seed)
    V = model.mesh.vertices
    i = rng.integers(0, len(V), n)
    j = (i + rng.integers(1, len(V), n)) % len(V)
    return V[i], V[j]


def _off_mesh(model, x):
    """Distance of every point of x (..., 3) from the mesh, mesh units."""
    snapped = snap_to_mesh(model, x, device=DEV)[0]
    return np.linalg.norm(np.asarray(snapped, np.float64) - np.asarray(x, np.float64), axis=-1)


def _diag(model):
    v = model.mesh.vertices
    return float(np.linalg.norm(v.max(0) - v.min(0)))


@pytest.mark.slow
@pytest.mark.parametrize("which", ["torus", "ellipsoid_model"])
def test_default_paths_lie_on_the_mesh(which, request):
    """With a mesh attached, every point of a default path (no options) is on the mesh (it was the head's point,
    up to 10% of the tube radius inside or outside the torus); project=None still gives the head's points."""
    model = request.getfixturevalue(which)
    p, q = _pairs(model, 24, 1)
    default = ngf.path(model, p, q, m=32, device=DEV)
    tol = 1e-6 * _diag(model)
    assert _off_mesh(model, default).max() <= tol
    raw = ngf.path(model, p, q, m=32, project=None, device=DEV)
    np.testing.assert_array_equal(np.asarray(default), np.asarray(snap_to_mesh(model, raw, device=DEV)[0]))
    # faces and barycentrics come with the default too (it is project="mesh")
    pts, faces, bary = ngf.path(model, p[:3], q[:3], m=8, return_faces=True, device=DEV)
    assert faces.shape == (3, 8) and bary.shape == (3, 8, 3) and _off_mesh(model, pts).max() <= tol
    refined = ngf.path(model, p[:8], q[:8], m=32, refine=5, device=DEV)
    assert _off_mesh(model, refined).max() <= tol


def _candidates(model, p, q, m):
    """What refinement competes with: the head's path and the straight line, each snapped to the mesh (ends kept,
    as refine keeps them)."""
    head = np.asarray(ngf.path(model, p, q, m=m, project=None, device=DEV), np.float64)
    t = np.linspace(0, 1, m)[None, :, None]
    straight = p[:, None] * (1 - t) + q[:, None] * t
    out = []
    for x in (head, straight):
        s = np.asarray(snap_to_mesh(model, x.astype(np.float32), device=DEV)[0], np.float64)
        s[:, 0], s[:, -1] = p, q
        out.append(s.astype(np.float32))
    return out


def _follows(length, excess, m):
    return excess <= paths_mod.SURFACE_TOL * length / (m - 1)


@pytest.mark.slow
@pytest.mark.parametrize("which,sweeps,precision", [("torus", 20, "fp32"), ("ellipsoid_model", 5, "fp32"),
                                                     ("ellipsoid_model", 5, "fp16")])
def test_refined_never_worse_by_the_criterion(which, sweeps, precision, request):
    """Per pair: the refined path follows the surface and is no longer along it than the head's path or the
    straight line (both snapped), whichever of those follows the surface; and it neither zigzags nor loops (on
    these smooth surfaces consecutive chords turn by less than 45 degrees)."""
    model = request.getfixturevalue(which)
    p, q = _pairs(model, 32, 2)
    m = 64
    with warnings.catch_warnings():
        warnings.simplefilter("error", PathWarning)
        ref = ngf.path(model, p, q, m=m, refine=sweeps, device=DEV, precision=precision)
    lr, er = surface_fit(model, ref, device=DEV)
    assert np.all(_follows(lr, er, m))
    for other in _candidates(model, p, q, m):
        lo, eo = surface_fit(model, other, device=DEV)
        ok = _follows(lo, eo, m)
        assert np.all(lr[ok] <= lo[ok] * (1 + 1e-5)), (lr[ok] - lo[ok]).max()
    d = np.diff(np.asarray(ref, np.float64), axis=1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    assert np.all((d[:, 1:] * d[:, :-1]).sum(-1) > np.cos(np.radians(45)))


@pytest.mark.slow
@pytest.mark.parametrize("which", ["torus", "ellipsoid_model"])
def test_refined_paths_closer_to_solver_paths(which, request):
    """Chamfer-L1 to our solver's paths: refine=20 below the head's paths (raw and snapped) on average and at the
    90th percentile, and no refined path farther than the worst head path; lengths along the surface within a
    few percent of the solver's."""
    model = request.getfixturevalue(which)
    mesh = model.mesh
    rng = np.random.default_rng(3)
    src = int(rng.integers(0, len(mesh.vertices)))
    tg = rng.choice(np.delete(np.arange(len(mesh.vertices)), src), 16, replace=False)
    gt = ngf.geodesic_paths(mesh, mesh.index[src], mesh.index[tg], m=64, device=DEV)
    p, q = gt[:, 0], gt[:, -1]
    norm = lambda x: mesh.normalize(np.asarray(x, np.float64).reshape(-1, 3)).reshape(np.shape(x))
    cd = lambda x: L.chamfer_l1(norm(x), norm(gt))
    raw = ngf.path(model, p, q, m=64, project=None, device=DEV)
    snapped = ngf.path(model, p, q, m=64, device=DEV)
    ref = ngf.path(model, p, q, m=64, refine=20, device=DEV)
    c_raw, c_snap, c_ref = cd(raw), cd(snapped), cd(ref)
    for c in (c_raw, c_snap):
        assert c_ref.mean() < c.mean() and np.quantile(c_ref, 0.9) <= np.quantile(c, 0.9), (c_ref, c)
    assert c_ref.max() <= max(c_raw.max(), c_snap.max())
    length = lambda x: np.linalg.norm(np.diff(np.asarray(x, np.float64), axis=1), axis=2).sum(1)
    assert np.abs(surface_fit(model, ref, device=DEV)[0] / length(gt) - 1).max() < 0.05


@pytest.mark.slow
@pytest.mark.parametrize("refine", [0, 3])
@pytest.mark.parametrize("project", ["auto", None, "sdf", "mesh"])
def test_path_from_a_point_to_itself_is_the_point(torus, refine, project):
    """Rows with p == q (vertices and points off the surface, mixed with other pairs) come back as the point
    repeated: p itself, or its projection (one point) with a projection; other rows are unaffected."""
    V = torus.mesh.vertices
    rng = np.random.default_rng(4)
    p = V[rng.integers(0, len(V), 6)].astype(np.float32)
    p[3:] += np.float32(0.05) * rng.normal(size=(3, 3)).astype(np.float32)  # off the surface
    q = p.copy()
    q[[1, 4]] = V[rng.integers(0, len(V), 2)]  # two ordinary pairs among them
    x = np.asarray(ngf.path(torus, p, q, m=16, refine=refine, project=project, device=DEV))
    same = np.array([0, 2, 3, 5])
    assert np.all(x[same] == x[same, :1]), "a path from a point to itself moves"
    if project is None:
        np.testing.assert_array_equal(x[same, 0], p[same])
    elif project in ("auto", "mesh"):
        np.testing.assert_array_equal(x[same, 0], snap_to_mesh(torus, p[same], device=DEV)[0])
    else:
        np.testing.assert_array_equal(x[same, 0], ngf.project(torus, p[same], steps=2 * paths_mod.PROJECT_STEPS,
                                                              device=DEV))
    assert np.all(np.linalg.norm(np.diff(x[[1, 4]], axis=1), axis=2).sum(1) > 0)
    one = np.asarray(ngf.path(torus, p[0], p[0], m=5, refine=refine, project=project, device=DEV))
    assert one.shape == (5, 3) and np.all(one == one[:1])


def _two_spheres():
    """A random network on two disjoint spheres (two components)."""
    import trimesh

    from neurogf_warp.model.network import NeuroGFNet

    torch.manual_seed(0)
    a = trimesh.creation.icosphere(subdivisions=2)
    v = np.vstack([a.vertices, a.vertices + [3.0, 0.0, 0.0]])
    f = np.vstack([a.faces, a.faces + len(a.vertices)])
    mesh = ngf.load_mesh((v, f))
    return ngf.Model(net=NeuroGFNet(64).eval(), mesh=mesh, center=mesh.center, scale=mesh.scale), len(a.vertices)


@pytest.mark.parametrize("refine", [0, 2])
def test_paths_across_components_stay_nan(refine):
    model, k = _two_spheres()
    V = model.mesh.vertices
    p, q = V[[0, 1, 2]], V[[5, k + 3, 2]]  # within one sphere, across, the same point
    for project in ("auto", None):
        with warnings.catch_warnings():
            warnings.simplefilter("error", PathWarning)  # the cross pair's path leaves the surface: no warning
            x = np.asarray(ngf.path(model, p, q, m=8, refine=refine, project=project, device=DEV))
        assert np.all(np.isfinite(x[0])) and np.all(np.isnan(x[1])) and np.all(x[2] == x[2, :1])


@pytest.mark.slow
def test_warns_when_no_candidate_follows_the_surface(torus, monkeypatch):
    """A pair none of whose candidates follows the surface gets the least-leaving one and a PathWarning that
    counts them (forced here: a negative tolerance refuses every candidate)."""
    p, q = _pairs(torus, 4, 5)
    monkeypatch.setattr(paths_mod, "SURFACE_TOL", -1.0)
    with pytest.warns(PathWarning, match="4 of 4 refined paths leave the surface"):
        x = ngf.path(torus, p, q, m=16, refine=2, project=None, device=DEV)
    length, excess = surface_fit(torus, x, device=DEV)
    assert np.all(np.isfinite(excess))


def test_surface_fit_sees_a_jump():
    """A polyline along a sphere follows it; one that cuts through the solid does not, and counts its detour."""
    import trimesh

    tm = trimesh.creation.icosphere(subdivisions=5)
    model, _ = _two_spheres()
    model = ngf.Model(net=model.net, mesh=ngf.load_mesh((tm.vertices, tm.faces)))
    t = np.linspace(0, np.pi, 65)
    arc = np.stack([np.cos(t), np.sin(t), 0 * t], -1)[None].astype(np.float32)  # half a great circle
    chord = np.stack([np.cos(t), 0 * t, 0 * t], -1)[None].astype(np.float32)  # the diameter between its ends
    chord = np.asarray(snap_to_mesh(model, chord, device=DEV)[0])  # each point on the sphere: a jump across
    la, ea = surface_fit(model, arc, device=DEV)
    lc, ec = surface_fit(model, chord, device=DEV)
    assert np.all(_follows(la, ea, 65)) and not np.any(_follows(lc, ec, 65))
    assert abs(la[0] / np.pi - 1) < 1e-3  # the arc's length along the sphere: pi (the mesh is within 1e-3)
    with pytest.raises(ValueError, match="shape"):
        surface_fit(model, arc[0], device=DEV)


@pytest.mark.slow
def test_refinement_without_a_mesh_uses_the_sdf_surface():
    """The released fandisk model without its mesh: refined paths are chosen on the SDF head's surface, never
    longer along it than the head's path projected there, and p == q rows are the point."""
    model = ngf.load(shared_path("checkpoints", "official", "NeuroGF_Pretrainer__fandisk_final.pth"))
    withmesh = ngf.load(shared_path("checkpoints", "official", "NeuroGF_Pretrainer__fandisk_final.pth"),
                        mesh=shared_path("meshes", "fandisk.obj"))
    v = withmesh.mesh.internal_normalized_vertices
    rng = np.random.default_rng(6)
    p, q = v[rng.integers(0, len(v), 6)], v[rng.integers(0, len(v), 6)]
    q[5] = p[5]
    ref = ngf.path(model, p, q, m=32, refine=3, device=DEV)
    head = ngf.path(model, p, q, m=32, project="sdf", device=DEV)
    head[:, 0], head[:, -1] = p, q
    lr, er = surface_fit(model, ref, device=DEV)
    lh, eh = surface_fit(model, head, device=DEV)
    ok = _follows(lh, eh, 32)
    assert np.all(lr[ok] <= lh[ok] * (1 + 1e-5))
    assert np.all(ref[5] == ref[5, :1])
    # the default without a mesh: the head's points, as before
    np.testing.assert_array_equal(ngf.path(model, p, q, m=8, device=DEV), ngf.path(model, p, q, m=8, project=None,
                                                                                   device=DEV))


def test_released_fandisk_refined_paths():
    """Released fandisk with its mesh against the solver's paths (was test_inference's SDF-surface version):
    ends pinned, every point on the mesh, lengths within 2% of the solver's, lower mean Chamfer than the head."""
    model = ngf.load(shared_path("checkpoints", "official", "NeuroGF_Pretrainer__fandisk_final.pth"),
                     mesh=shared_path("meshes", "fandisk.obj"))
    mesh = model.mesh
    rng = np.random.default_rng(3)
    tg = rng.choice(len(mesh.vertices), 8, replace=False)
    gt = ngf.geodesic_paths(mesh, 11, tg, m=64, device=DEV)
    p, q = gt[:, 0], gt[:, -1]
    raw = ngf.path(model, p, q, m=64, project=None, device=DEV)
    ref = ngf.path(model, p, q, m=64, refine=20, project=None, device=DEV)
    np.testing.assert_allclose(ref[:, 0], p, atol=1e-6)
    np.testing.assert_allclose(ref[:, -1], q, atol=1e-6)
    assert _off_mesh(model, ref).max() <= 1e-6 * _diag(model)
    lg = np.linalg.norm(np.diff(gt, axis=1), axis=2).sum(1)
    assert np.abs(surface_fit(model, ref, device=DEV)[0] / lg - 1).max() < 0.02
    norm = lambda x: mesh.normalize(x.reshape(-1, 3)).reshape(x.shape)
    assert L.chamfer_l1(norm(ref), norm(gt)).mean() < L.chamfer_l1(norm(raw), norm(gt)).mean()


def test_bad_project_option():
    model, _ = _two_spheres()
    nomesh = ngf.Model(net=model.net)
    x = np.zeros((1, 3), np.float32)
    with pytest.raises(ValueError, match="project must be"):
        ngf.path(model, x, x + 0.1, project="surface", device=DEV)
    with pytest.raises(ValueError, match="needs the model's mesh"):
        ngf.path(nomesh, x, x + 0.1, project="mesh", device=DEV)
    with pytest.raises(ValueError, match="return_faces"):
        ngf.path(nomesh, x, x + 0.1, return_faces=True, device=DEV)
    assert isinstance(ngf.path(model, wp.array(x, dtype=wp.vec3, device=DEV), wp.array(x + 0.1, dtype=wp.vec3,
                                                                                           device=DEV), m=4), wp.array)


class _Along:
    """A stand-in backend whose distance between two points is the straight one, plus 5 where they lie on
    different sides of the plane x = 0 (a gap that the surface goes around)."""

    def pairs(self, a, b, out, raw, frame):
        pa, pb = a.numpy(), b.numpy()
        d = np.linalg.norm(pb - pa, axis=1) + 5.0 * (np.sign(pa[:, 0]) != np.sign(pb[:, 0]))
        wp.copy(out, wp.array(d.astype(np.float32), dtype=wp.float32, device=out.device))


def test_a_candidate_that_jumps_a_gap_counts_as_leaving_the_surface():
    """Refinement snaps points to the closest surface point, so a candidate can cross a gap narrower than a point
    spacing with every chord near the surface (a cow model: refined paths 15-20% shorter than the geodesic). The
    network's distance across the gap is far longer than the straight distance: such a candidate's excess exceeds
    the tolerance, and one that stays on its side keeps its excess."""
    m = 33
    t = np.linspace(0.0, 1.0, m)
    across = np.stack([t - 0.5, 0.2 * t, 0 * t], 1)          # crosses x = 0
    beside = np.stack([t + 0.1, 0.2 * t, 0 * t], 1)          # stays at x > 0
    x = wp.array(np.stack([across, beside]).astype(np.float32), dtype=wp.vec3, device=DEV)
    excess = wp.zeros(2, dtype=wp.float32, device=DEV)
    length = wp.array(np.linalg.norm(np.diff(np.stack([across, beside]), axis=1), axis=2).sum(1).astype(np.float32),
                      dtype=wp.float32, device=DEV)
    both = np.stack([across, beside]).astype(np.float32)
    ends = lambda k: wp.array(both[:, k], dtype=wp.vec3, device=DEV)  # noqa: E731
    paths_mod._fold_jumps(_Along(), x, excess, DEV, None, length, ends(0), ends(-1))
    spacing = np.linalg.norm(np.diff(across, axis=0), axis=1).mean()
    e = excess.numpy()
    assert e[0] > paths_mod.SURFACE_TOL * spacing * 10, e
    assert abs(e[1]) < 1e-5, e


def test_a_candidate_shorter_than_the_networks_distance_counts_as_leaving_the_surface():
    """No path on the surface is shorter than the geodesic: a candidate shorter than SHORT_OF times the network's
    distance between its ends (here the stand-in's 5 + the straight distance) jumped somewhere, even where every
    span looks ordinary; one as long as that distance keeps its excess."""
    m = 33
    t = np.linspace(0.0, 1.0, m)
    short = np.stack([-0.5 + 0 * t, 0.3 * t - 0.15, 0 * t], 1)  # all at x < 0: no span crosses x = 0
    x = wp.array(short[None].astype(np.float32), dtype=wp.vec3, device=DEV)
    P = wp.array(np.array([[-0.5, -0.15, 0.0]], np.float32), dtype=wp.vec3, device=DEV)
    Q = wp.array(np.array([[0.5, 0.15, 0.0]], np.float32), dtype=wp.vec3, device=DEV)  # the stand-in's far side
    for length, flagged in ((0.3, True), (6.5, False)):
        excess = wp.zeros(1, dtype=wp.float32, device=DEV)
        L = wp.array([length], dtype=wp.float32, device=DEV)
        paths_mod._fold_jumps(_Along(), x, excess, DEV, None, L, P, Q)
        assert (excess.numpy()[0] > 1.0) == flagged, (length, excess.numpy())
