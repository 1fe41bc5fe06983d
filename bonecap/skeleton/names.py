"""The map between our generic bone names and OpenSim body names.

OpenSim models lump bones into bodies (Rajagopal2016's ``torso`` carries the
skull, spine, ribs and scapulae; its ``pelvis`` our sacrum and both hip bones).
``generic_skeleton/opensim_map.yaml`` lists, per model family, which of our
bones make up each body, so evaluation and marker transfer work across
templates.
"""

from __future__ import annotations

import fnmatch
import os
from functools import lru_cache
from pathlib import Path

from bonecap.errors import BonecapError, InputError
from bonecap.io import load_yaml

__all__ = ["OPENSIM_FAMILIES", "model_family", "opensim_body_map", "opensim_body_of", "bones_of_body"]

_MAP_FILE = Path(__file__).resolve().parents[2] / "generic_skeleton" / "opensim_map.yaml"
OPENSIM_FAMILIES = ("rajagopal2016", "gait2392", "hamner2010")


@lru_cache(maxsize=None)
def _load() -> dict[str, dict[str, list[str]]]:
    if not _MAP_FILE.is_file():
        raise BonecapError("the OpenSim name map is missing (bonecap must be run from its source tree)", _MAP_FILE)
    return load_yaml(_MAP_FILE.read_text())


def model_family(model: str | os.PathLike) -> str:
    """The model family of an ``.osim`` path or name (``"rajagopal2016"``, ``"gait2392"``, ``"hamner2010"``).

    Raises
    ------
    InputError
        If the name matches no family we map.
    """
    name = Path(model).name.lower()
    for family, keys in (("rajagopal2016", ("rajagopal",)), ("gait2392", ("gait2392", "gait2354")),
                         ("hamner2010", ("hamner",))):
        if any(k in name for k in keys):
            return family
    raise InputError(f"no bone-name map for this model (known families: {', '.join(OPENSIM_FAMILIES)})", model)


def opensim_body_map(family: str) -> dict[str, list[str]]:
    """``{OpenSim body: [our bone-name patterns]}`` for a family."""
    table = _load()
    if family not in table:
        raise InputError(f"unknown model family (known: {', '.join(OPENSIM_FAMILIES)})", family)
    return table[family]


def opensim_body_of(bone: str, family: str) -> str | None:
    """The OpenSim body that carries our ``bone`` in ``family``, or ``None``."""
    for body, patterns in opensim_body_map(family).items():
        if any(fnmatch.fnmatchcase(bone, p) for p in patterns):
            return body
    return None


def bones_of_body(body: str, bone_names: list[str], family: str) -> list[str]:
    """Those of ``bone_names`` that make up OpenSim ``body`` in ``family``."""
    patterns = opensim_body_map(family).get(body, [])
    return [b for b in bone_names if any(fnmatch.fnmatchcase(b, p) for p in patterns)]
