"""The OPENCV lens distortion of the rig format (nerfstudio's OPENCV model: radial ``k1..k4``, tangential ``p1, p2``).

Plain arithmetic, so the same function serves numpy arrays (report images) and torch tensors (the camera-registration
stage's differentiable projection). No torch, no nerfstudio import.
"""

from __future__ import annotations

from typing import Tuple, TypeVar

Array = TypeVar("Array")


def opencv_distort(x: Array, y: Array, k1: float, k2: float, k3: float, k4: float, p1: float, p2: float) -> Tuple[Array, Array]:
    """Distort normalised image coordinates (``x = X / Z``, ``y = Y / Z``, OpenCV axes).

    Args:
        x, y: undistorted normalised coordinates (numpy arrays or torch tensors of one shape).
        k1, k2, k3, k4: radial coefficients (``1 + k1 r + k2 r^2 + k3 r^3 + k4 r^4`` with ``r = x^2 + y^2``).
        p1, p2: tangential coefficients.

    Returns:
        The distorted ``(x, y)``, of the input's type.
    """
    r = x * x + y * y
    d = 1.0 + r * (k1 + r * (k2 + r * (k3 + r * k4)))
    return x * d + 2.0 * p1 * x * y + p2 * (r + 2.0 * x * x), y * d + 2.0 * p2 * x * y + p1 * (r + 2.0 * y * y)


def near_image(x: Array, y: Array, fx: float, fy: float, cx: float, cy: float, width: float, height: float) -> Array:
    """Which undistorted normalised coordinates lie within a 50 % margin of the image (pinhole pixels in
    ``(-w/2, 3w/2) x (-h/2, 3h/2)``): the distortion polynomial folds back far outside the image, so only these may be
    trusted through ``opencv_distort``.

    Args:
        x, y: undistorted normalised coordinates.
        fx, fy, cx, cy: pinhole intrinsics, pixels.
        width, height: image size, pixels.

    Returns:
        Boolean mask of the input's type (False for non-finite coordinates).
    """
    u, v = fx * x + cx, fy * y + cy
    return (u > -0.5 * width) & (u < 1.5 * width) & (v > -0.5 * height) & (v < 1.5 * height)
