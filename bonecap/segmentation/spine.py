"""The spine's levels from the MRI: where each intervertebral disc lies along the spinal column.

The slice rules extract the vertebrae as fragments of their bodies, and a
fragment is labelled by the nearest seed: when the template's spine is half a
vertebra off, the labels slip by a level. The warp therefore carries the
vertebrae between the pelvis and the skull fitted to the head's skin, spread
in the template's proportions (:func:`bonecap.skeleton.warp.warp_skeleton`'s
``fixed``). People's spines are not in the template's proportions: a cervical
spine short for its thoracic one puts C7 15 mm from where the spread does.

What the image does show well is the column's rhythm. Along the column, the
vertebral bodies (cancellous bone, bright with marrow fat, as the slice rules
assume) alternate with darker discs and end plates. This module reads that
rhythm and puts the chain's joints on it:

1. :func:`profile_along_curve` -- the mean intensity over a disc of tissue
   across a curve through the chain's joints (the intervertebral joint
   centres lie in the discs, on the line through the bodies), every
   millimetre, from every station that covers it;
2. :func:`match_discs` -- the profile's dark dips (relative to a running
   median, so that a station's intensity scale and the bias field drop out)
   matched to the expected discs in order by dynamic programming: each dip
   may be left unmatched (a disc too thin for the slices, a dip that is no
   disc) at a price, and the displacement from where the chain put a disc may
   change little from one level to the next. The order is what labels the
   levels -- counting up from the sacrum, as a radiologist does -- so a spine
   off by more than half a vertebra is not mislabelled;
3. :func:`spine_levels` -- the matched displacements smoothed along the
   column and the joints moved along the curve by them; refused (the chain
   stays as it was) when the profile shows too few discs.

Positions are in the volumes' world (LPS, mm); arc lengths in mm along the
curve from its first point.

References
----------
Kojima et al., the MRI-based personal skeleton paper this project follows
(the skeleton warped onto the bones the MRI shows; what it misses, from the
warp). Counting vertebral levels along the column from a fixed end is the
usual way of labelling the spine on MRI (e.g. Glocker et al., "Vertebrae
localization in pathological spine CT via dense classification from sparse
annotations", MICCAI 2013, and the references there).
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np
from scipy import ndimage, signal
from scipy.interpolate import make_interp_spline

from bonecap.model import Volume

__all__ = ["VERTEBRAL_BODIES", "is_disc_joint", "profile_along_curve", "match_discs", "spine_levels"]

#: Bones of bonecap's template with a vertebral body: a joint between two of them lies in a disc (the
#: atlas has no body, and the skull none: c1_c2 and the atlanto-occipital joint show no disc).
VERTEBRAL_BODIES = frozenset(["sacrum"] + [f"l{i}" for i in range(1, 6)] + [f"t{i}" for i in range(1, 13)]
                             + [f"c{i}" for i in range(2, 8)])


def is_disc_joint(bones: Sequence[str]) -> bool:
    """Whether a joint between these bones lies in an intervertebral disc (both have a vertebral body)."""
    return len(set(bones)) >= 2 and set(bones) <= VERTEBRAL_BODIES


def _curve(points: np.ndarray):
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    if np.any(np.diff(arc) <= 1e-6):
        raise ValueError("the curve's points must be distinct (two consecutive points coincide)")
    k = min(3, len(points) - 1)
    return make_interp_spline(arc, points, k=k, bc_type="natural" if k == 3 else None), arc


def profile_along_curve(volumes: Sequence[Volume], points, *, radius_mm: float = 6.0, step_mm: float = 1.0,
                        margin_mm: float = 30.0, min_cover: float = 0.9):
    """Mean intensity over a disc across a curve, every ``step_mm`` along it.

    Parameters
    ----------
    volumes : sequence of Volume
        The stations, registered into one world and on one intensity scale
        (build-subject's stage 1).
    points : array_like, shape (n, 3)
        Points the curve passes through, in order (an interpolating cubic
        spline in arc length), in the volumes' world (mm).
    radius_mm : float
        Radius of the disc across the curve that is averaged (a vertebral
        body is 15-50 mm across: 6 mm stays inside it when the curve is a few
        millimetres off its centre, and averages the noise of ~50 samples).
    step_mm : float
        Spacing of the samples along the curve.
    margin_mm : float
        The curve is extended this far beyond its first and last point
        (along the spline), so a disc at either end has both sides.
    min_cover : float
        A sample counts for a station when at least this fraction of its disc
        lies inside the station's grid (a disc cut by the station's first or
        last slice would mix in the padding).

    Returns
    -------
    s : ndarray, shape (m,)
        Arc length of each sample (mm, 0 at ``points[0]``, negative before).
    values : ndarray, shape (m,)
        The mean intensity; NaN where no station covers the sample. Where
        stations overlap their means are averaged.
    arc : ndarray, shape (n,)
        Arc length of each of ``points``.
    """
    P = np.asarray(points, float)
    if P.ndim != 2 or P.shape[1] != 3 or len(P) < 2:
        raise ValueError(f"points must be an (n >= 2, 3) array of positions, got shape {P.shape}")
    if radius_mm <= 0 or step_mm <= 0:
        raise ValueError(f"radius_mm and step_mm must be positive, got {radius_mm} and {step_mm}")
    spl, arc = _curve(P)
    s = np.arange(-margin_mm, arc[-1] + margin_mm + 0.5 * step_mm, step_mm)
    # the spline's extrapolation beyond its ends is its end polynomial: fine for a margin of a few cm
    c = spl(s)
    t = spl.derivative()(s)
    t /= np.maximum(np.linalg.norm(t, axis=1), 1e-9)[:, None]
    # two unit vectors across the curve (any pair: the disc is round)
    ref = np.where(np.abs(t[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    u = np.cross(t, ref)
    u /= np.linalg.norm(u, axis=1)[:, None]
    w = np.cross(t, u)
    g = np.arange(-radius_mm, radius_mm + 1e-9, min(1.5, radius_mm))
    offs = [(a, b) for a in g for b in g if a * a + b * b <= radius_mm ** 2 + 1e-9]
    total = np.zeros(len(s))
    count = np.zeros(len(s))
    for v in volumes:
        inv = np.linalg.inv(v.affine)
        shape = np.array(v.data.shape[:3])
        data = v.data if v.data.dtype == np.float32 else v.data.astype(np.float32)
        acc = np.zeros(len(s))
        n = np.zeros(len(s))
        for a, b in offs:
            q = c + a * u + b * w
            ijk = inv[:3, :3] @ q.T + inv[:3, 3:4]
            ok = np.all((ijk >= 0) & (ijk <= (shape - 1)[:, None]), axis=0)
            if np.any(ok):
                acc[ok] += ndimage.map_coordinates(data, ijk[:, ok], order=1)
                n[ok] += 1
        full = n >= min_cover * len(offs)
        total[full] += acc[full] / n[full]
        count[full] += 1
    with np.errstate(invalid="ignore", divide="ignore"):
        values = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    return s, values, arc


def _dips(s: np.ndarray, values: np.ndarray, *, baseline_mm: float, prominence: float, min_spacing_mm: float):
    """Positions (arc length) of the profile's dark dips, relative to a running median."""
    ok = np.isfinite(values)
    step = float(np.median(np.diff(s)))
    filled = np.interp(s, s[ok], values[ok])
    size = max(3, int(round(baseline_mm / step)) | 1)
    base = ndimage.median_filter(filled, size=size, mode="nearest")
    rel = filled / np.maximum(base, 1e-9 * max(float(np.nanmax(np.abs(filled))), 1e-30)) - 1.0
    idx, _ = signal.find_peaks(-rel, prominence=prominence, distance=max(1, int(round(min_spacing_mm / step))))
    idx = idx[ok[idx]]          # a dip where no station looked is the interpolation's
    # sub-sample position: the centroid of the dip's lower half (a 5 mm slice grid makes a disc's trough
    # flat or lopsided by a sample or two; its lower half is what the disc darkens)
    half = max(1, int(round(0.5 * min_spacing_mm / step)))
    pos = []
    for i in idx:
        lo, hi = max(0, i - half), min(len(s), i + half + 1)
        depth = rel[lo:hi].max() - rel[lo:hi]
        wgt = np.clip(depth - 0.5 * depth.max(), 0.0, None)
        pos.append(float(np.sum(wgt * s[lo:hi]) / wgt.sum()) if wgt.sum() > 0 else float(s[i]))
    return np.array(pos)


