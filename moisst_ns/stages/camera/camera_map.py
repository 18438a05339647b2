"""A metric map without a LiDAR: image features of the reference camera triangulated from its known poses.

The reference camera's poses are the reference trajectory (eq. 1-2 with the identity extrinsic and no offset), so
features matched between two of its frames (SIFT, Lowe's ratio test, ``cv2``) triangulate to metric world points
(``cv2.triangulatePoints`` on undistorted, normalised coordinates). A point is kept when it lies in front of both
frames, reprojects within ``max_reprojection_px`` in both, and is seen under at least ``min_parallax_deg`` (depth
from small parallax is noise); with ``confirmed`` it must also land within ``max_reprojection_px`` of the keypoint
matched in a third frame (a car driving along the frames' baselines triangulates in every pair of them, each at another
depth: ``camera_registration.map_part``). ``camera_registration`` then registers the other cameras against these points as
it does against a LiDAR map. A feature sits at the centre of a blob, where the image gradient vanishes and a
photometric residual is flat to first order; each point therefore brings a ring of points around it
(``patch_points``: DSO's residual pattern, Engel et al. 2017, on the blob's flanks where the gradient is). Measured on
the camera-only plaza rig of seed 1 (docs/method.md, "Without a LiDAR"): the forward-right camera's time offset
went from 5.1 ms off with the bare features to 0.10 ms with a 2-pixel ring (1.57 ms at 1 pixel, 0.14 at 3). No
nerfstudio import.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, List, Sequence, Tuple

import numpy as np
import open3d as o3d
import torch
from jaxtyping import Float, UInt8

from moisst_ns.rig.format import Calibration, Rig
from moisst_ns.rig.geometry import ReferenceTrajectory, row_time
from moisst_ns.stages.camera.lidar_map import CameraStageError, NoMapError, PinholeModel, project, read_grey


@dataclass
class FeatureMapConfig:
    """Settings of the reference camera's feature map."""

    features: int = 2000
    """SIFT features per frame."""
    ratio: float = 0.75
    """Lowe's ratio test of the nearest and second-nearest descriptor distances."""
    max_gap: int = 4
    """Each frame is matched with the next ``max_gap`` frames."""
    min_parallax_deg: float = 2.0
    """Least angle between the two viewing rays of a triangulated point, degrees."""
    max_reprojection_px: float = 1.0
    """Largest reprojection error in either frame, pixels."""
    confirmed: bool = False
    """Keep only the points that also project within ``max_reprojection_px`` of the keypoint matched in a third frame
    (``camera_registration.map_part``)."""
    voxel: float = 0.05
    """One point per voxel of this size, metres."""
    patch_points: int = 8
    """Points on the ring around each triangulated feature (0: the bare features)."""
    patch_radius_px: float = 2.0
    """Radius of that ring in the reference frame nearest the feature, undistorted pixels."""


def camera_matrix(intr: dict) -> np.ndarray:
    return np.array([[float(intr["fl_x"]), 0.0, float(intr["cx"]) - 0.5], [0.0, float(intr["fl_y"]), float(intr["cy"]) - 0.5], [0.0, 0.0, 1.0]])


def distortion(intr: dict) -> np.ndarray:
    return np.array([float(intr.get(k, 0.0)) for k in ("k1", "k2", "p1", "p2", "k3")])


def patch_points(world: Float[np.ndarray, "num 3"], poses: Float[np.ndarray, "frames 4 4"], model: PinholeModel,
                 count: int, radius_px: float) -> Float[np.ndarray, "total 3"]:
    """Each map point followed by ``count`` points on a ring of ``radius_px`` pixels around it (DSO's pattern).

    The ring lies in the frame of ``poses`` that sees the point nearest (in front, inside the image), on the plane
    parallel to that image at the point's depth: the points project there at ``radius_px`` from the point, evenly
    spaced in angle. A point no frame sees keeps no ring.

    Args:
        world: map points, world frame, metres.
        poses: ``world_T_camera`` of the frames the points were seen in.
        model: the frames' intrinsics (the ring is in undistorted pixels: ``fx``, ``fy``).
        count: points per ring (0 returns ``world``).
        radius_px: ring radius, pixels.

    Returns:
        ``world`` followed by the rings, metres.
    """
    if count <= 0 or len(world) == 0:
        return world
    cam = np.einsum("fji,nfj->nfi", poses[:, :3, :3], world[:, None, :] - poses[None, :, :3, 3])  # R^T (x - t), (num, frames, 3)
    z = cam[..., 2]
    u = model.fx * cam[..., 0] / np.where(z > 1e-6, z, 1.0) + model.cx
    v = model.fy * cam[..., 1] / np.where(z > 1e-6, z, 1.0) + model.cy
    seen = (z > 0.5) & (u >= 0) & (u <= model.width) & (v >= 0) & (v <= model.height)
    has = seen.any(axis=1)
    anchor = np.argmin(np.where(seen, z, np.inf), axis=1)[has]
    centre = cam[has, anchor]  # (m, 3)
    angle = 2.0 * np.pi * np.arange(count) / count
    offset = np.stack([radius_px / model.fx * np.cos(angle), radius_px / model.fy * np.sin(angle), np.zeros(count)], axis=-1)  # per unit depth
    ring = centre[:, None, :] + centre[:, None, 2:3] * offset[None]  # (m, count, 3) in the anchor camera
    pose = poses[anchor]
    ring_world = np.einsum("mij,mkj->mki", pose[:, :3, :3], ring) + pose[:, None, :3, 3]
    return np.concatenate([world, ring_world.reshape(-1, 3)])


