"""The paper's slice rules on analytic images: the density rule's 15/16 boundary, ranks, the cortical edge, skin."""

from __future__ import annotations

import numpy as np
import pytest

from bonecap.model import Volume
from bonecap.segmentation import cortical, density, skin


def test_drop_sparse_boundary_15_16():
    """A candidate with 16 candidate neighbours in its 7x7 window is kept, with 15 it is dropped."""
    rng = np.random.default_rng(0)
    window = [(di, dj) for di in range(-3, 4) for dj in range(-3, 4) if (di, dj) != (0, 0)]
    for n, kept in ((15, False), (16, True), (0, False), (48, True)):
        c = np.zeros((21, 21), bool)
        c[10, 10] = True
        for k in rng.choice(48, size=n, replace=False):
            di, dj = window[k]
            c[10 + di, 10 + dj] = True
        assert density.drop_sparse(c)[10, 10] == kept, n
    with pytest.raises(ValueError, match="0..48"):
        density.drop_sparse(c, min_neighbours=49)


def test_drop_sparse_counts_the_48_neighbours_of_the_7x7_window():
    """drop_sparse's counts equal a direct sum of the 48 shifted masks (pixels past the edge count as none),
    at any density and with an odd image shape."""
    rng = np.random.default_rng(4)
    for p in (0.05, 0.3, 0.6, 0.95):
        c = rng.random((37, 23)) < p
        pad = np.pad(c, 3).astype(int)
        counts = sum(pad[3 + di:3 + di + 37, 3 + dj:3 + dj + 23] for di in range(-3, 4) for dj in range(-3, 4)
                     if (di, dj) != (0, 0))
        for m in (1, 16, 30, 48):
            assert np.array_equal(density.drop_sparse(c, min_neighbours=m), c & (counts >= m)), (p, m)


def test_density_candidates_rank_within_the_body():
    """The top third by rank inside the body mask: air outside and a few very bright capsules do not shift it."""
    rng = np.random.default_rng(1)
    img = np.zeros((120, 120))
    body = np.zeros_like(img, bool)
    body[10:110, 10:110] = True
    img[body] = rng.uniform(0, 300, body.sum())
    img[50, 50] = img[60, 60] = 1e5  # two capsules
    cand = density.density_candidates(img, body)
    share = cand[body].mean()
    assert 0.28 < share < 0.38
    assert not cand[~body].any()


def _long_bone_slice(radius_px=12.0, cortex_px=4.0, pixel=1.0, noise=8.0, seed=0):
    rng = np.random.default_rng(seed)
    n = 160
    ii, jj = np.mgrid[:n, :n]
    r = np.hypot(ii - 80.3, jj - 77.6)
    img = np.full((n, n), 0.0)
    body = r < 70
    img[body] = 300.0                    # muscle
    img[r < radius_px] = 80.0            # cortex (dark)
    img[r < radius_px - cortex_px] = 900.0  # marrow (bright)
    img += rng.normal(0, noise, img.shape)
    return img, body


def test_cortical_edge_finds_the_periosteal_contour():
    img, body = _long_bone_slice()
    # seed 15 px off the centre, in the muscle
    mask = cortical.cortical_edge_slice(img, (95, 77), 1.0, body_mask=body, search_radius_mm=25.0)
    area_radius = np.sqrt(mask.sum() / np.pi)
    assert abs(area_radius - 12.0) < 1.0
    ci, cj = np.argwhere(mask).mean(axis=0)
    assert abs(ci - 80.3) < 1.0 and abs(cj - 77.6) < 1.0
    # no bone near the seed: nothing
    img2, _ = _long_bone_slice()
    img2[np.hypot(*np.mgrid[:160, :160] - np.array([80.3, 77.6])[:, None, None]) < 12] = 300.0
    assert not cortical.cortical_edge_slice(img2, (80, 77), 1.0, body_mask=body).any()


def _ring_slice(outer_mm, cortex_mm, pixel_mm, rng, n=160, ss=8):
    """A long bone's section: marrow, cortex and muscle at the phantom's (the real knee's) levels,
    each pixel the mean over 8 x 8 sub-pixels (partial volume), Rician noise and 4 % texture."""
    c = n / 2 + 0.37
    g = (np.arange(n * ss) + 0.5) / ss
    r = np.hypot(*np.meshgrid(g - c, g - c, indexing="ij")) * pixel_mm
    val = np.where(r < outer_mm - cortex_mm, 3082.0, np.where(r < outer_mm, 119.0, 1770.0))
    img = val.reshape(n, ss, n, ss).mean(axis=(1, 3)) * (1 + 0.04 * rng.standard_normal((n, n)))
    img = np.hypot(img + rng.normal(0, 14.4, img.shape), rng.normal(0, 14.4, img.shape))
    rr = np.hypot(*np.meshgrid(np.arange(n) + 0.5 - c, np.arange(n) + 0.5 - c, indexing="ij")) * pixel_mm
    return img, rr < outer_mm - cortex_mm - pixel_mm


def test_cortical_contour_lies_on_the_periosteum_for_thin_and_thick_cortices():
    """A cortex 1-2.5 mm thick at 1.8 mm pixels (and 1-1.5 mm at 0.7) is blurred into a dip whose
    half-way rise lies 0.2-0.5 mm outside the bone (the rule before: radius +0.29 mm on average, up to
    +0.52, thin bones 10-20 % too large); the depth-dependent level puts the contour on it."""
    rng = np.random.default_rng(3)
    errors = []
    for pixel, outer, thick in [(1.8, 7, 1.5), (1.8, 7, 2.5), (1.8, 10, 1.5), (1.8, 10, 2.5), (1.8, 14, 1.5),
                                (1.8, 14, 2.5), (0.7, 5, 1.0), (0.7, 5, 1.5), (0.7, 7, 1.0), (0.7, 7, 1.5)]:
        e = []
        for _ in range(2):
            img, marrow = _ring_slice(outer, thick, pixel, rng)
            bone = cortical.cortical_contour(img, marrow, pixel, 1770.0)
            e.append(np.sqrt(bone.sum() / np.pi) * pixel - outer)
        errors.append(np.mean(e))
    errors = np.array(errors)
    assert abs(errors.mean()) < 0.12, errors.round(2)
    assert np.abs(errors).max() < 0.3, errors.round(2)


def test_cortical_contour_keeps_a_long_marrow_whole_and_reads_only_near_it():
    """A shaft cut along its length (a sagittal slice): its marrow is 125 mm long, longer than the rays
    reach each way from its centre (45 mm). The marrow is kept whole and the contour lies on the
    periosteum (19 mm across) near its centre; the same bone in a larger image, with a bright structure
    30 mm beyond its cortex, gives the same pixels (the crop holds what the rays read)."""
    rng = np.random.default_rng(5)
    ii, jj = np.mgrid[:200, :80]
    img = np.full((200, 80), 300.0)                                        # muscle
    img[(abs(ii - 100) <= 65) & (abs(jj - 40) <= 9)] = 80.0                # cortex, 19 px across
    marrow = (abs(ii - 100) <= 62) & (abs(jj - 40) <= 6)
    img[marrow] = 900.0
    img += rng.normal(0.0, 8.0, img.shape)
    bone = cortical.cortical_contour(img, marrow, 1.0, 300.0)
    assert bone[marrow].all()
    widths = bone.sum(axis=1)
    # the rays start at the marrow's deepest pixel (the first of the shaft's axis, ~row 44): along 25 mm
    # and more around it they meet the cortex at their side; farther on the marrow alone is left
    assert (np.abs(widths - 19) <= 1).sum() >= 25 and widths.max() <= 20, widths
    assert not bone[:30].any() and not bone[170:].any()
    big = np.full((320, 220), 300.0)
    big[60:260, 70:150] = img
    big[140:180, 190:200] = 900.0                                          # 30 mm past the cortex
    big_marrow = np.zeros(big.shape, bool)
    big_marrow[60:260, 70:150] = marrow
    big_bone = cortical.cortical_contour(big, big_marrow, 1.0, 300.0)
    np.testing.assert_array_equal(big_bone[60:260, 70:150], bone)
    assert big_bone.sum() == bone.sum()


