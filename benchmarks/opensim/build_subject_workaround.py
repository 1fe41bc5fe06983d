"""Workaround for `bonecap build-subject --generic MODEL.osim --static ...` crashing in write_subject.

As of commit 17142fd, ``bonecap build-subject`` on an OpenSim template fails with
``yaml.representer.RepresenterError: ('cannot represent an object', OsimMarker(...))``:
``Skeleton.metadata["markers"]`` holds ``OsimMarker`` dataclasses that
``bonecap.subject._plain`` does not convert. This does what the command does
(``build_from_static`` then ``write_subject`` + ``report.json``) with those
markers turned into plain dicts first; nothing else changes.

    .venv/bin/python benchmarks/opensim/build_subject_workaround.py GENERIC.osim STATIC.c3d SUBJECT_DIR
"""
from __future__ import annotations

import dataclasses
import json
import shutil
import sys
from pathlib import Path

from bonecap.build_subject import build_from_static
from bonecap.subject import _plain, write_subject


def main(generic: str, static: str, out: str) -> None:
    subject, report = build_from_static(static, generic=generic)
    meta = subject.skeleton.metadata
    if "markers" in meta:
        meta["markers"] = [dataclasses.asdict(m) if dataclasses.is_dataclass(m) else m for m in meta["markers"]]
    report["bones"] = len(subject.skeleton.bones)
    out_p = Path(out)
    if out_p.exists():
        shutil.rmtree(out_p)
    out_p.mkdir(parents=True)
    write_subject(subject, out_p, extra={"report_file": "report.json"})
    (out_p / "report.json").write_text(json.dumps(_plain(report), indent=2, default=str))
    print(f"subject written to {out_p}")


if __name__ == "__main__":
    main(*sys.argv[1:4])
