"""The command line as a user meets it: help, inspect on real files, one-line errors."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from bonecap.cli import main


def test_help_lists_commands(cli):
    res = cli("--help")
    assert res.returncode == 0
    assert "inspect" in res.stdout
    res = cli("inspect", "--help")
    assert res.returncode == 0 and "--json" in res.stdout


@pytest.mark.parametrize("argv", [[], ["inspect"], ["no-such-command"], ["inspect", "--bogus", "x"]])
def test_bad_usage_exits_2(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2


def test_inspect_c3d_in_metres_reports_units_as_stored(cli, shared_data, tmp_path):
    path = shared_data / "c3d/optitrack_pig_fullbody/ktk_kinematics_tennis_serve.c3d"
    res = cli("inspect", path, "--json", "-o", tmp_path)
    assert res.returncode == 0, res.stderr
    summary = json.loads(res.stdout)
    assert summary["units_stored"].strip().lower() == "m"
    assert summary["frames"] == 1092 and summary["rate"] == pytest.approx(50)
    assert summary["marker_count"] == 39
    assert "Derrick" in summary["prefixes"]
    written = json.loads((tmp_path / "ktk_kinematics_tennis_serve.c3d.summary.json").read_text())
    assert written == summary


def test_inspect_c3d_gap_counts(cli, shared_data):
    path = shared_data / "c3d/optitrack_pig_fullbody/ktk_kinematics_tennis_serve_nan.c3d"
    res = cli("inspect", path, "--json")
    assert res.returncode == 0, res.stderr
    gaps = json.loads(res.stdout)["gap_samples"]
    assert gaps["RSHO"] > 0
    assert gaps["RSHO"] == max(gaps.values())


def test_inspect_text_output_is_readable(cli, shared_data):
    res = cli("inspect", shared_data / "c3d/vicon_pig_fullbody/pycgm_Test_Static_trial.c3d")
    assert res.returncode == 0, res.stderr
    assert "frames: 498" in res.stdout
    assert "LASI" in res.stdout


def test_inspect_dicom_folder(cli, shared_data):
    res = cli("inspect", shared_data / "mri/knee_mese_t2_echo1_dicom", "--json")
    assert res.returncode == 0, res.stderr
    series = json.loads(res.stdout)["series"]
    assert len(series) == 1
    assert list(series[0]["shape"]) == [256, 256, 24]
    assert np.allclose(series[0]["spacing"], [0.625, 0.625, 4.0], atol=1e-3)


@pytest.mark.parametrize("rel,shape", [
    ("mri/ct_pelvis_totalseg/example_ct.nii.gz", None),
    ("mri/knee_dess_bone_labels/SAG_3D_DESS_RIGHT_bones_cart_men_fib-label.nrrd", [384, 384, 160]),
])
def test_inspect_nifti_and_nrrd(cli, shared_data, rel, shape):
    res = cli("inspect", shared_data / rel, "--json")
    assert res.returncode == 0, res.stderr
    series = json.loads(res.stdout)["series"]
    assert len(series) == 1 and len(series[0]["shape"]) == 3
    if shape:
        assert list(series[0]["shape"]) == shape


def test_inspect_mesh(cli, shared_data):
    res = cli("inspect", shared_data / "bones/opensim/Geometry/femur_r.vtp", "--json")
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout)["triangles"] > 100


# --- bad input: one line, exit 1, nothing written -----------------------------------------

def _assert_one_line_error(res, path):
    assert res.returncode == 1, (res.stdout, res.stderr)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("bonecap: error: ")
    assert str(path) in lines[0]


def test_text_file_named_c3d(cli, tmp_path):
    bad = tmp_path / "notes.c3d"
    bad.write_text("this is not a motion capture file\n" * 40)
    out = tmp_path / "out"
    res = cli("inspect", bad, "-o", out)
    _assert_one_line_error(res, bad)
    assert not out.exists() or not any(out.iterdir())


@pytest.mark.parametrize("keep", [600, 0.6])
def test_truncated_c3d(cli, shared_data, tmp_path, keep):
    src = (shared_data / "c3d/vicon_pig_fullbody/pycgm_Test_Movement_trial.c3d").read_bytes()
    n = keep if isinstance(keep, int) else int(len(src) * keep)
    bad = tmp_path / "cut.c3d"
    bad.write_bytes(src[:n])
    out = tmp_path / "out"
    res = cli("inspect", bad, "-o", out)
    _assert_one_line_error(res, bad)
    assert not out.exists() or not any(out.iterdir())


def test_empty_folder(cli, tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    _assert_one_line_error(cli("inspect", empty), empty)


def test_missing_path(cli, tmp_path):
    missing = tmp_path / "nothing_here.c3d"
    _assert_one_line_error(cli("inspect", missing), missing)


def test_dicom_series_with_a_slice_removed(cli, shared_data, tmp_path):
    src = sorted((shared_data / "mri/knee_mese_t2_echo1_dicom").glob("*.dcm"))
    folder = tmp_path / "knee_gap"
    folder.mkdir()
    import pydicom

    # Remove the slice that sits in the middle along the slice normal, not by file name.
    by_pos = sorted(src, key=lambda f: float(pydicom.dcmread(f, stop_before_pixels=True).SliceLocation))
    for f in by_pos[:12] + by_pos[13:]:
        shutil.copy(f, folder / f.name)
    out = tmp_path / "out"
    res = cli("inspect", folder, "-o", out)
    _assert_one_line_error(res, folder)
    assert "slice" in res.stderr.lower()
    assert not out.exists() or not any(out.iterdir())


def test_one_bad_input_among_good_writes_nothing(cli, shared_data, tmp_path):
    good = shared_data / "c3d/encodings/sample02/pc_real.c3d"
    bad = tmp_path / "bad.c3d"
    bad.write_bytes(b"\x00" * 100)
    out = tmp_path / "out"
    res = cli("inspect", good, bad, "-o", out)
    _assert_one_line_error(res, bad)
    assert not out.exists() or not any(out.iterdir())


def test_mixed_folder_gives_each_series(cli, shared_data, tmp_path):
    """A folder holding two DICOM series and a stray text file: both series, no error."""
    from bonecap.io.imaging import write_dicom_series
    from bonecap.model import Volume

    folder = tmp_path / "mixed"
    shutil.copytree(shared_data / "mri/knee_mese_t2_echo1_dicom", folder)
    vol = Volume(np.arange(4 * 5 * 6, dtype=float).reshape(4, 5, 6), np.diag([2.0, 2.0, 5.0, 1.0]))
    write_dicom_series(vol, folder / "synthetic", series_description="synthetic")
    (folder / "README.txt").write_text("scanner notes")
    res = cli("inspect", folder, "--json")
    assert res.returncode == 0, res.stderr
    shapes = sorted(tuple(s["shape"]) for s in json.loads(res.stdout)["series"])
    assert shapes == [(4, 5, 6), (256, 256, 24)]
