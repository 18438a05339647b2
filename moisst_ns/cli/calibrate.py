"""``moisst-calibrate DATASET --output-dir OUT``: calibrate a rig and write ``OUT/calibration.json``.

Runs nerfstudio training of ``moisst`` or ``moisst-lite`` in-process and writes the calibration in the rig
format's ground-truth schema (metres and seconds in the dataset's own frame), plus the nerfstudio run
(config.yml, checkpoint) under ``OUT/<method>/run``. Nothing is written into DATASET.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Literal, Optional

import tyro


@dataclass
class CalibrateConfig:
    """Calibrate the extrinsics and time offsets of a rig (MOISST)."""

    dataset: tyro.conf.Positional[Path]
    """Dataset folder holding rig.json (moisst-rig/1)."""
    output_dir: Path = Path("outputs/calibration")
    """Where calibration.json and the nerfstudio run go (created; must not be a file)."""
    method: Literal["moisst", "moisst-lite"] = "moisst-lite"
    """``moisst`` (paper settings, for a GPU) or ``moisst-lite`` (2 CPU cores)."""
    max_num_iterations: Optional[int] = None
    """Training steps (schedules scale with it); the method's default when omitted."""
    seed: int = 42
    """Random seed (sampling, initialisation)."""
    viewer: bool = False
    """Also serve nerfstudio's viewer during training (on 127.0.0.1 unless --viewer-host)."""
    viewer_host: str = "127.0.0.1"
    """Host the viewer listens on; reach it remotely through an ssh port forward rather than 0.0.0.0."""
    depth_loss: bool = True
    """LiDAR depth loss L_D (paper eq. 7); --no-depth-loss for the Table VII ablation."""
    dssim_loss: bool = True
    """DSSIM patch loss (eq. 13; active with --patch-size > 1)."""
    depth_smoothness_loss: bool = True
    """Depth smoothness patch loss (eq. 13; active with --patch-size > 1)."""
    patch_size: Optional[int] = None
    """Sample camera pixels as P x P patches (needed by the patch losses); the method's default when omitted."""
    lidar_rays: Optional[int] = None
    """LiDAR points per step (0: cameras only); the method's default when omitted."""
    rays: Optional[int] = None
    """Camera pixels per step; the method's default when omitted."""
    extrinsics: bool = True
    """Optimise the extrinsics; --no-extrinsics keeps them at the priors (paper Tables II and V: temporal only)."""
    time_offsets: bool = True
    """Optimise the time offsets; --no-time-offsets keeps them at the priors (paper Tables I and V: spatial only)."""
    report: bool = True
    """Write diagnostics to OUT/report: LiDAR points over the images with prior vs calibrated extrinsics, the
    same over a model render, convergence plots, report.md (same as ``moisst-report``)."""
    max_time_offset: Optional[float] = None
    """Bound (seconds) on how far a sensor's time offset may move from its prior (default 0.3 s); a sensor that
    hits it is a runaway and shows in the still-moving / error report instead of going absurd."""
    resume: bool = False
    """Continue the run in --output-dir from its latest checkpoint (calibration, scene and optimiser state)."""
    save_every: Optional[int] = None
    """Checkpoint every N steps and keep every checkpoint (default: the method's, latest only)."""
    threads: Optional[int] = None
    """torch CPU threads (pin for bit-repeatable runs); torch's default when omitted."""
    depth_loss_per_m2: Optional[float] = None
    """LiDAR depth loss on the depth error in metres with this weight per m^2 (same meaning on every rig); the
    method's normalised-depth loss (the paper's) when omitted."""
    lidar_first: bool = True
    """Calibrate every LiDAR from its own scans before the NeRF (``moisst-lidar-calibrate``, into OUT/lidar_first);
    the NeRF starts from that estimate, holds the LiDARs there and lets their depth shape the scene.
    --no-lidar-first: the paper's pure joint schedule (for the ablation tables)."""


