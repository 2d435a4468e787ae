"""One training step of each stage: sampling, the stage's losses, the optimizer, validation, step state.

Stages (reference §3-§5), run in order as one global step sequence so that a checkpoint can resume anywhere:

  querier      SDF querier, MSE on SDF samples                              (§3)
  joint        the whole network with the paper's losses and weights       (§4)
  refine_dist  lifting + distance head, distance losses only, eval-mode BN (not in the paper: the distance
               network is fine-tuned as inference runs it, with steps ~3x cheaper than joint ones)
  refine_sdf   SDF head alone on eval-mode (running-stat) lifting features  (§5a)
  refine_path  guidance + path head on eval-mode lifting features           (§5b)

What each stage trains, draws and optimizes is its entry in ``stages.STAGE_TABLE``; its losses are methods here.

Differences from the official scripts, on purpose:
  * a fresh batch every ``resample_every`` steps (default 1) instead of one batch reused for 200 iterations:
    sampling is a few index draws on the device, and fresh data generalizes better;
  * per-step cosine decay instead of per-epoch;
  * SDF ground truth is computed once for a pool of points and batches are drawn from the pool;
  * the first path-head layer is split into xyz and guidance parts (exact, ~4x fewer FLOPs there);
  * the global distance targets use a relative L1 (the MRE itself), and the refine_dist stage above;
  * on CUDA: TF32, a bf16 path head, torch.compile'd losses and CUDA graphs (``acceleration.py``).
"""
from __future__ import annotations

import contextlib
import math

import numpy as np
import torch
import torch.nn.functional as F

from neurogf_warp.model.network import NeuroGFNet, SdfQuerier, straight_lines
from neurogf_warp.training import losses as L
from neurogf_warp.training.acceleration import CompiledLosses, GraphedStep, set_tf32
from neurogf_warp.training.config import STAGES, TrainConfig
from neurogf_warp.training.data import TrainingData
from neurogf_warp.training.stages import STAGE_TABLE

__all__ = ["Trainer", "Ranks", "fast_path", "cosine_lr"]

HARD_CANDIDATES = 8  # rows scored per hard-pool refresh, in batches of each distance set
HARD_KEEP = 1 / 8    # the worst share of them forms the pool
HARD_CHUNK = 65536   # rows scored per forward pass (full GPU batches rank 524K rows: 1M points x 256 x 4 B per layer)


def _bn(x, bn, training):
    if training and bn.num_batches_tracked is not None:
        bn.num_batches_tracked.add_(1)
    return F.batch_norm(x, bn.running_mean, bn.running_var, bn.weight, bn.bias, training, bn.momentum, bn.eps)


