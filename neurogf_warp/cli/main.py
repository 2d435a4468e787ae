"""The ``neurogf-warp`` command line: one argparse program, one function per subcommand that builds its parser
(``_add_<command>``) and one that runs it (``_cmd_<command>``); the domain logic lives in the library.

Each subcommand checks its options and output file first, then calls the public API (torch and Warp are
imported only then, so ``--help`` is fast). Results go to the file named with ``-o``, or to stdout when a
command has no ``-o``: nothing is written that the user did not name. Messages go to stderr in the command
line's own terms (its flags, not the Python API's arguments); ``-q`` keeps only results and errors.

Exit codes: 0 success; 2 bad input (``common.checks.InputError``, and for now the plain ``ValueError`` and
file errors that the other stages raise for bad input, see ``USER_ERRORS``); 1 a failure (a full disk, a
device error) or a bug of ours, reported as such with what to report; 130 interrupted. A closed stdout
(``neurogf-warp info --json | head``) ends the command quietly; a process started without stdout (``>&-``) that has
results to print fails saying so, and one started without stderr runs with its messages discarded. Warp's banner,
module-compile lines and the CUDA-driver warning of a GPU-less machine are shown only with ``--verbose``.

The generalizable network's commands (``gen-shapes``, ``gen-train``, ``gen-per-mesh``, see ``cli/gen.py``) are
listed in the help and share the exit codes and error messages, with their own parsers.
"""
from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time
import warnings

from neurogf_warp import __version__
from neurogf_warp.cli.gen import GEN_COMMANDS
from neurogf_warp.common.checks import InputError, finite_arg, number, say
from neurogf_warp.common.files import input_guard, output_target
from neurogf_warp.training.presets import DESCRIPTIONS, describe

__all__ = ["main", "build_parser", "BadInput", "model_summary"]

PROG = "neurogf-warp"
PRESET_HELP = ("training preset, one of " + "; ".join(describe(n) for n in DESCRIPTIONS)
               + ". Default: chosen by the device and the mesh size (default on a GPU, cpu or cpu_large on a CPU)")
VALUE_FORMATS = (".npy", ".csv", ".ply")
MIN_SIZE, MAX_SIZE = 16, 16384  # render --size, pixels per side
# what refinement does and what it costs, without a figure: its time depends on the network's width, the number
# of pairs and points, the sweeps and the device, and is fast on a GPU
REFINE_COST = ("each sweep moves every path point along the network's SDF surface to shorten the path, evaluating the "
               "SDF network at every point: fast on a GPU, slower on a CPU, growing with pairs x points x sweeps")

BadInput = InputError  # the name this module used before common.checks had the type
_STARTED_WITHOUT_STDOUT = False  # set by main(): stdout was closed when the process started


class _StdoutClosed(Exception):
    """The reader of our stdout went away (a pipe into ``head``): stop quietly."""


class _NoStdout(Exception):
    """The process was started with stdout closed (``>&-``) and has results to print: a failure, said so."""


# ------------------------------------------------------------------------------------------ parser

def _common() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--device", default=None, help="cpu or cuda:N (default: the GPU if there is one, else cpu)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("-q", "--quiet", action="store_true",
                   help="no progress bars, messages or warnings: only results and errors")
    g.add_argument("-v", "--verbose", action="store_true",
                   help="also Warp's own log (banner, kernel compilation) and a traceback on errors")
    return p


def _model_args(p: argparse.ArgumentParser):
    p.add_argument("model", help="model file: an .ngf written by train, or a released NeuroGF *_final.pth")
    p.add_argument("--mesh", default=None,
                   help="the model's mesh file; required for a released .pth (an .ngf carries its own)")
    p.add_argument("--allow-mesh-mismatch", action="store_true",
                   help="go on when --mesh is not the mesh the model was trained on (another fingerprint for an "
                        ".ngf, off the checkpoint's surface for a .pth); its answers are then not geodesics of "
                        "that mesh. Without it such a mesh is refused (exit code 2)")


def _pair_args(p: argparse.ArgumentParser):
    _model_args(p)
    for flag, name in (("--p", "start points p"), ("--q", "end points q (as many as p)")):
        p.add_argument(flag, nargs="+", metavar=("X Y Z | FILE", ""), required=True,
                       help=f"{name}: one point as three numbers (mesh coordinates), or a .npy / .csv file of (N, 3) "
                            "points")


def _values_output(p: argparse.ArgumentParser):
    p.add_argument("-o", "--output", default=None,
                   help="output file: .npy, .csv (vertex,distance) or .ply (the mesh coloured by distance); "
                        "default: print one distance per line to stdout, line i for vertex i ('nan' for vertices "
                        "no face uses)")


