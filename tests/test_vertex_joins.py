"""Meshes whose patches meet only at single vertices are refused before training, with the fix."""
import numpy as np
import pytest
import trimesh

import neurogf_warp as ngf
from neurogf_warp.common.checks import InputError
from neurogf_warp.dataset.build import check_trainable
from neurogf_warp.mesh.mesh import load_mesh
from neurogf_warp.mesh.topology import edge_patches, vertex_joins
from tests.conftest import shared_path


def _patch_sphere():
    """An icosphere cut into 8 octant patches whose seams are stored twice (one copy per patch), joined only at
    the vertices where three or more patches meet: the layout of a tessellated teapot's patches."""
    s = trimesh.creation.icosphere(subdivisions=3)
    v, f = s.vertices, s.faces
    c = v[f].mean(1)
    patch = (c[:, 0] > 0) * 4 + (c[:, 1] > 0) * 2 + (c[:, 2] > 0)
    users = [set() for _ in range(len(v))]
    for fi, p in enumerate(patch):
        for x in f[fi]:
            users[x].add(int(p))
    new_v, key_to_new, new_f = [], {}, np.empty_like(f)
    for fi, p in enumerate(patch):
        for k, x in enumerate(f[fi]):
            key = (int(x), -1 if len(users[x]) >= 3 else int(p))  # corners stay shared, seams are split
            if key not in key_to_new:
                key_to_new[key] = len(new_v)
                new_v.append(v[x])
            new_f[fi, k] = key_to_new[key]
    return np.array(new_v), new_f


def _two_touching_spheres():
    a = trimesh.creation.icosphere(subdivisions=2)
    top = int(np.argmax(a.vertices[:, 2]))
    b_v = a.vertices.copy()
    b_v[:, 2] = 2 * a.vertices[top, 2] - b_v[:, 2]  # mirrored: its lowest vertex is a's top vertex
    bottom = int(np.argmin(b_v[:, 2]))
    keep = np.arange(len(b_v)) != bottom
    remap = np.full(len(b_v), -1)
    remap[keep] = len(a.vertices) + np.arange(keep.sum())
    remap[bottom] = top
    return np.vstack([a.vertices, b_v[keep]]), np.vstack([a.faces, remap[a.faces]])


def test_patches_joined_at_vertices_are_found():
    mesh = load_mesh(_patch_sphere(), weld=False)
    assert mesh.n_components == 1
    j = vertex_joins(mesh)
    assert j.patches == 8 and j.joined_patches == 8 and j.pinch_vertices > 0 and j.coincident_vertices > 0
    welded = load_mesh(_patch_sphere(), weld=True)
    assert edge_patches(welded.internal_faces)[0] == 1 and not vertex_joins(welded).any


def test_training_refuses_them_before_any_work_and_says_how_to_weld(tmp_path):
    out = tmp_path / "teapot.ngf"
    with pytest.raises(InputError, match=r"single vertices.*weld=True") as e:
        ngf.train(_patch_sphere(), out, config="cpu_small", device="cpu", progress=False)
    assert "allow_vertex_joins=True" in str(e.value)
    assert not out.exists() and not (tmp_path / "teapot.train").exists()


def test_a_true_pinch_gets_no_weld_advice_and_can_be_allowed():
    mesh = load_mesh(_two_touching_spheres())
    j = vertex_joins(mesh)
    assert j.patches == 2 and j.pinch_vertices == 1 and j.coincident_vertices == 0
    with pytest.raises(InputError, match="single vertices") as e:
        check_trainable(mesh)
    assert "weld" not in str(e.value).split("allow_vertex_joins")[0].lower()
    check_trainable(mesh, allow_vertex_joins=True)


@pytest.mark.parametrize("name", ["cow.obj", "fandisk.obj", "spot.obj"])
def test_shared_meshes_are_not_refused(name):
    mesh = load_mesh(str(shared_path("meshes", name)))  # cow has a pinch vertex inside one patch
    assert not vertex_joins(mesh).any
    check_trainable(mesh)


def test_separate_parts_are_not_vertex_joins():
    a = trimesh.creation.icosphere(subdivisions=2)
    b = a.copy()
    b.vertices += [3.0, 0, 0]
    m = trimesh.util.concatenate([a, b])
    mesh = load_mesh((m.vertices, m.faces))
    assert mesh.n_components == 2 and not vertex_joins(mesh).any
