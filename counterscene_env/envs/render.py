"""Bird's-eye frames of a CounterScene episode, and video export.

Frames are drawn by highway-env's own viewer (``EnvViewer``: the road network, every vehicle as
an oriented box) with the CounterScene layer on top: the egos in green (red once crashed), the
adversary in purple, other world-model traffic in light blue, the adversary's current planned
path as a purple polyline, and the conflict point as a red ring. ``render_mode="rgb_array"``
returns ``[H, W, 3]`` uint8 (``screen_height`` x ``screen_width``, multiples of 16).

:class:`CounterSceneViewer` reads the env through the small :class:`Viewable` interface (it
never imports an env class). :func:`save_video` writes frames to mp4 or gif with imageio (the
``video`` extra).
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import gymnasium as gym
import numpy as np
import pygame
from highway_env.envs.common.graphics import EnvViewer
from highway_env.vehicle.graphics import VehicleGraphics
from highway_env.vehicle.kinematics import Vehicle

from counterscene_env.config import check_real
from counterscene_env.sim.state import Episode

EGO_COLOR = VehicleGraphics.EGO_COLOR
CRASHED_COLOR = VehicleGraphics.RED
PLAN_COLOR = ADVERSARY_COLOR = (200, 40, 220)
TRAFFIC_COLOR = (100, 200, 255)
CONFLICT_COLOR = (230, 30, 30)


@dataclass(frozen=True)
class EpisodeView:
    """What the CounterScene layer draws on top of highway-env's frame.

    Attributes:
        ego_hit: per ego, whether it is crashed or collided in the last policy step.
        adversaries: scene rows of the egos' adversaries.
        targets: per ego with an adversary, the adversary's remaining plan ``[F', 2]`` m (None:
            not planned yet) and the conflict point ``[2]`` m.
    """

    ego_hit: tuple[bool, ...]
    adversaries: frozenset[int]
    targets: tuple[tuple[np.ndarray | None, np.ndarray], ...]


def view_of(episode: Episode, ego_hit: Sequence[bool]) -> EpisodeView:
    """The view of a closed-loop episode: each ego's hit flag, the adversaries, and each
    selected adversary's remaining plan and conflict point."""
    targets = []
    for selection in episode.selections:
        conflict = selection.conflict
        if conflict is not None:
            targets.append((episode.remaining_plan(conflict.agent), conflict.conflict_point))
    return EpisodeView(tuple(ego_hit), frozenset(episode.adversaries), tuple(targets))


class Viewable(Protocol):
    """The viewer's interface to an env, beyond highway-env's ``AbstractEnv`` (``config``,
    ``road``, ``vehicle``, ...): the ego vehicles, the traffic's vehicles by scene row, and
    the episode's :class:`EpisodeView`."""

    config: dict[str, Any]
    controlled_vehicles: list[Vehicle]
    traffic: Mapping[int, Vehicle]

    def episode_view(self) -> EpisodeView: ...


