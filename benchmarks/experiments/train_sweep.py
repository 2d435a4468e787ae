"""Training variants side by side on one mesh, at the same time budget each, in one command.

    python benchmarks/experiments/train_sweep.py --mesh bunny --budget-seconds 80 \\
        --variant paper: --variant rel:dist_loss=relative --variant 'big:batch_g=131072;lr=0.02'

One dataset is built (its time printed) and shared by all variants; each variant trains for the same wall
time (steps fitted to it) and is evaluated against the exact reference (MRE over its sources) and solver
paths (Chamfer-L1). ``--check-graph`` first compares CUDA-graph and eager training steps on the same state
(agreement and seconds per step of each stage). Prints a table; writes <out>/sweep.json.
With torch.compile on (the CUDA default) the first variant, and any variant with new shapes (another D or batch),
pays the ~25 s compilation inside its budget; later variants reuse the cache. Put a throw-away variant first.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from common import MESHES, TARGETS, find_shared, parse_data_options  # noqa: E402

from neurogf_warp.dataset.build import build_dataset, load_dataset  # noqa: E402
from neurogf_warp.evaluation.evaluate import evaluate  # noqa: E402
from neurogf_warp.mesh.mesh import load_mesh  # noqa: E402
from neurogf_warp.training import STAGES, RunFiles, preset, train  # noqa: E402
from neurogf_warp.training.budget import calibrate  # noqa: E402
from neurogf_warp.training.config import parse_assignments  # noqa: E402
from neurogf_warp.training.data import TrainingData, make_sdf_pool  # noqa: E402
from neurogf_warp.training.trainer import Trainer  # noqa: E402


def check_graph(mesh, ds, device, overrides, steps=8) -> dict:
    """Same start, same draws: eager and CUDA-graph steps of every stage; max parameter difference and s/step."""
    cfg = preset("default").set(**overrides)
    data = TrainingData(ds, device)
    pool = make_sdf_pool(mesh, data.surface_points, 200_000, 0, device)
    out = {}
    runs = {}
    for graphs in (False, True):
        t = Trainer(cfg.set(cuda_graph=graphs), data, pool, device)
        terms = []
        for stage in STAGES:
            t.set_modes(stage)
            for i in range(steps):
                terms.append({k: float(v.detach()) for k, v in t.step(stage, i).items()})
        runs[graphs] = (t, terms)
    (te, ae), (tg, ag) = runs[False], runs[True]
    out["max_param_diff"] = max(float((a.float() - b.float()).abs().max())
                                for a, b in zip(te.net.state_dict().values(), tg.net.state_dict().values()))
    out["max_loss_rel_diff"] = max(abs(x[k] - y[k]) / max(abs(x[k]), 1e-12) for x, y in zip(ae, ag) for k in x)
    for graphs in (False, True):
        t = Trainer(cfg.set(cuda_graph=graphs), data, pool, device)
        out["s_per_step_graph" if graphs else "s_per_step_eager"] = calibrate(t, n=20)
    return out


def profile(mesh, ds, device, stages=("joint", "refine_dist"), steps=5) -> str:
    """torch.profiler table of the CUDA kernels of a few eager steps per stage."""
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as prof

    cfg = preset("default", cuda_graph=False)
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = True  # as training runs
    data = TrainingData(ds, device)
    t = Trainer(cfg, data, make_sdf_pool(mesh, data.surface_points, 200_000, 0, device), device)
    text = []
    for stage in stages:
        t.set_modes(stage)
        for i in range(3):
            t.step(stage, i)
        torch.cuda.synchronize()
        with prof(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as p:
            for i in range(steps):
                t.step(stage, i)
            torch.cuda.synchronize()
        ka = p.key_averages()
        for key in ("self_device_time_total", "self_cuda_time_total"):
            try:
                tab = ka.table(sort_by=key, row_limit=22, max_name_column_width=70)
                break
            except Exception:  # noqa: BLE001 - the key's name changed across torch versions
                tab = None
        text.append(f"== {stage}: {steps} steps\n{tab}")
    return "\n".join(text)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--mesh", default="bunny", choices=list(MESHES))
    p.add_argument("--device", default="cuda:0" if torch.cuda.is_available() else "cpu")
    p.add_argument("--budget-seconds", type=float, default=80.0, help="training wall time per variant")
    p.add_argument("--joint-steps", type=int, default=None,
                   help="instead of a time budget: this many joint steps per variant (other stages by their ratios), "
                        "so compile time does not confound variants of equal step cost; wall times are still reported")
    p.add_argument("--variant", action="append", default=[], metavar="NAME:K=V;K=V",
                   help="a TrainConfig variant (repeatable); 'paper:' is the defaults")
    p.add_argument("--data", action="append", default=[], metavar="KEY=VALUE", help="build_dataset option")
    p.add_argument("--check-graph", action="store_true")
    p.add_argument("--profile", action="store_true", help="print a kernel profile of joint and refine_dist steps")
    p.add_argument("--out", default=str(Path(os.environ.get("OUT", ROOT / "benchmarks" / "results")) / "sweep"))
    p.add_argument("--work", default=os.path.join(tempfile.gettempdir(), "neurogf-sweep"))
    a = p.parse_args(argv)

    out, work = Path(a.out), Path(a.work)
    out.mkdir(parents=True, exist_ok=True)
    work.mkdir(parents=True, exist_ok=True)
    obj, ref = MESHES[a.mesh]
    mesh = load_mesh(find_shared("meshes", obj))
    data_opts = dict(n_sources=512, n_path_sources=256, n_path_global=128, n_path_local=32, n_test=8)
    data_opts.update(parse_data_options(a.data))
    report = {"mesh": a.mesh, "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
              "torch": torch.__version__, "date": time.strftime("%Y-%m-%d"), "budget_s": None if a.joint_steps else a.budget_seconds,
              "joint_steps": a.joint_steps,
              "data_options": data_opts, "variants": {}}

    t0 = time.perf_counter()
    ds_path = work / f"{a.mesh}.dataset.npz"
    build_dataset(mesh, ds_path, preset("default").set(**data_opts).data, device=a.device, progress=False)
    ds = load_dataset(ds_path)
    report["dataset_s"] = round(time.perf_counter() - t0, 2)
    report["dataset_timings"] = ds.meta["timings"]
    print(f"[{a.mesh}] dataset {report['dataset_s']:.1f}s {ds.meta['timings']}", flush=True)

    if a.check_graph:
        t0 = time.perf_counter()
        report["check_graph"] = check_graph(mesh, ds, a.device, {})
        print(f"check_graph ({time.perf_counter() - t0:.1f}s): {json.dumps(report['check_graph'])}", flush=True)

    if a.profile:
        print(profile(mesh, ds, a.device), flush=True)

    for spec in a.variant or ["paper:"]:
        name, _, kv = spec.partition(":")
        opts = parse_assignments([x for x in kv.split(";") if x])
        t0 = time.perf_counter()
        model_path = work / f"{name}.ngf"
        try:
            fixed = {} if a.joint_steps is None else {"epochs": max(1, a.joint_steps // 200), "iters_per_epoch": 200}
            model = train(mesh, model_path, config=preset("default").set(**fixed, **opts), dataset=ds,
                          device=a.device, progress=False, budget_seconds=None if fixed else a.budget_seconds,
                          force=True)
        except Exception as e:  # noqa: BLE001 - one failing variant must not lose the others
            print(f"[{name}] FAILED: {type(e).__name__}: {e}", flush=True)
            report["variants"][name] = {"options": opts, "error": f"{type(e).__name__}: {e}"}
            continue
        wall = time.perf_counter() - t0
        log = json.loads(Path(RunFiles.for_model(model_path).log).read_text())
        ev = evaluate(model, mesh, find_shared("reference", "exact", ref), n_path_sources=16, n_path_targets=32,
                      device=a.device, verbose=False)
        with torch.no_grad():  # path fit on training paths (eval mode): the generalization gap next to the test Chamfer
            import numpy as np

            from neurogf_warp.evaluation import metrics as L

            allp = np.asarray(ds.path_global)
            pick = np.random.default_rng(0).choice(len(allp), min(512, len(allp)), replace=False)
            gt = torch.as_tensor(allp[pick], device=a.device)
            net = model.net.to(a.device).eval()
            pred = net.path(gt[:, 0], gt[:, -1], 128)
            train_paths = {"l1": float((pred - gt).abs().mean()),
                           "chamfer_l1": float(L.chamfer_l1(pred.cpu().numpy(), gt.cpu().numpy()).mean())}
        r = {"train_paths": train_paths, "options": opts, "train_wall_s": round(wall, 1), "train_s": log["config"]["train_seconds"],
             "steps": log["config"]["steps"], "mre": ev["neurogf"]["mre"], "max_rel": ev["neurogf"]["max_rel"],
             "p99_rel": ev["neurogf"]["p99_rel"], "chamfer_l1": ev["chamfer_l1"], "sdf_l1": ev.get("sdf_l1"),
             "val": [(v.get("stage", "joint"), v["step"], v["mre"]) for v in log["history"]["val"]],
             "last_joint": [x for x in log["history"]["loss"] if x["stage"] == "joint"][-1]}
        report["variants"][name] = r
        print(f"[{name}] MRE {r['mre']:.3%} max {r['max_rel']:.1%} Chamfer {r['chamfer_l1']:.3e} "
              f"(training paths: {train_paths['chamfer_l1']:.3e}, L1 {train_paths['l1']:.3e}) "
              f"steps {r['steps']} wall {wall:.0f}s", flush=True)
        (out / "sweep.json").write_text(json.dumps(report, indent=1))

    per = f"{a.joint_steps} joint steps" if a.joint_steps else f"{a.budget_seconds:.0f} s"
    print(f"\n{a.mesh}: {per} per variant; target MRE {TARGETS[a.mesh]:.2%}, "
          f"Chamfer {TARGETS['chamfer_l1']:.2e}")
    print(f"{'variant':14s} {'MRE':>8s} {'max':>7s} {'Chamfer':>9s} {'joint':>7s} {'train s':>8s}  options")
    for name, r in report["variants"].items():
        if "error" in r:
            print(f"{name:14s} failed: {r['error'][:80]}")
            continue
        print(f"{name:14s} {r['mre']:8.3%} {r['max_rel']:7.1%} {r['chamfer_l1']:9.3e} {r['steps']['joint']:7d} "
              f"{r['train_s']:8.1f}  {r['options']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
