"""The reference camera's triangulated features (``camera_map.feature_map``, bare: no rings) of a ``moisst-synth`` rig
without a LiDAR, against the true scene: each point's distance from the reference frame nearest it (within 25° of
that frame's axis) minus the true surface's along the same ray (open3d's ray cast of the generator's scene; points
more than 0.5 m off are left out), signed (negative: nearer than the surface), overall and by range.

Usage: PYTHONPATH=. .venv/bin/python scripts/lab/feature_map_depth.py RIG
"""
import json
import sys
from pathlib import Path

import numpy as np
import torch

from moisst_ns.datasets.synth import SynthConfig, build_scene
from moisst_ns.rig.format import load_calibration, load_rig
from moisst_ns.rig.geometry import ReferenceTrajectory
from moisst_ns.stages.camera.camera_map import FeatureMapConfig, feature_map

folder = Path(sys.argv[1])
rig, truth = load_rig(folder), load_calibration(folder / "ground_truth.json")
meta = json.loads((folder / "rig.json").read_text())["metadata"]
scene = build_scene(SynthConfig(out=folder, **{k: meta[k] for k in ("seed", "frames", "width", "height", "layout")}))
world = feature_map(rig, truth, FeatureMapConfig(patch_points=0), log=lambda s: None)
name = rig.reference_sensor
frames = sorted(rig.frames_of(name), key=lambda f: f.timestamp)
traj = ReferenceTrajectory.of(rig)
t = torch.tensor([f.timestamp for f in frames], dtype=torch.float64) - float(rig.trajectory_stamps[0])
poses = traj(t).numpy()  # world_T_ref; reference extrinsic identity
centres = poses[:, :3, 3]
fwd = poses[:, :3, 2]
rel = world[:, None, :] - centres[None]
depth = np.einsum("nfi,fi->nf", rel, fwd)
dist = np.linalg.norm(rel, axis=2)
cosang = depth / dist
score = np.where(cosang > np.cos(np.deg2rad(25)), dist, np.inf)
f = np.argmin(score, axis=1)
ok = np.isfinite(score[np.arange(len(world)), f])
o, w = centres[f[ok]], world[ok]
d = np.linalg.norm(w - o, axis=1)
hit = scene.cast(o, (w - o) / d[:, None])["t_hit"]
good = np.isfinite(hit) & (np.abs(d - hit) < 0.5)
err = d[good] - hit[good]
rel_err = err / hit[good]
print(f"{len(world)} points, {good.sum()} checked; signed depth error median {np.median(err)*1e3:.2f} mm, mean {err.mean()*1e3:.2f} mm, "
      f"relative median {np.median(rel_err)*1e3:.3f} per mille; |err| median {np.median(np.abs(err))*1e3:.2f} mm")
for lo, hi in [(0, 5), (5, 10), (10, 20), (20, 60)]:
    m = (hit[good] >= lo) & (hit[good] < hi)
    if m.sum():
        print(f"  {lo}-{hi} m: {m.sum()} points, median {np.median(err[m])*1e3:.2f} mm ({np.median(rel_err[m])*1e3:.3f} per mille)")