def match_discs(s, values, expected, *, prominence: float = 0.1, min_spacing_mm: float = 8.0,
                baseline_mm: float = 61.0, prior_mm: float = 15.0, step_sd_mm: float = 3.0,
                skip_cost: float = 3.0, spurious_cost: float = 1.0, max_gap: int = 4):
    """The profile's dark dips matched, in order, to the expected discs.

    Parameters
    ----------
    s, values : ndarray
        A profile along the column (:func:`profile_along_curve`); NaN where
        nothing was seen.
    expected : array_like, shape (k,)
        Arc lengths where the chain puts its discs, increasing.
    prominence : float
        A dip counts when it is at least this much darker than its
        surroundings, relative to the running median (0.1: 10 %).
    min_spacing_mm : float
        Dips closer than this are one (a disc and its end plates).
    baseline_mm : float
        Window of the running median the profile is divided by: two to three
        vertebrae, so a station's scale and the bias field drop out.
    prior_mm, step_sd_mm : float
        The cost of a match is ``0.5 (d / prior_mm)^2`` for a displacement
        ``d`` from the expected place, plus ``0.5 (d - d') ^ 2 / (step_sd_mm^2 g)``
        from the previous matched disc's displacement ``d'``, ``g`` levels
        below (the spine's proportions change slowly from level to level).
    skip_cost, spurious_cost : float
        The cost of an expected disc left unmatched and of a dip matched to
        no disc.
    max_gap : int
        At most this many discs or dips are skipped between two matches.

    Returns
    -------
    displacement : ndarray, shape (k,)
        Matched dip minus expected place (mm), NaN for a disc left unmatched.
    dips : ndarray
        Arc lengths of the dips found.
    """
    s = np.asarray(s, float)
    values = np.asarray(values, float)
    e = np.asarray(expected, float)
    if s.ndim != 1 or s.shape != values.shape or len(s) < 3:
        raise ValueError(f"s and values must be 1-D profiles of one length >= 3, got {s.shape} and {values.shape}")
    if e.ndim != 1 or len(e) == 0 or np.any(np.diff(e) <= 0):
        raise ValueError("expected must be a non-empty increasing sequence of arc lengths")
    if not np.any(np.isfinite(values)):
        return np.full(len(e), np.nan), np.zeros(0)
    m = _dips(s, values, baseline_mm=baseline_mm, prominence=prominence, min_spacing_mm=min_spacing_mm)
    K, J = len(e), len(m)
    out = np.full(K, np.nan)
    if J == 0:
        return out, m
    D = m[None, :] - e[:, None]                     # displacement if disc k takes dip j
    unary = 0.5 * (D / prior_mm) ** 2
    cost = np.full((K, J), np.inf)
    back: dict[tuple[int, int], tuple[int, int] | None] = {}
    for k in range(K):
        for j in range(J):
            best, arg = k * skip_cost + j * spurious_cost, None       # the first match
            for k2 in range(max(0, k - max_gap - 1), k):
                for j2 in range(max(0, j - max_gap - 1), j):
                    if not np.isfinite(cost[k2, j2]):
                        continue
                    c = (cost[k2, j2] + 0.5 * (D[k, j] - D[k2, j2]) ** 2 / (step_sd_mm ** 2 * (k - k2))
                         + (k - k2 - 1) * skip_cost + (j - j2 - 1) * spurious_cost)
                    if c < best:
                        best, arg = c, (k2, j2)
            cost[k, j] = best + unary[k, j]
            back[k, j] = arg
    total = cost + (K - 1 - np.arange(K))[:, None] * skip_cost + (J - 1 - np.arange(J))[None, :] * spurious_cost
    node: tuple[int, int] | None = tuple(int(i) for i in np.unravel_index(np.argmin(total), total.shape))
    while node is not None:
        out[node[0]] = D[node]
        node = back[node]
    return out, m


