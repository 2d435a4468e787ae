"""torch.compile under a budget (training.acceleration): a budget too short to win back a fresh machine's compile
time runs eagerly; a run that compiled records its time (and whether its cache was warm) next to the inductor cache
for the next run of the same shapes, which plans with it."""
import dataclasses
import json
import os

from neurogf_warp.training import acceleration as acc
from neurogf_warp.training.presets import preset


def _cache(tmp_path, monkeypatch, filled=True):
    monkeypatch.setattr(acc, "_inductor_cache", lambda: str(tmp_path))
    if filled:
        (tmp_path / "fxgraph").mkdir()
        (tmp_path / "fxgraph" / "entry").write_text("x")


def test_cold_machine_needs_a_long_budget(tmp_path, monkeypatch):
    _cache(tmp_path, monkeypatch, filled=False)
    assert acc.compile_estimate("k") == acc.COLD_COMPILE_S and not acc.compile_cached("k")
    assert acc.compile_pays("k", 60.0) == (False, acc.COLD_COMPILE_S)  # a 60 s budget never compiles cold
    assert acc.compile_pays("k", acc.COMPILE_PAYOFF * acc.COLD_COMPILE_S + 1)[0]


def test_recorded_time_counts_only_while_the_cache_is_there(tmp_path, monkeypatch):
    _cache(tmp_path, monkeypatch, filled=False)
    acc.record_compile("k", 8.0, warm=True)
    assert acc.compile_estimate("k") == acc.COLD_COMPILE_S  # no compiled graphs cached: the record is stale
    (tmp_path / "fxgraph").mkdir()
    (tmp_path / "fxgraph" / "entry").write_text("x")
    assert acc.compile_estimate("k") == 8.0 and acc.compile_cached("k")
    assert acc.compile_pays("k", 30.0) == (True, 8.0)
    assert acc.compile_estimate("other") == acc.COLD_COMPILE_S  # another configuration or GPU
    acc.record_compile("other", 12.5, warm=True)
    assert acc.compile_estimate("k") == 8.0 and acc.compile_estimate("other") == 12.5
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".neurogf")]  # atomic write left no temp file


def test_a_cold_compile_makes_the_next_one_warm(tmp_path, monkeypatch):
    # H200, 2026-11-27: the first 300 s run of a machine calibrated, compile included, in 48.6 s, the next runs of
    # the same shapes in 11.3-12.9 s, yet planned with 65 s (their key was the full batches', the record the shrunk
    # ones')
    _cache(tmp_path, monkeypatch)
    acc.record_compile("k", 48.0, warm=False)
    assert acc.compile_estimate("k") == acc.WARM_SHARE * 48.0
    assert acc.compile_pays("k", 45.0)[0]  # a 60 s run's time left after the bunny's dataset
    acc.record_compile("k", 12.0, warm=True)  # that warm run's own time replaces the guess
    assert acc.compile_estimate("k") == 12.0


def test_records_without_the_warm_flag_are_cold_compiles(tmp_path, monkeypatch):
    _cache(tmp_path, monkeypatch)
    (tmp_path / acc._RECORD).write_text(json.dumps({"k": 60.0}))  # a file written before the flag
    assert acc.compile_estimate("k") == acc.WARM_SHARE * 60.0


def test_unreadable_record_means_cold(tmp_path, monkeypatch):
    _cache(tmp_path, monkeypatch)
    (tmp_path / acc._RECORD).write_text("{not json")
    assert acc.compile_estimate("k") == acc.COLD_COMPILE_S
    acc.record_compile("k", 5.0, warm=True)  # a broken record is replaced
    assert acc.compile_estimate("k") == 5.0
    (tmp_path / acc._RECORD).write_text(json.dumps({"k": {"s": "x"}}))
    assert acc.compile_estimate("k") == acc.COLD_COMPILE_S


def test_the_compile_is_planned_for_the_batches_the_run_trains_on(tmp_path, monkeypatch):
    # the plan (training.api._plan_compile) reads the record of the batch shapes it is given: a run that shrank
    # its batches asks for the shrunk shapes, which are the ones its compile recorded
    from neurogf_warp.training import api

    _cache(tmp_path, monkeypatch)
    cfg = preset("default")
    small = dataclasses.replace(cfg, batches=cfg.batches.scaled(0.25))
    assert acc.compile_key(cfg, "cpu") != acc.compile_key(small, "cpu")
    acc.record_compile(acc.compile_key(small, "cpu"), 10.0, warm=True)
    timings = {}
    deadline = api.time.perf_counter() + 45.0
    assert api._plan_compile(small, "cpu", deadline, timings) and timings["compile"]["expected_s"] == 10.0
    assert not api._plan_compile(cfg, "cpu", deadline, timings) and timings["compile"]["expected_s"] == 65.0
