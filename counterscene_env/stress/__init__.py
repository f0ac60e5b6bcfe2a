"""Stress runs: an ego planner against world-model traffic with a guided adversary, scored
as the paper's tables (``counterscene stress``).

Episode i of a run uses the i-th scene of its source (``scene.sources.scenes_for``: generated
scenarios, the i-th safe seed from ``seed``, as ``counterscene generate`` picks them;
``scenarionet:DIR``, the i-th ``.pkl`` file of DIR, sorted; a dataset directory, its i-th
scene; sources are cycled when there are more episodes than scenes) and seed ``seed + i`` for
its sampling noise. So every row of a comparison (guidance presets, selectors) sees the same
scenes and the same noise. Episodes run in batches of ``batch`` (one world-model call per
replan for the batch); a batched call's floating-point results can depend on the batch's
composition, so every run of a config forms the same batches, serial, parallel
(``--workers``), on Ray (``--backend ray``) or resumed, and gives the same records.

The summary (:func:`summarize`, ``metrics.json``) is the paper's table row: ADE, FDE, ORR,
HBR, CR for the horizon groups 1-4 s, 5-7 s, 8-10 s and per second (CR at second h counts
episodes with an ego collision at or before h), plus the whole-episode rates,
ego-vs-adversary collisions, mean min TTC and fallbacks. Wall-clock figures are apart
(:func:`timings`, ``timings.json``), so two runs of the same episodes give identical
``metrics.json``.

Modules: ``config`` (:class:`StressConfig`), ``batch`` (one batch of episodes in a closed
loop), ``episodes`` (running a run's batches in this process),
``workers`` (in several), ``ray_backend`` (as Ray tasks), ``log`` (``episodes.jsonl`` and the
other files of ``--out``), ``summary``.
"""

from counterscene_env.stress.batch import play_batch, run_batch
from counterscene_env.stress.config import SB3_PREFIX, StressConfig, run_identity
from counterscene_env.stress.episodes import (
    BatchRunner,
    PolicyRunner,
    chunks,
    make_runner,
    run_episodes,
    run_policy_episodes,
)
from counterscene_env.stress.log import (
    TIMING_KEYS,
    EpisodeLog,
    write_outputs,
    write_summary,
    write_timings,
)
from counterscene_env.stress.ray_backend import run_ray
from counterscene_env.stress.summary import summarize, timings
from counterscene_env.stress.workers import run_parallel

__all__ = [
    "SB3_PREFIX",
    "TIMING_KEYS",
    "BatchRunner",
    "EpisodeLog",
    "PolicyRunner",
    "StressConfig",
    "chunks",
    "make_runner",
    "play_batch",
    "run_batch",
    "run_episodes",
    "run_identity",
    "run_parallel",
    "run_policy_episodes",
    "run_ray",
    "summarize",
    "timings",
    "write_outputs",
    "write_summary",
    "write_timings",
]
