"""KITTI-360, read from its download layout, converted to ``moisst-rig/1`` (``moisst-kitti360-to-rig``).

Pure numpy / OpenCV / PyYAML; no nerfstudio. The nerfstudio dataparser ``moisst-kitti360``
(``moisst_ns.data.kitti360_dataparser``) calls ``convert`` into a cache folder and reads the result.

Frames and conventions (KITTI-360 devkit, ``kitti360scripts/helpers/project.py``, and the paper, section IV-A):

* ``calib_cam_to_pose.txt``: ``pose_T_camX`` (unrectified camera X -> vehicle pose frame, 3x4).
* ``perspective.txt``: ``R_rect_0X`` rotates unrectified camera X into its rectified frame
  (``p_rect = R_rect_0X p_cam``); ``P_rect_0X`` holds the rectified intrinsics; ``S_rect_0X`` the size.
* ``calib_cam_to_velo.txt``: ``velo_T_cam0`` (unrectified camera 0 -> Velodyne).
* ``poses.txt``: ``world_T_pose`` per image_00 frame index (not every frame has one);
  ``cam0_to_world.txt``: ``world_T_rect0`` (rectified camera 0 -> world), the reference trajectory.
* ``image_02.yaml`` / ``image_03.yaml``: MEI (unified omnidirectional) fisheye models of the side cameras.

The reference sensor is the rectified ``image_00`` (as in the paper). Extrinsics of the other sensors in its frame::

    T_rect0_rect1 = R_rect_00 · pose_T_cam0^-1 · pose_T_cam1 · R_rect_01^-1
    T_rect0_fishX = R_rect_00 · pose_T_cam0^-1 · pose_T_camX          (X = 2, 3; rectified to a pinhole, same axes)
    T_rect0_velo  = R_rect_00 · velo_T_cam0^-1

Time: the per-sensor ``timestamps.txt`` are taken as the truth (ground-truth offsets 0); rig timestamps are
seconds since the sequence's first ``image_00`` timestamp, computed in integer nanoseconds.
Principal points: KITTI gives pixel-centre-at-integer (OpenCV) coordinates, nerfstudio/moisst-rig put pixel
centres at +0.5, so ``cx_rig = cx_kitti + 0.5``.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Annotated, Dict, List, Literal, Optional, Sequence, Tuple

import numpy as np
import tyro

from moisst_ns.rig.format import FORMAT, Calibration, RigFormatError, write_tum

CAMERAS = ("image_00", "image_01", "image_02", "image_03")
PERSPECTIVE = ("image_00", "image_01")
FISHEYE = ("image_02", "image_03")
VELODYNE = "velodyne"
REFERENCE = "image_00"


class Kitti360Error(RigFormatError):
    """A KITTI-360 folder is incomplete or malformed; one line naming the file, the field and the problem."""


# ----------------------------------------------------------------------------------------------------------------
# Readers


def _rigid(values: Sequence[float]) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :4] = np.asarray(values, dtype=np.float64).reshape(3, 4)
    return pose


def _inv(pose: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = pose[:3, :3].T
    out[:3, 3] = -pose[:3, :3].T @ pose[:3, 3]
    return out


def _rot4(rotation: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = rotation
    return out


def _check_rotation(rotation: np.ndarray, file: Path, key: str, tol: float = 1e-4) -> None:
    if not np.allclose(rotation @ rotation.T, np.eye(3), atol=tol) or np.linalg.det(rotation) < 0:
        raise Kitti360Error(file, key, "not a rotation (R R^T != I or det < 0)")


def _require(path: Path, what: str) -> Path:
    if not path.exists():
        raise Kitti360Error(path, what, "not found (see docs/kitti360.md for the folders to download)")
    return path


def read_key_values(path: Path) -> Dict[str, np.ndarray]:
    """Read a ``key: v1 v2 ...`` text file (``calib_cam_to_pose.txt``, ``perspective.txt``).

    Returns:
        key -> float64 values; lines whose values are not all numbers (``calib_time: 09-Jan-2012 ...``) are skipped.
    """
    _require(path, "(file)")
    out: Dict[str, np.ndarray] = {}
    for line in path.read_text().splitlines():
        if ":" not in line:
            continue
        key, _, rest = line.partition(":")
        try:
            out[key.strip()] = np.array([float(v) for v in rest.split()], dtype=np.float64)
        except ValueError:
            continue
    return out


def _values(table: Dict[str, np.ndarray], key: str, count: int, file: Path) -> np.ndarray:
    if key not in table:
        raise Kitti360Error(file, key, "missing")
    if table[key].size != count:
        raise Kitti360Error(file, key, f"expected {count} numbers, got {table[key].size}")
    if not np.all(np.isfinite(table[key])):
        raise Kitti360Error(file, key, "contains NaN or inf")
    return table[key]


def read_cam_to_pose(path: Path, cameras: Sequence[str]) -> Dict[str, np.ndarray]:
    """``calib_cam_to_pose.txt`` -> {camera: pose_T_cam (4x4)}."""
    table = read_key_values(path)
    out = {}
    for cam in cameras:
        pose = _rigid(_values(table, cam, 12, path))
        _check_rotation(pose[:3, :3], path, cam)
        out[cam] = pose
    return out


def read_cam_to_velo(path: Path) -> np.ndarray:
    """``calib_cam_to_velo.txt`` (one line of 12 numbers) -> velo_T_cam0 (4x4)."""
    _require(path, "(file)")
    numbers = path.read_text().split()
    try:
        values = [float(v) for v in numbers]
    except ValueError:
        raise Kitti360Error(path, "cam0 -> velo", "not a number") from None
    if len(values) != 12:
        raise Kitti360Error(path, "cam0 -> velo", f"expected 12 numbers (3x4), got {len(values)}")
    pose = _rigid(values)
    _check_rotation(pose[:3, :3], path, "cam0 -> velo")
    return pose


@dataclass
class Perspective:
    """Rectified pinhole camera from ``perspective.txt``."""

    K: np.ndarray
    """3x3 intrinsics of ``P_rect_0X`` (KITTI pixel convention: centre of pixel 0 at 0)."""
    R_rect: np.ndarray
    """3x3 ``R_rect_0X``: unrectified -> rectified camera frame."""
    size: Tuple[int, int]
    """(width, height) of ``S_rect_0X``."""


def read_perspective(path: Path, cameras: Sequence[str]) -> Dict[str, Perspective]:
    """``perspective.txt`` -> {image_0X: Perspective} for the perspective cameras among ``cameras``."""
    table = read_key_values(path)
    out = {}
    for cam in cameras:
        if cam not in PERSPECTIVE:
            continue
        n = cam[-2:]
        P = _values(table, f"P_rect_{n}", 12, path).reshape(3, 4)
        R = _values(table, f"R_rect_{n}", 9, path).reshape(3, 3)
        _check_rotation(R, path, f"R_rect_{n}")
        w, h = _values(table, f"S_rect_{n}", 2, path)
        if w <= 0 or h <= 0 or w != int(w) or h != int(h):
            raise Kitti360Error(path, f"S_rect_{n}", f"expected a positive integer width and height, got {w} {h}")
        if P[0, 0] <= 0 or P[1, 1] <= 0:
            raise Kitti360Error(path, f"P_rect_{n}", "focal lengths must be > 0")
        out[cam] = Perspective(K=P[:, :3].copy(), R_rect=R, size=(int(w), int(h)))
    return out


@dataclass
class MeiCamera:
    """The MEI unified omnidirectional camera model (KITTI-360 ``image_02.yaml`` / ``image_03.yaml``).

    A point ``X`` in the camera frame (OpenCV axes) is put on the unit sphere, projected from ``(0, 0, -xi)``
    onto the normalised plane, distorted radially (k1, k2) and tangentially (p1, p2), then scaled by
    (gamma1, gamma2) and shifted by (u0, v0) (pixel centre at integer coordinates, as OpenCV).
    """

    xi: float
    k1: float
    k2: float
    p1: float
    p2: float
    gamma1: float
    gamma2: float
    u0: float
    v0: float
    width: int
    height: int

    def project(self, points: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Project camera-frame points.

        Args:
            points: (N, 3) points or directions in the camera frame.

        Returns:
            ((N, 2) pixel coordinates u, v (pixel centres at integers), (N,) mask of points the model can image).
        """
        p = np.asarray(points, dtype=np.float64)
        s = p / np.linalg.norm(p, axis=-1, keepdims=True)
        denom = s[:, 2] + self.xi
        valid = denom > 1e-9
        denom = np.where(valid, denom, 1.0)
        x, y = s[:, 0] / denom, s[:, 1] / denom
        r2 = x * x + y * y
        radial = 1.0 + self.k1 * r2 + self.k2 * r2 * r2
        xd = x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x)
        yd = y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y
        return np.stack([self.gamma1 * xd + self.u0, self.gamma2 * yd + self.v0], axis=-1), valid

    def unproject(self, pixels: np.ndarray) -> np.ndarray:
        """Unit ray directions of pixels (inverse of ``project``; distortion inverted with OpenCV's iteration).

        Args:
            pixels: (N, 2) pixel coordinates u, v (pixel centres at integers).

        Returns:
            (N, 3) unit directions in the camera frame.
        """
        import cv2

        uv = np.asarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
        K = np.array([[self.gamma1, 0.0, self.u0], [0.0, self.gamma2, self.v0], [0.0, 0.0, 1.0]])
        dist = np.array([self.k1, self.k2, self.p1, self.p2])
        m = cv2.undistortPointsIter(uv, K, dist, None, None, (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12))
        m = m.reshape(-1, 2)
        r2 = (m * m).sum(axis=1)
        factor = (self.xi + np.sqrt(1.0 + (1.0 - self.xi**2) * r2)) / (1.0 + r2)
        d = np.stack([factor * m[:, 0], factor * m[:, 1], factor - self.xi], axis=1)
        return d / np.linalg.norm(d, axis=1, keepdims=True)


