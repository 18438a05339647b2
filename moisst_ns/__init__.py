"""moisst-ns: MOISST spatiotemporal calibration of camera/LiDAR rigs as a nerfstudio 1.1.5 plugin.

``moisst_ns.rig`` is the framework-free rig math (poses, interpolation, parameters, dataset format);
the rest is thin nerfstudio glue.
"""

from moisst_ns.compat import allow_numpy_in_checkpoints

allow_numpy_in_checkpoints()

__version__ = "0.1.0"
