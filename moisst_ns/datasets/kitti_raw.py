"""KITTI raw (a synced + rectified drive), read from its download layout, converted to ``moisst-rig/1``
(``moisst-kitti-raw-to-rig``). numpy / OpenCV / SciPy; no nerfstudio. The calibration files, the OXTS trajectory
(``convertOxtsToPose``), the extrinsics in the rectified ``image_00`` frame, the trigger time stamps and the Velodyne
sweep times: ``docs/kitti-raw.md``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Annotated, List, Literal, Optional, Sequence, Tuple

import numpy as np
import tyro

from moisst_ns.datasets.kitti360 import sensor_stamps
from moisst_ns.datasets.kitti360_io import (CAMERAS, REFERENCE, VELODYNE, Kitti360Error, KittiCalibration, _cameras, _Layout,
                                             _perturbed, _require, _rigid, _values, _write_image, format_timestamp,
                                             read_key_values, read_perspective, read_timestamps)
from moisst_ns.datasets.rig_writer import inverse, prepare_out, rigid, scaled_intrinsics, write_rig, write_trajectory

COLOUR = ("image_02", "image_03")
EARTH_RADIUS = 6378137.0
"""Metres, as the devkit's ``convertOxtsToPose``."""
OXTS_VALUES = 30
"""Numbers per OXTS packet (``oxts/dataformat.txt``)."""


KittiRawError = Kitti360Error
"""A KITTI raw folder is incomplete or malformed: one line naming the file, the field and the problem (the same class
as KITTI-360's, since the readers and output steps are shared)."""


# ----------------------------------------------------------------------------------------------------------------
# Layout and readers


@dataclass
class KittiRawPaths(_Layout):
    """Where a drive's files are: ``ROOT/DATE/DATE_drive_XXXX_sync`` and ``ROOT/DATE/calib_*.txt`` (pykitti), or
    ``ROOT/DRIVE/DATE/DRIVE`` and ``ROOT/DATE_calib/DATE/calib_*.txt`` (each KITTI zip unpacked into its own folder)."""

    drive_dir: Path
    calib_dir: Path
    layout: Literal["pykitti", "download"]

    @classmethod
    def find(cls, root: Path, drive: str) -> "KittiRawPaths":
        root, date = Path(root), drive[:10]
        _require(root, "KITTI raw root")
        flat, nested = root / date / drive, root / drive / date / drive
        if not flat.is_dir() and not nested.is_dir():
            raise KittiRawError(root / drive, "drive folder", f"not found: neither {flat} (pykitti layout) nor {nested} "
                                "(see docs/kitti-raw.md)")
        layout = "pykitti" if flat.is_dir() else "download"
        calib_dirs = (root / date, root / f"{date}_calib" / date)
        default = calib_dirs[layout == "download"]
        calib = next((d for d in calib_dirs if (d / "calib_cam_to_cam.txt").is_file()), default)
        return cls(flat if layout == "pykitti" else nested, calib, layout)

    def sensor_dir(self, sensor: str) -> Path:
        return self.drive_dir / ("velodyne_points" if sensor == VELODYNE else sensor)

    def data_dir(self, sensor: str) -> Path:
        return self.sensor_dir(sensor) / "data"


def read_rt(path: Path) -> np.ndarray:
    """``calib_velo_to_cam.txt`` / ``calib_imu_to_velo.txt`` (``R:`` 9 numbers, ``T:`` 3) -> 4x4 (``b_T_a`` of
    ``calib_a_to_b``: maps points of sensor a into sensor b's frame)."""
    table = read_key_values(path)
    return _rigid(np.c_[_values(table, "R", 9, path).reshape(3, 3), _values(table, "T", 3, path)], path, "R")


def read_calibration(paths: KittiRawPaths, cameras: Sequence[str]) -> KittiCalibration:
    """Read the three ``calib_*.txt`` files and express every sensor in the rectified ``image_00`` frame (the
    trajectory's body: the OXTS IMU)."""
    persp = read_perspective(paths.calib_dir / "calib_cam_to_cam.txt", sorted(set(cameras) | {REFERENCE}), CAMERAS)
    T_ref = {cam: rigid(translation=0.0 - persp[cam].offset) for cam in cameras}
    T_ref[REFERENCE] = np.eye(4)
    T_ref[VELODYNE] = rigid(persp[REFERENCE].R_rect) @ read_rt(paths.calib_dir / "calib_velo_to_cam.txt")
    ref_T_imu = T_ref[VELODYNE] @ read_rt(paths.calib_dir / "calib_imu_to_velo.txt")
    return KittiCalibration(T_ref=T_ref, perspective=persp, ref_T_body=ref_T_imu)


