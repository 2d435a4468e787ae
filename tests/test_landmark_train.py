"""Training a network with landmarks, end to end on the CPU: the run saves the table, the file loads, and the public
float32 queries answer as the torch network does; from a landmark the bracket closes on the table's exact row."""
import numpy as np
import pytest
import torch

import neurogf_warp as ngf
from neurogf_warp.training import preset, train

K = 16


@pytest.fixture(scope="module")
def landmark_model(tmp_path_factory, ellipsoid, tiny_dataset, one_thread):
    out = tmp_path_factory.mktemp("landmarks") / "m.ngf"
    cfg = preset("cpu_small", querier_steps=10, epochs=1, iters_per_epoch=60, landmarks=K, landmark_bracket=True)
    return train(ellipsoid, out, config=cfg, dataset=tiny_dataset, device="cpu", progress=False), out


@pytest.mark.slow
def test_trained_landmark_model_round_trip_and_queries(landmark_model, ellipsoid):
    from neurogf_warp.ground_truth.geodesics import geodesic_distances

    model, path = landmark_model
    assert model.landmarks.shape == (ellipsoid.n_input, K) and np.all(np.isfinite(model.landmarks))
    # each column is a landmark's exact row: zero at the landmark, the solver's distances elsewhere
    marks = model.landmarks.argmin(0)
    assert np.all(model.landmarks[marks, np.arange(K)] == 0.0) and len(set(marks.tolist())) == K
    exact = geodesic_distances(ellipsoid, marks[:2], device="cpu", near_source=False) * ellipsoid.scale
    np.testing.assert_allclose(model.landmarks[:, :2].T, exact, rtol=1e-5, atol=1e-6)

    back = ngf.load(path)
    np.testing.assert_array_equal(back.landmarks, model.landmarks)
    d = ngf.ssad(back, 5, precision="fp32")
    x = torch.from_numpy(back.normalized_vertices())
    with torch.no_grad():
        ref = back.net.distance(x[[5] * len(x)], x).numpy().astype(np.float64) / back.scale
    assert d[5] == 0.0  # the source itself: exactly 0, as for every network
    ref[5] = 0.0
    np.testing.assert_allclose(d, ref, rtol=2e-5, atol=1e-6 * ref.max())
    # from a landmark, its own column bounds every distance from above and below: the answer is that row, up to
    # where the solver's rows break the triangle inequality (its distances are exact to ~1e-4, not to float32)
    j = int(marks[0])
    from_mark = ngf.ssad(back, j, precision="fp32")
    column = model.landmarks[:, 0] / back.scale
    np.testing.assert_allclose(from_mark, column, rtol=2e-3, atol=1e-6)
    assert np.mean(np.abs(from_mark - column) <= 1e-5 * column + 1e-7) > 0.9
    # the tensor-core kernel (here its CPU form) on the bound model: fp16 activations, within 2e-3 of the largest
    half = ngf.ssad(back, 5, precision="fp16")
    assert np.abs(half - d).max() <= 2e-3 * d.max()
    with pytest.raises(ValueError, match="needs precision='fp32'"):
        ngf.distance(back, back.mesh.vertices[:2], back.mesh.vertices[2:4], precision="fp16")


@pytest.mark.slow
def test_landmark_rows_of_a_coarse_dataset_are_solved_again(tmp_path, ellipsoid, one_thread):
    """A dataset solved at k = 1 (the CPU presets) lends its landmarks but not their rows: the bounds read the table
    as exact, so the run solves those landmarks again at k = 3 (all of them without a budget)."""
    from neurogf_warp.ground_truth.geodesics import geodesic_distances

    cfg = preset("cpu_small", k=1, querier_steps=5, epochs=1, iters_per_epoch=20, landmarks=8, landmark_bracket=True)
    model = train(ellipsoid, tmp_path / "m.ngf", config=cfg, device="cpu", progress=False)
    marks = model.landmarks.argmin(0)
    fine = geodesic_distances(ellipsoid, marks, device="cpu", k=3, near_source=False) * ellipsoid.scale
    coarse = geodesic_distances(ellipsoid, marks, device="cpu", k=1, near_source=False) * ellipsoid.scale
    np.testing.assert_allclose(model.landmarks.T, fine, rtol=1e-5, atol=1e-6)
    assert np.abs(coarse - fine).max() > 1e-4  # the two solves differ, so the test tells them apart


def test_coarse_rows_get_the_larger_share_of_a_budget(ellipsoid):
    """Under a budget, rows of a k = 1 dataset are solved again within LANDMARK_RESOLVE_SHARE of it, the landmarks
    of other runs within LANDMARK_SHARE; without a budget all K."""
    import torch

    from neurogf_warp.dataset.build import cpu_seconds_per_source
    from neurogf_warp.training import api

    cpu = torch.device("cpu")
    per = cpu_seconds_per_source(len(ellipsoid.internal_vertices), 3)
    coarse = preset("cpu", landmarks=256, landmark_bracket=True)  # k = 1 rows
    fine = preset("cpu", k=3, landmarks=256, landmark_bracket=True)
    budget = 40.5 * per  # 40.5 sources' time: 20 at half of it, 6 (so 8, the least) at 15%
    assert api._landmark_plan(coarse, ellipsoid, cpu, budget)[0] == int(api.LANDMARK_RESOLVE_SHARE * 40)
    assert api._landmark_plan(fine, ellipsoid, cpu, budget)[0] == max(8, int(api.LANDMARK_SHARE * 40))
    assert api._landmark_plan(coarse, ellipsoid, cpu, None)[0] == 256
