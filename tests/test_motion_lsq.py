"""Tests of bonecap.motion.lsq: the joint-coupled least-squares solver."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bonecap.model import Bone, Skeleton
from bonecap.motion._qcp import place_points
from bonecap.motion.lsq import _fit_qcp, lowpass_markers, plan_segments, solve_lsq
from bonecap.motion.rigid import fit_rigid, rotation_angle_deg
from bonecap.skeleton.kinematics import pose_skeleton


def _lifted(z):
    """A frame with the world's axes, ``z`` mm up (the test skeletons' bones at rest)."""
    M = np.eye(4)
    M[2, 3] = z
    return M


def chain_skeleton():
    """pelvis -> thigh -> shank -> foot, ball joints 'hip', 'knee', 'ankle' (mm, frames = world at rest)."""
    bones = {
        "pelvis": Bone("pelvis", None, bone_to_world=_lifted(1000), joint_centres={"hip": [0, 0, -50]}),
        "thigh": Bone("thigh", "pelvis", bone_to_world=_lifted(950),
                      joint_centres={"hip": [0, 0, 0], "knee": [0, 0, -400]}),
        "shank": Bone("shank", "thigh", bone_to_world=_lifted(550),
                      joint_centres={"knee": [0, 0, 0], "ankle": [0, 0, -400]}),
        "foot": Bone("foot", "shank", bone_to_world=_lifted(150), joint_centres={"ankle": [0, 0, 0]}),
    }
    return Skeleton(bones, world="model")


# markers: 4 on the pelvis, only 2 on thigh and shank (a rigid fit needs 3), 3 on the foot
MARKER_BONES = ["pelvis"] * 4 + ["thigh"] * 2 + ["shank"] * 2 + ["foot"] * 3
MARKER_LOCAL = np.array([[100, 80, 0], [100, -80, 0], [-80, 60, 20], [-80, -60, 20],
                         [60, 10, -150], [0, 70, -390],
                         [50, 0, -120], [0, 60, -380],
                         [120, 0, -40], [-40, 30, -50], [-30, -30, -45]], float)


def truth_motion(F=60, seed=0):
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 1, F)
    root = np.tile(np.eye(4), (F, 1, 1))
    root[:, :3, :3] = Rotation.from_rotvec(np.c_[0.2 * np.sin(2 * np.pi * t), 0.1 * t, 1.5 * t]).as_matrix()
    root[:, :3, 3] = np.c_[800 * t, 20 * np.sin(4 * t), 1000 + 10 * t]
    rots = {b: np.c_[a * np.sin(2 * np.pi * t + p), 0.3 * np.cos(3 * t + p), 0.2 * t]
            for b, a, p in (("thigh", 0.6, 0.0), ("shank", 1.0, 1.0), ("foot", 0.4, 2.0))}
    skel = chain_skeleton()
    T = pose_skeleton(skel, root, rots)
    bi = [skel.names.index(b) for b in MARKER_BONES]
    Tb = T[:, bi]
    markers = np.einsum("fmij,mj->fmi", Tb[..., :3, :3], MARKER_LOCAL) + Tb[..., :3, 3]
    return skel, T, markers, rng


def test_qcp_matches_svd_fit():
    rng = np.random.default_rng(3)
    P = rng.normal(0, 50, (6, 3))
    R = Rotation.random(200, random_state=4).as_matrix()
    Q = np.einsum("fij,kj->fki", R, P) + rng.normal(0, 1000, (200, 1, 3)) + rng.normal(0, 2, (200, 6, 3))
    w = rng.uniform(0.2, 2, (200, 6))
    Rq, tq, v = _fit_qcp(P, Q.transpose(0, 2, 1), w)
    ref = fit_rigid(P, Q, w)
    assert v.all()
    assert np.abs(Rq - ref.transforms[:, :3, :3]).max() < 1e-8
    assert np.abs(tq - ref.transforms[:, :3, 3]).max() < 1e-6
    # collinear points are flagged, as in fit_rigid
    line = np.c_[np.arange(4.0), np.zeros(4), np.zeros(4)]
    assert not _fit_qcp(line, (line[None] + 1).transpose(0, 2, 1), np.ones((1, 4)))[2][0]
    # a point of weight 0 is left out whatever its value
    Qn = Q.copy()
    Qn[:, 0] = 1e6
    w0 = w.copy()
    w0[:, 0] = 0.0
    Rn = _fit_qcp(P, Qn.transpose(0, 2, 1), w0)[0]
    assert np.abs(Rn - fit_rigid(P[1:], Q[:, 1:], w[:, 1:]).transforms[:, :3, :3]).max() < 1e-8


def test_qcp_batch_of_segments_equals_one_by_one():
    """Several segments in one batched fit (padded with weight-0 points to a common K) give each
    segment's own fit: the red-black sweeps rely on it."""
    rng = np.random.default_rng(5)
    Ks, F = (4, 6, 3), 30
    Ps = [rng.normal(0, 60, (k, 3)) for k in Ks]
    Qs = [np.einsum("fij,kj->fik", Rotation.random(F, random_state=i).as_matrix(), P)
          + rng.normal(0, 500, (F, 3, 1)) + rng.normal(0, 1, (F, 3, len(P))) for i, P in enumerate(Ps)]
    ws = [rng.uniform(0.5, 2, (F, k)) for k in Ks]
    ws[2][:5, 0] = 0.0                        # two points left in 5 frames of the third: invalid there
    Kmax = max(Ks)
    Pg, Qg, Wg = np.zeros((3, Kmax, 3)), np.full((3, F, 3, Kmax), 7.0), np.zeros((3, F, Kmax))
    for i, (P, Q, w) in enumerate(zip(Ps, Qs, ws)):
        Pg[i, :len(P)], Qg[i, :, :, :len(P)], Wg[i, :, :len(P)] = P, Q, w
    R, t, v = _fit_qcp(Pg, Qg, Wg)
    assert R.shape == (3, F, 3, 3) and t.shape == (3, F, 3) and v.shape == (3, F)
    for i, (P, Q, w) in enumerate(zip(Ps, Qs, ws)):
        Ri, ti, vi = _fit_qcp(P, Q, w)
        assert (v[i] == vi).all()
        assert np.abs(R[i][vi] - Ri[vi]).max() < 1e-9 and np.abs(t[i][vi] - ti[vi]).max() < 1e-6
    assert not v[2, :5].any() and v[2, 5:].all()


def test_qcp_exact_far_from_the_lab_origin_and_on_strided_views():
    """The sweeps hand the compiled fit views into padded buffers (strided), with lab points metres
    from the origin: noise-free points give the rotation to rounding, whatever the layout."""
    rng = np.random.default_rng(8)
    F, K, Kpad = 50, 5, 9
    P = rng.normal(0, 40, (K, 3))
    R = Rotation.random(F, random_state=9).as_matrix()
    t = rng.uniform(-3000, 3000, (F, 3))
    buf = np.full((F, 3, Kpad), -1e5)                       # padding that must never be read
    buf[:, :, :K] = np.einsum("fij,kj->fik", R, P) + t[:, :, None]
    wbuf = np.ones((F, Kpad))
    Q, w = buf[:, :, :K], wbuf[:, :K]
    assert not Q.flags.c_contiguous
    Rq, tq, v = _fit_qcp(P, Q, w)
    assert v.all()
    assert np.abs(Rq - R).max() < 1e-11 and np.abs(tq - t).max() < 1e-8