def spine_levels(volumes: Sequence[Volume], points, is_disc, *, smooth_mm: float = 30.0,
                 min_matched: float = 0.7, max_displacement_mm: float = 40.0, keep_ends: bool = True,
                 max_step: float = 0.3, max_slice_mm: float = 8.0, radius_mm: float = 6.0,
                 profile_out: dict | None = None, **kwargs) -> tuple[np.ndarray | None, dict[str, Any]]:
    """The spine chain's joints moved along the column onto the discs the MRI shows.

    Parameters
    ----------
    volumes : sequence of Volume
        The registered stations (world LPS, mm).
    points : array_like, shape (n, 3)
        The chain's joint centres, bottom to top (the lumbosacral joint to
        the atlanto-occipital), where the warp's spread put them.
    is_disc : sequence of bool, length n
        Which joints lie in a disc (:func:`is_disc_joint`); the others (the
        atlas's) follow by interpolation.
    smooth_mm : float
        The matched displacements are smoothed along the column by a
        Gaussian of this width (one dip's position is uncertain by 1-2 mm
        at 5 mm slices; the spine's proportions change over levels).
    min_matched : float
        The fraction of the discs that must be matched, else nothing moves.
    max_displacement_mm : float
        Refused when a smoothed displacement exceeds this (a slipped level).
    keep_ends : bool
        The first and last joints stay (they belong to the anchored pelvis
        and the fixed skull); their displacements still inform the rest.
    max_step : float
        Refused when the matched displacement changes between neighbouring
        discs by more than this fraction of their spacing per level: a disc
        taken for its neighbour (seen on stations of 10 mm slices).
    max_slice_mm : float
        Refused when a station's slices (its largest voxel spacing) are
        thicker than this: a disc is 5-10 mm thick, and thicker slices
        average it away or place it by half a slice.
    profile_out : dict, optional
        Filled with what a QC picture shows: ``s``, ``values`` (the profile),
        ``dips``, ``expected`` (the discs' arc lengths as given), ``matched``
        (their displacements, NaN unmatched), ``arc`` (every joint's) and
        ``report`` (the returned report).
    radius_mm : float
        The disc across the column that is averaged (:func:`profile_along_curve`).
    **kwargs
        Passed to :func:`match_discs`.

    Returns
    -------
    points : ndarray (n, 3) or None
        The joints moved along the curve through ``points``; None when
        refused.
    report : dict
        ``discs``, ``dips``, ``matched``, ``displacement_mm`` (per joint,
        after smoothing), ``used`` and, when refused, ``reason``.

    References
    ----------
    See the module docstring.
    """
    P = np.asarray(points, float)
    flags = np.asarray(is_disc, bool)
    if P.ndim != 2 or P.shape[1] != 3 or len(P) != len(flags):
        raise ValueError(f"points (n, 3) and is_disc (n,) must match, got {P.shape} and {flags.shape}")
    report: dict[str, Any] = {"discs": int(flags.sum()), "used": False}
    if profile_out is not None:
        profile_out["report"] = report            # the same dict: what it says at the end
    if flags.sum() < 3:
        report["reason"] = "fewer than 3 discs in the chain"
        return None, report
    thick = max((float(np.max(v.spacing)) for v in volumes), default=np.inf)
    if thick > max_slice_mm:
        report["reason"] = f"slices of {thick:.1f} mm are too thick to show the discs (at most {max_slice_mm:g})"
        return None, report
    s, values, arc = profile_along_curve(volumes, P, radius_mm=radius_mm)
    d, dips = match_discs(s, values, arc[flags], **kwargs)
    matched = np.isfinite(d)
    if profile_out is not None:
        profile_out.update(s=s, values=values, dips=dips, expected=arc[flags], matched=d, arc=arc)
    report.update(dips=int(len(dips)), matched=int(matched.sum()))
    span = (s >= arc[flags][0]) & (s <= arc[flags][-1])
    if not np.all(np.isfinite(values[span])):
        report["reason"] = "the stations do not cover the whole column"
        return None, report
    if matched.sum() < min_matched * flags.sum():
        report["reason"] = (f"{matched.sum()} of {flags.sum()} discs found in the image "
                            f"(at least {min_matched:.0%} needed)")
        return None, report
    ad = arc[flags][matched]
    dd = d[matched]
    # a level slipped: between two matched discs the displacement jumps by a good part of a vertebra (the
    # spine's proportions change by 1-3 mm per level; a disc taken for its neighbour, by 15-30 mm)
    k = np.flatnonzero(matched)
    levels = np.diff(k)
    jump = np.abs(np.diff(dd)) / levels
    spacing = np.diff(ad) / levels
    if len(jump) and np.any(jump > max_step * spacing):
        i = int(np.argmax(jump / spacing))
        report["reason"] = (f"a level slipped: the displacement jumps by {jump[i]:.0f} mm per level between discs "
                            f"{k[i]} and {k[i + 1]} ({spacing[i]:.0f} mm apart)")
        return None, report
    w = np.exp(-0.5 * ((ad[None, :] - ad[:, None]) / smooth_mm) ** 2)
    sm = (w @ dd) / w.sum(axis=1)
    # every joint: the smoothed displacement at its arc length (linear between matched discs; at the top the
    # fixed bone's joint, 0)
    ka, kd = list(ad), list(sm)
    if keep_ends and arc[-1] > ad[-1]:
        ka.append(arc[-1])
        kd.append(0.0)
    disp = np.interp(arc, ka, kd)
    if keep_ends:
        disp[0] = disp[-1] = 0.0
    report["displacement_mm"] = [round(float(x), 2) for x in disp]
    if np.max(np.abs(disp)) > max_displacement_mm:
        report["reason"] = f"a displacement of {np.max(np.abs(disp)):.0f} mm (more than {max_displacement_mm:.0f})"
        return None, report
    spl, _ = _curve(P)
    out = spl(arc + disp)
    if keep_ends:
        out[0], out[-1] = P[0], P[-1]
    report["used"] = True
    return out, report
