"""``moisst-figures``: record a measured run into docs/figures.json and render README's "Where it stands" table.

* ``moisst-figures --record OUT --label "after (...)" [--command "..."] [--wall "9 min 45 s"] [--peak-rss "1.7 GB"]``:
  adds (or replaces, same label) the errors of the moisst-calibrate run in OUT (``OUT/summary.json``), then
  rewrites the README block.
* ``moisst-figures``: only rewrites the README block from docs/figures.json.
* ``moisst-figures --check``: exits 1 when README.md is not what docs/figures.json renders (writes nothing).

Errors are one line, ``moisst-figures: error: ...``, exit status 2.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Optional

import tyro

from moisst_ns.cli.common import fail
from moisst_ns.runs import RunError
from moisst_ns.runs.figures import load_figures, record_run, run_from_output, update_readme

PROG = "moisst-figures"
ROOT = Path(__file__).resolve().parents[2]


@dataclass
class FiguresConfig:
    """Record a measured run into docs/figures.json and render README's "Where it stands" table from it."""

    record: Annotated[Optional[Path], tyro.conf.arg(metavar="OUT")] = None
    """A finished moisst-calibrate output folder (its summary.json, from a dataset with ground truth) to record."""
    label: Optional[str] = None
    """Column label of the recorded run (a run with the same label is replaced). Required with --record."""
    command: Optional[str] = None
    """The command that produced OUT, as the README should show it."""
    wall: Optional[str] = None
    """Wall time of that command as measured (e.g. "9 min 45 s" from /usr/bin/time -v)."""
    peak_rss: Optional[str] = None
    """Peak memory of that command as measured (e.g. "1.7 GB")."""
    note: Optional[str] = None
    """Anything else the reader should know about this run."""
    figures: Path = ROOT / "docs" / "figures.json"
    """The measured figures."""
    readme: Path = ROOT / "README.md"
    """The README whose figures block is rewritten."""
    check: bool = False
    """Write nothing; exit 1 when the README's block differs from what the figures render."""


def _commit() -> Optional[str]:
    try:
        out = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return out.stdout.strip() or None


def main() -> None:
    """Console script ``moisst-figures``."""
    cfg = tyro.cli(FiguresConfig, prog=PROG)
    try:
        figures = load_figures(cfg.figures)
        if cfg.record is not None:
            if not cfg.label:
                raise RunError("--record needs --label (the table's column)")
            source = {"command": cfg.command, "measured": datetime.date.today().isoformat(), "commit": _commit(),
                      "machine": f"{platform.machine()}, {len(os.sched_getaffinity(0))} cores",
                      "wall": cfg.wall, "peak_rss": cfg.peak_rss, "note": cfg.note}
            figures = record_run(figures, run_from_output(cfg.record, cfg.label, {k: v for k, v in source.items() if v}))
        if not cfg.readme.is_file():
            raise RunError(f"{cfg.readme}: (file): not found")
        text = cfg.readme.read_text()
        rendered = update_readme(text, figures, str(cfg.readme))
    except RunError as err:
        fail(PROG, err)
    if cfg.check:
        if rendered != text:
            print(f"{PROG}: {cfg.readme} differs from what {cfg.figures} renders: run {PROG}", file=sys.stderr)
            raise SystemExit(1)
        print(f"{cfg.readme} matches {cfg.figures}")
        return
    if cfg.record is not None:
        cfg.figures.write_text(json.dumps(figures, indent=1) + "\n")
        print(f"wrote {cfg.figures}")
    if rendered != text:
        cfg.readme.write_text(rendered)
        print(f"wrote {cfg.readme}")
    else:
        print(f"{cfg.readme} already up to date")