def test_place_points_carries_points_and_drops_unsolved_frames():
    """The joint pseudo-markers: each point carried by its neighbour's pose into consecutive slots,
    weight times the scale; a frame where the neighbour is not solved (NaN) gets weight 0 and a
    finite target, so the fit ignores it."""
    rng = np.random.default_rng(10)
    F, K = 7, 6
    T = np.tile(np.eye(4), (F, 1, 1))
    T[:, :3, :3] = Rotation.random(F, random_state=11).as_matrix()
    T[:, :3, 3] = rng.normal(0, 500, (F, 3))
    T[2] = np.nan
    pts = rng.normal(0, 30, (2, 3))
    Q, W = np.full((F, 3, K), 5.0), np.full((F, K), 9.0)
    place_points(T, pts, np.array([10.0, 1.0]), 0.5, Q, W, 3)
    ok = np.arange(F) != 2
    expect = np.einsum("fij,kj->fik", T[ok, :3, :3], pts) + T[ok, :3, 3, None]
    assert np.allclose(Q[ok][:, :, 3:5], expect, atol=1e-9)
    assert (W[ok][:, 3:5] == [5.0, 0.5]).all()
    assert (Q[2, :, 3:5] == 0).all() and (W[2, 3:5] == 0).all()
    assert (Q[:, :, :3] == 5.0).all() and (Q[:, :, 5] == 5.0).all() and (W[:, [0, 1, 2, 5]] == 9.0).all()


def test_qcp_reaches_the_minimum_where_no_rotation_fits_well():
    """Targets that are no rigid image of the points (random: the two largest eigenvalues of the key
    matrix nearly meet, and Newton converges only linearly) still get the least-squares rotation:
    never above the SVD fit's cost (10 Newton steps left frames 4e-5 above it)."""
    rng = np.random.default_rng(14)
    F, K = 5000, 5
    P = rng.normal(0, 30, (K, 3))
    Q = rng.normal(0, 30, (F, K, 3)) + 1000.0
    w = np.ones((F, K))
    R, t, v = _fit_qcp(P, Q.transpose(0, 2, 1), w)
    ref = fit_rigid(P, Q, w).transforms

    def cost(R_, t_):
        return ((np.einsum("fij,kj->fki", R_, P) + t_[:, None] - Q) ** 2).sum(axis=(1, 2))

    c, c_ref = cost(R, t), cost(ref[:, :3, :3], ref[:, :3, 3])
    assert v.all()
    assert ((c - c_ref) / c_ref).max() < 1e-9


def test_compiled_kernels_check_shapes_and_compile_without_a_cache_where_none_can_be_written():
    """The compiled loops do not check indices themselves: disagreeing shapes or slots raise instead of
    reading or writing past the arrays. Read-only inputs are fitted (copied). A function numba cannot
    cache (here: no source file, as for a read-only install without a writable home) still compiles."""
    from bonecap.motion import _qcp

    with pytest.raises(ValueError, match="shapes"):
        _fit_qcp(np.zeros((4, 3)), np.zeros((5, 3, 3)), np.ones((5, 3)))
    with pytest.raises(ValueError, match="slots"):
        place_points(np.zeros((2, 4, 4)), np.zeros((2, 3)), np.ones(2), 1.0, np.zeros((2, 3, 3)),
                     np.zeros((2, 3)), 2)
    rng = np.random.default_rng(12)
    P = rng.normal(0, 30, (5, 3))
    Q = (P @ Rotation.random(random_state=13).as_matrix().T + 500.0).T[None].repeat(4, axis=0)
    w = np.ones((4, 5))
    for a in (P, Q, w):
        a.flags.writeable = False
    assert _fit_qcp(P, Q, w)[2].all()
    ns: dict = {}
    exec("def plus_one(x):\n    return x + 1.0\n", ns)             # no file: numba has no cache place
    f = _qcp._compiled("float64(float64)")(ns["plus_one"])
    assert f(1.0) == 2.0


def test_plan_segments_rules():
    skel = chain_skeleton()
    plan = plan_segments(skel, MARKER_BONES)
    assert plan.roots() == ["pelvis", "thigh", "shank", "foot"]
    # a shank with one marker cannot carry itself: it rides on the thigh
    mb = ["pelvis"] * 4 + ["thigh"] * 2 + ["shank"] + ["foot"] * 3
    plan = plan_segments(skel, mb)
    assert plan.segment_of["shank"] == plan.segment_of["thigh"]
    # a marker-less shank takes over the foot below it (joint at the knee, not the ankle)
    mb = ["pelvis"] * 4 + ["thigh"] * 2 + ["foot"] * 3
    plan = plan_segments(skel, mb)
    seg = plan.segments[plan.segment_of["foot"]]
    assert seg.root == "shank" and seg.joint == "knee" and "foot" in seg.members


def spine_skeleton():
    """sacrum -> l5 -> l4 -> t10 -> t9 -> c7 -> c6 (frames = world at rest, 100 mm apart), ball joints at the
    discs; a rib rides on t9 (the thorax)."""
    chain = [("sacrum", None, 1000, None), ("l5", "sacrum", 1100, "l5_s1"), ("l4", "l5", 1200, "l4_l5"),
             ("t10", "l4", 1300, "t10_l4"), ("t9", "t10", 1400, "t9_t10"), ("c7", "t9", 1500, "c7_t9"),
             ("c6", "c7", 1600, "c6_c7")]
    bones = {}
    for i, (n, p, z, j) in enumerate(chain):
        jc = {} if j is None else {j: [0.0, 0.0, -50.0]}
        if i + 1 < len(chain):
            jc[chain[i + 1][3]] = [0.0, 0.0, 50.0]
        bones[n] = Bone(n, p, bone_to_world=_lifted(z), joint_centres=jc)
    bones["rib9_r"] = Bone("rib9_r", "t9", bone_to_world=_lifted(1400), joint_centres={})
    return Skeleton(bones, world="model")


