"""The density rule's bones refined from a prior section and the image, slice by slice (beyond the paper).

The density-threshold rule (:mod:`bonecap.segmentation.density`) keeps, per
axial slice, the bright candidate region nearest a seed. On a plate-like bone
that is a fragment: the iliac wing's and the scapular blade's middle is cortex
only (a signal void on every sequence), their marrow-rich rims are separate
regions of which one is kept, and the cortex around any marrow is never a
candidate (hip bones, scapulae and vertebrae: Dice 0.2-0.5 against the truth on
the phantoms). Once the template is warped onto the subject, its section of the
bone in a slice is a prior good to ~2 mm (the personal skeleton's label map,
:func:`bonecap.build_mri.personal_labels`; Dice 0.74-0.95 there). This module
moves that prior's edge to what the image shows, pixel by pixel:

- **bone evidence** (:func:`bone_evidence`): the marrow -- the density rule's
  own candidates (the top third of intensities in the body, sparse ones dropped)
  and every pixel brighter than the muscle level by more than ``muscle_band``
  (where fat and marrow fill much of a slice, a kneecap's marrow can lie below
  the top third) -- and the cortex (darker than half the slice's muscle
  level: cortical bone has no signal, and half-way from it to muscle is the
  partial-volume edge of a cortex in muscle);
- **muscle-like** pixels: within ``muscle_band`` of the muscle level and not on
  the rim of any marrow-bright pixel: no bone tissue looks like that;
- the **refined section** (:func:`refine_section`): the prior's pixels that do
  not look like muscle, the prior's one-pixel rim where there is marrow or
  cortex or where it borders the marrow inside the prior (the partial-volume
  edge of the bone's own marrow with its cortex), and the prior's interior
  (``core_px`` in from its edge) whatever it looks like: haematopoietic (red)
  marrow is intermediate on T1 and must not be cut out of a vertebral body;
  only the edge is corrected.

Only the rim of the bone's *own* marrow counts: fat is as bright as marrow,
and the rim of the epidural and paravertebral fat round a vertebra, or of the
bone's marrow where its cortex is thinner than a pixel, put a whole extra ring
round sections that were right (the six phantoms of docs/benchmarks.md: every
marrow's rim as evidence met the Dice target 46 times on the density rule's
bones of seeds 1-3, the bone's own 55; seed 1's thoracic vertebrae 2 -> 4 of 12).

A refined bone never takes a pixel of another bone's prior nor one a kept
label holds (:func:`refine_labels`' ``keep``: labels trusted as they are).

Public API
----------
- :func:`bone_evidence` ``(image, body_mask, pixel_mm, ...) -> BoneEvidence``
- :func:`refine_section` ``(prior, evidence, free=None, core_px=2) -> ndarray[bool]``
- :func:`refine_labels` ``(volume, prior, bones, keep=None, ...) -> ndarray[uint16]``

References
----------
Kojima et al. (the density-threshold rule this refines). The prior is a
model-based segmentation: Heimann, T. & Meinzer, H.-P. (2009), Statistical
shape models for 3D medical image segmentation: a review, Medical Image
Analysis 13(4), 543-563.
"""

from __future__ import annotations

from typing import Mapping, NamedTuple

import numpy as np
from scipy import ndimage

from bonecap.model import Volume
from bonecap.segmentation import cortical, density
from bonecap.segmentation._checks import check_body_mask, check_image, check_mask

__all__ = ["BoneEvidence", "bone_evidence", "refine_section", "refine_labels"]

_EIGHT = np.ones((3, 3), bool)


class BoneEvidence(NamedTuple):
    """What one axial slice shows (:func:`bone_evidence`), boolean masks of the slice's shape."""

    marrow: np.ndarray       #: marrow-bright: the density rule's candidates and pixels above the marrow level
    cortex: np.ndarray       #: signal void inside the body (darker than ``dark_fraction`` x muscle)
    muscle_like: np.ndarray  #: within ``muscle_band`` of the muscle level, off every marrow-bright pixel's rim
    body: np.ndarray         #: the body


