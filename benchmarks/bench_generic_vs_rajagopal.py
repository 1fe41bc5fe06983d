"""How realistic is the generic skeleton? Compare its bones with the Rajagopal2016 meshes.

For each bone (or group of bones) of the generic skeleton, the corresponding meshes of
the Rajagopal2016 OpenSim model at its default pose (``../shared/data/bones/opensim/
rajagopal2016_default_pose_ply/``, metres, same world axes: X forward, Y up, Z right)
are the yardstick. Our bone is brought onto the reference by a similarity transform
(scale + rotation + translation): initialised by the centroids and the RMS radii (the
frames already agree), refined by a trimmed, symmetric point-to-point ICP with Umeyama
steps on dense surface samples. Reported per bone: the symmetric mean surface distance
(mm, mean of both directions) and the 95th percentile, the similarity scale, and shape
ratios measured the same way on both meshes (radius distal/proximal width, ulna
proximal/distal width, femoral neck-shaft angle, femur length / head diameter).

The shapes of the generic skeleton are authored (parametric); nothing is fitted to
these meshes. Run::

    .venv/bin/python benchmarks/bench_generic_vs_rajagopal.py [--out table.md]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parents[1]
REF_DIR = ROOT.parent / "shared" / "data" / "bones" / "opensim" / "rajagopal2016_default_pose_ply"

# ours (list of bone names) -> reference (list of ply files)
PAIRS = [
    ("femur_r", ["femur_r"], ["femur_r__r_femur.ply"]),
    ("femur_l", ["femur_l"], ["femur_l__l_femur.ply"]),
    ("tibia_r", ["tibia_r"], ["tibia_r__r_tibia.ply"]),
    ("fibula_r", ["fibula_r"], ["tibia_r__r_fibula.ply"]),
    ("humerus_r", ["humerus_r"], ["humerus_r__humerus_rv.ply"]),
    ("radius_r", ["radius_r"], ["radius_r__radius_rv.ply"]),
    ("ulna_r", ["ulna_r"], ["ulna_r__ulna_rv.ply"]),
    ("pelvis", ["sacrum", "hip_r", "hip_l"], ["pelvis__sacrum.ply", "pelvis__r_pelvis.ply", "pelvis__l_pelvis.ply"]),
    ("pelvis: hip_r", ["hip_r"], ["pelvis__r_pelvis.ply"]),
    ("pelvis: sacrum", ["sacrum"], ["pelvis__sacrum.ply"]),
    ("patella_r", ["patella_r"], ["patella_r__r_patella.ply"]),
    ("talus_r", ["talus_r"], ["talus_r__r_talus.ply"]),
    ("foot_r (calcaneus+foot)", ["calcaneus_r", "foot_r"], ["calcn_r__r_foot.ply", "toes_r__r_bofoot.ply"]),
    ("hand_r (carpals+rays)", ["carpals_r"] + [f"ray{i}_r" for i in range(1, 6)], "hand_r__*"),
    ("skull", ["skull"], ["torso__hat_skull.ply"]),
    ("mandible", ["mandible"], ["torso__hat_jaw.ply"]),
    ("spine C1-L5", [f"c{i}" for i in range(1, 8)] + [f"t{i}" for i in range(1, 13)] + [f"l{i}" for i in range(1, 6)],
     ["torso__hat_spine.ply"]),
    ("ribs+sternum+scapulae+clavicles",
     [f"rib{i}_{s}" for i in range(1, 13) for s in "rl"] + ["sternum"]
     + [f"{b}_{s}" for b in ("scapula", "clavicle") for s in "rl"], ["torso__hat_ribs_scap.ply"]),
]
LONG_BONES = {"femur_r", "femur_l", "tibia_r", "fibula_r", "humerus_r", "radius_r", "ulna_r", "pelvis"}


def load_reference(files) -> trimesh.Trimesh:
    if isinstance(files, str):
        paths = sorted(REF_DIR.glob(files + ".ply"))
    else:
        paths = [REF_DIR / f for f in files]
    meshes = [trimesh.load(p, process=True) for p in paths]
    m = trimesh.util.concatenate(meshes)
    m.apply_scale(1000.0)          # metres -> mm
    return m


def ours_mesh(skeleton, names) -> trimesh.Trimesh:
    parts = []
    for n in names:
        wm = skeleton.world_mesh(n)
        parts.append(trimesh.Trimesh(wm.vertices, wm.faces, process=False))
    return trimesh.util.concatenate(parts)


def surface_samples(mesh: trimesh.Trimesh, spacing: float, seed: int = 0) -> np.ndarray:
    """Uniform random surface samples, about one per ``spacing``^2 mm^2 (plus the vertices)."""
    n = int(np.clip(mesh.area / spacing ** 2, 2000, 120000))
    pts, _ = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return np.vstack([pts, mesh.vertices])


def umeyama(src: np.ndarray, dst: np.ndarray, w: np.ndarray | None = None):
    """Similarity (s, R, t) minimising sum w |s R src + t - dst|^2 (no reflection)."""
    w = np.ones(len(src)) if w is None else w
    w = w / w.sum()
    ms, md = w @ src, w @ dst
    A, B = src - ms, dst - md
    cov = (B * w[:, None]).T @ A
    U, S, Vt = np.linalg.svd(cov)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    var = w @ np.sum(A * A, axis=1)
    s = np.trace(np.diag(S) @ D) / var
    t = md - s * R @ ms
    return s, R, t


def similarity_icp(src_pts, dst_pts, iters: int = 40, trim: float = 0.9):
    """Symmetric, trimmed point-to-point ICP with a similarity transform, src -> dst."""
    s0 = np.sqrt(np.mean(np.sum((dst_pts - dst_pts.mean(0)) ** 2, 1)) /
                 np.mean(np.sum((src_pts - src_pts.mean(0)) ** 2, 1)))
    best = None
    tree_d = cKDTree(dst_pts)
    rng = np.random.default_rng(0)
    sub_s = src_pts[rng.choice(len(src_pts), min(len(src_pts), 4000), replace=False)]
    sub_d = dst_pts[rng.choice(len(dst_pts), min(len(dst_pts), 4000), replace=False)]
    for ang in [(0, 0, 0), (0, 0, 10), (0, 0, -10)]:
        R = _rot(ang)
        s = s0
        t = dst_pts.mean(0) - s * R @ src_pts.mean(0)
        for _ in range(iters):
            cur = s * sub_s @ R.T + t
            d1, i1 = tree_d.query(cur)
            tree_s = cKDTree(cur)
            d2, i2 = tree_s.query(sub_d)
            A = np.vstack([sub_s, sub_s[i2]])
            B = np.vstack([dst_pts[i1], sub_d])
            dd = np.concatenate([d1, d2])
            keep = dd <= np.quantile(dd, trim)
            s_new, R_new, t_new = umeyama(A[keep], B[keep])
            change = abs(s_new - s) + np.abs(R_new - R).sum() + np.abs(t_new - t).sum() / 100
            s, R, t = s_new, R_new, t_new
            if change < 1e-6:
                break
        cur = s * sub_s @ R.T + t
        score = np.mean(tree_d.query(cur)[0]) + np.mean(cKDTree(cur).query(sub_d)[0])
        if best is None or score < best[0]:
            best = (score, s, R, t)
    return best[1], best[2], best[3]


def _rot(angles_deg):
    ax, ay, az = np.radians(angles_deg)
    Rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    Ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    Rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def surface_distance(a: trimesh.Trimesh, b: trimesh.Trimesh, spacing: float = 1.0):
    """Symmetric surface distance between meshes (dense-sample approximation of the
    point-to-surface distance): (mean, p95, mean a->b, mean b->a)."""
    pa = surface_samples(a, spacing, 1)
    pb = surface_samples(b, spacing, 2)
    dab = cKDTree(pb).query(pa)[0]
    dba = cKDTree(pa).query(pb)[0]
    both = np.concatenate([dab, dba])
    return 0.5 * (dab.mean() + dba.mean()), float(np.quantile(both, 0.95)), dab.mean(), dba.mean()


# ---------------------------------------------------------------------------
# shape measurements, identical for both meshes (world orientation: Y up)


def _axis_and_extent(pts):
    c = pts.mean(0)
    _, _, Vt = np.linalg.svd(pts - c, full_matrices=False)
    ax = Vt[0] if Vt[0][1] > 0 else -Vt[0]          # pointing up
    t = (pts - c) @ ax
    return c, ax, t


def _hull_diameter(p2):
    from scipy.spatial import ConvexHull

    if len(p2) < 4:
        return 0.0
    h = p2[ConvexHull(p2).vertices]
    d = np.linalg.norm(h[:, None] - h[None], axis=2)
    return float(d.max())


def end_widths(mesh: trimesh.Trimesh, frac: float = 0.10):
    """Largest width perpendicular to the long axis in the proximal and distal ``frac``
    of the bone length: (proximal, distal, length)."""
    pts = surface_samples(mesh, 1.0)
    c, ax, t = _axis_and_extent(pts)
    L = t.max() - t.min()
    e1 = np.cross(ax, [1.0, 0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(ax, e1)
    out = []
    for sel in (t > t.max() - frac * L, t < t.min() + frac * L):
        q = pts[sel] - c
        out.append(_hull_diameter(np.stack([q @ e1, q @ e2], 1)))
    return out[0], out[1], L


def _fit_sphere(p):
    A = np.hstack([2 * p, np.ones((len(p), 1))])
    b = np.sum(p * p, axis=1)
    x = np.linalg.lstsq(A, b, rcond=None)[0]
    c = x[:3]
    return c, float(np.sqrt(x[3] + c @ c))


def femur_measures(mesh: trimesh.Trimesh, medial_sign: float):
    """Neck-shaft angle (deg), length / head diameter, head diameter (mm).

    ``medial_sign`` is -1 for a right femur (medial = -Z), +1 for a left one."""
    pts = surface_samples(mesh, 1.0)
    c, ax, t = _axis_and_extent(pts)
    L = t.max() - t.min()
    # shaft axis from the centroids of slabs at 30 % and 70 % of the length
    cen = []
    for f in (0.3, 0.7):
        s = np.abs(t - (t.min() + f * L)) < 0.02 * L
        cen.append(pts[s].mean(0))
    shaft = cen[1] - cen[0]
    shaft /= np.linalg.norm(shaft)                   # pointing up (proximal)
    # head: the medial part of the proximal 16 %
    top = t > t.max() - 0.16 * L
    q = pts[top]
    lat = np.array([0.0, 0.0, medial_sign])
    medial = q[(q - cen[1]) @ lat > np.quantile((q - cen[1]) @ lat, 0.55)]
    hc, r = _fit_sphere(medial)
    for _ in range(4):
        near = pts[np.abs(np.linalg.norm(pts - hc, axis=1) - r) < 2.5]
        near = near[(near - hc) @ (hc - cen[1]) > -0.2 * r] if len(near) > 50 else near
        hc, r = _fit_sphere(near)
    # neck axis: from the head centre through the centroid of the neck section
    d = cen[1] + shaft * 0.1 * L - hc
    d /= np.linalg.norm(d)
    for _ in range(5):
        slab = pts[np.abs((pts - hc) @ d - 1.45 * r) < 1.5]
        slab = slab[np.linalg.norm((slab - hc) - np.outer((slab - hc) @ d, d), axis=1) < 1.4 * r]
        if len(slab) < 10:
            break
        d = slab.mean(0) - hc
        d /= np.linalg.norm(d)
    neck = -d                                        # from the shaft toward the head
    nsa = np.degrees(np.arccos(np.clip(neck @ -shaft, -1, 1)))
    return nsa, L / (2 * r), 2 * r


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, help="also write the markdown table here")
    ap.add_argument("--stature", type=float, default=1700.0)
    args = ap.parse_args(argv)
    if not REF_DIR.is_dir():
        print(f"reference meshes not found: {REF_DIR}", file=sys.stderr)
        return 2
    sys.path.insert(0, str(ROOT))
    from bonecap.skeleton.generic import build_generic_skeleton

    t0 = time.perf_counter()
    sk = build_generic_skeleton(args.stature)
    t_build = time.perf_counter() - t0
    rows = []
    shape = {}
    for label, names, files in PAIRS:
        ours = ours_mesh(sk, names)
        ref = load_reference(files)
        s, R, t = similarity_icp(surface_samples(ours, 2.0), surface_samples(ref, 2.0))
        moved = ours.copy()
        moved.apply_transform(np.block([[s * R, t[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]]))
        mean, p95, ab, ba = surface_distance(moved, ref)
        rows.append((label, mean, p95, s, len(ours.faces), len(ref.faces)))
        if label.startswith(("radius_r", "ulna_r", "femur_r")):
            shape[label] = (ours, ref)
    lines = [f"Generic skeleton vs Rajagopal2016 (stature {args.stature:.0f} mm; build {t_build:.1f} s)", "",
             "| bone | mean surface distance (mm) | p95 (mm) | scale ours->ref | our triangles | ref triangles |",
             "|---|---:|---:|---:|---:|---:|"]
    for label, mean, p95, s, nf, nr in rows:
        flag = " *" if label.split(" ")[0] in LONG_BONES and mean > 5.0 else ""
        lines.append(f"| {label}{flag} | {mean:.2f} | {p95:.2f} | {s:.3f} | {nf} | {nr} |")
    lines += ["", "| shape ratio | generic | Rajagopal2016 |", "|---|---:|---:|"]
    o, r = shape["radius_r"]
    po, do_, _ = end_widths(o)
    pr, dr, _ = end_widths(r)
    lines.append(f"| radius distal / proximal width | {do_ / po:.2f} ({do_:.1f}/{po:.1f} mm) | "
                 f"{dr / pr:.2f} ({dr:.1f}/{pr:.1f} mm) |")
    o, r = shape["ulna_r"]
    po, do_, _ = end_widths(o)
    pr, dr, _ = end_widths(r)
    lines.append(f"| ulna proximal / distal width | {po / do_:.2f} ({po:.1f}/{do_:.1f} mm) | "
                 f"{pr / dr:.2f} ({pr:.1f}/{dr:.1f} mm) |")
    o, r = shape["femur_r"]
    nso, lho, hdo = femur_measures(o, -1.0)
    nsr, lhr, hdr = femur_measures(r, -1.0)
    lines.append(f"| femoral neck-shaft angle (deg) | {nso:.1f} (parameter {sk.bones['femur_r'].metadata['neck_shaft_angle_deg']:.0f}) | {nsr:.1f} |")
    lines.append(f"| femur length / head diameter | {lho:.2f} (head {hdo:.1f} mm) | {lhr:.2f} (head {hdr:.1f} mm) |")
    text = "\n".join(lines)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")
    bad = [r for r in rows if r[0].split(" ")[0] in LONG_BONES and r[1] > 5.0]
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
