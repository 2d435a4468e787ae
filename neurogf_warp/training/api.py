"""``train()``: one call from a mesh to a saved model, safe to repeat.

Order of work: every check first (output folder, settings, device, mesh), then the dataset (cached in the run
folder), the SDF pool, timing and fitting the step counts to the budget, the stages, and the model file.
A repeated call with the same settings continues an interrupted run from its checkpoint, or answers from the
finished one; other settings on top of an existing run are refused unless ``resume`` or ``force`` says which.
"""
from __future__ import annotations

import json
import os
import time
from typing import TYPE_CHECKING

from neurogf_warp.dataset.build import check_trainable
from neurogf_warp.mesh.mesh import load_mesh
from neurogf_warp.training.budget import Budget, calibrate, fastest_threads, fit_budget
from neurogf_warp.training.checkpoint import (
    CKPT_VERSION,
    RunFiles,
    finished,
    load_checkpoint,
    save_checkpoint,
    save_model,
)
from neurogf_warp.training.config import STAGES, TrainConfig
from neurogf_warp.training.data import TrainingData, _say, make_sdf_pool, obtain_dataset
from neurogf_warp.training.loop import Runner
from neurogf_warp.training.presets import choose_preset, preset

if TYPE_CHECKING:
    import torch

    from neurogf_warp.model.model import Model

__all__ = ["train", "resolve_config", "torch_device"]

