"""Frames with timestamps onto the exact 0.1 s grid of a scene.

One job: real logs come with their own clocks (ScenarioNet's Waymo files carry float32
timestamps whose steps run 0.09987-0.10013 s); a :class:`Scene` has ``dt = 0.1`` s exactly.
:func:`time_grid` accepts a source step within :data:`STEP_TOLERANCE` (1 %) of 0.1 s or of an
integer fraction of it (0.05 s, ...) and places the grid from the first frame;
:meth:`TimeGrid.apply` reads each grid step from the two frames around it, by plain selection
where the frames already lie on the grid (nuScenes, 20 Hz logs) and by linear interpolation
otherwise (headings along the shorter arc). A grid step is valid where the frames it reads are,
and not inside a gap of the source's clock (frames more than :data:`GAP` steps apart).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from counterscene_env.geometry import wrap_angle
from counterscene_env.scene.core import DEFAULT_DT, SceneError

#: Relative tolerance on the source step against 0.1 s / k.
STEP_TOLERANCE = 0.01
#: A grid time this close to a frame (in grid steps: 5 ms) may read that frame alone where its
#: neighbour is invalid, and a last frame this close to a grid time reaches it: float32
#: timestamps drift from the grid by up to 2.7 ms over a 9 s Waymo log (0.5 ms in two of the
#: three Waymo logs here).
SNAP = 0.05
#: Two frames more than this many source steps apart have a gap between them: a grid step
#: inside it is invalid rather than invented by interpolation.
GAP = 1.5


@dataclass(frozen=True)
class TimeGrid:
    """Where each 0.1 s grid step reads the source: frames ``left`` and ``left + 1`` with
    weight ``w`` on the second (``[T]`` each); ``source_dt`` s, ``interpolated`` whether any
    step falls between frames."""

    left: np.ndarray
    w: np.ndarray
    source_dt: float
    interpolated: bool
    bridged: np.ndarray | None = None  # [T] bool: steps inside a gap of the source's clock

    def apply(
        self, position: np.ndarray, heading: np.ndarray, velocity: np.ndarray, valid: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Tracks at the source rate -> the grid.

        Args:
            position: ``[N, T_src, 2]`` m; heading: ``[N, T_src]`` rad; velocity:
                ``[N, T_src, 2]`` m/s; valid: ``[N, T_src]`` bool.

        Returns:
            positions ``[N, T, 2]`` m, yaws ``[N, T]`` rad, signed speeds ``[N, T]`` m/s,
            valid ``[N, T]``.
        """
        i, w = self.left, self.w
        j = np.minimum(i + 1, valid.shape[1] - 1)
        vi, vj = valid[:, i], valid[:, j]
        # A frame whose weight is within SNAP of 0 is not needed: a track's first or last
        # frame stays valid when the grid time falls a float32 drift beside it.
        ok = (vi | (w >= 1 - SNAP)) & (vj | (w <= SNAP))
        if self.bridged is not None:  # no frame was recorded there: nothing to read
            ok &= ~self.bridged
        wv = np.where(vi & vj, w, np.where(vi, 0.0, 1.0))
        pos = (1 - wv[..., None]) * position[:, i] + wv[..., None] * position[:, j]
        vel = (1 - wv[..., None]) * velocity[:, i] + wv[..., None] * velocity[:, j]
        yaw = wrap_angle(heading[:, i] + wv * wrap_angle(heading[:, j] - heading[:, i]))
        # Signed speed (the scene contract): the velocity's magnitude, negative where it points
        # backwards relative to the heading (a reversing car). The magnitude, not the
        # projection, so that annotation slip between heading and velocity does not shrink it.
        along = vel[..., 0] * np.cos(yaw) + vel[..., 1] * np.sin(yaw)
        speed = np.where(along < 0, -1.0, 1.0) * np.linalg.norm(vel, axis=-1)
        return pos, yaw, speed, ok


def time_grid(times: np.ndarray, where: str) -> TimeGrid:
    """The exact 0.1 s grid over frames at ``times`` (``[T_src]`` s, T_src >= 2).

    Raises:
        SceneError: the times do not increase, or their step is neither 0.1 s nor an integer
            fraction of it (the message names ``where``, e.g. ``"f.pkl: metadata.ts"``).
    """
    times = np.asarray(times, dtype=np.float64)
    steps = np.diff(times)
    if (steps <= 0).any():
        raise SceneError(f"{where} is not strictly increasing")
    step = float(np.median(steps))
    k = max(1, round(DEFAULT_DT / step))
    if abs(step * k - DEFAULT_DT) > STEP_TOLERANCE * DEFAULT_DT:
        raise SceneError(
            f"{where} gives a step of {step:.6g} s; need {DEFAULT_DT} s or an integer fraction "
            f"of it (within {STEP_TOLERANCE:.0%})"
        )
    n = len(times)
    rel = (times - times[0]) / DEFAULT_DT  # frame times in grid steps
    grid = np.arange(int(np.floor(rel[-1] + SNAP)) + 1, dtype=np.float64)
    left = np.clip(np.searchsorted(rel, grid, side="right") - 1, 0, n - 2)
    span = rel[left + 1] - rel[left]
    w = np.clip((grid - rel[left]) / span, 0.0, 1.0)
    on_frames = bool(np.all((w <= 1e-9) | (w >= 1 - 1e-9)))
    # Frames further apart than GAP source steps leave a hole in the log (dropped frames):
    # the grid steps inside it are not read from the two frames around it.
    bridged = (span * DEFAULT_DT > GAP * step) & (w > SNAP) & (w < 1 - SNAP)
    return TimeGrid(left, w, round(step, 9), not on_frames, bridged)
