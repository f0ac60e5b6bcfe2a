"""A stress run's files: ``DIR/episodes.jsonl`` (:class:`EpisodeLog`), beside it
``DIR/episode_timings.jsonl``, ``DIR/run.json``, ``DIR/metrics.json`` and ``DIR/timings.json``.

Results and wall-clock figures live in separate files, so that two runs of the same episodes
write identical ``episodes.jsonl`` and ``metrics.json``: an episode record's
:data:`TIMING_KEYS` go to ``episode_timings.jsonl`` (``{"episode": i, "seconds": ..,
"replan_seconds": ..}`` per line) and are merged back into the records on reading. Runs
written before the split keep their timings inside ``episodes.jsonl``; they read the same."""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Sequence
from pathlib import Path

from counterscene_env import metrics

#: Per-episode record keys that are wall-clock timings [s]: written to
#: ``episode_timings.jsonl``, never to ``episodes.jsonl``; nothing in ``metrics.json``
#: depends on them.
TIMING_KEYS = ("seconds", "replan_seconds")
#: The per-episode timings' file, beside ``episodes.jsonl``.
TIMINGS_FILE = "episode_timings.jsonl"
#: Record key naming a planner given from Python (``planner_factory``), which no
#: ``--planner`` value names: a report then names it and makes no videos.
PYTHON_PLANNER_KEY = "python_planner"
#: The ``planner`` a run's report shows for such a planner (``python:NAME``).
PYTHON_PLANNER_PREFIX = "python:"
#: Record fields every summary, report and comparison reads; a record without one is
#: refused when the file is read (before a resumed run adds to it).
REQUIRED_FIELDS = (
    "episode",
    "seed",
    "scenario_id",
    "per_second",
    "cr",
    "cr_ego_adversary",
    "hbr_ego",
    "orr",
    "min_ttc",
    "min_clearance_adversary",
)
#: Record fields read as numbers wherever a record has them (JSON null: NaN, or inf for
#: ``min_ttc``): the whole-episode metrics and what summaries and reports compute with.
NUMBER_FIELDS = (*metrics.SCENE_KEYS, "rollout_s", "danger_score")
#: Record fields that are whole numbers (null allowed but for ``seed``): the seeds an episode
#: is replayed from, and counts.
INT_FIELDS = ("seed", "scene_seed", "rollout", "rollout_seed", "rollouts", "replans")


def differences(have: dict, want: dict, prefix: str = "") -> list[str]:
    """Where two run identities differ, field by field (nested settings as ``sim.guidance``):
    ``"sim.guidance: 'full' there, 'none' now"``, sorted by field."""
    out = []
    for key in sorted(set(have) | set(want), key=str):
        a, b = have.get(key), want.get(key)
        if a == b:
            continue
        if isinstance(a, dict) and isinstance(b, dict):
            out += differences(a, b, f"{prefix}{key}.")
        else:
            out.append(f"{prefix}{key}: {a!r} there, {b!r} now")
    return out


