"""KITTI-360, read from its download layout, converted to ``moisst-rig/1`` (``moisst-kitti360-to-rig``; the nerfstudio
dataparser ``moisst-kitti360`` calls ``convert`` into a cache folder). numpy / OpenCV / PyYAML; no nerfstudio.
The files read, the extrinsics in the rectified ``image_00`` frame, timestamps and intrinsics: ``docs/kitti360.md``.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Dict, List, Literal, Optional, Sequence, Tuple

import numpy as np
import tyro

from moisst_ns.datasets.kitti360_io import (CAMERAS, PERSPECTIVE, REFERENCE, SUFFIX, VELODYNE, Kitti360Error, KittiCalibration, MeiCamera,
                                             _cameras, _Layout, _perturbed, _require, _write_image, format_timestamp,
                                             read_cam_to_pose, read_cam_to_velo, read_indexed_poses, read_mei_yaml,
                                             read_perspective, read_timestamps)
from moisst_ns.datasets.rig_writer import inverse, prepare_out, rigid, scaled_intrinsics, write_rig, write_trajectory


# ----------------------------------------------------------------------------------------------------------------
# Layout


@dataclass
class Kitti360Paths(_Layout):
    """Where a sequence's files are in the KITTI-360 download layout."""

    root: Path
    sequence: str

    @property
    def calibration(self) -> Path:
        return self.root / "calibration"

    def sensor_dir(self, sensor: str) -> Path:
        if sensor == VELODYNE:
            return self.root / "data_3d_raw" / self.sequence / "velodyne_points"
        return self.root / "data_2d_raw" / self.sequence / sensor

    def data_dir(self, sensor: str) -> Path:
        if sensor == VELODYNE:
            return self.sensor_dir(sensor) / "data"
        return self.sensor_dir(sensor) / ("data_rect" if sensor in PERSPECTIVE else "data_rgb")

    @property
    def poses(self) -> Path:
        return self.root / "data_poses" / self.sequence / "poses.txt"

    @property
    def cam0_to_world(self) -> Path:
        return self.root / "data_poses" / self.sequence / "cam0_to_world.txt"


def read_calibration(paths: Kitti360Paths, cameras: Sequence[str], lidar: bool) -> KittiCalibration:
    """Read ``calibration/`` and express every sensor in the rectified ``image_00`` frame (see module doc)."""
    calib = _require(paths.calibration, "calibration folder")
    cam_to_pose = read_cam_to_pose(calib / "calib_cam_to_pose.txt", sorted(set(cameras) | {REFERENCE}))
    persp = read_perspective(calib / "perspective.txt", sorted(set(cameras) | {REFERENCE}))
    rect0_T_cam0 = rigid(persp[REFERENCE].R_rect)
    rect0_T_pose = rect0_T_cam0 @ inverse(cam_to_pose[REFERENCE])
    T_ref: Dict[str, np.ndarray] = {}
    fisheye: Dict[str, MeiCamera] = {}
    for cam in cameras:
        if cam in PERSPECTIVE:
            T_ref[cam] = rect0_T_pose @ cam_to_pose[cam] @ rigid(persp[cam].R_rect.T)
        else:
            T_ref[cam] = rect0_T_pose @ cam_to_pose[cam]
            fisheye[cam] = read_mei_yaml(calib / f"{cam}.yaml")
    if lidar:
        T_ref[VELODYNE] = rect0_T_cam0 @ inverse(read_cam_to_velo(calib / "calib_cam_to_velo.txt"))
    T_ref[REFERENCE] = np.eye(4)
    return KittiCalibration(T_ref=T_ref, perspective=persp, ref_T_body=rect0_T_pose, fisheye=fisheye)


def rectify_map(camera: MeiCamera, K: np.ndarray, size: Tuple[int, int]) -> Tuple[np.ndarray, np.ndarray]:
    """Maps for ``cv2.remap`` from a MEI fisheye image to a pinhole image with the same axes.

    Args:
        camera: the fisheye model.
        K: 3x3 pinhole intrinsics of the output (OpenCV pixel convention: centre of pixel 0 at 0).
        size: (width, height) of the output.

    Returns:
        (map_x, map_y) float32 (height, width): fisheye pixel sampled for every output pixel (-1 outside).
    """
    w, h = size
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rays = np.stack([(uu - K[0, 2]) / K[0, 0], (vv - K[1, 2]) / K[1, 1], np.ones_like(uu)], axis=-1).reshape(-1, 3)
    uv, valid = camera.project(rays)
    uv[~valid] = -1.0
    return uv[:, 0].reshape(h, w).astype(np.float32), uv[:, 1].reshape(h, w).astype(np.float32)


def pinhole_for_fisheye(fov_deg: float, size: Tuple[int, int]) -> np.ndarray:
    """Pinhole intrinsics (OpenCV pixel convention) of a rectified fisheye: horizontal FOV ``fov_deg``, centred."""
    w, h = size
    f = 0.5 * w / np.tan(np.deg2rad(fov_deg) / 2.0)
    return np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])


