"""Marker sets: loading, inheritance, label matching, errors, placement."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from bonecap.errors import DataError, FormatError, InputError
from bonecap.markers import (available_marker_sets, check_marker_set, load_marker_set, match_labels,
                             place_markers)
from bonecap.model import Bone, Mesh, Skeleton

PIG_39 = """LFHD RFHD LBHD RBHD C7 T10 CLAV STRN RBAK LSHO LUPA LELB LFRM LWRA LWRB LFIN RSHO RUPA RELB
RFRM RWRA RWRB RFIN LASI RASI LPSI RPSI LTHI LKNE LTIB LANK LHEE LTOE RTHI RKNE RTIB RANK RHEE RTOE""".split()


def test_shipped_sets():
    assert {"plug_in_gait_full_body", "kojima_paper"} <= set(available_marker_sets())


def test_plug_in_gait_has_the_39_markers():
    pig = load_marker_set("plug_in_gait_full_body")
    assert sorted(pig.physical) == sorted(PIG_39)
    assert pig.markers["SACR"].optional
    for m in pig.markers.values():
        assert m.bone and m.landmark and m.tracks and m.offset_mm > 0


def test_paper_set_extends_pig_with_distinct_names():
    paper = load_marker_set("kojima_paper")
    assert set(PIG_39) <= set(paper.physical)
    added = set(paper.physical) - set(PIG_39)
    assert {"RSHA", "RSHP", "RELA", "RELP", "RMEP", "LMEP", "RIPIP", "RIDIP", "RRPIP", "RRDIP"} <= added
    # PiG's RSHO stays the acromion marker, RELB the lateral epicondyle.
    assert paper.markers["RSHO"].landmark == "acromion"
    assert paper.markers["RELB"].landmark == "lateral_epicondyle"
    rule = paper.paper_solver["humerus_r"]
    assert rule["proximal"]["pair"] == ["RSHA", "RSHP"] and rule["twist"] == ["RELP", "RELA"]
    # Every marker named by the solver table exists in the set.
    for bone, r in paper.paper_solver.items():
        named = list(r["twist"])
        for end in ("proximal", "distal"):
            named += r[end].get("pair", []) + ([r[end]["marker"]] if "marker" in r[end] else [])
        assert set(named) <= set(paper.markers), bone


def test_match_labels_uses_aliases_and_ignores_case():
    pig = load_marker_set("plug_in_gait_full_body")
    found = match_labels(pig, ["lasi", "R.ASIS", "RKNEE", "Unrelated"])
    assert found == {"LASI": "lasi", "RASI": "R.ASIS", "RKNE": "RKNEE"}


def test_unknown_set_and_bad_yaml(tmp_path):
    with pytest.raises(InputError, match="unknown marker set"):
        load_marker_set("no_such_set")
    bad = tmp_path / "bad.yaml"
    bad.write_text("markers:\n  X: {landmark: foo}\n")
    with pytest.raises(FormatError, match="bone"):
        load_marker_set(bad)
    loop = tmp_path / "loop.yaml"
    loop.write_text("name: loop\nextends: " + str(loop) + "\nmarkers: {}\n")
    with pytest.raises(FormatError, match="loop"):
        load_marker_set(loop)


def _box_skeleton() -> Skeleton:
    box = trimesh.creation.box(extents=[20.0, 20.0, 20.0])
    mesh = Mesh(box.vertices, box.faces)
    T = np.eye(4)
    T[:3, 3] = [100.0, 0.0, 0.0]
    bone = Bone("block", mesh=mesh, bone_to_world=T, landmarks={"top": [0.0, 0.0, 10.0], "side": [10.0, 0, 0]})
    return Skeleton({"block": bone})


def test_place_markers_pushes_along_the_surface_normal(tmp_path):
    ms = tmp_path / "ms.yaml"
    ms.write_text("name: t\nmarkers:\n  TOP: {bone: block, landmark: top, offset_mm: 7}\n"
                  "  SIDE: {bone: block, landmark: side, offset_mm: 3}\n")
    placed = place_markers(load_marker_set(ms), _box_skeleton())
    assert np.allclose(placed["TOP"], [100.0, 0.0, 17.0])
    assert np.allclose(placed["SIDE"], [113.0, 0.0, 0.0])


def test_missing_landmark_is_a_clear_error(tmp_path):
    ms = tmp_path / "ms.yaml"
    ms.write_text("name: t\nmarkers:\n  A: {bone: block, landmark: nowhere}\n  B: {bone: femur_r, landmark: x}\n")
    with pytest.raises(DataError) as exc:
        check_marker_set(load_marker_set(ms), _box_skeleton())
    msg = str(exc.value)
    assert "A: bone 'block' has no landmark 'nowhere'" in msg and "B: no bone 'femur_r'" in msg


def test_opensim_marker_set_places_like_opensim(shared_data):
    """Rajagopal2016's MarkerSet as a marker set: 66 markers, 12 virtual, placed where
    the independently derived ground coordinates put them."""
    import csv

    from bonecap.skeleton.opensim import read_osim

    osim = shared_data / "bones/opensim/models/Rajagopal2016.osim"
    ms = load_marker_set(osim)
    assert len(ms.markers) == 66
    virtual = {n for n, m in ms.markers.items() if m.virtual}
    assert len(virtual) == 12 and "RKJC" in virtual and "RASI" not in virtual
    assert set(ms.physical) == set(ms.markers) - virtual
    placed = place_markers(ms, read_osim(osim, load_meshes=False), names=list(ms.markers))
    rows = list(csv.DictReader(open(shared_data / "bones/opensim/rajagopal2016_default_pose_ply/markers_in_ground.csv")))
    assert len(rows) == 66
    cols = [c for c in rows[0] if "ground" in c.lower()]
    assert len(cols) == 3, rows[0].keys()
    for r in rows:
        ref = np.array([float(r[c]) for c in cols]) * 1000.0  # metres -> mm
        assert np.allclose(placed[r[next(iter(r))]], ref, atol=0.1), r
