"""``bonecap build-subject`` from MRI on a tiny phantom, from a label map, and its bad inputs."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from bonecap.io.mesh import read_mesh
from bonecap.skeleton.kinematics import subtree


@pytest.fixture(scope="module")
def phantom(tmp_path_factory):
    from bonecap.phantom import make_phantom

    out = tmp_path_factory.mktemp("phantom") / "p"
    make_phantom(out, seed=4, preset="tiny")
    return out


@pytest.fixture(scope="module")
def built(phantom, tmp_path_factory):
    from bonecap.build_subject import run_build_subject

    out = tmp_path_factory.mktemp("subject") / "s"
    stations = sorted(str(p) for p in (phantom / "mri").glob("station_*"))
    # the tiny preset's forearm stacks (1.5 mm pixels, 5 mm slices) are too coarse for a forearm's marrow:
    # the stage must fail cleanly and leave the paper's model in place
    stacks = sorted((phantom / "mri").glob("forearm_*"), key=lambda p: float(p.name.split("_")[1]))
    report = run_build_subject(stations, out, static=phantom / "trials/static.c3d", forearm_poses=stacks)
    return out, report


def test_the_density_rules_extractions_are_warp_targets_only_when_trusted():
    """From template seeds the density rule's bones (hips, sacrum, vertebrae, scapulae, patellae) are carried
    by their neighbours; the long bones' extractions, and everything from the user's seeds or labels, stay."""
    import trimesh

    from bonecap.build_mri import warp_targets
    from bonecap.model import Mesh

    box = trimesh.creation.box((10, 10, 10))
    m = Mesh(np.asarray(box.vertices), np.asarray(box.faces), "lps")
    found = {n: m for n in ("femur_r", "radius_l", "sacrum", "hip_r", "l3", "scapula_l", "patella_r")}
    assert set(warp_targets(found, trusted=False)) == {"femur_r", "radius_l"}
    assert set(warp_targets(found, trusted=True)) == set(found)


def test_forearm_stacks_that_do_not_fit_leave_the_paper_model(built):
    from bonecap.subject import read_subject

    out, report = built
    fa = report["forearm"]
    assert fa["used"] is False and "forearm_" in fa["reason"] and "ulna" in fa["reason"]
    assert set(fa["capsules"]) == {"forearm_0", "forearm_99.5", "forearm_172.1"}
    assert not read_subject(out, load_meshes=False).forearm      # empty: the paper's coefficients


def test_forearm_stacks_read_beside_the_stations_as_here(phantom, tmp_path):
    """The stacks are read in a child while the stations are worked on: the same volume, body mask and
    capsules as read here; a stack that cannot be read raises its own error where it is used."""
    from bonecap.build_mri import _read_stack, _stack_read, start_reading_stacks
    from bonecap.errors import InputError

    stack = phantom / "mri/forearm_99.5"
    empty = tmp_path / "empty"
    empty.mkdir()
    read = start_reading_stacks([stack, empty])()
    v, body, caps = _read_stack(stack)
    v2, body2, caps2 = _stack_read(read[0])
    assert np.array_equal(v.data, v2.data) and np.array_equal(v.affine, v2.affine)
    assert body.any() and np.array_equal(body, body2)
    assert len(caps) >= 1 and caps2 == caps
    with pytest.raises(InputError, match="empty: no DICOM files found"):
        _stack_read(read[1])


def _surface_mean(a, b) -> float:
    from bonecap.evaluate import _surface_stats

    return _surface_stats(a, b)[0]


def test_subject_folder_layout(built, phantom):
    from bonecap.subject import read_subject

    out, report = built
    subj = read_subject(out)
    assert subj.skeleton.world == "lps" and len(subj.skeleton.bones) == 90
    n_st = len(list((phantom / "mri").glob("station_*")))
    assert len(list((out / "labels").glob("station_*.nii.gz"))) == n_st
    st = json.loads((out / "stations.json").read_text())
    assert len(st["stations"]) == n_st and st["ids"]
    for png in ("personal_skeleton_front.png", "personal_skeleton_side.png", "contours_01_station_1.png"):
        assert (out / "qc" / png).stat().st_size > 5000
    assert {"femur_r", "femur_l"} <= set(report["extracted_bones"])
    assert (out / "extracted/femur_r.ply").is_file()
    # every bone's origin is accounted for: warped onto its own extraction, carried, or placed (and said so)
    assert report["warp"].get("bones") or "not warped" in report["warp"].get("warning", "")
    # the density rule's bones are carried by their neighbours, whatever their extraction (seeds from the
    # template, not the user's)
    from bonecap.segmentation.bones import default_rule

    sources = {n: r.get("source", "") for n, r in (report["warp"].get("bones") or {}).items()}
    assert not [n for n, src in sources.items() if default_rule(n) == "density" and src == "own target"]
    # every marker of the set the static trial holds is bound from it
    assert report["markers_bound"] >= 57
    assert sum(m.source == "static" for m in subj.markers.values()) >= 57
    # a personal (MRI) girdle: the solvers turn its scapulae with the arms
    assert subj.provenance["girdle_rhythm"] is True and subj.follows_rhythm()
    # the station registration recovered the truth's relative motions to within a voxel
    truth = json.loads((phantom / "truth/stations.json").read_text())["stations"]
    assert len(report["stations"]) == len(truth)


def test_wild_extractions_do_not_drag_the_skeleton(built, phantom):
    """Tiny preset: 4 mm pixels and 15 mm slices, too coarse for the slice rules (docs/benchmarks.md has the
    default phantom). Whatever the extraction, the personal bones stay near the truth: an implausible
    extraction is rejected and the bone comes from the template placed on the body."""
    from bonecap.subject import read_subject

    out, _ = built
    subj = read_subject(out)
    for bone in ("femur_r", "femur_l", "tibia_l", "humerus_r"):
        truth = read_mesh(phantom / f"truth/meshes/{bone}.ply")
        personal = _surface_mean(subj.skeleton.world_mesh(bone), truth)
        assert personal < 11.0, bone
        ext = out / f"extracted/{bone}.ply"
        if ext.is_file():
            assert personal <= _surface_mean(read_mesh(ext), truth) + 1.0, bone


def test_evaluate_subject_cli(built, phantom, cli):
    out, _ = built
    res = cli("evaluate", "subject", out, "--truth", phantom / "truth", "--json")
    assert res.returncode == 0, res.stderr
    r = json.loads(res.stdout)
    f = r["bones"]["femur_r"]
    assert 0 < f["dice"] <= f["oracle_dice"] <= 1
    assert f["personal_surface_mean_mm"] < f["personal_surface_p95_mm"]
    assert r["summary"]["marker_binding_median_mm"] is not None
    # the forearm stacks' capsules (found while the stage failed) scored against the truth's; this
    # standard-protocol phantom has none at the marker spots
    for pose, c in r["capsules"].items():
        assert c["n_found"] == c["n_truth"] == len(c["centre_mm"]) and c["n_at_markers"] == 0, pose
        assert max(c["centre_mm"]) < 1.0
    assert len(r["capsules"]) == 3
    # the oracle (the truth voxelised on each station) is close to the truth
    assert r["summary"]["oracle_dice"] > 0.7
    # the warp-vs-affine comparison is made on the same bones (those with an affine-only mesh)
    paired = [(b["personal_surface_mean_mm"], b["affine_only_surface_mean_mm"]) for b in r["bones"].values()
              if b.get("affine_only_surface_mean_mm") is not None]
    if paired:
        assert r["summary"]["personal_surface_mean_mm_paired"] == pytest.approx(np.median([p for p, _ in paired]))
        assert r["summary"]["affine_only_over_personal"] == pytest.approx(np.median([a / p for p, a in paired]))
    # the personal skeleton's label maps are scored on the bones the rules segment, and only there; the
    # tiny preset's coarse warp still lays its femur over the truth's (0.50 here; misplaced by a few
    # centimetres it would score near 0)
    scored = {b for b, v in r["bones"].items() if "personal_dice" in v}
    assert scored == {b for b, v in r["bones"].items() if "dice" in v}
    assert all(0 <= r["bones"][b]["personal_dice"] <= 1 for b in scored)
    assert r["bones"]["femur_r"]["personal_dice"] > 0.3


def test_personal_dice_of_the_oracle_is_the_oracles(built, phantom, tmp_path):
    """evaluate subject scores the personal and the refined label maps as it scores the oracle: a subject
    folder whose personal and refined maps are the oracle's own station labels (voxel for voxel on the
    station grids, ids mapped to its personal ids) gets personal_dice == refined_dice == oracle_dice on
    every bone; a map that does not lie on its station's grid is refused."""
    from bonecap.errors import DataError
    import shutil

    from bonecap.evaluate import evaluate_subject
    from bonecap.io.imaging import read_nifti, write_nifti
    from bonecap.model import Volume

    out, _ = built
    sub = tmp_path / "s"
    shutil.copytree(out, sub)
    doc = json.loads((sub / "stations.json").read_text())
    truth_ids = json.loads((phantom / "truth" / "labels.json").read_text())["ids"]
    truth_st = json.loads((phantom / "truth" / "stations.json").read_text())["stations"]
    to_personal = np.zeros(max(truth_ids.values()) + 1, np.int16)
    for bone, i in truth_ids.items():
        to_personal[i] = doc["personal_ids"].get(bone, 0)
    for st in doc["stations"]:
        t = next(t for t in truth_st if np.allclose(t["affine_voxel_to_lps"], st["nominal_affine"], atol=1e-3))
        oracle = read_nifti(phantom / "truth" / "labels" / f"{t['name']}_oracle.nii.gz")
        mapped = to_personal[np.asarray(oracle.data).astype(int)]
        write_nifti(Volume(mapped, np.asarray(st["registered_affine"])), sub / st["personal_labels"])
        write_nifti(Volume(mapped, np.asarray(st["registered_affine"])), sub / st["refined_labels"])
    r = evaluate_subject(sub, phantom / "truth")
    rows = [v for v in r["bones"].values() if "personal_dice" in v]
    assert len(rows) > 10
    for v in rows:
        assert v["personal_dice"] == pytest.approx(v["oracle_dice"], abs=1e-12)
        assert v["refined_dice"] == pytest.approx(v["oracle_dice"], abs=1e-12)
    st = doc["stations"][0]
    moved = np.asarray(st["registered_affine"]).copy()
    moved[:3, 3] += 5.0
    for key in ("refined_labels", "personal_labels"):
        write_nifti(Volume(read_nifti(sub / st[key]).data, moved), sub / st[key])
        with pytest.raises(DataError, match=f"the {key.split('_')[0]} labels of station 1 do not lie on its grid"):
            evaluate_subject(sub, phantom / "truth")


