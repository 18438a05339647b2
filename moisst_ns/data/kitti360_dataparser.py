"""nerfstudio dataparser ``moisst-kitti360``: a KITTI-360 sequence straight from its download layout.

Thin glue: the sequence's frame range is converted once by ``moisst_ns.datasets.kitti360.convert`` into a cache folder
(never into the KITTI-360 folder) and read as ``moisst-rig/1``. Usage::

    ns-train moisst-lite moisst-kitti360 --data /data/KITTI-360 --sequence 2013_05_28_drive_0000_sync \\
        --first-frame 3000 --last-frame 3099 --downscale 4 --perturb paper
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Literal, Type

from nerfstudio.plugins.registry_dataparser import DataParserSpecification

from moisst_ns.data.dataparser import MoisstRigDataParser, MoisstRigDataParserConfig
from moisst_ns.datasets.kitti360 import Kitti360Config, Kitti360Frames, convert


@dataclass
class MoisstKitti360DataParserConfig(Kitti360Frames, MoisstRigDataParserConfig):
    """Reads one KITTI-360 sequence (frame range) from the dataset's download layout."""

    _target: Type = field(default_factory=lambda: MoisstKitti360DataParser)
    data: Path = Path("data/KITTI-360")
    """KITTI-360 root folder (holds calibration/, data_poses/, data_2d_raw/, data_3d_raw/). Read only."""
    sequence: str = "2013_05_28_drive_0000_sync"
    """Sequence folder name."""
    fisheye_fov: float = 100.0
    """Horizontal field of view (degrees) of the pinhole images the fisheye cameras are rectified to."""
    perturb: Literal["none", "paper"] = "none"
    """Priors: the dataset's calibration ('none') or perturbed as in MOISST section IV ('paper')."""
    seed: int = 0
    """Seed of the perturbation signs."""
    cache_dir: Path = field(default_factory=lambda: Path.home() / ".cache" / "moisst-ns" / "kitti360")
    """Where the converted moisst-rig/1 dataset is kept (one folder per distinct conversion)."""


def conversion_for(config: MoisstKitti360DataParserConfig) -> Kitti360Config:
    """The converter settings of a dataparser config, writing into a cache folder keyed by those settings."""
    shared = {f.name: getattr(config, f.name) for f in fields(Kitti360Config) if f.name not in ("root", "out", "overwrite")
              and hasattr(config, f.name)}
    conv = Kitti360Config(root=Path(config.data).resolve(), **shared)
    conv.cameras = tuple(conv.cameras)
    key = json.dumps({k: str(v) for k, v in asdict(conv).items() if k != "out"}, sort_keys=True)
    digest = hashlib.sha1(key.encode()).hexdigest()[:12]
    conv.out = Path(config.cache_dir) / f"{config.sequence}_{config.first_frame}_{digest}"
    conv.overwrite = True
    return conv


@dataclass
class MoisstKitti360DataParser(MoisstRigDataParser):
    """Dataparser for KITTI-360 (via a cached ``moisst-rig/1`` conversion)."""

    config: MoisstKitti360DataParserConfig

    def rig_folder(self) -> Path:
        """The cached conversion (made on first use)."""
        conv = conversion_for(self.config)
        done = conv.out / ".moisst-kitti360-done"
        if not done.is_file():
            convert(conv)
            done.write_text("converted\n")
        return conv.out


moisst_kitti360_dataparser = DataParserSpecification(
    config=MoisstKitti360DataParserConfig(),
    description="KITTI-360 sequence from its download layout (converted to moisst-rig/1 in a cache folder).",
)
