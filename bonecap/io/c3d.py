"""C3D motion-capture trials <-> :class:`~bonecap.model.Trial`.

C3D is a binary format from the 1980s that every optical motion-capture
system still writes. A file is a sequence of 512-byte blocks: a **header**
block, a **parameter section** (named groups of typed parameters, such as
``POINT:LABELS``) and a **data section** holding, frame after frame, four
words per point (x, y, z and a "residual" word) followed by the analog
samples of that frame. Words are 16-bit integers (multiplied by
``POINT:SCALE``) or 32-bit floats (``POINT:SCALE`` < 0), in one of three
processor layouts: Intel (little endian IEEE), DEC (little endian words,
VAX floats) or SGI/MIPS (big endian IEEE).

Readers
-------
:func:`read_c3d` parses the file with `ezc3d <https://github.com/pyomeca/ezc3d>`_
and falls back to `py-c3d <https://github.com/EmbodiedCognition/py-c3d>`_
(the ``c3d`` package) when ezc3d refuses it: ezc3d 1.7.2 cannot read
SGI/MIPS files, py-c3d rejects files whose parameters are duplicated or
disagree with the header. ``Trial.metadata["reader"]`` says which one was
used (``"ezc3d"`` or ``"c3d"``). Before either library sees the file, the
header is checked here (C3D signature byte, parameter-section pointer,
processor type, and that the file is long enough for the frames the header
promises): ezc3d can crash the interpreter on malformed files and silently
returns fewer frames for a truncated one, so a bad file must be stopped
first with a one-line :class:`~bonecap.errors.FormatError`.

How the file maps onto ``Trial``
--------------------------------
``labels``, ``prefixes``
    ``POINT:LABELS`` continued by ``POINT:LABELS2``, ``LABELS3``... (one
    parameter holds at most 255 entries), cut to ``POINT:USED`` (many files
    list more labels than points). Surrounding spaces are removed, and a
    subject prefix ``Subject:LSHO`` is split into label ``LSHO`` and prefix
    ``Subject``. When stripping prefixes would give two markers the same
    label (two subjects both wearing ``LSHO``), those markers keep their full
    ``Subject:LSHO`` name as label (their ``prefixes`` entry still names the
    subject); identical full labels get ``#2``, ``#3``... appended; blank
    labels become ``POINT<n>`` (``n`` counting from 1 in the file).
``subject``
    ``read_c3d(path, subject="Derrick")`` keeps only the points with that
    prefix and the unprefixed ones.
``points``
    Markers only, converted to **millimetres** from ``POINT:UNITS`` (``mm``,
    ``cm`` or ``m``, case and spaces ignored; anything else is a
    :class:`~bonecap.errors.DataError`). ``Trial.units`` keeps the unit as
    stored. For integer files the coordinates are the stored integers times
    ``abs(POINT:SCALE)`` computed here in float64 (the two libraries round
    that product through float32 differently); float files give the stored
    float32 values, identical in both libraries.
``other_points``, ``other_point_groups``
    Points named in ``POINT:ANGLES``, ``FORCES``, ``MOMENTS``, ``POWERS``,
    ``SCALARS``, ``REACTIONS`` or ``MODELED_MARKERS`` (Vicon model outputs),
    plus any further group named in Vicon's ``POINT:TYPE_GROUPS``, are not
    markers. They are kept **as stored** (joint angles stay in degrees, never
    scaled as if they were positions), keyed by their full stored label (the
    prefix is not stripped, so that they write back under the same name),
    and ``other_point_groups[label]`` names the parameter that listed them.
``residuals``
    The residual byte of the fourth word (its low byte, as the C3D manual
    defines it) times ``abs(POINT:SCALE)``, in mm; ``NaN`` in gaps.
``analog_labels``, ``analogs``, ``analog_rate``
    ``ANALOG:LABELS`` (+ ``LABELS2``...) cut to ``ANALOG:USED``; samples
    ``(channels, samples)`` already scaled by ``ANALOG:GEN_SCALE``,
    ``ANALOG:SCALE`` and ``ANALOG:OFFSET`` as both readers do; the rate from
    ``ANALOG:RATE``. A file without analogs gives shape ``(0, 0)`` and rate 0.
``events``
    From the ``EVENT`` group when it is present and well formed
    (``LABELS``, ``CONTEXTS``, ``TIMES`` as minutes + seconds): time in
    seconds as stored, i.e. from the start of the capture, not from
    ``first_frame``. Odd event blocks are skipped, never fatal.
``subject_parameters``
    The numbers of the ``PROCESSING`` group, where Vicon Nexus keeps the
    subject's measurements that Plug-in Gait uses (``LKNEEWIDTH``,
    ``RANKLEWIDTH``, ``LELBOWWIDTH``, ``INTERASISDISTANCE``,
    ``MARKERDIAMETER``...), one scalar each, keyed by the parameter name in
    upper case (C3D parameter names are case-insensitive; both readers give
    them upper case). Kept as stored: Nexus writes these lengths in mm
    whatever ``POINT:UNITS`` says, and the Plug-in Gait manual gives them in
    mm. Arrays and strings in the group are skipped.
``first_frame``, ``rate``
    The header's first frame number (1-based as written in the file; ezc3d
    reports it 0-based, we do not); when the 16-bit header word is saturated
    (65535) ``TRIAL:ACTUAL_START_FIELD`` is used. ``rate`` is ``POINT:RATE``.
``metadata``
    ``source``, ``reader``, ``processor`` (Intel/DEC/MIPS), ``storage``
    (float/integer), ``point_scale``, and when present ``manufacturer``
    (``MANUFACTURER:COMPANY``) and ``software`` (``SOFTWARE`` +
    ``VERSION_LABEL``); ``fallback_reason`` when ezc3d was refused.

Gaps
----
The two libraries disagree on what an invalid sample is: ezc3d takes the
*high* byte of the fourth word as the residual and gives ``NaN`` where that
is negative; py-c3d casts the word to an integer and flags ``-1`` where the
cast is negative (so a stored ``-0.5`` is a gap for one and not the other, a
stored ``NaN`` the reverse). bonecap applies its own rule, reading the
fourth word straight from the data section so the answer cannot depend on
the reader: a **marker** sample is a gap (``NaN``) when

- the fourth word is negative or not a number, or
- any coordinate is not finite, or
- the point sits exactly at ``(0, 0, 0)`` (how many systems write a
  missing marker).

For ``other_points`` the origin rule is not applied: a joint angle of
exactly ``(0, 0, 0)`` is a legitimate value.

Writing
-------
:func:`write_c3d` writes an Intel float C3D in mm with py-c3d's
``c3d.Writer`` (a file written by ezc3d 1.7.2 has header scale -1.0 but
``POINT:SCALE`` -0.01, which py-c3d rejects; py-c3d's files read in both).
Prefixes are re-attached (``prefix:label``) unless the label already carries
them, residual words are 0 for visible samples and -1 for gaps (with
coordinates 0), other points are written after the markers with their group
parameter (``POINT:ANGLES``...), analogs, events and ``subject_parameters``
(as ``PROCESSING`` floats) when present. A marker
written exactly at the origin reads back as a gap, by the rule above.
"""

