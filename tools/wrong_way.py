"""Wrong-way driving in the closed loop: how often the world model's traffic drives in the lane
of the oncoming traffic (docs/world_model_experiments.md, "Wrong-way driving").

A moving vehicle (over 1 m/s) is *wrong-way* at a step when its centre lies within 1 m of the
centre line of a lane whose direction is more than 135 degrees from its course, and more than
2 m from the centre line of every lane going its way (within 45 degrees). The tool runs the
unguided closed loop with the log replayed for the ego on stored scenes, and counts the
episodes in which a vehicle other than the ego is wrong-way for at least 1 s without a break,
and the share of moving vehicle-steps that are; the logs' own figures are given beside them
(0 on generated roads). It also sorts the collisions between two vehicles other than the ego
that the log does not have by how the two were heading at their first overlapping step:
head-on (courses over 150 degrees apart), the same way (under 30) or crossing, counts the
pairs in which a car is more than 2 m from every position of its own log at that step (it
took another path than the log, so the two met where the log never had them), and gives
per episode whether it had one (``per_episode``, to pair two runs on the same scenes):

    python tools/wrong_way.py data/eval-intersection [--episodes 50] [--set KEY=VALUE ...]

``--set`` takes closed-loop keys (JSON values), e.g. ``--set lane_steering=0 traffic_yields=false
road_keeping=false`` for the network alone. ``--withhold plan`` runs a model with
``plan_features="self"`` with its self-conditioning plan withheld (every denoising step is
told there is none); ``--withhold priority`` sets every lane's right of way to 0 (the lowest;
such a model has no value for "unknown") for a model with ``lane_priority``: whether the
network's closed loop depends on those inputs.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from counterscene_env.cli.common import parse_overrides
from counterscene_env.geometry import wrap_angle
from counterscene_env.metrics.common import rollout_slice, wilson_interval
from counterscene_env.metrics.safety import new_vehicle_collisions
from counterscene_env.planners import make_planner
from counterscene_env.scene.core import Scene
from counterscene_env.scene.sources import loaded_scenes
from counterscene_env.sim import ClosedLoop, SimConfig
from counterscene_env.stress import run_batch
from counterscene_env.world_model import features
from counterscene_env.world_model.checkpoint import load_model
from counterscene_env.world_model.model import WorldModel

MOVING = 1.0  # m/s
OWN_WAY = np.pi / 4  # rad: a lane within this of the course goes the car's way
OTHER_WAY = 3 * np.pi / 4  # rad: a lane beyond this goes against it
FAR_FROM_OWN = 2.0  # m from every centre line going its way
ON_OTHER = 1.0  # m from a centre line going against it, at most
MIN_STEPS = 10  # 1 s at 10 Hz: an episode counts when one vehicle is wrong-way this long


def longest_run(flags: np.ndarray) -> tuple[int, int]:
    """Length and first index of the longest run of True in ``flags [T]`` ((0, 0): none)."""
    best, start, run = (0, 0), 0, 0
    for t, f in enumerate(flags):
        run = run + 1 if f else 0
        if run == 1:
            start = t
        if run > best[0]:
            best = (run, start)
    return best


def _segments(scene: Scene) -> tuple[np.ndarray, ...]:
    """Every lane segment of the scene's map: starts, ends ``[S, 2]`` m and directions
    ``[S]`` rad."""
    a = np.concatenate([line[:-1] for line in scene.road.lane_centerlines])
    b = np.concatenate([line[1:] for line in scene.road.lane_centerlines])
    d = b - a
    return a, b, np.arctan2(d[:, 1], d[:, 0])


def wrong_way_steps(scene: Scene, rows: list[int], steps: slice) -> np.ndarray:
    """``[len(rows), T]`` bool: each vehicle of ``rows`` wrong-way at each step of ``steps``."""
    a, b, direction = _segments(scene)
    ab = b - a
    length2 = np.maximum((ab**2).sum(-1), 1e-9)
    pos, yaw, ok = scene.positions[:, steps], scene.yaws[:, steps], scene.valid[:, steps]
    speed = np.abs(scene.speeds[:, steps])
    out = np.zeros((len(rows), ok.shape[1]), bool)
    for i, r in enumerate(rows):
        moving = ok[r] & (speed[r] > MOVING)
        if not moving.any():
            continue
        p = pos[r, moving]  # [M, 2]
        u = np.clip(((p[:, None] - a) * ab).sum(-1) / length2, 0, 1)  # [M, S]
        dist = np.linalg.norm(p[:, None] - (a + u[..., None] * ab), axis=-1)
        turn = np.abs(wrap_angle(direction[None] - yaw[r, moving][:, None]))
        own = np.where(turn < OWN_WAY, dist, np.inf).min(-1)
        other = np.where(turn > OTHER_WAY, dist, np.inf).min(-1)
        out[i, moving] = (own > FAR_FROM_OWN) & (other < ON_OTHER)
    return out


OFF_PATH = 2.0  # m: a car this far from every logged position of its own took another path


def new_collision_kinds(sim: Scene, factual: Scene) -> list[tuple[str, bool]]:
    """Pairs of non-ego vehicles that overlap in ``sim``'s rollout but never in the log,
    each named by the angle between their courses at the first overlapping step, and whether
    one of the two is then more than ``OFF_PATH`` from every position of its own log."""
    sl = rollout_slice(sim)
    yaw, pos = sim.yaws[:, sl], sim.positions[:, sl]

    def off_path(r: int, t: int) -> bool:
        logged = factual.positions[r][factual.valid[r]]
        return not len(logged) or np.linalg.norm(logged - pos[r, t], axis=-1).min() > OFF_PATH

    kinds = []
    for a, b, t in new_vehicle_collisions(sim, factual):
        angle = abs(float(wrap_angle(yaw[a, t] - yaw[b, t])))
        kind = (
            "head-on" if angle > 5 * np.pi / 6 else "same way" if angle < np.pi / 6 else "crossing"
        )
        kinds.append((kind, bool(off_path(a, t) or off_path(b, t))))
    return kinds


def count(scenes: list[Scene]) -> dict:
    """Episodes with a vehicle wrong-way for ``MIN_STEPS`` or more, and the share of moving
    vehicle-steps wrong-way, over ``scenes`` (each a rollout or a log)."""
    episodes = steps = moving = 0
    turns = []  # course change [deg] over the 3 s before each wrong-way drive of MIN_STEPS
    for scene in scenes:
        sl = rollout_slice(scene)
        rows = [r for r in range(scene.num_agents) if r != scene.ego_index]
        rows = [r for r in rows if scene.vehicle_mask[r]]
        ww = wrong_way_steps(scene, rows, sl)
        drives = [longest_run(w) for w in ww]
        episodes += any(n >= MIN_STEPS for n, _ in drives)
        for r, (n, t0) in zip(rows, drives, strict=True):
            if n >= MIN_STEPS:  # the course over the 3 s (history included) before it began
                t = sl.start + t0
                change = wrap_angle(scene.yaws[r, t] - scene.yaws[r, max(t - 30, 0)])
                turns.append(round(float(np.degrees(change)), 1))
        steps += int(ww.sum())
        v = np.abs(scene.speeds[rows][:, sl])
        moving += int(((v > MOVING) & scene.valid[rows][:, sl]).sum())
    lo, hi = wilson_interval(episodes, len(scenes))
    return {
        "episodes": len(scenes),
        "episodes_wrong_way_1s": episodes,
        "episodes_wrong_way_1s_ci95": [lo, hi],
        "wrong_way_share_of_moving_steps": steps / max(moving, 1),
        "course_change_in_the_3_s_before_each_wrong_way_drive_deg": turns,
    }


def withhold(model: WorldModel, inputs: list[str]) -> WorldModel:
    """``model`` with the named inputs withheld at sampling (module docstring, ``--withhold``)."""
    if "plan" in inputs:
        if model.config.plan_features != "self":
            raise SystemExit("--withhold plan needs a model with plan_features='self'")
        denoise = model.denoise

        def no_plan(noisy, timesteps, ctx, state, valid, previous=None, given=None):
            return denoise(noisy, timesteps, ctx, state, valid, None, None)

        model.denoise = no_plan
    if "priority" in inputs:
        if not model.config.lane_priority:
            raise SystemExit("--withhold priority needs a model with lane_priority")
        lane_features = features.lane_features

        def no_priority(batch, priority=False):
            zero = torch.zeros_like(batch["map_priority"])
            return lane_features({**batch, "map_priority": zero}, priority)

        features.lane_features = no_priority  # this process only: a diagnosis run
    return model


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", help="stored scenes (a dataset directory or shard)")
    ap.add_argument("--episodes", type=int, default=50)
    ap.add_argument("--model", default="default")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE")
    ap.add_argument("--withhold", nargs="*", default=[], choices=["plan", "priority"])
    args = ap.parse_args()
    settings = parse_overrides(args.set)
    model = withhold(load_model(args.model), args.withhold)
    loop = ClosedLoop(model, SimConfig(**{"guidance": "none", **settings}))
    scenes = loaded_scenes(args.data)[: args.episodes]
    rollouts, logs, kinds, flags = [], [], [], []
    for i, scene in enumerate(scenes):
        run_batch(loop, [scene], [i], [make_planner("log")])
        rollouts.append(loop.scene(0))
        logs.append(scene.time_slice(0, rollouts[-1].num_steps))
        pairs = new_collision_kinds(rollouts[-1], logs[-1])
        kinds += pairs
        flags.append(int(bool(pairs)))
    hit = sum(flags)
    collisions = {
        "episodes_with_new_non_ego_collision": hit,
        "ci95": list(wilson_interval(hit, len(scenes))),
        "pairs": {
            k: sum(kind == k for kind, _ in kinds) for k in ("crossing", "same way", "head-on")
        },
        "pairs_with_a_car_off_its_logged_path": {
            k: sum(kind == k and off for kind, off in kinds)
            for k in ("crossing", "same way", "head-on")
        },
        # Per episode, in the order of the stored scenes: two runs on the same scenes pair up
        # (counterscene_env.report.stats.paired_rate).
        "per_episode": flags,
    }
    print(
        json.dumps(
            {
                "settings": settings,
                "withheld": args.withhold,
                "closed_loop": count(rollouts),
                "log": count(logs),
                "new_non_ego_collisions": collisions,
            }
        )
    )


if __name__ == "__main__":
    main()