def test_personal_label_maps_lie_on_the_station_grids(built):
    """build-subject writes the personal skeleton voxelised on every station's grid beside the rules'
    labels: the same registered affine and shape, the rules' ids kept, every bone with a mesh an id, and
    a bone's labelled volume within a tenth of a voxel's rim of its mesh's (1-3 % here) where a station
    holds it whole."""
    from bonecap.io.imaging import read_nifti
    from bonecap.subject import read_subject

    out, _ = built
    doc = json.loads((out / "stations.json").read_text())
    sk = read_subject(out).skeleton
    ids = doc["personal_ids"]
    assert {k: ids[k] for k in doc["ids"]} == doc["ids"]
    assert {n for n in sk.names if sk.bones[n].mesh is not None} == set(ids)
    assert len(set(ids.values())) == len(ids)
    whole = 0
    for st in doc["stations"]:
        vol = read_nifti(out / st["personal_labels"])
        assert list(vol.data.shape) == st["shape"]
        assert np.allclose(vol.affine, st["registered_affine"], atol=1e-4)
        data = np.asarray(vol.data)
        voxel = abs(np.linalg.det(vol.affine[:3, :3]))
        corners = np.array([[i, j, k, 1.0] for i in (0, data.shape[0] - 1) for j in (0, data.shape[1] - 1)
                            for k in (0, data.shape[2] - 1)]) @ vol.affine.T
        lo, hi = corners[:, :3].min(0), corners[:, :3].max(0)
        for name in ("femur_r", "tibia_r", "humerus_r"):
            m = sk.world_mesh(name)
            if not (np.all(m.vertices.min(0) > lo + 10) and np.all(m.vertices.max(0) < hi - 10)):
                continue
            import trimesh

            tm = trimesh.Trimesh(m.vertices, m.faces, process=False)
            got = np.count_nonzero(data == ids[name]) * voxel
            rim = tm.area * 0.1 * float(np.min(np.linalg.norm(vol.affine[:3, :3], axis=0)))
            assert abs(got - tm.volume) < rim, (name, got, tm.volume, rim)
            whole += 1
    assert whole, "no station holds a long bone whole"


def test_refined_label_maps_change_only_the_density_rule_s_bones(built):
    """build-subject writes a refined map per station on its grid: the personal map with the density
    rule's bones (hips, sacrum, vertebrae, scapulae, patellae) moved to the image's evidence: every other
    bone's voxels as the personal map has them, and no refined bone takes another bone's voxel."""
    from bonecap.io.imaging import read_nifti
    from bonecap.segmentation.bones import default_rule

    out, _ = built
    doc = json.loads((out / "stations.json").read_text())
    refined = set(doc["refined_bones"])
    assert refined == {b for b in doc["ids"] if default_rule(b) == "density"}
    rid = [doc["personal_ids"][b] for b in refined]
    changed = 0
    for st in doc["stations"]:
        ref = read_nifti(out / st["refined_labels"])
        per = np.asarray(read_nifti(out / st["personal_labels"]).data).astype(int)
        assert np.allclose(ref.affine, st["registered_affine"], atol=1e-4)
        ref = np.asarray(ref.data).astype(int)
        assert list(ref.shape) == st["shape"]
        same = ~np.isin(per, rid) & ~np.isin(ref, rid)
        assert np.array_equal(ref[same], per[same])
        # a refined bone's voxels were its own or nobody's in the personal map
        for i in rid:
            assert np.isin(per[ref == i], [0, i]).all()
        changed += int(np.count_nonzero(np.isin(per, rid) != np.isin(ref, rid)))
    assert changed > 0


def test_labels_path_reaches_the_truth(phantom, tmp_path):
    """With the truth's own label map (--labels; 6 mm voxels at the tiny preset), meshing + warp give the
    truth back to within a quarter to a third of a voxel: 1.3-1.55 mm on two versions of the subject, which
    moved by a few millimetres against the grid (where a voxel's centre falls decides its label). The map
    comes without its ribs; the personal skeleton voxelised on its grid has the map's bones where the map
    has them and the ribs besides."""
    import nibabel as nib

    from bonecap.build_subject import run_build_subject
    from bonecap.subject import read_subject

    # the truth's map without its ribs (as a user's map may lack bones), its table unchanged
    full = nib.load(phantom / "truth/labels/merged.nii.gz")
    table = json.loads((phantom / "truth/labels.json").read_text())["ids"]
    ribs = [b for b in table if b.startswith("rib")]
    data = np.asarray(full.dataobj).astype(np.int16)
    data[np.isin(data, [table[b] for b in ribs])] = 0
    (tmp_path / "map").mkdir()
    labels = tmp_path / "map/merged.nii.gz"
    nib.save(nib.Nifti1Image(data, full.affine), labels)
    (tmp_path / "map/labels.json").write_text(json.dumps({"ids": table}))     # the table still names them
    voxel = float(max(nib.load(labels).header.get_zooms()[:3]))
    report = run_build_subject(None, tmp_path / "s", labels=labels, static=phantom / "trials/static.c3d")
    assert {"femur_r", "tibia_l", "hip_r", "humerus_r"} <= set(report["extracted_bones"])
    subj = read_subject(tmp_path / "s")
    for bone in ("femur_r", "tibia_l", "humerus_r"):
        truth = read_mesh(phantom / f"truth/meshes/{bone}.ply")
        assert _surface_mean(read_mesh(tmp_path / f"s/extracted/{bone}.ply"), truth) < 0.3 * voxel
        assert _surface_mean(subj.skeleton.world_mesh(bone), truth) < 0.3 * voxel
    # the personal skeleton on the map's own grid: the map's bones where the map has them, and the bones
    # it lacks besides
    doc = json.loads((tmp_path / "s/stations.json").read_text())
    on_map = doc["personal_on_label_map"]
    given = nib.load(labels)
    personal = nib.load(tmp_path / "s" / on_map["labels"])
    assert personal.shape == given.shape and np.allclose(personal.affine, given.affine, atol=1e-4)
    g, p = np.asarray(given.dataobj).astype(int), np.asarray(personal.dataobj).astype(int)
    ids = doc["personal_ids"]
    for bone in ("femur_r", "tibia_l", "humerus_r"):
        a, b = g == doc["ids"][bone], p == ids[bone]
        dice = 2 * np.count_nonzero(a & b) / (np.count_nonzero(a) + np.count_nonzero(b))
        assert dice > 0.8, (bone, dice)
    # the ribs keep the labels the table gives them (the map lacks them, so the rules' ids do too)
    assert not set(ribs) & set(doc["ids"]) and all(ids[b] == table[b] for b in ribs)
    truth_ribs = np.isin(np.asarray(full.dataobj).astype(int), [table[b] for b in ribs])
    ours_ribs = np.isin(p, [ids[b] for b in ribs])
    from scipy import ndimage

    # carried by the warp from the spine and sternum, at 6 mm voxels (centroids 9-16 mm off here): about as
    # many voxels as the truth's ribs, most of them within two voxels of those
    near = ndimage.binary_dilation(truth_ribs, iterations=2)
    assert 0.5 < np.count_nonzero(ours_ribs) / np.count_nonzero(truth_ribs) < 2.0
    assert np.count_nonzero(ours_ribs & near) > 0.7 * np.count_nonzero(ours_ribs)


def test_bad_inputs(phantom, tmp_path, cli):
    from bonecap.io.imaging import read_volumes, write_nifti
    from bonecap.model import Volume

    st = sorted((phantom / "mri").glob("station_*"))
    # stations that do not overlap: a copy of the first one moved 2 m up
    v = read_volumes(st[0])[0]
    A = v.affine.copy()
    A[2, 3] += 2000.0
    write_nifti(Volume(v.data, A), tmp_path / "far.nii.gz")
    res = cli("build-subject", st[0], tmp_path / "far.nii.gz", "-o", tmp_path / "a")
    assert res.returncode == 1 and "gap" in res.stderr and res.stderr.count("\n") == 1
    assert not (tmp_path / "a").exists()
    # a station in another orientation (sagittal slices)
    sag = Volume(v.data, v.affine[:, [2, 0, 1, 3]])
    write_nifti(sag, tmp_path / "sag.nii.gz")
    res = cli("build-subject", st[0], tmp_path / "sag.nii.gz", "-o", tmp_path / "a2")
    assert res.returncode == 1 and "axial" in res.stderr and not (tmp_path / "a2").exists()
    # an empty folder
    (tmp_path / "empty").mkdir()
    res = cli("build-subject", tmp_path / "empty", "-o", tmp_path / "b")
    assert res.returncode == 1 and not (tmp_path / "b").exists()
    # nothing to build from
    res = cli("build-subject", "-o", tmp_path / "c")
    assert res.returncode == 1 and "--static" in res.stderr
    # a marker set naming a landmark the skeleton lacks
    bad = tmp_path / "bad_set.yaml"
    bad.write_text(yaml.safe_dump({"name": "bad", "markers": {
        "XX": {"bone": "femur_r", "landmark": "no_such_landmark", "offset_mm": 5}}}))
    res = cli("build-subject", "--static", phantom / "trials/static.c3d", "--marker-set", bad, "-o", tmp_path / "d")
    assert res.returncode == 1 and "no_such_landmark" in res.stderr and not (tmp_path / "d").exists()
    # a static trial without enough of the set's markers
    from bonecap.io.c3d import read_c3d, write_c3d
    from bonecap.model import Trial

    t = read_c3d(phantom / "trials/static.c3d")
    write_c3d(Trial(t.labels[:3], t.points[:, :3], t.rate), tmp_path / "few.c3d")
    res = cli("build-subject", "--static", tmp_path / "few.c3d", "-o", tmp_path / "e")
    assert res.returncode == 1 and "only 3 markers" in res.stderr
    # seeds file errors
    from bonecap.build_mri import load_seeds
    from bonecap.errors import InputError

    (tmp_path / "seeds.yaml").write_text("femur_r: [1, 2]\n")
    with pytest.raises(InputError, match="femur_r"):
        load_seeds(tmp_path / "seeds.yaml")
    (tmp_path / "seeds.yaml").write_text("seeds: {femur_r: [[0, 0, 0], [0, 0, -400]], patella_r: [10, -40, -380]}\n")
    s = load_seeds(tmp_path / "seeds.yaml")
    assert s["femur_r"].shape == (2, 3) and s["patella_r"].shape == (1, 3)


def test_static_frames_option(phantom):
    from bonecap.build_subject import parse_frames
    from bonecap.errors import InputError

    assert parse_frames("0:25", 100) == slice(0, 25)
    assert parse_frames(":10", 100) == slice(None, 10)
    with pytest.raises(InputError, match="selects no frame"):
        parse_frames("200:300", 100)
    with pytest.raises(InputError, match="START:STOP"):
        parse_frames("a:b", 100)


def _turned_about(ref, idx, pivot, axis, deg):
    """Bone-to-world poses ``ref`` (world frame) with the bones ``idx`` turned by ``deg`` about ``axis``
    through ``pivot`` (a rigid foot or hand turned at its proximal joint)."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(deg) * axis / np.linalg.norm(axis)).as_matrix()
    T[:3, 3] = pivot - T[:3, :3] @ pivot
    out = ref.copy()
    out[idx] = T @ ref[idx]
    return out


def _largest_turn_deg(a, b, idx):
    """The largest rotation (degrees) between the bone-to-world poses ``a`` and ``b`` over the bones ``idx``."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    rel = np.einsum("nji,njk->nik", a[idx][:, :3, :3], b[idx][:, :3, :3])
    return float(np.degrees(Rotation.from_matrix(rel).magnitude().max()))


def _roll_and_swing(sk, bones, pivot, tip, swing_axis, prefixes, axes, roll_deg, swing_deg):
    """:func:`neutral_twist` on the reference poses with ``bones`` rolled by ``roll_deg`` about
    pivot -> tip, then on them swung by ``swing_deg`` about ``swing_axis`` (made perpendicular to
    pivot -> tip: no roll): the largest turns (deg) left from the reference, and added to the swing."""
    import numpy as np

    from bonecap.build_subject import neutral_twist

    ref = np.array([sk.bones[n].bone_to_world for n in sk.names])
    idx = [sk.names.index(n) for n in bones]
    u = (tip - pivot) / np.linalg.norm(tip - pivot)
    a = np.asarray(swing_axis, float)
    swung = _turned_about(ref, idx, pivot, a - (a @ u) * u, swing_deg)
    return (_largest_turn_deg(neutral_twist(sk, _turned_about(ref, idx, pivot, u, roll_deg), prefixes, axes), ref, idx),
            _largest_turn_deg(neutral_twist(sk, swung, prefixes, axes), swung, idx))


