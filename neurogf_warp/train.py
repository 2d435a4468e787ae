"""Training a NeuroGF for one mesh: dataset, SDF-querier pretraining, joint training, refinement.

Stages (reference §3-§5), run in order and counted as one global step sequence so that a checkpoint
can resume anywhere:

  querier      SDF querier, MSE on SDF samples                              (§3)
  joint        the whole network with the paper's losses and weights       (§4)
  refine_dist  lifting + distance head, distance losses only, eval-mode BN (not in the paper: the distance
               network is fine-tuned as inference runs it, with steps ~3x cheaper than joint ones)
  refine_sdf   SDF head alone on eval-mode (running-stat) lifting features  (§5a)
  refine_path  guidance + path head on eval-mode lifting features           (§5b)

Differences from the official scripts, on purpose:
  * a fresh batch every ``resample_every`` steps (default 1) instead of one batch reused for 200
    iterations: sampling is a few index draws on the device, and fresh data generalizes better;
  * per-step cosine decay instead of per-epoch;
  * SDF ground truth is computed once for a pool of points and batches are drawn from the pool;
  * the first path-head layer is split into xyz and guidance parts (exact, ~4x fewer FLOPs there);
  * the global distance targets use a relative L1 (the MRE itself), and the refine_dist stage above;
  * the network options of network.py: Fourier inputs (2 octaves), distance = |p - q| + head, residual
    paths; path refinement 3x longer at lr 3e-3 (``PAPER`` / ``--paper`` restores the paper's network and
    recipe; bunny and fandisk sweeps in benchmarks/RESULTS.md measured each change);
  * on CUDA: TF32, a bf16 path head, torch.compile'd losses and one CUDA graph per stage (bitwise the same
    steps as eager; the graph replays gather, forward, backward and the fused AdamW update).
"""
from __future__ import annotations

import contextlib
import copy
import dataclasses
import json
import math
import os
import signal
import sys
import tempfile
import time
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from . import losses as L
from .files import atomic_write
from .mesh import Mesh, load_mesh
from .network import NeuroGFNet, SdfQuerier, straight_lines

__all__ = ["TrainConfig", "train", "train_main", "TrainingInterrupted", "checkpoint_path", "dataset_cache_path"]

STAGES = ("querier", "joint", "refine_dist", "refine_sdf", "refine_path")
# default steps of each stage per joint step (an explicit <stage>_steps overrides; querier capped, below)
RATIOS = {"querier": 0.25, "joint": 1.0, "refine_dist": 1.0, "refine_sdf": 0.1, "refine_path": 0.3}
DIST_LOSSES = ("l1", "relative", "relative_global")
QUERIER_MAX = 4000  # default querier steps: 0.25 x joint steps, at most this (it only guides the surface term)
GRAPH_WARMUP = 3  # eager steps per stage before its CUDA graph is captured
MIN_VERTICES = 16  # below this there is nothing to hold out or sample paths from
CKPT_VERSION = 3  # 2: the refine_dist stage; 3: network options (fourier, euclid, ...) in the config
# TrainConfig values that give the paper's network and recipe (`--paper`)
PAPER = {"fourier": 0, "euclid": False, "path_residual": False, "path_width": 1, "path_window": False, "dist_loss": "l1",
         "refine_dist_steps": 0, "refine_path_lr": 1e-3, "ratios": {"refine_path": 0.1}}


@dataclass
class TrainConfig:
    D: int = 256
    # network options (network.py; all off = the paper's network). Bunny/fandisk sweeps at 6,000 joint steps
    # (benchmarks/RESULTS.md): the |p - q| term alone took bunny MRE 0.99% -> 0.70%; with 2 Fourier octaves
    # and residual paths 0.62% (fandisk 0.60% -> 0.36%), and the residual path head cut the path error.
    fourier: int = 2                  # Fourier input octaves of the lifting
    euclid: bool = True               # distance = |p - q| + head
    path_residual: bool = True        # path head outputs offsets from the straight line
    path_width: int = 1               # path head hidden widths x1 or x2
    # path offsets x sin(pi t): exact end points. Path head alone on fixed fandisk features (CPU, 2,500 steps):
    # test Chamfer 3.03e-2 -> 2.65e-2 (benchmarks/RESULTS.md); on in every GPU run since session 4 (no GPU A/B)
    path_window: bool = True
    epochs: int = 100                 # joint-training epochs ...
    iters_per_epoch: int = 200        # ... of this many steps
    querier_steps: int | None = None      # default: RATIOS x joint steps (querier at most QUERIER_MAX)
    refine_dist_steps: int | None = None
    refine_sdf_steps: int | None = None
    refine_path_steps: int | None = None
    ratios: dict = dataclasses.field(default_factory=dict)  # overrides of RATIOS, e.g. {"refine_dist": 2.0}
    loss_weights: dict = dataclasses.field(default_factory=dict)  # overrides of losses.WEIGHTS (the paper's)
    lr: float = 1e-2
    lr_min: float = 1e-4
    refine_lr: float = 1e-3
    refine_dist_lr: float = 3e-3      # measured best of 1e-3 / 3e-3 / 1e-2 (bunny, benchmarks/RESULTS.md)
    refine_path_lr: float = 3e-3      # official 1e-3; 3e-3 fit the training paths better (bunny sweep 8)
    weight_decay: float = 1e-8
    # per-step batch sizes: the official §4 values (paths doubled by their reversed copies), except the
    # paths (official 4096 + 4096) and the surface term (official 1024): on an H200 halving the paths,
    # quartering the surface points and a bf16 path head halved the step (19.2 -> 9.7 ms) and, at equal
    # wall time, took MRE from 1.02% to 0.79% (bunny) and 0.65% to 0.50% (fandisk); benchmarks/RESULTS.md
    batch_sdf: int = 30000
    batch_g: int = 65536
    batch_l1: int = 8192
    batch_l2: int = 16384
    batch_paths_g: int = 2048
    batch_paths_l: int = 2048
    batch_surf: int = 256
    batch_querier: int = 90000
    refine_batch_paths: int | None = None  # global paths per refine_path step (+ reversed); None: batch_paths_g
    refine_amp: bool = True           # bf16 path head in refine_path too (CUDA)
    resample_every: int = 1
    sdf_pool: int = 1_000_000         # SDF ground-truth points computed once
    val_every: int = 500              # joint steps between validation MREs (0: only at the end)
    log_every: int = 50
    ckpt_every_s: float = 120.0
    amp: bool = True                  # bf16 autocast for the path head only (CUDA; ignored on CPU)
    # TF32 matmuls while training on CUDA (validation and saved weights stay fp32). The official runs used
    # PyTorch 1.10 on Ampere, where TF32 was on by default for both matmul and cuDNN.
    tf32: bool = True
    # CUDA: each stage's whole step (gather, forward, backward, AdamW) is captured once as a CUDA graph and
    # replayed; only the random index draws and the learning rate are set outside. Same math as eager.
    cuda_graph: bool = True
    # distance loss: "l1" = the paper's L1; "relative" = |pred - gt| / gt on all three target sets (the MRE
    # itself); "relative_global" = relative on global targets, L1 on the local ones
    dist_loss: str = "relative_global"
    # torch.compile the loss functions on CUDA: fused BatchNorm/elementwise kernels, ~1.5x the steps per
    # second for ~25 s of compilation (falls back to eager, with a warning, where compiling fails)
    compile: bool = True
    seed: int = 0
    dataset_options: dict = dataclasses.field(default_factory=dict)

    @property
    def joint_steps(self) -> int:
        return self.epochs * self.iters_per_epoch

    def network(self) -> NeuroGFNet:
        """A fresh network of this config's width and options."""
        return NeuroGFNet(self.D, self.fourier, self.euclid, self.path_residual, self.path_width, self.path_window)

    def ratio(self, stage) -> float:
        return float({**RATIOS, **self.ratios}[stage])

    def explicit_steps(self, stage):
        return None if stage == "joint" else getattr(self, f"{stage}_steps")

    def stage_steps(self) -> dict:
        j, out = self.joint_steps, {}
        for stage in STAGES:
            n = self.explicit_steps(stage)
            if n is None:
                n = max(1 if self.ratio(stage) > 0 else 0, int(round(self.ratio(stage) * j)))
                if stage == "querier":
                    n = min(n, QUERIER_MAX)
            out[stage] = int(n)
        return out


