"""The LiDAR stage: every LiDAR placed by its own scans (motion) and, where the reference is a camera, by the view they share (docs/lidar-first.md)."""
