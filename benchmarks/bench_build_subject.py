"""Speed and memory of ``bonecap build-subject`` on a whole-body phantom (issue #5: <= 60 s without the
QC pictures, <= 4 GB, on 2 cores).

Usage::

    .venv/bin/python benchmarks/bench_build_subject.py --phantom DIR [DIR ...] [--repeat K]

Each phantom (``bonecap phantom -o DIR``, with or without ``--marker-capsules``) is built as a user
builds it: ``python -m bonecap build-subject DIR/mri/station_* --static DIR/trials/static.c3d
--forearm-poses DIR/mri/forearm_*`` in a fresh process (imports included). The first run starts
from an empty template cache (``BONECAP_CACHE_DIR`` in a temporary folder: the embedded skeleton is
built, as on a first run on a machine), the later ones find the template there (every later run).
Printed per run: the build's own time (``report.json``'s stage timings without the QC pictures,
which the target leaves out), the process's wall time with the QC pictures and writing, user +
system CPU of the process tree, the peak resident memory of the largest process (MiB), the stage
timings and the load average before the run (the machine is shared: compare runs made together).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def run_once(phantom: Path, cache: Path, out: Path) -> dict:
    stations = sorted((phantom / "mri").glob("station_*"))
    forearm = sorted((phantom / "mri").glob("forearm_*"), key=lambda p: float(p.name.split("_")[1]))
    if not stations:
        raise SystemExit(f"{phantom}: no mri/station_* folders (make one with `bonecap phantom -o {phantom}`)")
    cmd = [sys.executable, "-m", "bonecap", "build-subject", *map(str, stations), "-o", str(out)]
    if (phantom / "trials/static.c3d").is_file():
        cmd += ["--static", str(phantom / "trials/static.c3d")]
    if len(forearm) == 3:
        cmd += ["--forearm-poses", *map(str, forearm)]
    env = dict(os.environ, BONECAP_CACHE_DIR=str(cache))
    load = os.getloadavg()[0]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode:
        raise SystemExit(f"build-subject failed on {phantom}:\n{proc.stderr[-3000:]}")
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    timings = json.loads((out / "report.json").read_text())["timings_s"]
    return {"build_s": sum(v for k, v in timings.items() if k != "qc pictures"), "wall_s": wall,
            "cpu_s": (ru.ru_utime - before.ru_utime) + (ru.ru_stime - before.ru_stime),
            "peak_mib": ru.ru_maxrss / 1024, "timings": timings, "load": load}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--phantom", type=Path, nargs="+", required=True)
    ap.add_argument("--repeat", type=int, default=2, help="runs per phantom, the first with an empty cache")
    args = ap.parse_args()
    print("| phantom | template cache | build without QC (s) | process wall (s) | CPU (s) | peak RSS (MiB) |"
          " stages (s) | load (1 min) |")
    print("|---|---|---:|---:|---:|---:|---|---:|")
    for ph in args.phantom:
        with tempfile.TemporaryDirectory() as tmp:
            cache = Path(tmp) / "cache"
            for k in range(args.repeat):
                r = run_once(ph, cache, Path(tmp) / f"subject_{k}")
                stages = ", ".join(f"{n} {v:.1f}" for n, v in r["timings"].items())
                # ru_maxrss of RUSAGE_CHILDREN is the largest child so far: exact for the first run,
                # an upper bound for the later ones
                print(f"| {ph} | {'empty' if k == 0 else 'warm'} | {r['build_s']:.1f} | {r['wall_s']:.1f} | "
                      f"{r['cpu_s']:.1f} | {r['peak_mib']:.0f} | {stages} | {r['load']:.1f} |", flush=True)


if __name__ == "__main__":
    main()
