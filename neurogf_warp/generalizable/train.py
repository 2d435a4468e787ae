"""Train a generalizable NeuroGF network on a folder of meshes, on one CPU/GPU or many ranks (torch.distributed).

    python -m neurogf_warp.generalizable.train FOLDER -o model.pt --budget-seconds 600
    torchrun --nproc_per_node 2 -m neurogf_warp.generalizable.train FOLDER -o model.pt --budget-seconds 600

Data, as the authors': per shape, ``sources`` (256) source vertices x ``targets`` (512) target vertices
with ground-truth geodesic distances from the project's solver (``ngf.geodesic_distances``), plus a
``cloud_points`` (2,048) point cloud sampled on the surface, all in the shape's unit-sphere frame (bounding-box
centre, largest vertex norm 1). A training step draws ``shapes_per_step`` shapes and, per shape,
``step_sources`` x ``step_targets`` of its pairs; the loss is the L1 error of the predicted ratio
geodesic / Euclidean (the authors' target). AdamW, lr 1e-2 cosine to 1e-4 over ``steps``, weight decay 1e-8.
A time budget (``budget_seconds``) covers the whole call, from the call (Python) or from the process start (the
command line; under torchrun the launcher's start, and rank 0's deadline on every rank): the ground truth gets at
most a third of it (fewer shapes, and fewer sources of the last one, when it runs short; said in the output), the
steps the rest less a second for the model file. A budgeted run's first step draws one shape and is timed, and the
later steps draw as many shapes as let about 20 steps fit (``BudgetSteps``); no step starts that would end past the
deadline. The cosine runs over whichever ends first, the steps or the training's time (progress =
max(step / steps, elapsed / training time)), so a budgeted run always ends at the low learning rate.
``rotate`` (off by default) turns each drawn shape by a random rotation and re-normalizes it (bounding-box
centre and largest vertex norm of the turned vertices, as conditioning would); the ratio target is unchanged.

Split: if FOLDER has ``train/`` and ``test/`` subfolders (as ``shapes.write_collection`` writes), those;
otherwise every 10th mesh file (sorted by path) is held out for validation. Validation MRE = mean over held-out
pairs of |d - d_gt| / d_gt with d = max(ratio, 1) |s - t| (what ``Conditioned.distance`` returns), eval mode.

Ground truth is cached per shape under ``--cache`` (default ``<output>.gt/``), keyed by the file's content and
the data settings, written atomically: an interrupted run recomputes only what is missing. Under torchrun the
shapes are sharded over the ranks (``common/shards.py``: largest first, by file size) both for ground truth and for training
(data-parallel DDP: each rank draws its batch from its own shard; gradients are averaged). Rank 0 writes the
checkpoint (atomically: a temporary file, then a rename) every ``checkpoint_seconds`` and at the end; ``--resume``
continues from it with any world size (the model and optimizer state are global; the shard is recomputed).

The output file (``torch.load(..., weights_only=True)``-safe dict) holds ``state_dict`` plus what it was trained
on (``trained_on``: folder, files, counts, families if a shapes manifest is present, ground-truth settings), the
config, step, elapsed time, loss and validation history; ``generalizable.load`` reads it.
"""
from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import os
import sys
import time
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import torch

from neurogf_warp.common.checks import finite_arg
from neurogf_warp.common.shards import balanced_shard, file_sizes
from neurogf_warp.generalizable.network import GenNeuroGF

MESH_EXTENSIONS = (".obj", ".ply", ".stl", ".off")
FORMAT = "neurogf-generalizable"
# Under DDP rank 0's clock decides when a budget ends and where the schedule is. Sharing it is a host sync (the
# broadcast's .item() waits for the GPU), which took the host's batch preparation out of the GPU's shadow: two
# H200s trained 1.70x the shapes/s of one with a broadcast every step (docs/performance.md).
# So it is shared every SYNC_EVERY steps; in between, every rank keeps the last shared fraction (the same lr).
SYNC_EVERY = 8
# Under a budget: the ground truth gets at most this share of it, as the per-mesh dataset (training/api.py), each
# shape's sources solved in batches that fit the time left (at least GT_MIN_SOURCES sources of one shape per rank,
# without which there is nothing to train on); the rest trains, less END_RESERVE_S for the model file and the exit.
GT_SHARE = 1 / 3
GT_MIN_SOURCES = 8
END_RESERVE_S = 1.0
# A budgeted run's first step draws one shape per rank and times it; the later steps draw as many shapes (at most
# shapes_per_step) as let at least BUDGET_STEPS steps fit in the time left (a 16-shape step took 55 s on a 2-core
# CPU: a 60 s budget would otherwise end after its first step, wherever that ends).
BUDGET_STEPS = 20


