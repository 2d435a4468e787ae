"""CUDA speed-ups of a training step that keep its maths: TF32, torch.compile'd losses, CUDA graphs.

On the CPU none of them applies and a step runs eagerly. Under CUDA graphs a stage's whole step (gather,
forward, backward, fused AdamW update) is captured once and replayed; only the random index draws and the
learning rate (a device tensor) are set outside the graph, so replayed steps equal eager ones.
"""
from __future__ import annotations

import dataclasses
import json
import os
import sys
import tempfile

import torch

__all__ = ["set_tf32", "sync", "CompiledLosses", "GraphedStep", "GRAPH_WARMUP", "compile_key", "compile_pays",
           "compile_cached", "compile_estimate", "record_compile"]

GRAPH_WARMUP = 3  # eager steps per stage before its CUDA graph is captured


def set_tf32(on: bool) -> bool:
    """Switch TF32 for matmul and cuDNN; returns the previous matmul setting."""
    was = torch.backends.cuda.matmul.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = on
    torch.backends.cudnn.allow_tf32 = on
    return was


def sync(device) -> None:
    """Wait for the device's queued work (a no-op on the CPU)."""
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


class CompiledLosses:
    """Per-stage ``torch.compile`` of loss functions, compiled on first use; a stage whose compilation fails
    (no Triton, no C compiler, an unsupported op) runs eagerly from then on, with one warning."""

    def __init__(self, enabled: bool):
        self.enabled = enabled
        self._fns = {}  # stage -> compiled function, or False after a failure

    def get(self, stage: str, fn):
        if not self.enabled or self._fns.get(stage) is False:
            return fn
        if stage not in self._fns:
            compiled = torch.compile(fn, dynamic=False)

            def first_call(b, compiled=compiled):
                try:
                    out = compiled(b)
                except Exception as e:  # noqa: BLE001 - any compiler failure falls back to eager
                    print(f"warning: torch.compile failed for the {stage} stage ({type(e).__name__}: {e}); "
                          "running eagerly (set compile=false to skip the attempt)", file=sys.stderr)
                    self._fns[stage] = False
                    return fn(b)
                self._fns[stage] = compiled
                return out

            return first_call
        return self._fns[stage]


# torch.compile under a budget. Compiling the five stages' losses took 62 s on a fresh H100 (cold inductor and
# Triton caches: querier 18.6 s with the compiler's own start-up, joint 26.4, refine_dist 4.9, refine_sdf 3.6,
# refine_path 8.7) and makes the steps 1.2-1.7x faster (joint 9.0 -> 6.25 ms on the bunny; docs/performance.md).
# It pays off only when the training time left is over COMPILE_PAYOFF x the compile time; a budget too short for
# that runs eagerly (under CUDA graphs). A run that compiled records how long it took, and whether the cache held
# its shapes already, in the inductor cache's own folder; a later run of the same shapes on the same machine plans
# with that: a warm compile's time as it was, a cold one's times WARM_SHARE, as the caches it filled serve the next
# compile (H200, quarter batches, 2026-11-27: the calibration, compile included, took 48.6 s on a fresh machine and
# 11.3-12.9 s in the next runs of the same shapes; the five stages alone 62.2 s cold, 8.2 s warm)
COLD_COMPILE_S = 65.0
COMPILE_PAYOFF = 3.3  # 1.45 / (1.45 - 1): the joint step's speed-up
WARM_SHARE = 0.25
_RECORD = "neurogf_warp_compile.json"


def _inductor_cache() -> str:
    try:
        from torch._inductor.runtime.cache_dir_utils import cache_dir

        return cache_dir()
    except Exception:  # noqa: BLE001 - another torch layout: the default place
        return os.environ.get("TORCHINDUCTOR_CACHE_DIR",
                              os.path.join(tempfile.gettempdir(), f"torchinductor_{os.environ.get('USER', 'user')}"))


