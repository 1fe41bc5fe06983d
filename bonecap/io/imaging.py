"""DICOM series, NIfTI and NRRD <-> :class:`~bonecap.model.Volume`.

Every reader returns a :class:`~bonecap.model.Volume` whose ``affine`` maps
voxel indices ``(i, j, k, 1)`` to **LPS** millimetres (DICOM patient
coordinates: +x towards the patient's Left, +y Posterior, +z Superior), so that
later stages never need to know which file format a volume came from.

DICOM (classic single-frame series)
-----------------------------------
*Grouping.* Every file under the folder (recursively) that pydicom recognises
as DICOM (a ``DICM`` preamble) is looked at; other files (``DICOMDIR``,
``readme.txt``, thumbnails) are skipped silently, as are DICOM objects that
are not positioned images (reports, presentation states, screenshots without
``ImagePositionPatient``). Slices are grouped by ``SeriesInstanceUID``, then
split by echo (``EchoNumbers``/``EchoTime``): a multi-echo spin-echo series
such as the original knee MESE acquisition stores all eight echoes under one
series UID, at the same eight-fold repeated positions. A group that still
holds the same slice position more than once is then split by
``AcquisitionNumber``, ``TemporalPositionIdentifier`` and ``TriggerTime`` in
that order. Those three splits are applied only when positions repeat,
because some scanners (CT in particular) give every slice its own
acquisition number; splitting those would make one volume per slice.

*Slice order.* Slices are sorted along the slice normal
``n = row_cosine x column_cosine`` (from ``ImageOrientationPatient``) by the
projection ``z = ImagePositionPatient . n``, **never** by ``InstanceNumber``:
instance numbers are free-form (the shared knee series numbers its slices 1,
9, 17, ... because the original interleaved eight echoes) and are sometimes
reversed. ``k`` therefore always increases along ``+n``; the affine is
right-handed whenever the row and column cosines are orthogonal.

*Geometry.* The slice spacing comes from the positions, not from
``SliceThickness`` (which is the excitation thickness and may be smaller than
the spacing, as in the knee: 3 mm thick, 4 mm apart). A missing slice, uneven
spacing, two slices at the same position, mixed orientations, pixel spacings
or matrix sizes inside one group raise :class:`~bonecap.errors.DataError`
naming the problem (``"missing slice between z=... and z=... mm (spacing ...
mm elsewhere)"``, ``z`` measured along ``n``), rather than silently
resampling: a volume stacked over a gap is wrong by a whole slice from the gap
on. Two spacings agree when they differ by at most ``max(0.01 mm, 1 %)``.

``Volume.data[i, j, k]``: ``i`` is the column index (along a row), ``j`` the
row index, ``k`` the slice, so each ``pixel_array`` (rows, columns) is stored
transposed. The affine's columns are

- col 0: row direction cosine ``IOP[0:3]`` x column spacing ``PixelSpacing[1]``,
- col 1: column direction cosine ``IOP[3:6]`` x row spacing ``PixelSpacing[0]``,
- col 2: the step from one slice to the next, ``(IPP_last - IPP_first) / (K - 1)``,
- col 3: ``ImagePositionPatient`` of the first slice (the centre of voxel 0,0,0).

Direction cosines are renormalised to unit length (scanners print them with
about six digits). Pixel values are passed through the Modality LUT (rescale
slope/intercept, per slice since some vendors vary them) and returned as
``float32``: MR in scanner units, CT in Hounsfield units. Compressed transfer
syntaxes (JPEG, JPEG-LS, JPEG 2000, RLE) are decoded by pydicom's pixel
backends (pylibjpeg for JPEG/JPEG 2000). Enhanced multi-frame images are not
supported and raise :class:`~bonecap.errors.FormatError`.

The geometry is done here with pydicom rather than by highdicom's
``get_volume_from_series`` so that the error messages can name the exact gap
and the ``[i, j, k]`` axis order matches the rest of bonecap.

NIfTI
-----
Read with nibabel, which chooses the sform when its code is non-zero, else the
qform, else a scaled identity (recorded in ``metadata["affine_source"]``).
NIfTI world space is RAS, so ``affine_lps = diag(-1, -1, 1, 1) @ affine_ras``.
The file's axis order is kept (no reorientation). Spatial units in metres or
micrometres are converted to mm. Scaling (``scl_slope``/``scl_inter``) is
applied by nibabel; unscaled data keep their stored dtype (label maps stay
integer). A 4-D image is refused unless its extra dimensions have length 1.

NRRD
----
Read with pynrrd in Fortran index order, so ``data[i, j, k]`` follows the
file's axes and ``space directions`` (one vector per axis) become the affine's
columns and ``space origin`` its translation. The ``space`` field is honoured:
``left-posterior-superior``/``LPS`` is kept, ``right-anterior-superior``/``RAS``
is converted with ``diag(-1, -1, 1)``, ``left-anterior-superior``/``LAS`` with
``diag(1, -1, 1)``. A file without an anatomical space (none, ``scanner-xyz``,
``3D-right-handed``...) is taken as LPS and says so in
``metadata["space_assumed"]``.

Writers
-------
:func:`write_dicom_series` writes one classic single-frame file per ``k``
slice (see its docstring for the quantisation of float data to 16 bits),
:func:`write_nifti` writes RAS (``diag(-1, -1, 1, 1)`` again) with both sform
and qform set, :func:`write_nrrd` writes ``space: left-posterior-superior``.
All three write through :func:`bonecap.io.atomic.atomic_path`, so a failure
never leaves a partial output.
"""

from __future__ import annotations

import io
import math
import os
import zlib
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from bonecap.errors import DataError, FormatError, InputError
from bonecap.io.atomic import atomic_path
from bonecap.progress import progress
from bonecap.model import Volume

__all__ = [
    "read_dicom_series",
    "read_nifti",
    "read_nrrd",
    "read_volumes",
    "write_dicom_series",
    "write_nifti",
    "write_nrrd",
    "volume_summary",
    "TRANSFER_SYNTAXES",
]

#: RAS <-> LPS: the same matrix converts both ways.
_RAS_TO_LPS = np.diag([-1.0, -1.0, 1.0, 1.0])

#: Names accepted by :func:`write_dicom_series` for its ``transfer_syntax``.
TRANSFER_SYNTAXES = {
    "explicit_little": "1.2.840.10008.1.2.1",  # Explicit VR Little Endian
    "jpeg2000_lossless": "1.2.840.10008.1.2.4.90",  # JPEG 2000 Image Compression (Lossless Only)
}

# Keys used, in this order, to split a group whose slice positions repeat.
_REPEAT_KEYS = ("AcquisitionNumber", "TemporalPositionIdentifier", "TriggerTime")


def _spacing_tolerance(spacing: float) -> float:
    """How far two slice spacings (mm) may differ and still count as equal.

    1 % of the spacing, but at least 0.01 mm: positions are printed with a few
    decimals, so a fixed relative tolerance alone would be too strict for thin
    slices.
    """
    return max(0.01, 0.01 * abs(spacing))


# --------------------------------------------------------------------------- #
# DICOM reading
# --------------------------------------------------------------------------- #