def test_a_vertebra_with_one_marker_joins_the_trunk_above_it():
    """Plug-in Gait's T10 is a thorax marker: its vertebra, too weakly held by one marker to be a segment
    of its own, takes over the thorax segment above it (as a marker-less vertebra does), and the
    marker-less lumbar vertebrae below carry it down to L5/S1 -- the trunk turns on the pelvis there, as
    OpenSim's full-body models have it (one lumbar joint). Before, T10 and the lumbar spine rode on the
    pelvis: a trunk turning 10 deg on the pelvis left them 10 deg off. C7's vertebra (one marker) rides on
    the thorax and does not take the head's segment above it over. A marker-less or one-marker bone that
    is not a vertebra keeps the old rule (test_plan_segments_rules)."""
    skel = spine_skeleton()
    mb = ["sacrum"] * 4 + ["t10"] + ["t9"] * 3 + ["c7"] + ["c6"] * 3
    local = np.array([[80, 60, 0], [80, -60, 0], [-60, 50, 20], [-60, -50, 20], [-70, 0, 0],
                      [-70, 0, 20], [60, 50, 0], [60, -50, 10], [-60, 0, 0],
                      [80, 70, 40], [80, -70, 40], [-90, 0, 60]], float)
    plan = plan_segments(skel, mb)
    assert plan.roots() == ["sacrum", "l5", "c6"]
    seg = plan.segments[plan.segment_of["t10"]]
    assert seg.root == "l5" and seg.joint == "l5_s1"
    assert set(seg.members) == {"l5", "l4", "t10", "t9", "c7", "rib9_r"}
    assert plan.segments[plan.segment_of["c6"]].joint == "c6_c7"
    # without the rib cage on t9 (not the thorax) T10 keeps riding on the pelvis
    bare = Skeleton({n: b for n, b in skel.bones.items() if n != "rib9_r"}, world="model")
    assert plan_segments(bare, mb).segment_of["t10"] == 0
    # the trunk turned on the pelvis about L5/S1 (rigid above it), the pelvis moving too
    F = 40
    t = np.linspace(0, 1, F)
    root = np.tile(np.eye(4), (F, 1, 1))
    root[:, :3, :3] = Rotation.from_rotvec(np.c_[0.05 * t, 0.1 * np.sin(2 * np.pi * t), 0.3 * t]).as_matrix()
    root[:, :3, 3] = np.c_[500 * t, 10 * t, np.zeros(F)]
    trunk = np.c_[0.1 * np.sin(2 * np.pi * t), 0.05 * np.cos(2 * np.pi * t), 0.17 * np.sin(4 * np.pi * t)]
    T = pose_skeleton(skel, root, {"l5": trunk})
    Tb = T[:, [skel.names.index(b) for b in mb]]
    markers = np.einsum("fmij,mj->fmi", Tb[..., :3, :3], local) + Tb[..., :3, 3]
    mo = solve_lsq(skel, mb, local, markers, rate_hz=100.0)
    assert np.nanmax(rotation_angle_deg(mo.transforms, T)) < 1e-5
    old = np.degrees(Rotation.from_rotvec(trunk).magnitude()).max()
    assert old > 9.0                                  # what riding on the pelvis would have missed


def _girdle_chain(thorax, sc, ac, gh, inferior_angle, elbow=None, world="model"):
    """thorax -> clavicle_r (sternoclavicular; the thorax lists it as ``sternoclavicular_r``, as the
    embedded skeleton's sternum does) -> scapula_r (acromioclavicular) -> humerus_r (shoulder, and the
    elbow where given), every frame the world's at rest, each origin at its proximal joint (mm)."""
    def T(p):
        M = np.eye(4)
        M[:3, 3] = p
        return M
    thorax, sc, ac, gh = (np.asarray(p, float) for p in (thorax, sc, ac, gh))
    arm = {"shoulder": [0, 0, 0]} | ({} if elbow is None else {"elbow": np.asarray(elbow, float) - gh})
    bones = {
        "thorax": Bone("thorax", None, bone_to_world=T(thorax), joint_centres={"sternoclavicular_r": sc - thorax}),
        "clavicle_r": Bone("clavicle_r", "thorax", bone_to_world=T(sc),
                           joint_centres={"sternoclavicular": [0, 0, 0], "acromioclavicular": ac - sc}),
        "scapula_r": Bone("scapula_r", "clavicle_r", bone_to_world=T(ac),
                          joint_centres={"acromioclavicular": [0, 0, 0], "shoulder": gh - ac},
                          landmarks={"inferior_angle": inferior_angle}),
        "humerus_r": Bone("humerus_r", "scapula_r", bone_to_world=T(gh), joint_centres=arm),
    }
    return Skeleton(bones, world=world)


def girdle_skeleton():
    """The girdle chain with frames = world at rest (x anterior, y right, z up), mm."""
    return _girdle_chain([0, 0, 1300], [30.0, 20.0, 1400.0], [-10.0, 170.0, 1420.0], [-20.0, 180.0, 1380.0],
                         [-60.0, -70.0, -150.0])


def test_a_shoulder_girdle_with_its_acromion_marker_turns_on_the_thorax():
    """The acromion marker rides on the girdle (clavicle and scapula), which rises and retracts on the
    thorax as the arm is raised (scapulohumeral rhythm): the girdle gets its own pose, turning at the
    sternoclavicular joint, held about the line from that joint to its one marker by a weak prior. On
    the thorax (before) the shoulder stood still while the acromion moved, and the arm hung from it."""
    skel = girdle_skeleton()
    mb = ["thorax"] * 4 + ["scapula_r"] + ["humerus_r"] * 2
    local = np.array([[100, -60, 50], [100, 60, 50], [-90, 0, 120], [-90, 40, -150],   # thorax
                      [0, 10, 15],                                                    # acromion
                      [25, 45, -150], [0, 35, -290]], float)                          # upper arm, elbow
    plan = plan_segments(skel, mb)
    assert plan.roots() == ["thorax", "clavicle_r", "humerus_r"]
    seg = plan.segments[plan.segment_of["scapula_r"]]
    assert seg.root == "clavicle_r" and seg.joint == "sternoclavicular" and seg.prior_in_self is not None
    np.testing.assert_allclose(seg.joint_in_parent, skel.bones["thorax"].joint_centres["sternoclavicular_r"])
    # the girdle lifts (about anterior) and retracts (about up) by up to 15 and 12 deg while the arm
    # abducts 70 deg on the scapula; the thorax walks and turns
    F = 50
    t = np.linspace(0, 1, F)
    root = np.tile(np.eye(4), (F, 1, 1))
    root[:, :3, :3] = Rotation.from_rotvec(np.c_[0.05 * t, 0.1 * t, 0.4 * t]).as_matrix()
    root[:, :3, 3] = np.c_[600 * t, 10 * t, 1300 + 5 * t]
    girdle = Rotation.from_rotvec(np.c_[np.radians(15) * t, 0 * t, -np.radians(12) * t]).as_matrix()
    arm = Rotation.from_rotvec(np.c_[np.radians(70) * t, 0.2 * t, 0 * t]).as_matrix()
    T = np.tile(np.eye(4), (F, 4, 1, 1))
    T[:, 0] = root
    for i, (name, R) in enumerate((("clavicle_r", girdle), ("scapula_r", None), ("humerus_r", arm)), start=1):
        b = skel.bones[name]
        rest = np.linalg.solve(skel.bones[b.parent].bone_to_world, b.bone_to_world)
        J = np.tile(np.eye(4), (F, 1, 1))
        if R is not None:
            c = rest[:3, 3]                     # the joint centre is each child's origin
            J[:, :3, :3] = R
            J[:, :3, 3] = c - R @ c
        T[:, i] = T[:, i - 1] @ J @ rest
    Tb = T[:, [skel.names.index(b) for b in mb]]
    markers = np.einsum("fmij,mj->fmi", Tb[..., :3, :3], local) + Tb[..., :3, 3]
    mo = solve_lsq(skel, mb, local, markers, rate_hz=100.0)
    assert mo.valid.all()
    err = rotation_angle_deg(mo.transforms, T)
    # noise-free, the girdle's 19 deg: what is left is mostly its turn about its own long axis (the line
    # from the joint to the marker), which the prior holds and the arm's shoulder centre sets only weakly
    assert err[:, 1].max() < 8.0 and err[:, 3].max() < 3.0
    assert mo.residuals[:, 4].max() < 6.0                          # the acromion marker
    # the girdle carried rigidly by the thorax (the former plan) leaves the acromion and the arm behind
    rigid = solve_lsq(skel, mb, local, markers, rate_hz=100.0,
                      segments={"thorax": "thorax", "clavicle_r": "thorax", "scapula_r": "thorax",
                                "humerus_r": "humerus_r"})
    assert rigid.residuals[:, 4].max() > 20.0
    r_err = rotation_angle_deg(rigid.transforms, T)
    assert r_err[:, 1].max() > 12.0 and r_err[:, 3].max() > 6.0


