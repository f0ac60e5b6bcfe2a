"""Scenes on disk: compressed shards of several scenes, readable without pickle.

A shard is one ``.npz`` file (``numpy.savez_compressed``; read with ``allow_pickle=False``):

========================  ============================================================
key                       content
========================  ============================================================
``format``                JSON: ``{"format": "counterscene-shard", "version": 1, "num_scenes": n}``
``{i}/positions``         ``[N, T, 2]`` float64, m
``{i}/yaws``              ``[N, T]`` float64, rad
``{i}/speeds``            ``[N, T]`` float64, m/s
``{i}/extents``           ``[N, 2]`` float64, m
``{i}/valid``             ``[N, T]`` bool
``{i}/agent_types``       ``[N]`` str
``{i}/agent_ids``         ``[N]`` str
``{i}/meta``              JSON: ego_index, dt, scenario_id, current_index, metadata
``{i}/road_network``      JSON: the highway-env lanes (class name + arguments, see road_json.py)
``{i}/road_area``         uint8 WKB of the drivable area
``{i}/road_lines``        ``[sum P, 2]`` float64 lane centre points, m
``{i}/road_offsets``      ``[L + 1]`` int64, where each centre line starts in ``road_lines``
``{i}/road_widths``       ``[L]`` float64, m
``{i}/road_extent``       uint8 WKB of the map's extent (optional: absent means the whole plane)
``{i}/road_priorities``   ``[L]`` float64 right of way of each centre line's lane (optional:
                          absent, in shards written before it existed, it is read from the
                          network's lanes)
========================  ============================================================

Writes are atomic (temporary file, then rename), so an interrupted run never leaves a shard
that looks complete. A truncated or corrupt file, or one written by a newer format version,
raises :class:`ShardError` naming the file and the problem.
"""

from __future__ import annotations

import itertools
import json
import os
import zipfile
import zlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import shapely

from counterscene_env.scene.core import Scene, SceneError
from counterscene_env.scene.road import RoadMap
from counterscene_env.scene.road_json import network_from_json, network_to_json

SHARD_FORMAT = "counterscene-shard"
SHARD_VERSION = 1

_STATE_FIELDS = ("positions", "yaws", "speeds", "extents", "valid", "agent_types", "agent_ids")


class ShardError(SceneError):
    """A shard file that cannot be read: truncated, corrupt, foreign or from a newer version."""


