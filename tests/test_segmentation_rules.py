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
