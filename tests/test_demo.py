"""``bonecap demo``: every stage that exists, end to end, on a template."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from bonecap.io.c3d import read_c3d
from bonecap.io.gltf import summarize_gltf
from gltf_validation import assert_clean, run_validator


def _check_demo(out, report):
    assert report["skeleton"]["bones_with_mesh"] > 10
    assert len(list((out / "skeleton/meshes").glob("*.ply"))) == report["skeleton"]["bones_with_mesh"]
    assert len(report["outputs"]["pictures"]) == 2
    for png in report["outputs"]["pictures"]:
        assert Path(png).suffix == ".png" and Path(png).stat().st_size > 10_000
    trial = read_c3d(report["outputs"]["trial_c3d"])
    assert trial.n_frames == report["motion"]["frames"] and len(trial.labels) == report["markers"]["placed"]
    # 0.5 mm marker noise: the rigid fit over all markers recovers the motion far better than that
    assert report["motion"]["rotation_error_deg_max"] < 0.5
    assert report["motion"]["origin_error_mm_max"] < 2.0
    assert 0.3 < report["motion"]["marker_residual_mm_rms"] < 1.2
    anim = summarize_gltf(report["outputs"]["animation_glb"])
    assert anim["animations"] == 1 and anim["frames"] == trial.n_frames
    assert anim["duration"] == pytest.approx((trial.n_frames - 1) / trial.rate, rel=1e-4)
    for key in ("animation_glb", "skeleton_glb"):
        assert_clean(run_validator(report["outputs"][key]))
    assert json.loads((out / "report.json").read_text())["motion"] == report["motion"]


def test_demo_on_an_opensim_template(shared_data, tmp_path):
    from bonecap.demo import run_demo

    out = tmp_path / "demo"
    report = run_demo(out, shared_data / "bones/opensim/models/Rajagopal2016.osim", n_frames=60, phantom=False)
    assert report["markers"]["placed"] == 54  # Rajagopal's 66 markers less its 12 virtual ones
    _check_demo(out, report)


def test_demo_cli_on_the_default_template(tmp_path, cli):
    out = tmp_path / "demo"
    res = cli("demo", "-o", out, "--frames", "40", "--preset", "tiny")
    assert res.returncode == 0, res.stderr
    assert "animated bones" in res.stdout
    report = json.loads((out / "report.json").read_text())
    assert report["markers"]["set"] == "plug_in_gait_full_body" and report["markers"]["placed"] == 39
    _check_demo(out, report)
    assert np.isfinite(report["skeleton"]["triangles"])
    # stage 5: the reduced phantom and its truth
    assert report["phantom"]["preset"] == "tiny" and report["phantom"]["stations"] >= 2 and len(report["phantom"]["forearm_stacks"]) == 3
    assert (out / "phantom/truth/README.md").is_file()
    assert sorted(p.name for p in (out / "phantom/trials").glob("*.c3d")) == sorted(
        f"{t}.c3d" for t in report["phantom"]["trials"])
    # stages 6-8: build-subject on the phantom, animate its trials, evaluate both
    assert (out / "subject/subject.yaml").is_file() and report["subject"]["bones"] == 90
    assert report["subject"]["markers_bound"] >= 57
    # the walk corrected both femurs' twist (build-subject --functional)
    assert set(report["subject"]["femurs_turned_deg"]) == {"femur_r", "femur_l"}
    assert set(report["animate"]) == set(report["phantom"]["trials"])
    for t, r in report["animate"].items():
        assert (out / "animate" / f"{t}.glb").is_file() and r["valid_share"] > 0.5
    ev = report["evaluation"]
    assert 0 < ev["subject"]["oracle_dice"] <= 1 and ev["subject"]["personal_surface_mean_mm"] > 0
    # the long bones' Dice, which the slice rules are for (the tiny preset's coarse slices: ~0.24)
    assert 0 < ev["subject"]["long_bone_dice_median"] < 1
    # the density rule's bones, as the rule found them and refined from the personal map (the tiny preset's
    # 15 mm slices: both 0.0 here, the phantoms of docs/benchmarks.md ~0.3 and ~0.85)
    rb = ev["subject"]["refined_bones_dice_median"]
    assert 0 <= rb["dice"] <= rb["refined_dice"] <= 1
    assert ev["motion"]["bones"] > 20 and np.isfinite(ev["motion"]["deg_median_over_bones"])
    assert "evaluate vs truth" in res.stdout and "refined" in res.stdout
