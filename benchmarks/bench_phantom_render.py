"""Benchmark of the phantom's MRI renderer on a crude whole-body scene.

The scene (1.8 m tall, ~200k triangles with triangles of a few mm, like the
phantom subject's meshes): skin and fascia of a head, trunk, two arms beside
it and two legs, each as closed ellipsoids/elliptic cylinders, plus 14 tubular
bones (outer + inner surface) and a skull shell.

- ``bonecap``: :func:`bonecap.phantom.mri.plan_stations` (8 stations, 1.8 mm
  pixels, 5 mm pitch and thickness) then :func:`~bonecap.phantom.mri.render_stations`
  with oracle labels and the merged 2 mm label volume, DICOM written to a
  temporary folder; timed end to end (wall and CPU: the machine may be
  shared); memory as the process's peak RSS (and, with ``--tracemalloc``,
  the traced peak of the call, numpy buffers included; tracing slows the
  DICOM writing ~3x, so it is off for the timing by default).
- peers: the usual label-painting approach, point-in-mesh tests of every
  voxel centre against every layer (painter's order, no partial volume), with
  VTK's ``vtkSelectEnclosedPoints`` (pyvista ``select_interior_points``) and
  with ``trimesh.Trimesh.contains`` (rtree ray casting); run on random voxels
  of the largest station and scaled to all voxels of all stations. Partial
  volume by 4 x 4 x 4 point sub-samples would cost 64x more (also reported,
  scaled; the renderer integrates rows exactly, so its 4 x 4 sampling is
  comparable).

Prints markdown table lines. Run with::

    .venv/bin/python benchmarks/bench_phantom_render.py [--subset 20000] [--edge 9] [--tracemalloc]
"""

from __future__ import annotations

import argparse
import platform
import resource
import tracemalloc
import tempfile
import time

import numpy as np
import trimesh

from bonecap.model import Mesh
from bonecap.phantom.mri import plan_stations, render_stations


def _ellipsoid(centre, radii, edge):
    """Closed ellipsoid: an icosphere refined until its edges are about ``edge`` long."""
    sub = int(np.clip(np.ceil(np.log2(max(radii) * 1.1 / edge)), 1, 6))
    s = trimesh.creation.icosphere(subdivisions=sub, radius=1.0)
    return trimesh.Trimesh(s.vertices * radii + centre, s.faces, process=False)


def _tube(centre, radii, height, edge):
    """Closed elliptic cylinder along z, rings of quads split in two, fan-capped; edges ~ ``edge``."""
    n = max(16, int(np.ceil(2 * np.pi * max(radii) / edge)))
    m = max(1, int(np.ceil(height / edge)))
    th = 2 * np.pi * np.arange(n) / n
    z = np.linspace(-height / 2, height / 2, m + 1)
    ring = np.c_[radii[0] * np.cos(th), radii[1] * np.sin(th)]
    v = np.concatenate([np.c_[np.tile(ring, (m + 1, 1)), np.repeat(z, n)],
                        [[0, 0, -height / 2], [0, 0, height / 2]]])
    a = np.arange(n)
    b = (a + 1) % n
    faces = []
    for r in range(m):
        lo, hi = r * n, (r + 1) * n
        faces.append(np.c_[lo + a, lo + b, hi + b])
        faces.append(np.c_[lo + a, hi + b, hi + a])
    bot, top = (m + 1) * n, (m + 1) * n + 1
    faces.append(np.c_[np.full(n, bot), b, a])
    faces.append(np.c_[np.full(n, top), m * n + a, m * n + b])
    return trimesh.Trimesh(v + np.asarray(centre, float), np.concatenate(faces), process=False)


def _merge(parts):
    v, f, off = [], [], 0
    for p in parts:
        v.append(p.vertices)
        f.append(p.faces + off)
        off += len(p.vertices)
    return Mesh(np.concatenate(v), np.concatenate(f), "lps")