def test_segment_body_keeps_separate_limbs():
    """Two legs and a noise speck: two components kept, holes filled per slice."""
    rng = np.random.default_rng(2)
    data = rng.normal(20, 5, (100, 80, 4))
    ii, jj = np.mgrid[:100, :80]
    for ci in (30, 70):
        leg = np.hypot(ii - ci, jj - 40) < 15
        data[leg] = 400
        data[np.hypot(ii - ci, jj - 40) < 5] = 20  # a dark hole (cortex) inside the leg
    data[5, 5] = 400  # a speck
    vol = Volume(data, np.diag([1.5, 1.5, 5.0, 1.0]))
    body = skin.segment_body(vol, min_area_mm2=50.0)
    from scipy import ndimage

    for k in range(4):
        lab, n = ndimage.label(body[:, :, k])
        assert n == 2
        assert body[30, 40, k] and body[70, 40, k]  # holes filled
        assert not body[5, 5, k]


def test_skin_edge_is_half_way_not_at_otsus_log_level():
    """A blurred disc (radius 60 mm, edge blur sigma 2.5 mm, Rician-like noise floor): the body
    boundary is within 1 mm of the true radius. Otsu's level of the log intensities alone sits
    far out on the blur (the skin was 4 mm too large on the phantom)."""
    from scipy import ndimage

    rng = np.random.default_rng(3)
    px = 1.0
    ii, jj = np.mgrid[:240, :240] * px
    r = np.hypot(ii - 120, jj - 120)
    inside = (r < 60.0).astype(float)
    data = np.stack([ndimage.gaussian_filter(inside, 2.5 / px)] * 3, axis=-1) * 300.0
    data = np.hypot(data + rng.normal(0, 4, data.shape), rng.normal(0, 4, data.shape))   # Rician
    vol = Volume(data, np.diag([px, px, 5.0, 1.0]))
    area = skin.segment_body(vol, skin=True)[1].sum(axis=(0, 1)) * px * px
    radius = np.sqrt(area / np.pi)
    assert np.all(np.abs(radius - 60.0) < 1.0), radius
    otsu_only = np.sqrt(skin.segment_body(vol).sum(axis=(0, 1)) * px * px / np.pi)
    assert np.all(otsu_only - 60.0 > 1.5)                       # what the half-way level fixes
    assert np.all(otsu_only - radius > 1.0)


def test_joint_space_is_the_valley_not_the_minimum():
    """Femoral shaft (small) -> condyles (large) -> joint space (dip) -> plateau (large) -> tibial
    shaft: the split goes in the dip even where the shaft's section is smaller; no valley -> minimum."""
    from bonecap.segmentation.bones import _joint_space

    profile = np.array([300, 320, 500, 900, 1400, 1500, 700, 1300, 1200, 800, 500, 450])
    assert _joint_space(profile) == 6
    assert _joint_space(np.array([900, 700, 500, 400, 300])) == 4


def test_muscle_level_where_bone_fills_the_view():
    # a limb's cross-section: muscle is the mode, and stays so
    rng = np.random.default_rng(0)
    limb = np.r_[rng.normal(1000, 40, 6000), rng.normal(3000, 60, 1500), rng.normal(5000, 80, 2000)]
    img = limb.reshape(1, -1)
    assert abs(cortical.muscle_level(img, np.ones_like(img, bool)) - 1000) < 60
    # a sagittal knee: the condyles' marrow is the most common tissue, muscle the darker class's mode
    knee = np.r_[rng.normal(1000, 40, 2500), rng.normal(3000, 60, 6000), rng.normal(5000, 80, 1500)]
    img = knee.reshape(1, -1)
    plain_mode = cortical._mode(knee, *np.percentile(knee, [1, 99]), 64)
    assert abs(plain_mode - 3000) < 100                  # what the plain mode would have said
    assert abs(cortical.muscle_level(img, np.ones_like(img, bool)) - 1000) < 60


