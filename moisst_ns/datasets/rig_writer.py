"""What the dataset converters (``moisst-kitti360-to-rig``, ``moisst-kitti-raw-to-rig``, ``moisst-bag-to-rig``) share
to write a ``moisst-rig/1`` dataset: the output folder, pinhole intrinsics, shrunk images, the reference trajectory
and ``rig.json`` / ``ground_truth.json``. numpy (OpenCV inside ``shrink``); no torch."""

from __future__ import annotations

import json
import shutil
from dataclasses import asdict
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
from jaxtyping import Float

from moisst_ns.rig.format import Calibration, rig_json, write_tum


def rigid(rotation=np.eye(3), translation=(0.0, 0.0, 0.0)) -> Float[np.ndarray, "4 4"]:
    """The 4x4 pose ``[rotation | translation]`` (float64)."""
    pose = np.eye(4)
    pose[:3, :3] = rotation
    pose[:3, 3] = translation
    return pose


def inverse(pose: Float[np.ndarray, "4 4"]) -> Float[np.ndarray, "4 4"]:
    """The inverse of a rigid 4x4 pose."""
    return rigid(pose[:3, :3].T, -pose[:3, :3].T @ pose[:3, 3])


def prepare_out(out: Path, sources: Sequence[Path], overwrite: bool, error: type, inside: str, clear: bool = True) -> Path:
    """Check that ``out`` can take a dataset: not inside any of ``sources`` (else ``error`` with the message ``inside``,
    ``{source}`` filled in), a folder, empty unless ``overwrite``; then (``clear``) empty it of a generated dataset (what
    a dataset generator or converter writes; other files there are left alone) and create it."""
    for source in map(Path, sources):
        if out.resolve() == source.resolve() or source.resolve() in out.resolve().parents:
            raise error(out, "--out", inside.format(source=source))
    if out.exists() and not out.is_dir():
        raise error(out, "--out", "exists and is not a folder")
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise error(out, "--out", "exists and is not empty; pass --overwrite to replace its dataset")
        if clear:
            for name in ("rig.json", "reference_poses.txt", "ground_truth.json"):
                (out / name).unlink(missing_ok=True)
            for name in ("images", "lidar"):
                if (out / name).is_dir():
                    shutil.rmtree(out / name)
    if clear:
        out.mkdir(parents=True, exist_ok=True)
    return out


def scaled_intrinsics(K: Float[np.ndarray, "3 3"], size: Tuple[int, int], factor: int) -> Dict[str, object]:
    """moisst-rig PINHOLE intrinsics (pixel centres at +0.5) of an OpenCV K (centres at integers) of ``size`` (w, h)
    pixels after shrinking by ``factor``."""
    w, h = size
    return {"camera_model": "PINHOLE", "w": w // factor, "h": h // factor, "fl_x": float(K[0, 0]) / factor,
            "fl_y": float(K[1, 1]) / factor, "cx": (float(K[0, 2]) + 0.5) / factor, "cy": (float(K[1, 2]) + 0.5) / factor}


def shrink(image: np.ndarray, factor: int) -> np.ndarray:
    """``image`` shrunk by the integer ``factor`` (``cv2.INTER_AREA``, sizes rounded down; 1: unchanged)."""
    import cv2

    return cv2.resize(image, (image.shape[1] // factor, image.shape[0] // factor), interpolation=cv2.INTER_AREA) if factor > 1 else image


def unit_quats(rotations: Float[np.ndarray, "num 3 3"]) -> Float[np.ndarray, "num 4"]:
    """Unit quaternions ``x, y, z, w`` with ``w >= 0`` of rotation matrices: Markley's variant of Shepperd's method as
    ``roma.rotmat_to_unitquat`` computes it, operation for operation (the same bits, without importing torch)."""
    (a11, a12, a13), (a21, a22, a23), (a31, a32, a33) = np.moveaxis(np.swapaxes(rotations, -1, -2), (-2, -1), (0, 1))
    x = np.stack([1 + a11 - a22 - a33, a12 + a21, a13 + a31, a23 - a32, a21 + a12, 1 + a22 - a33 - a11, a23 + a32, a31 - a13,
                  a31 + a13, a32 + a23, 1 + a33 - a11 - a22, a12 - a21, a23 - a32, a31 - a13, a12 - a21, 1 + a11 + a22 + a33],
                 axis=-1).reshape(-1, 4, 4)  # row i: 4 q_i q
    best = x[np.arange(len(x)), np.argmax(np.diagonal(x, axis1=-2, axis2=-1), axis=-1)]
    quats = best / np.linalg.norm(best, axis=-1, keepdims=True)
    return quats * np.where(quats[:, 3:4] < 0, -1.0, 1.0)


def write_trajectory(path: Path, stamps_s: Float[np.ndarray, "num"], poses: Float[np.ndarray, "num 4 4"], header: str) -> None:
    """TUM file of ``poses`` (metres) at ``stamps_s`` (seconds; quaternions with ``qw >= 0``)."""
    write_tum(path, stamps_s, poses[:, :3, 3], unit_quats(poses[:, :3, :3]), header=header)


def write_rig(out: Path, reference: str, sensors: Sequence[str], lidars: Sequence[str], intrinsics: Dict[str, Dict[str, object]],
              frames: List[dict], priors: Dict[str, Tuple[np.ndarray, float]], metadata: dict,
              truth: Optional[Dict[str, np.ndarray]] = None, config=None, accuracy=None) -> None:
    """``rig.json`` of ``sensors`` into ``out``: the ``lidars`` among them LiDARs, the others cameras; ``frames`` sorted
    by time first; ``priors`` name -> (T_ref_sensor, time offset); metadata: the fields of the dataclass ``config`` but
    out and overwrite (none without one), then ``metadata``. With ``truth`` (name -> T_ref_sensor), also
    ``ground_truth.json`` (offsets 0). ``accuracy``: the trajectory's stated errors (``rig.format.rig_json``)."""
    frames.sort(key=lambda f: (f["timestamp"], f["sensor"]))
    rig_sensors = {s: ("lidar" if s in lidars else "camera", priors[s][0], priors[s][1], intrinsics.get(s, {})) for s in sensors}
    meta = {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(config).items() if k not in ("out", "overwrite")} if config else {}
    meta.update(metadata)
    rig = rig_json(reference, "reference_poses.txt", rig_sensors, frames, meta, accuracy)
    (out / "rig.json").write_text(json.dumps(rig, indent=1) + "\n")
    if truth is not None:
        Calibration(reference, {s: truth[s] for s in sensors}, {s: 0.0 for s in sensors}).write(out / "ground_truth.json")
