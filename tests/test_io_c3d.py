"""bonecap.io.c3d: real public C3D files, the gap rule, the writer, bad input.

Independent reads go through raw ezc3d / raw py-c3d (or the bytes of the
file), never through the module under test.
"""

from __future__ import annotations

import json
import struct
import warnings
from pathlib import Path

import c3d as pyc3d
import ezc3d
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import bonecap.io.c3d as c3dio
from bonecap.errors import DataError, FormatError, InputError, OutputError
from bonecap.io.c3d import c3d_summary, read_c3d, write_c3d
from bonecap.model import Trial

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
C3D_DIR = SHARED / "c3d"
ALL_C3D = sorted(C3D_DIR.glob("**/*.c3d")) if C3D_DIR.is_dir() else []

ENC = C3D_DIR / "encodings" / "sample02"
TENNIS = C3D_DIR / "optitrack_pig_fullbody" / "ktk_kinematics_tennis_serve.c3d"
TENNIS_NAN = C3D_DIR / "optitrack_pig_fullbody" / "ktk_kinematics_tennis_serve_nan.c3d"
STATIC = C3D_DIR / "vicon_pig_fullbody" / "pycgm_Test_Static_trial.c3d"
MOVEMENT = C3D_DIR / "vicon_pig_fullbody" / "pycgm_Test_Movement_trial.c3d"
POMECA = C3D_DIR / "vicon_upper_limb" / "pyomeca_markers_analogs.c3d"


@pytest.fixture(scope="module")
def shared():
    if not SHARED.is_dir():
        pytest.skip(f"shared data not found at {SHARED}")
    return SHARED


# --- independent helpers --------------------------------------------------------------------

def _pyc3d_raw(path):
    """Labels (stripped), (F, N, 5) frames and analogs from raw py-c3d, no NaN handling."""
    with open(path, "rb") as fh, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = pyc3d.Reader(fh)
        frames, analog = [], []
        for _, p, a in r.read_frames(check_nan=False):
            frames.append(p.copy())
            if np.size(a):
                analog.append(a)
        labels = [s.strip() for s in r.point_labels]
        k = 2
        while r.get(f"POINT:LABELS{k}") is not None:
            labels += [s.strip() for s in r.get(f"POINT:LABELS{k}").string_array]
            k += 1
        labels = labels[: r.point_used]
    return labels, np.stack(frames), (np.concatenate(analog, axis=1) if analog else np.zeros((0, 0)))


def _ezc3d_points(path):
    """Labels and (F, N, 3) points from raw ezc3d (NaN where ezc3d says invalid)."""
    e = ezc3d.c3d(str(path))
    point = e["parameters"]["POINT"]
    labels = list(point["LABELS"]["value"])
    k = 2
    while f"LABELS{k}" in point:
        labels += point[f"LABELS{k}"]["value"]
        k += 1
    pts = e["data"]["points"][:3].transpose(2, 1, 0)
    return [s.strip() for s in labels][: pts.shape[1]], pts, e


def _data_words(path):
    """Writable float32 view ``(F, words per frame)`` of the data section of an Intel float file."""
    head = Path(path).read_bytes()[:512]
    n_points, analog_words, first, last = struct.unpack("<4H", head[2:10])
    data_block = struct.unpack("<H", head[16:18])[0]
    frames = last - first + 1
    return np.memmap(path, dtype="<f4", mode="r+", offset=(data_block - 1) * 512,
                     shape=(frames, 4 * n_points + analog_words)), n_points


def _patch_units(path, units: bytes):
    """Overwrite the 2-character POINT:UNITS string written by write_c3d."""
    blob = bytearray(Path(path).read_bytes())
    i = blob.index(b"UNITS", 512)
    # name, 2-byte offset, type -1 (char), 1 dimension of 2, then the characters
    assert blob[i + 7] == 0xFF and blob[i + 8] == 1 and blob[i + 9] == 2
    blob[i + 10:i + 12] = units
    Path(path).write_bytes(bytes(blob))


@pytest.fixture
def force_pyc3d(monkeypatch):
    """Make ezc3d refuse every file, so read_c3d takes its py-c3d path."""
    def refuse(path):
        raise RuntimeError("refused for the test")
    monkeypatch.setattr(c3dio, "_read_ezc3d", refuse)


