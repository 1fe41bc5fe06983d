"""MRI-visible marker capsules: find the oil spheres on the skin and their centres (build-subject stage 6).

Capsules are small oil spheres (8 mm) taped on the skin, brighter than fat on
T2-weighted images. With slices 2.5-5 mm thick a capsule shows as two or
three discs of different radius and brightness in consecutive slices; its
centre lies at an unknown depth between slice planes. :func:`find_capsules`
finds them and recovers the centre from the partial-volume cross-sections;
:func:`match_capsules` names them from expected marker positions.

Method
------
1. **Body and protrusions.** Foreground is everything brighter than the
   air/tissue threshold (Otsu on log intensity). The body is what is brighter
   than half the median tissue level; per slice its holes are filled and it
   is *opened* by a disc wider than the capsule: a capsule sticks out
   of the body and touches it at one point, so the opening keeps the body
   and removes the capsule discs. Foreground minus the opened body gives the
   protrusions; they are linked across consecutive slices as connected
   components (a capsule's discs overlap in-plane).
2. **Sphere fit with the slice profile.** Each candidate is fitted with
   the image a sphere of known radius ``R`` makes: the value of a voxel is
   ``m * f(c) + b`` where ``f`` is the fraction of the voxel's box (the pixel
   in-plane times the *slice thickness* along the normal, the renderer's and
   the scanner's partial-volume average) inside the sphere of centre ``c``.
   ``f`` is exact along the slice normal (the sphere's chord through each
   in-plane sub-sample, clipped to the slice profile) and sub-sampled
   in-plane; it is continuous in ``c``. ``m`` and ``b``
   are solved linearly inside the nonlinear least squares on ``c``
   (variable projection). The through-plane centre therefore comes from how
   the sphere's content splits between slices -- the per-slice integral of a
   sphere slab ``pi (R^2 (z1 - z0) - ((z1 - zc)^3 - (z0 - zc)^3) / 3)`` -- and
   the discs' radii, the in-plane centre from the discs' centres. Voxels of
   the body (dilated by one pixel) are left out: only air and oil are
   modelled.
3. **Acceptance.** A candidate is a capsule when its fitted oil level ``m``
   is at least ``min_contrast`` times the local fat level (median of the
   bright body voxels within 20 mm: the bias field moves it across the field
   of view by more than oil exceeds fat), most of the fitted sphere lies in
   the voxels the fit saw (``min_seen``), and the fit explains it (relative RMS
   residual below ``max_residual``): ears, toes and fingertips stick out too
   but are neither brighter than fat nor spheres.

Frames: the grid's own index space for the fit (axes may be oblique, they
must be orthogonal); centres are returned in **LPS mm** through the
volume's ``voxel_to_lps`` affine.

References
----------
- Gonzalez Ballester MA, Zisserman AP, Brady M. Estimation of the partial
  volume effect in MRI. *Med Image Anal* 6(4):389-405, 2002 (partial-volume
  voxel model).
- Golub GH, Pereyra V. The differentiation of pseudo-inverses and nonlinear
  least squares problems whose variables separate. *SIAM J Numer Anal*
  10(2):413-432, 1973 (variable projection).
- Kuhn HW. The Hungarian method for the assignment problem. *Naval Res
  Logist Q* 2:83-97, 1955 (:func:`match_capsules`).
"""

from __future__ import annotations

import math
from typing import Any, Mapping, Sequence

import numpy as np
from scipy import ndimage, optimize

from bonecap.model import Volume
from bonecap.segmentation import density

__all__ = ["find_capsules", "match_capsules", "sphere_slab_volume"]


def sphere_slab_volume(z0: np.ndarray, z1: np.ndarray, zc: float, radius: float) -> np.ndarray:
    """Volume of a sphere between two parallel planes (analytic).

    Parameters
    ----------
    z0, z1 : array_like
        Plane positions along the slice normal (mm), ``z0 <= z1``.
    zc : float
        Sphere centre along the same axis (mm).
    radius : float
        Sphere radius (mm).

    Returns
    -------
    ndarray
        ``integral over [z0, z1] of pi (R^2 - (z - zc)^2)_+ dz`` (mm^3).
    """
    a = np.clip(np.asarray(z0, float) - zc, -radius, radius)
    b = np.clip(np.asarray(z1, float) - zc, -radius, radius)
    return np.pi * (radius * radius * (b - a) - (b ** 3 - a ** 3) / 3.0)


