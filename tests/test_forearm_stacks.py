"""Forearm stacks (build-subject stage 8): the radius's turn about the ulna and its target, analytic cases.

The whole stage runs on the default phantom in ``benchmarks/bench_pipeline.py`` (the tiny preset's
1.5 mm / 5 mm stacks cannot show a forearm's marrow); here its two geometric steps are checked on a
synthetic stack whose answer is known.
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from bonecap.build_mri import _inside_mesh, _marrow_axis, _radius_turn, _swept_by
from bonecap.model import Bone, Mesh, Volume

L = 240.0          # radius length, mm
OFFSET = 15.0      # its shaft's distance from the ulna's radio-ulnar axis, mm
BOW = 4.0          # its bowing, mm (more than the marrow's radius: a straight chord leaves the marrow)
MARROW_R = 2.5


def _centre_x(y):
    return OFFSET + BOW * np.sin(np.pi * y / L)


def _radius_bone() -> Bone:
    """A bowed radius: bone y (long axis) = world z, bone x = world x; its marrow tube as the inner mesh."""
    tube = trimesh.creation.cylinder(radius=MARROW_R, height=L, sections=24)
    v = tube.vertices[:, [0, 2, 1]] * [1, 1, -1]          # cylinder along bone y (a reflection: faces flipped)
    v[:, 1] += L / 2
    sub = trimesh.Trimesh(v, tube.faces[:, ::-1], process=False).subdivide_to_size(4.0)
    sub.vertices[:, 0] += _centre_x(sub.vertices[:, 1])   # bowed after subdividing (a cylinder has no mid vertices)
    T = np.eye(4)
    T[:3, :3] = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])   # columns: bone x, y, z in world
    return Bone("radius_r", mesh=None, bone_to_world=T, inner_mesh=Mesh(sub.vertices, sub.faces, "radius_r"),
                joint_centres={"proximal_radioulnar": [OFFSET, L, 0.0], "wrist": [OFFSET, 0.0, 0.0]})


def _ulna_bone() -> Bone:
    return Bone("ulna_r", joint_centres={"proximal_radioulnar": [0.0, 0.0, L], "distal_radioulnar": [0.0, 0.0, 10.0]})


def _stack(turn_deg: float) -> Volume:
    """Muscle everywhere, the radius's marrow (bright) turned by ``turn_deg`` about the world z axis."""
    px, dz = 0.7, 2.5
    n, K = 120, int(L / dz)
    aff = np.diag([px, px, dz, 1.0])
    aff[:3, 3] = [-(n - 1) * px / 2, -(n - 1) * px / 2, dz / 2]
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    x, y = aff[0, 0] * i + aff[0, 3], aff[1, 1] * j + aff[1, 3]
    data = np.full((n, n, K), 1000.0, np.float32)
    c, s = np.cos(np.radians(turn_deg)), np.sin(np.radians(turn_deg))
    for k in range(K):
        z = aff[2, 2] * k + aff[2, 3]
        cx = _centre_x(z)
        data[..., k][np.hypot(x - c * cx, y - s * cx) <= MARROW_R] = 3000.0
    return Volume(data, aff)


def test_marrow_axis_follows_a_bowed_marrow():
    pts = _marrow_axis(_radius_bone(), fallback=np.zeros((2, 3)))
    assert len(pts) >= 15
    # on the tube's centre line (world z = bone y), over the distal part of the bone
    assert np.abs(pts[:, 0] - _centre_x(pts[:, 2])).max() < 0.5
    assert np.abs(pts[:, 1]).max() < 0.5
    assert pts[:, 2].min() < 0.1 * L and pts[:, 2].max() > 0.6 * L


