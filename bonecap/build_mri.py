"""The MRI path of ``build-subject`` (Kojima et al.), stage by stage.

1. **Stations** (:mod:`bonecap.stations`): ordered head to feet, each overlap
   registered (small rigid motions), intensities normalised, one LPS frame.
2. **Skin** (:mod:`bonecap.segmentation.skin`): body components per slice.
3. **Seeds**: the template turned into LPS (supine: model X anterior → −y,
   Y up → +z, Z right → −x) and scaled and placed on the body by its head-to-
   sole extent and its centre at hip level — an affine guess, good to ~2 cm,
   which the slice rules refine; the limbs turned toward the limbs' sections,
   the arms moved onto the elbows the marrow shows (:func:`elbow_offsets`).
   ``--seeds`` overrides per bone.
4. **Bone contours** (:mod:`bonecap.segmentation.bones`): the cortical-edge
   rule for long bones, the density-threshold rule for the rest, per slice in
   native pixels.
5. **Meshes** (:mod:`bonecap.meshing`): signed-distance interpolation between
   slices, watertight, smoothed, decimated.
6. **Personal skeleton** (:mod:`bonecap.skeleton.warp`): the template warped
   onto the extracted bones (affine + Gaussian RBF); bones the MRI missed come
   from their neighbours' warps; the skull from the head's skin; the
   vertebrae between the pelvis and the skull put on the discs the stations
   show along the column (:mod:`bonecap.segmentation.spine`); then, when the
   stations show marker capsules, the density rule's bones but the scapulae
   moved in plane by how far their refined sections' centroids moved
   (:func:`density_bone_shifts`; their joint centres stay; the ribs and the
   sternum follow their vertebrae, :func:`thorax_follows`).
7. **Markers**: each marker on the personal skin over its landmark; an
   MRI-visible capsule found near it (centre one marker-minus-capsule radius
   out along the skin normal) replaces the guess; a hand the scan did not
   measure is turned about the wrist into its skin (:func:`pose_inside_skin`)
   and sized onto its capsules ("hands from markers",
   :func:`pose_from_capsules`); with a static trial the
   skeleton is posed to it (a shank without capsules keeps the MRI's knee
   rotation, the foot its roll from the shank) and the markers without a
   capsule are bound at their measured positions. A capsule marker keeps its
   MRI binding unless the static refutes its segment's (a hand or foot the
   scan did not measure, carried at the template's angle): that segment is
   bound from the static.
8. **Forearm model** from three forearm stacks (``--forearm-poses``).

Everything is in LPS millimetres; the subject's world frame is ``lps``.
"""

from __future__ import annotations

import os
import pickle
import time
import warnings
from pathlib import Path
from typing import Any, Callable

import numpy as np

from bonecap.errors import DataError, InputError
from bonecap.io import load_yaml
from bonecap.model import Bone, Mesh, Skeleton, Volume
from bonecap.motion.paper import minimal_rotation
from bonecap.parallel import Pending, default_workers, fork_map, fork_or_here, fork_start
from bonecap.skeleton.kinematics import subtree as _subtree

__all__ = ["MODEL_TO_LPS", "capsules_to_markers", "forearm_capsule_markers", "load_stations", "template_to_body",
           "bone_seeds", "shaft_line", "load_seeds", "build_from_mri", "warp_targets", "SEGMENTED_BONES", "pose_from_capsules", "pose_inside_skin",
           "reframe_subject", "elbow_offsets", "personal_label_meshes", "personal_labels", "label_table"]

#: Template world (X anterior, Y up, Z right) to LPS for a supine subject.
MODEL_TO_LPS = np.array([[0.0, 0.0, -1.0, 0.0],
                         [-1.0, 0.0, 0.0, 0.0],
                         [0.0, 1.0, 0.0, 0.0],
                         [0.0, 0.0, 0.0, 1.0]])

_LONG = ("femur", "tibia", "fibula", "humerus", "radius", "ulna")
_VERTEBRAE = tuple([f"c{i}" for i in range(1, 8)] + [f"t{i}" for i in range(1, 13)] + [f"l{i}" for i in range(1, 6)])
#: Bones the slice rules look for; the rest come from the warp (ribs are too
#: thin for 5 mm slices, hands and feet too small at whole-body resolution).
SEGMENTED_BONES = tuple([f"{b}_{s}" for b in _LONG for s in "rl"] + ["hip_r", "hip_l", "sacrum"]
                        + [f"{b}_{s}" for b in ("scapula", "patella") for s in "rl"] + list(_VERTEBRAE))


def load_stations(paths: list[str | os.PathLike]) -> list[Volume]:
    """Read every MRI path (DICOM folder, NIfTI, NRRD) into volumes."""
    from bonecap.io.imaging import read_volumes

    vols: list[Volume] = []
    for p in paths:
        found = read_volumes(p)
        if not found:
            raise InputError("no image series found", p)
        vols.extend(found)
    return vols


def template_to_body(template: Skeleton, body_points_top: float, body_points_bottom: float,
                     hip_level_centre: np.ndarray) -> np.ndarray:
    """An affine guess of the template (model frame) in the subject's LPS frame.

    Parameters
    ----------
    template : Skeleton
        In its model frame, feet on Y = 0.
    body_points_top, body_points_bottom : float
        LPS z of the vertex and the soles (mm).
    hip_level_centre : ndarray (3,)
        LPS centre of the body's cross-section at the template's hip height
        (after scaling): the hips are set there in x and y.

    Returns
    -------
    ndarray (4, 4)
        model → LPS, a rotation (supine) times a uniform scale plus a shift.
    """
    top = max(float(np.max(b.mesh.transformed(b.bone_to_world).vertices[:, 1]))
              for b in template.bones.values() if b.mesh is not None)
    bottom = min(float(np.min(b.mesh.transformed(b.bone_to_world).vertices[:, 1]))
                 for b in template.bones.values() if b.mesh is not None)
    # skin adds a few mm over the vertex and under the heel
    s = (body_points_top - body_points_bottom) / (top - bottom + 12.0)
    A = MODEL_TO_LPS.copy()
    A[:3, :3] *= s
    hips = [template.bones[n].landmark_in_world("hip") for n in ("hip_r", "hip_l")
            if n in template.bones and "hip" in template.bones[n].joint_centres]
    h = np.mean(hips, axis=0) if hips else np.array([0.0, 0.5 * (top + bottom), 0.0])
    hz = A[:3, :3] @ h
    A[:3, 3] = [hip_level_centre[0] - hz[0], hip_level_centre[1] - hz[1], body_points_bottom + 6.0 * s - s * bottom]
    return A


def _body_extent(vols: list[Volume], bodies: list[np.ndarray]) -> tuple[float, float, Callable[[float], np.ndarray]]:
    """Top and bottom LPS z of the body and a function z -> body centre (x, y) at that level."""
    zs, centres = [], []
    for v, m in zip(vols, bodies):
        k_any = np.flatnonzero(m.any(axis=(0, 1)))
        for k in k_any:
            ii, jj = np.nonzero(m[:, :, k])
            p = v.index_to_world(np.column_stack([ii, jj, np.full(len(ii), k)]).astype(float))
            zs.append(float(p[:, 2].mean()))
            centres.append(p.mean(axis=0))
    if not zs:
        raise DataError("no body found in any station (is this an MRI of a person?)")
    zs = np.array(zs)
    centres = np.array(centres)
    order = np.argsort(zs)
    zs, centres = zs[order], centres[order]

    def at(z: float) -> np.ndarray:
        i = int(np.argmin(np.abs(zs - z)))
        return centres[i]

    return float(zs.max()), float(zs.min()), at


def _covers_whole_body(vols: list[Volume], bodies: list[np.ndarray]) -> bool:
    """True when the head and the feet are both imaged.

    The extreme slices of the stack (top of the first station, bottom of the
    last) must hold little body: less than 15 % of the median body area per
    slice (a vertex or a heel grazing the slice is still "imaged").
    """
    areas = [b.sum(axis=(0, 1)) * float(np.prod(v.spacing[:2])) for v, b in zip(vols, bodies)]
    median = float(np.median(np.concatenate(areas)))

    def extreme(v: Volume, area: np.ndarray, top: bool) -> float:
        z = [v.index_to_world(np.array([[0, 0, k]], float))[0, 2] for k in (0, v.shape[2] - 1)]
        k = (0 if z[0] > z[1] else v.shape[2] - 1) if top else (0 if z[0] < z[1] else v.shape[2] - 1)
        return float(area[k])

    return extreme(vols[0], areas[0], True) < 0.15 * median and extreme(vols[-1], areas[-1], False) < 0.15 * median


def _rotate_about(skeleton: Skeleton, bones: list[str], centre: np.ndarray, R: np.ndarray) -> None:
    """Turn ``bones`` (in place) rigidly about ``centre`` by ``R`` (world frame)."""
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = centre - R @ centre
    for n in bones:
        skeleton.bones[n].bone_to_world = M @ skeleton.bones[n].bone_to_world


def _body_components(body: np.ndarray, v: Volume, k: int, min_area_mm2: float):
    """A slice's body components of at least ``min_area_mm2``: ``(labels, their ids, areas mm^2, LPS
    centroids)`` (ids ascending), or None without one. Areas and centroids by counting (ndimage's
    per-label statistics took ~2 s a body)."""
    from scipy import ndimage

    lab, n = ndimage.label(body)
    if n == 0:
        return None
    flat = lab.ravel()
    count = np.bincount(flat, minlength=n + 1)[1:]
    areas = count * float(np.prod(v.spacing[:2]))
    keep = areas >= min_area_mm2
    if not keep.any():
        return None
    ii, jj = (a.ravel() for a in np.indices(body.shape, dtype=float))
    cents = np.column_stack([np.bincount(flat, ii, n + 1)[1:], np.bincount(flat, jj, n + 1)[1:]])
    cents /= np.maximum(count, 1)[:, None]
    world = v.index_to_world(np.column_stack([cents[keep], np.full(int(keep.sum()), k)]).astype(float))
    return lab, np.flatnonzero(keep) + 1, areas[keep], world


class _LimbSections:
    """Centroids of the body's separate components per slice (LPS mm): the limbs.

    At the level of a joint, the limb it belongs to is a connected component
    of the slice's body mask apart from the trunk (arms at chest level, legs
    below the crotch); its centroid is within a centimetre or two of the
    joint in the transverse plane, which is all a seed needs.
    """

    def __init__(self, vols: list[Volume], bodies: list[np.ndarray], min_area_mm2: float = 400.0):
        self.z, self.parts = [], []
        for v, m in zip(vols, bodies):
            for k in range(m.shape[2]):
                comps = _body_components(m[:, :, k], v, k, min_area_mm2)
                if comps is None:
                    continue
                _, _, areas, world = comps
                self.z.append(float(world[:, 2].mean()))
                self.parts.append((world, areas))
        self.z = np.asarray(self.z)

    def limb_centre(self, z: float, side: str, kind: str, window_mm: float = 12.0) -> np.ndarray | None:
        """Centre of the arm or leg on ``side`` ('r' = -x in LPS) near height ``z``.

        Components are sorted left to right: an arm is the outermost component
        of its side when the slice holds three or more; a leg is the
        innermost non-trunk component of its side below the crotch.
        """
        pts = []
        for i in np.flatnonzero(np.abs(self.z - z) <= window_mm):
            world, areas = self.parts[i]
            order = np.argsort(world[:, 0])
            w = world[order]
            if kind == "arm":
                if len(w) < 3:
                    continue
                pts.append(w[0] if side == "r" else w[-1])
            else:
                # legs: the two largest components when no trunk remains
                big = np.argsort(areas)[::-1][:2]
                if len(big) < 2:
                    continue
                legs = world[big]
                legs = legs[np.argsort(legs[:, 0])]
                pts.append(legs[0] if side == "r" else legs[1])
        return np.mean(pts, axis=0) if pts else None


#: The limbs :func:`repose_limbs` turns: (long bone, its distal joint, the limb's kind in :class:`_LimbSections`,
#: what is aimed at the limb's section: ``"joint"`` the distal joint centre, ``"bones"`` the centroid of the
#: bone's subtree's section at that joint's level). The arms aim their bones: the ulna's distal radioulnar
#: joint lies at the ulnar border of the wrist, not amid its section, and aimed there it turned every
#: phantom's forearm 4-6 deg too far out (0.2-0.9 deg aiming the bones; wrists placed 18-29 -> 3-20 mm
#: from the truth, seeds 0-4). The legs aim their joints: aiming the bones placed the knees 4-14 mm worse.
LIMB_CHAINS = (("femur", "knee", "leg", "joint"), ("tibia", "ankle", "leg", "joint"),
               ("humerus", "elbow", "arm", "bones"), ("ulna", "distal_radioulnar", "arm", "bones"))


def repose_limbs(skeleton: Skeleton, sections: _LimbSections, chains=LIMB_CHAINS) -> dict[str, float]:
    """Turn the template's limbs (in place, LPS) toward the limbs seen in the MRI.

    The MRI pose is not the template's (arms abducted or along the body,
    legs apart or together): a global affine leaves the elbows and wrists
    centimetres off. Each long bone is turned about its proximal joint so that
    its distal joint (a leg's) or its bones' section there (an arm's; see
    :data:`LIMB_CHAINS`) points at the centre of the limb's cross-section at
    that joint's height (knee, ankle, elbow, wrist), parent before child.

    Returns
    -------
    dict
        The turn applied per bone (degrees).
    """
    turned = {}
    for side in "rl":
        for base, distal, kind, aim in chains:
            name = f"{base}_{side}"
            b = skeleton.bones.get(name)
            if b is None or distal not in b.joint_centres:
                continue
            prox = [j for j in b.joint_centres if j != distal]
            if not prox:
                continue
            p = b.landmark_in_world(prox[0])
            d = b.landmark_in_world(distal)
            target = sections.limb_centre(float(d[2]), side, kind)
            if target is None:
                continue
            if aim == "bones":
                d = _section_centroid(skeleton, _subtree(skeleton, name), float(d[2]), d)
            # keep the template's length: turn only, toward the target's direction
            R = minimal_rotation(d - p, target - p)
            ang = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))
            if ang > 60:  # a mismatched component (a hand on the thigh): leave the limb alone
                continue
            _rotate_about(skeleton, _subtree(skeleton, name), p, R)
            turned[name] = round(ang, 1)
    return turned


def _section_centroid(skeleton: Skeleton, bones: list[str], z: float, fallback: np.ndarray,
                      half_mm: float = 10.0) -> np.ndarray:
    """The centroid of ``bones``' mesh vertices (world) within ``half_mm`` of level ``z`` (LPS); ``fallback``
    when fewer than 8 lie there. (The template's meshes are decimated to about even vertex spacing, so the
    vertices' mean stands for the section's.)"""
    pts = []
    for n in bones:
        b = skeleton.bones[n]
        if b.mesh is None:
            continue
        v = skeleton.world_mesh(n).vertices
        pts.append(v[np.abs(v[:, 2] - z) <= half_mm])
    pts = np.concatenate(pts) if pts else np.zeros((0, 3))
    return pts.mean(axis=0) if len(pts) >= 8 else fallback


def _arm_sections(body: np.ndarray, v: Volume, k: int, min_area_mm2: float, sides: str = "rl"
                  ) -> dict[str, tuple[np.ndarray, float]]:
    """The arms' components of a slice's body mask (as :meth:`_LimbSections.limb_centre` picks them: the
    outermost of three or more components of ``min_area_mm2`` on each side), with their centroids' LPS z."""
    comps = _body_components(body, v, k, min_area_mm2)
    if comps is None or len(comps[1]) < 3:
        return {}
    lab, ids, _, world = comps
    out = {}
    for side in sides:
        i = int(np.argmin(world[:, 0]) if side == "r" else np.argmax(world[:, 0]))
        out[side] = (lab == ids[i], float(world[i, 2]))
    return out


def _marrow_count(image: np.ndarray, section: np.ndarray, pixel_mm: float, sigma_px: float,
                  min_region_mm2: float, max_region_mm2: float) -> int:
    """How many marrow regions of ``min_region_mm2`` to ``max_region_mm2`` a limb's section holds: the
    slice rules' candidates (:func:`bonecap.segmentation.cortical.marrow_candidates`, marrow cut loose from
    the fat by :func:`~bonecap.segmentation.cortical.detach_from_skin`), in the section's box only."""
    from scipy import ndimage

    from bonecap.segmentation import cortical

    pad = int(np.ceil(4 * sigma_px)) + 2
    ii, jj = np.nonzero(section)
    box = (slice(max(ii.min() - pad, 0), ii.max() + pad + 1), slice(max(jj.min() - pad, 0), jj.max() + pad + 1))
    sec = section[box]
    med = ndimage.gaussian_filter(np.asarray(image[box], np.float32), sigma_px, mode="nearest")
    # the interior without the outer 3 mm, where fat reaches the skin (as segment_bones)
    inner = ndimage.binary_erosion(sec, iterations=max(1, int(round(3.0 / pixel_mm))), border_value=1)
    muscle = cortical.muscle_level(med, inner if inner.any() else sec)
    if not (np.isfinite(muscle) and muscle > 0):
        return 0
    lab, n = cortical.detach_from_skin(cortical.marrow_candidates(med, sec, muscle, pixel_mm), sec, inner, pixel_mm)
    area = np.bincount(lab.ravel(), minlength=n + 1)[1:] * pixel_mm ** 2
    return int(((area >= min_region_mm2) & (area <= max_region_mm2)).sum())


def elbow_offsets(skeleton: Skeleton, vols: list[Volume], bodies: list[np.ndarray], *, sides: str = "rl",
                  search_mm: float = 100.0, window_mm: float = 60.0, min_step: float = 0.6,
                  min_region_mm2: float = 20.0, max_region_mm2: float = 1500.0, min_area_mm2: float = 400.0,
                  sigma_px: float = 0.7) -> dict[str, float]:
    """How far (LPS z, mm) each elbow lies from where the placed template has it, from the marrow.

    Going down an arm at the side of a supine body, each section holds one
    marrow -- the humerus's -- until the olecranon's and the radial head's
    appear beside it, and two or more from there to the wrist. The level of
    that step is the top of the forearm's bones: it is found where the
    fraction of sections with two marrow regions (of ``min_region_mm2``,
    the slice rules' candidates) within ``window_mm`` below a level most
    exceeds that within ``window_mm`` above it, within ``search_mm`` of the
    placed template's forearm top (the highest point of its ulna and radius,
    in ``skeleton``'s LPS world). The top lies between the first slice with
    two regions and the one above it: the midpoint is taken.

    Why: the template is placed by the body's head-to-sole length, and
    people's proportions are not the template's. A phantom with a long neck
    and short legs had its shoulders and elbows placed 38-44 mm too high,
    beyond the elbow split's reach (:func:`bonecap.segmentation.bones.segment_bones`):
    its humeri came out 69 mm short and its radii took the distal humerus.
    The step is seen in every arm section that is its own component of the
    body (the arm apart from the trunk).

    Parameters
    ----------
    skeleton : Skeleton
        The placed template (world ``lps``).
    vols, bodies : list
        The registered stations and their body masks.
    sides : str
        ``"r"`` (−x in LPS), ``"l"``.
    search_mm, window_mm : float
    min_step : float
        The step's least score (0-1: 1 is every section above with one region, every one below with
        two); a side below it, or without an arm apart from the trunk, is left out.
    min_region_mm2, max_region_mm2 : float
        A marrow region's least and largest area: the distal humerus's marrow, the arm's widest, is
        ~1 000 mm^2; the thick subcutaneous fat of an arm, where ``detach_from_skin`` keeps its deep part,
        came in 2 600-3 000 mm^2 pieces (a phantom's upper arm, in every third section).
    min_area_mm2, sigma_px : float
        An arm section's least area; the in-plane noise removal (as ``segment_bones``).

    Returns
    -------
    dict side -> float
        The step's level minus the template's forearm top (negative: the elbow lies lower).

    References
    ----------
    Kojima et al. (the cortical-edge rule's bright marrow in its dark cortex).
    """
    out: dict[str, float] = {}
    z_top, rows = {}, {}
    for side in sides:
        tops = [skeleton.world_mesh(n).vertices[:, 2].max() for n in (f"ulna_{side}", f"radius_{side}")
                if n in skeleton.bones and skeleton.bones[n].mesh is not None]
        if tops:
            z_top[side], rows[side] = float(max(tops)), []
    if not z_top:
        return out
    reach = search_mm + window_mm
    for v, m in zip(vols, bodies):
        zk = v.index_to_world(np.column_stack([np.full(m.shape[2], 0.5 * (m.shape[0] - 1)),
                                               np.full(m.shape[2], 0.5 * (m.shape[1] - 1)),
                                               np.arange(m.shape[2])]).astype(float))[:, 2]
        px = float(0.5 * (v.spacing[0] + v.spacing[1]))
        for k in range(m.shape[2]):
            near = "".join(sd for sd, zt in z_top.items() if abs(zk[k] - zt) <= reach + 10.0)
            if not near:
                continue
            for side, (section, z) in _arm_sections(m[:, :, k], v, k, min_area_mm2, near).items():
                if abs(z - z_top[side]) <= reach:
                    rows[side].append((z, _marrow_count(v.data[:, :, k], section, px, sigma_px, min_region_mm2,
                                                        max_region_mm2) >= 2))
    for side, zt in z_top.items():
        got = sorted(rows[side])
        if len(got) < 6:
            continue
        z = np.array([r[0] for r in got])
        # a section's count by the majority of it and its neighbours: a fat lobule or a vessel bright in one
        # section is no second marrow; a marrow missed in one is not an end
        two = np.array([r[1] for r in got], float)
        two[1:-1] = np.median(np.column_stack([two[:-2], two[1:-1], two[2:]]), axis=1)
        best = None
        for i in np.flatnonzero(np.abs(z - zt) <= search_mm):
            above = two[(z > z[i]) & (z <= z[i] + window_mm)]
            below = two[(z <= z[i]) & (z > z[i] - window_mm)]
            if len(above) < 3 or len(below) < 3:
                continue
            score = float(below.mean() - above.mean())
            if best is None or score > best[0] + 1e-9:
                best = (score, i)
        if best is None or best[0] < min_step or best[1] + 1 >= len(z):
            continue
        i = best[1]
        out[side] = float(0.5 * (z[i] + z[i + 1]) - zt)
    return out