def _body_mask(data: np.ndarray, thr: float, open_radius_mm: float, spacing: np.ndarray) -> np.ndarray:
    """Per slice: foreground, holes filled, opened by a disc (removes what sticks out less than the disc).

    The opening is done with two in-plane distance transforms (erode: farther than r from the
    background; dilate back: within r of what is left), far cheaper than a large structuring element.
    """
    fg = data > thr
    out = np.zeros_like(fg)
    samp = (float(spacing[0]), float(spacing[1]))
    for k in range(fg.shape[2]):
        sl = fg[:, :, k]
        if not sl.any():
            continue
        # Slice by slice in 2-D (a 3-D transform with a huge z step costs several times more), on the
        # slice's bounding box: the same distances there (the nearest background of a pixel in the box is
        # never farther than the box's empty ring; a core pixel is in the box), for a fraction of the
        # pixels. Padded so that the FOV border counts as background for the erosion.
        sl = density.fill_holes(sl)
        ii, jj = np.flatnonzero(sl.any(axis=1)), np.flatnonzero(sl.any(axis=0))
        box = (slice(ii[0], ii[-1] + 1), slice(jj[0], jj[-1] + 1))
        sub = sl[box]
        core = ndimage.distance_transform_edt(np.pad(sub, 1), sampling=samp)[1:-1, 1:-1] > open_radius_mm
        if core.any():
            out[box + (k,)] = (ndimage.distance_transform_edt(~core, sampling=samp) <= open_radius_mm) & sub
    return out


class _SphereModel:
    """Partial-volume fraction of a sphere in voxel boxes: exact along the slice normal, sub-sampled in-plane.

    For an in-plane sub-sample at distance ``rho`` from the sphere's axis along
    the slice normal the sphere is the chord ``[zc - h, zc + h]``, ``h = sqrt(R^2
    - rho^2)``; its overlap with the slice profile ``[z - T/2, z + T/2]`` over
    ``T`` is that sub-sample's fraction. It is continuous in the centre (the chord
    shrinks to nothing at the rim), so the fit needs no anti-aliasing, and it
    integrates the box slice profile exactly through the plane.
    """

    def __init__(self, ijk: np.ndarray, spacing: np.ndarray, thickness: float, radius: float, n_inplane: int):
        self.xy = ijk[:, :2] * spacing[:2]
        self.z = ijk[:, 2] * spacing[2]
        oi = (np.arange(n_inplane) + 0.5) / n_inplane - 0.5
        a, b = np.meshgrid(oi * spacing[0], oi * spacing[1], indexing="ij")
        self.offsets = np.stack([a.ravel(), b.ravel()], axis=1)
        self.radius = float(radius)
        self.half = float(thickness) / 2
        self.thickness = float(thickness)
        # what does not depend on the centre, once: the sub-samples' in-plane coordinates and the
        # slices' extents (the least squares evaluate the model ~100 times per capsule)
        sub = self.xy[:, None, :] + self.offsets[None, :, :]
        self._x, self._y = np.ascontiguousarray(sub[..., 0]), np.ascontiguousarray(sub[..., 1])
        self._top, self._bot = (self.z + self.half)[:, None], (self.z - self.half)[:, None]

    def fraction(self, c: np.ndarray) -> np.ndarray:
        dx = self._x - c[0]
        dy = self._y - c[1]
        rho2 = dx * dx
        rho2 += dy * dy
        h = np.sqrt(np.maximum(self.radius ** 2 - rho2, 0.0))
        top = np.minimum(self._top, c[2] + h)
        top -= np.maximum(self._bot, c[2] - h)
        return np.maximum(top, 0.0).mean(axis=1) / self.thickness