def read_oxts(paths: KittiRawPaths) -> Tuple[np.ndarray, np.ndarray]:
    """Every OXTS sample of the drive.

    Returns:
        (timestamps (K,) int64 ns, packets (K, 6): lat, lon (degrees), alt (metres), roll, pitch, yaw (radians)).
    """
    stamps_file = paths.timestamps("oxts")
    stamps = read_timestamps(stamps_file)
    data = _require(paths.data_dir("oxts"), "data folder")
    on_disk = sum(1 for p in data.iterdir() if p.suffix == ".txt")
    if on_disk != len(stamps):
        raise KittiRawError(stamps_file, "frame count", f"mismatched frame counts: {len(stamps)} timestamps but {on_disk} .txt files in {data}")
    packets = []
    for index in range(len(stamps)):
        file = _require(paths.frame_file("oxts", index), "file_path")
        try:
            values = np.array([float(v) for v in file.read_text().split()])
        except ValueError:
            raise KittiRawError(file, "packet", "not a number") from None
        if values.size != OXTS_VALUES:
            raise KittiRawError(file, "packet", f"expected {OXTS_VALUES} numbers (oxts/dataformat.txt), got {values.size}")
        if not np.all(np.isfinite(values[:6])):
            raise KittiRawError(file, "lat lon alt roll pitch yaw", "contains NaN or inf")
        packets.append(values[:6])
    return stamps, np.stack(packets)


def oxts_poses(packets: np.ndarray) -> np.ndarray:
    """``world_T_imu`` (K, 4, 4) of OXTS packets (lat, lon, alt, roll, pitch, yaw), as the devkit's
    ``convertOxtsToPose`` (Mercator scale of the first packet), less the first packet's translation."""
    from scipy.spatial.transform import Rotation

    lat, lon, alt, roll, pitch, yaw = np.asarray(packets, dtype=np.float64).T
    scale = np.cos(lat[0] * np.pi / 180.0)
    t = np.stack([scale * EARTH_RADIUS * lon * np.pi / 180.0,
                  scale * EARTH_RADIUS * np.log(np.tan((90.0 + lat) * np.pi / 360.0)), alt], axis=1)
    poses = np.tile(np.eye(4), (len(lat), 1, 1))
    poses[:, :3, :3] = Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], axis=1)).as_matrix()  # Rz Ry Rx
    poses[:, :3, 3] = t - t[0]
    return poses


def sweep_times(points: np.ndarray, sweep_s: float, clockwise: bool = True) -> np.ndarray:
    """Per-point time offsets of a Velodyne sweep from the instant it faces forward (+x), seconds.

    The azimuth ``phi = atan2(y, x)`` turns once per sweep; clockwise seen from above (z up), time grows as ``phi``
    falls: ``times = -phi / (2 pi) * sweep_s`` (``phi = +pi`` -> ``-sweep_s / 2``, ``-pi`` -> ``+sweep_s / 2``).

    Args:
        points: (N, 3+) points in the Velodyne frame. sweep_s: the sweep's duration, seconds.
        clockwise: the spin direction (KITTI's HDL-64E: clockwise).

    Returns:
        (N,) float64 offsets in [-sweep_s / 2, sweep_s / 2].
    """
    phi = np.arctan2(np.asarray(points)[:, 1], np.asarray(points)[:, 0]).astype(np.float64)
    return (-phi if clockwise else phi) / (2.0 * np.pi) * sweep_s


# ----------------------------------------------------------------------------------------------------------------
# Converter