MEI_KEYS = {
    "mirror_parameters": ("xi",),
    "distortion_parameters": ("k1", "k2", "p1", "p2"),
    "projection_parameters": ("gamma1", "gamma2", "u0", "v0"),
}


def read_mei_yaml(path: Path) -> MeiCamera:
    """Read an ``image_0X.yaml`` MEI fisheye calibration (OpenCV FileStorage YAML starting with ``%YAML:1.0``)."""
    import yaml

    _require(path, "(file)")
    text = path.read_text()
    if text.startswith("%YAML"):
        text = text.split("\n", 1)[1] if "\n" in text else ""
    try:
        raw = yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise Kitti360Error(path, "(yaml)", f"not valid YAML ({str(err).splitlines()[0]})") from None
    if not isinstance(raw, dict):
        raise Kitti360Error(path, "(top level)", "expected a mapping")
    model = raw.get("model_type", "MEI")
    if str(model).upper() != "MEI":
        raise Kitti360Error(path, "model_type", f"unsupported fisheye model {model!r} (only MEI)")
    values: Dict[str, float] = {}
    for group, keys in MEI_KEYS.items():
        section = raw.get(group)
        if not isinstance(section, dict):
            raise Kitti360Error(path, group, "missing")
        for key in keys:
            value = section.get(key)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
                raise Kitti360Error(path, f"{group}.{key}", f"missing or not a finite number ({value!r})")
            values[key] = float(value)
    for key in ("image_width", "image_height"):
        value = raw.get(key)
        if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
            raise Kitti360Error(path, key, f"must be a positive integer, got {value!r}")
    if values["gamma1"] <= 0 or values["gamma2"] <= 0:
        raise Kitti360Error(path, "projection_parameters.gamma1", "gamma1 and gamma2 must be > 0")
    return MeiCamera(width=raw["image_width"], height=raw["image_height"], **values)


