"""The selection rows of a ``paper-tables`` run at one horizon band (docs/reproducing_the_paper.md).

``paper-tables`` averages its selection table over 3 s and 7 s, as the paper does; the issue
on the selectors asks for CR ego-adversary at 8-10 s. This reads a road's rows from a
``paper-tables`` output folder and prints, for each selector, CR ego-adversary and ADE over
the band (``paper_tables.per_episode``: the same per-episode values as the tables), the
whole-episode ego-adversary rate, the causal row's paired difference to each baseline and its
ratio to the best one:

    python tools/selection_horizon.py OUT/intersection [--seconds 8 9 10]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from counterscene_env.report import paper_tables as pt
from counterscene_env.report.rundir import load_run

ROWS = ("counterscene", "ttc", "distance", "random")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("road", type=Path, help="a road's folder of a paper-tables run")
    ap.add_argument("--seconds", type=int, nargs="+", default=[8, 9, 10])
    args = ap.parse_args()
    rows = [r for r in ROWS if (args.road / r / "episodes.jsonl").exists()]
    if "counterscene" not in rows or len(rows) < 2:
        raise SystemExit(f"{args.road}: needs the counterscene row and a baseline row")
    # load_run skips a last line cut short by a running or killed run, as every reader does.
    records = {r: load_run(args.road / r).records for r in rows}
    n = min(len(v) for v in records.values())  # the rows pair by episode order
    band = tuple(args.seconds)
    values = {}
    for r in rows:
        cr = np.nanmean(pt.per_episode(records[r][:n], "CR_adv", band), axis=1)
        ade = np.nanmean(pt.per_episode(records[r][:n], "ADE", band), axis=1)
        # No adversary (null, read back as NaN): no collision with it.
        whole = np.nan_to_num([float(x.get("cr_ego_adversary", np.nan)) for x in records[r][:n]])
        values[r] = (cr, ade, whole)
    ref_cr, ref_ade, _ = values["counterscene"]
    print(f"{args.road}: {n} episodes per row, seconds {band}")
    for r in rows:
        cr, ade, whole = values[r]
        line = (
            f"  {r:12s} CR ego-adversary {100 * np.nanmean(cr):5.1f} %  ADE {np.nanmean(ade):.2f} m"
            f"  ego-adversary over the episode {100 * whole.mean():5.1f} %"
        )
        if r != "counterscene":
            # paired() gives the row minus the reference; printed here as causal minus the row.
            c = pt.paired(ref_cr[:, None], cr[:, None], True)
            a = pt.paired(ref_ade[:, None], ade[:, None], False)
            line += (
                f" | causal minus it: CR {-100 * c.difference:+.1f} points"
                f" [{-100 * c.high:+.1f}, {-100 * c.low:+.1f}],"
                f" ADE {-a.difference:+.2f} m [{-a.high:+.2f}, {-a.low:+.2f}]"
            )
        print(line)
    best = max(rows[1:], key=lambda r: np.nanmean(values[r][0]))
    ratio = np.nanmean(ref_cr) / np.nanmean(values[best][0])
    print(f"  causal / best baseline ({best}): {ratio:.2f}x")


if __name__ == "__main__":
    main()
