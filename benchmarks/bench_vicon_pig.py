"""Hip and knee flexion against Vicon's own Plug-in Gait outputs on a real trial (issue #6, real-trial target).

The pyCGM test trials (``../shared/data``: ``pycgm_Test_Static_trial.c3d`` and
``pycgm_Test_Movement_trial.c3d``, 120 Hz, mm) hold Vicon Nexus's Plug-in Gait results beside the markers:
the joint angles (``LKneeAngles``, ``RHipAngles``...: flexion, adduction, rotation in degrees) and every
segment's frame as four points (``LFEO`` origin, ``LFEA`` anterior, ``LFEL`` lateral, ``LFEP``
proximal; ``FE`` femur, ``TI`` tibia). A user without MRI runs ``bonecap build-subject --static`` (the
template scaled to the static trial) and ``bonecap animate``; this script does exactly that, then compares
``<trial>_angles.csv`` (``femur_*`` = hip, ``tibia_*`` = knee; flexion positive) with Vicon's angles:
RMS of the difference, its mean (a constant offset) and its standard deviation (what the offset leaves).
Also printed: each marker group's residual (how far the solved bones put the markers from where they were),
the elbow's flexion against Plug-in Gait's ``ElbowAngles``, the ankle's against ``AnkleAngles``, and the
foot's other turns on the shank (their ranges and the largest turn between two frames: a foot that flips).

Plug-in Gait's thigh twist comes from the thigh wand marker: a wand a few degrees off turns the femur's
frame about its long axis and knee flexion leaks into knee adduction ("cross-talk"; Baudet et al. 2014).
To see how much of the difference is that, Vicon's femur frame is also turned about its own long axis
by the angle that minimises the variance of Vicon's knee adduction over the trial (Baudet et al.'s
correction), and the knee angles recomputed from Vicon's own frames (Cardan YXZ of tibia in femur, which
reproduces ``KneeAngles`` before the correction); bonecap's knee flexion is compared with both. The twist
between bonecap's femur frame and Vicon's is reported too.

References
----------
Baudet A, Morisset C, d'Athis P, et al. Cross-talk correction method for knee kinematics in gait
analysis using principal component analysis (PCA): a new proposal. PLoS One 2014;9(7):e102098.
Kadaba MP, Ramakrishnan HK, Wootten ME. Measurement of lower extremity kinematics during level walking.
J Orthop Res 1990;8:383-392.

Usage::

    .venv/bin/python benchmarks/bench_vicon_pig.py --work /tmp/vicon_pig
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
BONECAP = [sys.executable, "-m", "bonecap"]


def _find(name: str) -> Path:
    hits = sorted(DATA.rglob(name))
    if not hits:
        raise SystemExit(f"{name} not found under {DATA}")
    return hits[0]


def _frames(points: dict[str, np.ndarray], prefix: str) -> np.ndarray:
    """Vicon's segment frame per frame (F, 3, 3), columns anterior, lateral, proximal (lab, unit)."""
    o = points[prefix + "O"]
    cols = []
    for s in "ALP":
        v = points[prefix + s] - o
        cols.append(v / np.linalg.norm(v, axis=1, keepdims=True))
    return np.stack(cols, axis=2)


def _knee_from_frames(Rf: np.ndarray, Rt: np.ndarray) -> np.ndarray:
    """Plug-in Gait knee angles from the femur and tibia frames: tibia in femur, Cardan Y (flexion about
    the lateral axis), X (adduction), Z (rotation), degrees (F, 3) -- flexion, adduction, rotation."""
    rel = np.einsum("fji,fjk->fik", Rf, Rt)
    e = Rotation.from_matrix(rel).as_euler("YXZ", degrees=True)
    return e


def _stats(ours: np.ndarray, ref: np.ndarray) -> dict[str, float]:
    ok = np.isfinite(ours) & np.isfinite(ref)
    d = ours[ok] - ref[ok]
    return {"rms": float(np.sqrt(np.mean(d ** 2))), "mean": float(d.mean()), "sd": float(d.std()),
            "corr": float(np.corrcoef(ours[ok], ref[ok])[0, 1]), "frames": int(ok.sum())}