def seed_everything(seed: int) -> None:
    """Seed Python, numpy and torch as ``ns-train`` does (its train loop, which we bypass, would)."""
    import random

    import numpy as np
    import torch

    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def fail(message: str, prog: str = "moisst-calibrate") -> None:
    print(f"{prog}: error: {message}", file=sys.stderr)
    raise SystemExit(2)


def check_output_dir(dataset_root: Path, out: Path, prog: str = "moisst-calibrate") -> None:
    """Refuse an output folder that is a file or lies inside the dataset (datasets are never written); create it."""
    if out.exists() and not out.is_dir():
        fail(f"{out}: --output-dir: is a file, not a folder", prog)
    if out.resolve() == dataset_root.resolve() or dataset_root.resolve() in out.resolve().parents:
        fail(f"{out}: --output-dir: must not be inside the dataset folder {dataset_root} (datasets are never written)", prog)
    out.mkdir(parents=True, exist_ok=True)


def format_error_table(title: str, errors: Dict[str, Dict[str, float]]) -> str:
    """A fixed-width table of per-sensor translation (cm), rotation (deg) and time (ms) errors."""
    lines = [title, f"  {'sensor':<18}{'transl. (cm)':>14}{'rot. (deg)':>12}{'time (ms)':>11}"]
    for name, e in errors.items():
        lines.append(f"  {name:<18}{e['translation_cm']:>14.2f}{e['rotation_deg']:>12.3f}{e['time_ms']:>11.2f}")
    return "\n".join(lines)


def still_moving(history: Path, last: int = 10, max_cm: float = 1.0, max_deg: float = 0.05, max_ms: float = 0.5) -> Dict[str, str]:
    """Sensors whose last ``last`` logged estimates spread (std) more than the thresholds."""
    import numpy as np

    from moisst_ns.cli.evaluate import ESTIMATE_COLUMNS, EvalError, read_history

    if not history.is_file():
        return {}
    try:
        columns = read_history(history)
    except EvalError:  # nothing logged yet
        return {}
    out = {}
    for name, cols in columns.items():
        tail = np.stack([cols[c][-last:] for c in ESTIMATE_COLUMNS], axis=1)
        if len(tail) < 2:
            continue
        std = tail.std(axis=0)
        cm, deg, ms = 100 * np.linalg.norm(std[:3]), float(np.linalg.norm(std[3:6])), float(std[6])
        if cm > max_cm or deg > max_deg or ms > max_ms:
            out[name] = f"std {cm:.2f} cm, {deg:.3f} deg, {ms:.2f} ms"
    return out


