"""Meshes with odd but valid structure give the clean mesh's exact geodesics (the extra structure adds no path);
broken ones are refused naming what is wrong."""
import numpy as np
import pytest
import trimesh

import neurogf_warp as ngf
from neurogf_warp.common.checks import InputError

TM = trimesh.creation.icosphere(subdivisions=2)
V, F = np.asarray(TM.vertices) * [1.0, 0.7, 0.5], np.asarray(TM.faces)


def _row(v, f, src=0):
    return np.asarray(ngf.geodesic_distances((v, f), [src], device="cpu"), np.float64)[0]


@pytest.fixture(scope="module")
def clean():
    return _row(V, F)


VARIANTS = {
    "a zero-area face on existing vertices": lambda: (V, np.r_[F, [[0, 0, 1]]], 0, slice(None)),
    "duplicate faces": lambda: (V, np.r_[F, F[:7]], 0, slice(None)),
    "duplicate faces, flipped": lambda: (V, np.r_[F, F[:7, ::-1]], 0, slice(None)),
    "an unused vertex first": lambda: (np.r_[[[9.0, 9, 9]], V], F + 1, 1, slice(1, None)),
    "far from the origin (1e7)": lambda: (V + 1e7, F, 0, slice(None)),
    "a separate collinear sliver": lambda: (np.r_[V, [[3.0, 0, 0], [3 + 1e-9, 0, 0], [3 + 2e-9, 0, 0]]],
                                            np.r_[F, [[len(V), len(V) + 1, len(V) + 2]]], 0, slice(0, len(V))),
}


@pytest.mark.parametrize("case", sorted(VARIANTS))
def test_odd_but_valid_meshes_give_the_clean_geodesics(clean, case):
    v, f, src, keep = VARIANTS[case]()
    got = _row(v, f, src)
    np.testing.assert_allclose(got[keep], clean, rtol=2e-5, atol=1e-6 * clean.max())


def test_a_part_without_the_source_is_unreached_and_an_unused_vertex_has_no_distance():
    v = np.r_[V, [[3.0, 0, 0], [3 + 1e-9, 0, 0], [3 + 2e-9, 0, 0]]]
    got = _row(v, np.r_[F, [[len(V), len(V) + 1, len(V) + 2]]])
    assert np.isinf(got[len(V):]).all()
    with pytest.raises(IndexError, match="not used by any face"):
        _row(np.r_[[[9.0, 9, 9]], V], F + 1, src=0)


def test_single_triangle_and_non_manifold_edge():
    np.testing.assert_allclose(_row(np.eye(3), np.array([[0, 1, 2]])), [0, np.sqrt(2), np.sqrt(2)], rtol=1e-6)
    fan = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1.0]])
    np.testing.assert_allclose(_row(fan, np.array([[0, 1, 2], [0, 1, 3], [0, 1, 4]])), [0, 1, 1, 1, 1], rtol=1e-6)


BROKEN = {
    "face index out of range": ((V, np.r_[F, [[0, 1, 500]]]), InputError, r"face indices must lie in \[0, 162\)"),
    "negative face index": ((V, np.r_[F, [[0, 1, -1]]]), InputError, "face indices must lie"),
    "float faces": ((V, F + 0.5), TypeError, "faces must be integer indices"),
    "quads": ((V, np.c_[F, F[:, :1]]), InputError, "triangulate"),
    "NaN vertex": ((np.r_[V[:-1], [[np.nan, 0, 0]]], F), InputError, "non-finite vertex"),
    "no faces": ((V, np.zeros((0, 3), int)), InputError, "no faces"),
    "ragged faces": ((V, [[0, 1, 2], [0, 1]]), InputError, "equal-length rows"),
    "ragged vertices": (([[0, 0, 0], [1, 0]], F[:1]), InputError, "equal-length rows"),
    "2-D vertices": ((V[:, :2], F), InputError, r"vertices must have shape \(V, 3\)"),
}


@pytest.mark.parametrize("case", sorted(BROKEN))
def test_broken_meshes_are_refused(case):
    mesh, kind, words = BROKEN[case]
    with pytest.raises(kind, match=words):
        ngf.load_mesh(mesh)
