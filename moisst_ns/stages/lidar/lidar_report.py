"""What the LiDAR-first stage leaves in a run folder: ``calibration.json``, ``lidar_first.json``, ``lidar_first.md``
and a convergence plot. No nerfstudio import."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np

from moisst_ns.rig.calibration import calibration_report_errors
from moisst_ns.rig.format import Calibration
from moisst_ns.rig.trust import PARAMETERS, finite_or_none, parameter_difference
from moisst_ns.stages.lidar.lidar_first import LidarFirstConfig, LidarFirstResult, LidarResult
from moisst_ns.stages.trust.observability import MIN_EFFECT, UNITS

REPORT_JSON = "lidar_first.json"
REPORT_MD = "lidar_first.md"
PLOT = "lidar_first_convergence.png"


def _change(result: LidarResult) -> Dict[str, float]:
    """The estimate's change from the prior: lever arm (cm, reference frame), rotation (deg), time (ms)."""
    import roma
    import torch

    rel = torch.from_numpy(result.prior.rotation.T @ result.estimate.rotation)
    return {"translation_cm": float(100 * np.linalg.norm(result.estimate.translation - result.prior.translation)),
            "rotation_deg": float(np.rad2deg(roma.rotmat_to_rotvec(rel).norm())),
            "time_ms": 1000 * (result.estimate.time_offset - result.prior.time_offset)}


def stage_summary(result: LidarFirstResult, config: LidarFirstConfig, prior: Calibration, truth: Optional[Calibration]) -> dict:
    """The JSON-ready record of a stage run (what ``lidar_first.json`` holds)."""
    sensors = {}
    before = calibration_report_errors(prior, truth) if truth else {}
    after = calibration_report_errors(result.calibration, truth) if truth else {}
    for name, r in result.lidars.items():
        entry = {
            "T_ref_sensor": r.estimate.matrix().tolist(), "time_offset": r.estimate.time_offset,
            "prior_T_ref_sensor": r.prior.matrix().tolist(), "prior_time_offset": r.prior.time_offset,
            "change_from_prior": _change(r), "scans": r.num_scans, "deskewed": r.deskewed, "dropped_scans": r.dropped,
            "wall_s": r.wall_s, "history": r.history,
            "observability": [asdict(d) for d in r.observability.dofs], "weak": r.observability.weak,
            "undetermined": r.undetermined(), "motion_undetermined": r.motion_undetermined(),
        }
        if r.held_check is not None:
            entry["held_check"] = r.held_check
        if r.sigma_split is not None:  # half the difference of the drive's two halves (None: a half could not be fitted)
            entry["sigma_split_half"] = [finite_or_none(v) for v in r.sigma_split]
        if r.view_search is not None:
            entry["view_search"] = r.view_search
        if r.sigma_trajectory is not None:  # what the trajectory's stated errors put into the estimate
            entry["sigma_trajectory"] = [finite_or_none(v) for v in r.sigma_trajectory]
        if truth:
            entry["errors_before"], entry["errors_after"] = before[name], after[name]
        sensors[name] = entry
    return {"stage": "lidar-first", "config": asdict(config), "min_effect_m": MIN_EFFECT, "sensors": sensors}


def observability_lines(result: LidarResult) -> List[str]:
    """One line per parameter: the RMS effect of a typical error, the formal sigma and the verdict."""
    return [f"  {d.name:<12} effect {1000 * d.effect_m:7.2f} mm   sigma {scale * d.sigma:9.4f} {unit:<3}  {f'WEAK: {d.reason}' if d.weak else 'constrained'}"
            for d, (scale, unit) in zip(result.observability.dofs, UNITS)]


def write_stage_files(out: Path, calibration: Calibration, summary: dict, md: List[str], report_json: str, report_md: str) -> None:
    """Write a stage's ``calibration.json``, ``summary`` (``report_json``) and ``md`` (``report_md``) into ``out`` (the camera stage's too)."""
    out.mkdir(parents=True, exist_ok=True)
    calibration.write(out / "calibration.json")
    (out / report_json).write_text(json.dumps(summary, indent=1) + "\n")
    (out / report_md).write_text("\n".join(md))


def truth_table(sensor: dict, start: str) -> List[str]:
    """A stage report's markdown table of one sensor's ``errors_before`` (row ``start``) and ``errors_after`` the truth."""
    b, a = sensor["errors_before"], sensor["errors_after"]
    return ["| | translation (cm) | rotation (deg) | time (ms) |", "|---|---|---|---|",
            f"| {start} | {b['translation_cm']:.2f} | {b['rotation_deg']:.3f} | {b['time_ms']:.2f} |",
            f"| estimate | {a['translation_cm']:.2f} | {a['rotation_deg']:.4f} | {a['time_ms']:.3f} |", ""]


