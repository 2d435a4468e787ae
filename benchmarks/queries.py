"""Every NeuroGF query, Warp against every PyTorch variant, on the same inputs in one run.

    python benchmarks/queries.py --device cuda:0                  # a GPU: full sizes
    python benchmarks/queries.py --device cpu --quick             # small sizes: a smoke test on a CPU

For each query (SSAD on a bound model, SSAD cold from a point, MSAD with 8 sources, a 64-source distance
matrix, point-pair distances, SDF, paths) it times the library's call (``neurogf_warp.ssad`` etc., device
arrays in and out) and the PyTorch forms of the same network: eager fp32, TF32, fp16, bf16, a CUDA graph of
the fp16 forward, ``torch.compile(mode="max-autotune-no-cudagraphs")`` in fp16 with and without a CUDA graph
around it, and the cached-embedding form where one applies. Every result is checked against a float64
evaluation of the network (relative L2 error; 1e-3 is the bar). Next to each time it prints the roofline:
FLOPs at the measured fp16 tensor-core rate and bytes at the measured copy bandwidth, and the fraction of that
floor reached. Compile times (Warp cold and from its cache, torch.compile) are reported apart from run times.
It also measures the released bunny/fandisk checkpoints' MRE against the exact references in each precision.
Writes JSON ($OUT/queries.json or --json) and prints one table.
"""
from __future__ import annotations

import argparse
import datetime
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np
import torch

import _bootstrap  # noqa: F401  (this checkout's neurogf_warp, installed or not)
from common import ROOT, find_shared as shared, subdivided_bunny as benchmark_mesh, write_json
from released import released_mre as _released_rows

# multiply-accumulates of the D=256, 2-octave network (the released layout plus Fourier inputs: F = 15)
def macs(D=256, F=15):
    lift = F * D // 4 + D // 4 * D // 2 + D // 2 * D
    head = D * D // 4 + D // 4 * D // 4 + D // 4
    point = 3 * D // 2 + D // 2 * D // 4 + D // 4 * D // 8 + D // 8 * 3
    per_path = 2 * lift + 2 * D * D + D * D // 2
    return {"lift": lift, "head": head, "point": point, "per_path": per_path}


# ---- timing ---------------------------------------------------------------------------------------------------------

class Timer:
    """Median per-call time of back-to-back calls: CUDA events around a batch of calls, several batches."""

    def __init__(self, device: str, repeats: int, batches: int = 5):
        self.cuda = device.startswith("cuda")
        self.repeats, self.batches = repeats, batches

    def __call__(self, fn) -> float:
        fn()
        self.sync()
        per = []
        for _ in range(self.batches):
            if self.cuda:
                start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
                self.sync()
                start.record()
                for _ in range(self.repeats):
                    fn()
                end.record()
                self.sync()
                per.append(start.elapsed_time(end) / 1e3 / self.repeats)
            else:
                t = time.perf_counter()
                for _ in range(self.repeats):
                    fn()
                per.append((time.perf_counter() - t) / self.repeats)
        return statistics.median(per)

    def device(self, fn, n: int = 10) -> float:
        """Median GPU time of one call on an idle GPU (events on Warp's stream around the call)."""
        import warp as wp

        if not self.cuda:
            return float("nan")
        times = []
        for _ in range(n):
            self.sync()
            a, b = wp.Event(enable_timing=True), wp.Event(enable_timing=True)
            wp.record_event(a)
            fn()
            wp.record_event(b)
            self.sync()
            times.append(wp.get_event_elapsed_time(a, b) / 1e3)
        return statistics.median(times)

    def sync(self):
        import warp as wp

        if self.cuda:
            torch.cuda.synchronize()
            wp.synchronize()


def ceilings(device: str) -> dict:
    """Measured fp16 tensor-core rate (a large GEMM) and copy bandwidth (read + write) on this device."""
    if not device.startswith("cuda"):
        return {"fp16_flops": float("nan"), "bandwidth": float("nan")}
    t = Timer(device, 5, 3)
    a = torch.randn(8192, 8192, device=device, dtype=torch.float16)
    b = torch.randn(8192, 8192, device=device, dtype=torch.float16)
    gemm = t(lambda: a @ b)
    x = torch.randn(1 << 30, device=device, dtype=torch.float32)  # 4 GiB
    y = torch.empty_like(x)
    copy = t(lambda: y.copy_(x))
    del a, b, x, y
    torch.cuda.empty_cache()
    return {"fp16_flops": 2 * 8192**3 / gemm, "bandwidth": 2 * 4 * (1 << 30) / copy}


