"""The figures of the concept pages (docs/concepts/), made from the project itself.

    python docs/figures/make_figures.py            # writes the PNGs beside this file

Every figure shows the same generated intersection scene (the first safe highway-env seed from
``SCENE_SEED``, as ``counterscene stress --scenario intersection --seed SCENE_SEED`` draws it)
and uses the shipped default world model:

- ``world_model.png``: six samples of everyone's next 5.2 s from one sampling call, and one
  sample's predicted clean trajectory at each of the sampler's denoising steps;
- ``causal_selection.png``: the conflict mined for every candidate on the factual future, and
  which one the causal selector picks;
- ``counterfactual_guidance.png``: the same episode in closed loop, unguided and guided, with
  the IDM planner driving the ego, and the guidance's schedules m(p) and the arrival-time
  compression.

Deterministic: fixed scene and noise seeds, one torch thread; a rerun redraws the same figures.
It takes about 15 s on one core.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import torch

from counterscene_env.adversary.conflicts import (
    MIN_JOINT_STEPS,
    mine_conflicts,
    strict_gate_failures,
)
from counterscene_env.adversary.schedules import compressed_arrivals, stage_multiplier
from counterscene_env.adversary.selection import select_adversary
from counterscene_env.adversary.tracks import check_tracks
from counterscene_env.geometry import box_corners, from_frame
from counterscene_env.metrics import evaluate_scene
from counterscene_env.planners import IDMPlanner
from counterscene_env.scene.sources import scenes_for
from counterscene_env.sim import ClosedLoop, SimConfig
from counterscene_env.stress.batch import play_batch
from counterscene_env.world_model import load_model
from counterscene_env.world_model.window import collate, make_window

OUT = Path(__file__).resolve().parent
#: The scene: the first safe intersection seed from here (a held-out seed, as in the docs).
SCENE_SEED = 100016
#: Noise seed of the sampling call and of the closed-loop episode.
NOISE_SEED = 0
SAMPLES = 6
#: Half the side of the square drawn around the adversary's conflict point, m.
VIEW = 34.0
EGO, ADVERSARY, TRAFFIC = "tab:red", "tab:purple", "tab:blue"
DPI = 100


def causal_selection(scene):
    """The causal selection on the scene's factual future (as the closed loop's first)."""
    positions, valid, speeds, start = factual_future(scene)
    return select_adversary(
        "causal",
        positions,
        valid,
        scene.ego_index,
        speeds=speeds,
        extents=scene.extents,
        eligible=scene.agent_types == "vehicle",
        start_step=start,
    )


def view_centre(scene) -> np.ndarray:
    """``[2]`` m, world frame: the causal adversary's conflict point (the ego if none)."""
    selection = causal_selection(scene)
    if selection.conflict is None:
        return scene.positions[scene.ego_index, scene.current_index]
    return selection.conflict.conflict_point


def draw_road(ax, scene) -> None:
    """The drivable area (grey) and lane centre lines, around :func:`view_centre`."""
    centre = view_centre(scene)
    area = scene.road.drivable_area
    for poly in getattr(area, "geoms", [area]):
        ax.fill(*poly.exterior.xy, color="0.9", zorder=0, lw=0)
        for hole in poly.interiors:
            ax.fill(*hole.xy, color="white", zorder=0, lw=0)
    for line in scene.road.lane_centerlines:
        ax.plot(line[:, 0], line[:, 1], color="0.75", lw=0.5, zorder=1)
    ax.set_xlim(centre[0] - VIEW, centre[0] + VIEW)
    ax.set_ylim(centre[1] - VIEW, centre[1] + VIEW)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


def draw_box(ax, position, yaw, extent, color, alpha=1.0) -> None:
    corners = box_corners(np.asarray(position), np.asarray(yaw), np.asarray(extent))
    ax.fill(corners[:, 0], corners[:, 1], color=color, alpha=alpha, zorder=4, lw=0)


