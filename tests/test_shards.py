"""The work split over ranks (common/shards.py): every job once, the same split on every rank, balanced loads."""
import numpy as np
import pytest

from neurogf_warp.common.shards import balanced_shard, file_sizes


@pytest.mark.parametrize("world", [1, 2, 3, 5])
def test_every_job_once_and_loads_balanced(world):
    rng = np.random.default_rng(world)
    sizes = rng.integers(2500, 7500, 131).astype(float)
    parts = [balanced_shard(sizes, world, r) for r in range(world)]
    assert sorted(i for p in parts for i in p) == list(range(len(sizes)))
    loads = [sizes[p].sum() for p in parts]
    assert max(loads) - min(loads) <= sizes.max()  # the rule's bound: one job at most apart
    assert parts == [balanced_shard(sizes.copy(), world, r) for r in range(world)]  # deterministic


def test_families_in_turn_no_longer_fall_on_one_rank():
    # the collection draws six families in turn; i % 2 gave rank 0 the three larger ones on every pass
    sizes = np.tile([2562, 2977, 3555, 2562, 5260, 4185], 20).astype(float)
    by_index = [sizes[r::2].sum() for r in range(2)]
    balanced = [sizes[balanced_shard(sizes, 2, r)].sum() for r in range(2)]
    assert max(by_index) / min(by_index) > 1.1 and max(balanced) / min(balanced) < 1.01


def test_equal_jobs_split_by_count_and_bad_ranks_refused(tmp_path):
    parts = [balanced_shard(np.ones(7), 3, r) for r in range(3)]
    assert sorted(len(p) for p in parts) == [2, 2, 3]
    with pytest.raises(ValueError, match="rank 3 is not in a world of 3"):
        balanced_shard(np.ones(3), 3, 3)
    (tmp_path / "a.obj").write_text("v 0 0 0\n")
    assert list(file_sizes([tmp_path / "a.obj", tmp_path / "missing.obj"])) == [8.0, 0.0]
