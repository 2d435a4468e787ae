"""Queries of landmark networks (``NeuroGFNet(landmarks=K, landmark_bracket=True)``) on the per-thread float32 kernels
(Warp's CPU device) against a float64 evaluation of the same network, the in-kernel landmark functions and their
gradient, and the refusals."""
import copy
import warnings

import numpy as np
import pytest
import torch
import trimesh
import warp as wp

import neurogf_warp as ngf
from neurogf_warp.inference.warp_structs import frame as user_frame
from neurogf_warp.inference.warp_structs import landmarks as landmark_struct
from neurogf_warp.inference.warp_structs import weights
from neurogf_warp.kernels import field
from neurogf_warp.kernels.inference import landmark
from neurogf_warp.model.network import LANDMARK_UNREACHED
from tests.test_inference import random_net

DEV = "cpu"
K = 8
TOL = 1e-5  # of the largest distance, as the per-thread tests against float64 (tests/test_inference.py)


def fresh_seed() -> int:
    return int(np.random.SeedSequence().entropy % 2**31)  # fresh inputs each run; the seed goes in failure messages


def make_table(V: np.ndarray, comp: np.ndarray, landmarks: np.ndarray) -> np.ndarray:
    """(V, K) float32 distances in a consistent per-vertex form: Euclidean distances to the landmark vertices
    stretched by 1..1.8 per landmark (so that the lower bound can exceed |p - q|, as geodesic ones do; any values
    serve for parity), UNREACHED across components (the stretched ones stay below it: the mesh fits the unit
    sphere)."""
    d = np.linalg.norm(V[:, None] - V[landmarks][None], axis=-1) * np.linspace(1.0, 1.8, len(landmarks))
    d[comp[:, None] != comp[landmarks][None]] = LANDMARK_UNREACHED
    return d.astype(np.float32)


def build(seed: int, two: bool = False, floor: float = 1.0, bracket: bool = True):
    """(model, net64, V, F, table in normalized units): an ellipsoid (or, with ``two``, the ellipsoid and a far
    sphere without landmarks) and a random landmark network (``bracket``: its bracket form) with K landmarks on the
    ellipsoid."""
    rng = np.random.default_rng(seed)
    tm = trimesh.creation.icosphere(subdivisions=2)
    V = tm.vertices * np.array([2.0, 1.6, 1.2]) - 1.0
    F = np.asarray(tm.faces)
    comp = np.zeros(len(V), int)
    if two:
        s = trimesh.creation.icosphere(subdivisions=1)
        F = np.concatenate([F, s.faces + len(V)])
        V = np.concatenate([V, 0.5 * s.vertices + np.array([4.0, 0.0, 0.0])])
        comp = np.concatenate([comp, np.ones(len(s.vertices), int)])
    V = V.astype(np.float32).astype(np.float64)  # float32 vertices, as mesh files hold: a float32 point can be one
    mesh = ngf.load_mesh((V, F))
    lm = rng.choice(np.flatnonzero(comp == 0), K, replace=False)
    table = make_table(mesh.normalize(V), comp, lm)
    net = random_net(64, seed, euclid=True, landmarks=K, landmark_bracket=bracket, landmark_floor=floor)
    model = ngf.Model(net=net, mesh=mesh, center=mesh.center, scale=mesh.scale, landmarks=table)
    return model, net, V, F, table


def reference(net, P, Q, TP, TQ):
    """The landmark network's distance in float64 (normalized units): P, Q (N, 3) normalized points, TP, TQ (N, K)
    their landmark rows; the formula of ``NeuroGFNet.distance_from_embeddings`` on tensors."""
    P, Q, TP, TQ = (a if isinstance(a, torch.Tensor) else torch.as_tensor(np.asarray(a), dtype=torch.float64)
                    for a in (P, Q, TP, TQ))
    e = net.embed(torch.cat([P, Q]))
    es, eq = e[: len(P)], e[len(P):]
    diff = (TP - TQ).abs()
    lower, upper = diff.max(-1).values, (TP + TQ).min(-1).values
    chord = torch.linalg.vector_norm(P - Q, dim=-1)
    floor = torch.maximum(chord, net.landmark_floor * lower)
    d = net.gdf_head(torch.cat([(es - eq).abs(), diff, lower[:, None], upper[:, None]], -1)).squeeze(-1)
    if not net.landmark_bracket:
        return d + floor if net.euclid else d
    inside = floor + torch.sigmoid(d) * (torch.maximum(upper, floor) - floor)
    return torch.where(upper >= 2 * LANDMARK_UNREACHED, chord + d, inside)


