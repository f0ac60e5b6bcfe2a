"""Where the world model moves cars that the log keeps still (docs/world_model.md).

An agent is *still* in a window when it is under 0.5 m/s at "now" and its logged position 3 s
later is within 0.1 m of where it is (``evaluate-model``'s "still" agents). For each, one
sample of the model's plan: how far it moves in 3 s and its accelerations. The split tells a
creep (every still car drifts a little) from a decision (a few are sent off), and the share
of all cars stopped now that drive off tells whether that decision is calibrated, for cars
stopped on a lane of the model's window (queued: the log may go) and off every lane (parked
at the kerb or in a lot):

    python tools/still_agents.py scenarionet:path/to/nuscenes_mini_scenarionet [--model DIR]
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from counterscene_env.scene.sources import stored_scenes
from counterscene_env.world_model.checkpoint import load_model
from counterscene_env.world_model.eval_windows import window_batches, window_jobs
from counterscene_env.world_model.evaluate import PARKED_SPEED, STILL_DISPLACEMENT
from counterscene_env.world_model.map_guidance import lane_excess

HORIZON = 30  # steps (3 s at 10 Hz)
DRIVES_OFF = 0.5  # m in 3 s: a still car sent off, not drifting
ON_LANE = 0.5  # m: a car this close to a window lane strip (or inside one) is on a lane


def stopped_agents(model, scenes, every: int, seed: int) -> dict[str, np.ndarray]:
    """Every agent-window stopped now (< ``PARKED_SPEED``) and valid 3 s later, one sample:
    ``logged`` and ``moved`` [m], how far the log and the sample take it in 3 s, ``on_lane``
    whether it stands on a window lane, and ``accel [n, H]`` m/s^2, the sample's
    accelerations."""
    jobs = window_jobs(scenes, model.config.history_steps, every, HORIZON)
    g = torch.Generator().manual_seed(seed)
    rows, accel = [], []
    for part, batch in window_batches(model, scenes, jobs):
        with torch.no_grad():
            pred = model.sample(batch, 1, g)
            state = model.current_state(batch)  # [B, K, 4] x, y, course, speed
            lanes = (batch["map"], batch["map_valid"], batch["map_widths"])
            off_lane = lane_excess(state[:, :, None, :2], *lanes)[..., 0].numpy()  # [B, K] m
            state = state.numpy()
        future, ok = batch["future"].numpy(), batch["future_valid"].numpy()
        for b in range(len(part)):
            for k in range(state.shape[1]):
                if not pred.valid[b, k] or abs(state[b, k, 3]) >= PARKED_SPEED:
                    continue
                if not ok[b, k, HORIZON - 1]:
                    continue
                here = state[b, k, :2]
                end = pred.trajectory[b, 0, k, HORIZON - 1, :2].numpy()
                logged = float(np.linalg.norm(future[b, k, HORIZON - 1, :2] - here))
                moved = float(np.linalg.norm(end - here))
                rows.append((logged, moved, off_lane[b, k] <= ON_LANE))
                accel.append(pred.actions[b, 0, k, :HORIZON, 0].numpy())
    r = np.array(rows, float).reshape(-1, 3)
    return {
        "logged": r[:, 0],
        "moved": r[:, 1],
        "on_lane": r[:, 2].astype(bool),
        "accel": np.array(accel).reshape(len(r), HORIZON),
    }


def report(s: dict[str, np.ndarray]) -> None:
    still = s["logged"] < STILL_DISPLACEMENT
    if not still.any():
        raise SystemExit("no still agents in this source")
    a, d, lane = s["accel"][still], s["moved"][still], s["on_lane"][still]
    off = d > DRIVES_OFF
    print(f"still agent-windows: {len(d)}")
    print(f"moved in 3 s: mean {d.mean():.3f} m, median {np.median(d):.3f} m")
    for name, m in (("on a lane", lane), ("off every lane", ~lane)):
        if m.any():
            print(f"  {name}: {m.sum()}, mean {d[m].mean():.3f} m, sent off {off[m].sum()}")
    print(f"accelerations: mean {a.mean():.3f} m/s^2, mean |a| {np.abs(a).mean():.3f} m/s^2")
    went_log, went_model = s["logged"] > DRIVES_OFF, s["moved"] > DRIVES_OFF
    for name, m in (
        ("", slice(None)),
        (" on a lane", s["on_lane"]),
        (" off every lane", ~s["on_lane"]),
    ):
        n = len(went_log[m])
        if n:
            print(
                f"of {n} agent-windows stopped now (< {PARKED_SPEED} m/s){name}, moved over "
                f"{DRIVES_OFF} m in 3 s: log {went_log[m].mean():.1%}, model {went_model[m].mean():.1%}"
            )
    print(
        f"sent off (> {DRIVES_OFF} m): {off.sum()} ({off.mean():.1%}), "
        f"{d[off].sum() / max(d.sum(), 1e-9):.0%} of the mean; "
        f"the others move {d[~off].mean() if (~off).any() else 0.0:.3f} m on average"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("source", help="scenario spec: scenarionet:DIR, commonroad:DIR or a dataset")
    ap.add_argument("--model", default=None, help="model directory (default: shipped)")
    ap.add_argument("--every", type=int, default=10, help="window start every N steps (10)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    model = load_model(args.model).eval()
    scenes = list(stored_scenes(args.source))
    report(stopped_agents(model, scenes, args.every, args.seed))


if __name__ == "__main__":
    main()
