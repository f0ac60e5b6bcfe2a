"""Real logs, measured: what loads, how the maps fit the logs, and where selection finds an
adversary. The evaluation behind docs/scenes.md ("Real logs, measured").

    python tools/real_logs.py --scenarionet nuscenes=../shared/data/nuscenes_mini_scenarionet \
        --scenarionet waymo=../shared/data/waymo_scenarionet --commonroad ngsim=/tmp/cr \
        --plots 2 --out reports/real_logs

Per source (``NAME=DIR``; ``--scenarionet`` and ``--commonroad`` repeat; ``--scenarionet``
also reads a dataset directory of ``counterscene generate``, e.g. generated held-out scenes):

- loading: scenes, agents by type, what the importer repaired or dropped, load time;
- the factual log against its own map, over the whole log: the share of vehicle positions
  off the road (all vehicles; moving ones, over 1 m/s by ``metrics.path_speeds``) with a
  95 % Wilson interval over positions, counting only the positions the map can judge
  (``RoadMap.judged``: inside a cropped map's extent), as the ORR metrics do; the positions
  beyond the extent are counted apart (``vehicle_positions_beyond_map``) (positions of one track are correlated: read the
  interval as a floor on the uncertainty), ORR split parked / moving, and the ego's factual
  collision rate (ego CR, which must be 0: a log where the ego hits someone is no test);
- causal selection on the factual future from the scene's "now" (``adversary/``): scenes with
  a candidate in a paper tier, scenes with an adversary once the strict gates apply, and for
  the scenes left without one, how many of their tiered candidates fail each gate (a
  candidate can fail several);
- ``--closed-loop K``: the unguided closed loop (``guidance="none"``, log-replay ego, the
  shipped model unless ``--model``) on the first K scenes: the simulated vehicles' ORR (all;
  moving), vehicle-vehicle collisions between non-ego vehicles that the log itself does not
  have over the same steps (a pair overlapping in the log is not new), each named by how
  its two vehicles moved into their first overlapping step (``PLAN``: the model's plan;
  ``LOG``, ``IDM``, ``COAST``: the fallback movers the network does not drive; ``YIELD``,
  ``KEEP``: a reflex changed the step), and the episodes whose
  selection (on the factual future, as the closed loop makes it) found an adversary;
  ``--network-alone`` runs the same with the reflexes off (no yielding, no road keeping) and
  no final-step lane keeping: what the world model itself does. ``--min-seconds S`` keeps
  only logs at least S seconds long (all sources);
- ``--plots K``: the drivable area over the log for the first K scenes, PNG: moving vehicles'
  positions green on the road and red off it, parked ones grey or orange, those beyond the
  map's extent purple, the ego blue.

Writes ``OUT/real_logs.json`` and ``OUT/real_logs.md``; timings are kept apart from the
results (``timing`` in the JSON).
"""

from __future__ import annotations

import argparse
import json
import time
from collections import Counter
from pathlib import Path

import numpy as np

from counterscene_env.adversary.conflicts import (
    MIN_JOINT_STEPS,
    STRICT_GATES,
    mine,
    strict_gate_failures,
)
from counterscene_env.adversary.tracks import check_tracks
from counterscene_env.metrics import evaluate_scene, path_speeds, wilson_interval
from counterscene_env.scene.core import Scene

MOVING_SPEED = 1.0  # [m/s] the "moving" positions
HORIZON_STEPS = 100  # [steps] the selection looks this far into the factual future (10 s)


def load_source(kind: str, path: str) -> tuple[list[Scene], list[float], dict]:
    """Every scene of a source, the seconds each took to load, and what was skipped."""
    skipped: dict = {}
    if kind == "scenarionet":
        from counterscene_env.scene.reading import iter_scenes

        def short(name: str) -> None:
            skipped[name] = "too short"

        it = (scene for scene, _ in iter_scenes(path, on_short=short))
    else:
        from counterscene_env.scene.commonroad import iter_commonroad

        report: dict = {}
        it = iter_commonroad(path, report=report)
    scenes, times = [], []
    start = time.perf_counter()
    for scene in it:  # the time to produce each scene, parsing included
        scenes.append(scene)
        times.append(time.perf_counter() - start)
        start = time.perf_counter()
    if kind == "commonroad":
        skipped = {
            **report["skipped"],
            **{f: f"duplicate of {first}" for f, first in report["duplicates"].items()},
        }
    return scenes, times, skipped


