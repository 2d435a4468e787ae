"""Model files: our own ``.ngf`` format and the released NeuroGF ``.pth`` checkpoints, checked on load.

Our format is a safetensors file: tensors ``net.*`` (weights and BatchNorm statistics), optional
``querier.*`` and ``mesh.*`` (vertices, faces, index, input_to_internal, components), for a network with
landmarks ``landmarks.table`` ((V, K) float32 distances of the stored vertices to the landmarks), and JSON metadata
(format version, D, network options, normalization, config, mesh fingerprint). Why safetensors: loading runs
no pickled code, the file is memory-mappable and readable from any language, and the header carries the
metadata, so one file is the whole model.

Every file is checked before any of it reaches a kernel: index arrays in range and of the right length,
faces in range, the mesh fingerprint, normalization and component labels recomputed from the stored mesh,
metadata of the right types and ranges, D matching the weights. Format 2 also stores a SHA-256 of every
tensor and of every metadata field, so a flipped byte or an edited value is refused with the field's name.
(The checksums find damage and accidental edits; they are not a signature against deliberate forgery.)
Format 1 files (no checksums, no stored map or labels) still load, with every check that needs no checksum.
"""
from __future__ import annotations

import hashlib
import json
import math
import os

import numpy as np
import torch

from neurogf_warp.common.files import atomic_write_bytes, check_input_file, note_input
from neurogf_warp.mesh.mesh import Mesh, component_labels, load_mesh, mesh_fingerprint
from neurogf_warp.common.checks import InputError
from neurogf_warp.model.checkpoint_match import MeshMismatchError, warn_if_mesh_mismatch
from neurogf_warp.model.model import Model
from neurogf_warp.model.network import LANDMARK_UNREACHED, MAX_FOURIER, SUPPORTED_D, NeuroGFNet, SdfQuerier

__all__ = ["save", "load", "load_querier", "FORMAT_VERSION"]

FORMAT = "neurogf-warp"
FORMAT_VERSION = 2
# network options a file may set, with their JSON types (bool is checked apart from int: True is an int)
NET_OPTIONS = {"fourier": int, "euclid": bool, "path_residual": bool, "path_width": int, "path_window": bool,
               "landmarks": int, "landmark_floor": float, "landmark_bracket": bool, "landmark_bracket_log": bool,
               "landmark_pair_inputs": bool}
LANDMARK_TABLE = "landmarks.table"
MESH_TENSORS = ("mesh.vertices", "mesh.faces", "mesh.index")
MESH_TENSORS_V2 = MESH_TENSORS + ("mesh.input_to_internal", "mesh.components")
# relative tolerance for the stored normalization against the one recomputed from the stored vertices
FRAME_RTOL = 1e-9


def _digest_tensor(name: str, t: torch.Tensor) -> str:
    h = hashlib.sha256()
    h.update(f"{name}|{str(t.dtype)}|{tuple(t.shape)}|".encode())
    h.update(t.contiguous().numpy().tobytes())
    return h.hexdigest()