def test_foot_roll_comes_from_the_shank_but_its_flexion_from_the_markers():
    """neutral_twist with the foot axes: a static whose foot was rolled about its long axis
    (ankle -> 2nd metatarsal head) gets the reference roll back; a plantarflexion about the
    ankle's flexion axis is kept. Calcaneus and foot ride with the talus."""
    import numpy as np

    from bonecap.build_subject import FOOT_AXES, FOOT_PREFIXES
    from bonecap.skeleton.generic import build_generic_skeleton

    sk = build_generic_skeleton()
    ankle = sk.bones["talus_r"].landmark_in_world("ankle")
    mt2 = sk.bones["foot_r"].landmark_in_world("metatarsal2_head")
    roll, swing = _roll_and_swing(sk, ("talus_r", "calcaneus_r", "foot_r"), ankle, mt2,
                                  np.cross(mt2 - ankle, [0.0, 1.0, 0.0]), FOOT_PREFIXES, FOOT_AXES, 40.0, 25.0)
    assert roll < 0.01 and swing < 0.01


def test_opensim_foot_rolls_with_the_shank_about_ankle_to_mtp(shared_data):
    """An OpenSim model's foot (talus, calcn, toes: no landmarks) takes the roll of the foot's long axis
    (ankle -> the calcaneus body's metatarsophalangeal joint) from the shank; its flexion is kept."""
    from bonecap.build_subject import FOOT_AXES, FOOT_PREFIXES
    from bonecap.skeleton.template import load_template

    sk = load_template(shared_data / "bones/opensim/models/Rajagopal2016.osim")
    roll, swing = _roll_and_swing(sk, ("talus_r", "calcn_r", "toes_r"), sk.bones["talus_r"].landmark_in_world("ankle_r"),
                                  sk.bones["calcn_r"].landmark_in_world("mtp_r"), [0.0, 0.0, 1.0],
                                  FOOT_PREFIXES, FOOT_AXES, 20.0, 15.0)
    assert roll < 0.01 and swing < 0.5


def test_the_hand_takes_its_twist_from_the_radius_but_its_flexion_from_the_markers():
    """neutral_twist with the hand axes: a static hand turned about its long axis (wrist -> head of the
    3rd metacarpal) gets the reference twist back, the rays riding on the carpals; a palmar flexion
    about the wrist is kept (the wrist is ellipsoid: flexion and deviation, no axial rotation)."""
    import numpy as np

    from bonecap.build_subject import HAND_AXES, HAND_PREFIXES, neutral_twist
    from bonecap.skeleton.generic import build_generic_skeleton

    sk = build_generic_skeleton()
    ref = np.array([sk.bones[n].bone_to_world for n in sk.names])
    hand = [sk.names.index(n) for n in sk.names if n.endswith("_r") and n.startswith(HAND_PREFIXES)]
    assert len(hand) == 6
    wrist = sk.bones["carpals_r"].landmark_in_world("wrist")
    mc3 = sk.bones["ray3_r"].landmark_in_world("metacarpal_head")

    fixed = neutral_twist(sk, _turned_about(ref, hand, wrist, mc3 - wrist, 15.0), HAND_PREFIXES, HAND_AXES)
    assert _largest_turn_deg(fixed, ref, hand) < 0.05
    long_axis = (mc3 - wrist) / np.linalg.norm(mc3 - wrist)
    z = sk.bones["radius_r"].bone_to_world[:3, 2]                        # the radius's Z: flexion
    flexed = _turned_about(ref, hand, wrist, z - (z @ long_axis) * long_axis, 30.0)  # a swing, no twist
    kept = neutral_twist(sk, flexed, HAND_PREFIXES, HAND_AXES)
    assert _largest_turn_deg(kept, flexed, hand) < 0.5
    # without the hand's prefixes nothing moves
    twisted = _turned_about(ref, hand, wrist, mc3 - wrist, 15.0)
    assert np.allclose(neutral_twist(sk, twisted, ("femur",))[hand], twisted[hand])


def test_joint_consistent_keeps_the_solved_pronation():
    """A static whose radius is pronated 40 deg about the ulna (about the radial head) keeps it through
    joint_consistent: the radius shares three joint-centre names with the ulna and used to fall back to
    its reference twist (the phantom's wrist markers were then bound 35-47 mm off)."""
    from scipy.spatial.transform import Rotation

    from bonecap.build_subject import joint_consistent
    from bonecap.skeleton.generic import build_generic_skeleton

    sk = build_generic_skeleton()
    ref = np.array([sk.bones[n].bone_to_world for n in sk.names])
    ulna = sk.bones["ulna_r"]
    head = ulna.landmark_in_world("proximal_radioulnar") if "proximal_radioulnar" in ulna.landmarks else \
        ulna.bone_to_world[:3, :3] @ ulna.joint_centres["proximal_radioulnar"] + ulna.bone_to_world[:3, 3]
    distal = ulna.bone_to_world[:3, :3] @ ulna.joint_centres["distal_radioulnar"] + ulna.bone_to_world[:3, 3]
    axis = (distal - head) / np.linalg.norm(distal - head)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians(40.0) * axis).as_matrix()
    T[:3, 3] = head - T[:3, :3] @ head
    moved = [sk.names.index(n) for n in subtree(sk, "radius_r")]
    posed = ref.copy()
    posed[moved] = T @ ref[moved]
    out = joint_consistent(sk, posed)
    i = sk.names.index("radius_r")
    assert Rotation.from_matrix(out[i][:3, :3].T @ posed[i][:3, :3]).magnitude() < np.radians(0.01)
    assert np.allclose(out[i][:3, 3], posed[i][:3, 3], atol=1e-6)
    # the hand rides on the turned radius
    k = sk.names.index("carpals_r")
    assert np.allclose(out[k], posed[k], atol=1e-6)


def test_the_static_radius_turns_on_its_ulna_to_its_markers():
    """pronate_on_ulna: a static forearm (the ulna turned 25 deg at the elbow, the radius and the hand on it
    pronated 70 deg about the forearm's axis) whose solved radius came out twisted 9 deg about its own long
    axis, hung on its head as the coupled solve hangs it, the hand with it. Re-placed on the ulna and
    turned about the forearm's axis to its two markers: with exact marker bindings it is the true radius
    (1e-6), and the hand, carried to the new wrist and turned about it onto its three finger markers, the
    true hand; with the dorsal marker bound 8 mm aside (a placement on the soft forearm) the radius is
    within 3 deg, where the solve was 9 deg off. The left side is left alone when its radius has no
    marker; bad shapes are refused."""
    from scipy.spatial.transform import Rotation

    from bonecap.build_subject import PRONATION_AXIS, pronate_on_ulna
    from bonecap.skeleton.generic import build_generic_skeleton

    sk = build_generic_skeleton()
    ref = np.array([sk.bones[n].bone_to_world for n in sk.names])
    idx = {n: i for i, n in enumerate(sk.names)}

    (rb, rl), (ub, ul) = PRONATION_AXIS
    rad, uln = sk.bones["radius_r"], sk.bones["ulna_r"]
    elbow = uln.bone_to_world[:3, :3] @ uln.joint_centres["elbow"] + uln.bone_to_world[:3, 3]
    c, d = rad.landmark_in_world(rl), uln.landmark_in_world(ul)
    forearm = [idx[n] for n in subtree(sk, "radius_r")]
    hand = forearm[1:]
    assert len(hand) == 6
    # pronated about the forearm's axis, then the forearm (ulna, radius, hand) turned at the elbow
    true = _turned_about(_turned_about(ref, forearm, c, d - c, 70.0), [idx["ulna_r"]] + forearm, elbow,
                         uln.bone_to_world[:3, 2], 25.0)
    bones = ["radius_r", "radius_r", "ray2_r", "ray2_r", "ray4_r"]
    lm = [rad.landmarks["radial_styloid"], rad.landmarks["shaft_dorsal"], sk.bones["ray2_r"].landmarks["metacarpal_head"],
          sk.bones["ray2_r"].landmarks["dip"], sk.bones["ray4_r"].landmarks["pip"]]
    local = np.array(lm) + [[0.0, 0.0, 8.0], [-14.0, 0, 0], [-9.0, 0, 0], [-7.0, 0, 0], [-7.0, 0, 0]]
    lab = np.array([(true[idx[b]] @ np.r_[p, 1.0])[:3] for b, p in zip(bones, local)])
    # the solve: the radius twisted about its own long axis (head -> styloid) through its head, the hand on it
    head, sty = ((true[idx["radius_r"]] @ np.r_[rad.landmarks[k], 1.0])[:3] for k in (rl, "radial_styloid"))
    solved = _turned_about(true, forearm, head, sty - head, 9.0)

    def err(P):
        i = idx["radius_r"]
        return np.degrees(Rotation.from_matrix(P[i][:3, :3].T @ true[i][:3, :3]).magnitude())

    assert err(solved) == pytest.approx(9.0, abs=0.01)
    out, turns = pronate_on_ulna(sk, solved, bones, local, lab)
    assert err(out) < 1e-6 and np.allclose(out[forearm], true[forearm], atol=1e-6)   # radius and hand
    assert not np.allclose(solved[hand], true[hand], atol=1.0)
    assert set(turns) == {"radius_r"} and 3.0 < abs(turns["radius_r"]) < 9.5
    others = [i for i in range(len(sk.names)) if i not in forearm]
    assert np.array_equal(out[others], solved[others])                      # the left radius has no marker
    off = local.copy()
    off[1] += [0.0, 0.0, 8.0]                                               # the dorsal marker bound 8 mm aside
    out2, _ = pronate_on_ulna(sk, solved, bones, off, lab)
    assert err(out2) < 3.0, err(out2)                                      # 2.6
    with pytest.raises(ValueError, match="differ in length"):
        pronate_on_ulna(sk, solved, bones[:1], local, lab)
    with pytest.raises(ValueError, match="poses must be"):
        pronate_on_ulna(sk, solved[:3], bones, local, lab)


def test_seeds_file_settings(tmp_path):
    from bonecap.build_mri import load_seeds
    from bonecap.errors import InputError

    f = tmp_path / "seeds.yaml"
    f.write_text("margin_mm: 4\noptions: {femur_r: {marrow_over_muscle: 2.0}}\nrules: {patella_r: cortical}\n"
                 "seeds: {femur_r: [[0, 0, 0], [0, 0, -400]], patella_r: [10, -40, -380]}\n")
    seeds, settings = load_seeds(f, with_settings=True)
    assert settings == {"margin_mm": 4.0, "options": {"femur_r": {"marrow_over_muscle": 2.0}},
                        "rules": {"patella_r": "cortical"}}
    assert set(seeds) == {"femur_r", "patella_r"}
    for bad, msg in (("margin_mm: -1\n", "margin_mm"), ("options: {tibia_r: {a: 1}}\n", "tibia_r"),
                     ("rules: {patella_r: watershed}\n", "rules")):
        f.write_text(bad + "seeds: {femur_r: [[0, 0, 0], [0, 0, -400]], patella_r: [10, -40, -380]}\n")
        with pytest.raises(InputError, match=msg):
            load_seeds(f, with_settings=True)