def factual_fit(scene: Scene) -> dict:
    """Off-road counts of the logged vehicles over the whole log, and the factual metrics.

    The off-road counts and the positions they are shares of are both only the positions the
    map can judge (``RoadMap.judged``: inside a cropped map's extent), as the ORR metrics
    count them; ``vehicle_positions_beyond_map`` are the valid vehicle positions left out.
    """
    whole = scene.replace(current_index=0)
    logged = scene.valid & scene.vehicle_mask[:, None]
    veh = logged & scene.road.judged(scene.positions)
    off = scene.road.off_road(scene.positions) & veh
    moving = veh & (path_speeds(scene) > MOVING_SPEED)
    m = evaluate_scene(whole)
    return {
        "judged_vehicle_positions": int(veh.sum()),
        "vehicle_off": int(off.sum()),
        "judged_moving_positions": int(moving.sum()),
        "moving_off": int((off & moving).sum()),
        "vehicle_positions_beyond_map": int((logged & ~veh).sum()),
        "orr_parked": m["orr_parked"],
        "orr_moving": m["orr_moving"],
        "ego_cr": m["cr"],
        "non_ego_cr": m["cr_non_ego"],
    }


def selection_gates(scene: Scene) -> dict:
    """Causal mining on the factual future from "now": tiered candidates and the gates."""
    lo = scene.current_index + 1
    hi = min(scene.num_steps, lo + HORIZON_STEPS)
    tracks = check_tracks(
        scene.positions[:, lo:hi],
        scene.valid[:, lo:hi],
        scene.ego_index,
        speeds=scene.speeds[:, lo:hi],
        dt=scene.dt,
        min_joint_steps=MIN_JOINT_STEPS,
    )
    eligible = scene.vehicle_mask.copy()
    paper = [c for c in mine(tracks, eligible, lo, False, MIN_JOINT_STEPS) if c.tier is not None]
    fails = [strict_gate_failures(tracks, c, lo) for c in paper]
    return {
        "paper_candidates": len(paper),
        "adversary": any(not f for f in fails),
        "gate_failures": {g: sum(g in f for f in fails) for g in STRICT_GATES},
    }


def new_vehicle_collisions(sim: Scene, factual: Scene, source: np.ndarray) -> list[str]:
    """Pairs of non-ego vehicles that overlap in ``sim``'s rollout but never in the log over
    the same steps, each named by how the two moved into their first overlapping step
    (``source`` ``[N, T]``: ``ClosedLoop.motion_source``), e.g. ``"PLAN-PLAN"`` (both on
    the model's plans: the network's own collision) or ``"IDM-LOG"`` (neither)."""
    from counterscene_env.metrics.safety import new_vehicle_collisions, rollout_slice
    from counterscene_env.sim import MotionSource

    rolled = source[:, rollout_slice(sim)]
    kinds = []
    for a, b, t in new_vehicle_collisions(sim, factual):
        names = sorted(MotionSource(int(rolled[r, t])).name for r in (a, b))
        kinds.append("-".join(names))
    return kinds


def closed_loop(scenes: list[Scene], model_dir: str, network_alone: bool = False) -> dict:
    """The unguided closed loop with log-replay ego on each scene (module docstring)."""
    from counterscene_env.planners import make_planner
    from counterscene_env.sim import ClosedLoop, SimConfig
    from counterscene_env.stress import run_batch
    from counterscene_env.world_model import load_model

    alone = {"traffic_yields": False, "road_keeping": False, "lane_steering": 0}
    loop = ClosedLoop(
        load_model(model_dir), SimConfig(guidance="none", **(alone if network_alone else {}))
    )
    rows, start = [], time.perf_counter()
    for i, scene in enumerate(scenes):
        rec = run_batch(loop, [scene], [i], [make_planner("log")])[0]
        sim = loop.scene(0)
        factual = scene.time_slice(0, sim.num_steps)
        pairs = new_vehicle_collisions(sim, factual, loop.motion_source(0))
        rows.append(
            {
                "scenario_id": scene.scenario_id,
                "orr": rec["orr"],
                "orr_moving": rec["orr_moving"],
                "new_vehicle_collisions": len(pairs),
                "new_collision_movers": pairs,
                "adversary": rec["adversary_id"] is not None,
                "fallback": rec["fallback"],
                "rollout_s": rec["rollout_s"],
            }
        )
    n = len(rows)
    return {
        "episodes": n,
        "network_alone": network_alone,
        "orr_mean": float(np.nanmean([r["orr"] for r in rows])) if n else None,
        "orr_moving_mean": float(np.nanmean([r["orr_moving"] for r in rows])) if n else None,
        "episodes_with_new_vehicle_collision": rate(
            sum(r["new_vehicle_collisions"] > 0 for r in rows), n
        ),
        "episodes_with_adversary": rate(sum(r["adversary"] for r in rows), n),
        # Who was moving whom: PLAN-PLAN pairs are the network's own; pairs without PLAN are
        # between the fallback movers (log replay, IDM, coasting), which the network does not
        # drive.
        "new_collision_movers": dict(
            Counter(k for r in rows for k in r["new_collision_movers"]).most_common()
        ),
        "episodes_with_new_collision_involving_a_plan": rate(
            sum(any("PLAN" in k for k in r["new_collision_movers"]) for r in rows), n
        ),
        "per_episode": rows,
        "timing": {"seconds": time.perf_counter() - start},
    }