class TrainingInterrupted(KeyboardInterrupt):
    """Raised after Ctrl-C once the checkpoint is written; ``.checkpoint`` says where."""

    def __init__(self, message: str, checkpoint: str):
        super().__init__(message)
        self.checkpoint = checkpoint


# ----------------------------------------------------------------------------------------- paths

def _stem(out_path) -> str:
    return os.path.splitext(os.fspath(out_path))[0]


def checkpoint_path(out_path) -> str:
    return os.fspath(out_path) + ".ckpt"


def dataset_cache_path(out_path) -> str:
    return _stem(out_path) + ".dataset.npz"


def log_path(out_path) -> str:
    return _stem(out_path) + ".train.json"


def _check_writable(out_path) -> str:
    """Fail before any work if the model could not be written there."""
    out = os.path.abspath(os.fspath(out_path))
    if os.path.isdir(out):
        raise IsADirectoryError(f"output path {out} is a directory; give a file name such as model.ngf")
    folder = os.path.dirname(out)
    if not os.path.isdir(folder):
        raise FileNotFoundError(f"cannot write {out}: folder {folder} does not exist")
    try:
        fd, tmp = tempfile.mkstemp(prefix=".write-test-", dir=folder)
        os.close(fd)
        os.unlink(tmp)
    except OSError as e:
        raise PermissionError(f"cannot write to {folder}: {e.strerror or e}") from e
    if os.path.exists(out) and not os.access(out, os.W_OK):
        raise PermissionError(f"output file {out} exists and is not writable")
    return out


def _check_mesh(mesh: Mesh):
    V, Fc = len(mesh.vertices), len(mesh.faces)
    if Fc == 0:
        raise ValueError("the mesh has no faces: NeuroGF needs a triangle surface")
    if V < MIN_VERTICES:
        raise ValueError(f"the mesh has only {V} vertices; training needs at least {MIN_VERTICES} "
                         "to sample sources, targets and held-out test sources")
    v = mesh.normalized_vertices[mesh.faces]
    area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1).sum()
    if not area > 1e-8:
        raise ValueError("the mesh has zero surface area (all faces degenerate); nothing to sample from")


# --------------------------------------------------------------------------------------- dataset

DATA_KEYS = ("vertices", "faces", "surface_points", "gd_global", "gd_local1", "gd_local2",
             "path_global", "path_local", "test_src", "test_dist")


def _meta(ds) -> dict:
    m = ds["meta"] if "meta" in ds else "{}"
    m = m.item() if isinstance(m, np.ndarray) else m
    m = m.decode() if isinstance(m, bytes) else m
    return json.loads(m) if isinstance(m, str) else dict(m)


def _load_checked(path, mesh: Mesh):
    from .dataset import load_dataset

    ds = load_dataset(path)
    missing = [k for k in DATA_KEYS if k not in ds]
    if missing:
        raise ValueError(f"missing arrays {missing}")
    return ds, _meta(ds).get("fingerprint")


