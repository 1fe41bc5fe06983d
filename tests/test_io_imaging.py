"""Tests of bonecap.io.imaging: DICOM series, NIfTI and NRRD <-> Volume.

Real files are read in place from ``../shared/data/mri``; anything derived
from them (a series with a slice removed, shuffled names) is built in
``tmp_path``.
"""

from __future__ import annotations

import random
import shutil
import tempfile
from pathlib import Path

import nibabel as nib
import nrrd
import numpy as np
import pydicom
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydicom.uid import ExplicitVRBigEndian, JPEG2000Lossless, generate_uid

from bonecap.errors import DataError, InputError
from bonecap.io import imaging
from bonecap.io.imaging import (read_dicom_series, read_nifti, read_nrrd, read_volumes, volume_summary,
                                write_dicom_series, write_nifti, write_nrrd)
from bonecap.model import Volume

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
MRI = DATA / "mri"
KNEE = MRI / "knee_mese_t2_echo1_dicom"
DESS = MRI / "knee_dess_bone_labels" / "SAG_3D_DESS_RIGHT_bones_cart_men_fib-label.nrrd"
CT = MRI / "ct_pelvis_totalseg" / "example_ct.nii.gz"


@pytest.fixture(scope="module")
def mri() -> Path:
    if not DATA.is_dir():
        pytest.skip(f"shared data not found at {DATA}")
    return MRI


@pytest.fixture(scope="module")
def knee(mri) -> Volume:
    (vol,) = read_dicom_series(KNEE)
    return vol


def _knee_headers() -> list[tuple[Path, pydicom.Dataset]]:
    return [(p, pydicom.dcmread(p, stop_before_pixels=True)) for p in sorted(KNEE.iterdir())]


def _rotation(axis, degrees: float) -> np.ndarray:
    """Rodrigues' rotation about ``axis``."""
    axis = np.asarray(axis, dtype=float)
    axis /= np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    t = np.deg2rad(degrees)
    return np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K


def _synthetic(shape=(40, 33, 6), *, degrees=6.0, spacing=(0.7, 1.1, 2.5), origin=(-40.5, 12.25, 100.125),
               seed=0, metadata=None) -> Volume:
    """An oblique, anisotropic, float volume with a non-zero origin."""
    rng = np.random.default_rng(seed)
    affine = np.eye(4)
    affine[:3, :3] = _rotation([1, 2, 3], degrees) @ np.diag(spacing)
    affine[:3, 3] = origin
    i, j, k = np.meshgrid(*(np.arange(n) for n in shape), indexing="ij")
    data = (100 * np.sin(i / 5.0) + 30 * j - 7.5 * k + rng.normal(0, 3, shape)).astype(np.float32)
    return Volume(data, affine, dict(metadata or {}))


def _all_indices(shape) -> np.ndarray:
    return np.stack(np.meshgrid(*(np.arange(n) for n in shape), indexing="ij"), -1).reshape(-1, 3)


# --------------------------------------------------------------------------- #
# The real knee series
# --------------------------------------------------------------------------- #


@pytest.mark.shared
def test_knee_series_geometry_from_positions(knee):
    headers = _knee_headers()
    # The files number their slices 1, 9, 17... (8 echoes interleaved in the
    # original) and are big-endian: both must pass without complaint.
    assert sorted(int(ds.InstanceNumber) for _, ds in headers) == list(range(1, 186, 8))
    assert all(ds.file_meta.TransferSyntaxUID == ExplicitVRBigEndian for _, ds in headers)

    assert knee.shape == (256, 256, 24)
    assert knee.data.dtype == np.float32
    np.testing.assert_allclose(knee.spacing, [0.625, 0.625, 4.0], atol=1e-3)
    assert knee.metadata["slice_thickness"] == pytest.approx(3.0)  # not the 4 mm spacing
    assert knee.metadata["transfer_syntax"] == ExplicitVRBigEndian
    assert knee.metadata["echo_number"] == 1 and knee.metadata["echo_time"] == pytest.approx(6.312)
    assert knee.metadata["series_number"] == 8 and knee.metadata["modality"] == "MR"
    assert knee.metadata["instance_numbers"][:3] == [1, 9, 17]

    # Independent world coordinate from the first and last files' IPP/IOP.
    iop = np.array(headers[0][1].ImageOrientationPatient, dtype=float)
    normal = np.cross(iop[:3], iop[3:])
    by_z = sorted(headers, key=lambda h: np.dot(np.array(h[1].ImagePositionPatient, float), normal))
    (first_path, first), (last_path, last) = by_z[0], by_z[-1]
    row_sp, col_sp = (float(v) for v in last.PixelSpacing)
    i, j = 17, 201
    expected = np.array(last.ImagePositionPatient, float) + i * col_sp * iop[:3] + j * row_sp * iop[3:]
    np.testing.assert_allclose(knee.index_to_world([i, j, 23]), expected, atol=1e-3)
    np.testing.assert_allclose(knee.index_to_world([0, 0, 0]), np.array(first.ImagePositionPatient, float),
                               atol=1e-6)
    # i is the column and j the row: the pixel array is transposed.
    assert knee.data[i, j, 23] == pydicom.dcmread(last_path).pixel_array[j, i]
    assert knee.data[j, i, 0] == pydicom.dcmread(first_path).pixel_array[i, j]


