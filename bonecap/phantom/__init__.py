"""``bonecap phantom``: a synthetic subject with ground truth, the measuring stick of every stage.

No public whole-body MRI with bone labels exists, so bonecap makes its own
subject and keeps the truth:

- :mod:`bonecap.phantom.subject` -- a person, not the template: the skeleton
  varied non-affinely per seed, plus a body model (muscle, fat, skin);
- :mod:`bonecap.phantom.mri` / :mod:`bonecap.phantom.render` -- whole-body MRI
  stations rendered from the meshes with partial volume, knee-measured tissue
  contrast, bias and Rician noise, each station moved a little against the truth;
- :mod:`bonecap.phantom.forearm` -- the forearm posed at the paper's twists for
  the forearm stacks (with oil capsules on the skin);
- :mod:`bonecap.phantom.trials` -- C3D trials with soft-tissue artefact and gaps.

:func:`make_phantom` runs them all and writes ``OUT_DIR/mri``,
``OUT_DIR/trials`` and ``OUT_DIR/truth`` (formats in ``truth/README.md``,
written by :func:`write_truth_readme`).

Frames: the subject is built in the template world ``"model"`` (X anterior,
Y up, Z right, mm). Everything written beside the MRI (truth meshes, labels,
capsules, forearm axes) is in the **LPS** patient frame of the DICOM stacks,
``MODEL_TO_LPS`` away; the trials and their truth poses are in the Z-up lab.
"""

from __future__ import annotations

import json
import os
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from bonecap.errors import InputError
from bonecap.io.atomic import atomic_path
from bonecap.io.imaging import write_nifti
from bonecap.io.mesh import write_mesh
from bonecap.model import Mesh, Volume
from bonecap.motion.rigid import apply_transform
from bonecap.phantom.forearm import MODEL_TO_LPS, pose_forearm
from bonecap.progress import stage_bar

__all__ = ["PRESETS", "FOREARM_TWISTS_DEG", "make_phantom", "write_truth_readme", "MODEL_TO_LPS"]

#: The paper's measured forearm twists (it labelled them 0/90/180).
FOREARM_TWISTS_DEG = (0.0, 99.5, 172.1)

#: Acquisition and trial settings per preset. ``tiny`` is for the tests
#: (coarse, a few stations, short trials); ``default`` is the paper's set-up.
#: ``trials_beside``: the trials are made in a forked child while the MRI renders
#: (:func:`run_beside`); the default preset makes them after the subject instead,
#: in a child that ends before the MRI starts, for its memory target (the two
#: processes together held ~350 MiB; ~5 s longer). ``forearm_beside``: the
#: forearm stacks likewise, in a second child beside the stations (the tiny
#: preset: ~0.5 s less wall time on 2 cores); after them in this process otherwise.
PRESETS: dict[str, dict[str, Any]] = {
    "default": {"n_stations": 8, "pixel_mm": 1.8, "pitch_mm": 5.0, "thickness_mm": 5.0, "supersample": 4,
                "through": 4, "forearm_pixel_mm": 0.7, "forearm_pitch_mm": 2.5, "n_capsules": 8,
                "duration_scale": 1.0, "merged_voxel_mm": 2.0, "trials_beside": False,
                "forearm_beside": False},
    "tiny": {"n_stations": 2, "pixel_mm": 4.0, "pitch_mm": 15.0, "thickness_mm": 15.0, "supersample": 2,
             "through": 2, "forearm_pixel_mm": 1.5, "forearm_pitch_mm": 5.0, "n_capsules": 6,
             "duration_scale": 0.2, "merged_voxel_mm": 6.0, "trials_beside": True,
             "forearm_beside": True},
}


def _to_lps(mesh: Mesh) -> Mesh:
    return mesh.transformed(MODEL_TO_LPS, "lps")


def _bounding_sphere(mesh: Mesh) -> tuple[np.ndarray, float]:
    """Centre and radius of a sphere holding the mesh (its bounding box's), in the mesh's frame."""
    lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
    return 0.5 * (lo + hi), 0.5 * float(np.linalg.norm(hi - lo))


