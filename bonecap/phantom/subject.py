"""The synthetic subject of ``bonecap phantom``: a person's own skeleton inside a body.

A phantom measures a pipeline only if it is a *person*, not the template: each
seed varies the skeleton non-affinely (segment lengths independently, femoral
anteversion and neck-shaft angle, long-bone bowing, pelvis width, and a smooth
random shape of every bone over 60 mm that no template parameter reaches) and builds
a body of its own around it (muscle girths, subcutaneous fat, skin), so that
neither a threshold nor a scaled template can pass for the truth.

Public API
----------
- :class:`PhantomSubject` -- skeleton + skin + muscle (fascia) + drawn params.
- :func:`draw_subject_params` ``(seed, stature_mm=None, generic="default", *,
  generic_per_side=False) -> dict``
- :func:`make_subject` ``(seed=0, stature_mm=None, generic="default", *,
  preset="default", params=None) -> PhantomSubject``
- :func:`build_subject_skeleton` ``(params, generic="default") -> Skeleton`` (the
  varied skeleton alone, anatomical pose, without the MRI-pose adjustments)
- :func:`affine_fit_residual` ``(a, b) -> float``
- :data:`BODY_PARAM_RANGES`, :data:`GENERIC_DRAW_RANGES`, :data:`OSIM_SHAPE_RANGES`,
  :data:`BONE_SHAPE_RANGE`, :data:`STATURE_RANGE`, :data:`PRESETS`

Frames and pose
---------------
Everything is in the template world frame ``"model"``: X anterior, Y superior,
Z to the subject's right, millimetres (the generic skeleton's and OpenSim's
ground convention). The subject stands in the anatomical reference pose
(palms forward) **except** that arms and legs are abducted about the
glenohumeral and hip joint centres by the smallest angle (0.5 deg steps) that
leaves a drawn air gap (``arm_gap_mm``, ``leg_gap_mm``) between the arm skin
(from 42 % of the humerus down to the fingertips) and the trunk and hip skin,
and between the two legs from 25 mm below the crotch down. That is the MRI
pose: in a supine whole-body scan the arms lie beside the body and the legs
slightly apart, and the pipeline segments the skin per axial slice expecting
the arms (at chest level) and the legs (below the pelvis) as separate
components. Clearing the chest wall at mid-humerus takes ~18-24 deg of
abduction (a hanging upper arm overlaps the chest outline by ~4-5 cm; in a
standing person it is pressed against it), which puts the hands ~25-30 cm
beside the thighs; the legs take ~6-12 deg. The angles are in
``params["pose"]``; ``PhantomSubject.skeleton`` is in that pose. Gravity (the
supine flattening of the soft tissue) is not modelled.

How the body is built
---------------------
1. **Segments.** Per body segment an implicit solid (an approximate signed
   distance, negative inside): swept ellipses along the thigh, shank, foot,
   upper arm, forearm and hand axes, a super-elliptic loft for the trunk from
   the crotch to the neck base, a swept ellipse for the neck and ellipsoids
   for the head and the floor of the mouth. Limb sections have the
   anthropometric girths (ANSUR II means, :data:`_GIRTH`) scaled by stature
   and the drawn girth factors, centred on the bones with anatomical offsets
   (the thigh's adductor mass is medial; the calf is anchored behind the
   tibia's anterior border, which stays subcutaneous). The trunk follows its
   bones (pelvis, spine, ribs, scapulae, clavicles, proximal femora) in 10 mm
   slabs plus a muscle and a fat thickness, except at the waist, where only
   the spine is and the waist circumference sets the section; its top narrows
   to the neck along the trapezius. Foot and palm follow their bones' extent
   plus heel pad, sole and dorsum.
2. **Smooth union** along the kinematic chain only (trunk-thigh, thigh-shank,
   ...; polynomial smooth minimum): segments that are not neighbours (the two
   thighs, an arm and the trunk below the axilla) are joined by a hard minimum,
   so they never bridge their gap.
3. **Bones inside.** The union is smoothly joined with every bone dilated by a
   per-bone skin margin (distance to a dense sampling of the bone surfaces):
   this is what makes the skull 5-7 mm under the scalp, the tibia's anterior
   border and the malleoli, olecranon, epicondyles and patella a few mm under
   the skin, and the fingers and toes.
4. **Fat.** The fascia (``muscle`` surface) is the skin offset inward by the
   local subcutaneous fat thickness (per segment, scaled by the drawn fat
   factors, with a smooth random variation), joined with the bones dilated by
   >= 2 mm and kept >= 1.5 mm inside the skin.
5. **Meshes.** The skin and fascia fields are sampled on a regular grid
   (3.5 mm, ``tiny``: 6 mm), holes are filled, the zero level sets extracted
   with marching cubes, Taubin-smoothed and decimated; both meshes are checked
   watertight with outward normals.

References
----------
- Gordon CC, Blackwell CL, Bradtmiller B, et al. *2012 Anthropometric Survey of
  U.S. Army Personnel: Methods and Summary Statistics* (ANSUR II).
  NATICK/TR-15/007, 2014. Segment circumferences, stature.
- Störchle P, Müller W, Sengeis M, et al. Measurement of mean subcutaneous fat
  thickness: eight standardised ultrasound sites compared to 216 randomly
  selected sites. *Sci Rep* 8:16268, 2018. Subcutaneous fat thickness.
- Wagner DR. Ultrasound as a tool to assess body fat. *J Obes* 2013:280713.
- Sarkalkan N, Weinans H, Zadpoor AA. Statistical shape and appearance models
  of bones. *Bone* 60:129-140, 2014 (individual bone shape beyond a few
  parameters: :data:`BONE_SHAPE_RANGE`).
- Stephan CN, Simpson EK. Facial soft tissue depths in craniofacial
  identification (part I). *J Forensic Sci* 53(6):1257-1272, 2008 (facial
  soft tissue of ~4-15 mm: the face is filled by an ellipsoid over the bones'
  dilation). The scalp over the vault is ``scalp_mm`` (5-7 mm, the usual
  adult skin-to-skull depth).
- Toogood PA, Skalak A, Cooperman DR. Proximal femoral anatomy in the normal
  human population. *Clin Orthop Relat Res* 467(4):876-885, 2009 (femoral
  anteversion ~10 +- 9 deg, neck-shaft angle ~129 +- 7 deg).
- Eycleshymer AC, Schoemaker DM. *A Cross-Section Anatomy.* Appleton, 1911
  (where the bones sit in the limb cross-sections: the femur lateral and
  anterior of the thigh's centre, the calf behind the tibia).
- Inigo Quilez, "distance functions" and "smooth minimum" (iquilezles.org):
  the ellipse/ellipsoid distance bound and the polynomial smooth minimum.

Rough edges
-----------
No breasts, genitals, ears or nose cartilage; the hand is a mitten whose
fingers come from the bones' dilation; the skin may keep a few thin tunnels
(genus > 0) where bone dilations arch (zygoma, fingers); where decimation
pinched such a tunnel into a non-manifold edge the two sheets are split
(coincident to 0.05 mm). Bones of an OpenSim template come without an
endosteal surface; one is made at the embedded description's cortical
thickness (:func:`with_marrow`), without it they rendered as solid cortex,
dark in every slice, which no bone rule finds and no person has. Their
cortex is uniform per zone (a long bone's ends, metaphyses and shaft), not
the embedded skeleton's graded shell.
An OpenSim model whose arms are geometry of the torso (gait2392) gets them
inside the trunk. The arm abduction of the MRI pose is larger than in most
real scans (see above).
"""

from __future__ import annotations

import fnmatch
import gc
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from bonecap.errors import InputError
from bonecap.model import Mesh, Skeleton

__all__ = [
    "PhantomSubject",
    "draw_subject_params",
    "make_subject",
    "build_subject_skeleton",
    "affine_fit_residual",
    "BODY_PARAM_RANGES",
    "GENERIC_DRAW_RANGES",
    "OSIM_SHAPE_RANGES",
    "OSIM_CORTEX",
    "with_marrow",
    "BONE_SHAPE_RANGE",
    "STATURE_RANGE",
    "PRESETS",
]

WORLD = "model"

# --------------------------------------------------------------------------- #
# anthropometry
# --------------------------------------------------------------------------- #
#: Skin circumferences (mm), (male, female) means, rounded to 5 mm, after ANSUR II
#: (Gordon et al. 2014): chest, waist (omphalion), buttock, thigh (gluteal
#: furrow), knee, calf, ankle (minimum), upper arm (relaxed, ~0.93 x the flexed
#: biceps circumference), elbow, forearm, wrist, neck, head. Scaled by
#: stature / _STATURE_REF.
_GIRTH = {
    "chest": (1030.0, 920.0),
    "waist": (940.0, 860.0),
    "buttock": (1020.0, 1020.0),
    "thigh": (620.0, 630.0),
    "knee": (395.0, 380.0),
    "calf": (390.0, 370.0),
    "ankle": (225.0, 215.0),
    "upper_arm": (330.0, 285.0),
    "elbow": (280.0, 245.0),
    "forearm": (300.0, 250.0),
    "wrist": (175.0, 155.0),
    "neck": (390.0, 330.0),
}
#: ANSUR II mean statures (male, female), mm.
_STATURE_REF = (1756.0, 1629.0)

#: Typical single-layer subcutaneous fat thickness (mm) of normal-weight adults,
#: (male, female), per region: the order of the ultrasound figures of
#: Störchle et al. 2018 and Wagner 2013 (abdomen 10-30 mm, thigh 5-25 mm, upper
#: arm 4-15 mm, calf 3-10 mm, scalp ~3-4 mm). Multiplied by the drawn
#: ``fat_factor`` (0.6-1.6) and the regional factors.
_FAT_REF = {
    "chest": (8.0, 11.0),      # chest and upper back
    "abdomen": (18.0, 22.0),   # anterior abdominal wall
    "back": (10.0, 12.0),      # lumbar back
    "buttock": (12.0, 22.0),
    "thigh": (8.0, 16.0),
    "calf": (5.0, 9.0),
    "upper_arm": (5.0, 11.0),
    "forearm": (4.0, 6.0),
    "hand": (2.5, 3.0),
    "foot": (3.0, 3.5),
    "neck": (6.0, 7.0),
    "head": (3.0, 3.0),
}

# --------------------------------------------------------------------------- #
# parameter ranges
# --------------------------------------------------------------------------- #
_SEGMENTS = ("thigh", "shank", "foot", "trunk", "upper_arm", "forearm", "hand")

#: Skeleton parameters drawn for an OpenSim template, (low, high), uniform.
#: ``length.<segment>`` multiplies the segment's length (along its joint-to-joint
#: axis), drawn for both sides together, times a per-side asymmetry of +-1 %
#: (bilateral length asymmetry of adults is ~1 %); ``width.<segment>`` its
#: breadth. Femoral anteversion and neck-shaft angle are absolute (the template
#: is assumed to have 13 deg and 127 deg, typical adult values); ``bow.*`` adds a
#: sagitta (mm) to the bone's mid-shaft, 0 at both joint centres.
OSIM_SHAPE_RANGES: dict[str, tuple[float, float]] = {
    **{f"length.{s}": (0.93, 1.07) for s in _SEGMENTS},
    **{f"width.{s}": (0.95, 1.05) for s in _SEGMENTS},
    "length_asymmetry": (-0.01, 0.01),
    "pelvis_width": (0.92, 1.08),
    "femoral_anteversion_deg": (5.0, 25.0),
    "neck_shaft_angle_deg": (120.0, 135.0),
    "bow.femur_mm": (-5.0, 5.0),
    "bow.tibia_mm": (-4.0, 4.0),
    "bow.humerus_mm": (-3.0, 3.0),
    "bow.radius_mm": (-3.0, 3.0),
}
_OSIM_NOMINAL_ANTEVERSION = 13.0
_OSIM_NOMINAL_NECK_SHAFT = 127.0

#: Body-shape parameters, (low, high), uniform.
#: ``sex_blend`` mixes the male (0) and female (1) girth and fat tables;
#: ``girth.*`` scales a segment's muscle circumference (+-15 %); ``fat_factor``
#: scales every fat thickness, ``fat.trunk``/``fat.limbs`` shift fat between trunk
#: and limbs; ``scalp_mm`` is the skull-to-scalp distance, ``shin_mm`` the tibia's
#: anterior border to skin; ``arm_gap_mm``/``leg_gap_mm`` the air gap of the MRI
#: pose; ``skin_noise_mm`` the amplitude of a smooth random skin relief and
#: ``fat_noise`` the relative amplitude of the fat thickness's random variation.
BODY_PARAM_RANGES: dict[str, tuple[float, float]] = {
    "sex_blend": (0.0, 1.0),
    **{f"girth.{g}": (0.85, 1.15) for g in ("chest", "waist", "buttock", "thigh", "calf",
                                             "upper_arm", "forearm", "neck")},
    "girth_asymmetry": (-0.02, 0.02),
    "fat_factor": (0.6, 1.6),
    "fat.trunk": (0.8, 1.25),
    "fat.limbs": (0.8, 1.25),
    "scalp_mm": (5.0, 7.0),
    "shin_mm": (4.5, 7.0),
    "arm_gap_mm": (5.0, 15.0),
    "leg_gap_mm": (5.0, 15.0),
    "skin_noise_mm": (0.5, 2.0),
    "fat_noise": (0.1, 0.3),
}
#: Individual bone shape beyond the template's parameters: RMS (mm, for a 400 mm bone; proportional to
#: the bone's length) of a smooth random non-affine displacement of every bone longer than 60 mm. Bone
#: statistical shape models leave a residual of this order after alignment and their first modes
#: (Sarkalkan N, Weinans H, Zadpoor AA. Statistical shape and appearance models of bones. *Bone*
#: 60:129-140, 2014).
BONE_SHAPE_RANGE = (2.0, 3.5)
#: Default stature: 1700 mm x U(0.96, 1.04).
STATURE_RANGE = (1632.0, 1768.0)

#: Grid spacing (mm), bone surface sampling (mm) and face budgets per preset.
#: ``tiny`` is for tests and quick looks: a 6 mm grid (margins over the bones widened to >= 0.8 x the
#: spacing so that the coarse meshes still enclose them), coarse meshes. ``mesh_at_once``: how many
#: bones of the skeleton are meshed at the same time (default preset: one, for its memory target;
#: two workers with their grids held ~360 MiB with this process; ~8 s longer on 2 cores). ``lean``:
#: memory is handed back between stages (:func:`release_memory`) and large decimations run in child
#: processes (:func:`_decimate`); the tiny preset, a few tens of MB, skips both (~2.5 s of its ~14,
#: 2026-11-28: every child imported trimesh again; the results are the same either way).
PRESETS: dict[str, dict[str, float]] = {
    "default": {"spacing": 3.5, "sample_spacing": 2.0, "skin_faces": 200_000, "muscle_faces": 200_000,
                "taubin_iterations": 10, "mesh_at_once": 1, "lean": True},
    "tiny": {"spacing": 6.0, "sample_spacing": 3.5, "skin_faces": 20_000, "muscle_faces": 20_000,
             "taubin_iterations": 6, "bone_resolution": 3.5, "lean": False},
}

_F_MIN = 1.5      # minimum fat (skin to fascia) thickness, mm
_M_MUS = 2.5      # bone surface to fascia, mm (the periosteum and a thin muscle layer)


# --------------------------------------------------------------------------- #
# the subject
# --------------------------------------------------------------------------- #
@dataclass
class PhantomSubject:
    """A synthetic person: skeleton, skin and fascia, all in the world frame ``"model"``.

    Attributes
    ----------
    skeleton : Skeleton
        The subject's own bones, ``world="model"`` (X anterior, Y up, Z right,
        mm), in the MRI pose (anatomical pose, arms and legs abducted just
        enough to leave ``params["body"]["arm_gap_mm"]`` / ``leg_gap_mm`` of air;
        see the module docstring).
    skin : Mesh
        The skin surface, world frame, watertight, outward normals.
    muscle : Mesh
        The fascia: the inner boundary of the subcutaneous fat (everything
        between ``muscle`` and ``skin`` is fat); it contains every bone.
    params : dict
        ``seed``, ``generic``, ``preset``, ``stature_mm`` (drawn),
        ``skeleton`` (the template's parameters), ``bone_shape`` (individual
        bone shape), ``body`` (the body parameters), ``ranges`` (the ranges
        they were drawn from), ``pose`` (abduction angles of the MRI pose, deg,
        and the gaps obtained, mm).
    metadata : dict
        ``preset``, ``spacing_mm``, ``timings_s``, ``skin_faces``,
        ``muscle_faces``, ``height_mm`` (of the skin), ``levels_mm`` (heights
        of the hip joint centres, crotch, waist, chest, shoulders, neck base,
        head, mid-humerus and mid-thigh in the MRI pose), ``joints_mm`` (joint
        centres, world) and ``anatomical_bone_to_world`` (each bone's pose
        before the MRI-pose abduction, nested lists).
    """

    skeleton: Skeleton
    skin: Mesh
    muscle: Mesh
    params: dict[str, Any]
    metadata: dict[str, Any] = field(default_factory=dict)

    def layers(self, world_to: np.ndarray | None = None, frame: str = "") -> list[tuple[Mesh, str]]:
        """The ordered render layers for :mod:`bonecap.phantom.mri`.

        Parameters
        ----------
        world_to : ndarray (4, 4), optional
            A transform from the world frame (e.g. model -> LPS) applied to
            every layer. The layers share the faces arrays of the subject's
            meshes rather than copying them (they are for reading: the
            whole-body set's faces are ~20 MB at the default preset).
        frame : str
            Frame name of the transformed layers (without ``world_to``: the
            skeleton's world).

        Returns
        -------
        list of (Mesh, str)
            ``(skin, "fat")``, ``(muscle, "muscle")``, then per bone (skeleton
            order) ``(outer surface, "cortex")`` and, when the bone has an
            endosteal surface, ``(inner surface, "marrow")``; in the world
            frame, or mapped by ``world_to``. Later layers overwrite earlier
            ones, so a bone without an inner mesh renders as solid cortex.
        """
        # every layer is a new mesh over the subject's own faces array (they are for reading)
        T_w = np.eye(4) if world_to is None else np.asarray(world_to, dtype=float)
        frame = self.skeleton.world if world_to is None else frame

        def mapped(mesh: Mesh, bone_to_world: np.ndarray | None = None) -> Mesh:
            v = mesh.vertices
            if bone_to_world is not None:     # two steps, as world_mesh then transformed: the same digits
                v = v @ bone_to_world[:3, :3].T + bone_to_world[:3, 3]
            return Mesh(v @ T_w[:3, :3].T + T_w[:3, 3], mesh.faces, frame)

        out = [(mapped(self.skin), "fat"), (mapped(self.muscle), "muscle")]
        for bone in self.skeleton.bones.values():
            if bone.mesh is None:
                continue
            out.append((mapped(bone.mesh, bone.bone_to_world), "cortex"))
            if bone.inner_mesh is not None:
                out.append((mapped(bone.inner_mesh, bone.bone_to_world), "marrow"))
        return out

    def bone_world_vertices(self, names: list[str] | None = None) -> np.ndarray:
        """All vertices of the named bones (default all) in the world frame, stacked (N, 3)."""
        names = self.skeleton.names if names is None else names
        parts = [self.skeleton.world_mesh(n).vertices for n in names if self.skeleton.bones[n].mesh is not None]
        return np.concatenate(parts) if parts else np.zeros((0, 3))


# --------------------------------------------------------------------------- #
# parameters
# --------------------------------------------------------------------------- #
def _is_osim(generic) -> bool:
    return str(generic) != "default"