def triangulate(proj_a: Float[np.ndarray, "n 3 4"], proj_b: Float[np.ndarray, "n 3 4"], xy_a: Float[np.ndarray, "n 2"],
                xy_b: Float[np.ndarray, "n 2"]) -> Float[np.ndarray, "n 3"]:
    """Linear (DLT) triangulation of matches each seen from its own pair of poses (``cv2.triangulatePoints`` with a
    projection matrix per match: a rolling shutter's rows).

    Args:
        proj_a, proj_b: ``camera_T_world[:3]`` of each match's two observations.
        xy_a, xy_b: their normalised (undistorted) image coordinates.

    Returns:
        World points (nan where the solution is at infinity).
    """
    rows = [xy[:, k:k + 1] * proj[:, 2] - proj[:, k] for proj, xy in ((proj_a, xy_a), (proj_b, xy_b)) for k in (0, 1)]
    hom = np.linalg.svd(np.stack(rows, axis=1))[2][:, -1]
    return hom[:, :3] / np.where(np.abs(hom[:, 3:]) > 1e-12, hom[:, 3:], np.nan)


def sift(image: UInt8[np.ndarray, "h w"], features: int) -> Tuple[Float[np.ndarray, "k 2"], np.ndarray]:
    """SIFT keypoints of an 8-bit grey image (OpenCV pixel convention, centre of column ``i`` at ``i``) and their
    descriptors ((0, 128) when there are none). OpenCV's SIFT puts its keypoints 0.25 px right of and below the
    feature (opencv/opencv#23123: the octave -1 upsampling's half-pixel shift, halved); they are moved back."""
    import cv2

    kp, desc = cv2.SIFT_create(nfeatures=features).detectAndCompute(image, None)
    return np.array([k.pt for k in kp], dtype=np.float64).reshape(-1, 2) - 0.25, desc if desc is not None else np.zeros((0, 128), np.float32)


