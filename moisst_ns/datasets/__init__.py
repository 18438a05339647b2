"""Dataset writers of the ``moisst-rig/1`` format: synthetic rigs (``synth``) and KITTI-360 (``kitti360``)."""
