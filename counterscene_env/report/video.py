"""Videos of replayed episodes (``report.replay``), drawn with matplotlib frame by frame and
written as MP4 and GIF (``envs.render.save_video``: imageio, the ``video`` extra).

Each frame shows the road (drivable area and lane centre lines), every agent's box (the ego
green, red while it collides; the adversary purple; other traffic light blue), the ego's and
adversary's paths so far, the adversary's current plan (purple line), the conflict point
(red ring), the time since the episode's start, the ego's speed and acceleration, and the
step's collision and hard-braking flags. The camera is fixed on the ego's and adversary's
whole paths, so the frames line up.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import shapely
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure as MplFigure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch, PathPatch, Polygon
from matplotlib.path import Path as MplPath

from counterscene_env import geometry
from counterscene_env.envs.render import (
    ADVERSARY_COLOR,
    CONFLICT_COLOR,
    CRASHED_COLOR,
    EGO_COLOR,
    TRAFFIC_COLOR,
    save_video,
)
from counterscene_env.report.replay import Replay

#: Frame size, px (multiples of 16: the MP4 encoder's macro blocks).
WIDTH, HEIGHT = 640, 512
#: Frames per second (one frame per 0.1 s step: real time).
FPS = 10
#: Space around the ego's and adversary's paths, m; the view is at least MIN_SPAN wide.
MARGIN, MIN_SPAN = 15.0, 50.0
#: Fraction of the frame's height the map takes (the text lines sit above it).
MAP_HEIGHT = 0.9


def _rgb(color: tuple[int, int, int]) -> tuple[float, ...]:
    return tuple(c / 255 for c in color)


def _area_path(area: shapely.Geometry) -> MplPath | None:
    """The drivable area as one matplotlib path, holes included (a roundabout's island):
    exteriors counter-clockwise and holes clockwise, so the non-zero fill leaves holes."""
    polys = getattr(area, "geoms", [area])
    verts, codes = [], []
    for poly in polys:
        if poly.is_empty or not isinstance(poly, shapely.Polygon):
            continue
        poly = shapely.geometry.polygon.orient(poly, 1.0)
        for ring in (poly.exterior, *poly.interiors):
            xy = np.asarray(ring.coords)
            verts.append(xy)
            codes += [MplPath.MOVETO] + [MplPath.LINETO] * (len(xy) - 2) + [MplPath.CLOSEPOLY]
    return MplPath(np.concatenate(verts), codes) if verts else None


def _view(replay: Replay) -> tuple[float, float, float, float]:
    """``(xmin, xmax, ymin, ymax)`` m: the ego's and adversary's paths and the conflict
    point with a margin, stretched to the frame's aspect."""
    rows = [replay.ego] + ([replay.adversary] if replay.adversary is not None else [])
    pts = [f.positions[r] for f in replay.frames for r in rows if f.valid[r]]
    pts += [f.info["conflict_point"] for f in replay.frames if f.info.get("conflict_point")]
    pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
    lo, hi = pts.min(0) - MARGIN, pts.max(0) + MARGIN
    centre = (lo + hi) / 2
    aspect = HEIGHT * MAP_HEIGHT / WIDTH
    span = max(hi[0] - lo[0], (hi[1] - lo[1]) / aspect, MIN_SPAN)
    half = np.array([span, span * aspect]) / 2
    return centre[0] - half[0], centre[0] + half[0], centre[1] - half[1], centre[1] + half[1]


def frames(replay: Replay) -> Iterator[np.ndarray]:
    """The replay's frames, ``[HEIGHT, WIDTH, 3]`` uint8 each (module docstring)."""
    scene, rec = replay.scene, replay.record
    fig = MplFigure(figsize=(WIDTH / 100, HEIGHT / 100), dpi=100)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_axes((0.0, 0.0, 1.0, MAP_HEIGHT))
    ax.set_facecolor("#5a8f3d")  # grass: the road reads at a glance
    xmin, xmax, ymin, ymax = _view(replay)
    ax.set(xlim=(xmin, xmax), ylim=(ymin, ymax), aspect="equal", xticks=[], yticks=[])
    road = _area_path(scene.road.drivable_area)
    if road is not None:
        ax.add_patch(PathPatch(road, facecolor="#6b6b6b", edgecolor="#d0d0d0", lw=0.8))
    for line in scene.road.lane_centerlines:
        ax.plot(line[:, 0], line[:, 1], color="white", lw=0.5, ls=(0, (4, 6)), alpha=0.6)
    colors = [_rgb(TRAFFIC_COLOR)] * scene.num_agents
    if replay.adversary is not None:
        colors[replay.adversary] = _rgb(ADVERSARY_COLOR)
    boxes = [
        ax.add_patch(Polygon(np.zeros((4, 2)), closed=True, fc=c, ec="black", lw=0.6, zorder=3))
        for c in colors
    ]
    (ego_trail,) = ax.plot([], [], color=_rgb(EGO_COLOR), lw=1.5, alpha=0.7, zorder=2)
    (adv_trail,) = ax.plot([], [], color=_rgb(ADVERSARY_COLOR), lw=1.5, alpha=0.5, zorder=2)
    (plan_line,) = ax.plot([], [], color=_rgb(ADVERSARY_COLOR), lw=2.0, ls="--", zorder=4)
    conflict = ax.scatter(
        [], [], s=300, marker="o", facecolors="none", edgecolors=[_rgb(CONFLICT_COLOR)],
        linewidths=2.5, zorder=5,
    )  # fmt: skip
    adversary = "none" if replay.adversary is None else str(scene.agent_ids[replay.adversary])
    fig.text(
        0.01, 0.975,
        f"{scene.scenario_id} · episode {rec['episode']} · seed {rec['seed']} · adversary "
        f"{adversary} ({rec.get('adversary_type') or 'no conflict'})",
        va="center", fontsize=8,
    )  # fmt: skip
    clock = fig.text(0.01, 0.93, "", fontsize=10, va="center", family="monospace")
    flags = ax.text(
        0.99, 0.98, "", transform=ax.transAxes, ha="right", va="top", fontsize=12,
        color="white", weight="bold", zorder=6,
    )  # fmt: skip
    _legend(ax)
    for i, f in enumerate(replay.frames):
        corners = geometry.box_corners(f.positions, f.yaws, scene.extents)  # [N, 4, 2]
        for row, box in enumerate(boxes):
            box.set_visible(bool(f.valid[row]))
            box.set_xy(corners[row])
        hit = f.info.get("collision", False)
        boxes[replay.ego].set_facecolor(_rgb(CRASHED_COLOR if hit else EGO_COLOR))
        ego_path = np.array([g.positions[replay.ego] for g in replay.frames[: i + 1]])
        ego_trail.set_data(ego_path[:, 0], ego_path[:, 1])
        if replay.adversary is not None:
            a = replay.adversary
            path = np.array([g.positions[a] for g in replay.frames[: i + 1] if g.valid[a]])
            adv_trail.set_data(*(path.T if len(path) else ([], [])))
        plan = f.plan if f.plan is not None else np.zeros((0, 2))
        plan_line.set_data(plan[:, 0], plan[:, 1])
        point = f.info.get("conflict_point")
        conflict.set_offsets(np.reshape(point if point else np.zeros((0, 2)), (-1, 2)))
        clock.set_text(
            f"t = {f.time:4.1f} s   v = {f.info.get('ego_speed', np.nan):4.1f} m/s   "
            f"a = {f.info.get('ego_acceleration', np.nan):+5.1f} m/s²"
        )
        flags.set_text(_flag_text(f.info))
        flags.set_bbox(
            {"facecolor": "#cc3311", "alpha": 0.85} if flags.get_text() else {"alpha": 0.0}
        )
        canvas.draw()
        yield np.asarray(canvas.buffer_rgba())[..., :3].copy()


def _legend(ax) -> None:
    """What the colours mean, bottom left."""
    handles = [
        Patch(color=_rgb(EGO_COLOR), label="ego"),
        Patch(color=_rgb(CRASHED_COLOR), label="ego, colliding"),
        Patch(color=_rgb(ADVERSARY_COLOR), label="adversary"),
        Patch(color=_rgb(TRAFFIC_COLOR), label="traffic"),
        Line2D([], [], color=_rgb(ADVERSARY_COLOR), ls="--", label="adversary's plan"),
        Line2D(
            [],
            [],
            marker="o",
            ls="none",
            mfc="none",
            mec=_rgb(CONFLICT_COLOR),
            mew=2,
            label="conflict point",
        ),
    ]
    ax.legend(handles=handles, loc="lower left", fontsize=7, framealpha=0.85)


def _flag_text(info: dict) -> str:
    flags = []
    if info.get("collision"):
        who = info.get("collided_with")
        flags.append("COLLISION" + (f" with {who}" if who else ""))
    if info.get("hard_braking"):
        flags.append("HARD BRAKING")
    return "\n".join(flags)


def write_videos(replay: Replay, directory: Path, stem: str) -> dict[str, Path | str]:
    """``directory/stem.mp4`` and ``directory/stem.gif`` of a replay.

    Returns:
        ``{"mp4": path, "gif": path}`` for the files written; a format that could not be
        written (imageio-ffmpeg missing for MP4) maps to the reason instead.

    Raises:
        ImportError: imageio is not installed (``pip install "counterscene-env[video]"``).
    """
    images = list(frames(replay))
    out: dict[str, Path | str] = {}
    out["gif"] = save_video(images, directory / f"{stem}.gif", fps=FPS)
    try:
        out["mp4"] = save_video(images, directory / f"{stem}.mp4", fps=FPS)
    except ImportError as exc:  # imageio without imageio-ffmpeg: the GIF still stands
        out["mp4"] = str(exc)
    return out
