"""``bonecap animate``: C3D trials → each bone's pose per frame → glTF, NPZ, CSV, PNG, C3D.

For each trial the subject's bound markers are matched to the trial's labels
(names and the marker set's aliases), optionally low-pass filtered, and solved
by the joint-coupled least-squares solver (:mod:`bonecap.motion.lsq`) — the
radius and ulna by the forearm pronation model (:mod:`bonecap.motion.forearm`)
unless ``forearm=False``. What the trial lacks is reported, solved where it
can be (a bone without markers leans on its joints) and flagged invalid where
it cannot.

Outputs per trial (``<trial>`` is the C3D file's stem)
------------------------------------------------------
``<trial>.glb``
    The subject's bone meshes animated at the trial rate (glTF 2.0, TRS
    channels; the lab turned Y-up by the root node).
``<trial>_poses.npz``
    ``bones`` (names), ``times`` (s from 0), ``first_frame``, ``transforms``
    (frames x bones x 4 x 4, bone frame → lab, mm, NaN where invalid),
    ``valid``, ``markers`` (names), ``residuals`` (frames x markers, mm).
``<trial>_angles.csv``
    Joint angles in degrees, one row per frame: for every joint, the child's
    ISB frame relative to its parent's decomposed as an intrinsic Z-X-Y Cardan
    sequence (Grood & Suntay / ISB: flexion–extension about the parent's Z,
    ab/adduction about the floating X, axial rotation about the child's Y).
    Left-side adduction and rotation are negated so that the same anatomical
    motion has the same sign on both sides (the left ISB frames here are
    right-handed with Z to the right, as OpenSim's). The knee's flexion (the
    tibia on the femur) is negated too: a right-handed turn about Z carries
    the shank forward, and Grood & Suntay, ISB and Plug-in Gait all count knee
    flexion positive (on the pyCGM movement trial the raw angle ran against
    Vicon's knee flexion, correlation -0.98). Angles are absolute (not
    relative to the static pose), as Plug-in Gait reports them.
``<trial>_residuals.png``
    Marker residuals over the trial.
``<trial>_bonecap.c3d``
    A copy of the trial with the virtual joint centres (``POINT:MODELED_MARKERS``,
    named ``<child bone>_jc``) and the joint angles (``POINT:ANGLES``, named
    ``<child bone>_angles``, degrees) written back, for Nexus and Visual3D users.
"""

from __future__ import annotations

import csv
import os
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from bonecap.errors import DataError, InputError
from bonecap.io.atomic import atomic_path
from bonecap.io.c3d import read_c3d, write_c3d
from bonecap.io.gltf import write_animated_glb
from bonecap.markers import load_marker_set, match_labels
from bonecap.model import Motion, Skeleton, Trial
from bonecap.subject import Subject, read_subject

__all__ = ["trial_markers", "solve_trial", "joint_angles", "joint_centres", "markers_off_their_bones",
           "write_outputs", "animate"]


def trial_markers(subject: Subject, trial: Trial, *, path: str | os.PathLike | None = None
                  ) -> tuple[list[str], np.ndarray, list[str]]:
    """The subject's markers in a trial.

    Returns
    -------
    names : list of str
        Subject marker names found in the trial (and seen at least once).
    measured : ndarray (F, M, 3)
        Their positions, lab mm, NaN in gaps.
    missing : list of str
        Subject markers the trial lacks or never sees.

    Raises
    ------
    DataError
        The trial has no points, or none of the subject's markers.
    """
    if trial.points.shape[1] == 0:
        raise DataError("the trial holds no marker points", path)
    try:
        mset = load_marker_set(subject.marker_set) if subject.marker_set else None
    except InputError:
        mset = None
    if mset is not None:
        found = match_labels(mset, trial.labels)
    else:
        found = {}
    key = {lab.replace(" ", "").lower(): lab for lab in trial.labels}
    names, cols, missing = [], [], []
    for n in subject.markers:
        lab = found.get(n) or key.get(n.replace(" ", "").lower())
        if lab is None:
            missing.append(n)
            continue
        j = trial.labels.index(lab)
        if not np.isfinite(trial.points[:, j]).all(axis=1).any():
            missing.append(n)
            continue
        names.append(n)
        cols.append(j)
    if not names:
        raise DataError(f"none of the subject's {len(subject.markers)} markers is in the trial "
                        f"(it has {', '.join(trial.labels[:10])}{'...' if len(trial.labels) > 10 else ''})", path)
    return names, trial.points[:, cols], missing


