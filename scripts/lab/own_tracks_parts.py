"""Lab (2026-12-07, issue 38): scripts/lab/own_motion_check.py with the own-tracks fit's sigma parts printed (solver
order: rotation vector deg, lever arm cm, delta ms). With docs/lab/2026-12-07-own-tracks-jackknife.patch applied and JK=5
in the environment it also prints a delete-one-block jackknife over 5 time blocks of the tracks' first frames.
GAP=N in the environment matches each frame with its next N frames instead of ``OwnMotionConfig.max_gap`` (3).

Usage: PYTHONPATH=. .venv/bin/python scripts/lab/own_tracks_parts.py RIG CAMERA --map none
"""
import os, sys, runpy, numpy as np
import moisst_ns.stages.camera.own_tracks as ot
orig = ot.fit_own_tracks
def wrapped(*a, **k):
    r = orig(*a, **k)
    if r is not None:
        for n in ("theta", "sigma_formal", "sigma_split", "sigma_baseline", "sigma_resolution"):
            v = np.asarray(getattr(r, n)); print("PARTS", n, "rot deg", np.round(np.rad2deg(v[:3]), 3).tolist(), "t cm", np.round(100 * v[3:6], 2).tolist(), "ms", round(1000 * v[6], 2))
    return r
ot.fit_own_tracks = wrapped
import moisst_ns.stages.camera.own_motion as om
if "GAP" in os.environ:
    om.OWN.max_gap = int(os.environ["GAP"])
sys.argv = ["own_motion_check.py"] + sys.argv[1:]
runpy.run_path("scripts/lab/own_motion_check.py", run_name="__main__")
