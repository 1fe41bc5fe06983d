"""Pooled motion errors of an ``animate`` output against the phantom's truth (every bone and frame together).

Usage: ``python benchmarks/motion_pooled.py ANIMATE_OUT_DIR TRUTH_DIR``

``bonecap evaluate motion`` reports per bone (median and p95 over a bone's frames); the #6 targets
(orientation median <= 1 deg, p95 <= 3 deg, origin <= 2 mm) can also be read over all bones and frames
at once, which weighs every bone-frame equally. Prints the pooled median and 95th percentile of the
orientation error (deg, the angle of ``R_true^T R``) and of the origin error (mm), and the median over
bones of each bone's p95. Frames where either pose is invalid (NaN) are left out.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation


def pooled(anim: Path, truth: Path) -> dict:
    degs, mms, per_bone = [], [], {}
    for f in sorted(anim.glob("*_poses.npz")):
        trial = f.name[: -len("_poses.npz")]
        t_file = truth / f"{trial}_poses.npz"
        if not t_file.exists():
            continue
        a, t = np.load(f, allow_pickle=True), np.load(t_file, allow_pickle=True)
        ba, bt = [str(b) for b in a["bones"]], [str(b) for b in t["bones"]]
        for b in ba:
            if b not in bt:
                continue
            A, T = a["transforms"][:, ba.index(b)], t["transforms"][:, bt.index(b)]
            n = min(len(A), len(T))
            A, T = A[:n], T[:n]
            ok = np.isfinite(A[:, 0, 0]) & np.isfinite(T[:, 0, 0])
            if not ok.any():
                continue
            E = np.einsum("nji,njk->nik", T[ok, :3, :3], A[ok, :3, :3])
            d = np.degrees(Rotation.from_matrix(E).magnitude())
            degs.append(d)
            mms.append(np.linalg.norm(A[ok, :3, 3] - T[ok, :3, 3], axis=1))
            per_bone.setdefault(b, []).append(d)
    if not degs:
        raise SystemExit(f"no trial of {anim} has a truth in {truth}")
    D, M = np.concatenate(degs), np.concatenate(mms)
    return {"deg_median": float(np.median(D)), "deg_p95": float(np.percentile(D, 95)),
            "mm_median": float(np.median(M)), "mm_p95": float(np.percentile(M, 95)),
            "median_of_bone_p95_deg": float(np.median([np.percentile(np.concatenate(v), 95)
                                                       for v in per_bone.values()])),
            "bones": len(per_bone)}


if __name__ == "__main__":
    if len(sys.argv) != 3:
        raise SystemExit(__doc__)
    r = pooled(Path(sys.argv[1]), Path(sys.argv[2]))
    print(f"pooled deg median {r['deg_median']:.2f} p95 {r['deg_p95']:.2f}; mm median {r['mm_median']:.2f} "
          f"p95 {r['mm_p95']:.2f}; median over bones of each bone's p95 {r['median_of_bone_p95_deg']:.2f} deg; "
          f"{r['bones']} bones")