@pytest.mark.shared
def test_knee_agrees_with_highdicom(knee):
    import highdicom as hd

    ref = hd.get_volume_from_series([pydicom.dcmread(p) for p in sorted(KNEE.iterdir())])
    # highdicom indexes (slice, row, column) with slices the other way round.
    assert np.array_equal(ref.array[::-1].transpose(2, 1, 0), knee.data)
    idx = np.array([[0, 0, 0], [5, 200, 100], [23, 255, 255], [11, 0, 255]])
    ours = knee.index_to_world(np.stack([idx[:, 2], idx[:, 1], 23 - idx[:, 0]], axis=1))
    np.testing.assert_allclose(ours, idx @ ref.affine[:3, :3].T + ref.affine[:3, 3], atol=1e-3)


@pytest.mark.shared
def test_knee_summary(knee):
    s = volume_summary(knee)
    assert s["shape"] == [256, 256, 24]
    np.testing.assert_allclose(s["spacing"], [0.625, 0.625, 4.0], atol=1e-3)
    np.testing.assert_allclose(s["direction_cosines"]["k"], knee.direction[:, 2])
    assert s["orientation"] == "PIR"  # sagittal: rows run posterior, columns inferior, slices right
    assert s["file_count"] == 24 and s["dtype"] == "float32"
    assert s["value_range"][0] == 0.0 and 8000 < s["value_range"][1] < 10000
    assert volume_summary([knee, knee])[1]["series_number"] == 8


@pytest.mark.shared
def test_knee_missing_slice_is_named(mri, tmp_path):
    headers = _knee_headers()
    iop = np.array(headers[0][1].ImageOrientationPatient, float)
    normal = np.cross(iop[:3], iop[3:])
    headers.sort(key=lambda h: np.dot(np.array(h[1].ImagePositionPatient, float), normal))
    z = [np.dot(np.array(ds.ImagePositionPatient, float), normal / np.linalg.norm(normal)) for _, ds in headers]
    for n, (path, _) in enumerate(headers):
        if n != 12:
            shutil.copy(path, tmp_path / path.name)
    (tmp_path / "readme.txt").write_text("not DICOM\n")
    with pytest.raises(DataError) as err:
        read_dicom_series(tmp_path)
    msg = str(err.value)
    assert "missing slice between" in msg
    assert f"z={z[11]:.2f}" in msg and f"z={z[13]:.2f}" in msg
    assert "spacing 4 mm elsewhere" in msg
    assert str(tmp_path) in msg and "\n" not in msg


@pytest.mark.shared
def test_knee_file_order_does_not_matter(knee, tmp_path):
    files = sorted(KNEE.iterdir())
    names = [f"{n:03d}" for n in range(len(files))]
    random.Random(3).shuffle(names)
    for path, name in zip(files, names):
        shutil.copy(path, tmp_path / name)  # no extension, shuffled order
    (vol,) = read_dicom_series(tmp_path)
    assert np.array_equal(vol.data, knee.data)
    np.testing.assert_allclose(vol.affine, knee.affine)


@pytest.mark.shared
def test_two_series_in_one_folder(knee, tmp_path):
    shutil.copytree(KNEE, tmp_path / "mix" / "knee")
    files = write_dicom_series(_synthetic(), tmp_path / "mix" / "phantom", series_number=99,
                               series_description="phantom")
    vols = read_dicom_series(tmp_path / "mix")
    assert [v.metadata["series_number"] for v in vols] == [8, 99]
    assert vols[0].shape == (256, 256, 24) and vols[1].shape == (40, 33, 6)
    assert vols[1].metadata["series_description"] == "phantom"
    # One file names its own series only.
    (only,) = read_volumes(files[2])
    assert only.metadata["series_uid"] == vols[1].metadata["series_uid"]
    (only,) = read_volumes(tmp_path / "mix" / "knee" / "E3655S8I049.MR.dcm")
    assert only.shape == (256, 256, 24)


