"""The real knee MRI (sagittal spin echo) through build-subject with the seeds of ``examples/knee_seeds.yaml``.

A local scan in a non-axial orientation, segmented in its own slices: femur,
tibia, patella and fibular head as separate closed meshes, in anatomically
plausible places and sizes, with contour overlays in ``qc/``. The slice rules'
pieces (the muscle level where bone fills the view, marrow cut loose from fat
through a gap in the cortex, seeds that may stay unmatched) are unit-tested
in ``test_segmentation_rules.py``.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from conftest import ROOT


@pytest.fixture(scope="module")
def knee_subject(shared_data, tmp_path_factory):
    from conftest import run_cli

    out = tmp_path_factory.mktemp("knee") / "subject"
    r = run_cli("build-subject", shared_data / "mri" / "knee_mese_t2_echo1_dicom",
                "--seeds", ROOT / "examples" / "knee_seeds.yaml", "-o", out)
    assert r.returncode == 0, r.stderr[-2000:]
    return out


@pytest.mark.shared
def test_knee_bones_are_separate_closed_meshes(knee_subject):
    import trimesh

    meshes = {b: trimesh.load(knee_subject / "extracted" / f"{b}.ply")
              for b in ("femur_r", "tibia_r", "patella_r", "fibula_r")}
    for b, m in meshes.items():
        assert m.is_watertight, b
        assert m.volume > 0, b
    # sizes in the field of view (24 sagittal slices of 160 mm): the distal femur and proximal tibia are
    # the big ones, a patella is ~10-20 cm^3, the fibular head a few
    vol = {b: m.volume / 1000.0 for b, m in meshes.items()}
    assert vol["femur_r"] > 60 and vol["tibia_r"] > 40, vol
    assert 3 < vol["patella_r"] < 30, vol
    assert 0.5 < vol["fibula_r"] < 15, vol
    c = {b: m.center_mass for b, m in meshes.items()}
    # LPS: the femur above the tibia, the patella in front of the femur, the fibula behind the tibia and lateral
    assert c["femur_r"][2] > c["tibia_r"][2] + 30
    assert c["patella_r"][1] < c["femur_r"][1] - 25
    assert c["fibula_r"][1] > c["tibia_r"][1] and c["fibula_r"][0] < c["tibia_r"][0]
    # separate: the meshes' filled 1 mm voxels barely overlap (surface smoothing at the joints); trimesh's
    # `contains` casts rays per point and needs tens of GB here, voxels do not
    cells = {b: {tuple(v) for v in np.round(m.voxelized(1.0).fill().points).astype(int)}
             for b, m in meshes.items()}
    for a, b in (("femur_r", "tibia_r"), ("femur_r", "patella_r"), ("tibia_r", "fibula_r")):
        shared = len(cells[a] & cells[b]) / min(len(cells[a]), len(cells[b]))
        assert shared < 0.05, (a, b, shared)


@pytest.mark.shared
def test_knee_report_and_overlays(knee_subject):
    report = json.loads((knee_subject / "report.json").read_text())
    assert {"femur_r", "tibia_r", "patella_r", "fibula_r"} <= set(report["extracted_bones"])
    pngs = list((knee_subject / "qc").glob("contours_*.png"))
    assert pngs and all(p.stat().st_size > 10_000 for p in pngs)
    from bonecap.io.imaging import read_nifti

    lab = read_nifti(knee_subject / "labels" / "station_1.nii.gz")
    ids = set(np.unique(np.asarray(lab.data)).tolist())
    assert len(ids - {0}) == 4
