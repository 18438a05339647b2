"""``MoisstDataManager``: camera pixels and LiDAR points in one batch (paper III-A.3, III-C).

Camera rays come from nerfstudio's ``VanillaDataManager`` (posed with the priors; the calibration optimiser
re-poses them). LiDAR rays are appended to the same ``RayBundle``: each carries, in its metadata, the point in the
LiDAR frame, the LiDAR's sensor index and the point's own-clock time (frame stamp + per-point offset), and the
calibration optimiser regenerates its origin ``T_r(t + delta_L) @ ref_T_L`` and direction every step. The target
is the measured range (``batch["lidar_range"]``, model units).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Dict, Tuple, Type

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor

from nerfstudio.cameras.rays import RayBundle
from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManager, VanillaDataManagerConfig
from nerfstudio.data.pixel_samplers import PixelSamplerConfig
from nerfstudio.utils.rich_utils import CONSOLE

from moisst_ns.data.layout import RayLayout
from moisst_ns.rig.format import Rig, RigFormatError, load_lidar_scan
from moisst_ns.rig.geometry import row_time

REGISTRATION_REFERENCE_FRACTION = 0.5
"""Share of camera rays from the reference camera while registering (the others' rays then only move their
calibration, so the scene keeps being trained by a fair number of rays)."""
MAP_RANGE_VOXEL = 0.05
"""Voxel of the LiDAR map behind the range targets (``map_range_sensors``), metres."""
HELD_BACK_EVERY = 5
"""Of each camera of ``held_back_sensors``, the training frames ``k`` with ``k % HELD_BACK_EVERY == 2`` (its 3rd,
8th, ...: never its first, which the report renders) are held back: a fifth of its frames."""


@dataclass
class MoisstDataManagerConfig(VanillaDataManagerConfig):
    """Camera pixels plus LiDAR points per step."""

    _target: Type = field(default_factory=lambda: MoisstDataManager)
    lidar_rays_per_batch: int = 256
    """LiDAR points sampled per step (on top of ``train_num_rays_per_batch`` camera pixels); 0 disables LiDAR."""
    lidar_min_range: float = 1.0
    """Points closer than this (metres) are dropped (the vehicle itself)."""
    lidar_max_range: float = 80.0
    """Points farther than this (metres) are dropped."""
    reference_only_steps: int = 0
    """Before this step only the reference camera's images are sampled (the warm-up builds the scene from the
    sensor whose poses are known, with every ray)."""
    registration_steps: int = 0
    """Until this step, a share ``REGISTRATION_REFERENCE_FRACTION`` of the camera rays comes from the reference camera."""
    lidar_start_step: int = 0
    """LiDAR points are sampled from this step on (set to where the depth loss starts)."""
    patch_fraction: float = 0.25
    """With ``patch_size > 1``: share of the camera rays sampled as P x P patches (the DSSIM and depth-smoothness
    losses of eq. 13 use them); the rest are single pixels spread over the images. All-patch sampling (1.0)
    concentrates the rays on few image locations, which measurably slowed the calibration at 1024 rays."""
    map_range_sensors: Tuple[str, ...] = ()
    """Cameras whose training rays get a metric range target from the LiDAR map (``batch["map_range"]``, model units,
    NaN where the map has none): the rig's LiDAR scans placed at the prior calibration, seen from each frame at its
    prior pose (``stages.map_range``). Only cameras whose pose is known belong here: the reference camera, cameras
    held at a stage's estimate (``moisst-calibrate`` sets it), every camera at the truth (``moisst-floor``)."""
    held_back_sensors: Tuple[str, ...] = ()
    """Cameras some of whose frames (``HELD_BACK_EVERY``) no training ray comes from: the joint refinement of a
    registered camera is kept only when it renders those frames significantly better (``uncertainty.refinement_check``)."""


