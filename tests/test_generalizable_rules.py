"""The generalizable model held to the per-mesh model's rules: query points in the domain, conditioning clouds
judged by their spread (not their count) and size, a clear error before conditioning, the per-mesh functions and
the command line given a generalizable network, a collection that does not depend on where the package lives."""
import json

import numpy as np
import pytest
import trimesh

import neurogf_warp as ngf
from neurogf_warp.common.checks import InputError
from neurogf_warp.generalizable import model as gm

from .conftest import shared_path

GEN = ("checkpoints", "official", "GenNeuroGF.pth")
FIRST = "condition it first: model.condition(points) or ngf.load(path, mesh=...)"


@pytest.fixture(scope="module")
def model():
    return gm.load(shared_path(*GEN))


def _ellipsoid_cloud(n, seed=3, center=(0.0, 0.0, 0.0), axes=(2.0, 1.0, 0.5)):
    g = np.random.default_rng(seed).standard_normal((n, 3))
    return g / np.linalg.norm(g, axis=1, keepdims=True) * np.array(axes) + np.array(center)


@pytest.fixture(scope="module")
def cond(model):
    """A cloud far from the origin (centre (5, -3, 1), bounding radius 2): the domain is centred on it."""
    return model.condition(_ellipsoid_cloud(200, center=(5.0, -3.0, 1.0)))


@pytest.fixture(scope="module")
def small_mesh(tmp_path_factory):
    tm = trimesh.creation.icosphere(subdivisions=2)
    tm.vertices *= np.array([1.0, 0.7, 0.5])
    path = tmp_path_factory.mktemp("gen_rules") / "blob.obj"
    tm.export(path)
    return path


# ---- domain -------------------------------------------------------------------------------------------------------

def test_points_outside_the_domain_are_refused_by_every_query(cond):
    c = cond.center
    r = 1.0 / cond.scale  # the bounding radius in user units
    inside = c + np.array([1.45 * r, 0.0, 0.0])  # within the cube of half-side 1.5 radii
    far = c + np.array([0.0, 0.0, 1e6])
    near_far = c + np.array([1.6 * r, 0.0, 0.0])
    assert np.isfinite(cond.distance(inside, cond.points[0]))
    for bad in (far, near_far):
        with pytest.raises(ValueError, match=r"q\[0\] = .* outside the model's domain"):
            cond.distance(cond.points[:1], bad[None])
        with pytest.raises(ValueError, match=r"p\[1\] = .* outside"):
            cond.distance(np.stack([inside, bad]), cond.points[:2])
        with pytest.raises(ValueError, match="outside"):
            cond.ssad(bad)
        with pytest.raises(ValueError, match=r"sources\[0\]"):
            cond.msad(bad[None])
        with pytest.raises(ValueError, match=r"targets\[1\]"):
            cond.distance_matrix(cond.points[:1], np.stack([inside, bad]))
    with pytest.raises(ValueError, match="non-finite"):
        cond.distance([np.nan, 0.0, 0.0], cond.points[0])
    # the per-mesh entry point refuses it the same way (it answers through the model's own method)
    with pytest.raises(ValueError, match="outside"):
        ngf.distance(cond, far[None], cond.points[:1])


# ---- the conditioning cloud ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("case", ["repeated", "few_distinct", "line", "coincident"])
def test_degenerate_clouds_are_refused_whatever_their_count(model, case):
    base = _ellipsoid_cloud(5)
    if case == "repeated":  # five points, repeated to 2,048: still five points
        pts, why = np.tile(base, (410, 1))[:2048], "only 5 distinct points"
    elif case == "few_distinct":  # 39 distinct points (one short of the neighbour count) padded with copies
        pts, why = np.concatenate([_ellipsoid_cloud(39), _ellipsoid_cloud(39)[:30]]), "only 39 distinct"
    elif case == "line":
        t = np.linspace(-1.0, 1.0, 500)[:, None]
        pts, why = np.array([3.0, 1.0, -2.0]) + t * np.array([1.0, 2.0, 0.5]), "on a line"
    else:
        pts, why = np.ones((100, 3)), "coincide"
    with pytest.raises(InputError, match=why):
        model.condition(pts)


