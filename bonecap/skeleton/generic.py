"""The embedded generic skeleton: a parametric, whole-body template with ISB frames.

The template is *authored* here from published anthropometry (segment lengths as
fractions of stature after Winter 2009 / de Leva 1996, the hip-joint-centre
regression of Bell et al. 1989...) and from parametric shape primitives
(:mod:`bonecap.skeleton.shapes`): no scanned or third-party mesh goes into it.
Its readable description -- dimensions with their sources, shape parameters and
their ranges, the ISB frame of every bone, cortical thickness, landmarks -- is
``generic_skeleton/skeleton.yaml`` at the repository root.

World frame (``Skeleton.world == "model"``): the anatomical standing position
(arms at the sides, palms forward), **X anterior, Y superior, Z to the subject's
right** (the ISB global frame, OpenSim's ground), in mm. The origin is on the
floor (Y = 0 is the floor under the soles; the calcanei sit above it by the heel
pad), midway between the two ankle joint centres.

Bone frames follow the ISB recommendations (Wu et al. 2002 for the pelvis, hip,
knee, ankle and spine; Wu et al. 2005 for the shoulder, elbow, wrist and hand)
wherever ISB defines one; other bones get a documented convention (see each
bone's ``metadata["frame"]``). Left bones: ISB defines the right side and asks to
mirror left data (z -> -z). We store every frame right-handed: a left bone's frame
is the mirror image of the right one with its Z axis turned back to point to the
subject's right, so a left bone's local coordinates are the right ones with z
negated (OpenSim does the same).

Public API: :func:`build_generic_skeleton`, :func:`load_generic_description`,
:func:`default_shape_params`, :func:`render_skeleton_views`.
"""

from __future__ import annotations

import copy
import gc
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..errors import BonecapError, InputError
from ..model import Bone, Mesh, Skeleton
from .shapes import (
    Field, Ellipsoid, EllipticCylinder, HalfSpace, Intersect, Plate, RoundCone, ShapeBuilder, Shell, Sphere, Tube,
    field_to_mesh, frame_from_axes, rotation_about, surface_extreme, unit,
)

__all__ = [
    "build_generic_skeleton", "load_generic_description", "default_shape_params", "render_skeleton_views",
    "DESCRIPTION_PATH", "REQUIRED_LANDMARKS", "INTERIOR_LANDMARKS",
]

#: The readable description, located relative to the package (repository checkout
#: or editable install): ``<repo>/generic_skeleton/skeleton.yaml``.
DESCRIPTION_PATH = Path(__file__).resolve().parents[2] / "generic_skeleton" / "skeleton.yaml"

MIRROR = np.diag([1.0, 1.0, -1.0])
X, Y, Z = np.eye(3)

#: Landmarks that are volumetric centres, not surface points.
INTERIOR_LANDMARKS = {"acetabulum_centre", "head_centre", "radial_head_centre"}

#: Landmarks later stages rely on (bone base name -> landmark names).
REQUIRED_LANDMARKS: dict[str, list[str]] = {
    "skull": ["frontal_l", "frontal_r", "occipital_l", "occipital_r", "vertex", "nasion"],
    "sternum": ["jugular_notch", "xiphoid"],
    "clavicle": ["sternal_end", "acromial_end"],
    "scapula": ["acromion", "inferior_angle", "spine_root", "blade_centre", "coracoid"],
    "humerus": ["greater_tubercle", "head_anterior", "head_posterior", "shaft_lateral",
                "lateral_epicondyle", "medial_epicondyle", "elbow_anterior"],
    "ulna": ["olecranon", "ulnar_styloid", "ulnar_head_fovea", "coronoid"],
    "radius": ["radial_styloid", "radial_head_centre", "shaft_dorsal"],
    "ray1": ["metacarpal_head"],
    "ray2": ["metacarpal_head", "pip", "dip"],
    "ray3": ["metacarpal_head"],
    "ray4": ["metacarpal_head", "pip", "dip"],
    "ray5": ["metacarpal_head"],
    "hip": ["asis", "psis", "pubic_tubercle", "ischial_tuberosity", "acetabulum_centre"],
    "sacrum": ["s2_spinous"],
    "femur": ["greater_trochanter", "shaft_lateral", "lateral_epicondyle", "medial_epicondyle", "head_centre"],
    "patella": ["anterior_centre"],
    "tibia": ["tibial_tuberosity", "shaft_lateral", "medial_malleolus", "medial_condyle", "lateral_condyle"],
    "fibula": ["lateral_malleolus", "head"],
    "calcaneus": ["heel_posterior"],
    "foot": ["metatarsal2_head", "metatarsal1_head", "metatarsal5_head"],
    "talus": ["head"],
}

VERTEBRAE = [f"c{i}" for i in range(1, 8)] + [f"t{i}" for i in range(1, 13)] + [f"l{i}" for i in range(1, 6)]
for _v in VERTEBRAE:
    REQUIRED_LANDMARKS[_v] = ["spinous_process"]

SIDE_BONES = (["hip"] + [f"rib{i}" for i in range(1, 13)]
              + ["clavicle", "scapula", "humerus", "ulna", "radius", "carpals", "ray1", "ray2", "ray3", "ray4",
                 "ray5", "femur", "patella", "tibia", "fibula", "talus", "calcaneus", "foot"])
MIDLINE_BONES = ["sacrum"] + VERTEBRAE[::-1] + ["skull", "mandible", "sternum"]


# ---------------------------------------------------------------------------
# description and parameters


def load_generic_description(path: str | os.PathLike | None = None) -> dict:
    """Read the generic skeleton description (YAML).

    ``path`` defaults to :data:`DESCRIPTION_PATH`, the repository's
    ``generic_skeleton/skeleton.yaml`` located relative to this package (it works
    from a checkout or an editable install; a non-editable install must be given
    the path). Raises :class:`~bonecap.errors.InputError` when the file is missing
    or not a valid description.
    """
    import yaml

    from ..io import load_yaml

    p = Path(path) if path is not None else DESCRIPTION_PATH
    if not p.is_file():
        raise InputError(
            "generic skeleton description not found (expected the repository's generic_skeleton/skeleton.yaml; "
            "pass its path explicitly when bonecap is installed without the repository)", p)
    # parsed once per file version (the pure-Python parser takes ~1.5 s; libyaml's ~0.1 s),
    # handed out as a copy because callers may add keys
    st = p.stat()
    key = (str(p.resolve()), st.st_mtime_ns, st.st_size)
    cached = _DESCRIPTION_CACHE.get(key)
    if cached is not None:
        return copy.deepcopy(cached)
    try:
        with open(p, encoding="utf-8") as fh:
            desc = load_yaml(fh)
    except yaml.YAMLError as exc:
        raise InputError(f"not valid YAML: {exc}", p) from None
    for key in ("dimensions", "shape_parameters", "cortical_thickness", "vertebrae", "ribs", "bones"):
        if not isinstance(desc, dict) or key not in desc:
            raise InputError(f"generic skeleton description has no {key!r} section", p)
    desc["_path"] = str(p)
    _DESCRIPTION_CACHE.clear()
    _DESCRIPTION_CACHE[key] = copy.deepcopy(desc)
    return desc


_DESCRIPTION_CACHE: dict[tuple, dict] = {}


def default_shape_params(description: dict | None = None) -> dict[str, dict[str, Any]]:
    """The non-affine shape parameters: ``{name: {"default", "range", "unit", "what"}}``.

    Per-segment length scales (thigh, shank, foot, upper arm, forearm, hand, trunk,
    shoulder width), femoral anteversion and neck-shaft angle, femoral anterior bow,
    radial lateral bow, tibial torsion, humeral retroversion, pelvis width scale and
    a cortical thickness scale. ``range`` is the allowed ``[min, max]``.
    """
    desc = description or load_generic_description()
    out = {}
    for name, spec in desc["shape_parameters"].items():
        out[name] = {"default": float(spec["default"]), "range": [float(spec["range"][0]), float(spec["range"][1])],
                     "unit": spec.get("unit", ""), "what": spec.get("what", "")}
    return out


def _resolve_params(spec: dict, params: dict | None, side: str, mirroring: bool) -> dict[str, float]:
    params = dict(params or {})
    out = {k: v["default"] for k, v in spec.items()}
    for key, val in params.items():
        base = key
        key_side = None
        if key[-2:] in ("_l", "_r") and key[:-2] in spec:
            base, key_side = key[:-2], key[-1]
        if base not in spec:
            raise BonecapError(f"unknown generic skeleton parameter {key!r} (known: {', '.join(sorted(spec))})")
        if key_side is not None and mirroring:
            raise BonecapError(f"parameter {key!r} is per side: build with side_mirroring=False to use it")
        try:
            val = float(val)
        except (TypeError, ValueError):
            raise BonecapError(f"parameter {key!r} must be a number, got {val!r}") from None
        lo, hi = spec[base]["range"]
        if not (lo <= val <= hi):
            raise BonecapError(f"parameter {key!r} = {val} is outside its allowed range [{lo}, {hi}]")
        if key_side is None:
            if base + "_" + side not in params:
                out[base] = val
        elif key_side == side:
            out[base] = val
    return out


# ---------------------------------------------------------------------------
# small geometry helpers


class _Frame:
    """Origin + rotation (columns = local x, y, z in world) for authoring."""

    def __init__(self, origin, R):
        self.o = np.asarray(origin, float)
        self.R = np.asarray(R, float)

    def __call__(self, x, y=None, z=None) -> np.ndarray:
        v = np.asarray(x, float) if y is None else np.array([x, y, z], float)
        return self.o + v @ self.R.T

    def v(self, x, y=None, z=None) -> np.ndarray:
        v = np.asarray(x, float) if y is None else np.array([x, y, z], float)
        return v @ self.R.T

    def local(self, p) -> np.ndarray:
        return (np.asarray(p, float) - self.o) @ self.R


def _segment_frame(distal, proximal, lateral=Z) -> _Frame:
    """Origin at ``distal``, y toward ``proximal``, z lateral, x anterior."""
    return _Frame(distal, frame_from_axes(np.asarray(proximal) - np.asarray(distal), lateral, "yz"))


def _transform(R, o) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = o
    return T


def _spline(points, n: int) -> np.ndarray:
    """Centripetal Catmull-Rom through ``points``, resampled to ``n`` points by arc length."""
    P = np.asarray(points, float)
    if len(P) == 2:
        return P[0] + np.linspace(0, 1, n)[:, None] * (P[1] - P[0])
    ext = np.vstack([2 * P[0] - P[1], P, 2 * P[-1] - P[-2]])
    dense = []
    for i in range(1, len(ext) - 2):
        p0, p1, p2, p3 = ext[i - 1:i + 3]
        t = np.linspace(0, 1, 24, endpoint=False)[:, None]
        d = (2 * p1 + (-p0 + p2) * t + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t ** 2 + (-p0 + 3 * p1 - 3 * p2 + p3) * t ** 3)
        dense.append(0.5 * d)
    dense.append(P[-1][None])
    D = np.vstack(dense)
    s = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(D, axis=0), axis=1))])
    u = np.linspace(0, s[-1], n)
    return np.stack([np.interp(u, s, D[:, k]) for k in range(3)], axis=1)


def _axial_thickness(p0, p1, knots, values):
    """Cortical thickness as a function of the fraction along the axis p0 -> p1.

    The returned function takes broadcastable coordinate arrays ``(X, Y, Z)``."""
    p0 = np.asarray(p0, float)
    d = np.asarray(p1, float) - p0
    L2 = float(d @ d)
    knots = np.asarray(knots, float)
    values = np.asarray(values, float)

    def f(X, Y, Z):
        u = ((X - p0[0]) * d[0] + (Y - p0[1]) * d[1] + (Z - p0[2]) * d[2]) / L2
        u = np.broadcast_to(u, np.broadcast_shapes(np.shape(X), np.shape(Y), np.shape(Z)))
        return np.interp(u.ravel(), knots, values).reshape(u.shape)
    return f


def _table_fn(uv: np.ndarray, vals: np.ndarray, res: float):
    """A fast look-up ``f(U, V)`` of scattered values: binned on a grid of ``res`` mm,
    empty cells filled from the nearest filled one, read back bilinearly."""
    from scipy import ndimage

    lo = uv.min(axis=0)
    n = np.ceil((uv.max(axis=0) - lo) / res).astype(int) + 2
    idx = np.round((uv - lo) / res).astype(int)
    S = np.zeros(n)
    C = np.zeros(n)
    np.add.at(S, (idx[:, 0], idx[:, 1]), vals)
    np.add.at(C, (idx[:, 0], idx[:, 1]), 1.0)
    T = S / np.maximum(C, 1.0)
    empty = C == 0
    if np.any(empty):
        _, ind = ndimage.distance_transform_edt(empty, return_indices=True)
        T = T[ind[0], ind[1]]

    def f(U, V):
        fu = np.clip((np.asarray(U) - lo[0]) / res, 0, n[0] - 1.001)
        fv = np.clip((np.asarray(V) - lo[1]) / res, 0, n[1] - 1.001)
        i, j = fu.astype(int), fv.astype(int)
        a, b = fu - i, fv - j
        return (T[i, j] * (1 - a) + T[i + 1, j] * a) * (1 - b) + (T[i, j + 1] * (1 - a) + T[i + 1, j + 1] * a) * b
    return f