class MoisstDataManager(VanillaDataManager):
    """VanillaDataManager + LiDAR points (rays are (re)built from the calibration by the model)."""

    config: MoisstDataManagerConfig

    def __init__(self, config: MoisstDataManagerConfig, *args, **kwargs):
        with warnings.catch_warnings():  # nerfstudio's 4 loader workers never start: CacheDataloader loads with threads
            warnings.filterwarnings("ignore", message="This DataLoader will create", category=UserWarning)
            super().__init__(config, *args, **kwargs)
        self.rig = self.train_dataparser_outputs.metadata["moisst_rig"]
        frame_sensor = torch.as_tensor(self.rig.frame_sensor_index)
        self.frame_is_reference = frame_sensor == self.rig.reference_index
        full = self.rig.rig
        self.lidar_points, self.lidar_stamps, self.lidar_sensor = load_lidar_points(self.rig, full, config.lidar_min_range, config.lidar_max_range)
        # Only the points inside the reference camera's view (by the priors): LiDAR rays land where the sensor whose
        # poses are known observes the scene; a 360 degree scan otherwise mostly hits space no camera constrains.
        if self.lidar_points.shape[0] > 0:
            keep = reference_view_mask(self.rig, full, self.lidar_points, self.lidar_sensor)
            if keep is not None and bool(keep.any()):
                CONSOLE.print(f"LiDAR: {int(keep.sum())} of {keep.numel()} points inside the reference camera's view")
                self.lidar_points, self.lidar_stamps, self.lidar_sensor = self.lidar_points[keep], self.lidar_stamps[keep], self.lidar_sensor[keep]
        self.lidar_generator = torch.Generator().manual_seed(int(kwargs.get("seed", 0)) + 12345)
        self.frame_readout, self.frame_height = frame_readouts(self.rig, full, self.train_dataset.cameras)
        self.map_range, self.map_slot = self._map_ranges()
        self.held_back = held_back_frames(self.rig.sensor_names, self.rig.frame_sensor_index, config.held_back_sensors)
        self.single_pixel_sampler = None
        if config.patch_size > 1 and config.patch_fraction < 1.0:
            self.single_pixel_sampler = PixelSamplerConfig(num_rays_per_batch=config.train_num_rays_per_batch).setup()

    def _get_pixel_sampler(self, dataset, num_rays_per_batch: int):
        sampler = super()._get_pixel_sampler(dataset, num_rays_per_batch)
        # nerfstudio 1.1.5's PatchPixelSampler rounds the batch with its default patch size (32) before it takes
        # ours, so e.g. 512 rays became 0: round again with the real patch size.
        sampler.set_num_rays_per_batch(num_rays_per_batch)
        return sampler

    def _map_ranges(self) -> Tuple[Tensor | None, Tensor | None]:
        """Range images of the LiDAR map for the training frames of ``map_range_sensors`` (model units, NaN: none),
        and each training image's row in them (-1: no target)."""
        names = tuple(self.config.map_range_sensors)
        if not names:
            return None, None
        from moisst_ns.rig.format import Calibration
        from moisst_ns.stages.camera.lidar_map import lidar_map
        from moisst_ns.stages.camera.map_range import opengl_to_opencv, range_image, rolling_camera_points

        full = self.rig.rig
        unknown = [n for n in names if n not in full.sensors or full.sensors[n].type != "camera"]
        if unknown:
            raise RigFormatError(full.root / "rig.json", "sensors", f"map_range_sensors names no camera of the rig: {unknown}")
        world = lidar_map(full, Calibration.from_rig(full), MAP_RANGE_VOXEL, self.config.lidar_min_range, log=lambda s: None)
        points = self.rig.world.points_to_model(torch.from_numpy(world)).numpy()
        cameras = self.train_dataset.cameras
        sensor = [self.rig.sensor_names[i] for i in self.rig.frame_sensor_index]
        frames = [i for i, n in enumerate(sensor) if n in names]
        if not frames:
            return None, None
        slot = torch.full((len(sensor),), -1, dtype=torch.long)
        height, width = int(cameras.height.max()), int(cameras.width.max())
        ranges = torch.full((len(frames), height, width), float("nan"))
        c2w = cameras.camera_to_worlds.double().numpy()
        for row, i in enumerate(frames):
            rolling = self.frame_readout is not None and bool(self.frame_readout[i] > 0)
            cam = rolling_camera_points(self.rig, i, float(self.frame_readout[i]), world) if rolling else opengl_to_opencv(c2w[i], points)
            image = range_image(cam, float(cameras.fx[i]), float(cameras.fy[i]), float(cameras.cx[i]), float(cameras.cy[i]),
                                int(cameras.width[i]), int(cameras.height[i]), distortion=cameras.distortion_params[i].tolist())
            ranges[row, : image.shape[0], : image.shape[1]] = torch.from_numpy(image)
            slot[i] = row
        covered = float(torch.isfinite(ranges).float().mean())
        CONSOLE.print(f"LiDAR map ranges: {len(world)} map points, {len(frames)} frames of {list(names)}, {100 * covered:.0f} % of their pixels")
        return ranges, slot

    def map_range_of(self, indices: Tensor) -> Tensor:
        """The map's range (model units, NaN: none) of sampled pixels ``indices`` (image, y, x)."""
        idx = indices.long().cpu()
        row = self.map_slot[idx[:, 0]]
        out = torch.full((len(idx),), float("nan"))
        has = row >= 0
        out[has] = self.map_range[row[has], idx[has, 1], idx[has, 2]]
        return out

    def _sample(self, sampler, image_batch: Dict, count: int, fraction) -> Dict | None:
        """``count`` rays (pixels or patches, by ``sampler``), a share ``fraction`` of them from the reference camera
        (None: from all images uniformly)."""
        if count <= 0:
            return None
        unit = max(getattr(sampler.config, "patch_size", 1), 1) ** 2
        trained = ~self.held_back[image_batch["image_idx"].cpu()]
        if fraction is None:
            return sample_images(sampler, image_batch, torch.nonzero(trained)[:, 0], count)
        is_ref = self.frame_is_reference[image_batch["image_idx"].cpu()]
        n_ref = int(round(count * fraction / unit)) * unit
        return joined([sample_images(sampler, image_batch, torch.nonzero(mask)[:, 0], n) if n > 0 and bool(mask.any()) else None
                       for mask, n in ((is_ref & trained, n_ref), (~is_ref & trained, count - n_ref))])

    @property
    def has_lidar(self) -> bool:
        return self.config.lidar_rays_per_batch > 0 and self.lidar_points.shape[0] > 0

    def reference_fraction(self, step: int):
        """Share of camera rays from the reference camera at ``step`` (None: sample all images uniformly, also
        always when the reference sensor is a LiDAR: then every camera is sampled from the start)."""
        if not bool(self.frame_is_reference.any()):
            return None
        if step < self.config.reference_only_steps:
            return 1.0
        if step < self.config.registration_steps:
            return REGISTRATION_REFERENCE_FRACTION
        return None

    def next_train(self, step: int) -> Tuple[RayBundle, Dict]:
        self.train_count += 1
        image_batch = next(self.iter_train_image_dataloader)
        fraction = self.reference_fraction(step)
        total = self.train_pixel_sampler.num_rays_per_batch
        patch = max(self.config.patch_size, 1)
        cached = isinstance(image_batch["image"], torch.Tensor)  # not with variable-resolution images (a list)
        if self.single_pixel_sampler is not None and cached:
            n_patch = int(round(total * self.config.patch_fraction / patch**2)) * patch**2
            batch = joined([self._sample(self.train_pixel_sampler, image_batch, n_patch, fraction),
                            self._sample(self.single_pixel_sampler, image_batch, total - n_patch, fraction)])
        else:
            if not cached or (fraction is None and not bool(self.held_back.any())):
                batch = self.train_pixel_sampler.sample(image_batch)
            else:
                batch = self._sample(self.train_pixel_sampler, image_batch, total, fraction)
            n_patch = len(batch["indices"]) if patch > 1 else 0
        ray_bundle = self.train_ray_generator(batch["indices"])
        device = ray_bundle.origins.device
        if self.frame_readout is not None:  # a rolling shutter: each ray at its row's time (the calibration optimiser)
            ray_bundle.metadata["row_time"] = pixel_row_times(batch["indices"], self.frame_readout, self.frame_height).to(device)
        num_lidar = self.config.lidar_rays_per_batch if self.has_lidar and step >= self.config.lidar_start_step else 0
        batch["ray_layout"] = RayLayout(len(ray_bundle), num_lidar, n_patch, patch)
        if self.map_range is not None:
            batch["map_range"] = self.map_range_of(batch["indices"]).to(device)
        if not num_lidar:
            return ray_bundle, batch
        pick = torch.randint(self.lidar_points.shape[0], (num_lidar,), generator=self.lidar_generator)
        points = self.lidar_points[pick].to(device)
        batch["lidar_range"] = points.norm(dim=-1) * float(self.rig.world.scale)
        batch["lidar_sensor"] = self.lidar_sensor[pick].to(device)
        return with_lidar_rays(ray_bundle, points, self.lidar_stamps[pick].to(device), batch["lidar_sensor"]), batch


