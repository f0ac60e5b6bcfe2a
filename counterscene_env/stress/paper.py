"""The runs behind the paper's comparisons (``counterscene paper-tables``).

Every table of the paper compares settings of one method on one set of episodes. Here each
setting is a *row*: a stress run whose closed-loop config differs from the default in the
keys the row names, on the same scenario, planner, seeds and episodes as every other row, so
that any two rows can be compared episode by episode (paired tests, ``report.paper_tables``).

Rows and the paper's tables they feed (the paper's names in brackets):

- ``unguided``: the world model with guidance ``none`` (the adversary is still selected, so
  its collisions with the ego are counted the same way).
- ``random``, ``distance`` [SafeSim], ``ttc`` [CCDiff]: the baseline selectors with the full
  guidance; ``counterscene``: the causal selector with the full guidance [CounterScene, Ours,
  Full].
- ``no_jerk``, ``no_conflict_aware``, ``no_progressive``, ``no_adaptive``, ``minimal``: the
  guidance ablations with the causal selector.

Runs live in ``OUT/<scenario>/<row>/`` as ordinary ``counterscene stress --out`` directories
(``counterscene report`` and ``compare`` read them too) and resume where they stopped: a row
that holds all its episodes is not run again.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from counterscene_env.config import COMMONROAD_PREFIX, REAL_MIN_FUTURE, SCENARIONET_PREFIX
from counterscene_env.scene.sources import is_generated
from counterscene_env.sim.config import SimConfig
from counterscene_env.stress.config import StressConfig, run_identity
from counterscene_env.stress.episodes import run_episodes
from counterscene_env.stress.log import EpisodeLog, write_summary
from counterscene_env.stress.summary import summarize
from counterscene_env.stress.workers import run_parallel


@dataclass(frozen=True)
class Row:
    """One setting compared in the paper's tables.

    Attributes:
        name: directory and JSON name.
        label: its name in our tables.
        sim: the ``SimConfig`` keys it sets (the others keep their defaults).
        paper: its name in the paper's tables (None: the paper has no such row).
    """

    name: str
    label: str
    sim: dict = field(default_factory=dict)
    paper: str | None = None


ROWS = {
    r.name: r
    for r in (
        Row("unguided", "world model, unguided", {"guidance": "none"}),
        Row("random", "random selector", {"selector": "random"}, "Random"),
        Row("distance", "distance selector", {"selector": "distance"}, "SafeSim"),
        Row("ttc", "TTC selector", {"selector": "ttc"}, "CCDiff"),
        Row("counterscene", "CounterScene (causal, full guidance)", {}, "CounterScene"),
        Row("no_jerk", "no jerk", {"guidance": "no_jerk"}, "No Jerk"),
        Row(
            "no_conflict_aware",
            "no conflict-aware weighting",
            {"guidance": "no_conflict_aware"},
            "No Conflict Aware",
        ),
        Row(
            "no_progressive",
            "no progressive schedule",
            {"guidance": "no_progressive"},
            "No Progressive",
        ),
        Row("no_adaptive", "no adaptive compression", {"guidance": "no_adaptive"}, "No Adaptive"),
        Row("minimal", "minimal guidance", {"guidance": "minimal"}, "Minimal"),
    )
}

#: The rows of each table (``report.paper_tables``), the reference row first.
TABLES = {
    "main": ("counterscene", "unguided", "random", "distance", "ttc"),
    "selection": ("counterscene", "random", "distance", "ttc"),
    "ablation": (
        "counterscene",
        "no_jerk",
        "no_conflict_aware",
        "no_progressive",
        "no_adaptive",
        "minimal",
    ),
}
#: Tables of the generated roads; real logs get the main rows at 3, 5 and 7 s (the paper's
#: zero-shot table).
GENERATED_TABLES = ("main", "selection", "ablation")
REAL_TABLES = ("real",)
TABLE_ROWS = {**TABLES, "real": TABLES["main"]}


def is_real(spec: str) -> bool:
    """Whether a scenario spec holds stored logs (not only generated roads)."""
    return not is_generated(spec)


def tables_for(spec: str, generated: Sequence[str] = GENERATED_TABLES) -> tuple[str, ...]:
    """The tables of a scenario: :data:`REAL_TABLES` for real logs, else ``generated`` (a
    subset of :data:`GENERATED_TABLES`, in that order)."""
    unknown = sorted(set(generated) - set(GENERATED_TABLES))
    if unknown or not generated:
        raise ValueError(f"tables must be some of {list(GENERATED_TABLES)}, got {list(generated)}")
    if is_real(spec):
        return REAL_TABLES
    return tuple(t for t in GENERATED_TABLES if t in generated)


def rows_for(spec: str, generated: Sequence[str] = GENERATED_TABLES) -> tuple[str, ...]:
    """The rows a scenario needs for its tables (:func:`tables_for`), in run order (the
    reference row first)."""
    tables = tables_for(spec, generated)
    out: list[str] = []
    for table in tables:
        out += [r for r in TABLE_ROWS[table] if r not in out]
    return tuple(out)


def scenario_dir(spec: str) -> str:
    """A directory name for a scenario spec: the road, ``scenarionet-<name>`` /
    ``commonroad-<name>`` after the folder of real logs, or a stored dataset's own name."""
    for prefix, tag in ((SCENARIONET_PREFIX, "scenarionet"), (COMMONROAD_PREFIX, "commonroad")):
        if spec.startswith(prefix):
            name = Path(spec[len(prefix) :].rstrip("/")).name
            return f"{tag}-{re.sub(r'[^A-Za-z0-9_.-]', '_', name)}"
    if not is_real(spec):
        return spec
    return re.sub(r"[^A-Za-z0-9_.-]", "_", Path(spec.rstrip("/")).name)  # a stored dataset


