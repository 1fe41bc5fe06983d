"""Tests of bonecap.motion.rigid: the weighted least-squares rigid fit."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from bonecap.motion.rigid import (
    BoneFits,
    RigidFit,
    apply_transform,
    fit_rigid,
    fit_rigid_bones,
    rotation_angle_deg,
)

# --------------------------------------------------------------------------- helpers


def rodrigues(axis, angle):
    """Rotation matrix about a unit axis (independent of the code under test)."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def make_T(R, t):
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def random_T(rng, trans=1000.0):
    """Random rigid transform(s): uniform rotation (via a normalised Gaussian quaternion)."""
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    R = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])
    return make_T(R, rng.uniform(-trans, trans, 3))


def move(T, p):
    """Apply a 4x4 to (N, 3) points, written out independently of apply_transform."""
    return p @ T[:3, :3].T + T[:3, 3]


def cluster(rng, m, scale=60.0):
    return rng.normal(scale=scale, size=(m, 3))


# --------------------------------------------------------------------------- property: exact recovery


def rms_spread_across(p):
    """RMS spread of points across their main axis (second singular value / sqrt(M))."""
    s = np.linalg.svd(p - p.mean(axis=0), compute_uv=False)
    return s[1] / np.sqrt(len(p))


unit_floats = st.floats(-1.0, 1.0, allow_nan=False)
angles = st.one_of(
    st.floats(0.0, np.pi),
    st.floats(np.pi - 1e-6, np.pi),  # near a half turn, where trace-based methods break
    st.just(np.pi),
    st.floats(0.0, 1e-6),
)