def _may_reach_forearm_stack(sphere: tuple[np.ndarray, float], bone_to_model: np.ndarray, elbow: np.ndarray,
                             wrist: np.ndarray, cfg: dict[str, Any]) -> bool:
    """Whether a bone (its bounding sphere, :func:`_bounding_sphere`) can reach the forearm stack's field of view.

    :func:`~bonecap.phantom.mri.plan_forearm_stack` covers skin within
    ``max_radius_mm`` (80) of the elbow-wrist axis plus a margin (<= 20 mm):
    an in-plane box whose corners lie <= 100 * sqrt(2) mm from the axis, and
    slices from ``extend_mm`` (10) before the elbow to as far past the wrist,
    each a slice thickness deep. A bone whose bounding sphere stays outside a
    cylinder of 160 mm radius around that stretch (plus 40 mm) cannot show.
    """
    c_bone, r = sphere
    c = bone_to_model[:3, :3] @ c_bone + bone_to_model[:3, 3]
    d = np.asarray(wrist, float) - np.asarray(elbow, float)
    L = float(np.linalg.norm(d))
    n = d / L
    s = float((c - elbow) @ n)
    radial = float(np.linalg.norm((c - elbow) - s * n))
    reach = 40.0 + 2 * float(cfg["forearm_pitch_mm"])
    return radial - r <= 160.0 and s + r >= -reach and s - r <= L + reach


def _twist_name(theta: float) -> str:
    return f"{theta:g}"


def _write_json(path: Path, obj: Any) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=2))


def _marker_capsules(marker_set, skeleton, skin, capsule_radius_mm: float | None = None,
                     marker_radius_mm: float = 7.0) -> dict[str, Any]:
    """Oil capsules under the trial markers at the MRI (reference) pose, LPS.

    The markers are placed as the trials place them
    (:func:`~bonecap.phantom.trials.place_phantom_markers`: centre one marker
    radius out along the skin normal); each capsule touches the skin at the
    same contact point, so its centre is ``marker_radius - capsule_radius``
    closer to the skin along that normal. ``capsule_radius_mm``: by default
    half of :data:`~bonecap.phantom.mri.CAPSULE_DIAMETER_MM`.
    """
    from bonecap.phantom.mri import CAPSULE_DIAMETER_MM
    from bonecap.phantom.trials import place_phantom_markers

    if capsule_radius_mm is None:
        capsule_radius_mm = CAPSULE_DIAMETER_MM / 2
    binding = place_phantom_markers(marker_set, skeleton, skin, marker_radius_mm=marker_radius_mm)
    lps = apply_transform(MODEL_TO_LPS, _capsules_under(binding.world, skin, capsule_radius_mm))
    return {"frame": "LPS, MRI pose (the stations' true world)", "capsule_radius_mm": capsule_radius_mm,
            "marker_radius_mm": marker_radius_mm,
            "centres_lps": {n: c.tolist() for n, c in zip(binding.names, lps)}}


def _capsules_under(markers: np.ndarray, skin: Mesh, capsule_radius_mm: float) -> np.ndarray:
    """Centres of capsules touching the skin where markers (centres ``(M, 3)``, resting on ``skin``) touch it.

    A marker's centre is one marker radius out along the skin's normal from its contact point; the capsule
    rests on the same contact point, its centre one capsule radius out.
    """
    contact, _, _ = skin.to_trimesh().nearest.on_surface(markers)
    normal = markers - contact
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-9)
    return contact + capsule_radius_mm * normal


def _forearm_marker_capsules(marker_set, skeleton, skin: Mesh, side: str, capsule_radius_mm: float | None = None,
                             marker_radius_mm: float = 7.0) -> dict[str, tuple[str, np.ndarray]]:
    """Oil capsules at the forearm markers' spots, model frame, reference pose: name -> (bone, centre).

    The paper marked its marker spots with capsules in the forearm stacks as in
    the whole body; its twist was read on them. The markers of the forearm are
    those bound to the ulna or the radius and the elbow line's two epicondyle
    markers (:data:`bonecap.motion.forearm.FOREARM_MARKERS`; the medial one
    lies beyond the stacks' field of view on the phantoms made so far). Each is placed as
    the trials place it (:func:`~bonecap.phantom.trials.place_phantom_markers`,
    on ``skin``: the forearm's part of the reference skin is enough, the rays
    and nearest points being local), and its capsule touches the skin at the
    same spot (centre ``marker_radius - capsule_radius`` nearer the skin).
    """
    from bonecap.motion.forearm import FOREARM_MARKERS
    from bonecap.phantom.mri import CAPSULE_DIAMETER_MM
    from bonecap.phantom.trials import place_phantom_markers

    if capsule_radius_mm is None:
        capsule_radius_mm = CAPSULE_DIAMETER_MM / 2
    forearm_bones = {f"ulna_{side}", f"radius_{side}"}
    names = [n for n in marker_set.physical
             if n in FOREARM_MARKERS[side] or marker_set.markers[n].bone in forearm_bones]
    names = [n for n in names if marker_set.markers[n].bone in skeleton.bones]
    if not names:
        return {}
    binding = place_phantom_markers(marker_set, skeleton, skin, names=names, marker_radius_mm=marker_radius_mm)
    centres = _capsules_under(binding.world, skin, capsule_radius_mm)
    return {n: (b, c) for n, b, c in zip(binding.names, binding.bones, centres)}


