"""What a fleet run leaves: ``OUT/<vehicle>/calibration.json`` (the consensus), ``OUT/fleet.json``, ``OUT/fleet.md``
and ``OUT/plots/<sensor>.png`` (each sensor's estimates over the drives, as deviations from its vehicle's consensus)."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Callable, Dict, List

import numpy as np

from moisst_ns.fleet.consensus import COMPONENTS, UNITS, DriveEstimate, SensorEstimate, fleet_spread, sigma_from_uncertainty, vehicle_consensus
from moisst_ns.fleet.manifest import Manifest, drive_dir

FORMAT = "moisst-fleet/1"
SHOW = {"m": (100.0, " cm"), "deg": (1.0, "°"), "s": (1000.0, " ms")}
UNIT = dict(zip(COMPONENTS, UNITS))


def load_estimate(drive_id: str, path: Path) -> tuple:
    """A drive's calibration.json as ``(DriveEstimate, reference sensor, sensors left out)``: σ from each sensor's
    ``uncertainty``; a sensor whose verdict is ``not converged`` (its prior kept, or still moving) is no measurement
    of the mount and is left out of the consensus."""
    from moisst_ns.rig.format import load_calibration

    cal = load_calibration(path)
    raw = json.loads(path.read_text())["sensors"]
    left_out = sorted(n for n in cal.T_ref_sensor if raw[n].get("verdict") == "not converged")
    sensors = {n: SensorEstimate(T, cal.time_offset[n], sigma_from_uncertainty(raw[n].get("uncertainty"), T[:3, :3]))
               for n, T in cal.T_ref_sensor.items() if n not in left_out}
    return DriveEstimate(drive_id, sensors), cal.reference_sensor, left_out


def _comps(values) -> Dict[str, float]:
    return {c: float(v) for c, v in zip(COMPONENTS, values)}


def _fmt(comp: str, value: float) -> str:
    scale, unit = SHOW[UNIT[comp]]
    return f"{scale * value:+.2f}{unit}"


def write_reports(cfg, manifest: Manifest, rows: List[Dict[str, Any]], wall_s: float, report: Callable[[str], None]) -> Dict[str, Any]:
    """Consensus per vehicle, then fleet.json, fleet.md, the plots; returns fleet.json's content."""
    from moisst_ns.rig.format import Calibration

    out = cfg.output_dir
    by_id = {d.id: d for d in manifest.drives}
    vehicles: Dict[str, List[DriveEstimate]] = {v: [] for v in manifest.vehicles()}
    reference: Dict[str, str] = {}
    for row in rows:
        if row["status"] != "done":
            continue
        estimate, ref, row["left_out"] = load_estimate(row["id"], drive_dir(out, by_id[row["id"]]) / "calibration.json")
        if reference.setdefault(row["vehicle"], ref) != ref:
            row["note"] = f"reference sensor {ref} is not the vehicle's {reference[row['vehicle']]}: left out of the consensus"
            continue
        vehicles[row["vehicle"]].append(estimate)
    own = [s.sigma is not None for v in vehicles.values() for d in v for s in d.sensors.values()]
    source = "uncertainty" if own and all(own) else ("mixed" if any(own) else "spread")
    vehicles = {v: d for v, d in vehicles.items() if d}
    spread = fleet_spread(vehicles, reference)
    consensus = {v: vehicle_consensus(d, reference[v], spread, cfg.flag_sigma) for v, d in vehicles.items()}

    for row in rows:
        row["sensors"] = {}
        vc = consensus.get(row["vehicle"])
        if vc is None or row["status"] != "done":
            continue
        for name in row.get("left_out", ()):
            row["sensors"][name] = {"verdict": "not converged (left out)", "max_abs_z": None}
        for name, sc in vc.sensors.items():
            if row["id"] in sc.verdict:
                z = sc.z[row["id"]]
                row["sensors"][name] = {"verdict": sc.verdict[row["id"]], "max_abs_z": float(np.max(np.abs(z))),
                                        "deviation": _comps(sc.deviation[row["id"]]), "z": _comps(z)}
    blocks = {}
    for vehicle, vc in consensus.items():
        cal = Calibration(vc.reference_sensor, {vc.reference_sensor: np.eye(4), **{n: s.T_ref_sensor for n, s in vc.sensors.items()}},
                          {vc.reference_sensor: 0.0, **{n: s.time_offset for n, s in vc.sensors.items()}})
        (out / vehicle).mkdir(parents=True, exist_ok=True)
        cal.write(out / vehicle / "calibration.json")
        blocks[vehicle] = {
            "calibration": f"{vehicle}/calibration.json", "reference_sensor": vc.reference_sensor, "drives": vc.drives,
            "sensors": {n: {"T_ref_sensor": s.T_ref_sensor.tolist(), "time_offset": s.time_offset, "used_drives": s.used,
                            "spread": _comps(s.spread), "moved": s.move.line() if s.move else None}
                        for n, s in vc.sensors.items()},
            "moves": [m.line() for m in vc.moves()],
        }
    for vehicle in manifest.vehicles():
        blocks.setdefault(vehicle, {"calibration": None, "drives": [], "sensors": {}, "moves": [], "note": "no finished drive"})
    fleet = {"format": FORMAT, "manifest": str(manifest.path), "written": time.strftime("%Y-%m-%dT%H:%M:%S"),
             "wall_s": wall_s, "cpus_per_drive": cfg.cpus_per_drive, "flag_sigma": cfg.flag_sigma,
             "sigma_source": source, "spread_sigma": {n: _comps(v) for n, v in sorted(spread.items())}, "drives": rows, "vehicles": blocks}
    (out / "fleet.json").write_text(json.dumps(fleet, indent=1) + "\n")
    plots = write_plots(out / "plots", consensus, spread, cfg.flag_sigma)
    (out / "fleet.md").write_text(fleet_markdown(fleet, plots, out))
    for vehicle, block in blocks.items():
        for line in block["moves"]:
            report(f"{vehicle}: {line}")
    failed = [r for r in rows if r["status"] == "failed"]
    report(f"{len(rows) - len(failed)}/{len(rows)} drives done, {len(failed)} failed; wrote {out / 'fleet.json'}, {out / 'fleet.md'}")
    return fleet


