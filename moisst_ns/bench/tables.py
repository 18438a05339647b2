"""Tables and plots of ``moisst-bench``: pooled cells, the Markdown report, the error-vs-time plot."""

from __future__ import annotations

from pathlib import Path
from typing import Dict, Iterable, List, Optional, Sequence, Tuple

import numpy as np

from moisst_ns.runs import ERROR_KEYS
from moisst_ns.runs.history import ERROR_COLUMNS

# ----------------------------------------------------------------------------------------------------------------
# Aggregation


def pooled(runs: List[dict], last: int) -> Dict[str, Dict[str, Tuple[float, float]]]:
    """Per sensor and error: mean and std over runs (seeds) and their last ``last`` logged estimates."""
    values: Dict[str, Dict[str, List[float]]] = {}
    for run in runs:
        if "history" not in run:
            continue
        for sensor, cols in run["history"].items():
            for key, hkey in zip(ERROR_KEYS, ERROR_COLUMNS):
                values.setdefault(sensor, {}).setdefault(key, []).extend(cols[hkey][-last:])
    return {s: {k: (float(np.mean(v)), float(np.std(v))) for k, v in keys.items()} for s, keys in values.items()}


def merge_frame_errors(runs: List[Dict[str, dict]]) -> Dict[str, Dict[str, Tuple[float, float]]]:
    """Per-frame pose errors of several runs (``frame_pose_errors`` per sensor) as (mean of the means, RMS of the
    per-run stds) per sensor, for translation_cm and rotation_deg."""
    merged: Dict[str, List[dict]] = {}
    for run in runs:
        for sensor, e in run.items():
            merged.setdefault(sensor, []).append(e)
    return {s: {m: (float(np.mean([e[m] for e in es])), float(np.sqrt(np.mean([e[m + "_std"] ** 2 for e in es]))))
                for m in ("translation_cm", "rotation_deg")} for s, es in merged.items()}


def time_to_target(run: dict, target: dict, cameras: List[str]) -> Optional[float]:
    """Wall seconds (from the first logged step) until every listed camera is within the target at once."""
    if "history" not in run or not cameras:
        return None
    hist = run["history"]
    rows = len(hist[cameras[0]]["step"])
    for r in range(rows):
        ok = all(
            hist[c]["err_translation_cm"][r] <= target["translation_cm"] and hist[c]["err_rotation_deg"][r] <= target["rotation_deg"]
            and hist[c]["err_time_ms"][r] <= target["time_ms"] for c in cameras
        )
        if ok:
            return float(hist[cameras[0]]["elapsed_s"][r])
    return None


def _cell(stat: Optional[Tuple[float, float]], digits: int) -> str:
    return "–" if stat is None else f"{stat[0]:.{digits}f} ± {stat[1]:.{digits}f}"


def sensor_means(entries: Iterable[Tuple[str, dict]], keys: Sequence[str]) -> Dict[str, Dict[str, float]]:
    """Per sensor, the mean of each of ``keys`` over its ``(sensor, values)`` entries (sensors in first-seen order)."""
    values: Dict[str, List[dict]] = {}
    for sensor, entry in entries:
        values.setdefault(sensor, []).append(entry)
    return {s: {k: float(np.mean([e[k] for e in es])) for k in keys} for s, es in values.items()}


def stage_errors(runs: List[dict]) -> Dict[str, Dict[str, float]]:
    """Per LiDAR, the LiDAR-first stage's errors and wall time averaged over the runs that ran it."""
    return sensor_means(((s, {**e["errors_after"], "wall_s": e["wall_s"]}) for run in runs for s, e in run.get("lidar_first", {}).items()
                         if "errors_after" in e), ERROR_KEYS + ("wall_s",))


def _stage_cell(case: dict, sensor: str) -> str:
    e = case.get("lidar_first", {}).get(sensor)
    return "–" if e is None else f"{e['translation_cm']:.2f} / {e['rotation_deg']:.3f} / {e['time_ms']:.2f} ({e['wall_s']:.0f} s)"


