"""Import CommonRoad XML scenarios (e.g. NGSIM US-101, Lankershim, Peachtree) as Scenes.

One job: turn a CommonRoad file, parsed by ``commonroad-io``'s ``CommonRoadFileReader`` (an
optional extra: ``pip install "counterscene-env[commonroad]"``), into the scene contract.

Ego: the planning problem's ego is a planning task, not a logged car (in the NGSIM files its
initial state matches no obstacle), so it is ignored. An ego choice follows the rule of
``scene/egos.py`` (a moving vehicle, present around "now", whose box never overlaps another's:
15 of the 84 usable NGSIM recordings hold overlapping logged boxes, and a factual log must not
start from an ego collision). Best first: most valid steps, then by id.

Short logs: "now" moves earlier where the log does not hold 1 s after ``current_index``
(``core.default_current_index``: 1 s of future if 1 s of history remains, else one future
step); a log without 1 s of history before a future step raises :class:`CommonRoadTooShort`.
``metadata["history_steps"]`` counts the frames up to and including "now"
(``current_index + 1``), ``metadata["future_steps"]`` those after it.

Agents: read by ``scene/commonroad_tracks.py`` (its docstring); a scene's rows are the ego,
then the others by obstacle id.

Road: the lanelets, by ``scene/commonroad_map.py``.

Duplicates: many files share their traffic and differ only in the planning problem.
:func:`iter_commonroad` hashes each file's tracks (ids, types, validity, positions rounded to
1 cm) and uses the first file (sorted by path) of each recording.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import logging.handlers
import os
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from counterscene_env.scene.commonroad_map import CommonRoadError, road_from_lanelets
from counterscene_env.scene.commonroad_tracks import Tracks, file_fault, read_tracks
from counterscene_env.scene.core import (
    AGENT_TYPES,
    DEFAULT_DT,
    Scene,
    SceneError,
    SceneTooShort,
    default_current_index,
)
from counterscene_env.scene.egos import EGO_RULE, best_first, ego_problem
from counterscene_env.scene.road import RoadMap

__all__ = [
    "CommonRoadError",
    "CommonRoadTooShort",
    "commonroad_egos",
    "iter_commonroad",
    "load_commonroad",
]

HASH_RESOLUTION = 0.01  # [m] positions are rounded to this before hashing the traffic
INSTALL_HINT = 'pip install "counterscene-env[commonroad]"'


class CommonRoadTooShort(CommonRoadError, SceneTooShort):
    """A recording too short for any episode (:func:`iter_commonroad` skips and counts it)."""


# ---------------------------------------------------------------------- public API
def load_commonroad(
    path: str | os.PathLike, ego: int | str | None = None, current_index: int = 30
) -> Scene:
    """Load one CommonRoad XML file as a 10 Hz :class:`Scene` (rules: module docstring).

    Args:
        path: a CommonRoad ``.xml`` scenario.
        ego: obstacle id of the ego; None takes the default (first of :func:`commonroad_egos`).
        current_index: the "now" step; moved earlier in a short log.

    Returns:
        The scene: ego at row 0, ``positions [N, T, 2]`` m, ``yaws [N, T]`` rad, ``speeds
        [N, T]`` m/s, ``extents [N, 2]`` m, ``dt = 0.1`` s, ``scenario_id``
        ``"<benchmark id>/ego=<id>"``.

    Raises:
        CommonRoadError: unreadable or malformed file, too short a log, no (or a bad) ego.
        ImportError: ``commonroad-io`` is missing (the message says how to install it).
    """
    path = Path(path)
    scenario, notes = _read_file(path)
    tracks = read_tracks(scenario, path.name)
    return _scenes(scenario, tracks, path.name, current_index, notes, ego=ego)[0]


def commonroad_egos(source: Any, current_index: int = 30) -> list[str]:
    """Obstacle ids that are ego choices, best first (module docstring, "Ego").

    Args:
        source: a CommonRoad ``.xml`` path or a parsed commonroad-io ``Scenario``.
        current_index: the "now" step the choices must be present around (moved earlier in a
            short log, as in :func:`load_commonroad`).
    """
    if isinstance(source, str | os.PathLike):
        scenario, name = _read_file(Path(source))[0], Path(source).name
    else:
        scenario, name = source, str(getattr(source, "scenario_id", "<scenario>"))
    tracks = read_tracks(scenario, name)
    ci = _effective_index(tracks.valid.shape[1], current_index, name)
    return [tracks.ids[r] for r in _ego_rows(tracks, ci)]


def commonroad_files(dir_or_file: str | os.PathLike) -> list[Path]:
    """The ``.xml`` files under a directory (sorted, recursive), or the one file given."""
    path = Path(dir_or_file)
    files = sorted(path.rglob("*.xml")) if path.is_dir() else [path]
    if not path.exists() or not files:
        raise FileNotFoundError(f"{path}: no CommonRoad .xml files")
    return files


def duplicate_files(dir_or_file: str | os.PathLike) -> dict[str, str]:
    """``{file: first file with the same traffic}`` over :func:`commonroad_files`, found from
    the tracks alone (no road, no scene is built); unreadable files are left out."""
    seen: dict[str, str] = {}
    duplicates = {}
    for f in commonroad_files(dir_or_file):
        try:
            tracks = read_tracks(_read_file(f)[0], f.name)
        except CommonRoadError:
            continue
        first = seen.setdefault(_traffic_hash(tracks), f.name)
        if first != f.name:
            duplicates[f.name] = first
    return duplicates


def iter_commonroad(
    dir_or_file: str | os.PathLike,
    all_egos: bool = False,
    *,
    current_index: int = 30,
    skip_duplicates: bool = True,
    report: dict | None = None,
) -> Iterator[Scene]:
    """Scenes of the ``.xml`` files under a directory (sorted, recursive) or of one file: one
    per distinct recording (default ego), or with ``all_egos`` one per ego choice.

    Files that fail (too short, malformed, no ego) are skipped and reported, not raised.

    Args:
        skip_duplicates: skip files whose traffic an earlier file had; if False they are
            yielded too, with ``metadata["duplicate_of"]`` naming that earlier file.
        report: if given, filled (and kept current while iterating) with ``files``,
            ``scenes``, ``duplicates`` (``{file: first file with that traffic}``),
            ``skipped`` (``{file: reason}``) and ``too_short`` (how many of those were).
    """
    files = commonroad_files(dir_or_file)
    report = {} if report is None else report
    report.update(files=len(files), scenes=0, duplicates={}, skipped={}, too_short=0)
    seen: dict[str, str] = {}  # traffic hash -> first file with it
    for f in files:
        try:
            scenario, notes = _read_file(f)
            tracks = read_tracks(scenario, f.name)
            first = seen.setdefault(_traffic_hash(tracks), f.name)
            duplicate_of = None if first == f.name else first
            if duplicate_of:
                report["duplicates"][f.name] = first
                if skip_duplicates:
                    continue
            scenes = _scenes(scenario, tracks, f.name, current_index, notes, all_egos)
        except CommonRoadError as exc:
            report["skipped"][f.name] = str(exc)
            report["too_short"] += isinstance(exc, SceneTooShort)
            continue
        report["scenes"] += len(scenes)
        for scene in scenes:
            scene.metadata["duplicate_of"] = duplicate_of
            yield scene


# ---------------------------------------------------------------------- reading
@contextlib.contextmanager
def _captured_notes(notes: list[str]) -> Iterator[None]:
    """Collect what the reader says about a file (e.g. "Scenario tag 'illegal_cut_in' not
    valid.": older versions warn, newer ones log) instead of printing it on the console.
    DeprecationWarnings are about the package's own code, not the file: dropped."""
    log, handler = logging.getLogger("commonroad"), logging.handlers.BufferingHandler(1 << 20)
    handler.setLevel(logging.WARNING)
    propagate = log.propagate
    log.addHandler(handler)
    log.propagate = False
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            yield
    finally:
        log.removeHandler(handler)
        log.propagate = propagate
    notes.extend(record.getMessage() for record in handler.buffer)
    notes.extend(str(w.message) for w in caught if not issubclass(w.category, DeprecationWarning))


def _read_file(path: Path) -> tuple[Any, list[str]]:
    """The scenario parsed by ``CommonRoadFileReader`` and the reader's notes on the file."""
    notes: list[str] = []
    with _captured_notes(notes):
        try:  # imported here: commonroad-io is an optional extra
            from commonroad.common.file_reader import CommonRoadFileReader
        except ImportError as exc:
            raise ImportError(
                f"reading CommonRoad files needs commonroad-io ({exc}): {INSTALL_HINT}"
            ) from exc
        if not path.is_file():
            raise CommonRoadError(f"{path}: no such file")
        try:
            scenario, _planning_problems = CommonRoadFileReader(str(path)).open()
        except Exception as exc:  # lxml, assertion, key errors alike: the file's fault
            raise CommonRoadError(
                f"{path.name}: not a readable CommonRoad file ({type(exc).__name__}: {exc})"
            ) from exc
    return scenario, sorted(set(notes))


def _effective_index(num_steps: int, current_index: int, source: str) -> int:
    """``current_index``, moved earlier in a short log (``core.default_current_index``)."""
    if current_index < 0:
        raise CommonRoadError(f"{source}: current_index must be >= 0, got {current_index}")
    try:
        return default_current_index(num_steps, source, preferred=current_index)
    except SceneTooShort as exc:
        raise CommonRoadTooShort(str(exc)) from None


# ---------------------------------------------------------------------- egos
def _ego_problem(tracks: Tracks, row: int, ci: int) -> str | None:
    """Why ``row`` is no ego choice at "now" step ``ci`` (``scene.egos``' rule), or None."""
    problem = ego_problem(
        tracks.types,
        tracks.valid,
        tracks.speeds,
        tracks.positions,
        tracks.yaws,
        tracks.extents,
        row,
        ci,
    )
    if isinstance(problem, tuple):
        other, t = problem
        return f"its box overlaps obstacle {tracks.ids[other]}'s at step {t}"
    return problem


def _ego_rows(tracks: Tracks, ci: int) -> list[int]:
    """Rows of the ego choices: most valid steps first, then by id (the row order)."""
    rows = [r for r in range(len(tracks.ids)) if _ego_problem(tracks, r, ci) is None]
    return best_first(tracks.valid, rows)


# ---------------------------------------------------------------------- scenes
def _traffic_hash(tracks: Tracks) -> str:
    """Hash of the logged traffic: ids, types, validity and positions rounded to 1 cm."""
    text = "|".join(f"{i}:{t}" for i, t in zip(tracks.ids, tracks.types, strict=True))
    h = hashlib.sha256(text.encode())
    h.update(np.packbits(tracks.valid).tobytes())
    h.update(np.rint(tracks.positions[tracks.valid] / HASH_RESOLUTION).astype(np.int64).tobytes())
    return h.hexdigest()[:16]


def _scenes(
    scenario: Any,
    tracks: Tracks,
    source: str,
    current_index: int,
    notes: list[str],
    all_egos: bool = False,
    ego: int | str | None = None,
) -> list[Scene]:
    """The scenes of one file: with ``ego`` that obstacle's, else the default or all choices."""
    ci = _effective_index(tracks.valid.shape[1], current_index, source)
    rows = _ego_rows(tracks, ci)
    if ego is not None:
        if str(ego) not in tracks.ids:
            raise CommonRoadError(f"{source}: no usable obstacle with id {str(ego)!r}")
        chosen = [tracks.ids.index(str(ego))]
        if (problem := _ego_problem(tracks, chosen[0], ci)) is not None:
            raise CommonRoadError(f"{source}: obstacle {ego} cannot be the ego: {problem}")
    elif not rows:
        raise CommonRoadError(f"{source}: no vehicle qualifies as ego ({EGO_RULE})")
    else:
        chosen = rows if all_egos else rows[:1]
    with file_fault(source, "lanelet"):  # e.g. a lanelet of zero width
        road, facts = road_from_lanelets(scenario.lanelet_network.lanelets, source)
    sid = scenario.scenario_id
    metadata = {
        "dataset": "commonroad",
        "source_file": source,
        "benchmark_id": str(sid),
        "location": "_".join(
            str(x) for x in (getattr(sid, "country_id", ""), getattr(sid, "map_name", "")) if x
        ),
        "tags": sorted(
            str(getattr(t, "value", t)) for t in (getattr(scenario, "tags", None) or ())
        ),
        "ego_choices": len(rows),
        "num_tracks": {k: tracks.types.count(k) for k in AGENT_TYPES},
        "history_steps": ci + 1,
        "future_steps": tracks.valid.shape[1] - ci - 1,
        "duplicate_of": None,
        "traffic_hash": _traffic_hash(tracks),
        "reader_notes": notes,
        **facts,
        **tracks.notes,
    }
    return [_assemble(tracks, road, r, ci, metadata) for r in chosen]


def _assemble(tracks: Tracks, road: RoadMap, ego_row: int, ci: int, metadata: dict) -> Scene:
    order = [ego_row, *(r for r in range(len(tracks.ids)) if r != ego_row)]
    ego_id = tracks.ids[ego_row]
    try:
        return Scene(
            positions=tracks.positions[order],
            yaws=tracks.yaws[order],
            speeds=tracks.speeds[order],
            extents=tracks.extents[order],
            valid=tracks.valid[order],
            agent_types=np.array([tracks.types[r] for r in order]),
            agent_ids=np.array([tracks.ids[r] for r in order]),
            ego_index=0,
            road=road,
            dt=DEFAULT_DT,
            scenario_id=f"{metadata['benchmark_id']}/ego={ego_id}",
            current_index=ci,
            metadata={**metadata, "ego": ego_id},
        )
    except SceneError as exc:
        raise CommonRoadError(f"{metadata['source_file']}: {exc}") from exc
