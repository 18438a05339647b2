"""``moisst-calibrate DATASET --output-dir OUT``: calibrate a rig and write ``OUT/calibration.json``.

The pipeline (LiDAR first, then the NeRF) is ``moisst_ns.pipeline``; this module parses the command line and turns
its errors into one line on stderr and exit status 2.
"""

from __future__ import annotations

from pathlib import Path

import tyro

from moisst_ns.cli.common import fail
from moisst_ns.pipeline import CalibrateConfig, CalibrationError
from moisst_ns.pipeline import run_calibration as _run_calibration
from moisst_ns.quiet import quiet_third_party
from moisst_ns.rig.format import RigFormatError

PROG = "moisst-calibrate"


def run_calibration(cfg: CalibrateConfig) -> Path:
    """``moisst_ns.pipeline.run_calibration`` with its errors as ``moisst-calibrate: error: ...`` and exit 2."""
    try:
        return _run_calibration(cfg)
    except (CalibrationError, RigFormatError) as err:
        fail(PROG, err)


def main() -> None:
    cfg = tyro.cli(CalibrateConfig, prog=PROG)
    quiet_third_party(cfg.verbose)
    run_calibration(cfg)


if __name__ == "__main__":
    main()