def _marrow_and_fat(bridge_px: int):
    """A body disc whose skin band holds fat; a marrow disc joined to the fat by a bridge."""
    yy, xx = np.mgrid[:120, :120]
    body = (yy - 60) ** 2 + (xx - 60) ** 2 < 58 ** 2
    inner = (yy - 60) ** 2 + (xx - 60) ** 2 < 54 ** 2
    fat = body & ~((yy - 60) ** 2 + (xx - 60) ** 2 < 48 ** 2)
    marrow = (yy - 60) ** 2 + (xx - 60) ** 2 < 15 ** 2
    bridge = (np.abs(yy - 60) <= bridge_px // 2) & (xx > 60) & body
    return body, inner, fat | marrow | bridge, marrow


def test_detach_from_skin_cuts_marrow_loose_from_fat_through_a_gap():
    body, inner, cand, marrow = _marrow_and_fat(bridge_px=1)
    lab, n = cortical.detach_from_skin(cand, body, inner, pixel_mm=1.0, neck_mm=1.5)
    got = lab == lab[60, 60]
    assert lab[60, 60] > 0 and not (got & ~inner).any()          # the marrow, away from the skin
    dice = 2 * (got & marrow).sum() / (got.sum() + marrow.sum())
    assert dice > 0.97
    # a wide connection is no gap in a cortex: the region reaches the skin and is dropped whole
    body, inner, cand, marrow = _marrow_and_fat(bridge_px=12)
    lab, n = cortical.detach_from_skin(cand, body, inner, pixel_mm=1.0, neck_mm=1.5)
    assert lab[60, 60] == 0 or (lab == lab[60, 60]).sum() > 3 * marrow.sum()
    # nothing at the skin: returned as labelled
    lab, n = cortical.detach_from_skin(marrow, body, inner, pixel_mm=1.0)
    assert n == 1 and (lab > 0).sum() == marrow.sum()


def test_two_long_bones_in_one_region_are_split_and_a_density_seed_leaves_it():
    from bonecap.segmentation.bones import _cortical_slice, _split_shared_regions

    yy, xx = np.mgrid[:160, :120].astype(float)
    a = (yy - 45) ** 2 + (xx - 60) ** 2 < 25 ** 2            # a condyle
    b = (yy - 108) ** 2 + (xx - 60) ** 2 < 25 ** 2           # a plateau, touching it through a neck
    neck = (np.abs(xx - 60) <= 2) & (yy > 60) & (yy < 90)
    lab, n = _split_shared_regions((a | b | neck).astype(np.int32), 1,
                                   {"femur_r": np.array([[45.0, 60.0]]), "tibia_r": np.array([[108.0, 60.0]])})
    assert n == 2 and lab[45, 60] != lab[108, 60]
    assert (lab[a] == lab[45, 60]).all() and (lab[b] == lab[108, 60]).all()
    # _cortical_slice: femur seed inside the one marrow region, a patella seed 8 px off it and nothing
    # else within reach: the femur keeps its marrow (the patella's row may not push it onto nothing)
    rng = np.random.default_rng(1)
    img = np.full(yy.shape, 1000.0) + rng.normal(0, 10, yy.shape)
    r = np.hypot(yy - 60, xx - 60)
    img[r < 22] = 3000.0
    img[(r >= 22) & (r < 25)] = 100.0                        # the cortex
    body = np.ones(img.shape, bool)
    body[:2] = body[-2:] = False
    body[:, :2] = body[:, -2:] = False
    from scipy import ndimage

    inner = ndimage.binary_erosion(body, iterations=3)
    opts = {"femur_r": {"search_radius_mm": 30.0}, "patella_r": {"max_distance_mm": 25.0}}
    out = _cortical_slice(img, img, body, inner, 1.0, {"femur_r": np.array([[60.0, 60.0]])},
                          {"femur_r": np.array([False])}, opts, {"patella_r": np.array([[60.0, 90.0]])})
    truth = r < 25
    dice = 2 * (out["femur_r"] & truth).sum() / (out["femur_r"].sum() + truth.sum())
    assert dice > 0.9


def test_slice_seeds_point_on_a_slice_crosses_it():
    from bonecap.segmentation.bones import slice_seeds

    aff = np.diag([1.0, 1.0, 4.0, 1.0])
    v = Volume(np.zeros((10, 10, 24), np.float32), aff)
    # the polyline ends on slice 19 up to a rounding of the world coordinates (0.1 mm in a YAML file)
    line = np.array([[5.0, 5.0, 40.0], [5.0, 5.0, 19 * 4.0 - 0.04]])
    crossing = slice_seeds(v, line, 0.0)
    assert len(crossing[19]) == 1 and len(crossing[10]) == 1 and len(crossing[20]) == 0
    # a vertex on slice 12 (both segments find it, a hair apart): one seed there, not two
    line = np.array([[5.0, 5.0, 40.0], [6.0, 5.0, 12 * 4.0 + 0.03], [8.0, 5.0, 80.0]])
    crossing = slice_seeds(v, line, 0.0)
    assert len(crossing[12]) == 1 and np.allclose(crossing[12][0], [6.0, 5.0], atol=0.01)


def _tube_stack(n: int, K: int, dz: float, tubes, seed: int):
    """An axial stack of long-bone sections in muscle: ``tubes`` = (i, j, outer px, marrow px, slices).

    Cortex 80, marrow 900, muscle 300 inside a body disc of radius ``n // 2 - 6``, noise 8.
    Returns the Volume and the body mask.
    """
    rng = np.random.default_rng(seed)
    ii, jj = np.mgrid[:n, :n].astype(float)
    data = np.full((n, n, K), 300.0)
    body = np.hypot(ii - n / 2, jj - n / 2) < n // 2 - 6
    data[~body] = 0.0
    for ci, cj, outer, inner, ks in tubes:
        r = np.hypot(ii - ci, jj - cj)
        for k in ks:
            data[:, :, k][r < outer] = 80.0
            data[:, :, k][r < inner] = 900.0
    data += rng.normal(0, 8, data.shape)
    return Volume(data.astype(np.float32), np.diag([1.0, 1.0, dz, 1.0])), np.repeat(body[:, :, None], K, axis=2)


def test_a_long_bone_stops_where_its_sections_stop_continuing_it():
    """A radius-like tube ends at slice 12; a humerus-like bone begins at slice 14, 6 px off its axis.

    The seed margin (20 mm past the polyline's end) searches slices 13-16 too: the big marrow
    there is the neighbour's and must not be labelled as the thin bone (it was, before the
    continuity check: 3.5 times the thin bone's section on the phantom's elbow).
    """
    from bonecap.segmentation.bones import segment_bones

    K = 20
    vol, body = _tube_stack(120, K, 4.0, [(60, 60, 7, 4, range(0, 13)),       # the thin bone
                                          (60, 66, 16, 13, range(14, K))],    # the neighbour
                            seed=3)
    seeds = {"radius_r": np.array([[60.0, 60.0, 0.0], [60.0, 60.0, 12 * 4.0]])}
    labels, ids = segment_bones(vol, seeds, body_mask=body, progress=False, margin_mm=20.0)
    area = (labels == ids["radius_r"]).sum(axis=(0, 1))
    # the thin bone is found on its slices (pi 7^2 ~ 154 px) ...
    assert np.all(np.abs(area[:13] - np.pi * 49) < 40)
    # ... and nothing of the neighbour is given to it
    assert area[13:].sum() == 0


def test_an_elbow_keeps_both_bones_in_the_slices_they_share():
    """Two long bones share a joint point, but lie side by side in the slices around it.

    An elbow-like joint: the upper bone (section radius 12 px) occupies slices 7-17, the lower one
    (radius 6 px, 22 px behind it) slices 0-10 -- slices 7-10 hold both, as the olecranon lies
    behind the trochlea. Both polylines end at the joint point inside the upper bone. A
    whole-slice split at the joint space gives each shared slice to one bone; following each
    bone from its shaft keeps both.
    """
    from bonecap.segmentation.bones import segment_bones

    K = 18
    vol, body = _tube_stack(140, K, 5.0, [(70, 60, 12, 9, range(7, K)),       # the upper bone
                                          (70, 82, 6, 3.5, range(0, 11))],    # the lower bone
                            seed=5)
    joint = [70.0, 62.0, 9 * 5.0]
    seeds = {"humerus_r": np.array([[70.0, 60.0, 17 * 5.0], joint]),
             "ulna_r": np.array([joint, [70.0, 82.0, 0.0]])}
    labels, ids = segment_bones(vol, seeds, body_mask=body, progress=False)
    for k in range(7, 11):                  # the shared slices: each bone on its own section
        h = labels[:, :, k] == ids["humerus_r"]
        u = labels[:, :, k] == ids["ulna_r"]
        assert abs(h.sum() - np.pi * 144) < 60, (k, h.sum())
        assert abs(u.sum() - np.pi * 36) < 30, (k, u.sum())
        assert h[70, 60] and u[70, 82]


def test_the_continuity_walk_trims_ends_but_does_not_take_half_a_bone():
    """keep_continuous on given labels: sections that jump aside past the shaft are dropped -- unless
    that would be most of the bone (a seed swapping between two bones broke the shaft: trust nothing)."""
    from bonecap.segmentation.bones import keep_continuous

    K = 20
    vol = Volume(np.zeros((60, 60, K), np.float32), np.diag([1.0, 1.0, 4.0, 1.0]))
    yy, xx = np.mgrid[:60, :60]
    at = {"A": (xx - 20) ** 2 + (yy - 20) ** 2 <= 16, "B": (xx - 40) ** 2 + (yy - 40) ** 2 <= 16}

    def labels_for(place_of_slice):
        lab = np.zeros(vol.data.shape, np.int32)
        for k in range(K):
            lab[:, :, k][at[place_of_slice(k)]] = 1
        return lab

    # the polyline crosses slices 0-12 at A; slices 13-19 jump to B: the ends are trimmed
    seeds = {"radius_r": np.array([[20.0, 20.0, 0.0], [20.0, 20.0, 48.0]])}
    lab = labels_for(lambda k: "A" if k <= 12 else "B")
    out = keep_continuous(lab, {"radius_r": 1}, vol, seeds)
    area = (out == 1).sum(axis=(0, 1))
    assert (area[:13] > 0).all() and (area[13:] == 0).all()
    assert (lab == 1).sum(axis=(0, 1))[13:].all()            # the input is left as it was
    # the polyline crosses only slices 0-3 at A, the other 16 sections lie at B: the walk would drop
    # 80 % of the bone -- the labels are kept as segmented, with a warning
    seeds = {"radius_r": np.array([[20.0, 20.0, 0.0], [20.0, 20.0, 12.0]])}
    lab = labels_for(lambda k: "A" if k <= 3 else "B")
    with pytest.warns(UserWarning, match="do not continue"):
        out = keep_continuous(lab, {"radius_r": 1}, vol, seeds)
    np.testing.assert_array_equal(out, lab)


@pytest.mark.parametrize("gap, beyond_crossed, kept", [(2, False, False), (1, False, True), (2, True, True)])
def test_past_a_gap_the_seed_margin_finds_the_next_bone_not_this_one(gap, beyond_crossed, kept):
    """A radius-like tube on slices 0-13 (5 mm apart), then ``gap`` empty slices, then two slices of
    another bone on its axis, as large (the carpals past the distal radius): the seed margin (20 mm)
    reaches them and they continue the tube in place and size. Past more than MARGIN_GAP_MM of empty
    slices they are dropped; one empty slice is the bone going on past its template's end; and a slice
    the polyline crosses stays past any gap (the femoral neck and head past a stretch of grey shaft)."""
    from bonecap.segmentation.bones import MARGIN_GAP_MM, segment_bones

    dz, K = 5.0, 20
    assert 5.0 < MARGIN_GAP_MM < 10.0          # one empty 5 mm slice is no gap, two are
    beyond = range(14 + gap, 16 + gap)
    vol, body = _tube_stack(120, K, dz, [(60, 60, 7, 4, range(0, 14)), (60, 60, 7, 4, beyond)], seed=4)
    end = (beyond[-1] if beyond_crossed else 13) * dz
    seeds = {"radius_r": np.array([[60.0, 60.0, 0.0], [60.0, 60.0, end]])}
    labels, ids = segment_bones(vol, seeds, body_mask=body, progress=False, margin_mm=20.0)
    area = (labels == ids["radius_r"]).sum(axis=(0, 1))
    assert np.all(np.abs(area[:14] - np.pi * 49) < 40)
    assert (area[list(beyond)] > 0).all() == kept and (area[list(beyond)] == 0).all() != kept


def test_where_stations_overlap_the_one_holding_the_shaft_judges_a_long_bone_s_end():
    """Two overlapping stations: A (z 0-95 mm) holds most of the radius's line (z 10-70: 13 of its
    slices), B (z 60-155) three. B's sections where A labels the radius too stay; those A images
    without the radius (the carpals past its end) are dropped; one only B images stays; A is left as
    it is, and so are a bone crossing no station and a density bone."""
    from bonecap.segmentation.bones import defer_to_shaft_stacks

    dz = 5.0
    A = Volume(np.zeros((40, 40, 20), np.float32), np.diag([1.0, 1.0, dz, 1.0]))
    B = Volume(np.zeros((40, 40, 20), np.float32), np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0],
                                                             [0, 0, dz, 60.0], [0, 0, 0, 1.0]]))
    seeds = {"radius_r": np.array([[20.0, 20.0, 10.0], [20.0, 20.0, 70.0]]),
             "ulna_r": np.array([[20.0, 20.0, 200.0], [20.0, 20.0, 260.0]]),   # in no station
             "hip_r": np.array([[20.0, 20.0, 30.0]])}
    ids_a = {"radius_r": 1, "ulna_r": 2, "hip_r": 3}
    ids_b = {"radius_r": 4, "ulna_r": 5, "hip_r": 6}             # each stack its own ids
    la, lb = np.zeros(A.shape, np.int32), np.zeros(B.shape, np.int32)
    la[15:25, 15:25, 2:15] = 1         # z 10-70
    lb[15:25, 15:25, 0:3] = 4          # z 60-70: A labels the radius there too
    lb[15:25, 15:25, 3:6] = 4          # z 75-85: A images it, without the radius
    lb[15:25, 15:25, 12] = 4           # z 120: B alone images it
    lb[5:10, 5:10, 0:6] = 5
    lb[30:35, 30:35, 3:6] = 6
    before_a, before_b = la.copy(), lb.copy()
    dropped = defer_to_shaft_stacks([la, lb], [ids_a, ids_b], [A, B], seeds)
    assert dropped == {"radius_r": 3}
    np.testing.assert_array_equal(la, before_a)
    radius = (lb == 4).sum(axis=(0, 1))
    assert list(np.flatnonzero(radius)) == [0, 1, 2, 12]
    np.testing.assert_array_equal(lb == 5, before_b == 5)
    np.testing.assert_array_equal(lb == 6, before_b == 6)
    # B's slices staggered against A's (z 63, 68, 73, 78): the section at z 73 lies nearest A's z 75, past
    # the radius, but A's slice at z 70 images its slab too: kept; the one at z 78 is past both
    B2 = Volume(B.data, B.affine.copy())
    B2.affine[2, 3] = 63.0
    lb2 = np.zeros(B2.shape, np.int32)
    lb2[15:25, 15:25, 0:4] = 4
    assert defer_to_shaft_stacks([la, lb2], [ids_a, ids_b], [A, B2], seeds) == {"radius_r": 1}
    assert list(np.flatnonzero((lb2 == 4).sum(axis=(0, 1)))) == [0, 1, 2]
    with pytest.raises(ValueError, match="as many"):
        defer_to_shaft_stacks([la], [ids_a, ids_b], [A, B], seeds)
    with pytest.raises(ValueError, match="does not match"):
        defer_to_shaft_stacks([la[:, :, :5], lb], [ids_a, ids_b], [A, B], seeds)
    with pytest.raises(ValueError, match="min_share"):
        defer_to_shaft_stacks([la, lb], [ids_a, ids_b], [A, B], seeds, min_share=0.0)


