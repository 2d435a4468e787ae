"""Small entry points for the existing package (``ngf.load``) to reach this subpackage (the command line's are in
``neurogf_warp/cli/gen.py``).

Kept here so that the hooks in the modules outside this subpackage stay one or two lines each.
"""
from __future__ import annotations


def load_if_generalizable(path, mesh=None):
    """For ``ngf.load``: None when ``path`` is not a generalizable-network file; otherwise the
    :class:`~neurogf_warp.generalizable.model.GeneralizableModel`, or, when ``mesh`` is given, the model already
    conditioned on that mesh (a :class:`~neurogf_warp.generalizable.model.Conditioned`)."""
    from neurogf_warp.generalizable.network import is_generalizable_file

    try:  # torch files are zip archives; anything else (an .ngf, a missing file) is left to the per-mesh loader
        with open(path, "rb") as f:
            if f.read(2) != b"PK":
                return None
    except OSError:
        return None
    if not is_generalizable_file(path):
        return None
    from neurogf_warp.generalizable.model import load

    model = load(path)
    return model.condition(mesh) if mesh is not None else model


def summary(model) -> dict:
    """What a generalizable network (or one conditioned on a shape) holds, as a JSON-ready dict (``info``)."""
    cond = model if hasattr(model, "wn") else None
    net = cond.model if cond is not None else model
    out = {"kind": "generalizable NeuroGF (one network for a family of shapes, conditioned on a point cloud)",
           "parameters": int(sum(p.numel() for p in net.net.parameters())),
           "cloud_points": net.cloud_points, "neighbours": int(net.net.backbone.econv_1.k),
           "queries": "distance, ssad, msad, distance_matrix once conditioned on a shape (--mesh); no SDF or path "
                      "head (sdf, path, render, eval need a per-mesh model)"}
    meta = {k: v for k, v in net.meta.items() if k in ("trained_on", "config", "step", "elapsed_s", "val_mre",
                                                        "world_size", "date_utc")}
    if meta:
        meta.get("trained_on", {}).pop("train_files", None)
        meta.get("trained_on", {}).pop("val_files", None)
        out["training"] = meta
    if cond is not None:
        out["conditioned_on"] = {"points": int(len(cond.points)), "center": cond.center.tolist(), "scale": cond.scale}
        if cond.mesh is not None:
            m = cond.mesh
            out["conditioned_on"]["mesh"] = {"vertices_as_given": int(m.n_input), "faces": int(len(m.faces)),
                                             "components": int(m.n_components)}
    return out


def cli_info(args, model, write) -> int:
    """``neurogf-warp info FILE`` of a generalizable network: ``write`` its summary (text or --json)."""
    import json

    info = summary(model)
    if args.json:
        write(json.dumps(info, indent=1) + "\n")
        return 0
    lines = [f"{args.model}: {info['kind']}, {info['parameters']:,} parameters, "
             f"{info['cloud_points']}-point clouds, k={info['neighbours']} neighbours",
             f"  queries: {info['queries']}"]
    t = info.get("training")
    if t:
        lines.append(f"  training: step {t.get('step', '?')}, {t.get('elapsed_s', 0) or 0:.0f} s, validation MRE "
                     f"{t.get('val_mre')}")
    else:
        lines.append("  training: the released network (no training record in the file)")
    c = info.get("conditioned_on")
    if c:
        lines.append(f"  conditioned on {c['points']} points" +
                     (f" of a mesh of {c['mesh']['vertices_as_given']} vertices" if "mesh" in c else ""))
    write("\n".join(lines) + "\n")
    return 0