def get_dataset(mesh: Mesh, dataset, out_path, device, progress, options: dict):
    """The training data: the given dict / file, else the cache next to the output, else a fresh build."""
    if isinstance(dataset, dict):
        return dataset
    if dataset is not None:
        ds, fp = _load_checked(dataset, mesh)
        if fp is not None and fp != mesh.fingerprint:
            raise ValueError(f"dataset {dataset} was built for a different mesh (fingerprint {fp[:12]}...)")
        return ds
    cache = dataset_cache_path(out_path)
    if os.path.exists(cache):
        try:
            ds, fp = _load_checked(cache, mesh)
            if fp == mesh.fingerprint:
                _say(progress, f"reusing dataset {cache}")
                return ds
            _say(True, f"dataset cache {cache} belongs to another mesh; rebuilding it")
        except Exception as e:  # any unreadable cache is rebuilt, never trusted
            _say(True, f"dataset cache {cache} is unreadable ({type(e).__name__}: {e}); rebuilding it")
    from .dataset import build_dataset

    _say(progress, f"building the training dataset -> {cache}")
    build_dataset(mesh, out_path=cache, seed=options.pop("seed", 0), device=_warp_device(device), progress=progress,
                  **options)
    return _load_checked(cache, mesh)[0]


def _say(on: bool, msg: str):
    if on:
        print(msg, file=sys.stderr, flush=True)


class Data:
    """Training arrays on the device, flattened so one randint draws a (source, target) pair uniformly."""

    def __init__(self, ds, device):
        t = lambda a, dt=torch.float32: torch.as_tensor(np.asarray(a), dtype=dt, device=device)
        self.gd = {k: t(ds[f"gd_{k}"]).reshape(-1, 7) for k in ("global", "local1", "local2")}
        self.pg = t(ds["path_global"]).reshape(-1, np.shape(ds["path_global"])[-2], 3)
        self.pl = t(ds["path_local"]).reshape(-1, np.shape(ds["path_local"])[-2], 3)
        self.vertices = t(ds["vertices"])
        self.test_src = torch.as_tensor(np.asarray(ds["test_src"]), dtype=torch.long, device=device)
        self.test_dist = t(ds["test_dist"])
        self.surface_points = np.asarray(ds["surface_points"], dtype=np.float32)
        for k, v in list(self.gd.items()) + [("path_global", self.pg), ("path_local", self.pl)]:
            if len(v) == 0:
                raise ValueError(f"the dataset has no {k} samples; the mesh is too small to sample from")


def make_sdf_pool(mesh: Mesh, surface_points, n: int, seed: int, device):
    """n SDF samples (§3 thirds) with ground truth, computed once: (n,3), (n,) on the device."""
    from .dataset import sample_sdf_points, sdf_truth

    rng = np.random.default_rng([seed, 3])
    pts = np.asarray(sample_sdf_points(rng, surface_points, n), dtype=np.float32)
    sdf = np.asarray(sdf_truth(mesh, pts, device=_warp_device(device)), dtype=np.float32)
    return torch.as_tensor(pts, device=device), torch.as_tensor(sdf, device=device)


def _warp_device(device) -> str:
    d = torch.device(device)
    return "cpu" if d.type == "cpu" else f"cuda:{d.index or 0}"


# --------------------------------------------------------------------------------------- network

def _bn(x, bn, training):
    if training and bn.num_batches_tracked is not None:
        bn.num_batches_tracked.add_(1)
    return F.batch_norm(x, bn.running_mean, bn.running_var, bn.weight, bn.bias, training, bn.momentum, bn.eps)


def fast_path(net: NeuroGFNet, es, et, lines):
    """Same function as ``net.path_from_embeddings`` (training or eval BN), cheaper.

    The first point-wise layer sees [xyz | g] with g constant along a path, so W·[xyz|g] is split into
    W_xyz·xyz (per point) + W_g·g (per path): the 256-wide part runs once per path, not once per point.
    Later layers run as plain matmuls on (K*M, C) instead of 1x1 convolutions with permutes.
    """
    g = net.cdw_fc(torch.cat([es, et], dim=-1))
    K, M, _ = lines.shape
    layers = list(net.spf_head)
    w0 = layers[0].conv.weight.flatten(1)
    h = (lines @ w0[:, :3].t() + (g @ w0[:, 3:].t()).unsqueeze(1)).reshape(K * M, -1)
    for i, layer in enumerate(layers):
        if i > 0:
            h = h @ layer.conv.weight.flatten(1).t()
        if layer.bn is not None:
            h = _bn(h, layer.bn, layer.bn.training)
        if layer.act is not None:
            h = torch.relu(h)
    return net.path_output(h.reshape(K, M, 3), lines)  # float32 lines: float32 points under autocast too


def _set_tf32(on: bool) -> bool:
    """Switch TF32 for matmul and cuDNN; returns the previous matmul setting."""
    was = torch.backends.cuda.matmul.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = on
    torch.backends.cudnn.allow_tf32 = on
    return was


def _cosine(step: int, n: int, hi: float, lo: float) -> float:
    return lo + 0.5 * (hi - lo) * (1.0 + math.cos(math.pi * min(step, n) / max(n, 1)))


# ---------------------------------------------------------------------------------------- stages