from __future__ import annotations

import os
import struct
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bonecap.errors import DataError, FormatError, InputError, OutputError
from bonecap.io.atomic import atomic_path
from bonecap.model import Trial

__all__ = ["read_c3d", "write_c3d", "c3d_summary", "OTHER_POINT_GROUPS"]

#: ``POINT`` parameters that list points which are not markers (Vicon model outputs).
OTHER_POINT_GROUPS = ("ANGLES", "FORCES", "MOMENTS", "POWERS", "SCALARS", "REACTIONS", "MODELED_MARKERS")

_UNIT_TO_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
_PROCESSORS = {84: "Intel", 85: "DEC", 86: "MIPS"}
_BLOCK = 512
# POINT parameters the writer fills itself: no other-point group may take these names.
_POINT_RESERVED = frozenset({"LABELS", "DESCRIPTIONS", "UNITS", "USED", "SCALE", "RATE", "FRAMES",
                             "LONG_FRAMES", "DATA_START", "X_SCREEN", "Y_SCREEN"})
# One C3D parameter dimension is a byte: a label list holds at most 255 names,
# the rest goes to LABELS2, LABELS3...
_MAX_DIM = 255


# --------------------------------------------------------------------------------------------
# Header: checked by us before any library touches the file
# --------------------------------------------------------------------------------------------

@dataclass
class _Header:
    """The header fields bonecap needs, decoded for the file's processor type."""

    processor: int          # 84 Intel, 85 DEC, 86 MIPS
    parameter_block: int    # 1-based block number of the parameter section
    point_count: int        # points per frame (header word 2)
    analog_words: int       # analog samples per point frame, all channels (word 3)
    first_frame: int        # 1-based, 16 bits (word 4)
    last_frame: int         # (word 5)
    scale: float            # header copy of POINT:SCALE (words 7-8)
    data_block: int         # 1-based block number of the data section (word 9)
    rate: float             # point rate (words 11-12)
    file_size: int

    @property
    def endian(self) -> str:
        return ">" if self.processor == 86 else "<"

    @property
    def frames(self) -> int:
        return max(self.last_frame - self.first_frame + 1, 0)


def _dec_to_float(raw: np.ndarray) -> np.ndarray:
    """Decode DEC (VAX F) floats from a ``(..., 4)`` uint8 array.

    A VAX float stores its two 16-bit halves most significant first, each
    half little endian; its exponent bias is 128 and its hidden bit sits
    before the binary point, so once the halves are swapped the bits read as
    an IEEE float four times too large.
    """
    swapped = np.ascontiguousarray(raw[..., [2, 3, 0, 1]])
    return swapped.view("<f4")[..., 0].astype(np.float64) / 4.0


def _decode_float(b: bytes, processor: int) -> float:
    if processor == 85:
        return float(_dec_to_float(np.frombuffer(b, np.uint8).reshape(1, 4))[0])
    return struct.unpack(">f" if processor == 86 else "<f", b)[0]


_TEXT_CONTROLS = frozenset(b"\t\n\r\f")


def _looks_like_text(head: bytes) -> bool:
    """True when the bytes are printable UTF-8 (a C3D header holds control bytes and zeros)."""
    if any(b < 0x20 and b not in _TEXT_CONTROLS for b in head) or 0x7F in head:
        return False
    try:
        head.decode("utf-8")
    except UnicodeDecodeError:
        # A multi-byte character cut at the end of the sample is still text.
        try:
            head[:-3].decode("utf-8")
        except UnicodeDecodeError:
            return False
    return True


