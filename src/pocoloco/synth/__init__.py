"""The synthetic capture pipeline: procedural motions on the anny body, garments simulated with
newton's cloth solver, a virtual multi-view capture, and the launcher that writes a dataset in
shards (``pocoloco data synth``). Needs the ``synth`` extra (newton, warp, open3d); the dataset
side (formats, readers, poses) is :mod:`pocoloco.data`."""