def read_indexed_poses(path: Path, columns: int) -> Tuple[np.ndarray, np.ndarray]:
    """``poses.txt`` (index + 12 numbers) or ``cam0_to_world.txt`` (index + 16 numbers).

    Returns:
        (frame indices (K,), poses (K, 4, 4)), sorted by index.
    """
    _require(path, "(file)")
    indices, poses = [], []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        parts = line.split()
        if not parts:
            continue
        if len(parts) != columns + 1:
            raise Kitti360Error(path, f"line {lineno}", f"expected a frame index and {columns} numbers, got {len(parts)} values")
        try:
            index = int(parts[0])
            values = np.array([float(v) for v in parts[1:]])
        except ValueError:
            raise Kitti360Error(path, f"line {lineno}", "not a number") from None
        if not np.all(np.isfinite(values)):
            raise Kitti360Error(path, f"line {lineno}", "contains NaN or inf")
        pose = np.eye(4)
        pose[: columns // 4] = values.reshape(columns // 4, 4)
        _check_rotation(pose[:3, :3], path, f"line {lineno}", tol=1e-3)
        indices.append(index)
        poses.append(pose)
    if not indices:
        raise Kitti360Error(path, "(file)", "no poses")
    order = np.argsort(indices, kind="stable")
    idx = np.asarray(indices)[order]
    if np.any(np.diff(idx) == 0):
        raise Kitti360Error(path, "frame index", f"frame {int(idx[np.argmax(np.diff(idx) == 0)])} appears twice")
    return idx, np.stack(poses)[order]


def read_timestamps(path: Path) -> np.ndarray:
    """``timestamps.txt``: one ``YYYY-MM-DD HH:MM:SS.nnnnnnnnn`` per frame.

    Returns:
        (N,) int64 nanoseconds since the Unix epoch (exact).
    """
    _require(path, "(file)")
    stamps = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        text = line.strip()
        if not text:
            continue
        try:
            stamps.append(np.datetime64(text.replace(" ", "T"), "ns").astype(np.int64))
        except ValueError:
            raise Kitti360Error(path, f"line {lineno}", f"not a 'YYYY-MM-DD HH:MM:SS.nnnnnnnnn' timestamp: {text!r}") from None
    if not stamps:
        raise Kitti360Error(path, "(file)", "no timestamps")
    out = np.asarray(stamps, dtype=np.int64)
    if np.any(np.diff(out) <= 0):
        bad = int(np.argmax(np.diff(out) <= 0)) + 2
        raise Kitti360Error(path, f"line {bad}", "timestamps must be strictly increasing")
    return out


def format_timestamp(ns: int) -> str:
    """Inverse of one ``read_timestamps`` line."""
    text = str(np.datetime64(int(ns), "ns"))
    return text.replace("T", " ")


# ----------------------------------------------------------------------------------------------------------------
# Layout


@dataclass
class Kitti360Paths:
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

    def frame_file(self, sensor: str, index: int) -> Path:
        return self.data_dir(sensor) / (f"{index:010d}" + (".bin" if sensor == VELODYNE else ".png"))

    def timestamps(self, sensor: str) -> Path:
        return self.sensor_dir(sensor) / "timestamps.txt"

    @property
    def poses(self) -> Path:
        return self.root / "data_poses" / self.sequence / "poses.txt"

    @property
    def cam0_to_world(self) -> Path:
        return self.root / "data_poses" / self.sequence / "cam0_to_world.txt"


@dataclass
class Kitti360Calibration:
    """Everything the dataset says about the rig: extrinsics in the rectified image_00 frame and intrinsics."""

    T_ref: Dict[str, np.ndarray]
    """sensor -> T_rect0_sensor (4x4)."""
    perspective: Dict[str, Perspective]
    fisheye: Dict[str, MeiCamera]
    pose_T_rect0: np.ndarray
    """Vehicle pose frame <- rectified camera 0 (to turn ``poses.txt`` into the reference trajectory)."""


def read_calibration(paths: Kitti360Paths, cameras: Sequence[str], lidar: bool) -> Kitti360Calibration:
    """Read ``calibration/`` and express every sensor in the rectified ``image_00`` frame (see module doc)."""
    calib = _require(paths.calibration, "calibration folder")
    cam_to_pose = read_cam_to_pose(calib / "calib_cam_to_pose.txt", sorted(set(cameras) | {REFERENCE}))
    persp = read_perspective(calib / "perspective.txt", sorted(set(cameras) | {REFERENCE}))
    rect0_T_cam0 = _rot4(persp[REFERENCE].R_rect)
    rect0_T_pose = rect0_T_cam0 @ _inv(cam_to_pose[REFERENCE])
    T_ref: Dict[str, np.ndarray] = {}
    fisheye: Dict[str, MeiCamera] = {}
    for cam in cameras:
        if cam in PERSPECTIVE:
            T_ref[cam] = rect0_T_pose @ cam_to_pose[cam] @ _rot4(persp[cam].R_rect.T)
        else:
            T_ref[cam] = rect0_T_pose @ cam_to_pose[cam]
            fisheye[cam] = read_mei_yaml(calib / f"{cam}.yaml")
    if lidar:
        T_ref[VELODYNE] = rect0_T_cam0 @ _inv(read_cam_to_velo(calib / "calib_cam_to_velo.txt"))
    T_ref[REFERENCE] = np.eye(4)
    return Kitti360Calibration(T_ref=T_ref, perspective=persp, fisheye=fisheye, pose_T_rect0=_inv(rect0_T_pose))


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
class Kitti360Config:
    """Convert one KITTI-360 sequence (frame range) from its download layout to a ``moisst-rig/1`` dataset."""

    root: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="ROOT")]
    """KITTI-360 root folder (holds calibration/, data_poses/, data_2d_raw/, data_3d_raw/). Read only."""
    sequence: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="SEQ")]
    """Sequence folder name, e.g. 2013_05_28_drive_0000_sync."""
    out: Path = Path("kitti360-rig")
    """Output dataset folder (created; must be absent or empty unless --overwrite)."""
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


