"""Ground truth on several CPU cores (solver_workers.py): the same rows and datasets as one process, in order,
with failing workers, time limits, early exits and Ctrl-C handled and no process left behind."""
import os
import signal
import time

import numpy as np
import pytest

from neurogf_warp.dataset.build import DatasetSettings, build_dataset
from neurogf_warp.ground_truth import workers as solver_workers
from neurogf_warp.ground_truth.geodesics import GeodesicSolver
from neurogf_warp.ground_truth.workers import DistanceRows


@pytest.fixture
def eager(monkeypatch):
    """Workers start even for small jobs (normally only when the work left outweighs their start-up), and this
    process solves slowly (0.3 s per batch), so that the workers, once up, have work left on this small mesh."""
    monkeypatch.setattr(solver_workers, "START_COST_S", 0.0)
    run = GeodesicSolver.run

    def slow(self, sources):
        time.sleep(0.3)
        return run(self, sources)

    monkeypatch.setattr(GeodesicSolver, "run", slow)  # this process only: the workers import their own


@pytest.fixture
def patient(eager, monkeypatch):
    """``eager``, and once the workers are started (after this process's first batch) this process waits (up to
    60 s) until a worker has solved one, so that the workers take part however slowly they start on a loaded
    machine. Before the workers start there is nothing to wait for (waiting then only ran into the 60 s)."""
    pools = []
    init, run = DistanceRows.__init__, GeodesicSolver.run

    def recorded(self, *args, **kwargs):
        init(self, *args, **kwargs)
        pools.append(self)

    def waiting(self, sources):
        end = time.monotonic() + 60
        while pools and pools[-1]._pool and not pools[-1].worker_batches and time.monotonic() < end:
            time.sleep(0.05)
        return run(self, sources)

    monkeypatch.setattr(DistanceRows, "__init__", recorded)
    monkeypatch.setattr(GeodesicSolver, "run", waiting)


@pytest.fixture(scope="module")
def solver(ellipsoid):
    return GeodesicSolver(ellipsoid, k=2, device="cpu", batch=4)


def _batches(n_vertices, n, seed):
    src = np.random.default_rng(seed).choice(n_vertices, n, replace=False)
    return [src[i: i + 4] for i in range(0, n, 4)]


def _alive(pool: DistanceRows) -> list:
    return [w for w in pool._pool if w.proc.poll() is None]


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_rows_match_one_process_in_order(solver, seed, request):
    batches = _batches(solver.nv, 40 + 3 * seed, seed)  # a short last batch for seed 1
    expect = [solver.solve(b) for b in batches]
    request.getfixturevalue("patient")
    with DistanceRows(solver, workers=3) as pool:
        got = list(pool.rows(batches))
        assert pool.worker_batches > 0  # the workers did take part
        procs = list(pool._pool)
    assert [i for i, _ in got] == list(range(len(batches)))
    for (i, d), e in zip(got, expect):
        np.testing.assert_array_equal(d, e)
    assert all(w.proc.poll() is not None for w in procs)  # every worker has exited


@pytest.mark.slow
def test_dataset_is_the_same_with_workers(ellipsoid, request):
    settings = DatasetSettings(n_sources=40, n_global=64, n_local1=8, n_local2=16, n_path_sources=4, n_test=3,
                               n_surface=1000, n_spread=400, k=2, batch=4)
    one = build_dataset(ellipsoid, None, settings, seed=5, device="cpu", progress=False, workers=1)
    request.getfixturevalue("patient")
    two = build_dataset(ellipsoid, None, settings, seed=5, device="cpu", progress=False, workers=2)
    assert two.meta["timings"]["worker_batches"] > 0
    assert one.meta["timings"]["worker_batches"] == 0
    for k in one.array_names():
        np.testing.assert_array_equal(getattr(one, k), getattr(two, k), err_msg=k)
    assert one.meta["requested"] == two.meta["requested"]  # workers change speed only: same cache key


def test_a_stop_keeps_a_prefix_of_batches(solver, eager):
    batches = _batches(solver.nv, 60, 2)
    with DistanceRows(solver, workers=2) as pool:
        got = [i for i, _ in pool.rows(batches, more=lambda i: i < 6)]
    assert got == list(range(len(got))) and 6 <= len(got) < len(batches)  # those started finish, in order


@pytest.mark.slow
def test_a_failing_worker_is_reported_and_its_work_done_here(solver, monkeypatch, request):
    batches = _batches(solver.nv, 24, 3)
    expect = [solver.solve(b) for b in batches]
    request.getfixturevalue("eager")
    real = solver_workers._Worker.__init__

    def broken(self, mesh, settings):
        real(self, mesh, dict(settings, batch=1))  # the worker's solver refuses the batches of 4 it is sent

    monkeypatch.setattr(solver_workers._Worker, "__init__", broken)
    # once the workers are started (after this process's first batch), this process waits (up to 60 s) for one
    # to fail before solving on, however slowly workers start
    pools, init, run = [], DistanceRows.__init__, GeodesicSolver.run
    monkeypatch.setattr(DistanceRows, "__init__", lambda self, *a, **k: (init(self, *a, **k), pools.append(self))[0])

    def waiting(self, sources):
        end = time.monotonic() + 60
        while pools and pools[-1]._pool and not any(w.failed for w in pools[-1]._pool) and time.monotonic() < end:
            time.sleep(0.05)
        return run(self, sources)

    monkeypatch.setattr(GeodesicSolver, "run", waiting)
    with pytest.warns(RuntimeWarning, match=r"worker process failed.*run\(\) takes 1..1 sources"):
        with DistanceRows(solver, workers=2) as pool:
            got = list(pool.rows(batches))
    assert pool.worker_batches == 0 and [i for i, _ in got] == list(range(len(batches)))
    for (_, d), e in zip(got, expect):
        np.testing.assert_array_equal(d, e)