def test_a_canal_too_narrow_to_show_bright_is_found_inside_its_cortex():
    """A fibula-sized bone (4-4.5 mm radius, 1.8-2 mm of cortex) at 1.8 mm pixels: partial volume
    leaves its canal at most ~1.2-1.4 x muscle, so bright-marrow candidates alone find nothing (seed 2's
    right fibula lost 170 mm of shaft so); inside its closed dark ring it is found, and the section
    comes out within 0.5 mm of its radius. A dark tendon (solid) and a bone whose ring is open on
    one side give no enclosed candidate."""
    rng = np.random.default_rng(5)
    for outer, thick in [(4.0, 1.8), (4.5, 2.0)]:
        img, _ = _ring_slice(outer, thick, 1.8, rng)
        body = np.zeros(img.shape, bool)
        body[10:-10, 10:-10] = True
        assert not cortical.find_marrow(img, (80, 85), 1.8, body, enclosed_max_mm2=0).any()
        assert cortical.find_marrow(img, (80, 85), 1.8, body).any()
        bone = cortical.cortical_edge_slice(img, (80, 85), 1.8, body)
        assert abs(np.sqrt(bone.sum() / np.pi) * 1.8 - outer) < 0.5
        # the same ring cut open on one side (a gap of muscle through the cortex): no enclosed hole
        g = (np.arange(160) + 0.5) * 1.8
        ii, jj = np.meshgrid(g - 80.37 * 1.8, g - 80.37 * 1.8, indexing="ij")
        opened = img.copy()
        opened[(np.abs(ii) < 1.8) & (jj > 0) & (jj < outer + 3)] = 1770.0
        assert not cortical.enclosed_marrow(opened, body, 1770.0, 1.8).any()
    # a tendon: dark and solid, nothing enclosed
    img = np.full((80, 80), 1770.0)
    ii, jj = np.mgrid[:80, :80]
    img[np.hypot(ii - 40, jj - 40) < 4] = 119.0
    assert not cortical.enclosed_marrow(img, np.ones(img.shape, bool), 1770.0, 1.8).any()
    # a canal in it (9 px); the body in air: the air is dark but outside the body, so the body itself
    # is no hole; a hole larger than max_area_mm2 is no canal
    img[np.hypot(ii - 40, jj - 40) < 2] = 1770.0
    body = np.hypot(ii - 40, jj - 40) < 30
    img[~body] = 0.0
    assert cortical.enclosed_marrow(img, body, 1770.0, 1.8).sum() == 9
    assert not cortical.enclosed_marrow(img, body, 1770.0, 1.8, max_area_mm2=25.0).any()
    with pytest.raises(ValueError, match="shape"):
        cortical.enclosed_marrow(img, np.ones((3, 3), bool), 1770.0, 1.8)


def test_rim_darkness_tells_marrow_from_a_speck_of_fat():
    """Marrow is rimmed by its dark cortex, a speck of fat between muscles by muscle."""
    from scipy import ndimage

    img, body = _long_bone_slice()
    ii, jj = np.mgrid[:160, :160]
    img[np.hypot(ii - 80, jj - 120) < 3] = 900.0          # the speck, in the muscle
    lab, n = ndimage.label(ndimage.gaussian_filter(img, 0.7) > 1.2 * 300.0)
    marrow, speck = lab[80, 78], lab[80, 120]
    rim = cortical.rim_darkness(lab, [marrow, speck], img, 300.0, 1.0)
    assert rim[0] > 0.9 and rim[1] < 0.1
    with pytest.raises(ValueError, match="width_mm"):
        cortical.rim_darkness(lab, [marrow], img, 300.0, 1.0, width_mm=0.0)
    with pytest.raises(ValueError, match="shape"):
        cortical.rim_darkness(lab[:10], [marrow], img, 300.0, 1.0)


def test_a_seed_nearer_a_speck_of_fat_than_the_marrow_takes_the_marrow():
    """A seed line 8 px off a bone's axis, and in one slice a bright speck of fat 2 px from it: the
    marrow is 3 px farther but rimmed by cortex; without the rim's cost (``unrimmed_cost_mm=0``)
    the speck takes the seed and the bone loses that section (seen on a forearm stack, where it cut
    the ulna's chain from its shaft to the olecranon)."""
    from bonecap.segmentation.bones import segment_bones

    K = 12
    vol, body = _tube_stack(120, K, 4.0, [(60, 60, 9, 6, range(K))], seed=7)
    ii, jj = np.mgrid[:120, :120]
    vol.data[:, :, 6][np.hypot(ii - 60, jj - 70) < 2.6] = 900.0   # the speck, 2 px beyond the seed
    seeds = {"ulna_r": np.array([[60.0, 68.0, 0.0], [60.0, 68.0, (K - 1) * 4.0]])}
    labels, ids = segment_bones(vol, seeds, body_mask=body, progress=False)
    sec = labels[:, :, 6] == ids["ulna_r"]
    assert sec[60, 60] and abs(sec.sum() - np.pi * 81) < 40
    labels, ids = segment_bones(vol, seeds, body_mask=body, progress=False,
                                options={"ulna_r": {"unrimmed_cost_mm": 0.0}}, continuity=False)
    assert not labels[60, 60, 6]


