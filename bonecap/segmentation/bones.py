"""Every bone of an axial MRI stack, slice by slice, from seeds (stage 3 of ``build-subject``).

Each bone has a seed polyline in the LPS world (for a long bone a line from
its proximal to its distal joint centre, through its shaft: build-subject
takes the template's section centres, :func:`bonecap.build_mri.shaft_line`; for other bones one or a few
points, e.g. from the template roughly aligned to the skin, or placed by eye
as in the paper). In each axial slice the bone's seeds are where its polyline
crosses the slice plane; the bone is segmented there by its rule --
:mod:`bonecap.segmentation.cortical` for long bones,
:mod:`bonecap.segmentation.density` for the others -- and each region is
labelled with the bone's id. Holes are filled per slice (bones leave the
field of view, so a 3-D fill would leave the cortical tube open).

Public API
----------
- :data:`LONG_BONES`, :func:`default_rule` ``(bone) -> "cortical" | "density"``
- :func:`slice_seeds` ``(volume, polyline_lps, margin_mm=20.0) -> list of ndarray (n_k, 2)``
- :func:`segment_bones` ``(volume, seeds, *, body_mask=None, rules=None, progress=True, ...) -> (labels, ids)``
- :func:`keep_continuous` (the continuity walk on given labels), :func:`defer_to_shaft_stacks`
  (overlapping stacks: a long bone's sections kept where the stack holding its shaft labels it too)

References
----------
Kojima et al., the MRI-based personal skeleton and motion-capture paper this
project follows (bone contours slice by slice; the cortical-edge and
density-threshold rules; seeds per bone).
"""

from __future__ import annotations

import re
import warnings
from functools import partial
from typing import Iterable, Mapping

import numpy as np
from scipy import ndimage
from scipy.optimize import linear_sum_assignment

from bonecap.model import Volume
from bonecap.progress import progress as _progress
from bonecap.segmentation import cortical, density
from bonecap.segmentation._checks import check_body_mask

__all__ = ["LONG_BONES", "RULES", "default_rule", "slice_seeds", "segment_bones", "keep_continuous",
           "defer_to_shaft_stacks"]

#: Bones segmented by the cortical-edge rule (base names, without ``_r``/``_l``).
LONG_BONES = ("femur", "tibia", "fibula", "humerus", "radius", "ulna")
RULES = ("cortical", "density")

# Proximal femur: the hip-knee line (the mechanical axis) passes through the
# femoral head but runs 30-40 mm medial of the shaft at the lesser trochanter,
# so the femur's marrow is looked for farther from its seed.
_SEARCH_RADIUS_MM = {"femur": 45.0, "humerus": 35.0}

#: A long bone's section past its polyline's end (found by the seed margin) is kept only when the
#: empty slices between it and the bone's last section span at most this, mm (:func:`_keep_continuous`).
MARGIN_GAP_MM = 7.5


def _base(bone: str) -> str:
    return re.sub(r"_[rl]$", "", str(bone).lower())


def default_rule(bone: str) -> str:
    """``"cortical"`` for the long bones (femur, tibia, fibula, humerus, radius, ulna), else ``"density"``.

    Pelvis (``hip_r``/``hip_l``), sacrum, scapula, vertebrae, ribs, patella,
    sternum, clavicle and everything else (hands, feet, skull) have little
    cortex on MRI and take the density-threshold rule (Kojima et al.).
    """
    return "cortical" if _base(bone) in LONG_BONES else "density"


def slice_seeds(volume: Volume, polyline_lps, margin_mm: float = 20.0) -> list[np.ndarray]:
    """Where a seed polyline crosses each axial slice, in pixel coordinates.

    Parameters
    ----------
    volume : Volume
        Axial stack (``k`` the slice axis), ``affine`` voxel -> LPS mm.
    polyline_lps : array (N, 3)
        Seed points in the LPS world, mm, in order along the bone (N >= 1).
    margin_mm : float
        Slices beyond the polyline's ends by at most this (along the slice
        normal) get the nearest end's in-plane position; farther slices get
        no seed (the bone is not searched there). A single point is seeded
        on the slices within ``margin_mm`` of it.

    Returns
    -------
    list of ndarray (n_k, 2)
        Per slice ``k``, the ``(i, j)`` of every crossing (0, 1 or several:
        a bent polyline may cross a slice more than once).

    Raises
    ------
    ValueError
        Not an (N, 3) finite array, or a negative margin.
    """
    pts = np.asarray(polyline_lps, dtype=float)
    if pts.ndim == 1 and pts.shape == (3,):
        pts = pts[None]
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0 or not np.isfinite(pts).all():
        raise ValueError(f"a seed polyline must be a finite (N, 3) array of LPS mm, got shape {pts.shape}")
    if not margin_mm >= 0:
        raise ValueError(f"margin_mm must be >= 0, got {margin_mm}")
    ijk = volume.world_to_index(pts)
    K = volume.shape[2]
    dz = float(volume.spacing[2])
    tol = 0.1 / dz
    ks = np.arange(K, dtype=float)
    out: list[list[np.ndarray]] = [[] for _ in range(K)]
    # crossings of each segment (vectorised over slices)
    for a, b in zip(ijk[:-1], ijk[1:]):
        lo, hi = min(a[2], b[2]), max(a[2], b[2])
        # a point placed on a slice (by eye, on the slice shown; its world coordinates written to
        # 0.1 mm) maps to k +- rounding: it is on that slice
        sel = ks[(ks >= lo - tol) & (ks <= hi + tol)]
        if sel.size == 0:
            continue
        if hi - lo < 1e-9:           # segment lying in a slice: its midpoint
            pts_k = np.repeat(((a + b) / 2)[None, :2], sel.size, axis=0)
        else:
            t = (sel - a[2]) / (b[2] - a[2])
            pts_k = a[None, :2] + t[:, None] * (b - a)[None, :2]
        for k, p in zip(sel.astype(int), pts_k):
            out[k].append(p)
    # beyond the ends: the nearest end, within the margin
    kmin, kmax = ijk[:, 2].min(), ijk[:, 2].max()
    end_lo, end_hi = ijk[np.argmin(ijk[:, 2]), :2], ijk[np.argmax(ijk[:, 2]), :2]
    for k in range(K):
        if out[k]:
            continue
        if kmin - margin_mm / dz <= k < kmin:
            out[k].append(end_lo)
        elif kmax < k <= kmax + margin_mm / dz:
            out[k].append(end_hi)
    result = []
    for lst in out:
        arr = np.array(lst, float).reshape(-1, 2)
        # duplicates: a crossing at a vertex is found by both segments, a hair apart (the tolerance)
        if len(arr) > 1:
            keep = [0]
            for q in range(1, len(arr)):
                if np.min(np.linalg.norm(arr[keep] - arr[q], axis=1)) > 0.5:
                    keep.append(q)
            arr = arr[keep]
        result.append(arr)
    return result