def _plate_from_grid(mids: np.ndarray, half: np.ndarray, res: float) -> Plate:
    """A :class:`Plate` through a (nu, nv, 3) grid of mid-surface points with half
    thicknesses (nu, nv): best-fit plane, outline = the grid's border, height field
    and thickness tabulated from the (densified) grid."""
    from scipy import ndimage

    nu, nv = mids.shape[:2]
    P0 = mids.reshape(-1, 3)
    c = P0.mean(axis=0)
    _, _, Vt = np.linalg.svd(P0 - c, full_matrices=False)
    e1, e2 = Vt[0], Vt[1]
    n = np.cross(e1, e2)
    # densify so that every table cell gets samples
    span_u = np.linalg.norm(np.diff(mids, axis=0), axis=2).sum(axis=0).max()
    span_v = np.linalg.norm(np.diff(mids, axis=1), axis=2).sum(axis=1).max()
    fu = max(1.0, 2.0 * span_u / res / nu)
    fv = max(1.0, 2.0 * span_v / res / nv)
    dense = np.stack([ndimage.zoom(mids[..., k], (fu, fv), order=1) for k in range(3)], -1)
    hd = ndimage.zoom(half, (fu, fv), order=1)
    P = dense.reshape(-1, 3)
    uv = np.stack([(P - c) @ e1, (P - c) @ e2], 1)
    w = (P - c) @ n
    # outline: the border of the parameter grid, at most ~64 vertices
    border = np.concatenate([mids[:, 0], mids[-1, 1:], mids[-2::-1, -1], mids[0, -2:0:-1]])
    step = max(1, len(border) // 64)
    border = border[::step]
    outline = np.stack([(border - c) @ e1, (border - c) @ e2], 1)
    return Plate(c, e1, e2, outline, half_thickness=_table_fn(uv, hd.ravel(), res),
                 height=_table_fn(uv, w, res), res=res)


# ---------------------------------------------------------------------------
# drafts: one bone authored in the (right-side) world frame


@dataclass
class _Rule:
    """A landmark: the surface vertex within ``radius`` of ``seed`` that lies furthest
    along ``direction`` (restricted to the mid-sagittal plane when ``midline``; with
    ``column``, within ``radius`` of the line through ``seed`` along ``direction``: the
    surface point over the seed, for a landmark on a nearly flat surface, whose
    furthest point within a ball jumps from edge to edge with a degree of tilt)."""
    name: str
    seed: np.ndarray
    direction: np.ndarray
    radius: float = 12.0
    midline: bool = False
    column: bool = False


@dataclass(eq=False)
class _Draft:
    name: str                      # base name ("femur", "c7", "rib3")
    parent: str | None             # base name of the parent
    builder: ShapeBuilder
    target_faces: int
    thickness: Callable | None = None      # world points -> cortical thickness (mm)
    max_thickness: float = 0.0
    inner_min_volume: float = 8.0
    inner_target_faces: int | None = None
    rules: list[_Rule] = field(default_factory=list)
    fixed: dict[str, np.ndarray] = field(default_factory=dict)     # interior landmarks
    joints: dict[str, np.ndarray] = field(default_factory=dict)
    axes: dict[str, np.ndarray] = field(default_factory=dict)
    frame: Callable | None = None      # (lookup) -> (R, o); default: translation to the mesh centroid
    frame_text: str = ""
    meta: dict[str, Any] = field(default_factory=dict)
    side: bool = True                  # built per side (False: midline)
    # results (world, right side)
    V: np.ndarray | None = None
    F: np.ndarray | None = None
    Vi: np.ndarray | None = None
    Fi: np.ndarray | None = None
    landmarks: dict[str, np.ndarray] = field(default_factory=dict)


class _Ctx:
    """Everything a bone builder needs: stature, scales, parameters, the layout."""

    def __init__(self, H: float, p: dict, desc: dict):
        self.H = float(H)
        self.w = self.H / 1700.0
        self.p = p
        self.desc = desc
        self.dim = {k: float(v["fraction"]) for k, v in desc["dimensions"].items()}
        self.cort = desc["cortical_thickness"]
        self.ct = p["cortical_thickness_scale"] * self.w

    def frac(self, key):
        return self.dim[key] * self.H

    def thick(self, bone: str, part: str) -> float:
        return float(self.cort[bone][part]) * self.ct


# ---------------------------------------------------------------------------
# layout: joint centres and key points of the standing body (right side)


def _layout(c: _Ctx) -> dict[str, Any]:
    w, p = c.w, c.p
    L: dict[str, Any] = {}
    iad = c.frac("inter_asis_distance")
    pw = p["pelvis_width_scale"]
    L["iad"] = iad
    hjc_z = 0.36 * iad * pw                       # Bell et al. 1989: 14 % of IAD medial of ASIS
    ankle_h = c.frac("ankle_height")
    shank = c.frac("shank_length") * p["shank_scale"]
    thigh = c.frac("thigh_length") * p["thigh_scale"]
    A = np.array([0.0, ankle_h, hjc_z])
    K = A + np.array([0.0, shank, 0.0])
    Hj = K + np.array([0.0, thigh, 0.0])
    L.update(ankle=A, knee=K, hip=Hj, shank=shank, thigh=thigh)
    # pelvis, from the hip joint centre (Bell 1989: HJC 22 % IAD posterior, 30 % distal of mid-ASIS)
    asis_mid = Hj + np.array([0.22 * iad, 0.30 * iad, -hjc_z])
    L["asis_mid"] = asis_mid

    def pp(x, y, z):      # pelvis authoring coordinates (mm at 1.70 m, z scaled by pelvis width)
        return asis_mid + np.array([x * w, y * w, z * w * pw])
    L["pp"] = pp
    # sacral plate: pelvic tilt 13 deg, sacral slope 40 deg (Legaye et al. 1998)
    ss = float(c.desc["pelvis"]["sacral_slope_deg"])
    L["s1"] = pp(-84.0, 40.0, 0.0)
    L["s1_normal"] = np.array([np.sin(np.radians(ss)), np.cos(np.radians(ss)), 0.0])
    # spine chain
    _spine_layout(c, L)
    # thorax and shoulder girdle
    _thorax_layout(c, L)
    # upper limb
    gh = L["gh"]
    ua = c.frac("upper_arm_length") * p["upper_arm_scale"]
    fa = c.frac("forearm_length") * p["forearm_scale"]
    E = gh + ua * unit([-0.03, -1.0, -0.02])
    carry = np.radians(float(c.desc["upper_limb"]["carrying_angle_deg"]))
    W = E + fa * unit([0.03, -np.cos(carry), np.sin(carry)])
    L.update(elbow=E, wrist=W, upper_arm=ua, forearm=fa)
    return L


def _spine_layout(c: _Ctx, L):
    w, p = c.w, c.p
    table = c.desc["vertebrae"]
    # raw chain from S1 upward with unit scales, then fit the thoraco-lumbar scale
    # to the de Leva trunk length (hip centres to C7 spinous) and the cervical scale to
    # the skull height.
    levels = VERTEBRAE[::-1]                   # l5 ... c1

    def chain(s_tl, s_c):
        top = L["s1"].copy()
        prev_n = L["s1_normal"].copy()
        out = {}
        for name in levels:
            d = table[name]
            s = s_tl if (name[0] in "lt" or name == "c7") else s_c
            t = np.radians(float(d["tilt_deg"]))
            n = np.array([np.sin(t), np.cos(t), 0.0])
            nbar = unit(prev_n + n)
            disc = float(d["disc_below"]) * w * s
            bh = float(d["body_height"]) * w * s
            centre = top + disc * nbar + 0.5 * bh * n
            out[name] = dict(centre=centre, n=n, bh=bh, disc_centre=top + 0.5 * disc * nbar)
            top = centre + 0.5 * bh * n
            prev_n = n
        return out

    def c7_spinous_y(ch):
        d = table["c7"]
        v = ch["c7"]
        R = frame_from_axes(v["n"], Z, "yz")
        tip = _spinous_tip_local(d, w)
        return (v["centre"] + R @ tip)[1]

    target_c7 = L["hip"][1] + c.frac("trunk_length")
    # C7 spinous height is linear in the thoraco-lumbar scale
    y1 = c7_spinous_y(chain(1.0, 1.0))
    y2 = c7_spinous_y(chain(1.2, 1.0))
    s_tl = 1.0 + 0.2 * (target_c7 - y1) / (y2 - y1)
    s_tl *= p["trunk_scale"]
    # skull: the vertex at stature minus scalp (fitted at unit trunk scale, so that the
    # head rides on the trunk when the trunk scale changes)
    sk = c.desc["skull"]
    ao_to_vertex = float(sk["ao_to_vertex"]) * w
    target_ao = c.H - float(sk["scalp"]) * w - ao_to_vertex
    s_tl_fit = s_tl / p["trunk_scale"]
    a1 = chain(s_tl_fit, 1.0)
    a2 = chain(s_tl_fit, 1.2)

    def ao_y(ch):
        v = ch["c1"]
        return (v["centre"] + 0.5 * v["bh"] * v["n"])[1]
    s_c = 1.0 + 0.2 * (target_ao - ao_y(a1)) / (ao_y(a2) - ao_y(a1))
    ch = chain(s_tl, s_c)
    L["spine"] = ch
    L["spine_scales"] = (s_tl, s_c)
    v = ch["c1"]
    L["ao"] = v["centre"] + 0.5 * v["bh"] * v["n"]


def _spinous_tip_local(d, w):
    bd = float(d["body_depth"]) * w
    cd = float(d["canal_depth"]) * w
    ln = float(d["spinous_length"]) * w
    ang = np.radians(float(d["spinous_angle_deg"]))
    base = np.array([-0.5 * bd - cd - 2.0 * w, 0.0, 0.0])
    return base + ln * np.array([-np.cos(ang), -np.sin(ang), 0.0])


def _vertebra_frame(L, name) -> _Frame:
    v = L["spine"][name]
    return _Frame(v["centre"], frame_from_axes(v["n"], Z, "yz"))


def _thorax_layout(c: _Ctx, L):
    w, p = c.w, c.p
    sp = L["spine"]
    th = c.desc["thorax"]
    t2, t3 = sp["t2"]["centre"], sp["t3"]["centre"]
    ij = 0.5 * (t2 + t3)
    ij = ij + np.array([0.5 * float(c.desc["vertebrae"]["t2"]["body_depth"]) * w
                        + float(th["ij_depth_from_t2"]) * w, 0.0, 0.0])
    L["ij"] = ij
    inc = np.radians(float(th["sternum_inclination_deg"]))
    L["sternum_axis"] = np.array([np.sin(inc), -np.cos(inc), 0.0])
    L["sternum_length"] = float(th["sternum_length"]) * w * p["trunk_scale"]
    sc = ij + np.array([-8.0, 6.0, 24.0]) * w
    cl = c.frac("clavicle_length") * p["shoulder_width_scale"]
    retr = np.radians(float(th["clavicle_retraction_deg"]))
    elev = np.radians(float(th["clavicle_elevation_deg"]))
    ac = sc + cl * np.array([-np.sin(retr) * np.cos(elev), np.sin(elev), np.cos(retr) * np.cos(elev)])
    L.update(sc=sc, ac=ac, clavicle_length=cl)
    L["gh"] = ac + np.array([6.0, -34.0, 14.0]) * w


# ---------------------------------------------------------------------------
# lower limb


def _femur(c: _Ctx, L) -> _Draft:
    w, p = c.w, c.p
    Hc, K = L["hip"], L["knee"]
    F = _segment_frame(K, Hc)
    Lf = np.linalg.norm(Hc - K)
    rh = float(c.desc["femur"]["head_diameter"]) * 0.5 * w
    b = ShapeBuilder(voxel=2.0 * w)
    # shaft axis: through the knee notch and the neck-shaft junction at the default
    # angles (so the shaft does not move when the neck angles change)
    spec = c.desc["shape_parameters"]
    nsa0 = float(spec["femoral_neck_shaft_deg"]["default"])
    av0 = float(spec["femoral_anteversion_deg"]["default"])
    t_neck = float(c.desc["femur"]["head_to_shaft_axis"]) * w
    D = F(3.0 * w, 0.0, 0.0)

    def neck_dir(s, nsa, av):
        lat = unit(F.R[:, 2] - (F.R[:, 2] @ s) * s)
        ant = np.cross(s, lat)
        perp = np.sin(np.radians(av)) * ant - np.cos(np.radians(av)) * lat
        return unit(-np.cos(np.radians(nsa)) * s + np.sin(np.radians(nsa)) * perp)
    s = F.R[:, 1]
    for _ in range(6):
        Pn = Hc - t_neck * neck_dir(s, nsa0, av0)
        s = unit(Pn - D)
    lat = unit(F.R[:, 2] - (F.R[:, 2] @ s) * s)
    ant = np.cross(s, lat)
    n = neck_dir(s, p["femoral_neck_shaft_deg"], p["femoral_anteversion_deg"])
    Ls = np.linalg.norm(Pn - D)
    # shaft with the anterior bow
    fd = c.desc["femur"]
    u = np.linspace(0.0, 0.96, 20)
    bow = p["femur_anterior_bow_mm"] * w * (Lf / (c.frac("thigh_length")))
    v = np.clip((u - 0.15) / (0.88 - 0.15), 0, 1)
    nodes = D + np.outer(u * Ls, s) + np.outer(bow * 4 * v * (1 - v), ant)
    prof = np.array(fd["shaft_profile"], float)     # u, half-width ML, half-depth AP
    rml = np.interp(u, prof[:, 0], prof[:, 1]) * w
    rap = np.interp(u, prof[:, 0], prof[:, 2]) * w
    b.add(Tube(nodes, np.stack([rml, rap], 1), e1=lat))
    # linea aspera (posterior ridge)
    ua = np.linspace(0.28, 0.78, 8)
    va = np.clip((ua - 0.15) / (0.88 - 0.15), 0, 1)
    ridge = (D + np.outer(ua * Ls, s) + np.outer(bow * 4 * va * (1 - va), ant)
             - np.outer(np.interp(ua, prof[:, 0], prof[:, 2]) * w - 0.5 * w, ant))
    b.add(Tube(ridge, np.full(8, 3.0 * w)), k=3 * w)
    # distal femur: condyles, epicondyles, trochlea, metaphysis
    for zs, cx, r in ((1, -5.0, (26.0, 23.0, 13.0)), (-1, -7.0, (27.0, 23.0, 14.0))):
        b.add(Ellipsoid(F(cx * w, 2.0 * w, zs * 21.0 * w), np.array(r) * w, F.R), k=4 * w)
        b.add(Ellipsoid(F(-10.0 * w, 4.0 * w, zs * 21.0 * w), np.array([19.0, 19.0, 12.5]) * w, F.R), k=3 * w)
    b.add(Ellipsoid(F(-2.0 * w, 3.0 * w, 31.0 * w), np.array([9.0, 9.0, 7.0]) * w, F.R), k=2.5 * w)
    b.add(Ellipsoid(F(-2.0 * w, 5.0 * w, -32.0 * w), np.array([10.0, 10.0, 7.0]) * w, F.R), k=2.5 * w)
    b.add(Ellipsoid(F(-5.0 * w, 28.0 * w, -26.0 * w), np.array([7.0, 9.0, 5.0]) * w, F.R), k=4 * w)
    b.add(Ellipsoid(F(9.0 * w, 20.0 * w, 0.0), np.array([14.0, 24.0, 30.0]) * w, F.R), k=5 * w)
    b.add(Ellipsoid(F(-1.0 * w, 34.0 * w, 0.0), np.array([15.0, 28.0, 24.0]) * w, F.R), k=10 * w)
    b.cut(RoundCone(F(31.0 * w, 42.0 * w, 2.0 * w), F(29.0 * w, 2.0 * w, 1.0 * w), 8.0 * w, 8.0 * w), k=3 * w)
    b.cut(Ellipsoid(F(-26.0 * w, -10.0 * w, 0.0), np.array([22.0, 18.0, 9.5]) * w, F.R), k=2 * w)
    # proximal femur: neck, head, trochanters
    Rs = np.stack([ant, s, lat], axis=1)
    gt = Pn + s * 10.0 * w + lat * 18.0 * w - ant * 5.0 * w
    b.add(Ellipsoid(gt, np.array([17.0, 25.0, 11.0]) * w, Rs), k=6 * w)
    lt = Pn - s * 40.0 * w - lat * 15.0 * w - ant * 11.0 * w
    b.add(Ellipsoid(lt, np.array([8.0, 11.0, 8.0]) * w, Rs), k=4 * w)
    b.add(Tube([gt - ant * 14.0 * w - s * 4 * w, Pn - s * 22.0 * w - ant * 13.0 * w, lt - ant * 2 * w],
               np.full(3, 5.0 * w)), k=4 * w)
    e1 = unit(s - (s @ n) * n)
    # the neck runs along n through the head centre; its base stays near the default
    # neck-shaft junction, so other angles turn the neck about the head centre
    Pa = Hc - t_neck * n
    neck_nodes = [Pa - 4.0 * w * n, Pa + 0.35 * t_neck * n, Hc - 0.55 * rh * n]
    b.add(Tube(neck_nodes, np.array([[21.0, 17.0], [16.5, 13.5], [17.0, 15.0]]) * w, e1=e1), k=6 * w)
    b.add(Sphere(Hc, rh), k=3 * w)
    # cortical thickness along the shaft (fraction u from the knee notch to the neck junction)
    ct = c.cort["femur"]
    thick_axis = _axial_thickness(D, Pn, [0.0, 0.08, 0.22, 0.35, 0.65, 0.8, 0.92, 1.0],
                                  np.array([ct["epiphysis"], ct["epiphysis"], ct["metaphysis"], ct["diaphysis"],
                                            ct["diaphysis"], ct["metaphysis"], ct["epiphysis"],
                                            ct["epiphysis"]], float) * c.ct)

    def thickness(X_, Y_, Z_):
        t = thick_axis(X_, Y_, Z_)
        # femoral head and neck: thin cortex
        dn = np.sqrt((X_ - Hc[0]) ** 2 + (Y_ - Hc[1]) ** 2 + (Z_ - Hc[2]) ** 2)
        return np.where(dn < rh + 0.9 * t_neck, np.minimum(t, ct["epiphysis"] * c.ct), t)
    mid = D + 0.5 * Ls * s + bow * ant
    rules = [
        _Rule("greater_trochanter", gt + lat * 6 * w, lat, 14 * w),
        _Rule("shaft_lateral", D + 0.45 * Ls * s + bow * 0.9 * ant, lat, 10 * w),
        _Rule("lateral_epicondyle", F(-2 * w, 4 * w, 34 * w), F.R[:, 2], 12 * w),
        _Rule("medial_epicondyle", F(-2 * w, 6 * w, -35 * w), -F.R[:, 2], 12 * w),
    ]
    meta = dict(neck_axis=n, shaft_axis=s, shaft_mid=mid, neck_shaft_angle_deg=p["femoral_neck_shaft_deg"],
                anteversion_deg=p["femoral_anteversion_deg"], head_radius_mm=rh)
    L["patella_centre"] = F(34.5 * w, 19.0 * w, 2.0 * w)
    L["patellofemoral"] = F(22.0 * w, 19.0 * w, 1.0 * w)
    knee_axis = F.R[:, 2]

    def frame(lk):
        le, me = lk("femur", "lateral_epicondyle"), lk("femur", "medial_epicondyle")
        yax = unit(Hc - 0.5 * (le + me))
        R = frame_from_axes(yax, le - me, "yz")
        return R, Hc
    return _Draft("femur", "hip", b, 6000, thickness=thickness, max_thickness=ct["diaphysis"] * c.ct,
                  rules=rules, fixed={"head_centre": Hc},
                  joints={"hip": Hc, "knee": K, "patellofemoral": L["patellofemoral"]},
                  axes={"knee": knee_axis}, frame=frame, meta=meta)


def _patella(c: _Ctx, L) -> _Draft:
    w = c.w
    F = _segment_frame(L["knee"], L["hip"])
    P = L["patella_centre"]
    b = ShapeBuilder(voxel=1.2 * w)
    b.add(Ellipsoid(P, np.array([10.5, 22.0, 22.5]) * w, F.R))
    b.add(Ellipsoid(P + F.v(-1.0, -14.0, 0.0) * w, np.array([8.0, 12.0, 13.0]) * w, F.R), k=4 * w)
    b.add(Ellipsoid(P + F.v(-5.0, 0.0, 3.0) * w, np.array([6.0, 18.0, 14.0]) * w, F.R), k=3 * w)

    def frame(lk):
        R = lk.frame("femur")[0]
        return R, P
    return _Draft("patella", "femur", b, 2500, thickness=c.thick("patella", "shell"),
                  max_thickness=c.thick("patella", "shell"),
                  rules=[_Rule("anterior_centre", P + F.v(8, 0, 0) * w, F.R[:, 0], 10 * w)],
                  joints={"patellofemoral": L["patellofemoral"]}, frame=frame,
                  frame_text=c.desc["bones"]["patella"]["frame"])


def _tibia(c: _Ctx, L) -> _Draft:
    w, p = c.w, c.p
    A, K = L["ankle"], L["knee"]
    T = _segment_frame(A, K)
    Ls = np.linalg.norm(K - A)
    b = ShapeBuilder(voxel=1.9 * w)
    yp = Ls - 27.0 * w                      # plateau level (the femoral condyles end 21 mm below the knee centre)
    tor = rotation_about(T.R[:, 1], -p["tibial_torsion_deg"])  # external torsion of the distal tibia
    Td = _Frame(A, tor @ T.R)
    # plateau and condyles
    b.add(EllipticCylinder(T(-3 * w, yp - 9 * w, 0), 24 * w, 9 * w, 37 * w, T.R, rounding=7 * w))
    b.add(Ellipsoid(T(-4 * w, yp - 24 * w, 0), np.array([23.0, 26.0, 35.0]) * w, T.R), k=8 * w)
    b.add(Ellipsoid(T(-6 * w, yp - 1 * w, 0), np.array([7.0, 5.0, 5.0]) * w, T.R), k=2 * w)
    b.cut(Ellipsoid(T(-4 * w, yp + 26 * w, -20 * w), np.array([22.0, 25.0, 15.0]) * w, T.R), k=2 * w)
    b.cut(Ellipsoid(T(-4 * w, yp + 26 * w, 20 * w), np.array([22.0, 25.5, 15.0]) * w, T.R), k=2 * w)
    b.add(Ellipsoid(T(21 * w, yp - 33 * w, 4 * w), np.array([8.0, 14.0, 11.0]) * w, T.R), k=5 * w)
    # shaft: round core plus an anterior crest (triangular section)
    u = np.linspace(0.08, 0.86, 16)
    prof = np.array(c.desc["tibia"]["shaft_profile"], float)
    centre_x = np.interp(u, [0.0, 0.5, 1.0], [0.5, 0.5, -2.0]) * w
    nodes = np.array([T(cx, uu * Ls, 0.0) for uu, cx in zip(u, centre_x)])
    rr = np.stack([np.interp(u, prof[:, 0], prof[:, 1]), np.interp(u, prof[:, 0], prof[:, 2])], 1) * w
    b.add(Tube(nodes, rr, e1=T.R[:, 2]))
    uc = np.linspace(0.2, 0.85, 8)
    crest = np.array([T(np.interp(uu, prof[:, 0], prof[:, 2]) * w - 2.5 * w, uu * Ls, -1.5 * w) for uu in uc])
    b.add(Tube(crest, np.full(8, 3.2 * w)), k=3 * w)
    # distal tibia, plafond at +17 mm, medial malleolus
    b.add(Ellipsoid(Td(0.5 * w, 36 * w, -3 * w), np.array([19.0, 30.0, 21.0]) * w, Td.R), k=10 * w)
    b.add(EllipticCylinder(Td(0.5 * w, 24 * w, -2 * w), 20 * w, 7 * w, 22 * w, Td.R, rounding=4 * w), k=4 * w)
    mm_c = Td(3.0 * w, 8.0 * w, -25.0 * w)
    b.add(Tube([Td(2 * w, 27 * w, -22 * w), mm_c, Td(3 * w, -2 * w, -25 * w)],
               np.array([[11.0, 7.0], [9.5, 6.0], [6.0, 4.0]]) * w, e1=Td.R[:, 0]), k=3 * w)
    b.cut(Ellipsoid(A + Td.v(0, 2, 0) * w, np.array([19.0, 15.0, 17.0]) * w, Td.R), k=1.0 * w)
    ct = c.cort["tibia"]
    thickness = _axial_thickness(A, K, [0.0, 0.1, 0.25, 0.4, 0.65, 0.78, 0.9, 1.0],
                                 np.array([ct["epiphysis"], ct["epiphysis"], ct["metaphysis"], ct["diaphysis"],
                                           ct["diaphysis"], ct["metaphysis"], ct["epiphysis"], ct["epiphysis"]],
                                          float) * c.ct)
    lat = T.R[:, 2]
    rules = [
        _Rule("tibial_tuberosity", T(28 * w, yp - 33 * w, 4 * w), T.R[:, 0], 12 * w),
        _Rule("shaft_lateral", T(6 * w, 0.5 * Ls, 8 * w), unit(0.55 * T.R[:, 0] + lat), 10 * w),
        _Rule("medial_malleolus", Td(3 * w, 2 * w, -30 * w), -Td.R[:, 2], 10 * w),
        _Rule("medial_condyle", T(-4 * w, yp - 12 * w, -36 * w), -lat, 12 * w),
        _Rule("lateral_condyle", T(-4 * w, yp - 12 * w, 36 * w), lat, 12 * w),
    ]
    L["tibia_frame"] = T
    L["tibia_distal_frame"] = Td
    L["tibia_plateau_y"] = yp

    def frame(lk):
        mm, lm = lk("tibia", "medial_malleolus"), lk("fibula", "lateral_malleolus")
        ic = 0.5 * (lk("tibia", "medial_condyle") + lk("tibia", "lateral_condyle"))
        im = 0.5 * (mm + lm)
        zax = unit(lm - mm)
        xax = unit(np.cross(ic - im, zax))     # normal of the plane (IC, MM, LM), anterior
        if xax @ X < 0:
            xax = -xax
        R = frame_from_axes(zax, xax, "zx")
        return R, im
    ankle_axis = unit(Td.R[:, 2] - 0.14 * Td.R[:, 1])   # talocrural axis: lateral, ~8 deg down (Inman 1976)
    return _Draft("tibia", "femur", b, 6000, thickness=thickness, max_thickness=ct["diaphysis"] * c.ct,
                  rules=rules, joints={"knee": K, "ankle": A, "proximal_tibiofibular": T(-16 * w, yp - 22 * w, 30 * w),
                                        "distal_tibiofibular": Td(-6 * w, 22 * w, 21 * w)},
                  axes={"knee": T.R[:, 2], "ankle": ankle_axis}, frame=frame)


def _fibula(c: _Ctx, L) -> _Draft:
    w = c.w
    T, Td, yp = L["tibia_frame"], L["tibia_distal_frame"], L["tibia_plateau_y"]
    b = ShapeBuilder(voxel=1.2 * w)
    head = T(-20 * w, yp - 25 * w, 38 * w)
    b.add(Ellipsoid(head, np.array([11.0, 10.0, 9.0]) * w, T.R))
    b.add(RoundCone(head + T.v(-2, 8, 2) * w, head + T.v(-3, 14, 3) * w, 5 * w, 2.5 * w), k=3 * w)
    lm = Td(-6 * w, 4 * w, 30 * w)
    shaft = [head - T.v(0, 8, 0) * w, T(-13 * w, 0.75 * yp, 36 * w), T(-10 * w, 0.45 * yp, 35 * w),
             Td(-6 * w, 40 * w, 29 * w), lm]
    nodes = _spline(shaft, 14)
    r = np.interp(np.linspace(0, 1, 14), [0, 0.1, 0.5, 0.85, 1.0], [7.5, 6.0, 6.5, 8.0, 9.5]) * w
    r2 = np.interp(np.linspace(0, 1, 14), [0, 0.1, 0.5, 0.85, 1.0], [7.0, 5.5, 6.0, 7.0, 7.0]) * w
    b.add(Tube(nodes, np.stack([r, r2], 1), e1=T.R[:, 0]), k=3 * w)
    b.add(Ellipsoid(lm + Td.v(0, -4, 1) * w, np.array([11.0, 19.0, 7.5]) * w, Td.R), k=4 * w)
    b.cut(Ellipsoid(L["ankle"] + Td.v(0, 2, 0) * w, np.array([19.0, 15.0, 17.0]) * w, Td.R), k=1.0 * w)
    ct = c.cort["fibula"]
    thickness = _axial_thickness(L["ankle"], L["knee"], [0.0, 0.1, 0.3, 0.75, 0.88, 1.0],
                                 np.array([ct["epiphysis"], ct["epiphysis"], ct["diaphysis"], ct["diaphysis"],
                                           ct["epiphysis"], ct["epiphysis"]], float) * c.ct)
    rules = [
        _Rule("lateral_malleolus", Td(-6 * w, 0, 37 * w), Td.R[:, 2], 12 * w),
        _Rule("head", head + T.v(-2, 0, 10) * w, unit(T.R[:, 2] - 0.3 * T.R[:, 0]), 10 * w),
    ]

    def frame(lk):
        return lk.frame("tibia")
    return _Draft("fibula", "tibia", b, 4000, thickness=thickness, max_thickness=ct["diaphysis"] * c.ct, rules=rules,
                  joints={"proximal_tibiofibular": T(-16 * w, yp - 22 * w, 30 * w),
                          "distal_tibiofibular": Td(-6 * w, 22 * w, 21 * w)},
                  frame=frame, frame_text=c.desc["bones"]["fibula"]["frame"])


def _foot_pt(c, L, x, y, z):
    w = c.w
    fx = L.setdefault("foot_x_scale", (c.frac("foot_length") * c.p["foot_scale"] - 13.0 * w) / (261.0 * w))
    return L["ankle"] + np.array([x * w * fx, y * w, z * w])


def _talus(c: _Ctx, L) -> _Draft:
    w = c.w
    fp = lambda x, y, z: _foot_pt(c, L, x, y, z)   # noqa: E731
    b = ShapeBuilder(voxel=1.1 * w)
    b.add(Ellipsoid(fp(-2, 1, 0), np.array([17.0, 13.5, 15.0]) * w))
    b.add(Tube([fp(8, -2, -2), fp(20, -6, -7)], np.full(2, 9.0 * w)), k=4 * w)
    b.add(Ellipsoid(fp(28, -8, -11), np.array([10.0, 10.0, 12.0]) * w, rotation_about(Y, 25)), k=4 * w)
    b.add(Ellipsoid(fp(-2, -9, 13), np.array([7.0, 6.0, 5.0]) * w), k=3 * w)
    b.add(Ellipsoid(fp(-17, -6, 1), np.array([6.0, 5.0, 6.0]) * w), k=3 * w)
    ct = c.thick("tarsal", "shell")
    sub = _subtalar(c, L)
    head_seed = fp(30, -4, -18)
    return _Draft("talus", "tibia", b, 3000, thickness=ct, max_thickness=ct,
                  rules=[_Rule("head", head_seed, unit([0.3, 0.6, -0.75]), 10 * w)],
                  joints={"ankle": L["ankle"], "subtalar": sub[0], "talonavicular": fp(34, -8, -13)},
                  axes={"ankle": None, "subtalar": sub[1]},
                  frame=lambda lk: lk.frame("tibia"), frame_text=c.desc["bones"]["talus"]["frame"])


def _subtalar(c, L):
    # Inman (1976): the subtalar axis rises 42 deg from the horizontal and deviates
    # 23 deg medially from the foot's long axis.
    a = np.radians(42.0)
    m = np.radians(23.0)
    axis = unit([np.cos(a) * np.cos(m), np.sin(a), -np.cos(a) * np.sin(m)])
    return _foot_pt(c, L, -6, -16, 3), axis


def _calcaneus(c: _Ctx, L) -> _Draft:
    w = c.w
    fp = lambda x, y, z: _foot_pt(c, L, x, y, z)   # noqa: E731
    b = ShapeBuilder(voxel=1.3 * w)
    pitch = rotation_about(Z, 18.0)
    b.add(Ellipsoid(fp(-20, -30, 3), np.array([33.0, 16.0, 15.0]) * w, pitch))
    b.add(Ellipsoid(fp(-48, -34, 4), np.array([15.0, 17.0, 14.0]) * w, rotation_about(Z, -10)), k=6 * w)
    b.add(Ellipsoid(fp(12, -24, 10), np.array([15.0, 10.0, 12.0]) * w), k=6 * w)
    b.add(Ellipsoid(fp(-6, -17, -12), np.array([11.0, 5.0, 8.0]) * w), k=4 * w)
    b.cut(Ellipsoid(fp(-2, 1, 0), np.array([18.5, 15.0, 16.5]) * w), k=1.0 * w)
    ct = c.thick("tarsal", "shell")
    sub = _subtalar(c, L)
    return _Draft("calcaneus", "talus", b, 3000, thickness=ct, max_thickness=ct,
                  rules=[_Rule("heel_posterior", fp(-64, -34, 4), -X, 12 * w)],
                  joints={"subtalar": sub[0], "calcaneocuboid": fp(28, -26, 13)},
                  axes={"subtalar": sub[1]},
                  frame=lambda lk: lk.frame("tibia"), frame_text=c.desc["bones"]["calcaneus"]["frame"])


def _foot(c: _Ctx, L) -> _Draft:
    w = c.w
    fp = lambda x, y, z: _foot_pt(c, L, x, y, z)   # noqa: E731
    b = ShapeBuilder(voxel=1.1 * w)
    # navicular, cuboid, cuneiforms
    b.add(Ellipsoid(fp(47, -10, -13), np.array([7.5, 13.0, 15.0]) * w, rotation_about(Y, 30)))
    b.add(Ellipsoid(fp(44, -28, 13), np.array([13.0, 10.5, 11.5]) * w, rotation_about(Z, 15)), k=2 * w)
    b.add(Ellipsoid(fp(60, -18, -18), np.array([10.0, 14.0, 7.5]) * w), k=2 * w)
    b.add(Ellipsoid(fp(58, -12, -6), np.array([8.5, 10.5, 5.5]) * w), k=2 * w)
    b.add(Ellipsoid(fp(58, -18, 5), np.array([9.0, 11.0, 6.0]) * w), k=2 * w)
    mt = c.desc["foot"]["metatarsals"]
    heads = {}
    for i, m in enumerate(mt, start=1):
        base, head = fp(*m["base"]), fp(*m["head"])
        rb, rs, rh = np.array([m["r_base"], m["r_shaft"], m["r_head"]]) * w
        d = unit(head - base)
        b.add(Ellipsoid(base + d * rb * 0.6, np.array([rb * 0.9, rb * 1.2, rb]), frame_from_axes(d, Y, "xy")),
              k=2 * w)
        b.add(Tube([base + d * rb, 0.5 * (base + head), head - d * rh * 0.8], np.array([rs * 1.1, rs, rs * 1.05])),
              k=3 * w)
        b.add(Ellipsoid(head, np.array([rh, rh, rh * 0.85]), frame_from_axes(d, Y, "xy")), k=3 * w)
        heads[i] = (head, d, rh)
        # phalanges, with joint gaps
        pos = head + d * (rh + 2.0 * w)
        dirn = unit(d * np.array([1.0, 0.0, 1.0]) + np.array([0.0, 0.12, 0.0]))
        for k_, ln in enumerate(m["phalanges"]):
            ln = ln * w * L.get("foot_x_scale", 1.0)
            rp = rh * (0.8 - 0.12 * k_)
            dirn = unit(rotation_about(np.cross(dirn, Y), -6.0) @ dirn) if k_ else dirn
            b.add(RoundCone(pos + dirn * rp * 0.7, pos + dirn * (ln - rp * 0.6), rp, rp * 0.75))
            pos = pos + dirn * (ln + 2.0 * w)
    b.add(Ellipsoid(fp(52, -31, 29), np.array([8.0, 6.0, 6.0]) * w), k=3 * w)   # 5th metatarsal tuberosity
    # joint spaces against the talar head and the calcaneus
    b.cut(Ellipsoid(fp(28, -8, -11), np.array([12.0, 12.0, 14.0]) * w, rotation_about(Y, 25)), k=1.5 * w)
    b.cut(Ellipsoid(fp(12, -24, 10), np.array([17.0, 12.0, 14.0]) * w), k=1.5 * w)
    ct = c.thick("tarsal", "shell")
    rules = [
        _Rule("metatarsal2_head", heads[2][0] + Y * heads[2][2], Y, 8 * w),
        _Rule("metatarsal1_head", heads[1][0] - Z * heads[1][2], -Z, 8 * w),
        _Rule("metatarsal5_head", heads[5][0] + Z * heads[5][2], Z, 8 * w),
    ]
    return _Draft("foot", "calcaneus", b, 7000, thickness=ct, max_thickness=ct,
                  inner_min_volume=20.0, rules=rules, joints={"calcaneocuboid": fp(28, -26, 13)},
                  frame=lambda lk: lk.frame("tibia"), frame_text=c.desc["bones"]["foot"]["frame"])


# ---------------------------------------------------------------------------
# pelvis


def _hip(c: _Ctx, L) -> _Draft:
    w = c.w
    pp = L["pp"]
    hd = c.desc["hip_bone"]
    b = ShapeBuilder(voxel=1.7 * w)
    Hj = L["hip"]
    rh = float(c.desc["femur"]["head_diameter"]) * 0.5 * w
    # acetabulum: a thick cup open antero-latero-inferiorly
    inc, av = np.radians(hd["acetabular_inclination_deg"]), np.radians(hd["acetabular_anteversion_deg"])
    cup = unit([np.sin(av) * np.sin(inc), -np.cos(inc), np.cos(av) * np.sin(inc)])
    b.add(Intersect(Sphere(Hj, 33.0 * w), HalfSpace(Hj + cup * 5.0 * w, cup), k=3 * w))
    # ilium body above the acetabulum and the wing
    P = lambda pts: [pp(*q) for q in pts]   # noqa: E731
    crest = np.array(P(hd["crest"]))
    base = np.array(P(hd["wing_base"]))
    nu, nv = 60, 36
    Cc = _spline(crest, nu)
    Bc = _spline(base, nu)
    uu, vv = np.meshgrid(np.linspace(0, 1, nu), np.linspace(0, 1, nv), indexing="ij")
    mids = Bc[:, None, :] * (1 - vv[..., None]) + Cc[:, None, :] * vv[..., None]
    bulge = float(hd["wing_bulge"]) * w * np.sin(np.pi * vv) * np.sin(np.pi * np.clip(uu * 1.1, 0, 1))
    mids = mids + bulge[..., None] * Z[None, None, :]
    half = (float(hd["wing_half_thickness"]) * w + 5.0 * w * vv ** 8 + 5.5 * w * (1 - vv) ** 3
            + 7.0 * w * np.clip((uu - 0.72) / 0.28, 0, 1) ** 1.5)
    b.add(_plate_from_grid(mids, half, 1.0 * w), k=3 * w)
    cr = _spline(crest, 30)
    rc = np.interp(np.linspace(0, 1, 30), [0, 0.15, 0.45, 0.8, 1.0], [5.5, 7.0, 6.0, 7.0, 6.5]) * w
    b.add(Tube(cr, np.stack([rc, rc * 0.85], 1), e1=Z), k=4 * w)
    b.add(Ellipsoid(pp(*hd["asis"]), np.array([6.5, 6.5, 5.5]) * w), k=4 * w)
    b.add(Tube(P(hd["anterior_border"]), np.array([[5.0, 6.0]] * len(hd["anterior_border"])) * w, e1=Z), k=4 * w)
    b.add(Ellipsoid(pp(*hd["aiis"]), np.array([5.5, 6.5, 5.5]) * w), k=4 * w)
    b.add(Ellipsoid(Hj + np.array([8.0, 30.0, -6.0]) * w, np.array([22.0, 26.0, 13.0]) * w), k=8 * w)
    b.add(Ellipsoid(pp(*hd["iliac_tuberosity"]), np.array(hd["iliac_tuberosity_radii"]) * w), k=8 * w)
    b.add(Ellipsoid(pp(*hd["auricular"]), np.array(hd["auricular_radii"]) * w, rotation_about(Z, -35)), k=6 * w)
    b.add(Tube(_spline(P(hd["posterior_border"]), 10), np.array([[7.0, 9.0]] * 10) * w, e1=Z), k=5 * w)
    # pubis
    b.add(Tube(_spline(P(hd["superior_ramus"]), 8), np.array([[9.0, 7.5]] * 8) * w, e1=Y), k=5 * w)
    b.add(Ellipsoid(pp(*hd["pubic_body"]), np.array([9.0, 19.0, 8.0]) * w), k=5 * w)
    b.add(Ellipsoid(pp(*hd["pubic_tubercle"]), np.array([5.0, 5.0, 5.0]) * w), k=3 * w)
    b.add(Tube(_spline(P(hd["inferior_ramus"]), 10), np.array([[6.0, 8.0]] * 10) * w, e1=Z), k=4 * w)
    # ischium
    b.add(Tube(_spline(P(hd["ischial_body"]), 6), np.array([[13.0, 10.0]] * 6) * w, e1=Z), k=6 * w)
    b.add(Ellipsoid(pp(*hd["ischial_tuberosity"]), np.array([14.0, 16.0, 11.0]) * w, rotation_about(Z, -25)),
          k=6 * w)
    b.add(RoundCone(pp(*hd["ischial_spine"][0]), pp(*hd["ischial_spine"][1]), 4.0 * w, 2.0 * w), k=3 * w)
    # the socket
    b.cut(Sphere(Hj, rh + float(hd["joint_space"]) * w), k=1.5 * w)
    ct = c.thick("hip", "shell")
    rules = [
        _Rule("asis", pp(*hd["asis"]) + X * 8 * w, X, 12 * w),
        _Rule("psis", crest[-1] - X * 6 * w, -X, 12 * w),
        _Rule("pubic_tubercle", pp(*hd["pubic_tubercle"]) + X * 4 * w, X, 8 * w),
        _Rule("ischial_tuberosity", pp(*hd["ischial_tuberosity"]) - Y * 14 * w, -Y, 14 * w),
    ]
    return _Draft("hip", "sacrum", b, 7500, thickness=ct, max_thickness=ct,
                  inner_min_volume=30.0, rules=rules, fixed={"acetabulum_centre": Hj},
                  joints={"hip": Hj, "sacroiliac": pp(-118, 10, 48), "pubic_symphysis": pp(-10, -105, 0)},
                  frame=lambda lk: lk.frame("pelvis"), frame_text=c.desc["bones"]["hip"]["frame"])


def _sacrum(c: _Ctx, L) -> _Draft:
    w = c.w
    pp = L["pp"]
    sd = c.desc["sacrum"]
    b = ShapeBuilder(voxel=1.7 * w)
    n1 = L["s1_normal"]
    axis_pts = np.array([pp(*q) for q in sd["axis"]])
    ax = _spline(axis_pts, 16)
    t = np.linspace(0, 1, 16)
    rml = np.interp(t, [0, 0.3, 0.6, 1.0], [24.0, 19.0, 13.0, 7.0]) * w
    rap = np.interp(t, [0, 0.3, 0.6, 1.0], [15.0, 11.0, 8.0, 5.0]) * w
    s1c = L["s1"] - n1 * 12.0 * w
    b.add(EllipticCylinder(s1c, 16.0 * w, 12.0 * w, 25.0 * w, frame_from_axes(n1, Z, "yz"), rounding=3 * w))
    b.add(Tube(ax, np.stack([rml, rap], 1), e1=Z), k=4 * w)
    # lateral masses (a curved plate following the axis) and alae
    nv = 15
    tang = np.gradient(ax, axis=0)
    post = np.array([unit(np.cross(tg, Z)) for tg in tang])      # posterior direction along the curve
    hw = np.interp(t, [0, 0.25, 0.5, 0.75, 1.0], sd["half_width"]) * w
    ht = np.interp(t, [0, 0.25, 0.5, 0.75, 1.0], sd["half_thickness"]) * w
    vv = np.linspace(-1, 1, nv)
    mids = (ax[:, None, :] + (hw[:, None] * vv[None, :])[..., None] * Z[None, None, :]
            + (post * 4.0 * w)[:, None, :])
    half = np.repeat(ht[:, None], nv, 1) * (1 - 0.25 * vv[None, :] ** 2)
    b.add(_plate_from_grid(mids, half, 1.0 * w), k=4 * w)
    for zs in (1, -1):
        b.add(Ellipsoid(s1c + np.array([-6.0, 2.0, zs * 28.0]) * w, np.array([16.0, 13.0, 17.0]) * w), k=6 * w)
        b.add(Ellipsoid(L["s1"] + (-post[0] * 0 + np.array([-26.0, 4.0, zs * 17.0])) * w,
                        np.array([6.0, 7.0, 5.0]) * w), k=3 * w)
    # dorsal roof over the sacral canal (fused laminae), the median crest with the spinous
    # tubercles S1-S4 on it, and the canal itself
    roof = ax[:12] + post[:12] * (rap[:12, None] + 7.0 * w)
    b.add(Tube(roof, np.stack([np.interp(t[:12], [0, 1], [16.0, 7.0]) * w, np.full(12, 4.5 * w)], 1), e1=Z), k=3 * w)
    crest = ax[1:12] + post[1:12] * (rap[1:12, None] + 11.0 * w)
    b.add(Tube(crest, np.full(len(crest), 3.0 * w)), k=3 * w)
    tub = {}
    for k_, idx in enumerate((2, 5, 8, 10), start=1):
        q = ax[idx] + post[idx] * (rap[idx] + 13.0 * w)
        b.add(Sphere(q, 4.0 * w), k=3 * w)
        tub[k_] = (q, post[idx])
    canal = ax[:12] + post[:12] * (rap[:12, None] + 2.5 * w)
    b.cut(Tube(canal, np.stack([np.interp(t[:12], [0, 1], [10.0, 4.0]) * w,
                                np.interp(t[:12], [0, 1], [4.5, 2.0]) * w], 1), e1=Z), k=1.0 * w)
    # coccyx
    b.add(Tube(_spline([pp(*q) for q in sd["coccyx"]], 6), np.linspace(6.0, 3.0, 6) * w), k=2 * w)
    ct = c.thick("sacrum", "shell")
    return _Draft("sacrum", None, b, 6000, thickness=ct, max_thickness=ct,
                  inner_min_volume=30.0, side=False,
                  rules=[_Rule("s2_spinous", tub[2][0] + tub[2][1] * 4 * w, tub[2][1], 8 * w, midline=True)],
                  joints={"l5_s1": L["spine"]["l5"]["disc_centre"]},
                  frame=lambda lk: lk.frame("pelvis"), frame_text=c.desc["bones"]["sacrum"]["frame"])


# ---------------------------------------------------------------------------
# spine, skull


def _vertebra(c: _Ctx, L, name: str) -> _Draft:
    w = c.w
    d = c.desc["vertebrae"][name]
    Fv = _vertebra_frame(L, name)
    kind = name[0]
    bw, bd = float(d["body_width"]) * w, float(d["body_depth"]) * w
    bh = L["spine"][name]["bh"]
    cw, cd = float(d["canal_width"]) * w, float(d["canal_depth"]) * w
    tp = float(d["transverse_span"]) * w
    vox = {"c": 0.9, "t": 1.15, "l": 1.4}[kind] * w
    b = ShapeBuilder(voxel=vox)
    R = Fv.R
    if name == "c1":
        ring = []
        for th in np.linspace(0, 2 * np.pi, 25):
            ring.append(Fv(-4.0 * w + 19.0 * w * np.cos(th), 0.0, 21.0 * w * np.sin(th)))
        rr = np.array([[5.5 if np.cos(th) > 0.3 else 4.5, 3.5] for th in np.linspace(0, 2 * np.pi, 25)]) * w
        b.add(Tube(ring, rr, e1=R[:, 1]))
        for zs in (1, -1):
            b.add(Ellipsoid(Fv(2.0 * w, 0.0, zs * 19.0 * w), np.array([9.0, 6.0, 7.0]) * w, R), k=3 * w)
            b.add(RoundCone(Fv(0, 0, zs * 22.0 * w), Fv(-2.0 * w, 0, zs * tp / 2), 4.5 * w, 4.0 * w), k=2 * w)
        b.add(Ellipsoid(Fv(-23.0 * w, 0, 0), np.array([4.0, 5.0, 5.0]) * w, R), k=2 * w)
        tip = Fv(-27.0 * w, 0, 0)
        sp_dir = -R[:, 0]
    else:
        b.add(EllipticCylinder(Fv.o, 0.5 * bd, 0.5 * bh, 0.5 * bw, R, rounding=min(2.5 * w, 0.25 * bh)))
        if name == "c2":
            b.add(RoundCone(Fv(0, 0.5 * bh, 0), Fv(1.0 * w, 0.5 * bh + 14.0 * w, 0), 5.5 * w, 4.5 * w), k=2 * w)
            b.add(Ellipsoid(Fv(0, 0.5 * bh - 2 * w, 0), np.array([8.0, 3.5, 14.0]) * w, R), k=3 * w)
        ped_r = {"c": (3.5, 2.5), "t": (6.0, 3.5), "l": (7.5, 4.5)}[kind]
        back = -0.5 * bd
        J = {zs: Fv(back - 0.6 * cd, 0.1 * bh, zs * (0.5 * cw + 2.5 * w)) for zs in (1, -1)}
        sb = Fv(back - cd - 2.0 * w, 0.05 * bh, 0)
        for zs in (1, -1):
            b.add(Tube([Fv(back + 3 * w, 0.1 * bh, zs * (0.5 * cw - 1.0 * w)), J[zs]],
                       np.array([ped_r, ped_r]) * w, e1=R[:, 1]), k=2 * w)
            lam_h = {"c": 4.5, "t": 6.5, "l": 9.0}[kind] * w
            b.add(Tube([J[zs], sb], np.array([[lam_h, 3.0 * w], [lam_h, 3.0 * w]]), e1=R[:, 1]), k=2 * w)
            # transverse processes
            if kind == "l":
                tpt = Fv(back - 0.4 * cd, 0.05 * bh, zs * tp / 2)
                b.add(Tube([J[zs], tpt], np.array([[5.5, 3.0], [4.0, 2.5]]) * w, e1=R[:, 1]), k=2 * w)
            elif kind == "t":
                tpt = Fv(back - cd * 0.9, 0.15 * bh, zs * tp / 2)
                b.add(Tube([J[zs], tpt], np.array([[5.0, 4.0], [5.0, 4.5]]) * w, e1=R[:, 1]), k=2 * w)
            else:
                tpt = Fv(back + 0.2 * bd, 0.0, zs * tp / 2)
                b.add(Tube([Fv(back + 0.25 * bd, 0, zs * 0.45 * bw), tpt], np.array([[4.0, 3.0], [3.0, 2.5]]) * w,
                           e1=R[:, 1]), k=2 * w)
            # articular processes
            ar = {"c": (3.0, 3.5, 5.0), "t": (3.0, 5.0, 4.0), "l": (3.5, 6.5, 5.0)}[kind]
            b.add(Ellipsoid(J[zs] + R[:, 1] * 0.45 * bh + R[:, 0] * 2.0 * w, np.array(ar) * w, R), k=2 * w)
            b.add(Ellipsoid(J[zs] - R[:, 1] * 0.45 * bh - R[:, 0] * 6.0 * w, np.array(ar) * w, R), k=2 * w)
        tip_local = _spinous_tip_local(d, w)
        tip = Fv(tip_local)
        sp_dir = unit(tip - sb)
        sp_h = {"c": (4.0, 3.0), "t": (5.5, 4.0), "l": (10.0, 9.0)}[kind]
        b.add(Tube([sb, tip], np.array([[sp_h[0], 2.8], [sp_h[1], 3.2]]) * w, e1=R[:, 1]), k=2 * w)
        if name in ("c3", "c4", "c5", "c6"):
            for zs in (1, -1):
                b.add(Sphere(tip + R[:, 2] * zs * 3.5 * w, 3.2 * w), k=1.5 * w)
        else:
            b.add(Sphere(tip, 3.8 * w * (1.5 if kind == "l" else 1.0)), k=2 * w)
    ct = c.thick("vertebra", "shell")
    joints = {}
    idx = VERTEBRAE.index(name)
    lower = VERTEBRAE[idx + 1] if idx + 1 < len(VERTEBRAE) else "s1"
    parent = "sacrum" if name == "l5" else lower
    joints[f"{name}_{lower}"] = L["spine"][name]["disc_centre"]
    if idx > 0:
        upper = VERTEBRAE[idx - 1]
        joints[f"{upper}_{name}"] = L["spine"][upper]["disc_centre"]
    else:
        joints["atlanto_occipital"] = L["ao"]
    text = c.desc["bones"]["vertebra"]["frame"] if name != "c1" else c.desc["bones"]["c1"]["frame"]
    return _Draft(name, parent, b, 2500 if kind != "c" else 2000,
                  thickness=ct, max_thickness=ct, inner_min_volume=10.0, side=False,
                  rules=[_Rule("spinous_process", tip + sp_dir * 3 * w, sp_dir, 8 * w, midline=name not in ("c3", "c4", "c5", "c6"))],
                  joints=joints, frame=lambda lk, Fv=Fv: (Fv.R, Fv.o), frame_text=text,
                  meta={"body_width_mm": bw, "body_depth_mm": bd, "body_height_mm": bh})


def _skull(c: _Ctx, L) -> _Draft:
    w = c.w
    sk = c.desc["skull"]
    ao = L["ao"]
    origin = ao - np.array(sk["ao_in_head_frame"], float) * w      # porion midpoint
    Hf = _Frame(origin, np.eye(3))
    L["head_frame"] = Hf
    b = ShapeBuilder(voxel=2.4 * w)
    cran = Intersect(Ellipsoid(Hf(*(np.array(sk["cranium_centre"]) * w)), np.array(sk["cranium_radii"]) * w),
                     HalfSpace(Hf(0, -26 * w, 0), -Y), k=8 * w)
    b.add(Shell(cran, float(sk["vault_thickness"]) * w))
    P = lambda x, y, z: Hf(x * w, y * w, z * w)   # noqa: E731
    # cranial base and occipital condyles
    b.add(Ellipsoid(P(-8, -14, 0), np.array([42.0, 8.0, 40.0]) * w), k=6 * w)
    for zs in (1, -1):
        b.add(Ellipsoid(P(-6, -19, zs * 13), np.array([9.0, 5.0, 6.0]) * w), k=3 * w)
        b.add(Ellipsoid(P(-22, -16, zs * 52), np.array([8.0, 11.0, 7.0]) * w), k=5 * w)       # mastoid
        b.add(Ellipsoid(P(52, 2, zs * 50), np.array([16.0, 14.0, 13.0]) * w), k=5 * w)        # zygoma
        b.add(Tube([P(48, -2, zs * 56), P(25, -3, zs * 62), P(2, -4, zs * 60)], np.array([[3.0, 6.0]] * 3) * w,
                   e1=Z), k=3 * w)
    # face: brow, maxilla, nasal bones
    b.add(Ellipsoid(P(78, 30, 0), np.array([16.0, 11.0, 50.0]) * w), k=8 * w)
    b.add(Ellipsoid(P(62, -20, 0), np.array([32.0, 32.0, 40.0]) * w), k=10 * w)
    arch = [(18, -44, 30), (42, -49, 27), (62, -52, 17), (70, -53, 0)]
    arch_pts = [P(*q) for q in arch] + [P(x, y, -z) for (x, y, z) in arch[::-1][1:]]
    b.add(Tube(_spline(arch_pts, 20), np.array([[7.0, 5.5]] * 20) * w, e1=Y), k=6 * w)      # upper alveolar arch
    b.add(Tube([P(92, 12, 0), P(100, -6, 0)], np.array([4.0, 3.0]) * w), k=3 * w)
    for zs in (1, -1):
        b.cut(Ellipsoid(P(84, 12, zs * 33), np.array([22.0, 17.0, 17.0]) * w), k=3 * w)         # orbits
        b.cut(Ellipsoid(P(3, -11, zs * 50), np.array([8.0, 8.0, 13.0]) * w), k=2 * w)           # mandibular fossa
    b.cut(Ellipsoid(P(96, -16, 0), np.array([12.0, 16.0, 11.0]) * w), k=3 * w)                  # nasal aperture
    rules = [
        _Rule("vertex", P(-10, 130, 0), Y, 15 * w, midline=True),
        _Rule("nasion", P(97, 15, 0), X, 6 * w, midline=True),
        _Rule("frontal_r", P(70, 60, 40), unit([0.75, 0.3, 0.6]), 20 * w),
        _Rule("frontal_l", P(70, 60, -40), unit([0.75, 0.3, -0.6]), 20 * w),
        _Rule("occipital_r", P(-80, 50, 40), unit([-0.8, 0.15, 0.55]), 20 * w),
        _Rule("occipital_l", P(-80, 50, -40), unit([-0.8, 0.15, -0.55]), 20 * w),
    ]
    vt = float(sk["vault_thickness"]) * w
    tmj = P(8, -10, 0)
    L["tmj"] = tmj
    return _Draft("skull", "c1", b, 8000, thickness=c.thick("skull", "table"),
                  max_thickness=c.thick("skull", "table"), inner_min_volume=50.0, side=False, rules=rules,
                  joints={"atlanto_occipital": ao, "temporomandibular": tmj},
                  frame=lambda lk: (np.eye(3), origin), frame_text=c.desc["bones"]["skull"]["frame"],
                  meta={"vault_thickness_mm": vt})


def _mandible(c: _Ctx, L) -> _Draft:
    w = c.w
    Hf = L["head_frame"]
    P = lambda x, y, z: Hf(x * w, y * w, z * w)   # noqa: E731
    b = ShapeBuilder(voxel=1.6 * w)
    half = [(-4, -61, 46), (22, -69, 43), (46, -75, 33), (64, -79, 16), (70, -80, 0)]
    pts = [P(*q) for q in half] + [P(x, y, -z) for (x, y, z) in half[::-1][1:]]
    body = _spline(pts, 30)
    s = np.linspace(0, 1, 30)
    hv = (13.0 + 3.0 * np.cos(np.pi * (2 * s - 1)) ** 2 * 0 + 3.0 * (1 - np.abs(2 * s - 1))) * w   # taller at the chin
    b.add(Tube(body, np.stack([hv, np.full(30, 5.5 * w)], 1), e1=Y))
    for zs in (1, -1):
        b.add(Tube([P(-4, -61, zs * 46), P(-3, -38, zs * 48), P(2, -15, zs * 50)], np.array([[13.0, 4.0]] * 3) * w,
                   e1=X), k=4 * w)
        b.add(Ellipsoid(P(3, -11, zs * 50), np.array([5.0, 5.0, 10.0]) * w), k=3 * w)
        b.add(Tube([P(16, -50, zs * 45), P(24, -20, zs * 46)], np.array([[6.0, 2.5], [3.0, 2.0]]) * w, e1=X), k=3 * w)
    b.add(Ellipsoid(P(70, -89, 0), np.array([7.0, 8.0, 12.0]) * w), k=4 * w)
    ct = c.thick("skull", "table")
    o = L["tmj"]
    return _Draft("mandible", "skull", b, 4000, thickness=ct, max_thickness=ct,
                  side=False, rules=[_Rule("menton", P(70, -98, 0), -Y, 10 * w, midline=True)],
                  joints={"temporomandibular": o},
                  frame=lambda lk: (np.eye(3), o), frame_text=c.desc["bones"]["mandible"]["frame"])


# ---------------------------------------------------------------------------
# thorax


def _sternum(c: _Ctx, L) -> _Draft:
    w = c.w
    ij = L["ij"]
    ax = L["sternum_axis"]
    ln = L["sternum_length"]
    sd = c.desc["sternum"]
    prof = np.array(sd["outline"], float)          # fraction of length, half width (mm), half thickness (mm)
    b = ShapeBuilder(voxel=1.2 * w)
    # outline in (s along the sternum, z): both sides of the width profile, a notch at the top
    fs = np.linspace(0.0, 1.0, 60)
    hw = np.interp(fs, prof[:, 0], prof[:, 1]) * w
    right = np.stack([fs * ln, hw], 1)
    left = np.stack([fs[::-1] * ln, -hw[::-1]], 1)
    zn = np.linspace(-hw[0] * 0.99, hw[0] * 0.99, 15)
    top = np.stack([5.0 * w * np.exp(-(zn / (9.0 * w)) ** 2), zn], 1)
    outline = np.vstack([right, left, top])
    b.add(Plate(ij, ax, Z, outline, half_thickness=lambda s_, z_: np.interp(s_ / ln, prof[:, 0], prof[:, 2]) * w,
                res=0.6 * w))
    ct = c.thick("sternum", "shell")
    px = ij + ax * ln
    L["xiphoid"] = px
    rules = [_Rule("jugular_notch", ij + ax * 5 * w, -ax, 6 * w, midline=True),
             _Rule("xiphoid", px - ax * 2 * w, ax, 6 * w, midline=True)]

    def frame(lk):
        # ISB thorax (Wu et al. 2005): origin IJ; Y from mid(PX, T8) to mid(IJ, C7); Z normal to the
        # plane (IJ, C7, mid(PX, T8)) pointing right; X = Y x Z (forward)
        IJ, PX = lk("sternum", "jugular_notch"), lk("sternum", "xiphoid")
        C7, T8 = lk("c7", "spinous_process"), lk("t8", "spinous_process")
        lo_mid, hi_mid = 0.5 * (PX + T8), 0.5 * (IJ + C7)
        yax = unit(hi_mid - lo_mid)
        zax = unit(np.cross(IJ - C7, lo_mid - C7))
        if zax @ Z < 0:
            zax = -zax
        R = frame_from_axes(yax, zax, "yz")
        return R, IJ
    return _Draft("sternum", "t1", b, 4000, thickness=ct, max_thickness=ct, side=False,
                  rules=rules, joints={}, frame=frame, frame_text=c.desc["bones"]["sternum"]["frame"])


def _rib(c: _Ctx, L, i: int) -> _Draft:
    w = c.w
    rd = c.desc["ribs"][f"rib{i}"]
    name = f"t{i}"
    Fv = _vertebra_frame(L, name)
    vd = c.desc["vertebrae"][name]
    bw, bd = float(vd["body_width"]) * w, float(vd["body_depth"]) * w
    bh = L["spine"][name]["bh"]
    head = Fv(-0.3 * bd, 0.45 * bh, 0.5 * bw + 6.0 * w)
    tub = Fv(-0.5 * bd - float(vd["canal_depth"]) * w * 0.9 - 3.0 * w, 0.3 * bh,
             float(vd["transverse_span"]) * w * 0.5 + 5.0 * w)
    # thorax ellipse at this level: back (rib angle) beside the spine, front at the sternum
    W = float(rd["half_width"]) * w
    drop = float(rd["drop"]) * w * c.p["trunk_scale"]
    th0, th1 = np.radians(rd["theta_start_deg"]), np.radians(rd["theta_end_deg"])
    y0 = tub[1] - 6.0 * w
    y_end = y0 - drop
    # sternum x at the height of the rib's anterior end
    ij, axs = L["ij"], L["sternum_axis"]
    s_at = np.clip((ij[1] - y_end) / (-axs[1]), 0, L["sternum_length"])
    x_front = (ij + axs * s_at)[0] - float(rd["front_gap"]) * w
    x_back = tub[0] - float(rd["angle_depth"]) * w
    a = (x_front - x_back) / (1.0 - np.cos(th0))
    xc = x_back - a * np.cos(th0)
    thetas = np.linspace(th0, th1, 22)
    f = (thetas - th0) / (th1 - th0)
    ys = y0 - drop * (0.5 - 0.5 * np.cos(np.pi * np.clip(f * 1.1, 0, 1)))
    arc = np.stack([xc + a * np.cos(thetas), ys, W * np.sin(thetas)], 1)
    # widen the start so the arc leaves the tubercle smoothly
    pts = np.vstack([head, tub, arc[1:]])
    nodes = _spline(pts, 34)
    # section: thin across the thoracic wall, wide along it
    centre_axis = np.array([xc, 0.0, 0.0])
    radial = nodes - centre_axis
    radial[:, 1] = 0.0
    tang = unit(np.gradient(nodes, axis=0))
    e_thin = unit(radial - np.sum(radial * tang, axis=1, keepdims=True) * tang)
    s = np.linspace(0, 1, 34)
    wide = np.interp(s, [0, 0.08, 0.2, 0.9, 1.0], [4.5, 4.0, rd["wide"], rd["wide"], rd["wide"] * 1.15]) * w
    thin = np.interp(s, [0, 0.08, 0.2, 0.9, 1.0], [4.5, 3.8, rd["thin"], rd["thin"], rd["thin"] * 1.1]) * w
    b = ShapeBuilder(voxel=1.2 * w)
    b.add(Tube(nodes, np.stack([thin, wide], 1), e1=e_thin))
    b.add(Sphere(head, 5.0 * w), k=2 * w)
    ct = c.thick("rib", "shell")

    def frame(lk, Fv=Fv, head=head):
        return Fv.R, head
    return _Draft(f"rib{i}", name, b, 1800, thickness=ct, max_thickness=ct,
                  inner_min_volume=5.0, rules=[], joints={f"costovertebral{i}": head}, frame=frame,
                  frame_text=c.desc["bones"]["rib"]["frame"], meta={"rib_number": i})


# ---------------------------------------------------------------------------
# shoulder girdle and upper limb


def _clavicle(c: _Ctx, L) -> _Draft:
    w = c.w
    sc, ac = L["sc"], L["ac"]
    d = unit(ac - sc)
    fwd = unit(np.cross(Y, d))            # anterior, perpendicular to the clavicle
    up = np.cross(d, fwd)
    ln = np.linalg.norm(ac - sc)
    s = np.linspace(0, 1, 16)
    # S shape: medial two thirds convex forward, lateral third concave forward
    off = (9.0 * np.sin(np.pi * np.clip(s / 0.7, 0, 1)) - 7.0 * np.sin(np.pi * np.clip((s - 0.62) / 0.38, 0, 1))) * w
    ln_b = ln - 5.0 * w                     # the bone ends short of the joint centres (joint spaces)
    nodes = sc + d * 3.0 * w + np.outer(s * (ln_b - 3.0 * w), d) + np.outer(off, fwd) + np.outer(2.0 * w * np.sin(np.pi * s), up)
    r_ap = np.interp(s, [0, 0.1, 0.5, 0.85, 1.0], [11.0, 8.5, 6.5, 9.5, 10.0]) * w
    r_si = np.interp(s, [0, 0.1, 0.5, 0.85, 1.0], [11.0, 7.5, 5.5, 4.5, 4.5]) * w
    b = ShapeBuilder(voxel=1.2 * w)
    b.add(Tube(nodes, np.stack([r_ap, r_si], 1), e1=fwd))
    ct = c.cort["clavicle"]
    thickness = _axial_thickness(sc, ac, [0, 0.15, 0.35, 0.65, 0.85, 1.0],
                                 np.array([ct["epiphysis"], ct["epiphysis"], ct["diaphysis"], ct["diaphysis"],
                                           ct["epiphysis"], ct["epiphysis"]], float) * c.ct)
    rules = [_Rule("sternal_end", sc + fwd * 8 * w, fwd, 9 * w),
             _Rule("acromial_end", ac - fwd * 6 * w + up * 2 * w, unit(-fwd + 0.3 * up), 9 * w)]

    def frame(lk):
        # Wu et al. 2005: origin SC; Z from SC to AC; X perpendicular to Z and the thorax Y axis
        # (forward); Y = Z x X
        SC, AC = lk("clavicle", "sternal_end"), lk("clavicle", "acromial_end")
        yt = lk.frame("sternum")[0][:, 1]
        zax = unit(AC - SC)
        xax = unit(np.cross(yt, zax))
        R = frame_from_axes(zax, xax, "zx")
        return R, SC
    return _Draft("clavicle", "sternum", b, 3000, thickness=thickness, max_thickness=ct["diaphysis"] * c.ct,
                  rules=rules, joints={"sternoclavicular": sc, "acromioclavicular": ac}, frame=frame)


def _scapula(c: _Ctx, L) -> _Draft:
    w = c.w
    sd = c.desc["scapula"]
    gh = L["gh"]
    rh = float(c.desc["humerus"]["head_diameter"]) * 0.5 * w
    plane = np.radians(float(sd["plane_angle_deg"]))
    e_m = np.array([-np.sin(plane), 0.0, -np.cos(plane)])       # medial, in the scapular plane
    e_up = rotation_about(np.cross(e_m, Y), 0.0) @ Y
    e_n = -np.cross(e_m, e_up)                                   # posterolateral normal
    e_n = unit(e_n)
    ng = unit(-e_m + 0.08 * Y)                                   # glenoid faces anterolaterally
    G = gh - ng * (rh + float(sd["joint_space"]) * w)
    S = lambda u, v, n=0.0: G + (u * e_m + v * e_up + n * e_n) * w   # noqa: E731
    b = ShapeBuilder(voxel=0.9 * w)
    outline = np.array(sd["blade_outline"], float) * w            # (u, v) polygon
    curv_mm = float(sd["blade_curvature_mm"])

    def curv(u):       # posterior bulge of the blade (mm) at in-plane u (mm)
        return curv_mm * w * (1 - ((u / w - 55.0) / 55.0) ** 2)
    # blade: a thin plate in the scapular plane, bulging posteriorly; the plate normal
    # e_m x e_up points antero-medially, so the bulge is a negative height
    b.add(Plate(G, e_m, e_up, outline, half_thickness=float(sd["blade_half_thickness"]) * w,
                height=lambda u_, v_: -curv(u_), res=0.6 * w))
    # thick borders
    lb = np.array(sd["lateral_border"], float)
    b.add(Tube([S(*q, curv(q[0] * w) / w) for q in lb],
               np.array([[5.0, 7.0]] * len(lb)) * w, e1=e_n), k=2 * w)
    mb = np.array(sd["medial_border"], float)
    b.add(Tube([S(*q, curv(q[0] * w) / w) for q in mb],
               np.array([[3.0, 4.0]] * len(mb)) * w, e1=e_n), k=2 * w)
    # glenoid and neck
    b.add(Ellipsoid(G - ng * 9 * w, np.array([10.0, 20.0, 14.0]) * w, frame_from_axes(ng, Y, "xy")), k=3 * w)
    b.add(Tube([G - ng * 10 * w, S(22, -4)], np.array([[7.0, 15.0], [4.0, 14.0]]) * w, e1=e_n), k=5 * w)
    b.cut(Sphere(gh, rh + float(sd["joint_space"]) * w), k=1.0 * w)
    # spine of the scapula: a plate standing on the blade, its crest thick
    sp = np.array(sd["spine_base"], float)        # (u, v, height)
    tilt = unit(e_n + 0.45 * e_up)
    base_line = _spline([S(u, v, curv(u * w) / w) for u, v, _ in sp], 40)
    heights = np.interp(np.linspace(0, 1, 40), np.linspace(0, 1, len(sp)), sp[:, 2]) * w
    tv = np.linspace(0.0, 1.0, 8)
    mids = base_line[:, None, :] + (heights[:, None] * tv[None, :])[..., None] * tilt[None, None, :]
    b.add(_plate_from_grid(mids, np.full(mids.shape[:2], 2.6 * w), 0.6 * w), k=2 * w)
    crest = base_line + tilt * heights[:, None]
    b.add(Tube(crest[::3], np.array([[4.5, 3.5]] * len(crest[::3])) * w, e1=tilt), k=2 * w)
    # acromion: a plate above the humeral head, continuing the spine
    ac_pts = [gh + np.array(q, float) * w for q in sd["acromion_outline"]]
    yfit = float(np.mean([q[1] for q in ac_pts]))
    lat_drop = float(sd["acromion_lateral_tilt"])
    ac_outline = np.array([[q[0] - gh[0], q[2] - gh[2]] for q in ac_pts])
    # plate in the (x, z) plane (normal x cross z = -y); its lateral edge tilts down
    b.add(Plate(np.array([gh[0], yfit, gh[2]]), X, Z, ac_outline, half_thickness=4.0 * w,
                height=lambda u_, v_: lat_drop * v_ / 30.0, res=0.6 * w), k=3 * w)
    b.add(Tube([crest[-1], gh + np.array(sd["acromion_root"], float) * w], np.array([[5.0, 6.0]] * 2) * w), k=4 * w)
    # coracoid
    cor = [gh + np.array(q, float) * w for q in sd["coracoid"]]
    b.add(Tube(_spline(cor, 8), np.linspace(7.0, 4.5, 8) * w), k=3 * w)
    ct = c.thick("scapula", "shell")
    aa = gh + np.array(sd["acromial_angle"], float) * w
    ts = S(*sd["trigonum_spinae"])
    ai = S(*sd["inferior_angle"])
    rules = [
        # the top of the acromion over a point beside the acromioclavicular joint (PiG SHO): the plate is
        # nearly flat, and its highest point within a ball (radius 9 mm) had jumped 9-10 mm between its
        # front and back edges from one phantom seed to the next, the scapulae otherwise alike within 1-2 mm
        _Rule("acromion", L["ac"] + np.array([4.0, 4.0, 8.0]) * w, Y, 3 * w, column=True),
        _Rule("acromial_angle", aa, unit(-X + 0.8 * Z - 0.3 * Y), 10 * w),
        _Rule("inferior_angle", ai, -Y, 10 * w),
        _Rule("spine_root", ts, e_m, 8 * w),
        _Rule("blade_centre", S(*sd["blade_centre"], 6.0), e_n, 6 * w),
        _Rule("coracoid", cor[-1], unit(cor[-1] - cor[-2]), 8 * w),
    ]

    def frame(lk):
        # Wu et al. 2005: origin AA; Z from TS to AA; X normal to the plane (AI, AA, TS), forward; Y = Z x X
        AA, TS, AI = lk("scapula", "acromial_angle"), lk("scapula", "spine_root"), lk("scapula", "inferior_angle")
        zax = unit(AA - TS)
        xax = unit(np.cross(AA - TS, AI - TS))
        if xax @ X < 0:
            xax = -xax
        R = frame_from_axes(zax, xax, "zx")
        return R, AA
    return _Draft("scapula", "clavicle", b, 7000, thickness=ct, max_thickness=ct,
                  inner_min_volume=15.0, rules=rules, joints={"acromioclavicular": L["ac"], "shoulder": gh},
                  frame=frame, meta={"blade_thickness_mm": 2 * float(sd["blade_half_thickness"]) * w,
                                     "blade_normal": e_n})


def _humerus(c: _Ctx, L) -> _Draft:
    w, p = c.w, c.p
    gh, E = L["gh"], L["elbow"]
    Fh = _segment_frame(E, gh)
    Lh = np.linalg.norm(gh - E)
    hd = c.desc["humerus"]
    rh = float(hd["head_diameter"]) * 0.5 * w
    ret = np.radians(p["humeral_retroversion_deg"])
    incl = np.radians(float(hd["head_inclination_deg"]))
    med = -Fh.R[:, 2]
    nh = unit(np.cos(incl) * Fh.R[:, 1]
              + np.sin(incl) * (np.cos(ret) * med - np.sin(ret) * Fh.R[:, 0]))
    b = ShapeBuilder(voxel=1.5 * w)
    b.add(Intersect(Sphere(gh, rh), HalfSpace(gh - nh * 7.0 * w, -nh), k=2 * w))
    H = lambda x, y, z: Fh(x * w, y, z * w)   # noqa: E731  (y in mm along the bone, not scaled)
    b.add(Ellipsoid(gh + Fh.v(-3, -12, 13) * w, np.array([17.0, 20.0, 13.0]) * w, Fh.R), k=6 * w)   # greater tub.
    b.add(Ellipsoid(gh + Fh.v(14, -15, -1) * w, np.array([8.0, 10.0, 7.0]) * w, Fh.R), k=4 * w)     # lesser tub.
    b.add(Ellipsoid(gh + Fh.v(-1, -12, 4) * w, np.array([19.0, 19.0, 19.0]) * w, Fh.R), k=6 * w)
    u = np.linspace(0.12, 0.92, 14)
    prof = np.array(hd["shaft_profile"], float)
    nodes = np.array([H(np.interp(uu, [0, 0.5, 1], [-1.0, 0.0, 0.0]), uu * Lh, np.interp(uu, [0, 1], [-2.0, 7.0]))
                      for uu in u])
    rr = np.stack([np.interp(u, prof[:, 0], prof[:, 1]), np.interp(u, prof[:, 0], prof[:, 2])], 1) * w
    b.add(Tube(nodes, rr, e1=Fh.R[:, 2]), k=5 * w)
    b.add(Ellipsoid(H(0, 0.55 * Lh, 10), np.array([6.0, 20.0 / w, 4.0]) * w, Fh.R), k=4 * w)       # deltoid tub.
    # distal humerus: capitulum, trochlea, epicondyles, fossae
    b.add(Sphere(H(6, 0, 12), 10.5 * w), k=2 * w)
    b.add(RoundCone(H(1, 0, -24), H(1, 0, -13), 12.5 * w, 9.5 * w), k=2 * w)
    b.add(RoundCone(H(1, 0, -13), H(1, 0, -1), 9.5 * w, 11.0 * w), k=2 * w)
    b.add(Ellipsoid(H(-3, 6, -26), np.array([8.0, 10.0, 9.0]) * w, Fh.R), k=3 * w)
    b.add(Ellipsoid(H(-2, 7, 21), np.array([8.0, 10.0, 7.0]) * w, Fh.R), k=3 * w)
    b.add(Ellipsoid(H(-2, 24, -1), np.array([10.0, 24.0 / w, 27.0]) * w, Fh.R), k=6 * w)
    b.cut(Ellipsoid(H(-13, 17, -5), np.array([8.0, 12.0, 10.0]) * w, Fh.R), k=2 * w)
    b.cut(Ellipsoid(H(11, 16, -5), np.array([5.0, 8.0, 7.0]) * w, Fh.R), k=2 * w)
    ct = c.cort["humerus"]
    thickness = _axial_thickness(E, gh, [0.0, 0.1, 0.25, 0.4, 0.65, 0.8, 0.9, 1.0],
                                 np.array([ct["epiphysis"], ct["epiphysis"], ct["metaphysis"], ct["diaphysis"],
                                           ct["diaphysis"], ct["metaphysis"], ct["epiphysis"], ct["epiphysis"]],
                                          float) * c.ct)
    lat = Fh.R[:, 2]
    rules = [
        _Rule("greater_tubercle", gh + Fh.v(-3, -12, 26) * w, lat, 12 * w),
        _Rule("head_anterior", gh + Fh.v(22, -8, 0) * w, Fh.R[:, 0], 16 * w),
        _Rule("head_posterior", gh + Fh.v(-22, -8, 0) * w, -Fh.R[:, 0], 16 * w),
        _Rule("shaft_lateral", H(0, 0.5 * Lh, 12), lat, 10 * w),
        _Rule("lateral_epicondyle", H(-2, 7, 29), lat, 10 * w),
        _Rule("medial_epicondyle", H(-3, 6, -34), -lat, 10 * w),
        _Rule("elbow_anterior", H(10, 26, 0), Fh.R[:, 0], 12 * w),
    ]
    elbow_axis = unit(H(6, 0, 12) - H(1, 0, -18))

    def frame(lk):
        # Wu et al. 2005 (option 1): origin GH; Y from mid(EL, EM) to GH; X normal to the plane
        # (EL, EM, GH), forward; Z = X x Y
        el, em = lk("humerus", "lateral_epicondyle"), lk("humerus", "medial_epicondyle")
        yax = unit(gh - 0.5 * (el + em))
        xax = unit(np.cross(el - gh, em - gh))
        if xax @ X < 0:
            xax = -xax
        R = frame_from_axes(yax, xax, "yx")
        return R, gh
    L["capitulum"] = H(6, 0, 12)
    return _Draft("humerus", "scapula", b, 6000, thickness=thickness, max_thickness=ct["diaphysis"] * c.ct,
                  rules=rules, joints={"shoulder": gh, "elbow": E}, axes={"elbow": elbow_axis}, frame=frame,
                  meta={"retroversion_deg": p["humeral_retroversion_deg"]})


def _forearm_frame(L) -> _Frame:
    return _segment_frame(L["wrist"], L["elbow"])


def _ulna(c: _Ctx, L) -> _Draft:
    w = c.w
    Fa = _forearm_frame(L)
    Lf = np.linalg.norm(L["elbow"] - L["wrist"])
    U = lambda x, y, z: Fa(x * w, y, z * w)    # noqa: E731 (y in mm along the forearm)
    b = ShapeBuilder(voxel=1.2 * w)
    top = Lf
    b.add(Ellipsoid(U(-17, top + 4 * w, -12), np.array([9.0, 15.0, 10.0]) * w, Fa.R))            # olecranon
    b.add(Ellipsoid(U(-6, top - 15 * w, -12), np.array([12.0, 16.0, 10.0]) * w, Fa.R), k=5 * w)
    b.add(Ellipsoid(U(12, top - 13 * w, -11), np.array([8.0, 6.0, 9.0]) * w, Fa.R), k=4 * w)      # coronoid
    uh = U(-3, 7 * w, -17)
    L["ulnar_head"] = uh
    shaft = [U(-7, top - 28 * w, -12), U(-6, 0.6 * Lf, -14), U(-4, 0.3 * Lf, -16), U(-3, 22 * w, -17), uh]
    nodes = _spline(shaft, 14)
    s = np.linspace(0, 1, 14)
    r1 = np.interp(s, [0, 0.2, 0.6, 1], [11.0, 8.5, 6.5, 6.0]) * w
    r2 = np.interp(s, [0, 0.2, 0.6, 1], [12.0, 8.0, 6.5, 6.0]) * w
    b.add(Tube(nodes, np.stack([r1, r2], 1), e1=Fa.R[:, 0]), k=5 * w)
    b.add(Sphere(uh, 8.0 * w), k=3 * w)
    sty = [uh + Fa.v(-4, -3, -4) * w, uh + Fa.v(-5, -13, -5) * w]
    b.add(RoundCone(sty[0], sty[1], 3.5 * w, 2.0 * w), k=2 * w)
    # articular cuts: humeral trochlea, radial head
    b.cut(RoundCone(L["elbow"] + Fa.v(1, 0, -27) * w, L["elbow"] + Fa.v(1, 0, 0) * w, 12.5 * w, 12.5 * w), k=1 * w)
    rhc = U(1, top - 18 * w, 14)
    L["radial_head_centre"] = rhc
    b.cut(Sphere(rhc, 12.5 * w), k=1 * w)
    ct = c.cort["ulna"]
    thickness = _axial_thickness(L["wrist"], L["elbow"], [0.0, 0.08, 0.25, 0.7, 0.85, 1.0],
                                 np.array([ct["epiphysis"], ct["epiphysis"], ct["diaphysis"], ct["diaphysis"],
                                           ct["epiphysis"], ct["epiphysis"]], float) * c.ct)
    fovea_seed = uh + Fa.v(2, -8, 2) * w
    rules = [
        _Rule("olecranon", U(-24, top + 2 * w, -12), -Fa.R[:, 0], 10 * w),
        _Rule("ulnar_styloid", sty[1], unit(-Fa.R[:, 1] - 0.4 * Fa.R[:, 2] - 0.3 * Fa.R[:, 0]), 5 * w),
        _Rule("ulnar_head_fovea", fovea_seed, -Fa.R[:, 1], 3.5 * w),
        _Rule("coronoid", U(18, top - 13 * w, -11), Fa.R[:, 0], 8 * w),
    ]
    L["forearm_frame"] = Fa

    def frame(lk):
        # Wu et al. 2005: origin US; Y from US to mid(EL, EM); X normal to the plane (US, EL, EM),
        # forward; Z = X x Y
        us = lk("ulna", "ulnar_styloid")
        el, em = lk("humerus", "lateral_epicondyle"), lk("humerus", "medial_epicondyle")
        yax = unit(0.5 * (el + em) - us)
        xax = unit(np.cross(el - us, em - us))
        if xax @ X < 0:
            xax = -xax
        return frame_from_axes(yax, xax, "yx"), us
    ru = unit(uh - rhc)
    return _Draft("ulna", "humerus", b, 5000, thickness=thickness, max_thickness=ct["diaphysis"] * c.ct, rules=rules,
                  joints={"elbow": L["elbow"], "proximal_radioulnar": rhc, "distal_radioulnar": uh},
                  axes={"elbow": None, "radioulnar": None}, frame=frame, meta={"radioulnar_axis_world": ru})


def _radius(c: _Ctx, L) -> _Draft:
    w, p = c.w, c.p
    Fa = L["forearm_frame"]
    Lf = np.linalg.norm(L["elbow"] - L["wrist"])
    U = lambda x, y, z: Fa(x * w, y, z * w)    # noqa: E731
    b = ShapeBuilder(voxel=1.2 * w)
    rhc = L["radial_head_centre"]
    b.add(EllipticCylinder(rhc, 10.5 * w, 5.5 * w, 10.5 * w, Fa.R, rounding=2.5 * w))
    b.add(Tube([rhc - Fa.R[:, 1] * 4 * w, rhc - Fa.R[:, 1] * 18 * w], np.array([7.0, 7.5]) * w), k=3 * w)
    b.add(Ellipsoid(rhc + Fa.v(2, -28, -5) * w, np.array([6.0, 10.0, 6.0]) * w, Fa.R), k=4 * w)
    # shaft with the lateral bow
    p0 = rhc - Fa.R[:, 1] * 16 * w
    p1 = U(1, 34 * w, 11)
    s = np.linspace(0, 1, 14)
    bow = p["radius_lateral_bow_mm"] * w
    prof = np.sin(np.pi * s ** 1.1)
    nodes = p0 + np.outer(s, p1 - p0) + np.outer(bow * prof, Fa.R[:, 2])
    r1 = np.interp(s, [0, 0.3, 0.7, 1.0], [7.0, 7.0, 8.5, 13.0]) * w
    r2 = np.interp(s, [0, 0.3, 0.7, 1.0], [7.0, 6.5, 6.5, 8.5]) * w
    b.add(Tube(nodes, np.stack([r2, r1], 1), e1=Fa.R[:, 0]), k=4 * w)
    # distal radius and styloid
    b.add(Ellipsoid(U(1, 13 * w, 10), np.array([10.0, 11.0, 17.0]) * w, Fa.R), k=6 * w)
    b.add(RoundCone(U(0, 10 * w, 21), U(1, -9 * w, 26), 7.0 * w, 3.0 * w), k=3 * w)
    b.add(Sphere(U(-10, 14 * w, 10), 3.0 * w), k=2 * w)          # Lister's tubercle
    b.cut(Sphere(L["ulnar_head"], 9.5 * w), k=1 * w)
    b.cut(Sphere(L["capitulum"], 12.0 * w), k=1 * w)
    ct = c.cort["radius"]
    thickness = _axial_thickness(L["wrist"], L["elbow"], [0.0, 0.08, 0.25, 0.7, 0.85, 1.0],
                                 np.array([ct["epiphysis"], ct["epiphysis"], ct["diaphysis"], ct["diaphysis"],
                                           ct["epiphysis"], ct["epiphysis"]], float) * c.ct)
    rules = [
        _Rule("radial_styloid", U(1, -9 * w, 29), unit(-Fa.R[:, 1] + 0.9 * Fa.R[:, 2]), 7 * w),
        _Rule("shaft_dorsal", U(-6, 0.4 * Lf, 10 + bow / w * 0.85), -Fa.R[:, 0], 10 * w),
    ]

    def frame(lk):
        # after Wu et al. 2005: origin RS; Y from RS to the radial head centre (proximal);
        # X normal to the plane (RS, US, radial head centre), forward; Z = X x Y
        rs, us = lk("radius", "radial_styloid"), lk("ulna", "ulnar_styloid")
        yax = unit(rhc - rs)
        xax = unit(np.cross(us - rs, rhc - rs))
        if xax @ X < 0:
            xax = -xax
        return frame_from_axes(yax, xax, "yx"), rs
    return _Draft("radius", "ulna", b, 5000, thickness=thickness, max_thickness=ct["diaphysis"] * c.ct, rules=rules,
                  fixed={"radial_head_centre": rhc},
                  joints={"elbow": L["elbow"], "proximal_radioulnar": rhc, "distal_radioulnar": L["ulnar_head"],
                          "wrist": L["wrist"]},
                  axes={"radioulnar": None, "wrist": Fa.R[:, 2]}, frame=frame,
                  frame_text=c.desc["bones"]["radius"]["frame"], meta={"lateral_bow_mm": bow})


def _hand_frame(c, L) -> _Frame:
    Fa = L["forearm_frame"]
    return _Frame(L["wrist"], Fa.R)


def _hand_scale(c, L):
    return c.frac("hand_length") * c.p["hand_scale"] / (184.0 * c.w)


def _carpals(c: _Ctx, L) -> _Draft:
    w = c.w
    Fh = _hand_frame(c, L)
    hs = _hand_scale(c, L)
    P = lambda x, y, z: Fh(x * w, y * w * hs, z * w)   # noqa: E731
    b = ShapeBuilder(voxel=0.9 * w)
    for (x, y, z, rx, ry, rz) in c.desc["hand"]["carpals"]:
        b.add(Ellipsoid(P(x, y, z), np.array([rx, ry * hs, rz]) * w, Fh.R), k=1.5 * w)
    ct = c.thick("hand", "shell")
    joints = {"wrist": L["wrist"]}
    for i, r in enumerate(c.desc["hand"]["rays"], start=1):
        joints[f"cmc{i}"] = P(*r["base"])
    L["hand_P"] = P
    return _Draft("carpals", "radius", b, 4000, thickness=ct, max_thickness=ct,
                  inner_min_volume=4.0, joints=joints, axes={"wrist": Fh.R[:, 2]},
                  frame=lambda lk: _ray_frame(lk, L, 3), frame_text=c.desc["bones"]["carpals"]["frame"])


def _ray_geometry(c, L, i):
    P = L["hand_P"]
    Fh = _hand_frame(c, L)
    hs = _hand_scale(c, L)
    r = c.desc["hand"]["rays"][i - 1]
    base, head = P(*r["base"]), P(*r["head"])
    return r, base, head, Fh, hs


def _ray_frame(lk, L, i):
    """Wu et al. 2005 (hand): origin at the centre of the metacarpal base, Y along the
    metacarpal from its head to its base (proximal), X palmar (perpendicular, in the
    plane of Y and the hand's palmar direction), Z = X x Y."""
    base, head = L[f"ray{i}_base"], L[f"ray{i}_head"]
    yax = unit(base - head)
    palm = L["forearm_frame"].R[:, 0]
    return frame_from_axes(yax, palm, "yx"), base


def _ray(c: _Ctx, L, i: int) -> _Draft:
    w = c.w
    r, base, head, Fh, hs = _ray_geometry(c, L, i)
    L[f"ray{i}_base"], L[f"ray{i}_head"] = base, head
    b = ShapeBuilder(voxel=0.85 * w)
    d = unit(head - base)
    palm = Fh.R[:, 0]
    rb, rs, rh = np.array([r["r_base"], r["r_shaft"], r["r_head"]]) * w
    Rm = frame_from_axes(d, palm, "yx")
    b.add(Ellipsoid(base + d * rb * 0.5, np.array([rb, rb * 0.9, rb * 1.1]), Rm))
    b.add(Tube([base + d * rb, 0.5 * (base + head), head - d * rh * 0.5], np.array([[rs * 1.1, rs * 1.2], [rs, rs],
                                                                                     [rs * 1.1, rs * 1.2]]),
               e1=palm), k=2 * w)
    b.add(Ellipsoid(head, np.array([rh, rh * 1.05, rh * 0.9]), Rm), k=2 * w)
    rules = [_Rule("metacarpal_head", head - palm * rh, -palm, 6 * w)]
    pos = head + d * (rh + 1.8 * w)
    dirn = d
    flex_axis = unit(np.cross(d, palm))
    names = ["pip", "dip"]
    for k_, ln in enumerate(r["phalanges"]):
        ln = ln * w * hs
        dirn = unit(rotation_about(flex_axis, float(r["flexion_deg"])) @ dirn)
        rp0 = rh * (0.85 - 0.13 * k_)
        rp1 = rp0 * 0.72
        a, e = pos + dirn * rp0 * 0.7, pos + dirn * (ln - rp1)
        b.add(RoundCone(a, e, rp0, rp1))
        b.add(Ellipsoid(e, np.array([rp1 * 1.05, rp1 * 1.0, rp1 * 1.2]), frame_from_axes(dirn, palm, "yx")), k=1 * w)
        if k_ < len(r["phalanges"]) - 1 and i != 1 and k_ < 2:
            rules.append(_Rule(names[k_], e - palm * rp1, -palm, 5 * w))
        pos = pos + dirn * (ln + 1.8 * w)
    ct = c.thick("hand", "shell")
    return _Draft(f"ray{i}", "carpals", b, 3000, thickness=ct, max_thickness=ct,
                  inner_min_volume=2.0, rules=rules, joints={f"cmc{i}": base},
                  frame=lambda lk, i=i: _ray_frame(lk, L, i), frame_text=c.desc["bones"]["ray"]["frame"])


# ---------------------------------------------------------------------------
# assembly


class _Lookup:
    """Landmark and frame lookup used by the frame definitions (right-side world)."""

    def __init__(self, drafts: dict[str, _Draft], frames: dict[str, tuple], mirror_midline: bool, pelvis):
        self.drafts = drafts
        self.frames = frames
        self.mirror_midline = mirror_midline
        self.pelvis = pelvis

    def __call__(self, bone, name):
        d = self.drafts[bone]
        p = d.landmarks[name] if name in d.landmarks else d.fixed[name]
        if self.mirror_midline and not d.side:
            p = MIRROR @ p
        return p

    def frame(self, bone):
        if bone == "pelvis":
            R, o = self.pelvis
            if self.mirror_midline:
                return MIRROR @ R @ MIRROR, MIRROR @ o
            return R, o
        if bone not in self.frames:
            self.frames[bone] = self.drafts[bone].frame(self)
        R, o = self.frames[bone]
        if self.mirror_midline and not self.drafts[bone].side:
            return MIRROR @ R @ MIRROR, MIRROR @ o
        return R, o


def _tag_cortical_scale(c: _Ctx, drafts: dict[str, _Draft]) -> dict[str, _Draft]:
    for d in drafts.values():
        d.meta.setdefault("cortical_scale", c.ct)
    return drafts


def _side_drafts(c: _Ctx, L) -> dict[str, _Draft]:
    d: dict[str, _Draft] = {}
    d["hip"] = _hip(c, L)
    d["femur"] = _femur(c, L)
    d["patella"] = _patella(c, L)
    d["tibia"] = _tibia(c, L)
    d["fibula"] = _fibula(c, L)
    d["talus"] = _talus(c, L)
    d["calcaneus"] = _calcaneus(c, L)
    d["foot"] = _foot(c, L)
    for i in range(1, 13):
        d[f"rib{i}"] = _rib(c, L, i)
    d["clavicle"] = _clavicle(c, L)
    d["scapula"] = _scapula(c, L)
    d["humerus"] = _humerus(c, L)
    d["ulna"] = _ulna(c, L)
    d["radius"] = _radius(c, L)
    d["carpals"] = _carpals(c, L)
    for i in range(1, 6):
        d[f"ray{i}"] = _ray(c, L, i)
    return _tag_cortical_scale(c, d)


def _midline_drafts(c: _Ctx, L) -> dict[str, _Draft]:
    d: dict[str, _Draft] = {"sacrum": _sacrum(c, L)}
    for v in VERTEBRAE[::-1]:
        d[v] = _vertebra(c, L, v)
    d["skull"] = _skull(c, L)
    d["mandible"] = _mandible(c, L)
    d["sternum"] = _sternum(c, L)
    return _tag_cortical_scale(c, d)


def _mesh_draft(d: _Draft) -> None:
    key = _draft_key(d)
    hit = _MESH_CACHE.get(key)
    if hit is not None:
        d.V, d.F, d.Vi, d.Fi, lms = hit
        d.landmarks = dict(lms)
        return
    depth = d.max_thickness + 1.0 if d.thickness is not None else 0.0
    fld = d.builder.sample(depth=depth)
    try:
        out = field_to_mesh(fld, d.target_faces, return_dense=True)
    except RuntimeError:
        # parts that almost touch leave one-voxel bridges that decimation pinches:
        # open them (remove what is thinner than ~2 voxels) and mesh again
        try:
            out = field_to_mesh(fld, d.target_faces, opening=True, return_dense=True)
        except RuntimeError as exc:
            raise BonecapError(f"generic skeleton: bone {d.name!r}: {exc}") from None
    if out is None:
        raise BonecapError(f"generic skeleton: bone {d.name!r} produced no surface")
    d.V, d.F, dense = out
    if d.thickness is not None:
        # the inner surface is smooth and needs less resolution: mesh it on every other
        # grid point when the grid is fine
        stride = 2 if fld.voxel <= 1.0 else 1
        fi = fld if stride == 1 else Field(fld.values[::stride, ::stride, ::stride], fld.origin, fld.voxel * stride)
        if callable(d.thickness):
            ax = [fi.origin[k] + fi.voxel * np.arange(n) for k, n in enumerate(fi.values.shape)]
            t = d.thickness(ax[0][:, None, None], ax[1][None, :, None], ax[2][None, None, :])
            t = np.broadcast_to(t, fi.values.shape).astype(np.float32)
        else:
            t = np.float32(d.thickness)
        try:
            inner = field_to_mesh(fi, d.inner_target_faces or d.target_faces, offset=t,
                                  min_component_volume=d.inner_min_volume, opening=True)
        except RuntimeError:
            inner = None
        if inner is not None:
            d.Vi, d.Fi = inner
    _place_landmarks(d, dense)
    _cache_put(key, (d.V, d.F, d.Vi, d.Fi, dict(d.landmarks)))


#: A column rule's landmark: among the column's vertices within this of its extreme (mm, along the
#: rule's direction: the outer surface, not the underside), the one nearest the column's axis.
COLUMN_SURFACE_MM = 1.0


def _place_landmarks(d: _Draft, dense: np.ndarray) -> None:
    """Each rule's extreme surface point, taken on the dense (undecimated) surface so it
    does not depend on where decimation left vertices; among near-ties (within 0.3 mm
    along the direction) the vertex closest to their mean. A column rule's point is the
    outer surface's vertex nearest the column's axis (:data:`COLUMN_SURFACE_MM`)."""
    for r in d.rules:
        V = dense
        if r.midline:
            near = np.abs(V[:, 2]) < 2.0
            if np.count_nonzero(near) > 3:
                V = V[near]
        dn = unit(r.direction)
        if r.column:
            rel = V - r.seed
            along = rel @ dn
            off_axis = np.linalg.norm(rel - np.outer(along, dn), axis=1)
            inside = off_axis <= r.radius
            if np.any(inside):
                outer = inside & (along >= along[inside].max() - COLUMN_SURFACE_MM)
                d.landmarks[r.name] = V[np.flatnonzero(outer)[np.argmin(off_axis[outer])]].copy()
                continue
        best = surface_extreme(V, r.seed, r.direction, r.radius)
        cand = V[np.linalg.norm(V - best, axis=1) < 3.0]
        ties = cand[(best - cand) @ dn < 0.3]
        p = best
        if len(ties) > 1:
            p = ties[np.argmin(np.linalg.norm(ties - ties.mean(axis=0), axis=1))]
        d.landmarks[r.name] = p.copy()


# in-process cache of meshed bones, keyed by the content of their definition, so that
# rebuilding with a few parameters changed re-meshes only the bones they affect
_MESH_CACHE: dict[str, tuple] = {}
_MESH_CACHE_MAX = 400


def forget_meshes(keys) -> None:
    """Drop these keys from the in-process mesh cache (unknown keys are ignored).

    A caller that builds a one-off skeleton (a phantom subject: every seed's
    bones differ) frees the cached copies of its meshes, ~25 MB at full
    resolution, instead of carrying them to the end of the process.
    """
    for k in list(keys):
        _MESH_CACHE.pop(k, None)


def mesh_cache_keys() -> set[str]:
    """The keys now in the in-process mesh cache (see :func:`forget_meshes`)."""
    return set(_MESH_CACHE)


def _cache_put(key, value):
    if len(_MESH_CACHE) >= _MESH_CACHE_MAX:
        _MESH_CACHE.pop(next(iter(_MESH_CACHE)))
    _MESH_CACHE[key] = value


def _hash_obj(h, obj, depth=0):
    if depth > 6:
        return
    if isinstance(obj, np.ndarray):
        # dtype.str ('<f8'), not str(dtype), whose name lookup took 0.07 of the keys' 0.11 s (tiny phantom)
        h.update(obj.dtype.str.encode() + str(obj.shape).encode())
        h.update(np.ascontiguousarray(obj).tobytes())
    elif isinstance(obj, (float, int, str, bool, np.floating, np.integer)) or obj is None:
        h.update(repr(obj).encode())
    elif isinstance(obj, (list, tuple)):
        for o in obj:
            _hash_obj(h, o, depth + 1)
    elif hasattr(obj, "__dict__"):
        h.update(type(obj).__name__.encode())
        for k in sorted(vars(obj)):
            v = vars(obj)[k]
            if callable(v) and not hasattr(v, "__dict__"):
                continue
            _hash_obj(h, v, depth + 1)


def _draft_key(d: _Draft) -> str:
    import hashlib

    cached = d.meta.get("_key")
    if cached is not None:
        return cached
    h = hashlib.sha1()
    h.update(d.name.encode())
    _hash_obj(h, [d.builder.voxel, d.builder.band, d.target_faces, d.max_thickness, d.inner_min_volume,
                  d.inner_target_faces])
    for op, prims, k in d.builder.ops:
        h.update(op.encode())
        _hash_obj(h, [k, prims])
    for r in d.rules:
        _hash_obj(h, [r.name, r.seed, r.direction, r.radius, r.midline, r.column])
    if d.thickness is not None:
        lo, hi = d.builder.bounds()
        g = [np.linspace(lo[k], hi[k], 5) for k in range(3)]
        if callable(d.thickness):
            probe = np.asarray(d.thickness(g[0][:, None, None], g[1][None, :, None], g[2][None, None, :]), float)
        else:
            probe = np.asarray(d.thickness, float)
        _hash_obj(h, probe)
    key = h.hexdigest()
    d.meta["_key"] = key
    return key


_JOBS: list = []


def _mesh_job(i):
    from ..parallel import one_blas_thread

    d = _JOBS[i]
    with one_blas_thread():
        _mesh_draft(d)
    return i, (d.V, d.F, d.Vi, d.Fi, d.landmarks)


def _mesh_all(drafts: list[_Draft], workers: int | None = None, *, at_once: int | None = None) -> None:
    """Mesh every draft, in worker processes when possible (fork start method).

    ``BONECAP_WORKERS`` sets the number of processes (1: no subprocess, e.g. inside a
    multi-threaded host); the default is the number of CPUs, at most 4. The workers are
    forked from a child of this process (:func:`_mesh_pool`), so that this one never
    holds the meshing libraries. ``at_once`` caps how many bones are meshed at the
    same time and meshes the large ones in workers of their own (the phantom's
    default preset: one at a time, for its memory target).
    """
    global _JOBS
    if workers is None:
        workers = int(os.environ.get("BONECAP_WORKERS", "0")) or min(os.cpu_count() or 1, 4)
    todo = [d for d in drafts if _draft_key(d) not in _MESH_CACHE]
    todo_ids = {id(d) for d in todo}
    for d in drafts:
        if id(d) not in todo_ids:
            _mesh_draft(d)                     # from the cache
    results = None
    if workers > 1 and len(todo) > 3:
        from ..parallel import fork_child

        _JOBS = todo
        n = max(1, min(workers, len(todo), at_once or workers))
        try:
            join = fork_child(lambda: _mesh_pool(n, lean=at_once is not None), daemon=False)
        except RuntimeError:                   # no fork here: mesh in this process
            join = None
        try:
            results = join() if join is not None else None
        finally:
            _JOBS = []
    if results is None:
        for d in todo:
            _mesh_draft(d)
        return
    for d, res in zip(todo, results):
        d.V, d.F, d.Vi, d.Fi, lms = res
        d.landmarks = dict(lms)
        _cache_put(_draft_key(d), (d.V, d.F, d.Vi, d.Fi, dict(d.landmarks)))


#: A bone whose sampling grid (its bounds over the voxel size) has at least this many voxels is
#: meshed in a worker process of its own (:func:`_mesh_pool`); at the default phantom's resolution
#: that is the 17 largest of 59, the hip bone, scapula, ribs, hands' rays, femur, skull...
OWN_WORKER_VOXELS = 400_000


def _mesh_pool(workers: int, lean: bool = False) -> list:
    """Mesh :data:`_JOBS` in ``workers`` forked processes; the results in their order.

    Runs in a child of the caller (:func:`_mesh_all`): the meshing libraries (VTK,
    trimesh, fast_simplification; ~75 MiB of module state) are imported here once
    and shared with the workers forked from here, and the caller never holds them.
    The bones go largest first to a pool of ``workers``.

    ``lean`` (a cap on the bones meshed at once was asked for, for memory): the
    bones sampled on a large grid (:data:`OWN_WORKER_VOXELS`) are meshed one after
    the other, each in a worker of its own that then exits, beside the small ones
    when ``workers`` > 1, before them otherwise. A pool's workers keep what their
    largest bone left (the decimation library keeps its working vectors at their
    largest size, the heap what the grids left): ~90 MiB more per worker after the
    hip bone at the default phantom's resolution. The small bones' workers stay (a
    fork per bone costs ~0.1 s of page copies and first calls). Slower: the default
    generic skeleton took 11 s instead of 8 on 2 cores.
    """
    import multiprocessing as mp

    import fast_simplification  # noqa: F401 - imported before the fork, shared with the workers
    import trimesh  # noqa: F401
    from vtkmodules.vtkFiltersCore import vtkFlyingEdges3D  # noqa: F401

    todo = _JOBS
    cost = [float(np.prod((d.builder.bounds()[1] - d.builder.bounds()[0]) / d.builder.voxel)) for d in todo]
    order = [int(i) for i in np.argsort(cost)[::-1]]
    if lean:
        big = [i for i in order if cost[i] >= OWN_WORKER_VOXELS]
        small = [i for i in order if cost[i] < OWN_WORKER_VOXELS]
        # (ids, processes, bones per process before it is replaced)
        groups = [(big, 1, 1), (small, workers - 1 if big and workers > 1 else workers, None)]
    else:
        groups = [(order, workers, None)]
    out: list = [None] * len(todo)
    # the objects alive now (modules, the drafts) are shared with the workers page by page; the cyclic
    # collector's passes in a worker would write to every one of them and copy their pages
    gc.freeze()
    ctx = mp.get_context("fork")
    pools, running = [], []
    try:
        for ids, n, per_worker in groups:
            if not ids:
                continue
            pools.append(ctx.Pool(min(n, len(ids)), maxtasksperchild=per_worker))
            running.append(pools[-1].imap_unordered(_mesh_job, ids, chunksize=1))
            if lean and workers == 1:               # one process at a time: this group, then the next
                for i, res in running.pop():
                    out[i] = res
                pools[-1].terminate()               # (a pool that forks a worker per bone keeps an idle one)
        for results in running:
            for i, res in results:
                out[i] = res
    finally:
        for pool in pools:
            pool.terminate()
            pool.join()
    return out


def _pelvis_frame(drafts_r, drafts_l_rightworld):
    """ISB pelvis (Wu et al. 2002): origin mid-ASIS; Z from the left to the right ASIS;
    X anterior, in the plane of the ASISs and the PSIS midpoint; Y = Z x X."""
    asis_r = drafts_r["hip"].landmarks["asis"]
    psis_r = drafts_r["hip"].landmarks["psis"]
    asis_l = MIRROR @ drafts_l_rightworld["hip"].landmarks["asis"]
    psis_l = MIRROR @ drafts_l_rightworld["hip"].landmarks["psis"]
    o = 0.5 * (asis_r + asis_l)
    zax = unit(asis_r - asis_l)
    R = frame_from_axes(zax, o - 0.5 * (psis_r + psis_l), "zx")
    return R, o


def _local(R, o, pts):
    return (np.asarray(pts, float) - o) @ R


def build_generic_skeleton(stature_mm: float = 1700.0, params: dict | None = None, *,
                           side_mirroring: bool = True, description: dict | None = None,
                           bones=None) -> Skeleton:
    """Build the generic skeleton for a stature (mm) and shape parameters.

    Parameters
    ----------
    stature_mm : float
        Standing height; every dimension scales with it (segment lengths are
        fractions of stature, widths scale by ``stature / 1700``).
    params : dict, optional
        Shape parameters overriding :func:`default_shape_params` (per-segment length
        scales, femoral anteversion and neck-shaft angle, bows, torsions...). With
        ``side_mirroring=False`` a key suffixed ``_l`` / ``_r`` sets one side only.
    side_mirroring : bool
        True (default): right and midline bones are built and the left side is their
        exact mirror image. False: the left side is built from its own parameters
        (then mirrored into place), allowing asymmetry.
    description : dict, optional
        An already loaded :func:`load_generic_description`.
    bones : iterable of str, optional
        Build only these bones (names with or without the ``_r``/``_l`` suffix), plus
        their ancestors up to the root and the bones their frames are defined from.
        Default: every bone.

    Returns
    -------
    Skeleton
        ``world == "model"``: X anterior, Y up, Z right, mm, Y = 0 the floor.
        Bones in parent-before-child order, rooted at ``sacrum`` (the hip bones are
        rigidly attached to it and share the ISB pelvis frame).
    """
    return _build_generic_skeleton(stature_mm, params, side_mirroring=side_mirroring, description=description,
                                   bones=bones)


def _build_generic_skeleton(stature_mm: float = 1700.0, params: dict | None = None, *,
                            side_mirroring: bool = True, description: dict | None = None, bones=None,
                            resolution: float = 1.0, mesh_at_once: int | None = None) -> Skeleton:
    """:func:`build_generic_skeleton` with a mesh resolution factor.

    ``resolution`` > 1 samples every bone's implicit shape on a grid that many times
    coarser, without decimation: the same shapes, frames,
    joint centres and parameters, meshed ~``resolution**3`` times faster (the phantom's
    ``tiny`` preset, whose MRI voxels are 4 mm and more, uses 3.5). Thin parts then lose
    detail and a cortex thinner than about a voxel may get no inner surface.
    """
    t0 = time.perf_counter()
    if not resolution >= 1.0:
        raise ValueError(f"resolution must be >= 1 (a coarsening factor), got {resolution}")
    if not (800.0 <= float(stature_mm) <= 2500.0):
        raise BonecapError(f"stature_mm = {stature_mm} is outside the supported 800-2500 mm")
    desc = description or load_generic_description()
    spec = default_shape_params(desc)
    p_r = _resolve_params(spec, params, "r", side_mirroring)
    p_l = p_r if side_mirroring else _resolve_params(spec, params, "l", side_mirroring)
    c_r = _Ctx(stature_mm, p_r, desc)
    L_r = _layout(c_r)
    mid = _midline_drafts(c_r, L_r)
    side_r = _side_drafts(c_r, L_r)
    if side_mirroring:
        side_l = side_r
    else:
        c_l = _Ctx(stature_mm, p_l, desc)
        L_l = _layout(c_l)
        # midline geometry comes from the right-side layout; the left uses its own limbs
        side_l = _side_drafts(c_l, L_l)
    needed = _needed_bases(bones, {**mid, **side_r})
    todo = [d for k, d in {**mid, **side_r}.items() if k in needed]
    if not side_mirroring:
        todo += [d for k, d in side_l.items() if k in needed]
    if resolution != 1.0:
        for d in todo:
            d.builder.voxel *= resolution
            # no decimation: the coarse surfaces are about the budgets already, and quadric
            # decimation (with its retries) would cost more than the meshing itself
            d.target_faces = 0
            d.inner_target_faces = 0
    # in worker processes at every resolution: the coarse (tiny phantom) bones too, 0.6 s sooner on 2 cores
    # and 50 MB less in this process (2026-11-24)
    _mesh_all(todo, at_once=mesh_at_once)
    all_r = {**mid, **side_r}
    all_l = {**mid, **side_l}
    pelvis = _pelvis_frame(side_r, side_l)
    lk_r = _Lookup(all_r, {}, False, pelvis)
    lk_l = _Lookup(all_l, {}, True, pelvis)
    bones: dict[str, Bone] = {}

    def full(base, side):
        if base in mid:
            return base
        return f"{base}_{side}"

    order = ["sacrum", "hip", "femur", "patella", "tibia", "fibula", "talus", "calcaneus", "foot"]
    order += VERTEBRAE[::-1] + ["skull", "mandible"] + [f"rib{i}" for i in range(1, 13)]
    order += ["sternum", "clavicle", "scapula", "humerus", "ulna", "radius", "carpals"] + [f"ray{i}" for i in range(1, 6)]
    for base in order:
        if base not in needed:
            continue
        sides = [None] if base in mid else ["r", "l"]
        for side in sides:
            d = (all_l if side == "l" else all_r)[base]
            lk = lk_l if side == "l" else lk_r
            if base in ("sacrum", "hip"):
                R, o = pelvis if side != "l" else (MIRROR @ pelvis[0] @ MIRROR, MIRROR @ pelvis[1])
            else:
                R, o = lk.frame(base)
            R = np.asarray(R, float)
            o = np.asarray(o, float)
            mesh_v = _local(R, o, d.V)
            inner_v = _local(R, o, d.Vi) if d.Vi is not None else None
            lms = {k: _local(R, o, v) for k, v in {**d.landmarks, **d.fixed}.items()}
            jcs = {k: _local(R, o, v) for k, v in d.joints.items()}
            axes = {}
            for k, v in d.axes.items():
                axes[k] = None if v is None else v @ R
            if side == "l":
                # local coordinates of the left bone = right ones with z negated
                mesh_v = mesh_v @ MIRROR
                inner_v = None if inner_v is None else inner_v @ MIRROR
                lms = {k: v @ MIRROR for k, v in lms.items()}
                jcs = {k: v @ MIRROR for k, v in jcs.items()}
                axes = {k: (None if v is None else v @ MIRROR) for k, v in axes.items()}
                T = _transform(MIRROR @ R @ MIRROR, MIRROR @ o)
                faces = d.F[:, ::-1].copy()
                ifaces = None if d.Fi is None else d.Fi[:, ::-1].copy()
            else:
                T = _transform(R, o)
                faces = d.F.copy()
                ifaces = None if d.Fi is None else d.Fi.copy()
            name = full(base, side) if side else base
            parent = None if d.parent is None else (d.parent if d.parent in mid else f"{d.parent}_{side}")
            meta = _bone_metadata(desc, base, d, side)
            bones[name] = Bone(name=name, parent=parent, mesh=Mesh(mesh_v, faces, name), bone_to_world=T,
                               joint_centres=jcs, joint_axes={k: v for k, v in axes.items() if v is not None},
                               landmarks=lms,
                               inner_mesh=None if inner_v is None else Mesh(inner_v, ifaces, name),
                               metadata=meta)
    _add_shared_axes(bones)
    _add_bilateral_joints(bones)
    sk = Skeleton(bones=bones, world="model", metadata={
        "template": "bonecap generic skeleton",
        "description": desc.get("_path"),
        "stature_mm": float(stature_mm),
        "params": p_r if side_mirroring else {"r": p_r, "l": p_l},
        "side_mirroring": bool(side_mirroring),
        "world_frame": desc["world_frame"],
        "root": "sacrum",
        "rigid_bodies": [[b for b in g if b in bones] for g in desc.get("rigid_bodies", [])
                         if sum(b in bones for b in g) > 1],
        "spine_scales": L_r["spine_scales"],
        "build_seconds": time.perf_counter() - t0,
        **({"mesh_resolution_factor": float(resolution)} if resolution != 1.0 else {}),
    })
    return sk


# bones whose ISB frame is defined from landmarks of other bones
_FRAME_DEPS = {"tibia": ["fibula"], "fibula": ["tibia"], "talus": ["tibia"], "calcaneus": ["tibia"],
               "foot": ["tibia"], "patella": ["femur"], "ulna": ["humerus"], "radius": ["ulna", "humerus"],
               "sternum": ["c7", "t8"], "clavicle": ["sternum"], "sacrum": ["hip"], "hip": ["sacrum"]}


def _needed_bases(bones, drafts: dict[str, _Draft]) -> set[str]:
    if bones is None:
        return set(drafts)
    req = set()
    for b in ([bones] if isinstance(bones, str) else bones):
        base = b[:-2] if b[-2:] in ("_r", "_l") and b[:-2] in drafts else b
        if base not in drafts:
            raise BonecapError(f"unknown generic skeleton bone {b!r}")
        req.add(base)
    req |= {"sacrum", "hip"}
    while True:
        extra = set()
        for b in req:
            p = drafts[b].parent
            if p is not None and p not in req:
                extra.add(p)
            extra |= set(_FRAME_DEPS.get(b, [])) - req
        if not extra:
            return req
        req |= extra


def _bone_metadata(desc, base, d: _Draft, side):
    bd = desc["bones"]
    key = base
    if base in VERTEBRAE:
        key = "c1" if base == "c1" else "vertebra"
    elif base.startswith("rib"):
        key = "rib"
    elif base.startswith("ray"):
        key = "ray"
    info = bd.get(key, {})
    frame_text = d.frame_text or info.get("frame", "")
    m = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in d.meta.items()}
    scale = float(m.pop("cortical_scale", 1.0))
    m.pop("_key", None)
    summary = _cortical_summary(desc, base)
    m.update({
        "frame": frame_text,
        "isb": bool(info.get("isb", False)),
        "cortical_thickness_mm": {k: float(v) * scale for k, v in summary.items() if isinstance(v, (int, float))},
        "cortical_thickness_note": summary.get("note", ""),
        "inner_mesh_is": ("endosteal (marrow) surface" if base in ("femur", "tibia", "fibula", "humerus", "radius",
                                                                   "ulna", "clavicle")
                          else "cancellous core (absent where the bone is thinner than twice the shell)"),
        "side": side or "midline",
        "interior_landmarks": sorted(k for k in d.fixed if k in INTERIOR_LANDMARKS),
    })
    if side == "l":
        for k in ("neck_axis", "shaft_axis", "shaft_mid", "blade_normal", "radioulnar_axis_world"):
            if k in m and isinstance(m[k], list):
                m[k] = (MIRROR @ np.asarray(m[k])).tolist()
    return m