def _check_header(path: Path) -> _Header:
    """Check that ``path`` is plausibly a complete C3D file and decode its header.

    Raises
    ------
    InputError
        The path does not exist or is a folder.
    FormatError
        Not a C3D file, or truncated.
    """
    if not path.exists():
        raise InputError("no such file", path)
    if path.is_dir():
        raise InputError("is a folder, not a C3D file", path)
    size = path.stat().st_size
    if size == 0:
        raise FormatError("not a C3D file (the file is empty)", path)
    with open(path, "rb") as fh:
        head = fh.read(_BLOCK)
        if _looks_like_text(head):
            raise FormatError("not a C3D file (first bytes are text)", path)
        if size < _BLOCK:
            raise FormatError(f"not a C3D file (only {size} bytes, shorter than the 512-byte header)", path)
        if head[1] != 0x50:
            raise FormatError(f"not a C3D file (second byte is 0x{head[1]:02X}, a C3D header has 0x50)", path)
        param_block = head[0]
        param_start = (param_block - 1) * _BLOCK
        if param_block < 2 or param_start + 4 > size:
            raise FormatError(
                f"truncated or corrupt: header points to a parameter section in block {param_block}, "
                f"file ends after {size} bytes", path)
        fh.seek(param_start)
        section = fh.read(4)
    n_param_blocks, processor = section[2], section[3]
    if processor not in _PROCESSORS:
        raise FormatError(
            f"not a C3D file (processor type {processor} in the parameter section; "
            "expected 84 Intel, 85 DEC or 86 MIPS)", path)
    if param_start + n_param_blocks * _BLOCK > size:
        raise FormatError(
            f"truncated: the parameter section needs {param_start + n_param_blocks * _BLOCK} bytes, "
            f"file ends after {size} bytes", path)
    e = ">" if processor == 86 else "<"
    words = struct.unpack(e + "10H", head[2:22])  # words 2..11 (1-based) of the header
    hdr = _Header(
        processor=processor,
        parameter_block=param_block,
        point_count=words[0],
        analog_words=words[1],
        first_frame=words[2],
        last_frame=words[3],
        scale=_decode_float(head[12:16], processor),
        data_block=words[7],
        rate=_decode_float(head[20:24], processor),
        file_size=size,
    )
    if hdr.data_block <= param_block and (hdr.point_count or hdr.analog_words) and hdr.frames:
        raise FormatError(
            f"corrupt header: data section starts in block {hdr.data_block}, "
            f"before the end of the parameter section (block {param_block})", path)
    _check_data_length(path, hdr, hdr.frames, hdr.point_count, hdr.scale < 0)
    return hdr


def _frame_bytes(hdr: _Header, points: int, is_float: bool) -> int:
    return (4 * points + hdr.analog_words) * (4 if is_float else 2)


def _check_data_length(path: Path, hdr: _Header, frames: int, points: int, is_float: bool) -> None:
    """Raise if the file is too short for ``frames`` frames of data."""
    if frames <= 0 or not (points or hdr.analog_words):
        return
    need = (hdr.data_block - 1) * _BLOCK + frames * _frame_bytes(hdr, points, is_float)
    if hdr.file_size < need:
        raise FormatError(
            f"truncated: header promises {frames} frames ({need} bytes), "
            f"file ends after {hdr.file_size} bytes", path)


# --------------------------------------------------------------------------------------------
# The two readers, brought to one shape
# --------------------------------------------------------------------------------------------

@dataclass
class _Parsed:
    """What a library gave us, before bonecap's rules are applied.

    ``params`` maps ``GROUP -> NAME -> value`` where strings are a list of
    str and numbers a numpy array shaped like the C3D dimensions (Fortran
    order, as ezc3d gives them). ``xyz`` is ``(F, N, 3)`` in file units.
    """

    reader: str
    params: dict[str, dict[str, Any]]
    xyz: np.ndarray
    analogs: np.ndarray


def _read_ezc3d(path: Path) -> _Parsed:
    import ezc3d

    # Never ignore_bad_formatting=True: it crashed the interpreter on a malformed
    # file; a strict failure here just means we try py-c3d.
    c = ezc3d.c3d(str(path))
    params: dict[str, dict[str, Any]] = {}
    for group, content in c["parameters"].items():
        params[group.upper()] = {
            name.upper(): p["value"] for name, p in content.items()
            if name != "__METADATA__" and isinstance(p, dict) and "value" in p
        }
    xyz = np.asarray(c["data"]["points"], dtype=float)[:3].transpose(2, 1, 0)  # (F, N, 3)
    analogs = np.asarray(c["data"]["analogs"], dtype=float)
    analogs = analogs[0] if analogs.ndim == 3 else analogs.reshape(0, 0)
    return _Parsed("ezc3d", params, xyz, analogs)


def _pyc3d_value(param) -> Any:
    dims = list(param.dimensions)
    bpe = param.bytes_per_element
    if bpe == -1:
        strings = param.string_array
        return [str(s) for s in np.ravel(strings)] if len(dims) else []
    if 0 in dims:
        return np.zeros([0])
    if bpe == 1:
        arr = param.int8_array if dims else np.array(param.int8_value)
    elif bpe == 2:
        arr = param.int16_array if dims else np.array(param.int16_value)
    elif bpe == 4:
        arr = param.float32_array if dims else np.array(param.float_value)
    else:
        return None
    # py-c3d shapes arrays with the dimensions reversed (C order); transpose to
    # the C3D (Fortran) order ezc3d uses, so both readers look the same.
    return np.asarray(arr).T


def _read_pyc3d(path: Path) -> _Parsed:
    import c3d

    with open(path, "rb") as fh, warnings.catch_warnings():
        # py-c3d warns about every missing optional parameter; not our business.
        warnings.simplefilter("ignore")
        reader = c3d.Reader(fh)
        params: dict[str, dict[str, Any]] = {}
        for gname, group in reader.group_items():
            params[gname.upper()] = {pname.upper(): _pyc3d_value(p) for pname, p in group.param_items()}
        frames, analog = [], []
        # check_nan=False: keep coordinates as stored; our gap rule decides.
        for _, pts, ana in reader.read_frames(copy=True, check_nan=False):
            frames.append(pts[:, :3].astype(float))
            if np.size(ana):
                analog.append(np.asarray(ana, dtype=float))
        n = reader.point_used
    xyz = np.stack(frames) if frames else np.zeros((0, n, 3))
    analogs = np.concatenate(analog, axis=1) if analog else np.zeros((0, 0))
    return _Parsed("c3d", params, xyz, analogs)


