"""``moisst-calibrate DATASET --output-dir OUT``: calibrate a rig and write ``OUT/calibration.json``.

The work is ``moisst_ns.calibrate.run_calibration`` (``MoisstPipeline``, the code path of ``ns-train moisst*``); this
module parses the command line and turns its errors into one line on stderr and exit status 2.

Exit status: 0 when every sensor's verdict (``calibration.json``) is ``converged`` or ``weakly observable``;
``NOT_CONVERGED_EXIT`` (3) when calibration.json was written but at least one sensor is ``not converged`` (still
moving, ran into a bound, or no better than its prior on held-back pixels: then its prior was kept); 2 on bad input.
"""

from __future__ import annotations

import sys
from pathlib import Path

import tyro

from moisst_ns.cli.common import fail
from moisst_ns.calibrate import CalibrateConfig, CalibrationError
from moisst_ns.calibrate import run_calibration as _run_calibration
from moisst_ns.quiet import quiet_third_party
from moisst_ns.rig.format import RigFormatError

PROG = "moisst-calibrate"
NOT_CONVERGED_EXIT = 3
"""Exit status when calibration.json holds a sensor whose verdict is ``not converged``."""


def run_calibration(cfg: CalibrateConfig) -> Path:
    """``moisst_ns.calibrate.run_calibration`` with its errors as ``moisst-calibrate: error: ...`` and exit 2."""
    try:
        return _run_calibration(cfg)
    except (CalibrationError, RigFormatError) as err:
        fail(PROG, err)


def not_converged(calibration: Path) -> list:
    """Names of the sensors whose verdict in ``calibration`` is ``not converged`` (none for a file without verdicts)."""
    from moisst_ns.rig.format import load_calibration

    return [n for n, t in load_calibration(calibration).trust.items() if t.verdict == "not converged"]


def main() -> None:
    cfg = tyro.cli(CalibrateConfig, prog=PROG)
    quiet_third_party(cfg.verbose)
    run_calibration(cfg)
    bad = not_converged(cfg.output_dir / "calibration.json")
    if bad:
        print(f"{PROG}: not converged: {', '.join(bad)} (exit status {NOT_CONVERGED_EXIT}; see calibration.json 'reason')", file=sys.stderr)
        raise SystemExit(NOT_CONVERGED_EXIT)