def test_empty_folder_and_text_files(tmp_path):
    with pytest.raises(InputError, match="no DICOM files"):
        read_dicom_series(tmp_path)
    (tmp_path / "readme.txt").write_text("hello\n")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "notes.dcm").write_text("not really DICOM\n" * 20)
    with pytest.raises(InputError, match="no DICOM files") as err:
        read_dicom_series(tmp_path)
    assert str(tmp_path) in str(err.value)
    with pytest.raises(InputError, match="no such"):
        read_volumes(tmp_path / "absent")
    (tmp_path / "image.png").write_bytes(b"\x89PNG\r\n")
    with pytest.raises(InputError, match="unknown image format"):
        read_volumes(tmp_path / "image.png")


# --------------------------------------------------------------------------- #
# NRRD and NIfTI, real files
# --------------------------------------------------------------------------- #


@pytest.mark.shared
def test_dess_label_nrrd(mri):
    (vol,) = read_volumes(DESS)
    _, header = nrrd.read(str(DESS), index_order="F")
    assert vol.shape == (384, 384, 160)
    np.testing.assert_allclose(vol.spacing, [0.364583, 0.364583, 0.70], atol=1e-4)
    assert vol.metadata["space"] == "left-posterior-superior" and not vol.metadata["space_assumed"]
    np.testing.assert_allclose(vol.affine[:3, 3], header["space origin"])  # LPS kept as is
    np.testing.assert_allclose(vol.affine[:3, :3], np.asarray(header["space directions"]).T)
    assert vol.data.dtype == np.uint8
    assert {5, 6, 7, 8} <= set(np.unique(vol.data).tolist())
    # The femur label is a sizeable object, not a few stray voxels.
    assert (vol.data == 5).sum() > 100_000


@pytest.mark.shared
def test_ct_pelvis_nifti_ras_to_lps(mri):
    vol = read_nifti(CT)
    img = nib.load(CT)
    assert vol.shape == img.shape == (122, 101, 112)
    np.testing.assert_allclose(vol.affine, np.diag([-1, -1, 1, 1]) @ img.affine)
    np.testing.assert_allclose(vol.spacing, [3, 3, 3])
    assert vol.metadata["affine_source"] == "sform"
    assert vol.data.min() <= -900 and 1000 < vol.data.max() < 4000  # air and cortical bone in HU
    assert volume_summary(vol)["orientation"] == "RAS"


# --------------------------------------------------------------------------- #
# Writers and round trips
# --------------------------------------------------------------------------- #


def test_three_formats_agree_on_world_coordinates(tmp_path):
    vol = _synthetic()
    files = write_dicom_series(vol, tmp_path / "dcm")
    write_nifti(vol, tmp_path / "v.nii.gz")
    write_nrrd(vol, tmp_path / "v.nrrd")
    (d,) = read_volumes(tmp_path / "dcm")
    (n,) = read_volumes(tmp_path / "v.nii.gz")
    (r,) = read_volumes(tmp_path / "v.nrrd")

    idx = _all_indices(vol.shape)
    truth = vol.index_to_world(idx)
    for other in (d, n, r):
        assert other.shape == vol.shape
        np.testing.assert_allclose(other.index_to_world(idx), truth, atol=1e-3, rtol=1e-4)
    assert np.array_equal(n.data, vol.data) and np.array_equal(r.data, vol.data)
    step = float(pydicom.dcmread(files[0]).RescaleSlope)
    assert 0 < step < (vol.data.max() - vol.data.min()) / 65000
    assert np.abs(d.data - vol.data).max() <= step / 2 * (1 + 1e-6) + 1e-4
    assert len(files) == 6 and all(f.is_file() for f in files)
    assert [int(pydicom.dcmread(f).InstanceNumber) for f in files] == list(range(1, 7))


