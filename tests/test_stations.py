"""Tests of whole-body station ordering, registration and intensity normalisation (bonecap.stations).

Truth comes from the renderer: a scene is imaged as overlapping stations with
known patient motions ``true_to_nominal`` (``render_volume(motion=...)``) and
known intensity scales, and from the tiny phantom's ``truth/stations.json``.
A correction ``C_s`` is right when ``C_s @ T_s`` is the same rigid transform
for every station (the gauge); the residual between consecutive stations is
``inv(C_s T_s) @ C_t T_t``, measured in mm at body points and in degrees.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from bonecap.io.imaging import read_volumes
from bonecap.model import Mesh, Volume
from bonecap.phantom.mri import render_volume
from bonecap.stations import normalise_intensity, order_stations, register_stations, station_z_range


def _mesh(tm: trimesh.Trimesh) -> Mesh:
    return Mesh(tm.vertices, tm.faces, "lps")


def _oblique_rod(r, p0, p1):
    """A cylinder from p0 to p1 (trimesh's segment form)."""
    return trimesh.creation.cylinder(radius=r, segment=np.array([p0, p1], float), sections=64)


def _taper(tm: trimesh.Trimesh, rate: float) -> trimesh.Trimesh:
    """Scale x and y by ``1 + rate * z``: a body whose outline changes along z, as a real one does."""
    v = tm.vertices.copy()
    v[:, :2] *= (1.0 + rate * v[:, 2])[:, None]
    return trimesh.Trimesh(v, tm.faces, process=False)


def _scene():
    """A trunk with structure along z: tapering outline, oblique bones, blobs every ~2 cm."""
    body = trimesh.creation.cylinder(radius=70.0, height=320.0, sections=128)
    body.apply_scale([1.0, 0.75, 1.0])
    muscle = trimesh.creation.cylinder(radius=55.0, height=316.0, sections=128)
    muscle.apply_scale([1.0, 0.7, 1.0])
    layers = [(_mesh(_taper(body, 0.0015)), "fat"), (_mesh(_taper(muscle, -0.001)), "muscle")]
    for p0, p1, r in (([-50, -10, -150], [10, 20, 150], 11.0), ([45, 15, -150], [15, -25, 150], 9.0)):
        p0, p1 = np.array(p0, float), np.array(p1, float)
        layers.append((_mesh(_oblique_rod(r, p0, p1)), "cortex"))
        layers.append((_mesh(_oblique_rod(r - 4.5, p0 + [0, 0, 2], p1 - [0, 0, 2])), "marrow"))
    # "Vertebrae and organs": spheres along z give the overlaps something to lock onto in z.
    rng = np.random.default_rng(0)
    for z in np.arange(-150.0, 150.0, 22.0):
        ball = trimesh.creation.icosphere(subdivisions=3, radius=float(rng.uniform(6, 11)))
        ball.apply_translation([rng.uniform(-30, 30), rng.uniform(-20, 20), z + rng.uniform(-5, 5)])
        layers.append((_mesh(ball), str(rng.choice(["cortex", "marrow", "fat"]))))
    return layers


def _motion(rng, centre, shift=3.0, deg=1.0):
    ax = rng.normal(size=3)
    R = Rotation.from_rotvec(ax / np.linalg.norm(ax) * math.radians(rng.uniform(0.5, deg))).as_matrix()
    t = rng.normal(size=3)
    t = t / np.linalg.norm(t) * rng.uniform(1.0, shift)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = centre + t - R @ centre
    return T


def _stations(rng, *, n=3, bias=0.15, scales=None, z_top=140.0, length_slices=24, pitch=5.0, pixel=2.0,
              overlap_slices=8):
    layers = _scene()
    I, J = 86, 70
    out, truth = [], []
    for s in range(n):
        z_hi = z_top - s * (length_slices - overlap_slices) * pitch + 0.7 * s   # grids not aligned
        A = np.diag([pixel, pixel, pitch, 1.0])
        A[:3, 3] = [-(I - 1) / 2 * pixel, -(J - 1) / 2 * pixel, z_hi - (length_slices - 1) * pitch]
        centre = A[:3, :3] @ ((np.array([I, J, length_slices]) - 1) / 2) + A[:3, 3]
        T = _motion(rng, centre)
        sc = 1.0 if scales is None else scales[s]
        img = render_volume(layers, A, (I, J, length_slices), slice_thickness_mm=pitch, inplane_supersample=2,
                            through_plane_samples=4, rng=rng, bias=bias, scale=sc, motion=T)
        out.append(Volume(img, A, {"station": f"station_{s + 1}", "slice_thickness": pitch}))
        truth.append(T)
    return out, truth


def _pair_residuals(vols, reports, truths, thr):
    """Residual motion between consecutive stations: max mm at body voxels of the overlap, and degrees."""
    E = [r["correction"] @ T for r, T in zip(reports, truths)]
    mm, deg = [], []
    for s in range(1, len(vols)):
        D = np.linalg.inv(E[s - 1]) @ E[s]
        v = vols[s]
        zlo = station_z_range(vols[s - 1])[0]
        ks = [k for k in range(v.shape[2]) if v.index_to_world(np.array([0.0, 0.0, k]))[2] >= zlo]
        ii, jj, kk = np.nonzero(v.data[:, :, ks] > thr)
        p = v.index_to_world(np.c_[ii, jj, np.asarray(ks)[kk]])
        mm.append(float(np.max(np.linalg.norm(p @ D[:3, :3].T + D[:3, 3] - p, axis=1))))
        deg.append(float(np.degrees(np.linalg.norm(Rotation.from_matrix(D[:3, :3]).as_rotvec()))))
    return np.array(mm), np.array(deg)


@pytest.fixture(scope="module")
def rendered():
    rng = np.random.default_rng(42)
    return _stations(rng, scales=[1.0, 0.8, 1.25])


def test_register_recovers_relative_motion(rendered):
    vols, truths = rendered
    shuffled = [vols[2], vols[0], vols[1]]
    out, rep = register_stations(shuffled)
    assert [v.metadata["station"] for v in out] == ["station_1", "station_2", "station_3"]
    mm, deg = _pair_residuals(out, rep, truths, thr=1000.0)
    # Before: the true relative motions are several mm; after: under half the 2 mm pixel. This
    # scene (a tapering prism with blobs, 8-slice overlaps) pins the tilt less than a body does:
    # measured 0.4-0.6 mm, 0.25-0.3 deg; on the default phantom the residuals are <= 0.4 mm, 0.08 deg.
    before = _pair_residuals(out, [{"correction": np.eye(4)}] * 3, truths, thr=1000.0)[0]
    assert np.all(before > 1.5), before
    assert np.all(mm < 1.0), mm
    assert np.all(deg < 0.5), deg
    # Data untouched, affines corrected.
    assert out[0].data is vols[0].data
    by_name = {w.metadata["station"]: w for w in vols}
    for v, r in zip(out, rep):
        assert np.allclose(v.affine, r["correction"] @ by_name[r["name"]].affine)
        assert r["pair"] is None or (r["pair"]["registered"] and r["pair"]["ncc_after"] > 0.9)


def test_gauges(rendered):
    vols, truths = rendered
    out, rep = register_stations(vols, reference=1)
    assert np.allclose(rep[1]["correction"], np.eye(4))
    out0, rep0 = register_stations(vols)
    # Least-total-correction gauge: the corrected FOV corners stay, on average, where the headers put them.
    from bonecap.stations import _fov_corners

    disp = np.concatenate([_fov_corners(v) @ r["correction"][:3, :3].T + r["correction"][:3, 3] - _fov_corners(v)
                           for v, r in zip(vols, rep0)])
    assert np.linalg.norm(disp.mean(axis=0)) < 1e-6
    # Both gauges differ by one common rigid motion.
    G = [r0["correction"] @ np.linalg.inv(r["correction"]) for r0, r in zip(rep0, rep)]
    assert np.allclose(G[0], G[1], atol=1e-6) and np.allclose(G[0], G[2], atol=1e-6)
    with pytest.raises(ValueError, match="reference"):
        register_stations(vols, reference=3)


def test_normalise_intensity_without_bias():
    rng = np.random.default_rng(3)
    scales = np.array([1.0, 0.7, 1.3])
    vols, truths = _stations(rng, bias=0.0, scales=scales)
    reg, _ = register_stations(vols)
    out, est = normalise_intensity(reg, reference=0)
    assert np.allclose(est, scales / scales[0], rtol=0.01), est
    assert out[1].metadata["intensity_scale"] == pytest.approx(est[1])
    assert np.allclose(out[2].data, vols[2].data / np.float32(est[2]))
    _, est_gm = normalise_intensity(reg)
    assert math.prod(est_gm) == pytest.approx(1.0)
    assert np.allclose(est_gm / est_gm[0], est, rtol=1e-9)


def _box(z_lo, n=10, pitch=5.0, normal_axis=2, name="s"):
    A = np.eye(4)
    if normal_axis == 2:
        A[:3, :3] = np.diag([2.0, 2.0, pitch])
        A[:3, 3] = [0, 0, z_lo]
    else:  # sagittal: slices along x
        A[:3, :3] = np.array([[0, 0, pitch], [2.0, 0, 0], [0, -2.0, 0]], float)
        A[:3, 3] = [0, 0, z_lo + 20]
    return Volume(np.zeros((20, 20, n), np.float32), A, {"station": name})


def test_order_stations_sorts_and_checks():
    a, b, c = _box(100, name="head"), _box(70, name="mid"), _box(40, name="feet")
    assert [v.metadata["station"] for v in order_stations([c, a, b])] == ["head", "mid", "feet"]
    # Slices running feet -> head or head -> feet do not matter.
    flipped = Volume(b.data[:, :, ::-1], b.affine @ np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, -1, 9], [0, 0, 0, 1]]),
                     {"station": "mid"})
    assert station_z_range(flipped) == pytest.approx(station_z_range(b))
    assert [v.metadata["station"] for v in order_stations([flipped, c, a])] == ["head", "mid", "feet"]
    # A gap names both stations.
    with pytest.raises(ValueError, match=r"head.*feet.*gap"):
        order_stations([a, c])
    # Too little overlap (5 mm < 10 mm).
    with pytest.raises(ValueError, match="overlap of only"):
        order_stations([a, _box(60, name="low")])
    assert len(order_stations([a, c], allow_gaps=True)) == 2
    # Another orientation is refused with its plane named.
    with pytest.raises(ValueError, match="sagittal"):
        order_stations([a, _box(70, normal_axis=0, name="sag")])
    with pytest.raises(ValueError, match="at least one"):
        order_stations([])
    with pytest.raises(ValueError, match="not a Volume"):
        order_stations([a, np.zeros((3, 3, 3))])