def _walking_knees(sk, n=120):
    """The template's legs flexing: hips -10..30 deg, knees 0..65 deg about the tibia's own knee axis."""
    from scipy.spatial.transform import Rotation

    from bonecap.skeleton.kinematics import pose_skeleton

    t = np.linspace(0, 2 * np.pi, n)
    rots = {}
    for s in "rl":
        tib = sk.bones[f"tibia_{s}"]
        rel = np.linalg.solve(sk.bones[f"femur_{s}"].bone_to_world, tib.bone_to_world)[:3, :3]
        axis = rel @ tib.joint_axes["knee"]                       # the knee axis in the femur frame
        knee = np.radians(32.5 - 32.5 * np.cos(t + (np.pi if s == "l" else 0.0)))
        rots[f"tibia_{s}"] = Rotation.from_rotvec(knee[:, None] * axis).as_matrix()
        hip_axis = np.linalg.inv(sk.bones[f"hip_{s}"].bone_to_world)[:3, :3] @ np.array([0.0, 0.0, 1.0])
        rots[f"femur_{s}"] = Rotation.from_rotvec(np.radians(10 + 20 * np.sin(t))[:, None] * hip_axis).as_matrix()
    root = sk.bones[sk.names[0]].bone_to_world
    return pose_skeleton(sk, np.repeat(root[None], n, axis=0), rots)


def test_knee_flexion_gives_back_a_femurs_wrong_twist():
    """A femur whose frame is turned about its long axis (a thigh marker placed 5 mm off turns it by
    5-14 deg) sees the knee flex about a turned axis: ``knee_flexion_twist`` reads the turn back from
    the hip-knee-ankle planes of the flexed frames, ``turn_femurs`` undoes it (hip and knee centres
    stay), and a trial whose knees hardly flex gives no estimate."""
    from scipy.spatial.transform import Rotation

    from bonecap.build_subject import knee_flexion_twist, turn_femurs
    from bonecap.skeleton.generic import build_generic_skeleton

    sk = build_generic_skeleton()
    poses = _walking_knees(sk)
    idx = {n: i for i, n in enumerate(sk.names)}
    wrong = poses.copy()
    for s, err in (("r", 9.0), ("l", -6.0)):
        f = sk.bones[f"femur_{s}"]
        u = f.joint_centres["knee"] / np.linalg.norm(f.joint_centres["knee"])    # origin = hip centre
        wrong[:, idx[f"femur_{s}"], :3, :3] = poses[:, idx[f"femur_{s}"], :3, :3] @ \
            Rotation.from_rotvec(np.radians(err) * u).as_matrix()
    est = knee_flexion_twist(sk, wrong)
    assert set(est) == {"femur_r", "femur_l"}
    assert est["femur_r"]["twist_deg"] == pytest.approx(-9.0, abs=0.3)
    assert est["femur_l"]["twist_deg"] == pytest.approx(6.0, abs=0.3)
    assert est["femur_r"]["frames"] >= 40 and est["femur_r"]["spread_deg"] < 0.5
    assert knee_flexion_twist(sk, poses)["femur_r"]["twist_deg"] == pytest.approx(0.0, abs=0.3)
    fixed = turn_femurs(sk, wrong[50], {k: v["twist_deg"] for k, v in est.items()})
    for s in "rl":
        i = idx[f"femur_{s}"]
        d = np.linalg.solve(poses[50, i], fixed[i])
        assert np.degrees(np.linalg.norm(Rotation.from_matrix(d[:3, :3]).as_rotvec())) < 0.3
        assert np.allclose(fixed[i][:3, 3], poses[50, i][:3, 3], atol=1e-6)   # about the hip centre
    # knees flexed less than 25 deg: nothing to read
    assert knee_flexion_twist(sk, wrong[np.r_[0:8, 112:120]]) == {}
    with pytest.raises(ValueError, match="transforms"):
        knee_flexion_twist(sk, wrong[:, :3])


def test_functional_trials_turn_the_femurs_of_an_mri_subject(phantom, built, tmp_path, cli):
    """``--functional walk.c3d``: each femur of the MRI subject is turned by the twist its knee's
    flexion axis reads in the walk (the report says by how much), only the legs' bindings move, and
    animating the walk with the new binding reads (nearly) no twist left. Without ``--static``, or
    without MRI (the template's knee axis is not the subject's: measured worse), it is a clear error."""
    from bonecap.animate import solve_trial, trial_markers
    from bonecap.build_subject import knee_flexion_twist
    from bonecap.io.c3d import read_c3d
    from bonecap.subject import read_subject

    stations = sorted(str(p) for p in (phantom / "mri").glob("station_*"))
    walk = str(phantom / "trials/walk.c3d")
    res = cli("build-subject", *stations, "--static", str(phantom / "trials/static.c3d"), "--functional", walk,
              "-o", str(tmp_path / "f"))
    assert res.returncode == 0, res.stderr
    rep = json.loads((tmp_path / "f/report.json").read_text())
    turned = rep["functional_femur_turned_deg"]
    assert set(turned) == {"femur_r", "femur_l"} and all(abs(v) < 45 for v in turned.values())
    assert all(d["frames"] >= 20 for d in rep["functional_knee_twist"].values())
    before, after = read_subject(built[0], load_meshes=False), read_subject(tmp_path / "f", load_meshes=False)
    moved = {n for n in after.markers
             if np.linalg.norm(after.markers[n].local - before.markers[n].local) > 1e-6}
    legs = ("femur", "patella", "tibia", "fibula", "talus", "calcaneus", "foot")
    assert moved and all(after.markers[n].bone.startswith(legs) for n in moved), moved
    trial = read_c3d(walk)
    names, measured, _ = trial_markers(after, trial)
    left = knee_flexion_twist(after.skeleton, solve_trial(after, names, measured, rate=trial.rate).transforms)
    assert all(abs(left[f]["twist_deg"]) < max(1.5, 0.3 * abs(turned[f])) for f in turned), (left, turned)
    res = cli("build-subject", *stations, "--functional", walk, "-o", str(tmp_path / "x"))
    assert res.returncode != 0 and "--functional needs --static" in res.stderr
    assert not (tmp_path / "x").exists()
    res = cli("build-subject", "--static", str(phantom / "trials/static.c3d"), "--functional", walk,
              "-o", str(tmp_path / "s"))
    assert res.returncode != 0 and "--functional needs the MRI stations" in res.stderr
    assert not (tmp_path / "s").exists()


def test_capsule_bindings_the_static_refutes_are_flagged_by_segment():
    """capsule_static_disagreement: capsule bindings made with the right hand lying off in the MRI (a hand
    carried at the template's wrist: 20 deg turned about its long axis, which the wrist does not allow,
    and 8 mm aside) fit the static only as a pattern its joints refuse: the hand's segment is flagged, no
    other. Capsules within 1.4 mm of their places pass."""
    from bonecap.build_subject import (FOOT_AXES, FOOT_PREFIXES, HAND_AXES, HAND_PREFIXES,
                                       capsule_static_disagreement, joint_consistent, neutral_twist,
                                       pose_to_static)
    from scipy.spatial.transform import Rotation

    from bonecap.markers import load_marker_set, place_markers
    from bonecap.skeleton.generic import build_generic_skeleton

    sk = build_generic_skeleton()
    mset = load_marker_set("kojima_paper")
    names = [n for n, m in mset.markers.items() if not m.virtual and not m.optional]
    placed = place_markers(mset, sk, names)
    bones = [mset.markers[n].bone for n in names]
    ref = np.array([sk.bones[n].bone_to_world for n in sk.names])
    idx = {n: i for i, n in enumerate(sk.names)}
    rng = np.random.default_rng(0)
    # the static: the subject standing as in the reference pose (lab = world), 0.5 mm noise
    static = np.array([placed[n] for n in names]) + rng.normal(0.0, 0.5, (len(names), 3))

    def posed(local):
        """The static solved as build-subject does: the hand's twist the radius's, the foot's roll the
        shank's, the chain rebuilt through its joint centres."""
        solved = neutral_twist(sk, pose_to_static(sk, bones, local, static), HAND_PREFIXES, HAND_AXES)
        return joint_consistent(sk, neutral_twist(sk, solved, FOOT_PREFIXES, FOOT_AXES))

    def local(world):
        return np.array([(p - ref[idx[b]][:3, 3]) @ ref[idx[b]][:3, :3] for p, b in zip(world, bones)])

    capsules = set(names)
    good = local(np.array([placed[n] for n in names]) + rng.uniform(-0.8, 0.8, (len(names), 3)))
    rms, flagged = capsule_static_disagreement(sk, names, bones, good, static, posed(good), capsules)
    assert flagged == [] and max(rms.values()) < 3.0, rms
    # the right hand's capsules as bound to a hand lying turned and shifted in the MRI
    hand = [i for i, b in enumerate(bones) if b.startswith(("carpals", "ray")) and b.endswith("_r")]
    assert len(hand) >= 4
    wrist = sk.bones["carpals_r"].landmark_in_world("wrist")
    mc3 = sk.bones["ray3_r"].landmark_in_world("metacarpal_head")
    R = Rotation.from_rotvec(np.radians(20.0) * (mc3 - wrist) / np.linalg.norm(mc3 - wrist)).as_matrix()
    world = np.array([placed[n] for n in names])
    world[hand] = (world[hand] - wrist) @ R.T + wrist + sk.bones["radius_r"].bone_to_world[:3, 2] * 8.0
    bad = local(world)
    rms, flagged = capsule_static_disagreement(sk, names, bones, bad, static, posed(bad), capsules)
    assert flagged == ["carpals_r"] and rms["carpals_r"] > 5.0, rms
    assert {bones[i] for i in hand} <= set(subtree(sk, flagged[0]))
    # markers without capsules are never looked at
    assert capsule_static_disagreement(sk, names, bones, bad, static, posed(bad), set())[1] == []
    with pytest.raises(ValueError, match="tolerance_mm"):
        capsule_static_disagreement(sk, names, bones, bad, static, ref, capsules, tolerance_mm=0.0)


def test_capsule_markers_keep_their_mri_binding_unless_the_static_refutes_it(monkeypatch):
    """build-subject's binding with an MRI-visible capsule under every marker (the paper's protocol): the
    markers sit up to 8 mm (5 mm along each axis) from where the marker set's landmarks put them, the capsule finder sees them
    there, the static is the subject standing as it lay. Each capsule marker keeps its MRI binding, exact,
    except on a segment whose capsules the static refutes -- the right hand's, found as a hand lying 25
    deg turned and 10 mm aside in the MRI would show them -- which is bound from the static. A segment the
    scan measured (the left upper arm) keeps its capsules even where the static does not fit them."""
    from scipy.spatial.transform import Rotation

    import bonecap.segmentation.capsules as capsules_mod
    from bonecap.build_mri import _place_and_bind
    from bonecap.markers import load_marker_set, place_markers
    from bonecap.model import Trial
    from bonecap.skeleton.generic import build_generic_skeleton
    from bonecap.subject import Subject

    sk = build_generic_skeleton()
    mset = load_marker_set("kojima_paper")
    names = [n for n, m in mset.markers.items() if not m.virtual and not m.optional]
    rng = np.random.default_rng(3)
    true = {n: p + rng.uniform(-5.0, 5.0, 3) for n, p in place_markers(mset, sk, names).items()}
    hand = [n for n in names if mset.markers[n].bone.startswith(("carpals", "ray")) and mset.markers[n].bone.endswith("_r")]
    assert len(hand) >= 4
    wrist = sk.bones["carpals_r"].landmark_in_world("wrist")
    axis = sk.bones["ray3_r"].landmark_in_world("metacarpal_head") - wrist
    R = Rotation.from_rotvec(np.radians(25.0) * axis / np.linalg.norm(axis)).as_matrix()
    shown = dict(true)
    for n in hand:
        shown[n] = R @ (true[n] - wrist) + wrist + np.array([0.0, 10.0, 0.0])
    # the capsule finder sees a capsule under each marker (its marker-minus-capsule radius outward left out)
    monkeypatch.setattr(capsules_mod, "find_capsules", lambda vol: (np.array([shown[n] for n in names]), None))
    monkeypatch.setattr("bonecap.build_mri.capsules_to_markers", lambda found, skin: found)
    # the left upper arm's markers stand 9 mm off in the static (where a rigid model cannot follow the
    # soft tissue): the scan measured that segment, so its capsules stay, the static's misfit reported
    arm = [n for n in names if mset.markers[n].bone == "humerus_l"]
    standing = {n: true[n] + (np.array([0.0, 0.0, -9.0]) if n in arm else 0.0) for n in names}
    static = Trial(labels=list(names), points=np.array([[standing[n] for n in names]] * 3)
                   + rng.normal(0.0, 0.5, (3, len(names), 3)), rate=100.0)
    subject = Subject(skeleton=sk, skin=None, marker_set=mset.name)
    report = _place_and_bind(subject, mset, [object()], None, static, "static.c3d")
    assert sorted(report["capsules_matched"]) == sorted(names)
    assert report["capsule_segments_bound_from_static"] == ["carpals_r"]
    assert report["capsule_segments_refuted_but_scanned"] == ["humerus_l"] and len(arm) >= 3
    assert report["capsule_static_rms_mm"]["carpals_r"] > 5.0
    kept = [n for n, m in subject.markers.items() if m.source == "capsule"]
    assert sorted(kept) == sorted(set(names) - set(hand))
    for n in kept:          # the MRI binding, not the static's
        assert np.linalg.norm(subject.marker_world(n) - true[n]) < 1e-9
    assert all(subject.markers[n].source == "static" for n in hand)
    assert report["markers_missing_in_static"] == []
    # bound from the static, the hand's markers lie where the standing subject shows them (lab = world)
    assert max(np.linalg.norm(subject.marker_world(n) - true[n]) for n in hand) < 3.0