class EpisodeLog:
    """A stress run's durable record: ``DIR/episodes.jsonl``, one line per finished episode.

    Each batch's records are appended, flushed and synced to disk as the batch finishes
    (their timings to ``DIR/episode_timings.jsonl`` first, module docstring), so a killed
    run (Ctrl-C, a crash, a lost machine) loses only the episodes in flight. With
    ``resume``, the run continues after the last recorded episode; a larger ``--episodes``
    extends it. ``DIR/run.json`` holds what the run is (the config but its episode count, and
    the model): a run with anything else is refused, so one directory never mixes two runs.
    With ``summarize``, ``DIR/metrics.json`` is rewritten after each append with
    ``summarize(records so far)``, so even a killed run leaves a readable summary.

    Nothing is written before the first :meth:`append`: a run refused or stopped before its
    first batch finished leaves the directory as it was.

    Args:
        directory: the run's output directory (created at the first append).
        identity: what the run is, as plain JSON values.
        resume: continue the episodes already in ``directory``; without it, a directory that
            holds any is refused.
        summarize: finished records -> the summary for ``metrics.json``.

    Raises:
        ValueError: ``directory`` is a file, holds another run (the message names the
            differing keys), or holds episodes and ``resume`` is false.
    """

    def __init__(
        self,
        directory: str | os.PathLike,
        identity: dict,
        resume: bool = False,
        summarize: Callable[[list[dict]], dict] | None = None,
    ) -> None:
        self.dir = Path(directory)
        if self.dir.exists() and not self.dir.is_dir():
            raise ValueError(f"--out {self.dir} is a file, not a directory")
        self.path = self.dir / "episodes.jsonl"
        self.timings_path = self.dir / TIMINGS_FILE
        self.identity = json.loads(json.dumps(metrics.json_safe(identity)))
        self.summarize = summarize
        run = self.dir / "run.json"
        if run.is_file():
            try:
                have = json.loads(run.read_text())
            except json.JSONDecodeError as exc:
                raise ValueError(
                    f"{run} is not JSON ({exc}): it is not a stress run's, or it was edited"
                ) from None
            if have != self.identity:
                diff = "; ".join(differences(have, self.identity))
                why = (
                    " (its episodes were scored by another definition of the metrics, "
                    "docs/metrics.md: finish it with the version of counterscene that began it)"
                    if have.get("metrics_version") != self.identity.get("metrics_version")
                    else ""
                )
                raise ValueError(
                    f"{self.dir} holds a stress run with other settings ({diff}){why}: "
                    "use another --out, or delete it to start over"
                )
        self._kept: list[str] | None = None  # set when the file's last line was cut short
        self.records = self._read()
        if self.records and not resume:
            n = len(self.records)
            raise ValueError(
                f"{self.dir} already holds {n} finished episode{'s' * (n != 1)} of this run: "
                "pass --resume to continue it, or pick another --out"
            )

    def _read(self) -> list[dict]:
        """The finished episodes on disk, in order; a last line cut short by a kill is
        dropped (and removed from the file at the next append)."""
        if not self.path.is_file():
            return []
        # A kill mid-line: the whole records are kept, each ended, so appends start afresh.
        records, self._kept, _ = read_records(self.path)
        return records

    def append(self, records: Sequence[dict]) -> None:
        """Add finished episodes, on disk before this returns (and ``metrics.json``, with
        ``summarize``)."""
        self.dir.mkdir(parents=True, exist_ok=True)
        run = self.dir / "run.json"
        if not run.is_file():
            _write_atomic(run, json.dumps(self.identity, indent=2) + "\n")
        if self._kept is not None:
            self.path.write_text("".join(f"{x}\n" for x in self._kept))
            self._kept = None
        results, timings = zip(*(split_timings(rec) for rec in records), strict=True)
        # The timings first: a kill between the two writes leaves episodes without timings
        # (read as such), never results that a rerun would append again.
        _append_lines(self.timings_path, timings)
        _append_lines(self.path, results)
        self.records += list(records)
        if self.summarize is not None:
            write_summary(self.dir, self.summarize(self.records))

    def reload(self) -> list[dict]:
        """The finished episodes as the file holds them, now. After a Ctrl-C, which can
        strike between an append's write and its bookkeeping, the file is the truth."""
        self.records = self._read()
        return self.records


