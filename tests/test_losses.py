"""Training losses on hand-made inputs; expected values worked out by hand in the comments."""
import pytest
import torch

from neurogf_warp.training import losses as L


def test_l1_is_mean_absolute_error():
    # |1-2| + |2-2| + |3-1| = 3, over 3 elements
    assert L.l1(torch.tensor([1.0, 2.0, 3.0]), torch.tensor([2.0, 2.0, 1.0])).item() == pytest.approx(1.0)


def test_relative_l1_is_the_mre_with_a_floor():
    # |1.1-1|/1 = 0.1; |1-0.5|/0.5 = 1.0; the target 0 counts as the floor 0.25: |0.5-0|/0.25 = 2.0
    pred, gt = torch.tensor([1.1, 1.0, 0.5]), torch.tensor([1.0, 0.5, 0.0])
    assert L.relative_l1(pred, gt, floor=0.25).item() == pytest.approx((0.1 + 1.0 + 2.0) / 3)


def test_path_l1_averages_over_all_coordinates():
    pred = torch.zeros(2, 4, 3)
    gt = torch.zeros(2, 4, 3)
    gt[0, 0, 0] = 2.4  # one coordinate off by 2.4 among 2*4*3 = 24 -> 0.1
    assert L.l1(pred, gt).item() == pytest.approx(0.1)


def test_polyline_length_and_length_loss():
    # 3-4-5 segment then a 12-long vertical one: 5 + 12 = 17
    a = torch.tensor([[[0.0, 0, 0], [3, 4, 0], [3, 4, 12]]])
    assert L.polyline_length(a).item() == pytest.approx(17.0)
    b = torch.tensor([[[0.0, 0, 0], [0, 0, 4], [0, 0, 10]]])  # length 10
    # batch of two: |17-10| = 7 and |10-10| = 0 -> mean 3.5
    assert L.length_loss(torch.cat([a, b]), torch.cat([b, b])).item() == pytest.approx(3.5)


def test_surface_loss_uses_absolute_sdf_and_passes_gradients():
    sphere = lambda x: x.norm(dim=-1) - 1.0  # unit-sphere SDF
    pts = torch.tensor([[[0.0, 0, 2.0], [0, 0, 0.5]]], requires_grad=True)  # sdf +1 and -0.5
    loss = L.surface_loss(sphere, pts)
    assert loss.item() == pytest.approx(0.75)
    loss.backward()
    # d/dz of 0.5*|z-1| at z=2 is +0.5; of 0.5*|z-1| at z=0.5 (sdf<0) is -0.5
    assert pts.grad[0, :, 2].tolist() == pytest.approx([0.5, -0.5])


def test_weighted_sum_uses_paper_weights():
    t = {"sdf": torch.tensor(1.0), "dist_g": torch.tensor(2.0), "surf": torch.tensor(3.0)}
    assert L.weighted_sum(t).item() == pytest.approx(0.1 * 1 + 1.0 * 2 + 0.1 * 3)
    assert L.weighted_sum(t, {"sdf": 2.0}).item() == pytest.approx(2 + 2 + 3)
