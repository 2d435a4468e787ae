"""Per-mesh queries given hostile arrays and arguments: the right answer, or an error naming the argument and the
fix, never a raw numpy/Warp exception or a silent wrong answer. A small untrained model: only the input handling
is under test (the answers are compared with the same query on clean input)."""
import numpy as np
import pytest
import torch
import trimesh

import neurogf_warp as ngf
from neurogf_warp.common.checks import InputError


@pytest.fixture(scope="module")
def model():
    from neurogf_warp.model.model import Model
    from neurogf_warp.model.network import NeuroGFNet

    tm = trimesh.creation.icosphere(subdivisions=2)
    m = ngf.load_mesh((np.asarray(tm.vertices) * [1.0, 0.7, 0.5], np.asarray(tm.faces)))
    torch.manual_seed(0)
    return Model(net=NeuroGFNet(64), mesh=m, center=m.center, scale=m.scale)


def _pq(model):
    V = model.mesh.vertices
    return V[:4].copy(), V[4:8].copy()


# ---- refused, naming the argument -------------------------------------------------------------------------------

REFUSED = {
    "ragged p": (lambda m, P, Q: ngf.distance(m, [[0, 0, 0], [1, 1]], Q[:2]), InputError, r"^p has rows of different"),
    "ragged q": (lambda m, P, Q: ngf.distance(m, P[:2], [[0, 0, 0], [1]]), InputError, r"^q has rows of different"),
    "ragged x": (lambda m, P, Q: ngf.sdf(m, [[0.1, 0, 0], [0.2, 0]]), InputError, r"^x has rows of different"),
    "sources mixed": (lambda m, P, Q: ngf.msad(m, [0, [0.1, 0.2, 0.3]]),
        ValueError, r"^sources must be a vertex index"),
    "float index": (lambda m, P, Q: ngf.ssad(m, 1.5),
        TypeError, r"^source: a vertex index must be an integer, got 1.5"),
    "float index 2.0": (lambda m, P, Q: ngf.ssad(m, np.float64(2.0)), TypeError, r"must be an integer"),
    "bool index": (lambda m, P, Q: ngf.ssad(m, True), TypeError, "booleans"),
    "bool sources": (lambda m, P, Q: ngf.msad(m, np.array([True, False])), TypeError, "booleans"),
    "str source": (lambda m, P, Q: ngf.ssad(m, "3"), TypeError, "dtype <U1"),
    "None source": (lambda m, P, Q: ngf.ssad(m, None), ValueError, "got 'None'"),
    "negative target": (lambda m, P, Q: ngf.distance_matrix(m, [0], targets=[-1]),
        IndexError, "targets: vertex index -1"),
    "int64 beyond mesh": (lambda m, P, Q: ngf.msad(m, np.array([2 ** 40])), IndexError, "out of range"),
    "uint64 max": (lambda m, P, Q: ngf.ssad(m, np.uint64(2 ** 64 - 1)), IndexError, "out of range"),
    "int8 negative": (lambda m, P, Q: ngf.ssad(m, np.int8(-1)), IndexError, "negative"),
    "bool points": (lambda m, P, Q: ngf.distance(m, np.zeros((2, 3), bool), Q[:2]), TypeError, "p must hold numeric"),
    "complex points": (lambda m, P, Q: ngf.distance(m, P.astype(complex), Q), TypeError, "complex128"),
    "object points": (lambda m, P, Q: ngf.sdf(m, np.array([[0, 0, 0], [1, "a", 0]], object)),
        TypeError, "dtype object"),
    "nan point": (lambda m, P, Q: ngf.distance(m, P, np.r_[Q[:3], [[np.nan, 0, 0]]]),
        ValueError, r"q\[3\].*non-finite"),
    "inf point": (lambda m, P, Q: ngf.sdf(m, [[np.inf, 0, 0]]), ValueError, r"x\[0\].*non-finite"),
    "0-d point": (lambda m, P, Q: ngf.sdf(m, np.array(1.0)), InputError, r"x must have shape \(N, 3\), got \(\)"),
    "(N, 2) points": (lambda m, P, Q: ngf.distance(m, P[:, :2], Q[:, :2]), InputError, r"p must have shape \(N, 3\)"),
    "meta tensor": (lambda m, P, Q: ngf.sdf(m, torch.zeros((2, 3), device="meta")),
        InputError, "x is a torch tensor on the 'meta'"),
    "torch int points": (lambda m, P, Q: ngf.sdf(m, torch.zeros((2, 3), dtype=torch.int64)),
        TypeError, "floating-point"),
    "far point": (lambda m, P, Q: ngf.sdf(m, [[1e30, 0, 0]]), ValueError, "outside the model's domain"),
    "embed nan": (lambda m, P, Q: ngf.embed(m, [[np.nan, 0, 0]], device="cpu"), ValueError, r"x\[0\].*non-finite"),
    "embed far": (lambda m, P, Q: ngf.embed(m, [[1e6, 0, 0]], device="cpu"), ValueError, "outside the model's domain"),
    "path m huge": (lambda m, P, Q: ngf.path(m, P, Q, m=10 ** 12),
        MemoryError, r"m=1,000,000,000,000 points.*fewer points"),
    "path m float": (lambda m, P, Q: ngf.path(m, P, Q, m=2.0), ValueError, r"m \(points per path\)"),
    "reconstruct level str": (lambda m, P, Q: ngf.reconstruct(m, 16, level="0"), InputError, "level must be a finite"),
    "reconstruct level None": (lambda m, P, Q: ngf.reconstruct(m, 16, level=None),
        InputError, "level must be a finite"),
    "reconstruct level bool": (lambda m, P, Q: ngf.reconstruct(m, 16, level=True),
        InputError, "level must be a finite"),
    "device tpu": (lambda m, P, Q: ngf.sdf(m, P, device="tpu"), InputError, "unknown device 'tpu'"),
    "fps k float": (lambda m, P, Q: ngf.farthest_point_sampling(m, 2.0), InputError, "k must be an integer"),
    "voronoi repeated seed": (lambda m, P, Q: ngf.voronoi(m, [1, 1]), InputError, "repeats a vertex"),
    "check as text (sdf)": (lambda m, P, Q: ngf.sdf(m, P, check="no"), InputError, "check must be True or False"),
    "check as text (distance)": (lambda m, P, Q: ngf.distance(m, P, Q, check="no"), InputError, "check must be"),
    "check as text (path)": (lambda m, P, Q: ngf.path(m, P, Q, check=0), InputError, "check must be True or False"),
    "raw as text (ssad)": (lambda m, P, Q: ngf.ssad(m, 0, raw="yes"), InputError, "raw must be True or False"),
    "raw as text (distance)": (lambda m, P, Q: ngf.distance(m, P, Q, raw="no"), InputError, "raw must be True"),
    "cache as text (msad)": (lambda m, P, Q: ngf.msad(m, [0, 1], cache="no"), InputError, "cache must be True"),
    "cache as 0 (matrix)": (lambda m, P, Q: ngf.distance_matrix(m, [0], cache=0), InputError, "cache must be True"),
    "isolines nan level": (lambda m, P, Q: ngf.isolines(m, ngf.ssad(m, 0), [np.nan]), InputError, "finite"),
}