def _cortical_summary(desc, base):
    ct = desc["cortical_thickness"]
    for key in (base, base.rstrip("0123456789"), "vertebra" if base in VERTEBRAE else None,
                "hand" if base.startswith("ray") or base == "carpals" else None,
                "tarsal" if base in ("talus", "calcaneus", "foot") else None):
        if key and key in ct:
            return dict(ct[key])
    return {}


def _add_bilateral_joints(bones: dict[str, Bone]) -> None:
    """A midline parent (sternum, sacrum, thoracic vertebra) gets the joint centres of its
    paired children under side-suffixed names: ``sternoclavicular_r``, ``sacroiliac_l``,
    ``costovertebral_r``..."""
    distal: dict[str, set] = {}
    for bone in bones.values():
        if bone.parent is not None:
            distal.setdefault(bone.parent, set()).update(bone.joint_centres)
    for name, bone in bones.items():
        if bone.parent is None or name[-2:] not in ("_r", "_l"):
            continue
        parent = bones[bone.parent]
        if parent.name[-2:] in ("_r", "_l"):
            continue
        side = name[-1]
        Tp = np.linalg.inv(parent.bone_to_world)
        for key in bone.joint_centres:
            if key in parent.joint_centres or key in distal.get(name, set()):
                continue
            p = bone.landmark_in_world(key)
            parent.joint_centres[f"{key}_{side}"] = Tp[:3, :3] @ p + Tp[:3, 3]


