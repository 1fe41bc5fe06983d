"""The density rule's bones refined from a prior section by the image, on analytic slices."""

from __future__ import annotations

import numpy as np
import pytest

from bonecap.model import Volume
from bonecap.segmentation import density, refine

MUSCLE, MARROW, FAT = 100.0, 230.0, 250.0


def _dice(a, b):
    return 2 * (a & b).sum() / (a.sum() + b.sum())


def _plate_slice(seed: int = 0, ss: int = 4, n: int = 96):
    """A slice through an iliac wing: a thin cortical plate (signal void) 3 px thick and 56 px long in
    muscle, a marrow-filled rim at one end (bright inside 1 px of cortex), subcutaneous fat round the body;
    drawn ``ss`` times finer and averaged (partial volume), light noise. Returns (image, body, bone):
    ``bone`` the pixels at least half bone."""
    rng = np.random.default_rng(seed)
    N = n * ss
    y, x = (np.mgrid[0:N, 0:N] + 0.5) / ss
    c = n / 2
    r = np.hypot(x - c, y - c)
    fine = np.where(r < 44, MUSCLE, 0.0)
    fine[(r >= 40) & (r < 44)] = FAT
    # the plate along a slanted line, 3 px thick
    u = ((x - 20) + (y - 26)) / np.sqrt(2)        # along
    v = (-(x - 20) + (y - 26)) / np.sqrt(2)       # across
    plate = (u > 0) & (u < 56) & (np.abs(v) < 1.5)
    # the marrow-filled end: a disc of radius 5 px at the plate's end, 1 px of cortex round its marrow
    ex, ey = 20 + 56 / np.sqrt(2), 26 + 56 / np.sqrt(2)
    re = np.hypot(x - ex, y - ey)
    end = re < 5
    bone_fine = plate | end
    fine[bone_fine] = 0.0
    fine[re < 4] = MARROW
    img = fine.reshape(n, ss, n, ss).mean(axis=(1, 3))
    frac = bone_fine.reshape(n, ss, n, ss).mean(axis=(1, 3))
    body = (r < 44).reshape(n, ss, n, ss).mean(axis=(1, 3)) >= 0.5
    img = img + rng.normal(0, 3.0, img.shape)
    return img, body, frac >= 0.5


def test_a_plate_the_density_rule_finds_in_part_is_refined_from_a_prior_two_pixels_off():
    """The density rule keeps the marrow nearest its seed (the plate's cortex is no candidate: Dice < 0.5);
    a prior section two pixels off (a warp's ~2-3 mm; 1.4 px across the slanted plate) scores ~0.6;
    refined, > 0.85 and better than both."""
    img, body, bone = _plate_slice()
    seed = np.argwhere(bone)[-1].astype(float)
    rule = density.density_threshold_slice(img, seed, 1.0, body)
    prior = np.roll(bone, 2, axis=0)
    ev = refine.bone_evidence(img, body, 1.0)
    got = refine.refine_section(prior, ev)
    assert _dice(rule, bone) < 0.5
    assert _dice(got, bone) > 0.85
    assert _dice(prior, bone) < 0.7
    assert _dice(got, bone) > _dice(prior, bone) + 0.2
    # the fat round the body is bright like marrow, but it is no bone: nothing of it is taken
    assert not (got & ~bone & (img > MUSCLE * 1.5)).any()


def test_a_prior_over_muscle_keeps_only_its_interior():
    """A prior section where the image shows plain muscle (the subcutaneous fat round it): its edge goes (no bone tissue looks like
    muscle), its interior ``core_px`` in from the edge stays (red marrow is intermediate on T1 and must not
    be cut out); with ``core_px=0`` nothing is left."""
    rng = np.random.default_rng(2)
    n = 80
    y, x = np.mgrid[0:n, 0:n]
    r = np.hypot(x - 40, y - 40)
    body = r < 36
    img = np.where(body, MUSCLE, 0.0) + rng.normal(0, 2.0, (n, n))
    img[(r >= 28) & body] = FAT          # a third of the body and more: the candidates are the fat
    prior = np.hypot(x - 40, y - 40) < 9
    ev = refine.bone_evidence(img, body, 1.0)
    got = refine.refine_section(prior, ev, core_px=2)
    from scipy import ndimage
    core = ndimage.binary_erosion(prior, np.ones((3, 3), bool), iterations=2)
    assert np.array_equal(got, core)
    assert not refine.refine_section(prior, ev, core_px=0).any()