#: Population ranges drawn for the generic skeleton's parameters (``default_shape_params()``), each
#: clipped to the parameter's allowed range there. Segment lengths +-7 % (+-6 % foot, hand, trunk);
#: pelvis and shoulder width +-8 %; femoral anteversion 5-25 deg and neck-shaft angle 120-135 deg
#: (adult means ~10-13 deg and ~128-129 deg, SD ~7-9 deg: Toogood et al. 2009); bows and torsions around
#: the template's defaults. Parameters not listed here are drawn in the middle half of their range.
#: ``GENERIC_SIDE_SPREAD``: per-side deviation added to the bilateral draw (left/right asymmetry).
GENERIC_DRAW_RANGES: dict[str, tuple[float, float]] = {
    "thigh_scale": (0.93, 1.07), "shank_scale": (0.93, 1.07), "foot_scale": (0.94, 1.06),
    "upper_arm_scale": (0.93, 1.07), "forearm_scale": (0.93, 1.07), "hand_scale": (0.94, 1.06),
    "trunk_scale": (0.94, 1.06), "shoulder_width_scale": (0.92, 1.08), "pelvis_width_scale": (0.92, 1.08),
    "femoral_anteversion_deg": (5.0, 25.0), "femoral_neck_shaft_deg": (120.0, 135.0),
    "femur_anterior_bow_mm": (4.0, 14.0), "radius_lateral_bow_mm": (5.0, 13.0),
    "tibial_torsion_deg": (10.0, 30.0), "humeral_retroversion_deg": (20.0, 40.0),
    "cortical_thickness_scale": (0.85, 1.15),
}
GENERIC_SIDE_SPREAD: dict[str, tuple[str, float]] = {
    "thigh_scale": ("rel", 0.01), "shank_scale": ("rel", 0.01), "foot_scale": ("rel", 0.01),
    "upper_arm_scale": ("rel", 0.01), "forearm_scale": ("rel", 0.01), "hand_scale": ("rel", 0.01),
    "femoral_anteversion_deg": ("abs", 3.0), "femoral_neck_shaft_deg": ("abs", 2.0),
    "tibial_torsion_deg": ("abs", 3.0), "humeral_retroversion_deg": ("abs", 3.0),
    "femur_anterior_bow_mm": ("abs", 1.0), "radius_lateral_bow_mm": ("abs", 1.0),
}


def _generic_spec() -> dict[str, tuple[float, float, float]]:
    """``{name: (default, low, high)}`` from the generic module's ``default_shape_params()``.

    Accepts the forms ``{name: {"default", "range"|"min"/"max"|"low"/"high"}}``,
    ``{name: (default, low, high)}`` and ``{name: ShapeParam}`` (attributes of
    the same names); a parameter without a range is not varied.
    """
    from bonecap.skeleton import generic as gen

    raw = gen.default_shape_params()
    spec: dict[str, tuple[float, float, float]] = {}
    for name, v in raw.items():
        d = lo = hi = None
        if isinstance(v, dict):
            d = v.get("default", v.get("value"))
            rng = v.get("range")
            if rng is None and ("min" in v or "low" in v):
                rng = (v.get("min", v.get("low")), v.get("max", v.get("high")))
        elif isinstance(v, (tuple, list)) and len(v) == 3:
            d, rng = v[0], (v[1], v[2])
        elif hasattr(v, "default"):
            d = getattr(v, "default")
            rng = getattr(v, "range", None)
            if rng is None and hasattr(v, "low"):
                rng = (v.low, v.high)
        else:
            d, rng = v, None
        if d is None:
            continue
        if rng is None or not isinstance(d, (int, float)):
            spec[name] = (d, d, d)
            continue
        lo, hi = float(rng[0]), float(rng[1])
        spec[name] = (float(d), lo, hi)
    return spec


def draw_subject_params(seed: int, stature_mm: float | None = None, generic="default", *,
                        generic_per_side: bool = False) -> dict[str, Any]:
    """Draw one subject's shape parameters.

    Parameters
    ----------
    seed : int
        Seed of :func:`numpy.random.default_rng`; the same seed gives the same
        parameters.
    stature_mm : float, optional
        Stature; default drawn uniformly in :data:`STATURE_RANGE` (1700 mm +-4 %,
        about the pooled ANSUR II mean).
    generic : str or path-like
        ``"default"`` (the embedded generic skeleton: the parameters of
        ``bonecap.skeleton.generic.default_shape_params()``, drawn uniformly in
        :data:`GENERIC_DRAW_RANGES` clipped to their allowed ranges) or an
        OpenSim ``.osim`` path (the parameters of :data:`OSIM_SHAPE_RANGES`).
    generic_per_side : bool
        For the generic skeleton: draw left and right values apart
        (:data:`GENERIC_SIDE_SPREAD`, ``_r``/``_l`` keys). The generic builder
        then builds both sides, which takes twice as long, so it is off by
        default (the generic subject is left-right symmetric; an OpenSim
        subject always gets per-side segment lengths).

    Returns
    -------
    dict
        ``seed``, ``generic``, ``stature_mm``, ``skeleton`` (name -> value: the
        template's own parameters), ``bone_shape`` (``noise_mm``, ``seed``: the
        individual shape added to every bone, :data:`BONE_SHAPE_RANGE`),
        ``body`` (name -> value, see :data:`BODY_PARAM_RANGES`), ``ranges``
        (``{"skeleton": {name: (lo, hi)}, "body": {...}, "bone_shape": {...},
        "stature_mm": (lo, hi)}``). Plain numbers: JSON-serialisable.

    References
    ----------
    Stature and girths: ANSUR II (Gordon et al. 2014); fat thickness: Störchle
    et al. 2018, Wagner 2013; femoral anteversion and neck-shaft angle:
    Toogood et al. 2009; residual bone shape: Sarkalkan et al. 2014 (full
    entries in the module docstring).
    """
    rng = np.random.default_rng(seed)
    stature = float(rng.uniform(*STATURE_RANGE)) if stature_mm is None else float(stature_mm)
    if not stature > 0:
        raise InputError(f"stature must be positive, got {stature_mm}")
    skel: dict[str, Any] = {}
    skel_ranges: dict[str, tuple[float, float]] = {}
    if _is_osim(generic):
        for name, (lo, hi) in OSIM_SHAPE_RANGES.items():
            if name.startswith("length.") or name == "length_asymmetry":
                continue
            skel[name] = float(rng.uniform(lo, hi))
            skel_ranges[name] = (lo, hi)
        alo, ahi = OSIM_SHAPE_RANGES["length_asymmetry"]
        for s in _SEGMENTS:
            lo, hi = OSIM_SHAPE_RANGES[f"length.{s}"]
            both = rng.uniform(lo, hi)
            for side in ("r", "l"):
                skel[f"length.{s}_{side}"] = float(both * (1.0 + rng.uniform(alo, ahi)))
                skel_ranges[f"length.{s}_{side}"] = (lo * (1 + alo), hi * (1 + ahi))
    else:
        for name, (d, lo, hi) in _generic_spec().items():
            if not hi > lo:
                continue
            dlo, dhi = GENERIC_DRAW_RANGES.get(name, (d - 0.25 * (hi - lo), d + 0.25 * (hi - lo)))
            dlo, dhi = max(dlo, lo), min(dhi, hi)
            both = float(rng.uniform(dlo, dhi))
            if name in GENERIC_SIDE_SPREAD and generic_per_side:
                kind, spread = GENERIC_SIDE_SPREAD[name]
                for side in ("r", "l"):
                    dev = rng.uniform(-spread, spread)
                    v = both * (1.0 + dev) if kind == "rel" else both + dev
                    skel[f"{name}_{side}"] = float(np.clip(v, lo, hi))
                    wide = (dlo * (1 - spread), dhi * (1 + spread)) if kind == "rel" else (dlo - spread, dhi + spread)
                    skel_ranges[f"{name}_{side}"] = (max(lo, wide[0]), min(hi, wide[1]))
            else:
                skel[name] = both
                skel_ranges[name] = (dlo, dhi)
    body: dict[str, Any] = {}
    body_ranges: dict[str, tuple[float, float]] = {}
    for name, (lo, hi) in BODY_PARAM_RANGES.items():
        body[name] = float(rng.uniform(lo, hi))
        body_ranges[name] = (lo, hi)
    glo, ghi = BODY_PARAM_RANGES["girth_asymmetry"]
    for g in ("thigh", "calf", "upper_arm", "forearm"):
        for side in ("r", "l"):
            body[f"girth.{g}_{side}"] = float(body[f"girth.{g}"] * (1.0 + rng.uniform(glo, ghi)))
    body["noise_seed"] = int(rng.integers(0, 2**31 - 1))
    lo, hi = BONE_SHAPE_RANGE
    bone_shape = {"noise_mm": float(rng.uniform(lo, hi)), "seed": int(rng.integers(0, 2**31 - 1))}
    return {
        "seed": int(seed),
        "generic": str(generic),
        "stature_mm": stature,
        "skeleton": skel,
        "bone_shape": bone_shape,
        "body": body,
        "ranges": {"skeleton": skel_ranges, "body": body_ranges, "bone_shape": {"noise_mm": BONE_SHAPE_RANGE},
                   "stature_mm": STATURE_RANGE if stature_mm is None else (stature, stature)},
    }


# --------------------------------------------------------------------------- #
# bone roles
# --------------------------------------------------------------------------- #
_ROLE_BODIES = ("pelvis", "torso", "femur", "patella", "tibia", "talus", "calcn", "toes", "humerus", "ulna",
                "radius", "hand")


def _bone_roles(sk: Skeleton) -> dict[str, str]:
    """Map each bone to a Rajagopal-style body name (``femur_r``, ``torso``...), or leave it out.

    The generic skeleton's names go through ``generic_skeleton/opensim_map.yaml``
    (rajagopal2016 family); OpenSim bodies named like Rajagopal's, Hamner's or
    gait2392's are their own role.
    """
    roles: dict[str, str] = {}
    known = {b if b in ("pelvis", "torso") else f"{b}_{s}" for b in _ROLE_BODIES for s in "rl"}
    map_fn = None
    if sk.world != "opensim_ground" and sk.metadata.get("format") != "opensim":
        try:
            from bonecap.skeleton.names import opensim_body_of

            map_fn = lambda n: opensim_body_of(n, "rajagopal2016")  # noqa: E731
        except Exception:  # noqa: BLE001 - the map is optional: fall back to names
            map_fn = None
    for name in sk.bones:
        role = name if name in known else (map_fn(name) if map_fn else None)
        if role is None:
            # a few common spellings of OpenSim models
            low = name.lower()
            for b in ("femur", "tibia", "patella", "talus", "calcn", "toes", "humerus", "ulna", "radius", "hand"):
                for s in "rl":
                    if low in (f"{b}_{s}", f"{s}_{b}"):
                        role = f"{b}_{s}"
        if role in known:
            roles[name] = role
    return roles


def _bones_with_role(roles: dict[str, str], *wanted: str) -> list[str]:
    return [b for b, r in roles.items() if r in wanted]


# --------------------------------------------------------------------------- #
# skeleton
# --------------------------------------------------------------------------- #
def _world_points(sk: Skeleton, name: str, pts: np.ndarray) -> np.ndarray:
    T = sk.bones[name].bone_to_world
    return pts @ T[:3, :3].T + T[:3, 3]


def _shared_joint(sk: Skeleton, child: str, parent: str | None = None) -> np.ndarray | None:
    """World position of the joint centre a bone shares with its parent (or with ``parent``)."""
    b = sk.bones[child]
    parent = b.parent if parent is None else parent
    if parent is None:
        return None
    p = sk.bones[parent]
    keys = sorted(set(b.joint_centres) & set(p.joint_centres))
    for k in keys:
        a = b.landmark_in_world(k)
        c = p.landmark_in_world(k)
        if np.linalg.norm(a - c) < 10.0:
            return 0.5 * (a + c)
    return None


def _descendants(sk: Skeleton, root: str) -> list[str]:
    out = [root]
    for name, bone in sk.bones.items():  # parent-before-child order
        if bone.parent in out:
            out.append(name)
    return out


def _skeleton_extent_y(sk: Skeleton) -> tuple[float, float]:
    lo, hi = np.inf, -np.inf
    for n, b in sk.bones.items():
        if b.mesh is None:
            continue
        y = _world_points(sk, n, b.mesh.vertices)[:, 1]
        lo, hi = min(lo, y.min()), max(hi, y.max())
    return float(lo), float(hi)


