"""One mesh's ground truth over several devices and ranks (ground_truth/devices.py): the rows equal one device's
bit for bit, whatever the split; the ``devices`` argument's bad values are refused with clear errors."""
import os

import numpy as np
import pytest
import trimesh
import warp as wp

from neurogf_warp.common.checks import InputError
from neurogf_warp.ground_truth import devices as dv
from neurogf_warp.ground_truth import geodesics as G
from neurogf_warp.ground_truth import near_source as ns
from neurogf_warp.mesh.mesh import load_mesh

SOURCES = [0, 5, 17, 90, 200, 333, 501]


def _mesh():
    tm = trimesh.creation.icosphere(subdivisions=3)
    tm.vertices *= np.array([1.0, 0.8, 0.6])
    return load_mesh(tm)


@pytest.fixture(scope="module")
def mesh():
    return _mesh()


@pytest.fixture
def small_chunks(monkeypatch):
    """Near-source union solves of a few sources each, so that several chunks are split between devices."""
    monkeypatch.setattr(ns, "NODE_CAP", 3000)


def test_split_blocks_are_balanced_contiguous_and_cover_everything():
    for n in (0, 1, 7, 8, 100):
        for parts in (1, 2, 3, 4):
            blocks = dv.split_blocks(n, parts)
            sizes = [b.stop - b.start for b in blocks]
            assert len(blocks) == parts and sum(sizes) == n and max(sizes) - min(sizes) <= 1
            assert blocks[0].start == 0 and all(a.stop == b.start for a, b in zip(blocks, blocks[1:]))
            assert sizes == sorted(sizes, reverse=True)


class _FakeCuda:
    """A stand-in GPU for the checks that need one on a CPU-only machine."""

    is_cpu, is_cuda = False, True

    def __init__(self, name):
        self.name = name

    def __str__(self):
        return self.name


@pytest.fixture
def two_gpus(monkeypatch):
    fakes = {"cuda:0": _FakeCuda("cuda:0"), "cuda:1": _FakeCuda("cuda:1")}
    real = dv.resolve_device

    def resolve(d=None, like=None):
        if d is None:
            return fakes["cuda:0"]
        if isinstance(d, _FakeCuda):
            return d
        return fakes[d] if d in fakes else real(d)

    monkeypatch.setattr(dv, "resolve_device", resolve)
    monkeypatch.setattr(wp, "get_cuda_devices", lambda: list(fakes.values()))
    return fakes


def test_devices_are_validated_with_clear_errors(two_gpus, monkeypatch):
    monkeypatch.delenv(dv.ENV, raising=False)
    names = lambda ds: [str(d) for d in ds]  # noqa: E731
    assert names(dv.resolve_devices("all")) == ["cuda:0", "cuda:1"]
    assert names(dv.resolve_devices(["cuda:0", "cuda:1"], device="cuda:1")) == ["cuda:1", "cuda:0"]
    assert names(dv.resolve_devices("cuda:1, cuda:0")) == ["cuda:1", "cuda:0"]
    assert names(dv.resolve_devices(None, device="cuda:1")) == ["cuda:1"]
    with pytest.raises(InputError, match=r"devices: unknown device 'cuda:7'"):
        dv.resolve_devices(["cuda:0", "cuda:7"])
    with pytest.raises(InputError, match="devices names cuda:0 twice"):
        dv.resolve_devices(["cuda:0", "cuda:1", "cuda:0"])
    with pytest.raises(InputError, match="devices mixes the CPU with GPUs"):
        dv.resolve_devices(["cpu", "cuda:0"])
    with pytest.raises(InputError, match="device cuda:1 is not among devices"):
        dv.resolve_devices(["cuda:0"], device="cuda:1")
    with pytest.raises(InputError, match="at least one device"):
        dv.resolve_devices([])
    with pytest.raises(InputError, match="must be 'all', a device name or a list"):
        dv.resolve_devices(3)
    # the environment default: for GPU work only, with the call's device first
    monkeypatch.setenv(dv.ENV, "all")
    assert names(dv.resolve_devices(None, device="cuda:1")) == ["cuda:1", "cuda:0"]
    assert names(dv.resolve_devices(None, device="cpu")) == ["cpu"]
    assert names(dv.resolve_devices("cuda:0")) == ["cuda:0"]  # an explicit argument wins
    monkeypatch.setenv(dv.ENV, "cuda:0,cuda:9")
    with pytest.raises(InputError, match=f"the environment variable {dv.ENV}: unknown device 'cuda:9'"):
        dv.resolve_devices()


def test_all_without_a_gpu_and_distributed_without_a_group_are_refused(mesh, monkeypatch):
    monkeypatch.setattr(wp, "get_cuda_devices", lambda: [])
    with pytest.raises(InputError, match="devices='all' asks for every GPU, but this machine has none"):
        G.geodesic_distances(mesh, [0], devices="all")
    with pytest.raises(InputError, match="distributed=True needs an initialised torch.distributed process group"):
        G.geodesic_distances(mesh, [0], device="cpu", distributed=True)