def test_only_the_bone_s_own_marrow_rim_is_taken_not_the_rim_of_fat_beside_it():
    """A bone (bright marrow in 2 px of cortex) with a 1-px band of muscle between its cortex and a pad of fat:
    the band is on the fat's rim (a partial-volume edge like a marrow's) but borders no marrow of the bone, so
    a prior that is right stays right; the band pixels next to its marrow-filled end, where the cortex is thin,
    are its own rim. Every marrow's rim as evidence put the band into the bone."""
    ss, n = 4, 64
    N = n * ss
    y, x = (np.mgrid[0:N, 0:N] + 0.5) / ss
    r = np.hypot(x - 32, y - 32)
    fine = np.where(r < 30, MUSCLE, 0.0)
    bone_fine = r < 10
    fine[bone_fine] = 0.0                          # cortex 2 px thick
    fine[r < 8] = MARROW
    fine[(r >= 11) & (r < 16) & (x > 32)] = FAT    # the fat pad beside it, one pixel of muscle between
    fine[(r >= 22) & (r < 30)] = FAT               # subcutaneous fat: the top third of the body is fat and marrow
    img = fine.reshape(n, ss, n, ss).mean(axis=(1, 3))
    bone = bone_fine.reshape(n, ss, n, ss).mean(axis=(1, 3)) >= 0.5
    body = (r < 30).reshape(n, ss, n, ss).mean(axis=(1, 3)) >= 0.5
    img = img + np.random.default_rng(4).normal(0, 2.0, img.shape)
    ev = refine.bone_evidence(img, body, 1.0)
    from scipy import ndimage
    eight = np.ones((3, 3), bool)
    # the bone's outer pixels on the fat's side that look like neither marrow nor cortex, all on the fat's rim
    band = ndimage.binary_dilation(bone, eight) & ~bone & ~ev.marrow & ~ev.cortex & (x[::ss, ::ss] > 34)
    assert band.sum() >= 5
    assert not (band & ~ndimage.binary_dilation(ev.marrow & ~bone, eight)).any()
    got = refine.refine_section(bone, ev)
    assert not (got & band).any()
    assert _dice(got, bone) > 0.95        # what it adds is the fat's partial-volume pixels (marrow-bright)


def test_refine_labels_keeps_the_long_bones_and_the_other_priors():
    """On a stack: the kept labels (a long bone) are copied and never taken; a refined bone takes no pixel of
    another bone's prior; a bone not refined keeps its prior where free; ids are the prior's."""
    img, body, bone = _plate_slice(seed=3)
    K = 3
    vol = Volume(np.repeat(img[:, :, None], K, axis=2), np.eye(4))
    bodies = np.repeat(body[:, :, None], K, axis=2)
    prior = np.zeros(vol.data.shape, np.uint16)
    prior[np.repeat(np.roll(bone, 2, axis=0)[:, :, None], K, axis=2)] = 7      # the plate, refined
    other = np.zeros(bone.shape, bool)
    other[10:16, 40:50] = True
    prior[other] = 9                                                            # another bone's prior
    keep = np.zeros(vol.data.shape, np.int16)
    keep[5:9, 40:50, :] = 3                                                     # a long bone's section
    out = refine.refine_labels(vol, prior, {"hip_r": 7}, keep=keep, body_mask=bodies)
    assert out.dtype == np.uint16 and out.shape == vol.data.shape
    assert np.array_equal(out[keep > 0], keep[keep > 0])
    assert np.array_equal(out[:, :, 1] == 9, other)
    for k in range(K):
        assert _dice(out[:, :, k] == 7, bone) > 0.85
    assert set(np.unique(out)) == {0, 3, 7, 9}


def test_refine_input_checks():
    img, body, bone = _plate_slice()
    vol = Volume(img[:, :, None], np.eye(4))
    with pytest.raises(ValueError, match="pixel_mm"):
        refine.bone_evidence(img, body, 0.0)
    with pytest.raises(ValueError, match="dark_fraction"):
        refine.bone_evidence(img, body, 1.0, dark_fraction=1.5)
    with pytest.raises(ValueError, match="shape"):
        refine.bone_evidence(img, body[:-1], 1.0)
    ev = refine.bone_evidence(img, body, 1.0)
    with pytest.raises(ValueError, match="core_px"):
        refine.refine_section(bone, ev, core_px=-1)
    with pytest.raises(ValueError, match="BoneEvidence"):
        refine.refine_section(bone, (bone, bone, bone, bone))
    with pytest.raises(ValueError, match="evidence.marrow"):
        refine.refine_section(bone, refine.BoneEvidence(bone[:-1], *ev[1:]))
    with pytest.raises(ValueError, match="Volume"):
        refine.refine_labels(img, bone, {"hip_r": 1})
    with pytest.raises(ValueError, match="prior must have the volume's shape"):
        refine.refine_labels(vol, bone, {"hip_r": 1}, body_mask=body[:, :, None])
    with pytest.raises(ValueError, match="1..65535"):
        refine.refine_labels(vol, bone[:, :, None].astype(int), {"hip_r": 0}, body_mask=body[:, :, None])
    with pytest.raises(ValueError, match="unknown option"):
        refine.refine_labels(vol, bone[:, :, None].astype(int), {"hip_r": 1}, body_mask=body[:, :, None],
                             dark=0.4)
