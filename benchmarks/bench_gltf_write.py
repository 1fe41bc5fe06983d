"""Benchmark: writing an animated skeleton to binary glTF.

30 bones (icospheres of 5 120 triangles each) x 10 000 frames of random rigid
poses are written with :func:`bonecap.io.gltf.write_animated_glb`; the median
of 3 runs is compared, in the same run, with :func:`numpy.save` of the same
``(F, B, 4, 4)`` float64 transforms array -- the least any writer of this data
must spend (one contiguous dump, no decomposition, no meshes).

Run from the repository root::

    .venv/bin/python benchmarks/bench_gltf_write.py [--bones 30] [--frames 10000]

Prints a few lines of detail and one markdown table row. Goal: <= 1 s.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bonecap.io.gltf import write_animated_glb  # noqa: E402
from bonecap.model import Mesh, Motion  # noqa: E402


def make_case(n_bones: int, n_frames: int, seed: int = 0) -> tuple[dict[str, Mesh], Motion]:
    """Icosphere bones and a smooth random rigid motion at 100 Hz."""
    import trimesh
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=30.0)  # 2 562 vertices, 5 120 faces
    names = [f"bone_{b:02d}" for b in range(n_bones)]
    meshes = {n: Mesh(sphere.vertices * [1.0, 1.0, 4.0], sphere.faces, n) for n in names}
    # Rotation vectors that wander (random walk) so quaternion signs do flip.
    rotvec = np.cumsum(rng.normal(scale=0.05, size=(n_frames, n_bones, 3)), axis=0)
    T = np.zeros((n_frames, n_bones, 4, 4))
    T[..., :3, :3] = Rotation.from_rotvec(rotvec.reshape(-1, 3)).as_matrix().reshape(n_frames, n_bones, 3, 3)
    T[..., :3, 3] = np.cumsum(rng.normal(scale=2.0, size=(n_frames, n_bones, 3)), axis=0) + [0, 0, 1000]
    T[..., 3, 3] = 1.0
    return meshes, Motion(names, np.arange(n_frames) / 100.0, T)


def median_time(fn, repeats: int = 3) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bones", type=int, default=30)
    parser.add_argument("--frames", type=int, default=10_000)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)

    meshes, motion = make_case(args.bones, args.frames)
    triangles = sum(len(m.faces) for m in meshes.values())
    with tempfile.TemporaryDirectory() as tmp:
        glb = Path(tmp) / "motion.glb"
        npy = Path(tmp) / "transforms.npy"
        t_glb = median_time(lambda: write_animated_glb(glb, meshes, motion), args.repeats)
        t_npy = median_time(lambda: np.save(npy, motion.transforms), args.repeats)
        size_glb, size_npy = glb.stat().st_size, npy.stat().st_size

    print(f"{args.bones} bones, {triangles} triangles, {args.frames} frames, median of {args.repeats}")
    print(f"write_animated_glb: {t_glb:.3f} s, {size_glb / 1e6:.1f} MB")
    print(f"numpy.save (F, B, 4, 4) float64: {t_npy:.3f} s, {size_npy / 1e6:.1f} MB")
    print()
    print("| case | bonecap .glb | size | numpy.save | size | ratio |")
    print("|---|---|---|---|---|---|")
    print(f"| {args.bones} bones x {args.frames} frames | {t_glb:.3f} s | {size_glb / 1e6:.1f} MB "
          f"| {t_npy:.3f} s | {size_npy / 1e6:.1f} MB | {t_glb / t_npy:.1f}x |")
    if t_glb > 1.0:
        print(f"WARNING: above the 1 s goal ({t_glb:.2f} s)", file=sys.stderr)


if __name__ == "__main__":
    main()