def test_marrow_sections_finds_a_bone_without_a_seed():
    """Two bones; the one in ``exclude`` is left, a speck of fat is not a bone, one section per slice."""
    from bonecap.segmentation.bones import marrow_sections

    K = 6
    vol, body = _tube_stack(120, K, 4.0, [(45, 60, 9, 6, range(K)), (78, 60, 7, 4, range(K))], seed=8)
    ii, jj = np.mgrid[:120, :120]
    vol.data[:, :, 2][np.hypot(ii - 60, jj - 90) < 4] = 900.0         # a speck bigger than the marrow
    exclude = np.repeat((np.hypot(ii - 45, jj - 60) < 10)[:, :, None], K, axis=2)
    out = marrow_sections(vol, body, body_mask=body, exclude=exclude, per_slice=1)
    for k in range(K):
        assert out[78, 60, k] and not out[45, 60, k] and not out[60, 90, k], k
        assert abs(out[:, :, k].sum() - np.pi * 49) < 30, (k, out[:, :, k].sum())
    # without ``exclude`` the bigger bone comes first
    out = marrow_sections(vol, body, body_mask=body, per_slice=1)
    assert out[45, 60].all() and not out[78, 60].any()
    with pytest.raises(ValueError, match="where"):
        marrow_sections(vol, body[:, :, :2])


def test_marrow_sections_reuses_the_regions_segment_bones_found(monkeypatch):
    """On a stack segment_bones has been through (a forearm stack: the ulna by its seed, then the radius
    without one), its slices' marrow regions are reused, not found again, with the same sections; found
    with other options they are not used."""
    from bonecap.segmentation import bones as bones_mod
    from bonecap.segmentation.bones import marrow_sections, segment_bones

    K = 6
    vol, body = _tube_stack(120, K, 4.0, [(45, 60, 9, 6, range(K)), (78, 60, 7, 4, range(K))], seed=8)
    seeds = {"ulna_r": np.array([[45.0, 60.0, 0.0], [45.0, 60.0, (K - 1) * 4.0]])}
    regions: dict = {}
    labels, ids = segment_bones(vol, seeds, body_mask=body, progress=False, continuity=False,
                                marrow_regions=regions)
    assert sorted(regions) == list(range(K))
    exclude = labels == ids["ulna_r"]
    found = []
    detach = bones_mod.cortical.detach_from_skin
    monkeypatch.setattr(bones_mod.cortical, "detach_from_skin", lambda *a, **k: found.append(1) or detach(*a, **k))
    again = marrow_sections(vol, body, body_mask=body, exclude=exclude, per_slice=1)
    assert len(found) == K
    reused = marrow_sections(vol, body, body_mask=body, exclude=exclude, per_slice=1, regions=regions)
    assert len(found) == K                                    # nothing found again
    assert np.array_equal(reused, again) and reused[78, 60].all() and not reused[45, 60].any()
    other = marrow_sections(vol, body, body_mask=body, exclude=exclude, per_slice=1, regions=regions,
                            options={"marrow_over_muscle": 1.3})
    assert len(found) == 2 * K and other[78, 60].all()


def test_long_bone_seeds_stop_short_of_a_joint_with_an_unsegmented_bone():
    """The tibia's seed line ends the 20 mm search margin + the talus's reach into the ankle's mortise
    (how far its template mesh extends past the ankle's centre back along the tibia) short of the
    ankle's centre: searched to 20 mm beyond that centre, the tibia took the talus's sections (not
    segmented at whole-body resolution) on a phantom. The carpals begin beyond the wrist's centre
    (reach < 0): the radius's line reaches the wrist, as do lines that end where another long bone's
    begins (femur-tibia). A bone that goes on past its distal centre by more than the margin, where
    no other line begins (the fibula's malleolus past the distal tibiofibular joint), is searched
    to half the margin past its end."""
    from bonecap.build_mri import bone_seeds
    from bonecap.skeleton.template import load_template

    sk = load_template("default")

    def reach(bone, partner, prox, joint):
        b, o = sk.bones[bone], sk.bones[partner]
        back = b.landmark_in_world(prox) - b.landmark_in_world(joint)
        back /= np.linalg.norm(back)
        return float(((o.mesh.transformed(o.bone_to_world).vertices - b.landmark_in_world(joint)) @ back).max())

    talus, carpals = reach("tibia_r", "talus_r", "knee", "ankle"), reach("radius_l", "carpals_l", "elbow", "wrist")
    assert 5.0 < talus < 25.0 and -10.0 < carpals < 5.0
    def own(bone, prox, joint):
        """How far the bone itself goes on past its distal joint centre."""
        b = sk.bones[bone]
        p0, p1 = b.landmark_in_world(prox), b.landmark_in_world(joint)
        return float(((b.mesh.transformed(b.bone_to_world).vertices - p1) @ (p1 - p0)).max() / np.linalg.norm(p1 - p0))

    # the fibula's lateral malleolus ends ~40 mm past the distal tibiofibular joint, the ulna's styloid ~15 mm
    # past the distal radio-ulnar joint: past the margin, the line goes on to half the margin short of it
    malleolus, styloid = own("fibula_l", "proximal_tibiofibular", "distal_tibiofibular"), \
        own("ulna_r", "elbow", "distal_radioulnar")
    assert 25.0 < malleolus < 60.0 and 5.0 < styloid < 20.0

    def on(reach, margin):
        return -(reach - 0.5 * margin) if reach > margin else 0.0
    for margin in (20.0, 5.0, 60.0):
        seeds = bone_seeds(sk, np.eye(4), margin_mm=margin)
        for bone, prox, dist, short in (("tibia_r", "knee", "ankle", min(margin + talus, 0.25 * 389.3)),
                                        ("radius_l", "elbow", "wrist", 0.0),
                                        ("femur_r", "hip", "knee", 0.0),
                                        ("fibula_l", "proximal_tibiofibular", "distal_tibiofibular",
                                         on(malleolus, margin)),
                                        ("ulna_r", "elbow", "distal_radioulnar", on(styloid, margin))):
            b = sk.bones[bone]
            p0, p1 = b.landmark_in_world(prox), b.landmark_in_world(dist)
            line = seeds[bone]
            u = (p1 - p0) / np.linalg.norm(p1 - p0)
            assert np.allclose(line[0], p0)
            # ``short`` mm short of the distal centre (negative: beyond it), on the joint-to-joint line
            assert (p1 - line[-1]) @ u == pytest.approx(short, abs=0.5), (bone, margin)
            assert np.linalg.norm(np.cross(line[-1] - p0, u)) < 1e-6


