"""Single-source distances (SSAD) on a bound model for landmark bracket networks: GPU time against K.

    python benchmarks/landmark_ssad.py --device cuda:0                 # the 436K-vertex bunny, K = 0, 32, ..., 256
    python benchmarks/landmark_ssad.py --device cpu --small            # a tiny mesh on the CPU emulation: a smoke test

For each K a random network ``NeuroGFNet(D, fourier=2, euclid=True, landmarks=K, landmark_bracket=True)`` (K = 0:
today's default network, no landmarks) is bound to the mesh (``neurogf_warp.bind``) and its SSAD from one vertex
timed on tensor cores (precision="fp16"):

- kernel ms: CUDA events around many back-to-back launches of the backend's call (what the public call launches,
  without its Python), median of several batches after a warm-up: the GPU time of one SSAD;
- public ms: the same around ``neurogf_warp.ssad(model, vertex, output="warp")`` (host time included);
- bytes per vertex: what the kernel reads per mesh vertex (fp16 embedding, fp32 table row, the point) plus the
  4-byte answer it writes; the table's size in MB.

The landmark table holds scaled straight-line distances to K random vertices (a metric, so the bounds bracket
every pair; the kernel's time does not depend on the values). Answers are checked against a float64 torch
evaluation of the same network on a random subset of vertices: the largest error relative to the largest distance
(``max err``, the tests' measure) and the largest error relative to each distance (``max rel``). Prints a table and
writes JSON ($OUT/landmark_ssad.json or --json) with the device, date, commit and command.
"""
from __future__ import annotations

import argparse
import datetime
import os
import statistics
import sys
import time

import numpy as np
import torch

import _bootstrap  # noqa: F401  (this checkout's neurogf_warp, installed or not)
from common import bumpy_torus, subdivided_bunny, write_json

FULL_K = (0, 32, 64, 128, 256)
SMALL_K = (0, 16, 32)
CHECK_BAR = 2e-3  # max err against float64 relative to the largest distance (tests/test_landmark_tensorcore.py)


def parse_k(text: str) -> list:
    from neurogf_warp.kernels.inference.tensorcore import LANDMARK_K

    try:
        ks = [int(k) for k in text.split(",") if k.strip()]
    except ValueError:
        raise SystemExit(f"--k takes comma-separated integers, got {text!r}")
    bad = [k for k in ks if k != 0 and k not in LANDMARK_K]
    if bad or not ks:
        raise SystemExit(f"--k: {bad or text!r} not supported: K is 0 (no landmarks) or one of {LANDMARK_K}")
    return ks


def load_mesh(a):
    """(vertices, faces) of the benchmark mesh: the subdivided bunny of benchmarks/queries.py, a bumpy torus, or a
    mesh file."""
    if a.small:
        return bumpy_torus(24)  # 576 vertices
    if a.mesh == "bunny":
        try:
            return subdivided_bunny(a.vertices)
        except FileNotFoundError as e:
            raise SystemExit(f"{e}\n(or pass --mesh torus for a generated 435,600-vertex mesh, or --mesh FILE)")
    if a.mesh == "torus":
        return bumpy_torus(660)
    import trimesh

    if not os.path.exists(a.mesh):
        raise SystemExit(f"--mesh {a.mesh!r}: no such file (or pass bunny or torus)")
    tm = trimesh.load(a.mesh, process=False, force="mesh")
    return np.asarray(tm.vertices, np.float64), np.asarray(tm.faces, np.int64)


def make_net(D: int, K: int, seed: int):
    from neurogf_warp.model.network import NeuroGFNet

    torch.manual_seed(seed + K)
    if K == 0:
        return NeuroGFNet(D, fourier=2, euclid=True, path_residual=True, path_window=True).eval()
    return NeuroGFNet(D, fourier=2, euclid=True, landmarks=K, landmark_bracket=True).eval()


def landmark_table(xn: np.ndarray, K: int, rng) -> np.ndarray:
    """(V, K) float32 scaled chords to K random vertices, in chunks of vertices (436K x 256 is 450 MB)."""
    marks = xn[rng.choice(len(xn), K, replace=False)]
    out = np.empty((len(xn), K), np.float32)
    for lo in range(0, len(xn), 1 << 15):
        out[lo: lo + (1 << 15)] = 1.2 * np.linalg.norm(xn[lo: lo + (1 << 15), None] - marks[None], axis=-1)
    return out


class _Rows(torch.nn.Module):
    """The float64 reference's landmark lookup: a ``network.Landmarks`` on float32 points (bit-identical match)."""

    def __init__(self, xyz32: np.ndarray, table: np.ndarray):
        super().__init__()
        from neurogf_warp.model.network import Landmarks

        self.lm = Landmarks(table.shape[1])
        self.lm.set_table(torch.from_numpy(xyz32), torch.from_numpy(table))

    def set_table(self, xyz, table):  # a Model sets its table here too: the same float32 rows
        self.lm.set_table(xyz, table)

    def forward(self, x):
        return self.lm(x.float()).double()


