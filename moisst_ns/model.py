"""``MoisstModel``: nerfacto whose pose optimiser is the rig calibration (paper section III-B/C).

Thin glue over nerfacto: the field, proposal sampling and losses are nerfacto's; what changes is
(1) the camera optimiser is ``CalibrationOptimizer`` (rays regenerated from ``T_r(t + delta_i) @ ref_T_i``),
(2) the schedule of paper III-C.3 (weight decay on the hash grids for the first steps, then removed), plus an
optional reference-only warm-up and a BARF-style coarse-to-fine release of the hash levels,
(3) no LPIPS (its weights would be downloaded at run time).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Literal, Optional, Tuple, Type

import torch
from torch import Tensor
from torch.nn import Parameter

from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.field_components.encodings import HashEncoding
from nerfstudio.models.nerfacto import NerfactoModel, NerfactoModelConfig
from nerfstudio.utils.rich_utils import CONSOLE

from moisst_ns.runs.history import append_history
from moisst_ns.viewer_panel import CalibrationPanel
from moisst_ns.compat import allow_numpy_in_checkpoints, without_lpips
from moisst_ns.data.layout import RayLayout
from moisst_ns.losses import depth_smoothness_loss, dssim_loss, lidar_depth_loss, map_range_loss
from moisst_ns.schedules import rescale_schedules
from moisst_ns.calibration_optimizer import CalibrationOptimizer, CalibrationOptimizerConfig
from moisst_ns.compiled_grid import compile_hash_encodings
from moisst_ns.contraction import use_linf_contraction

allow_numpy_in_checkpoints()  # nerfstudio 1.1.5 checkpoints under torch >= 2.6 (moisst_ns.compat)

COARSE_TO_FINE_START_LEVELS = 2.0
"""Levels fully on at the start of the coarse-to-fine release."""
COMPILE_MIN_STEPS = 300
"""Shortest run that ``compile_hash_grid="auto"`` compiles for (a cold compile costs about as much as it saves in 300
``moisst-lite`` steps)."""


def hash_level_weights(progress: float, num_levels: int, start_levels: float) -> Tensor:
    """BARF-style coarse-to-fine weights of the hash levels (BARF, ICCV 2021, eq. 14 adapted to levels).

    Args:
        progress: 0 at the start of the release, 1 when every level is on.
        num_levels: levels of the hash grid.
        start_levels: how many levels are fully on at ``progress = 0``.

    Returns:
        (num_levels,) weights in [0, 1]: level ``k`` is weighted ``(1 - cos(pi * clamp(a - k, 0, 1))) / 2`` with
        ``a = start_levels + progress * (num_levels - start_levels)``.
    """
    alpha = start_levels + min(max(progress, 0.0), 1.0) * (num_levels - start_levels)
    k = torch.arange(num_levels, dtype=torch.float32)
    return (1.0 - torch.cos(math.pi * torch.clamp(alpha - k, 0.0, 1.0))) / 2.0


def _detached_positions(density_fn):
    """A proposal network's density function that sees its positions without their gradient."""

    def density(positions: Tensor, times: Optional[Tensor] = None) -> Tensor:
        return density_fn(positions.detach(), times)

    return density


