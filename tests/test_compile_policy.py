"""torch.compile under a budget (training.acceleration): a budget too short to win back a fresh machine's compile
time runs eagerly; a run that compiled records its time next to the inductor cache for the next run."""
import os

from neurogf_warp.training import acceleration as acc


def test_cold_machine_needs_a_long_budget(tmp_path, monkeypatch):
    monkeypatch.setattr(acc, "_inductor_cache", lambda: str(tmp_path))
    assert acc.compile_estimate("k") == acc.COLD_COMPILE_S
    assert acc.compile_pays("k", 60.0) == (False, acc.COLD_COMPILE_S)  # a 60 s budget never compiles cold
    assert acc.compile_pays("k", acc.COMPILE_PAYOFF * acc.COLD_COMPILE_S + 1)[0]


def test_recorded_time_counts_only_while_the_cache_is_there(tmp_path, monkeypatch):
    monkeypatch.setattr(acc, "_inductor_cache", lambda: str(tmp_path))
    acc.record_compile("k", 8.0)
    assert acc.compile_estimate("k") == acc.COLD_COMPILE_S  # no compiled graphs cached: the record is stale
    (tmp_path / "fxgraph").mkdir()
    (tmp_path / "fxgraph" / "entry").write_text("x")
    assert acc.compile_estimate("k") == 8.0
    assert acc.compile_pays("k", 30.0) == (True, 8.0)
    assert acc.compile_estimate("other") == acc.COLD_COMPILE_S  # another configuration or GPU
    acc.record_compile("other", 12.5)
    assert acc.compile_estimate("k") == 8.0 and acc.compile_estimate("other") == 12.5
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".neurogf")]  # atomic write left no temp file


def test_unreadable_record_means_cold(tmp_path, monkeypatch):
    monkeypatch.setattr(acc, "_inductor_cache", lambda: str(tmp_path))
    (tmp_path / "fxgraph").mkdir()
    (tmp_path / "fxgraph" / "entry").write_text("x")
    (tmp_path / acc._RECORD).write_text("{not json")
    assert acc.compile_estimate("k") == acc.COLD_COMPILE_S
    acc.record_compile("k", 5.0)  # a broken record is replaced
    assert acc.compile_estimate("k") == 5.0