class Trainer:
    """Holds the networks, data and per-stage optimizer; ``step(stage)`` runs one iteration."""

    def __init__(self, cfg: TrainConfig, data: Data, sdf_pool, device):
        self.cfg, self.data, self.device = cfg, data, torch.device(device)
        torch.manual_seed(cfg.seed)  # weight init
        self.net = cfg.network().to(self.device)
        self.querier = SdfQuerier().to(self.device)
        self.sdf_pts, self.sdf_val = sdf_pool
        self.gen = torch.Generator(device=self.device)
        self.gen.manual_seed(cfg.seed + 1)
        self.steps = cfg.stage_steps()
        self.opt = None
        self.opt_stage = None
        self._idx_now = None       # index vectors of the current batch
        self._gen_at_batch = None  # generator state when the current batch was drawn (for resume)
        self._graph = None         # (CUDAGraph, static index vectors, static loss terms) of this stage
        self._eager_steps = 0
        self._compiled = {}
        self.amp = cfg.amp and self.device.type == "cuda"
        self.graphs = cfg.cuda_graph and self.device.type == "cuda"
        if cfg.dist_loss not in DIST_LOSSES:
            raise ValueError(f"dist_loss must be one of {DIST_LOSSES}, got {cfg.dist_loss!r}")
        if not isinstance(cfg.ratios, dict) or set(cfg.ratios) - set(STAGES):
            raise ValueError(f"ratios must map stage names {STAGES} to step ratios, e.g. {{\"refine_dist\": 0}}; "
                             f"got {cfg.ratios!r}")
        unknown = set(cfg.loss_weights) - set(L.WEIGHTS)
        if unknown:
            raise ValueError(f"loss_weights: unknown terms {sorted(unknown)}; known: {sorted(L.WEIGHTS)}")
        self.weights = {**L.WEIGHTS, **cfg.loss_weights}

    # -- sampling (all on the device, no host sync). A step draws index vectors (``draw``), then gathers
    # its batch from the device arrays (``gather``); with CUDA graphs only the draw runs outside the graph.
    def _idx(self, n, k):
        return torch.randint(0, n, (k,), device=self.device, generator=self.gen)

    def _draws(self, stage):
        """(name, pool size, count) of the index vectors one step of ``stage`` uses."""
        c, d = self.cfg, self.data
        sdf = lambda k: ("sdf", len(self.sdf_pts), min(k, len(self.sdf_pts)))
        if stage in ("querier", "refine_sdf"):
            return [sdf(c.batch_querier)]
        if stage == "refine_path":
            return [("pg", len(d.pg), c.refine_batch_paths or c.batch_paths_g)]
        dist = [(k, len(d.gd[k]), n) for k, n in (("global", c.batch_g), ("local1", c.batch_l1), ("local2", c.batch_l2))]
        if stage == "refine_dist":
            return dist
        return [sdf(c.batch_sdf)] + dist + [("pg", len(d.pg), c.batch_paths_g), ("pl", len(d.pl), c.batch_paths_l)]

    def draw(self, stage):
        return {k: self._idx(n, m) for k, n, m in self._draws(stage)}

    def gather(self, idx):
        d, b = self.data, {}
        for k, i in idx.items():
            if k == "sdf":
                b[k] = (self.sdf_pts[i], self.sdf_val[i])
            elif k in ("pg", "pl"):
                b[k] = (d.pg if k == "pg" else d.pl)[i]
            else:
                rows = d.gd[k][i]
                b[k] = (rows[:, :3], rows[:, 3:6], rows[:, 6])
        return b

    def _optimizer(self, stage):
        if self.opt_stage == stage:
            return self.opt
        c = self.cfg
        params = {"querier": lambda: self.querier.parameters(),
                  "joint": lambda: self.net.parameters(),
                  "refine_dist": lambda: list(self.net.lifting.parameters()) + list(self.net.gdf_head.parameters()),
                  "refine_sdf": lambda: self.net.sdf_head.parameters(),
                  "refine_path": lambda: list(self.net.cdw_fc.parameters()) + list(self.net.spf_head.parameters()),
                  }[stage]()
        cuda = self.device.type == "cuda"
        # fused: one kernel for the whole update on CUDA. Under CUDA graphs the learning rate is a device
        # tensor (filled before each replay) and the step counter lives on the device (capturable).
        lr = torch.tensor(c.lr, device=self.device) if self.graphs else c.lr
        self.opt = torch.optim.AdamW(params, lr=lr, weight_decay=c.weight_decay, fused=cuda,
                                     capturable=self.graphs)
        self.opt_stage = stage
        self._idx_now = None
        self._graph = None  # the previous stage's graph and its memory pool go
        self._eager_steps = 0
        return self.opt

    def set_modes(self, stage):
        """Train/eval flags and frozen parts for a stage."""
        self.net.train(stage == "joint")
        self.querier.train(stage == "querier")
        self.querier.requires_grad_(stage == "querier")
        self.net.requires_grad_(stage == "joint")
        if stage == "refine_dist":  # eval-mode BN: a fixed affine map, exactly what inference computes
            self.net.lifting.requires_grad_(True)
            self.net.gdf_head.requires_grad_(True)
        if stage == "refine_sdf":
            self.net.sdf_head.train().requires_grad_(True)
        if stage == "refine_path":
            for m in (self.net.cdw_fc, self.net.spf_head):
                m.train().requires_grad_(True)

    def lr_at(self, stage, step):
        c, n = self.cfg, self.steps[stage]
        hi = {"querier": c.lr, "joint": c.lr, "refine_dist": c.refine_dist_lr,
              "refine_path": c.refine_path_lr}.get(stage, c.refine_lr)
        return _cosine(step, n, hi, c.lr_min)

    def _set_lr(self, lr):
        for g in self.opt.param_groups:
            if isinstance(g["lr"], torch.Tensor):
                g["lr"].fill_(lr)
            else:
                g["lr"] = lr

    def _update(self, stage, idx):
        """Gather, forward, backward, optimizer step: everything a CUDA graph captures."""
        terms = self._loss_fn(stage)(self.gather(idx))
        loss = L.weighted_sum(terms, self.weights) if stage in ("joint", "refine_dist") else sum(terms.values())
        loss.backward()
        self.opt.step()
        return terms

    def _loss_fn(self, stage):
        fn = getattr(self, f"_loss_{stage}")
        if not (self.cfg.compile and self.device.type == "cuda") or self._compiled.get(stage) is False:
            return fn
        if stage not in self._compiled:
            compiled = torch.compile(fn, dynamic=False)

            def first_call(b, compiled=compiled):  # compiles; on failure, eager from now on
                try:
                    out = compiled(b)
                except Exception as e:  # noqa: BLE001 - no Triton / no C compiler / unsupported op
                    print(f"warning: torch.compile failed for the {stage} stage ({type(e).__name__}: {e}); "
                          "running eagerly (set compile=False to skip the attempt)", file=sys.stderr)
                    self._compiled[stage] = False
                    return fn(b)
                self._compiled[stage] = compiled
                return out

            return first_call
        return self._compiled[stage]

    def step(self, stage, step):
        self._optimizer(stage)
        self._set_lr(self.lr_at(stage, step))
        if self._idx_now is None or step % self.cfg.resample_every == 0:
            if step % self.cfg.resample_every == 0:
                self._gen_at_batch = self.gen.get_state()
            elif self._gen_at_batch is not None:  # resumed mid-reuse: redraw the batch the run was using
                now = self.gen.get_state()
                self.gen.set_state(self._gen_at_batch)
                self._idx_now = self.draw(stage)
                self.gen.set_state(now)
            if self._idx_now is None or step % self.cfg.resample_every == 0:
                self._idx_now = self.draw(stage)
        if not self.graphs:
            self.opt.zero_grad(set_to_none=True)
            return self._update(stage, self._idx_now)
        if self._graph is None and self._eager_steps >= GRAPH_WARMUP:
            self._graph = self._capture(stage)
        if self._graph is not None:
            graph, static_idx, terms = self._graph
            for k, v in self._idx_now.items():
                static_idx[k].copy_(v)
            graph.replay()
            return terms
        # the first steps of a stage run eagerly on a side stream (allocator and cuBLAS warm-up before capture)
        side = torch.cuda.Stream(self.device)
        side.wait_stream(torch.cuda.current_stream(self.device))
        with torch.cuda.stream(side):
            self.opt.zero_grad(set_to_none=True)
            terms = self._update(stage, self._idx_now)
        torch.cuda.current_stream(self.device).wait_stream(side)
        self._eager_steps += 1
        return terms

    def _capture(self, stage):
        static_idx = {k: v.clone() for k, v in self._idx_now.items()}
        self.opt.zero_grad(set_to_none=True)  # gradients are then allocated inside the graph's pool
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            terms = self._update(stage, static_idx)
        return graph, static_idx, terms

    # -- losses per stage
    def _loss_querier(self, b):
        x, y = b["sdf"]
        return {"querier_mse": F.mse_loss(self.querier(x), y)}

    def _paths(self, es, et, gt, amp=True):
        """Predicted paths for gt and for its reversed copy (swapped endpoints): (2K, M, 3) each."""
        p, q = gt[:, 0], gt[:, -1]
        m = gt.shape[1]
        lines = torch.cat([straight_lines(p, q, m), straight_lines(q, p, m)])
        ctx = torch.autocast("cuda", dtype=torch.bfloat16, cache_enabled=False) if self.amp and amp \
            else contextlib.nullcontext()
        with ctx:
            pred = fast_path(self.net, torch.cat([es, et]), torch.cat([et, es]), lines)
        return pred.float(), torch.cat([gt, gt.flip(1)])

    def _loss_joint(self, b):
        sp, sv = b["sdf"]
        pg, pl = b["pg"], b["pl"]
        parts = [sp]
        for key in ("global", "local1", "local2"):
            parts += [b[key][0], b[key][1]]
        parts += [pg[:, 0], pg[:, -1], pl[:, 0], pl[:, -1]]
        sizes = [len(x) for x in parts]
        e = self.net.embed(torch.cat(parts)).split(sizes)  # one lifting call: shared BN statistics
        t = {"sdf": L.l1(self.net.sdf_from_embeddings(e[0]), sv)}
        t.update(self._distance_terms(b, e[1:7]))
        pred_g, gt_g = self._paths(e[7], e[8], pg)
        pred_l, gt_l = self._paths(e[9], e[10], pl)
        t["path_g"] = L.l1(pred_g, gt_g)
        t["path_l"] = L.l1(pred_l, gt_l)
        t["len"] = L.length_loss(pred_g, gt_g)
        if self.cfg.batch_surf > 0:
            t["surf"] = L.surface_loss(self.querier, pred_g[: self.cfg.batch_surf])
        return t

    def _distance_terms(self, b, e):
        """The three distance losses from the (source, target) embeddings of global, local1, local2."""
        # One distance-head call for all three target sets: with three calls the BN running statistics
        # would follow the last (local) batch and eval-mode distances would be far off the trained ones.
        keys = ("global", "local1", "local2")
        d = self.net.distance_from_embeddings(torch.cat(e[0::2]), torch.cat(e[1::2]),
                                              torch.cat([b[k][0] for k in keys]), torch.cat([b[k][1] for k in keys]))
        d = d.split([len(x) for x in e[0::2]])
        t = {}
        for i, key in enumerate(("global", "local1", "local2")):
            name = {"global": "dist_g", "local1": "dist_l1", "local2": "dist_l2"}[key]
            rel = self.cfg.dist_loss == "relative" or (self.cfg.dist_loss == "relative_global" and key == "global")
            t[name] = L.relative_l1(d[i], b[key][2]) if rel else L.l1(d[i], b[key][2])
        return t

    def _loss_refine_dist(self, b):
        parts = [x for key in ("global", "local1", "local2") for x in b[key][:2]]
        e = self.net.embed(torch.cat(parts)).split([len(x) for x in parts])
        return self._distance_terms(b, e)

    def _eval_features(self, x):
        with torch.no_grad():
            self.net.lifting.eval()
            return self.net.embed(x)

    def _loss_refine_sdf(self, b):
        x, y = b["sdf"]
        return {"sdf": L.l1(self.net.sdf_from_embeddings(self._eval_features(x)), y)}

    def _loss_refine_path(self, b):
        pg = b["pg"]
        e = self._eval_features(torch.cat([pg[:, 0], pg[:, -1]]))
        pred, gt = self._paths(e[: len(pg)], e[len(pg):], pg, amp=self.cfg.refine_amp)
        return {"path_g": L.l1(pred, gt)}

    # -- validation: MRE on held-out sources, eval-mode BN (what inference sees)
    @torch.no_grad()
    def validate(self) -> float:
        was = self.net.training
        self.net.eval()
        tf32 = _set_tf32(False)
        d = self.data
        ev = self.net.embed(d.vertices)
        errs = []
        for i, s in enumerate(d.test_src):
            pred = self.net.distance_from_embeddings(ev[s].expand_as(ev), ev, d.vertices[s].expand_as(d.vertices),
                                                     d.vertices)
            gt = d.test_dist[i]
            ok = torch.isfinite(gt) & (gt > 0)
            errs.append(((pred[ok] - gt[ok]).abs() / gt[ok]).mean())
        self.net.train(was)
        _set_tf32(tf32)
        return float(torch.stack(errs).mean()) if errs else float("nan")

    # -- checkpoint state
    def state(self, stage_i, step, history, elapsed, fingerprint):
        return {
            "version": CKPT_VERSION, "config": dataclasses.asdict(self.cfg), "fingerprint": fingerprint,
            "stage": stage_i, "step": step, "steps": self.steps,
            "net": self.net.state_dict(), "querier": self.querier.state_dict(),
            "opt": self._opt_state(), "opt_stage": self.opt_stage,
            "gen": self.gen.get_state(), "gen_at_batch": self._gen_at_batch, "history": history,
            "elapsed": elapsed,
        }

    def _opt_state(self):
        if self.opt is None:
            return None
        sd = self.opt.state_dict()
        for g in sd["param_groups"]:  # a graph run's device-tensor lr is stored as a number
            g["lr"] = float(g["lr"])
        return sd

    def load_state(self, ck):
        self.net.load_state_dict(ck["net"])
        self.querier.load_state_dict(ck["querier"])
        self.steps = dict(ck["steps"])
        self.gen.set_state(ck["gen"].cpu())
        g = ck.get("gen_at_batch")
        self._gen_at_batch = g.cpu() if g is not None else None
        if ck["opt"] is not None and ck["opt_stage"] is not None:
            self.set_modes(ck["opt_stage"])
            opt = self._optimizer(ck["opt_stage"])
            opt.load_state_dict(ck["opt"])
            if self.graphs:  # keep the lr a device tensor, or a captured graph would bake in one value
                for g in opt.param_groups:
                    g["lr"] = torch.tensor(float(g["lr"]), device=self.device)