def test_gap_kept_nominal_when_allowed(rendered):
    vols, _ = rendered
    far = Volume(vols[2].data, vols[2].affine @ np.diag([1, 1, 1, 1.0]) + np.array(
        [[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, -200.0], [0, 0, 0, 0]]), {"station": "far"})
    with pytest.raises(ValueError, match="far"):
        register_stations([vols[0], vols[1], far])
    out, rep = register_stations([vols[0], vols[1], far], allow_gaps=True, reference=1)
    assert rep[2]["pair"]["registered"] is False
    assert np.allclose(rep[2]["correction"], rep[1]["correction"])   # nominal relative geometry kept


# --------------------------------------------------------------------------- #
# the tiny phantom: its truth/stations.json
# --------------------------------------------------------------------------- #
@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    from bonecap.phantom import make_phantom

    out = tmp_path_factory.mktemp("ph_tiny")
    make_phantom(out, seed=1, preset="tiny")
    return out


def test_tiny_phantom_against_truth(tiny):
    st = json.loads((tiny / "truth" / "stations.json").read_text())["stations"]
    vols = []
    for s in st:
        v = read_volumes(tiny / "mri" / s["name"])[0]
        v.metadata["station"] = s["name"]
        vols.append(v)
    out, rep = register_stations(vols[::-1])
    truths = {s["name"]: np.array(s["true_to_nominal"]) for s in st}
    mm, deg = _pair_residuals(out, rep, [truths[r["name"]] for r in rep], thr=1000.0)
    assert np.all(mm < 1.0), mm          # 4 mm pixels, 15 mm slices
    assert np.all(deg < 0.2), deg
    _, est = normalise_intensity(out, reference=0)
    true = np.array([s["intensity_scale"] for s in st])
    # Each station has its own smooth bias field (up to 15 %), which an overlap cannot tell
    # from a gain: the scales agree only to that level.
    assert np.all(np.abs(est / (true / true[0]) - 1) < 0.10), (est, true / true[0])


def test_tiny_phantom_capsules(tiny):
    from bonecap.segmentation.capsules import find_capsules, match_capsules

    fa = json.loads((tiny / "truth" / "forearm.json").read_text())
    for twist, pose in fa["poses"].items():
        v = read_volumes(tiny / pose["folder"])[0]
        found, info = find_capsules(v, radius_mm=fa["capsule_radius_mm"])
        truth = np.array(pose["capsule_centres_lps"])
        idx, dist = match_capsules(found, truth, 5.0, return_index=True)
        assert np.all(idx >= 0) and len(found) == len(truth), (twist, info["rejected"])
        n = v.direction[:, 2]
        e = found[idx] - truth
        assert np.max(np.abs(e @ n)) <= 1.0
        assert np.max(np.linalg.norm(e - np.outer(e @ n, n), axis=1)) <= 1.0
    # The stations carry no capsules: nothing may be found there.
    for s in json.loads((tiny / "truth" / "stations.json").read_text())["stations"]:
        assert len(find_capsules(read_volumes(tiny / "mri" / s["name"])[0])[0]) == 0