def forearm_models(subject: Subject) -> dict[str, Any]:
    """The subject's forearm model per side: fitted from its forearm stacks, else the paper's.

    A side without stacks takes the other side's fitted model when there is one (the paper imaged one
    forearm): its coefficients are side-free (the twist and the turns are positive in pronation on both
    arms, the control points on segments whose radial-side marker is +1), and the subject's own forearm
    mirrored is nearer than the paper's subject. On the phantom (seed 1, left forearm, no stacks):
    radius_l 11.7 deg with the paper's coefficients, 5.4 deg with the right arm's fit.
    """
    from dataclasses import replace

    from bonecap.motion.forearm import PAPER_MODEL, ForearmModel

    fitted = {side: ForearmModel.from_dict(d) for side, d in (subject.forearm or {}).items() if d}
    out = {}
    for side, other in (("r", "l"), ("l", "r")):
        if side in fitted:
            out[side] = fitted[side]
        elif other in fitted:
            # the coefficients are side-free; the radius's axis measured in the other ulna's frame is not
            out[side] = replace(fitted[other], radius_axis_ulna_mm=())
        else:
            out[side] = PAPER_MODEL
    return out


def solve_trial(subject: Subject, names: list[str], measured: np.ndarray, *, rate: float,
                solver: str = "lsq", forearm: bool = True, max_gap_frames: int = 10,
                lowpass_hz: float | None = None) -> Motion:
    """Solve one trial's bone poses (lab frame of the trial, mm)."""
    from bonecap.motion import lsq

    if lowpass_hz:
        measured = lsq.lowpass_markers(measured, rate, lowpass_hz)
    _, bones, local = subject.marker_arrays(names)
    weights = np.array([subject.markers[n].weight for n in names])
    model = forearm_models(subject) if forearm else None
    if solver == "lsq":
        motion = lsq.solve_lsq(subject.skeleton, bones, local, measured, weights=weights,
                               max_gap_frames=max_gap_frames, forearm=model, marker_labels=names, rate_hz=rate,
                               rhythm=subject.follows_rhythm())
    elif solver == "paper":
        from bonecap.motion.paper_solver import solve_paper

        motion = solve_paper(subject, names, measured, max_gap_frames=max_gap_frames, forearm=model,
                             rate_hz=rate)
    else:
        raise ValueError(f"solver must be 'lsq' or 'paper', got {solver!r}")
    motion.marker_labels = list(names)
    motion.valid = flag_unsupported(subject.skeleton, motion, bones, measured, max_gap_frames)
    motion.transforms[~motion.valid] = np.nan
    # the kneecaps no marker holds lag the knee's flexion (both solvers carry them on the femur); where
    # the tibia is lost, so is the knee's angle and the kneecap with it
    from bonecap.motion.patella import patella_from_knee

    motion.transforms = patella_from_knee(subject.skeleton, motion.bones, motion.transforms, bones)
    motion.valid &= np.isfinite(motion.transforms).all(axis=(2, 3))
    return motion


#: A marker whose median distance from where its solved bone puts it exceeds this (mm) is reported
#: (:func:`markers_off_their_bones`): soft-tissue artefact moves skin markers by up to ~10-15 mm
#: (thigh; Peters et al. 2010), so twice that is more than the skin.
MARKER_OFF_MM = 20.0