def _levels_of(m: int) -> list:
    out = [m]
    while len(out) < 3 and out[0] // 2 >= 8:
        out.insert(0, out[0] // 2)
    return out


def rel_err(got, ref) -> float:
    g = np.asarray(got, dtype=np.float64).reshape(-1)
    r = np.asarray(ref, dtype=np.float64).reshape(-1)
    ok = np.isfinite(r)
    if not np.array_equal(np.isfinite(g), ok):
        return float("inf")
    return float(np.linalg.norm(g[ok] - r[ok]) / max(np.linalg.norm(r[ok]), 1e-30))


# ---- PyTorch forms of the network ------------------------------------------------------------------------------------

class TorchForms:
    """The network in every PyTorch variant, on normalized inputs; results in the user's units."""

    def __init__(self, model, device: str, compile_modes):
        self.model, self.device, self.compile_modes = model, device, compile_modes
        self.nets = {}
        self.compile_s = {}

    def net(self, dtype):
        if dtype not in self.nets:
            import copy

            self.nets[dtype] = copy.deepcopy(self.model.net).to(self.device, dtype).eval()
        return self.nets[dtype]

    def variants(self, name: str, build, inputs: dict, cached_build=None) -> dict:
        """{variant: zero-argument callable}; build(net, dtype) -> fn(**inputs_in_dtype)."""
        cuda = self.device.startswith("cuda")
        out = {}

        def bind(dtype, tf32=False, fn_builder=build):
            x = {k: (v.to(dtype) if torch.is_floating_point(v) else v) for k, v in inputs.items()}
            fn = fn_builder(self.net(dtype), dtype)

            def run():
                torch.backends.cuda.matmul.allow_tf32 = tf32
                torch.backends.cudnn.allow_tf32 = tf32
                with torch.no_grad():
                    return fn(**x)
            return run, fn, x

        out["torch eager fp32"] = bind(torch.float32)[0]
        if not cuda:
            return out
        out["torch eager TF32"] = bind(torch.float32, tf32=True)[0]
        out["torch eager fp16"], fn16, x16 = bind(torch.float16)
        out["torch eager bf16"] = bind(torch.bfloat16)[0]
        out["torch CUDA graph fp16"] = self._graph(lambda: fn16(**x16))
        if cached_build is not None:
            out["torch eager fp16, cached e(x)"], cfn, cx = bind(torch.float16, fn_builder=cached_build)
            out["torch CUDA graph fp16, cached e(x)"] = self._graph(lambda: cfn(**cx))
        for mode in self.compile_modes:
            for label, b in (("", build), (", cached e(x)", cached_build)):
                if b is None:
                    continue
                _, f, x = bind(torch.float16, fn_builder=b)
                t = time.perf_counter()
                cf = torch.compile(f, mode=mode, dynamic=False)
                with torch.no_grad():
                    cf(**x)
                    cf(**x)
                torch.cuda.synchronize()
                self.compile_s[f"{name}: torch.compile {mode}{label}"] = time.perf_counter() - t
                run = (lambda cf=cf, x=x: cf(**x))
                out[f"torch.compile {mode} fp16{label}"] = lambda run=run: _nograd(run)
                out[f"torch.compile {mode} fp16 + CUDA graph{label}"] = self._graph(run)
        return out

    @staticmethod
    def _graph(fn):
        s = torch.cuda.Stream()
        s.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(s), torch.no_grad():
            for _ in range(3):
                fn()
        torch.cuda.current_stream().wait_stream(s)
        g = torch.cuda.CUDAGraph()
        with torch.cuda.graph(g), torch.no_grad():
            out = fn()
        return lambda: (g.replay(), out)[1]


def _nograd(fn):
    with torch.no_grad():
        return fn()


# ---- the queries -------------------------------------------------------------------------------------------------

def device_bytes_in_use(dev) -> dict:
    """Device memory in use, from the driver (total - free) and, on CUDA, from Warp's memory pool (Warp's
    arrays come from the pool; memory freed to the pool shows there, not in the driver's count)."""
    import warp as wp

    wp.synchronize_device(dev)
    out = {}
    if dev.is_cuda:
        out["device used (bytes)"] = int(dev.total_memory - dev.free_memory)
        if wp.is_mempool_enabled(dev):
            out["warp mempool used (bytes)"] = int(wp.get_mempool_used_mem_current(dev))
    return out


def bind_memory(ngf, model, src, device) -> dict:
    """Memory before ``bind``, after it and one bound SSAD (tables and recorded launches made), and after
    ``unbind`` (unbind returns the bound memory); on the CPU only the bytes kept."""
    import gc

    import warp as wp

    dev = wp.get_device(device)
    model.unbind()
    gc.collect()
    before = device_bytes_in_use(dev)
    kept = ngf.bind(model, device)
    ngf.ssad(model, src, device=device, output="warp")
    bound = device_bytes_in_use(dev)
    model.unbind()
    gc.collect()
    after = device_bytes_in_use(dev)
    out = {"kept by bind (bytes)": kept}
    for k in before:
        out[f"{k}: before bind"] = before[k]
        out[f"{k}: bound, after one ssad"] = bound[k]
        out[f"{k}: after unbind"] = after[k]
    if "warp mempool used (bytes)" in before:
        got_back = bound["warp mempool used (bytes)"] - after["warp mempool used (bytes)"]
        out["returned by unbind (bytes)"] = got_back
        print(f"memory: bind keeps {kept / 1e6:.1f} MB; unbind returns {got_back / 1e6:.1f} MB to Warp's pool "
              f"(in use: {before['warp mempool used (bytes)'] / 1e6:.1f} MB before bind, "
              f"{bound['warp mempool used (bytes)'] / 1e6:.1f} MB bound, "
              f"{after['warp mempool used (bytes)'] / 1e6:.1f} MB after unbind)", flush=True)
    return out


def run(a) -> dict:
    cold_cache = tempfile.mkdtemp(prefix="warp-cache-")
    os.environ["WARP_CACHE_PATH"] = cold_cache  # a cold kernel cache: compile times measured from scratch
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    wp.config.kernel_cache_dir = cold_cache
    wp.init()
    import neurogf_warp as ngf

    device = a.device
    dev = wp.get_device(device)
    tdev = torch.device(device)
    cuda = dev.is_cuda
    quick = a.quick or not cuda
    M = macs()
    sizes = dict(V=436_000, S_msad=8, S_matrix=64, pairs=4_000_000, sdf=1_000_000, paths=10_000, m=128,
                 refine_pairs=1000, refine=50, refine_check=64)
    if quick:
        sizes = dict(V=6_000, S_msad=8, S_matrix=16, pairs=20_000, sdf=20_000, paths=200, m=128,
                     refine_pairs=4, refine=3, refine_check=2)
    for kv in a.size:
        k, v = kv.split("=")
        sizes[k] = int(v)
    res = {"date": datetime.date.today().isoformat(), "device": device,
           "device_name": torch.cuda.get_device_name(tdev) if cuda else platform.processor() or platform.machine(),
           "warp": wp.config.version, "torch": torch.__version__, "sizes": sizes, "rows": [], "compile_s": {}}
    res["ceilings"] = ceil = ceilings(device)
    print(f"device {res['device_name']}: fp16 GEMM {ceil['fp16_flops'] / 1e12:.0f} TFLOP/s, "
          f"copy {ceil['bandwidth'] / 1e12:.2f} TB/s", flush=True)

    t = time.perf_counter()
    v, f = benchmark_mesh(sizes["V"])
    ckpt = shared("checkpoints", "official", "NeuroGF_Pretrainer__bunny_final.pth")
    model = ngf.load(ckpt, mesh=(v, f))
    # the released network has no Fourier inputs or |p - q| term; the default trained network has both:
    # time the default layout with the released weights' scale by a random network of the same shape
    if a.network == "default":
        from neurogf_warp.model.network import NeuroGFNet

        torch.manual_seed(0)
        net = NeuroGFNet(256, fourier=2, euclid=True, path_residual=True, path_window=True)
        net.load_state_dict({k: v for k, v in model.net.state_dict().items()
                             if not k.startswith("lifting.0")}, strict=False)
        model = ngf.Model(net=net, mesh=model.mesh, center=model.center, scale=model.scale)
    V = model.mesh.n_input
    res["mesh"] = {"vertices": V, "faces": int(len(f)), "build_s": time.perf_counter() - t, "network": a.network}
    print(f"mesh: {V} vertices ({res['mesh']['build_s']:.1f} s to build); network: {a.network}", flush=True)

    # Warp: compile every kernel from a cold cache, then again in a fresh process from the cache
    t = time.perf_counter()
    ngf.warmup(model, device)
    res["compile_s"]["warp cold (every query's kernels)"] = time.perf_counter() - t
    code = (f"import sys;sys.path.insert(0,{str(ROOT / 'benchmarks')!r});import _bootstrap;"
            "import time,warp as wp,neurogf_warp as ngf;wp.config.log_level=wp.LOG_WARNING;wp.init();"
            f"m=ngf.load({str(ckpt)!r});t=time.perf_counter();ngf.warmup(m,{device!r});"
            "print(time.perf_counter()-t)")
    if a.network == "released":
        try:
            out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                                 env={**os.environ, "WARP_CACHE_PATH": cold_cache})
            res["compile_s"]["warp from the kernel cache, new process"] = float(out.stdout.strip().splitlines()[-1])
        except (subprocess.SubprocessError, ValueError, IndexError):
            pass

    timer = Timer(device, a.repeats)
    torch_forms = TorchForms(model, device, [] if (quick or a.no_compile) else ["max-autotune-no-cudagraphs"])
    rng = np.random.default_rng(a.seed)
    mesh = model.mesh
    xv = torch.from_numpy(mesh.normalize(mesh.internal_vertices)).to(tdev)
    scale = model.scale
    net64 = torch_forms.net(torch.float64)

    def dist_build(net, dtype):
        def fn(xs, xv):
            es = net.embed(xs)
            ev = net.embed(xv)
            return net.distance_from_embeddings(es.expand(len(xv), -1), ev, xs.expand(len(xv), 3), xv) / scale
        return fn

    def dist_cached_build(net, dtype):
        with torch.no_grad():
            ev_c = net.embed(xv.to(dtype))

        def fn(xs, xv):
            es = net.embed(xs)
            return net.distance_from_embeddings(es.expand(len(xv), -1), ev_c, xs.expand(len(xv), 3), xv) / scale
        return fn

    from neurogf_warp.inference.state import query_state
    from neurogf_warp.kernels.inference import tensorcore as tc

    def tuned(label, fn, settings):
        """Warp variants of one query under other tile settings (--tune): {name: callable}. Each variant runs
        with the model's state retuned (a new engine: its first call records launches again, as any first call)."""
        out = {label: fn}
        if not a.tune or not cuda:
            return out
        state = query_state(model, device)
        for setting in settings:
            def run(setting=setting):
                if state.tuning != tc.Tuning(**setting):
                    state.retune(tc.Tuning(**setting))
                return fn()
            out[f"{label} [{', '.join(f'{k}={v}' for k, v in setting.items())}]"] = run
        base = out[label]

        def default():
            if state.tuning != tc.Tuning():
                state.retune(tc.Tuning())
            return base()
        out[label] = default
        return out

    def add(query, variants, ref, flops, bytes_, extra=None):
        """ref: float64 result on the mesh's internal vertices or the query's rows; Warp's per-vertex results
        (the file's numbering) are compared through mesh.index."""
        rows = []
        for name, fn in variants.items():
            try:
                out = fn()
                if isinstance(out, wp.array):
                    got = out.numpy()
                elif isinstance(out, torch.Tensor):
                    got = out.detach().float().cpu().numpy()
                else:
                    got = np.asarray(out)
                if got.shape != ref.shape and got.shape[-1] == mesh.n_input:
                    got = got[..., mesh.index]
                err = rel_err(got, ref)
                s = timer(fn)
                rows.append({"query": query, "variant": name, "ms": s * 1e3, "rel_err": err})
                if name.startswith("warp"):
                    rows[-1]["device_ms"] = timer.device(fn) * 1e3
            except Exception as e:  # a variant that fails (e.g. out of memory) is reported, not fatal
                rows.append({"query": query, "variant": name, "error": f"{type(e).__name__}: {e}"[:300]})
            print(f"  {query}: {name}: " + (f"{rows[-1]['ms']:.4f} ms (device {rows[-1].get('device_ms', float('nan')):.4f}), "
                                            f"err {rows[-1]['rel_err']:.1e}" if "ms" in rows[-1] else rows[-1]["error"]),
                  flush=True)
        # the fastest PyTorch variant whatever its error (fp16 forms can be far less accurate; see rel_err)
        torch_best = min((r["ms"] for r in rows if "ms" in r and r["variant"].startswith("torch")), default=float("nan"))
        floor = max(flops / ceil["fp16_flops"], bytes_ / ceil["bandwidth"]) * 1e3
        for r in rows:
            if "ms" in r:
                r["vs_best_torch"] = torch_best / r["ms"]
                r["floor_ms"] = floor
                r["roofline_fraction"] = floor / r["ms"]
            r["flops"], r["bytes"] = flops, bytes_
            r.update(extra or {})
        res["rows"].extend(rows)
        if cuda:
            torch.cuda.empty_cache()

    warp_out = "warp" if not a.torch_out else "torch"
    # Warp distance queries run with raw=True: the references are the network's own values (float64 torch), and
    # the finishing rule (the straight-line bound, 0 at the source) costs the same either way
    src = int(mesh.index[rng.integers(len(mesh.internal_vertices))])
    src_pt = mesh.internal_vertices[mesh.vertex(src)]
    xs = torch.from_numpy(mesh.normalize(src_pt)[None]).to(tdev)
    with torch.no_grad():
        ref = dist_build(net64, torch.float64)(xs, xv).cpu().numpy()

    want = set(a.queries.split(","))
    lo, hi = mesh.internal_vertices.min(0), mesh.internal_vertices.max(0)
    # SSAD, model bound to its mesh
    res["memory"] = bind_memory(ngf, model, src, device)
    bytes_kept = ngf.bind(model, device)
    res["memory"]["bound vertex embeddings (bytes)"] = bytes_kept
    n = len(mesh.internal_vertices)
    v1 = tuned("warp ssad, bound (fp16 tensor cores)" if cuda else "warp ssad, bound",
               lambda: ngf.ssad(model, src, device=device, output=warp_out, raw=True),
               [{"ssad": (1, False)}, {"ssad": (1, True)}, {"warps_ssad": 12}, {"warps_ssad": 24}])
    if cuda:
        v1["warp ssad, bound, precision=fp32"] = lambda: ngf.ssad(model, src, device=device, output=warp_out,
                                                                    precision="fp32", raw=True)
    if "ssad_bound" in want:
        v1.update(torch_forms.variants("ssad bound", dist_build, {"xs": xs, "xv": xv}, dist_cached_build))
        add("ssad bound", v1, ref, 2 * M["head"] * n, n * (2 * 256 + 12 + 4))

    # SSAD cold, source given as a point
    model.unbind()
    pt = src_pt + 1e-3 * mesh.internal_vertices.std()
    xs_pt = torch.from_numpy(mesh.normalize(pt)[None]).to(tdev)
    with torch.no_grad():
        ref_pt = dist_build(net64, torch.float64)(xs_pt, xv).cpu().numpy()
    v2 = tuned("warp ssad, cold, point source", lambda: ngf.ssad(model, pt, device=device, output=warp_out, cache=False,
                                                             raw=True),
               [{"lift_ssad": (1, 4)}, {"warps_lift_ssad": 12}, {"warps_lift_ssad": 24}])
    if "ssad_cold" in want:
        v2.update(torch_forms.variants("ssad cold", dist_build, {"xs": xs_pt, "xv": xv}))
        add("ssad cold (point source)", v2, ref_pt, 2 * (M["lift"] + M["head"]) * n, n * 16)

    # MSAD with 8 sources (bound)
    ngf.bind(model, device)
    srcs = mesh.index[rng.choice(n, sizes["S_msad"], replace=False)]
    xss = torch.from_numpy(mesh.normalize(mesh.internal_vertices[mesh.vertex(srcs)])).to(tdev)

    def sources_build(reduce_min: bool, cached: bool, chunk: int = 8):
        """S sources at once, `chunk` at a time: |e_s - e_v| as an (chunk, V, D) batch through the head."""
        def build(net, dtype):
            ev_c = None
            if cached:
                with torch.no_grad():
                    ev_c = net.embed(xv.to(dtype))

            def fn(xss, xv):
                ev = ev_c if cached else net.embed(xv)
                es = net.embed(xss)
                outs = []
                for i in range(0, len(xss), chunk):
                    e, x = es[i:i + chunk], xss[i:i + chunk]
                    h = net.gdf_head((e[:, None, :] - ev[None]).abs().reshape(-1, ev.shape[1])).view(len(e), -1)
                    if net.euclid:
                        h = h + torch.linalg.vector_norm(x[:, None, :] - xv[None], dim=-1)
                    outs.append(h)
                d = torch.cat(outs) / scale
                return d.min(0).values if reduce_min else d
            return fn
        return build

    if "msad" in want:
        with torch.no_grad():
            ref_m = sources_build(True, False, 1)(net64, torch.float64)(xss, xv).cpu().numpy()
        v3 = tuned("warp msad, bound", lambda: ngf.msad(model, srcs, device=device, output=warp_out, raw=True),
                   [{"source_group": 1}, {"warps_distance": 8}, {"warps_distance": 12}])
        v3.update(torch_forms.variants("msad", sources_build(True, False), {"xss": xss, "xv": xv},
                                       sources_build(True, True)))
        add(f"msad {sizes['S_msad']} sources (bound)", v3, ref_m, 2 * M["head"] * n * sizes["S_msad"],
            n * (2 * 256 + 16))

    # distance matrix: S sources x every vertex (bound)
    S = sizes["S_matrix"]
    srcm = mesh.index[rng.choice(n, S, replace=False)]
    xsm = torch.from_numpy(mesh.normalize(mesh.internal_vertices[mesh.vertex(srcm)])).to(tdev)

    if "matrix" in want:
        with torch.no_grad():
            refS = sources_build(False, False, 1)(net64, torch.float64)(xsm, xv).cpu().numpy()
        v4 = tuned(f"warp distance_matrix ({S}, V), bound",
                   lambda: ngf.distance_matrix(model, srcm, device=device, output=warp_out, raw=True),
                   [{"warps_distance": 8}])
        tv = torch_forms.variants("matrix", sources_build(False, True), {"xss": xsm, "xv": xv})
        v4.update({f"{k}, cached e(x)": fn for k, fn in tv.items()})
        add(f"distance matrix {S} x V (bound)", v4, refS, 2 * M["head"] * n * S, n * (2 * 256 + 12) + 4 * S * n,
            {"pairs": S * n})
    model.unbind()

    # point-pair distances
    if "distance" in want:
        N = sizes["pairs"]
        P = rng.uniform(lo, hi, (N, 3)).astype(np.float32)
        Q = rng.uniform(lo, hi, (N, 3)).astype(np.float32)
        Pt, Qt = torch.from_numpy(P).to(tdev), torch.from_numpy(Q).to(tdev)
        Pn = torch.from_numpy(mesh.normalize(P)).to(tdev)
        Qn = torch.from_numpy(mesh.normalize(Q)).to(tdev)

        def pair_build(net, dtype):
            return lambda p, q: net.distance(p, q) / scale

        with torch.no_grad():
            ref_pairs = torch.cat([pair_build(net64, None)(Pn[i:i + 262144], Qn[i:i + 262144])
                                   for i in range(0, N, 262144)]).cpu().numpy()
        v5 = tuned("warp distance", lambda: ngf.distance(model, Pt, Qt, device=device, raw=True), [])
        v5.update(tuned("warp distance, check=False",
                        lambda: ngf.distance(model, Pt, Qt, device=device, raw=True, check=False),
                        [{"pair_nc": 4}, {"warps_pairs": 12}]))
        v5.update(torch_forms.variants("distance", pair_build, {"p": Pn, "q": Qn}))
        add(f"distance {N} pairs", v5, ref_pairs, 2 * (2 * M["lift"] + M["head"]) * N, 28 * N, {"pairs": N})
        del Pt, Qt, Pn, Qn


    # SDF
    if "sdf" in want:
        N = sizes["sdf"]
        X = rng.uniform(lo, hi, (N, 3)).astype(np.float32)
        Xt, Xn = torch.from_numpy(X).to(tdev), torch.from_numpy(mesh.normalize(X)).to(tdev)

        def sdf_build(net, dtype):
            return lambda x: net.sdf(x) / scale

        with torch.no_grad():
            ref_sdf = sdf_build(net64, None)(Xn).cpu().numpy()
        v6 = tuned("warp sdf", lambda: ngf.sdf(model, Xt, device=device), [])
        v6.update(tuned("warp sdf, check=False", lambda: ngf.sdf(model, Xt, device=device, check=False),
                        [{"sdf_tile": (1, 8)}, {"sdf_tile": (2, 2)}, {"warps_sdf": 8}]))
        v6.update(torch_forms.variants("sdf", sdf_build, {"x": Xn}))
        add(f"sdf {N} points", v6, ref_sdf, 2 * (M["lift"] + M["head"]) * N, 16 * N)
        del Xt, Xn


    # paths (the path head)
    if "path" in want:
        N, m = sizes["paths"], sizes["m"]
        vi = rng.integers(0, n, (N, 2))
        P, Q = mesh.internal_vertices[vi[:, 0]].astype(np.float32), mesh.internal_vertices[vi[:, 1]].astype(np.float32)
        Pt, Qt = torch.from_numpy(P).to(tdev), torch.from_numpy(Q).to(tdev)
        Pn, Qn = torch.from_numpy(mesh.normalize(P)).to(tdev), torch.from_numpy(mesh.normalize(Q)).to(tdev)
        center = torch.from_numpy(model.center).to(tdev)

        def path_build(net, dtype):
            c = center.to(dtype)
            return lambda p, q: net.path(p, q, m) / scale + c

        with torch.no_grad():
            ref_path = path_build(net64, torch.float64)(Pn, Qn).cpu().numpy()
        # the path head's own points (project=None), what the PyTorch variants compute (the default also snaps
        # every point onto the mesh)
        v7 = {"warp path": lambda: ngf.path(model, Pt, Qt, m=m, device=device, project=None),
              "warp path, check=False": lambda: ngf.path(model, Pt, Qt, m=m, device=device, check=False,
                                                        project=None)}
        v7.update(torch_forms.variants("path", path_build, {"p": Pn, "q": Qn}))
        add(f"path {N} pairs x {m} points", v7, ref_path, 2 * (M["per_path"] + m * M["point"]) * N, (24 + 12 * m) * N)


    # path refinement (no PyTorch form exists): time at --size refine_pairs, agreement with the fp32 method
    if "refine" in want:
        N, m, sweeps = sizes["refine_pairs"], sizes["m"], sizes["refine"]
        vi = rng.integers(0, n, (N, 2))
        P = wp.array(mesh.internal_vertices[vi[:, 0]].astype(np.float32), dtype=wp.vec3, device=device)
        Q = wp.array(mesh.internal_vertices[vi[:, 1]].astype(np.float32), dtype=wp.vec3, device=device)
        run16 = lambda: ngf.path(model, P, Q, m=m, refine=sweeps, device=device)
        out16 = run16().numpy()
        t16 = Timer(device, 2, 3)(run16)
        k = min(sizes["refine_check"], N)
        t = time.perf_counter()
        out32 = ngf.path(model, P[:k], Q[:k], m=m, refine=sweeps, device=device, precision="fp32").numpy()
        wp.synchronize()
        t32 = (time.perf_counter() - t) * N / k
        length = lambda x: np.linalg.norm(np.diff(x, axis=1), axis=2).sum(1)
        from neurogf_warp.evaluation.metrics import chamfer_l1

        cd = chamfer_l1(mesh.normalize(out16[:k].reshape(-1, 3)).reshape(k, m, 3),
                        mesh.normalize(out32.reshape(-1, 3)).reshape(k, m, 3))
        sdf_res = np.abs(ngf.sdf(model, out16[:, 1:-1].reshape(-1, 3), device=device, precision="fp32")) * mesh.scale
        label = "fp16" if cuda else "fp32 (the CPU's precision)"
        row = {"query": f"path refine={sweeps}, {N} pairs x {m} points", "variant": f"warp path(refine) {label}",
               "ms": t16 * 1e3, "fp32_ms_scaled": t32 * 1e3,
               "length_rel_diff_vs_fp32": float(np.mean(np.abs(length(out16[:k]) - length(out32)) / length(out32))),
               "chamfer_vs_fp32": float(cd.mean()), "surface_residual_max": float(sdf_res.max()),
               "surface_residual_mean": float(sdf_res.mean()), "sdf_evaluations": 4 * 3 * N * sum(
                   mm * (sweeps + (2 if i == 0 else 2)) for i, mm in enumerate(_levels_of(m))) + 4 * 3 * N * m * 4}
        res["rows"].append(row)
        print(f"  refine: {label} {t16 * 1e3:.1f} ms for {N} pairs; fp32 {t32 * 1e3:.0f} ms (scaled from {k}); length "
              f"diff {row['length_rel_diff_vs_fp32']:.2e}, Chamfer vs fp32 {row['chamfer_vs_fp32']:.2e}, surface "
              f"residual max {row['surface_residual_max']:.1e} (normalized)", flush=True)

    # the heat method (potpourri3d, CPU) on the same mesh, for completeness: a different method with ~1% MRE
    if "heat" in want:
        try:
            import potpourri3d as pp3d

            t = time.perf_counter()
            solver = pp3d.MeshHeatMethodDistanceSolver(mesh.internal_vertices, mesh.internal_faces.astype(np.int64))
            setup = time.perf_counter() - t
            t = time.perf_counter()
            solver.compute_distance(int(mesh.vertex(src)))
            res["heat"] = {"setup_s": setup, "ssad_ms": (time.perf_counter() - t) * 1e3}
            print(f"  heat method (potpourri3d, CPU): setup {setup:.2f} s, one SSAD {res['heat']['ssad_ms']:.1f} ms",
                  flush=True)
        except ImportError:
            res["heat"] = {"error": "potpourri3d not installed"}

    res["compile_s"].update(torch_forms.compile_s)
    if not a.no_mre:
        res["released_mre"] = released_mre(device, cuda)
    return res