# ------------------------------------------------------------------------------------ checkpoint

def save_checkpoint(state: dict, path: str) -> bool:
    """Atomic write (tmp + os.replace); on failure the previous checkpoint stays and we go on."""
    try:
        atomic_write(path, lambda f: torch.save(state, f))
        return True
    except Exception as e:
        print(f"warning: could not save checkpoint {path} ({e}); the previous one is kept", file=sys.stderr)
        return False


def load_checkpoint(path: str) -> dict:
    try:
        ck = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise ValueError(f"checkpoint {path} is unreadable ({e}); delete it to start over") from e
    if not isinstance(ck, dict) or "version" not in ck:
        raise ValueError(f"{path} is not a neurogf-warp training checkpoint")
    if ck["version"] != CKPT_VERSION:
        raise ValueError(f"{path} is a training checkpoint of format {ck['version']}; this version resumes format "
                         f"{CKPT_VERSION} only (its stages or network differ). Delete it, or drop --resume, to start over")
    return ck


def _save_model(trainer: Trainer, mesh: Mesh, path: str, info: dict):
    """The final model file. One place to switch formats."""
    from .model import Model
    from .model_io import save

    net = copy.deepcopy(trainer.net).cpu().eval()
    querier = copy.deepcopy(trainer.querier).cpu().eval()
    model = Model(net=net, querier=querier, mesh=mesh, center=mesh.center, scale=mesh.scale, config=info)
    save(model, path)
    return model


