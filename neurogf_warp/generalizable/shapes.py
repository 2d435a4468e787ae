"""A deterministic collection of shapes to train and test generalizable geodesic networks on.

    from neurogf_warp.generalizable import shapes
    V, F, info = shapes.make_shape(17)                  # shape number 17 of the collection (seed 0)
    shapes.write_collection("coll/", n=600)              # coll/train/*.obj, coll/test/*.obj, coll/manifest.json

Shape i of a collection with seed s is fully determined by (s, i): its family is ``FAMILIES[i % len(FAMILIES)]``
and its random numbers come from ``np.random.default_rng([s, i])``. The split is by number too: shape i is the
``i // len(FAMILIES)``-th instance of its family and a test shape when that instance number is
``test_every - 1`` modulo ``test_every`` (default 10: 10% test, of every family alike), so test shapes are
unseen instances of the training families. (A first rule, ``i % test_every == test_every - 1``, put only 3 of the
6 families in the test split at test_every = 10, since 10 and 6 share the factor 2; ``manifest.json`` records the
rule as ``split``.)

Families (all closed, one connected component, 2K-10K vertices, in roughly unit size):
- ``blob``: an icosphere (2,562 vertices) displaced radially by a random smooth field, random anisotropic scale;
- ``torus``: a torus (random radii, 2.5K-3.5K vertices) with a smooth normal displacement;
- ``vase``: a surface of revolution of a random smooth radius profile r(z) > 0, closed at both poles, bent;
- ``rounded_box``: a superellipsoid (exponent 4-10: a box with rounded edges) of random proportions;
- ``capsules``: an articulated figure (torso, head, four limbs with random joint angles) as the smooth union of
  capsules, meshed by marching tetrahedra on a 40-56 cell grid;
- ``deformed``: a shared mesh (cow, homer, rocker-arm, cheburashka, alligator, igea; NOT stanford-bunny, fandisk,
  spot, which stay unseen for evaluation) simplified to 3K-8K vertices, randomly rotated, scaled and bent by a
  smooth sinusoidal displacement field. Needs a meshes folder given as ``shared_meshes=`` (``--shared-meshes``)
  with all six source files; without one this family is replaced by ``blob`` (``write_collection`` says so once),
  wherever the package is installed.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

FAMILIES = ("blob", "torus", "vase", "rounded_box", "capsules", "deformed")
DEFORM_SOURCES = ("cow.obj", "homer.obj", "rocker-arm.obj", "cheburashka.obj", "alligator.obj", "igea.ply")
HELD_OUT_MESHES = ("stanford-bunny.obj", "fandisk.obj", "spot.obj")


def _smooth_field(rng, x, n_waves=6, freq=(0.8, 2.5), amp=1.0):
    """A random smooth scalar field on points x (M, 3): a sum of random plane waves."""
    k = rng.standard_normal((n_waves, 3))
    k *= rng.uniform(*freq, (n_waves, 1)) / np.linalg.norm(k, axis=1, keepdims=True)
    ph = rng.uniform(0, 2 * np.pi, n_waves)
    a = rng.standard_normal(n_waves) / np.sqrt(n_waves)
    return amp * (np.sin(x @ k.T + ph) * a).sum(axis=1)


def _random_rotation(rng):
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q *= np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def _blob(rng):
    import trimesh

    tm = trimesh.creation.icosphere(subdivisions=4)
    u = tm.vertices
    r = np.exp(0.35 * _smooth_field(rng, u, 8, (0.8, 3.0)))
    return u * r[:, None] * rng.uniform(0.6, 1.4, 3), tm.faces


def _torus(rng):
    import trimesh

    R = rng.uniform(0.6, 1.0)
    r = rng.uniform(0.15, 0.4) * R
    tm = trimesh.creation.torus(R, r, major_sections=int(rng.integers(56, 80)), minor_sections=int(rng.integers(40, 48)))
    v = tm.vertices
    n = np.asarray(tm.vertex_normals)
    v = v + n * (0.35 * r * _smooth_field(rng, v, 6, (1.0, 3.0)))[:, None]
    return v * rng.uniform(0.7, 1.3, 3), tm.faces


def _vase(rng):
    nz, nt = int(rng.integers(50, 80)), int(rng.integers(48, 64))
    z = np.linspace(-1, 1, nz)
    prof = 0.35 + 0.2 * _smooth_field(rng, np.stack([z, 0 * z, 0 * z], 1), 4, (1.0, 4.0))
    prof = np.clip(prof, 0.08, None) * np.sqrt(np.clip(1 - z ** 2, 0, None) + 0.02)  # closes towards the poles
    t = np.linspace(0, 2 * np.pi, nt, endpoint=False)
    ring = np.stack([np.cos(t), np.sin(t)], 1)
    V = np.concatenate([[[0, 0, -1.02]], np.concatenate([np.c_[ring * p, np.full(nt, zz)] for zz, p in
                                                         zip(z[1:-1], prof[1:-1])]), [[0, 0, 1.02]]])
    F = []
    for a in range(nz - 3):
        for b in range(nt):
            i0, i1 = 1 + a * nt + b, 1 + a * nt + (b + 1) % nt
            j0, j1 = i0 + nt, i1 + nt
            F += [[i0, i1, j1], [i0, j1, j0]]
    last = 1 + (nz - 3) * nt
    for b in range(nt):
        F.append([0, 1 + (b + 1) % nt, 1 + b])
        F.append([len(V) - 1, last + b, last + (b + 1) % nt])
    V = np.asarray(V, float)
    bend = rng.uniform(-0.3, 0.3, 2)
    V[:, 0] += bend[0] * V[:, 2] ** 2
    V[:, 1] += bend[1] * V[:, 2] ** 2
    return V * np.r_[rng.uniform(0.7, 1.3, 2), rng.uniform(0.8, 1.2)], np.asarray(F)


def _rounded_box(rng):
    import trimesh

    tm = trimesh.creation.icosphere(subdivisions=4)
    u = tm.vertices / np.linalg.norm(tm.vertices, axis=1, keepdims=True)
    p = rng.uniform(4.0, 10.0)
    # radial projection of the unit sphere onto |x|^p + |y|^p + |z|^p = 1 keeps the triangulation valid
    s = (np.abs(u) ** p).sum(axis=1) ** (-1.0 / p)
    return u * s[:, None] * rng.uniform(0.4, 1.0, 3), tm.faces


def _capsule_sdf(x, segs):
    """Smooth union (polynomial smooth-min, k = 0.08) of capsules (a, b, radius)."""
    d = None
    for a, b, r in segs:
        ab = b - a
        h = np.clip(((x - a) @ ab) / (ab @ ab), 0, 1)
        di = np.linalg.norm(x - a - h[:, None] * ab, axis=1) - r
        if d is None:
            d = di
        else:
            k = 0.08
            hh = np.clip(0.5 + 0.5 * (di - d) / k, 0, 1)
            d = di * (1 - hh) + d * hh - k * hh * (1 - hh)
    return d


def _capsules(rng):
    def limb(root, direction, l1, l2, bend, r):
        d = direction / np.linalg.norm(direction)
        j = root + d * l1
        perp = np.cross(d, rng.standard_normal(3))
        perp /= np.linalg.norm(perp)
        e = j + (np.cos(bend) * d + np.sin(bend) * perp) * l2
        return [(root, j, r), (j, e, r * 0.85)]

    torso = rng.uniform(0.5, 0.8)
    rt = rng.uniform(0.14, 0.22)
    a, b = np.array([0, 0, -torso / 2]), np.array([0, 0, torso / 2])
    segs = [(a, b, rt), (b + [0, 0, 0.05], b + [0, 0, 0.05 + rng.uniform(0.15, 0.25)], rng.uniform(0.1, 0.16))]
    rl = rng.uniform(0.06, 0.1)
    for side in (-1, 1):
        arm_dir = np.array([side, 0, rng.uniform(-1.0, 0.5)]) + 0.3 * rng.standard_normal(3)
        segs += limb(b - [0, 0, 0.05], arm_dir, rng.uniform(0.25, 0.4), rng.uniform(0.2, 0.35),
                     rng.uniform(0, 1.2), rl)
        leg_dir = np.array([side * 0.3, 0, -1]) + 0.25 * rng.standard_normal(3)
        segs += limb(a + [side * 0.08, 0, 0], leg_dir, rng.uniform(0.3, 0.45), rng.uniform(0.25, 0.4),
                     rng.uniform(0, 0.9), rl * 1.2)
    pts = np.concatenate([[s[0], s[1]] for s in segs])
    lo, hi = pts.min(0) - 0.3, pts.max(0) + 0.3
    n = int(rng.integers(40, 57))
    h = (hi - lo).max() / n
    shape = np.ceil((hi - lo) / h).astype(int) + 1
    g = np.stack(np.meshgrid(*[lo[i] + h * np.arange(shape[i]) for i in range(3)], indexing="ij"), -1)
    f = _capsule_sdf(g.reshape(-1, 3), segs).reshape(shape)
    return marching_tetrahedra(f, lo, h)


# the 6 tetrahedra of a cube (corner c = (i, j, k) bits), all sharing the diagonal 0-7
_CUBE_TETS = np.array([[0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]])
_CORNERS = np.array([[(c >> 2) & 1, (c >> 1) & 1, c & 1] for c in range(8)])


def marching_tetrahedra(f: np.ndarray, origin, h: float):
    """Triangle mesh of the zero level set of grid values f (nx, ny, nz) (negative inside): vertices on grid
    edges, shared between neighbouring tetrahedra (so the surface is closed where it does not leave the grid),
    triangles oriented outward (towards increasing f)."""
    f = np.where(f == 0, 1e-12, f)  # no vertex exactly on the level set: every crossing is strictly inside an edge
    _, ny, nz = f.shape
    idx = np.arange(f.size).reshape(f.shape)
    base = idx[:-1, :-1, :-1].reshape(-1)
    offs = np.array([c[0] * ny * nz + c[1] * nz + c[2] for c in _CORNERS])
    tets = (base[:, None, None] + offs[_CUBE_TETS][None]).reshape(-1, 4)
    fv = f.reshape(-1)[tets]
    inside = fv < 0
    cnt = inside.sum(1)
    keep = (cnt > 0) & (cnt < 4)
    tets, fv, inside, cnt = tets[keep], fv[keep], inside[keep], cnt[keep]
    pos = lambda i: np.asarray(origin) + h * np.stack(np.unravel_index(i, f.shape), -1)
    tris, outdir = [], []

    def edge_keys(t, a, b):
        va, vb = t[np.arange(len(t)), a], t[np.arange(len(t)), b]
        return np.minimum(va, vb), np.maximum(va, vb)

    order = np.argsort(~inside, axis=1, kind="stable")  # inside corners first
    for c in (1, 2, 3):
        m = cnt == c
        t, o = tets[m], order[m]
        if c == 1 or c == 3:
            lone = o[:, 0] if c == 1 else o[:, 3]
            others = o[:, 1:] if c == 1 else o[:, :3]
            tri = [edge_keys(t, lone, others[:, q]) for q in range(3)]
            tris.append(np.stack([np.stack(k, 1) for k in tri], 1))
            sign = 1.0 if c == 1 else -1.0  # outward = away from the inside corner(s)
            pl = pos(t[np.arange(len(t)), lone])
            po = pos(t[np.arange(len(t))[:, None], others]).mean(1)
            outdir.append(sign * (po - pl))
        else:
            i0, i1, o0, o1 = o[:, 0], o[:, 1], o[:, 2], o[:, 3]
            e = [edge_keys(t, i0, o0), edge_keys(t, i0, o1), edge_keys(t, i1, o1), edge_keys(t, i1, o0)]
            q = [np.stack(k, 1) for k in e]
            tris.append(np.stack([q[0], q[1], q[2]], 1))
            tris.append(np.stack([q[0], q[2], q[3]], 1))
            d = pos(t[np.arange(len(t))[:, None], o[:, 2:]]).mean(1) - pos(t[np.arange(len(t))[:, None],
                                                                           o[:, :2]]).mean(1)
            outdir += [d, d]
    tri_keys = np.concatenate(tris)  # (T, 3, 2) grid-edge endpoints
    outdir = np.concatenate(outdir)
    flat = tri_keys.reshape(-1, 2)
    uniq, inv = np.unique(flat[:, 0] * f.size + flat[:, 1], return_inverse=True)
    a, b = uniq // f.size, uniq % f.size
    fa, fb = f.reshape(-1)[a], f.reshape(-1)[b]
    w = fa / (fa - fb)
    V = pos(a) + w[:, None] * (pos(b) - pos(a))
    F = inv.reshape(-1, 3)
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    flip = (n * outdir).sum(1) < 0
    F[flip] = F[flip][:, ::-1]
    good = (F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2])
    return V, F[good]


def _deformed(rng, shared_meshes):
    import fast_simplification
    import trimesh

    name = DEFORM_SOURCES[int(rng.integers(len(DEFORM_SOURCES)))]
    tm = trimesh.load(os.path.join(shared_meshes, name), process=False, force="mesh")
    tm.remove_unreferenced_vertices()
    V, F = np.asarray(tm.vertices, float), np.asarray(tm.faces)
    target = int(rng.integers(3000, 8000))
    if len(V) > target:
        V, F = fast_simplification.simplify(V.astype(np.float32), F.astype(np.int32), 1 - target / len(V))
        V = V.astype(float)
    c = (V.min(0) + V.max(0)) / 2
    V = (V - c) / np.linalg.norm(V - c, axis=1).max()
    V = V @ _random_rotation(rng).T
    disp = np.stack([_smooth_field(rng, V, 5, (0.8, 2.0), 0.08) for _ in range(3)], 1)
    return (V + disp) * rng.uniform(0.75, 1.25, 3), F, name


def deform_sources_present(shared_meshes) -> bool:
    """Whether ``shared_meshes`` holds every source mesh of the ``deformed`` family."""
    return shared_meshes is not None and all(os.path.isfile(os.path.join(shared_meshes, n)) for n in DEFORM_SOURCES)


def make_shape(i: int, seed: int = 0, shared_meshes=None):
    """Shape number i of the collection ``seed`` -> (vertices (V, 3) float64, faces (F, 3) int64, info dict)."""
    rng = np.random.default_rng([int(seed), int(i)])
    fam = FAMILIES[i % len(FAMILIES)]
    info = {"index": int(i), "seed": int(seed), "family": fam}
    if fam == "deformed" and not deform_sources_present(shared_meshes):
        fam = info["family"] = "blob"
    if fam == "deformed":
        V, F, src = _deformed(rng, shared_meshes)
        info["source"] = src
    else:
        V, F = {"blob": _blob, "torus": _torus, "vase": _vase, "rounded_box": _rounded_box,
                "capsules": _capsules}[fam](rng)
    V = np.asarray(V, np.float64) @ _random_rotation(rng).T
    info["vertices"], info["faces"] = len(V), len(F)
    return V, np.asarray(F, np.int64), info


SPLIT_RULE = "family-instance"


def is_test(i: int, test_every: int = 10) -> bool:
    """Whether shape i is a test shape: its instance number within its family is test_every - 1 mod test_every."""
    return (i // len(FAMILIES)) % test_every == test_every - 1


def _write_shape(job):
    """Make shape i and write it (unless its file exists); returns its manifest entry. One job of
    :func:`write_collection` (module level, so that worker processes can run it)."""
    import trimesh

    folder, i, seed, test_every, shared_meshes = job
    split = "test" if is_test(i, test_every) else "train"
    V, F, info = make_shape(i, seed, shared_meshes)
    name = f"shape_{i:05d}_{info['family']}.obj"
    (folder / split).mkdir(parents=True, exist_ok=True)
    path = folder / split / name
    if not path.exists():
        tmp = path.with_name(f"{path.stem}.tmp{os.getpid()}.obj")
        trimesh.Trimesh(V, F, process=False).export(tmp)
        os.replace(tmp, path)
    info["split"] = split
    info["file"] = f"{split}/{name}"
    return info


MAX_SHAPES = 1_000_000  # shapes of one collection: 10^8 asked ran for minutes building its job list, writing nothing


def write_collection(folder, n: int = 600, seed: int = 0, test_every: int = 10, shared_meshes=None,
                     start: int = 0, progress: bool = True, workers: int = 1) -> dict:
    """Write shapes start .. n-1 as ``folder/{train,test}/shape_{i:05d}_{family}.obj`` and a manifest.json
    (family, seed, split, vertex/face counts of each). Existing files are kept (so a run can be resumed).
    ``workers`` > 1 makes the shapes in that many processes (same files: each shape depends on (seed, i) only)."""
    if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or not 1 <= n <= MAX_SHAPES:
        from neurogf_warp.common.checks import InputError

        raise InputError(f"n must be an integer from 1 to {MAX_SHAPES:,} (shapes of a collection), got {n!r}: "
                         "a collection is written as one .obj per shape and one manifest, all of it before the "
                         "manifest is saved")
    folder = Path(folder)
    # only the folder given: a default looked up beside the package made the files depend on where it was installed
    deform = deform_sources_present(shared_meshes)
    man_path = folder / "manifest.json"
    man = json.loads(man_path.read_text()) if man_path.exists() else {"seed": seed, "test_every": test_every,
                                                                       "split": SPLIT_RULE, "shapes": {},
                                                                       "deformed_family": deform}
    if man.get("split") != SPLIT_RULE:
        raise ValueError(f"{folder} holds a collection split by an older rule ({man.get('split', 'i % test_every')});"
                         f" use another folder")
    if man["seed"] != seed or man["test_every"] != test_every:
        raise ValueError(f"{folder} holds a collection with seed {man['seed']} / test_every {man['test_every']}; "
                         f"use another folder or the same settings")
    if man.get("deformed_family", deform) != deform:
        raise ValueError(f"{folder} holds a collection made {'with' if not deform else 'without'} the deformed "
                         f"family's source meshes; continue it "
                         f"{'with the same shared_meshes folder' if not deform else 'without shared_meshes'}, "
                         f"or use another folder")
    if progress and not deform_sources_present(shared_meshes) and any(
            FAMILIES[i % len(FAMILIES)] == "deformed" for i in range(start, n)):
        where = f"the shared meshes folder ({shared_meshes})" if shared_meshes else "a folder given as shared_meshes"
        print(f"note: the 'deformed' family needs {', '.join(DEFORM_SOURCES)} in {where} (--shared-meshes DIR); "
              f"those shapes are 'blob' instead", flush=True)
    jobs = [(folder, i, seed, test_every, shared_meshes) for i in range(start, n)]
    if workers > 1 and len(jobs) > 1:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(min(workers, len(jobs)), mp_context=mp.get_context("spawn")) as ex:
            infos = ex.map(_write_shape, jobs, chunksize=4)
            for n_done, info in enumerate(infos, 1):
                man["shapes"][str(info["index"])] = info
                if progress and n_done % 100 == 0:
                    print(f"shapes: {n_done}/{len(jobs)}", flush=True)
    else:
        for job in jobs:
            info = _write_shape(job)
            man["shapes"][str(info["index"])] = info
            if progress and (info["index"] + 1) % 50 == 0:
                print(f"shapes: {info['index'] + 1}/{n}", flush=True)
    tmp = man_path.with_suffix(".tmp")
    tmp.write_text(json.dumps(man, indent=1))
    os.replace(tmp, man_path)
    return man


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(description="write a shape collection (train/test split by shape number)")
    ap.add_argument("folder")
    ap.add_argument("-n", type=int, default=600)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--test-every", type=int, default=10)
    ap.add_argument("--shared-meshes", default=None)
    ap.add_argument("--workers", type=int, default=1)
    a = ap.parse_args()
    write_collection(a.folder, a.n, a.seed, a.test_every, a.shared_meshes, workers=a.workers)
