"""Path-head output forms compared on fixed lifting features (CPU, fandisk).

    python benchmarks/experiments/path_head_cpu.py STEPS BATCH MODE [MODE ...]     # MODE: absolute | residual | window
    NGF_MODEL=path/to/fandisk.ngf (a trained fandisk model; its lifting is kept, in eval mode)

Each MODE trains a freshly initialized guidance + path head for STEPS steps of BATCH paths (+ their reversed
copies) and is scored by Chamfer-L1 on the 512 test pairs that `evaluate()` uses (seed 0, 16 x 32).
"""
import copy
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from common import find_shared  # noqa: E402

import neurogf_warp as ngf  # noqa: E402
from neurogf_warp.evaluation import metrics  # noqa: E402
from neurogf_warp.dataset.build import build_dataset  # noqa: E402
from neurogf_warp.ground_truth.geodesics import geodesic_paths  # noqa: E402
from neurogf_warp.model.network import NeuroGFNet, straight_lines  # noqa: E402
from neurogf_warp.training import losses as L  # noqa: E402
from neurogf_warp.training.trainer import cosine_lr, fast_path  # noqa: E402


def test_pairs(mesh):
    rng, V, gts = np.random.default_rng(0), len(mesh.internal_vertices), []
    for s in rng.choice(V, 16, replace=False):
        tg = rng.choice(V, 32, replace=False)
        g = geodesic_paths(mesh, mesh.index[s], mesh.index[tg[tg != s]], m=128, device="cpu")
        g = mesh.normalize(g.reshape(-1, 3)).reshape(g.shape)
        gts.append(g[np.isfinite(g).all(axis=(1, 2))])
    return np.concatenate(gts)


def run(base, mode, pg, gt_test, steps, batch):
    torch.manual_seed(0)
    net = copy.deepcopy(base)
    fresh = NeuroGFNet(base.D, path_residual=mode != "absolute", path_window=mode == "window")
    net.cdw_fc, net.spf_head = fresh.cdw_fc, fresh.spf_head
    net.path_residual, net.path_window = fresh.path_residual, fresh.path_window
    opt = torch.optim.AdamW(list(net.cdw_fc.parameters()) + list(net.spf_head.parameters()), lr=3e-3, weight_decay=1e-8)
    net.cdw_fc.train()
    net.spf_head.train()
    gen = torch.Generator().manual_seed(1)

    def predict(p, q):
        with torch.no_grad():
            e = net.embed(torch.cat([p, q]))
        return fast_path(net, e[: len(p)], e[len(p):], straight_lines(p, q, 128))

    t0 = time.time()
    for i in range(steps):
        for g in opt.param_groups:
            g["lr"] = cosine_lr(i, steps, 3e-3, 1e-4)
        b = pg[torch.randint(0, len(pg), (batch,), generator=gen)]
        loss = L.l1(predict(torch.cat([b[:, 0], b[:, -1]]), torch.cat([b[:, -1], b[:, 0]])), torch.cat([b, b.flip(1)]))
        opt.zero_grad()
        loss.backward()
        opt.step()
    net.eval()
    with torch.no_grad():
        P, Q = (torch.as_tensor(gt_test[:, i], dtype=torch.float32) for i in (0, -1))
        pred = predict(P, Q).double().numpy()
        tr = pg[:512]
        cdt = metrics.chamfer_l1(predict(tr[:, 0], tr[:, -1]).double().numpy(), tr.double().numpy())
    cd = metrics.chamfer_l1(pred, gt_test)
    ends = 0.5 * (np.linalg.norm(pred[:, 0] - gt_test[:, 0], axis=1) + np.linalg.norm(pred[:, -1] - gt_test[:, -1], axis=1))
    print(f"{mode:9s} training L1 {float(loss.detach()):.3e}  test Chamfer {cd.mean():.3e} (median {np.median(cd):.3e}, "
          f"end points {ends.mean():.2e})  training-path Chamfer {cdt.mean():.3e}  {time.time() - t0:.0f}s", flush=True)


def main(argv):
    steps, batch, modes = int(argv[0]), int(argv[1]), argv[2:]
    torch.set_num_threads(2)
    mesh = ngf.load_mesh(find_shared("meshes", "fandisk.obj"))
    base = ngf.load(os.environ.get("NGF_MODEL", "fandisk.ngf")).net.eval()
    t0 = time.time()
    ds = build_dataset(mesh, None, n_sources=256, n_global=64, n_local1=8, n_local2=64, n_path_sources=256,
                       n_path_global=64, n_path_local=4, n_test=0, device="cpu", progress=False)
    print(f"dataset {time.time() - t0:.1f} s", flush=True)
    pg = torch.as_tensor(ds.path_global)
    gt_test = test_pairs(mesh)
    for mode in modes:
        run(base, mode, pg, gt_test, steps, batch)


if __name__ == "__main__":
    main(sys.argv[1:])
