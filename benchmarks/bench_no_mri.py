"""The no-MRI path on phantoms: ``build-subject --static``, ``animate``, scored against the truth.

What a user without MRI runs: the template scaled to the phantom's static trial (which carries the knee
and ankle widths a gait lab measures, in its ``PROCESSING`` group, as Nexus writes them), then the four
movement trials animated. Reported per phantom:

- the pooled orientation and origin errors of every bone and frame (``motion_pooled.py``) and the median
  over bones of each bone's p95;
- the joint centres' errors (mm, median and p95 over both sides and every frame of the four trials): each
  bone's proximal joint centre as ``animate`` writes it into ``<trial>_bonecap.c3d``
  (``tibia_r_jc`` = the right knee...) against the truth's ``joint_centres``.

Usage::

    .venv/bin/python benchmarks/bench_no_mri.py --work /tmp/nomri PHANTOM_DIR...

A phantom folder is ``bonecap phantom -o DIR --seed N`` (the default preset). The embedded template's
joint names are used (hip/knee/ankle/shoulder/elbow/wrist).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
BONECAP = [sys.executable, "-m", "bonecap"]
TRIALS = ("walk", "arm_raise", "pronation", "touch")
#: joint -> the bone whose proximal joint it is (the embedded template's names)
JOINTS = {"hip": "femur", "knee": "tibia", "ankle": "talus", "shoulder": "humerus", "elbow": "ulna",
          "wrist": "carpals"}


def joint_centre_errors(anim: Path, truth: Path) -> dict[str, list[float]]:
    """Per joint ``[median, p95]`` (mm) of ``|ours - truth|`` over both sides and all frames of the trials."""
    from bonecap.io.c3d import read_c3d

    errs: dict[str, list[np.ndarray]] = {}
    for trial in TRIALS:
        ours = read_c3d(anim / f"{trial}_bonecap.c3d").other_points
        t = np.load(truth / f"{trial}_poses.npz", allow_pickle=True)
        names = [str(n) for n in t["joint_names"]]
        for joint, bone in JOINTS.items():
            for s in "rl":
                o = ours[f"{bone}_{s}_jc"][:, :3]
                g = t["joint_centres"][:, names.index(f"{joint}:{bone}_{s}")]
                e = np.linalg.norm(o - g, axis=1)
                errs.setdefault(joint, []).append(e[np.isfinite(e)])
    return {j: [round(float(np.median(np.concatenate(v))), 1), round(float(np.percentile(np.concatenate(v), 95)), 1)]
            for j, v in errs.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", type=Path, required=True, help="output folder")
    ap.add_argument("phantoms", type=Path, nargs="+", help="phantom folders (bonecap phantom -o DIR)")
    args = ap.parse_args()
    sys.path.insert(0, str(ROOT))
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from motion_pooled import pooled

    summary = {}
    for ph in args.phantoms:
        w = args.work / ph.name
        w.mkdir(parents=True, exist_ok=True)
        for cmd in (["build-subject", "--static", ph / "trials/static.c3d", "-o", w / "subject"],
                    ["animate", w / "subject", *(ph / f"trials/{t}.c3d" for t in TRIALS), "-o", w / "animate"]):
            res = subprocess.run([*BONECAP, *map(str, cmd)], capture_output=True, text=True, cwd=ROOT)
            if res.returncode != 0:
                raise SystemExit(f"bonecap {cmd[0]} failed on {ph}:\n{res.stderr}")
        report = json.loads((w / "subject/report.json").read_text())
        summary[ph.name] = {"pooled": pooled(w / "animate", ph / "truth"),
                            "joint_centres_mm": joint_centre_errors(w / "animate", ph / "truth"),
                            "joint_centre_targets": report.get("joint_centre_targets"),
                            "measured_joint_widths": report.get("measured_joint_widths")}
        print(ph.name, json.dumps(summary[ph.name]))
    (args.work / "summary.json").write_text(json.dumps(summary, indent=1))
    print(f"-> {args.work / 'summary.json'}")


if __name__ == "__main__":
    main()