# ----------------------------------------------------------------------------------------------------------------
# Converter


@dataclass
class Kitti360Frames:
    """The frames and sensors converted, at what size: the settings the dataparser ``moisst-kitti360`` shares."""

    first_frame: int = 0
    """First frame index (inclusive)."""
    last_frame: Optional[int] = None
    """Last frame index (inclusive); default first_frame + 99."""
    stride: int = 1
    """Keep every stride-th frame of the range (all sensors)."""
    cameras: Tuple[str, ...] = CAMERAS
    """Cameras to include (image_00, the reference, is always included)."""
    lidar: bool = True
    """Include the Velodyne (data_3d_raw/SEQ/velodyne_points)."""
    downscale: int = 1
    """Shrink every image by this integer factor (intrinsics scaled accordingly); 4 suits 2 CPU cores."""


@dataclass
class _Kitti360Source:
    """The converter's first fields (a base, so that they stay first: rig.json's metadata keeps the fields' order)."""

    root: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="ROOT")]
    """KITTI-360 root folder (holds calibration/, data_poses/, data_2d_raw/, data_3d_raw/). Read only."""
    sequence: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="SEQ")]
    """Sequence folder name, e.g. 2013_05_28_drive_0000_sync."""
    out: Path = Path("kitti360-rig")
    """Output dataset folder (created; must be absent or empty unless --overwrite)."""


@dataclass
class Kitti360Config(Kitti360Frames, _Kitti360Source):
    """Convert one KITTI-360 sequence (frame range) from its download layout to a ``moisst-rig/1`` dataset."""

    fisheye_size: Tuple[int, int] = (704, 704)
    """Width and height, before --downscale, of the pinhole images the fisheye cameras are rectified to."""
    fisheye_fov: float = 100.0
    """Horizontal field of view (degrees) of the rectified fisheye pinhole images."""
    perturb: Literal["none", "paper"] = "none"
    """Priors in rig.json: 'none' = the dataset's calibration; 'paper' = perturbed as in MOISST section IV
    (+-translation on every axis, rotation +-rotation about every axis, +-time on the offset; random signs)."""
    seed: int = 0
    """Seed of the perturbation signs."""
    perturb_translation: float = 0.5
    """Metres per axis for --perturb paper."""
    perturb_rotation: float = 5.0
    """Degrees about each axis for --perturb paper (R_prior = R_true Rx Ry Rz)."""
    perturb_time: float = 0.1
    """Seconds for --perturb paper."""
    pose_margin: int = 10
    """Also keep this many reference poses before and after the frame range (less extrapolation at the ends)."""
    overwrite: bool = False
    """Replace the converter's outputs in a non-empty --out."""


def _check_config(config: Kitti360Config) -> Tuple[List[str], List[int]]:
    """The cameras and the frame indices of ``config``, after checking it."""
    cameras = _cameras(config, CAMERAS, "KITTI-360")
    if not 10.0 <= config.fisheye_fov < 170.0:
        raise Kitti360Error("(command line)", "--fisheye-fov", f"must be in [10, 170) degrees, got {config.fisheye_fov}")
    last = config.first_frame + 99 if config.last_frame is None else config.last_frame
    if config.first_frame < 0 or last < config.first_frame or config.stride < 1:
        raise Kitti360Error("(command line)", "--first-frame/--last-frame/--stride",
                            f"need 0 <= first <= last and stride >= 1, got {config.first_frame}, {last}, {config.stride}")
    return cameras, list(range(config.first_frame, last + 1, config.stride))


def sensor_stamps(paths: Kitti360Paths, sensor: str, frames: Sequence[int]) -> np.ndarray:
    """Timestamps (int64 ns) of ``frames`` of a sensor, checking that files and timestamps agree.

    ``paths`` may be any layout with ``timestamps``, ``data_dir`` and ``frame_file`` (``KittiRawPaths`` too)."""
    stamps_file = paths.timestamps(sensor)
    stamps = read_timestamps(stamps_file)
    data = _require(paths.data_dir(sensor), "data folder")
    suffix = SUFFIX.get(sensor, ".png")
    on_disk = sum(1 for p in data.iterdir() if p.suffix == suffix)
    if on_disk > len(stamps):
        raise Kitti360Error(stamps_file, "frame count",
                            f"mismatched frame counts: {len(stamps)} timestamps but {on_disk} {suffix} files in {data}")
    if frames[-1] >= len(stamps):
        raise Kitti360Error(stamps_file, "frame count",
                            f"mismatched frame counts: {len(stamps)} timestamps, frame {frames[-1]} requested")
    for index in frames:
        if not paths.frame_file(sensor, index).is_file():
            raise Kitti360Error(paths.frame_file(sensor, index), "file_path", f"frame {index} of {sensor} not found")
    return stamps[np.asarray(frames)]


