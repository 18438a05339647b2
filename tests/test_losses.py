"""The patch losses of paper eq. 13 on known inputs."""

import pytest
import torch

from moisst_ns.losses import depth_smoothness_loss, dssim_loss
from moisst_ns.model import hash_level_weights


def test_dssim_is_zero_for_identical_patches_and_known_for_a_constant_offset():
    patch = torch.rand(4, 5, 5, 3)
    assert float(dssim_loss(patch, patch)) == pytest.approx(0.0, abs=1e-6)
    # a constant image vs another constant: variances and covariance 0 -> SSIM = luminance term only
    a, b = torch.full((1, 4, 4, 3), 0.2), torch.full((1, 4, 4, 3), 0.6)
    c1 = 0.01**2
    ssim = (2 * 0.2 * 0.6 + c1) / (0.2**2 + 0.6**2 + c1)
    assert float(dssim_loss(a, b)) == pytest.approx((1 - ssim) / 2, rel=1e-5)
    # anti-correlated structure is maximally dissimilar in the structure term
    x = torch.linspace(0, 1, 16).view(1, 4, 4, 1).expand(1, 4, 4, 3)
    assert float(dssim_loss(x, 1 - x)) > 0.9


def test_depth_smoothness_known_values():
    flat = torch.ones(2, 3, 3)
    assert float(depth_smoothness_loss(flat)) == 0.0
    ramp = torch.arange(3.0).view(1, 1, 3).expand(1, 3, 3)  # +1 per column: 6 horizontal pairs of 1
    assert float(depth_smoothness_loss(ramp)) == pytest.approx(6.0)


def test_hash_level_release():
    w = hash_level_weights(0.0, 6, 2.0)
    assert torch.allclose(w, torch.tensor([1.0, 1.0, 0, 0, 0, 0]))
    assert torch.allclose(hash_level_weights(1.0, 6, 2.0), torch.ones(6))
    half = hash_level_weights(0.5, 6, 2.0)  # a = 4: levels 0-3 on, 4-5 off
    assert torch.allclose(half, torch.tensor([1.0, 1, 1, 1, 0, 0]))


def test_line_of_sight_loss_is_zero_only_for_mass_at_the_surface():
    from moisst_ns.losses import line_of_sight_loss

    # Four unit intervals [0,1) .. [3,4); the surface at 2.5 with a 0.5 band covers [2, 3) exactly.
    starts = torch.arange(4.0).view(1, 4, 1)
    ends = starts + 1.0
    z = torch.tensor([2.5])
    at_surface = torch.tensor([0.0, 0.0, 1.0, 0.0]).view(1, 4, 1)
    assert float(line_of_sight_loss(at_surface, starts, ends, z, 0.5)) == 0.0
    early = torch.tensor([1.0, 0.0, 0.0, 0.0]).view(1, 4, 1)  # free space is not free: counted twice
    assert float(line_of_sight_loss(early, starts, ends, z, 0.5)) == 2.0
    behind = torch.tensor([0.0, 0.0, 0.0, 1.0]).view(1, 4, 1)  # terminates behind the surface: once
    assert float(line_of_sight_loss(behind, starts, ends, z, 0.5)) == 1.0
    nothing = torch.zeros(1, 4, 1)  # the ray passes through everything
    assert float(line_of_sight_loss(nothing, starts, ends, z, 0.5)) == 1.0
    # Fractional overlap: the band [2.25, 2.75) covers half of the interval [2, 3) and a quarter of [2, 3) lies before it.
    half = torch.tensor([0.0, 0.0, 1.0, 0.0]).view(1, 4, 1)
    assert float(line_of_sight_loss(half, starts, ends, z, 0.25)) == pytest.approx(0.25 + 0.5)
    # Mean over rays.
    both = torch.cat([at_surface, early])
    assert float(line_of_sight_loss(both, torch.cat([starts, starts]), torch.cat([ends, ends]), torch.tensor([2.5, 2.5]), 0.5)) == 1.0


def test_line_of_sight_loss_gradient_moves_mass_towards_the_surface():
    from moisst_ns.losses import line_of_sight_loss

    starts = torch.arange(8.0).view(1, 8, 1)
    logits = torch.zeros(1, 8, 1, requires_grad=True)
    loss = line_of_sight_loss(torch.softmax(logits, dim=1), starts, starts + 1.0, torch.tensor([5.5]), 0.5)
    loss.backward()
    grad = logits.grad[0, :, 0]
    assert int(torch.argmin(grad)) == 5  # descending raises the weight of the surface's interval most
    assert bool((grad[:5] > 0).all())  # and lowers the free space before it


def test_guided_far_planes_end_lidar_rays_behind_their_range_only():
    from moisst_ns.model import guided_far_planes

    nears = torch.full((4, 1), 0.05)
    fars = torch.full((4, 1), 2.0)
    ranges = torch.tensor([[0.5], [0.5], [1.99], [0.01]])
    is_lidar = torch.tensor([[True], [False], [True], [True]])
    out = guided_far_planes(nears, fars, ranges, is_lidar, 0.1)
    # LiDAR ray: range + margin; camera ray: unchanged; never beyond the far plane; never before the near plane
    assert torch.allclose(out, torch.tensor([[0.6], [2.0], [2.0], [0.11]]))
    assert torch.equal(guided_far_planes(nears, fars, torch.zeros(4, 1), is_lidar, 0.0)[:, 0] > nears[:, 0], torch.ones(4, dtype=torch.bool))
