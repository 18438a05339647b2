"""Run a fleet: every drive is one Ray task running ``moisst_ns.calibrate.run_calibration`` (``moisst-calibrate``'s
code path) into ``OUT/<vehicle>/<drive>/``; then the per-vehicle consensus and the reports. Ray's start, the
scheduling, retries and the resume marker ``fleet_done.json``: ``docs/fleet.md`` ("How it runs").
"""

from __future__ import annotations

import json
import os
import shutil
import time
from contextlib import redirect_stderr, redirect_stdout
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Callable, Dict, List, Literal, Optional

import tyro

from moisst_ns.fleet import FleetError
from moisst_ns.fleet.manifest import Manifest, drive_dir, load_manifest

MARKER = "fleet_done.json"
"""Written atomically (temporary file, then rename) as the last step of a finished drive."""
LOG = "calibrate.log"
"""What the drive's calibration printed (the fleet's console only shows progress)."""


@dataclass
class FleetConfig:
    """Calibrate a fleet of drives on Ray, combine each vehicle's drives and flag sensors that moved."""

    manifest: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="MANIFEST")]
    """Fleet manifest (TOML: [[drive]] tables with id, vehicle, dataset; a [calibrate] table; docs/fleet.md)."""
    output_dir: Path = Path("outputs/fleet")
    """Where OUT/<vehicle>/<drive>/, OUT/<vehicle>/calibration.json, fleet.json, fleet.md and the plots go."""
    address: Optional[str] = None
    """Ray cluster address (e.g. ray://head:10001 or auto); a local Ray on this machine when omitted."""
    cpus: Optional[int] = None
    """CPUs the local Ray may use (default: all cores); ignored with --address."""
    cpus_per_drive: int = 1
    """CPUs each drive's task asks Ray for, and its torch threads (2 drives x 1 or 1 x 2 on a 2-core machine)."""
    method: Optional[Literal["moisst", "moisst-lite"]] = None
    """Method of every drive, over the manifest's (default: the manifest's, else moisst-calibrate's)."""
    retries: int = 1
    """Retries of a failed drive before it is reported as failed (the other drives go on)."""
    flag_sigma: float = 5.0
    """Threshold in σ units: a drive's sensor beyond it "deviates"; a lasting step beyond it is a moved sensor."""