def markers_off_their_bones(marker_bones: Sequence[str], marker_local: np.ndarray, measured: np.ndarray,
                            motion: Motion, *, threshold_mm: float = MARKER_OFF_MM) -> dict[str, dict[str, Any]]:
    """Markers that stay far from where their solved bones put them through a trial.

    For each marker the residual ``measured - bone_to_lab @ local`` is taken in
    its bone's frame, frame by frame. A marker whose median distance exceeds
    ``threshold_mm`` is reported with the length of the median residual vector
    (the part that is constant in the bone's frame) and the median distance of
    the residuals from it (the part that varies): a large constant part means
    the static's binding does not hold in this trial -- the marker was moved or
    re-applied, is mislabelled, or the model cannot put its bone where its
    markers are (a real walk's arm markers sat 16-37 mm off, varying by 1-3 mm,
    from shoulders that the model's girdle could not lower); a large varying
    part, a marker that wobbles or swaps.

    Parameters
    ----------
    marker_bones : sequence of str
        Each marker's bone (one of ``motion.bones``).
    marker_local : ndarray (M, 3)
        Each marker in its bone's frame (mm).
    measured : ndarray (F, M, 3)
        The trial's markers (lab, mm; NaN where missing).
    motion : Motion
        The solved poses (``bone_to_lab``, NaN where invalid); ``marker_labels`` names the markers.
    threshold_mm : float
        Report markers whose median distance exceeds this.

    Returns
    -------
    dict
        Marker name -> ``{"bone", "median_mm", "constant_mm", "varying_mm", "frames"}``, worst first.
    """
    if not np.isfinite(threshold_mm) or threshold_mm < 0:
        raise ValueError(f"threshold_mm must be a non-negative number, got {threshold_mm!r}")
    meas = np.asarray(measured, float)
    local = np.asarray(marker_local, float)
    if meas.ndim != 3 or meas.shape[1:] != (len(marker_bones), 3) or local.shape != (len(marker_bones), 3):
        raise ValueError(f"measured must be (frames, {len(marker_bones)}, 3) and marker_local "
                         f"({len(marker_bones)}, 3), got {meas.shape} and {local.shape}")
    labels = list(motion.marker_labels or [f"marker_{i}" for i in range(len(marker_bones))])
    index = {b: i for i, b in enumerate(motion.bones)}
    unknown = sorted(set(marker_bones) - set(index))
    if unknown:
        raise ValueError(f"markers are bound to bones the motion does not have: {unknown}")
    out: dict[str, dict[str, Any]] = {}
    for m, (bone, p) in enumerate(zip(marker_bones, local)):
        T = motion.transforms[: len(meas), index[bone]]
        # the residual in the bone's frame: R^T (measured - (R p + t))
        v = np.einsum("fji,fj->fi", T[:, :3, :3], meas[:, m] - (T[:, :3, :3] @ p + T[:, :3, 3]))
        ok = np.isfinite(v).all(axis=1)
        if not ok.any():
            continue
        d = np.linalg.norm(v[ok], axis=1)
        if np.median(d) <= threshold_mm:
            continue
        c = np.median(v[ok], axis=0)
        out[labels[m]] = {"bone": bone, "median_mm": round(float(np.median(d)), 1),
                          "constant_mm": round(float(np.linalg.norm(c)), 1),
                          "varying_mm": round(float(np.median(np.linalg.norm(v[ok] - c, axis=1))), 1),
                          "frames": int(ok.sum())}
    return dict(sorted(out.items(), key=lambda kv: -kv[1]["median_mm"]))


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) of the runs of True in a 1-D mask."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)))


def flag_unsupported(skeleton: Skeleton, motion: Motion, marker_bones: list[str], measured: np.ndarray,
                     max_gap_frames: int) -> np.ndarray:
    """Invalidate bones whose pose rests on markers that are missing for longer than ``max_gap_frames``.

    A bone that loses markers so that fewer than two of its own remain is
    held only by its joints; over a short gap that is a fair guess (and the
    solver interpolates), over a long one it is not a measurement. Such runs
    longer than ``max_gap_frames`` are flagged, and so are the same frames of
    its descendants that carry fewer than three markers of their own (their
    pose hangs on the flagged joint).

    Returns
    -------
    ndarray of bool (F, B)
        The new ``valid``.
    """
    valid = motion.valid.copy()
    seen = np.isfinite(measured).all(axis=2)  # (F, M)
    mb = np.asarray(marker_bones)
    index = {b: i for i, b in enumerate(motion.bones)}
    lost = np.zeros_like(valid)
    for b, i in index.items():
        cols = np.flatnonzero(mb == b)
        if len(cols) == 0:
            continue
        n_seen = seen[:, cols].sum(axis=1)
        weak = (n_seen < len(cols)) & (n_seen < 2)
        if not weak.any():
            continue
        for a, z in _runs(weak):
            if z - a > max_gap_frames:
                lost[a:z, i] = True
    counts = {b: int((mb == b).sum()) for b in index}
    for name in skeleton.names:  # parent first: a lost parent makes weak children lost
        bone = skeleton.bones[name]
        if name in index and bone.parent in index and counts.get(name, 0) < 3:
            lost[:, index[name]] |= lost[:, index[bone.parent]]
    valid &= ~lost
    return valid


