"""``bonecap phantom`` end to end (tiny preset): every output exists and agrees with the truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bonecap.io.c3d import read_c3d
from bonecap.io.imaging import read_dicom_series, read_nifti
from bonecap.io.mesh import read_mesh
from bonecap.phantom import PRESETS


@pytest.fixture(scope="module")
def phantom(tmp_path_factory):
    from bonecap.cli import main

    out = tmp_path_factory.mktemp("phantom")
    assert main(["phantom", "-o", str(out), "--preset", "tiny", "--seed", "3", "--marker-capsules"]) == 0
    return out


def test_marker_capsules_touch_the_skin_under_the_markers(phantom):
    import trimesh

    summary = json.loads((phantom / "phantom.json").read_text())
    caps = json.loads((phantom / "truth" / "marker_capsules.json").read_text())
    import yaml

    markers = yaml.safe_load((phantom / "truth" / "marker_binding.yaml").read_text())["markers"]
    assert set(caps["centres_lps"]) == set(markers) and summary["marker_capsules"] == len(markers)
    skin = read_mesh(phantom / "truth" / "meshes" / "skin.ply")
    tm = trimesh.Trimesh(skin.vertices, skin.faces, process=False)
    c = np.array(list(caps["centres_lps"].values()))
    _, dist, _ = trimesh.proximity.closest_point(tm, c)
    # one capsule radius off the skin (a few sit in a crease, nearer to another patch of skin)
    assert np.median(np.abs(dist - caps["capsule_radius_mm"])) < 0.3
    assert (np.abs(dist - caps["capsule_radius_mm"]) < 1.0).mean() > 0.9
    assert not tm.contains(c).any()                     # outside the body


def test_summary_and_layout(phantom):
    summary = json.loads((phantom / "phantom.json").read_text())
    assert summary["seed"] == 3 and summary["preset"] == "tiny"
    assert len(summary["stations"]) == PRESETS["tiny"]["n_stations"]
    for name in ("README.md", "labels.json", "stations.json", "forearm.json", "skeleton.json", "subject.json",
                 "marker_binding.yaml"):
        assert (phantom / "truth" / name).is_file(), name


def test_stations_are_dicom_with_bounded_patient_motion(phantom):
    truth = json.loads((phantom / "truth/stations.json").read_text())["stations"]
    uids = set()
    for st in truth:
        vols = read_dicom_series(phantom / "mri" / st["name"])
        assert len(vols) == 1
        v = vols[0]
        uids.add(v.metadata["series_uid"])
        assert list(v.shape) == st["shape"]
        assert np.allclose(v.affine, st["affine_voxel_to_lps"], atol=1e-3)
        assert 0 < st["shift_mm"] <= 3.0 + 1e-9 and 0 <= st["rotation_deg"] <= 1.0 + 1e-9
        T = np.array(st["true_to_nominal"])
        assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
        # the oracle labels sit voxel for voxel on the station's grid
        lab = read_nifti(phantom / "truth/labels" / f"{st['name']}_oracle.nii.gz")
        assert lab.shape == v.shape and np.allclose(lab.affine, v.affine, atol=1e-3)
        assert lab.data.max() > 0
        # no single threshold reads the bones off the image (cortex dark, marrow below fat)
        bone = lab.data > 0
        best = 0.0
        for thr in np.percentile(v.data[v.data > 0], np.arange(5, 100, 5)):
            for seg in (v.data > thr, (v.data < thr) & (v.data > 0)):
                best = max(best, 2 * np.sum(seg & bone) / (seg.sum() + bone.sum()))
        assert best < 0.8, best
    assert len(uids) == len(truth)


def test_truth_meshes_and_labels_agree(phantom):
    ids = json.loads((phantom / "truth/labels.json").read_text())["ids"]
    assert {"femur_r", "tibia_r", "humerus_r", "radius_r", "ulna_r", "hip_r", "l3"} <= set(ids)
    femur = read_mesh(phantom / "truth/meshes/femur_r.ply")
    merged = read_nifti(phantom / "truth/labels/merged.nii.gz")
    # The femur's vertices fall on (or next to) femur-labelled voxels of the merged volume.
    ijk = np.round(merged.world_to_index(femur.vertices)).astype(int)
    inside = np.all((ijk >= 0) & (ijk < np.array(merged.shape)), axis=1)
    near = merged.data[tuple(ijk[inside].T)]
    assert np.mean(near == ids["femur_r"]) > 0.3


def test_forearm_stacks_and_capsules(phantom):
    fa = json.loads((phantom / "truth/forearm.json").read_text())
    assert sorted(float(k) for k in fa["poses"]) == [0.0, 99.5, 172.1]
    ends0 = np.array(fa["poses"]["0"]["radioulnar_axis_lps"])
    for name, pose in fa["poses"].items():
        v = read_dicom_series(phantom / pose["folder"])[0]
        c = np.array(pose["capsule_centres_lps"])
        at_markers = pose["marker_capsules_lps"]
        assert len(c) == PRESETS["tiny"]["n_capsules"] + len(at_markers)
        # the capsules at marker spots are the last rows
        np.testing.assert_allclose(c[len(c) - len(at_markers):], np.array(list(at_markers.values())).reshape(-1, 3))
        # capsules lie inside the stack's field of view
        ijk = v.world_to_index(c)
        assert np.all((ijk > -1) & (ijk < np.array(v.shape)))
        ends = np.array(pose["radioulnar_axis_lps"])
        assert np.linalg.norm(ends - ends0, axis=1).max() < 10.0  # the axis migrates only a little
    assert fa["poses"]["0"]["capsule_centres_lps"] != fa["poses"]["172.1"]["capsule_centres_lps"]


def test_forearm_capsules_at_the_marker_spots(phantom):
    """The forearm stacks' marker capsules lie under the trials' markers, carried with their bones."""
    import yaml

    fa = json.loads((phantom / "truth/forearm.json").read_text())
    bones = json.loads((phantom / "truth/skeleton.json").read_text())["bones"]
    markers = yaml.safe_load((phantom / "truth" / "marker_binding.yaml").read_text())["markers"]
    seen = set()
    for name, pose in fa["poses"].items():
        moved = pose["bone_to_lps"]
        v = read_dicom_series(phantom / pose["folder"])[0]
        for m, c in pose["marker_capsules_lps"].items():
            # the stack was planned to hold the capsule whole, a slice's reach included
            ijk = v.world_to_index(np.array([c]))[0]
            reach = fa["capsule_radius_mm"] / np.asarray(v.spacing)
            assert np.all(ijk - reach >= -0.5) and np.all(ijk + reach <= np.array(v.shape) - 0.5), (name, m)
            b = markers[m]["bone"]
            T = np.array(moved.get(b, bones[b]["bone_to_lps"]))
            marker = T[:3, :3] @ np.array(markers[m]["local_mm"]) + T[:3, 3]
            # capsule and marker touch the skin at one spot: centres a marker-minus-capsule radius apart
            assert np.linalg.norm(marker - np.array(c)) == pytest.approx(7.0 - fa["capsule_radius_mm"], abs=0.05), (
                name, m)
            seen.add(m)
    # the wrist pair that the forearm's twist is read on, in the reference stack at least
    assert {"RWRA", "RWRB"} <= set(fa["poses"]["0"]["marker_capsules_lps"])
    assert "RWRA" in fa["poses"]["172.1"]["marker_capsules_lps"]
    assert {"RWRA", "RWRB", "RELB"} <= seen


def test_trials_read_back_with_their_truth(phantom):
    for trial in ("static", "walk", "arm_raise", "pronation", "touch"):
        t = read_c3d(phantom / "trials" / f"{trial}.c3d")
        truth = np.load(phantom / "truth" / f"{trial}_poses.npz")
        F, B = truth["valid"].shape
        assert t.n_frames == F == len(truth["times"]) and truth["transforms"].shape == (F, B, 4, 4)
        assert truth["times"][0] == 0.0
        assert set(truth["markers"]) == set(t.labels)
        order = [list(truth["markers"]).index(lab) for lab in t.labels]
        err = t.points - truth["marker_truth"][:, order]
        # what was written is the truth plus the artefact and noise: within a few cm, never more
        assert np.nanmax(np.linalg.norm(err, axis=2)) < 30.0


def test_bad_stature_is_a_clean_error(tmp_path, cli):
    res = cli("phantom", "-o", tmp_path / "p", "--preset", "tiny", "--stature", "5")
    assert res.returncode == 1 and res.stderr.startswith("bonecap: error:")
    assert not (tmp_path / "p").exists()


def test_run_beside_returns_the_childs_result_and_raises_its_error(monkeypatch):
    """The trials stage runs in a forked child: its result comes back, its error is raised here,
    and with BONECAP_WORKERS=1 it runs in this process (same result)."""
    import os

    from bonecap.errors import DataError
    from bonecap.phantom import run_beside

    parent = os.getpid()
    monkeypatch.setenv("BONECAP_WORKERS", "2")        # a child even on a one-CPU machine
    job = run_beside(lambda: (os.getpid(), np.arange(5)))
    pid, arr = job()
    assert pid != parent and np.array_equal(arr, np.arange(5))

    def boom():
        raise DataError("no marker RTHI in the set")
    job = run_beside(boom)
    with pytest.raises(DataError, match="RTHI"):
        job()
    monkeypatch.setenv("BONECAP_WORKERS", "1")
    pid, _ = run_beside(lambda: (os.getpid(), None))()
    assert pid == parent


def test_trials_made_after_the_subject_equal_the_trials_made_beside_the_mri(phantom, tmp_path, monkeypatch):
    """The default preset makes its trials after the subject, in a child that ends before the MRI starts
    (its memory target), the tiny one in a child beside the MRI: the same C3D files and truth poses
    either way. Likewise its forearm stacks, after the stations in this process or beside them in a
    child (their own random stream): the same images and truth."""
    import os

    import bonecap.phantom.trials as trials_module
    from bonecap.phantom import PRESETS, make_phantom

    pids = tmp_path / "pids"
    library = trials_module.make_trials

    def recorded(*args, **kwargs):                  # which process made the trials
        pids.write_text(str(os.getpid()))
        return library(*args, **kwargs)

    monkeypatch.setattr(trials_module, "make_trials", recorded)
    monkeypatch.delenv("BONECAP_WORKERS", raising=False)
    monkeypatch.setitem(PRESETS["tiny"], "trials_beside", False)
    monkeypatch.setitem(PRESETS["tiny"], "forearm_beside", False)
    out = tmp_path / "here"
    make_phantom(out, seed=3, preset="tiny", marker_capsules=True)
    assert int(pids.read_text()) != os.getpid()
    assert json.loads((out / "truth/forearm.json").read_text()) == json.loads(
        (phantom / "truth/forearm.json").read_text())
    for stack in sorted((phantom / "mri").glob("forearm_*")):
        a, b = read_dicom_series(stack)[0], read_dicom_series(out / "mri" / stack.name)[0]
        assert np.array_equal(a.data, b.data) and np.allclose(a.affine, b.affine), stack.name
    c3ds = sorted(p.name for p in (phantom / "trials").glob("*.c3d"))
    assert len(c3ds) >= 5 and c3ds == sorted(p.name for p in (out / "trials").glob("*.c3d"))
    for name in c3ds:
        assert (out / "trials" / name).read_bytes() == (phantom / "trials" / name).read_bytes(), name
    for f in sorted((phantom / "truth").glob("*_poses.npz")):
        a, b = np.load(f), np.load(out / "truth" / f.name)
        assert a.files == b.files
        for k in a.files:
            np.testing.assert_array_equal(a[k], b[k], err_msg=f"{f.name}:{k}")


def test_a_failure_stops_the_children_writing(tmp_path, monkeypatch):
    """The trials and the forearm stacks run in forked children beside the stations (tiny preset): when
    the stations fail, make_phantom raises and the children are stopped, not left writing into OUT_DIR."""
    import multiprocessing as mp
    import time

    import bonecap.phantom.mri as mri_module
    from bonecap.phantom import make_phantom

    def broken(*args, **kwargs):
        raise RuntimeError("the stations failed")

    monkeypatch.setattr(mri_module, "render_stations", broken)
    monkeypatch.setenv("BONECAP_WORKERS", "2")
    out = tmp_path / "p"
    with pytest.raises(RuntimeError, match="stations failed"):
        make_phantom(out, seed=1, preset="tiny")
    assert mp.active_children() == []
    written = sorted(str(f) for f in out.rglob("*"))
    time.sleep(2.0)                                  # nothing goes on writing
    assert sorted(str(f) for f in out.rglob("*")) == written


def test_forearm_stage_on_the_stacks_truth(phantom):
    """build-subject's forearm stage fed the stacks' true bone poses and capsules (a stand-in for their
    registration): a wrist marker bound 6 mm off is bound again where its capsules say, the radius's axis
    comes out on the phantom's radio-ulnar axis, and the model goes through the subject file's dict."""
    import yaml

    from bonecap.build_mri import fit_forearm_from_stacks
    from bonecap.motion.forearm import FOREARM_MARKERS, ForearmModel, forearm_twist
    from bonecap.subject import MarkerBinding
    from test_motion_lsq import skeleton_from_truth

    truth = phantom / "truth"
    sk = skeleton_from_truth(truth)
    for b in ("ulna_r", "radius_r", "humerus_r"):
        sk.bones[b].mesh = read_mesh(truth / "meshes" / f"{b}.ply").transformed(
            np.linalg.inv(sk.bones[b].bone_to_world), "bone")
    skin = read_mesh(truth / "meshes" / "skin.ply")
    fa = json.loads((truth / "forearm.json").read_text())
    doc = yaml.safe_load((truth / "marker_binding.yaml").read_text())["markers"]
    markers = {n: MarkerBinding(n, m["bone"], np.array(m["local_mm"]), "static") for n, m in doc.items()}
    true_local = markers["RWRA"].local.copy()
    markers["RWRA"] = MarkerBinding("RWRA", "radius_r", true_local + [0.0, 6.0, 0.0], "static")
    names = sorted(fa["poses"], key=float)

    class Registered:            # what start_forearm_registration's workers return, from the truth
        def result(self):
            out = []
            for nm in names:
                p = fa["poses"][nm]
                Ts = {b: np.array(p["bone_to_lps"].get(b, sk.bones[b].bone_to_world.tolist()))
                      for b in ("ulna_r", "radius_r", "humerus_r")}
                out.append((Ts, {}, p["capsule_centres_lps"]))
            return out

    dirs = [phantom / fa["poses"][nm]["folder"] for nm in names]
    model, report = fit_forearm_from_stacks(dirs, sk, "r", markers=markers, registered=Registered(), skin=skin)
    assert "RWRA" in report["rebound_after_static"] and markers["RWRA"].source == "capsule"
    assert np.linalg.norm(markers["RWRA"].local - true_local) < 1.0          # was 6 mm off
    # the stacks' twist read on the wrist markers' own spots: the true markers' twist in each pose
    ix = FOREARM_MARKERS["r"]
    true_pts = [[np.array(fa["poses"][nm]["bone_to_lps"].get(doc[n]["bone"], sk.bones[doc[n]["bone"]].bone_to_world
                                                                  .tolist())) @ np.r_[doc[n]["local_mm"], 1]
                 for n in ix] for nm in names]
    raw = np.array([forearm_twist(*(np.array(q)[:3] for q in pts))[0] for pts in true_pts])
    # (within 3.5 deg: the tiny preset's coarse skin tilts the normals that carry a capsule out to its marker,
    # which put the wrist markers 0.7-1.4 mm off theirs over a ~60 mm wrist line; 6 mm off, RWRA alone made 6 deg)
    np.testing.assert_allclose(report["twists_deg"], raw - raw[0], atol=3.5)
    for n in ("RWRA", "RWRB", "RFRM", "RELP"):
        assert np.linalg.norm(markers[n].local - np.array(doc[n]["local_mm"])) < 1.6, n
    # the radius's axis from its turns in the stacks lies on the phantom's, whose ends migrate with the twist
    # (~2 mm at the wrist from 0 to 172 deg): within 1 mm of a pronated pose's axis, 2.5 mm of every pose's
    ends = np.reshape(model["radius_axis_ulna_mm"], (2, 3))
    U = sk.bones["ulna_r"].bone_to_world
    off = []
    for nm in names:
        true_ends = np.array(fa["poses"][nm]["radioulnar_axis_lps"])
        d = (true_ends[1] - true_ends[0]) / np.linalg.norm(true_ends[1] - true_ends[0])
        v = ends @ U[:3, :3].T + U[:3, 3] - true_ends[0]
        off.append(np.linalg.norm(v - np.outer(v @ d, d), axis=1))
    off = np.array(off)
    assert off[1:].min(axis=0).max() < 1.0 and off.max() < 2.5, off
    assert report["radius_axis"]["used"] and max(report["radius_axis"]["turn_deg"]) > 150
    again = ForearmModel.from_dict(model)
    assert again.radius_axis_ulna_mm == tuple(model["radius_axis_ulna_mm"]) and again.radius_axis == "anatomical"
