"""Pinhole projection and drawing helpers of the diagnostics report (LiDAR points over images). No nerfstudio."""

from __future__ import annotations

from typing import Any, List, Mapping, Sequence, Tuple

import numpy as np
from jaxtyping import Bool, Float, UInt8


COLORMAP = "turbo"
"""matplotlib colormap of the depth colouring (near = blue, far = red)."""


def project_points(
    points_world: Float[np.ndarray, "num 3"],
    world_T_cam: Float[np.ndarray, "4 4"],
    intrinsics: Mapping[str, Any],
    min_depth: float = 1e-3,
) -> Tuple[Float[np.ndarray, "num 2"], Float[np.ndarray, "num"], Bool[np.ndarray, "num"]]:
    """Project world points into a camera (OpenCV axes: x right, y down, z forward) with the stages' projection
    (``lidar_map.project``: OpenCV distortion when any ``k1, k2, k3, k4, p1, p2`` is non-zero; continuous pixels from
    the image's top-left corner, the centre of pixel column ``i`` at ``i + 0.5``, as in the rig format and nerfstudio).

    Args:
        points_world: points in the world frame, metres.
        world_T_cam: the camera's pose (maps camera coordinates to world coordinates).
        intrinsics: rig.json's ``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``, ``h`` and optionally the distortion.
        min_depth: points with camera depth ``z <= min_depth`` are behind (or on) the camera.

    Returns:
        (uv pixel coordinates (NaN for points behind the camera), depth ``z`` in the camera frame (metres, negative
        behind), mask of points in front of the camera and inside ``[0, w) x [0, h)``).
    """
    import torch

    from moisst_ns.stages.camera.lidar_map import PinholeModel, project

    pose = np.asarray(world_T_cam, dtype=np.float64)
    cam = (np.asarray(points_world, dtype=np.float64).reshape(-1, 3) - pose[:3, 3]) @ pose[:3, :3]  # R^T (p - t)
    model = PinholeModel.of(intrinsics)
    uv, z = (t.numpy() for t in project(model, torch.from_numpy(cam)))
    front = z > min_depth
    uv[~front] = np.nan
    mask = front & (uv[:, 0] >= 0) & (uv[:, 0] < model.width) & (uv[:, 1] >= 0) & (uv[:, 1] < model.height)
    return uv, z, mask


def depth_colors(depth: Float[np.ndarray, "num"], vmin: float, vmax: float, cmap: str = COLORMAP) -> UInt8[np.ndarray, "num 3"]:
    """RGB colours of depths through a matplotlib colormap, ``vmin`` -> low end, ``vmax`` -> high end (clipped).

    Args:
        depth: depths, metres.
        vmin: depth of the colormap's low end.
        vmax: depth of the colormap's high end.
        cmap: matplotlib colormap name.

    Returns:
        8-bit colours.
    """
    import matplotlib

    t = np.clip((np.asarray(depth, dtype=np.float64) - vmin) / max(vmax - vmin, 1e-9), 0.0, 1.0)
    return (matplotlib.colormaps[cmap](t)[:, :3] * 255.0 + 0.5).astype(np.uint8)


def depth_range(*depths: np.ndarray) -> Tuple[float, float]:
    """A robust common colour range (2nd and 98th percentiles) of several depth arrays; (0, 1) when empty."""
    values = np.concatenate([np.asarray(d, dtype=np.float64).ravel() for d in depths] + [np.zeros(0)])
    values = values[np.isfinite(values)]
    if values.size == 0:
        return 0.0, 1.0
    lo, hi = np.percentile(values, [2.0, 98.0])
    return float(lo), float(max(hi, lo + 1e-6))


def draw_points(
    image: UInt8[np.ndarray, "h w 3"],
    uv: Float[np.ndarray, "num 2"],
    depth: Float[np.ndarray, "num"],
    mask: Bool[np.ndarray, "num"],
    vmin: float,
    vmax: float,
    radius: int = 0,
) -> UInt8[np.ndarray, "h w 3"]:
    """Draw projected points as squares of side ``2 radius + 1`` coloured by depth, nearest on top (z-buffer).

    Args:
        image: the camera image (not modified).
        uv: pixel coordinates (``project_points``' convention: pixel ``(floor(u), floor(v))``).
        depth: camera depth of each point.
        mask: points to draw.
        vmin: depth of the colormap's low end.
        vmax: depth of the colormap's high end.
        radius: half size of the drawn squares, pixels.

    Returns:
        A copy of ``image`` with the points drawn.
    """
    out = np.array(image, dtype=np.uint8, copy=True)
    h, w = out.shape[:2]
    idx = np.flatnonzero(mask)
    if idx.size == 0:
        return out
    colors = depth_colors(depth[idx], vmin, vmax)
    col, row = np.floor(uv[idx, 0]).astype(np.int64), np.floor(uv[idx, 1]).astype(np.int64)
    d_row, d_col = np.meshgrid(np.arange(-radius, radius + 1), np.arange(-radius, radius + 1), indexing="ij")
    rows, cols = (row[:, None] + d_row.ravel()).ravel(), (col[:, None] + d_col.ravel()).ravel()
    point = np.repeat(np.arange(len(idx)), d_row.size)
    inside = (cols >= 0) & (cols < w) & (rows >= 0) & (rows < h)
    pixel, point = rows[inside] * w + cols[inside], point[inside]
    order = np.lexsort((depth[idx][point], pixel))  # per pixel, nearest point first
    pixel, point = pixel[order], point[order]
    first = np.unique(pixel, return_index=True)[1]
    out.reshape(-1, 3)[pixel[first]] = colors[point[first]]
    return out


def side_by_side(left: np.ndarray, right: np.ndarray, labels: Sequence[str] = ("prior", "calibrated"), gap: int = 4) -> np.ndarray:
    """Two images of the same size next to each other, with a caption strip above each (Pillow's default font)."""
    from PIL import Image, ImageDraw

    h, w = left.shape[:2]
    strip = 14
    canvas = Image.new("RGB", (2 * w + gap, h + strip), (255, 255, 255))
    canvas.paste(Image.fromarray(left), (0, strip))
    canvas.paste(Image.fromarray(right), (w + gap, strip))
    draw = ImageDraw.Draw(canvas)
    for k, label in enumerate(labels):
        draw.text((k * (w + gap) + 2, 1), label, fill=(0, 0, 0))
    return np.asarray(canvas)


def pick_evenly(num: int, count: int) -> List[int]:
    """``count`` indices spread evenly over ``range(num)`` (first and last included), without repeats."""
    if num <= 0 or count <= 0:
        return []
    return sorted(set(np.linspace(0, num - 1, min(count, num)).round().astype(int).tolist()))