@pytest.mark.parametrize("case", sorted(REFUSED))
def test_hostile_query_input_is_refused_naming_it(model, case):
    call, kind, words = REFUSED[case]
    P, Q = _pq(model)
    with pytest.raises(kind, match=words):
        call(model, P, Q)


# ---- accepted: the same answer as clean input ---------------------------------------------------------------------

def test_layouts_and_dtypes_give_the_clean_answer(model, tmp_path):
    P, Q = _pq(model)
    want = ngf.distance(model, P, Q)
    mm = np.lib.format.open_memmap(tmp_path / "p.npy", mode="w+", dtype=np.float64, shape=P.shape)
    mm[:] = P
    mm.flush()
    ro = np.load(tmp_path / "p.npy", mmap_mode="r")  # a read-only memmap
    wide = np.zeros((4, 6))
    wide[:, ::2] = P  # every other column: a non-contiguous view
    for p in (np.asfortranarray(P), ro, wide[:, ::2], P.tolist()):
        np.testing.assert_array_equal(ngf.distance(model, p, Q), want)
    grad = torch.from_numpy(P).float().requires_grad_()
    np.testing.assert_allclose(ngf.distance(model, grad, torch.from_numpy(Q).float()).detach().numpy(), want,
                               rtol=1e-5, atol=1e-6)


def test_repeated_sources_and_zero_d_indices_answer_as_one(model):
    np.testing.assert_array_equal(ngf.msad(model, [3, 3, 3]), ngf.ssad(model, 3))
    np.testing.assert_array_equal(ngf.ssad(model, np.array(3)), ngf.ssad(model, 3))
    np.testing.assert_array_equal(ngf.msad(model, np.array([3, 5], np.uint8)), ngf.msad(model, [3, 5]))


def test_empty_inputs_give_empty_answers(model):
    assert ngf.distance(model, np.zeros((0, 3)), np.zeros((0, 3))).shape == (0,)
    p, f, b = ngf.path(model, np.zeros((0, 3)), np.zeros((0, 3)), m=8, return_faces=True)
    assert p.shape == (0, 8, 3) and f.shape == (0, 8) and b.shape == (0, 8, 3)
    with pytest.raises(ValueError, match="sources is empty"):
        ngf.msad(model, [])
