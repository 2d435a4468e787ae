"""Model files: round trips, released checkpoints, integrity checks on load, atomic saves and clear errors."""
import json
import os
import warnings

import numpy as np
import pytest
import torch
import trimesh

import neurogf_warp as ngf
from neurogf_warp.common import files
from tests.conftest import shared_path

DEV = "cpu"


def bunny_ckpt():
    return shared_path("checkpoints", "official", "NeuroGF_Pretrainer__bunny_final.pth")


def fandisk():
    return (shared_path("checkpoints", "official", "NeuroGF_Pretrainer__fandisk_final.pth"),
            shared_path("meshes", "fandisk.obj"))


def test_load_mesh_normalization_and_index_map(tmp_path):
    v = np.array([[9, 9, 9], [0, 0, 0], [2, 0, 0], [0, 4, 0], [0, 0, 1]], float)  # vertex 0 unused
    f = np.array([[1, 2, 3], [1, 3, 4], [1, 4, 2], [2, 4, 3]])
    path = tmp_path / "tet.obj"
    trimesh.Trimesh(v, f, process=False).export(path)
    m = ngf.load_mesh(path)
    assert m.n_input == 5 and list(m.index) == [1, 2, 3, 4]  # the file's own numbering
    m = ngf.load_mesh((v, f))
    assert m.n_input == 5 and list(m.index) == [1, 2, 3, 4]
    np.testing.assert_allclose(m.center, [1, 2, 0.5])
    assert np.isclose(np.linalg.norm(m.internal_normalized_vertices, axis=1).max(), 1.0)
    np.testing.assert_allclose(m.denormalize(m.normalize(v[1:])), v[1:])
    assert np.isnan(m.to_input(np.ones(4))[0])


def test_released_checkpoint_normalization_matches_reference():
    """Bounding-box centre + unit max norm, as measured for the released bunny (reference/README.md)."""
    model = ngf.load(bunny_ckpt(), mesh=shared_path("meshes", "stanford-bunny.obj"))
    np.testing.assert_allclose(model.center, [-0.0168405, 0.110154, -0.001537], atol=1e-6)
    assert abs(model.scale - 9.543826404254942) < 1e-6
    # the mesh lies on the SDF head's zero level set
    s = ngf.sdf(model, model.mesh.internal_vertices[::50], device=DEV) * model.scale
    assert np.abs(s).mean() < 2e-3


def test_save_load_round_trip(tmp_path):
    ck, mesh = fandisk()
    model = ngf.load(ck, mesh=mesh, querier=shared_path("checkpoints", "official",
                                                        "SDist_Querier_Offline_Pretrainer__fandisk.pth"))
    out = tmp_path / "fandisk.ngf"
    ngf.save(model, out)
    back = ngf.load(out)  # the file carries its mesh and normalization
    assert back.mesh is not None and back.mesh.fingerprint == model.mesh.fingerprint
    assert back.querier is not None
    for k, v in model.net.state_dict().items():
        assert torch.equal(v, back.net.state_dict()[k]), k
    np.testing.assert_array_equal(ngf.ssad(back, 7, device=DEV), ngf.ssad(model, 7, device=DEV))
    again = ngf.load(out, mesh=mesh)  # with the right mesh given explicitly
    np.testing.assert_array_equal(again.center, model.center)


def test_mesh_fingerprint_mismatch_is_an_error(tmp_path):
    ck, mesh = fandisk()
    out = tmp_path / "m.ngf"
    ngf.save(ngf.load(ck, mesh=mesh), out)
    with pytest.raises(ValueError, match="different mesh"):
        ngf.load(out, mesh=shared_path("meshes", "spot.obj"))
    m = ngf.load(out, mesh=shared_path("meshes", "spot.obj"), check_mesh=False)
    assert m.mesh.n_input == 2930


def test_failed_save_keeps_previous_file(tmp_path, monkeypatch):
    ck, mesh = fandisk()
    model = ngf.load(ck, mesh=mesh)
    out = tmp_path / "m.ngf"
    ngf.save(model, out)
    before = out.read_bytes()

    def broken_fsync(fd):
        raise OSError("disk full (simulated)")

    monkeypatch.setattr(files.os, "fsync", broken_fsync)
    with pytest.raises(OSError, match="disk full"):
        ngf.save(model, out)
    assert out.read_bytes() == before
    assert os.listdir(tmp_path) == ["m.ngf"]  # no temporary file left behind


