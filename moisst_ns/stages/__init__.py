"""Calibration stages that run outside the NeRF (no nerfstudio import): LiDAR first, ..."""
