"""nerfstudio dataparser ``moisst-rig`` for the ``moisst-rig/1`` format (thin glue over ``moisst_ns.rig``).

Camera frames become nerfstudio ``Cameras`` posed with the *priors* (eq. 2 with prior extrinsic and delta); the
calibration optimiser regenerates every training ray from the current calibration. The world is normalised by a
translation and a uniform scale only (no rotation), stored as ``dataparser_transform`` / ``dataparser_scale``, so
metric results map back exactly.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Type

import numpy as np
import torch

from nerfstudio.cameras.cameras import CAMERA_MODEL_TO_TYPE, Cameras
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataParserConfig, DataparserOutputs
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.plugins.registry_dataparser import DataParserSpecification

from moisst_ns.rig.calibration import RigCalibration, RigData
from moisst_ns.rig.format import Calibration, RigFormatError, load_calibration, load_rig
from moisst_ns.rig.world import WorldFrame

TRAJECTORY_EXTENT = 0.5
"""The reference trajectory's half extent (largest axis) is scaled to this many model units."""
EVAL_EVERY = 10
"""Eval frames: every ``EVAL_EVERY``-th camera frame (they stay in the training set too: calibration uses all data)."""


@dataclass
class MoisstRigDataParserConfig(DataParserConfig):
    """Reads a ``moisst-rig/1`` dataset (``DATASET/rig.json``)."""

    _target: Type = field(default_factory=lambda: MoisstRigDataParser)
    data: Path = Path("data/rig")
    """Dataset folder holding rig.json."""
    prior_calibration: Optional[Path] = None
    """A calibration.json whose sensors replace rig.json's priors (e.g. the LiDAR-first stage's estimate, so the
    NeRF starts from it); rig.json itself is never modified."""


def apply_prior_calibration(rig, calibration, file: Path) -> None:
    """Replace the priors of ``rig`` (in memory) by those of ``calibration`` for every sensor it names, and carry its
    trajectory to the reference sensor's frame when ``calibration`` says the two differ (``trajectory_T_reference``)."""
    if calibration.reference_sensor != rig.reference_sensor:
        raise RigFormatError(file, "reference_sensor", f"{calibration.reference_sensor!r} is not the rig's reference sensor {rig.reference_sensor!r}")
    for name, pose in calibration.T_ref_sensor.items():
        if name not in rig.sensors:
            raise RigFormatError(file, f"sensors.{name}", f"not a sensor of the rig {sorted(rig.sensors)}")
        if name != rig.reference_sensor:
            rig.sensors[name].T_ref_sensor = np.asarray(pose, dtype=np.float64)
            rig.sensors[name].time_offset = float(calibration.time_offset[name])
    if calibration.trajectory_T_reference is not None:
        rig.carry_trajectory(calibration.trajectory_T_reference)


@dataclass
class MoisstRigDataParser(DataParser):
    """Dataparser for ``moisst-rig/1``."""

    config: MoisstRigDataParserConfig

    def rig_folder(self) -> Path:
        """The ``moisst-rig/1`` folder read (``MoisstPipeline`` runs the calibration stages on it)."""
        return Path(self.config.data)

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        rig = load_rig(self.rig_folder())
        dataset_priors, prior = None, None
        if self.config.prior_calibration is not None:
            dataset_priors, prior = Calibration.from_rig(rig), load_calibration(self.config.prior_calibration)
            apply_prior_calibration(rig, prior, self.config.prior_calibration)
        gt_file = rig.root / "ground_truth.json"  # for error metrics only (never optimised)
        truth = load_calibration(gt_file) if gt_file.is_file() else None
        if truth is not None:
            missing = sorted(set(rig.sensors) - set(truth.T_ref_sensor))
            if missing or truth.reference_sensor != rig.reference_sensor:
                raise RigFormatError(gt_file, "sensors", f"must name the rig's reference sensor and every sensor (missing: {missing})")
        data = RigData.from_rig(rig, truth)
        data.dataset_priors = dataset_priors
        data.trajectory_T_reference = None if prior is None else prior.trajectory_T_reference

        # Normalisation: world_model = scale * (world - center); no rotation, so extrinsics keep their axes.
        world = WorldFrame.fit(rig.trajectory_positions, TRAJECTORY_EXTENT)

        camera_frames = [i for i, f in enumerate(rig.frames) if rig.sensors[f.sensor].type == "camera"]
        if not camera_frames:
            raise RigFormatError(rig.root / "rig.json", "frames", "no camera frames (MOISST needs at least one camera)")
        if split != "train":
            camera_frames = camera_frames[::EVAL_EVERY]

        frames = [rig.frames[i] for i in camera_frames]
        sensor_idx = torch.tensor([data.sensor_names.index(f.sensor) for f in frames])
        stamps = torch.tensor([f.timestamp - data.t0 for f in frames], dtype=torch.float64)
        with torch.no_grad():
            c2w = world.camera_to_model(RigCalibration(data).prior_sensor_poses(sensor_idx, stamps)).numpy()

        intr = [rig.sensors[f.sensor].intrinsics for f in frames]
        distortion = torch.tensor([[k["k1"], k["k2"], k.get("k3", 0.0), k.get("k4", 0.0), k["p1"], k["p2"]] for k in intr]).float()
        cameras = Cameras(
            camera_to_worlds=torch.from_numpy(c2w[:, :3, :4]).float(),
            fx=torch.tensor([k["fl_x"] for k in intr]).float()[:, None],
            fy=torch.tensor([k["fl_y"] for k in intr]).float()[:, None],
            cx=torch.tensor([k["cx"] for k in intr]).float()[:, None],
            cy=torch.tensor([k["cy"] for k in intr]).float()[:, None],
            width=torch.tensor([k["w"] for k in intr])[:, None],
            height=torch.tensor([k["h"] for k in intr])[:, None],
            distortion_params=distortion,
            camera_type=torch.tensor([int(CAMERA_MODEL_TO_TYPE[k["camera_model"]].value) for k in intr])[:, None],
            times=stamps.float()[:, None],
            metadata={"sensor_idx": sensor_idx[:, None]},
        )
        transform = torch.eye(4)[:3, :]
        # nerfstudio applies the transform, then the scale: store the translation pre-scale so that
        # model = scale * (transform @ world) holds.
        transform[:, 3] = torch.from_numpy(-world.center).float()
        data.world, data.frame_sensor_index, data.frame_stamps = world, sensor_idx.numpy(), stamps.numpy()
        return DataparserOutputs(
            image_filenames=[rig.root / f.file_path for f in frames],
            cameras=cameras,
            scene_box=SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])),
            dataparser_transform=transform,
            dataparser_scale=world.scale,
            metadata={"moisst_rig": data},
        )


moisst_rig_dataparser = DataParserSpecification(
    config=MoisstRigDataParserConfig(),
    description="moisst-rig/1 rig datasets (rig.json + TUM reference trajectory).",
)