def test_a_flat_cloud_is_a_shape(model):
    """A plane (a flat plate) is spread over a surface: accepted."""
    g = np.random.default_rng(1).uniform(-1, 1, (120, 2))
    c = model.condition(np.column_stack([g, np.zeros(120)]))
    assert np.isfinite(c.distance(c.points[:3], c.points[3:6])).all()


def test_clouds_above_the_size_limit_are_refused_before_any_work(model, small_mesh, monkeypatch):
    limit = gm.max_points_for("cpu")
    big = _ellipsoid_cloud(limit + 1)
    with pytest.raises(InputError, match=f"{limit + 1:,} points.*N\\^2.*{limit:,}.*max_points="):
        model.condition(big)
    with pytest.raises(InputError, match="n_points=9000"):
        model.condition(str(small_mesh), n_points=9000)
    # the limit is the caller's to raise or lower
    with pytest.raises(InputError, match="300 points"):
        model.condition(_ellipsoid_cloud(300), max_points=200)
    with pytest.raises(InputError, match="max_points must be >= 1"):
        model.condition(_ellipsoid_cloud(300), max_points=0)
    monkeypatch.setitem(gm.MAX_POINTS, "cpu", 100)
    assert model.condition(_ellipsoid_cloud(150), max_points=150).points.shape == (150, 3)


# ---- before conditioning, and through the per-mesh functions -------------------------------------------------------

def test_queries_before_conditioning_say_how_to_condition(model):
    for call in (lambda: model.distance([0.0, 0, 0], [0.1, 0, 0]), lambda: model.ssad(0),
                 lambda: model.msad([0, 1]), lambda: model.distance_matrix([0])):
        with pytest.raises(InputError, match="condition it first"):
            call()
    for call in (lambda: ngf.ssad(model, 0), lambda: ngf.msad(model, [0]), lambda: ngf.distance_matrix(model, [0]),
                 lambda: ngf.distance(model, np.zeros((1, 3)), np.zeros((1, 3))), lambda: ngf.sdf(model, np.zeros(3)),
                 lambda: ngf.path(model, np.zeros(3), np.ones(3))):
        with pytest.raises(InputError) as e:
            call()
        assert FIRST in str(e.value)


def test_per_mesh_functions_answer_for_a_conditioned_model(model, small_mesh):
    c = model.condition(str(small_mesh), n_points=256)
    v = np.asarray(c.mesh.vertices)
    np.testing.assert_array_equal(ngf.ssad(c, 3), c.ssad(3))
    np.testing.assert_array_equal(ngf.msad(c, [3, 40]), c.msad([3, 40]))
    np.testing.assert_array_equal(ngf.distance_matrix(c, [1, 2], targets=[5, 6, 7]),
                                  c.distance_matrix([1, 2], [5, 6, 7]))
    np.testing.assert_array_equal(ngf.distance(c, v[:4], v[4:8]), c.distance(v[:4], v[4:8]))
    with pytest.raises(InputError, match="no SDF or path head"):
        ngf.sdf(c, v[:2])
    with pytest.raises(InputError, match="no SDF or path head"):
        ngf.path(c, v[0], v[1])
    with pytest.raises(InputError, match="output='numpy'"):
        ngf.ssad(c, 0, output="torch")
    with pytest.raises(InputError, match="raw=True"):
        ngf.distance(c, v[:1], v[1:2], raw=True)


# ---- command line --------------------------------------------------------------------------------------------------

