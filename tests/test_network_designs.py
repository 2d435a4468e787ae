"""The training-time network designs ``norm="none"``, ``hash_levels`` and ``landmarks``: shapes, the default
layout untouched, the hash grid's interpolation against a float64 reference, the landmark lookup and bounds,
and the settings' checks."""
import itertools

import pytest
import torch

from neurogf_warp.common.checks import InputError
from neurogf_warp.model.network import FC, HashGrid, Landmarks, NeuroGFNet
from neurogf_warp.training.config import TrainConfig

OPTS = dict(fourier=2, euclid=True, path_residual=True, path_window=True)


def test_default_layout_and_options_unchanged():
    torch.manual_seed(0)
    net = NeuroGFNet(64, **OPTS)
    assert set(net.options) == {"fourier", "euclid", "path_residual", "path_width", "path_window"}
    keys = list(net.state_dict())
    assert "lifting.0.bn.running_mean" in keys and not any(".linear.bias" in k for k in keys)
    assert not any(k.startswith("lifting.0.grid") for k in keys)


def test_no_norm_has_biases_and_no_batch_statistics():
    torch.manual_seed(0)
    net = NeuroGFNet(64, norm="none", **OPTS)
    assert net.options["norm"] == "none"
    for part in (net.lifting, net.gdf_head, net.sdf_head):
        assert not any(isinstance(m, torch.nn.BatchNorm1d) for m in part.modules())
    assert all(m.linear.bias is not None for m in net.lifting)
    p, q = torch.rand(40, 3) * 2 - 1, torch.rand(40, 3) * 2 - 1
    train = net.train().distance(p, q)
    with torch.no_grad():
        ev = net.eval().distance(p, q)
    # without batch statistics a pair's distance does not depend on the rest of the batch or on the mode
    torch.testing.assert_close(train.detach(), ev)
    torch.testing.assert_close(net.distance(p[:5], q[:5]).detach(), ev[:5])


def test_no_norm_keeps_activation_scale():
    torch.manual_seed(1)
    fc = FC(256, 256, norm="none")
    x = torch.randn(4096, 256)
    # He init: E[relu(Wx)^2] = E[x^2] for unit inputs, so the mean square stays near 1 (the PyTorch default
    # init would shrink it to about a sixth)
    ms = fc(x).pow(2).mean().item()
    assert 0.7 < ms < 1.3


def _trilinear_reference(grid: HashGrid, x: torch.Tensor, level: int) -> torch.Tensor:
    """Float64 trilinear blend of one dense level, corner by corner from its definition."""
    res = int(grid.res[level])
    s = res + 1
    u = (x.clamp(-1, 1) + 1) / 2 * res
    i0 = torch.minimum(u.floor(), torch.full_like(u, res - 1))
    f = u - i0
    out = torch.zeros(len(x), grid.features, dtype=torch.float64)
    table = grid.table.detach().double()
    for n in range(len(x)):
        for bits in itertools.product((0, 1), repeat=3):
            c = [int(i0[n, k]) + bits[k] for k in range(3)]
            w = 1.0
            for k in range(3):
                w *= float(f[n, k]) if bits[k] else 1.0 - float(f[n, k])
            out[n] += w * table[level * grid.size + c[0] + s * (c[1] + s * c[2])]
    return out


def test_hash_grid_matches_float64_trilinear_reference():
    torch.manual_seed(2)
    grid = HashGrid(3, features=2, log2_size=12, base=4, finest=64).double()
    with torch.no_grad():
        grid.table.normal_()
    x = torch.rand(30, 3, dtype=torch.float64) * 2.2 - 1.1  # some outside [-1, 1]: clamped onto the cube
    x[0] = torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)  # the +1 faces blend their last cell
    out = grid(x)
    assert out.shape == (30, 6)
    dense = [lv for lv in range(grid.levels) if bool(grid.dense[lv])]
    assert dense and len(dense) < grid.levels  # both kinds of level are exercised
    for lv in dense:
        torch.testing.assert_close(out[:, 2 * lv: 2 * lv + 2], _trilinear_reference(grid, x, lv))


