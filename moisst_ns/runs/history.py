"""``calibration_history.csv``: its schema, its one writer and its one reader, statistics and tables.

A row per logged step and non-reference sensor: ``step, sensor``, the estimate ``x, y, z`` (m, reference frame),
``roll, pitch, yaw`` (deg, ``pose_to_xyz_rpy``), ``delta_ms``, the errors against ``ground_truth.json`` when the
dataset has one (empty cells otherwise) and ``elapsed_s``. Rows at negative steps are the LiDAR-first stage's
outer iterations (the NeRF's rows follow from step 0). No nerfstudio import.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Dict, List

import numpy as np

from moisst_ns.runs import ERROR_KEYS, RunError


ESTIMATE_COLUMNS = ("x", "y", "z", "roll", "pitch", "yaw", "delta_ms")
"""Estimate columns of calibration_history.csv (metres, degrees, milliseconds)."""


ERROR_COLUMNS = tuple(f"err_{k}" for k in ERROR_KEYS)
"""Error columns of calibration_history.csv (empty when the dataset has no ground truth)."""


UNITS = {"x": "m", "y": "m", "z": "m", "roll": "deg", "pitch": "deg", "yaw": "deg", "delta_ms": "ms",
         "err_translation_cm": "cm", "err_rotation_deg": "deg", "err_time_ms": "ms"}


HISTORY_FILE = "calibration_history.csv"
HISTORY_COLUMNS = ("step", "sensor") + ESTIMATE_COLUMNS + ERROR_COLUMNS + ("elapsed_s",)
"""Every column of calibration_history.csv, in file order."""


def find_history(path: Path) -> Path:
    """calibration_history.csv of a run folder, the CSV itself, or the single run under a moisst-calibrate OUT.

    Args:
        path: ``RUN_DIR``, ``RUN_DIR/calibration_history.csv`` or moisst-calibrate's ``OUT``.

    Returns:
        The CSV path.

    Raises:
        RunError: none found (or several runs under OUT).
    """
    path = Path(path)
    if path.is_file():
        return path
    if (path / HISTORY_FILE).is_file():
        return path / HISTORY_FILE
    if path.is_dir():
        found = sorted(path.glob(f"*/run/{HISTORY_FILE}"))
        if len(found) == 1:
            return found[0]
        if len(found) > 1:
            raise RunError(f"{path}: several runs ({', '.join(str(f.parent) for f in found)}); pass one run folder")
    raise RunError(f"{path}: {HISTORY_FILE} not found (pass a run folder, e.g. OUT/moisst-lite/run)")


def read_history(path: Path) -> Dict[str, Dict[str, np.ndarray]]:
    """Read calibration_history.csv into per-sensor columns.

    Args:
        path: the CSV (``step,sensor,x,...,delta_ms[,err_translation_cm,err_rotation_deg,err_time_ms]``).

    Returns:
        ``{sensor: {"step": (R,) int, column: (R,) float}}`` in file order; empty error cells are NaN, and an
        error column absent from the header is absent from the result.

    Raises:
        RunError: missing columns, non-numeric values, no rows.
    """
    out: Dict[str, Dict[str, List[float]]] = {}
    with Path(path).open(newline="") as handle:
        reader = csv.DictReader(handle)
        header = reader.fieldnames or []
        missing = [c for c in ("step", "sensor") + ESTIMATE_COLUMNS if c not in header]
        if missing:
            raise RunError(f"{path}: header: missing column(s) {', '.join(missing)}")
        columns = ("step",) + ESTIMATE_COLUMNS + tuple(c for c in ERROR_COLUMNS + ("elapsed_s",) if c in header)
        for lineno, row in enumerate(reader, start=2):
            entry = out.setdefault(row["sensor"], {c: [] for c in columns})
            for c in columns:
                cell = (row.get(c) or "").strip()
                try:
                    value = float(cell) if cell else math.nan
                except ValueError:
                    raise RunError(f"{path}: line {lineno}: column {c}: not a number {cell!r}") from None
                if c not in ERROR_COLUMNS + ("elapsed_s",) and not cell:
                    raise RunError(f"{path}: line {lineno}: column {c}: empty")
                entry[c].append(value)
    if not out:
        raise RunError(f"{path}: no rows (the run logged nothing yet)")
    return {s: {c: np.asarray(v, dtype=np.int64 if c == "step" else np.float64) for c, v in cols.items()} for s, cols in out.items()}


def history_stats(history: Dict[str, Dict[str, np.ndarray]], last: int, columns: str = "all") -> Dict[str, dict]:
    """Mean and population standard deviation of each sensor's last ``last`` rows.

    Args:
        history: ``read_history`` output.
        last: number of trailing rows per sensor (all when fewer).
        columns: ``all`` (errors where logged, and estimates), ``errors`` or ``estimates``.

    Returns:
        ``{sensor: {"rows", "first_step", "last_step", "mean": {column: v}, "std": {column: v}}}``.

    Raises:
        RunError: ``last < 1``, or errors requested but not logged (no ground truth) for a sensor.
    """
    if last < 1:
        raise RunError(f"--last: must be >= 1, got {last}")
    out = {}
    for name, cols in history.items():
        tail = {c: v[-last:] for c, v in cols.items()}
        logged = [c for c in ERROR_COLUMNS if c in tail and not np.isnan(tail[c]).any()]
        if columns == "errors" and len(logged) != len(ERROR_COLUMNS):
            raise RunError(f"sensor {name}: no error columns in the history's last {last} rows (the dataset has no "
                            "ground_truth.json?); use --columns estimates")
        chosen = (logged if columns != "estimates" else []) + (list(ESTIMATE_COLUMNS) if columns != "errors" else [])
        out[name] = {
            "rows": int(len(tail["step"])),
            "first_step": int(tail["step"][0]),
            "last_step": int(tail["step"][-1]),
            "mean": {c: float(np.mean(tail[c])) for c in chosen},
            "std": {c: float(np.std(tail[c])) for c in chosen},
        }
    return out


def format_stats_table(stats: Dict[str, dict], last: int) -> str:
    """Fixed-width table of ``history_stats``: one line per sensor and column, mean and std."""
    lines = [f"mean and std (population) over each sensor's last {last} logged rows:",
             f"  {'sensor':<18}{'quantity':<24}{'mean':>14}{'std':>14}{'rows':>6}{'steps':>14}"]
    for name, s in stats.items():
        for c in s["mean"]:
            label = f"{c} ({UNITS[c]})"
            steps = f"{s['first_step']}-{s['last_step']}"
            lines.append(f"  {name:<18}{label:<24}{s['mean'][c]:>14.6g}{s['std'][c]:>14.6g}{s['rows']:>6}{steps:>14}")
    return "\n".join(lines)


def format_error_table(title: str, errors: Dict[str, Dict[str, float]]) -> str:
    """A fixed-width table of per-sensor translation (cm), rotation (deg) and time (ms) errors."""
    lines = [title, f"  {'sensor':<18}{'transl. (cm)':>14}{'rot. (deg)':>12}{'time (ms)':>11}"]
    for name, e in errors.items():
        lines.append(f"  {name:<18}{e['translation_cm']:>14.2f}{e['rotation_deg']:>12.3f}{e['time_ms']:>11.2f}")
    return "\n".join(lines)


def still_moving(history: Path, last: int = 10) -> Dict[str, str]:
    """Sensors whose last ``last`` logged estimates spread (std) more than 1 cm, 0.05 deg or 0.5 ms."""
    if not history.is_file():
        return {}
    try:
        columns = read_history(history)
    except RunError:  # nothing logged yet
        return {}
    out = {}
    for name, cols in columns.items():
        tail = np.stack([cols[c][-last:] for c in ESTIMATE_COLUMNS], axis=1)
        if len(tail) < 2:
            continue
        std = tail.std(axis=0)
        cm, deg, ms = 100 * np.linalg.norm(std[:3]), float(np.linalg.norm(std[3:6])), float(std[6])
        if cm > 1.0 or deg > 0.05 or ms > 0.5:
            out[name] = f"std {cm:.2f} cm, {deg:.3f} deg, {ms:.2f} ms"
    return out


def append_history(path: Path, step: int, rows: Dict[str, Dict[str, float]]) -> None:
    """The one writer of calibration_history.csv: append one row per sensor at ``step`` (header on a new file).

    Args:
        path: the CSV.
        step: training step (negative: the LiDAR-first stage's iterations).
        rows: ``{sensor: {column: value}}`` with any of ``HISTORY_COLUMNS[2:]`` (missing ones stay empty).
    """
    new = not path.exists()
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("a", newline="") as handle:
        writer = csv.writer(handle)
        if new:
            writer.writerow(HISTORY_COLUMNS)
        for name, values in rows.items():
            writer.writerow([step, name] + [f"{values[c]:.9g}" if c in values else "" for c in HISTORY_COLUMNS[2:]])


def stage_history_rows(stage: dict, truth) -> List[tuple]:
    """``(step, {sensor: values})`` of a stage's outer iterations, at steps -N..-1 per sensor.

    Args:
        stage: ``{"sensors": {name: {"history": [...]}}}``: a stage summary (``lidar_first.json``,
            ``camera_registration.json``) or several stages' sensors merged.
        truth: the ground truth ``Calibration``, or None (then no error columns).
    """
    import torch

    from moisst_ns.rig.calibration import calibration_report_errors
    from moisst_ns.rig.format import Calibration
    from moisst_ns.rig.geometry import pose_to_xyz_rpy

    out = []
    for name, entry in stage["sensors"].items():
        history = entry["history"]
        for k, h in enumerate(history):
            pose = np.asarray(h["T_ref_sensor"])
            values = dict(zip(ESTIMATE_COLUMNS[:6], pose_to_xyz_rpy(torch.from_numpy(pose)).tolist()))
            values.update(delta_ms=1000 * h["time_offset"], elapsed_s=h["elapsed_s"])
            if truth is not None:
                est = Calibration(truth.reference_sensor, {name: pose}, {name: h["time_offset"]})
                values.update({f"err_{c}": v for c, v in calibration_report_errors(est, truth)[name].items()})
            out.append((k - len(history), {name: values}))
    return out
