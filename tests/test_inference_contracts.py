"""Every contract between the Python side and the native header is written once and checked: struct
initializers come from both declarations, flag bits from their Python names, recorded launches are updated by
parameter name, and distances are finished by the header's one rule on both backends."""
import numpy as np
import pytest
import warp as wp

from neurogf_warp.kernels.inference import finish, mlp
from neurogf_warp.kernels.inference import tensorcore as tc


@pytest.mark.parametrize("py,native", [(tc.Lifting, "Lifting"), (tc.Head, "Head"), (tc.PathHead, "PathWeights")])
def test_packed_structs_match_the_header(py, native):
    """Same field names in the same order; the initializer passes each field, pointers cast to the header's type."""
    fields = tc.native_fields(native)
    assert [f for _, f in fields] == list(py.vars)
    init = tc.native_initializer(py, native, "v", "X")
    for ctype, f in fields:
        want = f"(const ngf::{ctype.split()[1]}*)v.{f}.data" if ctype.endswith("*") else f"v.{f}"
        assert want in init, (f, init)


def test_a_mismatched_struct_is_refused():
    @wp.struct
    class Swapped:
        b0: wp.array(dtype=wp.float32)
        w0: wp.array(dtype=wp.uint32)
        w1: wp.array(dtype=wp.uint32)
        b1: wp.array(dtype=wp.float32)
        w2: wp.array(dtype=wp.float32)

    with pytest.raises(RuntimeError, match="change both together"):
        tc.native_initializer(Swapped, "Head", "v", "H")
    with pytest.raises(RuntimeError, match="change both together"):
        tc.native_init("Frame", "F", {"cx": "0", "cy": "0", "cz": "0", "xscale": "1"})


def test_assembled_structs_name_every_header_field():
    """Sources, DistanceOut and Frame are assembled from kernel arguments by field name, in the header's order."""
    for native, text in (("Sources", tc._DISTANCE_CPP), ("DistanceOut", tc._DISTANCE_CPP),
                         ("Frame", tc._frame_cpp("frame"))):
        line = next(ln for ln in text.splitlines() if f"ngf::{native} " in ln)
        n_values = len(line.split("{", 1)[1].rsplit("}", 1)[0].split(", "))
        assert n_values == len(tc.native_fields(native)), native
    assert f"flags & {tc.REDUCE_MIN}" in tc._DISTANCE_CPP and f"flags & {tc.RAW}" in tc._DISTANCE_CPP
    assert tc.REDUCE_MIN & tc.RAW == 0


def test_recorded_launch_parameters_exist_by_name():
    """The parameters the engine updates on a recorded launch are looked up by name in each kernel."""
    for kernel in (tc.distance_kernel(64, 2, True, 2), tc.ssad_kernel(64, 2, False), tc.lift_ssad_kernel(64, 2, 1, 8)):
        index = tc.param_index(kernel)
        for name in ("src", "src_ids", "src_row", "n_src", "out", "ld", "flags"):
            assert name in index, (kernel.key, name)
        assert index["n_warps"] == len(index) - 1  # launch() appends the warp count last
    index = tc.param_index(tc.embed_kernel(64, 2))
    assert "pts" in index and "out" in index


def test_finishing_rule_is_the_native_one():
    """finish.finish_distance is the header's ngf::finish_distance (one definition), used by the fp32 kernels."""
    assert finish.finish_distance.native_snippet is not None
    assert "ngf::finish_distance" in finish.finish_distance.native_snippet
    f = mlp.make_frame((1.0, 2.0, 3.0), 0.5, 2.0, limit=1.5)
    rng = np.random.default_rng(0)
    head = rng.normal(size=(1, 6)).astype(np.float32)
    rows = (src_c := np.array([1.0, 2.0, 3.0])) + rng.uniform(-1, 1, size=(6, 3)).astype(np.float32)
    rows = rows.astype(np.float32)
    rows[5] = [9.0, 2.0, 3.0]  # (9 - 1) * 0.5 = 4 > 1.5: outside the domain
    rows[2] = [1.0, 2.0, 3.0]  # the source itself
    src = src_c[None].astype(np.float32)
    none = wp.empty(0, dtype=wp.int32, device="cpu")
    out = wp.empty((1, 6), dtype=float, device="cpu")
    wp.launch(finish.finish_rows, (1, 6), inputs=[wp.array(head, dtype=float, device="cpu"),
                                                  wp.array(rows, dtype=wp.vec3, device="cpu"), none,
                                                  wp.array(src, dtype=wp.vec3, device="cpu"), none, f, 1.0, 0],
              outputs=[out], device="cpu")
    chord = np.linalg.norm(rows - src, axis=1) * 0.5
    want = np.maximum((head[0] + chord) * 2.0, chord * 2.0)  # never below the straight line
    want[2] = 0.0
    want[5] = np.nan
    np.testing.assert_allclose(out.numpy()[0], want, rtol=1e-6, atol=1e-7)
