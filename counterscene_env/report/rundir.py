"""A stress run directory, read back: what was run (``run.json``, ``metrics.json``) and its
episode records (``episodes.jsonl``), as ``counterscene stress --out DIR`` writes them.

Reading never changes the directory: a run killed mid-line keeps its cut last line on disk
(the next ``stress`` rerun repairs it, ``stress.EpisodeLog``); here it is skipped.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

from counterscene_env.stress.log import (
    PYTHON_PLANNER_KEY,
    PYTHON_PLANNER_PREFIX,
    read_records,
)


@dataclass(frozen=True)
class Run:
    """One stress run on disk.

    Attributes:
        directory: the run directory.
        identity: what the run is: ``run.json`` (``stress.run_identity``: the stress config
            but its episode count, plus ``model``), else ``metrics.json``'s ``config``.
        summary: ``metrics.json`` (``stress.summarize``; ``"complete": false`` while the
            run is unfinished), None when there is none.
        timings: ``timings.json`` (wall-clock figures, apart from the metrics), None when
            there is none.
        records: the finished episodes in order, one dict each (``stress.batch.record``), with
            JSON nulls read back as NaN, and ``min_ttc`` null as inf (no projected conflict).
        cut_lines: lines of ``episodes.jsonl`` skipped as cut short by a kill (0 or 1).
    """

    directory: Path
    identity: dict
    summary: dict | None
    timings: dict | None
    records: list[dict]
    cut_lines: int = 0

    @property
    def name(self) -> str:
        """The directory's name (the run's label where nothing better distinguishes it)."""
        return self.directory.resolve().name

    @property
    def planned_episodes(self) -> int | None:
        """Episodes the run was started for (``metrics.json``), None when unknown."""
        if self.summary is None:
            return None
        return self.summary.get(
            "episodes_requested", self.summary.get("config", {}).get("episodes")
        )

    @property
    def complete(self) -> bool | None:
        """Whether every episode the run was started for is in ``records`` (None: no
        ``metrics.json`` to tell how many that is)."""
        if self.summary is None:
            return None
        planned = self.planned_episodes
        return planned is None or len(self.records) >= planned

    def sim(self) -> dict:
        """The closed-loop settings of the run (``SimConfig`` fields as a dict)."""
        return dict(self.identity.get("sim", {}))


def load_run(directory: str | os.PathLike) -> Run:
    """Read a stress run directory.

    Raises:
        FileNotFoundError: no such directory, or it has no ``episodes.jsonl``, or neither
            ``run.json`` nor ``metrics.json`` (the message names the files).
        ValueError: a JSON file that is not a JSON object, a run whose ``sim`` is not one;
            ``episodes.jsonl`` has no finished episode, a line that is not JSON before the
            last, a record without a required field or with a wrongly typed one, or
            episodes out of order (the message names the file, the line and the field).
    """
    root = Path(directory)
    if root.is_file():
        raise FileNotFoundError(f"{root} is a file: give the run's directory")
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: no such run directory")
    episodes = root / "episodes.jsonl"
    if not episodes.is_file():
        raise FileNotFoundError(
            f"{episodes}: no episodes file; is {root} a `counterscene stress --out` directory?"
        )
    summary = _read_json(root / "metrics.json")
    identity = _read_json(root / "run.json")
    if identity is None:
        if summary is None or "config" not in summary:
            raise FileNotFoundError(
                f"{root}: neither run.json nor metrics.json (with its 'config'): what was run "
                "is unknown"
            )
        identity = {k: v for k, v in summary["config"].items() if k != "episodes"}
    if not isinstance(identity.get("sim", {}), dict):
        source = "run.json" if (root / "run.json").is_file() else "metrics.json, its config"
        raise ValueError(
            f"{root / source}: field 'sim' is {identity['sim']!r}, not an object of "
            "closed-loop settings"
        )
    records, cut = _read_records(episodes)
    if PYTHON_PLANNER_KEY in records[0]:  # run.json names the config's planner, not this one
        identity = {**identity, "planner": PYTHON_PLANNER_PREFIX + records[0][PYTHON_PLANNER_KEY]}
    return Run(root, identity, summary, _read_json(root / "timings.json"), records, cut)


def _read_json(path: Path) -> dict | None:
    if not path.is_file():
        return None
    try:
        out = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not JSON ({exc})") from None
    if not isinstance(out, dict):
        raise ValueError(f"{path}: {type(out).__name__}, not a JSON object")
    return out


def _read_records(path: Path) -> tuple[list[dict], int]:
    """The records of ``episodes.jsonl`` (``stress.log.read_records``) and the number of cut
    lines skipped."""
    records, _, cut = read_records(path)
    if not records:
        raise ValueError(f"{path}: no finished episode")
    return records, cut
