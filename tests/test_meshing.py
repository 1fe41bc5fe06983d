"""Meshes from slice-wise masks (bonecap.meshing), checked against analytic shapes.

Every shape is voxelised on MRI-like grids (1.8 x 1.8 mm pixels, 5 mm slices)
by sampling its exact signed distance at the voxel centres, so the truth is
the analytic surface: distances are measured to it, not to another mesh.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bonecap.meshing import mesh_from_slices, meshes_from_labels, surface_distance
from bonecap.model import Mesh

SPACING = (1.8, 1.8, 5.0)


def voxelise(sdf, shape, origin, spacing=SPACING, rotation=None):
    """A boolean mask ``[i, j, k]`` of ``sdf < 0`` at the voxel centres and its voxel -> LPS affine."""
    R = np.eye(3) if rotation is None else rotation
    A = np.eye(4)
    A[:3, :3] = R @ np.diag(spacing)
    A[:3, 3] = R @ np.asarray(origin, dtype=float)
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1).reshape(-1, 3)
    world = ijk @ A[:3, :3].T + A[:3, 3]
    return (sdf(world) < 0).reshape(shape), A


CENTRE = np.array([1.3, -0.7, 2.1])


def sphere_sdf(p, r=30.0):
    return np.linalg.norm(p - CENTRE, axis=1) - r


RADII = np.array([22.0, 30.0, 40.0])
ELL_ROT = Rotation.from_euler("xyz", [20, -15, 35], degrees=True).as_matrix()


def ellipsoid_surface_points(n=40000, seed=0):
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return (u * RADII) @ ELL_ROT.T + CENTRE


def ellipsoid_sdf(p):
    # the exact distance is not closed-form: the scaled-sphere bound, exact on the surface (its sign is all the
    # voxelisation needs)
    q = (p - CENTRE) @ ELL_ROT / RADII
    return (np.linalg.norm(q, axis=1) - 1.0) * RADII.min()


AXIS = np.array([0.5, 0.3, 1.0]) / np.linalg.norm([0.5, 0.3, 1.0])
CYL_R, CYL_H = 12.0, 45.0


def cylinder_sdf(p):
    """Exact signed distance of a capped cylinder (radius 12, half-length 45) on an oblique axis."""
    q = p - CENTRE
    t = q @ AXIS
    r = np.linalg.norm(q - np.outer(t, AXIS), axis=1)
    a, b = r - CYL_R, np.abs(t) - CYL_H
    return np.hypot(np.maximum(a, 0), np.maximum(b, 0)) + np.minimum(np.maximum(a, b), 0)


def check_closed_outward(mesh: Mesh):
    tm = mesh.to_trimesh()
    assert tm.is_watertight
    assert tm.volume > 0                      # outward normals
    return tm


def test_sphere_volume_distance_no_terraces():
    mask, A = voxelise(sphere_sdf, (60, 60, 24), (-54, -54, -60))
    m = mesh_from_slices([(mask, A)])
    assert m.frame == "lps"
    tm = check_closed_outward(m)
    assert tm.volume == pytest.approx(4 / 3 * np.pi * 30.0 ** 3, rel=0.03)
    d = np.abs(sphere_sdf(m.vertices))
    assert d.mean() <= 0.5
    # terraces one 5 mm slice high would put the p95 near 1-2.5 mm
    assert np.percentile(d, 95) <= 1.0
    # and the true surface is everywhere near the mesh (no missing cap)
    u = np.random.default_rng(1).normal(size=(5000, 3))
    true_pts = CENTRE + 30.0 * u / np.linalg.norm(u, axis=1, keepdims=True)
    assert np.percentile(surface_distance(true_pts, m), 95) <= 1.0


def test_sphere_without_interpolation_would_terrace():
    """The check above can fail: a coarse grid equal to the slice pitch shows the 5 mm steps' error."""
    mask, A = voxelise(sphere_sdf, (60, 60, 24), (-54, -54, -60))
    fine = np.abs(sphere_sdf(mesh_from_slices([(mask, A)]).vertices))
    coarse = np.abs(sphere_sdf(mesh_from_slices([(mask, A)], voxel_mm=5.0, smooth_iterations=0).vertices))
    assert np.percentile(coarse, 95) > np.percentile(fine, 95)


