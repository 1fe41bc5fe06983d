"""End-to-end accuracy and speed on phantoms: build-subject, animate, evaluate (issues #5 and #6).

For each seed: make the default phantom (or reuse one), run ``bonecap build-subject``
on its MRI stations with its static trial and forearm stacks (wall time and peak RSS
of that process), score it with ``bonecap evaluate subject``; animate its trials with
the least-squares solver (with and without the forearm model) and the paper solver,
and score each with ``bonecap evaluate motion`` (and the right forearm's bones in the
pronation trial, also at the twists between the forearm stacks': :func:`forearm_between`). The no-MRI path (template scaled to
the static trial) is run beside it as the baseline a lab without MRI gets.

Every step runs as its own ``bonecap`` process, as a user would run it.

Usage::

    python benchmarks/bench_pipeline.py --seeds 1 --work /tmp/bench_pipeline [--phantom /tmp/ph_default]
        [--marker-capsules] [--functional]

``--marker-capsules`` follows the paper's protocol: the phantoms image an 8 mm oil capsule under
every marker (``bonecap phantom --marker-capsules``), which build-subject finds and places the
markers on. A reused ``--phantom`` must have been made that way too.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

BONECAP = [sys.executable, "-m", "bonecap"]
LONG = ("femur", "tibia", "fibula", "humerus", "radius", "ulna")
FLAT = ("hip_", "sacrum", "scapula", "c", "t", "l")


def run(args: list, log: Path) -> tuple[float, float]:
    """Run a bonecap command; return (wall s, peak RSS MB of that child)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    t0 = time.perf_counter()
    with open(log, "w") as fh:
        res = subprocess.run([*BONECAP, *map(str, args)], stdout=fh, stderr=subprocess.STDOUT)
    wall = time.perf_counter() - t0
    if res.returncode != 0:
        raise SystemExit(f"failed ({res.returncode}): {' '.join(map(str, args))}; see {log}")
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    # ru_maxrss of children is the max over all children so far: report it when it grew
    return wall, max(peak, before) / 1024.0


#: The phantom's forearm stacks' true twists (deg): the forearm model is fitted there.
FOREARM_TWISTS = (0.0, 99.5, 172.1)


def forearm_between(anim: Path, truth: Path, side: str = "r", away_deg: float = 10.0) -> dict:
    """The forearm bones' orientation error in the pronation trial, all frames and those whose true
    twist lies more than ``away_deg`` from every fitted twist (#6: the model "evaluated also at twists
    between the fitted ones"): bone -> {"deg_median", "deg_p95", "between_deg_median", "between_deg_p95",
    "between_frames"}."""
    from scipy.spatial.transform import Rotation

    f_an, f_tr = anim / "pronation_poses.npz", truth / "pronation_poses.npz"
    if not (f_an.is_file() and f_tr.is_file()):
        return {}
    a, t = np.load(f_an), np.load(f_tr)
    tw = t[f"forearm_twist_deg_{side}"]
    between = np.min(np.abs(tw[:, None] - np.asarray(FOREARM_TWISTS)[None]), axis=1) > away_deg
    out = {}
    for bone in (f"radius_{side}", f"ulna_{side}"):
        ba, bt = [str(b) for b in a["bones"]], [str(b) for b in t["bones"]]
        A, T = a["transforms"][:, ba.index(bone)], t["transforms"][:, bt.index(bone)]
        n = min(len(A), len(T))
        ok = np.isfinite(A[:n]).all(axis=(1, 2))
        E = np.einsum("nji,njk->nik", T[:n][ok, :3, :3], A[:n][ok, :3, :3])
        deg = np.degrees(Rotation.from_matrix(E).magnitude())
        bw = between[:n][ok]
        out[bone] = {"deg_median": float(np.median(deg)), "deg_p95": float(np.percentile(deg, 95)),
                     "between_deg_median": float(np.median(deg[bw])) if bw.any() else None,
                     "between_deg_p95": float(np.percentile(deg[bw], 95)) if bw.any() else None,
                     "between_frames": int(bw.sum())}
    return out


def evaluate(what: str, path: Path, truth: Path, log: Path) -> dict:
    res = subprocess.run([*BONECAP, "evaluate", what, str(path), "--truth", str(truth), "--json"],
                         capture_output=True, text=True)
    log.write_text(res.stderr)
    if res.returncode != 0:
        raise SystemExit(f"evaluate {what} failed: {res.stderr}")
    return json.loads(res.stdout)