def test_saved_files_get_normal_permissions(tmp_path):
    ck, mesh = fandisk()
    out = tmp_path / "m.ngf"
    umask = os.umask(0o022)
    try:
        ngf.save(ngf.load(ck, mesh=mesh), out)
        assert out.stat().st_mode & 0o777 == 0o644
        out.chmod(0o640)
        ngf.save(ngf.load(ck, mesh=mesh), out)  # overwriting keeps the file's own permissions
        assert out.stat().st_mode & 0o777 == 0o640
    finally:
        os.umask(umask)


def test_bad_model_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        ngf.load(tmp_path / "missing.pth")
    junk = tmp_path / "junk.ngf"
    junk.write_bytes(b"not a model at all")
    with pytest.raises(ValueError, match="could not read"):
        ngf.load(junk)
    state = torch.load(bunny_ckpt(), weights_only=True)
    state.pop("gdf_head.1.linear.weight")
    state["extra.weight"] = torch.zeros(3)
    state["sdf_head.0.linear.weight"] = torch.zeros(64, 200)
    bad = tmp_path / "bad.pth"
    torch.save(state, bad)
    with pytest.raises(ValueError) as e:
        ngf.load(bad)
    msg = str(e.value)
    assert "missing keys (1): gdf_head.1.linear.weight" in msg
    assert "unexpected keys (1): extra.weight" in msg
    assert "sdf_head.0.linear.weight: file (64, 200) vs model (64, 256)" in msg
    with pytest.raises(ValueError, match="SDF-querier checkpoint"):
        ngf.load(shared_path("checkpoints", "official", "SDist_Querier_Offline_Pretrainer__bunny.pth"))


@pytest.mark.slow
def test_cli_writes_ssad(tmp_path):
    from neurogf_warp.cli.main import main

    ck, mesh = fandisk()
    out = tmp_path / "d.npy"
    assert main(["ssad", str(ck), "--mesh", str(mesh), "--source", "3", "-o", str(out), "--device", DEV]) == 0
    d = np.load(out)
    model = ngf.load(ck, mesh=mesh)
    np.testing.assert_array_equal(d, ngf.ssad(model, 3, device=DEV))
    assert main(["ssad", str(ck), "--mesh", str(mesh), "--source", "999999", "-o", str(out)]) == 2


# --- model files checked on load ---------------------------------------------------------------------------

def small_model(weld_soup=False, euclid=True):
    """A D=64 model on two tetrahedra (two components) with an unused vertex first; optionally a welded soup."""
    from neurogf_warp.model.model import Model
    from neurogf_warp.model.network import NeuroGFNet

    tet = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    tf = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    v = np.vstack([[[9, 9, 9]], tet, tet + [3, 0, 0]])
    f = np.vstack([tf, tf + 4]) + 1
    if weld_soup:
        v, f = v[f.ravel()], np.arange(3 * len(f)).reshape(-1, 3)
    mesh = ngf.load_mesh((v, f))
    torch.manual_seed(0)
    net = NeuroGFNet(64, euclid=euclid)
    for mod in net.modules():  # non-trivial BatchNorm statistics, so that a wrong load shows
        if isinstance(mod, torch.nn.BatchNorm1d):
            mod.running_mean.uniform_(-0.1, 0.1)
            mod.running_var.uniform_(0.5, 2.0)
    return Model(net=net, mesh=mesh, center=mesh.center, scale=mesh.scale, config={"note": "test", "lr": 1e-3})


def read_raw(path):
    from safetensors import safe_open

    with safe_open(str(path), framework="pt") as f:
        meta = json.loads(f.metadata()["neurogf"])
        tensors = {k: f.get_tensor(k) for k in f.keys()}
    return meta, tensors


def write_raw(path, meta, tensors, fix_checksums=False):
    """Write a model file from parts; ``fix_checksums`` recomputes them, so later checks are reached."""
    from safetensors.torch import save_file

    from neurogf_warp.model import files as model_io

    if fix_checksums and "checksums" in meta:
        body = {k: v for k, v in meta.items() if k != "checksums"}
        meta["checksums"] = {"tensors": {k: model_io._digest_tensor(k, v) for k, v in tensors.items()},
                             "meta": {k: model_io._digest_value(v) for k, v in body.items()}}
    save_file({k: v.contiguous() for k, v in tensors.items()}, str(path), metadata={"neurogf": json.dumps(meta)})