def test_hash_grid_gradients_and_index_range():
    torch.manual_seed(3)
    grid = HashGrid(4, features=2, log2_size=10, base=4, finest=200).double()
    with torch.no_grad():
        grid.table.normal_()
    x = (torch.rand(20, 3, dtype=torch.float64) * 1.8 - 0.9).requires_grad_()
    assert torch.autograd.gradcheck(grid, (x,), eps=1e-7, atol=1e-5)
    grid(x.detach()).sum().backward()
    # every point touches 8 corners on every level: the table's gradient is non-zero on at most that many rows
    touched = (grid.table.grad.abs().sum(1) > 0).sum().item()
    assert 0 < touched <= 20 * 8 * 4


def test_hash_network_forward_and_options():
    torch.manual_seed(4)
    net = NeuroGFNet(64, hash_levels=4, **OPTS)
    assert net.options["hash_levels"] == 4
    p, q = torch.rand(16, 3) * 2 - 1, torch.rand(16, 3) * 2 - 1
    d = net.distance(p, q)
    assert d.shape == (16,) and torch.isfinite(d).all()
    d.sum().backward()
    assert net.lifting[0].grid.table.grad is not None


def test_landmark_lookup_matches_vertices_and_refuses_other_points():
    torch.manual_seed(5)
    xyz = torch.rand(500, 3) * 2 - 1
    table = torch.rand(500, 6)
    lm = Landmarks(6)
    lm.set_table(xyz, table)
    perm = torch.randperm(500)
    torch.testing.assert_close(lm(xyz[perm]), table[perm], rtol=0, atol=0)
    off = xyz[:10] + 1e-4  # not vertices: NaN rows, never a neighbour's distances
    assert torch.isnan(lm(off)).all()
    with pytest.raises(InputError, match="landmark table"):
        lm.set_table(xyz, table[:, :5])