def _parse(path: Path) -> tuple[_Parsed, str | None]:
    """ezc3d first, py-c3d when ezc3d refuses; FormatError when both do."""
    try:
        return _read_ezc3d(path), None
    except Exception as exc:  # noqa: BLE001 -- any refusal means: try the other library
        first = _one_line(exc)
    try:
        return _read_pyc3d(path), first
    except Exception as exc:  # noqa: BLE001
        raise FormatError(f"unreadable C3D (ezc3d: {first}; c3d: {_one_line(exc)})", path) from exc


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text[:200]


# --------------------------------------------------------------------------------------------
# Parameter helpers
# --------------------------------------------------------------------------------------------

def _get(params, group: str, name: str, default=None):
    return params.get(group, {}).get(name, default)


def _strings(params, group: str, name: str) -> list[str]:
    value = _get(params, group, name)
    if value is None or isinstance(value, np.ndarray):
        return []
    return [str(s).strip() for s in value]


def _continued_strings(params, group: str, name: str) -> list[str]:
    """``NAME`` followed by ``NAME2``, ``NAME3``... as long as they exist."""
    out = _strings(params, group, name)
    k = 2
    while f"{name}{k}" in params.get(group, {}):
        out += _strings(params, group, f"{name}{k}")
        k += 1
    return out


def _number(params, group: str, name: str, default: float | None = None) -> float | None:
    value = _get(params, group, name)
    if value is None or isinstance(value, list):
        return default
    arr = np.ravel(np.asarray(value, dtype=float))
    return float(arr[0]) if arr.size else default


def _processing(params) -> dict[str, float]:
    """The scalar numbers of the ``PROCESSING`` group (Vicon's subject measurements), upper-case names."""
    out = {}
    for name, value in params.get("PROCESSING", {}).items():
        if value is None or isinstance(value, list):
            continue
        arr = np.ravel(np.asarray(value, dtype=float))
        if arr.size == 1 and np.isfinite(arr[0]):
            out[str(name).strip().upper()] = float(arr[0])
    return out


def _uint32_from_words(params, group: str, name: str) -> int | None:
    value = _get(params, group, name)
    if value is None or isinstance(value, list):
        return None
    words = np.ravel(np.asarray(value)).astype(np.int64) & 0xFFFF
    if words.size == 0:
        return None
    return int(words[0] + (words[1] << 16 if words.size > 1 else 0))


# --------------------------------------------------------------------------------------------
# The raw fourth word, read by us so that the gap rule does not depend on the reader
# --------------------------------------------------------------------------------------------

def _raw_point_words(path: Path, hdr: _Header, frames: int, points: int, is_float: bool) -> np.ndarray:
    """The four stored words of every point sample, ``(F, N, 4)``, decoded to float64.

    Integer files give the raw integers (not multiplied by the scale).
    """
    if frames == 0 or points == 0:
        return np.zeros((frames, points, 4))
    _check_data_length(path, hdr, frames, points, is_float)
    width = 4 if is_float else 2
    stride = _frame_bytes(hdr, points, is_float)
    start = (hdr.data_block - 1) * _BLOCK
    raw = np.fromfile(path, dtype=np.uint8, count=frames * stride, offset=start).reshape(frames, stride)
    raw = raw[:, : 4 * points * width].reshape(frames, points, 4, width)
    if is_float and hdr.processor == 85:
        return _dec_to_float(raw)
    dtype = (hdr.endian + ("f4" if is_float else "i2"))
    return np.ascontiguousarray(raw).view(dtype)[..., 0].astype(np.float64)


# --------------------------------------------------------------------------------------------
# Labels, prefixes, groups
# --------------------------------------------------------------------------------------------

def _split_prefix(full: str) -> tuple[str, str]:
    """``"Subject:LSHO"`` -> ``("Subject", "LSHO")``; no colon -> ``("", full)``."""
    prefix, sep, name = full.partition(":")
    if not sep or not name.strip():
        return "", full
    return prefix.strip(), name.strip()


def _unique_labels(full: list[str], names: list[str]) -> list[str]:
    """Stripped names, except full names where stripping collides; ``#k`` for exact duplicates."""
    counts: dict[str, int] = {}
    for n in names:
        counts[n] = counts.get(n, 0) + 1
    labels = [f if counts[n] > 1 else n for f, n in zip(full, names)]
    seen: dict[str, int] = {}
    out = []
    for lab in labels:
        seen[lab] = seen.get(lab, 0) + 1
        out.append(lab if seen[lab] == 1 else f"{lab}#{seen[lab]}")
    return out


def _point_group_of(params, full_labels: list[str]) -> list[str | None]:
    """For each point, the ``POINT`` parameter listing it as a non-marker, or None."""
    groups = list(OTHER_POINT_GROUPS)
    # Vicon's POINT:TYPE_GROUPS pairs a parameter name with its type name
    # ("ANGLES", "ANGLE", "FORCES", "FORCE"...): honour groups we did not know.
    type_groups = _strings(params, "POINT", "TYPE_GROUPS")
    for name in type_groups[0::2]:
        name = name.upper()
        if name and name not in groups and name not in ("LABELS", "MARKERS", "DESCRIPTIONS"):
            groups.append(name)
    by_name: dict[str, str] = {}
    for g in groups:
        for member in _continued_strings(params, "POINT", g):
            if member:
                by_name.setdefault(member, g)
    out: list[str | None] = []
    for full in full_labels:
        # Listed by full name, or (some writers) without the subject prefix.
        out.append(by_name.get(full) or by_name.get(_split_prefix(full)[1]))
    return out