def _fit_sphere(values: np.ndarray, model: _SphereModel, c0: np.ndarray, pitch: float,
                fit_radius: bool = False):
    """Least squares on the centre (and radius); gain and offset solved linearly at each evaluation."""
    r0 = model.radius

    def linear(p):
        if fit_radius:
            model.radius = float(p[3])
        f = model.fraction(p[:3])
        A = np.c_[f, np.ones_like(f)]
        coef, *_ = np.linalg.lstsq(A, values, rcond=None)
        return f, coef

    def resid(p):
        f, coef = linear(p)
        return f * coef[0] + coef[1] - values

    best = None
    # Starts spread across one slice pitch: the split between slices is the only
    # through-plane evidence, and the cost can have a shallow second minimum.
    for dz in (-pitch / 3, 0.0, pitch / 3):
        start = c0 + np.array([0.0, 0.0, dz])
        if fit_radius:
            lo = np.r_[start - 50.0, 0.6 * r0]
            hi = np.r_[start + 50.0, 1.4 * r0]
            sol = optimize.least_squares(resid, np.r_[start, r0], diff_step=1e-3, method="trf", bounds=(lo, hi))
        else:
            sol = optimize.least_squares(resid, start, diff_step=1e-3, method="lm")
        if best is None or sol.cost < best.cost:
            best = sol
    f, coef = linear(best.x)
    radius = float(best.x[3]) if fit_radius else r0
    return best.x[:3], coef, float(np.sqrt(np.mean(best.fun ** 2))), radius