def isb_girdle_skeleton():
    """The girdle chain with the arm hanging straight down and an elbow; frames = world at rest, which is
    ISB's (x anterior, y up, z right), mm."""
    gh = np.array([-20.0, 1380.0, 185.0])
    return _girdle_chain([0, 1300, 0], [20.0, 1400.0, 30.0], [-10.0, 1420.0, 170.0], gh, [-60.0, -150.0, -70.0],
                         elbow=gh - [0.0, 290.0, 0.0], world="isb")


def _turn_about(R, c):
    J = np.tile(np.eye(4), (len(R), 1, 1))
    J[:, :3, :3] = R
    J[:, :3, 3] = c - R @ c
    return J


def test_the_rhythm_turns_the_scapula_by_a_third_of_the_arms_elevation_less_the_clavicles():
    """Scapulohumeral rhythm (lsq.rhythm_turns): the scapula turns upward on the clavicle about its
    plane's normal through the acromioclavicular joint by a third of the arm's elevation on the thorax
    (Inman's 2:1) less what the clavicle's own elevation gives, held within RHYTHM_LIMITS_DEG."""
    from bonecap.motion.lsq import RHYTHM_LIMITS_DEG, plan_rhythms, rhythm_turns

    skel = isb_girdle_skeleton()
    mb = ["thorax"] * 4 + ["scapula_r"] + ["humerus_r"] * 2
    plan = plan_segments(skel, mb)
    (rh,) = plan_rhythms(skel, plan)
    assert rh.scapula == "scapula_r" and abs(rh.elevation_ref) < 1e-9
    # without an elbow the arm's elevation is unknown: no rhythm
    no_elbow = isb_girdle_skeleton()
    no_elbow.bones["humerus_r"].joint_centres.pop("elbow")
    assert plan_rhythms(no_elbow, plan_segments(no_elbow, mb)) == []
    I = np.eye(4)[None]
    gh_rest = skel.bones["humerus_r"].bone_to_world[:3, 3]
    ac = skel.bones["scapula_r"].bone_to_world[:3, 3]
    sc = skel.bones["clavicle_r"].bone_to_world[:3, 3]
    u = (ac - sc) / np.linalg.norm(ac - sc)

    def rise(clav):
        # the clavicle's elevation above the transverse plane, from its reference (deg)
        v = Rotation.from_rotvec([-np.radians(clav), 0, 0]).apply(u)
        return np.degrees(np.arcsin(v[1]) - np.arcsin(u[1]))

    assert 9.5 < rise(10.0) < 10.0                   # the clavicle also points back a little
    for E, clav, expect in ((90.0, 0.0, 30.0), (90.0, 10.0, 30.0 - rise(10.0)), (150.0, 12.0, 50.0 - rise(12.0)),
                            (30.0, 25.0, 10.0 - rise(25.0)), (180.0, -30.0, RHYTHM_LIMITS_DEG[1])):
        # abduction: a turn about -anterior lifts the right arm; the clavicle lifts about -anterior at SC
        arm = I @ _turn_about(Rotation.from_rotvec([-np.radians(E), 0, 0]).as_matrix()[None],
                              gh_rest) @ skel.bones["humerus_r"].bone_to_world
        girdle = _turn_about(Rotation.from_rotvec([-np.radians(clav), 0, 0]).as_matrix()[None],
                             sc) @ skel.bones["clavicle_r"].bone_to_world
        turn, alpha = rhythm_turns(rh, skel.bones["thorax"].bone_to_world[None], girdle, arm)
        np.testing.assert_allclose(alpha, [expect], atol=1e-6)
        # about the scapula's x (its plane's normal), through the acromioclavicular joint, lifting the
        # shoulder centre
        np.testing.assert_allclose(np.abs(Rotation.from_matrix(turn[0, :3, :3]).as_rotvec()),
                                   [np.radians(abs(expect)), 0, 0], atol=1e-9)
        np.testing.assert_allclose(turn[0, :3, :3] @ (ac - sc) + turn[0, :3, 3], ac - sc, atol=1e-9)
        lift = (turn[0, :3, :3] @ (gh_rest - sc) + turn[0, :3, 3] - (gh_rest - sc))[1]
        assert np.sign(lift) == np.sign(expect)
    # an unsolved neighbour: no turn
    turn, alpha = rhythm_turns(rh, np.full((1, 4, 4), np.nan), I, I)
    assert alpha[0] == 0.0 and np.allclose(turn[0], np.eye(4))