def _joints(skeleton: Skeleton) -> list[tuple[str, str, str, np.ndarray]]:
    """(child, parent, joint name, centre in child frame) for every coupled joint."""
    from bonecap.skeleton.kinematics import proximal_joint

    out = []
    for name, b in skeleton.bones.items():
        if b.parent is None:
            continue
        try:
            j, _, c = proximal_joint(skeleton, name)
        except ValueError:
            continue
        out.append((name, b.parent, j, c))
    return out


def joint_centres(skeleton: Skeleton, motion: Motion) -> dict[str, np.ndarray]:
    """Each joint centre in the lab per frame ``(F, 3)``, keyed ``<child bone>_jc``."""
    index = {n: i for i, n in enumerate(motion.bones)}
    out = {}
    for child, _, _, c in _joints(skeleton):
        if child in index:
            T = motion.transforms[:, index[child]]
            out[f"{child}_jc"] = T[:, :3, :3] @ c + T[:, :3, 3]
    return out


def _is_left(name: str) -> bool:
    return name.endswith("_l") or name.lower().startswith("l_") or name.endswith("_L")


def _is_knee(child: str, parent: str) -> bool:
    """The tibia on the femur (embedded skeleton and OpenSim models name them so)."""
    return child.lower().startswith("tibia") and parent.lower().startswith("femur")


def joint_angles(skeleton: Skeleton, motion: Motion) -> dict[str, np.ndarray]:
    """Joint angles in degrees ``(F, 3)`` = (flexion Z, adduction X, rotation Y), keyed by child bone.

    See the module docstring for the convention.
    """
    from scipy.spatial.transform import Rotation

    index = {n: i for i, n in enumerate(motion.bones)}
    out = {}
    for child, parent, _, _ in _joints(skeleton):
        if child not in index or parent not in index:
            continue
        Rp = motion.transforms[:, index[parent], :3, :3]
        Rc = motion.transforms[:, index[child], :3, :3]
        rel = np.swapaxes(Rp, 1, 2) @ Rc
        ok = np.isfinite(rel).all(axis=(1, 2))
        ang = np.full((len(rel), 3), np.nan)
        if ok.any():
            # intrinsic Z, then X, then Y (capitals = intrinsic in scipy)
            ang[ok] = Rotation.from_matrix(rel[ok]).as_euler("ZXY", degrees=True)
        if _is_left(child):
            ang[:, 1:] *= -1
        if _is_knee(child, parent):
            ang[:, 0] *= -1              # flexion positive (module docstring)
        out[child] = ang
    return out


def _write_angles_csv(path: Path, times: np.ndarray, angles: dict[str, np.ndarray]) -> None:
    header = ["time_s"] + [f"{b}_{c}_deg" for b in angles for c in ("flexion", "adduction", "rotation")]
    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(header)
            cols = [times[:, None]] + [a for a in angles.values()]
            for row in np.hstack(cols):
                w.writerow(["" if not np.isfinite(v) else f"{v:.4f}" for v in row])


