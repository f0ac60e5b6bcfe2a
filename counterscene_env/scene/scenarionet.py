"""Import one ScenarioNet scenario pickle (nuScenes, Waymo, nuPlan, Argoverse 2, Lyft) as a
:class:`Scene`.

One job: turn a ScenarioNet "scenario description" file, exactly as ScenarioNet's converters
write it, into the scene contract (:class:`~counterscene_env.scene.core.Scene`). The file is
unpickled by ``scene/safe_pickle.py`` (nothing in it can run code); its map becomes a
:class:`RoadMap` in ``scene/scenarionet_map.py``.

Time base
---------
The step is read from ``metadata.ts`` (the timestamps of the frames) where it has one entry per
frame, else from ``metadata.sample_rate`` (seconds per frame), and the tracks are put on the
exact 0.1 s grid by ``scene/timebase.py`` (a step within 1 % of 0.1 s or an integer fraction
of it: ScenarioNet's Waymo converter writes float32 timestamps with steps of 0.09987 to
0.10013 s).

Tracks
------
Every track is read, checked and repaired by ``scene/scenarionet_tracks.py`` (its docstring
lists each repair; one bad track never costs the scene). The ego (``metadata["sdc_id"]``) is
row 0, the other tracks follow in file order.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from counterscene_env.scene.core import (
    DEFAULT_DT,
    Scene,
    SceneError,
    default_current_index,
    drop_impossible_jumps,
)
from counterscene_env.scene.safe_pickle import ALLOWED_GLOBALS, UnsafePickleError, safe_load
from counterscene_env.scene.scenarionet_map import MapError, road_from_features
from counterscene_env.scene.scenarionet_tracks import DEFAULT_BOX, ScenarioNetError, read_tracks
from counterscene_env.scene.timebase import TimeGrid, time_grid

__all__ = [
    "ALLOWED_GLOBALS",
    "DEFAULT_BOX",
    "ScenarioNetError",
    "UnsafePickleError",
    "load_scenarionet",
    "read_scenario_description",
    "scene_from_description",
]


# ---------------------------------------------------------------------- public API
def read_scenario_description(path: str | os.PathLike) -> dict:
    """Safely unpickle a ScenarioNet file and check its top-level layout.

    Returns:
        The scenario dict with at least ``metadata``, ``tracks`` and ``map_features`` (dicts).

    Raises:
        UnsafePickleError: the pickle names a global outside :data:`ALLOWED_GLOBALS`.
        ScenarioNetError: the file is unreadable, not a pickle, truncated, or not a scenario.
    """
    path = Path(path)
    try:
        with path.open("rb") as f:
            data = safe_load(f)
    except UnsafePickleError as exc:
        raise UnsafePickleError(f"{path}: {exc}") from None
    except OSError as exc:
        raise ScenarioNetError(f"{path}: cannot read file ({exc})") from exc
    except Exception as exc:  # any unpickling failure: not a pickle, truncated, bad numpy data
        raise ScenarioNetError(
            f"{path}: not a readable pickle ({type(exc).__name__}: {exc})"
        ) from exc
    if not isinstance(data, dict):
        raise ScenarioNetError(
            f"{path}: expected a scenario dict at the top level, got {type(data).__name__}"
        )
    for key in ("metadata", "tracks", "map_features"):
        if key not in data:
            raise ScenarioNetError(f"{path}: missing top-level field {key!r}")
        if not isinstance(data[key], Mapping):
            raise ScenarioNetError(
                f"{path}: field {key!r} must be a dict, got {type(data[key]).__name__}"
            )
    return data


#: The index files ScenarioNet writes into every dataset directory beside the scenarios.
INDEX_FILES = ("dataset_summary.pkl", "dataset_mapping.pkl")


def _refuse_counterscene_data(path: Path) -> None:
    """Raise :class:`ScenarioNetError` naming ``path`` if it is a CounterScene dataset
    directory (it holds a ``manifest.json``) or shard (``.npz``), which ``counterscene
    generate`` wrote: those are read as datasets, and a ScenarioNet source given one would
    otherwise read it as if it were logs (or find no ``.pkl`` in it)."""
    from counterscene_env.scene.manifest import MANIFEST

    if path.is_dir() and (path / MANIFEST).is_file():
        what = f"a CounterScene dataset directory (its {MANIFEST}: made by counterscene generate)"
    elif path.is_file() and path.suffix == ".npz":
        what = "a CounterScene shard file (.npz: made by counterscene generate)"
    else:
        return
    raise ScenarioNetError(
        f"{path} is {what}, not ScenarioNet data: it is read as a dataset as it is (--data "
        f"{path}, or --scenario {path} without 'scenarionet:')"
    )


def scenarionet_files(path: str | os.PathLike) -> list[Path]:
    """The scenario files of a ScenarioNet ``.pkl`` file or dataset directory.

    A directory's ``dataset_mapping.pkl`` (scenario file name -> its directory, relative to
    the dataset) lists them, as ScenarioNet's readers use it: a merged dataset holds only
    the index files and points into the datasets it merged. Without one, every ``*.pkl``
    under the directory (sorted, recursively) but the index files.

    Raises:
        FileNotFoundError: no scenario file, or one the mapping lists is missing.
        ScenarioNetError: the mapping is not a dict of file names to directories, or ``path``
            is a CounterScene dataset directory or shard (:func:`_refuse_counterscene_data`).
    """
    path = Path(path)
    _refuse_counterscene_data(path)
    if not path.is_dir():
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such ScenarioNet file or directory")
        return [path]
    mapping_file = path / "dataset_mapping.pkl"
    if mapping_file.is_file():
        try:
            with mapping_file.open("rb") as f:
                mapping = safe_load(f)
        except Exception as exc:
            raise ScenarioNetError(f"{mapping_file}: not a readable mapping ({exc})") from None
        if not isinstance(mapping, dict) or not all(
            isinstance(k, str) and isinstance(v, str) for k, v in mapping.items()
        ):
            raise ScenarioNetError(f"{mapping_file}: not a dict of file names to directories")
        files = sorted(path / rel / name for name, rel in mapping.items())
        missing = [f for f in files if not f.is_file()]
        if missing:
            raise FileNotFoundError(
                f"{mapping_file} lists {len(missing)} file(s) that are not there, e.g. {missing[0]}"
            )
    else:
        files = sorted(f for f in path.rglob("*.pkl") if f.name not in INDEX_FILES)
    if not files:
        raise FileNotFoundError(f"{path}: no dataset manifest, and no ScenarioNet .pkl files")
    return files


def load_scenarionet(path: str | os.PathLike, current_index: int | None = None) -> Scene:
    """Load a ScenarioNet scenario pickle as a 10 Hz :class:`Scene`.

    Args:
        path: a ScenarioNet ``*.pkl`` scenario file.
        current_index: the "now" step of the returned scene (in 10 Hz steps, on the 0.1 s
            grid); None: 30 (3 s of history), or for a short log the last step but one if
            that leaves 1 s of history (``core.default_current_index``).

    Returns:
        A scene with the ego at row 0, ``dt = 0.1`` s, ``positions`` ``[N, T, 2]`` m,
        ``yaws`` ``[N, T]`` rad, ``speeds`` ``[N, T]`` m/s, ``extents`` ``[N, 2]`` m, and a
        :class:`RoadMap` built from the file's map features (``scene/scenarionet_map.py``).

    Raises:
        UnsafePickleError: the file is a pickle that names anything but numpy arrays.
        ScenarioNetError: the file is malformed; the message names the file and the field.
    """
    path = Path(path)
    sd = read_scenario_description(path)
    try:
        return scene_from_description(sd, source=str(path), current_index=current_index)
    except SceneError:
        raise
    except (TypeError, ValueError, KeyError, IndexError, AttributeError, OverflowError) as exc:
        # A field of a type or shape the checks above did not foresee: still the file's fault,
        # and said so with the file's name rather than a traceback.
        raise ScenarioNetError(f"{path}: malformed scenario ({type(exc).__name__}: {exc})") from exc


def scene_from_description(
    sd: Mapping[str, Any], source: str = "<memory>", current_index: int | None = None
) -> Scene:
    """Convert an already loaded ScenarioNet scenario dict (see :func:`load_scenarionet`).

    Args:
        sd: the scenario description (``metadata``, ``tracks``, ``map_features``).
        source: the file name, used in error messages and ``metadata["source_file"]``.
        current_index: the "now" step, in 10 Hz steps (None: see :func:`load_scenarionet`).
    """
    for key in ("metadata", "tracks", "map_features"):
        if not isinstance(sd.get(key), Mapping):
            raise ScenarioNetError(f"{source}: missing or non-dict top-level field {key!r}")
    meta = sd["metadata"]
    tracks = read_tracks(sd["tracks"], meta, source)
    grid = _time_grid(meta, tracks.num_source_steps, source)
    positions, yaws, speeds, valid = grid.apply(
        tracks.position, tracks.heading, tracks.velocity, tracks.valid
    )
    num_steps = positions.shape[1]
    if current_index is None:
        current_index = default_current_index(num_steps, source)
    if not 0 <= current_index < num_steps:
        raise ScenarioNetError(
            f"{source}: current_index {current_index} outside the log's {num_steps} steps at 10 Hz"
        )
    # A corrupt position (a jump no road user makes) costs its track's steps, not the scene.
    valid, jumped = drop_impossible_jumps(positions, valid, DEFAULT_DT)
    for row, n in jumped.items():
        tracks.repair(tracks.ids[row], f"{n} steps after an impossible jump made invalid")
    tracks.drop_empty(valid)
    keep = np.array([i for i, k in enumerate(tracks.ids) if k not in tracks.dropped], dtype=int)
    dataset = str(meta.get("dataset", ""))
    try:
        road, map_summary = road_from_features(sd["map_features"], source)
    except MapError as exc:
        raise ScenarioNetError(str(exc)) from exc
    types = [tracks.types[i] for i in keep]
    counts = {t: types.count(t) for t in ("vehicle", "pedestrian", "cyclist", "other")}
    metadata = {
        "dataset": dataset,
        "source_file": Path(source).name,
        "map": str(meta.get("map", "")),
        "num_tracks": counts,
        "dropped_tracks": tracks.dropped,
        "repairs": tracks.repairs,
        "source_dt": grid.source_dt,
        "resampled": grid.interpolated,
        "map_features": map_summary,
    }
    scenario_id = str(meta.get("scenario_id", sd.get("id", Path(source).stem)))
    try:
        return Scene(
            positions=positions[keep],
            yaws=yaws[keep],
            speeds=speeds[keep],
            extents=tracks.extents[keep],
            valid=valid[keep],
            agent_types=np.array(types),
            agent_ids=np.array([tracks.ids[i] for i in keep]),
            ego_index=0,
            road=road,
            dt=DEFAULT_DT,
            scenario_id=scenario_id,
            current_index=current_index,
            metadata=metadata,
        )
    except ScenarioNetError:
        raise
    except SceneError as exc:
        raise ScenarioNetError(f"{source}: {exc}") from exc


# ---------------------------------------------------------------------- time base
def _time_grid(meta: Mapping[str, Any], num_frames: int, source: str) -> TimeGrid:
    """The exact 0.1 s grid over the log's frames (``scene/timebase.py``)."""
    if num_frames < 2:
        raise ScenarioNetError(f"{source}: the log has {num_frames} frame; a scene needs two")
    times, field_name = _frame_times(meta, num_frames, source)
    try:
        return time_grid(times, f"{source}: {field_name}")
    except SceneError as exc:
        raise ScenarioNetError(str(exc)) from None