def find_capsules(volume: Volume, *, radius_mm: float = 4.0, body_mask: np.ndarray | None = None,
                  slice_thickness_mm: float | None = None, min_contrast: float = 1.1, max_residual: float = 0.12,
                  min_seen: float = 0.2, fit_radius: bool = False,
                  n_inplane: int | None = None, threshold: float | None = None, min_voxels: int = 8
                  ) -> tuple[np.ndarray, dict[str, Any]]:
    """Find oil capsules on the skin and fit their centres, including the depth between slices.

    Parameters
    ----------
    volume : Volume
        Any stack of parallel slices (axial station, forearm stack), affine
        ``voxel_to_lps`` (LPS mm) with orthogonal axes; ``k`` is the slice axis.
    radius_mm : float
        Capsule radius (the sphere is assumed, its radius known).
    body_mask : ndarray of bool (I, J, K), optional
        The body (e.g. the skin segmentation), with or without the capsules:
        it is opened per slice by a disc of radius ``radius_mm + 1.5`` mm,
        which removes them. Default: the voxels above half the median tissue
        level, holes filled, opened likewise.
    slice_thickness_mm : float, optional
        Slice profile thickness; default ``metadata["slice_thickness"]``, else
        the slice pitch.
    min_contrast : float
        Minimum fitted oil level over the local fat level (oil is ~1.3x fat).
    max_residual : float
        Maximum RMS fit residual relative to the fitted oil level.
    fit_radius : bool
        Also fit the radius (within 0.6-1.4 ``radius_mm``) when the
        capsules' size is not known well: a 10 % radius error costs ~0.5 mm
        in-plane and lowers the fitted oil level by the volume ratio
        (a smaller capsule than assumed may then fail ``min_contrast``).
    min_seen : float
        Minimum fraction of the fitted sphere's volume inside the voxels the
        fit used (outside the body): rejects a sphere fitted to a speck
        (real capsules: 0.3-0.65 at 1.8 mm pixels, the part by the skin is
        left out with the body).
    n_inplane : int, optional
        Sub-samples per pixel side for the partial-volume model (default:
        enough for ~0.25 mm); through the slice the model is exact.
    min_voxels : int
        Minimum number of voxels the fitted sphere fills by at least 10 %:
        fewer cannot show a sphere's shape, and any speck fits. An 8 mm
        capsule fills 27-37 voxels in the tiny phantom's forearm stacks and
        12-23 of 1.8 mm x 1.8 mm x 5 mm (the tests' analytic scenes); at
        4 mm x 4 mm x 15 mm (the tiny phantom's stations) 3-4, where the thin
        edge of a shoulder's skin at the last slice was taken for one.
    threshold : float, optional
        Air/tissue threshold (default: Otsu on the log of the volume).

    Returns
    -------
    centres : ndarray (N, 3)
        Capsule centres, LPS mm.
    info : dict
        ``index`` (N, 3) fractional voxel indices of the centres, ``oil_level``
        (N,, fitted ``m``), ``offset`` (N,, fitted background ``b``),
        ``fat_level`` (N,), ``residual`` (N,, relative RMS),
        ``seen`` (N,, see ``min_seen``), ``radius_mm`` (N,, fitted or
        the given one), ``slices`` (list of the slice
        indices each capsule touches),
        ``rejected`` (list of dicts: candidates turned down and why),
        ``threshold``.

    Raises
    ------
    ValueError
        Non-positive radius or thickness, ``min_voxels`` < 1, a ``body_mask``
        of another shape, non-orthogonal grid axes.
    """
    if not float(radius_mm) > 0:
        raise ValueError(f"radius_mm must be positive, got {radius_mm}")
    if int(min_voxels) < 1:
        raise ValueError(f"min_voxels must be at least 1, got {min_voxels}")
    if not isinstance(volume, Volume):
        raise ValueError(f"volume must be a Volume, got {type(volume).__name__}")
    data = np.asarray(volume.data, np.float32)
    spacing = volume.spacing
    d = volume.direction
    if np.max(np.abs(d.T @ d - np.eye(3))) > 1e-3:
        raise ValueError("find_capsules needs orthogonal grid axes (sheared affine given)")
    thick = slice_thickness_mm
    if thick is None:
        thick = (volume.metadata or {}).get("slice_thickness") or spacing[2]
    thick = float(thick)
    if not thick > 0:
        raise ValueError(f"slice thickness must be positive, got {thick}")
    R = float(radius_mm)
    from skimage.filters import threshold_otsu

    if threshold is None:
        # Otsu on log intensity: the air/tissue gap is the widest there (on linear values Otsu
        # may split fat from muscle instead when the body fills the field of view).
        sub = data[::2, ::2, :]
        sub = sub[np.isfinite(sub) & (sub > 0)]
        threshold = float(np.exp(threshold_otsu(np.log(sub)))) if sub.size and sub.min() < sub.max() else 0.0
    # The fg threshold for linking is half the air/tissue split: the
    # end discs of a capsule are faint (a sliver of sphere averaged over the slice).
    fg_thr = 0.5 * float(threshold)
    if body_mask is None:
        # The body's edge at half the typical tissue level (the 50 % partial-volume contour); the
        # air/tissue threshold itself sits at a few % of tissue and would bloat the body by the
        # skin's partial-volume rim, swallowing the capsule's contact region.
        tissue = data[::2, ::2, :][data[::2, ::2, :] > threshold]
        body_thr = max(float(threshold), 0.5 * float(np.median(tissue))) if tissue.size else float(threshold)
        body = _body_mask(data, body_thr, R + 1.5, spacing)
    else:
        body = np.asarray(body_mask, bool)
        if body.shape != data.shape:
            raise ValueError(f"body_mask shape {body.shape} differs from the volume's {data.shape}")
        # A skin segmentation usually includes the capsules stuck on it: open it as well (a
        # mask without capsules loses only protrusions thinner than the disc).
        body = _body_mask(body.astype(np.float32), 0.5, R + 1.5, spacing)
    body_d = ndimage.binary_dilation(body, structure=np.ones((3, 3, 1), bool))
    prot = (data > fg_thr) & ~body_d
    lab, n = ndimage.label(prot, structure=np.ones((3, 3, 3), bool))
    objs = ndimage.find_objects(lab)
    if n_inplane is None:
        n_inplane = max(2, int(math.ceil(float(max(spacing[:2])) / 0.25)))
    pad = np.array([int(math.ceil(2.0 / spacing[0])) + 1, int(math.ceil(2.0 / spacing[1])) + 1, 1])
    max_extent = 2 * R + 2 * float(max(spacing[:2]))
    max_slices = int(math.ceil((2 * R + thick) / spacing[2])) + 1
    centres, idx_out, oil, fat, res, slices, rejected, seen_out, radii, offsets = ([] for _ in range(10))
    fat_r = int(math.ceil(20.0 / float(min(spacing[:2]))))
    for lbl, sl in enumerate(objs, start=1):
        if sl is None:
            continue
        comp = lab[sl] == lbl
        ext = np.array([s.stop - s.start for s in sl])
        n_vox = int(comp.sum())
        vol_mm3 = n_vox * float(np.prod(spacing))
        # Quick shape screens: too small to hold a sphere's worth of signal, or too big to be one.
        if vol_mm3 < 0.15 * (4 / 3) * math.pi * R ** 3 or ext[0] * spacing[0] > max_extent + 2 * spacing[0] \
                or ext[1] * spacing[1] > max_extent + 2 * spacing[1] or ext[2] > max_slices:
            if vol_mm3 >= 0.15 * (4 / 3) * math.pi * R ** 3:
                rejected.append({"label": lbl, "reason": "size", "extent_mm": (ext * spacing).tolist()})
            continue
        lo = np.maximum([s.start for s in sl] - pad, 0)
        hi = np.minimum([s.stop for s in sl] + pad, data.shape)
        box = tuple(slice(a, b) for a, b in zip(lo, hi))
        vals = data[box]
        use = ~body_d[box]
        # Other candidates in the box are not this sphere: leave them out too.
        other = (lab[box] > 0) & (lab[box] != lbl)
        use &= ~other
        ii, jj, kk = np.nonzero(use)
        ijk = np.c_[ii + lo[0], jj + lo[1], kk + lo[2]].astype(float)
        y = vals[use].astype(float)
        w = np.where(comp, data[sl], 0.0)
        ci, cj, ck = np.nonzero(comp)
        wt = w[comp]
        c0_idx = np.array([ci @ wt, cj @ wt, ck @ wt]) / wt.sum() + np.array([s.start for s in sl])
        # Local fat level: the median of the bright class (Otsu) of the body voxels within 20 mm,
        # on the candidate's slices: subcutaneous fat beside the capsule. Local, because
        # the bias field changes the level across the field of view by more than oil exceeds fat.
        ks = slice(max(int(lo[2]), 0), int(hi[2]))
        ci0, cj0 = int(round(c0_idx[0])), int(round(c0_idx[1]))
        region = (slice(max(ci0 - fat_r, 0), ci0 + fat_r + 1), slice(max(cj0 - fat_r, 0), cj0 + fat_r + 1), ks)
        bvals = data[region][body[region]]
        if bvals.size > 20 and bvals.min() < bvals.max():
            bvals = bvals[bvals > threshold_otsu(bvals)]        # the bright class: fat (and marrow)
        fat_level = float(np.median(bvals)) if bvals.size > 20 else float("nan")
        # Cheap screen before the fit: even a capsule centred on a slice boundary keeps 80 % of the
        # oil level at its brightest voxel (8 mm sphere, 5 mm slices).
        if not (np.isfinite(fat_level) and float(wt.max()) >= 0.8 * min_contrast * fat_level):
            rejected.append({"label": lbl, "reason": "contrast", "peak": float(wt.max()), "fat_level": fat_level})
            continue
        # Only voxels that the sphere can reach from about where it starts carry information.
        near = np.linalg.norm((ijk - c0_idx) * spacing, axis=1) <= R + 2 * float(max(spacing[:2])) + thick
        ijk, y = ijk[near], y[near]
        model = _SphereModel(ijk, spacing, thick, R, n_inplane)
        c_mm, coef, rms, r_fit = _fit_sphere(y, model, c0_idx * spacing, float(spacing[2]), fit_radius)
        m, b = float(coef[0]), float(coef[1])
        c_idx = c_mm / spacing
        rel = rms / m if m > 0 else float("inf")
        # How much of the fitted sphere lies in the voxels the fit saw (the rest is in the body or
        # outside the box): a sphere fitted to a speck with only its rim touching is no capsule.
        frac = model.fraction(c_mm)
        seen = float(frac.sum() * np.prod(spacing[:2]) * thick) / ((4 / 3) * math.pi * r_fit ** 3)
        inside = np.all((c_idx >= lo - 1) & (c_idx <= hi))
        reason = None
        if not (m > 0 and np.isfinite(fat_level) and m >= min_contrast * fat_level):
            reason = "contrast"
        elif rel > max_residual:
            reason = "residual"
        elif not (c_mm[2] - r_fit >= -thick / 2 - 0.5
                  and c_mm[2] + r_fit <= (data.shape[2] - 1) * spacing[2] + thick / 2 + 0.5):
            # A blob at the first or last slice may be anything cut by the end of the stack, and its
            # depth is not measurable there.
            reason = "cut by the end of the stack"
        elif seen < min_seen:
            reason = "sphere not in the image"
        elif int(np.count_nonzero(frac > 0.1)) < min_voxels:
            reason = "too few voxels to resolve a sphere"
        elif not inside:
            reason = "centre outside candidate"
        if reason:
            rejected.append({"label": lbl, "reason": reason, "oil_level": m, "fat_level": fat_level,
                             "residual": rel, "seen": seen, "index": c_idx.tolist()})
            continue
        centres.append(volume.index_to_world(c_idx))
        idx_out.append(c_idx)
        oil.append(m)
        offsets.append(b)
        radii.append(r_fit)
        seen_out.append(seen)
        fat.append(fat_level)
        res.append(rel)
        slices.append(sorted(set((ck + sl[2].start).tolist())))
    centres_arr = np.asarray(centres, float).reshape(-1, 3)
    info = {"index": np.asarray(idx_out, float).reshape(-1, 3), "oil_level": np.asarray(oil),
            "fat_level": np.asarray(fat), "residual": np.asarray(res), "seen": np.asarray(seen_out),
            "radius_mm": np.asarray(radii), "offset": np.asarray(offsets), "slices": slices,
            "rejected": rejected, "threshold": float(threshold), "slice_thickness_mm": thick}
    return centres_arr, info


