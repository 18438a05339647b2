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

import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Dict, Literal, Optional

import tyro

from moisst_ns.runs import RunError
from moisst_ns.runs.history import find_history, format_error_table, format_stats_table, history_stats, read_history


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
        RunError: unreadable / invalid file (``RigFormatError`` message), other reference, no common sensor.
    """
    from moisst_ns.rig.calibration import calibration_report_errors
    from moisst_ns.rig.format import RigFormatError, load_calibration

    try:
        estimate, truth = load_calibration(calibration), load_calibration(ground_truth)
    except RigFormatError as err:
        raise RunError(str(err)) from None
    if estimate.reference_sensor != truth.reference_sensor:
        raise RunError(f"{calibration}: reference_sensor: {estimate.reference_sensor!r}, but {ground_truth} has {truth.reference_sensor!r}")
    errors = {k: v for k, v in calibration_report_errors(estimate, truth).items() if k != truth.reference_sensor}
    if not errors:
        raise RunError(f"{calibration}: sensors: no non-reference sensor in common with {ground_truth}")
    return errors


# --- output ---------------------------------------------------------------------------------------------------


def run_evaluate(cfg: EvaluateConfig) -> str:
    """The text moisst-eval prints for ``cfg``. Raises ``RunError`` on bad input."""
    if cfg.history is not None:
        if cfg.calibration is not None or cfg.ground_truth is not None:
            raise RunError("--history takes no CALIBRATION.json / GROUND_TRUTH.json")
        path = find_history(cfg.history)
        stats = history_stats(read_history(path), cfg.last, cfg.columns)
        return json.dumps(stats, indent=1) if cfg.as_json else format_stats_table(stats, cfg.last)
    if cfg.calibration is None or cfg.ground_truth is None:
        raise RunError("expected CALIBRATION.json GROUND_TRUTH.json, or --history RUN_DIR")
    errors = compare_files(cfg.calibration, cfg.ground_truth)
    if cfg.as_json:
        return json.dumps(errors, indent=1)
    return format_error_table(f"errors of {cfg.calibration} against {cfg.ground_truth}:", errors)


def main() -> None:
    """Console script ``moisst-eval``."""
    cfg = tyro.cli(EvaluateConfig)
    try:
        text = run_evaluate(cfg)
    except (RunError, OSError) as err:
        message = str(err).replace("\r", "\\r").replace("\n", "\\n")
        print(f"moisst-eval: error: {message}", file=sys.stderr)
        raise SystemExit(2)
    print(text)


if __name__ == "__main__":
    main()