def rate(k: int, n: int) -> dict:
    lo, hi = wilson_interval(k, n)
    return {"k": k, "n": n, "rate": k / n if n else None, "ci95": [lo, hi]}


def summarise(name: str, scenes: list[Scene], times: list[float], skipped: dict) -> dict:
    """One source's results (and its timing, kept apart)."""
    types: Counter = Counter()
    repairs: Counter = Counter()
    dropped: Counter = Counter()
    for s in scenes:
        types.update(s.agent_types.tolist())
        for what in s.metadata.get("repairs", {}).values():
            repairs.update(w.split(":")[0].lstrip("0123456789 ") for w in what)
        dropped.update(
            str(w).split("(")[0].strip() for w in s.metadata.get("dropped_tracks", {}).values()
        )
    fits = [factual_fit(s) for s in scenes]
    gates = [selection_gates(s) for s in scenes]
    no_adv = [g for g in gates if not g["adversary"]]
    return {
        "source": name,
        "scenes": len(scenes),
        "skipped": skipped,
        "agents_by_type": dict(types),
        "repairs": dict(repairs),
        "dropped": dict(dropped),
        # Shares of the judged positions (inside the map's extent), see factual_fit.
        "vehicle_off_road": rate(
            sum(f["vehicle_off"] for f in fits), sum(f["judged_vehicle_positions"] for f in fits)
        ),
        "moving_off_road": rate(
            sum(f["moving_off"] for f in fits), sum(f["judged_moving_positions"] for f in fits)
        ),
        "vehicle_positions_beyond_map": sum(f["vehicle_positions_beyond_map"] for f in fits),
        "orr_parked_mean": float(np.nanmean([f["orr_parked"] for f in fits])),
        "orr_moving_mean": float(np.nanmean([f["orr_moving"] for f in fits])),
        "factual_ego_cr": rate(int(sum(f["ego_cr"] for f in fits)), len(fits)),
        "factual_non_ego_cr": rate(int(sum(f["non_ego_cr"] for f in fits)), len(fits)),
        "selection": {
            "scenes_with_paper_tier_candidate": sum(g["paper_candidates"] > 0 for g in gates),
            "scenes_with_adversary_strict": sum(g["adversary"] for g in gates),
            "scenes_without_candidate": sum(g["paper_candidates"] == 0 for g in gates),
            "without_adversary": len(no_adv),
            "their_tiered_candidates": sum(g["paper_candidates"] for g in no_adv),
            "of_which_fail_gate": {
                gate: sum(g["gate_failures"][gate] for g in no_adv) for gate in STRICT_GATES
            },
        },
        "per_scene": [
            {"scenario_id": s.scenario_id, **f, **g}
            for s, f, g in zip(scenes, fits, gates, strict=True)
        ],
        "timing": {
            "load_s_median": float(np.median(times)) if times else None,
            "load_s_total": float(np.sum(times)),
        },
    }


