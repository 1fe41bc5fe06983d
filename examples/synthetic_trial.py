"""Write a small synthetic trial and its animated bones, using bonecap's Python API.

A three-segment arm (upper arm, forearm, hand) swings for two seconds at
100 Hz; three markers ride on each segment. The script writes

- ``OUT_DIR/arm_swing.c3d``: the marker trajectories (mm, Z-up lab) with a
  short occlusion gap on one marker, through :func:`bonecap.io.c3d.write_c3d`;
- ``OUT_DIR/arm_swing.glb``: the segments as animated meshes, through
  :func:`bonecap.io.gltf.write_animated_glb`, to open in any glTF viewer.

Usage: ``python examples/synthetic_trial.py OUT_DIR`` then
``bonecap inspect OUT_DIR/arm_swing.c3d OUT_DIR/arm_swing.glb``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from bonecap.io.c3d import write_c3d
from bonecap.io.gltf import write_animated_glb
from bonecap.model import Mesh, Motion, Trial

RATE = 100.0
SEGMENTS = {"upper_arm": 300.0, "forearm": 260.0, "hand": 90.0}  # lengths in mm


def arm_motion(n_frames: int = 200) -> Motion:
    """Segment poses (segment frame -> Z-up lab, mm): shoulder at 1400 mm, the arm swinging."""
    t = np.arange(n_frames) / RATE
    shoulder = np.array([0.0, 0.0, 1400.0])
    # Joint angles (rad) about the lab's Y axis: shoulder swing, elbow flexion, wrist.
    angles = np.stack([0.6 * np.sin(np.pi * t), 0.8 + 0.5 * np.sin(np.pi * t), 0.3 * np.sin(2 * np.pi * t)], 1)
    transforms = np.zeros((n_frames, len(SEGMENTS), 4, 4))
    origin = np.tile(shoulder, (n_frames, 1))
    cumulative = np.zeros(n_frames)
    for b, length in enumerate(SEGMENTS.values()):
        cumulative = cumulative + angles[:, b]
        R = Rotation.from_rotvec(np.outer(cumulative, [0.0, 1.0, 0.0])).as_matrix()
        transforms[:, b, :3, :3] = R
        transforms[:, b, :3, 3] = origin
        transforms[:, b, 3, 3] = 1.0
        origin = origin + R @ np.array([0.0, 0.0, -length])  # segments hang along their -Z
    return Motion(list(SEGMENTS), t, transforms)


def segment_meshes() -> dict[str, Mesh]:
    meshes = {}
    for name, length in SEGMENTS.items():
        cyl = trimesh.creation.cylinder(radius=25.0 if name != "hand" else 35.0, height=length, sections=24)
        cyl.apply_translation([0.0, 0.0, -length / 2])
        meshes[name] = Mesh(cyl.vertices, cyl.faces, frame=name)
    return meshes


def markers_on_segments(motion: Motion) -> Trial:
    """Three markers per segment, 40 mm off its axis; one occluded for 20 frames."""
    labels, points = [], []
    for b, (name, length) in enumerate(SEGMENTS.items()):
        local = np.array([[40.0, 0.0, -0.2 * length], [0.0, 40.0, -0.6 * length], [-40.0, 0.0, -0.9 * length]])
        T = motion.transforms[:, b]
        points.append(np.einsum("fij,mj->fmi", T[:, :3, :3], local) + T[:, None, :3, 3])
        labels += [f"{name.upper()}{k}" for k in range(1, 4)]
    pts = np.concatenate(points, axis=1)
    pts[80:100, 4] = np.nan  # an occlusion gap
    return Trial(labels, pts, RATE, prefixes=["Demo"] * len(labels))


def main(out_dir: str) -> None:
    out = Path(out_dir)
    motion = arm_motion()
    write_c3d(markers_on_segments(motion), out / "arm_swing.c3d")
    write_animated_glb(out / "arm_swing.glb", segment_meshes(), motion)
    print(f"wrote {out / 'arm_swing.c3d'} and {out / 'arm_swing.glb'}")


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    main(sys.argv[1])
