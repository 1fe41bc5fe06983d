"""The forearm pronation model of Kojima et al. (section 8.2).

Radius and ulna carry too few markers for a rigid fit, so the paper drives
them from one number, the **twist** ``theta`` measured between the wrist and
elbow marker lines (:func:`forearm_twist`). Each bone's pose at ``theta = 0``
is carried with the elbow frame (:func:`elbow_frame`) and then turned by
``f(theta)`` about the line through two **control points** that slide along
the wrist and elbow marker segments (:func:`forearm_bone_poses`).

The paper's coefficients (eq. 3', 4', 4'') are :data:`PAPER_MODEL`;
:func:`fit_forearm_model` fits a subject's own from forearm MRI poses.

Conventions
-----------
- Lab frame of the trial (Z up) or any common frame for MRI poses; mm, degrees.
- The 1-D axis of a marker segment: ``point = midpoint + u * (radial_side - other) / 2``,
  so the markers sit at ``u = +-1`` and the radial-side marker (radial
  styloid ``RWRA``, lateral epicondyle ``RELB``) at ``+1``.
- ``theta`` and ``f`` are positive in pronation for both arms: a right-hand
  rotation about the proximally pointing forearm axis for the right arm, about
  the distally pointing one for the (mirrored) left arm.
- **Unit of the paper's polynomials: quarter turns.** The paper states none.
  Its three MRI poses were at 0, 90 and 180 degrees (nominal), i.e. at
  ``theta = 0, 1, 2`` quarter turns. Read that way, at 180 degrees the radius
  turns ``90 * (-0.127 * 4 + 1.101 * 2) = 152`` degrees and the ulna
  ``90 * (0.008 * 4 - 0.134 * 2) = -21`` degrees -- the radius carries most
  of the pronation, as in vivo -- and all four control points stay within
  their marker segments (``|u| <= 1.05`` on 0-180 degrees). Read in radians
  (``theta = pi``), the ulna's wrist control point lands at ``u = -1.70``,
  far outside its segment, and in degrees the polynomials explode
  (``-0.127 * 180**2`` degrees). :data:`PAPER_MODEL` therefore uses
  ``unit="quarter_turn"``; a fitted model uses the same unit.

References
----------
.. [1] Kojima et al., section 8.2 (forearm pronation model: twist from the
   styloid and epicondyle markers, eq. 3', 4', 4'').
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["ForearmModel", "PAPER_MODEL", "forearm_twist", "elbow_frame", "forearm_bone_poses",
           "fit_forearm_model", "forearm_poses_from_markers", "FOREARM_MARKERS", "radius_axis_from_poses"]

_UNITS = {"quarter_turn": 90.0, "deg": 1.0, "rad": 180.0 / np.pi}
#: Default marker labels per side: radial styloid, ulnar styloid, lateral and medial epicondyle.
FOREARM_MARKERS = {"r": ("RWRA", "RWRB", "RELB", "RMEP"), "l": ("LWRA", "LWRB", "LELB", "LMEP")}


def _check_side(side: str) -> str:
    if side not in ("r", "l"):
        raise ValueError(f"side must be 'r' or 'l', got {side!r}")
    return side


def _points(name: str, a) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    if a.ndim == 1:
        a = a[None]
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (F, 3) or (3,) (positions in mm), got {a.shape}")
    return a


def _unit(v):
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return v / n


def forearm_twist(radial_styloid, ulnar_styloid, lateral_epicondyle, medial_epicondyle, *,
                  zero_deg: float = 0.0, side: str = "r") -> np.ndarray:
    """Forearm twist ``theta`` (deg) from the wrist and elbow marker lines (Kojima et al. §8.2).

    The wrist line (radial styloid -> ulnar styloid) and the elbow line
    (lateral -> medial epicondyle) are projected on the plane normal to the
    forearm axis (epicondyle midpoint -> styloid midpoint); ``theta`` is the
    signed angle from the elbow line to the wrist line, minus ``zero_deg``.

    Parameters
    ----------
    radial_styloid, ulnar_styloid, lateral_epicondyle, medial_epicondyle : array_like, shape (F, 3) or (3,)
        Marker positions in one frame (the lab, Z up), mm.
    zero_deg : float
        The raw angle at the subject's 0 degree (supinated reference) pose, subtracted.
    side : {"r", "l"}
        Right: positive is a right-hand rotation about the proximally pointing
        axis (pronation); left: about the distally pointing axis, so that
        pronation is positive for both arms (the left arm is the mirror image).

    Returns
    -------
    ndarray, shape (F,)
        Twist in degrees, wrapped into [-90, 270) (supination past -90 or
        pronation past 270 degrees do not occur); NaN where a marker is missing.

    References
    ----------
    .. [1] Kojima et al., section 8.2.
    """
    side = _check_side(side)
    rs, us = _points("radial_styloid", radial_styloid), _points("ulnar_styloid", ulnar_styloid)
    le, me = _points("lateral_epicondyle", lateral_epicondyle), _points("medial_epicondyle", medial_epicondyle)
    n = _unit(0.5 * (rs + us) - 0.5 * (le + me))  # distal
    u = -n if side == "r" else n

    def project(v):
        return v - np.sum(v * u, axis=-1, keepdims=True) * u

    a, b = project(me - le), project(us - rs)
    ang = np.degrees(np.arctan2(np.sum(np.cross(a, b) * u, axis=-1), np.sum(a * b, axis=-1))) - zero_deg
    return np.mod(ang + 90.0, 360.0) - 90.0


def elbow_frame(radial_styloid, ulnar_styloid, lateral_epicondyle, medial_epicondyle) -> np.ndarray:
    """The frame that carries a forearm bone's ``theta = 0`` pose (``elbow -> lab``, F x 4 x 4).

    Origin at the epicondyle midpoint, y along the ulna (to the ulnar
    styloid, which pronation leaves in place: the radius turns about the
    ulna), x along the elbow line (lateral -> medial) made normal to y,
    z = x cross y. It follows the humerus (the epicondyles) and elbow flexion
    (the ulna), but not the twist, which is measured against it. (The styloid
    midpoint would do for y too, but it swings with the radius, so the frame
    itself would turn with the twist it is meant to carry the bones through.)
    """
    _points("radial_styloid", radial_styloid)  # checked, unused: see above
    us = _points("ulnar_styloid", ulnar_styloid)
    le, me = _points("lateral_epicondyle", lateral_epicondyle), _points("medial_epicondyle", medial_epicondyle)
    o = 0.5 * (le + me)
    y = _unit(us - o)
    x = me - le
    x = _unit(x - np.sum(x * y, axis=-1, keepdims=True) * y)
    z = np.cross(x, y)
    E = np.zeros(o.shape[:-1] + (4, 4))
    E[..., :3, 0], E[..., :3, 1], E[..., :3, 2], E[..., :3, 3] = x, y, z, o
    E[..., 3, 3] = 1.0
    return E


@dataclass(frozen=True)
class ForearmModel:
    """Quadratic pronation model of Kojima et al. §8.2.

    Every polynomial is ``c[0] * x**2 + c[1] * x + c[2]`` with ``x = theta``
    in :attr:`unit`; rotations come out in the same unit, control points on
    the 1-D segment axis (markers at +-1, radial side +1).

    Attributes
    ----------
    ulna_rotation, radius_rotation : tuple of 3 float
        ``f(theta)``: each bone's rotation from its ``theta = 0`` pose.
    ulna_wrist, ulna_elbow, radius_wrist, radius_elbow : tuple of 3 float
        Control points of each bone's rotation axis on the wrist and elbow segments.
    unit : {"quarter_turn", "deg", "rad"}
    theta_range_deg : tuple of 2 float
        Fitted range; outside it ``theta`` is clamped and the pose flagged.
    theta_zero : {"reference", "anatomical"}
        Where ``theta`` is 0. ``"reference"``: at the subject's reference pose
        (a model fitted from the subject's forearm stacks, whose 0 degree stack
        is the MRI pose). ``"anatomical"``: full supination, where the wrist
        line is parallel to the elbow line (raw angle 0) -- the paper's
        definition, used with its published coefficients: a subject without
        stacks has no measured 0 degree pose, and the static trial's forearm is
        wherever the subject held it (pyomeca's static: ~68 degrees).
    radius_axis : {"markers", "anatomical"}
        The line the radius turns about. ``"markers"``: through its control
        points on the wrist and elbow marker segments (the paper's). The
        marker segments lie on the skin, and a line through points on them
        misses the true axis (radial head to ulnar head) by ~10 mm, which a
        half turn carries into 20 mm of radius position error on the
        phantom. ``"anatomical"``: the subject's own radio-ulnar axis (the
        ulna's ``proximal_radioulnar`` and ``distal_radioulnar`` joint
        centres, as the MRI placed them), carried with the ulna; ``f(theta)``
        is the same. Falls back to the markers where the ulna lacks them.
    radius_axis_ulna_mm : tuple of 6 float, or ()
        With ``radius_axis="anatomical"``: the ends of the line the radius
        turns about (proximal then distal, x y z each) in the **ulna's bone
        frame**, mm, as the subject's forearm stacks showed it
        (:func:`radius_axis_from_poses`); used instead of the ulna's joint
        centres. Empty: the joint centres. A model borrowed by the other arm
        drops it (it is one ulna's).
    """

    ulna_rotation: tuple
    radius_rotation: tuple
    ulna_wrist: tuple
    ulna_elbow: tuple
    radius_wrist: tuple
    radius_elbow: tuple
    unit: str = "quarter_turn"
    theta_range_deg: tuple = (0.0, 180.0)
    theta_zero: str = "reference"
    radius_axis: str = "markers"
    radius_axis_ulna_mm: tuple = ()

    def __post_init__(self):
        if self.radius_axis_ulna_mm is None:
            object.__setattr__(self, "radius_axis_ulna_mm", ())
        if not isinstance(self.radius_axis_ulna_mm, (tuple, list)) or len(self.radius_axis_ulna_mm) not in (0, 6) \
                or not np.all(np.isfinite(np.asarray(self.radius_axis_ulna_mm, float))):
            raise ValueError(f"radius_axis_ulna_mm must be empty or 6 finite numbers (two ends, mm), "
                             f"got {self.radius_axis_ulna_mm!r}")
        if self.unit not in _UNITS:
            raise ValueError(f"unit must be one of {sorted(_UNITS)}, got {self.unit!r}")
        if self.theta_zero not in ("reference", "anatomical"):
            raise ValueError(f"theta_zero must be 'reference' or 'anatomical', got {self.theta_zero!r}")
        if self.radius_axis not in ("markers", "anatomical"):
            raise ValueError(f"radius_axis must be 'markers' or 'anatomical', got {self.radius_axis!r}")
        lo, hi = self.theta_range_deg
        if not lo < hi:
            raise ValueError(f"theta_range_deg must be increasing, got {self.theta_range_deg}")

    def to_dict(self) -> dict:
        """Plain lists, for ``subject.yaml``."""
        from dataclasses import asdict

        # an empty radius axis is left out: a subject file without a measured axis stays readable by
        # versions that do not know the key
        return {k: (list(map(float, v)) if isinstance(v, tuple) else v) for k, v in asdict(self).items()
                if not (k == "radius_axis_ulna_mm" and not v)}

    @classmethod
    def from_dict(cls, d: dict) -> "ForearmModel":
        """The inverse of :meth:`to_dict`; unknown keys raise ``ValueError``."""
        fields = set(cls.__dataclass_fields__)
        extra = set(d) - fields - {"side", "fitted_from"}
        if extra:
            raise ValueError(f"unknown forearm model keys: {sorted(extra)}")
        return cls(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items() if k in fields})

    def _x(self, theta_deg):
        return np.asarray(theta_deg, dtype=float) / _UNITS[self.unit]

    def rotation_deg(self, bone: str, theta_deg) -> np.ndarray:
        """``f(theta)`` of ``bone`` ("ulna" or "radius") in degrees."""
        c = {"ulna": self.ulna_rotation, "radius": self.radius_rotation}[bone]
        return np.polyval(c, self._x(theta_deg)) * _UNITS[self.unit]

    def control_points(self, bone: str, theta_deg) -> tuple[np.ndarray, np.ndarray]:
        """``(u_wrist, u_elbow)`` of ``bone`` at ``theta`` on the 1-D segment axes."""
        cw, ce = {"ulna": (self.ulna_wrist, self.ulna_elbow),
                  "radius": (self.radius_wrist, self.radius_elbow)}[bone]
        x = self._x(theta_deg)
        return np.polyval(cw, x), np.polyval(ce, x)


#: Kojima et al. eq. 3' (rotations), 4' and 4'' (control points), theta in quarter turns.
PAPER_MODEL = ForearmModel(
    ulna_rotation=(0.008, -0.134, 0.0), radius_rotation=(-0.127, 1.101, 0.0),
    ulna_wrist=(-0.2348, 0.4337, -0.7492), ulna_elbow=(0.1564, -0.4052, 0.2864),
    radius_wrist=(0.0851, -0.2781, -0.5283), radius_elbow=(-0.158, 0.894, -1.0465),
    unit="quarter_turn", theta_range_deg=(0.0, 180.0), theta_zero="anatomical")


def _segment_point(radial_side, other, u):
    return 0.5 * (radial_side + other) + u[..., None] * 0.5 * (radial_side - other)


def _axis_rotation(p0, d, angle_deg):
    """Rotations by ``angle_deg`` about the lines through ``p0`` along unit ``d`` (F, 4, 4)."""
    a = np.radians(angle_deg)
    K = np.zeros(d.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -d[..., 2], d[..., 1], -d[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = d[..., 2], -d[..., 1], d[..., 0]
    R = np.eye(3) + np.sin(a)[..., None, None] * K + (1 - np.cos(a))[..., None, None] * (K @ K)
    G = np.zeros(d.shape[:-1] + (4, 4))
    G[..., :3, :3] = R
    G[..., :3, 3] = p0 - np.einsum("...ij,...j->...i", R, p0)
    G[..., 3, 3] = 1.0
    return G


def forearm_bone_poses(model: ForearmModel, theta_deg, ulna_rest_to_lab, radius_rest_to_lab,
                       wrist_markers, elbow_markers, *, side: str = "r") -> dict[str, np.ndarray]:
    """Ulna and radius poses from the twist (Kojima et al. §8.2).

    Parameters
    ----------
    model : ForearmModel
    theta_deg : array_like, shape (F,)
        Twist from :func:`forearm_twist`.
    ulna_rest_to_lab, radius_rest_to_lab : array_like, shape (F, 4, 4)
        Each bone's ``theta = 0`` pose carried with the elbow frame, bone -> lab (mm):
        ``E(t) @ inv(E_ref) @ T_bone_ref`` (:func:`elbow_frame`).
    wrist_markers : array_like, shape (F, 2, 3)
        Radial and ulnar styloid markers (lab, mm).
    elbow_markers : array_like, shape (F, 2, 3)
        Lateral and medial epicondyle markers (lab, mm).
    side : {"r", "l"}
        The left arm is mirrored: its rotation axis points distally.

    Returns
    -------
    dict
        ``ulna``, ``radius`` (F, 4, 4) bone -> lab; ``clamped`` (F,) True where
        ``theta`` was outside ``model.theta_range_deg`` and was clamped;
        ``axis_ulna``, ``axis_radius`` (F, 2, 3) the control points (wrist, elbow) in the lab.

    References
    ----------
    .. [1] Kojima et al., section 8.2, eq. 3', 4', 4''.
    """
    side = _check_side(side)
    theta = np.asarray(theta_deg, dtype=float).reshape(-1)
    F = len(theta)
    W = np.asarray(wrist_markers, dtype=float)
    El = np.asarray(elbow_markers, dtype=float)
    rests = {"ulna": np.asarray(ulna_rest_to_lab, dtype=float), "radius": np.asarray(radius_rest_to_lab, dtype=float)}
    for name, a, shape in (("wrist_markers", W, (F, 2, 3)), ("elbow_markers", El, (F, 2, 3)),
                           ("ulna_rest_to_lab", rests["ulna"], (F, 4, 4)),
                           ("radius_rest_to_lab", rests["radius"], (F, 4, 4))):
        if a.shape != shape:
            raise ValueError(f"{name} must have shape {shape} (one per twist value), got {a.shape}")
    lo, hi = model.theta_range_deg
    clamped = (theta < lo) | (theta > hi)
    th = np.clip(theta, lo, hi)
    out = {"clamped": clamped & np.isfinite(theta)}
    for bone in ("ulna", "radius"):
        uw, ue = model.control_points(bone, th)
        pw = _segment_point(W[:, 0], W[:, 1], uw)
        pe = _segment_point(El[:, 0], El[:, 1], ue)
        d = _unit(pe - pw) if side == "r" else _unit(pw - pe)
        G = _axis_rotation(pw, d, model.rotation_deg(bone, th))
        out[bone] = G @ rests[bone]
        out[f"axis_{bone}"] = np.stack([pw, pe], axis=1)
    return out


def _screw_axis(G):
    """Axis direction (unit), angle (deg, about it) and the point nearest the origin of rigid motions G (K,4,4)."""
    R, t = G[:, :3, :3], G[:, :3, 3]
    w = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    s = np.linalg.norm(w, axis=1) / 2
    c = (np.trace(R, axis1=1, axis2=2) - 1) / 2
    ang = np.degrees(np.arctan2(s, c))
    # no rotation, no axis: a zero vector and the origin (callers skip such poses)
    a = np.where(s[:, None] > 1e-12, w / np.where(s > 1e-12, 2 * s, 1.0)[:, None], 0.0)
    pts = np.array([np.linalg.lstsq(np.eye(3) - R[k], t[k] - (t[k] @ a[k]) * a[k], rcond=None)[0]
                    if s[k] > 1e-12 else np.zeros(3) for k in range(len(G))])
    return a, ang, pts


#: A pose whose radius turned less than this (deg) from the reference pose does not place the radius's axis:
#: the axis's position error grows as ``1 / sin(angle / 2)`` of the poses' registration error.
MIN_AXIS_TURN_DEG = 30.0


def radius_axis_from_poses(ulna_to_world, radius_to_world, ends_guess, *, ref: int = 0,
                           min_turn_deg: float = MIN_AXIS_TURN_DEG) -> tuple[np.ndarray | None, dict]:
    """The line the radius turns about on the ulna, from both bones' poses at several twists.

    The radius's motion relative to the ulna from the reference pose to each
    other pose is a rotation about a helical axis (:func:`_screw_axis`); in the
    ulna's frame these axes are the forearm's radio-ulnar axis (radial head
    to ulnar head, Hollister et al. 1994) as those poses show it. The axes of
    the poses that turned at least ``min_turn_deg`` are combined with weights
    ``sin^2(angle / 2)`` (a half turn places its axis best): each end is the
    weighted mean of the points of the axes nearest the guessed end.

    Parameters
    ----------
    ulna_to_world, radius_to_world : array_like (K, 4, 4)
        Each bone's pose (bone frame -> a common world frame, mm) in each of K poses, e.g. forearm stacks.
    ends_guess : array_like (2, 3)
        Proximal and distal ends of the axis as guessed (the ulna's radio-ulnar joint centres), **ulna frame**.
    ref : int
        The reference pose (twist 0).
    min_turn_deg : float

    Returns
    -------
    ends : ndarray (2, 3) or None
        The fitted ends in the ulna's frame (None when no pose turned enough).
    report : dict
        Each pose's ``turn_deg`` and ``slide_mm`` (translation along its axis), the guessed ends'
        distance from the fitted line (``guess_off_mm``) and the spread of the poses' axes at each end
        (``spread_mm``).

    References
    ----------
    .. [1] Hollister AM, Gellman H, Waters RL. The relationship of the interosseous membrane to the axis
       of rotation of the forearm. Clin Orthop Relat Res 298:267-271, 1994.
    """
    U = np.asarray(ulna_to_world, float)
    R = np.asarray(radius_to_world, float)
    guess = np.asarray(ends_guess, float)
    if U.ndim != 3 or U.shape[1:] != (4, 4) or R.shape != U.shape:
        raise ValueError(f"ulna_to_world and radius_to_world must both be (K, 4, 4), got {U.shape} and {R.shape}")
    if guess.shape != (2, 3):
        raise ValueError(f"ends_guess must be (2, 3) (proximal, distal; ulna frame, mm), got {guess.shape}")
    if not 0 <= ref < len(U):
        raise ValueError(f"ref must index one of the {len(U)} poses, got {ref}")
    rel = np.linalg.inv(U) @ R                       # radius -> ulna frame, per pose
    others = [k for k in range(len(U)) if k != ref]
    report: dict = {"turn_deg": [], "slide_mm": []}
    if not others:
        return None, report
    G = rel[others] @ np.linalg.inv(rel[ref])
    a, ang, pts = _screw_axis(G)
    slide = np.einsum("ki,ki->k", G[:, :3, 3], a)
    report["turn_deg"], report["slide_mm"] = ang.tolist(), slide.tolist()
    keep = ang >= float(min_turn_deg)
    if not keep.any():
        return None, report
    a, pts, w = a[keep], pts[keep], np.sin(np.radians(ang[keep]) / 2) ** 2
    d_guess = guess[1] - guess[0]
    a = a * np.sign(a @ d_guess)[:, None]            # every axis pointing proximal -> distal
    ends, spread = [], []
    for q in guess:
        on = pts + np.einsum("ki,ki->k", q - pts, a)[:, None] * a      # each axis's point nearest q
        ends.append(np.average(on, axis=0, weights=w))
        spread.append(float(np.max(np.linalg.norm(on - ends[-1], axis=1))))
    ends = np.array(ends)
    d = (ends[1] - ends[0]) / np.linalg.norm(ends[1] - ends[0])
    off = [float(np.linalg.norm((q - ends[0]) - ((q - ends[0]) @ d) * d)) for q in guess]
    report.update(guess_off_mm=off, spread_mm=spread)
    return ends, report


def _closest_on_segment_line(p, a, m0, m1):
    """u of the point of the segment line (m1 = +1, m0 = -1) closest to the line (p, a)."""
    mid, half = 0.5 * (m0 + m1), 0.5 * (m1 - m0)
    # minimise |mid + u half - p - s a|^2 over (u, s)
    A = np.stack([half, -a], axis=-1)  # (K, 3, 2)
    sol = np.array([np.linalg.lstsq(A[k], p[k] - mid[k], rcond=None)[0] for k in range(len(p))])
    return sol[:, 0]


def _parallel_on_segment_lines(a, w0, w1, e0, e1):
    """``(u_w, u_e)``: the line through a point of each segment line that is parallel to ``a``.

    Solves ``mid_e + u_e h_e - mid_w - u_w h_w = s a`` (3 equations, 3 unknowns) per pose."""
    mw, hw = 0.5 * (w0 + w1), 0.5 * (w1 - w0)
    me, he = 0.5 * (e0 + e1), 0.5 * (e1 - e0)
    A = np.stack([-hw, he, -a], axis=-1)  # (K, 3, 3)
    sol = np.array([np.linalg.lstsq(A[k], mw[k] - me[k], rcond=None)[0] for k in range(len(a))])
    return sol[:, 0], sol[:, 1]


def fit_forearm_model(theta_deg, ulna_to_world, radius_to_world, wrist_markers, elbow_markers, *,
                      side: str = "r", min_rotation_deg: float = 2.0, control: str = "closest"
                      ) -> ForearmModel:
    """Fit a subject's forearm model from MRI poses at measured twists (Kojima et al. §8.2).

    Pose 0 is the reference (``theta`` closest to 0). For each pose ``k`` the
    motion of each bone from its carried ``theta = 0`` pose,
    ``G_k = T_k @ inv(C_k @ inv(C_0) @ T_0)``, is a rotation about a (finite
    helical) axis: its angle gives ``f(theta_k)`` and the points of the axis
    closest to the wrist and elbow marker lines give the control points. The
    carrier ``C`` is the elbow frame (:func:`elbow_frame`) for the ulna and the
    ulna for the radius -- the radius turns about the ulna, and
    :func:`bonecap.motion.lsq.solve_lsq` places it on the ulna it solved.
    Quadratics (in quarter turns, see the module documentation) are fitted by
    least squares -- through the points when there are three. Pose 0 has no
    rotation and so no axis: control points use the other poses (a straight
    line through two axes with three poses); a bone turning less than
    ``min_rotation_deg`` has no reliable axis and keeps its control points at
    the midpoints of the segments.

    Parameters
    ----------
    theta_deg : array_like, shape (K,)
        Measured twists of the poses (e.g. 0, 99.5, 172.1), :func:`forearm_twist`.
    ulna_to_world, radius_to_world : array_like, shape (K, 4, 4)
        Bone poses in each MRI (any common world frame, mm).
    wrist_markers, elbow_markers : array_like, shape (K, 2, 3)
        Radial/ulnar styloid and lateral/medial epicondyle marker (or capsule) positions per pose.
    side : {"r", "l"}
    min_rotation_deg : float
    control : {"closest", "parallel"}, default "closest"
        Where the control points go. ``"closest"``: the points of the fitted
        axis closest to the wrist and elbow marker lines, as the paper
        describes. The true axis rarely meets both marker lines, so the line
        through those points is tilted against it (2-3 degrees on the phantom,
        a 3-5 degree orientation error of the radius after a 100-170 degree
        turn). ``"parallel"``: the points where the line **parallel** to the
        fitted axis meets both marker lines (one exact solution), so the bone
        turns about the right direction and its orientation is reproduced
        exactly at the fitted poses -- but where the marker lines are far from
        the axis that parallel line can lie far from it too (85 mm at the
        phantom's 172 degree pose against 31 mm for ``"closest"``), a position
        error the rotation carries into the bone. The default is the paper's.

    Returns
    -------
    ForearmModel
        ``unit="quarter_turn"``, ``theta_range_deg`` the range of the poses.

    References
    ----------
    .. [1] Kojima et al., section 8.2.
    """
    side = _check_side(side)
    if control not in ("parallel", "closest"):
        raise ValueError(f"control must be 'parallel' or 'closest', got {control!r}")
    th = np.asarray(theta_deg, dtype=float).reshape(-1)
    K = len(th)
    if K < 3:
        raise ValueError(f"fit_forearm_model needs at least 3 poses (a quadratic), got {K}")
    arrays = {"ulna": np.asarray(ulna_to_world, float), "radius": np.asarray(radius_to_world, float)}
    W = np.asarray(wrist_markers, float)
    El = np.asarray(elbow_markers, float)
    for name, a, shape in (("ulna_to_world", arrays["ulna"], (K, 4, 4)),
                           ("radius_to_world", arrays["radius"], (K, 4, 4)),
                           ("wrist_markers", W, (K, 2, 3)), ("elbow_markers", El, (K, 2, 3))):
        if a.shape != shape:
            raise ValueError(f"{name} must have shape {shape}, got {a.shape}")
    if not all(np.isfinite(a).all() for a in (*arrays.values(), W, El, th)):
        raise ValueError("fit_forearm_model needs finite poses, markers and twists")
    order = np.argsort(np.abs(th))
    th, W, El = th[order], W[order], El[order]
    E = elbow_frame(W[:, 0], W[:, 1], El[:, 0], El[:, 1])
    x = th / 90.0
    coefs = {}
    U = arrays["ulna"][order]
    for bone in ("ulna", "radius"):
        T = arrays[bone][order]
        # The ulna's theta = 0 pose is carried with the elbow frame; the radius's with the
        # ulna it turns about (as solve_lsq applies it, the ulna being solved from its markers).
        carrier = E if bone == "ulna" else U
        carried = carrier @ np.linalg.inv(carrier[0]) @ T[0]
        G = T @ np.linalg.inv(carried)
        a, ang, p = _screw_axis(G)
        # sign the angle by the model's axis convention: proximal (right) / distal (left)
        prox = 0.5 * (El[:, 0] + El[:, 1]) - 0.5 * (W[:, 0] + W[:, 1])
        ref = _unit(prox) if side == "r" else -_unit(prox)
        f = np.where(np.sum(a * ref, axis=1) < 0, -ang, ang)
        a = np.where(np.sum(a * ref, axis=1)[:, None] < 0, -a, a)
        # A screw angle is read in (-180, 180]: a radius turned 190 deg at the last pose reads -170 deg
        # and the quadratic through it dives (a phantom's radius was then 30 deg off at 90 deg of twist).
        # Each pose after the first moving one takes the turn, of those 360 deg apart, nearest the
        # previous pose's turn extrapolated through theta = 0 (the bones turn about in step with theta).
        for k in range(2, K):
            if abs(th[k - 1]) > 1e-9:
                guess = f[k - 1] * th[k] / th[k - 1]
                f[k] += 360.0 * np.round((guess - f[k]) / 360.0)
        use = np.abs(ang) >= min_rotation_deg
        use[0] = False
        uw, ue = np.zeros(K), np.zeros(K)
        if use.any():
            if control == "closest":
                uw[use] = _closest_on_segment_line(p[use], a[use], W[use, 1], W[use, 0])
                ue[use] = _closest_on_segment_line(p[use], a[use], El[use, 1], El[use, 0])
            else:
                uw[use], ue[use] = _parallel_on_segment_lines(a[use], W[use, 1], W[use, 0],
                                                              El[use, 1], El[use, 0])
        coefs[f"{bone}_rotation"] = tuple(np.polyfit(x, f / 90.0, 2))
        for seg, u in (("wrist", uw), ("elbow", ue)):
            if use.sum() == 0:
                coefs[f"{bone}_{seg}"] = (0.0, 0.0, 0.0)
                continue
            deg = min(2, int(use.sum()) - 1)
            c = np.polyfit(x[use], u[use], deg) if deg > 0 else np.array([u[use][0]])
            coefs[f"{bone}_{seg}"] = tuple(np.concatenate([np.zeros(3 - len(c)), c]))
    return ForearmModel(unit="quarter_turn", theta_range_deg=(float(th.min()), float(th.max())), **coefs)


def forearm_poses_from_markers(skeleton, forearm, labels: Sequence[str], marker_bones: Sequence[str],
                               marker_local: np.ndarray, measured: np.ndarray,
                               ulna_to_lab: Mapping[str, np.ndarray] | None = None) -> dict[str, dict]:
    """Ulna and radius poses for every side whose four markers a trial has (used by ``solve_lsq``).

    The bones' ``theta = 0`` pose is the skeleton's reference pose: its markers
    are placed by ``marker_local`` on the bones at ``bone_to_world`` and the
    elbow frame there is ``E_ref``. ``theta`` is counted from the raw twist of
    those reference markers (``model.theta_zero == "reference"``) or from full
    anatomical supination (``"anatomical"``, raw angle 0).

    Parameters
    ----------
    skeleton : Skeleton
        Needs ``ulna_<side>`` and ``radius_<side>``.
    forearm : ForearmModel or mapping side -> ForearmModel
    labels, marker_bones, marker_local : the markers (names, bones, positions in the bone frame, mm)
    measured : ndarray (F, M, 3)
        Lab frame, mm.
    ulna_to_lab : mapping of ulna bone name -> ndarray (F, 4, 4), optional
        Solved ulna poses: when given, the radius's ``theta = 0`` pose is carried
        with the ulna (as :func:`fit_forearm_model` fits it) instead of the elbow frame.

    Returns
    -------
    dict
        Bone name -> ``{"transforms": (F, 4, 4), "clamped": (F,)}``.
    """
    models = forearm if isinstance(forearm, Mapping) else {"r": forearm, "l": forearm}
    out = {}
    labels = list(labels)
    for side, model in models.items():
        if not isinstance(model, ForearmModel):
            raise ValueError(f"forearm[{side!r}] must be a ForearmModel, got {type(model).__name__}")
        names = FOREARM_MARKERS[_check_side(side)]
        ulna, radius = f"ulna_{side}", f"radius_{side}"
        if not all(n in labels for n in names) or ulna not in skeleton.bones or radius not in skeleton.bones:
            continue
        idx = [labels.index(n) for n in names]
        ref = np.array([skeleton.bones[marker_bones[i]].bone_to_world[:3, :3] @ marker_local[i]
                        + skeleton.bones[marker_bones[i]].bone_to_world[:3, 3] for i in idx])
        E_ref = elbow_frame(*ref)[0]
        zero = 0.0 if model.theta_zero == "anatomical" else float(forearm_twist(*ref, side=side)[0])
        m = measured[:, idx].copy()
        U_ref = skeleton.bones[ulna].bone_to_world
        carry_r = None
        if ulna_to_lab and ulna in ulna_to_lab:
            # The radius is placed relative to the solved ulna, and so are the elbow markers:
            # the epicondyles are carried with the ulna from the reference pose. The measured
            # ones sit on the humerus and, off the flexion axis, move up to ~25 mm relative to
            # the ulna as the elbow flexes, which would leak flexion into the twist and tilt
            # the radius's axis.
            carry_r = ulna_to_lab[ulna] @ np.linalg.inv(U_ref)
            m[:, 2:] = np.einsum("fij,kj->fki", carry_r[:, :3, :3], ref[2:]) + carry_r[:, None, :3, 3]
        theta = forearm_twist(m[:, 0], m[:, 1], m[:, 2], m[:, 3], zero_deg=zero, side=side)
        E = elbow_frame(m[:, 0], m[:, 1], m[:, 2], m[:, 3])
        carry = E @ np.linalg.inv(E_ref)
        carry_r = carry if carry_r is None else carry_r
        poses = forearm_bone_poses(model, theta, carry @ U_ref,
                                   carry_r @ skeleton.bones[radius].bone_to_world, m[:, :2], m[:, 2:], side=side)
        ub = skeleton.bones[ulna]
        if model.radius_axis == "anatomical" and (len(model.radius_axis_ulna_mm) == 6 or {
                "proximal_radioulnar", "distal_radioulnar"} <= set(ub.joint_centres)):
            # the radius turns about the subject's radio-ulnar axis (as its stacks showed it, else the
            # ulna's joint centres), carried with the ulna
            if len(model.radius_axis_ulna_mm) == 6:
                local = np.reshape(model.radius_axis_ulna_mm, (2, 3))
                ends = local @ ub.bone_to_world[:3, :3].T + ub.bone_to_world[:3, 3]
            else:
                ends = np.array([ub.landmark_in_world("proximal_radioulnar"),
                                 ub.landmark_in_world("distal_radioulnar")])
            pe = np.einsum("fij,j->fi", carry_r[:, :3, :3], ends[0]) + carry_r[:, :3, 3]
            pw = np.einsum("fij,j->fi", carry_r[:, :3, :3], ends[1]) + carry_r[:, :3, 3]
            d = _unit(pe - pw) if side == "r" else _unit(pw - pe)
            th = np.clip(theta, *model.theta_range_deg)
            poses["radius"] = _axis_rotation(pw, d, model.rotation_deg("radius", th)) @ (
                carry_r @ skeleton.bones[radius].bone_to_world)
        out[ulna] = {"transforms": poses["ulna"], "clamped": poses["clamped"]}
        out[radius] = {"transforms": poses["radius"], "clamped": poses["clamped"]}
    return out
