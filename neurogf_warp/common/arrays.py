"""Plain arrays in and out: numpy, torch or wp.array, validated, on the device the work runs on."""
from __future__ import annotations

import numpy as np
import warp as wp

from neurogf_warp.common.checks import InputError
from neurogf_warp.common.warp_setup import init_warp, quiet_warp

__all__ = ["resolve_device", "as_points", "Output"]

# Every module of this package that uses Warp imports this one: Warp's log level is set here, once, before any
# of our kernels loads (see common/warp_setup.py; NEUROGF_WARP_VERBOSE=1 keeps Warp's messages).
quiet_warp()


def resolve_device(device=None, like=None) -> wp.Device:
    """The Warp device to run on: explicit ``device``, else the input's device, else Warp's preferred one."""
    init_warp()
    if device is None and like is not None:
        device = _device_of(like)
    if device is None:
        return wp.get_preferred_device()
    if hasattr(device, "type") and hasattr(device, "index") and not isinstance(device, wp.Device):
        device = str(device)  # torch.device
        if device == "cuda":
            device = "cuda:0"
    try:
        return wp.get_device(device)
    except Exception as e:
        known = ", ".join(str(d) for d in wp.get_devices())
        raise InputError(f"unknown device {device!r}: this machine has {known}") from e


def _device_of(x):
    if isinstance(x, wp.array):
        return x.device
    if _is_torch(x):
        return x.device
    return None


def _is_torch(x) -> bool:
    t = type(x)
    return t.__module__.startswith("torch") and t.__name__ in ("Tensor", "Parameter")


def as_array(x, name: str) -> np.ndarray:
    """``np.asarray(x)``, with ragged input (rows of different lengths) refused naming ``name``."""
    try:
        return np.asarray(x)
    except ValueError:
        raise InputError(f"{name} has rows of different lengths: points are an (N, 3) array, one [x, y, z] per "
                         "row") from None


def as_points(x, name: str, device, check: bool = True, single: bool = False) -> tuple:
    """Return (wp.array of vec3 on ``device``, kind) for (N, 3) float input; kind in numpy|torch|warp.

    Float32 inputs already on the device are used without a copy. ``single`` accepts one point (3,).
    """
    if isinstance(x, wp.array):
        kind = "warp"
        if x.dtype == wp.vec3:
            arr = x
        elif x.dtype == wp.float32 and x.ndim == 2 and x.shape[1] == 3:
            arr = x.contiguous().view(wp.vec3)
        else:
            raise TypeError(f"{name} must be a wp.array of vec3 or an (N, 3) float32 array, got dtype "
                            f"{wp.types.type_repr(x.dtype)} with shape {x.shape}")
        if check and not np.all(np.isfinite(arr.numpy())):
            raise InputError(f"{name} contains non-finite coordinates (NaN or inf)")
        return (arr if arr.device == device else arr.to(device)), kind
    if _is_torch(x):
        import torch

        kind = "torch"
        if not torch.is_floating_point(x):
            raise TypeError(f"{name} must hold floating-point coordinates, got {x.dtype}")
        t = x.detach()
        if single and t.shape == (3,):
            t = t.view(1, 3)
        if t.ndim != 2 or t.shape[1] != 3:
            raise InputError(f"{name} must have shape (N, 3), got {tuple(x.shape)}")
        if check and not bool(torch.isfinite(t).all()):
            raise InputError(f"{name} contains non-finite coordinates (NaN or inf)")
        t = t.to(device=wp.device_to_torch(device), dtype=torch.float32).contiguous()
        return wp.from_torch(t, dtype=wp.vec3), kind
    a = as_array(x, name)
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise TypeError(f"{name} must hold numeric coordinates, got dtype {a.dtype}")
    if single and a.shape == (3,):
        a = a.reshape(1, 3)
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputError(f"{name} must have shape (N, 3), got {a.shape}")
    if check and not np.all(np.isfinite(a)):
        raise InputError(f"{name} contains non-finite coordinates (NaN or inf)")
    return wp.array(np.ascontiguousarray(a, dtype=np.float32), dtype=wp.vec3, device=device), "numpy"


class Output:
    """Allocates a result on the device and hands it back in the caller's kind of array."""

    def __init__(self, kind: str, device):
        if kind not in ("numpy", "torch", "warp"):
            raise InputError(f"output must be 'numpy', 'torch' or 'warp', got {kind!r}")
        self.kind, self.device = kind, device

    def empty(self, shape, dtype=wp.float32, fill=None):
        a = wp.empty(shape, dtype=dtype, device=self.device)
        if fill is not None:
            a.fill_(fill)
        return a

    def result(self, a: wp.array):
        if self.kind == "warp":
            return a
        if self.kind == "torch":
            return wp.to_torch(a)
        return a.numpy()