def unit_head(net, xn32: np.ndarray, table, rng):
    """Scale the distance head's last layer to outputs of about unit spread around 0: a random head is far from 0,
    where the bracket's sigmoid saturates and an error check would not see the head."""
    x = torch.from_numpy(xn32[rng.integers(0, len(xn32), 1024)].astype(np.float64))
    with torch.no_grad():
        net64 = net.double()
        i, j = torch.arange(512), torch.arange(512, 1024)
        e = net64.embed(x)
        parts = [(e[i] - e[j]).abs()]
        if table is not None:
            tp, tq = net64.landmark_table(x[i]), net64.landmark_table(x[j])
            d = (tp - tq).abs()
            parts += [d, d.max(-1).values[:, None], (tp + tq).min(-1).values[:, None]]
        hidden = net64.gdf_head[:-1](torch.cat(parts, -1))
        w = net64.gdf_head[-1].linear.weight
        y = hidden @ w[0]
        w.sub_((y.mean() / hidden.mean(0).square().sum()) * hidden.mean(0)).mul_(1.0 / y.std())
    return net.float()


def reference(net, mesh, xn32, src: int, subset: np.ndarray, scale: float) -> np.ndarray:
    """float64 distances (no finishing) from file vertex ``src`` to file vertices ``subset``, mesh units."""
    net64 = net.double()
    p = torch.from_numpy(xn32[[src]].astype(np.float64))
    q = torch.from_numpy(xn32[subset].astype(np.float64))
    with torch.no_grad():
        es, eq = net64.embed(p), net64.embed(q)
        d = net64.distance_from_embeddings(es.expand(len(q), -1), eq, p.expand(len(q), 3), q)
    net.float()
    return d.numpy() / scale


def median_ms(fn, repeats: int, batches: int, cuda: bool, sync) -> float:
    """Median per-call ms of ``repeats`` back-to-back calls (events around them on CUDA), over ``batches``."""
    import warp as wp

    fn()
    sync()
    per = []
    for _ in range(batches):
        if cuda:
            a, b = wp.Event(enable_timing=True), wp.Event(enable_timing=True)
            sync()
            wp.record_event(a)
            for _ in range(repeats):
                fn()
            wp.record_event(b)
            sync()
            per.append(wp.get_event_elapsed_time(a, b) / repeats)
        else:
            t = time.perf_counter()
            for _ in range(repeats):
                fn()
            per.append((time.perf_counter() - t) * 1e3 / repeats)
    return statistics.median(per)