def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def _rot(axis, angle) -> np.ndarray:
    """Rotation matrix about a unit axis (Rodrigues)."""
    a = _unit(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def _rotate_points(p, centre, axis, angles):
    """Rotate points ``p`` (N,3) about the line (centre, axis) by per-point ``angles`` (N,)."""
    a = _unit(axis)
    q = p - centre
    c, s = np.cos(angles)[:, None], np.sin(angles)[:, None]
    cross = np.cross(a, q)
    dot = (q @ a)[:, None]
    return centre + q * c + cross * s + a * dot * (1 - c)


def build_subject_skeleton(params: dict[str, Any], generic="default") -> Skeleton:
    """The subject's varied skeleton in the anatomical reference pose.

    Parameters
    ----------
    params : dict
        As returned by :func:`draw_subject_params` (``stature_mm`` and
        ``skeleton`` are used).
    generic : str or path-like
        ``"default"``: ``build_generic_skeleton(stature_mm, params["skeleton"])``.
        An ``.osim`` path: the model read with :func:`read_osim`, scaled to the
        stature, then varied per body (see :func:`_vary_osim_skeleton`).
        Either way every bone then gets its individual shape
        (``params["bone_shape"]``, see :func:`_individual_bone_shapes`).

    Returns
    -------
    Skeleton
        ``world="model"``; ``metadata["phantom"]`` records what was applied.
    """
    stature = float(params["stature_mm"])
    if not _is_osim(generic):
        from bonecap.skeleton.generic import _build_generic_skeleton, forget_meshes, mesh_cache_keys

        sp = dict(params["skeleton"])
        per_side = any(k[-2:] in ("_r", "_l") for k in sp)
        # the tiny preset images at >= 4 mm: bones meshed on a grid 3.5 times as coarse (same shapes,
        # frames and parameters, undecimated) cost ~2 s and are about as fine as its 4 mm pixels
        preset_cfg = PRESETS.get(params.get("preset", "default"), {})
        resolution = float(preset_cfg.get("bone_resolution", 1.0))
        cached = mesh_cache_keys()
        sk = _build_generic_skeleton(stature_mm=stature, params=sp, side_mirroring=not per_side,
                                     resolution=resolution, mesh_at_once=preset_cfg.get("mesh_at_once"))
        # every subject's bones differ (the drawn stature scales them all): their cached copies would
        # only hold memory (~25 MB at the default preset) to the end of the process
        forget_meshes(mesh_cache_keys() - cached)
        sk.world = WORLD
        sk.metadata = dict(sk.metadata)
        sk.metadata["phantom"] = {"template": "default"}
        return _individual_bone_shapes(sk, params.get("bone_shape"))
    from bonecap.skeleton.opensim import read_osim

    path = Path(generic)
    if path.suffix.lower() != ".osim" or not path.is_file():
        raise InputError("--generic takes 'default' or an existing OpenSim .osim model", path)
    sk = read_osim(path)
    sk = _individual_bone_shapes(_vary_osim_skeleton(sk, params["skeleton"], stature), params.get("bone_shape"))
    preset_cfg = PRESETS.get(params.get("preset", "default"), {})
    # (a coarser grid loses the shafts' marrow to the opening: the tiny preset caps the big bodies' grids instead)
    return with_marrow(sk, max_voxels=2e6 if preset_cfg.get("bone_resolution", 1.0) == 1.0 else 1e6)


#: An OpenSim body's bone, by its name without the side suffix, for the embedded description's cortical
#: thicknesses (``cortical_thickness`` of the generic skeleton's description; a name not listed is looked up
#: as it is): the pelvis's hip bones, the foot's tarsals, the torso's vertebrae (its ribs, girdles and skull
#: have shells as thin), the hand's bones.
OSIM_CORTEX = {"pelvis": "hip", "talus": "tarsal", "calcn": "tarsal", "toes": "tarsal", "torso": "vertebra",
               "hand": "hand"}


def with_marrow(sk: Skeleton, *, voxel_mm: float = 1.5, max_voxels: float = 2e6) -> Skeleton:
    """Bones given as outer surfaces only (an OpenSim model's) get an endosteal surface: marrow inside a cortex.

    The phantom renders a bone without an inner mesh as solid cortex, dark in
    every slice: no bone rule finds that, and no person has it. Each bone's
    inside is sampled on a grid (``voxel_mm``, coarser for large bodies so that
    it holds at most ``max_voxels``), its depth below the surface measured
    (Euclidean distance transform), and the level at the cortical thickness
    meshed (:func:`bonecap.skeleton.shapes.field_to_mesh`, thin parts opened
    away, as the embedded skeleton's cancellous cores). The thickness is the
    embedded description's for that bone (:data:`OSIM_CORTEX`): a long bone's
    ``diaphysis`` over the middle 60 % of its length (along its principal
    axis), its ``metaphysis`` from there to 12 % from either end, its
    ``epiphysis`` over the last 12 %; another bone's ``shell`` (or ``table``).
    On a grid coarser than ~1.5 mm the opening takes the marrow of thin shafts
    (a radius's, a humerus's) with the slivers.

    Parameters
    ----------
    sk : Skeleton
        Bones with meshes in their own frames; those with an inner mesh are kept.
    voxel_mm, max_voxels : float
        The grid.

    Returns
    -------
    Skeleton
        A copy whose bones have ``inner_mesh`` where a marrow cavity of some
        volume remains (``metadata["marrow"]`` lists them).

    Raises
    ------
    ValueError
        If ``voxel_mm`` or ``max_voxels`` is not positive.
    """
    import dataclasses

    from scipy import ndimage

    from bonecap.phantom.render import voxelise_labels
    from bonecap.skeleton.generic import _cortical_summary, load_generic_description
    from bonecap.skeleton.shapes import Field, field_to_mesh

    if not (voxel_mm > 0 and max_voxels > 0):
        raise ValueError(f"voxel_mm and max_voxels must be positive, got {voxel_mm} and {max_voxels}")
    desc = load_generic_description()
    bones = dict(sk.bones)
    done = []
    for name, b in sk.bones.items():
        if b.mesh is None or b.inner_mesh is not None:
            continue
        base = name[:-2] if name[-2:] in ("_r", "_l") else name
        ct = _cortical_summary(desc, OSIM_CORTEX.get(base, base))
        if not ct:
            continue
        V = np.asarray(b.mesh.vertices, float)
        lo, hi = V.min(axis=0), V.max(axis=0)
        h = max(float(voxel_mm), float(np.cbrt(np.prod(hi - lo + 8.0) / max_voxels)))
        lo = lo - 3.0 * h
        shape = tuple(int(n) for n in np.ceil((hi + 3.0 * h - lo) / h) + 1)
        A = np.eye(4)
        A[:3, :3] *= h
        A[:3, 3] = lo
        inside = voxelise_labels([(b.mesh, 1)], A, shape, inplane_supersample=1, through_plane_samples=1) > 0
        if inside.sum() < 8:
            continue
        sd = (ndimage.distance_transform_edt(~inside) - ndimage.distance_transform_edt(inside)).astype(np.float32) * h
        if "diaphysis" in ct:
            # along the principal axis: s in [0, 1] from one end to the other
            u = np.linalg.svd(V - V.mean(axis=0), full_matrices=False)[2][0]
            # (each grid node's coordinate along u, summed from the three axes' parts: no coordinate grid)
            ax = [(lo[i] + h * np.arange(n)) * u[i] for i, n in enumerate(shape)]
            t_along = ax[0][:, None, None] + ax[1][None, :, None] + ax[2][None, None, :]
            s_lo, s_hi = float((V @ u).min()), float((V @ u).max())
            sfrac = np.clip((t_along - s_lo) / (s_hi - s_lo), 0.0, 1.0)
            end = np.minimum(sfrac, 1.0 - sfrac)
            thick = np.where(end < 0.12, ct.get("epiphysis", 1.0),
                             np.where(end < 0.2, ct.get("metaphysis", ct["diaphysis"]), ct["diaphysis"]))
            thick = thick.astype(np.float32)
        else:
            thick = float(next(v for v in ct.values() if isinstance(v, (int, float))))
        inner = field_to_mesh(Field(sd, lo, h), max(3000, len(b.mesh.faces)), offset=thick,
                              min_component_volume=8.0, opening=True)
        if inner is None:
            continue
        vi, fi = inner
        bones[name] = dataclasses.replace(b, inner_mesh=Mesh(np.asarray(vi, float), np.asarray(fi), b.mesh.frame))
        done.append(name)
    out = dataclasses.replace(sk, bones=bones, metadata=dict(sk.metadata))
    out.metadata["marrow"] = done
    return out


def _long_axis(sk: Skeleton, name: str) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """A bone's long axis in its own frame: (unit axis pointing proximally, proximal JC, distal JC)."""
    bone = sk.bones[name]
    prox = None
    if bone.parent is not None:
        keys = set(bone.joint_centres) & set(sk.bones[bone.parent].joint_centres)
        if keys:
            prox = bone.joint_centres[sorted(keys)[0]]
    dist = None
    children = [c for c, b in sk.bones.items() if b.parent == name]
    # the distal joint: the child joint farthest from the proximal one (the knee, not the patella); joints
    # about as far (both shoulders of a torso) are averaged
    cands = []
    for c in children:
        for k in set(sk.bones[c].joint_centres) & set(bone.joint_centres):
            p = bone.joint_centres[k]
            cands.append((float(np.linalg.norm(p - (prox if prox is not None else 0.0))), p))
    if cands:
        far = max(d for d, _ in cands)
        dist = np.mean([p for d, p in cands if d >= 0.8 * far], axis=0)
    if prox is not None and dist is not None and np.linalg.norm(prox - dist) > 20:
        return _unit(prox - dist), prox, dist
    if bone.mesh is not None and len(bone.mesh.vertices) > 3:
        v = bone.mesh.vertices - bone.mesh.vertices.mean(0)
        w, V = np.linalg.eigh(v.T @ v)
        ax = V[:, -1]
        if prox is not None:
            far = bone.mesh.vertices[np.argmax(np.linalg.norm(bone.mesh.vertices - prox, axis=1))]
            if np.dot(prox - far, ax) < 0:
                ax = -ax
        elif ax[1] < 0:
            ax = -ax
        return ax, prox, dist
    return np.array([0.0, 1.0, 0.0]), prox, dist


def _vary_osim_skeleton(sk: Skeleton, sp: dict[str, float], stature: float) -> Skeleton:
    """Scale an OpenSim skeleton to a stature and vary it per body, non-affinely.

    Each body ``b`` gets a point map ``phi_b`` in its own frame, applied to its
    mesh, landmarks and joint centres:

    - a global scale ``stature / model stature`` (the model's stature is its
      bone height plus 6 mm of scalp and 20 mm of heel pad);
    - a linear map ``w (I - u u^T) + s u u^T`` along the body's long axis ``u``
      (proximal to distal joint centre): ``s = length.<segment>_<side>``,
      ``w = width.<segment>``; the pelvis is scaled by ``pelvis_width`` along Z;
    - for the femur: a twist of the proximal femur about the shaft axis (smooth
      weight from 70 % to 88 % of the length) that sets the anteversion, and a
      rotation of the neck and head about the AP axis through the neck base
      that sets the neck-shaft angle (both relative to the template's assumed
      13 deg and 127 deg), then a shift that puts the femoral head back on the
      hip joint centre;
    - a bow ``bow.<bone>_mm * 16 s^2 (1 - s)^2`` (s from distal to proximal joint
      centre, zero slope at both ends) of the femur (anterior), tibia (lateral),
      humerus (anterior) and radius (lateral).

    The poses are rebuilt down the chain so that each child's joint centre,
    mapped by its own ``phi``, meets the parent's, mapped by the parent's
    (``child_in_parent`` keeps its rotation): lengths change per segment, so
    the skeleton as a whole is not an affine image of the template, and each
    femur, tibia, humerus and radius is not an affine image of the template
    bone either. The feet are put back on their original height.
    """
    roles = _bone_roles(sk)
    lo, hi = _skeleton_extent_y(sk)
    model_stature = (hi - lo) + 6.0 + 20.0
    g = stature / model_stature
    seg_of = {"femur": "thigh", "patella": None, "tibia": "shank", "talus": "foot", "calcn": "foot", "toes": "foot",
              "torso": "trunk", "humerus": "upper_arm", "ulna": "forearm", "radius": "forearm", "hand": "hand"}
    maps: dict[str, Callable[[np.ndarray], np.ndarray]] = {}
    applied: dict[str, Any] = {"global_scale": g, "model_stature_mm": model_stature}
    for name, bone in sk.bones.items():
        role = roles.get(name)
        base, side = (role.rsplit("_", 1) + [""])[:2] if role and role[-2:] in ("_r", "_l") else (role, "")
        u, prox, dist = _long_axis(sk, name)
        S = g * np.eye(3)
        seg = seg_of.get(base) if base else None
        if base == "pelvis":
            S = g * np.diag([1.0, 1.0, sp.get("pelvis_width", 1.0)])
        elif seg is not None:
            s = sp.get(f"length.{seg}_{side}" if side else f"length.{seg}_r", 1.0)
            if not side:
                s = 0.5 * (sp.get(f"length.{seg}_r", 1.0) + sp.get(f"length.{seg}_l", 1.0))
            w = sp.get(f"width.{seg}", 1.0)
            if base in ("talus", "calcn", "toes"):
                S = g * s * np.eye(3)          # the foot scales as a whole with its length
            else:
                S = g * (w * (np.eye(3) - np.outer(u, u)) + s * np.outer(u, u))
        nonlinear: list[Callable[[np.ndarray], np.ndarray]] = []
        sigma = 1.0 if side == "r" else -1.0
        Rw = bone.bone_to_world[:3, :3]
        anterior = Rw.T @ np.array([1.0, 0.0, 0.0])           # world directions in the bone frame
        lateral = Rw.T @ np.array([0.0, 0.0, sigma])
        if base in ("femur", "tibia", "humerus", "radius") and prox is not None and dist is not None:
            P, D = S @ prox, S @ dist
            L = float(np.linalg.norm(P - D))
            ax = (P - D) / L
            bow = sp.get(f"bow.{base}_mm", 0.0)
            ref = anterior if base in ("femur", "humerus") else lateral
            e = _unit(ref - ax * np.dot(ref, ax))
            if base == "femur" and bone.mesh is not None:
                nonlinear.append(_femur_torsion_map(
                    bone.mesh.vertices @ S.T, P, D, anterior,
                    sp.get("femoral_anteversion_deg", _OSIM_NOMINAL_ANTEVERSION) - _OSIM_NOMINAL_ANTEVERSION,
                    sp.get("neck_shaft_angle_deg", _OSIM_NOMINAL_NECK_SHAFT) - _OSIM_NOMINAL_NECK_SHAFT))

            def bow_map(p, D=D, ax=ax, L=L, e=e, bow=bow):
                s = np.clip((p - D) @ ax / L, 0.0, 1.0)
                return p + np.outer(bow * 16.0 * s**2 * (1 - s) ** 2, e)

            nonlinear.append(bow_map)

        def phi(p, S=S, nl=tuple(nonlinear)):
            q = np.asarray(p, dtype=float) @ S.T
            for f in nl:
                q = f(q)
            return q

        maps[name] = phi
    applied["maps"] = sorted(maps)
    out = _apply_bone_maps(sk, maps)
    # feet back on the ground
    lo2, _ = _skeleton_extent_y(out)
    shift = lo - lo2
    for b in out.bones.values():
        b.bone_to_world[1, 3] += shift
    out.world = WORLD
    out.metadata["phantom"] = {"template": str(sk.metadata.get("source", "")), **{k: v for k, v in applied.items()
                                                                              if k != "maps"}}
    return out


def _femur_torsion_map(verts: np.ndarray, hip: np.ndarray, knee: np.ndarray, anterior: np.ndarray,
                       d_anteversion_deg: float, d_nsa_deg: float) -> Callable[[np.ndarray], np.ndarray]:
    """The femur's change of anteversion and neck-shaft angle, as a point map in the (scaled) femur frame.

    ``verts`` (N, 3) are the scaled mesh vertices (to find the shaft axis),
    ``hip``/``knee`` the joint centres and ``anterior`` the anterior direction,
    all in the femur frame. The proximal femur (weight rising from 70 % to 88 %
    of the hip-knee length) twists about the shaft axis so that the head moves
    forward by ``d_anteversion_deg``; the neck and head (above 80 % and more than
    5 mm medial of the shaft) rotate about the AP axis through the neck base so
    that the head rises by ``d_nsa_deg``. The map is then shifted so that the
    head centre stays at ``hip``.
    """
    L = float(np.linalg.norm(hip - knee))
    ax = (hip - knee) / L
    s = (verts - knee) @ ax / L
    shaft = verts[(s > 0.25) & (s < 0.75)]
    if len(shaft) < 10:
        shaft = verts
    c = shaft.mean(0)
    _, V = np.linalg.eigh((shaft - c).T @ (shaft - c))
    d = V[:, -1] if np.dot(V[:, -1], ax) > 0 else -V[:, -1]
    q = c + d * np.dot(hip - c, d)          # neck base: the head centre projected on the shaft axis
    medial = hip - q
    medial = medial / max(np.linalg.norm(medial), 1e-9)
    ap = _unit(anterior - d * np.dot(anterior, d))
    # signs from the effect: a positive twist must move the head forward, a positive tilt upward
    eps = 1e-3
    sgn_t = 1.0 if np.dot(_rotate_points(hip[None], c, d, np.array([eps]))[0] - hip, ap) > 0 else -1.0
    sgn_n = 1.0 if np.dot(_rotate_points(hip[None], q, ap, np.array([eps]))[0] - hip, d) > 0 else -1.0
    beta = sgn_t * math.radians(d_anteversion_deg)
    gamma = sgn_n * math.radians(d_nsa_deg)

    def raw(p):
        s = (p - knee) @ ax / L
        out = _rotate_points(p, c, d, beta * _smoothstep((s - 0.70) / 0.18))
        med = (p - q) @ medial
        w = _smoothstep((s - 0.80) / 0.10) * _smoothstep((med - 5.0) / 15.0)
        return _rotate_points(out, q, ap, gamma * w)

    shift = raw(hip[None])[0] - hip

    def f(p):
        return raw(p) - shift

    return f


def _individual_bone_shapes(sk: Skeleton, spec: dict[str, Any] | None) -> Skeleton:
    """Give every bone longer than 60 mm a shape of its own: a smooth, non-affine random displacement.

    Per bone (in its own frame): 6 random plane waves of wavelength 0.5-1.2 x
    the bone's length ``L`` with random displacement directions across the
    bone's long axis, scaled to an
    RMS of ``noise_mm * L / 400`` over the mesh; their least-squares affine part
    is removed (so all of it is beyond any affine map) and the field is tapered
    to zero within 25-60 mm of each joint centre, so the articular surfaces
    stay where they were and the joints keep fitting. Meshes, endosteal
    meshes, landmarks and joint centres all move with it.
    """
    if not spec or not spec.get("noise_mm"):
        return sk
    rng = np.random.default_rng(int(spec.get("seed", 0)))
    maps: dict[str, Callable[[np.ndarray], np.ndarray]] = {}
    for name, bone in sk.bones.items():
        seed = int(rng.integers(0, 2**31 - 1))       # one draw per bone, whether it is deformed or not
        if bone.mesh is None or len(bone.mesh.vertices) < 20:
            continue
        V = bone.mesh.vertices
        c = V.mean(0)
        _, ev = np.linalg.eigh(np.cov((V - c).T))
        proj = (V - c) @ ev[:, -1]
        L = float(proj.max() - proj.min())
        if L < 60.0:
            continue
        r = np.random.default_rng(seed)
        k = np.array([_unit(r.normal(size=3)) * 2 * np.pi / (r.uniform(0.5, 1.2) * L) for _ in range(6)])
        # displacements across the long axis: along a shaft they move the surface (not slide along it)
        axis = ev[:, -1]
        amp = np.array([_unit(v - axis * np.dot(v, axis)) for v in r.normal(size=(6, 3))])
        phase = r.uniform(0, 2 * np.pi, 6)
        joints = np.array(list(bone.joint_centres.values())) if bone.joint_centres else np.zeros((0, 3))

        def raw(p, k=k, amp=amp, phase=phase):
            return np.cos(p @ k.T + phase) @ amp

        d = raw(V)
        Ah = np.hstack([V, np.ones((len(V), 1))])
        M, *_ = np.linalg.lstsq(Ah, d, rcond=None)
        rms = float(np.sqrt(((d - Ah @ M) ** 2).sum(1).mean()))
        scale = float(spec["noise_mm"]) * L / 400.0 / max(rms, 1e-9)

        def phi(p, raw=raw, M=M, scale=scale, joints=joints):
            p = np.asarray(p, dtype=float)
            disp = (raw(p) - np.hstack([p, np.ones((len(p), 1))]) @ M) * scale
            if len(joints):
                dmin = np.min(np.linalg.norm(p[:, None, :] - joints[None], axis=2), axis=1)
                disp *= _smoothstep((dmin - 25.0) / 35.0)[:, None]
            return p + disp

        maps[name] = phi
    out = _apply_bone_maps(sk, maps)
    out.metadata.setdefault("phantom", {})
    out.metadata["phantom"] = {**out.metadata["phantom"], "bone_shape": dict(spec)}
    return out


def _apply_bone_maps(sk: Skeleton, maps: dict[str, Callable[[np.ndarray], np.ndarray]]) -> Skeleton:
    """A new skeleton whose bones' own-frame geometry is mapped by ``maps`` and whose poses follow the joints."""
    from bonecap.model import Bone
    from bonecap.skeleton.kinematics import joint_groups

    # the joint each bone shares with its parent: the same name, or the parent's side-suffixed one (a hip
    # bone's ``sacroiliac`` is the sacrum's ``sacroiliac_r``, a rib's ``costovertebral5`` its vertebra's
    # ``costovertebral5_r``), as the warp groups joints; the same name first. Placed by its origin instead
    # (mid-ASIS, where neither bone's shape field is tapered to zero), a hip bone came off the sacrum by up
    # to 15 mm: seed 2's hip bones met neither the sacrum nor each other at the pubic symphysis.
    shared: dict[str, list[tuple[str, str]]] = {}
    for g in joint_groups(sk):
        for b1, k1 in g:
            shared.setdefault(b1, []).extend((k1, k2) for b2, k2 in g if sk.bones[b1].parent == b2)
    new: dict[str, Bone] = {}
    for name, bone in sk.bones.items():
        phi = maps.get(name, lambda p: np.asarray(p, dtype=float))

        def mp(m: Mesh | None) -> Mesh | None:
            return None if m is None else Mesh(phi(m.vertices), m.faces.copy(), m.frame)

        if bone.parent is None:
            T = bone.bone_to_world.copy()
        else:
            par = sk.bones[bone.parent]
            rel = np.linalg.solve(par.bone_to_world, bone.bone_to_world)
            pair = min(shared.get(name, []), key=lambda p: (p[0] != p[1], p[0]), default=None)
            if pair is not None:
                cp, cb = par.joint_centres[pair[1]], bone.joint_centres[pair[0]]
            else:
                cp, cb = rel[:3, 3], np.zeros(3)
            phi_p = maps.get(bone.parent, lambda p: np.asarray(p, dtype=float))
            cp2 = phi_p(cp[None])[0]
            cb2 = phi(cb[None])[0]
            rel2 = rel.copy()
            rel2[:3, 3] = cp2 - rel[:3, :3] @ cb2
            T = new[bone.parent].bone_to_world @ rel2
        jc = {k: phi(v[None])[0] for k, v in bone.joint_centres.items()}
        lm = {k: phi(v[None])[0] for k, v in bone.landmarks.items()}
        new[name] = Bone(name=name, parent=bone.parent, mesh=mp(bone.mesh), bone_to_world=T, joint_centres=jc,
                         joint_axes=dict(bone.joint_axes), landmarks=lm, inner_mesh=mp(bone.inner_mesh),
                         metadata=dict(bone.metadata))
    return Skeleton(bones=new, world=sk.world, metadata=dict(sk.metadata))


# --------------------------------------------------------------------------- #
# implicit shapes
# --------------------------------------------------------------------------- #
def _smin(a, b, k):
    """Polynomial smooth minimum (Quilez): ``min(a, b)`` rounded over a width ``k``."""
    if k <= 0:
        return np.minimum(a, b)
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def _interp(t, knots, values):
    return np.interp(t, knots, values)


class _Swept:
    """A swept (super-)ellipse: the solid of cross-sections along a straight axis.

    The local frame has columns ``(e1, e2, u)``: ``u`` along the axis from
    ``origin`` (t = 0) over ``length`` (t = 1), ``e1`` the direction of the
    semi-axis ``a`` (anterior for limbs and trunk, up for the foot), ``e2 = u x e1``.
    Profiles are piecewise linear in ``t`` (knots ``tk``): semi-axes ``a``, ``b``,
    centre offsets ``c1`` (along e1), ``c2`` (along e2), fat thickness on the
    +e1 side ``fat_pos`` and the -e1 side ``fat_neg``. The solid spans
    ``t_lo..t_hi`` with flat ends; its distance is the usual first-order bound
    ``(rho - 1) / |grad rho|`` of the super-ellipse norm ``rho`` (exact for a
    circle), combined with the axial distance like a box.
    """

    def __init__(self, name, origin, R, length, tk, a, b, c1, c2, fat_pos, fat_neg=None, n=2.0,
                 t_lo=0.0, t_hi=1.0):
        self.name = name
        self.origin = np.asarray(origin, dtype=float)
        self.R = np.asarray(R, dtype=float)
        self.length = float(length)
        self.tk = np.asarray(tk, dtype=float)
        self.a, self.b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
        self.c1, self.c2 = np.asarray(c1, dtype=float), np.asarray(c2, dtype=float)
        self.fat_pos = np.asarray(fat_pos, dtype=float)
        self.fat_neg = self.fat_pos if fat_neg is None else np.asarray(fat_neg, dtype=float)
        self.n = float(n)
        self.t_lo, self.t_hi = float(t_lo), float(t_hi)
        self._lut_cache = None

    def copy(self, **kw) -> "_Swept":
        new = _Swept.__new__(_Swept)
        new.__dict__.update(self.__dict__)
        new.__dict__.update(kw)
        new._lut_cache = None
        return new

    def transformed(self, M: np.ndarray) -> "_Swept":
        return self.copy(origin=M[:3, :3] @ self.origin + M[:3, 3], R=M[:3, :3] @ self.R)

    def _local(self, X, Y, Z):
        # float32 throughout on the grid: Python floats keep the arrays' precision
        o = [float(v) for v in self.origin]
        e1, e2, u = ([float(v) for v in self.R[:, i]] for i in range(3))
        dx, dy, dz = X - o[0], Y - o[1], Z - o[2]
        x1 = dx * e1[0] + dy * e1[1] + dz * e1[2]
        x2 = dx * e2[0] + dy * e2[1] + dz * e2[2]
        s = dx * u[0] + dy * u[1] + dz * u[2]
        return x1, x2, s

    def _profiles(self, t):
        return (_interp(t, self.tk, self.a), _interp(t, self.tk, self.b),
                _interp(t, self.tk, self.c1), _interp(t, self.tk, self.c2))

    _LUT_N = 1024

    def _lut(self):
        """Profiles tabulated on 1024 values of t over the knots (~1 mm apart): a lookup is
        much faster than ``np.interp`` on millions of grid points."""
        if getattr(self, "_lut_cache", None) is None:
            t = np.linspace(self.tk[0], self.tk[-1], self._LUT_N)
            cols = [_interp(t, self.tk, v) for v in (self.a, self.b, self.c1, self.c2, self.fat_pos, self.fat_neg)]
            self._lut_cache = (float(self.tk[0]), (self._LUT_N - 1) / max(float(self.tk[-1] - self.tk[0]), 1e-9),
                               np.stack(cols).astype(np.float32))
        return self._lut_cache

    def _lookup(self, s, rows):
        t0, inv, tab = self._lut()
        i = np.clip((s * np.float32(1.0 / self.length) - np.float32(t0)) * np.float32(inv) + np.float32(0.5),
                    0, self._LUT_N - 1).astype(np.int32)
        return [tab[r][i] for r in rows]

    def sdf(self, X, Y, Z) -> np.ndarray:
        x1, x2, s = self._local(X, Y, Z)
        shape = np.broadcast(x1, x2, s).shape
        x1, x2, s = (np.broadcast_to(v, shape) for v in (x1, x2, s))
        a, b, c1, c2 = self._lookup(s, (0, 1, 2, 3))
        px, pz = np.abs(x1 - c1) / a, np.abs(x2 - c2) / b
        n = self.n
        if n == 2.0:
            rho = np.sqrt(px * px + pz * pz)
            gx, gz = px / a, pz / b
            grad = np.sqrt(gx * gx + gz * gz) / np.maximum(rho, np.float32(1e-9))
        else:
            rho = (px**n + pz**n) ** (1.0 / n)
            r1n = np.maximum(rho, np.float32(1e-9)) ** (1.0 - n)
            gx, gz = r1n * px ** (n - 1) / a, r1n * pz ** (n - 1) / b
            grad = np.sqrt(gx * gx + gz * gz)
        dr = np.where(grad > 1e-9, (rho - 1.0) / np.maximum(grad, np.float32(1e-9)), -np.minimum(a, b))
        da = np.maximum(self.t_lo * self.length - s, s - self.t_hi * self.length)
        out = np.sqrt(np.maximum(dr, 0) ** 2 + np.maximum(da, 0) ** 2) + np.minimum(np.maximum(dr, da), 0)
        return out.astype(np.float32, copy=False)

    def fat(self, X, Y, Z) -> np.ndarray:
        x1, x2, s = self._local(X, Y, Z)
        shape = np.broadcast(x1, x2, s).shape
        x1, s = np.broadcast_to(x1, shape), np.broadcast_to(s, shape)
        s = np.clip(s, self.t_lo * self.length, self.t_hi * self.length)
        a, c1, fp, fn = self._lookup(s, (0, 2, 4, 5))
        w = _smoothstep(0.5 + 0.5 * (x1 - c1) / a)
        return (fn + (fp - fn) * w).astype(np.float32, copy=False)

    def surface_points(self, t0=None, t1=None, step=12.0, n_theta=36) -> np.ndarray:
        """Points on the lateral surface between ``t0`` and ``t1`` (world)."""
        t0 = self.t_lo if t0 is None else max(t0, self.t_lo)
        t1 = self.t_hi if t1 is None else min(t1, self.t_hi)
        if t1 <= t0:
            return np.zeros((0, 3))
        ts = np.linspace(t0, t1, max(2, int((t1 - t0) * self.length / step) + 1))
        th = np.linspace(0, 2 * np.pi, n_theta, endpoint=False)
        a, b, c1, c2 = self._profiles(ts)
        e = 2.0 / self.n
        cx = np.sign(np.cos(th)) * np.abs(np.cos(th)) ** e
        cz = np.sign(np.sin(th)) * np.abs(np.sin(th)) ** e
        x1 = c1[:, None] + a[:, None] * cx[None]
        x2 = c2[:, None] + b[:, None] * cz[None]
        s = np.broadcast_to(ts[:, None] * self.length, x1.shape)
        loc = np.stack([x1.ravel(), x2.ravel(), s.ravel()], axis=1)
        return loc @ self.R.T + self.origin

    def bbox(self) -> tuple[np.ndarray, np.ndarray]:
        ts = np.linspace(self.t_lo, self.t_hi, 60)
        a, b, c1, c2 = self._profiles(ts)
        pts = []
        for sa in (-1, 1):
            for sb in (-1, 1):
                loc = np.stack([c1 + sa * a, c2 + sb * b, ts * self.length], axis=1)
                pts.append(loc @ self.R.T + self.origin)
        pts = np.concatenate(pts)
        return pts.min(0), pts.max(0)


class _Ellipsoid:
    """An ellipsoid (Quilez's distance bound ``k0 (k0 - 1) / k1``) with a constant fat thickness."""

    def __init__(self, name, centre, R, radii, fat):
        self.name = name
        self.centre = np.asarray(centre, dtype=float)
        self.R = np.asarray(R, dtype=float)
        self.radii = np.asarray(radii, dtype=float)
        self.fat_mm = float(fat)

    def transformed(self, M):
        return _Ellipsoid(self.name, M[:3, :3] @ self.centre + M[:3, 3], M[:3, :3] @ self.R, self.radii, self.fat_mm)

    def sdf(self, X, Y, Z):
        c, R, r = [float(v) for v in self.centre], self.R.astype(float).tolist(), [float(v) for v in self.radii]
        d = [X - c[0], Y - c[1], Z - c[2]]
        q = [d[0] * R[0][i] + d[1] * R[1][i] + d[2] * R[2][i] for i in range(3)]
        k0 = np.sqrt(sum((q[i] / r[i]) ** 2 for i in range(3)))
        k1 = np.sqrt(sum((q[i] / r[i] ** 2) ** 2 for i in range(3)))
        out = np.where(k1 > 1e-12, k0 * (k0 - 1.0) / np.maximum(k1, 1e-12), -min(r))
        return np.asarray(out, dtype=np.float32)

    def fat(self, X, Y, Z):
        return np.full(np.broadcast(X, Y, Z).shape, self.fat_mm, dtype=np.float32)

    def surface_points(self, *args, n=400, **kw):
        i = np.arange(n) + 0.5
        phi = np.arccos(1 - 2 * i / n)
        th = np.pi * (1 + 5**0.5) * i
        u = np.stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)], axis=1)
        return (u * self.radii) @ self.R.T + self.centre

    def bbox(self):
        ext = np.sqrt(((self.R * self.radii[None, :]) ** 2).sum(axis=1))
        return self.centre - ext, self.centre + ext


