"""Pictures (render) and coloured meshes (write_ply) on Warp's CPU device, with tiny images and constructed meshes."""
import numpy as np
import pytest
import torch

import neurogf_warp as ngf
from neurogf_warp.pictures.render import COLOR_STOPS, View, _camera, colorize
from tests.test_inference import random_net

DEV = "cpu"
TOP = dict(up="y", elevation=0, azimuth=0)  # from +z at the xy plane: image x along +x, image up along +y


def grid(n=12, size=2.0):
    """A flat square [-1, 1]^2 at z = 0, n x n quads, plus one unused vertex at the start of the file."""
    u = np.linspace(-size / 2, size / 2, n + 1)
    X, Y = np.meshgrid(u, u, indexing="ij")
    V = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], 1)
    k = np.arange(n * (n + 1)).reshape(n, n + 1)[:, :n].ravel()
    F = np.concatenate([np.stack([k, k + n + 1, k + n + 2], 1), np.stack([k, k + n + 2, k + 1], 1)])
    return np.concatenate([[[5.0, 5.0, 5.0]], V]), F + 1


def project(vertices, view, size, p):
    """Pixel (column, row) of point p in an image of ``size`` rendered with ``view`` (the renderer's camera)."""
    cam = _camera(vertices, View.of(view), *size)
    eye, f, r, u = (np.array(v, dtype=np.float64) for v in (cam.eye, cam.forward, cam.right, cam.up))
    d = p - eye
    z = d @ f
    sx, sy = (d @ r) / z / (r @ r), (d @ u) / z / (u @ u)
    return (sx + 1) / 2 * size[0] - 0.5, (1 - sy) / 2 * size[1] - 0.5


def luminance(img):
    return img.astype(np.float64) @ np.array([0.2126, 0.7152, 0.0722])


def test_field_colours_isolines_and_background():
    V, F = grid()
    x = V[:, 0].copy()
    x[0] = np.nan  # the unused vertex: no value
    for lines in (5, 0):
        img = ngf.render((V, F), x, isolines=lines, size=(64, 64), view=TOP, supersample=1, device=DEV)
        assert img.shape == (64, 64, 3) and img.dtype == np.uint8
        assert np.all(img[[0, 0, -1, -1], [0, -1, 0, -1]] == 255)  # corners: background
        row = img[32]
        surf = np.flatnonzero(np.any(row < 250, axis=1))
        assert len(surf) > 30, "the plane fills the middle of the image"
        lum = luminance(row[surf])
        # the colour map brightens with the value, and x grows to the right of the picture
        q = len(surf) // 4
        assert lum[:q].mean() < lum[q:3 * q].mean() < lum[3 * q:].mean()
        # isolines: samples darker than both neighbours by a factor, one run per interior level change
        dark = (lum[1:-1] < 0.6 * lum[:-2]) | (lum[1:-1] < 0.6 * lum[2:])
        runs = np.count_nonzero(np.diff(np.concatenate([[0], dark.astype(int), [0]])) == 1)
        assert runs == max(lines - 1, 0), (lines, runs)
    # unlit-by-field (NaN) surface is grey; the colour at the value's low end is the map's first stop, shaded
    img = ngf.render((V, F), np.full(len(V), np.nan), isolines=3, size=(32, 32), view=TOP, supersample=1, device=DEV)
    c = img[16, 16].astype(float)
    assert np.ptp(c) <= 2 and 100 < c[0] < 255
    row = ngf.render((V, F), V[:, 0], isolines=0, size=(64, 64), view=TOP, supersample=1, device=DEV)[32]
    surf = np.flatnonzero(np.any(row < 250, axis=1))
    hue = lambda c: c / np.linalg.norm(c, axis=-1, keepdims=True)
    for px, stop in ((row[surf[0]], 0), (row[surf[-1]], len(COLOR_STOPS) - 1)):  # the ends of the map, shaded
        assert np.argmax(hue(COLOR_STOPS) @ hue(px.astype(float))) == stop, (px, stop)