@settings(max_examples=150, deadline=None)
@given(
    markers=st.integers(3, 10).flatmap(
        lambda m: hnp.arrays(float, (m, 3), elements=st.floats(-150.0, 150.0))),
    axis=st.tuples(unit_floats, unit_floats, unit_floats),
    angle=angles,
    translation=st.tuples(*[st.floats(-5000.0, 5000.0)] * 3),
)
def test_noise_free_motion_is_recovered_exactly(markers, axis, angle, translation):
    assume(np.linalg.norm(axis) > 0.1)
    assume(rms_spread_across(markers) >= 10.0)  # non-collinear, spread >= 10 mm
    R = rodrigues(axis, angle)
    t = np.array(translation)
    measured = markers @ R.T + t

    fit = fit_rigid(markers, measured)

    assert isinstance(fit, RigidFit)
    assert fit.valid
    np.testing.assert_allclose(fit.transforms[:3, :3], R, rtol=0, atol=1e-9)
    np.testing.assert_allclose(fit.transforms[:3, 3], t, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(fit.transforms[3], [0, 0, 0, 1])
    assert np.linalg.det(fit.transforms[:3, :3]) == pytest.approx(1.0, abs=1e-12)
    assert np.all(fit.residuals < 1e-9)
    assert fit.rms < 1e-9
    assert fit.n_used == len(markers)


def test_reflected_data_give_a_proper_rotation():
    """Mirror-image data: plain Kabsch would return det = -1; the fix must not."""
    rng = np.random.default_rng(3)
    local = cluster(rng, 6)
    measured = local * [1, 1, -1]  # a reflection, not a rotation
    fit = fit_rigid(local, measured)
    R = fit.transforms[:3, :3]
    assert fit.valid
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert fit.rms > 1.0  # a mirror cannot be fitted exactly


# --------------------------------------------------------------------------- lab-frame independence


def test_fit_does_not_depend_on_the_lab_frame():
    rng = np.random.default_rng(11)
    for _ in range(20):
        local = cluster(rng, rng.integers(3, 9))
        T = random_T(rng)
        measured = move(T, local) + rng.normal(scale=2.0, size=local.shape)  # not exactly rigid
        G = random_T(rng, trans=3000.0)
        fit_a = fit_rigid(local, measured)
        fit_g = fit_rigid(local, move(G, measured))
        np.testing.assert_allclose(fit_g.transforms, G @ fit_a.transforms, rtol=0, atol=1e-9)
        np.testing.assert_allclose(fit_g.residuals, fit_a.residuals, rtol=0, atol=1e-9)
        assert fit_a.rms > 0.1  # the data were noisy: the check was not trivial


# --------------------------------------------------------------------------- weights


def test_zero_weight_outlier_equals_fit_without_it():
    rng = np.random.default_rng(5)
    local = cluster(rng, 6)
    T = random_T(rng)
    measured = move(T, local) + rng.normal(scale=0.5, size=local.shape)
    measured[2] += [40.0, -30.0, 25.0]  # gross outlier
    w = np.ones(6)
    w[2] = 0.0

    with_zero = fit_rigid(local, measured, w)
    without = fit_rigid(np.delete(local, 2, 0), np.delete(measured, 2, 0))
    unweighted = fit_rigid(local, measured)

    np.testing.assert_allclose(with_zero.transforms, without.transforms, rtol=0, atol=1e-9)
    assert with_zero.n_used == 5
    assert with_zero.rms == pytest.approx(without.rms, abs=1e-12)
    # the outlier still gets a residual, and it is large
    assert with_zero.residuals[2] > 40.0
    # the outlier does pull the unweighted fit away
    assert rotation_angle_deg(unweighted.transforms, with_zero.transforms) > 0.5


def test_weights_are_scale_invariant_but_do_matter():
    rng = np.random.default_rng(6)
    local = cluster(rng, 5)
    measured = move(random_T(rng), local) + rng.normal(scale=3.0, size=local.shape)
    w = rng.uniform(0.1, 5.0, 5)
    base = fit_rigid(local, measured, w)
    for c in (1e-6, 3.7, 1e6):
        scaled = fit_rigid(local, measured, c * w)
        np.testing.assert_allclose(scaled.transforms, base.transforms, rtol=0, atol=1e-9)
        assert scaled.rms == pytest.approx(base.rms, rel=1e-9)
    uniform = fit_rigid(local, measured)
    assert np.abs(uniform.transforms - base.transforms).max() > 1e-3


def test_weighted_fit_minimises_weighted_objective():
    """Perturbing the weighted optimum must not lower sum w r^2."""
    rng = np.random.default_rng(8)
    local = cluster(rng, 5)
    measured = move(random_T(rng), local) + rng.normal(scale=3.0, size=local.shape)
    w = rng.uniform(0.1, 5.0, 5)
    T = fit_rigid(local, measured, w).transforms

    def cost(T):
        return np.sum(w * np.sum((move(T, local) - measured) ** 2, axis=1))

    c0 = cost(T)
    for _ in range(50):
        dT = make_T(rodrigues(rng.normal(size=3), 1e-3), rng.normal(scale=1e-2, size=3))
        assert cost(dT @ T) >= c0 - 1e-9


def test_per_frame_weights_broadcast():
    rng = np.random.default_rng(9)
    local = cluster(rng, 4)
    meas = np.stack([move(random_T(rng), local) + rng.normal(size=local.shape) for _ in range(3)])
    w = rng.uniform(0.5, 2.0, (3, 4))
    fit = fit_rigid(local, meas, w)
    for f in range(3):
        np.testing.assert_allclose(fit.transforms[f], fit_rigid(local, meas[f], w[f]).transforms,
                                   rtol=0, atol=1e-12)


# --------------------------------------------------------------------------- NaN / degenerate


def test_two_visible_markers_give_nan_and_invalid():
    rng = np.random.default_rng(1)
    local = cluster(rng, 5)
    measured = move(random_T(rng), local)
    measured[[0, 2, 4]] = np.nan
    fit = fit_rigid(local, measured)
    assert not fit.valid
    assert np.isnan(fit.transforms).all()
    assert np.isnan(fit.rms)
    assert fit.n_used == 2
    assert np.isnan(fit.residuals).all()


def test_three_visible_markers_fit_exactly():
    rng = np.random.default_rng(2)
    local = cluster(rng, 6)
    T = random_T(rng)
    measured = move(T, local)
    measured[[1, 3, 4]] = np.nan
    fit = fit_rigid(local, measured)
    assert fit.valid
    np.testing.assert_allclose(fit.transforms, T, rtol=0, atol=1e-9)
    assert np.isnan(fit.residuals[[1, 3, 4]]).all()
    assert np.all(fit.residuals[[0, 2, 5]] < 1e-9)
    # a partly-NaN marker counts as missing too
    measured[0, 1] = np.nan
    assert not fit_rigid(local, measured).valid


def test_min_markers_is_honoured():
    rng = np.random.default_rng(4)
    local = cluster(rng, 5)
    measured = move(random_T(rng), local)
    measured[:2] = np.nan
    assert fit_rigid(local, measured, min_markers=3).valid
    assert not fit_rigid(local, measured, min_markers=4).valid
    # zero weights count as absent
    assert not fit_rigid(local, move(random_T(rng), local), weights=[1, 1, 0, 0, 1], min_markers=4).valid


def test_collinear_markers_are_invalid():
    rng = np.random.default_rng(7)
    direction = np.array([0.3, -0.5, 0.8])
    line = np.outer([-60.0, -10.0, 25.0, 80.0], direction) + [10.0, 20.0, 30.0]
    T = random_T(rng)
    # exact line, and noisy measurements of an exact line: both undetermined
    for measured in (move(T, line), move(T, line) + rng.normal(scale=0.5, size=line.shape)):
        fit = fit_rigid(line, measured)
        assert not fit.valid
        assert np.isnan(fit.transforms).all()
    # nearly collinear (1e-4 mm off a 140 mm line) is invalid; 5 mm off is fine
    for offset, ok in ((1e-4, False), (5.0, True)):
        local = line.copy()
        local[1] += offset * np.array([0.0, 0.8, 0.5])
        fit = fit_rigid(local, move(T, local))
        assert bool(fit.valid) is ok, (offset, fit.spread_ratio)
    # all markers on one point
    assert not fit_rigid(np.zeros((4, 3)), np.ones((4, 3))).valid


def test_spread_ratio_threshold_is_configurable():
    rng = np.random.default_rng(12)
    local = np.array([[0, 0, 0], [100, 0, 0], [200, 0, 0], [100, 2, 0]], float)
    measured = move(random_T(rng), local)
    fit = fit_rigid(local, measured)
    assert fit.valid and 1e-3 < fit.spread_ratio < 0.05
    assert not fit_rigid(local, measured, min_spread_ratio=0.05).valid


# --------------------------------------------------------------------------- batching


def test_batched_frames_equal_single_fits():
    rng = np.random.default_rng(21)
    F, M = 40, 6
    local = cluster(rng, M)
    meas = np.stack([move(random_T(rng), local) for _ in range(F)])
    meas += rng.normal(scale=1.0, size=meas.shape)
    meas[rng.random((F, M)) < 0.3] = np.nan
    w = rng.uniform(0.2, 3.0, M)
    fit = fit_rigid(local, meas, w)
    assert fit.transforms.shape == (F, 4, 4) and fit.residuals.shape == (F, M)
    assert fit.valid.any() and not fit.valid.all()  # both branches exercised
    for f in range(F):
        one = fit_rigid(local, meas[f], w)
        np.testing.assert_allclose(fit.transforms[f], one.transforms, rtol=0, atol=1e-12)
        np.testing.assert_allclose(fit.residuals[f], one.residuals, rtol=0, atol=1e-12)
        assert fit.valid[f] == one.valid


def test_bones_batch_equals_per_frame_single_fits():
    rng = np.random.default_rng(22)
    F, M = 30, 14
    bones = {"pelvis": [0, 1, 2, 3], "femur_r": [3, 4, 5, 6, 7], "tibia_r": [8, 9, 10],
             "foot_r": [10, 11, 12, 13]}  # markers 3 and 10 are shared
    local_by_bone = {b: cluster(rng, len(i)) for b, i in bones.items()}
    measured = np.full((F, M, 3), np.nan)
    truth = np.zeros((F, len(bones), 4, 4))
    for f in range(F):
        for b, (name, idx) in enumerate(bones.items()):
            truth[f, b] = random_T(rng)
            measured[f, idx] = move(truth[f, b], local_by_bone[name])
    measured += rng.normal(scale=0.8, size=measured.shape)
    measured[rng.random((F, M)) < 0.2] = np.nan
    w = rng.uniform(0.5, 2.0, M)

    out = fit_rigid_bones(local_by_bone, bones, measured, w)

    assert isinstance(out, BoneFits)
    assert out.bones == list(bones)
    assert out.transforms.shape == (F, 4, 4, 4) and out.valid.shape == (F, 4)
    assert out.residuals.shape == (F, M)
    assert out.valid.any() and not out.valid.all()
    np.testing.assert_array_equal(out.marker_bone, [0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 3, 3, 3])
    for f in range(F):
        for b, (name, idx) in enumerate(bones.items()):
            one = fit_rigid(local_by_bone[name], measured[f, idx], w[idx])
            assert out.valid[f, b] == one.valid
            np.testing.assert_allclose(out.transforms[f, b], one.transforms, rtol=0, atol=1e-10)
            assert out.n_used[f, b] == one.n_used
            np.testing.assert_allclose(out.rms[f, b], one.rms, rtol=0, atol=1e-10)
            # each marker reports the residual of its first bone
            first = [k for k, m in enumerate(idx) if out.marker_bone[m] == b]
            np.testing.assert_allclose(out.residuals[f, np.asarray(idx)[first]],
                                       one.residuals[first], rtol=0, atol=1e-10)
    # the shared marker 3 (pelvis and femur) reports the pelvis residual
    pelvis = [fit_rigid(local_by_bone["pelvis"], measured[f, bones["pelvis"]], w[bones["pelvis"]])
              for f in range(F)]
    np.testing.assert_allclose(out.residuals[:, 3], [p.residuals[3] for p in pelvis], atol=1e-10)
    # the truth is recovered, up to the noise, for the bones whose markers were all
    # written from their own pose (the shared markers 3 and 10 were last written by
    # femur_r and foot_r, so pelvis and tibia_r see one inconsistent marker)
    for b in (1, 3):
        ok = out.valid[:, b]
        assert ok.sum() > 10
        assert rotation_angle_deg(out.transforms[ok, b], truth[ok, b]).max() < 3.0


def test_bones_with_per_frame_weights_and_unused_markers():
    rng = np.random.default_rng(23)
    F = 5
    local = {"a": cluster(rng, 3), "b": cluster(rng, 4)}
    idx = {"a": [0, 1, 2], "b": [4, 5, 6, 7]}  # marker 3 is on no bone
    measured = rng.normal(scale=100, size=(F, 8, 3))
    w = rng.uniform(0.5, 2.0, (F, 8))
    out = fit_rigid_bones(local, idx, measured, w)
    assert np.isnan(out.residuals[:, 3]).all()
    assert out.marker_bone[3] == -1
    for f in range(F):
        one = fit_rigid(local["b"], measured[f, 4:], w[f, 4:])
        np.testing.assert_allclose(out.transforms[f, 1], one.transforms, atol=1e-10)


# --------------------------------------------------------------------------- noise


def test_noise_rotation_error_matches_analytic_expectation():
    rng = np.random.default_rng(31)
    sigma, F = 0.5, 1000
    local = np.array([[0, 0, 0], [100, 0, 0], [0, 100, 0], [0, 0, 100]], float)
    truth = np.stack([random_T(rng) for _ in range(F)])
    clean = np.einsum("fij,mj->fmi", truth[:, :3, :3], local) + truth[:, None, :3, 3]
    fit = fit_rigid(local, clean + rng.normal(scale=sigma, size=clean.shape))
    err = rotation_angle_deg(fit.transforms, truth)
    assert fit.valid.all()
    # small-angle theory: rotation-vector covariance sigma^2 (tr(C) I - C)^-1,
    # C = sum (p - pbar)(p - pbar)^T; the mean angle is a bit under its RMS.
    pc = local - local.mean(axis=0)
    C = pc.T @ pc
    rms_expected = np.degrees(sigma * np.sqrt(np.trace(np.linalg.inv(np.trace(C) * np.eye(3) - C))))
    mean_err = err.mean()
    assert 0 < mean_err < 1.0
    assert 0.6 * rms_expected < mean_err < 1.1 * rms_expected
    assert np.sqrt(np.mean(err ** 2)) == pytest.approx(rms_expected, rel=0.1)


# --------------------------------------------------------------------------- helpers of the module


def test_apply_transform_batches_and_matches_loop():
    rng = np.random.default_rng(41)
    T = np.stack([random_T(rng) for _ in range(6)]).reshape(2, 3, 4, 4)
    pts = rng.normal(size=(2, 3, 5, 3))
    out = apply_transform(T, pts)
    for i in range(2):
        for j in range(3):
            np.testing.assert_allclose(out[i, j], move(T[i, j], pts[i, j]), atol=1e-12)
    # one set of points for every transform
    np.testing.assert_allclose(apply_transform(T, pts[0, 0])[1, 2], move(T[1, 2], pts[0, 0]), atol=1e-12)


def test_apply_transform_inverts_the_fit():
    rng = np.random.default_rng(42)
    local = cluster(rng, 4)
    measured = move(random_T(rng), local)
    fit = fit_rigid(local, measured)
    np.testing.assert_allclose(apply_transform(fit.local_to_lab, local), measured, atol=1e-9)


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-4, 0.3, 1.0, 2.5, np.pi - 1e-7, np.pi])
def test_rotation_angle_deg_is_accurate(angle):
    rng = np.random.default_rng(43)
    Ta = random_T(rng)
    Tb = Ta @ make_T(rodrigues(rng.normal(size=3), angle), [5, 6, 7])
    got = rotation_angle_deg(Ta, Tb)
    assert got == pytest.approx(np.degrees(angle), rel=1e-7, abs=1e-12)
    assert rotation_angle_deg(Tb, Ta) == pytest.approx(got, rel=1e-7, abs=1e-12)
    # 3x3 input too
    assert rotation_angle_deg(Ta[:3, :3], Tb[:3, :3]) == pytest.approx(got, rel=1e-7, abs=1e-12)


