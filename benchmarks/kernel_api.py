"""Cost per call of the in-kernel API (``neurogf_warp.kernels.field``) and its gradient errors, one command.

    python benchmarks/kernel_api.py --device cpu --points 2048        # a CPU
    python benchmarks/kernel_api.py --device cuda:0 --points 1048576  # a GPU

Each function runs in a kernel of one thread per point (points near the released bunny's surface, normalized
frame); the table gives time per call (median of the repeats, compile excluded) and the dense FLOP count
(a multiply-add is 2 FLOPs; the backward passes skip rows whose ReLU is off, so they do fewer). The gradient
errors are relative to float64 torch autograd and to float64 one-sided differences (the closer one), on the
released bunny and fandisk networks. JSON goes to --json.
"""
from __future__ import annotations

import argparse
import datetime
import platform
import statistics
import sys
import time

import numpy as np
import torch

import _bootstrap  # noqa: F401  (this checkout's neurogf_warp, installed or not)
import warp as wp
from common import find_shared, write_json

from neurogf_warp.kernels import field

N_SOURCES = 5


@wp.kernel(enable_backward=False)
def k_distance(net: field.NeuroGFWeights, x: wp.array(dtype=wp.vec3), y: wp.array(dtype=wp.vec3),
               out: wp.array(dtype=float)):
    i = wp.tid()
    out[i] = field.geodesic_distance(net, x[i], y[i])