def test_markers_paths_and_points_land_where_projected():
    V, F = grid()
    size, view = (80, 64), TOP
    src = 1 + 3 * 13 + 4  # a file-numbered vertex of the plane
    path = np.stack([np.linspace(-0.8, 0.8, 50), 0.5 * np.ones(50), np.zeros(50)], 1)
    pt = np.array([[0.6, -0.6, 0.0]])
    img = ngf.render((V, F), V[:, 1], sources=[src], paths=[path], points=pt, size=size, view=view, isolines=0,
                     supersample=1, marker_radius=0.12, path_radius=0.04, device=DEV)
    assert img.shape == (64, 80, 3)
    f = img.astype(int)
    gold = (f[..., 0] > 150) & (f[..., 1] > 100) & (f[..., 2] < 60)
    crimson = (f[..., 0] > 120) & (f[..., 1] < 40) & (f[..., 2] < 80)
    white = np.all(f > 170, axis=-1) & (np.ptp(f, axis=-1) < 20) & np.any(f < 250, axis=-1)  # not the background
    for mask, p in ((gold, V[src]), (white, pt[0])):
        ys, xs = np.nonzero(mask)
        assert len(xs) > 3
        cx, cy = project(V[1:], view, size, p)
        assert abs(xs.mean() - cx) < 2 and abs(ys.mean() - cy) < 2, (xs.mean(), ys.mean(), cx, cy)
    ys, xs = np.nonzero(crimson)
    ends = [project(V[1:], view, size, path[i]) for i in (0, -1)]
    assert len(xs) > 20 and np.all(np.abs(ys - ends[0][1]) < 3)  # a horizontal tube at the path's row
    assert xs.min() <= ends[0][0] + 2 and xs.max() >= ends[1][0] - 2


def test_model_fields_and_file(tmp_path):
    """values=None with a model renders its SSAD (one source) / MSAD (several); the PNG holds the image."""
    import trimesh
    from PIL import Image

    tm = trimesh.creation.icosphere(subdivisions=2)
    mesh = ngf.load_mesh((tm.vertices * [2.0, 1.5, 1.0] + 3.0, tm.faces))
    model = ngf.Model(net=random_net(64, 1, euclid=True), mesh=mesh, center=mesh.center, scale=mesh.scale)
    kw = dict(size=(48, 40), isolines=6, supersample=2, device=DEV)
    one = ngf.render(model, sources=[7], out=tmp_path / "one.png", **kw)
    assert np.array_equal(one, ngf.render(mesh, ngf.ssad(model, 7, device=DEV), sources=[7], **kw))
    assert np.array_equal(np.asarray(Image.open(tmp_path / "one.png").convert("RGB")), one)
    many = ngf.render(model, sources=[7, 90, 150], **kw)
    assert np.array_equal(many, ngf.render(mesh, ngf.msad(model, [7, 90, 150], device=DEV), sources=[7, 90, 150], **kw))
    # torch values work like numpy; the camera can be given as (azimuth, elevation)
    d = ngf.ssad(model, 7, device=DEV)
    assert np.array_equal(ngf.render(mesh, torch.from_numpy(d), view=(30, 20), **kw), ngf.render(mesh, d, **kw))


def test_bad_inputs(tmp_path):
    V, F = grid(4)
    with pytest.raises(ValueError, match="one number per mesh vertex"):
        ngf.render((V, F), np.zeros(7), device=DEV)
    with pytest.raises(ValueError, match="size must be"):
        ngf.render((V, F), size=(0, 10), device=DEV)
    with pytest.raises(ValueError, match="unknown keys"):
        ngf.render((V, F), view={"azimut": 3}, device=DEV)
    with pytest.raises(ValueError, match="view.up"):
        ngf.render((V, F), view={"up": "w"}, size=(8, 8), device=DEV)
    with pytest.raises(ValueError, match=".png or .jpg"):
        ngf.render((V, F), size=(8, 8), out=tmp_path / "x.gif", device=DEV)
    assert not (tmp_path / "x.gif").exists()
    with pytest.raises(ValueError, match="isolines"):
        ngf.render((V, F), isolines=-1, device=DEV)
    with pytest.raises(ValueError, match="paths must be"):
        ngf.render((V, F), paths=np.zeros((2, 2, 2, 3)), size=(8, 8), device=DEV)
    with pytest.raises(ValueError, match="vrange"):
        ngf.render((V, F), V[:, 0], vrange=(1, 1), size=(8, 8), device=DEV)
    with pytest.raises(IndexError, match="not used by any face"):
        ngf.render((V, F), sources=[0], size=(8, 8), device=DEV)
    with pytest.raises(ValueError, match="has no mesh"):
        ngf.render(ngf.Model(net=random_net(64, 0)), size=(8, 8), device=DEV)