def _random_trial(rng, frames=25, markers=5, with_analogs=True, prefix="Sub"):
    pts = rng.uniform(-1500, 2500, (frames, markers, 3))
    gaps = rng.random((frames, markers)) < 0.15
    pts[gaps] = np.nan
    analogs = rng.normal(0, 3, (3, frames * 4)) if with_analogs else np.zeros((0, 0))
    return Trial(
        labels=[f"M{i}" for i in range(markers)],
        points=pts,
        rate=100.0,
        first_frame=12,
        prefixes=[prefix if i % 2 == 0 else "" for i in range(markers)],
        other_points={"LKneeAngles": rng.normal(0, 40, (frames, 3)),
                      "CentreOfMass": rng.normal(0, 500, (frames, 3))},
        other_point_groups={"LKneeAngles": "ANGLES", "CentreOfMass": "MODELED_MARKERS"},
        analog_labels=["Fx", "Fy", "EMG1"] if with_analogs else [],
        analogs=analogs,
        analog_rate=400.0 if with_analogs else 0.0,
        events=[{"label": "Foot Strike", "context": "Left", "time": 0.05},
                {"label": "Foot Off", "context": "Right", "time": 75.125}],
    )


def _nan_equal(a, b):
    return np.array_equal(np.isnan(a), np.isnan(b)) and np.array_equal(a[~np.isnan(a)], b[~np.isnan(b)])


# --- every real file --------------------------------------------------------------------

@pytest.mark.shared
def test_shared_c3d_files_are_all_there(shared):
    names = {p.relative_to(C3D_DIR).as_posix() for p in ALL_C3D}
    expected = {f"encodings/sample02/{p}_{k}.c3d" for p in ("pc", "dec", "sgi") for k in ("int", "real")}
    expected |= {p.relative_to(C3D_DIR).as_posix() for p in (TENNIS, TENNIS_NAN, STATIC, MOVEMENT, POMECA)}
    assert expected <= names


@pytest.mark.shared
@pytest.mark.parametrize("path", ALL_C3D, ids=lambda p: p.name)
def test_every_shared_file_reads(shared, path):
    trial = read_c3d(path)
    assert trial.n_frames > 0 and len(trial.labels) > 0
    seen = np.isfinite(trial.points).all(axis=2)
    assert seen.any(axis=1).sum() > 0
    # In mm, whatever the stored unit: markers of a lab sit within 10 m, and not all within 10 mm.
    assert np.nanmax(np.abs(trial.points)) < 10_000
    assert np.nanmax(np.abs(trial.points)) > 100
    # NaN comes per sample, never per coordinate; residuals follow the same gaps.
    assert np.array_equal(np.isnan(trial.points).any(axis=2), np.isnan(trial.points).all(axis=2))
    assert np.array_equal(np.isnan(trial.residuals), ~seen)
    assert len(set(trial.labels)) == len(trial.labels)
    summary = c3d_summary(path)
    assert json.loads(json.dumps(summary)) == summary
    assert summary["frames"] == trial.n_frames and summary["marker_count"] == len(trial.labels)
    assert sum(summary["gap_samples"].values()) == int((~seen).sum())


@pytest.mark.shared
@pytest.mark.parametrize("path", [p for p in ALL_C3D if not p.name.startswith("sgi_")], ids=lambda p: p.name)
def test_both_readers_give_the_same_trial(shared, path, monkeypatch):
    a = read_c3d(path)
    assert a.metadata["reader"] == "ezc3d"
    monkeypatch.setattr(c3dio, "_read_ezc3d", lambda p: (_ for _ in ()).throw(RuntimeError("no")))
    b = read_c3d(path)
    assert b.metadata["reader"] == "c3d"
    assert a.labels == b.labels and a.prefixes == b.prefixes
    assert _nan_equal(a.points, b.points)
    assert _nan_equal(a.residuals, b.residuals)
    assert list(a.other_points) == list(b.other_points)
    for k in a.other_points:
        assert _nan_equal(a.other_points[k], b.other_points[k])
    assert a.analog_labels == b.analog_labels and np.array_equal(a.analogs, b.analogs)
    assert (a.rate, a.first_frame, a.units, a.analog_rate) == (b.rate, b.first_frame, b.units, b.analog_rate)


# --- the six encodings of sample02 -------------------------------------------------------