def markdown(result: dict) -> str:
    """The Markdown report of a benchmark result."""
    raw, cases = result["scenario"], result["cases"]
    lines = [
        f"# Benchmarks ({raw['name']})",
        "",
        f"Measured {result['date']} with `{result['command']}` on {result['machine']['summary']}.",
        f"Rigs: `moisst-synth` {raw['rig']['width']}x{raw['rig']['height']}, {raw['rig']['frames']} frames per sensor, "
        f"3 cameras + 32-beam LiDAR, seeds/layouts {', '.join(f'{s}/{l}' for s, l in raw['seeds'])}. "
        f"`moisst-lite`, {raw['steps']} steps, {raw['rays']} camera rays + {raw['lidar_rays']} LiDAR points per step. "
        f"Cells: mean ± std over seeds and the last {raw['last']} logged estimates (every 25 steps); errors of the "
        "priors in the 'before' column. The Table VII cases sample a quarter of the camera rays as 4x4 patches (the "
        "patch losses need them; `moisst-lite` does not by default). Total wall time "
        f"{result['total_s'] / 60:.1f} min, peak RSS {result['peak_rss_gb']:.2f} GB.",
        "",
    ]
    table_titles = {
        "I": "Table I: spatial calibration (spatial error only; only extrinsics optimised)",
        "II": "Table II: temporal calibration (time error only; only time offsets optimised)",
        "III": "Table III: spatiotemporal calibration (±50 cm, ±5°, ±100 ms)",
        "IV": "Table IV: initial-error sensitivity (solely rotation or solely translation error; everything optimised)",
        "V": "Table V: optimised parameters (full perturbation)",
        "VII": "Table VII: losses (full perturbation)",
    }
    for table, title in table_titles.items():
        rows = []
        for case in cases:
            for tag in case["tables"]:
                name, _, label = tag.partition(":")
                if name != table:
                    continue
                for sensor, s in sorted(case["pooled"].items()):
                    b = case["before"].get(sensor, {})
                    rows.append(f"| {label or case['id']} | {sensor} | {b.get('translation_cm', float('nan')):.1f} / "
                                f"{b.get('rotation_deg', float('nan')):.2f} / {b.get('time_ms', float('nan')):.0f} | "
                                f"{_cell(s.get('translation_cm'), 1)} | {_cell(s.get('rotation_deg'), 2)} | {_cell(s.get('time_ms'), 1)} | "
                                f"{_stage_cell(case, sensor)} |")
                if case.get("failed"):
                    rows.append(f"| {label or case['id']} | – | {case['failed']} | | | | |")
        if rows:
            lines += [f"## {title}", "", "| case | sensor | before (cm / ° / ms) | translation (cm) | rotation (°) | time (ms) | "
                      "LiDAR-first stage alone (cm / ° / ms, wall) |", "| --- | --- | --- | --- | --- | --- | --- |"] + rows + [""]
    # Table VI
    rows = []
    for case in cases:
        if not any(t.startswith("V") and not t.startswith("VI") for t in case["tables"]):
            continue
        label = next(t.partition(":")[2] for t in case["tables"] if t.startswith("V:"))
        for sensor, e in sorted(case["frame_errors"].items()):
            rows.append(f"| MOISST, {label} | {sensor} | {_cell(e['translation_cm'], 1)} | {_cell(e['rotation_deg'], 2)} |")
        if label == "both":
            for sensor, e in sorted(case["frame_errors_prior"].items()):
                rows.append(f"| priors alone | {sensor} | {_cell(e['translation_cm'], 1)} | {_cell(e['rotation_deg'], 2)} |")
    for sensor, e in sorted(result.get("baseline", {}).get("frame_errors", {}).items()):
        rows.append(f"| nerfacto SO3xR3 per-frame poses | {sensor} | {_cell(e['translation_cm'], 1)} | {_cell(e['rotation_deg'], 2)} |")
    if rows:
        lines += ["## Table VI: per-frame pose errors (final estimate; mean ± std over frames and seeds)", "",
                  "| method | sensor | translation (cm) | rotation (°) |", "| --- | --- | --- | --- |"] + rows + [""]
    # Speed
    lines += ["## Speed and cost", "", "| preset | moisst s/step (cameras only) | nerfacto s/step (same field, same rays) | overhead ratio | moisst s/step with LiDAR |",
              "| --- | --- | --- | --- | --- |"]
    for t in result["timing"]:
        lines.append(f"| {t['preset']} ({t['steps']} steps) | {t['moisst_s']:.3f} | {t['nerfacto_s']:.3f} | {t['ratio']:.2f} | "
                     f"{t['moisst_lidar_s']:.3f} |")
    lines += [""]
    ttt = result["time_to_target"]
    target = raw.get("target", {})
    lines += [f"Wall time until every non-reference camera is within {target.get('translation_cm')} cm / "
              f"{target.get('rotation_deg')}° / {target.get('time_ms')} ms (combined case): "
              + ", ".join(f"{k}: {'not reached' if v is None else f'{v:.0f} s'}" for k, v in ttt.items()) + ".", ""]
    fail_at = result.get("sensitivity")
    if fail_at:
        lines += [f"Initial-error sensitivity (cam_front_right): {fail_at}", ""]
    lines += floor_markdown(result.get("floor", []))
    if "coverage" in result:
        from moisst_ns.bench.coverage import coverage_markdown

        lines += coverage_markdown(result["coverage"])
    lines += ["![error vs wall time](bench_error_vs_time.png)", ""]
    return "\n".join(lines)


