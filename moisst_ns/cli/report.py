"""``moisst-report RUN``: diagnostics of a MOISST run (``moisst_ns.report.write_report``)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Optional

import tyro

from moisst_ns.cli.common import fail
from moisst_ns.quiet import quiet_third_party
from moisst_ns.rig.format import RigFormatError
from moisst_ns.runs import RunError
from moisst_ns.runs.folder import resolve_config_path


@dataclass
class ReportConfig:
    """Diagnostics of a MOISST run: LiDAR on images (prior vs calibrated), renders, convergence plots, report.md."""

    run: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="RUN_DIR_OR_CONFIG")]
    """The run folder (OUT/<method>/run) or its config.yml."""
    output_dir: Annotated[Optional[Path], tyro.conf.arg(metavar="DIR")] = None
    """Where the report goes (created); RUN/report when omitted. Never inside the dataset folder."""
    frames_per_camera: int = 3
    """Camera frames per camera for the prior / calibrated LiDAR overlays (spread over the sequence)."""
    render: bool = True
    """Render one frame per camera with the model at its calibrated pose (--no-render skips it)."""
    render_width: int = 160
    """Width of those renders, pixels (never upscaled; keeps the render cheap on CPU)."""
    verbose: bool = False
    """Show every third-party warning (known-harmless ones are hidden by default: ``moisst_ns.quiet``)."""


def main() -> None:
    """Console script ``moisst-report``."""
    cfg = tyro.cli(ReportConfig)
    quiet_third_party(cfg.verbose)
    from moisst_ns.report import write_report  # numpy/jaxtyping/nerfstudio: after the command line parsed

    try:
        config_path = resolve_config_path(cfg.run)
        out = cfg.output_dir if cfg.output_dir is not None else config_path.parent / "report"
        report = write_report(config_path, out, frames_per_camera=cfg.frames_per_camera, render=cfg.render, render_width=cfg.render_width)
    except (RunError, RigFormatError) as err:
        fail("moisst-report", err)
    print(f"wrote {report}")

