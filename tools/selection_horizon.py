"""The selection rows of a ``paper-tables`` run at one horizon band (docs/reproducing_the_paper.md).

``paper-tables`` averages its selection table over 3 s and 7 s, as the paper does; the issue
on the selectors asks for CR ego-adversary at 8-10 s. This reads a road's rows from a
``paper-tables`` output folder and prints, for each selector, CR ego-adversary and ADE over
the band (``paper_tables.per_episode``: the same per-episode values as the tables), the
whole-episode ego-adversary rate, the causal row's paired difference to each baseline and its
ratio to the best one. ``--split`` tells where each gap comes from: the episodes split by
whether the two selectors chose the same adversary, and if not by the two conflict types
(causal's first), each group's figures for both rows and its share of the gap.

``--mined`` restricts every row to the paper's evaluation set: the episodes whose causal
selection on the log found a conflict. The paper's appendix treats a scene where no candidate
survives the filtering as an invalid mining case that gets no guidance configuration; a
``paper-tables`` run plays every episode, those included (the causal row has no adversary
there, the baselines choose one anyway). The subset is fixed by the log before any rollout,
so it does not depend on an outcome:

    python tools/selection_horizon.py OUT/intersection [--seconds 8 9 10] [--split] [--mined]
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
    ap.add_argument("--split", action="store_true", help="where each gap comes from")
    ap.add_argument(
        "--mined",
        action="store_true",
        help="only episodes where the causal mining found a conflict",
    )
    args = ap.parse_args()
    rows = [r for r in ROWS if (args.road / r / "episodes.jsonl").exists()]
    if "counterscene" not in rows or len(rows) < 2:
        raise SystemExit(f"{args.road}: needs the counterscene row and a baseline row")
    # load_run skips a last line cut short by a running or killed run, as every reader does.
    records = {r: load_run(args.road / r).records for r in rows}
    n = min(len(v) for v in records.values())  # the rows pair by episode order
    records = {r: v[:n] for r, v in records.items()}
    if args.mined:  # the paper's valid mining cases: a causal adversary chosen on the log
        keep = [i for i, x in enumerate(records["counterscene"]) if x["adversary_tier"] is not None]
        print(f"{args.road}: {len(keep)} of {n} episodes are valid mining cases")
        records = {r: [v[i] for i in keep] for r, v in records.items()}
        n = len(keep)
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
                f" | causal minus it: CR {signed(-100 * c.difference, 1)} points"
                f" [{signed(-100 * c.high, 1)}, {signed(-100 * c.low, 1)}],"
                f" ADE {signed(-a.difference, 2)} m [{signed(-a.high, 2)}, {signed(-a.low, 2)}]"
            )
        print(line)
    best = max(rows[1:], key=lambda r: np.nanmean(values[r][0]))
    ratio = np.nanmean(ref_cr) / np.nanmean(values[best][0])
    print(f"  causal / best baseline ({best}): {ratio:.2f}x")
    if args.split:
        for r in rows[1:]:
            split(records["counterscene"][:n], records[r][:n], values["counterscene"], values[r], r)


def signed(x: float, digits: int) -> str:
    """``x`` with its sign to ``digits`` decimals; no difference reads ``+0.0``, never
    ``-0.0`` (a negated zero, or a small negative value that rounds to zero)."""
    return f"{round(float(x), digits) + 0.0:+.{digits}f}"


def split(causal: list, other: list, ref: tuple, val: tuple, name: str) -> None:
    """Print the causal row against ``name`` per group of episodes: the same adversary, or
    the two rows' conflict types; each group's CR and ADE over the band for both rows and
    its share of the whole gap (the shares add up to the gap)."""
    groups: dict[str, list[int]] = {}
    for i, (a, b) in enumerate(zip(causal, other, strict=True)):
        if a.get("adversary_id") == b.get("adversary_id"):
            key = "same adversary"
        else:
            key = f"{a.get('adversary_type') or 'none'} / {b.get('adversary_type') or 'none'}"
        groups.setdefault(key, []).append(i)
    # A group's share of a gap: its summed difference over the episodes where both rows have
    # a value (the gap's own denominator), so the shares add up to the gap.
    d_cr, d_ade = ref[0] - val[0], ref[1] - val[1]
    n_cr, n_ade = np.isfinite(d_cr).sum(), np.isfinite(d_ade).sum()
    print(f"  causal against {name}, by group (causal's conflict type / {name}'s):")
    for key, idx in sorted(groups.items(), key=lambda kv: -len(kv[1])):
        cr_a, cr_b = np.nanmean(ref[0][idx]), np.nanmean(val[0][idx])
        ade_a, ade_b = np.nanmean(ref[1][idx]), np.nanmean(val[1][idx])
        share_cr = 100 * np.nansum(d_cr[idx]) / n_cr
        share_ade = np.nansum(d_ade[idx]) / n_ade
        print(
            f"    {key:30s} {len(idx):4d} episodes  CR {100 * cr_a:5.1f} / {100 * cr_b:5.1f} %"
            f" ({signed(share_cr, 1):>5s} points of the gap)  ADE {ade_a:.2f} / {ade_b:.2f} m"
            f" ({signed(share_ade, 2)} m of the gap)"
        )


if __name__ == "__main__":
    main()
