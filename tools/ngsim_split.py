"""Split the NGSIM CommonRoad scenarios into training and held-out recordings, by map section.

    python tools/ngsim_split.py data/commonroad_ngsim data/ngsim_split

writes ``OUT/train/`` and ``OUT/heldout/``: symbolic links to the ``.xml`` files (nothing is
copied), then ``counterscene generate --from-commonroad OUT/train --out data/ngsim`` converts
them.

Why by map section, not by file: the files of one map section (``USA_US101-10_1_T-1``,
``USA_US101-10_2_T-1``, ...) are overlapping time windows of the same traffic (they share
vehicles), and many files differ only in their planning problem. A file-level split would put
the same cars on both sides.

Held out (:data:`HELDOUT`): all of Peachtree Street (Atlanta; another city and another street
than the training arterial, Lankershim Boulevard in Los Angeles), and every fifth US-101 map
section. US-101's sections are crops of one freeway recorded in the same periods: a held-out
section's vehicles may have driven through a training section earlier or later, so the
Peachtree figures are the clean test of unseen traffic.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

#: Map sections (``<country>_<map>-<id>``) held out of training.
HELDOUT = (
    "USA_Peach-1",
    "USA_Peach-2",
    "USA_Peach-3",
    "USA_Peach-4",
    *(f"USA_US101-{i}" for i in (5, 10, 15, 20, 25, 30)),
)


def map_section(name: str) -> str:
    """``USA_US101-10_2_T-1.xml`` -> ``USA_US101-10``: the file name's map section."""
    m = re.match(r"([A-Z]+_[A-Za-z0-9]+-\d+)_", name)
    if m is None:
        raise ValueError(f"{name}: not a CommonRoad benchmark file name")
    return m.group(1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("source", help="directory of CommonRoad NGSIM .xml files")
    ap.add_argument("out", help="output directory (gets train/ and heldout/)")
    args = ap.parse_args()
    files = sorted(Path(args.source).rglob("*.xml"))
    if not files:
        raise SystemExit(f"{args.source}: no .xml files")
    # Every name is read before anything is written: a foreign file refuses the whole split.
    try:
        sides = ["heldout" if map_section(f.name) in HELDOUT else "train" for f in files]
    except ValueError as exc:
        raise SystemExit(f"{args.source}: {exc}") from None
    counts = {"train": 0, "heldout": 0}
    for f, side in zip(files, sides, strict=True):
        dest = Path(args.out) / side / f.name
        dest.parent.mkdir(parents=True, exist_ok=True)
        if not dest.exists():
            dest.symlink_to(f.resolve())
        counts[side] += 1
    print(f"{counts['train']} training files, {counts['heldout']} held-out files in {args.out}")


if __name__ == "__main__":
    main()
