"""Model files: our own ``.ngf`` format and the released NeuroGF ``.pth`` checkpoints.

Our format is a safetensors file: tensors ``net.*`` (weights and BatchNorm statistics), optional
``querier.*`` and ``mesh.*``, and JSON metadata (format version, config, normalization, mesh fingerprint).
Why safetensors: loading runs no pickled code, the file is memory-mappable and readable from any language,
and the header carries the metadata, so one file is the whole model.
"""
from __future__ import annotations

import json
import os

import numpy as np
import torch

from .files import atomic_write_bytes
from .mesh import Mesh, load_mesh
from .model import Model
from .network import SUPPORTED_D, NeuroGFNet, SdfQuerier

__all__ = ["save", "load", "load_querier"]

FORMAT = "neurogf-warp"
FORMAT_VERSION = 1


def save(model: Model, path, include_mesh: bool = True):
    """Write ``model`` to ``path`` (one safetensors file; any previous file survives a failed save)."""
    from safetensors.torch import save as st_save

    tensors = {f"net.{k}": v.detach().cpu().contiguous() for k, v in model.net.state_dict().items()}
    if model.querier is not None:
        tensors.update({f"querier.{k}": v.detach().cpu().contiguous() for k, v in model.querier.state_dict().items()})
    meta = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "D": model.D,
        "net_options": model.net.options,
        "center": model.center.tolist(),
        "scale": model.scale,
        "config": model.config,
        "mesh_fingerprint": model.mesh.fingerprint if model.mesh is not None else None,
    }
    if model.mesh is not None and include_mesh:
        m = model.mesh
        tensors["mesh.vertices"] = torch.from_numpy(np.ascontiguousarray(m.vertices, dtype=np.float64))
        tensors["mesh.faces"] = torch.from_numpy(np.ascontiguousarray(m.faces, dtype=np.int32))
        tensors["mesh.index"] = torch.from_numpy(np.ascontiguousarray(m.index, dtype=np.int64))
        meta["mesh_n_input"] = m.n_input
        meta["mesh_center"] = m.center.tolist()
        meta["mesh_scale"] = m.scale
    atomic_write_bytes(path, st_save(tensors, metadata={"neurogf": json.dumps(meta)}))


def _strict_load(module: torch.nn.Module, state: dict, what: str, path: str):
    own = module.state_dict()
    missing = sorted(set(own) - set(state))
    unexpected = sorted(set(state) - set(own))
    shapes = [f"{k}: file {tuple(state[k].shape)} vs model {tuple(own[k].shape)}"
              for k in sorted(set(own) & set(state)) if tuple(state[k].shape) != tuple(own[k].shape)]
    if missing or unexpected or shapes:
        lines = [f"{path} does not match the {what} layout:"]
        if missing:
            lines.append(f"  missing keys ({len(missing)}): {', '.join(missing[:12])}{' ...' if len(missing) > 12 else ''}")
        if unexpected:
            lines.append(f"  unexpected keys ({len(unexpected)}): {', '.join(unexpected[:12])}{' ...' if len(unexpected) > 12 else ''}")
        if shapes:
            lines.append("  shape mismatches: " + "; ".join(shapes[:8]))
        raise ValueError("\n".join(lines))
    module.load_state_dict({k: v.to(own[k].dtype) for k, v in state.items()}, strict=True)