def _girdle_root(skeleton: Skeleton, side: str) -> str | None:
    """The topmost bone of a side's arm below the one that meets the trunk: the scapula (the clavicle stays
    on the sternum); the humerus in a model without a shoulder girdle."""
    name = f"humerus_{side}"
    if name not in skeleton.bones:
        return None
    while (p := skeleton.bones[name].parent) is not None and p.endswith(f"_{side}") \
            and (skeleton.bones[p].parent or "").endswith(f"_{side}"):
        name = p
    return name


def shaft_line(vertices: np.ndarray, start: np.ndarray, end: np.ndarray,
               fractions=(0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9), min_vertices: int = 12) -> list[np.ndarray]:
    """A long bone's seed line through its sections: joint centre, section centres, joint centre.

    The line between a long bone's joint centres is its mechanical axis, not
    its shaft: the femur's runs from the head, medial of the shaft by the
    neck's offset, so below the trochanters the marrow lies 28-42 mm from it
    (a phantom's femur, 25 mm searched: 25 mm of its proximal shaft lost), the
    radius's and fibula's 13-17 mm. The template's surface knows where the
    shaft is: at each fraction along the axis, the centroid of the mesh
    vertices in a slab across it (half-width 2 % of the length, at least
    3 mm), moved onto that slab's plane. A slab with fewer than
    ``min_vertices`` vertices adds no point.

    Parameters
    ----------
    vertices : ndarray (V, 3)
        The bone's surface, the frame of ``start`` and ``end`` (mm).
    start, end : ndarray (3,)
        The proximal joint centre and the distal end of the seed line.
    fractions : sequence of float
        Where along the axis, 0 at ``start`` and 1 at ``end``.
    min_vertices : int

    Returns
    -------
    list of ndarray (3,)
        ``start``, the section centres in order, ``end``.
    """
    V = np.asarray(vertices, float)
    a, b = np.asarray(start, float), np.asarray(end, float)
    length = float(np.linalg.norm(b - a))
    if length < 1e-6 or len(V) == 0:
        return [a, b]
    u = (b - a) / length
    s = (V - a) @ u
    half = max(0.02 * length, 3.0)
    out = [a]
    for f in fractions:
        sel = np.abs(s - f * length) <= half
        if sel.sum() < min_vertices:
            continue
        c = V[sel].mean(axis=0)
        out.append(c + (f * length - (c - a) @ u) * u)
    out.append(b)
    return out


#: How far past its search a long bone whose line ends short of its joint may be followed
#: (:func:`bone_seeds`' ``followed``), as a fraction of its joint-to-joint length: twice the 5-8 %
#: by which a segment's length varies beyond stature, the template's placement error on top.
FOLLOW_FRACTION = 0.15

#: The long bones whose distal ends are followed past their search (:func:`bone_seeds`' ``followed``):
#: the distal tibia widens to its plafond and the talus's dome under it is smaller, which stops the
#: track (:func:`bonecap.segmentation.bones._follow_distal_end`), and the fibula's malleolus ends beside
#: the talus. Not the radius and ulna: the carpals past them are as large as their distal sections,
#: and a phantom's ulna, followed, took twice the carpal voxels it had taken before (seed 1: 110 -> 222).
FOLLOWED_ENDS = ("tibia", "fibula")

#: Those of :data:`FOLLOWED_ENDS` whose distal end is a free tip, not a joint: the fibula's lateral
#: malleolus narrows to its point beside the talus, where the search takes the talus's marrow with the
#: tip's sections and the continuity walk drops them all (a phantom's fibula ended 10 mm short of its
#: point, its malleolus landmark 5 mm up the shaft); its tip is tracked after the walk
#: (:func:`bonecap.segmentation.bones._extend_tip`). The tibia's end is its plafond over the talus.
FOLLOWED_TIPS = ("fibula",)

#: The long bones whose proximal end is a head in a density-rule bone's socket, followed past the
#: search into it (:func:`bone_seeds`' ``heads``; :func:`bonecap.segmentation.bones._follow_head`): the
#: femoral head in the acetabulum, the humeral head on the glenoid.
FOLLOWED_HEADS = ("femur", "humerus")

#: How far (mm) a bone's rigid fit may move it from where the template was placed before its target is
#: taken for another bone's (``warp_skeleton``'s ``max_shift_mm``; bones carried onto joints, twice that).
#: The placement from the body's extent is that far off: the demo subject's (seed 0) femora sat 35-41 mm
#: too high. Once the seed margin's gap limit dropped a false section above its right femoral head, the
#: right femur's correct fit (40.7 mm) was refused at 40 mm, and its pelvis and spine were carried from
#: it (cervical vertebrae 20-40 mm off).
PLACED_MAX_SHIFT_MM = 60.0

#: The long bones whose distal end is a process without marrow, the ulnar styloid (the template's marrow
#: ends 6 mm short of its tip): the cortical rule, which starts from marrow, ends the bone where the marrow
#: does (on three phantoms every ulna extraction ended 6-10 mm short of its styloid, once the search no
#: longer ran on into the carpals), so that end is always a cut for the warp (:func:`unseen_ends`), and the
#: template's marrow is stretched to reach the extraction there
#: (:func:`bonecap.skeleton.warp.warp_skeleton`'s ``cover_marrow``). Not the radius: the template's marrow
#: reaches within 2 mm of its styloid, so the cover never applies, and with the end cut alone the demo
#: subject's radii had every RBF width fold and stayed 9-10 mm short (their tips within 1 mm without the
#: cut); its warp is checked against its ulna's length instead, and cut when short (:data:`LENGTH_FROM`).
MARROWLESS_ENDS = ("ulna",)

#: The long bones whose warp is checked at its distal end against the length a measured neighbour gives
#: them in the template's proportion, and warped again with that end cut to that length when it falls
#: short (:func:`bonecap.skeleton.warp.warp_skeleton`'s ``length_from``, :func:`distal_cuts`): the radius
#: from its ulna. The radius's extraction ends 9-14 mm short of its styloid (where the cortical rule stops
#: resolving its marrow at 1.8 mm pixels and 5 mm slices), and its tip was bistable in the warp: within
#: 2 mm of the truth on 8 of 10 phantom radii, 7.2-7.3 mm short on two (the template's tip paired with the
#: extraction's end cap). A cut alone (the radius as a marrowless end) left the affine's axial scale, set
#: by that short end, to place the tip: 9.5-10.9 mm short on four radii. The ulna's tip, its marrow
#: stretched to its extraction's end, lands within 1.5 mm on all ten; the radius's length from its affine
#: is less sure (4.9 mm short to 4.2 mm long of the direct warp where that was right: the phantoms' radius
#: and ulna vary on their own), so it is the fallback past a margin
#: (:data:`bonecap.skeleton.warp.LENGTH_FROM_MARGIN_MM`), not the rule.
LENGTH_FROM = {"radius": "ulna"}

#: The long bones whose extraction, end to end, is a lower bound on their length: the warp stretches a
#: template that falls short of it along the axis (:func:`bonecap.skeleton.warp.cover_extent`). The
#: fibula's ends lie free of other long bones' lines; a femoral head's search runs on into the pelvis, so
#: its extent is no bound. A radius's or ulna's could run on into the carpals (9-28 mm past the bone on
#: phantoms, before :func:`bonecap.segmentation.bones.defer_to_shaft_stacks` and the seed margin's gap
#: limit); now their extractions end short of their styloids: the ulna's marrow covers its extraction
#: (:data:`MARROWLESS_ENDS`), the radius's length is its ulna's in the template's proportion
#: (:data:`LENGTH_FROM`).
COVERED_EXTENTS = ("fibula",)


def bone_seeds(template: Skeleton, model_to_lps: np.ndarray, bones: tuple[str, ...] = SEGMENTED_BONES,
               margin_mm: float = 20.0, followed: dict[str, float] | None = None,
               heads: dict[str, float] | None = None) -> dict[str, np.ndarray]:
    """Seed polylines (LPS mm) of the bones to segment, from the aligned template.

    A long bone's seed runs from its proximal to its distal joint centre
    through the centres of its shaft's sections (:func:`shaft_line`: its
    marrow lies along it); another bone's is its joint centres, its mesh
    centroid and the centres of its sections in slabs of
    :data:`DENSITY_SEED_SLAB_MM` along z (a hip bone's or scapula's joints
    and centroid left 55-106 mm of it beyond the search's margin), ordered
    along z.

    Where the bone across a long bone's distal joint is not among ``bones``
    (too small to segment at whole-body resolution) and reaches past the
    joint centre back along the long bone -- the talus, whose dome sits
    14.5 mm deep in the ankle's mortise -- ``segment_bones``' search, which
    goes ``margin_mm`` past the line's ends, must stop where that bone
    begins: the line ends ``margin_mm`` + that reach short of the joint
    centre. Ending at the ankle's centre, the tibia's line searched 20 mm
    into the talus and took its sections (a phantom's ankle centres then
    19-21 mm too low, its static feet 20-22 deg off); what the search now
    leaves out (the malleoli) comes from the warp. The carpals begin 4 mm
    beyond the wrist's centre: the radius's line is left as it is (ended
    16 mm short, one phantom's radius lost its styloid's end and came out
    27.6 mm off in the trials, 11.0 before).

    A bone that reaches farther than ``margin_mm`` past its distal joint
    centre, where no other long bone's line begins -- the fibula, whose
    lateral malleolus ends 40 mm past the distal tibiofibular joint -- has
    its line carried on along it to half the margin short of its end (its
    last 20 mm were not searched: a phantom's malleoli were lost).

    The lines end where the *template's* bones do; a subject whose bone is
    longer (segment lengths vary by 5-8 % beyond stature) loses its end to the
    search: a phantom's distal tibiae, 40 mm of metaphysis up to the plafond,
    and its fibulae's malleoli. ``followed``, when given, receives the bones of
    :data:`FOLLOWED_ENDS` with how far (mm, :data:`FOLLOW_FRACTION` of the
    bone's length) ``segment_bones`` may follow them past the search, slice
    by slice, while they continue and until they reach their joint
    (:func:`bonecap.segmentation.bones._follow_distal_end`). ``heads`` likewise receives the
    bones of :data:`FOLLOWED_HEADS`, whose proximal heads are followed into their sockets
    (:func:`bonecap.segmentation.bones._follow_head`).
    """
    from bonecap.skeleton.kinematics import joint_groups

    group_of = {e: g for g in joint_groups(template) for e in g}
    out = {}
    for name in bones:
        b = template.bones.get(name)
        if b is None:
            continue
        pts = [b.landmark_in_world(j) for j in b.joint_centres]
        # a density bone's mesh in world: its centroid, and below its sections' centres
        Vd = b.mesh.transformed(b.bone_to_world).vertices if b.mesh is not None and not name.startswith(_LONG) \
            else None
        if Vd is not None:
            pts.append(Vd.mean(axis=0))
        if name.startswith(_LONG) and len(pts) >= 2:
            V = b.mesh.transformed(b.bone_to_world).vertices if b.mesh is not None else None
            # the shaft's two ends only: proximal = first, distal = farthest from it
            d = [np.linalg.norm(p - pts[0]) for p in pts]
            far = int(np.argmax(d))
            pts = [pts[0], pts[far]]
            # the bones across that joint (the warp's joint groups: one name at one place, side suffixes aside)
            partners = [n for n, _ in group_of[(name, list(b.joint_centres)[far])] if n != name]
            meshes = [template.bones[n] for n in partners if template.bones[n].mesh is not None]
            if meshes and not any(n in bones for n in partners):
                length = float(np.linalg.norm(pts[1] - pts[0]))
                back = (pts[0] - pts[1]) / max(length, 1e-9)
                reach = max(float(((o.mesh.transformed(o.bone_to_world).vertices - pts[1]) @ back).max())
                            for o in meshes)
                if reach > 0.0:
                    pts[1] = pts[1] + float(min(margin_mm + reach, 0.25 * length)) * back
            elif V is not None and not any(
                    n in bones and n.startswith(_LONG) and list(template.bones[n].joint_centres)[0] == j
                    for n, j in group_of[(name, list(b.joint_centres)[far])] if n != name):
                # a bone that goes on far past its distal joint centre, where no other long bone's line
                # begins (the fibula's lateral malleolus, 40 mm past the distal tibiofibular joint): its line
                # goes on along it, so that the search reaches half the margin past its end as it does
                # past the radius's or the humerus's (it stopped 20 mm short: a phantom's malleoli lost)
                length = float(np.linalg.norm(pts[1] - pts[0]))
                u = (pts[1] - pts[0]) / max(length, 1e-9)
                own = float(((V - pts[1]) @ u).max())
                if own > margin_mm:
                    pts[1] = pts[1] + (own - 0.5 * margin_mm) * u
            span = float(np.linalg.norm(b.landmark_in_world(list(b.joint_centres)[far])
                                        - b.landmark_in_world(list(b.joint_centres)[0])))
            if followed is not None and name[:-2] in FOLLOWED_ENDS:
                followed[name] = FOLLOW_FRACTION * span
            if heads is not None and name[:-2] in FOLLOWED_HEADS:
                heads[name] = FOLLOW_FRACTION * span
            if V is not None:
                pts = shaft_line(V, pts[0], pts[1])
        if not pts:
            continue
        p = np.asarray(pts) @ model_to_lps[:3, :3].T + model_to_lps[:3, 3]
        if Vd is not None:
            # the centres of its sections, slab by slab: joint centres and one centroid reach only part of
            # a tall plate (an iliac wing, a scapula), and slices farther than the margin are not searched
            W = Vd @ model_to_lps[:3, :3].T + model_to_lps[:3, 3]
            z = W[:, 2]
            slabs = [np.abs(z - z0) <= 0.5 * DENSITY_SEED_SLAB_MM
                     for z0 in np.arange(z.min() + 0.5 * DENSITY_SEED_SLAB_MM, z.max(), DENSITY_SEED_SLAB_MM)]
            p = np.vstack([p] + [W[near].mean(axis=0)[None] for near in slabs if near.sum() >= 10])
        # a long bone's stays proximal -> distal (segment_bones: past the proximal end lies its head)
        out[name] = p if name.startswith(_LONG) else p[np.argsort(-p[:, 2])]
    return out


#: :func:`bone_seeds`: a density bone's seed runs through its sections' centres in slabs this thick (mm).
DENSITY_SEED_SLAB_MM = 10.0


def load_label_map(path: str | os.PathLike) -> tuple[list[tuple[np.ndarray, np.ndarray]], dict[str, int]]:
    """A user's bone label map (3D Slicer, ITK-SNAP, TotalSegmentator...) and its label -> bone table.

    The table is looked for beside the map: ``<stem>.yaml`` / ``<stem>.json``,
    then ``labels.yaml`` / ``labels.json`` in the same folder or the one
    above (a phantom's ``truth/labels.json``). It maps bone names (the
    template's) to label values, either at the top level or under ``ids``.

    Returns
    -------
    pieces : list of (labels, affine)
        One piece, voxel -> LPS.
    ids : dict of str -> int
    """
    from bonecap.io.imaging import read_volumes

    path = Path(path)
    if not path.exists():
        raise InputError("no such label map", path)
    vols = read_volumes(path)
    if len(vols) != 1:
        raise InputError(f"a label map must be one volume, found {len(vols)}", path)
    v = vols[0]
    data = np.asarray(v.data)
    if not np.allclose(data, np.round(data)):
        raise DataError("not a label map: it holds non-integer values", path)
    table, table_path = label_table(path)
    present = set(np.unique(data.astype(np.int64)).tolist())
    ids = {str(b): int(i) for b, i in table.items() if int(i) in present and int(i) > 0}
    if not ids:
        raise DataError(f"none of the table's labels occurs in the map ({table_path.name})", path)
    return [(data.astype(np.int32), v.affine)], ids


def label_table(path: str | os.PathLike) -> tuple[dict[str, int], Path]:
    """The label -> bone table beside a label map (see :func:`load_label_map`), and where it was found.

    Returns
    -------
    table : dict of str -> int
        Every entry of the table, whether or not the map holds its label.
    table_path : Path
    """
    import json

    import yaml

    path = Path(path)
    stem = path.name.split(".")[0]
    candidates = [path.with_name(stem + ext) for ext in (".yaml", ".yml", ".json")]
    candidates += [d / f"labels{ext}" for d in (path.parent, path.parent.parent) for ext in (".yaml", ".json")]
    table_path = next((c for c in candidates if c.is_file()), None)
    if table_path is None:
        raise InputError(f"no label -> bone table beside the label map (looked for {stem}.yaml, {stem}.json, "
                         f"labels.yaml, labels.json)", path)
    try:
        doc = load_yaml(table_path.read_text()) if table_path.suffix != ".json" \
            else json.loads(table_path.read_text())
    except (yaml.YAMLError, json.JSONDecodeError) as exc:
        raise InputError(f"unreadable label table ({type(exc).__name__})", table_path) from None
    table = doc.get("ids", doc) if isinstance(doc, dict) else None
    if not isinstance(table, dict) or not all(isinstance(i, int) for i in table.values()):
        raise InputError("the label table must map bone names to integer labels (optionally under 'ids')",
                         table_path)
    return {str(b): int(i) for b, i in table.items()}, table_path


def load_seeds(path: str | os.PathLike, *, with_settings: bool = False):
    """Seeds from YAML: ``bone: [[x, y, z], ...]`` in LPS mm (world), a point or a polyline.

    The seeds may sit under a ``seeds:`` key, beside two optional settings for
    :func:`bonecap.segmentation.bones.segment_bones`: ``margin_mm`` (how far
    beyond a polyline's ends a bone is still searched; seeds placed by eye
    over a bone's whole extent want a slice or so, the default 20 mm suits
    joint-to-joint lines), ``options`` (bone -> keyword options of its
    rule, e.g. ``marrow_over_muscle`` for a sequence whose marrow is much
    brighter than muscle) and ``rules`` (bone -> ``cortical`` | ``density``,
    e.g. a patella whose cortex shows as clearly as a long bone's).

    A long bone's polyline (femur, tibia, fibula, humerus, ulna, radius) runs
    from its proximal end to its distal end: in an axial stack, a region
    holding its seed past the proximal end (a femoral head around the hip's
    centre) stays the long bone's rather than going to a density-rule bone
    there (:func:`bonecap.segmentation.bones.segment_bones`). Points in the
    other order still seed the bone; only that rule then looks the wrong way.

    Returns
    -------
    dict bone -> ndarray (N, 3)
        With ``with_settings``: ``(seeds, {"margin_mm": ..., "options": ...})``
        holding only the settings the file gives.
    """
    import yaml

    path = Path(path)
    if not path.is_file():
        raise InputError("no such seeds file", path)
    try:
        doc = load_yaml(path.read_text())
    except yaml.YAMLError as exc:
        raise InputError(f"not valid YAML ({str(exc).splitlines()[0]})", path) from None
    seeds = doc.get("seeds", doc) if isinstance(doc, dict) else None
    if not isinstance(seeds, dict) or not seeds:
        raise InputError("expected a mapping bone -> [[x, y, z], ...] (LPS mm)", path)
    out = {}
    for bone, pts in seeds.items():
        if bone in ("frame", "units", "description"):
            continue
        a = np.asarray(pts, dtype=float)
        if a.ndim == 1:
            a = a[None]
        if a.ndim != 2 or a.shape[1] != 3 or not np.isfinite(a).all():
            raise InputError(f"seed of {bone!r} must be a point or a list of [x, y, z] in mm", path)
        out[str(bone)] = a
    if not with_settings:
        return out
    settings: dict[str, Any] = {}
    if isinstance(doc, dict) and "seeds" in doc:
        if "margin_mm" in doc:
            try:
                settings["margin_mm"] = float(doc["margin_mm"])
            except (TypeError, ValueError):
                settings["margin_mm"] = -1.0
            if not settings["margin_mm"] >= 0:
                raise InputError(f"margin_mm must be a number >= 0, got {doc['margin_mm']!r}", path)
        opts = doc.get("options")
        if opts is not None:
            if not isinstance(opts, dict) or not all(isinstance(o, dict) for o in opts.values()):
                raise InputError("options must map bone names to {option: value}", path)
            unknown = sorted(set(opts) - set(out))
            if unknown:
                raise InputError(f"options for bones without seeds: {', '.join(map(str, unknown))}", path)
            settings["options"] = {str(b): dict(o) for b, o in opts.items()}
        rules = doc.get("rules")
        if rules is not None:
            if not isinstance(rules, dict) or not all(r in ("cortical", "density") for r in rules.values()):
                raise InputError("rules must map bone names to 'cortical' or 'density'", path)
            unknown = sorted(set(rules) - set(out))
            if unknown:
                raise InputError(f"rules for bones without seeds: {', '.join(map(str, unknown))}", path)
            settings["rules"] = {str(b): str(r) for b, r in rules.items()}
    return out, settings


def build_from_mri(mri: list[str | os.PathLike], *, generic: str | os.PathLike = "default",
                   marker_set: str | os.PathLike | None = None, static: str | os.PathLike | None = None,
                   forearm_poses: list[str] | None = None, seeds: str | os.PathLike | None = None,
                   labels: str | os.PathLike | None = None, subject_name: str | None = None,
                   functional: list[str | os.PathLike] | None = None):
    """Build a subject from MRI stations; see the module docstring for the stages.

    ``functional``: movement trials (C3D) with knee flexion, with ``static``: the femurs' twist in the
    static binding is corrected from the knee's flexion axis
    (:func:`bonecap.build_subject.knee_flexion_twist`) where no capsule measured the thigh's markers.

    Returns
    -------
    subject : Subject
    report : dict
    qc : callable
        ``qc(folder)`` writes the QC pictures into ``folder/qc``.
    """
    # Work runs in children beside the stages that leave a core idle (loading the stations, the seeds,
    # the bone contours' last station, the hands' pose and the markers): what of the forearm stacks
    # needs nothing from the stations (reading them, their body masks, their capsules: ~8 s of CPU)
    # starts now, the stations' capsule search once they are registered (~4 s), the skin's mesh once
    # the body masks are made (~5 s), the stacks' registration after the warp. ``beside`` holds their
    # joins (and the registration's Pending), stopped if the build fails.
    import contextlib

    from bonecap.parallel import one_blas_thread

    beside: list = []
    reading = start_reading_stacks(list(forearm_poses)) if forearm_poses else None
    if reading is not None:
        beside.append(reading)
    # This process works beside its children and workers most of the time (they run BLAS on one thread
    # each): its own BLAS on one thread too. With OpenBLAS's threads spinning beside them the phantom's
    # build took 1.7-12.8 s longer on two cores (its CPU 6-22 s more); the results differ in the last
    # digits only (summation order: 7.5e-7 at most in subject.yaml).
    with one_blas_thread() if default_workers() > 1 else contextlib.nullcontext():
        try:
            return _build_from_mri(mri, generic=generic, marker_set=marker_set, static=static,
                                   forearm_poses=forearm_poses, seeds=seeds, labels=labels,
                                   subject_name=subject_name, functional=functional, reading=reading,
                                   beside=beside)
        except BaseException:
            for join in beside:
                if hasattr(join, "cancel"):
                    join.cancel()
            raise


