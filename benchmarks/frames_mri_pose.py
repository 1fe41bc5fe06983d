"""Each bone's frame of a built subject against the phantom's truth at the MRI pose.

Usage: ``python benchmarks/frames_mri_pose.py SUBJECT_DIR TRUTH_DIR [BONE ...]``

``bonecap evaluate subject`` scores surfaces and labels; the frames are what ``animate`` reports every
pose in, and a frame turned against the bone's own shape (a tibia's twist about its long axis, a foot
the scan did not measure) is an error in every frame of every trial that no marker can remove. This
prints, per bone (default: the long bones, the feet and the hands), the rotation taking the truth's frame
to the subject's as a rotation vector in the truth bone's axes (deg: X anterior, Y along the bone, Z to
the right, so ``Y`` is the twist about the long axis) and the origin's offset in the same axes (mm),
then the root mean square of each component over the bones listed. Both skeletons are in the MRI's
world (LPS, mm): the subject's ``bone_to_world``, the truth's ``skeleton.json`` ``bone_to_lps``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

DEFAULT_BONES = [f"{b}_{s}" for s in "rl" for b in ("femur", "tibia", "fibula", "patella", "talus", "foot",
                                                     "humerus", "ulna", "radius", "carpals")]


def frame_errors(subject_dir: Path, truth_dir: Path, bones: list[str]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per bone present in both: (rotation vector deg, origin offset mm), both in the truth bone's axes."""
    from bonecap.subject import read_subject

    sub = read_subject(subject_dir)
    truth = json.loads((Path(truth_dir) / "skeleton.json").read_text())["bones"]
    out = {}
    for b in bones:
        if b not in sub.skeleton.bones or b not in truth:
            continue
        Tt = np.asarray(truth[b]["bone_to_lps"], float)
        Tp = sub.skeleton.bones[b].bone_to_world
        rv = Rotation.from_matrix(Tt[:3, :3].T @ Tp[:3, :3]).as_rotvec(degrees=True)
        out[b] = (rv, Tt[:3, :3].T @ (Tp[:3, 3] - Tt[:3, 3]))
    return out


if __name__ == "__main__":
    if len(sys.argv) < 3:
        raise SystemExit(__doc__)
    errs = frame_errors(Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3:] or DEFAULT_BONES)
    if not errs:
        raise SystemExit(f"no bone of {sys.argv[1]} is in {sys.argv[2]}/skeleton.json")
    print("| bone | turn X / Y / Z (deg) | origin X / Y / Z (mm) |")
    print("|---|---|---|")
    for b, (rv, d) in errs.items():
        print(f"| {b} | {rv[0]:+.2f} / {rv[1]:+.2f} / {rv[2]:+.2f} | {d[0]:+.1f} / {d[1]:+.1f} / {d[2]:+.1f} |")
    R = np.array([v[0] for v in errs.values()])
    D = np.array([v[1] for v in errs.values()])
    rms = lambda a: np.sqrt(np.mean(a ** 2, axis=0))      # noqa: E731
    print(f"RMS over {len(errs)} bones: turn {' / '.join(f'{v:.2f}' for v in rms(R))} deg, "
          f"origin {' / '.join(f'{v:.1f}' for v in rms(D))} mm")