def test_unseen_ends_mark_where_the_search_cut_a_long_bone():
    """unseen_ends: a long bone searched from 20 mm below to 20 mm above its seed line (z 100..300) and
    labelled down to the last slice searched is cut there (a half-space over its last pitch, -z); its top,
    which ends 40 mm inside the search, is not; a density-rule bone never is; the images' end cuts too;
    stations whose slice axes differ give nothing."""
    import trimesh

    from bonecap.build_mri import unseen_ends
    from bonecap.model import Mesh, Volume

    def station(z0, n, axis=2):
        A = np.diag([2.0, 2.0, 5.0, 1.0])
        A[:3, 3] = [-100.0, -100.0, z0]
        if axis != 2:                       # slices along x instead
            A[:3, :3] = np.array([[0.0, 0.0, 5.0], [2.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
        return Volume(np.zeros((4, 4, n), np.float32), A)

    def rod(z_lo, z_hi):
        box = trimesh.creation.box(extents=(20.0, 20.0, z_hi - z_lo))
        return Mesh(np.asarray(box.vertices) + [0.0, 0.0, 0.5 * (z_lo + z_hi)], np.asarray(box.faces), "lps")

    seeds = {"tibia_r": np.array([[0.0, 0.0, 300.0], [0.0, 0.0, 100.0]]),
             "hip_r": np.array([[0.0, 0.0, 300.0], [0.0, 0.0, 100.0]])}
    vols = [station(0.0, 50), station(200.0, 50)]
    cuts = unseen_ends({"tibia_r": rod(78.5, 280.0), "hip_r": rod(78.5, 280.0)}, seeds, vols)
    assert list(cuts) == ["tibia_r"] and len(cuts["tibia_r"]) == 1
    n, c = cuts["tibia_r"][0]
    assert np.allclose(n, [0.0, 0.0, -1.0]) and c == pytest.approx(-(78.5 + 5.0))
    # ending two slices inside the search: the bone's own end, no cut
    assert unseen_ends({"tibia_r": rod(92.0, 280.0)}, seeds, vols) == {}
    # the images end at z = 245 (below the search's top, 320): a bone labelled up to there is cut there too
    cuts = unseen_ends({"tibia_r": rod(92.0, 246.0)}, seeds, [station(0.0, 50)])
    assert [np.round(n).tolist() for n, _ in cuts["tibia_r"]] == [[0.0, 0.0, 1.0]]
    assert unseen_ends({"tibia_r": rod(78.5, 280.0)}, seeds, [station(0.0, 50), station(200.0, 50, axis=0)]) == {}
    # labelled a slice past the search (z 72.5-77.5): a tip tracked to its point ends there, a joint's follow
    # is cut (what lies past the talus's dome is the malleolus); ending on the last slice searched, a tip is cut too
    seeds["fibula_r"] = seeds["tibia_r"]
    past = unseen_ends({"tibia_r": rod(72.5, 280.0), "fibula_r": rod(72.5, 280.0)}, seeds, vols, tips=("fibula",))
    assert list(past) == ["tibia_r"]
    assert list(unseen_ends({"fibula_r": rod(78.5, 280.0)}, seeds, vols, tips=("fibula",))) == ["fibula_r"]
    # a bone whose distal end is a process without marrow (the radial styloid) is cut there even where its
    # extraction ends two slices inside the search; its proximal end, 40 mm inside, is not
    seeds["radius_r"] = seeds["tibia_r"]
    assert unseen_ends({"radius_r": rod(92.0, 280.0)}, seeds, vols) == {}
    cuts = unseen_ends({"radius_r": rod(92.0, 280.0)}, seeds, vols, processes=("radius",))
    assert [np.round(n).tolist() for n, _ in cuts["radius_r"]] == [[0.0, 0.0, -1.0]]
    assert cuts["radius_r"][0][1] == pytest.approx(-(92.0 + 5.0))
    # a line drawn distal end up (an arm raised in the scanner): the cut is at the top
    seeds["radius_r"] = seeds["tibia_r"][::-1]
    cuts = unseen_ends({"radius_r": rod(120.0, 280.0)}, seeds, vols, processes=("radius",))
    assert [np.round(n).tolist() for n, _ in cuts["radius_r"]] == [[0.0, 0.0, 1.0]]


def test_distal_cuts_give_the_distal_end_only():
    """distal_cuts: the half-space past the named bones' extraction's distal end (toward the seed line's last
    point) only, also where the search cut the proximal end; other bones are left out."""
    import trimesh

    from bonecap.build_mri import distal_cuts
    from bonecap.model import Mesh, Volume

    A = np.diag([2.0, 2.0, 5.0, 1.0])
    A[:3, 3] = [-100.0, -100.0, 0.0]
    vols = [Volume(np.zeros((4, 4, 100), np.float32), A)]          # z 0..495

    def rod(z_lo, z_hi):
        box = trimesh.creation.box(extents=(20.0, 20.0, z_hi - z_lo))
        return Mesh(np.asarray(box.vertices) + [0.0, 0.0, 0.5 * (z_lo + z_hi)], np.asarray(box.faces), "lps")

    down = np.array([[0.0, 0.0, 300.0], [0.0, 0.0, 100.0]])        # proximal at the top
    # the extraction reaches past the search's top (320): a search cut there, and the distal one
    cuts = distal_cuts({"radius_r": rod(120.0, 330.0), "ulna_r": rod(120.0, 330.0)},
                       {"radius_r": down, "ulna_r": down}, vols, ("radius",))
    assert list(cuts) == ["radius_r"] and len(cuts["radius_r"]) == 1
    n, c = cuts["radius_r"][0]
    assert np.allclose(n, [0.0, 0.0, -1.0]) and c == pytest.approx(-(120.0 + 5.0))
    cuts = distal_cuts({"radius_r": rod(120.0, 280.0)}, {"radius_r": down[::-1]}, vols, ("radius",))
    n, c = cuts["radius_r"][0]
    assert np.allclose(n, [0.0, 0.0, 1.0]) and c == pytest.approx(280.0 - 5.0)


def test_no_mri_trunk_and_arms_against_the_truth(phantom, tmp_path):
    """The template scaled to the static trial alone (no MRI), animated: the spine scaled by its own
    length puts the trunk where the truth has it (the chest's scale factor had stood it 60 mm high on
    this phantom, the shoulders 64-74 mm), and the embedded elbow's hinge carries Plug-in Gait's
    one-marker ulna and the humerus's twist (30-43 deg off in the arm trial before, 7-10 now)."""
    import numpy as np

    from bonecap.animate import animate
    from bonecap.build_subject import run_build_subject
    from bonecap.motion.rigid import rotation_angle_deg

    from bonecap.subject import read_subject

    run_build_subject(None, tmp_path / "s", static=phantom / "trials/static.c3d")
    # the template's girdle is not the subject's: no rhythm counted from it (Subject.follows_rhythm)
    assert read_subject(tmp_path / "s", load_meshes=False).follows_rhythm() is False
    animate(tmp_path / "s", [phantom / "trials/static.c3d", phantom / "trials/arm_raise.c3d"], tmp_path / "a")
    for trial in ("static", "arm_raise"):
        ours = np.load(tmp_path / f"a/{trial}_poses.npz", allow_pickle=True)
        truth = np.load(phantom / f"truth/{trial}_poses.npz", allow_pickle=True)
        ob, tb = [str(b) for b in ours["bones"]], [str(b) for b in truth["bones"]]

        def pose(bone, o=ours, t=truth, ob=ob, tb=tb):
            return o["transforms"][:, ob.index(bone)], t["transforms"][:, tb.index(bone)]

        if trial == "static":
            a, t = pose("t6")
            assert np.nanmedian(np.linalg.norm(a[:, :3, 3] - t[:, :3, 3], axis=1)) < 25.0
        for bone in ("humerus_r", "humerus_l", "ulna_r", "ulna_l"):
            a, t = pose(bone)
            ok = np.isfinite(a).all(axis=(1, 2)) & np.isfinite(t).all(axis=(1, 2))
            assert ok.mean() > 0.9, bone
            assert np.median(rotation_angle_deg(a[ok], t[ok])) < 15.0, (trial, bone)


def test_reframe_subject_moves_nothing_in_world():
    """A bone described in a new frame keeps its markers and its static pose where they were in world
    (what the malleolar turn of the tibia's frame after the static binding relies on)."""
    from bonecap.build_mri import reframe_subject
    from bonecap.skeleton.generic import build_generic_skeleton
    from bonecap.subject import MarkerBinding, Subject

    sk = build_generic_skeleton()
    T = sk.bones["tibia_r"].bone_to_world
    rng = np.random.default_rng(0)
    local = rng.normal(0.0, 40.0, (3, 3))
    sub = Subject(skeleton=sk, markers={f"M{i}": MarkerBinding(f"M{i}", "tibia_r", p) for i, p in enumerate(local)})
    sub.markers["RTHI"] = MarkerBinding("RTHI", "femur_r", np.array([10.0, 20.0, 30.0]))
    P = np.eye(4)
    P[:3, :3] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    P[:3, 3] = [100.0, 200.0, 900.0]
    sub.static = {"bone_to_lab": {"tibia_r": P.copy()}}
    world = [T[:3, :3] @ p + T[:3, 3] for p in local]
    lab = [P[:3, :3] @ p + P[:3, 3] for p in local]
    T_new = T.copy()
    c, s = np.cos(0.2), np.sin(0.2)
    T_new[:3, :3] = T[:3, :3] @ np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    T_new[:3, 3] += [5.0, 0.0, -3.0]
    reframe_subject(sub, {"tibia_r": T_new})
    assert np.allclose(sub.skeleton.bones["tibia_r"].bone_to_world, T_new)
    P_new = sub.static["bone_to_lab"]["tibia_r"]
    for i in range(3):
        q = sub.markers[f"M{i}"].local
        assert np.allclose(T_new[:3, :3] @ q + T_new[:3, 3], world[i])
        assert np.allclose(P_new[:3, :3] @ q + P_new[:3, 3], lab[i])
        assert not np.allclose(q, local[i])
    assert np.allclose(sub.markers["RTHI"].local, [10.0, 20.0, 30.0])
    with pytest.raises(ValueError, match="no bone"):
        reframe_subject(sub, {"tibia_x": T_new})


def test_a_marker_placed_far_off_does_not_tilt_the_static_when_reweighted():
    """pose_to_static(robust_rounds=3): the subject stands at its reference pose; every marker is bound
    where it is except T10, bound 18 mm below its place (what a spinous tip's normal that is not the
    subject's does to a marker pushed off it by 40 mm of soft tissue). Plain least squares tilts the thorax
    toward it (0.29 deg from the pose the same static gives with T10 bound where it is: its joints and other
    markers hold it); reweighted, the tilt is at least halved (0.05). The thorax carries Plug-in Gait's four
    thorax markers (the acromion markers ride on the shoulder girdles), so the static's noise alone turns
    it by ~0.17 deg: the tilt is measured against the well-bound solve of the same static."""
    from scipy.spatial.transform import Rotation

    from bonecap.build_subject import pose_to_static
    from bonecap.markers import load_marker_set, place_markers
    from bonecap.skeleton.generic import build_generic_skeleton

    sk = build_generic_skeleton()
    mset = load_marker_set("kojima_paper")
    names = [n for n, m in mset.markers.items() if not m.virtual and not m.optional]
    placed = place_markers(mset, sk, names)
    bones = [mset.markers[n].bone for n in names]
    ref = {n: sk.bones[n].bone_to_world for n in sk.names}
    static = np.array([placed[n] for n in names]) + np.random.default_rng(1).normal(0.0, 0.5, (len(names), 3))
    t6 = sk.names.index("t6")

    def local(t10_offset):
        world = np.array([placed[n] for n in names])
        world[names.index("T10")] += [0.0, t10_offset, 0.0]          # the template world is Y up
        return np.array([(p - ref[b][:3, 3]) @ ref[b][:3, :3] for p, b in zip(world, bones)])

    def tilt(rounds):
        good = pose_to_static(sk, bones, local(0.0), static, robust_rounds=rounds)
        off = pose_to_static(sk, bones, local(-18.0), static, robust_rounds=rounds)
        return np.degrees(Rotation.from_matrix(good[t6][:3, :3].T @ off[t6][:3, :3]).magnitude())

    plain, robust = tilt(0), tilt(3)
    assert plain > 0.2, plain
    assert robust < 0.5 * plain, (plain, robust)
    with pytest.raises(ValueError, match="robust_rounds"):
        pose_to_static(sk, bones, local(0.0), static, robust_rounds=-1)


def test_the_build_runs_its_own_blas_on_one_thread_beside_its_workers(monkeypatch):
    """With worker processes the build's own process runs BLAS on one thread (its workers do), and the
    limit ends with the build."""
    import bonecap.build_mri as bm
    from threadpoolctl import threadpool_info, threadpool_limits

    def blas_threads():
        return max((d["num_threads"] for d in threadpool_info() if d["user_api"] == "blas"), default=1)

    monkeypatch.setattr(bm, "_build_from_mri", lambda *a, **k: blas_threads())
    with threadpool_limits(limits=2, user_api="blas"):
        before = blas_threads()
        monkeypatch.setenv("BONECAP_WORKERS", "2")
        assert bm.build_from_mri([]) == 1
        assert blas_threads() == before
        monkeypatch.setenv("BONECAP_WORKERS", "1")
        assert bm.build_from_mri([]) == before


def _arms_scene(elbow_z: dict[str, float], rng_seed: int = 3):
    """A trunk and two arms at its sides (LPS, z up the body), each arm one marrow (humerus) above
    ``elbow_z[side]`` and two (ulna, radius) from 3 mm below it; an arm not in ``elbow_z`` has the humerus
    only, to the bottom. Rendered by the phantom's partial-volume renderer at 2 mm x 5 mm."""
    import trimesh

    from bonecap.model import Mesh, Volume
    from bonecap.phantom.mri import render_volume

    def cyl(r, z0, z1, x=0.0, y=0.0):
        tm = trimesh.creation.cylinder(radius=r, height=z1 - z0, sections=64)
        tm.apply_translation([x, y, 0.5 * (z0 + z1)])
        return Mesh(tm.vertices, tm.faces, "lps")

    layers = [(cyl(110, -20, 420), "fat"), (cyl(100, -20, 420), "muscle")]
    for side, x in (("r", -200.0), ("l", 200.0)):
        layers += [(cyl(40, -20, 420, x), "fat"), (cyl(33, -20, 420, x), "muscle")]
        z_e = elbow_z.get(side, -40.0)
        layers += [(cyl(12, z_e, 420, x), "cortex"), (cyl(8, z_e + 3, 420, x), "marrow")]
        if side in elbow_z:
            for dx in (-14.0, 14.0):
                layers += [(cyl(8, -20, z_e - 3, x + dx), "cortex"), (cyl(5, -20, z_e - 5, x + dx), "marrow")]
    A = np.diag([2.0, 2.0, 5.0, 1.0])
    A[:3, 3] = [-259.0, -79.0, 0.0]
    img = render_volume(layers, A, (260, 80, 80), inplane_supersample=2, through_plane_samples=4, rng=rng_seed)
    return Volume(img, A, {"slice_thickness": 5.0})


def _forearm_template(top_z: dict[str, float]):
    """Ulnae and radii (boxes) whose tops lie at ``top_z`` (LPS), as a placed template has them."""
    import trimesh

    from bonecap.model import Bone, Mesh, Skeleton

    bones = {}
    for side, x in (("r", -200.0), ("l", 200.0)):
        for name, dx in (("ulna", -14.0), ("radius", 14.0)):
            tm = trimesh.creation.box(extents=(16, 16, 240))
            tm.apply_translation([x + dx, 0.0, top_z[side] - 120.0])
            bones[f"{name}_{side}"] = Bone(f"{name}_{side}", mesh=Mesh(tm.vertices, tm.faces, f"{name}_{side}"))
    return Skeleton(bones, world="lps")


def test_elbow_offsets_find_where_the_second_marrow_begins():
    """The arms' height from the MRI (build_mri.elbow_offsets): the forearm bones' tops (the true elbow
    step) at 200 mm (right) and 230 mm (left); a template placed 40 mm too high on the right and 25 mm too
    low on the left is told to move by -40 and +25 within the slice pitch (5 mm). An arm whose sections hold
    one marrow all the way (no forearm in the scan) gives no offset."""
    from bonecap.build_mri import elbow_offsets
    from bonecap.segmentation.skin import segment_body

    vol = _arms_scene({"r": 200.0, "l": 230.0})
    body = segment_body(vol)
    true_top = {"r": 197.0, "l": 227.0}                 # the forearm bones' cortex begins 3 mm below the step
    placed = {"r": true_top["r"] + 40.0, "l": true_top["l"] - 25.0}
    got = elbow_offsets(_forearm_template(placed), [vol], [body])
    assert set(got) == {"r", "l"}
    for side in "rl":
        assert abs(got[side] - (true_top[side] - placed[side])) <= 5.0, (side, got[side])
    # the template where the MRI has it: no move beyond the pitch
    got = elbow_offsets(_forearm_template(true_top), [vol], [body])
    assert max(abs(v) for v in got.values()) <= 5.0, got

    one = _arms_scene({"r": 200.0})
    got = elbow_offsets(_forearm_template(placed), [one], [segment_body(one)])
    assert "l" not in got and abs(got["r"] - (true_top["r"] - placed["r"])) <= 5.0, got


def test_repose_limbs_aims_the_forearm_bones_not_the_ulnar_joint():
    """build_mri.repose_limbs with the arms' "bones" aim: the forearm's section centre, not the ulna's distal
    radioulnar joint (which lies at the wrist's ulnar border), is turned onto the limb's section centre. A
    forearm whose bones hang 12 deg from the template's: aiming the bones recovers the direction within
    1 deg; aiming the joint, 12 mm beside the bones' middle on a 240 mm forearm, misses it by ~3 deg."""
    import trimesh

    from bonecap.build_mri import repose_limbs
    from bonecap.model import Bone, Mesh, Skeleton

    def forearm():
        bones = {"humerus_r": Bone("humerus_r", joint_centres={"shoulder": [0, 0, 280.0], "elbow": [0, 0, 0]})}
        for name, x, parent in (("ulna_r", -12.0, "humerus_r"), ("radius_r", 12.0, "ulna_r")):
            tm = trimesh.creation.box(extents=(14, 14, 240))
            tm.apply_translation([x, 0.0, -120.0])
            joints = {"elbow": [0, 0, 0], "distal_radioulnar": [-12.0, 0, -235.0]} if name == "ulna_r" else {}
            bones[name] = Bone(name, parent, Mesh(tm.vertices, tm.faces, name), joint_centres=joints)
        return Skeleton(bones, world="lps")

    tilt = np.radians(12.0)
    axis_true = np.array([np.sin(tilt), 0.0, -np.cos(tilt)])        # the forearm's middle, from the elbow

    class Sections:                       # the limb's section centre at height z: on the true forearm's middle
        @staticmethod
        def limb_centre(z, side, kind):
            return axis_true * (z / axis_true[2])

    def direction_error(sk):
        u = sk.bones["ulna_r"]
        d = u.bone_to_world[:3, :3] @ np.array([0.0, 0.0, -1.0])
        return float(np.degrees(np.arccos(np.clip(d @ axis_true, -1, 1))))

    errors = {}
    for aim in ("bones", "joint"):
        sk = forearm()
        turned = repose_limbs(sk, Sections(), chains=[("ulna", "distal_radioulnar", "arm", aim)])
        assert "ulna_r" in turned
        # the radius turns with the ulna (its subtree)
        assert np.allclose(sk.bones["radius_r"].bone_to_world, sk.bones["ulna_r"].bone_to_world)
        errors[aim] = direction_error(sk)
    assert errors["bones"] < 1.0, errors
    assert errors["joint"] > 2.0, errors


def test_an_opensim_template_on_a_whole_body_mri_is_refused_before_any_work(phantom, shared_data, tmp_path):
    """The whole-body MRI path places the template by the embedded skeleton's hip bones and joints; an OpenSim
    model (its pelvis holds both hips) fails with one clear line naming the model, before the stations are
    read, and writes nothing (it crashed with a KeyError at the seeds)."""
    from bonecap.build_subject import run_build_subject
    from bonecap.errors import InputError

    osim = shared_data / "bones/opensim/models/Rajagopal2016.osim"
    stations = sorted(str(p) for p in (phantom / "mri").glob("station_*"))
    out = tmp_path / "s"
    with pytest.raises(InputError, match="cannot be placed on a whole-body MRI") as err:
        run_build_subject(stations, out, generic=osim)
    assert "Rajagopal2016.osim" in str(err.value)
    assert not out.exists()


def test_personal_label_ids_keep_the_given_ones_and_number_on_above_those_in_use():
    """personal_label_meshes: given ids kept, bones without one numbered above every id in use (``taken``:
    a user's map may hold labels its table does not name), bones without a mesh left out, ids beyond the
    16-bit maps refused."""
    from bonecap.build_mri import personal_label_meshes
    from bonecap.model import Bone, Mesh, Skeleton

    box = Mesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float),
               np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]), "lps")
    sk = Skeleton({"a": Bone("a", None, box, np.eye(4)), "b": Bone("b", "a", box, np.eye(4)),
                   "c": Bone("c", "a", None, np.eye(4)), "d": Bone("d", "a", box, np.eye(4))}, world="lps")
    ids, meshes = personal_label_meshes(sk, {"a": 5})
    assert ids == {"a": 5, "b": 6, "d": 7} and [i for _, i in meshes] == [5, 6, 7]
    ids, _ = personal_label_meshes(sk, {"a": 5, "z": 12}, taken=40)
    assert ids == {"a": 5, "z": 12, "b": 41, "d": 42}
    with pytest.raises(ValueError, match="outside 1..65535"):
        personal_label_meshes(sk, {"a": 70000})