def read_records(path: Path) -> tuple[list[dict], list[str] | None, int]:
    """The finished episodes of an ``episodes.jsonl``, in order (:func:`record_from_json`,
    timings merged in: :func:`merge_timings`); the lines to rewrite the file with when a kill
    cut its end (a line cut short, or the last newline lost; None: it ends cleanly); and
    how many cut lines were skipped (at most the last).

    Raises:
        ValueError: a line that is not JSON before the last, a record without a field of
            :data:`REQUIRED_FIELDS` or with a wrongly typed one (:func:`record_problem`),
            episodes out of order, or a wrongly typed timing in ``episode_timings.jsonl``
            (naming the file, the line and the field).
    """
    text = path.read_text()
    lines = text.splitlines()
    records: list[dict] = []
    for n, line in enumerate(lines, start=1):
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            if n != len(lines):
                raise ValueError(f"{path}: line {n} is not JSON") from None
            break
        if not isinstance(rec, dict):
            raise ValueError(f"{path}: line {n} is {_json(rec)}, not a JSON object (a record)")
        missing = [k for k in REQUIRED_FIELDS if k not in rec]
        if missing:
            raise ValueError(f"{path}: line {n} has no field {', '.join(map(repr, missing))}")
        problem = record_problem(rec)
        if problem:
            raise ValueError(f"{path}: line {n}: {problem}")
        if rec["episode"] != len(records):
            raise ValueError(
                f"{path}: line {n} is episode {rec['episode']!r}, expected {len(records)}"
            )
        records.append(rec)
    cut = len(lines) - len(records)
    repair = lines[: len(records)] if cut or (text and not text.endswith("\n")) else None
    return merge_timings([record_from_json(r) for r in records], path.parent), repair, cut


def _is_number(value: object) -> bool:
    """A JSON number (not a bool: ``true`` is no rate or distance)."""
    return isinstance(value, int | float) and not isinstance(value, bool)


def _json(value: object) -> str:
    """``value`` as the file spells it (``"yes"``, ``true``), cut to a readable length."""
    text = json.dumps(value)
    return text if len(text) <= 40 else text[:37] + "..."


def record_problem(record: dict) -> str | None:
    """What is wrongly typed in an episode record as ``episodes.jsonl`` holds it (None:
    nothing): ``"field 'cr' is "yes", not a number or null"``. Checked when the file is read,
    so that a bad record is named by its file, line and field, not by a numpy error later.

    Checks :data:`NUMBER_FIELDS` (numbers or null), :data:`INT_FIELDS` (whole numbers; null
    but for ``seed``) and ``per_second`` (an object of horizon seconds, each an object of
    numbers or null)."""
    for key in NUMBER_FIELDS:
        value = record.get(key)
        if value is not None and not _is_number(value):
            return f"field {key!r} is {_json(value)}, not a number or null"
    for key in INT_FIELDS:
        if key not in record or (record[key] is None and key != "seed"):
            continue
        value = record[key]
        if not isinstance(value, int) or isinstance(value, bool):
            return f"field {key!r} is {_json(value)}, not a whole number"
    return _per_second_problem(record["per_second"])


def _per_second_problem(per_second: object) -> str | None:
    """What is wrongly typed in a record's ``per_second`` (None: nothing)."""
    if not isinstance(per_second, dict):
        return f"field 'per_second' is {_json(per_second)}, not an object of horizon seconds"
    for second, row in per_second.items():
        where = f"per_second[{second!r}]"
        try:
            float(second)
        except ValueError:
            return f"field 'per_second' has the key {second!r}, not a horizon in seconds"
        if not isinstance(row, dict):
            return f"field {where} is {_json(row)}, not an object of metrics"
        for key, value in row.items():
            if value is not None and not _is_number(value):
                return f"field {where}[{key!r}] is {_json(value)}, not a number or null"
    return None


def split_timings(record: dict) -> tuple[dict, dict]:
    """An episode record as ``(its results, {"episode": i, its TIMING_KEYS})``."""
    results = {k: v for k, v in record.items() if k not in TIMING_KEYS}
    timing = {"episode": record.get("episode")}
    timing.update({k: record[k] for k in TIMING_KEYS if k in record})
    return results, timing


