"""``moisst-report RUN_DIR_OR_CONFIG [--output-dir DIR]``: diagnostics of a calibration run, as images and Markdown.

Writes into ``DIR`` (default ``RUN/report``):

* ``overlays/``: (a) LiDAR points projected onto camera images with the PRIOR extrinsics and time offsets and with
  the CALIBRATED ones, coloured by depth, side by side (MOISST paper Fig. 3), for a few frames per camera.
* ``renders/``: (b) the image the model renders at a camera frame's calibrated pose (one frame per camera, small),
  its depth, and the calibrated LiDAR points drawn over it.
* ``convergence/``: (c) per sensor, the errors (when logged) and the estimates against the step, from
  ``calibration_history.csv``.
* ``report.md``: (d) links to all of them and a per-sensor table (the history's last row), preceded by the verdict:
  which sensors to trust, the errors before (priors) and after (with ground truth), each sensor's flags
  (``moisst_ns.runs.verdict``: worse than its prior, still moving, depth mismatch, the optional ``verdict`` /
  ``weak`` / ``reason`` / ``uncertainty`` of calibration.json).
* ``report.json``: the verdicts and the renders' depth statistics, for scripts.

Poses and scans: ``report_views`` (each point at its own time with the rig's pose model; per camera frame the LiDAR
frame nearest in reference-clock time, the same scan in both panels); projection and pixel convention:
``report_images.project_points``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Dict, List, Optional

import numpy as np

from moisst_ns.report_images import COLORMAP
from moisst_ns.runs.history import ERROR_COLUMNS, ESTIMATE_COLUMNS
from moisst_ns.report_views import make_overlays, make_renders


def convergence_plots(history: Dict[str, Dict[str, np.ndarray]], truth: Optional[Dict[str, Dict[str, float]]], out_dir: Path) -> Dict[str, str]:
    """(c): per sensor, errors (when logged) and estimates against the step (matplotlib, Agg canvas).

    Args:
        history: ``moisst_ns.runs.history.read_history`` output.
        truth: per sensor ``{x, y, z, roll, pitch, yaw, delta_ms}`` of the ground truth (dashed lines), or None.
        out_dir: the report folder.

    Returns:
        ``{sensor: png path}``.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    files = {}
    (out_dir / "convergence").mkdir(parents=True, exist_ok=True)
    for name, cols in history.items():
        steps = cols["step"]
        errors = [c for c in ERROR_COLUMNS if c in cols and np.isfinite(cols[c]).any()]
        rows = 2 if errors else 1
        fig = Figure(figsize=(12, 3.2 * rows))
        FigureCanvasAgg(fig)
        axes = fig.subplots(rows, 3, squeeze=False)
        if errors:
            for ax, c, label in zip(axes[0], ERROR_COLUMNS, ("translation error (cm)", "rotation error (deg)", "time error (ms)")):
                ax.plot(steps, cols[c], marker=".")
                ax.set_title(label), ax.set_xlabel("step"), ax.grid(alpha=0.3)
        groups = ((("x", "y", "z"), "position (m)"), (("roll", "pitch", "yaw"), "roll / pitch / yaw (deg)"), (("delta_ms",), "time offset (ms)"))
        for ax, (keys, label) in zip(axes[-1], groups):
            for key in keys:
                line = ax.plot(steps, cols[key], marker=".", label=key)[0]
                if truth is not None and name in truth:
                    ax.axhline(truth[name][key], color=line.get_color(), linestyle="--", linewidth=1)
            ax.set_title(label + (" (dashed: truth)" if truth is not None else "")), ax.set_xlabel("step"), ax.grid(alpha=0.3)
            if len(keys) > 1:
                ax.legend(fontsize="small")
        fig.suptitle(name)
        fig.tight_layout()
        path = out_dir / "convergence" / f"{name}.png"
        fig.savefig(path, dpi=80)
        files[name] = path.as_posix()
    return files


def _rel(path: str, base: Path) -> str:
    return Path(path).relative_to(base).as_posix()


