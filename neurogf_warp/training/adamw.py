"""AdamW without ``torch.optim``: the same update, from torch's ``_foreach`` tensor ops.

Every ``torch.optim`` optimizer imports ``torch._dynamo`` on its first step; in a fresh process on a GPU machine
that took 3.8-5.0 s of a 10 s training call (``benchmarks/results/bakeoff_setup10_h200_2026-11-29.json``). This
class does the decoupled-weight-decay Adam update of ``torch.optim.AdamW`` (amsgrad off) with tensor ops only, so a
CUDA graph can capture it (the learning rate may be a 0-d device tensor, the step counts live on the device), and
its ``state_dict`` has ``torch.optim.AdamW``'s layout, so checkpoints of either load into the other.
"""
from __future__ import annotations

import torch

__all__ = ["AdamW"]


class AdamW:
    """``torch.optim.AdamW(params, lr, betas, eps, weight_decay)``'s update and state, without ``torch.optim``.

    Parameters
    ----------
    params : iterable of tensors, or of dicts {"params": [...], other group settings}
    lr : float, or a 0-d tensor on the parameters' device (a CUDA graph then replays with its current value)
    betas, eps, weight_decay : as ``torch.optim.AdamW``
    """

    def __init__(self, params, lr=1e-3, betas=(0.9, 0.999), eps=1e-8, weight_decay=1e-2):
        defaults = {"lr": lr, "betas": tuple(betas), "eps": float(eps), "weight_decay": float(weight_decay)}
        params = list(params)
        groups = params if params and isinstance(params[0], dict) else [{"params": params}]
        self.param_groups = [{**defaults, **g, "params": list(g["params"])} for g in groups]
        self.state = {}  # parameter -> {"step", "exp_avg", "exp_avg_sq"}

    def _state(self, p: torch.Tensor) -> dict:
        s = self.state.get(p)
        if s is None:
            s = self.state[p] = {"step": torch.zeros((), dtype=torch.float32, device=p.device),
                                 "exp_avg": torch.zeros_like(p, memory_format=torch.preserve_format),
                                 "exp_avg_sq": torch.zeros_like(p, memory_format=torch.preserve_format)}
        return s

    @torch.no_grad()
    def step(self) -> None:
        """One update of every parameter that has a gradient."""
        for g in self.param_groups:
            ps = [p for p in g["params"] if p.grad is not None]
            if not ps:
                continue
            grads = [p.grad for p in ps]
            states = [self._state(p) for p in ps]
            m, v = [s["exp_avg"] for s in states], [s["exp_avg_sq"] for s in states]
            steps = [s["step"] for s in states]
            (b1, b2), lr, eps, wd = g["betas"], g["lr"], g["eps"], g["weight_decay"]
            torch._foreach_add_(steps, 1.0)
            if wd:
                torch._foreach_mul_(ps, 1.0 - lr * wd)
            torch._foreach_lerp_(m, grads, 1.0 - b1)
            torch._foreach_mul_(v, b2)
            torch._foreach_addcmul_(v, grads, grads, 1.0 - b2)
            # step size lr / (1 - b1^t) and denominator sqrt(v) / sqrt(1 - b2^t) + eps, per parameter on the device
            t = [s.to(p.dtype) for s, p in zip(steps, ps)]  # the bias corrections in the parameters' precision
            size, root = torch._foreach_pow(b1, t), torch._foreach_pow(b2, t)
            for x in (size, root):  # 1 - beta^t
                torch._foreach_neg_(x)
                torch._foreach_add_(x, 1.0)
            torch._foreach_reciprocal_(size)
            torch._foreach_mul_(size, lr)
            torch._foreach_sqrt_(root)
            denom = torch._foreach_sqrt(v)
            torch._foreach_div_(denom, root)
            torch._foreach_add_(denom, eps)
            update = torch._foreach_div(m, denom)
            torch._foreach_mul_(update, size)
            torch._foreach_sub_(ps, update)

    def zero_grad(self, set_to_none: bool = True) -> None:
        for g in self.param_groups:
            for p in g["params"]:
                if p.grad is None:
                    continue
                if set_to_none:
                    p.grad = None
                else:
                    p.grad.zero_()

    def state_dict(self) -> dict:
        """``torch.optim.AdamW.state_dict()``'s layout: parameters numbered in group order."""
        index, groups, n = {}, [], 0
        for g in self.param_groups:
            ids = list(range(n, n + len(g["params"])))
            index.update({id(p): i for p, i in zip(g["params"], ids)})
            groups.append({**{k: v for k, v in g.items() if k != "params"}, "amsgrad": False, "maximize": False,
                           "params": ids})
            n += len(ids)
        state = {index[id(p)]: dict(s) for p, s in self.state.items()}
        return {"state": state, "param_groups": groups}

    def load_state_dict(self, sd: dict) -> None:
        """A ``state_dict`` of this class or of ``torch.optim.AdamW`` (same parameters, same order)."""
        params = [p for g in self.param_groups for p in g["params"]]
        if len(sd["param_groups"]) != len(self.param_groups) or \
                sum(len(g["params"]) for g in sd["param_groups"]) != len(params):
            raise ValueError("the optimizer state is of other parameter groups than this optimizer's: it cannot "
                             "be loaded here (a checkpoint of another network or stage?)")
        for g, saved in zip(self.param_groups, sd["param_groups"]):
            for k in ("lr", "betas", "eps", "weight_decay"):
                g[k] = tuple(saved[k]) if k == "betas" else saved[k]
        self.state = {}
        for i, s in sd["state"].items():
            p = params[int(i)]
            self.state[p] = {"step": torch.as_tensor(s["step"], dtype=torch.float32).to(p.device).reshape(()),
                             "exp_avg": s["exp_avg"].to(p.device, p.dtype).clone(),
                             "exp_avg_sq": s["exp_avg_sq"].to(p.device, p.dtype).clone()}
