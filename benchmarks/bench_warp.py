"""Benchmark of the personal skeleton: the default template warped onto a phantom's true bone meshes.

For every bone of the phantom's ``truth/meshes/`` (LPS), the template bone is
warped by :func:`bonecap.skeleton.warp.warp_skeleton` (rigid ICP, affine ICP,
Gaussian RBF) starting from :func:`bonecap.skeleton.warp.initial_transform`
(a similarity from the targets' centroids: no truth pose is given). Per bone
it prints the symmetric mean and 95th-percentile point-to-surface distance
(mm) of

- ``personal``: the warped bone vs the truth,
- ``affine``: the template after the per-bone affine ICP alone (the baseline),

the joint-centre error against ``truth/skeleton.json``, the feature points,
the RBF residual and the minimum Jacobian determinant; then the means and the
warp time. Optionally also meshes the phantom's oracle station labels with
:func:`bonecap.meshing.meshes_from_labels` and scores those meshes (time,
surface distance). Run with::

    .venv/bin/python benchmarks/bench_warp.py [/tmp/ph_default] [--bones femur_r,tibia_r] [--meshing]

The phantom folder is one written by ``bonecap phantom -o DIR`` (default:
``/tmp/ph_default``, ``--seed 1``).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from bonecap.io.mesh import read_mesh
from bonecap.meshing import surface_distance


def _sym(a, b) -> tuple[float, float]:
    d = np.concatenate([surface_distance(a.vertices, b), surface_distance(b.vertices, a)])
    return float(d.mean()), float(np.percentile(d, 95))


def bench_warp(root: Path, bones: list[str] | None) -> None:
    from bonecap.skeleton.template import load_template
    from bonecap.skeleton.warp import initial_transform, warp_skeleton

    t0 = time.perf_counter()
    template = load_template("default")
    t_template = time.perf_counter() - t0
    names = bones or [n for n, b in template.bones.items() if b.mesh is not None
                      and (root / "truth" / "meshes" / f"{n}.ply").is_file()]
    targets = {n: read_mesh(root / "truth" / "meshes" / f"{n}.ply") for n in names}
    truth = json.loads((root / "truth" / "skeleton.json").read_text())["bones"]
    init = initial_transform(template, targets)
    t0 = time.perf_counter()
    sk, report = warp_skeleton(template, targets, init=init)
    t_warp = time.perf_counter() - t0

    print("| bone | personal mean | personal p95 | affine mean | affine p95 | joint max | features | "
          "RBF residual mean | min det J | flags |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    rows = []
    for n in names:
        pm, pp = _sym(sk.world_mesh(n), targets[n])
        aff = template.world_mesh(n).transformed(np.array(report["transforms"][n]), "lps")
        am, ap = _sym(aff, targets[n])
        jc = [np.linalg.norm(sk.bones[n].landmark_in_world(k) - np.array(p))
              for k, p in truth[n]["joint_centres_lps"].items()]
        r = report["bones"][n]
        res = r["residual_mean_mm"]
        rows.append((pm, pp, am, ap, max(jc) if jc else np.nan))
        print(f"| {n} | {pm:.2f} | {pp:.2f} | {am:.2f} | {ap:.2f} | {max(jc) if jc else float('nan'):.2f} | "
              f"{r['n_features']} | {'-' if res is None else f'{res:.3f}'} | {r['min_jacobian_det']:.2f} | "
              f"{len(r['flags'])} |")
    a = np.array(rows)
    print()
    print(f"bones: {len(names)}; mean personal {a[:, 0].mean():.2f} mm (p95 mean {a[:, 1].mean():.2f}), "
          f"mean affine-only {a[:, 2].mean():.2f} mm (p95 mean {a[:, 3].mean():.2f}); "
          f"ratio {a[:, 2].mean() / a[:, 0].mean():.1f}x; joint centre max error median "
          f"{np.nanmedian(a[:, 4]):.2f} mm, p90 {np.nanpercentile(a[:, 4], 90):.2f} mm")
    print(f"warp {t_warp:.1f} s ({t_warp / len(names):.2f} s per bone); template build {t_template:.1f} s")


def bench_meshing(root: Path) -> None:
    from bonecap.io.imaging import read_volumes
    from bonecap.meshing import meshes_from_labels

    stations = json.loads((root / "truth" / "stations.json").read_text())["stations"]
    ids = json.loads((root / "truth" / "labels.json").read_text())["ids"]
    pieces = []
    for st in stations:
        v = read_volumes(root / "truth" / "labels" / f"{st['name']}_oracle.nii.gz")[0]
        # the oracle lies where the body was during the station: undo that motion (registration's job)
        pieces.append((np.asarray(v.data).astype(np.int16), np.linalg.inv(np.array(st["true_to_nominal"])) @ v.affine))
    t0 = time.perf_counter()
    meshes = meshes_from_labels(pieces, ids)
    dt = time.perf_counter() - t0
    d = [_sym(m, read_mesh(root / "truth" / "meshes" / f"{n}.ply")) for n, m in meshes.items()]
    watertight = sum(m.to_trimesh().is_watertight for m in meshes.values())
    print(f"meshing: {len(meshes)} bones from {len(pieces)} oracle stations in {dt:.1f} s; "
          f"surface distance to truth mean {np.mean([x[0] for x in d]):.2f} mm, "
          f"p95 mean {np.mean([x[1] for x in d]):.2f} mm; watertight {watertight}/{len(meshes)}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("phantom", nargs="?", default="/tmp/ph_default", help="a bonecap phantom output folder")
    ap.add_argument("--bones", default="", help="comma-separated bones (default: all with a truth mesh)")
    ap.add_argument("--meshing", action="store_true", help="also mesh the oracle station labels")
    args = ap.parse_args()
    root = Path(args.phantom)
    if not (root / "truth" / "skeleton.json").is_file():
        raise SystemExit(f"{root}: not a phantom folder (no truth/skeleton.json)")
    if args.meshing:
        bench_meshing(root)
    bench_warp(root, [b for b in args.bones.split(",") if b] or None)


if __name__ == "__main__":
    main()