@dataclass
class _Slice:
    """The header facts of one image file that the grouping needs."""

    path: Path
    ds: Any  # pydicom Dataset, read with stop_before_pixels
    position: np.ndarray  # ImagePositionPatient (3,)
    orientation: np.ndarray  # ImageOrientationPatient (6,)
    pixel_spacing: np.ndarray  # (row spacing, column spacing)
    matrix: tuple[int, int]  # (Rows, Columns)

    def get(self, keyword: str) -> Any:
        return _plain(self.ds.get(keyword))


def _plain(value: Any) -> Any:
    """A DICOM value as plain Python: numbers as int/float, multi-values as tuples."""
    if value is None:
        return None
    if isinstance(value, (list, tuple)) or type(value).__name__ == "MultiValue":
        items = tuple(_plain(v) for v in value)
        return items[0] if len(items) == 1 else items
    if isinstance(value, bytes):
        return value
    if isinstance(value, int):
        return int(value)
    if isinstance(value, float):
        return float(value)
    text = str(value)
    return text


def _is_dicom_file(path: Path) -> bool:
    """True when the file carries the DICOM Part 10 preamble (``DICM`` at byte 128)."""
    try:
        with open(path, "rb") as fh:
            fh.seek(128)
            return fh.read(4) == b"DICM"
    except OSError:
        return False


def _scan_dicom(folder: Path, recursive: bool, series_uid: str | None) -> list[_Slice]:
    """Read the headers of every DICOM image under ``folder``.

    Raises
    ------
    InputError
        When no DICOM file at all, or no positioned image, is found.
    FormatError
        When a file with a DICOM preamble cannot be parsed, or is multi-frame.
    """
    import pydicom
    from pydicom.errors import InvalidDicomError

    files = sorted(p for p in (folder.rglob("*") if recursive else folder.iterdir()) if p.is_file())
    n_dicom = 0
    skipped: dict[str, int] = defaultdict(int)
    slices: list[_Slice] = []
    for path in progress(files, desc=f"scan {folder.name}", unit="file"):
        try:
            ds = pydicom.dcmread(path, stop_before_pixels=True)
        except InvalidDicomError:
            continue  # not DICOM (readme, thumbnails...): skip silently
        except OSError as exc:
            raise InputError(f"cannot read file: {exc.strerror or exc}", path) from None
        except Exception as exc:  # a DICOM preamble followed by garbage
            raise FormatError(f"cannot parse DICOM file: {type(exc).__name__}: {exc}", path) from None
        n_dicom += 1
        if series_uid is not None and str(ds.get("SeriesInstanceUID", "")) != series_uid:
            continue
        if "Rows" not in ds or "Columns" not in ds:
            # DICOMDIR, structured reports, presentation states...
            skipped["not an image"] += 1
            continue
        if int(ds.get("NumberOfFrames", 1) or 1) > 1:
            raise FormatError(
                "enhanced multi-frame DICOM is not supported (convert it to NIfTI first, e.g. with dcm2niix)",
                path)
        if "ImagePositionPatient" not in ds or "ImageOrientationPatient" not in ds or "PixelSpacing" not in ds:
            skipped["image without ImagePositionPatient/ImageOrientationPatient/PixelSpacing"] += 1
            continue
        try:
            position = np.array([float(v) for v in ds.ImagePositionPatient], dtype=float)
            orientation = np.array([float(v) for v in ds.ImageOrientationPatient], dtype=float)
            spacing = np.array([float(v) for v in ds.PixelSpacing], dtype=float)
        except (TypeError, ValueError) as exc:
            raise FormatError(f"unreadable image geometry: {exc}", path) from None
        if position.shape != (3,) or orientation.shape != (6,) or spacing.shape != (2,):
            raise FormatError(
                f"malformed geometry: ImagePositionPatient has {position.size} values, "
                f"ImageOrientationPatient {orientation.size}, PixelSpacing {spacing.size}", path)
        slices.append(_Slice(path, ds, position, orientation, spacing, (int(ds.Rows), int(ds.Columns))))

    if n_dicom == 0:
        raise InputError(f"no DICOM files found ({len(files)} files looked at)", folder)
    if not slices:
        if series_uid is not None and not skipped:
            raise InputError(f"no DICOM image of series {series_uid}", folder)
        why = "; ".join(f"{n} {reason}" for reason, n in skipped.items())
        raise InputError(f"no positioned DICOM image slices among {n_dicom} DICOM files ({why})", folder)
    return slices


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _normal(orientation: np.ndarray) -> np.ndarray:
    """Unit slice normal: row cosine x column cosine."""
    return _unit(np.cross(orientation[:3], orientation[3:]))


def _split_repeats(group: list[_Slice], keys: Sequence[str]) -> list[list[_Slice]]:
    """Split ``group`` by ``keys`` (in order) only while slice positions repeat."""
    normal = _normal(group[0].orientation)
    z = np.sort([s.position @ normal for s in group])
    repeats = len(z) > 1 and bool(np.any(np.diff(z) < 1e-3))
    if not repeats or not keys:
        return [group]
    by_value: dict[Any, list[_Slice]] = defaultdict(list)
    for s in group:
        by_value[s.get(keys[0])].append(s)
    out: list[list[_Slice]] = []
    for sub in by_value.values():
        out.extend(_split_repeats(sub, keys[1:]))
    return out


def _uniform(values: Iterable[Any]) -> Any:
    """The common value of ``values``, or ``None`` when they differ."""
    values = list(values)
    first = values[0]
    return first if all(v == first for v in values) else None


def _fmt_mm(x: float) -> str:
    return f"{x:.2f}"


def _check_spacing(z: np.ndarray, names: list[str], folder: Path) -> float:
    """Check the sorted slice positions ``z`` are evenly spaced; return the spacing.

    Raises
    ------
    DataError
        Naming the first duplicate position, gap, or uneven step found.
    """
    diffs = np.diff(z)
    dup = np.flatnonzero(diffs < 1e-3)
    if dup.size:
        a = dup[0]
        raise DataError(
            f"two slices at the same position z={_fmt_mm(z[a])} mm ({names[a]} and {names[a + 1]}); "
            "mixed acquisitions that cannot be told apart", folder)
    # The usual step is the one most steps agree with (ties: the smallest, so
    # that with only [4, 8] the 8 is read as a missing slice, not the 4 as an
    # extra one).
    ordered = np.sort(diffs)
    tols = np.maximum(0.01, 0.01 * ordered)
    support = (np.searchsorted(ordered, ordered + tols, side="right")
               - np.searchsorted(ordered, ordered - tols, side="left"))
    ref = float(ordered[int(np.argmax(support))])
    tol = _spacing_tolerance(ref)
    regular = np.abs(diffs - ref) <= tol
    if regular.all():
        return float(np.mean(diffs))
    usual = float(np.median(diffs[regular]))
    tol = _spacing_tolerance(usual)
    bad = np.flatnonzero(~regular)
    a = bad[0]
    more = f"; {bad.size - 1} more irregular step(s)" if bad.size > 1 else ""
    where = (f"between z={_fmt_mm(z[a])} and z={_fmt_mm(z[a + 1])} mm "
             f"(spacing {usual:.4g} mm elsewhere; z along the slice normal; files {names[a]} and {names[a + 1]})")
    ratio = diffs[a] / usual
    n_missing = int(round(ratio)) - 1
    if n_missing >= 1 and abs(diffs[a] - (n_missing + 1) * usual) <= tol * (n_missing + 1):
        what = "missing slice" if n_missing == 1 else f"missing {n_missing} slices"
        raise DataError(f"{what} {where}{more}", folder)
    raise DataError(f"uneven slice spacing: {diffs[a]:.4g} mm {where}{more}", folder)


