"""Import one ScenarioNet scenario pickle (nuScenes, Waymo, ...) as a :class:`Scene`.

One job: turn a ScenarioNet "scenario description" file into the scene contract
(:class:`~counterscene_env.scene.core.Scene`), tracks and map included.

Safety policy
-------------
The files are Python pickles, and unpickling an untrusted pickle can run arbitrary code. They
are never read with the standard loader: :class:`_SafeUnpickler` resolves only the globals in
:data:`ALLOWED_GLOBALS`, an exact ``(module, name)`` allowlist of numpy's data-only
reconstruction helpers (``_reconstruct``, ``ndarray``, ``dtype``; ``scalar`` for numpy scalars
and ``_frombuffer`` for protocol-5 arrays), each under both its numpy-1 (``numpy.core``) and
numpy-2 (``numpy._core``) spelling. Every other global (``os.system``, ``builtins.eval``,
``subprocess.Popen``, any class) raises :class:`UnsafePickleError` *before* anything is called,
so nothing in a hostile file runs. Persistent ids are refused too, and the one Python-level
helper (``_frombuffer``) is handed out sealed so that a BUILD opcode cannot rewrite its
attributes for the whole process. The ten nuScenes-mini files (protocol 4) name exactly
``numpy.core.multiarray._reconstruct``, ``numpy.ndarray`` and ``numpy.dtype`` (checked with
``pickletools``); their dicts, lists, sets and tuples are pickle opcodes, so no ``builtins``
name is allowed at all. Protocols 3 to 5 load; protocol 2 would need ``_codecs.encode`` for
bytes and is refused. Unpickling can still allocate memory (a file may describe a huge array);
it cannot execute code.

Tracks
------
``VEHICLE``/``PEDESTRIAN``/``CYCLIST`` map to ``"vehicle"``/``"pedestrian"``/``"cyclist"``;
every other type (``TRAFFIC_CONE``, ``TRAFFIC_BARRIER``, ...) becomes ``"other"`` and is kept
for collision checks. Tracks with no valid step are dropped. The ego (``metadata["sdc_id"]``)
is row 0, the other tracks follow in file order. Speed is the norm of the logged velocity,
negative where it points backwards relative to the heading (a reversing car)
(m/s); extents are the median (length, width) over valid steps, and any vehicle whose length
is below its width (the nuScenes ego box is stored as 1.73 x 4.08) gets the two swapped; the
ids so fixed are listed in ``scene.metadata["swapped_extents"]``. Logs must be at 10 Hz or at
an exact integer multiple of it (subsampled exactly, e.g. 20 Hz -> every 2nd frame).

Map choices
-----------
Lanes are the ``LANE_*`` features except ``LANE_BIKE_LANE``. Each becomes a highway-env
``PolyLaneFixedWidth`` lane via :meth:`RoadMap.from_centerlines`. Width: the ``width`` field
where present (an array is reduced to the median of its per-point total, left + right),
else the lane polygon's area over the centre-line length, else 3.5 m; the first two are
clipped to [2.5, 6] m. Connectivity: ``exit_lanes`` (and the reverse of ``entry_lanes``) where
the file carries them; the nuScenes files carry neither, but their lanes and lane connectors
meet at bit-identical end points, so without those fields a lane's successors are the lanes
starting within :data:`CONNECT_TOLERANCE` of its end.

Drivable area: the union of the lane polygons (nuScenes lanes) and, for lanes without one
(nuScenes lane connectors, which are what crosses the intersections), the centre line buffered
by half the lane width. Beyond that only ``DRIVEWAY`` polygons (Waymo) are added. The nuScenes
files contain no other drivable surface (their non-lane features are only ``ROAD_LINE_*``
dividers, which lie inside the lanes; no road edges, road segments or intersection polygons),
and ``ROAD_EDGE_*`` polylines elsewhere are open boundaries that do not close into reliable
polygons, so they are not used. Interior holes of the union smaller than
:data:`HOLE_FILL_AREA` (50 m^2) are filled: in the nuScenes files the ~520 holes under 10 m^2
(and most up to ~40 m^2) are slivers between the lane polygons and the buffered connectors
inside junctions, which traffic crosses (the logged ego left the unfilled area at some frames
of scene-0757); larger holes are medians, gore areas, blocks and parking-lot islands with
parked cars, which stay off the drivable area. Parking lots, and roads beyond the map crop,
are not in the files at all, so parked and far vehicles legitimately lie outside the area.
"""

from __future__ import annotations