def make_scene(edge_mm: float = 9.0):
    """Layers and label meshes of the crude body (LPS mm, +z superior, feet at z = 0)."""
    segs = [  # (kind, centre, radii, height)
        ("ell", (0, 0, 1680), (80, 95, 115), None),      # head
        ("tube", (0, 0, 1230), (165, 110), 600),        # trunk, z 930..1530
        ("tube", (-240, 0, 1230), (45, 50), 560),       # left arm, beside the trunk
        ("tube", (240, 0, 1230), (45, 50), 560),        # right arm
        ("tube", (-95, 0, 460), (75, 80), 860),         # left leg, z 30..890
        ("tube", (95, 0, 460), (75, 80), 860),          # right leg
    ]
    skin, muscle = [], []
    for kind, c, r, h in segs:
        r = np.asarray(r, float)
        if kind == "ell":
            skin.append(_ellipsoid(c, r, edge_mm))
            muscle.append(_ellipsoid(c, r - 8, edge_mm))
        else:
            skin.append(_tube(c, r, h, edge_mm))
            muscle.append(_tube(c, r - 12, h - 8, edge_mm))
    bones = [  # (centre, outer radius, inner radius, height)
        ((-95, 0, 680), 14, 9, 380), ((95, 0, 680), 14, 9, 380),      # femurs
        ((-95, 5, 270), 12, 8, 360), ((95, 5, 270), 12, 8, 360),      # tibias
        ((-115, 25, 270), 6, 3, 340), ((115, 25, 270), 6, 3, 340),    # fibulas
        ((-240, 0, 1360), 12, 7, 280), ((240, 0, 1360), 12, 7, 280),  # humeri
        ((-245, -10, 1080), 8, 4, 240), ((245, -10, 1080), 8, 4, 240),  # radii
        ((-235, 12, 1080), 8, 4, 240), ((235, 12, 1080), 8, 4, 240),    # ulnae
        ((0, 60, 1230), 18, 12, 560),                                 # spine
        ((0, 0, 960), 60, 50, 50),                                    # pelvis ring (crude)
    ]
    outer, inner = [], []
    for c, ro, ri, h in bones:
        outer.append(_tube(c, (ro, ro), h, edge_mm / 2))
        inner.append(_tube(c, (ri, ri), h - 6, edge_mm / 2))
    outer.append(_ellipsoid((0, 0, 1690), np.array([72, 87, 105.0]), edge_mm / 1.5))  # skull
    inner.append(_ellipsoid((0, 0, 1690), np.array([65, 80, 98.0]), edge_mm / 1.5))
    layers = [(_merge(skin), "fat"), (_merge(muscle), "muscle")]
    labels = []
    for n, (o, i) in enumerate(zip(outer, inner)):
        mo = Mesh(o.vertices, o.faces, "lps")
        layers += [(mo, "cortex"), (Mesh(i.vertices, i.faces, "lps"), "marrow")]
        labels.append((mo, n + 1))
    return layers, labels


def _rss_mb() -> float:
    """Current resident set size (MiB), from /proc (Linux)."""
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def _voxel_subset(plan, n_points, seed=0):
    """World positions (true frame) of random voxel centres of one station."""
    I, J, K = plan.shape
    flat = np.random.default_rng(seed).choice(I * J * K, size=min(n_points, I * J * K), replace=False)
    ijk = np.c_[np.c_[np.unravel_index(flat, (I, J, K))], np.ones(flat.size)]
    return (np.linalg.inv(plan.true_to_nominal) @ plan.affine @ ijk.T).T[:, :3]