def _assemble(group: list[_Slice], folder: Path) -> Volume:
    """Turn one group of slices into a Volume (geometry checks, then pixels)."""
    import pydicom
    from pydicom.pixels import apply_modality_lut

    first = group[0]
    for s in group[1:]:
        if not np.allclose(s.orientation, first.orientation, atol=1e-4):
            raise DataError(
                f"mixed image orientations in one series ({first.path.name}: {np.round(first.orientation, 4).tolist()}, "
                f"{s.path.name}: {np.round(s.orientation, 4).tolist()})", folder)
        if not np.allclose(s.pixel_spacing, first.pixel_spacing, rtol=1e-4, atol=1e-5):
            raise DataError(
                f"mixed pixel spacings in one series ({first.path.name}: {first.pixel_spacing.tolist()} mm, "
                f"{s.path.name}: {s.pixel_spacing.tolist()} mm)", folder)
        if s.matrix != first.matrix:
            raise DataError(
                f"mixed image sizes in one series ({first.path.name}: {first.matrix[0]}x{first.matrix[1]}, "
                f"{s.path.name}: {s.matrix[0]}x{s.matrix[1]})", folder)

    row_dir = _unit(first.orientation[:3])
    col_dir = _unit(first.orientation[3:])
    normal = _normal(first.orientation)
    z_all = np.array([s.position @ normal for s in group])
    order = np.argsort(z_all, kind="stable")
    group = [group[o] for o in order]
    z = z_all[order]
    names = [s.path.name for s in group]
    positions = np.array([s.position for s in group])
    n = len(group)

    if n > 1:
        spacing = _check_spacing(z, names, folder)
        step = (positions[-1] - positions[0]) / (n - 1)
        # The in-plane part of the positions must also advance evenly (a
        # gantry tilt shears the stack, which the affine can hold; scattered
        # positions it cannot).
        off = np.linalg.norm(positions - (positions[0] + np.arange(n)[:, None] * step), axis=1)
        if off.max() > _spacing_tolerance(spacing):
            a = int(off.argmax())
            raise DataError(
                f"slice positions do not lie on a straight line: {names[a]} at z={_fmt_mm(z[a])} mm "
                f"is {off[a]:.3g} mm off", folder)
        spacing_assumed = False
    else:
        # One slice: no positions to measure a spacing from.
        thick = first.get("SpacingBetweenSlices") or first.get("SliceThickness") or 1.0
        step = normal * float(thick)
        spacing_assumed = True

    rows, cols = first.matrix
    affine = np.eye(4)
    affine[:3, 0] = row_dir * first.pixel_spacing[1]
    affine[:3, 1] = col_dir * first.pixel_spacing[0]
    affine[:3, 2] = step
    affine[:3, 3] = positions[0]

    data = np.empty((cols, rows, n), dtype=np.float32)
    syntaxes = []
    for k, s in enumerate(progress(group, desc="read slices", unit="slice")):
        ds = None
        try:
            ds = pydicom.dcmread(s.path)
            syntax = str(ds.file_meta.TransferSyntaxUID)
            pixels = ds.pixel_array
        except Exception as exc:
            ts = getattr(getattr(ds, "file_meta", None), "TransferSyntaxUID", None)
            ts_name = getattr(ts, "name", ts) or "unknown transfer syntax"
            raise FormatError(f"cannot decode pixel data ({ts_name}): {type(exc).__name__}: {exc}",
                              s.path) from None
        if pixels.shape != (rows, cols):
            raise DataError(f"pixel data of shape {pixels.shape} where {rows}x{cols} single-channel "
                            "pixels were expected (colour or multi-frame image)", s.path)
        data[:, :, k] = np.asarray(apply_modality_lut(pixels, ds), dtype=np.float32).T
        syntaxes.append(syntax)

    echo = first.get("EchoNumbers")
    metadata = {
        "format": "dicom",
        "modality": first.get("Modality"),
        "series_uid": first.get("SeriesInstanceUID"),
        "series_description": first.get("SeriesDescription") or "",
        "series_number": first.get("SeriesNumber"),
        "echo_number": _uniform(s.get("EchoNumbers") for s in group) if echo is not None else None,
        "echo_time": _uniform(s.get("EchoTime") for s in group),
        "acquisition_number": _uniform(s.get("AcquisitionNumber") for s in group),
        "temporal_position": _uniform(s.get("TemporalPositionIdentifier") for s in group),
        "source_files": [str(s.path) for s in group],
        "instance_numbers": [s.get("InstanceNumber") for s in group],
        "transfer_syntax": _uniform(syntaxes) or sorted(set(syntaxes)),
        "slice_thickness": first.get("SliceThickness"),
        "spacing_between_slices": first.get("SpacingBetweenSlices"),
        "slice_spacing_assumed": spacing_assumed,
        "frame_of_reference_uid": first.get("FrameOfReferenceUID"),
        "study_uid": first.get("StudyInstanceUID"),
        "manufacturer": first.get("Manufacturer"),
    }
    return Volume(data, affine, metadata)


def _sort_key(v: Volume) -> tuple:
    def part(x: Any) -> tuple:
        if x is None:
            return (1, 0.0)
        if isinstance(x, tuple):
            x = x[0]
        try:
            return (0, float(x))
        except (TypeError, ValueError):
            return (0, 0.0)

    m = v.metadata
    return (part(m.get("series_number")), part(m.get("echo_number")), part(m.get("echo_time")),
            part(m.get("acquisition_number")), part(m.get("temporal_position")), str(m.get("series_uid")))