def save(fig, name: str) -> None:
    path = OUT / name
    # No "Software" entry: the bytes do not depend on the matplotlib version.
    fig.savefig(path, dpi=DPI, bbox_inches="tight", metadata={"Software": None})
    plt.close(fig)
    print(f"wrote {path.relative_to(Path.cwd()) if path.is_relative_to(Path.cwd()) else path}")


# ---------------------------------------------------------------------- world model
def sample_with_steps(model, window: dict):
    """One sampling call of ``SAMPLES`` samples; also the first sample's predicted clean
    actions at every denoising step, read through the guidance hook (which edits nothing)."""
    batch = collate([window])
    x0_steps = []

    def record(mean, sigma, t, x0):
        x0_steps.append(x0[0].detach().clone())
        return mean

    pred = model.sample(batch, SAMPLES, torch.Generator().manual_seed(NOISE_SEED), guidance=record)
    state = model.current_state(batch)[0]
    with torch.no_grad():
        steps = [model.rollout(x0, state)[..., :2].numpy() for x0 in x0_steps]
    return pred, steps


def world_model_figure(model, scene) -> None:
    t0 = scene.current_index
    window = make_window(scene, t0, model.window_config())
    pred, steps = sample_with_steps(model, window)
    origin, rows = window["origin"], window["rows"]
    agents = np.flatnonzero(pred.valid[0].numpy())
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 6))
    for ax in (ax1, ax2):
        draw_road(ax, scene)
    for k in agents:
        row = rows[k]
        colour = EGO if k == 0 else TRAFFIC
        past = scene.valid[row, : t0 + 1]
        ax1.plot(*scene.positions[row, : t0 + 1][past].T, color="k", lw=1.2, zorder=2)
        future = scene.valid[row, t0 + 1 : t0 + 53]
        log = scene.positions[row, t0 + 1 : t0 + 53][future]
        ax1.plot(*log.T, color="k", lw=1.2, ls=(0, (3, 2)), zorder=2)
        for s in range(SAMPLES):
            xy = from_frame(pred.trajectory[0, s, k, :, :2].numpy(), origin)
            ax1.plot(*xy.T, color=colour, lw=1, alpha=0.55, zorder=3)
        draw_box(ax1, scene.positions[row, t0], scene.yaws[row, t0], scene.extents[row], colour)
        draw_box(ax2, scene.positions[row, t0], scene.yaws[row, t0], scene.extents[row], colour)
        cmap = plt.get_cmap("viridis")
        for i, xy in enumerate(steps):
            world = from_frame(xy[k], origin)
            ax2.plot(*world.T, color=cmap(i / max(len(steps) - 1, 1)), lw=1.2, zorder=3)
        final = from_frame(pred.trajectory[0, 0, k, :, :2].numpy(), origin)
        ax2.plot(*final.T, color="k", lw=1.6, zorder=3)
    ax1.set_title(
        f"{SAMPLES} samples of the next 5.2 s (ego red)\n"
        "black: the log's history (solid) and future (dashed)"
    )
    ax2.set_title(
        f"sample 1 at each of the {len(steps)} denoising steps\n"
        "purple: first, yellow: last; black: final"
    )
    fig.suptitle(f"World model, {scene.scenario_id}, one sampling call at t = 3.0 s")
    save(fig, "world_model.png")


# ---------------------------------------------------------------------- causal selection
def factual_future(scene):
    """The inputs the closed loop mines on (``sim/adversaries.py``): the factual future after "now"."""
    lo = scene.current_index + 1
    return scene.positions[:, lo:], scene.valid[:, lo:], scene.speeds[:, lo:], lo


def candidate_label(scene, conflict, failures: list[str]) -> str:
    """``veh3 intersection, tier 1`` or ``..., tier 1, fails: late, far`` or ``..., no tier``."""
    status = "no tier" if conflict.tier is None else f"tier {conflict.tier}"
    if failures:
        status += ", fails: " + ", ".join(failures)
    return f"{scene.agent_ids[conflict.agent]} {conflict.subtype}, {status}"


