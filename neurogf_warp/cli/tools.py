"""The geodesic-tool commands: ``sample``, ``voronoi``, ``isolines``, ``reconstruct``."""
from __future__ import annotations

from neurogf_warp.common.checks import InputError

cli = None  # the command line's module (cli.main), handed in by add_commands: its argument and output utilities

INDEX_FORMATS = (".npy", ".csv")
LINE_FORMATS = (".obj", ".csv")
MESH_FORMATS = (".obj", ".ply", ".stl")


def add_commands(sub, common, main_module):
    global cli
    cli = main_module
    s = sub.add_parser("sample", parents=[common], help="farthest point sampling of mesh vertices by the field",
                       description="Farthest point sampling: K vertices, each the one geodesically farthest from "
                       "those chosen before it (every part of a mesh gets a sample before any gets a second).")
    cli._model_args(s)
    s.add_argument("-k", type=int, required=True, help="number of samples")
    s.add_argument("--start", type=int, default=0, help="the first sample, a vertex index (default 0)")
    s.add_argument("-o", "--output", default=None,
                   help="output file: .npy or .csv of vertex indices; default: print one index per line")
    s.set_defaults(run=_cmd_sample)

    v = sub.add_parser("voronoi", parents=[common], help="geodesic Voronoi cells of seed vertices",
                       description="The nearest seed of every vertex by the field's geodesic distance: for vertex i, "
                       "the position of its nearest seed in --seeds (-1 for vertices no face uses or on a part "
                       "without a seed).")
    cli._model_args(v)
    g = v.add_mutually_exclusive_group(required=True)
    g.add_argument("--seeds", type=int, nargs="+", metavar="V", help="seed vertex indices, the mesh's own numbering")
    g.add_argument("--fps", type=int, metavar="K", help="use K farthest-point samples (from vertex 0) as the seeds")
    v.add_argument("-o", "--output", default=None,
                   help="output file: .npy, .csv (vertex,label) or .ply (the mesh coloured by label); default: "
                        "print one label per line, line i for vertex i")
    v.set_defaults(run=_cmd_voronoi)

    i = sub.add_parser("isolines", parents=[common], help="isolines of a source's distance field as polylines",
                       description="Level sets of the SSAD field of one source vertex, traced on the mesh.")
    cli._model_args(i)
    i.add_argument("--source", type=int, default=0, help="source vertex index (default 0)")
    lv = i.add_mutually_exclusive_group()
    lv.add_argument("--levels", type=int, default=10, help="number of evenly spaced levels (default 10)")
    lv.add_argument("--values", type=cli._finite("--values"), nargs="+", metavar="D",
                    help="the distances to trace, mesh units")
    i.add_argument("-o", "--output", required=True,
                   help="output file: .obj (polylines as 'l' elements) or .csv (level,line,point,x,y,z)")
    i.set_defaults(run=_cmd_isolines)

    r = sub.add_parser("reconstruct", parents=[common], help="a triangle mesh from the model's SDF head",
                       description="Marching cubes on the SDF head over a grid around the mesh (Warp kernels); "
                       "prints the Chamfer-L1 and Hausdorff distance to the model's mesh when it has one.")
    r.add_argument("model", help="model file: an .ngf written by train, or a released NeuroGF *_final.pth")
    r.add_argument("--mesh", default=None, help="the model's mesh file (a released .pth needs it for its frame)")
    r.add_argument("--allow-mesh-mismatch", action="store_true",
                   help="go on when --mesh is not the mesh the model was trained on")
    r.add_argument("--resolution", type=int, default=256, help="grid samples along the longest side (default 256)")
    r.add_argument("-o", "--output", required=True, help="mesh file to write: .obj, .ply or .stl")
    r.set_defaults(run=_cmd_reconstruct)


def _cmd_sample(args) -> int:
    import neurogf_warp as ngf

    if args.output is not None:
        cli._check_output(args.output, INDEX_FORMATS)
    model = cli._load_model(args, needs_mesh=True)
    start = cli._vertex_indices(model, [args.start], "--start")[0]
    s = ngf.farthest_point_sampling(model, args.k, start=start, device=args.device)
    _indices_out(args.output, s, "vertex")
    cli._say(args, f"{len(s)} samples")
    return 0


