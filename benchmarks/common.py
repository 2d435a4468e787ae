"""Code the benchmarks share: where the test data is, the large benchmark meshes, and the provenance block that
every benchmark writes into its JSON (command, device, driver, Warp / torch versions, date, commit)."""
from __future__ import annotations

import datetime
import json
import os
import platform
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("NEUROGF_SHARED", ROOT.parent / "shared"))


def find_shared(*parts) -> Path:
    """A file of the shared data folder: ``$NEUROGF_SHARED``, else ``../shared`` beside the checkout, else
    ``./shared`` inside it."""
    for base in (SHARED, ROOT / "shared"):
        p = base.joinpath(*parts)
        if p.exists():
            return p
    raise FileNotFoundError(f"{Path(*parts)} not found under {SHARED} or {ROOT / 'shared'}: set NEUROGF_SHARED to "
                            "the folder that holds meshes/, reference/ and checkpoints/")


def _git(*args) -> str | None:
    try:
        r = subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return r.stdout.strip() if r.returncode == 0 else None


def _cpu_name() -> str | None:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or None


def provenance(device: str | None = None, argv: list[str] | None = None) -> dict:
    """Where a result comes from: the command as typed, the device and its name, the CUDA driver, the Warp /
    torch / Python versions, the date (UTC) and the checkout's commit (``dirty`` when files differ from it).

    Parameters
    ----------
    device : str, optional
        ``"cpu"`` or ``"cuda:N"``; ``None`` for a benchmark that spans several devices (names them all).
    argv : list of str, optional
        The arguments after the script name (default ``sys.argv[1:]``).
    """
    import torch
    import warp as wp

    script = Path(sys.argv[0]).resolve()
    try:
        script_name = script.relative_to(ROOT).as_posix()
    except ValueError:
        script_name = script.name
    args = sys.argv[1:] if argv is None else list(argv)
    driver = wp.get_cuda_driver_version() if wp.is_cuda_available() else None
    if device is not None and str(device).startswith("cuda"):
        name = torch.cuda.get_device_name(torch.device(device)) if torch.cuda.is_available() else None
    elif device is None and torch.cuda.is_available():
        name = ", ".join(torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count()))
    else:
        name = _cpu_name()
    return {
        "command": shlex.join(["python", script_name, *args]),
        "device": device,
        "device_name": name,
        "driver": ".".join(map(str, driver)) if driver else None,
        "warp": wp.__version__,
        "torch": torch.__version__,
        "python": platform.python_version(),
        "date_utc": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M:%S"),
        # a copy of the tree without its history (the GPU machine) names its commit in NEUROGF_COMMIT
        "commit": os.environ.get("NEUROGF_COMMIT") or _git("rev-parse", "--short", "HEAD"),
        "dirty": bool(_git("status", "--porcelain", "--untracked-files=no")),
        "cpu_cores": os.cpu_count(),
        # CPU timings depend on what else runs: the 1-minute load average when the result was written
        "load_average_1min": round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None,
    }


def write_json(path, result: dict, benchmark: str, device: str | None = None) -> Path:
    """Write ``result`` as JSON with ``benchmark`` and a ``provenance`` block (see :func:`provenance`) added.

    ``benchmarks/make_performance.py`` reads such files into ``docs/performance.md``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    doc = {"benchmark": benchmark, "provenance": provenance(device), **result}
    path.write_text(json.dumps(doc, indent=1, default=float) + "\n")
    return path


def subdivided_bunny(target: int = 436_000):
    """A conforming ~``target``-vertex bunny: midpoint-subdivide until above it, then QSlim back down.

    (Subdividing only some faces would leave T-junctions, i.e. cracks that change geodesics.)
    """
    import fast_simplification
    import trimesh

    tm = trimesh.load(find_shared("meshes", "stanford-bunny.obj"), process=False, force="mesh")
    v, f = np.asarray(tm.vertices), np.asarray(tm.faces)
    used = np.unique(f)  # drop vertices no face uses
    remap = np.full(len(v), -1)
    remap[used] = np.arange(len(used))
    v, f = v[used], remap[f]
    while len(v) < target:
        v, f = trimesh.remesh.subdivide(v, f)
    if len(v) > 1.02 * target:
        v, f = fast_simplification.simplify(v.astype(np.float32), f.astype(np.int32), 1.0 - target / len(v))
    return np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64)


def bumpy_torus(n: int = 660) -> tuple[np.ndarray, np.ndarray]:
    """A clean closed genus-1 mesh of n*n vertices (660 -> 435,600) with smooth bumps: well-shaped triangles,
    no slivers, so exact MMP (gdist) and our solver can be compared on it."""
    u, w = np.meshgrid(np.arange(n) * (2 * np.pi / n), np.arange(n) * (2 * np.pi / n), indexing="ij")
    r = 0.35 * (1 + 0.15 * np.sin(3 * u) * np.cos(2 * w))
    R = 1.0 + 0.1 * np.cos(5 * u)
    x = (R + r * np.cos(w)) * np.cos(u)
    y = (R + r * np.cos(w)) * np.sin(u)
    z = r * np.sin(w) * 1.3
    v = np.stack([x, y, z], -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a, b = i * n + j, ((i + 1) % n) * n + j
    c, d = ((i + 1) % n) * n + (j + 1) % n, i * n + (j + 1) % n
    f = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return v, f