def rows_at(table, F, faces, bary):
    """Interpolated rows (N, K), float64, of points on ``faces`` with barycentric weights (N, 3)."""
    t = table.astype(np.float64)[F[faces]]  # (N, 3, K)
    return t[:, 0] + bary[:, 1:2] * (t[:, 1] - t[:, 0]) + bary[:, 2:] * (t[:, 2] - t[:, 0])


def surface_points(rng, V, F, n, faces=None):
    """n random points on the faces (mesh coordinates, float64): (points, faces, barycentric weights)."""
    f = rng.choice(len(F) if faces is None else faces, n)
    w = rng.dirichlet(np.ones(3), n)
    return (w[:, :, None] * V[F[f]]).sum(1), f, w


def check(got, ref, seed, what):
    ref = np.asarray(ref, np.float64)
    assert got.shape == ref.shape, what
    scale = np.abs(ref[np.isfinite(ref)]).max()
    same_inf = np.isinf(got) == np.isinf(ref)
    assert same_inf.all(), f"seed {seed}, {what}: infinities differ"
    fin = np.isfinite(ref)
    err = np.abs(got[fin] - ref[fin]).max()
    assert err <= TOL * scale, f"seed {seed}, {what}: max error {err:.3g} of {scale:.3g}"


@pytest.fixture(scope="module", autouse=True)
def _precompile():
    wp.load_module(landmark, device=DEV)


def test_reference_is_the_network():
    """The float64 reference formula is the network's own forward (float32, its table lookup) at vertices."""
    seed = fresh_seed()
    model, net, V, F, table = build(seed)
    net32 = copy.deepcopy(net).float()
    xyz = torch.from_numpy(model.normalized_vertices())
    net32.landmark_table.set_table(xyz, torch.from_numpy(table))
    rng = np.random.default_rng(seed)
    a, b = rng.integers(0, len(V), 50), rng.integers(0, len(V), 50)
    with torch.no_grad():
        own = net32.distance(xyz[a], xyz[b]).double().numpy()
        ref = reference(net, xyz[a].double(), xyz[b].double(), table[a], table[b]).numpy()
    assert np.abs(own - ref).max() <= 1e-5 * np.abs(ref).max(), f"seed {seed}"


@pytest.mark.parametrize("floor,bracket", [(1.0, True), (0.5, True), (0.5, False)])
def test_vertex_queries_match_float64(floor, bracket):
    """SSAD, MSAD and the distance matrix from vertices, with and without kept embeddings."""
    seed = fresh_seed()
    rng = np.random.default_rng(seed)
    model, net, V, F, table = build(seed, floor=floor, bracket=bracket)
    X = model.mesh.normalize(V)
    src = rng.choice(len(V), 3, replace=False)
    with torch.no_grad():
        ref = np.stack([reference(net, np.repeat(X[[s]], len(V), 0), X, np.repeat(table[[s]], len(V), 0), table)
                        .numpy() for s in src]) / model.mesh.scale
    for cache in (False, True):
        check(ngf.ssad(model, int(src[0]), device=DEV, raw=True, cache=cache), ref[0], seed, f"ssad cache={cache}")
    check(ngf.msad(model, src, device=DEV, raw=True), ref.min(0), seed, "msad")
    check(ngf.distance_matrix(model, src, device=DEV, raw=True), ref, seed, "distance matrix")
    # finished answers: 0 at the source, never below the straight line
    d = ngf.ssad(model, int(src[0]), device=DEV)
    chord = np.linalg.norm(V - V[src[0]], axis=1)
    assert d[src[0]] == 0.0 and np.all(d >= chord * (1 - 1e-6))


