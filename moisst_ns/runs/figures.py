"""Figures that cannot go stale: the README's "Where it stands" table is rendered from ``docs/figures.json``.

``docs/figures.json`` holds measured runs: per run a column label, where the figures came from (command, commit,
date, machine, wall time, peak memory, run folder) and per sensor the errors before (priors) and after. A run is
recorded from a ``moisst-calibrate`` output folder (its ``summary.json``) by ``moisst-figures --record OUT``;
``render_block`` turns the file into the Markdown between ``BEGIN`` and ``END`` in README.md, and
``tests/test_figures.py`` checks that README.md holds exactly that. Pure Python: no torch, no nerfstudio.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Dict, List, Optional

from moisst_ns.runs import ERROR_KEYS, RunError

BEGIN = "<!-- figures: generated from docs/figures.json by `moisst-figures`; do not edit by hand -->"
END = "<!-- /figures -->"


def _num(x: float) -> str:
    text = f"{x:.4g}"  # 4 significant digits: 142.9, 15.75, 0.833, 0.003
    return f"{x:.3f}" if "e" in text else text


def _cell(err: Optional[Dict[str, float]]) -> str:
    return " / ".join(_num(float(err[k])) for k in ERROR_KEYS) if err else "-"


def _read_json(path: Path) -> Any:
    """``rig.format.read_json`` (one line naming the file, line and column of a syntax error) as a ``RunError``."""
    from moisst_ns.rig.format import RigFormatError, read_json

    try:
        return read_json(path)
    except RigFormatError as err:
        raise RunError(str(err)) from None


def load_figures(path: Path) -> Dict[str, Any]:
    """Read figures.json (one-line ``RunError`` naming the file on a missing or malformed file)."""
    path = Path(path)
    if not path.is_file():
        raise RunError(f"{path}: (file): not found")
    data = _read_json(path)
    if not isinstance(data, dict) or not isinstance(data.get("runs"), list) or not data["runs"]:
        raise RunError(f"{path}: runs: must be a non-empty list")
    for i, run in enumerate(data["runs"]):
        if not isinstance(run, dict) or not isinstance(run.get("label"), str) or not isinstance(run.get("sensors"), dict):
            raise RunError(f"{path}: runs[{i}]: needs a 'label' (text) and 'sensors' (object)")
        for name, entry in run["sensors"].items():
            for side in ("before", "after"):
                err = entry.get(side) if isinstance(entry, dict) else None
                if err is not None and not all(isinstance(err.get(k), (int, float)) for k in ERROR_KEYS):
                    raise RunError(f"{path}: runs[{i}].sensors.{name}.{side}: needs numbers {', '.join(ERROR_KEYS)}")
    return data


def run_from_output(out: Path, label: str, source: Dict[str, Any]) -> Dict[str, Any]:
    """A figures.json run from a moisst-calibrate output folder (``OUT/summary.json``, written with ground truth)."""
    path = Path(out) / "summary.json"
    if not path.is_file():
        raise RunError(f"{path}: (file): not found (give the --output-dir of a finished moisst-calibrate)")
    summary = _read_json(path)
    before, after = summary.get("errors_before"), summary.get("errors_after")
    if not isinstance(before, dict) or not isinstance(after, dict):
        raise RunError(f"{path}: errors_after: missing (the dataset had no ground_truth.json: no errors to record)")
    measured = {"method": summary.get("method"), "iterations": summary.get("iterations"), "seed": summary.get("seed"),
                "training_wall_time_s": summary.get("wall_time_s"), "output_dir": str(Path(out).resolve())}
    return {"label": label, "source": {**{k: v for k, v in measured.items() if v is not None}, **source},
            "sensors": {name: {"before": before.get(name), "after": after[name]} for name in after}}


def record_run(figures: Dict[str, Any], run: Dict[str, Any]) -> Dict[str, Any]:
    """``figures`` with ``run`` replacing the run of the same label (or appended)."""
    runs = [r for r in figures.get("runs", []) if r.get("label") != run["label"]]
    labels = [r.get("label") for r in figures.get("runs", [])]
    at = labels.index(run["label"]) if run["label"] in labels else len(runs)
    return {**figures, "runs": runs[:at] + [run] + runs[at:]}


def render_block(figures: Dict[str, Any]) -> str:
    """The README block (markers included): where each column came from, then the table."""
    runs = figures["runs"]
    notes = figures.get("sensor_notes", {})
    sensors: List[str] = []
    for run in runs:
        sensors += [n for n in run["sensors"] if n not in sensors]
    lines = [BEGIN, ""]
    if figures.get("setup"):
        lines += [figures["setup"], ""]
    for run in runs:
        src = run.get("source", {})
        facts = [f"`{src['command']}`" if src.get("command") else None,
                 src.get("measured"), src.get("commit") and f"commit {src['commit']}", src.get("machine"),
                 src.get("wall") and f"{src['wall']} wall", src.get("peak_rss") and f"{src['peak_rss']} peak RSS", src.get("note")]
        lines.append(f"* **{run['label']}**: " + "; ".join(f for f in facts if f) + ".")
    lines += ["", "| sensor | priors | " + " | ".join(r["label"] for r in runs) + " |", "|---|---|" + "---|" * len(runs)]
    for name in sensors:
        prior = next((r["sensors"][name].get("before") for r in runs if r["sensors"].get(name, {}).get("before")), None)
        label = f"{name} ({notes[name]})" if name in notes else name
        lines.append(f"| {label} | {_cell(prior)} | " + " | ".join(_cell(r["sensors"].get(name, {}).get("after")) for r in runs) + " |")
    lines += ["", "Errors: translation cm / rotation deg / time ms against the rig's ground truth.", "", END]
    return "\n".join(lines)


def update_readme(text: str, figures: Dict[str, Any], where: str = "README.md") -> str:
    """``text`` with the block between the markers replaced by ``render_block(figures)``."""
    start, stop = text.find(BEGIN), text.find(END)
    if start < 0 or stop < start:
        raise RunError(f"{where}: figures block: markers not found ({BEGIN} ... {END})")
    return text[:start] + render_block(figures) + text[stop + len(END):]