@wp.kernel(enable_backward=False)
def k_distance_grad(net: field.NeuroGFWeights, x: wp.array(dtype=wp.vec3), y: wp.array(dtype=wp.vec3),
                    out: wp.array(dtype=float), g: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    d, gr = field.distance_and_gradient(net, x[i], y[i])
    out[i] = d
    g[i] = gr


@wp.kernel(enable_backward=False)
def k_sources(net: field.NeuroGFWeights, src: field.SourceSet, x: wp.array(dtype=wp.vec3), out: wp.array(dtype=float)):
    i = wp.tid()
    out[i] = field.distance_to_sources(net, src, x[i])


@wp.kernel(enable_backward=False)
def k_sources_grad(net: field.NeuroGFWeights, src: field.SourceSet, x: wp.array(dtype=wp.vec3),
                   out: wp.array(dtype=float), g: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    d, gr, s = field.distance_to_sources_and_gradient(net, src, x[i])
    out[i] = d
    g[i] = gr


@wp.kernel(enable_backward=False)
def k_direction(net: field.NeuroGFWeights, src: field.SourceSet, x: wp.array(dtype=wp.vec3),
                out: wp.array(dtype=float), g: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    d, t = field.geodesic_direction(net, src, x[i])
    out[i] = d
    g[i] = t


@wp.kernel(enable_backward=False)
def k_sdf(net: field.NeuroGFWeights, x: wp.array(dtype=wp.vec3), out: wp.array(dtype=float)):
    i = wp.tid()
    out[i] = field.signed_distance(net, x[i])


@wp.kernel(enable_backward=False)
def k_sdf_grad(net: field.NeuroGFWeights, x: wp.array(dtype=wp.vec3), out: wp.array(dtype=float),
               g: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    s, gr = field.signed_distance_and_gradient(net, x[i])
    out[i] = s
    g[i] = gr


@wp.kernel(enable_backward=False)
def k_project(net: field.NeuroGFWeights, x: wp.array(dtype=wp.vec3), g: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    g[i] = field.project_to_surface(net, x[i], 2)


def flops(net, n_sources: int) -> dict:
    """Dense FLOP counts per call from the layer widths (multiply-add = 2)."""
    D, n_in, H = net.D, net.lifting[0].linear.in_features, net.gdf_head[0].linear.out_features
    lift = 2 * (n_in * D // 4 + D // 4 * D // 2 + D // 2 * D)
    head = 2 * (D * H + H * H + H)
    return {"geodesic_distance": 2 * lift + head,
            "distance_and_gradient": 3 * lift + 2 * head,
            f"distance_to_sources (S={n_sources})": lift + n_sources * head,
            f"distance_to_sources_and_gradient (S={n_sources})": 2 * lift + (n_sources + 2) * head,
            f"geodesic_direction (S={n_sources})": 3 * lift + (n_sources + 4) * head,
            "signed_distance": lift + head,
            "signed_distance_and_gradient": 2 * lift + 2 * head,
            "project_to_surface (2 steps)": 2 * (2 * lift + 2 * head)}


def gradient_errors(model, rng, n=256) -> dict:
    """Warp gradients against float64 torch autograd and one-sided differences, points near the surface."""
    import neurogf_warp as ngf

    net64 = model.net.double().eval()
    v = model.mesh.internal_normalized_vertices
    p = v[rng.integers(0, len(v), n)] + rng.normal(0, 0.01, (n, 3))
    q = v[rng.integers(0, len(v), n)]
    P, Q = (wp.array(a.astype(np.float32), dtype=wp.vec3, device="cpu") for a in (p, q))
    d, g = wp.zeros(n, dtype=float), wp.zeros(n, dtype=wp.vec3)
    s, gs = wp.zeros(n, dtype=float), wp.zeros(n, dtype=wp.vec3)
    w = ngf.warp_weights(model, "cpu")
    wp.launch(k_distance_grad, n, inputs=[w, P, Q], outputs=[d, g], device="cpu")
    wp.launch(k_sdf_grad, n, inputs=[w, P], outputs=[s, gs], device="cpu")
    Pt = torch.from_numpy(p.astype(np.float32).astype(np.float64)).requires_grad_(True)
    Qt = torch.from_numpy(q.astype(np.float32).astype(np.float64))
    ref_g, = torch.autograd.grad(net64.distance(Pt, Qt).sum(), Pt)
    X = Pt.detach().clone().requires_grad_(True)
    ref_gs, = torch.autograd.grad(net64.sdf(X).sum(), X)
    h, eye = 1e-6, torch.eye(3, dtype=torch.float64)
    with torch.no_grad():
        P0 = Pt.detach()
        sided = lambda f: torch.stack([torch.stack([(f(P0 + s_ * h * eye[c]) - f(P0)) / (s_ * h) for c in range(3)], -1)
                                       for s_ in (1.0, -1.0)]).numpy()
        fd, fds = sided(lambda x: net64.distance(x, Qt)), sided(net64.sdf)
    out = {}
    for name, got, ref, sd in (("distance", g.numpy(), ref_g.numpy(), fd), ("sdf", gs.numpy(), ref_gs.numpy(), fds)):
        scale = np.maximum(np.linalg.norm(ref, axis=1), 1e-12)
        ra = np.linalg.norm(got - ref, axis=1) / scale
        rf = np.linalg.norm(np.abs(got[None] - sd).min(0), axis=1) / scale
        out[name] = {"autograd": {"median": float(np.median(ra)), "p99": float(np.quantile(ra, 0.99)),
                                  "max": float(ra.max())},
                     "differences": {"median": float(np.median(rf)), "p99": float(np.quantile(rf, 0.99)),
                                     "max": float(rf.max())}}
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--points", type=int, default=2048)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    import neurogf_warp as ngf
    from neurogf_warp.inference.warp_structs import source_set

    ck = lambda n: find_shared("checkpoints", "official", f"NeuroGF_Pretrainer__{n}_final.pth")
    model = ngf.load(ck("bunny"), mesh=find_shared("meshes", "stanford-bunny.obj"))
    dev = a.device
    rng = np.random.default_rng(0)
    v = model.mesh.internal_normalized_vertices
    n = a.points
    x = wp.array((v[rng.integers(0, len(v), n)] + rng.normal(0, 0.005, (n, 3))).astype(np.float32), dtype=wp.vec3,
                 device=dev)
    y = wp.array(v[rng.integers(0, len(v), n)].astype(np.float32), dtype=wp.vec3, device=dev)
    w = ngf.warp_weights(model, dev)
    src = source_set(model, rng.choice(model.mesh.n_input, N_SOURCES, replace=False), dev)
    f1, f2 = wp.zeros(n, dtype=float, device=dev), wp.zeros(n, dtype=wp.vec3, device=dev)
    runs = {"geodesic_distance": (k_distance, [w, x, y, f1]),
            "distance_and_gradient": (k_distance_grad, [w, x, y, f1, f2]),
            f"distance_to_sources (S={N_SOURCES})": (k_sources, [w, src, x, f1]),
            f"distance_to_sources_and_gradient (S={N_SOURCES})": (k_sources_grad, [w, src, x, f1, f2]),
            f"geodesic_direction (S={N_SOURCES})": (k_direction, [w, src, x, f1, f2]),
            "signed_distance": (k_sdf, [w, x, f1]),
            "signed_distance_and_gradient": (k_sdf_grad, [w, x, f1, f2]),
            "project_to_surface (2 steps)": (k_project, [w, x, f2])}
    t0 = time.perf_counter()
    wp.load_module(sys.modules[__name__], device=dev)
    compile_s = time.perf_counter() - t0
    fl = flops(model.net, N_SOURCES)
    rows = {}
    print(f"device {wp.get_device(dev)}, {n} points, released bunny (D={model.D}); module load {compile_s:.1f} s")
    print(f"{'function':52s} {'time/call':>12s} {'kFLOP':>8s}")
    for name, (kern, args) in runs.items():
        def once():
            wp.launch(kern, n, inputs=args, device=dev)
            wp.synchronize_device(dev)
        once()
        ts = []
        for _ in range(a.repeats):
            t = time.perf_counter()
            once()
            ts.append(time.perf_counter() - t)
        per = statistics.median(ts) / n
        rows[name] = {"seconds_per_call": per, "flops": fl[name]}
        unit = f"{per * 1e6:.1f} us" if per >= 1e-6 else f"{per * 1e9:.2f} ns"
        print(f"{name:52s} {unit:>12s} {fl[name] / 1e3:8.0f}")
    errs = {}
    for name in ("bunny", "fandisk"):
        mesh = find_shared("meshes", {"bunny": "stanford-bunny.obj"}.get(name, f"{name}.obj"))
        errs[name] = gradient_errors(ngf.load(ck(name), mesh=mesh), np.random.default_rng(1))
        for what, e in errs[name].items():
            print(f"{name} {what} gradient, relative error vs autograd: median {e['autograd']['median']:.1e}, "
                  f"p99 {e['autograd']['p99']:.1e}, max {e['autograd']['max']:.1e}; vs differences: median "
                  f"{e['differences']['median']:.1e}, p99 {e['differences']['p99']:.1e}, max {e['differences']['max']:.1e}")
    res = {"date": datetime.date.today().isoformat(), "device": str(wp.get_device(dev)), "host": platform.node(),
           "points": n, "D": model.D, "module_load_s": compile_s, "calls": rows, "gradient_errors": errs}
    if a.json:
        write_json(a.json, res, "kernel_api", a.device)
    return res


if __name__ == "__main__":
    main()