@pytest.mark.parametrize("view, words", [
    ((float("nan"), 0), "view.azimuth must be finite"),
    ((0, float("inf")), "view.elevation must be finite"),
    ({"zoom": float("nan")}, "view.zoom must be finite"),
    ({"center": (0, float("nan"), 0)}, "view.center must be a finite point"),
])
def test_non_finite_views_are_refused(view, words, tmp_path):
    """A NaN camera used to draw an empty picture without a word."""
    V, F = grid(4)
    with pytest.raises(ValueError, match=words):
        ngf.render((V, F), view=view, size=(8, 8), out=tmp_path / "x.png", device=DEV)
    assert not (tmp_path / "x.png").exists()


@pytest.mark.parametrize("name, value", [("path_radius", float("nan")), ("marker_radius", 0.0),
                                         ("path_radius", -1.0)])
def test_radii_must_be_positive_numbers(name, value):
    V, F = grid(4)
    with pytest.raises(ValueError, match=name):
        ngf.render((V, F), size=(8, 8), device=DEV, **{name: value})


def test_write_ply_round_trip(tmp_path):
    """Vertex colours and values survive trimesh's PLY reader; the file holds every vertex in the mesh's numbering
    (vertex 0, in no face, with NaN coordinates and value), so values land on the right vertices."""
    import trimesh

    V, F = grid(5)
    values = np.arange(len(V), dtype=np.float64)  # the file index itself
    values[7] = np.nan
    path = ngf.write_ply(tmp_path / "f.ply", (V, F), values, vrange=(0, len(V)))
    tm = trimesh.load(path, process=False)
    assert len(tm.vertices) == len(V) and np.array_equal(tm.faces, F)
    assert np.isnan(tm.vertices[0]).all()
    np.testing.assert_allclose(tm.vertices[1:], V[1:], atol=1e-6)
    want = values.copy()
    want[0] = np.nan  # no face uses vertex 0: no distance, no colour
    col = np.asarray(tm.visual.vertex_colors)
    np.testing.assert_array_equal(col[:, :3], colorize(want, (0, len(V))))
    assert np.all(col[:, 3] == 255) and np.all(col[[0, 7], :3] == round(0.72 * 255))  # NaN: grey
    q = tm.metadata["_ply_raw"]["vertex"]["data"]["quality"]
    np.testing.assert_array_equal(q, want.astype(np.float32))
    # colours follow the map: low values dark indigo, high values cream
    np.testing.assert_array_equal(colorize([0.0, 1.0]), np.round(255 * COLOR_STOPS[[0, -1]]).astype(np.uint8))
    with pytest.raises(ValueError, match="one number per mesh vertex"):
        ngf.write_ply(tmp_path / "g.ply", (V, F), values[:3])
    assert not (tmp_path / "g.ply").exists()


# --- framing, up axis, the source's side, path targets ---------------------------------------------------------

def ellipsoid_mesh(radii, subdivisions=2):
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=subdivisions)
    return np.asarray(s.vertices) * np.asarray(radii, dtype=np.float64), np.asarray(s.faces)


def surface_mask(img):
    return np.any(img < 250, axis=-1)


@pytest.mark.parametrize("size", [(48, 32), (32, 48), (40, 40)])
def test_everything_drawn_fits_with_a_margin_at_every_view(size):
    """Wide, tall and square pictures, 24 views around and over an elongated mesh with a marker and a path
    sticking out: the outermost 2 pixels are always background."""
    V, F = ellipsoid_mesh((1.0, 0.3, 0.5), subdivisions=1)
    path = np.stack([np.linspace(-1.0, 1.0, 20), np.zeros(20), 0.5 + 0.2 * np.sin(np.linspace(0, np.pi, 20))], 1)
    for az in range(0, 360, 45):
        for el in (-80, 0, 60):
            img = ngf.render((V, F), V[:, 0], sources=[0], paths=[path], size=size, view=(az, el), isolines=0,
                             supersample=1, device=DEV)
            m = surface_mask(img)
            border = np.concatenate([m[:2].ravel(), m[-2:].ravel(), m[:, :2].ravel(), m[:, -2:].ravel()])
            assert m.sum() > 0.02 * m.size and not border.any(), (size, az, el)


@pytest.mark.parametrize("axis", [1, 2])
def test_auto_up_stands_a_tall_mesh_upright(axis):
    """A mesh three times taller along y (y-up) or along z (z-up) comes out taller than wide by default;
    up="x" lays it down, and View(up=...) overrides the choice."""
    from neurogf_warp.pictures.render import choose_up

    radii = [0.3, 0.3, 0.3]
    radii[axis] = 1.0
    V, F = ellipsoid_mesh(radii)
    assert choose_up(V) == "yz"[axis - 1]

    def height_over_width(view):
        m = surface_mask(ngf.render((V, F), size=(64, 64), view=view, isolines=0, supersample=1, device=DEV))
        rows, cols = np.flatnonzero(m.any(1)), np.flatnonzero(m.any(0))
        return (rows.max() - rows.min()) / (cols.max() - cols.min())

    assert height_over_width(None) > 2.0
    # up x: azimuth 0 looks from +y, 90 from +z; look across the long axis
    assert height_over_width({"up": "x", "azimuth": 90 if axis == 1 else 0, "elevation": 0}) < 0.5


