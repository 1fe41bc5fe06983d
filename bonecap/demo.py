"""``bonecap demo``: every stage that exists, end to end, on the embedded default.

Stages run today:

1. **Template**: build the generic skeleton (or import ``--generic MODEL.osim``)
   and write its bone meshes (PLY, world frame) and a static glTF.
2. **Pictures**: front and side views of the skeleton.
3. **Markers**: place the template's marker set (Plug-in Gait for the default)
   on the bones and write them as CSV.
4. **Motion**: move the skeleton by a synthetic rigid motion in a Z-up lab
   (walking forward while turning), write the markers it carries as a C3D
   trial with 0.5 mm noise, read that trial back, recover the motion with the
   rigid-fit core, and export the recovered motion as an animated glTF.
5. **Phantom**: a synthetic subject (``bonecap phantom``; the whole body by
   default, ``preset="tiny"`` for a quick check): a varied skeleton and body,
   MRI stations and forearm stacks, trials, and their truth.
6. **build-subject** on the phantom's MRI stations, its static trial and its
   three forearm stacks, with its walk as the functional trial (the femurs'
   twist from the knees' flexion axis): the personal skeleton with bound markers.
7. **animate** the phantom's trials with that subject.
8. **evaluate** both against the phantom's truth.

Stages 6-8 need the phantom (skipped with ``phantom=False``).
"""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from bonecap.io.atomic import atomic_path
from bonecap.io.c3d import read_c3d, write_c3d
from bonecap.io.gltf import write_animated_glb, write_static_glb
from bonecap.io.mesh import write_mesh
from bonecap.markers import place_markers
from bonecap.model import Motion, Trial
from bonecap.motion.rigid import fit_rigid, rotation_angle_deg
from bonecap.progress import stage_bar
from bonecap.skeleton.template import MODEL_TO_LAB_ZUP, load_template, template_marker_set

__all__ = ["run_demo", "synthetic_walk"]


def synthetic_walk(n_frames: int = 200, rate: float = 100.0) -> np.ndarray:
    """A whole-body rigid motion: ``template_world_to_lab`` transforms (F, 4, 4).

    The body walks 1.2 m/s along the lab's +X, turns 45 degrees to its left
    about the vertical and bobs 20 mm up and down twice a second; the template's
    Y-up world is first turned into the Z-up lab (:data:`MODEL_TO_LAB_ZUP`).
    """
    t = np.arange(n_frames) / rate
    yaw = np.deg2rad(45.0) * t / max(t[-1], 1e-9)
    G = np.tile(np.eye(4), (n_frames, 1, 1))
    G[:, :3, :3] = Rotation.from_euler("z", yaw[:, None]).as_matrix()
    G[:, :3, 3] = np.stack([1200.0 * t, np.zeros_like(t), 20.0 * np.sin(2 * np.pi * 2.0 * t)], axis=1)
    return G @ MODEL_TO_LAB_ZUP


def _write_csv(path: Path, rows: list[list[Any]], header: list[str]) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="") as fh:
            writer = csv.writer(fh)
            writer.writerow(header)
            writer.writerows(rows)


