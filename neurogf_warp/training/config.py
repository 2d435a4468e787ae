"""Training settings, nested by concern: network, schedule, batches, runtime and the dataset.

Every setting is a field of one of the groups below, and every field name is unique across the groups, so
``TrainConfig.set(lr=3e-3)``, ``--set lr=3e-3`` and ``--set schedule.lr=3e-3`` all reach the same field.
Values are converted from text and checked when set (``--set lr=abc`` fails at once, before any work).
Named starting points are in ``presets.py``.
"""
from __future__ import annotations

import dataclasses
import difflib
import json
import math
import os
from dataclasses import dataclass, field

from neurogf_warp.common.checks import InputError, integer
from neurogf_warp.dataset.build import DatasetSettings
from neurogf_warp.model.network import MAX_FOURIER, MAX_HASH_LEVELS, MAX_LANDMARKS, NORMS, SUPPORTED_D, NeuroGFNet
from neurogf_warp.training.stages import QUERIER_MAX, STAGE_TABLE

__all__ = ["TrainConfig", "NetworkConfig", "ScheduleConfig", "BatchConfig", "RuntimeConfig", "DatasetSettings",
           "STAGES", "RATIOS", "QUERIER_MAX", "DIST_LOSSES", "parse_assignments"]

# the stages in run order; what each one does is its entry in stages.STAGE_TABLE
STAGES = tuple(STAGE_TABLE)
# default steps of each stage per joint step (an explicit <stage>_steps overrides; Stage.max_steps caps)
RATIOS = {name: s.ratio for name, s in STAGE_TABLE.items()}
DIST_LOSSES = ("l1", "relative_global")
# settings of older versions that did not improve training, with the value that meant "off":
# old configs that carry that value still load; any other value is refused
REMOVED = {"refine_amp": True, "refine_batch_paths": None}
# dict settings (ratios, loss_weights) are flat; deeper nesting is refused before it can exhaust the stack
MAX_NESTING = 8