def peer_contains(layers, plan, n_points, method):
    """Label painting by point-in-mesh tests of voxel centres, painter's order; seconds per point.

    ``method``: ``"vtk"`` (pyvista ``select_interior_points`` with the
    ``cell_locator`` method, i.e. vtkSelectEnclosedPoints) or ``"trimesh"``
    (``Trimesh.contains``, rtree ray casting). Only the points inside a mesh's
    bounding box are tested against it.
    """
    import pyvista as pv

    world = _voxel_subset(plan, n_points)
    t0 = time.perf_counter()
    lab = np.zeros(len(world), np.int16)
    for n, (m, _) in enumerate(layers):
        lo, hi = m.vertices.min(axis=0), m.vertices.max(axis=0)
        idx = np.nonzero(np.all((world >= lo) & (world <= hi), axis=1))[0]
        if idx.size == 0:
            continue
        if method == "vtk":
            surf = pv.PolyData(m.vertices, np.c_[np.full(len(m.faces), 3), m.faces].ravel())
            sel = pv.PolyData(world[idx]).select_interior_points(surf, method="cell_locator",
                                                                 check_surface=False)
            inside = np.asarray(sel["selected_points"], bool)
        else:
            tm = trimesh.Trimesh(m.vertices, m.faces, process=False)
            # Small chunks: trimesh's ray casting holds every (ray, candidate
            # triangle) pair at once and exhausts memory on large batches.
            inside = np.concatenate([tm.contains(world[idx[c:c + 100]]) for c in range(0, idx.size, 100)])
        lab[idx[inside]] = n + 1
    return (time.perf_counter() - t0) / len(world)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subset", type=int, default=20000, help="voxels of one station for the VTK peer")
    ap.add_argument("--tracemalloc", action="store_true", help="also trace Python/numpy allocations")
    ap.add_argument("--subset-trimesh", type=int, default=300, help="voxels for the trimesh peer")
    ap.add_argument("--edge", type=float, default=9.0, help="target skin triangle edge (mm)")
    args = ap.parse_args(argv)

    t0 = time.perf_counter()
    layers, labels = make_scene(args.edge)
    n_tri = sum(len(m.faces) for m, _ in layers)
    t_scene = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    body = layers[0][0]
    plans = plan_stations(body, n_stations=8, rng=rng)
    n_vox = sum(int(np.prod(p.shape)) for p in plans)
    rss_before = _rss_mb()
    with tempfile.TemporaryDirectory() as tmp:
        if args.tracemalloc:
            tracemalloc.start()
        t0, c0 = time.perf_counter(), time.process_time()
        res = render_stations(layers, plans, tmp, rng, label_meshes=labels, show_progress=False)
        t_render, c_render = time.perf_counter() - t0, time.process_time() - c0
        traced = tracemalloc.get_traced_memory()[1] / 2**20 if args.tracemalloc else float("nan")
        tracemalloc.stop()
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB -> MiB on Linux
    plan = max(plans, key=lambda p: int(np.prod(p.shape)))
    per_vtk = peer_contains(layers, plan, args.subset, "vtk")
    per_tm = peer_contains(layers, plan, args.subset_trimesh, "trimesh")

    print(f"Scene: {n_tri} triangles in {len(layers)} layers, {len(labels)} labelled bones "
          f"(built in {t_scene:.1f} s); 8 stations, {n_vox / 1e6:.2f} M voxels "
          f"({', '.join('x'.join(map(str, p.shape)) for p in plans[:2])}, ...); merged labels "
          f"{'x'.join(map(str, res.merged_labels.shape))} at 2 mm. "
          f"{platform.processor() or platform.machine()}, numpy {np.__version__}, trimesh {trimesh.__version__}.")
    print()
    print("| method | what | time (s) | peak memory (MB) |")
    print("|---|---|---:|---:|")
    tm = res.timings_s
    print(f"| bonecap `render_stations` | render (4x4 sub-samples, bias, texture, Rician) "
          f"+ oracle labels + merged labels + DICOM | {t_render:.1f} wall, {c_render:.1f} CPU "
          f"(render {tm['render']:.1f}, labels {tm['labels']:.1f}, merged {tm['merged']:.1f}, "
          f"write {tm['write']:.1f}) | "
          + (f"{traced:.0f} traced; " if args.tracemalloc else "")
          + f"process peak RSS {peak:.0f} ({rss_before:.0f} before the call) |")
    for name, per, n in (("VTK `vtkSelectEnclosedPoints` (pyvista)", per_vtk, args.subset),
                         ("trimesh `contains` (rtree rays)", per_tm, args.subset_trimesh)):
        print(f"| {name} | 1 point per voxel (no partial volume), all layers, labels only; "
              f"measured on {n} voxels, scaled to {n_vox / 1e6:.2f} M | {per * n_vox:.0f} | - |")
        print(f"| {name} x 64 | same with 4 x 4 x 4 sub-samples for partial volume, scaled | "
              f"{64 * per * n_vox:.0f} | - |")

if __name__ == "__main__":
    main()
