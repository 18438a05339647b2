"""The files a ``moisst-rig/1`` dataset points to: TUM trajectories and LiDAR scans (``.npy``, KITTI ``.bin``,
``.npz`` with per-point times), and the one-line ``RigFormatError`` every reader raises (``<file>: <field>: <what is
wrong>``). ``rig.format`` reads rig.json itself. Nothing here writes into a dataset folder.
"""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import Optional, Tuple

import numpy as np


def _one_line(text) -> str:
    """Escape line breaks, so that a message built from user data (key names, paths) stays on one line."""
    return str(text).replace("\r", "\\r").replace("\n", "\\n")


class RigFormatError(ValueError):
    """A dataset does not follow ``moisst-rig/1``; the message names the file and the field."""

    def __init__(self, file: Path | str, fieldname: str, problem: str):
        self.file, self.field, self.problem = _one_line(file), _one_line(fieldname), _one_line(problem)
        super().__init__(f"{self.file}: {self.field}: {self.problem}")


def load_tum(path: Path) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read a TUM trajectory: ``timestamp tx ty tz qx qy qz qw`` per line, ``#`` comments allowed.

    Returns:
        (stamps (K,), positions (K, 3), unit quaternions x, y, z, w (K, 4)). Quaternions whose norm is within 1e-12
        of 1 are returned exactly as written (so ``write_tum`` -> ``load_tum`` round-trips bit for bit); the others
        (norm within 1e-3 of 1, else an error) are renormalised.
    """
    if not path.is_file():
        raise RigFormatError(path, "trajectory", "file not found")
    rows = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        if len(parts) != 8:
            raise RigFormatError(path, f"line {lineno}", f"expected 8 values 'timestamp tx ty tz qx qy qz qw', got {len(parts)}")
        try:
            rows.append([float(p) for p in parts])
        except ValueError:
            raise RigFormatError(path, f"line {lineno}", "not a number") from None
    data = np.asarray(rows, dtype=np.float64).reshape(-1, 8)
    if len(data) < 2:
        raise RigFormatError(path, "poses", f"needs at least 2 poses, got {len(data)}")
    if not np.all(np.isfinite(data)):
        raise RigFormatError(path, "poses", "contains NaN or inf")
    if np.any(np.diff(data[:, 0]) <= 0):
        bad = int(np.argmax(np.diff(data[:, 0]) <= 0)) + 2
        raise RigFormatError(path, "timestamp", f"timestamps must be strictly increasing (pose {bad})")
    norms = np.linalg.norm(data[:, 4:8], axis=1)
    if np.any(np.abs(norms - 1.0) > 1e-3):
        bad = int(np.argmax(np.abs(norms - 1.0) > 1e-3)) + 1
        raise RigFormatError(path, f"quaternion of pose {bad}", f"not a unit quaternion (norm {norms[bad - 1]:.6f})")
    quats = np.where(np.abs(norms - 1.0)[:, None] > 1e-12, data[:, 4:8] / norms[:, None], data[:, 4:8])
    return data[:, 0], data[:, 1:4], quats


def write_tum(path: Path, stamps, positions, quats_xyzw, header: str = "timestamp tx ty tz qx qy qz qw") -> None:
    """Write a TUM trajectory (full float precision)."""
    lines = [f"# {header}"] + [" ".join(repr(float(v)) for v in (s, *p, *q)) for s, p, q in zip(stamps, positions, quats_xyzw)]
    Path(path).write_text("\n".join(lines) + "\n")


def load_lidar_scan(path: Path | str, min_range: float = 0.0) -> Tuple[np.ndarray, Optional[np.ndarray], int]:
    """Read one LiDAR frame (``.npy`` (N,3), KITTI ``.bin`` (N,4), ``.npz`` with ``points`` and optional ``times``).

    Points with NaN/inf coordinates are dropped (and counted); so are points closer than ``min_range``.

    Returns:
        (points (M, 3) float32 in the LiDAR frame, per-point time offsets (M,) seconds or None, dropped count).
    """
    file = Path(path)
    if not file.is_file():
        raise RigFormatError(file, "file_path", "file not found")
    times = None
    suffix = file.suffix.lower()
    try:
        if suffix == ".npy":
            points = np.load(file, allow_pickle=False)
            key = "array"
        elif suffix == ".bin":
            size = file.stat().st_size
            if size % 16:  # np.fromfile would silently drop a partial trailing float
                raise RigFormatError(
                    file, "data", f"KITTI .bin must hold float32 x,y,z,intensity records; {size} bytes is not a multiple of 16 (4 floats)"
                )
            flat = np.fromfile(file, dtype=np.float32)
            points = flat.reshape(-1, 4)[:, :3]
            key = "data"
        elif suffix == ".npz":
            with np.load(file, allow_pickle=False) as data:
                if "points" not in data:
                    raise RigFormatError(file, "points", "missing array")
                points = data["points"]
                times = data["times"] if "times" in data else None
            key = "points"
        else:
            raise RigFormatError(file, "file_path", f"unsupported LiDAR file type {suffix!r}")
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as err:
        if isinstance(err, RigFormatError):
            raise
        raise RigFormatError(file, "data", f"unreadable ({err})") from None
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise RigFormatError(file, key, f"expected an (N, 3) array, got shape {points.shape}")
    if points.dtype.kind not in "fiu":
        raise RigFormatError(file, key, f"expected real numbers (float or integer), got dtype {points.dtype}")
    if times is not None:
        times = np.asarray(times, dtype=np.float64)
        if times.shape != (points.shape[0],):
            raise RigFormatError(file, "times", f"expected shape ({points.shape[0]},) to match points, got {times.shape}")
        if not np.all(np.isfinite(times)):
            raise RigFormatError(file, "times", "contains NaN or inf")
    finite = np.all(np.isfinite(points), axis=1)
    keep = finite & (np.linalg.norm(np.where(finite[:, None], points, 0), axis=1) > min_range)
    dropped = int((~finite).sum())
    points = points[keep].astype(np.float32)
    if times is not None:
        times = times[keep]
    if len(points) == 0:
        raise RigFormatError(file, key, "no points left after dropping non-finite points and range filtering (empty scan)")
    return points, times, dropped
