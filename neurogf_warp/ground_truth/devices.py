"""One mesh's ground truth on several devices: the sources in balanced contiguous blocks, one solver per device.

Design: in one process, one thread per device, each with its own ``GeodesicSolver`` (the solver's mesh tables are
cached per device). Threads and not processes: the solver's relaxation loop runs as a captured CUDA graph and the
host only launches it and waits, in Warp calls (ctypes) that release the GIL, so the devices solve concurrently
without a second Python, a second Warp start-up or pickled rows. Across processes (``torch.distributed``, e.g.
one rank per GPU under ``torchrun``) each rank solves its block of the sources and the rows are all-gathered, so
every rank ends with the whole result; this is opt-in (``distributed=True``), because ranks that work on
different meshes (a collection sharded over ranks) must not enter a collective. Every source row is solved on its
own, so the rows do not depend on how the sources are split.
"""
from __future__ import annotations

import os
import threading

import numpy as np
import warp as wp

from neurogf_warp.common.arrays import resolve_device
from neurogf_warp.common.checks import InputError

__all__ = ["ENV", "LAST_RUN", "capture_lock", "lock_captures", "resolve_devices", "split_blocks", "run_on_devices",
           "process_group", "all_gather_rows", "all_gather_objects"]

ENV = "NEUROGF_DEVICES"  # default of ``devices``: "all", or a comma-separated list such as "cuda:0,cuda:1"
# Where the last call of geodesic_distances over several devices (or ranks) spent its time, for benchmarks: per
# device (start s, end s, sources or chunks) of its solve and of its near-source patches, from the call's start
LAST_RUN: dict = {}


def _parse(devices, name: str) -> list:
    if isinstance(devices, str):
        text = devices.strip()
        if text.lower() == "all":
            cuda = wp.get_cuda_devices()
            if not cuda:
                raise InputError(f"{name}='all' asks for every GPU, but this machine has none "
                                 f"(devices: {', '.join(str(d) for d in wp.get_devices())}); use device='cpu'")
            return list(cuda)
        items = [t.strip() for t in text.split(",") if t.strip()]
        if not items:
            raise InputError(f"{name} must name at least one device, got {devices!r}")
        return items
    if isinstance(devices, (wp.Device,)) or (hasattr(devices, "type") and hasattr(devices, "index")):
        return [devices]
    try:
        items = list(devices)
    except TypeError:
        raise InputError(f"{name} must be 'all', a device name or a list of them, got {devices!r}") from None
    if not items:
        raise InputError(f"{name} must name at least one device, got an empty list")
    return items


def resolve_devices(devices=None, device=None, name: str = "devices") -> list:
    """The Warp devices of a call, ``device`` (resolved) first.

    Parameters
    ----------
    devices : "all" (every CUDA device), a device or a list of them (``["cuda:0", "cuda:1"]``, also as the
        comma-separated string "cuda:0,cuda:1"), or None: the environment variable ``NEUROGF_DEVICES`` (same
        forms) where it is set and ``device`` is not the CPU, else ``[device]``
    device : the single device of the call (None: Warp's preferred one); with ``devices`` given it must be one of
        them, and it comes first (the device that does any single-device work of the call)

    Returns
    -------
    list of warp.Device, without duplicates, all CUDA or the one CPU. InputError (naming ``name``) for an unknown
    device, a device given twice, the CPU mixed with GPUs, or ``device`` not among ``devices``.
    """
    from_env = False
    if devices is None:
        env = os.environ.get(ENV, "").strip()
        primary = resolve_device(device)
        if not env or primary.is_cpu:
            return [primary]
        devices, name, from_env = env, f"the environment variable {ENV}", True
    out = []
    for d in _parse(devices, name):
        try:
            out.append(resolve_device(d))
        except InputError as e:
            raise InputError(f"{name}: {e}") from None
    seen = set()
    for d in out:
        if str(d) in seen:
            raise InputError(f"{name} names {d} twice: give each device once")
        seen.add(str(d))
    if len({d.is_cpu for d in out}) > 1:
        raise InputError(f"{name} mixes the CPU with GPUs ({', '.join(map(str, out))}): the CPU solves on its cores "
                         "through worker processes; give GPUs only, or device='cpu' alone")
    if device is not None or from_env:
        first = resolve_device(device)
        if str(first) not in seen:
            if not from_env:
                raise InputError(f"device {first} is not among {name} ({', '.join(map(str, out))}): leave device "
                                 "out or make it one of them")
            if first.is_cpu != out[0].is_cpu:
                return [first]
            out.append(first)
        out = [first] + [d for d in out if str(d) != str(first)]
    return out