def _resolve_overlaps(masks: dict[str, np.ndarray], seeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Pixels claimed by two or more bones go to the bone with the nearest seed (in this slice)."""
    names = list(masks)
    if len(names) < 2:
        return masks
    stack = np.stack([masks[n] for n in names])
    multi = stack.sum(axis=0) > 1
    if not multi.any():
        return masks
    ii, jj = np.nonzero(multi)
    d = np.full((len(names), ii.size), np.inf)
    for b, n in enumerate(names):
        s = seeds[n]
        claim = stack[b, ii, jj]
        dd = np.min((ii[:, None] - s[None, :, 0]) ** 2 + (jj[:, None] - s[None, :, 1]) ** 2, axis=1)
        d[b] = np.where(claim, dd, np.inf)
    win = np.argmin(d, axis=0)
    stack[:, ii, jj] = False
    stack[win, ii, jj] = True
    return {n: stack[b] for b, n in enumerate(names)}


def _cortical_slice(img, med, body, inner, pixel_mm, bones: dict[str, np.ndarray], extension: dict[str, np.ndarray],
                    opts: dict, others: dict[str, np.ndarray] | None = None,
                    holds: dict[str, np.ndarray] | None = None, regions_out: list | None = None
                    ) -> dict[str, np.ndarray]:
    """All long bones of one slice: marrow regions assigned to seeds jointly, then each contour.

    The marrow candidates (:func:`~bonecap.segmentation.cortical.find_marrow`'s criteria, with one
    muscle level for the slice) are found once; each seed is then matched to one region by
    a minimum-cost assignment on the seed-to-region distances (Hungarian method), so two
    bones ~20 mm apart with seeds ~15 mm off (tibia and fibula, radius and ulna) do not both
    take the nearer marrow, and a bone searched only because its polyline ends near the
    slice (a joint: the tibia's seed above the knee) yields to a bone that crosses it.
    The seeds of the slice's other (density-rule) bones take part in the assignment too,
    with a handicap so that a tie goes to the long bone: a region assigned to one of them
    (the patella's marrow, a seed ~15 mm off, next to the femur's) is left to its rule. A
    region holding a long bone's seed that ``holds`` (default: the crossing ones) is never a
    density bone's: past a long bone's proximal end the joint centre lies in its head (the
    hip's seed passes through the hip's centre too, and took the femoral head), past its
    distal end in the next bone (the ankle's in the talus).

    ``regions_out``: a list that gets the slice's marrow regions as :func:`_marrow_regions`
    finds them (``(options key, labels, count, muscle level)``), before any is split between seeds.
    """
    m_slice = cortical.muscle_level(med, inner)
    out = {name: np.zeros(img.shape, bool) for name in bones}
    if not np.isfinite(m_slice) or m_slice <= 0:
        return out
    o0 = opts[next(iter(bones))]          # the slice's candidates follow its (first) long bone's options
    # fat reaches the skin and is dropped; marrow joined to it through a gap in the cortex is cut loose
    cand = _marrow_candidates(med, body, pixel_mm, m_slice, o0)
    lab, n = cortical.detach_from_skin(cand, body, inner, pixel_mm)
    if regions_out is not None:
        regions_out.append((_marrow_key(o0), lab.copy(), n, m_slice))
    if n == 0:
        return out
    lab, n = _split_shared_regions(lab, n, {b: p[~extension[b]] for b, p in bones.items()})
    bad = np.zeros(n + 1, bool)
    bad[0] = True
    bad |= np.bincount(lab.ravel(), minlength=n + 1) * pixel_mm ** 2 < o0.get("min_marrow_mm2", 6.0)
    ids = np.flatnonzero(~bad)
    if ids.size == 0:
        return out
    ii, jj = np.nonzero(np.isin(lab, ids))
    ll = lab[ii, jj]
    rows, cost = [], []
    for name, pts in bones.items():
        radius = opts[name]["search_radius_mm"] / pixel_mm
        for p, ext in zip(pts, extension[name]):
            d = np.sqrt(ndimage.minimum((ii - p[0]) ** 2 + (jj - p[1]) ** 2, ll, ids))
            c = np.where(d <= radius, d + (radius if ext else 0.0), np.inf)
            rows.append(name)
            cost.append(c)
    # a region holding a long bone's own seed (its polyline crosses this slice inside it, or its proximal
    # end carried past it: the femoral head around the hip's centre) is that bone's: a density-rule seed
    # nearby may not take it (the assignment would push the long bone onto a far region to make room --
    # seen on a sagittal knee, the patella's seed taking the femur's condyle; the hip's seed, through
    # the hip's centre too, taking the femoral head)
    held = np.zeros(ids.size, bool)
    for name, pts in bones.items():
        hold = ~extension[name] if holds is None else holds[name]
        for p in np.asarray(pts)[hold]:
            i, j = int(round(p[0])), int(round(p[1]))
            if 0 <= i < lab.shape[0] and 0 <= j < lab.shape[1]:
                held |= ids == lab[i, j]
    for name, pts in (others or {}).items():
        radius = opts[name]["max_distance_mm"] / pixel_mm
        for p in pts:
            d = np.sqrt(ndimage.minimum((ii - p[0]) ** 2 + (jj - p[1]) ** 2, ll, ids))
            rows.append(None)
            cost.append(np.where((d <= radius) & ~held, d + 0.5 * radius, np.inf))
    cost = np.array(cost)
    finite = np.isfinite(cost)
    if not finite.any():
        return out
    # Marrow is rimmed by dark cortex; a bright speck of noise or fat between muscles by muscle. A region
    # (within reach of a seed) pays for the part of its rim that is not dark: a 17-pixel speck 2 px from
    # a seed 8 mm off took the seed from the marrow 6 px away (rims 0.0 and 0.9), and the bone lost that
    # section and with it its continuity from the shaft to the olecranon.
    reach = finite.any(axis=0)
    cost[:, reach] += (1.0 - cortical.rim_darkness(lab, ids[reach], med, m_slice, pixel_mm)) * (
        o0.get("unrimmed_cost_mm", 10.0) / pixel_mm)
    r_idx, c_idx = linear_sum_assignment(np.where(finite, cost, 1e9))
    for r, c in zip(r_idx, c_idx):
        if not finite[r, c]:
            continue
        name = rows[r]
        if name is None:
            continue
        out[name] |= _section_from_marrow(img, med, body, inner, pixel_mm, lab == ids[c], m_slice, opts[name])
    return out


def _section_from_marrow(img, med, body, inner, pixel_mm: float, region: np.ndarray, m_slice: float,
                         opts: Mapping) -> np.ndarray:
    """A long bone's section in one slice from its marrow region: holes filled, the cortical contour
    (:func:`~bonecap.segmentation.cortical.cortical_contour`) with the muscle level around it (the
    slice's where the neighbourhood gives none)."""
    marrow = density.fill_holes(region)
    mi, mj = np.nonzero(marrow)
    box, _ = cortical._crop_box(np.array([mi.mean(), mj.mean()]), img.shape, 65.0 / pixel_mm)
    m = cortical.muscle_level(med[box], inner[box])
    if not np.isfinite(m):
        m = m_slice
    return cortical.cortical_contour(img, marrow, pixel_mm, m, body_mask=body,
                                     **{k: v for k, v in opts.items() if k in _CONTOUR_KEYS})


def _split_shared_regions(lab: np.ndarray, n: int, seeds: Mapping[str, np.ndarray]) -> tuple[np.ndarray, int]:
    """Split a marrow region that holds the seeds of two or more long bones between them.

    Where two bones' marrow touch through a thin or partial-volumed cortex (a
    condyle on its plateau in a sagittal slice, radius and ulna at the distal
    radio-ulnar joint) the candidates are one region and the assignment could
    give it to one bone only. Such a region is cut along its neck: a
    watershed of its distance map from each bone's seed(s).
    """
    from skimage.segmentation import watershed

    inside: dict[int, list[tuple[str, np.ndarray]]] = {}
    for name, pts in seeds.items():
        for p in np.asarray(pts, float).reshape(-1, 2):
            i, j = int(round(p[0])), int(round(p[1]))
            if 0 <= i < lab.shape[0] and 0 <= j < lab.shape[1] and lab[i, j] > 0:
                inside.setdefault(int(lab[i, j]), []).append((name, np.array([i, j])))
    for region, hits in inside.items():
        names = sorted({h[0] for h in hits})
        if len(names) < 2:
            continue
        mask = lab == region
        markers = np.zeros(lab.shape, np.int32)
        for name, (i, j) in hits:
            markers[i, j] = names.index(name) + 1
        parts = watershed(-ndimage.distance_transform_edt(mask), markers, mask=mask)
        for q in range(2, len(names) + 1):
            n += 1
            lab[parts == q] = n
    return lab, n


_MARROW_KEYS = {"marrow_over_muscle", "min_marrow_mm2", "unrimmed_cost_mm", "enclosed_max_mm2"}
_CONTOUR_KEYS = {"n_rays", "max_radius_mm", "max_cortex_mm", "dip_fraction", "profile_sigma_px", "smooth_rays"}
_DENSITY_KEYS = {"fraction", "min_neighbours", "exclude_skin_band_mm"}


def _split_joints(labels: np.ndarray, ids: dict[str, int], seeds: Mapping[str, np.ndarray], volume: Volume,
                  long_bones: list[str], zone_mm: float, track=None) -> None:
    """Give each long bone its own side of a joint it shares with another (in place).

    Two long bones whose polylines share an end point (femur and tibia at the knee, humerus
    and ulna at the elbow) both reach into the slices around it, and with seeds ~15 mm off
    along the limb, the seed-distance rule hands the condyles to either. The joint space
    (cartilage, meniscus: no marrow) is the deepest valley of the two bones' summed
    cross-section within ``zone_mm`` (at most 15 % of the shorter bone's polyline) of the
    shared point (:func:`_joint_space`): every slice beyond it on a bone's side is given to
    that bone.

    Where both bones lie side by side in the joint's slices (the elbow: the olecranon behind
    the trochlea, both beside the capitulum), one slice cannot go to one bone. With ``track``
    (:func:`_track_joint`'s arguments bound) each bone is first followed from its own shaft
    through the zone, marrow region by marrow region; the regions so claimed keep their bone
    on either side of the joint space, and only what neither follows is split at it.
    """
    pts = {n: volume.world_to_index(np.asarray(seeds[n], float).reshape(-1, 3)) for n in long_bones}
    dz = float(volume.spacing[2])
    K = labels.shape[2]
    for a in long_bones:
        for b in long_bones:
            if a >= b or len(pts[a]) < 2 or len(pts[b]) < 2:
                continue
            ends_a, ends_b = pts[a][[0, -1]], pts[b][[0, -1]]
            gap = np.linalg.norm((ends_a[:, None, :] - ends_b[None, :, :]) * volume.spacing, axis=2)
            ia, ib = np.unravel_index(int(np.argmin(gap)), gap.shape)
            if gap[ia, ib] > 1.0:                # mm: not a shared joint point
                continue
            kj = ends_a[ia, 2]
            side_a = np.sign(ends_a[1 - ia, 2] - kj)
            side_b = np.sign(ends_b[1 - ib, 2] - kj)
            if side_a == 0 or side_a == side_b:
                continue
            # the seeds' joint point can be 20 mm off: the zone must reach the joint space from there,
            # yet stay on the short bones of an elbow (15 % of the shorter bone)
            length = min(float(np.sum(np.linalg.norm(np.diff(p, axis=0) * volume.spacing, axis=1)))
                         for p in (pts[a], pts[b]))
            zone_ab = min(zone_mm, 0.15 * length)
            zone = np.arange(K)[np.abs(np.arange(K) - kj) * dz <= zone_ab]
            if zone.size < 3:
                continue
            la, lb = ids[a], ids[b]
            both = (labels[:, :, zone] == la) | (labels[:, :, zone] == lb)
            area = both.sum(axis=(0, 1)).astype(float)
            ks = int(zone[_joint_space(area)])
            claimed = {} if track is None else track(labels, (a, b), zone, (side_a, side_b))
            for z, k in enumerate(zone):
                if k in claimed:
                    sec = claimed[k]
                    rest = both[:, :, z] & ~sec[a] & ~sec[b]
                    if k != ks:
                        owner = a if np.sign(k - ks) == side_a else b
                        # what the bone followed here does not continue is not its (the patella's marrow
                        # that the tibia's seed took above the knee); else the joint-space split
                        labels[:, :, k][rest] = 0 if sec[owner].any() else ids[owner]
                    for n in (a, b):
                        labels[:, :, k][sec[n]] = ids[n]
                    continue
                if k == ks:
                    continue
                owner = la if np.sign(k - ks) == side_a else lb
                labels[:, :, k][both[:, :, z]] = owner


def _marrow_candidates(med: np.ndarray, body: np.ndarray, pixel_mm: float, m_slice: float, opts: Mapping
                       ) -> np.ndarray:
    """:func:`~bonecap.segmentation.cortical.marrow_candidates` with a bone's options."""
    return cortical.marrow_candidates(med, body, m_slice, pixel_mm,
                                      marrow_over_muscle=opts.get("marrow_over_muscle", 1.2),
                                      enclosed_max_mm2=opts.get("enclosed_max_mm2", cortical.ENCLOSED_MAX_MM2))


def _marrow_key(opts: Mapping) -> tuple[float, float]:
    """The options a slice's marrow candidates depend on (:func:`_marrow_candidates`)."""
    return (float(opts.get("marrow_over_muscle", 1.2)), float(opts.get("enclosed_max_mm2", cortical.ENCLOSED_MAX_MM2)))


def _marrow_regions(med: np.ndarray, body: np.ndarray, inner: np.ndarray, pixel_mm: float, opts: Mapping,
                    found: tuple | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """A slice's marrow candidates as :func:`_cortical_slice` finds them: (labels, kept ids, muscle level).

    ``found``: the slice's regions as :func:`_cortical_slice` found them (its ``regions_out`` entry),
    used when they were found with the same options.
    """
    if found is not None and found[0] == _marrow_key(opts):
        _, lab, n, m_slice = found
    else:
        m_slice = cortical.muscle_level(med, inner)
        if not np.isfinite(m_slice) or m_slice <= 0:
            return np.zeros(med.shape, np.int32), np.zeros(0, int), m_slice
        cand = _marrow_candidates(med, body, pixel_mm, m_slice, opts)
        lab, n = cortical.detach_from_skin(cand, body, inner, pixel_mm)
    area = np.bincount(lab.ravel(), minlength=n + 1)[1:] * pixel_mm ** 2
    keep = np.flatnonzero(area >= opts.get("min_marrow_mm2", 6.0)) + 1
    return lab, keep, m_slice


def _track_joint(labels: np.ndarray, pair: tuple[str, str], zone: np.ndarray, sides: tuple[float, float], *,
                 ids: Mapping[str, int], img: np.ndarray, med: np.ndarray, body: np.ndarray, inner: np.ndarray,
                 pixel_mm: float, opts: Mapping[str, Mapping], crossed: Mapping[str, list[bool]] | None = None,
                 reach_mm: float = 3.0, min_overlap: float = 0.5) -> dict[int, dict[str, np.ndarray]]:
    """Follow two long bones from their shafts through a joint's slices, marrow region by region.

    Each bone starts from its section on the zone's slice farthest on its own side (its
    shaft, where the seed assignment is reliable) and steps towards the other side: on
    each slice the marrow regions (:func:`_marrow_regions`) lying on its previous ones (at
    least ``min_overlap`` of a region within ``reach_mm`` of them) are its; it stops where
    no region continues it (its end). The sections are the claimed regions' cortical
    contours. A bone whose polyline does not cross its starting slice (``crossed``) is not
    followed: its section there came from the seed margin and may be the other bone's. A
    region both bones reach goes to the one it lies on the more. Two marrow regions beside
    each other in one slice -- the elbow's trochlea in the olecranon's notch -- thus keep
    their own bones.

    Returns
    -------
    dict slice -> {bone: section mask}
        The zone's slices where either bone was followed.
    """
    from skimage.morphology import disk

    fp = disk(max(1, int(round(reach_mm / pixel_mm))))
    regions: dict[int, tuple] = {}

    def regions_of(k):
        if k not in regions:
            regions[k] = _marrow_regions(med[:, :, k], body[:, :, k], inner[:, :, k], pixel_mm, opts[pair[0]])
        return regions[k]

    follow: dict[str, dict[int, dict[int, float]]] = {}
    start: dict[str, tuple[int, np.ndarray]] = {}
    for n, side in zip(pair, sides):
        order = sorted(zone, key=lambda k: -side * k)         # from this bone's shaft towards the joint
        prev = labels[:, :, order[0]] == ids[n]
        start[n] = (int(order[0]), prev)                       # its own section there, as assigned
        if crossed is not None and not crossed[n][int(order[0])]:
            follow[n] = {}
            continue
        got: dict[int, dict[int, float]] = {}
        for k in order[1:]:
            if not prev.any():
                break
            lab, keep, _ = regions_of(k)
            if keep.size == 0:
                break
            near = ndimage.binary_dilation(prev, fp)
            area = np.asarray(ndimage.sum(np.ones_like(near), lab, keep))
            on = np.asarray(ndimage.sum(near, lab, keep)) / np.maximum(area, 1)
            mine = on >= min_overlap
            if not mine.any():
                break
            got[k] = {int(r): float(f) for r, f in zip(keep[mine], on[mine])}
            prev = np.isin(lab, keep[mine])
        follow[n] = got
    out: dict[int, dict[str, np.ndarray]] = {}
    a, b = pair
    for k in sorted(set(follow[a]) | set(follow[b]) | {start[a][0], start[b][0]}):
        lab, _, m_slice = regions_of(k)
        fa, fb = follow[a].get(k, {}), follow[b].get(k, {})
        own = {a: [r for r, f in fa.items() if f >= fb.get(r, -1.0)],
               b: [r for r, f in fb.items() if f > fa.get(r, -1.0)]}
        sec = {}
        for n in pair:
            mask = np.zeros(lab.shape, bool)
            for r in own[n]:
                mask |= _section_from_marrow(img[:, :, k], med[:, :, k], body[:, :, k], inner[:, :, k], pixel_mm,
                                             lab == r, m_slice, opts[n])
            if k == start[n][0] and not mask.any():
                mask = start[n][1].copy()
            sec[n] = mask
        sec[a] &= ~sec[b]
        out[k] = sec
    return out


def _joint_space(area: np.ndarray) -> int:
    """Index of the joint space in a profile of summed cross-sections along a joint's zone.

    The joint space is a valley between two peaks (femoral condyles above, tibial plateau below),
    not the profile's minimum: with the seeds' joint point 20 mm off, the zone reaches the femoral
    shaft, whose section is smaller than the joint space's, and the minimum handed the condyles to
    the tibia. The deepest valley -- the slice whose area lies furthest below the lower of the
    largest areas on either side of it -- is the joint space; a profile without a valley (the zone
    inside one bone) falls back to the minimum.
    """
    a = np.asarray(area, float)
    if a.size < 3:
        return int(np.argmin(a))
    left = np.maximum.accumulate(a)
    right = np.maximum.accumulate(a[::-1])[::-1]
    depth = np.minimum(left, right) - a
    depth[[0, -1]] = -np.inf
    k = int(np.argmax(depth))
    return k if depth[k] > 0 else int(np.argmin(a))


def _seed_distance(mask: np.ndarray, seed: np.ndarray) -> float:
    ii, jj = np.nonzero(mask)
    if ii.size == 0:
        return float("inf")
    return float(np.sqrt(np.min((ii - seed[0]) ** 2 + (jj - seed[1]) ** 2)))


def segment_bones(volume: Volume, seeds: Mapping[str, np.ndarray], *, body_mask: np.ndarray | None = None,
                  rules: Mapping[str, str] | None = None, progress: bool = True, margin_mm: float = 20.0,
                  options: Mapping[str, Mapping] | None = None, sigma_px: float = 0.7,
                  joint_zone_mm: float = 60.0, continuity: bool = True,
                  follow_mm: Mapping[str, float] | None = None,
                  follow_head_mm: Mapping[str, float] | None = None,
                  follow_tips: Iterable[str] = (),
                  marrow_regions: dict | None = None) -> tuple[np.ndarray, dict[str, int]]:
    """Label every seeded bone of an axial stack, slice by slice, by its rule.

    Per slice ``k``: each bone whose seed polyline reaches the slice (with
    ``margin_mm``; :func:`slice_seeds`) is segmented around its crossing
    point(s) -- long bones by the cortical-edge rule (all of a slice's long
    bones together, so that two seeds never take the same marrow), the
    others by the density-threshold rule (the slice's candidates computed
    once; candidate regions already taken by a long bone are not offered to
    them). Two bones claiming one pixel: the nearest seed wins. Holes are
    filled per slice. A long bone's single searched slice left empty between
    two of its sections is tracked from its neighbours
    (:func:`_fill_single_gaps`). Long bones meeting at a joint are split at
    the joint space (see ``joint_zone_mm``).

    Parameters
    ----------
    volume : Volume
        Axial stack: ``data[i, j, k]`` with ``k`` the slice axis, ``affine``
        voxel -> LPS mm. Square-ish pixels (the mean in-plane spacing is used).
    seeds : dict bone name -> array (N, 3)
        Seed polyline per bone, LPS world mm (see :func:`slice_seeds`); a long
        bone's from its proximal to its distal end (its joint centres, in that
        order: past the first one the region around it is its head).
    body_mask : ndarray of bool, optional
        The body (:func:`bonecap.segmentation.skin.segment_body`, computed
        when not given).
    rules : dict bone name -> "cortical" | "density", optional
        Overrides of :func:`default_rule`.
    progress : bool
        A progress bar over slices on stderr (:mod:`bonecap.progress`).
    margin_mm : float
        How far beyond its polyline's ends a bone is still searched.
    options : dict bone name -> dict, optional
        Keyword options per bone for its rule: for cortical bones
        ``search_radius_mm`` and those of
        :func:`~bonecap.segmentation.cortical.find_marrow` /
        :func:`~bonecap.segmentation.cortical.cortical_contour`; for density
        bones ``max_distance_mm`` and those of
        :func:`~bonecap.segmentation.density.slice_candidates` (the slice's
        candidates are computed once per distinct set of those).
    sigma_px : float
        In-plane Gaussian of the noise removal, pixels, applied once to the
        stack (see :func:`~bonecap.segmentation.density.density_candidates`).
    continuity : bool
        Keep only the sections of each long bone that continue it from its
        shaft outwards (:func:`_keep_continuous`; default), and none the seed
        margin found past more than :data:`MARGIN_GAP_MM` of empty slices. Off for a stack that
        is registered as a whole afterwards, where every section helps (the
        forearm stacks: in a pronated forearm the ulna's chain breaks where its
        seed took the radius).
    follow_mm : dict bone name -> float, optional
        Long bones whose distal end is followed past the search, slice by
        slice, up to this far (mm), where it goes on: a polyline from a
        template ends where the template's bone does (the tibia's, short of
        the talus), and a bone longer than its template would be cut there.
        See :func:`_follow_distal_end`.
    follow_head_mm : dict bone name -> float, optional
        Long bones whose proximal end is a head in another bone's socket
        (femur, humerus), followed past the search up to this far (mm) while
        the head goes on, taking back what the socket's density rule took
        (:func:`_follow_head`).
    follow_tips : iterable of str
        Those of ``follow_mm`` whose distal end is a free tip (the fibula's
        lateral malleolus): after the continuity walk, the sections past the
        last one kept that go on narrowing are the bone's (:func:`_extend_tip`,
        over at most 15 mm). For the others a drop in the section is their
        joint, where the following stops.
    joint_zone_mm : float
        Two long bones whose polylines share an end point (a joint centre:
        femur and tibia at the knee) are split at the deepest valley of their summed
        cross-section (the joint space) within this distance of that point (at most 15 %
        of the shorter bone's length);
        each side goes to the bone whose polyline lies there.
    marrow_regions : dict, optional
        Filled with each slice's marrow candidate regions where the cortical
        rule looked for them (slice index -> entry), for :func:`marrow_sections`
        (``regions``) to reuse on the same stack instead of finding them again.

    Returns
    -------
    labels : ndarray int32, same shape as ``volume.data``
        0 background, else the bone's id.
    ids : dict bone name -> int
        Label ids, 1.. in the order of ``seeds``.

    Raises
    ------
    ValueError
        Not a Volume, an unknown rule, bad seeds, a body mask of another shape.

    References
    ----------
    Kojima et al. (bone contours slice by slice, the two rules, seeds).
    """
    if not isinstance(volume, Volume):
        raise ValueError(f"volume must be a bonecap.model.Volume, got {type(volume).__name__}")
    if not isinstance(seeds, Mapping) or not seeds:
        raise ValueError("seeds must be a non-empty dict: bone name -> (N, 3) LPS polyline")
    rules = dict(rules or {})
    unknown = {b: r for b, r in rules.items() if r not in RULES}
    if unknown:
        raise ValueError(f"unknown rule(s) {unknown}; use one of {RULES}")
    options = {str(k): dict(v) for k, v in (options or {}).items()}
    data = np.asarray(volume.data)
    body_mask = check_body_mask(volume, body_mask)
    sp = volume.spacing
    pixel_mm = float(0.5 * (sp[0] + sp[1]))

    names = list(seeds)
    ids = {n: i + 1 for i, n in enumerate(names)}
    rule_of = {n: rules.get(n, default_rule(n)) for n in names}
    per_slice = {n: slice_seeds(volume, seeds[n], margin_mm) for n in names}
    # seeds only there because of the margin (beyond the polyline's ends) yield to crossings
    crossing = {n: slice_seeds(volume, seeds[n], 0.0) for n in names}
    # slices past a polyline's first point (a long bone's proximal end, its seeds run proximal to distal)
    before_start = {}
    for n in (n for n in names if rule_of[n] == "cortical"):
        kk = volume.world_to_index(np.asarray(seeds[n], float).reshape(-1, 3))[:, 2]
        ks = np.arange(data.shape[2])
        before_start[n] = (ks < kk[0]) if kk[0] <= kk[-1] else (ks > kk[0])
    opts = {}
    for n in names:
        o = dict(options.get(n, {}))
        if rule_of[n] == "cortical":
            o.setdefault("search_radius_mm", _SEARCH_RADIUS_MM.get(_base(n), 30.0))
            bad = set(o) - _MARROW_KEYS - _CONTOUR_KEYS - {"search_radius_mm"}
        else:
            o.setdefault("max_distance_mm", 25.0)
            bad = set(o) - _DENSITY_KEYS - {"max_distance_mm"}
        if bad:
            raise ValueError(f"unknown option(s) {sorted(bad)} for bone {n!r} ({rule_of[n]} rule)")
        opts[n] = o

    # Noise removal once for the stack (in-plane Gaussian, slices independent), and the body's
    # interior (without its outer 3 mm, where fat reaches the skin), both shared by all bones.
    smooth = ndimage.gaussian_filter(data.astype(np.float32, copy=False), (sigma_px, sigma_px, 0.0), mode="nearest")
    inplane = np.zeros((3, 3, 3), bool)
    inplane[:, :, 1] = True
    band_px = max(1, int(round(3.0 / pixel_mm)))
    interior = ndimage.binary_erosion(body_mask, inplane, iterations=band_px, border_value=1)
    labels = np.zeros(data.shape, np.int32)
    K = data.shape[2]
    it = _progress(range(K), desc="bones", total=K, unit="slice") if progress else range(K)
    for k in it:
        here = {n: per_slice[n][k] for n in names if len(per_slice[n][k])}
        if not here:
            continue
        img = data[:, :, k]
        body = body_mask[:, :, k]
        masks: dict[str, np.ndarray] = {}
        long_here = {n: s for n, s in here.items() if rule_of[n] == "cortical"}
        if long_here:
            ext = {n: np.full(len(s), len(crossing[n][k]) == 0) for n, s in long_here.items()}
            holds = {n: np.full(len(s), len(crossing[n][k]) > 0 or before_start[n][k]) for n, s in long_here.items()}
            others = {n: s for n, s in here.items() if rule_of[n] == "density"}
            got: list | None = [] if marrow_regions is not None else None
            masks.update(_cortical_slice(img, smooth[:, :, k], body, interior[:, :, k], pixel_mm, long_here, ext,
                                         opts, others, holds, regions_out=got))
            if got:
                marrow_regions[k] = got[0]
        taken = np.zeros(img.shape, bool)
        for m in masks.values():
            taken |= m
        cand_cache: dict[tuple, np.ndarray] = {}
        for n, pts in here.items():
            if rule_of[n] != "density":
                continue
            o = opts[n]
            key = tuple(sorted((k_, v) for k_, v in o.items() if k_ in _DENSITY_KEYS))
            if key not in cand_cache:
                cand = density.slice_candidates(smooth[:, :, k], body, pixel_mm, sigma_px=0.0, **dict(key))
                if taken.any() and cand.any():
                    # regions overlapping a long bone belong to it: not offered to density bones
                    lab, nl = ndimage.label(cand, structure=np.ones((3, 3), bool))
                    hit = np.zeros(nl + 1, bool)
                    hit[np.unique(lab[taken & cand])] = True
                    hit[0] = True
                    cand = ~hit[lab]
                cand_cache[key] = cand
            region = np.zeros(img.shape, bool)
            for s in pts:
                region |= density.density_threshold_slice(img, s, pixel_mm, body, candidates=cand_cache[key],
                                                          max_distance_mm=o["max_distance_mm"])
            masks[n] = region
        masks = {n: m for n, m in masks.items() if m.any()}
        masks = _resolve_overlaps(masks, here)
        for n, m in masks.items():
            labels[:, :, k][density.fill_holes(m) & (labels[:, :, k] == 0)] = ids[n]
    long_bones = [n for n in names if rule_of[n] == "cortical"]
    searched = {n: np.array([len(s) > 0 for s in per_slice[n]]) for n in long_bones}

    def to_follow(reaches):
        """``(bone, slice step towards its distal end, slices)`` of the searched long bones in ``reaches``."""
        for n, reach in (reaches or {}).items():
            if n in ids and rule_of[n] == "cortical" and reach > 0 and searched[n].any():
                kk = volume.world_to_index(np.asarray(seeds[n], float).reshape(-1, 3))[:, 2]
                yield n, (1 if kk[-1] >= kk[0] else -1), int(np.ceil(reach / float(sp[2])))

    tips = set(follow_tips)
    for n, step, slices in to_follow(follow_mm):
        where = np.flatnonzero(searched[n])
        last = int(where.max() if step > 0 else where.min())
        _follow_distal_end(labels, ids[n], n, last, step, slices, data, smooth, body_mask, interior, pixel_mm, opts)
    for n in long_bones:
        _fill_single_gaps(labels, ids[n], n, searched[n], data, smooth, body_mask, interior, pixel_mm, opts)
    crossed = {n: [len(c) > 0 for c in crossing[n]] for n in long_bones}
    track = partial(_track_joint, ids=ids, img=data, med=smooth, body=body_mask, inner=interior, pixel_mm=pixel_mm,
                    opts=opts, crossed=crossed)
    _split_joints(labels, ids, seeds, volume, long_bones, joint_zone_mm, track=track)
    if continuity:
        _keep_continuous(labels, ids, crossed, pixel_mm, slice_mm=float(sp[2]))
    # a free tip after the walk: its narrowing sections are tracked from the last one the walk kept
    # (the search past the fibula's point took the talus's marrow with it, which the walk dropped)
    for n, step, _ in to_follow({n: v for n, v in (follow_mm or {}).items() if n in tips}):
        _extend_tip(labels, ids[n], n, step, int(np.ceil(_TIP_MM / float(sp[2]))), data, smooth, body_mask,
                    interior, pixel_mm, opts)
    # the heads last: from the sections that continue the shaft (a stray section past the head would
    # start the track in the socket's roof)
    density_ids = [ids[n] for n in names if rule_of[n] == "density"]
    for n, step, slices in to_follow(follow_head_mm):
        _follow_head(labels, ids[n], n, -step, slices, data, smooth, body_mask, interior, pixel_mm, opts,
                     density_ids)
    return labels, ids


# A long bone's section tracked from its section on a neighbouring slice (:func:`_follow_distal_end`,
# :func:`_fill_single_gaps`): at most this much larger (_continues), overlapping by this fraction
# within this reach, its marrow within this window and no brighter than this times the previous marrow's.
_TRACK_GROW = 1.6
_TRACK_MIN_OVERLAP = 0.5
_TRACK_REACH_MM = 3.0
_TRACK_WINDOW_MM = 2.0
_TRACK_MARROW_TOP = 1.25
# How far past a bone's last kept section its narrowing tip is tracked (:func:`_extend_tip`): the
# fibula's lateral malleolus narrows from its widest section to its point over ~10-15 mm.
_TIP_MM = 15.0


def _follow_distal_end(labels: np.ndarray, lid: int, name: str, last: int, step: int, max_slices: int,
                       data: np.ndarray, smooth: np.ndarray, body_mask: np.ndarray, interior: np.ndarray,
                       pixel_mm: float, opts: Mapping, *, grow: float = _TRACK_GROW,
                       min_overlap: float = _TRACK_MIN_OVERLAP, reach_mm: float = _TRACK_REACH_MM,
                       window_mm: float = _TRACK_WINDOW_MM, joint_drop: float = 0.6,
                       marrow_top: float = _TRACK_MARROW_TOP) -> int:
    """Follow a long bone past the last slice its search reached (in place); the number of slices added.

    Only when the bone is labelled on that slice (it goes on past the search).
    Each next slice's section is tracked from the previous one: its marrow is
    the largest piece of the slice's marrow candidates within ``window_mm`` of
    the previous section, its contour the cortical rule's around that marrow
    (:func:`_section_from_marrow`, kept within three windows of the previous
    section), on pixels no other bone holds. It is kept while it continues
    the previous one (:func:`_continues`: one lies on the other,
    ``min_overlap`` within ``reach_mm``, at most ``grow`` times larger) and is
    at least ``joint_drop`` of the largest of the bone's last four sections.
    The second condition is the joint: a long bone's end widens into its
    epiphysis up to the joint line (the distal tibia to its plafond, ~2.5
    times its shaft's section on the phantoms), and the bone
    across the joint (the talus's dome in the mortise) shows in the next
    slices as a smaller section lying on it -- continuity alone would follow
    into it (as :func:`_keep_continuous` explains). The track is kept only
    when it ended so, at a joint (or at the images' end): one that ran to
    ``max_slices`` or lost the marrow on the way followed something past the
    bone's end, and nothing of it is labelled. What lies past the stop
    (the medial malleolus beside the talus) stays unlabelled: the warp
    extrapolates it (:func:`bonecap.build_mri.unseen_ends`); a free tip (the
    fibula's lateral malleolus) is tracked after the continuity walk
    (:func:`_extend_tip`).

    The marrow is kept to the marrow's own brightness (``marrow_top`` times the
    90th percentile of the previous slice's marrow), and so is the section:
    where marrow touches fat that is brighter (T2; the phantom's distal tibia,
    subcutaneous on its medial face), the track would otherwise widen into the
    fat by a window each slice.
    """
    from skimage.morphology import disk

    K = labels.shape[2]
    prev = labels[:, :, last] == lid
    if not prev.any():
        return 0
    sums = (labels == lid).sum(axis=(0, 1))
    towards_end = sums[:last + 1] if step > 0 else sums[last:][::-1]
    areas = [int(a) for a in towards_end if a > 0][-4:]
    fp = disk(max(1, int(round(reach_mm / pixel_mm))))
    win_fp = disk(max(1, int(round(window_mm / pixel_mm))))
    o = opts[name]
    top = _section_marrow_top(smooth, interior, last, prev, o, marrow_top)
    added_at: list[tuple[int, np.ndarray]] = []
    at_joint = False
    k = last + step
    while 0 <= k < K and len(added_at) < max_slices:
        got = _track_section(labels, k, prev, top, data, smooth, body_mask, interior, pixel_mm, o, win_fp)
        if got is None:
            break
        sec, region = got
        n = int(sec.sum())
        if n == 0 or not _continues(sec, prev, fp, grow, min_overlap):
            break
        if n < joint_drop * max(areas[-4:]):
            at_joint = True
            break
        added_at.append((k, sec))
        areas.append(n)
        prev = sec
        top = _marrow_top(smooth[:, :, k], region, marrow_top)
        k += step
    # A bone's end is its joint: the track stands only where it ended at one (or at the images' end). One
    # that ran to its limit, or lost the bone's marrow on the way, followed something else beyond the
    # bone's end (past the distal ulna the carpals, larger than its head, continue it slice after slice).
    return _commit_track(labels, lid, added_at, at_joint or not 0 <= k < K)


def _extend_tip(labels: np.ndarray, lid: int, name: str, step: int, tip_slices: int, data: np.ndarray,
                smooth: np.ndarray, body_mask: np.ndarray, interior: np.ndarray, pixel_mm: float, opts: Mapping,
                *, reach_mm: float = _TRACK_REACH_MM, window_mm: float = _TRACK_WINDOW_MM,
                marrow_top: float = _TRACK_MARROW_TOP) -> int:
    """Label a long bone's narrowing tip past its last section towards ``step`` (in place); how many slices.

    For a bone that ends in a free point (the fibula's lateral malleolus): the
    next slice's section is tracked from the last labelled one as
    :func:`_follow_distal_end` tracks (:func:`_track_section`) and taken, with
    the sections after it, only while each is smaller than the one before
    (:func:`_tapering_tip`). A section no smaller than the last is another
    bone's or the bone's own shaft cut off by the continuity walk
    (:func:`_keep_continuous`), which is not undone here.
    """
    from skimage.morphology import disk

    area = (labels == lid).sum(axis=(0, 1))
    nz = np.flatnonzero(area)
    if not len(nz) or tip_slices < 1:
        return 0
    last = int(nz.max() if step > 0 else nz.min())
    fp = disk(max(1, int(round(reach_mm / pixel_mm))))
    win_fp = disk(max(1, int(round(window_mm / pixel_mm))))
    o = opts[name]
    sec = labels[:, :, last] == lid
    top = _section_marrow_top(smooth, interior, last, sec, o, marrow_top)
    # from the last kept section itself: it heads the run when the next one is smaller (and is labelled already)
    tip = _tapering_tip(labels, last, step, sec, top, tip_slices + 1, data, smooth, body_mask, interior, pixel_mm,
                        o, win_fp, fp)[1:]
    for kk, s_ in tip:
        labels[:, :, kk][s_] = lid
    return len(tip)


def _tapering_tip(labels: np.ndarray, k: int, step: int, sec: np.ndarray, top: float, tip_slices: int,
                  data: np.ndarray, smooth: np.ndarray, body_mask: np.ndarray, interior: np.ndarray,
                  pixel_mm: float, o: Mapping, win_fp: np.ndarray, fp: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """The sections ``(slice, mask)`` of a bone's tip from its section ``sec`` on slice ``k``
    (:func:`_extend_tip`); none when they are not a tip.

    A tip narrows to its point: each of its sections, ``sec`` first, is kept when the next one, tracked
    from it (:func:`_track_section`), is smaller still, or when no marrow lies past it (or the images
    end), up to ``tip_slices`` sections. The first section that the next one does not continue smaller
    is not kept: a bone across a joint grows again past the drop (the talus's dome into its body),
    and past a tip's point the track takes whatever bright tissue lies beside it (fat at the
    phantom's malleolus, growing slice by slice).
    """
    K = labels.shape[2]
    out: list[tuple[int, np.ndarray]] = []
    prev, kk = sec, k
    while len(out) < tip_slices:
        nk = kk + step
        if not 0 <= nk < K:
            return out + [(kk, prev)]
        got = _track_section(labels, nk, prev, top, data, smooth, body_mask, interior, pixel_mm, o, win_fp)
        if got is None or not got[0].any():
            return out + [(kk, prev)]
        nxt = got[0]
        if nxt.sum() >= prev.sum() or not _continues(nxt, prev, fp, 1.0, _TRACK_MIN_OVERLAP):
            return out
        out.append((kk, prev))
        prev, kk = nxt, nk
    return out


def _commit_track(labels: np.ndarray, lid: int, added: list[tuple[int, np.ndarray]], ended: bool) -> int:
    """Label a track's sections ``(slice, mask)`` with ``lid`` when it ended at the bone's end, else none
    of them (a track that ran to its limit followed something else); how many slices were labelled."""
    if added and not ended:
        return 0
    for k, sec in added:
        labels[:, :, k][sec] = lid
    return len(added)


#: A head's section may grow by this factor per slice towards its equator (:func:`_follow_head`); past
#: the equator it may not grow at all (by more than a pixel row of noise).
_HEAD_GROW = 1.3
_HEAD_REGROW = 1.1
#: Past the equator a ball's sections are concentric: a section whose centre moved by more than this
#: (mm) or a fifth of the previous section's radius is the socket's (its roof's fossa), not the head's.
_HEAD_DRIFT_MM = 2.5


def _follow_head(labels: np.ndarray, lid: int, name: str, step: int, max_slices: int, data: np.ndarray,
                 smooth: np.ndarray, body_mask: np.ndarray, interior: np.ndarray, pixel_mm: float, opts: Mapping,
                 yield_ids, *, min_overlap: float = _TRACK_MIN_OVERLAP, reach_mm: float = _TRACK_REACH_MM,
                 window_mm: float = _TRACK_WINDOW_MM, marrow_top: float = _TRACK_MARROW_TOP) -> int:
    """Follow a long bone's head past its proximal end, into its socket (in place); the slices added.

    The search of a long bone reaches ``margin_mm`` past the joint centre of the
    template placed on the body, which can lie 15-25 mm from the subject's (the
    template is placed from the body's extent): the phantoms' femoral heads lost
    their upper 8-25 mm (seeds 1, 2, 4) and seed 4's humeral heads 26 mm, and the
    socket's density rule (the hip bone's, the scapula's) took them as its own.
    From the bone's last section on the proximal side, each next slice's section
    is tracked (:func:`_track_section`), on pixels that are free or held by a
    density-rule bone (``yield_ids``), while it continues the previous one
    (:func:`_continues`) and grows by at most :data:`_HEAD_GROW` up to the head's
    equator and not at all past it (by at most :data:`_HEAD_REGROW`: a ball's
    sections shrink to its pole; a larger one is the socket's roof), its centre
    staying put past the equator (:data:`_HEAD_DRIFT_MM`). The equator may lie
    below the start: the search's last two sections already shrinking count.
    The track ends where the marrow ends or stops continuing (the pole); one that
    runs to ``max_slices`` followed something else and is dropped. Run after
    :func:`_keep_continuous`, from the sections that continue the shaft (a
    stray section past the pole would start it in the socket's roof).
    """
    from skimage.morphology import disk

    K = labels.shape[2]
    sums = (labels == lid).sum(axis=(0, 1))
    where = np.flatnonzero(sums)
    if where.size == 0:
        return 0
    first = int(where.min() if step < 0 else where.max())
    prev = labels[:, :, first] == lid
    fp = disk(max(1, int(round(reach_mm / pixel_mm))))
    win_fp = disk(max(1, int(round(window_mm / pixel_mm))))
    o = opts[name]
    top = _section_marrow_top(smooth, interior, first, prev, o, marrow_top)
    added: list[tuple[int, np.ndarray]] = []
    # past the equator already where the search stopped (its last section smaller than the one before)
    shrinking = 0 <= first - step < K and 0 < sums[first] < sums[first - step]
    ended = False
    k = first + step
    while 0 <= k < K and len(added) < max_slices:
        got = _track_section(labels, k, prev, top, data, smooth, body_mask, interior, pixel_mm, o, win_fp,
                             yield_ids)
        if got is None:
            ended = True
            break
        sec, region = got
        n, n_prev = int(sec.sum()), int(prev.sum())
        if n == 0 or not _continues(sec, prev, fp, _HEAD_GROW, min_overlap) or (
                shrinking and n > _HEAD_REGROW * n_prev + 4):
            ended = True
            break
        if shrinking:
            drift = np.linalg.norm(np.argwhere(sec).mean(axis=0) - np.argwhere(prev).mean(axis=0)) * pixel_mm
            if drift > max(_HEAD_DRIFT_MM, 0.2 * np.sqrt(n_prev / np.pi) * pixel_mm):
                ended = True
                break
        shrinking = shrinking or n < n_prev
        added.append((k, sec))
        prev = sec
        top = _marrow_top(smooth[:, :, k], region, marrow_top)
        k += step
    return _commit_track(labels, lid, added, ended or not 0 <= k < K)


def _fill_single_gaps(labels: np.ndarray, lid: int, name: str, searched: np.ndarray, data: np.ndarray,
                      smooth: np.ndarray, body_mask: np.ndarray, interior: np.ndarray, pixel_mm: float, opts: Mapping,
                      *, grow: float = _TRACK_GROW, min_overlap: float = _TRACK_MIN_OVERLAP,
                      reach_mm: float = _TRACK_REACH_MM, window_mm: float = _TRACK_WINDOW_MM,
                      marrow_top: float = _TRACK_MARROW_TOP) -> int:
    """Fill a long bone's single missing slices between two of its sections (in place); how many.

    A slice searched and left empty between two sections of the bone is where the whole-slice rule
    lost the marrow (touching fat through a cortex too thin to show, or joined to a neighbour's
    region). The section there is tracked from the slice before (:func:`_track_section`, as
    :func:`_follow_distal_end` does) and kept only if it continues both neighbours
    (:func:`_continues`).
    """
    from skimage.morphology import disk

    K = labels.shape[2]
    area = (labels == lid).sum(axis=(0, 1))
    fp = disk(max(1, int(round(reach_mm / pixel_mm))))
    win_fp = disk(max(1, int(round(window_mm / pixel_mm))))
    o = opts[name]
    filled = 0
    for k in range(1, K - 1):
        if area[k] or not (area[k - 1] and area[k + 1]) or not searched[k]:
            continue
        prev, nxt = labels[:, :, k - 1] == lid, labels[:, :, k + 1] == lid
        top = _section_marrow_top(smooth, interior, k - 1, prev, o, marrow_top)
        got = _track_section(labels, k, prev, top, data, smooth, body_mask, interior, pixel_mm, o, win_fp)
        if got is None:
            continue
        sec = got[0]
        if sec.any() and _continues(sec, prev, fp, grow, min_overlap) and _continues(sec, nxt, fp, grow, min_overlap):
            labels[:, :, k][sec] = lid
            filled += 1
    return filled


def _track_section(labels: np.ndarray, k: int, prev: np.ndarray, top: float, data: np.ndarray, smooth: np.ndarray,
                   body_mask: np.ndarray, interior: np.ndarray, pixel_mm: float, o: Mapping, win_fp: np.ndarray,
                   yield_ids=()) -> tuple[np.ndarray, np.ndarray] | None:
    """A long bone's section on slice ``k`` tracked from its section ``prev`` on a neighbouring slice:
    ``(section, marrow)``, or None where no marrow lies on it. See :func:`_follow_distal_end`. Pixels
    labelled with one of ``yield_ids`` count as free (:func:`_follow_head`)."""
    med, body, inner = smooth[:, :, k], body_mask[:, :, k], interior[:, :, k]
    m_slice = cortical.muscle_level(med, inner)
    if not np.isfinite(m_slice) or m_slice <= 0:
        return None
    # the marrow lying on the previous section: the candidates within a few mm of it, so that where
    # the cortex is too thin to show (the distal tibia's subcutaneous face) the marrow is not lost
    # to the fat it touches (the whole-slice rule drops such a region with the fat)
    free = (labels[:, :, k] == 0) | np.isin(labels[:, :, k], list(yield_ids))
    cand = _marrow_candidates(med, body, pixel_mm, m_slice, o) & ndimage.binary_dilation(prev, win_fp) & free
    if np.isfinite(top):
        # no brighter than the marrow above: where the marrow touches fat that is brighter (T2, or fat
        # suppression's failure), the track would otherwise widen into the fat by a window a slice
        cand &= med <= top
    lab, nl = ndimage.label(cand, structure=np.ones((3, 3), bool))
    if nl == 0:
        return None
    region = lab == 1 + int(np.argmax(np.bincount(lab.ravel())[1:]))
    if region.sum() * pixel_mm ** 2 < o.get("min_marrow_mm2", 6.0):
        return None
    # the section's own edge (the cortical contour around that marrow), within three windows
    sec = density.fill_holes(_section_from_marrow(data[:, :, k], med, body, inner, pixel_mm, region, m_slice, o))
    sec &= ndimage.binary_dilation(prev, win_fp, iterations=3) & free
    if np.isfinite(top):
        sec &= med <= top          # nor the contour: with no cortex against the fat it runs on into it
    return sec, region


def _section_marrow_top(smooth: np.ndarray, interior: np.ndarray, k: int, section: np.ndarray, o: Mapping,
                        factor: float) -> float:
    """:func:`_marrow_top` of a labelled section's marrow (its pixels brighter than the rule's marrow level)."""
    m0 = cortical.muscle_level(smooth[:, :, k], interior[:, :, k])
    if not np.isfinite(m0):
        return np.inf
    return _marrow_top(smooth[:, :, k], section & (smooth[:, :, k] > o.get("marrow_over_muscle", 1.2) * m0), factor)


def _marrow_top(med: np.ndarray, marrow: np.ndarray, factor: float) -> float:
    """``factor`` x the 90th percentile of a marrow region's intensities (inf for an empty region)."""
    vals = med[marrow]
    return float(factor * np.percentile(vals, 90)) if vals.size >= 5 else np.inf


def marrow_sections(volume: Volume, where: np.ndarray, *, body_mask: np.ndarray | None = None,
                    exclude: np.ndarray | None = None, per_slice: int | None = None, min_rim: float = 0.2,
                    sigma_px: float = 0.7, options: Mapping | None = None,
                    regions: Mapping | None = None) -> np.ndarray:
    """Every long-bone section whose marrow meets ``where``, without seeds.

    Per slice, the marrow candidates of :func:`segment_bones`'s cortical rule
    (bright regions inside the body, cut loose from the fat at the skin, not
    too small) that overlap ``where``, lie mostly outside ``exclude`` and are
    rimmed by dark cortex (at least ``min_rim`` of their rim,
    :func:`~bonecap.segmentation.cortical.rim_darkness`; a speck of fat
    between muscles is not) are each grown to their cortical contour; with
    ``per_slice``, only that many per slice, those with the most rimmed area
    (area x dark fraction of the rim) first. For a bone whose place is known
    better than any seed line could give it: the radius in a pronated
    forearm, somewhere in the ring it sweeps about the ulna.

    Parameters
    ----------
    volume : Volume
        Axial stack (``data[i, j, k]``, ``k`` the slice axis).
    where : ndarray of bool, the volume's shape
        Where the marrow may be.
    body_mask : ndarray of bool, optional
        The body (computed when not given).
    exclude : ndarray of bool, optional
        Another bone's place: a region half inside it (of its part in ``where``)
        is not a candidate.
    per_slice : int, optional
        At most this many sections per slice (one for a single bone).
    min_rim : float
        Smallest dark fraction of a marrow region's rim. Shaft marrow is
        rimmed 0.7-0.9, an epiphysis behind its thin cortex 0.2-0.5 (a
        forearm stack at 0.7 mm pixels), specks of fat between muscles 0-0.2.
    sigma_px : float
        In-plane Gaussian of the noise removal, pixels.
    options : dict, optional
        Cortical-rule options (``marrow_over_muscle``, ``min_marrow_mm2`` and
        those of :func:`~bonecap.segmentation.cortical.cortical_contour`).
    regions : dict, optional
        :func:`segment_bones`'s ``marrow_regions`` of the same volume, body
        mask and ``sigma_px`` (0.7 there): the slices' marrow candidates it
        found already (where found with the same options), not found again.

    Returns
    -------
    ndarray of bool, the volume's shape
        The sections (filled); they may reach beyond ``where``.

    References
    ----------
    Kojima et al. (the cortical-edge rule: bright marrow in a dark cortical ring).
    """
    if not isinstance(volume, Volume):
        raise ValueError(f"volume must be a bonecap.model.Volume, got {type(volume).__name__}")
    data = np.asarray(volume.data)
    where = np.asarray(where, bool)
    if where.shape != data.shape:
        raise ValueError(f"where must have the volume's shape {data.shape}, got {where.shape}")
    opts = dict(options or {})
    bad = set(opts) - _MARROW_KEYS - _CONTOUR_KEYS
    if bad:
        raise ValueError(f"unknown option(s) {sorted(bad)} for the cortical rule")
    body_mask = check_body_mask(volume, body_mask)
    exclude = np.zeros(data.shape, bool) if exclude is None else np.asarray(exclude, bool)
    if exclude.shape != data.shape:
        raise ValueError(f"exclude must have the volume's shape {data.shape}, got {exclude.shape}")
    if per_slice is not None and per_slice < 1:
        raise ValueError(f"per_slice must be at least 1, got {per_slice}")
    pixel_mm = float(0.5 * (volume.spacing[0] + volume.spacing[1]))
    out = np.zeros(data.shape, bool)
    for k in np.flatnonzero(where.any(axis=(0, 1))):
        img = data[:, :, k]
        med = ndimage.gaussian_filter(img.astype(np.float32), sigma_px, mode="nearest")
        body = body_mask[:, :, k]
        inner = cortical._interior(body, pixel_mm, 3.0)
        lab, keep, m = _marrow_regions(med, body, inner, pixel_mm, opts, found=(regions or {}).get(int(k)))
        keep = np.intersect1d(keep, np.unique(lab[where[:, :, k]]))
        if not keep.size:
            continue
        area = np.bincount(lab.ravel(), minlength=lab.max() + 1)
        # half inside ``exclude`` of what of it lies in ``where`` (all the caller may have tested)
        there = np.bincount(lab[where[:, :, k]], minlength=lab.max() + 1)
        inside = np.bincount(lab[exclude[:, :, k] & where[:, :, k]], minlength=lab.max() + 1)
        keep = keep[inside[keep] < 0.5 * there[keep]]
        rim = cortical.rim_darkness(lab, keep, med, m, pixel_mm)
        keep, rim = keep[rim >= min_rim], rim[rim >= min_rim]
        if per_slice is not None:
            keep = keep[np.argsort(-area[keep] * rim, kind="stable")[:per_slice]]
        for i in keep:
            out[:, :, k] |= _section_from_marrow(img, med, body, inner, pixel_mm, lab == i, m, opts)
    return out


def keep_continuous(labels: np.ndarray, ids: Mapping[str, int], volume: Volume, seeds: Mapping[str, np.ndarray],
                    rules: Mapping[str, str] | None = None) -> np.ndarray:
    """The continuity walk of :func:`segment_bones` on labels it made with ``continuity=False``.

    For a caller that wants both (the forearm stacks: the ulna from the walked
    labels, the radius from every forearm bone voxel before it) without
    segmenting twice.

    Parameters
    ----------
    labels : ndarray (I, J, K) of int
        From ``segment_bones(volume, seeds, continuity=False)``; not modified.
    ids : dict of str -> int
        Its bone ids.
    volume : Volume
        The stack it was segmented from (its grid).
    seeds : dict of str -> ndarray (N, 3)
        The same seeds (LPS polylines).
    rules : dict of str -> str, optional
        The same rules; only long (``"cortical"``) bones are walked.

    Returns
    -------
    ndarray
        A copy of ``labels`` with the sections that do not continue their bone removed.
    """
    labels = np.array(labels, copy=True)
    if labels.shape != np.asarray(volume.data).shape:
        raise ValueError(f"labels must have the volume's shape {np.asarray(volume.data).shape}, got {labels.shape}")
    rules = dict(rules or {})
    long_bones = [n for n in seeds if n in ids and rules.get(n, default_rule(n)) == "cortical"]
    crossed = {n: [len(c) > 0 for c in slice_seeds(volume, seeds[n], 0.0)] for n in long_bones}
    pixel_mm = float(0.5 * (volume.spacing[0] + volume.spacing[1]))
    # no gap limit here: a forearm stack's seeds come from a forearm posed by guess, and its sections
    # are registered as a whole afterwards (the limit cost seed 2's 172 deg stack its ulna's fit)
    _keep_continuous(labels, ids, crossed, pixel_mm)
    return labels


def defer_to_shaft_stacks(labels: list[np.ndarray], ids: list[Mapping[str, int]], volumes: list[Volume],
                          seeds: Mapping[str, np.ndarray], rules: Mapping[str, str] | None = None, *,
                          min_share: float = 0.5) -> dict[str, int]:
    """Where two stacks overlap, a long bone's sections are the stack's that holds more of its shaft (in place).

    :func:`segment_bones` judges a long bone's end by its sections' continuity
    from the shaft (:func:`_keep_continuous`), and a stack that holds only the
    end -- the polyline crosses a slice or two at its edge, or none and only
    the seed margin reaches in -- has no shaft to walk from: it keeps whatever
    its seeds found (past the distal radius and ulna, the carpals of the hand
    lying beside the thigh, in the station below the forearm's). Overlapping
    stations image those slices twice, and the one whose slices the polyline
    crosses more often holds the shaft and has judged the end. So a section
    is kept only where that stack labels the bone too: at least ``min_share``
    of its voxels, mapped in-plane to the other stack's nearest voxels, carry
    the bone there. Stacks are settled from the one crossed most, each judged by the
    most crossed stack that images the section's centre; a section no more
    crossed stack images is the only view and stays. The stacks' slices need
    not line up: a voxel counts as labelled there when either of the judging
    stack's two slices around it is.

    Parameters
    ----------
    labels : list of ndarray (I, J, K) of int
        Per stack, from :func:`segment_bones`; modified in place.
    ids : list of dict str -> int
        Per stack, its bone ids.
    volumes : list of Volume
        The stacks (their grids: ``affine`` voxel -> LPS mm, registered to one world).
    seeds : dict of str -> ndarray (N, 3)
        The seed polylines the stacks were segmented with (LPS mm).
    rules : dict of str -> str, optional
        As given to :func:`segment_bones`; only long (``"cortical"``) bones are
        treated.
    min_share : float
        The share of a section's voxels the judging stack must label as the bone.

    Returns
    -------
    dict of str -> int
        Per bone, the number of sections dropped (bones with none left out).

    Raises
    ------
    ValueError
        The three lists differ in length, a label map is not its volume's shape,
        or ``min_share`` is not within (0, 1].
    """
    if not len(labels) == len(ids) == len(volumes):
        raise ValueError(f"labels, ids and volumes must be as many, got {len(labels)}, {len(ids)}, {len(volumes)}")
    for lab, v in zip(labels, volumes):
        if lab.shape != tuple(v.shape[:3]):
            raise ValueError(f"a label map of shape {lab.shape} does not match its volume's {tuple(v.shape[:3])}")
    if not 0 < min_share <= 1:
        raise ValueError(f"min_share must be within (0, 1], got {min_share}")
    rules = dict(rules or {})
    names = {n for m in ids for n in m if n in seeds and rules.get(n, default_rule(n)) == "cortical"}
    dropped: dict[str, int] = {}

    def inside(v: Volume, idx: np.ndarray) -> np.ndarray:
        return np.all((idx >= -0.5) & (idx <= np.asarray(v.shape[:3]) - 0.5), axis=-1)

    for n in sorted(names):
        crossings = [sum(len(c) > 0 for c in slice_seeds(v, seeds[n], 0.0)) for v in volumes]
        order = sorted(range(len(volumes)), key=lambda s: -crossings[s])
        for s in order:
            lab, m, v = labels[s], ids[s], volumes[s]
            judges = [t for t in order if crossings[t] > crossings[s] and n in ids[t]]
            if n not in m or not judges:
                continue
            lid = m[n]
            for k in np.flatnonzero((lab == lid).any(axis=(0, 1))):
                sec = lab[:, :, k] == lid
                ij = np.argwhere(sec)
                xyz = v.index_to_world(np.column_stack([ij, np.full(len(ij), k)]).astype(float))
                centre = xyz.mean(axis=0)
                for t in judges:                      # the most crossed stack imaging the section judges it
                    w = volumes[t]
                    if not inside(w, w.world_to_index(centre)):
                        continue
                    idx = w.world_to_index(xyz)
                    idx = idx[inside(w, idx)]
                    hi = np.asarray(w.shape[:3]) - 1
                    i, j = (np.clip(np.rint(idx[:, a]).astype(int), 0, hi[a]) for a in (0, 1))
                    # the stacks' slices are staggered: the judge's two slices around the section both image
                    # its slab (nearest alone, the last slice of a femoral condyle, 0.4 of a pitch off, took
                    # the thinner end's section for it: 0.48 of the section)
                    k0 = np.clip(np.floor(idx[:, 2] + 1e-6).astype(int), 0, hi[2])   # one slice when aligned
                    k1 = np.clip(np.ceil(idx[:, 2] - 1e-6).astype(int), 0, hi[2])
                    there = (labels[t][i, j, k0] == ids[t][n]) | (labels[t][i, j, k1] == ids[t][n])
                    share = np.count_nonzero(there) / len(ij)
                    if share < min_share:
                        lab[:, :, k][sec] = 0
                        dropped[n] = dropped.get(n, 0) + 1
                    break
    return dropped


def _keep_continuous(labels: np.ndarray, ids: Mapping[str, int], crossed: Mapping[str, list[bool]],
                      pixel_mm: float, *, slice_mm: float | None = None, grow: float = 2.5,
                      min_overlap: float = 0.5, reach_mm: float = 3.0, max_loss: float = 0.5,
                      max_gap_mm: float = MARGIN_GAP_MM) -> None:
    """Keep a long bone's sections only where they continue it, from its shaft to its ends (in place).

    A long bone's sections follow each other from slice to slice; towards its
    ends (hip, shoulder, elbow, wrist, knee, ankle) the seed -- its polyline
    there, or the seed margin beyond it -- may instead find the neighbouring
    bone's marrow (the humeral capitellum above the radial head, the carpals
    past the wrist, the acetabulum above the femoral head, the fibula where the
    tibia's plafond is grey with partial volume; the talus below it is not told
    apart, see below). A section
    continues another when it lies on it or that one on it (at least
    ``min_overlap`` within ``reach_mm``; :func:`_continues`) and is no larger
    than ``grow`` times it (the femoral condyles still widen ~20 % past the
    knee's centre; a neighbour's marrow reached instead is often a whole other
    bone's section, seen 3.5 times the radius's). Walking outwards from the
    shaft -- the longest run of sections each continuing the one before, among
    those holding a slice the polyline crosses -- a section that does not
    continue the last kept one is dropped, and the next compared with the last
    kept. Ending a bone after a gap of more than 7.5 mm was tried: it took the
    talus off the tibia (the talus under the plafond lies on the tibia's last
    section, two 5 mm slices away; phantom seed 1: tibia Dice +0.02), but on
    seed 2 the proximal femoral shaft's marrow was grey for 30 mm, the seed
    took the ischium there, and the limit cut off the whole femoral neck and
    head beyond (femur Dice 0.93 -> 0.82). What a gap does end is the seed
    margin: past a gap of more than ``max_gap_mm`` (empty slices between it
    and the last section kept, ``slice_mm`` apart), a section on a slice the
    polyline does not cross is dropped (the margin catches a bone a little
    longer than its template, which goes on without a gap; across one it found
    the next bone: the carpals 10 mm past the distal radius and ulna, where the
    joint space and its partial volume left two slices without marrow). The
    femoral neck and head past seed 2's grey shaft are crossed by the femur's
    polyline (hip to knee centre) and stay.
    Re-growing a dropped section from the marrow lying on the previous one was
    tried: at the top of the femoral head, where partial volume leaves the
    marrow muscle-grey, that marrow is the acetabulum's. So was the longest
    chain of continuing sections with skips: through the fibula beside the
    plafond it reached the talus. A bone whose polyline crosses no slice of
    this stack (only its end reaches in) has nothing to continue from and is
    left as it is. Nor is a bone the walk would take more than ``max_loss`` of
    (by slices): the walk trims ends, and losing half a bone means the shaft
    was broken (a pronated radius lying against the ulna left half-sections in
    four slices of a forearm stack: the longest unbroken run was its proximal
    third, and the walk dropped the rest).
    """
    from skimage.morphology import disk

    fp = disk(max(1, int(round(reach_mm / pixel_mm))))
    K = labels.shape[2]
    for name, cr in crossed.items():
        lid = ids[name]
        area = (labels == lid).sum(axis=(0, 1))
        cr = np.asarray(cr, bool)
        if not (cr & (area > 0)).any():
            continue
        # the shaft: the longest run of sections each continuing the one before that holds a crossing
        # slice (a median-sized anchor could be a slice where the seed took the neighbour)
        links = [area[k] > 0 and area[k + 1] > 0 and
                 _continues(labels[:, :, k + 1] == lid, labels[:, :, k] == lid, fp, grow, min_overlap)
                 for k in range(K - 1)]
        best, run_start = (0, -1, -1), None
        for k in range(K):
            if area[k] == 0:
                run_start = None
                continue
            if run_start is None or not links[k - 1]:
                run_start = k
            if cr[run_start:k + 1].any() and k - run_start + 1 > best[0]:
                best = (k - run_start + 1, run_start, k)
        _, lo, hi = best
        drop = []
        for step, anchor in ((1, hi), (-1, lo)):
            prev, k_prev = labels[:, :, anchor] == lid, anchor
            for k in range(anchor + step, K if step > 0 else -1, step):
                if area[k] == 0:
                    continue
                if slice_mm is not None and not cr[k] and (abs(k - k_prev) - 1) * slice_mm > max_gap_mm:
                    drop.append(k)
                    continue
                cur = labels[:, :, k] == lid
                # the next section up: the link found for the shaft is the same test (downwards the roles of
                # the two sections swap, and the size limit is one-sided)
                ok = links[k_prev] if k == k_prev + 1 else _continues(cur, prev, fp, grow, min_overlap)
                if ok:
                    prev, k_prev = cur, k
                else:
                    drop.append(k)
        # counted in slices: a big neighbour's sections past a thin bone's end outweigh it in voxels
        if len(drop) > max_loss * np.count_nonzero(area):
            warnings.warn(f"{name}: its sections do not continue each other over more than {max_loss:.0%} "
                          "of it; kept as segmented", stacklevel=3)
            continue
        for k in drop:
            labels[:, :, k][labels[:, :, k] == lid] = 0


def _continues(cur: np.ndarray, prev: np.ndarray, fp: np.ndarray, grow: float, min_overlap: float) -> bool:
    """``cur`` continues ``prev``: not more than ``grow`` times larger, and one lies on the other.

    Either way round: where a bone flares (the distal radius, a few mm aside per slice) the
    smaller previous section lies within the new one more than the new one on it.
    """
    n_cur, n_prev = int(cur.sum()), int(prev.sum())
    if n_cur > grow * n_prev + 4:
        return False
    if n_cur == 0:
        return True
    # the dilations matter only around the two sections: their common box plus the footprint's
    # reach gives the same counts as the whole slice, at a fraction of its size
    both = cur | prev
    ii = np.flatnonzero(both.any(axis=1))
    jj = np.flatnonzero(both.any(axis=0))
    m = max(fp.shape) // 2 + 1
    box = (slice(max(ii[0] - m, 0), ii[-1] + m + 1), slice(max(jj[0] - m, 0), jj[-1] + m + 1))
    cur, prev = cur[box], prev[box]
    if int((cur & ndimage.binary_dilation(prev, fp)).sum()) >= min_overlap * n_cur:
        return True
    return int((prev & ndimage.binary_dilation(cur, fp)).sum()) >= min_overlap * n_prev