def run(a) -> dict:
    import warp as wp

    wp.config.quiet = True
    wp.init()
    import neurogf_warp as ngf
    from neurogf_warp.inference.backends import backend_of
    from neurogf_warp.inference.state import query_state

    dev = wp.get_device(a.device)
    cuda = dev.is_cuda
    if not cuda and not a.small:
        raise SystemExit("on the CPU the tensor-core kernels run as a slow emulation: pass --small (a tiny mesh)")
    ks = parse_k(a.k) if a.k else list(SMALL_K if a.small else FULL_K)
    D = a.d or (64 if a.small else 256)
    repeats = a.repeats or (3 if not cuda else 200)
    t = time.perf_counter()
    v, f = load_mesh(a)
    mesh = ngf.load_mesh((v, f))
    res = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"), "device": a.device,
           "argv": sys.argv[1:], "D": D, "repeats": repeats, "batches": a.batches,
           "mesh": {"name": "small torus" if a.small else a.mesh, "vertices": int(mesh.n_input),
                    "internal_vertices": int(len(mesh.internal_vertices)), "faces": int(len(f)),
                    "build_s": time.perf_counter() - t}, "rows": []}
    print(f"mesh: {res['mesh']['vertices']:,} vertices ({res['mesh']['build_s']:.1f} s); D = {D}; "
          f"device {a.device}", flush=True)
    rng = np.random.default_rng(a.seed)
    V = len(mesh.internal_vertices)
    src = int(mesh.index[rng.integers(V)])  # a file vertex that a face uses
    used = np.asarray(mesh.index)
    subset = np.unique(np.concatenate([[src], rng.choice(used, min(a.check, len(used)), replace=False)]))

    def sync():
        wp.synchronize_device(dev)

    for K in ks:
        row = {"K": K}
        try:
            net = make_net(D, K, a.seed)
            xn32 = ((np.asarray(mesh.vertices, np.float64) - mesh.center) * mesh.scale).astype(np.float32)
            table = landmark_table(xn32.astype(np.float64), K, rng) if K else None
            if K:
                net.landmark_table = _Rows(xn32, table)
            if K:  # (today's network keeps its random head, as benchmarks/queries.py times it)
                net = unit_head(net, xn32, table, rng)
            model = ngf.Model(net=net, mesh=mesh, center=mesh.center, scale=mesh.scale, landmarks=table)
            t = time.perf_counter()
            row["bound_bytes"] = ngf.bind(model, a.device, precision="fp16")
            first = ngf.ssad(model, src, device=a.device, precision="fp16", output="warp", raw=True)
            sync()
            row["first_call_s"] = time.perf_counter() - t  # binding, compiling (or loading) the kernel
            st = query_state(model, a.device)
            be, md = backend_of(st, "fp16"), st.mesh("ssad")
            ids = np.array([mesh.vertex(src)], np.int64)
            pts = md.rel64[ids]
            out = wp.empty(V, dtype=wp.float32, device=dev)
            row["kernel_ms"] = median_ms(lambda: be.vertex_distances(md, pts, ids, None, out, False, True), repeats,
                                         a.batches, cuda, sync)
            row["public_ms"] = median_ms(lambda: ngf.ssad(model, src, device=a.device, precision="fp16",
                                                          output="warp", raw=True), repeats, a.batches, cuda, sync)
            row["table_mb"] = V * K * 4 / 1e6
            row["bytes_per_vertex"] = 2 * D + 4 * K + 12 + 4  # embedding, table row, point; the answer written
            row["gb_per_s"] = V * row["bytes_per_vertex"] / (row["kernel_ms"] * 1e-3) / 1e9
            got = first.numpy()[subset].astype(np.float64)
            ref = reference(net, mesh, xn32, src, subset, mesh.scale)
            err = np.abs(got - ref)
            row["max_err"] = float(err.max() / np.abs(ref).max())
            away = subset != src
            row["max_rel"] = float((err[away] / np.abs(ref[away])).max())
            row["checked_vertices"] = int(len(subset))
            model.invalidate()  # frees this K's embeddings and table before the next K
        except Exception as e:  # a K that fails (memory, compilation) is reported, the others still run
            row["error"] = f"{type(e).__name__}: {e}"[:500]
        res["rows"].append(row)
        print("  " + (f"K={K}: kernel {row['kernel_ms']:.4f} ms, public {row['public_ms']:.4f} ms, "
                      f"max err {row['max_err']:.1e}" if "error" not in row else f"K={K}: {row['error']}"), flush=True)
    return res


def table(res: dict) -> str:
    cols = f"{'K':>4} {'table MB':>9} {'B/vertex':>9} {'kernel ms':>10} {'GB/s':>7} {'public ms':>10} " \
           f"{'max err':>8} {'max rel':>8}"
    lines = [f"SSAD on a bound model, {res['mesh']['vertices']:,} vertices, D = {res['D']}, {res['device']} "
             f"({'GPU time' if res['device'].startswith('cuda') else 'CPU emulation, wall time'})", cols]
    for r in res["rows"]:
        if "error" in r:
            lines.append(f"{r['K']:>4} {r['error']}")
            continue
        lines.append(f"{r['K']:>4} {r['table_mb']:>9.1f} {r['bytes_per_vertex']:>9d} {r['kernel_ms']:>10.4f} "
                     f"{r['gb_per_s']:>7.0f} {r['public_ms']:>10.4f} {r['max_err']:>8.1e} {r['max_rel']:>8.1e}")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cuda:0" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--small", action="store_true", help="a tiny mesh, D = 64, K in 0, 16, 32 (a smoke test)")
    ap.add_argument("--k", default=None, help="comma-separated landmark counts (0: no landmarks; else multiples of "
                                              "16 up to 256); default 0,32,64,128,256 (--small: 0,16,32)")
    ap.add_argument("--d", type=int, default=None, choices=(64, 128, 256), help="embedding width (default 256; "
                                                                                "--small: 64)")
    ap.add_argument("--mesh", default="bunny", help="bunny (the subdivided bunny of benchmarks/queries.py, from the "
                                                    "shared data), torus (a generated 435,600-vertex mesh) or a file")
    ap.add_argument("--vertices", type=int, default=436_000, help="the bunny's vertex target")
    ap.add_argument("--repeats", type=int, default=None, help="calls per timed batch (default 200; CPU 3)")
    ap.add_argument("--batches", type=int, default=5, help="timed batches (the median is kept)")
    ap.add_argument("--check", type=int, default=4096, help="vertices checked against float64")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default=None, help="output JSON (default: $OUT/landmark_ssad.json, else "
                                                 "./landmark_ssad.json)")
    a = ap.parse_args(argv)
    res = run(a)
    text = table(res)
    out = write_json(a.json or os.path.join(os.environ.get("OUT", "."), "landmark_ssad.json"), res, "landmark_ssad",
                     a.device)
    print("\n" + text + f"\nJSON: {out}")
    bad = [r for r in res["rows"] if not r.get("max_err", np.inf) <= CHECK_BAR]
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