def save_scenes(scenes: Sequence[Scene], path: str | os.PathLike) -> Path:
    """Write scenes to one compressed shard at ``path`` (atomically). Returns the path."""
    path = Path(path)
    arrays: dict[str, np.ndarray] = {
        "format": _json_array(
            {"format": SHARD_FORMAT, "version": SHARD_VERSION, "num_scenes": len(scenes)}
        )
    }
    for i, scene in enumerate(scenes):
        for name in _STATE_FIELDS:
            arrays[f"{i}/{name}"] = getattr(scene, name)
        arrays[f"{i}/meta"] = _json_array(
            {
                "ego_index": scene.ego_index,
                "dt": scene.dt,
                "scenario_id": scene.scenario_id,
                "current_index": scene.current_index,
                "metadata": scene.metadata,
            }
        )
        road = scene.road
        lines = road.lane_centerlines
        arrays[f"{i}/road_network"] = np.array(network_to_json(road.network))
        arrays[f"{i}/road_area"] = np.frombuffer(shapely.to_wkb(road.drivable_area), np.uint8)
        arrays[f"{i}/road_lines"] = np.concatenate(lines) if lines else np.zeros((0, 2))
        arrays[f"{i}/road_offsets"] = np.cumsum([0] + [len(c) for c in lines]).astype(np.int64)
        arrays[f"{i}/road_widths"] = road.lane_widths
        arrays[f"{i}/road_priorities"] = road.lane_priorities
        if road.extent is not None:
            arrays[f"{i}/road_extent"] = np.frombuffer(shapely.to_wkb(road.extent), np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    # A plain open() (not mkstemp, which makes 0600 files) so the shard gets the usual umask.
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def load_scenes(path: str | os.PathLike) -> list[Scene]:
    """Read every scene of a shard written by :func:`save_scenes`."""
    path = Path(path)
    if path.is_dir():
        raise ShardError(
            f"{path}: a directory without a dataset manifest (make one with counterscene "
            "generate; a shard is a .npz file)"
        )
    if not path.is_file():
        raise ShardError(f"{path}: no such shard file")
    _refuse_other_files(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            header = _read_json(data, "format", path)
            if header.get("format") != SHARD_FORMAT:
                raise ShardError(
                    f"{path}: not a CounterScene shard (format={header.get('format')!r})"
                )
            version = int(header.get("version", -1))
            if version > SHARD_VERSION:
                raise ShardError(
                    f"{path}: shard format version {version} is newer than this counterscene_env "
                    f"reads ({SHARD_VERSION}); upgrade counterscene-env"
                )
            if version < 1:
                raise ShardError(f"{path}: invalid shard format version {version}")
            return [_read_scene(data, i, path) for i in range(int(header["num_scenes"]))]
    except ShardError:
        raise
    except (
        zipfile.BadZipFile,
        zlib.error,
        EOFError,
        OSError,
        ValueError,
        KeyError,
        TypeError,
        AttributeError,
        IndexError,
        OverflowError,
        shapely.errors.ShapelyError,
    ) as exc:
        raise ShardError(
            f"{path}: truncated or corrupt shard ({type(exc).__name__}: {exc})"
        ) from exc


#: The first bytes of a zip archive (a shard is one: ``numpy.savez_compressed``), and of a
#: pickle of protocol 2 and later (the PROTO opcode, then the protocol).
_ZIP_MAGIC = b"PK"
_PICKLE_MAGIC = (b"\x80\x02", b"\x80\x03", b"\x80\x04", b"\x80\x05")


def _refuse_other_files(path: Path) -> None:
    """Raise :class:`ShardError` naming ``path`` when it is a pickle (a ScenarioNet log, say),
    or a file neither a zip nor named ``.npz``: not a shard, whatever numpy would say of it
    (its message on a pickle is how to load it unsafely). Nothing is unpickled; a damaged
    ``.npz`` is left to the reader's "truncated or corrupt"."""
    with path.open("rb") as f:
        head = f.read(2)
    if head in _PICKLE_MAGIC:
        raise ShardError(
            f"{path}: a Python pickle, not a CounterScene dataset directory or shard .npz (not "
            "unpickled). ScenarioNet .pkl logs are named as such (evaluate-model --scenarionet, "
            "stress --scenario scenarionet:DIR) or converted into a dataset: counterscene "
            "generate --from-scenarionet DIR --out DATASET"
        )
    if head != _ZIP_MAGIC and path.suffix != ".npz":
        raise ShardError(
            f"{path}: not a CounterScene dataset directory or shard .npz (give a directory made "
            "by counterscene generate, or one of its shard files)"
        )


def _read_scene(data, i: int, path: Path) -> Scene:
    def get(name: str) -> np.ndarray:
        key = f"{i}/{name}"
        if key not in data.files:
            raise ShardError(f"{path}: scene {i} lacks the field {name!r}")
        return data[key]

    meta = _read_json(data, f"{i}/meta", path)
    lines, offsets = get("road_lines"), get("road_offsets")
    road = RoadMap(
        network=network_from_json(str(get("road_network"))),
        drivable_area=shapely.from_wkb(get("road_area").tobytes()),
        lane_centerlines=[lines[a:b] for a, b in itertools.pairwise(offsets)],
        lane_widths=get("road_widths"),
        extent=(
            shapely.from_wkb(data[f"{i}/road_extent"].tobytes())
            if f"{i}/road_extent" in data.files
            else None
        ),
        lane_priorities=(
            data[f"{i}/road_priorities"] if f"{i}/road_priorities" in data.files else None
        ),
    )
    return Scene(
        **{name: get(name) for name in _STATE_FIELDS},
        ego_index=meta["ego_index"],
        road=road,
        dt=meta["dt"],
        scenario_id=meta["scenario_id"],
        current_index=meta["current_index"],
        metadata=meta.get("metadata", {}),
    )


def _json_array(obj) -> np.ndarray:
    return np.array(json.dumps(obj))


def _read_json(data, key: str, path: Path) -> dict:
    if key not in data.files:
        raise ShardError(f"{path}: missing {key!r}; not a CounterScene shard")
    return json.loads(str(data[key]))
