"""``train()``: one call from a mesh to a saved model, safe to repeat.

Order of work: every check first (output folder, settings, device, mesh), then the dataset (cached in the run
folder), the SDF pool, timing and fitting the step counts to the budget, the stages, and the model file.
A repeated call with the same settings continues an interrupted run from its checkpoint, or answers from the
finished one; other settings on top of an existing run are refused unless ``resume`` or ``force`` says which.
"""
from __future__ import annotations

import dataclasses
import json
import os
import time
from typing import TYPE_CHECKING

import numpy as np

from neurogf_warp.common.checks import InputError, number, say
from neurogf_warp.dataset.build import check_trainable
from neurogf_warp.ground_truth.solver import load_seconds
from neurogf_warp.mesh.mesh import load_mesh
from neurogf_warp.training.budget import (MIN_SDF_SCALE, Budget, ThreadChooser, calibrate, fit_budget,
                                         short_budget_done, short_budget_said, short_budget_scale)
from neurogf_warp.training.checkpoint import (
    CKPT_VERSION,
    RunFiles,
    finished,
    load_checkpoint,
    save_checkpoint,
    save_model,
)
from neurogf_warp.training.config import STAGES, TrainConfig
from neurogf_warp.training.data import TrainingData, make_sdf_pool, obtain_dataset
from neurogf_warp.training.loop import Runner
from neurogf_warp.training.presets import choose_preset, preset
from neurogf_warp.training.run_folder import call_key, finished_log
from neurogf_warp.training.quality import (HeatBaseline, ModelQualityWarning, budget_verdict, final_verdict,
                                          mre_estimate)

if TYPE_CHECKING:
    import torch

    from neurogf_warp.model.model import Model

__all__ = ["train", "resolve_config", "torch_device", "check_budget", "ModelQualityWarning", "MAX_BUDGET_S"]

SAVE_RESERVE_S = 1.0  # seconds of a budget kept for writing the model and the log
# The largest share of a budgeted call that ground truth may take: where sources are slow (large meshes on a CPU),
# more sources buy accuracy only while the steps left can still fit them, and past about a third they cannot
DATA_SHARE = 1 / 3
MAX_BUDGET_S = 30 * 24 * 3600.0  # 30 days: a larger budget is a typo (or inf / 1e308), refused before any work


def check_budget(budget_seconds) -> float | None:
    """``budget_seconds`` as a float, or None; InputError for a non-number, <= 0, not finite or above 30 days.

    Cheap and import-free: callers (the command line, the demo) run it before loading anything."""
    if budget_seconds is None:
        return None
    return number("budget_seconds", budget_seconds, above=0, maximum=MAX_BUDGET_S)


def torch_device(device=None) -> "torch.device":
    """The torch device to train on, through ``arrays.resolve_device`` (default: Warp's preferred device)."""
    import torch
    import warp as wp

    from neurogf_warp.common.arrays import resolve_device

    return torch.device(wp.device_to_torch(resolve_device(device)))


def resolve_config(config=None, device=None, n_vertices: int = 0, **settings) -> TrainConfig:
    """The run's TrainConfig: ``config`` (a TrainConfig or a preset name; None: the preset for the device and
    the mesh size, ``presets.choose_preset``) with ``settings`` (flat or dotted names) applied and checked."""
    if config is None:
        config = choose_preset(str(device or "cpu"), n_vertices)
    if isinstance(config, str):
        cfg = preset(config)
    elif isinstance(config, TrainConfig):
        cfg = config.copy()
    else:
        raise TypeError(f"config must be a TrainConfig or a preset name, got {type(config).__name__}")
    return cfg.set(**settings) if settings else cfg.validate()