@dataclass
class MoisstModelConfig(NerfactoModelConfig):
    """nerfacto + MOISST rig calibration."""

    _target: Type = field(default_factory=lambda: MoisstModel)
    camera_optimizer: CalibrationOptimizerConfig = field(default_factory=CalibrationOptimizerConfig)
    """The rig calibration (replaces nerfacto's per-frame pose optimiser)."""
    calibration_warmup_steps: int = 0
    """Steps at the start during which the calibration is frozen."""
    reference_only_warmup: bool = False
    """During the warm-up, supervise with the reference sensor's rays only (the others get zero loss weight), so
    the scene is first built from the one sensor whose poses are known."""
    coarse_to_fine: Tuple[int, int] = (0, 0)
    """(start, end) steps of a BARF-style release of the hash levels: before ``start`` only
    ``COARSE_TO_FINE_START_LEVELS`` levels are on, at ``end`` all; (0, 0) disables it."""
    depth_loss_mult: float = 20.0
    """lambda_D of paper eq. 13: weight of the LiDAR depth loss (L2 on the expected ray depth in model units, the
    paper's normalised depths). Model units are metres x the dataparser's ``world_scale``, so per square metre it is
    ``lambda_D * world_scale**2`` and falls with the drive's extent (0.03 on the 50-frame synthetic rig; moisst-floor
    measured a five-fold lower floor with 500 on the tiny rig)."""
    map_range_mult: float = 0.0
    """Weight per square metre of the metric depth loss of camera rays against the LiDAR map's range
    (``losses.map_range_loss``, Huber at 0.2 m), on the rays of the datamanager's ``map_range_sensors`` (cameras whose
    pose is known). The LiDAR rays shape the density only along their own rays; this shapes it along the camera rays,
    whose rendered depth was otherwise off by about half a metre at CPU budgets. 0 disables it."""
    depth_loss_start: int = 0
    """Step from which the depth loss applies (paper: after 2 epochs of colour-only training)."""
    dssim_loss_mult: float = 0.1
    """lambda_SSIM of paper eq. 13 (needs ``datamanager.patch_size > 1``)."""
    depth_smoothness_mult: float = 1e-4
    """lambda_DS of paper eq. 13, RegNeRF's depth smoothness on patches (needs ``datamanager.patch_size > 1``)."""
    calibration_log_every: int = 25
    """Every this many steps, append each sensor's estimate (and errors, with ground truth) to
    ``calibration_history.csv`` in the run folder."""
    registration_steps: int = 0
    """Until this step, rays of non-reference sensors do not update the scene, only their calibration (they register
    against the reference camera's scene, as in SOAC). 0 disables it; so does a LiDAR reference sensor."""
    depth_loss_ramp_steps: int = 0
    """The depth loss weight rises linearly from 0 to ``depth_loss_mult`` over this many steps after
    ``depth_loss_start`` (avoids a gradient spike on the LiDAR's calibration when depth first applies)."""
    hash_weight_decay_steps: int = 0
    """Step at which the hash grids' weight decay (set on the ``hash_grids`` optimiser) is removed (paper
    III-C.3: kept for the first epochs, then removed so finer detail can be learned)."""
    compile_hash_grid: Literal["auto", "on", "off"] = "auto"
    """``torch.compile`` the torch hash-grid encodings (``moisst_ns.compiled_grid``). ``auto``: on for CPU runs of at
    least ``COMPILE_MIN_STEPS`` steps (compiling costs ~20-40 s once per process); ``on``: always; ``off``: eager."""
    schedule_steps: int = 0
    """Run length the schedules were built for; another trainer length rescales them at set-up
    (``schedules.rescale_schedules``). 0: never rescale."""