def test_ellipsoid_oblique():
    mask, A = voxelise(ellipsoid_sdf, (70, 70, 30), (-63, -63, -72))
    m = mesh_from_slices([(mask, A)])
    tm = check_closed_outward(m)
    assert tm.volume == pytest.approx(4 / 3 * np.pi * RADII.prod(), rel=0.03)
    truth = ellipsoid_surface_points()
    # distance mesh -> true surface, via a dense sampling of the true surface (spacing ~0.6 mm)
    from scipy.spatial import cKDTree

    d_mesh, _ = cKDTree(truth).query(m.vertices)
    d_true = surface_distance(truth[::8], m)
    assert 0.5 * (d_mesh.mean() + d_true.mean()) <= 0.5
    assert np.percentile(d_true, 95) <= 1.2


def test_oblique_cylinder_two_rotated_overlapping_stations():
    rot = Rotation.from_rotvec(np.deg2rad([0.6, -0.5, 0.4])).as_matrix()      # 0.9 deg
    lower = voxelise(cylinder_sdf, (60, 60, 14), (-54, -54, -62))             # z -62 .. 3
    upper = voxelise(cylinder_sdf, (60, 60, 17), (-54, -54, -12.5), rotation=rot)  # overlaps by 15 mm
    assert lower[0].any() and upper[0].any()
    m = mesh_from_slices([lower, upper])
    tm = check_closed_outward(m)
    assert len(tm.split(only_watertight=False)) == 1                         # one body, no seam
    assert tm.volume == pytest.approx(np.pi * CYL_R ** 2 * 2 * CYL_H, rel=0.05)
    d = np.abs(cylinder_sdf(m.vertices))
    assert d.mean() <= 0.5
    assert np.percentile(d, 95) <= 1.0


def test_bone_cut_by_field_of_view_is_capped():
    # the cylinder runs out of the top of the only station: the mesh must still be closed, capped at the FOV
    mask, A = voxelise(cylinder_sdf, (60, 60, 10), (-54, -54, -30))          # slices z = -30 .. 15
    top = A[2, 3] + A[2, 2] * (mask.shape[2] - 1)
    m = mesh_from_slices([(mask, A)])
    check_closed_outward(m)
    assert m.vertices[:, 2].max() <= top + 0.5 * 5.0 + 1.0                   # not beyond the last slab
    assert m.vertices[:, 2].max() >= top - 1.0


def test_decimation_and_smoothing_parameters():
    mask, A = voxelise(sphere_sdf, (60, 60, 24), (-54, -54, -60))
    m = mesh_from_slices([(mask, A)], target_faces=2000, frame="station_1")
    assert m.frame == "station_1"
    assert len(m.faces) <= 2200
    check_closed_outward(m)
    assert np.abs(sphere_sdf(m.vertices)).mean() <= 0.6


def test_meshes_from_labels_two_bones_two_stations():
    rot = Rotation.from_rotvec(np.deg2rad([0.0, 0.5, -0.5])).as_matrix()

    def labels(shape, origin, rotation=None):
        sph, A = voxelise(lambda p: np.linalg.norm(p - [-25.0, 0, -20], axis=1) - 15.0, shape, origin,
                          rotation=rotation)
        cyl, _ = voxelise(lambda p: cylinder_sdf(p - [25.0, 0, 0]), shape, origin, rotation=rotation)
        lab = np.zeros(shape, np.int16)
        lab[sph] = 3
        lab[cyl & ~sph] = 7
        return lab, A

    pieces = [labels((70, 50, 14), (-63, -45, -62)), labels((70, 50, 17), (-63, -45, -12.5), rot)]
    out = meshes_from_labels(pieces, {"ball": 3, "rod": 7, "absent": 9})
    assert list(out) == ["ball", "rod"]
    ball = check_closed_outward(out["ball"])
    assert ball.volume == pytest.approx(4 / 3 * np.pi * 15.0 ** 3, rel=0.06)
    d = np.abs(cylinder_sdf(out["rod"].vertices - [25.0, 0, 0]))
    assert d.mean() <= 0.5
    # each bone only from its own label: the ball's mesh stays around the ball
    assert np.linalg.norm(out["ball"].vertices - [-25.0, 0, -20], axis=1).max() <= 17.0
    # a bone seen in too few slices is left out and said so
    n_ball, n_rod = (sum(int((lab == i).any(axis=(0, 1)).sum()) for lab, _ in pieces) for i in (3, 7))
    assert n_rod > n_ball + 1
    errors = {}
    few = meshes_from_labels(pieces, {"ball": 3, "rod": 7}, min_slices=n_ball + 1, errors=errors)
    assert list(few) == ["rod"] and "slice" in errors["ball"]