def read_dicom_series(folder: str | os.PathLike, *, series_uid: str | None = None,
                      recursive: bool = True) -> list[Volume]:
    """Read every classic DICOM image series under a folder.

    Parameters
    ----------
    folder : path-like
        Folder searched for DICOM files (recursively by default). Files that
        are not DICOM are skipped silently.
    series_uid : str, optional
        Keep only the slices of this ``SeriesInstanceUID``.
    recursive : bool
        Also look in sub-folders.

    Returns
    -------
    list of Volume
        One per series, echo and (when positions repeat) acquisition or
        temporal position, sorted by series number then echo. Data are
        ``float32`` after rescale slope/intercept; ``data[i, j, k]`` with ``i``
        the column, ``j`` the row, ``k`` the slice along the normal (see the
        module docstring for the affine). ``metadata``: ``format``
        (``"dicom"``), ``modality``, ``series_uid``, ``series_description``,
        ``series_number``, ``echo_number``, ``echo_time`` (ms),
        ``acquisition_number`` and ``temporal_position`` (``None`` when they
        vary across the volume's slices), ``source_files`` and
        ``instance_numbers`` (both in ``k`` order), ``transfer_syntax`` (UID
        string), ``slice_thickness`` and ``spacing_between_slices`` (mm, as
        stored; the true spacing is the affine's), ``slice_spacing_assumed``
        (True for a single slice, whose step is taken from the header),
        ``frame_of_reference_uid``, ``study_uid``, ``manufacturer``.

    Raises
    ------
    InputError
        ``folder`` does not exist or holds no DICOM image.
    FormatError
        A DICOM file cannot be parsed or its pixels decoded, or it is an
        enhanced multi-frame image.
    DataError
        A series has a missing slice, uneven spacing, repeated positions, or
        mixed orientations, pixel spacings or matrix sizes.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError("no such folder" if not folder.exists() else "not a folder", folder)
    slices = _scan_dicom(folder, recursive, series_uid)

    # Series, then echo: always distinct images even at identical positions.
    groups: dict[tuple, list[_Slice]] = defaultdict(list)
    for s in slices:
        echo_time = s.get("EchoTime")
        echo_time = round(float(echo_time), 3) if isinstance(echo_time, (int, float)) else echo_time
        groups[(str(s.get("SeriesInstanceUID") or ""), s.get("EchoNumbers"), echo_time)].append(s)

    volumes = []
    for group in groups.values():
        # Orientation is checked per group in _assemble; splitting only looks
        # at positions, so it needs one normal, taken from the first slice.
        for sub in _split_repeats(group, _REPEAT_KEYS):
            volumes.append(_assemble(sub, folder))
    volumes.sort(key=_sort_key)
    return volumes


# --------------------------------------------------------------------------- #
# NIfTI and NRRD reading
# --------------------------------------------------------------------------- #


def _squeeze_to_3d(data: np.ndarray, path: Path) -> np.ndarray:
    """Drop trailing length-1 dimensions beyond the third; refuse real 4-D data."""
    while data.ndim > 3 and data.shape[-1] == 1:
        data = data[..., 0]
    if data.ndim > 3:
        raise DataError(f"{data.ndim}-D image of shape {data.shape}: only 3-D volumes are supported "
                        "(extract one volume first)", path)
    while data.ndim < 3:
        data = data[..., np.newaxis]
    return data


def read_nifti(path: str | os.PathLike) -> Volume:
    """Read a NIfTI-1/2 file (``.nii`` or ``.nii.gz``).

    Parameters
    ----------
    path : path-like

    Returns
    -------
    Volume
        ``data`` in the file's own axis order (scaled by ``scl_slope`` and
        ``scl_inter`` when those are set, else in the stored dtype); ``affine``
        = ``diag(-1, -1, 1, 1) @`` nibabel's chosen RAS affine, in mm.
        ``metadata``: ``format`` ``"nifti"``, ``source_files``,
        ``affine_source`` (``"sform"``, ``"qform"`` or ``"none"``),
        ``spatial_unit`` as stored.

    Raises
    ------
    InputError
        The file does not exist.
    FormatError
        nibabel cannot read it as NIfTI.
    DataError
        It is 4-D (or more) with more than one volume.
    """
    import nibabel as nib

    path = Path(path)
    if not path.is_file():
        raise InputError("no such file", path)
    try:
        img = nib.load(path)
    except Exception as exc:  # ImageFileError, gzip/zlib errors, header errors
        raise FormatError(f"not a readable NIfTI file: {type(exc).__name__}: {exc}", path) from None
    if not isinstance(img, (nib.Nifti1Image, nib.Nifti2Image)):
        raise FormatError(f"not a NIfTI image (nibabel read it as {type(img).__name__})", path)
    header = img.header
    try:
        if img.dataobj.slope != 1 or img.dataobj.inter != 0:
            data = np.asarray(img.get_fdata(dtype=np.float32))
        else:
            data = np.asarray(img.dataobj)
    except Exception as exc:  # truncated file
        raise FormatError(f"cannot read NIfTI voxel data: {type(exc).__name__}: {exc}", path) from None
    data = _squeeze_to_3d(data, path)

    if header.get_sform(coded=True)[1]:
        source = "sform"
    elif header.get_qform(coded=True)[1]:
        source = "qform"
    else:
        source = "none"  # nibabel falls back to voxel sizes only
    unit = header.get_xyzt_units()[0]
    scale = {"meter": 1000.0, "micron": 1e-3}.get(unit, 1.0)  # "mm" and "unknown" stay as is
    affine_ras = np.array(img.affine, dtype=float)
    affine_ras[:3, :] *= scale
    affine = _RAS_TO_LPS @ affine_ras
    metadata = {
        "format": "nifti",
        "source_files": [str(path)],
        "affine_source": source,
        "spatial_unit": unit,
        "description": header["descrip"].item().decode("latin-1", "replace").strip("\x00 "),
    }
    return Volume(data, affine, metadata)


# NRRD space name (lower case) -> diagonal that maps that space to LPS.
_NRRD_SPACES = {
    "left-posterior-superior": (1.0, 1.0, 1.0),
    "lps": (1.0, 1.0, 1.0),
    "right-anterior-superior": (-1.0, -1.0, 1.0),
    "ras": (-1.0, -1.0, 1.0),
    "left-anterior-superior": (1.0, -1.0, 1.0),
    "las": (1.0, -1.0, 1.0),
}
_NRRD_TIME_SPACES = {"right-anterior-superior-time", "left-anterior-superior-time",
                     "left-posterior-superior-time", "rast", "last", "lpst",
                     "scanner-xyz-time", "3d-right-handed-time", "3d-left-handed-time"}


def read_nrrd(path: str | os.PathLike) -> Volume:
    """Read a NRRD file (``.nrrd``, or a ``.nhdr`` header with its data file).

    Parameters
    ----------
    path : path-like

    Returns
    -------
    Volume
        ``data`` in the file's axis order and dtype; ``affine`` columns are the
        ``space directions`` converted to LPS, translation the ``space origin``
        (zero when absent). Without ``space directions``, ``spacings`` (or 1 mm)
        give an axis-aligned grid. ``metadata``: ``format`` ``"nrrd"``,
        ``source_files``, ``space`` as stored (``None`` when absent),
        ``space_assumed`` (True when the file had no anatomical space and LPS
        was assumed).

    Raises
    ------
    InputError
        The file does not exist.
    FormatError
        pynrrd cannot parse it.
    DataError
        More than 3 spatial axes, a non-spatial axis longer than 1, or a
        time-varying space.
    """
    import nrrd

    path = Path(path)
    if not path.is_file():
        raise InputError("no such file", path)
    try:
        data, header = nrrd.read(str(path), index_order="F")
    except Exception as exc:  # nrrd.NRRDError, missing detached data file, bad gzip
        raise FormatError(f"not a readable NRRD file: {type(exc).__name__}: {exc}", path) from None

    space = header.get("space")
    key = str(space).lower() if space is not None else None
    if key in _NRRD_TIME_SPACES:
        raise DataError(f"time-varying NRRD space {space!r} is not supported (only 3-D volumes)", path)
    flip = _NRRD_SPACES.get(key) if key is not None else None
    space_assumed = flip is None
    if flip is None:
        flip = (1.0, 1.0, 1.0)
    M = np.diag(flip)

    directions = header.get("space directions")
    if directions is not None:
        directions = np.asarray(directions, dtype=float)
        spatial = np.flatnonzero(np.isfinite(directions).all(axis=1))  # 'none' rows are NaN
        if directions.shape[1] != 3 or spatial.size != 3:
            raise DataError(f"NRRD with {spatial.size} spatial axes in a {directions.shape[1]}-D space: "
                            "only 3-D volumes are supported", path)
        other = [a for a in range(data.ndim) if a not in spatial]
        if any(data.shape[a] != 1 for a in other):
            raise DataError(f"NRRD of shape {data.shape} has non-spatial axes longer than 1 "
                            f"(kinds {header.get('kinds')}): only scalar 3-D volumes are supported", path)
        if other:
            sizes = [data.shape[a] for a in spatial]
            data = np.transpose(data, list(spatial) + other).reshape(sizes)
        linear = M @ directions[spatial].T  # columns = axis vectors in LPS
    else:
        data = _squeeze_to_3d(data, path)
        spacings = np.asarray(header.get("spacings", [1.0, 1.0, 1.0]), dtype=float)[:3]
        spacings = np.where(np.isfinite(spacings), spacings, 1.0)
        linear = M @ np.diag(spacings)
    if data.ndim != 3:
        data = _squeeze_to_3d(data, path)
    origin = header.get("space origin")
    origin = np.zeros(3) if origin is None else np.asarray(origin, dtype=float)
    if origin.shape != (3,) or not np.isfinite(origin).all():
        origin = np.zeros(3)
    affine = np.eye(4)
    affine[:3, :3] = linear
    affine[:3, 3] = M @ origin
    metadata = {
        "format": "nrrd",
        "source_files": [str(path)],
        "space": space,
        "space_assumed": space_assumed,
        "nrrd_type": header.get("type"),
    }
    return Volume(data, affine, metadata)


# --------------------------------------------------------------------------- #
# Dispatch
# --------------------------------------------------------------------------- #


def read_volumes(path: str | os.PathLike) -> list[Volume]:
    """Read whatever imaging input ``path`` names.

    Parameters
    ----------
    path : path-like
        A folder (every DICOM series in it, recursively); a ``.nii``,
        ``.nii.gz``, ``.nrrd`` or ``.nhdr`` file; or one DICOM file (by
        ``.dcm``/``.ima`` extension or by its ``DICM`` preamble), which reads
        that file's whole series from the files beside it.

    Returns
    -------
    list of Volume

    Raises
    ------
    InputError
        Missing path or unknown format; see the individual readers for the rest.
    """
    import pydicom

    path = Path(path)
    if path.is_dir():
        return read_dicom_series(path)
    if not path.exists():
        raise InputError("no such file or folder", path)
    name = path.name.lower()
    if name.endswith((".nii", ".nii.gz")):
        return [read_nifti(path)]
    if name.endswith((".nrrd", ".nhdr")):
        return [read_nrrd(path)]
    if name.endswith((".dcm", ".ima", ".dicom")) or _is_dicom_file(path):
        try:
            uid = str(pydicom.dcmread(path, stop_before_pixels=True).get("SeriesInstanceUID", ""))
        except Exception as exc:
            raise FormatError(f"not a readable DICOM file: {type(exc).__name__}: {exc}", path) from None
        # The series' other slices sit beside the file; only that folder is
        # searched so that a file at the top of a large archive stays cheap.
        return read_dicom_series(path.parent, series_uid=uid, recursive=False)
    raise InputError("unknown image format (expected a DICOM folder or file, .nii, .nii.gz, .nrrd or .nhdr)",
                     path)


# --------------------------------------------------------------------------- #
# Writers
# --------------------------------------------------------------------------- #


def _orthonormal_directions(affine: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Column norms and unit columns of ``affine[:3, :3]``; ValueError unless orthogonal."""
    linear = np.asarray(affine, dtype=float)[:3, :3]
    spacing = np.linalg.norm(linear, axis=0)
    if not np.all(spacing > 0) or not np.all(np.isfinite(linear)):
        raise ValueError(f"affine has a zero or non-finite voxel axis: spacing {spacing.tolist()}")
    directions = linear / spacing
    gram = directions.T @ directions
    if np.abs(gram - np.eye(3)).max() > 1e-6:
        raise ValueError("DICOM needs orthogonal voxel axes; the affine's direction cosines are not "
                         f"orthogonal (dot products {np.round(gram[np.triu_indices(3, 1)], 6).tolist()})")
    return spacing, directions


