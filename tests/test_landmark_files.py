"""Model files of networks with landmarks: the table of distances at the mesh's vertices is stored, checked and
read back in the mesh file's numbering, and the loaded network answers as the saved one."""
import numpy as np
import pytest
import torch

import neurogf_warp as ngf
from neurogf_warp.common.checks import InputError
from neurogf_warp.model.model import Model
from neurogf_warp.model.network import LANDMARK_UNREACHED, NeuroGFNet
from tests.test_model_io import read_raw, small_model, write_raw

K = 4


def landmark_model(weld_soup=False, bracket=True):
    """``small_model``'s two tetrahedra (an unused vertex first) with a K = 4 bracket network and a table:
    landmarks at vertices 1 and 3 (first piece) and 5 and 7 (second), straight-line distances inside a piece,
    ``LANDMARK_UNREACHED`` across pieces."""
    base = small_model(weld_soup=weld_soup)
    torch.manual_seed(1)
    net = NeuroGFNet(64, euclid=True, landmarks=K, landmark_bracket=bracket)
    for mod in net.modules():
        if isinstance(mod, torch.nn.BatchNorm1d):
            mod.running_mean.uniform_(-0.1, 0.1)
            mod.running_var.uniform_(0.5, 2.0)
    m = base.mesh
    x = (m.vertices - m.center) * m.scale
    comp = m.components
    marks = [m.input_to_internal.tolist().index(i) for i in (0, 2, 4, 6)]  # input vertices of internal 0, 2, 4, 6
    table = np.linalg.norm(x[:, None, :] - x[marks][None, :, :], axis=-1)
    table = np.where(comp[:, None] == comp[marks][None, :], table, LANDMARK_UNREACHED).astype(np.float32)
    table[m.input_to_internal < 0] = np.nan
    return Model(net=net, mesh=m, center=m.center, scale=m.scale, config={"note": "landmarks"}, landmarks=table)


def torch_distances(model, i, j):
    x = torch.from_numpy(model.normalized_vertices())
    with torch.no_grad():
        return model.net.distance(x[i], x[j]).numpy()


@pytest.mark.parametrize("soup", [False, True])
def test_round_trip_keeps_the_table_and_the_answers(tmp_path, soup):
    model = landmark_model(weld_soup=soup)
    used = np.flatnonzero(model.mesh.input_to_internal >= 0)
    i, j = np.meshgrid(used, used)
    before = torch_distances(model, i.ravel(), j.ravel())
    assert np.all(np.isfinite(before))
    out = tmp_path / "lm.ngf"
    ngf.save(model, out)
    meta, tensors = read_raw(out)
    assert tensors["landmarks.table"].shape == (len(model.mesh.internal_vertices), K)
    assert meta["net_options"]["landmarks"] == K and meta["net_options"]["landmark_bracket"] is True
    back = ngf.load(out)
    np.testing.assert_array_equal(back.landmarks, model.landmarks)  # NaN rows (unused vertices) included
    np.testing.assert_array_equal(torch_distances(back, i.ravel(), j.ravel()), before)
    if not soup:  # the unused vertex has no row: its distances are NaN, never a plausible number
        assert np.isnan(back.landmarks[0]).all() and np.isnan(torch_distances(back, [0], [1])).all()


def test_given_training_mesh_and_no_mesh(tmp_path):
    model = landmark_model()
    out = tmp_path / "lm.ngf"
    ngf.save(model, out, include_mesh=False)
    again = ngf.load(out, mesh=(model.mesh.vertices, model.mesh.faces))
    np.testing.assert_array_equal(again.landmarks, model.landmarks)
    assert ngf.load(out).landmarks is None  # no mesh: the frame stays, the table waits for one
    with pytest.raises(InputError, match="cannot query another mesh"):
        ngf.load(out, mesh=(model.mesh.vertices * 2.0, model.mesh.faces), check_mesh=False)


def test_damaged_tables_are_refused(tmp_path):
    model = landmark_model()
    out = tmp_path / "lm.ngf"
    ngf.save(model, out)
    meta, tensors = read_raw(out)
    bad = dict(tensors)
    bad["landmarks.table"] = tensors["landmarks.table"].clone()
    bad["landmarks.table"][0, 0] += 1e-3
    write_raw(out, meta, bad)
    with pytest.raises(InputError, match="landmarks.table does not match its checksum"):
        ngf.load(out)
    for name, edit, message in (("negative", lambda t: t.fill_(-1.0), "must hold distances"),
                                ("nan", lambda t: t.fill_(float("nan")), "must hold distances"),
                                ("shape", lambda t: t[:-1], "must be")):
        bad["landmarks.table"] = edit(tensors["landmarks.table"].clone())
        write_raw(out, meta, bad, fix_checksums=True)
        with pytest.raises(InputError, match=message):
            ngf.load(out)
    del bad["landmarks.table"]
    write_raw(out, meta, bad, fix_checksums=True)
    with pytest.raises(InputError, match="landmarks.table is missing"):
        ngf.load(out)


def test_a_table_is_needed_and_must_fit():
    model = landmark_model()
    with pytest.raises(InputError, match="without its mesh and its table"):
        ngf.save(Model(net=model.net, center=model.center, scale=model.scale), "unused.ngf")
    with pytest.raises(ValueError, match="landmarks must be"):
        Model(net=model.net, mesh=model.mesh, center=model.center, scale=model.scale, landmarks=model.landmarks[:, :2])
    plain = small_model()
    with pytest.raises(ValueError, match="landmarks must be"):
        Model(net=plain.net, mesh=plain.mesh, center=plain.center, scale=plain.scale, landmarks=model.landmarks)
