"""Ctrl-C within seconds on long CPU queries: large launches run in chunks (``chunks.in_chunks``), the answers
are the same bits as one launch, and a SIGINT raises KeyboardInterrupt between two chunks instead of after the
whole query."""
import _thread
import threading

import numpy as np
import pytest

from neurogf_warp.common import chunks
from neurogf_warp.inference import backends

from .conftest import shared_path


@pytest.fixture(scope="module")
def fandisk():
    import neurogf_warp as ngf

    path = shared_path("checkpoints", "official", "NeuroGF_Pretrainer__fandisk_final.pth")
    return ngf.load(path, mesh=shared_path("meshes", "fandisk.obj"))


def _points(model, n, seed=0):
    rng = np.random.default_rng(seed)
    V = model.mesh.vertices
    return V[rng.integers(0, len(V), n)] + 1e-3 * rng.standard_normal((n, 3))


def signal_on(seen):
    """A thread that sends SIGINT (``_thread.interrupt_main``, as from a terminal) once the caller sets the first
    event: (that event, the event set once the signal is out, [len(seen) when it went out]). Counting from the
    signal, not from the event, keeps the check free of thread scheduling under load."""
    third, sent, sent_at = threading.Event(), threading.Event(), []

    def send():
        if third.wait(120):
            sent_at.append(len(seen))
            _thread.interrupt_main()
            sent.set()

    threading.Thread(target=send, daemon=True).start()
    return third, sent, sent_at


def _fixed_chunks(monkeypatch, size):
    """Every CPU chunk ``size`` rows (no growing or shrinking with the clock)."""
    monkeypatch.setattr(chunks, "CPU_FIRST_CHUNK", size)
    monkeypatch.setattr(chunks, "CPU_CHUNK_ALIGN", size)
    monkeypatch.setattr(chunks, "CPU_MAX_CHUNK", size)


def _counting(monkeypatch, model, precision, method):
    """Count the calls of the CPU backend's ``method`` (one per chunk)."""
    from neurogf_warp.inference.state import query_state

    be = backends.backend_of(query_state(model, "cpu"), precision)
    calls = []
    inner = getattr(be, method)

    def wrapped(*a, **k):
        calls.append(1)
        return inner(*a, **k)

    monkeypatch.setattr(be, method, wrapped)
    return calls


def test_in_chunks_covers_every_row_once(monkeypatch):
    """Consecutive, non-overlapping ranges over [0, n), sized from the previous chunk's time."""
    monkeypatch.setattr(chunks, "CPU_CHUNK_SECONDS", 1e-9)  # every chunk 'too slow': sizes shrink to the floor
    seen = []
    n = chunks.in_chunks("cpu", 1000, lambda lo, hi: seen.append((lo, hi)), first=300, align=7)
    assert n == len(seen) > 3
    assert seen[0] == (0, 300) and seen[-1][1] == 1000
    assert all(a[1] == b[0] for a, b in zip(seen, seen[1:]))
    sizes = [hi - lo for lo, hi in seen]
    assert sizes[:4] == [300, 70, 14, 7] and set(sizes[4:-1]) == {7}  # at most 4x smaller a step, aligned, floor
    assert chunks.in_chunks("cpu", 0, lambda lo, hi: seen.append("never")) == 0 and seen[-1] != "never"


