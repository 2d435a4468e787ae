"""The generalizable model's input checks on clouds that stay on a CUDA device (torch tensors and wp.arrays):
domain, degeneracy, sizes and non-finite points refused as for the same points from numpy, word for word."""
import numpy as np
import pytest

from neurogf_warp.common.checks import InputError
from neurogf_warp.generalizable import model as gm

from .conftest import shared_path

pytestmark = pytest.mark.gpu


@pytest.fixture(scope="module")
def torch_cuda():
    import torch

    if not torch.cuda.is_available():
        pytest.skip("torch has no CUDA device")
    return torch


@pytest.fixture(scope="module")
def model():
    return gm.load(shared_path("checkpoints", "official", "GenNeuroGF.pth"))


def _cloud(n, seed=3, center=(0.0, 0.0, 0.0), axes=(2.0, 1.0, 0.5)):
    g = np.random.default_rng(seed).standard_normal((n, 3))
    return g / np.linalg.norm(g, axis=1, keepdims=True) * np.array(axes) + np.array(center)


def _on_device(torch, pts, kind):
    t = torch.as_tensor(np.asarray(pts, np.float32), device="cuda:0")
    if kind == "torch":
        return t
    import warp as wp

    return wp.from_torch(t.contiguous(), dtype=wp.vec3)


def _host_error(model, pts):
    with pytest.raises(ValueError) as e:
        model.condition(np.asarray(pts, np.float32).astype(np.float64), device="cuda:0")
    return e


DEGENERATE = {
    "repeated": lambda: np.tile(_cloud(5), (410, 1))[:2048],
    "few_distinct": lambda: np.concatenate([_cloud(39), _cloud(39)[:30]]),
    "line": lambda: np.array([3.0, 1.0, -2.0]) + np.linspace(-1.0, 1.0, 500)[:, None] * np.array([1.0, 2.0, 0.5]),
    "coincident": lambda: np.ones((100, 3)),
}


@pytest.mark.parametrize("kind", ["torch", "warp"])
@pytest.mark.parametrize("case", sorted(DEGENERATE))
def test_degenerate_device_clouds_are_refused_as_host_ones(torch_cuda, model, case, kind):
    pts = DEGENERATE[case]()
    host = _host_error(model, pts)
    with pytest.raises(InputError) as dev:
        model.condition(_on_device(torch_cuda, pts, kind), device="cuda:0")
    assert str(dev.value) == str(host.value)
    assert host.type is InputError


@pytest.mark.parametrize("kind", ["torch", "warp"])
def test_non_finite_device_clouds_name_the_row(torch_cuda, model, kind):
    pts = _cloud(300)
    pts[17, 1] = np.nan
    with pytest.raises(InputError, match="non-finite coordinate.*row 17"):
        model.condition(_on_device(torch_cuda, pts, kind), device="cuda:0")
    pts[17, 1] = np.inf
    with pytest.raises(InputError, match="non-finite coordinate.*row 17"):
        model.condition(_on_device(torch_cuda, pts, kind), device="cuda:0")


@pytest.mark.parametrize("kind", ["torch", "warp"])
def test_device_clouds_above_the_size_limit_are_refused(torch_cuda, model, kind, monkeypatch):
    pts = _cloud(300)
    with pytest.raises(InputError, match="300 points.*max_points=300"):
        model.condition(_on_device(torch_cuda, pts, kind), device="cuda:0", max_points=200)
    monkeypatch.setitem(gm.MAX_POINTS, "cuda", 250)
    with pytest.raises(InputError, match="300 points.*250 is the limit"):
        model.condition(_on_device(torch_cuda, pts, kind), device="cuda:0")
    assert model.condition(_on_device(torch_cuda, pts, kind), device="cuda:0", max_points=300).points.shape == \
        (300, 3)


def test_device_clouds_of_the_wrong_shape_or_too_few_points(torch_cuda, model):
    few = torch_cuda.as_tensor(_cloud(20), device="cuda:0")
    with pytest.raises(InputError, match="20 points; conditioning needs at least 40"):
        model.condition(few, device="cuda:0")
    with pytest.raises(ValueError, match=r"shape \(N, 3\).*\(300, 4\)"):
        model.condition(torch_cuda.zeros((300, 4), device="cuda:0"), device="cuda:0")
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        model.condition(torch_cuda.zeros((2, 300, 3), device="cuda:0"), device="cuda:0")


def test_device_conditioned_shapes_keep_the_domain(torch_cuda, model):
    """A cloud far from the origin, conditioned on the device: the same frame as from numpy, and points outside
    its domain refused by every query with the host path's message."""
    pts = _cloud(300, center=(5.0, -3.0, 1.0)).astype(np.float32)
    dev = model.condition(torch_cuda.as_tensor(pts, device="cuda:0"), device="cuda:0")
    host = model.condition(pts.astype(np.float64), device="cuda:0")
    np.testing.assert_array_equal(dev.center, host.center)
    assert dev.scale == host.scale
    far = dev.center + np.array([0.0, 0.0, 1e6])
    inside = dev.center + np.array([1.45 / dev.scale, 0.0, 0.0])
    assert np.isfinite(dev.distance(inside, dev.points[0]))
    for c in (dev, host):
        with pytest.raises(ValueError, match=r"q\[0\] = .* outside the model's domain"):
            c.distance(c.points[:1], far[None])
        with pytest.raises(ValueError, match="outside"):
            c.ssad(far)
        with pytest.raises(ValueError, match=r"targets\[0\]"):
            c.distance_matrix(c.points[:1], far[None])
    with pytest.raises(ValueError, match="non-finite"):
        dev.distance(torch_cuda.tensor([[np.nan, 0.0, 0.0]], device="cuda:0"), dev.points[:1])


@pytest.mark.parametrize("scale", [1e-30, 1e31])
def test_device_clouds_beyond_float32_are_refused_as_host_ones(torch_cuda, model, scale):
    pts = _cloud(300) * scale
    host = _host_error(model, pts)
    with pytest.raises(InputError, match="outside the supported range") as dev:
        model.condition(torch_cuda.as_tensor(pts, dtype=torch_cuda.float64, device="cuda:0"), device="cuda:0")
    assert str(dev.value) == str(host.value)