# ------------------------------------------------------------------------------------ budgeting

def _sync(device):
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def calibrate(trainer: Trainer, n: int = 6) -> dict:
    """Seconds per step of each stage, timed on the trainer itself; its state is restored afterwards.

    (In place rather than on a copy: compiled loss functions are then compiled once, for the real run.)
    """
    saved = (copy.deepcopy(trainer.net.state_dict()), copy.deepcopy(trainer.querier.state_dict()),
             trainer.gen.get_state(), trainer._gen_at_batch)
    warm = 2 + (GRAPH_WARMUP + 1 if trainer.graphs else 0)  # and the capture, when graphs are on
    out = {}
    try:
        for stage in STAGES:
            trainer.set_modes(stage)
            for i in range(n + warm):
                if i == warm:
                    _sync(trainer.device)
                    t0 = time.perf_counter()
                trainer.step(stage, 0)
            _sync(trainer.device)
            out[stage] = (time.perf_counter() - t0) / n
    finally:
        trainer.net.load_state_dict(saved[0])
        trainer.querier.load_state_dict(saved[1])
        trainer.gen.set_state(saved[2])
        trainer._gen_at_batch = saved[3]
        trainer.opt, trainer.opt_stage, trainer._idx_now, trainer._graph = None, None, None, None
    return out


