"""Misuse and extreme inputs get errors that name the argument and the fix: mesh scales beyond float32, wrong objects
to save, deeply nested settings, torch meta tensors, integer arrays that could be indices or points; references that
are meshes or lack positions, and evaluation results that stay valid JSON."""
from __future__ import annotations

import json

import numpy as np
import pytest

import neurogf_warp as ngf
from neurogf_warp.common.checks import InputError
from neurogf_warp.mesh.mesh import MAX_RADIUS, MIN_RADIUS

TET_V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
TET_F = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])
TET_RADIUS = float(np.linalg.norm(TET_V - 0.5, axis=1).max())  # from the bounding-box centre (0.5, 0.5, 0.5)


# ---- mesh scales ------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("scale", [1e-300, 1e-40, 1e-30, 1e-22, 3e38, 1e31, 1e300])
def test_meshes_beyond_float32_are_refused_with_the_range(scale):
    with pytest.raises(InputError, match=r"outside the supported range.*rescale the mesh") as e:
        ngf.load_mesh((TET_V * scale, TET_F))
    assert f"{MIN_RADIUS:g}" in str(e.value) and f"{MAX_RADIUS:g}" in str(e.value)


def test_the_range_boundaries():
    ngf.load_mesh((TET_V * (1.001 * MIN_RADIUS / TET_RADIUS), TET_F))
    ngf.load_mesh((TET_V * (0.999 * MAX_RADIUS / TET_RADIUS), TET_F))
    with pytest.raises(InputError, match="supported range"):
        ngf.load_mesh((TET_V * (0.999 * MIN_RADIUS / TET_RADIUS), TET_F))
    with pytest.raises(InputError, match="supported range"):
        ngf.load_mesh((TET_V * (1.001 * MAX_RADIUS / TET_RADIUS), TET_F))
    with pytest.raises(InputError, match="coordinates reach"):  # a normal size far beyond float32's coordinates
        ngf.load_mesh((TET_V * 1e29 + 3e38, TET_F))
    with pytest.raises(InputError, match="coordinates reach"):
        ngf.load_mesh((TET_V * 1e20 + 1e33, TET_F))
    ngf.load_mesh((TET_V * 1e20 + 1e31, TET_F))  # far, but float32 holds it and float64 keeps its shape


def test_scale_refusal_names_the_file(tmp_path):
    p = tmp_path / "tiny.obj"
    p.write_text("".join(f"v {x * 1e-40:.6g} {y * 1e-40:.6g} {z * 1e-40:.6g}\n" for x, y, z in TET_V)
                 + "f 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n")
    with pytest.raises(InputError, match=r"tiny\.obj.*supported range"):
        ngf.load_mesh(p)


@pytest.mark.parametrize("scale", [1e-18, 1e-6, 1e6, 1e28])
def test_supported_scales_give_scaled_distances(scale):
    """Exact distances and a model's answers scale with the mesh, from near one end of the range to the other."""
    import trimesh

    tm = trimesh.creation.icosphere(subdivisions=2)
    V, F = np.asarray(tm.vertices) * [1.0, 0.7, 0.5], np.asarray(tm.faces)
    base = np.asarray(ngf.geodesic_distances((V, F), [0], device="cpu"), np.float64)[0]
    got = np.asarray(ngf.geodesic_distances((V * scale, F), [0], device="cpu"), np.float64)[0]
    assert np.all(np.isfinite(got)) and got[1:].min() > 0
    np.testing.assert_allclose(got / scale, base, rtol=1e-5)
    m1, ms = _model((V, F)), _model((V * scale, F))
    a = np.asarray(ngf.ssad(m1, 0, device="cpu"), np.float64)
    b = np.asarray(ngf.ssad(ms, 0, device="cpu"), np.float64)
    np.testing.assert_allclose(b / scale, a, rtol=1e-4, atol=1e-6 * a.max())


def _model(mesh, seed=0):
    import torch

    from neurogf_warp.model.model import Model
    from neurogf_warp.model.network import NeuroGFNet

    torch.manual_seed(seed)
    m = ngf.load_mesh(mesh)
    return Model(net=NeuroGFNet(64), mesh=m, center=m.center, scale=m.scale)


# ---- misuse -----------------------------------------------------------------------------------------------------

def test_save_names_a_wrong_model_argument(tmp_path):
    mesh = ngf.load_mesh((TET_V, TET_F))
    with pytest.raises(TypeError, match=r"save\(model, path\): model must be a neurogf_warp Model, got None"):
        ngf.save(None, tmp_path / "m.ngf")
    with pytest.raises(TypeError, match="a Mesh is not a model: train one with neurogf_warp.train"):
        ngf.save(mesh, tmp_path / "m.ngf")
    with pytest.raises(TypeError, match="got str"):
        ngf.save("model.ngf", tmp_path / "m.ngf")
    assert not (tmp_path / "m.ngf").exists()