def _frame_range(config: Kitti360Config) -> List[int]:
    last = config.first_frame + 99 if config.last_frame is None else config.last_frame
    if config.first_frame < 0 or last < config.first_frame or config.stride < 1:
        raise Kitti360Error("(command line)", "--first-frame/--last-frame/--stride",
                            f"need 0 <= first <= last and stride >= 1, got {config.first_frame}, {last}, {config.stride}")
    return list(range(config.first_frame, last + 1, config.stride))


def _check_config(config: Kitti360Config) -> Tuple[List[str], List[int]]:
    unknown = [c for c in config.cameras if c not in CAMERAS]
    if unknown:
        raise Kitti360Error("(command line)", "--cameras", f"unknown camera {unknown[0]!r}; KITTI-360 has {', '.join(CAMERAS)}")
    if config.downscale < 1:
        raise Kitti360Error("(command line)", "--downscale", f"must be >= 1, got {config.downscale}")
    if not 10.0 <= config.fisheye_fov < 170.0:
        raise Kitti360Error("(command line)", "--fisheye-fov", f"must be in [10, 170) degrees, got {config.fisheye_fov}")
    cameras = [REFERENCE] + [c for c in CAMERAS if c in config.cameras and c != REFERENCE]
    return cameras, _frame_range(config)