def as_format_1(meta, tensors):
    """What format 1 wrote: no checksums, no stored map or labels."""
    meta = {k: v for k, v in meta.items() if k != "checksums"}
    meta["format_version"] = 1
    return meta, {k: v for k, v in tensors.items() if k not in ("mesh.input_to_internal", "mesh.components")}


def assert_same_model(a, b):
    sa, sb = a.net.state_dict(), b.net.state_dict()
    assert sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)
    np.testing.assert_array_equal(a.center, b.center)
    assert a.scale == b.scale and a.config == b.config and a.net.options == b.net.options
    for k in ("vertices", "faces", "index", "input_to_internal", "components"):
        np.testing.assert_array_equal(getattr(a.mesh, k), getattr(b.mesh, k))
    assert (a.mesh.n_input, a.mesh.fingerprint) == (b.mesh.n_input, b.mesh.fingerprint)


def test_format_2_round_trip_keeps_numbering_map_and_labels(tmp_path):
    for soup in (False, True):
        model = small_model(weld_soup=soup)
        assert model.mesh.n_components == 2 and model.mesh.welded == soup
        out = tmp_path / "m.ngf"
        ngf.save(model, out)
        meta, tensors = read_raw(out)
        assert meta["format_version"] == 2
        np.testing.assert_array_equal(tensors["mesh.components"].numpy(), model.mesh.internal_components)
        back = ngf.load(out)
        assert_same_model(model, back)
        assert back.mesh.welded == soup and back.mesh.n_components == 2


def test_format_1_files_still_load(tmp_path):
    model = small_model()
    out = tmp_path / "m.ngf"
    ngf.save(model, out)
    meta, tensors = as_format_1(*read_raw(out))
    # format 1 stored the fingerprint of the arrays as given, unused vertex included
    v = np.vstack([[[9, 9, 9]], model.mesh.internal_vertices])
    f = model.mesh.internal_faces.astype(np.int64) + 1
    meta["mesh_fingerprint"] = ngf.mesh.mesh.mesh_fingerprint(v, f)
    write_raw(out, meta, tensors)
    back = ngf.load(out)
    assert back.mesh.n_input == 9 and back.mesh.n_components == 2
    np.testing.assert_array_equal(back.mesh.input_to_internal, model.mesh.input_to_internal)
    ngf.load(out, mesh=(v, f))  # the same arrays pass the stored (old-rule) fingerprint
    # without unused vertices the format-1 fingerprint is the stored mesh's own, so it is checked
    ck, mesh = fandisk()
    ngf.save(ngf.load(ck, mesh=mesh), out)
    meta, tensors = as_format_1(*read_raw(out))
    write_raw(out, meta, tensors)
    assert ngf.load(out).mesh.n_input == 6475
    tensors["mesh.vertices"][100, 1] += 1e-3
    write_raw(out, meta, tensors)
    with pytest.raises(ValueError, match="does not match 'mesh_fingerprint'"):
        ngf.load(out)


