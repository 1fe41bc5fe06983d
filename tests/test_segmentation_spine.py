"""The spine's levels read from the MRI (bonecap.segmentation.spine): dark discs between bright bodies,
matched in order to where the warp's chain put them."""

import numpy as np
import pytest

from bonecap.model import Volume
from bonecap.segmentation.spine import is_disc_joint, match_discs, profile_along_curve, spine_levels

R_ARC = 600.0          # the column bends on a circle in the sagittal plane (a kyphosis)
CENTRE = np.array([0.0, -600.0, 250.0])


def _on_arc(t):
    """Point of the column at arc length t (0 at the vertex, z up)."""
    phi = np.asarray(t, float) / R_ARC
    return np.stack([np.zeros_like(phi), CENTRE[1] + R_ARC * np.cos(phi), CENTRE[2] + R_ARC * np.sin(phi)], -1)


def _discs():
    """True disc centres (arc length): bodies of 17-31 mm, not in any template's proportions."""
    t, out = -200.0, []
    for i in range(16):
        out.append(t)
        t += 6.0 + 24.0 + 7.0 * np.sin(1.3 * i)
    return np.array(out)


def _column_volumes(discs, *, seed=0, split=True):
    """Axial stations (1.5 mm pixels, 5 mm slices) of bright bodies (1.0) with darker discs (0.6) in
    muscle (0.5): rendered at 1 mm through the slice and averaged over each slice's thickness, Gaussian
    noise of 3 %. Two stations overlapping by 40 mm."""
    rng = np.random.default_rng(seed)
    xs = np.arange(-30.0, 30.01, 1.5)
    ys = np.arange(-80.0, 30.01, 1.5)
    zs = np.arange(0.0, 500.0, 1.0)
    X, Y, Z = np.meshgrid(xs, ys, zs, indexing="ij")
    rho = np.hypot(Y - CENTRE[1], Z - CENTRE[2])
    t = R_ARC * np.arctan2(Z - CENTRE[2], Y - CENTRE[1])
    inside = np.hypot(X, rho - R_ARC) < 14.0
    k = np.searchsorted(discs, t)
    near = np.minimum(np.abs(t - discs[np.clip(k - 1, 0, len(discs) - 1)]), np.abs(t - discs[np.clip(k, 0, len(discs) - 1)]))
    img = np.where(inside, np.where(near < 3.0, 0.6, 1.0), 0.5).astype(np.float32)
    slices = img.reshape(len(xs), len(ys), -1, 5).mean(axis=3)        # 5 mm slices, centres at z = 2, 7, ...
    slices += rng.normal(0.0, 0.03, slices.shape).astype(np.float32)

    def station(k0, k1):
        A = np.diag([1.5, 1.5, 5.0, 1.0])
        A[:3, 3] = [xs[0], ys[0], 2.0 + 5.0 * k0]
        return Volume(np.ascontiguousarray(slices[:, :, k0:k1]), A)
    n = slices.shape[2]
    return [station(0, n // 2 + 4), station(n // 2 - 4, n)] if split else [station(0, n)]


def test_match_discs_counts_levels_in_order_past_half_a_vertebra():
    """Dips 25 mm apart, the expected places off by a smooth displacement of up to 14 mm -- more than half
    a level, where the nearest dip is the wrong disc -- one disc invisible and one spurious dip: every seen
    disc gets its own dip (displacement within 0.3 mm), the invisible one none."""
    s = np.arange(0.0, 400.0, 1.0)
    true = 20.0 + 25.0 * np.arange(15)
    shift = 14.0 * np.sin(np.pi * (true - 20.0) / 350.0)        # true minus expected
    expected = true - shift
    seen = np.ones(15, bool)
    seen[6] = False
    prof = np.ones_like(s)
    for m in true[seen]:
        prof -= 0.4 * np.exp(-0.5 * ((s - m) / 2.0) ** 2)
    prof -= 0.2 * np.exp(-0.5 * ((s - (true[10] + 12.0)) / 2.0) ** 2)     # a dip that is no disc
    d, dips = match_discs(s, prof, expected)
    assert len(dips) == 15
    np.testing.assert_allclose(d[seen], shift[seen], atol=0.3)
    assert np.isnan(d[6])
    # the nearest dip would have mislabelled the discs where the displacement passes half a level
    nearest = dips[np.argmin(np.abs(dips[None, :] - expected[:, None]), axis=1)]
    assert np.sum(np.abs(nearest - true)[seen] > 5.0) >= 3


def test_match_discs_input_checks():
    s = np.arange(10.0)
    with pytest.raises(ValueError, match="increasing"):
        match_discs(s, np.ones(10), [5.0, 3.0])
    with pytest.raises(ValueError, match="1-D profiles"):
        match_discs(s, np.ones(9), [5.0])


def test_profile_along_a_curved_column_shows_its_discs():
    """Sampled across two overlapping stations of 5 mm axial slices, along a column bent by 20 deg: the
    profile's dips lie on the true discs within 1.2 mm."""
    discs = _discs()
    vols = _column_volumes(discs)
    pts = _on_arc(np.linspace(-210.0, 230.0, 12))
    s, values, arc = profile_along_curve(vols, pts)
    assert np.all(np.isfinite(values[(s >= 0) & (s <= arc[-1])]))
    d, dips = match_discs(s, values, discs - (-210.0))
    assert np.sum(np.isfinite(d)) >= 15
    assert np.max(np.abs(d[np.isfinite(d)])) < 1.2


def test_spine_levels_move_the_chain_onto_the_discs():
    """A chain spread in the wrong proportions (its joints up to 12 mm from their discs along the column)
    is moved onto the discs the stations show: within 1.5 mm (median <= 1); its two ends and the joint
    without a disc (the atlas's, on top) stay where the anchor and the fixed bone hold them."""
    discs = _discs()
    vols = _column_volumes(discs, seed=1)
    true_t = np.concatenate([discs, [discs[-1] + 20.0]])                # + the atlas's joint, no disc
    off = 12.0 * np.sin(np.pi * (true_t - true_t[0]) / (true_t[-1] - true_t[0]))   # 0 at both ends
    given = _on_arc(true_t - off)
    flags = [True] * len(discs) + [False]
    out, rep = spine_levels(vols, given, flags)
    assert rep["used"], rep
    truth = _on_arc(true_t)
    before = np.linalg.norm(given - truth, axis=1)
    after = np.linalg.norm(out - truth, axis=1)
    assert before.max() > 11.0
    assert np.median(after[1:-1]) <= 1.0 and after[1:-1].max() < 1.5
    np.testing.assert_allclose(out[[0, -1]], given[[0, -1]])


def test_spine_levels_refuses_a_column_without_discs():
    """Bodies and discs alike (no contrast): nothing to count, the chain is left to the warp's spread."""
    discs = _discs()
    vols = _column_volumes(discs)
    for v in vols:
        v.data[:] = np.random.default_rng(2).normal(1.0, 0.02, v.data.shape)
    out, rep = spine_levels(vols, _on_arc(discs), [True] * len(discs))
    assert out is None and not rep["used"] and "discs found" in rep["reason"]


def test_disc_joints_are_between_two_vertebral_bodies():
    assert is_disc_joint(["l5", "sacrum"]) and is_disc_joint(["c2", "c3"]) and is_disc_joint(["t12", "l1"])
    assert not is_disc_joint(["c1", "c2"]) and not is_disc_joint(["c1", "skull"]) and not is_disc_joint(["l5"])


def test_spine_levels_refuses_thick_slices_and_a_slipped_level(monkeypatch):
    """Slices thicker than a disc (10 mm) are not read; a match whose displacement jumps by a vertebra
    between neighbouring discs (a disc taken for its neighbour, as on 10 mm stations of a phantom) is
    refused rather than used."""
    discs = _discs()
    vols = _column_volumes(discs)
    thick = [Volume(v.data[:, :, ::2].copy(), v.affine @ np.diag([1.0, 1.0, 2.0, 1.0])) for v in vols]
    out, rep = spine_levels(thick, _on_arc(discs), [True] * len(discs))
    assert out is None and "too thick" in rep["reason"]
    import bonecap.segmentation.spine as spine

    def slipped(s, values, expected, **kw):
        d = np.where(np.arange(len(expected)) < 8, 3.0, -20.0)      # one level down from the ninth disc on
        return d, np.asarray(expected) + d
    monkeypatch.setattr(spine, "match_discs", slipped)
    out, rep = spine_levels(vols, _on_arc(discs), [True] * len(discs))
    assert out is None and "slipped" in rep["reason"]
    # the same displacement without the jump is used
    monkeypatch.setattr(spine, "match_discs", lambda s, v, e, **kw: (np.full(len(e), 3.0), np.asarray(e) + 3.0))
    out, rep = spine_levels(vols, _on_arc(discs), [True] * len(discs))
    assert rep["used"] and np.allclose(rep["displacement_mm"][1:-1], 3.0)


def test_the_qc_picture_says_whether_the_levels_were_used(tmp_path):
    """qc/spine_levels.png: the profile, the dips, the discs as spread and as matched; the title says
    how many discs were matched and, when refused, why (the template's proportions kept)."""
    from PIL import Image

    from bonecap.qc import spine_levels_plot

    discs = _discs()
    vols = _column_volumes(discs)
    for kw, word in (({}, "moved onto"), ({"min_matched": 1.01}, "not used")):
        prof = {}
        out, rep = spine_levels(vols, _on_arc(discs), [True] * len(discs), profile_out=prof, **kw)
        assert prof["report"] is rep and (out is not None) == rep["used"]
        assert rep["used"] == (word == "moved onto")
        p = spine_levels_plot(tmp_path / f"s{len(kw)}.png", prof)
        w, h = Image.open(p).size
        assert w > 2 * h                    # a wide strip along the column
        px = np.asarray(Image.open(p).convert("RGB"), float)
        green = (px[..., 1] > 100) & (px[..., 0] < 80) & (px[..., 2] < 80)
        assert green.sum() > 50             # the matched discs are drawn


def test_a_real_lumbar_spine_keeps_its_discs_under_a_wrong_spread(shared_data):
    """Real anatomy: the TotalSegmentator example CT (abdomen-pelvis, 3 mm voxels) with its vertebra
    masks (reference outputs). CT shows the bodies brighter than the discs, as marrow does on T1 MRI.
    A chain through the five lumbar discs (L5/L4 to T12/T11, from where the masks' bodies meet) finds
    them within 4 mm; spread 6-10 mm wrong along the column (a shift, a ramp, a bulge), it is put back
    within 2.5 mm of where the right chain's discs were found."""
    from scipy.interpolate import make_interp_spline

    from bonecap.io.imaging import read_nifti

    d = shared_data / "mri" / "ct_pelvis_totalseg"
    ct = read_nifti(d / "example_ct.nii.gz")
    names = ["L5", "L4", "L3", "L2", "L1", "T12", "T11"]
    pts = {}
    for n in names:
        m = read_nifti(d / "bone_masks_v1" / f"vertebrae_{n}.nii.gz")
        p = np.argwhere(m.data > 0) @ m.affine[:3, :3].T + m.affine[:3, 3]
        pts[n] = p
    discs = []
    for lo, hi in zip(names[:-1], names[1:]):
        c = 0.5 * (pts[lo].mean(0) + pts[hi].mean(0))
        # the bodies lie ~10 mm anterior (-y in LPS) of the whole vertebrae's centroids (their arches behind)
        def body(p):
            return p[np.abs(p[:, 1] - (p[:, 1].mean() - 10.0)) < 12.0]
        z = 0.5 * (body(pts[lo])[:, 2].max() + body(pts[hi])[:, 2].min())
        discs.append([c[0], c[1] - 10.0, z])
    discs = np.array(discs)
    s, values, arc = profile_along_curve([ct], discs)
    found, _ = match_discs(s, values, arc)
    assert np.all(np.isfinite(found[:5])) and np.max(np.abs(found[:5])) < 4.0, found
    right = make_interp_spline(arc, discs, k=3, bc_type="natural")
    at = right(arc + np.nan_to_num(found))
    for off in (np.full(len(arc), 6.0), np.linspace(0.0, 10.0, len(arc)), 8.0 * np.sin(np.linspace(0, np.pi, len(arc)))):
        given = right(arc - off)
        out, rep = spine_levels([ct], given, [True] * len(arc))
        assert rep["used"], rep
        err = np.linalg.norm(out - at, axis=1)[1:-1]
        before = np.linalg.norm(given - at, axis=1)[1:-1]
        assert err.max() < 2.5 and before.max() > 5.0, (err, before)
