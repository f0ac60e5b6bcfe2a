"""Sample the world model's futures for one scene and plot them next to the log.

python examples/predict_scene.py intersection --seed 100000 --out prediction.png
python examples/predict_scene.py roundabout --model runs/wm --samples 6
"""

from __future__ import annotations

import argparse

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import torch
from torch.utils.data import default_collate

from counterscene_env.scene import SCENARIOS, generate
from counterscene_env.world_model import load_model
from counterscene_env.world_model.dataset import SceneWindowDataset


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("scenario", choices=SCENARIOS)
    parser.add_argument("--seed", type=int, default=100000)
    parser.add_argument("--model", default="default", help="model directory (default: shipped)")
    parser.add_argument("--samples", type=int, default=4)
    parser.add_argument("--out", default="prediction.png")
    args = parser.parse_args()

    model = load_model(args.model)
    scene = generate(args.scenario, args.seed)
    ds = SceneWindowDataset([scene], model.window_config())
    window = ds.window(0, scene.current_index)
    batch = default_collate([{k: torch.from_numpy(np.asarray(v)) for k, v in window.items()}])
    pred = model.sample(batch, args.samples, torch.Generator().manual_seed(0))

    # Everything is drawn in the ego frame at "now" (ego at the origin heading +x).
    fig, ax = plt.subplots(figsize=(8, 8))
    for lane, ok in zip(window["map"], window["map_valid"], strict=True):
        if ok:
            ax.plot(lane[:, 0], lane[:, 1], color="0.8", lw=6, solid_capstyle="round", zorder=0)
    valid = pred.valid[0].numpy()
    for k in np.flatnonzero(valid):
        colour = "tab:red" if k == 0 else "tab:blue"
        hist = window["history"][k][window["history_valid"][k]]
        ax.plot(hist[:, 0], hist[:, 1], color="k", lw=1)
        fut = window["future"][k][window["future_valid"][k]]
        ax.plot(fut[:, 0], fut[:, 1], color="k", lw=1, ls="--")
        for s in range(args.samples):
            xy = pred.trajectory[0, s, k, :, :2].numpy()
            ax.plot(xy[:, 0], xy[:, 1], color=colour, lw=1, alpha=0.6)
    ax.set_aspect("equal")
    ax.set_title(
        f"{args.scenario} seed {args.seed}: log (black, dashed = future), "
        f"{args.samples} samples (ego red)"
    )
    fig.savefig(args.out, dpi=120, bbox_inches="tight")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
