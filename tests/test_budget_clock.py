"""One budget clock: from the process start on the command line (imports and exit included), from the call in
Python; the generalizable training's ground truth inside the budget; rank 0's deadline on every rank."""
import os
import subprocess
import sys
import time

import numpy as np
import pytest
import torch
import trimesh

from neurogf_warp.common import clock
from neurogf_warp.generalizable import train as gt


def test_process_start_is_read_from_the_os():
    """A fresh process that sleeps 1 s before asking finds its start at least that long ago."""
    code = ("import time; time.sleep(1.0); from neurogf_warp.common.clock import process_start; "
            "print(time.perf_counter() - process_start())")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    ago = float(r.stdout)
    assert 0.99 <= ago < 120
    assert clock.process_start() <= time.perf_counter()


def test_budget_start_counts_from_the_process_only_inside_the_command_line_clock():
    now = time.perf_counter()
    assert clock.budget_start(now) == now
    with clock.process_clock() as start:
        want = start - clock.exit_reserve(now - start)
        assert start is not None and clock.budget_start(now) == want
        with clock.process_clock(False):  # nested, inactive: from each call again (a budget per mesh of a folder)
            assert clock.budget_start(now) == now
        assert clock.budget_start(now) == want
    assert clock.budget_start(now) == now
    assert clock.exit_reserve(0.1) == clock.EXIT_RESERVE_S and clock.exit_reserve(10.0) == 10.0 * clock.EXIT_SHARE


def test_per_mesh_folder_budgets_count_from_each_call(tmp_path, monkeypatch):
    """gen-per-mesh's budget is per mesh: under the command line's clock each ngf.train still counts from its call."""
    import neurogf_warp as ngf
    from neurogf_warp.generalizable.per_mesh import train_folder

    for i in range(2):
        trimesh.creation.icosphere(subdivisions=1).export(tmp_path / f"m{i}.obj")
    starts = []

    def fake_train(mesh, out, **kw):
        now = time.perf_counter()
        starts.append(clock.budget_start(now) == now)
        open(out, "w").close()

    monkeypatch.setattr(ngf, "train", fake_train, raising=False)
    with clock.process_clock():
        s = train_folder(tmp_path, tmp_path / "out", budget_seconds=5, device="cpu", log=lambda s: None)
    assert s["failed"] == 0 and starts == [True, True]


def test_cli_entry_counts_from_the_process_start_and_main_with_argv_from_the_call(monkeypatch):
    """``neurogf-warp`` run as the program (main() without argv) starts budgets at the process start; a call of
    main([...]) from Python (tests, scripts) at the call."""
    from neurogf_warp.cli import gen
    from neurogf_warp.cli import main as cli

    seen = []

    def fake_run_gen(name, argv):
        now = time.perf_counter()
        seen.append((now, clock.budget_start(now)))
        return 0

    monkeypatch.setattr(gen, "run_gen", fake_run_gen)
    monkeypatch.setattr(sys, "argv", ["neurogf-warp", "gen-train"])
    assert cli.main() == 0
    assert cli.main(["gen-train"]) == 0
    (now1, start1), (now2, start2) = seen
    assert start1 <= clock.process_start() - clock.EXIT_RESERVE_S + 0.02 and start1 < now1 - 1.0
    assert start2 == now2


# ---- the decisions of a budgeted generalizable run -------------------------------------------------------------------

def test_budget_steps_decisions():
    end = 1000.0
    b = gt.BudgetSteps(16, end)
    assert b.shapes == 1 and not b.stop(0, now=5000.0)  # the first step always runs, with one shape
    b.step_done(0, 2.0, say=lambda s: None, now=900.0)  # 2 s a shape, 100 s left: 20 steps of 2 shapes fit
    assert b.shapes == 2 and b.step_time() == 4.0
    assert not b.stop(1, now=995.0) and b.stop(1, now=996.5)  # a step that would end past the end is not begun
    unbounded = gt.BudgetSteps(16, None)
    assert unbounded.shapes == 16 and not unbounded.stop(10**6) and unbounded.share_every() == gt.SYNC_EVERY
    roomy = gt.BudgetSteps(16, time.perf_counter() + 1e6)
    roomy.step_done(0, 0.01, say=lambda s: None)
    assert roomy.shapes == 16 and roomy.share_every() == gt.SYNC_EVERY
    tight = gt.BudgetSteps(16, time.perf_counter() + 3.0)
    said = []
    tight.step_done(0, 1.0, say=said.append)
    assert tight.shapes == 1 and "1 shape(s) per step instead of 16" in said[0]
    assert tight.share_every() == 1  # near the end rank 0's clock is shared every step