@pytest.mark.shared
def test_sample02_encodings_agree(shared):
    trials = {f"{p}_{k}": read_c3d(ENC / f"{p}_{k}.c3d") for p in ("pc", "dec", "sgi") for k in ("int", "real")}
    with open(ENC / "pc_int.c3d", "rb") as fh, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = pyc3d.Reader(fh)
        step = abs(float(r.point_scale))
        units = r.get("POINT:UNITS").string_value.strip().lower()
        used = r.point_used
        n_labels = len(r.point_labels)
    step *= {"mm": 1.0, "cm": 10.0, "m": 1000.0}[units]
    assert 0.2 < step < 0.4 and used == 36 and n_labels > used  # labels longer than POINT:USED

    ref = trials["pc_real"]
    assert len(ref.labels) == 36 and ref.labels[0] == "RFT1" and ref.labels[-1] == "LFA3"
    ref_gaps = np.isnan(ref.points).any(axis=2)
    assert 0 < ref_gaps.sum() < ref_gaps.size
    for name, t in trials.items():
        assert t.labels == ref.labels, name
        assert np.array_equal(np.isnan(t.points).any(axis=2), ref_gaps), name
        diff = np.nanmax(np.abs(t.points - ref.points))
        assert diff <= step, (name, diff)
        assert t.n_frames == 89 and t.rate == 50 and t.analogs.shape == (16, 356), name
    # Same stored numbers in every processor layout -- except that dec_int's
    # integers were rounded differently (59 coordinates one step off pc_int).
    assert _nan_equal(trials["dec_real"].points, ref.points)
    assert _nan_equal(trials["sgi_real"].points, ref.points)
    assert _nan_equal(trials["sgi_int"].points, trials["pc_int"].points)
    assert np.nanmax(np.abs(trials["dec_int"].points - trials["pc_int"].points)) <= step * (1 + 1e-9)
    assert trials["pc_int"].metadata["storage"] == "integer" and ref.metadata["storage"] == "float"
    assert np.nanmax(np.abs(trials["pc_int"].points - ref.points)) > 0  # the int twin is really rounded
    for k in ("int", "real"):
        assert trials[f"sgi_{k}"].metadata["reader"] == "c3d"
        assert trials[f"sgi_{k}"].metadata["processor"] == "MIPS"
        assert "MIPS" in trials[f"sgi_{k}"].metadata["fallback_reason"]
        assert trials[f"dec_{k}"].metadata["processor"] == "DEC"


# --- OptiTrack: metres, prefixes --------------------------------------------------------

@pytest.mark.shared
def test_optitrack_metres_become_mm_and_prefix_is_stripped(shared):
    t = read_c3d(TENNIS)
    assert t.units == "m"
    assert len(t.labels) == 39 and set(t.prefixes) == {"Derrick"}
    assert not any(":" in lab for lab in t.labels)
    assert {"LSHO", "RSHO", "LASI", "RFHD", "C7"} <= set(t.labels)
    assert t.metadata["manufacturer"] == "OptiTrack"

    labels, raw, _ = _ezc3d_points(TENNIS)
    assert labels[0].startswith("Derrick:")
    order = [labels.index(f"Derrick:{lab}") for lab in t.labels]
    assert np.array_equal(t.points, raw[:, order] * 1000.0)

    # A person's size, in mm: forehead to ankle about 1.2-2 m, shoulder width 250-500 mm.
    head_ankle = np.linalg.norm(t.marker("LFHD") - t.marker("LANK"), axis=1)
    assert 1200 < np.nanmedian(head_ankle) < 2000
    shoulders = np.linalg.norm(t.marker("LSHO") - t.marker("RSHO"), axis=1)
    assert 250 < np.nanmedian(shoulders) < 500
    assert 500 < np.nanmax(np.abs(t.points)) < 5000


@pytest.mark.shared
def test_optitrack_nan_copy_shows_the_rsho_gap(shared):
    full, holed = read_c3d(TENNIS), read_c3d(TENNIS_NAN)
    labels, raw, _ = _ezc3d_points(TENNIS_NAN)
    measured_ezc3d = int(np.isnan(raw[:, labels.index("Derrick:RSHO")]).any(axis=1).sum())
    pl, pframes, _ = _pyc3d_raw(TENNIS_NAN)
    measured_pyc3d = int((~np.isfinite(pframes[:, pl.index("Derrick:RSHO"), :3]).all(axis=1)).sum())
    gaps = holed.gap_counts()
    assert gaps["RSHO"] == measured_ezc3d == measured_pyc3d > 0
    assert gaps["RSHO"] == 145  # as the data README says
    assert sum(gaps.values()) == gaps["RSHO"]
    assert full.labels == holed.labels
    for lab in full.labels:
        if lab != "RSHO":
            assert np.array_equal(full.marker(lab), holed.marker(lab)), lab
    seen = ~np.isnan(holed.marker("RSHO")).any(axis=1)
    assert np.array_equal(holed.marker("RSHO")[seen], full.marker("RSHO")[seen])
    assert c3d_summary(TENNIS_NAN)["gap_samples"]["RSHO"] == 145


# --- Vicon model outputs ---------------------------------------------------------------