@dataclass
class KittiRawConfig:
    """Convert one KITTI raw drive (synced + rectified) from its download layout to a ``moisst-rig/1`` dataset."""

    root: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="ROOT")]
    """Folder holding the drive and its calibration (ROOT/DATE/DRIVE + ROOT/DATE/calib_*.txt, or
    ROOT/DRIVE/DATE/DRIVE + ROOT/DATE_calib/DATE/calib_*.txt). Read only."""
    drive: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="DRIVE")]
    """Synced drive folder name, e.g. 2011_09_26_drive_0048_sync (DATE = its first 10 characters)."""
    out: Path = Path("kitti-raw-rig")
    """Output dataset folder (created; must be absent or empty unless --overwrite)."""
    first_frame: int = 0
    """First frame index (inclusive)."""
    last_frame: Optional[int] = None
    """Last frame index (inclusive); default: the last image_00 frame."""
    cameras: Tuple[str, ...] = CAMERAS
    """Cameras to include (image_00, the reference, is always included)."""
    lidar: bool = True
    """Include the Velodyne (velodyne_points), written as .npz with per-point times."""
    downscale: int = 1
    """Shrink every image by this integer factor (intrinsics scaled accordingly)."""
    perturb: Literal["none", "paper", "rot10"] = "none"
    """Priors in rig.json: 'none' = the factory calibration; 'paper' = perturbed as in MOISST section IV
    (+-translation on every axis, +-rotation about every axis, +-time; random signs); 'rot10' = 'paper' with 10 deg."""
    seed: int = 0
    """Seed of the perturbation signs and of the --points-per-scan subsets."""
    perturb_translation: float = 0.5
    """Metres per axis for --perturb paper/rot10."""
    perturb_rotation: float = 5.0
    """Degrees about each axis for --perturb paper (R_prior = R_true Rx Ry Rz); rot10 uses 10."""
    perturb_time: float = 0.1
    """Seconds for --perturb paper/rot10."""
    points_per_scan: int = 0
    """Keep a seeded uniform random subset of this many points per Velodyne scan (0 = all, ~120 k)."""
    stamps: Literal["trigger", "recorded"] = "trigger"
    """Camera time stamps: 'trigger' = the Velodyne's timestamps.txt (it triggers the cameras as it faces forward);
    'recorded' = each camera's own timestamps.txt (6-20 ms of recording latency)."""
    overwrite: bool = False
    """Replace the converter's outputs in a non-empty --out."""


def _check_config(config: KittiRawConfig) -> List[str]:
    cameras = _cameras(config, CAMERAS, "KITTI raw")
    if config.points_per_scan < 0:
        raise KittiRawError("(command line)", "--points-per-scan", f"must be >= 0, got {config.points_per_scan}")
    return cameras


def _frame_range(config: KittiRawConfig, count: int, stamps_file: Path) -> List[int]:
    last = count - 1 if config.last_frame is None else config.last_frame
    if config.first_frame < 0 or last < config.first_frame:
        raise KittiRawError("(command line)", "--first-frame/--last-frame", f"need 0 <= first <= last, got {config.first_frame}, {last}")
    if last >= count:
        raise KittiRawError(stamps_file, "frame count", f"{count} image_00 frames, frame {last} requested")
    return list(range(config.first_frame, last + 1))


def sweep_durations(paths: KittiRawPaths, frames: Sequence[int]) -> np.ndarray:
    """``timestamps_end - timestamps_start`` (seconds) of the Velodyne sweeps ``frames``."""
    start, end = (read_timestamps(paths.timestamps(VELODYNE, w)) for w in ("start", "end"))
    for file, stamps in ((paths.timestamps(VELODYNE, "start"), start), (paths.timestamps(VELODYNE, "end"), end)):
        if frames[-1] >= len(stamps):
            raise KittiRawError(file, "frame count", f"mismatched frame counts: {len(stamps)} timestamps, frame {frames[-1]} requested")
    sweep = (end[frames] - start[frames]) * 1e-9
    if np.any(sweep <= 0.0) or np.any(sweep > 1.0):
        bad = frames[int(np.argmax((sweep <= 0.0) | (sweep > 1.0)))]
        raise KittiRawError(paths.timestamps(VELODYNE, "end"), f"line {bad + 1}", "sweep end not within 1 s after its start")
    return sweep