def _ds(x: float):
    """A DICOM decimal string (at most 16 characters) for ``x``."""
    from pydicom.valuerep import DSfloat

    return DSfloat(float(x), auto_format=True)


def _quantise(data: np.ndarray, rescale: bool) -> tuple[np.ndarray, float, float]:
    """Map ``data`` to 16-bit integers; return ``(stored, slope, intercept)``.

    Integer-valued data that fit ``uint16`` or ``int16`` are stored exactly
    with slope 1 and intercept 0. Anything else (with ``rescale``) is spread
    over the full ``uint16`` range: ``intercept = min``, ``slope = (max -
    min) / 65535``, ``stored = round((value - intercept) / slope)``, so the
    read-back error is at most ``slope / 2``. Slope and intercept are first
    rounded to the 16-character decimal strings DICOM stores, and the stored
    integers computed from those rounded values, so the error bound holds for
    what a reader sees.
    """
    values = np.asarray(data)
    if values.dtype == bool:
        values = values.astype(np.uint8)
    if not np.issubdtype(values.dtype, np.number) or np.iscomplexobj(values):
        raise ValueError(f"cannot write {values.dtype} data as DICOM pixels")
    if not np.all(np.isfinite(values)):
        raise ValueError("cannot write NaN or infinite values as DICOM pixels")
    lo = float(values.min())
    hi = float(values.max())
    integral = np.issubdtype(values.dtype, np.integer) or bool(np.all(values == np.round(values)))
    if integral and lo >= 0 and hi <= 65535:
        return values.astype(np.uint16), 1.0, 0.0
    if integral and lo >= -32768 and hi <= 32767:
        return values.astype(np.int16), 1.0, 0.0
    if not rescale:
        raise ValueError(f"values in [{lo}, {hi}] are not 16-bit integers; pass rescale=True to quantise")
    intercept = float(_ds(lo))
    slope = float(_ds((hi - lo) / 65535.0)) if hi > lo else 1.0
    stored = np.rint((values.astype(np.float64) - intercept) / slope)
    return np.clip(stored, 0, 65535).astype(np.uint16), slope, intercept


_SOP_CLASSES = {
    "MR": "1.2.840.10008.5.1.4.1.1.4",  # MR Image Storage
    "CT": "1.2.840.10008.5.1.4.1.1.2",  # CT Image Storage
}
_SECONDARY_CAPTURE = "1.2.840.10008.5.1.4.1.1.7"