def test_the_solver_follows_a_scapula_that_turns_with_the_arm():
    """A girdle whose scapula turns on the clavicle as the rhythm says, noise-free, is recovered with
    the rhythm (its acromion marker and the shoulder centre go with the scapula); carried rigidly on
    the clavicle (rhythm=False) the scapula misses the turn and drags the arm. A static frame, solved
    to convergence by Gauss-Newton steps, gives the same."""
    from bonecap.motion.lsq import RHYTHM_SCAPULOTHORACIC

    skel = isb_girdle_skeleton()
    mb = ["thorax"] * 4 + ["scapula_r"] + ["humerus_r"] * 3
    local = np.array([[100, 50, -60], [100, 50, 60], [-90, 120, 0], [-90, -150, 40],   # thorax
                      [10, 15, 20],                                                   # acromion
                      [25, -150, 45], [0, -290, 35], [-10, -200, -30]], float)        # upper arm, elbow
    F = 40
    t = np.linspace(0, 1, F)
    E = 150.0 * t                                     # abduction, the arm hanging at rest
    clav = 0.12 * E
    B = skel.bones
    # the clavicle swings up about the horizontal normal to the line from its joint to the acromion
    # marker, so that it turns none about that line (which the girdle's prior holds: one marker
    # cannot see it)
    line = B["scapula_r"].bone_to_world[:3, :3] @ local[4] + B["scapula_r"].bone_to_world[:3, 3] \
        - B["clavicle_r"].bone_to_world[:3, 3]
    lift = np.cross(line, [0.0, 1.0, 0.0])
    lift /= np.linalg.norm(lift)
    u = B["clavicle_r"].joint_centres["acromioclavicular"]
    u = u / np.linalg.norm(u)
    v = Rotation.from_rotvec(np.radians(clav)[:, None] * lift).apply(u)
    assert (v[:, 1] >= u[1] - 1e-12).all()
    alpha = RHYTHM_SCAPULOTHORACIC * E - np.degrees(np.arcsin(v[:, 1]) - np.arcsin(u[1]))
    root = np.tile(np.eye(4), (F, 1, 1))
    root[:, :3, :3] = Rotation.from_rotvec(np.c_[0.05 * t, 0.3 * t, 0.04 * t]).as_matrix()
    root[:, :3, 3] = np.c_[600 * t, 1300 + 5 * t, 10 * t]
    rel = {n: np.linalg.solve(B[B[n].parent].bone_to_world, B[n].bone_to_world) for n in skel.names[1:]}
    swing = Rotation.from_rotvec(np.radians(clav)[:, None] * lift).as_matrix()
    up = Rotation.from_rotvec(np.c_[-np.radians(alpha), 0 * t, 0 * t]).as_matrix()
    T = np.tile(np.eye(4), (F, 4, 1, 1))
    T[:, 0] = root
    T[:, 1] = root @ _turn_about(swing, rel["clavicle_r"][:3, 3]) @ rel["clavicle_r"]
    T[:, 2] = T[:, 1] @ _turn_about(up, rel["scapula_r"][:3, 3]) @ rel["scapula_r"]
    # the humerus: elevated E on the thorax (about its anterior axis), its centre where the scapula puts it
    R_arm = root[:, :3, :3] @ Rotation.from_rotvec(np.c_[-np.radians(E), 0 * t, 0 * t]).as_matrix()
    T[:, 3, :3, :3] = R_arm
    T[:, 3, :3, 3] = T[:, 2, :3, :3] @ B["scapula_r"].joint_centres["shoulder"] + T[:, 2, :3, 3]
    Tb = T[:, [skel.names.index(b) for b in mb]]
    markers = np.einsum("fmij,mj->fmi", Tb[..., :3, :3], local) + Tb[..., :3, 3]
    with_rhythm = solve_lsq(skel, mb, local, markers, n_sweeps=100)
    rigid = solve_lsq(skel, mb, local, markers, n_sweeps=100, rhythm=False)
    err, r_err = rotation_angle_deg(with_rhythm.transforms, T), rotation_angle_deg(rigid.transforms, T)
    assert err[:, 2].max() < 0.3 and err[:, 3].max() < 0.1, (err[:, 2].max(), err[:, 3].max())
    assert np.nanmax(with_rhythm.residuals) < 0.3
    assert r_err[:, 2].max() > 15.0 and np.nanmax(rigid.residuals) > 5.0
    # a trial's six sweeps get most of the way (linear convergence along the girdle's weak turns)
    six = rotation_angle_deg(solve_lsq(skel, mb, local, markers).transforms, T)
    assert six[:, 2].max() < 5.0 and np.median(six[:, 2]) < 2.0
    # one frame to convergence (the static's path: sweeps, then Gauss-Newton rounds)
    k = F - 5
    static = solve_lsq(skel, mb, local, markers[k:k + 1], n_sweeps=2000, tol_mm=1e-4, newton=True)
    assert rotation_angle_deg(static.transforms[0, 2], T[k, 2]) < 0.05
    assert np.nanmax(static.residuals) < 0.05


def test_a_static_scapula_is_re_turned_to_the_rhythm_of_its_final_arm():
    """build_subject.rhythm_consistent: a static whose scapula sits at another turn than its arm and
    clavicle give (a static of a few sweeps, or changed after the solve) gets the solver's turn before the
    markers are bound; nothing else moves."""
    from bonecap.build_subject import rhythm_consistent

    skel = isb_girdle_skeleton()
    mb = ["thorax"] * 4 + ["scapula_r"] + ["humerus_r"] * 2
    B = skel.bones
    poses = np.array([B[n].bone_to_world for n in skel.names])
    gh = B["humerus_r"].bone_to_world[:3, 3]
    i = skel.names.index("humerus_r")
    poses[i] = _turn_about(Rotation.from_rotvec([-np.pi / 2, 0, 0]).as_matrix()[None], gh)[0] @ poses[i]
    out = rhythm_consistent(skel, mb, poses)
    s, c = skel.names.index("scapula_r"), skel.names.index("clavicle_r")
    rel = np.linalg.solve(out[c], out[s])[:3, :3] @ np.linalg.solve(B["clavicle_r"].bone_to_world,
                                                                   B["scapula_r"].bone_to_world)[:3, :3].T
    assert abs(np.degrees(Rotation.from_matrix(rel).magnitude()) - 30.0) < 1e-6   # a third of 90
    others = [k for k in range(len(skel.names)) if k != s]
    np.testing.assert_allclose(out[others], poses[others])
    # the acromioclavicular joint stays where it was
    ac = B["clavicle_r"].joint_centres["acromioclavicular"]
    np.testing.assert_allclose(out[c, :3, :3] @ ac + out[c, :3, 3], out[s, :3, 3], atol=1e-9)


def _ankle_skeleton():
    """shank (root) -> foot at the 'ankle', whose flexion axis is the shank's y (mm, frames = world at rest)."""
    bones = {
        "shank": Bone("shank", None, bone_to_world=_lifted(500), joint_centres={"ankle": [0, 0, -400]},
                      joint_axes={"ankle": [0, 1, 0]}),
        "foot": Bone("foot", "shank", bone_to_world=_lifted(100), joint_centres={"ankle": [0, 0, 0]}),
    }
    return Skeleton(bones, world="model")