def test_long_bone_seed_lines_run_through_the_shaft():
    """A femur's joint centres (head, knee) lie off its shaft by the neck's offset: below the
    trochanters the head-to-knee line leaves the bone (a phantom's marrow 28-42 mm from it, 25 mm
    searched). The seed line through the template's section centres (``shaft_line``) stays inside
    the bone; on a tube bent away from its end points it follows the tube's axis."""
    import trimesh

    from bonecap.build_mri import bone_seeds, shaft_line
    from bonecap.skeleton.template import load_template

    # a tube along z from 0 to 400 mm whose axis is 30 mm off the line between its end points in the
    # middle (a smooth bow), radius 12 mm
    z = np.linspace(0, 400, 201)
    off = 30.0 * np.sin(np.pi * z / 400)
    ang = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    V = np.array([[o + 12 * np.cos(a), 12 * np.sin(a), zz] for zz, o in zip(z, off) for a in ang])
    line = np.array(shaft_line(V, np.array([0.0, 0, 0]), np.array([0.0, 0, 400])))
    assert len(line) == 11
    inner = line[1:-1]
    assert np.abs(inner[:, 0] - 30.0 * np.sin(np.pi * inner[:, 2] / 400)).max() < 1.0
    assert np.abs(inner[:, 1]).max() < 1e-6
    assert len(shaft_line(V[:5], np.zeros(3), np.array([0.0, 0, 400]))) == 2   # too few vertices: the ends

    sk = load_template("default")
    seeds = bone_seeds(sk, np.eye(4))
    for bone in ("femur_r", "femur_l", "radius_r", "fibula_l"):
        b = sk.bones[bone]
        tm = trimesh.Trimesh(b.mesh.vertices, b.mesh.faces, process=False)
        inside = tm.contains((seeds[bone][1:-1] - b.bone_to_world[:3, 3]) @ b.bone_to_world[:3, :3])
        assert inside.all(), (bone, inside)
    b = sk.bones["femur_r"]
    p0, p1 = b.landmark_in_world("hip"), b.landmark_in_world("knee")
    tm = trimesh.Trimesh(b.mesh.vertices, b.mesh.faces, process=False)
    on_joint_line = [p0 + f * (p1 - p0) for f in (0.1, 0.2)]
    assert not tm.contains((np.array(on_joint_line) - b.bone_to_world[:3, 3]) @ b.bone_to_world[:3, :3]).any()


def test_a_density_bone_seed_reaches_every_slab_of_the_bone():
    """A density bone's seed runs through its sections' centres, slab by slab: every 10 mm of the template
    hip bone's and scapula's height lies within the seed margin of the line (with their joint centres and
    one centroid alone, parts of them lay 55-106 mm beyond those: slices never searched), and the line
    stays ordered along z."""
    from bonecap.build_mri import DENSITY_SEED_SLAB_MM, MODEL_TO_LPS, bone_seeds
    from bonecap.skeleton.template import load_template

    sk = load_template("default")
    seeds = bone_seeds(sk, MODEL_TO_LPS, margin_mm=20.0)
    for bone in ("hip_r", "scapula_l", "sacrum"):
        W = sk.world_mesh(bone).vertices @ MODEL_TO_LPS[:3, :3].T + MODEL_TO_LPS[:3, 3]
        line = seeds[bone]
        assert np.all(np.diff(line[:, 2]) <= 0), bone                    # head to feet
        # every slab of the bone has a seed point within half a slab (the margin is 20 mm)
        for z0 in np.arange(W[:, 2].min(), W[:, 2].max(), DENSITY_SEED_SLAB_MM):
            assert np.abs(line[:, 2] - z0).min() <= DENSITY_SEED_SLAB_MM, (bone, z0)
        # the joint centres and the centroid alone leave part of the bone beyond the 20 mm margin
        b = sk.bones[bone]
        old = np.array([b.landmark_in_world(j) for j in b.joint_centres] + [sk.world_mesh(bone).vertices.mean(0)])
        old_z = (old @ MODEL_TO_LPS[:3, :3].T + MODEL_TO_LPS[:3, 3])[:, 2]
        gap = max(np.abs(old_z - z).min() for z in W[:, 2])
        assert gap > 20.0, (bone, gap)


def test_fill_holes_is_scipys_binary_fill_holes():
    """``density.fill_holes`` labels the background instead of scipy's repeated dilation: the same
    masks on rings with noise, a mask touching the slice edge, nested rings and an empty one."""
    from scipy import ndimage

    rng = np.random.default_rng(5)
    yy, xx = np.mgrid[:90, :120]
    cases = [np.zeros((90, 120), bool)]
    for k in range(30):
        r = np.hypot(yy - rng.uniform(0, 90), xx - rng.uniform(0, 120))
        ring = (r < rng.uniform(15, 40)) & (r > rng.uniform(3, 12))
        ring |= (r < 2.5) & (k % 3 == 0)            # an island inside the hole
        cases.append(ring ^ (rng.random(ring.shape) < 0.04))
    n_filled = 0
    for m in cases:
        ours = density.fill_holes(m)
        assert np.array_equal(ours, ndimage.binary_fill_holes(m))
        n_filled += int(ours.sum() - m.sum())
    assert n_filled > 1000                           # holes were there to fill


def test_per_slice_fill_of_the_body_is_scipys_in_plane_fill():
    """segment_body fills each slice's holes by labelling the background once: the same masks as
    ``binary_fill_holes`` with the in-plane structure, on stacks of noisy rings (holes to fill), with
    full and empty slices, and masks touching the first and last slices (which are no border)."""
    from scipy import ndimage

    from bonecap.segmentation.skin import _INPLANE, _fill_holes_per_slice

    rng = np.random.default_rng(11)
    n_filled = 0
    for k in range(12):
        shape = (int(rng.integers(20, 70)), int(rng.integers(20, 70)), int(rng.integers(1, 9)))
        yy, xx = np.mgrid[:shape[0], :shape[1]]
        m = np.zeros(shape, bool)
        for s in range(shape[2]):
            r = np.hypot(yy - rng.uniform(0, shape[0]), xx - rng.uniform(0, shape[1]))
            m[:, :, s] = (r < rng.uniform(8, 25)) & (r > rng.uniform(2, 7))
        m ^= rng.random(shape) < 0.03
        m[:, :, 0] |= k % 4 == 0                      # a full slice
        if k % 3 == 0:
            m[:, :, -1] = False                        # an empty one
        ours = _fill_holes_per_slice(m)
        assert np.array_equal(ours, ndimage.binary_fill_holes(m, structure=_INPLANE))
        n_filled += int(ours.sum() - m.sum())
    assert n_filled > 500                             # holes were there to fill


def test_section_continuity_on_its_box_equals_the_whole_slice():
    """``bones._continues`` dilates on the two sections' box (speed): the decision must be the
    whole slice's, including sections at the slice's edge, far apart, and one of them empty."""
    from scipy import ndimage
    from skimage.morphology import disk

    from bonecap.segmentation import bones

    def whole_slice(cur, prev, fp, grow, min_overlap):
        n_cur, n_prev = int(cur.sum()), int(prev.sum())
        if n_cur > grow * n_prev + 4:
            return False
        if int((cur & ndimage.binary_dilation(prev, fp)).sum()) >= min_overlap * n_cur:
            return True
        return int((prev & ndimage.binary_dilation(cur, fp)).sum()) >= min_overlap * n_prev

    rng = np.random.default_rng(11)
    yy, xx = np.mgrid[:70, :80]
    fp = disk(4)
    seen = set()
    for _ in range(300):
        c1, c2 = rng.uniform(-5, 85, 2), rng.uniform(-5, 85, 2)
        cur = np.hypot(yy - c1[0], xx - c1[1]) < rng.uniform(0, 12)
        prev = np.hypot(yy - c2[0], xx - c2[1]) < rng.uniform(0, 12)
        grow, ov = rng.uniform(1.2, 3.0), rng.uniform(0.3, 0.9)
        want = whole_slice(cur, prev, fp, grow, ov)
        assert bones._continues(cur, prev, fp, grow, ov) == want
        seen.add(want)
    assert seen == {True, False}


def _round_body(n: int, K: int, radius: float, seed: int):
    """A round body (muscle 300, air 0) centred in n x n slices, K of them: the generator, the pixel
    grids, the in-plane body mask and the stack (to be filled with bone)."""
    rng = np.random.default_rng(seed)
    ii, jj = np.mgrid[:n, :n].astype(float)
    body = np.hypot(ii - n / 2, jj - n / 2) < radius
    data = np.full((n, n, K), 300.0)
    data[~body] = 0.0
    return rng, ii, jj, body, data