def selection_figure(scene) -> None:
    positions, valid, speeds, start = factual_future(scene)
    vehicles = scene.agent_types == "vehicle"
    selection = causal_selection(scene)
    tracks = check_tracks(
        positions,
        valid,
        scene.ego_index,
        speeds=speeds,
        dt=scene.dt,
        min_joint_steps=MIN_JOINT_STEPS,
    )
    # The paper's tiers for every candidate; the strict gates are checked one by one below.
    conflicts = mine_conflicts(
        positions, valid, scene.ego_index, speeds=speeds, eligible=vehicles, start_step=start
    )
    chosen = selection.conflict
    t0 = scene.current_index
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 5.8))
    draw_road(ax1, scene)
    e = scene.ego_index
    ax1.plot(*positions[e][valid[e]].T, color=EGO, lw=2, zorder=3)
    draw_box(ax1, scene.positions[e, t0], scene.yaws[e, t0], scene.extents[e], EGO)
    bars = []
    for c in conflicts:
        failures = strict_gate_failures(tracks, c, start) if c.tier is not None else []
        strict_tier = None if failures else c.tier
        picked = chosen is not None and c.agent == chosen.agent
        colour = ADVERSARY if picked else ("tab:orange" if strict_tier else "0.55")
        a = c.agent
        ax1.plot(*positions[a][valid[a]].T, color=colour, lw=2 if picked else 1, zorder=3)
        draw_box(ax1, scene.positions[a, t0], scene.yaws[a, t0], scene.extents[a], colour)
        bars.append((c.score, candidate_label(scene, c, failures), colour))
    if chosen is not None:
        pe = positions[e, chosen.ego_step - start]
        pa = positions[chosen.agent, chosen.adversary_step - start]
        ax1.plot(*np.stack([pe, pa]).T, color="k", ls=":", lw=1.2, zorder=5)
        ax1.scatter(*pe, color=EGO, edgecolor="k", s=40, zorder=6, label="ego at $\\tau_e$")
        ax1.scatter(
            *pa, color=ADVERSARY, edgecolor="k", s=40, zorder=6, label="adversary at $\\tau_a$"
        )
        ax1.scatter(
            *chosen.conflict_point,
            facecolor="none",
            edgecolor="red",
            s=160,
            lw=2,
            zorder=6,
            label="conflict point c",
        )
        ax1.legend(loc="lower left")
        ax1.set_title(
            f"logged 10 s; adversary {scene.agent_ids[chosen.agent]} ({chosen.subtype})\n"
            f"$d_{{min}}$ {chosen.min_distance:.1f} m, gap {chosen.arrival_gap:.1f} s, "
            f"$v_{{rel}}$ {chosen.relative_speed:.1f} m/s"
        )
    bars.sort(key=lambda b: b[0])
    top = max(b[0] for b in bars)
    for y, (score, label, colour) in enumerate(bars):
        ax2.barh(y, score, color=colour)
        ax2.text(score + 0.02 * top, y, label, va="center", fontsize=9.5)
    ax2.set_xlim(0, 2.1 * top)
    ax2.set_yticks([])
    ax2.axvline(0.05, color="k", lw=0.8, ls="--")
    ax2.set_xlabel("danger score s [m/s² for intersections]")
    ax2.set_title(
        "every candidate: purple chosen, orange tiered,\ngrey no tier or a failed strict gate"
    )
    fig.suptitle(f"Causal adversary selection, {scene.scenario_id} at t = 3.0 s")
    fig.tight_layout()
    save(fig, "causal_selection.png")


# ---------------------------------------------------------------------- guidance
def run_closed_loop(model, scene, guidance: str):
    """One closed-loop episode, the IDM planner driving the ego: the simulated scene, the
    adversary's conflict and the episode's metrics (as ``counterscene stress`` records them)."""
    loop = ClosedLoop(model, SimConfig(guidance=guidance))
    play_batch(loop, [scene], [NOISE_SEED], [IDMPlanner()])
    sim, conflict = loop.scene(0), loop.episodes[0].conflict
    factual = scene.time_slice(0, sim.num_steps)
    return sim, conflict, evaluate_scene(sim, factual, adversary=conflict.agent)