def write_atomic(path: Path, text: str) -> None:
    """Write ``text`` so that ``path`` is either absent or complete (a crash never leaves half a file)."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def one_line(text: object) -> str:
    """The first non-empty line of a message (Ray wraps errors in tracebacks)."""
    lines = [ln.strip() for ln in str(text).splitlines() if ln.strip()]
    return lines[0] if lines else type(text).__name__


def calibrate_drive(spec: Dict[str, Any]) -> Dict[str, Any]:
    """The body of one drive's Ray task: empty its folder, calibrate, check, write the marker.

    Args:
        spec: ``dataset``, ``out`` (the drive folder), ``threads``, ``options`` (CalibrateConfig fields), ``id``,
            ``vehicle``.

    Returns:
        ``{"wall_s": ...}``.

    Raises:
        CalibrationError: the calibration failed or left no finite calibration.json (its one-line message).
    """
    import math

    import torch

    from moisst_ns.calibrate import CalibrateConfig, CalibrationError, run_calibration
    from moisst_ns.rig.format import RigFormatError, load_calibration

    out = Path(spec["out"])
    if out.exists():
        shutil.rmtree(out)  # a killed or failed attempt's leftovers (never the dataset: checked by the driver)
    out.mkdir(parents=True)
    torch.set_num_threads(spec["threads"])
    cfg = CalibrateConfig(dataset=Path(spec["dataset"]), output_dir=out, threads=spec["threads"], **spec["options"])
    start = time.time()
    with open(out / LOG, "w") as log, redirect_stdout(log), redirect_stderr(log):
        try:
            run_calibration(cfg)
        except RigFormatError as err:
            raise CalibrationError(str(err)) from None
    wall = time.time() - start
    try:
        estimate = load_calibration(out / "calibration.json")
    except RigFormatError as err:
        raise CalibrationError(f"{out / 'calibration.json'}: {err}") from None
    if not all(math.isfinite(v) for v in estimate.time_offset.values()):
        raise CalibrationError(f"{out / 'calibration.json'}: time offsets are not finite")
    marker = {"id": spec["id"], "vehicle": spec["vehicle"], "dataset": spec["dataset"], "wall_s": wall,
              "options": spec["options"], "threads": spec["threads"], "finished": time.strftime("%Y-%m-%dT%H:%M:%S")}
    write_atomic(out / MARKER, json.dumps(marker, indent=1) + "\n")
    return {"wall_s": wall}


def check_folders(manifest: Manifest, out: Path) -> None:
    """Refuse an output folder overlapping a dataset (drive folders are emptied on retry; datasets are never written)."""
    if out.exists() and not out.is_dir():
        raise FleetError(f"{out}: --output-dir: is a file, not a folder")
    for drive in manifest.drives:
        folder, data = drive_dir(out, drive).resolve(), drive.dataset.resolve()
        if folder == data or data in folder.parents or folder in data.parents:
            raise FleetError(f"{manifest.path}: drive {drive.id}: dataset {drive.dataset} and its output folder {folder} overlap")


def _skip_slow_import(shim: Path) -> List[str]:
    """The ``PYTHONPATH`` entries (``[shim]``, or none) that make ``rfc3987_syntax`` unimportable in the Ray processes
    started with them (not in this one).

    jsonschema's optional IRI format checker builds a Lark grammar when imported: 4.5 of the 6.9 s that Ray's dashboard
    agent takes to import in this environment (``python -X importtime``). Ray 2.60's raylet gives that agent a hard
    15 s to report its ports and aborts otherwise, after which ``ray.init`` waits forever: seen on 2 cores at load 8,
    and always under ``nice``. Ray's processes inherit PYTHONPATH, so a stand-in package that raises ImportError makes
    jsonschema skip that one format checker there.
    """
    import importlib.util

    if importlib.util.find_spec("rfc3987_syntax") is None:
        return []
    (shim / "rfc3987_syntax").mkdir(parents=True, exist_ok=True)
    (shim / "rfc3987_syntax" / "__init__.py").write_text('raise ImportError("skipped in Ray processes by moisst-fleet (slow import)")\n')
    return [str(shim)]


def start_ray(cfg: FleetConfig, shim: Path) -> None:
    """``ray.init``: the cluster at ``--address``, else a local, quiet Ray (no dashboard, no usage statistics, nothing
    downloaded) with ``--cpus`` CPUs; ``shim``: a scratch folder for ``_skip_slow_import``."""
    import logging

    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # nothing leaves the machine
    try:
        import ray
    except ImportError:
        raise FleetError("moisst-fleet needs Ray, an optional dependency: make install-fleet (or pip install '.[fleet]')") from None
    kwargs = dict(log_to_driver=False, logging_level=logging.ERROR)
    saved = os.environ.get("PYTHONPATH")
    if cfg.address is None:
        kwargs.update(num_cpus=cfg.cpus or os.cpu_count() or 1, num_gpus=0, include_dashboard=False)
        # local workers inherit this environment: let them import moisst_ns from where the driver did
        package_parent = str(Path(__file__).resolve().parents[2])
        os.environ["PYTHONPATH"] = os.pathsep.join(_skip_slow_import(shim) + [package_parent] + [q for q in (saved or "").split(os.pathsep) if q])
    try:
        ray.init(address=cfg.address or "local", **kwargs)  # "local": a new Ray, never one found on the machine
    except Exception as err:  # connection refused, bad address, a node that did not start
        raise FleetError(f"--address {cfg.address}: cannot start or reach Ray: {one_line(err)}") from None
    finally:  # Ray's processes took their copy of the environment; leave this process's as it was
        if saved is None:
            os.environ.pop("PYTHONPATH", None)
        else:
            os.environ["PYTHONPATH"] = saved


def _progress(line: str) -> None:
    print(f"[fleet] {line}", flush=True)


def run_drives(cfg: FleetConfig, manifest: Manifest, report: Callable[[str], None] = _progress) -> List[Dict[str, Any]]:
    """Calibrate every unfinished drive as a Ray task; one row per drive (manifest order).

    Rows: ``id``, ``vehicle``, ``dataset``, ``status`` (``done``/``failed``), ``reason`` (one line, failed only),
    ``wall_s`` (the calibration's wall time), ``resumed`` (finished by an earlier run).
    """
    import ray

    out = cfg.output_dir
    rows, pending = {}, {}
    for drive in manifest.drives:
        folder = drive_dir(out, drive)
        row = {"id": drive.id, "vehicle": drive.vehicle, "dataset": str(drive.dataset), "status": None, "reason": None,
               "wall_s": None, "resumed": False}
        rows[drive.id] = row
        if (folder / MARKER).is_file() and (folder / "calibration.json").is_file():  # finished by an earlier run
            row.update(status="done", resumed=True, wall_s=json.loads((folder / MARKER).read_text()).get("wall_s"))
    todo = [d for d in manifest.drives if rows[d.id]["status"] is None]
    skipped = len(manifest.drives) - len(todo)
    if skipped:
        report(f"{skipped} drive(s) already finished in {out} (resume): {', '.join(d.id for d in manifest.drives if rows[d.id]['resumed'])}")
    if not todo:
        return [rows[d.id] for d in manifest.drives]
    import tempfile

    shim = Path(tempfile.mkdtemp(prefix="moisst-fleet-"))
    try:
        start_ray(cfg, shim)
        slots = max(1, int(ray.cluster_resources().get("CPU", 1)) // cfg.cpus_per_drive)
        task = ray.remote(calibrate_drive).options(num_cpus=cfg.cpus_per_drive, max_retries=cfg.retries, retry_exceptions=True)
        for drive in todo:
            options = dict(drive.options)
            if cfg.method is not None:
                options["method"] = cfg.method
            spec = {"id": drive.id, "vehicle": drive.vehicle, "dataset": str(drive.dataset), "out": str(drive_dir(out, drive).resolve()),
                    "threads": cfg.cpus_per_drive, "options": options}
            pending[task.remote(spec)] = drive
        started = time.time()
        report(f"{len(todo)} drive(s) to calibrate on Ray ({slots} at a time, {cfg.cpus_per_drive} CPU each, up to {cfg.retries} retries)")
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=30.0)
            for ref in ready:
                drive = pending.pop(ref)
                row = rows[drive.id]
                try:
                    result = ray.get(ref)
                    row.update(status="done", wall_s=result["wall_s"])
                except ray.exceptions.RayTaskError as err:
                    row.update(status="failed", reason=one_line(getattr(err, "cause", None) or err))
                except ray.exceptions.RayError as err:  # a worker that died (killed, out of memory) after its retries
                    row.update(status="failed", reason=one_line(err))
                report(f"{drive.id} done in {row['wall_s']:.0f} s" if row["status"] == "done" else f"{drive.id} FAILED: {row['reason']}")
            done = sum(r["status"] == "done" and not r["resumed"] for r in rows.values())
            failed = sum(r["status"] == "failed" for r in rows.values())
            running = min(slots, len(pending))
            elapsed = time.time() - started
            eta = f", ETA {elapsed / (done + failed) * len(pending) / 60:.1f} min" if pending and done + failed else ""
            report(f"{done + skipped}/{len(manifest.drives)} done, {running} running, {len(pending) - running} waiting, "
                   f"{failed} failed, {elapsed:.0f} s{eta}")
    finally:
        ray.shutdown()
        shutil.rmtree(shim, ignore_errors=True)
    return [rows[d.id] for d in manifest.drives]


def run_fleet(cfg: FleetConfig, report: Callable[[str], None] = _progress) -> Dict[str, Any]:
    """Validate the manifest, calibrate the drives, combine them per vehicle and write the reports.

    Returns:
        The content of ``OUT/fleet.json``.

    Raises:
        FleetError: a bad manifest, options or output folder (before any work starts), or Ray not reachable.
    """
    from moisst_ns.fleet.report import write_reports

    if cfg.cpus_per_drive < 1 or cfg.retries < 0 or (cfg.cpus is not None and cfg.cpus < 1) or not cfg.flag_sigma > 0:
        raise FleetError("--cpus-per-drive and --cpus must be >= 1, --retries >= 0, --flag-sigma > 0")
    manifest = load_manifest(cfg.manifest)
    check_folders(manifest, cfg.output_dir)
    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    start = time.time()
    rows = run_drives(cfg, manifest, report)
    return write_reports(cfg, manifest, rows, time.time() - start, report)