def test_rotation_angle_deg_batched_and_nan():
    Ta = np.stack([make_T(rodrigues([0, 0, 1], np.radians(a)), [0, 0, 0]) for a in (10, 90, 170)])
    np.testing.assert_allclose(rotation_angle_deg(Ta, np.eye(4)), [10, 90, 170], atol=1e-10)
    assert np.isnan(rotation_angle_deg(np.full((4, 4), np.nan), np.eye(4)))


# --------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    "local, measured, weights, kwargs, match",
    [
        (np.zeros((4, 2)), np.zeros((4, 3)), None, {}, r"local must have shape \(\.\.\., M, 3\).*\(4, 2\)"),
        (np.zeros(3), np.zeros((4, 3)), None, {}, r"local must have shape"),
        (np.zeros((4, 3)), np.zeros((4, 4)), None, {}, r"measured must have shape.*lab"),
        (np.zeros((4, 3)), np.zeros((5, 3)), None, {}, r"local has 4 markers.*measured has 5"),
        (np.zeros((2, 4, 3)), np.zeros((3, 4, 3)), None, {}, r"do not broadcast"),
        (np.zeros((4, 3)), np.zeros((4, 3)), np.ones(3), {}, r"weights must have shape \(4,\)"),
        (np.zeros((4, 3)), np.zeros((4, 3)), [1, -1, 1, 1], {}, r"non-negative"),
        (np.zeros((4, 3)), np.zeros((4, 3)), [1, np.inf, 1, 1], {}, r"finite"),
        (np.zeros((4, 3)), np.zeros((4, 3)), None, {"min_markers": 2}, r"min_markers.*>= 3"),
        (np.zeros((4, 3)), np.zeros((4, 3)), None, {"min_markers": 3.5}, r"min_markers"),
        (np.zeros((4, 3)), np.zeros((4, 3)), None, {"min_spread_ratio": 2.0}, r"min_spread_ratio"),
        (np.zeros((0, 3)), np.zeros((0, 3)), None, {}, r"M = 0"),
    ],
)
def test_fit_rigid_rejects_bad_input(local, measured, weights, kwargs, match):
    with pytest.raises(ValueError, match=match):
        fit_rigid(local, measured, weights, **kwargs)