def schedule_panel(ax) -> None:
    p = np.linspace(0, 1, 201)
    ax.plot(p, [stage_multiplier(q) for q in p], color="k", label="m(p), stage multiplier")
    gap = [compressed_arrivals(0.0, 1.0, q)[1] for q in p]
    ax.plot(p, gap, color="tab:green", label="target gap / mined gap")
    ax.set_xlabel("progress p over the denoising steps, 1 - t/K")
    ax.legend(loc="upper left")
    ax.set_title("schedules of the guidance")
    ax.grid(alpha=0.3)


def guidance_figure(model, scene) -> None:
    runs = {g: run_closed_loop(model, scene, g) for g in ("none", "full")}
    conflict = runs["full"][1]
    a, e, t0 = conflict.agent, scene.ego_index, scene.current_index
    fig = plt.figure(figsize=(11, 7))
    grid = fig.add_gridspec(2, 2, width_ratios=(1.25, 1))
    ax1 = fig.add_subplot(grid[:, 0])
    ax2, ax3 = fig.add_subplot(grid[0, 1]), fig.add_subplot(grid[1, 1])
    draw_road(ax1, scene)
    styles = {"none": dict(ls=(0, (3, 2)), alpha=0.8), "full": dict(ls="-", alpha=1.0)}
    for g, (sim, _, scores) in runs.items():
        ok = sim.valid[e] & sim.valid[a]
        dist = np.linalg.norm(sim.positions[e] - sim.positions[a], axis=-1)
        dist = np.where(ok, dist, np.nan)[t0:]
        closest = t0 + int(np.nanargmin(dist))
        for row, colour in ((e, EGO), (a, ADVERSARY)):
            path = sim.positions[row, t0:][sim.valid[row, t0:]]
            ax1.plot(*path.T, color=colour, lw=1.8, zorder=3, **styles[g])
            draw_box(
                ax1,
                sim.positions[row, closest],
                sim.yaws[row, closest],
                sim.extents[row],
                colour,
                alpha=0.35 if g == "none" else 0.9,
            )
        seconds = np.arange(len(dist)) * sim.dt
        label = (
            f"{g}: closest {np.nanmin(dist):.1f} m,\n  box clearance "
            f"{scores['min_clearance_adversary']:.1f} m"
            + (" (collision)" if scores["cr_ego_adversary"] > 0 else "")
        )
        ax2.plot(seconds, dist, color="k", lw=1.5, label=label, **styles[g])
    ax1.scatter(*conflict.conflict_point, facecolor="none", edgecolor="red", s=160, lw=2, zorder=6)
    ax1.set_title(
        "ego (red, IDM) and adversary (purple), 10 s\n"
        "dashed: unguided, solid: guided; boxes at closest"
    )
    ax2.set_xlabel("time after t = 3.0 s [s]")
    ax2.set_ylabel("ego-adversary distance [m]")
    ax2.legend(loc="upper left", title="guidance")
    ax2.set_ylim(0, 1.45 * ax2.get_ylim()[1])  # room for the legend
    ax2.grid(alpha=0.3)
    ax2.set_title("same scene, same noise seed")
    schedule_panel(ax3)
    fig.suptitle(f"Counterfactual guidance, {scene.scenario_id}")
    fig.tight_layout()
    save(fig, "counterfactual_guidance.png")


def main() -> None:
    torch.set_num_threads(1)
    plt.rcParams.update({"font.size": 11, "axes.titlesize": 11, "legend.fontsize": 9.5})
    model = load_model()
    scene = next(scenes_for("intersection", 1, SCENE_SEED))
    world_model_figure(model, scene)
    selection_figure(scene)
    guidance_figure(model, scene)


if __name__ == "__main__":
    main()