def run_demo(out_dir: str | os.PathLike, generic: str | os.PathLike = "default", *, n_frames: int = 200,
             rate: float = 100.0, seed: int = 0, phantom: bool = True, preset: str = "default"
             ) -> dict[str, Any]:
    """Run every stage that exists on the template and write the results under ``out_dir``.

    Parameters
    ----------
    out_dir : path-like
        Output folder (created).
    generic : str or path-like
        ``"default"`` or an OpenSim ``.osim`` model.
    n_frames, rate : int, float
        Length and rate of the synthetic trial.
    seed : int
        Seed of the marker noise and of the phantom.
    phantom : bool
        Also make the phantom subject (stage 5) and build, animate and evaluate it (6-8).
    preset : {"default", "tiny"}
        The phantom's preset (:func:`bonecap.phantom.make_phantom`): the whole body, 8 MRI
        stations (what the issue's targets are measured on; a few minutes on two cores), or the
        reduced one the tests use (2 coarse stations: too little of the body for the template's
        placement, so its personal skeleton is the template placed, not warped, and scores so).

    Returns
    -------
    dict
        The report, also written as ``out_dir/report.json``: what was made,
        where, and the figures measured on it.
    """
    out = Path(out_dir)
    report: dict[str, Any] = {"generic": str(generic), "outputs": {}}
    bar = stage_bar(8 if phantom else 5, "demo")

    # 1. Template and its meshes.
    bar.set_postfix_str("template")
    skeleton = load_template(generic)
    meshes_dir = out / "skeleton" / "meshes"
    with_mesh = [n for n, b in skeleton.bones.items() if b.mesh is not None and len(b.mesh.faces)]
    for name in with_mesh:
        write_mesh(skeleton.world_mesh(name), meshes_dir / f"{name}.ply")
    glb = out / "skeleton" / "skeleton.glb"
    write_static_glb(glb, {n: skeleton.bones[n].mesh for n in with_mesh},
                     {n: skeleton.bones[n].bone_to_world for n in with_mesh}, lab_up="y")
    report["skeleton"] = {
        "bones": len(skeleton.bones), "bones_with_mesh": len(with_mesh),
        "triangles": int(sum(len(skeleton.bones[n].mesh.faces) for n in with_mesh)),
        "world_frame": skeleton.world,
    }
    report["outputs"]["bone_meshes"] = str(meshes_dir)
    report["outputs"]["skeleton_glb"] = str(glb)

    # 2. Pictures.
    bar.update()
    bar.set_postfix_str("pictures")
    from bonecap.skeleton.generic import render_skeleton_views

    pictures = render_skeleton_views(skeleton, out / "skeleton")
    report["outputs"]["pictures"] = [str(p) for p in pictures]

    # 3. Markers on the template.
    bar.update()
    bar.set_postfix_str("markers")
    marker_set = template_marker_set(generic)
    names = marker_set.physical
    placed = place_markers(marker_set, skeleton, names)
    markers_csv = out / "markers" / f"{marker_set.name}.csv"
    _write_csv(markers_csv, [[n, marker_set.markers[n].bone, *np.round(placed[n], 3)] for n in names],
               ["marker", "bone", "x_mm", "y_mm", "z_mm"])
    report["markers"] = {"set": marker_set.name, "placed": len(names)}
    report["outputs"]["markers_csv"] = str(markers_csv)

    # 4. A synthetic trial, written as C3D, read back and solved.
    bar.update()
    bar.set_postfix_str("motion")
    world_to_lab = synthetic_walk(n_frames, rate)
    local = np.array([placed[n] for n in names])  # template world, mm
    truth = local @ world_to_lab[:, :3, :3].transpose(0, 2, 1) + world_to_lab[:, None, :3, 3]
    rng = np.random.default_rng(seed)
    measured = truth + rng.normal(scale=0.5, size=truth.shape)
    trial_path = out / "motion" / "demo_walk.c3d"
    write_c3d(Trial(names, measured, rate, prefixes=["Demo"] * len(names)), trial_path)
    trial = read_c3d(trial_path)
    order = [trial.labels.index(n) for n in names]
    fit = fit_rigid(local, trial.points[:, order])
    rot_err = rotation_angle_deg(fit.transforms, world_to_lab)
    pos_err = np.linalg.norm(fit.transforms[:, :3, 3] - world_to_lab[:, :3, 3], axis=1)
    bone_names = with_mesh
    rest = np.stack([skeleton.bones[n].bone_to_world for n in bone_names])
    motion = Motion(bone_names, trial.times, fit.transforms[:, None] @ rest[None],
                    marker_labels=names, residuals=fit.residuals)
    anim = out / "motion" / "demo_walk.glb"
    write_animated_glb(anim, {n: skeleton.bones[n].mesh for n in bone_names}, motion)
    report["motion"] = {
        "frames": trial.n_frames, "rate_hz": trial.rate, "markers": len(names),
        "rotation_error_deg_max": float(np.max(rot_err)),
        "origin_error_mm_max": float(np.max(pos_err)),
        "marker_residual_mm_rms": float(np.sqrt(np.nanmean(fit.residuals ** 2))),
    }
    report["outputs"]["trial_c3d"] = str(trial_path)
    report["outputs"]["animation_glb"] = str(anim)

    # 5. A phantom subject with its truth.
    bar.update()
    bar.set_postfix_str("phantom")
    if phantom:
        from bonecap.phantom import make_phantom

        ph = make_phantom(out / "phantom", seed=seed, generic=generic, preset=preset)
        report["phantom"] = {"seed": ph["seed"], "preset": ph["preset"], "stature_mm": ph["stature_mm"],
                             "stations": len(ph["stations"]), "forearm_stacks": ph["forearm_stacks"],
                             "trials": ph["trials"], "seconds": round(sum(ph["timings_s"].values()), 1)}
        report["outputs"]["phantom"] = str(out / "phantom")
    bar.update()
    if phantom:
        _subject_and_motion(out, report, bar)
    bar.close()
    with atomic_path(out / "report.json") as tmp:
        tmp.write_text(json.dumps(report, indent=2))
    report["outputs"]["report"] = str(out / "report.json")
    return report


