"""Is the stated uncertainty calibrated? Each parameter's true error against its sigma, over benchmark runs.

Issue "Trust without ground truth": over the ``moisst-bench --quick`` rigs and seeds the true error of a parameter
must be within 3 sigma in >= 90 % of cases, and for a converged sensor sigma must not be more than 10x the true error
(a sigma that is always huge is as useless as none). The second is judged per sensor and kind (translation,
rotation, time offset) on the root-mean-square of the kind's sigmas against that of its errors: one parameter's
error alone is below a tenth of its sigma by chance in 8 % of Gaussian draws, a 3-vector's norm in under 0.1 %.
Where no sensor is converged (a drive that leaves some parameter weak marks every sensor ``weakly observable``), the
same ratio is also reported for the kinds without a weak parameter of every sensor not marked ``not converged``, so
the 10x rule is not vacuous; and every parameter beyond 5 sigma of a sensor not marked ``not converged`` is listed
(the issue: every sensor farther from the truth than 5x its sigma is marked ``not converged``).

Pure numpy/roma on ``calibration.json`` files; no nerfstudio import.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Dict, List

import numpy as np

KINDS = (("translation", slice(0, 3)), ("rotation", slice(3, 6)), ("time offset", slice(6, 7)))
"""Parameter groups (``rig.trust.PARAMETERS`` order) judged together for the 10x rule."""
MAX_SIGMA_RATIO = 10.0
"""A converged sensor's RMS sigma of a kind may be at most this many times its RMS true error."""


def sensor_coverage(estimate_file: Path, truth_file: Path) -> Dict[str, dict]:
    """Per non-reference sensor of an estimate that carries sigmas: its 7 true errors and sigmas.

    Args:
        estimate_file: a ``calibration.json`` with trust fields.
        truth_file: the rig's ``ground_truth.json``.

    Returns:
        ``{sensor: {"error": [7], "sigma": [7], "verdict": str, "weak": [names]}}``, both in ``rig.trust.PARAMETERS``
        order and in m, rad, s (error = estimate - truth as ``rig.trust.parameter_difference``); sensors without
        sigmas left out.
    """
    from moisst_ns.rig.format import load_calibration
    from moisst_ns.rig.trust import parameter_difference

    est, truth = load_calibration(estimate_file), load_calibration(truth_file)
    out = {}
    for name, trust in est.trust.items():
        sig = trust.sigmas()
        if name == est.reference_sensor or sig is None or name not in truth.T_ref_sensor:
            continue
        error = parameter_difference(truth.T_ref_sensor[name], truth.time_offset[name], est.T_ref_sensor[name], est.time_offset[name])
        sigma = [math.radians(s) if 3 <= k < 6 else s for k, s in enumerate(sig)]
        out[name] = {"error": [float(e) for e in error], "sigma": [float(s) for s in sigma], "verdict": trust.verdict,
                     "weak": list(trust.weak or [])}
    return out


