"""Training scenes from the network's own closed-loop states, highway-env's traffic driving
the future from there (a DAgger-style prototype; docs/world_model_experiments.md, "The network's
crossing collisions").

About three quarters of the network alone's collisions at the generated intersections are
meetings the log never had: a car left its logged path. No recorded window holds such a
meeting, so the training loss never says how to get out of one. This tool runs the network
alone (unguided, log-replay ego, no reflexes, no lane keeping) on stored generated
intersections and, at a few steps of each rollout, hands every vehicle to highway-env's IDM
traffic (its intersection road, which gives way by lane priority) for 5.2 s. Each branch
becomes a scene: 3 s of the network's history, then highway-env's answer. Each car keeps the
destination of its own log. Branches in which two boxes overlap (at the branch step or in
highway-env's answer) are dropped:

    python tools/closed_loop_data.py data/intersection --scenes 200 --out data/cl-intersection.npz
"""

from __future__ import annotations

import argparse

import numpy as np

from counterscene_env.geometry import overlaps_over_time, wrap_angle
from counterscene_env.planners import make_planner
from counterscene_env.scene.core import DEFAULT_DT, Scene
from counterscene_env.scene.handover import drive_on
from counterscene_env.scene.shards import save_scenes
from counterscene_env.scene.sources import loaded_scenes
from counterscene_env.sim import ClosedLoop, SimConfig
from counterscene_env.stress import run_batch
from counterscene_env.world_model.checkpoint import load_model

BRANCHES = (10, 25, 40)  # steps after "now" at which the rollout is handed to highway-env
#: m/s: the IDM's desired speed is the fastest of the car's log, at least this.
MIN_TARGET_SPEED = 5.0


def destination(scene: Scene, row: int) -> str | None:
    """The end node of the lane where ``row``'s log ends (its route's destination)."""
    ok = np.flatnonzero(scene.valid[row])
    if not ok.size:
        return None
    k = ok[-1]
    lane = scene.road.network.get_closest_lane_index(scene.positions[row, k], scene.yaws[row, k])
    return lane[1]


def branch(sim: Scene, log: Scene, t: int, history: int, future: int) -> Scene | None:
    """The scene of one branch at step ``t`` of ``sim`` (module docstring), or None."""
    rows = np.flatnonzero(sim.valid[:, t] & (sim.agent_types == "vehicle"))
    if sim.ego_index not in rows or t - history + 1 < 0:
        return None
    target = [max(log.speeds[r][log.valid[r]].max(initial=0.0), MIN_TARGET_SPEED) for r in rows]
    state, valid = drive_on(
        sim.positions[rows, t],
        sim.yaws[rows, t],
        sim.speeds[rows, t],
        np.array(target),
        [destination(log, int(r)) for r in rows],
        future,
    )
    h = slice(t - history + 1, t + 1)
    positions = np.concatenate([sim.positions[rows, h], state[..., :2]], axis=1)
    yaws = np.concatenate([sim.yaws[rows, h], wrap_angle(state[..., 2])], axis=1)
    speeds = np.concatenate([sim.speeds[rows, h], state[..., 3]], axis=1)
    ok = np.concatenate([sim.valid[rows, h], valid], axis=1)
    extents = sim.extents[rows]
    if overlaps_over_time(
        positions[:, history - 1 :], yaws[:, history - 1 :], extents, ok[:, history - 1 :]
    ).any():
        return None
    return Scene(
        positions=positions,
        yaws=yaws,
        speeds=speeds,
        extents=extents,
        valid=ok,
        agent_types=sim.agent_types[rows],
        agent_ids=sim.agent_ids[rows],
        ego_index=int(np.flatnonzero(rows == sim.ego_index)[0]),
        road=log.road,
        dt=DEFAULT_DT,
        scenario_id=f"{log.scenario_id}/closed-loop-branch={t}",
        current_index=history - 1,
        metadata={**log.metadata, "source": "closed-loop branch", "branch_step": int(t)},
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", help="stored generated intersections (training seeds)")
    ap.add_argument("--scenes", type=int, default=200)
    ap.add_argument("--model", default="default")
    ap.add_argument("--out", required=True, help="shard file to write (.npz)")
    args = ap.parse_args()
    model = load_model(args.model)
    config = SimConfig(guidance="none", traffic_yields=False, road_keeping=False, lane_steering=0)
    loop = ClosedLoop(model, config)
    H, F = model.config.history_steps, model.config.future_steps
    out, tried = [], 0
    for i, log in enumerate(loaded_scenes(args.data)[: args.scenes]):
        run_batch(loop, [log], [i], [make_planner("log")])
        sim = loop.scene(0)
        for step in BRANCHES:
            t = sim.current_index + step
            if t < sim.num_steps:
                tried += 1
                scene = branch(sim, log, t, H, F)
                if scene is not None:
                    out.append(scene)
    save_scenes(out, args.out)
    print(f"{len(out)} branch scenes of {tried} tried -> {args.out}")


if __name__ == "__main__":
    main()
