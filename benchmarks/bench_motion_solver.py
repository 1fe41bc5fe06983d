"""Benchmark of the joint-coupled least-squares solver and the forearm model on phantom trials.

Given the phantom's true skeleton (``truth/skeleton.json``) and true marker
binding (``marker_local``), each movement trial's C3D is solved by

- ``lsq``: :func:`bonecap.motion.lsq.solve_lsq` with its default segmentation
  (:func:`~bonecap.motion.lsq.plan_segments`);
- ``lsq-J``: the same with the segmentation of the joints the phantom really
  moves (bones whose pose relative to their parent never changes in the truth
  ride on it) -- the skeleton's true joint structure;
- ``rigid``: a plain per-bone rigid fit (:func:`bonecap.motion.rigid.fit_rigid_bones`),
  for the bones with >= 3 markers of their own (the others it cannot solve).

Per bone, over all frames of the trials where both are finite: orientation
error (deg) median / p95 and origin error (mm) median / p95 against
``truth/<trial>_poses.npz``. Then the forearm model on the pronation trial:
radius and ulna without the model, with the paper's coefficients and with the
subject's, fitted from the phantom's forearm MRI poses (``truth/forearm.json``;
twists measured on the markers placed by the true binding), over all frames
and over the frames whose true twist lies between the fitted ones (> 10 deg
from each). Last, frames per second on the walk tiled to ``--frames`` frames.

Run with::

    .venv/bin/python benchmarks/bench_motion_solver.py [--phantom /tmp/ph_default] [--frames 20000]
        [--lowpass HZ] [--sweeps N]

``--lowpass`` filters the markers (as ``animate --lowpass``) and ``--sweeps``
sets the solver's ``n_sweeps`` for the lsq rows.

Without ``--phantom`` a tiny phantom is made in a temporary folder (seed 1).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from bonecap.io.c3d import read_c3d
from bonecap.model import Bone, Skeleton
from bonecap.motion.forearm import FOREARM_MARKERS, PAPER_MODEL, fit_forearm_model, forearm_twist
from bonecap.motion.lsq import lowpass_markers, plan_segments, solve_lsq
from bonecap.motion.rigid import fit_rigid_bones, rotation_angle_deg

TRIALS = ("walk", "arm_raise", "pronation", "touch")


def skeleton_from_truth(truth: Path) -> Skeleton:
    """The subject's true skeleton (LPS world, joint centres and landmarks in the bone frames)."""
    doc = json.loads((truth / "skeleton.json").read_text())["bones"]
    bones = {}
    for n, b in doc.items():
        T = np.array(b["bone_to_lps"])
        Ti = np.linalg.inv(T)
        jc = {k: Ti[:3, :3] @ np.array(v) + Ti[:3, 3] for k, v in b["joint_centres_lps"].items()}
        lm = {k: Ti[:3, :3] @ np.array(v) + Ti[:3, 3] for k, v in b.get("landmarks_lps", {}).items()}
        bones[n] = Bone(n, b["parent"], bone_to_world=T, joint_centres=jc, landmarks=lm)
    return Skeleton(bones, world="lps")


def true_segments(skel: Skeleton, truths: list, marker_bones: list[str]) -> dict[str, str]:
    """bone -> segment root from the truth: a bone that never moves relative to its parent rides on it."""
    names = skel.names
    seg = {}
    for i, n in enumerate(names):
        p = skel.bones[n].parent
        if p is None:
            seg[n] = n
            continue
        j = names.index(p)
        moves = False
        for d in truths:
            rel = np.linalg.inv(d["transforms"][:, j]) @ d["transforms"][:, i]
            moves |= bool(np.abs(rel - rel[0]).max() > 1e-6)
        seg[n] = n if moves else seg[p]
    # a moving bone with no markers and no marked bone below (a patella) cannot be solved: it rides
    for n in reversed(names):
        if seg[n] == n and skel.bones[n].parent is not None:
            members = [b for b in names if seg[b] == n]
            below = [b for b in names if seg[b] != n and skel.bones[b].parent in members]
            if not any(b in marker_bones for b in members) and not below:
                for b in members:
                    seg[b] = seg[skel.bones[n].parent]
    return seg


def load_trial(root: Path, trial: str):
    d = np.load(root / "truth" / f"{trial}_poses.npz")
    tr = read_c3d(root / "trials" / f"{trial}.c3d")
    meas = tr.points[:, [tr.labels.index(m) for m in d["markers"]]]
    return d, meas, tr.rate


def bone_errors(T_est, T_true):
    deg = rotation_angle_deg(T_est, T_true)
    mm = np.linalg.norm(T_est[..., :3, 3] - T_true[..., :3, 3], axis=-1)
    return deg, mm