import os
import pickle
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import shapely

from counterscene_env.geometry import wrap_angle
from counterscene_env.scene.core import DEFAULT_DT, Scene, SceneError, drop_impossible_jumps
from counterscene_env.scene.road import RoadMap

try:  # numpy >= 2 spelling first
    from numpy._core.multiarray import _reconstruct, scalar
    from numpy._core.numeric import _frombuffer
except ImportError:  # pragma: no cover - older numpy
    from numpy.core.multiarray import _reconstruct, scalar
    from numpy.core.numeric import _frombuffer

__all__ = [
    "ALLOWED_GLOBALS",
    "ScenarioNetError",
    "UnsafePickleError",
    "load_scenarionet",
    "read_scenario_description",
    "scene_from_description",
]


class ScenarioNetError(SceneError):
    """A ScenarioNet file is malformed; the message names the file and the field."""


class UnsafePickleError(SceneError):
    """A pickle named a global outside :data:`ALLOWED_GLOBALS` (or a persistent id)."""


class _Sealed:
    """A callable stand-in for a Python-level helper that a pickle's BUILD opcode cannot alter.

    Built-in functions and types reject attribute writes by themselves; a plain Python function
    does not (BUILD could rewrite numpy's own ``_frombuffer.__defaults__`` for the whole
    process), so such helpers are handed out behind this wrapper instead.
    """

    __slots__ = ("_fn",)

    def __init__(self, fn: Any) -> None:
        object.__setattr__(self, "_fn", fn)

    def __call__(self, *args: Any) -> Any:
        return self._fn(*args)

    def __setattr__(self, name: str, value: Any) -> None:
        raise UnsafePickleError(f"refused attribute write {name!r} on an allowed global")


#: The only globals a ScenarioNet pickle may name: ``(module, name)`` -> object. All of them
#: build numpy arrays, dtypes or scalars from plain data and cannot run code.
ALLOWED_GLOBALS: dict[tuple[str, str], Any] = {
    ("numpy", "ndarray"): np.ndarray,
    ("numpy", "dtype"): np.dtype,
    ("numpy.core.multiarray", "_reconstruct"): _reconstruct,
    ("numpy._core.multiarray", "_reconstruct"): _reconstruct,
    ("numpy.core.multiarray", "scalar"): scalar,
    ("numpy._core.multiarray", "scalar"): scalar,
    ("numpy.core.numeric", "_frombuffer"): _Sealed(_frombuffer),
    ("numpy._core.numeric", "_frombuffer"): _Sealed(_frombuffer),
}

#: Agent type of each ScenarioNet track type; anything else is ``"other"``.
TRACK_TYPES = {"VEHICLE": "vehicle", "PEDESTRIAN": "pedestrian", "CYCLIST": "cyclist"}

DEFAULT_LANE_WIDTH = 3.5  # [m] lanes with neither a width field nor a polygon
LANE_WIDTH_RANGE = (2.5, 6.0)  # [m] clip for widths read or estimated from the file
CONNECT_TOLERANCE = 0.1  # [m] end-to-start gap under which two lanes are joined
HOLE_FILL_AREA = 50.0  # [m^2] interior holes of the drivable area below this are filled
_SAMPLE_RATE_TOL = 1e-6  # [s]


class _SafeUnpickler(pickle.Unpickler):
    """An unpickler that resolves only :data:`ALLOWED_GLOBALS` and no persistent ids."""

    def find_class(self, module: str, name: str) -> Any:
        try:
            return ALLOWED_GLOBALS[(module, name)]
        except (KeyError, TypeError):
            raise UnsafePickleError(
                f"refused global {module}.{name}: a ScenarioNet pickle may only name numpy's "
                f"array reconstruction helpers (see ALLOWED_GLOBALS)"
            ) from None

    def persistent_load(self, pid: Any) -> Any:
        raise UnsafePickleError(f"refused persistent id {pid!r}: not used by ScenarioNet pickles")


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
            data = _SafeUnpickler(f).load()
    except UnsafePickleError as exc:
        raise UnsafePickleError(f"{path.name}: {exc}") from None
    except OSError as exc:
        raise ScenarioNetError(f"{path}: cannot read file ({exc})") from exc
    except Exception as exc:  # any unpickling failure: not a pickle, truncated, bad numpy data
        raise ScenarioNetError(
            f"{path.name}: not a readable pickle ({type(exc).__name__}: {exc})"
        ) from exc
    if not isinstance(data, dict):
        raise ScenarioNetError(
            f"{path.name}: expected a scenario dict at the top level, got {type(data).__name__}"
        )
    for key in ("metadata", "tracks", "map_features"):
        if key not in data:
            raise ScenarioNetError(f"{path.name}: missing top-level field {key!r}")
        if not isinstance(data[key], Mapping):
            raise ScenarioNetError(
                f"{path.name}: field {key!r} must be a dict, got {type(data[key]).__name__}"
            )
    return data


