"""Summaries of the files bonecap reads, for ``bonecap inspect``.

:func:`inspect_path` recognises the kind of input from the path (a C3D trial,
a DICOM folder or file, a NIfTI/NRRD volume, a glTF, a mesh) and returns a
JSON-able dict built by the reader module of that format; :func:`format_summary`
turns it into a few human-readable lines.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from bonecap.errors import InputError

__all__ = ["inspect_path", "format_summary", "kind_of_path", "write_summaries"]

_VOLUME_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".nhdr", ".dcm")
_MESH_SUFFIXES = (".ply", ".stl", ".obj", ".vtp", ".vtk")


def kind_of_path(path: str | os.PathLike) -> str:
    """Name the kind of input at ``path``: ``c3d``, ``volume``, ``gltf`` or ``mesh``.

    Raises
    ------
    InputError
        If the path does not exist or its kind is not one bonecap reads.
    """
    p = Path(path)
    if not p.exists():
        raise InputError("no such file or folder", p)
    name = p.name.lower()
    if p.is_dir():
        return "volume"  # a DICOM folder
    if name.endswith(".c3d"):
        return "c3d"
    if name.endswith((".glb", ".gltf")):
        return "gltf"
    if name.endswith(_VOLUME_SUFFIXES):
        return "volume"
    if name.endswith(_MESH_SUFFIXES):
        return "mesh"
    raise InputError(
        "unknown file type (expected .c3d, a DICOM folder, .nii/.nii.gz, .nrrd, .glb or a mesh)", p)


def inspect_path(path: str | os.PathLike, subject: str | None = None) -> dict[str, Any]:
    """Summarise one input file or folder.

    Parameters
    ----------
    path : path-like
        A C3D file, a DICOM folder (or one file of a series), a NIfTI or NRRD
        file, a ``.glb``, or a mesh file.
    subject : str, optional
        For C3D files holding several subjects, the one to summarise.

    Returns
    -------
    dict
        JSON-able; always has ``format`` and ``path``.
    """
    kind = kind_of_path(path)
    if kind == "c3d":
        from bonecap.io.c3d import c3d_summary

        return c3d_summary(path, subject=subject)
    if kind == "gltf":
        from bonecap.io.gltf import summarize_gltf

        return summarize_gltf(path)
    if kind == "mesh":
        from bonecap.io.mesh import read_mesh

        mesh = read_mesh(path)
        lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
        return {
            "format": "mesh", "path": os.fspath(path), "vertices": int(len(mesh.vertices)),
            "triangles": int(len(mesh.faces)), "bounds_min": lo.tolist(), "bounds_max": hi.tolist(),
            "units": "as stored (mesh files carry no unit)",
        }
    from bonecap.io.imaging import read_volumes, volume_summary

    volumes = read_volumes(path)
    return {"format": "volumes", "path": os.fspath(path), "series": [volume_summary(v) for v in volumes]}


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, (list, tuple)) and value and all(isinstance(v, (int, float)) for v in value):
        return "(" + ", ".join(_fmt(float(v)) if isinstance(v, float) else str(v) for v in value) + ")"
    if isinstance(value, (list, tuple)):
        return ", ".join(str(v) for v in value)
    if isinstance(value, dict):
        return ", ".join(f"{k}={_fmt(v)}" for k, v in value.items())
    return str(value)


def format_summary(summary: dict[str, Any], indent: str = "") -> str:
    """Human-readable lines for a summary from :func:`inspect_path`."""
    lines = []
    for key, value in summary.items():
        if key == "series" and isinstance(value, list):
            for n, series in enumerate(value, 1):
                lines.append(f"{indent}series {n}:")
                lines.append(format_summary(series, indent + "  "))
        elif isinstance(value, list) and value and isinstance(value[0], list):
            lines.append(f"{indent}{key}: " + "; ".join(_fmt(v) for v in value))
        else:
            lines.append(f"{indent}{key}: {_fmt(value)}")
    return "\n".join(lines)


def write_summaries(summaries: list[dict[str, Any]], out_dir: str | os.PathLike) -> list[Path]:
    """Write each summary as ``OUT_DIR/<input name>.summary.json`` (atomically)."""
    from bonecap.io.atomic import atomic_path

    written = []
    for summary in summaries:
        name = Path(str(summary["path"]).rstrip("/\\")).name or "input"
        target = Path(out_dir) / f"{name}.summary.json"
        with atomic_path(target) as tmp:
            tmp.write_text(json.dumps(summary, indent=2, default=str))
        written.append(target)
    return written
