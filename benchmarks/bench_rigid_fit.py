"""Benchmark of the batched rigid fit against a per-frame scipy loop.

20 bones x 4 markers x 10 000 frames of noise-free synthetic data.

- ``bonecap``: one :func:`bonecap.motion.rigid.fit_rigid_bones` call (one
  batched SVD over all frames and bones); median of 3 runs.
- ``scipy loop``: the usual per-frame, per-bone Python loop, centring the
  markers and calling :meth:`scipy.spatial.transform.Rotation.align_vectors`
  (Kabsch), run on a subset of frames and scaled to the full count.

Prints markdown table lines (frames/s of both, speed ratio) and the accuracy
(max error against the known truth). Run with::

    .venv/bin/python benchmarks/bench_rigid_fit.py [--frames 10000] [--subset 500]
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np
import scipy
from scipy.spatial.transform import Rotation

from bonecap.motion.rigid import fit_rigid_bones, rotation_angle_deg


def make_data(n_frames: int, n_bones: int, n_markers: int, seed: int = 0):
    """Random marker clusters (bone frame), random true poses and the lab data they give."""
    rng = np.random.default_rng(seed)
    local_by_bone = {f"bone{b:02d}": rng.normal(scale=50.0, size=(n_markers, 3)) for b in range(n_bones)}
    index_by_bone = {name: list(range(b * n_markers, (b + 1) * n_markers))
                     for b, name in enumerate(local_by_bone)}
    R = Rotation.random(n_frames * n_bones, random_state=seed).as_matrix().reshape(n_frames, n_bones, 3, 3)
    t = rng.uniform(-2000.0, 2000.0, size=(n_frames, n_bones, 3))
    truth = np.zeros((n_frames, n_bones, 4, 4))
    truth[..., :3, :3] = R
    truth[..., :3, 3] = t
    truth[..., 3, 3] = 1.0
    local = np.stack(list(local_by_bone.values()))  # (B, m, 3)
    measured = np.einsum("fbij,bmj->fbmi", R, local) + t[:, :, None, :]
    measured = measured.reshape(n_frames, n_bones * n_markers, 3)
    return local_by_bone, index_by_bone, measured, truth


def scipy_loop(local_by_bone, index_by_bone, measured):
    """Per frame, per bone: centre, Rotation.align_vectors, translation from centroids."""
    F = measured.shape[0]
    B = len(local_by_bone)
    out = np.zeros((F, B, 4, 4))
    out[..., 3, 3] = 1.0
    items = [(loc, loc.mean(axis=0), idx) for loc, idx in
             zip(local_by_bone.values(), index_by_bone.values())]
    for f in range(F):
        for b, (loc, cl, idx) in enumerate(items):
            q = measured[f, idx]
            cq = q.mean(axis=0)
            rot, _ = Rotation.align_vectors(q - cq, loc - cl)  # maps local -> lab
            R = rot.as_matrix()
            out[f, b, :3, :3] = R
            out[f, b, :3, 3] = cq - R @ cl
    return out


def max_errors(T, truth):
    return (float(np.max(np.abs(T[..., :3, :3] - truth[..., :3, :3]))),
            float(np.max(np.abs(T[..., :3, 3] - truth[..., :3, 3]))),
            float(np.max(rotation_angle_deg(T, truth))))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=10_000)
    ap.add_argument("--bones", type=int, default=20)
    ap.add_argument("--markers", type=int, default=4)
    ap.add_argument("--subset", type=int, default=500, help="frames for the scipy loop")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    F, B, m = args.frames, args.bones, args.markers
    local_by_bone, index_by_bone, measured, truth = make_data(F, B, m)

    times, fit = [], None
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        fit = fit_rigid_bones(local_by_bone, index_by_bone, measured)
        times.append(time.perf_counter() - t0)
    t_batched = float(np.median(times))
    assert fit.valid.all()

    S = min(args.subset, F)
    t0 = time.perf_counter()
    T_scipy = scipy_loop(local_by_bone, index_by_bone, measured[:S])
    t_scipy_subset = time.perf_counter() - t0
    t_scipy = t_scipy_subset * F / S

    fps_batched = F / t_batched
    fps_scipy = F / t_scipy
    print(f"<!-- numpy {np.__version__}, scipy {scipy.__version__}, python {platform.python_version()}, "
          f"{platform.machine()}; {B} bones x {m} markers x {F} frames -->")
    print("| method | frames | time (s) | frames/s | bone fits/s | speed-up |")
    print("|---|---:|---:|---:|---:|---:|")
    print(f"| bonecap `fit_rigid_bones` (batched SVD, median of {args.repeats}) | {F} | "
          f"{t_batched:.3f} | {fps_batched:,.0f} | {fps_batched * B:,.0f} | {t_scipy / t_batched:.0f}x |")
    print(f"| scipy `Rotation.align_vectors` per-frame loop ({S} frames, scaled) | {F} | "
          f"{t_scipy:.2f} | {fps_scipy:,.0f} | {fps_scipy * B:,.0f} | 1x |")
    print()
    eb = max_errors(fit.transforms, truth)
    es = max_errors(T_scipy, truth[:S])
    print("| method | max rotation-matrix error | max translation error (mm) | max angle error (deg) | "
          "max residual (mm) |")
    print("|---|---:|---:|---:|---:|")
    print(f"| bonecap | {eb[0]:.1e} | {eb[1]:.1e} | {eb[2]:.1e} | {np.nanmax(fit.residuals):.1e} |")
    print(f"| scipy loop | {es[0]:.1e} | {es[1]:.1e} | {es[2]:.1e} | -- |")


if __name__ == "__main__":
    main()