def _residual_png(path: Path, motion: Motion, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    res = motion.residuals
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5), gridspec_kw={"width_ratios": [3, 2]})
    im = axes[0].imshow(res.T, aspect="auto", interpolation="nearest", cmap="magma",
                        extent=[motion.times[0], motion.times[-1] if len(motion.times) > 1 else 1, len(res.T), 0],
                        vmin=0, vmax=max(5.0, float(np.nanpercentile(res, 99)) if np.isfinite(res).any() else 5))
    axes[0].set_yticks(np.arange(len(motion.marker_labels)) + 0.5)
    axes[0].set_yticklabels(motion.marker_labels, fontsize=5)
    axes[0].set_xlabel("time (s)")
    axes[0].set_title("marker residual (mm); blank = gap")
    fig.colorbar(im, ax=axes[0])
    med = np.nanmedian(res, axis=0) if np.isfinite(res).any() else np.zeros(res.shape[1])
    order = np.argsort(np.nan_to_num(med))[::-1][:25]
    axes[1].barh([motion.marker_labels[i] for i in order][::-1], np.nan_to_num(med[order])[::-1])
    axes[1].set_xlabel("median residual (mm)")
    axes[1].tick_params(axis="y", labelsize=6)
    fig.suptitle(title)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def write_outputs(out_dir: Path, stem: str, subject: Subject, trial: Trial, motion: Motion) -> dict[str, str]:
    """Write every per-trial output (see the module docstring); returns name → path."""
    out_dir.mkdir(parents=True, exist_ok=True)
    sk = subject.skeleton
    paths = {}
    meshes = {n: sk.bones[n].mesh for n in motion.bones if sk.bones[n].mesh is not None}
    paths["glb"] = out_dir / f"{stem}.glb"
    write_animated_glb(paths["glb"], meshes, motion, lab_up="z")
    paths["poses"] = out_dir / f"{stem}_poses.npz"
    with atomic_path(paths["poses"]) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, bones=np.array(motion.bones), times=motion.times,
                                first_frame=np.int64(motion.first_frame), transforms=motion.transforms,
                                valid=motion.valid, markers=np.array(motion.marker_labels),
                                residuals=motion.residuals,
                                **{k: np.asarray(v, bool) for k, v in motion.flags.items()})
    angles = joint_angles(sk, motion)
    paths["angles"] = out_dir / f"{stem}_angles.csv"
    _write_angles_csv(paths["angles"], motion.times, angles)
    paths["residuals_png"] = out_dir / f"{stem}_residuals.png"
    _residual_png(paths["residuals_png"], motion, stem)
    # The trial written back with what we computed, for Nexus / Visual3D users.
    other = dict(trial.other_points)
    groups = dict(trial.other_point_groups)
    for k, v in joint_centres(sk, motion).items():
        other[k], groups[k] = v, "MODELED_MARKERS"
    for k, v in angles.items():
        other[f"{k}_angles"], groups[f"{k}_angles"] = v, "ANGLES"
    copy = Trial(trial.labels, trial.points, trial.rate, trial.first_frame, prefixes=trial.prefixes,
                 other_points=other, other_point_groups=groups, analog_labels=trial.analog_labels,
                 analogs=trial.analogs, analog_rate=trial.analog_rate, events=trial.events,
                 subject_parameters=trial.subject_parameters)
    paths["c3d"] = out_dir / f"{stem}_bonecap.c3d"
    write_c3d(copy, paths["c3d"])
    return {k: str(v) for k, v in paths.items()}


