"""The body (and so the skin) of an axial MRI stack, slice by slice.

Stage 2 of ``bonecap build-subject``: per axial slice every body component
above a size threshold (at chest level the arms are separate components,
below the pelvis the legs), holes filled per slice. The skin is the boundary
of the result.

Public API
----------
- :func:`body_threshold` ``(volume, smooth_mm=2.0) -> float``
- :func:`edge_threshold` ``(smoothed, body, spacing) -> float``
- :func:`segment_body` ``(volume, min_area_mm2=200.0, smooth_mm=2.0, threshold=None, skin=False) -> ndarray[bool]``

References
----------
Kojima et al., the MRI-based personal skeleton and motion-capture paper this
project follows (skin contours per slice).
Otsu N. A threshold selection method from gray-level histograms. *IEEE Trans
Syst Man Cybern* 9(1):62-66, 1979.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from skimage.filters import threshold_otsu

from bonecap.model import Volume
from bonecap.segmentation._distance import inplane_edt

__all__ = ["body_threshold", "edge_threshold", "segment_body"]

# In-plane 8-connectivity, no link between slices: every operation below is
# per slice, done on the whole stack at once.
_INPLANE = np.zeros((3, 3, 3), bool)
_INPLANE[:, :, 1] = True


def _check_volume(volume: Volume) -> np.ndarray:
    if not isinstance(volume, Volume):
        raise ValueError(f"volume must be a bonecap.model.Volume, got {type(volume).__name__}")
    data = np.asarray(volume.data)
    if data.size == 0 or min(data.shape) < 1:
        raise ValueError(f"volume is empty (shape {data.shape})")
    if not np.isfinite(data).all():
        raise ValueError("volume holds NaN or infinite values; replace them before segmenting")
    return data


def _smoothed(data: np.ndarray, spacing: np.ndarray, smooth_mm: float) -> np.ndarray:
    """Gaussian smoothing in-plane only (sigma in mm), so slices stay independent."""
    sigma = (smooth_mm / spacing[0], smooth_mm / spacing[1], 0.0)
    return ndimage.gaussian_filter(data.astype(np.float32, copy=False), sigma, mode="nearest")


def body_threshold(volume: Volume, smooth_mm: float = 2.0) -> float:
    """The air/tissue threshold of an MRI stack, from its own data.

    Otsu's threshold of ``log(1 + I)`` of the in-plane smoothed stack, returned
    in image units.

    Why this way: smoothing first (Gaussian, ``smooth_mm``) removes most of
    the Rician noise of the air, whose single bright pixels would otherwise
    form specks and ragged skin. The logarithm turns the scanner's smooth
    multiplicative bias field (and the per-station receiver gain) into an
    additive offset, and it puts muscle and fat (a factor ~3 apart on T2,
    less on T1) close together compared with air (hundreds of times darker):
    Otsu's two classes are then air versus tissue whatever the share of fat,
    rather than muscle versus fat, which a linear-intensity Otsu finds on a
    trunk station where air is a small part of the field of view. One
    threshold for the whole stack (not per slice), because a slice that
    barely touches the body (the top of the head, the toes) has no air/tissue
    balance of its own.

    Parameters
    ----------
    volume : Volume
        Axial stack, ``data[i, j, k]`` with ``k`` the slice axis (LPS world).
    smooth_mm : float
        Standard deviation of the in-plane Gaussian, mm.

    Returns
    -------
    float
        Threshold in the image's units (tissue is brighter).

    Raises
    ------
    ValueError
        Not a Volume, empty, NaN in the data, non-positive ``smooth_mm``, or a
        constant image.

    References
    ----------
    Otsu N. *IEEE Trans Syst Man Cybern* 9(1):62-66, 1979.
    """
    data = _check_volume(volume)
    if not smooth_mm > 0:
        raise ValueError(f"smooth_mm must be positive, got {smooth_mm}")
    sm = _smoothed(data, volume.spacing, smooth_mm)
    lo = float(sm.min())
    if float(sm.max()) <= lo:
        raise ValueError("the volume is constant: no body to find")
    logs = np.log1p(np.maximum(sm - min(lo, 0.0), 0.0))
    # Otsu on a regular subsample is the same threshold to a fraction of a bin and 10x faster.
    step = max(1, logs.size // 2_000_000)
    return float(np.expm1(threshold_otsu(logs.ravel()[::step], nbins=512)) + min(lo, 0.0))


def edge_threshold(smoothed: np.ndarray, body: np.ndarray, spacing, inner_mm: tuple[float, float] = (2.0, 8.0),
                   outer_mm: tuple[float, float] = (6.0, 12.0)) -> float:
    """The half-way level between the tissue under the skin and the air beside it.

    Otsu's threshold of the log intensities separates air from tissue
    reliably, but it sits near the air (a geometric, not arithmetic, middle):
    on a blurred skin edge that level lies several millimetres outside the
    skin (4 mm on the phantom's stations, 1.8 mm pixels). The edge of a
    blurred step is where the intensity is half-way between its two sides, so
    the level is taken there: between the upper quartile of the (smoothed)
    tissue ``inner_mm`` inside the Otsu boundary and the median of the air
    ``outer_mm`` outside it, per slice in-plane distances.

    Parameters
    ----------
    smoothed : ndarray
        The in-plane smoothed stack.
    body : ndarray of bool
        The Otsu body mask.
    spacing : sequence of float
        Voxel size (mm), the slice axis last.

    Returns
    -------
    float
        The threshold; Otsu's own (``smoothed`` at the mask edge) when either
        ring is empty.
    """
    # in-plane distances only, slice by slice
    samp = (float(spacing[0]), float(spacing[1]))
    d_in = inplane_edt(body, samp)
    d_out = inplane_edt(~body, samp)
    inner = smoothed[(d_in >= inner_mm[0]) & (d_in <= inner_mm[1])]
    outer = smoothed[(d_out >= outer_mm[0]) & (d_out <= outer_mm[1])]
    if inner.size < 100 or outer.size < 100:
        edge = smoothed[body & (d_in <= 1.5 * max(samp[:2]))]
        return float(np.median(edge)) if edge.size else float(smoothed[body].min())
    # under the skin lies fat (bright) over muscle (a third of it on T2) within a few millimetres: the
    # upper quartile of the ring is the fat's level where there is fat; a median would mix in muscle
    # and put the edge out again
    return 0.5 * (float(np.percentile(inner, 75)) + float(np.median(outer)))


def segment_body(volume: Volume, min_area_mm2: float = 200.0, smooth_mm: float = 2.0,
                 threshold: float | None = None, skin: bool = False):
    """Every body component of each axial slice, holes filled per slice.

    Kojima et al. segment the skin slice by slice: each slice's tissue
    (:func:`body_threshold`) is split into connected components (8-connected,
    in-plane), components smaller than ``min_area_mm2`` are dropped (noise,
    a capsule's partial volume), and the holes of each component are filled
    *per slice* (air in the bowel or lungs, dark bone would otherwise be
    holes; a 3-D fill would leave slices open where the body leaves the field
    of view). Arms at chest level and legs below the pelvis are kept as
    separate components of the same mask.

    Parameters
    ----------
    volume : Volume
        Axial stack in the LPS world: ``data[i, j, k]`` with ``k`` the slice
        axis, ``affine`` voxel -> LPS mm.
    min_area_mm2 : float
        Smallest component kept, per slice, in mm^2 (pixel area from the
        affine). 200 mm^2 keeps a finger-sized cross-section of a hand and
        drops noise specks.
    smooth_mm : float
        In-plane Gaussian standard deviation, mm, used for the threshold and
        the mask (a 2 mm Gaussian moves a straight skin edge by nothing and
        removes the speckle of the air).
    threshold : float, optional
        Air/tissue threshold in image units; default :func:`body_threshold`.
    skin : bool
        Also return the skin's mask: the body with its boundary at the
        half-way level of :func:`edge_threshold` (Otsu's boundary is millimetres
        outside a blurred skin; the body mask keeps it, as the template
        placement and the seeds were built on it).

    Returns
    -------
    body : ndarray of bool, same shape as ``volume.data``
        True inside the body.
    skin : ndarray of bool
        With ``skin=True``: the mask whose boundary is the skin.

    Raises
    ------
    ValueError
        Bad volume or parameters.

    References
    ----------
    Kojima et al. (skin contours per slice); Otsu 1979 (the threshold).
    """
    data = _check_volume(volume)
    if not min_area_mm2 >= 0:
        raise ValueError(f"min_area_mm2 must be >= 0, got {min_area_mm2}")
    if not smooth_mm > 0:
        raise ValueError(f"smooth_mm must be positive, got {smooth_mm}")
    sm = _smoothed(data, volume.spacing, smooth_mm)
    t = body_threshold(volume, smooth_mm) if threshold is None else float(threshold)
    pixel_area = float(volume.spacing[0] * volume.spacing[1])
    body = _components(sm > t, pixel_area, min_area_mm2)
    if not skin:
        return body
    # the skin: the same components, their boundary moved to the half-way level (threshold measured on
    # every 4th slice: one level for the stack, a quarter of the distance transforms)
    t_skin = edge_threshold(sm[:, :, ::4], body[:, :, ::4], volume.spacing)
    return body, _components(sm > t_skin, pixel_area, min_area_mm2)


def _components(tissue: np.ndarray, pixel_area: float, min_area_mm2: float) -> np.ndarray:
    lab, n = ndimage.label(tissue, structure=_INPLANE)
    if n:
        area = np.bincount(lab.ravel(), minlength=n + 1) * pixel_area
        keep = area >= min_area_mm2
        keep[0] = False
        tissue = keep[lab]
    return _fill_holes_per_slice(tissue)


def _fill_holes_per_slice(mask: np.ndarray) -> np.ndarray:
    """``binary_fill_holes(mask, structure=_INPLANE)``: each slice's holes filled, in one labelling.

    With the in-plane structure scipy's fill propagates the outside from the
    slices' edges only (nothing connects along ``k``, so the first and last
    slices are no border); it repeats a dilation until nothing changes, ~0.3 s
    per whole-body station. The same set is the background's in-plane
    components (8-connected, the structure's) that touch a slice's edge: one
    ``label`` pass.
    """
    bg, n = ndimage.label(~mask, structure=_INPLANE)
    if n == 0:
        return mask.copy()
    outside = np.zeros(n + 1, dtype=bool)
    outside[np.concatenate([bg[0].ravel(), bg[-1].ravel(), bg[:, 0].ravel(), bg[:, -1].ravel()])] = True
    outside[0] = False                        # label 0 is the mask itself
    return ~outside[bg]