def released_mre(device: str, cuda: bool) -> dict:
    """MRE of the released checkpoints against the exact references, per precision (fp16 on CUDA only)."""
    precs = ("fp16", "fp32") if cuda else ("fp32",)
    rows = _released_rows(device, {"bunny": precs, "fandisk": precs})
    return {f"{r['mesh']} {r['precision']}": r["mre"] for r in rows}


def table(res: dict) -> str:
    lines = [f"{res['device_name']} ({res['device']}), {res['date']}, Warp {res['warp']}, "
             f"torch {res['torch']}; ceilings: fp16 {res['ceilings']['fp16_flops'] / 1e12:.0f} TFLOP/s, "
             f"copy {res['ceilings']['bandwidth'] / 1e12:.2f} TB/s",
             f"{'query':34s} {'variant':52s} {'ms/call':>9s} {'device ms':>9s} {'vs best torch':>13s} {'floor ms':>9s} "
             f"{'roofline':>8s} {'rel err':>8s}"]
    for r in res["rows"]:
        if "fp32_ms_scaled" in r:
            lines.append(f"{r['query'][:34]:34s} {r['variant'][:52]:52s} {r['ms']:9.1f} (fp32 method {r['fp32_ms_scaled']:.0f}"
                         f" ms; lengths within {r['length_rel_diff_vs_fp32']:.1e}, Chamfer to it "
                         f"{r['chamfer_vs_fp32']:.1e}, on-surface max {r['surface_residual_max']:.1e})")
            continue
        if "ms" in r:
            dev_ms = f"{r['device_ms']:9.4f}" if "device_ms" in r else " " * 9
            lines.append(f"{r['query'][:34]:34s} {r['variant'][:52]:52s} {r['ms']:9.4f} {dev_ms} "
                         f"{r['vs_best_torch']:12.2f}x {r['floor_ms']:9.4f} {r['roofline_fraction']:8.1%} "
                         f"{r['rel_err']:8.1e}")
        else:
            lines.append(f"{r['query'][:34]:34s} {r['variant'][:52]:52s} {r['error'][:60]}")
    for k, v in res["compile_s"].items():
        lines.append(f"compile: {k}: {v:.2f} s")
    for k, v in res.get("released_mre", {}).items():
        lines.append(f"released checkpoint MRE vs exact: {k}: {v:.4%}")
    if "ssad_ms" in res.get("heat", {}):
        lines.append(f"heat method (potpourri3d, CPU) on the same mesh: setup {res['heat']['setup_s']:.2f} s, one SSAD "
                     f"{res['heat']['ssad_ms']:.1f} ms")
    for k, v in res.get("memory", {}).items():
        lines.append(f"memory: {k}: {v / 1e6:.1f} MB")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cuda:0" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--quick", action="store_true", help="small sizes (the default on the CPU)")
    ap.add_argument("--size", action="append", default=[], metavar="KEY=N",
                    help="override a size: V, S_msad, S_matrix, pairs, sdf, paths, m")
    ap.add_argument("--repeats", type=int, default=20, help="calls per timed batch (5 batches, median)")
    ap.add_argument("--network", choices=("released", "default"), default="released",
                    help="released: the bunny checkpoint; default: the default trained layout (Fourier inputs, "
                         "|p - q| term, windowed residual paths) with random first-layer weights")
    ap.add_argument("--no-compile", action="store_true", help="skip the torch.compile variants")
    ap.add_argument("--no-mre", action="store_true", help="skip the released checkpoints' MRE")
    ap.add_argument("--torch-out", action="store_true", help="Warp results as torch tensors instead of wp.arrays")
    ap.add_argument("--queries", default="ssad_bound,ssad_cold,msad,matrix,distance,sdf,path,refine,heat",
                    help="comma-separated subset of ssad_bound, ssad_cold, msad, matrix, distance, sdf, path, refine, "
                         "heat")
    ap.add_argument("--tune", action="store_true", help="also time the Warp queries under other tile settings")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default=None, help="output JSON (default: $OUT/queries.json, else ./queries.json)")
    a = ap.parse_args(argv)
    res = run(a)
    text = table(res)
    out = write_json(a.json or os.path.join(os.environ.get("OUT", "."), "queries.json"), res, "queries", a.device)
    print("\n" + text + f"\nJSON: {out}")
    bad = [r for r in res["rows"] if "rel_err" in r and r["variant"].startswith("warp") and not r["rel_err"] <= 1e-3]
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