def fleet_markdown(fleet: Dict[str, Any], plots: List[Path], out: Path) -> str:
    """fleet.md: one row per drive, one block per vehicle, the plots."""
    lines = ["# Fleet calibration", "", f"Manifest `{fleet['manifest']}`, {len(fleet['drives'])} drives, "
             f"{fleet['wall_s']:.0f} s wall, {fleet['cpus_per_drive']} CPU per drive. Flag threshold {fleet['flag_sigma']:g} σ; "
             f"σ from {fleet['sigma_source']}" + (" (the drives' calibration.json carry no uncertainty: robust spread of the "
                                                    "fleet, 1.4826 × median absolute residual)" if fleet["sigma_source"] == "spread" else "")
             + ":", ""] + [f"* {n}: " + ", ".join(f"{c} {_fmt(c, v).lstrip('+')}" for c, v in s.items()) for n, s in fleet["spread_sigma"].items()] + ["",
             "| drive | vehicle | status | wall | sensors (verdict, largest deviation in σ) |", "|---|---|---|---|---|"]
    for row in fleet["drives"]:
        wall = f"{row['wall_s']:.0f} s" if row["wall_s"] is not None else "-"
        sensors = "; ".join(f"{n} {s['verdict']}" + ("" if s["max_abs_z"] is None else f" ({s['max_abs_z']:.1f} σ)") for n, s in row["sensors"].items())
        status = row["status"] + (" (resumed)" if row["resumed"] else "") + (f": {row['reason']}" if row["reason"] else "")
        lines.append(f"| {row['id']} | {row['vehicle']} | {status} | {wall} | {sensors or row.get('note', '-')} |")
    for vehicle, block in fleet["vehicles"].items():
        lines += ["", f"## {vehicle}", ""]
        if block["calibration"] is None:
            lines.append("No finished drive: no consensus.")
            continue
        lines += [f"Consensus `{block['calibration']}` over drives {', '.join(block['drives'])} (reference {block['reference_sensor']}).", ""]
        lines += [f"**{m}**" for m in block["moves"]] + ([""] if block["moves"] else [])
        lines += ["| sensor | x, y, z (m) | time offset (ms) | spread (cm / ° / ms) | drives used |", "|---|---|---|---|---|"]
        for name, s in block["sensors"].items():
            xyz = ", ".join(f"{v:.3f}" for v in np.asarray(s["T_ref_sensor"])[:3, 3])
            sp = s["spread"]
            spread = f"{100 * max(sp['x'], sp['y'], sp['z']):.2f} / {max(sp['rot_x'], sp['rot_y'], sp['rot_z']):.2f} / {1000 * sp['time_offset']:.1f}"
            lines.append(f"| {name} | {xyz} | {1000 * s['time_offset']:+.1f} | {spread} | {', '.join(s['used_drives'])} |")
    if plots:
        lines += ["", "## Estimates over the drives", ""] + [f"![{p.stem}]({p.relative_to(out)})" for p in plots]
    return "\n".join(lines) + "\n"


def write_plots(folder: Path, consensus: Dict[str, Any], spread: Dict[str, np.ndarray], flag_sigma: float) -> List[Path]:
    """One PNG per sensor: its seven components per drive minus its vehicle's consensus, a line per vehicle, with
    the ±flag_sigma·σ band of the fleet's spread."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    names = sorted({n for vc in consensus.values() for n in vc.sensors})
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for name in names:
        fig, axes = plt.subplots(1, 7, figsize=(17, 3.0), constrained_layout=True)
        for j, (ax, comp) in enumerate(zip(axes, COMPONENTS)):
            scale, unit = SHOW[UNIT[comp]]
            band = flag_sigma * spread[name][j] * scale
            ax.axhspan(-band, band, color="0.9", zorder=0)
            for vehicle, vc in consensus.items():
                sc = vc.sensors.get(name)
                if sc is None:
                    continue
                ids = [d for d in vc.drives if d in sc.deviation]
                ax.plot(range(len(ids)), [scale * sc.deviation[d][j] for d in ids], "o-", label=vehicle)
                if sc.move is not None and sc.move.component == comp:
                    ax.axvline(ids.index(sc.move.after) - 0.5, color="red", lw=1)
            ax.set_title(f"{comp} ({unit.strip()})", fontsize=9)
            ax.set_xlabel("drive (per vehicle, in order)", fontsize=7)
            ax.tick_params(labelsize=7)
            ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        axes[0].legend(fontsize=7)
        fig.suptitle(f"{name}: estimate minus its vehicle's consensus (grey: ±{flag_sigma:g} σ; red: a flagged move)", fontsize=10)
        path = folder / f"{name}.png"
        fig.savefig(path, dpi=80)
        plt.close(fig)
        paths.append(path)
    return paths