def _add_shared_axes(bones: dict[str, Bone]) -> None:
    """Axes defined by two bones: the radio-ulnar axis (radial-head centre -> ulnar-head
    fovea) on radius and ulna, the elbow flexion axis on the ulna, the ankle on the talus."""
    for s in ("r", "l"):
        if f"radius_{s}" in bones:
            rad, uln, hum = bones[f"radius_{s}"], bones[f"ulna_{s}"], bones[f"humerus_{s}"]
            a = rad.landmark_in_world("radial_head_centre")
            b = uln.landmark_in_world("ulnar_head_fovea")
            ax = unit(b - a)
            for bone in (rad, uln):
                bone.joint_axes["radioulnar"] = unit(bone.bone_to_world[:3, :3].T @ ax)
            el = hum.bone_to_world[:3, :3] @ hum.joint_axes["elbow"]
            uln.joint_axes["elbow"] = unit(uln.bone_to_world[:3, :3].T @ el)
        if f"talus_{s}" in bones:
            tib, tal = bones[f"tibia_{s}"], bones[f"talus_{s}"]
            an = tib.bone_to_world[:3, :3] @ tib.joint_axes["ankle"]
            tal.joint_axes["ankle"] = unit(tal.bone_to_world[:3, :3].T @ an)


# ---------------------------------------------------------------------------
# pictures


