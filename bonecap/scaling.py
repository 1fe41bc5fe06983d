"""Scaling a template skeleton bone by bone (the no-MRI path of build-subject).

Without MRI a lab scales a template to the subject from a static trial, as
OpenSim's Scale tool does. Here each bone gets one uniform factor ``s_b``
(a length ratio), applied in the bone's own frame; the skeleton is then
reassembled so that every child's proximal joint centre lands on its
parent's (scaled) joint centre, keeping each joint's reference orientation.

The factors are fitted to the static trial rather than read from a table of
marker pairs: with the bones posed to the static markers, the factor that
best maps a bone's *placed* markers onto its *measured* ones, both taken
relative to the bone's proximal joint centre and projected on the bone's
length axis ``u``, is the least-squares ratio

.. math::  s_b = \\frac{\\sum_i (a_i \\cdot u)(b_i \\cdot u)}{\\sum_i (a_i \\cdot u)^2}

with ``a_i`` the placed and ``b_i`` the measured marker offsets in the bone
frame. Only the length counts because a marker's distance from the bone
across it is soft tissue, which varies from person to person far more than
the skeleton does: a template whose markers sit 20-50 mm closer to the bone
than a subject's skin (an OpenSim model's MarkerSet on a well-covered thigh
or back) had its pelvis, femora and humeri scaled up by 30-45 % when the
whole offsets were compared. ``u`` runs from the proximal joint centre to the
bone's distal joint centres (their mean); a bone without a distal joint at
least ``min_span_mm`` away, or the root, uses the direction of its markers'
largest spread (the pelvis: across, ASIS to ASIS, as the pairs of
measurement-based scaling do). Bones without enough markers along their
length take the factor of their nearest scaled relative (parent first),
then the global factor.

References
----------
.. [1] Delp SL et al. (2007). OpenSim: open-source software to create and
   analyze dynamic simulations of movement. IEEE TBME 54(11):1940-1950
   (marker-based scaling).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from bonecap.model import Bone, Mesh, Skeleton
from bonecap.skeleton.kinematics import proximal_joint

__all__ = ["scale_skeleton", "similarity_fit", "fit_scale_factors", "length_axis"]


def _scaled_mesh(mesh: Mesh | None, s: float) -> Mesh | None:
    if mesh is None:
        return None
    return Mesh(mesh.vertices * s, mesh.faces.copy(), mesh.frame)


def scale_skeleton(skeleton: Skeleton, scales: Mapping[str, float], default: float = 1.0) -> Skeleton:
    """Scale each bone uniformly in its own frame and reassemble the skeleton.

    Parameters
    ----------
    skeleton : Skeleton
        Bones in parent-before-child order (any world frame).
    scales : mapping of str -> float
        Length factor per bone; bones left out use ``default``.
    default : float
        Factor for bones not in ``scales``.

    Returns
    -------
    Skeleton
        Same bone names and frames' orientations; meshes, joint centres and
        landmarks scaled about each bone's origin; the root keeps its pose;
        each child is translated so that its proximal joint centre meets the
        parent's. A child that shares no joint centre with its parent keeps
        its offset from the parent's origin, scaled by the parent's factor.

    Raises
    ------
    ValueError
        If a factor is not finite and positive, or names an unknown bone.
    """
    unknown = set(scales) - set(skeleton.bones)
    if unknown:
        raise ValueError(f"scale factors given for bones not in the skeleton: {sorted(unknown)}")
    for name, s in scales.items():
        if not (np.isfinite(s) and s > 0):
            raise ValueError(f"scale factor of bone {name!r} must be finite and positive, got {s}")
    out: dict[str, Bone] = {}
    for name, b in skeleton.bones.items():
        s = float(scales.get(name, default))
        T = b.bone_to_world.copy()
        if b.parent is not None:
            parent_old = skeleton.bones[b.parent]
            parent_new = out[b.parent]
            try:
                jname, _, c_child = proximal_joint(skeleton, name)
                target = parent_new.landmark_in_world(jname)
                T[:3, 3] = target - T[:3, :3] @ (c_child * s)
            except ValueError:
                sp = float(scales.get(b.parent, default))
                rel = np.linalg.solve(parent_old.bone_to_world, b.bone_to_world)
                rel[:3, 3] *= sp
                T = parent_new.bone_to_world @ rel
        out[name] = Bone(
            name=name, parent=b.parent, mesh=_scaled_mesh(b.mesh, s), inner_mesh=_scaled_mesh(b.inner_mesh, s),
            bone_to_world=T,
            joint_centres={k: v * s for k, v in b.joint_centres.items()},
            joint_axes=dict(b.joint_axes),
            landmarks={k: v * s for k, v in b.landmarks.items()},
            # cumulative, so that markers given by location (OpenSim's) scale with a twice-scaled bone
            metadata={**b.metadata, "scale_factor": float(b.metadata.get("scale_factor", 1.0)) * s},
        )
    return Skeleton(bones=out, world=skeleton.world, metadata=dict(skeleton.metadata))


def similarity_fit(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray]:
    """Least-squares similarity transform (scale, rotation, translation), Umeyama 1991.

    Parameters
    ----------
    source, target : ndarray (N, 3)
        Corresponding points (NaN rows are ignored), N >= 3 non-collinear.

    Returns
    -------
    scale : float
    T : ndarray (4, 4)
        ``target ≈ T @ [source, 1]`` with ``T[:3, :3] = scale * R``.
    """
    source = np.asarray(source, float)
    target = np.asarray(target, float)
    ok = np.isfinite(source).all(1) & np.isfinite(target).all(1)
    if ok.sum() < 3:
        raise ValueError(f"a similarity fit needs at least 3 corresponding points, got {int(ok.sum())}")
    a, b = source[ok], target[ok]
    ma, mb = a.mean(0), b.mean(0)
    A, B = a - ma, b - mb
    U, S, Vt = np.linalg.svd(B.T @ A / len(a))
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.diag([1.0, 1.0, d])
    R = U @ D @ Vt
    var_a = (A ** 2).sum() / len(a)
    scale = float(np.trace(np.diag(S) @ D) / var_a)
    T = np.eye(4)
    T[:3, :3] = scale * R
    T[:3, 3] = mb - scale * R @ ma
    return scale, T


def length_axis(skeleton: Skeleton, bone: str, markers_local: np.ndarray | None = None, *,
                min_span_mm: float = 60.0) -> np.ndarray:
    """The unit direction along which a bone's length is measured, in its own frame.

    Parameters
    ----------
    skeleton : Skeleton
    bone : str
    markers_local : ndarray (N, 3), optional
        Markers on the bone (its frame, mm), for bones without a usable joint axis.
    min_span_mm : float
        A distal joint centre nearer than this to the proximal one (the ulna's
        radio-ulnar joint, beside the elbow) does not give the length.

    Returns
    -------
    ndarray (3,)
        From the proximal joint centre towards the mean of the distal joint
        centres; for the root, or a bone with no distal joint far enough, the
        principal direction of the markers' spread about their centroid (its
        sign is arbitrary: only the projection's square and products count);
        the bone frame's Y (the long axis of ISB frames and OpenSim bodies)
        when there is neither.
    """
    b = skeleton.bones[bone]
    if b.parent is not None:
        try:
            jname, _, c = proximal_joint(skeleton, bone)
            distal = [np.asarray(p, float) - c for k, p in b.joint_centres.items() if k != jname]
            distal = [d for d in distal if np.linalg.norm(d) >= min_span_mm]
            if distal:
                axis = np.mean(distal, axis=0)
                if np.linalg.norm(axis) >= min_span_mm:
                    return axis / np.linalg.norm(axis)
        except ValueError:
            pass
    if markers_local is not None:
        pts = np.asarray(markers_local, float)
        pts = pts[np.isfinite(pts).all(1)]
        if len(pts) >= 2:
            _, _, vt = np.linalg.svd(pts - pts.mean(0))
            return vt[0]
    return np.array([0.0, 1.0, 0.0])


def fit_scale_factors(skeleton: Skeleton, marker_bones: list[str], placed_local: np.ndarray,
                      measured_local: np.ndarray, *, min_markers: int = 2, min_span_mm: float = 60.0,
                      limits: tuple[float, float] = (0.7, 1.4), fallback: float = 1.0,
                      along_length: bool = True) -> dict[str, float]:
    """Per-bone length factors from placed vs measured marker positions in the bone frames.

    Parameters
    ----------
    skeleton : Skeleton
        The skeleton the placed markers sit on (its bone frames).
    marker_bones : list of str
        Bone of each marker.
    placed_local, measured_local : ndarray (M, 3)
        Each marker where the template puts it and where the static trial saw
        it, both in its bone's frame (mm; NaN where unseen).
    min_markers : int
        Fewest markers for a bone to get its own factor.
    min_span_mm : float
        The markers' offsets from the proximal joint must reach at least this
        far, or the ratio is too noisy to use (a cluster at the joint).
    limits : (float, float)
        Factors are clipped to this range (a bad marker must not halve a bone).
    fallback : float
        Factor for bones that get none from markers or relatives.
    along_length : bool
        Compare the offsets along the bone's length axis only
        (:func:`length_axis`; the default, see the module notes); False compares
        the whole offsets.

    Returns
    -------
    dict of str -> float
        A factor for every bone of ``skeleton``.
    """
    placed_local = np.asarray(placed_local, float)
    measured_local = np.asarray(measured_local, float)
    own: dict[str, float] = {}
    bones = np.asarray(marker_bones)
    for name, b in skeleton.bones.items():
        idx = np.flatnonzero(bones == name)
        if len(idx) < min_markers:
            continue
        try:
            jname, _, c = proximal_joint(skeleton, name)
        except ValueError:
            c = np.zeros(3)
        a = placed_local[idx] - c
        m = measured_local[idx] - c
        ok = np.isfinite(a).all(1) & np.isfinite(m).all(1)
        if ok.sum() < min_markers:
            continue
        if along_length:
            u = length_axis(skeleton, name, placed_local[idx][ok], min_span_mm=min_span_mm)
            a, m = (a[ok] @ u)[:, None], (m[ok] @ u)[:, None]
        else:
            a, m = a[ok], m[ok]
        if np.linalg.norm(a, axis=1).max() < min_span_mm:
            continue
        s = float((a * m).sum() / (a * a).sum())
        own[name] = float(np.clip(s, *limits))
    out: dict[str, float] = {}
    children: dict[str, list[str]] = {}
    for name, b in skeleton.bones.items():
        if b.parent is not None:
            children.setdefault(b.parent, []).append(name)
    glob = float(np.median(list(own.values()))) if own else fallback
    for name, b in skeleton.bones.items():
        if name in own:
            out[name] = own[name]
            continue
        # nearest relative with its own factor: the parent chain first (a hand
        # follows its forearm), then the children (a sacrum follows the hips)
        p = b.parent
        while p is not None and p not in own:
            p = skeleton.bones[p].parent
        kids = [c for c in children.get(name, []) if c in own]
        out[name] = own[p] if p is not None else (float(np.mean([own[k] for k in kids])) if kids else glob)
    return out


def load_scaling_groups(marker_set) -> dict[str, dict]:
    """The ``scaling`` section of a marker set's YAML (following ``extends``), or ``{}``.

    Each group: ``bones`` (scaled together) and ``pairs`` (marker pairs whose
    distance ratio, static over template, gives the group's factor).
    """
    from pathlib import Path

    from bonecap.io import load_yaml
    from bonecap.markers import _resolve_path

    source = getattr(marker_set, "source", "")
    if not source or not str(source).endswith((".yaml", ".yml")):
        return {}
    groups: dict[str, dict] = {}
    path, seen = Path(source), set()
    chain = []
    while path is not None and str(path) not in seen:
        seen.add(str(path))
        doc = load_yaml(path.read_text()) or {}
        chain.append(doc.get("scaling") or {})
        parent = doc.get("extends")
        path = _resolve_path(parent) if parent else None
    for part in reversed(chain):  # the extending set wins
        groups.update(part)
    return groups


def scale_factors_from_pairs(skeleton: Skeleton, groups: Mapping[str, dict], placed: Mapping[str, np.ndarray],
                             measured: Mapping[str, np.ndarray], *, default: float = 1.0,
                             limits: tuple[float, float] = (0.6, 1.6)) -> tuple[dict[str, float], dict[str, float]]:
    """Per-bone factors from marker-pair distances (OpenSim's measurement-based scaling).

    Parameters
    ----------
    skeleton : Skeleton
        The template.
    groups : mapping
        From :func:`load_scaling_groups`.
    placed : mapping of str -> (3,)
        Markers placed on the template (its world frame, mm).
    measured : mapping of str -> (3,)
        The static trial's markers (lab, mm). Distances do not depend on the frame.
    default : float
        Factor of groups with no measurable pair (e.g. the global similarity scale).
    limits : (float, float)
        A group's factor is clipped to ``default`` times this range.

    Returns
    -------
    factors : dict of str -> float
        Every bone of the skeleton: its group's factor, else its nearest
        ancestor's, else ``default``.
    group_factors : dict of str -> float
        Per group, the factor measured (groups without pairs are left out).
    """
    group_factors: dict[str, float] = {}
    own: dict[str, float] = {}
    for gname, g in groups.items():
        ratios = []
        for a, b in g.get("pairs", []):
            if a in placed and b in placed and a in measured and b in measured:
                dt = np.linalg.norm(np.asarray(placed[a]) - placed[b])
                dm = np.linalg.norm(np.asarray(measured[a]) - measured[b])
                if dt > 1e-6 and np.isfinite(dm):
                    ratios.append(dm / dt)
        if not ratios:
            continue
        f = float(np.clip(np.mean(ratios), default * limits[0], default * limits[1]))
        group_factors[gname] = f
        for bone in g.get("bones", []):
            if bone in skeleton.bones:
                own[bone] = f
    out = {}
    for name, b in skeleton.bones.items():
        p = name
        while p is not None and p not in own:
            p = skeleton.bones[p].parent
        out[name] = own[p] if p is not None else default
    return out, group_factors