# (what, edit of (meta, tensors), message of the field's own check; None where only the checksum sees it).
# Format 1 runs the same checks, except the fingerprint one for meshes with unused vertices (V1_SKIP; "version"
# is skipped because rewriting as format 1 undoes that edit).
EDITS = [
    ("scale 0", lambda m, t: m.update(scale=0), r"'scale' must be a finite number > 0"),
    ("scale x2", lambda m, t: m.update(scale=m["scale"] * 2), None),
    ("scale text", lambda m, t: m.update(scale="1.0"), r"'scale' must be a finite number"),
    ("center", lambda m, t: m.update(center=[c + 0.1 for c in m["center"]]), None),
    ("center nan", lambda m, t: m.update(center=[float("nan"), 0, 0]), r"'center' must be 3 finite numbers"),
    ("center short", lambda m, t: m.update(center=[0, 0]), r"'center' must be 3 finite numbers"),
    ("euclid flipped", lambda m, t: m["net_options"].update(euclid=False), None),
    ("euclid text", lambda m, t: m["net_options"].update(euclid="no"), r"option 'euclid' must be bool"),
    ("unknown option", lambda m, t: m["net_options"].update(wings=2), r"unknown network option 'wings'"),
    ("D", lambda m, t: m.update(D=256), r"'D' is 256 but the stored weights have D=64"),
    ("fingerprint removed", lambda m, t: m.pop("mesh_fingerprint"), r"'mesh_fingerprint' is missing"),
    ("fingerprint edited", lambda m, t: m.update(mesh_fingerprint="0" * 64), r"does not match 'mesh_fingerprint'"),
    ("scale removed", lambda m, t: m.pop("scale"), r"'scale' is missing"),
    ("n_input", lambda m, t: m.update(mesh_n_input=3), r"'mesh_n_input' must be an integer >="),
    ("mesh_scale", lambda m, t: m.update(mesh_scale=m["mesh_scale"] * 1.01), r"'mesh_center'/'mesh_scale' do not match"),
    ("config", lambda m, t: m["config"].update(lr=1.0), None),
    ("config type", lambda m, t: m.update(config=[1, 2]), r"'config' must be a JSON object"),
    ("version", lambda m, t: m.update(format_version=99), r"newer neurogf-warp"),
    ("index short", lambda m, t: t.update({"mesh.index": t["mesh.index"][:-1]}), r"mesh.index must be \(8,\) int64"),
    ("index range", lambda m, t: t["mesh.index"].__setitem__(-1, 10 ** 6), r"mesh.index must increase strictly"),
    ("index order", lambda m, t: t["mesh.index"].__setitem__(0, 5), r"mesh.index must increase strictly"),
    ("index dtype", lambda m, t: t.update({"mesh.index": t["mesh.index"].int()}), r"mesh.index must be \(8,\) int64"),
    ("faces range", lambda m, t: t["mesh.faces"].__setitem__((0, 0), 99), r"mesh.faces indexes vertices"),
    ("faces negative", lambda m, t: t["mesh.faces"].__setitem__((0, 0), -1), r"mesh.faces indexes vertices"),
    ("vertex moved", lambda m, t: t["mesh.vertices"].__setitem__((0, 0), 0.25), r"does not match 'mesh_fingerprint'"),
    ("vertex nan", lambda m, t: t["mesh.vertices"].__setitem__((0, 0), float("nan")), r"mesh.vertices holds NaN"),
    ("weight nan", lambda m, t: t["net.gdf_head.0.linear.weight"].__setitem__((0, 0), float("nan")), r"holds NaN or inf"),
    ("weight changed", lambda m, t: t["net.gdf_head.0.linear.weight"].mul_(1.5), None),
    ("negative variance", lambda m, t: t["net.lifting.0.bn.running_var"].__setitem__(0, -1.0), r"negative variances"),
    ("weight removed", lambda m, t: t.pop("net.gdf_head.0.linear.weight"), r"missing keys \(1\)"),
    ("mesh tensor removed", lambda m, t: t.pop("mesh.faces"), r"stored mesh is incomplete"),
    ("tensor added", lambda m, t: t.update({"extra": torch.zeros(2)}), r"unexpected tensors extra"),
]


V1_SKIP = ("fingerprint edited", "vertex moved", "version")


@pytest.mark.parametrize("what, edit, v1_message", EDITS, ids=[e[0] for e in EDITS])
def test_edited_or_damaged_files_are_refused(tmp_path, what, edit, v1_message):
    """Format 2: every edit breaks a checksum named in the message; with the checksums recomputed (or in format 1)
    the field's own check refuses it before anything reaches a kernel."""
    model = small_model()
    out = tmp_path / "m.ngf"
    ngf.save(model, out)
    meta, tensors = read_raw(out)
    edit(meta, tensors)
    write_raw(out, meta, tensors)
    with pytest.raises(ValueError, match=r"is missing|was added|checksum|newer|malformed") as e:
        ngf.load(out)
    assert str(out) in str(e.value)
    write_raw(out, meta, tensors, fix_checksums=True)
    if v1_message is None:
        ngf.load(out)  # a consistent edit of a value nothing else pins down loads: only the checksum saw it
    else:
        with pytest.raises(ValueError, match=v1_message):
            ngf.load(out)
    meta, tensors = as_format_1(meta, tensors)
    write_raw(out, meta, tensors)
    if v1_message is not None and what not in V1_SKIP:
        with pytest.raises(ValueError, match=v1_message):
            ngf.load(out)


