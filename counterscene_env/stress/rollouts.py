"""Candidate rollouts: each episode run under several closed-loop seeds, the most severe for
the ego kept (the paper's protocol, "Implementation details": 16 candidate rollouts per
scene, the one with the highest adversarial effectiveness kept, every baseline under the same
protocol; docs/closed_loop.md, "Candidate rollouts").

An episode's outcome is chaotic in its noise: with the same adversary, a fifth to a third of
the development intersections end the other way under another seed
(docs/history/closed_loop.md, twenty-seventh sitting). Running each episode K times and
keeping the worst for the ego turns a stress run's question from "how often does the planner
fail in this scene" into "can the traffic make it fail in K tries": a search for the
planner's failures, at K times the cost.

Candidate k of the episode with closed-loop seed ``s`` runs with :func:`rollout_seed` ``(s,
k)``; candidate 0 is the episode's own seed, so one candidate is the plain run. Every
candidate keeps ``s`` as its selection seed (``ClosedLoop.reset``), so the candidates differ
in their noise and not in their adversary, a ``random`` selector's included.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from counterscene_env.metrics import severity

__all__ = ["keep_most_severe", "rollout_seed"]

#: The timing field that adds up over the candidates (one of ``stress.log.TIMING_KEYS``).
SECONDS = "seconds"


def rollout_seed(seed: int, k: int) -> int:
    """The closed-loop seed of candidate rollout ``k`` of the episode seeded ``seed``: the seed
    itself for ``k = 0``, else a 32-bit seed drawn from ``numpy.random.SeedSequence((seed,
    k))`` (independent of the other candidates' and of the neighbouring episodes' seeds)."""
    if k == 0:
        return int(seed)
    return int(np.random.SeedSequence((int(seed), int(k))).generate_state(1)[0])


def keep_most_severe(candidates: Sequence[Sequence[dict]]) -> list[dict]:
    """Each episode's most severe candidate for the ego (``metrics.severity``: a collision
    first, with the adversary before others, then the smallest time to collision and
    clearance); ties to the lower candidate.

    Args:
        candidates: ``[K][B]`` records: candidate k of each of B episodes, as ``stress`` records
            them (``seed`` is the seed the candidate ran with).

    Returns:
        ``[B]`` records: the kept candidate's, with ``seed`` the episode's own (candidate 0's,
        so that runs pair by episode), ``rollout`` the kept candidate, ``rollout_seed`` the
        seed it ran with (a replay's), ``rollouts`` K, and ``seconds`` summed over the K
        candidates: what the episode cost (``replan_seconds`` stays the kept candidate's, as
        its ``replans`` do, so that their ratio is a replan's time).
    """
    if not candidates:
        raise ValueError("keep_most_severe needs at least one candidate per episode")
    out = []
    for own in zip(*candidates, strict=True):
        k = min(range(len(own)), key=lambda i: (severity(own[i]), i))
        kept = dict(own[k])
        kept.update(seed=own[0]["seed"], rollout=k, rollout_seed=own[k]["seed"], rollouts=len(own))
        if all(SECONDS in r for r in own):
            kept[SECONDS] = float(sum(r[SECONDS] for r in own))
        out.append(kept)
    return out
