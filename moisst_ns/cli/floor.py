"""``moisst-floor DATASET --output-dir OUT``: the accuracy floor of a dataset at a training budget
(``moisst_ns.floor``). Nothing is written into DATASET."""

from __future__ import annotations

import tyro

from moisst_ns.cli.common import fail
from moisst_ns.quiet import quiet_third_party
from moisst_ns.floor import FloorConfig, FloorError, floor_summary, run_floor


def main() -> None:
    from moisst_ns.rig.format import RigFormatError

    cfg = tyro.cli(FloorConfig, config=(tyro.conf.PositionalRequiredArgs,))
    quiet_third_party(cfg.verbose)
    try:
        result = run_floor(cfg)
    except (FloorError, RigFormatError) as err:
        fail("moisst-floor", str(err))
    print(floor_summary(result))
    print(f"wrote {cfg.output_dir / 'floor.json'}")


if __name__ == "__main__":
    main()