def _faces_across(mesh: Mesh, elbow: np.ndarray, wrist: np.ndarray, lo_mm: float, hi_mm: float) -> np.ndarray:
    """Faces whose extent along elbow -> wrist overlaps ``[lo_mm, hi_mm]`` (0 at the elbow), as a mask."""
    n = np.asarray(wrist, float) - np.asarray(elbow, float)
    n /= np.linalg.norm(n)
    sf = ((mesh.vertices - elbow) @ n)[mesh.faces]
    return (sf.max(axis=1) >= lo_mm) & (sf.min(axis=1) <= hi_mm)


def _keep_faces(mesh: Mesh, keep: np.ndarray) -> Mesh:
    """The faces in ``keep`` and the vertices they use (in their order), as a new mesh."""
    F = mesh.faces[keep]
    used = np.zeros(len(mesh.vertices), bool)
    used[F.ravel()] = True
    new_id = np.cumsum(used) - 1
    return Mesh(mesh.vertices[used], new_id[F], mesh.frame)


#: A capsule at a forearm marker's spot, carried with the marker's bone, is shown in a forearm stack while
#: its centre is within this distance (mm) of one capsule radius from the posed skin.
_CAPSULE_ON_SKIN_MM = 1.0

#: Slices of a forearm stack reach :data:`~bonecap.phantom.mri.FOREARM_EXTEND_MM` past the
#: elbow and the wrist, plus half a slice thickness of slice profile; the posed skin and
#: fascia are kept this much further on each side (mm).
_FOREARM_CROP_MARGIN_MM = 40.0


def make_phantom(out_dir: str | os.PathLike, *, seed: int = 0, stature_mm: float | None = None,
                 generic: str | os.PathLike = "default", preset: str = "default",
                 marker_capsules: bool = False) -> dict[str, Any]:
    """Make a synthetic subject: MRI stations, forearm stacks, trials and the truth.

    The trials are made in a forked child process: at the tiny preset while this
    one renders the MRI (:func:`run_beside`), at the default preset after the
    subject, for memory (``PRESETS[preset]["trials_beside"]``). At the tiny
    preset the forearm stacks are rendered in a second child beside the
    stations (``forearm_beside``); each has its own random stream, so the
    outputs are the same wherever they run. ``BONECAP_WORKERS=1`` keeps
    everything in one process. ``timings_s["trials"]`` and ``["forearm"]`` are
    the stages' own times, ``trials_wait`` and ``forearm_wait`` what was left to
    wait for when they were joined (~0 when they ran in this process), ``wall_s``
    the whole run. A failure stops the children (they are not left writing).

    Parameters
    ----------
    out_dir : path-like
        Output folder; ``mri/``, ``trials/``, ``truth/`` and ``phantom.json``
        are written in it.
    seed : int
        Everything is deterministic for a seed.
    stature_mm : float, optional
        Stature; drawn around 1.70 m when not given.
    generic : str or path-like
        ``"default"`` or an OpenSim ``.osim`` model. With a model, the trial
        markers are its MarkerSet without its virtual markers.
    preset : {"default", "tiny"}
        ``tiny``: a few coarse stations and short trials, for the tests.
    marker_capsules : bool
        Image an oil capsule (8 mm) on the skin under every trial marker in
        the whole-body stations and under the forearm's markers in the forearm
        stacks (carried there with their bones; ``truth/forearm.json``'s
        ``marker_capsules_lps``), as the paper's protocol did (the capsules
        mark the spots the motion-capture markers are later stuck on). Each
        capsule touches the skin at the marker's contact point, its centre one
        capsule radius out along the skin normal (the marker's is one marker
        radius out); the centres go to ``truth/marker_capsules.json``.

    Returns
    -------
    dict
        The summary also written to ``phantom.json``.
    """
    # the trials and (tiny preset) the forearm stacks run in forked children: if anything fails
    # meanwhile, they are stopped, not left writing into OUT_DIR after the error
    children: list = []
    try:
        return _make_phantom(out_dir, seed, stature_mm, generic, preset, marker_capsules, children)
    except BaseException:
        for join in children:
            getattr(join, "cancel", lambda: None)()
        raise


