"""Choosing a template: ``--generic default`` or ``--generic MODEL.osim``.

Every command that starts from a template takes it the same way; this module
turns the option into a :class:`~bonecap.model.Skeleton` and the marker set
that goes with it (Plug-in Gait for the embedded skeleton, the model's own
MarkerSet for an OpenSim model).

Both kinds of template share one world frame convention: X anterior,
Y superior, Z to the right, in mm (the ISB global frame and OpenSim's ground).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from bonecap.errors import InputError
from bonecap.markers import MarkerSet, load_marker_set
from bonecap.model import Skeleton

__all__ = ["load_template", "template_marker_set", "MODEL_TO_LAB_ZUP"]

#: Rotation of the template world (X anterior, Y up, Z right) into a Z-up lab
#: whose X points forward and Y to the subject's left: (x, y, z) -> (x, -z, y).
MODEL_TO_LAB_ZUP = np.array([[1.0, 0.0, 0.0, 0.0],
                             [0.0, 0.0, -1.0, 0.0],
                             [0.0, 1.0, 0.0, 0.0],
                             [0.0, 0.0, 0.0, 1.0]])


def load_template(generic: str | os.PathLike = "default", **kwargs) -> Skeleton:
    """The template skeleton named by ``--generic``.

    Parameters
    ----------
    generic : str or path-like
        ``"default"`` for bonecap's embedded parametric skeleton, or the path of
        an OpenSim ``.osim`` model (its Geometry folder beside it or one level up).
    **kwargs
        Passed to :func:`bonecap.skeleton.generic.build_generic_skeleton`
        (``stature_mm``, ``params``) for the default template.

    Raises
    ------
    InputError
        If ``generic`` is neither ``"default"`` nor an existing ``.osim`` file.
    """
    if str(generic) == "default":
        from bonecap.skeleton.generic import build_generic_skeleton

        return build_generic_skeleton(**kwargs)
    path = Path(generic)
    if path.suffix.lower() != ".osim":
        raise InputError("--generic takes 'default' or an OpenSim .osim model", path)
    if not path.is_file():
        raise InputError("no such OpenSim model", path)
    from bonecap.skeleton.opensim import read_osim

    return read_osim(path)


def template_marker_set(generic: str | os.PathLike = "default") -> MarkerSet:
    """The marker set that goes with a template: Plug-in Gait, or the model's MarkerSet."""
    if str(generic) == "default":
        return load_marker_set("plug_in_gait_full_body")
    return load_marker_set(Path(generic))