def train(mesh, out: str | os.PathLike, *, config: TrainConfig | str | None = None, device=None, dataset=None,
          resume: bool = False, force: bool = False, budget_seconds: float | None = None, progress: bool = True,
          callback=None, allow_vertex_joins: bool = False, devices=None, distributed: bool = False,
          **settings) -> "Model":
    """Train a NeuroGF for ``mesh`` and write it to ``out``; returns the saved Model.

    Parameters
    ----------
    mesh : path, trimesh.Trimesh, (vertices, faces) or Mesh
    out : model file to write (e.g. ``spot.ngf``); the run's checkpoint, cached dataset and log go to the folder
        ``spot.train/`` beside it
    config : a TrainConfig, a preset name ("default", "paper", "cpu", "cpu_small"), or None for the preset that
        fits the device and the mesh (``presets.choose_preset``)
    device : "cpu", "cuda", "cuda:N" or a torch/Warp device (default: the GPU if there is one)
    dataset : None (the run folder's cache, else built), a Dataset, or a dataset ``.npz`` file
    resume : continue the checkpoint in the run folder with its own settings (the settings given here are not
        used); a finished run's checkpoint gives its model back
    force : start over, replacing an existing run and model file (never the mesh or dataset file trained from:
        an ``out`` that is one of them is refused, as is a device, FIFO or folder; a link is written through)
    budget_seconds : seconds for the whole run (dataset, set-up, all stages, saving; in a fresh process also the
        import of torch and the training stage that ``ngf.train`` triggers; under the command line, everything
        from the process start to its exit), a number > 0 and at most 30
        days (InputError otherwise, before any work). The ground truth gets at most a third of it (fewer sources
        when it runs short, noted in the dataset); the step counts are fitted to the rest and re-planned from the
        measured step times. A run interrupted and continued by a later call gets what the earlier calls left.
    progress : progress bars and messages on stderr
    callback : ``callback(stage, step, terms)`` after every step (raise KeyboardInterrupt there to stop like Ctrl-C)
    allow_vertex_joins : train a mesh whose patches meet only at single vertices (refused by default, before any
        work: geodesics through such vertices are fitted poorly; the error says how to weld seams stored twice)
    devices : GPUs that share the dataset's ground truth ("all", a list such as ["cuda:0", "cuda:1"], or None:
        the environment variable ``NEUROGF_DEVICES`` where set, else ``device`` alone; ``build_dataset``); the
        steps run on ``device`` (default: the first of them). The same dataset as on ``device`` alone; under a
        budget its share of the time solves more sources.
    distributed : train on every rank of torch.distributed's default process group (data-parallel; every rank
        makes this same call, e.g. one process per GPU under ``torchrun`` with ``device=f"cuda:{LOCAL_RANK}"``,
        the default on CUDA). Every rank trains a replica from the same initial weights on batches of its own; the
        gradients are averaged over the ranks before each update, so the replicas stay equal and a step trains on
        world size x the batch. Rank 0 builds the dataset (with ``devices`` if given) while the others wait, then
        every rank reads it from the run folder (on several machines: a shared file system); rank 0 decides the
        step counts under a budget, validates, and writes the checkpoints, the log and the model file; every rank
        returns that model. The group must be
        initialised (``torch.distributed.init_process_group``: NCCL on GPUs, gloo on CPUs), else InputError.
        CUDA graphs are not used. A run continued with another number of ranks needs ``resume``.
    **settings : any TrainConfig setting by name, e.g. ``D=128, lr=3e-3, n_sources=256, epochs=20``

    Notes
    -----
    Without ``resume`` or ``force``, a call that finds a run of the same settings continues it (interrupted) or
    returns its model (finished), and one that finds a run of other settings, or a model file with no run, raises
    ValueError. Ctrl-C writes a checkpoint and raises ``TrainingInterrupted``. A second process training to the
    same ``out`` while one runs gets an InputError (the run folder is locked with ``flock``).

    The dataset's held-out sources (uniformly random vertices, as ``evaluate`` draws its sources) score the final
    model: ``validation_mre`` over all their pairs and ``validation_mre_upper``, a 95% upper bound over sources
    drawn the same way (``training.quality.mre_estimate``); with potpourri3d installed, the heat method on the same
    pairs (``heat_mre``). These, ``worse_than_heat`` and ``quality_warning`` go into the model's ``config`` (the
    file's metadata) and the run's log. A model worse than the heat method, one whose upper bound reaches the heat
    method's MRE, or a budget predicted too small before the steps start, gives a ``ModelQualityWarning``.
    """
    from neurogf_warp.common.clock import budget_start
    from neurogf_warp.common.lazy import call_started

    # a fresh process's import of this stage counts too; on the command line, everything since the process began
    t_call = budget_start(call_started("train", time.perf_counter()))
    budget_seconds = check_budget(budget_seconds)
    if distributed:
        from neurogf_warp.training.trainer import Ranks

        ranks = Ranks.of(distributed)
        if ranks is not None:
            return _train_ranks(ranks, mesh, out, config, device, dataset, resume, force, budget_seconds, progress,
                                callback, settings, t_call, allow_vertex_joins, devices)
    files = RunFiles.for_model(out)
    files.check_writable()
    from neurogf_warp.common.files import output_target

    output_target(out, inputs=(mesh, dataset), what="model file")  # never the mesh or dataset, even with force
    from neurogf_warp.model.files import _not_a_mesh_name

    _not_a_mesh_name(out)  # the rule save() applies at the end, checked before the work
    created = not os.path.isdir(files.folder)
    lock = files.lock()
    try:
        key = None if force else call_key(mesh, config, device, dataset, budget_seconds, settings)
        model = _quick_finished(files, key, progress)
        if model is not None:
            return model
        return _train_locked(mesh, files, config, device, dataset, resume, force, budget_seconds, progress,
                             callback, settings, key, t_call, allow_vertex_joins, devices)
    except BaseException:
        if created and os.path.isdir(files.folder) and not os.listdir(files.folder):
            os.rmdir(files.folder)  # refused before anything was written: leave no empty run folder
        raise
    finally:
        lock.release()