def frame_readouts(rig, full: Rig, cameras) -> Tuple[Tensor | None, Tensor | None]:
    """Per training image, its camera's rolling-shutter readout (seconds, float64) and height (pixels); (None, None)
    when every camera has a global shutter. ``rig``: the dataparser's RigData, ``full``: the loaded rig.json."""
    readout = torch.tensor([float(full.sensors[rig.sensor_names[i]].readout_time) for i in rig.frame_sensor_index], dtype=torch.float64)
    if not bool((readout > 0).any()):
        return None, None
    return readout, cameras.height.reshape(-1).long()


def pixel_row_times(indices: Tensor, readout: Tensor, height: Tensor) -> Float[Tensor, "num 1"]:
    """Capture time of sampled pixels ``indices`` (image, y, x) after their frames' stamps (``geometry.row_time`` of
    the row's centre ``y + 0.5``, nerfstudio's pixel centre), seconds, float64."""
    image, y = indices[:, 0].long().cpu(), indices[:, 1].cpu().to(torch.float64)
    heights, out = height[image], torch.zeros(len(image), 1, dtype=torch.float64)
    for h in torch.unique(heights).tolist():
        rows = heights == h
        out[rows, 0] = row_time(y[rows] + 0.5, readout[image][rows], int(h))
    return out