# --------------------------------------------------------------------------------------------
# Public API
# --------------------------------------------------------------------------------------------

def read_c3d(path: str | os.PathLike, subject: str | None = None) -> Trial:
    """Read a C3D file into a :class:`~bonecap.model.Trial` (markers in mm).

    Parameters
    ----------
    path : path-like
        The ``.c3d`` file (Intel, DEC or SGI/MIPS; integer or float).
    subject : str, optional
        Keep only the points whose label prefix is ``subject``
        (``"Derrick:LSHO"``), plus unprefixed ones.

    Returns
    -------
    Trial
        See the module docstring for how each field is filled. A file without
        any point gives a Trial with zero markers.

    Raises
    ------
    InputError
        ``path`` does not exist or is a folder.
    FormatError
        Not a C3D file, truncated, or refused by both ezc3d and py-c3d.
    DataError
        Readable but unusable: unknown ``POINT:UNITS``, no positive point
        rate, ``subject`` not in the file, header and parameters disagreeing
        on the data layout.
    """
    path = Path(path)
    hdr = _check_header(path)
    parsed, fallback_reason = _parse(path)
    params = parsed.params

    # --- layout: how many points and frames, and how they are stored --------------------
    n = parsed.xyz.shape[1]  # both libraries give POINT:USED points
    frames = parsed.xyz.shape[0]
    if n == 0 and frames == 0:
        # Nothing stored per frame: the header alone knows how long the trial was.
        frames = hdr.frames
        parsed.xyz = np.zeros((frames, 0, 3))
    scale = _number(params, "POINT", "SCALE", hdr.scale)
    if scale is None or not np.isfinite(scale) or scale == 0:
        scale = hdr.scale
    is_float = scale < 0
    rate = _number(params, "POINT", "RATE", None) or hdr.rate
    if not (rate and np.isfinite(rate) and rate > 0):
        raise DataError(f"no usable point rate (POINT:RATE {rate})", path)
    if n and hdr.point_count != n:
        raise DataError(f"header says {hdr.point_count} points per frame, POINT:USED says {n}", path)

    xyz = parsed.xyz
    words = _raw_point_words(path, hdr, frames, n, is_float)
    _cross_check(path, xyz, words, scale, is_float)
    if not is_float:
        # Integer files: stored integer times the scale, in float64. The two
        # libraries round this product through float32 differently (up to
        # 1e-4 mm apart); computing it here keeps the result reader-independent.
        xyz = words[..., :3] * abs(scale)

    # --- bonecap's gap rule, from the raw fourth word ----------------------------------
    w4 = words[..., 3]
    bad_word = ~(w4 >= 0)  # negative or NaN
    nonfinite = ~np.isfinite(xyz).all(axis=2)
    at_origin = (xyz == 0).all(axis=2)
    residual_byte = np.where(bad_word, 0, w4).astype(np.int64) & 0xFF
    residuals = residual_byte * abs(scale)

    # --- labels, prefixes, groups -------------------------------------------------------
    stored = _continued_strings(params, "POINT", "LABELS")[:n]
    stored += [""] * (n - len(stored))
    full = [s if s else f"POINT{i + 1}" for i, s in enumerate(stored)]
    split = [_split_prefix(f) for f in full]
    groups = _point_group_of(params, full)

    subjects = sorted({p for p, _ in split if p})
    if subject is not None:
        subject = subject.strip()
        if subject not in subjects:
            listed = ", ".join(subjects) if subjects else "none (labels carry no prefix)"
            raise DataError(f"no subject {subject!r} in file; subjects present: {listed}", path)
    keep = [subject is None or p in ("", subject) for p, _ in split]

    marker_idx = [i for i in range(n) if keep[i] and groups[i] is None]
    other_idx = [i for i in range(n) if keep[i] and groups[i] is not None]

    # --- units --------------------------------------------------------------------------
    units_stored = (_strings(params, "POINT", "UNITS") or [""])[0]
    unit_key = units_stored.replace(" ", "").lower()
    if unit_key in _UNIT_TO_MM:
        factor = _UNIT_TO_MM[unit_key]
    elif not unit_key and not marker_idx:
        factor = 1.0
    elif not unit_key:
        raise DataError("POINT:UNITS is missing; cannot tell the marker units", path)
    else:
        raise DataError(f"unknown POINT:UNITS {units_stored!r} (expected mm, cm or m)", path)

    gap = bad_word | nonfinite | at_origin
    points = np.where(gap[..., None], np.nan, xyz)[:, marker_idx] * factor
    res = np.where(gap, np.nan, residuals)[:, marker_idx] * factor

    other_gap = bad_word | nonfinite
    other_names = _unique_labels([full[i] for i in other_idx], [full[i] for i in other_idx])
    other_points = {k: np.where(other_gap[:, i, None], np.nan, xyz[:, i]) for k, i in zip(other_names, other_idx)}
    other_groups = {k: groups[i] for k, i in zip(other_names, other_idx)}

    m_full = [full[i] for i in marker_idx]
    m_prefix = [split[i][0] for i in marker_idx]
    m_names = [split[i][1] for i in marker_idx]
    labels = _unique_labels(m_full, m_names)

    # --- analogs, events, metadata -----------------------------------------------------
    analog_labels, analogs, analog_rate = _analogs(params, parsed.analogs, rate, frames)
    first_frame = hdr.first_frame
    if first_frame == 0xFFFF:
        first_frame = _uint32_from_words(params, "TRIAL", "ACTUAL_START_FIELD") or first_frame

    metadata: dict[str, Any] = {
        "source": os.fspath(path),
        "reader": parsed.reader,
        "processor": _PROCESSORS[hdr.processor],
        "storage": "float" if is_float else "integer",
        "point_scale": float(scale),
    }
    company = _strings(params, "MANUFACTURER", "COMPANY")
    if company and company[0]:
        metadata["manufacturer"] = company[0]
    software = " ".join(s for s in (_strings(params, "MANUFACTURER", "SOFTWARE")[:1]
                                    + _strings(params, "MANUFACTURER", "VERSION_LABEL")[:1]) if s)
    if software:
        metadata["software"] = software
    if fallback_reason:
        metadata["fallback_reason"] = f"ezc3d: {fallback_reason}"
    if subject is not None:
        metadata["subject"] = subject

    return Trial(
        labels=labels,
        points=points.reshape(frames, len(marker_idx), 3),
        rate=float(rate),
        first_frame=int(first_frame),
        prefixes=m_prefix,
        residuals=res.reshape(frames, len(marker_idx)),
        other_points=other_points,
        other_point_groups=other_groups,
        analog_labels=analog_labels,
        analogs=analogs,
        analog_rate=analog_rate,
        events=_events(params),
        subject_parameters=_processing(params),
        units=units_stored,
        metadata=metadata,
    )