def write_report(
    config_path: Path,
    out_dir: Path,
    pipeline=None,
    frames_per_camera: int = 3,
    render: bool = True,
    render_width: int = 160,
) -> Path:
    """Write the diagnostics of a run (overlays, renders, convergence plots, report.md) into ``out_dir``.

    Args:
        config_path: the run's config.yml (or its folder).
        out_dir: output folder (created; must not lie inside the dataset folder).
        pipeline: the run's pipeline when already in memory (e.g. at the end of moisst-calibrate); loaded from the
            checkpoint with ``eval_setup`` otherwise.
        frames_per_camera: camera frames per camera for the prior / calibrated overlays.
        render: also render one frame per camera with the model.
        render_width: width of those renders, pixels (never upscaled).

    Returns:
        The path of report.md.

    Raises:
        moisst_ns.runs.RunError: a config of another method, no checkpoint, output inside the dataset, ...
    """
    from moisst_ns.runs.folder import check_output_dir, dataset_of, load_run_config, open_run, resolve_config_path, xyz_rpy_delta
    from moisst_ns.runs import RunError
    from moisst_ns.runs.history import find_history, read_history
    from moisst_ns.rig.format import load_rig

    config_path = resolve_config_path(Path(config_path))
    config = load_run_config(config_path)
    out_dir = Path(out_dir)
    check_output_dir(out_dir, dataset_of(config))
    step = None
    if pipeline is None:
        config, pipeline, step, rig = open_run(config_path)
    else:
        rig = load_rig(dataset_of(config), check_files=False)
    out_dir.mkdir(parents=True, exist_ok=True)
    calib = pipeline.model.camera_optimizer.rig
    datamanager = config.pipeline.datamanager
    min_range, max_range = float(getattr(datamanager, "lidar_min_range", 0.0)), float(getattr(datamanager, "lidar_max_range", np.inf))
    has_lidar = any(s.type == "lidar" for s in rig.sensors.values())

    overlays = make_overlays(rig, calib, out_dir, frames_per_camera, min_range, max_range) if has_lidar else []
    renders = make_renders(rig, pipeline, out_dir, render_width, min_range, max_range) if has_lidar and render else []

    try:
        history_path = find_history(config_path.parent)
        history = read_history(history_path)
    except RunError as err:
        history_path, history, history_problem = None, None, str(err)
    gt = calib.data.ground_truth
    truth = None if gt is None else {n: xyz_rpy_delta(gt.T_ref_sensor[n], gt.time_offset[n]) for n in gt.T_ref_sensor}
    plots = convergence_plots(history, truth, out_dir) if history else {}

    lines = ["# MOISST calibration report", "", f"Run: `{config_path.resolve()}`" + (f", checkpoint step {step}" if step is not None else ""),
             f"Dataset: `{rig.root.resolve()}`; reference sensor `{rig.reference_sensor}`.", ""]
    lines += ["## Calibration (last logged row of calibration_history.csv)", ""]
    if history:
        lines += ["| sensor | step | x (m) | y (m) | z (m) | roll (deg) | pitch (deg) | yaw (deg) | delta (ms) | err. transl. (cm) | err. rot. (deg) | err. time (ms) |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for name, cols in history.items():
            cells = [f"{cols[c][-1]:.{digits}f}" for c, digits in zip(ESTIMATE_COLUMNS, (4, 4, 4, 3, 3, 3, 2))]
            cells += [f"{cols[c][-1]:.3f}" if c in cols and np.isfinite(cols[c][-1]) else "-" for c in ERROR_COLUMNS]
            lines.append(f"| {name} | {int(cols['step'][-1])} | " + " | ".join(cells) + " |")
        lines += ["", f"From `{history_path.resolve()}`; errors are '-' when the dataset has no ground_truth.json.", ""]
    else:
        lines += [f"No history: {history_problem}", ""]

    lines += uncertainty_lines(config_path, calib.estimate())
    verdicts = run_verdicts(config_path, rig, calib, renders)
    lines += verdict_section(verdicts)
    lines += ["## (a) LiDAR points on camera images: prior vs calibrated", ""]
    if not has_lidar:
        lines += ["The rig has no LiDAR: no LiDAR projections (sections a and b are skipped).", ""]
    else:
        lines += ["Left: priors (rig.json extrinsics and time offsets); right: calibration. Points coloured by camera depth "
                  f"({COLORMAP}: near blue, far red), each point at the pose of its own time; the LiDAR frame nearest in time.", ""]
        for o in overlays:
            lines += [f"**{o.camera}**, frame {o.frame} (LiDAR: {o.lidar_frames}); points in the image: prior {o.prior_in_image}, "
                      f"calibrated {o.calibrated_in_image}", "", f"![{o.camera} {o.frame}]({_rel(o.files['side_by_side'], out_dir)})",
                      f"([prior]({_rel(o.files['prior'], out_dir)}), [calibrated]({_rel(o.files['calibrated'], out_dir)}))", ""]
        lines += ["## (b) LiDAR points on the model's render at the calibrated pose", ""]
        if not render:
            lines += ["Skipped (--no-render).", ""]
        for r in renders:
            f = r["files"]
            lines += [f"**{r['camera']}** ({r['size'][0]}x{r['size'][1]}): {r['points']} LiDAR points; median |rendered depth - LiDAR "
                      f"depth| = {r['median_depth_residual_m']:.3f} m", "",
                      f"![render]({_rel(f['rendered'], out_dir)}) ![depth]({_rel(f['rendered_depth'], out_dir)}) ![lidar]({_rel(f['rendered_lidar'], out_dir)})", ""]
    lines += ["## (c) Convergence", ""]
    if plots:
        for name, path in plots.items():
            lines += [f"**{name}**", "", f"![{name}]({_rel(path, out_dir)})", ""]
    else:
        lines += ["No calibration_history.csv to plot.", ""]
    report = out_dir / "report.md"
    report.write_text("\n".join(lines))
    renders_json = [{k: v for k, v in r.items() if k != "files"} for r in renders]
    (out_dir / "report.json").write_text(json.dumps({"verdicts": verdicts, "renders": renders_json}, indent=1, default=str) + "\n")
    return report


def uncertainty_lines(config_path: Path, estimate) -> List[str]:
    """report.md's uncertainty section: sigma, verdict and reason per sensor from moisst-calibrate's calibration.json
    (``runs.folder.run_trust``); empty when the run has none."""
    from moisst_ns.runs.folder import run_trust, trust_markdown

    trusted = run_trust(config_path, estimate)
    if not trusted.trust:
        return []
    table = trust_markdown({n: t.to_json() for n, t in trusted.trust.items()})[:-1]  # its blank line after the note
    return table + ["Verdicts: `converged`, `weakly observable` (see weak), `not converged` (moisst-calibrate exits "
                    "with status 3; docs/uncertainty.md).", ""]


def _json_object(path: Path) -> Optional[dict]:
    """The JSON object in ``path``, or None (no file, not an object, or damaged: a damaged side file only loses the
    report its extra flags; the report still comes)."""
    try:
        loaded = json.loads(path.read_text()) if path.is_file() else None
    except (OSError, ValueError):
        return None
    return loaded if isinstance(loaded, dict) else None


def run_verdicts(config_path: Path, rig, calib, renders: List[Dict[str, Any]]) -> Dict[str, Dict[str, Any]]:
    """Per-sensor verdicts of a run (``runs.verdict``): errors before (the dataset's priors) and after (the
    checkpoint's estimate) when the dataset has ground truth, plus the run's summary.json and calibration.json
    (``runs.folder.outputs_dir``)."""
    from moisst_ns.rig.calibration import calibration_report_errors
    from moisst_ns.rig.format import Calibration, load_calibration
    from moisst_ns.runs.folder import outputs_dir
    from moisst_ns.runs.verdict import sensor_verdicts

    out = outputs_dir(config_path)
    summary = dict(_json_object(out / "summary.json") or {})
    calibration = _json_object(out / "calibration.json")
    truth_file = rig.root / "ground_truth.json"
    if truth_file.is_file():
        truth = load_calibration(truth_file)
        summary["errors_before"] = calibration_report_errors(Calibration.from_rig(rig), truth)
        summary["errors_after"] = calibration_report_errors(calib.estimate(), truth)
    sensors = [n for n in rig.sensors if n != rig.reference_sensor]
    lidars = [n for n in sensors if rig.sensors[n].type == "lidar"]
    return sensor_verdicts(sensors, summary, calibration, renders, lidars, rig.reference_sensor)


def verdict_section(verdicts: Dict[str, Dict[str, Any]]) -> List[str]:
    """report.md's verdict: errors before and after (with ground truth) and each sensor's flags and caveats."""
    from moisst_ns.runs.verdict import trust_lines

    lines = ["## Verdict", ""] + [f"**{line}**" for line in trust_lines(verdicts)] + [""]
    if any("errors_after" in v for v in verdicts.values()):
        lines += ["| sensor | before: cm / deg / ms | after: cm / deg / ms |", "|---|---|---|"]
        for name, v in verdicts.items():
            if "errors_after" in v:
                b, a = v["errors_before"], v["errors_after"]
                lines.append(f"| {name} | {b['translation_cm']:.2f} / {b['rotation_deg']:.3f} / {b['time_ms']:.2f} | "
                             f"{a['translation_cm']:.2f} / {a['rotation_deg']:.3f} / {a['time_ms']:.2f} |")
        lines += ["", "Before: the dataset's priors; after: this run's estimate; both against ground_truth.json.", ""]
    for name, v in verdicts.items():
        extra = [f"verdict: {v['verdict']}"] if "verdict" in v else []
        extra += [f"uncertainty: {json.dumps(v['uncertainty'])}"] if "uncertainty" in v else []
        lines.append(f"- **{name}**: " + "; ".join(v["flags"] + v["caveats"] + extra or ["no flag"]))
    return lines + [""]
