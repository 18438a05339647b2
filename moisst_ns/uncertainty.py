"""Per-sensor standard deviations of a trained calibration and its held-back loss against the prior.

For every camera the NeRF calibrated, fresh pixels of its frames (drawn with their own seed, not a training batch)
are rendered at the estimate; each pixel's colour residual (rendered minus observed, 3 channels) is differentiated
with respect to the sensor's 7 parameters by central finite differences (re-posing the rays, ``FD_STEPS``), and
``stages.uncertainty_math.least_squares_sigma`` turns the Jacobian and residuals into standard deviations, with the
frames as clusters (pixels of one frame share the scene's errors). The same pixels rendered with that sensor's
correction set to zero give the loss at the prior: a calibration that does not beat its prior there is not trusted.

Cost: ``2 x 7 + 2`` renders of ``RAYS_PER_SENSOR`` rays per camera (a few seconds each on a CPU for 1024 rays).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

from moisst_ns.stages.lidar.lidar_report import stage_sigma
from moisst_ns.stages.trust.uncertainty_math import inherited_sigma, least_squares_sigma

FD_STEPS = (0.002, 0.002, 0.002, np.deg2rad(0.02), np.deg2rad(0.02), np.deg2rad(0.02), 0.0005)
"""Finite-difference half-steps: 2 mm, 0.02 deg, 0.5 ms (a tenth of a pixel's footprint at 10 m for a 320-pixel
camera: small against the calibration's errors, large against float32 rendering noise)."""
RAYS_PER_SENSOR = 1024
"""Pixels per camera, spread evenly over its frames."""
CHUNK = 4096
"""Rays rendered per forward pass."""


@dataclass
class SensorUncertainty:
    """What the held-back pixels say about one sensor."""

    sigma: List[float]
    """7 standard deviations in ``PARAMETERS`` order: metres, radians, seconds."""
    loss_estimate: float
    """Mean squared colour residual at the estimate."""
    loss_prior: float
    """The same with this sensor's correction at zero (the prior the NeRF started from)."""


def _param_views(rig, index: int):
    """The 7 scalar views (translation x, y, z; rotvec 1-3; time offset) of sensor ``index``'s corrections."""
    return [(rig.translation, (index, 0)), (rig.translation, (index, 1)), (rig.translation, (index, 2)),
            (rig.rotvec, (index, 0)), (rig.rotvec, (index, 1)), (rig.rotvec, (index, 2)), (rig.time_offset, (index,))]


def _draw_pixels(datamanager, frames: List[int], count: int, generator: torch.Generator):
    """``count`` random pixels over ``frames`` (training-frame indices): (N, 3) ``[frame, y, x]`` and (N, 3) RGB."""
    per = max(count // max(len(frames), 1), 1)
    indices, colours = [], []
    for frame in frames:
        image = datamanager.train_dataset.get_image_float32(frame)[..., :3]
        h, w = image.shape[:2]
        y = torch.randint(h, (per,), generator=generator)
        x = torch.randint(w, (per,), generator=generator)
        indices.append(torch.stack([torch.full_like(y, frame), y, x], dim=1))
        colours.append(image[y, x])
    return torch.cat(indices), torch.cat(colours)


def _ray_generator(datamanager):
    """The training ray generator (built when the pipeline was loaded for inference, which sets up none)."""
    generator = getattr(datamanager, "train_ray_generator", None)
    if generator is None:
        from nerfstudio.model_components.ray_generators import RayGenerator

        generator = RayGenerator(datamanager.train_dataset.cameras.to(datamanager.device))
        datamanager.train_ray_generator = generator
    return generator


@torch.no_grad()
def _render(model, datamanager, indices: torch.Tensor, at: Sequence[Tuple[torch.Tensor, tuple, float]] = ()) -> torch.Tensor:
    """Colours of the pixels ``indices`` at the current calibration, re-posing the rays (in eval mode), with the scalar
    corrections ``at`` (``(parameter, index, value)``) set for the render and restored after."""
    saved = [(param, i, float(param[i])) for param, i, _ in at]
    for param, i, value in at:
        param[i] = value
    was_training = model.training
    out = []
    model.eval()
    try:
        generator = _ray_generator(datamanager)
        for start in range(0, len(indices), CHUNK):
            bundle = generator(indices[start:start + CHUNK].to(model.device))
            model.camera_optimizer.apply_to_raybundle(bundle)
            out.append(model(bundle)["rgb"].float().cpu())
    finally:
        model.train(was_training)
        for param, i, value in saved:
            param[i] = value
    return torch.cat(out)


def _at_prior(model, sensor: int) -> list:
    """``_render``'s ``at`` that sets camera ``sensor``'s corrections to zero (its prior)."""
    return [(param, i, 0.0) for param, i in _param_views(model.camera_optimizer.rig, sensor)]


@torch.no_grad()
def sensor_uncertainty(pipeline, sensor: int, seed: int) -> Optional[SensorUncertainty]:
    """Standard deviations and held-back losses of camera ``sensor`` (None when it has no training frame).

    Args:
        pipeline: the trained pipeline (its model renders in eval mode and is put back).
        sensor: sensor index in the rig.
        seed: seed of the pixel draw (independent of training's).

    Returns:
        ``SensorUncertainty`` or None.
    """
    model, datamanager = pipeline.model, pipeline.datamanager
    rig = model.camera_optimizer.rig
    frames = torch.nonzero(model.camera_optimizer.frame_sensor.cpu() == sensor)[:, 0].tolist()
    if not frames:
        return None
    generator = torch.Generator().manual_seed(seed * 1000 + sensor)
    indices, target = _draw_pixels(datamanager, frames, RAYS_PER_SENSOR, generator)
    base = _render(model, datamanager, indices)
    columns = []
    for (param, i), h in zip(_param_views(rig, sensor), FD_STEPS):
        plus, minus = (_render(model, datamanager, indices, [(param, i, float(param[i]) + sign * h)]) for sign in (1, -1))
        columns.append(((plus - minus) / (2 * h)).reshape(-1).numpy())
    at_prior = _render(model, datamanager, indices, _at_prior(model, sensor))
    residuals = (base - target).reshape(-1).numpy().astype(np.float64)
    clusters = np.repeat(indices[:, 0].numpy(), 3)
    fit = least_squares_sigma(np.stack(columns, axis=1).astype(np.float64), residuals, clusters)
    return SensorUncertainty(sigma=[float(s) for s in fit.sigma], loss_estimate=float(np.mean(residuals**2)),
                             loss_prior=float(((at_prior - target) ** 2).mean()))


REFINEMENT_P = 0.05
"""A refinement is kept when a one-sided paired t-test over the held-back frames (their mean squared colour residual
at the stages' estimate against at the refined one) gives a p-value under this."""


@torch.no_grad()
def refinement_check(pipeline, names: List[str], seed: int) -> Dict[str, dict]:
    """Whether the NeRF's joint refinement of each camera of ``names`` renders its held-back frames (the datamanager's
    ``held_back``: no training ray came from them) significantly better than the estimate it started from (the
    stages', which the calibration optimiser holds as its prior: correction zero).

    Args:
        pipeline: the trained pipeline.
        names: cameras the NeRF refined from a stage's estimate.
        seed: seed of the pixel draws.

    Returns:
        ``{name: {"frames", "loss_refined", "loss_stage", "p_value", "kept"}}`` (losses: mean squared colour residual
        over the held-back pixels); a camera without held-back frames is not kept.
    """
    from scipy.stats import ttest_rel

    model, datamanager = pipeline.model, pipeline.datamanager
    rig = model.camera_optimizer.rig
    held = datamanager.held_back.cpu()
    out = {}
    for name in names:
        sensor = rig.data.sensor_names.index(name)
        frames = torch.nonzero(held & (model.camera_optimizer.frame_sensor.cpu() == sensor))[:, 0].tolist()
        if len(frames) < 2:
            out[name] = {"frames": len(frames), "loss_refined": None, "loss_stage": None, "p_value": None, "kept": False}
            continue
        indices, target = _draw_pixels(datamanager, frames, 4 * RAYS_PER_SENSOR, torch.Generator().manual_seed(seed * 1000 + sensor + 500))
        refined = _render(model, datamanager, indices)
        stage = _render(model, datamanager, indices, _at_prior(model, sensor))
        frame = indices[:, 0].numpy()
        per_frame = [[float(((r[frame == f] - target[frame == f]) ** 2).mean()) for f in frames] for r in (refined, stage)]
        p = float(ttest_rel(per_frame[1], per_frame[0], alternative="greater").pvalue)
        out[name] = {"frames": len(frames), "loss_refined": float(np.mean(per_frame[0])), "loss_stage": float(np.mean(per_frame[1])),
                     "p_value": p, "kept": bool(p < REFINEMENT_P)}
    return out


def trust_entry(sigma: Optional[List[float]], verdict: str, weak: List[str], reason: str):
    """A ``SensorTrust`` from 7 sigmas in m / rad / s (None: not measured)."""
    from moisst_ns.rig.trust import SensorTrust

    if sigma is None:
        return SensorTrust(verdict=verdict, weak=weak, reason=reason)
    return SensorTrust([float(s) for s in sigma[:3]], [float(np.rad2deg(s)) for s in sigma[3:6]], float(sigma[6]), verdict, weak, reason)


def assess_run(pipeline, estimate, stage: Optional[dict], drive: list, moving: Dict[str, str], hit: Dict[str, list],
               seed: Optional[int]):
    """Sigma, weak parameters and verdict of every non-reference sensor; the prior replaces any estimate that the
    held-back loss says is no better than it. A camera of a rig whose LiDARs the LiDAR-first stage placed inherits
    their sigma too (``uncertainty_math.inherited_sigma``; variances added): its registration and the scene rest on
    their map.

    Args:
        pipeline: the trained pipeline.
        estimate: the NeRF's estimate (``Calibration``).
        stage: ``{"sensors": ...}`` of the sensors the NeRF held at a stage's estimate (LiDAR-first: formal sigma
            and weak parameters; camera registration: sigma and held-back costs), or None.
        drive: ``stages.trust.observability.analyse_rig_drive`` results.
        moving: sensors still moving (name -> spread).
        hit: sensors that ran into a bound (name -> bounds).
        seed: seed of the held-back pass's pixel draws; None skips it (no sigma for the NeRF's sensors).

    Returns:
        ``(calibration with trust fields, JSON-ready per-sensor record, lines to print)``.
    """
    from moisst_ns.rig.format import Calibration
    from moisst_ns.rig.trust import PARAMETERS, UNCONSTRAINED, decide_verdict, finite_or_none
    from moisst_ns.stages.trust.observability import TEST_STEPS, UNITS

    start = time.time()
    from moisst_ns.runs.folder import prior_calibration

    rig = pipeline.model.camera_optimizer.rig
    dataset_prior = prior_calibration(rig.data)
    measured = {} if seed is None else {  # every trainable camera (frozen and reference sensors skipped)
        name: sensor_uncertainty(pipeline, i, seed) for i, name in enumerate(rig.data.sensor_names)
        if bool(rig.trainable[i]) and rig.data.sensor_types[i] == "camera"}
    measured = {name: m for name, m in measured.items() if m is not None}
    final = Calibration(estimate.reference_sensor, dict(estimate.T_ref_sensor), dict(estimate.time_offset), {}, estimate.trajectory_T_reference)
    drive_weak = {r.sensor: r.weak for r in drive}
    record, lines = {}, []
    lidars = {n: stage_sigma(e) for n, e in (stage or {"sensors": {}})["sensors"].items() if "observability" in e}
    for i, name in enumerate(rig.data.sensor_names):
        if i == rig.data.reference_index:
            continue
        sigma, loss_est, loss_prior, source = None, None, None, "none"
        entry = stage["sensors"].get(name) if stage is not None else None
        if name in measured:
            m = measured[name]
            sigma, loss_est, loss_prior, source = m.sigma, m.loss_estimate, m.loss_prior, "held-back pixels"
        elif name in lidars:
            sigma, source = lidars[name]
        elif entry is not None:  # a camera held at its camera-registration estimate
            sigma = [np.inf if v is None else float(v) for v in entry["sigma"]]
            loss_est, loss_prior, source = entry["loss_estimate"], entry["loss_prior"], "camera-registration pairs"
        if sigma is not None and name not in lidars and lidars and (entry or {}).get("map_source", "lidar") == "lidar":  # placed against the LiDARs' map
            inherited = [inherited_sigma(estimate.T_ref_sensor[n], estimate.T_ref_sensor[name], s) ** 2 for n, (s, _) in lidars.items()]
            sigma, source = list(np.sqrt(np.asarray(sigma, dtype=np.float64) ** 2 + np.sum(inherited, axis=0))), source + " and the LiDAR map's"
        blind = entry.get("blind") if entry is not None else None
        weak = list(drive_weak.get(name, []))
        if entry is not None:
            weak += entry["weak"] + (blind or [])
            weak = [p for p in weak if p not in (entry.get("shared_instant") or {}).get("taken", [])]  # placed by the shared view
        if sigma is not None:
            weak += [p for p, s, step in zip(PARAMETERS, sigma, TEST_STEPS) if not s <= step]
        weak = [p for p in PARAMETERS if p in weak]
        free = [] if sigma is None else [p for p, s, step in zip(PARAMETERS, sigma, TEST_STEPS) if not s <= UNCONSTRAINED * step]
        check = (entry or {}).get("held_check") or {}
        held = f"{check['note']}: the free parameters absorbed that error" if check.get("note") else None
        if entry is not None and entry.get("held_there") and not blind:  # the camera-registration stage held it (its note),
            held, free = entry["note"], []  # unfitted (sigma inf): the note says why, not the sigma
        verdict, reason = decide_verdict(moving.get(name), loss_est, loss_prior, weak, hit.get(name, []), free, blind, held)
        keep_prior = verdict == "not converged"
        if keep_prior:  # the dataset's prior (rig.json), also for a LiDAR the NeRF started from the LiDAR-first estimate
            final.T_ref_sensor[name] = np.array(dataset_prior.T_ref_sensor[name], dtype=np.float64)
            final.time_offset[name] = float(dataset_prior.time_offset[name])
            lines.append(f"WARNING: {name}: {reason}; calibration.json keeps it")
        # a kept prior's own uncertainty is unknown: the sigma measured belongs to the estimate set aside (summary only)
        final.trust[name] = trust_entry(None if keep_prior else sigma, verdict, weak, reason)
        record[name] = {"sigma": None if sigma is None else [finite_or_none(v) for v in sigma], "sigma_source": source, "loss_estimate": loss_est, "loss_prior": loss_prior,
                        "kept_prior": keep_prior, **final.trust[name].to_json()}
    head = f"{'sensor':<12}" + "".join(f"{'s_' + p:>14}" for p in PARAMETERS) + "  verdict"
    table = ["uncertainty (1 sigma: cm, deg, ms) and verdict per sensor:", head]
    for name, r in record.items():
        cells = ["-" if r["sigma"] is None else "inf" if r["sigma"][k] is None else f"{r['sigma'][k] * UNITS[k][0]:.3g}" for k in range(7)]
        table.append(f"{name:<12}" + "".join(f"{c:>14}" for c in cells) + f"  {r['verdict']}: {r['reason']}")
    wall = time.time() - start
    table.append(f"(sigma from {', '.join(sorted({r['sigma_source'] for r in record.values()}))}; {wall:.1f} s)")
    return final, {"sensors": record, "wall_s": wall}, table + lines
