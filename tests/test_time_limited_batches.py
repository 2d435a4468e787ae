"""GPU solver batches under a dataset time limit (dataset.build.limited_batch): powers of two that fit the share."""
from neurogf_warp.dataset import build


def test_batches_fit_the_time_and_stay_powers_of_two():
    for seconds, per in [(0.8, 8.5e-3), (2.4, 8.5e-3), (10.0, 1e-3), (0.5, 0.3)]:
        b = build.limited_batch(seconds, per)
        assert b & (b - 1) == 0  # a power of two
        assert b == build.MIN_LIMITED_BATCH or b * per <= seconds
        assert b >= build.MIN_LIMITED_BATCH


def test_a_20_s_bunny_budget_gets_small_batches():
    limit = 20.0 / 3  # the dataset's share of a 20 s budget
    per = build.gpu_seconds_per_source(34_834)
    # 0.8 s at 5 ms a source: 128, not the solver's memory-sized 512
    assert build.limited_batch(build.DISTANCE_BATCH_SHARE * limit, per) == 128
    # bigger meshes cost more per source: never a larger batch
    assert build.gpu_seconds_per_source(436_000) > 10 * per
    assert build.limited_batch(0.0, per) == build.MIN_LIMITED_BATCH


def test_the_estimate_goes_through_the_measured_rates_and_grows_with_the_mesh():
    for v, t in build.GPU_S_PER_SOURCE:
        assert abs(build.gpu_seconds_per_source(v) / t - 1) < 1e-9
    sizes = [1_000, 2_903, 34_834, 80_000, 134_345, 436_000, 2_223_321, 10_000_000]
    est = [build.gpu_seconds_per_source(v) for v in sizes]
    assert all(a < b for a, b in zip(est, est[1:]))
