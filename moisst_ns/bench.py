"""``moisst-bench``: the MOISST paper's evaluation protocol (Tables I-VII) on synthetic rigs with exact ground
truth, side by side with the baselines a user would otherwise try, plus speed and cost.

A scenario file (``configs/bench-quick.toml``, ``configs/bench-full.toml``) lists cases: a prior perturbation
(translation per axis, rotation about every axis, time offset), what is optimised (spatial, temporal, both),
which losses are off, and the table cells the case fills. Every case runs ``moisst-calibrate`` (in-process) on
``moisst-synth`` rigs for one or all (seed, layout) pairs. A cell is the mean ± std over seeds and over the last
N logged estimates (the paper averages its last epochs). Baselines: the priors alone, and nerfacto's per-frame
pose optimiser (SO3xR3, same field) as per-frame pose errors (Table VI style). Speed: seconds/step of each MOISST
preset and of plain nerfacto with the same field and camera rays (the calibration overhead ratio), the wall time
until the cameras reach the target accuracy, and the peak RSS.

Writes ``OUT/bench.json``, ``OUT/benchmarks.md``, ``OUT/error_vs_time.png`` and, with ``--docs``, copies the two
last into the repository's ``docs/``.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import resource
import shutil
import sys
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np

REPO = Path(__file__).resolve().parents[1]
LOSS_SWITCHES = {"no-depth": "depth_loss", "no-dssim": "dssim_loss", "no-depth-smoothness": "depth_smoothness_loss"}
OPTIMISE = ("both", "spatial", "temporal")
ERR_KEYS = ("translation_cm", "rotation_deg", "time_ms")
HIST_KEYS = ("err_translation_cm", "err_rotation_deg", "err_time_ms")


class BenchError(ValueError):
    """A scenario file is malformed: ``<file>: <field>: <problem>``."""


@dataclass
class BenchConfig:
    """Benchmark MOISST on synthetic rigs with the paper's protocol (Tables I-VII), baselines and speed."""

    quick: bool = False
    """Run configs/bench-quick.toml (the default when neither --quick nor --full is given; < 20 min on 2 cores)."""
    full: bool = False
    """Run configs/bench-full.toml (hours on 2 CPU cores)."""
    scenarios: Optional[Path] = None
    """Another scenario file (overrides --quick/--full)."""
    out: Path = Path("outputs/bench")
    """Output folder: rigs/, runs/, bench.json, benchmarks.md, error_vs_time.png."""
    docs: bool = False
    """Also copy benchmarks.md and the plot into the repository's docs/ (docs/benchmarks.md)."""
    threads: Optional[int] = None
    """torch CPU threads (torch's default when omitted)."""


# ----------------------------------------------------------------------------------------------------------------
# Scenarios


def load_scenarios(path: Path) -> dict:
    """Read and validate a scenario file."""
    path = Path(path)
    if not path.is_file():
        raise BenchError(f"{path}: (file): not found")
    try:
        raw = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as err:
        raise BenchError(f"{path}: (toml): {err}") from None
    for key in ("name", "steps", "rays", "lidar_rays", "last", "rig", "seeds", "case"):
        if key not in raw:
            raise BenchError(f"{path}: {key}: missing")
    for key in ("steps", "rays", "last"):
        if not isinstance(raw[key], int) or raw[key] < 1:
            raise BenchError(f"{path}: {key}: must be a positive integer, got {raw[key]!r}")
    if not raw["seeds"] or any(not (isinstance(s, list) and len(s) == 2 and isinstance(s[0], int) and s[1] in ("street", "plaza")) for s in raw["seeds"]):
        raise BenchError(f"{path}: seeds: must be a non-empty list of [seed, 'street' | 'plaza'] pairs")
    ids = set()
    for i, case in enumerate(raw["case"]):
        where = f"case[{i}]"
        if "id" not in case or case["id"] in ids:
            raise BenchError(f"{path}: {where}.id: missing or repeated")
        ids.add(case["id"])
        perturb = case.get("perturb", {})
        for key in ("translation", "rotation", "time"):
            value = perturb.get(key)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or value < 0:
                raise BenchError(f"{path}: {where}.perturb.{key}: must be a number >= 0, got {value!r}")
        if case.get("optimise", "both") not in OPTIMISE:
            raise BenchError(f"{path}: {where}.optimise: must be one of {OPTIMISE}, got {case.get('optimise')!r}")
        for loss in case.get("losses", []):
            if loss not in LOSS_SWITCHES:
                raise BenchError(f"{path}: {where}.losses: unknown {loss!r}; known: {sorted(LOSS_SWITCHES)}")
        patch = case.get("patch_size", None)
        if patch is not None and (isinstance(patch, bool) or not isinstance(patch, int) or patch < 1):
            raise BenchError(f"{path}: {where}.patch_size: must be a positive integer, got {patch!r}")
        if case.get("seeds", "all") not in ("all", "first"):
            raise BenchError(f"{path}: {where}.seeds: must be 'all' or 'first'")
        if not case.get("tables"):
            raise BenchError(f"{path}: {where}.tables: missing (which table cells this case fills)")
    return raw


