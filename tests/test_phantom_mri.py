"""Tests of the phantom's MRI: partial-volume rendering, oracle labels, stations, capsules.

Scenes are built here from trimesh primitives (LPS mm): a limb (fat and
muscle cylinders around a cortical tube with a marrow cavity), spheres, and a
forearm along an oblique axis. The knee ROIs are re-measured from
``../shared/data/mri`` when it is present.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

from bonecap.io.imaging import read_dicom_series
from bonecap.model import Mesh
from bonecap.phantom import mri
from bonecap.phantom.mri import (KNEE_ROIS, ForearmPose, capsule_meshes, load_tissue_intensities,
                                 measure_knee_tissues, mesh_coverage, place_capsules, plan_forearm_stack,
                                 plan_stations, render_forearm_stacks, render_stations, render_volume,
                                 tissue_fractions, voxelise_labels)

KNEE = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "mri" / "knee_mese_t2_echo1_dicom"
TABLE = load_tissue_intensities()
MEANS = {k: v["mean"] for k, v in TABLE["tissues"].items()}


def _mesh(tm: trimesh.Trimesh) -> Mesh:
    return Mesh(tm.vertices, tm.faces, "lps")


def _cyl(r, h, centre=(0, 0, 0), sections=128) -> trimesh.Trimesh:
    c = trimesh.creation.cylinder(radius=r, height=h, sections=sections)
    c.apply_translation(centre)
    return c


def _sphere(r, centre=(0, 0, 0), sub=5) -> trimesh.Trimesh:
    s = trimesh.creation.icosphere(subdivisions=sub, radius=r)
    s.apply_translation(centre)
    return s


def _limb(length=200.0):
    """Fat (r 50) > muscle (r 40) > cortex (r 15, off-centre) > marrow (r 9) along z."""
    return [(_mesh(_cyl(50, length)), "fat"), (_mesh(_cyl(40, length - 4)), "muscle"),
            (_mesh(_cyl(15, length - 8, (8, -6, 0))), "cortex"),
            (_mesh(_cyl(9, length - 12, (8, -6, 0))), "marrow")]


def _grid(spacing, origin, R=None):
    A = np.eye(4)
    A[:3, :3] = (np.eye(3) if R is None else R) @ np.diag(spacing)
    A[:3, 3] = origin
    return A


def _rot(axis, deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    t = math.radians(deg)
    return np.eye(3) + math.sin(t) * K + (1 - math.cos(t)) * K @ K


def _angle_deg(R):
    return math.degrees(math.acos(np.clip((np.trace(R) - 1) / 2, -1, 1)))


# --------------------------------------------------------------------------- #
# intensities
# --------------------------------------------------------------------------- #
def test_rendered_tissue_intensities_match_the_knee_table():
    """Mean and spread per tissue, measured in region interiors, match the YAML (texture + Rician noise)."""
    layers = _limb()
    A = _grid((1.0, 1.0, 3.0), (-60, -60, -30))
    shape = (121, 121, 21)
    img = render_volume(layers, A, shape, rng=3, bias=0.0)
    frac = tissue_fractions(layers, A, shape)
    sigma = TABLE["noise_sigma"]
    for tissue in ("fat", "muscle", "cortex", "marrow"):
        inside = frac[tissue] > 0.999
        vals = img[inside]
        assert vals.size > 300, tissue
        m = MEANS[tissue]
        cv = TABLE["tissues"][tissue]["texture_cv"]
        # Rician bias of the mean is sigma^2 / (2 m): < 1 % for the darkest (cortex).
        assert abs(vals.mean() - m) < 0.03 * m + 3, (tissue, vals.mean(), m)
        expected_std = math.hypot(cv * m, sigma)
        assert 0.75 * expected_std < vals.std() < 1.25 * expected_std, (tissue, vals.std(), expected_std)
    air = img[sum(frac.values()) == 0]
    # Rician background: mean sigma sqrt(pi/2), as measured behind the knee.
    assert abs(air.mean() - sigma * math.sqrt(math.pi / 2)) < 0.05 * sigma * math.sqrt(math.pi / 2)
    # The contrast order of a T2-weighted spin echo: fat > marrow > muscle > cortex > air.
    assert MEANS["fat"] > MEANS["marrow"] > MEANS["muscle"] > MEANS["cortex"] > MEANS["air"]
    assert MEANS["oil"] > MEANS["fat"]


def test_bias_and_scale_multiply_and_rng_reproduces():
    layers = _limb(60)
    A = _grid((2.0, 2.0, 5.0), (-60, -60, -20))
    a = render_volume(layers, A, (61, 61, 8), rng=7)
    b = render_volume(layers, A, (61, 61, 8), rng=7)
    np.testing.assert_array_equal(a, b)
    flat = render_volume(layers, A, (61, 61, 8), rng=7, noise=False, texture=False, bias=0.0)
    biased = render_volume(layers, A, (61, 61, 8), rng=7, noise=False, texture=False, bias=0.15)
    sel = flat > 100
    ratio = biased[sel] / flat[sel]
    assert np.abs(ratio - 1).max() <= 0.15 * 1.01 and ratio.max() - ratio.min() > 0.03
    # smooth: exactly a quadratic polynomial of the voxel position
    i, j, k = np.nonzero(sel)
    X = np.c_[np.ones(i.size), i, j, k, i * i, j * j, k * k, i * j, i * k, j * k]
    coef, *_ = np.linalg.lstsq(X, ratio, rcond=None)
    assert np.abs(X @ coef - ratio).max() < 1e-4
    scaled = render_volume(layers, A, (61, 61, 8), rng=7, noise=False, texture=False, bias=0.0, scale=1.25)
    np.testing.assert_allclose(scaled, 1.25 * flat, rtol=1e-5)


def test_unknown_tissue_and_bad_grid_are_refused():
    layers = [(_mesh(_sphere(5, sub=2)), "bone_marrow_typo")]
    with pytest.raises(ValueError, match="unknown tissue"):
        render_volume(layers, np.eye(4), (4, 4, 4))
    with pytest.raises(ValueError, match="shape"):
        render_volume([(_mesh(_sphere(5, sub=2)), "fat")], np.eye(4), (4, 4))
    with pytest.raises(ValueError, match="invertible"):
        mesh_coverage(_mesh(_sphere(5, sub=2)), np.zeros((4, 4)), (4, 4, 4))


# --------------------------------------------------------------------------- #
# partial volume
# --------------------------------------------------------------------------- #
def test_sphere_volume_and_partial_voxels():
    r = 11.0
    sph = _sphere(r, (0.37, -0.81, 1.3))
    A = _grid((1.8, 1.8, 5.0), (-20.2, -19.9, -21.1))
    shape = (23, 23, 9)
    img = render_volume([(_mesh(sph), "oil")], A, shape, intensities={"oil": 1.0}, noise=False,
                        texture=False, bias=0.0)
    vol = img.sum() * 1.8 * 1.8 * 5.0
    assert abs(vol / (4 / 3 * math.pi * r**3) - 1) < 0.02
    assert abs(vol / sph.volume - 1) < 0.005          # against the mesh's own volume
    partial = (img > 0.05) & (img < 0.95)
    assert partial.sum() > 50                          # boundary voxels are intermediate
    assert img.max() == pytest.approx(1.0, abs=1e-5) and img.min() >= 0


def test_oblique_thick_slices_give_fractions_and_keep_volume():
    r = 12.0
    sph = _sphere(r)
    R = _rot((1, 1, 0.3), 35)
    A = _grid((1.5, 1.5, 5.0), (0, 0, 0), R)
    A[:3, 3] = -R @ (np.array([1.5, 1.5, 5.0]) * np.array([15.3, 14.8, 3.4]))
    frac = mesh_coverage(_mesh(sph), A, (31, 31, 8))
    vol = frac.sum() * 1.5 * 1.5 * 5.0
    assert abs(vol / sph.volume - 1) < 0.01
    # A 5 mm slice cut obliquely: the central slice is mixed over a wide rim.
    k = int(np.argmax(frac.sum(axis=(0, 1))))
    mixed = (frac[:, :, k] > 0.02) & (frac[:, :, k] < 0.98)
    assert mixed.sum() > 20
    # Slices thicker than the pitch overlap: each voxel averages over 7.5 mm, so
    # the sum of fractions (volume per pitch) is unchanged but more voxels are touched.
    thick = mesh_coverage(_mesh(sph), A, (31, 31, 8), slice_thickness_mm=7.5)
    assert abs(thick.sum() / frac.sum() - 1) < 0.01
    assert (thick > 0).sum() > 1.05 * (frac > 0).sum()


def test_painter_order_is_exact_when_layers_are_not_nested():
    """A bone sticking out of the muscle into the fat is painted over both, voxel by voxel."""
    fat, mus = _cyl(50, 120, sections=160), _cyl(40, 116, sections=160)
    bone = _cyl(8, 60, (-40, 0, 0), sections=96)                      # straddles the fascia
    layers = [(_mesh(fat), "fat"), (_mesh(mus), "muscle"), (_mesh(bone), "cortex")]
    A = _grid((1.7, 1.7, 4.0), (-55, -55, -70))
    frac = tissue_fractions(layers, A, (66, 66, 36))
    vv = 1.7 * 1.7 * 4.0
    assert frac["cortex"].sum() * vv == pytest.approx(bone.volume, rel=0.005)
    # Muscle = muscle cylinder minus the part of the bone inside it (computed by a
    # fine independent sampling of the bone's cross-section).
    rng = np.random.default_rng(0)
    p = rng.uniform(-8, 8, (400_000, 2))
    p = p[np.hypot(*p.T) < 8] + [-40, 0]
    inside_mus = np.hypot(*p.T) < 40 * math.cos(math.pi / 160)       # polygon inradius ~ 40
    area_in = math.pi * 64 * inside_mus.mean()
    assert frac["muscle"].sum() * vv == pytest.approx(mus.volume - area_in * 60, rel=0.005)
    total = sum(frac.values())
    assert total.max() <= 1 + 1e-5


def test_painter_order_over_more_than_64_layers():
    """70 concentric spheres, alternating tissues: each shell is its sphere minus the next (bit masks > 64)."""
    radii = np.linspace(30, 3, 70)
    spheres = [_sphere(r, sub=3) for r in radii]
    layers = [(_mesh(sp), ("fat", "muscle")[t % 2]) for t, sp in enumerate(spheres)]
    vols = np.array([sp.volume for sp in spheres] + [0.0])
    A = _grid((1.5, 1.5, 1.5), (-32, -32, -32))
    frac = tissue_fractions(layers, A, (44, 44, 44))
    vv = 1.5**3
    assert frac["fat"].sum() * vv == pytest.approx(sum(vols[t] - vols[t + 1] for t in range(0, 70, 2)), rel=1e-3)
    assert frac["muscle"].sum() * vv == pytest.approx(sum(vols[t] - vols[t + 1] for t in range(1, 70, 2)),
                                                      rel=1e-3)


def test_a_mesh_with_a_hole_does_not_streak():
    sp = _sphere(10, sub=4)
    holed = Mesh(sp.vertices, sp.faces[6:], "lps")
    A = _grid((1.0, 1.0, 1.0), (-15, -15, -15))
    cov = mesh_coverage(holed, A, (31, 31, 31))
    assert cov.max() <= 1 + 1e-6
    assert cov.sum() == pytest.approx(sp.volume, rel=0.01)
    assert cov[:, :, :3].sum() == 0 and cov[:3].sum() == 0         # nothing outside the sphere


# --------------------------------------------------------------------------- #
# oracle labels
# --------------------------------------------------------------------------- #
def test_oracle_labels_equal_an_independent_voxelisation():
    """voxelise_labels == VTK point-in-mesh tests on 4x4x4 sub-samples per voxel (>= 1/2 inside)."""
    import pyvista as pv

    tube = _cyl(10, 50, (-14, 3, 0), sections=64)
    ball = _sphere(9, (16, -2, 4), sub=4)
    A = _grid((1.6, 1.6, 3.0), (-30.3, -20.1, -31.0), _rot((0.2, 1, 0.1), 12))
    shape = (38, 26, 22)
    labels = voxelise_labels([(_mesh(tube), 3), (_mesh(ball), 7)], A, shape)
    # independent: VTK's vtkSelectEnclosedPoints on a regular sub-grid
    s = (np.arange(4) + 0.5) / 4 - 0.5
    ii, jj, kk = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), np.arange(shape[2]), indexing="ij")
    sub = np.stack(np.meshgrid(s, s, s, indexing="ij"), -1).reshape(-1, 3)
    idx = np.c_[ii.ravel(), jj.ravel(), kk.ravel()].astype(float)
    pts = (idx[:, None, :] + sub[None]).reshape(-1, 3)
    world = pts @ A[:3, :3].T + A[:3, 3]
    ref = np.zeros(idx.shape[0], np.uint16)
    for tm, lab in ((tube, 3), (ball, 7)):
        surf = pv.PolyData(tm.vertices, np.c_[np.full(len(tm.faces), 3), tm.faces].ravel())
        inside = pv.PolyData(world).select_interior_points(surf, method="cell_locator", check_surface=False)
        frac = np.asarray(inside["selected_points"], bool).reshape(-1, 64).mean(axis=1)
        ref[frac >= 0.5] = lab
    ref = ref.reshape(shape)
    n_lab = (ref > 0).sum()
    assert n_lab > 1500
    assert set(np.unique(labels)) == {0, 3, 7}
    differ = labels != ref
    # Only voxels whose coverage is within sampling error of one half can disagree.
    assert differ.sum() <= 0.02 * n_lab
    cov = np.maximum(mesh_coverage(_mesh(tube), A, shape), mesh_coverage(_mesh(ball), A, shape))
    assert np.all(np.abs(cov[differ] - 0.5) < 0.15)


# --------------------------------------------------------------------------- #
# stations
# --------------------------------------------------------------------------- #
def test_station_plan_covers_the_body_with_overlaps_and_small_motions():
    body = np.array([[-250.0, -150.0, 0.0], [250.0, 150.0, 1800.0]])
    plans = plan_stations(body, n_stations=8, rng=11)
    assert [p.name for p in plans] == [f"station_{k}" for k in range(1, 9)]
    ranges = [p.slice_range_mm() for p in plans]
    assert ranges[0][1] >= 1800 and ranges[-1][0] <= 0                    # head and feet covered
    for (lo0, hi0), (lo1, hi1) in zip(ranges, ranges[1:]):
        assert lo1 < lo0                                                  # head to feet
        overlap = hi1 - lo0
        assert 0.15 * (hi0 - lo0) <= overlap <= 0.3 * (hi0 - lo0)
    for p in plans:
        T = p.true_to_nominal
        assert _angle_deg(T[:3, :3]) <= 1.0 + 1e-9
        assert np.linalg.norm(T[:3, :3] @ p.centre + T[:3, 3] - p.centre) <= 3.0 + 1e-9
        assert p.shift_mm <= 3.0 and p.rotation_deg <= 1.0
        assert 0.75 <= p.intensity_scale <= 1.3
        np.testing.assert_allclose(p.spacing, [1.8, 1.8, 5.0])
        fov_lo, fov_hi = p.affine[:2, 3], p.affine[:2, 3] + (np.array(p.shape[:2]) - 1) * 1.8
        assert np.all(fov_lo < body[0, :2]) and np.all(fov_hi > body[1, :2])
    assert len({round(p.rotation_deg, 6) for p in plans}) == 8               # drawn per station


def test_stations_write_dicom_with_nominal_geometry_and_moved_content(tmp_path):
    """Two stations, one ball each: DICOM has the nominal geometry, the ball is where the motion put it."""
    r = 15.0
    centres = {1: np.array([3.0, -5.0, 160.0]), 2: np.array([-4.0, 6.0, 20.0])}   # station 1 = head end
    balls = {k: _mesh(_sphere(r, c)) for k, c in centres.items()}
    plans = plan_stations(list(balls.values()), n_stations=2, pixel_mm=1.5, pitch_mm=3.0, thickness_mm=3.0,
                          overlap_mm=20.0, max_shift_mm=3.0, max_rotation_deg=1.0, rng=5)
    seen = []
    res = render_stations([(b, "oil") for b in balls.values()], plans, tmp_path, rng=1,
                          label_meshes=[(b, 8 + k) for k, b in balls.items()], intensities={"oil": 1000.0},
                          noise=False, texture=False, bias=0.0, merged_voxel_mm=2.0, show_progress=False,
                          on_station=lambda t: seen.append(t))
    assert [t.plan.name for t in seen] == ["station_1", "station_2"] and seen[0].labels is not None
    uids, displacement = set(), []
    for st in res.stations:
        plan = st.plan
        (vol,) = read_dicom_series(st.folder)
        np.testing.assert_allclose(vol.affine, plan.affine, atol=1e-6)
        assert vol.shape == plan.shape
        assert vol.metadata["series_description"] == f"station {plan.index}"
        assert vol.metadata["series_number"] == plan.index
        assert vol.metadata["study_uid"] == res.study_uid
        assert vol.metadata["frame_of_reference_uid"] == res.frame_of_reference_uid
        uids.add(vol.metadata["series_uid"])
        # This station's ball lies wholly inside it, the other wholly outside.
        c = centres[plan.index]
        T = plan.true_to_nominal
        moved = T[:3, :3] @ c + T[:3, 3]
        zr = plan.slice_range_mm()
        assert zr[0] < moved[2] - r - 2 and zr[1] > moved[2] + r + 2
        # The content is the ball moved by true_to_nominal, in nominal coordinates.
        w = vol.data.astype(float)
        ijk = np.stack(np.meshgrid(*[np.arange(n) for n in vol.shape], indexing="ij"), -1).reshape(-1, 3)
        cen = vol.index_to_world((ijk * w.reshape(-1, 1)).sum(0) / w.sum())
        assert np.linalg.norm(cen - moved) < 0.3
        displacement.append(np.linalg.norm(moved - c))
        lab = st.labels.data
        assert set(np.unique(lab)) == {0, 8 + plan.index}
        labc = vol.index_to_world(np.argwhere(lab == 8 + plan.index).mean(0))
        assert np.linalg.norm(labc - moved) < 0.5         # the oracle moves with the image
        # the oracle is voxelise_labels of the moved meshes on the acquisition grid
        ref = voxelise_labels([(b.transformed(T), 8 + k) for k, b in balls.items()], plan.affine, plan.shape,
                              slice_thickness_mm=plan.slice_thickness_mm)
        np.testing.assert_array_equal(lab, ref)
    assert len(uids) == 2
    assert max(displacement) > 1.0                       # the motion is measurable
    merged = res.merged_labels
    for k, c in centres.items():                          # merged labels: the true frame
        assert np.linalg.norm(merged.index_to_world(np.argwhere(merged.data == 8 + k).mean(0)) - c) < 0.3
        assert (merged.data == 8 + k).sum() * 8.0 == pytest.approx(4 / 3 * math.pi * r**3, rel=0.05)


# --------------------------------------------------------------------------- #
# forearm stacks and capsules
# --------------------------------------------------------------------------- #
def _forearm_pose(angle_deg, axis_pts):
    """Skin, fascia and two bones along a tilted axis, twisted by ``angle_deg`` about it."""
    p0, p1 = axis_pts
    d = p1 - p0
    L = np.linalg.norm(d)
    n = d / L
    # Build along z, then rotate z onto the axis and twist about it.
    z = np.array([0, 0, 1.0])
    v = np.cross(z, n)
    R_align = _rot(v, math.degrees(math.acos(n @ z))) if np.linalg.norm(v) > 1e-9 else np.eye(3)
    T = np.eye(4)
    T[:3, :3] = _rot(n, angle_deg) @ R_align
    T[:3, 3] = p0 + n * L / 2
    radius, ulna = (10, 4, 0), (-10, -2, 0)
    parts = [(_cyl(32, L, sections=96), "fat"), (_cyl(26, L - 4, sections=96), "muscle"),
             (_cyl(7, L - 10, radius, sections=48), "cortex"), (_cyl(4, L - 14, radius, sections=48), "marrow"),
             (_cyl(6, L - 10, ulna, sections=48), "cortex"), (_cyl(3, L - 14, ulna, sections=48), "marrow")]
    layers = [(_mesh(tm).transformed(T, "lps"), t) for tm, t in parts]
    labels = [(layers[2][0], 1), (layers[4][0], 2)]
    return ForearmPose(layers=layers, axis=np.array([p0, p1]), label_meshes=labels)


def test_capsules_sit_on_the_skin_between_slices_and_image_where_the_truth_says(tmp_path):
    axis = (np.array([-200.0, 20.0, 1100.0]), np.array([-215.0, 40.0, 980.0]))
    poses = {name: _forearm_pose(float(name), axis) for name in ("0", "99.5", "172.1")}
    truths, placement = render_forearm_stacks(poses, tmp_path, rng=4, n_capsules=6, noise=False,
                                              texture=False, bias=0.0)
    assert set(truths) == {"0", "99.5", "172.1"}
    r = placement.radius_mm
    assert r == 4.0
    for name, tr in truths.items():
        pose, plan = poses[name], tr.plan
        assert tr.folder.name == f"forearm_{name}"
        skin = pose.skin.to_trimesh()
        closest, dist, tri = trimesh.proximity.closest_point(skin, tr.capsule_centres)
        np.testing.assert_allclose(dist, r, atol=0.1)                   # on the skin + radius
        normals = skin.face_normals[tri]
        np.testing.assert_allclose(tr.capsule_centres, closest + r * normals, atol=0.1)  # along the normal
        # between slice planes, never on one
        k = (tr.capsule_centres - plan.affine[:3, 3]) @ np.linalg.inv(plan.affine[:3, :3]).T
        depth = np.abs(k[:, 2] - np.rint(k[:, 2])) * plan.spacing[2]
        assert depth.min() >= 0.5
        # the stack is axial to the forearm
        n_axis = (axis[1] - axis[0]) / np.linalg.norm(axis[1] - axis[0])
        assert plan.affine[:3, 2] / plan.spacing[2] @ n_axis == pytest.approx(1.0)
        assert plan.spacing[0] == pytest.approx(0.7) and plan.spacing[2] == pytest.approx(2.5)
        # Capsule signal: the written stack minus the same pose rendered without capsules.
        (vol,) = read_dicom_series(tr.folder)
        np.testing.assert_allclose(vol.affine, plan.affine, atol=1e-6)
        bare = render_volume(pose.layers, plan.affine, plan.shape, slice_thickness_mm=plan.slice_thickness_mm,
                             noise=False, texture=False, bias=0.0, scale=plan.intensity_scale)
        diff = np.clip(vol.data.astype(float) - bare, 0, None)
        diff[diff < 2] = 0                                              # DICOM rounding
        for c in tr.capsule_centres:
            ci = np.linalg.solve(plan.affine[:3, :3], c - plan.affine[:3, 3])
            lo = np.maximum(np.floor(ci - 12 / plan.spacing).astype(int), 0)
            hi = np.minimum(np.ceil(ci + 12 / plan.spacing).astype(int) + 1, plan.shape)
            win = diff[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
            idx = np.argwhere(win > 0) + lo
            w = win[win > 0]
            cen_idx = (idx * w[:, None]).sum(0) / w.sum()
            err = (cen_idx - ci) * plan.spacing
            assert np.hypot(err[0], err[1]) < 1.0 and abs(err[2]) < 1.5, (name, err)
        # oil is brighter than fat in the image
        assert vol.data.max() > 1.2 * MEANS["fat"] * plan.intensity_scale
        assert bare.max() < 1.01 * MEANS["fat"] * plan.intensity_scale
        assert tr.labels is not None and set(np.unique(tr.labels.data)) == {0, 1, 2}
    # the same skin triangles in every pose: capsules twist with the forearm
    c0, c1 = truths["0"].capsule_centres, truths["172.1"].capsule_centres
    assert np.all(np.linalg.norm(c0 - c1, axis=1) > 20)


def test_place_capsules_refuses_impossible_requests():
    skin = _mesh(_cyl(30, 100, sections=64))
    plan = plan_forearm_stack(skin, np.array([[0, 0, -50.0], [0, 0, 50.0]]))
    with pytest.raises(ValueError, match="no room"):
        place_capsules(skin, 3, 0, plans=[plan], min_plane_distance_mm=1.3)
    with pytest.raises(ValueError, match="could place only"):
        place_capsules(skin, 200, 0, min_separation_mm=30, max_tries=5)
    caps = place_capsules(skin, 5, 0, plans=[plan])
    assert len(capsule_meshes(caps.centres, caps.radius_mm)) == 5 == len(caps.meshes)


def test_capsule_icosphere_is_trimeshs_and_leaves_a_process_without_trimesh_without_it():
    """The capsules' sphere is trimesh's icosphere; a process that has not imported trimesh gets it from a
    short child and still has no trimesh after (the default phantom's main process: ~21 MiB)."""
    import subprocess
    import sys

    code = ("import sys, numpy as np\n"
            "from bonecap.phantom.mri import capsule_meshes\n"
            "m = capsule_meshes(np.array([[1.0, 2.0, 3.0]]), 4.0)[0]\n"
            "assert 'trimesh' not in sys.modules, 'trimesh was imported here'\n"
            "np.save(sys.stdout.buffer, m.vertices); np.save(sys.stdout.buffer, m.faces)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, check=False)
    assert out.returncode == 0, out.stderr.decode()
    import io

    buf = io.BytesIO(out.stdout)
    V, F = np.load(buf), np.load(buf)
    ref = trimesh.creation.icosphere(subdivisions=3, radius=4.0)
    assert np.array_equal(V, ref.vertices + [1.0, 2.0, 3.0]) and np.array_equal(F, ref.faces)
    # made once per size, shared read-only; every capsule gets its own arrays
    a, b = capsule_meshes(np.zeros((2, 3)), 4.0)
    assert mri.icosphere(4.0)[0] is mri.icosphere(4.0)[0] and not mri.icosphere(4.0)[0].flags.writeable
    a.vertices[0] += 1.0
    assert not np.array_equal(a.vertices, b.vertices) and a.faces is not b.faces


# --------------------------------------------------------------------------- #
# the knee table
# --------------------------------------------------------------------------- #
@pytest.mark.shared
def test_knee_rois_remeasured_equal_the_yaml():
    if not KNEE.is_dir():
        pytest.skip(f"shared data not found at {KNEE}")
    doc = yaml.safe_load(mri.TISSUE_YAML.read_text())
    assert {k: v["box"] for k, v in doc["rois"].items()} == {k: v["box"] for k, v in KNEE_ROIS.items()}
    measured = measure_knee_tissues(KNEE)
    for roi, stats in doc["measured"].items():
        if isinstance(stats, dict):
            for key, val in stats.items():
                assert measured[roi][key] == pytest.approx(val, rel=0.01), (roi, key)
        else:
            assert measured[roi] == pytest.approx(stats, rel=0.01)
    table = mri.tissue_table(measured)
    for t, v in table["tissues"].items():
        assert doc["tissues"][t]["mean"] == pytest.approx(v["mean"], rel=0.01)
    assert doc["noise_sigma"] == pytest.approx(table["noise_sigma"], rel=0.01)


# --------------------------------------------------------------------------- #
# writing large outputs without holding them (the phantom's memory budget)
# --------------------------------------------------------------------------- #
def test_merged_labels_streamed_in_slabs_equal_the_whole_grid(tmp_path):
    """``write_merged_labels`` (slab by slab) holds the labels ``voxelise_labels`` gives on the whole grid."""
    from bonecap.io.imaging import read_nifti
    from bonecap.phantom.mri import merged_grid, write_merged_labels

    items = [(_mesh(_cyl(15, 80, (0, 0, 0))), 1), (_mesh(_sphere(18, (30, 10, 60), sub=3)), 2),
             (_mesh(_cyl(12, 70, (-20, 5, 120))), 7)]
    # 7-slice slabs over ~100 slices: many slab edges cut through every mesh
    aff, shp = write_merged_labels(items, tmp_path / "m.nii.gz", voxel_mm=2.0, inplane_supersample=2,
                                   through_plane_samples=2, slab_slices=7)
    ref_aff, ref_shp = merged_grid([m for m, _ in items], 2.0)
    assert shp == ref_shp and np.allclose(aff, ref_aff)
    full = voxelise_labels(items, aff, shp, inplane_supersample=2, through_plane_samples=2)
    assert set(np.unique(full)) == {0, 1, 2, 7}
    vol = read_nifti(tmp_path / "m.nii.gz")
    assert vol.data.dtype == np.uint16
    assert np.array_equal(vol.data, full)
    assert np.allclose(vol.affine, aff, atol=1e-4)


def test_nifti_written_in_slabs_is_byte_identical(tmp_path):
    """The slab writer's file is byte for byte ``write_nifti``'s (header, data order, gzip)."""
    from bonecap.io.imaging import _write_nifti_slabs, write_nifti
    from bonecap.model import Volume

    rng = np.random.default_rng(3)
    A = _grid((2.0, 1.5, 3.0), (-100.0, 20.5, 300.0))
    for dtype in (np.uint16, np.float32):
        data = (rng.random((21, 13, 17)) * 90).astype(dtype)
        for ext in (".nii", ".nii.gz"):
            write_nifti(Volume(data, A, {}), tmp_path / f"a{ext}")
            # uneven slabs, the last one short
            _write_nifti_slabs(A, data.shape, dtype, (data[:, :, k:k + 5] for k in range(0, 17, 5)),
                               tmp_path / f"b{ext}")
            assert (tmp_path / f"a{ext}").read_bytes() == (tmp_path / f"b{ext}").read_bytes()
    with pytest.raises(ValueError, match="slices"):
        _write_nifti_slabs(A, (21, 13, 17), np.uint16, [np.zeros((21, 13, 5), np.uint16)], tmp_path / "c.nii")
    assert not (tmp_path / "c.nii").exists()


@pytest.mark.parametrize("kind", ["uint16", "int16", "float_rescaled"])
def test_dicom_series_bytes_are_pydicoms_from_scratch(tmp_path, kind):
    """``write_dicom_series`` encodes a series' constant elements once and each file's changing ones in
    between; every file must be the bytes pydicom writes for the same elements built from scratch (no
    stale value from slice 1), for unsigned, signed and rescaled (float) data."""
    import io

    import pydicom
    from pydicom.dataelem import DataElement
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.filewriter import dcmwrite

    from bonecap.io.imaging import write_dicom_series
    from bonecap.model import Volume

    rng = np.random.default_rng(4)
    data = {"uint16": rng.integers(0, 3000, (24, 20, 4)).astype(np.uint16),
            "int16": rng.integers(-1000, 3000, (24, 20, 4)).astype(np.int16),
            "float_rescaled": rng.normal(100.0, 30.0, (24, 20, 4))}[kind]
    vol = Volume(data, _grid((1.5, 1.7, 5.0), (-10.0, 20.0, 30.0)), {"patient_name": "Ph^X", "slice_thickness": 4.0,
                                                                     "echo_number": 2, "echo_time": 12.5})
    files = write_dicom_series(vol, tmp_path / "s", rescale=kind == "float_rescaled", series_number=3,
                               modality="CT" if kind == "int16" else "MR")
    seen = set()
    for k, f in enumerate(files):
        ds = pydicom.dcmread(f)
        fresh = Dataset()
        for elem in ds:
            fresh.add(DataElement(elem.tag, elem.VR, elem.value))
        fm = FileMetaDataset()
        for elem in ds.file_meta:
            fm.add(DataElement(elem.tag, elem.VR, elem.value))
        fresh.file_meta = fm
        buf = io.BytesIO()
        dcmwrite(buf, fresh, enforce_file_format=True)
        assert buf.getvalue() == f.read_bytes()
        # the per-slice elements are this slice's
        assert int(ds.InstanceNumber) == k + 1
        assert np.allclose([float(v) for v in ds.ImagePositionPatient], vol.affine[:3, :3] @ [0, 0, k] + vol.affine[:3, 3])
        if kind == "float_rescaled":
            got = ds.pixel_array * float(ds.RescaleSlope) + float(ds.RescaleIntercept)
            assert np.allclose(got, data[:, :, k].T, atol=float(ds.RescaleSlope))
        else:
            assert np.array_equal(ds.pixel_array, data[:, :, k].T)
        assert ds.SOPInstanceUID == ds.file_meta.MediaStorageSOPInstanceUID
        seen.add(ds.SOPInstanceUID)
    assert len(seen) == len(files)


def test_forearm_crop_keeps_every_face_a_stack_sees():
    """``make_phantom`` cuts the posed whole-body skin to a slab across the forearm before the
    stacks are rendered (memory): the image must be the one of the whole mesh. A bent tube (an
    arm beside a body-sized block) rendered on a stack along its forearm part, whole and cut."""
    from bonecap.phantom import _FOREARM_CROP_MARGIN_MM, _faces_across, _keep_faces

    arm = trimesh.creation.cylinder(radius=35.0, height=600.0, sections=48)
    arm.apply_translation((0.0, 0.0, 100.0))
    trunk = trimesh.creation.box(extents=(300.0, 200.0, 900.0))
    trunk.apply_translation((250.0, 0.0, 0.0))
    body = trimesh.util.concatenate([trunk, arm])
    v, f = trimesh.remesh.subdivide_to_size(body.vertices, body.faces, max_edge=25.0)
    skin = Mesh(v, f, "lps")
    elbow, wrist = np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.0, 250.0])
    plan = mri.plan_forearm_stack(skin, np.stack([elbow, wrist]), name="f", index=1, pixel_mm=4.0,
                                  pitch_mm=5.0, thickness_mm=5.0, margin_mm=12.0)
    reach = 10.0 + 5.0
    keep = _faces_across(skin, elbow, wrist, -reach - _FOREARM_CROP_MARGIN_MM, 250.0 + reach + _FOREARM_CROP_MARGIN_MM)
    assert 0 < keep.sum() < len(skin.faces)
    cut = _keep_faces(skin, keep)
    assert len(cut.vertices) < len(skin.vertices)
    assert np.array_equal(cut.vertices[cut.faces], skin.vertices[skin.faces[keep]])   # same triangles
    kw = dict(slice_thickness_mm=5.0, inplane_supersample=2, through_plane_samples=2, noise=False,
              texture=False, bias=0.0)
    whole = mri.render_volume([(skin, "fat")], plan.affine, plan.shape, rng=0, **kw)
    part = mri.render_volume([(cut, "fat")], plan.affine, plan.shape, rng=0, **kw)
    assert whole.max() > 0 and np.array_equal(whole, part)
    # a cut short of the stack's end slices would change them (the check has teeth)
    short = _keep_faces(skin, _faces_across(skin, elbow, wrist, 60.0, 190.0))
    assert not np.array_equal(whole, mri.render_volume([(short, "fat")], plan.affine, plan.shape, rng=0, **kw))
