"""The generalizable NeuroGF network (paper section "Extension to Generalizable Learning Frameworks") in torch.

Written from the paper's architecture description (and the released weights' shapes); parameter names
follow the released state_dict ``GenNeuroGF.pth`` so that it loads with ``strict=True``.

Structure (every "layer" is a bias-free 1x1 linear map, then BatchNorm, then ReLU, unless said otherwise):

- encoder (``backbone``), input a point cloud ``(B, N, 3)`` in the unit-sphere frame:
  - three EdgeConv blocks. For each point i: the k = 40 nearest points j in the block's *input* feature space
    (the point itself included, distance 0), the edge feature ``[f_i, f_j - f_i]``, the block's layers applied
    per edge, then the maximum over the k edges. Widths: block 1 ``6 -> 64 -> 64``, block 2 ``128 -> 64 -> 64``,
    block 3 ``128 -> 64``. Outputs f1, f2, f3 (64 each).
  - ``pw_embedding``: ``[f1, f2, f3]`` (192) -> 320 per point; the maximum over all points is the codeword (320).
  - ``mlp``: ``[codeword, f1, f2, f3]`` (512) -> 128 -> 128 per point: the per-point feature F (B, N, 128).
- query network, for a query point q: ``fuse([F[nn(q)], q])`` (131 -> 128), nn(q) = the nearest cloud point.
  For a pair (s, t): ``head(|fuse(s) - fuse(t)|)``: 128 -> 128 -> 64 -> 1, the last layer a plain bias-free
  linear map (no BatchNorm, no ReLU). The output is the ratio geodesic / Euclidean distance; the distance is
  ``ratio * |s - t|`` (so it is exactly 0 at s == t).

In eval mode every BatchNorm folds into its linear map: ``W' = diag(g / sqrt(var + eps)) W``,
``b' = beta - mean * g / sqrt(var + eps)`` (see :func:`folded_layers`); the Warp kernels use the folded form.
"""
from __future__ import annotations

import os
from collections import OrderedDict

import torch
from torch import nn

K_NEIGHBOURS = 40
BN_EPS = 1e-5


class PointLayer(nn.Module):
    """Per-point bias-free linear ``ic -> oc`` (a 1x1 Conv2d, as in the released weights) + optional BN + ReLU.

    Input ``(B, ic, N, K)`` (channels first; K = 1 for per-point layers); output ``(B, oc, N, K)``.
    """

    def __init__(self, ic: int, oc: int, bn: bool = True, relu: bool = True):
        super().__init__()
        self.conv = nn.Conv2d(ic, oc, kernel_size=1, bias=False)
        if bn:
            self.bn = nn.BatchNorm2d(oc, eps=BN_EPS)
        self.relu = relu

    def forward(self, x):
        x = self.conv(x)
        if hasattr(self, "bn"):
            x = self.bn(x)
        return torch.relu(x) if self.relu else x


def knn_indices(x: torch.Tensor, k: int, exact: bool | None = None) -> torch.Tensor:
    """Exact k nearest neighbours of every point among the same points, closest first, the point itself included.

    x: ``(B, N, C)`` features. Returns ``(B, N, k)`` int64 indices. With ``exact`` (default: for float64 input)
    the distances are computed as ``sqrt(sum((x_i - x_j)^2))`` (``cdist`` without the matrix-product shortcut,
    which loses digits and can swap near ties); otherwise by the faster matrix-product form (training, float32).
    Ties are broken by the smaller index (a stable sort), the rule the Warp kernel follows too.
    """
    _, n, _ = x.shape
    if n < k:
        raise ValueError(f"a point cloud needs at least k={k} points for the neighbour graph, got {n}")
    if exact is None:
        exact = x.dtype == torch.float64
    mode = "donot_use_mm_for_euclid_dist" if exact else "use_mm_for_euclid_dist"
    with torch.no_grad():  # indices only: no graph through the (B, N, N) distances
        d = torch.cdist(x.detach(), x.detach(), compute_mode=mode)  # (B, N, N)
        if exact:
            return torch.sort(d, dim=-1, stable=True).indices[..., :k]
        return torch.topk(d, k, dim=-1, largest=False).indices