def compile_key(cfg, device) -> str:
    """What a compilation depends on: torch, the GPU, the network and batch shapes, the precision settings."""
    name = torch.cuda.get_device_name(device) if torch.device(device).type == "cuda" else "cpu"
    rt = cfg.runtime
    return json.dumps([torch.__version__, name, dataclasses.asdict(cfg.network), dataclasses.asdict(cfg.batches),
                       rt.amp, rt.tf32, rt.cuda_graph], sort_keys=True)


def _cached_record(key: str):
    """(seconds, warm) of the last compile recorded for ``key`` while the inductor cache it filled is still there,
    else None (a bare number, as files before the warm flag hold, is a cold compile's)."""
    folder = _inductor_cache()
    try:
        with open(os.path.join(folder, _RECORD)) as f:
            seen = json.load(f).get(key)
        if seen is None:
            return None
        with os.scandir(os.path.join(folder, "fxgraph")) as entries:
            if not any(entries):
                return None
        if isinstance(seen, dict):
            return float(seen["s"]), bool(seen["warm"])
        return float(seen), False
    except (OSError, ValueError, TypeError, AttributeError, KeyError):
        return None


def compile_cached(key: str) -> bool:
    """Whether this machine's inductor cache holds a compile of ``key``'s shapes (the next one is warm)."""
    return _cached_record(key) is not None


def compile_estimate(key: str) -> float:
    """Seconds the compilation of a run with ``key`` is expected to take here: a warm compile's recorded time, a
    cold one's times ``WARM_SHARE`` (its caches serve this one), or a fresh machine's time without a record."""
    rec = _cached_record(key)
    if rec is None:
        return COLD_COMPILE_S
    seconds, warm = rec
    return seconds if warm else WARM_SHARE * seconds


def compile_pays(key: str, seconds_left: float) -> tuple:
    """(compile?, expected compile seconds) for a budgeted run with ``seconds_left`` for set-up and steps."""
    est = compile_estimate(key)
    return seconds_left > COMPILE_PAYOFF * est, est


def record_compile(key: str, seconds: float, *, warm: bool) -> None:
    """Keep how long this run's compilation took, and whether the cache held its shapes before (``warm``), next
    to the inductor cache (best effort, atomic)."""
    folder = _inductor_cache()
    path = os.path.join(folder, _RECORD)
    try:
        try:
            with open(path) as f:
                seen = json.load(f)
        except (OSError, ValueError):
            seen = {}
        seen[key] = {"s": round(float(seconds), 2), "warm": bool(warm)}
        os.makedirs(folder, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=".neurogf_compile")
        with os.fdopen(fd, "w") as f:
            json.dump(seen, f)
        os.replace(tmp, path)
    except OSError:
        pass


class GraphedStep:
    """One stage's update ``update(idx) -> terms``: ``GRAPH_WARMUP`` eager steps on a side stream (allocator
    and cuBLAS warm-up), then captured once as a CUDA graph and replayed with the new index vectors copied in."""

    def __init__(self, update, zero_grad, device: torch.device):
        self.update, self.zero_grad, self.device = update, zero_grad, device
        self.side = torch.cuda.Stream(device)  # the warm-up steps' stream, one for all of them
        self.eager_steps = 0
        self.graph = None  # (CUDAGraph, static index vectors, static loss terms)

    def __call__(self, idx: dict) -> dict:
        if self.graph is None and self.eager_steps >= GRAPH_WARMUP:
            self.graph = self._capture(idx)
        if self.graph is not None:
            graph, static_idx, terms = self.graph
            for k, v in idx.items():
                static_idx[k].copy_(v)
            graph.replay()
            return terms
        side = self.side
        side.wait_stream(torch.cuda.current_stream(self.device))
        with torch.cuda.stream(side):
            self.zero_grad(set_to_none=True)
            terms = self.update(idx)
        torch.cuda.current_stream(self.device).wait_stream(side)
        self.eager_steps += 1
        return terms

    def _capture(self, idx: dict):
        static_idx = {k: v.clone() for k, v in idx.items()}
        self.zero_grad(set_to_none=True)  # gradients are then allocated inside the graph's pool
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            terms = self.update(static_idx)
        return graph, static_idx, terms
