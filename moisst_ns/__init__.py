"""moisst-ns: MOISST spatiotemporal calibration of camera/LiDAR rigs as a nerfstudio 1.1.5 plugin.

``moisst_ns.rig`` is the framework-free rig math (poses, interpolation, parameters, dataset format);
the rest is thin nerfstudio glue.

Importing the package imports neither torch nor nerfstudio (``moisst-* --help`` stays instant); the checkpoint
shim of ``moisst_ns.compat`` is applied by ``moisst_ns.model``, which every run, checkpoint load and
``ns-*`` tool of our methods imports.
"""

__version__ = "0.1.0"