def merge_timings(records: list[dict], directory: str | os.PathLike) -> list[dict]:
    """``records`` (in episode order) with the timings of ``DIR/episode_timings.jsonl``
    merged in, where the file has them; a line cut short by a kill, or timings of episodes
    the records do not hold, are ignored. Records that carry their own timings (runs written
    before the split) keep them.

    Raises:
        ValueError: a timing that is not a number (naming the file, the line and the field).
    """
    path = Path(directory) / TIMINGS_FILE
    if not path.is_file():
        return records
    found: dict[int, dict] = {}
    for n, line in enumerate(path.read_text().splitlines(), start=1):
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(row, dict) and isinstance(row.get("episode"), int):
            for key in TIMING_KEYS:
                if key in row and not _is_number(row[key]):
                    raise ValueError(
                        f"{path}: line {n}: field {key!r} is {_json(row[key])}, not a number "
                        "of seconds"
                    )
            found[row["episode"]] = row
    out = []
    for rec in records:
        row = found.get(rec.get("episode"))
        if row is not None:
            rec = {**rec, **{k: row[k] for k in TIMING_KEYS if k in row and k not in rec}}
        out.append(rec)
    return out


def _append_lines(path: Path, rows: Sequence[dict]) -> None:
    """Append one JSON line per row, on disk before this returns. One write call: Ctrl-C
    (raised between Python statements) never splits a batch."""
    text = "".join(json.dumps(metrics.json_safe(row)) + "\n" for row in rows)
    if path.is_file() and path.stat().st_size:
        with open(path, "rb") as f:
            f.seek(-1, os.SEEK_END)
            if f.read(1) != b"\n":  # a line cut short by a kill: start on a line of our own
                text = "\n" + text
    with open(path, "a") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())


def record_from_json(record: dict) -> dict:
    """An episode record as written (``metrics.json_safe``: NaN and inf as null) back to its
    values: a null ``min_ttc`` is inf (no projected conflict), any other null metric NaN;
    nulls that mean "none" (no adversary, no fallback) stay None."""
    out = dict(record)
    for key in metrics.SCENE_KEYS:
        if out.get(key, 0) is None:
            out[key] = math.inf if key == "min_ttc" else math.nan
    out["per_second"] = {
        h: {k: math.nan if v is None else v for k, v in row.items()}
        for h, row in record.get("per_second", {}).items()
    }
    return out


def _write_atomic(path: Path, text: str) -> None:
    """``path`` holds ``text`` or its previous content, never half of it (a kill mid-write)."""
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def _write_json(path: Path, obj: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    _write_atomic(path, json.dumps(metrics.json_safe(obj), indent=2) + "\n")


def write_summary(directory: str | os.PathLike, summary: dict) -> None:
    """``DIR/metrics.json``: the summary of a run (written whole or not at all)."""
    _write_json(Path(directory) / "metrics.json", summary)


def write_timings(directory: str | os.PathLike, timings: dict) -> None:
    """``DIR/timings.json``: the run's wall-clock figures (kept apart from ``metrics.json``,
    which two runs of the same episodes give identically)."""
    _write_json(Path(directory) / "timings.json", timings)


def write_outputs(
    directory: str | os.PathLike,
    summary: dict,
    records: Sequence[dict],
    timings: dict | None = None,
) -> None:
    """``DIR/metrics.json`` (the summary), ``DIR/episodes.jsonl`` and
    ``DIR/episode_timings.jsonl`` (one line per episode, rewritten whole) and, if given,
    ``DIR/timings.json``: a run kept in memory, not through an :class:`EpisodeLog`."""
    write_summary(directory, summary)
    results, rows = (
        zip(*(split_timings(rec) for rec in records), strict=True) if records else ((), ())
    )
    for name, lines in (("episodes.jsonl", results), (TIMINGS_FILE, rows)):
        with open(Path(directory) / name, "w") as f:
            for row in lines:
                f.write(json.dumps(metrics.json_safe(row)) + "\n")
    if timings is not None:
        write_timings(directory, timings)
