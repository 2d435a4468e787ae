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
    assert build.limited_batch(build.DISTANCE_BATCH_SHARE * limit, per) == 64  # not the solver's memory-sized 512
    assert build.limited_batch(build.PATH_SHARE * limit / 2, build.PATH_COST * per) == 32
    # bigger meshes cost more per source: never a larger batch
    assert build.gpu_seconds_per_source(436_000) > 10 * per
    assert build.limited_batch(0.0, per) == build.MIN_LIMITED_BATCH
