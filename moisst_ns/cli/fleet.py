"""``moisst-fleet MANIFEST --output-dir OUT``: calibrate many drives on Ray, a consensus per vehicle, moved sensors.

The work is ``moisst_ns.fleet.run.run_fleet`` (each drive: ``moisst_ns.calibrate.run_calibration`` in a Ray task);
this module parses the command line and turns its errors into one line on stderr and exit status 2. Exit status 1
when some drive failed (the others' results are written).
"""

from __future__ import annotations

import tyro

from moisst_ns.cli.common import fail
from moisst_ns.fleet import FleetError
from moisst_ns.fleet.run import FleetConfig, run_fleet

PROG = "moisst-fleet"


def main() -> None:
    """Console script ``moisst-fleet``."""
    cfg = tyro.cli(FleetConfig, prog=PROG)
    try:
        fleet = run_fleet(cfg)
    except FleetError as err:
        fail(PROG, err)
    if any(row["status"] != "done" for row in fleet["drives"]):
        raise SystemExit(1)


if __name__ == "__main__":
    main()
