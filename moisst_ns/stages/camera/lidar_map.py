"""The calibrated LiDAR map and what cameras see of it: projection (with the rig format's OPENCV distortion),
z-buffer visibility and image pyramids. Support of ``moisst_ns.stages.camera.camera_registration``; no nerfstudio import.

Pixel convention (the rig format's and nerfstudio's): continuous coordinates from the image's top-left corner, the
centre of pixel column ``i`` at ``i + 0.5``; a pyramid level ``l`` (``2^l`` times smaller, ``cv2.pyrDown``) maps
``u`` to ``u / 2^l`` with the same convention.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
import open3d as o3d
import torch
from jaxtyping import Bool, Float, Int, UInt8
from torch import Tensor

from moisst_ns.rig.distortion import near_image, opencv_distort
from moisst_ns.rig.format import Calibration, Rig, RigFormatError, load_lidar_scan
from moisst_ns.rig.geometry import ReferenceTrajectory
from moisst_ns.stages.lidar.lidar_geometry import Extrinsic, place_points


class CameraStageError(ValueError):
    """The camera-registration stage cannot run on this input; the message is one line naming the file and field."""


class NoMapError(CameraStageError):
    """The data hold no usable map (too few triangulated features): the stage is skipped, the NeRF calibrates."""


class NoOverlapError(CameraStageError):
    """A camera sees too little of the map: it keeps its prior in this stage, the NeRF calibrates it."""


def lidar_map(rig: Rig, calibration: Calibration, voxel: float, min_range: float,
              log: Callable[[str], None] = print) -> Float[np.ndarray, "num 3"]:
    """Every scan of every LiDAR placed in the world by paper eq. 1-2 at ``calibration``, on a voxel grid.

    Args:
        rig: the dataset.
        calibration: extrinsics and time offsets of the LiDARs (the LiDAR-first estimate; the reference LiDAR at
            the identity).
        voxel: voxel size of the map, metres (one point per voxel).
        min_range: points closer to their LiDAR are dropped (returns from the vehicle), metres.
        log: where progress lines go.

    Returns:
        World points, metres (float64).

    Raises:
        CameraStageError: the rig has no LiDAR or a scan cannot be read.
    """
    traj = ReferenceTrajectory.of(rig)
    t0 = float(rig.trajectory_stamps[0])
    lidars = [n for n, s in rig.sensors.items() if s.type == "lidar"]
    if not lidars:
        raise CameraStageError(f"{rig.root / 'rig.json'}: sensors: no LiDAR to build the map from")
    chunks = []
    for name in lidars:
        T = np.asarray(calibration.T_ref_sensor[name], dtype=np.float64)
        ext = Extrinsic(T[:3, :3], T[:3, 3], float(calibration.time_offset[name]))
        for frame in rig.frames_of(name):
            try:
                points, offsets, _ = load_lidar_scan(rig.root / frame.file_path, min_range=min_range)
            except RigFormatError as err:
                raise CameraStageError(str(err)) from None
            times = frame.timestamp - t0 + (offsets if offsets is not None else np.zeros(len(points)))
            chunks.append(place_points(traj, ext, points.astype(np.float64), times))
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.concatenate(chunks)))
    world = np.asarray(cloud.voxel_down_sample(voxel).points)
    log(f"[camera-registration] LiDAR map: {len(world)} points ({voxel * 100:.0f} cm voxels) from {len(chunks)} scans of {', '.join(lidars)}")
    return world


@dataclass
class PinholeModel:
    """A camera's intrinsics at one pyramid level (rig format names; distortion as nerfstudio's OPENCV model)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: Tuple[float, float, float, float, float, float] = (0.0,) * 6
    """``k1, k2, k3, k4, p1, p2``."""

    @classmethod
    def of(cls, intrinsics: Dict[str, object], factor: int = 1) -> "PinholeModel":
        """The model of rig.json ``intrinsics`` at a level ``factor`` times smaller."""
        dist = tuple(float(intrinsics.get(k, 0.0)) for k in ("k1", "k2", "k3", "k4", "p1", "p2"))
        return cls(float(intrinsics["fl_x"]) / factor, float(intrinsics["fl_y"]) / factor, float(intrinsics["cx"]) / factor,
                   float(intrinsics["cy"]) / factor, int(intrinsics["w"]) // factor, int(intrinsics["h"]) // factor, dist)


def project(model: PinholeModel, cam: Float[Tensor, "num 3"]) -> Tuple[Float[Tensor, "num 2"], Float[Tensor, "num"]]:
    """Pixel coordinates and depth of points in a camera's frame (OpenCV axes: x right, y down, z forward).

    Args:
        model: intrinsics.
        cam: points in the camera frame, metres.

    Returns:
        (``(u, v)`` pixels, continuous from the top-left corner; depth ``z``, metres). Points with ``z <= 0`` get
        finite but meaningless pixels: mask them with the depth. A point beyond the image's 50 % margin keeps its
        pinhole pixel, outside the image (``rig.distortion.near_image``: the lens polynomial folds back there).
    """
    z = cam[:, 2]
    safe = torch.where(z > 1e-6, z, torch.ones_like(z))
    x, y = cam[:, 0] / safe, cam[:, 1] / safe
    if any(model.distortion):
        near = near_image(x, y, model.fx, model.fy, model.cx, model.cy, model.width, model.height)
        xd, yd = opencv_distort(x, y, *model.distortion)
        x, y = torch.where(near, xd, x), torch.where(near, yd, y)
    return torch.stack([model.fx * x + model.cx, model.fy * y + model.cy], dim=-1), z


def world_to_camera(world_T_cam: Float[Tensor, "num 4 4"], points: Float[Tensor, "num 3"]) -> Float[Tensor, "num 3"]:
    """``R^T (x - t)`` for each point with its own pose (``bmm``: under ``jacfwd`` 6x faster than ``einsum``)."""
    return torch.bmm((points - world_T_cam[:, :3, 3])[:, None, :], world_T_cam[:, :3, :3])[:, 0]


def visible(uv: Float[np.ndarray, "num 2"], depth: Float[np.ndarray, "num"], model: PinholeModel, max_depth: float = 40.0, cell: int = 4,
            margin_m: float = 0.3, margin_fraction: float = 0.03) -> Bool[np.ndarray, "num"]:
    """Which of a frame's projected map points are not hidden behind other map points (a z-buffer).

    The nearest depth is kept per ``cell`` x ``cell`` pixel block and spread to the 8 neighbouring blocks (the map
    is sparse: a background point must not shine through the gaps of a foreground surface); a point is visible
    when it is within ``margin_m + margin_fraction * depth`` of that nearest depth.

    Args:
        uv: pixel coordinates (full resolution).
        depth: camera depths, metres.
        model: intrinsics (full resolution).
        max_depth: points farther than this are not used, metres (``CameraRegistrationConfig.max_depth``'s default).
        cell: z-buffer block size, full-resolution pixels.
        margin_m: absolute depth tolerance, metres.
        margin_fraction: relative depth tolerance.

    Returns:
        Mask of visible points inside the image.
    """
    from scipy.ndimage import minimum_filter

    inside = (depth > 0.1) & (depth < max_depth) & (uv[:, 0] >= 0) & (uv[:, 0] < model.width) & (uv[:, 1] >= 0) & (uv[:, 1] < model.height)
    nx, ny = -(-model.width // cell), -(-model.height // cell)
    key = np.zeros(len(depth), dtype=np.int64)
    key[inside] = (uv[inside, 1] // cell).astype(np.int64) * nx + (uv[inside, 0] // cell).astype(np.int64)
    zmin = np.full(nx * ny, np.inf)
    np.minimum.at(zmin, key[inside], depth[inside])
    zmin = minimum_filter(zmin.reshape(ny, nx), size=3, mode="nearest").ravel()
    return inside & (depth <= zmin[key] + margin_m + margin_fraction * depth)


def pyramid_factors(width: int, min_width: int) -> List[int]:
    """Downsampling factors, coarse to fine, down to 1: halving while the image stays at least ``min_width`` wide."""
    factors = [1]
    while width // (factors[-1] * 2) >= min_width:
        factors.append(factors[-1] * 2)
    return factors[::-1]


@dataclass
class ImageStack:
    """One camera's frames at one pyramid level: standardised grey images and their gradients."""

    intensity: Float[np.ndarray, "frames h w"]
    """Grey level, zero mean and unit standard deviation per image (exposure differences cancel)."""
    gradient: Float[np.ndarray, "frames 2 h w"]
    """``d I / d u`` and ``d I / d v``, per pixel of this level."""
    model: PinholeModel

    @classmethod
    def of(cls, images: Float[np.ndarray, "frames h w"], model: PinholeModel) -> "ImageStack":
        """``images`` (float32) with their gradients."""
        gy, gx = np.gradient(images, axis=(1, 2))
        return cls(images, np.stack([gx, gy], axis=1).astype(np.float32), model)


def read_grey(rig: Rig, sensor: str, file_path: str) -> UInt8[np.ndarray, "h w"]:
    """One frame of a camera as 8-bit grey.

    Raises:
        CameraStageError: the image is missing, unreadable or not of the size rig.json gives.
    """
    import cv2

    intr, path = rig.sensors[sensor].intrinsics, rig.root / file_path
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) if path.is_file() else None
    if image is None:
        raise CameraStageError(f"{path}: file_path: missing or not an image")
    if image.shape != (int(intr["h"]), int(intr["w"])):
        raise CameraStageError(f"{path}: size {image.shape[1]}x{image.shape[0]} is not rig.json's {intr['w']}x{intr['h']} (sensors.{sensor}.intrinsics)")
    return image


def load_pyramid(rig: Rig, sensor: str, files: Sequence[str], factors: Sequence[int]) -> Dict[int, ImageStack]:
    """Every frame of a camera as grey images at each factor of ``factors`` (``cv2.pyrDown``, Gaussian 5x5).

    Raises:
        CameraStageError: an image is missing, unreadable or not of the size rig.json gives.
    """
    import cv2

    levels: Dict[int, List[np.ndarray]] = {f: [] for f in factors}
    for rel in files:
        level, factor = read_grey(rig, sensor, rel).astype(np.float32) / 255.0, 1
        while True:
            if factor in levels:
                levels[factor].append((level - level.mean()) / max(float(level.std()), 1e-3))
            if factor >= max(factors):
                break
            level, factor = cv2.pyrDown(level), factor * 2
    return {f: ImageStack.of(np.stack(images), PinholeModel.of(rig.sensors[sensor].intrinsics, f)) for f, images in levels.items()}


def bilinear(stack: ImageStack, frame: Int[np.ndarray, "num"], uv: Float[np.ndarray, "num 2"]) -> Tuple[
        Float[np.ndarray, "num"], Float[np.ndarray, "num 2"], Bool[np.ndarray, "num"]]:
    """Intensity and gradient of each point's frame at ``uv`` (this level's pixels), bilinear.

    Returns:
        (intensity, gradient ``(dI/du, dI/dv)``, inside: the 2x2 neighbourhood is within the image; values of
        points outside are 0).
    """
    _, h, w = stack.intensity.shape
    x, y = uv[:, 0] - 0.5, uv[:, 1] - 0.5
    ok = np.isfinite(x) & np.isfinite(y) & (x >= 0) & (y >= 0) & (x < w - 1) & (y < h - 1)
    x, y = np.where(ok, x, 0.0), np.where(ok, y, 0.0)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = x - x0, y - y0
    weights = [((1 - fx) * (1 - fy), 0, 0), (fx * (1 - fy), 1, 0), ((1 - fx) * fy, 0, 1), (fx * fy, 1, 1)]
    value, grad = np.zeros(len(x)), np.zeros((len(x), 2))
    for wgt, dx, dy in weights:
        value += wgt * stack.intensity[frame, y0 + dy, x0 + dx]
        grad += wgt[:, None] * stack.gradient[frame, :, y0 + dy, x0 + dx]
    return np.where(ok, value, 0.0), np.where(ok[:, None], grad, 0.0), ok


def map_source(rig: Rig, lidar_undetermined: Optional[Dict[str, Sequence[str]]] = None) -> Tuple[str, str]:
    """What the cameras are registered against, and why when it is not the LiDAR on a rig with one.

    The LiDAR map places its points with the LiDAR-first estimate, so a LiDAR parameter its scans' motion did not
    determine (``LidarResult.motion_undetermined``: held at its prior, or a split-half sigma above a typical prior error)
    moves the whole map by about its prior error, and every camera registered against it inherits that error under a
    sigma that cannot see it (KITTI raw 0048: the Velodyne's along-track lever arm held 50 cm off; image_03 then 27 cm
    off). That stage's depth edges' view may place such a parameter, but only the cameras registered without the LiDAR
    can check it at the shared instants (``lidar_placement.place_lidars``; the view placed KITTI's Velodyne 33 cm off in
    x under a sigma of 3 cm from the converter's ``--seed 1`` prior, and image_01 ended 4.4 cm off on its map). The
    reference camera's features, triangulated from its known poses, carry only the trajectory's error: the map where a
    LiDAR is undetermined and the reference sensor is a camera (docs/method.md, "The cameras' map").

    Returns:
        ``("lidar", "")``, or ``("features", why)`` (``why`` empty on a rig without a LiDAR).
    """
    lidars = [n for n, s in rig.sensors.items() if s.type == "lidar"]
    if not lidars:
        return "features", ""
    unknown = {n: list(w) for n, w in (lidar_undetermined or {}).items() if n in lidars and w}
    if not unknown or rig.sensors[rig.reference_sensor].type != "camera":
        return "lidar", ""
    return "features", ("the LiDAR-first stage's scans' motion left " + "; ".join(f"{n}'s {', '.join(w)}" for n, w in unknown.items())
                        + " undetermined, which a LiDAR map would pass on to every camera")