def _seeds(raw: dict, which: str) -> List[Tuple[int, str]]:
    pairs = [tuple(s) for s in raw["seeds"]]
    return pairs if which == "all" else pairs[:1]


# ----------------------------------------------------------------------------------------------------------------
# Running


def make_bench_rig(out: Path, raw: dict, seed: int, layout: str, perturb: dict) -> Path:
    """The moisst-synth rig of a (seed, layout, perturbation), generated once.

    The scene, images and scans of a (seed, layout) are rendered once (``perturb none``); a perturbed variant
    hard-links them (copies across file systems) and gets the rig.json ``moisst-synth`` would write for that
    perturbation (the same seeded signs, ``synth.make_priors``).
    """
    from moisst_ns.datasets.synth import SynthConfig, make_priors, make_rig, make_truth

    rig = raw["rig"]
    t, r, d = (float(perturb[k]) for k in ("translation", "rotation", "time"))
    config = SynthConfig(out=out / "rigs" / f"{layout}-s{seed}-base", seed=seed, layout=layout, width=rig["width"],
                         height=rig["height"], frames=rig["frames"], perturb="none")
    if not (config.out / "rig.json").is_file():
        if config.out.exists():
            shutil.rmtree(config.out)
        make_rig(config)
    if not (t or r or d):
        return config.out
    folder = out / "rigs" / f"{layout}-s{seed}-t{t:g}-r{r:g}-d{d:g}"
    if (folder / "rig.json").is_file():
        return folder
    if folder.exists():
        shutil.rmtree(folder)

    def link(src: str, dst: str) -> None:
        try:
            os.link(src, dst)
        except OSError:
            shutil.copy2(src, dst)

    shutil.copytree(config.out, folder, copy_function=link, ignore=shutil.ignore_patterns("rig.json"))
    variant = SynthConfig(**{**config.__dict__, "out": folder, "perturb": "paper", "perturb_translation": t,
                             "perturb_rotation": r, "perturb_time": d})
    priors = make_priors(variant, make_truth(variant))
    rig_json = json.loads((config.out / "rig.json").read_text())
    for name, (prior, delta) in priors.items():
        rig_json["sensors"][name]["T_ref_sensor"] = prior.tolist()
        rig_json["sensors"][name]["time_offset"] = float(delta)
    rig_json.setdefault("metadata", {}).update(perturb="paper", perturb_translation=t, perturb_rotation=r, perturb_time=d)
    (folder / "rig.json").write_text(json.dumps(rig_json, indent=1) + "\n")
    return folder