@dataclass
class NetworkConfig:
    """The network's width and options (``network.NeuroGFNet``; all options off = the paper's network)."""

    D: int = 256                   # embedding width: 64, 128, 256 or 512
    fourier: int = 2               # Fourier input octaves of the lifting (0..MAX_FOURIER)
    euclid: bool = True            # distance = |p - q| + head
    path_residual: bool = True     # path head outputs offsets from the straight line
    path_width: int = 1            # path head hidden widths x1 or x2
    path_window: bool = True       # path offsets x sin(pi t): exact end points (needs path_residual)
    # other field designs (benchmarks/bakeoff.py): landmarks (with or without the bracket) train and answer fp32
    # queries; norm, hash_levels and the bracket's two other forms train only for the bake-off
    norm: str = "batch"            # "batch" or "none" (biases + He init, no BatchNorm outside the path head)
    hash_levels: int = 0           # levels of a hash-grid encoding appended to the lifting's inputs (0: none)
    landmarks: int = 0             # exact distances to this many landmark vertices feed the distance head (0: none)
    landmark_floor: float = 1.0    # landmarks: the output's floor is max(|p - q|, this x their lower bound); 0: |p - q|
    landmark_bracket: bool = False  # landmarks: the output between that floor and their upper bound, the head choosing
    landmark_bracket_log: bool = False  # that bracket geometric: floor x (upper / floor) ** sigmoid(head)
    landmark_pair_inputs: bool = False  # landmarks: the distance head also sees |p - q| and log(upper / floor)

    def validate(self):
        if self.D not in SUPPORTED_D:
            raise ValueError(f"D must be one of {SUPPORTED_D}, got {self.D}")
        if not 0 <= self.fourier <= MAX_FOURIER:
            raise ValueError(f"fourier must be an integer in 0..{MAX_FOURIER}, got {self.fourier}")
        if self.path_width not in (1, 2) or self.path_width * self.D > 512:
            raise ValueError(f"path_width must be 1 or 2 (2 only for D <= 256), got {self.path_width} with D={self.D}")
        if self.path_window and not self.path_residual:
            raise ValueError("path_window scales the path offsets: it needs path_residual=True")
        if self.norm not in NORMS:
            raise ValueError(f"norm must be one of {NORMS}, got {self.norm!r}")
        if not 0 <= self.hash_levels <= MAX_HASH_LEVELS:
            raise ValueError(f"hash_levels must be an integer in 0..{MAX_HASH_LEVELS} (0: none), got {self.hash_levels}")
        if not 0 <= self.landmarks <= MAX_LANDMARKS:
            raise ValueError(f"landmarks must be an integer in 0..{MAX_LANDMARKS} (0: none), got {self.landmarks}")
        if not 0.0 <= self.landmark_floor <= 1.0:
            raise ValueError(f"landmark_floor must be a number in 0..1 (0: no floor), got {self.landmark_floor}")
        if (self.norm != "batch" or self.hash_levels or self.landmark_bracket_log or self.landmark_pair_inputs) and \
                not os.environ.get("NEUROGF_BAKEOFF_DESIGNS"):
            # their models train, but no inference backend runs them: refuse rather than lose a run
            raise ValueError(f"norm={self.norm!r} / hash_levels={self.hash_levels} / landmark_bracket_log="
                             f"{self.landmark_bracket_log} / landmark_pair_inputs={self.landmark_pair_inputs} are "
                             "training-time designs measured by benchmarks/bakeoff.py; the inference kernels run "
                             "norm='batch', hash_levels=0 and landmarks without those two forms")

    def build(self) -> NeuroGFNet:
        """A freshly initialized ``NeuroGFNet`` of this shape (draws from torch's global RNG)."""
        return NeuroGFNet(self.D, self.fourier, self.euclid, self.path_residual, self.path_width, self.path_window,
                          self.norm, self.hash_levels, self.landmarks, self.landmark_floor, self.landmark_bracket,
                          self.landmark_bracket_log, self.landmark_pair_inputs)


