"""Differentiable queries: gradients from the Warp kernels against float64 torch autograd of the same network."""
import copy

import numpy as np
import pytest
import torch

import neurogf_warp as ngf

pytestmark = pytest.mark.slow  # uses the trained fixture; the gradient kernels compile once


@pytest.fixture(scope="module")
def model(trained):
    """The test suite's trained model (the default network layout: Fourier inputs and the |p - q| term)."""
    return trained[0]


@pytest.fixture(scope="module")
def net64(model):
    return copy.deepcopy(model.net).double().eval()


def _surface_points(model, n, seed):
    import trimesh

    t = trimesh.Trimesh(model.mesh.internal_vertices, model.mesh.internal_faces, process=False)
    return trimesh.sample.sample_surface(t, n, seed=seed)[0]


def _ref_distance(model, net64, p, q):
    """float64 torch: max(network, |p - q|) in mesh units, as the public query answers."""
    c = torch.as_tensor(model.center)
    pn, qn = (p - c) * model.scale, (q - c) * model.scale
    d = net64.distance(pn, qn) / model.scale
    return torch.maximum(d, torch.linalg.vector_norm(p - q, dim=-1))


def test_distance_gradients_match_float64_autograd(model, net64):
    rng = np.random.default_rng(7)
    pts = _surface_points(model, 64, int(rng.integers(1 << 30)))
    p = torch.tensor(pts[:32], dtype=torch.float32, requires_grad=True)
    q = torch.tensor(pts[32:], dtype=torch.float32, requires_grad=True)
    w = torch.rand(32, dtype=torch.float32)
    d = ngf.distance(model, p, q, device="cpu")
    assert d.requires_grad
    np.testing.assert_array_equal(d.detach().numpy(), ngf.distance(model, p.detach(), q.detach(), device="cpu")
                                  .numpy())  # forward values are the plain query's, bit for bit
    (d * w).sum().backward()
    p64 = p.detach().double().requires_grad_(True)
    q64 = q.detach().double().requires_grad_(True)
    (_ref_distance(model, net64, p64, q64) * w.double()).sum().backward()
    for got, want in ((p.grad, p64.grad), (q.grad, q64.grad)):
        err = torch.linalg.vector_norm(got.double() - want) / torch.linalg.vector_norm(want)
        assert err < 1e-4, float(err)


def test_sdf_gradient_matches_float64_autograd(model, net64):
    rng = np.random.default_rng(8)
    x0 = _surface_points(model, 40, int(rng.integers(1 << 30))) + rng.normal(0, 0.05, (40, 3))
    x = torch.tensor(x0, dtype=torch.float32, requires_grad=True)
    ngf.sdf(model, x, device="cpu").sum().backward()
    x64 = torch.tensor(x0, dtype=torch.float64, requires_grad=True)
    c = torch.as_tensor(model.center)
    (net64.sdf((x64 - c) * model.scale) / model.scale).sum().backward()
    err = torch.linalg.vector_norm(x.grad.double() - x64.grad) / torch.linalg.vector_norm(x64.grad)
    assert err < 1e-4, float(err)


def test_ssad_and_msad_gradients_flow_to_their_sources(model, net64):
    rng = np.random.default_rng(9)
    src = _surface_points(model, 2, int(rng.integers(1 << 30)))
    V = torch.tensor(model.mesh.internal_vertices[:200], dtype=torch.float64)
    targets = model.mesh.index[:200]  # file indices of the first internal vertices
    w = torch.zeros(model.mesh.n_input)
    w[targets] = torch.rand(200, dtype=torch.float32)

    s = torch.tensor(src[0], dtype=torch.float32, requires_grad=True)
    (ngf.ssad(model, s, device="cpu").nan_to_num(0) * w).sum().backward()
    s64 = torch.tensor(src[0], dtype=torch.float64, requires_grad=True)
    ref = _ref_distance(model, net64, s64.expand(200, 3), V)
    (ref * w[targets].double()).sum().backward()
    assert torch.linalg.vector_norm(s.grad.double() - s64.grad) / torch.linalg.vector_norm(s64.grad) < 1e-4

    S = torch.tensor(src, dtype=torch.float32, requires_grad=True)
    m = ngf.msad(model, S, device="cpu")
    (m.nan_to_num(0) * w).sum().backward()
    S64 = torch.tensor(src, dtype=torch.float64, requires_grad=True)
    both = torch.stack([_ref_distance(model, net64, S64[i].expand(200, 3), V) for i in range(2)])
    (both.min(0).values * w[targets].double()).sum().backward()
    assert torch.linalg.vector_norm(S.grad.double() - S64.grad) / torch.linalg.vector_norm(S64.grad) < 1e-4


def test_no_gradient_means_the_plain_query(model):
    p = torch.tensor(model.mesh.vertices[:3], dtype=torch.float32)
    d = ngf.distance(model, p, p.flip(0), device="cpu")
    assert not d.requires_grad
    with torch.no_grad():
        pg = p.clone().requires_grad_(True)
        assert not ngf.distance(model, pg, p.flip(0), device="cpu").requires_grad