@pytest.mark.shared
def test_pycgm_static_model_outputs_are_other_points(shared):
    t = read_c3d(STATIC)
    e = ezc3d.c3d(str(STATIC))
    angles = [s.strip() for s in e["parameters"]["POINT"]["ANGLES"]["value"]]
    assert len(angles) == 26
    assert set(t.other_points) == set(angles)
    assert set(t.other_point_groups.values()) == {"ANGLES"}
    assert "LKneeAngles" not in t.labels and not set(angles) & set(t.labels)
    pig = {"LFHD", "RFHD", "LBHD", "RBHD", "C7", "T10", "CLAV", "STRN", "RBAK", "LSHO", "LUPA", "LELB",
           "LFRM", "LWRA", "LWRB", "LFIN", "RSHO", "RUPA", "RELB", "RFRM", "RWRA", "RWRB", "RFIN", "LASI",
           "RASI", "LPSI", "RPSI", "LTHI", "LKNE", "LTIB", "LANK", "LHEE", "LTOE", "RTHI", "RKNE", "RTIB",
           "RANK", "RHEE", "RTOE"}
    assert pig <= set(t.labels)
    # As stored, in degrees: identical to raw ezc3d, never multiplied.
    all_labels = [s.strip() for s in e["parameters"]["POINT"]["LABELS"]["value"]]
    raw = e["data"]["points"][:3, all_labels.index("LKneeAngles")].T
    assert _nan_equal(t.other_points["LKneeAngles"], raw)
    assert np.nanmax(np.abs(t.other_points["LKneeAngles"])) < 360
    assert c3d_summary(STATIC)["other_points"] == {"ANGLES": 26}
    assert t.analogs.shape[0] == 69 and t.analog_rate == 1080


@pytest.mark.shared
def test_pycgm_movement_groups_and_first_frame(shared):
    t = read_c3d(MOVEMENT)
    e = ezc3d.c3d(str(MOVEMENT))
    for group in ("ANGLES", "FORCES", "MOMENTS", "POWERS", "MODELED_MARKERS"):
        listed = {s.strip() for s in e["parameters"]["POINT"][group]["value"]}
        assert {k for k, g in t.other_point_groups.items() if g == group} == listed, group
    assert "CentreOfMass" in t.other_points and "CentreOfMass" not in t.labels
    header_first = struct.unpack("<H", MOVEMENT.read_bytes()[6:8])[0]
    assert t.first_frame == header_first == 695
    assert t.analogs.shape == (69, t.n_frames * 9)


# --- mixed prefixes ---------------------------------------------------------------------

@pytest.mark.shared
def test_pyomeca_mixed_prefixes_and_subject_selection(shared):
    t = read_c3d(POMECA)
    assert sorted(set(t.prefixes)) == ["Daphnee", "boite"]
    assert len(t.labels) == 51
    d = read_c3d(POMECA, subject="Daphnee")
    assert len(d.labels) == 43 and set(d.prefixes) == {"Daphnee"} and "ASISr" in d.labels
    b = read_c3d(POMECA, subject="boite")
    assert len(b.labels) == 8 and "gauche_ext" in b.labels and "ASISr" not in b.labels
    assert np.array_equal(d.marker("ASISr"), t.marker("ASISr"), equal_nan=True)
    with pytest.raises(DataError) as exc:
        read_c3d(POMECA, subject="Nobody")
    assert "Daphnee" in str(exc.value) and "boite" in str(exc.value) and str(POMECA) in str(exc.value)
    s = c3d_summary(POMECA, subject="boite")
    assert s["marker_count"] == 8 and s["prefixes"] == ["boite"]
    assert t.analogs.shape == (38, 11600) and t.analog_rate == 2000 and len(t.analog_labels) == 38
    _, _, raw_analogs = _pyc3d_raw(POMECA)
    assert np.allclose(t.analogs, raw_analogs)
    assert t.gap_counts() and sum(t.gap_counts().values()) > 0


def test_colliding_prefixed_labels_keep_full_names(tmp_path):
    pts = np.arange(4 * 3 * 3, dtype=float).reshape(4, 3, 3) + 1
    trial = Trial(["LSHO", "LSHO", "RSHO"], pts, 100.0, prefixes=["Anna", "Bob", "Anna"])
    target = tmp_path / "two.c3d"
    write_c3d(trial, target)
    both = read_c3d(target)
    assert both.labels == ["Anna:LSHO", "Bob:LSHO", "RSHO"]
    assert both.prefixes == ["Anna", "Bob", "Anna"]
    anna = read_c3d(target, subject="Anna")
    assert anna.labels == ["LSHO", "RSHO"] and anna.prefixes == ["Anna", "Anna"]
    assert np.array_equal(anna.marker("LSHO"), pts[:, 0].astype(np.float32))
    with pytest.raises(DataError, match="Anna, Bob"):
        read_c3d(target, subject="Carl")
    # Written back, the full names stay single-prefixed.
    write_c3d(both, tmp_path / "again.c3d")
    labels, _, _ = _ezc3d_points(tmp_path / "again.c3d")
    assert labels == ["Anna:LSHO", "Bob:LSHO", "Anna:RSHO"]


