"""Readers of KITTI-360's download layout (calibration text files, MEI fisheye YAML, poses, timestamps), each
failing with a one-line ``Kitti360Error`` naming the file and the key, and the steps both KITTI converters share
(cameras, priors, images; the rest in ``moisst_ns.datasets.rig_writer``). Used by ``moisst_ns.datasets.kitti360``
and ``moisst_ns.datasets.kitti_raw`` (KITTI raw uses the same calibration key files and timestamps)."""

from __future__ import annotations

import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from moisst_ns.datasets.rig_writer import rigid, shrink
from moisst_ns.rig.format import RigFormatError

CAMERAS = ("image_00", "image_01", "image_02", "image_03")
"""The cameras of both datasets: KITTI raw's rectified 00/01 grey and 02/03 colour; KITTI-360's 00/01 perspective and
02/03 fisheye."""
PERSPECTIVE = ("image_00", "image_01")
"""The rectified perspective cameras (KITTI-360; in KITTI raw all four cameras are)."""
REFERENCE = "image_00"
"""The reference sensor of both KITTI converters: the rectified left grey camera."""
VELODYNE = "velodyne"
SUFFIX = {VELODYNE: ".bin", "oxts": ".txt"}
"""Frame file suffix of a sensor in both KITTI layouts (cameras: ``.png``)."""


class Kitti360Error(RigFormatError):
    """A KITTI-360 folder is incomplete or malformed; one line naming the file, the field and the problem."""


def _rigid(values: Sequence[float], file: Path, key: str) -> np.ndarray:
    """The 4x4 pose of 12 numbers ``[R | t]`` (row by row) read from ``file``'s ``key``, checking that R is a rotation."""
    values = np.asarray(values, dtype=np.float64).reshape(3, 4)
    _check_rotation(values[:, :3], file, key)
    return rigid(values[:, :3], values[:, 3])


class _Layout:
    """Frame files ``NNNNNNNNNN<SUFFIX>`` and ``timestamps*.txt`` of a KITTI layout's ``data_dir`` / ``sensor_dir``."""

    def frame_file(self, sensor: str, index: int) -> Path:
        return self.data_dir(sensor) / f"{index:010d}{SUFFIX.get(sensor, '.png')}"

    def timestamps(self, sensor: str, which: str = "") -> Path:
        """``timestamps.txt``, or ``timestamps_start.txt`` / ``timestamps_end.txt`` (``which``) of the Velodyne."""
        return self.sensor_dir(sensor) / (f"timestamps_{which}.txt" if which else "timestamps.txt")


def _check_rotation(rotation: np.ndarray, file: Path, key: str, tol: float = 1e-4) -> None:
    if not np.allclose(rotation @ rotation.T, np.eye(3), atol=tol) or np.linalg.det(rotation) < 0:
        raise Kitti360Error(file, key, "not a rotation (R R^T != I or det < 0)")


def _require(path: Path, what: str) -> Path:
    if not path.exists():
        raise Kitti360Error(path, what, "not found (see docs/kitti360.md or docs/kitti-raw.md for the folders to download)")
    return path


def _lines(path: Path) -> List[Tuple[int, str]]:
    """(line number, text without surrounding blanks) of the non-blank lines of the file ``path``."""
    lines = enumerate(_require(path, "(file)").read_text().splitlines(), start=1)
    return [(n, line.strip()) for n, line in lines if line.strip()]


def read_key_values(path: Path) -> Dict[str, np.ndarray]:
    """Read a ``key: v1 v2 ...`` text file (``calib_cam_to_pose.txt``, ``perspective.txt``).

    Returns:
        key -> float64 values; lines whose values are not all numbers (``calib_time: 09-Jan-2012 ...``) are skipped.
    """
    out: Dict[str, np.ndarray] = {}
    for line in _require(path, "(file)").read_text().splitlines():
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
    return {cam: _rigid(_values(table, cam, 12, path), path, cam) for cam in cameras}


def read_cam_to_velo(path: Path) -> np.ndarray:
    """``calib_cam_to_velo.txt`` (one line of 12 numbers) -> velo_T_cam0 (4x4)."""
    numbers = _require(path, "(file)").read_text().split()
    try:
        values = [float(v) for v in numbers]
    except ValueError:
        raise Kitti360Error(path, "cam0 -> velo", "not a number") from None
    if len(values) != 12:
        raise Kitti360Error(path, "cam0 -> velo", f"expected 12 numbers (3x4), got {len(values)}")
    return _rigid(values, path, "cam0 -> velo")


@dataclass
class Perspective:
    """Rectified pinhole camera from ``perspective.txt``."""

    K: np.ndarray
    """3x3 intrinsics of ``P_rect_0X`` (KITTI pixel convention: centre of pixel 0 at 0)."""
    R_rect: np.ndarray
    """3x3 ``R_rect_0X``: unrectified -> rectified camera frame."""
    size: Tuple[int, int]
    """(width, height) of ``S_rect_0X``."""
    offset: Optional[np.ndarray] = None
    """``K^-1 P_rect_0X[:, 3]``: ``P_rect_0X = K [I | offset]``, so rectified camera X sees a point ``x_0`` of
    rectified camera 0 at ``x_0 + offset`` (zero for camera 0; KITTI raw's stereo baselines)."""


