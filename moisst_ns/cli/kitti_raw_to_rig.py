"""``moisst-kitti-raw-to-rig ROOT DRIVE --out DIR``: a KITTI raw drive (synced + rectified) as a moisst-rig/1
dataset (``moisst_ns.datasets.kitti_raw``; docs/kitti-raw.md)."""

from __future__ import annotations

from moisst_ns.cli.common import run_converter
from moisst_ns.datasets.kitti_raw import KittiRawConfig, convert


def main() -> None:
    """Console script ``moisst-kitti-raw-to-rig``."""
    run_converter("moisst-kitti-raw-to-rig", KittiRawConfig, convert, "drive")


if __name__ == "__main__":
    main()