def _deep_text(n):
    return '{"x": ' * n + '{"refine_dist": 1}' + "}" * n


def _deep(n):
    d = {"refine_dist": 1.0}
    for _ in range(n):
        d = {"x": d}
    return d


def test_deeply_nested_settings_are_refused():
    from neurogf_warp.training import TrainConfig
    from neurogf_warp.training.config import parse_assignments

    cfg = TrainConfig()
    for value in (_deep(5000), _deep_text(5000), "[" * 5000 + "]" * 5000, _deep(9), _deep_text(9)):
        with pytest.raises(InputError, match="ratios is nested deeper than"):
            cfg.set(ratios=value)
    loop = {}
    loop["self"] = loop
    with pytest.raises(InputError, match="refers to itself"):
        cfg.set(loss_weights=loop)
    with pytest.raises(InputError, match="nested deeper"):
        TrainConfig.from_dict({"schedule": {"ratios": _deep(5000)}})
    settings = parse_assignments(["ratios=" + _deep_text(5000)])
    with pytest.raises(InputError, match="nested deeper"):
        cfg.set(**settings)
    assert cfg.set(ratios={"refine_dist": 2.0}).schedule.ratios == {"refine_dist": 2.0}


def test_train_refuses_deep_settings_before_work(tmp_path):
    import trimesh

    tm = trimesh.creation.icosphere(subdivisions=2)
    mesh = tmp_path / "s.obj"
    tm.export(mesh)
    with pytest.raises(InputError, match="nested deeper"):
        ngf.train(str(mesh), tmp_path / "s.ngf", ratios=_deep(5000), device="cpu", progress=False)
    assert not (tmp_path / "s.ngf").exists()


@pytest.fixture(scope="module")
def tet_model():
    import trimesh

    tm = trimesh.creation.icosphere(subdivisions=1)
    return _model((np.asarray(tm.vertices), np.asarray(tm.faces)))


def test_meta_tensors_are_refused_naming_the_argument(tet_model):
    import torch

    meta3 = torch.empty(3, 3, device="meta")
    calls = [(lambda: ngf.ssad(tet_model, torch.empty(3, device="meta"), device="cpu"), "source"),
             (lambda: ngf.msad(tet_model, torch.empty(2, dtype=torch.int64, device="meta"), device="cpu"), "sources"),
             (lambda: ngf.distance_matrix(tet_model, [0], targets=meta3, device="cpu"), "targets"),
             (lambda: ngf.distance(tet_model, meta3, np.zeros((3, 3)), device="cpu"), "p"),
             (lambda: ngf.distance(tet_model, np.zeros((3, 3)), meta3, device="cpu"), "q"),
             (lambda: ngf.sdf(tet_model, meta3), "x"),
             (lambda: ngf.path(tet_model, meta3, meta3, m=4), "p"),
             (lambda: ngf.project(tet_model, meta3), "x")]
    for call, name in calls:
        with pytest.raises(InputError, match=rf"^{name} is a torch tensor on the 'meta' device"):
            call()


def test_integer_2d_sources_are_refused_by_every_query(tet_model):
    import torch

    two = np.array([[0, 1, 2], [3, 4, 5]])
    calls = [(lambda x: ngf.msad(tet_model, x, device="cpu"), "sources"),
             (lambda x: ngf.distance_matrix(tet_model, x, device="cpu"), "sources"),
             (lambda x: ngf.distance_matrix(tet_model, [0, 1], targets=x, device="cpu"), "targets"),
             (lambda x: ngf.ssad(tet_model, x[:1], device="cpu"), "source")]
    for call, name in calls:
        for x in (two, two.tolist(), torch.as_tensor(two), two.astype(np.uint16)):
            arr = x if not isinstance(x, list) else np.asarray(x)
            rows = arr.shape[0] if name != "source" else 1
            with pytest.raises(InputError, match=rf"{name} is an integer array of shape \({rows}, 3\).*dtype=float"):
                call(x)
    # the two readings it names both work, and agree with their spellings elsewhere
    by_index = np.asarray(ngf.msad(tet_model, two.ravel(), device="cpu"))
    by_points = np.asarray(ngf.msad(tet_model, tet_model.mesh.vertices[two.ravel()], device="cpu"))
    np.testing.assert_allclose(by_index, by_points, rtol=1e-4, atol=1e-5)
    unit = np.array([[0, 1, 0], [1, 0, 0]])  # point arguments: coordinates of any real dtype
    pts = np.asarray(ngf.distance(tet_model, unit, unit[::-1], device="cpu"))
    np.testing.assert_allclose(pts, ngf.distance(tet_model, unit.astype(float), unit[::-1].astype(float), device="cpu"))