def _train_ranks(ranks, mesh, out, config, device, dataset, resume, force, budget_seconds, progress, callback,
                 settings, t_call, allow_vertex_joins, devices):
    """``train`` over the ranks of ``ranks``: rank 0 takes the run folder and decides (a finished run, the
    checkpoint to continue), every rank loads the mesh and the same checkpoint, then ``_run`` on every rank."""
    import torch

    from neurogf_warp.common.files import output_target
    from neurogf_warp.model.files import _not_a_mesh_name, load

    files = RunFiles.for_model(out)
    progress = progress and ranks.first
    held = {}
    try:  # before the first collective: NCCL's run on the current device
        dev = torch_device(_rank_device(device, ranks))
        if dev.type == "cuda":
            if dev.index is None:
                dev = torch.device("cuda", torch.cuda.current_device())
            torch.cuda.set_device(dev)
    except InputError as e:
        held["device_error"] = e

    def take_folder():  # as train() does in one process: checks, the lock, a finished run's answer
        files.check_writable()
        output_target(out, inputs=(mesh, dataset), what="model file")
        _not_a_mesh_name(out)
        held["created"] = not os.path.isdir(files.folder)
        held["lock"] = files.lock()
        held["key"] = None if force else call_key(mesh, config, device, dataset, budget_seconds, settings)
        held["model"] = _quick_finished(files, held["key"], progress)
        return held["model"] is not None

    try:
        if ranks.on_first(take_folder):
            return held["model"] if ranks.first else load(files.model)

        def prepare():  # every rank: its device, the mesh and the settings, checked alike
            if "device_error" in held:
                raise held["device_error"]
            if dev.type != "cuda" and ranks.nccl:
                raise InputError(f"distributed=True with device {dev}: the process group uses NCCL, which needs "
                                 "GPUs; initialise it with the gloo backend to train on CPUs")
            if devices is not None and ranks.first:  # rank 0 alone builds the dataset, on these GPUs
                from neurogf_warp.ground_truth.devices import resolve_devices

                resolve_devices(devices, str(dev))
            m = load_mesh(mesh)
            check_trainable(m, allow_vertex_joins)
            cfg = resolve_config(config, dev.type, len(m.internal_vertices), **settings)
            ds = None if dataset is None else os.path.abspath(dataset) if isinstance(dataset, (str, os.PathLike)) \
                else "given"
            request = {"config": cfg.to_dict(), "budget_seconds": budget_seconds, "dataset": ds,
                       "world_size": ranks.world}
            return m, cfg, request

        mesh, cfg, request = ranks.on_each(prepare)
        calls = ranks.gather((dev.type, request, mesh.fingerprint))
        if any(c != calls[0] for c in calls):
            r = next(i for i, c in enumerate(calls) if c != calls[0])
            raise InputError(f"distributed=True: rank {r} asked for another training than rank 0 (device type, mesh "
                             "or settings differ); every rank must make the same call")

        def decide():
            ck = _existing_run(files, mesh, request, resume, force, progress)
            files.clean_stale_temporaries()
            return None if ck is None else "finished" if finished(ck) else "continue"

        state = ranks.on_first(decide)
        ck = None if state is None else load_checkpoint(files.checkpoint)
        if state == "finished":
            model = ranks.on_first(lambda: _finished_model(ck, files, mesh, progress), share=False)
            return model if ranks.first else load(files.model)
        if ck is not None:
            cfg = ck["config"]
            old = ck["request"] or {}
            if old.get("world_size", 1) != ranks.world:
                say(progress, f"continuing a run of {old.get('world_size', 1)} rank(s) with {ranks.world}: a step now "
                              f"trains on {ranks.world} x the batch")
            request = dict(old or request, world_size=ranks.world)
        threads = torch.get_num_threads()
        if cfg.runtime.threads:
            torch.set_num_threads(cfg.runtime.threads)
        try:
            return _run(RunPlan(mesh, files, cfg, request, ck, dataset, dev, progress, callback, t_call,
                                held.get("key"), devices if ranks.first else None, ranks))
        finally:
            torch.set_num_threads(threads)
    except BaseException:
        if held.get("created") and os.path.isdir(files.folder) and not os.listdir(files.folder):
            os.rmdir(files.folder)  # refused before anything was written: leave no empty run folder
        raise
    finally:
        if "lock" in held:
            held["lock"].release()


def _rank_device(device, ranks):
    """A rank's training device: ``device``; None or "cuda" on a machine with GPUs: ``cuda:LOCAL_RANK`` (torchrun's
    variable, else the rank modulo the GPU count), so that the ranks of one machine take one GPU each."""
    import torch

    if device is None and not torch.cuda.is_available():
        return device
    if device is None or str(device) == "cuda":
        local = os.environ.get("LOCAL_RANK")
        index = int(local) if local is not None else ranks.rank % max(torch.cuda.device_count(), 1)
        return f"cuda:{index}"
    return device


def _rank_dataset(ranks, mesh, dataset, files, cfg, dev, progress, limit, partial_ok, devices):
    """The dataset of a data-parallel run, the same on every rank: rank 0 obtains it as one process does (building
    it into the run folder's cache while the other ranks wait), then the others read that file; checked by digest."""
    import hashlib

    from neurogf_warp.dataset.build import Dataset

    cache = files.dataset if dataset is None else None
    ds = ranks.on_first(lambda: obtain_dataset(mesh, dataset, cache, cfg.data, cfg.seed, dev, progress,
                                               time_limit_s=limit, partial_ok=partial_ok, devices=devices),
                        share=False)
    if not ranks.first:
        ds = ranks.on_each(lambda: Dataset.load(cache) if cache is not None else
                           obtain_dataset(mesh, dataset, None, cfg.data, cfg.seed, dev, False))
    else:
        ranks.on_each(lambda: None)
    digest = hashlib.sha1()
    for name, a in sorted(ds.arrays().items()):
        a = np.ascontiguousarray(a)
        digest.update(f"{name}{a.dtype}{a.shape}".encode())
        digest.update(a.tobytes())
    digests = ranks.gather(digest.hexdigest())
    if any(d != digests[0] for d in digests):
        raise InputError("distributed=True: the ranks' datasets differ (a Dataset passed to train must be the same "
                         "on every rank); pass a dataset file, or none")
    return ds


def _train_locked(mesh, files, config, device, dataset, resume, force, budget_seconds, progress, callback,
                  settings, key, t_call, allow_vertex_joins=False, devices=None):
    import torch

    if devices is not None:  # checked before any work; the steps run on `device`, else the first of them
        from neurogf_warp.ground_truth.devices import resolve_devices

        devices = [str(d) for d in resolve_devices(devices, device)]
        device = devices[0]
    dev = torch_device(device)
    if dev.type == "cuda" and dev.index is None:  # generators and tensors must agree on the index
        dev = torch.device("cuda", torch.cuda.current_device())
    mesh = load_mesh(mesh)
    check_trainable(mesh, allow_vertex_joins)
    cfg = resolve_config(config, dev.type, len(mesh.internal_vertices), **settings)
    request = {"config": cfg.to_dict(), "budget_seconds": budget_seconds,
               "dataset": None if dataset is None else os.path.abspath(dataset) if isinstance(dataset, (str, os.PathLike))
               else "given"}

    ck = _existing_run(files, mesh, request, resume, force, progress)
    files.clean_stale_temporaries()
    if ck is not None and finished(ck):
        return _finished_model(ck, files, mesh, progress)
    if ck is not None:
        cfg = ck["config"]
        request = ck["request"] or request
        if "world_size" in request:  # a data-parallel run continued in one process
            request = {k: v for k, v in request.items() if k != "world_size"}
    threads = torch.get_num_threads()
    if cfg.runtime.threads:
        torch.set_num_threads(cfg.runtime.threads)
    try:
        return _run(RunPlan(mesh, files, cfg, request, ck, dataset, dev, progress, callback, t_call, key, devices))
    finally:
        torch.set_num_threads(threads)


