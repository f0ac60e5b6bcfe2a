"""Which agents of a log can take the ego's seat: one rule for every source.

A real log has one recorded ego (ScenarioNet's ``sdc_id``, CommonRoad's default choice), but
few logs with one ego each make few distinct episodes. Any other vehicle that drove through
the log can be the ego instead: the planner under test then drives it, and the recorded ego
becomes traffic. An *ego choice* is a vehicle that

- moves: its mean speed over its valid steps is above :data:`MIN_EGO_SPEED`;
- is present from :data:`~counterscene_env.scene.core.MIN_HISTORY_STEPS` steps before "now"
  to one step after it (the history the world model reads, and a first step to drive);
- never overlaps another agent's box at a step both are valid (a log whose boxes overlap
  would start the episode in a collision).

:func:`ego_choices` lists them, :func:`with_ego` puts one in the seat.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from counterscene_env.geometry import boxes_overlap
from counterscene_env.scene.core import MIN_HISTORY_STEPS, Scene

__all__ = ["EGO_RULE", "MIN_EGO_SPEED", "best_first", "ego_choices", "ego_problem", "with_ego"]

MIN_EGO_SPEED = 1.0  # [m/s] mean speed above which a vehicle is "moving" (an ego choice)
EGO_RULE = f"a vehicle above {MIN_EGO_SPEED:g} m/s mean speed, present around now, no overlap"


def ego_problem(
    types: Sequence[str],
    valid: np.ndarray,
    speeds: np.ndarray,
    positions: np.ndarray,
    yaws: np.ndarray,
    extents: np.ndarray,
    row: int,
    now: int,
) -> tuple[int, int] | str | None:
    """Why agent ``row`` is no ego choice at step ``now``, or None if it is one.

    Args:
        types: ``[N]`` agent types; valid: ``[N, T]`` bool; speeds: ``[N, T]`` m/s;
        positions: ``[N, T, 2]`` m; yaws: ``[N, T]`` rad; extents: ``[N, 2]`` m.
        row: the candidate; now: the "now" step.

    Returns:
        None, a reason, or ``(other_row, step)`` of the first box overlap (callers name the
        other agent in their own ids).
    """
    ok, start = valid[row], max(0, now - MIN_HISTORY_STEPS)
    if types[row] != "vehicle":
        return f"its type is {types[row]!r}, not 'vehicle'"
    if not ok[start : now + 2].all():
        return f"it is not present at every step from {start} to {now + 1}"
    if np.abs(speeds[row][ok]).mean() <= MIN_EGO_SPEED:
        return f"its mean speed is not above {MIN_EGO_SPEED:g} m/s"
    hit = boxes_overlap(
        positions[row][None], yaws[row][None], extents[row], positions, yaws, extents[:, None]
    )
    hit &= valid & ok[None]
    hit[row] = False
    if hit.any():
        other, t = np.argwhere(hit)[0]
        return int(other), int(t)
    return None


def best_first(valid: np.ndarray, rows: Sequence[int]) -> list[int]:
    """``rows`` ordered as ego choices: most valid steps first (``valid [N, T]``), then by row."""
    return sorted(rows, key=lambda r: (-int(valid[r].sum()), r))


def ego_choices(scene: Scene) -> list[int]:
    """Rows that can be the ego at ``scene.current_index``: the scene's own ego first (even if
    the rule would refuse it: it is the recorded one), then every vehicle the rule accepts,
    most valid steps first, then by row."""
    now = scene.current_index
    arrays = (scene.agent_types, scene.valid, scene.speeds, scene.positions, scene.yaws)
    others = [
        r
        for r in range(scene.num_agents)
        if r != scene.ego_index and ego_problem(*arrays, scene.extents, r, now) is None
    ]
    return [scene.ego_index, *best_first(scene.valid, others)]


def with_ego(scene: Scene, row: int) -> Scene:
    """The scene with agent ``row`` as the ego; its id gains ``/ego=<agent id>`` and its
    metadata ``ego`` (the recorded ego stays in ``metadata``'s source fields)."""
    if row == scene.ego_index:
        return scene
    agent = str(scene.agent_ids[row])
    base = scene.scenario_id.split("/ego=")[0]
    return scene.replace(
        ego_index=int(row),
        scenario_id=f"{base}/ego={agent}",
        metadata={**scene.metadata, "ego": agent},
    )