def test_leaving_early_stops_the_workers(solver, eager):
    batches = _batches(solver.nv, 80, 4)
    with DistanceRows(solver, workers=2) as pool:
        for i, _ in pool.rows(batches):
            if i == 2:
                procs = list(pool._pool)
                break
        assert procs and not _alive(pool)
    assert all(w.proc.poll() is not None for w in procs)


def test_ctrl_c_stops_the_workers(solver, eager, ctrl_c_raises):
    batches = _batches(solver.nv, 80, 5)
    seen = {}

    def more(i):
        if i == 8:
            os.kill(os.getpid(), signal.SIGINT)  # as a terminal sends it
        return True

    pool = DistanceRows(solver, workers=2)
    with pytest.raises(KeyboardInterrupt):
        with pool:
            for i, _ in pool.rows(batches, more):
                seen[i] = True
                seen["procs"] = list(pool._pool)
    assert seen["procs"] and all(w.proc.poll() is not None for w in seen["procs"])


def test_bad_worker_counts_are_refused(solver):
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(ValueError, match="workers must be"):
            DistanceRows(solver, workers=bad)
    with pytest.raises(ValueError, match="workers must be"):
        DatasetSettings(workers=0).validate()
    assert DistanceRows(solver, workers=64).workers == solver_workers.MAX_WORKERS


def test_workers_that_cannot_start_leave_the_work_here(solver, monkeypatch, request):
    batches = _batches(solver.nv, 24, 6)
    expect = [solver.solve(b) for b in batches]
    request.getfixturevalue("eager")
    monkeypatch.setattr(solver_workers.sys, "executable", "/nonexistent/python")
    with pytest.warns(RuntimeWarning, match="could not start ground-truth worker processes"):
        with DistanceRows(solver, workers=2) as pool:
            got = list(pool.rows(batches))
    assert pool.workers == 1 and pool.worker_batches == 0
    for (_, d), e in zip(got, expect):
        np.testing.assert_array_equal(d, e)


DECOYS = {
    # a checkout-like folder whose package cannot even be imported (no kernels/, say)
    "broken": {"neurogf_warp/__init__.py": "raise ImportError('the decoy package was imported')\n"},
    # one that imports and answers, wrongly: every row zero
    "wrong": {"neurogf_warp/__init__.py": "",
              "neurogf_warp/ground_truth/__init__.py": "",
              "neurogf_warp/ground_truth/workers.py": (
                  "import os, pickle, sys\nimport numpy as np\n"
                  "def _serve():\n"
                  "    out, inp = os.fdopen(os.dup(1), 'wb'), sys.stdin.buffer\n"
                  "    _, mesh, _ = pickle.load(inp)\n"
                  "    pickle.dump(('ready', None), out); out.flush()\n"
                  "    while True:\n"
                  "        try: _, s = pickle.load(inp)\n"
                  "        except EOFError: return\n"
                  "        pickle.dump(('rows', np.zeros((len(s), 10), np.float32)), out); out.flush()\n"
                  "if __name__ == '__main__': _serve()\n")},
}


@pytest.mark.parametrize("decoy", sorted(DECOYS))
def test_workers_run_the_callers_package_whatever_the_current_directory(solver, decoy, tmp_path, monkeypatch,
                                                                       request):
    """Run from a folder holding another neurogf_warp/ package (a checkout after pip install .): the workers
    still import the caller's package, and take part without a warning."""
    import warnings

    for name, text in DECOYS[decoy].items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("PYTHONPATH", str(tmp_path))  # even first on PYTHONPATH
    batches = _batches(solver.nv, 24, 4)
    expect = [solver.solve(b) for b in batches]
    request.getfixturevalue("patient")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with DistanceRows(solver, workers=2) as pool:
            got = list(pool.rows(batches))
    assert pool.worker_batches > 0
    for (_, d), e in zip(got, expect):
        np.testing.assert_array_equal(d, e)


def test_a_worker_that_cannot_start_says_why(solver, monkeypatch, request):
    """The warning names the worker's own error (here: an import that fails in the worker), not the broken
    pipe the caller sees."""
    request.getfixturevalue("eager")
    monkeypatch.setattr(solver_workers, "_BOOT", "raise ImportError('no module named neurogf_warp.kernels')")
    batches = _batches(solver.nv, 16, 5)
    with pytest.warns(RuntimeWarning, match=r"worker process failed: ImportError: no module named "
                                            r"neurogf_warp\.kernels \(exit status 1"):
        with DistanceRows(solver, workers=2) as pool:
            assert len(list(pool.rows(batches))) == len(batches)