def test_point_queries_match_float64():
    """Point pairs at random surface points, a point source, targets given as points."""
    seed = fresh_seed()
    rng = np.random.default_rng(seed)
    model, net, V, F, table = build(seed)
    s = model.mesh.scale
    p, fp, bp = surface_points(rng, V, F, 40)
    q, fq, bq = surface_points(rng, V, F, 40)
    TP, TQ = rows_at(table, F, fp, bp), rows_at(table, F, fq, bq)
    norm = model.mesh.normalize
    with torch.no_grad():
        ref = reference(net, norm(p), norm(q), TP, TQ).numpy() / s
        X = norm(V)
        ref_src = reference(net, np.repeat(norm(p[:1]), len(V), 0), X, np.repeat(TP[:1], len(V), 0), table)
        ref_mat = reference(net, np.repeat(X[[5, 9]], 40, 0), np.tile(norm(q), (2, 1)), np.repeat(table[[5, 9]], 40, 0),
                            np.tile(TQ, (2, 1))).numpy().reshape(2, 40) / s
    check(ngf.distance(model, p, q, device=DEV, raw=True), ref, seed, "point pairs")
    check(ngf.ssad(model, p[0], device=DEV, raw=True), ref_src.numpy() / s, seed, "point source")
    check(ngf.distance_matrix(model, [5, 9], q, device=DEV, raw=True), ref_mat, seed, "vertex sources, point targets")
    got = ngf.distance(model, p, q, device=DEV)  # finished: symmetric, 0 for a point and itself
    assert np.array_equal(got, ngf.distance(model, q, p, device=DEV))
    assert np.all(ngf.distance(model, p, p, device=DEV) == 0.0)


def test_point_at_a_vertex_is_the_vertex():
    """A point exactly at a vertex gets that vertex's row: its answers are the vertex's own, bit for bit, and its
    location is the vertex with weights (1, 0, 0)."""
    seed = fresh_seed()
    model, net, V, F, table = build(seed)
    rng = np.random.default_rng(seed)
    for i in rng.choice(len(V), 3, replace=False):
        i = int(i)
        assert np.array_equal(ngf.ssad(model, V[i], device=DEV, raw=True), ngf.ssad(model, i, device=DEV, raw=True))
    from neurogf_warp.inference.state import query_state

    st = query_state(model, DEV)
    md = st.mesh("test")
    lm = md.landmark_table(model)
    ids, w = wp.empty(md.V, dtype=wp.vec3i, device=DEV), wp.empty(md.V, dtype=wp.vec3, device=DEV)
    wp.launch(landmark.locate_points, md.V, inputs=[lm, md.verts, st.frame], outputs=[ids, w], device=DEV)
    assert np.array_equal(ids.numpy(), np.repeat(np.arange(md.V)[:, None], 3, 1))
    assert np.array_equal(w.numpy(), np.tile([1.0, 0.0, 0.0], (md.V, 1)).astype(np.float32))


def test_two_components():
    """Across components: +inf; on the component without landmarks: |p - q| + head (no bounds)."""
    seed = fresh_seed()
    rng = np.random.default_rng(seed)
    model, net, V, F, table = build(seed, two=True)
    comp = model.mesh.internal_components[model.mesh.input_to_internal]
    a, b = np.flatnonzero(comp == comp[0]), np.flatnonzero(comp != comp[0])
    X = model.mesh.normalize(V)
    s = model.mesh.scale
    for src in (int(a[3]), int(b[2])):
        with torch.no_grad():
            ref = reference(net, np.repeat(X[[src]], len(V), 0), X, np.repeat(table[[src]], len(V), 0), table).numpy()
        ref = ref / s
        ref[comp != comp[src]] = np.inf
        check(ngf.ssad(model, src, device=DEV, raw=True), ref, seed, f"ssad from {src}")
    # point pairs on the far component (every landmark unreached), and across
    faces_b = np.flatnonzero(np.isin(F[:, 0], b))
    p, fp, bp = surface_points(rng, V, F, 20, faces_b)
    q, fq, bq = surface_points(rng, V, F, 20, faces_b)
    with torch.no_grad():
        ref = reference(net, model.mesh.normalize(p), model.mesh.normalize(q), rows_at(table, F, fp, bp),
                        rows_at(table, F, fq, bq)).numpy() / s
    check(ngf.distance(model, p, q, device=DEV, raw=True), ref, seed, "pairs without landmarks")
    assert np.all(np.isinf(ngf.distance(model, p, V[a[:20]], device=DEV)))
    assert np.all(np.isinf(ngf.distance_matrix(model, [int(a[0])], p, device=DEV)))


