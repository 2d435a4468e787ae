"""The generalizable model given hostile clouds and query arguments: the per-mesh model's rules (dtypes, shapes,
sizes, domain) and errors that name the argument; never a silent wrong answer or a raw numpy/torch exception."""
import numpy as np
import pytest
import torch
import trimesh

import neurogf_warp as ngf
from neurogf_warp.common.checks import InputError
from neurogf_warp.generalizable import model as gm

from .conftest import shared_path


@pytest.fixture(scope="module")
def gen():
    return gm.load(shared_path("checkpoints", "official", "GenNeuroGF.pth"))


def _cloud(n=256, seed=5):
    g = np.random.default_rng(seed).standard_normal((n, 3))
    return g / np.linalg.norm(g, axis=1, keepdims=True) * np.array([1.5, 1.0, 0.6])


@pytest.fixture(scope="module")
def cond(gen):
    return gen.condition(_cloud())


CLOUDS = {
    "booleans": (lambda: np.ones((256, 3), bool), "numeric coordinates.*bool"),
    "complex": (lambda: _cloud().astype(complex), "numeric coordinates.*complex128"),
    "objects": (lambda: np.array(_cloud().tolist(), dtype=object), "numeric coordinates.*object"),
    "None": (lambda: None, "numeric coordinates"),
    "ragged": (lambda: [[0, 0, 0], [1, 1]], "rows of different lengths"),
    "meta tensor": (lambda: torch.zeros((256, 3), device="meta"), "'meta' device"),
    "tiny (1e-30)": (lambda: _cloud() * 1e-30, "outside the supported range"),
    "huge (1e31)": (lambda: _cloud() * 1e31, "outside the supported range"),
    "overflowing (1e300)": (lambda: _cloud() * 1e300, "outside the supported range"),
    "far (coordinates 1e33)": (lambda: _cloud() * 1e30 + 1e33, "outside the supported range"),
}


@pytest.mark.parametrize("case", sorted(CLOUDS))
def test_hostile_clouds_are_refused(gen, case):
    make, words = CLOUDS[case]
    with pytest.raises(InputError, match=words):
        gen.condition(make())


def test_condition_arguments_are_checked(gen):
    V, F = trimesh.creation.icosphere(subdivisions=2).vertices, trimesh.creation.icosphere(subdivisions=2).faces
    with pytest.raises(InputError, match="seed must be >= 0, got -1"):
        gen.condition((V, F), n_points=256, seed=-1)
    with pytest.raises(InputError, match="unknown device 'tpu'"):
        gen.condition(_cloud(), device="tpu")
    with pytest.raises(InputError, match="max_points must be an integer"):
        gen.condition(_cloud(), max_points=float("nan"))


def test_cloud_layouts_give_the_same_frame(gen):
    c = _cloud()
    want = gen.condition(c)
    for other in (np.asfortranarray(c), c.astype(np.float32).astype(np.float64), torch.from_numpy(c)):
        got = gen.condition(other)
        np.testing.assert_allclose(got.center, want.center, rtol=1e-6, atol=1e-7)
        assert got.scale == pytest.approx(want.scale, rel=1e-6)


QUERIES = {
    "ragged p": (lambda c: c.distance([[0, 0, 0], [1, 1]], c.points[:2]), InputError, "p has rows of different"),
    "mixed sources": (lambda c: c.msad([0, [0.1, 0.2, 0.3]]), InputError, "sources has rows of different"),
    "bool index": (lambda c: c.distance(True, 2), InputError, "p must be integer indices or float points"),
    "bool ssad": (lambda c: c.ssad(True), InputError, "booleans"),
    "meta tensor": (lambda c: c.distance(torch.zeros((1, 3), device="meta"), c.points[:1]), InputError, "'meta'"),
    "chunk 0": (lambda c: c.msad([1, 2], chunk=0), InputError, "chunk must be >= 1, got 0"),
    "chunk -1": (lambda c: c.msad([1, 2], chunk=-1), InputError, "chunk must be >= 1, got -1"),
    "chunk 1.5": (lambda c: c.msad([1, 2], chunk=1.5), InputError, "chunk must be an integer"),
    "far point": (lambda c: c.distance([1e6, 0, 0], c.points[0]), ValueError, "outside the model's domain"),
    "negative index": (lambda c: c.distance_matrix([0], [-1]), IndexError, r"targets: point index out of range"),
    "scalar points": (lambda c: c.distance(1.5, 2), ValueError, r"p must have shape \(M, 3\) or \(3,\)"),
    "2-D integers": (lambda c: c.msad(np.array([[0, 1, 2], [3, 4, 5]])), InputError, "integer array of shape"),
    "complex point": (lambda c: c.distance(c.points[:1].astype(complex), c.points[1:2]), InputError, "complex"),
    "evaluate": (lambda c: ngf.evaluate(c), InputError, "evaluate needs a per-mesh model.*Conditioned"),
}


@pytest.mark.parametrize("case", sorted(QUERIES))
def test_hostile_queries_of_a_conditioned_shape(cond, case):
    call, kind, words = QUERIES[case]
    with pytest.raises(kind, match=words):
        call(cond)


def test_repeated_and_low_precision_queries_answer(cond):
    np.testing.assert_array_equal(cond.msad([3, 3]), cond.ssad(3))
    half = cond.points[:4].astype(np.float16)
    np.testing.assert_array_equal(cond.distance(half, cond.points[4:8]),
                                  cond.distance(half.astype(np.float64), cond.points[4:8]))
    assert cond.distance(np.zeros((0, 3)), np.zeros((0, 3))).shape == (0,)
