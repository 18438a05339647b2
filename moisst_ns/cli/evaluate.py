"""``moisst-eval``: errors of a calibration against the ground truth, or the statistics of a run's history.

* ``moisst-eval CALIBRATION.json GROUND_TRUTH.json [--json]``: per non-reference sensor, translation error (cm, L2),
  rotation error (deg, geodesic) and time error (ms, absolute) (``calibration_report_errors``).
* ``moisst-eval --history RUN_DIR [--last N] [--columns all|errors|estimates] [--json]``: per sensor, mean and
  standard deviation (population, numpy's default ``ddof=0``) of the last N logged rows of
  ``RUN_DIR/calibration_history.csv``: the error columns (when logged, i.e. the dataset has ground truth) and the
  estimates x, y, z (m), roll, pitch, yaw (deg), delta (ms). The paper reports the mean over its last epochs.

Errors are one line, ``moisst-eval: error: ...``, exit status 2. Nothing here imports nerfstudio.
"""

from __future__ import annotations

import csv
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Dict, List, Literal, Optional

import numpy as np
import tyro

ESTIMATE_COLUMNS = ("x", "y", "z", "roll", "pitch", "yaw", "delta_ms")
"""Estimate columns of calibration_history.csv (metres, degrees, milliseconds)."""
ERROR_COLUMNS = ("err_translation_cm", "err_rotation_deg", "err_time_ms")
"""Error columns of calibration_history.csv (empty when the dataset has no ground truth)."""
UNITS = {"x": "m", "y": "m", "z": "m", "roll": "deg", "pitch": "deg", "yaw": "deg", "delta_ms": "ms",
         "err_translation_cm": "cm", "err_rotation_deg": "deg", "err_time_ms": "ms"}
HISTORY_FILE = "calibration_history.csv"


class EvalError(ValueError):
    """Bad input to moisst-eval; the message is one line."""


@dataclass
class EvaluateConfig:
    """Errors of a calibration against ground truth, or mean/std of a run's last logged estimates.

    Either CALIBRATION.json GROUND_TRUTH.json, or --history RUN_DIR (then no positional arguments)."""

    calibration: Annotated[Optional[Path], tyro.conf.Positional, tyro.conf.arg(metavar="[CALIBRATION.json]")] = None
    """Estimated calibration (calibration.json of moisst-calibrate / moisst-export). Required unless --history."""
    ground_truth: Annotated[Optional[Path], tyro.conf.Positional, tyro.conf.arg(metavar="[GROUND_TRUTH.json]")] = None
    """True calibration (the dataset's ground_truth.json). Required unless --history."""
    history: Annotated[Optional[Path], tyro.conf.arg(metavar="RUN_DIR")] = None
    """Run folder holding calibration_history.csv (OUT/<method>/run), or the CSV itself."""
    last: Annotated[int, tyro.conf.arg(metavar="N")] = 10
    """With --history: statistics over each sensor's last N logged rows."""
    columns: Literal["all", "errors", "estimates"] = "all"
    """With --history: ``all`` (errors when logged, and estimates), ``errors`` (fails when the run logged none),
    ``estimates``."""
    as_json: Annotated[bool, tyro.conf.arg(name="json")] = False
    """Print JSON instead of a fixed-width table."""


# --- calibration vs ground truth ------------------------------------------------------------------------------


def compare_files(calibration: Path, ground_truth: Path) -> Dict[str, Dict[str, float]]:
    """Per-sensor errors of a calibration file against a ground-truth file (the reference sensor skipped).

    Args:
        calibration: estimated calibration.json.
        ground_truth: ground_truth.json.

    Returns:
        ``{sensor: {"translation_cm", "rotation_deg", "time_ms"}}`` for the non-reference sensors in both.

    Raises:
        EvalError: unreadable / invalid file (``RigFormatError`` message), other reference, no common sensor.
    """
    from moisst_ns.rig.calibration import calibration_report_errors
    from moisst_ns.rig.format import RigFormatError, load_calibration

    try:
        estimate, truth = load_calibration(calibration), load_calibration(ground_truth)
    except RigFormatError as err:
        raise EvalError(str(err)) from None
    if estimate.reference_sensor != truth.reference_sensor:
        raise EvalError(f"{calibration}: reference_sensor: {estimate.reference_sensor!r}, but {ground_truth} has {truth.reference_sensor!r}")
    errors = {k: v for k, v in calibration_report_errors(estimate, truth).items() if k != truth.reference_sensor}
    if not errors:
        raise EvalError(f"{calibration}: sensors: no non-reference sensor in common with {ground_truth}")
    return errors