def _frame_times(meta: Mapping[str, Any], num_frames: int, source: str) -> tuple[np.ndarray, str]:
    """``[T_src]`` s frame times from ``metadata.ts`` (one per frame) or ``sample_rate``."""
    ts = meta.get("ts")
    if ts is not None:
        try:
            times = np.asarray(ts, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            raise ScenarioNetError(f"{source}: metadata.ts is not numeric") from None
        if times.size == num_frames and num_frames >= 2 and np.isfinite(times).all():
            return times, "metadata.ts"
    rate = meta.get("sample_rate")
    if rate is None:
        if ts is None:
            raise ScenarioNetError(f"{source}: missing metadata.sample_rate (and metadata.ts)")
        raise ScenarioNetError(
            f"{source}: metadata.ts has {np.size(ts)} timestamps for {num_frames} frames "
            "and there is no metadata.sample_rate"
        )
    try:
        rate = float(rate)
    except (TypeError, ValueError):
        raise ScenarioNetError(
            f"{source}: metadata.sample_rate must be a number, got {rate!r}"
        ) from None
    if not (np.isfinite(rate) and rate > 0):
        raise ScenarioNetError(f"{source}: metadata.sample_rate gives a step of {rate} s")
    return np.arange(num_frames) * rate, "metadata.sample_rate"