def _quick_finished(files: RunFiles, key: dict | None, progress: bool):
    """The finished model when the run folder's log says that this same call already finished it (the model file
    and the checkpoint still there), else None; costs a JSON read and the model file's load."""
    if finished_log(files, key) is None:
        return None
    from neurogf_warp.model.files import load

    try:
        model = load(files.model)
    except (ValueError, OSError):
        return None  # the full path says what is wrong and writes it again
    say(progress, f"{files.model} is already trained (finished run in {files.folder}); pass force=True "
                  "(--force) to train again")
    _warn_again(model)
    return model


def _warn_again(model) -> None:
    """A finished model that was worse than the heat method is still so: say it on every call that returns it."""
    msg = (model.config or {}).get("quality_warning")
    if msg:
        import warnings

        warnings.warn(msg, ModelQualityWarning, stacklevel=4)


def _calibrate(trainer, cfg: TrainConfig, dev, n: int, rounds: list, deadline: float | None = None) -> dict | None:
    """Seconds per step of each stage, timed with the run's own TF32 setting; None when ``deadline`` (a
    ``time.perf_counter()`` value) passed before the timing was done. Appends the round's per-stage warm-up and
    step seconds to ``rounds`` (the run log's ``timings["calibrate_rounds"]``)."""
    from neurogf_warp.training.acceleration import set_tf32

    tf32 = set_tf32(cfg.runtime.tf32) if dev.type == "cuda" else None
    warm = {}
    try:
        per = calibrate(trainer, n=n, give_up_s=None if deadline is None else max(0.0, deadline - time.perf_counter()),
                        warm_s=warm)
        rounds.append({"n": n, "warm_s": warm, "per_step_s": per})
        return per
    finally:
        if tf32 is not None:
            set_tf32(tf32)


def _plan_compile(cfg: TrainConfig, dev, deadline: float, timings: dict) -> str | None:
    """The compile key of ``cfg``'s batches if a budgeted CUDA run compiles its losses, from the time left to
    ``deadline`` (``acceleration.compile_pays``), else None; the decision, its expected cost and whether the cache
    holds these shapes go into ``timings["compile"]``."""
    from neurogf_warp.training.acceleration import compile_cached, compile_key, compile_pays

    key = compile_key(cfg, dev)
    use, expected = compile_pays(key, deadline - time.perf_counter())
    # "cached": this machine had compiled these shapes before (a run's speed then depends on its history)
    timings["compile"] = {"used": use, "expected_s": round(expected, 1), "cached": compile_cached(key)}
    return key if use else None


LANDMARK_SHARE = 0.15  # of a budget, at most, for the landmark rows of a ``landmarks=K`` network
# ... where the dataset's rows are coarser (k < trainer.LANDMARK_MIN_K) and are solved again: the table's accuracy
# outweighs the training time it costs (two CPU cores, 60 s, share 0.15 / 0.3 / 0.5: spot 0.152 / 0.097 / 0.074%
# MRE, cow 0.186 / 0.156 / 0.135%; bakeoff_landmark_resolve_share_cpu_2026-11-29.json)
LANDMARK_RESOLVE_SHARE = 0.5