def bone_evidence(image: np.ndarray, body_mask: np.ndarray, pixel_mm: float, *, muscle: float | None = None,
                  sigma_px: float = 0.7, fraction: float = 1 / 3, min_neighbours: int = 16,
                  dark_fraction: float = 0.5, muscle_band: float = 0.2, skin_band_mm: float = 3.0
                  ) -> BoneEvidence:
    """Where one axial slice shows bone tissue, and where it shows muscle.

    Parameters
    ----------
    image : ndarray (I, J)
        One axial slice (``Volume.data[:, :, k]``).
    body_mask : ndarray of bool (I, J)
        The body in this slice (:func:`bonecap.segmentation.skin.segment_body`).
    pixel_mm : float
        In-plane pixel size, mm.
    muscle : float, optional
        The slice's muscle level; by default :func:`~bonecap.segmentation.cortical.muscle_level`
        of the body without its outer ``skin_band_mm``.
    sigma_px : float
        In-plane Gaussian of the noise removal, pixels (0: the image is smoothed already).
    fraction, min_neighbours
        The density rule's candidates (:func:`~bonecap.segmentation.density.slice_candidates`).
    dark_fraction : float
        Cortex is darker than this times the muscle level (0.5: the partial-volume
        edge of a signal void in muscle).
    muscle_band : float
        Muscle-like: within this fraction of the muscle level; marrow: brighter
        than ``1 + muscle_band`` times it (or a candidate).
    skin_band_mm : float
        The body's outer band: the dark partial-volume pixels there are air at
        the skin, not cortex, and the rule's candidates touching it are fat. A
        pixel brighter than the marrow level counts wherever it lies (fat
        included): only those within a pixel of a bone's prior are used.

    Returns
    -------
    BoneEvidence
        ``marrow`` and ``cortex`` inside the body, ``muscle_like`` off every
        marrow-bright pixel's one-pixel rim (all three False when the slice has
        no muscle level: an empty body), and the ``body``.

    Raises
    ------
    ValueError
        Bad shapes or parameters.

    References
    ----------
    Kojima et al. (the density rule's candidates).
    """
    image = check_image(image)
    body = check_mask(body_mask, image.shape, "body_mask")
    if not pixel_mm > 0:
        raise ValueError(f"pixel_mm must be positive, got {pixel_mm}")
    if not 0 < dark_fraction < 1:
        raise ValueError(f"dark_fraction must be in (0, 1), got {dark_fraction}")
    if not 0 < muscle_band < 1:
        raise ValueError(f"muscle_band must be in (0, 1), got {muscle_band}")
    if not sigma_px >= 0:
        raise ValueError(f"sigma_px must be >= 0, got {sigma_px}")
    smooth = ndimage.gaussian_filter(image.astype(np.float32), sigma_px, mode="nearest") if sigma_px > 0 else image
    band_px = max(1, int(round(skin_band_mm / pixel_mm)))
    interior = ndimage.binary_erosion(body, _EIGHT, iterations=band_px, border_value=1)
    if muscle is None:
        muscle = cortical.muscle_level(smooth, interior)
    none = np.zeros(image.shape, bool)
    if not (np.isfinite(muscle) and muscle > 0):
        return BoneEvidence(none, none, none, body)
    cand = density.slice_candidates(smooth, body, pixel_mm, fraction=fraction, min_neighbours=min_neighbours,
                                    sigma_px=0.0, exclude_skin_band_mm=skin_band_mm)
    marrow = cand | ((smooth > (1 + muscle_band) * muscle) & body)
    rim = ndimage.binary_dilation(marrow, _EIGHT) & body
    dark = (smooth < dark_fraction * muscle) & interior
    # a prior pixel on any bright pixel's rim is not cut (it may be the bone's own cortex edge); which
    # rim pixels are added is refine_section's: only its own marrow's
    muscle_like = (np.abs(smooth - muscle) < muscle_band * muscle) & ~rim & body
    return BoneEvidence(marrow, dark, muscle_like, body)


def refine_section(prior: np.ndarray, evidence: BoneEvidence, *,
                   free: np.ndarray | None = None, core_px: int = 2) -> np.ndarray:
    """One bone's prior section in one slice, its edge moved to the image's evidence.

    The result is the prior without its muscle-like pixels, plus the pixels
    of its one-pixel rim (8-neighbours) that show marrow or cortex or border
    the marrow inside the prior, plus its interior ``core_px`` pixels in from
    its edge, all within ``free``.

    Parameters
    ----------
    prior : ndarray of bool (I, J)
        The bone's section by the prior (the personal skeleton's label map).
    evidence : BoneEvidence
        From :func:`bone_evidence`, of the same slice (or the same box of it).
    free : ndarray of bool (I, J), optional
        Where the bone may be (not another bone's prior, not a kept label);
        everywhere by default.
    core_px : int
        The prior's interior this many pixels in from its edge is kept whatever
        the image shows (0: none).

    Returns
    -------
    ndarray of bool (I, J)

    Raises
    ------
    ValueError
        Masks of different shapes, a negative ``core_px``.
    """
    prior = check_mask(prior, np.shape(prior), "prior")
    if prior.ndim != 2:
        raise ValueError(f"prior must be one 2-D slice mask, got shape {prior.shape}")
    if not isinstance(evidence, BoneEvidence):
        raise ValueError(f"evidence must be a BoneEvidence (bone_evidence's result), got {type(evidence).__name__}")
    marrow, cortex, muscle_like, body = (check_mask(m, prior.shape, f"evidence.{f}")
                                         for m, f in zip(evidence, evidence._fields))
    free = check_mask(free, prior.shape, "free", allow_none=True)
    if int(core_px) != core_px or core_px < 0:
        raise ValueError(f"core_px must be an integer >= 0, got {core_px}")
    if not prior.any():
        return np.zeros(prior.shape, bool)
    own_rim = ndimage.binary_dilation(marrow & prior, _EIGHT) & body
    out = (prior & ~muscle_like) | (ndimage.binary_dilation(prior, _EIGHT) & (marrow | cortex | own_rim))
    if core_px:
        out |= ndimage.binary_erosion(prior, _EIGHT, iterations=int(core_px))
    return out & free