# --- the gap rule ------------------------------------------------------------------------

@pytest.mark.parametrize("reader", ["ezc3d", "c3d"])
def test_gap_rule_on_patched_samples(tmp_path, reader, request):
    if reader == "c3d":
        request.getfixturevalue("force_pyc3d")
    F, M = 8, 6
    pts = np.random.default_rng(3).uniform(100, 900, (F, M, 3))
    angle = np.full((F, 3), 10.0)
    trial = Trial([f"P{i}" for i in range(M)], pts, 60.0, other_points={"LHipAngles": angle},
                  other_point_groups={"LHipAngles": "ANGLES"})
    target = tmp_path / "gaps.c3d"
    write_c3d(trial, target)
    words, n = _data_words(target)
    assert n == M + 1
    w = words[:, : 4 * n].reshape(F, n, 4)
    w[0, 0, :3] = 0.0          # exactly at the origin, residual 0
    w[1, 1, 3] = -0.5          # negative residual, not an integer
    w[2, 2, 3] = -1.0          # the usual invalid flag
    w[3, 3, 0] = np.nan        # non-finite coordinate, residual 0
    w[4, 4, 3] = np.nan        # non-finite residual word
    w[5, 5, 3] = -0.0          # negative zero is not negative: visible
    w[6, 6, :3] = 0.0          # the angle may be exactly zero: not a gap
    words.flush()
    del w, words

    t = read_c3d(target)
    assert t.metadata["reader"] == reader
    expected = np.zeros((F, M), bool)
    expected[[0, 1, 2, 3, 4], [0, 1, 2, 3, 4]] = True
    assert np.array_equal(np.isnan(t.points).any(axis=2), expected)
    assert np.array_equal(np.isnan(t.points).all(axis=2), expected)
    ok = ~expected
    assert np.array_equal(t.points[ok], pts.astype(np.float32)[ok])
    assert np.array_equal(t.other_points["LHipAngles"][6], [0.0, 0.0, 0.0])
    assert np.isfinite(t.other_points["LHipAngles"]).all()
    assert t.gap_counts()["P5"] == 0


def test_file_without_points_reads_as_zero_markers(tmp_path):
    rng = np.random.default_rng(5)
    trial = Trial([], np.zeros((10, 0, 3)), 50.0, analog_labels=["EMG"], analogs=rng.normal(size=(1, 40)),
                  analog_rate=200.0)
    write_c3d(trial, tmp_path / "emg.c3d")
    t = read_c3d(tmp_path / "emg.c3d")
    assert t.labels == [] and t.points.shape == (10, 0, 3)
    assert np.array_equal(t.analogs, trial.analogs.astype(np.float32))
    write_c3d(Trial([], np.zeros((7, 0, 3)), 50.0), tmp_path / "nothing.c3d")
    t = read_c3d(tmp_path / "nothing.c3d")
    assert t.points.shape == (7, 0, 3) and t.analogs.size == 0
    assert c3d_summary(tmp_path / "nothing.c3d")["marker_count"] == 0


# --- units -------------------------------------------------------------------------------

@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(units=st.sampled_from([b"mm", b"MM", b"cm", b"Cm", b"m ", b" m", b"M "]),
       seed=st.integers(0, 2**32 - 1))
def test_units_are_converted_to_mm(tmp_path_factory, units, seed):
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-3, 3, (5, 2, 3))
    angles = rng.uniform(-180, 180, (5, 3))
    trial = Trial(["A", "B"], pts, 100.0, other_points={"LHipAngles": angles},
                  other_point_groups={"LHipAngles": "ANGLES"})
    target = tmp_path_factory.mktemp("units") / "u.c3d"
    write_c3d(trial, target)
    _patch_units(target, units)
    t = read_c3d(target)
    factor = {"mm": 1.0, "cm": 10.0, "m": 1000.0}[units.decode().strip().lower()]
    assert t.units == units.decode().strip()
    assert np.array_equal(t.points, pts.astype(np.float32).astype(float) * factor)
    assert np.array_equal(t.other_points["LHipAngles"], angles.astype(np.float32))  # never scaled


