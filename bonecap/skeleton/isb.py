"""ISB bone frames from landmarks, for skeletons whose bones have been reshaped.

The generic skeleton (:mod:`bonecap.skeleton.generic`) defines the frame of each
long bone from its palpable landmarks, as the ISB recommends (Wu et al. 2002,
2005): the femur from the hip centre and the epicondyles, the tibia from the
malleoli and the condyles, and so on. A personal skeleton made by warping the
template (:mod:`bonecap.skeleton.warp`) moves every landmark with the warp, but
a frame carried along as a rigid body (the affine's rotation, the warped
origin) no longer sits on them: the tibia's origin, the midpoint of the two
malleoli, lies between tibia and fibula, where neither bone's warp has feature
points, and drifted by 15-25 mm on the phantom. :func:`refresh_isb_frames`
rebuilds those frames' origins (and, on request, orientations) from the warped
landmarks with the same definitions, so a personal bone's frame means what the
template's (and the phantom truth's) means.

Definitions are written once, for either side: axis signs are taken from the
bone's current frame (anterior X, proximal Y, rightward Z on both sides, the
convention of the generic skeleton), so no world direction is assumed (the
skeleton may be in the model frame or in the MRI's LPS). A definition is only
applied where it reproduces the *template's* frame (an OpenSim model's bodies,
for example, are not ISB frames and are left alone).

References
----------
.. [1] Wu G et al. (2002). ISB recommendation on definitions of joint coordinate
   system of various joints for the reporting of human joint motion -- part I:
   ankle, hip, and spine. J Biomech 35(4):543-548.
.. [2] Wu G et al. (2005). ISB recommendation ... part II: shoulder, elbow, wrist
   and hand. J Biomech 38(5):981-992.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from bonecap.model import Bone, Mesh, Skeleton

__all__ = ["ISB_FRAMES", "SHARED_FRAMES", "isb_frame", "refresh_isb_frames", "DISTAL_FIBULA_WINDOW",
           "MAX_MALLEOLAR_TURN_DEG", "distal_fibula_bearing", "distal_torsion", "malleolar_turns", "malleolar_frames",
           "reframe_bone"]

#: Bones whose frame *is* another bone's (stem names, either side): ISB's tibia/fibula frame is one
#: segment's [1]_, and the generic skeleton gives the fibula the tibia's frame. A warp carries each
#: bone's rotation separately (its own rigid fit), which left the personal fibula's frame 1-3 deg off
#: its tibia's about the long axis on phantoms of seeds 1-3 (the thin fibula's fit is the looser:
#: 1.9-6.5 deg from the truth where the tibia was 0.2-5.9).
SHARED_FRAMES: dict[str, str] = {"fibula": "tibia"}

Lookup = Callable[[str, str], np.ndarray]


def _femur(lk: Lookup, s: str):
    # Wu 2002: origin hip centre; Y from mid(LE, ME) to it; Z along ME -> LE (lateral)
    hc = lk(f"femur{s}", "hip")
    le, me = lk(f"femur{s}", "lateral_epicondyle"), lk(f"femur{s}", "medial_epicondyle")
    return ("y", hc - 0.5 * (le + me)), ("z", le - me), hc


def _tibia(lk: Lookup, s: str):
    # Wu 2002: origin mid(MM, LM); Z along MM -> LM; X normal to the plane (IC, MM, LM)
    mm, lm = lk(f"tibia{s}", "medial_malleolus"), lk(f"fibula{s}", "lateral_malleolus")
    ic = 0.5 * (lk(f"tibia{s}", "medial_condyle") + lk(f"tibia{s}", "lateral_condyle"))
    im = 0.5 * (mm + lm)
    return ("z", lm - mm), ("x", np.cross(ic - im, lm - mm)), im


def _humerus(lk: Lookup, s: str):
    # Wu 2005 option 1: origin GH; Y from mid(EL, EM) to GH; X normal to (EL, EM, GH)
    gh = lk(f"humerus{s}", "shoulder")
    el, em = lk(f"humerus{s}", "lateral_epicondyle"), lk(f"humerus{s}", "medial_epicondyle")
    return ("y", gh - 0.5 * (el + em)), ("x", np.cross(el - gh, em - gh)), gh


def _ulna(lk: Lookup, s: str):
    # Wu 2005: origin US; Y from US to mid(EL, EM); X normal to (US, EL, EM)
    us = lk(f"ulna{s}", "ulnar_styloid")
    el, em = lk(f"humerus{s}", "lateral_epicondyle"), lk(f"humerus{s}", "medial_epicondyle")
    return ("y", 0.5 * (el + em) - us), ("x", np.cross(el - us, em - us)), us


def _radius(lk: Lookup, s: str):
    # after Wu 2005: origin RS; Y from RS to the radial head centre; X normal to (RS, US, head)
    rs, us = lk(f"radius{s}", "radial_styloid"), lk(f"ulna{s}", "ulnar_styloid")
    rhc = lk(f"radius{s}", "radial_head_centre")
    return ("y", rhc - rs), ("x", np.cross(us - rs, rhc - rs)), rs


#: bone base name -> definition; bones listed in ``_SHARED`` take another bone's frame.
ISB_FRAMES = {"femur": _femur, "tibia": _tibia, "humerus": _humerus, "ulna": _ulna, "radius": _radius}
_SHARED = {"fibula": "tibia", "talus": "tibia", "calcaneus": "tibia", "foot": "tibia"}
_AXIS = {"x": 0, "y": 1, "z": 2}


def _lookup(sk: Skeleton) -> Lookup:
    def lk(bone: str, name: str) -> np.ndarray:
        b = sk.bones[bone]
        p = b.landmarks.get(name)
        if p is None:
            p = b.joint_centres[name]
        return b.bone_to_world[:3, :3] @ np.asarray(p, float) + b.bone_to_world[:3, 3]
    return lk


def _split(name: str) -> tuple[str, str]:
    if name[-2:] in ("_r", "_l"):
        return name[:-2], name[-2:]
    return name, ""


def isb_frame(skeleton: Skeleton, name: str) -> np.ndarray | None:
    """The ISB ``bone_to_world`` of one bone from the skeleton's landmarks (world frame of the skeleton).

    Parameters
    ----------
    skeleton : Skeleton
    name : str
        A bone of :data:`ISB_FRAMES` or one sharing such a frame (fibula, talus,
        calcaneus and foot take the tibia's), with its side suffix.

    Returns
    -------
    ndarray (4, 4) or None
        None when the bone has no definition or a landmark is missing. Axis
        signs follow the bone's current frame (the definitions fix each axis
        only up to its sign).
    """
    base, s = _split(name)
    owner = _SHARED.get(base, base)
    if owner not in ISB_FRAMES or name not in skeleton.bones or f"{owner}{s}" not in skeleton.bones:
        return None
    try:
        (a1, v1), (a2, v2), origin = ISB_FRAMES[owner](_lookup(skeleton), s)
    except KeyError:
        return None
    cur = skeleton.bones[f"{owner}{s}"].bone_to_world[:3, :3]
    v1 = np.asarray(v1, float)
    v2 = np.asarray(v2, float)
    if not (np.linalg.norm(v1) > 1e-9 and np.linalg.norm(v2) > 1e-9):
        return None
    v1 = v1 / np.linalg.norm(v1) * np.sign(v1 @ cur[:, _AXIS[a1]] or 1.0)
    v2 = v2 - (v2 @ v1) * v1
    if np.linalg.norm(v2) < 1e-9:
        return None
    v2 = v2 / np.linalg.norm(v2) * np.sign(v2 @ cur[:, _AXIS[a2]] or 1.0)
    R = np.zeros((3, 3))
    R[:, _AXIS[a1]], R[:, _AXIS[a2]] = v1, v2
    a3 = 3 - _AXIS[a1] - _AXIS[a2]
    # the third axis completes a right-handed frame: x = y cross z, y = z cross x, z = x cross y
    R[:, a3] = np.cross(R[:, (a3 + 1) % 3], R[:, (a3 + 2) % 3])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, origin
    return T


def _reframe(bone: Bone, T_new: np.ndarray) -> Bone:
    """The same bone in world, described in a new frame (meshes, landmarks, joints re-expressed)."""
    M = np.linalg.solve(T_new, bone.bone_to_world)          # old local -> new local
    R, t = M[:3, :3], M[:3, 3]

    def pts(p):
        return np.asarray(p, float) @ R.T + t

    def mesh(m: Mesh | None) -> Mesh | None:
        return None if m is None else Mesh(pts(m.vertices), m.faces.copy(), m.frame)

    return Bone(name=bone.name, parent=bone.parent, mesh=mesh(bone.mesh), bone_to_world=T_new.copy(),
                joint_centres={k: pts(v) for k, v in bone.joint_centres.items()},
                joint_axes={k: R @ np.asarray(v, float) for k, v in bone.joint_axes.items()},
                landmarks={k: pts(v) for k, v in bone.landmarks.items()}, inner_mesh=mesh(bone.inner_mesh),
                metadata=dict(bone.metadata))


def refresh_isb_frames(skeleton: Skeleton, template: Skeleton, tol_deg: float = 0.05, tol_mm: float = 0.05,
                       rotation: bool = False) -> tuple[Skeleton, dict[str, dict[str, float]]]:
    """Rebuild the ISB frames of reshaped bones from their own landmarks.

    Parameters
    ----------
    skeleton : Skeleton
        A personal skeleton (e.g. the warped template), any world frame.
    template : Skeleton
        The skeleton it was made from. A bone is re-framed only where its
        definition reproduces the template's frame within ``tol_deg`` / ``tol_mm``
        (so that the definition is the one the template was built with).
    rotation : bool
        Also rebuild the orientation. Off by default: the origin is one or two
        landmarks, but an orientation hangs on landmark *differences* a few
        centimetres apart (the malleoli are ~65 mm apart, so 10 mm of landmark
        error turns the tibia's Z axis by ~9 degrees), while the carried
        rotation is fitted to every surface point of the bone. On the phantom
        (seed 1), rebuilding the rotation too made the tibia 17 degrees wrong
        instead of 4, the origin alone took its 23 mm error to 11 mm.

    A bone of :data:`SHARED_FRAMES` whose template frame is its owner's (the
    fibula's, the tibia's) takes the owner's personal frame.

    Returns
    -------
    skeleton : Skeleton
        A copy with the frames rebuilt; every bone keeps its world geometry.
    moved : dict
        Per re-framed bone, the change: ``{"deg": ..., "mm": ...}``.
    """
    from scipy.spatial.transform import Rotation

    bones = dict(skeleton.bones)
    moved: dict[str, dict[str, float]] = {}
    for name, bone in skeleton.bones.items():
        if name not in template.bones:
            continue
        T_ref = isb_frame(template, name)
        T0 = template.bones[name].bone_to_world
        if T_ref is None or not _close(T_ref, T0, tol_deg, tol_mm):
            continue
        T_new = isb_frame(skeleton, name)
        if T_new is None:
            continue
        if not rotation:
            T_new[:3, :3] = bone.bone_to_world[:3, :3]
        dR = Rotation.from_matrix(bone.bone_to_world[:3, :3].T @ T_new[:3, :3]).magnitude()
        moved[name] = {"deg": float(np.degrees(dR)),
                       "mm": float(np.linalg.norm(T_new[:3, 3] - bone.bone_to_world[:3, 3]))}
        bones[name] = _reframe(bone, T_new)
    # a shared frame is its owner's, rebuilt or not: where the template has them equal
    for name, bone in skeleton.bones.items():
        stem, side = (name[:-2], name[-2:]) if name.endswith(("_r", "_l")) else (name, "")
        owner = SHARED_FRAMES[stem] + side if stem in SHARED_FRAMES else None
        if owner is None or owner not in bones or name not in template.bones or owner not in template.bones:
            continue
        if not _close(template.bones[name].bone_to_world, template.bones[owner].bone_to_world, tol_deg, tol_mm):
            continue
        T_new = bones[owner].bone_to_world.copy()
        dR = Rotation.from_matrix(bone.bone_to_world[:3, :3].T @ T_new[:3, :3]).magnitude()
        moved[name] = {"deg": float(np.degrees(dR)),
                       "mm": float(np.linalg.norm(T_new[:3, 3] - bone.bone_to_world[:3, 3]))}
        bones[name] = _reframe(bones[name], T_new)
    out = Skeleton(bones=bones, world=skeleton.world, metadata=dict(skeleton.metadata))
    return out, moved


def _close(A: np.ndarray, B: np.ndarray, tol_deg: float, tol_mm: float) -> bool:
    c = np.clip((np.trace(A[:3, :3].T @ B[:3, :3]) - 1) / 2, -1.0, 1.0)
    return float(np.degrees(np.arccos(c))) <= tol_deg and float(np.linalg.norm(A[:3, 3] - B[:3, 3])) <= tol_mm


#: Where along the tibia (fractions of its length from its distal end) :func:`distal_fibula_bearing`
#: reads the fibula's bearing: 5-20 %, above the ankle joint (the extractions lose the malleoli's
#: tips) and below the mid-shaft (where the bearing varied by +-4 deg between phantom seeds).
DISTAL_FIBULA_WINDOW = (0.05, 0.2)
#: The largest turn :func:`malleolar_turns` applies (deg); beyond it the meshes are not trusted.
MAX_MALLEOLAR_TURN_DEG = 15.0


def distal_fibula_bearing(skeleton: Skeleton, side: str, window: tuple[float, float] = DISTAL_FIBULA_WINDOW
                          ) -> float | None:
    """Bearing of the fibula from the tibia above the ankle, in the tibia's frame (deg about its Y).

    The mean of the fibula's surface points minus the tibia's, over the slab
    ``window`` (fractions of the tibia's length from its distal end, along
    the tibia frame's Y), as ``atan2(x, z)`` in the tibia's frame (X
    anterior, Y proximal, Z to the right on both sides).

    Parameters
    ----------
    skeleton : Skeleton
        Any world frame; needs the ``tibia<side>`` and ``fibula<side>`` meshes.
    side : {"_r", "_l"}
    window : (float, float)

    Returns
    -------
    float or None
        Degrees in (-180, 180]; None without both meshes or with fewer than ten
        vertices of either bone in the slab.
    """
    if side not in ("_r", "_l"):
        raise ValueError(f"side must be '_r' or '_l', got {side!r}")
    if not 0.0 <= window[0] < window[1] <= 1.0:
        raise ValueError(f"window must be two fractions 0 <= lo < hi <= 1, got {window!r}")
    slab = _distal_slab(skeleton, side, window)
    if slab is None:
        return None
    t, f, _, _ = slab
    v = f.mean(axis=0) - t.mean(axis=0)
    return float(np.degrees(np.arctan2(v[0], v[2])))


def _distal_slab(skeleton: Skeleton, side: str, window: tuple[float, float], dense: bool = False
                 ) -> tuple[np.ndarray, np.ndarray, float, float] | None:
    """The tibia's and the fibula's surface points over ``window`` (fractions of the tibia's length from its
    distal end, along the tibia frame's Y), in the tibia's frame, with the tibia's distal end and length
    along Y; ``dense``: the meshes subdivided once first (about four times the vertices; the same extent).
    None without both meshes or with fewer than ten points of either bone there."""
    import trimesh

    tib, fib = skeleton.bones.get("tibia" + side), skeleton.bones.get("fibula" + side)
    if tib is None or fib is None or tib.mesh is None or fib.mesh is None:
        return None
    M = np.linalg.solve(tib.bone_to_world, fib.bone_to_world)        # fibula frame -> tibia frame

    def points(m: Mesh) -> np.ndarray:
        v = np.asarray(m.vertices, float)
        return trimesh.remesh.subdivide(v, np.asarray(m.faces))[0] if dense else v

    t = points(tib.mesh)
    f = points(fib.mesh) @ M[:3, :3].T + M[:3, 3]
    y0, y1 = float(t[:, 1].min()), float(t[:, 1].max())
    lo, hi = y0 + window[0] * (y1 - y0), y0 + window[1] * (y1 - y0)
    ts, fs = t[(t[:, 1] > lo) & (t[:, 1] < hi)], f[(f[:, 1] > lo) & (f[:, 1] < hi)]
    if len(ts) < 10 or len(fs) < 10:
        return None
    return ts, fs, y0, y1 - y0


def distal_torsion(skeleton: Skeleton, template: Skeleton, side: str,
                   window: tuple[float, float] = DISTAL_FIBULA_WINDOW, *, iterations: int = 40,
                   keep: float = 0.9) -> float | None:
    """The turn of a tibia's frame about its long axis that makes its distal tibia and fibula lie as the template's.

    The template's tibia and fibula over ``window`` (fractions of the tibia's
    length from its distal end, along the tibia frame's Y), in its tibia
    frame, are registered onto the skeleton's, in its own: a rotation about
    Y, and a shift and a size factor across it (a person's sections are
    larger or smaller; heights are compared as fractions of each tibia's
    length), by iterated closest points [1]_ from the turn of
    :func:`distal_fibula_bearing`, the worst ``1 - keep`` of the pairs left
    out each round, each round's fit the two-dimensional similarity of the
    transverse coordinates [2]_, weighted so that each bone counts as much
    as the other. Both bones' surfaces take part: the fibula's place beside
    the tibia and the shape of the tibia's own section, where
    :func:`distal_fibula_bearing` reads the fibula's centroid only (a fibula
    lying 1.5 mm further forward: 1.6 deg here, 2.7 there).

    Parameters
    ----------
    skeleton, template : Skeleton
        Any world frames; both need ``tibia<side>`` and ``fibula<side>`` meshes.
    side : {"_r", "_l"}
    window : (float, float)
    iterations : int
        Closest-point rounds (>= 1).
    keep : float
        Fraction of the pairs kept each round, in (0, 1].

    Returns
    -------
    float or None
        Degrees about the skeleton's tibia frame's Y: turning that frame by it
        (``T @ Ry``) puts the skeleton's distal tibia and fibula as the
        template's lie in its frame; None without both bones' meshes, or with
        fewer than ten vertices of either bone in the window, on either skeleton.

    References
    ----------
    .. [1] Besl PJ, McKay ND (1992). A method for registration of 3-D shapes. IEEE PAMI 14(2):239-256.
    .. [2] Umeyama S (1991). Least-squares estimation of transformation parameters between two point
       patterns. IEEE PAMI 13(4):376-380.
    """
    from scipy.spatial import cKDTree

    if side not in ("_r", "_l"):
        raise ValueError(f"side must be '_r' or '_l', got {side!r}")
    if not 0.0 <= window[0] < window[1] <= 1.0:
        raise ValueError(f"window must be two fractions 0 <= lo < hi <= 1, got {window!r}")
    if iterations < 1 or not 0.0 < keep <= 1.0:
        raise ValueError(f"iterations >= 1 and keep in (0, 1] expected, got {iterations!r}, {keep!r}")
    a_, b_ = _distal_slab(template, side, window, dense=True), _distal_slab(skeleton, side, window, dense=True)
    if a_ is None or b_ is None:
        return None
    # both bones' points, heights from the tibia's distal end
    A, B = np.vstack(a_[:2]), np.vstack(b_[:2])
    # each bone counts as one: the tibia's nearly round section, with 3-4 times the fibula's surface, holds the
    # turn poorly, and its surface's noise read as turn where the fibula's place beside it is the cue (over
    # twelve phantom tibiae 1.28 deg RMS with the points counted alike, 1.15 with the bones weighted alike)
    wA = np.r_[np.ones(len(a_[0])), np.full(len(a_[1]), len(a_[0]) / len(a_[1]))]
    A[:, 1] -= a_[2]
    B[:, 1] -= b_[2]
    length_a, length_b = a_[3], b_[3]
    a0 = A[:, [0, 2]] - A[:, [0, 2]].mean(axis=0)               # transverse (X, Z), centred
    B[:, [0, 2]] -= B[:, [0, 2]].mean(axis=0)
    B[:, 1] *= length_a / length_b                              # heights as the template's: a longer shank's too
    tree = cKDTree(B)
    # started from the fibula's bearing (closest points alone fall into a nearer minimum of these
    # nearly round sections beyond ~15 deg: 19.6 of a 25 deg turn)
    a_t, a_p = distal_fibula_bearing(template, side, window), distal_fibula_bearing(skeleton, side, window)
    th = np.radians((a_p - a_t + 180.0) % 360.0 - 180.0) if a_t is not None and a_p is not None else 0.0
    shift, scale = np.zeros(2), 1.0
    for _ in range(iterations):
        c, s_ = np.cos(th), np.sin(th)
        R2 = np.array([[c, s_], [-s_, c]])                      # Ry(th) on (x, z)
        P = np.column_stack([scale * a0 @ R2.T + shift, A[:, 1]])[:, [0, 2, 1]]
        d, j = tree.query(P)
        sel = d <= np.quantile(d, keep)
        a, b, w = a0[sel], B[j[sel]][:, [0, 2]], wA[sel]
        am, bm = w @ a / w.sum(), w @ b / w.sum()
        U, S, Vt = np.linalg.svd((w[:, None] * (a - am)).T @ (b - bm))
        D = np.diag([1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
        R2 = Vt.T @ D @ U.T                                      # a -> b
        # the sections' size too (Umeyama's factor): a person's bones 6 % larger than the template's, fitted
        # without it, read 0.5 deg of turn they do not have
        scale = float(np.sum(S * np.diag(D)) / np.sum(w[:, None] * (a - am) ** 2))
        th_new = float(np.arctan2(R2[0, 1], R2[0, 0]))
        shift = bm - scale * R2 @ am
        if abs(th_new - th) < 1e-9:
            th = th_new
            break
        th = th_new
    return float(np.degrees(th))


def malleolar_turns(skeleton: Skeleton, template: Skeleton, measured, max_deg: float = MAX_MALLEOLAR_TURN_DEG
                    ) -> dict[str, float]:
    """Per tibia, the turn of its frame about its long axis that puts the malleoli where ISB wants them.

    The ISB tibia/fibula frame takes its twist from the malleoli [1]_. A warp
    carries each bone's frame with its rigid fit, which the condyles and the
    shaft decide, so the personal frame inherits the template's tibial torsion
    (drawn from 10-30 deg on the phantoms): it was -5.9 to +3.9 deg off the
    truth about the long axis on six phantom subjects. The malleoli's own
    landmarks cannot correct it: they sit where the extraction is worst (the
    tibia runs into the talus, the fibula stops short of its tip), and 10 mm
    of error on landmarks 65 mm apart is 9 deg. The fibula's bearing from the
    tibia a few centimetres higher (:func:`distal_fibula_bearing`) turns with
    the malleoli and both bones' extractions measure it: in the truth's own
    frame it was within 0.6 deg of the template's on those phantoms. The turn
    is :func:`distal_torsion`: the template's distal tibia and fibula over
    that window registered onto the skeleton's about the long axis, both
    surfaces, and their size (the bearing of the fibula's centroid alone left
    the frames 0.0-3.0 deg off about the long axis, 1.8 deg RMS, over eight
    tibiae of four phantom subjects; the surfaces 0.0-2.5 deg, 1.3 deg RMS).

    Parameters
    ----------
    skeleton : Skeleton
        The warped personal skeleton (any world frame).
    template : Skeleton
        The template it was warped from (its frames the definition's).
    measured : collection of str
        Bones warped onto their own extracted surfaces; a side is turned only
        where its tibia and fibula both are.
    max_deg : float
        Larger turns are not applied (the side is left out).

    Returns
    -------
    dict of str -> float
        ``tibia_r`` / ``tibia_l`` -> degrees about that tibia frame's Y.

    References
    ----------
    .. [1] Wu G et al. (2002), see the module.
    """
    if not max_deg > 0:
        raise ValueError(f"max_deg must be positive, got {max_deg!r}")
    measured = set(measured)
    out: dict[str, float] = {}
    for side in ("_r", "_l"):
        tib, fib = "tibia" + side, "fibula" + side
        if not {tib, fib} <= measured or tib not in template.bones or fib not in template.bones:
            continue
        d = distal_torsion(skeleton, template, side)
        if d is not None and abs(d) <= max_deg:
            out[tib] = float(d)
    return out


def malleolar_frames(skeleton: Skeleton, turns: dict[str, float], measured=()) -> dict[str, np.ndarray]:
    """New bone-to-world frames for :func:`malleolar_turns`: the tibia's, its fibula's, the foot's.

    Only frames turn: the bones stay where they are in world (apply with
    :func:`reframe_bone`). The tibia's frame turns by ``turns[tibia]`` about its
    own Y; the fibula's, where it is the tibia's (:data:`SHARED_FRAMES`), is
    the new tibia frame; the bones below the ankle that no scan measured
    (talus, calcaneus, foot: placed with the tibia's carried rotation, and the
    talus sits in the malleoli's mortise) turn their frames by the same world
    rotation.

    Parameters
    ----------
    skeleton : Skeleton
    turns : dict of str -> float
        Tibia name -> degrees about its frame's Y.
    measured : collection of str
        Bones with their own extracted surface (their frames are kept).

    Returns
    -------
    dict of str -> ndarray (4, 4)
        Bone name -> new bone-to-world transform (same world frame).
    """
    from scipy.spatial.transform import Rotation

    from bonecap.skeleton.kinematics import subtree

    measured = set(measured)
    out: dict[str, np.ndarray] = {}
    for tib, deg in turns.items():
        if tib not in skeleton.bones:
            raise ValueError(f"malleolar_frames: no bone {tib!r}")
        T = skeleton.bones[tib].bone_to_world
        Ry = Rotation.from_rotvec([0.0, np.radians(deg), 0.0]).as_matrix()
        T_new = T.copy()
        T_new[:3, :3] = T[:3, :3] @ Ry
        out[tib] = T_new
        W = T_new[:3, :3] @ T[:3, :3].T                                   # the same turn in world
        fib = "fibula" + tib[len("tibia"):]
        if fib in skeleton.bones and _close(skeleton.bones[fib].bone_to_world, T, 0.05, 0.05):
            out[fib] = T_new.copy()
        below = [n for c, b in skeleton.bones.items() if b.parent == tib and c != fib for n in subtree(skeleton, c)]
        for n in below:
            if n in measured:
                continue
            Tb = skeleton.bones[n].bone_to_world.copy()
            Tb[:3, :3] = W @ Tb[:3, :3]
            out[n] = Tb
    return out


def reframe_bone(bone: Bone, bone_to_world: np.ndarray) -> Bone:
    """The same bone in world, described in the frame ``bone_to_world`` (meshes, landmarks, joints re-expressed).

    Parameters
    ----------
    bone : Bone
    bone_to_world : ndarray (4, 4)
        The new frame, in the same world as ``bone.bone_to_world``.

    Returns
    -------
    Bone
    """
    T = np.asarray(bone_to_world, float)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ValueError("bone_to_world must be a finite 4x4 transform")
    return _reframe(bone, T)