def test_the_ankle_holds_the_feet_turns_its_heel_and_toe_cannot_see():
    """Heel and toe markers and the ankle centre lie near one line, so a heel marker a few centimetres
    off its place rolls the foot about that line (a real walk's left foot turned by up to 156 deg in
    15 frames). Two weak points on the ankle's axis hold the foot's turns other than its flexion at
    the reference relative pose; the flexion, which moves neither, stays the markers' alone."""
    from bonecap.motion import lsq

    skel = _ankle_skeleton()
    mb = ["shank"] * 4 + ["foot"] * 2
    local = np.array([[60, 0, -100], [0, 60, -200], [-50, -30, -300], [40, 40, 0],
                      [-50, 0, -50], [150, 0, -50]], float)          # heel, toe
    plan = plan_segments(skel, mb)
    seg = plan.segments[plan.segment_of["foot"]]
    assert seg.hold_in_self is not None and seg.axis_in_self is None and len(seg.links()) == 3
    assert seg.link_weights(10.0) == pytest.approx([10.0, 10.0 * lsq.AXIS_HOLD, 10.0 * lsq.AXIS_HOLD])
    np.testing.assert_allclose(np.abs(seg.hold_in_self[:, 1]), lsq.HINGE_LEVER_MM)   # on the axis
    np.testing.assert_allclose(seg.hold_in_parent - seg.hold_in_self, [[0, 0, -400]] * 2, atol=1e-9)

    F = 40
    t = np.linspace(0, 1, F)
    root = np.tile(np.eye(4), (F, 1, 1))
    root[:, :3, :3] = Rotation.from_rotvec(np.c_[0.1 * t, 0.3 * t, 0.2 * t]).as_matrix()
    root[:, :3, 3] = np.c_[500 * t, 0 * t, 500 + 0 * t]

    def markers_for(foot_rot):
        T = pose_skeleton(skel, root, {"foot": foot_rot})
        Tb = T[:, [skel.names.index(b) for b in mb]]
        return T, np.einsum("fmij,mj->fmi", Tb[..., :3, :3], local) + Tb[..., :3, 3]

    # flexion alone, up to 35 deg: reproduced (the hold's points do not move)
    T, markers = markers_for(np.c_[0 * t, np.radians(35) * t, 0 * t])
    mo = solve_lsq(skel, mb, local, markers, rate_hz=100.0)
    assert rotation_angle_deg(mo.transforms, T)[:, 1].max() < 0.05

    # the heel marker swung 90 deg about the line from the ankle to the toe and pulled to within 12 mm
    # of that line (a marker pushed ~65 mm off its place): the foot flexed 20 deg
    T, markers = markers_for(np.c_[0 * t, np.radians(20) * t, 0 * t])
    foot = T[:, 1]
    toe_f, heel_f = local[5], local[4]
    u = toe_f / np.linalg.norm(toe_f)
    off = heel_f - (heel_f @ u) * u
    moved = (heel_f @ u) * u + 12.0 * np.cross(u, off / np.linalg.norm(off))
    markers[:, 4] = np.einsum("fij,j->fi", foot[:, :3, :3], moved) + foot[:, :3, 3]

    def foot_error(hold):
        mo = solve_lsq(skel, mb, local, markers, rate_hz=100.0, hold_axes=hold)
        return rotation_angle_deg(mo.transforms, T)[:, 1]

    held, free = foot_error(True), foot_error(False)
    assert free.max() > 45.0                       # without the hold the foot rolls to the marker
    assert held.max() < 20.0 and held.max() < 0.3 * free.max()
    # (a static binds its markers without it: the foot's roll is then set from the shank by rule)
    assert plan_segments(skel, mb, hold_axes=False).segments[1].hold_in_self is None
    from bonecap.build_subject import pose_to_static

    static = pose_to_static(skel, mb, local, markers[5], converge=False)
    free5 = solve_lsq(skel, mb, local, markers[5:6], max_gap_frames=0, hold_axes=False).transforms[0]
    np.testing.assert_allclose(static, free5, atol=1e-9)


def test_coupled_solver_exact_on_noise_free_ball_joints():
    skel, T, markers, _ = truth_motion()
    mo = solve_lsq(skel, MARKER_BONES, MARKER_LOCAL, markers, rate_hz=100.0)
    assert mo.valid.all()
    assert np.nanmax(rotation_angle_deg(mo.transforms, T)) < 1e-6
    assert np.abs(mo.transforms - T).max() < 1e-5
    assert np.nanmax(mo.residuals) < 1e-6
    assert mo.times[1] == pytest.approx(0.01)


def test_coupling_beats_uncoupled_with_noise():
    skel, T, markers, rng = truth_motion(F=200, seed=1)
    noisy = markers + rng.normal(0, 1.5, markers.shape)
    coupled = solve_lsq(skel, MARKER_BONES, MARKER_LOCAL, noisy)
    loose = solve_lsq(skel, MARKER_BONES, MARKER_LOCAL, noisy, joint_weight=0.0)
    # two markers cannot place a thigh without its joints
    i = skel.names.index("thigh")
    assert coupled.valid[:, i].all() and not loose.valid[:, i].any()
    # the foot (3 markers) is solved both ways; the joint makes it better
    j = skel.names.index("foot")
    e_c = np.median(rotation_angle_deg(coupled.transforms[:, j], T[:, j]))
    e_l = np.median(rotation_angle_deg(loose.transforms[:, j], T[:, j]))
    assert e_c < 0.9 * e_l


def test_gaps_interpolated_then_invalid():
    skel, T, markers, _ = truth_motion(F=80)
    gapped = markers.copy()
    ft = [k for k, b in enumerate(MARKER_BONES) if b == "foot"]
    gapped[20:26, ft] = np.nan  # 6 frames: interpolated
    gapped[50:70, ft] = np.nan  # 20 frames: longer than max_gap_frames
    mo = solve_lsq(skel, MARKER_BONES, MARKER_LOCAL, gapped, max_gap_frames=10)
    j = skel.names.index("foot")
    assert mo.valid[20:26, j].all()
    assert rotation_angle_deg(mo.transforms[20:26, j], T[20:26, j]).max() < 3.0
    assert not mo.valid[50:70, j].any() and np.isnan(mo.transforms[50:70, j]).all()
    assert mo.valid[:20, j].all() and mo.valid[70:, j].all()
    assert np.isnan(mo.residuals[55, ft]).all()


def test_sweeps_until_converged():
    # markers misplaced on the two-marker thigh and shank: the sweeps then settle slowly
    skel, _, markers, rng = truth_motion(F=5, seed=1)
    local = MARKER_LOCAL.copy()
    local[4:8] += rng.normal(0, 6, (4, 3))
    fixed = solve_lsq(skel, MARKER_BONES, local, markers, n_sweeps=300).transforms
    six = solve_lsq(skel, MARKER_BONES, local, markers).transforms
    tol = solve_lsq(skel, MARKER_BONES, local, markers, n_sweeps=3000, tol_mm=1e-4).transforms
    # six sweeps had not settled; the tolerance ran on to where 300 sweeps are
    assert np.abs(six - fixed).max() > 0.1
    assert np.abs(tol - fixed).max() < 1e-2
    # a loose tolerance stops after the first red-black sweep (the top-down one is always run)
    assert np.array_equal(solve_lsq(skel, MARKER_BONES, local, markers, n_sweeps=50, tol_mm=1e3).transforms,
                          solve_lsq(skel, MARKER_BONES, local, markers, n_sweeps=2).transforms)
    for bad in (0.0, -1.0, np.nan):
        with pytest.raises(ValueError, match="tol_mm"):
            solve_lsq(skel, MARKER_BONES, local, markers, tol_mm=bad)