def test_rows_split_over_devices_equal_one_devices_bit_for_bit(mesh, small_chunks, monkeypatch):
    # The blocks, their solvers and the near-source chunks split over three devices (the same CPU three times, one
    # after another: a CPU device cannot capture two solves at once): the assembled rows are one device's.
    one = G.geodesic_distances(mesh, SOURCES, device="cpu")
    cpu = wp.get_device("cpu")
    solved = []

    def in_turn(fn, n):
        solved.append(n)
        for j in range(n):
            fn(j)

    monkeypatch.setattr(dv, "run_on_devices", in_turn)
    src = G._vertices(mesh, SOURCES, "sources")
    assert len(ns.plan_chunks(G.GeodesicSolver(mesh, device="cpu", batch=1), src,
                              G.GeodesicSolver(mesh, device="cpu").solve(src))) >= 3
    for n in (2, 3):
        got = G._to_output(mesh, G._spread_distances(mesh, src, [cpu] * n, None, k=G.DEFAULT_K, windows=True,
                                                     batch=None, delta=G.DEFAULT_DELTA, near=True))
        np.testing.assert_array_equal(got, one)
    plain = G.geodesic_distances(mesh, SOURCES, device="cpu", near_source=False)
    got = G._to_output(mesh, G._spread_distances(mesh, src, [cpu] * 2, None, k=G.DEFAULT_K, windows=True,
                                                 batch=2, delta=G.DEFAULT_DELTA, near=False))
    np.testing.assert_array_equal(got, plain)
    assert solved == [2, 2, 3, 3, 2]  # blocks and chunks of each split, then the plain one's blocks


def test_run_on_devices_runs_every_part_and_raises_the_first_error():
    seen = []
    dv.run_on_devices(seen.append, 4)
    assert sorted(seen) == [0, 1, 2, 3]

    def fail(j):
        if j == 2:
            raise ValueError("part 2")

    with pytest.raises(ValueError, match="part 2"):
        dv.run_on_devices(fail, 3)


def _rank(rank, world, init, out, sources, near):
    import torch.distributed as dist

    import neurogf_warp.ground_truth.near_source as near_source
    from neurogf_warp.ground_truth.geodesics import geodesic_distances

    near_source.NODE_CAP = 3000  # several chunks, split over the ranks
    dist.init_process_group("gloo", init_method=init, rank=rank, world_size=world)
    try:
        d = geodesic_distances(_mesh(), sources, device="cpu", distributed=True, near_source=near)
        np.save(os.path.join(out, f"rank{rank}.npy"), d)
    finally:
        dist.destroy_process_group()


