"""Ctrl-C within seconds on the remaining long CPU work: paths (head, refined, projected, snapped), closest mesh
points and the generalizable model's distance queries run in chunks of rows on the CPU; the answers are the same
bits as one launch, and a SIGINT raises KeyboardInterrupt between two chunks."""
import numpy as np
import pytest

from neurogf_warp.common import chunks
from neurogf_warp.inference import backends, paths

from .conftest import shared_path
from .test_interrupt import signal_on


@pytest.fixture(scope="module")
def fandisk():
    import neurogf_warp as ngf

    return ngf.load(shared_path("checkpoints", "official", "NeuroGF_Pretrainer__fandisk_final.pth"),
                    mesh=shared_path("meshes", "fandisk.obj"))


def _ends(model, n, seed):
    rng = np.random.default_rng(seed)
    V = model.mesh.vertices
    return V[rng.integers(0, len(V), n)], V[rng.integers(0, len(V), n)]


def _chunks_of(monkeypatch, size, where=(paths, backends, chunks)):
    """Every CPU chunk of rows exactly ``size`` rows (the last one less); returns the list of (lo, hi) run."""
    real = chunks.in_chunks
    seen = []
    monkeypatch.setattr(chunks, "CPU_MAX_CHUNK", size)
    monkeypatch.setattr(chunks, "CPU_CHUNK_SECONDS", 1e9)  # never shrink below it

    def fixed(device, n, run, first=None, align=1):
        def counted(lo, hi):
            seen.append((lo, hi))
            return run(lo, hi)
        return real(device, n, counted, first=size, align=1)

    for mod in where:
        monkeypatch.setattr(mod, "in_chunks", fixed)
    return seen


def _same(a, b):
    a, b = np.asarray(a), np.asarray(b)
    assert a.dtype == b.dtype and a.shape == b.shape
    assert ((a == b) | (np.isnan(a) & np.isnan(b))).all()


@pytest.mark.parametrize("kw", [dict(project=None), dict(), dict(return_faces=True), dict(refine=1, m=16),
                                dict(project="sdf", m=8)], ids=["head", "mesh", "faces", "refined", "sdf"])
def test_chunked_paths_are_the_single_launch_bits(fandisk, monkeypatch, kw):
    import neurogf_warp as ngf

    n = 24 if kw.get("refine") else 60
    p, q = _ends(fandisk, n, 3)
    q[:2] = p[:2]  # p == q rows too
    kw = dict({"m": 32}, **kw)
    one = ngf.path(fandisk, p, q, device="cpu", precision="fp32", **kw)
    with monkeypatch.context() as mp:
        seen = _chunks_of(mp, 7)
        many = ngf.path(fandisk, p, q, device="cpu", precision="fp32", **kw)
    assert len([s for s in seen if s[1] - s[0] <= 7]) >= n // 7  # the pairs ran in chunks of 7
    for a, b in zip(one if isinstance(one, tuple) else (one,), many if isinstance(many, tuple) else (many,)):
        _same(a, b)


def test_snap_to_mesh_in_chunks_gives_the_same_bits(fandisk, monkeypatch):
    from neurogf_warp.mesh.surface import snap_to_mesh

    x = fandisk.mesh.vertices[:500] + 0.01
    one = snap_to_mesh(fandisk, x, device="cpu")
    seen = _chunks_of(monkeypatch, 64)
    many = snap_to_mesh(fandisk, x, device="cpu")
    assert len(seen) == 8
    for a, b in zip(one, many):
        _same(a, b)