def run_calibration(cfg: CalibrateConfig) -> Path:
    """Train, then write ``calibration.json``; returns the run's config.yml path."""
    import torch

    from moisst_ns.method_configs import moisst_trainer_config
    from moisst_ns.rig.calibration import calibration_report_errors
    from moisst_ns.rig.format import Calibration, RigFormatError, load_calibration, load_rig

    try:
        rig = load_rig(cfg.dataset)
    except RigFormatError as err:
        fail(str(err))
    out = cfg.output_dir
    check_output_dir(rig.root, out)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)

    config = moisst_trainer_config(cfg.method, cfg.max_num_iterations)
    config.pipeline.datamanager.data = rig.root
    config.pipeline.datamanager.dataparser.data = rig.root
    config.output_dir = out
    config.experiment_name = "."
    config.timestamp = "run"
    config.machine.seed = cfg.seed
    model = config.pipeline.model
    if cfg.depth_loss_per_m2 is not None:
        model.depth_loss_units, model.depth_loss_mult = "metric", cfg.depth_loss_per_m2
    if not cfg.depth_loss:
        model.depth_loss_mult = 0.0
    if not cfg.dssim_loss:
        model.dssim_loss_mult = 0.0
    if not cfg.depth_smoothness_loss:
        model.depth_smoothness_mult = 0.0
    if cfg.max_time_offset is not None:
        model.camera_optimizer.max_time_offset = cfg.max_time_offset
    if cfg.patch_size is not None:
        config.pipeline.datamanager.patch_size = cfg.patch_size
    if cfg.lidar_rays is not None:
        config.pipeline.datamanager.lidar_rays_per_batch = cfg.lidar_rays
    if cfg.rays is not None:
        config.pipeline.datamanager.train_num_rays_per_batch = cfg.rays
        config.pipeline.datamanager.eval_num_rays_per_batch = cfg.rays
    if not cfg.extrinsics and not cfg.time_offsets:
        fail("--no-extrinsics and --no-time-offsets together leave nothing to calibrate")
    model.camera_optimizer.optimize_extrinsics = cfg.extrinsics
    model.camera_optimizer.optimize_time_offsets = cfg.time_offsets
    config.viewer.quit_on_train_completion = True
    config.viewer.websocket_host = cfg.viewer_host
    config.vis = "viewer+tensorboard" if cfg.viewer else "tensorboard"
    if cfg.save_every:
        config.steps_per_save = cfg.save_every
        config.save_only_latest_checkpoint = False
    checkpoints = config.get_checkpoint_dir()
    if cfg.resume:
        if not checkpoints.is_dir() or not any(checkpoints.glob("step-*.ckpt")):
            fail(f"{checkpoints}: --resume: no checkpoint to resume from")
        config.load_dir = checkpoints
    config.save_config()

    truth_file = rig.root / "ground_truth.json"
    truth = load_calibration(truth_file) if truth_file.is_file() else None
    prior = Calibration.from_rig(rig)
    stage = run_lidar_first(cfg, rig, prior, truth, out) if cfg.lidar_first else None
    if stage is not None:
        config.pipeline.datamanager.dataparser.prior_calibration = out / "lidar_first" / "calibration.json"
        model.camera_optimizer.frozen_sensors = tuple(stage["sensors"])
        model.registration_sensors = "cameras"  # the calibrated LiDARs shape the scene while the cameras register
        config.save_config()
        if not cfg.resume:
            write_stage_history(stage, truth, config.get_base_dir() / "calibration_history.csv")

    seed_everything(cfg.seed)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    start = time.time()
    try:
        trainer.train()
    except FloatingPointError as err:
        fail(str(err))
    wall = time.time() - start

    optimizer = trainer.pipeline.model.camera_optimizer
    estimate = optimizer.rig.estimate()
    estimate.write(out / "calibration.json")
    summary = {"method": cfg.method, "iterations": config.max_num_iterations, "wall_time_s": wall, "seed": cfg.seed}
    if stage is not None:
        summary["lidar_first"] = {n: {k: e[k] for k in ("wall_s", "weak", "change_from_prior") + (("errors_after",) if truth else ())}
                                  for n, e in stage["sensors"].items()}
    print(f"\nwrote {out / 'calibration.json'}  ({config.max_num_iterations} steps, {wall:.0f} s)")
    if truth is not None:
        before = calibration_report_errors(prior, truth)
        after = calibration_report_errors(estimate, truth)
        skip = {truth.reference_sensor}
        before = {k: v for k, v in before.items() if k not in skip}
        after = {k: v for k, v in after.items() if k not in skip}
        print(format_error_table("errors of the priors (before):", before))
        print(format_error_table("errors after calibration:", after))
        summary["errors_before"], summary["errors_after"] = before, after
    bounds = optimizer.config
    for i, name in enumerate(optimizer.rig.data.sensor_names):
        hit = []
        if bounds.max_time_offset > 0 and abs(float(optimizer.rig.time_offset[i])) >= 0.999 * bounds.max_time_offset:
            hit.append(f"time offset (±{bounds.max_time_offset * 1000:.0f} ms)")
        if bounds.max_translation > 0 and float(optimizer.rig.translation[i].abs().max()) >= 0.999 * bounds.max_translation:
            hit.append(f"translation (±{bounds.max_translation} m)")
        if hit:
            print(f"WARNING: {name} ran into its bound on {', '.join(hit)}: a runaway, do not trust its estimate")
            summary.setdefault("hit_bounds", {})[name] = hit
    moving = still_moving(config.get_base_dir() / "calibration_history.csv")
    for name, spread in moving.items():
        print(f"WARNING: {name} is still moving over its last estimates ({spread}); run longer or check the data")
    summary["still_moving"] = moving
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    if cfg.report:
        from moisst_ns.report import write_report

        report = write_report(config.get_base_dir() / "config.yml", out / "report", pipeline=trainer.pipeline)
        print(f"diagnostics: {report}")
    return config.get_base_dir() / "config.yml"


