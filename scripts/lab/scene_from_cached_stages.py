"""``moisst-calibrate`` with the stages loaded from an earlier run's OUT (its ``lidar_first/`` and
``camera_registration/``) instead of run again: experiments on the scene only (docs/lab/2026-11-23-metric-scene.md,
2026-11-26 entry).

Usage: .venv/bin/python scripts/lab/scene_from_cached_stages.py STAGES_OUT DATASET --output-dir OUT [moisst-calibrate options]
"""
import sys
from pathlib import Path

import moisst_ns.stage_run as stage_run
from moisst_ns.cli.calibrate import main

cached, stages = stage_run._cached, Path(sys.argv.pop(1))
stage_run._cached = lambda name, folders: cached(name, (stages,))
main()