def _indices_out(path, a, header: str):
    import numpy as np

    if path is None:
        cli._print_array(np.asarray(a).reshape(-1, 1), None, "%d")
    else:
        cli._write_array(path, np.asarray(a), header, "%d")


def _cmd_voronoi(args) -> int:
    import numpy as np

    import neurogf_warp as ngf

    if args.output is not None:
        cli._check_output(args.output, cli.VALUE_FORMATS)
    model = cli._load_model(args, needs_mesh=True)
    if args.seeds is not None:
        seeds = cli._vertex_indices(model, args.seeds, "--seeds")
    else:
        seeds = ngf.farthest_point_sampling(model, args.fps, device=args.device)
    labels = ngf.voronoi(model, seeds, device=args.device)
    if args.output is None:
        cli._print_array(labels.reshape(-1, 1), None, "%d")
    elif args.output.lower().endswith(".ply"):
        cli._write_values(args.output, np.where(labels >= 0, labels, np.nan).astype(np.float32), model)
    elif args.output.lower().endswith(".csv"):
        cli._write_array(args.output, np.column_stack([np.arange(len(labels)), labels]), "vertex,label", "%d")
    else:
        cli._write_array(args.output, labels, "", "%d")
    cli._say(args, f"{len(seeds)} cells")
    return 0


def _cmd_isolines(args) -> int:
    import numpy as np

    import neurogf_warp as ngf
    from neurogf_warp.common.files import atomic_write

    cli._check_output(args.output, LINE_FORMATS)
    model = cli._load_model(args, needs_mesh=True)
    src = cli._vertex_indices(model, [args.source], "--source")[0]
    d = ngf.ssad(model, src, device=args.device)
    levels = args.values if args.values is not None else args.levels
    lines = ngf.isolines(model, d, levels)
    if args.output.lower().endswith(".csv"):
        rows = [(li, k, j, *p) for li, level in enumerate(lines) for k, pl in enumerate(level)
                for j, p in enumerate(pl)]
        a = np.array(rows, dtype=np.float64).reshape(-1, 6)
        atomic_write(args.output, lambda f: np.savetxt(f, a, fmt=["%d", "%d", "%d", "%.9g", "%.9g", "%.9g"],
                                                       delimiter=",", header="level,line,point,x,y,z", comments=""))
    else:
        out, n = [], 0
        for level in lines:
            for pl in level:
                out += [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in pl]
                out.append("l " + " ".join(str(n + j + 1) for j in range(len(pl))))
                n += len(pl)
        atomic_write(args.output, lambda f: f.write(("\n".join(out) + "\n").encode()))
    cli._say(args, f"{sum(len(level) for level in lines)} polylines on {len(lines)} levels")
    return 0


def _cmd_reconstruct(args) -> int:
    import neurogf_warp as ngf
    from neurogf_warp.common.files import atomic_write
    from neurogf_warp.inference.reconstruct import surface_distances

    ext = cli._check_output(args.output, MESH_FORMATS)
    model = cli._load_model(args, needs_mesh=False)
    v, f = ngf.reconstruct(model, resolution=args.resolution, device=args.device)
    if len(f) == 0:
        raise InputError("the SDF head's zero level set does not cross the grid: no surface to write")
    import trimesh

    data = trimesh.Trimesh(v, f, process=False).export(file_type=ext[1:])
    atomic_write(args.output, lambda fh: fh.write(data if isinstance(data, bytes) else data.encode()))
    msg = f"{len(f):,} triangles to {args.output}"
    if model.mesh is not None:
        m = surface_distances(v, f, model.mesh.internal_vertices, model.mesh.internal_faces)
        msg += f"; against the mesh: Chamfer-L1 {m['chamfer_l1']:.4g}, Hausdorff {m['hausdorff']:.4g} (mesh units)"
    print(msg, file=__import__("sys").stderr)
    return 0