def _budget(text: str) -> float:
    """--budget-seconds: a finite number of seconds > 0, checked while parsing (before any work or folder)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    try:
        return number("--budget-seconds", value, above=0.0)
    except InputError as e:
        raise argparse.ArgumentTypeError(str(e).replace("--budget-seconds ", "")) from None


def _finite(flag: str):
    """An argparse type: a finite number (nan and inf refused, naming ``flag``)."""
    return finite_arg(flag)


def build_parser() -> argparse.ArgumentParser:
    """The whole command line (``neurogf-warp COMMAND ...``)."""
    common = _common()
    p = argparse.ArgumentParser(
        prog=PROG, description="Neural geodesic fields (NeuroGF) with NVIDIA Warp: ground truth, training and "
        "fast geodesic queries on triangle meshes.",
        epilog="run 'neurogf-warp COMMAND -h' for a command's options; exit codes: 0 success, 1 failure, 2 bad "
               "input, 130 interrupted")
    p.add_argument("--version", action="version", version=f"{PROG} {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for add in (_add_demo, _add_data, _add_train, _add_eval, _add_ssad, _add_msad, _add_distance, _add_path,
                _add_info, _add_render):
        add(sub, common)
    from neurogf_warp.cli import tools

    tools.add_commands(sub, common, sys.modules[__name__])
    # listed here; main() hands their arguments to their own parsers (`neurogf-warp gen-train -h`)
    for name, line in GEN_COMMANDS.items():
        sub.add_parser(name, help=line, add_help=False)
    return p


def _add_demo(sub, common):
    d = sub.add_parser("demo", parents=[common], help="train on the bundled mesh (or yours), report accuracy, answer SSAD",
                       description="The main job: train a NeuroGF on the bundled default mesh (or --mesh), measure its "
                       "accuracy against the solver (and the heat method when potpourri3d is installed), and answer "
                       "an SSAD query. Safe to repeat: a finished run is reused (--force trains again).")
    d.add_argument("-o", "--output", default="neurogf-demo",
                   help="output folder for the model, its run files and the results (default: ./neurogf-demo)")
    d.add_argument("--mesh", default=None, help="a mesh file (default: the bundled generated blob, 2,562 vertices)")
    d.add_argument("--budget-seconds", type=_budget, default=None,
                   help="seconds for the whole training call, dataset included (default 180 on a CPU, 300 on a GPU)")
    d.add_argument("--force", action="store_true", help="train again even if the folder holds a finished run")
    d.set_defaults(run=_cmd_demo)


DEVICES_HELP = ("GPUs that share the ground truth: all, or a list such as cuda:0,cuda:1 (default: the environment "
                "variable NEUROGF_DEVICES where set, else --device alone)")


def _add_data(sub, common):
    t = sub.add_parser("data", parents=[common], help="build a training dataset (ground-truth geodesics and paths)",
                       description="Compute NeuroGF training data for a mesh with the Warp geodesic solver: distance "
                       "rows from sources to targets, shortest paths, surface points and held-out test fields.")
    t.add_argument("mesh", help="triangle mesh file (.obj, .ply, .stl, ...)")
    t.add_argument("-o", "--output", required=True, help="dataset file to write (.npz)")
    t.add_argument("--preset", default=None, help=PRESET_HELP + " (its dataset settings are used)")
    t.add_argument("--sources", type=int, default=None, help="distance sources (default: the preset's)")
    t.add_argument("--path-sources", type=int, default=None, help="path sources (default: the preset's)")
    t.add_argument("--test-sources", type=int, default=None, help="held-out test sources (default: the preset's)")
    t.add_argument("--k", type=int, default=None, help="Steiner points per edge of the solver (default 3)")
    t.add_argument("--seed", type=int, default=0, help="random seed of every draw (default 0)")
    t.add_argument("--devices", default=None, help=DEVICES_HELP)
    t.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="any other dataset setting, e.g. --set n_global=2048 (repeatable)")
    t.set_defaults(run=_cmd_data)


def _add_train(sub, common):
    t = sub.add_parser("train", parents=[common], help="train a NeuroGF model for a mesh",
                       description="Train a NeuroGF for one mesh and write the model file. The run's checkpoint, "
                       "cached dataset and log go to the folder <model>.train beside it. Running the same command "
                       "again continues an interrupted run or reports a finished one.")
    t.add_argument("mesh", help="triangle mesh file (.obj, .ply, .stl, ...)")
    t.add_argument("-o", "--output", required=True, help="model file to write (e.g. model.ngf)")
    t.add_argument("--preset", default=None, help=PRESET_HELP)
    t.add_argument("--paper", action="store_true", help="the same as --preset paper")
    t.add_argument("--budget-seconds", type=_budget, default=None,
                   help="fit the step counts so that the whole call, dataset included, takes about this long")
    g = t.add_mutually_exclusive_group()
    g.add_argument("--resume", action="store_true",
                   help="continue the run in <model>.train with its own settings (also a finished one)")
    g.add_argument("--force", action="store_true", help="start over, replacing an existing run and model file")
    t.add_argument("--dataset", default=None, help="train on this dataset .npz instead of building one")
    t.add_argument("--devices", default=None, help=DEVICES_HELP + "; the steps run on --device, else the first")
    t.add_argument("--no-distributed", action="store_true",
                   help="under torchrun (WORLD_SIZE > 1), do not train data-parallel over the ranks (the default: "
                        "one GPU per rank, rank 0 writes the model); each process would then train alone")
    t.add_argument("--weld", action="store_true",
                   help="merge vertices with exactly equal coordinates first (seams stored twice)")
    t.add_argument("--allow-vertex-joins", action="store_true",
                   help="train a mesh whose patches meet only at single vertices (refused by default: geodesics "
                        "through such vertices are fitted poorly)")
    t.add_argument("--D", type=int, default=None, help="embedding width: 64, 128, 256 or 512 (default: the preset's)")
    t.add_argument("--epochs", type=int, default=None, help="joint-training epochs (default: the preset's)")
    t.add_argument("--iters-per-epoch", type=int, default=None, help="steps per epoch (default: the preset's)")
    t.add_argument("--lr", type=_finite("--lr"), default=None, help="learning rate of the querier and joint stages")
    t.add_argument("--n-sources", type=int, default=None, help="distance sources of the dataset")
    t.add_argument("--seed", type=int, default=None, help="random seed (dataset, initialization, batches)")
    t.add_argument("--no-amp", action="store_true", help="float32 path head (default: bf16 on CUDA)")
    t.add_argument("--no-compile", action="store_true",
                   help="skip torch.compile (default on CUDA: faster steps after ~25 s of compiling)")
    t.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="any training setting, e.g. --set batch_g=131072 --set schedule.lr=3e-3 (repeatable; "
                        "names as in neurogf_warp.training.TrainConfig)")
    t.set_defaults(run=_cmd_train)


def _add_eval(sub, common):
    e = sub.add_parser("eval", parents=[common], help="measure a model's accuracy",
                       description="Distance MRE against an exact reference (or the solver), path Chamfer-L1 against "
                       "solver paths, SDF L1; optionally the heat method on the same sources.")
    _model_args(e)
    e.add_argument("--reference", default=None,
                   help="exact-distance .npz (positions, orig_index or file_index, sources, dist)")
    e.add_argument("--heat", action="store_true", help='also run the heat method (needs pip install "neurogf-warp[heat]")')
    e.add_argument("--sources", type=int, default=8, help="solver sources when no reference is given (default 8)")
    e.add_argument("--path-sources", type=int, default=8, help="sources of the random path pairs (default 8)")
    e.add_argument("--path-targets", type=int, default=8, help="targets per path source (default 8)")
    e.add_argument("--no-paths", action="store_true", help="skip the path comparison")
    e.add_argument("--no-sdf", action="store_true", help="skip the SDF comparison")
    e.add_argument("--path-refine", type=int, default=0, metavar="N",
                   help="also score the paths after N shortening sweeps per level (e.g. 50; "
                        + REFINE_COST + ")")
    e.add_argument("--surface", type=int, default=0, metavar="N",
                   help="also reconstruct the SDF head's surface with N grid samples along the longest side (e.g. "
                        "256) and report its Chamfer-L1 and Hausdorff distance to the mesh")
    e.add_argument("--seed", type=int, default=0, help="random seed of the solver sources and path pairs")
    e.add_argument("--json", default=None, help="also write the results to this .json file")
    e.set_defaults(run=_cmd_eval)


def _add_ssad(sub, common):
    s = sub.add_parser("ssad", parents=[common], help="distances from one source to every mesh vertex",
                       description="Single source, all destinations: the model's geodesic distance from one vertex "
                       "or point to every vertex of the mesh, in mesh units and the mesh file's vertex numbering.")
    _model_args(s)
    g = s.add_mutually_exclusive_group()
    g.add_argument("--source", type=int, default=None, help="source vertex index, 0-based, the mesh's own numbering "
                   "(default 0)")
    g.add_argument("--point", type=_finite("--point"), nargs=3, metavar=("X", "Y", "Z"),
                   help="source point in mesh coordinates")
    _values_output(s)
    s.set_defaults(run=_cmd_ssad)


def _add_msad(sub, common):
    s = sub.add_parser("msad", parents=[common], help="distance from every vertex to the nearest of several sources",
                       description="Multiple sources, all destinations: each vertex's geodesic distance to its "
                       "nearest source vertex.")
    _model_args(s)
    s.add_argument("--sources", type=int, nargs="+", required=True, metavar="V",
                   help="source vertex indices, 0-based, the mesh's own numbering")
    _values_output(s)
    s.set_defaults(run=_cmd_msad)


def _add_distance(sub, common):
    s = sub.add_parser("distance", parents=[common], help="geodesic distances between point pairs",
                       description="Geodesic distance between points p and q (mesh coordinates and units), pair by "
                       "pair; points should lie on or near the surface.")
    _pair_args(s)
    s.add_argument("-o", "--output", default=None, help="output .npy or .csv (default: print the distances to stdout, "
                   "one per line)")
    s.set_defaults(run=_cmd_distance)


def _add_path(sub, common):
    s = sub.add_parser("path", parents=[common], help="shortest paths between point pairs",
                       description="Shortest surface paths from p to q as m points each (mesh coordinates). By "
                       "default every point is put on the mesh (--project mesh); the summary line says how far "
                       "the network's own points were from it.")
    _pair_args(s)
    s.add_argument("--m", type=int, default=128, help="points per path, ends included (default 128)")
    s.add_argument("--refine", type=int, default=0, metavar="N",
                   help="N shortening sweeps per level on the network's SDF surface (e.g. 50; default 0: the path "
                        "head's path); " + REFINE_COST)
    s.add_argument("--project", choices=("none", "sdf", "mesh"), default=None,
                   help="where the points go: mesh (each snapped to the closest point of the mesh; the default "
                        "when the model has a mesh), sdf (Newton steps onto the network's SDF surface; the default "
                        "without a mesh), none (the network's points as they come: they can lie inside or outside "
                        "the surface)")
    s.add_argument("-o", "--output", default=None,
                   help="output .npy of shape (N, m, 3), or .csv with rows path,point,x,y,z; default: print the "
                        "CSV rows to stdout")
    s.set_defaults(run=_cmd_path)


def _add_info(sub, common):
    s = sub.add_parser("info", parents=[common], help="what a model file holds",
                       description="Print what a model file holds: network width and options, normalization, mesh "
                       "size, fingerprint and components, training settings and steps.")
    _model_args(s)
    s.add_argument("--json", action="store_true", help="print it as JSON")
    s.set_defaults(run=_cmd_info)


def _add_render(sub, common):
    s = sub.add_parser("render", parents=[common], help="a picture of the distance field (and paths)",
                       description="Render the mesh coloured by the geodesic distance from the sources, with isolines "
                       "and optionally shortest paths to some vertices (their targets marked with dark spheres). The "
                       "camera faces the source(s) unless --view is given; everything fits in the frame.")
    _model_args(s)
    s.add_argument("--source", type=int, nargs="+", default=[0], metavar="V",
                   help="source vertex indices (default 0); several: distance to the nearest")
    s.add_argument("--paths", type=int, nargs="+", default=None, metavar="V",
                   help="also draw the shortest paths from the first source to these vertices")
    s.add_argument("--refine", type=int, default=0, metavar="N",
                   help="shortening sweeps for the model's paths (default 0: the path head's); " + REFINE_COST)
    field = s.add_mutually_exclusive_group()
    field.add_argument("--exact", metavar="REF.npz", help="draw the exact field of this reference file (positions, "
                       "file_index or orig_index, sources, dist) instead of the model's; paths from the geodesic solver")
    field.add_argument("--heat", action="store_true", help="draw the heat method's field (potpourri3d) instead of the "
                       "model's; paths from potpourri3d's edge-flip solver")
    s.add_argument("--isolines", type=int, default=20, help="number of isolines (default 20; 0: none)")
    s.add_argument("--vrange", type=_finite("--vrange"), nargs=2, default=None, metavar=("LOW", "HIGH"),
                   help="the colour scale's range in mesh units (default: the field's), to compare pictures")
    s.add_argument("--view", type=_finite("--view"), nargs=2, default=None, metavar=("AZIMUTH", "ELEVATION"),
                   help="camera direction in degrees: azimuth around the up axis (0: from the axis after it in x, y, "
                        "z order, e.g. +z for up y) and elevation above the plane across it (default: facing the "
                        "source, or several sources when they lie mostly on one side; elevation within 60 degrees)")
    s.add_argument("--up", default="auto", choices=("auto", "x", "y", "z", "-x", "-y", "-z"),
                   help="the mesh axis drawn upward (default auto: z when the mesh is at least 1.2 times taller "
                        "along z than along y, else y)")
    s.add_argument("--size", type=int, nargs=2, default=(1024, 1024), metavar=("W", "H"),
                   help=f"picture size in pixels, each {MIN_SIZE} to {MAX_SIZE} (default 1024 1024)")
    s.add_argument("-o", "--output", required=True, help="picture file (.png)")
    s.set_defaults(run=_cmd_render)


# ---------------------------------------------------------------------------------------- utilities

def start_warp(verbose: bool):
    """Import and initialize Warp: quiet (log level WARNING, no driver warning) unless ``verbose``."""
    from neurogf_warp.common.warp_setup import init_warp

    return init_warp(verbose=True if verbose else None)


def _say(args, msg: str):
    say(not args.quiet, msg)


def _plural(n: int, word: str, plural: str | None = None) -> str:
    """'1 path', '3 paths'."""
    return f"{n} {word if n == 1 else (plural or word + 's')}"


def _stdout_write(text: str):
    """Write to stdout; a reader that went away (``| head``) ends the command quietly."""
    if _STARTED_WITHOUT_STDOUT:
        raise _NoStdout()
    try:
        sys.stdout.write(text)
        sys.stdout.flush()
    except BrokenPipeError:
        raise _StdoutClosed() from None


def _check_output(path: str, formats: tuple, what: str = "output") -> str:
    """Refuse an unknown extension or a folder that cannot be written, before any work."""
    ext = os.path.splitext(path)[1].lower()
    if ext not in formats:
        raise InputError(f"{what} {path!r}: the file extension chooses the format; use one of {', '.join(formats)}")
    full = os.path.abspath(path)
    if os.path.isdir(full):
        raise InputError(f"{what} {path!r} is a folder; give a file name")
    folder = os.path.dirname(full)
    if not os.path.isdir(folder):
        raise InputError(f"cannot write {path}: folder {folder} does not exist")
    if not os.access(folder, os.W_OK) or (os.path.exists(full) and not os.access(full, os.W_OK)):
        raise InputError(f"cannot write {path}: permission denied")
    output_target(path, what=what)  # a device, FIFO or socket is refused here, before any work
    return ext


def _write_values(path: str, values, mesh):
    """Per-vertex values (file numbering) to .npy, .csv (vertex,value) or .ply (coloured mesh)."""
    import numpy as np

    from neurogf_warp.common.files import atomic_write

    ext = os.path.splitext(path)[1].lower()
    values = np.asarray(values)
    if ext == ".npy":
        atomic_write(path, lambda f: np.save(f, values))
    elif ext == ".csv":
        rows = np.column_stack([np.arange(len(values)), values])
        atomic_write(path, lambda f: np.savetxt(f, rows, fmt=["%d", "%.9g"], delimiter=",", header="vertex,distance",
                                                comments=""))
    else:
        from neurogf_warp.pictures.render import write_ply

        write_ply(path, mesh, values)


def _write_array(path: str, a, header: str, fmt):
    import numpy as np

    from neurogf_warp.common.files import atomic_write

    if path.lower().endswith(".npy"):
        atomic_write(path, lambda f: np.save(f, a))
    else:
        atomic_write(path, lambda f: np.savetxt(f, a, fmt=fmt, delimiter=",", header=header, comments=""))


def _print_array(a, header: str | None, fmt):
    import io

    import numpy as np

    buf = io.StringIO()
    np.savetxt(buf, a, fmt=fmt, delimiter=",", header=header or "", comments="")
    _stdout_write(buf.getvalue())


def _load_model(args, needs_mesh: bool):
    """The model of ``args.model`` (with ``--mesh``): a mesh that is not the model's is refused unless
    ``--allow-mesh-mismatch``; then it is used, with a warning (unless -q)."""
    import neurogf_warp as ngf
    from neurogf_warp.model.checkpoint_match import (
        MeshMismatchError,
        MeshMismatchWarning,
    )

    from neurogf_warp.generalizable.hooks import load_if_generalizable

    gen = load_if_generalizable(args.model)  # refused before it is conditioned on --mesh (seconds of work)
    if gen is not None and args.command not in ("info", "ssad", "msad", "distance"):
        raise InputError(f"{args.model} is a generalizable network: it answers info, ssad, msad and distance (with "
                         f"--mesh MESHFILE); {args.command} needs a per-mesh model (neurogf-warp train)")
    if gen is not None:
        return gen.condition(args.mesh) if args.mesh is not None else gen
    allow = getattr(args, "allow_mesh_mismatch", False)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", MeshMismatchWarning)
        try:
            model = ngf.load(args.model, mesh=args.mesh, check_mesh=not allow)
        except MeshMismatchError as e:
            raise InputError(f"{e.problem}. Pass the mesh it was trained on with --mesh, or --allow-mesh-mismatch "
                             "to query this mesh in the model's stored frame anyway") from None
    for w in caught:
        if issubclass(w.category, MeshMismatchWarning):
            if not allow:
                raise InputError(f"{w.message} To go on anyway, pass --allow-mesh-mismatch.")
            _say(args, f"{PROG} {args.command}: warning: {w.message} (going on: --allow-mesh-mismatch)")
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    if needs_mesh and model.mesh is None:
        raise InputError(f"{args.model} carries no mesh: pass the mesh it was trained on with --mesh MESHFILE")
    return model


def _vertex_indices(model, indices, flag: str):
    m = model.mesh
    n = m.n_input
    for i in indices:
        if i < 0 or i >= n:
            raise InputError(f"{flag} {i} is out of range: the mesh has {n} vertices, numbered 0 to {n - 1}")
        if m.input_to_internal[i] < 0:
            raise InputError(f"{flag} {i}: vertex {i} is not used by any face of the mesh, so it has no geodesic "
                             "distances; pick a vertex of the surface")
    return list(indices)


def _points(values, flag: str):
    """--p / --q: three numbers, or one .npy / .csv file of (N, 3) points -> (N, 3) float64."""
    import numpy as np

    if len(values) == 3:
        try:
            a = np.array([[float(v) for v in values]])
        except ValueError:
            a = None
        if a is not None:
            if not np.isfinite(a).all():
                raise InputError(f"{flag} {' '.join(values)}: coordinates must be finite numbers")
            return a
    if len(values) == 1:
        path = values[0]
        if not os.path.isfile(path):
            raise InputError(f"{flag} {path}: no such file (give X Y Z, or a .npy / .csv file of (N, 3) points)")
        ext = os.path.splitext(path)[1].lower()
        try:
            a = np.load(path, allow_pickle=False) if ext == ".npy" else \
                np.loadtxt(path, delimiter=",", ndmin=2) if ext == ".csv" else None
        except Exception as e:  # noqa: BLE001 - any unreadable file is bad input
            raise InputError(f"{flag} {path}: unreadable ({e})") from e
        if a is None:
            raise InputError(f"{flag} {path}: use a .npy or .csv file")
        a = np.asarray(a, dtype=np.float64)
        if a.ndim != 2 or a.shape[1] != 3:
            raise InputError(f"{flag} {path}: expected (N, 3) points, got shape {a.shape}")
        bad = np.flatnonzero(~np.isfinite(a).all(axis=1))
        if len(bad):
            raise InputError(f"{flag} {path}: point {bad[0]} (row {bad[0]}, 0-based) is not finite: {a[bad[0]]}; "
                             f"{len(bad)} such point(s)")
        return a
    raise InputError(f"{flag} takes three numbers X Y Z or one file, got {' '.join(values)}")


def _pairs(args):
    p, q = _points(args.p, "--p"), _points(args.q, "--q")
    if len(p) != len(q):
        raise InputError(f"--p has {len(p)} points and --q {len(q)}; give as many of each")
    return p, q


def _nonnegative(args, *flags):
    for flag in flags:
        v = getattr(args, flag)
        if v is not None and v < 0:
            raise InputError(f"--{flag.replace('_', '-')} must be >= 0, got {v}")


def _require_heat():
    from neurogf_warp.evaluation.evaluate import require_heat

    try:
        require_heat()
    except ImportError as e:
        raise InputError(str(e)) from None


# ------------------------------------------------------------------------------------------ commands

def _cmd_demo(args) -> int:
    from neurogf_warp.cli.demo import run_demo

    run_demo(args.output, mesh=args.mesh, device=args.device, budget_seconds=args.budget_seconds, force=args.force,
             progress=not args.quiet)
    return 0


def _cmd_data(args) -> int:
    from neurogf_warp.training.config import parse_assignments

    _check_output(args.output, (".npz",), "dataset file")
    _nonnegative(args, "sources", "path_sources", "test_sources", "k")
    changes = parse_assignments(args.set)
    for flag, name in (("sources", "n_sources"), ("path_sources", "n_path_sources"), ("test_sources", "n_test"),
                       ("k", "k")):
        if getattr(args, flag) is not None:
            changes[name] = getattr(args, flag)
    import neurogf_warp as ngf
    from neurogf_warp.training import choose_preset, preset
    from neurogf_warp.training.api import torch_device

    if args.devices is not None and args.device is None:  # the first of them does the single-device work
        from neurogf_warp.ground_truth.devices import resolve_devices

        args.device = str(resolve_devices(args.devices)[0])
    dev = torch_device(args.device)
    mesh = ngf.load_mesh(args.mesh)
    cfg = preset(args.preset or choose_preset(dev.type, len(mesh.internal_vertices)))
    bad = [k for k in changes if k.split(".")[-1] not in {f for f in cfg.data.__dataclass_fields__}]
    if bad:
        raise InputError(f"--set {bad[0]}: not a dataset setting (see neurogf_warp.DatasetSettings)")
    settings = cfg.set(**changes).data
    t0 = time.perf_counter()
    ds = ngf.build_dataset(mesh, args.output, settings, seed=args.seed, device=str(dev), progress=not args.quiet,
                           devices=args.devices)
    m = ds.meta
    _say(args, f"wrote {args.output}: {_plural(len(ds.gd_src), 'source')}, "
               f"{_plural(len(ds.path_global) + len(ds.path_local), 'path')} ({m['dropped_paths']} untraceable left "
               f"out), {_plural(len(ds.test_src), 'test source')}, {os.path.getsize(args.output) / 1e6:.1f} MB in "
               f"{time.perf_counter() - t0:.1f} s")
    return 0


def _cmd_train(args) -> int:
    from neurogf_warp.training.config import parse_assignments

    if os.path.splitext(args.output)[1].lower() != ".ngf":
        raise InputError(f"model file {args.output!r}: use the .ngf extension")
    if args.preset and args.paper:
        raise InputError("--paper is --preset paper: give one of them")
    changes = parse_assignments(args.set)
    for flag, name in (("D", "D"), ("epochs", "epochs"), ("iters_per_epoch", "iters_per_epoch"), ("lr", "lr"),
                       ("n_sources", "n_sources"), ("seed", "seed")):
        if getattr(args, flag) is not None:
            changes[name] = getattr(args, flag)
    if args.no_amp:
        changes["amp"] = False
    if args.no_compile:
        changes["compile"] = False
    if args.dataset is not None and not os.path.isfile(args.dataset):
        raise InputError(f"--dataset {args.dataset}: no such file")
    from neurogf_warp.training.run_folder import already_trained

    config = "paper" if args.paper else args.preset
    mesh = args.mesh
    if args.weld:
        from neurogf_warp.mesh.mesh import load_mesh

        mesh = load_mesh(args.mesh, weld=True)
    done = None if args.force or args.resume or args.weld else already_trained(
        args.mesh, args.output, config=config, device=args.device, dataset=args.dataset,
        budget_seconds=args.budget_seconds, **changes)
    if done is not None:  # answered from the run's log, before torch is imported
        if os.environ.get("RANK", "0") == "0":  # under torchrun: said once
            _say(args, f"{args.output} is already trained (--force trains again)")
            print(_quality_line(done), file=sys.stderr)
        return 0
    import neurogf_warp as ngf

    ranks = None if args.no_distributed else _start_ranks(args.device)
    try:
        model = ngf.train(mesh, args.output, config=config, device=args.device, dataset=args.dataset,
                          resume=args.resume, force=args.force, budget_seconds=args.budget_seconds,
                          progress=not args.quiet, allow_vertex_joins=args.allow_vertex_joins, devices=args.devices,
                          distributed=ranks is not None, **changes)
    except ValueError as e:
        raise InputError(_in_cli_terms(str(e))) from None
    if ranks is None or ranks == 0:  # also with -q: the one line that says how good it is
        print(_quality_line(model.config), file=sys.stderr)
    if ranks is not None:
        _leave_ranks()
    return 0


def _leave_ranks() -> None:
    """End a finished torchrun process: every rank past its last collective, the group destroyed, the process
    gone. Its files are written and closed by now; the interpreter's own teardown after a gloo group can abort
    (``terminate called without an active exception``), which torchrun reports as a failed run, so it is skipped."""
    import torch.distributed as dist

    dist.barrier()
    dist.destroy_process_group()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


def _start_ranks(device) -> int | None:
    """Under torchrun (``WORLD_SIZE`` > 1): this process's rank, once the default process group is initialised
    (NCCL on GPUs, gloo on CPUs); None for a process started alone."""
    if int(os.environ.get("WORLD_SIZE", "1") or 1) <= 1:
        return None
    import torch
    import torch.distributed as dist

    if not dist.is_available():
        raise InputError("torchrun started several processes, but this torch has no torch.distributed: run one "
                         "process, or pass --no-distributed")
    gpu = torch.cuda.is_available() and (device is None or str(device).startswith("cuda"))
    if gpu:  # one GPU per process of this machine; the training call keeps to it
        local = int(os.environ.get("LOCAL_RANK", "0"))
        torch.cuda.set_device(local if device in (None, "cuda") else torch.device(device))
    if not dist.is_initialized():
        from datetime import timedelta

        # the other ranks wait in a collective while rank 0 builds the dataset: as long as that may take
        dist.init_process_group("nccl" if gpu else "gloo", timeout=timedelta(hours=6))
    return dist.get_rank()


def _quality_line(q: dict) -> str:
    """The final accuracy line of ``train``: validation MRE against the heat method on the same held-out pairs."""
    v, h = q.get("validation_mre"), q.get("heat_mre")
    if v is None:
        return "accuracy: not measured (a run that predates validation)"
    line = f"accuracy: validation MRE {100 * v:.3f}% on held-out sources"
    up, n = q.get("validation_mre_upper"), q.get("validation_sources")
    if up is not None:
        line += f" ({100 * q.get('validation_level', 0.95):.0f}% upper bound {100 * up:.3f}% over {n} sources)"
    if h is not None:
        line += f" (heat method {100 * h:.3f}% on the same pairs)"
        if q.get("worse_than_heat"):
            line += ": WORSE than the heat method, train longer (--budget-seconds) or use the heat method"
        elif q.get("quality_warning"):
            line += ": NOT CLEARLY BETTER than the heat method, train longer (--budget-seconds)"
    else:
        line += " (heat method not compared: pip install potpourri3d)"
    return line


# The training stage's messages name its Python arguments; on the command line they are flags.
_API_TO_FLAG = (("pass force=True (--force)", "pass --force"), ("force=True (--force)", "--force"),
                ("pass resume=True (--resume)", "pass --resume"), ("resume=True (--resume)", "--resume"),
                ("force=True", "--force"), ("resume=True", "--resume"), ("budget_seconds", "--budget-seconds"))


def _in_cli_terms(msg: str) -> str:
    for api, flag in _API_TO_FLAG:
        msg = msg.replace(api, flag)
    return msg


def _cmd_eval(args) -> int:
    _nonnegative(args, "sources", "path_sources", "path_targets", "path_refine")
    if args.json:
        _check_output(args.json, (".json",), "--json")
    if args.heat:
        _require_heat()
    if args.reference is not None and not os.path.exists(args.reference):  # a FIFO etc.: the reader says what it is
        raise InputError(f"--reference {args.reference}: no such file")
    import json

    from neurogf_warp.common.files import atomic_write
    from neurogf_warp.evaluation.evaluate import evaluate

    model = _load_model(args, needs_mesh=True)
    res = evaluate(model, reference=args.reference, heat=args.heat, n_sources=args.sources,
                   n_path_sources=args.path_sources, n_path_targets=args.path_targets, paths=not args.no_paths,
                   sdf=not args.no_sdf, path_refine=args.path_refine, surface=args.surface, device=args.device,
                   seed=args.seed,
                   progress=not args.quiet, verbose=True)
    if args.json:
        text = json.dumps(res, indent=1).encode()
        atomic_write(args.json, lambda f: f.write(text))
    return 0


def _timed_twice(fn):
    """(result, first call s, second call s, whether Warp compiled kernels during the first call)."""
    import warp as wp

    cache = wp.config.kernel_cache_dir
    before = set(os.listdir(cache)) if cache and os.path.isdir(cache) else set()
    t = time.perf_counter()
    fn()
    first = time.perf_counter() - t
    compiled = bool(set(os.listdir(cache)) - before) if cache and os.path.isdir(cache) else False
    t = time.perf_counter()
    out = fn()
    return out, first, time.perf_counter() - t, compiled


def _emit_values(args, model, d, first, again, compiled, what):
    """Per-vertex distances to -o, or to stdout (one per line); then the summary line on stderr."""
    import numpy as np

    if args.output is None:
        _print_array(np.asarray(d, dtype=np.float64), None, "%.9g")
        where = "printed"
    else:
        _write_values(args.output, d, model.mesh)
        where = f"written to {args.output}"
    ok = np.isfinite(d)
    note = "includes kernel compilation" if compiled else "kernels from the cache"
    _say(args, f"{what}: {int(ok.sum())} of {_plural(len(d), 'distance')} {where} (min "
               f"{np.nanmin(d) if ok.any() else float('nan'):.6g}, max "
               f"{np.nanmax(d[ok]) if ok.any() else float('nan'):.6g}, mesh units); first call {first:.2f} s "
               f"({note}), second {again * 1e3:.1f} ms")


def _cmd_ssad(args) -> int:
    if args.output is not None:
        _check_output(args.output, VALUE_FORMATS)
    if args.source is not None and args.source < 0:
        raise InputError(f"--source must be a vertex index >= 0, got {args.source}")
    import numpy as np

    import neurogf_warp as ngf

    model = _load_model(args, needs_mesh=True)
    if args.point is not None:
        src = np.array(args.point, dtype=np.float64)
    else:
        src = _vertex_indices(model, [0 if args.source is None else args.source], "--source")[0]
    d, first, again, compiled = _timed_twice(lambda: ngf.ssad(model, src, device=args.device))
    _emit_values(args, model, d, first, again, compiled, "ssad")
    return 0


def _cmd_msad(args) -> int:
    if args.output is not None:
        _check_output(args.output, VALUE_FORMATS)
    import neurogf_warp as ngf

    model = _load_model(args, needs_mesh=True)
    src = _vertex_indices(model, args.sources, "--sources")
    d, first, again, compiled = _timed_twice(lambda: ngf.msad(model, src, device=args.device))
    _emit_values(args, model, d, first, again, compiled, "msad")
    return 0


def _cmd_distance(args) -> int:
    if args.output is not None:
        _check_output(args.output, (".npy", ".csv"))
    p, q = _pairs(args)
    import numpy as np

    import neurogf_warp as ngf

    model = _load_model(args, needs_mesh=False)
    d = np.asarray(ngf.distance(model, p, q, device=args.device))
    if args.output is None:
        _print_array(d.astype(np.float64), None, "%.9g")
    else:
        _write_array(args.output, d, "distance", "%.9g")
        _say(args, f"distance: {_plural(len(d), 'value')} written to {args.output}")
    return 0


def _cmd_path(args) -> int:
    if args.output is not None:
        _check_output(args.output, (".npy", ".csv"))
    if args.m < 2:
        raise InputError(f"--m (points per path) must be >= 2, got {args.m}")
    _nonnegative(args, "refine")
    p, q = _pairs(args)
    import numpy as np

    import neurogf_warp as ngf

    model = _load_model(args, needs_mesh=args.project == "mesh")
    project = args.project or ("mesh" if model.mesh is not None else "sdf")
    paths = np.asarray(ngf.path(model, p, q, m=args.m, refine=args.refine, device=args.device,
                                project=None if project == "none" else project))
    # the network's own points, for the note on how far they were from the surface (a second head evaluation,
    # cheap; skipped after refinement, whose points are not the network's)
    raw = None if project == "none" or args.refine else \
        np.asarray(ngf.path(model, p, q, m=args.m, device=args.device, project=None))
    n, m = paths.shape[:2]
    rows = np.column_stack([np.repeat(np.arange(n), m), np.tile(np.arange(m), n), paths.reshape(-1, 3)])
    fmt = ["%d", "%d", "%.9g", "%.9g", "%.9g"]
    if args.output is None:
        _print_array(rows, "path,point,x,y,z", fmt)
        where = "printed"
    elif args.output.lower().endswith(".npy"):
        _write_array(args.output, paths, "", None)
        where = f"written to {args.output}"
    else:
        _write_array(args.output, rows, "path,point,x,y,z", fmt)
        where = f"written to {args.output}"
    note = _offset_note(model, raw, paths, project)
    _say(args, f"path: {_plural(n, 'path')} of {args.m} points {where}{note}")
    return 0


def _offset_note(model, raw, paths, project: str) -> str:
    """How far the network's own path points ``raw`` (None after refinement) were from where they were put (mesh
    units)."""
    import numpy as np

    if project == "none":
        return " (the network's points as they come, not projected onto the surface: --project mesh or sdf puts them on it)"
    where = "the mesh" if project == "mesh" else "the network's SDF surface"
    if raw is None:  # refined paths: their points are not the network's
        return f", every point on {where}"
    ok = np.isfinite(raw).all(-1) & np.isfinite(paths).all(-1)
    if not ok.any():
        return ""
    off = np.linalg.norm((raw - paths)[ok], axis=-1)
    return (f", every point on {where} (the network's points were up to {off.max():.3g} mesh units off it, median "
            f"{np.median(off):.3g})")


def model_summary(model) -> dict:
    """What a model holds, as a JSON-ready dict (the ``info`` command)."""
    import numpy as np

    out = {"D": model.D, "network_options": model.net.options, "querier": model.querier is not None,
           "normalization": {"center": np.asarray(model.center).tolist(), "scale": model.scale,
                             "frame": "mesh coordinates" if model.in_mesh_frame else "normalized unit sphere"}}
    m = model.mesh
    if m is not None:
        out["mesh"] = {"vertices_as_given": int(m.n_input), "vertices_used": int(len(m.internal_vertices)),
                       "faces": int(len(m.internal_faces)), "components": int(m.n_components),
                       "fingerprint": m.fingerprint}
    cfg = dict(model.config or {})
    if cfg:
        out["training"] = cfg
    return out


def _cmd_info(args) -> int:
    import json

    model = _load_model(args, needs_mesh=False)
    if not hasattr(model, "D"):  # a generalizable network (neurogf_warp.generalizable)
        from neurogf_warp.generalizable.hooks import cli_info
        return cli_info(args, model, _stdout_write)
    info = model_summary(model)
    if args.json:
        _stdout_write(json.dumps(info, indent=1) + "\n")
        return 0
    lines = [f"{args.model}: NeuroGF, D={info['D']}, options {info['network_options']}, "
             f"SDF querier {'included' if info['querier'] else 'not included'}"]
    n = info["normalization"]
    lines.append(f"  frame: {n['frame']}; normalized = (x - {[round(c, 6) for c in n['center']]}) * {n['scale']:.6g}")
    if "mesh" in info:
        m = info["mesh"]
        lines.append(f"  mesh: {m['vertices_as_given']} vertices as given ({m['vertices_used']} used by faces), "
                     f"{_plural(m['faces'], 'face')}, {_plural(m['components'], 'connected component')}, "
                     f"fingerprint {m['fingerprint'][:16]}...")
    else:
        lines.append("  mesh: none stored (pass --mesh to query by vertex)")
    t = info.get("training")
    if t:
        steps = t.get("steps")
        lines.append(f"  training: preset {t.get('preset', '?')}, steps {steps}, {t.get('train_seconds', '?')} s of "
                     "steps" if steps else f"  from: {t.get('source', t)}")
    _stdout_write("\n".join(lines) + "\n")
    return 0


def _cmd_render(args) -> int:
    _check_output(args.output, (".png",), "picture")
    _nonnegative(args, "isolines", "refine")
    if not all(MIN_SIZE <= x <= MAX_SIZE for x in args.size):
        raise InputError(f"--size {args.size[0]} {args.size[1]}: each side must be {MIN_SIZE} to {MAX_SIZE} pixels")
    if args.vrange is not None and not args.vrange[0] < args.vrange[1]:
        raise InputError(f"--vrange {args.vrange[0]:g} {args.vrange[1]:g}: LOW must be below HIGH")
    if args.heat:
        _require_heat()
    import numpy as np

    import neurogf_warp as ngf
    from neurogf_warp.evaluation import fields
    from neurogf_warp.pictures.render import Style, View, render

    model = _load_model(args, needs_mesh=True)
    mesh = model.mesh
    src = _vertex_indices(model, args.source, "--source")
    if args.exact:
        try:
            values = fields.exact_field(args.exact, mesh, src)
        except InputError as e:
            raise InputError(f"--{e}") from None  # "source 5 is not one of ..." -> "--source 5 ..."
        what = "exact"
    elif args.heat:
        values, what = fields.heat_field(mesh, src), "heat method"
    else:
        values = ngf.ssad(model, src[0], device=args.device) if len(src) == 1 else ngf.msad(model, src, device=args.device)
        what = "NeuroGF"
    paths = None
    if args.paths:
        tg = _vertex_indices(model, args.paths, "--paths")
        if args.exact:
            paths = ngf.geodesic_paths(mesh, src[0], tg, m=128, device=args.device)
        elif args.heat:
            paths = fields.heat_paths(mesh, src[0], tg)
        else:
            v = mesh.internal_vertices[mesh.vertex(np.asarray(tg))]
            s = np.repeat(mesh.internal_vertices[mesh.vertex(np.asarray(src[:1]))], len(tg), axis=0)
            paths = np.asarray(ngf.path(model, s, v, m=128, refine=args.refine, project="mesh", device=args.device))
    view = None if args.view is None else View(azimuth=args.view[0], elevation=args.view[1], up=args.up)
    if view is None and args.up != "auto":  # face the sources as render would, with the given up axis
        from neurogf_warp.pictures.render import SOURCE_VIEW_MAX_ELEVATION, source_side

        side = source_side(mesh.internal_vertices[mesh.vertex(np.asarray(src))], mesh.internal_vertices)
        view = View(up=args.up) if side is None else View.toward(side, up=args.up,
                                                                 max_elevation=SOURCE_VIEW_MAX_ELEVATION)
    render(model, values, sources=src, paths=paths, view=view, style=Style(isolines=args.isolines, vrange=args.vrange),
           size=tuple(args.size), out=args.output, device=args.device)
    _say(args, f"render: {what} field from {_plural(len(src), 'source')}, {_plural(len(args.paths or []), 'path')}: "
               f"{args.output}")
    return 0


# errors that mean "what was asked for is wrong" (exit 2). InputError is ours; the plain ValueError is still what
# the training and inference stages raise for bad arguments, and the file errors come from the user's paths.
USER_ERRORS = (InputError, ValueError, FileNotFoundError, IsADirectoryError, NotADirectoryError, FileExistsError,
               PermissionError)


@contextlib.contextmanager
def _one_line_warnings(args):
    """Warnings as one line on stderr in the command's name (no Python source line), none with -q."""
    def show(message, category, filename, lineno, file=None, line=None):
        if not args.quiet:
            print(f"{PROG} {args.command}: warning: {message}", file=sys.stderr, flush=True)

    with warnings.catch_warnings():
        warnings.simplefilter("default")
        warnings.showwarning = show
        yield


