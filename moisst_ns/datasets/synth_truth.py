"""What a ``moisst-synth`` rig's truth is, for measuring a scene against it: the generator's configuration (from
rig.json's ``metadata``, from which ``synth.build_scene`` rebuilds the exact geometry) and the field its LiDAR sees."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from moisst_ns.datasets.synth import SynthConfig
from moisst_ns.datasets.synth_render import LIDAR_MAX_RANGE, LIDAR_MIN_RANGE


def config_of_rig(metadata: dict) -> Optional[SynthConfig]:
    """The ``SynthConfig`` a moisst-synth rig was generated with (rig.json's ``metadata``), or None for other rigs.

    Args:
        metadata: rig.json's ``"metadata"`` object (``{}`` when absent).

    Returns:
        The configuration (``out`` set to ``.``), from which ``build_scene`` rebuilds the exact scene geometry.
    """
    if metadata.get("generator") != "moisst-synth":
        return None
    names = {f for f in SynthConfig.__dataclass_fields__ if f not in ("out", "overwrite")}
    return SynthConfig(out=Path("."), **{k: v for k, v in metadata.items() if k in names})


def in_lidar_field(points: np.ndarray) -> np.ndarray:
    """Which points (LiDAR frame, metres) the synthetic LiDAR can measure: range and beam elevation limits.

    Args:
        points: (N, 3) points in the LiDAR frame, metres.

    Returns:
        (N,) boolean mask.
    """
    ranges = np.linalg.norm(points, axis=-1)
    elevation = np.rad2deg(np.arcsin(np.clip(points[:, 2] / np.maximum(ranges, 1e-9), -1.0, 1.0)))
    return (ranges >= LIDAR_MIN_RANGE) & (ranges <= LIDAR_MAX_RANGE) & (elevation >= -25.0) & (elevation <= 10.0)