def sift_frames(rig: Rig, frames: Sequence, features: int, downscale: int = 1) -> Tuple[List[np.ndarray], List[np.ndarray]]:
    """``sift`` of each frame's grey image (``lidar_map.read_grey``), found on the image shrunk ``downscale`` times
    (pixel areas averaged): keypoints (in the full image's pixels) and descriptors.

    Raises:
        CameraStageError: an image cannot be read.
    """
    import cv2

    def shrunk(image: np.ndarray) -> np.ndarray:
        return image if downscale == 1 else cv2.resize(image, (image.shape[1] // downscale, image.shape[0] // downscale), interpolation=cv2.INTER_AREA)

    found = [sift(shrunk(read_grey(rig, frame.sensor, frame.file_path)), features) for frame in frames]
    return [downscale * k + (downscale - 1) / 2 for k, _ in found], [d for _, d in found]


def ratio_matches(desc_a: np.ndarray, desc_b: np.ndarray, ratio: float) -> Tuple[np.ndarray, np.ndarray]:
    """Indices ``(ia, ib)`` of the descriptors of ``a`` whose nearest in ``b`` passes Lowe's ratio test."""
    import cv2

    if desc_a is None or desc_b is None or len(desc_a) < 2 or len(desc_b) < 2:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    good = [m for m, n in (p for p in cv2.BFMatcher(cv2.NORM_L2).knnMatch(desc_a, desc_b, k=2) if len(p) == 2) if m.distance < ratio * n.distance]
    return np.array([m.queryIdx for m in good], dtype=np.int64), np.array([m.trainIdx for m in good], dtype=np.int64)


def feature_map(rig: Rig, calibration: Calibration, config: FeatureMapConfig, log: Callable[[str], None] = print) -> Float[np.ndarray, "num 3"]:
    """Triangulated SIFT features of the reference camera, world frame, metres.

    Args:
        rig: the dataset (its reference sensor must be a camera).
        calibration: the calibration (the reference camera's extrinsic and offset, normally identity and 0).
        config: settings.
        log: where progress lines go.

    Returns:
        World points on a ``config.voxel`` grid, each followed by its ring (``patch_points``).

    Raises:
        CameraStageError: the reference sensor is not a camera or an image cannot be read; ``NoMapError`` when
            fewer than 50 points triangulate.
    """
    import cv2

    name = rig.reference_sensor
    spec = rig.sensors[name]
    if spec.type != "camera":
        raise CameraStageError(f"{rig.root / 'rig.json'}: reference_sensor: {name} is a {spec.type}; a map without a LiDAR needs a camera reference")
    frames = sorted(rig.frames_of(name), key=lambda f: f.timestamp)
    traj = ReferenceTrajectory.of(rig)
    stamps = torch.tensor([f.timestamp for f in frames], dtype=torch.float64) - float(rig.trajectory_stamps[0])
    T = torch.from_numpy(np.asarray(calibration.T_ref_sensor[name], dtype=np.float64))
    poses = (traj(stamps + float(calibration.time_offset[name])) @ T).numpy()
    readout, height = float(spec.readout_time), int(spec.intrinsics["h"])

    def pose_at(f: int, i: np.ndarray) -> np.ndarray:
        """Frame ``f``'s pose for its keypoints ``i``: at each keypoint's row's time (a rolling shutter), (n, 4, 4)."""
        if not readout:
            return np.broadcast_to(poses[f], (len(i), 4, 4))
        t = stamps[f] + float(calibration.time_offset[name]) + torch.from_numpy(row_time(keys[f][i, 1] + 0.5, readout, height))
        return (traj(t) @ T).numpy()

    K, dist = camera_matrix(spec.intrinsics), distortion(spec.intrinsics)
    model = PinholeModel.of(spec.intrinsics)
    keys, descs = sift_frames(rig, frames, config.features)

    def reprojects(world: np.ndarray, f: int, i: np.ndarray) -> np.ndarray:
        """Which of ``world`` lie in front of frame ``f`` and project within ``max_reprojection_px`` of its keypoints ``i``."""
        pose = pose_at(f, i)
        cam = np.einsum("nji,nj->ni", pose[:, :3, :3], np.nan_to_num(world) - pose[:, :3, 3])
        uv, z = project(model, torch.from_numpy(cam))
        return (z.numpy() > 0.5) & (np.linalg.norm(uv.numpy() - (keys[f][i] + 0.5), axis=1) < config.max_reprojection_px)

    points = []
    for a in range(len(frames)):
        pairs = {}  # partner frame b -> (ia, ib, world, ok): frame a's keypoints ia matched in b, triangulated
        for b in range(a + 1, min(a + 1 + config.max_gap, len(frames))):
            ia, ib = ratio_matches(descs[a], descs[b], config.ratio)
            if len(ia) < 8:
                continue
            norm = [cv2.undistortPoints(keys[f][i].reshape(-1, 1, 2), K, dist).reshape(-1, 2) for f, i in ((a, ia), (b, ib))]
            if readout:
                seen = [pose_at(f, i) for f, i in ((a, ia), (b, ib))]
                world = triangulate(np.linalg.inv(seen[0])[:, :3], np.linalg.inv(seen[1])[:, :3], norm[0], norm[1])
            else:
                proj = [np.linalg.inv(poses[f])[:3] for f in (a, b)]
                hom = cv2.triangulatePoints(proj[0], proj[1], norm[0].T, norm[1].T)
                world = (hom[:3] / np.where(np.abs(hom[3]) > 1e-12, hom[3], np.nan)).T
            ok = np.all(np.isfinite(world), axis=1)
            for f, i in ((a, ia), (b, ib)):
                ok &= reprojects(world, f, i)
            rays = [world - pose_at(f, i)[:, :3, 3] for f, i in ((a, ia), (b, ib))]
            cos = np.sum(rays[0] * rays[1], axis=1) / np.maximum(np.linalg.norm(rays[0], axis=1) * np.linalg.norm(rays[1], axis=1), 1e-12)
            ok &= np.degrees(np.arccos(np.clip(cos, -1, 1))) >= config.min_parallax_deg
            pairs[b] = (ia, ib, world, ok)
        for b, (ia, _, world, ok) in pairs.items():
            if config.confirmed:  # a third frame of the keypoint must see the point there too
                seen = np.zeros(len(ia), dtype=bool)
                for c, (ja, jc, _, _) in pairs.items():
                    if c != b:
                        _, here, there = np.intersect1d(ia, ja, return_indices=True)
                        seen[here[reprojects(world[here], c, jc[there])]] = True
                ok = ok & seen
            points.append(world[ok])
    if not points or sum(len(p) for p in points) < 50:
        raise NoMapError(f"{rig.root / 'rig.json'}: frames: fewer than 50 feature points of {name} triangulate (too little texture or motion)")
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.concatenate(points)))
    world = np.asarray(cloud.voxel_down_sample(config.voxel).points)
    dense = patch_points(world, poses, model, config.patch_points, config.patch_radius_px)
    log(f"[camera-registration] feature map: {len(world)} points triangulated from {len(frames)} frames of {name}"
        f"{f', {len(dense)} with their {config.patch_radius_px:g}-pixel rings' if len(dense) > len(world) else ''}")
    return dense