def load_scenarionet(path: str | os.PathLike, current_index: int = 30) -> Scene:
    """Load a ScenarioNet scenario pickle as a 10 Hz :class:`Scene`.

    Args:
        path: a ScenarioNet ``*.pkl`` scenario file.
        current_index: the "now" step of the returned scene (in 10 Hz steps, after any
            subsampling); 30 gives 3 s of history.

    Returns:
        A scene with the ego at row 0, ``dt = 0.1`` s, ``positions`` ``[N, T, 2]`` m,
        ``yaws`` ``[N, T]`` rad, ``speeds`` ``[N, T]`` m/s, ``extents`` ``[N, 2]`` m, and a
        :class:`RoadMap` built from the file's lanes (see the module docstring).

    Raises:
        UnsafePickleError: the file is a pickle that names anything but numpy arrays.
        ScenarioNetError: the file is malformed; the message names the file and the field.
    """
    path = Path(path)
    sd = read_scenario_description(path)
    try:
        return scene_from_description(sd, source=path.name, current_index=current_index)
    except SceneError:
        raise
    except (TypeError, ValueError, KeyError, IndexError, AttributeError, OverflowError) as exc:
        # A field of a type or shape the checks above did not foresee: still the file's fault,
        # and said so with the file's name rather than a traceback.
        raise ScenarioNetError(
            f"{path.name}: malformed scenario ({type(exc).__name__}: {exc})"
        ) from exc