def test_jpeg2000_lossless_matches_uncompressed(tmp_path):
    vol = _synthetic(seed=4)
    write_dicom_series(vol, tmp_path / "raw")
    files = write_dicom_series(vol, tmp_path / "j2k", transfer_syntax="jpeg2000_lossless")
    assert pydicom.dcmread(files[0]).file_meta.TransferSyntaxUID == JPEG2000Lossless
    (raw,) = read_dicom_series(tmp_path / "raw")
    (j2k,) = read_dicom_series(tmp_path / "j2k")
    assert j2k.metadata["transfer_syntax"] == JPEG2000Lossless
    assert np.array_equal(j2k.data, raw.data)
    # Signed integers (CT-like) also survive exactly, with no rescale needed.
    ct = Volume(np.random.default_rng(1).integers(-1024, 3000, (32, 40, 3)).astype(np.int16), vol.affine)
    write_dicom_series(ct, tmp_path / "ct", modality="CT", transfer_syntax="jpeg2000_lossless")
    (back,) = read_dicom_series(tmp_path / "ct")
    assert np.array_equal(back.data, ct.data) and back.metadata["modality"] == "CT"
    with pytest.raises(ValueError, match="32x32"):
        write_dicom_series(_synthetic((20, 40, 2)), tmp_path / "small", transfer_syntax="jpeg2000_lossless")


def test_written_series_is_read_by_highdicom(tmp_path):
    import highdicom as hd

    vol = _synthetic(seed=2)
    files = write_dicom_series(vol, tmp_path / "s")
    ref = hd.get_volume_from_series([pydicom.dcmread(f) for f in files])
    assert ref.array.shape == (6, 33, 40)
    idx = _all_indices(ref.array.shape)
    # highdicom's slice axis runs against the normal: our k = K-1-s.
    ours = vol.index_to_world(np.stack([idx[:, 2], idx[:, 1], 5 - idx[:, 0]], axis=1))
    np.testing.assert_allclose(idx @ ref.affine[:3, :3].T + ref.affine[:3, 3], ours, atol=1e-6)


def test_reversed_instance_numbers_and_shuffled_files(tmp_path):
    vol = _synthetic(seed=5)
    files = write_dicom_series(vol, tmp_path / "ordered")
    (expected,) = read_dicom_series(tmp_path / "ordered")
    names = [f"x{n}.dcm" for n in range(len(files))]
    random.Random(7).shuffle(names)
    (tmp_path / "messy").mkdir()
    for n, (path, name) in enumerate(zip(files, names)):
        ds = pydicom.dcmread(path)
        ds.InstanceNumber = len(files) - n
        ds.save_as(tmp_path / "messy" / name)
    (vol2,) = read_dicom_series(tmp_path / "messy")
    assert np.array_equal(vol2.data, expected.data)
    np.testing.assert_allclose(vol2.affine, expected.affine)
    assert vol2.metadata["instance_numbers"] == [6, 5, 4, 3, 2, 1]


def _shift_slice(path: Path, by_mm: float) -> None:
    """Move one written slice along the normal (to fake a gap or bad spacing)."""
    ds = pydicom.dcmread(path)
    iop = np.array(ds.ImageOrientationPatient, float)
    ipp = np.array(ds.ImagePositionPatient, float) + by_mm * np.cross(iop[:3], iop[3:])
    ds.ImagePositionPatient = [imaging._ds(v) for v in ipp]
    ds.save_as(path)


def test_uneven_spacing_and_duplicates(tmp_path):
    files = write_dicom_series(_synthetic(), tmp_path / "s")
    _shift_slice(files[3], 1.0)  # 2.5 mm steps become 3.5 then 1.5
    with pytest.raises(DataError, match=r"uneven slice spacing: 3\.5 mm between z=.* \(spacing 2\.5 mm elsewhere"):
        read_dicom_series(tmp_path / "s")
    files = write_dicom_series(_synthetic(), tmp_path / "gap2")
    for f in files[2:4]:
        f.unlink()
    with pytest.raises(DataError, match="missing 2 slices between"):
        read_dicom_series(tmp_path / "gap2")
    files = write_dicom_series(_synthetic(), tmp_path / "dup")
    _shift_slice(files[3], -2.5)
    with pytest.raises(DataError, match="same position"):
        read_dicom_series(tmp_path / "dup")