def calibrate_case(rig: Path, out: Path, raw: dict, case: dict, steps: Optional[int] = None, lidar_rays: Optional[int] = None,
                   method: str = "moisst-lite") -> dict:
    """One moisst-calibrate run; returns its summary plus the history statistics and per-frame pose errors."""
    import torch

    from moisst_ns.pipeline import CalibrateConfig, CalibrationError, run_calibration
    from moisst_ns.runs.history import read_history
    from moisst_ns.rig.calibration import RigData, frame_pose_errors, frame_poses
    from moisst_ns.rig.format import Calibration, load_calibration, load_rig

    optimise = case.get("optimise", "both")
    flags = {LOSS_SWITCHES[loss]: False for loss in case.get("losses", [])}
    cfg = CalibrateConfig(dataset=rig, output_dir=out, method=method, max_num_iterations=steps or raw["steps"], seed=0, rays=raw["rays"],
                          lidar_rays=raw["lidar_rays"] if lidar_rays is None else lidar_rays, report=False, threads=raw.get("threads"),
                          extrinsics=optimise != "temporal", time_offsets=optimise != "spatial", patch_size=case.get("patch_size"), **flags)
    start = time.perf_counter()
    try:
        config_yml = run_calibration(cfg)
    except CalibrationError as err:  # a stopped run (non-finite values...) is a result, not a crash of the benchmark
        return {"failed": f"moisst-calibrate stopped: {err}", "rig": str(rig)}
    result = json.loads((out / "summary.json").read_text())
    result["total_s"] = time.perf_counter() - start
    result["seconds_per_step"] = result["wall_time_s"] / result["iterations"]
    history = read_history(config_yml.parent / "calibration_history.csv")
    result["history"] = {s: {k: v.tolist() for k, v in cols.items()} for s, cols in history.items()}
    # per-frame pose errors of the final estimate and of the priors (Table VI)
    rig_ = load_rig(rig)
    truth = load_calibration(rig / "ground_truth.json")
    data = RigData.from_rig(rig_, truth)
    estimate = load_calibration(out / "calibration.json")
    prior = Calibration.from_rig(rig_)
    result["frame_errors"], result["frame_errors_prior"] = {}, {}
    for name in rig_.sensor_names:
        if name == rig_.reference_sensor:
            continue
        stamps = np.array([f.timestamp for f in rig_.frames_of(name)])
        true_poses = frame_poses(data, truth, name, stamps)
        with torch.no_grad():
            result["frame_errors"][name] = frame_pose_errors(frame_poses(data, estimate, name, stamps), true_poses)
            result["frame_errors_prior"][name] = frame_pose_errors(frame_poses(data, prior, name, stamps), true_poses)
    return result


def nerfacto_case(rig: Path, out: Path, raw: dict, steps: int, pose_optimizer: str, preset: str = "moisst-lite",
                  rays: Optional[int] = None) -> dict:
    """A plain nerfacto run (baseline or timing) with the preset's field; per-frame pose errors of its cameras."""
    import torch

    from moisst_ns.baseline import run_nerfacto
    from moisst_ns.rig.calibration import RigData, frame_pose_errors, frame_poses
    from moisst_ns.rig.format import load_calibration, load_rig

    result = run_nerfacto(rig, out, preset, steps, pose_optimizer, rays=rays if rays is not None else raw["rays"], seed=0)
    rig_ = load_rig(rig)
    truth = load_calibration(rig / "ground_truth.json")
    data = RigData.from_rig(rig_, truth)
    errors = {}
    for i, name in enumerate(data.sensor_names):
        mask = result.frame_sensor_index == i
        if name == rig_.reference_sensor or not mask.any():
            continue
        true_poses = frame_poses(data, truth, name, result.frame_stamps[mask] + data.t0)
        with torch.no_grad():
            errors[name] = frame_pose_errors(torch.from_numpy(result.poses[mask]), true_poses)
    return {"seconds_per_step": result.seconds_per_step, "frame_errors": errors, "steps": steps}


# ----------------------------------------------------------------------------------------------------------------
# Aggregation


def pooled(runs: List[dict], last: int) -> Dict[str, Dict[str, Tuple[float, float]]]:
    """Per sensor and error: mean and std over runs (seeds) and their last ``last`` logged estimates."""
    values: Dict[str, Dict[str, List[float]]] = {}
    for run in runs:
        if "history" not in run:
            continue
        for sensor, cols in run["history"].items():
            for key, hkey in zip(ERR_KEYS, HIST_KEYS):
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