def fit_budget(cfg: TrainConfig, per_step: dict, seconds: float) -> TrainConfig:
    """Scale the joint steps (other stages keep their ratios) so all stages fit ``seconds``."""
    fixed = sum(per_step[s] * cfg.explicit_steps(s) for s in STAGES if cfg.explicit_steps(s) is not None)
    scaled = [s for s in STAGES if cfg.explicit_steps(s) is None and s != "querier"]
    per_joint = sum(per_step[s] * cfg.ratio(s) for s in scaled)
    avail = 0.95 * seconds - fixed  # 5% slack for the loop itself (logging, validation, checkpoints)
    joint = avail / per_joint
    if cfg.querier_steps is None:  # ratio x joint querier steps, capped at QUERIER_MAX
        joint = avail / (per_joint + cfg.ratio("querier") * per_step["querier"])
        if cfg.ratio("querier") * joint > QUERIER_MAX:
            joint = (avail - per_step["querier"] * QUERIER_MAX) / per_joint
    joint = max(10, int(joint))
    epochs = max(1, joint // cfg.iters_per_epoch)
    if epochs * cfg.iters_per_epoch > joint:  # fewer steps than one epoch: shrink the epoch
        return dataclasses.replace(cfg, epochs=1, iters_per_epoch=joint)
    return dataclasses.replace(cfg, epochs=epochs)


# -------------------------------------------------------------------------------------- training

def train(mesh, out_path, *, D: int = 256, epochs: int | None = None, iters_per_epoch: int | None = None,
          device=None, seed: int = 0, dataset=None, resume: bool = False, progress: bool = True,
          budget_seconds: float | None = None, callback=None, **options):
    """Train a NeuroGF for ``mesh`` and write it to ``out_path``; returns the saved Model.

    dataset: None (cached next to the output, else built), a dataset .npz path, or a dict of its arrays.
    budget_seconds: scale the number of steps so that everything after the dataset (SDF pool, timing and
      compiling, all stages, saving) takes about this long; the step counts are fixed in the checkpoint.
    callback(stage, step, terms): called after every step (e.g. to stop early by raising KeyboardInterrupt).
    options: any other TrainConfig field (batch sizes, lr, val_every, ...).
    A checkpoint ``<out_path>.ckpt`` is written every ``ckpt_every_s`` seconds, at stage ends and on Ctrl-C.
    """
    out_path = _check_writable(out_path)
    mesh = load_mesh(mesh)
    _check_mesh(mesh)
    device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    if device.type == "cuda" and device.index is None:  # generators and tensors must agree on the index
        device = torch.device("cuda", torch.cuda.current_device())
    ckpt_file = checkpoint_path(out_path)

    ck = None
    if resume:
        if os.path.exists(ckpt_file):
            ck = load_checkpoint(ckpt_file)
            if ck["fingerprint"] != mesh.fingerprint:
                raise ValueError(f"checkpoint {ckpt_file} belongs to a different mesh; remove it or drop --resume")
        else:
            _say(True, f"no checkpoint at {ckpt_file}; starting from scratch")
    if ck is not None:
        cfg = TrainConfig(**ck["config"])
    else:
        kw = dict(D=D, seed=seed, **options)
        if epochs is not None:
            kw["epochs"] = epochs
        if iters_per_epoch is not None:
            kw["iters_per_epoch"] = iters_per_epoch
        cfg = TrainConfig(**kw)
        cfg.network()  # validates D and the options before the expensive steps

    t_start = time.perf_counter()
    ds = get_dataset(mesh, dataset, out_path, device, progress, dict(cfg.dataset_options, seed=cfg.seed))
    t_ready = time.perf_counter()
    data = Data(ds, device)
    pool = make_sdf_pool(mesh, data.surface_points, cfg.sdf_pool, cfg.seed, device)
    trainer = Trainer(cfg, data, pool, device)
    prep_s = time.perf_counter() - t_start

    if ck is not None:
        trainer.load_state(ck)
        stage_i, step, history, elapsed = ck["stage"], ck["step"], ck["history"], ck["elapsed"]
        _say(progress, f"resuming from {ckpt_file}: stage {STAGES[stage_i]}, step {step}")
    else:
        if budget_seconds is not None:
            tf32 = _set_tf32(cfg.tf32) if device.type == "cuda" else None  # time what the run will do
            try:
                per = calibrate(trainer, n=20 if trainer.graphs else 6)
            finally:
                if tf32 is not None:
                    _set_tf32(tf32)
            # what set-up and timing (incl. compilation) took comes out of the budget; 2 s for the save
            cfg = fit_budget(cfg, per, budget_seconds - (time.perf_counter() - t_ready) - 2.0)
            trainer.cfg = cfg
            trainer.steps = cfg.stage_steps()
            _say(progress, "budget {:.0f}s: s/step {}; steps {}".format(
                budget_seconds, {k: round(v, 4) for k, v in per.items()}, trainer.steps))
        stage_i, step, history, elapsed = 0, 0, {"loss": [], "val": [], "prep_s": prep_s}, 0.0

    info = lambda: dict(dataclasses.asdict(cfg), steps=trainer.steps, train_seconds=round(elapsed, 2))
    run = _Runner(trainer, mesh, ckpt_file, progress, callback)
    try:
        stage_i, step, history, elapsed = run(stage_i, step, history, elapsed)
    except TrainingInterrupted:
        raise
    history["prep_s"] = prep_s
    model = _save_model(trainer, mesh, out_path, info())
    with open(log_path(out_path), "w") as f:
        json.dump({"config": info(), "history": history}, f)
    _say(progress, f"saved {out_path} ({elapsed:.0f}s of training)")
    return model


class _Runner:
    """The step loop: progress bar, logging, validation, periodic checkpoints, clean Ctrl-C."""

    def __init__(self, trainer, mesh, ckpt_file, progress, callback):
        self.t, self.mesh, self.ckpt_file, self.progress, self.callback = trainer, mesh, ckpt_file, progress, callback
        self.stop = False

    def _on_sigint(self, signum, frame):
        if self.stop:  # second Ctrl-C: give up at once
            raise KeyboardInterrupt
        self.stop = True

    def __call__(self, stage_i, step, history, elapsed):
        t, cfg = self.t, self.t.cfg
        total = sum(t.steps.values())
        done = sum(t.steps[s] for s in STAGES[:stage_i]) + step
        bar = None
        if self.progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=total, initial=done, unit="step", dynamic_ncols=True, file=sys.stderr)
        old = None
        try:
            old = signal.signal(signal.SIGINT, self._on_sigint)
        except ValueError:  # not the main thread: Ctrl-C arrives as KeyboardInterrupt instead
            pass
        tf32 = _set_tf32(cfg.tf32 and t.device.type == "cuda") if t.device.type == "cuda" else None
        save = lambda i, s: save_checkpoint(t.state(i, s, history, elapsed, self.mesh.fingerprint), self.ckpt_file)
        last_save = time.perf_counter()
        try:
            while stage_i < len(STAGES):
                stage = STAGES[stage_i]
                n = t.steps[stage]
                t.set_modes(stage)
                acc, acc_n = None, 0
                t0 = time.perf_counter()
                while step < n:
                    interrupted = False
                    try:
                        terms = t.step(stage, step)
                        step += 1
                        vals = torch.stack([v.detach().float() for v in terms.values()])
                        acc = vals if acc is None else acc + vals
                        acc_n += 1
                        if self.callback is not None:
                            self.callback(stage, step, terms)
                    except KeyboardInterrupt:
                        interrupted = True
                    if bar is not None:
                        bar.update(1)
                    if acc_n and (step % cfg.log_every == 0 or step == n):
                        row = dict(zip(terms, (acc / acc_n).tolist()))
                        total_loss = float(L.weighted_sum({k: torch.tensor(v) for k, v in row.items()})) \
                            if stage in ("joint", "refine_dist") else sum(row.values())
                        history["loss"].append({"stage": stage, "step": step, "lr": t.lr_at(stage, step - 1),
                                                "loss": total_loss, **row})
                        acc, acc_n = None, 0
                        if bar is not None:
                            bar.set_postfix_str(f"{stage} loss {total_loss:.4g} lr {t.lr_at(stage, step - 1):.2e}"
                                                + (f" valMRE {history['val'][-1]['mre']:.3%}" if history["val"] else ""))
                    if stage in ("joint", "refine_dist") and ((cfg.val_every and step % cfg.val_every == 0)
                                                              or step == n):
                        history["val"].append({"stage": stage, "step": step, "mre": t.validate()})
                    if interrupted or self.stop:
                        elapsed += time.perf_counter() - t0
                        t0 = time.perf_counter()
                        save(stage_i, step)
                        raise TrainingInterrupted(
                            f"interrupted at {stage} step {step}/{n}; checkpoint saved to {self.ckpt_file}. "
                            "Run again with --resume to continue.", self.ckpt_file)
                    if time.perf_counter() - last_save > cfg.ckpt_every_s:
                        elapsed += time.perf_counter() - t0
                        t0 = time.perf_counter()
                        save(stage_i, step)
                        last_save = time.perf_counter()
                elapsed += time.perf_counter() - t0
                stage_i, step = stage_i + 1, 0
                save(stage_i, step)
                last_save = time.perf_counter()
        finally:
            if tf32 is not None:
                _set_tf32(tf32)
            if old is not None:
                signal.signal(signal.SIGINT, old)
            if bar is not None:
                bar.close()
        return stage_i, step, history, elapsed