def write_dicom_series(volume: Volume, folder: str | os.PathLike, *, series_description: str = "",
                       modality: str = "MR", transfer_syntax: str = "explicit_little",
                       series_uid: str | None = None, rescale: bool = True, series_number: int = 1,
                       study_uid: str | None = None, frame_of_reference_uid: str | None = None) -> list[Path]:
    """Write a volume as a classic single-frame DICOM series, one file per ``k`` slice.

    Parameters
    ----------
    volume : Volume
        Its affine must have orthogonal axes (any rotation, anisotropic
        spacing). Slice ``k`` is written at ``ImagePositionPatient = affine @
        (0, 0, k, 1)``; a left-handed affine (``k`` against the row x column
        normal) is therefore read back with ``k`` reversed but the same world
        position for every voxel. ``metadata`` ``echo_number``, ``echo_time``,
        ``acquisition_number`` and ``slice_thickness`` are written when set.
    folder : path-like
        Output folder, written as a whole (an existing folder is replaced).
    series_description : str
    modality : str
        ``"MR"`` and ``"CT"`` use their image storage SOP classes, anything
        else Secondary Capture.
    transfer_syntax : {"explicit_little", "jpeg2000_lossless"}
        JPEG 2000 lossless is encoded by pylibjpeg-openjpeg through
        :meth:`pydicom.dataset.Dataset.compress`.
    series_uid, study_uid, frame_of_reference_uid : str, optional
        New UIDs (:func:`pydicom.uid.generate_uid`) when not given.
    rescale : bool
        Allow quantising non-integer data (see Notes). With ``False``, data
        must be integers fitting 16 bits and no rescale is written.
    series_number : int

    Returns
    -------
    list of pathlib.Path
        The files written, in ``k`` order (``IM00001.dcm``...).

    Raises
    ------
    ValueError
        Unknown transfer syntax, non-orthogonal axes, NaN/inf data,
        non-integer data with ``rescale=False``, or slices smaller than
        32x32 for JPEG 2000 (pylibjpeg-openjpeg's fixed 6 resolutions).

    Notes
    -----
    Pixels are 16-bit. Integer data within ``uint16``/``int16`` are stored
    exactly (slope 1, intercept 0). Other data are quantised over the whole
    ``uint16`` range with ``RescaleIntercept = min`` and ``RescaleSlope =
    (max - min) / 65535``, so a value read back differs by at most
    ``RescaleSlope / 2``; that step is returned in every file's
    ``RescaleSlope``. Geometry is written as decimal strings of at most 16
    characters, about 1e-12 mm of rounding.
    """
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import PYDICOM_IMPLEMENTATION_UID, UID, generate_uid

    if transfer_syntax not in TRANSFER_SYNTAXES:
        raise ValueError(f"unknown transfer_syntax {transfer_syntax!r}; expected one of {sorted(TRANSFER_SYNTAXES)}")
    syntax = UID(TRANSFER_SYNTAXES[transfer_syntax])
    if transfer_syntax == "jpeg2000_lossless" and min(volume.shape[:2]) < 32:
        # pylibjpeg-openjpeg always uses 6 wavelet resolutions, which needs
        # 2**5 pixels along each side; OpenJPEG fails with an opaque message.
        raise ValueError(f"JPEG 2000 needs slices of at least 32x32 pixels, got {volume.shape[0]}x{volume.shape[1]}")
    spacing, directions = _orthonormal_directions(volume.affine)
    stored, slope, intercept = _quantise(volume.data, rescale)
    signed = stored.dtype == np.int16

    I, J, K = volume.shape
    row_dir, col_dir = directions[:, 0], directions[:, 1]
    normal = np.cross(row_dir, col_dir)
    step = volume.affine[:3, 2]
    origin = volume.affine[:3, 3]
    meta = volume.metadata
    sop_class = UID(_SOP_CLASSES.get(modality.upper(), _SECONDARY_CAPTURE))
    series_uid = series_uid or generate_uid()
    study_uid = study_uid or generate_uid()
    frame_of_reference_uid = frame_of_reference_uid or generate_uid()
    thickness = meta.get("slice_thickness") or spacing[2]
    lo, hi = float(stored.min()) * slope + intercept, float(stored.max()) * slope + intercept

    folder = Path(folder)
    names = [f"IM{k + 1:05d}.dcm" for k in range(K)]

    def header(k: int, sop_uid: str) -> tuple[Dataset, FileMetaDataset]:
        fm = FileMetaDataset()
        fm.MediaStorageSOPClassUID = sop_class
        fm.MediaStorageSOPInstanceUID = sop_uid
        fm.TransferSyntaxUID = UID(TRANSFER_SYNTAXES["explicit_little"])
        fm.ImplementationClassUID = PYDICOM_IMPLEMENTATION_UID
        ds = Dataset()
        ds.file_meta = fm
        ds.SpecificCharacterSet = "ISO_IR 100"
        ds.ImageType = ["DERIVED", "SECONDARY"]
        ds.SOPClassUID = sop_class
        ds.SOPInstanceUID = sop_uid
        ds.Modality = modality
        ds.SeriesDescription = series_description
        ds.Manufacturer = "bonecap"
        ds.PatientName = str(meta.get("patient_name", ""))
        ds.PatientID = str(meta.get("patient_id", ""))
        ds.StudyInstanceUID = study_uid
        ds.SeriesInstanceUID = series_uid
        ds.FrameOfReferenceUID = frame_of_reference_uid
        ds.SeriesNumber = int(series_number)
        ds.InstanceNumber = k + 1
        ds.PositionReferenceIndicator = ""
        if modality.upper() == "MR":
            ds.ScanningSequence = "RM"  # research mode: a synthetic or derived image
            ds.SequenceVariant = "NONE"
            ds.MRAcquisitionType = "3D"
        if meta.get("echo_number") is not None:
            ds.EchoNumbers = meta["echo_number"]
        if meta.get("echo_time") is not None:
            ds.EchoTime = _ds(meta["echo_time"])
        if meta.get("acquisition_number") is not None:
            ds.AcquisitionNumber = int(meta["acquisition_number"])
        position = origin + k * step
        ds.ImagePositionPatient = [_ds(v) for v in position]
        ds.ImageOrientationPatient = [_ds(v) for v in np.concatenate([row_dir, col_dir])]
        ds.PixelSpacing = [_ds(spacing[1]), _ds(spacing[0])]  # (between rows, between columns)
        ds.SliceThickness = _ds(thickness)
        ds.SpacingBetweenSlices = _ds(spacing[2])
        ds.SliceLocation = _ds(position @ normal)
        ds.SamplesPerPixel = 1
        ds.PhotometricInterpretation = "MONOCHROME2"
        ds.Rows = J
        ds.Columns = I
        ds.BitsAllocated = 16
        ds.BitsStored = 16
        ds.HighBit = 15
        ds.PixelRepresentation = 1 if signed else 0
        if rescale:
            ds.RescaleIntercept = _ds(intercept)
            ds.RescaleSlope = _ds(slope)
            ds.RescaleType = "HU" if modality.upper() == "CT" else "US"
        ds.WindowCenter = _ds((lo + hi) / 2)
        ds.WindowWidth = _ds(max(hi - lo, 1.0))
        return ds, fm

    def plane(k: int) -> np.ndarray:
        p = np.ascontiguousarray(stored[:, :, k].T)  # (rows = j, columns = i)
        return p.astype(p.dtype.newbyteorder("<"), copy=False)

    with atomic_path(folder, directory=True) as tmp:
        if syntax != UID(TRANSFER_SYNTAXES["explicit_little"]):
            for k in range(K):
                ds, fm = header(k, generate_uid())
                px = plane(k)
                ds.PixelData = px.tobytes()
                ds.compress(syntax, px, encoding_plugin="pylibjpeg", generate_instance_uid=False)
                ds.save_as(tmp / names[k], enforce_file_format=True)
        else:
            # Uncompressed: every slice's file is the first one's but for four elements (the SOP
            # instance UID, the instance number, the position and the slice location), the file
            # meta (which repeats the SOP instance UID) and the pixels. The elements that do not
            # change are encoded once, by pydicom, in the order write_dataset writes them (tags
            # ascending), and each file is those bytes with the changing elements encoded in
            # between: ~0.9 ms a file instead of ~1.7 ms for a dataset written whole (re-encoding its
            # ~45 elements was most of a series' time). The bytes are those of a dataset built from
            # scratch and written by dcmwrite (tests/test_phantom_mri.py checks it).
            from pydicom.dataelem import DataElement
            from pydicom.filebase import DicomBytesIO
            from pydicom.filewriter import write_data_element, write_file_meta_info
            from pydicom.tag import Tag

            uids = [generate_uid() for _ in range(K)]
            ds0, fm = header(0, uids[0])
            encodings = ds0.SpecificCharacterSet

            def encoded(write) -> bytes:
                fp = DicomBytesIO()
                fp.is_implicit_VR, fp.is_little_endian = False, True
                write(fp)
                return fp.getvalue()

            changing = [Tag(t) for t in ("SOPInstanceUID", "InstanceNumber", "ImagePositionPatient", "SliceLocation")]
            # the constant bytes before each changing element, and after the last one
            gaps: list[bytes] = []
            run: list = []
            for tag in sorted(ds0.keys()):
                if tag in changing:
                    gaps.append(encoded(lambda fp: [write_data_element(fp, e, encodings) for e in run]))
                    run = []
                else:
                    run.append(ds0[tag])
            gaps.append(encoded(lambda fp: [write_data_element(fp, e, encodings) for e in run]))
            assert len(gaps) == len(changing) + 1
            # PixelData (7FE0,0010) sorts after every element of the header: its tag, VR and length
            # are the same for every slice (OW: 16-bit pixels), then the plane's bytes
            pixel_head = encoded(lambda fp: write_data_element(
                fp, DataElement(0x7FE00010, "OW", plane(0).tobytes()), encodings))[:12]
            for k in range(K):
                position = origin + k * step
                fm.MediaStorageSOPInstanceUID = uids[k]
                values = (uids[k], k + 1, [_ds(v) for v in position], _ds(position @ normal))
                parts = [b"\x00" * 128 + b"DICM", encoded(lambda fp: write_file_meta_info(fp, fm)), gaps[0]]
                for tag, value, gap in zip(changing, values, gaps[1:]):
                    elem = DataElement(tag, ds0[tag].VR, value)
                    parts += [encoded(lambda fp: write_data_element(fp, elem, encodings)), gap]
                parts += [pixel_head, plane(k).tobytes()]
                _write_slice(tmp / names[k], parts)
    return [folder / name for name in names]


