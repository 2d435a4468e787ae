"""The NeuroGF networks in PyTorch, with the official layer layout and parameter names.

Every layer is a bias-free linear map, optionally followed by BatchNorm and ReLU, so the released
``*_final.pth`` and querier checkpoints load with ``load_state_dict(strict=True)``.
Widths scale with D; D=256 is the released layout (lifting 3-64-128-256, heads 256-64-64-1,
guidance 512-256, path head 259-128-64-32-3).

Seven options (not in the paper; all off reproduces it exactly, and released checkpoints load that way):
  fourier=L     the lifting sees [x, sin(2^k pi x), cos(2^k pi x)], k < L (3 + 6L inputs) instead of x;
  euclid=True   distance = |p - q| + gdf_head(|e_p - e_q|): the head learns only the excess over the
                straight line, so it needs the query points as well as their embeddings;
  path_residual=True  the path head outputs offsets from the straight line instead of absolute points;
  path_window=True  (with path_residual) the offsets are scaled by sin(pi t), t in [0, 1] along the line, so a
                path starts exactly at p and ends exactly at q;
  path_width=2  the path head's hidden layers twice as wide (D/2, D/4, D/8 -> D, D/2, D/4);
  norm="none"   the lifting, the distance and SDF heads and the guidance layer without BatchNorm: each layer
                gets a bias instead and He initialization (a leaner training step; the path head keeps BatchNorm);
  hash_levels=n the lifting also sees a multiresolution hash-grid encoding of the point (``HashGrid``: n levels
                of trainable features, trilinearly interpolated), appended to its Fourier inputs;
  landmarks=K   the distance head also sees the exact distances of both points to K landmark vertices
                (``Landmarks``): |T(p) - T(q)| per landmark and the triangle-inequality bounds, and the straight
                line under the head's output becomes max(|p - q|, lower bound) (vertex queries only);
                ``landmark_floor`` scales that bound, ``landmark_bracket`` puts the output between it and the upper
                bound (floor + sigmoid(head) x (upper - floor); with ``landmark_bracket_log``,
                floor x (upper / floor) ** sigmoid(head)); ``landmark_pair_inputs`` also gives the head |p - q| and
                log(upper / floor).
Model files store all of them. ``norm`` and ``hash_levels`` train only for the bake-off (no inference kernel runs
them); landmark networks (linear bracket or none, without pair inputs) answer distance queries on the per-thread
float32 kernels (precision "fp32") from the model's table (``Model.landmarks``), not on the tensor-core kernels.
"""
from __future__ import annotations

import math

import torch
from torch import nn

from neurogf_warp.common.checks import InputError

__all__ = ["FC", "PointMLP", "NeuroGFNet", "SdfQuerier", "HashGrid", "Landmarks", "widths", "fourier_features",
           "NORMS"]

SUPPORTED_D = (64, 128, 256, 512)
MAX_FOURIER = 8
NORMS = ("batch", "none")
MAX_HASH_LEVELS = 16
MAX_LANDMARKS = 256
LANDMARK_WIDTH_MAX = 8.0  # log(upper / floor) as a head input stops here (p = q; pieces no landmark reaches)
LANDMARK_UNREACHED = 4.0  # a landmark table's entry across components (+inf): the normalized mesh fits the unit sphere


class FC(nn.Module):
    """Bias-free Linear -> optional BatchNorm1d -> optional ReLU (state-dict keys ``linear.*``, ``bn.*``).

    ``norm="none"`` drops the BatchNorm of a normalized layer: the Linear then has a bias (BatchNorm's shift
    was the only offset) and He-normal weights, so that activations keep their scale through the ReLUs."""

    def __init__(self, ic: int, oc: int, bn: bool = True, relu: bool = True, norm: str = "batch"):
        super().__init__()
        plain = bn and norm == "none"
        self.linear = nn.Linear(ic, oc, bias=plain)
        self.bn = nn.BatchNorm1d(oc) if bn and not plain else None
        self.act = nn.ReLU(inplace=True) if relu else None
        if plain:
            nn.init.kaiming_normal_(self.linear.weight, nonlinearity="relu" if relu else "linear")
            nn.init.zeros_(self.linear.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, ic) -> (B, oc)."""
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

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, N, ic) -> (B, N, oc)."""
        b, n, c = x.shape
        y = self.conv(x.permute(0, 2, 1).unsqueeze(-1))
        if self.bn is not None:
            y = self.bn(y)
        if self.act is not None:
            y = self.act(y)
        return y.squeeze(-1).permute(0, 2, 1)