def check_config(cfg: "GenTrainConfig") -> None:
    """InputError, before any work, for a count below its minimum (sources=0 failed inside the ground truth) or a
    rate or period that is not a finite positive number."""
    from neurogf_warp.common.checks import integer, number

    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        if f.name == "budget_seconds" or isinstance(f.default, bool):
            continue
        if isinstance(f.default, int):  # 0 validations (val_every, val_shapes) means none; a seed may be 0
            integer(f.name, v, minimum=0 if f.name in ("seed", "val_every", "val_shapes") else 1)
        elif isinstance(f.default, float):
            zero_ok = f.name in ("weight_decay", "lr_min")
            number(f.name, v, minimum=0.0 if zero_ok else None, above=None if zero_ok else 0)


@dataclass
class GenTrainConfig:
    """Settings of :func:`train_generalizable` (defaults: the authors' data sizes, a smaller batch)."""

    sources: int = 256  # ground truth: source vertices per shape
    targets: int = 512  # ground truth: target vertices per source
    cloud_points: int = 2048  # points sampled on each shape (the encoder's input)
    shapes_per_step: int = 16  # shapes per step and rank (the authors used 64 on one GPU)
    step_sources: int = 32  # sources per shape and step
    step_targets: int = 64  # targets per source and step
    steps: int = 20000  # cosine schedule length (and the last step)
    lr: float = 1e-2
    lr_min: float = 1e-4
    weight_decay: float = 1e-8
    budget_seconds: float | None = None  # the whole call, ground truth included (command line: the process)
    rotate: bool = False  # augmentation: a random rotation of every drawn shape (re-normalized)
    checkpoint_seconds: float = 120.0
    val_every: int = 200  # steps between validations
    val_shapes: int = 32  # held-out shapes used per validation (the first ones)
    val_sources: int = 16
    val_targets: int = 64
    seed: int = 0
    log_every: int = 20


# ---- files and split ------------------------------------------------------------------------------------------