def test_format_2_only_checks(tmp_path):
    """The stored numbering map and component labels are checked against the mesh (checksums recomputed)."""
    model = small_model()
    out = tmp_path / "m.ngf"
    for name, edit, match in [
        ("labels", lambda t: t["mesh.components"].fill_(0), "does not match the connected components"),
        ("map short", lambda t: t.update({"mesh.input_to_internal": t["mesh.input_to_internal"][:-1]}),
         r"input_to_internal must be \(9,\) int64"),
        ("map wrong", lambda t: t["mesh.input_to_internal"].__setitem__(1, 5), "does not map the stored vertices"),
        ("map range", lambda t: t["mesh.input_to_internal"].__setitem__(0, 99), "does not map the stored vertices"),
    ]:
        ngf.save(model, out)
        meta, tensors = read_raw(out)
        edit(tensors)
        write_raw(out, meta, tensors, fix_checksums=True)
        with pytest.raises(ValueError, match=match):
            ngf.load(out)


def test_short_index_never_reaches_a_kernel(tmp_path):
    """The issue's crash: a stored mesh.index shorter than the vertex list used to load, then segfault in ssad."""
    model = small_model()
    out = tmp_path / "m.ngf"
    ngf.save(model, out)
    meta, tensors = as_format_1(*read_raw(out))
    tensors["mesh.index"] = tensors["mesh.index"][:4]
    write_raw(out, meta, tensors)
    with pytest.raises(ValueError, match=r"mesh.index must be \(8,\) int64"):
        ngf.load(out)


def test_pickled_code_in_a_checkpoint_is_not_run(tmp_path):
    marker = tmp_path / "ran"

    class Payload:
        def __reduce__(self):
            return (open, (str(marker), "w"))

    bad = tmp_path / "evil.pth"
    torch.save({"lifting.2.linear.weight": Payload()}, bad)
    with pytest.raises(ValueError, match="could not read"):
        ngf.load(bad)
    assert not marker.exists()


def test_released_checkpoint_with_another_mesh_warns():
    from neurogf_warp.model.checkpoint_match import MAX_MEAN_ABS_SDF, MeshMismatchWarning, mesh_sdf_residual

    ck, mesh = fandisk()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        right = ngf.load(ck, mesh=mesh)  # no warning
    assert mesh_sdf_residual(right) < MAX_MEAN_ABS_SDF / 10
    with pytest.warns(MeshMismatchWarning, match="does not lie on this checkpoint's surface"):
        wrong = ngf.load(ck, mesh=shared_path("meshes", "spot.obj"))
    assert mesh_sdf_residual(wrong) > MAX_MEAN_ABS_SDF * 3
    # the right surface with a stray triangle beyond its bounding box: the normalization moves
    m = ngf.load_mesh(mesh)
    far = m.internal_vertices.max(0) + 0.05 * (m.internal_vertices.max(0) - m.internal_vertices.min(0))
    v = np.vstack([m.internal_vertices, far, far + [1e-3, 0, 0], far + [0, 1e-3, 0]])
    n = len(m.internal_vertices)
    f = np.vstack([m.internal_faces, [[n, n + 1, n + 2]]])
    with pytest.warns(MeshMismatchWarning):
        ngf.load(ck, mesh=(v, f))


# --- property tests: round trips and damaged files -----------------------------------------------------------

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

PROPERTY = settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
json_scalars = st.one_of(st.none(), st.booleans(), st.integers(-10 ** 6, 10 ** 6), st.text(max_size=8),
                         st.floats(allow_nan=False, allow_infinity=False))


@pytest.mark.slow
@PROPERTY
@given(options=st.fixed_dictionaries({"fourier": st.integers(0, 2), "euclid": st.booleans(),
                                      "path_residual": st.booleans(), "path_width": st.sampled_from([1, 2])}),
       window=st.booleans(), soup=st.booleans(), include_mesh=st.booleans(),
       config=st.dictionaries(st.text(max_size=6), json_scalars, max_size=4),
       frame=st.tuples(st.floats(-1e3, 1e3), st.floats(-1e3, 1e3), st.floats(-1e3, 1e3), st.floats(1e-3, 1e3)))
def test_property_model_file_round_trip(tmp_path, options, window, soup, include_mesh, config, frame):
    from neurogf_warp.model.network import NeuroGFNet

    model = small_model(weld_soup=soup)
    options["path_window"] = window and options["path_residual"]
    model.net = NeuroGFNet(64, **options).eval()
    model.config = config
    model.center, model.scale = np.array(frame[:3]), frame[3]
    out = tmp_path / "p.ngf"
    ngf.save(model, out, include_mesh=include_mesh)
    back = ngf.load(out)
    if include_mesh:
        assert_same_model(model, back)
    else:
        assert back.mesh is None
        ngf.load(out, mesh=model.mesh)  # the stored fingerprint still recognises the mesh
    assert back.net.options == model.net.options and back.config == config


