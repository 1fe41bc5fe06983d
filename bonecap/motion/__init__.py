"""Motion solving: marker trajectories -> bone poses.

- :mod:`bonecap.motion.rigid` -- the weighted least-squares rigid fit, the core
  every solver builds on.
"""