def _flared_bone_stack(K: int = 30, fat: bool = False, seed: int = 5):
    """A tibia-like bone from slice K-1 down to slice 8 in an axial stack of 5 mm slices, 1 mm pixels.

    Shaft (outer 8 px, marrow 5 px) down to slice 16, then an epiphysis widening to outer 14 px
    at slice 8 (the plafond); a talus-like bone (outer 9 px) right below it, slices 2-7. With
    ``fat``, the body has a subcutaneous fat layer (1400) that the epiphysis touches on one
    side with no cortex there (the distal tibia's subcutaneous face, its cortex too thin to show).
    Returns the Volume, the body mask and the true per-slice areas of the bone.
    """
    rng, ii, jj, body, data = _round_body(120, K, 54.0, seed)
    if fat:
        data[body & (np.hypot(ii - 60, jj - 60) >= 46)] = 1400.0
    ci = 60.0 + (35.0 if fat else 0.0)        # with fat: the epiphysis runs into the layer
    outer = {k: 8.0 for k in range(16, K)}
    outer.update({k: 14.0 - 0.75 * (k - 8) for k in range(8, 16)})
    true_area = np.zeros(K)
    for k, ro in outer.items():
        r = np.hypot(ii - ci, jj - 60)
        bone = body & (r < ro)
        sl = data[:, :, k]
        sl[bone] = 80.0
        sl[body & (r < ro - 3.0)] = 900.0
        if fat:
            sl[bone & (ii > ci) & (np.hypot(ii - 60, jj - 60) >= 44)] = 900.0    # no cortex against the fat
        true_area[k] = bone.sum()
    r = np.hypot(ii - ci, jj - 60)
    for k in range(2, 8):
        data[:, :, k][r < 9.0] = 80.0
        data[:, :, k][r < 6.0] = 900.0
    data += rng.normal(0, 8, data.shape)
    vol = Volume(data.astype(np.float32), np.diag([1.0, 1.0, 5.0, 1.0]))
    return vol, np.repeat(body[:, :, None], K, axis=2), true_area, ci


@pytest.mark.parametrize("fat", [False, True])
def test_a_long_bone_cut_by_its_search_is_followed_to_its_joint(fat):
    """The line ends at slice 20 (its template shorter than the bone): searched 10 mm past it, the
    bone is cut at slice 18. Followed, it is labelled down to its plafond (slice 8) with its true
    sections, and not into the smaller bone lying right under it (the talus, 0.41 of the plafond's
    section). With a fat layer the epiphysis touches without cortex, the whole-slice rule drops
    that marrow with the fat; tracked from the section above, it is kept. A track that runs to its
    limit without reaching the joint followed something else past the bone (the carpals past an
    ulna): it is dropped."""
    from bonecap.segmentation.bones import segment_bones

    K = 30
    vol, body, true_area, ci = _flared_bone_stack(K, fat=fat)
    seeds = {"tibia_r": np.array([[ci, 60.0, (K - 1) * 5.0], [ci, 60.0, 20 * 5.0]])}
    cut, ids = segment_bones(vol, seeds, body_mask=body, progress=False, margin_mm=10.0)
    a_cut = (cut == ids["tibia_r"]).sum(axis=(0, 1))
    assert a_cut[18:].min() > 0 and a_cut[:18].sum() == 0
    got, ids = segment_bones(vol, seeds, body_mask=body, progress=False, margin_mm=10.0,
                             follow_mm={"tibia_r": 60.0})
    area = (got == ids["tibia_r"]).sum(axis=(0, 1))
    assert np.array_equal(area[18:], a_cut[18:])                 # what the search found is unchanged
    assert area[:8].sum() == 0                                   # the talus is not the tibia's
    assert np.all(np.abs(area[8:18] - true_area[8:18]) <= 0.12 * true_area[8:18]), (area[8:18], true_area[8:18])
    if fat:
        # the whole-slice rule on such a slice: the marrow goes with the fat
        one, ids1 = segment_bones(vol, {"tibia_r": np.array([[ci, 60.0, 50.0], [ci, 60.0, 40.0]])}, body_mask=body,
                                  progress=False, margin_mm=0.0)
        assert (one == ids1["tibia_r"]).sum(axis=(0, 1))[8:11].sum() < 0.3 * true_area[8:11].sum()
    # a track that runs to its limit (12 mm here) without reaching a joint is not the bone's end: dropped whole
    short, ids = segment_bones(vol, seeds, body_mask=body, progress=False, margin_mm=10.0,
                               follow_mm={"tibia_r": 12.0})
    assert np.array_equal(short, cut)


def _tipped_bone_stack(K: int = 30, seed: int = 7, beside_tip: bool = False):
    """A fibula-like bone from slice K-1 down to its point in an axial stack of 5 mm slices, 1 mm pixels.

    Shaft (outer 8 px, cortex 3 px) down to slice 12, a malleolus widening to outer 12 px at slices 8-9,
    then its tip narrowing (outer 7 px at slice 7, 4.5 px at slice 6; cortex 2 px) with nothing below.
    With ``beside_tip``, bright tissue (fat, marrow-bright) lies under the point and grows downwards
    (slice 5 a 3 px disc, slices 4-2 9 px), as at the phantom's malleolus. Returns the Volume, the body
    mask and the true per-slice areas of the bone.
    """
    rng, ii, jj, body, data = _round_body(100, K, 46.0, seed)
    outer = {k: 8.0 for k in range(12, K)}
    outer.update({11: 9.0, 10: 10.5, 9: 12.0, 8: 12.0, 7: 7.0, 6: 4.5})
    true_area = np.zeros(K)
    r = np.hypot(ii - 50, jj - 50)
    for k, ro in outer.items():
        bone = r < ro
        sl = data[:, :, k]
        sl[bone] = 80.0
        sl[r < ro - (3.0 if ro > 7.5 else 2.0)] = 900.0
        true_area[k] = bone.sum()
    if beside_tip:
        for k, rb in {5: 3.0, 4: 9.0, 3: 9.0, 2: 9.0}.items():
            data[:, :, k][r < rb] = 900.0
    data += rng.normal(0, 8, data.shape)
    vol = Volume(data.astype(np.float32), np.diag([1.0, 1.0, 5.0, 1.0]))
    return vol, np.repeat(body[:, :, None], K, axis=2), true_area


@pytest.mark.parametrize("beside_tip", [False, True])
def test_a_followed_bone_s_tip_is_kept_to_its_point(beside_tip):
    """The fibula's line ends at slice 16: searched 10 mm past it, the bone is cut at slice 14 and
    followed down. Where its malleolus narrows to its point the section drops to 0.34 of the largest,
    which stops a track at a joint (slice 8 is the last kept). Given as a tip (``follow_tips``), the
    narrowing sections are the bone's down to its point (slice 6), with their true areas; the bright
    tissue under the point, once it grows again, is not taken. A tibia's drop into a talus that does
    not narrow stays its joint when it is given as a tip."""
    from bonecap.segmentation.bones import segment_bones

    K = 30
    vol, body, true_area = _tipped_bone_stack(K, beside_tip=beside_tip)
    seeds = {"fibula_r": np.array([[50.0, 50.0, (K - 1) * 5.0], [50.0, 50.0, 16 * 5.0]])}
    kw = dict(body_mask=body, progress=False, margin_mm=10.0, follow_mm={"fibula_r": 60.0})
    joint, ids = segment_bones(vol, seeds, **kw)
    a_joint = (joint == ids["fibula_r"]).sum(axis=(0, 1))
    assert a_joint[:8].sum() == 0 and a_joint[8:].min() > 0
    tip, ids = segment_bones(vol, seeds, follow_tips=["fibula_r"], **kw)
    area = (tip == ids["fibula_r"]).sum(axis=(0, 1))
    assert np.array_equal(area[8:], a_joint[8:])                   # above the drop nothing changes
    assert area[:6].sum() == 0                                     # nothing past the point
    assert np.all(np.abs(area[6:8] - true_area[6:8]) <= 0.2 * true_area[6:8]), (area[6:8], true_area[6:8])
    # the plafond over a talus (0.41 of its section, the same size on the slices below): a joint still
    tvol, tbody, _, ci = _flared_bone_stack(K)
    tseeds = {"tibia_r": np.array([[ci, 60.0, (K - 1) * 5.0], [ci, 60.0, 20 * 5.0]])}
    tkw = dict(body_mask=tbody, progress=False, margin_mm=10.0, follow_mm={"tibia_r": 60.0})
    plain, tids = segment_bones(tvol, tseeds, **tkw)
    as_tip, tids = segment_bones(tvol, tseeds, follow_tips=["tibia_r"], **tkw)
    assert np.array_equal(as_tip, plain) and (plain == tids["tibia_r"]).sum(axis=(0, 1))[:8].sum() == 0