def _twist(R_ref: np.ndarray, anterior: np.ndarray) -> np.ndarray:
    """Angle (deg) from the reference frame's anterior axis to ``anterior`` about its proximal axis."""
    n = R_ref[:, :, 2]

    def flat(a):
        a = a - np.einsum("fi,fi->f", a, n)[:, None] * n
        return a / np.linalg.norm(a, axis=1, keepdims=True)

    a1, a2 = flat(R_ref[:, :, 0]), flat(anterior)
    return np.degrees(np.arctan2(np.einsum("fi,fi->f", np.cross(a1, a2), n), np.einsum("fi,fi->f", a1, a2)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", type=Path, required=True, help="output folder (subject, animation, results)")
    args = ap.parse_args()
    sys.path.insert(0, str(ROOT))
    from bonecap.io.c3d import read_c3d

    static, movement = _find("pycgm_Test_Static_trial.c3d"), _find("pycgm_Test_Movement_trial.c3d")
    args.work.mkdir(parents=True, exist_ok=True)
    subj, anim = args.work / "subject", args.work / "animate"
    for cmd in (["build-subject", "--static", static, "-o", subj], ["animate", subj, movement, "-o", anim]):
        res = subprocess.run([*BONECAP, *map(str, cmd)], capture_output=True, text=True, cwd=ROOT)
        if res.returncode != 0:
            raise SystemExit(f"bonecap {cmd[0]} failed:\n{res.stderr}")

    trial = read_c3d(movement)
    points = {n: trial.points[:, i] for i, n in enumerate(trial.labels)}
    rows = list(csv.DictReader(open(anim / f"{movement.stem}_angles.csv")))
    poses = np.load(anim / f"{movement.stem}_poses.npz", allow_pickle=True)
    bones = list(poses["bones"])

    def col(name: str) -> np.ndarray:
        return np.array([float(r[name]) if r[name] not in ("", None) else np.nan for r in rows])

    out: dict[str, dict] = {}
    print("| side | angle | RMS deg | mean (offset) | SD | corr |")
    print("|---|---|---:|---:|---:|---:|")
    for side in "LR":
        s = side.lower()
        for bone, joint in (("femur", "Hip"), ("tibia", "Knee")):
            st = _stats(col(f"{bone}_{s}_flexion_deg"), trial.other_points[f"{side}{joint}Angles"][:, 0])
            out[f"{side}{joint}Flexion"] = st
            print(f"| {side} | {joint.lower()} flexion vs Vicon | {st['rms']:.1f} | {st['mean']:+.1f} | "
                  f"{st['sd']:.1f} | {st['corr']:.3f} |")
        Rf, Rt = _frames(points, side + "FE"), _frames(points, side + "TI")
        ok = np.isfinite(Rf).all(axis=(1, 2)) & np.isfinite(Rt).all(axis=(1, 2))
        vic = _knee_from_frames(Rf[ok], Rt[ok])
        check = _stats(vic[:, 0], trial.other_points[f"{side}KneeAngles"][ok, 0])
        # Baudet's correction: the femur frame turned about its long axis to minimise adduction variance
        phis = np.arange(-90.0, 90.01, 0.5)
        var = [np.var(_knee_from_frames(Rf[ok] @ Rotation.from_euler("z", p, degrees=True).as_matrix(),
                                        Rt[ok])[:, 1]) for p in phis]
        phi = float(phis[int(np.argmin(var))])
        cor = _knee_from_frames(Rf[ok] @ Rotation.from_euler("z", phi, degrees=True).as_matrix(), Rt[ok])
        ours = col(f"tibia_{s}_flexion_deg")[ok]
        st = _stats(ours, cor[:, 0])
        Tf = poses["transforms"][:, bones.index(f"femur_{s}")]
        okb = ok & np.isfinite(Tf).all(axis=(1, 2))
        twist = float(np.median(_twist(Rf[okb], Tf[okb, :3, 0])))
        out[f"{side}KneeFlexionCorrected"] = {**st, "phi_deg": phi, "vicon_adduction_range_deg":
                                              [float(vic[:, 1].min()), float(vic[:, 1].max())],
                                              "corrected_adduction_range_deg":
                                              [float(cor[:, 1].min()), float(cor[:, 1].max())],
                                              "frames_check_rms_deg": check["rms"],
                                              "femur_twist_bonecap_vs_vicon_deg": twist}
        print(f"| {side} | knee flexion vs Vicon cross-talk corrected (femur turned {phi:+.1f} deg; Vicon "
              f"adduction {vic[:, 1].min():.0f}..{vic[:, 1].max():.0f} -> {cor[:, 1].min():.0f}.."
              f"{cor[:, 1].max():.0f} deg) | {st['rms']:.1f} | {st['mean']:+.1f} | {st['sd']:.1f} | "
              f"{st['corr']:.3f} |")
        print(f"|   | (Vicon frames reproduce KneeAngles flexion to {check['rms']:.2f} deg RMS; bonecap's femur "
              f"turned {twist:+.1f} deg from Vicon's about its long axis) | | | | |")
    # How well the solved bones carry the markers: each marker's median distance from where its bone puts
    # it (mm), by group; the static binds every marker, so what is left is the model (joints, rigid
    # segments) against the movement's skin and pose.
    res = np.nanmedian(poses["residuals"], axis=0)
    labels = [str(m) for m in poses["markers"]]
    groups = {"head": ("FHD", "BHD"), "trunk": ("C7", "T10", "CLAV", "STRN", "RBAK"), "shoulder": ("SHO",),
              "upper arm": ("UPA", "ELB"), "forearm and hand": ("FRM", "WRA", "WRB", "FIN"),
              "pelvis": ("ASI", "PSI"), "leg": ("THI", "KNE", "TIB", "ANK"), "foot": ("HEE", "TOE")}
    out["marker_residual_median_mm"] = {}
    print("\n| marker group | residual median over its markers (mm) | markers |")
    print("|---|---:|---|")
    for g, keys in groups.items():
        idx = [i for i, m in enumerate(labels) if m.lstrip("LR") in keys or m in keys]
        v = float(np.median(res[idx]))
        out["marker_residual_median_mm"][g] = {labels[i]: round(float(res[i]), 1) for i in idx}
        print(f"| {g} | {v:.1f} | {', '.join(f'{labels[i]} {res[i]:.0f}' for i in idx)} |")
    # the elbow against Plug-in Gait's ElbowAngles (flexion): ours is the ulna on the humerus
    for side in "LR":
        st = _stats(col(f"ulna_{side.lower()}_flexion_deg"), trial.other_points[f"{side}ElbowAngles"][:, 0])
        out[f"{side}ElbowFlexion"] = st
        print(f"{side} elbow flexion vs Vicon: RMS {st['rms']:.1f}, mean {st['mean']:+.1f}, SD {st['sd']:.1f} deg")
    # the foot on the shank: ankle flexion against Plug-in Gait's AnkleAngles, and how far the foot turns
    # otherwise (heel and toe lie near one line with the ankle centre, so a misplaced heel marker can roll
    # it: the frame-to-frame turn of the talus in the tibia shows a flip)
    for side in "LR":
        s = side.lower()
        st = _stats(col(f"talus_{s}_flexion_deg"), trial.other_points[f"{side}AnkleAngles"][:, 0])
        Tt, Ta = (poses["transforms"][:, bones.index(f"{b}_{s}")] for b in ("tibia", "talus"))
        okf = np.isfinite(Tt).all(axis=(1, 2)) & np.isfinite(Ta).all(axis=(1, 2))
        rel = Rotation.from_matrix(np.einsum("fji,fjk->fik", Tt[okf, :3, :3], Ta[okf, :3, :3]))
        step = np.degrees((rel[1:] * rel[:-1].inv()).magnitude())
        add, rot = col(f"talus_{s}_adduction_deg"), col(f"talus_{s}_rotation_deg")
        out[f"{side}AnkleFlexion"] = {**st, "adduction_range_deg": [float(np.nanmin(add)), float(np.nanmax(add))],
                                      "rotation_range_deg": [float(np.nanmin(rot)), float(np.nanmax(rot))],
                                      "largest_frame_to_frame_turn_deg": float(step.max())}
        print(f"{side} ankle flexion vs Vicon: RMS {st['rms']:.1f}, mean {st['mean']:+.1f}, SD {st['sd']:.1f} deg; "
              f"foot on the shank: adduction {np.nanmin(add):.0f}..{np.nanmax(add):.0f}, rotation "
              f"{np.nanmin(rot):.0f}..{np.nanmax(rot):.0f} deg, largest turn between frames {step.max():.1f} deg")
    (args.work / "results.json").write_text(json.dumps(out, indent=1))
    print(f"-> {args.work / 'results.json'}")


if __name__ == "__main__":
    main()
