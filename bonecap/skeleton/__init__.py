"""Skeletons: the embedded generic template and imported OpenSim models.

- :mod:`bonecap.skeleton.generic` -- the parametric generic skeleton (ISB frames)
  described by ``generic_skeleton/*.yaml``.
- :mod:`bonecap.skeleton.opensim` -- ``.osim`` models with their Geometry folder.
"""