def stage_errors(runs: List[dict]) -> Dict[str, Dict[str, float]]:
    """Per LiDAR, the LiDAR-first stage's errors and wall time averaged over the runs that ran it."""
    out: Dict[str, Dict[str, List[float]]] = {}
    for run in runs:
        for sensor, entry in run.get("lidar_first", {}).items():
            if "errors_after" in entry:
                cell = out.setdefault(sensor, {k: [] for k in ERR_KEYS + ("wall_s",)})
                for k in ERR_KEYS:
                    cell[k].append(entry["errors_after"][k])
                cell["wall_s"].append(entry["wall_s"])
    return {s: {k: float(np.mean(v)) for k, v in cols.items()} for s, cols in out.items()}


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
                stats = case["pooled"]
                before = case["before"]
                for sensor in sorted(stats):
                    s = stats[sensor]
                    b = before.get(sensor, {})
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
    lines += ["![error vs wall time](bench_error_vs_time.png)", ""]
    return "\n".join(lines)


def plot_error_vs_time(run: dict, path: Path, title: str) -> None:
    """Translation, rotation and time error of every sensor against wall time (one run)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    for sensor, cols in run.get("history", {}).items():
        for ax, key, label in zip(axes, HIST_KEYS, ("translation error (cm)", "rotation error (deg)", "time error (ms)")):
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


def machine() -> dict:
    import torch

    device = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "CPU"
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {"cores": cores, "torch": torch.__version__, "device": device, "python": platform.python_version(),
            "summary": f"{cores} cores, torch {torch.__version__}, device {device}, Python {platform.python_version()}"}


def run_bench(cfg: BenchConfig) -> dict:
    """Run every case of the scenario file; write the JSON, Markdown and plot; return the result."""
    import torch

    if cfg.scenarios is not None:
        path = cfg.scenarios
    else:
        path = REPO / "configs" / ("bench-full.toml" if cfg.full else "bench-quick.toml")
    raw = load_scenarios(path)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    command = "moisst-bench " + " ".join(sys.argv[1:]) if sys.argv and "bench" in Path(sys.argv[0]).name else f"moisst-bench --{raw['name']}"
    cases = []
    for case in raw["case"]:
        runs = []
        for seed, layout in _seeds(raw, case.get("seeds", "all")):
            rig = make_bench_rig(out, raw, seed, layout, case["perturb"])
            print(f"[moisst-bench] case {case['id']}, seed {seed} ({layout})", flush=True)
            run = calibrate_case(rig, out / "runs" / f"{case['id']}-{layout}-s{seed}", raw, case)
            run.update(seed=seed, layout=layout)
            runs.append(run)
        ok = [r for r in runs if "history" in r]
        before: Dict[str, dict] = {}
        for r in ok:
            for s, e in r["errors_before"].items():
                before.setdefault(s, []).append(e)
        before = {s: {k: float(np.mean([e[k] for e in es])) for k in ERR_KEYS} for s, es in before.items()}
        frame = {key: merge_frame_errors([r[key] for r in ok]) for key in ("frame_errors", "frame_errors_prior")}
        cases.append({"lidar_first": stage_errors(ok), "id": case["id"], "tables": case["tables"], "perturb": case["perturb"], "optimise": case.get("optimise", "both"),
                      "patch_size": case.get("patch_size"),
                      "losses": case.get("losses", []), "runs": runs, "pooled": pooled(ok, raw["last"]), "before": before,
                      "failed": None if ok else "; ".join(r.get("failed", "") for r in runs), **frame})

    result: dict = {"scenario": raw, "scenario_file": str(path), "cases": cases, "command": command,
                    "date": datetime.date.today().isoformat(), "machine": machine()}
    first_seed, first_layout = raw["seeds"][0]
    combined = next((c for c in cases if "III" in c["tables"]), cases[0])
    combined_rig = make_bench_rig(out, raw, first_seed, first_layout, combined["perturb"])

    # Baseline: nerfacto's per-frame pose optimiser on the combined rigs.
    base = raw.get("baseline")
    if base:
        runs = []
        for seed, layout in _seeds(raw, base.get("seeds", "first")):
            rig = make_bench_rig(out, raw, seed, layout, combined["perturb"])
            print(f"[moisst-bench] baseline nerfacto SO3xR3, seed {seed} ({layout})", flush=True)
            b = nerfacto_case(rig, out / "runs" / f"nerfacto-so3xr3-{layout}-s{seed}", raw, base.get("steps", raw["steps"]), "SO3xR3")
            runs.append(b["frame_errors"])
        result["baseline"] = {"frame_errors": merge_frame_errors(runs)}

    # Speed: MOISST preset (cameras only, and with LiDAR) vs nerfacto with the same field and camera rays.
    result["timing"] = []
    for preset, steps in raw.get("timing", []):
        print(f"[moisst-bench] timing {preset}, {steps} steps", flush=True)
        rays = raw["rays"] if preset == "moisst-lite" else None
        timing_raw = dict(raw, rays=rays)
        cam_only = calibrate_case(combined_rig, out / "runs" / f"timing-{preset}-cameras", timing_raw, {}, steps=steps, lidar_rays=0,
                                  method=preset)
        with_lidar = calibrate_case(combined_rig, out / "runs" / f"timing-{preset}-lidar", dict(timing_raw, lidar_rays=None), {},
                                    steps=steps, method=preset)
        plain = nerfacto_case(combined_rig, out / "runs" / f"timing-nerfacto-{preset}", timing_raw, steps, "off", preset=preset, rays=rays)
        m = cam_only.get("seconds_per_step", float("nan"))
        result["timing"].append({"preset": preset, "steps": steps, "method_run": [cam_only.get("method"), with_lidar.get("method")], "moisst_s": m, "nerfacto_s": plain["seconds_per_step"],
                                 "ratio": m / plain["seconds_per_step"], "moisst_lidar_s": with_lidar.get("seconds_per_step", float("nan"))})

    # Time to the camera target, per seed of the combined case; where the initial-rotation sweep fails.
    cameras = [s for s in combined["pooled"] if s.startswith("cam")]
    result["time_to_target"] = {f"{r['layout']}-s{r['seed']}": time_to_target(r, raw.get("target", {}), cameras)
                                for r in combined["runs"] if "history" in r}
    sweep = []
    for c in cases:
        if c["perturb"]["rotation"] > 0 and c["perturb"]["translation"] == 0 and c["perturb"]["time"] == 0 and "cam_front_right" in c["pooled"]:
            rot = c["pooled"]["cam_front_right"]["rotation_deg"][0]
            sweep.append((c["perturb"]["rotation"], c["before"]["cam_front_right"]["rotation_deg"], rot))
    if sweep:
        failed = [deg for deg, before, rot in sorted(sweep) if rot > 0.5 * before]
        result["sensitivity"] = ", ".join(f"{deg:g}° per axis ({before:.1f}° total) -> {rot:.2f}°" for deg, before, rot in sorted(sweep)) + (
            f"; smallest initial rotation that fails (final error > half the initial): {failed[0]:g}° per axis" if failed else "; none failed")

    result["total_s"] = time.perf_counter() - started
    result["peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2
    (out / "bench.json").write_text(json.dumps(result, indent=1, default=float) + "\n")
    plot_error_vs_time(combined["runs"][0], out / "bench_error_vs_time.png",
                       f"{raw['name']}: combined case, seed {first_seed} ({first_layout}), moisst-lite {raw['steps']} steps")
    md = markdown(result)
    (out / "benchmarks.md").write_text(md)
    if cfg.docs:
        (REPO / "docs").mkdir(exist_ok=True)
        (REPO / "docs" / "benchmarks.md").write_text(md)
        shutil.copyfile(out / "bench_error_vs_time.png", REPO / "docs" / "bench_error_vs_time.png")
    print(md)
    return result