def held_back_frames(sensor_names, frame_sensor, held_back_sensors) -> Tensor:
    """Which training frames no ray is drawn from: of each camera named in ``held_back_sensors``, its frames ``k`` with
    ``k % HELD_BACK_EVERY == 2`` (``frame_sensor``: sensor index of every training frame, in order).

    Returns:
        (num_frames,) bool.
    """
    unknown = set(held_back_sensors) - set(sensor_names)
    if unknown:
        raise ValueError(f"held_back_sensors: {sorted(unknown)} not sensors of the rig {list(sensor_names)}")
    held = torch.zeros(len(frame_sensor), dtype=torch.bool)
    for name in held_back_sensors:
        held[torch.as_tensor(np.flatnonzero(np.asarray(frame_sensor) == sensor_names.index(name))[2::HELD_BACK_EVERY])] = True
    return held


def joined(parts) -> Dict:
    """Sampled batches (None: an empty part) concatenated, key by key."""
    parts = [p for p in parts if p is not None]
    return {k: torch.cat([p[k] for p in parts]) for k in parts[0]}


def sample_images(sampler, image_batch: Dict, positions: Tensor, count: int) -> Dict:
    """``count`` pixels (or patches) from the images at ``positions`` of a cached image batch, without copying
    the images (nerfstudio's collate would need a sliced copy of the whole cache)."""
    image = image_batch["image"]
    height, width = image.shape[1:3]
    local = sampler.sample_method(count, len(positions), height, width, device=image.device)
    c = positions.to(local.device)[local[:, 0].long()].cpu()
    y, x = local[:, 1].long().cpu(), local[:, 2].long().cpu()
    out = {k: v[c, y, x] for k, v in image_batch.items() if k != "image_idx" and isinstance(v, torch.Tensor) and v.dim() >= 3}
    indices = local.clone()
    indices[:, 0] = image_batch["image_idx"][c]
    out["indices"] = indices
    return out