def _cross_check(path: Path, xyz: np.ndarray, words: np.ndarray, scale: float, is_float: bool) -> None:
    """Make sure our raw reading of the data section lines up with the library's.

    The gap rule reads the fourth word itself; if the header and the
    parameters described the layout differently than the library assumed,
    the words would be garbage. Comparing x, y, z where both are valid proves
    the alignment.
    """
    if xyz.size == 0:
        return
    raw_xyz = words[..., :3] if is_float else words[..., :3] * abs(scale)
    both = np.isfinite(xyz) & np.isfinite(raw_xyz) & (words[..., 3:4] >= 0)
    if not both.any():
        return
    a, b = xyz[both], raw_xyz[both]
    tol = 1e-5 * np.abs(b) + (0 if is_float else 1e-3 * abs(scale)) + 1e-30
    if not np.all(np.abs(a - b) <= tol):
        raise DataError("point data layout disagrees with the header (data start, point count or format)", path)


def _analogs(params, data: np.ndarray, rate: float, frames: int) -> tuple[list[str], np.ndarray, float]:
    used = int(_number(params, "ANALOG", "USED", 0) or 0)
    if used == 0 or data.size == 0:
        return [], np.zeros((0, 0)), 0.0
    data = data[:used]
    labels = _continued_strings(params, "ANALOG", "LABELS")[: data.shape[0]]
    labels += [f"ANALOG{i + 1}" for i in range(len(labels), data.shape[0])]
    labels = [lab if lab else f"ANALOG{i + 1}" for i, lab in enumerate(labels)]
    analog_rate = _number(params, "ANALOG", "RATE", None)
    if not analog_rate or analog_rate <= 0:
        # No ANALOG:RATE: samples per point frame times the point rate.
        analog_rate = rate * data.shape[1] / frames if frames else 0.0
    return labels, data, float(analog_rate)


def _events(params) -> list[dict[str, Any]]:
    """Events of the ``EVENT`` group, best effort: anything odd gives fewer events, not an error."""
    try:
        group = params.get("EVENT")
        if not group:
            return []
        used = int(_number(params, "EVENT", "USED", 0) or 0)
        times = group.get("TIMES")
        if used <= 0 or times is None or isinstance(times, list):
            return []
        times = np.asarray(times, dtype=float)
        if times.ndim != 2 or times.shape[0] != 2:
            return []
        labels = _continued_strings(params, "EVENT", "LABELS")
        contexts = _continued_strings(params, "EVENT", "CONTEXTS")
        n = min(used, times.shape[1])
        events = []
        for i in range(n):
            t = times[0, i] * 60.0 + times[1, i]  # stored as (minutes, seconds)
            if not np.isfinite(t):
                continue
            events.append({
                "label": labels[i] if i < len(labels) else "",
                "context": contexts[i] if i < len(contexts) else "",
                "time": float(t),
            })
        return events
    except Exception:  # noqa: BLE001 -- events are a courtesy; never fail a read on them
        return []


def c3d_summary(path: str | os.PathLike, subject: str | None = None) -> dict[str, Any]:
    """A JSON-able description of a C3D trial, for ``bonecap inspect``.

    Parameters
    ----------
    path : path-like
        The ``.c3d`` file.
    subject : str, optional
        As in :func:`read_c3d`.

    Returns
    -------
    dict
        ``format`` ("c3d"), ``path``, ``frames``, ``rate``, ``first_frame``,
        ``duration_s``, ``units_stored``, ``marker_count``, ``markers``,
        ``gap_samples`` (missing frames per marker), ``prefixes`` (sorted,
        non-empty), ``other_points`` (count per group), ``analog_channels``,
        ``analog_labels``, ``analog_rate``, ``events``, ``reader``.

    Raises
    ------
    InputError, FormatError, DataError
        As :func:`read_c3d`.
    """
    trial = read_c3d(path, subject=subject)
    other: dict[str, int] = {}
    for group in trial.other_point_groups.values():
        other[group] = other.get(group, 0) + 1
    summary = {
        "format": "c3d",
        "path": os.fspath(path),
        "frames": int(trial.n_frames),
        "rate": float(trial.rate),
        "first_frame": int(trial.first_frame),
        "duration_s": float(trial.n_frames / trial.rate),
        "units_stored": trial.units,
        "marker_count": len(trial.labels),
        "markers": list(trial.labels),
        "gap_samples": trial.gap_counts(),
        "prefixes": sorted({p for p in trial.prefixes if p}),
        "other_points": dict(sorted(other.items())),
        "analog_channels": len(trial.analog_labels),
        "analog_labels": list(trial.analog_labels),
        "analog_rate": float(trial.analog_rate),
        "events": len(trial.events),
        "reader": trial.metadata.get("reader", ""),
    }
    if subject is not None:
        summary["subject"] = subject
    return summary