def reference_trajectory(paths: Kitti360Paths, calib: KittiCalibration, frames: Sequence[int], margin: int):
    """world_T_rect0 at image_00 frames with a pose, within ``frames`` +- ``margin``.

    ``cam0_to_world.txt`` is used when present (rectified camera 0 -> world, as published); otherwise
    ``poses.txt`` composed with the calibration (``world_T_pose · pose_T_rect0``, ``calib.ref_T_body`` inverted).

    Returns:
        (frame indices (K,), poses (K, 4, 4), source file).
    """
    if not paths.poses.parent.is_dir():
        raise Kitti360Error(paths.poses.parent, "data_poses", f"sequence {paths.sequence} has no poses (folder not found)")
    if paths.cam0_to_world.is_file():
        indices, poses = read_indexed_poses(paths.cam0_to_world, 16)
        source = paths.cam0_to_world
    else:
        indices, poses = read_indexed_poses(_require(paths.poses, "poses.txt"), 12)
        poses = poses @ inverse(calib.ref_T_body)
        source = paths.poses
    keep = (indices >= frames[0] - margin) & (indices <= frames[-1] + margin)
    if keep.sum() < 2:
        raise Kitti360Error(source, "frame index",
                            f"fewer than 2 poses for frames {frames[0]}..{frames[-1]} (+-{margin}); this part of the sequence has no poses")
    return indices[keep], poses[keep], source


def convert(config: Kitti360Config) -> Path:
    """Write the ``moisst-rig/1`` dataset of ``config`` into ``config.out``; returns that folder.

    Perspective images are copied (or shrunk), fisheye images rectified to pinhole images with the fisheye's
    axes, Velodyne scans copied as KITTI ``.bin``. ``ground_truth.json`` holds the dataset's own calibration
    (offsets 0); ``rig.json`` holds it perturbed per ``--perturb``.
    """
    cameras, frames = _check_config(config)
    paths = Kitti360Paths(Path(config.root), config.sequence)
    _require(paths.root, "KITTI-360 root")
    calib = read_calibration(paths, cameras, config.lidar)
    sensors = cameras + ([VELODYNE] if config.lidar else [])
    stamps = {s: sensor_stamps(paths, s, frames) for s in sensors}
    ref_all = read_timestamps(paths.timestamps(REFERENCE))
    origin = int(ref_all[0])
    pose_idx, poses, pose_source = reference_trajectory(paths, calib, frames, config.pose_margin)
    if pose_idx[-1] >= len(ref_all):
        raise Kitti360Error(pose_source, "frame index",
                            f"pose of frame {int(pose_idx[-1])} but {paths.timestamps(REFERENCE)} has {len(ref_all)} timestamps")
    out = prepare_out(Path(config.out), [config.root], config.overwrite, Kitti360Error,
                      "must not be inside the KITTI-360 folder (nothing is written into the dataset)")

    write_trajectory(out / "reference_poses.txt", (ref_all[pose_idx] - origin) * 1e-9, poses,
                     header=f"world_T_image_00 (rectified) from {pose_source.name} of {config.sequence}: timestamp tx ty tz qx qy qz qw")

    factor = config.downscale
    fish_K = pinhole_for_fisheye(config.fisheye_fov, config.fisheye_size)
    intr: Dict[str, Dict[str, object]] = {}
    for cam in cameras:
        if cam in PERSPECTIVE:
            intr[cam] = scaled_intrinsics(calib.perspective[cam].K, calib.perspective[cam].size, factor)
        else:
            intr[cam] = scaled_intrinsics(fish_K, config.fisheye_size, factor)
    maps = {cam: rectify_map(calib.fisheye[cam], fish_K, config.fisheye_size) for cam in calib.fisheye}

    rig_frames = []
    for sensor in sensors:
        folder = ("lidar/" if sensor == VELODYNE else "images/") + sensor
        (out / folder).mkdir(parents=True, exist_ok=True)
        for index, stamp in zip(frames, stamps[sensor]):
            src = paths.frame_file(sensor, index)
            rel = f"{folder}/{src.name}"
            if sensor == VELODYNE:
                shutil.copyfile(src, out / rel)
            elif sensor in calib.fisheye:
                mei = calib.fisheye[sensor]
                _write_image(src, out / rel, (mei.width, mei.height), factor, False, f"{sensor}.yaml", maps[sensor])
            else:
                _write_image(src, out / rel, calib.perspective[sensor].size, factor, factor == 1, "perspective.txt S_rect")
            rig_frames.append({"sensor": sensor, "timestamp": round((int(stamp) - origin) * 1e-9, 9), "file_path": rel})
    write_rig(out, REFERENCE, sensors, [VELODYNE], intr, rig_frames, _perturbed(config, calib.T_ref), dict(
        generator="moisst-kitti360-to-rig", time_origin=format_timestamp(origin), trajectory_source=pose_source.name,
        note="fisheye cameras rectified to pinhole images with the fisheye's own axes; ground_truth.json is the "
             "dataset's calibration (its LiDAR calibration is itself good to a few cm only)"), calib.T_ref, config)
    return out
