"""Opening a run folder (config.yml + checkpoint), the output-folder check, and the run's summaries.

A run folder is what ``moisst-calibrate`` / ``ns-train moisst*`` leave: ``RUN/config.yml``,
``RUN/nerfstudio_models/step-*.ckpt`` and ``RUN/calibration_history.csv``. Errors are ``RunError``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

from moisst_ns.rig.format import Calibration, Rig
from moisst_ns.runs import RunError
from moisst_ns.runs.history import ESTIMATE_COLUMNS


def resolve_config_path(path: Path) -> Path:
    """The config.yml of a run given either the file or its folder ``RUN``; ``RunError`` when there is none."""
    path = Path(path)
    if path.is_dir():
        path = path / "config.yml"
    if not path.is_file():
        raise RunError(f"{path}: config not found (pass the run's config.yml, e.g. OUT/moisst-lite/run/config.yml)")
    return path


def checkpoint_dir(config_path: Path) -> Path:
    """``RUN/nerfstudio_models``, next to the run's config.yml (so a moved or copied run folder still opens);
    ``RunError`` when it is missing or holds no ``step-*.ckpt``."""
    folder = config_path.parent / "nerfstudio_models"
    if not folder.is_dir() or not any(folder.glob("step-*.ckpt")):
        raise RunError(f"{config_path.parent}: no checkpoint ({folder.name}/step-*.ckpt missing); the run saved none or did not finish")
    return folder


def load_run_config(config_path: Path):
    """Read a run's config.yml and check it is a MOISST run (without building anything).

    nerfstudio's config.yml is read with PyYAML's unsafe loader (as ``eval_setup`` does): a run folder is trusted
    input, open only runs you made.

    Args:
        config_path: the run's config.yml.

    Returns:
        The ``TrainerConfig``.

    Raises:
        RunError: unreadable YAML, not a nerfstudio config, or a method other than moisst / moisst-lite.
    """
    import yaml

    from nerfstudio.engine.trainer import TrainerConfig

    from moisst_ns.model import MoisstModel, MoisstModelConfig

    try:
        config = yaml.load(config_path.read_text(), Loader=yaml.Loader)
    except Exception as err:  # yaml errors, missing classes named by tags (ImportError / AttributeError)
        raise RunError(f"{config_path}: not a readable nerfstudio config ({type(err).__name__})") from None
    if not isinstance(config, TrainerConfig):
        raise RunError(f"{config_path}: not a nerfstudio run config (no TrainerConfig)")
    model = getattr(config.pipeline, "model", None)
    target = getattr(model, "_target", None)
    if not isinstance(model, MoisstModelConfig) or not (isinstance(target, type) and issubclass(target, MoisstModel)):
        name = getattr(target, "__name__", type(model).__name__)
        raise RunError(f"{config_path}: method {config.method_name!r} trains {name}, not MoisstModel: not a moisst calibration run")
    return config


def dataset_of(config) -> Path:
    """The dataset folder a run was trained on (``config.pipeline.datamanager.dataparser.data``)."""
    return Path(config.pipeline.datamanager.dataparser.data)


def check_output_dir(output_dir: Path, dataset: Path, create: bool = False) -> None:
    """Refuse (``RunError``) an output folder that is a file or lies inside the dataset folder (datasets are never
    written); ``create``: create the folder once it passed."""
    if output_dir.exists() and not output_dir.is_dir():
        raise RunError(f"{output_dir}: --output-dir: is a file, not a folder")
    out, root = output_dir.resolve(), dataset.resolve()
    if out == root or root in out.parents:
        raise RunError(f"{output_dir}: --output-dir: must not be inside the dataset folder {dataset} (datasets are never written)")
    if create:
        output_dir.mkdir(parents=True, exist_ok=True)


def open_run(config_path: Path) -> Tuple[Any, Any, int, Rig]:
    """Check and load a MOISST run for inference (``eval_setup``, checkpoint read from next to config.yml).

    Args:
        config_path: ``RUN/config.yml`` (or ``RUN``).

    Returns:
        (config, pipeline in eval mode, checkpoint step, the dataset's rig (files not re-checked)).

    Raises:
        RunError: missing config, another method, no checkpoint, missing/bad dataset, no rig calibration.
    """
    from nerfstudio.utils.eval_utils import eval_setup

    from moisst_ns.calibration_optimizer import CalibrationOptimizer
    from moisst_ns.rig.format import RigFormatError, load_rig

    config_path = resolve_config_path(config_path)
    config = load_run_config(config_path)
    models = checkpoint_dir(config_path).resolve()
    try:
        rig = load_rig(dataset_of(config))
    except RigFormatError as err:
        raise RunError(f"dataset of the run: {err}") from None

    def from_run_folder(cfg):
        # An absolute relative_model_dir wins over output_dir/experiment/method/timestamp in get_checkpoint_dir.
        cfg.relative_model_dir = models
        return cfg

    _, pipeline, _, step = eval_setup(config_path, test_mode="inference", update_config_callback=from_run_folder)
    optimizer = getattr(pipeline.model, "camera_optimizer", None)
    if not isinstance(optimizer, CalibrationOptimizer) or optimizer.rig is None:
        raise RunError(f"{config_path}: the model has no rig calibration (camera_optimizer is not a CalibrationOptimizer with a rig)")
    if set(optimizer.rig.data.sensor_names) != set(rig.sensor_names):
        raise RunError(f"{dataset_of(config)}: rig.json's sensors {rig.sensor_names} differ from the run's {optimizer.rig.data.sensor_names}")
    return config, pipeline, step, rig


def prior_calibration(data) -> Calibration:
    """The dataset's priors (rig.json's) of the run's ``RigData``, as a calibration: what "change from the prior" and
    "errors before" mean to a user, also when the NeRF started from other priors (the LiDAR-first stage's estimate)."""
    if getattr(data, "dataset_priors", None) is not None:
        return data.dataset_priors
    names = data.sensor_names
    return Calibration(
        names[data.reference_index],
        {n: np.asarray(data.prior_extrinsics[i], dtype=np.float64) for i, n in enumerate(names)},
        {n: float(data.prior_time_offsets[i]) for i, n in enumerate(names)},
    )


def xyz_rpy_delta(pose: np.ndarray, time_offset: float) -> Dict[str, float]:
    """x, y, z (m), roll, pitch, yaw (deg, ``pose_to_xyz_rpy``) and delta (ms) of one sensor.

    Args:
        pose: ``T_ref_sensor``, 4x4.
        time_offset: delta, seconds.

    Returns:
        ``{x, y, z, roll, pitch, yaw, delta_ms}``.
    """
    import torch

    from moisst_ns.rig.geometry import pose_to_xyz_rpy

    values = pose_to_xyz_rpy(torch.as_tensor(pose, dtype=torch.float64)).numpy()
    out = {k: float(v) + 0.0 for k, v in zip(ESTIMATE_COLUMNS[:6], values)}  # + 0.0: no -0.0 in the tables
    out["delta_ms"] = float(time_offset) * 1000.0 + 0.0
    return out


def change_from_prior(estimate: Dict[str, float], prior: Dict[str, float], est_pose: np.ndarray, prior_pose: np.ndarray) -> Dict[str, float]:
    """Estimate minus prior of every quantity, plus the translation and geodesic rotation distances.

    Angle differences are wrapped into [-180, 180) degrees.

    Args:
        estimate: ``xyz_rpy_delta`` of the estimate.
        prior: ``xyz_rpy_delta`` of the prior.
        est_pose: estimated ``T_ref_sensor``.
        prior_pose: prior ``T_ref_sensor``.

    Returns:
        ``{x, y, z, roll, pitch, yaw, delta_ms, translation_cm, rotation_deg}``.
    """
    import torch

    from moisst_ns.rig.geometry import calibration_errors

    out = {k: estimate[k] - prior[k] for k in ESTIMATE_COLUMNS}
    for k in ("roll", "pitch", "yaw"):
        out[k] = (out[k] + 180.0) % 360.0 - 180.0
    trans, rot = calibration_errors(torch.as_tensor(est_pose, dtype=torch.float64), torch.as_tensor(prior_pose, dtype=torch.float64))
    out["translation_cm"] = float(trans) * 100.0
    out["rotation_deg"] = float(rot)
    return out


def build_summary(estimate: Calibration, prior: Calibration, types: Dict[str, str], truth: Optional[Calibration]) -> dict:
    """summary.json content: per sensor estimate, prior, change and (with ground truth) errors before / after.

    Args:
        estimate: the calibration of the run.
        prior: the priors the run started from.
        types: sensor name -> ``camera`` / ``lidar``.
        truth: ground truth, or None.

    Returns:
        ``{"reference_sensor", "sensors": {name: {"type", "estimate", "prior", "change"}}, ["errors_before",
        "errors_after"]}`` (errors skip the reference sensor, as moisst-calibrate's summary does).
    """
    from moisst_ns.rig.calibration import calibration_report_errors

    sensors = {}
    for name in estimate.T_ref_sensor:
        est = xyz_rpy_delta(estimate.T_ref_sensor[name], estimate.time_offset[name])
        pri = xyz_rpy_delta(prior.T_ref_sensor[name], prior.time_offset[name])
        sensors[name] = {
            "type": types[name],
            "estimate": est,
            "prior": pri,
            "change": change_from_prior(est, pri, estimate.T_ref_sensor[name], prior.T_ref_sensor[name]),
        }
    for name, trust in getattr(estimate, "trust", {}).items():
        if name in sensors:
            sensors[name]["trust"] = trust.to_json()
    summary = {"reference_sensor": estimate.reference_sensor, "sensors": sensors}
    if truth is not None:
        skip = {truth.reference_sensor}
        summary["errors_before"] = {k: v for k, v in calibration_report_errors(prior, truth).items() if k not in skip}
        summary["errors_after"] = {k: v for k, v in calibration_report_errors(estimate, truth).items() if k not in skip}
    return summary


def summary_markdown(summary: dict) -> str:
    """summary.md: the tables of ``build_summary`` as Markdown."""
    run = summary.get("run", {})
    lines = ["# Calibration summary", ""]
    if run:
        lines += [f"Run `{run.get('config')}`, step {run.get('step')}, dataset `{run.get('dataset')}`.", ""]
    lines += [f"Reference sensor: `{summary['reference_sensor']}` (identity, delta 0). Units: metres, degrees "
              "(roll, pitch, yaw: R = Rz(yaw) Ry(pitch) Rx(roll)), milliseconds.", ""]
    head = "| sensor | type | x | y | z | roll | pitch | yaw | delta (ms) |"
    rule = "|---|---|---:|---:|---:|---:|---:|---:|---:|"
    for title, key in (("Estimate", "estimate"), ("Prior", "prior")):
        lines += [f"## {title}", "", head, rule]
        for name, s in summary["sensors"].items():
            v = s[key]
            lines.append(f"| {name} | {s['type']} | {v['x']:.4f} | {v['y']:.4f} | {v['z']:.4f} | {v['roll']:.3f} | "
                         f"{v['pitch']:.3f} | {v['yaw']:.3f} | {v['delta_ms']:.2f} |")
        lines.append("")
    lines += ["## Change from the prior (estimate minus prior)", "",
              "| sensor | dx | dy | dz | droll | dpitch | dyaw | ddelta (ms) | translation (cm) | rotation (deg, geodesic) |",
              "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, s in summary["sensors"].items():
        c = s["change"]
        lines.append(f"| {name} | {c['x']:.4f} | {c['y']:.4f} | {c['z']:.4f} | {c['roll']:.3f} | {c['pitch']:.3f} | "
                     f"{c['yaw']:.3f} | {c['delta_ms']:.2f} | {c['translation_cm']:.2f} | {c['rotation_deg']:.3f} |")
    lines.append("")
    lines += trust_markdown({n: s.get("trust") for n, s in summary["sensors"].items()})
    if "errors_after" in summary:
        lines += ["## Errors against ground_truth.json", "",
                  "| sensor | translation (cm) before | after | rotation (deg) before | after | time (ms) before | after |",
                  "|---|---:|---:|---:|---:|---:|---:|"]
        for name, after in summary["errors_after"].items():
            before = summary["errors_before"][name]
            lines.append(f"| {name} | {before['translation_cm']:.2f} | {after['translation_cm']:.2f} | {before['rotation_deg']:.3f} | "
                         f"{after['rotation_deg']:.3f} | {before['time_ms']:.2f} | {after['time_ms']:.2f} |")
        lines.append("")
    return "\n".join(lines)


def outputs_dir(config_path: Path) -> Path:
    """Where a run's calibration.json and summary.json are: its own folder (``ns-train moisst*``), else ``OUT`` of
    ``moisst-calibrate``'s ``OUT/<method>/run/config.yml``."""
    run = Path(config_path).resolve().parent
    return run if (run / "calibration.json").is_file() else run.parent.parent


def run_trust(config_path: Path, estimate: Calibration) -> Calibration:
    """The estimate with the trust fields the run wrote (``outputs_dir``'s calibration.json), and the priors it kept
    for sensors no better than them.

    The file is used only when every sensor it did not revert agrees with the checkpoint's estimate (same run, same
    step, every matrix entry and time offset within 1e-6); otherwise (a run trained further, or none) the estimate
    comes back unchanged.

    Args:
        config_path: the run's config.yml.
        estimate: the checkpoint's calibration.

    Returns:
        The calibration to export.
    """
    from moisst_ns.rig.format import RigFormatError, load_calibration

    file = outputs_dir(config_path) / "calibration.json"
    try:
        written = load_calibration(file) if file.is_file() else None
    except RigFormatError:
        return estimate
    if written is None or not written.trust or set(written.T_ref_sensor) != set(estimate.T_ref_sensor):
        return estimate
    for name in estimate.T_ref_sensor:
        kept = "prior is kept" in written.trust[name].reason if name in written.trust else False
        same = (np.abs(np.asarray(written.T_ref_sensor[name]) - estimate.T_ref_sensor[name]).max() <= 1e-6
                and abs(written.time_offset[name] - estimate.time_offset[name]) <= 1e-6)
        if not (same or kept):
            return estimate
    return written


def trust_markdown(trust: Dict[str, Optional[dict]]) -> List[str]:
    """The uncertainty / verdict table (Markdown lines, a blank one last) of the sensors of ``trust`` (name -> the
    ``trust`` entry of ``build_summary``) that have one (none: no lines)."""
    trusted = {n: t for n, t in trust.items() if t}
    lines: List[str] = []
    if trusted:
        lines += ["## Uncertainty (1 sigma) and verdict", "",
                  "| sensor | sx (cm) | sy | sz | s roll (deg) | s pitch | s yaw | s delta (ms) | verdict | weak | reason |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|---|---|---|"]
        for name, t in trusted.items():
            u = t.get("uncertainty")
            cells = (["-"] * 7 if u is None else [f"{100 * v:.3g}" for v in u["translation_m"]] + [f"{v:.3g}" for v in u["rotation_deg"]]
                     + [f"{1000 * u['time_offset_s']:.3g}"])
            lines.append(f"| {name} | " + " | ".join(cells) + f" | {t.get('verdict', '')} | {', '.join(t.get('weak', []))} | {t.get('reason', '')} |")
        lines.append("")
    return lines


def calibrated_rig_json(rig: Rig, estimate: Calibration, comment: str) -> dict:
    """rig.json content of ``rig`` with every sensor's prior replaced by ``estimate``.

    Paths (``trajectory``, every ``file_path``) stay relative to the dataset folder, as in the input: the result
    is valid next to the dataset's rig.json, not elsewhere (``load_rig`` refuses paths leaving the json's folder).

    Args:
        rig: the dataset's rig (``load_rig``).
        estimate: a calibration naming every sensor of the rig.
        comment: stored in the (ignored) ``comment`` key.

    Returns:
        The JSON object (``rig_to_json`` layout).
    """
    from moisst_ns.rig.format import rig_to_json

    content = rig_to_json(rig)
    for name, entry in content["sensors"].items():
        entry["T_ref_sensor"] = np.asarray(estimate.T_ref_sensor[name], dtype=np.float64).tolist()
        entry["time_offset"] = float(estimate.time_offset[name])
    return {"format": content.pop("format"), "comment": comment, **content}
