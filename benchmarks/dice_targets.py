"""Issue #5's Dice targets over ``bonecap evaluate subject --json`` results: the slice rules' labels, the
personal skeleton's label maps and the refined maps (the personal map with the density rule's bones moved
to the image, ``refined_station_<k>.nii.gz``), side by side.

Usage::

    bonecap evaluate subject SUBJECT_DIR --truth PHANTOM/truth --json > ev.json
    python benchmarks/dice_targets.py ev.json [ev2.json ...]

Per evaluation and bone group (long bones: target Dice >= oracle - 0.03; pelvis, sacrum, scapulae,
patellae: >= oracle - 0.06; the vertebrae by region, also >= oracle - 0.06): the median Dice of the
rules' labels (``dice``), of the personal skeleton's maps (``personal_dice``), of the refined maps
(``refined_dice``) and of the oracle, and how many bones of the group meet the target with each. Prints a
markdown table.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

LONG = ("femur", "tibia", "fibula", "humerus", "radius", "ulna")
GROUPS = {
    "long bones": lambda b: b.startswith(LONG),
    "pelvis, sacrum": lambda b: b.startswith(("hip_", "sacrum")),
    "scapulae, patellae": lambda b: b.startswith(("scapula", "patella")),
    "lumbar": lambda b: b[0] == "l" and b[1:].isdigit(),
    "thoracic": lambda b: b[0] == "t" and b[1:].isdigit(),
    "cervical": lambda b: b[0] == "c" and b[1:].isdigit(),
}


def rows(path: Path) -> list[str]:
    """The table's rows (markdown) for one evaluation file, a row per bone group it has."""
    bones = json.loads(path.read_text())["bones"]
    name = f"{path.parent.name}/{path.name}" if path.parent.name else path.name
    out = []
    for group, member in GROUPS.items():
        sel = {b: r for b, r in bones.items() if member(b) and "dice" in r and "oracle_dice" in r}
        if not sel:
            continue
        margin = 0.03 if group == "long bones" else 0.06

        def med(key):
            v = [r[key] for r in sel.values() if r.get(key) is not None and np.isfinite(r[key])]
            return f"{np.median(v):.3f}" if v else "-"

        def meet(key):
            return sum(1 for r in sel.values() if r.get(key) is not None and r[key] >= r["oracle_dice"] - margin)

        has = {k: any(k in r for r in sel.values()) for k in ("personal_dice", "refined_dice")}
        out.append(f"| {name} | {group} | {len(sel)} | {med('dice')} | "
                   + " | ".join(med(k) if has[k] else "-" for k in has)
                   + f" | {med('oracle_dice')} | {meet('dice')} | "
                   + " | ".join(str(meet(k)) if has[k] else "-" for k in has) + " |")
    return out


def main(argv: list[str]) -> int:
    """Print the table for the evaluation files ``argv``; 2 on a missing file or no argument."""
    if not argv:
        print(__doc__)
        return 2
    print("| evaluation | bones | n | Dice, rules | Dice, personal | Dice, refined | oracle | meet, rules | "
          "meet, personal | meet, refined |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for a in argv:
        p = Path(a)
        if not p.is_file():
            print(f"{p}: no such file", file=sys.stderr)
            return 2
        print("\n".join(rows(p)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
