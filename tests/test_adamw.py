"""training.adamw.AdamW against torch.optim.AdamW in float64: the same parameters after many steps, with a float
or a device-tensor learning rate, and state dicts that load into each other."""
import subprocess
import sys

import pytest
import torch

from neurogf_warp.training.adamw import AdamW


def _params(seed: int):
    g = torch.Generator().manual_seed(seed)
    return [torch.randn(7, 5, generator=g, dtype=torch.float64, requires_grad=True),
            torch.randn(5, generator=g, dtype=torch.float64, requires_grad=True)]


def _run(opt, params, steps: int, seed, lr_sched=None, start: int = 0):
    """``steps`` updates from random gradients (``seed``: an int, or a Generator to go on drawing from)."""
    g = seed if isinstance(seed, torch.Generator) else torch.Generator().manual_seed(seed)
    for i in range(start, start + steps):
        if lr_sched is not None:
            lr_sched(opt, i)
        for p in params:
            p.grad = torch.randn(p.shape, generator=g, dtype=p.dtype)
        params[1].grad = None if i % 7 == 3 else params[1].grad  # a parameter without a gradient this step
        opt.step()
        opt.zero_grad(set_to_none=True)


@pytest.mark.parametrize("wd", [0.0, 0.05])
def test_the_update_is_torchs_adamw(wd):
    a, b = _params(1), _params(1)
    ours = AdamW(a, lr=3e-3, betas=(0.9, 0.99), eps=1e-8, weight_decay=wd)
    ref = torch.optim.AdamW(b, lr=3e-3, betas=(0.9, 0.99), eps=1e-8, weight_decay=wd)
    _run(ours, a, 60, seed=2)
    _run(ref, b, 60, seed=2)
    for x, y in zip(a, b):
        torch.testing.assert_close(x, y, rtol=1e-12, atol=1e-14)


def test_a_tensor_learning_rate_is_read_at_each_step():
    """The lr as a 0-d tensor filled before each step (how a captured CUDA graph replays) equals the float lr."""
    a, b = _params(3), _params(3)
    lr = torch.tensor(1e-2, dtype=torch.float64)
    ours = AdamW(a, lr=lr, weight_decay=0.01)
    ref = torch.optim.AdamW(b, lr=1e-2, weight_decay=0.01)

    def cosine(opt, i):
        value = 1e-2 * (0.5 + 0.5 * torch.cos(torch.tensor(i / 40 * 3.14159)).item())
        if opt is ours:
            lr.fill_(value)
        else:
            opt.param_groups[0]["lr"] = value

    _run(ours, a, 40, seed=4, lr_sched=cosine)
    _run(ref, b, 40, seed=4, lr_sched=cosine)
    for x, y in zip(a, b):
        torch.testing.assert_close(x, y, rtol=1e-12, atol=1e-14)


def test_state_dicts_load_into_each_other():
    """20 steps by one optimizer, its state into the other, 20 more: as 40 steps of torch's AdamW, both ways."""
    ref_p = _params(5)
    _run(torch.optim.AdamW(ref_p, lr=5e-3, weight_decay=0.02), ref_p, 40, seed=6)
    for first_kind, second_kind in ((torch.optim.AdamW, AdamW), (AdamW, torch.optim.AdamW)):
        p, g = _params(5), torch.Generator().manual_seed(6)
        first = first_kind(p, lr=5e-3, weight_decay=0.02)
        _run(first, p, 20, g)
        second = second_kind(p, lr=5e-3, weight_decay=0.02)
        second.load_state_dict(first.state_dict())
        _run(second, p, 20, g, start=20)
        for x, y in zip(p, ref_p):
            torch.testing.assert_close(x, y, rtol=1e-12, atol=1e-14)
    with pytest.raises(ValueError, match="other parameter groups"):
        AdamW(_params(5)[:1], lr=1e-3).load_state_dict(first.state_dict())


def test_no_torch_dynamo_import():
    script = ("import sys, torch\nfrom neurogf_warp.training.adamw import AdamW\n"
              "p = torch.zeros(3, requires_grad=True); o = AdamW([p], lr=0.1)\n"
              "p.grad = torch.ones(3); o.step(); o.zero_grad()\nprint('torch._dynamo' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip().endswith("False"), out.stderr[-2000:]
