"""``moisst-bag-to-rig BAG... --out DIR --trajectory TOPIC --camera TOPIC --lidar TOPIC``: ROS 1 bags, ROS 2 bags
(sqlite3 or MCAP) as a moisst-rig/1 dataset (``moisst_ns.datasets.rosbag``; docs/bags.md)."""

from __future__ import annotations

from moisst_ns.cli.common import run_converter
from moisst_ns.datasets.rosbag import BagConfig, convert


def main() -> None:
    """Console script ``moisst-bag-to-rig``."""
    run_converter("moisst-bag-to-rig", BagConfig, convert, "source", log=True)

