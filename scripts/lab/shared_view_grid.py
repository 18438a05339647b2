"""Coarse-to-fine grid of the shared-view cost over what a straight drive leaves the LiDAR stage unsure of (roll, the
lateral and the vertical lever arm), from the LiDAR-first estimate: does the global minimum of the edges' cost lie
at the truth? (docs/lab/2026-11-25-kitti-shared-view.md, "next routes").

Usage: .venv/bin/python scripts/lab/shared_view_grid.py RIG
"""

from __future__ import annotations

import itertools
import sys
import time
from pathlib import Path

import numpy as np

from moisst_ns.rig.format import load_calibration, load_rig
from moisst_ns.rig.trust import parameter_difference
from moisst_ns.stages.lidar_first import LidarFirstConfig, calibrate_lidar, consistency_residuals, find_correspondences, load_scans, scan_pairs
from moisst_ns.stages.lidar_geometry import Extrinsic, Trajectory
from moisst_ns.stages.lidar_view import SharedView, view_residuals
from moisst_ns.stages.photometric import huber_costs

COLUMNS = (0, 1, 4, 5)
"""Roll and pitch (rotations about the LiDAR's x and y), y and z of the lever arm: columns of the increment (Jacobian
order). Without the pitch (a first run) the vertical lever arm went to the grid's edge: it trades with the pitch."""


def main() -> None:
    rig = load_rig(sys.argv[1])
    truth = load_calibration(rig.root / "ground_truth.json")
    name = next(n for n, s in rig.sensors.items() if s.type == "lidar")
    traj, config = Trajectory.from_rig(rig), LidarFirstConfig()
    begun = time.time()
    cache = Path(sys.argv[2]) if len(sys.argv) > 2 else None  # the stage's estimate, kept between runs
    if cache is not None and cache.is_file():
        saved = np.load(cache)
        ext = Extrinsic(saved["rotation"], saved["translation"], float(saved["time_offset"]))
    else:
        ext = calibrate_lidar(rig, name, config, log=lambda line: None).estimate
        if cache is not None:
            np.savez(cache, rotation=ext.rotation, translation=ext.translation, time_offset=ext.time_offset)
    err = lambda e: np.array(parameter_difference(truth.T_ref_sensor[name], truth.time_offset[name], e.matrix(), e.time_offset))
    print(f"stage: {time.time() - begun:.0f} s, error x y z {100 * err(ext)[:3]} cm, roll pitch yaw {np.degrees(err(ext)[3:6])} deg")
    scans = load_scans(rig, name, traj, config, lambda line: None)
    pairs, _ = scan_pairs(traj, scans, ext.time_offset, config)
    plane = consistency_residuals(traj, ext, scans, find_correspondences(traj, ext, scans, pairs, config.radius_end, config), np.zeros(7))[0]
    at = SharedView.of(rig, traj, scans).at(traj, ext, scans, pairs, plane)
    print(f"{len(at.rows.point)} depth-edge rows")

    def cost(values) -> float:
        increment = np.zeros(7)
        increment[list(COLUMNS)] = values
        return float(np.mean(huber_costs(view_residuals(traj, ext, scans, at.view, at.rows, increment)[0], 2.0)))

    centre = np.zeros(len(COLUMNS))
    spans = [(np.deg2rad(6.0), np.deg2rad(1.0)), (np.deg2rad(2.0), np.deg2rad(0.5)), (0.6, 0.1), (0.6, 0.1)]
    begun = time.time()
    for level in range(2):
        axes = [centre[k] + np.arange(-span, span + step / 2, step) for k, (span, step) in enumerate(spans)]
        costs = {v: cost(np.array(v)) for v in itertools.product(*axes)}
        centre = np.array(min(costs, key=costs.get))
        increment = np.zeros(7)
        increment[list(COLUMNS)] = centre
        e, e0 = err(ext.updated(increment)), err(ext)
        print(f"level {level}: {len(costs)} points, {time.time() - begun:.0f} s, minimum {costs[tuple(centre)]:.3f}; error y z "
              f"{100 * e[1]:+.1f} {100 * e[2]:+.1f} cm, roll pitch {np.degrees(e[3]):+.2f} {np.degrees(e[4]):+.2f} deg (stage: "
              f"{100 * e0[1]:+.1f} {100 * e0[2]:+.1f} cm, {np.degrees(e0[3]):+.2f} {np.degrees(e0[4]):+.2f} deg)")
        spans = [(2 * step, step / 4) for _, step in spans]


if __name__ == "__main__":
    main()
