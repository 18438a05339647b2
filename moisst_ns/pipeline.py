"""``MoisstPipeline``: nerfstudio's ``VanillaPipeline`` with MOISST's calibration stages before the NeRF and its checks
after it; the one code path of ``ns-train moisst*`` and ``moisst-calibrate`` (``moisst_ns.calibrate``).

Training, before step 0: the LiDAR-first stage and the camera registration into ``output_dir`` (a resumed run loads
them), and the ``CalibrationOptimizer`` starts from their estimate (``moisst_ns.stage_run``); config.yml is saved again
with it, so a run loaded for inference (``ns-viewer``, ``ns-export``, ``ns-eval``) redoes nothing. After the last step
(``TrainingCallbackLocation.AFTER_TRAIN``): ``calibration.json`` with sigma and verdicts (``uncertainty.assess_run``),
``summary.json`` and ``report/`` into ``output_dir``: the run folder under ``ns-train``, ``OUT`` of ``moisst-calibrate``.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional, Type

import torch
import tyro
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.engine.trainer import Trainer
from nerfstudio.pipelines.base_pipeline import VanillaPipeline, VanillaPipelineConfig

from moisst_ns.runs.history import HISTORY_FILE, append_history, format_error_table, stage_history_rows, still_moving
from moisst_ns.runs.verdict import sensor_verdicts, trust_lines
from moisst_ns.stage_run import CalibrationSwitches, StageRun, prepare_stages


@dataclass
class MoisstPipelineConfig(VanillaPipelineConfig, CalibrationSwitches):
    """``VanillaPipeline`` with the calibration stages before the NeRF and calibration.json after it."""

    _target: Type = field(default_factory=lambda: MoisstPipeline)
    """target class to instantiate"""
    output_dir: Optional[Path] = None
    """Where the stages' folders, calibration.json, summary.json and report/ go; the run folder when omitted."""
    run_dir: tyro.conf.Suppress[Optional[Path]] = None
    """The run folder (set by ``MoisstTrainer``)."""
    seed: tyro.conf.Suppress[int] = 42
    """Seed of the stages and of the held-back pixels: ``--machine.seed`` (set by ``MoisstTrainer``)."""
    resume_from: tyro.conf.Suppress[Optional[Path]] = None
    """Folder of the run a resumed one continues (``--load-dir``, set by ``MoisstTrainer``): stages cached in
    ``output_dir``, there or in the ``moisst-calibrate`` OUT above it are loaded instead of run again."""


