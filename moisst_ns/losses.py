"""The losses of paper eq. 7 and 13 beyond nerfacto's colour loss (LiDAR depth, DSSIM, depth smoothness) and the
LiDAR map's range on camera rays, as pure torch functions.

Patches come from nerfstudio's ``PatchPixelSampler`` (``datamanager.patch_size > 1``), which orders the camera
rays of a batch as (num_patches, patch, patch).
"""

from __future__ import annotations

import torch
from jaxtyping import Float
from torch import Tensor


def dssim_loss(
    pred: Float[Tensor, "num_patches patch patch 3"], target: Float[Tensor, "num_patches patch patch 3"], c1: float = 0.01**2, c2: float = 0.03**2
) -> Float[Tensor, ""]:
    """Structural dissimilarity ``(1 - SSIM) / 2`` of each patch (one SSIM window = the whole patch), averaged.

    Args:
        pred: rendered colours in [0, 1].
        target: image colours in [0, 1].
        c1: SSIM luminance constant ((0.01 L)^2, L = 1).
        c2: SSIM contrast constant ((0.03 L)^2).

    Returns:
        Mean DSSIM over patches and channels, in [0, 1].
    """
    dims = (1, 2)
    mu_p, mu_t = pred.mean(dims), target.mean(dims)
    var_p = pred.var(dims, unbiased=False)
    var_t = target.var(dims, unbiased=False)
    cov = ((pred - mu_p[:, None, None]) * (target - mu_t[:, None, None])).mean(dims)
    ssim = ((2 * mu_p * mu_t + c1) * (2 * cov + c2)) / ((mu_p**2 + mu_t**2 + c1) * (var_p + var_t + c2))
    return ((1.0 - ssim) / 2.0).mean()


def depth_smoothness_loss(depth: Float[Tensor, "num_patches patch patch"]) -> Float[Tensor, ""]:
    """RegNeRF's depth smoothness: squared differences between horizontally and vertically adjacent depths.

    Args:
        depth: rendered depth of each patch.

    Returns:
        Sum over neighbours within a patch, averaged over patches.
    """
    dx = (depth[:, :, 1:] - depth[:, :, :-1]).pow(2).sum((1, 2))
    dy = (depth[:, 1:, :] - depth[:, :-1, :]).pow(2).sum((1, 2))
    return (dx + dy).mean()


def lidar_depth_loss(expected_depth: Float[Tensor, "num_rays"], measured_range: Float[Tensor, "num_rays"]) -> Float[Tensor, ""]:
    """Paper eq. 7: squared error between the rendered (expected) depth of a LiDAR ray and the measured range.

    Args:
        expected_depth: volume-rendered expected distance along each unit-direction LiDAR ray (model units).
        measured_range: the LiDAR's range for that ray, same units.

    Returns:
        The mean squared error, in those units squared (the paper's normalised depths).
    """
    return (expected_depth - measured_range.to(expected_depth)).pow(2).mean()


def map_range_loss(expected_depth: Float[Tensor, "num_rays"], map_range: Float[Tensor, "num_rays"], units_per_metre: float,
                   delta_m: float = 0.2) -> Float[Tensor, ""]:
    """Metric depth loss of camera rays against the LiDAR map's range (``stages.map_range``): Huber in metres.

    Args:
        expected_depth: volume-rendered expected distance along each unit-direction camera ray, model units.
        map_range: the map's range for the same pixel, model units; NaN where the map has none (left out).
        units_per_metre: model units in a metre (the dataparser's ``world_scale``).
        delta_m: Huber threshold, metres: quadratic below, linear above (a pixel on a depth edge of the map is
            an outlier, not a target to chase).

    Returns:
        The mean Huber loss over the rays with a range, square metres (0 when none has one).
    """
    target = map_range.to(expected_depth)
    valid = torch.isfinite(target)
    if not bool(valid.any()):
        return expected_depth.sum() * 0.0
    error = (expected_depth[valid] - target[valid]) / units_per_metre
    return torch.nn.functional.huber_loss(error, torch.zeros_like(error), delta=delta_m)
