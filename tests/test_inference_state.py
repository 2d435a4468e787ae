"""The per-device query state: one owner of what a model keeps on a device, freed by ``unbind`` /
``invalidate``; the network's shape read from its weights and checked by each backend."""
import gc
import weakref

import numpy as np
import pytest
import torch
import warp as wp

import neurogf_warp as ngf
from neurogf_warp.inference.backends import backend_of, fp32_refusal
from neurogf_warp.inference.engine import fp16_refusal
from neurogf_warp.inference.state import QueryState, query_state
from neurogf_warp.model.folded import folded_layers, net_shape
from neurogf_warp.model.network import NeuroGFNet, _head

DEV = "cpu"


def small_model(D=64, seed=0, **options):
    import trimesh

    torch.manual_seed(seed)
    tm = trimesh.creation.icosphere(subdivisions=1)
    mesh = ngf.load_mesh((tm.vertices * [1.5, 1.0, 0.8] + [0.3, -0.2, 0.1], tm.faces))
    net = NeuroGFNet(D, **options).eval()
    return ngf.Model(net=net, mesh=mesh, center=mesh.center, scale=mesh.scale)


def dead(refs) -> bool:
    gc.collect()
    return all(r() is None for r in refs)


@pytest.mark.slow
@pytest.mark.parametrize("precision", ["fp32", "fp16"])
def test_unbind_leaves_no_reference_to_the_kept_embeddings(precision):
    """After every kind of vertex query on a bound model (which makes tables and recorded launches from the kept
    embeddings), unbind drops the last reference: the arrays are freed, and the next query binds anew."""
    model = small_model(fourier=2, euclid=True)
    kw = dict(device=DEV, precision=precision)
    before = ngf.ssad(model, 3, cache=False, **kw)
    ngf.bind(model, DEV, precision)
    st = query_state(model, DEV)
    kept = st.bound[precision]
    refs = [weakref.ref(kept)]
    np.testing.assert_array_equal(ngf.ssad(model, 3, **kw), before)  # tables + a recorded launch on them
    ngf.msad(model, [1, 5, 9], **kw)
    ngf.ssad(model, model.mesh.vertices[4], **kw)
    if st.tables is not None:
        refs += [weakref.ref(st.tables[1]), weakref.ref(st.tables[2])]
    del kept
    assert not dead(refs), "the binding should be alive while bound"
    ngf.unbind(model, DEV)
    assert dead(refs), "unbind left a reference to the kept embeddings"
    assert st.bound == {} and st.tables is None
    np.testing.assert_array_equal(ngf.ssad(model, 3, **kw), before)  # binds again, same answers
    assert precision in st.bound


def test_model_unbind_and_invalidate_free_the_state():
    model = small_model()
    ngf.ssad(model, 0, device=DEV, precision="fp32")
    st = query_state(model, DEV)
    refs = [weakref.ref(st.bound["fp32"]), weakref.ref(st.weights.l0_w), weakref.ref(st.mesh("x").verts)]
    model.unbind("cuda:7")  # another device: nothing freed here
    assert "fp32" in st.bound
    model.unbind(wp.get_device(DEV))
    assert dead(refs[:1]) and not dead(refs[1:])
    model.invalidate()
    del st
    assert dead(refs) and model._states == {}
    assert isinstance(query_state(model, DEV), QueryState)