def _block_scene(offset_mm: float):
    """A 'vertebral body' (a 17 x 13 mm block: 1 mm of dark cortex round bright marrow) in muscle, in a
    body ringed by fat, imaged in 6 axial slices (1 mm pixels, 5 mm thick), and a skeleton whose ``l3`` is
    that block placed ``offset_mm`` to +x of it with a joint centre at its top (two bones without meshes
    beside it, which no shift concerns)."""
    import trimesh

    from bonecap.model import Bone, Mesh, Skeleton, Volume

    n, K = 64, 6
    x, y = np.mgrid[0:n, 0:n] + 0.0
    r = np.hypot(x - 32, y - 32)
    img = np.where(r < 30, 100.0, 0.0)
    img[(r >= 26) & (r < 30)] = 250.0                              # subcutaneous fat
    box = (np.abs(x - 32) <= 8) & (np.abs(y - 32) <= 6)          # 17 x 13 px, centred at (32, 32)
    img[box] = 0.0                                                 # cortex
    img[(np.abs(x - 32) <= 7) & (np.abs(y - 32) <= 5)] = 230.0     # marrow
    data = np.repeat(img[:, :, None], K, axis=2) + np.random.default_rng(0).normal(0, 2.0, (n, n, K))
    A = np.diag([1.0, 1.0, 5.0, 1.0])
    vol = Volume(data, A)
    body = np.repeat((r < 30)[:, :, None], K, axis=2)
    m = trimesh.creation.box(extents=(17.0, 13.0, 40.0))
    mesh = Mesh(np.asarray(m.vertices), np.asarray(m.faces), "lps")
    T = np.eye(4)
    T[:3, 3] = [32.0 + offset_mm, 32.0, 12.5]
    sk = Skeleton({"l3": Bone("l3", None, mesh, T, joint_centres={"l2_l3": np.array([0.0, 0.0, 20.0])}),
                   "rib3_r": Bone("rib3_r", "l3", None, np.eye(4)), "sternum": Bone("sternum", "l3", None, np.eye(4))},
                  world="lps")
    labels = np.zeros((n, n, K), np.int32)
    return sk, vol, body, labels