def _write_slice(path: Path, parts: list[bytes]) -> None:
    """One DICOM file from its encoded parts (a seam for tests of failed writes)."""
    with open(path, "wb") as f:
        f.writelines(parts)


def _nifti_ready(data: np.ndarray) -> np.ndarray:
    """Data in a dtype NIfTI-1 holds without nibabel's int64 refusal."""
    data = np.asarray(data)
    if data.dtype == bool:
        return data.astype(np.uint8)
    if data.dtype in (np.int64, np.uint64):
        info = np.iinfo(np.int32)
        if data.size == 0 or (data.min() >= info.min and data.max() <= info.max):
            return data.astype(np.int32)
        return data.astype(np.float64)
    return data


def write_nifti(volume: Volume, path: str | os.PathLike) -> Path:
    """Write a volume as NIfTI-1 (``.nii``, or gzipped ``.nii.gz``).

    Parameters
    ----------
    volume : Volume
    path : path-like
        Must end in ``.nii`` or ``.nii.gz``.

    Returns
    -------
    pathlib.Path

    Raises
    ------
    ValueError
        Another extension.

    Notes
    -----
    The RAS affine ``diag(-1, -1, 1, 1) @ volume.affine`` goes in the sform
    (code 1, scanner), and in the qform too when the axes are orthogonal (a
    qform cannot hold shear). Units are set to mm. The data dtype is kept
    (booleans become uint8, int64 becomes int32 when it fits); note that
    nibabel stores the sform as float32 (about 1e-5 mm at 100 mm).
    """
    from nibabel.fileholders import FileHolder

    path = Path(path)
    name = path.name.lower()
    if not name.endswith((".nii", ".nii.gz")):
        raise ValueError(f"NIfTI path must end in .nii or .nii.gz: {path}")
    img = _nifti_image(_nifti_ready(volume.data), volume.affine)
    # nibabel writes the header, then the data slab by slab: gzipped as it comes, only the
    # compressed bytes are held (for a whole-body label grid ~0.5 MB instead of an encoded
    # copy of the volume plus its gzip, ~100 MB more). The bytes are those of
    # gzip.compress(img.to_bytes(), compresslevel=6, mtime=0): mtime 0, so the same volume
    # always gives the same file.
    chunks: list[bytes] = []
    stream = _GzipStream(chunks) if name.endswith(".gz") else _ForwardStream(chunks)
    img.to_file_map({"image": FileHolder(fileobj=stream), "header": FileHolder(fileobj=stream)})
    stream.finish()
    with atomic_path(path) as tmp:
        tmp.write_bytes(b"".join(chunks))
    return path


def _nifti_image(data, affine: np.ndarray):
    """The Nifti1Image :func:`write_nifti` writes: RAS sform (and qform when orthogonal), mm."""
    import nibabel as nib

    affine_ras = _RAS_TO_LPS @ affine
    img = nib.Nifti1Image(data, affine_ras)
    img.set_sform(affine_ras, code=1)
    try:
        _orthonormal_directions(affine)
        img.set_qform(affine_ras, code=1)
    except ValueError:
        img.set_qform(None, code=0)
    img.header.set_xyzt_units(xyz="mm")
    return img


def _write_nifti_slabs(affine: np.ndarray, shape: tuple[int, int, int], dtype, slabs: Iterable[np.ndarray],
                       path: str | os.PathLike) -> Path:
    """:func:`write_nifti` of a volume given as consecutive ``k`` slabs, never held whole.

    ``slabs`` yields arrays ``(I, J, k_n)`` of ``dtype`` whose ``k_n`` add up to ``shape[2]``.
    NIfTI stores ``i`` fastest and ``k`` slowest, so each slab's Fortran-order bytes are a
    contiguous stretch of the file; the file is byte for byte what :func:`write_nifti` writes
    for the whole volume (the header is nibabel's for a placeholder of the same shape and dtype).
    """
    from nibabel.fileholders import FileHolder

    path = Path(path)
    name = path.name.lower()
    if not name.endswith((".nii", ".nii.gz")):
        raise ValueError(f"NIfTI path must end in .nii or .nii.gz: {path}")
    dtype = np.dtype(dtype)
    shape = tuple(int(n) for n in shape)
    placeholder = np.broadcast_to(np.zeros((), dtype), shape)      # no memory
    img = _nifti_image(placeholder, affine)
    chunks: list[bytes] = []
    stream = _GzipStream(chunks) if name.endswith(".gz") else _ForwardStream(chunks)
    header = _HeaderOnly(stream)
    img.to_file_map({"image": FileHolder(fileobj=header), "header": FileHolder(fileobj=header)})
    k = 0
    for slab in slabs:
        slab = np.asarray(slab)
        if slab.dtype != dtype or slab.shape[:2] != shape[:2] or slab.ndim != 3:
            raise ValueError(f"slab {slab.shape} {slab.dtype} does not fit a {shape} {dtype} volume")
        stream.write(np.asfortranarray(slab).tobytes(order="F"))
        k += slab.shape[2]
    if k != shape[2]:
        raise ValueError(f"slabs hold {k} slices, the volume {shape[2]}")
    stream.finish()
    with atomic_path(path) as tmp:
        tmp.write_bytes(b"".join(chunks))
    return path


