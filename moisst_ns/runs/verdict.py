"""Which sensors to trust after a run: per-sensor flags from what the run measured, and the words that say so.

A sensor is flagged when
* it ends **worse than its prior** (ground truth only: a larger translation, rotation or time error after than before);
* it is **still moving** (its last logged estimates spread, ``runs.history.still_moving``) or **ran into a bound**;
* **depth mismatch**: the median |rendered depth - LiDAR depth| over a camera's render is above
  ``max(DEPTH_MISMATCH_M, DEPTH_MISMATCH_FRACTION x median LiDAR depth)``. At the reference camera (known poses)
  it means the scene or the LiDAR is wrong: a LiDAR calibrated by the LiDAR-first stage (from its own scans, not
  from the scene) is not blamed, nor is a camera held at its camera-registration estimate (registered against the
  stage's map); the other cameras are (they were registered against that scene); a LiDAR calibrated in the NeRF is.
  At another camera, with the reference's render in agreement, it flags that camera;
* ``calibration.json`` says so: the optional per-sensor fields ``verdict`` ("converged" | "not converged" |
  "weakly observable"), ``weak`` (parameters), ``reason`` and ``uncertainty`` are shown when present.

Weakly observable parameters (from the LiDAR-first stage or ``calibration.json``) are caveats, not flags: the drive
does not constrain them, so their value is the prior's or close to it. Pure Python; no torch, no nerfstudio.
"""

from __future__ import annotations

import math
from typing import Any, Dict, Iterable, List, Optional

from moisst_ns.runs import ERROR_KEYS

DEPTH_MISMATCH_M = 0.5
"""A median depth disagreement below this (metres) is never flagged (the scene's own error at the budgets here)."""
DEPTH_MISMATCH_FRACTION = 0.1
"""... nor below this share of the median LiDAR depth."""


def _worse(before: Dict[str, float], after: Dict[str, float]) -> List[str]:
    words = {"translation_cm": "translation", "rotation_deg": "rotation", "time_ms": "time"}
    return [words[k] for k in ERROR_KEYS if k in before and k in after and after[k] > before[k] * 1.0001 + 1e-9]


def _fmt(err: Dict[str, float]) -> str:
    return f"{err['translation_cm']:.2f} cm / {err['rotation_deg']:.3f} deg / {err['time_ms']:.2f} ms"


def sensor_verdicts(sensors: Iterable[str], summary: Dict[str, Any], calibration: Optional[Dict[str, Any]] = None,
                    renders: Iterable[Dict[str, Any]] = (), lidars: Iterable[str] = (),
                    reference: Optional[str] = None) -> Dict[str, Dict[str, Any]]:
    """Per sensor: ``flags`` (why not to trust it), ``caveats``, ``trust`` and the errors before/after when known.

    Args:
        sensors: the non-reference sensors.
        summary: ``OUT/summary.json`` of moisst-calibrate (``errors_before``/``errors_after``, ``still_moving``,
            ``hit_bounds``, ``lidar_first``, ``camera_registration``; every key optional).
        calibration: the parsed ``calibration.json`` (its optional per-sensor ``verdict``, ``weak``, ``reason``,
            ``uncertainty`` are used when present).
        renders: the report's renders (``camera``, ``median_depth_residual_m``, optional ``median_lidar_depth_m``).
        lidars: the LiDAR sensors among ``sensors`` (the ones whose points the renders checked).
        reference: the reference sensor (its render tells whether the scene agrees with the LiDAR at all).
    """
    sensors, lidars = list(sensors), [n for n in lidars]
    stage = set((summary.get("lidar_first") or {}))
    registered = {n for n, e in (summary.get("camera_registration") or {}).items() if isinstance(e, dict) and not e.get("kept_prior")}
    mismatch = {}  # camera -> text, for the renders whose depth disagrees with the LiDAR's
    for r in renders if lidars else ():
        residual = r.get("median_depth_residual_m")
        if residual is None or not math.isfinite(residual):
            continue
        limit = max(DEPTH_MISMATCH_M, DEPTH_MISMATCH_FRACTION * float(r.get("median_lidar_depth_m") or 0.0))
        if residual > limit:
            mismatch[r.get("camera")] = f"median |rendered depth - LiDAR depth| = {residual:.2f} m on {r.get('camera')}'s render (> {limit:.2f} m)"
    reference_bad = mismatch.get(reference) if reference is not None else None
    entries = calibration.get("sensors") if isinstance(calibration, dict) else None
    entries = entries if isinstance(entries, dict) else {}
    before, after = summary.get("errors_before") or {}, summary.get("errors_after") or {}
    out: Dict[str, Dict[str, Any]] = {}
    for name in sensors:
        flags: List[str] = []
        caveats: List[str] = []
        v: Dict[str, Any] = {}
        if name in before and name in after:
            v["errors_before"], v["errors_after"] = before[name], after[name]
            worse = _worse(before[name], after[name])
            if worse:
                flags.append(f"worse than its prior in {', '.join(worse)} ({_fmt(after[name])} after, {_fmt(before[name])} before)")
        if name in (summary.get("still_moving") or {}):
            flags.append(f"still moving ({summary['still_moving'][name]})")
        if name in (summary.get("hit_bounds") or {}):
            flags.append(f"ran into its bound on {', '.join(summary['hit_bounds'][name])}")
        if name in lidars and name not in stage and reference_bad:
            flags.append(f"depth mismatch: {reference_bad}")
        elif name in lidars and reference_bad:
            caveats.append(f"the scene disagrees with its depth ({reference_bad}); this LiDAR was calibrated from its "
                           "own scans, the scene is what is off")
        elif name not in lidars and name in registered and reference_bad:
            caveats.append(f"the scene disagrees with the LiDAR ({reference_bad}); this camera was registered by the "
                           "camera stage against its map, not against the scene")
        elif name not in lidars and reference_bad:
            flags.append(f"registered against an unreliable scene ({reference_bad})")
        elif name in mismatch:
            flags.append(f"depth mismatch: {mismatch[name]}")
        weak = list((summary.get("lidar_first") or {}).get(name, {}).get("weak") or [])
        entry = entries.get(name) if isinstance(entries.get(name), dict) else {}
        for key in ("verdict", "reason", "uncertainty"):
            if key in entry:
                v[key] = entry[key]
        weak += [str(w) for w in (entry.get("weak") if isinstance(entry.get("weak"), list) else []) if w not in weak]
        if entry.get("verdict") == "not converged":
            flags.append("not converged" + (f": {entry['reason']}" if entry.get("reason") else ""))
        if weak:
            caveats.append(f"weakly observable from this drive: {', '.join(weak)}"
                           + (f" ({entry['reason']})" if entry.get("reason") and entry.get("verdict") == "weakly observable" else ""))
            v["weak"] = weak
        v.update(flags=flags, caveats=caveats, trust=not flags)
        out[name] = v
    return out


def trust_lines(verdicts: Dict[str, Dict[str, Any]]) -> List[str]:
    """The run's last words: which sensors to trust and which not, and why."""
    trusted = [f"{n} ({'; '.join(v['caveats'])})" if v["caveats"] else n for n, v in verdicts.items() if v["trust"]]
    distrusted = [f"{n} ({'; '.join(v['flags'])})" for n, v in verdicts.items() if not v["trust"]]
    lines = []
    if distrusted:
        lines.append("Do not trust: " + "; ".join(distrusted) + ".")
    lines.append("Trust: " + (", ".join(trusted) if trusted else "no sensor of this run") + ".")
    return lines