@pytest.mark.parametrize("D", [64, 128, 256])
def test_supported_widths_are_read_from_the_weights(D):
    """D = 64, 128, 256: the shape comes from the weights, both backends accept it, the fp16 engine packs it, and
    the fp32 answers match float64 torch (the fp16 kernels themselves: tests/test_tensorcore.py)."""
    model = small_model(D, seed=D, fourier=2, euclid=True)
    shape = net_shape(folded_layers(model.net))
    assert shape.D == D and shape.distance == (D, D // 4, D // 4, 1) and shape.lifting[0] == 15
    assert fp16_refusal(shape) is None and fp32_refusal(shape) is None
    st = query_state(model, DEV)
    assert st.engine.D == D  # packed for the tensor-core kernels (launched only on a GPU or in the emulation)
    V = model.mesh.vertices
    x = torch.from_numpy(model.mesh.normalize(V[[0, 7]])).double()
    with torch.no_grad():
        ref = model.net.double().distance(x[:1], x[1:]).numpy() / model.scale
    got = ngf.distance(model, V[[0]], V[[7]], device=DEV, precision="fp32", raw=True)
    assert abs(got[0] - ref[0]) <= 1e-5 * max(1.0, abs(ref[0]))


def test_other_shapes_run_in_fp32_or_are_refused_naming_the_shape():
    """A head twice as wide runs in fp32 (and auto picks fp32 for it), fp16 refuses it; a deeper head is refused by
    both, and every refusal names the widths."""
    wide = small_model(64, seed=1)
    wide.net.gdf_head = _head([64, 32, 32, 1]).eval()
    with pytest.raises(ValueError, match=r"distance head widths \(64, 32, 32, 1\)"):
        ngf.distance(wide, wide.mesh.vertices[:2], wide.mesh.vertices[2:4], device=DEV, precision="fp16")
    x = wide.mesh.vertices[[0, 1]]
    xn = torch.from_numpy(wide.mesh.normalize(x)).float()
    with torch.no_grad():
        ref = wide.net.distance(xn[:1], xn[1:]).numpy() / wide.scale
    got = ngf.distance(wide, x[:1], x[1:], device=DEV, raw=True)
    assert backend_of(query_state(wide, DEV), "auto").precision == "fp32"
    assert abs(got[0] - ref[0]) <= 1e-4 * max(1.0, abs(ref[0]))

    deep = small_model(64, seed=2)
    deep.net.gdf_head = _head([64, 16, 16, 16, 1]).eval()
    for prec in ("fp32", "fp16", "auto"):
        with pytest.raises(ValueError, match=r"\(64, 16, 16, 16, 1\)"):
            ngf.ssad(deep, 0, device=DEV, precision=prec)
    big = small_model(64, seed=3)
    big.net.sdf_head = _head([64, 256, 16, 1]).eval()  # wider than the per-thread accumulators
    with pytest.raises(ValueError, match=r"SDF head widths \(64, 256, 16, 1\)"):
        ngf.sdf(big, big.mesh.vertices[:2], device=DEV)


@pytest.mark.parametrize("precision", ["fp32", "fp16"])
def test_replayed_path_launches_answer_each_call(precision, monkeypatch):
    """Path queries replay their recorded launches (fp16: embeddings, per-path layer, points, with kept scratch;
    both: the finishing pass) with each call's arrays: a second call of the same size with other ends, a p == q row
    among them, and the per-call launches of large queries give what a fresh state gives; unbind drops the
    recorded launches and the arrays they hold."""
    import neurogf_warp.inference.engine as engine

    model = small_model(fourier=2)
    rng = np.random.default_rng(5)
    v = model.mesh.vertices
    kw = dict(device=DEV, precision=precision, project=None, m=8)
    calls = [(v[rng.integers(0, len(v), 6)], v[rng.integers(0, len(v), 6)]) for _ in range(3)]
    calls[1][1][2] = calls[1][0][2]  # a point to itself
    got = [ngf.path(model, p, q, **kw) for p, q in calls]
    st = query_state(model, DEV)
    held = [weakref.ref(a) for a in st.engine.launches.held(("path", 6, 8))] if precision == "fp16" else []
    fresh = []
    for p, q in calls:
        model.invalidate()
        fresh.append(ngf.path(model, p, q, **kw))
    for a, b in zip(got, fresh):
        np.testing.assert_array_equal(a, b)
    # the point itself, to float32 (host input runs relative to the mesh centre and is moved back)
    np.testing.assert_allclose(got[1][2], np.repeat(calls[1][0][2:3], 8, axis=0), rtol=0, atol=1e-6)
    assert not np.array_equal(got[0], got[2])
    monkeypatch.setattr(engine, "_PATH_SCRATCH_BYTES", 0)  # every size above the kept-scratch limit
    model.invalidate()
    for (p, q), want in zip(calls, got):
        np.testing.assert_array_equal(ngf.path(model, p, q, **kw), want)
    if held:
        del st
        model.invalidate()
        assert dead(held), "invalidate left the recorded path scratch alive"


def test_kept_source_buffers_and_index_sets_answer_each_call_and_each_model():
    """A single source point goes through buffers the state keeps (no copy from the host), and many-source index
    sets stay on the device: back-to-back calls still each give their own answer, a second model on the same
    device its own, and unbind / retune / invalidate drop what was kept."""
    from neurogf_warp.kernels.inference import tensorcore as tc

    a, b = small_model(seed=0), small_model(seed=1)
    kw = dict(device=DEV, precision="fp16", raw=True)
    v = a.mesh.vertices
    p, q = v[4] + [0.01, -0.02, 0.0], v[9] + [0.0, 0.01, 0.02]
    ref_a = ngf.distance_matrix(a, np.stack([p, q]), **kw)  # two sources: rows uploaded, not the kept buffers
    ref_b = ngf.distance_matrix(b, np.stack([p, q]), **kw)
    assert not np.array_equal(ref_a[0], ref_b[0])
    for bound in (False, True):
        if bound:
            ngf.bind(a, DEV, "fp16")
            ngf.bind(b, DEV, "fp16")
        ra_p = ngf.ssad(a, p, output="warp", cache=bound, **kw)  # no synchronization between the calls
        ra_q = ngf.ssad(a, q, output="warp", cache=bound, **kw)
        rb_p = ngf.ssad(b, p, output="warp", cache=bound, **kw)
        np.testing.assert_allclose(ra_p.numpy(), ref_a[0], rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(ra_q.numpy(), ref_a[1], rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(rb_p.numpy(), ref_b[0], rtol=1e-6, atol=1e-6)
    st = query_state(a, DEV)
    assert st.point_source is not None
    sets = [[1, 5, 9], [2, 6], [1, 5, 9]]
    first = [ngf.msad(a, s, **kw) for s in sets]
    np.testing.assert_array_equal(first[0], first[2])
    assert len(st._ids) == 2  # the repeated set was found again
    for k in range(12):
        ngf.msad(a, [k, k + 1], **kw)
    assert len(st._ids) <= 8
    np.testing.assert_array_equal(ngf.msad(b, sets[0], **kw), ngf.msad(b, sets[0], cache=False, **kw))
    assert not np.array_equal(ngf.msad(b, sets[0], **kw), first[0])
    ngf.unbind(a, DEV)
    assert st._ids == {}
    np.testing.assert_array_equal(ngf.msad(a, sets[1], **kw), first[1])
    st.retune(tc.Tuning(source_group=1))
    assert st.point_source is None
    np.testing.assert_array_equal(ngf.ssad(a, p, **kw), ra_p.numpy())
    a.invalidate()
    np.testing.assert_array_equal(ngf.ssad(a, p, **kw), ra_p.numpy())


def test_single_point_source_checks_match_the_general_ones():
    """The single-point route of sources_in refuses the same points with the same messages as the general one."""
    model = small_model()
    far = model.mesh.center + 10.0 / model.scale
    for bad, what in ((np.array([np.nan, 0.0, 0.0]), "non-finite"), (far, "outside the model's domain")):
        with pytest.raises(ValueError, match=r"source\[0\] = .*" + what):
            ngf.ssad(model, bad, device=DEV)
        with pytest.raises(ValueError, match=r"source\[0\] = .*" + what):
            ngf.ssad(model, bad.tolist(), device=DEV)  # a list takes the general route