@wp.kernel
def _user_kernel(net: field.NeuroGFWeights, lm: field.LandmarkTable, fr: field.Frame, ps: wp.array(dtype=wp.vec3),
                 qs: wp.array(dtype=wp.vec3), d: wp.array(dtype=float), g: wp.array(dtype=wp.vec3),
                 d_only: wp.array(dtype=float), loc_ids: wp.array2d(dtype=wp.int32), loc_w: wp.array2d(dtype=float)):
    i = wp.tid()
    p = field.to_net(fr, ps[i])
    q = field.to_net(fr, qs[i])
    ip, wp_ = field.locate(lm, p)
    iq, wq = field.locate(lm, q)
    di, gi = field.landmark_distance_and_gradient(net, lm, p, ip, wp_, q, iq, wq)
    d[i] = di
    g[i] = gi
    d_only[i] = field.landmark_distance(net, lm, p, ip, wp_, q, iq, wq)
    for k in range(3):  # the locations of p and q
        loc_ids[i, k] = ip[k]
        loc_ids[i, 3 + k] = iq[k]
        loc_w[i, k] = wp_[k]
        loc_w[i, 3 + k] = wq[k]


@pytest.mark.parametrize("two,bracket", [(False, True), (True, True), (False, False)])
def test_in_kernel_distance_and_gradient(two, bracket):
    """field.landmark_distance(_and_gradient) in a user kernel against float64 torch autograd of the same formula,
    T(p) interpolated on the triangle that ``locate`` found, held fixed."""
    seed = fresh_seed()
    rng = np.random.default_rng(seed)
    model, net, V, F, table = build(seed, two=two, bracket=bracket)
    n = 24
    comp = model.mesh.internal_components[model.mesh.input_to_internal]
    faces = np.flatnonzero(comp[F[:, 0]] == (1 if two else 0))
    p, _, _ = surface_points(rng, V, F, n, faces)
    q, _, _ = surface_points(rng, V, F, n, faces)
    q[0] = V[F[faces[0], 1]]  # a vertex: its exact row
    net_w, lm = weights(model, DEV), landmark_struct(model, DEV)
    out = [wp.empty(n, dtype=t, device=DEV) for t in (float, wp.vec3, float)]
    out += [wp.empty((n, 6), dtype=wp.int32, device=DEV), wp.empty((n, 6), dtype=float, device=DEV)]
    wp.launch(_user_kernel, n, inputs=[net_w, lm, user_frame(model), wp.array(p.astype(np.float32), dtype=wp.vec3,
                                                                              device=DEV),
                                       wp.array(q.astype(np.float32), dtype=wp.vec3, device=DEV)],
              outputs=out, device=DEV)
    d, g, d_only, ids, bary = (a.numpy() for a in out)
    assert np.array_equal(d, d_only)
    # the reference: the same triangles (internal numbering, network frame), p's weights a function of p
    from neurogf_warp.inference.state import landmark_rows

    R = landmark_rows(model).astype(np.float64)
    pts = lm.points.numpy().astype(np.float64)
    P = torch.tensor(((p.astype(np.float32) - model.center) * np.float32(model.scale)), dtype=torch.float64,
                     requires_grad=True)
    Q = torch.tensor(((q.astype(np.float32) - model.center) * np.float32(model.scale)), dtype=torch.float64)
    a, b, c = (torch.from_numpy(pts[ids[:, k]]) for k in range(3))
    N = torch.cross(b - a, c - a, dim=-1)
    nn = (N * N).sum(-1, keepdim=True)
    w1 = (torch.cross(a - c, P - c, dim=-1) * N).sum(-1, keepdim=True) / nn
    w2 = (torch.cross(b - a, P - a, dim=-1) * N).sum(-1, keepdim=True) / nn
    r0, r1, r2 = (torch.from_numpy(R[ids[:, k]]) for k in range(3))
    TP = r0 + w1 * (r1 - r0) + w2 * (r2 - r0)
    iq, wq = ids[:, 3:], bary[:, 3:]
    TQ = torch.from_numpy(R[iq[:, 0]] + wq[:, 1:2] * (R[iq[:, 1]] - R[iq[:, 0]]) + wq[:, 2:] * (R[iq[:, 2]] - R[iq[:, 0]]))
    assert np.array_equal(iq[0], [iq[0, 0]] * 3) and np.array_equal(wq[0], [1, 0, 0]), (iq[0], wq[0], q[0], ids[0], V[F[faces[0]]])  # q[0], a vertex
    ref = reference(net, P, Q, TP, TQ)
    ref.sum().backward()
    ref = ref.detach().numpy()
    gref = P.grad.numpy()
    assert np.abs(d - ref).max() <= TOL * np.abs(ref).max(), f"seed {seed}"
    err = np.linalg.norm(g - gref, axis=1)
    assert np.all(err <= 1e-4 * np.linalg.norm(gref, axis=1).max()), f"seed {seed}: gradient error {err.max():.3g}"