def _eval_min(shapes, P: np.ndarray) -> np.ndarray:
    """Hard union distance of ``shapes`` at points ``P`` (N, 3)."""
    out = np.full(len(P), np.inf)
    for sh in shapes:
        out = np.minimum(out, sh.sdf(P[:, 0], P[:, 1], P[:, 2]))
    return out


# --------------------------------------------------------------------------- #
# bone samples
# --------------------------------------------------------------------------- #
#: Skin margin over each bone (mm): the distance at which the bone's dilation
#: joins the skin. Where the segment solids already cover the bone this does
#: not show; it matters where bone is subcutaneous: the skull (``scalp_mm``),
#: tibia (``shin_mm``), malleoli, olecranon, epicondyles, patella, clavicle,
#: fingers and toes. First match wins (fnmatch patterns on bone names).
_SKIN_MARGIN = [
    ("skull", "scalp"), ("mandible", 8.0), ("tibia_*", "shin"), ("fibula_*", 5.0), ("patella_*", 6.0),
    ("ulna_*", 5.0), ("radius_*", 5.0), ("humerus_*", 5.0), ("femur_*", 7.0),
    ("hand_*", 5.0), ("carpals_*", 5.0), ("ray*", 5.0), ("talus_*", 6.0), ("calcn_*", 8.0),
    ("calcaneus_*", 8.0), ("toes_*", 5.0), ("foot_*", 5.0), ("clavicle_*", 7.0), ("scapula_*", 10.0),
    ("sternum", 9.0), ("rib*", 12.0), ("c[1-7]", 12.0), ("t[1-9]", 10.0), ("t1[0-2]", 10.0),
    ("l[1-5]", 10.0), ("sacrum", 12.0), ("hip_*", 12.0), ("pelvis", 12.0), ("torso", 10.0),
]


@dataclass
class _Samples:
    """Dense samples of the bone surfaces, in each bone's own frame."""

    bone: np.ndarray            # (N,) index into names
    local: np.ndarray           # (N, 3) bone-frame points
    m_skin: np.ndarray          # (N,) skin margin, mm
    m_mus: np.ndarray           # (N,) fascia margin, mm
    names: list[str]
    part: np.ndarray            # (N,) connected component of the bone's mesh the sample is on (global id)

    def world(self, sk: Skeleton, mask=None) -> np.ndarray:
        """World positions at the skeleton's current pose (samples are stored bone by bone)."""
        out = np.empty_like(self.local)
        bounds = np.searchsorted(self.bone, np.arange(len(self.names) + 1))
        for i, n in enumerate(self.names):
            sl = slice(bounds[i], bounds[i + 1])
            T = sk.bones[n].bone_to_world
            out[sl] = self.local[sl] @ T[:3, :3].T + T[:3, 3]
        return out if mask is None else out[mask]

    def of(self, bones: list[str]) -> np.ndarray:
        idx = [self.names.index(b) for b in bones if b in self.names]
        return np.isin(self.bone, idx)


