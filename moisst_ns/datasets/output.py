"""The output folder of a dataset generator (``moisst-synth``, ``moisst-kitti360-to-rig``)."""

from __future__ import annotations

import shutil
from pathlib import Path


def clear_generated_dataset(out: Path) -> None:
    """Remove what a dataset generator (``moisst-synth``, ``moisst-kitti360-to-rig``) writes into ``out``.

    Args:
        out: A folder the generator owns (``--overwrite`` was given); other files in it are left alone.
    """
    for name in ("rig.json", "reference_poses.txt", "ground_truth.json"):
        (Path(out) / name).unlink(missing_ok=True)
    for name in ("images", "lidar"):
        if (Path(out) / name).is_dir():
            shutil.rmtree(Path(out) / name)