def scene_from_description(
    sd: Mapping[str, Any], source: str = "<memory>", current_index: int = 30
) -> Scene:
    """Convert an already loaded ScenarioNet scenario dict (see :func:`load_scenarionet`).

    Args:
        sd: the scenario description (``metadata``, ``tracks``, ``map_features``).
        source: the file name, used in error messages and ``metadata["source_file"]``.
        current_index: the "now" step, in 10 Hz steps.
    """
    for key in ("metadata", "tracks", "map_features"):
        if not isinstance(sd.get(key), Mapping):
            raise ScenarioNetError(f"{source}: missing or non-dict top-level field {key!r}")
    meta = sd["metadata"]
    stem = Path(source).stem
    scenario_id = str(meta.get("scenario_id", sd.get("id", stem)))
    step = _subsample_factor(meta, source)

    ids, types, positions, yaws, speeds, valids, extents, swapped, dropped = _read_tracks(
        sd["tracks"], meta, source, step
    )
    num_steps = positions.shape[1]
    if not 0 <= current_index < num_steps:
        raise ScenarioNetError(
            f"{source}: current_index {current_index} outside the log's {num_steps} steps at 10 Hz"
        )
    road, num_lanes = _read_map(sd["map_features"], source)
    # A corrupt position (a jump no road user makes) costs its track's steps, not the scene.
    valids, repaired = drop_impossible_jumps(positions, valids, DEFAULT_DT)
    positions = np.where(valids[..., None], positions, 0.0)

    counts = {t: int(sum(1 for x in types if x == t)) for t in ("vehicle", "pedestrian", "cyclist")}
    counts["other"] = len(types) - sum(counts.values())
    metadata = {
        "dataset": str(meta.get("dataset", "")),
        "source_file": Path(source).name,
        "map": str(meta.get("map", "")),
        "num_tracks": counts,
        "dropped_tracks": dropped,
        "swapped_extents": swapped,
        "source_dt": round(DEFAULT_DT / step, 9),
        "subsample": step,
        "num_lanes": num_lanes,
        "repaired_tracks": {ids[row]: n for row, n in repaired.items()},
    }
    try:
        return Scene(
            positions=positions,
            yaws=yaws,
            speeds=speeds,
            extents=extents,
            valid=valids,
            agent_types=np.array(types),
            agent_ids=np.array(ids),
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
def _subsample_factor(meta: Mapping[str, Any], source: str) -> int:
    """How many source frames make one 0.1 s step (1 for 10 Hz logs, 2 for 20 Hz, ...)."""
    if meta.get("sample_rate") is not None:
        try:
            rate = float(meta["sample_rate"])
        except (TypeError, ValueError):
            raise ScenarioNetError(
                f"{source}: metadata.sample_rate must be a number, got {meta['sample_rate']!r}"
            ) from None
        field_name = "metadata.sample_rate"
    elif meta.get("ts") is not None:
        ts = np.asarray(meta["ts"], dtype=np.float64).reshape(-1)
        if ts.size < 2:
            raise ScenarioNetError(f"{source}: metadata.ts has fewer than 2 timestamps")
        rate = float(np.median(np.diff(ts)))
        field_name = "metadata.ts"
    else:
        raise ScenarioNetError(f"{source}: missing metadata.sample_rate (and metadata.ts)")
    if not np.isfinite(rate) or rate <= 0:
        raise ScenarioNetError(f"{source}: {field_name} gives a step of {rate} s")
    ratio = DEFAULT_DT / rate
    k = round(ratio)
    if k < 1 or abs(rate * k - DEFAULT_DT) > _SAMPLE_RATE_TOL:
        raise ScenarioNetError(
            f"{source}: {field_name} gives a step of {rate} s; need {DEFAULT_DT} s or an exact "
            f"integer fraction of it"
        )
    return int(k)


# ---------------------------------------------------------------------- tracks
def _read_tracks(
    tracks: Mapping[Any, Any], meta: Mapping[str, Any], source: str, step: int
) -> tuple[
    list[str],
    list[str],
    np.ndarray,
    np.ndarray,
    np.ndarray,
    np.ndarray,
    np.ndarray,
    list[str],
    int,
]:
    """Stack the tracks: ids, types, positions [N,T,2] m, yaws [N,T] rad, speeds [N,T] m/s,
    valid [N,T], extents [N,2] m, the ids whose extents were swapped, the number dropped."""
    sdc = meta.get("sdc_id")
    if sdc is None:
        raise ScenarioNetError(f"{source}: missing metadata.sdc_id (the ego's track id)")
    if sdc not in tracks:
        raise ScenarioNetError(f"{source}: metadata.sdc_id {sdc!r} is not a key of tracks")
    order = [sdc, *(k for k in tracks if k != sdc)]
    num_source_steps = None
    rows: list[tuple[str, str, dict[str, np.ndarray]]] = []
    swapped: list[str] = []
    dropped = 0
    for key in order:
        track = tracks[key]
        if not isinstance(track, Mapping) or not isinstance(track.get("state"), Mapping):
            raise ScenarioNetError(f"{source}: tracks[{key!r}] has no 'state' dict")
        raw_type = str(track.get("type", ""))
        agent_type = TRACK_TYPES.get(raw_type, "other")
        state = _read_state(track["state"], f"{source}: tracks[{key!r}].state")
        t_len = len(state["valid"])
        if num_source_steps is None:
            num_source_steps = t_len
        elif t_len != num_source_steps:
            raise ScenarioNetError(
                f"{source}: tracks[{key!r}].state has {t_len} steps, the ego track {num_source_steps}"
            )
        valid_any = state["valid"]
        if key == sdc:
            if agent_type != "vehicle":
                raise ScenarioNetError(f"{source}: the sdc track {sdc!r} has type {raw_type!r}")
            if not valid_any.any():
                raise ScenarioNetError(f"{source}: the sdc track {sdc!r} has no valid step")
        elif not valid_any.any():
            dropped += 1
            continue
        # Extents over all valid source frames, before subsampling.
        v = state["valid"]
        length = float(np.median(state["length"][v]))
        width = float(np.median(state["width"][v]))
        if not (np.isfinite(length) and np.isfinite(width) and length > 0 and width > 0):
            raise ScenarioNetError(
                f"{source}: tracks[{key!r}] has a bad box (length {length}, width {width}) m"
            )
        if agent_type == "vehicle" and length < width:
            length, width = width, length
            swapped.append(str(key))
        sub = {name: arr[::step] for name, arr in state.items()}
        if not sub["valid"].any():
            if key == sdc:
                raise ScenarioNetError(f"{source}: the sdc track has no valid step at 10 Hz")
            dropped += 1
            continue
        sub["extent"] = np.array([length, width])
        rows.append((str(key), agent_type, sub))
    ids = [r[0] for r in rows]
    if len(set(ids)) != len(ids):
        raise ScenarioNetError(f"{source}: track ids are not unique as strings")
    types = [r[1] for r in rows]
    positions = np.stack([r[2]["position"] for r in rows])
    yaws = np.stack([r[2]["heading"] for r in rows])
    speeds = np.stack([r[2]["speed"] for r in rows])
    valid = np.stack([r[2]["valid"] for r in rows])
    extents = np.stack([r[2]["extent"] for r in rows])
    return ids, types, positions, yaws, speeds, valid, extents, swapped, dropped


def _read_state(state: Mapping[str, Any], where: str) -> dict[str, np.ndarray]:
    """One track's per-step arrays at the source rate: position [T,2] m, heading [T] rad
    (wrapped to [-pi, pi)), speed [T] m/s, valid [T] bool, length/width [T] m."""
    out: dict[str, np.ndarray] = {}
    for name in ("position", "heading", "velocity", "valid", "length", "width"):
        if name not in state:
            raise ScenarioNetError(f"{where}: missing field {name!r}")
        try:
            arr = np.asarray(state[name], dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ScenarioNetError(f"{where}.{name}: not a numeric array ({exc})") from None
        out[name] = arr
    pos, vel = out["position"], out["velocity"]
    if pos.ndim != 2 or pos.shape[1] not in (2, 3):
        raise ScenarioNetError(f"{where}.position: expected shape (T, 2|3), got {pos.shape}")
    t = pos.shape[0]
    if t == 0:
        raise ScenarioNetError(f"{where}.position: no steps")
    if vel.ndim != 2 or vel.shape[0] != t or vel.shape[1] < 2:
        raise ScenarioNetError(f"{where}.velocity: expected shape ({t}, 2), got {vel.shape}")
    flat = {}
    for name in ("heading", "valid", "length", "width"):
        arr = out[name]
        if arr.shape not in ((t,), (t, 1)):
            raise ScenarioNetError(
                f"{where}.{name}: expected shape ({t},) or ({t}, 1), got {arr.shape}"
            )
        flat[name] = arr.reshape(t)
    valid = np.isfinite(flat["valid"]) & (flat["valid"] != 0)
    pos2 = pos[:, :2]
    # Signed speed (the scene contract): the velocity's magnitude, negative where it points
    # backwards relative to the heading (a reversing car). The magnitude, not the projection,
    # so that annotation slip between heading and velocity does not shrink speeds.
    along = vel[:, 0] * np.cos(flat["heading"]) + vel[:, 1] * np.sin(flat["heading"])
    speed = np.where(along < 0, -1.0, 1.0) * np.linalg.norm(vel[:, :2], axis=1)
    for name, arr in (("position", pos2), ("heading", flat["heading"]), ("velocity", speed)):
        if not np.isfinite(arr[valid]).all():
            raise ScenarioNetError(f"{where}.{name}: non-finite values at valid steps")
    heading = np.where(valid, flat["heading"], 0.0)
    heading = wrap_angle(heading)
    return {
        "position": np.where(valid[:, None], pos2, 0.0),
        "heading": heading,
        "speed": np.where(valid, speed, 0.0),
        "valid": valid,
        "length": flat["length"],
        "width": flat["width"],
    }


# ---------------------------------------------------------------------- map
def _read_map(features: Mapping[Any, Any], source: str) -> tuple[RoadMap, int]:
    """Lanes -> RoadMap (network, drivable area, centre lines); returns it and the lane count."""
    keys: list[str] = []
    lines: list[np.ndarray] = []
    polys: list[np.ndarray | None] = []
    widths: list[float] = []
    exits: list[list[str]] = []
    entries: list[list[str]] = []
    has_links = False
    driveways = []
    for key, feat in features.items():
        if not isinstance(feat, Mapping):
            raise ScenarioNetError(f"{source}: map_features[{key!r}] is not a dict")
        ftype = str(feat.get("type", ""))
        where = f"{source}: map_features[{key!r}]"
        if ftype == "DRIVEWAY":
            poly = _points(feat.get("polygon"), f"{where}.polygon", allow_none=True)
            if poly is not None and len(poly) >= 3:
                driveways.append(shapely.make_valid(shapely.Polygon(poly)))
            continue
        if not ftype.startswith("LANE") or ftype == "LANE_BIKE_LANE":
            continue
        line = _points(feat.get("polyline"), f"{where}.polyline")
        if len(line) < 2:
            continue  # a lane needs a direction
        poly = _points(feat.get("polygon"), f"{where}.polygon", allow_none=True)
        if poly is not None and len(poly) < 3:
            poly = None
        keys.append(str(key))
        lines.append(line)
        polys.append(poly)
        widths.append(_lane_width(feat.get("width"), line, poly, f"{where}.width"))
        for field_name, store in (("exit_lanes", exits), ("entry_lanes", entries)):
            links = feat.get(field_name)
            has_links |= links is not None
            store.append([] if links is None else [str(x) for x in np.asarray(links).reshape(-1)])
    if has_links:
        successors = _successors_from_links(keys, exits, entries)
    else:
        successors = _successors_from_geometry(lines)
    road = RoadMap.from_centerlines(lines, widths, polygons=polys, successors=successors)
    area = road.drivable_area
    if driveways:
        area = shapely.union(area, shapely.union_all(driveways))
    area = _fill_small_holes(area, HOLE_FILL_AREA)
    road = RoadMap(road.network, area, road.lane_centerlines, road.lane_widths)
    return road, len(road.lane_centerlines)


def _points(value: Any, where: str, allow_none: bool = False) -> np.ndarray | None:
    """A ``(P, 2|3)`` point list as ``[P, 2]`` float64 m (the third column, z or yaw, dropped)."""
    if value is None:
        if allow_none:
            return None
        raise ScenarioNetError(f"{where}: missing")
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ScenarioNetError(f"{where}: not a numeric array ({exc})") from None
    if arr.ndim != 2 or arr.shape[1] not in (2, 3):
        raise ScenarioNetError(f"{where}: expected shape (P, 2|3), got {arr.shape}")
    arr = arr[:, :2]
    if not np.isfinite(arr).all():
        raise ScenarioNetError(f"{where}: non-finite coordinates")
    return arr


def _lane_width(value: Any, line: np.ndarray, poly: np.ndarray | None, where: str) -> float:
    """Lane width, m: the ``width`` field, else polygon area / centre-line length, else 3.5."""
    lo, hi = LANE_WIDTH_RANGE
    if value is not None:
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ScenarioNetError(f"{where}: not numeric ({exc})") from None
        if arr.ndim == 2:  # per point (left, right) half widths
            arr = arr.sum(axis=1)
        arr = arr.reshape(-1)
        arr = arr[np.isfinite(arr)]
        if arr.size and float(np.median(arr)) > 0:
            return float(np.clip(np.median(arr), lo, hi))
    if poly is not None:
        length = float(np.linalg.norm(np.diff(line, axis=0), axis=1).sum())
        area = float(shapely.make_valid(shapely.Polygon(poly)).area)
        if length > 1e-6 and area > 0:
            return float(np.clip(area / length, lo, hi))
    return DEFAULT_LANE_WIDTH


def _successors_from_links(
    keys: list[str], exits: list[list[str]], entries: list[list[str]]
) -> list[list[int]]:
    """Successor lane indices from ``exit_lanes`` and (reversed) ``entry_lanes`` ids."""
    index = {k: i for i, k in enumerate(keys)}
    succ: list[set[int]] = [set() for _ in keys]
    for i, (ex, en) in enumerate(zip(exits, entries, strict=True)):
        for other in ex:
            j = index.get(other)
            if j is not None and j != i:
                succ[i].add(j)
        for other in en:
            j = index.get(other)
            if j is not None and j != i:
                succ[j].add(i)
    return [sorted(s) for s in succ]


def _successors_from_geometry(lines: list[np.ndarray]) -> list[list[int]]:
    """Lane j continues lane i where j starts within CONNECT_TOLERANCE of i's end."""
    if not lines:
        return []
    starts = shapely.points(np.array([line[0] for line in lines]))
    ends = shapely.points(np.array([line[-1] for line in lines]))
    tree = shapely.STRtree(starts)
    src, dst = tree.query(ends, predicate="dwithin", distance=CONNECT_TOLERANCE)
    succ: list[list[int]] = [[] for _ in lines]
    for i, j in zip(src.tolist(), dst.tolist(), strict=True):
        if i != j:
            succ[i].append(j)
    return [sorted(s) for s in succ]


def _fill_small_holes(area: shapely.Geometry, max_hole: float) -> shapely.Geometry:
    """The area with every interior ring enclosing less than ``max_hole`` m^2 filled."""
    parts = []
    for poly in getattr(area, "geoms", [area]):
        if poly.geom_type != "Polygon" or poly.is_empty:
            continue
        holes = [r for r in poly.interiors if shapely.Polygon(r).area >= max_hole]
        parts.append(shapely.Polygon(poly.exterior, holes))
    if not parts:
        return area
    return shapely.union_all(parts)