def _make_phantom(out_dir, seed, stature_mm, generic, preset, marker_capsules, children: list) -> dict[str, Any]:
    """:func:`make_phantom`'s work; the joins of the children it forks are appended to ``children``."""
    from bonecap.markers import load_marker_set
    from bonecap.phantom.mri import (CAPSULE_DIAMETER_MM, FOREARM_EXTEND_MM, ForearmPose, capsule_meshes,
                                     icosphere, plan_stations, render_forearm_stacks, render_stations,
                                     write_merged_labels)
    from bonecap.phantom.subject import make_subject, memory_tidier
    from bonecap.phantom.trials import make_trials
    from bonecap.skeleton.template import template_marker_set

    if preset not in PRESETS:
        raise InputError(f"unknown preset (choose from {', '.join(PRESETS)})", preset)
    if stature_mm is not None and not 1000.0 <= stature_mm <= 2300.0:
        raise InputError(f"stature must be between 1.0 and 2.3 m, got {stature_mm / 1000:g} m")
    cfg = PRESETS[preset]
    tidy = memory_tidier(preset)        # memory handed back between stages where it is worth its time
    out = Path(out_dir)
    truth = out / "truth"
    rng = np.random.default_rng(seed)
    timings: dict[str, float] = {}
    t_start = time.perf_counter()
    bar = stage_bar(5, "phantom")

    # The capsules' sphere first, while this process is small: it takes trimesh, which the default
    # preset otherwise imports only in children (see mri.icosphere). The tiny preset, which makes its
    # trials beside the MRI, decimates its small body surfaces here and has trimesh by then anyway: a
    # child now would only add its start (~0.6 s, the import of trimesh there).
    if not cfg["trials_beside"]:
        icosphere(CAPSULE_DIAMETER_MM / 2)

    # 1. The subject.
    t0 = time.perf_counter()
    bar.set_postfix_str("subject")
    subject = make_subject(seed, stature_mm, generic, preset=preset)
    skeleton = subject.skeleton
    bone_ids = {name: i + 1 for i, name in enumerate(n for n, b in skeleton.bones.items() if b.mesh is not None)}
    # LPS copies for the renderer share the faces of the subject's meshes, and the oracle labels
    # share the cortex layers' meshes (the same bone surfaces): ~27 MB less while the stations render
    layers = subject.layers(MODEL_TO_LPS, "lps")
    cortex = iter(m for m, tissue in layers if tissue == "cortex")    # skeleton order, bones with a mesh
    label_meshes = [(next(cortex), i) for i in bone_ids.values()]
    timings["subject"] = time.perf_counter() - t0
    bar.update()

    # 4. Trials, in a forked child while this process renders the MRI (tiny preset), or now in a child
    # that ends before the MRI starts (default): they need only the subject and their own seeded
    # generator, so the outputs are the same either way.
    marker_set = load_marker_set("kojima_paper") if str(generic) == "default" else template_marker_set(generic)

    def trials_stage():
        from bonecap.parallel import one_blas_thread

        t = time.perf_counter()
        with one_blas_thread():      # as a child runs them: bit-identical trials wherever they run
            res = make_trials(skeleton, marker_set, out, skin=subject.skin, seed=seed,
                              duration_scale=cfg["duration_scale"])
        return res, time.perf_counter() - t

    if cfg["trials_beside"]:
        trials_job = run_beside(trials_stage)
        children.append(trials_job)
    else:
        from bonecap.parallel import fork_or_here

        # a child for memory, not speed: what the trials import (trimesh and its dependencies,
        # ~21 MiB) and leave on the heap goes with it instead of sitting under the MRI's peaks
        trials_done = fork_or_here(trials_stage)()
        trials_job = lambda: trials_done  # noqa: E731

    # 3. Forearm stacks at the paper's twists: defined here, run beside the stations at the tiny preset
    # (a forked child, like the trials) or after them in this process (default: memory). Their own
    # random stream and the study UID made here: the same stacks wherever they run.
    # a UUID-derived UID (DICOM PS3.5 B.2), made without importing pydicom here: imported before the
    # children are forked, its modules were copied into each of them (+13 MiB on the default preset's peak)
    study_uid = f"2.25.{uuid.uuid4().int}"
    patient = {"patient_name": f"Phantom^{seed}", "patient_id": f"PHANTOM{seed:04d}"}
    labels_dir = truth / "labels"
    forearm_rng = np.random.default_rng([int(seed), 3])

    def forearm_stage():
        t = time.perf_counter()
        poses, forearm_truth = {}, {}
        forearm_marker_capsules: dict[str, dict[str, np.ndarray]] = {}
        spheres = {name: _bounding_sphere(b.mesh) for name, b in skeleton.bones.items() if b.mesh is not None}
        crop = None
        for theta in FOREARM_TWISTS_DEG:
            posed = pose_forearm(skeleton, subject.skin, subject.muscle, theta, side="r")
            # Only a slab of the posed body across the forearm can show in a stack: the rest of the
            # whole-body skin and fascia (~43 MB for the three twists in LPS at the default preset)
            # is cut off here. Whole faces go, in order, and every face a stack's slice planes cross
            # stays (so the images are unchanged); one face set for all twists keeps the skins'
            # common topology, which the capsule placement needs.
            L = float(np.linalg.norm(posed.wrist - posed.elbow))
            reach = FOREARM_EXTEND_MM + cfg["forearm_pitch_mm"]     # the slices' reach, profile included
            if crop is None:
                crop = [_faces_across(m, posed.elbow, posed.wrist, -reach - _FOREARM_CROP_MARGIN_MM,
                                      L + reach + _FOREARM_CROP_MARGIN_MM) for m in (posed.skin, posed.muscle)]
                # the paper's protocol marks the forearm markers' spots in the forearm stacks too: where the
                # trials place the markers, on the skin of the first (reference) twist
                at_ref = _forearm_marker_capsules(marker_set, skeleton, _keep_faces(subject.skin, crop[0]), "r") \
                    if marker_capsules else {}
            # Each carried with its marker's bone, as the trials carry the marker (its rigid part: the trials'
            # soft-tissue artefact is not applied to the capsules, so they are the truth's). The phantom's skin winds
            # with the radius about the radio-ulnar axis (pose_forearm) while a marker rides its bone: where the
            # two part (the ulnar styloid's spot is 12 mm under the wound skin at 172 deg, the dorsal forearm's
            # 5 mm), the capsule would be buried in the tissue or float off it, and this stack does not show it.
            skin_crop = _keep_faces(posed.skin, crop[0])
            tm = skin_crop.to_trimesh() if at_ref else None
            for mname, (bone, c_ref) in at_ref.items():
                T = posed.bone_to_world.get(bone, skeleton.bones[bone].bone_to_world) @ np.linalg.inv(
                    skeleton.bones[bone].bone_to_world)
                c = T[:3, :3] @ c_ref + T[:3, 3]
                q, _, tri = tm.nearest.on_surface(c[None])
                height = float((c - q[0]) @ tm.face_normals[tri[0]])      # out of the skin (outward normals)
                if abs(height - CAPSULE_DIAMETER_MM / 2) <= _CAPSULE_ON_SKIN_MM:
                    forearm_marker_capsules.setdefault(mname, {})[_twist_name(theta)] = apply_transform(MODEL_TO_LPS, c[None])[0]
            for m, keep in zip((posed.skin, posed.muscle), crop):
                if (_faces_across(m, posed.elbow, posed.wrist, -reach, L + reach) & ~keep).any():
                    raise RuntimeError(f"the forearm at {theta} deg moved out of the first twist's crop")
            f_layers = [(_to_lps(skin_crop), "fat"),
                        (_to_lps(_keep_faces(posed.muscle, crop[1])), "muscle")]
            posed.skin = posed.muscle = None      # the whole posed body (~14 MB) is not needed past here
            f_labels = []
            for name, bone in skeleton.bones.items():
                if bone.mesh is None:
                    continue
                T_model = posed.bone_to_world.get(name, bone.bone_to_world)
                # only the bones that can reach a forearm stack: the whole skeleton posed three times
                # was ~100 MB of copies that the renderer sectioned only to find nothing in the stack
                if not _may_reach_forearm_stack(spheres[name], T_model, posed.elbow, posed.wrist, cfg):
                    continue
                T = MODEL_TO_LPS @ T_model
                f_layers.append((bone.mesh.transformed(T, "lps"), "cortex"))
                if bone.inner_mesh is not None:
                    f_layers.append((bone.inner_mesh.transformed(T, "lps"), "marrow"))
                if name in posed.bone_to_world:
                    f_labels.append((bone.mesh.transformed(T, "lps"), bone_ids[name]))
            axis = np.stack([posed.elbow, posed.wrist]) @ MODEL_TO_LPS[:3, :3].T
            poses[_twist_name(theta)] = ForearmPose(f_layers, axis, skin=f_layers[0][0], label_meshes=f_labels)
            forearm_truth[_twist_name(theta)] = {
                "theta_deg": theta,
                "radioulnar_axis_lps": (posed.axis_ends @ MODEL_TO_LPS[:3, :3].T).tolist(),
                "bone_to_lps": {n: (MODEL_TO_LPS @ T).tolist() for n, T in posed.bone_to_world.items()},
            }
        stacks, placement = render_forearm_stacks(
            poses, out / "mri", forearm_rng, n_capsules=cfg["n_capsules"], pixel_mm=cfg["forearm_pixel_mm"],
            pitch_mm=cfg["forearm_pitch_mm"], thickness_mm=cfg["forearm_pitch_mm"],
            inplane_supersample=cfg["supersample"], through_plane_samples=cfg["through"],
            study_uid=study_uid, patient=patient, marker_capsules=forearm_marker_capsules)
        # the posed meshes of the three twists (~100 MB at the default preset) are not used again
        del poses, posed, f_layers, f_labels
        for name, st in stacks.items():
            forearm_truth[name]["folder"] = str(st.folder.relative_to(out))
            forearm_truth[name]["capsule_centres_lps"] = np.asarray(st.capsule_centres).tolist()
            forearm_truth[name]["marker_capsules_lps"] = {m: np.asarray(c).tolist() for m, c in st.marker_capsules.items()}
            forearm_truth[name]["stack"] = st.plan.to_dict()
            if st.labels is not None:
                write_nifti(st.labels, labels_dir / f"forearm_{name}_oracle.nii.gz")
                st.labels = None
        return forearm_truth, placement.radius_mm, sorted(stacks), time.perf_counter() - t

    if cfg["forearm_beside"]:
        forearm_job = run_beside(forearm_stage)
        children.append(forearm_job)

    capsule_truth = None
    if marker_capsules:
        capsule_truth = _marker_capsules(marker_set, skeleton, subject.skin)
        layers.extend((m, "oil") for m in capsule_meshes(np.array(list(capsule_truth["centres_lps"].values())),
                                                         capsule_truth["capsule_radius_mm"]))

    # 2. Whole-body stations.
    tidy()
    t0 = time.perf_counter()
    bar.set_postfix_str("stations")
    plans = plan_stations(layers[0][0], n_stations=cfg["n_stations"], pixel_mm=cfg["pixel_mm"],
                          pitch_mm=cfg["pitch_mm"], thickness_mm=cfg["thickness_mm"], rng=rng)

    def save_station_labels(st) -> None:
        write_nifti(st.labels, labels_dir / f"{st.plan.name}_oracle.nii.gz")

    stations = render_stations(layers, plans, out / "mri", rng, label_meshes=label_meshes,
                               merged_voxel_mm=None, inplane_supersample=cfg["supersample"],
                               through_plane_samples=cfg["through"], on_station=save_station_labels,
                               keep_labels=False, study_uid=study_uid, patient=patient)
    # streamed slab by slab: the whole-body grid (~140 MB at the default preset) is never held
    write_merged_labels(label_meshes, labels_dir / "merged.nii.gz", voxel_mm=cfg["merged_voxel_mm"],
                        inplane_supersample=cfg["supersample"], through_plane_samples=cfg["through"])
    # the LPS copies of the bones (render layers and labels, ~30 MB at the default preset) are
    # not used again, nor are the LPS skin and fascia (14 MB; the truth stage transforms them again)
    del label_meshes, layers
    timings["stations"] = time.perf_counter() - t0
    bar.update()

    # 3. The forearm stacks (beside the stations at the tiny preset).
    tidy()
    t0 = time.perf_counter()
    bar.set_postfix_str("forearm")
    if cfg["forearm_beside"]:
        forearm_truth, capsule_radius_mm, forearm_stacks, timings["forearm"] = forearm_job()
        timings["forearm_wait"] = time.perf_counter() - t0
    else:
        forearm_truth, capsule_radius_mm, forearm_stacks, timings["forearm"] = forearm_stage()
    bar.update()

    # 4. Trials (started beside the MRI above).
    tidy()
    t0 = time.perf_counter()
    bar.set_postfix_str("trials")
    trials, timings["trials"] = trials_job()
    timings["trials_wait"] = time.perf_counter() - t0
    bar.update()

    # 5. The rest of the truth.
    tidy()
    t0 = time.perf_counter()
    bar.set_postfix_str("truth")
    meshes_dir = truth / "meshes"
    for name in bone_ids:
        write_mesh(_to_lps(skeleton.world_mesh(name)), meshes_dir / f"{name}.ply")
    write_mesh(_to_lps(subject.skin), meshes_dir / "skin.ply")
    write_mesh(_to_lps(subject.muscle), meshes_dir / "muscle.ply")
    _write_json(truth / "labels.json", {"ids": bone_ids, "background": 0,
                                        "frame": "LPS (NIfTI files store RAS; readers convert)"})
    _write_json(truth / "stations.json", {"stations": [st.plan.to_dict() for st in stations.stations],
                                          "study_uid": stations.study_uid})
    _write_json(truth / "forearm.json", {"side": "r", "poses": forearm_truth,
                                         "capsule_radius_mm": capsule_radius_mm})
    _write_json(truth / "skeleton.json", _skeleton_truth(skeleton))
    if capsule_truth is not None:
        _write_json(truth / "marker_capsules.json", capsule_truth)
    _write_json(truth / "subject.json", _jsonable({"seed": seed, "generic": str(generic), "preset": preset,
                                                   "params": subject.params}))
    write_truth_readme(truth / "README.md")
    timings["truth"] = time.perf_counter() - t0
    bar.update()
    bar.close()

    summary = {
        "seed": seed, "generic": str(generic), "preset": preset,
        "stature_mm": float(subject.params.get("stature_mm", np.nan)),
        "bones": len(bone_ids),
        "stations": [{"name": st.plan.name, "shape": list(st.plan.shape),
                      "shift_mm": round(st.plan.shift_mm, 3), "rotation_deg": round(st.plan.rotation_deg, 4)}
                     for st in stations.stations],
        "forearm_stacks": forearm_stacks,
        "marker_capsules": len(capsule_truth["centres_lps"]) if capsule_truth else 0,
        "trials": sorted(trials.get("trials", {})) if isinstance(trials.get("trials"), dict) else trials.get(
            "trials"),
        "timings_s": {k: round(v, 2) for k, v in timings.items()},
        "wall_s": round(time.perf_counter() - t_start, 2),
        "out_dir": str(out),
    }
    _write_json(out / "phantom.json", _jsonable(summary))
    return summary