def read_perspective(path: Path, cameras: Sequence[str], perspective: Sequence[str] = PERSPECTIVE) -> Dict[str, Perspective]:
    """``perspective.txt`` (KITTI-360) or ``calib_cam_to_cam.txt`` (KITTI raw) -> {image_0X: Perspective} for the
    cameras among ``cameras`` that are in ``perspective``."""
    table = read_key_values(path)
    out = {}
    for cam in [c for c in cameras if c in perspective]:
        n = cam[-2:]
        P = _values(table, f"P_rect_{n}", 12, path).reshape(3, 4)
        R = _values(table, f"R_rect_{n}", 9, path).reshape(3, 3)
        _check_rotation(R, path, f"R_rect_{n}")
        w, h = _values(table, f"S_rect_{n}", 2, path)
        if w <= 0 or h <= 0 or w != int(w) or h != int(h):
            raise Kitti360Error(path, f"S_rect_{n}", f"expected a positive integer width and height, got {w} {h}")
        if P[0, 0] <= 0 or P[1, 1] <= 0:
            raise Kitti360Error(path, f"P_rect_{n}", "focal lengths must be > 0")
        if abs(np.linalg.det(P[:, :3])) < 1e-12:
            raise Kitti360Error(path, f"P_rect_{n}", "its left 3x3 block (K) is singular")
        out[cam] = Perspective(K=P[:, :3].copy(), R_rect=R, size=(int(w), int(h)), offset=np.linalg.solve(P[:, :3], P[:, 3]))
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


@dataclass
class KittiCalibration:
    """What a KITTI dataset says about the rig: extrinsics in the rectified image_00 frame and intrinsics."""

    T_ref: Dict[str, np.ndarray]
    """sensor -> T_rect0_sensor (4x4), every camera asked for (and the Velodyne)."""
    perspective: Dict[str, Perspective]
    ref_T_body: np.ndarray
    """Rectified camera 0 <- the frame the dataset's trajectory poses (KITTI-360's vehicle pose frame of ``poses.txt``,
    KITTI raw's OXTS IMU): turns ``world_T_body`` into the reference trajectory."""
    fisheye: Dict[str, MeiCamera] = field(default_factory=dict)
    """KITTI-360's fisheye cameras."""


MEI_KEYS = {
    "mirror_parameters": ("xi",),
    "distortion_parameters": ("k1", "k2", "p1", "p2"),
    "projection_parameters": ("gamma1", "gamma2", "u0", "v0"),
}


def read_mei_yaml(path: Path) -> MeiCamera:
    """Read an ``image_0X.yaml`` MEI fisheye calibration (OpenCV FileStorage YAML starting with ``%YAML:1.0``)."""
    import yaml

    text = _require(path, "(file)").read_text()
    if text.startswith("%YAML"):
        text = text.partition("\n")[2]
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
    indices, poses = [], []
    for lineno, line in _lines(path):
        parts = line.split()
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
    stamps = []
    for lineno, text in _lines(path):
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
    return str(np.datetime64(int(ns), "ns")).replace("T", " ")


# ----------------------------------------------------------------------------------------------------------------
# Steps shared by the KITTI converters (their configs have cameras, downscale, perturb, seed, perturb_*)


def _cameras(config, cameras: Sequence[str], dataset: str) -> List[str]:
    """The reference and ``config.cameras`` in ``cameras`` order, after checking them and ``config.downscale``."""
    unknown = [c for c in config.cameras if c not in cameras]
    if unknown:
        raise Kitti360Error("(command line)", "--cameras", f"unknown camera {unknown[0]!r}; {dataset} has {', '.join(cameras)}")
    if config.downscale < 1:
        raise Kitti360Error("(command line)", "--downscale", f"must be >= 1, got {config.downscale}")
    return [REFERENCE] + [c for c in cameras if c in config.cameras and c != REFERENCE]


def _perturbed(config, T_ref: Dict[str, np.ndarray]) -> Dict[str, Tuple[np.ndarray, float]]:
    from moisst_ns.datasets.synth_rig import perturbed_priors

    return perturbed_priors(config, sorted(T_ref), {n: (T, 0.0) for n, T in T_ref.items()}, np.random.default_rng(config.seed), REFERENCE)


def _write_image(src: Path, dst: Path, size: Tuple[int, int], factor: int, copy: bool, says: str, remap=None) -> None:
    """Copy the image ``src`` to ``dst`` (``copy``), or write it as a 3-channel PNG, rectified by the ``cv2.remap`` maps
    ``remap`` and shrunk by ``factor``; it must be ``size`` (w, h) pixels, as the file ``says`` says."""
    import cv2

    image = cv2.imread(str(src), cv2.IMREAD_COLOR)  # grey images become 3 identical channels
    if image is None:
        raise Kitti360Error(src, "image", "unreadable image")
    if image.shape[1::-1] != tuple(size):
        raise Kitti360Error(src, "image", f"is {image.shape[1]}x{image.shape[0]}, {says} says {size[0]}x{size[1]}")
    if copy:
        shutil.copyfile(src, dst)
        return
    if remap is not None:
        image = cv2.remap(image, *remap, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    cv2.imwrite(str(dst), shrink(image, factor))