@pytest.mark.parametrize("offset_mm", [0.0, 2.0])
def test_a_density_bone_placed_off_its_image_is_shifted_back_in_plane(offset_mm):
    """density_bone_shifts: a block placed 2 mm off its image moves back towards it, in the slice plane
    only; one placed right stays (< 0.5 mm); the shift applied keeps its joint centres where they were."""
    from bonecap.build_mri import density_bone_shifts, shift_bones_keeping_joints

    sk, vol, body, labels = _block_scene(offset_mm)
    shifts = density_bone_shifts(sk, {"l3": 1}, [((labels, vol.affine), vol)], [body])
    d = shifts["l3"]
    assert d[2] == 0.0
    if offset_mm == 0.0:
        assert np.linalg.norm(d) < 0.5
    else:
        assert -2.5 < d[0] < -0.7 and abs(d[1]) < 0.5
        joint = sk.bones["l3"].landmark_in_world("l2_l3")
        origin = sk.bones["l3"].bone_to_world[:3, 3].copy()
        shift_bones_keeping_joints(sk, shifts)
        assert np.allclose(sk.bones["l3"].bone_to_world[:3, 3], origin + d)
        assert np.allclose(sk.bones["l3"].landmark_in_world("l2_l3"), joint)
    # a bone seen in too few voxels is not moved
    assert density_bone_shifts(sk, {"l3": 1}, [((labels, vol.affine), vol)], [body], min_voxels=10 ** 6) == {}


def test_the_ribs_and_the_sternum_follow_their_vertebrae():
    """thorax_follows: rib<k> takes t<k>'s shift, the sternum the mean of t1-t7's that have one."""
    from bonecap.build_mri import thorax_follows
    from bonecap.model import Bone, Skeleton

    names = ["t1", "t2", "t9", "rib1_r", "rib1_l", "rib2_r", "rib9_l", "rib5_r", "sternum"]
    sk = Skeleton({n: Bone(n, None if n == "t1" else "t1", None, np.eye(4)) for n in names}, world="lps")
    shifts = {"t1": np.array([1.0, 0.0, 0.0]), "t2": np.array([0.0, 2.0, 0.0]), "t9": np.array([0.0, 0.0, 3.0])}
    out = thorax_follows(sk, shifts)
    assert set(out) == {"rib1_r", "rib1_l", "rib2_r", "rib9_l", "sternum"}
    assert np.allclose(out["rib9_l"], [0, 0, 3]) and np.allclose(out["rib1_l"], [1, 0, 0])
    assert np.allclose(out["sternum"], [0.5, 1.0, 0.0])
    assert thorax_follows(sk, {}) == {}


def test_no_mri_knees_and_ankles_are_held_where_the_lateral_markers_put_them(phantom, tmp_path, monkeypatch):
    """Without MRI the knee and ankle centres come from the lateral markers (Plug-in Gait's rule, the
    depth from the joint widths the phantom's trials carry as Nexus stores them): in the static they lie
    within 30 mm of the truth (17-19 mm when written), at least twice as close as the six sweeps alone
    leave them (53-88 mm). Without the widths the template's depths are held (33-49 mm)."""
    from bonecap.build_subject import build_from_static
    from bonecap.io.c3d import read_c3d, write_c3d

    static = phantom / "trials/static.c3d"
    assert set(read_c3d(static).subject_parameters) >= {"LKNEEWIDTH", "RKNEEWIDTH", "LANKLEWIDTH", "RANKLEWIDTH"}
    truth = np.load(phantom / "truth/static_poses.npz", allow_pickle=True)
    jn = [str(j) for j in truth["joint_names"]]

    def errors(subject):
        sk, P = subject.skeleton, subject.static["bone_to_lab"]
        out = {}
        for joint, bone in (("knee", "tibia"), ("ankle", "talus")):
            for s in "rl":
                T = np.asarray(P[f"{bone}_{s}"])
                ours = T[:3, :3] @ sk.bones[f"{bone}_{s}"].joint_centres[joint] + T[:3, 3]
                out[f"{joint}_{s}"] = float(np.linalg.norm(ours - truth["joint_centres"][0, jn.index(f"{joint}:{bone}_{s}")]))
        return out

    held, report = build_from_static(static)
    assert report["joint_centre_targets"] == 4
    assert {k: v["width_mm"] for k, v in report["measured_joint_widths"].items()} == {
        m: read_c3d(static).subject_parameters[f"{m[0]}{'KNEE' if m.endswith('KNE') else 'ANKLE'}WIDTH"]
        for m in ("LKNE", "RKNE", "LANK", "RANK")}
    monkeypatch.setattr("bonecap.build_subject.converge_limbs", lambda sk, ms, n, b, loc, lab, first: (first, 0))
    sweeps, _ = build_from_static(static)
    monkeypatch.undo()
    e_held, e_sweeps = errors(held), errors(sweeps)
    assert max(e_held.values()) < 30.0, e_held
    assert sum(e_held.values()) < 0.5 * sum(e_sweeps.values()), (e_held, e_sweeps)

    # the same static without its measurements: the template's depths, still held
    trial = read_c3d(static)
    trial.subject_parameters = {}
    write_c3d(trial, tmp_path / "bare.c3d")
    bare, report = build_from_static(tmp_path / "bare.c3d")
    assert report["measured_joint_widths"] == {} and report["joint_centre_targets"] == 4
    assert sum(errors(bare).values()) < sum(e_sweeps.values()), (errors(bare), e_sweeps)


def test_a_width_that_is_no_joints_is_a_clear_error(phantom, tmp_path, cli):
    """A knee width in the wrong unit (1.3 m written as 1300) stops the no-MRI build with one line naming
    the file and the parameter, and nothing is written."""
    from bonecap.io.c3d import read_c3d, write_c3d

    trial = read_c3d(phantom / "trials/static.c3d")
    trial.subject_parameters = {**trial.subject_parameters, "LKNEEWIDTH": 1300.0}
    write_c3d(trial, tmp_path / "bad.c3d")
    res = cli("build-subject", "--static", str(tmp_path / "bad.c3d"), "-o", str(tmp_path / "out"))
    assert res.returncode != 0
    assert "bad.c3d" in res.stderr and "LKneeWidth = 1300 mm is not a joint width" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_joint_consistent_keeps_a_turned_shoulder_girdle():
    """The static's shoulder girdle (clavicle and scapula, one segment of the solve) keeps its solved turn on
    the thorax: the sternum lists the sternoclavicular joint once per side (``sternoclavicular_r``), and the
    rebuilt chain used to fall back to the clavicle's reference orientation there while the scapula kept the
    turn, so the acromion marker was bound to a scapula turned on its clavicle. A joint whose two copies do
    not meet at the reference keeps its gap (the bones turn about the parent's copy, as pose_skeleton turns
    them)."""
    from scipy.spatial.transform import Rotation

    from bonecap.build_subject import joint_consistent
    from bonecap.model import Bone, Skeleton

    def T(p, R=np.eye(3)):
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = R, p
        return M

    sc, ac, gh = np.array([30.0, 20.0, 1400.0]), np.array([-10.0, 170.0, 1420.0]), np.array([-20.0, 180.0, 1380.0])
    sk = Skeleton({
        "thorax": Bone("thorax", None, bone_to_world=T([0, 0, 1300]),
                       joint_centres={"sternoclavicular_r": sc - [0, 0, 1300]}),
        "clavicle_r": Bone("clavicle_r", "thorax", bone_to_world=T(sc),
                           joint_centres={"sternoclavicular": [0, 0, 0], "acromioclavicular": ac - sc}),
        # the scapula's copy of the acromioclavicular joint 9 mm from the clavicle's, as a personal skeleton's
        # may lie (seed 3: 12-13 mm): the rebuilt chain keeps that gap rather than moving the arm by it
        "scapula_r": Bone("scapula_r", "clavicle_r", bone_to_world=T(ac),
                          joint_centres={"acromioclavicular": [5.0, 0.0, 7.5], "shoulder": gh - ac}),
        "humerus_r": Bone("humerus_r", "scapula_r", bone_to_world=T(gh), joint_centres={"shoulder": [0, 0, 0]}),
    }, world="model")
    G = Rotation.from_rotvec([np.radians(15), 0, -np.radians(10)]).as_matrix()
    A = Rotation.from_rotvec([np.radians(40), 0.1, 0]).as_matrix()
    thorax = T([5.0, -3.0, 1302.0], Rotation.from_rotvec([0.02, 0.0, 0.1]).as_matrix())
    R0 = thorax[:3, :3]
    sc_lab = thorax[:3, :3] @ (sc - [0, 0, 1300]) + thorax[:3, 3]
    clav = T(sc_lab, R0 @ G)
    scap = T(clav[:3, :3] @ (ac - sc) + clav[:3, 3], R0 @ G)
    hum = T(scap[:3, :3] @ (gh - ac) + scap[:3, 3], R0 @ G @ A)
    poses = np.array([thorax, clav, scap, hum])
    wobbly = poses.copy()
    wobbly[1:, :3, 3] += [[1.0, -2.0, 0.5], [0.0, 1.5, -1.0], [2.0, 0.0, 1.0]]    # gaps at the joints
    np.testing.assert_allclose(joint_consistent(sk, wobbly), poses, atol=1e-9)


