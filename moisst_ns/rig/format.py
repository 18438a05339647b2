"""Reading, validating and writing the ``moisst-rig/1`` dataset format (see ``docs/rig-format.md``); the trajectory and
LiDAR files it points to are read by ``rig.files``.

Every problem with the input raises ``RigFormatError`` whose message is one line: ``<file>: <field>: <what is
wrong>``. Nothing here writes into a dataset folder; writers take an explicit output path.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np

from moisst_ns.rig.files import RigFormatError, load_lidar_scan, load_tum, write_tum  # noqa: F401 (the readers' names, imported from here too)
from moisst_ns.rig.trajectory_noise import TrajectoryAccuracy
from moisst_ns.rig.trust import SensorTrust, TrustFieldError, parse_trust

FORMAT = "moisst-rig/1"
SENSOR_TYPES = ("camera", "lidar")
CAMERA_MODELS = ("PINHOLE", "OPENCV")
CAMERA_KEYS = ("camera_model", "w", "h", "fl_x", "fl_y", "cx", "cy")
DISTORTION_KEYS = ("k1", "k2", "p1", "p2")
TOP_KEYS = ("format", "reference_sensor", "trajectory", "sensors", "frames")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
LIDAR_SUFFIXES = (".npy", ".bin", ".npz")


@dataclass
class SensorSpec:
    """One sensor of the rig as rig.json describes it."""

    name: str
    """Sensor name (a plain identifier: no path separators)."""
    type: str
    """``camera`` or ``lidar``."""
    T_ref_sensor: np.ndarray
    """Prior 4x4 pose of the sensor in the reference sensor's frame, metres."""
    time_offset: float = 0.0
    """Prior delta, seconds: a frame stamped t by this sensor was captured at reference time t + delta."""
    intrinsics: Dict[str, object] = field(default_factory=dict)
    """Camera only: nerfstudio transforms.json names (camera_model, w, h, fl_x, fl_y, cx, cy, k1, k2, p1, p2)."""
    readout_time: float = 0.0
    """Camera only: rolling-shutter readout, seconds, first row to last (the stamp is the middle row's time); 0: global."""


@dataclass
class FrameSpec:
    """One frame: which sensor, its own-clock timestamp, and its file (relative to the dataset folder)."""

    sensor: str
    timestamp: float
    file_path: str


@dataclass
class Rig:
    """A loaded and validated rig dataset."""

    root: Path
    """Dataset folder (holds rig.json)."""
    reference_sensor: str
    sensors: Dict[str, SensorSpec]
    frames: List[FrameSpec]
    trajectory_file: str
    """Path of the TUM trajectory, relative to ``root``."""
    trajectory_stamps: np.ndarray
    """(K,) absolute reference-clock timestamps."""
    trajectory_positions: np.ndarray
    """(K, 3) ``world_t_ref``, metres."""
    trajectory_quats_xyzw: np.ndarray
    """(K, 4) ``world_q_ref``, x, y, z, w."""
    trajectory_accuracy: TrajectoryAccuracy = field(default_factory=TrajectoryAccuracy)
    """What the trajectory's source states of its errors (rig.json ``trajectory_accuracy``; none: taken as exact)."""

    @property
    def sensor_names(self) -> List[str]:
        return list(self.sensors.keys())

    def frames_of(self, sensor: str) -> List[FrameSpec]:
        return [f for f in self.frames if f.sensor == sensor]

    def carry_trajectory(self, trajectory_T_reference: np.ndarray) -> None:
        """Carry the trajectory (in memory) from the frame it is given in to the reference sensor's:
        ``world_T_ref(t) = trajectory(t) @ trajectory_T_reference`` (``Calibration.trajectory_T_reference``)."""
        from scipy.spatial.transform import Rotation

        T = np.asarray(trajectory_T_reference, dtype=np.float64)
        turn = Rotation.from_quat(self.trajectory_quats_xyzw)
        self.trajectory_positions = self.trajectory_positions + turn.apply(T[:3, 3])
        self.trajectory_quats_xyzw = (turn * Rotation.from_matrix(T[:3, :3])).as_quat()