class MoisstPipeline(VanillaPipeline):
    """``VanillaPipeline`` that calibrates the rig with the stages, then the NeRF, then checks the result."""

    config: MoisstPipelineConfig

    def __init__(self, config: MoisstPipelineConfig, device: str, test_mode: Literal["test", "val", "inference"] = "val",
                 world_size: int = 1, local_rank: int = 0, grad_scaler=None):
        run = None
        if test_mode == "val":  # training: the stages run (or load) before the datamanager and the model exist
            run = prepare_stages(config, Path(config.output_dir or config.run_dir or "."), config.seed, config.resume_from)
        super().__init__(config, device, test_mode, world_size, local_rank, grad_scaler)
        self.stage_run: Optional[StageRun] = run
        if test_mode != "val":  # loaded: training rays (``ns-export pointcloud``) at the calibrated poses, as in training
            self.datamanager.next_train = _calibrated(self.datamanager.next_train, self.model.camera_optimizer.apply_to_raybundle)

    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes):
        trainer, run = training_callback_attributes.trainer, self.stage_run
        if run is None or trainer is None:
            return super().get_training_callbacks(training_callback_attributes)
        if run.all_held:
            trainer.config.max_num_iterations = self.config.scene_steps or trainer.config.max_num_iterations
        if not run.resumed:  # the history opens with the stages' iterations
            history = Path(trainer.base_dir) / HISTORY_FILE
            history.unlink(missing_ok=True)
            for step, rows in stage_history_rows({"sensors": run.held}, run.truth):
                append_history(history, step, rows)
        callbacks = super().get_training_callbacks(training_callback_attributes)  # the model rescales its schedules
        trainer.config.save_config()  # with the stages' results: a loaded run redoes nothing
        callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN], self.finish, args=[trainer]))
        self._started = time.time()
        return callbacks

    def judge_refinement(self, moving: dict) -> dict:
        """Keep the NeRF's refinement of a registered camera only when it renders the camera's held-back frames
        significantly better than the stage's estimate, stays within 3 sigma of the stage's estimate on every parameter
        (the map's evidence: the held-back frames alone preferred refinements that ran 19-42 cm off, the scene having
        followed them) and has settled; otherwise the camera goes back to the stage's estimate (the optimiser's prior)
        and counts as held there (``run.frozen``; removed from ``moving``)."""
        from moisst_ns.rig.trust import PARAMETERS, parameter_difference
        from moisst_ns.uncertainty import refinement_check

        run, rig = self.stage_run, self.model.camera_optimizer.rig
        checks = refinement_check(self, list(run.refined), run.seed)
        for name, check in checks.items():
            i = rig.data.sensor_names.index(name)
            with torch.no_grad():
                change = parameter_difference(rig.prior_extrinsics[i].cpu().numpy(), float(rig.prior_time_offsets[i]),
                                              rig.extrinsics()[i].cpu().numpy(), float(rig.time_offsets()[i]))
            sigma = run.held[name]["sigma"]
            check["beyond_3_sigma"] = [p for p, d, s in zip(PARAMETERS, change, sigma) if s is not None and abs(d) > 3 * s]
            check["still_moving"] = name in moving
            check["kept"] = check["kept"] and not check["beyond_3_sigma"] and not check["still_moving"]
            if not check["kept"]:
                with torch.no_grad():
                    rig.translation[i], rig.rotvec[i], rig.time_offset[i], rig.trainable[i] = 0.0, 0.0, 0.0, False
                run.frozen, _ = run.frozen + (name,), moving.pop(name, None)
            losses = "no held-back frames" if check["p_value"] is None else \
                f"held-back loss {check['loss_refined']:.5g} refined vs {check['loss_stage']:.5g} at the stage's estimate, p = {check['p_value']:.3g}"
            beyond = f", beyond the stage's 3 sigma on {', '.join(check['beyond_3_sigma'])}" if check["beyond_3_sigma"] else ""
            print(f"refinement: {name}: {losses}{beyond}{', still moving' if check['still_moving'] else ''}: "
                  f"{'kept' if check['kept'] else 'the stage estimate is kept'}")
        return checks

    def finish(self, trainer, step: int) -> None:
        """After the last step: ``calibration.json`` (the prior kept where the held-back loss says the estimate is no
        better), ``summary.json``, the report and the verdicts, into ``run.out``."""
        from moisst_ns.rig.calibration import calibration_report_errors
        from moisst_ns.stages.trust.observability import drive_json
        from moisst_ns.uncertainty import assess_run

        run, wall = self.stage_run, time.time() - self._started
        out, truth, rig = run.out, run.truth, run.rig
        optimizer = self.model.camera_optimizer
        steps = trainer.config.max_num_iterations
        summary = {"method": trainer.config.method_name, "iterations": steps, "wall_time_s": wall, "seed": run.seed}
        # a sensor the NeRF held never moved in it: its convergence is its stage's (whose iterations open the history)
        moving = {n: s for n, s in still_moving(Path(trainer.base_dir) / HISTORY_FILE).items() if n not in run.frozen}
        if run.refined:
            summary["refinement"] = self.judge_refinement(moving)
            if not all(c["kept"] for c in summary["refinement"].values()):
                trainer.save_checkpoint(step)  # a loaded run holds the stage's estimate of the cameras set back
        estimate = optimizer.rig.estimate()
        estimate.write(out / "calibration.json")
        if run.lidar is not None:
            summary["lidar_first"] = {n: {k: e[k] for k in ("wall_s", "weak", "change_from_prior") + (("errors_after",) if truth else ())}
                                      for n, e in run.lidar["sensors"].items()}
        print(f"\nwrote {out / 'calibration.json'}  ({steps} steps, {wall:.0f} s)")
        if truth is not None:
            skip = {truth.reference_sensor}
            before = {k: v for k, v in calibration_report_errors(run.prior, truth).items() if k not in skip}
            after = {k: v for k, v in calibration_report_errors(estimate, truth).items() if k not in skip}
            print(format_error_table("errors of the priors (before):", before))
            print(format_error_table("errors after calibration:", after))
            summary["errors_before"], summary["errors_after"] = before, after
        bounds = optimizer.config
        for i, name in enumerate(optimizer.rig.data.sensor_names):
            hit = []
            if bounds.max_time_offset > 0 and abs(float(optimizer.rig.time_offset[i])) >= 0.999 * bounds.max_time_offset:
                hit.append(f"time offset (±{bounds.max_time_offset * 1000:.0f} ms)")
            if bounds.max_translation > 0 and float(optimizer.rig.translation[i].abs().max()) >= 0.999 * bounds.max_translation:
                hit.append(f"translation (±{bounds.max_translation} m)")
            if hit:
                print(f"WARNING: {name} ran into its bound on {', '.join(hit)}: a runaway, do not trust its estimate")
                summary.setdefault("hit_bounds", {})[name] = hit
        for name, spread in moving.items():
            print(f"WARNING: {name} is still moving over its last estimates ({spread}); run longer or check the data")
        summary["still_moving"] = moving
        if run.cameras is not None:
            summary["camera_registration"] = {n: {k: e[k] for k in ("wall_s", "kept_prior", "loss_prior", "loss_estimate") + (("errors_after",) if truth else ())}
                                              for n, e in run.cameras["sensors"].items()}
        held = {"sensors": {n: e for n, e in run.held.items() if n in run.frozen}} if run.frozen else None
        final, summary["trust"], lines = assess_run(self, estimate, held, run.drive, moving, summary.get("hit_bounds", {}),
                                                    run.seed if self.config.uncertainty else None)
        summary["drive_observability"] = drive_json(run.drive)
        print("\n".join(lines))
        final.write(out / "calibration.json")
        if truth is not None:
            summary["errors_final"] = {k: v for k, v in calibration_report_errors(final, truth).items() if k != truth.reference_sensor}
        (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
        if self.config.report:
            from moisst_ns.report import write_report

            report = write_report(Path(trainer.base_dir) / "config.yml", out / "report", pipeline=self)
            print(f"diagnostics: {report}")
            verdicts = json.loads((report.parent / "report.json").read_text())["verdicts"]
        else:  # the same flags, without the depth check of the renders
            names = [n for n in optimizer.rig.data.sensor_names if n != rig.reference_sensor]
            lidars = [n for n in names if rig.sensors[n].type == "lidar"]
            verdicts = sensor_verdicts(names, summary, json.loads((out / "calibration.json").read_text()), (), lidars, rig.reference_sensor)
        summary["verdicts"] = verdicts
        (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
        print("\n".join(trust_lines(verdicts)))


def _calibrated(sample, calibrate):
    """``next_train`` with its rays re-posed by ``calibrate`` (the model re-poses them itself only in training)."""

    def next_train(step: int):
        bundle, batch = sample(step)
        calibrate(bundle)
        return bundle, batch

    return next_train


class MoisstTrainer(Trainer):
    """nerfstudio's ``Trainer`` that tells a ``MoisstPipelineConfig``, before the pipeline is set up, its run folder,
    the seed and, when resuming (``--load-dir`` / ``--load-checkpoint``), the run it continues."""

    def setup(self, test_mode: Literal["test", "val", "inference"] = "val") -> None:
        pipeline = self.config.pipeline
        if isinstance(pipeline, MoisstPipelineConfig):
            load = self.config.load_dir or (self.config.load_checkpoint.parent if self.config.load_checkpoint else None)
            pipeline.run_dir, pipeline.seed = Path(self.base_dir), self.config.machine.seed
            pipeline.resume_from = Path(load).parent if load else None
        super().setup(test_mode)
