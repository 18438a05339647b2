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