def _quiet_stdout_exit():
    """After a closed stdout: point it at /dev/null so that the interpreter's final flush cannot fail again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):
        pass


def _closed_std_streams() -> set:
    """The standard streams the process was started without (``>&-``, ``2>&-``): each is opened on /dev/null, so
    that no file this command opens later takes its descriptor (and gets the output meant for it); returns their
    names."""
    global _STARTED_WITHOUT_STDOUT
    closed = set()
    for fd, name in ((0, "stdin"), (1, "stdout"), (2, "stderr")):
        try:
            os.fstat(fd)
            continue
        except OSError:
            closed.add(name)
        null = os.open(os.devnull, os.O_RDWR)  # the lowest free descriptor: this one, as the lower ones are open
        if null != fd:
            os.dup2(null, fd)
            os.close(null)
    if "stderr" in closed or sys.stderr is None:  # messages go nowhere; the exit code still tells
        sys.stderr = open(os.devnull, "w")
    _STARTED_WITHOUT_STDOUT = "stdout" in closed or sys.stdout is None
    if sys.stdout is None:  # Python's stand-in for a closed stdout; libraries that print expect a stream
        sys.stdout = open(os.devnull, "w")
    return closed


def _versions() -> str:
    """Versions to quote in a bug report: this package, Python, and torch and Warp when loaded."""
    import platform

    out = [f"{PROG} {__version__}", f"Python {platform.python_version()}"]
    for mod, name in (("torch", "torch"), ("warp", "warp-lang")):
        m = sys.modules.get(mod)
        v = getattr(m, "__version__", None) or getattr(getattr(m, "config", None), "version", None)
        if v:
            out.append(f"{name} {v}")
    return ", ".join(out)


def main(argv=None) -> int:
    """Run ``neurogf-warp`` with ``argv`` (default: sys.argv[1:]); returns the exit code."""
    from neurogf_warp.common.clock import process_clock

    clock = process_clock(argv is None)  # the process's own command: --budget-seconds counts from its start
    argv = sys.argv[1:] if argv is None else list(argv)
    _closed_std_streams()
    if argv and argv[0] in GEN_COMMANDS:  # generalizable NeuroGF: their own parsers
        from neurogf_warp.cli.gen import run_gen

        args = argparse.Namespace(command=argv[0], verbose=False, quiet=False)

        def run_generalizable():
            with clock:
                return run_gen(argv[0], argv[1:])

        return _run_guarded(args, run_generalizable)
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help(sys.stderr)
        return 2

    def run():
        with clock:
            start_warp(args.verbose)
            return args.run(args)

    return _run_guarded(args, run)


def _run_guarded(args, run) -> int:
    """``run()``'s exit code, with every failure turned into a message on stderr and its exit code."""
    debug = args.verbose or os.environ.get("NEUROGF_DEBUG", "") not in ("", "0")
    try:
        # input_guard: no -o of a command may replace a file the command reads (mesh, model, reference, dataset)
        with _one_line_warnings(args), input_guard():
            return run()
    except _StdoutClosed:
        _quiet_stdout_exit()
        return 0
    except _NoStdout:
        print(f"{PROG} {args.command}: failed: standard output is closed, so the results cannot be printed; "
              "redirect it to a file (or give -o FILE where the command has it)", file=sys.stderr)
        return 1
    except KeyboardInterrupt as e:  # TrainingInterrupted says where its checkpoint is
        msg = str(e) or "interrupted"
        print(f"{PROG} {args.command}: {msg}", file=sys.stderr)
        return 130
    except USER_ERRORS as e:
        if debug:
            raise
        print(f"{PROG} {args.command}: error: {e}", file=sys.stderr)
        return 2
    except (OSError, MemoryError) as e:  # the machine, not the input and not our code: a full disk, too little memory
        if debug:
            raise
        print(f"{PROG} {args.command}: failed: {e or 'out of memory'}", file=sys.stderr)
        return 1
    except Exception as e:  # noqa: BLE001 - the one place that turns failures into an exit code
        if debug:
            raise
        again = "with NEUROGF_DEBUG=1" if args.command in GEN_COMMANDS else "with --verbose"
        print(f"{PROG} {args.command}: internal error: {type(e).__name__}: {e}\n"
              f"This is a bug in neurogf-warp, not a problem with your input. Please report it to the maintainers "
              f"with the command line, these versions ({_versions()}) and the traceback that the same command "
              f"prints {again}.", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
