"""What the NeRF's joint refinement did to each refined camera of ``moisst-calibrate ... --camera-refinement`` runs
(docs/lab/2026-11-27-refinement.md): the stage's errors, the refined estimate's (the run's last logged step, before
the run judges it), the held-back frames' losses and p-value, the parameters beyond the stage's 3 sigma (computed here
from the stage's sigma, so also for runs of code before that rule) and what calibration.json holds.

Usage: .venv/bin/python scripts/lab/refinement_table.py OUT[:STAGES_OUT] [...] (STAGES_OUT: where the stages of a run of
scripts/lab/scene_from_cached_stages.py were loaded from)
"""
import json
import sys
from pathlib import Path

import numpy as np
import roma
import torch

from moisst_ns.rig.trust import PARAMETERS, parameter_difference
from moisst_ns.runs.history import find_history, read_history, still_moving


def errors(e: dict) -> str:
    return f"{e['translation_cm']:.2f} / {e['rotation_deg']:.3f} / {e['time_ms']:.2f}"


for arg in sys.argv[1:]:
    out, stages = (Path(a) for a in (arg.split(":") + [arg])[:2])
    stage = json.loads((stages / "camera_registration" / "camera_registration.json").read_text())["sensors"]
    summary = json.loads((out / "summary.json").read_text())
    history, moving = read_history(find_history(out)), still_moving(find_history(out))
    for name, check in summary.get("refinement", {}).items():
        h = {k: v[-1] for k, v in history[name].items()}
        pose = np.eye(4)
        pose[:3, :3] = roma.euler_to_rotmat("XYZ", torch.tensor([h["roll"], h["pitch"], h["yaw"]]), degrees=True).numpy()
        pose[:3, 3] = [h["x"], h["y"], h["z"]]
        change = parameter_difference(np.asarray(stage[name]["T_ref_sensor"]), stage[name]["time_offset"], pose, h["delta_ms"] / 1000)
        beyond = [p for p, d, s in zip(PARAMETERS, change, stage[name]["sigma"]) if s is not None and abs(d) > 3 * s]
        refined = {"translation_cm": h["err_translation_cm"], "rotation_deg": h["err_rotation_deg"], "time_ms": h["err_time_ms"]}
        print(f"| {out.name} | {name} | {errors(stage[name]['errors_after'])} | {errors(refined)} | "
              f"{check['loss_refined']:.5g} / {check['loss_stage']:.5g}, p = {check['p_value']:.3g} | {', '.join(beyond) or '-'} | "
              f"{moving.get(name, 'settled')} | "
              f"{'refined' if check['kept'] else 'stage'}: {errors(summary['errors_final'][name])} |")