def test_split_by_echo_and_acquisition(tmp_path):
    uid = generate_uid()
    for n in (1, 2):
        write_dicom_series(_synthetic(seed=n, metadata={"echo_number": n, "echo_time": 6.3 * n}),
                           tmp_path / "echoes" / f"e{n}", series_uid=uid)
        write_dicom_series(_synthetic(seed=n, metadata={"acquisition_number": 3 - n}),
                           tmp_path / "acqs" / f"a{n}", series_uid=uid)
    echoes = read_dicom_series(tmp_path / "echoes")
    assert [v.metadata["echo_number"] for v in echoes] == [1, 2]
    assert echoes[1].metadata["echo_time"] == pytest.approx(12.6)
    assert not np.array_equal(echoes[0].data, echoes[1].data)
    acqs = read_dicom_series(tmp_path / "acqs")
    assert [v.metadata["acquisition_number"] for v in acqs] == [1, 2]
    assert all(v.shape == (40, 33, 6) for v in acqs)

    # CT-style: each slice its own acquisition number, positions unique -> one volume.
    files = write_dicom_series(_synthetic(), tmp_path / "ct", modality="CT")
    for n, f in enumerate(files):
        ds = pydicom.dcmread(f)
        ds.AcquisitionNumber = n + 1
        ds.save_as(f)
    (ct,) = read_dicom_series(tmp_path / "ct")
    assert ct.shape == (40, 33, 6) and ct.metadata["acquisition_number"] is None


def test_mixed_orientation_in_one_series(tmp_path):
    uid = generate_uid()
    write_dicom_series(_synthetic(degrees=6), tmp_path / "a", series_uid=uid)
    write_dicom_series(_synthetic(degrees=30, origin=(0, 0, 300)), tmp_path / "b", series_uid=uid)
    with pytest.raises(DataError, match="mixed image orientations"):
        read_dicom_series(tmp_path)


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(axis=st.tuples(*[st.floats(-1, 1)] * 3).filter(lambda a: np.linalg.norm(a) > 0.1),
       degrees=st.floats(-180, 180), flips=st.tuples(*[st.sampled_from([-1.0, 1.0])] * 3),
       spacing=st.tuples(*[st.floats(0.2, 5.0)] * 3))
def test_any_orthogonal_grid_keeps_each_value_at_its_place(axis, degrees, flips, spacing):
    """Whatever the rotation and handedness, every value comes back at the same LPS point."""
    affine = np.eye(4)
    affine[:3, :3] = _rotation(axis, degrees) @ np.diag(np.multiply(flips, spacing))
    affine[:3, 3] = [10.0, -20.0, 30.0]
    vol = Volume(np.arange(60, dtype=np.int16).reshape(5, 4, 3), affine)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        write_dicom_series(vol, tmp / "d")
        write_nifti(vol, tmp / "v.nii")
        write_nrrd(vol, tmp / "v.nrrd")
        for back in (read_dicom_series(tmp / "d")[0], read_nifti(tmp / "v.nii"), read_nrrd(tmp / "v.nrrd")):
            idx = _all_indices(back.shape)
            values = back.data[tuple(idx.T)].astype(int)
            original = np.argwhere(np.ones(vol.shape, bool))[np.argsort(vol.data.ravel())][values]
            np.testing.assert_allclose(back.index_to_world(idx), vol.index_to_world(original), atol=1e-3)
            # DICOM reverses k for a left-handed grid; its own affine is then right-handed.
            if back.metadata["format"] == "dicom":
                assert np.linalg.det(back.affine[:3, :3]) > 0