@pytest.mark.parametrize("units", [b"in", b"xx", b"  "])
def test_unknown_units_are_a_data_error(tmp_path, units):
    target = tmp_path / "u.c3d"
    write_c3d(Trial(["A"], np.ones((3, 1, 3)), 100.0), target)
    _patch_units(target, units)
    with pytest.raises(DataError) as exc:
        read_c3d(target)
    assert str(target) in str(exc.value) and "UNITS" in str(exc.value)


# --- writer round trip -------------------------------------------------------------------

def _check_round_trip(trial, target):
    write_c3d(trial, target)
    full = [f"{p}:{lab}" if p else lab for lab, p in zip(trial.labels, trial.prefixes)]
    names = full + list(trial.other_points)
    want = np.concatenate([trial.points] + [v[:, None] for v in trial.other_points.values()], axis=1)
    want32 = want.astype(np.float32).astype(float)
    gaps = np.isnan(want).any(axis=2)

    # ours
    t = read_c3d(target)
    assert t.labels == trial.labels and t.prefixes == trial.prefixes
    assert _nan_equal(t.points, want32[:, : len(full)])
    for k, v in trial.other_points.items():
        assert np.array_equal(t.other_points[k], v.astype(np.float32)), k
        assert t.other_point_groups[k] == trial.other_point_groups[k]
    assert t.rate == trial.rate and t.first_frame == trial.first_frame and t.units == "mm"
    assert t.analog_labels == trial.analog_labels and t.analog_rate == trial.analog_rate
    assert np.array_equal(t.analogs, trial.analogs.astype(np.float32))
    assert [(e["label"], e["context"]) for e in t.events] == [(e["label"], e["context"]) for e in trial.events]
    assert np.allclose([e["time"] for e in t.events], [e["time"] for e in trial.events], atol=1e-5)

    # raw ezc3d
    e_labels, e_pts, e = _ezc3d_points(target)
    assert e_labels == names
    assert _nan_equal(e_pts, np.where(gaps[..., None], np.nan, want32))
    assert e["parameters"]["POINT"]["UNITS"]["value"] == ["mm"]
    if trial.analogs.size:
        assert np.array_equal(e["data"]["analogs"][0], trial.analogs.astype(np.float32))

    # raw py-c3d
    p_labels, p_frames, p_analogs = _pyc3d_raw(target)
    assert p_labels == names
    p_gaps = p_frames[:, :, 3] < 0
    assert np.array_equal(p_gaps, gaps)
    assert np.array_equal(p_frames[:, :, :3][~gaps], want32[~gaps])
    assert np.all(p_frames[:, :, :3][gaps] == 0)  # no stale coordinates in gaps
    assert np.array_equal(p_frames[:, :, :3][~gaps], e_pts[~gaps])  # the two libraries agree
    if trial.analogs.size:
        assert np.array_equal(p_analogs, trial.analogs.astype(np.float32))
    return t


@pytest.mark.parametrize("seed", [0, 1])
def test_write_round_trip_through_three_readers(tmp_path, seed):
    trial = _random_trial(np.random.default_rng(seed))
    assert np.isnan(trial.points).any()
    _check_round_trip(trial, tmp_path / "rt.c3d")


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(frames=st.integers(1, 30), markers=st.integers(0, 6), analogs=st.booleans(),
       seed=st.integers(0, 2**32 - 1), prefix=st.sampled_from(["", "Derrick", "S 1"]))
def test_write_round_trip_property(tmp_path_factory, frames, markers, analogs, seed, prefix):
    trial = _random_trial(np.random.default_rng(seed), frames, markers, analogs, prefix)
    _check_round_trip(trial, tmp_path_factory.mktemp("rt") / "p.c3d")


def test_written_file_reads_the_same_through_py_c3d(tmp_path, monkeypatch):
    trial = _random_trial(np.random.default_rng(11))
    write_c3d(trial, tmp_path / "w.c3d")
    a = read_c3d(tmp_path / "w.c3d")
    monkeypatch.setattr(c3dio, "_read_ezc3d", lambda p: (_ for _ in ()).throw(RuntimeError("no")))
    b = read_c3d(tmp_path / "w.c3d")
    assert (a.metadata["reader"], b.metadata["reader"]) == ("ezc3d", "c3d")
    assert a.labels == b.labels and a.prefixes == b.prefixes and a.events == b.events
    assert _nan_equal(a.points, b.points) and np.array_equal(a.analogs, b.analogs)
    assert a.other_point_groups == b.other_point_groups
    assert len(b.events) == 2 and b.events[1]["label"] == "Foot Off"