def test_sigint_stops_a_long_path_query_between_chunks(fandisk, monkeypatch, ctrl_c_raises):
    """A SIGINT sent while chunk 3 of 30 runs ends ngf.path after at most a few more chunks."""
    import neurogf_warp as ngf

    p, q = _ends(fandisk, 30 * 8, 4)
    seen = _chunks_of(monkeypatch, 8)
    be = backends.backend_of(__import__("neurogf_warp.inference.state", fromlist=["x"]).query_state(fandisk, "cpu"),
                             "fp32")
    inner = be.paths
    third, sent, sent_at = signal_on(seen)

    def signalling(*a, **k):
        if len(seen) == 3:
            third.set()
            sent.wait(30)  # the chunk runs once the signal is out, whatever the machine's load
        return inner(*a, **k)

    monkeypatch.setattr(be, "paths", signalling)
    with pytest.raises(KeyboardInterrupt):
        ngf.path(fandisk, p, q, m=16, project=None, device="cpu", precision="fp32")
    assert sent_at and len(seen) - sent_at[0] <= 1, f"{len(seen)} of 30 chunks ran, the signal sent at {sent_at}"


# ---- the generalizable model's queries -----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def conditioned():
    from neurogf_warp.generalizable.model import load

    g = np.random.default_rng(5).standard_normal((256, 3))
    cloud = g / np.linalg.norm(g, axis=1, keepdims=True) * np.array([1.5, 1.0, 0.6])
    return load(shared_path("checkpoints", "official", "GenNeuroGF.pth")).condition(cloud, device="cpu")


def test_generalizable_queries_in_chunks_give_the_same_bits(conditioned, monkeypatch):
    from neurogf_warp.generalizable import encoder

    rng = np.random.default_rng(6)
    p, q = conditioned.points[rng.integers(0, 256, 300)], conditioned.points[rng.integers(0, 256, 300)]
    src = [0, 5, 17, 100, 200, 3, 9]

    def run():
        return (conditioned.distance(p, q), conditioned.distance_matrix(src), conditioned.distance_matrix(src, p),
                conditioned.msad(src))

    one = run()
    monkeypatch.setattr(encoder, "PAIR_CHUNK", 50)
    seen = _chunks_of(monkeypatch, 2, where=(chunks,))
    many = run()
    assert len(seen) >= 150 + 4 + 4  # 300 pairs by 2, 7 sources by 2 (twice), msad
    for a, b in zip(one, many):
        _same(a, b)


def test_sigint_stops_a_long_generalizable_query(conditioned, monkeypatch, ctrl_c_raises):
    from neurogf_warp.generalizable import encoder

    monkeypatch.setattr(encoder, "PAIR_CHUNK", 50)
    seen = _chunks_of(monkeypatch, 4, where=(chunks,))
    third, sent, sent_at = signal_on(seen)
    real = chunks.in_chunks

    def watching(device, n, run, first=None, align=1):
        def r(lo, hi):
            if len(seen) == 3:
                third.set()
                sent.wait(30)  # the chunk runs once the signal is out, whatever the machine's load
            return run(lo, hi)
        return real(device, n, r, first, align)

    monkeypatch.setattr(chunks, "in_chunks", watching)
    p = conditioned.points[np.arange(4 * 40) % 256]
    with pytest.raises(KeyboardInterrupt):
        conditioned.distance(p, p[::-1].copy())
    assert sent_at and len(seen) - sent_at[0] <= 1, f"{len(seen)} of 40 chunks ran, the signal sent at {sent_at}"


def test_project_and_surface_fit_in_chunks_give_the_same_bits(fandisk, monkeypatch):
    import neurogf_warp as ngf
    from neurogf_warp.inference.paths import project, surface_fit

    x = fandisk.mesh.vertices[:300] + 0.02
    p, q = _ends(fandisk, 40, 8)
    pts = ngf.path(fandisk, p, q, m=16, device="cpu", precision="fp32")
    one = (project(fandisk, x, device="cpu"), *surface_fit(fandisk, pts, device="cpu", precision="fp32"))
    seen = _chunks_of(monkeypatch, 16)
    many = (project(fandisk, x, device="cpu"), *surface_fit(fandisk, pts, device="cpu", precision="fp32"))
    assert len(seen) >= 300 // 16 + 40 // 16
    for a, b in zip(one, many):
        _same(a, b)