# --------------------------------------------------------------------------------------------
# Writer
# --------------------------------------------------------------------------------------------

def _full_label(label: str, prefix: str) -> str:
    if not prefix or label.startswith(prefix + ":"):
        return label
    return f"{prefix}:{label}"


def _add_strings(group, name: str, strings: list[str], desc: str) -> None:
    """Add a string-list parameter, continued in NAME2, NAME3... past 255 entries."""
    for k, start in enumerate(range(0, max(len(strings), 1), _MAX_DIM)):
        chunk = strings[start:start + _MAX_DIM]
        width = max([len(s.encode("utf-8")) for s in chunk] + [1])
        packed = b"".join(s.encode("utf-8").ljust(width) for s in chunk)
        group.add_param(name if k == 0 else f"{name}{k + 1}", desc=desc, bytes_per_element=-1,
                        bytes=packed, dimensions=[width, len(chunk)])


def write_c3d(trial: Trial, path: str | os.PathLike) -> None:
    """Write ``trial`` as an Intel float C3D file in millimetres.

    Parameters
    ----------
    trial : Trial
        Markers in mm (``NaN`` for gaps); other points (listed under
        ``POINT:<other_point_groups[name]>``, ``SCALARS`` when unnamed),
        analogs and events are written too.
    path : path-like
        The target file; written to a temporary file beside it and renamed
        at the end, so a failure leaves nothing behind.

    Raises
    ------
    OutputError
        The trial cannot be represented in C3D (no frames, duplicate, empty
        or too long labels, analog rate not a whole multiple of the point
        rate, analog sample count not matching the frames, more than 255
        analog channels or events, first frame outside 1..65534) or the file
        cannot be written.

    Notes
    -----
    The file reads back identically (labels, float32 positions, gaps) with
    :func:`read_c3d`, raw ezc3d and raw py-c3d. Residual words are 0 for
    visible samples and -1 for gaps (``Trial.residuals`` is not written).
    A visible marker exactly at ``(0, 0, 0)`` reads back as a gap.
    """
    import c3d

    path = Path(path)
    F = trial.n_frames
    if F == 0:
        raise OutputError("cannot write a C3D file of a trial with no frames", path)

    # py-c3d keeps frame numbers >= 65535 in TRIAL:ACTUAL_START_FIELD but
    # decodes that parameter off by one (x 65535 instead of 65536), so stay below.
    if not 1 <= int(trial.first_frame) < 0xFFFF:
        raise OutputError(f"first frame {trial.first_frame} outside what C3D headers hold (1 to 65534)", path)
    if len(trial.events) > _MAX_DIM:
        raise OutputError(f"{len(trial.events)} events; this writer handles at most {_MAX_DIM}", path)

    full = [_full_label(lab, pre) for lab, pre in zip(trial.labels, trial.prefixes)]
    other_names = list(trial.other_points)
    all_labels = full + other_names
    _check_labels(all_labels, path)
    for name in other_names:
        arr = np.asarray(trial.other_points[name])
        if arr.shape != (F, 3):
            raise OutputError(f"other point {name!r} has shape {arr.shape}, expected ({F}, 3)", path)

    xyz = np.concatenate([trial.points] + [np.asarray(trial.other_points[k], float)[:, None] for k in other_names],
                         axis=1) if other_names else trial.points
    visible = np.isfinite(xyz).all(axis=2)
    with np.errstate(over="ignore", invalid="ignore"):
        xyz32 = np.where(visible[..., None], xyz, 0.0).astype(np.float32)
    if not np.isfinite(xyz32[visible]).all():
        raise OutputError("a point coordinate does not fit in a float32", path)
    visible &= np.isfinite(xyz32).all(axis=2)

    if trial.analogs.size and trial.analogs.ndim != 2:
        raise OutputError(f"analogs must be (channels, samples), got shape {trial.analogs.shape}", path)
    A = trial.analogs.shape[0] if trial.analogs.size else 0
    ratio = 0
    if A:
        ratio_f = trial.analog_rate / trial.rate
        ratio = int(round(ratio_f))
        if ratio < 1 or abs(ratio_f - ratio) > 1e-9 * max(1.0, ratio_f):
            raise OutputError(
                f"analog rate {trial.analog_rate:g} Hz is not a whole multiple of the point rate "
                f"{trial.rate:g} Hz", path)
        if trial.analogs.shape[1] != F * ratio:
            raise OutputError(
                f"{trial.analogs.shape[1]} analog samples for {F} frames at {ratio} samples per frame", path)
        if A > _MAX_DIM:
            raise OutputError(f"{A} analog channels; this writer handles at most {_MAX_DIM}", path)
    analog_labels = list(trial.analog_labels)[:A]
    analog_labels += [f"ANALOG{i + 1}" for i in range(len(analog_labels), A)]

    try:
        writer = c3d.Writer(point_rate=float(trial.rate), analog_rate=float(trial.rate * ratio) if A else 0.0,
                            point_scale=-1.0, point_units="mm")
        pg = writer.point_group
        _add_strings(pg, "LABELS", all_labels, "Point labels")
        # py-c3d would write DESCRIPTIONS with one dimension per point, which
        # overflows past 255 points; give it our own, continued like LABELS.
        _add_strings(pg, "DESCRIPTIONS", [""] * len(all_labels), "Point descriptions")
        by_group: dict[str, list[str]] = {}
        for name in other_names:
            group_name = str(trial.other_point_groups.get(name, "SCALARS")).strip().upper()
            if not _usable_group_name(group_name):
                raise OutputError(f"other point {name!r} has an unusable group name {group_name!r}", path)
            by_group.setdefault(group_name, []).append(name)
        for group_name, members in by_group.items():
            _add_strings(pg, group_name, members, f"{group_name} outputs")
        if A:
            ag = writer.analog_group
            _add_strings(ag, "LABELS", analog_labels, "Analog labels")
            _add_strings(ag, "DESCRIPTIONS", [""] * A, "Analog descriptions")
            ag.add_param("SCALE", desc="Analog scales", bytes_per_element=4,
                         bytes=np.ones(A, "<f4").tobytes(), dimensions=[A])
            ag.add_param("OFFSET", desc="Analog offsets", bytes_per_element=2,
                         bytes=np.zeros(A, "<i2").tobytes(), dimensions=[A])
        _add_events(writer, trial.events)
        _add_processing(writer, trial.subject_parameters)
        writer.set_start_frame(int(trial.first_frame))

        residual = np.where(visible, 0.0, -1.0).astype(np.float32)
        analogs = np.asarray(trial.analogs, dtype=float) if A else None
        # An object array of (points, analog) pairs: handing py-c3d a list of
        # tuples lets numpy merge equally shaped arrays into one block.
        frames = np.empty((F, 2), dtype=object)
        for f in range(F):
            pts = np.zeros((xyz32.shape[1], 5), np.float32)
            pts[:, :3] = xyz32[f]
            pts[:, 3] = residual[f]
            frames[f, 0] = pts
            frames[f, 1] = analogs[:, f * ratio:(f + 1) * ratio] if A else np.zeros((0, 0))
        writer.add_frames(frames)

        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh, warnings.catch_warnings():
                warnings.simplefilter("ignore")
                writer.write(fh)
            _zero_gap_coordinates(tmp, visible, A * ratio)
    except OSError as exc:
        raise OutputError(f"cannot write: {exc.strerror or exc}", path) from exc
    except (ValueError, TypeError, KeyError, AssertionError, RuntimeError, struct.error) as exc:
        # py-c3d signals what it cannot encode with assorted exceptions.
        raise OutputError(f"C3D writer failed: {_one_line(exc)}", path) from exc