def test_more_than_255_points_use_labels2(tmp_path):
    rng = np.random.default_rng(9)
    trial = Trial([f"M{i:03d}" for i in range(300)], rng.uniform(1, 10, (3, 300, 3)), 100.0)
    target = tmp_path / "many.c3d"
    t = _check_round_trip(trial, target)
    e = ezc3d.c3d(str(target))
    assert len(e["parameters"]["POINT"]["LABELS"]["value"]) == 255
    assert len(e["parameters"]["POINT"]["LABELS2"]["value"]) == 45
    assert t.labels[-1] == "M299"


def test_labels_are_stripped_and_cut_to_used(tmp_path):
    w = pyc3d.Writer(point_rate=50.0)
    pts = np.zeros((2, 5), np.float32)
    pts[:, :3] = 1.0
    # Three labels for two points (POINT:USED = 2), padded with spaces on both sides.
    w.point_group.add_str("LABELS", "", "  X:AA    Y: BB ZZZZ    ", 8, 3)
    w.add_frames([(pts, np.zeros((0, 0))), (pts, np.zeros((0, 0)))])
    target = tmp_path / "pad.c3d"
    with open(target, "wb") as fh, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        w.write(fh)
    t = read_c3d(target)
    assert t.labels == ["AA", "BB"] and t.prefixes == ["X", "Y"]


def test_odd_event_block_is_ignored(tmp_path):
    w = pyc3d.Writer(point_rate=50.0)
    pts = np.zeros((1, 5), np.float32)
    pts[:, :3] = 1.0
    w.point_group.add_str("LABELS", "", "A", 1, 1)
    ev = w.get_create("EVENT")
    ev.add("USED", "", 2, "<h", 3)
    ev.add_str("TIMES", "", "not numbers", 11)
    w.add_frames([(pts, np.zeros((0, 0)))])
    target = tmp_path / "ev.c3d"
    with open(target, "wb") as fh, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        w.write(fh)
    t = read_c3d(target)
    assert t.events == [] and t.labels == ["A"]


# --- bad input ---------------------------------------------------------------------------

def _expect(exc_type, path, *words):
    with pytest.raises(exc_type) as exc:
        read_c3d(path)
    msg = str(exc.value)
    assert str(path) in msg and "\n" not in msg
    for w in words:
        assert w in msg, msg
    with pytest.raises(exc_type):
        c3d_summary(path)
    return msg


@pytest.fixture
def no_library(monkeypatch):
    """Bad files must be stopped by the header check, before ezc3d or py-c3d see them."""
    def forbidden(path):
        raise AssertionError("a library was handed a bad file")
    monkeypatch.setattr(c3dio, "_parse", forbidden)


def test_text_file_named_c3d(tmp_path, no_library):
    bad = tmp_path / "notes.c3d"
    bad.write_text("this is not a motion capture file\n" * 40)
    _expect(FormatError, bad, "first bytes are text")
    short = tmp_path / "short.c3d"
    short.write_text("hello")
    _expect(FormatError, short, "first bytes are text")


def test_empty_and_tiny_binary_files(tmp_path, no_library):
    empty = tmp_path / "empty.c3d"
    empty.write_bytes(b"")
    _expect(FormatError, empty, "file is empty")
    zeros = tmp_path / "zeros.c3d"
    zeros.write_bytes(b"\x00" * 100)
    _expect(FormatError, zeros, "only 100 bytes")
    wrong = tmp_path / "wrong.c3d"
    wrong.write_bytes(b"\x02\x00" + b"\x00" * 2000)
    _expect(FormatError, wrong, "0x50")


def test_bad_processor_type(tmp_path, no_library):
    blob = bytearray(b"\x02\x50" + b"\x01" * 1022)
    blob[512 + 3] = 99
    bad = tmp_path / "proc.c3d"
    bad.write_bytes(bytes(blob))
    _expect(FormatError, bad, "processor type 99")


@pytest.mark.shared
def test_truncated_real_files(shared, tmp_path, no_library):
    src = MOVEMENT.read_bytes()
    head = tmp_path / "head.c3d"
    head.write_bytes(src[:600])
    _expect(FormatError, head, "truncated:")
    middle = tmp_path / "middle.c3d"
    middle.write_bytes(src[: int(len(src) * 0.6)])
    msg = _expect(FormatError, middle, "truncated: header promises 323 frames")
    assert str(int(len(src) * 0.6)) in msg
    last_frame = tmp_path / "last.c3d"
    tennis = TENNIS.read_bytes()
    last_frame.write_bytes(tennis[: len(tennis) - 1000])  # one frame short
    _expect(FormatError, last_frame, "truncated: header promises 1092 frames")