def test_writer_refuses_what_dicom_cannot_hold(tmp_path):
    sheared = _synthetic()
    sheared.affine[:3, 2] += 0.3 * sheared.affine[:3, 0]
    with pytest.raises(ValueError, match="orthogonal"):
        write_dicom_series(sheared, tmp_path / "s")
    nan = _synthetic()
    nan.data[1, 2, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        write_dicom_series(nan, tmp_path / "n")
    with pytest.raises(ValueError, match="rescale=True"):
        write_dicom_series(_synthetic(), tmp_path / "r", rescale=False)
    with pytest.raises(ValueError, match="transfer_syntax"):
        write_dicom_series(_synthetic(), tmp_path / "t", transfer_syntax="jpeg_xl")
    assert list(tmp_path.iterdir()) == []
    # A sheared grid is fine for NIfTI (sform) and NRRD.
    write_nifti(sheared, tmp_path / "s.nii")
    np.testing.assert_allclose(read_nifti(tmp_path / "s.nii").affine, sheared.affine, atol=1e-4)
    assert read_nifti(tmp_path / "s.nii").metadata["affine_source"] == "sform"


def test_failed_writes_leave_nothing(tmp_path, monkeypatch):
    vol = _synthetic()
    target = tmp_path / "series"
    target.mkdir()
    (target / "keep.txt").write_text("old output\n")
    calls = []
    real_write = imaging._write_slice

    def failing_write(path, parts):
        calls.append(path)
        if len(calls) == 3:
            raise OSError("disk full")
        return real_write(path, parts)

    # every uncompressed slice file is written through this seam
    monkeypatch.setattr(imaging, "_write_slice", failing_write)
    with pytest.raises(OSError, match="disk full"):
        write_dicom_series(vol, target)
    calls.clear()
    with pytest.raises(OSError, match="disk full"):
        write_dicom_series(vol, tmp_path / "fresh")
    monkeypatch.undo()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["series"]
    assert [p.name for p in target.iterdir()] == ["keep.txt"]  # the old output is untouched

    def failing_nrrd_write(filename, *args, **kwargs):
        Path(filename).write_bytes(b"NRRD0005\npartial")
        raise OSError("disk full")

    monkeypatch.setattr(nrrd, "write", failing_nrrd_write)
    with pytest.raises(OSError):
        write_nrrd(vol, tmp_path / "v.nrrd")
    monkeypatch.setattr(Path, "write_bytes", lambda self, data: (_ for _ in ()).throw(OSError("disk full")))
    with pytest.raises(OSError):
        write_nifti(vol, tmp_path / "v.nii.gz")
    monkeypatch.undo()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["series"]


def test_written_files_are_readable_by_others(tmp_path):
    files = write_dicom_series(_synthetic(), tmp_path / "s")
    out = write_nifti(_synthetic(), tmp_path / "v.nii.gz")
    # atomic_path's temporaries are private (0700/0600); outputs must not be.
    for p in (tmp_path / "s", files[0], out):
        assert p.stat().st_mode & 0o044, oct(p.stat().st_mode)


# --------------------------------------------------------------------------- #
# NIfTI / NRRD details
# --------------------------------------------------------------------------- #


def test_nifti_4d_and_units(tmp_path):
    affine = np.diag([2.0, 3.0, 4.0, 1.0])
    nib.save(nib.Nifti1Image(np.zeros((4, 5, 6, 2), np.float32), affine), tmp_path / "t.nii.gz")
    with pytest.raises(DataError, match="4-D"):
        read_volumes(tmp_path / "t.nii.gz")
    nib.save(nib.Nifti1Image(np.ones((4, 5, 6, 1), np.int16), affine), tmp_path / "one.nii")
    one = read_nifti(tmp_path / "one.nii")
    assert one.shape == (4, 5, 6) and one.data.dtype == np.int16
    np.testing.assert_allclose(one.affine, np.diag([-2.0, -3.0, 4.0, 1.0]))
    img = nib.Nifti1Image(np.zeros((2, 2, 2), np.float32), np.diag([0.001, 0.001, 0.002, 1.0]))
    img.header.set_xyzt_units(xyz="meter")
    nib.save(img, tmp_path / "m.nii")
    np.testing.assert_allclose(read_nifti(tmp_path / "m.nii").spacing, [1.0, 1.0, 2.0])
    (tmp_path / "bad.nii.gz").write_bytes(b"not gzip at all")
    with pytest.raises(InputError, match="NIfTI"):
        read_nifti(tmp_path / "bad.nii.gz")


@pytest.mark.parametrize("space, flip", [("right-anterior-superior", [-1, -1, 1]), ("RAS", [-1, -1, 1]),
                                         ("left-anterior-superior", [1, -1, 1]), ("LPS", [1, 1, 1]),
                                         (None, [1, 1, 1])])
def test_nrrd_spaces(tmp_path, space, flip):
    directions = np.array([[0.0, 1.5, 0.0], [2.0, 0.0, 0.0], [0.0, 0.0, 3.0]])
    header = {"space directions": directions, "space origin": np.array([1.0, 2.0, 3.0])}
    if space is None:
        header = {"spacings": [1.5, 2.0, 3.0]}
    else:
        header["space"] = space
    nrrd.write(str(tmp_path / "x.nrrd"), np.zeros((2, 3, 4), np.int16), header, index_order="F")
    vol = read_nrrd(tmp_path / "x.nrrd")
    assert vol.shape == (2, 3, 4)
    if space is None:
        assert vol.metadata["space_assumed"]
        np.testing.assert_allclose(vol.affine, np.diag([1.5, 2.0, 3.0, 1.0]))
    else:
        assert not vol.metadata["space_assumed"]
        np.testing.assert_allclose(vol.affine[:3, :3], np.diag(flip) @ directions.T)
        np.testing.assert_allclose(vol.affine[:3, 3], np.multiply(flip, [1.0, 2.0, 3.0]))