def edge_features(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """``[f_i, f_j - f_i]`` for every point i and neighbour j: x ``(B, N, C)``, idx ``(B, N, k)`` -> ``(B, 2C, N, k)``."""
    b, n, c = x.shape
    k = idx.shape[-1]
    nb = torch.gather(x, 1, idx.reshape(b, n * k, 1).expand(-1, -1, c)).reshape(b, n, k, c)
    xi = x[:, :, None, :].expand(-1, -1, k, -1)
    return torch.cat([xi, nb - xi], dim=-1).permute(0, 3, 1, 2).contiguous()


class EdgeConv(nn.Module):
    """One EdgeConv block: dynamic kNN graph in the input feature space, per-edge layers, max over neighbours."""

    def __init__(self, widths, k: int = K_NEIGHBOURS):
        super().__init__()
        layers = [PointLayer(a, b) for a, b in zip(widths[:-1], widths[1:])]
        # the released names: a two-layer block is ``smlp.0`` / ``smlp.1``, a one-layer block is ``smlp`` itself
        self.smlp = layers[0] if len(layers) == 1 else nn.Sequential(*layers)
        self.k = k

    def forward(self, x, idx=None):  # x (B, N, C) -> (B, N, C_out)
        if idx is None:
            idx = knn_indices(x, self.k)
        e = self.smlp(edge_features(x, idx))  # (B, C_out, N, k)
        return e.max(dim=-1).values.permute(0, 2, 1)


class Encoder(nn.Module):
    """Point cloud ``(B, N, 3)`` -> per-point features ``(B, N, 128)``."""

    def __init__(self, k: int = K_NEIGHBOURS):
        super().__init__()
        self.econv_1 = EdgeConv((6, 64, 64), k)
        self.econv_2 = EdgeConv((128, 64, 64), k)
        self.econv_3 = EdgeConv((128, 64), k)
        self.pw_embedding = PointLayer(192, 320)
        self.mlp = nn.Sequential(PointLayer(512, 128), PointLayer(128, 128))

    def forward(self, pts):
        f1 = self.econv_1(pts)
        f2 = self.econv_2(f1)
        f3 = self.econv_3(f2)
        f = torch.cat([f1, f2, f3], dim=-1)  # (B, N, 192)
        e = self.pw_embedding(f.permute(0, 2, 1)[..., None])[..., 0]  # (B, 320, N)
        cw = e.max(dim=-1, keepdim=True).values.expand(-1, -1, f.shape[1])
        g = torch.cat([cw, f.permute(0, 2, 1)], dim=1)[..., None]  # (B, 512, N, 1)
        return self.mlp(g)[..., 0].permute(0, 2, 1)


def nearest_indices(cloud: torch.Tensor, q: torch.Tensor, exact: bool | None = None) -> torch.Tensor:
    """Index of the nearest cloud point (Euclidean, ties -> smaller index) for each query.

    cloud ``(B, N, 3)``, q ``(B, M, 3)`` -> ``(B, M)`` int64. With ``exact`` (default: for float64 input) the
    distances are computed coordinate by coordinate (the rule the Warp kernels follow); otherwise by the
    matrix-product form, which may swap near ties (training in float32). The exact form is a slow elementwise
    kernel on CUDA: on an H100 it took 175 of the 210 ms of a 16-shape training step (16 x 4,096 queries x 2,048
    points); the matrix-product form takes a few ms.
    """
    if exact is None:
        exact = cloud.dtype == torch.float64
    mode = "donot_use_mm_for_euclid_dist" if exact else "use_mm_for_euclid_dist"
    with torch.no_grad():
        d = torch.cdist(q.detach(), cloud.detach(), compute_mode=mode)
        return d.argmin(dim=-1)  # torch.argmin returns the first minimum


class GenNeuroGF(nn.Module):
    """The whole generalizable network; ``forward(cloud, s, t)`` returns the ratio ``(B, M)``.

    cloud ``(B, N, 3)``, s and t ``(B, M, 3)``, all in the unit-sphere frame of the cloud.
    """

    def __init__(self, k: int = K_NEIGHBOURS):
        super().__init__()
        self.backbone = Encoder(k)
        self.fuse = PointLayer(131, 128)
        self.head = nn.Sequential(PointLayer(128, 128), PointLayer(128, 64), PointLayer(64, 1, bn=False, relu=False))

    def encode(self, cloud):
        return self.backbone(cloud)

    def fused(self, feats, cloud, q):
        """``fuse([F[nn(q)], q])``: feats ``(B, N, 128)``, q ``(B, M, 3)`` -> ``(B, M, 128)``."""
        nn_idx = nearest_indices(cloud, q)
        f = torch.gather(feats, 1, nn_idx[..., None].expand(-1, -1, feats.shape[-1]))
        x = torch.cat([f, q], dim=-1).permute(0, 2, 1)[..., None]
        return self.fuse(x)[..., 0].permute(0, 2, 1)

    def ratio_from_fused(self, fs, ft):
        x = (fs - ft).abs().permute(0, 2, 1)[..., None]
        return self.head(x)[:, 0, :, 0]

    def forward(self, cloud, s, t):
        feats = self.encode(cloud)
        # one fuse call for s and t together, so train-mode BN sees both (as the authors' single fused batch)
        ff = self.fused(feats, cloud, torch.cat([s, t], dim=1))
        m = s.shape[1]
        return self.ratio_from_fused(ff[:, :m], ff[:, m:])


def load_state_dict_file(path) -> OrderedDict[str, torch.Tensor]:
    """Read a plain state_dict (``torch.load(weights_only=True)``, mapped to the CPU)."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise ValueError(f"no such file: {path!r}; pass the path of GenNeuroGF.pth or a trained model file")
    obj = torch.load(path, map_location="cpu", weights_only=True)
    if isinstance(obj, dict) and "state_dict" in obj and isinstance(obj["state_dict"], dict):
        obj = obj["state_dict"]  # our own training files wrap the state_dict with metadata
    if not isinstance(obj, dict):
        raise ValueError(f"{path!r} does not hold a state_dict (found {type(obj).__name__})")
    return obj


def is_generalizable_state_dict(sd) -> bool:
    """True when a state_dict has the generalizable network's parameter names (for ``ngf.load`` dispatch)."""
    return isinstance(sd, dict) and "backbone.econv_1.smlp.0.conv.weight" in sd and "fuse.conv.weight" in sd


def load_network(path_or_state_dict, dtype=torch.float64) -> GenNeuroGF:
    """Build :class:`GenNeuroGF` from ``GenNeuroGF.pth`` (or a state_dict), strict key matching, eval mode."""
    sd = path_or_state_dict
    if not isinstance(sd, dict):
        sd = load_state_dict_file(sd)
    net = GenNeuroGF()
    try:
        net.load_state_dict(sd, strict=True)
    except RuntimeError as e:
        raise ValueError(f"the state_dict does not match the generalizable NeuroGF network: {e}") from None
    return net.to(dtype).eval()


def _fold(layer: PointLayer):
    w = layer.conv.weight.detach()[:, :, 0, 0].to(torch.float64)
    if hasattr(layer, "bn"):
        bn = layer.bn
        s = bn.weight.detach().double() / torch.sqrt(bn.running_var.detach().double() + bn.eps)
        return s[:, None] * w, bn.bias.detach().double() - bn.running_mean.detach().double() * s
    return w, torch.zeros(w.shape[0], dtype=torch.float64)


def folded_layers(net: GenNeuroGF) -> OrderedDict[str, tuple]:
    """Eval-mode BatchNorm folded into each linear map, float64: name -> (W (out, in), b (out,)).

    Names: ``e1a e1b e2a e2b e3 pw mlp0 mlp1 fuse head0 head1 head2``; ``e1a``'s input is the edge feature
    ``[f_i, f_j - f_i]`` (its first half acts on f_i).
    """
    bb = net.backbone
    out = OrderedDict()
    out["e1a"], out["e1b"] = _fold(bb.econv_1.smlp[0]), _fold(bb.econv_1.smlp[1])
    out["e2a"], out["e2b"] = _fold(bb.econv_2.smlp[0]), _fold(bb.econv_2.smlp[1])
    out["e3"] = _fold(bb.econv_3.smlp)
    out["pw"] = _fold(bb.pw_embedding)
    out["mlp0"], out["mlp1"] = _fold(bb.mlp[0]), _fold(bb.mlp[1])
    out["fuse"] = _fold(net.fuse)
    out["head0"], out["head1"], out["head2"] = _fold(net.head[0]), _fold(net.head[1]), _fold(net.head[2])
    return out


def is_generalizable_file(path) -> bool:
    """True when ``path`` is a torch file holding the generalizable network's state_dict (released or trained)."""
    try:
        return is_generalizable_state_dict(load_state_dict_file(path))
    except Exception:  # noqa: BLE001  (anything unreadable is simply not ours)
        return False
