"""Lab (2026-12-07, issues 38, 35): the own-tracks costs of a camera along its time offset, every other parameter at
the truth. Tests whether a trajectory's white noise pulls the offset towards the phases halfway between its samples
(eq. 1 interpolates linearly, so a pose halfway between two noisy samples carries half their noise variance, one at a
sample all of it).

Prints, every 10 ms of the offset from the truth, the mean soft-L1 cost (as the fit weighs it) of the matches' Sampson
distances (the epipolar start's cost) and of the tracks' angles (the fine fit's cost, capped at 8 px), pixels.
``--resample PHASE CM DEG``: first replace the rig's trajectory by itself sampled at the same rate, shifted by PHASE
of a sample period, with white noise of CM centimetres / DEG degrees added (``perturb_trajectory``, seed 0): on an
exact rig whose cameras sit on the samples, PHASE 0.5 puts them halfway.

Usage: .venv/bin/python scripts/lab/delta_phase_profile.py RIG CAMERA [--resample PHASE CM DEG]
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np
import torch

from moisst_ns.rig.format import load_calibration, load_rig
from moisst_ns.rig.geometry import ReferenceTrajectory
from moisst_ns.rig.trajectory_noise import perturb_trajectory
from moisst_ns.stages.camera.own_motion import OWN, own_matches
from moisst_ns.stages.camera.own_tracks import sampson_px, track_px, tracks


def resampled(rig, phase: float, noise_cm: float, noise_deg: float):
    """The rig with its trajectory sampled again ``phase`` of a period later, white noise added."""
    import roma

    traj = ReferenceTrajectory.of(rig)
    stamps = np.asarray(rig.trajectory_stamps, dtype=np.float64)
    shifted = stamps + phase * float(np.median(np.diff(stamps)))
    poses = traj(torch.from_numpy(shifted - traj.t0)).numpy()
    quats = roma.rotmat_to_unitquat(torch.from_numpy(poses[:, :3, :3])).numpy()
    positions, quats = perturb_trajectory(shifted, poses[:, :3, 3], quats, (noise_cm, noise_deg), (0.0, 0.0), np.random.SeedSequence(0))
    return replace(rig, trajectory_stamps=shifted, trajectory_positions=positions, trajectory_quats_xyzw=quats)


def from_arguments():
    """The command line's camera, its rig (``--resample``: resampled) and the rig's truth."""
    parser = argparse.ArgumentParser()
    parser.add_argument("rig")
    parser.add_argument("camera")
    parser.add_argument("--resample", nargs=3, type=float, metavar=("PHASE", "CM", "DEG"))
    args = parser.parse_args()
    rig = load_rig(args.rig)
    truth = load_calibration(rig.root / "ground_truth.json")
    return args.camera, resampled(rig, *args.resample) if args.resample else rig, truth


def phase(rig, camera: str, offset: float) -> float:
    """Where the camera's frames fall between the trajectory's samples (0: on them), median over the frames."""
    stamps = np.array([f.timestamp for f in rig.frames_of(camera)]) + offset
    return float(np.median(np.interp(stamps, rig.trajectory_stamps, np.arange(len(rig.trajectory_stamps))) % 1.0))


def main() -> None:
    camera, rig, truth = from_arguments()
    traj = ReferenceTrajectory.of(rig)
    matches = own_matches(rig, camera, OWN)
    T, offset = np.asarray(truth.T_ref_sensor[camera]), float(truth.time_offset[camera])
    focal = float(rig.sensors[camera].intrinsics["fl_x"])
    obs = tracks(matches)
    views = np.bincount(obs.track, minlength=obs.count)
    obs = obs.subset(views[obs.track] >= 3)
    print(f"{len(matches.frame_a)} matches, {obs.count} tracks; the camera's frames at phase {phase(rig, camera, offset):.2f} of the trajectory's "
          f"{1000 * np.median(np.diff(rig.trajectory_stamps)):.0f} ms samples")
    soft = lambda r: float(np.mean(2 * (np.sqrt(1 + r ** 2) - 1)))  # noqa: E731 (scipy's soft_l1, f_scale 1 px)
    for step in np.arange(-0.16, 0.161, 0.01):
        theta = np.zeros(7)
        theta[6] = step
        sampson = sampson_px(theta, matches, focal, traj, T, offset)
        track = track_px(theta, obs, focal, traj, T, offset)
        print(f"offset {1000 * step:+5.0f} ms from the truth: Sampson {soft(sampson):.4f}, tracks {soft(np.clip(track, -8, 8)):.4f}")


if __name__ == "__main__":
    main()