@dataclass
class ScheduleConfig:
    """Steps, learning rates and losses of the five stages (``STAGES``)."""

    epochs: int = 100                      # joint-training epochs ...
    iters_per_epoch: int = 200             # ... of this many steps
    querier_steps: int | None = None       # None: RATIOS x joint steps (querier at most QUERIER_MAX)
    refine_dist_steps: int | None = None
    refine_sdf_steps: int | None = None
    refine_path_steps: int | None = None
    ratios: dict = field(default_factory=dict)        # overrides of RATIOS, e.g. {"refine_dist": 2.0}
    lr: float = 1e-2                       # querier and joint stages; cosine decay to lr_min
    lr_min: float = 1e-4
    refine_lr: float = 1e-3                # refine_sdf
    refine_dist_lr: float = 3e-3
    refine_path_lr: float = 3e-3           # the official scripts use 1e-3
    weight_decay: float = 1e-8
    # "l1" = the paper's L1; "relative_global" = |pred - gt| / gt (the MRE itself) on global targets, L1 on the
    # local ones, where relative errors of near-zero distances would dominate
    dist_loss: str = "relative_global"
    loss_weights: dict = field(default_factory=dict)  # overrides of training.losses.WEIGHTS (the paper's)
    resample_every: int = 1                # steps between fresh batches
    # hard pairs: this share of every distance batch (joint and refine_dist) is drawn from the pairs the
    # network currently gets most wrong, re-ranked every ``hard_every`` steps (0: uniform batches only)
    hard_share: float = 0.0
    hard_every: int = 100

    def validate(self):
        from neurogf_warp.training.losses import WEIGHTS

        if not (_number(self.hard_share) and 0 <= self.hard_share < 1):
            raise ValueError(f"hard_share must be a number in [0, 1), got {self.hard_share!r}")
        for name in ("epochs", "iters_per_epoch", "resample_every", "hard_every"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        for stage in STAGES:
            n = getattr(self, f"{stage}_steps", None)
            if n is not None and n < 0:
                raise ValueError(f"{stage}_steps must be None or >= 0, got {n}")
        for name in ("lr", "refine_lr", "refine_dist_lr", "refine_path_lr"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("lr_min", "weight_decay"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.dist_loss not in DIST_LOSSES:
            raise ValueError(f"dist_loss must be one of {DIST_LOSSES}, got {self.dist_loss!r}")
        bad = set(self.ratios) - set(STAGES)
        if bad or not all(_number(v) and v >= 0 for v in self.ratios.values()):
            raise ValueError(f"ratios must map stage names {STAGES} to step ratios >= 0, e.g. "
                             f"{{\"refine_dist\": 2.0}}; got {self.ratios!r}")
        unknown = set(self.loss_weights) - set(WEIGHTS)
        if unknown:
            raise ValueError(f"loss_weights: unknown terms {sorted(unknown)}; known: {sorted(WEIGHTS)}")
        if not all(_number(v) and v >= 0 for v in self.loss_weights.values()):
            raise ValueError(f"loss_weights must be numbers >= 0, got {self.loss_weights!r}")


SDF_BATCHES = ("batch_sdf", "batch_querier")


@dataclass
class BatchConfig:
    """Samples per step (distance pairs, paths before their reversed copies, SDF points)."""

    batch_sdf: int = 30000          # SDF points, joint stage
    batch_g: int = 65536            # global distance pairs
    batch_l1: int = 8192            # local_1 pairs
    batch_l2: int = 16384           # local_2 pairs
    batch_paths_g: int = 2048       # global paths (+ reversed)
    batch_paths_l: int = 2048       # local paths (+ reversed)
    batch_surf: int = 256           # global paths whose points the surface term checks (0: no surface term)
    batch_querier: int = 90000      # SDF points, querier and refine_sdf stages
    sdf_pool: int = 1_000_000       # SDF ground-truth points computed once; batches are drawn from them
    # with a budget: when fewer than training.budget.SHORT_BUDGET_STEPS joint steps fit, every batch above (not
    # sdf_pool) shrinks, down to a quarter on a GPU and a sixteenth on the CPU (SDF batches a quarter), for more
    # steps (bunny, H100: 60 s 0.82% -> 0.59% MRE, 300 s 0.41% -> 0.37%; fandisk, 60 s, 2-core CPU: 1.11% -> 0.76%;
    # training/budget.py)
    short_budget_batches: bool = True

    def scaled(self, factor: float, sdf_factor: float | None = None) -> "BatchConfig":
        """A copy with every per-step batch multiplied by ``factor`` (at least 1 each; ``sdf_pool`` unchanged), the
        SDF batches (``batch_sdf``, ``batch_querier``) by ``sdf_factor`` (default: ``factor``)."""
        sdf_factor = factor if sdf_factor is None else sdf_factor
        sizes = {f.name: max(1, int(round(getattr(self, f.name) * (sdf_factor if f.name in SDF_BATCHES else factor))))
                 for f in dataclasses.fields(self) if f.name.startswith("batch_") and f.name != "batch_surf"}
        return dataclasses.replace(self, **sizes, batch_surf=min(int(round(self.batch_surf * factor)),
                                                                 sizes["batch_paths_g"]))

    def validate(self):
        for f in dataclasses.fields(self):
            if f.name == "short_budget_batches":
                continue
            v = getattr(self, f.name)
            lo = 0 if f.name == "batch_surf" else 1
            if v is not None and v < lo:
                raise ValueError(f"{f.name} must be >= {lo}, got {v}")


OPTIMIZERS = ("torch", "plain")


@dataclass
class RuntimeConfig:
    """How the steps run (none of these change the maths on the CPU) and how often the loop reports."""

    amp: bool = True           # bf16 autocast for the path head (CUDA; ignored on CPU)
    tf32: bool = True          # TF32 matmuls while training on CUDA (validation and saved weights stay fp32)
    cuda_graph: bool = True    # CUDA: each stage's step captured once as a CUDA graph and replayed
    compile: bool = True       # CUDA: torch.compile the loss functions (eager where compiling fails)
    val_every: int = 500       # joint / refine_dist steps between validation MREs (0: at stage ends only)
    log_every: int = 50        # steps between logged loss rows
    ckpt_every_s: float = 120.0  # seconds between checkpoints (also written at stage ends and on Ctrl-C)
    # with a budget: True fits the step counts to fill it; False runs the preset's own step counts and uses the
    # budget only as a cap (the model then depends less on the machine's load; the log and the model's metadata
    # say ``budget_bound`` when the cap cut steps)
    fill_budget: bool = True
    # torch CPU threads during the run (None: torch's own choice; 0: whichever of 1, 4 and torch's own count
    # runs this run's steps fastest, timed at its start: on a busy machine one thread can beat several)
    threads: int | None = None
    # "torch": torch.optim.AdamW (fused); "plain": training.adamw.AdamW, the same update from tensor ops, which
    # spares a fresh process torch._dynamo's import at the first step (bakeoff_setup10_h200_2026-11-29.json);
    # the GPU presets use "plain" (presets.py)
    optimizer: str = "torch"

    def validate(self):
        if self.optimizer not in OPTIMIZERS:
            raise ValueError(f"optimizer must be one of {OPTIMIZERS}, got {self.optimizer!r}")
        if self.threads is not None:  # None: torch's own; 0: timed at the start; n >= 1
            integer("threads", self.threads, minimum=0)
        if self.val_every < 0 or self.log_every < 1:
            raise ValueError(f"val_every must be >= 0 and log_every >= 1, got {self.val_every}, {self.log_every}")
        if not self.ckpt_every_s > 0:
            raise ValueError(f"ckpt_every_s must be > 0, got {self.ckpt_every_s}")


GROUPS = {"network": NetworkConfig, "schedule": ScheduleConfig, "batches": BatchConfig, "runtime": RuntimeConfig,
          "data": DatasetSettings}


def _leaf_groups() -> dict:
    out = {}
    for group, cls in GROUPS.items():
        for f in dataclasses.fields(cls):
            assert f.name not in out, f"setting {f.name} is defined twice"
            out[f.name] = (group, f.type)
    out["seed"] = (None, "int")
    return out


LEAVES = _leaf_groups()  # setting name -> (group, type annotation as text)


@dataclass
class TrainConfig:
    """Everything a training run needs besides the mesh: five groups and the seed.

    Build one from a preset (``presets.preset("cpu")``), change it with ``set(...)`` (flat or dotted names,
    values as Python objects or text), and pass it to ``neurogf_warp.train(..., config=cfg)``.
    """

    network: NetworkConfig = field(default_factory=NetworkConfig)
    schedule: ScheduleConfig = field(default_factory=ScheduleConfig)
    batches: BatchConfig = field(default_factory=BatchConfig)
    runtime: RuntimeConfig = field(default_factory=RuntimeConfig)
    data: DatasetSettings = field(default_factory=DatasetSettings)
    seed: int = 0
    preset: str = "default"  # the preset it started from (informative)

    # ---- derived step counts
    @property
    def joint_steps(self) -> int:
        return self.schedule.epochs * self.schedule.iters_per_epoch

    def ratio(self, stage: str) -> float:
        return float({**RATIOS, **self.schedule.ratios}[stage])

    def explicit_steps(self, stage: str) -> int | None:
        return None if stage == "joint" else getattr(self.schedule, f"{stage}_steps")

    def stage_steps(self, joint: int | None = None) -> dict:
        """{stage: steps}: explicit counts, else ratio x joint steps (at most the stage's ``max_steps``)."""
        j, out = self.joint_steps if joint is None else int(joint), {}
        for stage in STAGES:
            n = j if stage == "joint" else self.explicit_steps(stage)
            if n is None:
                n = max(1 if self.ratio(stage) > 0 else 0, int(round(self.ratio(stage) * j)))
                cap = STAGE_TABLE[stage].max_steps
                if cap is not None:
                    n = min(n, cap)
            out[stage] = int(n)
        return out

    # ---- changing and checking
    def set(self, **values) -> "TrainConfig":
        """A copy with the given settings changed: ``cfg.set(lr=3e-3, D=128)`` or ``cfg.set(**{"schedule.lr": ...})``.

        Values may be text (``"3e-3"``, ``"true"``, ``'{"refine_dist": 2}'``), as from ``--set``. Raises ValueError
        for an unknown name or a value of the wrong kind or out of range.
        """
        out = self.copy()
        for key, value in values.items():
            group, leaf, typ = _resolve(key)
            value = _convert(leaf, typ, value)
            setattr(out if group is None else getattr(out, group), leaf, value)
        return out.validate()

    def copy(self) -> "TrainConfig":
        return TrainConfig.from_dict(self.to_dict())

    def validate(self) -> "TrainConfig":
        """Raise ValueError naming the first setting that is out of range; returns self."""
        for group in GROUPS:
            g = getattr(self, group)
            for f in dataclasses.fields(g):  # kinds first, so range checks can compare
                setattr(g, f.name, _convert(f.name, f.type, getattr(g, f.name)))
            g.validate()
        self.seed = _convert("seed", "int", self.seed)
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")
        return self

    # ---- (de)serialization
    def to_dict(self) -> dict:
        """Nested plain dict (JSON-ready): {"network": {...}, ..., "seed": 0, "preset": "cpu"}."""
        return json.loads(json.dumps(dataclasses.asdict(self)))

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        """Inverse of ``to_dict``; also reads the flat dicts of format-3 checkpoints (``from_flat``)."""
        if not isinstance(d, dict):
            raise ValueError(f"a training config must be a dict, got {type(d).__name__}")
        if not any(isinstance(d.get(g), dict) for g in GROUPS):
            return cls.from_flat(d)
        unknown = set(d) - set(GROUPS) - {"seed", "preset"}
        if unknown:
            raise ValueError(f"unknown config groups {sorted(unknown)}; known: {sorted(GROUPS)}")
        kw = {}
        for group, gcls in GROUPS.items():
            sub = _without_removed(dict(d.get(group) or {}))
            names = {f.name for f in dataclasses.fields(gcls)}
            bad = set(sub) - names
            if bad:
                raise ValueError(f"unknown {group} settings {sorted(bad)}; known: {sorted(names)}")
            kw[group] = gcls(**sub)
        return cls(**kw, seed=d.get("seed", 0), preset=d.get("preset", "default")).validate()

    @classmethod
    def from_flat(cls, flat: dict) -> "TrainConfig":
        """From flat names, e.g. {"D": 64, "lr": 3e-3, "n_sources": 256}; ``dataset_options`` (a dict of dataset
        settings, as format-3 checkpoints store them) is unpacked."""
        flat = _without_removed(dict(flat))
        data = flat.pop("dataset_options", None) or {}
        flat.pop("preset", None)
        return cls().set(**{k: v for k, v in data.items() if k != "seed"}, **flat)


def _without_removed(d: dict) -> dict:
    for name, off in REMOVED.items():
        if name in d:
            if d[name] != off:
                raise ValueError(f"setting {name}={d[name]!r} was removed (it did not improve training); this "
                                 "version cannot continue a run that used it")
            del d[name]
    return d


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _resolve(key: str):
    key = key.strip().replace("-", "_")
    group, _, leaf = key.rpartition(".")
    if leaf not in LEAVES or (group and LEAVES[leaf][0] != group):
        close = difflib.get_close_matches(leaf, list(LEAVES), n=3)
        hint = f"; did you mean {', '.join(close)}?" if close else f"; known: {', '.join(sorted(LEAVES))}"
        raise ValueError(f"unknown setting {key!r}{hint}")
    return LEAVES[leaf][0], leaf, LEAVES[leaf][1]


_TRUE, _FALSE = ("true", "yes", "on", "1"), ("false", "no", "off", "0")


def _convert(name: str, typ: str, value):
    """``value`` (an object or text) as the kind ``typ`` names ("int", "float | None", "dict", ...)."""
    optional = "None" in typ
    base = typ.replace("| None", "").strip()
    if isinstance(value, str) and base != "str":
        text = value.strip()
        if optional and text.lower() in ("none", "null"):
            return None
        if base in ("dict", "bool"):
            value = text
        elif base == "int":
            try:
                value = int(text)
            except ValueError:
                raise ValueError(f"{name} must be an integer, got {value!r}") from None
        elif base == "float":
            try:
                value = float(text)
            except ValueError:
                raise ValueError(f"{name} must be a number, got {value!r}") from None
    if value is None:
        if optional:
            return None
        raise ValueError(f"{name} must be set, got None")
    if base == "bool":
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in _TRUE + _FALSE:
            return value.lower() in _TRUE
        raise ValueError(f"{name} must be true or false, got {value!r}")
    if base == "int":
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        if isinstance(value, bool) or not isinstance(value, int):
            if hasattr(value, "__index__") and not isinstance(value, bool):  # numpy integers
                return int(value)
            raise ValueError(f"{name} must be an integer, got {value!r}")
        return value
    if base == "float":
        if not _number(value) and not (hasattr(value, "dtype") and math.isfinite(float(value))):
            raise ValueError(f"{name} must be a finite number, got {value!r}")
        return float(value)
    if base == "str":
        if not isinstance(value, str):
            raise ValueError(f"{name} must be text, got {value!r}")
        return value
    if base == "dict":
        if isinstance(value, str):
            try:
                value = json.loads(value)
            except RecursionError:  # json recurses once per level
                raise InputError(f"{name} is nested deeper than {MAX_NESTING} levels; give a flat JSON object such "
                                 "as '{\"refine_dist\": 2}'") from None
            except json.JSONDecodeError:
                raise ValueError(f"{name} must be a JSON object such as '{{\"refine_dist\": 2}}', got {value!r}") from None
        if not isinstance(value, dict):
            raise ValueError(f"{name} must be a mapping, got {str(value)[:80]!r}")
        if not _shallow(value, MAX_NESTING):
            raise InputError(f"{name} is nested deeper than {MAX_NESTING} levels (or refers to itself); give a flat "
                             "mapping such as {\"refine_dist\": 2}")
        return dict(value)
    raise AssertionError(f"no conversion for {name}: {typ}")  # a new field kind: add it above


def _shallow(value, limit: int) -> bool:
    """True when the dicts and lists in ``value`` nest at most ``limit`` levels (walked without recursion, so a
    deep or self-referring value cannot exhaust the stack here or later when the config is copied)."""
    stack = [(value, 1)]
    while stack:
        v, depth = stack.pop()
        items = v.values() if isinstance(v, dict) else v if isinstance(v, (list, tuple)) else None
        if items is None:
            continue
        if depth > limit:
            return False
        stack.extend((x, depth + 1) for x in items)
    return True


def parse_assignments(items, flag: str = "--set") -> dict:
    """['lr=3e-3', 'batch_g=4096'] -> {'lr': '3e-3', 'batch_g': '4096'} (text; ``TrainConfig.set`` converts).

    Raises ValueError for an item without ``=`` or with an unknown name.
    """
    out = {}
    for item in items:
        key, sep, val = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"{flag} {item!r}: expected KEY=VALUE, e.g. {flag} lr=3e-3")
        try:
            _resolve(key)
        except ValueError as e:
            raise ValueError(f"{flag} {item!r}: {e}") from None
        out[key.strip()] = val
    return out