def _ranks(world, tmp_path, sources, near=None):
    import torch.multiprocessing as mp

    ctx = mp.get_context("spawn")
    init = f"file://{tmp_path / 'rendezvous'}"
    procs = [ctx.Process(target=_rank, args=(r, world, init, str(tmp_path), sources, near)) for r in range(world)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(300)
    assert [p.exitcode for p in procs] == [0] * world
    return [np.load(tmp_path / f"rank{r}.npy") for r in range(world)]


@pytest.mark.slow
@pytest.mark.parametrize("world", [2, 3])
def test_gloo_ranks_return_one_process_rows_bit_for_bit(mesh, small_chunks, tmp_path, world):
    one = G.geodesic_distances(mesh, SOURCES, device="cpu")
    for got in _ranks(world, tmp_path, SOURCES):
        assert got.shape == one.shape and got.dtype == np.float32
        np.testing.assert_array_equal(got, one)


@pytest.mark.slow
def test_gloo_ranks_with_fewer_sources_than_ranks(mesh, small_chunks, tmp_path):
    # rank 2 has no source of its own: it still plans the near-source chunks and takes part in every collective
    one = G.geodesic_distances(mesh, SOURCES[:2], device="cpu")
    for got in _ranks(3, tmp_path, SOURCES[:2]):
        np.testing.assert_array_equal(got, one)


@pytest.fixture
def no_capture(monkeypatch):
    """Solvers run their programs from the host (two solvers on the one CPU device cannot capture at once), and
    the main thread's solver is slowed down, so that a second device's thread has batches left to take."""
    import threading
    import time

    class Refused:
        def __init__(self, *a, **k):
            pass

        def __enter__(self):
            raise RuntimeError("capture refused by the test")

        def __exit__(self, *exc):
            return False

    monkeypatch.setattr(wp, "ScopedCapture", Refused)
    run = G.GeodesicSolver.run

    def slow(self, sources):
        if threading.current_thread() is threading.main_thread():
            time.sleep(0.3)
        return run(self, sources)

    monkeypatch.setattr(G.GeodesicSolver, "run", slow)


@pytest.mark.filterwarnings("ignore:the geodesic solver's")
def test_distance_rows_on_a_second_device_are_the_same_in_order(mesh, no_capture):
    # held batches (the dataset's traced ones): the solver that made each, on either device, still holds its
    # state when the batch is yielded, so its paths can be traced from it
    import time

    from neurogf_warp.ground_truth.workers import DistanceRows

    solver = G.GeodesicSolver(mesh, k=2, device="cpu", batch=4)
    src = np.random.default_rng(3).choice(solver.nv, 40, replace=False)
    batches = [src[i: i + 4] for i in range(0, 40, 4)]
    expect = [G.GeodesicSolver(mesh, k=2, device="cpu", batch=4).solve(b) for b in batches]
    got, where = [], []
    with DistanceRows(solver, workers=1, devices=[wp.get_device("cpu")]) as pool:
        for i, d in pool.rows(batches, hold=lambda i: i < 7):
            got.append((i, d))
            holder = pool.solver_of(i)
            where.append(holder is solver)
            if i < 7:
                np.testing.assert_array_equal(holder.rows, batches[i])
                np.testing.assert_array_equal(holder.vertex_distances(), d)
            time.sleep(0.1)  # the other device gets ahead and waits on its kept batch
    assert [i for i, _ in got] == list(range(len(batches)))
    for (_, d), e in zip(got, expect):
        np.testing.assert_array_equal(d, e)
    assert pool.device_batches > 0 and not all(where)  # the second device took part, held batches too


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore:the geodesic solver's")
def test_dataset_is_the_same_with_a_second_device(mesh, no_capture, monkeypatch):
    from neurogf_warp.dataset.build import DatasetSettings, build_dataset

    from neurogf_warp.dataset import build

    # the GPU's way: paths traced in the distance pass, from whichever device solved their batch
    monkeypatch.setattr(build, "trace_with_distances", lambda device: True)
    settings = DatasetSettings(n_sources=32, n_global=64, n_local1=8, n_local2=16, n_path_sources=20, n_test=3,
                               n_surface=1000, n_spread=400, k=2, batch=4, workers=1)
    one = build_dataset(mesh, None, settings, seed=5, device="cpu", progress=False)
    assert one.meta["timings"]["paths_traced_with_distances"]
    cpu = wp.get_device("cpu")
    monkeypatch.setattr(dv, "resolve_devices", lambda devices=None, device=None: [cpu, cpu])
    tracers, trace = set(), build._PathSet.trace

    def recorded(self, solver, *args, **kwargs):
        tracers.add(id(solver))
        return trace(self, solver, *args, **kwargs)

    monkeypatch.setattr(build._PathSet, "trace", recorded)
    two = build_dataset(mesh, None, settings, seed=5, device="cpu", progress=False)
    assert two.meta["timings"]["worker_batches"] > 0 and two.meta["timings"]["devices"] == ["cpu", "cpu"]
    assert len(tracers) == 2  # paths traced from both devices' solvers
    for k in one.array_names():
        np.testing.assert_array_equal(getattr(one, k), getattr(two, k), err_msg=k)


def test_dataset_devices_are_checked(mesh):
    from neurogf_warp.dataset.build import build_dataset

    with pytest.raises(InputError, match="devices names cpu twice"):
        build_dataset(mesh, None, device="cpu", progress=False, devices=["cpu", "cpu"])


def test_train_and_the_command_line_check_devices_before_any_work(tmp_path, capsys):
    import neurogf_warp as ngf
    from neurogf_warp.cli import main as cli

    tm = trimesh.creation.icosphere(subdivisions=2)
    tm.export(tmp_path / "s.obj")
    with pytest.raises(InputError, match="devices names cpu twice"):
        ngf.train(tmp_path / "s.obj", tmp_path / "m.ngf", device="cpu", devices="cpu,cpu")
    assert not (tmp_path / "m.train").exists() and not (tmp_path / "m.ngf").exists()
    for cmd in (["data", tmp_path / "s.obj", "-o", tmp_path / "d.npz"],
                ["train", tmp_path / "s.obj", "-o", tmp_path / "m.ngf", "--device", "cpu"]):
        assert cli.main([str(a) for a in cmd] + ["--devices", "cpu,cuda:9"]) == 2
        assert "devices: unknown device 'cuda:9'" in capsys.readouterr().err
    assert not (tmp_path / "d.npz").exists() and not (tmp_path / "m.ngf").exists()


def _held_elsewhere(lock) -> bool:
    """Whether another thread would have to wait for ``lock``."""
    import threading

    got = []

    def probe():
        ok = lock.acquire(blocking=False)
        got.append(ok)
        if ok:
            lock.release()

    t = threading.Thread(target=probe)
    t.start()
    t.join()
    return not got[0]


def test_lock_captures_holds_the_lock_for_first_launches_only():
    class Fake:
        def __init__(self):
            self._graphs = {}
            self.locked = []

        def _launch(self, name, program):
            self.locked.append((name, _held_elsewhere(dv.capture_lock())))
            self._graphs.setdefault(name, object())

    s = dv.lock_captures(Fake())
    for name in ("start", "loop", "start"):
        s._launch(name, None)
    assert s.locked == [("start", True), ("loop", True), ("start", False)]
