"""The trajectory smoother of docs/lab/2026-12-07-trajectory-smoother.patch (not adopted) on a moisst-synth rig's
written trajectory: the error of the steps between poses 1, 3 and 10 apart (cm; deg) before and after, against the
exact trajectory the generator rebuilds from the rig's metadata, and how far an exact trajectory moves. Needs the patch
applied (``TrajectoryAccuracy.smoothed``); the realistic rigs' stated errors (1 cm / 0.02 deg white, 3 cm / 0.05 deg drift).

Usage: .venv/bin/python scripts/lab/trajectory_smoother_check.py RIG   (RIG from moisst-synth ... --realistic)
"""
import numpy as np, sys, json, time
from pathlib import Path
from scipy.spatial.transform import Rotation
from moisst_ns.datasets.synth import make_path, reference_trajectory_samples, config_of_rig
from moisst_ns.datasets.synth_rig import make_truth
from moisst_ns.rig.files import load_tum
from moisst_ns.rig.trajectory_noise import TrajectoryAccuracy
rig = Path(sys.argv[1])
config = config_of_rig(json.loads((rig / "rig.json").read_text())["metadata"])
stamps, pos_true, q_true = reference_trajectory_samples(config, make_path(config), make_truth(config))
s, pos, q = load_tum(rig / "reference_poses.txt")
acc = TrajectoryAccuracy(0.01, 0.02, 0.03, 0.05)
def rel(p):
    e = p - pos_true
    return np.round([float(np.sqrt(np.mean((e[k:] - e[:-k]) ** 2)) * 100) for k in (1, 3, 10)], 3)
def relr(qq):
    e = (Rotation.from_quat(q_true).inv() * Rotation.from_quat(qq)).as_rotvec()
    return np.round([float(np.rad2deg(np.sqrt(np.mean((e[k:] - e[:-k]) ** 2)))) for k in (1, 3, 10)], 4)
for name, P, Q in (("noisy", pos, q), ("clean", pos_true, q_true)):
    t0 = time.time(); ps, qs = acc.smoothed(s, P, Q)
    print(name, "%.3fs" % (time.time() - t0), "pos", rel(P), "->", rel(ps), "| rot", relr(Q), "->", relr(qs), "moved max cm %.4f" % (100*np.abs(ps-P).max()))
# big n timing
n = 6000; tt = np.arange(n) * 0.01; P = np.column_stack([np.sin(tt/5)*30, tt*8, 0*tt]) + np.random.default_rng(0).normal(0, 0.01, (n, 3))
t0 = time.time(); from moisst_ns.rig.trajectory_noise import smooth_trajectory; smooth_trajectory(tt, P, 0.01); print("n=6000 %.2fs" % (time.time() - t0))
