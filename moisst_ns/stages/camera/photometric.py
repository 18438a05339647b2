"""The photometric problem of the camera-registration stage: a camera's pixels as a function of its 7 corrections
(eq. 1, 2, 12) with their Jacobian, pairs of observations of map points, and their residuals. The method is described
in ``moisst_ns.stages.camera.camera_registration``'s docstring. No nerfstudio import."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional, Sequence, Tuple

import numpy as np
import torch
from jaxtyping import Float, Int

from moisst_ns.rig.format import Calibration, Rig
from moisst_ns.rig.geometry import ReferenceTrajectory, calibrated_extrinsic, row_time, row_times, sensor_pose
from moisst_ns.stages.lidar.lidar_geometry import right_jacobian
from moisst_ns.stages.camera.lidar_map import CameraStageError, ImageStack, PinholeModel, bilinear, load_pyramid, project, visible, world_to_camera


@dataclass
class CameraFrames:
    """One camera's frames: own-clock stamps (seconds since the trajectory's ``t0``) and the image pyramid."""

    sensor: str
    stamps: Float[np.ndarray, "frames"]
    levels: Dict[int, ImageStack]
    model: PinholeModel
    """Full-resolution intrinsics."""
    readout: float = 0.0
    """Rolling-shutter readout time, seconds (rig.json's ``readout_time``; 0: global shutter)."""

    @classmethod
    def of(cls, rig: Rig, sensor: str, factors: Sequence[int]) -> "CameraFrames":
        """A camera's frames sorted by stamp, as grey pyramids (``factors``)."""
        frames = sorted(rig.frames_of(sensor), key=lambda f: f.timestamp)
        if len(frames) < 2:
            raise CameraStageError(f"{rig.root / 'rig.json'}: frames: camera {sensor} has {len(frames)} frame(s); at least 2 are needed")
        stamps = np.array([f.timestamp for f in frames]) - float(rig.trajectory_stamps[0])
        return cls(sensor, stamps, load_pyramid(rig, sensor, [f.file_path for f in frames], factors),
                   PinholeModel.of(rig.sensors[sensor].intrinsics), float(rig.sensors[sensor].readout_time))


PIXEL_CHUNK = 65536
"""Points per chunk of ``CameraModel.pixels``."""


class CameraModel:
    """``theta -> pixel`` of map points in a camera's frames (eq. 1, 2, 12), and its Jacobian (forward mode; analytic
    with a rolling shutter, ``_rolling``).

    ``theta``: the 7 corrections (rotation vector, translation, time offset), or 8 with a readout-time correction
    (seconds, added to ``readout``). With a readout (or 8 corrections) a point is projected from the pose at its row's
    time (``geometry.row_times``, ``row_time``), and the Jacobian follows the row: with ``u = f(theta, tau)`` and
    ``tau = g(v, theta)`` at the fixed point, ``dtau/dtheta = (g_v df_v/dtheta + dg/dtheta) / (1 - g_v df_v/dtau)``
    (implicit differentiation) and ``du/dtheta = df/dtheta + df/dtau dtau/dtheta``."""

    def __init__(self, traj: ReferenceTrajectory, prior: Float[np.ndarray, "4 4"], prior_offset: float,
                 stamps: Float[np.ndarray, "frames"], readout: float = 0.0, full: Optional[PinholeModel] = None):
        """``readout``: rolling-shutter readout time, seconds; ``full``: the full-resolution intrinsics (required with a
        readout: rows are timed in the stored image's pixels)."""
        self.traj, self.prior_offset = traj, prior_offset
        self.prior = torch.from_numpy(np.asarray(prior, dtype=np.float64))
        self.stamps = torch.from_numpy(np.asarray(stamps, dtype=np.float64))
        self.readout, self.full = float(readout), full
        self._ends: Dict[tuple, list] = {}

    def poses(self, theta: Float[torch.Tensor, "7"]) -> Float[torch.Tensor, "frames 4 4"]:
        """``world_T_c`` of every frame at its stamp: ``T_r(s_k + delta_prior + d) @ ref_T_c(w, v)``."""
        ext = calibrated_extrinsic(self.prior, theta[:3], theta[3:6])
        return sensor_pose(self.traj(self.stamps + self.prior_offset + theta[6]), ext)

    def _seen(self, theta: torch.Tensor, points: torch.Tensor, frame: torch.Tensor, tau: torch.Tensor):
        """Each point from its frame's pose ``tau`` seconds after the stamp: ``(t, world_T_ref, q = ref_T_world x,
        camera-frame point, ref_T_c)`` (reference-clock time, eq. 1-2 and 12 per point)."""
        ext = calibrated_extrinsic(self.prior, theta[:3], theta[3:6])
        t = self.stamps[frame] + self.prior_offset + theta[6] + tau
        ref = self.traj(t)
        q = world_to_camera(ref, points)
        return t, ref, q, (q - ext[:3, 3]) @ ext[:3, :3], ext

    def camera_points(self, theta: Float[np.ndarray, "p"], points: Float[np.ndarray, "num 3"], frame: Int[np.ndarray, "num"]) -> Float[np.ndarray, "num 3"]:
        """``points`` (world, metres) in the camera frame of the pose that sees each (its row's with a readout)."""
        th = torch.from_numpy(np.asarray(theta, dtype=np.float64))
        pts, idx = torch.from_numpy(np.asarray(points, dtype=np.float64)), torch.from_numpy(np.asarray(frame))
        with torch.no_grad():
            return self._seen(th, pts, idx, self.row_times(th, self.full, pts, idx))[3].numpy()

    def row_times(self, theta: torch.Tensor, model: PinholeModel, points: torch.Tensor, frame: torch.Tensor) -> torch.Tensor:
        """Each point's capture time after its frame's stamp (seconds; ``geometry.row_times``), projected at ``model``'s
        level (its rows are timed in the full-resolution image's). The iterations move each point along the chord
        between its frame's poses at the first and the last row (two trajectory evaluations per frame, none per point):
        within a readout the chord is the pose to a fraction of a millimetre (constant velocity within a trajectory
        segment), and the caller projects exactly from the pose at the time found."""
        full = self.full if self.full is not None else model
        readout = float(self.readout + (theta[7] if len(theta) > 7 else 0.0))
        if readout == 0.0:
            return torch.zeros(len(points), dtype=torch.float64)
        key = (theta.numpy().tobytes(), readout)
        if key not in self._ends:  # the frames' poses at their first and last rows, kept for the last theta
            ext, t = calibrated_extrinsic(self.prior, theta[:3], theta[3:6]), self.stamps + self.prior_offset + theta[6]
            self._ends = {key: [sensor_pose(self.traj(t + h), ext) for h in (-readout / 2, readout / 2)]}
        first, last = (world_to_camera(pose[frame], points) for pose in self._ends[key])

        def rows(tau):
            cam = first + (torch.as_tensor(tau, dtype=torch.float64).expand(len(points)) / readout + 0.5)[:, None] * (last - first)
            return full.cy + (project(model, cam)[0][:, 1] - model.cy) * (full.fy / model.fy)

        return row_times(rows, readout, full.height)

    def _rolling(self, theta: torch.Tensor, model: PinholeModel, points: torch.Tensor, frame: torch.Tensor, jacobian: bool):
        """``(pixels, depths, d pixel / d theta or None)`` of one chunk with the rows at their own times. The derivative
        of the camera-frame point ``c = R_E^T (q - t_E)``, ``q = R_r^T (x - p_r)`` (eq. 1-2, 12 at the row's time ``t``):
        ``dc/dt = -R_E^T (omega x q + R_r^T velocity)`` (the segment's rates, ``ReferenceTrajectory.rates``),
        ``dc/dw = [c]x J_r(w)``, ``dc/dv = -R_E^T``; times the projection's (forward mode, 3 tangents)."""
        full = self.full if self.full is not None else model
        scale = full.fy / model.fy  # full-resolution rows per row of ``model``'s level
        readout = self.readout + (theta[7] if len(theta) > 7 else 0.0)
        t, ref, q, cam, ext = self._seen(theta, points, frame, self.row_times(theta, model, points, frame))
        uv, depth = project(model, cam)
        if not jacobian:
            return uv, depth, None
        omega, velocity = self.traj.rates(t)
        d_time = -(torch.cross(omega, q, dim=-1) + torch.einsum("nji,nj->ni", ref[:, :3, :3], velocity)) @ ext[:3, :3]
        d_rot = torch.cross(cam[:, :, None].expand(-1, -1, 3), torch.from_numpy(right_jacobian(theta[:3].numpy()))[None].expand(len(cam), 3, 3), dim=1)
        d_cam = torch.cat([d_rot, -ext[:3, :3].T.expand(len(cam), 3, 3), d_time[:, :, None]], dim=2)  # (n, 3, 7)
        d_pixel = torch.stack([torch.func.jvp(lambda c: project(model, c)[0], (cam,), (torch.zeros_like(cam).index_fill_(1, torch.tensor([k]), 1.0),))[1]
                               for k in range(3)], dim=-1)  # (n, 2, 3)
        f_theta = torch.cat([d_pixel @ d_cam, torch.zeros(len(cam), 2, len(theta) - 7, dtype=cam.dtype)], dim=2)
        f_tau = f_theta[..., 6]
        g_v = readout * scale / max(full.height - 1, 1)
        g_theta = torch.zeros_like(f_theta[:, 1])
        if len(theta) > 7:
            g_theta[:, 7] = row_time(full.cy + (uv[:, 1] - model.cy) * scale, 1.0, full.height)
        dtau = (g_v * f_theta[:, 1] + g_theta) / (1.0 - g_v * f_tau[:, 1:2])
        return uv, depth, f_theta + f_tau[..., None] * dtau[:, None, :]

    def project(self, theta: Float[np.ndarray, "p"], model: PinholeModel, points: Float[np.ndarray, "num 3"],
                frame: Int[np.ndarray, "num"]) -> Tuple[Float[np.ndarray, "num 2"], Float[np.ndarray, "num"]]:
        """Pixels and depths (metres) of ``points`` in frames ``frame`` at ``theta``, each from its row's pose."""
        th = torch.from_numpy(np.asarray(theta, dtype=np.float64))
        pts, idx = torch.from_numpy(np.asarray(points, dtype=np.float64)), torch.from_numpy(np.asarray(frame))
        with torch.no_grad():
            if self.readout == 0.0 and len(th) == 7:
                return tuple(a.numpy() for a in project(model, world_to_camera(self.poses(th)[idx], pts)))
            uv, depth, _ = self._rolling(th, model, pts, idx, False)
        return uv.numpy(), depth.numpy()

    def pixels(self, theta: Float[np.ndarray, "p"], model: PinholeModel, points: Float[np.ndarray, "num 3"],
               frame: Int[np.ndarray, "num"], jacobian: bool) -> Tuple[Float[np.ndarray, "num 2"], Optional[Float[np.ndarray, "num 2 p"]]]:
        """Pixels of ``points`` in frames ``frame`` at correction ``theta`` (and ``d pixel / d theta``), in chunks of
        ``PIXEL_CHUNK`` points (forward mode carries 7 tangents of every intermediate: unchunked, the finest level's
        half a million pairs took the stage's peak memory from 1.2 to 2.0 GB)."""
        th = torch.from_numpy(np.asarray(theta, dtype=np.float64))
        rolling = self.readout != 0.0 or len(th) > 7
        values, jacobians = [], []
        with torch.no_grad():
            poses = self.poses(th) if not jacobian and not rolling else None
            for lo in range(0, len(points), PIXEL_CHUNK):
                pts, idx = torch.from_numpy(points[lo:lo + PIXEL_CHUNK]), torch.from_numpy(frame[lo:lo + PIXEL_CHUNK])
                if rolling:
                    uv_chunk, _, jac_chunk = self._rolling(th, model, pts, idx, jacobian)
                    values.append(uv_chunk.numpy())
                    if jacobian:
                        jacobians.append(jac_chunk.numpy())
                    continue

                def uv(t):
                    return project(model, world_to_camera((self.poses(t) if poses is None else poses)[idx], pts))[0]

                values.append(uv(th).numpy())
                if jacobian:
                    jacobians.append(torch.func.jacfwd(uv)(th).numpy())
        if not values:
            return np.zeros((0, 2)), (np.zeros((0, 2, len(th))) if jacobian else None)
        return np.concatenate(values), (np.concatenate(jacobians) if jacobian else None)


@dataclass
class PairSet:
    """Pairs of observations of map points: camera ``c``'s frame ``frame_a`` against a partner observation."""

    points: Float[np.ndarray, "rows 3"]
    frame_a: Int[np.ndarray, "rows"]
    own: np.ndarray
    """(rows,) bool: the partner is another frame of the same camera (else a reference-camera frame)."""
    frame_b: Int[np.ndarray, "rows"]
    """The partner frame (the camera's own frame index, or the reference camera's frame index)."""
    value_b: Float[np.ndarray, "rows"]
    """Grey level of reference partners (fixed; 0 for own partners)."""
    shared: float = 0.0
    """Share of the sampled points whose reference partner is the reference frame nearest in time
    (``CameraRegistrationConfig.shared_view_share``)."""


class Registration:
    """The photometric problem of one camera: pair selection, residuals, Jacobian and solve."""

    def __init__(self, traj: ReferenceTrajectory, world: np.ndarray, camera: CameraFrames, reference: Optional[CameraFrames],
                 prior: Calibration, config):
        """``reference``: the reference camera's frames (None when the reference sensor is a LiDAR: own pairs only);
        ``config``: the stage's ``CameraRegistrationConfig``."""
        self.world, self.camera, self.reference, self.config = world, camera, reference, config
        name = camera.sensor
        self.model = CameraModel(traj, np.asarray(prior.T_ref_sensor[name]), float(prior.time_offset[name]), camera.stamps, camera.readout, camera.model)
        if reference is not None:
            ref_name = reference.sensor
            self.ref_model = CameraModel(traj, np.asarray(prior.T_ref_sensor[ref_name]), float(prior.time_offset[ref_name]), reference.stamps,
                                         reference.readout, reference.model)
            ref_poses = self.ref_model.poses(torch.zeros(7, dtype=torch.float64)).numpy()
            self.ref_visible = np.stack([self._visible(ref_poses[j], reference.model) for j in range(len(reference.stamps))])
        self.rng = np.random.default_rng(config.seed)

    # -- visibility -------------------------------------------------------------------------------------------
    def _visible(self, pose: np.ndarray, model: PinholeModel) -> np.ndarray:
        """(map points,) bool: which map points a frame at ``pose`` sees (z-buffer)."""
        near = np.linalg.norm(self.world - pose[:3, 3], axis=1) < self.config.max_depth
        index = np.flatnonzero(near)
        cam = (self.world[index] - pose[:3, 3]) @ pose[:3, :3]
        uv, z = project(model, torch.from_numpy(cam))
        uv, z = uv.numpy(), z.numpy()
        ok = visible(uv, z, model, self.config.max_depth)
        mask = np.zeros(len(self.world), dtype=bool)
        mask[index[ok]] = True
        return mask

    def pairs(self, theta: np.ndarray, factor: int, per_frame: int) -> PairSet:
        """Sample map points visible in every frame of the camera at ``theta`` and give each its partners."""
        cam, ref, c = self.camera, self.reference, self.config
        poses = self.model.poses(torch.from_numpy(theta)).numpy()
        seen_by = np.stack([self._visible(poses[k], cam.model) for k in range(len(cam.stamps))])
        travelled = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1))]
        stack = cam.levels[factor]
        baseline = c.fine_baseline if c.fine_baseline > 0 and factor == min(cam.levels) else c.own_baseline
        rows = []  # (map points, frame_a, own, frame_b, value_b) of each block of pairs
        drawn = []  # per frame: its sampled points and which of them found a reference partner
        for k in range(len(cam.stamps)):
            candidates = np.flatnonzero(seen_by[k])
            if len(candidates) == 0:
                continue
            uv, _ = self.model.pixels(theta, stack.model, self.world[candidates], np.full(len(candidates), k), jacobian=False)
            _, grad, ok = bilinear(stack, np.full(len(candidates), k), uv)
            weight = np.linalg.norm(grad, axis=1) * ok
            if weight.sum() <= 0:
                continue
            take = self.rng.choice(len(candidates), size=min(per_frame, int((weight > 0).sum())), replace=False, p=weight / weight.sum())
            chosen = candidates[take]
            # reference partner: the reference frame nearest in time that sees the point
            pending, at_once = np.full(len(chosen), ref is not None), 0
            for rank, j in enumerate(np.argsort(np.abs(ref.stamps - cam.stamps[k])) if ref is not None else []):
                if not pending.any():
                    break
                seen = self.ref_visible[j, chosen] & pending
                if not seen.any():
                    continue
                ref_stack = ref.levels[factor]
                uvb, _ = self.ref_model.pixels(np.zeros(7), ref_stack.model, self.world[chosen[seen]], np.full(int(seen.sum()), j), False)
                value, _, okb = bilinear(ref_stack, np.full(int(seen.sum()), j), uvb)
                hit = np.flatnonzero(seen)[okb]
                rows.append((chosen[hit], np.full(len(hit), k), np.zeros(len(hit), bool), np.full(len(hit), j), value[okb]))
                pending[hit] = False
                at_once += len(hit) if rank == 0 else 0
            drawn.append((k, chosen, (ref is not None) & ~pending, at_once))
        # own partner: the nearest frame at least ``baseline`` of driving away (both sides when possible); none for a
        # point with a reference partner when most points have one at the same instant (``shared_view_share``)
        share = sum(d[3] for d in drawn) / max(1, sum(len(d[1]) for d in drawn))
        for k, chosen, paired, _ in drawn:
            unpaired = ~paired if share >= c.shared_view_share else np.ones(len(chosen), dtype=bool)
            for partner in (self._partner(travelled, k, +1, baseline), self._partner(travelled, k, -1, baseline)):
                if partner is None:
                    continue
                seen = seen_by[partner, chosen] & unpaired
                n = int(seen.sum())
                rows.append((chosen[seen], np.full(n, k), np.ones(n, bool), np.full(n, partner), np.zeros(n)))
        if not rows:
            return PairSet(np.zeros((0, 3)), *(np.zeros(0, dtype=t) for t in (np.int64, bool, np.int64, np.float64)))
        points, frame_a, own, frame_b, value_b = (np.concatenate(c) for c in zip(*rows))
        return PairSet(self.world[points], frame_a, own, frame_b, value_b, share)

    def _partner(self, travelled: np.ndarray, k: int, direction: int, baseline: float) -> Optional[int]:
        far = np.flatnonzero(np.abs(travelled - travelled[k]) >= baseline)
        far = far[far > k] if direction > 0 else far[far < k]
        if len(far) == 0:
            return None
        return int(far.min() if direction > 0 else far.max())

    # -- residuals --------------------------------------------------------------------------------------------
    def residuals(self, theta: np.ndarray, pairs: PairSet, factor: int, jacobian: bool):
        """``I_c(u_a) - I_b(u_b)`` per pair (0 where an observation leaves the image: a fit that gains by pushing its
        pairs out of the image runs away and is caught by the bound and cost-ratio tests) and ``d r / d theta``."""
        stack = self.camera.levels[factor]
        uv_a, ju_a = self.model.pixels(theta, stack.model, pairs.points, pairs.frame_a, jacobian)
        value_a, grad_a, ok = bilinear(stack, pairs.frame_a, uv_a)
        value_b = pairs.value_b.copy()
        jac = np.einsum("nc,ncp->np", grad_a, ju_a) if jacobian else None
        own = np.flatnonzero(pairs.own)
        if len(own):
            uv_b, ju_b = self.model.pixels(theta, stack.model, pairs.points[own], pairs.frame_b[own], jacobian)
            vb, grad_b, okb = bilinear(stack, pairs.frame_b[own], uv_b)
            value_b[own] = vb
            ok[own] &= okb
            if jacobian:
                jac[own] -= np.einsum("nc,ncp->np", grad_b, ju_b)
        res = np.where(ok, value_a - value_b, 0.0)
        if jacobian:
            jac[~ok] = 0.0
        return res, jac, ok


def huber_costs(residuals: np.ndarray, scale: float) -> np.ndarray:
    """Huber cost of each residual (``0.5 r^2`` inside ``scale``, linear beyond)."""
    a = np.abs(residuals)
    return np.where(a <= scale, 0.5 * a * a, scale * (a - 0.5 * scale))


def robust_cost(residuals: np.ndarray, scale: float) -> float:
    """Mean Huber cost of residuals (nan for none)."""
    return float(np.mean(huber_costs(residuals, scale))) if len(residuals) else float("nan")
