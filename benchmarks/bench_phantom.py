"""Time, CPU and peak memory of ``bonecap phantom`` (targets: default <= 90 s and <= 300 MB, tiny <= 5 s).

Usage: ``python benchmarks/bench_phantom.py [--preset default|tiny|both] [--seed N] [--generic ...] [--repeat K]``.

Each run is a fresh ``python -m bonecap phantom`` process (imports included, as a user runs it),
so its peak resident memory is its own: ``ru_maxrss`` of the finished child (the largest of the
process and the children it forks: the skeleton's meshing workers, the trials child, the children
that decimate the body surfaces at the default preset). Some run beside the main process, so the machine's total
is measured too: the proportional set size (PSS: shared pages split among the processes sharing
them) summed over the process tree, sampled every 50 ms (Linux; NaN elsewhere). Both in MiB
(2**20 bytes). Prints a markdown table: wall time, user + system CPU (the machine is shared, so
wall times vary with the load; CPU time much less), the two peaks, the stage timings from
``phantom.json`` and the load average before the run. Run it alone: another Python process that maps
the same libraries (a second phantom, a test run) takes its share of their pages, and the tree's PSS
reads low by up to ~20 MiB.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path


def _tree_pss_mib(pid: int) -> float:
    """Proportional set size of a process and all its descendants (Linux), MiB.

    PSS splits pages shared between processes (the forked meshing workers and the
    trials child share the parent's pages copy-on-write) among them, so the sum is
    what the whole command holds on the machine at that moment.
    """
    total, todo = 0, [pid]
    while todo:
        p = todo.pop()
        try:
            for line in Path(f"/proc/{p}/smaps_rollup").read_text().splitlines():
                if line.startswith("Pss:"):
                    total += int(line.split()[1])
                    break
            for task in Path(f"/proc/{p}/task").iterdir():
                todo += [int(c) for c in (task / "children").read_text().split()]
        except (OSError, ValueError):          # the process ended meanwhile
            continue
    return total / 1024


def _sample_tree(proc: subprocess.Popen, peak: list) -> None:
    while proc.poll() is None:
        peak[0] = max(peak[0], _tree_pss_mib(proc.pid))
        time.sleep(0.05)


def run_once(preset: str, seed: int, generic: str) -> dict:
    """One ``bonecap phantom`` in a child process: wall (s), cpu (s), peak RSS (MB), stage timings."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "ph"
        cmd = [sys.executable, "-m", "bonecap", "phantom", "-o", str(out), "--seed", str(seed),
               "--preset", preset, "--generic", generic]
        load = os.getloadavg()[0]
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        tree_peak = [0.0]
        sampler = threading.Thread(target=_sample_tree, args=(proc, tree_peak), daemon=True)
        if Path("/proc/self/smaps_rollup").exists():
            sampler.start()
        _, err = proc.communicate()
        if sampler.is_alive():
            sampler.join()
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            raise SystemExit(f"bonecap phantom failed:\n{err.decode(errors='replace')}")
        ru = resource.getrusage(resource.RUSAGE_CHILDREN)
        summary = json.loads((out / "phantom.json").read_text())
        size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    return {"wall": wall, "ru": ru, "stages": summary["timings_s"], "size_mb": size / 1e6, "load": load,
            "tree_pss": tree_peak[0] if tree_peak[0] > 0 else float("nan")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--preset", default="both", choices=["default", "tiny", "both"])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--generic", default="default")
    ap.add_argument("--repeat", type=int, default=1)
    args = ap.parse_args()
    presets = ["tiny", "default"] if args.preset == "both" else [args.preset]
    print("| preset | seed | wall (s) | CPU user+sys (s) | peak RSS, largest process (MiB) |"
          " peak PSS, process tree (MiB) | stages, wall (s) | load (1 min) | output (MB) |")
    print("|---|---:|---:|---:|---:|---:|---|---:|---:|")
    prev_cpu = 0.0
    for preset in presets:
        for _ in range(args.repeat):
            r = run_once(preset, args.seed, args.generic)
            # RUSAGE_CHILDREN accumulates CPU over the children so far: take the difference;
            # ru_maxrss is the largest child so far, so run the small preset first
            cpu = r["ru"].ru_utime + r["ru"].ru_stime
            stages = ", ".join(f"{k} {v:.1f}" for k, v in r["stages"].items())
            print(f"| {preset} | {args.seed} | {r['wall']:.1f} | {cpu - prev_cpu:.1f} | "
                  f"{r['ru'].ru_maxrss / 1024:.0f} | {r['tree_pss']:.0f} | {stages} | {r['load']:.1f} | "
                  f"{r['size_mb']:.0f} |",
                  flush=True)
            prev_cpu = cpu


if __name__ == "__main__":
    main()