def _head_in_socket_stack(seed: int = 11):
    """A femur-like bone in an axial stack of 5 mm slices, 1 mm pixels: a shaft (outer 15 mm, marrow
    11.5) up to a ball head (radius 22 mm, 2.5 mm cortex, centred at z = 70 mm, slice 14), and over the
    head's upper half a socket of another bone (a cup 5-13 mm off the head: cortex, marrow, cortex)
    that goes on upwards as a plate. Returns the Volume, the body mask and the head's centre (i, j, z)."""
    n, K = 180, 22
    rng = np.random.default_rng(seed)
    ii, jj = np.mgrid[:n, :n].astype(float)
    r2 = np.hypot(ii - 90, jj - 90)                           # in-plane mm from the axis
    body = r2 < 85
    data = np.full((n, n, K), 300.0)
    data[~body] = 0.0
    zc = 70.0
    for k in range(K):
        z = 5.0 * k
        sl = data[:, :, k]
        r3 = np.hypot(r2, z - zc)
        shaft = z < zc
        sl[shaft & (r2 < 15.0) | (r3 < 22.0)] = 80.0
        sl[shaft & (r2 < 11.5) | (r3 < 19.5)] = 900.0
        if z > zc - 2.0:                                      # the cup, and the plate above it
            cup = (r3 >= 27.0) & (r3 < 35.0)
            if z > zc + 26.0:
                cup = cup | (r2 < 35.0)
            sl[cup] = 80.0
            sl[cup & (r3 >= 29.5) & (r3 < 32.5) | (z > zc + 28.5) & (r2 < 32.5)] = 900.0
    data += rng.normal(0, 8, data.shape)
    vol = Volume(data.astype(np.float32), np.diag([1.0, 1.0, 5.0, 1.0]))
    return vol, np.repeat(body[:, :, None], K, axis=2), (90.0, 90.0, zc)


def test_a_head_cut_by_its_search_is_followed_into_its_socket():
    """The femur's line starts 25 mm below the head's centre (a template placed from the body's
    extent is that far off): its search stops 5 mm below the centre, and the socket's density rule,
    whose line passes through the head too, takes the head's upper half (the phantoms lost 8-26 mm
    of their femoral and humeral heads so). Followed, the head is the femur's up to its pole, each
    section within 15 % of the ball's; away from the ball every label stays (the socket, the plate
    above the pole)."""
    from bonecap.segmentation.bones import segment_bones

    vol, body, (ci, cj, zc) = _head_in_socket_stack()
    seeds = {"femur_r": np.array([[ci, cj, zc - 25.0], [ci, cj, 0.0]]),
             "hip_r": np.array([[ci, cj, zc + 90.0], [ci, cj, zc + 28.0]])}
    kc = int(zc / 5)
    cut, ids = segment_bones(vol, seeds, body_mask=body, progress=False, margin_mm=20.0)
    f_cut = (cut == ids["femur_r"]).sum(axis=(0, 1))
    assert f_cut[kc:].sum() == 0 and f_cut[kc - 1] > 0
    assert cut[90, 90, kc + 2] == ids["hip_r"]                   # the socket's rule took the head
    got, ids = segment_bones(vol, seeds, body_mask=body, progress=False, margin_mm=20.0,
                             follow_head_mm={"femur_r": 60.0})
    f = (got == ids["femur_r"]).sum(axis=(0, 1))
    assert np.array_equal(f[:kc], f_cut[:kc])                    # what the search found is unchanged
    for k in range(kc, kc + 4):              # z = 70 .. 85 mm (at 90 the cap is all cortex: no marrow to track)
        ball = np.pi * (22.0 ** 2 - (5.0 * k - zc) ** 2)
        assert abs(f[k] - ball) <= 0.15 * ball, (k, f[k], ball)
    assert f[kc + 5:].sum() == 0                                 # the pole is at 92 mm
    # away from the ball (the cup, the plate above the pole) every label stays as it was
    ii, jj, kk = np.mgrid[:180, :180, :22].astype(float)
    away = np.sqrt((ii - ci) ** 2 + (jj - cj) ** 2 + (5.0 * kk - zc) ** 2) > 24.0
    assert np.array_equal(got[away & (kk >= kc)], cut[away & (kk >= kc)])
    assert got[90, 90, kc + 6] == ids["hip_r"]


def test_only_the_ankles_long_bones_are_followed_past_their_search():
    """bone_seeds names the tibiae and fibulae (their ends at the ankle, where the talus's smaller
    section stops the track) with 15 % of their joint-to-joint length; not the radius and ulna (the
    carpals past them are as large as their ends), nor the femur and humerus (a long bone's line
    goes on past their distal joints). The femurs' and humeri's heads are followed into their sockets."""
    from bonecap.build_mri import FOLLOW_FRACTION, bone_seeds
    from bonecap.skeleton.template import load_template

    sk = load_template("default")
    followed: dict[str, float] = {}
    seeds = bone_seeds(sk, np.eye(4), followed=followed)
    assert set(followed) == {"tibia_r", "tibia_l", "fibula_r", "fibula_l"}
    tib = sk.bones["tibia_r"]
    length = np.linalg.norm(tib.landmark_in_world("ankle") - tib.landmark_in_world("knee"))
    assert followed["tibia_r"] == pytest.approx(FOLLOW_FRACTION * length)
    # the heads followed into their sockets: the femurs' and humeri's proximal ends, 15 % of their length
    heads: dict[str, float] = {}
    bone_seeds(sk, np.eye(4), heads=heads)
    assert set(heads) == {"femur_r", "femur_l", "humerus_r", "humerus_l"}
    fem = sk.bones["femur_l"]
    assert heads["femur_l"] == pytest.approx(
        FOLLOW_FRACTION * np.linalg.norm(fem.landmark_in_world("knee") - fem.landmark_in_world("hip")))
    # the lines themselves do not depend on either
    assert all(np.array_equal(seeds[n], v) for n, v in bone_seeds(sk, np.eye(4)).items())


def test_a_single_slice_lost_inside_a_long_bone_is_tracked_from_its_neighbours():
    """A shaft whose cortex on one slice does not show where it touches a subcutaneous fat layer: the
    whole-slice rule drops that slice's marrow with the fat and leaves a hole in the bone; tracked from
    the section before and continuing both neighbours, the section is filled in (within 12 % of its true
    area), and no slice is added anywhere else."""
    from bonecap.segmentation.bones import segment_bones

    n, K = 120, 21
    rng = np.random.default_rng(7)
    ii, jj = np.mgrid[:n, :n].astype(float)
    rb = np.hypot(ii - 60, jj - 60)
    body = rb < 54
    data = np.full((n, n, K), 300.0)
    data[~body] = 0.0
    data[body & (rb >= 46)] = 1400.0
    ci = 95.0
    r = np.hypot(ii - ci, jj - 60)
    bone = body & (r < 12.0)
    for k in range(K):
        sl = data[:, :, k]
        sl[bone] = 80.0
        sl[body & (r < 9.0)] = 900.0
        if k == 10:
            sl[bone & (ii > ci) & (rb >= 44)] = 900.0            # no cortex against the fat here
    data += rng.normal(0, 8, data.shape)
    vol = Volume(data.astype(np.float32), np.diag([1.0, 1.0, 5.0, 1.0]))
    body3 = np.repeat(body[:, :, None], K, axis=2)
    seeds = {"tibia_r": np.array([[ci, 60.0, (K - 1) * 5.0], [ci, 60.0, 0.0]])}
    lab, ids = segment_bones(vol, seeds, body_mask=body3, progress=False)
    area = (lab == ids["tibia_r"]).sum(axis=(0, 1))
    assert area.min() > 0
    assert abs(area[10] - bone.sum()) <= 0.12 * bone.sum(), (area[10], bone.sum())
    # the whole-slice rule alone on that slice (searched there only): nothing, or the fat with it
    one, ids1 = segment_bones(vol, {"tibia_r": np.array([[ci, 60.0, 50.0]])}, body_mask=body3, progress=False,
                              margin_mm=0.0)
    assert (one == ids1["tibia_r"]).sum() < 0.3 * bone.sum() or (one == ids1["tibia_r"]).sum() > 2 * bone.sum()
