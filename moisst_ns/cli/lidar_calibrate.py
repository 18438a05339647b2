"""``moisst-lidar-calibrate DATASET --output-dir OUT``: calibrate every LiDAR of a rig from its own scans.

No image and no NeRF: each LiDAR's extrinsic and time offset come from the consistency of its scans placed by the
reference trajectory (``moisst_ns.stages.lidar.lidar_first``). Writes ``OUT/calibration.json`` (every LiDAR estimated,
every other sensor at its prior), ``OUT/lidar_first.json`` / ``.md`` (per-iteration cost, estimate, observability
of each parameter) and a convergence plot. Also LiDAR-to-INS/GNSS calibration: make the INS the reference sensor.
Nothing is written into DATASET.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Tuple

import tyro

from moisst_ns.cli.common import fail
from moisst_ns.runs import RunError
from moisst_ns.runs.folder import check_output_dir
from moisst_ns.runs.history import format_error_table


@dataclass
class LidarCalibrateConfig:
    """Calibrate every LiDAR of a rig against the reference trajectory from its own scans (no image, no NeRF)."""

    dataset: tyro.conf.Positional[Path]
    """Dataset folder holding rig.json (moisst-rig/1)."""
    output_dir: Path = Path("outputs/lidar-calibration")
    """Where calibration.json and the stage's report go (created; must not be inside the dataset)."""
    sensors: Tuple[str, ...] = ()
    """LiDARs to calibrate (default: every non-reference LiDAR)."""
    max_time_offset: float = 0.3
    """Bound on how far a LiDAR's time offset may move from its prior, seconds."""
    seed: int = 0
    """Seed of the point sampling (same seed, same result)."""
    points_per_scan: int = 3000
    """Source points sampled per scan (more: slower, slightly more accurate)."""
    threads: Optional[int] = None
    """torch CPU threads; torch's default when omitted."""


def run_lidar_calibration(cfg: LidarCalibrateConfig) -> dict:
    """Run the stage and write its outputs; returns the stage summary (``lidar_first.json``)."""
    import torch

    from moisst_ns.rig.format import Calibration, RigFormatError, load_calibration, load_rig
    from moisst_ns.stages.lidar.lidar_first import LidarFirstConfig, LidarFirstError, calibrate_lidars
    from moisst_ns.stages.lidar.lidar_report import observability_lines, write_stage_outputs

    prog = "moisst-lidar-calibrate"
    try:
        rig = load_rig(cfg.dataset)
        truth_file = rig.root / "ground_truth.json"
        truth = load_calibration(truth_file) if truth_file.is_file() else None
        check_output_dir(cfg.output_dir, rig.root, create=True)
    except (RigFormatError, RunError) as err:
        fail(prog, err)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    config = LidarFirstConfig(max_time_offset=cfg.max_time_offset, seed=cfg.seed, points_per_scan=cfg.points_per_scan)
    start = time.perf_counter()
    try:
        result = calibrate_lidars(rig, config, cfg.sensors or None)
    except LidarFirstError as err:
        fail(prog, err)
    prior = Calibration.from_rig(rig)
    summary = write_stage_outputs(result, config, prior, truth, cfg.output_dir)
    print(f"\nwrote {cfg.output_dir / 'calibration.json'}  ({time.perf_counter() - start:.1f} s)")
    for name, r in result.lidars.items():
        print(f"{name}: observability (effect of a 10 cm / 1 deg / 10 ms error on the residuals):")
        print("\n".join(observability_lines(r)))
        for dof in r.observability.dofs:
            if dof.weak:
                print(f"WARNING: {name}: {dof.name} is weakly observable from this drive: {dof.reason}")
    if truth is not None:
        names = list(result.lidars)
        print(format_error_table("errors of the priors (before):", {n: summary["sensors"][n]["errors_before"] for n in names}))
        print(format_error_table("errors after the LiDAR-first stage:", {n: summary["sensors"][n]["errors_after"] for n in names}))
    return summary


def main() -> None:
    run_lidar_calibration(tyro.cli(LidarCalibrateConfig))