def _build_from_mri(mri, *, generic, marker_set, static, forearm_poses, seeds, labels, subject_name, functional,
                    reading, beside):
    """:func:`build_from_mri`'s stages; ``reading``: :func:`start_reading_stacks` of ``forearm_poses``;
    ``beside``: the children started, to which the later ones are added (stopped if the build fails)."""
    from bonecap.io.c3d import read_c3d
    from bonecap.markers import check_marker_set, load_marker_set
    from bonecap.meshing import mesh_from_slices, meshes_from_labels
    from bonecap.progress import stage_bar
    from bonecap.segmentation.bones import defer_to_shaft_stacks, segment_bones
    from bonecap.segmentation.skin import segment_body
    from bonecap.skeleton.isb import malleolar_frames, malleolar_turns
    from bonecap.skeleton.template import load_template
    from bonecap.skeleton.warp import warp_skeleton
    from bonecap.stations import normalise_intensity, order_stations, register_stations
    from bonecap.subject import Subject

    timings: dict[str, float] = {}
    t = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal t
        now = time.perf_counter()
        timings[name] = round(now - t, 2)
        t = now

    bar = stage_bar(7, "build-subject")
    template = load_template(generic)
    mset = load_marker_set(marker_set or ("kojima_paper" if str(generic) == "default" else generic))
    check_marker_set(mset, template)
    static_trial = read_c3d(static, subject=subject_name) if static else None
    if functional and static_trial is None:
        raise InputError("--functional needs --static (the trials correct the static's binding)", functional[0])
    functional_trials = [(read_c3d(f, subject=subject_name), str(f)) for f in functional or ()]
    if mri and seeds is None and labels is None and not _placeable(template):
        # a whole-body MRI places the template by the embedded skeleton's bones and joints (fail before
        # the stations are read, not at the seeds with a KeyError)
        raise InputError("this template cannot be placed on a whole-body MRI (the MRI path needs the embedded "
                         "skeleton's hip_r / hip_l bones with their 'hip' joints): use --generic default, or give "
                         "--seeds SEEDS.yaml or --labels LABELMAP", generic)
    lap("template")

    # 1. stations
    bar.set_postfix_str("stations")
    vols = load_stations(mri) if mri else []
    reg_report: list = []
    scales = np.ones(len(vols))
    nominal_affines = [v.affine.copy() for v in vols]
    # one local series with the user's seeds or labels (a knee, an elbow) is segmented in its own
    # slices, whatever their orientation -- the slice rules work in pixel space, as the paper's did; a
    # whole body must be axial stations (the template is placed from their head-to-feet extent)
    local_scan = len(vols) == 1 and (seeds is not None or labels is not None)
    if vols and not local_scan:
        try:
            vols = order_stations(vols)
            nominal_affines = [v.affine.copy() for v in vols]
            if len(vols) > 1:
                vols, reg_report = register_stations(vols)
                vols, scales = normalise_intensity(vols)
        except ValueError as exc:
            raise DataError(str(exc), mri[0] if len(mri) == 1 else None) from None
    lap("stations")
    bar.update()
    # the capsules of the stations (the markers' stage names them) need only the registered images
    capsule_search = fork_or_here(lambda: _station_capsules(vols), beside=True)
    beside.append(capsule_search)

    # 2. skin
    bar.set_postfix_str("skin")
    # the body masks (Otsu's boundary) place the template and bound the density rule; the skin's own
    # masks (the half-way boundary) make the skin mesh the markers are put on
    both = fork_map(lambda v: segment_body(v, skin=True), vols)
    bodies = [b for b, _ in both]
    skin_masks = [(s, v.affine) for (_, s), v in zip(both, vols)]
    del both
    # The skin's mesh (~5 s) is needed from the warp on (the skull is fitted to it): it is made in a
    # child beside the seeds (serial) and the bone contours' last station, where a core was idle.
    skin_meshing = fork_or_here(lambda: mesh_from_slices(skin_masks, voxel_mm=4.0, target_faces=40000),
                                beside=True) if vols else (lambda: None)
    beside.append(skin_meshing)
    lap("skin")
    bar.update()

    posed, align_report = None, {}
    overlap_dropped: dict[str, int] = {}
    if labels is not None:
        # 3-4. the user's own segmentation replaces seeds and contours
        bar.set_postfix_str("labels")
        pieces, ids = load_label_map(labels)
        lap("labels")
        bar.update()
        bar.update()
    else:
        # 3. seeds from the template roughly aligned to the body
        bar.set_postfix_str("seeds")
        seg_settings: dict[str, Any] = {}
        if seeds is not None:
            seed_map, seg_settings = load_seeds(seeds, with_settings=True)
        else:
            top, bottom, centre_at = _body_extent(vols, bodies)
            if not _covers_whole_body(vols, bodies):
                raise DataError("the stations do not cover the whole body (head to feet), so the template cannot "
                                "be placed from the body's extent: give --seeds SEEDS.yaml (bone -> LPS points)",
                                mri[0])
            posed, align_report = place_template(template, vols, bodies, top, bottom, centre_at)
            follow: dict[str, float] = {}
            heads: dict[str, float] = {}
            seed_map = bone_seeds(posed, np.eye(4), followed=follow, heads=heads)
            seg_settings["follow_mm"] = follow
            seg_settings["follow_head_mm"] = heads
            seg_settings["follow_tips"] = [n for n in follow if n[:-2] in FOLLOWED_TIPS]
        lap("seeds")
        bar.update()

        # 4. bone contours per station
        bar.set_postfix_str("bone contours")
        pieces = []
        ids: dict[str, int] = {}
        try:
            # stations are independent: one per worker process
            segmented = fork_map(lambda vb: segment_bones(vb[0], seed_map, body_mask=vb[1], progress=False,
                                                          **seg_settings), list(zip(vols, bodies)))
        except ValueError as exc:     # an unknown option in the seeds file
            raise InputError(str(exc), seeds) from None
        # where stations overlap, a long bone's end is judged by the one holding its shaft (a station holding
        # only the end kept the carpals past the forearm's bones)
        overlap_dropped = defer_to_shaft_stacks([lab for lab, _ in segmented], [m for _, m in segmented], vols,
                                                seed_map, seg_settings.get("rules"))
        for v, (lab, station_ids) in zip(vols, segmented):
            # one id space across stations
            remap = np.zeros(max(station_ids.values(), default=0) + 1, dtype=np.int32)
            for name, i in station_ids.items():
                ids.setdefault(name, len(ids) + 1)
                remap[i] = ids[name]
            pieces.append((remap[lab], v.affine))
        lap("bone contours")
        bar.update()

    # 5. meshes
    bar.set_postfix_str("meshes")
    not_meshed: dict[str, str] = {}
    # a bone seen in a slice or two (its tip entering the field of view) gives
    # no usable surface: the warp carries it from its neighbours
    extracted = meshes_from_labels(pieces, ids, min_slices=3, errors=not_meshed)
    lap("meshes")
    bar.update()

    # 6. personal skeleton
    bar.set_postfix_str("warp")
    if posed is None:  # user seeds: place the template on the extracted bones' centroids
        posed = _template_from_targets(template, extracted)
    targets = warp_targets(_plausible_targets(posed, extracted, strict=labels is None and seeds is None),
                           trusted=labels is not None or seeds is not None)
    # the template is placed bone by bone already (limbs re-posed toward the MRI)
    placed_ok = labels is None and seeds is None
    skin = skin_meshing()
    del skin_masks
    # the skull from the head's skin (its thin cortex escapes the slice rules); fitted before the warp so
    # that the spine carried up from the pelvis meets it (see warp_skeleton's ``fixed``)
    skull_A, skull_report = fit_skull_to_skin(posed, skin) if "skull" not in targets else (np.eye(4), None)
    skull_fixed = {n: skull_A for n in ("skull", "mandible") if n in posed.bones and n not in targets} \
        if skull_report is not None and skull_report["used"] else None
    spine_qc: dict[str, Any] = {}
    if targets:
        # a user's label map says nothing of where it was looked for: no cut
        cut = unseen_ends(targets, seed_map, vols, margin_mm=seg_settings.get("margin_mm", 20.0),
                          tips=FOLLOWED_TIPS if seg_settings.get("follow_tips") else (),
                          # the template's lines run proximal -> distal; a user's may not
                          processes=MARROWLESS_ENDS if seeds is None else ()) if labels is None else {}
        # the radius's distal end, which its extraction may end short of (LENGTH_FROM): cut only if its warp
        # falls short of its ulna's length there (template lines run proximal -> distal; a user's may not)
        ends = distal_cuts(targets, seed_map, vols, tuple(LENGTH_FROM)) if labels is None and seeds is None else {}
        personal, warp_report = warp_skeleton(posed, targets, init=np.eye(4) if placed_ok else None,
                                              start_from="placed" if placed_ok else "ancestor",
                                              max_turn_deg=35.0 if placed_ok else 45.0,
                                              max_shift_mm=PLACED_MAX_SHIFT_MM if placed_ok else np.inf,
                                              fixed=skull_fixed,
                                              unseen=cut, refine_chain=_spine_from_discs(vols, spine_qc) if vols else None,
                                              cover=[n for n in targets if n[:-2] in COVERED_EXTENTS],
                                              cover_marrow=[n for n in cut if n[:-2] in MARROWLESS_ENDS],
                                              # (a template without the neighbour, an .osim one: no check)
                                              length_from={n: (LENGTH_FROM[n[:-2]] + n[-2:], h)
                                                           for n, h in ends.items()
                                                           if LENGTH_FROM[n[:-2]] + n[-2:] in posed.bones})
    else:
        # nothing extracted well enough to warp onto (coarse or partial images):
        # the template as placed on the body is all there is -- said loudly
        import copy

        personal = copy.deepcopy(posed)
        personal.world = "lps"
        warp_report = {"bones": {}, "warning": "no extracted bone passed the plausibility checks: the personal "
                       "skeleton is the template placed on the body (scaled, limbs re-posed), not warped"}
        warnings.warn(warp_report["warning"], stacklevel=2)
    if skull_report is not None and (not targets or not skull_report["used"]):
        # no warp to hand it to, or the fit was out of bounds (identity: the placed skull is kept)
        place_skull(personal, posed, skull_A)
    elif skull_fixed:
        for n in skull_fixed:
            personal.bones[n].metadata["source"] = "template fitted to the head's skin"
    lap("warp")
    # the density rule's bones moved in plane onto what the image shows of them (before the markers are
    # placed and bound on them, and before the forearm's workers copy the skeleton) -- in the capsule
    # protocol only (SHIFT_MIN_CAPSULES): there each marker is bound where the scan shows it against the
    # bones as placed in that scan, so a trunk bone placed 2 mm off is 2 mm off in every trial
    centres = capsule_search()
    capsule_search = lambda: centres     # noqa: E731 - joined once, handed on to the markers' stage
    shifts: dict[str, np.ndarray] = {}
    if labels is None and targets and pieces and len(centres) >= SHIFT_MIN_CAPSULES:
        shifts = density_bone_shifts(personal, ids, list(zip(pieces, vols)), bodies, seg_settings.get("rules"))
        shifts.update(thorax_follows(personal, shifts))
        shift_bones_keeping_joints(personal, shifts)
        lap("density shifts")
    bar.update()

    # The forearm stacks' registrations need the personal forearm bones, nothing after the warp (the
    # hands turned into the skin below, the markers): started now, they run in worker processes while
    # the hands are posed and the markers placed here. The workers see the skeleton as it is now; the
    # turn below replaces only the hands' bones (pose_inside_skin copies the ones it turns).
    registering = None
    if forearm_poses:
        read = reading()
        side = _stack_side(forearm_poses[0], personal, read[0])
        registering = start_forearm_registration(list(forearm_poses), personal, side, read=read)
        beside.append(registering)

    # the hands, which no bone rule resolves at whole-body resolution, turned at the wrist into the skin
    skin_posed = None
    if skin is not None:
        personal, skin_posed = pose_inside_skin(personal, skin)

    # 7. markers
    bar.set_postfix_str("markers")
    subject = Subject(skeleton=personal, skin=skin, marker_set=mset.name,
                      provenance={"command": "build-subject", "mode": "mri", "girdle_rhythm": True,
                                  "generic": str(generic),
                                  "marker_set": mset.source or mset.name, "mri": [str(p) for p in mri],
                                  "static": str(static) if static else None,
                                  "seeds": str(seeds) if seeds else "template (affine to the body)"})
    marker_report = _place_and_bind(subject, mset, vols, bodies, static_trial, static, functional_trials,
                                    capsule_search=capsule_search)
    # the tibiae's frames (and the feet's carried with them) turned to their malleoli's twist, after the
    # markers are placed and bound: a frame only says how a bone's pose is reported, so the bones stay
    # where the warp and the static put them (turned before the placement, the shank markers' "lateral"
    # turned with it and the static's shanks followed: seed 1's legs 37.5 -> 47.9 deg summed)
    measured = {n for n, r in (warp_report.get("bones") or {}).items() if r.get("source") == "own target"}
    turns = malleolar_turns(subject.skeleton, template, measured)
    if turns:
        reframe_subject(subject, malleolar_frames(subject.skeleton, turns, measured))
    marker_report["malleolar_turns_deg"] = {k: round(v, 2) for k, v in turns.items()}
    lap("markers")
    bar.update()
    forearm_report = None
    if forearm_poses:
        bar.set_postfix_str("forearm")
        try:
            model, forearm_report = fit_forearm_from_stacks(list(forearm_poses), personal, side=side,
                                                            markers=subject.markers, registered=registering,
                                                            skin=skin)
            subject.forearm = {side: model}
        except DataError as exc:
            # the stacks could not be read as three poses of this forearm: the
            # paper's coefficients stay, and the report says why
            forearm_report = {"used": False, "reason": str(exc), "capsules": forearm_capsules(forearm_poses, read)}
        lap("forearm")
    bar.close()

    report: dict[str, Any] = {
        "mode": "mri", "stations": reg_report, "intensity_scales": np.asarray(scales).tolist(),
        "template_placement": align_report, "skull_from_skin": skull_report,
        "extracted_bones": sorted(extracted), "not_meshed": not_meshed,
        "overlap_sections_dropped": overlap_dropped, "warp": warp_report,
        "density_shifts_mm": {n: np.round(d, 2).tolist() for n, d in shifts.items()},
        "skin_posed_segments": skin_posed, **marker_report,
        "timings_s": timings, "seconds": round(sum(timings.values()), 2),
    }
    if forearm_report is not None:
        report["forearm"] = forearm_report
    qc_data = {"vols": vols, "pieces": pieces if labels is None else [], "ids": ids, "extracted": extracted,
               "skin": skin, "bodies": bodies, "spine": spine_qc}

    def qc(folder: Path) -> None:
        from bonecap.qc import write_build_qc

        t0 = time.perf_counter()
        write_build_qc(Path(folder) / "qc", subject, qc_data, report)
        # written to report.json after this: the speed target counts the build without its pictures
        timings["qc pictures"] = round(time.perf_counter() - t0, 2)

    # extracted meshes are part of the result (the evaluation scores them)
    def qc_and_meshes(folder: Path) -> None:
        import json

        from bonecap.io.imaging import write_nifti
        from bonecap.io.mesh import write_mesh

        folder = Path(folder)
        for name, m in extracted.items():
            write_mesh(m, folder / "extracted" / f"{name}.ply")
        # the baseline the warp must beat: the placed template after each bone's affine alone
        for name, r in (warp_report.get("bones") or {}).items():
            aff = (warp_report.get("transforms") or {}).get(name)
            if r.get("source") == "own target" and aff is not None and posed.bones[name].mesh is not None:
                write_mesh(posed.world_mesh(name).transformed(np.asarray(aff, float), "lps"),
                           folder / "affine_only" / f"{name}.ply")
        # the slice-wise labels, on each station's own grid placed in the
        # registered frame: open them over the DICOM in Slicer / ITK-SNAP, fix,
        # and pass them back with --labels
        stations = []
        # (with --labels the user's own map is the segmentation: nothing of ours to write)
        station_pieces = list(zip(pieces, vols)) if labels is None else []
        for n, ((lab, aff), v) in enumerate(station_pieces):
            rel = f"labels/station_{n + 1}.nii.gz"
            (folder / "labels").mkdir(parents=True, exist_ok=True)
            write_nifti(Volume(lab.astype(np.int16), aff), folder / rel)
            files = v.metadata.get("source_files")
            stations.append({"index": n + 1, "labels": rel, "source": str(Path(files[0]).parent) if files else "",
                             "nominal_affine": nominal_affines[n].tolist(), "registered_affine": aff.tolist(),
                             "shape": list(lab.shape)})
        doc: dict[str, Any] = {"ids": ids, "stations": stations}
        # the personal skeleton on the same grids; with --labels on the user's map's, which it completes with
        # the bones the map lacks (ribs, hands, feet, the skull) and shows where the warp left its labels
        t0 = time.perf_counter()
        personal_ids, personal = _personal_ids(subject.skeleton, ids, labels, pieces)
        qc_data["personal"] = []
        if personal:
            for st, ((lab, aff), v) in zip(stations, station_pieces):
                st["personal_labels"] = f"labels/personal_station_{st['index']}.nii.gz"
                plab = personal_labels(personal, aff, lab.shape, v)      # uint16 (ids checked 1..65535)
                write_nifti(Volume(plab, aff), folder / st["personal_labels"])
                qc_data["personal"].append(plab)     # drawn over the rules' contours
            if station_pieces:      # the rules ran (not a user's --labels map)
                refine_station_labels(station_pieces, qc_data["personal"], stations, personal_ids, ids, bodies,
                                      seg_settings.get("rules"), folder, doc, timings)
            if labels is not None:
                lab, aff = pieces[0]
                rel = "labels/personal_labelmap.nii.gz"
                (folder / "labels").mkdir(parents=True, exist_ok=True)
                write_nifti(Volume(personal_labels(personal, aff, lab.shape), aff), folder / rel)
                doc["personal_on_label_map"] = {"labels": rel, "label_map": str(labels), "affine": aff.tolist(),
                                                "shape": list(lab.shape)}
            # part of the build's time (the speed target counts it; the QC pictures it does not)
            spent = round(time.perf_counter() - t0, 2)
            timings["personal labels"] = round(spent - timings.get("refined labels", 0.0), 2)
            report["seconds"] = round(report["seconds"] + spent, 2)
            doc["personal_ids"] = personal_ids
        (folder / "stations.json").write_text(json.dumps(doc, indent=1))
        qc(folder)

    return subject, report, qc_and_meshes


#: Bones :func:`density_bone_shifts` leaves where the warp put them (by name prefix): the scapula's blade lies
#: on the ribs, whose marrow within a pixel of it the refinement takes as the blade's; on the six phantoms the
#: refined scapulae's centroids lay further from the truth's than the personal ones' on five of six (by
#: 1.7-3.9 mm), while of all 31 density bones' the refined centroids lay nearer on 26 and 27 (seeds 2, 3; 17 on
#: seed 1, whose personal ones were 1.0 mm off already).
SHIFT_EXCLUDED = ("scapula",)
#: :func:`density_bone_shifts` runs only when the stations show at least this many capsules (the paper's
#: protocol). Without capsules the markers are placed on the skin over the bones' landmarks and bound by
#: the static trial, and the trunk's bones in the trials are where the static's thorax puts them: there the
#: shifts took standard seed 3's upper thoracic vertebrae 1-2 mm further off (the density bones' origins in
#: the trials, median over those bones, 1.68 -> 2.25 mm), where with capsules they bring them nearer (seeds
#: 2, 3: 2.39 -> 1.71 and 2.35 -> 1.80 mm; seed 1, 0.95 mm before, 1.04; docs/benchmarks.md, session 40).
SHIFT_MIN_CAPSULES = 10


def density_bone_shifts(skeleton: Skeleton, ids: dict[str, int], station_pieces: list, bodies: list[np.ndarray],
                        rules: dict[str, str] | None = None, *, min_voxels: int = 50,
                        max_shift_mm: float = 4.0) -> dict[str, np.ndarray]:
    """In-plane shifts (mm, the skeleton's world) that move the density rule's bones onto the image.

    The density rule finds these bones (hips, sacrum, vertebrae, scapulae,
    kneecaps) in fragments, so the warp places them mostly from their
    neighbours: on the phantoms their label maps' centroids lay 1-2.3 mm (median
    by seed) from the truth's, seeds 2-3's cervical and upper thoracic
    vertebrae ~3 mm. The refined label map
    (:func:`bonecap.segmentation.refine.refine_labels`) moves each bone's
    section onto the image's bone evidence within a pixel; where that is one
    sided, the section's centroid moves with it. Each bone is shifted by that
    move of its centroid, in the stations' slice planes only (the refinement
    moves edges within a slice, not from slice to slice), averaged over the
    stations that show it (weighted by its voxels there).

    Parameters
    ----------
    skeleton : Skeleton
        The personal skeleton (world: the subject's, LPS mm).
    ids : dict of str -> int
        The slice rules' label ids (``stations.json`` ``ids``).
    station_pieces : list of ((labels, affine), Volume)
        Each station's rules' labels with its registered voxel -> world affine, and its image.
    bodies : list of ndarray of bool
        Each station's body mask.
    rules : dict, optional
        Rule per bone where not :func:`~bonecap.segmentation.bones.default_rule`'s.
    min_voxels : int
        A bone seen in fewer voxels (over all stations) is not moved.
    max_shift_mm : float
        Longest shift (the refinement moves an edge by a pixel at most, ~2 mm).

    Returns
    -------
    dict of str -> ndarray (3,)
        World shift per bone; bones not shown, not the density rule's, or in
        :data:`SHIFT_EXCLUDED`, absent (:func:`shift_bones_keeping_joints`
        applies them).
    """
    from scipy import ndimage

    from bonecap.segmentation.bones import default_rule
    from bonecap.segmentation.refine import refine_labels

    rules = dict(rules or {})
    personal_ids, meshes = personal_label_meshes(skeleton, ids)
    refine = {b: personal_ids[b] for b in ids if rules.get(b, default_rule(b)) == "density" and b in personal_ids}
    if not refine or not station_pieces:
        return {}
    index = sorted(refine.values())
    moved = [b for b in refine if not b.startswith(SHIFT_EXCLUDED)]

    def one(n: int):
        (lab, aff), v = station_pieces[n]
        prior = personal_labels(meshes, aff, lab.shape, v)
        refined = refine_labels(v, prior, refine, body_mask=bodies[n])
        ones = np.ones(prior.shape, np.uint8)
        counts = [np.bincount(m.ravel(), minlength=max(index) + 1)[index] for m in (prior, refined)]
        with np.errstate(invalid="ignore", divide="ignore"):      # a bone not in this station: NaN, unused
            centres = [np.asarray(ndimage.center_of_mass(ones, m, index)) for m in (prior, refined)]
        return counts, centres

    acc = {b: [np.zeros(3), 0] for b in refine}
    for ((_, aff), _v), (counts, centres) in zip(station_pieces, fork_map(one, list(range(len(station_pieces))))):
        A = np.asarray(aff, float)
        for r, b in enumerate(sorted(refine, key=refine.get)):
            w = int(min(counts[0][r], counts[1][r]))
            if w == 0:
                continue
            # in the slice plane (index axes i, j) only, to the world by the station's affine
            acc[b][0] += w * (A[:3, :2] @ (centres[1][r][:2] - centres[0][r][:2]))
            acc[b][1] += w
    out = {}
    for b, (s, w) in acc.items():
        if w >= min_voxels and b in moved:
            d = s / w
            norm = float(np.linalg.norm(d))
            out[b] = d * (max_shift_mm / norm) if norm > max_shift_mm else d
    return out


