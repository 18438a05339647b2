"""``moisst-bench``: the MOISST paper's evaluation protocol (Tables I-VII) on ``moisst-synth`` rigs with exact ground
truth, beside the baselines (priors alone, nerfacto's per-frame pose optimiser), plus speed and cost. Cases come from
a scenario file (``moisst_ns/scenarios/bench-*.toml``); the protocol and the outputs (``OUT/bench.json``,
``OUT/benchmarks.md``, ``OUT/bench_error_vs_time.png``; ``--docs`` copies the two last): ``docs/benchmarks.md``.
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
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, List, Optional, Tuple

import numpy as np

from moisst_ns.bench.speed import keep_speed_block, with_speed_table
from moisst_ns.bench.scenarios import LOSS_SWITCHES, load_scenarios, packaged_scenarios
from moisst_ns.runs import ERROR_KEYS
from moisst_ns.bench.tables import markdown, merge_frame_errors, plot_error_vs_time, pooled, sensor_means, stage_errors, time_to_target

REPO = Path(__file__).resolve().parents[2]

@dataclass
class BenchConfig:
    """Benchmark MOISST on synthetic rigs with the paper's protocol (Tables I-VII), baselines and speed."""

    quick: bool = False
    """Run the packaged scenarios/bench-quick.toml (the default when neither --quick nor --full is given; an hour or more on 2 cores)."""
    full: bool = False
    """Run the packaged scenarios/bench-full.toml (hours on 2 CPU cores)."""
    scenarios: Optional[Path] = None
    """Another scenario file (overrides --quick/--full)."""
    out: Path = Path("outputs/bench")
    """Output folder: rigs/, runs/, bench.json, benchmarks.md, bench_error_vs_time.png."""
    docs: bool = False
    """Also copy benchmarks.md and the plot into the repository's docs/ (docs/benchmarks.md)."""
    threads: Optional[int] = None
    """torch CPU threads (torch's default when omitted)."""
    speed: bool = False
    """Measure only the speed table (s/step of moisst-lite and moisst, cameras only and with LiDAR, against stock
    nerfacto with the same field and rays; a few minutes on 2 cores): writes OUT/speed.json and OUT/speed.md."""


# ----------------------------------------------------------------------------------------------------------------
# Running


def make_bench_rig(out: Path, raw: dict, seed: int, layout: str, perturb: dict) -> Path:
    """The moisst-synth rig of a (seed, layout, perturbation), generated once (``raw["rig"]``: its settings).

    The scene, images and scans of a (seed, layout) are rendered once (``perturb none``); a perturbed variant
    hard-links them (copies across file systems) and gets the rig.json ``moisst-synth`` would write for that
    perturbation (the same seeded signs, ``synth.make_priors``).
    """
    from moisst_ns.datasets.synth import SynthConfig, make_priors, make_rig, make_truth

    t, r, d = (float(perturb[k]) for k in ("translation", "rotation", "time"))
    config = SynthConfig(out=out / "rigs" / f"{layout}-s{seed}-base", seed=seed, layout=layout, perturb="none", **raw["rig"])
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


def bench_rigs(out: Path, raw: dict, which: str, perturb: dict, what: str) -> Iterator[Tuple[int, str, Path]]:
    """``(seed, layout, rig)`` of the scenario's seeds (``which``: ``all``, or ``first`` alone), each rig made with
    ``perturb`` (``make_bench_rig``) and announced as ``[moisst-bench] <what>, seed <seed> (<layout>)``."""
    seeds = [tuple(s) for s in raw["seeds"]]
    for seed, layout in seeds if which == "all" else seeds[:1]:
        rig = make_bench_rig(out, raw, seed, layout, perturb)
        print(f"[moisst-bench] {what}, seed {seed} ({layout})", flush=True)
        yield seed, layout, rig