def _bones_ok():
    return {"a": np.eye(3) * 50, "b": np.eye(3) * 40 + 1}, {"a": [0, 1, 2], "b": [3, 4, 5]}


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda L, I, m: (L, I, m[0]), r"measured must have shape \(frames, markers, 3\)"),
        (lambda L, I, m: ({}, {}, m), r"empty"),
        (lambda L, I, m: (L, {"a": I["a"]}, m), r"missing \['b'\]"),
        (lambda L, I, m: (L, {**I, "c": [0, 1, 2]}, m), r"unexpected \['c'\]"),
        (lambda L, I, m: (L, {**I, "a": [0, 1]}, m), r"bone 'a': 3 local markers but 2"),
        (lambda L, I, m: (L, {**I, "a": [0, 1, 9]}, m), r"indices must lie in \[0, 5\]"),
        (lambda L, I, m: (L, {**I, "a": [0, 1, 1]}, m), r"repeated"),
        (lambda L, I, m: (L, {**I, "a": [0.0, 1.0, 2.0]}, m), r"integer"),
        (lambda L, I, m: ({**L, "a": np.zeros((3, 2))}, I, m), r"local_by_bone\['a'\].*\(3, 2\)"),
        (lambda L, I, m: ({**L, "a": np.full((3, 3), np.nan)}, I, m), r"non-finite"),
        (lambda L, I, m: ({**L, "a": np.eye(3)[:2]}, {**I, "a": [0, 1]}, m), r"2 markers.*at least"),
    ],
)
def test_fit_rigid_bones_rejects_bad_input(mutate, match):
    L, I = _bones_ok()
    L, I, m = mutate(L, I, np.zeros((2, 6, 3)))
    with pytest.raises(ValueError, match=match):
        fit_rigid_bones(L, I, m)


def test_fit_rigid_bones_rejects_bad_weights():
    L, I = _bones_ok()
    with pytest.raises(ValueError, match=r"weights must have shape \(6,\) or \(2, 6\)"):
        fit_rigid_bones(L, I, np.zeros((2, 6, 3)), np.ones((3, 6)))


def test_helpers_reject_bad_shapes():
    with pytest.raises(ValueError, match=r"T must have shape \(\.\.\., 4, 4\)"):
        apply_transform(np.eye(3), np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"points must have shape"):
        apply_transform(np.eye(4), np.zeros(3))
    with pytest.raises(ValueError, match=r"do not broadcast"):
        apply_transform(np.tile(np.eye(4), (2, 1, 1)), np.zeros((3, 5, 3)))
    with pytest.raises(ValueError, match=r"Tb must have shape"):
        rotation_angle_deg(np.eye(4), np.eye(2))