# ------------------------------------------------------------------------------------------- CLI

def _parser():
    import argparse

    p = argparse.ArgumentParser(prog="neurogf-warp train", description="Train a NeuroGF for one mesh.")
    p.add_argument("mesh", help="triangle mesh file (.obj, .ply, ...)")
    p.add_argument("-o", "--output", required=True, help="model file to write (e.g. model.ngf)")
    p.add_argument("--resume", action="store_true", help="continue from <output>.ckpt")
    p.add_argument("--D", type=int, default=256, choices=(64, 128, 256, 512), help="embedding width")
    p.add_argument("--device", default=None, help="torch device, e.g. cuda:0 or cpu (default: cuda if present)")
    p.add_argument("--epochs", type=int, default=None)
    p.add_argument("--iters-per-epoch", type=int, default=None)
    p.add_argument("--budget-seconds", type=float, default=None, help="scale the steps to fit this training time")
    p.add_argument("--dataset", default=None, help="use this dataset .npz instead of building/caching one")
    p.add_argument("--n-sources", type=int, default=None, help="training sources for the dataset build")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--lr", type=float, default=None)
    p.add_argument("--no-amp", dest="amp", action="store_false", help="float32 path head (default: bf16 on CUDA)")
    p.add_argument("--no-compile", dest="compile", action="store_false",
                   help="skip torch.compile (default on CUDA: ~1.5x faster steps after ~25 s of compiling)")
    p.add_argument("--paper", action="store_true",
                   help="the paper's network and recipe: no Fourier inputs, |p - q| term or residual paths, L1 "
                        "distance loss, no refine_dist stage, path refinement as published (our defaults measured better)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="any other TrainConfig field, e.g. --set batch_g=131072 --set val_every=1000")
    p.add_argument("--no-progress", action="store_true")
    return p


def parse_overrides(items, fields=None, flag: str = "--set") -> dict:
    """['batch_g=4096', 'amp=true'] -> {'batch_g': 4096, 'amp': True}; keys not in ``fields`` (default: the
    TrainConfig fields) are an error."""
    fields = {f.name for f in dataclasses.fields(TrainConfig)} if fields is None else set(fields)
    out = {}
    for item in items:
        key, sep, val = item.partition("=")
        key = key.strip().replace("-", "_")
        if not sep or key not in fields:
            raise ValueError(f"{flag} {item!r}: expected KEY=VALUE with KEY one of {sorted(fields)}")
        try:
            out[key] = json.loads(val)
        except json.JSONDecodeError:
            out[key] = val
    return out


def train_main(argv=None) -> int:
    a = _parser().parse_args(argv)
    try:
        opts = parse_overrides(a.set)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if a.lr is not None:
        opts["lr"] = a.lr
    if not a.amp:
        opts["amp"] = False
    if not a.compile:
        opts["compile"] = False
    if a.paper:
        for k, v in PAPER.items():
            opts.setdefault(k, v)
    if a.n_sources is not None:
        opts["dataset_options"] = dict(opts.get("dataset_options") or {}, n_sources=a.n_sources)
    try:
        train(a.mesh, a.output, D=a.D, epochs=a.epochs, iters_per_epoch=a.iters_per_epoch, device=a.device,
              seed=a.seed, dataset=a.dataset, resume=a.resume, progress=not a.no_progress,
              budget_seconds=a.budget_seconds, **opts)
    except TrainingInterrupted as e:
        print(str(e), file=sys.stderr)
        return 130
    except (ValueError, OSError, TypeError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0