def _net_from_state(state: dict, path: str, options: dict | None = None) -> NeuroGFNet:
    w = state.get("lifting.2.linear.weight")
    if w is None and "fc.0.linear.weight" in state:
        raise ValueError(f"{path} is an SDF-querier checkpoint, not a NeuroGF model: pass it as "
                         "neurogf_warp.load(model_path, mesh=..., querier=this_path)")
    if w is None:
        raise ValueError(f"{path} is not a NeuroGF checkpoint: no 'lifting.2.linear.weight' key "
                         f"(found {', '.join(list(state)[:5])} ...)")
    D = int(w.shape[0])
    if D not in SUPPORTED_D:
        raise ValueError(f"{path}: embedding width {D} is not supported (expected one of {SUPPORTED_D})")
    opts = dict(options or {})
    w0 = state.get("lifting.0.linear.weight")
    if w0 is not None and "fourier" not in opts:  # the input width says how many Fourier octaves
        opts["fourier"] = (int(w0.shape[1]) - 3) // 6
    p0 = state.get("spf_head.0.conv.weight")
    if p0 is not None and "path_width" not in opts:  # ... and the path head's width its multiplier
        opts["path_width"] = max(1, 2 * int(p0.shape[0]) // D)
    try:
        net = NeuroGFNet(D, **opts)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{path}: unsupported network options {opts} ({e}); upgrade neurogf-warp") from e
    _strict_load(net, state, f"NeuroGF (D={D}, {net.options})", path)
    return net


def _read_torch(path: str) -> dict:
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise ValueError(f"could not read {path} as a PyTorch checkpoint: {e}") from e
    if isinstance(state, dict) and "state_dict" in state and isinstance(state["state_dict"], dict):
        state = state["state_dict"]
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise ValueError(f"{path} does not hold a plain state_dict of tensors")
    return state


def load_querier(path) -> SdfQuerier:
    """Load a released ``SDist_Querier_Offline_Pretrainer__*.pth`` SDF querier."""
    path = _check_file(path)
    q = SdfQuerier()
    _strict_load(q, _read_torch(path), "SDF querier", path)
    return q.eval()


def _check_file(path) -> str:
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"model file not found: {path}")
    if not os.access(path, os.R_OK):
        raise PermissionError(f"model file is not readable: {path}")
    return path


def load(path, mesh=None, querier=None, check_mesh: bool = True) -> Model:
    """Load a model file: our ``.ngf`` (safetensors) or a released NeuroGF ``_final.pth``.

    mesh: the mesh the model belongs to (path, trimesh or Mesh). Released checkpoints carry no
    normalization, so it is computed from this mesh; our files carry their own (and usually the mesh).
    querier: optional path of a released SDF-querier checkpoint to attach.
    """
    path = _check_file(path)
    with open(path, "rb") as f:
        head = f.read(8)
    if head[:2] == b"PK":  # torch zip archive: a released checkpoint
        net = _net_from_state(_read_torch(path), path)
        m = load_mesh(mesh) if mesh is not None else None
        model = Model(net=net, mesh=m,
                      center=m.center if m is not None else np.zeros(3),
                      scale=m.scale if m is not None else 1.0,
                      config={"source": os.path.basename(path), "D": net.D})
    else:
        model = _load_ngf(path, mesh, check_mesh)
    if querier is not None:
        model.querier = querier if isinstance(querier, SdfQuerier) else load_querier(querier)
        model.querier.eval()
    return model


def _load_ngf(path: str, mesh, check_mesh: bool) -> Model:
    from safetensors import safe_open

    try:
        with safe_open(path, framework="pt") as f:
            meta = json.loads((f.metadata() or {}).get("neurogf", "null"))
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except Exception as e:
        raise ValueError(f"could not read {path}: not a neurogf-warp model file nor a PyTorch checkpoint ({e})") from e
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise ValueError(f"{path} is a safetensors file but not a neurogf-warp model (no '{FORMAT}' metadata)")
    if meta.get("format_version", 0) > FORMAT_VERSION:
        raise ValueError(f"{path} was written by a newer neurogf-warp (format {meta['format_version']}); upgrade the package")
    net = _net_from_state({k[4:]: v for k, v in tensors.items() if k.startswith("net.")}, path,
                          meta.get("net_options"))
    querier = None
    qstate = {k[8:]: v for k, v in tensors.items() if k.startswith("querier.")}
    if qstate:
        querier = SdfQuerier()
        _strict_load(querier, qstate, "SDF querier", path)
    if mesh is not None:
        m = load_mesh(mesh)
        want = meta.get("mesh_fingerprint")
        if check_mesh and want is not None and m.fingerprint != want:
            raise ValueError(f"{path} was trained on a different mesh (fingerprint {want[:12]}..., given "
                             f"{m.fingerprint[:12]}...). Pass the training mesh, or check_mesh=False to query "
                             "this mesh in the model's stored frame.")
    elif "mesh.vertices" in tensors:
        m = Mesh(vertices=tensors["mesh.vertices"].numpy().astype(np.float64),
                 faces=tensors["mesh.faces"].numpy().astype(np.int32),
                 index=tensors["mesh.index"].numpy().astype(np.int64),
                 n_input=int(meta["mesh_n_input"]), center=np.asarray(meta["mesh_center"]),
                 scale=float(meta["mesh_scale"]), fingerprint=meta["mesh_fingerprint"])
    else:
        m = None
    return Model(net=net, querier=querier, mesh=m, center=np.asarray(meta["center"]), scale=float(meta["scale"]),
                 config=dict(meta.get("config") or {}))