def widths(D: int, path_width: int = 1) -> dict:
    """Layer widths of each part for embedding width ``D``: {"lifting", "head", "guidance", "path"} -> lists."""
    if D not in SUPPORTED_D:
        raise InputError(f"D must be one of {SUPPORTED_D}, got {D}")
    if path_width not in (1, 2) or path_width * D > 512:
        raise InputError(f"path_width must be 1 or 2 (2 only for D <= 256), got {path_width} with D={D}")
    w = path_width
    return {
        "lifting": [3, D // 4, D // 2, D],
        "head": [D, D // 4, D // 4, 1],
        "guidance": [2 * D, D],
        "path": [D + 3, w * D // 2, w * D // 4, w * D // 8, 3],
    }


def _head(ws, norm="batch"):
    layers = [FC(a, b, norm=norm) for a, b in zip(ws[:-2], ws[1:-1])]
    return nn.Sequential(*layers, FC(ws[-2], ws[-1], bn=False, relu=False))


class HashGrid(nn.Module):
    """Multiresolution hash-grid encoding of points in [-1, 1]^3 (instant-NGP style), in plain torch.

    Level l is a grid of resolution ``base * g**l`` (g fills the span up to ``finest``) over the cube; each
    corner owns ``features`` trainable numbers, stored densely while the level's corners fit the table and
    hashed into ``2**log2_size`` rows past that. A point gets, per level, the trilinear blend of its cell's 8
    corners. Gathers use ``index_select`` so that the backward pass is an atomic ``index_add`` (no host
    synchronization: the step stays capturable as a CUDA graph).

    Parameters: levels >= 1; features per level; log2_size of each level's table; base and finest resolutions.
    Input (N, 3) points (normalized frame, coordinates clamped to [-1, 1]) -> (N, levels * features).
    """

    PRIMES = (1, 2654435761, 805459861)

    def __init__(self, levels: int, features: int = 2, log2_size: int = 18, base: int = 16, finest: int = 1024):
        super().__init__()
        if not (isinstance(levels, int) and 1 <= levels <= MAX_HASH_LEVELS):
            raise InputError(f"hash_levels must be an integer in 1..{MAX_HASH_LEVELS}, got {levels!r}")
        self.levels, self.features, self.size = levels, features, 1 << log2_size
        g = math.exp((math.log(finest) - math.log(base)) / max(levels - 1, 1))
        res = [int(math.floor(base * g ** i)) for i in range(levels)]
        # buffers, not lists: a captured graph must not copy host data; non-persistent: rebuilt from the options
        self.register_buffer("res", torch.tensor(res, dtype=torch.float32), persistent=False)
        self.register_buffer("stride", torch.tensor([r + 1 for r in res], dtype=torch.long), persistent=False)
        self.register_buffer("dense", torch.tensor([(r + 1) ** 3 <= self.size for r in res]), persistent=False)
        self.register_buffer("offset", torch.arange(levels, dtype=torch.long) * self.size, persistent=False)
        self.register_buffer("corners", torch.tensor([[(c >> k) & 1 for k in range(3)] for c in range(8)]),
                             persistent=False)
        self.register_buffer("primes", torch.tensor(self.PRIMES, dtype=torch.long), persistent=False)
        # small uniform start, as instant-NGP: the lifting first sees its Fourier inputs, the grid grows in
        self.table = nn.Parameter(torch.empty(levels * self.size, features).uniform_(-1e-4, 1e-4))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(N, 3) -> (N, levels * features)."""
        n = x.shape[0]
        u = ((x.clamp(-1.0, 1.0) + 1.0) * 0.5).unsqueeze(1) * self.res.view(1, -1, 1)  # (N, L, 3) grid units
        i0 = torch.minimum(u.floor(), self.res.view(1, -1, 1) - 1)  # a point at +1 blends its last cell's corners
        f = u - i0
        c = i0.long().unsqueeze(2) + self.corners.view(1, 1, 8, 3)  # (N, L, 8, 3)
        s = self.stride.view(1, -1, 1)
        dense = c[..., 0] + s * (c[..., 1] + s * c[..., 2])
        h = c * self.primes
        hashed = (h[..., 0] ^ h[..., 1] ^ h[..., 2]) & (self.size - 1)
        idx = torch.where(self.dense.view(1, -1, 1), dense, hashed) + self.offset.view(1, -1, 1)
        cw = self.corners.view(1, 1, 8, 3).to(f.dtype)
        w = (cw * f.unsqueeze(2) + (1 - cw) * (1 - f.unsqueeze(2))).prod(-1)  # (N, L, 8) trilinear weights
        v = self.table.index_select(0, idx.reshape(-1)).view(n, self.levels, 8, self.features)
        return (w.unsqueeze(-1) * v).sum(2).reshape(n, self.levels * self.features)


class _HashInput(nn.Module):
    """Appends ``HashGrid`` features of the point (the first 3 input columns) to the lifting's inputs."""

    def __init__(self, grid: HashGrid):
        super().__init__()
        self.grid = grid

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        return torch.cat([h, self.grid(h[:, :3])], dim=-1)


class Landmarks(nn.Module):
    """Exact geodesic distances from K landmark vertices, looked up for points that are mesh vertices.

    ``set_table(xyz, table)`` stores the vertices (V, 3) (normalized frame, float32) and their distances (V, K)
    to the landmarks (normalized units). A point is matched to the vertex with bit-identical coordinates (the
    training rows and the scoring use the same float32 vertex array); an unmatched point gets NaN features, so
    that a query off the vertices shows as a non-finite distance, never as a plausible wrong one.
    Buffers are not persistent: the table is rebuilt from the mesh, never read from a checkpoint.
    """

    PRIMES = (73856093, 19349663, 83492791)

    def __init__(self, k: int):
        super().__init__()
        self.k = k
        for name, shape, dt in (("xyz", (0, 3), torch.float32), ("table", (0, k), torch.float32),
                                ("keys", (0,), torch.long), ("order", (0,), torch.long)):
            self.register_buffer(name, torch.zeros(shape, dtype=dt), persistent=False)

    def _key(self, x: torch.Tensor) -> torch.Tensor:
        b = x.contiguous().view(torch.int32).long()
        return (b[:, 0] * self.PRIMES[0]) ^ (b[:, 1] * self.PRIMES[1]) ^ (b[:, 2] * self.PRIMES[2])

    def set_table(self, xyz: torch.Tensor, table: torch.Tensor) -> None:
        """xyz : (V, 3) float32 vertices; table : (V, K) float32 distances to the landmarks."""
        if table.shape != (len(xyz), self.k):
            raise InputError(f"landmark table must be ({len(xyz)}, {self.k}), got {tuple(table.shape)}")
        dev = self.table.device
        self.xyz = xyz.to(dev, torch.float32).contiguous()
        self.table = table.to(dev, torch.float32).contiguous()
        keys = self._key(self.xyz)
        self.keys, self.order = torch.sort(keys)

    def match(self, x: torch.Tensor) -> tuple:
        """(N, 3) points -> ((N,) table row of each, (N,) bool: the row's vertex is the point, bit for bit)."""
        if len(self.keys) == 0:
            raise InputError("this network's landmark table is empty: it is set from the mesh before training")
        v = self.order[torch.searchsorted(self.keys, self._key(x)).clamp_max(len(self.keys) - 1)]
        return v, (self.xyz[v] == x).all(-1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(N, 3) points -> (N, K) distances to the landmarks (NaN rows for points that are not vertices)."""
        v, hit = self.match(x)
        rows = self.table[v]
        return torch.where(hit[:, None], rows, rows.new_full((), float("nan")))


def fourier_features(x: torch.Tensor, L: int) -> torch.Tensor:
    """[x, sin(2^k pi x), cos(2^k pi x) for k < L]: (..., 3) -> (..., 3 + 6L); L = 0 returns x."""
    if L == 0:
        return x
    f = x.unsqueeze(-1) * (math.pi * 2.0 ** torch.arange(L, dtype=x.dtype, device=x.device))  # (..., 3, L)
    return torch.cat([x, torch.sin(f).flatten(-2), torch.cos(f).flatten(-2)], dim=-1)


_TINY = 1e-12  # distances (normalized units) clamped here before a log: p = q gives a floor of 0


def _log_ratio(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """log(a / b) of two non-negative distance tensors, each clamped at ``_TINY``."""
    return torch.log(torch.clamp(a, min=_TINY)) - torch.log(torch.clamp(b, min=_TINY))


class NeuroGFNet(nn.Module):
    """Overfitted NeuroGF: shared point lifting, distance head, SDF head and path head."""

    def __init__(self, D: int = 256, fourier: int = 0, euclid: bool = False, path_residual: bool = False,
                 path_width: int = 1, path_window: bool = False, norm: str = "batch", hash_levels: int = 0,
                 landmarks: int = 0, landmark_floor: float = 1.0, landmark_bracket: bool = False,
                 landmark_bracket_log: bool = False, landmark_pair_inputs: bool = False):
        super().__init__()
        w = widths(D, path_width)
        if not (isinstance(fourier, int) and 0 <= fourier <= MAX_FOURIER):
            raise InputError(f"fourier must be an integer in 0..{MAX_FOURIER}, got {fourier!r}")
        if norm not in NORMS:
            raise InputError(f"norm must be one of {NORMS}, got {norm!r}")
        if not (isinstance(hash_levels, int) and 0 <= hash_levels <= MAX_HASH_LEVELS):
            raise InputError(f"hash_levels must be an integer in 0..{MAX_HASH_LEVELS} (0: no hash grid), "
                             f"got {hash_levels!r}")
        self.D, self.fourier, self.euclid, self.path_residual = D, fourier, bool(euclid), bool(path_residual)
        self.path_width, self.path_window = path_width, bool(path_window)
        if not (isinstance(landmarks, int) and 0 <= landmarks <= MAX_LANDMARKS):
            raise InputError(f"landmarks must be an integer in 0..{MAX_LANDMARKS} (0: none), got {landmarks!r}")
        if not (isinstance(landmark_floor, (int, float)) and 0.0 <= landmark_floor <= 1.0):
            raise InputError(f"landmark_floor must be a number in 0..1 (0: no floor), got {landmark_floor!r}")
        self.norm, self.hash_levels, self.landmarks = norm, hash_levels, landmarks
        self.landmark_floor, self.landmark_bracket = float(landmark_floor), bool(landmark_bracket)
        if landmark_bracket_log and not landmark_bracket:
            raise InputError("landmark_bracket_log sets the form of the bracket: it needs landmark_bracket=True")
        self.landmark_bracket_log = bool(landmark_bracket_log)
        if landmark_pair_inputs and not landmarks:
            raise InputError("landmark_pair_inputs adds inputs to the landmark features: it needs landmarks > 0")
        self.landmark_pair_inputs = bool(landmark_pair_inputs)
        if self.path_window and not self.path_residual:
            raise InputError("path_window scales the path offsets: it needs path_residual=True")
        lw = [3 + 6 * fourier] + w["lifting"][1:]
        encode = []
        if hash_levels:
            grid = HashGrid(hash_levels)
            encode, lw[0] = [_HashInput(grid)], lw[0] + grid.levels * grid.features
        self.lifting = nn.Sequential(*encode, *[FC(a, b, norm=norm) for a, b in zip(lw[:-1], lw[1:])])
        self.sdf_head = _head(w["head"], norm)
        # landmark features: |T(p) - T(q)| per landmark, the lower and the upper triangle bound
        self.landmark_table = Landmarks(landmarks) if landmarks else None
        extra = (landmarks + 2 + 2 * self.landmark_pair_inputs) if landmarks else 0
        self.gdf_head = _head([w["head"][0] + extra] + w["head"][1:], norm)
        self.cdw_fc = FC(*w["guidance"], norm=norm)
        pw = w["path"]
        self.spf_head = nn.Sequential(
            *[PointMLP(a, b) for a, b in zip(pw[:-2], pw[1:-1])], PointMLP(pw[-2], pw[-1], bn=False, relu=False)
        )

    @property
    def options(self) -> dict:
        """What a model file must record besides the weights to rebuild this network."""
        out = {"fourier": self.fourier, "euclid": self.euclid, "path_residual": self.path_residual,
               "path_width": self.path_width, "path_window": self.path_window}
        # recorded only when set: files of the default design stay readable by every version
        if self.norm != "batch":
            out["norm"] = self.norm
        if self.hash_levels:
            out["hash_levels"] = self.hash_levels
        if self.landmarks:
            out["landmarks"] = self.landmarks
            if self.landmark_floor != 1.0:
                out["landmark_floor"] = self.landmark_floor
            if self.landmark_bracket:
                out["landmark_bracket"] = True
            if self.landmark_bracket_log:
                out["landmark_bracket_log"] = True
            if self.landmark_pair_inputs:
                out["landmark_pair_inputs"] = True
        return out

    def path_output(self, out: torch.Tensor, lines: torch.Tensor) -> torch.Tensor:
        """Path points from the head's output: absolute (paper), or offsets from the lines (optionally windowed)."""
        if not self.path_residual:
            return out
        if self.path_window:
            t = torch.linspace(0.0, 1.0, lines.shape[1], dtype=lines.dtype, device=lines.device).view(1, -1, 1)
            out = out * torch.sin(math.pi * t)
        return lines + out

    # Each query kind on its own; training may instead lift all points in one call (shared BN statistics).
    def embed(self, x: torch.Tensor) -> torch.Tensor:
        """Point embeddings: (N, 3) normalized-frame points -> (N, D)."""
        return self.lifting(fourier_features(x, self.fourier))

    def distance_from_embeddings(self, es: torch.Tensor, et: torch.Tensor, p: torch.Tensor | None = None,
                                 q: torch.Tensor | None = None) -> torch.Tensor:
        """gdf_head(|e_p - e_q|) (+ |p - q| with ``euclid``, which then needs the points p, q).

        es, et : (N, D) embeddings; p, q : (N, 3) points -> (N,) distances, normalized units."""
        if self.landmarks:
            if p is None or q is None:
                raise InputError("this network reads landmark distances of its query points: pass p and q too")
            tp, tq = self.landmark_table(p), self.landmark_table(q)
            diff = (tp - tq).abs()
            lower, upper = diff.max(-1).values, (tp + tq).min(-1).values
            e = torch.linalg.vector_norm(p - q, dim=-1)
            floor = torch.maximum(e, self.landmark_floor * lower)
            parts = [(es - et).abs(), diff, lower[:, None], upper[:, None]]
            if self.landmark_pair_inputs:  # the pair's own scale and how wide its bracket is, relative to it
                parts += [e[:, None], torch.clamp(_log_ratio(upper, floor), max=LANDMARK_WIDTH_MAX)[:, None]]
            d = self.gdf_head(torch.cat(parts, dim=-1)).squeeze(-1)
            if self.landmark_bracket:  # the head picks a point between the floor and the upper bound
                top = torch.maximum(upper, floor)
                if self.landmark_bracket_log:  # geometric: a head error costs the same relative error at any scale
                    inside = torch.clamp(floor, min=_TINY) * torch.exp(torch.sigmoid(d) * _log_ratio(top, floor))
                    inside = torch.where(floor > 0, inside, floor)  # p = q: floor 0 stays 0
                else:
                    inside = floor + torch.sigmoid(d) * (top - floor)
                # a piece without landmarks (every entry unreached): the head on |p - q|, as the default network
                return torch.where(upper >= 2 * LANDMARK_UNREACHED, e + d, inside)
            if self.euclid:  # under the head: |p - q|, raised to landmark_floor x the landmarks' lower bound
                d = d + floor
            return d
        d = self.gdf_head((es - et).abs()).squeeze(-1)
        if self.euclid:
            if p is None or q is None:
                raise InputError("this network adds |p - q| to its distances: pass the query points p and q too")
            d = d + torch.linalg.vector_norm(p - q, dim=-1)
        return d

    def sdf_from_embeddings(self, e: torch.Tensor) -> torch.Tensor:
        """(N, D) embeddings -> (N,) signed distances, normalized units (negative inside)."""
        return self.sdf_head(e).squeeze(-1)

    def path_from_embeddings(self, es: torch.Tensor, et: torch.Tensor, lines: torch.Tensor) -> torch.Tensor:
        """es, et : (N, D) end embeddings; lines : (N, M, 3) straight-line samples -> (N, M, 3) path points."""
        g = self.cdw_fc(torch.cat([es, et], dim=-1))
        g = g.unsqueeze(1).expand(-1, lines.shape[1], -1)
        return self.path_output(self.spf_head(torch.cat([lines, g], dim=-1)), lines)

    def distance(self, p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """(N, 3), (N, 3) normalized points -> (N,) geodesic distances, normalized units."""
        e = self.embed(torch.cat([p, q], 0))
        return self.distance_from_embeddings(e[: len(p)], e[len(p):], p, q)

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        """(N, 3) normalized points -> (N,) signed distances (negative inside)."""
        return self.sdf_from_embeddings(self.embed(x))

    def path(self, p: torch.Tensor, q: torch.Tensor, m: int = 128) -> torch.Tensor:
        """(N, 3), (N, 3) normalized points -> (N, m, 3) path points from p to q."""
        e = self.embed(torch.cat([p, q], 0))
        return self.path_from_embeddings(e[: len(p)], e[len(p):], straight_lines(p, q, m))


def straight_lines(p: torch.Tensor, q: torch.Tensor, m: int) -> torch.Tensor:
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

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(N, 3) normalized points -> (N,) signed distances."""
        return self.fc(x).squeeze(-1)