#: Closed-loop keys the rows vary: not settable for all rows at once.
ROW_KEYS = ("selector", "guidance")


def row_config(
    spec: str,
    row: Row,
    episodes: int,
    seed: int,
    planner: str,
    batch: int,
    base: dict | None = None,
    egos: int = 1,
    min_future: float = REAL_MIN_FUTURE,
    rollouts: int = 1,
) -> StressConfig:
    """The stress run of one row on one scenario; ``base``: closed-loop settings shared by
    every row (``SimConfig`` keys other than :data:`ROW_KEYS`); ``egos``: ego choices per
    real scene (``StressConfig.egos``; generated roads draw a new scene every episode);
    ``min_future``: s of log a real scene needs after its start (``StressConfig.min_future``);
    ``rollouts``: candidate rollouts per episode (``StressConfig.rollouts``)."""
    base = dict(base or {})
    fixed = sorted(set(base) & set(ROW_KEYS))
    if fixed:
        raise ValueError(f"{fixed} differ between the rows; they cannot be set for all rows")
    return StressConfig(
        scenario=spec,
        episodes=episodes,
        seed=seed,
        planner=planner,
        sim=SimConfig.from_mapping({**base, **row.sim}),
        batch=batch,
        egos=egos,
        min_future=min_future,
        rollouts=rollouts,
    )


def _check_dirs_differ(specs: Sequence[str]) -> None:
    """Refuse scenarios whose rows would share a folder (real-log folders of one name)."""
    dirs = [scenario_dir(spec) for spec in specs]
    twice = sorted({d for d in dirs if dirs.count(d) > 1})
    if twice:
        raise ValueError(f"two scenarios would share the output folder {twice}: rename one")


def _open_logs(
    out: str | Path, plan: list[tuple[str, str, StressConfig]], model: str, refuse_longer: bool
) -> list[EpisodeLog]:
    """Each planned row's log in ``out`` (nothing is written). ``refuse_longer``: a row that
    holds more finished episodes than asked for is refused (its summary would count
    ``--episodes`` and its episode file every recorded one)."""
    logs = []
    for where, name, config in plan:
        log = EpisodeLog(
            Path(out) / where / name,
            run_identity(config, model),
            resume=True,
            summarize=lambda r, c=config: summarize(r[: c.episodes], c, model),
        )
        if refuse_longer and len(log.records) > config.episodes:
            raise ValueError(
                f"{log.dir} holds {len(log.records)} finished episodes of this row, more than "
                f"--episodes {config.episodes}: rerun with --episodes {len(log.records)} or "
                "more, or pick another --out"
            )
        logs.append(log)
    return logs


def run_rows(
    out: str | Path,
    specs: Sequence[str],
    episodes: int,
    seed: int,
    planner: str = "idm",
    model: str = "default",
    workers: int = 1,
    batch: int = 4,
    base: dict | None = None,
    egos: int = 1,
    min_future: float = REAL_MIN_FUTURE,
    rollouts: int = 1,
    progress: bool = True,
    on_row: Callable[[str, str, int], None] | None = None,
    run: bool = True,
    tables: Sequence[str] = GENERATED_TABLES,
) -> dict[str, dict[str, list[dict]]]:
    """Run (or finish) every row each scenario needs; ``{scenario dir: {row: records}}``.

    ``tables``: the generated roads' tables to run (:func:`tables_for`); real logs always
    run the real-logs table. ``rollouts``: candidate rollouts per episode in every row
    (``StressConfig.rollouts``).

    ``on_row(scenario dir, row, episodes already done)`` is called before each row runs.
    Every config is checked before the first episode runs, so a bad spec or planner fails
    at once and leaves nothing behind. ``run=False``: run nothing, return the episodes
    already in ``out`` (a row may then hold fewer than ``episodes``; rows with none are
    left out of the result, and ``report.paper_document.build`` names them as not run).
    """
    from counterscene_env.world_model.checkpoint import load_model

    plan = []
    _check_dirs_differ(specs)
    for spec in specs:
        for name in rows_for(spec, tables):
            config = row_config(
                spec, ROWS[name], episodes, seed, planner, batch, base, egos, min_future, rollouts
            )
            if config.is_sb3:
                raise ValueError("paper-tables runs the built-in planners (idm, log, ...)")
            plan.append((scenario_dir(spec), name, config))
    logs = _open_logs(out, plan, model, refuse_longer=run)
    world_model = load_model(model) if workers == 1 and run else None
    results: dict[str, dict[str, list[dict]]] = {}
    for (where, name, config), log in zip(plan, logs, strict=True):
        directory = log.dir
        done = len(log.records[: config.episodes])
        if not run:
            if done:
                results.setdefault(where, {})[name] = log.records[: config.episodes]
            continue
        if on_row is not None:
            on_row(where, name, done)
        if done < config.episodes:
            if workers > 1:
                records = run_parallel(config, workers, model, progress=progress, log=log)
            else:
                records = run_episodes(world_model, config, progress=progress, log=log)
        else:
            records = log.records[: config.episodes]
        write_summary(directory, summarize(records, config, model))
        results.setdefault(where, {})[name] = records
    return results
