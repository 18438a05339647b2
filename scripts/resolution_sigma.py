"""Coverage of the camera stage's sigma with and without the resolution spread and the convergence tail, from runs
already made.

For each accepted camera of each ``camera_registration.json`` (a ``moisst-calibrate`` output's
``camera_registration/`` or the stage's own), recomputes the resolution spread from the per-level history (half the
change between the two finest levels' last estimates) and the convergence tail from the last three iterates
(``camera_guards.convergence_tail``), and counts the parameters whose true error is within 3 sigma, with the sigma as
recorded, with ``max(sigma, spread)`` and with ``max(sigma, spread, tail)`` (docs/uncertainty.md).

Usage: .venv/bin/python scripts/resolution_sigma.py CAMERA_REGISTRATION_JSON RIG [CAMERA_REGISTRATION_JSON RIG ...]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from moisst_ns.rig.format import load_calibration
from moisst_ns.rig.trust import PARAMETERS, parameter_difference
from moisst_ns.stages.camera.camera_guards import convergence_tail


def main() -> None:
    args = sys.argv[1:]
    if not args or len(args) % 2:
        raise SystemExit(__doc__.strip().splitlines()[-1])
    counts = {"recorded": [0, 0], "with the resolution spread": [0, 0], "with the resolution spread and the convergence tail": [0, 0]}
    for record, rig in zip(args[::2], args[1::2]):
        truth = load_calibration(Path(rig) / "ground_truth.json")
        for name, cam in json.loads(Path(record).read_text())["sensors"].items():
            if cam["kept_prior"]:
                continue
            last = {h["level"]: h for h in cam.get("history", [])}
            levels = sorted(last)
            error = np.abs(parameter_difference(truth.T_ref_sensor[name], truth.time_offset[name], np.array(cam["T_ref_sensor"]), cam["time_offset"]))
            sigma = np.array([np.inf if s is None else s for s in cam["sigma"]], dtype=float)
            spread = np.zeros(7)
            if len(levels) >= 2:
                fine, coarse = last[levels[0]], last[levels[1]]
                spread = np.abs(parameter_difference(np.array(coarse["T_ref_sensor"]), coarse["time_offset"], np.array(fine["T_ref_sensor"]), fine["time_offset"])) / 2
            prior = np.array(cam["prior_T_ref_sensor"]), cam["prior_time_offset"]
            tail = convergence_tail([parameter_difference(*prior, np.array(h["T_ref_sensor"]), h["time_offset"]) for h in cam.get("history", [])])
            free = sigma > 0  # held parameters (sigma 0) are not estimates
            for label, s in zip(counts, (sigma, np.fmax(sigma, spread), np.fmax.reduce([sigma, spread, tail]))):
                counts[label][0] += int((error[free] <= 3 * s[free]).sum())
                counts[label][1] += int(free.sum())
            ratio = error / np.fmax.reduce([sigma, spread, tail])
            print(f"{record}: {name}: |error| / sigma " + ", ".join(f"{p} {r:.1f}" for p, r, f in zip(PARAMETERS, ratio, free) if f))
    for label, (k, n) in counts.items():
        print(f"within 3 sigma, {label}: {k} of {n}")


if __name__ == "__main__":
    main()
