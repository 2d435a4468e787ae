"""The shape-family generator: determinism, mesh quality, split, writing a collection."""
import json

import numpy as np
import pytest
import trimesh

from neurogf_warp.generalizable.shapes import (
    DEFORM_SOURCES,
    FAMILIES,
    HELD_OUT_MESHES,
    is_test,
    make_shape,
    write_collection,
)

from .conftest import shared_path


@pytest.fixture(scope="module")
def meshes_dir():
    return str(shared_path("meshes", "spot.obj").parent)


def test_deterministic_and_seeded(meshes_dir):
    for i in (0, 4, 5):
        V1, F1, i1 = make_shape(i, 3, meshes_dir)
        V2, F2, i2 = make_shape(i, 3, meshes_dir)
        np.testing.assert_array_equal(V1, V2)
        np.testing.assert_array_equal(F1, F2)
        assert i1 == i2
        V3, _, _ = make_shape(i, 4, meshes_dir)
        assert V3.shape != V1.shape or not np.allclose(V3, V1)


def test_every_family_gives_closed_connected_meshes(meshes_dir):
    seen = set()
    for i in range(2 * len(FAMILIES)):
        V, F, info = make_shape(i, 0, meshes_dir)
        seen.add(info["family"])
        tm = trimesh.Trimesh(V, F, process=False)
        assert 2000 <= len(V) <= 10000, info
        assert len(trimesh.graph.connected_components(tm.edges, nodes=np.arange(len(V)))) == 1, info
        assert tm.is_winding_consistent, info
        if info["family"] != "deformed":  # alligator has open boundaries in the source file
            assert tm.is_watertight and tm.volume > 0, info
        else:
            assert info["source"] in DEFORM_SOURCES and info["source"] not in HELD_OUT_MESHES
    assert seen == set(FAMILIES)


def test_write_collection_and_split(tmp_path, meshes_dir):
    man = write_collection(tmp_path, n=12, seed=1, test_every=5, shared_meshes=meshes_dir, progress=False)
    tests = sorted(int(k) for k, v in man["shapes"].items() if v["split"] == "test")
    assert tests == [i for i in range(12) if is_test(i, 5)] == [4, 9]
    assert len(list((tmp_path / "train").glob("*.obj"))) == 10 and len(list((tmp_path / "test").glob("*.obj"))) == 2
    on_disk = json.loads((tmp_path / "manifest.json").read_text())
    assert on_disk["shapes"]["4"]["file"] == man["shapes"]["4"]["file"]
    V, _, _ = make_shape(4, 1, meshes_dir)
    tm = trimesh.load(tmp_path / man["shapes"]["4"]["file"], process=False, force="mesh")
    np.testing.assert_allclose(tm.vertices, V, atol=1e-6 * np.abs(V).max())
    with pytest.raises(ValueError, match="seed"):
        write_collection(tmp_path, n=2, seed=2, test_every=5, progress=False)