def _digest_value(value) -> str:
    return hashlib.sha256(json.dumps(value, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def save(model: Model, path, include_mesh: bool = True) -> str:
    """Write ``model`` to ``path``: one safetensors file (format 2), written atomically.

    Parameters
    ----------
    model : Model
        The model; its mesh (if any) is stored with it unless ``include_mesh`` is False.
    path : str or os.PathLike
        Target file (``.ngf`` by convention): a new path or a regular file, replaced atomically (a failed or
        killed save leaves any previous file as it was); a link is written through to its target; a folder,
        device or FIFO is refused (``common.files``).
    include_mesh : bool
        Store the mesh (vertices, faces, numbering map, component labels). Without it, loading needs
        ``mesh=`` to answer vertex queries; the fingerprint and the normalization are stored either way, so
        the loaded model still takes and returns points in the mesh's coordinates and units.

    Returns
    -------
    str, the path written.

    Raises
    ------
    TypeError
        ``model`` is not a Model (None, a Mesh, ...).
    InputError (a ValueError), IsADirectoryError, FileNotFoundError
        ``path`` breaks the writing rule or its folder does not exist.
    """
    from safetensors.torch import save as st_save

    if not isinstance(model, Model):
        hint = (" (a Mesh is not a model: train one with neurogf_warp.train(mesh, path), which saves it)"
                if isinstance(model, Mesh) else " (from neurogf_warp.train or neurogf_warp.load)")
        raise TypeError(f"save(model, path): model must be a neurogf_warp Model, got "
                        f"{'None' if model is None else type(model).__name__}{hint}")
    _check_frame(np.asarray(model.center, dtype=np.float64).tolist(), model.scale, "center", "scale", "model")
    _not_a_mesh_name(path)
    tensors = {f"net.{k}": v.detach().cpu().contiguous() for k, v in model.net.state_dict().items()}
    if model.querier is not None:
        tensors.update({f"querier.{k}": v.detach().cpu().contiguous() for k, v in model.querier.state_dict().items()})
    meta = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "D": model.D,
        "net_options": model.net.options,
        "center": [float(c) for c in model.center],
        "scale": float(model.scale),
        "config": model.config,
        "mesh_fingerprint": model.mesh.fingerprint if model.mesh is not None else None,
    }
    if model.net.landmarks:
        tensors[LANDMARK_TABLE] = torch.from_numpy(_internal_table(model))
    if model.mesh is not None and include_mesh:
        m = model.mesh
        tensors["mesh.vertices"] = torch.from_numpy(np.ascontiguousarray(m.internal_vertices, dtype=np.float64))
        tensors["mesh.faces"] = torch.from_numpy(np.ascontiguousarray(m.internal_faces, dtype=np.int32))
        tensors["mesh.index"] = torch.from_numpy(np.ascontiguousarray(m.index, dtype=np.int64))
        tensors["mesh.input_to_internal"] = torch.from_numpy(np.ascontiguousarray(m.input_to_internal, dtype=np.int64))
        tensors["mesh.components"] = torch.from_numpy(np.ascontiguousarray(m.internal_components, dtype=np.int32))
        meta["mesh_n_input"] = int(m.n_input)
        meta["mesh_center"] = [float(c) for c in m.center]
        meta["mesh_scale"] = float(m.scale)
    try:
        meta = json.loads(json.dumps(meta))  # the checksums cover the values as a reader will see them
    except (TypeError, ValueError) as e:
        raise InputError(f"cannot save: the model's config must be JSON data (numbers, strings, lists, dicts): {e}") from e
    meta["checksums"] = {"tensors": {k: _digest_tensor(k, v) for k, v in tensors.items()},
                         "meta": {k: _digest_value(v) for k, v in meta.items()}}
    return atomic_write_bytes(path, st_save(tensors, metadata={"neurogf": json.dumps(meta)}), what="model file")


def _internal_table(model: Model) -> np.ndarray:
    """A landmark network's table in the mesh's internal vertex order (the order of the stored vertices)."""
    if model.mesh is None or model.landmarks is None:
        raise InputError("cannot save a network with landmarks without its mesh and its table (model.landmarks): "
                         "its distances are read from that table at the mesh's vertices")
    return model.internal_landmarks()


def _not_a_mesh_name(path, suffix: str = ".ngf") -> None:
    """Refuse a model path named like a mesh file: saving there would replace a mesh (``save(m, "bunny.obj")``),
    and the file would later be read as one."""
    from neurogf_warp.common.files import output_target
    from neurogf_warp.mesh.files import ARCHIVE_SUFFIXES, COMPRESSED_SUFFIXES, MESH_SUFFIXES

    name = os.path.basename(output_target(path, what="model file")).lower()
    bad = [s for s in MESH_SUFFIXES + ARCHIVE_SUFFIXES + COMPRESSED_SUFFIXES if name.endswith(s)]
    if bad:
        raise InputError(f"cannot write model file {os.fspath(path)}: a '{bad[0]}' name is a mesh file's (saving "
                         f"there would replace a mesh, and the file would be read as one); save to a {suffix} path")


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
        raise InputError("\n".join(lines))
    module.load_state_dict({k: v.to(own[k].dtype) for k, v in state.items()}, strict=True)


def _check_weights(state: dict, path: str, prefix: str = ""):
    """Weights and BatchNorm statistics must be finite, running variances non-negative."""
    for k, v in state.items():
        if v.is_floating_point():
            if not bool(torch.isfinite(v).all()):
                raise InputError(f"{path}: tensor {prefix}{k} holds NaN or inf values: the file is damaged")
            if k.endswith("running_var") and bool((v < 0).any()):
                raise InputError(f"{path}: tensor {prefix}{k} holds negative variances: the file is damaged")


def _check_options(options, path: str) -> dict:
    if not isinstance(options, dict):
        raise InputError(f"{path}: metadata field 'net_options' must be a JSON object, got {type(options).__name__}")
    for k, v in options.items():
        if k not in NET_OPTIONS:
            raise InputError(f"{path}: unknown network option {k!r} in 'net_options' (known: {', '.join(NET_OPTIONS)}); "
                             "the file may come from a newer neurogf-warp")
        want = NET_OPTIONS[k]
        if (want is bool and not isinstance(v, bool)) or (want is int and (isinstance(v, bool) or not isinstance(v, int))) \
                or (want is float and not _is_number(v)):
            raise InputError(f"{path}: network option {k!r} must be {want.__name__}, got {v!r}")
    if not 0 <= options.get("fourier", 0) <= MAX_FOURIER:
        raise InputError(f"{path}: network option 'fourier' must lie in 0..{MAX_FOURIER}, got {options['fourier']}")
    return options


def _net_from_state(state: dict, path: str, options: dict | None = None) -> NeuroGFNet:
    w = state.get("lifting.2.linear.weight")
    if w is None and "fc.0.linear.weight" in state:
        raise InputError(f"{path} is an SDF-querier checkpoint, not a NeuroGF model: pass it as "
                         "neurogf_warp.load(model_path, mesh=..., querier=this_path)")
    if w is None:
        raise InputError(f"{path} is not a NeuroGF checkpoint: no 'lifting.2.linear.weight' key "
                         f"(found {', '.join(list(state)[:5])} ...)")
    if w.ndim != 2:
        raise InputError(f"{path}: tensor lifting.2.linear.weight must be a matrix, got shape {tuple(w.shape)}")
    D = int(w.shape[0])
    if D not in SUPPORTED_D:
        raise InputError(f"{path}: embedding width {D} is not supported (expected one of {SUPPORTED_D})")
    opts = dict(options or {})
    w0 = state.get("lifting.0.linear.weight")
    if w0 is not None and w0.ndim == 2 and "fourier" not in opts:  # the input width says how many Fourier octaves
        opts["fourier"] = (int(w0.shape[1]) - 3) // 6
    p0 = state.get("spf_head.0.conv.weight")
    if p0 is not None and p0.ndim >= 1 and "path_width" not in opts:  # ... and the path head's width its multiplier
        opts["path_width"] = max(1, 2 * int(p0.shape[0]) // D)
    try:
        net = NeuroGFNet(D, **opts)
    except (TypeError, ValueError) as e:
        raise InputError(f"{path}: unsupported network options {opts} ({e}); upgrade neurogf-warp") from e
    _strict_load(net, state, f"NeuroGF (D={D}, {net.options})", path)
    _check_weights(state, path)
    return net


def _read_torch(path: str) -> dict:
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise InputError(f"could not read {path} as a PyTorch checkpoint: {e}") from e
    if isinstance(state, dict) and "state_dict" in state and isinstance(state["state_dict"], dict):
        state = state["state_dict"]
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise InputError(f"{path} does not hold a plain state_dict of tensors")
    return state


def load_querier(path) -> SdfQuerier:
    """Load a released ``SDist_Querier_Offline_Pretrainer__*.pth`` SDF querier."""
    path = _check_file(path)
    q = SdfQuerier()
    _strict_load(q, _read_torch(path), "SDF querier", path)
    note_input(path)
    return q.eval()


def _check_file(path) -> str:
    path = os.fspath(path)
    if os.path.isdir(path):
        raise IsADirectoryError(f"model file {path} is a folder: give the model file itself (e.g. model.ngf or a "
                                "*_final.pth)")
    return check_input_file(path, "model file", note=False)  # noted once it has loaded


def load(path, mesh=None, querier=None, check_mesh: bool = True) -> Model:
    """Load a model file: our ``.ngf`` (safetensors) or a released NeuroGF ``_final.pth``.

    Parameters
    ----------
    path : str or os.PathLike
        The model file. Every part of it is checked before use (see the module docstring).
    mesh : path, trimesh.Trimesh, (vertices, faces) or Mesh, optional
        The mesh the model belongs to. Released checkpoints carry no normalization, so it is computed from
        this mesh, and a warning is given when the mesh does not lie on the checkpoint's SDF zero level set
        (it looks like another mesh). Our files carry their own normalization and usually the mesh; a given
        mesh must have the stored fingerprint unless ``check_mesh`` is False.
    querier : path or SdfQuerier, optional
        A released SDF-querier checkpoint to attach.
    check_mesh : bool
        Refuse a given mesh whose fingerprint differs from the stored one (default). False queries that
        mesh in the model's stored frame.

    Returns
    -------
    Model

    Raises
    ------
    FileNotFoundError, IsADirectoryError, PermissionError
        For a missing or unreadable file, or a folder.
    InputError (a ValueError)
        For anything wrong in the file, naming the field or tensor; ``MeshMismatchError`` (an InputError) for
        a mesh whose fingerprint differs from the stored one.

    Warns
    -----
    MeshMismatchWarning
        A released checkpoint given a mesh that does not lie on its SDF zero level set: the model is returned,
        but its answers for that mesh are wrong. Make it an error with
        ``warnings.simplefilter("error", neurogf_warp.MeshMismatchWarning)``.
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
        if m is not None:
            warn_if_mesh_mismatch(model, path)
    else:
        model = _load_ngf(path, mesh, check_mesh)
    if querier is not None:
        model.querier = querier if isinstance(querier, SdfQuerier) else load_querier(querier)
        model.querier.eval()
    note_input(path)  # an input of this command now: no output of it may replace the file
    return model


def _fail(path: str, what: str):
    raise InputError(f"{path}: {what}")


def _field(meta: dict, key: str, path: str):
    if key not in meta:
        _fail(path, f"metadata field {key!r} is missing (the file was edited or damaged)")
    return meta[key]


def _is_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _check_frame(center, scale, cname: str, sname: str, path: str):
    if not (isinstance(center, (list, tuple)) and len(center) == 3 and all(_is_number(c) for c in center)):
        _fail(path, f"{cname!r} must be 3 finite numbers, got {center!r}")
    if not (_is_number(scale) and scale > 0):
        _fail(path, f"{sname!r} must be a finite number > 0, got {scale!r}")


def _verify_checksums(meta: dict, tensors: dict, path: str):
    sums = _field(meta, "checksums", path)
    if not (isinstance(sums, dict) and isinstance(sums.get("tensors"), dict) and isinstance(sums.get("meta"), dict)):
        _fail(path, "metadata field 'checksums' is malformed (the file was edited or damaged)")
    for k in sorted(set(sums["meta"]) | (set(meta) - {"checksums"})):
        if k not in meta:
            _fail(path, f"metadata field {k!r} is missing (the file was edited or damaged)")
        if k not in sums["meta"]:
            _fail(path, f"metadata field {k!r} was added after the file was saved")
        if _digest_value(meta[k]) != sums["meta"][k]:
            _fail(path, f"metadata field {k!r} does not match its checksum: the file was edited or damaged")
    for k in sorted(set(sums["tensors"]) | set(tensors)):
        if k not in tensors:
            _fail(path, f"tensor {k} is missing (the file was edited or damaged)")
        if k not in sums["tensors"]:
            _fail(path, f"tensor {k} was added after the file was saved")
        if _digest_tensor(k, tensors[k]) != sums["tensors"][k]:
            _fail(path, f"tensor {k} does not match its checksum: the file was edited or damaged")


def _read_ngf(path: str) -> tuple[dict, dict]:
    """Metadata and tensors of a safetensors file, or a clear error."""
    from safetensors import safe_open

    try:
        with safe_open(path, framework="pt") as f:
            raw = (f.metadata() or {}).get("neurogf")
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except Exception as e:
        raise InputError(f"could not read {path}: not a neurogf-warp model file nor a PyTorch checkpoint, "
                         f"or a damaged one ({e})") from e
    meta = None
    if raw is not None:
        try:
            meta = json.loads(raw)
        except ValueError:
            _fail(path, "the model metadata is not valid JSON (the file was edited or damaged)")
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise InputError(f"{path} is a safetensors file but not a neurogf-warp model (no '{FORMAT}' metadata)")
    return meta, tensors


def _load_ngf(path: str, mesh, check_mesh: bool) -> Model:
    meta, tensors = _read_ngf(path)
    version = _field(meta, "format_version", path)
    if isinstance(version, bool) or not isinstance(version, int) or version < 1:
        _fail(path, f"'format_version' must be a positive integer, got {version!r}")
    if version > FORMAT_VERSION:
        _fail(path, f"written by a newer neurogf-warp (format {version}; this one reads up to {FORMAT_VERSION}): "
              "upgrade the package")
    if version >= 2:
        _verify_checksums(meta, tensors, path)

    options = _check_options(_field(meta, "net_options", path), path)
    net = _net_from_state({k[4:]: v for k, v in tensors.items() if k.startswith("net.")}, path, options)
    D = _field(meta, "D", path)
    if isinstance(D, bool) or D != net.D:
        _fail(path, f"metadata field 'D' is {D!r} but the stored weights have D={net.D}")
    center, scale = _field(meta, "center", path), _field(meta, "scale", path)
    _check_frame(center, scale, "center", "scale", path)
    config = meta.get("config") or {}
    if not isinstance(config, dict):
        _fail(path, f"metadata field 'config' must be a JSON object, got {type(config).__name__}")
    querier = None
    qstate = {k[8:]: v for k, v in tensors.items() if k.startswith("querier.")}
    if qstate:
        querier = SdfQuerier()
        _strict_load(querier, qstate, "SDF querier", path)
        _check_weights(qstate, path, "querier.")
    unknown = sorted(k for k in tensors if not k.startswith(("net.", "querier.", "mesh.")) and k != LANDMARK_TABLE)
    if unknown:
        _fail(path, f"unexpected tensors {', '.join(unknown)}")

    want = _field(meta, "mesh_fingerprint", path)
    if want is not None and not (isinstance(want, str) and len(want) == 64):
        _fail(path, f"'mesh_fingerprint' must be a 64-character SHA-256 hex string or null, got {want!r}")
    stored = _stored_mesh(meta, tensors, version, want, path)
    if mesh is not None:
        m = load_mesh(mesh)
        # format 1 stored the fingerprint of the input arrays as given (unused vertices included)
        known = {m.fingerprint} | ({m._v1_fingerprint} if version == 1 and m._v1_fingerprint else set())
        if check_mesh and want is not None and want not in known:
            raise MeshMismatchError(f"{path} was trained on a different mesh (fingerprint {want[:12]}..., given "
                                    f"{m.fingerprint[:12]}...)", "Pass the training mesh, or check_mesh=False to "
                                    "query this mesh in the model's stored frame.")
    else:
        m = stored
    landmarks = _landmarks(net, tensors.get(LANDMARK_TABLE), m, stored, want, path)
    # without a mesh the stored normalization is still the frame the model answered in when it was saved
    return Model(net=net, querier=querier, mesh=m, center=np.asarray(center, dtype=np.float64), scale=float(scale),
                 config=dict(config), mesh_frame=m is None, landmarks=landmarks)


def _landmarks(net: NeuroGFNet, table, mesh: Mesh | None, stored: Mesh | None, fingerprint, path: str):
    """A landmark network's table in the mesh file's numbering (rows of unused input vertices NaN), checked;
    None for other networks and for a model loaded without a mesh."""
    if not net.landmarks:
        if table is not None:
            _fail(path, f"tensor {LANDMARK_TABLE} is stored but the network has no landmarks")
        return None
    if table is None:
        _fail(path, f"the network reads {net.landmarks} landmark distances per vertex but tensor {LANDMARK_TABLE} is "
              "missing (the file was edited or damaged)")
    t = table.numpy()
    if mesh is None:
        return None  # the frame is kept; vertex queries need the mesh, and with it the table
    if mesh.fingerprint != fingerprint:
        raise InputError(f"{path}: a network with landmarks answers from its table of distances at its training "
                         "mesh's vertices, so it cannot query another mesh: pass the training mesh")
    V = len(mesh.internal_vertices)
    if t.dtype != np.float32 or t.shape != (V, net.landmarks):
        _fail(path, f"tensor {LANDMARK_TABLE} must be ({V}, {net.landmarks}) float32, got {t.dtype} {t.shape}")
    if not (np.all(np.isfinite(t)) and t.min() >= 0.0 and t.max() <= LANDMARK_UNREACHED):
        _fail(path, f"tensor {LANDMARK_TABLE} must hold distances in [0, {LANDMARK_UNREACHED:g}] (normalized units; "
              f"{LANDMARK_UNREACHED:g}: another component)")
    out = np.full((mesh.n_input, net.landmarks), np.nan, np.float32)
    used = mesh.input_to_internal >= 0
    out[used] = t[mesh.input_to_internal[used]]
    return out


def _stored_mesh(meta: dict, tensors: dict, version: int, fingerprint, path: str) -> Mesh | None:
    """The mesh stored in the file, every array checked against the others; None when there is none."""
    names = MESH_TENSORS if version == 1 else MESH_TENSORS_V2
    present = [k for k in names if k in tensors]
    extra = sorted(k for k in tensors if k.startswith("mesh.") and k not in names)
    if extra:
        _fail(path, f"unexpected mesh tensors {', '.join(extra)}")
    if not present:
        return None
    if len(present) != len(names):
        _fail(path, f"the stored mesh is incomplete: missing {', '.join(k for k in names if k not in tensors)}")
    if fingerprint is None:
        _fail(path, "metadata field 'mesh_fingerprint' is null but the file stores a mesh")
    v, f, idx = (tensors[k].numpy() for k in MESH_TENSORS)
    if v.dtype != np.float64 or v.ndim != 2 or v.shape[1] != 3 or len(v) < 3:
        _fail(path, f"tensor mesh.vertices must be (V >= 3, 3) float64, got {v.dtype} {v.shape}")
    if not np.all(np.isfinite(v)):
        _fail(path, "tensor mesh.vertices holds NaN or inf values")
    V = len(v)
    if f.dtype != np.int32 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        _fail(path, f"tensor mesh.faces must be (F >= 1, 3) int32, got {f.dtype} {f.shape}")
    if f.min() < 0 or f.max() >= V:
        _fail(path, f"tensor mesh.faces indexes vertices {f.min()}..{f.max()}, outside [0, {V})")
    if len(np.unique(f)) != V:
        _fail(path, "tensor mesh.faces leaves stored vertices unused (a stored mesh holds used vertices only)")
    n_input = _field(meta, "mesh_n_input", path)
    if isinstance(n_input, bool) or not isinstance(n_input, int) or n_input < V:
        _fail(path, f"metadata field 'mesh_n_input' must be an integer >= the {V} stored vertices, got {n_input!r}")
    if idx.dtype != np.int64 or idx.shape != (V,):
        _fail(path, f"tensor mesh.index must be ({V},) int64, one entry per stored vertex; got {idx.dtype} {idx.shape}")
    if idx[0] < 0 or idx[-1] >= n_input or np.any(np.diff(idx) <= 0):
        _fail(path, f"tensor mesh.index must increase strictly within [0, {n_input})")
    mc, ms = _field(meta, "mesh_center", path), _field(meta, "mesh_scale", path)
    _check_frame(mc, ms, "mesh_center", "mesh_scale", path)
    center = (v.min(0) + v.max(0)) / 2.0
    radius = np.linalg.norm(v - center, axis=1).max()
    if not radius > 0:
        _fail(path, "tensor mesh.vertices is degenerate: all vertices coincide")
    if (not np.allclose(mc, center, rtol=FRAME_RTOL, atol=FRAME_RTOL * radius)
            or not math.isclose(ms, 1.0 / radius, rel_tol=FRAME_RTOL)):
        _fail(path, "'mesh_center'/'mesh_scale' do not match the stored vertices (the file was edited or damaged)")
    # format 1 stored the fingerprint of the input arrays, which a mesh with unused vertices does not keep
    if (version >= 2 or n_input == V) and mesh_fingerprint(v, f) != fingerprint:
        _fail(path, "the stored mesh (mesh.vertices, mesh.faces) does not match 'mesh_fingerprint' "
              "(the file was edited or damaged)")
    inverse = components = None
    if version >= 2:
        inv, comp = tensors["mesh.input_to_internal"].numpy(), tensors["mesh.components"].numpy()
        if inv.dtype != np.int64 or inv.shape != (n_input,):
            _fail(path, f"tensor mesh.input_to_internal must be ({n_input},) int64, got {inv.dtype} {inv.shape}")
        if inv.min() < -1 or inv.max() >= V or not np.array_equal(inv[idx], np.arange(V)):
            _fail(path, "tensor mesh.input_to_internal does not map the stored vertices onto themselves "
                  f"(values must lie in [-1, {V}) and mesh.index[i] must map to i)")
        if comp.dtype != np.int32 or comp.shape != (V,):
            _fail(path, f"tensor mesh.components must be ({V},) int32, got {comp.dtype} {comp.shape}")
        components = component_labels(V, f)
        if not np.array_equal(comp, components):
            _fail(path, "tensor mesh.components does not match the connected components of mesh.faces")
        inverse = inv.astype(np.int64)
    return Mesh(internal_vertices=v.astype(np.float64), internal_faces=f.astype(np.int32), index=idx.astype(np.int64),
                n_input=int(n_input), center=np.asarray(mc, dtype=np.float64), scale=float(ms),
                fingerprint=fingerprint, _inverse=inverse, _components=components)