def _write_scan(src: Path, dst: Path, sweep_s: float, keep: int, rng: np.random.Generator) -> None:
    raw = np.fromfile(src, dtype=np.float32)
    if raw.size == 0 or raw.size % 4:
        raise KittiRawError(src, "data", f"expected x y z reflectance float32 records, got {raw.size} floats")
    points = raw.reshape(-1, 4)[:, :3]
    if 0 < keep < len(points):
        points = points[np.sort(rng.choice(len(points), keep, replace=False))]
    np.savez(dst, points=np.ascontiguousarray(points), times=sweep_times(points, sweep_s))


def convert(config: KittiRawConfig) -> Path:
    """Write the ``moisst-rig/1`` dataset of ``config`` into ``config.out``; returns that folder.

    Images are copied (colour, full size) or re-encoded as 3-channel PNGs (grey, or shrunk); Velodyne sweeps become
    ``.npz`` with per-point times (``sweep_times``). ``ground_truth.json`` holds the factory calibration (offsets 0);
    ``rig.json`` holds it perturbed per ``--perturb``. Calibration, timestamps, OXTS and the frame files' presence are
checked before anything is written (an unreadable or wrong-sized image or scan stops it midway).
    """
    cameras = _check_config(config)
    paths = KittiRawPaths.find(config.root, config.drive)
    calib = read_calibration(paths, cameras)
    ref_all = read_timestamps(paths.timestamps(REFERENCE))
    frames = _frame_range(config, len(ref_all), paths.timestamps(REFERENCE))
    sensors = cameras + ([VELODYNE] if config.lidar else [])
    stamps = {s: sensor_stamps(paths, s, frames) for s in sensors}
    if config.stamps == "trigger":
        trigger = stamps[VELODYNE] if config.lidar else sensor_stamps(paths, VELODYNE, frames)
        stamps.update({cam: trigger for cam in cameras})
    sweeps = sweep_durations(paths, frames) if config.lidar else None
    oxts_stamps, packets = read_oxts(paths)
    out = prepare_out(Path(config.out), [config.root], config.overwrite, KittiRawError,
                      "must not be inside the KITTI raw folder (nothing is written into the dataset)")

    origin = int(ref_all[0])
    write_trajectory(out / "reference_poses.txt", (oxts_stamps - origin) * 1e-9, oxts_poses(packets) @ inverse(calib.ref_T_body),
                     header=f"world_T_image_00 (rectified) from the OXTS of {config.drive}: timestamp tx ty tz qx qy qz qw")
    factor = config.downscale
    intr = {cam: scaled_intrinsics(calib.perspective[cam].K, calib.perspective[cam].size, factor) for cam in cameras}
    rig_frames = []
    for sensor in sensors:
        kind = "lidar" if sensor == VELODYNE else "images"
        (out / kind / sensor).mkdir(parents=True, exist_ok=True)
        for i, (index, stamp) in enumerate(zip(frames, stamps[sensor])):
            src = paths.frame_file(sensor, index)
            if sensor == VELODYNE:
                rel = f"{kind}/{sensor}/{src.stem}.npz"
                _write_scan(src, out / rel, float(sweeps[i]), config.points_per_scan, np.random.default_rng((config.seed, index)))
            else:
                rel = f"{kind}/{sensor}/{src.name}"
                _write_image(src, out / rel, calib.perspective[sensor].size, factor, factor == 1 and sensor in COLOUR,
                             "calib_cam_to_cam.txt S_rect")
            rig_frames.append({"sensor": sensor, "timestamp": round((int(stamp) - origin) * 1e-9, 9), "file_path": rel})

    priors_config = replace(config, perturb_rotation=10.0) if config.perturb == "rot10" else config
    truth = {s: calib.T_ref[s] for s in sensors}
    write_rig(out, REFERENCE, sensors, [VELODYNE], intr, rig_frames, _perturbed(priors_config, truth), dict(
        generator="moisst-kitti-raw-to-rig", time_origin=format_timestamp(origin), layout=paths.layout,
        trajectory_source="oxts (every sample, its own timestamps)",
        camera_stamps="velodyne_points/timestamps.txt (camera trigger)" if config.stamps == "trigger"
        else "each camera's timestamps.txt (recorded)",
        velodyne_times="clockwise sweep: times = -atan2(y, x) / (2 pi) * (timestamps_end - timestamps_start)",
        note="ground_truth.json is the factory calibration (good to a few cm) with offsets 0"), truth, priors_config)
    return out
