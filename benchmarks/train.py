"""Train NeuroGF on bunny and fandisk and measure it against the exact references, in one command.

GPU (the target: everything, ground truth included, inside one 9-minute call; one GPU per mesh):
    python benchmarks/train.py --device cuda:0 --parallel --budget-seconds 510
CPU smoke test (a couple of minutes; tiny data and network, numbers meaningless):
    python benchmarks/train.py --device cpu --small

Per mesh: build the dataset (our solver), train with the step counts scaled to the time left, then
evaluate: MRE / max relative error over the 8 exact-reference sources, path Chamfer-L1 against solver
paths, SDF L1, and the heat method on the same sources. Writes <out>/train_bench.json and, when
matplotlib is importable, <out>/loss_curves.png.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import shlex
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the checkout's package when it is not installed (the GPU machine)
import neurogf_warp as ngf  # noqa: E402
from neurogf_warp.evaluation.evaluate import format_table  # noqa: E402
from neurogf_warp.training import RunFiles, preset  # noqa: E402
from neurogf_warp.training.config import parse_assignments  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import MESHES, TARGETS, find_shared, parse_data_options  # noqa: E402  (./.bench on the GPU machine)

SHARE = {"bunny": 0.6, "fandisk": 0.4}  # bunny is larger and has the harder target

# The GPU recipe's dataset is build_dataset's default (DatasetSettings); the history of these counts is in
# benchmarks/RESULTS.md. --small: tiny data and network (preset cpu_small, k=1: ~14 s of ground truth for bunny).
SMALL_DATA = dict(n_sources=24, n_global=512, n_local1=16, n_local2=64, n_path_sources=8, n_path_global=16,
                  n_path_local=16, n_test=2, n_surface=30000, n_spread=2000, k=1)


def _usable(path: Path, mesh) -> bool:
    if not path.exists():
        return False
    try:
        ngf.load_dataset(path, mesh=mesh)
        return True
    except Exception as e:  # stale or corrupt: rebuild
        print(f"not reusing {path}: {e}", flush=True)
        return False


def _plot(results: dict, path: Path) -> bool:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except Exception:  # matplotlib is optional here
        return False
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    for name, r in results.items():
        h = r.get("history")
        if not h:
            continue
        n_joint = r["steps"]["joint"]
        x_of = lambda row: row["step"] + (n_joint if row.get("stage") == "refine_dist" else 0)
        dist = [x for x in h["loss"] if x["stage"] in ("joint", "refine_dist")]
        joint = [x for x in dist if x["stage"] == "joint"]
        axes[0].semilogy([x["step"] for x in joint], [x["loss"] for x in joint], label=f"{name} joint loss")
        axes[0].semilogy([x_of(x) for x in dist], [x["dist_g"] for x in dist], "--",
                         label=f"{name} global distance loss (relative)")
        if h["val"]:
            axes[1].semilogy([x_of(v) for v in h["val"]], [100 * v["mre"] for v in h["val"]], "o-", label=name)
        for ax in axes:
            ax.axvline(n_joint, color="0.7", lw=0.8)
    axes[0].set_xlabel("step (joint, then refine_dist after the grey line)")
    axes[0].legend()
    axes[1].set_xlabel("step (joint, then refine_dist)")
    axes[1].set_ylabel("validation MRE % (held-out solver sources)")
    axes[1].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def _chamfer(r: dict) -> str:
    ref = r.get("chamfer_l1_refined")
    return f"{r['chamfer_l1']:.3e} ({ref:.3e})" if ref is not None else f"{r['chamfer_l1']:.3e} (-)"


def _released(r: dict) -> str:
    rel = r.get("released", {})
    return f"{rel['mre']:.3%}  {_chamfer(rel)}" if "mre" in rel else "-"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda:0" if torch.cuda.is_available() else "cpu")
    p.add_argument("--meshes", nargs="+", default=list(MESHES), choices=list(MESHES))
    p.add_argument("--budget-seconds", type=float, default=None,
                   help="wall time for the whole command (default 500 on GPU, 150 with --small)")
    p.add_argument("--small", action="store_true", help="tiny data and network: a CPU smoke test")
    p.add_argument("--D", type=int, default=None)
    p.add_argument("--n-sources", type=int, default=None, help="training sources per mesh")
    p.add_argument("--eval-reserve", type=float, default=None, help="seconds kept for evaluation per mesh")
    p.add_argument("--path-refine", type=int, default=None, metavar="N",
                   help="also score the paths after N shortening sweeps per level (default 50 on GPU, 2 with --small)")
    p.add_argument("--no-released", dest="released", action="store_false",
                   help="skip evaluating the released checkpoint on the same sources and pairs")
    p.add_argument("--no-amp", dest="amp", action="store_false", help="float32 path head (default: bf16 on CUDA)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="training setting (TrainConfig, dataset settings included), e.g. --set batch_surf=256")
    p.add_argument("--data", action="append", default=[], metavar="KEY=VALUE",
                   help="dataset setting (DatasetSettings), e.g. --data target_pool=all (repeatable)")
    p.add_argument("--variant", action="append", default=[], metavar="NAME:OPTIONS",
                   help="with --parallel: also run every mesh with these extra options, e.g. "
                        "'pool:--data target_pool=all' (repeatable; one GPU per mesh and variant)")
    p.add_argument("--out", default=str(Path(os.environ.get("OUT", ROOT / "benchmarks" / "results")) / "train"),
                   help="models, JSON and PNG (small files)")
    p.add_argument("--work", default=os.path.join(tempfile.gettempdir(), "neurogf-train-bench"),
                   help="datasets (large; kept out of --out)")
    p.add_argument("--parallel", action="store_true",
                   help="one process per mesh (and --variant), run i on GPU i (CUDA_VISIBLE_DEVICES), each with "
                        "the whole budget")
    p.add_argument("--reuse-data", action="store_true",
                   help="reuse a dataset already in --work for the same mesh and settings (its time is then not counted)")
    argv = list(sys.argv[1:] if argv is None else argv)
    a = p.parse_args(argv)
    if a.parallel:
        return _parallel(a, argv)

    t_begin = time.perf_counter()
    budget = a.budget_seconds or (150.0 if a.small else 500.0)
    reserve = a.eval_reserve if a.eval_reserve is not None else (10.0 if a.small else 20.0)
    out, work = Path(a.out), Path(a.work)
    out.mkdir(parents=True, exist_ok=True)
    work.mkdir(parents=True, exist_ok=True)
    if a.small:
        torch.set_num_threads(1)  # tiny batches: threads only add sync overhead
    cfg = preset("cpu_small" if a.small else "default")
    if a.small:
        cfg = cfg.set(**SMALL_DATA)
    changes = parse_assignments(a.set)
    if a.D:
        changes["D"] = a.D
    if not a.amp:
        changes["amp"] = False
    if a.n_sources:
        changes["n_sources"] = a.n_sources
    cfg = cfg.set(**changes, **parse_data_options(a.data))
    data_opts, train_opts = cfg.to_dict()["data"], {k: v for k, v in cfg.to_dict().items() if k != "data"}
    report = {"device": a.device, "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
              "torch": torch.__version__, "python": platform.python_version(), "budget_s": budget,
              "small": a.small, "data_options": data_opts, "train_options": train_opts, "meshes": {}}

    # 0. the Warp inference kernels (evaluation, refined paths), compiled once and timed on their own
    import warp as wp

    from neurogf_warp.kernels.inference import mlp

    t0 = time.perf_counter()
    wp.load_module(mlp, device="cpu" if a.device == "cpu" else f"cuda:{torch.device(a.device).index or 0}")
    report["warp_compile_s"] = round(time.perf_counter() - t0, 2)

    # 1. ground truth for every mesh first, so the training budget is what is really left
    meshes, datasets = {}, {}
    for name in a.meshes:
        obj, _ = MESHES[name]
        meshes[name] = ngf.load_mesh(find_shared("meshes", obj))
        tag = hashlib.sha1(json.dumps(data_opts, sort_keys=True).encode()).hexdigest()[:8]
        path = work / f"{name}-{'small' if a.small else 'full'}-{tag}.dataset.npz"
        t0 = time.perf_counter()
        reused = a.reuse_data and _usable(path, meshes[name])
        if not reused:
            ngf.build_dataset(meshes[name], path, cfg.data, seed=cfg.seed, device=a.device, progress=True)
        datasets[name] = path
        report["meshes"][name] = {"dataset_s": round(time.perf_counter() - t0, 2), "dataset_reused": reused}
        print(f"[{name}] dataset {'reused' if reused else 'built'} in {report['meshes'][name]['dataset_s']:.1f}s",
              flush=True)

    # 2. train, each mesh getting its share of the time left
    left = budget - (time.perf_counter() - t_begin) - reserve * len(a.meshes)
    shares = {n: SHARE[n] / sum(SHARE[m] for m in a.meshes) for n in a.meshes}
    results = {}
    for i, name in enumerate(a.meshes):
        left = budget - (time.perf_counter() - t_begin) - reserve * (len(a.meshes) - i)
        rest = sum(shares[m] for m in a.meshes[i:])
        secs = max(5.0, left * shares[name] / rest)  # train() fits set-up, compiling and saving inside it
        model_path = work / f"{name}.ngf"  # models and run folders stay out of --out (small files only)
        t0 = time.perf_counter()
        model = ngf.train(meshes[name], model_path, config=cfg, dataset=datasets[name], device=a.device,
                          budget_seconds=secs, progress=True, force=True)
        r = report["meshes"][name]
        r["train_budget_s"] = round(secs, 1)
        r["train_wall_s"] = round(time.perf_counter() - t0, 2)
        log = json.loads(Path(RunFiles.for_model(model_path).log).read_text())
        r["train_s"] = log["config"]["train_seconds"]
        r["steps"] = log["config"]["steps"]
        r["history"] = log["history"]

        # 3. evaluate against the exact reference
        t0 = time.perf_counter()
        ref = find_shared("reference", "exact", MESHES[name][1])
        kw = dict(n_path_sources=1 if a.small else 16, n_path_targets=16 if a.small else 32,
                  solver_k=1 if a.small else None, device=a.device, verbose=False,
                  path_refine=a.path_refine if a.path_refine is not None else (2 if a.small else 50))
        ev = ngf.evaluate(model, meshes[name], ref, heat=True, **kw)
        r["eval_s"] = round(time.perf_counter() - t0, 2)
        r["eval"] = ev
        r["released"] = {"missing": "not evaluated (--no-released)"}
        if a.released:  # the released checkpoint on the same sources and path pairs, for scale
            try:
                rel = ngf.load(find_shared("checkpoints", "official", f"NeuroGF_Pretrainer__{name}_final.pth"),
                           mesh=meshes[name])
                er = ngf.evaluate(rel, meshes[name], ref, sdf=False, **kw)
                r["released"] = {"mre": er["neurogf"]["mre"], "max_rel": er["neurogf"]["max_rel"],
                                 **{k: v for k, v in er.items() if k.startswith("chamfer_l1")}}
            except FileNotFoundError as e:
                r["released"] = {"missing": str(e)}
        r["mre"] = ev["neurogf"]["mre"]
        r["chamfer_l1"] = ev.get("chamfer_l1")
        r["chamfer_l1_refined"] = ev.get("chamfer_l1_refined")
        r["meets_mre_target"] = bool(r["mre"] <= TARGETS[name])
        r["meets_chamfer_target"] = bool(r["chamfer_l1"] is not None and r["chamfer_l1"] <= TARGETS["chamfer_l1"])
        r["meets_chamfer_target_refined"] = bool(r["chamfer_l1_refined"] is not None
                                                 and r["chamfer_l1_refined"] <= TARGETS["chamfer_l1"])
        print(f"[{name}] " + format_table(ev).replace("\n", f"\n[{name}] "), flush=True)
        results[name] = r

    report["total_s"] = round(time.perf_counter() - t_begin, 2)
    report["plot"] = _plot(report["meshes"], out / "loss_curves.png")
    (out / "train_bench.json").write_text(json.dumps(report, indent=1))

    print("\nmesh     MRE      target   Chamfer-L1 (refined)   dataset_s  train_s  steps(joint)  "
          "released: MRE  Chamfer-L1 (refined)")
    for name, r in results.items():
        print(f"{name:8s} {r['mre']:.3%}  {TARGETS[name]:.2%}   {_chamfer(r)}   {r['dataset_s']:8.1f}"
              f"  {r['train_s']:7.1f}  {r['steps']['joint']:12d}  {_released(r)}")
    print(f"total {report['total_s']:.1f}s of budget {budget:.0f}s; results in {out}, models in {work}")
    return 0


def _parallel(a, argv) -> int:
    """One process per mesh and variant, each on its own GPU; merge their reports into <out>/train_bench.json."""
    import subprocess

    base, skip = [], False
    for x in argv:  # the same options minus --parallel / --meshes / --out / --work / --variant
        if skip and not x.startswith("--"):
            continue
        skip = x in ("--meshes", "--out", "--work", "--variant")
        if not skip and x != "--parallel" and not x.startswith(("--meshes=", "--out=", "--work=", "--variant=")):
            base.append(x)
    variants = {}
    for v in a.variant or [":"]:
        name, sep, opts = v.partition(":")
        if not sep or not name.replace("-", "").replace("_", "").isalnum() and name:
            raise SystemExit(f"--variant {v!r}: expected NAME:OPTIONS with NAME made of letters, digits, - and _")
        variants[name] = shlex.split(opts)
    runs = [(m, v) for m in a.meshes for v in variants]  # run i gets GPU i
    if torch.cuda.is_available() and len(runs) > torch.cuda.device_count():
        raise SystemExit(f"{len(runs)} runs (meshes x variants) but {torch.cuda.device_count()} GPUs")
    out, work = Path(a.out), Path(a.work)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    procs = {}
    for i, (mesh, v) in enumerate(runs):
        key = f"{mesh}_{v}" if v else mesh
        env = dict(os.environ, CUDA_VISIBLE_DEVICES=str(i))
        # each process's own report and plot go to the work folder; --out gets the merged ones and the logs
        cmd = [sys.executable, __file__, *base, *variants[v], "--meshes", mesh, "--out", str(work / key / "report"),
               "--work", str(work / key)]
        log = open(out / f"{key}.log", "w")
        procs[key] = (mesh, v, subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT), log)
    codes = {}
    for key, (_, _, proc, log) in procs.items():
        codes[key] = proc.wait()
        log.close()
    wall = time.perf_counter() - t0
    merged = {"parallel": True, "wall_s": round(wall, 2), "exit_codes": codes,
              "variants": {v: shlex.join(o) for v, o in variants.items()}, "meshes": {}}
    for key, (mesh, v, _, _) in procs.items():
        f = work / key / "report" / "train_bench.json"
        if f.exists():
            r = json.loads(f.read_text())
            merged["meshes"][key] = dict(r["meshes"][mesh], mesh=mesh, variant=v, process_total_s=r["total_s"],
                                         data_options=r["data_options"], train_options=r["train_options"])
            for k in ("gpu", "torch", "python", "budget_s"):
                merged.setdefault(k, r.get(k))
    merged["plot"] = _plot(merged["meshes"], out / "loss_curves.png")
    (out / "train_bench.json").write_text(json.dumps(merged, indent=1))
    print("run              MRE      target   Chamfer-L1 (refined)   process_s  exit  released: MRE  Chamfer-L1 (refined)")
    for key, (mesh, _, _, _) in procs.items():
        r = merged["meshes"].get(key)
        if r is None:
            print(f"{key:16s} failed (exit {codes[key]}); see {out / f'{key}.log'}")
            continue
        print(f"{key:16s} {r['mre']:.3%}  {TARGETS[mesh]:.2%}   {_chamfer(r)}   {r['process_total_s']:8.1f}"
              f"  {codes[key]:4d}  {_released(r)}")
    print(f"{len(runs)} runs in {wall:.1f}s (one process and one GPU each); results in {out}")
    return max(codes.values())


if __name__ == "__main__":
    sys.exit(main())
