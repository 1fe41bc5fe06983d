"""Compare two ``bonecap phantom`` output folders file for file (a change meant to keep the phantom).

Usage: ``python benchmarks/compare_phantoms.py REF_DIR NEW_DIR``

DICOM files by pixel data and image position, NIfTI by data, JSON by content without timings (the study
UID is random per run: ``truth/stations.json`` and ``phantom.json`` are reported but expected to differ
in it and in the output path), everything else byte for byte. Exit code 1 when a file is missing or
differs beyond those.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import nibabel as nib
import numpy as np
import pydicom

#: Keys that legitimately change between two runs of the same phantom.
_VOLATILE = {"timings_s", "wall_s", "out_dir", "study_uid"}


def _strip(obj):
    if isinstance(obj, dict):
        return {k: _strip(v) for k, v in obj.items() if k not in _VOLATILE}
    if isinstance(obj, list):
        return [_strip(v) for v in obj]
    return obj


def same_file(a: Path, b: Path) -> bool:
    if a.suffix == ".dcm" or (a.suffix == "" and "mri" in a.parts):
        da, db = pydicom.dcmread(a), pydicom.dcmread(b)
        return bool(np.array_equal(da.pixel_array, db.pixel_array)
                    and da.ImagePositionPatient == db.ImagePositionPatient)
    if a.name.endswith((".nii", ".nii.gz")):
        return bool(np.array_equal(np.asanyarray(nib.load(a).dataobj), np.asanyarray(nib.load(b).dataobj)))
    if a.suffix == ".json":
        return _strip(json.loads(a.read_text())) == _strip(json.loads(b.read_text()))
    return a.read_bytes() == b.read_bytes()


def main() -> int:
    if len(sys.argv) != 3:
        print(__doc__)
        return 2
    ref, new = Path(sys.argv[1]), Path(sys.argv[2])
    fa = sorted(p.relative_to(ref) for p in ref.rglob("*") if p.is_file())
    fb = sorted(p.relative_to(new) for p in new.rglob("*") if p.is_file())
    missing = sorted(set(fa) ^ set(fb))
    differing = [r for r in fa if r in set(fb) and not same_file(ref / r, new / r)]
    print(f"{len(fa)} files in {ref}, {len(fb)} in {new}; {len(missing)} in one only, {len(differing)} differ")
    for r in missing[:20]:
        print("  only in one:", r)
    for r in differing[:20]:
        print("  differs:", r)
    return 1 if missing or differing else 0


if __name__ == "__main__":
    sys.exit(main())