def test_newton_steps_reach_the_minimum_the_sweeps_creep_to():
    """solve_lsq(newton=True): a few sweeps, then Gauss-Newton on all segments at once -- the same poses
    as thousands of sweeps, in far fewer fits; each segment's objective has no downhill direction left."""
    import bonecap.motion.lsq as lsq

    skel, _, markers, rng = truth_motion(F=4, seed=1)
    local = MARKER_LOCAL.copy()
    local[4:8] += rng.normal(0, 6, (4, 3))
    count = {"fits": 0}
    fit = lsq._fit_qcp

    def counted(*a, **k):
        count["fits"] += 1
        return fit(*a, **k)

    try:
        lsq._fit_qcp = counted
        swept = solve_lsq(skel, MARKER_BONES, local, markers, n_sweeps=20000, tol_mm=1e-7).transforms
        n_swept, count["fits"] = count["fits"], 0
        stepped = solve_lsq(skel, MARKER_BONES, local, markers, n_sweeps=20000, tol_mm=1e-7, newton=True)
        n_stepped = count["fits"]
    finally:
        lsq._fit_qcp = fit
    assert np.abs(stepped.transforms - swept).max() < 1e-3
    assert n_stepped < n_swept / 5
    # without tol_mm the option does nothing (six sweeps), nor on more frames than a static's
    assert np.array_equal(solve_lsq(skel, MARKER_BONES, local, markers, newton=True).transforms,
                          solve_lsq(skel, MARKER_BONES, local, markers).transforms)
    many = np.concatenate([markers] * 17)                   # 68 frames
    assert np.array_equal(solve_lsq(skel, MARKER_BONES, local, many, n_sweeps=200, tol_mm=1e-2, newton=True).transforms,
                          solve_lsq(skel, MARKER_BONES, local, many, n_sweeps=200, tol_mm=1e-2).transforms)

    # no small turn of a bone about its own origin lowers the objective of the solved poses
    def objective(T):
        Tm = T[:, [skel.names.index(b) for b in MARKER_BONES]]
        pred = np.einsum("fmij,mj->fmi", Tm[..., :3, :3], local) + Tm[..., :3, 3]
        out = ((pred - markers) ** 2).sum(axis=(1, 2))
        for child, parent, joint in (("thigh", "pelvis", "hip"), ("shank", "thigh", "knee"), ("foot", "shank", "ankle")):
            c, p = skel.names.index(child), skel.names.index(parent)
            a = T[:, c, :3, :3] @ skel.bones[child].joint_centres[joint] + T[:, c, :3, 3]
            b = T[:, p, :3, :3] @ skel.bones[parent].joint_centres[joint] + T[:, p, :3, 3]
            out = out + lsq.DEFAULT_JOINT_WEIGHT * ((a - b) ** 2).sum(-1)
        return out

    T = stepped.transforms
    base = objective(T)
    for b in range(len(skel.names)):
        for axis in np.eye(3):
            for sign in (-1, 1):
                Tp = T.copy()
                Tp[:, b, :3, :3] = Rotation.from_rotvec(sign * 1e-4 * axis).as_matrix() @ T[:, b, :3, :3]
                assert (objective(Tp) >= base - 1e-6).all()


def test_input_checks():
    skel, _, markers, _ = truth_motion(F=5)
    with pytest.raises(ValueError, match="marker_local"):
        solve_lsq(skel, MARKER_BONES, MARKER_LOCAL[:3], markers)
    with pytest.raises(ValueError, match="measured"):
        solve_lsq(skel, MARKER_BONES, MARKER_LOCAL, markers[0])
    with pytest.raises(ValueError, match="joint_weight"):
        solve_lsq(skel, MARKER_BONES, MARKER_LOCAL, markers, joint_weight=-1)
    with pytest.raises(ValueError, match="not in the skeleton"):
        solve_lsq(skel, MARKER_BONES[:-1] + ["wing"], MARKER_LOCAL, markers)


def test_lowpass_zero_lag_and_gap_aware():
    rate = 100.0
    t = np.arange(400) / rate
    clean = 100 * np.sin(2 * np.pi * 1.0 * t)
    x = np.zeros((400, 2, 3))
    x[:, :, 0] = (clean + 5 * np.sin(2 * np.pi * 30 * t))[:, None]
    x[150:170, 1] = np.nan
    y = lowpass_markers(x, rate, cutoff_hz=6.0)
    assert np.isnan(y[150:170, 1]).all() and np.isfinite(y[:150, 1]).all()
    core = slice(40, 360)
    assert np.abs(y[core, 0, 0] - clean[core]).max() < 1.0  # 30 Hz gone, no phase lag
    assert np.abs(y[40:110, 1, 0] - clean[40:110]).max() < 1.0
    with pytest.raises(ValueError, match="Nyquist"):
        lowpass_markers(x, rate, cutoff_hz=60.0)


# --------------------------------------------------------------------------- phantom


@pytest.fixture(scope="module")
def phantom(tmp_path_factory):
    from bonecap.phantom import make_phantom

    out = tmp_path_factory.mktemp("ph")
    make_phantom(out, seed=2, preset="tiny")
    return out


def skeleton_from_truth(truth):
    import json

    doc = json.load(open(truth / "skeleton.json"))["bones"]
    bones = {}
    for n, b in doc.items():
        T = np.array(b["bone_to_lps"])
        Ti = np.linalg.inv(T)
        loc = {k: Ti[:3, :3] @ np.array(v) + Ti[:3, 3] for k, v in b["joint_centres_lps"].items()}
        lm = {k: Ti[:3, :3] @ np.array(v) + Ti[:3, 3] for k, v in b.get("landmarks_lps", {}).items()}
        bones[n] = Bone(n, b["parent"], bone_to_world=T, joint_centres=loc, landmarks=lm)
    return Skeleton(bones, world="lps")


