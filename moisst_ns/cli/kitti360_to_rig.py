"""``moisst-kitti360-to-rig ROOT SEQUENCE --out DIR``: a KITTI-360 sequence as a moisst-rig/1 dataset
(``moisst_ns.datasets.kitti360``)."""

from __future__ import annotations

import json
import time

import tyro

from moisst_ns.cli.common import fail
from moisst_ns.datasets.kitti360 import Kitti360Config, convert
from moisst_ns.rig.format import RigFormatError


def main() -> None:
    """Console script ``moisst-kitti360-to-rig``."""
    config = tyro.cli(Kitti360Config)
    start = time.perf_counter()
    try:
        out = convert(config)
    except RigFormatError as err:
        fail("moisst-kitti360-to-rig", err)
    rig = json.loads((out / "rig.json").read_text())
    counts = {}
    for f in rig["frames"]:
        counts[f["sensor"]] = counts.get(f["sensor"], 0) + 1
    print(f"moisst-kitti360-to-rig: wrote {out} ({config.sequence}, "
          + ", ".join(f"{n} {c} frames" for n, c in counts.items())
          + f", perturb {config.perturb}) in {time.perf_counter() - start:.1f} s")


if __name__ == "__main__":
    main()