def run_beside(fn):
    """Start ``fn()`` in a forked child process; return a ``join()`` that gives its result.

    :func:`bonecap.parallel.fork_or_here` with ``beside=True``: where ``fork`` is
    missing, with one CPU, or with ``BONECAP_WORKERS=1``, ``fn`` runs here at once
    and ``join()`` returns its result. An error in the child is raised again by ``join()``.
    """
    from bonecap.parallel import fork_or_here

    return fork_or_here(fn, beside=True)


def _skeleton_truth(skeleton) -> dict[str, Any]:
    """Bones of the true skeleton at the MRI pose in LPS: parent, pose, joint centres, landmarks."""
    out = {}
    for name, b in skeleton.bones.items():
        T = MODEL_TO_LPS @ b.bone_to_world
        out[name] = {
            "parent": b.parent,
            "bone_to_lps": T.tolist(),
            "joint_centres_lps": {k: (T[:3, :3] @ v + T[:3, 3]).tolist() for k, v in b.joint_centres.items()},
            "landmarks_lps": {k: (T[:3, :3] @ v + T[:3, 3]).tolist() for k, v in b.landmarks.items()},
        }
    return {"frame": "LPS, mm, MRI pose", "bones": out}


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating, np.integer, np.bool_)):
        return obj.item()
    if isinstance(obj, (str, int, float, bool)) or obj is None:
        return obj
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, Volume):
        return {"shape": list(obj.shape)}
    return str(obj)