def _is_rigid(matrix: np.ndarray, tol: float = 1e-4) -> Optional[str]:
    if matrix.shape != (4, 4):
        return f"expected a 4x4 matrix, got shape {matrix.shape}"
    if not np.all(np.isfinite(matrix)):
        return "contains NaN or inf"
    if not np.allclose(matrix[3], [0, 0, 0, 1], atol=tol):
        return f"last row must be [0, 0, 0, 1], got {matrix[3].tolist()}"
    rot = matrix[:3, :3]
    if not np.allclose(rot.T @ rot, np.eye(3), atol=tol) or abs(np.linalg.det(rot) - 1.0) > tol:
        return "rotation block is not orthonormal with determinant +1 (not a rigid transform)"
    return None


def parse_rigid(value, file: Path | str, fieldname: str) -> np.ndarray:
    """A 4x4 rigid transform from JSON, or ``RigFormatError`` naming file and field."""
    try:
        matrix = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise RigFormatError(file, fieldname, "must be a 4x4 list of numbers") from None
    problem = _is_rigid(matrix)
    if problem:
        raise RigFormatError(file, fieldname, problem)
    return matrix


def _number(value, file, fieldname, positive=False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise RigFormatError(file, fieldname, f"must be a finite number, got {value!r}")
    if positive and value <= 0:
        raise RigFormatError(file, fieldname, f"must be > 0, got {value!r}")
    return float(value)


def _require(raw: dict, keys, file, where: str = "", problem: str = "missing", allowed=None, unknown: str = "unknown key") -> None:
    """``RigFormatError`` naming the first of ``keys`` that ``raw`` lacks, then (with ``allowed``) the first of its keys
    not in ``allowed`` (the field ``where`` + the key)."""
    for key in keys:
        if key not in raw:
            raise RigFormatError(file, f"{where}{key}", problem)
    extra = sorted(set(raw) - set(allowed)) if allowed is not None else []
    if extra:
        raise RigFormatError(file, f"{where}{extra[0]}", unknown)


def check_name(name: str, file, fieldname: str) -> str:
    """Sensor names become folder and metric names: refuse anything that could act as a path."""
    if (
        not isinstance(name, str) or not name or name in (".", "..") or any(c in name for c in "/\\\0:")
        or name.strip() != name or not name.isprintable()
    ):
        raise RigFormatError(file, fieldname, f"invalid sensor name {name!r} (no '/', '\\', ':', '..', control characters or leading/trailing blanks)")
    return name


def resolve_in(root: Path, relative: str, file, fieldname: str) -> Path:
    """Resolve a dataset-relative path, refusing absolute paths and ones that escape the dataset folder."""
    if not isinstance(relative, str) or not relative:
        raise RigFormatError(file, fieldname, "must be a non-empty relative path")
    rel = Path(relative)
    if rel.is_absolute():
        raise RigFormatError(file, fieldname, f"{relative!r} must be relative to the dataset folder")
    resolved = (root / rel).resolve()
    if root.resolve() not in resolved.parents and resolved != root.resolve():
        raise RigFormatError(file, fieldname, f"{relative!r} points outside the dataset folder")
    return resolved


def _parse_sensor(name: str, raw, file: Path) -> SensorSpec:
    where = f"sensors.{name}"
    if not isinstance(raw, dict):
        raise RigFormatError(file, where, "must be an object")
    stype = raw.get("type")
    if stype not in SENSOR_TYPES:
        raise RigFormatError(file, f"{where}.type", f"must be one of {SENSOR_TYPES}, got {stype!r}")
    allowed = {"type", "T_ref_sensor", "time_offset"}
    if stype == "camera":
        allowed |= set(CAMERA_KEYS) | set(DISTORTION_KEYS) | {"k3", "k4", "readout_time"}
    _require(raw, ["T_ref_sensor"], file, f"{where}.", allowed=allowed, unknown=f"unknown key for a {stype}")
    spec = SensorSpec(
        name=name,
        type=stype,
        T_ref_sensor=parse_rigid(raw["T_ref_sensor"], file, f"{where}.T_ref_sensor"),
        time_offset=_number(raw.get("time_offset", 0.0), file, f"{where}.time_offset"),
    )
    if stype == "camera":
        _require(raw, CAMERA_KEYS, file, f"{where}.", "missing (required for a camera)")
        model = raw["camera_model"]
        if model not in CAMERA_MODELS:
            raise RigFormatError(file, f"{where}.camera_model", f"unsupported camera model {model!r}; supported: {', '.join(CAMERA_MODELS)}")
        intr: Dict[str, object] = {"camera_model": model}
        for key in ("w", "h"):
            value = raw[key]
            if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
                raise RigFormatError(file, f"{where}.{key}", f"must be a positive integer, got {value!r}")
            intr[key] = value
        for key in ("fl_x", "fl_y", "cx", "cy") + DISTORTION_KEYS + ("k3", "k4"):  # the focal lengths > 0, no distortion by default
            intr[key] = _number(raw.get(key, 0.0), file, f"{where}.{key}", positive=key in ("fl_x", "fl_y"))
        if model == "PINHOLE" and any(intr[k] != 0.0 for k in DISTORTION_KEYS + ("k3", "k4")):
            raise RigFormatError(file, f"{where}.camera_model", "PINHOLE cameras take no distortion; use OPENCV")
        spec.readout_time = _number(raw.get("readout_time", 0.0), file, f"{where}.readout_time")
        if spec.readout_time < 0:
            raise RigFormatError(file, f"{where}.readout_time", f"must be >= 0 seconds, got {spec.readout_time!r}")
        spec.intrinsics = intr
    return spec


def _image_size(path: Path) -> Tuple[int, int]:
    from PIL import Image

    with Image.open(path) as img:
        return img.size


def read_json(file: Path) -> object:
    """Parse a JSON file; a syntax error is a one-line ``RigFormatError`` naming the file, line and column."""
    try:
        return json.loads(file.read_text())
    except json.JSONDecodeError as err:
        msg = err.msg[: -len(" at")] + " there" if err.msg.endswith(" starting at") else err.msg
        raise RigFormatError(file, f"line {err.lineno}, column {err.colno}", f"invalid JSON: {msg}") from None
    except UnicodeDecodeError as err:
        raise RigFormatError(file, f"byte {err.start}", "not UTF-8 text") from None


def load_rig(dataset: Path | str, check_files: bool = True) -> Rig:
    """Load and validate ``DATASET/rig.json`` (and its trajectory, and the frames' files).

    Args:
        dataset: the dataset folder, or the rig.json file itself.
        check_files: check that every frame's file exists, images have the size w x h, scans are readable.

    Returns:
        The validated rig.
    """
    path = Path(dataset)
    file = path if path.suffix == ".json" else path / "rig.json"
    root = file.parent
    if not root.exists():
        raise RigFormatError(root, "dataset", "folder not found")
    if not root.is_dir():
        raise RigFormatError(root, "dataset", "not a folder (give the dataset folder holding rig.json)")
    if not file.is_file():
        raise RigFormatError(file, "rig.json", "file not found (the dataset folder has no rig.json)")
    raw = read_json(file)
    if not isinstance(raw, dict):
        raise RigFormatError(file, "(top level)", "must be a JSON object")
    _require(raw, TOP_KEYS, file, allowed=TOP_KEYS + ("comment", "metadata", "trajectory_accuracy"))
    if raw["format"] != FORMAT:
        raise RigFormatError(file, "format", f"expected {FORMAT!r}, got {raw['format']!r}")
    if not isinstance(raw["sensors"], dict) or not raw["sensors"]:
        raise RigFormatError(file, "sensors", "must be a non-empty object")
    sensors = {check_name(n, file, f"sensors.{n}"): _parse_sensor(n, s, file) for n, s in raw["sensors"].items()}
    ref = raw["reference_sensor"]
    if not isinstance(ref, str) or ref not in sensors:
        raise RigFormatError(file, "reference_sensor", f"{ref!r} is not one of the sensors {sorted(sensors)}")
    if not np.allclose(sensors[ref].T_ref_sensor, np.eye(4), atol=1e-6):
        raise RigFormatError(file, f"sensors.{ref}.T_ref_sensor", "the reference sensor's extrinsic must be the identity")
    if sensors[ref].time_offset != 0.0:
        raise RigFormatError(file, f"sensors.{ref}.time_offset", "the reference sensor's time offset must be 0")
    traj_path = resolve_in(root, raw["trajectory"], file, "trajectory")
    traj_stamps, positions, quats = load_tum(traj_path)

    if not isinstance(raw["frames"], list) or not raw["frames"]:
        raise RigFormatError(file, "frames", "must be a non-empty list")
    frames: List[FrameSpec] = []
    for i, fr in enumerate(raw["frames"]):
        where = f"frames[{i}]"
        if not isinstance(fr, dict):
            raise RigFormatError(file, where, "must be an object")
        _require(fr, ("sensor", "timestamp", "file_path"), file, f"{where}.", allowed=("sensor", "timestamp", "file_path"))
        if not isinstance(fr["sensor"], str) or fr["sensor"] not in sensors:
            raise RigFormatError(file, f"{where}.sensor", f"unknown sensor {fr['sensor']!r}")
        stamp = _number(fr["timestamp"], file, f"{where}.timestamp")
        fpath = resolve_in(root, fr["file_path"], file, f"{where}.file_path")
        stype = sensors[fr["sensor"]].type
        suffixes = IMAGE_SUFFIXES if stype == "camera" else LIDAR_SUFFIXES
        if fpath.suffix.lower() not in suffixes:
            raise RigFormatError(file, f"{where}.file_path", f"a {stype} frame must be one of {suffixes}, got {fr['file_path']!r}")
        if check_files:
            if not fpath.is_file():
                raise RigFormatError(file, f"{where}.file_path", f"file not found: {fpath}")
            if stype == "camera":
                intr = sensors[fr["sensor"]].intrinsics
                try:
                    size = _image_size(fpath)
                except Exception as err:  # PIL raises several types for unreadable images
                    raise RigFormatError(fpath, f"{where}.file_path", f"unreadable image ({type(err).__name__})") from None
                if size != (intr["w"], intr["h"]):
                    raise RigFormatError(
                        fpath, f"{where} (sensor {fr['sensor']})", f"image is {size[0]}x{size[1]}, rig.json says w x h = {intr['w']}x{intr['h']}"
                    )
        frames.append(FrameSpec(sensor=fr["sensor"], timestamp=stamp, file_path=fr["file_path"]))
    for name in sensors:
        if not any(f.sensor == name for f in frames):
            raise RigFormatError(file, f"sensors.{name}", "has no frames")
        stamps = np.unique([f.timestamp for f in frames if f.sensor == name])
        if len(stamps) > 1 and sensors[name].readout_time >= (period := round(float(np.median(np.diff(stamps))), 9)):
            raise RigFormatError(file, f"sensors.{name}.readout_time", f"must be < the camera's frame period {period:.6g} s, got {sensors[name].readout_time!r}")
    return Rig(root=root, reference_sensor=ref, sensors=sensors, frames=frames, trajectory_file=raw["trajectory"],
               trajectory_stamps=traj_stamps, trajectory_positions=positions, trajectory_quats_xyzw=quats,
               trajectory_accuracy=TrajectoryAccuracy.parse(raw.get("trajectory_accuracy"), file))


def rig_to_json(rig: Rig) -> dict:
    """The rig.json content of ``rig`` (inverse of ``load_rig``)."""
    rolling = {n: {"readout_time": s.readout_time} for n, s in rig.sensors.items() if s.readout_time}
    return rig_json(rig.reference_sensor, rig.trajectory_file,
                    {n: (s.type, s.T_ref_sensor, s.time_offset, {**s.intrinsics, **rolling.get(n, {})}) for n, s in rig.sensors.items()},
                    [{"sensor": f.sensor, "timestamp": f.timestamp, "file_path": f.file_path} for f in rig.frames], accuracy=rig.trajectory_accuracy)


def rig_json(reference_sensor: str, trajectory: str, sensors: Dict[str, tuple], frames: List[dict],
             metadata: Optional[dict] = None, accuracy: Optional[TrajectoryAccuracy] = None) -> dict:
    """The rig.json content (``moisst-rig/1``) from its parts; the one place that lays out the file.

    Args:
        reference_sensor: Name of the reference sensor.
        trajectory: Path of the TUM trajectory, relative to the dataset folder.
        sensors: ``name -> (type, T_ref_sensor (4, 4) metres, time_offset seconds, intrinsics dict)``.
        frames: ``{"sensor", "timestamp", "file_path"}`` per frame, in file order.
        metadata: Free-form provenance written under ``"metadata"`` (omitted when None).
        accuracy: The trajectory's stated errors, ``"trajectory_accuracy"`` (omitted when None or nothing stated).

    Returns: the JSON object, ready for ``json.dumps``.
    """
    entries = {name: {"type": kind, "T_ref_sensor": np.asarray(T).tolist(), "time_offset": float(delta), **intrinsics}
               for name, (kind, T, delta, intrinsics) in sensors.items()}
    stated = {"trajectory_accuracy": asdict(accuracy)} if accuracy is not None and accuracy.stated() else {}
    out = {"format": FORMAT, "reference_sensor": reference_sensor, "trajectory": trajectory, **stated, "sensors": entries, "frames": frames}
    return out if metadata is None else {**out, "metadata": metadata}


@dataclass
class Calibration:
    """Extrinsics and time offsets of every sensor: the ground_truth.json / calibration.json schema."""

    reference_sensor: str
    T_ref_sensor: Dict[str, np.ndarray]
    time_offset: Dict[str, float]
    trust: Dict[str, SensorTrust] = field(default_factory=dict)
    """Optional per-sensor uncertainty and verdict (``moisst_ns.rig.trust``); absent in older files."""
    trajectory_T_reference: Optional[np.ndarray] = None
    """The reference sensor's pose (4x4, metres) in the frame the rig's trajectory is given in, when a stage found
    them to differ (``stages.lidar.lidar_placement.trajectory_turn``): ``world_T_ref(t) = trajectory(t) @ this``, and
    every ``T_ref_sensor`` is relative to the reference sensor itself. None (absent in the file): the identity."""

    def to_json(self) -> dict:
        turn = {} if self.trajectory_T_reference is None else {"trajectory_T_reference": np.asarray(self.trajectory_T_reference).tolist()}
        return {
            "reference_sensor": self.reference_sensor,
            **turn,
            "sensors": {
                n: {"T_ref_sensor": np.asarray(self.T_ref_sensor[n]).tolist(), "time_offset": float(self.time_offset[n]),
                    **(self.trust[n].to_json() if n in self.trust else {})}
                for n in self.T_ref_sensor
            },
        }

    def write(self, path: Path) -> None:
        Path(path).write_text(json.dumps(self.to_json(), indent=1) + "\n")

    @classmethod
    def from_rig(cls, rig: Rig) -> "Calibration":
        """The priors of a rig, as a calibration."""
        return cls(rig.reference_sensor, {n: s.T_ref_sensor for n, s in rig.sensors.items()}, {n: s.time_offset for n, s in rig.sensors.items()})


def load_calibration(path: Path | str) -> Calibration:
    """Read ground_truth.json / calibration.json, validating every field."""
    file = Path(path)
    if not file.is_file():
        raise RigFormatError(file, "(file)", "file not found")
    raw = read_json(file)
    if not isinstance(raw, dict):
        raise RigFormatError(file, "(top level)", "must be a JSON object")
    _require(raw, ("reference_sensor", "sensors"), file)
    if not isinstance(raw["sensors"], dict) or not isinstance(raw["reference_sensor"], str) or raw["reference_sensor"] not in raw["sensors"]:
        raise RigFormatError(file, "reference_sensor", f"{raw['reference_sensor']!r} is not in sensors")
    transforms, offsets, trust = {}, {}, {}
    for name, entry in raw["sensors"].items():
        check_name(name, file, f"sensors.{name}")
        if not isinstance(entry, dict) or "T_ref_sensor" not in entry:
            raise RigFormatError(file, f"sensors.{name}.T_ref_sensor", "missing")
        transforms[name] = parse_rigid(entry["T_ref_sensor"], file, f"sensors.{name}.T_ref_sensor")
        offsets[name] = _number(entry.get("time_offset", 0.0), file, f"sensors.{name}.time_offset")
        try:
            found = parse_trust(entry)
        except TrustFieldError as err:
            raise RigFormatError(file, f"sensors.{name}.{err.field}", err.problem) from None
        if found is not None:
            trust[name] = found
    turn = parse_rigid(raw["trajectory_T_reference"], file, "trajectory_T_reference") if "trajectory_T_reference" in raw else None
    return Calibration(raw["reference_sensor"], transforms, offsets, trust, turn)
