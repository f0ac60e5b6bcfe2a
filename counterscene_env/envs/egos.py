"""Which vehicles of a scene the external policies drive: the egos of an episode."""

from __future__ import annotations

import numpy as np

from counterscene_env.scene.core import Scene


def pick_egos(scene: Scene, n: int) -> list[int]:
    """``n`` ego rows of a scene: its own ego, then the vehicles nearest to it that are
    present now and for the longest part of the log.

    Raises:
        ValueError: the scene has fewer than ``n`` such vehicles.
    """
    e, t = scene.ego_index, scene.current_index
    if n == 1:
        return [e]
    ok = scene.valid[:, t] & (scene.agent_types == "vehicle")
    ok[e] = False
    rows = np.flatnonzero(ok)
    if rows.size < n - 1:
        raise ValueError(
            f"scene {scene.scenario_id!r} has {rows.size + 1} vehicles present at the start, "
            f"fewer than the {n} egos asked for"
        )
    # Prefer vehicles that stay in the log (an ego whose log ends is still simulated, but a
    # short-lived one makes a poor policy target), then the nearest.
    stays = scene.valid[rows, t:].mean(-1)
    dist = np.linalg.norm(scene.positions[rows, t] - scene.positions[e, t], axis=-1)
    order = np.lexsort((dist, -np.round(stays, 1)))
    return [int(e), *(int(r) for r in rows[order[: n - 1]])]
