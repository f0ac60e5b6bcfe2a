"""The text report ``counterscene stress`` prints at the end of a run (without ``--json``)."""

from __future__ import annotations

from counterscene_env.cli.common import fmt
from counterscene_env.report.document import count
from counterscene_env.scene.sources import skip_text


def print_stress(config, summary: dict, times: dict, scenario: str, workers: int) -> None:
    """The text report of a finished run (a ``StressConfig``, its ``summarize`` and
    ``timings``; ``scenario`` as given on the command line): the run, the paper's table row,
    the rates, the timing line."""
    sim = config.sim
    print(
        f"{count(summary['episodes'], 'episode')} of {scenario}, planner {config.planner}, "
        f"selector {sim.selector}, guidance {sim.guidance} (source {sim.selection_source}, "
        f"{sim.num_samples} samples)"
        + (
            f", the most severe of {config.rollouts} rollouts per episode"
            if config.rollouts > 1
            else ""
        )
    )
    model = summary.get("model") or {}
    if model.get("given") not in (None, "default"):  # the shipped one goes without saying
        print(f"world model: {model['given']} ({model['directory']})")
    print(f"{'':8s}" + "".join(f"{k:>10s}" for k in ("ADE", "FDE", "ORR", "HBR", "CR")))
    for name, row in summary["horizons"].items():
        print(
            f"{name:8s}"
            + "".join(f"{fmt(row[k]):>10s}" for k in ("ADE", "FDE", "ORR", "HBR", "CR"))
        )
    # An episode whose agents never close on each other has no TTC: the mean is over the rest.
    without = summary["episodes_without_ttc_conflict"]
    if without == summary["episodes"]:
        ttc = "no TTC conflict in any episode"
    else:
        ttc = f"mean min TTC {fmt(summary['mean_min_ttc'])} s" + (
            f" ({count(without, 'episode')} without a TTC conflict)" if without else ""
        )
    print(
        f"episode CR {fmt(summary['cr'])}, ego-adversary CR {fmt(summary['cr_ego_adversary'])}, "
        f"non-ego CR {fmt(summary['cr_non_ego'])} (not in the log "
        f"{fmt(summary['cr_non_ego_new'])}), "
        f"{ttc}, min clearance to adversary "
        f"{fmt(summary['mean_min_clearance_adversary'])} m, fallbacks {summary['fallbacks']}"
    )
    # A real map lacks the car parks and driveways where logged cars stand: the log's own
    # positions on the same map are the reference for the simulation's off-road share.
    print(
        f"off the road: ORR {fmt(summary['orr'])} (the log itself "
        f"{fmt(summary['orr_log'])}), moving vehicles {fmt(summary['orr_moving'])} (the log "
        f"itself {fmt(summary['orr_moving_log'])})"
    )
    cut = summary["episodes_cut_at_log_end"]
    if cut:
        its = "its" if cut == 1 else "their"
        print(f"{count(cut, 'episode')} ended with {its} log (short logs)")
    if summary["scenes_skipped"]:
        print(f"stored scenes not played: {skip_text(summary['scenes_skipped'])}")
    print(
        f"{fmt(times['seconds_per_episode'])} s per episode, "
        f"{fmt(times['seconds_per_replan'])} s per replan"
        + (f" ({workers} workers)" if workers > 1 else "")
    )