def _landmark_plan(cfg: TrainConfig, mesh, dev, budget_seconds) -> tuple:
    """(landmarks to solve, estimated seconds each) of a ``landmarks=K`` network: K, or under a budget as many as
    fit in ``LANDMARK_SHARE`` of it (``LANDMARK_RESOLVE_SHARE`` where coarse dataset rows are solved again; at
    least 8; the network's K columns then repeat them, or keep their coarse rows). (0, 0.0) without."""
    k = cfg.network.landmarks
    if not k:
        return 0, 0.0
    from neurogf_warp.dataset.build import cpu_seconds_per_source, gpu_seconds_per_source
    from neurogf_warp.ground_truth.geodesics import DEFAULT_K

    from neurogf_warp.training.trainer import LANDMARK_MIN_K

    v = len(mesh.internal_vertices)
    per = cpu_seconds_per_source(v, DEFAULT_K) if dev.type == "cpu" else gpu_seconds_per_source(v)
    if budget_seconds is None:
        return k, per
    share = LANDMARK_RESOLVE_SHARE if cfg.data.k < LANDMARK_MIN_K else LANDMARK_SHARE
    return int(min(k, max(8, share * budget_seconds // per))), per


@dataclasses.dataclass
class RunPlan:
    """What a run is given: the checked call, its settings and the checkpoint it continues.

    Attributes
    ----------
    mesh : the loaded, checked Mesh
    files : the run folder's files (``RunFiles``)
    cfg : the run's settings (a continued run's own)
    request : what the call asked for (settings, ``budget_seconds``, dataset), as the checkpoint stores it
    checkpoint : the checkpoint dict to continue, or None for a new run
    dataset : None (the run folder's cache, else built), a Dataset, or a dataset ``.npz`` file
    device : the torch device the steps run on
    progress : progress bars and messages on stderr
    callback : ``callback(stage, step, terms)`` after every step, or None
    t_call : ``time.perf_counter()`` at the start of the call (s; the budget counts from it)
    key : the call's key (``run_folder.call_key``) written to the log, or None
    devices : GPUs that share the dataset's ground truth, or None
    ranks : a ``trainer.Ranks`` (data-parallel), or None
    """

    mesh: object
    files: RunFiles
    cfg: TrainConfig
    request: dict
    checkpoint: dict | None
    dataset: object
    device: "torch.device"
    progress: bool
    callback: object
    t_call: float
    key: dict | None
    devices: list | None = None
    ranks: object = None

    @property
    def first(self) -> bool:
        """Whether this process decides and writes (one process, or rank 0)."""
        return self.ranks is None or self.ranks.first

    def agree(self, value):
        """Rank 0's ``value`` on every rank (``value`` itself in one process)."""
        return value if self.ranks is None else self.ranks.agree(value)


@dataclasses.dataclass
class _RunState:
    """What a run has made and measured so far, passed from one phase of ``_run`` to the next.

    ``deadline`` and the times are ``time.perf_counter()`` values and seconds; ``per`` is seconds per step of each
    stage; ``stage_i, step, history, elapsed`` are where the stages stand (as a checkpoint stores them)."""

    cfg: TrainConfig
    deadline: float | None
    spent_before: float
    t_data: float = 0.0
    dataset_s: float = 0.0
    timings: dict = dataclasses.field(default_factory=dict)
    ds: object = None
    data: object = None
    pool: tuple | None = None
    heat: object = None
    heat_mre: float | None = None
    trainer: object = None
    budget: object = None
    per: dict | None = None
    chooser: object = None
    history: dict | None = None
    stage_i: int = 0
    step: int = 0
    elapsed: float = 0.0


def _run(plan: RunPlan):
    """Dataset, set-up, budget, the stages and the model file of a run (new, or continued from its checkpoint).

    The budget (``request["budget_seconds"]``) covers every call of a run: a continued run gets what the earlier
    calls left (their wall seconds are kept in the checkpoint as ``spent_s``) and re-plans its steps to fit it.

    With ``ranks`` (data-parallel) every rank runs this, and every value that steers the steps and is measured on a
    clock (time left, step times, the compile decision) is rank 0's (``agree``); only rank 0 writes."""
    run = _run_clock(plan)
    _run_data(plan, run)
    _run_set_up(plan, run)
    _run_stages(plan, run)
    if plan.ranks is None:
        return _run_finish(plan, run)
    model = plan.ranks.on_first(lambda: _run_finish(plan, run), share=False)
    if plan.first:
        return model
    from neurogf_warp.model.files import load

    return load(plan.files.model)  # the file rank 0 wrote: the same model on every rank


def _run_clock(plan: RunPlan) -> _RunState:
    """The run's state with its deadline: the budget less what earlier calls spent and ``SAVE_RESERVE_S``."""
    budget_seconds = plan.request.get("budget_seconds")
    ck = plan.checkpoint
    spent_before = float(ck.get("spent_s", 0.0)) if ck is not None else 0.0
    deadline = None if budget_seconds is None else plan.t_call + budget_seconds - spent_before - SAVE_RESERVE_S
    if plan.ranks is not None and deadline is not None:  # rank 0's deadline on every rank's own clock
        deadline = time.perf_counter() + plan.agree(deadline - time.perf_counter())
    return _RunState(cfg=plan.cfg, deadline=deadline, spent_before=spent_before)


def _run_data(plan: RunPlan, run: _RunState) -> None:
    """The dataset (within its share of the budget), the heat-method baseline, the device data and the SDF pool."""
    mesh, ck, dev, ranks, cfg = plan.mesh, plan.checkpoint, plan.device, plan.ranks, run.cfg
    budget_seconds = plan.request.get("budget_seconds")
    run.t_data = t_data = time.perf_counter()
    loaded_before = load_seconds()
    # the ground truth's share counts from the start of the call (the mesh was loaded and checked in it)
    limit = None if budget_seconds is None or ck is not None else \
        max(0.0, DATA_SHARE * budget_seconds - (t_data - plan.t_call))
    landmarks_solved, _ = _landmark_plan(cfg, mesh, dev, budget_seconds)
    if cfg.network.landmarks and cfg.data.full_rows < cfg.network.landmarks:
        # the landmark rows come with the dataset's first distance sources (a proxy dataset has none: the trainer
        # then solves ``landmarks_solved`` of them itself)
        cfg = run.cfg = dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, full_rows=cfg.network.landmarks))
    if ranks is None:
        ds = obtain_dataset(mesh, plan.dataset, plan.files.dataset if plan.dataset is None else None, cfg.data,
                            cfg.seed, dev, plan.progress, time_limit_s=limit, partial_ok=ck is not None,
                            devices=plan.devices)
    else:
        ds = _rank_dataset(ranks, mesh, plan.dataset, plan.files, cfg, dev, plan.progress, limit, ck is not None,
                           plan.devices)
    run.ds, run.dataset_s = ds, time.perf_counter() - t_data
    # the dataset's own phases (sampling, distances, paths; a cached dataset's are those of its build)
    run.timings = {"dataset_s": run.dataset_s, "dataset_phases": dict(ds.meta.get("timings") or {}),
                   "kernels_load_s": load_seconds() - loaded_before}  # Warp's modules, compiled or from its cache
    if ck is not None and "heat_mre" in ck["history"]:
        run.heat_mre = ck["history"]["heat_mre"]
    elif plan.first:  # the baseline on the held-out pairs, made by another process while the model trains
        run.heat = HeatBaseline(ds.vertices, ds.faces, ds.test_src, ds.test_dist)
    run.data = TrainingData(ds, dev)
    run.data.landmarks_solved = landmarks_solved
    t0 = time.perf_counter()
    run.pool = make_sdf_pool(mesh, run.data.surface_points, cfg.batches.sdf_pool, cfg.seed, dev)
    if ranks is not None:  # rank 0's SDF values (a GPU's may differ in the last bits)
        ranks.broadcast_(run.pool)
    run.timings["sdf_pool_s"] = time.perf_counter() - t0


def _run_set_up(plan: RunPlan, run: _RunState) -> None:
    """The trainer, and where the stages start: the checkpoint's step, or step 0 with the steps fitted to the
    budget; then the history's record of the set-up."""
    import torch

    cfg, dev, ds = run.cfg, plan.device, run.ds
    run.trainer = _new_trainer(plan, run, cfg)
    if dev.type == "cpu" and cfg.runtime.threads == 0:
        run.chooser = ThreadChooser()  # the thread count is chosen on the first steps of the main stages
        torch.set_num_threads(1)  # calibrated at one thread; the budget re-plans from the measured steps
    # torch.compile under a budget: decided for the batch shapes the run trains on (a new run may shrink its
    # batches, short_budget_scale, on eager steps first), so that it compiles once and plans with the time a run
    # of those shapes took here (acceleration.compile_estimate); a budget too short to win it back runs eagerly
    plan_compile = run.deadline is not None and dev.type == "cuda" and cfg.runtime.compile
    if plan_compile:
        run.trainer.compile_losses(False)
    if plan.checkpoint is not None:
        _run_continue(plan, run, plan_compile)
    else:
        run.stage_i, run.step, run.elapsed = 0, 0, 0.0
        run.history = {"loss": [], "val": []}
        if run.deadline is not None:
            _run_fit_budget(plan, run, plan_compile)
    history = run.history
    history["heat_mre"] = run.heat_mre
    history["sources"] = {"distance": int(len(ds.gd_src)), "asked": int(run.cfg.data.n_sources),
                          "test": int(len(ds.test_src)), "complete": bool(ds.meta.get("complete", True))}
    history["per_step"] = run.per
    history["dataset_s"] = run.dataset_s
    history["proxy"] = proxy = ds.meta.get("proxy")  # training sources on a decimated copy (dataset/proxy.py)
    if proxy and (proxy.get("error") or {}).get("mre") is not None:
        off = f"{100 * proxy['error']['mre']:.3f}% off the mesh's own geodesics from the held-out sources"
        say(plan.progress, f"ground truth on a {proxy['vertices']:,}-vertex proxy of the mesh ({off})" if proxy["kept"]
            else f"a {proxy['vertices']:,}-vertex proxy was {off}: ground truth on the mesh itself")
    history["threads"] = torch.get_num_threads() if dev.type == "cpu" else None  # chooser: per stage, below
    history["prep_s"] = time.perf_counter() - run.t_data


def _run_continue(plan: RunPlan, run: _RunState, plan_compile: bool) -> None:
    """A continued run: the checkpoint's state and step, and the steps left re-planned from the budget left."""
    ck, trainer, deadline = plan.checkpoint, run.trainer, run.deadline
    if plan_compile:  # the checkpoint's batches: the shapes the run goes on with
        trainer.compile_losses(plan.agree(_plan_compile(run.cfg, plan.device, deadline, run.timings)) is not None)
    trainer.load_state(ck)
    run.stage_i, run.step, run.history, run.elapsed = ck["stage"], ck["step"], ck["history"], ck["elapsed"]
    say(plan.progress, f"continuing the run in {plan.files.folder}: stage {STAGES[run.stage_i]}, step {run.step}")
    if deadline is not None:  # re-plan the steps left from the budget left
        history, budget_seconds = run.history, plan.request.get("budget_seconds")
        run.per = plan.agree(history.get("per_step") or calibrate(trainer, n=3))
        cap = history["planned_steps"]["joint"] if "planned_steps" in history else None
        run.budget = Budget(trainer.cfg, deadline, run.per, cap=cap)
        say(plan.progress, f"{budget_seconds - run.spent_before:.0f} s of the {budget_seconds:.0f} s budget left")


def _run_fit_budget(plan: RunPlan, run: _RunState, plan_compile: bool) -> None:
    """A new budgeted run: its steps timed (at smaller batches when the budget is short, compiled where that
    pays) and their counts fitted to the time left; the untrained model's zero steps when the budget is gone."""
    cfg, dev, ranks, deadline, agree = run.cfg, plan.device, plan.ranks, run.deadline, plan.agree
    budget_seconds, history, timings = plan.request.get("budget_seconds"), run.history, run.timings
    rescale = cfg.batches.short_budget_batches and cfg.runtime.fill_budget
    t0 = time.perf_counter()
    # the budget ended before the steps or while they were timed (a fresh GPU machine's 20 s call took 2.8 s
    # to time them and ended 1.6-2.2 s late; timing a first step costs 2.4 s on a fresh 2-core CPU): no
    # steps, the untrained model is saved, and the warnings say why
    out_of_time = agree(deadline <= time.perf_counter())
    # data-parallel: every rank times the same steps (they all-reduce), none giving up alone
    rounds = timings["calibrate_rounds"] = []
    per = None if out_of_time else agree(_calibrate(run.trainer, cfg, dev, n=20 if run.trainer.graphs else 2,
                                                    rounds=rounds, deadline=deadline if ranks is None else None))
    out_of_time = per is None
    if out_of_time:
        per = {s: float(budget_seconds) for s in STAGES}
    left = agree(deadline - time.perf_counter())
    fitted = fit_budget(cfg, per, max(left, 0.0))
    scale, history["batch_scale"] = short_budget_scale(fitted.joint_steps, dev.type), 1.0
    shrunk = rescale and scale < 1 and not out_of_time
    if shrunk:
        batches = cfg.batches.scaled(scale, sdf_factor=max(scale, MIN_SDF_SCALE))
        cfg = dataclasses.replace(cfg, batches=batches)
        run.trainer = _new_trainer(plan, run, cfg)  # its CUDA graphs are captured for the new shapes
        run.trainer.compile_losses(False)
        history["batch_scale"] = scale
    compiling = agree(_plan_compile(cfg, dev, deadline, timings)) if plan_compile and not out_of_time else None
    if plan_compile and out_of_time:
        timings["compile"] = {"used": False, "expected_s": None, "cached": None}
    if compiling is not None:  # compile every stage now, timed: later runs of these shapes plan with that
        from neurogf_warp.training.acceleration import record_compile

        run.trainer.compile_losses(True)
        t1 = time.perf_counter()
        per = agree(_calibrate(run.trainer, cfg, dev, n=20, rounds=rounds))
        if plan.first:
            record_compile(compiling, time.perf_counter() - t1, warm=timings["compile"]["cached"])
    elif shrunk:  # timed again at the smaller batches; the full batches' times if the budget ends first
        per = agree(_calibrate(run.trainer, cfg, dev, n=8 if run.trainer.graphs else 2, rounds=rounds,
                               deadline=deadline if ranks is None else None) or per)
    if shrunk or compiling is not None:
        left = agree(deadline - time.perf_counter())
        fitted = fit_budget(cfg, per, max(left, 0.0))
    if shrunk:
        history["short_budget"] = {"scale": scale, "planned_joint_steps": int(fitted.joint_steps)}
        say(plan.progress, short_budget_said(scale))
    timings["calibrate_s"] = time.perf_counter() - t0
    _run_plan_steps(plan, run, cfg, fitted, per, left, out_of_time)


def _new_trainer(plan: RunPlan, run: _RunState, cfg: TrainConfig):
    """A Trainer of ``cfg`` on the run's data, SDF pool, device and ranks."""
    from neurogf_warp.training.trainer import Trainer

    return Trainer(cfg, run.data, run.pool, plan.device, plan.ranks)


def _run_plan_steps(plan: RunPlan, run: _RunState, cfg: TrainConfig, fitted: TrainConfig, per: dict, left: float,
                    out_of_time: bool) -> None:
    """The run's step counts (``fitted``'s, or the preset's where the budget only caps them), its Budget and the
    verdict on the budget; ``left`` is the time left (s) that ``fitted`` was fitted to."""
    history, budget_seconds = run.history, plan.request.get("budget_seconds")
    cap = None
    if not cfg.runtime.fill_budget:  # the preset's own steps, the budget only a cap
        cap = cfg.joint_steps
        history["planned_steps"] = cfg.stage_steps()
        if fitted.joint_steps >= cfg.joint_steps:
            fitted = cfg
    cfg = run.cfg = fitted
    trainer = run.trainer
    trainer.cfg = cfg
    trainer.steps = {s: 0 for s in STAGES} if out_of_time else cfg.stage_steps()
    run.per = per
    run.budget = None if out_of_time else Budget(cfg, run.deadline, per, cap=cap)  # its floor plan is one step
    if plan.first:  # data-parallel: said once
        history["budget_warning"] = budget_verdict(trainer.steps["joint"], max(left, 0.0) / budget_seconds,
                                                   len(run.ds.gd_src), cfg.data.n_sources, plan.progress,
                                                   kernels_s=run.timings["kernels_load_s"])


def _save(plan: RunPlan, run: _RunState, stage_i: int, step: int, history: dict, elapsed: float) -> bool:
    """Write the run's checkpoint at (stage ``stage_i``, ``step``); data-parallel: rank 0 alone writes."""
    if not plan.first:
        return False
    spent = run.spent_before + time.perf_counter() - plan.t_call
    return save_checkpoint({"version": CKPT_VERSION, "config": run.trainer.cfg.to_dict(), "request": plan.request,
                            "fingerprint": plan.mesh.fingerprint, "stage": stage_i, "step": step,
                            **run.trainer.state(), "history": history, "elapsed": elapsed, "spent_s": spent},
                           plan.files.checkpoint)


def _run_stages(plan: RunPlan, run: _RunState) -> None:
    """The stages from the run's (stage, step) to the end (``loop.Runner``), with checkpoints on the way."""
    runner = Runner(run.trainer, lambda *at: _save(plan, run, *at), plan.files.checkpoint, plan.progress,
                    plan.callback, run.budget, run.chooser, plan.ranks)
    t0 = time.perf_counter()
    try:
        run.stage_i, run.step, run.history, run.elapsed = runner(run.stage_i, run.step, run.history, run.elapsed)
    except BaseException:
        if run.heat is not None:
            run.heat.close()
        raise
    run.timings["steps_s"] = time.perf_counter() - t0


def _run_finish(plan: RunPlan, run: _RunState):
    """The verdict, the last checkpoint, the model file and the log; returns the saved Model."""
    progress, trainer, history, timings = plan.progress, run.trainer, run.history, run.timings
    budget_seconds, deadline, files, chooser = plan.request.get("budget_seconds"), run.deadline, plan.files, run.chooser
    if chooser is not None:
        history["threads"] = chooser.chosen
        say(progress and bool(chooser.chosen), "torch threads (timed fastest on the first steps): "
            + ", ".join(f"{k} {v}" for k, v in chooser.chosen.items()))
    estimate, heat_note = mre_estimate(*trainer.source_errors()), None
    val_mre = estimate["mre"]
    if run.heat is not None:  # wait for the heat method at most until the deadline
        t0 = time.perf_counter()
        run.heat_mre, heat_note = run.heat.mre(None if deadline is None else max(0.0, deadline - t0))
        timings.update(heat_wait_s=time.perf_counter() - t0, heat_s=run.heat.seconds)
        history["heat_mre"] = run.heat_mre
    quality = final_verdict(val_mre, run.heat_mre, progress, heat_note, n_test=len(run.ds.test_src),
                            estimate=estimate)
    if "planned_steps" in history:  # fill_budget=False: did the budget cut the preset's steps?
        planned = history["planned_steps"]
        quality["budget_bound"] = any(trainer.steps[s] < planned[s] for s in STAGES)
        if quality["budget_bound"]:
            say(progress, f"note: the budget bound: {sum(trainer.steps.values()):,} of the preset's "
                          f"{sum(planned.values()):,} steps ran (the machine was slower than the budget allows)")
    history["quality"] = quality
    # the checkpoint keeps the verdict too: a model file written again from it (lost or unreadable) says the same
    _save(plan, run, run.stage_i, run.step, history, run.elapsed)
    info = dict(trainer.cfg.to_dict(), steps=trainer.steps, train_seconds=round(run.elapsed, 2), **quality,
                budget_warning=history.get("budget_warning"))
    model = save_model(trainer.net, trainer.querier, plan.mesh, files.model, info)
    call_s = time.perf_counter() - plan.t_call
    timings.update(call_s=call_s, spent_s=run.spent_before + call_s, budget_seconds=budget_seconds,
                   calibrated_s_per_step=run.per)
    _write_log(files, info, history, timings, plan.key)
    if "short_budget" in history:
        say(progress, short_budget_done(history["short_budget"], trainer.steps["joint"]))
    say(progress, f"saved {files.model} ({call_s:.0f} s; {trainer.steps['joint']:,} joint steps, "
                  f"{sum(trainer.steps.values()):,} in all)")
    over = run.spent_before + call_s - budget_seconds if budget_seconds else 0.0
    if over > max(1.0, 0.02 * budget_seconds if budget_seconds else 0.0):
        say(progress, f"the run took {over:.0f} s more than its {budget_seconds:g} s budget: loading, the held-out "
                      "ground truth and saving take at least that long on this machine; give a larger budget_seconds "
                      "(--budget-seconds)")
    return model


def _existing_run(files: RunFiles, mesh, request: dict, resume: bool, force: bool, progress: bool):
    """The checkpoint to continue, or None to start afresh; raises ValueError where the choice is the user's."""
    if force:
        return None
    if not os.path.exists(files.checkpoint):
        if resume:
            say(True, f"no checkpoint at {files.checkpoint}; starting from scratch")
        elif os.path.exists(files.model):
            raise ValueError(f"{files.model} exists and no run of it is in {files.folder}: pass force=True (--force) "
                             "to overwrite it, or write to another file")
        return None
    ck = load_checkpoint(files.checkpoint)
    if ck["fingerprint"] != mesh.fingerprint:
        raise ValueError(f"the run in {files.folder} belongs to a different mesh; pass force=True (--force) to "
                         "start over, or write to another file")
    if resume or ck["request"] == request:
        return ck
    diff = _differences(ck["request"], request)
    raise ValueError(f"the run in {files.folder} was started with other settings ({diff}); pass resume=True "
                     "(--resume) to continue it with its own settings, or force=True (--force) to start over")


def _differences(old, new) -> str:
    if old is None:
        return "it predates this version"

    def flat(d, prefix=""):
        out = {}
        for k, v in (d or {}).items():
            if isinstance(v, dict) and k != "ratios" and k != "loss_weights":
                out.update(flat(v, f"{prefix}{k}."))
            else:
                out[prefix + k] = v
        return out

    a, b = flat(old), flat(new)
    keys = [k for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k) and not k.endswith("preset")]
    shown = ", ".join(f"{k.split('.')[-1]} {a.get(k)!r} -> {b.get(k)!r}" for k in keys[:4])
    return shown + (" ..." if len(keys) > 4 else "") if keys else "preset"