def thorax_follows(skeleton: Skeleton, shifts: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Shifts for the ribs and the sternum that keep the thorax one piece with its shifted vertebrae.

    The motion solver carries the thoracic vertebrae, ribs and sternum as one rigid segment driven by the
    trunk's markers, placed over the vertebrae's and the sternum's landmarks: vertebrae moved apart from
    their ribs (:func:`density_bone_shifts`) left seed 3's upper thoracic vertebrae 1-2 mm further off in the
    trials than where the warp had put them. Each rib ``rib<k>_<side>`` follows ``t<k>``; the sternum the mean
    of the vertebrae its ribs hold (t1-t7) that have a shift.
    """
    out = {}
    for name in skeleton.names:
        if name.startswith("rib") and "_" in name:
            k = name[3:].split("_")[0]
            if f"t{k}" in shifts:
                out[name] = np.asarray(shifts[f"t{k}"], float)
    held = [np.asarray(shifts[f"t{k}"], float) for k in range(1, 8) if f"t{k}" in shifts]
    if "sternum" in skeleton.bones and held:
        out["sternum"] = np.mean(held, axis=0)
    return out


def shift_bones_keeping_joints(skeleton: Skeleton, shifts: dict[str, np.ndarray]) -> None:
    """Translate bones (in place) by world ``shifts``, each with its mesh and landmarks, its joint centres
    left where they are in the world.

    The joint centres tie a density-rule bone to the long bones, whose own
    extraction placed them (a scapula's glenoid, a hip bone's acetabulum under
    the femoral head), and the static trial binds the limbs' markers through
    them: moved with the bones (:func:`density_bone_shifts`), seed 2's arm
    markers were bound 2-3 mm further off.
    """
    for name, d in shifts.items():
        bone = skeleton.bones[name]
        d = np.asarray(d, float)
        back = bone.bone_to_world[:3, :3].T @ d
        bone.joint_centres = {j: c - back for j, c in bone.joint_centres.items()}
        T = bone.bone_to_world.copy()      # a new array: the warp's input skeleton may share this one
        T[:3, 3] += d
        bone.bone_to_world = T


def refine_station_labels(station_pieces: list, priors: list[np.ndarray], stations: list[dict],
                          personal_ids: dict[str, int], ids: dict[str, int], bodies: list[np.ndarray],
                          rules: dict[str, str] | None, folder: Path, doc: dict[str, Any],
                          timings: dict[str, float]) -> None:
    """Write each station's refined label map (``labels/refined_station_<k>.nii.gz``).

    The personal skeleton's label map on the station's grid (``priors``, in
    ``station_pieces``' order) with the density rule's bones refined by the image
    (:func:`bonecap.segmentation.refine.refine_labels`); every other bone as the
    personal map has it (the long bones too: there it matches the cortical-edge
    rule's sections or does better, Dice against the truth on the seed-1 phantom
    0.94-0.96 for femora, tibiae and humeri either way, the forearm bones 0.91-0.92
    against the rule's 0.85-0.89). On the six phantoms of docs/benchmarks.md the density
    rule's bones met #5's Dice target (the oracle's minus 0.06) 114 times of 186 refined,
    71 as the personal map has them; what the refinement loses is a prior that is
    very good already (seed 1's thoracic vertebrae: 0.90 -> 0.84, a pixel ring round
    bodies whose cortex is thinner than a pixel).

    ``stations`` gets ``refined_labels`` per station and ``doc`` (``stations.json``) the
    ``refined_bones``; the time is ``timings["refined labels"]``. ``bonecap evaluate subject``
    scores the maps (``refined_dice``).
    """
    from bonecap.io.imaging import write_nifti
    from bonecap.segmentation.bones import default_rule
    from bonecap.segmentation.refine import refine_labels

    t0 = time.perf_counter()
    rules = dict(rules or {})
    refine = {b: personal_ids[b] for b in ids if rules.get(b, default_rule(b)) == "density" and b in personal_ids}
    if not refine or not station_pieces:
        return

    def one(n: int) -> np.ndarray:
        return refine_labels(station_pieces[n][1], priors[n], refine, body_mask=bodies[n])

    # stations are independent: one per worker process
    for n, refined in enumerate(fork_map(one, list(range(len(station_pieces))))):
        rel = f"labels/refined_station_{stations[n]['index']}.nii.gz"
        write_nifti(Volume(refined, station_pieces[n][0][1]), folder / rel)
        stations[n]["refined_labels"] = rel
    doc["refined_bones"] = sorted(refine)
    timings["refined labels"] = round(time.perf_counter() - t0, 2)


def _personal_ids(skeleton: Skeleton, ids: dict[str, int], labels, pieces) -> tuple[dict[str, int], list]:
    """:func:`personal_label_meshes` for the build: on the stations with the rules' ids; on a user's map
    (``labels``) with its table's, every bone it names keeping its label and new ones above every label
    the map or the table uses, so that the two maps merge without clashes (ids beyond 16 bits: no map,
    said)."""
    if not pieces:
        return {}, []
    if labels is None:
        return personal_label_meshes(skeleton, ids)
    table = {b: i for b, i in label_table(labels)[0].items() if b in skeleton.bones and i > 0}
    try:
        return personal_label_meshes(skeleton, table,
                                     taken=max(int(pieces[0][0].max()), max(table.values(), default=0)))
    except ValueError as exc:
        warnings.warn(f"{labels}: the personal skeleton is not written on the label map's grid ({exc})",
                      stacklevel=3)
        return {}, []


def personal_label_meshes(skeleton: Skeleton, ids: dict[str, int], *, taken: int = 0
                          ) -> tuple[dict[str, int], list[tuple[Mesh, int]]]:
    """The personal skeleton's bones as ``(mesh in world, label id)`` for :func:`personal_labels`.

    Parameters
    ----------
    skeleton : Skeleton
    ids : dict of str -> int
        Ids to keep: the slice rules' (a bone is one id in both label maps),
        or a user's label table.
    taken : int
        Ids up to this one are in use besides ``ids`` (a user's map may hold
        labels its table does not name: organs, for one).

    Returns
    -------
    ids : dict of str -> int
        ``ids`` and every bone with a mesh, the bones ``ids`` lacks (ribs,
        hands, feet, the skull for the rules) numbered on from the largest id
        in use; ``personal_ids`` in ``stations.json``.
    meshes : list of (Mesh, int)
        Each bone's mesh in the skeleton's world and its id.

    Raises
    ------
    ValueError
        An id outside 1..65535 (a label map's voxels are 16-bit here).
    """
    out = dict(ids)
    meshes = []
    top = max(max(out.values(), default=0), int(taken))
    for name in skeleton.names:
        if skeleton.bones[name].mesh is None:
            continue
        if name not in out:
            top += 1
            out[name] = top
        if not 1 <= out[name] <= 65535:
            raise ValueError(f"label id {out[name]} of {name} is outside 1..65535")
        meshes.append((skeleton.world_mesh(name), out[name]))
    return out, meshes


def personal_labels(meshes: list[tuple[Mesh, int]], affine: np.ndarray, shape, volume: Volume | None = None
                    ) -> np.ndarray:
    """The personal skeleton as a label map on one grid (a station's, or a user's label map's).

    The density rule (Kojima et al.) finds the bones with little cortex in
    pieces: in a T2-weighted contrast a scapula is nearly all dark cortex and
    a vertebra loses its posterior elements (hips, scapulae and vertebrae:
    Dice 0.0-0.5 against the truth on the phantoms). The personal skeleton,
    the template warped onto what the rules did find and carried from its
    neighbours where they found nothing, covers every bone whole: a
    model-based segmentation [1]_. Voxelised on a station's acquisition grid
    (as registered: ``affine`` is voxel -> the subject's world) by
    :func:`bonecap.phantom.render.voxelise_labels` (a voxel takes a bone
    covering at least half of it over the slice's thickness; samples about
    0.5 mm apart in plane and 1.25 mm through the slice, at most 4 x 4: the
    default phantom's oracle's sampling on its 1.8 mm x 5 mm stations, fewer
    on finer grids), it opens over the images in 3D Slicer or ITK-SNAP
    beside the rules' own labels. ``bonecap evaluate subject`` scores it on
    the bones the rules segment (``personal_dice``).

    Parameters
    ----------
    meshes : list of (Mesh, int)
        From :func:`personal_label_meshes` (world frame, LPS mm).
    affine : ndarray (4, 4)
        The grid's voxel -> world (mm).
    shape : tuple of 3 int
    volume : Volume, optional
        The station, for its slice thickness (DICOM ``SliceThickness``; else the spacing).

    Returns
    -------
    ndarray (I, J, K) of uint16
        0 outside every bone.

    References
    ----------
    .. [1] Heimann, T. & Meinzer, H.-P. (2009). Statistical shape models for
       3D medical image segmentation: a review. Medical Image Analysis 13(4),
       543-563.
    """
    from bonecap.phantom.render import voxelise_labels

    thickness = (volume.metadata.get("slice_thickness") if volume is not None else None) or None
    spacing = np.linalg.norm(np.asarray(affine, float)[:3, :3], axis=0)
    through = float(thickness) if thickness else float(spacing[2])
    # samples ~0.5 mm apart in plane and ~1.25 mm through the slice, at most the oracle's 4 x 4 (a
    # whole-body station's 1.8 mm pixels and 5 mm slices get exactly that); a fine grid (a CT label
    # map's 1 mm voxels) gets fewer: one voxel's coverage hardly matters there, and its voxels are many
    inplane = int(np.clip(np.ceil(max(spacing[0], spacing[1]) / 0.5), 1, 4))
    across = int(np.clip(np.ceil(through / 1.25), 1, 4))
    return voxelise_labels(meshes, affine, shape, slice_thickness_mm=float(thickness) if thickness else None,
                           inplane_supersample=inplane, through_plane_samples=across)


def unseen_ends(extracted: dict[str, Mesh], seeds: dict[str, np.ndarray], vols: list[Volume], *,
                margin_mm: float = 20.0, tips: tuple[str, ...] = (),
                processes: tuple[str, ...] = ()) -> dict[str, list[tuple[np.ndarray, float]]]:
    """Where each long bone's extraction ends because the search did, not the bone: half-spaces for the warp.

    The cortical rule looks for a long bone on the slices its seed polyline
    crosses and ``margin_mm`` beyond its ends
    (:func:`bonecap.segmentation.bones.slice_seeds`), within the stations'
    field of view. A bone labelled up to the last slice searched goes on
    beyond it (the tibia's line ends short of the talus, the femoral head's
    dome rises above the hip centre's margin, a short template's wrist): the
    extraction's end there is a cut. Left as it is, the warp's ICPs and
    feature points take the cut for the bone's end and shrink the personal
    bone to it (a phantom's tibias came out 12-37 mm short, its forearms
    11-15 mm: their ISB origins, at the malleoli and the ulnar styloid,
    moved with them). The half-space covers the extraction's last slice
    pitch (its cap, ``normal . p > offset``, LPS); the warp then
    extrapolates the template there (:func:`bonecap.skeleton.warp.warp_skeleton`'s
    ``unseen``). A bone that ends in a free tip (``tips``), labelled past its
    search's last slice, was tracked there to its point
    (:func:`bonecap.segmentation.bones._extend_tip`): that end is its own.
    Other bones followed past their search stop at their joint, past which
    they may go on (the medial malleolus beside the talus): a cut. A bone
    whose distal end is a process without marrow (``processes``: the ulnar
    styloid) ends where its marrow does, short of the process, wherever the
    search stopped: its distal end is always a cut.

    Parameters
    ----------
    extracted : dict of str -> Mesh
        Extracted bone surfaces (LPS mm).
    seeds : dict of str -> ndarray (N, 3)
        The seed polylines the slice rules searched along (LPS mm).
    vols : list of Volume
        The axial stations (their slices' z and pitch).
    margin_mm : float
        How far past a polyline's ends the search went.
    tips : tuple of str
        Bone names without their side suffix (:data:`FOLLOWED_TIPS`).
    processes : tuple of str
        Bone names without their side suffix (:data:`MARROWLESS_ENDS`); the
        distal end is the seed polyline's last point's.

    Returns
    -------
    dict of str -> list of (normal, offset)
        The long bones with a cut end (an extraction ending at a search's or
        the images' end), in LPS: ``normal`` along the slice axis (-z for a
        cut at the feet's end of axial stations, +z at the head's). Empty
        when the stations' slice axes differ.
    """
    if not vols:
        return {}
    # the slice axis (z for axial stations; a sagittal knee's is x): the stations must share it
    u = vols[0].affine[:3, 2] / np.linalg.norm(vols[0].affine[:3, 2])
    u = u if u[np.argmax(np.abs(u))] > 0 else -u
    if any(abs(float(v.affine[:3, 2] @ u)) < 0.999 * np.linalg.norm(v.affine[:3, 2]) for v in vols):
        return {}
    dz = max(float(v.spacing[2]) for v in vols)
    zs = np.concatenate([[(v.affine @ [0.0, 0.0, k, 1.0])[:3] @ u for k in (0, v.shape[2] - 1)] for v in vols])
    fov_lo, fov_hi = float(zs.min()), float(zs.max())
    out: dict[str, list[tuple[np.ndarray, float]]] = {}
    for name, mesh in extracted.items():
        if not name.startswith(_LONG) or name not in seeds or mesh is None or not len(mesh.vertices):
            continue
        z = np.asarray(seeds[name], float).reshape(-1, 3) @ u
        lo, hi = max(z.min() - margin_mm, fov_lo), min(z.max() + margin_mm, fov_hi)
        ez = mesh.vertices @ u
        cuts = []
        # labelled on the last slice searched: its section reaches half a pitch past that slice's centre;
        # a tip tracked a slice or more past it ended there (past the images' end nothing is labelled)
        tip = name[:-2] in tips
        distal_low = name[:-2] in processes and z[-1] < z[0]
        distal_high = name[:-2] in processes and z[-1] > z[0]
        if distal_low or (ez.min() < lo + 0.5 * dz + 1.0
                          and not (tip and fov_lo < lo and ez.min() < lo - 0.5 * dz - 1.0)):
            cuts.append((-u, -(float(ez.min()) + dz)))
        if distal_high or (ez.max() > hi - 0.5 * dz - 1.0
                           and not (tip and hi < fov_hi and ez.max() > hi + 0.5 * dz + 1.0)):
            cuts.append((u.copy(), float(ez.max()) - dz))
        if cuts:
            out[name] = cuts
    return out


def distal_cuts(extracted: dict[str, Mesh], seeds: dict[str, np.ndarray], vols: list[Volume],
                bones: tuple[str, ...]) -> dict[str, list[tuple[np.ndarray, float]]]:
    """The half-space past each named long bone's extraction's distal end (its last slice pitch), for the warp.

    As :func:`unseen_ends` cuts a marrowless end (``processes``), but for the
    bones whose extraction only *may* end short there: the warp cuts that end
    when the bone's warp falls short of the length a neighbour gives it
    (:func:`bonecap.skeleton.warp.warp_skeleton`'s ``length_from``;
    :data:`LENGTH_FROM`).

    Parameters
    ----------
    extracted : dict of str -> Mesh
        Extracted bone surfaces (LPS mm).
    seeds : dict of str -> ndarray (N, 3)
        Seed polylines, proximal to distal (LPS mm).
    vols : list of Volume
        The axial stations.
    bones : tuple of str
        Bone names without their side suffix.

    Returns
    -------
    dict of str -> list of (normal, offset)
        One half-space per bone (``normal . p > offset``, LPS), empty when the
        stations' slice axes differ.
    """
    cuts = unseen_ends({n: m for n, m in extracted.items() if n[:-2] in bones}, seeds, vols, processes=bones)
    out = {}
    for name, hs in cuts.items():
        line = np.asarray(seeds[name], float).reshape(-1, 3)
        # the distal one, toward the polyline's last point (a search's cut at the proximal end may come with it)
        distal = [(n, c) for n, c in hs if float((line[-1] - line[0]) @ n) > 0]
        if distal:
            out[name] = distal
    return out


def _spine_from_discs(vols: list[Volume], qc: dict | None = None):
    """The warp's ``refine_chain``: the vertebrae between the pelvis and the skull put on the discs the
    stations show (:func:`bonecap.segmentation.spine.spine_levels`); ``qc`` gets its profile."""
    from bonecap.segmentation.spine import is_disc_joint, spine_levels

    def refine(joint_bones: list[list[str]], points: np.ndarray):
        try:
            return spine_levels(vols, points, [is_disc_joint(b) for b in joint_bones], profile_out=qc)
        except ValueError as exc:      # an odd chain (two joints at one place): the spread stays, said why
            return None, {"used": False, "reason": str(exc)}
    return refine


def warp_targets(targets: dict[str, Mesh], trusted: bool) -> dict[str, Mesh]:
    """The extractions the warp takes as bones' own targets.

    The density rule's bones (:func:`bonecap.segmentation.bones.default_rule`)
    are carried by their neighbours unless the extraction is ``trusted`` (the
    user's seeds or label map): at whole-body resolution the rule's regions
    cover 0.2-0.8 of such a bone (Dice against the oracle on phantoms), and
    where one passed the plausibility checks (a sacrum at Dice 0.72-0.78, once
    its seed ran through its sections) its warp dragged the pelvis and the
    bones carried from it (a phantom's bone origins, median over the trials,
    2.32 -> 7.71 mm; its marker binding 2.32 -> 3.62 mm).

    Parameters
    ----------
    targets : dict of str -> Mesh
        Plausible extractions (:func:`_plausible_targets`).
    trusted : bool

    Returns
    -------
    dict of str -> Mesh
    """
    from bonecap.segmentation.bones import default_rule

    return dict(targets) if trusted else {n: m for n, m in targets.items() if default_rule(n) != "density"}


def _plausible_targets(template: Skeleton, extracted: dict[str, Mesh], strict: bool = True) -> dict[str, Mesh]:
    """Extracted meshes whose size and place fit the placed template bone.

    A wild one (two bones merged, a bone mistaken for its neighbour) would
    drag the warp: it is left out and the bone comes from its neighbours.
    """
    out = {}
    for name, m in extracted.items():
        b = template.bones.get(name)
        if b is None or b.mesh is None or len(m.faces) == 0:
            continue
        wt = template.world_mesh(name)
        v_t = abs(wt.to_trimesh().volume)
        v_e = abs(m.to_trimesh().volume)
        size = np.linalg.norm(np.ptp(wt.vertices, axis=0))
        shift = np.linalg.norm(wt.vertices.mean(0) - m.vertices.mean(0))
        # placed bone by bone, a bone's centroid is within a few centimetres;
        # placed by a similarity only (user seeds or labels), limbs may be far
        near = shift < (0.25 * size + 15.0 if strict else 0.5 * size + 20.0)
        if 0.5 < v_e / max(v_t, 1e-9) < 2.0 and near:
            out[name] = m
    return out


def _template_from_targets(template: Skeleton, extracted: dict[str, Mesh]) -> Skeleton:
    """The template placed on the extracted bones by a similarity fit of their centroids (LPS)."""
    from bonecap.scaling import similarity_fit

    names = [n for n in extracted if n in template.bones and template.bones[n].mesh is not None]
    if len(names) < 3:
        # too few bones to fit a similarity: orientation from the supine convention only
        c_e = np.mean([extracted[n].vertices.mean(0) for n in names], axis=0) if names else np.zeros(3)
        c_t = MODEL_TO_LPS[:3, :3] @ np.mean([template.world_mesh(n).vertices.mean(0) for n in names] or
                                             [np.zeros(3)], axis=0)
        T = MODEL_TO_LPS.copy()
        T[:3, 3] = c_e - c_t
        return _moved(template, T, 1.0)
    src = np.array([template.world_mesh(n).vertices.mean(0) for n in names])
    dst = np.array([extracted[n].vertices.mean(0) for n in names])
    s, T = similarity_fit(src, dst)
    T[:3, :3] /= s
    return _moved(template, T, s)


def _moved(template: Skeleton, T: np.ndarray, s: float) -> Skeleton:
    """The template scaled by ``s`` (about its own origin) then moved rigidly by ``T`` into LPS."""
    from bonecap.scaling import scale_skeleton

    scaled = scale_skeleton(template, {}, default=s)
    root = scaled.bones[scaled.names[0]].bone_to_world[:3, 3]
    # scale_skeleton keeps the root's origin: compensate so that p -> T(s p)
    shift = np.eye(4)
    shift[:3, 3] = (s - 1.0) * root
    M = T @ shift
    for b in scaled.bones.values():
        b.bone_to_world = M @ b.bone_to_world
    scaled.world = "lps"
    return scaled


def _placeable(template: Skeleton) -> bool:
    """Whether :func:`place_template` can place ``template``: the embedded skeleton's hip bones and joints
    (an OpenSim model names its bodies and joints otherwise: its pelvis holds both hips)."""
    return all(n in template.bones and "hip" in template.bones[n].joint_centres for n in ("hip_r", "hip_l"))


def place_template(template: Skeleton, vols: list[Volume], bodies: list[np.ndarray], top: float, bottom: float,
                   centre_at) -> tuple[Skeleton, dict[str, Any]]:
    """The template in LPS, scaled to the body's length, centred, and its limbs turned toward the MRI's.

    Each arm, with its scapula, is then moved along the body's axis onto the elbow the MRI shows
    (:func:`elbow_offsets`) and turned again.

    Returns the placed skeleton and a report (scale, shift, per-limb turns, the arms' moves).
    """
    a0 = template_to_body(template, top, bottom, np.zeros(3))
    hip = np.mean([template.bones[n].landmark_in_world("hip") for n in ("hip_r", "hip_l")], axis=0)
    hz = (a0[:3, :3] @ hip + a0[:3, 3])[2]
    A = template_to_body(template, top, bottom, centre_at(hz))
    s = float(np.cbrt(abs(np.linalg.det(A[:3, :3]))))
    T = A.copy()
    T[:3, :3] /= s
    posed = _moved(template, T, s)
    sections = _LimbSections(vols, bodies)
    # centre the legs in their thighs (the trunk's centroid is not the hips')
    offsets = []
    for side in "rl":
        f = posed.bones.get(f"femur_{side}")
        if f is None:
            continue
        mid = 0.5 * (f.landmark_in_world("hip") + f.landmark_in_world("knee"))
        c = sections.limb_centre(float(mid[2]), side, "leg")
        if c is not None:
            offsets.append(c - mid)
    shift = np.zeros(3)
    if offsets:
        shift[:2] = np.mean(offsets, axis=0)[:2]
        M = np.eye(4)
        M[:3, 3] = shift
        for b in posed.bones.values():
            b.bone_to_world = M @ b.bone_to_world
    turned = repose_limbs(posed, sections)
    # the arms' height from the elbows the MRI shows: the scapula and the arm moved along the body's axis
    # (the trunk's length is what the head-to-sole scale gets most wrong), then re-aimed. The clavicle
    # stays on the sternum: moved with them, the warp carried it 3-4.5 mm worse (a phantom's, moved 3-7 mm)
    elbows = elbow_offsets(posed, vols, bodies)
    for side, dz in elbows.items():
        root = _girdle_root(posed, side)
        if root is None:
            continue
        M = np.eye(4)
        M[2, 3] = dz
        for n in _subtree(posed, root):
            posed.bones[n].bone_to_world = M @ posed.bones[n].bone_to_world
    if elbows:
        # (the report keeps the arms' second turns, from where they were moved)
        turned.update(repose_limbs(posed, sections, chains=[c for c in LIMB_CHAINS if c[2] == "arm"]))
    return posed, {"scale": s, "shift_mm": shift.tolist(), "limb_turns_deg": turned,
                   "elbow_shift_mm": {k: round(v, 1) for k, v in elbows.items()}}


def reframe_subject(subject, frames: dict[str, np.ndarray]) -> None:
    """Describe bones of a subject in new frames, in place; nothing moves in world.

    Each bone's meshes, landmarks and joints (:func:`bonecap.skeleton.isb.reframe_bone`), the markers
    bound to it, its solved static pose (``subject.static["bone_to_lab"]``) and, for an ulna, the radius's
    axis of a fitted forearm model (``radius_axis_ulna_mm``) are re-expressed in ``frames[bone]``
    (bone-to-world, the skeleton's world frame).
    """
    from bonecap.skeleton.isb import reframe_bone
    from bonecap.subject import MarkerBinding

    sk = subject.skeleton
    for b, T_new in frames.items():
        if b not in sk.bones:
            raise ValueError(f"reframe_subject: no bone {b!r} in the skeleton")
        T_old = sk.bones[b].bone_to_world
        C = np.linalg.solve(T_new, T_old)                   # old bone frame -> new bone frame
        for n, m in list(subject.markers.items()):
            if m.bone == b:
                subject.markers[n] = MarkerBinding(n, b, C[:3, :3] @ m.local + C[:3, 3], m.source, m.weight)
        static = (subject.static or {}).get("bone_to_lab") or {}
        if b in static:
            static[b] = np.asarray(static[b], float) @ np.linalg.inv(C)
        for side, model in (subject.forearm or {}).items():
            # the radius's axis the forearm stacks measured is held in the ulna's frame
            if b == f"ulna_{side}" and len(model.get("radius_axis_ulna_mm") or ()) == 6:
                ends = np.reshape(model["radius_axis_ulna_mm"], (2, 3)) @ C[:3, :3].T + C[:3, 3]
                model["radius_axis_ulna_mm"] = ends.ravel().tolist()
        sk.bones[b] = reframe_bone(sk.bones[b], T_new)


def _station_capsules(vols: list[Volume]) -> np.ndarray:
    """Capsule centres (LPS mm) found in the stations, one for each capsule the overlaps show twice."""
    from bonecap.segmentation.capsules import find_capsules

    found = [find_capsules(v)[0] for v in vols]
    centres = np.concatenate([c for c in found if len(c)]) if any(len(c) for c in found) else np.zeros((0, 3))
    # a capsule in the overlap of two stations is found in both: one capsule
    return _merge_close(centres, 4.0)


def _place_and_bind(subject, mset, vols, bodies, static_trial, static_path, functional=(),
                    capsule_search=None) -> dict[str, Any]:
    """Markers on the personal skin over their landmarks; capsules where found; the static trial binds.

    ``functional``: ``(trial, path)`` of movement trials whose knee flexion corrects the femurs' twist
    (:func:`bonecap.build_subject.knee_flexion_twist`). ``capsule_search``: the join of
    :func:`_station_capsules` of ``vols`` started earlier (else the stations are searched here)."""
    from bonecap.build_subject import (CAPSULE_STATIC_TOLERANCE_MM, FOOT_AXES, FOOT_PREFIXES, HAND_AXES,
                                       HAND_PREFIXES, STATIC_ROBUST_ROUNDS, bind_static, capsule_static_disagreement, functional_twists,
                                       joint_consistent, neutral_twist, pose_to_static, pronate_on_ulna,
                                       rhythm_consistent, static_markers, turn_femurs)
    from bonecap.markers import place_markers
    from bonecap.motion.lsq import plan_segments
    from bonecap.subject import MarkerBinding

    sk = subject.skeleton
    # optional markers (SACR in Plug-in Gait) are bound only if the static trial has them
    in_static = set()
    if static_trial is not None:
        from bonecap.markers import match_labels

        in_static = set(match_labels(mset, static_trial.labels))
    names = [n for n, m in mset.markers.items() if not m.virtual and (not m.optional or n in in_static)]
    placed = place_markers(mset, sk, names)
    placed = _onto_skin(placed, subject.skin, sk, mset)
    report: dict[str, Any] = {}
    # capsules
    centres = capsule_search() if capsule_search is not None else _station_capsules(vols)
    capsule_names = name_capsules(centres, placed)
    report["capsules_found"] = int(len(centres))
    report["capsules_matched"] = sorted(capsule_names)
    if capsule_names and subject.skin is not None:
        capsule_names = capsules_to_markers(capsule_names, subject.skin)
        # the hands the scan did not measure: sized onto their capsules, then their
        # markers placed again and every capsule named again (a finger capsule that lay too far
        # from its marker, or was taken by another's, on the template's hand is found now)
        sk, posed = pose_from_capsules(sk, mset, capsule_names)
        subject.skeleton = sk
        report["capsule_posed_segments"] = {
            r: {k: round(v, 2) if isinstance(v, float) else v for k, v in d.items()} for r, d in posed.items()}
        turned = [r for r, d in posed.items() if d["applied"]]
        if turned:
            moved = {b for r in turned for b in _subtree(sk, r)}
            again = [n for n in names if mset.markers[n].bone in moved]
            placed.update(_onto_skin(place_markers(mset, sk, again), subject.skin, sk, mset))
            capsule_names = capsules_to_markers(name_capsules(centres, placed), subject.skin)
            report["capsules_matched"] = sorted(capsule_names)
    landmark_local = {}     # over the landmarks, for a capsule binding the static refutes
    for n in names:
        m = mset.markers[n]
        T = sk.bones[m.bone].bone_to_world
        landmark_local[n] = T[:3, :3].T @ (placed[n] - T[:3, 3])
        p = capsule_names.get(n, placed[n])
        subject.markers[n] = MarkerBinding(n, m.bone, T[:3, :3].T @ (p - T[:3, 3]),
                                           "capsule" if n in capsule_names else "placed")
    if static_trial is not None:
        snames, lab = static_markers(static_trial, mset, path=static_path)
        bones = [subject.markers[n].bone for n in snames]

        # The shank's twist about its long axis hangs on one shank marker placed over a landmark-less
        # shaft (10-12 deg of error on the phantom). Where no capsule measured the shank's markers, the
        # knee's axial rotation is taken from the MRI: in full extension the knee is locked (screw-home)
        # lying as standing, so the tibia keeps its MRI twist relative to the femur. The hip and the
        # shoulder are not locked (legs roll outward supine, the arms are abducted in the static): their
        # twist stays the markers'.
        def unmeasured(bones_of):
            """Those of ``bones_of`` (bone -> the bones whose markers count) that carry a marker no capsule measured."""
            return [b for b, group in bones_of.items() if b in sk.bones and any(
                subject.markers[n].bone in group and subject.markers[n].source != "capsule" for n in snames)]

        def shanks_unmeasured():
            return unmeasured({t: (t, t.replace("tibia", "fibula")) for t in ("tibia_r", "tibia_l")})

        def chain(solved):
            if guessed:
                solved = neutral_twist(sk, solved, tuple(guessed))
            # each radius turned on its ulna about the forearm's axis to its markers (its own twist, hung
            # on a dorsal marker over soft tissue, was 2-9 deg off on phantoms; the hand's follows it)
            solved, turns = pronate_on_ulna(sk, solved, bones, local, lab)
            report["static_radius_turn_deg"] = {k: round(v, 2) for k, v in turns.items()}
            # the hand's twist is the radius's (the wrist turns no way about its long axis), and the foot's
            # roll about its long axis is not observable from heel and toe: the shank's (Plug-in Gait)
            solved = neutral_twist(sk, solved, HAND_PREFIXES, HAND_AXES)
            solved = neutral_twist(sk, solved, FOOT_PREFIXES, FOOT_AXES)
            return joint_consistent(sk, rhythm_consistent(sk, bones, solved))

        def solve_static():
            local = np.array([subject.markers[n].local for n in snames])
            # reweighted: a few markers placed 10-25 mm off by the placement rule must not tilt a segment
            return local, pose_to_static(sk, bones, local, lab, robust_rounds=STATIC_ROBUST_ROUNDS)

        local, solved = solve_static()
        guessed = shanks_unmeasured()
        poses = chain(solved)
        # A capsule binds its marker to the bone as the bone lies in the MRI: right where the scan measured
        # the bone, a guess where it did not (hands and feet carried at the template's wrist and ankle
        # angles). Capsule markers keep their MRI binding unless their segment, one the scan did not measure, has
        # a pattern that does not fit the static (then the whole segment is bound from the static, as markers
        # without capsules are).
        caps_in_static = {n for n in snames if subject.markers[n].source == "capsule"}
        if caps_in_static:
            # only segments the scan did not measure (a hand, a foot): bound from the static instead, seed 3's
            # trunk capsules (4.4 mm RMS from the static) had left the trunk 2.4 deg off in every trial
            rms, flagged = capsule_static_disagreement(sk, snames, bones, local, lab, poses, caps_in_static,
                                                       scanned_bones=SEGMENTED_BONES)
            report["capsule_static_rms_mm"] = {r: round(v, 2) for r, v in rms.items()}
            report["capsule_segments_refuted_but_scanned"] = sorted(
                r for r, v in rms.items() if v > CAPSULE_STATIC_TOLERANCE_MM and r not in flagged)
            report["capsule_segments_bound_from_static"] = flagged
            if flagged:
                plan = plan_segments(sk, bones)
                for n, b in zip(snames, bones):
                    if n in caps_in_static and plan.segments[plan.segment_of[b]].root in flagged:
                        subject.markers[n] = MarkerBinding(n, b, landmark_local[n], "placed")
                        caps_in_static.discard(n)
                local, solved = solve_static()
                guessed = shanks_unmeasured()
                poses = chain(solved)
        report["static_knee_twist_from_mri"] = guessed

        def bind(poses):
            """The static's markers bound at ``poses``; capsule bindings kept."""
            return {n: b for n, b in bind_static(sk, snames, bones, lab, poses).items() if n not in caps_in_static}

        bound = bind(poses)
        placed_local = {n: subject.markers[n].local for n in bound}
        if functional:
            # the femur's twist from the knee's flexion axis in the movement trials, where no capsule
            # measured the thigh's markers (a capsule puts them within a millimetre of the truth)
            guessed_f = unmeasured({f: (f, f.replace("femur", "patella")) for f in ("femur_r", "femur_l")})
            subject.markers.update(bound)
            twists = functional_twists(subject, functional)
            report["functional_knee_twist"] = {f: {k: round(v, 2) for k, v in d.items()} for f, d in twists.items()}
            turn = {f: d["twist_deg"] for f, d in twists.items() if f in guessed_f}
            if turn:
                poses = chain(turn_femurs(sk, solved, turn))
                bound = bind(poses)
            report["functional_femur_turned_deg"] = {f: round(v, 2) for f, v in turn.items()}
        moved = {n: float(np.linalg.norm(bound[n].local - placed_local[n])) for n in bound}
        subject.markers.update(bound)
        report["static_binding_shift_mm"] = {k: round(v, 2) for k, v in moved.items()}
        report["markers_missing_in_static"] = [n for n in names if n not in bound and n not in caps_in_static]
        subject.static = {"trial": str(static_path), "markers_lab": {n: p for n, p in zip(snames, lab)},
                          "bone_to_lab": {b: poses[i] for i, b in enumerate(sk.names)
                                          if np.isfinite(poses[i]).all()}}
    report["markers_bound"] = len(subject.markers)
    return report


#: Segments the whole-body scan does not measure (no carpal is in :data:`SEGMENTED_BONES`: too small at
#: its resolution), carried into the MRI at the template's wrist angle and size from their neighbours'
#: warps: the root bone of each; its subtree turns and scales with it. Not the feet: with a heel and a
#: toe capsule only, the fit left them 4-10 mm RMS from their capsules on phantoms of seeds 1-3 (the
#: warped heel 15-34 deg from where its capsule points) and turned seed 2's right foot 2.3 -> 3.5 deg
#: away from the truth.
CAPSULE_POSED_ROOTS = ("carpals_r", "carpals_l")
#: What :func:`pose_from_capsules` accepts: a turn about the proximal joint up to ``CAPSULE_POSE_MAX_DEG``,
#: a size factor within ``CAPSULE_POSE_SCALE``, and capsules left within ``CAPSULE_POSE_MAX_RMS_MM`` (RMS)
#: of the segment's placed markers. Beyond any of them the capsules are not the segment's own (a misnamed
#: capsule, a foot the warp lost) and the segment stays as the warp left it.
CAPSULE_POSE_MAX_DEG = 30.0
CAPSULE_POSE_SCALE = (0.8, 1.25)
CAPSULE_POSE_MAX_RMS_MM = 6.0
#: Whether :func:`pose_from_capsules` applies the turn it fits, or only the size. The placed markers'
#: pattern is the template's (landmark plus the set's soft-tissue offset); a subject's own pattern, a few
#: millimetres different over a hand's ~70 mm of markers, turned the fit 1.8-2.9 deg (three capsule
#: phantoms), and the hands' frames at the MRI pose went from 0.7-1.9 deg off (turned into the skin,
#: :func:`pose_inside_skin`) to 1.4-3.2 deg: every trial carries that turn through the capsules' binding.
CAPSULE_POSE_TURN = False


#: Segments the scan images only as skin (no bone rule resolves a hand at whole-body resolution): turned
#: about their proximal joint until their bones lie under the skin (:func:`pose_inside_skin`).
SKIN_POSED_ROOTS = ("carpals_r", "carpals_l")
#: What :func:`pose_inside_skin` asks and accepts: bone at least ``SKIN_POSE_MARGIN_MM`` under the skin; a
#: turn up to ``SKIN_POSE_MAX_DEG``; at least ``SKIN_POSE_MIN_INSIDE`` of the segment's surface under the
#: skin before the fit (less: the hand is not in the scan, or not where the warp put it).
SKIN_POSE_MARGIN_MM = 2.0
SKIN_POSE_MAX_DEG = 30.0
SKIN_POSE_MIN_INSIDE = 0.5
#: The turn (deg) whose reach :func:`pose_inside_skin` samples the skin's distance over first; a fit that
#: turns beyond 80 % of it is done again over the reach of ``max_deg``. The hands of six phantom builds
#: turned 0.1-2.9 deg.
SKIN_POSE_FIRST_DEG = 10.0


def pose_inside_skin(skeleton: Skeleton, skin: Mesh, roots: tuple[str, ...] = SKIN_POSED_ROOTS, *,
                     margin_mm: float = SKIN_POSE_MARGIN_MM, max_deg: float = SKIN_POSE_MAX_DEG,
                     min_inside: float = SKIN_POSE_MIN_INSIDE, voxel_mm: float = 2.0, prior: float = 100.0
                     ) -> tuple[Skeleton, dict[str, dict[str, float]]]:
    """Segments the scan shows only as skin (the hands), turned about their proximal joint into it.

    The personal skeleton carries a hand from the forearm's warp at the
    template's wrist angle: on three phantom subjects its frame lay 3.1-5.9 deg
    from the truth at the MRI pose, and 11-37 % of its bones' surface lay
    outside the personal skin or less than 2 mm under it, where no bone can be. The
    skin of a whole-body scan does hold the hand (the arms lie at the sides):
    the segment (the root and its subtree) is turned about the root's proximal
    joint centre on its parent (the radius's wrist, which the scan measured)
    by the rotation that puts its surface at least ``margin_mm`` under the skin,
    in the least-squares sense (the depth missing at each surface point; a
    weak pull, ``prior``, towards no turn decides what the skin leaves free).
    The skin's signed distance is sampled on a ``voxel_mm`` grid around the
    segment (:func:`bonecap.phantom.render.voxelise_labels`, then Euclidean
    distance transforms). Capsules, where found, size the result
    (:func:`pose_from_capsules`).

    Parameters
    ----------
    skeleton : Skeleton
        The personal skeleton at the MRI pose, in the skin's world (LPS mm).
    skin : Mesh
        The personal skin, closed.
    roots : tuple of str
        Segment roots; missing ones, or those without meshes, are left alone.
    margin_mm, max_deg, min_inside : float
        Depth asked of the bone under the skin; the largest turn applied; the
        smallest fraction of the segment's surface inside the skin before the
        fit for a fit to be tried.
    voxel_mm, prior : float
        Grid of the distance field; weight of the pull towards no turn (per
        rad^2, against the mean squared missing depth in mm^2).

    Returns
    -------
    skeleton : Skeleton
        A copy with the fitted segments turned (the input is not changed).
    report : dict of str -> dict
        Per root considered: ``turn_deg``, ``inside_before`` and ``shallow_before`` /
        ``shallow_after`` (fractions of the surface inside the skin, and less than
        ``margin_mm`` under it) and ``applied`` (1.0 or 0.0).
    """
    import dataclasses

    from scipy import ndimage
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    from bonecap.phantom.render import voxelise_labels
    from bonecap.skeleton.kinematics import proximal_joint

    if not (margin_mm >= 0 and max_deg > 0 and 0 <= min_inside <= 1 and voxel_mm > 0 and prior >= 0):
        raise ValueError(f"pose_inside_skin: margin_mm >= 0, max_deg > 0, min_inside in [0, 1], voxel_mm > 0 and "
                         f"prior >= 0 expected, got {margin_mm!r}, {max_deg!r}, {min_inside!r}, {voxel_mm!r}, "
                         f"{prior!r}")
    # a new skeleton sharing the bones it does not turn (their meshes are large; nothing else changes)
    out_sk = Skeleton(bones=dict(skeleton.bones), world=skeleton.world, metadata=dict(skeleton.metadata))
    report: dict[str, dict[str, float]] = {}
    for root in roots:
        if root not in skeleton.bones or skeleton.bones[root].parent is None:
            continue
        members = _subtree(skeleton, root)
        bones = [b for b in members if skeleton.bones[b].mesh is not None]
        if not bones:
            continue
        V = np.concatenate([skeleton.world_mesh(b).vertices for b in bones])
        _, c_par, _ = proximal_joint(skeleton, root)
        Tp = skeleton.bones[skeleton.bones[root].parent].bone_to_world
        centre = Tp[:3, :3] @ c_par + Tp[:3, 3]
        radius = float(np.linalg.norm(V - centre, axis=1).max())
        # the skin's signed distance (positive inside) on a grid over the segment and the room it may turn
        # in: the grid for max_deg, of which only the box a turn of SKIN_POSE_FIRST_DEG can reach is filled
        # first (a fifth of the voxels; the distance transforms were 3 of the 4 s), the whole one only
        # when the fit turns further (the same lattice: the box's values are the grid's wherever a
        # surface point's depth matters, within the margin of the skin)
        reach = radius * np.sin(np.radians(max_deg)) + 10.0
        lo = V.min(axis=0) - reach
        shape = np.ceil((V.max(axis=0) + reach - lo) / voxel_mm).astype(int) + 1

        def depth_field(deg: float):
            r = radius * np.sin(np.radians(deg)) + 10.0
            i0 = np.clip(np.floor((V.min(axis=0) - r - lo) / voxel_mm).astype(int), 0, shape - 1)
            i1 = np.clip(np.ceil((V.max(axis=0) + r - lo) / voxel_mm).astype(int) + 1, i0 + 1, shape)
            o = lo + i0 * voxel_mm
            A = np.eye(4)
            A[:3, :3] *= voxel_mm
            A[:3, 3] = o
            inside = voxelise_labels([(skin, 1)], A, tuple(int(n) for n in i1 - i0), inplane_supersample=1,
                                     through_plane_samples=1) > 0
            sdf = (ndimage.distance_transform_edt(inside) - ndimage.distance_transform_edt(~inside)) * voxel_mm
            return lambda Q: ndimage.map_coordinates(sdf, ((Q - o) / voxel_mm).T, order=1, mode="nearest")

        def turned(x: np.ndarray) -> np.ndarray:
            return (V - centre) @ Rotation.from_rotvec(x).as_matrix().T + centre

        def residuals(x: np.ndarray) -> np.ndarray:
            return np.concatenate([np.maximum(0.0, margin_mm - depth(turned(x))) / np.sqrt(len(V)),
                                   np.sqrt(prior) * x])

        first = min(SKIN_POSE_FIRST_DEG, max_deg)
        depth = depth_field(first)
        d0 = depth(V)
        rep = {"inside_before": round(float(np.mean(d0 > 0)), 3),
               "shallow_before": round(float(np.mean(d0 < margin_mm)), 3), "applied": 0.0}
        report[root] = rep
        if rep["inside_before"] < min_inside:
            continue
        for deg in (first, max_deg):
            # (residuals reads ``depth`` when called: the field of this round)
            x = least_squares(residuals, np.zeros(3), diff_step=1e-4, max_nfev=200).x
            if np.degrees(np.linalg.norm(x)) <= 0.8 * deg or deg >= max_deg:
                break
            depth = depth_field(max_deg)
        rep["turn_deg"] = round(float(np.degrees(np.linalg.norm(x))), 2)
        rep["shallow_after"] = round(float(np.mean(depth(turned(x)) < margin_mm)), 3)
        if rep["turn_deg"] <= max_deg and rep["shallow_after"] < rep["shallow_before"]:
            for b in members:
                out_sk.bones[b] = dataclasses.replace(skeleton.bones[b],
                                                      bone_to_world=skeleton.bones[b].bone_to_world.copy())
            _rotate_about(out_sk, members, centre, Rotation.from_rotvec(x).as_matrix())
            rep["applied"] = 1.0
    return out_sk, report


def _scale_about(skeleton: Skeleton, bones: list[str], centre: np.ndarray, s: float) -> Skeleton:
    """A copy of ``skeleton`` with ``bones`` scaled by ``s`` about ``centre`` (world): each one's mesh,
    landmarks and joint centres about its own origin, its origin moved towards or away from ``centre``
    (frames' orientations kept; the other bones are shared with the input, untouched)."""
    import dataclasses

    from bonecap.scaling import _scaled_mesh

    new = dict(skeleton.bones)
    for n in bones:
        b = skeleton.bones[n]
        T = b.bone_to_world.copy()
        T[:3, 3] = centre + s * (T[:3, 3] - centre)
        new[n] = dataclasses.replace(
            b, mesh=_scaled_mesh(b.mesh, s), inner_mesh=_scaled_mesh(b.inner_mesh, s), bone_to_world=T,
            joint_centres={k: v * s for k, v in b.joint_centres.items()},
            landmarks={k: v * s for k, v in b.landmarks.items()},
            metadata={**b.metadata, "scale_factor": float(b.metadata.get("scale_factor", 1.0)) * s})
    return dataclasses.replace(skeleton, bones=new, metadata=dict(skeleton.metadata))


def pose_from_capsules(skeleton: Skeleton, marker_set, markers: dict[str, np.ndarray],
                       roots: tuple[str, ...] = CAPSULE_POSED_ROOTS, *, max_deg: float = CAPSULE_POSE_MAX_DEG,
                       scale_limits: tuple[float, float] = CAPSULE_POSE_SCALE,
                       max_rms_mm: float = CAPSULE_POSE_MAX_RMS_MM, iterations: int = 3,
                       turn: bool = CAPSULE_POSE_TURN) -> tuple[Skeleton, dict[str, dict[str, float]]]:
    """Segments the scan did not measure (the hands), sized (and turned) onto the capsules found on them.

    The personal skeleton carries a hand from its neighbours' warps at the
    template's wrist angle and size (the mission's "hands from markers"): on
    phantoms of seeds 1-3 the hands lay 3-6 deg from the truth in the MRI and
    were up to 9 % small, and every capsule bound to them carried that into
    every trial. The capsules measure where the segment's
    markers really were: the segment (the root and its subtree) is scaled and
    turned about its proximal joint's centre on the parent (the radius's
    wrist, the tibia's ankle: bones the scan did measure) by the similarity
    that best takes its placed markers (landmark plus the set's soft-tissue
    offset, :func:`bonecap.markers.place_markers`) onto the capsule-measured
    ones (Kabsch about a fixed centre [1]_, then the least-squares factor).
    The offsets do not scale with the bone, so the fit is repeated on the
    re-placed markers (``iterations``). By default only the fit's size factor
    is applied (``turn``, :data:`CAPSULE_POSE_TURN`): the turn is measured and
    checked, but the hand's orientation stays the skin's.

    Parameters
    ----------
    skeleton : Skeleton
        The personal skeleton at the MRI pose (LPS mm).
    marker_set : MarkerSet
    markers : dict of str -> ndarray (3,)
        Marker centres measured by capsules (:func:`capsules_to_markers`), same frame.
    roots : tuple of str
        Segment roots to fit; those missing from the skeleton, or with fewer
        than two capsule markers (or all in line with the joint), are left alone.
    max_deg, scale_limits, max_rms_mm : float, (float, float), float
        The fit is applied only if its total turn is at most ``max_deg``, its
        factor within ``scale_limits`` and the markers' RMS distance from their
        capsules after it at most ``max_rms_mm`` and smaller than before.
    iterations : int
        Fit, apply, place again: rounds (>= 1).
    turn : bool
        Apply the fitted turn too (else the size factor only).

    Returns
    -------
    skeleton : Skeleton
        A new skeleton (the input is not changed) with the fitted segments
        scaled about the joint (meshes, landmarks and joint centres follow) and,
        with ``turn``, turned; the other bones are the input's.
    report : dict of str -> dict
        Per root considered: ``turn_deg`` (the fitted turn, applied or not), ``scale``,
        ``rms_before_mm``, ``rms_fit_mm`` (after the fitted similarity, what
        the limits check), ``rms_after_mm`` (after what was applied), ``markers``
        (how many fitted) and ``applied`` (1.0 or
        0.0); ``dropped``, the marker left out, where the fit with all of them
        failed and one without one of them (of four or more) passed: a capsule
        named for the wrong marker.

    References
    ----------
    .. [1] Kabsch W (1976). Acta Cryst A32:922-923.
    """
    from scipy.spatial.transform import Rotation

    from bonecap.markers import place_markers
    from bonecap.skeleton.kinematics import proximal_joint
    from bonecap.skeleton.warp import _kabsch

    if not (max_deg > 0 and max_rms_mm > 0 and 0 < scale_limits[0] <= 1.0 <= scale_limits[1]):
        raise ValueError(f"max_deg and max_rms_mm must be positive and scale_limits bracket 1, got "
                         f"{max_deg!r}, {max_rms_mm!r}, {scale_limits!r}")
    if int(iterations) < 1:
        raise ValueError(f"iterations must be >= 1, got {iterations!r}")
    out: dict[str, dict[str, float]] = {}
    for root in roots:
        if root not in skeleton.bones or skeleton.bones[root].parent is None:
            continue
        bones = _subtree(skeleton, root)
        names = [n for n, q in markers.items() if n in marker_set.markers
                 and marker_set.markers[n].bone in bones and marker_set.markers[n].location is None
                 and np.isfinite(np.asarray(q, float)).all()]
        if len(names) < 2:
            continue
        _, c_par, _ = proximal_joint(skeleton, root)
        Tp = skeleton.bones[skeleton.bones[root].parent].bone_to_world
        centre = Tp[:3, :3] @ c_par + Tp[:3, 3]

        def fit(use: list[str]):
            """Fit, apply, place again (``iterations`` rounds) on the markers ``use``."""
            B = np.array([markers[n] for n in use], float) - centre

            def vectors(sk: Skeleton) -> np.ndarray:
                placed = place_markers(marker_set, sk, use)
                return np.array([placed[n] for n in use]) - centre

            A = vectors(skeleton)
            rms0 = float(np.sqrt(np.mean(np.sum((A - B) ** 2, axis=1))))
            if np.linalg.svd(A, compute_uv=False)[1] < 1e-3 * np.linalg.norm(A):
                return None                   # in line with the joint: the turn about that line is free
            fitted, R_tot, s_tot, R_open = skeleton, np.eye(3), 1.0, np.eye(3)
            for _ in range(int(iterations)):
                M = _kabsch(A, B, scale=True, centred=False)[:3, :3]          # s R
                s = float(np.cbrt(np.linalg.det(M)))
                R = M / s if s > 0 else M
                if not (np.isfinite(s) and s > 0):
                    break
                fitted = _scale_about(fitted, bones, centre, s)
                s_tot *= s
                if turn:
                    _rotate_about(fitted, bones, centre, R)
                    R_tot = R @ R_tot
                else:
                    R_open = R        # the turn still between the sized markers and the capsules
                A = vectors(fitted)
            rms1 = float(np.sqrt(np.mean(np.sum((A - B) ** 2, axis=1))))
            rms_fit = rms1 if turn else float(np.sqrt(np.mean(np.sum((A @ R_open.T - B) ** 2, axis=1))))
            deg = float(np.degrees(Rotation.from_matrix(R_tot if turn else R_open).magnitude()))
            ok = (deg <= max_deg and scale_limits[0] <= s_tot <= scale_limits[1] and rms_fit <= max_rms_mm
                  and rms_fit < rms0)
            return fitted, {"turn_deg": deg, "scale": s_tot, "rms_before_mm": rms0, "rms_fit_mm": rms_fit,
                            "rms_after_mm": rms1, "markers": float(len(use)), "applied": float(ok)}

        res = fit(names)
        if res is None:
            continue
        dropped = None
        if not res[1]["applied"] and len(names) >= 4:
            # one capsule named for the wrong marker (seed 1's left hand: the ring finger's DIP marker,
            # placed 23 mm from its own capsule, took the index finger's) spoils the fit: the best fit
            # without one of them, if that one passes
            trials = [(n, fit([m for m in names if m != n])) for n in names]
            trials = [(n, r) for n, r in trials if r is not None and r[1]["applied"]]
            if trials:
                dropped, res = min(trials, key=lambda t: t[1][1]["rms_fit_mm"])
        fitted, row = res
        if row["applied"]:
            skeleton = fitted
        out[root] = {**row, **({"dropped": dropped} if dropped else {})}
    return skeleton, out


def name_capsules(centres: np.ndarray, placed: dict[str, np.ndarray], near_mm: float = 25.0,
                  far_mm: float = 45.0) -> dict[str, np.ndarray]:
    """Which found capsule marks which marker: two one-to-one passes, near first.

    The first pass (:func:`bonecap.segmentation.capsules.match_capsules`, within
    ``near_mm``) settles the markers placed close to their capsules; the markers
    it left get a second pass within ``far_mm`` among the capsules it left
    (a heel, C7 or the clavicle were placed 25-32 mm from their capsules on the
    phantom). Settling the close pairs first keeps the wider reach from taking
    a capsule away from its own marker.

    Parameters
    ----------
    centres : ndarray (N, 3)
        Capsule centres (LPS mm), duplicates from station overlaps merged.
    placed : dict of str -> ndarray (3,)
        Each marker's expected position (LPS mm), e.g. on the personal skin.

    Returns
    -------
    dict of str -> ndarray (3,)
        Marker name -> its capsule's centre.
    """
    from bonecap.segmentation.capsules import match_capsules

    centres = np.asarray(centres, float).reshape(-1, 3)
    if not len(centres) or not placed:
        return {}
    named = match_capsules(centres, placed, max_distance_mm=near_mm)
    used = {tuple(c) for c in named.values()}
    rest_c = np.array([c for c in centres if tuple(c) not in used]).reshape(-1, 3)
    rest_m = {n: p for n, p in placed.items() if n not in named}
    if len(rest_c) and rest_m:
        named.update(match_capsules(rest_c, rest_m, max_distance_mm=far_mm))
    return named


def _merge_close(points: np.ndarray, tol_mm: float) -> np.ndarray:
    """Points closer than ``tol_mm`` to each other merged into their mean (single linkage)."""
    from scipy.cluster.hierarchy import fcluster, linkage

    points = np.asarray(points, float).reshape(-1, 3)
    if len(points) < 2:
        return points
    groups = fcluster(linkage(points, method="single"), t=tol_mm, criterion="distance")
    return np.array([points[groups == g].mean(axis=0) for g in np.unique(groups)])


def capsules_to_markers(capsules: dict[str, np.ndarray], skin: Mesh, *, capsule_radius_mm: float = 4.0,
                        marker_radius_mm: float = 7.0, normal_radius_mm: float = 12.0) -> dict[str, np.ndarray]:
    """Marker centres from the MRI capsules that marked their spots (Kojima et al.'s protocol).

    A capsule and the motion-capture marker that replaces it rest on the
    same spot of skin, each with its centre one own radius out along the skin
    normal: the marker is ``marker_radius_mm - capsule_radius_mm`` farther out
    (3 mm for 8 mm capsules and 14 mm markers). The normal is the mean of the
    skin's vertex normals within ``normal_radius_mm`` of the capsule, so the
    bump the capsule itself may leave on the skin mask does not tilt it. The
    ball must stay small against the body part's own curvature: a finger is
    about 9 mm in radius, and a 20 mm ball took in the whole finger and its
    neighbours (markers on the finger joints 1.2-1.35 mm off, median over
    three phantoms, from the true capsule centres; 0.6-0.8 mm with 12 mm).

    Parameters
    ----------
    capsules : dict name -> (3,)
        Capsule centres (LPS mm), named by :func:`~bonecap.segmentation.capsules.match_capsules`.
    skin : Mesh
        The personal skin, same frame, outward normals.

    Returns
    -------
    dict name -> ndarray (3,)
        Marker centres.
    """
    from scipy.spatial import cKDTree

    import trimesh

    tm = trimesh.Trimesh(skin.vertices, skin.faces, process=False)
    vn = tm.vertex_normals
    tree = cKDTree(tm.vertices)
    out = {}
    for name, c in capsules.items():
        c = np.asarray(c, float)
        idx = tree.query_ball_point(c, normal_radius_mm)
        if not idx:
            idx = [int(tree.query(c)[1])]
        n = vn[idx].mean(axis=0)
        norm = np.linalg.norm(n)
        out[name] = c + (marker_radius_mm - capsule_radius_mm) * n / norm if norm > 1e-6 else c
    return out


def _onto_skin(placed: dict[str, np.ndarray], skin: Mesh | None, sk: Skeleton, mset, marker_radius_mm: float = 7.0,
               snap_mm: float = 40.0) -> dict[str, np.ndarray]:
    """Move each placed marker to the personal skin plus the marker's radius, along the landmark's normal.

    The marker set's ``offset_mm`` is a typical tissue depth; with MRI we
    measure the real one: the ray from the landmark through the guessed
    marker position meets the skin, and the marker sits one radius beyond.
    A ray that meets no skin within 8 cm (the bone surface's normal at a
    notch, the jugular notch's, points into the neck) leaves the marker at
    the skin point nearest its guessed position, if that lies within
    ``snap_mm``: it had stayed inside the body, 30 mm behind the skin (CLAV on
    every phantom). A guess outside the skin, or farther than that from it
    (the hands of a whole-body scan), stays.
    """
    if skin is None:
        return placed
    import trimesh

    tm = trimesh.Trimesh(skin.vertices, skin.faces, process=False)
    names = list(placed)
    origins, dirs = [], []
    for n in names:
        m = mset.markers[n]
        b = sk.bones[m.bone]
        lm = (b.landmarks.get(m.landmark) if m.landmark in b.landmarks else b.joint_centres.get(m.landmark)) \
            if m.landmark else None
        o = b.bone_to_world[:3, :3] @ lm + b.bone_to_world[:3, 3] if lm is not None else placed[n]
        d = placed[n] - o
        nd = np.linalg.norm(d)
        origins.append(o)
        dirs.append(d / nd if nd > 1e-6 else np.array([0.0, 0.0, 1.0]))
    origins, dirs = np.array(origins), np.array(dirs)
    out = dict(placed)
    try:
        locs, ray_idx, tri = tm.ray.intersects_location(origins, dirs, multiple_hits=False)
    except Exception:  # noqa: BLE001 - no ray engine: keep the manual's depths
        return placed
    hit = np.zeros(len(names), bool)
    for loc, r, f in zip(locs, ray_idx, tri):
        depth = np.linalg.norm(loc - origins[r])
        if depth < 80.0:  # a hit beyond 8 cm is another body part (the other leg, an arm)
            # the marker rests on the skin: its centre is one radius out along the skin's normal there,
            # not along the ray (which meets the side of a shank or a thigh obliquely)
            n = tm.face_normals[f]
            n = n if n @ dirs[r] > 0 else -n
            out[names[r]] = loc + n * marker_radius_mm
            hit[r] = True
    if not hit.all():
        miss = np.flatnonzero(~hit)
        guess = np.array([placed[names[i]] for i in miss])
        near, dist, f = tm.nearest.on_surface(guess)
        for i, q, d, fi, g in zip(miss, near, dist, f, guess):
            n = tm.face_normals[fi]   # the skin's normals point out of the body
            # only a guess behind the skin moves: one outside it (a finger marker beside a hand the scan
            # did not cover well) snapped onto the nearest skin bent the hand's marker pattern (carpals
            # 12.8 -> 14.4 deg)
            if d <= snap_mm and (g - q) @ n < 0:
                out[names[i]] = q + n * marker_radius_mm
    return out


def _landmark(b, name: str, T: np.ndarray) -> np.ndarray | None:
    p = b.landmarks.get(name, b.joint_centres.get(name))
    return None if p is None else T[:3, :3] @ p + T[:3, 3]


def forearm_capsules(dirs, read: list | None = None) -> dict[str, list]:
    """Capsule centres (LPS mm) found in each forearm stack, keyed by the stack's folder name.

    ``read``: :func:`start_reading_stacks`'s result for ``dirs``, whose capsules are taken as found.
    """
    from bonecap.segmentation.capsules import find_capsules

    out = {}
    for i, d in enumerate(dirs):
        if read is not None:
            out[Path(d).name] = _stack_read(read[i])[2]
            continue
        v = max(load_stations([d]), key=lambda x: x.data.size)
        out[Path(d).name] = find_capsules(v)[0].tolist()
    return out


def _read_stack(d) -> tuple[Volume, np.ndarray, list]:
    """One forearm stack's largest series, its body mask and the capsule centres found in it (LPS mm)."""
    from bonecap.segmentation.capsules import find_capsules
    from bonecap.segmentation.skin import segment_body

    v = max(load_stations([d]), key=lambda x: x.data.size)
    return v, segment_body(v), find_capsules(v)[0].tolist()


def start_reading_stacks(dirs: list[str | os.PathLike]):
    """Start reading the forearm stacks (:func:`_read_stack`) in a forked child; returns ``join()``.

    They need nothing from the stations, so build-subject starts them first, and the child works
    beside the stages that leave a core idle (loading and registering the stations, the skin's
    mesh, the seeds, the bone meshes). ``join()`` gives one entry per stack: its
    ``(volume, body mask, capsule centres)``, or the exception reading it raised, which
    :func:`_stack_read` raises where the stack is used -- as reading it there would have. Without
    worker processes (``BONECAP_WORKERS=1``, no ``fork``, one CPU) they are read here at once
    (:func:`bonecap.parallel.fork_or_here`).
    """
    dirs = list(dirs)

    def read_all() -> list:
        out: list = []
        for d in dirs:
            try:
                out.append(_read_stack(d))
            except Exception as exc:  # noqa: BLE001 - raised where the stack is used
                try:       # it travels back through a pipe: one that does not pickle says what it was
                    pickle.loads(pickle.dumps(exc))
                except Exception:  # noqa: BLE001
                    exc = RuntimeError(f"{d}: {type(exc).__name__}: {exc}")
                out.append(exc)
        return out

    return fork_or_here(read_all, beside=True)


def _stack_read(entry):
    """An entry of :func:`start_reading_stacks`'s result: the read stack, or its error raised."""
    if isinstance(entry, BaseException):
        raise entry
    return entry


def _stack_side(path, personal: Skeleton, read=None) -> str:
    """Which forearm a stack shows: right when its centre lies on the body's right (LPS -x).

    ``read``: the stack's :func:`start_reading_stacks` entry (else it is read here).
    """
    v = _stack_read(read)[0] if read is not None else load_stations([path])[0]
    centre = v.index_to_world(np.array([(np.array(v.shape) - 1) / 2.0]))[0]
    mid = personal.bones[personal.names[0]].bone_to_world[:3, 3]
    return "r" if centre[0] < mid[0] else "l"


#: The radius's axis measured in the forearm stacks (:func:`~bonecap.motion.forearm.radius_axis_from_poses`)
#: replaces the ulna's radio-ulnar joint centres unless one of them lies farther than this (mm) from it: then a
#: stack's registration, not the warp, is the likelier to be wrong.
RADIUS_AXIS_MAX_OFF_MM = 10.0

#: A capsule in a forearm stack is named for a marker of the forearm when it lies within this distance (mm)
#: of the marker's bound position carried by the registered bone (the marker 3 mm farther out than its
#: capsule; the static binding of a wrist marker 5 mm off on phantoms). The one-to-one assignment keeps a
#: marker from taking another's capsule; a capsule elsewhere on the forearm (the phantom's other capsules
#: keep 14 mm from the marker spots) within reach of a marker whose own is not in the stack can still be taken,
#: which the checks below (:data:`FOREARM_CAPSULE_SKIN_MM`, :data:`FOREARM_CAPSULE_SPREAD_MM`) are for.
FOREARM_CAPSULE_MATCH_MM = 12.0
#: A stack's capsule, carried back to the MRI pose with its bone, is used while its centre lies between
#: ``FOREARM_CAPSULE_SKIN_MM[0]`` mm inside the personal skin and ``[1]`` mm outside it: a capsule lies on the
#: skin (centre one radius, 4 mm, out), and the skin does not follow the bone through a half turn (on the
#: phantom it is 5-12 mm off the bone-carried spot at 172 deg). Inside, because where the whole-body stations
#: show capsules too the personal skin holds their bumps (the capsule's own centre up to a radius inside).
FOREARM_CAPSULE_SKIN_MM = (6.0, 7.0)
#: A marker is bound from its stacks' capsules only while their centres, carried back to the MRI pose, lie
#: within this distance (mm) of their mean: the stacks' registrations (0.6-1.5 mm ICP residuals) agree that far.
FOREARM_CAPSULE_SPREAD_MM = 4.0


def forearm_capsule_markers(stacks, personal: Skeleton, side: str, markers, skin: Mesh | None, *,
                            max_distance_mm: float = FOREARM_CAPSULE_MATCH_MM,
                            capsule_radius_mm: float = 4.0, marker_radius_mm: float = 7.0
                            ) -> tuple[dict[str, Any], dict[str, Any]]:
    """The forearm's markers bound from the capsules the forearm stacks show at their spots.

    The paper's protocol marked every marker spot with an oil capsule, in the
    forearm stacks too, and read the stacks' twist on them. In each stack the
    markers are expected where their bound positions ride the registered
    bones (the humerus's, the epicondyles, with the ulna), and the capsules
    found there are named one to one (:func:`~bonecap.segmentation.capsules.match_capsules`).
    A marker on the ulna or the radius that got a capsule, and that no capsule
    of the whole-body stations bound already, is bound again from it: the
    capsule carried back to the MRI pose with its bone's registration (kept
    where it lies on the personal skin there, within :data:`FOREARM_CAPSULE_SKIN_MM`),
    averaged over the stacks that show it (while they agree,
    :data:`FOREARM_CAPSULE_SPREAD_MM`), and the marker one
    marker-minus-capsule radius out along the personal skin's normal
    (:func:`capsules_to_markers`). The epicondyle markers keep their binding:
    the humerus is not registered in the stacks, and the elbow's flexion there
    need not be the whole-body scan's.

    Parameters
    ----------
    stacks : sequence of (Ts, capsules)
        Per stack: each registered bone's pose (bone -> LPS) and the capsule centres found (LPS mm).
    personal : Skeleton
        The personal skeleton at the MRI pose (LPS).
    side : {"r", "l"}
    markers : mapping of str -> MarkerBinding
        The subject's markers.
    skin : Mesh or None
        The personal skin at the MRI pose (LPS, outward normals), whose normal
        carries a capsule's centre out to its marker's; without it nothing is bound.
    max_distance_mm : float
        :data:`FOREARM_CAPSULE_MATCH_MM`.

    Returns
    -------
    bindings : dict of str -> MarkerBinding
        The markers bound again (source ``"capsule"``).
    report : dict
        Per marker: the stacks that showed its capsule (``stacks``), those whose
        capsule was off the skin (``off_skin``), the spread of the carried
        centres (mm), how far the new binding moved it (``moved_mm``) or why it
        was not bound (``not_bound``).

    References
    ----------
    .. [1] Kojima et al., sections 4 and 8.2 (capsules at the marker spots; the twist read on them).
    """
    from bonecap.motion.forearm import FOREARM_MARKERS
    from bonecap.motion.rigid import apply_transform
    from bonecap.segmentation.capsules import match_capsules
    from bonecap.subject import MarkerBinding

    if side not in FOREARM_MARKERS:
        raise ValueError(f"side must be 'r' or 'l', got {side!r}")
    ulna_n = f"ulna_{side}"
    own = {ulna_n, f"radius_{side}"}
    names = [n for n, m in markers.items()
             if m.bone in personal.bones and (m.bone in own or n in FOREARM_MARKERS[side])]
    carried: dict[str, list[np.ndarray]] = {}
    report: dict[str, Any] = {}
    if not names or ulna_n not in personal.bones or skin is None:
        return {}, report
    import trimesh

    skin_tm = trimesh.Trimesh(skin.vertices, skin.faces, process=False)
    off_skin: dict[str, int] = {}
    U = personal.bones[ulna_n].bone_to_world
    for Ts, centres in stacks:
        centres = np.asarray(centres, float).reshape(-1, 3)
        if not len(centres) or ulna_n not in Ts:
            continue
        moves = {}
        for n in names:
            b = markers[n].bone
            # bone -> its MRI pose's motion into this stack; the humerus's markers ride the ulna
            moves[n] = (Ts[b] if b in Ts else Ts[ulna_n] @ np.linalg.inv(U) @ personal.bones[b].bone_to_world
                        ) @ np.linalg.inv(personal.bones[b].bone_to_world)
        expected = {n: apply_transform(moves[n] @ personal.bones[markers[n].bone].bone_to_world,
                                       markers[n].local[None])[0] for n in names}
        for n, c in match_capsules(centres, expected, max_distance_mm=max_distance_mm).items():
            # a marker the whole-body stations' capsules bound keeps that binding: measured at the MRI pose
            # itself, it needs no registration (seed 2 of the capsule protocol: its RWRA 1.9 mm from the
            # truth so, 2.6 mm bound again from the stacks, the radius 1.8 -> 3.2 deg in the trials)
            if markers[n].bone in own and markers[n].bone in Ts and markers[n].source != "capsule":
                back = apply_transform(np.linalg.inv(moves[n]), c[None])[0]
                q, _, tri = skin_tm.nearest.on_surface(back[None])
                height = float((back - q[0]) @ skin_tm.face_normals[tri[0]])     # + outside the body
                if not -FOREARM_CAPSULE_SKIN_MM[0] <= height <= FOREARM_CAPSULE_SKIN_MM[1]:
                    off_skin[n] = off_skin.get(n, 0) + 1
                    continue
                carried.setdefault(n, []).append(back)
    for n, k in off_skin.items():
        report[n] = {"stacks": 0, "off_skin": k, "not_bound": "its capsules lie off the skin at the MRI pose"}
    mean = {n: np.mean(c, axis=0) for n, c in carried.items()}
    spread = {n: float(np.max(np.linalg.norm(np.asarray(carried[n]) - mean[n], axis=1))) for n in mean}
    for n in [n for n in mean if spread[n] > FOREARM_CAPSULE_SPREAD_MM]:
        report[n] = {"stacks": len(carried[n]), "off_skin": off_skin.get(n, 0), "spread_mm": round(spread[n], 2),
                     "not_bound": "the stacks disagree"}
        del mean[n]
    if not mean:
        return {}, report
    placed = capsules_to_markers(mean, skin, capsule_radius_mm=capsule_radius_mm, marker_radius_mm=marker_radius_mm)
    bindings = {}
    for n, p in placed.items():
        B = personal.bones[markers[n].bone].bone_to_world
        local = B[:3, :3].T @ (np.asarray(p, float) - B[:3, 3])
        bindings[n] = MarkerBinding(n, markers[n].bone, local, "capsule", markers[n].weight)
        report[n] = {"stacks": len(carried[n]), "off_skin": off_skin.get(n, 0), "spread_mm": round(spread[n], 2),
                     "moved_mm": round(float(np.linalg.norm(local - markers[n].local)), 2)}
    return bindings, report


def fit_forearm_from_stacks(dirs: list[str | os.PathLike], personal: Skeleton, side: str = "r",
                            max_icp_mm: float = 6.0, markers=None, registered: Pending | None = None,
                            skin: Mesh | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
    """Stage 8: the subject's forearm model from three forearm stacks (Kojima et al. §8.2).

    For each stack: the humerus, ulna and radius are segmented with the
    cortical rule (seeds: the personal bones' axes), the ulna is meshed and
    the personal ulna rigidly registered onto it (ICP); the radius's target
    is every forearm bone voxel the registered ulna does not hold, within the
    ring the radius sweeps turning about the ulna (its seed, placed at the MRI
    pose, takes either bone's marrow in a pronated stack), and the personal
    radius is registered onto it from starts turned about the radio-ulnar
    axis. That gives each bone's pose in that stack. The twist of each stack is measured from four points
    (:func:`bonecap.motion.forearm.forearm_twist`) — the paper measured 0°,
    99.5° and 172.1°, not the nominal 0/90/180 — and the quadratics are fitted
    against the measured twists. With ``markers`` (the subject's bound wrist and
    elbow markers, :data:`~bonecap.motion.forearm.FOREARM_MARKERS`) the four
    points are those markers carried by the registered bones, the epicondyle
    markers with the ulna as ``animate`` carries them: the twist and the
    control-point segments are then the same measure ``animate`` uses on a
    trial (the paper measured its stacks on the capsules that marked the marker
    spots); the styloid and epicondyle landmarks lie ~8 mm deeper and gave a
    twist scale the trials did not reproduce. Without them, the landmarks.
    Capsules found in the stacks are reported.

    Parameters
    ----------
    dirs : list of path
        The three stacks (DICOM folders), any order.
    personal : Skeleton
        The personal skeleton at the MRI pose (LPS), with ulna, radius and humerus meshes.
    side : {"r", "l"}
    max_icp_mm : float
        A bone whose registration leaves a larger median residual is not in that stack: error (the
        median: where the stack's segmentation missed part of the bone, the mean grows with what was
        missed, however well the rest fits).
    markers : dict of str -> MarkerBinding, optional
        The subject's markers (bone, position in the bone frame). Those of the
        ulna and the radius whose capsules the stacks show (and that no
        whole-body capsule bound) are bound again from them, **in this dict**
        (:func:`forearm_capsule_markers`), before the twists are read.
    registered : Pending, optional
        The stacks' registrations already started (:func:`start_forearm_registration`
        with the same ``dirs``, ``personal``, ``side`` and ``max_icp_mm``).
    skin : Mesh, optional
        The personal skin at the MRI pose, for the capsules' markers.

    Returns
    -------
    model : dict
        :meth:`ForearmModel.to_dict` plus ``side``.
    report : dict
        Per stack: measured twist, ICP residuals, capsule centres (LPS); ``twist_from``.

    References
    ----------
    .. [1] Kojima et al., section 8.2.
    """
    from bonecap.motion.forearm import FOREARM_MARKERS, fit_forearm_model, forearm_twist, radius_axis_from_poses

    if len(dirs) != 3:
        raise InputError(f"--forearm-poses takes three stacks, got {len(dirs)}")
    ulna_n, radius_n, hum_n = f"ulna_{side}", f"radius_{side}", f"humerus_{side}"
    for n in (ulna_n, radius_n, hum_n):
        if n not in personal.bones or personal.bones[n].mesh is None:
            raise DataError(f"the personal skeleton has no {n} mesh to register into the forearm stacks")
    U, Rb, H = (personal.bones[n] for n in (ulna_n, radius_n, hum_n))
    lat = _landmark(H, "lateral_epicondyle", H.bone_to_world)
    med = _landmark(H, "medial_epicondyle", H.bone_to_world)
    names = FOREARM_MARKERS[side]
    use_markers = markers is not None and all(n in markers and markers[n].bone in personal.bones for n in names)
    poses, report = [], {"stacks": {}, "capsules": {}}
    if registered is None:
        registered = start_forearm_registration(dirs, personal, side, max_icp_mm)
    results = registered.result()
    if use_markers:
        # the ulna's and the radius's markers bound where the stacks' capsules mark them, so the stacks'
        # twist is read on the wrist markers' own spots, as the paper read its stacks and as a trial reads
        # its real markers: the static's binding of the radial styloid marker was 5 mm off on a phantom,
        # which tilted every stack's wrist line against the trials' (their twists 2.6-4 deg apart). The
        # static's solved pose (subject.static) keeps the bindings it was solved with.
        rebound, report["capsule_markers"] = forearm_capsule_markers(
            [(Ts, caps) for Ts, _, caps in results], personal, side, markers, skin)
        markers.update(rebound)
        report["rebound_after_static"] = sorted(rebound)
    for d, (Ts, stack_report, capsules) in zip(dirs, results):
        report["stacks"][str(d)] = stack_report
        if use_markers:
            # each marker rides on its bone's registration in this stack; the ones on the humerus
            # (epicondyles) are carried with the ulna, as animate carries them on a trial
            carry_u = Ts[ulna_n] @ np.linalg.inv(U.bone_to_world)
            pts = []
            for n in names:
                mb = markers[n]
                T = Ts[mb.bone] if mb.bone in Ts else carry_u @ personal.bones[mb.bone].bone_to_world
                pts.append(T[:3, :3] @ np.asarray(mb.local, float) + T[:3, 3])
            wrist, elbow = np.array(pts[:2]), np.array(pts[2:])
        else:
            wrist = np.array([_landmark(Rb, "radial_styloid", Ts[radius_n]),
                              _landmark(U, "ulnar_styloid", Ts[ulna_n])])
            elbow = np.array([lat, med])
        poses.append((Ts[ulna_n], Ts[radius_n], wrist, elbow))
        report["capsules"][Path(d).name] = capsules
    wr = np.array([p[2] for p in poses])
    el = np.array([p[3] for p in poses])
    raw = forearm_twist(wr[:, 0], wr[:, 1], el[:, 0], el[:, 1], side=side)
    theta = raw - raw[int(np.argmin(np.abs(raw)))]
    for (d, _), t in zip(report["stacks"].items(), theta):
        report["stacks"][d]["twist_deg"] = float(t)
    ulna_at, radius_at = np.array([p[0] for p in poses]), np.array([p[1] for p in poses])
    model = fit_forearm_model(theta, ulna_at, radius_at, wr, el, side=side)
    out = model.to_dict()
    # the subject's MRI knows where its radio-ulnar axis is: the radius turns about it rather than
    # about the line through the control points on the skin markers' segments (ForearmModel.radius_axis)
    out["radius_axis"] = "anatomical"
    # ... and where the stacks show it: the radius's turn relative to the ulna from the 0 degree stack is
    # about that axis, whose place the warped ulna's joint centres guessed 2-4 mm off on a phantom (a half
    # turn carried that into 4-8 mm of radius position)
    if {"proximal_radioulnar", "distal_radioulnar"} <= set(U.joint_centres):
        guess = np.array([U.joint_centres["proximal_radioulnar"], U.joint_centres["distal_radioulnar"]])
        ends, report["radius_axis"] = radius_axis_from_poses(ulna_at, radius_at, guess,
                                                             ref=int(np.argmin(np.abs(raw))))
        if ends is not None and max(report["radius_axis"]["guess_off_mm"]) <= RADIUS_AXIS_MAX_OFF_MM:
            out["radius_axis_ulna_mm"] = ends.ravel().tolist()
        report["radius_axis"]["used"] = "radius_axis_ulna_mm" in out
    out["side"] = side
    out["fitted_from"] = [str(d) for d in dirs]
    report["twists_deg"] = theta.tolist()
    report["twist_from"] = "markers" if use_markers else "landmarks"
    report["used"] = True
    return out, report


def start_forearm_registration(dirs: list[str | os.PathLike], personal: Skeleton, side: str = "r",
                               max_icp_mm: float = 6.0, read: list | None = None) -> Pending:
    """Start registering the personal forearm bones into each stack, in worker processes.

    The stacks are independent of each other and of the markers: build-subject
    starts them before it places the markers and hands the result to
    :func:`fit_forearm_from_stacks` (``registered``). All three run at once even
    on two cores (two rounds of one and two stacks take 2/3 of the serial
    time, three processes sharing two cores about half of it). The workers see
    ``personal`` as it is now. ``read``: the stacks already read
    (:func:`start_reading_stacks`'s result for ``dirs``); else each worker reads its own.
    """
    dirs = list(dirs)
    entries = list(read) if read is not None else [None] * len(dirs)
    return fork_start(lambda de: _register_stack(de[0], personal, side, max_icp_mm, read=de[1]),
                      list(zip(dirs, entries)), workers=len(dirs) if default_workers() > 1 else 1)


#: The share of matches the ulna's ICP in a forearm stack keeps each way (the warp's keep 0.9). Half a
#: turn pronated, the radius crosses the ulna, whose seed then takes radius sections and loses its own
#: (phantom seed 2 at 172 deg: a tenth of the ulna's target was radius, a quarter of the ulna missing): at
#: 0.9 the fit settled 3-13 mm (mean over the bone) from its fit onto the true ulna, at 0.8 within 0.5-1.1.
STACK_ULNA_TRIM = 0.8


def _register_stack(d, personal: Skeleton, side: str, max_icp_mm: float, read=None):
    """One forearm stack: ulna and radius segmented and the personal bones registered onto them.

    ``read``: the stack's :func:`start_reading_stacks` entry (else it is read here).
    Returns ``(Ts, report, capsules)``: each bone's pose in the stack (bone -> LPS), the stack's
    report entries (ICP residuals, the radius seed's turn) and the capsule centres found (LPS).
    """
    from bonecap.meshing import mesh_from_slices
    from bonecap.segmentation.bones import keep_continuous, marrow_sections, segment_bones
    from bonecap.skeleton.warp import rigid_icp

    ulna_n, radius_n, hum_n = f"ulna_{side}", f"radius_{side}", f"humerus_{side}"
    U, Rb = personal.bones[ulna_n], personal.bones[radius_n]
    report: dict[str, Any] = {}
    v, body, centres = _stack_read(read if read is not None else _read_stack(d))
    # each bone's own axis: the ulna from the elbow to its head, the radius from its head to the wrist
    # (elbow -> distal radio-ulnar joint, as both had, is the ulna's line: the two seeds coincided), and
    # the humerus (shoulder -> elbow): a stack reaching above the elbow holds the distal humerus, and
    # without its own label its trochlea and epicondyles went to the ulna (a quarter of the ulna's
    # target, 13 mm above the olecranon: its ICP settled 5-12 deg off on the phantom, 1 deg with it).
    # Each bone is kept continuous from its shaft (``continuity``), which drops carpals past the wrist.
    axis_joints = {hum_n: ("shoulder", "elbow"), ulna_n: ("elbow", "distal_radioulnar"),
                   radius_n: ("proximal_radioulnar", "wrist")}
    seeds = {n: np.array([personal.bones[n].landmark_in_world(j) for j in axis_joints[n]
                          if j in personal.bones[n].joint_centres])
             for n in (hum_n, ulna_n, radius_n) if n in personal.bones}
    seeds = {n: p for n, p in seeds.items() if len(p) == 2}
    regions: dict = {}                  # the slices' marrow candidates, found once for both rules below
    raw, ids = segment_bones(v, seeds, body_mask=body, progress=False, continuity=False, marrow_regions=regions)
    lab = keep_continuous(raw, ids, v, seeds)
    Ts = {}
    turn = None
    for n, bone in ((ulna_n, U), (radius_n, Rb)):
        if n not in ids or not (lab == ids[n]).any():
            raise DataError(f"the {n.split('_')[0]} was not found in this forearm stack", d)
        mask = lab == ids[n]
        if n == radius_n:
            # The radius's seeds were its line at the MRI pose; pronated by up to half a turn, its distal
            # end lies on the other side of the ulna, and its seed takes the ulna's marrow, the radius's or
            # a bright speck of fat from slice to slice. The ulna, registered first, tells where it can be:
            # it turns about the radio-ulnar axis, so it sweeps, level by level along the axis, the ring
            # between its nearest and farthest points from it -- not the humeral capitellum above the
            # radial head, nor the carpals past the wrist. Its target is every marrow rimmed by cortex in
            # that ring (no seed needed) that the registered ulna does not hold. Tried before: the voxels
            # either seed labelled (it missed the radius's distal third where neither seed reached it and
            # took fat the seeds had found: 18 % of the target > 5 mm off the true radius at 99.5 deg);
            # a seed line turned about the radio-ulnar axis into the brightest marrow and the stack
            # segmented again from there (on one of two phantoms it picked the wrong side of the ulna).
            ulna_move = Ts[ulna_n] @ np.linalg.inv(U.bone_to_world)
            ax = _radioulnar_axis(U, ulna_move)
            if ax is not None:
                ring = _swept_by(Rb.mesh.transformed(ulna_move @ Rb.bone_to_world).vertices, ax, v, body)
                ulna_at = _inside_mesh(v, Ts[ulna_n], U.mesh, ring, margin_mm=1.5)
                mask = marrow_sections(v, ring, body_mask=body, exclude=ulna_at, per_slice=1,
                                       regions=regions) & ring
            else:
                mask = (raw == ids[ulna_n]) | (raw == ids[radius_n])
            mask &= ~_inside_mesh(v, Ts[ulna_n], U.mesh, mask, margin_mm=1.5)
            if not mask.any():
                raise DataError("the radius was not found in this forearm stack", d)
            # the turn into the brightest marrow is one more start for the ICP
            turn = _radius_turn(v, _marrow_axis(Rb, seeds[radius_n]), ulna_move, U, body_mask=body)
            if turn is not None:
                report["radius_seed_turn_deg"] = float(
                    np.degrees(np.arccos(np.clip((np.trace(turn[:3, :3]) - 1) / 2, -1, 1))))
        target = mesh_from_slices([(mask, v.affine)], target_faces=8000)
        pts = bone.mesh.transformed(bone.bone_to_world).vertices
        if n == ulna_n:
            T, res = rigid_icp(pts, target, trim=STACK_ULNA_TRIM)
        else:
            ulna_move = Ts[ulna_n] @ np.linalg.inv(U.bone_to_world)
            T, res = _radius_icp(pts, target, ulna_move, U,
                                 extra_starts=[turn @ ulna_move] if turn is not None else ())
        Ts[n] = T @ bone.bone_to_world
        report[f"{n}_icp_mm"] = float(np.mean(res))
        report[f"{n}_icp_median_mm"] = float(np.median(res))
        if np.median(res) > max_icp_mm:
            raise DataError(f"the personal {n} does not fit the {n.split('_')[0]} segmented in this stack "
                            f"(median ICP residual {np.median(res):.1f} mm > {max_icp_mm:g} mm)", d)
    # the capsules were found with their own body mask (find_capsules): the skin mask holds them
    return Ts, report, centres


def _swept_by(points: np.ndarray, axis: tuple[np.ndarray, np.ndarray], volume: Volume, where: np.ndarray,
              bin_mm: float = 5.0, margin_mm: float = 2.0) -> np.ndarray:
    """Voxels (of ``where``) that ``points`` can reach turning about ``axis`` (a point and a unit direction).

    Per ``bin_mm`` level along the axis, the ring between the points' nearest and farthest distances
    from it, widened by ``margin_mm``; nothing beyond their ends.
    """
    def cyl(p):
        d = p - axis[0]
        t = d @ axis[1]
        return t, np.linalg.norm(d - t[:, None] * axis[1], axis=1)

    t, r = cyl(points)
    lo = np.floor(t.min() / bin_mm)
    nb = int(np.floor(t.max() / bin_mm) - lo) + 1
    b = (np.floor(t / bin_mm) - lo).astype(int)
    rmin, rmax = np.full(nb, np.inf), np.full(nb, -np.inf)
    np.minimum.at(rmin, b, r)
    np.maximum.at(rmax, b, r)
    # a level the points skip (none there) takes its neighbours' ring
    for k in np.flatnonzero(~np.isfinite(rmin)):
        rmin[k] = min(rmin[max(k - 1, 0)], rmin[min(k + 1, nb - 1)])
        rmax[k] = max(rmax[max(k - 1, 0)], rmax[min(k + 1, nb - 1)])
    ijk = np.argwhere(where)
    out = np.zeros(where.shape, bool)
    tv, rv = cyl(volume.index_to_world(ijk.astype(float)))
    bv = np.floor(tv / bin_mm) - lo
    ok = (tv >= t.min() - 1.0) & (tv <= t.max() + 1.0)
    bi = np.clip(bv, 0, nb - 1).astype(int)
    ok &= (rv >= rmin[bi] - margin_mm) & (rv <= rmax[bi] + margin_mm)
    out[tuple(ijk[ok].T)] = True
    return out


def _inside_mesh(volume: Volume, bone_to_world: np.ndarray, mesh: Mesh, where: np.ndarray,
                 margin_mm: float = 1.5) -> np.ndarray:
    """Voxels (of ``where``) inside a bone's mesh posed by ``bone_to_world`` or within ``margin_mm`` of it.

    The mesh is voxelised on the stack's grid (by the phantom's scan-line rasteriser); voxels deeper
    inside it than a voxel's diagonal are in, those farther out than the margin and a diagonal are
    out, and only the band between is tested point by point (VTK's signed distance, ~5 us a point:
    on every voxel of the ring a radius sweeps it took 7 s a stack).
    """
    import pyvista as pv
    from scipy.ndimage import distance_transform_edt

    from bonecap.phantom.render import voxelise_labels

    where = np.asarray(where, bool)
    out = np.zeros(where.shape, bool)
    verts = mesh.vertices @ bone_to_world[:3, :3].T + bone_to_world[:3, 3]
    inside = voxelise_labels([(Mesh(verts, mesh.faces, "lps"), 1)], volume.affine, where.shape,
                             inplane_supersample=1, through_plane_samples=1) > 0
    sp = np.asarray(volume.spacing, float)
    diag = float(np.linalg.norm(sp))
    if inside.any():
        pad = np.ceil((margin_mm + diag) / sp).astype(int) + 1
        nz = np.nonzero(inside)
        box = tuple(slice(max(int(a.min()) - p, 0), min(int(a.max()) + p + 1, n))
                    for a, p, n in zip(nz, pad, where.shape))
        ins = inside[box]
        deep = ins & (distance_transform_edt(ins, sampling=sp) > diag)
        band = (ins & ~deep) | (~ins & (distance_transform_edt(~ins, sampling=sp) <= margin_mm + diag))
        out[box] = deep
        test = np.zeros(where.shape, bool)
        test[box] = band
    else:  # smaller than a voxel: test the mesh's box
        test = np.zeros(where.shape, bool)
        lo = np.floor(volume.world_to_index(verts).min(axis=0) - (margin_mm + diag) / sp.min()).astype(int)
        hi = np.ceil(volume.world_to_index(verts).max(axis=0) + (margin_mm + diag) / sp.min()).astype(int) + 1
        test[tuple(slice(max(a, 0), max(min(b, n), 0)) for a, b, n in zip(lo, hi, where.shape))] = True
    ijk = np.argwhere(test & where)
    if len(ijk):
        surf = pv.PolyData(verts, np.hstack([np.full((len(mesh.faces), 1), 3), mesh.faces]).ravel())
        # VTK's implicit distance: signed by the (outward) normals, negative inside
        dist = pv.PolyData(volume.index_to_world(ijk.astype(float))).compute_implicit_distance(surf)
        out[tuple(ijk[np.asarray(dist["implicit_distance"]) <= margin_mm].T)] = True
    return out & where


def _radioulnar_axis(ulna: Bone, ulna_move: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The registered ulna's radio-ulnar axis: a point on it and its unit direction (LPS), or None."""
    ends = [ulna.landmark_in_world(j) for j in ("proximal_radioulnar", "distal_radioulnar")
            if j in ulna.joint_centres]
    if len(ends) != 2:
        return None
    a = ulna_move[:3, :3] @ ends[0] + ulna_move[:3, 3]
    b = ulna_move[:3, :3] @ ends[1] + ulna_move[:3, 3]
    return a, (b - a) / np.linalg.norm(b - a)


def _turn_about(point: np.ndarray, axis: np.ndarray, deg: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    from bonecap.skeleton.kinematics import turn_about

    return turn_about(point, Rotation.from_rotvec(np.radians(deg) * axis).as_matrix())


def _marrow_axis(bone: Bone, fallback: np.ndarray, n: int = 24, span=(0.05, 0.7)) -> np.ndarray:
    """Points on a long bone's medullary axis (world, its reference pose), distal part first.

    Centroids of the endosteal (inner) mesh in ``n`` slabs across the bone's
    long (ISB y) axis over ``span`` of its length from the distal end. A
    straight joint-to-joint line misses a bowed radius's thin marrow (its
    median intensity in a forearm stack was the muscle's); these points stay
    in it. Without an inner mesh: ``n`` points on ``fallback``'s distal two thirds.
    """
    inner = bone.inner_mesh
    if inner is None or len(inner.vertices) < 50:
        f = np.asarray(fallback, float)
        t = np.linspace(1 / 3, 1.0, n)[:, None]
        return f[0] + t * (f[-1] - f[0])
    v = inner.vertices
    y = v[:, 1]
    lo, hi = float(y.min()), float(y.max())
    half = (hi - lo) / (2 * n)
    pts = [v[np.abs(y - yy) < half].mean(axis=0) for yy in lo + np.linspace(*span, n) * (hi - lo)
           if (np.abs(y - yy) < half).sum() >= 5]
    T = bone.bone_to_world
    return np.array(pts) @ T[:3, :3].T + T[:3, 3]


def _radius_turn(volume: Volume, axis_points: np.ndarray, ulna_move: np.ndarray, ulna: Bone,
                 step_deg: float = 5.0, body_mask: np.ndarray | None = None,
                 min_depth_mm: float = 5.0) -> np.ndarray | None:
    """The turn about the registered ulna's radio-ulnar axis that puts the radius's line in its marrow.

    Points on the radius's medullary axis at the MRI pose (:func:`_marrow_axis`,
    its distal part: the radial head stays on the turning axis whatever the
    twist) are carried with the ulna's registration, then turned about the
    radio-ulnar axis in ``step_deg`` steps; at each turn the image is sampled
    at them and the turn with the highest median -- the points inside bright
    marrow, not in muscle -- wins (the marrow is a few mm wide: the peak is
    ~20 deg wide, hence the fine step). Subcutaneous fat is as bright as marrow in T2: with ``body_mask``,
    samples less than ``min_depth_mm`` under the skin count as air, so a line
    swung out into the fat layer loses to one in the marrow (without it, a
    99.5 deg stack picked a 40 deg turn). Returns the 4x4 turn (LPS, applied
    after ``ulna_move``), or None without the ulna's radio-ulnar joints.
    """
    from scipy.ndimage import distance_transform_edt, map_coordinates

    ax = _radioulnar_axis(ulna, ulna_move)
    if ax is None or len(axis_points) < 2:
        return None
    pts = np.asarray(axis_points, float) @ ulna_move[:3, :3].T + ulna_move[:3, 3]
    shape = np.array(volume.data.shape)
    turns = [_turn_about(ax[0], ax[1], ang) for ang in np.arange(0.0, 360.0, step_deg)]
    at = [volume.world_to_index(pts @ R[:3, :3].T + R[:3, 3]) for R in turns]
    # Only the box the turned points sweep is sampled: the image (and the depth under the skin) on that box
    # and a margin beyond min_depth_mm, so that a background voxel within min_depth_mm of a sampled voxel is
    # in it -- the same depths there as on the whole stack, for a fraction of the distance transform.
    spacing = np.asarray(volume.spacing, float)
    margin = np.ceil(min_depth_mm / spacing).astype(int) + 2
    every = np.concatenate(at)
    lo = np.clip(np.floor(every.min(axis=0)).astype(int) - margin, 0, shape)
    hi = np.clip(np.ceil(every.max(axis=0)).astype(int) + 2 + margin, 0, shape)
    if np.any(hi <= lo):
        return None
    box = tuple(slice(a, b) for a, b in zip(lo, hi))
    data = np.asarray(volume.data[box], np.float32)
    if body_mask is not None:
        body = np.asarray(body_mask[box], bool)
        if body.all():              # no skin within reach of the box: every voxel in it is deep
            deep = body
        else:
            # depth under the skin, in mm (voxel spacing per axis)
            deep = distance_transform_edt(body, sampling=spacing) >= min_depth_mm
        data = np.where(deep, data, 0.0).astype(np.float32)
    best, best_score = None, -np.inf
    for R, ijk in zip(turns, at):
        inside = ((ijk >= -0.5) & (ijk <= shape - 0.5)).all(axis=1)
        if inside.sum() < len(pts) // 2:
            continue
        # mode "nearest" clamps at the stack's edge as before: the box reaches it wherever a point is near
        vals = map_coordinates(data, (ijk[inside] - lo).T, order=1, mode="nearest")
        score = float(np.median(vals))
        if score > best_score:
            best, best_score = R @ ulna_move, score
    return None if best is None else best @ np.linalg.inv(ulna_move)


def _radius_icp(pts: np.ndarray, target: Mesh, ulna_move: np.ndarray, ulna: Bone,
                step_deg: float = 45.0, extra_starts=()) -> tuple[np.ndarray, np.ndarray]:
    """Rigid ICP of the radius into a forearm stack, started around the registered ulna.

    ICP is local (~20 degrees), and a stack at 172 degrees of pronation holds the
    radius turned half a turn about the ulna from the MRI pose: started there,
    it settled 144 degrees off. The radius turns about the radio-ulnar axis (the
    ulna's proximal and distal radio-ulnar joints), so ICP starts from the ulna's
    registration followed by turns about that axis every ``step_deg``; the
    lowest mean residual wins. The starts are compared on a few hundred of the
    bone's points (a coarse ICP each), and only the winner is refined on all
    of them: the same choice at a fifth of the time (the forearm stage was
    the slowest of build-subject).
    """

    from bonecap.skeleton.warp import _as_surface, rigid_icp

    surface = _as_surface(target)  # built once for every start
    starts = [ulna_move, *extra_starts]
    ax = _radioulnar_axis(ulna, ulna_move)
    if ax is not None:
        for ang in np.arange(step_deg, 360.0, step_deg):
            starts.append(_turn_about(ax[0], ax[1], ang) @ ulna_move)
    coarse = pts[np.linspace(0, len(pts) - 1, min(len(pts), 400)).astype(int)]
    best = None
    for C in starts:
        T, res = rigid_icp(coarse, surface, init=C, iterations=30)
        if best is None or float(np.mean(res)) < float(np.mean(best[1])):
            best = (T, res)
    return rigid_icp(pts, surface, init=best[0])


#: :func:`fit_skull_to_skin` turns the skull's lateral axis onto the head's plane of symmetry when the
#: plane is found within this angle (deg) of where the vault's fit put that axis ...
SKULL_SYMMETRY_MAX_DEG = 10.0
#: ... and the head's skin mirrored across it lies within this RMS (mm) of itself (a head turned in the
#: scanner's coil, or cut by the field of view, is not symmetric: the vault's fit is kept).
SKULL_SYMMETRY_MAX_RMS_MM = 6.0


def head_symmetry_plane(points: np.ndarray, normal: np.ndarray, offset: float, *, iterations: int = 60,
                        trim: float = 0.9) -> tuple[np.ndarray, float, float]:
    """The plane of bilateral symmetry of a point set (a head's skin), by mirror registration.

    The points are mirrored across the current plane and registered rigidly
    onto themselves (nearest neighbours, the ``trim`` closest kept, Kabsch
    [2]_); the registration composed with the mirror is an improper rigid map
    whose eigenvector of eigenvalue -1 is the better plane's normal, its fixed
    points the plane [1]_. Repeated from ``(normal, offset)`` until it settles.

    Parameters
    ----------
    points : ndarray (N, 3)
        The surface's points (mm), N >= 10.
    normal : ndarray (3,)
        Start: the plane's normal (need not be unit).
    offset : float
        Start: the plane is ``{x : x . n = offset}`` (mm, ``n`` the unit normal).
    iterations : int
        At most this many rounds.
    trim : float
        Fraction of the mirrored points (closest to the surface) that take part, in (0, 1].

    Returns
    -------
    normal : ndarray (3,)
        Unit normal, on the side of the start's.
    offset : float
        mm.
    rms_mm : float
        RMS distance of the kept mirrored points from the surface at the end.

    Raises
    ------
    ValueError
        Too few points, a zero normal or a trim outside (0, 1].

    References
    ----------
    .. [1] Prima S, Ourselin S, Ayache N (2002). Computation of the mid-sagittal plane in 3-D brain
       images. IEEE Trans Med Imaging 21(2):122-138.
    .. [2] Kabsch W (1976). Acta Cryst A32:922-923.
    """
    from scipy.spatial import cKDTree

    from bonecap.skeleton.warp import _kabsch

    P = np.asarray(points, float)
    n = np.asarray(normal, float).reshape(3)
    if P.ndim != 2 or P.shape[1] != 3 or len(P) < 10:
        raise ValueError(f"head_symmetry_plane needs at least 10 points (N, 3), got shape {P.shape}")
    if not np.linalg.norm(n) > 0 or not 0 < trim <= 1:
        raise ValueError(f"head_symmetry_plane: a non-zero normal and trim in (0, 1] expected, got {normal!r}, {trim!r}")
    n = n / np.linalg.norm(n)
    d = float(offset)
    tree = cKDTree(P)
    rms = np.inf
    for _ in range(int(iterations)):
        H = np.eye(3) - 2.0 * np.outer(n, n)
        h = 2.0 * d * n
        mirrored = P @ H.T + h
        dist, j = tree.query(mirrored)
        keep = dist <= np.quantile(dist, trim)
        rms = float(np.sqrt(np.mean(dist[keep] ** 2)))
        T = _kabsch(mirrored[keep], P[j[keep]])
        Q, q = T[:3, :3] @ H, T[:3, :3] @ h + T[:3, 3]
        w, V = np.linalg.eig(Q)
        n_new = np.real(V[:, int(np.argmin(np.abs(w + 1.0)))])
        n_new = n_new / np.linalg.norm(n_new)
        if n_new @ n < 0:
            n_new = -n_new
        d_new = float(q @ n_new) / 2.0        # a mirror x -> H x + 2 d n moves the origin by 2 d n
        settled = float(n_new @ n) > np.cos(np.radians(1e-4)) and abs(d_new - d) < 1e-3
        n, d = n_new, d_new
        if settled:
            break
    return n, d, rms


def fit_skull_to_skin(posed: Skeleton, skin: Mesh, scalp_mm: float = 6.0,
                      max_residual_mm: float = 12.0) -> tuple[np.ndarray, dict[str, Any] | None]:
    """The skull's placement on the head's skin: what MRI bone contours miss.

    The skull's cortex is thin and its marrow scant, so the slice rules do not
    find it; the scalp over the cranial vault is thin and nearly uniform
    (5–7 mm), so the vault of the placed template skull, pushed out by that
    thickness along its normals, is registered to the skin of the head by an
    affine ICP. The face and the neck are left out (their soft tissue is
    thick and varied): only template vertices above the orbits and ear
    canals (the upper 60 % of the skull's height) take part.

    The vault is nearly round, so its fit says where the skull is better than
    how it is turned: on six phantom builds its lateral axis lay 1.2-3.5 deg
    from the truth's. The whole head's skin is close to symmetric about the
    skull's mid-sagittal plane whatever its soft tissue (faces are, to a few
    millimetres; on the phantoms the skin's plane lay 0.3-0.4 deg from the
    skull's): the skull is then turned about its origin so that its lateral axis (ISB ``Z``)
    is the normal of the skin's plane of symmetry
    (:func:`head_symmetry_plane`, started from the fitted axis), and moved
    across so that its origin lies on it; its turn about the lateral axis
    stays the vault's. Not applied when the plane is not found within
    :data:`SKULL_SYMMETRY_MAX_DEG` of the fitted axis or the mirrored skin lies
    further than :data:`SKULL_SYMMETRY_MAX_RMS_MM` from itself.

    Returns
    -------
    A : ndarray (4, 4)
        Rigid map of the placed template's world (LPS) onto the skull's place;
        the identity when the fit is not used.
    report : dict or None
        ICP residual, the transform and ``used`` (False, with a ``reason``,
        when the fit was out of bounds: the placed skull is kept), or
        ``None`` when the head is not imaged.
    """
    import trimesh

    from bonecap.skeleton.warp import rigid_icp

    if "skull" not in posed.bones or posed.bones["skull"].mesh is None or skin is None:
        return np.eye(4), None
    sk_world = posed.world_mesh("skull")
    tm = trimesh.Trimesh(sk_world.vertices, sk_world.faces, process=False)
    z = tm.vertices[:, 2]
    lo, hi = float(z.min()), float(z.max())
    cut = lo + 0.4 * (hi - lo)
    normals = tm.vertex_normals
    vault = (z > cut) & (normals[:, 2] > -0.2)
    src = tm.vertices[vault] + scalp_mm * normals[vault]
    # the head's skin: everything above the skull's cut, within 40 mm of the vault's box
    sv, sf = skin.vertices, skin.faces
    keep_v = sv[:, 2] > cut - 10.0
    if keep_v.sum() < 100:
        return np.eye(4), None
    fz = keep_v[sf].all(axis=1)
    # only the head's own vertices (a target's unused vertices would still attract the ICP)
    used = np.unique(sf[fz])
    remap = np.full(len(sv), -1)
    remap[used] = np.arange(len(used))
    head = Mesh(sv[used], remap[sf[fz]], "lps")
    # rigid only: the vault's shape under a uniform scalp says where the skull
    # is and how it is turned; an affine would trade the scalp's unevenness
    # (thicker over the occiput) for a stretch of the skull
    A, res = rigid_icp(src, head)
    out = {"icp_residual_mean_mm": float(np.mean(res)), "transform": A.tolist(), "scalp_mm": scalp_mm}
    turn = float(np.degrees(np.arccos(np.clip((np.trace(A[:3, :3]) - 1) / 2, -1, 1))))
    if np.mean(res) > max_residual_mm or turn > 30.0:
        # the head's skin did not take the vault (neck or shoulders caught, a
        # truncated head): the skull stays where the template was placed on
        # the body (head-to-sole extent), and the report says so
        out["used"] = False
        out["reason"] = f"ICP residual {np.mean(res):.1f} mm or turn {turn:.0f} deg out of bounds: placed skull kept"
        A = np.eye(4)
    else:
        out["used"] = True
        A, out["symmetry"] = _skull_onto_symmetry(A, posed.bones["skull"].bone_to_world, tm.vertices, sv)
        out["transform"] = A.tolist()
    return A, out


def _skull_onto_symmetry(A: np.ndarray, T_placed: np.ndarray, skull_world: np.ndarray, skin_vertices: np.ndarray,
                         margin_mm: float = 30.0) -> tuple[np.ndarray, dict[str, Any]]:
    """``A`` (placed skull -> fitted, world) corrected so that the skull's lateral axis (its frame's ``Z``,
    ISB) is the head's skin's symmetry normal and its origin on that plane (:func:`fit_skull_to_skin`).
    The head's skin: the skin's vertices over the fitted skull's extent (``margin_mm`` around it in plane,
    from its lowest point up)."""
    fitted = skull_world @ A[:3, :3].T + A[:3, 3]
    lo, hi = fitted.min(axis=0), fitted.max(axis=0)
    sel = ((skin_vertices[:, 2] >= lo[2]) & np.all(skin_vertices[:, :2] >= lo[:2] - margin_mm, axis=1)
           & np.all(skin_vertices[:, :2] <= hi[:2] + margin_mm, axis=1))
    rep: dict[str, Any] = {"skin_points": int(sel.sum()), "used": False}
    if sel.sum() < 100:
        rep["reason"] = "too little of the head's skin"
        return A, rep
    R = A[:3, :3] @ T_placed[:3, :3]
    origin = A[:3, :3] @ T_placed[:3, 3] + A[:3, 3]
    lateral = R[:, 2]
    n, d, rms = head_symmetry_plane(skin_vertices[sel], lateral, float(lateral @ origin))
    deg = float(np.degrees(np.arccos(np.clip(n @ lateral, -1.0, 1.0))))
    rep.update({"plane_rms_mm": round(rms, 2), "turn_deg": round(deg, 2)})
    if deg > SKULL_SYMMETRY_MAX_DEG or rms > SKULL_SYMMETRY_MAX_RMS_MM:
        rep["reason"] = "no clear plane of symmetry: the vault's fit kept"
        return A, rep
    # the smallest turn taking the lateral axis onto the normal, about the skull's origin
    axis = np.cross(lateral, n)
    s = float(np.linalg.norm(axis))
    turn = np.eye(3)
    if s > 1e-12:
        from scipy.spatial.transform import Rotation

        turn = Rotation.from_rotvec(axis / s * np.arcsin(min(1.0, s))).as_matrix()
    shift = (d - float(n @ origin)) * n
    M = np.eye(4)
    M[:3, :3] = turn
    M[:3, 3] = origin - turn @ origin + shift
    rep.update({"shift_mm": round(float(np.linalg.norm(shift)), 2), "used": True})
    return M @ A, rep


def place_skull(personal: Skeleton, posed: Skeleton, A: np.ndarray) -> None:
    """Put the placed template's skull and mandible into ``personal``, mapped by ``A`` (in place)."""
    from bonecap.model import Bone

    # the rigid part of A keeps the ISB frame; the rest reshapes the mesh
    U, _, Vt = np.linalg.svd(A[:3, :3])
    R = U @ Vt
    for name in ("skull", "mandible"):
        pb = posed.bones.get(name)
        if pb is None:
            continue
        T_new = np.eye(4)
        T_new[:3, :3] = R @ pb.bone_to_world[:3, :3]
        T_new[:3, 3] = A[:3, :3] @ pb.bone_to_world[:3, 3] + A[:3, 3]
        inv = np.linalg.inv(T_new)

        def move(p_local: np.ndarray, _pb=pb, _inv=inv) -> np.ndarray:
            w = p_local @ _pb.bone_to_world[:3, :3].T + _pb.bone_to_world[:3, 3]
            w = w @ A[:3, :3].T + A[:3, 3]
            return w @ _inv[:3, :3].T + _inv[:3, 3]

        mesh = Mesh(move(pb.mesh.vertices), pb.mesh.faces.copy(), name) if pb.mesh is not None else None
        inner = Mesh(move(pb.inner_mesh.vertices), pb.inner_mesh.faces.copy(), name) \
            if pb.inner_mesh is not None else None
        personal.bones[name] = Bone(
            name, personal.bones[name].parent, mesh, T_new,
            joint_centres={k: move(v[None])[0] for k, v in pb.joint_centres.items()},
            joint_axes=dict(pb.joint_axes),  # frame-relative: unchanged by the rigid part
            landmarks={k: move(v[None])[0] for k, v in pb.landmarks.items()}, inner_mesh=inner,
            metadata={**pb.metadata, "source": "template fitted to the head's skin"})
