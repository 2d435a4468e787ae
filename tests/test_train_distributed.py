"""Training one mesh data-parallel over gloo ranks on the CPU: equal replicas, one writer, a budget, Ctrl-C, resume."""
import glob
import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch
import trimesh

from neurogf_warp.common.checks import InputError
from neurogf_warp.training import TrainingInterrupted, preset, train
from neurogf_warp.training.checkpoint import RunFiles, load_checkpoint

TINY = dict(querier_steps=10, epochs=1, iters_per_epoch=24, val_every=0, n_sources=24, n_test=4)
TIMEOUT_S = 300  # a hang fails the test instead of blocking the suite


@pytest.fixture(scope="module")
def sphere(tmp_path_factory):
    """A 162-vertex ellipsoid file."""
    tm = trimesh.creation.icosphere(subdivisions=2)
    tm.vertices *= np.array([1.0, 0.8, 0.6])
    path = tmp_path_factory.mktemp("mesh") / "sphere.obj"
    tm.export(path)
    return str(path)


def _config():
    return preset("cpu_small", **TINY)


def _rank(rank, world, init, folder, mesh, kwargs, stop_at):
    """One rank: train, then write its replica's final tensors, its first step's losses and what train returned."""
    import torch.distributed as dist

    from neurogf_warp.training import loop

    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=init, rank=rank, world_size=world)
    seen, replica = {}, {}
    call = loop.Runner.__call__

    def keep(self, *a):  # the replica itself: the returned model is rank 0's file on every rank
        try:
            return call(self, *a)
        finally:
            querier = (("querier." + k, v) for k, v in self.t.querier.state_dict().items())
            replica.update({k: v.clone() for k, v in [*self.t.net.state_dict().items(), *querier]})
            replica["steps"] = torch.tensor([self.t.steps[s] for s in sorted(self.t.steps)])

    loop.Runner.__call__ = keep

    def callback(stage, step, terms):
        seen.setdefault(stage, {k: float(v) for k, v in terms.items()})
        if stop_at is not None and rank == world - 1 and stage == "joint" and step == stop_at:
            raise KeyboardInterrupt

    out = os.path.join(folder, "m.ngf")
    result = {}
    try:
        model = train(mesh, out, config=_config(), device="cpu", progress=False, callback=callback,
                      distributed=True, **(kwargs[rank] if isinstance(kwargs, list) else kwargs))
        result["model_steps"] = model.config["steps"]
    except TrainingInterrupted as e:
        result["interrupted"] = str(e)
    except InputError as e:
        result["error"] = str(e)
    finally:
        dist.destroy_process_group()
    torch.save(replica, os.path.join(folder, f"replica{rank}.pt"))
    result["first_terms"] = seen
    with open(os.path.join(folder, f"rank{rank}.json"), "w") as f:
        json.dump(result, f)