def test_landmark_network_starts_from_the_triangle_bound():
    torch.manual_seed(6)
    xyz = torch.rand(300, 3) * 2 - 1
    table = torch.rand(300, 8) * 3
    net = NeuroGFNet(64, landmarks=8, **OPTS)
    net.landmark_table.set_table(xyz, table)
    assert net.options["landmarks"] == 8
    i, j = torch.randint(0, 300, (64,)), torch.randint(0, 300, (64,))
    d = net.distance(xyz[i], xyz[j])
    assert d.shape == (64,) and torch.isfinite(d).all()
    d.sum().backward()  # the head's first layer reads the landmark features
    assert net.gdf_head[0].linear.weight.grad[:, 64:].abs().sum() > 0
    with torch.no_grad():  # a zero head leaves max(|p - q|, max_k |T(p) - T(q)|), the lower bound, in float64
        net.gdf_head[-1].linear.weight.zero_()
        d0 = net.eval().distance(xyz[i], xyz[j]).double()
    lower = (table[i].double() - table[j].double()).abs().max(-1).values
    ref = torch.maximum((xyz[i] - xyz[j]).double().norm(dim=-1), lower)
    torch.testing.assert_close(d0, ref, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("floor", [0.0, 0.5])
def test_landmark_floor_scales_the_bound_under_the_output(floor):
    """landmark_floor c: a zero head leaves max(|p - q|, c x the lower bound); the option is recorded in the
    network's options (and so in its files) only where it is not 1."""
    torch.manual_seed(7)
    xyz = torch.rand(200, 3) * 2 - 1
    table = torch.rand(200, 8) * 3
    net = NeuroGFNet(64, landmarks=8, landmark_floor=floor, **OPTS)
    net.landmark_table.set_table(xyz, table)
    assert net.options["landmark_floor"] == floor
    assert "landmark_floor" not in NeuroGFNet(64, landmarks=8, **OPTS).options
    i, j = torch.randint(0, 200, (64,)), torch.randint(0, 200, (64,))
    with torch.no_grad():
        net.gdf_head[-1].linear.weight.zero_()
        d0 = net.eval().distance(xyz[i], xyz[j]).double()
    lower = (table[i].double() - table[j].double()).abs().max(-1).values
    ref = torch.maximum((xyz[i] - xyz[j]).double().norm(dim=-1), floor * lower)
    torch.testing.assert_close(d0, ref, rtol=1e-6, atol=1e-6)
    with pytest.raises(InputError, match="landmark_floor"):
        NeuroGFNet(64, landmarks=8, landmark_floor=1.5, **OPTS)


def _bracket_parts(net, xyz, table, i, j):
    """(distances, floor, top, head output) of a bracket network's pairs (i, j), the bounds in float64."""
    with torch.no_grad():
        d = net.distance(xyz[i], xyz[j]).double()
        es, et = net.embed(xyz[i]), net.embed(xyz[j])
    tp, tq = table[i].double(), table[j].double()
    lower, upper = (tp - tq).abs().max(-1).values, (tp + tq).min(-1).values
    floor = torch.maximum((xyz[i] - xyz[j]).double().norm(dim=-1), lower)
    h = torch.cat([(es - et).abs(), (tp - tq).abs().float(), lower[:, None].float(), upper[:, None].float()], -1)
    with torch.no_grad():
        head = net.gdf_head(h).squeeze(-1).double()
    return d, floor, torch.maximum(upper, floor), head


def _bracket_net(seed: int, n: int, option: str):
    """A D = 64 bracket network with ``option`` on, its table set from n random points: (net, xyz, table)."""
    torch.manual_seed(seed)
    xyz = torch.rand(n, 3) * 2 - 1
    table = torch.rand(n, 8) * 3
    net = NeuroGFNet(64, landmarks=8, landmark_bracket=True, **{option: True}, **OPTS).eval()
    net.landmark_table.set_table(xyz, table)
    assert net.options[option] is True
    return net, xyz, table


def test_landmark_bracket_keeps_the_output_between_the_bounds():
    """landmark_bracket: floor + sigmoid(head) x (upper - floor) in float64, so never outside the landmarks' two
    bounds; a point pair on a piece without landmarks (every entry unreached) gets |p - q| + head."""
    from neurogf_warp.model.network import LANDMARK_UNREACHED

    torch.manual_seed(8)
    xyz = torch.rand(200, 3) * 2 - 1
    table = torch.rand(200, 8) * 3
    table[150:] = LANDMARK_UNREACHED  # the last 50 points: a piece no landmark reaches
    net = NeuroGFNet(64, landmarks=8, landmark_bracket=True, **OPTS).eval()
    net.landmark_table.set_table(xyz, table)
    assert net.options["landmark_bracket"] is True
    assert "landmark_bracket" not in NeuroGFNet(64, landmarks=8, **OPTS).options
    i, j = torch.randint(0, 150, (64,)), torch.randint(0, 150, (64,))
    d, floor, top, head = _bracket_parts(net, xyz, table, i, j)
    assert bool(((d >= floor - 1e-6) & (d <= top + 1e-6)).all())
    torch.testing.assert_close(d, floor + torch.sigmoid(head) * (top - floor), rtol=1e-5, atol=1e-6)
    k, m = torch.randint(150, 200, (16,)), torch.randint(150, 200, (16,))
    with torch.no_grad():
        far = net.distance(xyz[k], xyz[m])
        ek, em = net.embed(xyz[k]), net.embed(xyz[m])
        z = torch.zeros(16, 8)
        hk = torch.cat([(ek - em).abs(), z, z[:, :1], torch.full((16, 1), 2 * LANDMARK_UNREACHED)], -1)
        ref = (xyz[k] - xyz[m]).norm(dim=-1) + net.gdf_head(hk).squeeze(-1)
    torch.testing.assert_close(far, ref, rtol=1e-5, atol=1e-6)


def test_landmark_bracket_log_is_geometric_between_the_bounds():
    """landmark_bracket_log: floor x (upper / floor) ** sigmoid(head), against float64; the same pair gives 0 and a
    finite gradient; the form needs the bracket."""
    net, xyz, table = _bracket_net(9, 120, "landmark_bracket_log")
    assert "landmark_bracket_log" not in NeuroGFNet(64, landmarks=8, landmark_bracket=True, **OPTS).options
    i, j = torch.randint(0, 120, (64,)), torch.randint(0, 120, (64,))
    j[:4] = i[:4]  # p = q
    d, floor, top, head = _bracket_parts(net, xyz, table, i, j)
    s = torch.sigmoid(head)
    ref = torch.where(floor > 0, floor.clamp(min=1e-300) ** (1 - s) * top ** s, floor)
    torch.testing.assert_close(d, ref, rtol=1e-5, atol=1e-6)
    assert bool((d[:4] == 0).all()) and bool(((d >= floor - 1e-6) & (d <= top + 1e-6)).all())
    p = xyz[i].clone().requires_grad_(True)
    net.distance(p, xyz[j]).sum().backward()
    assert bool(torch.isfinite(p.grad).all())
    with pytest.raises(InputError, match="landmark_bracket_log"):
        NeuroGFNet(64, landmarks=8, landmark_bracket_log=True, **OPTS)


def test_landmark_pair_inputs_reach_the_head():
    """landmark_pair_inputs: the head's input also holds |p - q| and log(upper / floor) (capped), in that order."""
    from neurogf_warp.model.network import LANDMARK_WIDTH_MAX

    net, xyz, table = _bracket_net(10, 100, "landmark_pair_inputs")
    seen = []
    net.gdf_head.register_forward_hook(lambda m, args, out: seen.append(args[0]))
    i, j = torch.arange(0, 50), torch.arange(50, 100)
    j[0] = i[0]  # p = q: the width input is capped
    with torch.no_grad():
        net.distance(xyz[i], xyz[j])
    h = seen[-1].double()
    tp, tq = table[i].double(), table[j].double()
    lower, upper = (tp - tq).abs().max(-1).values, (tp + tq).min(-1).values
    e = (xyz[i] - xyz[j]).double().norm(dim=-1)
    width = torch.log(upper) - torch.log(torch.maximum(e, lower).clamp(min=1e-12))
    torch.testing.assert_close(h[:, -2], e, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(h[:, -1], width.clamp(max=LANDMARK_WIDTH_MAX), rtol=1e-5, atol=1e-5)
    assert h[0, -1] == LANDMARK_WIDTH_MAX
    with pytest.raises(InputError, match="landmark_pair_inputs"):
        NeuroGFNet(64, landmark_pair_inputs=True, **OPTS)


def test_settings_reach_the_network_and_bad_values_are_refused(monkeypatch):
    with pytest.raises(ValueError, match="training-time designs"):
        TrainConfig().set(norm="none", D=64)
    with pytest.raises(ValueError, match="training-time designs"):
        TrainConfig().set(landmarks=16, landmark_bracket=True, landmark_bracket_log=True, D=64)
    # the bracket design trains for users: its model files and fp32 queries exist
    assert TrainConfig().set(landmarks=16, landmark_bracket=True, D=64).network.build().landmark_bracket
    monkeypatch.setenv("NEUROGF_BAKEOFF_DESIGNS", "1")
    net = TrainConfig().set(norm="none", hash_levels="3", D=64).network.build()
    assert net.norm == "none" and net.hash_levels == 3
    with pytest.raises(ValueError, match="norm"):
        TrainConfig().set(norm="layer")
    with pytest.raises(ValueError, match="hash_levels"):
        TrainConfig().set(hash_levels=99)
    assert TrainConfig().set(landmarks=16, D=64).network.build().landmarks == 16
    with pytest.raises(ValueError, match="landmarks"):
        TrainConfig().set(landmarks=-1)
    assert TrainConfig().set(landmarks=16, landmark_floor="0", D=64).network.build().landmark_floor == 0.0
    assert TrainConfig().set(landmarks=16, landmark_bracket="true", D=64).network.build().landmark_bracket
    with pytest.raises(ValueError, match="landmark_floor"):
        TrainConfig().set(landmark_floor=-0.5)
    with pytest.raises(InputError, match="norm"):
        NeuroGFNet(64, norm="group")


def test_landmark_table_holds_solver_distances_and_maps_other_row_points():
    from types import SimpleNamespace

    import numpy as np
    import trimesh

    from neurogf_warp.ground_truth.geodesics import geodesic_distances
    from neurogf_warp.training.trainer import landmark_table

    s = trimesh.creation.icosphere(subdivisions=2)
    v = torch.as_tensor(np.asarray(s.vertices, np.float32))
    f = np.asarray(s.faces, np.int32)
    # rows between vertices, and rows whose end points are off the vertices (as a proxy dataset's are)
    off = v[:5] * 0.999
    rows = torch.cat([torch.cat([v[:20], v[20:40], torch.ones(20, 1)], 1),
                      torch.cat([off, v[40:45], torch.ones(5, 1)], 1)])
    data = SimpleNamespace(vertices=v, faces=f, gd={"global": rows})
    xyz, table = landmark_table(data, 6, "cpu")
    assert table.shape == (len(v) + 5, 6)
    torch.testing.assert_close(xyz[: len(v)], v, rtol=0, atol=0)
    assert sorted(map(tuple, xyz[len(v):].tolist())) == sorted(map(tuple, off.tolist()))
    # the first landmark is vertex 0: its column is that vertex's solver row (plain solve, normalized units)
    ref = geodesic_distances((v.double().numpy(), f), [0], device="cpu", near_source=False)[0]
    np.testing.assert_allclose(table[: len(v), 0].numpy(), ref, rtol=1e-6)
    net = NeuroGFNet(64, landmarks=6, **OPTS)
    net.landmark_table.set_table(xyz, table)
    # an off-vertex point takes its nearest vertex's distances (here v[i] itself)
    torch.testing.assert_close(net.landmark_table(off), table[:5], rtol=0, atol=0)
    assert torch.isfinite(net.distance(rows[:, :3], rows[:, 3:6])).all()


def test_landmarks_under_a_budget_repeat_the_solved_columns():
    from types import SimpleNamespace

    import numpy as np
    import trimesh

    from neurogf_warp.mesh.mesh import load_mesh
    from neurogf_warp.training.api import LANDMARK_SHARE, _landmark_plan
    from neurogf_warp.training.trainer import landmark_table

    s = trimesh.creation.icosphere(subdivisions=1)  # 42 vertices: fewer than the columns asked for
    v = torch.as_tensor(np.asarray(s.vertices, np.float32))
    data = SimpleNamespace(vertices=v, faces=np.asarray(s.faces, np.int32),
                           gd={"global": torch.cat([v[:10], v[10:20], torch.ones(10, 1)], 1)})
    _, t = landmark_table(data, 64, "cpu", solved=5)
    assert t.shape == (42, 64)
    torch.testing.assert_close(t[:, 5:10], t[:, :5], rtol=0, atol=0)
    assert len(torch.unique(t, dim=1).T) == 5
    _, t = landmark_table(data, 64, "cpu")
    assert t.shape == (42, 64) and len(torch.unique(t, dim=1).T) == 42
    # the plan: K without a budget; under one, as many as fit in its share (at least 8, at most K)
    cfg = TrainConfig()
    cfg.network.landmarks = 128
    mesh = load_mesh((np.asarray(s.vertices), np.asarray(s.faces)))
    cpu = torch.device("cpu")
    assert _landmark_plan(cfg, mesh, cpu, None)[0] == 128
    k, per = _landmark_plan(cfg, mesh, cpu, 1.0)
    assert k == max(8, min(128, int(LANDMARK_SHARE * 1.0 // per))) and 8 <= k <= 128
    cfg.network.landmarks = 0
    assert _landmark_plan(cfg, mesh, cpu, 60.0) == (0, 0.0)