class MoisstModel(NerfactoModel):
    """nerfacto with the rig calibration of MOISST."""

    config: MoisstModelConfig
    camera_optimizer: CalibrationOptimizer

    def populate_modules(self):
        with without_lpips():
            super().populate_modules()
        use_linf_contraction(self)  # the same contraction without torch's slow CPU max norm (moisst_ns.contraction)
        rig = (self.kwargs.get("metadata") or {}).get("moisst_rig")
        if rig is None:
            raise ValueError("MoisstModel needs a rig: use the moisst-rig dataparser (ns-train moisst --data DATASET)")
        self.camera_optimizer = self.config.camera_optimizer.setup(num_cameras=self.num_train_data, device="cpu", rig=rig)
        names = [n for i, n in enumerate(rig.sensor_names) if i != rig.reference_index]
        self.calibration = CalibrationPanel(names, rig.ground_truth is not None)
        self.calibration.update(self.camera_optimizer.sensor_summary())
        self._hash_encodings: List[HashEncoding] = [m for m in self.modules() if isinstance(m, HashEncoding)]
        self._c2f_progress: Optional[float] = None
        if self.config.coarse_to_fine != (0, 0):
            if any(enc.tcnn_encoding is not None for enc in self._hash_encodings):
                CONSOLE.print("[yellow]coarse_to_fine needs the torch hash grid (tcnn fuses it): disabled")
            else:
                for enc in self._hash_encodings:
                    enc.register_forward_hook(self._mask_levels)
        # The proposal networks see the sample positions detached from the calibration. They only choose where the
        # field samples (nerfacto's interlevel loss fits them to the field's weights); otherwise that fitting loss
        # pulls on every sensor's extrinsic and time offset, and their backward computes a position gradient that is
        # ~40 % of a ``moisst`` step (docs/benchmarks.md). The field's samples keep their gradient.
        self.density_fns = [_detached_positions(fn) for fn in self.density_fns]
        self._step = 0
        self._hash_optimizer = None  # the ``hash_grids`` optimiser whose weight decay ends at ``hash_weight_decay_steps``
        # With a LiDAR as the reference sensor no camera's poses are known: no camera rays can build the scene alone,
        # so the detached registration phase is skipped and every sensor trains jointly (the paper's schedule).
        self._reference_is_camera = bool((self.camera_optimizer.frame_sensor == rig.reference_index).any())
        self._detached_pass = False
        self._warmup_active = self.config.calibration_warmup_steps > 0
        if self._warmup_active:
            self.camera_optimizer.set_trainable(False)

    # --- schedule ------------------------------------------------------------------------------------------------

    def _mask_levels(self, module: HashEncoding, inputs, output: Tensor) -> Tensor:
        if self._c2f_progress is None:
            return output
        weights = hash_level_weights(self._c2f_progress, module.num_levels, COARSE_TO_FINE_START_LEVELS)
        return output * weights.to(output).repeat_interleave(module.features_per_level)

    def _update_schedule(self, step: int) -> None:
        self._step = step
        start, end = self.config.coarse_to_fine  # (0, 0): never on (the levels' hooks are registered only otherwise)
        self._c2f_progress = None if step >= end else max(step - start, 0) / max(end - start, 1)
        if self._warmup_active and step >= self.config.calibration_warmup_steps:
            self._warmup_active = False
            self.camera_optimizer.set_trainable(True)
        if self._hash_optimizer is not None and step >= self.config.hash_weight_decay_steps:
            for group in self._hash_optimizer.param_groups:
                group["weight_decay"] = 0.0

    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        trainer = training_callback_attributes.trainer
        if trainer is not None and self.config.schedule_steps > 0 and trainer.config.max_num_iterations != self.config.schedule_steps:
            rescale_schedules(trainer.config, self.config.schedule_steps, trainer.config.max_num_iterations)
        callbacks = super().get_training_callbacks(training_callback_attributes)
        steps = trainer.config.max_num_iterations if trainer is not None else self.config.schedule_steps
        self._compile_hash_grid(steps)
        callbacks += [TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], self._update_schedule),  # every step
                      TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self._after_step)]
        if trainer is not None and self.config.calibration_log_every > 0:
            history = Path(trainer.base_dir) / "calibration_history.csv"
            callbacks.append(
                TrainingCallback(
                    [TrainingCallbackLocation.AFTER_TRAIN_ITERATION],
                    lambda step: self.log_calibration(history, step),
                    update_every_num_iters=self.config.calibration_log_every,
                )
            )
        optimizers = training_callback_attributes.optimizers
        if self.config.hash_weight_decay_steps > 0 and optimizers is not None:
            self._hash_optimizer = optimizers.optimizers.get("hash_grids")
        return callbacks

    def _compile_hash_grid(self, steps: int) -> None:
        """Compile the torch hash grids for a run of ``steps`` steps (``compile_hash_grid``); say so in one line."""
        mode = self.config.compile_hash_grid
        if mode == "off" or (mode == "auto" and (steps < COMPILE_MIN_STEPS or self.device.type != "cpu")):
            return
        started = time.perf_counter()
        why_not = compile_hash_encodings([e for e in self._hash_encodings if e.tcnn_encoding is None], self.device)
        if why_not is None:
            CONSOLE.print(f"hash grids compiled (torch.compile, deterministic algorithms on) in {time.perf_counter() - started:.0f} s")
        else:
            CONSOLE.print(f"[yellow]hash grids stay eager: {why_not}")

    def get_param_groups(self) -> Dict[str, List[Parameter]]:
        hash_params = [p for enc in self._hash_encodings for p in enc.parameters()]
        hash_ids = {id(p) for p in hash_params}
        groups = {
            "proposal_networks": [p for p in self.proposal_networks.parameters() if id(p) not in hash_ids],
            "fields": [p for p in self.field.parameters() if id(p) not in hash_ids],
            "hash_grids": hash_params,
        }
        self.camera_optimizer.get_param_groups(param_groups=groups)
        return groups

    def _after_step(self, step: int) -> None:
        """Stop on non-finite calibration parameters (naming the sensor and step), then apply the bounds."""
        rig = self.camera_optimizer.rig
        bad = ~(torch.isfinite(rig.rotvec).all(-1) & torch.isfinite(rig.translation).all(-1) & torch.isfinite(rig.time_offset))
        if bool(bad.any()):
            names = [rig.data.sensor_names[i] for i in torch.nonzero(bad)[:, 0].tolist()]
            raise FloatingPointError(f"step {step}: the calibration of sensor(s) {', '.join(names)} became NaN/inf; stopping (nothing written)")
        self.camera_optimizer.project()

    def log_calibration(self, path: Path, step: int) -> None:
        """Append the current estimate of every non-reference sensor to the history CSV."""
        summary = self.camera_optimizer.sensor_summary()
        self.calibration.update(summary)
        CONSOLE.print(f"[calibration] step {step}: " + " | ".join(self.camera_optimizer.change_summary()))
        if not hasattr(self, "_log_start"):
            self._log_start = time.perf_counter()
        append_history(path, step, {n: dict(v, elapsed_s=time.perf_counter() - self._log_start) for n, v in summary.items()})

    # --- registration: non-reference rays see a detached scene -------------------------------------------------

    def _is_reference(self, frames: Tensor) -> Tensor:
        """Whether each of the training frames ``frames`` is the reference sensor's (on the calibration's device)."""
        opt = self.camera_optimizer
        return opt.frame_sensor[frames.reshape(-1).long().to(opt.frame_sensor.device)] == opt.rig.data.reference_index

    def get_outputs(self, ray_bundle):
        if not self.training and not torch.is_inference_mode_enabled():
            return self._with_normals(ray_bundle, super().get_outputs(ray_bundle))
        registering = self.training and self._step < self.config.registration_steps and self._reference_is_camera
        if not registering or self._detached_pass:
            return super().get_outputs(ray_bundle)
        reference = self._is_reference(ray_bundle.camera_indices)  # a camera: a LiDAR ray's is a placeholder
        if "is_lidar" in ray_bundle.metadata:
            reference &= ~ray_bundle.metadata["is_lidar"][:, 0].to(reference.device)
        if bool(reference.all()) or not bool(reference.any()):
            return super().get_outputs(ray_bundle)
        ref_idx, other_idx = torch.nonzero(reference)[:, 0], torch.nonzero(~reference)[:, 0]
        outputs_ref = super().get_outputs(ray_bundle[ref_idx])
        detached = {
            name: p.detach()
            for name, p in self.named_parameters()
            if name.startswith(("field.", "proposal_networks.")) and "embedding_appearance" not in name
        }
        self._detached_pass = True
        try:
            outputs_other = torch.func.functional_call(self, detached, (ray_bundle[other_idx],), strict=False)
        finally:
            self._detached_pass = False
        merged = dict(outputs_ref)
        for key, value in outputs_ref.items():
            if isinstance(value, Tensor) and key in outputs_other and value.shape[0] == ref_idx.shape[0]:
                full = value.new_zeros((len(ray_bundle),) + tuple(value.shape[1:]))
                full[ref_idx] = value
                full[other_idx] = outputs_other[key].to(value)
                merged[key] = full
        return merged

    def _with_normals(self, ray_bundle, outputs: Dict[str, Tensor]) -> Dict[str, Tensor]:
        """Render outputs plus ``normals`` in [0, 1] (what ``ns-export pointcloud`` exports by default): minus the
        density's gradient at each ray's median depth, normalised (one more field query per ray)."""
        with torch.enable_grad():
            points = (ray_bundle.origins + ray_bundle.directions * outputs["depth"]).detach().requires_grad_(True)
            gradient = torch.autograd.grad(self.field.density_fn(points).sum(), points)[0]
        outputs["normals"] = (1.0 - torch.nn.functional.normalize(gradient, dim=-1)) / 2.0
        return outputs

    # --- losses and metrics --------------------------------------------------------------------------------------

    @staticmethod
    def _split(outputs: Dict[str, Tensor], batch: Dict) -> Tuple[Dict[str, Tensor], Optional[slice]]:
        """Camera-ray view of the outputs (for nerfacto's colour loss/metrics) and the LiDAR rays' slice
        (``batch["ray_layout"]``; eval batches have none: all camera rays)."""
        layout: Optional[RayLayout] = batch.get("ray_layout")
        if layout is None or layout.lidar is None or outputs["rgb"].shape[0] == layout.num_camera:
            return outputs, None
        camera = dict(outputs)
        for key in ("rgb", "accumulation", "depth", "expected_depth"):
            camera[key] = outputs[key][layout.camera]
        return camera, layout.lidar

    def get_metrics_dict(self, outputs, batch):
        camera, lidar = self._split(outputs, batch)
        metrics = super().get_metrics_dict(camera, batch)
        if lidar is not None and "lidar_range" in batch:
            mse = lidar_depth_loss(outputs["expected_depth"][lidar, 0].detach(), batch["lidar_range"])
            metrics["lidar_depth_rmse_m"] = mse.sqrt() / float(self.camera_optimizer.world_scale)
        return metrics

    def get_loss_dict(self, outputs, batch, metrics_dict=None):
        camera, lidar = self._split(outputs, batch)
        if self.training and self._warmup_active and self.config.reference_only_warmup:
            keep = self._is_reference(batch["indices"][:, 0]).cpu()
            if keep.any():
                batch = dict(batch)
                batch["image"] = batch["image"][keep]
                if not bool(keep.all()) and "ray_layout" in batch:
                    batch["ray_layout"] = batch["ray_layout"].without_patches()  # the filter breaks the patches
                for key in ("rgb", "accumulation", "expected_depth"):
                    camera[key] = camera[key][keep.to(camera[key].device)]
                if "map_range" in batch:
                    batch["map_range"] = batch["map_range"][keep.to(batch["map_range"].device)]
        loss_dict = super().get_loss_dict(camera, batch, metrics_dict)
        layout: Optional[RayLayout] = batch.get("ray_layout")
        if self.training and layout is not None and layout.has_patches and layout.num_patch <= camera["rgb"].shape[0]:
            num_patch, shape = layout.num_patch, (-1, layout.patch_size, layout.patch_size)
            if self.config.dssim_loss_mult > 0:
                image = self.renderer_rgb.blend_background(batch["image"][:num_patch].to(self.device))
                loss_dict["dssim_loss"] = self.config.dssim_loss_mult * dssim_loss(
                    camera["rgb"][:num_patch].view(*shape, 3), image[..., :3].view(*shape, 3))
            if self.config.depth_smoothness_mult > 0:
                depth = camera["expected_depth"][:num_patch].view(*shape)
                loss_dict["depth_smoothness_loss"] = self.config.depth_smoothness_mult * depth_smoothness_loss(depth)
        ramp = self._depth_ramp()
        if self.training and self.config.map_range_mult > 0 and "map_range" in batch and ramp > 0:
            loss_dict["map_range_loss"] = ramp * self.config.map_range_mult * map_range_loss(
                camera["expected_depth"][:, 0], batch["map_range"], float(self.camera_optimizer.world_scale))
        if self.training and lidar is not None and "lidar_range" in batch and ramp > 0:
            loss_dict["depth_loss"] = ramp * self.config.depth_loss_mult * lidar_depth_loss(
                outputs["expected_depth"][lidar, 0], batch["lidar_range"])
        if self.training:
            for name, value in loss_dict.items():
                if not bool(torch.isfinite(value).all()):
                    raise FloatingPointError(f"step {self._step}: loss {name} is NaN/inf; stopping (nothing written)")
        return loss_dict

    def _depth_ramp(self) -> float:
        """Weight factor of the depth terms (LiDAR depth, map range) at this step: 0 before
        ``depth_loss_start`` (the colour-only start), then rising linearly to 1 over ``depth_loss_ramp_steps``."""
        if self._step < self.config.depth_loss_start:
            return 0.0
        if self.config.depth_loss_ramp_steps <= 0:
            return 1.0
        return min(1.0, (self._step - self.config.depth_loss_start + 1) / self.config.depth_loss_ramp_steps)

    def get_image_metrics_and_images(self, outputs, batch):
        metrics, images = super().get_image_metrics_and_images(outputs, batch)
        metrics.pop("lpips", None)
        return metrics, images