# --- history --------------------------------------------------------------------------------------------------


def find_history(path: Path) -> Path:
    """calibration_history.csv of a run folder, the CSV itself, or the single run under a moisst-calibrate OUT.

    Args:
        path: ``RUN_DIR``, ``RUN_DIR/calibration_history.csv`` or moisst-calibrate's ``OUT``.

    Returns:
        The CSV path.

    Raises:
        EvalError: none found (or several runs under OUT).
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
            raise EvalError(f"{path}: several runs ({', '.join(str(f.parent) for f in found)}); pass one run folder")
    raise EvalError(f"{path}: {HISTORY_FILE} not found (pass a run folder, e.g. OUT/moisst-lite/run)")


def read_history(path: Path) -> Dict[str, Dict[str, np.ndarray]]:
    """Read calibration_history.csv into per-sensor columns.

    Args:
        path: the CSV (``step,sensor,x,...,delta_ms[,err_translation_cm,err_rotation_deg,err_time_ms]``).

    Returns:
        ``{sensor: {"step": (R,) int, column: (R,) float}}`` in file order; empty error cells are NaN, and an
        error column absent from the header is absent from the result.

    Raises:
        EvalError: missing columns, non-numeric values, no rows.
    """
    out: Dict[str, Dict[str, List[float]]] = {}
    with Path(path).open(newline="") as handle:
        reader = csv.DictReader(handle)
        header = reader.fieldnames or []
        missing = [c for c in ("step", "sensor") + ESTIMATE_COLUMNS if c not in header]
        if missing:
            raise EvalError(f"{path}: header: missing column(s) {', '.join(missing)}")
        columns = ("step",) + ESTIMATE_COLUMNS + tuple(c for c in ERROR_COLUMNS + ("elapsed_s",) if c in header)
        for lineno, row in enumerate(reader, start=2):
            entry = out.setdefault(row["sensor"], {c: [] for c in columns})
            for c in columns:
                cell = (row.get(c) or "").strip()
                try:
                    value = float(cell) if cell else math.nan
                except ValueError:
                    raise EvalError(f"{path}: line {lineno}: column {c}: not a number {cell!r}") from None
                if c not in ERROR_COLUMNS + ("elapsed_s",) and not cell:
                    raise EvalError(f"{path}: line {lineno}: column {c}: empty")
                entry[c].append(value)
    if not out:
        raise EvalError(f"{path}: no rows (the run logged nothing yet)")
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
        EvalError: ``last < 1``, or errors requested but not logged (no ground truth) for a sensor.
    """
    if last < 1:
        raise EvalError(f"--last: must be >= 1, got {last}")
    out = {}
    for name, cols in history.items():
        tail = {c: v[-last:] for c, v in cols.items()}
        logged = [c for c in ERROR_COLUMNS if c in tail and not np.isnan(tail[c]).any()]
        if columns == "errors" and len(logged) != len(ERROR_COLUMNS):
            raise EvalError(f"sensor {name}: no error columns in the history's last {last} rows (the dataset has no "
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


# --- output ---------------------------------------------------------------------------------------------------


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


def run_evaluate(cfg: EvaluateConfig) -> str:
    """The text moisst-eval prints for ``cfg``. Raises ``EvalError`` on bad input."""
    from moisst_ns.cli.calibrate import format_error_table

    if cfg.history is not None:
        if cfg.calibration is not None or cfg.ground_truth is not None:
            raise EvalError("--history takes no CALIBRATION.json / GROUND_TRUTH.json")
        path = find_history(cfg.history)
        stats = history_stats(read_history(path), cfg.last, cfg.columns)
        return json.dumps(stats, indent=1) if cfg.as_json else format_stats_table(stats, cfg.last)
    if cfg.calibration is None or cfg.ground_truth is None:
        raise EvalError("expected CALIBRATION.json GROUND_TRUTH.json, or --history RUN_DIR")
    errors = compare_files(cfg.calibration, cfg.ground_truth)
    if cfg.as_json:
        return json.dumps(errors, indent=1)
    return format_error_table(f"errors of {cfg.calibration} against {cfg.ground_truth}:", errors)


def main() -> None:
    """Console script ``moisst-eval``."""
    cfg = tyro.cli(EvaluateConfig)
    try:
        text = run_evaluate(cfg)
    except (EvalError, OSError) as err:
        message = str(err).replace("\r", "\\r").replace("\n", "\\n")
        print(f"moisst-eval: error: {message}", file=sys.stderr)
        raise SystemExit(2)
    print(text)


if __name__ == "__main__":
    main()