class _ForwardStream(io.RawIOBase):
    """A write-only, forward-only stream into a list of byte chunks that counts what it wrote
    (for nibabel's ``seek_tell``, which then checks the position instead of seeking)."""

    def __init__(self, chunks: list) -> None:
        super().__init__()
        self.chunks = chunks
        self.pos = 0

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return False

    def tell(self) -> int:
        return self.pos

    def seek(self, offset: int, whence: int = 0) -> int:
        if whence == 0 and offset == self.pos:
            return self.pos
        raise OSError("forward-only stream")

    def _put(self, b) -> None:
        self.chunks.append(bytes(b))

    def write(self, b) -> int:
        n = memoryview(b).nbytes
        self._put(b)
        self.pos += n
        return n

    def finish(self) -> None:
        pass


class _HeaderOnly(io.RawIOBase):
    """Passes what nibabel writes before it moves to the data offset (the header and its
    extension flag) to ``stream`` and drops the rest (the placeholder data)."""

    def __init__(self, stream: "_ForwardStream") -> None:
        super().__init__()
        self.stream, self.header_done, self.pos = stream, False, 0

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return False

    def tell(self) -> int:
        return self.pos

    def seek(self, offset: int, whence: int = 0) -> int:
        if whence == 0 and offset == self.pos:
            self.header_done = self.header_done or offset > 0   # the seek to the data offset
            return self.pos
        raise OSError("forward-only stream")

    def write(self, b) -> int:
        n = memoryview(b).nbytes
        if not self.header_done:
            self.stream.write(b)
        self.pos += n
        return n


class _GzipStream(_ForwardStream):
    """:class:`_ForwardStream` through zlib's gzip container, level 6, mtime 0 (the bytes of
    ``gzip.compress(data, 6, mtime=0)``, which is ``zlib.compress(data, 6, wbits=31)``)."""

    def __init__(self, chunks: list) -> None:
        super().__init__(chunks)
        self.z = zlib.compressobj(6, zlib.DEFLATED, 31)

    def _put(self, b) -> None:
        self.chunks.append(self.z.compress(b))

    def finish(self) -> None:
        self.chunks.append(self.z.flush())


def write_nrrd(volume: Volume, path: str | os.PathLike) -> Path:
    """Write a volume as an attached-header, gzip-encoded NRRD (``.nrrd``).

    Parameters
    ----------
    volume : Volume
    path : path-like
        Must end in ``.nrrd`` (a detached ``.nhdr`` would need two files
        renamed together, which cannot be done atomically).

    Returns
    -------
    pathlib.Path

    Raises
    ------
    ValueError
        Another extension.

    Notes
    -----
    ``space: left-posterior-superior``; ``space directions`` are the affine's
    columns and ``space origin`` its translation, written by pynrrd at full
    double precision; the data dtype is kept (booleans become uint8).
    """
    import nrrd

    path = Path(path)
    if path.suffix.lower() != ".nrrd":
        raise ValueError(f"NRRD path must end in .nrrd: {path}")
    data = np.asarray(volume.data)
    if data.dtype == bool:
        data = data.astype(np.uint8)
    header = {
        "space": "left-posterior-superior",
        "space directions": volume.affine[:3, :3].T,  # one row per axis
        "space origin": volume.affine[:3, 3],
        "kinds": ["domain", "domain", "domain"],
        "encoding": "gzip",
    }
    with atomic_path(path) as tmp:
        nrrd.write(str(tmp), data, header, index_order="F")
    return path


# --------------------------------------------------------------------------- #
# Summary for ``bonecap inspect``
# --------------------------------------------------------------------------- #


def _summary_one(volume: Volume) -> dict[str, Any]:
    from nibabel.orientations import aff2axcodes

    m = volume.metadata
    finite = volume.data[np.isfinite(volume.data)] if volume.data.dtype.kind == "f" else volume.data
    value_range = [float(finite.min()), float(finite.max())] if finite.size else [math.nan, math.nan]
    # aff2axcodes names each world axis by (negative end, positive end); our
    # world is LPS, so +x is L, +y is P and +z is S.
    code = "".join(aff2axcodes(volume.affine, labels=(("R", "L"), ("A", "P"), ("I", "S"))))
    files = m.get("source_files") or []
    return {
        "shape": [int(n) for n in volume.shape],
        "spacing": [float(s) for s in volume.spacing],
        "origin": [float(v) for v in volume.affine[:3, 3]],
        "direction_cosines": {axis: [float(v) for v in volume.direction[:, n]]
                                  for n, axis in enumerate("ijk")},
        "orientation": code,
        "orientation_convention": "LPS-based: letter n is the world direction the n-th index (i, j, k) "
                                  "increases towards",
        "format": m.get("format"),
        "modality": m.get("modality"),
        "series_description": m.get("series_description"),
        "series_number": m.get("series_number"),
        "echo_number": m.get("echo_number"),
        "echo_time": m.get("echo_time"),
        "value_range": value_range,
        "dtype": str(volume.data.dtype),
        "file_count": len(files),
        "source": files[0] if files else None,
    }


def volume_summary(volumes: Volume | Iterable[Volume]) -> dict[str, Any] | list[dict[str, Any]]:
    """Describe volumes for ``bonecap inspect``.

    Parameters
    ----------
    volumes : Volume or iterable of Volume

    Returns
    -------
    dict or list of dict
        A dict for a single Volume, a list of dicts (same order) for an
        iterable. Keys: ``shape``, ``spacing`` (mm along i, j, k),
        ``origin`` (LPS mm of voxel 0, 0, 0), ``direction_cosines`` (unit LPS
        vectors, ``{"i": [x, y, z], ...}``), ``orientation``
        (three letters such as ``"LPS"`` or ``"PSL"``: the world direction each
        index increases towards, in LPS terms, from
        :func:`nibabel.orientations.aff2axcodes`), ``orientation_convention``,
        ``format``, ``modality``, ``series_description``, ``series_number``,
        ``echo_number``, ``echo_time``, ``value_range`` (finite min, max),
        ``dtype``, ``file_count``, ``source``. All values are JSON-ready.
    """
    if isinstance(volumes, Volume):
        return _summary_one(volumes)
    return [_summary_one(v) for v in volumes]