def _mirror_symmetric_head(rng, n_true, d_true):
    """Points of a head-like surface symmetric about the plane x . n_true = d_true: an ellipsoid with a
    nose and a chin off its mid-plane's front and a bump on one ear's side mirrored on the other."""
    u = rng.normal(size=(4000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    P = u * np.array([75.0, 95.0, 110.0])                       # lateral x, anterior y, superior z (local)
    P = P[P[:, 0] >= 0]                                           # one half ...
    bump = np.array([60.0, 10.0, 0.0])
    P += 8.0 * np.exp(-np.sum((P - bump) ** 2, axis=1) / 400.0)[:, None] * np.array([1.0, 0.0, 0.0])
    nose = (np.abs(P[:, 0]) < 15) & (P[:, 1] > 70) & (np.abs(P[:, 2] + 10) < 25)
    P[nose, 1] += 12.0 * (1 - np.abs(P[nose, 0]) / 15)
    P = np.concatenate([P, P * np.array([-1.0, 1.0, 1.0])])      # ... and its mirror image
    # the local mid-plane x = 0 turned onto n_true and moved to d_true
    from scipy.spatial.transform import Rotation

    ex = np.array([1.0, 0.0, 0.0])
    axis = np.cross(ex, n_true)
    R = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.arccos(ex @ n_true)).as_matrix()
    return P @ R.T + d_true * n_true


def test_the_head_s_plane_of_symmetry_is_found_from_a_turned_start():
    """head_symmetry_plane: a symmetric head turned 6 deg and moved 4 mm across, started from the unturned
    plane: the plane comes back within 0.2 deg and 0.3 mm; bad input is refused."""
    from bonecap.build_mri import head_symmetry_plane

    rng = np.random.default_rng(3)
    n_true = np.array([np.cos(np.radians(6.0)), np.sin(np.radians(6.0)), 0.0])
    P = _mirror_symmetric_head(rng, n_true, 4.0)
    P = P + rng.normal(0, 0.3, P.shape)
    n, d, rms = head_symmetry_plane(P, np.array([1.0, 0.0, 0.0]), 0.0)
    assert np.degrees(np.arccos(min(1.0, n @ n_true))) < 0.2
    assert abs(d - 4.0) < 0.3
    assert rms < 2.0
    # the start's side is kept
    n2, d2, _ = head_symmetry_plane(P, np.array([-1.0, 0.0, 0.0]), 0.0)
    assert np.allclose(n2, -n, atol=1e-3) and abs(d2 + d) < 0.1
    with pytest.raises(ValueError, match="at least 10 points"):
        head_symmetry_plane(P[:5], n_true, 0.0)
    with pytest.raises(ValueError, match="non-zero normal"):
        head_symmetry_plane(P, np.zeros(3), 0.0)


def test_a_skull_turned_off_its_head_is_turned_back_onto_the_head_s_symmetry():
    """_skull_onto_symmetry: the template's skull, its scalp (6 mm out along its normals) the head's skin,
    the skull placed 4 deg turned about the vertical and 3 mm across: its lateral axis comes back within
    1 deg and its origin onto the mid-plane within 1 mm; its turn about the lateral axis is not touched.
    A skin that is not symmetric (one side cut away) leaves the fit as it was."""
    import trimesh
    from scipy.spatial.transform import Rotation

    from bonecap.build_mri import _skull_onto_symmetry
    from bonecap.skeleton.template import load_template

    sk = load_template("default")
    T_true = np.eye(4)
    T_true[:3, 3] = [0.0, 0.0, 1600.0]
    b = sk.bones["skull"]
    tm = trimesh.Trimesh(b.mesh.vertices, b.mesh.faces, process=False)
    local_skin = tm.vertices + 6.0 * tm.vertex_normals
    # world: the template's frame (x anterior, y superior, z lateral) laid into an LPS-like world where z is up
    W = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])   # local -> world rotation
    T_true[:3, :3] = W
    skin = local_skin @ W.T + T_true[:3, 3]
    T_off = T_true.copy()
    yaw = Rotation.from_rotvec(np.radians(4.0) * W[:, 1]).as_matrix()     # about the skull's superior axis
    T_off[:3, :3] = yaw @ W
    T_off[:3, 3] += 3.0 * W[:, 2]
    skull_world = b.mesh.vertices @ T_off[:3, :3].T + T_off[:3, 3]
    A, rep = _skull_onto_symmetry(np.eye(4), T_off, skull_world, skin)
    assert rep["used"] and 3.0 < rep["turn_deg"] < 5.0
    R = A[:3, :3] @ T_off[:3, :3]
    o = A[:3, :3] @ T_off[:3, 3] + A[:3, 3]
    assert np.degrees(np.arccos(min(1.0, R[:, 2] @ W[:, 2]))) < 1.0
    assert abs((o - T_true[:3, 3]) @ W[:, 2]) < 1.0
    # the turn about the lateral axis (the vault's pitch) is left as the fit had it
    assert abs(np.degrees(np.arctan2(R[:, 0] @ W[:, 1], R[:, 0] @ W[:, 0]))) < 1.0
    # half a head: no plane of symmetry is trusted
    half = skin[(skin - T_true[:3, 3]) @ W[:, 2] > -10.0]
    A2, rep2 = _skull_onto_symmetry(np.eye(4), T_off, skull_world, half)
    assert not rep2["used"] and np.allclose(A2, np.eye(4))


def test_forearm_capsule_markers_rebind_the_forearms_markers_from_its_stacks():
    """Capsules at the wrist markers' spots in three stacks (the radius turned, the ulna still) bind the
    markers where the capsules say, whatever the old binding; the humerus's marker keeps its own; a capsule
    beyond reach or a stray one is not taken."""
    import trimesh
    from scipy.spatial.transform import Rotation

    from bonecap.build_mri import FOREARM_CAPSULE_MATCH_MM, forearm_capsule_markers
    from bonecap.model import Bone, Mesh, Skeleton
    from bonecap.subject import MarkerBinding

    def pose(rotvec_deg, t):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
        T[:3, 3] = t
        return T

    U = pose([0, 0, 10], [0, 0, 0])
    R = pose([0, 0, -5], [25, 0, 0])
    H = pose([0, 0, 0], [0, 0, 280])
    sk = Skeleton({"humerus_r": Bone("humerus_r", None, bone_to_world=H),
                   "ulna_r": Bone("ulna_r", "humerus_r", bone_to_world=U),
                   "radius_r": Bone("radius_r", "humerus_r", bone_to_world=R)}, world="lps")
    # a forearm of skin: a cylinder of radius 30 mm about the z axis, the markers on it
    skin = trimesh.creation.cylinder(radius=30.0, height=600, sections=128).subdivide_to_size(6.0)
    skin = Mesh(np.asarray(skin.vertices), np.asarray(skin.faces), "lps")
    true_world = {"RWRA": np.array([37.0, 0.0, -200.0]), "RWRB": np.array([-37.0, 0.0, -190.0]),
                  "RELB": np.array([37.0, 0.0, 250.0])}
    bone_of = {"RWRA": "radius_r", "RWRB": "ulna_r", "RELB": "humerus_r"}
    caps_mri = {n: p * (34.0 / 37.0) * np.array([1, 1, 0]) + p * np.array([0, 0, 1]) for n, p in true_world.items()}

    def local(n, p):
        B = sk.bones[bone_of[n]].bone_to_world
        return B[:3, :3].T @ (p - B[:3, 3])

    # the old binding 6 mm off (RWRA), 4 mm off (RWRB); the humerus's marker 5 mm off
    markers = {n: MarkerBinding(n, bone_of[n], local(n, p + off), "static")
               for (n, p), off in zip(true_world.items(), ([0, 6, 0], [0, 0, 4], [0, 5, 0]))}
    stacks = []
    for turn in (0.0, 95.0, 170.0):
        # the radius turns about the z axis through the ulna; the ulna registered 2 mm off-axis in each stack
        move_u = pose([0, 0, 0], [2, -1, 3])
        move_r = pose([0, 0, turn], [0, 0, 0]) @ move_u
        Ts = {"ulna_r": move_u @ U, "radius_r": move_r @ R}
        caps = [(move_r if bone_of[n] == "radius_r" else move_u)[:3, :3] @ c
                + (move_r if bone_of[n] == "radius_r" else move_u)[:3, 3] for n, c in caps_mri.items()]
        caps.append(caps[0] + [0, 0, FOREARM_CAPSULE_MATCH_MM + 30])     # a stray capsule, far from all
        stacks.append((Ts, np.array(caps)))
    rebound, report = forearm_capsule_markers(stacks, sk, "r", markers, skin)
    assert set(rebound) == {"RWRA", "RWRB"}                 # the epicondyle marker rides the humerus
    for n, b in rebound.items():
        assert b.source == "capsule" and b.bone == bone_of[n]
        np.testing.assert_allclose(b.local, local(n, true_world[n]), atol=0.3)
        assert report[n]["stacks"] == 3 and report[n]["spread_mm"] < 0.01
    assert report["RWRA"]["moved_mm"] == pytest.approx(6.0, abs=0.3)
    # the old binding beyond reach: no capsule is named, nothing rebound
    far = dict(markers, RWRA=MarkerBinding("RWRA", "radius_r", local("RWRA", true_world["RWRA"] + [0, 25, 0])))
    rebound, _ = forearm_capsule_markers(stacks, sk, "r", far, skin)
    assert "RWRA" not in rebound and "RWRB" in rebound
    # a marker a whole-body capsule bound keeps that binding
    kept = dict(markers, RWRB=MarkerBinding("RWRB", "ulna_r", markers["RWRB"].local, "capsule"))
    rebound, _ = forearm_capsule_markers(stacks, sk, "r", kept, skin)
    assert set(rebound) == {"RWRA"}
    # a stack whose capsule lies off the skin once carried back (the skin slid over the bone) is not used;
    # stacks that disagree bind nothing
    def moved_cap(k, shift):
        st = [(Ts, caps.copy()) for Ts, caps in stacks]
        st[k][1][0] = st[k][1][0] + shift
        return st
    Ts2 = stacks[2][0]
    out_of_skin = Ts2["radius_r"][:3, :3] @ (R[:3, :3].T @ np.array([6.0, 0.0, 0.0]))   # radially out at turn 170
    rebound, report = forearm_capsule_markers(moved_cap(2, out_of_skin), sk, "r", markers, skin)
    assert report["RWRA"]["off_skin"] == 1 and report["RWRA"]["stacks"] == 2
    np.testing.assert_allclose(rebound["RWRA"].local, local("RWRA", true_world["RWRA"]), atol=0.3)
    along = Ts2["radius_r"][:3, :3] @ (R[:3, :3].T @ np.array([0.0, 0.0, 9.0]))          # along the forearm
    rebound, report = forearm_capsule_markers(moved_cap(2, along), sk, "r", markers, skin)
    assert "RWRA" not in rebound and report["RWRA"]["not_bound"] == "the stacks disagree"
    # without the skin's normals a capsule does not say where its marker is
    assert forearm_capsule_markers(stacks, sk, "r", markers, None)[0] == {}
    with pytest.raises(ValueError, match="side"):
        forearm_capsule_markers(stacks, sk, "x", markers, skin)