def _usable_group_name(name: str) -> bool:
    """A POINT parameter name we may create for other points (ANGLES, FORCES...)."""
    if not name or not name.isascii() or not name.replace("_", "").isalnum() or len(name) > 127:
        return False
    return name not in _POINT_RESERVED and not name.startswith(("LABELS", "DESCRIPTIONS"))


def _check_labels(labels: list[str], path: Path) -> None:
    seen = set()
    for lab in labels:
        if not lab.strip():
            raise OutputError("a point label is empty", path)
        if len(lab.encode("utf-8")) > _MAX_DIM:
            raise OutputError(f"point label {lab[:40]!r}... is longer than {_MAX_DIM} bytes", path)
        if lab in seen:
            raise OutputError(f"point label {lab!r} appears twice (markers and other points included)", path)
        seen.add(lab)


def _add_events(writer, events: list[dict[str, Any]]) -> None:
    events = [e for e in events if np.isfinite(float(e.get("time", np.nan)))]
    if not events:
        return
    g = writer.get_create("EVENT")
    n = len(events)
    g.add_param("USED", desc="Number of events", bytes_per_element=2,
                bytes=struct.pack("<h", n), dimensions=[])
    _add_strings(g, "LABELS", [str(e.get("label", "")) or "event" for e in events], "Event labels")
    _add_strings(g, "CONTEXTS", [str(e.get("context", "")) for e in events], "Event contexts")
    t = np.array([float(e["time"]) for e in events])
    minutes = np.floor(t / 60.0)
    times = np.stack([minutes, t - 60.0 * minutes], axis=1).astype("<f4")  # (n, 2): Fortran [2, n]
    g.add_param("TIMES", desc="Event times (minutes, seconds)", bytes_per_element=4,
                bytes=times.tobytes(), dimensions=[2, n])


def _add_processing(writer, parameters: dict[str, float]) -> None:
    """``Trial.subject_parameters`` as one float parameter each in ``PROCESSING`` (where Nexus keeps them)."""
    if not parameters:
        return
    g = writer.get_create("PROCESSING")
    for name, value in parameters.items():
        key = str(name).strip().upper()
        if not key or len(key) > 127 or not np.isfinite(float(value)):
            raise ValueError(f"subject parameter {name!r} = {value!r} cannot be written")
        g.add_param(key, desc="subject measurement", bytes_per_element=4,
                    bytes=struct.pack("<f", float(value)), dimensions=[])


def _zero_gap_coordinates(tmp: Path, visible: np.ndarray, analog_words: int) -> None:
    """Set x, y, z of gap samples to 0 in a file py-c3d just wrote.

    py-c3d 0.6 reuses one frame buffer and only fills the visible rows, so a
    gap would carry the coordinates of the last frame where that point was
    seen (with residual -1). Readers that honour the residual do not care,
    but a file should not hold stale positions.
    """
    if visible.all():
        return
    with open(tmp, "rb") as fh:
        head = fh.read(_BLOCK)
    data_block = struct.unpack("<H", head[16:18])[0]
    F, N = visible.shape
    words = np.memmap(tmp, dtype="<f4", mode="r+", offset=(data_block - 1) * _BLOCK,
                      shape=(F, 4 * N + analog_words))
    f, p = np.nonzero(~visible)
    for c in range(3):
        words[f, 4 * p + c] = 0.0
    words.flush()
    del words