def run_lidar_first(cfg: CalibrateConfig, rig, prior, truth, out: Path) -> Optional[dict]:
    """The LiDAR-first stage into ``out/lidar_first`` when the rig has a non-reference LiDAR; its summary, or None."""
    from moisst_ns.stages.lidar_first import LidarFirstConfig, LidarFirstError, calibrate_lidars, lidar_sensors
    from moisst_ns.stages.lidar_report import write_stage_outputs

    if not lidar_sensors(rig):
        return None
    config = LidarFirstConfig(max_time_offset=cfg.max_time_offset if cfg.max_time_offset is not None else 0.3, seed=cfg.seed,
                              estimate_extrinsic=cfg.extrinsics, estimate_time_offset=cfg.time_offsets)
    try:
        result = calibrate_lidars(rig, config)
    except LidarFirstError as err:
        fail(f"{err} (--no-lidar-first skips the LiDAR-first stage)")
    stage = write_stage_outputs(result, config, prior, truth, out / "lidar_first")
    for name, entry in stage["sensors"].items():
        line = f"LiDAR-first: {name} in {entry['wall_s']:.1f} s"
        if truth is not None:
            e = entry["errors_after"]
            line += f": {e['translation_cm']:.2f} cm / {e['rotation_deg']:.3f} deg / {e['time_ms']:.2f} ms from the truth"
        print(line + (f"; weakly observable: {', '.join(entry['weak'])}" if entry["weak"] else ""))
    return stage


def write_stage_history(stage: dict, truth, path: Path) -> None:
    """Start the run's history CSV with the LiDAR-first stage's outer iterations, at steps -N..-1 (the NeRF's
    rows follow from step 0), in the columns ``MoisstModel.log_calibration`` writes."""
    import csv

    import numpy as np
    import torch

    from moisst_ns.rig.calibration import calibration_report_errors
    from moisst_ns.rig.format import Calibration
    from moisst_ns.rig.geometry import pose_to_xyz_rpy

    columns = ["step", "sensor", "x", "y", "z", "roll", "pitch", "yaw", "delta_ms", "err_translation_cm", "err_rotation_deg",
               "err_time_ms", "elapsed_s"]
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(columns)
        for name, entry in stage["sensors"].items():
            history = entry["history"]
            for k, h in enumerate(history):
                pose = np.asarray(h["T_ref_sensor"])
                values = dict(zip(("x", "y", "z", "roll", "pitch", "yaw"), pose_to_xyz_rpy(torch.from_numpy(pose)).tolist()))
                values.update(delta_ms=1000 * h["time_offset"], elapsed_s=h["elapsed_s"])
                if truth is not None:
                    est = Calibration(truth.reference_sensor, {name: pose}, {name: h["time_offset"]})
                    values.update({f"err_{c}": v for c, v in calibration_report_errors(est, truth)[name].items()})
                writer.writerow([k - len(history), name] + [f"{values[c]:.9g}" if c in values else "" for c in columns[2:]])


def main() -> None:
    run_calibration(tyro.cli(CalibrateConfig))


if __name__ == "__main__":
    main()
