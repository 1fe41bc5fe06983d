"""Slice-wise bone segmentation on the phantom: Dice per bone against the oracle labels, and time.

For every MRI station of a phantom made by ``bonecap phantom`` (default preset:
1.8 mm pixels, 5 mm slices), the body is segmented
(:func:`bonecap.segmentation.skin.segment_body`) and every bone by its rule
(:func:`bonecap.segmentation.bones.segment_bones`) from seeds made the way the
pipeline will get them: the true joint centres and landmarks
(``truth/skeleton.json``), moved by the station's ``true_to_nominal`` (the
body lay moved while that station was imaged), then displaced by one random
affine error for the whole body (a template roughly aligned to the skin:
~10-15 mm at the bones). The labels are compared with
``truth/labels/station_<k>_oracle.nii.gz`` (same grid, voxel for voxel): Dice
per bone over all stations (voxel counts summed over stations), the oracle's
own voxel count, and the time of the body and bone segmentation.

Run::

    .venv/bin/python benchmarks/bench_segmentation_phantom.py PHANTOM_DIR [--seed 0] [--json OUT.json]

(``PHANTOM_DIR`` from ``bonecap phantom -o PHANTOM_DIR --seed 1``.)
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from bonecap.io.imaging import read_nifti, read_volumes
from bonecap.segmentation.bones import segment_bones
from bonecap.segmentation.skin import segment_body

VERTEBRAE = [f"c{i}" for i in range(1, 8)] + [f"t{i}" for i in range(1, 13)] + [f"l{i}" for i in range(1, 6)]
LONG = ("femur", "tibia", "fibula", "humerus", "radius", "ulna")


def seed_points(bones: dict) -> dict[str, np.ndarray]:
    """Seed polylines (true world, LPS mm) per bone from the truth skeleton's joint centres/landmarks.

    Long bones: proximal -> distal joint centre. Others: one or a few points
    of the bone (its joint centres or landmarks, in an order along the bone).
    """
    def jc(b, k):
        return np.asarray(bones[b]["joint_centres_lps"][k], float)

    def lm(b, k):
        return np.asarray(bones[b]["landmarks_lps"][k], float)

    out: dict[str, np.ndarray] = {}
    for s in "rl":
        out[f"femur_{s}"] = np.stack([jc(f"femur_{s}", "hip"), jc(f"femur_{s}", "knee")])
        out[f"tibia_{s}"] = np.stack([jc(f"tibia_{s}", "knee"), jc(f"tibia_{s}", "ankle")])
        out[f"fibula_{s}"] = np.stack([lm(f"fibula_{s}", "head"), lm(f"fibula_{s}", "lateral_malleolus")])
        out[f"humerus_{s}"] = np.stack([jc(f"humerus_{s}", "shoulder"), jc(f"humerus_{s}", "elbow")])
        out[f"radius_{s}"] = np.stack([lm(f"radius_{s}", "radial_head_centre"), jc(f"radius_{s}", "wrist")])
        out[f"ulna_{s}"] = np.stack([jc(f"ulna_{s}", "elbow"), lm(f"ulna_{s}", "ulnar_head_fovea")])
        out[f"hip_{s}"] = np.stack([jc(f"hip_{s}", "sacroiliac"), jc(f"hip_{s}", "hip"), lm(f"hip_{s}", "ischial_tuberosity")])
        out[f"patella_{s}"] = (0.5 * (jc(f"patella_{s}", "patellofemoral") + lm(f"patella_{s}", "anterior_centre")))[None]
        out[f"scapula_{s}"] = np.stack([lm(f"scapula_{s}", "acromion"), lm(f"scapula_{s}", "spine_root"),
                                        lm(f"scapula_{s}", "inferior_angle")])
        out[f"clavicle_{s}"] = np.stack([lm(f"clavicle_{s}", "sternal_end"), lm(f"clavicle_{s}", "acromial_end")])
        out[f"talus_{s}"] = np.stack([jc(f"talus_{s}", "ankle"), jc(f"talus_{s}", "subtalar")])
        out[f"calcaneus_{s}"] = np.stack([jc(f"calcaneus_{s}", "subtalar"), lm(f"calcaneus_{s}", "heel_posterior")])
    out["sacrum"] = np.stack([jc("sacrum", "l5_s1"), 0.5 * (jc("sacrum", "sacroiliac_r") + jc("sacrum", "sacroiliac_l"))])
    for v in VERTEBRAE:
        out[v] = np.stack(list(map(np.asarray, bones[v]["joint_centres_lps"].values()))[:2])
    out["sternum"] = np.stack([lm("sternum", "jugular_notch"), lm("sternum", "xiphoid")])
    return out


def random_affine(rng: np.random.Generator, centre: np.ndarray, shift_mm: float = 10.0, linear: float = 0.01
                  ) -> np.ndarray:
    """A 4x4 affine error about ``centre``: ``shift_mm`` translation, +-``linear`` strain/rotation."""
    d = rng.normal(size=3)
    A = np.eye(4)
    A[:3, :3] += rng.uniform(-linear, linear, (3, 3))
    A[:3, 3] = centre - A[:3, :3] @ centre + shift_mm * d / np.linalg.norm(d)
    return A


def apply(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ T[:3, :3].T + T[:3, 3]


def dice_counts(labels, ids, oracle, oracle_ids):
    """Per bone (intersection, |ours|, |oracle|) voxel counts."""
    out = {}
    for b, i in ids.items():
        if b not in oracle_ids:
            continue
        a = labels == i
        o = oracle == oracle_ids[b]
        out[b] = np.array([np.count_nonzero(a & o), np.count_nonzero(a), np.count_nonzero(o)], float)
    return out


def run(phantom: Path, seed: int = 0, shift_mm: float = 10.0, linear: float = 0.01, stations=None, quiet=False):
    truth = phantom / "truth"
    skel = json.loads((truth / "skeleton.json").read_text())["bones"]
    oracle_ids = json.loads((truth / "labels.json").read_text())["ids"]
    stations_js = json.loads((truth / "stations.json").read_text())["stations"]
    true_seeds = seed_points(skel)
    allp = np.concatenate(list(true_seeds.values()))
    err = random_affine(np.random.default_rng(seed), allp.mean(axis=0), shift_mm, linear)
    seed_err = np.linalg.norm(apply(err, allp) - allp, axis=1)
    totals: dict[str, np.ndarray] = {}
    t_body = t_bones = 0.0
    for st in stations_js:
        if stations is not None and st["index"] not in stations:
            continue
        vol = read_volumes(phantom / "mri" / st["name"])[0]
        oracle = read_nifti(truth / "labels" / f"{st['name']}_oracle.nii.gz").data
        T = np.asarray(st["true_to_nominal"], float)
        seeds = {b: apply(err, apply(T, p)) for b, p in true_seeds.items()}
        t0 = time.perf_counter()
        body = segment_body(vol)
        t1 = time.perf_counter()
        labels, ids = segment_bones(vol, seeds, body_mask=body, progress=False)
        t2 = time.perf_counter()
        t_body += t1 - t0
        t_bones += t2 - t1
        for b, c in dice_counts(labels, ids, oracle, oracle_ids).items():
            totals[b] = totals.get(b, 0) + c
        if not quiet:
            print(f"{st['name']}: {vol.shape} body {t1 - t0:.2f} s, bones {t2 - t1:.2f} s", file=sys.stderr)
    rows = {}
    for b, (inter, na, no) in totals.items():
        if no == 0 and na == 0:
            continue
        rows[b] = {"dice": float(2 * inter / (na + no)) if na + no else float("nan"), "voxels": int(na),
                   "oracle_voxels": int(no)}
    return {"rows": rows, "time_body_s": t_body, "time_bones_s": t_bones,
            "seed_error_mm": {"mean": float(seed_err.mean()), "max": float(seed_err.max())}}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("phantom", type=Path)
    ap.add_argument("--seed", type=int, default=0, help="seed of the random affine seed error")
    ap.add_argument("--shift-mm", type=float, default=10.0)
    ap.add_argument("--linear", type=float, default=0.01)
    ap.add_argument("--stations", type=int, nargs="*")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args(argv)
    res = run(a.phantom, a.seed, a.shift_mm, a.linear, a.stations)
    rows = res["rows"]
    print(f"seed error: mean {res['seed_error_mm']['mean']:.1f} mm, max {res['seed_error_mm']['max']:.1f} mm")
    print(f"time: body {res['time_body_s']:.2f} s, bones {res['time_bones_s']:.2f} s")
    print(f"{'bone':14s} {'rule':9s} {'dice':>6s} {'ours':>8s} {'oracle':>8s}")
    order = sorted(rows, key=lambda b: (b.rstrip('_rl').rstrip('_') not in [x for x in LONG], b))
    for b in order:
        r = rows[b]
        rule = "cortical" if b.rsplit("_", 1)[0] in LONG else "density"
        print(f"{b:14s} {rule:9s} {r['dice']:6.3f} {r['voxels']:8d} {r['oracle_voxels']:8d}")
    if a.json:
        a.json.write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
