"""``moisst-eval``: errors of a calibration against the ground truth (or its difference from a second estimate, in σ
units), or the statistics of a run's history (``--history``); what each prints: ``docs/outputs.md``. Errors are one
line, ``moisst-eval: error: ...``, exit status 2. Nothing here imports nerfstudio.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Dict, Literal, Optional

import tyro

from moisst_ns.cli.common import fail
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


def _load_pair(first: Path, second: Path) -> tuple:
    """Both calibration files; ``RunError`` when one is unreadable or invalid or their reference sensors differ."""
    from moisst_ns.rig.format import RigFormatError, load_calibration

    try:
        a, b = load_calibration(first), load_calibration(second)
    except RigFormatError as err:
        raise RunError(str(err)) from None
    if a.reference_sensor != b.reference_sensor:
        raise RunError(f"{first}: reference_sensor: {a.reference_sensor!r}, but {second} has {b.reference_sensor!r}")
    return a, b


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

    estimate, truth = _load_pair(calibration, ground_truth)
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
    rows = sigma_table(cfg.calibration, cfg.ground_truth)
    if rows["second_is_estimate"]:
        return json.dumps(rows, indent=1) if cfg.as_json else format_sigma_table(rows)
    errors = compare_files(cfg.calibration, cfg.ground_truth)
    if cfg.as_json:
        return json.dumps(errors, indent=1)  # unchanged schema; the sigma units are in the table and sigma_table
    text = format_error_table(f"errors of {cfg.calibration} against {cfg.ground_truth}:", errors)
    return text + ("\n" + format_sigma_table(rows) if rows["sensors"] else "")


def sigma_table(first: Path, second: Path) -> dict:
    """Per sensor, the 7 parameter differences ``second - first`` (cm, deg, ms) and their size in sigma units.

    Args:
        first: calibration.json (an estimate).
        second: another estimate (it carries ``uncertainty``) or the truth.

    Returns:
        ``{"second_is_estimate": bool, "sensors": {name: {"difference": [7] (second - first; first - truth when the
        second is the truth), "sigma_units": [7 or None],
        "verdicts": [a, b]}}}``; ``sensors`` empty when no file carries sigmas.

    Raises:
        RunError: unreadable file or another reference sensor.
    """
    from moisst_ns.rig.trust import parameter_difference, sigma_units

    a, b = _load_pair(first, second)
    second_is_estimate = any(t.sigmas() is not None for t in b.trust.values())
    sensors = {}
    for name in a.T_ref_sensor:
        if name == a.reference_sensor or name not in b.T_ref_sensor:
            continue
        trusts = [a.trust.get(name)] + ([b.trust.get(name)] if second_is_estimate else [])
        diff = parameter_difference(a.T_ref_sensor[name], a.time_offset[name], b.T_ref_sensor[name], b.time_offset[name])
        if not second_is_estimate:
            diff = [-d for d in diff]  # the error of the estimate: first - truth
        units = sigma_units(diff, *trusts)
        if all(u is None for u in units):
            continue
        scale = [100.0] * 3 + [57.29577951308232] * 3 + [1000.0]
        sensors[name] = {"difference": [d * s for d, s in zip(diff, scale)], "sigma_units": units,
                         "verdicts": [t.verdict if t is not None else None for t in (a.trust.get(name), b.trust.get(name))]}
    if second_is_estimate and not sensors:
        raise RunError(f"{first}: sensors: no non-reference sensor in common with {second}")
    return {"first": str(first), "second": str(second), "second_is_estimate": second_is_estimate, "sensors": sensors}


def format_sigma_table(rows: dict) -> str:
    """Fixed-width table of ``sigma_table``: difference (cm, deg, ms) and |difference| / sigma per parameter."""
    from moisst_ns.rig.trust import PARAMETERS

    what = (f"difference {rows['second']} - {rows['first']}" if rows["second_is_estimate"]
            else f"error of {rows['first']} (minus {rows['second']})")
    lines = [f"{what} in sigma units (cm, deg, ms; |d|/sigma in brackets; "
             "> 3 disagrees):", f"{'sensor':<14}" + "".join(f"{p:>18}" for p in PARAMETERS) + "  verdicts"]
    for name, r in rows["sensors"].items():
        cells = [f"{d:+.3g} ({'-' if u is None else f'{u:.1f}'})" for d, u in zip(r["difference"], r["sigma_units"])]
        worst = max((u for u in r["sigma_units"] if u is not None), default=0.0)
        lines.append(f"{name:<14}" + "".join(f"{c:>18}" for c in cells) + f"  {' / '.join(str(v) for v in r['verdicts'])}"
                     + ("  DISAGREE" if worst > 3 else ""))
    return "\n".join(lines)


def main() -> None:
    """Console script ``moisst-eval``."""
    cfg = tyro.cli(EvaluateConfig)
    try:
        text = run_evaluate(cfg)
    except (RunError, OSError) as err:
        fail("moisst-eval", err)
    print(text)


if __name__ == "__main__":
    main()