def fast_path(net: NeuroGFNet, es, et, lines):
    """Same function as ``net.path_from_embeddings`` (training or eval BN), cheaper.

    The first point-wise layer sees [xyz | g] with g constant along a path, so W·[xyz|g] is split into
    W_xyz·xyz (per point) + W_g·g (per path): the D-wide part runs once per path, not once per point.
    Later layers run as plain matmuls on (K*M, C) instead of 1x1 convolutions with permutes.

    es, et : (K, D) embeddings of the ends; lines : (K, M, 3) straight-line samples -> (K, M, 3) path points.
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


# the landmark table's rows come from a solve of at least this many Steiner points per edge: the bounds read them as
# exact (a spot model read with its k = 1 table 0.186% MRE, with k = 3 rows 0.069%; docs/design.md)
LANDMARK_MIN_K = 3


def landmark_table(data: TrainingData, k: int, device, solved: int | None = None) -> tuple:
    """The lookup table of a ``landmarks=k`` network: (n, 3) points and (n, k) exact distances (normalized units)
    from k landmark vertices, for every vertex and every other point the distance rows use.

    Landmarks are the dataset's first distance sources when it kept their whole rows (``data.full_dist``; rows of a
    solve coarser than ``LANDMARK_MIN_K`` are solved again at it, ``solved`` of them), else
    vertices spread by farthest-point sampling in space, solved by the ground-truth solver (plain solve, as the
    training rows); +inf across components becomes 4 (the normalized mesh fits the unit sphere, so every
    finite distance is far below it). Rows of a proxy dataset start and end at proxy vertices, which are not mesh
    vertices: each gets the distances of its nearest mesh vertex (a fraction of an edge off). ``solved``: solve
    only that many landmarks (a budget's share; at most k and the vertex count) and repeat their columns to k."""
    from neurogf_warp.ground_truth.geodesics import geodesic_distances
    from neurogf_warp.model.network import LANDMARK_UNREACHED, Landmarks
    from neurogf_warp.training.data import warp_device

    x = data.vertices
    kept = getattr(data, "full_dist", None)
    if kept is not None and len(kept):  # the dataset's own first distance sources: no solve of their own
        columns, k = k, min(k, len(kept))
        d = kept[:k].detach().cpu().numpy()
        if data.solve_k < LANDMARK_MIN_K:  # a coarse solve's rows: as many as the share allows solved again finer
            n = min(k, solved or k)
            v = x.detach().cpu().numpy().astype(np.float64)
            d = d.copy()
            d[:n] = geodesic_distances((v, data.faces), data.full_src[:n], device=warp_device(device), k=LANDMARK_MIN_K,
                                       near_source=False)
    else:
        columns, k = k, min(k, solved or k, len(x))
        far = torch.full((len(x),), float("inf"), device=x.device)
        pick = [0]
        for _ in range(k - 1):
            far = torch.minimum(far, (x - x[pick[-1]]).square().sum(-1))
            pick.append(int(far.argmax()))
        v = x.detach().cpu().numpy().astype(np.float64)
        d = geodesic_distances((v, data.faces), np.asarray(pick), device=warp_device(device), near_source=False)
    d = np.where(np.isfinite(d), d, LANDMARK_UNREACHED).astype(np.float32)[np.arange(columns) % k]
    table = torch.as_tensor(d.T.copy(), device=device)
    lookup = Landmarks(columns).to(device)
    lookup.set_table(x, table)
    pts = torch.cat([r[:, c:c + 3] for r in data.gd.values() for c in (0, 3)])
    pts = pts[_first_of_each(lookup._key(pts))]  # the rows' distinct end points (keys collide only by chance)
    other = ~lookup.match(pts)[1]
    if bool(other.any()):
        extra = pts[other]
        near = torch.cat([torch.cdist(part, x).argmin(-1) for part in extra.split(4096)])
        x, table = torch.cat([x, extra]), torch.cat([table, table[near]])
    return x, table


def _first_of_each(keys: torch.Tensor) -> torch.Tensor:
    """The index of the first occurrence of each distinct value of ``keys``."""
    uniq, inv = torch.unique(keys, return_inverse=True)
    first = torch.full((len(uniq),), len(keys), dtype=torch.long, device=keys.device)
    return first.scatter_reduce_(0, inv, torch.arange(len(keys), device=keys.device), reduce="amin")


def cosine_lr(step: int, n: int, hi: float, lo: float) -> float:
    """Cosine decay from ``hi`` at step 0 to ``lo`` at step ``n``."""
    return lo + 0.5 * (hi - lo) * (1.0 + math.cos(math.pi * min(step, n) / max(n, 1)))


class Ranks:
    """The ranks of one data-parallel run (a torch.distributed process group): rank 0 decides, every rank follows.

    Every method is a collective: all ranks call it, in the same order. ``of(distributed)`` is None for a run in
    one process (``distributed`` False, or a group of one rank), so that path enters no collective.
    """

    def __init__(self, group, rank: int, world: int):
        import torch.distributed as dist

        self.group, self.rank, self.world = group, rank, world
        self.first = rank == 0
        self.src = 0 if group is None else dist.get_global_rank(group, 0)
        self.nccl = dist.get_backend(group) == "nccl"

    @classmethod
    def of(cls, distributed) -> "Ranks | None":
        from neurogf_warp.ground_truth.devices import process_group

        pg = process_group(distributed)
        return None if pg is None or pg[2] == 1 else cls(*pg)

    def agree(self, value):
        """Rank 0's ``value`` (picklable) on every rank."""
        import torch.distributed as dist

        box = [value]
        dist.broadcast_object_list(box, src=self.src, group=self.group)
        return box[0]

    def gather(self, value) -> list:
        """Every rank's ``value`` (picklable, small), in rank order."""
        from neurogf_warp.ground_truth.devices import all_gather_objects

        return all_gather_objects(value, self.group)

    def on_first(self, fn, share: bool = True):
        """``fn()`` on rank 0 alone; what it raised is raised on every rank (the others would otherwise wait in
        the next collective forever), and with ``share`` its value is returned on every rank."""
        value, error = None, None
        if self.first:
            try:
                value = fn()
            except BaseException as e:  # noqa: BLE001 - raised again below, on every rank
                error = e
        sent = self.agree((_portable(error), value if share else None))
        if error is not None:
            raise error
        if sent[0] is not None:
            raise sent[0]
        return value if self.first else sent[1]

    def on_each(self, fn):
        """``fn()`` on every rank; when it raised on any rank, every rank raises (the first such rank's error)."""
        value, error = None, None
        try:
            value = fn()
        except BaseException as e:  # noqa: BLE001 - raised again below, on every rank
            error = e
        errors = self.gather(_portable(error))
        if error is not None:
            raise error
        for e in errors:
            if e is not None:
                raise e
        return value

    def _tensors(self, tensors, op):
        """Run ``op(flat)`` on ``tensors`` flattened into one buffer per dtype (on the CPU under gloo) and copy
        the result back."""
        by_dtype = {}
        for t in tensors:
            by_dtype.setdefault(t.dtype, []).append(t)
        for group in by_dtype.values():
            flat = torch.cat([t.detach().reshape(-1) for t in group])
            if flat.is_cuda and not self.nccl:
                flat = flat.cpu()
            op(flat)
            flat = flat.to(group[0].device)
            off = 0
            for t in group:
                t.data.copy_(flat[off: off + t.numel()].view_as(t))
                off += t.numel()

    def broadcast_(self, tensors) -> None:
        """Rank 0's ``tensors`` on every rank (in place)."""
        import torch.distributed as dist

        self._tensors(list(tensors), lambda f: dist.broadcast(f, src=self.src, group=self.group))

    def average_(self, tensors) -> None:
        """Every tensor replaced by its mean over the ranks (in place; one all_reduce per dtype)."""
        import torch.distributed as dist

        def mean(flat):
            dist.all_reduce(flat, group=self.group)
            flat /= self.world

        self._tensors(list(tensors), mean)


def _portable(error):
    """``error`` as an exception that survives pickling to the other ranks (its text, where it does not)."""
    if error is None:
        return None
    import pickle

    try:
        pickle.loads(pickle.dumps(error))
        return error
    except Exception:  # noqa: BLE001 - any pickling failure: send the text instead
        return RuntimeError(f"rank 0: {type(error).__name__}: {error}")


def rank_seed(seed: int, rank: int, *more: int) -> int:
    """The batch stream seed of ``rank`` > 0 of a data-parallel run (rank 0 draws the one-process stream)."""
    return int(np.random.SeedSequence([seed, rank, *more]).generate_state(1, np.uint64)[0] >> 1)


class Trainer:
    """The networks, data and per-stage optimizer of a run; ``step(stage, i)`` runs one iteration.

    cfg : TrainConfig; data : TrainingData; sdf_pool : ((n, 3), (n,)) tensors from ``make_sdf_pool``;
    ranks : a ``Ranks`` for data-parallel training (every rank draws its own batches and the gradients are
    averaged over the ranks before each update), or None.
    """

    def __init__(self, cfg: TrainConfig, data: TrainingData, sdf_pool, device, ranks: Ranks | None = None):
        self.cfg, self.data, self.device = cfg, data, torch.device(device)
        self.ranks = ranks
        torch.manual_seed(cfg.seed)  # weight init
        self.net = cfg.network.build().to(self.device)
        if cfg.network.landmarks:
            # solved once per run: a Trainer rebuilt for other batch sizes reuses the rows
            if data.landmark_rows is None:
                data.landmark_rows = landmark_table(data, cfg.network.landmarks, self.device, data.landmarks_solved)
            self.net.landmark_table.set_table(*data.landmark_rows)
        self.querier = SdfQuerier().to(self.device)
        self.sdf_pts, self.sdf_val = sdf_pool
        self.gen = torch.Generator(device=self.device)
        self.gen.manual_seed(cfg.seed + 1)
        if ranks is not None:
            # one start for every replica (a GPU's landmark rows may differ in the last bits), own batches per rank
            ranks.broadcast_(self.tensors())
            if not ranks.first:
                self.gen.manual_seed(rank_seed(cfg.seed + 1, ranks.rank))
        self.steps = cfg.stage_steps()
        self.opt = None
        self.opt_stage = None
        self._idx_now = None       # index vectors of the current batch
        self._gen_at_batch = None  # generator state when the current batch was drawn (for resume)
        self._graph = None         # GraphedStep of the current stage (CUDA graphs)
        self._hard = None          # {distance set: (n,) row indices} of the hard-pair pool (``hard_share``)
        self._hard_at = None       # (stage, step) of its last re-ranking
        cuda = self.device.type == "cuda"
        self.amp = cfg.runtime.amp and cuda
        # data-parallel steps all-reduce between backward and the update: not inside a captured graph
        self.graphs = cfg.runtime.cuda_graph and cuda and ranks is None
        self._compiled = CompiledLosses(cfg.runtime.compile and cuda)
        self.weights = {**L.WEIGHTS, **cfg.schedule.loss_weights}

    def compile_losses(self, on: bool) -> None:
        """Whether the losses are compiled (CUDA; before the first step): a short budget runs them eagerly."""
        self._compiled.enabled = bool(on) and self.device.type == "cuda" and self.cfg.runtime.compile

    # -- sampling (all on the device, no host sync). A step draws index vectors (``draw``), then gathers
    # its batch from the device arrays (``gather``); with CUDA graphs only the draw runs outside the graph.
    def _idx(self, n, k):
        return torch.randint(0, n, (k,), device=self.device, generator=self.gen)

    def _draws(self, stage):
        """(name, pool size, count) of the index vectors one step of ``stage`` uses, in draw order."""
        b, d = self.cfg.batches, self.data
        n_sdf = len(self.sdf_pts)
        parts = {  # stages.DRAWS
            "sdf": lambda: [("sdf", n_sdf, min(b.batch_sdf, n_sdf))],
            "querier_sdf": lambda: [("sdf", n_sdf, min(b.batch_querier, n_sdf))],
            "distances": lambda: [(k, len(d.gd[k]), n) for k, n in
                                  (("global", b.batch_g), ("local1", b.batch_l1), ("local2", b.batch_l2))],
            "paths_global": lambda: [("pg", len(d.pg), b.batch_paths_g)],
            "paths_local": lambda: [("pl", len(d.pl), b.batch_paths_l)],
        }
        return [row for part in STAGE_TABLE[stage].draws for row in parts[part]()]

    def draw(self, stage):
        """Fresh index vectors for one step of ``stage``: {name: (count,) long tensor}. With a hard-pair pool
        (``hard_share``), that share of each distance set's rows comes from the pool (same counts, so a
        captured graph's index shapes do not change)."""
        out = {}
        for k, n, m in self._draws(stage):
            pool = self._hard.get(k) if self._hard else None
            h = int(round(self.cfg.schedule.hard_share * m)) if pool is not None else 0
            out[k] = torch.cat([self._idx(n, m - h), pool[self._idx(len(pool), h)]]) if h else self._idx(n, m)
        return out

    @torch.no_grad()
    def refresh_hard(self):
        """Re-rank the hard-pair pools: ``HARD_CANDIDATES`` x the batch of fresh rows per distance set, scored by
        the eval-mode network's relative error (what the MRE measures); the worst ``HARD_KEEP`` of them stay.

        Why: a uniform batch spends most of its rows on pairs the network already has within 0.1%, while the
        error tail (p99) sits on few pairs: near the source, across thin parts, along cut loci."""
        b, was = self.cfg.batches, self.net.training
        self.net.eval()
        pools = {}
        for key, m in (("global", b.batch_g), ("local1", b.batch_l1), ("local2", b.batch_l2)):
            n = len(self.data.gd[key])
            c = min(n, HARD_CANDIDATES * m)
            cand = self._idx(n, c)
            err = torch.cat([self._relative_errors(self.data.gd[key][part]) for part in cand.split(HARD_CHUNK)])
            pools[key] = cand[err.topk(max(1, int(c * HARD_KEEP))).indices]
        self.net.train(was)
        self._hard = pools

    def gather(self, idx):
        """The batch of index vectors ``idx``: SDF (points, values), distance (p, q, d) rows, (K, M, 3) paths."""
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

    def _relative_errors(self, rows):
        """|pred - d| / d of (n, 7) distance rows under the network's current mode (targets floored at 1e-4)."""
        p, q, d = rows[:, :3], rows[:, 3:6], rows[:, 6]
        e = self.net.embed(torch.cat([p, q]))
        return (self.net.distance_from_embeddings(e[: len(p)], e[len(p):], p, q) - d).abs() / d.clamp_min(1e-4)

    def _optimizer(self, stage):
        if self.opt_stage == stage:
            return self.opt
        s = self.cfg.schedule
        params = self.trained_parameters(stage)
        # fused: one kernel for the whole update, on CUDA and on the CPU (there the cpu preset's small-batch steps
        # take 10-14% less time than with torch's default per-parameter loop). Under
        # CUDA graphs the learning rate is a device tensor (filled before each replay) and the step counter lives
        # on the device (capturable).
        lr = torch.tensor(s.lr, device=self.device) if self.graphs else s.lr
        if self.cfg.runtime.optimizer == "plain":  # the same update without torch.optim (training/adamw.py)
            from neurogf_warp.training.adamw import AdamW

            self.opt = AdamW(params, lr=lr, weight_decay=s.weight_decay)
        else:
            self.opt = torch.optim.AdamW(params, lr=lr, weight_decay=s.weight_decay, fused=True,
                                         capturable=self.graphs)
        self.opt_stage = stage
        self._idx_now = None
        self._graph = GraphedStep(lambda idx: self._update(stage, idx), self.opt.zero_grad, self.device) \
            if self.graphs else None  # the previous stage's graph and its memory pool go
        return self.opt

    def trained_modules(self, stage) -> list:
        """The modules ``stage`` trains (``Stage.trains``), in parameter-group order."""
        out = []
        for path in STAGE_TABLE[stage].trains:
            m = self
            for name in path.split("."):
                m = getattr(m, name)
            out.append(m)
        return out

    def trained_parameters(self, stage) -> list:
        """The parameters ``stage``'s optimizer updates, in its order."""
        return [p for m in self.trained_modules(stage) for p in m.parameters()]

    def tensors(self) -> list:
        """Every parameter and buffer of the networks (what makes two replicas equal)."""
        return [*self.net.parameters(), *self.net.buffers(), *self.querier.parameters(), *self.querier.buffers()]

    def share_buffers(self) -> None:
        """Rank 0's buffers (BatchNorm running statistics, drawn from its own batches) on every rank: the
        eval-mode stages and the saved model then use one set."""
        if self.ranks is not None:
            self.ranks.broadcast_([*self.net.buffers(), *self.querier.buffers()])

    def reset_stage(self):
        """Forget the current stage's optimizer, batch and graph (the next step starts the stage afresh)."""
        self.opt, self.opt_stage, self._idx_now, self._graph = None, None, None, None

    def set_modes(self, stage):
        """Train/eval flags and frozen parts for a stage: its trained modules (``Stage.trains``) get gradients and
        ``Stage.train_mode``; everything else is frozen in eval mode."""
        spec = STAGE_TABLE[stage]
        self.net.eval().requires_grad_(False)
        self.querier.eval().requires_grad_(False)
        for m in self.trained_modules(stage):
            m.train(spec.train_mode).requires_grad_(True)

    def lr_at(self, stage, step):
        """Learning rate of ``stage`` at ``step`` (cosine from the stage's rate to ``lr_min``)."""
        s, n = self.cfg.schedule, self.steps[stage]
        return cosine_lr(step, n, getattr(s, STAGE_TABLE[stage].lr), s.lr_min)

    def _set_lr(self, lr):
        for g in self.opt.param_groups:
            if isinstance(g["lr"], torch.Tensor):
                g["lr"].fill_(lr)
            else:
                g["lr"] = lr

    def _update(self, stage, idx):
        """Gather, forward, backward, optimizer step: everything a CUDA graph captures."""
        spec = STAGE_TABLE[stage]
        terms = self._compiled.get(stage, getattr(self, spec.loss))(self.gather(idx))
        loss = L.weighted_sum(terms, self.weights) if spec.weighted else sum(terms.values())
        loss.backward()
        if self.ranks is not None:  # the replicas stay equal: every rank applies the mean gradient
            self.ranks.average_([p.grad for g in self.opt.param_groups for p in g["params"] if p.grad is not None])
        self.opt.step()
        # detached: terms kept after the step (the loop's last ones, a captured graph's static ones) would keep this
        # step's autograd nodes alive, and the next step, on another stream, made torch warn on every GPU run
        # ("The AccumulateGrad node's stream does not match ...")
        return {k: v.detach() for k, v in terms.items()}

    def step(self, stage, step):
        """One step of ``stage`` at index ``step`` of it; returns the loss terms (tensors)."""
        every = self.cfg.schedule.resample_every
        self._optimizer(stage)
        self._set_lr(self.lr_at(stage, step))
        if self.cfg.schedule.hard_share > 0 and STAGE_TABLE[stage].hard_pairs and (self._hard is None or (
                step % self.cfg.schedule.hard_every == 0 and (stage, step) != self._hard_at)):
            # before the batch's generator state is kept: a resumed run redraws it alike. Once per (stage, step):
            # the budget's calibration runs step 0 several times and must time steps, not re-rankings
            self.refresh_hard()
            self._hard_at = (stage, step)
        if self._idx_now is None or step % every == 0:
            if step % every == 0:
                self._gen_at_batch = self.gen.get_state()
            elif self._gen_at_batch is not None:  # resumed mid-reuse: redraw the batch the run was using
                now = self.gen.get_state()
                self.gen.set_state(self._gen_at_batch)
                self._idx_now = self.draw(stage)
                self.gen.set_state(now)
            if self._idx_now is None or step % every == 0:
                self._idx_now = self.draw(stage)
        if self._graph is None:
            self.opt.zero_grad(set_to_none=True)
            return self._update(stage, self._idx_now)
        return self._graph(self._idx_now)

    # -- losses per stage
    def _loss_querier(self, b):
        x, y = b["sdf"]
        return {"querier_mse": F.mse_loss(self.querier(x), y)}

    def _paths(self, es, et, gt):
        """Predicted paths for gt and for its reversed copy (swapped endpoints): (2K, M, 3) each."""
        p, q = gt[:, 0], gt[:, -1]
        m = gt.shape[1]
        lines = torch.cat([straight_lines(p, q, m), straight_lines(q, p, m)])
        ctx = torch.autocast("cuda", dtype=torch.bfloat16, cache_enabled=False) if self.amp \
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
        if self.cfg.batches.batch_surf > 0:
            t["surf"] = L.surface_loss(self.querier, pred_g[: self.cfg.batches.batch_surf])
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
        loss = self.cfg.schedule.dist_loss
        for i, key in enumerate(keys):
            name = {"global": "dist_g", "local1": "dist_l1", "local2": "dist_l2"}[key]
            rel = loss == "relative_global" and key == "global"
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
        pred, gt = self._paths(e[: len(pg)], e[len(pg):], pg)
        return {"path_g": L.l1(pred, gt)}

    # -- validation: MRE on held-out sources, eval-mode BN (what inference sees)
    @torch.no_grad()
    def validate(self) -> float:
        """Mean relative error of the eval-mode network over every pair of the held-out test sources (a fraction)."""
        from neurogf_warp.training.quality import mre_estimate

        return mre_estimate(*self.source_errors())["mre"]

    def source_errors(self) -> tuple:
        """Per held-out test source with a pair of finite distance > 0: the eval-mode network's mean relative error
        over those pairs, and their count: ((S,) float64, (S,) int64), as ``quality.source_errors``."""
        was = self.net.training
        self.net.eval()
        tf32 = set_tf32(False)
        d = self.data
        errs, pairs = [], []
        with torch.no_grad():
            ev = self.net.embed(d.vertices)
            for i, s in enumerate(d.test_src):
                pred = self.net.distance_from_embeddings(ev[s].expand_as(ev), ev,
                                                         d.vertices[s].expand_as(d.vertices), d.vertices)
                gt = d.test_dist[i]
                ok = torch.isfinite(gt) & (gt > 0)
                if bool(ok.any()):
                    e = (pred[ok] - gt[ok]).abs() / gt[ok]
                    errs.append(float(torch.where(torch.isfinite(e), e, torch.ones_like(e)).double().mean()))
                    pairs.append(int(ok.sum()))
        self.net.train(was)
        set_tf32(tf32)
        return np.asarray(errs, np.float64), np.asarray(pairs, np.int64)

    # -- step state (what a checkpoint stores besides the run's bookkeeping)
    def state(self) -> dict:
        """Networks, optimizer, step counts and generator state (what a checkpoint needs to resume exactly)."""
        return {"steps": dict(self.steps), "net": self.net.state_dict(), "querier": self.querier.state_dict(),
                "opt": self._opt_state(), "opt_stage": self.opt_stage, "gen": self.gen.get_state(),
                "gen_at_batch": self._gen_at_batch, "hard": self._hard}

    def _opt_state(self):
        if self.opt is None:
            return None
        sd = self.opt.state_dict()
        for g in sd["param_groups"]:  # a graph run's device-tensor lr is stored as a number
            g["lr"] = float(g["lr"])
        return sd

    def load_state(self, ck: dict):
        """Restore ``state()`` from a checkpoint."""
        self.net.load_state_dict(ck["net"])
        self.querier.load_state_dict(ck["querier"])
        self.steps = dict(ck["steps"])
        self.gen.set_state(ck["gen"].cpu())
        g = ck.get("gen_at_batch")
        self._gen_at_batch = g.cpu() if g is not None else None
        if self.ranks is not None and not self.ranks.first:  # the checkpoint holds rank 0's stream: a fresh one
            self.gen.manual_seed(rank_seed(self.cfg.seed + 1, self.ranks.rank, ck["stage"], ck["step"]))
            self._gen_at_batch = None
        hard = ck.get("hard")
        self._hard = {k: v.to(self.device) for k, v in hard.items()} if hard else None
        if ck["opt"] is not None and ck["opt_stage"] is not None and ck["opt_stage"] in STAGES:
            self.set_modes(ck["opt_stage"])
            opt = self._optimizer(ck["opt_stage"])
            opt.load_state_dict(ck["opt"])
            if self.graphs:  # keep the lr a device tensor, or a captured graph would bake in one value
                for g in opt.param_groups:
                    g["lr"] = torch.tensor(float(g["lr"]), device=self.device)
