"""Coverage of the camera stage's sigma with and without the resolution spread, from runs already made.

For each accepted camera of each ``camera_registration.json`` (a ``moisst-calibrate`` output's
``camera_registration/`` or the stage's own), recomputes the resolution spread from the per-level history (half the
change between the two finest levels' last estimates) and counts the parameters whose true error is within 3 sigma,
with the sigma as recorded and with ``max(sigma, spread)`` (docs/uncertainty.md).

Usage: .venv/bin/python scripts/resolution_sigma.py CAMERA_REGISTRATION_JSON RIG [CAMERA_REGISTRATION_JSON RIG ...]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from moisst_ns.rig.format import load_calibration
from moisst_ns.rig.trust import PARAMETERS, parameter_difference


def main() -> None:
    args = sys.argv[1:]
    if not args or len(args) % 2:
        raise SystemExit(__doc__.strip().splitlines()[-1])
    counts = {"recorded": [0, 0], "with the resolution spread": [0, 0]}
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
            free = sigma > 0  # held parameters (sigma 0) are not estimates
            for label, s in (("recorded", sigma), ("with the resolution spread", np.fmax(sigma, spread))):
                counts[label][0] += int((error[free] <= 3 * s[free]).sum())
                counts[label][1] += int(free.sum())
            ratio = error / np.fmax(sigma, spread)
            print(f"{record}: {name}: |error| / sigma " + ", ".join(f"{p} {r:.1f}" for p, r, f in zip(PARAMETERS, ratio, free) if f))
    for label, (k, n) in counts.items():
        print(f"within 3 sigma, {label}: {k} of {n}")


if __name__ == "__main__":
    main()
