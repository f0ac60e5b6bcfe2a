"""The world model's input contract: fixed-size (history, future, map, validity) windows in
the ego frame.

Each item is one scene at one "now" step ``t0``: the ego and its ``num_agents - 1`` nearest
vehicles at ``t0`` (ego first, then by distance, zero-padded), their states over the
``history_steps`` frames ending at ``t0`` and the ``future_steps`` frames after it, and the
``num_lanes`` lane segments nearest the ego (``lane_anchors="ego"``) or nearest the places the
window's agents are and are heading to (``"agents"``). Everything is expressed in the
ego-centred frame (docs/design.md, "Ego-centred frame"): the ego at the origin, heading
along +x, at ``t0``.

Item keys (K agents, H history frames, F future frames, M lane segments of P points):

==================  ==================  =====================================================
key                 shape, dtype        meaning
==================  ==================  =====================================================
``history``         [K, H, 4] float32   x [m], y [m], yaw [rad, wrapped], speed [m/s]
``history_valid``   [K, H] bool
``future``          [K, F, 4] float32   as ``history``, frames ``t0 + 1 .. t0 + F``
``future_valid``    [K, F] bool
``extents``         [K, 2] float32      length, width [m]
``agent_valid``     [K] bool            real agent (True) or padding
``map``             [M, P, 2] float32   lane centre segments, x y [m], driving direction
``map_valid``       [M] bool
``map_widths``      [M] float32         lane width [m]
``map_priority``    [M] float32         the lane's right of way (``RoadMap.lane_priorities``:
                                        at a crossing the lower gives way; 0: none given)
``recorded``        [] float32          1: a recording of real driving, 0: highway-env's
                                        generated traffic (``Scene.generated``)
``origin``          [3] float64         world x [m], y [m], yaw [rad] of the frame
``scene_index``     [] int64            row of the scene in this dataset
``t0``              [] int64            the "now" step in that scene
``rows``            [K] int64           scene row of each window agent (-1: padding)
==================  ==================  =====================================================

Invalid entries (padding, frames where an agent is absent) are zero, never NaN.

The closed loop builds windows with :func:`make_window` and batches them with :func:`collate`;
training reads them through ``world_model.dataset.SceneWindowDataset``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch

from counterscene_env.config import LaneAnchors, check_fields, choice_field
from counterscene_env.geometry import arc_length, to_frame, wrap_angle
from counterscene_env.scene.core import Scene

#: Keys of a window that the model reads (``collate`` stacks these).
MODEL_KEYS = (
    "history",
    "history_valid",
    "extents",
    "agent_valid",
    "map",
    "map_valid",
    "map_widths",
    "map_priority",
    "recorded",
)


def check_batch(batch: dict[str, torch.Tensor]) -> None:
    """Raise unless ``batch`` holds the model's keys (:data:`MODEL_KEYS`) as batched tensors,
    floating ones in float32 (the model's dtype), and finite states where they are valid.

    Raises:
        ValueError: naming the key (a missing key, an unbatched window, float64 states, a
            NaN in a valid history frame).
    """
    missing = [k for k in MODEL_KEYS if k not in batch]
    if missing:
        raise ValueError(f"the batch lacks {missing} (windows from make_window, then collate)")
    if batch["history"].ndim != 4:
        raise ValueError(
            f"batch['history'] must be [B, K, H, 4], got shape {tuple(batch['history'].shape)}"
            " (an unbatched window? collate batches them)"
        )
    for key in MODEL_KEYS:
        if batch[key].is_floating_point() and batch[key].dtype != torch.float32:
            raise ValueError(f"batch[{key!r}] must be float32, got {batch[key].dtype}")
    if not torch.isfinite(batch["history"][batch["history_valid"]]).all():
        raise ValueError("batch['history'] has a NaN or inf in a valid frame")


@dataclass(frozen=True)
class WindowConfig:
    """Sizes of a training window.

    Attributes:
        history_steps: frames up to and including ``t0`` (paper: 31 = 3 s at 10 Hz).
        future_steps: frames after ``t0`` (paper: 52 = 5.2 s).
        num_agents: K, the ego plus its nearest vehicles.
        num_lanes: M lane segments nearest the anchors.
        lane_points: P points per lane segment.
        lane_segment_length: length of a lane segment, m.
        map_radius: segments farther than this from every anchor are left out, m.
        lane_anchors: where the map is centred. ``"ego"``: the segments nearest the ego.
            ``"agents"``: the segments nearest any window agent at ``t0`` or where constant
            velocity would take it at half and at the end of the horizon. With ``"ego"``, 30 %
            of the held-out highway, merge and roundabout agents' future positions lie more than
            0.5 m outside every window lane, so the model must guess the road of far agents;
            with ``"agents"`` and 48 segments it is 0-0.2 % (3.7 % in the roundabout).
        agent_radius: vehicles farther than this from the ego at ``t0`` are left out, m
            (``None``: no limit, only ``num_agents`` caps).
        stride: steps between consecutive ``t0`` of one scene.
    """

    history_steps: int = 31
    future_steps: int = 52
    num_agents: int = 16
    num_lanes: int = 32
    lane_points: int = 10
    lane_segment_length: float = 20.0
    map_radius: float = 60.0
    agent_radius: float | None = None
    stride: int = 10
    lane_anchors: str = choice_field(LaneAnchors, LaneAnchors.EGO)

    def __post_init__(self) -> None:
        check_fields(self)


def make_window(
    scene: Scene,
    t0: int,
    config: WindowConfig,
    segments: LaneSegments | None = None,
    include: Sequence[int] = (),
) -> dict[str, np.ndarray]:
    """One window (module docstring) of ``scene`` at step ``t0``.

    Args:
        scene: any scene; only frames ``t0 - history_steps + 1 .. t0 + future_steps`` are read
            (frames outside the log stay invalid).
        t0: the "now" step.
        config: window sizes.
        segments: ``lane_segments(scene, ...)`` when the caller already cut them (they depend
            only on the road, so a closed loop cuts them once per episode).
        include: agent rows that must be in the window whatever their distance (the closed
            loop keeps the adversary in); they follow the ego, before the nearest others.

    Returns:
        The item dict of the module docstring plus ``rows [K]`` int64: the scene row of each
        window agent (-1 for padding). ``scene_index`` is 0.
    """
    c = config
    K, H, F = c.num_agents, c.history_steps, c.future_steps
    origin = np.array([*scene.positions[scene.ego_index, t0], scene.yaws[scene.ego_index, t0]])
    nearest = scene.nearest_indices(scene.num_agents, t0, types=("vehicle",))
    if c.agent_radius is not None:
        dist = np.linalg.norm(scene.positions[nearest, t0] - origin[:2], axis=-1)
        nearest = nearest[dist <= c.agent_radius]  # the ego (distance 0) always stays
    forced = [int(i) for i in include if i != scene.ego_index and scene.valid[i, t0]]
    rest = [int(i) for i in nearest[1:] if int(i) not in forced]
    rows = np.array([scene.ego_index, *forced, *rest], dtype=np.int64)[:K]

    def to_ego(points: np.ndarray) -> np.ndarray:
        return to_frame(points, origin).astype(np.float32)

    def states(t_lo: int, t_hi: int) -> tuple[np.ndarray, np.ndarray]:
        out = np.zeros((K, t_hi - t_lo, 4), np.float32)
        ok = np.zeros((K, t_hi - t_lo), bool)
        # Frames outside the log stay invalid (zero) rather than being invented.
        lo, hi = max(t_lo, 0), min(t_hi, scene.num_steps)
        if lo >= hi:
            return out, ok
        sl = slice(lo - t_lo, hi - t_lo)
        ok[: len(rows), sl] = scene.valid[rows, lo:hi]
        xy = to_ego(scene.positions[rows, lo:hi])
        yaw = wrap_angle(scene.yaws[rows, lo:hi] - origin[2])
        out[: len(rows), sl] = np.concatenate(
            [xy, yaw[..., None], scene.speeds[rows, lo:hi, None]], -1
        )
        out[~ok] = 0.0
        return out, ok

    history, history_valid = states(t0 - H + 1, t0 + 1)
    future, future_valid = states(t0 + 1, t0 + 1 + F)
    extents = np.zeros((K, 2), np.float32)
    extents[: len(rows)] = scene.extents[rows]
    agent_valid = np.zeros(K, bool)
    agent_valid[: len(rows)] = True
    window_rows = np.full(K, -1, np.int64)
    window_rows[: len(rows)] = rows

    seg, widths, priorities = (
        segments
        if segments is not None
        else lane_segments(scene, c.lane_segment_length, c.lane_points)
    )
    lanes = np.zeros((c.num_lanes, c.lane_points, 2), np.float32)
    lane_valid = np.zeros(c.num_lanes, bool)
    lane_widths = np.zeros(c.num_lanes, np.float32)
    lane_priority = np.zeros(c.num_lanes, np.float32)
    if len(seg):
        anchors = origin[None, :2] if c.lane_anchors == "ego" else _anchors(scene, rows, t0, F)
        # distance of each segment to its nearest anchor [S]
        dist = np.linalg.norm(seg[:, None] - anchors[None, :, None], axis=-1).min(axis=(1, 2))
        near = np.flatnonzero(dist <= c.map_radius)
        near = near[np.argsort(dist[near], kind="stable")][: c.num_lanes]
        lanes[: len(near)] = to_ego(seg[near])
        lane_valid[: len(near)] = True
        lane_widths[: len(near)] = widths[near]
        lane_priority[: len(near)] = priorities[near]
    return {
        "history": history,
        "history_valid": history_valid,
        "future": future,
        "future_valid": future_valid,
        "extents": extents,
        "agent_valid": agent_valid,
        "map": lanes,
        "map_valid": lane_valid,
        "map_widths": lane_widths,
        "map_priority": lane_priority,
        "recorded": np.float32(not scene.generated),
        "origin": origin,
        "rows": window_rows,
        "scene_index": np.int64(0),
        "t0": np.int64(t0),
    }


def _anchors(scene: Scene, rows: np.ndarray, t0: int, future_steps: int) -> np.ndarray:
    """``[3 A, 2]`` m (world): each agent of ``rows`` valid at ``t0``, where it is and where
    constant velocity would take it after ``future_steps / 2`` and ``future_steps`` steps."""
    rows = rows[scene.valid[rows, t0]]
    pos, yaw = scene.positions[rows, t0], scene.yaws[rows, t0]
    reach = scene.speeds[rows, t0, None] * scene.dt * future_steps  # [A, 1] m
    heading = np.stack([np.cos(yaw), np.sin(yaw)], -1)
    return np.concatenate([pos, pos + 0.5 * reach * heading, pos + reach * heading])


class LaneSegments(NamedTuple):
    """A road's centre lines cut into pieces (:func:`lane_segments`), world frame."""

    points: np.ndarray  # [S, P, 2] m
    widths: np.ndarray  # [S] m
    priorities: np.ndarray  # [S], the lane's right of way (RoadMap.lane_priorities)


def lane_segments(scene: Scene, length: float, points: int) -> LaneSegments:
    """Cut every centre line into pieces of ``length`` m resampled to ``points`` points.

    A last piece shorter than ``length`` keeps its own length (points closer together), so no
    lane end is lost. Each piece keeps its lane's width and right of way.
    """
    road = scene.road
    segs, widths, priorities = [], [], []
    for line, width, priority in zip(
        road.lane_centerlines, road.lane_widths, road.lane_priorities, strict=True
    ):
        arc = arc_length(line)
        total = arc[-1]
        if total <= 1e-6:
            continue
        starts = np.arange(0.0, total, length)
        for a in starts:
            s = np.linspace(a, min(a + length, total), points)
            segs.append(
                np.stack([np.interp(s, arc, line[:, 0]), np.interp(s, arc, line[:, 1])], -1)
            )
            widths.append(width)
            priorities.append(priority)
    if not segs:
        return LaneSegments(np.zeros((0, points, 2)), np.zeros(0), np.zeros(0))
    return LaneSegments(np.stack(segs), np.asarray(widths), np.asarray(priorities))


#: Keys with an agent axis (axis 0 of a window).
_AGENT_KEYS = ("history", "history_valid", "extents", "agent_valid")


def collate(
    windows: Sequence[dict[str, np.ndarray]], trim: bool = False
) -> dict[str, torch.Tensor]:
    """Stack the model's keys (:data:`MODEL_KEYS`) of several windows into a batch
    (leading axis ``B``).

    ``trim``: cut the agent axis to the most agents any window holds (:func:`agent_count`),
    so the batch's ``K`` may be below the config's. Windows fill their slots from the front
    (``make_window``) and the model masks padding agents out of every attention, loss and
    choice, so the real agents' samples are those of the padded batch up to rounding, and the
    sampler's cost falls with ``K`` (a replan's window holds 3-8 of 12 agents at the
    generated intersection, docs/performance.md).
    """
    batch = {k: np.stack([w[k] for w in windows]) for k in MODEL_KEYS}
    if trim:
        k = max(agent_count(w) for w in windows)
        batch |= {key: np.ascontiguousarray(batch[key][:, :k]) for key in _AGENT_KEYS}
    return {key: torch.from_numpy(v) for key, v in batch.items()}


def agent_count(window: dict[str, np.ndarray]) -> int:
    """Agent slots a window fills (at least 1): its agent axis trimmed of trailing padding."""
    return max(int(np.flatnonzero(window["agent_valid"]).max(initial=0)) + 1, 1)