def test_phantom_trials_against_truth(phantom):
    from bonecap.io.c3d import read_c3d

    skel = skeleton_from_truth(phantom / "truth")
    for trial, limit in (("arm_raise", 1.5), ("touch", 2.0)):
        d = np.load(phantom / "truth" / f"{trial}_poses.npz")
        tr = read_c3d(phantom / "trials" / f"{trial}.c3d")
        meas = tr.points[:, [tr.labels.index(m) for m in d["markers"]]]
        mb = list(d["marker_bones"])
        mo = solve_lsq(skel, mb, d["marker_local"], meas, marker_labels=list(d["markers"]))
        # the girdles carried by the thorax, as before they had a pose of their own
        plan = plan_segments(skel, mb)
        rigid = {n: plan.segments[plan.segment_of[n]].root for n in skel.names}
        rigid = {n: rigid["sternum"] if r.startswith("clavicle") else r for n, r in rigid.items()}
        old = solve_lsq(skel, mb, d["marker_local"], meas, marker_labels=list(d["markers"]), segments=rigid)
        names = list(d["bones"])
        for bone in ("humerus_r", "humerus_l", "femur_r", "tibia_r", "ulna_r"):
            i = names.index(bone)
            deg = rotation_angle_deg(mo.transforms[:, i], d["transforms"][:, i])
            assert np.nanmedian(deg) < limit, (trial, bone, np.nanmedian(deg))
            mm = np.linalg.norm(mo.transforms[:, i, :3, 3] - d["transforms"][:, i, :3, 3], axis=1)
            if bone.startswith("humerus") and trial == "arm_raise":
                # the phantom's scapula also turns upward on the clavicle (GIRDLE_RHYTHM, ~25 deg at the
                # raise's 150 deg), which the solver follows by its own rhythm: the shoulder centre
                # ~2 mm off at seed 2, 3-4 mm on a scapula rigid on the clavicle, 16 mm with the girdle on
                # the thorax
                old_mm = np.linalg.norm(old.transforms[:, i, :3, 3] - d["transforms"][:, i, :3, 3], axis=1)
                assert np.nanmedian(mm) < 7.0 and np.nanmedian(old_mm) > 2 * np.nanmedian(mm), \
                    (bone, np.nanmedian(mm), np.nanmedian(old_mm))
            else:
                assert np.nanmedian(mm) < 3.0, (trial, bone, np.nanmedian(mm))
        # the scapulae: turned with the arm (the solver's rhythm) against rigid on the clavicle
        rigid_scapula = solve_lsq(skel, mb, d["marker_local"], meas, marker_labels=list(d["markers"]), rhythm=False)
        for bone in ("scapula_r", "scapula_l"):
            i = names.index(bone)
            deg = np.nanmedian(rotation_angle_deg(mo.transforms[:, i], d["transforms"][:, i]))
            rigid_deg = np.nanmedian(rotation_angle_deg(rigid_scapula.transforms[:, i], d["transforms"][:, i]))
            if trial == "arm_raise":        # seed 2: 2.9 / 3.2 deg against 7.2 / 7.6
                assert deg < 4.5 and deg < 0.6 * rigid_deg, (bone, deg, rigid_deg)
            else:                           # touch: 1.5-1.6 against 2.8
                assert deg < 2.5 and deg < rigid_deg, (bone, deg, rigid_deg)


def arm_skeleton(elbow="elbow_r"):
    """humerus -> ulna -> radius along -z, the elbow a hinge about x (when named as one), the radius on the
    ulna at 'radioulnar_r' with its own axis along the forearm (mm, frames = world at rest)."""
    bones = {
        "humerus_r": Bone("humerus_r", None, bone_to_world=_lifted(1400),
                          joint_centres={elbow: [0, 0, -300]}, joint_axes={elbow: [1, 0, 0]}),
        "ulna_r": Bone("ulna_r", "humerus_r", bone_to_world=_lifted(1100),
                       joint_centres={elbow: [0, 0, 0], "radioulnar_r": [0, 25, -10]},
                       joint_axes={elbow: [1, 0, 0], "radioulnar_r": [0, 0, 1]}),
        "radius_r": Bone("radius_r", "ulna_r", bone_to_world=_lifted(1090),
                         joint_centres={"radioulnar_r": [0, 25, 0]}, joint_axes={"radioulnar_r": [0, 0, 1]}),
    }
    # one-coordinate joints, as an OpenSim model declares its pin joints
    joints = {elbow: {"type": "PinJoint", "coordinates": ["elbow_flex_r"]},
              "radioulnar_r": {"type": "PinJoint", "coordinates": ["pro_sup_r"]}}
    return Skeleton(bones, world="model", metadata={"joints": joints})


def test_hinge_elbow_holds_an_ulna_with_one_marker():
    """The ulna with one marker rides a hinge: its flexion is solved, it does not turn with the radius;
    through the radio-ulnar hinge the radius's two wrist markers give the ulna's flexion too. Named as
    a ball joint (not in HINGE_JOINTS) the same ulna cannot carry itself and rides on the humerus; with
    two markers it needs no hinge and gets none."""
    from bonecap.motion.lsq import HINGE_LEVER_MM

    assert HINGE_LEVER_MM > 0
    mb = ["humerus_r"] * 3 + ["ulna_r"] + ["radius_r"] * 2
    local = np.array([[40, 0, -100], [-40, 10, -200], [0, 45, -280],     # humerus: determined alone
                      [0, -30, -80],                                       # ulna: one marker
                      [0, 45, -230], [0, -20, -235]], float)               # radius: two at the wrist
    F = 40
    t = np.linspace(0, 1, F)
    flex = np.radians(100 * t)                     # elbow flexion about x
    pron = np.radians(150 * t)                     # radius about the forearm axis (z)
    skel = arm_skeleton()
    hum = np.tile(np.eye(4), (F, 1, 1))
    hum[:, :3, :3] = Rotation.from_rotvec(np.c_[0.2 * t, 0.3 * t, 0.5 * t]).as_matrix()
    hum[:, :3, 3] = [100, 200, 1400]
    T = pose_skeleton(skel, hum, {"ulna_r": np.c_[flex, 0 * t, 0 * t], "radius_r": np.c_[0 * t, 0 * t, pron]})
    Tb = T[:, [skel.names.index(b) for b in mb]]
    meas = np.einsum("fmij,mj->fmi", Tb[..., :3, :3], local) + Tb[..., :3, 3]
    plan = plan_segments(skel, mb)
    assert plan.roots() == ["humerus_r", "ulna_r", "radius_r"]
    assert plan.segments[1].axis_in_self is not None and len(plan.segments[1].links()) == 3
    mo = solve_lsq(skel, mb, local, meas, n_sweeps=30)
    assert mo.valid.all()
    err = rotation_angle_deg(mo.transforms, T)
    assert err.max() < 0.5, err.max(axis=0)
    # the ulna's one marker 15 mm off: the radius's markers still flex it right, through the hinges
    off = local.copy()
    off[3] += [0, 15, 0]
    mo = solve_lsq(skel, mb, off, meas, n_sweeps=30)
    assert np.median(rotation_angle_deg(mo.transforms[:, 1], T[:, 1])) < 4.0
    # without hinges (a joint not named a hinge, or a template that declares its joints and this one
    # with three coordinates): the one-marker ulna is not a segment of its own
    plain = arm_skeleton(elbow="cubital")
    assert plan_segments(plain, mb).segment_of["ulna_r"] == 0
    ball = arm_skeleton()
    ball.metadata["joints"]["elbow_r"] = {"type": "CustomJoint", "coordinates": ["ex", "ey", "ez"]}
    assert plan_segments(ball, mb).segment_of["ulna_r"] == 0
    # a template that declares no joints (the embedded skeleton) has its elbow a hinge
    undeclared = arm_skeleton()
    undeclared.metadata = {}
    plan_u = plan_segments(undeclared, mb)
    assert plan_u.roots() == ["humerus_r", "ulna_r", "radius_r"] and len(plan_u.segments[1].links()) == 3
    # an ulna its two markers hold keeps ball joints (no hinge at the elbow or the radio-ulnar joint)
    two = plan_segments(skel, mb[:4] + ["ulna_r"] + mb[4:])
    assert [len(seg.links()) for seg in two.segments] == [0, 1, 1]
