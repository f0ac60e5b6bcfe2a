"""Where the world model moves cars that the log keeps still (docs/world_model.md).

An agent is *still* in a window when it is under 0.5 m/s at "now" and its logged position 3 s
later is within 0.1 m of where it is (``evaluate-model``'s "still" agents). For each, one
sample of the model's plan: how far it moves in 3 s and its accelerations. The split tells a
creep (every still car drifts a little) from a decision (a few are sent off), and the share
of all cars stopped now that drive off tells whether that decision is calibrated:

    python tools/still_agents.py scenarionet:path/to/nuscenes_mini_scenarionet [--model DIR]
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from counterscene_env.scene.sources import stored_scenes
from counterscene_env.world_model.checkpoint import load_model
from counterscene_env.world_model.evaluate import (
    PARKED_SPEED,
    STILL_DISPLACEMENT,
    window_batches,
    window_jobs,
)

HORIZON = 30  # steps (3 s at 10 Hz)
DRIVES_OFF = 0.5  # m in 3 s: a still car sent off, not drifting


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("source", help="scenario spec: scenarionet:DIR, commonroad:DIR or a dataset")
    ap.add_argument("--model", default=None, help="model directory (default: shipped)")
    ap.add_argument("--every", type=int, default=10, help="window start every N steps (10)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    model = load_model(args.model).eval()
    scenes = list(stored_scenes(args.source))
    jobs = window_jobs(scenes, model.config.history_steps, args.every, HORIZON)
    g = torch.Generator().manual_seed(args.seed)
    accel, moved, stopped = [], [], []
    for part, batch in window_batches(model, scenes, jobs):
        with torch.no_grad():
            pred = model.sample(batch, 1, g)
            state = model.current_state(batch).numpy()  # [B, K, 4] x, y, course, speed
        future, ok = batch["future"].numpy(), batch["future_valid"].numpy()
        for b in range(len(part)):
            for k in range(state.shape[1]):
                here = state[b, k, :2]
                if not pred.valid[b, k] or abs(state[b, k, 3]) >= PARKED_SPEED:
                    continue
                if not ok[b, k, HORIZON - 1]:
                    continue
                end = pred.trajectory[b, 0, k, HORIZON - 1, :2].numpy()
                logged = float(np.linalg.norm(future[b, k, HORIZON - 1, :2] - here))
                stopped.append(
                    (logged > DRIVES_OFF, float(np.linalg.norm(end - here)) > DRIVES_OFF)
                )
                if logged >= STILL_DISPLACEMENT:
                    continue
                accel.append(pred.actions[b, 0, k, :HORIZON, 0].numpy())
                moved.append(float(np.linalg.norm(end - here)))
    if not moved:
        raise SystemExit("no still agents in this source")
    a, d = np.array(accel), np.array(moved)
    off = d > DRIVES_OFF
    print(f"still agent-windows: {len(d)}")
    print(f"moved in 3 s: mean {d.mean():.3f} m, median {np.median(d):.3f} m")
    print(f"accelerations: mean {a.mean():.3f} m/s^2, mean |a| {np.abs(a).mean():.3f} m/s^2")
    went = np.array(stopped)  # [n, 2]: (the log went, the model went) per stopped agent
    print(
        f"of {len(went)} agent-windows stopped now (< {PARKED_SPEED} m/s), moved over "
        f"{DRIVES_OFF} m in 3 s: log {went[:, 0].mean():.1%}, model {went[:, 1].mean():.1%}"
    )
    print(
        f"sent off (> {DRIVES_OFF} m): {off.sum()} ({off.mean():.1%}), "
        f"{d[off].sum() / max(d.sum(), 1e-9):.0%} of the mean; "
        f"the others move {d[~off].mean() if (~off).any() else 0.0:.3f} m on average"
    )


if __name__ == "__main__":
    main()
