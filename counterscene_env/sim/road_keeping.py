"""Road keeping: traffic about to leave the road is kept on the nearest lane going its way.

The world model sometimes under-turns: in a curve its plan runs straight on, over the verge
(``docs/world_model.md``, "Training": the off-road points are mostly such under-turns). A
driver whose car drifts toward the edge steers back; this module is that reflex, applied by the
closed loop (``sim/motion.py``) at every step to every agent but the egos:

- only a step that would take a centre from the drivable area to outside it is changed;
- the new centre is the planned one moved sideways into the nearest lane strip whose direction
  is within :data:`MAX_HEADING_GAP` of the agent's course, :data:`EDGE_MARGIN` inside its edge
  (the progress along the road is kept, so is the speed), if that is at most
  :data:`MAX_SHIFT` away;
- the course becomes the direction of that corrected step, and the next replan starts the
  world model from there.

An agent already off the road (a log that records one) is left alone.
"""

from __future__ import annotations

import math

import numpy as np

from counterscene_env.geometry import wrap_angle

#: How far inside its lane's edge a corrected centre is placed [m].
EDGE_MARGIN = 0.3
#: A lane is "going the agent's way" if its direction is within this of the agent's course [rad].
MAX_HEADING_GAP = math.radians(60.0)
#: The farthest a centre is moved [m]. A correction steers back onto the lane the car is
#: drifting off; the nearest lane going its way may lie across a junction (a turning car's
#: course points at the crossing road), and moving there would teleport the car.
MAX_SHIFT = 5.0


def lane_pieces(lines: np.ndarray, widths: np.ndarray) -> tuple[np.ndarray, ...]:
    """Straight pieces of lane centre lines, for :func:`keep_on_lane`.

    Args:
        lines: ``[S, P, 2]`` m, centre-line segments (``world_model.window.lane_segments``).
        widths: ``[S]`` m.

    Returns:
        ``(start [Q, 2] m, end [Q, 2] m, half_width [Q] m, direction [Q] rad)``.
    """
    start = lines[:, :-1].reshape(-1, 2)
    end = lines[:, 1:].reshape(-1, 2)
    half = np.repeat(np.asarray(widths, float) / 2, lines.shape[1] - 1)
    keep = np.linalg.norm(end - start, axis=-1) > 1e-6
    d = end - start
    return start[keep], end[keep], half[keep], np.arctan2(d[keep, 1], d[keep, 0])


def keep_on_lane(
    point: np.ndarray, course: float, pieces: tuple[np.ndarray, ...]
) -> np.ndarray | None:
    """``point`` ``[2]`` m moved sideways into the nearest lane strip going ``course`` (rad).

    Unchanged if it already lies :data:`EDGE_MARGIN` inside that strip; None if no lane of
    ``pieces`` (:func:`lane_pieces`) goes the agent's way, or if reaching the nearest would
    move it more than :data:`MAX_SHIFT`.
    """
    start, end, half, direction = pieces
    if not len(start):
        return None
    seg = end - start
    u = np.clip(((point - start) * seg).sum(-1) / (seg * seg).sum(-1), 0.0, 1.0)
    foot = start + u[:, None] * seg
    offset = point - foot
    dist = np.linalg.norm(offset, axis=-1)
    gap = np.abs(wrap_angle(direction - course))
    dist = np.where(gap <= MAX_HEADING_GAP, dist, np.inf)
    q = int(np.argmin(dist))
    if not np.isfinite(dist[q]):
        return None
    limit = max(half[q] - EDGE_MARGIN, 0.0)
    if dist[q] <= limit:
        return point
    if dist[q] - limit > MAX_SHIFT:
        return None
    return foot[q] + offset[q] * (limit / dist[q])