@pytest.fixture(scope="module")
def saved_small_model(tmp_path_factory):
    model = small_model(weld_soup=True)
    path = tmp_path_factory.mktemp("flips") / "m.ngf"
    ngf.save(model, path)
    return model, path.read_bytes()


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(flips=st.lists(st.tuples(st.floats(0, 1, exclude_max=True), st.integers(1, 255), st.booleans()),
                      min_size=1, max_size=3))
def test_property_damaged_files_are_refused(tmp_path, saved_small_model, flips):
    """Random byte flips (half of them in the header) give a ValueError, or, where a flip changes nothing the
    file means (e.g. JSON whitespace), exactly the saved model: never a crash and never a silent change."""
    model, data = saved_small_model
    header = 8 + int.from_bytes(data[:8], "little")
    b = bytearray(data)
    for where, mask, in_header in flips:
        b[int(where * (header if in_header else len(b)))] ^= mask
    path = tmp_path / "damaged.ngf"
    path.write_bytes(bytes(b))
    try:
        back = ngf.load(path)
    except ValueError:
        return
    assert_same_model(model, back)


@pytest.mark.slow
@pytest.mark.parametrize("shift, stretch", [(0.0, 1.0), (250.0, 40.0), (-3.0, 0.01)])
def test_saved_without_mesh_answers_in_the_same_frame(tmp_path, shift, stretch):
    """save(include_mesh=False) then load(): the file keeps the normalization, so point queries answer in the
    mesh's coordinates and units as before saving (they answered in the unit-sphere frame, 1-10% off)."""
    ck, mesh = fandisk()
    m = ngf.load_mesh(mesh)
    model = ngf.load(ck, mesh=(m.internal_vertices * stretch + shift, m.internal_faces))
    path = tmp_path / "bare.ngf"
    ngf.save(model, path, include_mesh=False)
    bare = ngf.load(path)
    assert bare.mesh is None and bare.in_mesh_frame
    v = model.mesh.internal_vertices
    rng = np.random.default_rng(0)
    p, q = v[rng.choice(len(v), 64)], v[rng.choice(len(v), 64)]
    for query in (lambda mo: ngf.distance(mo, p, q, device=DEV), lambda mo: ngf.sdf(mo, p, device=DEV),
                  lambda mo: ngf.path(mo, p[:4], q[:4], m=16, device=DEV, project=None),  # the head (the default
                  # snaps to the mesh, which the bare file lacks)
                  lambda mo: ngf.ssad(mo, p[0], device=DEV) if mo.mesh is not None else None):
        want, got = query(model), query(bare)
        if got is not None:
            np.testing.assert_array_equal(got, want)
    # and the file loads with the mesh again, in the same frame
    again = ngf.load(path, mesh=(m.internal_vertices * stretch + shift, m.internal_faces))
    np.testing.assert_array_equal(ngf.distance(again, p, q, device=DEV), ngf.distance(model, p, q, device=DEV))
    assert "mesh coordinates" in json.dumps(__import__("neurogf_warp.cli.main", fromlist=["x"]).model_summary(bare))


def test_folder_paths_are_named_as_folders(tmp_path):
    with pytest.raises(IsADirectoryError, match="is a folder: give the model file itself"):
        ngf.load(tmp_path)
    ck, mesh = fandisk()
    model = ngf.load(ck, mesh=mesh)
    (tmp_path / "m.ngf").mkdir()
    with pytest.raises(IsADirectoryError, match=r"m\.ngf: it is a folder") as e:
        ngf.save(model, tmp_path / "m.ngf")
    assert ".tmp-" not in str(e.value)


def test_another_mesh_error_names_the_remedy(tmp_path):
    from neurogf_warp.common.checks import InputError
    from neurogf_warp.model.checkpoint_match import MeshMismatchError

    ck, mesh = fandisk()
    path = tmp_path / "f.ngf"
    ngf.save(ngf.load(ck, mesh=mesh), path)
    with pytest.raises(MeshMismatchError, match="check_mesh=False") as e:
        ngf.load(path, mesh=shared_path("meshes", "spot.obj"))
    assert isinstance(e.value, InputError) and "check_mesh" not in e.value.problem
