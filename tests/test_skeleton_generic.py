"""The embedded generic skeleton: meshes, tree, ISB frames, landmarks, shape facts, scaling."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from bonecap.errors import BonecapError, InputError
from bonecap.skeleton.generic import (
    INTERIOR_LANDMARKS, REQUIRED_LANDMARKS, VERTEBRAE, build_generic_skeleton, default_shape_params,
    load_generic_description,
)

SIDE = ["hip", "clavicle", "scapula", "humerus", "ulna", "radius", "carpals", "ray1", "ray2", "ray3", "ray4", "ray5",
        "femur", "patella", "tibia", "fibula", "talus", "calcaneus", "foot"] + [f"rib{i}" for i in range(1, 13)]
MIDLINE = ["skull", "mandible", "sacrum", "sternum"] + VERTEBRAE
REQUIRED = MIDLINE + [f"{b}_{s}" for b in SIDE for s in "rl"]
LEG = ["femur", "tibia", "fibula"]


@pytest.fixture(scope="module")
def sk():
    return build_generic_skeleton()


def world_trimesh(sk, name, inner=False):
    bone = sk.bones[name]
    m = bone.inner_mesh if inner else bone.mesh
    wm = m.transformed(bone.bone_to_world)
    return trimesh.Trimesh(wm.vertices, wm.faces, process=False)


def surface_points(mesh, n=60000, seed=0):
    pts, _ = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return pts


def base_of(name):
    return name[:-2] if name[-2:] in ("_r", "_l") else name


# --------------------------------------------------------------------------- meshes


def test_every_required_bone_has_a_closed_mesh_of_sane_size(sk):
    missing = [b for b in REQUIRED if b not in sk.bones]
    assert not missing, missing
    for name in REQUIRED:
        bone = sk.bones[name]
        m = bone.mesh.to_trimesh()
        assert m.is_watertight and m.is_winding_consistent, name
        assert m.volume > 0, name
        assert 500 <= len(m.faces) <= 8000, (name, len(m.faces))
        assert bone.mesh.frame == name
        if bone.inner_mesh is not None:
            mi = bone.inner_mesh.to_trimesh()
            assert mi.is_watertight and mi.is_winding_consistent and mi.volume > 0, name
            assert len(mi.faces) <= 8000, (name, len(mi.faces))


def test_inner_meshes_are_closed_and_inside(sk):
    for name in ["femur_r", "tibia_r", "humerus_l", "radius_r", "ulna_r", "l3", "hip_r", "skull"]:
        bone = sk.bones[name]
        assert bone.inner_mesh is not None, name
        mi = bone.inner_mesh.to_trimesh()
        assert mi.is_watertight and mi.is_winding_consistent and mi.volume > 0, name
        assert len(mi.faces) <= 8000
        mo = bone.mesh.to_trimesh()
        assert mi.volume < mo.volume
        inside = mo.contains(mi.vertices[:: max(1, len(mi.vertices) // 400)])
        assert inside.mean() > 0.97, (name, inside.mean())


def test_left_side_is_the_mirror_of_the_right(sk):
    M = np.diag([1.0, 1.0, -1.0])
    for b in SIDE:
        r = world_trimesh(sk, f"{b}_r")
        left = world_trimesh(sk, f"{b}_l")
        d, _ = cKDTree(left.vertices).query(r.vertices @ M)
        assert d.max() < 1e-6, b
        assert left.volume > 0
        # landmarks mirror too
        br, bl = sk.bones[f"{b}_r"], sk.bones[f"{b}_l"]
        for k in br.landmarks:
            assert np.allclose(M @ br.landmark_in_world(k), bl.landmark_in_world(k), atol=1e-6)


# --------------------------------------------------------------------------- tree and joints


def test_bones_form_a_single_tree_rooted_at_the_sacrum(sk):
    roots = [n for n, b in sk.bones.items() if b.parent is None]
    assert roots == ["sacrum"]
    seen = set()
    for name, bone in sk.bones.items():            # parent before child
        assert bone.parent is None or bone.parent in seen, name
        seen.add(name)
    for name in sk.bones:                          # no cycle: every chain reaches the root
        chain, cur = 0, name
        while sk.bones[cur].parent is not None:
            cur = sk.bones[cur].parent
            chain += 1
            assert chain < 60
        assert cur == "sacrum"


def test_joint_centres_coincide_in_parent_and_child(sk):
    shared_count = 0
    for name, bone in sk.bones.items():
        if bone.parent is None:
            continue
        parent = sk.bones[bone.parent]
        side = name[-1] if name[-2:] in ("_r", "_l") else ""
        shared = 0
        for key in bone.joint_centres:
            pkey = key if key in parent.joint_centres else f"{key}_{side}"
            if pkey not in parent.joint_centres:
                continue
            d = np.linalg.norm(bone.landmark_in_world(key) - parent.landmark_in_world(pkey))
            assert d < 0.5, (name, key, d)
            shared += 1
        if base_of(name) != "sternum":             # the sternum is rigidly attached to T1
            assert shared >= 1, f"{name} shares no joint centre with {bone.parent}"
        shared_count += shared
    assert shared_count > 80
    for key, bones in {"hip": ("hip_r", "femur_r"), "knee": ("femur_r", "tibia_r"), "ankle": ("tibia_r", "talus_r"),
                       "shoulder": ("scapula_r", "humerus_r"), "elbow": ("humerus_r", "ulna_r"),
                       "wrist": ("radius_r", "carpals_r"), "subtalar": ("talus_r", "calcaneus_r"),
                       "patellofemoral": ("femur_r", "patella_r"), "acromioclavicular": ("clavicle_r", "scapula_r"),
                       "atlanto_occipital": ("c1", "skull"), "l5_s1": ("sacrum", "l5"),
                       "proximal_radioulnar": ("ulna_r", "radius_r"), "distal_radioulnar": ("ulna_r", "radius_r")}.items():
        for b in bones:
            assert key in sk.bones[b].joint_centres, (key, b)
    assert "sternoclavicular_r" in sk.bones["sternum"].joint_centres


def test_joint_axes_are_units_and_the_radioulnar_axis_runs_head_to_fovea(sk):
    for s in "rl":
        rad, uln = sk.bones[f"radius_{s}"], sk.bones[f"ulna_{s}"]
        a = rad.landmark_in_world("radial_head_centre")
        b = uln.landmark_in_world("ulnar_head_fovea")
        expect = (b - a) / np.linalg.norm(b - a)
        for bone in (rad, uln):
            ax = bone.bone_to_world[:3, :3] @ bone.joint_axes["radioulnar"]
            assert np.allclose(ax, expect, atol=1e-9)
    for name, key in [("femur_r", "knee"), ("tibia_r", "ankle"), ("humerus_r", "elbow"), ("ulna_l", "elbow")]:
        v = sk.bones[name].joint_axes[key]
        assert abs(np.linalg.norm(v) - 1) < 1e-9
    # knee and elbow flexion axes are roughly medio-lateral
    assert abs((sk.bones["femur_r"].bone_to_world[:3, :3] @ sk.bones["femur_r"].joint_axes["knee"])[2]) > 0.9
    assert abs((sk.bones["humerus_r"].bone_to_world[:3, :3] @ sk.bones["humerus_r"].joint_axes["elbow"])[2]) > 0.8


# --------------------------------------------------------------------------- frames


def test_frames_are_orthonormal_right_handed_and_isb_oriented(sk):
    for name, bone in sk.bones.items():
        R = bone.bone_to_world[:3, :3]
        assert np.allclose(R.T @ R, np.eye(3), atol=1e-9), name
        assert np.linalg.det(R) > 0.999, name
        # X anterior, Y up, Z to the subject's right -- on both sides (left frames are
        # mirrored then Z turned back to the right)
        assert R[0, 0] > 0.3 and R[1, 1] > 0.3 and R[2, 2] > 0.3, (name, np.round(R, 2))


def test_femur_frame_follows_wu_2002(sk):
    for s, zsign in (("r", 1.0), ("l", 1.0)):
        f = sk.bones[f"femur_{s}"]
        R, o = f.bone_to_world[:3, :3], f.bone_to_world[:3, 3]
        hip = f.landmark_in_world("head_centre")
        assert np.allclose(o, hip) and np.allclose(f.joint_centres["hip"], 0, atol=1e-9)
        le, me = f.landmark_in_world("lateral_epicondyle"), f.landmark_in_world("medial_epicondyle")
        y = (hip - 0.5 * (le + me)) / np.linalg.norm(hip - 0.5 * (le + me))
        assert np.allclose(R[:, 1], y, atol=1e-9)
        assert R[2, 2] * zsign > 0.95                # Z to the right
        assert R[0, 0] > 0.95                        # X anterior
        # Z in the plane of the origin and the epicondyles
        n = np.cross(le - hip, me - hip)
        assert abs(n @ R[:, 2]) / np.linalg.norm(n) < 1e-9
    pel = sk.bones["sacrum"].bone_to_world
    for n in ("hip_r", "hip_l"):
        assert np.allclose(sk.bones[n].bone_to_world, pel)
    asis_r, asis_l = sk.bones["hip_r"].landmark_in_world("asis"), sk.bones["hip_l"].landmark_in_world("asis")
    assert np.allclose(pel[:3, 3], 0.5 * (asis_r + asis_l))
    z = (asis_r - asis_l) / np.linalg.norm(asis_r - asis_l)
    assert np.allclose(pel[:3, 2], z)


def test_world_frame_feet_on_the_floor_and_head_at_stature(sk):
    lows = min(world_trimesh(sk, n).vertices[:, 1].min() for n in ("calcaneus_r", "foot_r"))
    assert 3.0 < lows < 25.0          # heel pad / plantar soft tissue under the bones, floor at Y = 0
    vertex = sk.bones["skull"].landmark_in_world("vertex")
    assert 1680.0 < vertex[1] < 1700.0
    hips = [sk.bones[f"femur_{s}"].landmark_in_world("head_centre") for s in "rl"]
    assert hips[0][2] > 0 > hips[1][2]


# --------------------------------------------------------------------------- landmarks


def test_every_required_landmark_is_present_and_on_its_bone(sk):
    for name, bone in sk.bones.items():
        want = REQUIRED_LANDMARKS.get(base_of(name), [])
        missing = [k for k in want if k not in bone.landmarks]
        assert not missing, (name, missing)
        surf = [k for k in bone.landmarks if k not in INTERIOR_LANDMARKS]
        if not surf:
            continue
        m = bone.mesh.to_trimesh()
        pts = np.array([bone.landmarks[k] for k in surf])
        _, dist, _ = trimesh.proximity.closest_point(m, pts)
        bad = {k: round(float(d), 2) for k, d in zip(surf, dist) if d > 1.5}
        assert not bad, (name, bad)
    # interior landmarks are the joint centres they stand for
    for s in "rl":
        assert np.allclose(sk.bones[f"hip_{s}"].landmarks["acetabulum_centre"], sk.bones[f"hip_{s}"].joint_centres["hip"])
        assert np.allclose(sk.bones[f"femur_{s}"].landmarks["head_centre"], sk.bones[f"femur_{s}"].joint_centres["hip"])
        r = sk.bones[f"radius_{s}"]
        assert np.allclose(r.landmarks["radial_head_centre"], r.joint_centres["proximal_radioulnar"])
        assert r.mesh.to_trimesh().contains(r.landmarks["radial_head_centre"][None])[0]


def test_landmarks_are_where_anatomy_puts_them(sk):
    L = lambda b, k: sk.bones[b].landmark_in_world(k)   # noqa: E731
    assert L("femur_r", "lateral_epicondyle")[2] > L("femur_r", "medial_epicondyle")[2]
    assert L("femur_l", "lateral_epicondyle")[2] < L("femur_l", "medial_epicondyle")[2]
    assert L("humerus_r", "head_anterior")[0] > L("humerus_r", "head_posterior")[0] + 25
    assert L("radius_r", "radial_styloid")[2] > L("ulna_r", "ulnar_styloid")[2] + 30      # palms forward
    assert L("hip_r", "asis")[0] > L("hip_r", "psis")[0] + 100
    assert L("skull", "frontal_r")[2] > 0 > L("skull", "frontal_l")[2]
    assert L("skull", "nasion")[0] > L("skull", "occipital_r")[0] + 150
    assert L("c7", "spinous_process")[1] > L("t10", "spinous_process")[1] + 150
    assert L("sternum", "jugular_notch")[1] > L("sternum", "xiphoid")[1] + 120
    assert abs(L("sternum", "jugular_notch")[2]) < 2.0
    assert L("foot_r", "metatarsal2_head")[0] > L("calcaneus_r", "heel_posterior")[0] + 150
    assert L("fibula_r", "lateral_malleolus")[2] > L("tibia_r", "medial_malleolus")[2] + 50
    assert L("ulna_r", "olecranon")[0] < L("humerus_r", "elbow_anterior")[0] - 25


# --------------------------------------------------------------------------- shape facts


def _end_widths(mesh, axis, frac=0.10):
    pts = surface_points(mesh, 40000)
    t = pts @ axis
    lo, hi = t.min(), t.max()
    L = hi - lo
    e1 = np.cross(axis, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)

    def width(sel):
        q = pts[sel]
        p2 = np.stack([q @ e1, q @ e2], 1)
        from scipy.spatial import ConvexHull
        h = p2[ConvexHull(p2).vertices]
        return np.linalg.norm(h[:, None] - h[None], axis=2).max()
    return width(t > hi - frac * L), width(t < lo + frac * L)


def test_radius_is_wide_at_the_wrist_and_ulna_wide_at_the_elbow(sk):
    for s in "rl":
        for bone, check in (("radius", lambda p, d: d > 1.5 * p), ("ulna", lambda p, d: p > 1.5 * d)):
            b = sk.bones[f"{bone}_{s}"]
            m = world_trimesh(sk, f"{bone}_{s}")
            axis = b.bone_to_world[:3, :3][:, 1]                  # ISB Y: distal -> proximal
            prox, dist = _end_widths(m, axis)
            assert check(prox, dist), (bone, s, prox, dist)


def _femur_angles(sk, name):
    """Neck-shaft angle and anteversion measured on the mesh: shaft axis from the
    centroids of two diaphyseal slabs, neck axis from the head centre through the
    centroid of a slab across the neck, epicondylar axis from the landmarks."""
    f = sk.bones[name]
    m = world_trimesh(sk, name)
    pts = surface_points(m, 150000)
    R = f.bone_to_world[:3, :3]
    hc = f.landmark_in_world("head_centre")
    y = pts @ R[:, 1]
    lo, hi = y.min(), y.max()
    cen = [pts[np.abs(y - (lo + a * (hi - lo))) < 1.0].mean(0) for a in (0.3, 0.65)]
    s = (cen[1] - cen[0]) / np.linalg.norm(cen[1] - cen[0])
    r = f.metadata["head_radius_mm"]
    n = np.asarray(f.metadata["neck_axis"])                       # nominal, only to place the slabs
    for _ in range(2):
        rel = pts - hc
        along = rel @ -n
        radial = np.linalg.norm(rel + np.outer(along, n), axis=1)
        cents = [pts[(np.abs(along - k * r) < 1.0) & (radial < 1.1 * r)].mean(0) for k in (1.05, 1.15, 1.25)]
        c = np.mean(cents, axis=0)
        n = (hc - c) / np.linalg.norm(hc - c)
    nsa = np.degrees(np.arccos(np.clip(n @ -s, -1, 1)))
    le, me = f.landmark_in_world("lateral_epicondyle"), f.landmark_in_world("medial_epicondyle")
    lat = le - me
    lat = lat - (lat @ s) * s
    lat /= np.linalg.norm(lat)
    ant = np.cross(s, lat) if name.endswith("_r") else -np.cross(s, lat)
    npj = n - (n @ s) * s
    av = np.degrees(np.arctan2(npj @ ant, npj @ -lat))
    return nsa, av, n, s


def test_femoral_neck_angles_match_the_parameters(sk):
    p = sk.metadata["params"]
    for name in ("femur_r", "femur_l"):
        nsa, av, _, _ = _femur_angles(sk, name)
        assert abs(nsa - p["femoral_neck_shaft_deg"]) < 3.0, (name, nsa)
        assert abs(av - p["femoral_anteversion_deg"]) < 3.0, (name, av)


def _radial_profile(outer_pts, inner_pts, centre, axis, level, half=1.0):
    def ring(pts):
        rel = pts - centre
        t = rel @ axis
        sel = np.abs(t - level) < half
        q = rel[sel] - np.outer(t[sel], axis)
        return q
    return ring(outer_pts), ring(inner_pts)


def test_cortical_thickness_femur_and_scapula(sk):
    f = sk.bones["femur_r"]
    mo, mi = world_trimesh(sk, "femur_r"), world_trimesh(sk, "femur_r", inner=True)
    po, pi = surface_points(mo, 120000), surface_points(mi, 120000, seed=1)
    s = np.asarray(f.metadata["shaft_axis"])
    mid = np.asarray(f.metadata["shaft_mid"])
    qo, qi = _radial_profile(po, pi, mid, s, 0.0)
    c = qo.mean(0)
    t_mid = np.linalg.norm(qo - c, axis=1).mean() - np.linalg.norm(qi - c, axis=1).mean()
    assert 4.0 <= t_mid <= 7.0, t_mid
    f.metadata["measured_midshaft_cortex_mm"] = float(t_mid)
    # condyles: the outer surface below the knee centre is within 2 mm of the marrow surface
    knee = f.landmark_in_world("lateral_epicondyle") * 0.5 + f.landmark_in_world("medial_epicondyle") * 0.5
    cond = po[(po - knee) @ f.bone_to_world[:3, 1] < -8.0]
    _, d, _ = trimesh.proximity.closest_point(mi, cond[:: max(1, len(cond) // 800)])
    assert np.median(d) < 2.0, np.median(d)
    # scapular blade: 2-4 mm through the infraspinous fossa
    sc = sk.bones["scapula_r"]
    ms = world_trimesh(sk, "scapula_r")
    nrm = np.asarray(sc.metadata["blade_normal"])
    bc = sc.landmark_in_world("blade_centre")
    u = np.cross(nrm, [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(nrm, u)
    th = []
    for a in np.linspace(-6, 6, 5):
        for b in np.linspace(-6, 6, 5):
            o = bc + a * u + b * v + 8.0 * nrm
            locs, _, _ = ms.ray.intersects_location([o], [-nrm])
            if len(locs) >= 2:
                dd = np.sort((o - locs) @ nrm)
                th.append(dd[1] - dd[0])
    assert len(th) > 10
    assert 2.0 <= np.median(th) <= 4.0, np.median(th)


# --------------------------------------------------------------------------- scaling and parameters


def _lengths(s):
    fr, tb = s.bones["femur_r"], s.bones["tibia_r"]
    return (np.linalg.norm(fr.landmark_in_world("hip") - fr.landmark_in_world("knee")),
            np.linalg.norm(tb.landmark_in_world("knee") - tb.landmark_in_world("ankle")))


def _femur_length(s, name="femur_r"):
    f = s.bones[name]
    return np.ptp(f.mesh.vertices[:, 1])


def test_stature_scales_segments_proportionally(sk):
    tall = build_generic_skeleton(1900.0, bones=LEG)
    a0, b0 = _lengths(sk)
    a1, b1 = _lengths(tall)
    k = 1900.0 / 1700.0
    assert abs(a1 / a0 - k) < 1e-3 and abs(b1 / b0 - k) < 1e-3
    assert abs(tall.bones["femur_r"].metadata["head_radius_mm"] / sk.bones["femur_r"].metadata["head_radius_mm"] - k) < 1e-6
    assert abs(_femur_length(tall) / _femur_length(sk) - k) < 0.01


def test_thigh_scale_changes_the_femur_only(sk):
    long_thigh = build_generic_skeleton(params={"thigh_scale": 1.08}, bones=LEG)
    a0, b0 = _lengths(sk)
    a1, b1 = _lengths(long_thigh)
    assert abs(a1 / a0 - 1.08) < 1e-3
    assert abs(b1 / b0 - 1.0) < 1e-6
    assert 1.06 < _femur_length(long_thigh) / _femur_length(sk) < 1.085
    # widths do not change (non-affine): head radius, epicondylar width
    f0, f1 = sk.bones["femur_r"], long_thigh.bones["femur_r"]
    assert f1.metadata["head_radius_mm"] == f0.metadata["head_radius_mm"]
    w0 = np.linalg.norm(f0.landmarks["lateral_epicondyle"] - f0.landmarks["medial_epicondyle"])
    w1 = np.linalg.norm(f1.landmarks["lateral_epicondyle"] - f1.landmarks["medial_epicondyle"])
    assert abs(w1 - w0) < 1.0


def test_anteversion_turns_the_neck_but_not_the_shaft(sk):
    p = {"femoral_anteversion_deg": 25.0}
    twisted = build_generic_skeleton(params=p, bones=["femur"])
    nsa, av, n1, _ = _femur_angles(twisted, "femur_r")
    assert abs(av - 25.0) < 3.0, av
    _, _, n0, _ = _femur_angles(sk, "femur_r")
    turn = np.degrees(np.arccos(np.clip(n0 @ n1, -1, 1)))
    assert 8.0 < turn < 16.0, turn
    # the distal two thirds are unchanged (within meshing noise)
    a, b = world_trimesh(sk, "femur_r"), world_trimesh(twisted, "femur_r")
    hip_y = sk.bones["femur_r"].landmark_in_world("hip")[1]
    pa = surface_points(a, 20000)
    pa = pa[pa[:, 1] < hip_y - 120.0]
    _, d, _ = trimesh.proximity.closest_point(b, pa[::10])
    assert np.percentile(d, 99) < 0.8, np.percentile(d, 99)
    for k in ("lateral_epicondyle", "medial_epicondyle", "head_centre"):
        assert np.linalg.norm(twisted.bones["femur_r"].landmarks[k] - sk.bones["femur_r"].landmarks[k]) < 1.0


def test_parameters_are_validated():
    spec = default_shape_params()
    for key in ("thigh_scale", "shank_scale", "upper_arm_scale", "forearm_scale", "trunk_scale", "foot_scale",
                "hand_scale", "femoral_anteversion_deg", "femoral_neck_shaft_deg", "femur_anterior_bow_mm",
                "radius_lateral_bow_mm", "pelvis_width_scale"):
        lo, hi = spec[key]["range"]
        assert lo <= spec[key]["default"] <= hi
    with pytest.raises(BonecapError, match="unknown"):
        build_generic_skeleton(params={"thigh_scael": 1.0}, bones=["sacrum"])
    with pytest.raises(BonecapError, match="range"):
        build_generic_skeleton(params={"femoral_anteversion_deg": 80.0}, bones=["sacrum"])
    with pytest.raises(BonecapError, match="side_mirroring"):
        build_generic_skeleton(params={"thigh_scale_l": 1.05}, bones=["sacrum"])


def test_description_is_readable_and_cited(tmp_path):
    desc = load_generic_description()
    for key, spec in desc["dimensions"].items():
        assert 0 < spec["fraction"] < 1 and spec["source"], key
        assert spec["source"] == "authored" or spec["source"] in desc["references"], key
    for b in ("femur", "tibia", "humerus", "ulna", "radius", "scapula", "clavicle", "sternum", "vertebra", "sacrum"):
        assert "Wu" in desc["bones"][b]["frame"], b
    with pytest.raises(InputError):
        load_generic_description(tmp_path / "nope.yaml")


def test_the_built_template_is_cached_keyed_and_rebuilt_when_unreadable(tmp_path, monkeypatch):
    """load_template keeps the embedded skeleton it built in the cache folder; a later call returns
    the same bones from it, another build option has its own entry, a torn entry is rebuilt, and
    BONECAP_CACHE_DIR=off writes nothing."""
    from bonecap.skeleton.template import load_template, template_cache_dir

    monkeypatch.setenv("BONECAP_CACHE_DIR", str(tmp_path / "c"))
    assert template_cache_dir() == tmp_path / "c"
    first = load_template("default", bones=["femur_r"])
    entries = sorted((tmp_path / "c").glob("generic_*.pickle"))
    assert len(entries) == 1 and "cached_in" not in first.metadata
    again = load_template("default", bones=["femur_r"])
    assert again.metadata["cached_in"] == str(entries[0])
    assert list(again.bones) == list(first.bones)
    for n, b in first.bones.items():
        np.testing.assert_array_equal(again.bones[n].bone_to_world, b.bone_to_world)
        if b.mesh is not None:
            np.testing.assert_array_equal(again.bones[n].mesh.vertices, b.mesh.vertices)
            np.testing.assert_array_equal(again.bones[n].mesh.faces, b.mesh.faces)
    # another stature is another skeleton: its own entry, not the first one's
    tall = load_template("default", bones=["femur_r"], stature_mm=1850.0)
    assert "cached_in" not in tall.metadata
    assert len(list((tmp_path / "c").glob("generic_*.pickle"))) == 2
    assert np.ptp(tall.bones["femur_r"].mesh.vertices, axis=0).max() > np.ptp(first.bones["femur_r"].mesh.vertices, axis=0).max()
    # a torn entry (a run killed while writing it elsewhere, a disk error) is built afresh and replaced
    entries[0].write_bytes(b"not a pickle")
    rebuilt = load_template("default", bones=["femur_r"])
    assert "cached_in" not in rebuilt.metadata
    np.testing.assert_array_equal(rebuilt.bones["femur_r"].mesh.vertices, first.bones["femur_r"].mesh.vertices)
    assert load_template("default", bones=["femur_r"]).metadata["cached_in"] == str(entries[0])
    assert not list((tmp_path / "c").glob("*.part"))
    # a cache folder that cannot be made (a file stands there): built, returned, nothing cached
    (tmp_path / "file").write_text("x")
    monkeypatch.setenv("BONECAP_CACHE_DIR", str(tmp_path / "file" / "c"))
    assert "femur_r" in load_template("default", bones=["femur_r"]).bones
    # turned off: nothing written
    monkeypatch.setenv("BONECAP_CACHE_DIR", "off")
    assert template_cache_dir() is None
    load_template("default", bones=["femur_r"])
    assert len(list((tmp_path / "c").glob("*"))) == 2


def test_a_column_landmark_stays_over_its_seed_when_a_flat_plate_tilts():
    """The acromion's rule: the highest point of a nearly flat plate within a ball jumps from edge
    to edge with a degree of tilt (the acromion landmark had moved 9-10 mm between phantom seeds
    whose scapulae were alike within 1-2 mm); a column rule takes the outer surface's vertex over
    the seed, which a tilt does not move."""
    from types import SimpleNamespace

    from bonecap.skeleton.generic import _place_landmarks, _Rule

    g = np.arange(-20.0, 20.01, 0.5)
    gx, gz = np.meshgrid(g, g)
    top = np.c_[gx.ravel(), np.zeros(gx.size), gz.ravel()]
    plate = np.vstack([top, top - [0.0, 6.0, 0.0]])           # upper and lower surfaces, 6 mm thick
    seed = np.array([2.0, 3.0, 1.0])
    found = {}
    for deg in (-1.0, 1.0):
        a = np.radians(deg)
        R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
        V = plate @ R.T
        for column in (False, True):
            d = SimpleNamespace(rules=[_Rule("top", seed, np.array([0.0, 1.0, 0.0]), 9.0, column=column)],
                                landmarks={})
            _place_landmarks(d, V)
            found[deg, column] = d.landmarks["top"]
    assert np.linalg.norm(found[1.0, False] - found[-1.0, False]) > 10.0      # the ball: edge to edge
    for deg in (-1.0, 1.0):
        p = found[deg, True]
        assert np.hypot(p[0] - seed[0], p[2] - seed[2]) < 0.6, p             # over the seed
        assert p[1] > -0.5, p                                                 # on the upper surface


def test_meshing_one_bone_at_a_time_or_each_in_its_own_worker_gives_the_same_meshes(monkeypatch):
    """The meshing workers' schedule (two at once, one at a time, every bone in a worker of its own
    that then exits) changes the memory held, never a mesh: same vertices, faces and landmarks."""
    import bonecap.skeleton.generic as gen

    monkeypatch.delenv("BONECAP_WORKERS", raising=False)
    bones = ["femur_r", "tibia_r", "patella_r"]

    def build(**kw):
        before = gen.mesh_cache_keys()
        sk = gen._build_generic_skeleton(bones=bones, resolution=3.0, **kw)
        gen.forget_meshes(gen.mesh_cache_keys() - before)     # each build meshes afresh
        return sk

    ref = build()
    monkeypatch.setattr(gen, "OWN_WORKER_VOXELS", 0)         # every bone "large": a worker each
    own = build(mesh_at_once=1)
    monkeypatch.setattr(gen, "OWN_WORKER_VOXELS", 10 ** 12)
    one = build(mesh_at_once=1)
    assert len([b for b in ref.bones.values() if b.mesh is not None]) >= 5      # the pelvis and sacrum too
    for other in (own, one):
        assert list(other.bones) == list(ref.bones)
        for name, b in ref.bones.items():
            o = other.bones[name]
            if b.mesh is None:
                assert o.mesh is None
                continue
            np.testing.assert_array_equal(o.mesh.vertices, b.mesh.vertices)
            np.testing.assert_array_equal(o.mesh.faces, b.mesh.faces)
            assert o.landmarks.keys() == b.landmarks.keys()
            for k in b.landmarks:
                np.testing.assert_array_equal(o.landmarks[k], b.landmarks[k])
