"""``moisst-fleet``: many drives calibrated on Ray, a consensus per vehicle, and flags for sensors that moved.

``manifest.py`` reads and validates the fleet manifest (TOML), ``run.py`` runs each drive as one Ray task (the
code path of ``moisst-calibrate``: ``moisst_ns.calibrate.run_calibration``), ``consensus.py`` combines the drives
of a vehicle (pure numpy, no Ray) and ``report.py`` writes ``fleet.json``, ``fleet.md`` and the plots. Errors are
``FleetError`` with a one-line message; only ``moisst_ns.cli.fleet`` turns them into exit codes.
"""


class FleetError(ValueError):
    """A manifest, output folder or Ray set-up the fleet cannot use; the message is one line naming file and field."""
