"""The cortical-edge rule of Kojima et al.: long bones, one axial slice at a time.

On MRI a long bone (femur, tibia, fibula, humerus, radius, ulna) is bright
marrow inside a dark cortical ring, in muscle of middle intensity. The bone's
outer contour is where the signal, going outwards, turns from cortical-low to
muscle-mid. Per slice:

1. :func:`find_marrow`: the marrow near the (approximate) seed -- a compact
   region brighter than the surrounding muscle, not touching the skin (fat is
   bright too, but subcutaneous fat always reaches the skin, marrow never:
   it is enclosed by its cortex).
2. :func:`cortical_contour`: rays cast from the marrow; along each ray's
   profile the contour is the point where the signal rises from its cortical
   minimum back half-way to the muscle level (or, where the cortex is thinner
   than a pixel and shows no dip, where it falls half-way from marrow to
   muscle). The polygon of those points, united with the marrow, is filled.
3. :func:`cortical_edge_slice` does both.

Images are single axial slices ``image[i, j]`` (a ``Volume.data[:, :, k]``;
LPS world through the volume's affine); seeds are pixel coordinates ``(i, j)``.
Half-way levels put the contour at the 50 % partial-volume point of the edge,
the same convention as a label map that gives a voxel to the tissue covering
at least half of it.

Public API
----------
- :func:`muscle_level` ``(image, mask, nbins=64) -> float``,
  :func:`local_muscle_level` ``(image, seed_ij, pixel_mm, body_mask=None, radius_mm=65.0) -> float``
- :func:`detach_from_skin` ``(candidates, body, inner, pixel_mm, neck_mm=1.5) -> (labels, n)``
- :func:`enclosed_marrow` ``(image, body, muscle, pixel_mm, dark_below=0.8, max_area_mm2=150.0) -> ndarray[bool]``,
  :func:`marrow_candidates` ``(image, body, muscle, pixel_mm, marrow_over_muscle=1.2, enclosed_max_mm2=150.0) -> ndarray[bool]``
- :func:`find_marrow` ``(image, seed_ij, pixel_mm, body_mask=None, search_radius_mm=25.0, ...) -> ndarray[bool]``
- :func:`cortical_contour` ``(image, marrow, pixel_mm, muscle, ...) -> ndarray[bool]``
- :func:`cortical_edge_slice` ``(image, seed_ij, pixel_mm, body_mask=None, search_radius_mm=25.0, ...) -> ndarray[bool]``

References
----------
Kojima et al., the MRI-based personal skeleton and motion-capture paper this
project follows (the cortical-edge rule for long bones).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage, special
from skimage.draw import polygon2mask

from bonecap.segmentation.density import fill_holes
from bonecap.segmentation._checks import check_image, check_mask, check_seed

__all__ = ["muscle_level", "local_muscle_level", "detach_from_skin", "enclosed_marrow", "marrow_candidates", "find_marrow", "cortical_contour", "cortical_edge_slice"]

_EIGHT = np.ones((3, 3), bool)


def _check_mask(mask, shape, name) -> np.ndarray:
    return check_mask(mask, shape, name, allow_none=True)


def _positive(name, value):
    if not value > 0:
        raise ValueError(f"{name} must be positive, got {value}")


def muscle_level(image: np.ndarray, mask: np.ndarray, nbins: int = 64) -> float:
    """The muscle intensity of a slice region: the mode of its histogram.

    Muscle is the largest tissue of a limb's or the trunk's cross-section, so
    the highest peak of the histogram of the region (smoothed over 1.5 bins,
    bins spanning the 1st to 99th percentile) is taken as the muscle level.
    The median would be pulled towards fat and marrow where they are
    abundant; the mode is not.

    Where bone fills most of the region (a sagittal or coronal slice through
    a knee or an elbow, where the condyles are the largest tissue) the mode
    is the marrow's. So the mode must lie in the darker of the two classes
    Otsu's threshold splits the region into (muscle below, fat and marrow
    above); when it does not, the mode of the darker class is taken. In a
    limb's cross-section the mode is muscle and lies below the threshold:
    nothing changes there.

    Parameters
    ----------
    image : ndarray (I, J)
    mask : ndarray of bool (I, J)
        Where to look (the body's interior near the bone).
    nbins : int

    Returns
    -------
    float
        NaN when the mask is empty.
    """
    image = check_image(image)
    mask = _check_mask(mask, image.shape, "mask")
    v = image[mask].astype(float)
    if v.size == 0:
        return float("nan")
    lo, hi = np.percentile(v, [1, 99])
    if hi <= lo:
        return float(lo)
    mode = _mode(v, lo, hi, nbins)
    if v.size >= 64:
        from skimage.filters import threshold_otsu

        split = float(threshold_otsu(v[(v >= lo) & (v <= hi)]))
        if mode > split and (v < split).sum() >= 32:
            # the bright class (marrow, fat) is the most common tissue here: muscle is the darker class's mode
            mode = _mode(v[v < split], lo, split, max(8, int(nbins * (split - lo) / (hi - lo))))
    return mode


def _mode(v: np.ndarray, lo: float, hi: float, nbins: int) -> float:
    h, edges = np.histogram(v, bins=int(nbins), range=(lo, hi))
    h = ndimage.gaussian_filter1d(h.astype(float), 1.5, mode="constant")
    b = int(np.argmax(h))
    return float(0.5 * (edges[b] + edges[b + 1]))


def local_muscle_level(image: np.ndarray, seed_ij, pixel_mm: float, body_mask: np.ndarray | None = None,
                       radius_mm: float = 65.0, *, skin_band_mm: float = 3.0, sigma_px: float = 0.7) -> float:
    """:func:`muscle_level` of the body's interior in a square of half-side ``radius_mm`` around a seed.

    Local, because the scanner's bias field changes the muscle level across a
    whole-body field of view by tens of percent. The outer ``skin_band_mm``
    of the body is left out (partial volume with air), and the same Gaussian
    as the rule's noise removal is applied first.
    """
    image = check_image(image)
    seed = check_seed(seed_ij)
    _positive("pixel_mm", pixel_mm)
    _positive("radius_mm", radius_mm)
    box, _ = _crop_box(seed, image.shape, radius_mm / pixel_mm)
    img = image[box].astype(np.float32)
    if sigma_px > 0:
        img = ndimage.gaussian_filter(img, sigma_px, mode="nearest")
    if body_mask is None:
        region = np.ones(img.shape, bool)
    else:
        region = _interior(_check_mask(body_mask, image.shape, "body_mask")[box], pixel_mm, skin_band_mm)
    return muscle_level(img, region)


def _crop_box(seed, shape, half_px):
    lo = np.maximum(np.floor(seed - half_px).astype(int), 0)
    hi = np.minimum(np.ceil(seed + half_px).astype(int) + 1, shape)
    return (slice(lo[0], max(hi[0], lo[0] + 1)), slice(lo[1], max(hi[1], lo[1] + 1))), lo


def _interior(body: np.ndarray, pixel_mm: float, skin_band_mm: float) -> np.ndarray:
    w = int(round(skin_band_mm / pixel_mm))
    if w < 1:
        return body
    return ndimage.binary_erosion(body, _EIGHT, iterations=w, border_value=1)


def detach_from_skin(candidates: np.ndarray, body: np.ndarray, inner: np.ndarray, pixel_mm: float,
                     neck_mm: float = 1.5) -> tuple[np.ndarray, int]:
    """Bright regions of a slice, with marrow cut loose from the fat it touches through the cortex.

    Marrow is told from fat by the skin test (fat reaches the skin band, marrow
    is enclosed by its cortex), but where the cortex is thinner than the slice
    thickness -- a condyle cut obliquely, a sagittal slice through the knee --
    partial volume leaves gaps in it and one bright region runs from the
    marrow through the gap into the fat and out to the skin. Such regions are
    eroded by ``neck_mm`` (a gap narrower than twice that closes), the eroded
    parts farther than ``neck_mm`` from the skin band are kept and grown back
    by ``neck_mm`` inside the region (each its own label); the parts at the
    skin are fat and dropped. Regions that do not touch the skin band are
    returned as they are.

    Parameters
    ----------
    candidates : ndarray of bool (I, J)
        The bright pixels (marrow and fat candidates) inside the body.
    body, inner : ndarray of bool (I, J)
        The body and its interior (the body without its skin band).
    pixel_mm : float
    neck_mm : float
        Half the widest gap that is cut.

    Returns
    -------
    labels : ndarray of int (I, J)
        Candidate regions, 0 background; regions touching the skin band are gone
        or replaced by their detached parts.
    n : int
        Number of labels.
    """
    from skimage.morphology import disk
    from skimage.segmentation import expand_labels

    candidates = np.asarray(candidates, bool)
    band = np.asarray(body, bool) & ~np.asarray(inner, bool)
    lab, n = ndimage.label(candidates, structure=_EIGHT)
    if n == 0:
        return lab, 0
    touching = np.zeros(n + 1, bool)
    touching[np.unique(lab[band & candidates])] = True
    touching[0] = False
    if not touching.any():
        return lab, n
    at_skin = touching[lab]
    r = max(1, int(round(neck_mm / pixel_mm)))
    fp = disk(r)
    core = ndimage.binary_erosion(at_skin, fp)
    clab, cn = ndimage.label(core, structure=_EIGHT)
    near = ndimage.binary_dilation(band, fp)
    drop = np.zeros(cn + 1, bool)
    drop[np.unique(clab[near & core])] = True
    drop[0] = True
    clab[drop[clab]] = 0
    grown = expand_labels(clab, r) * at_skin
    out = np.where(at_skin, 0, lab)
    keep = np.unique(grown[grown > 0])
    out[grown > 0] = n + np.searchsorted(keep, grown[grown > 0]) + 1
    # compact ids
    ids = np.unique(out[out > 0])
    remap = np.zeros(out.max() + 1, int)
    remap[ids] = np.arange(1, ids.size + 1)
    return remap[out], int(ids.size)


def rim_darkness(labels: np.ndarray, ids, image: np.ndarray, muscle: float, pixel_mm: float, *,
                 width_mm: float = 2.0, dark_below: float = 0.8) -> np.ndarray:
    """How much of each bright region's rim is dark: the cortex around marrow.

    The rim is the band ``width_mm`` wide just outside the region (pixels of
    no other bright region). Marrow is enclosed by cortical bone, which gives
    almost no signal, so most of its rim lies below ``dark_below`` x muscle;
    a bright speck of noise or fat between muscles is rimmed by muscle.

    Parameters
    ----------
    labels : ndarray of int (I, J)
        Bright regions (0 background), e.g. from :func:`detach_from_skin`.
    ids : sequence of int
        The regions to score.
    image : ndarray (I, J)
        The slice (the smoothed one the regions were thresholded on).
    muscle : float
        The muscle level.
    pixel_mm : float
    width_mm : float
        Width of the rim (at least one pixel).
    dark_below : float
        A rim pixel is dark below this fraction of ``muscle``.

    Returns
    -------
    ndarray of float, one per id
        The dark fraction of each region's rim (0 when it has none).

    References
    ----------
    Kojima et al. (the cortical-edge rule: bright marrow in a dark cortical ring).
    """
    from skimage.morphology import disk

    labels = np.asarray(labels)
    image = check_image(image)
    if labels.shape != image.shape:
        raise ValueError(f"labels must have the image's shape {image.shape}, got {labels.shape}")
    _positive("pixel_mm", pixel_mm)
    _positive("width_mm", width_mm)
    ids = np.asarray(ids, int).ravel()
    out = np.zeros(ids.size, float)
    if ids.size == 0:
        return out
    w = max(1, int(round(width_mm / pixel_mm)))
    fp = disk(w)
    dark = np.asarray(image) < dark_below * muscle
    boxes = ndimage.find_objects(labels, max_label=int(ids.max()))
    for n, i in enumerate(ids):
        box = boxes[i - 1]
        if box is None:
            continue
        box = tuple(slice(max(s.start - w, 0), min(s.stop + w, size)) for s, size in zip(box, labels.shape))
        lab = labels[box]
        rim = ndimage.binary_dilation(lab == i, fp) & (lab == 0)
        if rim.any():
            out[n] = float(dark[box][rim].mean())
    return out


#: Largest marrow region taken from inside a closed cortical ring whatever its brightness (mm^2):
#: a fibula's or a distal radius's canal (3-6 mm across) and more; a femur's marrow is bright anyway.
ENCLOSED_MAX_MM2 = 150.0


def enclosed_marrow(image: np.ndarray, body: np.ndarray, muscle: float, pixel_mm: float, *,
                    dark_below: float = 0.8, max_area_mm2: float = ENCLOSED_MAX_MM2) -> np.ndarray:
    """Marrow candidates that are enclosed by a closed ring of cortex, however dim.

    The bright-marrow test (marrow brighter than muscle) fails where the
    canal is narrower than a few pixels: a fibula's canal is 3-5 mm across,
    and at 1.8 mm pixels and 5 mm slices the dark cortex around it averages
    it down to the muscle's level (a phantom's right fibula, seed 2: canal
    pixels 1.05-1.25 x muscle, one above the 1.2 x threshold; 170 mm of shaft
    lost). Its ring still shows: cortical bone gives almost no signal, so
    the canal is a hole in the slice's dark pixels (below ``dark_below`` x
    muscle, within the body: the air around the body does not enclose it).
    Such holes up to ``max_area_mm2`` are candidates too; muscle enclosed by
    dark tissue on every side does not occur in a limb (tendons and
    ligaments are dark but solid).

    Parameters
    ----------
    image : ndarray (I, J)
        The slice after the rule's noise removal.
    body : ndarray of bool (I, J)
        The body in this slice.
    muscle : float
        The muscle level.
    pixel_mm : float
    dark_below : float
        Cortex is darker than this fraction of ``muscle`` (as :func:`rim_darkness`).
    max_area_mm2 : float
        Largest hole kept; 0 keeps none.

    Returns
    -------
    ndarray of bool (I, J)
        The holes' pixels.

    References
    ----------
    Kojima et al. (the cortical-edge rule: bright marrow in a dark cortical ring).
    """
    image = check_image(image)
    body = np.asarray(body, bool)
    if body.shape != image.shape:
        raise ValueError(f"body must have the image's shape {image.shape}, got {body.shape}")
    _positive("pixel_mm", pixel_mm)
    out = np.zeros(image.shape, bool)
    if not (max_area_mm2 > 0 and np.isfinite(muscle) and muscle > 0):
        return out
    dark = body & (image < dark_below * muscle)
    holes = fill_holes(dark) & ~dark
    if not holes.any():
        return out
    lab, n = ndimage.label(holes, structure=_EIGHT)
    area = np.bincount(lab.ravel(), minlength=n + 1) * pixel_mm ** 2
    keep = area <= max_area_mm2
    keep[0] = False
    return keep[lab]


def marrow_candidates(image: np.ndarray, body: np.ndarray, muscle: float, pixel_mm: float, *,
                      marrow_over_muscle: float = 1.2, enclosed_max_mm2: float = ENCLOSED_MAX_MM2) -> np.ndarray:
    """A slice's marrow pixels before they are split into regions (the body's, after noise removal).

    Brighter than ``marrow_over_muscle`` x ``muscle``, or inside a closed ring
    of cortex however dim (:func:`enclosed_marrow`, up to ``enclosed_max_mm2``;
    0: bright marrow only). :func:`find_marrow` and
    :func:`bonecap.segmentation.bones.segment_bones` both start from these.
    """
    cand = np.asarray(body, bool) & (image > marrow_over_muscle * muscle)
    return cand | enclosed_marrow(image, body, muscle, pixel_mm, max_area_mm2=enclosed_max_mm2)


def find_marrow(image: np.ndarray, seed_ij, pixel_mm: float, body_mask: np.ndarray | None = None,
                search_radius_mm: float = 25.0, *, muscle: float | None = None, marrow_over_muscle: float = 1.2,
                min_marrow_mm2: float = 6.0, skin_band_mm: float = 3.0, sigma_px: float = 0.7,
                exclude: np.ndarray | None = None, enclosed_max_mm2: float = ENCLOSED_MAX_MM2) -> np.ndarray:
    """The marrow of a long bone near an approximate seed, in one axial slice.

    Marrow is bright, but so is fat; what tells them apart is the cortex:
    marrow is enclosed by it, fat is not. Candidates are the pixels brighter
    than ``marrow_over_muscle`` times the local muscle level (after a light
    Gaussian, ``sigma_px``, that takes the noise off single pixels), and, with
    a body mask, the pixels inside a closed ring of dark cortex however dim
    (:func:`enclosed_marrow`, a canal narrower than a few pixels); their connected
    regions that touch the body's outer ``skin_band_mm`` (subcutaneous fat
    reaching the skin, skin capsules) are discarded, as are regions smaller
    than ``min_marrow_mm2`` (noise). Of the rest, the one nearest the seed
    within ``search_radius_mm`` is the marrow; its holes are filled. The seed
    may lie in muscle or fat, up to ``search_radius_mm`` from the marrow.

    Parameters
    ----------
    image : ndarray (I, J)
        One axial slice (LPS world via its volume's affine).
    seed_ij : (2,) float
        Approximate position of the bone, pixel coordinates ``(i, j)``.
    pixel_mm : float
        In-plane pixel size, mm.
    body_mask : ndarray of bool (I, J), optional
        The body in this slice; default everything (no skin exclusion).
    search_radius_mm : float
        How far from the seed the marrow may be.
    muscle : float, optional
        Muscle level; default :func:`muscle_level` of the body's interior
        around the seed.
    marrow_over_muscle : float
        Candidate threshold as a multiple of the muscle level (> 1).
    min_marrow_mm2 : float
        Smallest marrow region, mm^2.
    skin_band_mm : float
        Width of the outer body band whose touching regions are fat.
    sigma_px : float
        Gaussian for noise removal, pixels (0 = none).
    exclude : ndarray of bool (I, J), optional
        Pixels already given to another bone: regions overlapping them are
        not candidates.
    enclosed_max_mm2 : float
        Largest dim region inside a cortical ring taken as marrow
        (:func:`enclosed_marrow`; 0: bright marrow only).

    Returns
    -------
    ndarray of bool (I, J)
        The marrow, or all False when there is no marrow within reach (the
        bone is not in this slice).

    Raises
    ------
    ValueError
        Bad shapes or parameters.

    References
    ----------
    Kojima et al. (the cortical-edge rule: bright marrow in a dark cortex).
    """
    image = check_image(image)
    seed = check_seed(seed_ij)
    body = _check_mask(body_mask, image.shape, "body_mask")
    excl = None if exclude is None else _check_mask(exclude, image.shape, "exclude")
    _positive("pixel_mm", pixel_mm)
    _positive("search_radius_mm", search_radius_mm)
    if not marrow_over_muscle > 1:
        raise ValueError(f"marrow_over_muscle must be > 1, got {marrow_over_muscle}")
    out = np.zeros(image.shape, bool)
    # Work on a crop: the search disc plus room for the marrow region and the muscle estimate.
    box, lo = _crop_box(seed, image.shape, (search_radius_mm + 40.0) / pixel_mm)
    img = image[box].astype(np.float32)
    if sigma_px > 0:
        img = ndimage.gaussian_filter(img, sigma_px, mode="nearest")
    b = body[box]
    inner = _interior(b, pixel_mm, skin_band_mm) if body_mask is not None else b
    m = muscle_level(img, inner) if muscle is None else float(muscle)
    if not np.isfinite(m) or m <= 0:
        return out
    # Candidates over the whole body, so that fat reaching into the skin band is one region with it.
    if body_mask is not None:
        # bright, or a canal too narrow to show bright inside its closed ring of cortex
        cand = marrow_candidates(img, b, m, pixel_mm, marrow_over_muscle=marrow_over_muscle,
                                 enclosed_max_mm2=enclosed_max_mm2)
        # fat reaching the skin is dropped, marrow joined to it through a gap in the cortex cut loose
        lab, n = detach_from_skin(cand, b, inner, pixel_mm)
    else:
        # without a body the air around it would enclose it: bright marrow only
        lab, n = ndimage.label(b & (img > marrow_over_muscle * m), structure=_EIGHT)
    if n == 0:
        return out
    bad = np.zeros(n + 1, bool)
    bad[0] = True
    area = np.bincount(lab.ravel(), minlength=n + 1) * pixel_mm ** 2
    bad |= area < min_marrow_mm2
    if excl is not None:
        bad[np.unique(lab[excl[box]])] = True
    ii, jj = np.nonzero(~bad[lab])
    if ii.size == 0:
        return out
    d2 = (ii + lo[0] - seed[0]) ** 2 + (jj + lo[1] - seed[1]) ** 2
    best = int(np.argmin(d2))
    if d2[best] > (search_radius_mm / pixel_mm) ** 2:
        return out
    out[box] = fill_holes(lab == lab[ii[best], jj[best]])
    return out


def cortical_contour(image: np.ndarray, marrow: np.ndarray, pixel_mm: float, muscle: float, *,
                     body_mask: np.ndarray | None = None, n_rays: int = 96, max_radius_mm: float = 45.0,
                     max_cortex_mm: float = 8.0, dip_fraction: float = 0.06, profile_sigma_px: float = 0.5,
                     smooth_rays: int = 5, cortex_level: float = 0.0) -> np.ndarray:
    """The bone around a marrow region by its cortical edge, filled.

    Rays are cast from the marrow's centre (its pixel deepest inside it, so
    the centre lies in the marrow for any shape). Along each ray the image
    profile (bilinear, 1/4-pixel steps, after a light Gaussian) leaves the marrow
    at ``r_exit``; within ``max_cortex_mm`` beyond it:

    - if the profile dips below ``(1 - dip_fraction)`` x muscle (a visible
      cortex), the contour is where it rises from that minimum back towards
      the muscle level -- the turn from cortical-low to muscle-mid. For a
      cortex several pixels thick that is half-way between the minimum and
      the muscle level (the 50 % partial-volume point of the periosteal edge);
      a thinner cortex is blurred into a shallower dip whose half-way rise
      lies outside the bone, so the level moves towards the minimum with the
      dip's depth ``D = (muscle - min) / (muscle - cortex_level)``: for a
      layer of thickness ``t`` under a Gaussian blur ``s``, ``D = 2 Phi(t / 2s)
      - 1`` and the outer edge lies ``(Phi(t / s) - 1/2) / D`` of the way from
      the muscle level down to the minimum (1/2 for a thick cortex, 1 for a
      vanishing one; ``s`` cancels out);
    - otherwise (a cortex thinner than a pixel), the contour is where the
      profile falls below half-way between the marrow level (median of the
      marrow) and the muscle level.

    The ray radii are median-filtered around the circle (``smooth_rays``) so
    one ray that ran into a vessel or a neighbouring bone does not make a
    spike; the polygon of the contour points is filled and united with the
    marrow, and holes are filled.

    Parameters
    ----------
    image : ndarray (I, J)
        One axial slice.
    marrow : ndarray of bool (I, J)
        The marrow (:func:`find_marrow`); empty gives an empty result.
    pixel_mm : float
        In-plane pixel size, mm.
    muscle : float
        Muscle level (:func:`muscle_level`).
    body_mask : ndarray of bool (I, J), optional
        The result is clipped to it.
    n_rays, max_radius_mm, max_cortex_mm, dip_fraction, profile_sigma_px, smooth_rays
        Number of rays; their length from the centre (mm); the thickest
        cortex looked for beyond the marrow (mm); the depth of a visible
        cortical dip as a fraction of the muscle level; the Gaussian (pixels)
        that takes the noise off the profiles (a median would erase a thin
        cortex); circular median window over the rays (odd, 1 = none).
    cortex_level : float
        The signal of cortical bone itself, for the dip's depth. Default 0:
        cortical bone's T2* (< 1 ms) leaves it a signal void in spin-echo and
        gradient-echo images alike (the real knee's posterior femoral cortex:
        7 % of the muscle level, its noise floor).

    Returns
    -------
    ndarray of bool (I, J)

    Raises
    ------
    ValueError
        Bad shapes or parameters.

    References
    ----------
    Kojima et al. (the cortical-edge rule).
    """
    image = check_image(image)
    marrow = _check_mask(marrow, image.shape, "marrow")
    _positive("pixel_mm", pixel_mm)
    _positive("max_radius_mm", max_radius_mm)
    _positive("max_cortex_mm", max_cortex_mm)
    if int(n_rays) != n_rays or n_rays < 8:
        raise ValueError(f"n_rays must be an integer >= 8, got {n_rays}")
    if not 0 < dip_fraction < 1:
        raise ValueError(f"dip_fraction must be in (0, 1), got {dip_fraction}")
    out = np.zeros(image.shape, bool)
    if not marrow.any() or not np.isfinite(muscle):
        return out
    ii, jj = np.nonzero(marrow)
    mlo = np.array([ii.min(), jj.min()])
    mhi = np.array([ii.max(), jj.max()])
    # The marrow's centre: its deepest pixel, by a distance transform on the marrow's own box and a
    # ring of background (the same distances as over a larger crop: a pixel beyond the ring is no
    # nearer than the ring straight across; the first maximum in the same order).
    depth = ndimage.distance_transform_edt(np.pad(marrow[mlo[0]:mhi[0] + 1, mlo[1]:mhi[1] + 1], 1))[1:-1, 1:-1]
    centre_ij = np.array(np.unravel_index(int(np.argmax(depth)), depth.shape)) + mlo
    # How far the rays are read. A ray leaves the marrow (bilinear value < 0.5) once no marrow pixel
    # is within a pixel's cell of it: by the farthest corner of the marrow's box plus sqrt(2) (the
    # marrow trimmed and filled below stays in that box). Nothing past ``max_cortex_mm`` beyond
    # that exit is looked at, so reading on to ``max_radius_mm`` (45 mm, for a marrow that does not
    # end) cost 3-4x the samples and a crop ~6x the area for the same contour.
    reach = max_radius_mm / pixel_mm + 2
    corners = np.array([[a, b] for a in (mlo[0], mhi[0]) for b in (mlo[1], mhi[1])], float)
    far = float(np.max(np.linalg.norm(corners - centre_ij, axis=1)))
    need = min(reach, far + np.sqrt(2.0) + 2 * 0.25 + max_cortex_mm / pixel_mm)
    # Crop around the centre plus the longest ray read, and 4 pixels more: the profile's Gaussian
    # (``truncate`` 4 x 0.5 px: 2 px) and the bilinear read (1 px) then see the pixels they would
    # see in the whole image, so the crop changes no sample.
    pad = int(np.ceil(need)) + 4 + int(4.0 * profile_sigma_px + 0.5)
    # It holds the marrow and 3 pixels around it too (its level is read through the same Gaussian;
    # a marrow reaching past the longest ray is trimmed and filled whole), and is never larger than
    # the marrow's box plus the longest ray (where a ray near the image's edge still reads the
    # Gaussian's edge).
    lo = np.maximum(np.minimum(centre_ij - pad, mlo - 3), np.maximum([int(mlo[0] - reach), int(mlo[1] - reach)], 0))
    hi = np.minimum(np.maximum(centre_ij + pad, mhi + 3) + 1,
                    np.minimum([int(mhi[0] + reach) + 1, int(mhi[1] + reach) + 1], image.shape))
    box = (slice(int(lo[0]), int(hi[0])), slice(int(lo[1]), int(hi[1])))
    # The profiles get only a light Gaussian: a 3x3 median would erase a cortex one pixel thin
    # (3 of its 9 pixels are dark), which is exactly the cortex whose dip places the edge.
    img = image[box].astype(np.float32)
    if profile_sigma_px > 0:
        img = ndimage.gaussian_filter(img, profile_sigma_px, mode="nearest")
    mar = marrow[box]
    centre = (centre_ij - lo).astype(float)
    marrow_level = float(np.median(img[mar]))
    m = float(muscle)
    # The marrow was found at a low threshold (a little above muscle); for the union below
    # keep only its part above half-way to muscle, which lies inside the bone.
    core = mar & (img > 0.5 * (marrow_level + m))
    if core.any():
        mar = fill_holes(core)

    step = 0.25
    r = np.arange(0.0, reach, step)                                      # (S,) px
    r = r[r <= need + step]
    theta = np.linspace(0.0, 2 * np.pi, int(n_rays), endpoint=False)     # (R,)
    pi = centre[0] + np.cos(theta)[:, None] * r[None, :]
    pj = centre[1] + np.sin(theta)[:, None] * r[None, :]
    prof = ndimage.map_coordinates(img, [pi, pj], order=1, mode="nearest")
    inside = ndimage.map_coordinates(mar.astype(np.float32), [pi, pj], order=1, mode="constant") >= 0.5
    S = r.size
    idx = np.arange(S)[None, :]
    # first sample out of the marrow (rays that never leave it end at the crop's reach)
    e = np.where((~inside).any(axis=1), np.argmax(~inside, axis=1), S - 1)[:, None]
    win = (idx >= e - int(1 / step)) & (r[None, :] <= r[e] + max_cortex_mm / pixel_mm)
    # The cortical dip is the first excursion below the muscle level after the marrow: from
    # the first sample under it (f) to the first sample back above it (g). Taking the first
    # excursion, not the window's minimum, keeps a darker spot in the muscle beyond from
    # being mistaken for the cortex.
    below = win & (prof < m)
    f = np.where(below.any(axis=1), np.argmax(below, axis=1), S)[:, None]
    back = win & (idx > f) & (prof >= m)
    g = np.where(back.any(axis=1), np.argmax(back, axis=1), np.max(np.where(win, idx, 0), axis=1))[:, None]
    exc = (idx >= f) & (idx <= g)
    kmin = np.argmin(np.where(exc, prof, np.inf), axis=1)[:, None]
    pmin = np.take_along_axis(prof, kmin, axis=1)
    dip = (f[:, 0] < S) & (pmin[:, 0] < (1.0 - dip_fraction) * m)
    # Visible cortex: the periosteal edge on the dip's rise back to muscle. A cortex several
    # pixels thick reaches the cortical level and its edge is the half-way rise. A thinner one is
    # blurred (pixel, point spread) into a dip that never gets there, and the half-way rise of
    # that dip lies outside the bone (0.3-0.7 mm at 1.8 mm pixels for a 1-2.5 mm cortex: thin
    # bones came out 10-20 % too large). For a layer of thickness t under a Gaussian blur s the
    # dip's depth D = (m - min) / (m - cortex) = 2 Phi(t / 2s) - 1 gives t / s, and the profile
    # at the outer edge lies rho = (Phi(t / s) - 1/2) / D of the way from the muscle level down
    # to the minimum: 1/2 for a thick cortex, -> 1 (the minimum) for a thin one, whatever s.
    depth = np.clip((m - pmin[:, 0]) / max(m - float(cortex_level), 1e-9), 1e-6, 1.0 - 1e-9)
    half_t = special.ndtri(0.5 * (1.0 + depth))                      # t / 2s
    rho = (special.ndtr(2.0 * half_t) - 0.5) / depth
    level = (m - rho * (m - pmin[:, 0]))[:, None]
    rise = (idx > kmin) & (idx <= g) & (prof > level)
    k_rise = np.where(rise.any(axis=1), np.argmax(rise, axis=1), g[:, 0])
    # (sub-sample: linear between the sample found and the one before it)
    p1 = np.take_along_axis(prof, k_rise[:, None], axis=1)[:, 0]
    p0 = np.take_along_axis(prof, np.maximum(k_rise - 1, 0)[:, None], axis=1)[:, 0]
    frac = np.clip((level[:, 0] - p0) / np.where(p1 > p0, p1 - p0, 1.0), 0.0, 1.0)
    r_dip = np.maximum(r[k_rise] - step * (1.0 - frac), r[kmin[:, 0]])
    # no visible cortex: first sample in the window below half-way (marrow -> muscle)
    fall = win & (prof < 0.5 * (marrow_level + m))
    k_fall = np.where(fall.any(axis=1), np.argmax(fall, axis=1), e[:, 0])
    radius = np.where(dip, r_dip, r[k_fall] - step * 0.5)
    if smooth_rays > 1:
        radius = ndimage.median_filter(radius, size=int(smooth_rays), mode="wrap")
    poly = np.stack([centre[0] + np.cos(theta) * radius, centre[1] + np.sin(theta) * radius], axis=1)
    bone = fill_holes(polygon2mask(mar.shape, poly) | mar)
    out[box] = bone
    if body_mask is not None:
        out &= _check_mask(body_mask, image.shape, "body_mask")
    return out


def cortical_edge_slice(image: np.ndarray, seed_ij, pixel_mm: float, body_mask: np.ndarray | None = None,
                        search_radius_mm: float = 25.0, *, muscle: float | None = None,
                        marrow_over_muscle: float = 1.2, min_marrow_mm2: float = 6.0, skin_band_mm: float = 3.0,
                        n_rays: int = 96, max_radius_mm: float = 45.0, max_cortex_mm: float = 8.0,
                        dip_fraction: float = 0.06, sigma_px: float = 0.7, exclude: np.ndarray | None = None
                        ) -> np.ndarray:
    """One long bone in one axial slice by the cortical-edge rule, filled.

    :func:`find_marrow` near the seed, then :func:`cortical_contour` from it.
    Returns an empty mask when no marrow is within ``search_radius_mm`` of the
    seed (the bone has left the field of view, or the seed is wrong).

    Parameters
    ----------
    image : ndarray (I, J)
        One axial slice (``Volume.data[:, :, k]``, LPS world via the volume's
        affine).
    seed_ij : (2,) float
        Approximate position of the bone in pixel coordinates ``(i, j)``; may
        be ~20 mm off, in muscle or fat.
    pixel_mm : float
        In-plane pixel size, mm.
    body_mask : ndarray of bool (I, J), optional
        The body in this slice (recommended: it lets fat reaching the skin be
        told from marrow).
    search_radius_mm : float
        How far from the seed the marrow may be.
    muscle : float, optional
        Muscle level; default :func:`muscle_level` around the seed.
    marrow_over_muscle, min_marrow_mm2, skin_band_mm, sigma_px, exclude
        See :func:`find_marrow`.
    n_rays, max_radius_mm, max_cortex_mm, dip_fraction
        See :func:`cortical_contour`.

    Returns
    -------
    ndarray of bool (I, J)

    Raises
    ------
    ValueError
        Bad shapes or parameters.

    References
    ----------
    Kojima et al. (the cortical-edge rule).
    """
    image = check_image(image)
    seed = check_seed(seed_ij)
    _positive("pixel_mm", pixel_mm)
    body = None if body_mask is None else _check_mask(body_mask, image.shape, "body_mask")
    if muscle is None:
        muscle = local_muscle_level(image, seed, pixel_mm, body, search_radius_mm + 40.0,
                                    skin_band_mm=skin_band_mm, sigma_px=sigma_px)
    marrow = find_marrow(image, seed, pixel_mm, body, search_radius_mm, muscle=muscle,
                         marrow_over_muscle=marrow_over_muscle, min_marrow_mm2=min_marrow_mm2,
                         skin_band_mm=skin_band_mm, sigma_px=sigma_px, exclude=exclude)
    return cortical_contour(image, marrow, pixel_mm, muscle, body_mask=body, n_rays=n_rays,
                            max_radius_mm=max_radius_mm, max_cortex_mm=max_cortex_mm, dip_fraction=dip_fraction)
