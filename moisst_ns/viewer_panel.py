"""A viewer panel with each sensor's current calibration (and errors, with ground truth), updated every N steps.

nerfstudio's viewer collects ``ViewerElement`` attributes of the modules under the pipeline; this module holds
one read-only group per non-reference sensor, under "Custom Elements / calibration".
"""

from __future__ import annotations

from typing import Dict, List

from torch import nn

from nerfstudio.viewer.viewer_elements import ViewerNumber, ViewerText, ViewerVec3


class CalibrationPanel(nn.Module):
    """Read-only viewer elements: x, y, z (m), roll, pitch, yaw (deg), delta (ms) and errors per sensor."""

    def __init__(self, sensors: List[str], has_truth: bool) -> None:
        super().__init__()
        self.sensors = list(sensors)
        for name in self.sensors:
            setattr(self, f"{name}_0_xyz", ViewerVec3(f"{name}: x y z (m)", (0.0, 0.0, 0.0), step=1e-4, disabled=True))
            setattr(self, f"{name}_1_rpy", ViewerVec3(f"{name}: roll pitch yaw (deg)", (0.0, 0.0, 0.0), step=1e-3, disabled=True))
            setattr(self, f"{name}_2_delta", ViewerNumber(f"{name}: delta (ms)", 0.0, disabled=True))
            if has_truth:
                setattr(self, f"{name}_3_errors", ViewerText(f"{name}: error", "", disabled=True))

    def update(self, summary: Dict[str, Dict[str, float]]) -> None:
        """Show a ``CalibrationOptimizer.sensor_summary()``."""
        for name, s in summary.items():
            if name not in self.sensors:
                continue
            getattr(self, f"{name}_0_xyz").value = (round(s["x"], 4), round(s["y"], 4), round(s["z"], 4))
            getattr(self, f"{name}_1_rpy").value = (round(s["roll"], 3), round(s["pitch"], 3), round(s["yaw"], 3))
            getattr(self, f"{name}_2_delta").value = round(s["delta_ms"], 3)
            if hasattr(self, f"{name}_3_errors") and "err_translation_cm" in s:
                getattr(self, f"{name}_3_errors").value = (
                    f"{s['err_translation_cm']:.2f} cm, {s['err_rotation_deg']:.3f} deg, {s['err_time_ms']:.2f} ms"
                )