def plot_scene(scene: Scene, path: Path) -> None:
    """The drivable area over the whole log (module docstring)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import shapely.plotting

    fig, ax = plt.subplots(figsize=(9, 9))
    shapely.plotting.plot_polygon(
        scene.road.drivable_area, ax=ax, add_points=False, facecolor="#ccd4ee", edgecolor="none"
    )
    if scene.road.extent is not None:
        shapely.plotting.plot_polygon(
            scene.road.extent, ax=ax, add_points=False, facecolor="none", edgecolor="0.6", ls="--"
        )
    for c in scene.road.lane_centerlines:
        ax.plot(c[:, 0], c[:, 1], "-", color="#8890b0", lw=0.3)
    veh = scene.valid & scene.vehicle_mask[:, None]
    off = scene.road.off_road(scene.positions)
    on = ~off & scene.road.judged(scene.positions)  # beyond the map's extent: neither
    moving = veh & (path_speeds(scene) > MOVING_SPEED)
    parked = veh & ~moving
    style = [
        (parked & on, "0.55", 2, "parked, on road"),
        (parked & off, "orange", 2, "parked, off road"),
        (moving & on, "green", 1, "moving, on road"),
        (moving & off, "red", 3, "moving, off road"),
        (veh & ~on & ~off, "purple", 1, "beyond the map's extent"),
    ]
    for mask, color, size, label in style:
        p = scene.positions[mask]
        ax.plot(p[:, 0], p[:, 1], ".", color=color, ms=size, label=f"{label} ({mask.sum()})")
    e = scene.ego_index
    p = scene.positions[e, scene.valid[e]]
    ax.plot(p[:, 0], p[:, 1], "-", color="blue", lw=1.2, label="ego")
    p = scene.positions[veh]
    ax.set_xlim(p[:, 0].min() - 20, p[:, 0].max() + 20)
    ax.set_ylim(p[:, 1].min() - 20, p[:, 1].max() + 20)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"{scene.scenario_id}: drivable area (blue), map extent (dashed)")
    ax.legend(loc="upper right", fontsize=7)
    fig.savefig(path, dpi=90, bbox_inches="tight")
    plt.close(fig)


def markdown(results: list[dict]) -> str:
    def pct(r: dict) -> str:
        if r["rate"] is None:
            return "n/a"
        lo, hi = r["ci95"]
        return f"{100 * r['rate']:.2f} % [{100 * lo:.2f}, {100 * hi:.2f}] ({r['k']}/{r['n']})"

    lines = [
        "| source | scenes | vehicle positions off-road (inside the map's extent) | "
        "moving (>1 m/s) off-road | positions beyond the map | "
        "ORR parked / moving (mean) | factual ego CR | adversary (strict) / paper tier |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        sel = r["selection"]
        lines.append(
            f"| {r['source']} | {r['scenes']} | {pct(r['vehicle_off_road'])} | "
            f"{pct(r['moving_off_road'])} | {r['vehicle_positions_beyond_map']} | "
            f"{r['orr_parked_mean']:.3f} / "
            f"{r['orr_moving_mean']:.3f} | {pct(r['factual_ego_cr'])} | "
            f"{sel['scenes_with_adversary_strict']} / {sel['scenes_with_paper_tier_candidate']} |"
        )
    loops = [r for r in results if "closed_loop" in r]
    if loops:
        lines += [
            "",
            "| source | closed-loop episodes | vehicle ORR (mean) | moving-vehicle ORR (mean) | "
            "episodes with a new vehicle-vehicle collision | of which one involves a plan | "
            "new collisions by movers | episodes with an adversary |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for r in loops:
            c = r["closed_loop"]
            lines.append(
                f"| {r['source']} | {c['episodes']} | {c['orr_mean']:.4f} | "
                f"{c['orr_moving_mean']:.4f} | {pct(c['episodes_with_new_vehicle_collision'])} | "
                f"{pct(c['episodes_with_new_collision_involving_a_plan'])} | "
                f"{', '.join(f'{k} {v}' for k, v in c['new_collision_movers'].items()) or '-'} | "
                f"{pct(c['episodes_with_adversary'])} |"
            )
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenarionet", action="append", default=[], metavar="NAME=DIR")
    ap.add_argument("--commonroad", action="append", default=[], metavar="NAME=DIR")
    ap.add_argument("--plots", type=int, default=0, help="plot the first K scenes per source")
    ap.add_argument("--closed-loop", type=int, default=0, metavar="K", help="closed loop on K")
    ap.add_argument("--model", default="default", help="world model directory (closed loop)")
    ap.add_argument(
        "--network-alone",
        action="store_true",
        help="closed loop without yielding, road keeping and lane keeping",
    )
    ap.add_argument("--min-seconds", type=float, default=0.0, help="only logs at least this long")
    ap.add_argument("--out", required=True, metavar="DIR")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = []
    sources = [("scenarionet", s) for s in args.scenarionet]
    sources += [("commonroad", s) for s in args.commonroad]
    for kind, spec in sources:
        name, _, path = spec.partition("=")
        scenes, times, skipped = load_source(kind, path)
        if args.min_seconds:
            long = [i for i, s in enumerate(scenes) if s.num_steps * s.dt >= args.min_seconds]
            skipped.update(
                {
                    scenes[i].scenario_id: "shorter than --min-seconds"
                    for i in range(len(scenes))
                    if i not in long
                }
            )
            scenes, times = [scenes[i] for i in long], [times[i] for i in long]
        results.append(summarise(name, scenes, times, skipped))
        if args.closed_loop:
            results[-1]["closed_loop"] = closed_loop(
                scenes[: args.closed_loop], args.model, args.network_alone
            )
        for scene in scenes[: args.plots]:
            plot_scene(scene, out / f"{name}_{scene.scenario_id.replace('/', '_')}.png")
        print(markdown(results[-1:]), flush=True)
    (out / "real_logs.json").write_text(json.dumps(results, indent=1, default=float) + "\n")
    (out / "real_logs.md").write_text(markdown(results))
    print(markdown(results))


if __name__ == "__main__":
    main()