def refine_labels(volume: Volume, prior: np.ndarray, bones: Mapping[str, int], *, keep: np.ndarray | None = None,
                  body_mask: np.ndarray | None = None, sigma_px: float = 0.7, core_px: int = 2,
                  **evidence_options) -> np.ndarray:
    """A station's label map: the prior's sections of ``bones`` refined by the image, slice by slice.

    Parameters
    ----------
    volume : Volume
        Axial stack: ``data[i, j, k]`` with ``k`` the slice axis.
    prior : ndarray of int (I, J, K)
        Label map on the volume's grid (the personal skeleton's,
        :func:`bonecap.build_mri.personal_labels`); 0 is background.
    bones : dict of str -> int
        The bones to refine and their ids in ``prior`` (the density rule's bones).
    keep : ndarray of int (I, J, K), optional
        Labels taken as they are, in the same id space (a rule's sections one
        trusts more than the prior): no refined bone takes their pixels.
    body_mask : ndarray of bool (I, J, K), optional
        The body (:func:`bonecap.segmentation.skin.segment_body` when not given).
    sigma_px : float
        In-plane Gaussian of the noise removal, pixels, per slice.
    core_px : int
        See :func:`refine_section`.
    **evidence_options
        ``dark_fraction``, ``muscle_band``, ``fraction``, ``min_neighbours``,
        ``skin_band_mm`` of :func:`bone_evidence`.

    Returns
    -------
    ndarray of uint16 (I, J, K)
        ``keep``'s labels; each of ``bones`` refined; every other bone of
        ``prior`` where neither holds the pixel. A pixel two refined bones'
        rims reach goes to the one with the smaller id.

    Raises
    ------
    ValueError
        Not a Volume, maps of another shape, ids outside 1..65535.
    """
    if not isinstance(volume, Volume):
        raise ValueError(f"volume must be a bonecap.model.Volume, got {type(volume).__name__}")
    data = np.asarray(volume.data)
    prior = np.asarray(prior)
    if prior.shape != data.shape:
        raise ValueError(f"prior must have the volume's shape {data.shape}, got {prior.shape}")
    if keep is not None:
        keep = np.asarray(keep)
        if keep.shape != data.shape:
            raise ValueError(f"keep must have the volume's shape {data.shape}, got {keep.shape}")
    bad = {b: i for b, i in bones.items() if not 1 <= int(i) <= 65535}
    if bad:
        raise ValueError(f"label ids must be in 1..65535, got {bad}")
    unknown = set(evidence_options) - {"dark_fraction", "muscle_band", "fraction", "min_neighbours", "skin_band_mm"}
    if unknown:
        raise ValueError(f"unknown option(s) {sorted(unknown)}")
    body_mask = check_body_mask(volume, body_mask)
    sp = volume.spacing
    pixel_mm = float(0.5 * (sp[0] + sp[1]))
    refine_ids = np.array(sorted(int(i) for i in bones.values()), dtype=np.int64)

    present = np.isin(prior, refine_ids)
    out = np.where(present, 0, prior).astype(np.uint16)
    if keep is not None:
        kept = keep > 0
        out[kept] = keep[kept]
    else:
        kept = np.zeros(data.shape, bool)
    for k in np.flatnonzero(present.any(axis=(0, 1))):
        pk = prior[:, :, k]
        img = ndimage.gaussian_filter(data[:, :, k].astype(np.float32), sigma_px, mode="nearest") \
            if sigma_px > 0 else data[:, :, k]
        evidence = bone_evidence(img, body_mask[:, :, k], pixel_mm, sigma_px=0.0, **evidence_options)
        taken = kept[:, :, k].copy()
        sl_out = out[:, :, k]
        for i in refine_ids:
            mine = pk == i
            if not mine.any():
                continue
            # the bone's box and a pixel around it: the rim and the dilation reach no farther
            ii, jj = np.nonzero(mine)
            box = (slice(max(ii.min() - 1, 0), ii.max() + 2), slice(max(jj.min() - 1, 0), jj.max() + 2))
            free = ~taken[box] & ~((pk[box] > 0) & ~mine[box])
            got = refine_section(mine[box], BoneEvidence(*(m[box] for m in evidence)), free=free, core_px=core_px)
            # an earlier bone's refined pixels stay its own
            got &= ~taken[box]
            sl_out[box][got] = i
            taken[box] |= got
    return out
