"""``moisst-kitti360-to-rig ROOT SEQUENCE --out DIR``: a KITTI-360 sequence as a moisst-rig/1 dataset
(``moisst_ns.datasets.kitti360``)."""

from __future__ import annotations

from moisst_ns.cli.common import run_converter
from moisst_ns.datasets.kitti360 import Kitti360Config, convert


def main() -> None:
    """Console script ``moisst-kitti360-to-rig``."""
    run_converter("moisst-kitti360-to-rig", Kitti360Config, convert, "sequence")


if __name__ == "__main__":
    main()