@pytest.fixture(scope="module")
def shapes3(tmp_path_factory):
    root = tmp_path_factory.mktemp("coll3")
    for i in range(3):
        tm = trimesh.creation.icosphere(subdivisions=2)
        tm.vertices *= np.random.default_rng(i).uniform(0.5, 1.4, 3)
        (root / ("test" if i == 2 else "train")).mkdir(exist_ok=True)
        tm.export(root / ("test" if i == 2 else "train") / f"s{i}.obj")
    return root


def test_ground_truth_stops_at_its_share_with_fewer_sources(shapes3, tmp_path):
    """A ground-truth deadline already passed: one shape per rank is still solved, with GT_MIN_SOURCES sources,
    marked incomplete (and solved again by a run without a budget)."""
    cfg = gt.GenTrainConfig(sources=64, targets=16, cloud_points=64)
    files, _ = gt.mesh_files(shapes3)
    lines = []
    paths = gt.ground_truth_cache(files, tmp_path, cfg, deadline=time.perf_counter() - 1, at_least=1,
                                  log=lines.append)
    assert [p.exists() for p in paths].count(True) == 1
    with np.load(next(p for p in paths if p.exists())) as z:
        assert len(z["src"]) == gt.GT_MIN_SOURCES and not bool(z["complete"])
    assert any("stopped at its share of the budget: 1/2" in s for s in lines)
    assert any(f"{gt.GT_MIN_SOURCES} of 64 sources" in s for s in lines)
    again = gt.ground_truth_cache(files, tmp_path, cfg, log=lambda s: None)
    for p in again:
        with np.load(p) as z:
            assert len(z["src"]) == 64 and bool(z["complete"])


@pytest.mark.slow  # the whole 8 s budget is spent
@pytest.mark.wallclock
@pytest.mark.usefixtures("one_thread")  # tiny steps: two threads spin-wait on a busy 2-core machine
def test_budgeted_generalizable_training_covers_the_ground_truth(shapes3, tmp_path):
    """The whole call within its budget, ground truth included (no cache): the run's own decisions say so."""
    budget = 8.0
    cfg = gt.GenTrainConfig(sources=16, targets=16, cloud_points=64, shapes_per_step=2, step_sources=4,
                            step_targets=8, steps=10**6, val_every=0, log_every=5, budget_seconds=budget)
    lines = []
    t0 = time.perf_counter()
    ck = gt.train_generalizable(shapes3, tmp_path / "m.pt", cfg, device="cpu", log=lines.append,
                                cache=tmp_path / "gt")
    wall = time.perf_counter() - t0
    head = next(s for s in lines if s.startswith("budget: "))  # "budget: L s of 8 s left (ground truth at most G s"
    left, share = float(head.split()[1]), float(head.split("at most ")[1].split()[0])
    assert 0 < left <= budget and share == pytest.approx(gt.GT_SHARE * left, abs=0.06)
    assert ck["step"] >= 1 and ck["gt_seconds"] + ck["elapsed_s"] <= budget
    assert wall < budget + 10  # generous: the deadline itself is budget - END_RESERVE_S from the call


def _agree(rank, world, init, results):
    import torch.distributed as dist

    dist.init_process_group("gloo", init_method=init, rank=rank, world_size=world)
    mine = time.perf_counter() + (30.0 if rank == 0 else 1000.0)
    agreed = gt.shared_deadline(mine, torch.device("cpu"), True)
    results.put((rank, agreed - time.perf_counter()))
    dist.destroy_process_group()


def test_ranks_take_rank_0s_deadline(tmp_path):
    import torch.multiprocessing as mp

    ctx = mp.get_context("spawn")
    results = ctx.Queue()
    init = f"file://{tmp_path / 'rendezvous'}"
    procs = [ctx.Process(target=_agree, args=(r, 2, init, results)) for r in range(2)]
    for p in procs:
        p.start()
    got = dict(results.get(timeout=120) for _ in procs)
    for p in procs:
        p.join(30)
    assert sorted(got) == [0, 1]
    assert all(0 < left <= 30.0 for left in got.values())  # rank 1's own 1,000 s are not used
    assert os.path.exists(tmp_path)