def mesh_files(folder) -> tuple[list[Path], list[Path]]:
    """(training files, validation files) of a collection folder (see the module docstring for the split)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"{folder} is not a folder; give a folder of mesh files ({', '.join(MESH_EXTENSIONS)})")
    find = lambda d: sorted(p for p in d.rglob("*") if p.suffix.lower() in MESH_EXTENSIONS
                            and ".tmp" not in p.name)
    if (folder / "train").is_dir() and (folder / "test").is_dir():
        train, val = find(folder / "train"), find(folder / "test")
    else:
        allf = find(folder)
        val = allf[9::10]
        train = [p for p in allf if p not in set(val)]
    if not train:
        raise ValueError(f"no mesh files ({', '.join(MESH_EXTENSIONS)}) for training under {folder}")
    return train, val


def _file_key(path: Path, cfg: GenTrainConfig) -> str:
    h = hashlib.sha256(path.read_bytes())
    h.update(json.dumps([cfg.sources, cfg.targets, cfg.cloud_points, cfg.seed]).encode())
    return h.hexdigest()[:16]


def shape_ground_truth(path, cfg: GenTrainConfig, device=None, deadline: float | None = None) -> dict:
    """Ground truth of one mesh file (unit-sphere frame): ``cloud`` (P, 3) f32, ``verts`` (V, 3) f32 (internal
    vertices), ``src`` (S,) i32, ``tgt`` (S, T) i32 vertex indices, ``dist`` (S, T) f32 geodesic distances,
    ``complete`` (whether every source asked for was solved).

    Sources: ``cfg.sources`` distinct vertices (all if fewer), random with a seed from (cfg.seed, file name);
    targets: per source, ``cfg.targets`` vertices of finite, non-zero distance (without replacement when enough).
    ``deadline`` (a ``time.perf_counter()`` value): the sources are solved in batches, the first of
    ``GT_MIN_SOURCES``, the next sized from its time to end by the deadline; the sources solved by then are kept
    (the first ones of the same random order, so a shorter run's sources are a prefix of a longer run's).
    """
    import neurogf_warp as ngf

    from neurogf_warp.generalizable.model import sample_surface

    path = Path(path)
    mesh = ngf.load_mesh(str(path))
    nv = len(mesh.internal_vertices)
    rng = np.random.default_rng([cfg.seed, int(hashlib.sha256(path.name.encode()).hexdigest()[:8], 16)])
    src = np.sort(rng.choice(nv, min(cfg.sources, nv), replace=False))
    # the plain solve, as the per-mesh training datasets use (near_source costs 1.3-2x on small CPU meshes)
    solve = lambda rows: ngf.geodesic_distances(mesh, mesh.index[rows], device=device, near_source=False)
    if deadline is None:
        d = solve(src)
    else:
        parts, done, step = [], 0, GT_MIN_SOURCES
        while done < len(src):
            t0 = time.perf_counter()
            parts.append(solve(src[done: done + step]))
            per = (time.perf_counter() - t0) / len(parts[-1])
            done += len(parts[-1])
            step = int((deadline - time.perf_counter()) / max(per, 1e-9))
            if step < 1:
                break
        src, d = src[:done], np.concatenate(parts)
    complete = len(src) == min(cfg.sources, nv)
    d = d[:, mesh.index] * np.float32(mesh.scale)
    tgt = np.zeros((len(src), cfg.targets), np.int32)
    keep = np.ones(len(src), bool)
    for r in range(len(src)):
        ok = np.flatnonzero(np.isfinite(d[r]) & (d[r] > 0))
        if len(ok) == 0:
            keep[r] = False
            continue
        tgt[r] = rng.choice(ok, cfg.targets, replace=len(ok) < cfg.targets)
    src, tgt = src[keep], tgt[keep]
    dist = np.take_along_axis(d[keep], tgt, axis=1).astype(np.float32)
    cloud, _ = sample_surface(mesh, cfg.cloud_points, cfg.seed)
    return {"cloud": ((cloud - mesh.center) * mesh.scale).astype(np.float32),
            "verts": mesh.internal_normalized_vertices.astype(np.float32), "src": src.astype(np.int32), "tgt": tgt,
            "dist": dist, "complete": np.bool_(complete)}


def _atomic_savez(path: Path, **arrays):
    from neurogf_warp.common.files import atomic_write

    atomic_write(path, lambda f: np.savez(f, **arrays))


def _complete(path: Path) -> bool:
    try:
        with np.load(path) as z:
            return bool(z["complete"]) if "complete" in z.files else True
    except (OSError, ValueError):
        return False


def ground_truth_cache(files, cache: Path, cfg: GenTrainConfig, rank: int = 0, world: int = 1, device=None,
                       log=print, deadline: float | None = None, at_least: int = 0) -> list[Path]:
    """Compute (rank's shard: ``balanced_shard`` of the file sizes) and cache the ground truth of ``files``; returns the
    cache path of every file (all ranks), whether or not it is computed yet (a barrier follows under DDP).
    ``deadline`` (a ``time.perf_counter()`` value): start no shape after it and solve the last one's sources up to it
    (the files left have no cache file); ``at_least``: shapes solved even past the deadline (with
    ``GT_MIN_SOURCES`` sources). A cached file solved short of its sources under a deadline is used under a deadline
    and solved again without one."""
    cache = Path(cache)
    cache.mkdir(parents=True, exist_ok=True)
    out = [cache / f"{p.stem}_{_file_key(p, cfg)}.npz" for p in files]
    mine = [i for i in balanced_shard(file_sizes(files), world, rank)
            if not out[i].exists() or (deadline is None and not _complete(out[i]))]
    t0 = time.perf_counter()
    for n, i in enumerate(mine):
        if deadline is not None and time.perf_counter() >= deadline and n >= at_least:
            log(f"[rank {rank}] ground truth stopped at its share of the budget: {n}/{len(mine)} shapes, "
                f"{time.perf_counter() - t0:.1f} s")
            break
        gt = shape_ground_truth(files[i], cfg, device, deadline)
        if not gt["complete"]:
            log(f"[rank {rank}] ground truth of {files[i].name}: {len(gt['src'])} of {cfg.sources} sources within "
                f"the budget's share")
        _atomic_savez(out[i], **gt)
        if (n + 1) % 10 == 0 or n + 1 == len(mine):
            log(f"[rank {rank}] ground truth {n + 1}/{len(mine)} shapes, {time.perf_counter() - t0:.1f} s")
    return out


class ShapeData:
    """Cached ground truth of a list of shapes, loaded on first use (each rank touches only its shard)."""

    def __init__(self, paths):
        self.paths = list(paths)
        self._data: dict = {}

    def __len__(self):
        return len(self.paths)

    def __getitem__(self, i):
        if i not in self._data:
            with np.load(self.paths[i]) as z:
                self._data[i] = {k: z[k] for k in z.files}
        return self._data[i]

    def batch(self, idx, n_src, n_tgt, rng, rotate: bool = False):
        """(cloud (B, P, 3), s (B, M, 3), t (B, M, 3), ratio (B, M), dist (B, M)) float32, M = n_src n_tgt.

        rotate: each shape turned by a random rotation and moved back into the unit-sphere frame of its turned
        vertices (ratios unchanged; distances scaled with the frame)."""
        C, S, T, D = [], [], [], []
        for i in idx:
            z = self[i]
            rs = rng.choice(len(z["src"]), n_src, replace=len(z["src"]) < n_src)
            ct = rng.integers(0, z["tgt"].shape[1], (n_src, n_tgt))
            tv = z["tgt"][rs[:, None], ct]
            verts, cloud, d = z["verts"], z["cloud"], z["dist"][rs[:, None], ct].reshape(-1)
            if rotate:
                q = random_rotation(rng).astype(np.float32)
                v = verts @ q.T
                c = (v.min(axis=0) + v.max(axis=0)) / 2
                r = np.float32(np.sqrt(((v - c) ** 2).sum(axis=1)).max())
                verts, cloud, d = (v - c) / r, (cloud @ q.T - c) / r, d / r
            S.append(np.repeat(verts[z["src"][rs]], n_tgt, axis=0))
            T.append(verts[tv.reshape(-1)])
            D.append(d)
            C.append(cloud)
        C, S, T, D = (np.stack(x) for x in (C, S, T, D))
        eu = np.linalg.norm(S - T, axis=-1)
        ratio = D / np.maximum(eu, 1e-12)
        return C, S, T, ratio.astype(np.float32), D


def random_rotation(rng) -> np.ndarray:
    """A uniformly random rotation matrix (3, 3) (QR of a Gaussian matrix, signs fixed, det +1)."""
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


# ---- distributed ---------------------------------------------------------------------------------------------

def _dist_setup(device_arg):
    """(rank, world, device, is_distributed): from torchrun's environment; gloo on CPU, NCCL on CUDA."""
    import torch.distributed as dist

    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local = int(os.environ.get("LOCAL_RANK", "0"))
    if device_arg in (None, "auto"):
        device = torch.device(f"cuda:{local}" if torch.cuda.is_available() else "cpu")
    else:
        device = torch.device(device_arg)
        if device.type == "cuda" and device.index is None:
            device = torch.device(f"cuda:{local}")
    if device.type == "cuda":
        torch.cuda.set_device(device)
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo", timeout=timedelta(hours=6))
        # NCCL builds its communicator at the first collective (seconds on two H200s): here, with the start-up,
        # rather than inside the first barrier, which ends the ground-truth phase
        dist.all_reduce(torch.zeros(1, device=device))
    return rank, world, device, world > 1


def shared_deadline(deadline: float | None, device, distributed: bool) -> float | None:
    """Rank 0's deadline on every rank: the time it has left is broadcast and each rank adds it to its own clock
    (``time.perf_counter()`` values of different hosts are not comparable). Every rank must call it."""
    if not distributed or deadline is None:
        return deadline
    import torch.distributed as dist

    left = torch.tensor([deadline - time.perf_counter()], dtype=torch.float64, device=device)
    dist.broadcast(left, 0)
    return time.perf_counter() + float(left.item())


class BudgetSteps:
    """A budgeted run's decisions on rank 0's clock: when to stop, how many shapes a step draws, how often the
    clock is shared.

    The first step draws one shape and is timed; then ``shapes`` becomes the most (up to ``shapes_per_step``) that
    let ``BUDGET_STEPS`` steps fit in the time left (steps of s shapes take about s times a one-shape step). A step
    is not started when it would end past ``end`` (``time.perf_counter()``), the first one excepted. Without a
    budget (``end`` None) nothing changes: ``shapes_per_step`` shapes, every SYNC_EVERY steps.
    """

    def __init__(self, shapes_per_step: int, end: float | None):
        self.full, self.end = int(shapes_per_step), end
        self.shapes = self.full if end is None else 1
        self.per_shape: float | None = None  # seconds of a step per shape drawn (the slowest measured)
        self.said = False

    def step_time(self) -> float:
        return 0.0 if self.per_shape is None else self.per_shape * self.shapes

    def stop(self, steps_done: int, now: float | None = None) -> bool:
        """Whether the next step must not start (``steps_done`` steps of this call so far)."""
        if self.end is None or steps_done == 0:
            return False
        now = time.perf_counter() if now is None else now
        return now + self.step_time() > self.end

    def step_done(self, steps_done: int, seconds: float, say=print, now: float | None = None):
        """After step ``steps_done`` of this call took ``seconds`` with ``shapes`` shapes."""
        per = seconds / max(self.shapes, 1)
        self.per_shape = per if self.per_shape is None or steps_done <= 1 else max(0.5 * self.per_shape, per)
        if steps_done == 0 and self.end is not None:
            now = time.perf_counter() if now is None else now
            fit = int(max(self.end - now, 0.0) / (BUDGET_STEPS * self.per_shape))
            self.shapes = max(1, min(self.full, fit))
            if self.shapes < self.full and not self.said:
                self.said = True
                say(f"short budget: {self.shapes} shape(s) per step instead of {self.full} (a step takes ~"
                    f"{self.per_shape:.2f} s per shape, {max(self.end - now, 0.0):.0f} s left)")

    def share_every(self) -> int:
        """Steps until rank 0's clock is shared again: SYNC_EVERY, fewer when that many might pass the end."""
        if self.end is None or self.per_shape is None:
            return SYNC_EVERY if self.end is None else 1
        left = self.end - time.perf_counter()
        return int(max(1, min(SYNC_EVERY, left / max(2 * self.step_time(), 1e-9))))

    def val_deadline(self) -> float | None:
        return self.end


# ---- checkpoints ---------------------------------------------------------------------------------------------

def atomic_torch_save(obj, path: Path):
    from neurogf_warp.common.files import atomic_write  # the package's one rule for every file it writes

    atomic_write(path, lambda f: torch.save(obj, f), what="model file")


def _trained_on(folder, train, val, cfg):
    info = {"folder": str(Path(folder).resolve()), "n_train": len(train), "n_val": len(val),
            "train_files": [str(Path(p).relative_to(folder)) for p in train],
            "val_files": [str(Path(p).relative_to(folder)) for p in val],
            "ground_truth": f"ngf.geodesic_distances, {cfg.sources} sources x {cfg.targets} targets per shape, "
                            f"{cfg.cloud_points}-point cloud (trimesh sample_surface, seed {cfg.seed}), "
                            f"unit-sphere frame"}
    man = Path(folder) / "manifest.json"
    if man.exists():
        try:
            m = json.loads(man.read_text())
            fams: dict = {}
            for s in m.get("shapes", {}).values():
                fams[s["family"]] = fams.get(s["family"], 0) + 1
            info["collection"] = {"seed": m.get("seed"), "families": fams}
        except (ValueError, KeyError):
            pass
    return info


# ---- validation ----------------------------------------------------------------------------------------------

@torch.no_grad()
def validation_mre(net: GenNeuroGF, data: ShapeData, cfg: GenTrainConfig, device,
                   deadline: float | None = None) -> float:
    """Mean relative error of max(ratio, 1) |s - t| on held-out shapes (fixed pairs: seed 12345), eval mode.
    ``deadline`` (a ``time.perf_counter()`` value): no shape after the first is started once a shape would end
    past it."""
    if len(data) == 0:
        return float("nan")
    was = net.training
    net.eval()
    rng = np.random.default_rng(12345)
    errs = []
    per = 0.0
    for i in range(min(cfg.val_shapes, len(data))):
        t0 = time.perf_counter()
        if i and deadline is not None and t0 + per > deadline:
            break
        C, S, T, _, D = data.batch([i], cfg.val_sources, cfg.val_targets, rng)
        args = (torch.from_numpy(x).to(device) for x in (C, S, T))
        r = net(*args).clamp_min(1.0).cpu().numpy()
        pred = r * np.linalg.norm(S - T, axis=-1)
        errs.append((np.abs(pred - D) / D).ravel())
        per = max(per, time.perf_counter() - t0)
    net.train(was)
    return float(np.concatenate(errs).mean())


# ---- training ------------------------------------------------------------------------------------------------

def train_generalizable(folder, output, config: GenTrainConfig | None = None, resume: bool = False,
                        cache=None, device=None, gt_device=None, log=None, callback=None, files=None) -> dict:
    """Train (or resume) on a folder of meshes; returns the final checkpoint dict (see the module docstring).

    ``files``: (training files, validation files) under ``folder`` instead of :func:`mesh_files`'s split (e.g.
    only the shapes whose ground truth is cached). Ground truth is computed (or read from the cache) for every
    training file and for the first ``val_shapes`` validation files, the only ones validation uses.

    ``callback(step, loss)`` runs after every step (raise KeyboardInterrupt there to stop like Ctrl-C: the
    checkpoint is written, then the KeyboardInterrupt propagates).

    Works alone or under torchrun (one process per GPU or several on the CPU).
    """
    import torch.distributed as dist
    from torch.nn.parallel import DistributedDataParallel as DDP

    from neurogf_warp.common.clock import budget_start

    t_call = budget_start(time.perf_counter())
    cfg = config or GenTrainConfig()
    if cfg.budget_seconds is not None:  # the per-mesh rule, before any work (a NaN budget would never end the run)
        from neurogf_warp.training.api import check_budget

        cfg = dataclasses.replace(cfg, budget_seconds=check_budget(cfg.budget_seconds))
    from neurogf_warp.model.files import _not_a_mesh_name

    _not_a_mesh_name(output, ".pt")  # never over a mesh of the collection (the model is written at the end)
    check_config(cfg)
    rank, world, dev, distributed = _dist_setup(device)
    log = log or (lambda s: print(s, flush=True))
    say = (lambda s: log(s)) if rank == 0 else (lambda s: None)
    output = Path(output)
    cache = Path(cache) if cache else output.with_name(output.name + ".gt")
    if dev.type == "cpu" and distributed:
        torch.set_num_threads(max(1, (os.cpu_count() or 1) // world))
    train_files, val_files = (list(files[0]), list(files[1])) if files is not None else mesh_files(folder)
    if not train_files:
        raise ValueError(f"no training shapes under {folder}")
    say(f"{len(train_files)} training shapes, {len(val_files)} held out ({min(len(val_files), cfg.val_shapes)} "
        f"used for validation); world size {world}, device {dev}")

    torch.manual_seed(cfg.seed)
    net = GenNeuroGF().to(dev)
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    state = {"step": 0, "elapsed_s": 0.0, "loss_history": [], "val_history": [], "gt_seconds": 0.0}
    if resume and output.exists():
        ck = torch.load(output, map_location="cpu", weights_only=True)
        if ck.get("format") != FORMAT:
            raise ValueError(f"{output} is not a generalizable training file; cannot resume from it")
        net.load_state_dict(ck["state_dict"])
        opt.load_state_dict(ck["optimizer"])
        state = {k: ck.get(k, v) for k, v in state.items()}
        say(f"resumed {output} at step {state['step']} (written with world size {ck.get('world_size')})")
    elif output.exists() and rank == 0:
        say(f"note: {output} exists and will be overwritten (use --resume to continue it)")

    # one deadline for the whole call (a resumed run gets what the earlier calls left), rank 0's on every rank
    budget = cfg.budget_seconds
    deadline = None
    if budget is not None:
        deadline = shared_deadline(t_call + budget - state["elapsed_s"] - state["gt_seconds"], dev, distributed)
        left = max(deadline - time.perf_counter(), 0.0)
        say(f"budget: {left:.1f} s of {budget:g} s left (ground truth at most {GT_SHARE * left:.1f} s of it)")

    # ground truth, sharded over ranks
    t_gt = time.perf_counter()
    gt_deadline = None if deadline is None else min(deadline, t_gt + GT_SHARE * max(deadline - t_gt, 0.0))
    gtd = gt_device or (str(dev) if dev.type == "cuda" else "cpu")
    tr_cache = ground_truth_cache(train_files, cache, cfg, rank, world, gtd, log, gt_deadline, at_least=1)
    va_cache = ground_truth_cache(val_files[: cfg.val_shapes], cache, cfg, rank, world, gtd, log, gt_deadline)
    if distributed:
        dist.barrier()
    gt_seconds = time.perf_counter() - t_gt
    state["gt_seconds"] += gt_seconds
    train_data, val_data = ShapeData(tr_cache), ShapeData([p for p in va_cache if p.exists()])
    # the shapes this rank solved (the same split as the ground truth's: a rank reads only its own cache files)
    shard = balanced_shard(file_sizes(train_files), world, rank) or list(range(len(train_data)))
    shard = [i for i in shard if tr_cache[i].exists()] or [i for i in range(len(tr_cache)) if tr_cache[i].exists()]
    if not shard:
        raise ValueError(f"no training shape has ground truth in {cache} (the budget ended first): raise "
                         f"--budget-seconds or run with --gt-only first")
    ready = sum(p.exists() for p in tr_cache)
    short = "" if ready == len(tr_cache) else (f": {ready} of {len(tr_cache)} training shapes and {len(val_data)} of "
                                              f"{len(va_cache)} validation shapes within the budget's share")
    say(f"ground truth ready in {gt_seconds:.1f} s ({cache}){short}")
    model = DDP(net, device_ids=[dev.index] if dev.type == "cuda" else None) if distributed else net
    model.train()
    first_step = state["step"]

    def progress(step, elapsed):
        """Fraction of the run done: by steps, or by time when a budget is set and runs out first."""
        p = step / cfg.steps
        if deadline is not None:  # where the step ends: the last one that fits then runs at the low rate
            p = max(p, (elapsed + plan.step_time()) / max(train_span, 1e-9))
        return min(p, 1.0)

    def lr_at(p):
        return cfg.lr_min + 0.5 * (cfg.lr - cfg.lr_min) * (1 + math.cos(math.pi * p))

    def checkpoint():
        if rank != 0:
            return None
        ck = {"format": FORMAT, "version": 1, "state_dict": {k: v.detach().cpu() for k, v in net.state_dict().items()},
              "optimizer": opt.state_dict(), "config": dataclasses.asdict(cfg),
              "trained_on": _trained_on(folder, train_files, val_files, cfg), "world_size": world,
              "date_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"), "torch": str(torch.__version__),
              "val_mre": state["val_history"][-1][1] if state["val_history"] else None, **state}
        atomic_torch_save(ck, output)
        return ck

    t_start = time.perf_counter() - state["elapsed_s"]
    t_ck = time.perf_counter()
    # the training's share: from here to the deadline less the model file's and the exit's time
    train_end = None if deadline is None else deadline - END_RESERVE_S
    train_span = 0.0 if deadline is None else state["elapsed_s"] + max(train_end - time.perf_counter(), 0.0)
    run_loss, run_n = torch.zeros((), device=dev), 0  # summed on the device: no host sync per step
    shared_frac = None  # rank 0's fraction of the run, as last shared (DDP)
    next_share = 0  # the step at which rank 0's clock is shared next
    plan = BudgetSteps(cfg.shapes_per_step, train_end)
    done_frac = 0.0  # the largest fraction of the run reached so far
    try:
        while True:
            step = state["step"]
            elapsed = time.perf_counter() - t_start
            stop = step >= cfg.steps or plan.stop(step - first_step)
            # the schedule only moves forward: a step faster than the last estimate must not raise the rate again
            frac = done_frac = max(progress(step, elapsed), done_frac)
            if distributed:  # every rank stops at the same step and follows one schedule (rank 0's clock)
                if step >= next_share or shared_frac is None:
                    flag = torch.tensor([1.0 if stop else 0.0, frac, plan.shapes, plan.share_every()], device=dev,
                                        dtype=torch.float64)
                    dist.broadcast(flag, 0)
                    stop, frac = bool(flag[0].item()), float(flag[1].item())
                    plan.shapes = int(flag[2].item())
                    shared_frac, next_share = frac, step + int(flag[3].item())
                else:  # the step count is the same on every rank; the clock waits for the next share
                    stop, frac = step >= cfg.steps, shared_frac
            if stop:
                break
            t_step = time.perf_counter()
            rng = np.random.default_rng([cfg.seed, step, rank])
            n_shapes = plan.shapes
            idx = rng.choice(shard, n_shapes, replace=len(shard) < n_shapes)
            C, S, T, R, _ = train_data.batch(idx, cfg.step_sources, cfg.step_targets, rng, rotate=cfg.rotate)
            C, S, T, R = (torch.from_numpy(x).to(dev, non_blocking=True) for x in (C, S, T, R))
            lr = lr_at(frac)
            for g in opt.param_groups:
                g["lr"] = lr
            loss = (model(C, S, T) - R).abs().mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            state["step"] = step + 1
            if deadline is not None:
                plan.step_done(step - first_step, time.perf_counter() - t_step, say)
            if callback is not None:
                callback(state["step"], float(loss.detach()))
            run_loss += loss.detach()
            run_n += 1
            if state["step"] % cfg.log_every == 0 or state["step"] == 1:
                mean = float(run_loss) / run_n
                if distributed:
                    t = torch.tensor([mean], device=dev)
                    dist.all_reduce(t)
                    mean = float(t.item()) / world
                state["loss_history"].append([state["step"], mean])
                say(f"step {state['step']}/{cfg.steps}  loss {mean:.4f}  lr {lr:.2e}  "
                    f"{time.perf_counter() - t_start:.1f} s")
                run_loss, run_n = torch.zeros((), device=dev), 0
            if cfg.val_every and state["step"] % cfg.val_every == 0 and rank == 0 and len(val_data):
                mre = validation_mre(net, val_data, cfg, dev, plan.val_deadline())
                state["val_history"].append([state["step"], mre])
                say(f"step {state['step']}  validation MRE {100 * mre:.2f}% ({min(cfg.val_shapes, len(val_data))} "
                    f"held-out shapes)")
            state["elapsed_s"] = time.perf_counter() - t_start
            if time.perf_counter() - t_ck >= cfg.checkpoint_seconds:
                checkpoint()
                t_ck = time.perf_counter()
    except KeyboardInterrupt:
        # Ctrl-C (or a callback raising KeyboardInterrupt): keep the finished steps, as per-mesh training does
        state["elapsed_s"] = time.perf_counter() - t_start
        checkpoint()
        say(f"interrupted at step {state['step']}: {output} written; --resume continues it")
        raise
    state["elapsed_s"] = time.perf_counter() - t_start
    if rank == 0 and len(val_data) and (not state["val_history"] or state["val_history"][-1][0] != state["step"]):
        mre = validation_mre(net, val_data, cfg, dev, train_end)
        state["val_history"].append([state["step"], mre])
        say(f"final validation MRE {100 * mre:.2f}%")
    ck = checkpoint()
    say(f"wrote {output}: step {state['step']}, {state['elapsed_s']:.1f} s of training")
    if distributed:
        dist.barrier()
        dist.destroy_process_group()
    return ck


def _flag(text: str) -> bool:
    t = text.strip().lower()
    if t in ("1", "true", "yes", "on"):
        return True
    if t in ("0", "false", "no", "off"):
        return False
    raise argparse.ArgumentTypeError(f"expected true or false, got {text!r}")


def torchrun_command(prog: str, args: str) -> str:
    """The torchrun line that runs command ``prog`` (``python -m MODULE`` or an installed program) on N ranks."""
    if prog.startswith("python -m "):
        return f"torchrun --nproc_per_node N -m {prog[len('python -m '):]} {args}"
    return f"torchrun --nproc_per_node N --no-python {prog} {args}"


_finite = finite_arg()


# the command line's help of each GenTrainConfig setting (its default is appended)
OPTION_HELP = {
    "sources": "ground truth: source vertices per shape",
    "targets": "ground truth: target vertices per source",
    "cloud_points": "points sampled on each shape, the encoder's input",
    "shapes_per_step": "shapes per training step and rank",
    "step_sources": "sources per shape and step",
    "step_targets": "targets per source and step",
    "steps": "length of the cosine learning-rate schedule, and the last step",
    "lr": "learning rate at the start of the cosine schedule",
    "lr_min": "learning rate at its end",
    "weight_decay": "AdamW weight decay",
    "rotate": "augmentation: turn every drawn shape by a random rotation (true or false)",
    "checkpoint_seconds": "seconds between checkpoints of the output file",
    "val_every": "steps between validations",
    "val_shapes": "held-out shapes used per validation (the first ones)",
    "val_sources": "sources per held-out shape in a validation",
    "val_targets": "targets per source in a validation",
    "seed": "random seed of the ground truth's sources and targets and of the batches",
    "log_every": "steps between log lines",
}


def main(argv=None, prog: str = "python -m neurogf_warp.generalizable.train"):
    import contextlib

    from neurogf_warp.common.clock import process_clock

    # run as a program: the budget counts from the process start (through neurogf-warp gen-train: already so)
    with process_clock() if argv is None else contextlib.nullcontext():
        return _main(argv, prog)


def _main(argv, prog: str):
    ap = argparse.ArgumentParser(prog=prog,
                                 description="Train a generalizable NeuroGF network on a folder of meshes "
                                             "(also under torchrun).",
                                 epilog="on N GPUs of one machine: " + torchrun_command(prog, "FOLDER -o model.pt"))
    ap.add_argument("folder", help="meshes (train/ and test/ subfolders, or every 10th file held out)")
    ap.add_argument("-o", "--output", required=True, help="model file to write (and resume from)")
    ap.add_argument("--budget-seconds", type=_finite, default=None,
                    help="time limit of the whole run from the process start (ground truth at most a third of it; "
                         "under torchrun rank 0's clock)")
    ap.add_argument("--resume", action="store_true", help="continue the output file's training")
    ap.add_argument("--cache", default=None, help="ground-truth cache folder (default: <output>.gt)")
    ap.add_argument("--device", default=None, help="cpu, cuda (this rank's GPU) or cuda:N (default: auto)")
    ap.add_argument("--gt-only", action="store_true", help="compute the ground truth and stop")
    for f in dataclasses.fields(GenTrainConfig):
        if f.name == "budget_seconds":
            continue
        kind = _flag if isinstance(f.default, bool) else _finite if isinstance(f.default, float) else type(f.default)
        ap.add_argument("--" + f.name.replace("_", "-"), type=kind, default=None,
                        help=f"{OPTION_HELP[f.name]} (default {f.default})")
    a = ap.parse_args(argv)
    cfg = GenTrainConfig(**{f.name: getattr(a, f.name) for f in dataclasses.fields(GenTrainConfig)
                            if f.name != "budget_seconds" and getattr(a, f.name) is not None},
                         budget_seconds=a.budget_seconds)
    try:
        check_config(cfg)
        if a.gt_only:
            rank, world, dev, distributed = _dist_setup(a.device)
            train, val = mesh_files(a.folder)
            out = Path(a.output)
            cache = Path(a.cache) if a.cache else out.with_name(out.name + ".gt")
            gtd = str(dev) if dev.type == "cuda" else "cpu"
            t0 = time.perf_counter()
            from neurogf_warp.common.clock import budget_start

            deadline = None if a.budget_seconds is None else shared_deadline(
                budget_start(t0) + a.budget_seconds - END_RESERVE_S, dev, distributed)
            ground_truth_cache(train + val, cache, cfg, rank, world, gtd, deadline=deadline, at_least=1)
            if distributed:
                import torch.distributed as dist
                dist.barrier()
                dist.destroy_process_group()
            if rank == 0:
                print(f"ground truth of {len(train) + len(val)} shapes in {time.perf_counter() - t0:.1f} s "
                      f"(world size {world})", flush=True)
            return 0
        train_generalizable(a.folder, a.output, cfg, resume=a.resume, cache=a.cache, device=a.device)
    except KeyboardInterrupt:
        return 130
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