def sensor_stamps(paths: Kitti360Paths, sensor: str, frames: Sequence[int]) -> np.ndarray:
    """Timestamps (int64 ns) of ``frames`` of a sensor, checking that files and timestamps agree."""
    stamps_file = paths.timestamps(sensor)
    stamps = read_timestamps(stamps_file)
    data = _require(paths.data_dir(sensor), "data folder")
    suffix = ".bin" if sensor == VELODYNE else ".png"
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


def reference_trajectory(paths: Kitti360Paths, calib: Kitti360Calibration, frames: Sequence[int], margin: int):
    """world_T_rect0 at image_00 frames with a pose, within ``frames`` +- ``margin``.

    ``cam0_to_world.txt`` is used when present (rectified camera 0 -> world, as published); otherwise
    ``poses.txt`` composed with the calibration (``world_T_pose · pose_T_rect0``).

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
        poses = poses @ calib.pose_T_rect0
        source = paths.poses
    keep = (indices >= frames[0] - margin) & (indices <= frames[-1] + margin)
    if keep.sum() < 2:
        raise Kitti360Error(source, "frame index",
                            f"fewer than 2 poses for frames {frames[0]}..{frames[-1]} (+-{margin}); this part of the sequence has no poses")
    return indices[keep], poses[keep], source


def _perturbed(config: Kitti360Config, T_ref: Dict[str, np.ndarray]) -> Dict[str, Tuple[np.ndarray, float]]:
    from moisst_ns.synth import paper_perturbation

    rng = np.random.default_rng(config.seed)
    priors = {}
    for name in sorted(T_ref):
        signs = rng.choice([-1.0, 1.0], size=7)
        if name == REFERENCE or config.perturb == "none":
            priors[name] = (T_ref[name].copy(), 0.0)
            continue
        priors[name] = paper_perturbation(T_ref[name], 0.0, signs, config.perturb_translation, config.perturb_rotation,
                                          config.perturb_time)
    return priors


def _prepare_out(config: Kitti360Config) -> Path:
    out = Path(config.out)
    root = Path(config.root).resolve()
    if out.resolve() == root or root in out.resolve().parents:
        raise Kitti360Error(out, "--out", "must not be inside the KITTI-360 folder (nothing is written into the dataset)")
    if out.exists() and not out.is_dir():
        raise Kitti360Error(out, "--out", "exists and is not a folder")
    if out.is_dir() and any(out.iterdir()):
        if not config.overwrite:
            raise Kitti360Error(out, "--out", "exists and is not empty; pass --overwrite to replace its dataset")
        for name in ("rig.json", "reference_poses.txt", "ground_truth.json"):
            (out / name).unlink(missing_ok=True)
        for name in ("images", "lidar"):
            if (out / name).is_dir():
                shutil.rmtree(out / name)
    out.mkdir(parents=True, exist_ok=True)
    return out


def _scaled_intrinsics(K: np.ndarray, size: Tuple[int, int], factor: int) -> Dict[str, object]:
    """moisst-rig PINHOLE intrinsics (pixel centres at +0.5) of a KITTI K after shrinking by ``factor``."""
    w, h = size
    return {"camera_model": "PINHOLE", "w": w // factor, "h": h // factor, "fl_x": float(K[0, 0]) / factor,
            "fl_y": float(K[1, 1]) / factor, "cx": (float(K[0, 2]) + 0.5) / factor, "cy": (float(K[1, 2]) + 0.5) / factor}


def convert(config: Kitti360Config) -> Path:
    """Write the ``moisst-rig/1`` dataset of ``config`` into ``config.out``; returns that folder.

    Perspective images are copied (or shrunk), fisheye images rectified to pinhole images with the fisheye's
    axes, Velodyne scans copied as KITTI ``.bin``. ``ground_truth.json`` holds the dataset's own calibration
    (offsets 0); ``rig.json`` holds it perturbed per ``--perturb``.
    """
    import cv2

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
    out = _prepare_out(config)

    import roma
    import torch

    quats = roma.rotmat_to_unitquat(torch.from_numpy(poses[:, :3, :3])).numpy()
    quats = quats * np.where(quats[:, 3:4] < 0, -1.0, 1.0)
    write_tum(out / "reference_poses.txt", (ref_all[pose_idx] - origin) * 1e-9, poses[:, :3, 3], quats,
              header=f"world_T_image_00 (rectified) from {pose_source.name} of {config.sequence}: timestamp tx ty tz qx qy qz qw")

    factor = config.downscale
    fish_K = pinhole_for_fisheye(config.fisheye_fov, config.fisheye_size)
    intr: Dict[str, Dict[str, object]] = {}
    for cam in cameras:
        if cam in PERSPECTIVE:
            intr[cam] = _scaled_intrinsics(calib.perspective[cam].K, calib.perspective[cam].size, factor)
        else:
            intr[cam] = _scaled_intrinsics(fish_K, config.fisheye_size, factor)
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
            else:
                image = cv2.imread(str(src), cv2.IMREAD_COLOR)
                if image is None:
                    raise Kitti360Error(src, "image", "unreadable image")
                if sensor in calib.fisheye:
                    mei = calib.fisheye[sensor]
                    if image.shape[:2] != (mei.height, mei.width):
                        raise Kitti360Error(src, "image", f"is {image.shape[1]}x{image.shape[0]}, {sensor}.yaml says {mei.width}x{mei.height}")
                    image = cv2.remap(image, *maps[sensor], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
                else:
                    w, h = calib.perspective[sensor].size
                    if image.shape[:2] != (h, w):
                        raise Kitti360Error(src, "image", f"is {image.shape[1]}x{image.shape[0]}, perspective.txt S_rect says {w}x{h}")
                if factor > 1:
                    image = cv2.resize(image, (intr[sensor]["w"], intr[sensor]["h"]), interpolation=cv2.INTER_AREA)
                if factor == 1 and sensor not in calib.fisheye:
                    shutil.copyfile(src, out / rel)
                else:
                    cv2.imwrite(str(out / rel), image)
            rig_frames.append({"sensor": sensor, "timestamp": round((int(stamp) - origin) * 1e-9, 9), "file_path": rel})
    rig_frames.sort(key=lambda f: (f["timestamp"], f["sensor"]))

    priors = _perturbed(config, calib.T_ref)
    rig_sensors = {}
    for sensor in sensors:
        prior, delta = priors[sensor]
        entry = {"type": "lidar" if sensor == VELODYNE else "camera", "T_ref_sensor": prior.tolist(), "time_offset": delta}
        entry.update(intr.get(sensor, {}))
        rig_sensors[sensor] = entry
    meta = {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(config).items() if k not in ("out", "overwrite")}
    meta.update(generator="moisst-kitti360-to-rig", time_origin=format_timestamp(origin), trajectory_source=pose_source.name,
                note="fisheye cameras rectified to pinhole images with the fisheye's own axes; ground_truth.json is the "
                     "dataset's calibration (its LiDAR calibration is itself good to a few cm only)")
    rig = {"format": FORMAT, "reference_sensor": REFERENCE, "trajectory": "reference_poses.txt", "sensors": rig_sensors,
           "frames": rig_frames, "metadata": meta}
    (out / "rig.json").write_text(json.dumps(rig, indent=1) + "\n")
    Calibration(REFERENCE, {s: calib.T_ref[s] for s in sensors}, {s: 0.0 for s in sensors}).write(out / "ground_truth.json")
    return out
