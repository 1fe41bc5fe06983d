"""Tests of bonecap.motion.forearm: the pronation model of Kojima et al. §8.2."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bonecap.motion.forearm import (
    FOREARM_MARKERS,
    PAPER_MODEL,
    ForearmModel,
    fit_forearm_model,
    forearm_bone_poses,
    forearm_twist,
    radius_axis_from_poses,
)
from bonecap.motion.rigid import rotation_angle_deg


def rot_about(axis, deg):
    return Rotation.from_rotvec(np.radians(deg) * np.asarray(axis, float) / np.linalg.norm(axis)).as_matrix()


def forearm_markers(phi_deg, side="r"):
    """Elbow at z = 250, wrist at z = 0; wrist markers turned by phi (pronation) about the forearm.

    Right arm: lateral at +x, pronation a right-hand turn about the proximal axis +z.
    Left arm: the mirror image (x -> -x), pronation a right-hand turn about the distal axis -z."""
    s = 1.0 if side == "r" else -1.0
    lat, med = np.array([35.0 * s, 0, 250]), np.array([-35.0 * s, 0, 250])
    rad0, uln0 = np.array([30.0 * s, 0, 0]), np.array([-30.0 * s, 0, 0])
    R = rot_about([0, 0, s], phi_deg)
    return R @ rad0, R @ uln0, lat, med


@pytest.mark.parametrize("side", ["r", "l"])
@pytest.mark.parametrize("phi", [0.0, 30.0, 99.5, 172.1, 200.0, -60.0])
def test_twist_sign_and_mirror(side, phi):
    th = forearm_twist(*forearm_markers(phi, side), side=side)
    assert th.shape == (1,)
    assert th[0] == pytest.approx(phi, abs=1e-9)
    # zero at the subject's own 0 degree pose
    zero = forearm_twist(*forearm_markers(10.0, side), side=side)[0]
    assert forearm_twist(*forearm_markers(phi, side), side=side, zero_deg=zero)[0] == pytest.approx(
        (phi - 10.0 + 90) % 360 - 90, abs=1e-9)


def test_twist_ignores_tilt_of_the_forearm_axis():
    # the same twist seen with the whole forearm turned in the lab: the projection removes it
    rad, uln, lat, med = forearm_markers(45.0)
    G = rot_about([1, 2, 0.5], 70.0)
    pts = [G @ p + [100, -50, 900] for p in (rad, uln, lat, med)]
    assert forearm_twist(*pts)[0] == pytest.approx(45.0, abs=1e-9)
    with pytest.raises(ValueError, match="side"):
        forearm_twist(*pts, side="x")


def test_paper_model_unit_quarter_turns():
    # the figures: at 180 degrees the radius turns ~152 and the ulna ~-21 degrees
    assert PAPER_MODEL.rotation_deg("radius", 180.0) == pytest.approx(90 * (-0.127 * 4 + 1.101 * 2))
    assert PAPER_MODEL.rotation_deg("radius", 180.0) == pytest.approx(152.46, abs=0.01)
    assert PAPER_MODEL.rotation_deg("ulna", 180.0) == pytest.approx(-21.24, abs=0.01)
    theta = np.linspace(0, 180, 181)
    for bone in ("ulna", "radius"):
        uw, ue = PAPER_MODEL.control_points(bone, theta)
        assert np.abs(uw).max() <= 1.05 and np.abs(ue).max() <= 1.05
    # read in radians, the ulna's wrist control point leaves its segment
    rad = ForearmModel(**{**PAPER_MODEL.__dict__, "unit": "rad"})
    uw, _ = rad.control_points("ulna", 180.0)
    assert uw == pytest.approx(-0.2348 * np.pi ** 2 + 0.4337 * np.pi - 0.7492)
    assert abs(uw) > 1.5


def linear_model(**kw):
    base = dict(ulna_rotation=(0, 0, 0), radius_rotation=(0, 1, 0), ulna_wrist=(0, 0, 0), ulna_elbow=(0, 0, 0),
                radius_wrist=(0, 0, -1), radius_elbow=(0, 0, -1), theta_range_deg=(0.0, 180.0))
    base.update(kw)
    return ForearmModel(**base)


def test_bone_poses_turn_about_the_control_line_and_clamp():
    model = linear_model()  # radius turns by theta about the ulnar styloid -> medial epicondyle line
    rad, uln, lat, med = forearm_markers(0.0)
    theta = np.array([0.0, 60.0, 120.0, 200.0])
    F = len(theta)
    W = np.broadcast_to(np.stack([rad, uln]), (F, 2, 3))
    E = np.broadcast_to(np.stack([lat, med]), (F, 2, 3))
    rest = np.tile(np.eye(4), (F, 1, 1))
    out = forearm_bone_poses(model, theta, rest, rest, W, E, side="r")
    axis = med - uln  # proximal for the right arm
    for k, th in enumerate(np.minimum(theta, 180.0)):
        R = rot_about(axis, th)
        p = np.array([10.0, 20.0, 100.0])
        expected = R @ (p - uln) + uln
        got = out["radius"][k, :3, :3] @ p + out["radius"][k, :3, 3]
        assert np.allclose(got, expected, atol=1e-9)
    assert np.allclose(out["ulna"], rest)
    assert out["clamped"].tolist() == [False, False, False, True]
    at_limit = forearm_bone_poses(model, [180.0], rest[:1], rest[:1], W[:1], E[:1])["radius"][0]
    assert np.allclose(out["radius"][3], at_limit)
    # the left arm turns the other way about the same line
    left = forearm_bone_poses(model, theta[:2], rest[:2], rest[:2], W[:2], E[:2], side="l")
    assert rotation_angle_deg(left["radius"][1], out["radius"][1]) == pytest.approx(120.0, abs=1e-6)
    with pytest.raises(ValueError, match="wrist_markers"):
        forearm_bone_poses(model, theta, rest, rest, W[:2], E, side="r")


def test_fit_recovers_a_known_model():
    truth = linear_model(radius_rotation=(-0.12, 1.05, 0.0), radius_wrist=(0, -0.15, -0.4),
                         radius_elbow=(0, 0.2, 0.1), theta_range_deg=(0.0, 172.1))
    rad, uln, lat, med = forearm_markers(0.0)
    theta = np.array([0.0, 99.5, 172.1])
    K = len(theta)
    W = np.broadcast_to(np.stack([rad, uln]), (K, 2, 3)).copy()
    E = np.broadcast_to(np.stack([lat, med]), (K, 2, 3)).copy()
    R0 = np.eye(4)
    R0[:3, 3] = [20, 5, 120]
    rest = np.broadcast_to(R0, (K, 4, 4))
    U = np.tile(np.eye(4), (K, 1, 1))
    radius = forearm_bone_poses(truth, theta, U, rest, W, E)["radius"]
    fitted = fit_forearm_model(theta, U, radius, W, E)
    assert np.allclose(fitted.radius_rotation, truth.radius_rotation, atol=1e-8)
    assert np.allclose(fitted.radius_wrist, truth.radius_wrist, atol=1e-8)
    assert np.allclose(fitted.radius_elbow, truth.radius_elbow, atol=1e-8)
    assert fitted.theta_range_deg == (0.0, 172.1)
    # the ulna did not move: no rotation, no axis
    assert np.allclose(fitted.ulna_rotation, 0.0, atol=1e-8)
    with pytest.raises(ValueError, match="at least 3"):
        fit_forearm_model(theta[:2], U[:2], radius[:2], W[:2], E[:2])


def test_fit_unwraps_a_turn_beyond_half_a_turn():
    """A radius turned 190 deg at the last pose: its screw angle reads -170 deg, the fit must not."""
    truth = linear_model(radius_rotation=(0.0, 1.08, 0.0), radius_wrist=(0, 0.0, -0.4),
                         radius_elbow=(0, 0.0, 0.1), theta_range_deg=(0.0, 176.0))
    rad, uln, lat, med = forearm_markers(0.0)
    theta = np.array([0.0, 90.0, 176.0])                  # turns 0, 97.2, 190.1 deg
    K = len(theta)
    W = np.broadcast_to(np.stack([rad, uln]), (K, 2, 3)).copy()
    E = np.broadcast_to(np.stack([lat, med]), (K, 2, 3)).copy()
    R0 = np.eye(4)
    R0[:3, 3] = [20, 5, 120]
    U = np.tile(np.eye(4), (K, 1, 1))
    radius = forearm_bone_poses(truth, theta, U, np.broadcast_to(R0, (K, 4, 4)), W, E)["radius"]
    fitted = fit_forearm_model(theta, U, radius, W, E)
    assert np.allclose(fitted.rotation_deg("radius", theta), [0.0, 97.2, 190.08], atol=1e-6)
    assert np.allclose(fitted.radius_rotation, truth.radius_rotation, atol=1e-8)


# --------------------------------------------------------------------------- phantom


@pytest.fixture(scope="module")
def phantom(tmp_path_factory):
    from bonecap.phantom import make_phantom

    out = tmp_path_factory.mktemp("ph")
    make_phantom(out, seed=3, preset="tiny")
    return out


def test_fit_on_phantom_mri_poses_and_use_in_lsq(phantom):
    from bonecap.io.c3d import read_c3d
    from bonecap.motion.lsq import solve_lsq
    from test_motion_lsq import skeleton_from_truth

    truth = phantom / "truth"
    skel = skeleton_from_truth(truth)
    d = np.load(truth / "pronation_poses.npz")
    labels, mb, local = list(d["markers"]), list(d["marker_bones"]), d["marker_local"]
    ix = [labels.index(n) for n in FOREARM_MARKERS["r"]]
    poses = sorted(json.load(open(truth / "forearm.json"))["poses"].values(), key=lambda p: p["theta_deg"])
    T = [{b: np.array(v) for b, v in p["bone_to_lps"].items()} for p in poses]
    P = np.array([[(t.get(mb[i], skel.bones[mb[i]].bone_to_world) @ np.r_[local[i], 1])[:3] for i in ix] for t in T])
    zero = forearm_twist(*P[0])[0]
    theta = forearm_twist(P[:, 0], P[:, 1], P[:, 2], P[:, 3], zero_deg=zero)
    assert theta[0] == pytest.approx(0.0, abs=1e-9) and np.all(np.diff(theta) > 30)
    U = np.array([t["ulna_r"] for t in T])
    R = np.array([t["radius_r"] for t in T])
    model = fit_forearm_model(theta, U, R, P[:, :2], P[:, 2:])
    # the fitted rotation at each measured twist is the true turn of the radius about the ulna
    rel = np.linalg.inv(U) @ R
    true_turn = rotation_angle_deg(rel[0], rel)
    assert np.allclose(model.rotation_deg("radius", theta), true_turn, atol=1e-6)
    # the fitted axis (control line) is close to the true radio-ulnar axis direction at the fitted twists
    ax = np.array([p["radioulnar_axis_lps"] for p in poses])
    for k in (1, 2):
        uw, ue = model.control_points("radius", theta[k])
        pw = 0.5 * (P[k, 0] + P[k, 1]) + uw * 0.5 * (P[k, 0] - P[k, 1])
        pe = 0.5 * (P[k, 2] + P[k, 3]) + ue * 0.5 * (P[k, 2] - P[k, 3])
        d_model = (pe - pw) / np.linalg.norm(pe - pw)
        d_true = (ax[k, 0] - ax[k, 1]) / np.linalg.norm(ax[k, 0] - ax[k, 1])
        assert np.degrees(np.arccos(abs(d_model @ d_true))) < 8.0

    tr = read_c3d(phantom / "trials" / "pronation.c3d")
    meas = tr.points[:, [tr.labels.index(m) for m in labels]]
    mo = solve_lsq(skel, mb, local, meas, marker_labels=labels, forearm={"r": model})
    i = list(d["bones"]).index("radius_r")
    deg = rotation_angle_deg(mo.transforms[:, i], d["transforms"][:, i])
    assert np.nanmedian(deg) < 5.0
    # the radius turned about the subject's own radio-ulnar axis (carried with the ulna) instead of the
    # control line on the skin markers' segments: the same turn, a truer axis, less position error
    import dataclasses

    mo_a = solve_lsq(skel, mb, local, meas, marker_labels=labels,
                     forearm={"r": dataclasses.replace(model, radius_axis="anatomical")})
    deg_a = rotation_angle_deg(mo_a.transforms[:, i], d["transforms"][:, i])
    mm = np.linalg.norm(mo.transforms[:, i, :3, 3] - d["transforms"][:, i, :3, 3], axis=1)
    mm_a = np.linalg.norm(mo_a.transforms[:, i, :3, 3] - d["transforms"][:, i, :3, 3], axis=1)
    assert np.nanmedian(deg_a) < 5.0 and np.nanmedian(mm_a) < np.nanmedian(mm)
    with pytest.raises(ValueError, match="radius_axis"):
        dataclasses.replace(model, radius_axis="skin")
    # twists beyond the fitted range are clamped and flagged; the clamped pose stays a pose (valid)
    th_trial = d["forearm_twist_deg_r"]
    clamped = mo.flags["forearm_clamped"][:, i]
    assert clamped[th_trial > 179.0].all() and mo.valid[th_trial > 179.0, i].all()
    assert not clamped[(th_trial > 20) & (th_trial < 120)].any()
    assert mo.valid[(th_trial > 20) & (th_trial < 120), i].all()


def test_a_side_without_stacks_takes_the_other_sides_fitted_model():
    """animate's models: the fitted side's own, the other side mirrored from it, the paper's only when
    nothing was fitted (on the phantom the right arm's fit put the left radius 5.4 deg off, the paper's
    coefficients 11.7 deg)."""
    from types import SimpleNamespace

    from bonecap.animate import forearm_models

    fitted = {**PAPER_MODEL.to_dict(), "radius_rotation": [-0.2, 1.4, 0.0], "side": "r"}
    models = forearm_models(SimpleNamespace(forearm={"r": fitted}))
    assert models["r"].radius_rotation == (-0.2, 1.4, 0.0)
    assert models["l"] == models["r"]
    both = forearm_models(SimpleNamespace(forearm={"r": fitted, "l": {**fitted, "radius_rotation": [0.0, 1.0, 0.0]}}))
    assert both["l"].radius_rotation == (0.0, 1.0, 0.0) and both["r"].radius_rotation == (-0.2, 1.4, 0.0)
    none = forearm_models(SimpleNamespace(forearm={}))
    assert none["r"] is PAPER_MODEL and none["l"] is PAPER_MODEL
    # the radius's axis measured in the right ulna's frame is the right arm's alone
    axis = [1.0, 250.0, 20.0, 5.0, 15.0, 4.0]
    models = forearm_models(SimpleNamespace(forearm={"r": {**fitted, "radius_axis": "anatomical",
                                                               "radius_axis_ulna_mm": axis}}))
    assert models["r"].radius_axis_ulna_mm == tuple(axis) and models["l"].radius_axis_ulna_mm == ()
    assert models["l"].radius_rotation == models["r"].radius_rotation
    with pytest.raises(ValueError, match="radius_axis_ulna_mm"):
        ForearmModel.from_dict({**fitted, "radius_axis_ulna_mm": [1.0, 2.0]})


def _screw(point, direction, angle_deg, slide_mm=0.0):
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    G = np.eye(4)
    G[:3, :3] = Rotation.from_rotvec(np.radians(angle_deg) * d).as_matrix()
    G[:3, 3] = point - G[:3, :3] @ point + slide_mm * d
    return G


def test_radius_axis_from_poses_finds_the_screw_axis():
    """Radius poses turned about a known line of the ulna's frame (with a slide along it) give that line;
    its ends are the points nearest the guessed ends; a pose that turned too little places nothing."""
    rng = np.random.default_rng(2)
    p0, d = np.array([4.0, 250.0, 19.0]), np.array([0.05, -1.0, -0.06])
    U = np.array([_screw(rng.normal(size=3) * 50, rng.normal(size=3), a) for a in (0.0, 37.0, -21.0)])
    R_rest = _screw(np.array([20.0, 100.0, 0.0]), [0.0, 0.0, 1.0], 12.0)      # radius frame in the ulna's
    rel = [R_rest, _screw(p0, d, 99.5, 0.4) @ R_rest, _screw(p0, d, 172.1, 0.1) @ R_rest]
    R = np.array([u @ r for u, r in zip(U, rel)])
    guess = np.array([p0 + [3.0, 0.0, 0.0], p0 + 235 * d / np.linalg.norm(d) + [0.0, 0.0, 3.0]])
    ends, rep = radius_axis_from_poses(U, R, guess)
    dn = d / np.linalg.norm(d)
    for e, q in zip(ends, guess):
        v = e - p0
        assert np.linalg.norm(v - (v @ dn) * dn) < 1e-6                # on the true axis
        assert abs((q - e) @ dn) < 1e-6                                   # nearest the guess
    assert rep["turn_deg"] == pytest.approx([99.5, 172.1])
    assert np.abs(rep["slide_mm"]) == pytest.approx([0.4, 0.1], abs=1e-6)
    assert rep["guess_off_mm"] == pytest.approx([3.0, 3.0], abs=0.05) and max(rep["spread_mm"]) < 1e-6
    # the reference need not come first; twists under the minimum turn place no axis
    ends2, _ = radius_axis_from_poses(U[::-1], R[::-1], guess, ref=2)
    np.testing.assert_allclose(ends2, ends, atol=1e-6)
    small = np.array([U[0] @ R_rest, U[1] @ _screw(p0, d, 20.0) @ R_rest])
    assert radius_axis_from_poses(U[:2], small, guess)[0] is None
    with pytest.raises(ValueError, match="ends_guess"):
        radius_axis_from_poses(U, R, guess[0])
    with pytest.raises(ValueError, match="ref"):
        radius_axis_from_poses(U, R, guess, ref=3)