def with_lidar_rays(camera: RayBundle, points: Float[Tensor, "num 3"], stamps: Float[Tensor, "num"], sensor: Tensor) -> RayBundle:
    """``camera``'s rays followed by LiDAR rays through ``points`` (LiDAR frame), whose origins and directions the
    calibration optimiser rebuilds; every other field of a LiDAR ray is a placeholder (0; ``directions_norm`` 1;
    ``pixel_area`` the camera rays' mean) and the camera rays get zero LiDAR columns."""
    num = points.shape[0]

    def rows(value, fill=0.0):  # ``value`` followed by ``num`` rows of ``fill``
        return None if value is None else torch.cat([value, torch.full((num, *value.shape[1:]), fill, dtype=value.dtype, device=value.device)])

    lidar = {"is_lidar": torch.ones(num, 1, dtype=torch.bool, device=points.device), "lidar_point": points,
             "lidar_stamp": stamps[:, None], "lidar_sensor": sensor[:, None]}
    metadata = {k: rows(v, 1.0 if k == "directions_norm" else 0.0) for k, v in camera.metadata.items()}
    metadata.update({k: torch.cat([v.new_zeros((len(camera), *v.shape[1:])), v]) for k, v in lidar.items()})
    return RayBundle(
        origins=rows(camera.origins), directions=torch.cat([camera.directions, points / points.norm(dim=-1, keepdim=True)]),
        pixel_area=rows(camera.pixel_area, float(camera.pixel_area.mean())), camera_indices=rows(camera.camera_indices),
        nears=rows(camera.nears), fars=rows(camera.fars), metadata=metadata, times=rows(camera.times),
    )


def reference_view_mask(rig, full: Rig, points: Tensor, sensor: Tensor):
    """Points that fall inside the reference camera's image when moved into its frame with the prior extrinsics
    (None when the reference is not a camera). ``full`` is the loaded rig.json (for the intrinsics)."""
    ref = full.sensors[full.reference_sensor]
    if ref.type != "camera":
        return None
    from moisst_ns.stages.camera.lidar_map import PinholeModel, project

    ext = torch.as_tensor(rig.prior_extrinsics, dtype=torch.float32)[sensor]  # ref_T_lidar per point
    model = PinholeModel.of(ref.intrinsics)
    uv, z = project(model, (ext[:, :3, :3] @ points[..., None])[..., 0] + ext[:, :3, 3])
    return (z > 0.5) & (uv[:, 0] >= 0) & (uv[:, 0] < model.width) & (uv[:, 1] >= 0) & (uv[:, 1] < model.height)


def load_lidar_points(rig, full: Rig, min_range: float, max_range: float):
    """All LiDAR points of the rig: (P, 3) float32 points, (P,) float64 own-clock times since t0, (P,) sensor ids.

    ``rig`` is the dataparser's RigData (sensor order, t0), ``full`` the loaded rig.json (frames and files).
    """
    points, stamps, sensors = [], [], []
    dropped_total = 0
    for frame in full.frames:
        if full.sensors[frame.sensor].type != "lidar":
            continue
        pts, times, dropped = load_lidar_scan(full.root / frame.file_path, min_range=min_range)
        keep = np.linalg.norm(pts, axis=1) <= max_range
        if not keep.any():
            raise RigFormatError(full.root / frame.file_path, "points", f"no points left within {min_range}-{max_range} m (range filtering)")
        dropped_total += dropped
        pts = pts[keep]
        offs = np.zeros(len(pts)) if times is None else times[keep]
        points.append(pts)
        stamps.append(frame.timestamp - rig.t0 + offs)
        sensors.append(np.full(len(pts), rig.sensor_names.index(frame.sensor)))
    if dropped_total:
        CONSOLE.print(f"[yellow]LiDAR: dropped {dropped_total} points with NaN/inf coordinates")
    if not points:
        return torch.zeros(0, 3), torch.zeros(0, dtype=torch.float64), torch.zeros(0, dtype=torch.long)
    return (
        torch.from_numpy(np.concatenate(points)).float(),
        torch.from_numpy(np.concatenate(stamps)).double(),
        torch.from_numpy(np.concatenate(sensors)).long(),
    )