def stats(x):
    x = x[np.isfinite(x)]
    if not len(x):
        return (np.nan, np.nan)
    return float(np.median(x)), float(np.percentile(x, 95))


def rigid_per_bone(names, marker_bones, local, meas):
    by_bone: dict[str, list[int]] = {}
    for m, b in enumerate(marker_bones):
        by_bone.setdefault(b, []).append(m)
    by_bone = {b: ix for b, ix in by_bone.items() if len(ix) >= 3}
    fits = fit_rigid_bones({b: local[ix] for b, ix in by_bone.items()}, by_bone, meas)
    out = np.full((meas.shape[0], len(names), 4, 4), np.nan)
    for k, b in enumerate(fits.bones):
        out[:, names.index(b)] = fits.transforms[:, k]
    return out


def fitted_forearm(root: Path, skel: Skeleton, labels, marker_bones, local, side="r"):
    """The subject's model from the phantom's forearm MRI poses, and the measured twists."""
    poses = sorted(json.loads((root / "truth" / "forearm.json").read_text())["poses"].values(),
                   key=lambda p: p["theta_deg"])
    ix = [labels.index(n) for n in FOREARM_MARKERS[side]]
    T = [{b: np.array(v) for b, v in p["bone_to_lps"].items()} for p in poses]
    P = np.array([[(t.get(marker_bones[i], skel.bones[marker_bones[i]].bone_to_world) @ np.r_[local[i], 1])[:3]
                   for i in ix] for t in T])
    zero = forearm_twist(*P[0], side=side)[0]
    theta = forearm_twist(P[:, 0], P[:, 1], P[:, 2], P[:, 3], zero_deg=zero, side=side)
    model = fit_forearm_model(theta, np.array([t[f"ulna_{side}"] for t in T]),
                              np.array([t[f"radius_{side}"] for t in T]), P[:, :2], P[:, 2:], side=side)
    return model, theta, [p["theta_deg"] for p in poses]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--phantom", type=Path, default=None, help="a phantom folder (bonecap phantom -o DIR)")
    ap.add_argument("--frames", type=int, default=20000, help="frames of the tiled walk for the speed figure")
    ap.add_argument("--lowpass", type=float, default=None, metavar="HZ",
                    help="low-pass the markers before lsq / lsq-J (animate --lowpass HZ)")
    ap.add_argument("--sweeps", type=int, default=None, help="lsq / lsq-J n_sweeps (default: the solver's)")
    args = ap.parse_args()
    opts = {} if args.sweeps is None else {"n_sweeps": args.sweeps}
    tmp = None
    root = args.phantom
    if root is None:
        from bonecap.phantom import make_phantom

        tmp = tempfile.TemporaryDirectory()
        root = Path(tmp.name)
        make_phantom(root, seed=1, preset="tiny")
    skel = skeleton_from_truth(root / "truth")
    names = skel.names
    data = {t: load_trial(root, t) for t in TRIALS}
    d0 = data[TRIALS[0]][0]
    labels, mb, local = list(d0["markers"]), list(d0["marker_bones"]), d0["marker_local"]
    seg_true = true_segments(skel, [data[t][0] for t in TRIALS], mb)
    plan = plan_segments(skel, mb)
    eval_bones = [n for n in names if n in mb or plan.segments[plan.segment_of[n]].root == n]

    methods = {"lsq": {}, "lsq-J": {}, "rigid": {}}
    timing = {}
    for t in TRIALS:
        d, meas, rate = data[t]
        t0 = time.perf_counter()
        m_in = meas if args.lowpass is None else lowpass_markers(meas, rate, args.lowpass)
        methods["lsq"][t] = solve_lsq(skel, mb, local, m_in, marker_labels=labels, rate_hz=rate, **opts).transforms
        timing[t] = time.perf_counter() - t0
        methods["lsq-J"][t] = solve_lsq(skel, mb, local, m_in, marker_labels=labels, rate_hz=rate,
                                        segments=seg_true, **opts).transforms
        methods["rigid"][t] = rigid_per_bone(names, mb, local, meas)

    print(f"# bonecap motion solvers on phantom {root} ({platform.processor() or platform.machine()}, "
          f"numpy {np.__version__}); lsq options: lowpass {args.lowpass} Hz, sweeps {args.sweeps or 'default'}")
    print(f"trials: {', '.join(f'{t} ({len(data[t][1])} frames)' for t in TRIALS)}; lsq segments: "
          f"{', '.join(plan.roots())}")
    print()
    print("| bone | lsq deg med/p95 | lsq mm med/p95 | lsq-J deg med/p95 | lsq-J mm med/p95 "
          "| rigid deg med/p95 | rigid mm med/p95 |")
    print("|---|---|---|---|---|---|---|")
    pooled = {m: ([], []) for m in methods}
    for b in eval_bones:
        i = names.index(b)
        row = [b]
        for m in methods:
            errs = [bone_errors(methods[m][t][:, i], data[t][0]["transforms"][:, i]) for t in TRIALS]
            deg = np.concatenate([e[0] for e in errs])
            mm = np.concatenate([e[1] for e in errs])
            pooled[m][0].append(deg)
            pooled[m][1].append(mm)
            (a, b95), (c, d95) = stats(deg), stats(mm)
            row += [f"{a:.2f} / {b95:.2f}", f"{c:.2f} / {d95:.2f}"]
        print("| " + " | ".join(row) + " |")
    row = ["**all**"]
    for m in methods:
        (a, b95), (c, d95) = stats(np.concatenate(pooled[m][0])), stats(np.concatenate(pooled[m][1]))
        row += [f"{a:.2f} / {b95:.2f}", f"{c:.2f} / {d95:.2f}"]
    print("| " + " | ".join(row) + " |")

    # ---- forearm model
    d, meas, rate = data["pronation"]
    model, theta_fit, nominal = fitted_forearm(root, skel, labels, mb, local)
    true_tw = d["forearm_twist_deg_r"]
    between = np.min(np.abs(true_tw[:, None] - np.asarray(nominal)[None]), axis=1) > 10.0
    print()
    def r4(c):
        return np.round(c, 4).tolist()

    print(f"Forearm, pronation trial ({len(true_tw)} frames, true twist {true_tw.min():.0f}..{true_tw.max():.0f} "
          f"deg); subject model fitted at measured twists {np.round(theta_fit, 1).tolist()} (nominal {nominal}): "
          f"radius f = {r4(model.radius_rotation)}, ulna f = {r4(model.ulna_rotation)}, radius wrist/elbow u = "
          f"{r4(model.radius_wrist)} / {r4(model.radius_elbow)}, ulna wrist/elbow u = {r4(model.ulna_wrist)} / "
          f"{r4(model.ulna_elbow)} (quarter turns)")
    print()
    print("| model | bone | deg med/p95 (all) | mm med/p95 (all) | deg med/p95 (between fitted twists) "
          "| flagged frames |")
    print("|---|---|---|---|---|---|")
    # the subject's model turning the radius about its own radio-ulnar axis (what build-subject fits)
    anat = dataclasses.replace(model, radius_axis="anatomical")
    for label, fm, seg in (("none (lsq-J)", None, seg_true), ("paper (lsq-J)", PAPER_MODEL, seg_true),
                           ("subject (lsq-J)", {"r": model, "l": model}, seg_true),
                           ("subject, anatomical axis (lsq-J)", {"r": anat, "l": anat}, seg_true),
                           ("none (lsq)", None, None), ("subject (lsq)", {"r": model, "l": model}, None),
                           ("subject, anatomical axis (lsq)", {"r": anat, "l": anat}, None)):
        mo = solve_lsq(skel, mb, local, meas, marker_labels=labels, rate_hz=rate, forearm=fm, segments=seg)
        for b in ("radius_r", "ulna_r", "radius_l", "ulna_l"):
            i = names.index(b)
            deg, mm = bone_errors(mo.transforms[:, i], d["transforms"][:, i])
            (a, a95), (c, c95), (e, e95) = stats(deg), stats(mm), stats(deg[between])
            print(f"| {label} | {b} | {a:.2f} / {a95:.2f} | {c:.2f} / {c95:.2f} | {e:.2f} / {e95:.2f} | "
                  f"{int((~mo.valid[:, i]).sum())} |")

    # ---- speed
    d, meas, rate = data["walk"]
    reps = int(np.ceil(args.frames / len(meas)))
    long = np.tile(meas, (reps, 1, 1))[: args.frames]
    solve_lsq(skel, mb, local, long[:200], marker_labels=labels)  # warm-up
    print()
    print("| solver | frames | markers | segments | s (best of 3) | frames/s |")
    print("|---|---|---|---|---|---|")
    for label, kw in (("lsq", {}), ("lsq + forearm model", {"forearm": {"r": model, "l": model}}),
                      ("rigid per bone", None)):
        best = np.inf
        for _ in range(3):
            t0 = time.perf_counter()
            if kw is None:
                rigid_per_bone(names, mb, local, long)
            else:
                solve_lsq(skel, mb, local, long, marker_labels=labels, **kw)
            best = min(best, time.perf_counter() - t0)
        print(f"| {label} | {len(long)} | {len(mb)} | {len(plan.segments)} | {best:.3f} | {len(long) / best:,.0f} |")
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()