def calibrate_case(rig: Path, out: Path, raw: dict, case: dict, method: str = "moisst-lite") -> dict:
    """One moisst-calibrate run; returns its summary plus the history statistics and per-frame pose errors."""
    import torch

    from moisst_ns.bench.coverage import sensor_coverage
    from moisst_ns.calibrate import CalibrateConfig, CalibrationError, run_calibration
    from moisst_ns.runs.history import read_history
    from moisst_ns.rig.calibration import RigData, frame_pose_errors, frame_poses
    from moisst_ns.rig.format import Calibration, load_calibration, load_rig

    optimise = case.get("optimise", "both")
    flags = {LOSS_SWITCHES[loss]: False for loss in case.get("losses", [])}
    cfg = CalibrateConfig(dataset=rig, output_dir=out, method=method, max_num_iterations=raw["steps"], seed=0, rays=raw["rays"],
                          lidar_rays=raw["lidar_rays"], report=False, threads=raw.get("threads"),
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
    result["coverage"] = sensor_coverage(out / "calibration.json", rig / "ground_truth.json")
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


def nerfacto_case(rig: Path, out: Path, raw: dict, steps: int, pose_optimizer: str, preset: str = "moisst-lite") -> dict:
    """A plain nerfacto run (baseline or timing) with the preset's field; per-frame pose errors of its cameras."""
    import torch

    from moisst_ns.bench.baseline import run_nerfacto
    from moisst_ns.rig.calibration import RigData, frame_pose_errors, frame_poses
    from moisst_ns.rig.format import load_calibration, load_rig

    result = run_nerfacto(rig, out, preset, steps, pose_optimizer, rays=raw["rays"])
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


def floor_cases(out: Path, raw: dict, perturb: dict) -> List[dict]:
    """Run ``moisst_ns.floor`` on the scenario's rigs (``[floor]`` table: steps, register_steps, depth_rays, seeds); the
    method preset's own rays per step.

    Returns:
        Per rig: ``{"layout", "seed", "scene_steps", "register_steps", "wall_s", "floor", "depth", "stages"}``.
    """
    from moisst_ns.floor import FloorConfig, run_floor

    spec = raw["floor"]
    floors = []
    for seed, layout, rig in bench_rigs(out, raw, spec.get("seeds", "all"), perturb, "floor"):
        started = time.perf_counter()
        measured = run_floor(FloorConfig(dataset=rig, output_dir=out / "runs" / f"floor-{layout}-s{seed}",
                                         scene_steps=spec.get("steps", raw["steps"]), register_steps=spec.get("register_steps", 100),
                                         seed=seed, depth_check_rays=spec.get("depth_rays", 4096)))
        floors.append({"layout": layout, "seed": seed, "scene_steps": measured["scene_steps"], "register_steps": measured["register_steps"],
                       "wall_s": time.perf_counter() - started, "floor": measured["floor"], "depth": measured["depth"],
                       "stages": measured.get("stages")})
    return floors


def machine() -> dict:
    import torch

    device = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "CPU"
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {"cores": cores, "torch": torch.__version__, "device": device, "python": platform.python_version(),
            "summary": f"{cores} cores, torch {torch.__version__}, device {device}, Python {platform.python_version()}"}


def run_bench(cfg: BenchConfig) -> dict:
    """Run every case of the scenario file; write the JSON, Markdown and plot; return the result."""
    import torch

    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    if cfg.speed:
        from moisst_ns.bench.speed import run_speed, speed_markdown

        result = run_speed(Path(cfg.out), machine())
        table = speed_markdown(result)
        (Path(cfg.out) / "speed.md").write_text(table + "\n")
        if cfg.docs:
            docs = REPO / "docs" / "benchmarks.md"
            docs.write_text(with_speed_table(docs.read_text() if docs.is_file() else "# Benchmarks\n", table))
        print(table)
        return result
    path = cfg.scenarios if cfg.scenarios is not None else packaged_scenarios("full" if cfg.full else "quick")
    raw = load_scenarios(path)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    command = "moisst-bench " + " ".join(sys.argv[1:]) if sys.argv and "bench" in Path(sys.argv[0]).name else f"moisst-bench --{raw['name']}"
    cases = []
    for case in raw["case"]:
        runs = [dict(calibrate_case(rig, out / "runs" / f"{case['id']}-{layout}-s{seed}", raw, case), seed=seed, layout=layout)
                for seed, layout, rig in bench_rigs(out, raw, case.get("seeds", "all"), case["perturb"], f"case {case['id']}")]
        ok = [r for r in runs if "history" in r]
        before = sensor_means(((s, e) for r in ok for s, e in r["errors_before"].items()), ERROR_KEYS)
        frame = {key: merge_frame_errors([r[key] for r in ok]) for key in ("frame_errors", "frame_errors_prior")}
        cases.append({"lidar_first": stage_errors(ok), "id": case["id"], "tables": case["tables"], "perturb": case["perturb"], "optimise": case.get("optimise", "both"),
                      "patch_size": case.get("patch_size"),
                      "losses": case.get("losses", []), "runs": runs, "pooled": pooled(ok, raw["last"]), "before": before,
                      "failed": None if ok else "; ".join(r.get("failed", "") for r in runs), **frame})

    from moisst_ns.bench.coverage import coverage_summary

    coverage = coverage_summary({f"{c['id']}-{r['layout']}-s{r['seed']}": r["coverage"] for c in cases for r in c["runs"] if "coverage" in r})
    result: dict = {"coverage": coverage, "scenario": raw, "scenario_file": str(path), "cases": cases, "command": command,
                    "date": datetime.date.today().isoformat(), "machine": machine()}
    first_seed, first_layout = raw["seeds"][0]
    combined = next((c for c in cases if "III" in c["tables"]), cases[0])
    combined_rig = make_bench_rig(out, raw, first_seed, first_layout, combined["perturb"])

    # Baseline: nerfacto's per-frame pose optimiser on the combined rigs.
    base = raw.get("baseline")
    if base:
        runs = [nerfacto_case(rig, out / "runs" / f"nerfacto-so3xr3-{layout}-s{seed}", raw, base.get("steps", raw["steps"]), "SO3xR3")["frame_errors"]
                for seed, layout, rig in bench_rigs(out, raw, base.get("seeds", "first"), combined["perturb"], "baseline nerfacto SO3xR3")]
        result["baseline"] = {"frame_errors": merge_frame_errors(runs)}

    # Floor: the scene at the truth, the calibration released at the truth (moisst-floor), per rig.
    if raw.get("floor"):
        result["floor"] = floor_cases(out, raw, combined["perturb"])

    # Speed: MOISST preset (cameras only, and with LiDAR) vs nerfacto with the same field and camera rays.
    result["timing"] = []
    for preset, steps in raw.get("timing", []):
        print(f"[moisst-bench] timing {preset}, {steps} steps", flush=True)
        timing_raw = dict(raw, rays=raw["rays"] if preset == "moisst-lite" else None, steps=steps)
        cam_only = calibrate_case(combined_rig, out / "runs" / f"timing-{preset}-cameras", dict(timing_raw, lidar_rays=0), {}, method=preset)
        with_lidar = calibrate_case(combined_rig, out / "runs" / f"timing-{preset}-lidar", dict(timing_raw, lidar_rays=None), {}, method=preset)
        plain = nerfacto_case(combined_rig, out / "runs" / f"timing-nerfacto-{preset}", timing_raw, steps, "off", preset=preset)
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
        docs = REPO / "docs" / "benchmarks.md"
        docs.parent.mkdir(exist_ok=True)
        docs.write_text(keep_speed_block(docs.read_text() if docs.is_file() else "", md))
        shutil.copyfile(out / "bench_error_vs_time.png", REPO / "docs" / "bench_error_vs_time.png")
    print(md)
    return result
