"""``moisst-bag-to-rig BAG... --out DIR --trajectory TOPIC --camera TOPIC --lidar TOPIC``: ROS 1 bags, ROS 2 bags
(sqlite3 or MCAP) as a moisst-rig/1 dataset (``moisst_ns.datasets.rosbag``; docs/bags.md)."""

from __future__ import annotations

import sys

from moisst_ns.cli.common import run_converter
from moisst_ns.datasets.rosbag import BagConfig, convert


def _convert(config: BagConfig):
    return convert(config, log=lambda line: print(f"moisst-bag-to-rig: {line}", file=sys.stderr))


def main() -> None:
    """Console script ``moisst-bag-to-rig``."""
    run_converter("moisst-bag-to-rig", BagConfig, _convert, "source")


if __name__ == "__main__":
    main()
