"""Benchmark of build-subject stage 1 (stations) and capsule detection against the phantom's truth.

- **Registration** (:func:`bonecap.stations.register_stations`, default gauge):
  for each consecutive pair of stations, the residual relative motion
  ``inv(C_a T_a) @ (C_b T_b)`` (``C`` our correction, ``T`` the truth's
  ``true_to_nominal``) in mm at the body voxels of their overlap (mean, max)
  and in degrees, next to the true relative motion before correction; NCC of
  the overlap before/after; seconds per pair.
- **Intensity** (:func:`bonecap.stations.normalise_intensity`, reference =
  station 1): estimated scale vs the truth's ``intensity_scale`` ratio (the
  stations' own bias fields, up to 15 %, are not in the truth: they are what
  an overlap cannot tell from a gain).
- **Capsules** (:func:`bonecap.segmentation.capsules.find_capsules`) in every
  forearm stack: found/true, error along the slice axis and in-plane (max,
  mean); detections in the whole-body stations (which carry none).
- **Analytic capsules**: 8 mm oil spheres tangent to a rendered limb at random
  sub-slice depths on a 1.8 x 1.8 x 5 mm grid with bias, texture and noise
  (the tests' scene), over several seeds; then the same with capsules unlike
  the model (radius 4.4 or 3.6 mm against the assumed 4.0, a 6 mm slice
  profile against the assumed 5 mm), radius fixed or fitted. The phantom
  renders perfect spheres with a box slice profile, exactly what the fit
  assumes, so these rows are the fairer guess for real capsules.

Prints markdown tables. Run with::

    .venv/bin/python benchmarks/bench_stations.py [PHANTOM_DIR] [--seeds 10] [--no-station-capsules]

``PHANTOM_DIR`` is the output of ``bonecap phantom -o DIR --seed 1`` (default
``/tmp/ph_default``; made in a temporary folder when missing).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from bonecap.io.imaging import read_volumes
from bonecap.segmentation.capsules import find_capsules, match_capsules
from bonecap.stations import normalise_intensity, register_stations, station_z_range


def _deg(T):
    return float(np.degrees(np.linalg.norm(Rotation.from_matrix(T[:3, :3]).as_rotvec())))


def _overlap_body_points(upper, lower, thr, step=3):
    zlo = station_z_range(upper)[0]
    ks = [k for k in range(lower.shape[2]) if lower.index_to_world(np.array([0.0, 0.0, k]))[2] >= zlo]
    ii, jj, kk = np.nonzero(lower.data[::step, ::step][:, :, ks] > thr)
    return lower.index_to_world(np.c_[ii * step, jj * step, np.asarray(ks)[kk]])


def bench_registration(root: Path):
    st = json.loads((root / "truth" / "stations.json").read_text())["stations"]
    t0 = time.perf_counter()
    vols = []
    for s in st:
        v = read_volumes(root / "mri" / s["name"])[0]
        v.metadata["station"] = s["name"]
        vols.append(v)
    t_read = time.perf_counter() - t0
    t0, c0 = time.perf_counter(), time.process_time()
    out, rep = register_stations(vols)
    t_reg, c_reg = time.perf_counter() - t0, time.process_time() - c0
    t0, c0 = time.perf_counter(), time.process_time()
    _, scales = normalise_intensity(out, reference=0)
    t_norm, c_norm = time.perf_counter() - t0, time.process_time() - c0
    T = {s["name"]: np.array(s["true_to_nominal"]) for s in st}
    true_scale = np.array([s["intensity_scale"] for s in st])
    true_scale = true_scale / true_scale[0]
    E = [r["correction"] @ T[r["name"]] for r in rep]
    print(f"\nStations: {root} ({len(st)} stations), read {t_read:.1f} s, register {t_reg:.1f} s wall / "
          f"{c_reg:.1f} s CPU, normalise {t_norm:.1f} s wall / {c_norm:.1f} s CPU\n")
    print("| pair | true rel. motion mm (mean/max at body) | true rel. deg | residual mm (mean/max) | residual deg "
          "| NCC before -> after | s |")
    print("|---|---|---|---|---|---|---|")
    worst = 0.0
    for s in range(1, len(out)):
        p = _overlap_body_points(out[s - 1], out[s], thr=1000.0)
        # Truth relative motion: where a body point of the lower station's frame lies in the upper's.
        Dt = T[rep[s - 1]["name"]] @ np.linalg.inv(T[rep[s]["name"]])
        D = np.linalg.inv(E[s - 1]) @ E[s]
        dt = np.linalg.norm(p @ Dt[:3, :3].T + Dt[:3, 3] - p, axis=1)
        d = np.linalg.norm(p @ D[:3, :3].T + D[:3, 3] - p, axis=1)
        worst = max(worst, float(d.max()))
        pr = rep[s]["pair"]
        print(f"| {rep[s - 1]['name']}-{rep[s]['name']} | {dt.mean():.2f} / {dt.max():.2f} | {_deg(Dt):.3f} | "
              f"{d.mean():.2f} / {d.max():.2f} | {_deg(D):.3f} | {pr['ncc_before']:.4f} -> {pr['ncc_after']:.4f} "
              f"| {pr['seconds']:.2f} |")
    print(f"\nWorst residual at the body: {worst:.2f} mm (pixel {vols[0].spacing[0]:.1f} mm)\n")
    print("| station | scale est. | scale truth (rel. station 1) | error % |")
    print("|---|---|---|---|")
    for r, e, t in zip(rep, scales, true_scale):
        print(f"| {r['name']} | {e:.4f} | {t:.4f} | {100 * (e / t - 1):+.1f} |")


def bench_capsules(root: Path, station_capsules: bool):
    fa = json.loads((root / "truth" / "forearm.json").read_text())
    print("\n| forearm stack | found / true | along slices max / mean mm | in-plane max / mean mm | s |")
    print("|---|---|---|---|---|")
    for tw, pose in fa["poses"].items():
        v = read_volumes(root / pose["folder"])[0]
        t0 = time.perf_counter()
        c, info = find_capsules(v, radius_mm=fa["capsule_radius_mm"])
        dt = time.perf_counter() - t0
        truth = np.array(pose["capsule_centres_lps"])
        idx, _ = match_capsules(c, truth, 5.0, return_index=True)
        m = idx >= 0
        n = v.direction[:, 2]
        e = c[idx[m]] - truth[m]
        ez = np.abs(e @ n)
        exy = np.linalg.norm(e - np.outer(e @ n, n), axis=1)
        sp = v.spacing
        print(f"| {tw} deg ({sp[0]:.1f} mm px, {sp[2]:.1f} mm slices) | {len(c)} ({m.sum()} matched) / {len(truth)} "
              f"| {ez.max():.2f} / {ez.mean():.2f} | {exy.max():.2f} / {exy.mean():.2f} | {dt:.1f} |")
    if station_capsules:
        st = json.loads((root / "truth" / "stations.json").read_text())["stations"]
        found, secs = 0, 0.0
        for s in st:
            v = read_volumes(root / "mri" / s["name"])[0]
            t0 = time.perf_counter()
            found += len(find_capsules(v)[0])
            secs += time.perf_counter() - t0
        print(f"\nCapsules found in the {len(st)} whole-body stations (truth: none): {found}, {secs:.1f} s in all")


def bench_analytic(seeds: int):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from test_capsules import _errors, _scene

    dz_all, dxy_all, missed, secs = [], [], 0, 0.0
    for seed in range(seeds):
        vol, truth = _scene(1.8, 5.0, np.random.default_rng(seed))
        t0 = time.perf_counter()
        found, _ = find_capsules(vol)
        secs += time.perf_counter() - t0
        idx, _ = match_capsules(found, truth, 5.0, return_index=True)
        missed += int((idx < 0).sum())
        if np.all(idx >= 0):
            dz, dxy = _errors(found, truth)
            dz_all.append(dz)
            dxy_all.append(dxy)
    dz, dxy = np.concatenate(dz_all), np.concatenate(dxy_all)
    print(f"\nAnalytic spheres, 1.8 x 1.8 x 5 mm, {seeds} scenes x 6 capsules: missed {missed}; along slices "
          f"max {dz.max():.2f} / mean {dz.mean():.2f} / p95 {np.percentile(dz, 95):.2f} mm; in-plane max "
          f"{dxy.max():.2f} / mean {dxy.mean():.2f} mm; {secs / seeds:.2f} s per scene")


def bench_mismatch(seeds: int):
    """Capsules unlike the model: radius off by 10 %, slice profile thicker than assumed."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from test_capsules import _scene

    print("\n| capsules (1.8 x 1.8 x 5 mm grid) | fit | missed | along slices max / mean mm "
          "| in-plane max / mean mm |")
    print("|---|---|---|---|---|")
    for r_true, thick, fit in ((4.4, 5.0, False), (4.4, 5.0, True), (3.6, 5.0, False), (3.6, 5.0, True),
                               (4.0, 6.0, False)):
        dz, dxy, missed = [], [], 0
        for seed in range(seeds):
            vol, truth = _scene(1.8, 5.0, np.random.default_rng(100 + seed), caps_r=r_true, thickness=thick)
            found, _ = find_capsules(vol, radius_mm=4.0, slice_thickness_mm=5.0, fit_radius=fit)
            idx, _ = match_capsules(found, truth, 5.0, return_index=True)
            missed += int((idx < 0).sum())
            e = found[idx[idx >= 0]] - truth[idx >= 0]
            dz.append(np.abs(e[:, 2]))
            dxy.append(np.linalg.norm(e[:, :2], axis=1))
        dz, dxy = np.concatenate(dz), np.concatenate(dxy)
        what = f"R {r_true} mm (model 4.0), profile {thick} mm (model 5.0)"
        print(f"| {what} | {'radius fitted' if fit else 'radius fixed'} | {missed}/{6 * seeds} | "
              f"{dz.max():.2f} / {dz.mean():.2f} | {dxy.max():.2f} / {dxy.mean():.2f} |")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("phantom", nargs="?", default="/tmp/ph_default")
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--no-station-capsules", action="store_true")
    args = ap.parse_args(argv)
    root = Path(args.phantom)
    if not (root / "truth" / "stations.json").exists():
        from bonecap.phantom import make_phantom

        root = Path(tempfile.mkdtemp(prefix="bench_stations_"))
        make_phantom(root, seed=1)
    bench_registration(root)
    bench_capsules(root, not args.no_station_capsules)
    bench_analytic(args.seeds)
    bench_mismatch(max(2, args.seeds // 2))


if __name__ == "__main__":
    main()