def render_skeleton_views(skeleton: Skeleton, out_dir: str | os.PathLike, *, size=(900, 1500),
                          prefix: str = "generic_skeleton") -> list[Path]:
    """Render front and side views of a skeleton to ``<out_dir>/<prefix>_front.png``
    and ``<prefix>_side.png``; returns the two paths.

    Uses pyvista/VTK off-screen (EGL when no display is available) and falls back
    to matplotlib when VTK cannot open a render window.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / f"{prefix}_front.png", out / f"{prefix}_side.png"]
    meshes = []
    for name, bone in skeleton.bones.items():
        if bone.mesh is None:
            continue
        m = skeleton.world_mesh(name)
        meshes.append((name, m.vertices, m.faces))
    try:
        _render_pyvista(meshes, paths, size, skeleton.world)
    except Exception:  # pragma: no cover - depends on the graphics stack
        _render_matplotlib(meshes, paths, size)
    return paths


def _bone_colour(name):
    base = name.rsplit("_", 1)[0] if name[-2:] in ("_r", "_l") else name
    if base in VERTEBRAE or base in ("sacrum",):
        return (0.93, 0.86, 0.70)
    if base.startswith("rib") or base == "sternum":
        return (0.95, 0.91, 0.80)
    return (0.96, 0.94, 0.86)


def _render_pyvista(meshes, paths, size, world):
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import pyvista as pv

    views = [("front", (1, 0, 0)), ("side", (0, 0, 1))]
    allv = np.vstack([v for _, v, _ in meshes])
    centre = 0.5 * (allv.min(0) + allv.max(0))
    for (label, vdir), path in zip(views, paths):
        pl = pv.Plotter(off_screen=True, window_size=list(size))
        pl.set_background("white")
        for name, v, f in meshes:
            poly = pv.PolyData(v, np.hstack([np.full((len(f), 1), 3), f]).ravel())
            pl.add_mesh(poly, color=_bone_colour(name), smooth_shading=True, specular=0.2)
        pl.enable_parallel_projection()
        pl.camera_position = [tuple(centre + np.array(vdir) * 3000.0), tuple(centre), (0, 1, 0)]
        ext = allv.max(0) - allv.min(0)
        aspect = size[0] / size[1]
        pl.camera.parallel_scale = 0.53 * max(ext[1], max(ext[0], ext[2]) / aspect)
        pl.add_text(f"{label} view ({'X toward viewer' if label == 'front' else 'Z (right) toward viewer'}, Y up)",
                    font_size=10, color="black")
        pl.screenshot(str(path))
        pl.close()


def _render_matplotlib(meshes, paths, size):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    for (label, (ax0, ax1, depth, sign)), path in zip([("front", (2, 1, 0, -1)), ("side", (0, 1, 2, 1))], paths):
        fig = plt.figure(figsize=(size[0] / 100, size[1] / 100), dpi=100)
        ax = fig.add_axes([0, 0, 1, 1])
        polys, cols, depths = [], [], []
        light = unit([0.4, 0.6, 0.7])
        for _name, v, f in meshes:
            tri = v[f]
            n = unit(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]))
            vis = n[:, depth] * (1 if label == "front" else 1) > 0
            tri, n = tri[vis], n[vis]
            shade = 0.35 + 0.65 * np.clip(n @ light, 0, 1)
            xy = tri[:, :, [ax0, ax1]].copy()
            if sign < 0:
                xy[:, :, 0] *= -1
            polys.extend(xy)
            cols.extend(np.stack([shade * 0.96, shade * 0.94, shade * 0.86], 1))
            depths.extend(tri[:, :, depth].mean(1))
        order = np.argsort(depths)
        pc = PolyCollection([polys[i] for i in order], facecolors=[cols[i] for i in order], edgecolors="none")
        ax.add_collection(pc)
        ax.autoscale()
        ax.set_aspect("equal")
        ax.axis("off")
        fig.savefig(path)
        plt.close(fig)