def match_capsules(centres: np.ndarray, expected: np.ndarray | Mapping[str, Sequence[float]],
                   max_distance_mm: float = 20.0, *, return_index: bool = False):
    """Name capsules: one-to-one assignment to expected positions, nearest overall.

    Parameters
    ----------
    centres : ndarray (N, 3)
        Found capsule centres, LPS mm.
    expected : ndarray (M, 3) or mapping name -> (3,)
        Expected marker/capsule positions in the same frame (LPS mm), e.g.
        the marker set's markers placed on the personal skin.
    max_distance_mm : float
        Pairs farther apart than this are not matched.
    return_index : bool
        Return index arrays instead of the name -> centre mapping.

    Returns
    -------
    named : dict
        ``{name: centre (3,)}`` for every expected position that got a
        capsule (keys: the mapping's names, or row numbers of an array).
    (index, distance_mm) : ndarray (M,) int, ndarray (M,)
        With ``return_index``: for each expected position (mapping order) the
        index into ``centres`` of its capsule, ``-1`` when none is within
        reach, and the distance of each match (``NaN`` when unmatched).

    Raises
    ------
    ValueError
        Bad shapes or a non-positive ``max_distance_mm``.

    Notes
    -----
    Minimum total distance (Hungarian method, Kuhn 1955) rather than nearest
    neighbour per marker, so two markers never claim the same capsule.
    """
    from scipy.optimize import linear_sum_assignment

    keys = list(expected.keys()) if isinstance(expected, Mapping) else None
    exp = np.asarray(list(expected.values()) if keys is not None else expected, float)
    exp = exp if exp.size else np.zeros((0, 3))
    c = np.asarray(centres, float)
    c = c if c.size else np.zeros((0, 3))
    if exp.ndim != 2 or exp.shape[1] != 3 or c.ndim != 2 or c.shape[1] != 3:
        raise ValueError(f"centres and expected must be (N, 3) and (M, 3), got {c.shape} and {exp.shape}")
    if not float(max_distance_mm) > 0:
        raise ValueError(f"max_distance_mm must be positive, got {max_distance_mm}")
    index = np.full(len(exp), -1, np.int64)
    dist = np.full(len(exp), np.nan)
    if len(exp) and len(c):
        D = np.linalg.norm(exp[:, None, :] - c[None, :, :], axis=2)
        # Out-of-reach pairs get a cost no in-reach assignment can beat, then are dropped.
        big = D.max() * (len(exp) + len(c)) + 1.0
        rows, cols = linear_sum_assignment(np.where(D <= max_distance_mm, D, big))
        ok = D[rows, cols] <= max_distance_mm
        index[rows[ok]] = cols[ok]
        dist[rows[ok]] = D[rows[ok], cols[ok]]
    if return_index:
        return index, dist
    names = keys if keys is not None else list(range(len(exp)))
    return {names[m]: c[index[m]].copy() for m in range(len(exp)) if index[m] >= 0}