def _finished_model(ck: dict, files: RunFiles, mesh, progress: bool):
    """The model of a finished run: the model file when it is there and readable, else written from the
    checkpoint (a run killed between its last checkpoint and the model file)."""
    from neurogf_warp.model.files import load
    from neurogf_warp.model.network import SdfQuerier

    if os.path.exists(files.model):
        try:
            model = load(files.model)
            say(progress, f"{files.model} is already trained (finished run in {files.folder}); pass force=True "
                          "(--force) to train again")
            _warn_again(model)
            return model
        except (ValueError, OSError) as e:
            say(True, f"{files.model} is unreadable ({e}); writing it again from the finished run's checkpoint")
    cfg = ck["config"]
    net = cfg.network.build()
    net.load_state_dict(ck["net"])
    querier = SdfQuerier()
    querier.load_state_dict(ck["querier"])
    info = dict(cfg.to_dict(), steps=ck["steps"], train_seconds=round(ck["elapsed"], 2),
                **ck["history"].get("quality", {}), budget_warning=ck["history"].get("budget_warning"))
    model = save_model(net, querier, mesh, files.model, info)
    if not os.path.exists(files.log):
        _write_log(files, info, ck["history"], {}, None)
    say(progress, f"saved {files.model} from the finished run's checkpoint")
    return model


def _write_log(files: RunFiles, info: dict, history: dict, timings: dict, key: dict | None):
    """The run's log: settings, loss and validation history, timings, the verdict on its quality, and the call
    that finished it (``call``: a repeat of that call answers from the model without loading anything else)."""
    from neurogf_warp.common.files import atomic_write

    text = json.dumps({"config": info, "history": history, "timings": timings, "quality": history.get("quality"),
                       "finished": True, "call": key}).encode()
    atomic_write(files.log, lambda f: f.write(text))
