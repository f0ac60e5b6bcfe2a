"""Plot a scene's bird's-eye view: drivable area, lanes, every trajectory, the ego in red.

python examples/plot_scene.py intersection --seed 1 --out scene.png
python examples/plot_scene.py path/to/scenario.pkl --out scene.png     # a ScenarioNet log
"""

from __future__ import annotations

import argparse

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from counterscene_env.geometry import box_corners
from counterscene_env.scene import SCENARIOS, generate, load_scenarionet


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("source", help=f"one of {SCENARIOS} or a ScenarioNet .pkl file")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="scene.png")
    args = parser.parse_args()
    scene = (
        generate(args.source, args.seed)
        if args.source in SCENARIOS
        else load_scenarionet(args.source)
    )

    fig, ax = plt.subplots(figsize=(8, 8))
    area = scene.road.drivable_area
    for poly in getattr(area, "geoms", [area]):
        ax.fill(*poly.exterior.xy, color="0.88", zorder=0)
        for hole in poly.interiors:
            ax.fill(*hole.xy, color="white", zorder=0)
    for line in scene.road.lane_centerlines:
        ax.plot(line[:, 0], line[:, 1], color="0.7", lw=0.5, zorder=1)
    t = scene.current_index
    for i in range(scene.num_agents):
        ego = i == scene.ego_index
        color = (
            "tab:red" if ego else ("tab:blue" if scene.agent_types[i] == "vehicle" else "tab:green")
        )
        v = scene.valid[i]
        ax.plot(
            scene.positions[i, v, 0],
            scene.positions[i, v, 1],
            color=color,
            lw=1.5 if ego else 0.8,
            zorder=2,
        )
        if scene.valid[i, t]:
            corners = box_corners(scene.positions[i, t], scene.yaws[i, t], scene.extents[i])
            ax.fill(corners[:, 0], corners[:, 1], color=color, zorder=3)
    x, y = scene.positions[scene.ego_index, t]
    ax.set_xlim(x - 70, x + 70)
    ax.set_ylim(y - 70, y + 70)
    ax.set_aspect("equal")
    ax.set_title(
        f"{scene.scenario_id}: {scene.num_agents} agents, boxes at t = {t * scene.dt:.1f} s"
    )
    fig.savefig(args.out, dpi=100, bbox_inches="tight")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
