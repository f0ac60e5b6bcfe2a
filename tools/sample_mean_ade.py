"""Bias or spread? ADE over 0-3 s of one sample, of the mean of S samples and of the best of S,
against constant velocity (docs/history/world_model.md, "Real driving").

If the model's samples were centred on the truth and only spread too wide, the mean of the
samples would beat constant velocity while one sample did not; if the mean loses too, the
model's central guess is off (bias), not only its spread:

    python tools/sample_mean_ade.py scenarionet:path/to/nuscenes_mini_scenarionet [--model DIR]
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from counterscene_env.scene.sources import stored_scenes
from counterscene_env.world_model.checkpoint import load_model
from counterscene_env.world_model.eval_windows import window_batches, window_jobs
from counterscene_env.world_model.evaluate import constant_velocity

HORIZON = 30  # steps (3 s at 10 Hz)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("source", help="scenario spec: scenarionet:DIR, commonroad:DIR or a dataset")
    ap.add_argument("--model", default=None, help="model directory (default: shipped)")
    ap.add_argument("--samples", type=int, default=6)
    ap.add_argument("--every", type=int, default=10, help="window start every N steps (10)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    model = load_model(args.model).eval()
    scenes = list(stored_scenes(args.source))
    jobs = window_jobs(scenes, model.config.history_steps, args.every, HORIZON)
    g = torch.Generator().manual_seed(args.seed)
    rows: dict[str, list[float]] = {"one": [], "mean": [], "best": [], "cv": [], "spread": []}
    for part, batch in window_batches(model, scenes, jobs):
        with torch.no_grad():
            pred = model.sample(batch, args.samples, g)
            state = model.current_state(batch).numpy()
        xy = pred.trajectory[..., :HORIZON, :2].numpy()  # [B, S, K, H, 2]
        future = batch["future"].numpy()[..., :HORIZON, :2]
        ok_all = batch["future_valid"].numpy()[..., :HORIZON]
        cv = constant_velocity(state, HORIZON, model.config.dt)  # [B, K, H, 2]
        for b in range(len(part)):
            for k in range(state.shape[1]):
                ok = ok_all[b, k]
                if not pred.valid[b, k] or not ok.any():
                    continue
                samples, truth = xy[b, :, k][:, ok], future[b, k][ok]  # [S, n, 2], [n, 2]
                err = np.linalg.norm(samples - truth, axis=-1).mean(-1)  # [S]
                centre = samples.mean(0)
                rows["one"].append(err[0])
                rows["best"].append(err.min())
                rows["mean"].append(np.linalg.norm(centre - truth, axis=-1).mean())
                rows["cv"].append(np.linalg.norm(cv[b, k][ok] - truth, axis=-1).mean())
                rows["spread"].append(np.linalg.norm(samples - centre, axis=-1).mean())
    r = {key: float(np.mean(v)) for key, v in rows.items()}
    s = args.samples
    print(f"{len(rows['one'])} agent-windows, ADE over 0-3 s:")
    print(f"  one sample      {r['one']:.3f} m  ({r['one'] / r['cv']:.2f}x constant velocity)")
    print(f"  mean of {s}       {r['mean']:.3f} m  ({r['mean'] / r['cv']:.2f}x)")
    print(f"  best of {s}       {r['best']:.3f} m  ({r['best'] / r['cv']:.2f}x)")
    print(f"  constant vel.   {r['cv']:.3f} m")
    print(f"  samples' spread about their mean {r['spread']:.3f} m")


if __name__ == "__main__":
    main()