_CAPTURE_LOCK = threading.RLock()


def capture_lock():
    """The lock that graph captures (``lock_captures``) and the device threads' solver set-ups take, so that no
    capture overlaps another thread's captures or allocations: a precaution, as a program whose capture fails
    runs from the host (slower; the solver warns)."""
    return _CAPTURE_LOCK


def lock_captures(solver):
    """``solver`` with its programs captured under ``capture_lock`` (its first launch of each); replays are not
    locked."""
    launch = solver._launch

    def locked(name, program):
        if solver._graphs.get(name) is not None:
            return launch(name, program)
        with _CAPTURE_LOCK:
            return launch(name, program)

    solver._launch = locked
    return solver


def split_blocks(n: int, parts: int) -> list:
    """``parts`` contiguous slices of range(n), sizes differing by at most one, larger ones first."""
    q, r = divmod(int(n), int(parts))
    bounds = np.cumsum([0] + [q + (i < r) for i in range(parts)])
    return [slice(int(bounds[i]), int(bounds[i + 1])) for i in range(parts)]


def run_on_devices(fn, n: int) -> None:
    """``fn(j)`` for j in range(n), each in its own thread (j = 0 in this one); the first error is raised after
    every thread has ended."""
    errors = [None] * n

    def call(j):
        try:
            fn(j)
        except BaseException as e:  # noqa: BLE001 - re-raised in the caller
            errors[j] = e

    threads = [threading.Thread(target=call, args=(j,), daemon=True) for j in range(1, n)]
    for t in threads:
        t.start()
    call(0)
    for t in threads:
        t.join()
    for e in errors:
        if e is not None:
            raise e


def process_group(distributed):
    """(group, rank, world) of ``distributed``: False/None -> None; True -> torch.distributed's default group;
    a ProcessGroup -> that group. InputError where True is asked and no process group is initialised."""
    if distributed is None or distributed is False:
        return None
    try:
        import torch.distributed as dist
    except ImportError:  # pragma: no cover - torch is a dependency
        raise InputError("distributed=True needs torch.distributed") from None
    if not (dist.is_available() and dist.is_initialized()):
        raise InputError("distributed=True needs an initialised torch.distributed process group (launch with "
                         "torchrun and call torch.distributed.init_process_group first), or leave it False")
    group = None if distributed is True else distributed
    return group, dist.get_rank(group), dist.get_world_size(group)


def _collective_device(group):
    import torch
    import torch.distributed as dist

    if dist.get_backend(group) == "nccl":
        return torch.device("cuda", torch.cuda.current_device())
    return torch.device("cpu")


def all_gather_rows(rows: np.ndarray, total: int, group) -> np.ndarray:
    """The (total, V) float32 rows of every rank, in rank order, from this rank's block ``rows`` (the blocks of
    ``split_blocks(total, world)``): one all_gather of padded tensors (on the current CUDA device under NCCL)."""
    import torch
    import torch.distributed as dist

    world = dist.get_world_size(group)
    blocks = split_blocks(total, world)
    most = max(b.stop - b.start for b in blocks)
    dev = _collective_device(group)
    width = rows.shape[1]
    mine = torch.zeros((most, width), dtype=torch.float32, device=dev)
    if len(rows):
        mine[: len(rows)] = torch.from_numpy(np.ascontiguousarray(rows, dtype=np.float32)).to(dev)
    parts = [torch.empty_like(mine) for _ in range(world)]
    dist.all_gather(parts, mine, group=group)
    out = np.empty((total, width), dtype=np.float32)
    for b, p in zip(blocks, parts):
        out[b] = p[: b.stop - b.start].cpu().numpy()
    return out


def all_gather_objects(obj, group) -> list:
    """Every rank's ``obj`` (picklable, small), in rank order."""
    import torch.distributed as dist

    out = [None] * dist.get_world_size(group)
    dist.all_gather_object(out, obj, group=group)
    return out