def write_stage_outputs(result: LidarFirstResult, config: LidarFirstConfig, prior: Calibration, truth: Optional[Calibration],
                        out: Path) -> dict:
    """Write ``calibration.json``, ``lidar_first.json``, ``lidar_first.md`` and the convergence plot into ``out``."""
    summary = stage_summary(result, config, prior, truth)
    md = ["# LiDAR-first stage", "",
          "Each LiDAR calibrated against the reference trajectory from its own scans (point-to-plane scan consistency).",
          f"A parameter is weak when a typical prior error (10 cm, 1 deg, 10 ms) changes the residuals by < {1000 * MIN_EFFECT:.0f} mm RMS.", ""]
    for name, r in result.lidars.items():
        s = summary["sensors"][name]
        c = s["change_from_prior"]
        md += [f"## {name}", "", f"{r.num_scans} scans ({'raw sweeps, de-skewed' if r.deskewed else 'no per-point times'}), "
               f"{len(r.history)} outer iterations, {r.wall_s:.1f} s. Change from the prior: {c['translation_cm']:.2f} cm, "
               f"{c['rotation_deg']:.3f} deg, {c['time_ms']:+.2f} ms.", ""]
        md += truth_table(s, "prior") if truth else []
        md += ["```", *observability_lines(r), "```", ""]
        md += ["| iteration | radius (m) | pairs | correspondences | inlier RMS (mm) | step (cm / deg / ms) |", "|---|---|---|---|---|---|"]
        md += [f"| {h['iteration']} | {h['radius_m']:.2f} | {h['pairs']} | {h['correspondences']} | {1000 * h['inlier_rms_m']:.2f} | "
               f"{100 * h['change_m']:.3f} / {np.rad2deg(h['change_rad']):.4f} / {1000 * h['change_s']:.3f} |" for h in r.history]
        md += [""]
    md += [f"![convergence]({PLOT})", ""]
    write_stage_files(out, result.calibration, summary, md, REPORT_JSON, REPORT_MD)
    _plot(result, out / PLOT)
    return summary


def _plot(result: LidarFirstResult, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(9, 3.2))
    for name, r in result.lidars.items():
        it = [h["iteration"] for h in r.history]
        ax[0].semilogy(it, [1000 * h["inlier_rms_m"] for h in r.history], "o-", label=name)
        ax[1].semilogy(it, [max(100 * h["change_m"], 1e-4) for h in r.history], "o-", label=f"{name} (cm)")
    ax[0].set(xlabel="outer iteration", ylabel="inlier RMS (mm)", title="point-to-plane residuals")
    ax[1].set(xlabel="outer iteration", ylabel="lever-arm step (cm)", title="update per iteration")
    for a in ax:
        a.grid(True, alpha=0.3)
        a.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def stage_sigma(entry: dict):
    """A LiDAR's sigma from its LiDAR-first record (trust order; m, rad, s) and where it comes from: the formal one,
    at least half the split-half difference and the release check's spread where those ran, the prior's sigma for
    a parameter held at the prior (``lidar_first.held_sigma``), at least what the trajectory's stated errors put into
    it (``trajectory_noise.trajectory_spread``), and for a parameter placed against the cameras at the
    same instants (``shared_instant``, ``lidar_placement.place_lidars``) that placement's sigma, its lever arm's with what
    the time offset's sigma moves it along the drive; for one placed there but kept at the motion's, at least the whole
    difference of the two (KITTI raw 0048 seed 2: the OXTS trajectory's turn from image_00 not found, the motion's pitch
    0.65 deg off under a sigma of 0.13)."""
    sigma, source = [d["sigma"] for d in entry["observability"]], "LiDAR-first formal"
    if entry.get("sigma_split_half"):  # the two halves of the drive fitted apart (None, not measured: NaN, which fmax skips)
        sigma, source = list(np.fmax(sigma, np.asarray(entry["sigma_split_half"], dtype=float))), "LiDAR-first formal and split-half"
    if entry.get("held_check"):  # the free parameters' spread when the held ones are released; the held ones' prior sigma
        check = entry["held_check"]
        sigma, source = list(np.fmax(np.fmax(sigma, check["sigma_release"]), check.get("sigma_held", np.zeros(7)))), source + " and release"
    if entry.get("sigma_trajectory"):  # the trajectory's stated errors drawn again (trajectory_noise.trajectory_spread)
        sigma, source = list(np.fmax(sigma, np.asarray(entry["sigma_trajectory"], dtype=float))), source + " and the trajectory's errors"
    instant = entry.get("shared_instant") or {}
    for p in instant.get("taken", []):
        i = PARAMETERS.index(p)
        sigma[i] = float(np.hypot(instant["sigma"][i], instant["along_track"][i] * sigma[6])) if i < 3 else instant["sigma"][i]
    kept = [p for p in instant.get("placed", []) if p not in instant.get("taken", [])]
    if kept:  # placed there, the motion's kept: two estimates of it (in frames that may differ) apart by their whole difference
        apart = parameter_difference(np.asarray(entry["T_ref_sensor"]), 0.0, np.asarray(instant["T_ref_sensor"]), 0.0)
        for p in kept:
            sigma[PARAMETERS.index(p)] = float(max(sigma[PARAMETERS.index(p)], abs(apart[PARAMETERS.index(p)])))
    return sigma, source + (" and the shared instants" if instant.get("taken") or kept else "")