@pytest.mark.slow  # two conditionings of the network on the mesh, ~4 s each on a 2-core CPU
def test_cli_info_and_queries_of_the_generalizable_network(small_mesh, tmp_path, capsys, monkeypatch):
    from neurogf_warp.cli.main import main

    path = str(shared_path(*GEN))
    assert main(["info", path]) == 0
    out = capsys.readouterr().out
    assert "generalizable NeuroGF" in out and "2048-point clouds" in out and "released network" in out
    assert main(["info", path, "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["neighbours"] == 40 and info["parameters"] > 0 and "conditioned_on" not in info
    # ssad on a mesh: conditioned on it (2,048 sampled points, as ngf.load(path, mesh=...)), answers per vertex
    out_file = tmp_path / "d.npy"
    assert main(["ssad", path, "--mesh", str(small_mesh), "--source", "4", "-o", str(out_file), "-q"]) == 0
    conditioned = ngf.load(path, mesh=str(small_mesh))
    np.testing.assert_array_equal(np.load(out_file), conditioned.ssad(4))
    # no path head: refused with exit 2 and the reason, not an internal error, before any conditioning on --mesh
    from neurogf_warp.generalizable.model import GeneralizableModel

    monkeypatch.setattr(GeneralizableModel, "condition",
                        lambda self, mesh: pytest.fail("conditioned on --mesh before refusing the command"))
    capsys.readouterr()
    for argv in (["path", path, "--mesh", str(small_mesh), "--p", "0", "0", "0", "--q", "0.1", "0", "0"],
                 ["render", path, "--mesh", str(small_mesh), "-o", str(tmp_path / "r.png")],
                 ["eval", path, "--mesh", str(small_mesh)]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert f"{argv[0]} needs a per-mesh model" in err and "internal error" not in err
    # a query without --mesh: how to give the shape
    assert main(["ssad", path, "--source", "0"]) == 2
    assert "pass --mesh MESHFILE" in capsys.readouterr().err


# ---- the collection ------------------------------------------------------------------------------------------------

def test_collection_does_not_depend_on_where_the_package_is(tmp_path, capsys):
    """Without shared_meshes the 'deformed' shapes are blobs, even where a shared/meshes folder happens to sit
    beside the package (it was looked up there), and a collection is not continued with the other choice."""
    from neurogf_warp.generalizable.shapes import FAMILIES, write_collection

    i = FAMILIES.index("deformed")
    man = write_collection(tmp_path / "a", n=i + 1, seed=0, start=i, progress=True)
    assert man["shapes"][str(i)]["family"] == "blob" and man["deformed_family"] is False
    assert "--shared-meshes" in capsys.readouterr().out
    meshes = shared_path("meshes")
    with pytest.raises(ValueError, match="without the deformed family's source meshes"):
        write_collection(tmp_path / "a", n=i + 2, seed=0, start=i + 1, shared_meshes=str(meshes), progress=False)



def test_a_two_dimensional_integer_array_is_refused_as_on_a_per_mesh_model(cond):
    """The per-mesh rule for index arguments: integers are indices (one, or 1-D), floats are points; (M, 3)
    integers are not guessed at (point arguments, as ``distance``'s, are coordinates: the test below)."""
    two_d = np.array([[0, 1, 2], [3, 4, 5]])
    for call in (lambda: cond.msad(two_d), lambda: cond.distance_matrix(two_d),
                 lambda: cond.distance_matrix([0], two_d)):
        with pytest.raises(InputError, match="integer array of shape"):
            call()
    assert np.isfinite(cond.msad([0, 1])).any()  # 1-D integers are still indices


# ---- one reading of integers ------------------------------------------------------------------------------------

def test_integers_read_as_the_per_mesh_queries_read_them(model):
    """Point arguments (distance) are coordinates of any real dtype, index arguments (ssad, msad, distance_matrix)
    are indices, in both kinds of model: the same integer array never means points in one and indices in the
    other."""
    cloud = _ellipsoid_cloud(200, axes=(3.0, 2.0, 1.5))
    c = model.condition(cloud)
    p, q = np.array([0, 1, 0]), np.array([1, 0, 0])
    assert c.distance(p, q) == c.distance(p.astype(float), q.astype(float))
    pairs = np.array([[0, 1, 0], [1, 0, 1]]), np.array([[1, 0, 0], [0, 0, 1]])
    np.testing.assert_array_equal(ngf.distance(c, *pairs), c.distance(*(x.astype(np.float32) for x in pairs)))
    with pytest.raises(ValueError, match=r"\(M, 3\) or \(3,\)"):  # five integers are not points, nor read as indices
        c.distance(np.arange(5), np.arange(5))
    np.testing.assert_allclose(c.distance_matrix([3], [7])[0, 0], c.distance(c.points[3], c.points[7]), rtol=1e-6)
