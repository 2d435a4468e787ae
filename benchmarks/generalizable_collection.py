"""A generalizable model trained on a generated shape collection, and its accuracy against the released network
and the heat method on unseen shapes.

    python benchmarks/generalizable_collection.py run      --out OUT   # collection, ground truth, training, evaluation
    python benchmarks/generalizable_collection.py per-mesh --out OUT   # 60 s per-mesh models on 3 + 3 shapes
    python benchmarks/generalizable_collection.py merge OUT/eval.json OUT2/eval_per_mesh.json -o merged
    python benchmarks/generalizable_collection.py pack-shared SHARED shared.tar.xz   # the data for another machine

Each of ``run`` and ``per-mesh`` fits in 10 minutes on one GPU; ``merge`` runs anywhere. ``--shared`` (or
``$NEUROGF_SHARED``) is the shared data folder or a ``pack-shared`` archive (meshes, the exact references and
GenNeuroGF.pth), unpacked once into the work folder.

``run`` (default: --time-limit 540 s from its start, so that it ends inside a 600 s call):
1. collection: 540 shapes (``shapes.write_collection``, seed 0, 6 families x 90), split by family instance:
   486 train, 54 unseen test (9 of each family); made in --gen-workers processes.
2. ground truth, as the authors' data: per shape 256 source vertices x 512 targets from the project's solver
   (``ngf.geodesic_distances``, default accuracy) and a 2,048-point cloud, for the training shapes and up to
   --val-shapes test shapes that the evaluation does not use (the 24 after its 30: the validation curve, which
   picks nothing); one process on the GPU (4 processes were no faster on an H100).
   It stops at a deadline that keeps --min-train-seconds of training; the shapes it reached are used, and the
   summary says how many.
3. training (``generalizable.train``, in this process): the rest of the time limit less --eval-reserve seconds,
   16 shapes x (64 x 128 pairs) per step, AdamW lr 1e-2 cosine to 1e-4 over the time budget, random rotations
   (--rotate, on by default), validation every 500 steps.
4. evaluation (``benchmarks/generalizable_eval.py``, a subprocess): --eval-shapes unseen test shapes (by name:
   the first of every family in turn) + the shared bunny, fandisk and spot (exact references): our model, the
   released GenNeuroGF.pth and the heat method on the same pairs (8 sources x 512 targets per shape).
Writes to --out: run.log, model.pt (the trained model; resumable, loadable by ``generalizable.load``),
eval.json, table.txt, summary.json (phase times, counts, validation curve).

``per-mesh``: regenerates the same test shapes (same seed: the same files) and evaluates the released network,
the heat method and a per-mesh NeuroGF trained for --per-mesh-seconds (60) on each of the first --eval-shapes
(3) unseen shapes and the 3 shared meshes (6 x ~70 s), on the same pairs as ``run`` (pairs depend on the shape's
name only). Writes eval_per_mesh.json, table_per_mesh.txt, per_mesh.log. ``merge`` joins the two JSONs by shape
into one table (and checks that the heat-method MRE of a shape is identical in both: the same pairs).

Times on one H100 (2026-11-24): ``run`` 479 s in all (collection 5 s, ground truth 149 s at 0.29 s a shape,
5,248 training steps in 296 s, evaluation 19 s); ``per-mesh`` 7-8 minutes. On a 2-core CPU a reduced run (``run
--device cpu --shapes 24 --test-every 4 --gen-workers 2 --sources 32 --targets 128 --shapes-per-step 2
--step-sources 8 --step-targets 16 --val-every 50 --val-shapes 4 --time-limit 420 --min-train-seconds 60
--eval-reserve 150 --eval-shapes 3``) takes about 5 minutes.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import _bootstrap  # noqa: F401  (this checkout's neurogf_warp, installed or not)
from common import ROOT, provenance

T0 = time.perf_counter()


class Log:
    """Print with the time since start, and append to a log file."""

    def __init__(self, path: Path):
        self.f = open(path, "a", buffering=1)  # noqa: SIM115 (open for the whole run)

    def __call__(self, msg: str):
        line = f"[{time.perf_counter() - T0:7.1f} s] {msg}"
        print(line, flush=True)
        self.f.write(line + "\n")


def unpack_shared(arg, work: Path):
    """A ``pack-shared`` archive (``*.tar.xz``, given as --shared or $NEUROGF_SHARED) is unpacked once into
    ``work/shared``; returns the folder to use (or ``arg`` unchanged when it is not such a file)."""
    arg = arg or os.environ.get("NEUROGF_SHARED")
    if not arg or not str(arg).endswith(".tar.xz") or not Path(arg).is_file():
        return arg
    import tarfile

    dst = work / "shared"
    if not (dst / "meshes").is_dir():
        tmp = work / "shared.tmp"
        tmp.mkdir(parents=True, exist_ok=True)
        with tarfile.open(arg, "r:xz") as tf:
            tf.extractall(tmp, filter="data")
        os.replace(tmp, dst)
    return str(dst)


def find_shared(arg=None) -> Path | None:
    env = arg or os.environ.get("NEUROGF_SHARED")
    for base in ([Path(env)] if env else []) + [ROOT.parent / "shared", ROOT / "shared"]:
        if (base / "meshes").is_dir():
            return base.resolve()
    return None


def make_collection(a, log, shared) -> dict:
    from neurogf_warp.generalizable.shapes import (
        deform_sources_present,
        write_collection,
    )

    meshes = str(shared / "meshes") if shared else None
    if not deform_sources_present(meshes):
        log(f"WARNING: {meshes} lacks the 'deformed' family's source meshes (cow, homer, rocker-arm, cheburashka, "
            f"alligator, igea): those shapes become 'blob'. Copy all 9 shared meshes there for the full collection.")
    t = time.perf_counter()
    man = write_collection(a.work / "coll", n=a.shapes, seed=a.seed, test_every=a.test_every, shared_meshes=meshes,
                           progress=False, workers=a.gen_workers)
    fams: dict = {}
    for s in man["shapes"].values():
        key = f"{s['family']}/{s['split']}"
        fams[key] = fams.get(key, 0) + 1
    log(f"collection: {len(man['shapes'])} shapes in {time.perf_counter() - t:.1f} s ({a.gen_workers} workers): "
        + ", ".join(f"{k} {v}" for k, v in sorted(fams.items())))
    return {"shapes": len(man["shapes"]), "by_family_split": fams, "seconds": time.perf_counter() - t}


def eval_order(files):
    """Test files in round-robin family order (first of each family, then the second, ...), so that the first N
    cover every family."""
    by: dict = {}
    for f in sorted(files):
        by.setdefault(f.stem.split("_", 2)[-1], []).append(f)
    out, k = [], 0
    while any(k < len(v) for v in by.values()):
        out += [v[k] for v in by.values() if k < len(v)]
        k += 1
    return out


def run_eval(a, log, files, extra, json_name, table_name, log_name, timeout):
    """benchmarks/generalizable_eval.py on a folder of links to ``files`` (its --collection) in a subprocess."""
    sel = a.work / f"eval_{json_name.split('.')[0]}" / "test"
    sel.mkdir(parents=True, exist_ok=True)
    for f in files:
        dst = sel / f.name
        if not dst.exists():
            dst.symlink_to(f)
    cmd = [sys.executable, str(ROOT / "benchmarks" / "generalizable_eval.py"), "--collection", str(sel.parent),
           "--max-shapes", str(len(files)), "--device", a.device, "--json", str(a.out / json_name),
           "--table", str(a.out / table_name)] + extra
    log("eval: " + " ".join(cmd[1:]))
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    shared = find_shared(a.shared)
    if shared:
        env["NEUROGF_SHARED"] = str(shared)
    t = time.perf_counter()
    with open(a.out / log_name, "w") as lf:
        try:
            p = subprocess.run(cmd, stdout=lf, stderr=subprocess.STDOUT, timeout=timeout, cwd=str(a.work), env=env,
                               check=False)
            rc = p.returncode
        except subprocess.TimeoutExpired:
            rc = "timeout"
    log(f"eval finished (exit {rc}) in {time.perf_counter() - t:.1f} s")
    table = a.out / table_name
    js = a.out / json_name
    if not table.exists() and js.exists():  # stopped early: the table of the rows it finished
        sys.path.insert(0, str(ROOT / "benchmarks"))
        from generalizable_eval import mre_table

        done = json.loads(js.read_text())
        rows = done["rows"]
        cols = [c for c in ("trained", "released", "heat", "per_mesh") if any(c in r for r in rows)]
        text, summary = mre_table(rows, cols, f"MRE on the same pairs (PARTIAL: {len(rows)} shapes finished)")
        done["summary"] = summary
        js.write_text(json.dumps(done, indent=1))
        table.write_text(text + "\n")
    if table.exists():
        for line in table.read_text().splitlines():
            log("  " + line)
    else:
        log("eval wrote no table; the end of its log:")
        for line in (a.out / log_name).read_text().splitlines()[-25:]:
            log("  " + line)
    return rc, time.perf_counter() - t


def cmd_run(a) -> int:
    a.out.mkdir(parents=True, exist_ok=True)
    a.work.mkdir(parents=True, exist_ok=True)
    log = Log(a.out / "run.log")
    deadline = T0 + a.time_limit
    summary = {"benchmark": "generalizable_collection", "provenance": provenance(a.device),
               "args": {k: str(v) for k, v in vars(a).items()}, "phases": {}}

    def save():
        tmp = a.out / "summary.json.tmp"
        tmp.write_text(json.dumps(summary, indent=1))
        os.replace(tmp, a.out / "summary.json")

    shared = find_shared(a.shared)
    log(f"shared data: {shared}; device {a.device}; time limit {a.time_limit:.0f} s")
    import numpy as np  # noqa: F401
    import torch
    import warp as wp

    wp.config.quiet = True
    from neurogf_warp.generalizable.train import (
        GenTrainConfig,
        ground_truth_cache,
        mesh_files,
        train_generalizable,
    )

    summary["phases"]["collection"] = make_collection(a, log, shared)
    save()
    coll = a.work / "coll"
    train_files, test_files = mesh_files(coll)
    test_files = eval_order(test_files)
    cfg = GenTrainConfig(sources=a.sources, targets=a.targets, cloud_points=a.cloud_points,
                         shapes_per_step=a.shapes_per_step, step_sources=a.step_sources, step_targets=a.step_targets,
                         steps=a.steps, lr=a.lr, rotate=a.rotate, val_every=a.val_every, val_shapes=a.val_shapes,
                         checkpoint_seconds=60.0, log_every=a.log_every)
    # validation (the curve only: no model is picked by it) on test shapes the evaluation does not use
    val_files = test_files[a.eval_shapes:][: a.val_shapes] or test_files[: a.val_shapes]
    log(f"{len(train_files)} training shapes; {len(test_files)} unseen: {min(a.eval_shapes, len(test_files))} "
        f"evaluated, {len(val_files)} for the validation curve"
        + (" (the same ones: too few test shapes)" if len(test_files) <= a.eval_shapes else ""))

    # ground truth: validation shapes first (few), then training shapes until the deadline
    cache = a.work / "gt"
    gt_deadline = deadline - a.eval_reserve - a.min_train_seconds
    t = time.perf_counter()
    if a.device.startswith("cuda"):  # compile once, timed apart (the first shape would pay it otherwise)
        from neurogf_warp.ground_truth.geodesics import load_kernels

        try:
            load_kernels(a.device)
            log(f"solver kernels ready in {time.perf_counter() - t:.1f} s")
        except Exception as e:  # noqa: BLE001 - only a warm-up: the first solve compiles them anyway
            log(f"solver kernel warm-up failed ({type(e).__name__}: {e}); the first shape compiles them")
    ground_truth_cache(val_files, cache, cfg, device=a.device, log=log)
    ground_truth_cache(train_files, cache, cfg, device=a.device, log=log, deadline=gt_deadline)
    from neurogf_warp.generalizable.train import _file_key

    have = lambda fs: [f for f in fs if (cache / f"{f.stem}_{_file_key(f, cfg)}.npz").exists()]
    tr_ok = have(train_files)
    gt_s = time.perf_counter() - t
    summary["phases"]["ground_truth"] = {"seconds": gt_s, "train_shapes": len(tr_ok), "of": len(train_files),
                                         "val_shapes": len(have(val_files)),
                                         "per_shape_s": gt_s / max(1, len(tr_ok) + len(val_files)),
                                         "settings": f"{cfg.sources} sources x {cfg.targets} targets, "
                                                     f"{cfg.cloud_points}-point cloud, solver defaults"}
    log(f"ground truth: {len(tr_ok)}/{len(train_files)} training + {len(val_files)} validation shapes in "
        f"{gt_s:.1f} s ({summary['phases']['ground_truth']['per_shape_s']:.2f} s per shape)")
    if len(tr_ok) < len(train_files):
        log(f"NOTE: ground truth reached only {len(tr_ok)} of {len(train_files)} training shapes by its deadline; "
            f"training uses those")
    save()

    # training
    budget = deadline - time.perf_counter() - a.eval_reserve - 10.0
    if a.train_seconds:
        budget = min(budget, a.train_seconds)
    cfg.budget_seconds = max(10.0, budget)
    log(f"training for {cfg.budget_seconds:.0f} s: {len(tr_ok)} shapes, {cfg.shapes_per_step} shapes x "
        f"({cfg.step_sources} x {cfg.step_targets}) pairs per step, lr {cfg.lr:g} cosine to {cfg.lr_min:g} over "
        f"the budget, rotate={cfg.rotate}")
    t = time.perf_counter()
    model = a.out / "model.pt"
    ck = train_generalizable(coll, model, cfg, device=a.device, cache=cache, log=log, files=(tr_ok, val_files))
    tr_s = time.perf_counter() - t
    summary["phases"]["training"] = {"seconds": tr_s, "steps": ck["step"], "train_seconds": ck["elapsed_s"],
                                     "s_per_step": ck["elapsed_s"] / max(1, ck["step"]),
                                     "val_history": ck["val_history"], "loss_history": ck["loss_history"][-50:],
                                     "config": ck["config"]}
    log(f"training: {ck['step']} steps in {ck['elapsed_s']:.1f} s ({1e3 * ck['elapsed_s'] / max(1, ck['step']):.1f} "
        f"ms per step); validation MRE " + ", ".join(f"{s}: {100 * v:.2f}%" for s, v in ck["val_history"]))
    save()
    del ck
    if torch.cuda.is_available():
        torch.cuda.empty_cache()

    # evaluation
    left = deadline - time.perf_counter()
    extra = ["--model", str(model), "--sources", "8", "--targets", "512"]
    rc, ev_s = run_eval(a, log, test_files[: a.eval_shapes], extra, "eval.json", "table.txt", "eval.log",
                        timeout=max(30.0, left + 25.0))
    summary["phases"]["evaluation"] = {"seconds": ev_s, "exit": rc, "unseen_shapes": min(a.eval_shapes,
                                                                                        len(test_files))}
    if (a.out / "eval.json").exists():
        summary["eval_summary"] = json.loads((a.out / "eval.json").read_text())["summary"]
    summary["total_seconds"] = time.perf_counter() - T0
    save()
    log(f"done in {summary['total_seconds']:.1f} s; files in {a.out}: "
        + ", ".join(sorted(p.name for p in a.out.iterdir())))
    return 0 if rc == 0 else 1


def cmd_per_mesh(a) -> int:
    a.out.mkdir(parents=True, exist_ok=True)
    a.work.mkdir(parents=True, exist_ok=True)
    log = Log(a.out / "per_mesh.log")
    shared = find_shared(a.shared)
    log(f"shared data: {shared}; device {a.device}")
    from neurogf_warp.generalizable.shapes import (
        deform_sources_present,
        is_test,
        write_collection,
    )

    meshes = str(shared / "meshes") if shared else None
    if not deform_sources_present(meshes):
        log("WARNING: no 'deformed' family sources in the shared meshes: those shapes become 'blob' (as in run?)")
    # only the test shapes (same seed and rule: the same files as in `run`), then the same order as `run`
    coll = a.work / "coll_pm"
    for i in range(a.shapes):
        if is_test(i, a.test_every):
            write_collection(coll, n=i + 1, seed=a.seed, test_every=a.test_every, shared_meshes=meshes, start=i,
                             progress=False)
    files = eval_order(sorted((coll / "test").glob("*.obj")))[: a.eval_shapes]
    log("per-mesh shapes: " + ", ".join(f.name for f in files) + " + the shared meshes")
    extra = ["--sources", "8", "--targets", "512", "--per-mesh-seconds", str(a.per_mesh_seconds),
             "--work", str(a.work / "per_mesh_models")]
    rc, _ = run_eval(a, log, files, extra, "eval_per_mesh.json", "table_per_mesh.txt", "eval_per_mesh.log",
                     timeout=a.time_limit - (time.perf_counter() - T0))
    return 0 if rc == 0 else 1


def cmd_merge(a) -> int:
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from generalizable_eval import mre_table

    base = json.loads(Path(a.run_json).read_text())
    extra = json.loads(Path(a.per_mesh_json).read_text())
    by = {(r["group"], r["shape"]): r for r in extra["rows"]}
    rows, notes = [], []
    for r in base["rows"]:
        r = dict(r)
        e = by.get((r["group"], r["shape"]))
        if e is not None:
            for k in ("per_mesh", "per_mesh_train_s"):
                if k in e:
                    r[k] = e[k]
            if "heat" in r and "heat" in e and abs(r["heat"] - e["heat"]) > 1e-9 * max(1.0, r["heat"]):
                notes.append(f"{r['shape']}: heat MRE differs between the calls ({r['heat']} vs {e['heat']}): "
                             f"not the same pairs")
        rows.append(r)
    cols = [c for c in ("trained", "released", "heat", "per_mesh") if any(c in r for r in rows)]
    text, summary = mre_table(rows, cols, f"MRE on the same pairs (merged: {a.run_json} + {a.per_mesh_json}; "
                                          f"device {base.get('device')})")
    text += "".join("\nNOTE: " + n for n in notes)
    print(text)
    out = Path(a.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps({"rows": rows, "summary": summary, "notes": notes}, indent=1))
    out.with_suffix(".txt").write_text(text + "\n")
    return 1 if notes else 0


def cmd_pack_shared(a) -> int:
    """Copy what these calls read from the shared data (all 9 meshes: 3 to evaluate, 6 as 'deformed' sources;
    the 3 exact references; GenNeuroGF.pth), 12.0 MiB, to take to another machine; a destination ending in ``.tar.xz`` gets an archive of them instead (5.0 MiB), which --shared and
    $NEUROGF_SHARED accept as they are."""
    import shutil
    import tarfile
    import tempfile

    src, dst = Path(a.src), Path(a.dst)
    need = [src / "meshes" / n for n in sorted(p.name for p in (src / "meshes").iterdir()
                                                if p.suffix in (".obj", ".ply"))]
    need += [src / "reference" / "exact" / f"{n}.npz" for n in ("stanford-bunny", "fandisk", "spot")]
    need += [src / "checkpoints" / "official" / "GenNeuroGF.pth"]
    missing = [str(p) for p in need if not p.is_file()]
    if missing:
        print("error: missing " + ", ".join(missing), file=sys.stderr)
        return 2
    archive = str(dst).endswith(".tar.xz")
    folder = Path(tempfile.mkdtemp(prefix="pack_shared_")) if archive else dst
    total = 0
    for p in need:
        q = folder / p.relative_to(src)
        q.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(p, q)
        total += q.stat().st_size
    if archive:
        dst.parent.mkdir(parents=True, exist_ok=True)
        with tarfile.open(dst, "w:xz") as tf:
            for name in ("meshes", "reference", "checkpoints"):
                tf.add(folder / name, arcname=name)
        shutil.rmtree(folder)
        print(f"{len(need)} files ({total / 2**20:.1f} MiB) in {dst}: {dst.stat().st_size / 2**20:.1f} MiB")
    else:
        print(f"{len(need)} files, {total / 2**20:.1f} MiB in {dst}")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    for name in ("run", "per-mesh"):
        p = sub.add_parser(name)
        p.add_argument("--out", type=Path, default=Path(os.environ.get("OUT", "out")))
        p.add_argument("--work", type=Path, default=Path("/tmp/gencoll"), help="scratch: collection, ground truth")
        p.add_argument("--shared", default=None, help="shared data folder (meshes/, reference/, checkpoints/) or a "
                                                      "pack-shared .tar.xz; default $NEUROGF_SHARED, ../shared, "
                                                      "./shared")
        p.add_argument("--device", default="cuda:0")
        p.add_argument("--shapes", type=int, default=540)
        p.add_argument("--seed", type=int, default=0)
        p.add_argument("--test-every", type=int, default=10)
        p.add_argument("--time-limit", type=float, default=540.0 if name == "run" else 560.0,
                       help="seconds from start to the end of the evaluation")
    r = sub.choices["run"]
    r.add_argument("--gen-workers", type=int, default=min(16, os.cpu_count() or 1))
    r.add_argument("--sources", type=int, default=256)
    r.add_argument("--targets", type=int, default=512)
    r.add_argument("--cloud-points", type=int, default=2048)
    r.add_argument("--shapes-per-step", type=int, default=16)
    r.add_argument("--step-sources", type=int, default=64)
    r.add_argument("--step-targets", type=int, default=128)
    r.add_argument("--steps", type=int, default=20000, help="cosine length in steps, if the time budget lasts")
    r.add_argument("--lr", type=float, default=1e-2)
    r.add_argument("--rotate", type=lambda v: v.lower() in ("1", "true", "yes", "on"), default=True)
    r.add_argument("--val-every", type=int, default=500)
    r.add_argument("--val-shapes", type=int, default=32)
    r.add_argument("--log-every", type=int, default=250)
    r.add_argument("--train-seconds", type=float, default=None, help="cap on training time (default: what is left)")
    r.add_argument("--min-train-seconds", type=float, default=180.0,
                   help="ground truth stops early enough to leave this much training")
    r.add_argument("--eval-reserve", type=float, default=75.0, help="seconds kept for the evaluation")
    r.add_argument("--eval-shapes", type=int, default=30)
    pm = sub.choices["per-mesh"]
    pm.add_argument("--eval-shapes", type=int, default=3)
    pm.add_argument("--per-mesh-seconds", type=float, default=60.0)
    ps = sub.add_parser("pack-shared", help="copy the shared files these calls need into a small folder")
    ps.add_argument("src", help="the shared data folder (meshes/, reference/, checkpoints/)")
    ps.add_argument("dst")
    m = sub.add_parser("merge")
    m.add_argument("run_json")
    m.add_argument("per_mesh_json")
    m.add_argument("-o", "--output", default="merged", help="writes OUTPUT.json and OUTPUT.txt")
    a = ap.parse_args(argv)
    if a.cmd == "merge":
        return cmd_merge(a)
    if a.cmd == "pack-shared":
        return cmd_pack_shared(a)
    a.out, a.work = a.out.resolve(), a.work.resolve()
    a.work.mkdir(parents=True, exist_ok=True)
    a.shared = unpack_shared(a.shared, a.work)
    return cmd_run(a) if a.cmd == "run" else cmd_per_mesh(a)


if __name__ == "__main__":
    sys.exit(main())