def _subject_and_motion(out: Path, report: dict[str, Any], bar) -> None:
    """Stages 6-8: build-subject, animate and evaluate on the demo phantom."""
    import time

    from bonecap.animate import animate
    from bonecap.build_subject import run_build_subject
    from bonecap.evaluate import evaluate_motion, evaluate_subject

    ph = out / "phantom"
    bar.set_postfix_str("build-subject")
    t0 = time.perf_counter()
    stations = sorted(str(p) for p in (ph / "mri").glob("station_*"))
    forearm = sorted((str(p) for p in (ph / "mri").glob("forearm_*")), key=lambda x: float(x.rsplit("_", 1)[1]))
    # the walk's knees correct the femurs' twist in the static binding (build-subject --functional)
    walk = ph / "trials" / "walk.c3d"
    built = run_build_subject(stations, out / "subject", static=ph / "trials" / "static.c3d",
                              forearm_poses=forearm, functional=[str(walk)] if walk.exists() else None)
    report["subject"] = {"bones": built["bones"], "markers_bound": built["markers_bound"],
                         "extracted_bones": len(built["extracted_bones"]),
                         "femurs_turned_deg": built.get("functional_femur_turned_deg"),
                         "forearm_twists_deg": (built.get("forearm") or {}).get("twists_deg"),
                         "seconds": round(time.perf_counter() - t0, 1)}
    report["outputs"]["subject"] = str(out / "subject")
    bar.update()
    bar.set_postfix_str("animate")
    trials = sorted(str(p) for p in (ph / "trials").glob("*.c3d"))
    anim = animate(out / "subject", trials, out / "animate")
    report["animate"] = {t: {"frames": r["frames"], "valid_share": round(r["valid_share"], 3),
                             "residual_median_mm": r["residual_median_mm"]} for t, r in anim["trials"].items()}
    report["outputs"]["animate"] = str(out / "animate")
    bar.update()
    bar.set_postfix_str("evaluate")
    ev_s = evaluate_subject(out / "subject", ph / "truth")
    ev_m = evaluate_motion(out / "animate", ph / "truth")
    deg = [v["deg_median"] for v in ev_m["overall"].values()]
    # the slice rules' long bones (the cortical rule): the summary's Dice is the median over every bone,
    # and most of the 90 (ribs, vertebrae, hands, feet) are not segmented at whole-body resolution
    from bonecap.segmentation.bones import default_rule

    long_dice = [r["dice"] for b, r in ev_s["bones"].items()
                 if default_rule(b) == "cortical" and np.isfinite(r.get("dice", np.nan))]
    # the density rule's bones that the build refined from the personal map (hips, sacrum, vertebrae, scapulae,
    # patellae)
    refined = json.loads((out / "subject" / "stations.json").read_text()).get("refined_bones", [])
    rows = [ev_s["bones"][b] for b in refined if np.isfinite(ev_s["bones"].get(b, {}).get("refined_dice", np.nan))]
    report["evaluation"] = {"subject": {**ev_s["summary"],
                                        "long_bone_dice_median": float(np.median(long_dice)) if long_dice else None,
                                        "refined_bones_dice_median": {
                                            k: float(np.median([r[k] for r in rows])) if rows else None
                                            for k in ("dice", "personal_dice", "refined_dice")}},
                            "motion": {"bones": len(deg), "deg_median_over_bones": float(np.median(deg)),
                                       "mm_median_over_bones": float(np.median(
                                           [v["mm_median"] for v in ev_m["overall"].values()]))}}
    bar.update()


