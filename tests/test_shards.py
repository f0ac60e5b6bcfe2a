"""Scenes on disk: round trip, and clear errors for truncated, foreign and newer files."""

from __future__ import annotations

import json

import numpy as np
import pytest
import shapely

from counterscene_env.scene import load_scenes, save_scenes
from counterscene_env.scene.shards import SHARD_VERSION, ShardError


def test_round_trip_is_exact(tmp_path, generated):
    scenes = [generated["roundabout"], generated["merge"]]
    path = save_scenes(scenes, tmp_path / "s.npz")
    back = load_scenes(path)
    assert len(back) == 2
    for a, b in zip(scenes, back, strict=True):
        for field in (
            "positions",
            "yaws",
            "speeds",
            "extents",
            "valid",
            "agent_types",
            "agent_ids",
        ):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
        assert (a.ego_index, a.dt, a.scenario_id, a.current_index) == (
            b.ego_index,
            b.dt,
            b.scenario_id,
            b.current_index,
        )
        assert a.metadata == b.metadata
        assert shapely.equals_exact(a.road.drivable_area, b.road.drivable_area, tolerance=0)
        assert len(a.road.network.lanes_list()) == len(b.road.network.lanes_list())
        for la, lb in zip(a.road.lane_centerlines, b.road.lane_centerlines, strict=True):
            np.testing.assert_array_equal(la, lb)
    assert not list(tmp_path.glob(".*.tmp")), "no temporary file left behind"


def test_truncated_shard_raises_a_clear_error(tmp_path, generated):
    path = save_scenes([generated["merge"]], tmp_path / "s.npz")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(ShardError, match="truncated or corrupt"):
        load_scenes(path)


def test_newer_format_version_is_refused(tmp_path, generated):
    path = save_scenes([generated["merge"]], tmp_path / "s.npz")
    with np.load(path) as d:
        arrays = {k: d[k] for k in d.files}
    arrays["format"] = np.array(
        json.dumps({"format": "counterscene-shard", "version": SHARD_VERSION + 1, "num_scenes": 1})
    )
    np.savez_compressed(path, **arrays)
    with pytest.raises(ShardError, match="newer"):
        load_scenes(path)


def test_foreign_and_missing_files(tmp_path):
    np.savez_compressed(tmp_path / "other.npz", x=np.zeros(3))
    with pytest.raises(ShardError, match="not a CounterScene shard"):
        load_scenes(tmp_path / "other.npz")
    with pytest.raises(ShardError, match="no such shard"):
        load_scenes(tmp_path / "missing.npz")
    with pytest.raises(ShardError, match="a directory without a dataset manifest"):
        load_scenes(tmp_path)  # a stress run's directory, say
    (tmp_path / "text.npz").write_text("hello")
    with pytest.raises(ShardError, match="truncated or corrupt"):
        load_scenes(tmp_path / "text.npz")


def test_object_arrays_are_never_unpickled(tmp_path, generated):
    # np.savez pickles object arrays; the reader must refuse them rather than unpickle.
    path = save_scenes([generated["merge"]], tmp_path / "s.npz")
    with np.load(path) as d:
        arrays = {k: d[k] for k in d.files}
    arrays["0/yaws"] = np.array([{"x": 1}], dtype=object)
    np.savez(path, **arrays)
    with pytest.raises(ShardError, match="truncated or corrupt"):
        load_scenes(path)


def test_shards_are_readable_by_others_like_any_file(tmp_path, generated):
    import os

    path = save_scenes([generated["merge"]], tmp_path / "s.npz")
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask


def test_polyline_lanes_survive_a_round_trip_exactly(tmp_path):
    # highway-env serialises a polyline lane as its 1 m resampling, which cannot rebuild a lane
    # under 2 m (nuScenes' shortest is 1.4 m) and moves lane ends; we keep the source points.
    from conftest import make_scene

    from counterscene_env.scene import RoadMap

    short = np.array([[0.0, 0.0], [1.4, 0.0]])
    bent = np.array([[1.4, 0.0], [10.0, 0.3], [20.25, 4.0]])
    road = RoadMap.from_centerlines([short, bent], [3.5, 3.5], successors=[[1], []])
    scene = make_scene(np.zeros((1, 3, 2)), road=road)
    back = load_scenes(save_scenes([scene], tmp_path / "s.npz"))[0].road.network
    for a, b in zip(road.network.lanes_list(), back.lanes_list(), strict=True):
        assert a.length == pytest.approx(b.length)
        np.testing.assert_allclose(a.position(a.length, 0.0), b.position(b.length, 0.0))