class CounterSceneViewer(EnvViewer):
    """highway-env's viewer plus the adversary's plan and the conflict point.

    highway-env's viewer draws nothing when ``SDL_VIDEODRIVER=dummy`` (its headless switch);
    off-screen ``rgb_array`` rendering needs no display, so it stays enabled here.
    """

    def __init__(self, env: Viewable) -> None:
        if env.config["offscreen_rendering"] and not os.environ.get("DISPLAY"):
            # No window is opened off-screen; without a display SDL would complain.
            os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
        super().__init__(env)
        if self.offscreen:
            self.enabled = True

    def window_position(self) -> np.ndarray:
        return np.asarray(self.env.vehicle.position, dtype=float)

    def display(self) -> None:
        if not self.enabled:
            return
        env = self.env
        view = env.episode_view()
        for v, hit in zip(env.controlled_vehicles, view.ego_hit, strict=True):
            v.color = CRASHED_COLOR if hit else EGO_COLOR
        for row, v in env.traffic.items():
            v.color = ADVERSARY_COLOR if row in view.adversaries else TRAFFIC_COLOR
        super().display()
        if env.config["show_adversary_plan"]:
            self._draw_adversaries(view)
            if not self.offscreen:
                self.screen.blit(self.sim_surface, (0, 0))
                pygame.display.flip()

    def _draw_adversaries(self, view: EpisodeView) -> None:
        surface = self.sim_surface
        width = max(2, surface.pix(0.3))
        for plan, conflict_point in view.targets:
            if plan is not None:
                # The rest of the current plan, from the adversary's next step on.
                points = [surface.vec2pix(p) for p in plan]
                if len(points) > 1:
                    pygame.draw.lines(surface, PLAN_COLOR, False, points, width)
            centre = surface.vec2pix(conflict_point)
            radius = max(6, surface.pix(2.0))
            pygame.draw.circle(surface, CONFLICT_COLOR, centre, radius, width)
            d = int(radius * 0.7)
            pygame.draw.line(
                surface,
                CONFLICT_COLOR,
                (centre[0] - d, centre[1] - d),
                (centre[0] + d, centre[1] + d),
                width,
            )
            pygame.draw.line(
                surface,
                CONFLICT_COLOR,
                (centre[0] - d, centre[1] + d),
                (centre[0] + d, centre[1] - d),
                width,
            )


def render_frame(env: Any) -> np.ndarray | None:
    """A CounterScene env's ``render()``: highway-env's, drawn by :class:`CounterSceneViewer`.
    ``[H, W, 3]`` uint8 in ``rgb_array`` mode; None in ``human`` mode (a window) and, with a
    warning, without a render mode."""
    if env.render_mode is None:
        gym.logger.warn(
            'render() without a render_mode: use gym.make("CounterScene-v0", '
            'render_mode="rgb_array")'
        )
        return None
    if env.viewer is None:
        env.viewer = CounterSceneViewer(env)
    env.enable_auto_render = True
    env.viewer.display()
    if not env.viewer.offscreen:
        env.viewer.handle_events()
    if env.render_mode == "rgb_array":
        return env.viewer.get_image()
    return None


def save_video(frames: Sequence[np.ndarray], path: str | os.PathLike, fps: int = 10) -> Path:
    """Write ``[H, W, 3]`` uint8 frames to ``path`` (``.mp4`` or ``.gif``); returns the path.

    Raises:
        ImportError: imageio (and, for mp4, imageio-ffmpeg) is not installed; install the
            extra with ``pip install "counterscene-env[video]"``.
        ValueError: no frames, frames of different sizes, another suffix, an fps not > 0
            (nothing is written).
    """
    fps = check_real("fps", fps, gt=0)
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".mp4", ".gif"):
        raise ValueError(f"save_video writes .mp4 or .gif, got {path.name!r}")
    if not len(frames):
        raise ValueError("save_video needs at least one frame")
    shapes = {np.shape(f) for f in frames}
    if len(shapes) != 1 or len(next(iter(shapes))) != 3 or next(iter(shapes))[2] != 3:
        raise ValueError(f"frames must all be [H, W, 3] of one size, got shapes {sorted(shapes)}")
    try:
        import imageio.v3 as iio
    except ImportError as exc:
        raise ImportError(
            'save_video needs imageio: pip install "counterscene-env[video]"'
        ) from exc
    if suffix == ".mp4":
        try:
            import imageio_ffmpeg  # noqa: F401
        except ImportError as exc:
            raise ImportError(
                'save_video writes mp4 with imageio-ffmpeg: pip install "counterscene-env[video]"'
            ) from exc
    stack = np.stack([np.asarray(f, dtype=np.uint8) for f in frames])
    path.parent.mkdir(parents=True, exist_ok=True)  # every check is done
    if suffix == ".gif":
        iio.imwrite(path, stack, duration=1000 / fps, loop=0)
    else:
        iio.imwrite(path, stack, fps=fps, codec="libx264", macro_block_size=16)
    return path
