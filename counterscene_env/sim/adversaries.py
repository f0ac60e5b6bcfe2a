"""Each ego's adversary in a closed-loop episode: who is eligible, and the selection on the
log's future at the start or, with ``selection_source="model"``, again at every replan on the
world model's own unguided prediction (docs/concepts/causal_selection.md).

The choice itself is ``adversary.selection.select_adversary``; here it gets the episode's
tracks, the eligible agents (vehicles that are neither an ego nor an earlier ego's adversary)
and the closed loop's selector settings (``SimConfig``), and its result is written to
``Episode.selections``. Shapes: A agents of the tracks, F future steps.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from counterscene_env.adversary.selection import Selection, select_adversary
from counterscene_env.geometry import from_frame, wrap_angle
from counterscene_env.scene.core import Scene
from counterscene_env.sim.config import SimConfig
from counterscene_env.sim.state import Episode
from counterscene_env.world_model.model import WorldModel
from counterscene_env.world_model.window import WindowConfig, agent_count, collate, make_window


def select_on_log(ep: Episode, config: SimConfig) -> None:
    """Select every ego's adversary on the factual future (``selection_source="log"``)."""
    s, lo, hi = ep.factual, ep.start + 1, ep.end + 1
    future = s.positions[:, lo:hi], s.valid[:, lo:hi], s.speeds[:, lo:hi]
    for k in range(len(ep.egos)):
        ep.selections[k] = select_for_ego(ep, k, config, *future, start_step=ep.start + 1)


def select_for_ego(
    ep: Episode,
    k: int,
    config: SimConfig,
    positions: np.ndarray,
    valid: np.ndarray,
    speeds: np.ndarray,
    start_step: int,
    rows: np.ndarray | None = None,
    yaws: np.ndarray | None = None,
) -> Selection:
    """Ego ``k``'s adversary on future tracks ``positions [A, F, 2]`` m, ``valid [A, F]``,
    ``speeds [A, F]`` m/s (``yaws [A, F]`` rad if known), starting at absolute step
    ``start_step``; ``rows`` maps their rows to scene rows (None: identity). Other egos, and
    the adversaries of egos before ``k``, are not eligible: every ego gets its own
    world-model adversary. The selection's conflict names a scene row."""
    scene = ep.factual
    rows = np.arange(scene.num_agents) if rows is None else rows
    ego = int(np.flatnonzero(rows == ep.egos[k])[0])
    taken = set(ep.egos) | {a for a in ep.adversaries[:k] if a is not None}
    eligible = (scene.agent_types[rows] == "vehicle") & ~np.isin(rows, sorted(taken))
    sel = select_adversary(
        config.selector,
        positions,
        valid,
        ego,
        speeds=speeds,
        extents=scene.extents[rows],
        yaws=yaws,
        eligible=eligible,
        dt=scene.dt,
        start_step=start_step,
        strict=config.strict_gates,
        yielders_first=config.yielders_first,
        reachable_first=config.reachable_first,
        rng=ep.selection_rng,
    )
    if sel.conflict is not None:  # back to scene rows
        agent = int(rows[sel.conflict.agent])
        sel = dataclasses.replace(sel, conflict=dataclasses.replace(sel.conflict, agent=agent))
    return sel


def reselect_on_model(
    model: WorldModel,
    config: SimConfig,
    window_config: WindowConfig,
    sample_kwargs: Mapping[str, Any],
    eps: Sequence[Episode],
    sims: Sequence[Scene],
) -> None:
    """``selection_source="model"``: re-select every ego's adversary on the world model's own
    unguided prediction (one sample) of the ego's window, from the simulated scenes ``sims``
    (one per episode of ``eps``, up to its current step). ``sample_kwargs``: the replan's
    sampler settings (``WorldModel.sample`` keywords)."""
    owner, items = [], []
    for i, (sim, ep) in enumerate(zip(sims, eps, strict=True)):
        for ego in ep.egos:
            view = sim if ego == sim.ego_index else sim.replace(ego_index=ego)
            items.append(make_window(view, ep.t, window_config, ep.segments))
            owner.append(i)
    counts = [agent_count(item) for item in items]
    # One call per agent count, as at a replan: an episode's result never depends on which
    # others share its call (sim/replan.py).
    for count in sorted(set(counts)):
        js = [j for j, c in enumerate(counts) if c == count]
        gens = [eps[owner[j]].generator for j in js]
        batch = collate([items[j] for j in js], trim=True)
        pred = model.sample(batch, 1, gens, **sample_kwargs)
        for i, j in enumerate(js):
            ep, item = eps[owner[j]], items[j]
            k = ep.egos.index(int(item["rows"][0]))
            ok = (item["rows"][:count] >= 0) & pred.valid[i].numpy()
            traj = pred.trajectory[i, 0].numpy()[ok]  # [A, F, 4] window frame
            xy = from_frame(traj[..., :2], item["origin"])
            yaw = wrap_angle(traj[..., 2] + item["origin"][2])
            valid = np.ones(xy.shape[:2], bool)
            rows = item["rows"][:count][ok]
            ep.selections[k] = select_for_ego(
                ep, k, config, xy, valid, traj[..., 3], ep.t + 1, rows, yaw
            )