TRUTH_README = """\
# Phantom truth

Everything a stage of bonecap can be scored against. Lengths in mm, times in s.
Frames: **LPS** (the patient frame of the DICOM stacks in `../mri/`: +x left,
+y posterior, +z superior) for everything beside the MRI; the **Z-up lab** of
the C3D trials for the motion truth.

| file | content |
|---|---|
| `meshes/<bone>.ply` | each bone's outer surface at the MRI pose, LPS |
| `meshes/skin.ply`, `meshes/muscle.ply` | skin and fascia (inner boundary of the subcutaneous fat), LPS |
| `labels.json` | bone label ids (`ids`: bone -> id, 0 = background) |
| `labels/station_<k>_oracle.nii.gz` | the oracle: the truth meshes, moved as the body lay during that station, voxelised on the station's own acquisition grid (the best any segmentation can reach there); aligned voxel for voxel with `../mri/station_<k>` |
| `labels/merged.nii.gz` | bone labels of the unmoved truth on one common grid |
| `labels/forearm_<twist>_oracle.nii.gz` | oracle labels of the posed radius and hand bones (and the ulna) on each forearm stack's grid |
| `stations.json` | per station: the nominal `affine_voxel_to_lps` written in its DICOM header, `shape`, `slice_thickness_mm`, `true_to_nominal` (4x4, `p_nominal = T @ p_true`: where a point of the true body lay during that station; the body was imaged moved by it), `shift_mm`, `rotation_deg`, `intensity_scale` |
| `forearm.json` | per forearm twist: `theta_deg`, `radioulnar_axis_lps` (radial-head end, ulnar-head end), `bone_to_lps` of the bones that moved, `capsule_centres_lps` (all the stack's capsules: the random ones, then those at the forearm markers' spots), `marker_capsules_lps` (with `--marker-capsules`: marker name -> the centre of the capsule at its spot, for the markers on the ulna and the radius and the epicondyle markers the stack shows, carried with their bones; 3 mm nearer the skin than the trial's marker; left out where the wound skin would bury it), the stack's geometry; `capsule_radius_mm` |
| `skeleton.json` | the true skeleton at the MRI pose: per bone `parent`, `bone_to_lps`, `joint_centres_lps`, `landmarks_lps` |
| `subject.json` | seed, template, preset and every drawn parameter (stature, segment scales, femoral anteversion and neck angle, bowing, pelvis width, body shape) |
| `marker_binding.yaml` | the true marker -> bone binding: bone, position in the bone frame (mm), placement, soft-tissue-artefact class |
| `marker_capsules.json` | only with `--marker-capsules`: per trial marker the centre (LPS mm, MRI pose) of the oil capsule imaged under it in the stations, `capsule_radius_mm`, `marker_radius_mm` (the marker's centre is `marker_radius - capsule_radius` farther out along the skin normal) |
| `<trial>_poses.npz` | per trial, with the keys `bonecap animate` writes: `bones` (names), `times` (s from 0), `first_frame`, `transforms` (frames x bones x 4 x 4, bone frame -> lab, mm), `valid` (frames x bones); plus `markers`, `marker_truth` (markers without artefact or noise, lab mm), `sta` (the artefact added), `noise`, `gaps`, `joint_names`, `joint_centres` (frames x joints x 3, lab mm), joint angles, and for the pronation trial `forearm_twist_deg` |

Bone frames follow the template's (ISB for the embedded skeleton; the OpenSim
body frames for an `.osim` template).

The trials (`../trials/*.c3d`) carry in their `PROCESSING` group what a gait lab
measures with callipers and Nexus stores there: `LKNEEWIDTH`, `RKNEEWIDTH`,
`LANKLEWIDTH`, `RANKLEWIDTH` (the skin's width across
the joint along its true axis through its true centre, MRI pose, plus a calliper's
2 mm error, whole mm) and `MARKERDIAMETER`; an OpenSim template's MarkerSet names no
such widths and its trials carry none.
"""


def write_truth_readme(path: str | os.PathLike) -> Path:
    """Write the README that documents every truth file's format."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(TRUTH_README)
    return path
