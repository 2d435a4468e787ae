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
    man = write_collection(tmp_path, n=18, seed=1, test_every=3, shared_meshes=meshes_dir, progress=False)
    tests = sorted(int(k) for k, v in man["shapes"].items() if v["split"] == "test")
    assert tests == [i for i in range(18) if is_test(i, 3)] == list(range(12, 18))
    # every family is in the test split (the first rule, i % test_every, left out half of them at 10)
    assert {man["shapes"][str(i)]["family"] for i in tests} == set(FAMILIES)
    assert sum(is_test(i, 10) and FAMILIES[i % len(FAMILIES)] == f for i in range(600) for f in FAMILIES) == 60
    assert {FAMILIES[i % len(FAMILIES)] for i in range(600) if is_test(i, 10)} == set(FAMILIES)
    assert len(list((tmp_path / "train").glob("*.obj"))) == 12 and len(list((tmp_path / "test").glob("*.obj"))) == 6
    on_disk = json.loads((tmp_path / "manifest.json").read_text())
    assert on_disk["shapes"]["13"]["file"] == man["shapes"]["13"]["file"]
    V, _, _ = make_shape(13, 1, meshes_dir)
    tm = trimesh.load(tmp_path / man["shapes"]["13"]["file"], process=False, force="mesh")
    np.testing.assert_allclose(tm.vertices, V, atol=1e-6 * np.abs(V).max())
    with pytest.raises(ValueError, match="seed"):
        write_collection(tmp_path, n=2, seed=2, test_every=3, progress=False)
    on_disk.pop("split")
    (tmp_path / "manifest.json").write_text(json.dumps(on_disk))
    with pytest.raises(ValueError, match="older rule"):
        write_collection(tmp_path, n=2, seed=1, test_every=3, progress=False)


@pytest.mark.slow
def test_workers_write_the_same_files(tmp_path, meshes_dir):
    one = write_collection(tmp_path / "a", n=8, seed=2, test_every=4, shared_meshes=meshes_dir, progress=False)
    two = write_collection(tmp_path / "b", n=8, seed=2, test_every=4, shared_meshes=meshes_dir, progress=False,
                           workers=2)
    assert one["shapes"] == two["shapes"]
    for info in one["shapes"].values():
        assert (tmp_path / "a" / info["file"]).read_bytes() == (tmp_path / "b" / info["file"]).read_bytes()


def test_deformed_needs_its_sources(tmp_path, capsys):
    """A meshes folder without the deformed family's sources (e.g. only the three evaluation meshes): blob
    shapes instead, said once, rather than a crash on the first deformed shape."""
    (tmp_path / "m").mkdir()
    (tmp_path / "m" / "spot.obj").write_text("")
    man = write_collection(tmp_path / "c", n=6, seed=0, shared_meshes=str(tmp_path / "m"))
    assert man["shapes"]["5"]["family"] == "blob"
    assert "deformed" in capsys.readouterr().out
