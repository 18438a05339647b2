"""Range images of the calibrated LiDAR map in camera frames whose pose is known: a metric depth target for camera rays.

The NeRF's LiDAR rays constrain the density along the LiDAR's own rays only; camera rays still sample out to the far
plane through density nothing supervised there, and at CPU budgets their rendered depth was off by 59 cm (median, in
the LiDAR's field) on the 320x240 street rig (``moisst-floor``). The calibrated LiDAR map seen from a camera frame whose
pose is known (the reference camera, a camera the pre-NeRF stages hold) gives each pixel the range of the surface it
sees: a dense depth prior for camera rays, as DS-NeRF (Deng et al., CVPR 2022) supervises camera rays with sparse
depth and CLONeR (Carlson et al., 2023) builds the camera rays' occupancy prior from LiDAR.

The map is sparse at pixel scale, so a far surface can show through the gaps of a near one; a pixel keeps its range
only where no range in its ``window`` x ``window`` neighbourhood is nearer by more than ``tolerance`` (the occlusion
filter of LiDAR depth projections). No nerfstudio import.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch
from jaxtyping import Float
from scipy.ndimage import minimum_filter

from moisst_ns.stages.camera.lidar_map import PinholeModel, project


def range_image(points: Float[np.ndarray, "num 3"], fx: float, fy: float, cx: float, cy: float, width: int, height: int,
                window: int = 5, tolerance: float = 0.1, layer: float = 0.02,
                distortion: Sequence[float] = (0.0,) * 6) -> Float[np.ndarray, "height width"]:
    """The range of the front surface in each pixel, occluded ranges removed.

    Args:
        points: points in the camera's frame (OpenCV axes: x right, y down, z forward), any unit.
        fx, fy, cx, cy: pinhole intrinsics, pixels (``u = fx x' + cx`` with ``x'`` the distorted ``x / z``; pixel
            column ``i`` spans ``[i, i + 1)``).
        width, height: image size, pixels.
        window: side of the neighbourhood of the occlusion filter, pixels (1: no filter).
        tolerance: a pixel's range is dropped when a range in its neighbourhood is nearer than ``range / (1 + tolerance)``.
        layer: the pixel's range is the mean over its points within ``1 + layer`` times its nearest one (the
            nearest alone is biased short on a slanted surface: 0.7 % of the range at 64x48 pixels, measured).
        distortion: OPENCV lens distortion ``k1, k2, k3, k4, p1, p2`` (nerfstudio's ``distortion_params`` order).

    Returns:
        Euclidean range from the camera centre per pixel, in the unit of ``points`` (float32); NaN where no point
        projects or the pixel's surface is occluded.
    """
    pts = points[points[:, 2] > 1e-6]
    uv, _ = project(PinholeModel(fx, fy, cx, cy, width, height, tuple(map(float, distortion))), torch.from_numpy(pts))
    u, v = np.floor(uv[:, 0].numpy()), np.floor(uv[:, 1].numpy())
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    u, v = u.astype(np.int64), v.astype(np.int64)
    pixel = v[inside] * width + u[inside]
    rng = np.linalg.norm(pts[inside], axis=1)
    nearest_in_pixel = np.full(height * width, np.inf)
    np.minimum.at(nearest_in_pixel, pixel, rng)
    front = rng <= nearest_in_pixel[pixel] * (1.0 + layer)  # the pixel's front surface, not what shows behind it
    total, count = np.zeros(height * width), np.zeros(height * width)
    np.add.at(total, pixel[front], rng[front])
    np.add.at(count, pixel[front], 1.0)
    image = np.where(count > 0, total / np.maximum(count, 1.0), np.inf).reshape(height, width)
    if window > 1:
        nearest = minimum_filter(image, size=window, mode="constant", cval=np.inf)
        image[image > nearest * (1.0 + tolerance)] = np.inf
    image[~np.isfinite(image)] = np.nan
    return image.astype(np.float32)


def opengl_to_opencv(c2w: Float[np.ndarray, "3 4"], world: Float[np.ndarray, "num 3"]) -> Float[np.ndarray, "num 3"]:
    """Points of the world in the OpenCV frame of a camera whose ``camera_to_world`` is in nerfstudio's (OpenGL)
    convention (x right, y up, looking along -z).

    Args:
        c2w: camera to world, OpenGL axes (3x4).
        world: points, world frame.

    Returns:
        The points in the camera's OpenCV frame (x right, y down, z forward), same unit.
    """
    cam = (world - c2w[:, 3]) @ c2w[:, :3]  # R^T (x - t), OpenGL axes
    return cam * np.array([1.0, -1.0, -1.0])


def rolling_camera_points(rig, frame: int, readout: float, world: Float[np.ndarray, "num 3"]) -> Float[np.ndarray, "num 3"]:
    """Points of the world in a rolling-shutter camera frame, each from the camera's prior pose at its row's time
    (``photometric.CameraModel.camera_points``), in the model's units (the frame's ``opengl_to_opencv`` points of a
    global shutter).

    Args:
        rig: the dataparser's ``RigData`` (trajectory, priors, training frames, world frame).
        frame: the training frame's index.
        readout: its camera's readout time, seconds.
        world: points, metric world frame.

    Returns:
        The points in the frame's OpenCV camera frame, model units.
    """
    from moisst_ns.stages.camera.lidar_map import PinholeModel
    from moisst_ns.stages.camera.photometric import CameraModel

    sensor = int(rig.frame_sensor_index[frame])
    camera = CameraModel(rig.trajectory(), rig.prior_extrinsics[sensor], float(rig.prior_time_offsets[sensor]), rig.frame_stamps[frame:frame + 1],
                         readout, PinholeModel.of(rig.rig.sensors[rig.sensor_names[sensor]].intrinsics))
    return camera.camera_points(np.zeros(7), world, np.zeros(len(world), dtype=np.int64)) * float(rig.world.scale)