def test_missing_path_and_folder(tmp_path):
    missing = tmp_path / "nothing_here.c3d"
    with pytest.raises(InputError) as exc:
        read_c3d(missing)
    assert type(exc.value) is InputError and "no such file" in str(exc.value) and str(missing) in str(exc.value)
    with pytest.raises(InputError) as exc:
        read_c3d(tmp_path)
    assert "folder" in str(exc.value)


# --- failed writes leave nothing behind ----------------------------------------------------

def test_write_into_a_folder_that_is_a_file(tmp_path):
    blocker = tmp_path / "blocker"
    blocker.write_text("I am a file")
    with pytest.raises(OutputError) as exc:
        write_c3d(_random_trial(np.random.default_rng(1)), blocker / "out.c3d")
    assert str(blocker / "out.c3d") in str(exc.value)
    assert blocker.read_text() == "I am a file"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["blocker"]


@pytest.mark.parametrize("broken", ["analog_rate", "analog_samples", "duplicate", "no_frames", "other_shape",
                                    "first_frame", "bad_group"])
def test_unwritable_trial_leaves_no_file(tmp_path, broken):
    rng = np.random.default_rng(2)
    trial = _random_trial(rng)
    if broken == "analog_rate":
        trial.analog_rate = 333.0
    elif broken == "analog_samples":
        trial.analogs = trial.analogs[:, :-1]
    elif broken == "duplicate":
        trial.labels[1] = trial.labels[0]
        trial.prefixes[1] = trial.prefixes[0]
    elif broken == "no_frames":
        trial = Trial(["A"], np.zeros((0, 1, 3)), 100.0)
    elif broken == "first_frame":
        trial.first_frame = 0
    elif broken == "bad_group":
        trial.other_point_groups["LKneeAngles"] = "LABELS"  # would clash with POINT:LABELS
    else:
        trial.other_points["LKneeAngles"] = np.zeros((3, 3))
    target = tmp_path / "out.c3d"
    with pytest.raises(OutputError) as exc:
        write_c3d(trial, target)
    assert str(target) in str(exc.value)
    assert list(tmp_path.iterdir()) == []


def test_failure_mid_write_keeps_the_old_file(tmp_path, monkeypatch):
    target = tmp_path / "keep.c3d"
    write_c3d(_random_trial(np.random.default_rng(4)), target)
    before = target.read_bytes()

    def half_then_fail(self, handle):
        handle.write(b"\x02\x50" + b"\x00" * 3000)
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(pyc3d.Writer, "write", half_then_fail)
    with pytest.raises(OutputError, match="disk on fire"):
        write_c3d(_random_trial(np.random.default_rng(5)), target)
    assert target.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["keep.c3d"]


@pytest.mark.shared
def test_pycgm_subject_measurements_are_read_and_written_back(shared, tmp_path, monkeypatch):
    """Nexus keeps the Plug-in Gait measurements in PROCESSING (the pyCGM static: knee widths 144 / 139 mm,
    as its VSK has them); they read as ``subject_parameters`` and survive a write through both readers."""
    t = read_c3d(STATIC)
    assert t.subject_parameters["LKNEEWIDTH"] == 144.0 and t.subject_parameters["RKNEEWIDTH"] == 139.0
    assert t.subject_parameters["LANKLEWIDTH"] == 85.0 and t.subject_parameters["INTERASISDISTANCE"] == 306.0
    write_c3d(t, tmp_path / "w.c3d")
    a = read_c3d(tmp_path / "w.c3d")
    monkeypatch.setattr(c3dio, "_read_ezc3d", lambda p: (_ for _ in ()).throw(RuntimeError("no")))
    b = read_c3d(tmp_path / "w.c3d")
    assert (a.metadata["reader"], b.metadata["reader"]) == ("ezc3d", "c3d")
    for back in (a, b):
        assert set(back.subject_parameters) == set(t.subject_parameters)
        for k, v in t.subject_parameters.items():      # float32 in the file
            assert back.subject_parameters[k] == pytest.approx(v, rel=1e-6, abs=1e-6), k


def test_a_trial_without_measurements_writes_no_processing_group(tmp_path):
    trial = _random_trial(np.random.default_rng(5))
    write_c3d(trial, tmp_path / "w.c3d")
    assert "PROCESSING" not in ezc3d.c3d(str(tmp_path / "w.c3d"))["parameters"]
    assert read_c3d(tmp_path / "w.c3d").subject_parameters == {}
