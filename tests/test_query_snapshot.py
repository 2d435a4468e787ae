"""Every public query answers fixed inputs bit for bit as the stored snapshot (tests/data/query_snapshot.npz, made by
tests/query_snapshot.py on Warp's CPU device; its docstring says at which commits)."""
from pathlib import Path

import numpy as np

from .conftest import shared_path
from .query_snapshot import answers

SNAPSHOT = Path(__file__).resolve().parent / "data" / "query_snapshot.npz"


def test_answers_bit_identical_to_snapshot():
    shared_path("checkpoints", "official", "NeuroGF_Pretrainer__fandisk_final.pth")
    before = np.load(SNAPSHOT)
    now = answers(shared_path())
    assert sorted(now) == sorted(before.files)
    for name in before.files:
        a, b = now[name], before[name]
        assert a.dtype == b.dtype and a.shape == b.shape, name
        same = (a == b) | (np.isnan(a) & np.isnan(b))
        assert same.all(), f"{name}: {int((~same).sum())} of {a.size} values differ (max {np.nanmax(abs(a - b))})"