def floor_markdown(floors: List[dict]) -> List[str]:
    """The floor section: per rig, each sensor's floor and the scene's depth errors (``moisst_ns.floor``).

    Args:
        floors: ``{"layout", "seed", "scene_steps", "register_steps", "wall_s", "floor", "depth"}`` per rig, and
            ``"stages"`` (``moisst_ns.floor.stages_floor``) where the stages' floor was measured.

    Returns:
        Markdown lines (none when no floor was measured).
    """
    if not floors:
        return []
    staged = [f for f in floors if f.get("stages")]
    lines = []
    if staged:
        lines += ["## Floor of the pre-NeRF stages: LiDAR first and the camera registration started at the truth (`moisst-floor`)", "",
                  "| rig | sensor | translation (cm) | rotation (°) | time (ms) | LiDAR-map depth error where the cameras look, median / p90 (mm) |",
                  "| --- | --- | --- | --- | --- | --- |"]
        for f in staged:
            st = f["stages"]
            depth = st.get("map_depth", {})
            map_cell = f"{depth['median_abs_m'] * 1000:.3g} / {depth['p90_abs_m'] * 1000:.3g}" if depth.get("camera_rays") else "–"
            for sensor, e in sorted(st["floor"].items()):
                lines.append(f"| {f['layout']} s{f['seed']} | {sensor} | {e['translation_cm']:.2f} | {e['rotation_deg']:.3f} | {e['time_ms']:.2f} | {map_cell} |")
            lines += [f"| {f['layout']} s{f['seed']} | {u.split(':')[0]} | not fitted: {u.split(':', 1)[1].strip()} | | | |" for u in st.get("unfitted", [])]
        lines.append("")
    lines += ["## NeRF floor: the scene trained at the truth, the calibration released at the truth (`moisst-floor`)", "",
             "| rig | scene / register steps | sensor | translation (cm) | rotation (°) | time (ms) | camera-ray depth error, median (cm) | LiDAR-ray depth error, median (cm) | wall (s) |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for f in floors:
        depth = f.get("depth", {})
        cam = f"{depth['median_abs_m'] * 100:.1f}" if "median_abs_m" in depth else "–"
        lid = f"{depth['lidar_median_abs_m'] * 100:.1f}" if "lidar_median_abs_m" in depth else "–"
        for sensor, e in sorted(f["floor"].items()):
            lines.append(f"| {f['layout']} s{f['seed']} | {f['scene_steps']} / {f['register_steps']} | {sensor} | "
                         f"{e['translation_cm']:.2f} | {e['rotation_deg']:.3f} | {e['time_ms']:.2f} | {cam} | {lid} | {f['wall_s']:.0f} |")
    return lines + [""]


def plot_error_vs_time(run: dict, path: Path, title: str) -> None:
    """Translation, rotation and time error of every sensor against wall time (one run)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    for sensor, cols in run.get("history", {}).items():
        for ax, key, label in zip(axes, ERROR_COLUMNS, ("translation error (cm)", "rotation error (deg)", "time error (ms)")):
            ax.plot(cols["elapsed_s"], cols[key], marker=".", label=sensor)
            ax.set_xlabel("wall time (s)")
            ax.set_ylabel(label)
            ax.set_yscale("log")
            ax.grid(True, which="both", alpha=0.3)
    axes[0].legend()
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