def _ranks(world, folder, mesh, stop_at=None, per_rank=None, **kwargs):
    import torch.multiprocessing as mp

    kwargs = per_rank or kwargs
    ctx = mp.get_context("spawn")
    init = f"file://{folder}/rendezvous"
    procs = [ctx.Process(target=_rank, args=(r, world, init, str(folder), mesh, kwargs, stop_at))
             for r in range(world)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(TIMEOUT_S)
    for p in procs:
        if p.is_alive():
            p.kill()
    assert [p.exitcode for p in procs] == [0] * world
    results = []
    for r in range(world):
        with open(folder / f"rank{r}.json") as f:
            results.append(json.load(f))
    return results, [torch.load(folder / f"replica{r}.pt", weights_only=True) for r in range(world)]


def _equal_replicas(replicas, buffers=True):
    assert replicas[0]
    for other in replicas[1:]:
        assert other.keys() == replicas[0].keys()
        for k, v in replicas[0].items():
            if buffers or not any(b in k for b in ("running_", "num_batches")):
                assert torch.equal(v, other[k]), k


def test_distributed_needs_a_process_group(sphere, tmp_path):
    import torch.distributed as dist

    assert not dist.is_initialized()
    with pytest.raises(InputError, match="torchrun"):
        train(sphere, tmp_path / "m.ngf", config=_config(), device="cpu", progress=False, distributed=True)
    assert os.listdir(tmp_path) == []  # refused before any work


@pytest.mark.slow
def test_ranks_asked_for_different_trainings_are_refused_together(sphere, tmp_path):
    results, _ = _ranks(2, tmp_path, sphere, per_rank=[{}, {"lr": 1e-3}])
    assert all("every rank must make the same call" in r.get("error", "") for r in results), results
    assert not (tmp_path / "m.ngf").exists() and not (tmp_path / "m.train").exists()


@pytest.mark.slow
def test_three_ranks_train_equal_replicas_and_rank_0_writes_once(sphere, tmp_path):
    results, replicas = _ranks(3, tmp_path, sphere)
    _equal_replicas(replicas)  # the averaged gradients keep the replicas equal, BatchNorm statistics included
    # each rank drew its own batches: the first step's losses differ between ranks
    firsts = [r["first_terms"]["joint"] for r in results]
    assert firsts[0] != firsts[1] and firsts[1] != firsts[2]
    assert all(r["model_steps"] == results[0]["model_steps"] for r in results)
    assert results[0]["model_steps"]["joint"] == 24
    # one model file, one run folder, written by rank 0 alone: no temporaries, no second copy
    files = RunFiles.for_model(tmp_path / "m.ngf")
    assert sorted(glob.glob(str(tmp_path / "*.ngf"))) == [str(tmp_path / "m.ngf")]
    assert sorted(os.listdir(files.folder)) == ["checkpoint.pt", "dataset.npz", "log.json"]
    ck = load_checkpoint(files.checkpoint)
    assert ck["request"]["world_size"] == 3
    from neurogf_warp.model.files import load

    model = load(tmp_path / "m.ngf")
    net = model.net.state_dict()
    for k, v in net.items():  # the file holds rank 0's replica (= every rank's)
        assert torch.equal(v.cpu(), replicas[0][k]), k
    import neurogf_warp as ngf

    d = ngf.ssad(model, 0, device="cpu")
    assert d.shape == (162,) and np.isfinite(d).all()


@pytest.mark.slow
def test_two_ranks_stop_together_on_ctrl_c_and_resume_in_one_process(sphere, tmp_path):
    """Rank 1 alone is interrupted at joint step 5: both ranks stop at the same step, rank 0 writes the checkpoint;
    the same call in one process is refused (another world size), and ``resume`` continues the run there."""
    results, replicas = _ranks(2, tmp_path, sphere, stop_at=5)
    assert all("interrupted" in r for r in results)
    assert results[0]["interrupted"] == results[1]["interrupted"]
    _equal_replicas(replicas, buffers=False)  # BatchNorm statistics follow each rank's batches until a stage ends
    out = tmp_path / "m.ngf"
    ck = load_checkpoint(RunFiles.for_model(out).checkpoint)
    assert ck["stage"] == 1 and 5 <= ck["step"] < 24 and ck["request"]["world_size"] == 2
    assert not out.exists()
    with pytest.raises(ValueError, match="world_size 2 -> None"):
        train(sphere, out, config=_config(), device="cpu", progress=False)
    model = train(sphere, out, config=_config(), device="cpu", progress=False, resume=True)
    assert model.config["steps"]["joint"] == 24


@pytest.mark.slow
def test_torchrun_two_ranks_finish_under_a_budget(sphere, tmp_path):
    """The command line under torchrun trains data-parallel by itself; a budget ends both ranks together."""
    out = tmp_path / "b.ngf"
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--master_port",
           str(29700 + os.getpid() % 200), "-m", "neurogf_warp.cli.main", "train", sphere, "-o", str(out),
           "--device", "cpu", "--preset", "cpu_small", "--budget-seconds", "20", "--epochs", "1000",
           "--n-sources", "24", "--set", "n_test=4", "--set", "val_every=0"]
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=TIMEOUT_S)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert r.stderr.count("accuracy: validation MRE") == 1  # rank 0's line
    ck = load_checkpoint(RunFiles.for_model(out).checkpoint)
    assert ck["request"]["world_size"] == 2 and ck["request"]["budget_seconds"] == 20
    assert 0 < ck["steps"]["joint"] < 1000 * ck["config"].schedule.iters_per_epoch  # the budget cut the steps
    with open(RunFiles.for_model(out).log) as f:
        assert json.load(f)["finished"]
