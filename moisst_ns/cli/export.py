"""``moisst-export --load-config RUN/config.yml --output-dir OUT``: take a calibration run's result home, from its
checkpoint: ``calibration.json``, ``rig.calibrated.json``, ``summary.json`` and ``summary.md`` (what each holds:
``docs/outputs.md``, "Taking the result home"). Nothing is written into the dataset folder. Errors are one line,
``moisst-export: error: ...``, exit status 2.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro

from moisst_ns.cli.common import fail
from moisst_ns.quiet import quiet_third_party
from moisst_ns.runs import RunError
from moisst_ns.runs.folder import (
    build_summary,
    calibrated_rig_json,
    check_output_dir,
    checkpoint_dir,
    dataset_of,
    load_run_config,
    open_run,
    prior_calibration,
    resolve_config_path,
    run_trust,
    summary_markdown,
)


@dataclass
class ExportConfig:
    """Export the calibration of a moisst / moisst-lite run (calibration.json, rig.calibrated.json, summaries)."""

    load_config: Annotated[Path, tyro.conf.arg(metavar="RUN/config.yml")]
    """config.yml of the run (as moisst-calibrate prints it: OUT/<method>/run/config.yml); a run folder holding
    config.yml is accepted too."""
    output_dir: Annotated[Path, tyro.conf.arg(metavar="OUT")]
    """Folder for the exported files (created; must not be a file nor lie inside the dataset folder)."""
    verbose: bool = False
    """Show every third-party warning (known-harmless ones are hidden by default: ``moisst_ns.quiet``)."""


def run_export(cfg: ExportConfig) -> Path:
    """Export a run; returns the output folder. Raises ``RunError`` on bad input (see ``main``)."""
    from moisst_ns.rig.format import RigFormatError, load_calibration

    config_path = resolve_config_path(cfg.load_config)
    if cfg.output_dir.exists() and not cfg.output_dir.is_dir():
        raise RunError(f"{cfg.output_dir}: --output-dir: is a file, not a folder")
    config = load_run_config(config_path)
    checkpoint_dir(config_path)
    check_output_dir(cfg.output_dir, dataset_of(config))
    config, pipeline, step, rig = open_run(config_path)
    calib = pipeline.model.camera_optimizer.rig
    estimate = run_trust(config_path, calib.estimate())
    prior = prior_calibration(calib.data)
    truth_file = rig.root / "ground_truth.json"
    try:
        truth = load_calibration(truth_file) if truth_file.is_file() else None
    except RigFormatError as err:
        raise RunError(str(err)) from None

    out = cfg.output_dir
    out.mkdir(parents=True, exist_ok=True)
    estimate.write(out / "calibration.json")
    comment = (f"moisst-export of {config_path.resolve()} (step {step}): priors replaced by the calibration. Paths are "
               "relative to the dataset folder: use this file next to the dataset's rig.json.")
    (out / "rig.calibrated.json").write_text(json.dumps(calibrated_rig_json(rig, estimate, comment), indent=1) + "\n")
    types = dict(zip(calib.data.sensor_names, calib.data.sensor_types))
    summary = {"run": {"config": str(config_path.resolve()), "step": int(step), "dataset": str(rig.root.resolve()),
                       "method": config.method_name}}
    summary.update(build_summary(estimate, prior, types, truth))
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    (out / "summary.md").write_text(summary_markdown(summary))
    return out


def main() -> None:
    """Console script ``moisst-export``."""
    cfg = tyro.cli(ExportConfig)
    quiet_third_party(cfg.verbose)
    try:
        out = run_export(cfg)
    except RunError as err:
        fail("moisst-export", str(err))
    for name in ("calibration.json", "rig.calibrated.json", "summary.json", "summary.md"):
        print(f"wrote {out / name}")

