"""The NeuroGF networks in PyTorch, with the official layer layout and parameter names.

Every layer is a bias-free linear map, optionally followed by BatchNorm and ReLU, so the released
``*_final.pth`` and querier checkpoints load with ``load_state_dict(strict=True)``.
Widths scale with D; D=256 is the released layout (lifting 3-64-128-256, heads 256-64-64-1,
guidance 512-256, path head 259-128-64-32-3).
"""
from __future__ import annotations

import torch
from torch import nn

__all__ = ["FC", "PointMLP", "NeuroGFNet", "SdfQuerier", "widths"]

SUPPORTED_D = (64, 128, 256, 512)


class FC(nn.Module):
    """Bias-free Linear -> optional BatchNorm1d -> optional ReLU (state-dict keys ``linear.*``, ``bn.*``)."""

    def __init__(self, ic: int, oc: int, bn: bool = True, relu: bool = True):
        super().__init__()
        self.linear = nn.Linear(ic, oc, bias=False)
        self.bn = nn.BatchNorm1d(oc) if bn else None
        self.act = nn.ReLU(inplace=True) if relu else None

    def forward(self, x):
        x = self.linear(x)
        if self.bn is not None:
            x = self.bn(x)
        return self.act(x) if self.act is not None else x


class PointMLP(nn.Module):
    """Per-point bias-free layer stored as a 1x1 Conv2d, as in the official code (keys ``conv.*``, ``bn.*``).

    Input (B, N, C). BatchNorm statistics pool over all B*N points, like the original.
    """

    def __init__(self, ic: int, oc: int, bn: bool = True, relu: bool = True):
        super().__init__()
        self.conv = nn.Conv2d(ic, oc, kernel_size=1, bias=False)
        self.bn = nn.BatchNorm2d(oc) if bn else None
        self.act = nn.ReLU(inplace=True) if relu else None

    def forward(self, x):
        b, n, c = x.shape
        y = self.conv(x.permute(0, 2, 1).unsqueeze(-1))
        if self.bn is not None:
            y = self.bn(y)
        if self.act is not None:
            y = self.act(y)
        return y.squeeze(-1).permute(0, 2, 1)


def widths(D: int) -> dict:
    if D not in SUPPORTED_D:
        raise ValueError(f"D must be one of {SUPPORTED_D}, got {D}")
    return {
        "lifting": [3, D // 4, D // 2, D],
        "head": [D, D // 4, D // 4, 1],
        "guidance": [2 * D, D],
        "path": [D + 3, D // 2, D // 4, D // 8, 3],
    }


def _head(ws):
    layers = [FC(a, b) for a, b in zip(ws[:-2], ws[1:-1])]
    return nn.Sequential(*layers, FC(ws[-2], ws[-1], bn=False, relu=False))


class NeuroGFNet(nn.Module):
    """Overfitted NeuroGF: shared point lifting, distance head, SDF head and path head."""

    def __init__(self, D: int = 256):
        super().__init__()
        w = widths(D)
        self.D = D
        lw = w["lifting"]
        self.lifting = nn.Sequential(*[FC(a, b) for a, b in zip(lw[:-1], lw[1:])])
        self.sdf_head = _head(w["head"])
        self.gdf_head = _head(w["head"])
        self.cdw_fc = FC(*w["guidance"])
        pw = w["path"]
        self.spf_head = nn.Sequential(
            *[PointMLP(a, b) for a, b in zip(pw[:-2], pw[1:-1])], PointMLP(pw[-2], pw[-1], bn=False, relu=False)
        )

    # Each query kind on its own; training may instead lift all points in one call (shared BN statistics).
    def embed(self, x):
        return self.lifting(x)

    def distance_from_embeddings(self, es, et):
        return self.gdf_head((es - et).abs()).squeeze(-1)

    def sdf_from_embeddings(self, e):
        return self.sdf_head(e).squeeze(-1)

    def path_from_embeddings(self, es, et, lines):
        """lines: (N, M, 3) straight-line samples; returns (N, M, 3) absolute path points."""
        g = self.cdw_fc(torch.cat([es, et], dim=-1))
        g = g.unsqueeze(1).expand(-1, lines.shape[1], -1)
        return self.spf_head(torch.cat([lines, g], dim=-1))

    def distance(self, p, q):
        e = self.embed(torch.cat([p, q], 0))
        return self.distance_from_embeddings(e[: len(p)], e[len(p):])

    def sdf(self, x):
        return self.sdf_from_embeddings(self.embed(x))

    def path(self, p, q, m: int = 128):
        e = self.embed(torch.cat([p, q], 0))
        return self.path_from_embeddings(e[: len(p)], e[len(p):], straight_lines(p, q, m))


def straight_lines(p, q, m: int):
    """m equally spaced points from p to q, both ends included: (N, 3), (N, 3) -> (N, m, 3)."""
    t = torch.linspace(0.0, 1.0, m, dtype=p.dtype, device=p.device).view(1, m, 1)
    return p.unsqueeze(1) + t * (q - p).unsqueeze(1)


class SdfQuerier(nn.Module):
    """Separate SDF network used as a frozen surface prior during training (keys ``fc.{0..6}``)."""

    WIDTHS = (3, 32, 64, 128, 256, 512, 128, 1)

    def __init__(self):
        super().__init__()
        w = self.WIDTHS
        self.fc = nn.Sequential(*[FC(a, b) for a, b in zip(w[:-2], w[1:-1])], FC(w[-2], w[-1], bn=False, relu=False))

    def forward(self, x):
        return self.fc(x).squeeze(-1)