@pytest.mark.parametrize("precision", ["fp32", "fp16"])
def test_chunked_answers_are_the_single_launch_bits(fandisk, monkeypatch, precision):
    """sdf, distance, msad and a distance matrix: many small chunks give exactly one big launch's answers."""
    import neurogf_warp as ngf

    n = 300 if precision == "fp16" else 1200  # the fp16 kernels are a slow emulation on the CPU
    p, q = _points(fandisk, n, 1), _points(fandisk, n, 2)
    srcs = [0, 17, 400, 4000, 5]
    kw = dict(device="cpu", precision=precision)

    def run():
        return (ngf.sdf(fandisk, p, **kw), ngf.distance(fandisk, p, q, **kw), ngf.msad(fandisk, srcs, **kw),
                ngf.distance_matrix(fandisk, srcs, **kw), ngf.ssad(fandisk, 9, cache=False, **kw),
                ngf.embed(fandisk, p, device="cpu").numpy())

    _fixed_chunks(monkeypatch, 1 << 22)
    one = run()
    _fixed_chunks(monkeypatch, 256)
    calls = _counting(monkeypatch, fandisk, precision, "vertex_distances")
    pairs = _counting(monkeypatch, fandisk, precision, "pairs")
    many = run()
    assert len(pairs) == -(-n // 256) and len(calls) >= 4  # msad and the matrix: two chunks of sources or more
    for a, b in zip(one, many):
        assert a.dtype == b.dtype and a.shape == b.shape
        assert ((a == b) | (np.isnan(a) & np.isnan(b))).all()
    fandisk.unbind()


@pytest.mark.parametrize("query", ["sdf", "distance"])
def test_sigint_stops_a_long_cpu_query_between_chunks(fandisk, monkeypatch, ctrl_c_raises, query):
    """A SIGINT sent (from another thread) while chunk 3 of 40 runs ends the query after at most a few chunks."""
    import neurogf_warp as ngf

    total = 40
    _fixed_chunks(monkeypatch, 256)
    x = _points(fandisk, 256 * total)
    calls = _counting(monkeypatch, fandisk, "fp32", "sdf" if query == "sdf" else "pairs")
    third, sent, sent_at = signal_on(calls)

    from neurogf_warp.inference.state import query_state

    be = backends.backend_of(query_state(fandisk, "cpu"), "fp32")
    name = "sdf" if query == "sdf" else "pairs"
    counted = getattr(be, name)

    def signalling(*a, **k):
        if len(calls) == 2:
            third.set()
            sent.wait(30)  # chunk 3 runs once the signal is out, whatever the machine's load
        return counted(*a, **k)

    monkeypatch.setattr(be, name, signalling)
    with pytest.raises(KeyboardInterrupt):
        if query == "sdf":
            ngf.sdf(fandisk, x, device="cpu", precision="fp32")
        else:
            ngf.distance(fandisk, x, x[::-1].copy(), device="cpu", precision="fp32")
    assert sent_at and len(calls) - sent_at[0] <= 1, f"{len(calls)} of {total} chunks ran, the signal sent at {sent_at}"


# ---- generalizable conditioning (N^2 neighbour searches) -----------------------------------------------------------

@pytest.fixture(scope="module")
def gen_model():
    from neurogf_warp.generalizable.model import load

    return load(shared_path("checkpoints", "official", "GenNeuroGF.pth"))


def _cloud(n, seed=5):
    g = np.random.default_rng(seed).standard_normal((n, 3))
    return g / np.linalg.norm(g, axis=1, keepdims=True) * np.array([1.5, 1.0, 0.6])


def test_conditioning_in_chunks_gives_the_same_bits(gen_model, monkeypatch):
    pts = _cloud(500)
    _fixed_chunks(monkeypatch, 1 << 22)
    one = gen_model.condition(pts)
    _fixed_chunks(monkeypatch, 48)  # rows 0..47, 48..95, ...: not a divisor of 500
    many = gen_model.condition(pts)
    for a, b in ((one.enc.feats, many.enc.feats), (one.enc.fused, many.enc.fused)):
        assert (a.numpy() == b.numpy()).all()
    for a, b in zip(one.enc.neighbours, many.enc.neighbours):
        assert (a.numpy() == b.numpy()).all()
    np.testing.assert_array_equal(one.ssad(3), many.ssad(3))


def test_sigint_stops_conditioning_between_chunks(gen_model, monkeypatch, ctrl_c_raises):
    """Every row-wise launch of the CPU encoder runs in chunks; a SIGINT during the third chunk ends it there."""
    _fixed_chunks(monkeypatch, 32)
    pts = _cloud(1024)
    inner = chunks.in_chunks
    runs = []
    third, sent, sent_at = signal_on(runs)

    def counting(device, n, run, *a, **k):
        def counted(lo, hi):
            runs.append((lo, hi))
            if len(runs) == 3:
                third.set()
                sent.wait(30)  # this chunk runs once the signal is out, whatever the machine's load
            return run(lo, hi)
        return inner(device, n, counted, *a, **k)

    monkeypatch.setattr(chunks, "in_chunks", counting)
    total = 13 * (1024 // 32)  # 13 row-wise launches of 32 chunks each (linear layers, kNN, edge layers)
    with pytest.raises(KeyboardInterrupt):
        gen_model.condition(pts)
    assert sent_at and len(runs) - sent_at[0] <= 1, f"{len(runs)} of {total}+ chunks ran, the signal sent at {sent_at}"