SAVE_RESERVE_S = 1.0  # seconds of a budget kept for writing the model and the log
# The largest share of a budgeted call that ground truth may take: where sources are slow (large meshes on a CPU),
# more sources buy accuracy only while the steps left can still fit them, and past about a third they cannot
DATA_SHARE = 1 / 3


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
          callback=None, **settings) -> "Model":
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
    force : start over, replacing an existing run and model file
    budget_seconds : fit the step counts so that the whole call (dataset, set-up, all stages, saving) takes about
        this long; the counts are then fixed in the checkpoint
    progress : progress bars and messages on stderr
    callback : ``callback(stage, step, terms)`` after every step (raise KeyboardInterrupt there to stop like Ctrl-C)
    **settings : any TrainConfig setting by name, e.g. ``D=128, lr=3e-3, n_sources=256, epochs=20``

    Without ``resume`` or ``force``, a call that finds a run of the same settings continues it (interrupted) or
    returns its model (finished), and one that finds a run of other settings, or a model file with no run, raises
    ValueError. Ctrl-C writes a checkpoint and raises ``TrainingInterrupted``.
    """
    import torch

    t_call = time.perf_counter()
    if budget_seconds is not None and not (isinstance(budget_seconds, (int, float)) and budget_seconds > 0):
        raise ValueError(f"budget_seconds must be a number > 0, got {budget_seconds!r}")
    files = RunFiles.for_model(out)
    files.check_writable()
    dev = torch_device(device)
    if dev.type == "cuda" and dev.index is None:  # generators and tensors must agree on the index
        dev = torch.device("cuda", torch.cuda.current_device())
    mesh = load_mesh(mesh)
    check_trainable(mesh)
    cfg = resolve_config(config, dev.type, len(mesh.vertices), **settings)
    request = {"config": cfg.to_dict(), "budget_seconds": budget_seconds,
               "dataset": None if dataset is None else os.path.abspath(dataset) if isinstance(dataset, (str, os.PathLike))
               else "given"}

    ck = _existing_run(files, mesh, request, resume, force, progress)
    files.make_folder()
    files.clean_stale_temporaries()
    if ck is not None and finished(ck):
        return _finished_model(ck, files, mesh, progress)
    if ck is not None:
        cfg = ck["config"]
        request = ck["request"] or request
    threads = torch.get_num_threads()
    if cfg.runtime.threads:
        torch.set_num_threads(cfg.runtime.threads)
    try:
        return _run(mesh, files, cfg, request, ck, dataset, dev, budget_seconds, progress, callback, t_call)
    finally:
        torch.set_num_threads(threads)


def _run(mesh, files: RunFiles, cfg: TrainConfig, request: dict, ck, dataset, dev, budget_seconds, progress,
         callback, t_call: float):
    """Dataset, set-up, budget, the stages and the model file of a run (new, or continued from ``ck``)."""
    import torch

    t_data = time.perf_counter()
    limit = None if budget_seconds is None or ck is not None else DATA_SHARE * budget_seconds
    ds = obtain_dataset(mesh, dataset, files.dataset if dataset is None else None, cfg.data, cfg.seed, dev, progress,
                        time_limit_s=limit, partial_ok=ck is not None)
    dataset_s = time.perf_counter() - t_data
    data = TrainingData(ds, dev)
    pool = make_sdf_pool(mesh, data.surface_points, cfg.batches.sdf_pool, cfg.seed, dev)
    from neurogf_warp.training.trainer import Trainer

    trainer = Trainer(cfg, data, pool, dev)
    budget, per = None, None
    if dev.type == "cpu" and cfg.runtime.threads == 0:
        cores = torch.get_num_threads()
        threads, per = fastest_threads(trainer)
        _say(progress, f"training with {threads} of {cores} torch thread{'s' if cores > 1 else ''} (timed fastest)")
    if ck is not None:
        trainer.load_state(ck)
        stage_i, step, history, elapsed = ck["stage"], ck["step"], ck["history"], ck["elapsed"]
        _say(progress, f"continuing the run in {files.folder}: stage {STAGES[stage_i]}, step {step}")
    else:
        if budget_seconds is not None:
            from neurogf_warp.training.acceleration import set_tf32

            tf32 = set_tf32(cfg.runtime.tf32) if dev.type == "cuda" else None  # time what the run will do
            try:
                per = per or calibrate(trainer, n=20 if trainer.graphs else 6)
            finally:
                if tf32 is not None:
                    set_tf32(tf32)
            deadline = t_call + budget_seconds - SAVE_RESERVE_S
            left = deadline - time.perf_counter()
            if left < 0.2 * budget_seconds:
                _say(True, f"warning: the dataset and set-up took {time.perf_counter() - t_call:.0f} s of the "
                           f"{budget_seconds:.0f} s budget; training gets the minimum steps. Raise the budget or "
                           "lower n_sources / n_path_sources")
            cfg = fit_budget(cfg, per, max(left, 0.0))
            trainer.cfg = cfg
            trainer.steps = cfg.stage_steps()
            budget = Budget(cfg, deadline, per)
        stage_i, step, elapsed = 0, 0, 0.0
        history = {"loss": [], "val": []}
    history["dataset_s"] = dataset_s
    history["threads"] = torch.get_num_threads() if dev.type == "cpu" else None
    history["prep_s"] = time.perf_counter() - t_data

    def save(stage_i, step, history, elapsed):
        return save_checkpoint({"version": CKPT_VERSION, "config": trainer.cfg.to_dict(), "request": request,
                                "fingerprint": mesh.fingerprint, "stage": stage_i, "step": step, **trainer.state(),
                                "history": history, "elapsed": elapsed}, files.checkpoint)

    run = Runner(trainer, save, files.checkpoint, progress, callback, budget)
    stage_i, step, history, elapsed = run(stage_i, step, history, elapsed)
    info = dict(trainer.cfg.to_dict(), steps=trainer.steps, train_seconds=round(elapsed, 2))
    model = save_model(trainer.net, trainer.querier, mesh, files.model, info)
    call_s = time.perf_counter() - t_call
    _write_log(files, info, history, {"call_s": call_s, "dataset_s": dataset_s, "budget_seconds": budget_seconds,
                                      "calibrated_s_per_step": per})
    _say(progress, f"saved {files.model} ({call_s:.0f} s in all, {elapsed:.0f} s of training steps)")
    return model


def _existing_run(files: RunFiles, mesh, request: dict, resume: bool, force: bool, progress: bool):
    """The checkpoint to continue, or None to start afresh; raises ValueError where the choice is the user's."""
    if force:
        return None
    if not os.path.exists(files.checkpoint):
        if resume:
            _say(True, f"no checkpoint at {files.checkpoint}; starting from scratch")
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
            _say(progress, f"{files.model} is already trained (finished run in {files.folder}); pass force=True "
                           "(--force) to train again")
            return model
        except (ValueError, OSError) as e:
            _say(True, f"{files.model} is unreadable ({e}); writing it again from the finished run's checkpoint")
    cfg = ck["config"]
    net = cfg.network.build()
    net.load_state_dict(ck["net"])
    querier = SdfQuerier()
    querier.load_state_dict(ck["querier"])
    info = dict(cfg.to_dict(), steps=ck["steps"], train_seconds=round(ck["elapsed"], 2))
    model = save_model(net, querier, mesh, files.model, info)
    if not os.path.exists(files.log):
        _write_log(files, info, ck["history"], {})
    _say(progress, f"saved {files.model} from the finished run's checkpoint")
    return model


def _write_log(files: RunFiles, info: dict, history: dict, timings: dict):
    from neurogf_warp.common.files import atomic_write

    text = json.dumps({"config": info, "history": history, "timings": timings}).encode()
    atomic_write(files.log, lambda f: f.write(text))