def test_the_default_view_faces_the_source():
    """A source on the far side of the default view's camera (azimuth 30) is in plain sight, near the middle."""
    V, F = ellipsoid_mesh((1.0, 0.6, 0.8))
    for direction in ([-0.5, 0.1, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.2], [0.2, 1.0, 0.0]):
        src = int(np.argmax(V @ np.asarray(direction)))
        img = ngf.render((V, F), V[:, 0], sources=[src], size=(64, 64), isolines=0, supersample=1,
                         marker_radius=0.1, device=DEV)
        f = img.astype(int)
        gold = (f[..., 0] > 150) & (f[..., 1] > 100) & (f[..., 2] < 60)
        ys, xs = np.nonzero(gold)
        assert len(xs) > 20, direction
        assert abs(xs.mean() - 31.5) < 10 and abs(ys.mean() - 31.5) < 22, (direction, xs.mean(), ys.mean())


def test_path_targets_are_marked():
    V, F = grid()
    path = np.stack([np.linspace(-0.8, 0.6, 30), np.linspace(-0.5, 0.4, 30), np.zeros(30)], 1)
    size = (80, 64)
    img = ngf.render((V, F), V[:, 1], paths=[path], size=size, view=TOP, isolines=0, supersample=1,
                     marker_radius=0.15, path_radius=0.03, device=DEV).astype(int)
    dark = np.all(img < 60, axis=-1)
    ys, xs = np.nonzero(dark)
    cx, cy = project(V[1:], TOP, size, path[-1])
    assert len(xs) > 3 and abs(xs.mean() - cx) < 2 and abs(ys.mean() - cy) < 2


def test_several_sources_are_faced_when_on_one_side():
    from neurogf_warp.pictures.render import source_side

    V, _ = ellipsoid_mesh((1.0, 0.6, 0.8))
    side = V[V[:, 0] > 0.5][:5]  # five sources on the +x side
    d = source_side(side, V)
    assert d is not None and d[0] > 0.8 * np.linalg.norm(d)
    around = V[[np.argmax(V[:, 0]), np.argmin(V[:, 0]), np.argmax(V[:, 1]), np.argmin(V[:, 1])]]
    assert source_side(around, V) is None  # no side to face: the default view
    assert source_side(np.zeros((1, 3)), V) is None  # a source at the centre


def test_style_groups_the_drawing_settings():
    """style=Style(...) or a dict draws the same picture as the same settings given as keywords; unknown names
    and bad values are refused."""
    from neurogf_warp.pictures.render import Style

    V, F = grid(6)
    kw = dict(size=(24, 24), view=TOP, device=DEV)
    flat = ngf.render((V, F), V[:, 0], isolines=3, vrange=(-1, 1), supersample=1, **kw)
    assert np.array_equal(ngf.render((V, F), V[:, 0], style=Style(isolines=3, vrange=(-1, 1), supersample=1), **kw), flat)
    assert np.array_equal(ngf.render((V, F), V[:, 0], style={"isolines": 5, "vrange": (-1, 1), "supersample": 1},
                                     isolines=3, **kw), flat)  # keywords override the style
    with pytest.raises(ValueError, match=r"unknown picture setting\(s\) \['isoline'\]"):
        ngf.render((V, F), V[:, 0], isoline=3, **kw)
    with pytest.raises(ValueError, match="supersample must be <= 8"):
        ngf.render((V, F), V[:, 0], style=Style(supersample=9), **kw)


def test_path_targets_can_be_left_unmarked():
    V, F = grid()
    path = np.stack([np.linspace(-0.8, 0.6, 30), np.linspace(-0.5, 0.4, 30), np.zeros(30)], 1)
    kw = dict(paths=[path], size=(80, 64), view=TOP, isolines=0, supersample=1, marker_radius=0.15, path_radius=0.03,
              device=DEV)
    img = ngf.render((V, F), V[:, 1], path_targets=False, **kw).astype(int)
    assert not np.all(img < 60, axis=-1).any()
