"""Time and peak memory of ``bonecap phantom`` (targets: default <= 90 s and <= 300 MB, tiny <= 5 s).

Usage: ``python benchmarks/bench_phantom.py [--preset default|tiny] [--seed N] [--generic ...]``.
Prints a markdown table row with the stage timings (from ``phantom.json``) and the process's
peak resident memory (``ru_maxrss``), measured in this process around one call.
"""

from __future__ import annotations

import argparse
import json
import resource
import tempfile
import time
from pathlib import Path

from bonecap.phantom import make_phantom


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--preset", default="default", choices=["default", "tiny"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--generic", default="default")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        summary = make_phantom(Path(tmp) / "ph", seed=args.seed, preset=args.preset, generic=args.generic)
        wall = time.perf_counter() - t0
        size = sum(p.stat().st_size for p in (Path(tmp) / "ph").rglob("*") if p.is_file())
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    stages = ", ".join(f"{k} {v:.1f}" for k, v in summary["timings_s"].items())
    print("| preset | template | seed | wall (s) | stages (s) | peak RSS (MB) | output (MB) |")
    print("|---|---|---:|---:|---|---:|---:|")
    print(f"| {args.preset} | {args.generic} | {args.seed} | {wall:.1f} | {stages} | {peak_mb:.0f} | "
          f"{size / 1e6:.0f} |")
    print(json.dumps(summary["timings_s"]))


if __name__ == "__main__":
    main()