def test_fp16_is_refused_and_auto_is_fp32():
    model, *_ = build(fresh_seed())  # K = 8: not a multiple of 16, so no tensor-core query at all
    for q in (lambda: ngf.ssad(model, 0, device=DEV, precision="fp16"),
              lambda: ngf.distance(model, model.mesh.vertices[:2], model.mesh.vertices[2:4], device=DEV,
                                   precision="fp16")):
        with pytest.raises(ValueError, match="K = 8 landmarks.*precision='fp32'"):
            q()
    from neurogf_warp.inference.backends import backend_of
    from neurogf_warp.inference.state import query_state

    assert backend_of(query_state(model, DEV), "auto").precision == "fp32"


def test_other_landmark_designs_are_refused():
    tm = trimesh.creation.icosphere(subdivisions=1)
    mesh = ngf.load_mesh((tm.vertices, tm.faces))
    table = np.ones((mesh.n_input, K), np.float32)
    for opt in (dict(landmark_bracket_log=True), dict(landmark_pair_inputs=True)):
        net = random_net(64, 1, landmarks=K, landmark_bracket=True, **opt)
        model = ngf.Model(net=net, mesh=mesh, center=mesh.center, scale=mesh.scale, landmarks=table)
        with pytest.raises(ValueError, match=next(iter(opt))):
            ngf.ssad(model, 0, device=DEV, precision="fp32")


def test_gradients_through_queries_are_refused():
    model, *_ = build(fresh_seed())
    p = torch.tensor(model.mesh.vertices[:2], dtype=torch.float32, requires_grad=True)
    with pytest.raises(ValueError, match="landmark_distance_and_gradient"):
        ngf.distance(model, p, p.detach() + 0.01)


def test_sdf_and_paths_still_run():
    """The SDF and path heads of a landmark network are the plain ones: they match float64 torch as before, and
    refined paths (which compare distances of their pieces) run."""
    seed = fresh_seed()
    rng = np.random.default_rng(seed)
    model, net, V, F, table = build(seed)
    p, _, _ = surface_points(rng, V, F, 8)
    q, _, _ = surface_points(rng, V, F, 8)
    P, Q = (torch.from_numpy(model.mesh.normalize(x)) for x in (p, q))
    with torch.no_grad():
        s_ref = net.sdf(P).numpy() / model.mesh.scale
        path_ref = net.path(P, Q, 16).numpy() / model.mesh.scale + model.center
    check(ngf.sdf(model, p, device=DEV), s_ref, seed, "sdf")
    got = ngf.path(model, p, q, m=16, project=None, device=DEV)  # the head's own points
    assert np.abs(got - path_ref).max() <= TOL * np.abs(path_ref).max(), f"seed {seed}"
    with warnings.catch_warnings():  # a random network's paths leave the surface, and refinement says so
        warnings.simplefilter("ignore")
        refined = ngf.path(model, p[:2], q[:2], m=8, refine=1, project="mesh", device=DEV)
    assert refined.shape == (2, 8, 3) and np.all(np.isfinite(refined))