def _face_components(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Connected components of a mesh (faces sharing a vertex, duplicate vertices merged).

    Returns the face labels and the vertex labels.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    _, inv = np.unique(np.round(v, 4), axis=0, return_inverse=True)
    inv = inv.ravel()
    fv = inv[f]
    nv, nf = int(inv.max()) + 1, len(f)
    rows = np.repeat(np.arange(nf), 3)
    g = coo_matrix((np.ones(3 * nf), (rows, nf + fv.ravel())), shape=(nf + nv, nf + nv))
    _, lab = connected_components(g, directed=False)
    return lab[:nf], lab[nf + inv]


def _sample_bones(sk: Skeleton, spacing: float, scalp: float, shin: float, rng) -> _Samples:
    names, bone_idx, pts, msk, parts = [], [], [], [], []
    n_parts = 0
    for name, bone in sk.bones.items():
        if bone.mesh is None or len(bone.mesh.faces) == 0:
            continue
        v, f = bone.mesh.vertices, bone.mesh.faces
        tri = v[f]
        area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        n = int(area.sum() / spacing**2) + 1
        which = rng.choice(len(f), size=n, p=area / area.sum()) if area.sum() > 0 else np.zeros(0, int)
        r1, r2 = rng.random(n), rng.random(n)
        flip = r1 + r2 > 1
        r1[flip], r2[flip] = 1 - r1[flip], 1 - r2[flip]
        t = tri[which]
        p = t[:, 0] + r1[:, None] * (t[:, 1] - t[:, 0]) + r2[:, None] * (t[:, 2] - t[:, 0])
        p = np.concatenate([v, p])
        flab, vlab = _face_components(v, f)
        parts.append(n_parts + np.concatenate([vlab, flab[which]]))
        n_parts += int(max(flab.max(), vlab.max())) + 1
        margin = 10.0
        for pat, m in _SKIN_MARGIN:
            if fnmatch.fnmatchcase(name.lower(), pat):
                margin = scalp if m == "scalp" else shin if m == "shin" else float(m)
                break
        names.append(name)
        bone_idx.append(np.full(len(p), len(names) - 1))
        pts.append(p)
        msk.append(np.full(len(p), margin))
    m_skin = np.concatenate(msk)
    return _Samples(np.concatenate(bone_idx), np.concatenate(pts), m_skin, _mus_margin(m_skin), names,
                    np.concatenate(parts))


def _mus_margin(m_skin: np.ndarray) -> np.ndarray:
    # the fascia stays >= 2.5 mm off the bone but leaves >= _F_MIN + 1 mm of fat under the skin
    return np.clip(np.minimum(_M_MUS, m_skin - _F_MIN - 1.0), 2.0, None)


def _coarse_margins(smp: "_Samples", h: float) -> None:
    """On a coarse grid (tiny preset) widen the margins so that the meshes still enclose the bones.

    A distance offset sampled on an ``h`` grid and linearly interpolated by
    marching cubes is misplaced by up to ~h/2 near a thin bone; the fascia
    margin becomes max(2.5, 0.8 h) and the skin margin at least that plus
    the minimum fat (max(1.5, 0.4 h)) plus 1 mm.
    """
    m_mus = max(_M_MUS, 0.8 * h)
    if m_mus > _M_MUS:
        smp.m_skin[:] = np.maximum(smp.m_skin, m_mus + _f_min(h) + 1.0)
        smp.m_mus[:] = np.maximum(_mus_margin(smp.m_skin), m_mus)


def _f_min(h: float) -> float:
    """Minimum skin-to-fascia distance on an ``h`` grid (1.5 mm, more on a coarse grid)."""
    return max(_F_MIN, 0.4 * h)


# --------------------------------------------------------------------------- #
# body plan: the segment solids around a skeleton
# --------------------------------------------------------------------------- #
def _ellipse_ab(C: np.ndarray, aspect: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Semi-axes (a, b) with a = aspect * b of an ellipse of perimeter C (Ramanujan's approximation)."""
    r = np.asarray(aspect, dtype=float)
    b = np.asarray(C, dtype=float) / (np.pi * (3 * (r + 1) - np.sqrt((3 * r + 1) * (r + 3))))
    return r * b, b


def _frame(u, ref) -> np.ndarray:
    """Columns (e1, e2, u): e1 = ref made orthogonal to u, e2 = u x e1."""
    u = _unit(u)
    e1 = _unit(ref - u * np.dot(ref, u))
    return np.stack([e1, np.cross(u, e1), u], axis=1)


def _slab_stats(P: np.ndarray, origin, R, length, ts, half_width) -> dict[str, np.ndarray]:
    """Per station t: centroid and extents of points P (world) in the local (e1, e2) plane.

    Stations without points take the values of the nearest station that has some.
    """
    loc = (P - origin) @ R
    s = loc[:, 2] / length
    out = {k: np.full(len(ts), np.nan) for k in ("c1", "c2", "min1", "max1", "min2", "max2")}
    hw = half_width / length
    order = np.argsort(s)
    s_sorted = s[order]
    for i, t in enumerate(ts):
        i0, i1 = np.searchsorted(s_sorted, [t - hw, t + hw])
        if i1 - i0 < 3:
            continue
        q = loc[order[i0:i1]]
        out["c1"][i], out["c2"][i] = q[:, 0].mean(), q[:, 1].mean()
        out["min1"][i], out["max1"][i] = q[:, 0].min(), q[:, 0].max()
        out["min2"][i], out["max2"][i] = q[:, 1].min(), q[:, 1].max()
    ok = np.isfinite(out["c1"])
    if not ok.any():
        for k in out:
            out[k][:] = 0.0
        return out
    idx = np.where(ok)[0]
    nearest = idx[np.abs(np.arange(len(ts))[:, None] - idx[None, :]).argmin(axis=1)]
    for k in out:
        out[k] = out[k][nearest]
    return out


@dataclass
class _Plan:
    shapes: dict[str, Any]
    edges: list[tuple[str, str, float]]
    chains: dict[str, tuple[str, list[str], list[str], np.ndarray]]   # chain -> (root bone, shapes, bones, centre)
    joints: dict[str, np.ndarray]
    levels: dict[str, float]
    groups: dict[str, list[str]]


class _Dims:
    """The drawn body dimensions: muscle circumferences and fat thicknesses (mm)."""

    _GIRTH_KEY = {"chest": "chest", "waist": "waist", "buttock": "buttock", "thigh": "thigh", "calf": "calf",
                  "upper_arm": "upper_arm", "forearm": "forearm", "neck": "neck"}
    _FAT_OF = {"chest": ("chest", 1.0), "waist": ("abdomen", 1.0), "buttock": ("buttock", 1.0),
               "thigh": ("thigh", 1.0), "knee": ("thigh", 0.5), "calf": ("calf", 1.0), "ankle": ("calf", 0.5),
               "upper_arm": ("upper_arm", 1.0), "elbow": ("upper_arm", 0.6), "forearm": ("forearm", 1.0),
               "wrist": ("forearm", 0.6), "neck": ("neck", 1.0)}
    _LIMB_REGIONS = ("thigh", "calf", "upper_arm", "forearm", "hand", "foot")

    def __init__(self, body: dict[str, float], stature: float):
        self.p = body
        self.sx = float(body["sex_blend"])
        self.stature = stature

    def _blend(self, pair):
        return (1.0 - self.sx) * pair[0] + self.sx * pair[1]

    def fat(self, region: str) -> float:
        f = self._blend(_FAT_REF[region]) * self.p["fat_factor"]
        return f * (self.p["fat.limbs"] if region in self._LIMB_REGIONS else self.p["fat.trunk"])

    def circ(self, key: str, side: str = "") -> float:
        """Muscle (fascia) circumference at a girth site, scaled by stature and the drawn girth factor."""
        region, frac = self._FAT_OF[key]
        ref_fat = self._blend(_FAT_REF[region]) * frac
        C = (self._blend(_GIRTH[key]) - 2 * np.pi * ref_fat) * self.stature / self._blend(_STATURE_REF)
        factor = 1.0
        if key in self._GIRTH_KEY:
            k = f"girth.{key}_{side}" if side and f"girth.{key}_{side}" in self.p else f"girth.{key}"
            factor = self.p.get(k, 1.0)
        elif key == "knee":
            factor = self.p.get(f"girth.thigh_{side}", 1.0) ** 0.3
        elif key == "elbow":
            factor = self.p.get(f"girth.upper_arm_{side}", 1.0) ** 0.5
        return C * factor


def _joint_between(sk: Skeleton, A: list[str], B: list[str], PA: np.ndarray, PB: np.ndarray) -> np.ndarray:
    """The joint centre between bone groups A (proximal) and B (distal), world.

    The centre both bones list (the child's parent in A), else the midpoint of
    the closest pair of surface samples.
    """
    for b in B:
        par = sk.bones[b].parent
        if par in A:
            c = _shared_joint(sk, b, par)
            if c is not None:
                return c
    if len(PA) and len(PB):
        d, i = cKDTree(PA).query(PB)
        j = int(np.argmin(d))
        return 0.5 * (PB[j] + PA[i[j]])
    raise InputError("cannot locate a joint centre between " + ", ".join(A) + " and " + ", ".join(B))


def _plan_body(sk: Skeleton, smp: _Samples, params: dict[str, Any]) -> _Plan:
    """Build the segment solids around the skeleton (anatomical pose)."""
    roles = _bone_roles(sk)
    stature = float(params["stature_mm"])
    sc = stature / 1700.0
    bp = params["body"]
    dims = _Dims(bp, stature)
    W = smp.world(sk)

    def group(*wanted):
        return _bones_with_role(roles, *wanted)

    groups = {"pelvis": group("pelvis"), "torso": group("torso")}
    for s in "rl":
        groups[f"femur_{s}"] = group(f"femur_{s}")
        groups[f"patella_{s}"] = group(f"patella_{s}")
        groups[f"shank_{s}"] = group(f"tibia_{s}")
        groups[f"foot_{s}"] = group(f"talus_{s}", f"calcn_{s}", f"toes_{s}")
        groups[f"humerus_{s}"] = group(f"humerus_{s}")
        groups[f"forearm_{s}"] = group(f"ulna_{s}", f"radius_{s}")
        groups[f"hand_{s}"] = group(f"hand_{s}")
    for need in ("pelvis", "torso", "femur_r", "femur_l", "shank_r", "shank_l", "foot_r", "foot_l"):
        if not [b for b in groups[need] if b in smp.names]:
            raise InputError(f"the template has no bone with a mesh for the {need.replace('_', ' ')}: "
                             "cannot build a body around it")
    has_arms = all(groups[f"{g}_{s}"] and all(b in smp.names for b in groups[f"{g}_{s}"])
                   for g in ("humerus", "forearm", "hand") for s in "rl")

    def pts(g):
        return W[smp.of(groups[g])] if isinstance(g, str) else W[smp.of(g)]

    joints: dict[str, np.ndarray] = {}
    for s in "rl":
        fem = groups[f"femur_{s}"]
        hip = _shared_joint(sk, fem[0])
        joints[f"hip_{s}"] = hip if hip is not None else sk.bones[fem[0]].bone_to_world[:3, 3].copy()
        joints[f"knee_{s}"] = _joint_between(sk, fem, groups[f"shank_{s}"], pts(fem), pts(f"shank_{s}"))
        joints[f"ankle_{s}"] = _joint_between(sk, groups[f"shank_{s}"], groups[f"foot_{s}"], pts(f"shank_{s}"),
                                              pts(f"foot_{s}"))
        if has_arms:
            hum = groups[f"humerus_{s}"]
            sh = _shared_joint(sk, hum[0])
            joints[f"shoulder_{s}"] = sh if sh is not None else sk.bones[hum[0]].bone_to_world[:3, 3].copy()
            joints[f"elbow_{s}"] = _joint_between(sk, hum, groups[f"forearm_{s}"], pts(hum), pts(f"forearm_{s}"))
            joints[f"wrist_{s}"] = _joint_between(sk, groups[f"forearm_{s}"], groups[f"hand_{s}"],
                                                  pts(f"forearm_{s}"), pts(f"hand_{s}"))

    y_hip = 0.5 * (joints["hip_r"][1] + joints["hip_l"][1])
    if has_arms:
        y_sh = 0.5 * (joints["shoulder_r"][1] + joints["shoulder_l"][1])
    else:
        y_sh = y_hip + 0.30 * stature
    torso_pts = pts("torso")
    # The head: the generic skull (cranium) and mandible (jaw); in an OpenSim torso, the mesh parts that
    # reach above shoulder + 10 % stature, the jaw being those that stop 6 % short of the top.
    if "skull" in smp.names:
        cranium = smp.of(["skull"])
        jaw = smp.of(["mandible"])
    else:
        tmask = smp.of(groups["torso"])
        top = np.full(int(smp.part.max()) + 1, -np.inf)
        np.maximum.at(top, smp.part[tmask], W[tmask, 1])
        head_parts = np.flatnonzero(top > y_sh + 0.10 * stature)
        if len(head_parts) == 0:
            raise InputError("the template has no skull: cannot build a head")
        y_top = top[head_parts].max()
        jaw_parts = head_parts[top[head_parts] < y_top - 0.06 * stature]
        cranium = tmask & np.isin(smp.part, head_parts) & ~np.isin(smp.part, jaw_parts)
        jaw = tmask & np.isin(smp.part, jaw_parts)
        smp.m_skin[cranium] = float(bp["scalp_mm"])
        smp.m_skin[jaw] = 8.0
        smp.m_mus[:] = _mus_margin(smp.m_skin)
    head_pts = W[cranium]
    jaw_pts = W[jaw]
    if len(head_pts) < 10:
        raise InputError("the template has no skull: cannot build a head")
    head_lo, head_hi = head_pts.min(0), head_pts.max(0)
    if len(jaw_pts) > 10:
        head_lo = np.minimum(head_lo, jaw_pts.min(0))
    levels = {
        "hip": y_hip, "crotch": y_hip - 0.05 * stature, "waist": y_hip + 0.105 * stature,
        "chest": y_sh - 0.10 * stature, "shoulder": y_sh, "neck_base": y_sh + 0.03 * stature,
        "head_bottom": float(head_lo[1]), "head_top": float(head_hi[1]),
    }
    shapes: dict[str, Any] = {}
    edges: list[tuple[str, str, float]] = []
    chains: dict[str, tuple[str, list[str], list[str], np.ndarray]] = {}
    X, Y, Z = np.eye(3)

    def limb(name, p0, p1, ref, sigma, P, tk, C, aspect, off1, off2, fat, t_lo, t_hi, anchor=None):
        L = float(np.linalg.norm(p1 - p0))
        R = _frame(p1 - p0, ref)
        ts = np.linspace(t_lo, t_hi, max(8, int((t_hi - t_lo) * L / 20.0) + 1))
        st = _slab_stats(P, p0, R, L, ts, 12.0 * sc)
        Ct, at, ft = (_interp(ts, tk, v) for v in (C, aspect, fat))
        a, b = _ellipse_ab(Ct + 2 * np.pi * ft, at)
        c1 = ndimage.gaussian_filter1d(st["c1"], 1.0, mode="nearest") + _interp(ts, tk, off1) * sc
        c2 = ndimage.gaussian_filter1d(st["c2"], 1.0, mode="nearest") + sigma * _interp(ts, tk, off2) * sc
        if anchor is not None:       # the front of the ellipse at the bone's front + pad
            pad = _interp(ts, *anchor) * sc
            front = ndimage.gaussian_filter1d(st["max1"], 1.0, mode="nearest")
            c1 = front + pad - a
        return _Swept(name, p0, R, L, ts, a, b, c1, c2, ft, n=2.0, t_lo=t_lo, t_hi=t_hi)

    for s, sigma in (("r", 1.0), ("l", -1.0)):
        hip, knee, ankle = joints[f"hip_{s}"], joints[f"knee_{s}"], joints[f"ankle_{s}"]
        # ---- thigh: adductors make it reach medially of the femur, hamstrings posteriorly
        Ct, Ck = dims.circ("thigh", s), dims.circ("knee", s)
        ft = dims.fat("thigh")
        thigh_args = dict(
            tk=[-0.2, 0.15, 0.5, 0.8, 1.0, 1.1], C=[Ct, Ct, 0.86 * Ct, 0.70 * Ct, Ck, 0.95 * Ck],
            aspect=[0.9, 0.95, 1.0, 1.0, 0.9, 0.9], off1=[-8, -8, -6, -5, -3, -3], off2=[-25, -28, -20, -10, 0, 0],
            fat=[ft, ft, ft, 0.8 * ft, 0.5 * ft, 0.5 * ft])
        P = pts(groups[f"femur_{s}"] + groups[f"patella_{s}"])
        thigh = limb(f"thigh_{s}", hip, knee, X, sigma, P, t_lo=-0.2, t_hi=1.1, **thigh_args)
        shapes[f"thigh_top_{s}"] = thigh.copy(name=f"thigh_top_{s}", t_hi=0.35)
        shapes[f"thigh_{s}"] = thigh.copy(t_lo=0.2)
        # ---- shank: the calf behind the tibia, whose anterior border stays subcutaneous
        Cc, Ca = dims.circ("calf", s), dims.circ("ankle", s)
        fc = dims.fat("calf")
        shapes[f"shank_{s}"] = limb(
            f"shank_{s}", knee, ankle, X, sigma, pts(f"shank_{s}"),
            # the top tapers inside the thigh's end (no popliteal shelf)
            tk=[-0.08, 0.05, 0.3, 0.6, 0.85, 1.0, 1.06], C=[0.8 * Ck, Ck, Cc, 0.85 * Cc, max(0.62 * Cc, Ca), Ca, Ca],
            aspect=[0.85, 0.85, 1.05, 1.0, 0.9, 0.85, 0.85], off1=[0] * 7, off2=[0, 0, -3, -3, 0, 0, 0],
            fat=[0.5 * fc, 0.7 * fc, fc, fc, 0.7 * fc, 0.5 * fc, 0.5 * fc], t_lo=-0.08, t_hi=1.06,
            anchor=([-0.08, 0.05, 0.15, 0.3, 0.85, 1.0, 1.06], [10, 10, 3, -2, -2, 8, 8]))
        # ---- foot: heel pad and sole below the bones, thin dorsum above
        Pf = pts(f"foot_{s}")
        h2 = Pf[:, [0, 2]] - Pf[:, [0, 2]].mean(0)
        _, V = np.linalg.eigh(h2.T @ h2)
        d2 = V[:, -1] if V[0, -1] > 0 else -V[:, -1]
        d = np.array([d2[0], 0.0, d2[1]])
        proj = Pf @ d
        heel = Pf[np.argmin(proj)]
        Lf = float(proj.max() - proj.min())
        p0 = np.array([heel[0], Pf[:, 1].min(), heel[2]])
        Rf = _frame(d, Y)
        tsf = np.linspace(-8.0 * sc / Lf, 1.0 + 4.0 * sc / Lf, 24)
        st = _slab_stats(Pf, p0, Rf, Lf, tsf, 10.0 * sc)
        sole = _interp(tsf, [0, 0.3, 0.65, 0.9, 1.0], [16, 14, 10, 7, 6]) * sc
        lo1 = ndimage.minimum_filter1d(st["min1"], 3, mode="nearest") - sole
        hi1 = ndimage.gaussian_filter1d(ndimage.maximum_filter1d(st["max1"], 3, mode="nearest"), 1.0) + 6.0 * sc
        lo2 = ndimage.minimum_filter1d(st["min2"], 3, mode="nearest") - 7.0 * sc
        hi2 = ndimage.maximum_filter1d(st["max2"], 3, mode="nearest") + 7.0 * sc
        ff = dims.fat("foot")
        # rounded toes and heel: the section shrinks over the last 8 % at both ends
        taper = 1.0 - 0.35 * _smoothstep((tsf - 0.92) / 0.1) - 0.2 * _smoothstep((0.04 - tsf) / 0.06)
        shapes[f"foot_{s}"] = _Swept(f"foot_{s}", p0, Rf, Lf, tsf, 0.5 * (hi1 - lo1) * taper, 0.5 * (hi2 - lo2) * taper,
                                     0.5 * (hi1 + lo1), 0.5 * (hi2 + lo2), np.full(len(tsf), ff),
                                     t_lo=tsf[0], t_hi=tsf[-1])
        edges += [("trunk", f"thigh_top_{s}", 30 * sc), (f"thigh_top_{s}", f"thigh_{s}", 40 * sc),
                  (f"thigh_{s}", f"shank_{s}", 30 * sc), (f"shank_{s}", f"foot_{s}", 25 * sc)]
        leg_bones = _descendants(sk, groups[f"femur_{s}"][0])
        chains[f"leg_{s}"] = (groups[f"femur_{s}"][0], [f"thigh_top_{s}", f"thigh_{s}", f"shank_{s}", f"foot_{s}"],
                              leg_bones, hip)

        if not has_arms:
            continue
        sh, el, wr = joints[f"shoulder_{s}"], joints[f"elbow_{s}"], joints[f"wrist_{s}"]
        # ---- upper arm with the deltoid cap over the humeral head
        Cu, Ce = dims.circ("upper_arm", s), dims.circ("elbow", s)
        fu = dims.fat("upper_arm")
        ua_args = dict(
            tk=[-0.16, -0.03, 0.25, 0.5, 0.8, 1.0, 1.08],
            C=[0.6 * Cu, 1.12 * Cu, 1.05 * Cu, Cu, 0.92 * Cu, Ce, 0.95 * Ce],
            aspect=[1.0, 1.0, 1.1, 1.15, 1.0, 0.8, 0.8], off1=[0, 0, 2, 4, 0, -3, -3], off2=[4, 6, 0, -3, -3, 0, 0],
            fat=[fu, fu, fu, fu, fu, 0.6 * fu, 0.6 * fu])
        Ph = pts(f"humerus_{s}")
        upper = limb(f"upper_arm_{s}", sh, el, X, sigma, Ph, t_lo=-0.16, t_hi=1.08, **ua_args)
        shapes[f"shoulder_{s}"] = upper.copy(name=f"shoulder_{s}", t_hi=0.22)
        shapes[f"upper_arm_{s}"] = upper.copy(t_lo=0.1)
        # ---- forearm, flattened towards the wrist (palms forward: thin front to back)
        Cf, Cw = dims.circ("forearm", s), dims.circ("wrist", s)
        fa = dims.fat("forearm")
        shapes[f"forearm_{s}"] = limb(
            f"forearm_{s}", el, wr, X, sigma, pts(f"forearm_{s}"),
            tk=[-0.08, 0.2, 0.5, 0.8, 1.0, 1.05], C=[Ce, Cf, 0.85 * Cf, 0.7 * Cf, Cw, Cw],
            aspect=[0.85, 0.8, 0.75, 0.7, 0.62, 0.62], off1=[0, 5, 3, 0, 0, 0], off2=[0] * 6,
            fat=[0.6 * fu, fa, fa, fa, 0.6 * fa, 0.6 * fa], t_lo=-0.08, t_hi=1.05)
        # ---- palm; the fingers come from the bones' dilation
        Pk = pts(f"hand_{s}")
        tip = Pk[np.argmax(np.linalg.norm(Pk - wr, axis=1))]
        Lh = float(np.linalg.norm(tip - wr))
        Rh = _frame(tip - wr, X)
        tsh = np.linspace(-0.05, 0.55, 12)
        st = _slab_stats(Pk, wr, Rh, Lh, tsh, 8.0 * sc)
        half2 = 0.5 * (st["max2"] - st["min2"]) + 3.0 * sc
        shapes[f"hand_{s}"] = _Swept(f"hand_{s}", wr, Rh, Lh, tsh, _interp(tsh, [0, 0.3, 0.55], [16, 15, 11]) * sc,
                                     half2, st["c1"], 0.5 * (st["max2"] + st["min2"]),
                                     np.full(len(tsh), dims.fat("hand")), t_lo=-0.05, t_hi=0.55)
        edges += [("trunk", f"shoulder_{s}", 25 * sc), (f"shoulder_{s}", f"upper_arm_{s}", 40 * sc),
                  (f"upper_arm_{s}", f"forearm_{s}", 25 * sc), (f"forearm_{s}", f"hand_{s}", 15 * sc)]
        hum0 = groups[f"humerus_{s}"][0]
        chains[f"arm_{s}"] = (hum0, [f"shoulder_{s}", f"upper_arm_{s}", f"forearm_{s}", f"hand_{s}"],
                              _descendants(sk, hum0), sh)

    shapes["trunk"] = _trunk(sk, W, smp, groups, levels, joints, dims, stature, head_pts)
    # ---- neck: posterior side 12 mm + fat behind the cervical spinous processes
    y0, y_sb = levels["neck_base"], float(head_lo[1] + 0.3 * (head_hi[1] - head_lo[1]))
    Ln = max(y_sb - y0, 40.0 * sc)
    Pn = torso_pts[(torso_pts[:, 1] > y0 - 30 * sc) & (torso_pts[:, 1] < y_sb) & (np.abs(torso_pts[:, 2]) < 40 * sc)]
    p0 = np.array([0.0, y0, 0.0])
    Rn = _frame(Y, X)
    tsn = np.linspace(-0.4, 1.3, 12)
    st = _slab_stats(Pn if len(Pn) > 10 else head_pts, p0, Rn, Ln, tsn, 15.0 * sc)
    fn = dims.fat("neck")
    an, bn = _ellipse_ab(np.full(len(tsn), dims.circ("neck") + 2 * np.pi * fn), np.full(len(tsn), 1.0))
    back = ndimage.gaussian_filter1d(ndimage.minimum_filter1d(st["min1"], 3, mode="nearest"), 1.0)
    back_s = back - (12.0 * sc + fn)
    if len(jaw_pts) > 10:   # the throat rises to the chin: the front reaches 15 mm behind the chin at the top
        chin = float(jaw_pts[:, 0].max()) - 15.0 * sc
        y_menton = float(jaw_pts[:, 1].min())
        rise = _smoothstep((y0 + tsn * Ln - y0) / max(y_menton + 10.0 * sc - y0, 10.0))
        front = np.maximum(back_s + 2 * an, back_s + 2 * an + rise * (chin - back_s - 2 * an))
        an = 0.5 * (front - back_s)
    c1n = back_s + an
    shapes["neck"] = _Swept("neck", p0, Rn, Ln, tsn, an, bn, c1n, np.zeros(len(tsn)), np.full(len(tsn), fn),
                            t_lo=-0.4, t_hi=1.3)
    # ---- head: an ellipsoid filling the face; the skull's dilation makes the scalp
    shapes["head"] = _head_ellipsoid(head_pts, float(bp["scalp_mm"]), dims.fat("head"))
    edges += [("trunk", "neck", 30 * sc), ("neck", "head", 25 * sc)]
    if len(jaw_pts) > 10:   # the floor of the mouth between the mandible's branches
        j_lo, j_hi = jaw_pts.min(0), jaw_pts.max(0)
        shapes["jaw"] = _Ellipsoid("jaw", 0.5 * (j_lo + j_hi), np.eye(3), 0.5 * (j_hi - j_lo) * 0.85,
                                   dims.fat("head"))
        edges += [("head", "jaw", 15 * sc), ("neck", "jaw", 30 * sc)]
    return _Plan(shapes, edges, chains, joints, levels, groups)


def _head_ellipsoid(P: np.ndarray, scalp: float, fat: float) -> _Ellipsoid:
    """The ellipsoid that fills the face and the skull, inside the scalp over the vault.

    Starts from the cranium's bounding box (half extents) and shrinks it until,
    in every direction of the upper half (the vault), it stays at least 4 mm
    inside the skull's outer surface + scalp, so that the scalp over the vault
    is the skull's dilation (``scalp_mm``) while the face, whose bones are
    irregular, is filled.
    """
    lo, hi = P.min(0), P.max(0)
    c, r = 0.5 * (lo + hi), 0.5 * (hi - lo)
    d = P - c
    rad = np.linalg.norm(d, axis=1)
    u = d / np.maximum(rad, 1e-9)[:, None]
    n = 300
    i = np.arange(n) + 0.5
    phi, th = np.arccos(1 - 2 * i / n), np.pi * (1 + 5**0.5) * i
    dirs = np.stack([np.cos(th) * np.sin(phi), np.cos(phi), np.sin(th) * np.sin(phi)], axis=1)   # Y = up
    _, b = cKDTree(dirs).query(u)
    r_skull = np.full(n, np.nan)
    np.fmax.at(r_skull, b, rad)
    vault = (dirs[:, 1] > 0.0) & np.isfinite(r_skull)
    r_e = 1.0 / np.sqrt(((dirs / r) ** 2).sum(axis=1))
    lam = 1.0
    if vault.any():
        lam = float(np.clip(np.min((r_skull[vault] + scalp - 4.0) / r_e[vault]), 0.7, 1.0))
    return _Ellipsoid("head", c, np.eye(3), r * lam, fat)


def _trunk(sk, W, smp, groups, levels, joints, dims: _Dims, stature, head_pts) -> _Swept:
    """The trunk: a super-elliptic loft along Y from below the crotch to the neck base.

    Per 10 mm station, the larger of (a) the trunk bones' extent (pelvis, spine,
    ribs, scapulae, clavicles, proximal femora) plus muscle and fat thickness
    and (b) an anthropometric girth (buttock, waist, chest circumference with a
    depth/breadth ratio) placed in front of the back. The back always follows
    the bones (spinous processes, scapulae, sacrum + gluteal muscles).
    """
    sc = stature / 1700.0
    lv = levels
    y_lo, y_hi = lv["crotch"] - 15 * sc, lv["shoulder"] + 0.055 * stature
    ys = np.arange(y_lo, y_hi + 1e-6, 10.0)
    P = [W[smp.of(groups["pelvis"] + groups["torso"])]]
    for s in "rl":
        Pf = W[smp.of(groups[f"femur_{s}"])]
        P.append(Pf[Pf[:, 1] > lv["hip"] - 0.045 * stature])
    P = np.concatenate(P)
    P = P[P[:, 1] < lv["neck_base"] + 20 * sc]
    if len(head_pts):
        hmin = head_pts.min(0)[1]
        P = P[P[:, 1] < hmin - 5]
    zc = float(np.median(W[smp.of(groups["pelvis"])][:, 2]))
    front = np.full(len(ys), np.nan)
    back, half = front.copy(), front.copy()
    order = np.argsort(P[:, 1])
    py = P[order, 1]
    for i, y in enumerate(ys):
        i0, i1 = np.searchsorted(py, [y - 6, y + 6])
        if i1 - i0 < 3:
            continue
        q = P[order[i0:i1]]
        front[i], back[i], half[i] = q[:, 0].max(), q[:, 0].min(), np.abs(q[:, 2] - zc).max()
    ok = np.isfinite(front)
    if not ok.any():
        raise InputError("the template's trunk bones are empty")
    for arr in (front, back, half):
        arr[~ok] = np.interp(ys[~ok], ys[ok], arr[ok])
    front = ndimage.gaussian_filter1d(ndimage.maximum_filter1d(front, 5, mode="nearest"), 2.0, mode="nearest")
    half = ndimage.gaussian_filter1d(ndimage.maximum_filter1d(half, 5, mode="nearest"), 2.0, mode="nearest")
    back = ndimage.gaussian_filter1d(ndimage.minimum_filter1d(back, 5, mode="nearest"), 2.0, mode="nearest")
    ky = [lv["crotch"], lv["hip"], lv["hip"] + 0.06 * stature, lv["waist"], lv["chest"], lv["shoulder"],
          lv["neck_base"]]
    # muscle thickness over the bones; the drawn girth factors scale it by 1 + 3 (g - 1) (+-45 %)
    g = 1.0 + 3.0 * (_interp(ys, ky, [dims.p["girth.buttock"]] * 3 + [dims.p["girth.waist"]]
                             + [dims.p["girth.chest"]] * 3) - 1.0)
    t_lat = _interp(ys, ky, [25, 22, 14, 12, 12, 12, 12]) * sc * g
    t_front = _interp(ys, ky, [20, 20, 10, 10, 14, 12, 10]) * sc * g
    t_back = _interp(ys, ky, [40, 45, 25, 18, 14, 14, 14]) * sc * g
    fb, fa, fk, fc = (dims.fat(r) for r in ("buttock", "abdomen", "back", "chest"))
    f_front = _interp(ys, ky, [0.8 * fb, 0.8 * fa, fa, fa, fc, fc, 0.7 * fc])
    f_back = _interp(ys, ky, [fb, fb, fb, fk, fc, fc, 0.8 * fc])
    f_lat = 0.5 * (f_front + f_back)
    front_s = front + t_front + f_front
    back_s = back - t_back - f_back
    half_s = half + t_lat + f_lat
    # The abdomen has no bones but the lumbar spine: there the waist circumference (ANSUR II) sets
    # breadth and depth (depth/breadth 0.72), fading out towards the iliac crests and the ribs. The
    # perimeter is taken x 0.93 because a real waist section is a rounded rectangle, whose extents are
    # smaller than those of the ellipse of the same perimeter. Elsewhere the bones plus tissue are the
    # shape, for the same reason (a chest or hip circumference as an ellipse comes out too wide).
    Cw = 0.93 * (dims.circ("waist") + 2 * np.pi * 0.5 * (fa + fk))
    a_w, b_w = _ellipse_ab(np.array([Cw]), np.array([0.72]))
    wgt = _interp(ys, [lv["hip"] + 0.02 * stature, lv["waist"] - 0.02 * stature, lv["waist"] + 0.02 * stature,
                       lv["chest"]], [0.0, 1.0, 1.0, 0.0])
    wgt = _smoothstep(wgt)
    front_s = np.maximum(front_s, back_s + wgt * 2 * a_w[0])
    half_s = np.maximum(half_s, wgt * b_w[0])
    front_s = ndimage.gaussian_filter1d(front_s, 1.5, mode="nearest")
    half_s = ndimage.gaussian_filter1d(half_s, 1.5, mode="nearest")
    # the trapezius: from just above the shoulder joints the trunk narrows to the neck along a concave slope
    # (the acromia stick out of it: the deltoid caps and the bones' dilation cover them)
    rn = (dims.circ("neck") + 2 * np.pi * dims.fat("neck")) / (2 * np.pi)
    y_s2 = lv["shoulder"] + 0.02 * stature
    i2 = int(np.searchsorted(ys, y_s2))
    if i2 < len(ys):
        uu = np.clip((ys - ys[i2]) / max(y_hi - ys[i2], 1.0), 0.0, 1.0)
        w = 1.0 - uu**1.5
        half_s = np.where(ys >= ys[i2], 1.05 * rn + (half_s[i2] - 1.05 * rn) * w, half_s)
        depth2 = front_s[i2] - back_s[i2]
        front_s = np.where(ys >= ys[i2], back_s + 2 * rn + (depth2 - 2 * rn) * w, front_s)
    # round the bottom off
    r = np.clip((ys - y_lo) / (60.0 * sc), 0.0, 1.0)
    shrink = np.sqrt(1.0 - (1.0 - r) ** 2) * 0.6 + 0.4
    xc = 0.5 * (front_s + back_s)
    a = 0.5 * (front_s - back_s) * shrink
    b = half_s * shrink
    origin = np.array([0.0, y_lo, zc])
    R = _frame(np.array([0.0, 1.0, 0.0]), np.array([1.0, 0.0, 0.0]))
    L = float(y_hi - y_lo)
    ts = (ys - y_lo) / L
    return _Swept("trunk", origin, R, L, ts, a, b, xc, np.zeros(len(ts)), f_front, f_back, n=2.3,
                  t_lo=0.0, t_hi=1.0)


# --------------------------------------------------------------------------- #
# the MRI pose: abduct arms and legs until their skin clears
# --------------------------------------------------------------------------- #
def _abduction(centre: np.ndarray, angle_rad: float) -> np.ndarray:
    """4x4 rotation about the world X axis through ``centre``."""
    M = np.eye(4)
    M[:3, :3] = _rot([1.0, 0.0, 0.0], angle_rad)
    M[:3, 3] = centre - M[:3, :3] @ centre
    return M


def _apply(M, P):
    return P @ M[:3, :3].T + M[:3, 3]


def _smallest_angle(gap_fn, target: float, max_deg: float) -> tuple[float, float]:
    """Smallest angle (0.5 deg steps, up to ``max_deg``) whose gap reaches ``target``: 2 deg steps, then back."""
    angle, gap = 0.0, gap_fn(0.0)
    while gap < target and angle < max_deg:
        angle = min(angle + 2.0, max_deg)
        gap = gap_fn(angle)
    if angle > 0 and gap >= target:
        for a in (angle - 1.5, angle - 1.0, angle - 0.5):
            if a > 0:
                g = gap_fn(a)
                if g >= target:
                    return a, g
    return angle, gap


def _gap(shapes_a, pts_a, m_a, shapes_b, pts_b, m_b, surf_a, surf_b, tree_b=None) -> float:
    """Smallest skin-to-skin distance between two groups (analytic surfaces and bone dilations)."""
    g = np.inf
    if len(surf_a):
        g = min(g, _eval_min(shapes_b, surf_a).min())
    if len(surf_b):
        g = min(g, _eval_min(shapes_a, surf_b).min())
    if len(pts_a):
        g = min(g, (_eval_min(shapes_b, pts_a) - m_a).min())
    if len(pts_b):
        g = min(g, (_eval_min(shapes_a, pts_b) - m_b).min())
    if len(pts_a) and len(pts_b):
        d, i = (tree_b if tree_b is not None else cKDTree(pts_b)).query(pts_a)
        g = min(g, (d - m_a - m_b[i]).min())
    return float(g)


def _solve_pose(sk: Skeleton, smp: _Samples, plan: _Plan, params, margin_extra: float,
                rng) -> dict[str, Any]:
    """Abduct legs (both by the same angle) and then each arm by the smallest angle that clears the gap.

    The legs must clear each other below the crotch (from 25 mm below it down),
    each arm must clear the trunk and legs from 42 % of the humerus down (above, the arm may
    touch the chest wall: that is the axilla; the margin keeps the mid-humerus level clear). Angles go up in
    0.5 deg steps to 25 deg (legs) / 30 deg (arms). Modifies ``sk`` and ``plan``
    in place and returns the angles (deg) and gaps (mm).
    """
    bp = params["body"]
    W = smp.world(sk)
    shapes = plan.shapes
    out: dict[str, Any] = {}

    def sub(mask, n=1500):
        idx = np.flatnonzero(mask)
        if len(idx) > n:
            idx = np.sort(rng.choice(idx, n, replace=False))
        return idx

    # ---- legs
    y_c = plan.levels["crotch"] - 25.0
    leg = {}
    for s in "rl":
        root, names, bones, centre = plan.chains[f"leg_{s}"]
        t_c = float((centre[1] - y_c) / max(shapes[f"thigh_{s}"].length, 1.0))
        surf = np.concatenate([shapes[f"thigh_top_{s}"].surface_points(t_c, None),
                               shapes[f"thigh_{s}"].surface_points(t_c, None),
                               shapes[f"shank_{s}"].surface_points()])
        idx = sub(smp.of(bones) & (W[:, 1] < y_c))
        leg[s] = (names, centre, surf, W[idx], smp.m_skin[idx])
    target = bp["leg_gap_mm"] + margin_extra

    def leg_gap(phi_deg):
        Ms = {s: _abduction(leg[s][1], math.radians(phi_deg) * (-1.0 if s == "r" else 1.0)) for s in "rl"}
        sh = {s: [shapes[n].transformed(Ms[s]) for n in leg[s][0][1:3]] for s in "rl"}
        return _gap(sh["r"], _apply(Ms["r"], leg["r"][3]), leg["r"][4], sh["l"], _apply(Ms["l"], leg["l"][3]),
                    leg["l"][4], _apply(Ms["r"], leg["r"][2]), _apply(Ms["l"], leg["l"][2]))

    phi_deg, gap = _smallest_angle(leg_gap, target, 25.0)
    out["leg_abduction_deg"] = phi_deg
    out["leg_gap_mm"] = gap - margin_extra
    for s in "rl":
        _pose_chain(sk, plan, f"leg_{s}", _abduction(leg[s][1], math.radians(phi_deg) * (-1.0 if s == "r" else 1.0)))
    # ---- arms
    if "arm_r" not in plan.chains:
        return out
    W = smp.world(sk)
    rest_names = ["trunk"] + [f"{p}_{s}" for p in ("thigh_top", "thigh", "shank") for s in "rl"]
    rest = [shapes[n] for n in rest_names]
    arm_bones = set(plan.chains["arm_r"][2]) | set(plan.chains["arm_l"][2])
    rest_bones = [b for b in smp.names if b not in arm_bones]
    ridx = sub(smp.of(rest_bones) & (W[:, 1] < plan.levels["shoulder"] - 0.05 * float(params["stature_mm"])),
               4000)
    rest_pts, rest_m = W[ridx], smp.m_skin[ridx]
    rest_tree = cKDTree(rest_pts)
    target = bp["arm_gap_mm"] + margin_extra
    for s in "rl":
        root, names, bones, centre = plan.chains[f"arm_{s}"]
        el = plan.joints[f"elbow_{s}"]
        y_mid = 0.5 * (centre[1] + el[1])
        surf = np.concatenate([shapes[f"upper_arm_{s}"].surface_points(0.42, None),
                               shapes[f"forearm_{s}"].surface_points(), shapes[f"hand_{s}"].surface_points()])
        idx = sub(smp.of(bones) & (W[:, 1] < y_mid + 0.08 * (centre[1] - el[1])))
        low_arm = shapes[f"upper_arm_{s}"].copy(t_lo=0.42)

        def arm_gap(theta, centre=centre, names=names, idx=idx, low_arm=low_arm, surf=surf, s=s):
            M = _abduction(centre, math.radians(theta) * (-1.0 if s == "r" else 1.0))
            arm = [shapes[n].transformed(M) for n in names[2:]] + [low_arm.transformed(M)]
            return _gap(arm, _apply(M, W[idx]), smp.m_skin[idx], rest, rest_pts, rest_m, _apply(M, surf),
                        np.zeros((0, 3)), tree_b=rest_tree)

        theta, gap = _smallest_angle(arm_gap, target, 30.0)
        out[f"arm_abduction_deg_{s}"] = theta
        out[f"arm_gap_mm_{s}"] = gap - margin_extra
        _pose_chain(sk, plan, f"arm_{s}", _abduction(centre, math.radians(theta) * (-1.0 if s == "r" else 1.0)))
    return out


def _pose_chain(sk: Skeleton, plan: _Plan, chain: str, M: np.ndarray) -> None:
    root, names, bones, centre = plan.chains[chain]
    for b in bones:
        sk.bones[b].bone_to_world = M @ sk.bones[b].bone_to_world
    for n in names:
        plan.shapes[n] = plan.shapes[n].transformed(M)
    for k in list(plan.joints):
        side = chain[-1]
        if (chain.startswith("leg") and k in (f"knee_{side}", f"ankle_{side}")) or \
                (chain.startswith("arm") and k in (f"elbow_{side}", f"wrist_{side}")):
            plan.joints[k] = _apply(M, plan.joints[k][None])[0]


# --------------------------------------------------------------------------- #
# voxel fields and meshes
# --------------------------------------------------------------------------- #
def _noise_field(P: np.ndarray, seed: int, wavelengths=(80.0, 250.0), n_waves=10) -> np.ndarray:
    """A smooth random field of unit RMS at points P: a sum of random plane waves."""
    rng = np.random.default_rng(seed)
    out = np.zeros(len(P), dtype=np.float32)
    P = np.asarray(P, dtype=np.float32)
    for _ in range(n_waves):
        d = _unit(rng.normal(size=3))
        k = (d * 2 * np.pi / rng.uniform(*wavelengths)).astype(np.float32)
        out += np.cos(P @ k + np.float32(rng.uniform(0, 2 * np.pi)))
    return out * np.float32(math.sqrt(2.0 / n_waves))


class _Grid:
    """A regular grid ``origin + h (i, j, k)``; ``noise`` evaluates smooth random fields at voxel indices
    from a coarse lattice (4 voxels apart) by trilinear interpolation."""

    def __init__(self, origin, h, shape):
        self.origin, self.h, self.shape = np.asarray(origin, dtype=float), float(h), tuple(shape)
        self.axes = [(self.origin[i] + self.h * np.arange(self.shape[i])).astype(np.float32) for i in range(3)]
        self._coarse: dict[tuple, np.ndarray] = {}

    def points(self, flat_idx: np.ndarray) -> np.ndarray:
        ijk = np.unravel_index(flat_idx, self.shape)
        return np.stack([self.axes[i][ijk[i]] for i in range(3)], axis=1)

    def noise(self, flat_idx: np.ndarray, seed: int, wavelengths) -> np.ndarray:
        step = 4
        key = (int(seed), tuple(wavelengths))
        coarse = self._coarse.get(key)
        if coarse is None:                   # the lattice once per field: the body is filled in slabs
            cshape = tuple(n // step + 2 for n in self.shape)
            ci = [np.arange(n) * step for n in cshape]
            P = np.stack(np.meshgrid(*[self.origin[i] + self.h * ci[i] for i in range(3)], indexing="ij"), axis=-1)
            coarse = self._coarse[key] = _noise_field(P.reshape(-1, 3), seed, wavelengths).reshape(cshape)
        out = np.empty(len(flat_idx), dtype=np.float32)
        # a quarter million voxels at a time: the indices, coordinates and values of a million were
        # ~60 MB, the main process's peak at the default preset (seed 4: 312 MiB)
        chunk = 250_000
        for i0 in range(0, len(flat_idx), chunk):
            ijk = np.unravel_index(flat_idx[i0:i0 + chunk], self.shape)
            coords = np.stack([ijk[i] / step for i in range(3)])
            del ijk
            out[i0:i0 + chunk] = ndimage.map_coordinates(coarse, coords, order=1, mode="nearest")
        return out


def memory_tidier(preset: str):
    """:func:`release_memory` where the preset is lean (``PRESETS[preset]["lean"]``), else a no-op."""
    return release_memory if PRESETS[preset].get("lean", True) else (lambda: None)


def release_memory() -> None:
    """Hand freed heap memory back to the system (glibc only; elsewhere a no-op).

    The phantom allocates and frees grids of tens of MB stage after stage; glibc
    serves large blocks from the heap once its dynamic mmap threshold has grown,
    and the freed space then stays in the process. Fixing the threshold at 4 MB
    (every grid-sized array its own mapping, returned on free; smaller ones stay
    on the heap, which avoids the page-fault cost of mapping every slab) and
    trimming the heap between stages keeps the resident memory nearer to what is
    alive. A full garbage collection first: the stages leave reference cycles
    holding ~130 MB at the default preset until the cyclic collector's rare
    generation-2 pass gets to them (measured 2026-11-25: 320 -> 189 MB resident
    after :func:`make_subject`; which objects form the cycles was not traced).
    """
    gc.collect()
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-3, 4 * 1024 * 1024)          # M_MMAP_THRESHOLD (also disables its dynamic growth)
        libc.malloc_trim(0)
    except (OSError, AttributeError):         # not glibc
        pass


def _label(mask: np.ndarray) -> tuple[np.ndarray, int]:
    """Connected components of a boolean grid, as uint16 labels when they fit (half the memory of int32)."""
    try:
        return ndimage.label(mask, output=np.uint16)
    except RuntimeError:                      # more than 65535 components
        return ndimage.label(mask, output=np.int32)


def _fill_cavities(field: np.ndarray, value: float) -> None:
    """Make ``field`` a single solid without holes.

    Outside regions not connected to the grid border (cavities) are set to
    ``value`` (< 0), and inside components other than the largest (specks) to
    ``-value``.
    """
    lab, n = _label(field >= 0)
    if n > 1:
        border = np.unique(np.concatenate([lab[0].ravel(), lab[-1].ravel(), lab[:, 0].ravel(), lab[:, -1].ravel(),
                                           lab[:, :, 0].ravel(), lab[:, :, -1].ravel()]))
        keep = np.zeros(n + 1, dtype=bool)
        keep[border] = True
        keep[0] = True
        for i in range(len(lab)):             # per plane: no whole-grid boolean temporaries
            field[i][~keep[lab[i]]] = value
    del lab
    lab, n = _label(field < 0)
    if n > 1:
        sizes = np.zeros(n + 1, dtype=np.int64)
        for part in lab:                      # per plane: bincount's int64 copy of the grid would be 8x its size
            sizes += np.bincount(part.ravel(), minlength=n + 1)
        sizes[0] = 0
        drop = np.ones(n + 1, dtype=bool)
        drop[[0, int(np.argmax(sizes))]] = False
        for i in range(len(lab)):
            field[i][drop[lab[i]]] = -value


#: Voxels per slab of the body grid (~2 MB per float32 array of a slab; a slab holds ~15 such arrays
#: and the distances of every segment crossing it: 1 000 000 was the main process's peak at seed 4).
_SLAB_VOXELS = 500_000
#: Voxels per slab of the marching cubes (:func:`_marching_cubes_slabs`). Not tied to
#: :data:`_SLAB_VOXELS`: the slabs set the order of the surface's vertices, which the
#: decimation depends on, so changing them changes the phantom.
_MC_SLAB_VOXELS = 1_500_000


def _y_slabs(shape: tuple[int, int, int], voxels: int | None = None) -> list[tuple[int, int]]:
    """Ranges ``[j0, j1)`` along the grid's long (Y, superior) axis, ``voxels`` (:data:`_SLAB_VOXELS`) each."""
    dy = max(4, (voxels or _SLAB_VOXELS) // max(shape[0] * shape[2], 1))
    return [(j0, min(j0 + dy, shape[1])) for j0 in range(0, shape[1], dy)]


def _fields(W: np.ndarray, m_skin: np.ndarray, m_mus: np.ndarray, plan: _Plan, params, h: float,
            timings: dict) -> tuple:
    """The skin field and the fat thickness on a regular grid (``field[i, j, k]`` at
    ``origin + h (i, j, k)``), model frame, with the bone term of the fascia at its candidate voxels:
    ``(S, Fat, origin, cand, bm)``, the last two the candidates' flat grid indices and their bone
    distance minus the fascia margin. :func:`_layers` makes the skin and fascia fields of them.

    ``W``: the bone samples in the model frame at the MRI pose (``_Samples.world``),
    ``m_skin`` / ``m_mus``: their skin and fascia margins (mm).

    Memory: the grid is filled in slabs along Y (:func:`_y_slabs`): segment
    distances, fat thickness, skin relief and the distance to the bones are
    computed per slab in float32 and only the two results are kept for the
    whole grid, as float16 (~18 M voxels for a whole body with abducted arms at
    3.5 mm: 36 MB each; float16 keeps 1/1000 of the value, < 0.01 mm near the
    surfaces). The result is the same as filling the whole grid at once. The
    bone samples are not needed after this: :func:`make_subject` frees them
    before :func:`_layers` labels the grid.
    """
    t0 = time.perf_counter()
    bp = params["body"]
    lo = W.min(0) - 40.0
    hi = W.max(0) + 40.0
    for sh in plan.shapes.values():
        a, b = sh.bbox()
        lo, hi = np.minimum(lo, a - 10.0), np.maximum(hi, b + 10.0)
    origin = np.floor(lo / h) * h
    shape = tuple(int(v) for v in np.ceil((hi - origin) / h).astype(int) + 1)
    grid = _Grid(origin, h, shape)
    axes = grid.axes
    BIG = np.float32(1e4)
    S = np.empty(shape, dtype=np.float16)      # the skin field
    Fat = np.empty(shape, dtype=np.float16)    # fat thickness, then the fascia field in place
    kmax = max(k for _, _, k in plan.edges)
    tau = np.float32(12.0)
    amp = float(bp["skin_noise_mm"])
    # bone proximity: occupied voxels, dilated by the largest margin per slab (with a halo)
    R = float(m_skin.max()) + 4.0
    r = int(math.ceil(R / h))
    # the samples' voxels, sorted along Y: each slab marks its own (with the halo) instead of one
    # whole-grid occupancy array (18 M voxels, 18 MB at the default preset, on the peak)
    ijk = np.round((W - origin) / h).astype(np.int64)
    ijk = ijk[np.argsort(ijk[:, 1], kind="stable")].astype(np.int32)
    tree = cKDTree(W)
    boxes = {}
    for name, sh in plan.shapes.items():
        a, b = sh.bbox()
        i0 = np.clip(np.floor((a - kmax - 5.0 - origin) / h).astype(int), 0, np.array(shape) - 1)
        i1 = np.clip(np.ceil((b + kmax + 5.0 - origin) / h).astype(int) + 1, 1, np.array(shape))
        boxes[name] = (i0, i1)
    cand_all, bm_all = [], []
    n_cand = 0
    t_seg = t_bone = 0.0
    for y0, y1 in _y_slabs(shape):
        ts = time.perf_counter()
        sshape = (shape[0], y1 - y0, shape[2])
        A = np.full(sshape, BIG, dtype=np.float32)
        num = np.zeros(sshape, dtype=np.float32)
        den = np.zeros(sshape, dtype=np.float32)
        blocks: dict[str, tuple[tuple[slice, ...], np.ndarray]] = {}
        for name, sh in plan.shapes.items():
            i0, i1 = boxes[name]
            j0, j1 = max(i0[1], y0), min(i1[1], y1)
            if j0 >= j1:
                continue
            sl = (slice(i0[0], i1[0]), slice(j0 - y0, j1 - y0), slice(i0[2], i1[2]))   # slab-local
            Yb = axes[1][j0:j1][None, :, None]
            Zb = axes[2][sl[2]][None, None, :]
            d = np.empty(tuple(x.stop - x.start for x in sl), dtype=np.float32)
            # ~15 float32 temporaries per point in sdf/fat: 150 000 points keep them near 9 MB
            step = max(1, 150_000 // max(d.shape[1] * d.shape[2], 1))
            for x0 in range(0, d.shape[0], step):    # the distance's temporaries stay small
                Xb = axes[0][sl[0]][x0:x0 + step, None, None]
                dj = sh.sdf(Xb, Yb, Zb)
                d[x0:x0 + step] = dj
                # fat thickness: a soft-min weighted mean over the segments (smooth across the joins)
                w = np.exp(-np.clip(dj, -60.0, 400.0) / tau)
                sub = (slice(sl[0].start + x0, sl[0].start + x0 + dj.shape[0]), sl[1], sl[2])
                num[sub] += w * sh.fat(Xb, Yb, Zb)
                den[sub] += w
            np.minimum(A[sl], d, out=A[sl])
            blocks[name] = (sl, d)
        for na, nb, k in plan.edges:
            if na not in blocks or nb not in blocks:
                continue
            (sa, da), (sb, db) = blocks[na], blocks[nb]
            lo_i = [max(sa[i].start, sb[i].start) for i in range(3)]
            hi_i = [min(sa[i].stop, sb[i].stop) for i in range(3)]
            if any(l >= u for l, u in zip(lo_i, hi_i)):
                continue
            box = tuple(slice(lo_i[i], hi_i[i]) for i in range(3))
            va = da[tuple(slice(lo_i[i] - sa[i].start, hi_i[i] - sa[i].start) for i in range(3))]
            vb = db[tuple(slice(lo_i[i] - sb[i].start, hi_i[i] - sb[i].start) for i in range(3))]
            np.minimum(A[box], _smin(va, vb, np.float32(k)), out=A[box])
        del blocks
        f = num                                   # in place
        np.divide(num, den, out=f, where=den > 1e-20)
        f[den <= 1e-20] = 8.0
        del den
        t_seg += time.perf_counter() - ts
        ts = time.perf_counter()
        base = y0 * shape[2]                      # slab-local flat index -> grid flat index

        def to_grid(flat):
            i, rest = np.divmod(flat, sshape[1] * sshape[2])
            return i * (shape[1] * shape[2]) + base + rest

        # skin relief: a smooth random displacement of the segment surface
        band = np.flatnonzero(np.abs(A) < 3 * h + amp)
        A.flat[band] += np.float32(amp) * grid.noise(to_grid(band), bp["noise_seed"], (80.0, 250.0))
        del band
        # fat thickness varies by +-fat_noise (relative), smoothly
        inner = np.flatnonzero((A < 0) & (A > -(np.float32(1.0 + 2.0 * float(bp["fat_noise"])) * f + 10.0)))
        f.flat[inner] *= 1.0 + np.float32(bp["fat_noise"]) * np.clip(
            grid.noise(to_grid(inner), bp["noise_seed"] + 1, (60.0, 200.0)), -2.0, 2.0)
        del inner
        # distance to the bone surfaces: near bones (within the largest margin) and not deep in the body,
        # where neither the skin nor the fascia can come near a bone
        h0, h1 = max(0, y0 - r), min(shape[1], y1 + r)
        p0, p1 = np.searchsorted(ijk[:, 1], [h0, h1])
        occ = np.zeros((shape[0], h1 - h0, shape[2]), dtype=np.uint8)
        occ[ijk[p0:p1, 0], ijk[p0:p1, 1] - h0, ijk[p0:p1, 2]] = 1
        near = ndimage.maximum_filter(occ, size=2 * r + 1)[:, y0 - h0:y1 - h0]
        del occ
        near &= A > -(f + np.float32(R))
        cand = np.flatnonzero(near)
        del near
        Bd = np.empty(len(cand), dtype=np.float32)
        idx = np.empty(len(cand), dtype=np.int64)
        for i0 in range(0, len(cand), 500_000):
            d, j = tree.query(grid.points(to_grid(cand[i0:i0 + 500_000])), distance_upper_bound=R, workers=-1)
            j[~np.isfinite(d)] = 0
            Bd[i0:i0 + 500_000] = np.minimum(d, R)
            idx[i0:i0 + 500_000] = j
        ms = np.where(Bd < R, m_skin[idx], 0.0).astype(np.float32)
        A.flat[cand] = _smin(A.flat[cand], Bd - ms, np.float32(3.0))
        # the fascia's bone term, applied once the skin has no cavities
        cand_all.append(to_grid(cand))
        bm_all.append(Bd - np.where(Bd < R, m_mus[idx], 0.0).astype(np.float32))
        n_cand += len(cand)
        S[:, y0:y1] = A
        Fat[:, y0:y1] = f
        del A, f, cand, Bd, idx, ms
        t_bone += time.perf_counter() - ts
    timings["segments"] = t_seg
    timings["bone_candidates"] = float(n_cand)
    timings["bone_distance"] = t_bone
    return S, Fat, origin, np.concatenate(cand_all), np.concatenate(bm_all)


def _layers(S: np.ndarray, Fat: np.ndarray, cand: np.ndarray, bm: np.ndarray, h: float,
            timings: dict) -> tuple[np.ndarray, np.ndarray]:
    """The skin and fascia fields from :func:`_fields`' results: ``(S, Mu)``, in place of ``S`` and ``Fat``.

    Cavities are filled on the whole grid (they need its connectivity). The skin
    field is returned finished; the fascia field still needs
    ``_fill_cavities(Mu, -h)`` and :func:`_close_field`, which
    :func:`make_subject` runs once the skin is extracted and its field freed
    (the cavity labels take ~56 MB at the default preset: with both fields
    alive beside them that had been the phantom's peak).
    """
    t0 = time.perf_counter()
    shape = S.shape
    _fill_cavities(S, -h)
    fmin = np.float32(_f_min(h))
    Mu = Fat                                  # in place: fascia = skin offset inward by the fat
    for y0, y1 in _y_slabs(shape):
        s32 = S[:, y0:y1].astype(np.float32)
        mu = Fat[:, y0:y1].astype(np.float32)
        mu += s32
        Mu[:, y0:y1] = mu
        del s32, mu
    # the bone term at the candidates: min(fascia, bone distance - muscle margin)
    Mu.flat[cand] = np.minimum(Mu.flat[cand].astype(np.float32), bm)
    for y0, y1 in _y_slabs(shape):
        np.maximum(Mu[:, y0:y1], (S[:, y0:y1].astype(np.float32) + fmin).astype(np.float16), out=Mu[:, y0:y1])
    _close_field(S)
    timings["layers"] = time.perf_counter() - t0
    return S, Mu


def _close_field(field: np.ndarray) -> None:
    """An outside border on the grid, so that every level surface closes."""
    for ax in range(3):
        field.swapaxes(0, ax)[[0, -1]] = np.float16(1e4)


def _marching_cubes_slabs(field: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Zero level set of a (float16) grid, in slabs along axis 1; vertices in voxel units.

    Adjacent slabs share one layer of voxels: the vertices on it come out identical
    from both (same values, integer coordinates across) and are merged, so the
    result is the marching-cubes surface of the whole grid with float32 copies of
    one slab at a time.
    """
    from skimage.measure import marching_cubes

    V, F = [], []
    nv = 0
    for y0, y1 in _y_slabs(field.shape, _MC_SLAB_VOXELS):
        y1 = min(y1 + 1, field.shape[1])          # overlap one layer with the next slab
        if y1 - y0 < 2:
            continue
        sub = field[:, y0:y1].astype(np.float32)
        if sub.min() >= 0 or sub.max() < 0:
            continue
        # grid values at the level (float16 rounds more of them to exactly 0) give coincident
        # vertices that merge into non-manifold edges: push them 1e-3 mm off it
        at = np.abs(sub) < np.float32(1e-3)
        sub[at] = np.where(sub[at] >= 0, np.float32(1e-3), np.float32(-1e-3))
        v, f, _, _ = marching_cubes(sub, level=0.0, allow_degenerate=False)
        v[:, 1] += y0
        V.append(v)
        F.append(f + nv)
        nv += len(v)
    V = np.concatenate(V)
    F = np.concatenate(F)
    # merge the duplicates of the shared layers (exactly equal coordinates)
    _, first, inv = np.unique(V, axis=0, return_index=True, return_inverse=True)
    order = np.sort(first)
    remap = np.empty(len(first), dtype=np.int64)
    remap[np.argsort(first)] = np.arange(len(first))
    # vertex i -> its unique row -> that row's new index, keeping the first occurrence's order
    F = remap[inv.ravel()][F]
    return V[order].astype(np.float64), F


def _taubin(V: np.ndarray, F: np.ndarray, lamb: float, nu: float, iterations: int) -> np.ndarray:
    """Taubin smoothing with the equal-weight umbrella operator, as ``trimesh.smoothing.filter_taubin``.

    The same operator (each vertex moved towards the mean of its edge neighbours,
    ``+lamb`` on even passes, ``-nu`` on odd ones), built straight from the faces as one
    CSR matrix: trimesh's builds it through a COO matrix divided by its dense row sums,
    which on the whole-body surface (~10^6 faces) took ~200 MB more at its peak.
    """
    from scipy.sparse import csr_matrix

    n = len(V)
    F = np.asarray(F)
    rows = F.ravel().astype(np.int32)
    cols = F[:, [1, 2, 0]].ravel().astype(np.int32)       # the directed edges of every face
    L = csr_matrix((np.ones(len(rows), dtype=np.float64), (rows, cols)), shape=(n, n))
    del rows, cols
    L.sum_duplicates()
    L.data[:] = 1.0                                       # an edge counts once, as trimesh's boolean matrix
    deg = np.diff(L.indptr)
    L.data /= np.repeat(np.maximum(deg, 1), deg)
    V = np.array(V, dtype=np.float64, copy=True)
    for index in range(iterations):
        dot = L @ V
        dot -= V
        if index % 2 == 0:
            dot *= lamb
            V += dot
        else:
            dot *= nu
            V -= dot
    return V


#: Above this many faces the body surfaces are decimated in a child process (see :func:`_decimate`):
#: the library's vectors for 100 000 faces, ~30 MB, would stay in this process to its end.
_SIMPLIFY_IN_CHILD_FACES = 100_000


def _decimate(v: np.ndarray, f: np.ndarray, reduction: float, *,
              lean: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """``fast_simplification.simplify(v, f, target_reduction=reduction)``, then trimesh's processing:
    ``(verts float64, faces int64)``; large meshes in a child process.

    The processing (``trimesh.Trimesh(..., process=True)``) merges the vertices the
    decimation leaves coincident and drops degenerate faces.

    Memory: the library keeps its working arrays in global C++ vectors that are
    cleared but never shrunk: decimating the whole-body skin (~450k faces) left
    ~120 MB allocated for the rest of the run. A forked child
    (:func:`bonecap.parallel.fork_or_here`) returns them when it exits; it shares
    this process's pages instead of starting an interpreter of its own (a fresh one
    held ~35 MiB more: its own numpy and the mesh read back from a pipe). trimesh's
    processing runs in a second child once the first has gone: with its
    dependencies trimesh held ~21 MiB in this process to the end, on the peaks of
    the MRI rendering, and beside the decimation's vectors in one child it made
    the process tree's peak (+13 MiB). Same algorithms and input, so the same
    result. Where there is no ``fork``, with ``BONECAP_WORKERS=1`` (no child
    processes, e.g. inside a multi-threaded host), or with ``lean=False`` (a small
    phantom: each child's import of trimesh costs more than the memory it returns),
    it all runs here.
    """
    def simplify():
        import fast_simplification

        return fast_simplification.simplify(v, f, target_reduction=reduction)

    def process(dv, df):
        import trimesh

        tm = trimesh.Trimesh(dv, df, process=True)
        return np.asarray(tm.vertices, dtype=float), np.asarray(tm.faces, dtype=np.int64)

    if not lean or len(f) <= _SIMPLIFY_IN_CHILD_FACES:
        return process(*simplify())
    from bonecap.parallel import fork_or_here

    dv, df = fork_or_here(simplify)()
    return fork_or_here(lambda: process(dv, df))()


#: A dense surface above this many faces is first decimated in two halves (:func:`_presimplify_halves`).
_HALVES_ABOVE_FACES = 300_000
#: The fraction of its faces each half keeps (at least 1.2 times the target, which the whole is then
#: decimated to).
_HALVES_KEEP = 0.6


def _presimplify_halves(v: np.ndarray, f: np.ndarray, keep: float = _HALVES_KEEP) -> tuple[np.ndarray, np.ndarray]:
    """A closed surface's first decimation, in two halves: ``(verts float32, faces int32)``, ~``keep`` of its faces.

    The decimation library's working vectors grow with the faces it is given
    (~300 bytes a face: the default phantom's dense skin, 500 000 faces at seed 4,
    took 153 MiB, the process tree's peak beside the main process). The surface is
    cut across its longest extent at the faces' median; each half is decimated to
    ``keep`` of its faces with its cut kept exactly (``preserve_border``: no edge
    at a border vertex collapses), and the halves are joined again on the cut's
    vertices, which both still hold unchanged. The whole is then decimated to its
    target as before, from ~60 % of the faces: the working vectors of a half or of
    that, never of the whole. Against one pass on seed 4's skin: the dense
    surface's points lie 0.012 mm (mean) / 0.067 mm (max) from the result, 0.012 /
    0.085 mm from one pass's. In a forked child (:func:`bonecap.parallel.fork_or_here`),
    so that the vectors go with it.
    """
    def run():
        import fast_simplification

        vv = np.asarray(v, dtype=np.float32)
        ff = np.asarray(f, dtype=np.int32)
        axis = int(np.argmax(np.ptp(vv, axis=0)))
        centre = vv[:, axis][ff].mean(axis=1)
        lower = centre < np.median(centre)
        del centre
        parts = []
        for half in (lower, ~lower):
            used, local = np.unique(ff[half], return_inverse=True)
            pv, pf = fast_simplification.simplify(vv[used], local.reshape(-1, 3).astype(np.int32),
                                                  target_reduction=1.0 - keep, preserve_border=True)
            parts.append((pv, pf))
        V = np.concatenate([pv for pv, _ in parts])
        F = np.concatenate([parts[0][1], parts[1][1] + len(parts[0][0])])
        # the cut's vertices, unchanged in both halves, become one again (exact coordinates)
        V, joined = np.unique(V, axis=0, return_inverse=True)
        return V.astype(np.float32), joined.ravel()[F].astype(np.int32)

    from bonecap.parallel import fork_or_here

    return fork_or_here(run)()


def _closed_and_oriented(faces: np.ndarray, n_vertices: int) -> bool:
    """Whether every edge joins exactly two faces that run it in opposite directions.

    The same as trimesh's ``is_watertight and is_winding_consistent`` (each
    undirected edge in two faces and each directed edge once), from one sorted
    array of directed-edge keys: trimesh's checks build edge groups and a face
    adjacency graph, ~60 MB at the whole-body skin's 200 000 faces.
    """
    F = np.asarray(faces, dtype=np.int64)
    n = np.int64(n_vertices)
    key = np.sort(np.concatenate([F[:, 0] * n + F[:, 1], F[:, 1] * n + F[:, 2], F[:, 2] * n + F[:, 0]]))
    if len(key) and (key[1:] == key[:-1]).any():
        return False                          # a directed edge twice: two faces disagree on it, or a 3rd face
    rev = np.sort((key % n) * n + key // n)   # every edge's reverse, each once too
    return bool(np.array_equal(key, rev))


def _signed_volume(V: np.ndarray, F: np.ndarray, chunk: int = 65_536) -> float:
    """Signed volume of a closed triangle mesh (divergence theorem), in chunks of faces.

    Positive when the faces wind outward. trimesh's ``volume`` computes every mass
    property at once (~80 MB of temporaries at 200 000 faces) for this sign.
    """
    vol = 0.0
    for i in range(0, len(F), chunk):
        f = F[i:i + chunk]
        vol += float(np.einsum("ij,ij->", V[f[:, 0]], np.cross(V[f[:, 1]], V[f[:, 2]])))
    return vol / 6.0


def _dense_surface(field: np.ndarray, origin: np.ndarray, h: float, taubin: int,
                   max_faces: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The zero level set of ``field`` (negative inside, model frame) as ``(verts, faces)``, Taubin-smoothed,
    not yet decimated nor checked (the field can be freed after it; :func:`_finish_surface` does the rest).

    A surface over ``max_faces``, which :func:`_finish_surface` will decimate, comes as float32
    vertices and int32 faces, what the decimation takes anyway (the same result; half the memory
    while it waits: ~8 MB each for the default phantom's skin and fascia).
    """
    verts, faces = _marching_cubes_slabs(field, h)
    verts *= h
    verts += origin
    if taubin:
        verts = _taubin(verts, faces, lamb=0.5, nu=0.53, iterations=taubin)
    if max_faces is not None and len(faces) > max_faces:
        verts, faces = verts.astype(np.float32), faces.astype(np.int32)
    return verts, faces


def _finish_surface(verts: np.ndarray, faces: np.ndarray, max_faces: int, what: str, *,
                    lean: bool = True) -> Mesh:
    """A :func:`_dense_surface` decimated to ``max_faces``, made watertight and wound outward.

    Memory (the whole-body skin at 3.5 mm: ~440 000 faces before decimation): plain
    arrays are carried, not trimesh objects, and the checks are
    :func:`_closed_and_oriented` and :func:`_signed_volume`; trimesh's cached
    edge groups, adjacency graph and mass properties had made this the phantom's
    peak (+140 MB over the field, 2026-11-26).
    """
    if len(faces) > max_faces:
        v32 = np.asarray(verts, dtype=np.float32)
        faces = np.asarray(faces, dtype=np.int32)         # (the decimation's own; the same result)
        del verts
        keep = max(_HALVES_KEEP, 1.2 * max_faces / len(faces))     # (the whole still decimated after)
        if len(faces) > _HALVES_ABOVE_FACES and keep < 0.9:
            v32, faces = _presimplify_halves(v32, faces, keep)
        n_in = len(faces)
        # quadric decimation now and then pinches two sheets into a non-manifold edge: retry with
        # other targets (each try ~0.1-0.5 s); only when none gives a repairable mesh are fins (a sliver
        # folded into two coincident faces of opposite winding) dropped too, so that the meshes of the
        # phantoms that decimated before stay as they were (default seed 3's fascia had fins at all three)
        for frac, fins in ((1.0, False), (0.9, False), (0.8, False), (1.0, True), (0.9, True), (0.8, True)):
            V_, F_ = _decimate(v32, faces, 1.0 - frac * max_faces / n_in, lean=lean)
            dec = _repair_pinches(*(_drop_fins(V_, F_) if fins else (V_, F_)))
            del V_, F_
            if dec is not None:
                verts, faces = dec
                break
        else:
            raise RuntimeError(f"could not decimate the {what} mesh to {max_faces} faces and keep it watertight")
        del v32
    elif not _closed_and_oriented(faces, len(verts)):
        import trimesh

        tm = trimesh.Trimesh(verts, faces, process=False)
        trimesh.repair.fill_holes(tm)
        if not (tm.is_watertight and tm.is_winding_consistent):
            raise RuntimeError(f"the {what} mesh is not watertight")
        verts, faces = np.asarray(tm.vertices, dtype=float), np.asarray(tm.faces)
    if _signed_volume(verts, faces) < 0:
        faces = np.ascontiguousarray(faces[:, ::-1])
    return Mesh(np.asarray(verts, dtype=float), np.asarray(faces), WORLD)


def _drop_fins(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mesh without its fins: pairs of faces on the same three vertices, wound opposite ways.

    Quadric decimation now and then folds a sliver flat into two coincident
    triangles back to back, a zero-volume fin whose edges then join three or
    four faces (default phantom, seed 3: the fascia, two such pairs on every
    decimation target tried). The two faces of a pair enclose nothing:
    both go, and the surface around them closes over their edges (what is
    left of them is then repaired by :func:`_repair_pinches`).
    """
    F = np.asarray(F, dtype=np.int64)
    srt = np.sort(F, axis=1)
    # the winding: an even (+1) or odd (-1) permutation of the sorted triple
    parity = np.where((F[:, 0] == srt[:, 0]) & (F[:, 1] == srt[:, 1]) | (F[:, 1] == srt[:, 0]) & (F[:, 2] == srt[:, 1])
                      | (F[:, 2] == srt[:, 0]) & (F[:, 0] == srt[:, 1]), 1, -1)
    _, inv, counts = np.unique(srt, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    drop = np.zeros(len(F), bool)
    for g in np.flatnonzero(counts == 2):
        pair = np.flatnonzero(inv == g)
        if parity[pair[0]] != parity[pair[1]]:
            drop[pair] = True
    return np.asarray(V, dtype=float), F[~drop]


def _repair_pinches(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """A watertight, consistently wound version ``(V, F)`` of a decimated mesh, or None.

    Quadric decimation sometimes collapses a thin tunnel (e.g. under a bone
    arch) into an edge shared by four faces: two sheets touching. The sheets
    are separated by giving each its own copy of the edge's vertices (found as
    the connected fans around each vertex once the bad edge is ignored); the
    copies are moved 0.05 mm apart along their sheet's normal so that a later
    vertex merge does not join them again.
    """
    V = np.array(V, dtype=float)
    F = np.array(F, dtype=np.int64)
    for _ in range(3):
        e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1).astype(np.int64)
        key, c = np.unique(e[:, 0] * (len(V) + 1) + e[:, 1], return_counts=True)
        bad_key = key[c > 2]
        bad = np.stack([bad_key // (len(V) + 1), bad_key % (len(V) + 1)], axis=1)
        if len(bad) == 0:
            break
        bad_set = {tuple(x) for x in bad}
        fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
        new_v = []
        for v in np.unique(bad):
            fan = np.flatnonzero((F == v).any(axis=1))
            # faces of the fan are neighbours through an edge (v, x) that is not a bad edge
            parent = {int(f): int(f) for f in fan}

            def find(x):
                while parent[x] != x:
                    parent[x] = parent[parent[x]]
                    x = parent[x]
                return x

            by_edge: dict[tuple[int, int], list[int]] = {}
            for f in fan:
                for x in F[f]:
                    if x != v:
                        key = (min(v, x), max(v, x))
                        if key not in bad_set:
                            by_edge.setdefault(key, []).append(int(f))
            for fs in by_edge.values():
                for f in fs[1:]:
                    parent[find(f)] = find(fs[0])
            comps: dict[int, list[int]] = {}
            for f in fan:
                comps.setdefault(find(int(f)), []).append(int(f))
            for fs in list(comps.values())[1:]:
                n = fn[fs].sum(0)
                n = n / max(np.linalg.norm(n), 1e-12)
                idx = len(V) + len(new_v)
                new_v.append(V[v] - 0.05 * n)
                for f in fs:
                    F[f][F[f] == v] = idx
        if not new_v:
            break
        V = np.vstack([V, np.array(new_v)])
    return (V, F) if _closed_and_oriented(F, len(V)) else None


# --------------------------------------------------------------------------- #
# the subject
# --------------------------------------------------------------------------- #
def make_subject(seed: int = 0, stature_mm: float | None = None, generic="default", *, preset: str = "default",
                 params: dict[str, Any] | None = None) -> PhantomSubject:
    """Build a synthetic subject: varied skeleton, body, MRI pose, meshes.

    Parameters
    ----------
    seed : int
        Seeds everything (parameters, bone surface sampling, skin relief).
    stature_mm : float, optional
        Stature; default drawn around 1700 mm (see :func:`draw_subject_params`).
    generic : str or path-like
        ``"default"`` (embedded generic skeleton) or an OpenSim ``.osim`` model.
        OpenSim meshes have no endosteal surface: one is made at the embedded
        description's cortical thickness (:func:`with_marrow`).
    preset : {"default", "tiny"}
        Grid spacing and mesh budgets (:data:`PRESETS`): ``default`` 3.5 mm,
        skin and fascia <= 200k triangles each; ``tiny`` 6 mm, <= 20k, with
        the soft tissue over the bones >= ~8 mm (the margins must exceed the
        grid's error).
    params : dict, optional
        Parameters as returned by :func:`draw_subject_params` (then ``seed``,
        ``stature_mm`` and ``generic`` only seed the sampling).

    Returns
    -------
    PhantomSubject

    Raises
    ------
    InputError
        Unknown preset, a ``generic`` that is neither ``"default"`` nor an
        ``.osim`` file, or a template without legs, trunk or skull meshes.
    RuntimeError
        A mesh could not be made watertight (not expected; a bug).

    Notes
    -----
    Cost on 2 cores (CPU time): the body takes ~10-12 s at the default preset
    (its grid filled in slabs, kept as float16: ~75 MB for the two fields),
    ~3-4 s at ``tiny``; the generic skeleton ~18 s to build at the default
    preset and ~3 s at ``tiny`` (meshed 3.5x coarser), an OpenSim model ~0.5 s
    to read and vary. ``metadata["timings_s"]`` has the breakdown (wall).

    References
    ----------
    See the module docstring (anthropometry, fat thickness, smooth minimum).
    """
    if preset not in PRESETS:
        raise InputError(f"unknown phantom preset {preset!r} (known: {', '.join(PRESETS)})")
    cfg = PRESETS[preset]
    lean = bool(cfg.get("lean", True))
    tidy = memory_tidier(preset)
    if not lean:
        # the meshing libraries imported once, here: the skeleton's meshing child (forked) and the body's
        # decimation (in this process) then both have them; the lean path keeps them out of this process
        import fast_simplification  # noqa: F401
        import trimesh  # noqa: F401
        from vtkmodules.vtkFiltersCore import vtkFlyingEdges3D  # noqa: F401
    timings: dict[str, float] = {}
    t_all = time.perf_counter()
    t0 = time.perf_counter()
    if params is None:
        params = draw_subject_params(seed, stature_mm, generic)
    params = {**params, "preset": preset}
    tidy()
    sk = build_subject_skeleton(params, generic)
    tidy()
    timings["skeleton"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    rng = np.random.default_rng([int(seed), 7])
    bp = params["body"]
    smp = _sample_bones(sk, cfg["sample_spacing"], bp["scalp_mm"], bp["shin_mm"], rng)
    plan = _plan_body(sk, smp, params)
    h = float(cfg["spacing"])
    _coarse_margins(smp, h)
    anatomical = {n: b.bone_to_world.tolist() for n, b in sk.bones.items()}
    # the skin relief and the grid may each take ~ their size off the gap
    pose = _solve_pose(sk, smp, plan, params, bp["skin_noise_mm"] + 0.5 * h, rng)
    params["pose"] = pose
    timings["plan"] = time.perf_counter() - t0
    tidy()
    # the bone samples at the MRI pose and their margins are all that is used of them from here: the
    # rest (~16 MB at the default preset) goes before the grid is filled, the others (~16 MB more)
    # before its cavities are labelled -- both the main process's peak in turn
    W, m_skin, m_mus = smp.world(sk), smp.m_skin, smp.m_mus
    del smp
    S, Fat, origin, cand, bm = _fields(W, m_skin, m_mus, plan, params, h, timings)
    del W, m_skin, m_mus
    tidy()
    S, Mu = _layers(S, Fat, cand, bm, h, timings)
    del Fat, cand, bm
    t0 = time.perf_counter()

    def fascia():
        _fill_cavities(Mu, -h)
        _close_field(Mu)
        return _dense_surface(Mu, origin, h, int(cfg["taubin_iterations"]), int(cfg["muscle_faces"]))

    if lean:
        # both dense surfaces first, then both decimations: the fields are freed before the decimation's
        # child process starts beside this one (the phase held ~400 MiB with them)
        skin = _dense_surface(S, origin, h, int(cfg["taubin_iterations"]), int(cfg["skin_faces"]))
        del S
        tidy()
        muscle = fascia()
        del Mu
        tidy()
        skin = _finish_surface(*skin, int(cfg["skin_faces"]), "skin", lean=lean)
        muscle = _finish_surface(*muscle, int(cfg["muscle_faces"]), "fascia", lean=lean)
        tidy()
    else:
        # a small body: the fascia is made in a forked child beside the skin (two cores: the two surfaces
        # 0.84 -> 0.69 s at the tiny preset); the same algorithms on the same fields, so the same surfaces
        from bonecap.parallel import fork_or_here

        muscle_job = fork_or_here(lambda: _finish_surface(*fascia(), int(cfg["muscle_faces"]), "fascia", lean=lean),
                                  beside=True)
        skin = _finish_surface(*_dense_surface(S, origin, h, int(cfg["taubin_iterations"]), int(cfg["skin_faces"])),
                               int(cfg["skin_faces"]), "skin", lean=lean)
        muscle = muscle_job()
        del S, Mu
    timings["meshes"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_all
    el = {s: plan.joints.get(f"elbow_{s}") for s in "rl"}
    levels = dict(plan.levels)
    if "arm_r" in plan.chains:
        levels["mid_humerus"] = float(np.mean([0.5 * (plan.chains[f"arm_{s}"][3][1] + el[s][1]) for s in "rl"]))
    levels["mid_thigh"] = float(np.mean([0.5 * (plan.joints[f"hip_{s}"][1] + plan.joints[f"knee_{s}"][1])
                                         for s in "rl"]))
    levels = {k: float(v) for k, v in levels.items()}
    meta = {
        "preset": preset,
        "spacing_mm": h,
        "timings_s": {k: round(v, 3) for k, v in timings.items()},
        "skin_faces": len(skin.faces),
        "muscle_faces": len(muscle.faces),
        "height_mm": float(skin.vertices[:, 1].max() - skin.vertices[:, 1].min()),
        "levels_mm": levels,
        "joints_mm": {k: v.tolist() for k, v in plan.joints.items()},
        "anatomical_bone_to_world": anatomical,
    }
    sk.metadata = dict(sk.metadata)
    sk.metadata["phantom"] = {**sk.metadata.get("phantom", {}), "seed": int(seed), "pose": pose}
    return PhantomSubject(skeleton=sk, skin=skin, muscle=muscle, params=params, metadata=meta)


# --------------------------------------------------------------------------- #
# affine residual
# --------------------------------------------------------------------------- #
def _points(x) -> np.ndarray:
    if isinstance(x, Mesh):
        return x.vertices
    if isinstance(x, (list, tuple)) and x and isinstance(x[0], Mesh):
        return np.concatenate([m.vertices for m in x])
    return np.asarray(x, dtype=float).reshape(-1, 3)


def _faces(x) -> np.ndarray | None:
    """The faces of a Mesh or list of Meshes (indices into :func:`_points`), else None."""
    if isinstance(x, Mesh):
        return x.faces
    if isinstance(x, (list, tuple)) and x and isinstance(x[0], Mesh):
        out, n = [], 0
        for m in x:
            out.append(m.faces + n)
            n += len(m.vertices)
        return np.concatenate(out)
    return None


def _fit_affine(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Least-squares 4x3 ``M`` with ``[A 1] M ~ B``."""
    Ah = np.hstack([A, np.ones((len(A), 1))])
    M, *_ = np.linalg.lstsq(Ah, B, rcond=None)
    return M


def affine_fit_residual(a, b, *, iterations: int = 40, correspondence: bool | None = None) -> float:
    """Mean residual (mm) of the best affine map from one shape to another.

    Parameters
    ----------
    a, b : Mesh, list of Mesh, or array (N, 3)
        Two shapes (e.g. the same bone, or the hip+femur+tibia chain as one
        point set, of two subjects).
    iterations : int
        ICP iterations when the shapes do not correspond vertex by vertex.
    correspondence : bool, optional
        Whether point ``i`` of ``a`` corresponds to point ``i`` of ``b``.
        Default: for meshes, when both have the same faces (the same topology,
        as the OpenSim variation produces; the generic skeleton's meshes are
        remeshed per build and do not correspond); for point arrays, when they
        have the same length.

    Returns
    -------
    float
        With correspondence: the mean distance between corresponding points
        after the least-squares affine map ``a -> b``.
        Otherwise an affine ICP: nearest neighbours both ways (``a -> b`` and
        ``b -> a``, which keeps the map from collapsing onto part of ``b``),
        refitted until stable; the residual is then the mean of both
        point-to-surface distances when both shapes are meshes (so that two
        different triangulations of one surface give ~0), else of both
        nearest-neighbour distances. Zero when ``b`` is an affine image of
        ``a``; a pipeline that warps a template affinely cannot get below it.
    """
    A, B = _points(a), _points(b)
    fa, fb = _faces(a), _faces(b)
    if correspondence is None:
        if fa is not None and fb is not None:
            correspondence = fa.shape == fb.shape and bool(np.array_equal(fa, fb))
        else:
            correspondence = len(A) == len(B)
    if correspondence:
        if len(A) != len(B):
            raise ValueError(f"correspondence needs as many points in both shapes, got {len(A)} and {len(B)}")
        M = _fit_affine(A, B)
        return float(np.linalg.norm(np.hstack([A, np.ones((len(A), 1))]) @ M - B, axis=1).mean())
    # affine ICP, initialised by matching centroids and scales
    ca, cb = A.mean(0), B.mean(0)
    s = math.sqrt(((B - cb) ** 2).sum(1).mean() / max(((A - ca) ** 2).sum(1).mean(), 1e-12))
    M = np.vstack([np.eye(3) * s, cb - s * ca])
    tb = cKDTree(B)
    prev = np.inf
    res = np.inf
    for _ in range(iterations):
        TA = np.hstack([A, np.ones((len(A), 1))]) @ M
        d1, i1 = tb.query(TA)
        d2, i2 = cKDTree(TA).query(B)
        res = 0.5 * (d1.mean() + d2.mean())
        M = _fit_affine(np.concatenate([A, A[i2]]), np.concatenate([B[i1], B]))
        if abs(prev - res) < 1e-4:
            break
        prev = res
    if fa is not None and fb is not None:
        import trimesh

        TA = np.hstack([A, np.ones((len(A), 1))]) @ M
        _, d1, _ = trimesh.Trimesh(B, fb, process=False).nearest.on_surface(TA)
        _, d2, _ = trimesh.Trimesh(TA, fa, process=False).nearest.on_surface(B)
        res = 0.5 * (d1.mean() + d2.mean())
    return float(res)