def coverage_summary(runs: Dict[str, Dict[str, dict]]) -> dict:
    """The two figures of the issue over many runs.

    Args:
        runs: ``{run label: sensor_coverage(...)}``.

    Returns:
        ``{"within_3sigma": k, "finite": n, "fraction": k / n (nan if n == 0), "misses": [(run, sensor, parameter,
        |error| / sigma, verdict)], "converged_kinds": m, "too_wide": [(run, sensor, kind, rms sigma / rms error)],
        "largest_ratio": float, "observable_ratios": [rms sigma / rms error], "observable_too_wide": [...],
        "past_5sigma": [misses beyond 5 sigma not marked not converged]}``: parameters with a finite, positive sigma
        and a non-zero error only (an error of exactly zero is a parameter held at a true prior, not an estimate); the
        10x rule on converged sensors, and again on the kinds without a weak parameter of the sensors not marked
        ``not converged``.
    """
    from moisst_ns.rig.trust import PARAMETERS

    within = finite = kinds = 0
    misses, wide, largest, observable, observable_wide = [], [], 0.0, [], []
    for label, sensors in runs.items():
        for name, row in sensors.items():
            err, sig = np.abs(row["error"]), np.asarray(row["sigma"])
            held = err < 1e-12  # exactly the truth: held at a true prior (an ablation's fixed parameter), not an estimate
            for k, p in enumerate(PARAMETERS):
                if not (np.isfinite(sig[k]) and sig[k] > 0) or held[k]:
                    continue
                finite += 1
                if err[k] <= 3.0 * sig[k]:
                    within += 1
                else:
                    misses.append((label, name, p, float(err[k] / sig[k]), row["verdict"]))
            if row["verdict"] == "not converged":
                continue
            weak = set(row.get("weak", []))
            for kind, part in KINDS:
                s, e = np.sqrt(np.mean(sig[part] ** 2)), np.sqrt(np.mean(err[part] ** 2))
                if not (np.isfinite(s) and s > 0) or held[part].all():
                    continue
                ratio = float(s / e) if e > 0 else math.inf
                if not weak & set(PARAMETERS[part]):
                    observable.append(ratio)
                    if ratio > MAX_SIGMA_RATIO:
                        observable_wide.append((label, name, kind, ratio))
                if row["verdict"] != "converged":
                    continue
                kinds += 1
                largest = max(largest, ratio)
                if ratio > MAX_SIGMA_RATIO:
                    wide.append((label, name, kind, ratio))
    return {"within_3sigma": within, "finite": finite, "fraction": within / finite if finite else float("nan"), "misses": misses,
            "converged_kinds": kinds, "too_wide": wide, "largest_ratio": largest, "observable_ratios": observable, "observable_too_wide": observable_wide,
            "past_5sigma": [m for m in misses if m[3] > 5.0 and m[4] != "not converged"]}


def coverage_markdown(summary: dict) -> List[str]:
    """The benchmark's section on the uncertainty's calibration (lines of Markdown)."""
    lines = ["## Uncertainty: true error against the stated sigma", ""]
    if not summary["finite"]:
        return lines + ["No run carried sigmas.", ""]
    lines += [f"Within 3 sigma: **{summary['within_3sigma']} of {summary['finite']}** parameters with a finite sigma "
              f"({100 * summary['fraction']:.0f} %; target >= 90 %). Converged sensors: {summary['converged_kinds']} "
              f"sensor-kinds (translation, rotation, time offset), RMS sigma / RMS error at most {summary['largest_ratio']:.1f}x "
              f"(target <= {MAX_SIGMA_RATIO:g}x), {len(summary['too_wide'])} above.", ""]
    ratios = summary.get("observable_ratios", [])
    if ratios:
        lines += [f"Sensors not marked not converged, on their kinds without a weak parameter: {len(ratios)} sensor-kinds, RMS sigma / "
                  f"RMS error median {np.median(ratios):.1f}x, at most {max(ratios):.1f}x, {len(summary['observable_too_wide'])} above "
                  f"{MAX_SIGMA_RATIO:g}x.", ""]
    past = summary.get("past_5sigma", [])
    lines += [f"Parameters beyond 5 sigma of a sensor not marked not converged: {len(past)}"
              + (" (" + "; ".join(f"{r} {s} {p} {u:.1f}" for r, s, p, u, _ in past) + ")." if past else " (target: none)."), ""]
    if summary["misses"]:
        lines += ["| run | sensor | parameter | error / sigma | verdict |", "| --- | --- | --- | --- | --- |"]
        lines += [f"| {r} | {s} | {p} | {u:.1f} | {v} |" for r, s, p, u, v in sorted(summary["misses"], key=lambda m: -m[3])]
        lines += [""]
    if summary["too_wide"]:
        lines += ["Too wide (converged): " + "; ".join(f"{r} {s} {k} {u:.1f}x" for r, s, k, u in summary["too_wide"]), ""]
    return lines