def animate(subject_dir: str | os.PathLike, trials: Sequence[str | os.PathLike], out_dir: str | os.PathLike, *,
            solver: str = "lsq", forearm: bool = True, max_gap_frames: int = 10,
            lowpass_hz: float | None = None, subject_name: str | None = None) -> dict[str, Any]:
    """Animate a subject from one or more C3D trials; see the module docstring.

    Every trial is read and matched before anything is solved or written, so
    a bad trial stops the run with nothing written.

    Returns
    -------
    dict
        Per trial: frames, rate, markers used and missing, bones valid share,
        residual median, the markers far from their bones
        (:func:`markers_off_their_bones`), seconds, and the output paths; once, the seconds
        spent loading the solver's compiled code before the first trial
        (``compiled_code_load_seconds``, :func:`bonecap.motion._qcp.warm_up`). Also written as
        ``OUT_DIR/animate_report.json``.
    """
    import json

    from bonecap.progress import progress

    if solver not in ("lsq", "paper"):
        raise ValueError(f"solver must be 'lsq' or 'paper', got {solver!r}")
    subject = read_subject(subject_dir)
    loaded = []
    for path in trials:
        trial = read_c3d(path, subject=subject_name)
        names, measured, missing = trial_markers(subject, trial, path=path)
        loaded.append((Path(path), trial, names, measured, missing))
    out = Path(out_dir)
    # the scapulae turn on their clavicles with the arms for a subject built from MRI (Subject.follows_rhythm)
    report: dict[str, Any] = {"subject": str(subject_dir), "solver": solver, "forearm_model": forearm,
                              "girdle_rhythm": subject.follows_rhythm(), "trials": {}}
    # the solver's compiled kernels loaded once (compiled, the first time after an install) before the
    # trials are timed: a trial's solve_seconds is its own solve
    t0 = time.perf_counter()
    from bonecap.motion._qcp import warm_up

    warm_up()
    report["compiled_code_load_seconds"] = round(time.perf_counter() - t0, 3)
    for path, trial, names, measured, missing in progress(loaded, "animate", unit="trial"):
        t0 = time.perf_counter()
        motion = solve_trial(subject, names, measured, rate=trial.rate, solver=solver, forearm=forearm,
                             max_gap_frames=max_gap_frames, lowpass_hz=lowpass_hz)
        motion.first_frame = int(trial.first_frame)
        t_solve = time.perf_counter() - t0
        paths = write_outputs(out, path.stem, subject, trial, motion)
        _, bones_m, local_m = subject.marker_arrays(names)
        off = markers_off_their_bones(bones_m, local_m, measured, motion)
        report["trials"][path.stem] = {
            "source": str(path), "frames": trial.n_frames, "rate_hz": trial.rate,
            "markers_used": len(names), "markers_missing": missing,
            "bones": len(motion.bones),
            "valid_share": float(motion.valid.mean()),
            "flags": {k: {motion.bones[i]: int(n) for i, n in enumerate(np.asarray(v).sum(axis=0)) if n}
                      for k, v in motion.flags.items()},
            "residual_median_mm": float(np.nanmedian(motion.residuals)) if np.isfinite(motion.residuals).any()
            else None,
            "markers_off_their_bones": off,
            "solve_seconds": round(t_solve, 3),
            "frames_per_second": round(trial.n_frames / max(t_solve, 1e-9), 1),
            "outputs": paths,
        }
    with atomic_path(out / "animate_report.json") as tmp:
        tmp.write_text(json.dumps(report, indent=2))
    return report


def format_report(report: dict[str, Any]) -> str:
    """A few lines per trial: frames, markers, validity, residuals, where the outputs are."""
    lines = []
    for stem, r in report["trials"].items():
        res = "n/a" if r["residual_median_mm"] is None else f"{r['residual_median_mm']:.2f} mm"
        lines.append(f"{stem}: {r['frames']} frames at {r['rate_hz']:g} Hz, {r['markers_used']} markers "
                     f"({len(r['markers_missing'])} missing), {r['bones']} bones, "
                     f"{100 * r['valid_share']:.1f}% valid, residual median {res}, "
                     f"{r['frames_per_second']:.0f} frames/s -> {r['outputs']['glb']}")
        if r["markers_missing"]:
            lines.append(f"  missing: {', '.join(r['markers_missing'])}")
        for flag, per_bone in r.get("flags", {}).items():
            if per_bone:
                lines.append(f"  {flag}: " + ", ".join(f"{b} {n} frames" for b, n in per_bone.items()))
        off = r.get("markers_off_their_bones") or {}
        if off:
            lines.append(f"  markers > {MARKER_OFF_MM:g} mm from their bones (median; constant part): "
                         + ", ".join(f"{n} {o['median_mm']:.0f} ({o['constant_mm']:.0f})" for n, o in off.items())
                         + " -- moved since the static, mislabelled, or where the model cannot follow")
    return "\n".join(lines)
