"""The slice rules on a real knee's anatomy, scored at full resolution (issue #5, DESS target).

No public knee MRI comes with both a clinical spin-echo image and bone labels. The shared DESS labels
(``../shared/data/mri/knee_dess_bone_labels``: a 3D DESS right knee, 384 x 384 x 160 at 0.364 x 0.364 x
0.70 mm, LPS, sagittal; 5 femur, 6 tibia, 7 patella, 8 fibula, 1-4 cartilage, 9/10 menisci) have no
image, so one is rendered from them with the contrast of the real MESE knee
(``bonecap/phantom/tissue_intensities.yaml``, measured on ROIs of ``knee_mese_t2_echo1_dicom``):

- at full resolution: every bone is marrow inside a cortex of ``--cortex-mm`` (3-D depth under the
  label's surface; 1 mm, the epiphyseal cortex of a knee), cartilage 1.2 x muscle (an assumption: the yaml has
  no cartilage ROI), menisci as dark as cortex (fibrocartilage has almost no signal at TE 6 ms), all
  other voxels muscle within ``--body-mm`` of the labelled structures, the outer ``--fat-mm`` of that
  a subcutaneous fat layer, air beyond (the labels give no body outline: a limb-like one is drawn
  around the joint, so the skin and body rules see a body in air as on the real knee). Each tissue gets
  its measured texture (coefficient of variation, ~1 mm correlated). There are no fat pads (Hoffa's,
  suprapatellar): the leaks seen on the real knee into them cannot happen here -- this scores the
  rules on real bone shapes, not on fat next to bone.
- resampled to the real MESE geometry: the DESS axes kept (sagittal), 0.625 mm pixels, 3 mm slices
  4 mm apart. Partial volume: each output voxel averages the rendered image over its in-plane pixel
  and the 3 mm slab (a Gaussian of the box's variance, sigma = width / sqrt(12) per axis, then linear
  sampling at the voxel centre), then Rician noise of the measured sigma.

Seeds come from the labels, as a user would place them by eye: per bone, in every other output slice
that holds it, the label voxel nearest the bone's centroid in that slab (so the point is inside the
bone). ``bonecap build-subject RENDERED.nii.gz --seeds SEEDS.yaml`` is run as a user runs it, and each
extracted mesh is voxelised on the full-resolution DESS grid and scored (Dice) against the labels. The
oracle is the best a segmentation on the MESE grid can reach: the labels' own partial-volume fraction
>= 0.5 on that grid, meshed the same way (``bonecap.meshing.mesh_from_slices``) and voxelised back.

Usage::

    .venv/bin/python benchmarks/bench_knee_dess.py --work /tmp/dess
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml
from scipy import ndimage

ROOT = Path(__file__).resolve().parents[1]
LABELS = ROOT.parent / "shared/data/mri/knee_dess_bone_labels/SAG_3D_DESS_RIGHT_bones_cart_men_fib-label.nrrd"
BONES = {"femur_r": 5, "tibia_r": 6, "patella_r": 7, "fibula_r": 8}
CARTILAGE, MENISCI = (1, 2, 3, 4), (9, 10)
PIXEL_MM, THICK_MM, PITCH_MM = 0.625, 3.0, 4.0


def render_full(lab: np.ndarray, spacing: np.ndarray, tissues: dict, cortex_mm: float, body_mm: float,
                fat_mm: float, rng: np.random.Generator) -> np.ndarray:
    """The MESE contrast on the label grid (see the module docstring)."""
    mean = {k: float(v["mean"]) for k, v in tissues.items()}
    cv = {k: float(v["texture_cv"]) for k, v in tissues.items()}
    img = np.full(lab.shape, mean["muscle"], np.float32)
    # 0 muscle, 1 marrow, 2 cortex, 3 cartilage, 4 meniscus, 5 fat, 6 air
    tissue_of = np.zeros(lab.shape, np.uint8)
    out_of = ndimage.distance_transform_edt(lab == 0, sampling=spacing)
    tissue_of[out_of > body_mm - fat_mm] = 5
    tissue_of[out_of > body_mm] = 6
    for b in BONES.values():
        m = lab == b
        depth = ndimage.distance_transform_edt(m, sampling=spacing)
        tissue_of[m & (depth > cortex_mm)] = 1
        tissue_of[m & (depth <= cortex_mm)] = 2
    tissue_of[np.isin(lab, CARTILAGE)] = 3
    tissue_of[np.isin(lab, MENISCI)] = 4
    values = {0: ("muscle", mean["muscle"]), 1: ("marrow", mean["marrow"]), 2: ("cortex", mean["cortex"]),
              3: ("muscle", 1.2 * mean["muscle"]), 4: ("cortex", mean["cortex"]), 5: ("fat", mean["fat"]),
              6: ("air", 0.0)}
    # ~1 mm correlated texture, unit variance
    tex = ndimage.gaussian_filter(rng.standard_normal(lab.shape).astype(np.float32), 1.0 / spacing)
    tex /= tex.std()
    for t, (name, value) in values.items():
        sel = tissue_of == t
        img[sel] = value * (1.0 + cv[name] * tex[sel])
    return np.maximum(img, 0.0)


def mese_grid(shape, affine) -> tuple[tuple[int, int, int], np.ndarray]:
    """The output grid: the DESS axes, 0.625 mm in-plane, slices 4 mm apart, covering the DESS field."""
    sp = np.linalg.norm(affine[:3, :3], axis=0)
    extent = np.asarray(shape) * sp
    out_sp = np.array([PIXEL_MM, PIXEL_MM, PITCH_MM])
    n = np.floor(extent / out_sp).astype(int)
    direction = affine[:3, :3] / sp
    # first voxel centre: half an output voxel inside the DESS field's corner
    corner = affine[:3, 3] - direction @ (0.5 * sp)
    A = np.eye(4)
    A[:3, :3] = direction * out_sp
    A[:3, 3] = corner + direction @ (0.5 * out_sp)
    return tuple(int(x) for x in n), A


def resample(img: np.ndarray, src_affine: np.ndarray, out_shape, out_affine: np.ndarray) -> np.ndarray:
    """Partial-volume resampling: a box of the output voxel (in-plane pixel x slice thickness) as a Gaussian."""
    sp = np.linalg.norm(src_affine[:3, :3], axis=0)
    width = np.array([PIXEL_MM, PIXEL_MM, THICK_MM]) / sp
    smooth = ndimage.gaussian_filter(img.astype(np.float32), width / np.sqrt(12.0), mode="nearest")
    M = np.linalg.inv(src_affine) @ out_affine            # output index -> source index
    return ndimage.affine_transform(smooth, M[:3, :3], offset=M[:3, 3], output_shape=out_shape, order=1,
                                    mode="nearest", output=np.float32)


def seeds_from_labels(lab: np.ndarray, affine: np.ndarray, out_shape, out_affine: np.ndarray) -> dict:
    """Per bone, in every other output slice holding it, the label voxel nearest its centroid there (LPS)."""
    sp = np.linalg.norm(affine[:3, :3], axis=0)
    # source slice index of each output slice centre
    k_src = (np.linalg.inv(affine) @ out_affine @ np.c_[np.zeros((out_shape[2], 2)), np.arange(out_shape[2]),
                                                          np.ones(out_shape[2])].T)[2]
    half = 0.5 * PITCH_MM / sp[2]
    out = {}
    for name, b in BONES.items():
        pts = []
        for kk in k_src[::2]:
            lo, hi = int(np.ceil(kk - half)), int(np.floor(kk + half))
            sub = np.argwhere(lab[:, :, max(lo, 0):max(hi + 1, 0)] == b)
            if len(sub) < 50:
                continue
            sub[:, 2] += max(lo, 0)
            c = sub.mean(axis=0)
            p = sub[np.argmin(np.linalg.norm((sub - c) * sp, axis=1))]
            pts.append((affine[:3, :3] @ p + affine[:3, 3]).round(1).tolist())
        if len(pts) >= 1:
            out[name] = pts
    return out


def voxelise(mesh, shape, affine) -> np.ndarray:
    """A closed mesh filled on a grid, slice by slice (sections along the grid's third axis, even-odd fill)."""
    import trimesh
    from skimage.draw import polygon

    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    inv = np.linalg.inv(affine)
    normal = affine[:3, 2] / np.linalg.norm(affine[:3, 2])
    ks = inv[2, :3] @ tm.vertices.T + inv[2, 3]
    out = np.zeros(shape, bool)
    for k in range(max(int(np.floor(ks.min())), 0), min(int(np.ceil(ks.max())) + 1, shape[2])):
        origin = affine[:3, :3] @ np.array([0.0, 0.0, k]) + affine[:3, 3]
        sec = tm.section(plane_origin=origin, plane_normal=normal)
        if sec is None:
            continue
        fill = np.zeros(shape[:2], bool)
        for loop in sec.discrete:
            ij = (loop @ inv[:3, :3].T + inv[:3, 3])[:, :2]
            rr, cc = polygon(ij[:, 0], ij[:, 1], shape[:2])
            fill[rr, cc] ^= True
        out[:, :, k] = fill
    return out


def dice(a: np.ndarray, b: np.ndarray) -> float:
    s = int(a.sum()) + int(b.sum())
    return 2.0 * int((a & b).sum()) / s if s else float("nan")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_knee_dess"))
    ap.add_argument("--cortex-mm", type=float, default=1.0)
    ap.add_argument("--body-mm", type=float, default=30.0, help="body outline: this far from the labels")
    ap.add_argument("--fat-mm", type=float, default=8.0, help="subcutaneous fat: the body's outer layer")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    from bonecap.io.imaging import read_nrrd, write_nifti
    from bonecap.io.mesh import read_mesh
    from bonecap.meshing import mesh_from_slices
    from bonecap.model import Volume

    work = args.work
    work.mkdir(parents=True, exist_ok=True)
    lab_vol = read_nrrd(LABELS)
    lab = np.asarray(lab_vol.data)
    sp = np.linalg.norm(lab_vol.affine[:3, :3], axis=0)
    tissues = yaml.safe_load((ROOT / "bonecap/phantom/tissue_intensities.yaml").read_text())
    rng = np.random.default_rng(args.seed)

    t0 = time.perf_counter()
    full = render_full(lab, sp, tissues["tissues"], args.cortex_mm, args.body_mm, args.fat_mm, rng)
    shape, A = mese_grid(lab.shape, lab_vol.affine)
    img = resample(full, lab_vol.affine, shape, A)
    sigma = float(tissues["noise_sigma"])
    img = np.hypot(img + rng.normal(0, sigma, img.shape), rng.normal(0, sigma, img.shape)).astype(np.float32)
    mri = work / "knee_dess_as_mese.nii.gz"
    write_nifti(Volume(img, A, {"modality": "MR", "series_description": "DESS labels rendered as MESE T2"}), mri)
    seeds = {"frame": "lps", "units": "mm", "margin_mm": 4,
             "description": "from the DESS labels (benchmarks/bench_knee_dess.py)",
             "seeds": seeds_from_labels(lab, lab_vol.affine, shape, A)}
    (work / "seeds.yaml").write_text(yaml.safe_dump(seeds, sort_keys=False))
    t_render = time.perf_counter() - t0

    subj = work / "subject"
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "bonecap", "build-subject", str(mri), "--seeds",
                          str(work / "seeds.yaml"), "-o", str(subj)], capture_output=True, text=True)
    t_build = time.perf_counter() - t0
    if res.returncode != 0:
        raise SystemExit(f"build-subject failed: {res.stderr}")

    rows = {}
    for name, b in BONES.items():
        truth = lab == b
        row = {"truth_cm3": float(truth.sum() * np.prod(sp) / 1000)}
        ext = subj / "extracted" / f"{name}.ply"
        if ext.is_file():
            m = voxelise(read_mesh(ext), lab.shape, lab_vol.affine)
            row.update(dice=dice(m, truth), extracted_cm3=float(m.sum() * np.prod(sp) / 1000))
        frac = resample(truth.astype(np.float32), lab_vol.affine, shape, A)
        oracle = mesh_from_slices([(frac >= 0.5, A)])
        row["oracle_dice"] = dice(voxelise(oracle, lab.shape, lab_vol.affine), truth)
        rows[name] = row
    result = {"command": " ".join(sys.argv), "cortex_mm": args.cortex_mm, "body_mm": args.body_mm,
              "fat_mm": args.fat_mm, "mese_shape": list(shape),
              "render_s": round(t_render, 1), "build_subject_s": round(t_build, 1), "bones": rows}
    (work / "result.json").write_text(json.dumps(result, indent=2))
    print(f"rendered {shape} in {t_render:.1f} s; build-subject {t_build:.1f} s")
    print("| bone | Dice | oracle Dice | truth cm³ | extracted cm³ |")
    print("|---|---:|---:|---:|---:|")
    for name, r in rows.items():
        print(f"| {name} | {r.get('dice', float('nan')):.3f} | {r['oracle_dice']:.3f} | {r['truth_cm3']:.1f} | "
              f"{r.get('extracted_cm3', float('nan')):.1f} |")


if __name__ == "__main__":
    main()
