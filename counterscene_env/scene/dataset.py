"""Training windows: fixed-size (history, future, map, validity) tensors in the ego frame.

Each item is one scene at one "now" step ``t0``: the ego and its ``num_agents - 1`` nearest
vehicles at ``t0`` (ego first, then by distance, zero-padded), their states over the
``history_steps`` frames ending at ``t0`` and the ``future_steps`` frames after it, and the
``num_lanes`` lane segments nearest the ego (``lane_anchors="ego"``) or nearest the places the
window's agents are and are heading to (``"agents"``). Everything is expressed in the
ego-centred frame of DESIGN 3.1: the ego at the origin, heading along +x, at ``t0``.

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
``origin``          [3] float64         world x [m], y [m], yaw [rad] of the frame
``scene_index``     [] int64            row of the scene in this dataset
``t0``              [] int64            the "now" step in that scene
``rows``            [K] int64           scene row of each window agent (-1: padding)
==================  ==================  =====================================================

Invalid entries (padding, frames where an agent is absent) are zero, never NaN.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from counterscene_env.geometry import arc_length
from counterscene_env.scene.core import Scene
from counterscene_env.scene.datagen import MANIFEST, shard_paths
from counterscene_env.scene.shards import load_scenes

LANE_ANCHORS = ("ego", "agents")


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
    lane_anchors: str = "ego"

    def __post_init__(self) -> None:
        if self.lane_anchors not in LANE_ANCHORS:
            raise ValueError(
                f"lane_anchors must be one of {LANE_ANCHORS}, got {self.lane_anchors!r}"
            )


class SceneWindowDataset(Dataset):
    """Windows over scenes from shard files or dataset directories (see module docstring).

    Args:
        sources: dataset directories (with ``manifest.json``), shard files, or ``Scene`` objects.
        config: window sizes.

    Windows are all ``t0`` in ``[history_steps - 1, T - future_steps - 1]`` (step ``stride``)
    at which the ego is valid.
    """

    def __init__(
        self,
        sources: Sequence[str | os.PathLike | Scene] | str | os.PathLike,
        config: WindowConfig | None = None,
    ) -> None:
        self.config = config or WindowConfig()
        self.scenes: list[Scene] = load_sources(sources)
        c = self.config
        self._segments = [
            lane_segments(s, c.lane_segment_length, c.lane_points) for s in self.scenes
        ]
        self.index: list[tuple[int, int]] = []
        for i, s in enumerate(self.scenes):
            first, last = c.history_steps - 1, s.num_steps - c.future_steps - 1
            self.index += [
                (i, t) for t in range(first, last + 1, c.stride) if s.valid[s.ego_index, t]
            ]

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, item: int) -> dict[str, torch.Tensor]:
        i, t0 = self.index[item]
        return {k: torch.from_numpy(np.asarray(v)) for k, v in self.window(i, t0).items()}

    def window(self, scene_index: int, t0: int) -> dict[str, np.ndarray]:
        """The window of one scene at one step, as numpy arrays (see the module docstring)."""
        window = make_window(self.scenes[scene_index], t0, self.config, self._segments[scene_index])
        window["scene_index"] = np.int64(scene_index)
        return window


def make_window(
    scene: Scene,
    t0: int,
    config: WindowConfig,
    segments: tuple[np.ndarray, np.ndarray] | None = None,
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
    to_ego = _frame_transform(origin)

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
        yaw = _wrap(scene.yaws[rows, lo:hi] - origin[2])
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

    seg, widths = (
        segments
        if segments is not None
        else lane_segments(scene, c.lane_segment_length, c.lane_points)
    )
    lanes = np.zeros((c.num_lanes, c.lane_points, 2), np.float32)
    lane_valid = np.zeros(c.num_lanes, bool)
    lane_widths = np.zeros(c.num_lanes, np.float32)
    if len(seg):
        anchors = origin[None, :2] if c.lane_anchors == "ego" else _anchors(scene, rows, t0, F)
        # distance of each segment to its nearest anchor [S]
        dist = np.linalg.norm(seg[:, None] - anchors[None, :, None], axis=-1).min(axis=(1, 2))
        near = np.flatnonzero(dist <= c.map_radius)
        near = near[np.argsort(dist[near], kind="stable")][: c.num_lanes]
        lanes[: len(near)] = to_ego(seg[near])
        lane_valid[: len(near)] = True
        lane_widths[: len(near)] = widths[near]
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


def load_sources(
    sources: Sequence[str | os.PathLike | Scene] | str | os.PathLike,
) -> list[Scene]:
    """Scenes from dataset directories (with ``manifest.json``), shard files or ``Scene``s."""
    if isinstance(sources, (str, os.PathLike)):
        sources = [sources]
    scenes: list[Scene] = []
    for src in sources:
        if isinstance(src, Scene):
            scenes.append(src)
        elif (Path(src) / MANIFEST).is_file():
            for shard in shard_paths(src):
                scenes.extend(load_scenes(shard))
        else:
            scenes.extend(load_scenes(src))
    return scenes


def _frame_transform(origin: np.ndarray):
    """World -> ego frame: translate by -origin[:2], rotate by -origin[2]."""
    c, s = np.cos(origin[2]), np.sin(origin[2])
    rot = np.array([[c, -s], [s, c]])  # columns: ego x and y axes in world coordinates

    def apply(points: np.ndarray) -> np.ndarray:
        return ((points - origin[:2]) @ rot).astype(np.float32)

    return apply


def lane_segments(scene: Scene, length: float, points: int) -> tuple[np.ndarray, np.ndarray]:
    """Cut every centre line into pieces of ``length`` m resampled to ``points`` points.

    Returns ``[S, points, 2]`` m (world frame) and ``[S]`` widths m. A last piece shorter than
    ``length`` keeps its own length (points closer together), so no lane end is lost.
    """
    segs, widths = [], []
    for line, width in zip(scene.road.lane_centerlines, scene.road.lane_widths, strict=True):
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
    if not segs:
        return np.zeros((0, points, 2)), np.zeros(0)
    return np.stack(segs), np.asarray(widths)


def _wrap(angle: np.ndarray) -> np.ndarray:
    return (angle + np.pi) % (2 * np.pi) - np.pi