def subject_table(ev: dict) -> list[str]:
    lines = ["| bone | dice | oracle | extracted mean mm | personal mean mm | p95 | affine-only mean mm |",
             "|---|---|---|---|---|---|---|"]
    for b, r in ev["bones"].items():
        if "dice" not in r and "extracted_surface_mean_mm" not in r:
            continue
        f = lambda k: "-" if r.get(k) is None else f"{r[k]:.3f}" if "dice" in k else f"{r[k]:.2f}"  # noqa: E731
        lines.append(f"| {b} | {f('dice')} | {f('oracle_dice')} | {f('extracted_surface_mean_mm')} | "
                     f"{f('personal_surface_mean_mm')} | {f('personal_surface_p95_mm')} | "
                     f"{f('affine_only_surface_mean_mm')} |")
    return lines


def motion_summary(ev: dict, bones=("femur_r", "femur_l", "tibia_r", "tibia_l", "humerus_r", "humerus_l",
                                    "radius_r", "ulna_r", "sacrum", "foot_r")) -> dict:
    o = ev["overall"]
    deg = [v["deg_median"] for v in o.values() if v.get("frames")]
    mm = [v["mm_median"] for v in o.values() if v.get("frames")]
    return {"median_over_bones_deg": float(np.median(deg)), "median_over_bones_mm": float(np.median(mm)),
            "bones": {b: (round(o[b]["deg_median"], 2), round(o[b]["deg_p95"], 2), round(o[b]["mm_median"], 1))
                      for b in bones if b in o and o[b].get("frames")}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1])
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_pipeline"))
    ap.add_argument("--phantom", type=Path, help="reuse this phantom folder (for the first seed)")
    ap.add_argument("--marker-capsules", action="store_true",
                    help="the paper's protocol: phantoms made with an oil capsule imaged under every marker")
    ap.add_argument("--functional", action="store_true",
                    help="build-subject from MRI with the walking trial as --functional (the femurs' twist "
                    "from the knee's flexion axis)")
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    summary = {}
    for n, seed in enumerate(args.seeds):
        w = args.work / f"seed{seed}"
        w.mkdir(exist_ok=True)
        ph = args.phantom if (args.phantom and n == 0) else w / "phantom"
        if not (ph / "truth").is_dir():
            run(["phantom", "-o", ph, "--seed", seed] + (["--marker-capsules"] if args.marker_capsules else []),
                w / "phantom.log")
        truth = ph / "truth"
        stations = sorted((ph / "mri").glob("station_*"))
        forearm = sorted((ph / "mri").glob("forearm_*"), key=lambda p: float(p.name.split("_")[1]))
        trials = sorted((ph / "trials").glob("*.c3d"))
        func = ["--functional", ph / "trials/walk.c3d"] if args.functional else []
        wall, rss = run(["build-subject", *stations, "--static", ph / "trials/static.c3d", "--forearm-poses",
                         *forearm, *func, "-o", w / "subject"], w / "build.log")
        rep = json.loads((w / "subject/report.json").read_text())
        ev_s = evaluate("subject", w / "subject", truth, w / "ev_subject.log")
        wall_s, _ = run(["build-subject", "--static", ph / "trials/static.c3d", "-o", w / "subject_static"],
                        w / "build_static.log")
        motions = {}
        for label, subj, extra in [("mri lsq", "subject", []),
                                   ("mri lsq --no-forearm-model", "subject", ["--no-forearm-model"]),
                                   ("mri paper", "subject", ["--solver", "paper"]),
                                   ("static-only lsq", "subject_static", [])]:
            out = w / ("anim_" + label.replace(" ", "_").replace("-", ""))
            t, _ = run(["animate", w / subj, *trials, "-o", out, *extra], w / f"{out.name}.log")
            ar = json.loads((out / "animate_report.json").read_text())
            fps = [r["frames_per_second"] for r in ar["trials"].values()]
            motions[label] = {**motion_summary(evaluate("motion", out, truth, w / f"ev_{out.name}.log")),
                              "wall_s": round(t, 1), "solve_frames_per_s_median": float(np.median(fps)),
                              "forearm_pronation": forearm_between(out, truth)}
        qc_s = float((rep.get("timings_s") or {}).get("qc pictures", 0.0))
        summary[seed] = {"build_wall_s": round(wall, 1), "build_wall_without_qc_s": round(wall - qc_s, 1),
                         "build_peak_rss_mb": round(rss),
                         "build_stage_s": rep.get("timings_s"), "static_only_build_wall_s": round(wall_s, 1),
                         "subject_summary": ev_s["summary"],
                         "capsules": ev_s.get("capsules"), "forearm": rep.get("forearm", {}).get("twists_deg"),
                         "forearm_used": rep.get("forearm", {}).get("used"),
                         "motion": motions}
        print(f"## seed {seed}")
        print(json.dumps(summary[seed], indent=1))
        print("\n".join(subject_table(ev_s)))
    (args.work / "summary.json").write_text(json.dumps(summary, indent=1))
    print(f"load: {os.getloadavg()}")


if __name__ == "__main__":
    main()