def test_meshes_from_labels_in_workers_as_in_one_process(monkeypatch):
    """The bones are meshed in worker processes, the largest first: the same meshes, in the order of
    ``ids``, as one after the other here; a bone that cannot be meshed is said so, or raises, naming it."""
    lab = np.zeros((60, 60, 20), np.int16)
    A = np.diag([1.5, 1.5, 4.0, 1.0])
    ii, jj = np.mgrid[:60, :60]
    for n, (ci, cj, r) in enumerate([(15, 15, 6), (45, 45, 10), (15, 45, 4), (45, 15, 8)], start=1):
        lab[((ii - ci) ** 2 + (jj - cj) ** 2 <= r * r)[:, :, None] & (np.arange(20) >= 2 + n)[None, None, :]] = n
    ids = {"small": 3, "big": 2, "first": 1, "mid": 4}
    monkeypatch.setenv("BONECAP_WORKERS", "2")
    forked = meshes_from_labels([(lab, A)], ids, target_faces=500)
    monkeypatch.setenv("BONECAP_WORKERS", "1")
    here = meshes_from_labels([(lab, A)], ids, target_faces=500)
    assert list(forked) == list(here) == list(ids)
    for name in ids:
        np.testing.assert_array_equal(forked[name].vertices, here[name].vertices)
        np.testing.assert_array_equal(forked[name].faces, here[name].faces)
    monkeypatch.setenv("BONECAP_WORKERS", "2")
    errors = {}
    assert meshes_from_labels([(lab, A)], ids, errors=errors, clip_mm=-1.0) == {}
    assert set(errors) == set(ids) and all("clip_mm" in e for e in errors.values())
    with pytest.raises(ValueError, match="bone 'small': clip_mm"):
        meshes_from_labels([(lab, A)], ids, clip_mm=-1.0)


def test_surface_distance_analytic():
    import trimesh

    box = trimesh.creation.box(extents=(10, 20, 30))
    m = Mesh(box.vertices, box.faces, "lps")
    pts = np.array([[0, 0, 0], [5 + 2.0, 0, 0], [0, 10 + 3.0, 1.0], [8, 13, 15]])
    np.testing.assert_allclose(surface_distance(pts, m), [5.0, 2.0, 3.0, np.sqrt(9 + 9)], atol=1e-9)


def test_bad_input():
    mask, A = voxelise(sphere_sdf, (20, 20, 8), (-18, -18, -20))
    with pytest.raises(ValueError, match="no pieces"):
        mesh_from_slices([])
    with pytest.raises(ValueError, match="3-D"):
        mesh_from_slices([(mask[:, :, 0], A)])
    with pytest.raises(ValueError, match="4x4"):
        mesh_from_slices([(mask, A[:3])])
    with pytest.raises(ValueError, match="singular"):
        mesh_from_slices([(mask, np.diag([1.0, 1.0, 0.0, 1.0]))])
    with pytest.raises(ValueError, match="empty"):
        mesh_from_slices([(np.zeros_like(mask), A)])
    with pytest.raises(ValueError, match="voxel_mm"):
        mesh_from_slices([(mask, A)], voxel_mm=0)
    with pytest.raises(ValueError, match="integer"):
        meshes_from_labels([(mask.astype(float), A)], {"a": 1})
    with pytest.raises(ValueError, match="positive integers"):
        meshes_from_labels([(mask.astype(np.int16), A)], {"a": 0})


def test_inplane_edt_equals_one_transform_with_a_huge_slice_spacing():
    """The slice-by-slice distances are the 3-D transform's with the slices kept apart (what the meshing
    and the skin's edge level used before), and a slice with no False voxel has none (inf)."""
    from scipy import ndimage

    from bonecap.segmentation._distance import inplane_edt

    rng = np.random.default_rng(3)
    m = ndimage.binary_opening(rng.random((40, 31, 7)) < 0.7, structure=np.ones((3, 3, 1)))
    m[:, :, 2] = True                       # nothing outside in this slice
    m[:, :, 4] = False                      # nothing inside in this one
    d = inplane_edt(m, (1.8, 0.9))
    old = ndimage.distance_transform_edt(m, sampling=(1.8, 0.9, 1e6))
    finite = np.isfinite(d)
    assert not finite[:, :, 2].any() and finite[:, :, [0, 1, 3, 4, 5, 6]].all()
    assert old[:, :, 2].min() > 1e5                              # the old way: the huge spacing
    np.testing.assert_array_equal(d[finite], old[finite])
    assert (d[:, :, 4] == 0).all() and (d[~m] == 0).all() and (d[m & finite] > 0).all()
    with pytest.raises(ValueError, match="3-D"):
        inplane_edt(m[:, :, 0], (1.0, 1.0))
