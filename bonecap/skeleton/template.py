"""Choosing a template: ``--generic default`` or ``--generic MODEL.osim``.

Every command that starts from a template takes it the same way; this module
turns the option into a :class:`~bonecap.model.Skeleton` and the marker set
that goes with it (Plug-in Gait for the embedded skeleton, the model's own
MarkerSet for an OpenSim model).

Both kinds of template share one world frame convention: X anterior,
Y superior, Z to the right, in mm (the ISB global frame and OpenSim's ground).
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import pickle
import tempfile
from pathlib import Path

import numpy as np

from bonecap.errors import InputError
from bonecap.markers import MarkerSet, load_marker_set
from bonecap.model import Skeleton

__all__ = ["load_template", "template_cache_dir", "template_marker_set", "MODEL_TO_LAB_ZUP"]

#: Rotation of the template world (X anterior, Y up, Z right) into a Z-up lab
#: whose X points forward and Y to the subject's left: (x, y, z) -> (x, -z, y).
MODEL_TO_LAB_ZUP = np.array([[1.0, 0.0, 0.0, 0.0],
                             [0.0, 0.0, -1.0, 0.0],
                             [0.0, 1.0, 0.0, 0.0],
                             [0.0, 0.0, 0.0, 1.0]])


def load_template(generic: str | os.PathLike = "default", *, cache: bool = True, **kwargs) -> Skeleton:
    """The template skeleton named by ``--generic``.

    Parameters
    ----------
    generic : str or path-like
        ``"default"`` for bonecap's embedded parametric skeleton, or the path of
        an OpenSim ``.osim`` model (its Geometry folder beside it or one level up).
    cache : bool
        The embedded skeleton is built from its description (meshing ~90 bones:
        5-8 s on two cores); once built it is kept in the user's cache folder
        (:func:`template_cache_dir`) and later runs load it (~0.2 s). The entry's
        key covers everything the build depends on -- the description file, the
        source of :mod:`bonecap.skeleton` and :mod:`bonecap.model`, ``kwargs``
        and the versions of the meshing libraries -- so an edit or an upgrade
        builds afresh. False: always build.
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

        folder = template_cache_dir() if cache else None
        if folder is None:
            return build_generic_skeleton(**kwargs)
        path = folder / f"generic_{_generic_key(kwargs)}.pickle"
        try:
            with open(path, "rb") as fh:
                skeleton = pickle.load(fh)
            if isinstance(skeleton, Skeleton):
                skeleton.metadata["cached_in"] = str(path)
                return skeleton
        except Exception:        # absent, unreadable or from another build: build it (again)
            pass
        skeleton = build_generic_skeleton(**kwargs)
        tmp = None
        try:
            folder.mkdir(parents=True, exist_ok=True)
            # written whole then renamed: a run killed half-way, or two runs at once, leave no torn entry
            with tempfile.NamedTemporaryFile(dir=folder, suffix=".part", delete=False) as fh:
                tmp = fh.name
                pickle.dump(skeleton, fh, protocol=pickle.HIGHEST_PROTOCOL)
            os.replace(tmp, path)
        except Exception:        # a read-only home, a full disk: no cache, the build is still good
            if tmp is not None:
                with contextlib.suppress(OSError):
                    os.unlink(tmp)
        return skeleton
    path = Path(generic)
    if path.suffix.lower() != ".osim":
        raise InputError("--generic takes 'default' or an OpenSim .osim model", path)
    if not path.is_file():
        raise InputError("no such OpenSim model", path)
    from bonecap.skeleton.opensim import read_osim

    return read_osim(path)


def template_cache_dir() -> Path | None:
    """Where the built embedded skeleton is kept: ``$BONECAP_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/bonecap``, else ``~/.cache/bonecap``. ``BONECAP_CACHE_DIR``
    set to an empty string, ``0`` or ``off`` turns the cache off (None)."""
    env = os.environ.get("BONECAP_CACHE_DIR")
    if env is not None:
        return None if env.strip().lower() in ("", "0", "off", "no", "none") else Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "bonecap"


def _generic_key(kwargs: dict) -> str:
    """A digest of everything the embedded skeleton's build depends on."""
    import importlib.metadata as md
    import sys

    import bonecap.model
    import bonecap.skeleton
    from bonecap.skeleton.generic import DESCRIPTION_PATH

    h = hashlib.sha256()
    sources = sorted(Path(bonecap.skeleton.__file__).parent.glob("*.py")) + [Path(bonecap.model.__file__)]
    for f in [DESCRIPTION_PATH, *sources]:
        h.update(f.name.encode() + b"\0" + (f.read_bytes() if f.is_file() else b"") + b"\0")
    for dist in ("numpy", "scipy", "scikit-image", "trimesh", "fast-simplification", "vtk", "pyvista"):
        try:
            h.update(f"{dist}={md.version(dist)};".encode())
        except md.PackageNotFoundError:
            h.update(f"{dist}=-;".encode())
    h.update(sys.version.encode() + repr(sorted(kwargs.items())).encode())
    return h.hexdigest()[:20]


def template_marker_set(generic: str | os.PathLike = "default") -> MarkerSet:
    """The marker set that goes with a template: Plug-in Gait, or the model's MarkerSet."""
    if str(generic) == "default":
        return load_marker_set("plug_in_gait_full_body")
    return load_marker_set(Path(generic))
