"""CUDA speed-ups of a training step that keep its maths: TF32, torch.compile'd losses, CUDA graphs.

On the CPU none of them applies and a step runs eagerly. Under CUDA graphs a stage's whole step (gather,
forward, backward, fused AdamW update) is captured once and replayed; only the random index draws and the
learning rate (a device tensor) are set outside the graph, so replayed steps equal eager ones.
"""
from __future__ import annotations

import sys

import torch

__all__ = ["set_tf32", "sync", "CompiledLosses", "GraphedStep", "GRAPH_WARMUP"]

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


class GraphedStep:
    """One stage's update ``update(idx) -> terms``: ``GRAPH_WARMUP`` eager steps on a side stream (allocator
    and cuBLAS warm-up), then captured once as a CUDA graph and replayed with the new index vectors copied in."""

    def __init__(self, update, zero_grad, device: torch.device):
        self.update, self.zero_grad, self.device = update, zero_grad, device
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
        side = torch.cuda.Stream(self.device)
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