def test_radius_turn_finds_the_pronated_marrow():
    """The stack holds the radius turned 100 deg about the ulna: the turn found is within a step of it."""
    radius, ulna = _radius_bone(), _ulna_bone()
    for truth in (0.0, 100.0, 170.0):
        T = _radius_turn(_stack(truth), _marrow_axis(radius, fallback=np.zeros((2, 3))), np.eye(4), ulna)
        assert T is not None
        want = Rotation.from_euler("z", truth, degrees=True)
        err = np.degrees((Rotation.from_matrix(T[:3, :3]) * want.inv()).magnitude())
        assert err <= 5.0 + 1e-6, (truth, err)           # the search step
        # a turn about the ulna's axis (the world z axis through the origin): the axis stays put
        assert np.allclose(T[:3, :3] @ [0, 0, 1.0], [0, 0, 1.0], atol=1e-9)
        assert np.allclose(T[:3, 3], 0.0, atol=1e-6)


def test_straight_chord_misses_the_bowed_marrow():
    """Why the medullary axis and not the joint-to-joint chord: the chord of a radius bowed by more than its
    marrow's radius samples mostly muscle, even at the right turn."""
    radius = _radius_bone()
    vol = _stack(0.0)
    chord = np.array([radius.landmark_in_world("wrist"), radius.landmark_in_world("proximal_radioulnar")])
    t = np.linspace(1 / 3, 1.0, 40)[:, None]
    on_chord = chord[0] + t * (chord[1] - chord[0])
    on_axis = _marrow_axis(radius, fallback=chord)
    from scipy.ndimage import map_coordinates

    def median(p):
        return float(np.median(map_coordinates(vol.data, vol.world_to_index(p).T, order=1)))

    assert median(on_axis) > 2500.0 > median(on_chord)


def test_the_radius_target_is_where_the_radius_can_turn_to():
    """Voxels the radius sweeps turning about the radio-ulnar axis: its ring, level by level, nothing else."""
    vol = _stack(0.0)
    radius = _radius_bone()
    pts = radius.inner_mesh.transformed(radius.bone_to_world).vertices       # marrow tube, 15-19 mm off the axis
    pts = pts[pts[:, 2] <= 200.0]                            # a radius ending 40 mm below the stack's top
    axis = (np.zeros(3), np.array([0.0, 0.0, 1.0]))
    everywhere = np.ones(vol.data.shape, bool)
    swept = _swept_by(pts, axis, vol, everywhere)

    def at(x, y, z):
        return swept[tuple(np.round(vol.world_to_index(np.array([[x, y, z]]))[0]).astype(int))]

    z = L / 2
    r = _centre_x(z)
    for ang in (0.0, 100.0, 180.0, 260.0):                   # the radius turned half a turn is still kept
        assert at(r * np.cos(np.radians(ang)), r * np.sin(np.radians(ang)), z)
    assert not at(0.0, 0.0, z)                               # the ulna's place, on the axis
    assert not at(r + MARROW_R + 6.0, 0.0, z)                # fat under the skin, farther out
    assert not at(_centre_x(220.0), 0.0, 220.0)              # past its end (a capitellum above a radial head)
    # near the ends the ring is the one of that level (the bow is smaller there)
    assert at(_centre_x(5.0), 0.0, 5.0) and not at(_centre_x(L / 2) + MARROW_R + 2.5, 0.0, 5.0)


def test_voxels_inside_a_posed_bone_or_near_it():
    vol = _stack(0.0)
    ball = trimesh.creation.icosphere(subdivisions=3, radius=10.0)
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    pose[:3, 3] = [5.0, -4.0, 120.0]
    got = _inside_mesh(vol, pose, Mesh(np.asarray(ball.vertices), np.asarray(ball.faces), "ulna_r"),
                       np.ones(vol.data.shape, bool), margin_mm=1.5)
    xyz = vol.index_to_world(np.argwhere(np.ones(vol.data.shape, bool)).astype(float))
    d = np.linalg.norm(xyz - pose[:3, 3], axis=1)
    flat = got.reshape(-1)
    assert flat[d <= 9.5].all()                              # inside
    assert flat[(d >= 10.3) & (d <= 11.2)].all()             # within the margin outside
    assert not flat[d >= 12.0].any()