# ---- references and evaluation ----------------------------------------------------------------------------------

def _reference(tmp_path, mesh, name, positions=True, key="file_index", idx=None):
    used = mesh.index if idx is None else idx  # the stored numbering
    files = mesh.index[:len(used)]  # the same vertices in the file's numbering
    d = np.asarray(ngf.geodesic_distances(mesh, files[:2], device="cpu"))[:, files].astype(np.float32)
    arrays = {key: used.astype(np.int32), "sources": np.array([0, 1], np.int32), "dist": d}
    if positions:
        arrays["positions"] = mesh.vertices[files].astype(np.float32)
    path = tmp_path / name
    np.savez(path, **arrays)
    return path


@pytest.fixture
def unused_mesh(tmp_path):
    p = tmp_path / "u.obj"
    p.write_text("v 5 5 5\n" + "".join(f"v {x} {y} {z}\n" for x, y, z in TET_V)
                 + "f 2 3 4\nf 2 3 5\nf 2 4 5\nf 3 4 5\n")
    return ngf.load_mesh(p), str(p)


def test_reference_that_is_a_mesh_says_so(tmp_path, unused_mesh):
    from neurogf_warp.evaluation.evaluate import load_reference

    mesh, path = unused_mesh
    with pytest.raises(InputError, match="is a mesh file, not a distance reference.*mesh=") as e:
        load_reference(path, mesh)
    assert "pickle" not in str(e.value)
    (tmp_path / "r.npz").write_text("plain text")
    with pytest.raises(InputError, match="not an .npz file"):
        load_reference(tmp_path / "r.npz", mesh)


def test_reference_without_positions_is_read_against_the_mesh(tmp_path, unused_mesh):
    from neurogf_warp.evaluation.evaluate import load_reference

    mesh, _ = unused_mesh
    full = load_reference(_reference(tmp_path, mesh, "a.npz"), mesh)
    bare = load_reference(_reference(tmp_path, mesh, "b.npz", positions=False), mesh)
    for x, y in zip(full, bare):
        np.testing.assert_array_equal(x, y)
    # trimesh's numbering (unused vertices dropped) differs from the file's here: without positions it is refused
    with pytest.raises(InputError, match="no positions"):
        load_reference(_reference(tmp_path, mesh, "c.npz", positions=False, key="orig_index",
                                  idx=np.arange(4)), mesh)
    with pytest.raises(InputError, match="no positions"):  # covers only part of the mesh
        load_reference(_reference(tmp_path, mesh, "d.npz", positions=False, idx=mesh.index[:3]), mesh)
    np.savez(tmp_path / "e.npz", sources=np.array([0]), dist=np.zeros((1, 4)))
    with pytest.raises(InputError, match="not a distance reference .*file_index"):
        load_reference(tmp_path / "e.npz", mesh)


def test_evaluation_results_are_valid_json_with_reasons():
    from neurogf_warp.evaluation.evaluate import _chamfer, format_table, json_safe

    cd = np.array([0.1, np.nan, 0.3])
    res = {"vertices": 4, "reference": "solver", "paths": 3, **_chamfer(cd, "chamfer_l1"),
           "neurogf": {"pairs": 0, "nonfinite": 0, "per_source_mre": [float("nan"), 0.2]}, "x": float("inf")}
    res = json_safe(res)
    text = json.dumps(res, allow_nan=False)  # raises on NaN/inf
    assert json.loads(text)["neurogf"]["per_source_mre"] == [None, 0.2]
    assert res["chamfer_l1"] == pytest.approx(0.2) and res["chamfer_l1_nonfinite"] == 1
    table = format_table(res)
    assert "1 of 3 predicted paths are NaN" in table and "nan" not in table.replace("NaN", "")
    none = json_safe({"vertices": 4, "reference": "solver", "paths": 2, **_chamfer(np.full(2, np.nan), "chamfer_l1")})
    json.dumps(none, allow_nan=False)
    assert none["chamfer_l1"] is None and "path Chamfer-L1: none (2 of 2 predicted paths are NaN" in format_table(none)


def test_evaluate_on_a_multi_part_mesh_writes_valid_json():
    import trimesh

    from neurogf_warp.evaluation.evaluate import evaluate

    a = trimesh.creation.icosphere(subdivisions=1)
    b = trimesh.creation.icosphere(subdivisions=1)
    V = np.vstack([a.vertices, np.asarray(b.vertices) + [3.0, 0, 0]])
    F = np.vstack([a.faces, np.asarray(b.faces) + len(a.vertices)])
    model = _model((V, F))
    res = evaluate(model, n_sources=2, n_path_sources=2, n_path_targets=2, sdf=False, device="cpu", verbose=False)
    json.dumps(res, allow_nan=False)
    assert res["cross_component"]["pairs"] > 0