def format_report(report: dict[str, Any]) -> str:
    """A few lines saying what the demo made and where."""
    s, m, mo = report["skeleton"], report["markers"], report["motion"]
    o = report["outputs"]
    lines = [
        f"template ({report['generic']}): {s['bones']} bones, {s['triangles']} triangles",
        f"  bone meshes (PLY, {s['world_frame']} frame): {o['bone_meshes']}",
        f"  skeleton glTF: {o['skeleton_glb']}",
        f"  pictures: {', '.join(o['pictures'])}",
        f"markers ({m['set']}): {m['placed']} placed -> {o['markers_csv']}",
        f"synthetic walk: {mo['frames']} frames at {mo['rate_hz']:g} Hz -> {o['trial_c3d']}",
        f"  recovered by the rigid fit: rotation error <= {mo['rotation_error_deg_max']:.3f} deg, "
        f"origin error <= {mo['origin_error_mm_max']:.2f} mm, marker residual RMS "
        f"{mo['marker_residual_mm_rms']:.2f} mm",
        f"  animated bones: {o['animation_glb']}",
    ]
    if "phantom" in report:
        p = report["phantom"]
        lines.append(f"phantom (seed {p['seed']}, {p['preset']}): stature {p['stature_mm']:.0f} mm, "
                     f"{p['stations']} MRI stations, forearm stacks at {', '.join(p['forearm_stacks'])} deg, "
                     f"trials {', '.join(p['trials'])} -> {o['phantom']} ({p['seconds']} s)")
    if "subject" in report:
        sb, ev = report["subject"], report["evaluation"]
        lines.append(f"build-subject: {sb['bones']} bones ({sb['extracted_bones']} extracted from the MRI), "
                     f"{sb['markers_bound']} markers bound -> {o['subject']} ({sb['seconds']} s)")
        lines.append(f"animate: {', '.join(report['animate'])} -> {o['animate']}")
        es, em = ev["subject"], ev["motion"]
        rb = es.get("refined_bones_dice_median") or {}
        fmt = lambda v: "n/a" if v is None else f"{v:.2f}"  # noqa: E731
        lines.append(f"evaluate vs truth: long-bone Dice median {fmt(es.get('long_bone_dice_median'))} "
                     f"(all bones' {fmt(es.get('dice'))}, as the personal skeleton's label maps "
                     f"{fmt(es.get('personal_dice'))}, oracle {fmt(es.get('oracle_dice'))}; the density rule's "
                     f"bones {fmt(rb.get('dice'))}, refined {fmt(rb.get('refined_dice'))}), "
                     f"personal surface {fmt(es.get('personal_surface_mean_mm'))} mm, "
                     f"bone orientation median {em['deg_median_over_bones']:.2f} deg, "
                     f"origin {em['mm_median_over_bones']:.1f} mm")
    lines.append(f"report: {o['report']}")
    return "\n".join(lines)
