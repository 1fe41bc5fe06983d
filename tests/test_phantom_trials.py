"""Phantom trials: what the C3D holds against the truth, the artefact model, the motions.

Every test runs on the OpenSim Rajagopal2016 model (its own MarkerSet without the virtual
markers) and, once ``bonecap.skeleton.generic`` exists, on the embedded generic skeleton
with the paper's marker set.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
import trimesh
import yaml
from scipy.spatial.transform import Rotation

from bonecap.io.c3d import read_c3d
from bonecap.markers import load_marker_set
from bonecap.model import Mesh
from bonecap.motion.rigid import fit_rigid
from bonecap.phantom.trials import (STA_AMPLITUDE_MM, TRIAL_NAMES, forearm_motion, joint_table, make_trials,
                                    sta_class, synthesize_trials)
from bonecap.skeleton.kinematics import proximal_joint
from bonecap.skeleton.opensim import read_osim
from bonecap.skeleton.template import template_marker_set

TEMPLATES = ["rajagopal", "generic"]
# heel marker and the bone the radius/ulna/humerus are called in each template
HEEL = {"rajagopal": "RCAL", "generic": "RHEE"}
NOISE, GAP, N_GAPS, SEED = 0.5, 15, 4, 3


def _template(kind, shared_data):
    if kind == "rajagopal":
        path = shared_data / "bones/opensim/models/Rajagopal2016.osim"
        return read_osim(path), template_marker_set(path)
    from bonecap.skeleton.generic import build_generic_skeleton

    skel = build_generic_skeleton()
    return skel, load_marker_set("kojima_paper")


@pytest.fixture(scope="module", params=TEMPLATES)
def phantom(request, shared_data, tmp_path_factory):
    """Every trial written to disk once per template, plus the skeleton and marker set."""
    skel, ms = _template(request.param, shared_data)
    out = tmp_path_factory.mktemp(f"phantom_{request.param}")
    t0 = time.perf_counter()
    summary = make_trials(skel, ms, out, seed=SEED, noise_mm=NOISE, gap_frames=GAP, n_gaps=N_GAPS)
    elapsed = time.perf_counter() - t0
    truth = {t: dict(np.load(out / "truth" / f"{t}_poses.npz")) for t in TRIAL_NAMES}
    binding = yaml.safe_load((out / "truth" / "marker_binding.yaml").read_text())["markers"]
    return {"kind": request.param, "skeleton": skel, "marker_set": ms, "out": out, "summary": summary,
            "truth": truth, "binding": binding, "elapsed": elapsed}


def _apply(T, p):
    return (T[..., :3, :3] @ p[..., None])[..., 0] + T[..., :3, 3]


def test_marker_set_is_the_physical_one(phantom):
    ms = phantom["marker_set"]
    names = list(phantom["truth"]["static"]["markers"])
    assert names == ms.physical
    assert not any(ms.markers[n].virtual for n in names)
    if phantom["kind"] == "rajagopal":
        assert "RKJC" not in names and "R_tibial_plateau" not in names and "RASI" in names


def test_c3d_reads_back_as_truth_plus_artefact_plus_noise(phantom):
    residuals = []
    for t in TRIAL_NAMES:
        tr = read_c3d(phantom["out"] / "trials" / f"{t}.c3d")
        d = phantom["truth"][t]
        assert tr.labels == list(d["markers"]) and set(tr.prefixes) == {"Phantom"}
        assert tr.rate == 100.0 and tr.n_frames == len(d["times"])
        # gaps exactly where configured, nowhere else
        expected = np.zeros(tr.points.shape[:2], bool)
        for m, start, n in d["gaps"]:
            expected[start:start + n, m] = True
        assert np.array_equal(np.isnan(tr.points).any(axis=2), expected), t
        assert len(d["gaps"]) == (0 if t == "static" else N_GAPS)
        assert all(n == GAP for _, _, n in d["gaps"])
        ok = ~expected
        # the file holds truth + artefact + the recorded noise (float32 storage)
        stored = d["marker_truth"] + d["sta"] + d["noise"]
        assert np.abs(tr.points[ok] - stored[ok]).max() < 2e-3
        residuals.append((tr.points - d["marker_truth"] - d["sta"])[ok])
    r = np.concatenate(residuals)
    assert abs(r.std() - NOISE) < 0.2 * NOISE
    assert np.abs(r.mean(axis=0)).max() < 0.05


def test_walk_events_are_written(phantom):
    tr = read_c3d(phantom["out"] / "trials" / "walk.c3d")
    strikes = [e for e in tr.events if e["label"] == "Foot Strike"]
    assert {e["context"] for e in strikes} == {"Right", "Left"} and len(strikes) >= 3


def test_sta_amplitudes_per_class_stay_within_bounds_and_are_real(phantom):
    peaks: dict[str, float] = {}
    classes = [phantom["binding"][n]["sta_class"] for n in phantom["truth"]["static"]["markers"]]
    for t in TRIAL_NAMES:
        mag = np.linalg.norm(phantom["truth"][t]["sta"], axis=2)
        for c in set(classes):
            cols = [i for i, k in enumerate(classes) if k == c]
            peaks[c] = max(peaks.get(c, 0.0), float(mag[:, cols].max()))
    for c, p in peaks.items():
        assert p <= STA_AMPLITUDE_MM[c] + 1e-9, (c, p)
    # the artefact is there, near its bound, where the literature puts the big ones
    for c in ("thigh", "upper_arm", "shank", "forearm"):
        if c in peaks:
            assert peaks[c] > 0.5 * STA_AMPLITUDE_MM[c], (c, peaks[c])
    assert peaks["bony"] <= 3.0
    # the class bounds differ as configured: the thigh moves more than a bony landmark
    assert peaks["thigh"] > 2 * peaks["bony"]


def test_sta_is_mostly_rigid_per_cluster(phantom):
    """Fit a rigid transform to each cluster's displaced markers: the rigid motion explains at
    least half of the artefact (RMS), as the literature finds."""
    d = phantom["truth"]["walk"]
    names = list(d["markers"])
    b = phantom["binding"]
    clusters: dict[tuple, list[int]] = {}
    for i, n in enumerate(names):
        clusters.setdefault((b[n]["bone"], b[n]["sta_class"]), []).append(i)
    checked = 0
    for trial in ("walk", "arm_raise"):
        d = phantom["truth"][trial]
        T = d["transforms"]
        bones = list(d["bones"])
        for (bone, cls), idx in clusters.items():
            if len(idx) < 3 or cls == "bony":
                continue
            local = np.array([b[names[i]]["local_mm"] for i in idx])
            truth = d["marker_truth"][:, idx]
            sta = d["sta"][:, idx]
            if np.sqrt((sta ** 2).sum(axis=2).mean()) < 0.5:
                continue  # this segment does not move in this trial
            fit = fit_rigid(local, truth + sta)
            assert fit.valid.all()
            rigid = _apply(fit.transforms[:, None], local[None]) - truth
            ratio = np.sqrt((rigid ** 2).sum() / (sta ** 2).sum())
            assert ratio >= 0.5, (trial, bone, cls, ratio)
            # and the truth transform is not the fitted one: the artefact moves the cluster
            assert np.abs(fit.transforms[:, :3, 3] - T[:, bones.index(bone), :3, 3]).max() > 0.3
            checked += 1
    assert checked >= 3


def test_truth_is_rigid_and_markers_follow_their_binding(phantom):
    b = phantom["binding"]
    for t in TRIAL_NAMES:
        d = phantom["truth"][t]
        T = d["transforms"]
        R = T[..., :3, :3]
        assert np.allclose(R @ np.swapaxes(R, -1, -2), np.eye(3), atol=1e-9)
        assert np.allclose(np.linalg.det(R), 1.0, atol=1e-9)
        assert np.allclose(T[..., 3, :], [0, 0, 0, 1]) and d["valid"].all()
        assert np.all(np.diff(d["times"]) > 0) and d["times"][0] == 0.0
        bones = list(d["bones"])
        for i, n in enumerate(d["markers"]):
            assert d["marker_bones"][i] == b[n]["bone"] and np.array_equal(d["marker_local"][i], b[n]["local_mm"])
            expect = _apply(T[:, bones.index(b[n]["bone"])], np.array(b[n]["local_mm"]))
            assert np.abs(d["marker_truth"][:, i] - expect).max() < 1e-9, (t, n)


def test_joint_centres_of_parent_and_child_coincide(phantom):
    skel = phantom["skeleton"]
    for t in ("walk", "arm_raise", "pronation"):
        d = phantom["truth"][t]
        T = d["transforms"]
        bones = list(d["bones"])
        sliding = set(d["sliding_joints"])
        seen = 0
        table = joint_table(skel)
        for k, (name, child, parent) in enumerate(zip(d["joint_names"], d["joint_child"], d["joint_parent"])):
            joint = str(name).split(":")[0]
            c_parent = skel.bones[str(parent)].joint_centres[joint]
            c_child = skel.bones[str(child)].joint_centres[joint]
            a = _apply(T[:, bones.index(str(parent))], c_parent)
            c = _apply(T[:, bones.index(str(child))], c_child)
            assert np.abs(c - d["joint_centres"][:, k]).max() < 1e-9
            gap = np.linalg.norm(a - c, axis=1).max()
            if name in sliding and "patella" in str(child):
                # the patella rides the trochlea: it turns about the knee axis, so it keeps its
                # distance to the knee centre while its own joint centre slides on the femur
                knee = [j for j in table.joints.values() if j.kind == "knee" and j.parent == str(parent)][0]
                kc = _apply(T[:, bones.index(str(parent))], knee.centre)
                r = np.linalg.norm(c - kc, axis=1)
                assert np.ptp(r) < 1e-6 and (gap > 1.0 or t != "walk"), (t, name)
            elif name in sliding:
                # the radius turns about the radio-ulnar axis (whose ends migrate a few mm): a
                # centre it shares with its parent moves apart by at most twice its distance
                # to that axis, plus the migration
                fs = [f for f in table.forearms.values() if f.radius == str(child)][0]
                p_u = _apply(np.linalg.inv(skel.bones[fs.ulna].bone_to_world) @ skel.bones[str(child)].bone_to_world,
                             c_child)
                axis = (fs.distal - fs.proximal) / np.linalg.norm(fs.distal - fs.proximal)
                off = p_u - fs.proximal
                r = np.linalg.norm(off - (off @ axis) * axis)
                assert gap < 2 * r + 8.0, (t, name, gap, r)
            else:
                assert gap < 1e-6, (t, name, gap)
                seen += 1
        assert seen >= 10


def _arm_angle(T, bones, skel, side):
    """Angle (deg) between the humerus long axis and the trunk's vertical, in the humerus's parent frame."""
    hum = [b for b in bones if b == f"humerus_{side}"][0]
    parent = skel.bones[hum].parent
    _, c_sh, _ = proximal_joint(skel, hum)
    ulna = f"ulna_{side}"
    _, c_el, _ = proximal_joint(skel, ulna)          # elbow centre in the humerus frame
    el = _apply(T[:, bones.index(hum)], c_el)
    sh = _apply(T[:, bones.index(parent)], c_sh)
    Rp = T[:, bones.index(parent), :3, :3]
    v = np.einsum("fji,fj->fi", Rp, el - sh)        # in the parent frame
    return v


def test_static_pose_is_not_the_reference_pose(phantom):
    skel = phantom["skeleton"]
    d = phantom["truth"]["static"]
    bones = list(d["bones"])
    for side in "rl":
        v_static = _arm_angle(d["transforms"], bones, skel, side)[0]
        ref = np.stack([skel.bones[b].bone_to_world for b in bones])[None]
        v_ref = _arm_angle(ref, bones, skel, side)[0]
        angle = np.degrees(np.arccos(v_static @ v_ref / np.linalg.norm(v_static) / np.linalg.norm(v_ref)))
        assert angle >= 30.0, (side, angle)
    # and the subject stands on the floor: the lowest foot bone point is just above z = 0
    z = []
    for b in bones:
        if skel.bones[b].mesh is not None and ("calc" in b or "toe" in b or "foot" in b or "talus" in b):
            z.append(_apply(d["transforms"][0, bones.index(b)], skel.bones[b].mesh.vertices)[:, 2].min())
    assert 0.0 < min(z) < 20.0


def _rel(d, a, b):
    """Pose of bone ``b`` in the frame of bone ``a`` per frame."""
    bones = list(d["bones"])
    T = d["transforms"]
    return np.linalg.inv(T[:, bones.index(a)]) @ T[:, bones.index(b)]


def test_pronation_turns_the_radius_about_the_radioulnar_axis(phantom):
    skel = phantom["skeleton"]
    table = joint_table(skel)
    d = phantom["truth"]["pronation"]
    for side in "rl":
        fs = table.forearms[f"radioulnar_{side}"]
        theta = d[f"forearm_twist_deg_{side}"]
        assert theta[0] == 0.0 and theta.max() >= 170.0
        # 0 -> 180 -> 0 at least twice
        assert np.count_nonzero(np.diff(np.sign(theta - 90.0)) != 0) >= 4
        rel = _rel(d, fs.ulna, fs.radius)
        M = rel @ np.linalg.inv(rel[0])                # motion of the radius, ulna frame
        rotvec = Rotation.from_matrix(M[:, :3, :3]).as_rotvec()
        angle = np.degrees(np.linalg.norm(rotvec, axis=1))
        assert np.abs(angle - theta).max() < 1e-6
        ends = d[f"radioulnar_axis_ulna_{side}"]          # (F, 2, 3): radial head, ulnar head
        for f in np.flatnonzero(theta > 5.0)[::25]:
            n = rotvec[f] / np.linalg.norm(rotvec[f])
            A, B = ends[f]
            axis = (B - A) / np.linalg.norm(B - A)
            assert abs(abs(n @ axis) - 1.0) < 1e-9
            # points of the stored axis are fixed by the motion up to a slide along the axis
            for p in (A, B):
                moved = _apply(M[f], p) - p
                assert np.linalg.norm(moved - (moved @ n) * n) < 1e-6
            # pronation is a right-hand turn about the proximal axis for the right arm
            proximal = (A - B) / np.linalg.norm(A - B)
            assert np.sign(n @ proximal) == (1 if side == "r" else -1)
        # the axis ends migrate by a few mm over the sweep, the ulnar end more
        mig_a = np.linalg.norm(ends[:, 0] - ends[0, 0], axis=1).max()
        mig_b = np.linalg.norm(ends[:, 1] - ends[0, 1], axis=1).max()
        assert 0.3 < mig_a < 5.0 and 1.0 < mig_b < 5.0 and mig_b > mig_a
        # ...and the lab copy of the axis is the ulna copy carried by the ulna
        lab = d[f"radioulnar_axis_lab_{side}"]
        U = d["transforms"][:, list(d["bones"]).index(fs.ulna)]
        assert np.abs(_apply(U[:, None], ends) - lab).max() < 1e-9
        # the ulna barely moves on the humerus while the forearm turns
        hum = skel.bones[fs.ulna].parent
        ru = _rel(d, hum, fs.ulna)
        sweep = np.flatnonzero(theta > 1.0)
        drift = Rotation.from_matrix(ru[sweep, :3, :3] @ np.linalg.inv(ru[sweep[0], :3, :3])).magnitude()
        assert np.degrees(drift).max() < 1.0
        # the radial side of the wrist crosses over the ulna: distal radius moves medially
        # and back by twice the radius-ulna distance, i.e. it really turns 180 deg
        f180 = int(np.argmax(theta))
        dist_r = _apply(M[f180], fs.distal) - fs.distal
        assert np.linalg.norm(dist_r) < 5.0  # the distal axis end (on the ulna head) barely moves
    # the right forearm's twist is also stored under the plain key
    assert np.array_equal(d["forearm_twist_deg"], d["forearm_twist_deg_r"])


def test_forearm_motion_is_identity_at_zero_and_a_screw(phantom):
    table = joint_table(phantom["skeleton"])
    fs = table.forearms["radioulnar_r"]
    M, A, B = forearm_motion(fs, np.array([0.0, 90.0, 180.0]))
    assert np.allclose(M[0], np.eye(4), atol=1e-12)
    assert np.allclose(A[0], fs.proximal) and np.allclose(B[0], fs.distal)
    assert np.allclose(M[:, :3, :3] @ np.swapaxes(M[:, :3, :3], 1, 2), np.eye(3), atol=1e-12)
    assert np.isclose(np.degrees(Rotation.from_matrix(M[2, :3, :3]).magnitude()), 180.0)


def test_walk_advances_with_a_periodic_heel(phantom):
    d = phantom["truth"]["walk"]
    bones = list(d["bones"])
    root = bones[0]
    x = d["transforms"][:, bones.index(root), 0, 3]
    assert x[-1] - x[0] >= 1000.0
    speed = phantom["summary"]["trials"]["walk"]["walking_speed_mm_s"]
    assert 900.0 < speed < 1500.0
    heel = d["marker_truth"][:, list(d["markers"]).index(HEEL[phantom["kind"]])]
    cycle = 110  # frames of one 1.1 s gait cycle
    F = len(heel)
    assert F >= 2 * cycle
    z = heel[:, 2]
    assert np.abs(z[cycle:] - z[:F - cycle]).max() < 1e-6
    # and it moves like a heel: on the floor in stance, well up in swing
    assert 10.0 < z.min() < 90.0 and z.max() - z.min() > 100.0
    # the stance foot does not slide much: heel forward speed near zero around mid-stance
    vx = np.gradient(heel[:, 0]) * 100.0
    stance = (np.arange(F) % cycle > 15) & (np.arange(F) % cycle < 35)
    assert np.abs(vx[stance]).mean() < 250.0


def test_same_seed_same_trials_other_seed_differs(phantom):
    skel, ms = phantom["skeleton"], phantom["marker_set"]
    kw = dict(trials=("static", "walk"), duration_scale=0.3, n_gaps=2, gap_frames=5)
    a = synthesize_trials(skel, ms, seed=11, **kw)[0]
    b = synthesize_trials(skel, ms, seed=11, **kw)[0]
    c = synthesize_trials(skel, ms, seed=12, **kw)[0]
    for x, y, z in zip(a, b, c):
        assert np.array_equal(x.points, y.points, equal_nan=True) and x.gaps == y.gaps
        assert np.array_equal(x.transforms, z.transforms)       # the motion is the same...
        assert not np.allclose(x.noise, z.noise)                # ...the noise is not,
        assert not np.allclose(x.sta, z.sta)                    # nor the artefact
    assert a[1].gaps != c[1].gaps


def test_scales_switch_artefact_and_noise_off(phantom):
    skel, ms = phantom["skeleton"], phantom["marker_set"]
    trs = synthesize_trials(skel, ms, trials=("walk",), duration_scale=0.5, sta_scale=0.0, noise_mm=0.0,
                            n_gaps=0)[0]
    assert np.array_equal(trs[0].points, trs[0].marker_truth)
    half = synthesize_trials(skel, ms, trials=("walk",), duration_scale=0.5, sta_scale=0.5, noise_mm=0.0,
                             n_gaps=0, seed=SEED)[0]
    full = synthesize_trials(skel, ms, trials=("walk",), duration_scale=0.5, sta_scale=1.0, noise_mm=0.0,
                             n_gaps=0, seed=SEED)[0]
    # same coefficients, half the amplitude (saturation acts near the bound only)
    ratio = np.linalg.norm(half[0].sta) / np.linalg.norm(full[0].sta)
    assert 0.45 < ratio <= 0.56


def test_lowest_foot_points_bone_by_bone_equal_one_argmin_over_all_points():
    """The walking feet's floor contact: each frame's lowest point, found bone by bone, is the one argmin over
    every point of the foot finds, ties included (the first point)."""
    from bonecap.phantom.trials import _lowest_points

    rng = np.random.default_rng(5)
    F, B = 50, 4
    T = np.tile(np.eye(4), (F, B, 1, 1))
    T[:, :, :3, :3] = Rotation.from_rotvec(rng.normal(scale=0.6, size=(F * B, 3))).as_matrix().reshape(F, B, 3, 3)
    T[:, :, :3, 3] = rng.normal(scale=20.0, size=(F, B, 3))
    idx = [3, 0, 2]
    pts = [np.round(rng.normal(scale=30.0, size=(n, 3))) for n in (40, 7, 25)]
    pts[0][11] = pts[2][5] = [0.0, 0.0, -300.0]     # the same point, far below the rest, on two bones...
    T[:, 2, :3, :3] = T[:, 3, :3, :3] = np.eye(3)
    T[:, 2] = T[:, 3]                    # ...that move together: the lowest point, tied, in every frame
    Z = np.concatenate([p @ T[:, i, 2, :3].T + T[:, i, 2, 3] for i, p in zip(idx, pts)], axis=0)
    low, z_low = _lowest_points(T, idx, pts)
    assert np.array_equal(low, np.argmin(Z, axis=0)) and np.array_equal(z_low, Z.min(axis=0))
    assert (low == 11).all()             # the tie, won by the first bone
    T[:, 2, 2, 3] -= 1000.0              # the third bone far below: its lowest point, offset past the others
    low2, _ = _lowest_points(T, idx, pts)
    assert (low2 >= 47).all()


def test_tiny_preset_is_fast(phantom, tmp_path):
    t0 = time.perf_counter()
    s = make_trials(phantom["skeleton"], phantom["marker_set"], tmp_path, duration_scale=0.2)
    assert time.perf_counter() - t0 < 5.0
    for t in TRIAL_NAMES:
        assert (tmp_path / "trials" / f"{t}.c3d").is_file()
        assert (tmp_path / "truth" / f"{t}_poses.npz").is_file()
        assert s["trials"][t]["frames"] <= phantom["summary"]["trials"][t]["frames"] * 0.55
    d = np.load(tmp_path / "truth" / "pronation_poses.npz")
    assert d["forearm_twist_deg"].max() >= 170.0  # compressed, not cut
    assert not list(tmp_path.rglob("*.tmp"))


def test_mri_pose_is_undone(phantom):
    """A subject whose reference (MRI) pose has the arms and legs abducted moves exactly like the
    same subject in the anatomical pose: angles are anatomical, never 'relative to the scan'. The
    same subject: its shoulder girdles are where the rhythm puts them for the abducted arms."""
    from bonecap.phantom.trials import _pose_core

    skel, ms = phantom["skeleton"], phantom["marker_set"]
    import copy

    mri = copy.deepcopy(skel)
    table = joint_table(skel)
    offsets = {f"{j}_{s}": np.array([[0.0, a, 0.0]]) for s in "rl" for j, a in (("shoulder", 12.0), ("hip", 4.0))}
    root = skel.names[0]
    T, _ = _pose_core(skel, table, offsets, {}, skel.bones[root].bone_to_world[None])
    for i, n in enumerate(skel.names):
        mri.bones[n].bone_to_world = T[0, i]
    moved = {n for i, n in enumerate(skel.names) if np.abs(T[0, i] - skel.bones[n].bone_to_world).max() > 1e-6}
    if phantom["kind"] != "rajagopal":
        assert {"scapula_r", "clavicle_l", "humerus_r", "femur_l"} <= moved
    mri.metadata = {**mri.metadata, "phantom": {"pose": {"arm_abduction_deg_r": 12.0, "arm_abduction_deg_l": 12.0,
                                                        "leg_abduction_deg": 4.0}}}
    kw = dict(trials=("static", "walk"), duration_scale=0.3, seed=5)
    a = synthesize_trials(skel, ms, **kw)[0]
    b = synthesize_trials(mri, ms, **kw)[0]
    # exact, but for the girdles and the arms they carry: the rhythm's turns (elevation, retraction, upward
    # rotation about axes fixed in the reference's frames) do not compose exactly (0.17 mm, 0.14 deg here)
    girdle = [i for i, n in enumerate(skel.names) if n.split("_")[0] in
              ("clavicle", "scapula", "humerus", "ulna", "radius", "carpals", "ray1", "ray2", "ray3", "ray4", "ray5")]
    rest = [i for i in range(len(skel.names)) if i not in girdle]
    for x, y in zip(a, b):
        assert np.abs(x.transforms[:, rest] - y.transforms[:, rest]).max() < 1e-6
        assert np.abs(x.transforms[:, girdle, :3, :3] - y.transforms[:, girdle, :3, :3]).max() < 0.005
        assert np.abs(x.transforms[:, girdle, :3, 3] - y.transforms[:, girdle, :3, 3]).max() < 0.5
        assert np.abs(x.marker_truth - y.marker_truth).max() < 0.5


def test_markers_sit_on_a_given_skin(phantom):
    """With a skin, each marker centre is one marker radius outside it, bound to its bone."""
    from bonecap.phantom.trials import place_phantom_markers

    skel, ms = phantom["skeleton"], phantom["marker_set"]
    pts = np.concatenate([skel.world_mesh(n).vertices for n in skel.names if skel.bones[n].mesh is not None])
    hull = trimesh.convex.convex_hull(pts)
    hull.vertices += 20.0 * hull.vertex_normals  # a (crude, convex) body 20 mm outside the bones
    skin = Mesh(hull.vertices, hull.faces, skel.world)
    bind = place_phantom_markers(ms, skel, skin, marker_radius_mm=7.0)
    _, dist, _ = trimesh.proximity.closest_point(hull, bind.world)
    assert np.allclose(dist, 7.0, atol=0.05)
    assert hull.contains(bind.world).sum() == 0
    for n, bone, loc, w in zip(bind.names, bind.bones, bind.local, bind.world):
        assert np.allclose(_apply(skel.bones[bone].bone_to_world, loc), w)


def test_sta_classes():
    assert sta_class("RTHI", "femur_r") == "thigh" and sta_class("LTH2", "femur_l") == "thigh"
    assert sta_class("RUPA", "humerus_r") == "upper_arm" and sta_class("RSHA", "humerus_r") == "upper_arm"
    assert sta_class("RTIB", "tibia_r") == "shank" and sta_class("RFRM", "radius_r") == "forearm"
    assert sta_class("RFAradius", "radius_r") == "forearm"
    for m, b in (("RASI", "hip_r"), ("RANK", "fibula_r"), ("RLMAL", "tibia_r"), ("RELB", "humerus_r"),
                 ("RMEP", "humerus_r"), ("RWRA", "radius_r"), ("RWRB", "ulna_r"), ("RHEE", "calcaneus_r"),
                 ("RTOE", "foot_r"), ("LFHD", "skull"), ("C7", "c7"), ("RKNE", "femur_r"), ("RMEL", "humerus_r")):
        assert sta_class(m, b) == "bony", m
    assert sta_class("RBAK", "scapula_r") == "soft"


# --------------------------------------------------------------------------------------------
# A toy skeleton with the generic skeleton's topology (radius hanging from the humerus, carpals
# below the radius, landmarks for the radio-ulnar axis) in arbitrary bone frames
# --------------------------------------------------------------------------------------------

_TOY = {  # bone: (parent, {joint centre or landmark: world position (X ant, Y up, Z right)})
    "pelvis": (None, {"hip_r": (0, 900, 90), "hip_l": (0, 900, -90), "back": (-30, 1000, 0),
                      "asis_r": (60, 980, 120), "asis_l": (60, 980, -120), "psis_r": (-110, 990, 40),
                      "psis_l": (-110, 990, -40)}),
    "torso": ("pelvis", {"back": (-30, 1000, 0), "shoulder_r": (0, 1400, 180), "shoulder_l": (0, 1400, -180),
                         "c7": (-90, 1480, 0), "jugular": (40, 1390, 0), "xiphoid": (90, 1220, 0)}),
    "femur_r": ("pelvis", {"hip_r": (0, 900, 90), "knee_r": (0, 480, 90), "lat_epi": (0, 480, 135),
                           "shaft": (10, 650, 140), "front": (60, 700, 95)}),
    "tibia_r": ("femur_r", {"knee_r": (0, 480, 90), "ankle_r": (0, 80, 90), "shaft": (10, 250, 125),
                            "lat_mal": (-10, 75, 120), "front": (45, 300, 90)}),
    "talus_r": ("tibia_r", {"ankle_r": (0, 80, 90), "heel": (-60, 30, 90), "toe": (150, 20, 100),
                            "sole": (40, 0, 90)}),
    "humerus_r": ("torso", {"shoulder_r": (0, 1400, 180), "elbow_r": (0, 1110, 190), "lat_epi": (0, 1110, 225),
                            "med_epi": (0, 1110, 150), "shaft": (0, 1250, 215), "head_ant": (30, 1400, 180)}),
    "ulna_r": ("humerus_r", {"elbow_r": (0, 1110, 190), "ulnar_head_fovea": (-5, 870, 175),
                             "ulnar_styloid": (-10, 860, 170), "olecranon": (-30, 1120, 185)}),
    "radius_r": ("humerus_r", {"elbow_r": (0, 1110, 190), "wrist_r": (0, 860, 200),
                               "radial_head_centre": (0, 1100, 210), "radial_styloid": (0, 860, 225),
                               "shaft": (-15, 980, 215)}),
    "carpals_r": ("radius_r", {"wrist_r": (0, 860, 200), "mc_head": (10, 780, 215), "mc5": (0, 785, 170)}),
}


def _toy_skeleton(rotate: bool):
    from bonecap.model import Bone, Skeleton

    spec = dict(_TOY)
    for name, (parent, pts) in list(_TOY.items()):
        if name.endswith("_r"):
            mirror = {k.replace("_r", "_l"): (x, y, -z) for k, (x, y, z) in pts.items()}
            spec[name[:-2] + "_l"] = (parent.replace("_r", "_l") if parent else None, mirror)
    rng = np.random.default_rng(7)
    bones = {}
    for name, (parent, pts) in spec.items():
        origin = np.array(next(iter(pts.values())), float)
        Q = Rotation.random(random_state=rng).as_matrix() if rotate else np.eye(3)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = Q, origin
        local = {k: Q.T @ (np.array(v, float) - origin) for k, v in pts.items()}
        centres = {k: v for k, v in local.items() if k in ("back",) or k.startswith(
            ("hip_", "knee_", "ankle_", "shoulder_", "elbow_", "wrist_"))}
        marks = {k: v for k, v in local.items() if k not in centres}
        bones[name] = Bone(name=name, parent=parent, bone_to_world=T, joint_centres=centres, landmarks=marks)
    return Skeleton(bones=bones, world="model")


def _toy_markers():
    from bonecap.markers import MarkerDef, MarkerSet

    defs = {}
    for s in "rl":
        S = s.upper()
        for name, bone, lm in ((f"{S}ASI", "pelvis", f"asis_{s}"), (f"{S}PSI", "pelvis", f"psis_{s}"),
                               (f"{S}THI", f"femur_{s}", "shaft"), (f"{S}THA", f"femur_{s}", "front"),
                               (f"{S}KNE", f"femur_{s}", "lat_epi"), (f"{S}TIB", f"tibia_{s}", "shaft"),
                               (f"{S}TIA", f"tibia_{s}", "front"), (f"{S}ANK", f"tibia_{s}", "lat_mal"),
                               (f"{S}HEE", f"talus_{s}", "heel"), (f"{S}TOE", f"talus_{s}", "toe"),
                               (f"{S}UPA", f"humerus_{s}", "shaft"), (f"{S}SHA", f"humerus_{s}", "head_ant"),
                               (f"{S}ELB", f"humerus_{s}", "lat_epi"), (f"{S}MEP", f"humerus_{s}", "med_epi"),
                               (f"{S}ELP", f"ulna_{s}", "olecranon"), (f"{S}WRB", f"ulna_{s}", "ulnar_styloid"),
                               (f"{S}FRM", f"radius_{s}", "shaft"), (f"{S}WRA", f"radius_{s}", "radial_styloid"),
                               (f"{S}FIN", f"carpals_{s}", "mc_head"), (f"{S}FI5", f"carpals_{s}", "mc5")):
            defs[name] = MarkerDef(name=name, bone=bone, landmark=lm, offset_mm=10.0, tracks=[bone])
    for name, lm in (("C7", "c7"), ("CLAV", "jugular"), ("STRN", "xiphoid")):
        defs[name] = MarkerDef(name=name, bone="torso", landmark=lm, offset_mm=10.0, tracks=["torso"])
    return MarkerSet(name="toy", markers=defs)


def test_generic_topology_and_bone_frames_do_not_matter():
    """Radius under the humerus, carpals under the radius, landmark-defined radio-ulnar axis, and
    arbitrary (rotated) bone frames: the lab trajectories of every landmark are the same as with
    world-aligned frames, so the joint table really is template-agnostic."""
    ms = _toy_markers()
    plain, rotated = _toy_skeleton(False), _toy_skeleton(True)
    table = joint_table(rotated)
    assert {"hip_r", "knee_r", "ankle_r", "lumbar", "shoulder_r", "elbow_r", "wrist_l"} <= set(table.joints)
    fs = table.forearms["radioulnar_r"]
    assert fs.source == "landmarks" and fs.radius == "radius_r" and table.hands["r"] == "carpals_r"
    kw = dict(seed=2, sta_scale=0.0, noise_mm=0.0, n_gaps=0, duration_scale=0.4)
    a = synthesize_trials(plain, ms, **kw)[0]
    b = synthesize_trials(rotated, ms, **kw)[0]
    for x, y in zip(a, b):
        assert np.abs(x.marker_truth - y.marker_truth).max() < 1e-6, x.name
        assert np.abs(x.joint_centres - y.joint_centres).max() < 1e-6, x.name
    # the radius (child of the humerus) flexes with the ulna and turns about the landmark axis
    pron = [t for t in b if t.name == "pronation"][0]
    names = pron.bones
    U, R = pron.transforms[:, names.index("ulna_r")], pron.transforms[:, names.index("radius_r")]
    rel = np.linalg.inv(U) @ R
    M = rel @ np.linalg.inv(rel[0])
    head = rotated.bones["radius_r"].landmarks["radial_head_centre"]
    fovea = rotated.bones["ulna_r"].landmarks["ulnar_head_fovea"]
    head_u = _apply(np.linalg.inv(rotated.bones["ulna_r"].bone_to_world) @ rotated.bones["radius_r"].bone_to_world,
                    head)
    # the landmarks themselves stay within the few-mm migration of the axis
    assert np.linalg.norm(_apply(M, head_u) - head_u, axis=1).max() < 5.0
    assert np.linalg.norm(_apply(M, fovea) - fovea, axis=1).max() < 6.0
    theta = pron.info["forearms"]["radioulnar_r"]["theta"]
    assert np.degrees(Rotation.from_matrix(M[np.argmax(theta), :3, :3]).magnitude()) > 179.0
    # the radial styloid marker crosses to the medial side of the ulnar one at full pronation
    wra, wrb = pron.markers.index("RWRA"), pron.markers.index("RWRB")
    lab_right = -np.array([0.0, 1.0, 0.0])  # lab -Y is the subject's right
    f0, f1 = 0, int(np.argmax(theta))
    d0 = (pron.marker_truth[f0, wra] - pron.marker_truth[f0, wrb]) @ lab_right
    d1 = (pron.marker_truth[f1, wra] - pron.marker_truth[f1, wrb]) @ lab_right
    assert d0 > 20.0 and d1 < -10.0


def test_bone_placement_matches_place_markers(shared_data):
    """Without a skin the markers are where place_markers puts them (the phantom reuses it): the
    landmark pushed along the normal of the nearest triangle, found here by brute force; where
    several triangles are equally near the landmark, their area-weighted normals are averaged."""
    from bonecap.markers import MarkerDef, MarkerSet, place_markers
    from bonecap.phantom.trials import place_phantom_markers

    skel = read_osim(shared_data / "bones/opensim/models/Rajagopal2016.osim")
    picks = (("femur_r", "walker_knee_r", 30.0), ("tibia_r", "ankle_r", 12.0), ("pelvis", "hip_r", 9.0),
             ("radius_r", "radius_hand_r", 8.0), ("pelvis", "ground_pelvis", 10.0), ("ulna_r", "radioulnar_r", 5.0))
    defs = {f"M{i}": MarkerDef(name=f"M{i}", bone=b, landmark=j, offset_mm=o, tracks=[b])
            for i, (b, j, o) in enumerate(picks)}
    ms = MarkerSet(name="centres", markers=defs)
    ref = place_markers(ms, skel)
    bind = place_phantom_markers(ms, skel)
    ties_seen = 0
    for n, w in zip(bind.names, bind.world):
        m = defs[n]
        bone = skel.bones[m.bone]
        p = bone.joint_centres[m.landmark]
        tm = bone.mesh.to_trimesh()
        q = trimesh.triangles.closest_point(tm.triangles, np.repeat(p[None], len(tm.faces), axis=0))
        d = np.linalg.norm(q - p, axis=1)
        tied = np.flatnonzero(d <= d.min() + 1e-6)
        ties_seen += len(tied) > 1
        normal = (tm.face_normals[tied] * tm.area_faces[tied, None]).sum(axis=0)
        normal /= np.linalg.norm(normal)
        if m.bone.startswith(("femur", "tibia", "radius", "ulna")):
            # limb long bones: away from the shaft axis (principal axis of the mesh through its centroid)
            c = bone.mesh.vertices.mean(axis=0)
            axis = np.linalg.eigh(np.cov((bone.mesh.vertices - c).T))[1][:, -1]
            r = (p - c) - ((p - c) @ axis) * axis
            if np.linalg.norm(r) >= 3.0:
                normal = r / np.linalg.norm(r)
            else:
                n_perp = normal - (normal @ axis) * axis
                normal = n_perp / np.linalg.norm(n_perp) if np.linalg.norm(n_perp) > 0.3 else normal
        expect = _apply(bone.bone_to_world, p + m.offset_mm * normal)
        assert np.linalg.norm(w - expect) < 1e-6, n
        assert np.linalg.norm(ref[n] - expect) < 1e-6, n
    assert ties_seen >= 1


def test_joint_widths_are_measured_across_the_skin_along_the_joint_axis(phantom):
    """A calliper across the joint along its axis: on a skin of spheres about the knees, ankles and elbows
    the width is the sphere's diameter (plus the calliper's error, drawn from its own stream of the seed);
    the trials carry the widths only when the markers went on a skin."""
    from bonecap.markers import joint_centre_axis
    from bonecap.phantom.trials import measured_joint_widths

    skel, ms = phantom["skeleton"], phantom["marker_set"]
    with_width = {n: m for n, m in ms.markers.items() if m.width is not None}
    if phantom["kind"] == "rajagopal":
        assert not with_width          # an OpenSim MarkerSet names no widths
    else:
        assert sorted(m.width[0] for m in with_width.values()) == sorted(
            f"{s}{j}Width" for s in "LR" for j in ("Knee", "Ankle"))
        radii = {n: 40.0 + 3.0 * i for i, n in enumerate(sorted(with_width))}
        spheres = []
        for n, m in with_width.items():
            c, _ = joint_centre_axis(skel, m.bone, m.width[1])
            s = trimesh.creation.icosphere(subdivisions=5, radius=radii[n])
            s.apply_translation(c)
            spheres.append(s)
        skin_tm = trimesh.util.concatenate(spheres)
        skin = Mesh(skin_tm.vertices, skin_tm.faces, skel.world)
        exact = measured_joint_widths(skel, skin, ms, error_mm=0.0)
        assert exact == {**{m.width[0]: 2 * radii[n] for n, m in with_width.items()}, "MarkerDiameter": 14.0}
        noisy = [measured_joint_widths(skel, skin, ms, seed=s) for s in (1, 2)]
        assert noisy[0] == measured_joint_widths(skel, skin, ms, seed=1)       # deterministic
        diffs = np.array([noisy[0][k] - exact[k] for k in exact if k != "MarkerDiameter"])
        assert 0 < np.abs(diffs).max() <= 10 and noisy[0] != noisy[1]
    assert read_c3d(phantom["out"] / "trials" / "static.c3d").subject_parameters == {}   # no skin: no widths


def test_the_shoulder_girdle_follows_the_arms_elevation(phantom):
    """Scapulohumeral rhythm (trials.GIRDLE_RHYTHM): the clavicle rises and retracts and the scapula turns
    upward as the arm is raised, so the acromion (the shoulder marker's bone) moves on the thorax by
    centimetres, while the humerus keeps the orientation its shoulder angles give it relative to the
    thorax (the girdle only carries the shoulder centre). An OpenSim model without clavicles has none."""
    from dataclasses import replace

    from bonecap.phantom.trials import GIRDLE_RHYTHM, girdle_angles, pose_trial, trial_motion

    skel = phantom["skeleton"]
    table = joint_table(skel)
    if phantom["kind"] == "rajagopal":
        assert table.girdles == {}
        return
    assert set(table.girdles) == {"r", "l"}
    m = trial_motion("arm_raise", table, skeleton=skel, duration_scale=0.3)
    T, _ = pose_trial(skel, table, m)
    T0, _ = pose_trial(skel, replace(table, girdles={}), m)
    names = skel.names
    th, sc, hu = names.index("t6"), names.index("scapula_r"), names.index("humerus_r")
    E = girdle_angles(table, m.angles, "r")["clavicle_elevation"] / GIRDLE_RHYTHM["clavicle_elevation"]
    top, rest = int(np.argmax(E)), int(np.argmin(E))
    assert E[top] > 140 and E[rest] < 1

    def in_thorax(T_, i, p):
        return np.linalg.solve(T_[:, th], np.c_[_apply(T_[:, i], p), np.ones(len(T_))][..., None])[:, :3, 0]

    acr = skel.bones["scapula_r"].landmarks["acromion"]
    up = in_thorax(T, sc, acr)[top] - in_thorax(T, sc, acr)[rest]
    assert up[1] > 25.0 and np.linalg.norm(up) > 40.0            # ISB thorax: y cranial
    assert np.linalg.norm(in_thorax(T0, sc, acr)[top] - in_thorax(T0, sc, acr)[rest]) < 1e-6
    # the humerus's orientation in the thorax is the girdle-free one
    R = np.linalg.solve(T[:, th, :3, :3], T[:, hu, :3, :3])
    R0 = np.linalg.solve(T0[:, th, :3, :3], T0[:, hu, :3, :3])
    assert np.abs(R - R0).max() < 1e-9
    # the scapula turns on its clavicle about the normal of its own plane (ISB's X at the reference)
    cl = names.index("clavicle_r")
    rel = np.linalg.solve(T[:, cl, :3, :3], T[:, sc, :3, :3]) @ np.linalg.inv(
        np.linalg.solve(T[rest, cl, :3, :3], T[rest, sc, :3, :3]))
    axis_in_clavicle = Rotation.from_matrix(rel[top]).as_rotvec()
    xs = np.linalg.solve(T[rest, cl, :3, :3], T[rest, sc, :3, 0])
    assert np.degrees(np.linalg.norm(axis_in_clavicle)) > 20.0
    assert abs(axis_in_clavicle @ xs) / np.linalg.norm(axis_in_clavicle) > np.cos(np.radians(1.0))
    # the joints still meet: the shoulder centre rides on the scapula
    gh_s = _apply(T[:, sc], skel.bones["scapula_r"].joint_centres["shoulder"])
    gh_h = _apply(T[:, hu], skel.bones["humerus_r"].joint_centres["shoulder"])
    assert np.abs(gh_s - gh_h).max() < 1e-6
