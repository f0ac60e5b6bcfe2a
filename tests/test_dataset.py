"""Training windows: fixed shapes, the ego-centred frame, padding and validity."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import make_scene, straight_road

from counterscene_env.scene import save_scenes
from counterscene_env.world_model.dataset import SceneWindowDataset
from counterscene_env.world_model.window import WindowConfig

CFG = WindowConfig(
    history_steps=11, future_steps=20, num_agents=4, num_lanes=6, lane_points=5, stride=5
)


def _northbound_scene():
    # Ego drives north (+y) at 10 m/s from (100, 0); agent 1 is 8 m ahead of it; agent 2 is
    # absent until step 20; agent 3 is 200 m away. 60 steps.
    t = np.arange(60) * 0.1
    pos = np.zeros((4, 60, 2))
    pos[0] = np.stack([np.full_like(t, 100.0), 10 * t], -1)
    pos[1] = pos[0] + [0.0, 8.0]
    pos[2] = pos[0] + [3.0, -5.0]
    pos[3] = pos[0] + [200.0, 0.0]
    valid = np.ones((4, 60), bool)
    valid[2, :20] = False
    return make_scene(
        pos, yaws=np.full((4, 60), np.pi / 2), speeds=np.full((4, 60), 10.0), valid=valid
    )


def test_window_shapes_and_dtypes(generated):
    ds = SceneWindowDataset(list(generated.values()))
    item = ds[0]
    c = ds.config
    assert item["history"].shape == (c.num_agents, c.history_steps, 4)
    assert item["future"].shape == (c.num_agents, c.future_steps, 4)
    assert item["map"].shape == (c.num_lanes, c.lane_points, 2)
    assert item["history"].dtype == torch.float32 and item["history_valid"].dtype == torch.bool
    # 131-step scenes with 31 + 52 frames: t0 = 30, 40, ..., 70 -> 5 windows per scene.
    assert len(ds) == 5 * len(generated)
    batch = torch.utils.data.default_collate([ds[i] for i in range(3)])
    assert batch["history"].shape[0] == 3
    for item in (ds[i] for i in range(len(ds))):
        assert torch.isfinite(item["history"]).all() and torch.isfinite(item["map"]).all()


def test_ego_frame_padding_and_validity():
    ds = SceneWindowDataset([_northbound_scene()], CFG)
    assert [t0 for _, t0, _ in ds.index] == [10, 15, 20, 25, 30, 35]
    w = ds.window(0, 10)
    # The ego is at the origin heading +x at t0; 1 s earlier it was 10 m behind.
    np.testing.assert_allclose(w["history"][0, -1], [0, 0, 0, 10], atol=1e-5)
    np.testing.assert_allclose(w["history"][0, 0, :2], [-10, 0], atol=1e-5)
    np.testing.assert_allclose(w["future"][0, 9, :2], [10, 0], atol=1e-5)
    # Agent 1 (8 m north in the world) is 8 m straight ahead; agent 2 is absent at t0 and so
    # not selected; the far agent 3 comes next; the fourth slot is padding.
    np.testing.assert_allclose(w["history"][1, -1, :2], [8, 0], atol=1e-5)
    assert w["agent_valid"].tolist() == [True, True, True, False]
    np.testing.assert_allclose(w["history"][2, -1, :2], [0, -200], atol=1e-4)
    assert not w["history_valid"][3].any() and not w["history"][3].any()
    np.testing.assert_allclose(w["origin"], [100, 10, np.pi / 2])
    # Lanes of the road run along world +x, i.e. along ego -y; only those within 60 m are used.
    lanes = w["map"][w["map_valid"]]
    assert len(lanes) > 0
    direction = lanes[:, -1] - lanes[:, 0]
    assert np.allclose(direction[:, 0], 0, atol=1e-4) and (direction[:, 1] < 0).all()
    assert (np.linalg.norm(lanes, axis=-1).min(axis=1) <= CFG.map_radius + 1e-4).all()


def _far_agent_scene():
    # A 600 m road along +x. The ego drives east at 10 m/s from x = 50; agent 1 drives east at
    # 20 m/s from x = 250, 200 m ahead, far beyond the ego's 60 m map radius.
    t = np.arange(40) * 0.1
    pos = np.stack([np.stack([50 + 10 * t, 0 * t], -1), np.stack([250 + 20 * t, 0 * t], -1)])
    speeds = np.array([np.full(40, 10.0), np.full(40, 20.0)])
    return make_scene(pos, speeds=speeds, road=straight_road(2, length=600.0))


@pytest.mark.parametrize("anchors", ["ego", "agents"])
def test_lane_anchors_choose_whose_road_the_window_holds(anchors):
    cfg = WindowConfig(
        history_steps=11,
        future_steps=20,
        num_agents=2,
        num_lanes=8,
        lane_points=5,
        lane_segment_length=20.0,
        lane_anchors=anchors,
    )
    w = SceneWindowDataset([_far_agent_scene()], cfg).window(0, 10)
    lanes = w["map"][w["map_valid"]]  # ego frame: the ego at (0, 0), agent 1 at (200, 0)

    def covered(x: float) -> bool:  # some window lane passes within 1 m of (x, 0)
        return bool((np.linalg.norm(lanes - [x, 0.0], axis=-1) < 1.0).any())

    assert covered(0.0) and covered(10.0)  # the ego's own road is always there
    # Agent 1 now, and where constant velocity takes it by the end of the 2 s horizon (+40 m).
    assert covered(200.0) == covered(240.0) == (anchors == "agents")


def test_unknown_lane_anchors_are_refused():
    with pytest.raises(ValueError, match="lane_anchors"):
        WindowConfig(lane_anchors="map")


def test_agent_appearing_later_is_masked_until_it_appears():
    ds = SceneWindowDataset([_northbound_scene()], CFG)
    w = ds.window(0, 25)
    row = 1 + int(np.argmin(np.linalg.norm(w["history"][1:3, -1, :2] - [-5, -3], axis=-1)))
    # Agent 2 appears at step 20: history frames 15..25 -> the first 5 are invalid.
    assert w["history_valid"][row].tolist() == [False] * 5 + [True] * 6
    assert not w["history"][row, :5].any()


def test_loads_from_shards_and_dataset_dirs(tmp_path, generated):
    from counterscene_env.scene.datagen import generate_dataset

    path = save_scenes([generated["merge"]], tmp_path / "s.npz")
    ds = SceneWindowDataset(path)
    assert len(ds) == 5
    generate_dataset(tmp_path / "d", "merge", scenes=2, seed=0, shard_size=1, progress=False)
    both = SceneWindowDataset([tmp_path / "d", path])
    assert len(both) == 15 and len(both.scenes) == 3
    with pytest.raises(Exception, match="no such shard"):
        SceneWindowDataset(tmp_path / "missing.npz")


def test_short_logs_give_windows_with_masked_futures_when_asked():
    """A 25-step log has no window with a whole 20-step future after 11 steps of history;
    with ``min_future_steps`` the ends of such logs become windows, the missing frames
    invalid (masked out of the loss)."""
    short = _northbound_scene().time_slice(0, 25)
    assert len(SceneWindowDataset([short], CFG)) == 0
    ds = SceneWindowDataset([short], CFG, min_future_steps=10)
    starts = [t for _, t, _ in ds.index]
    assert starts == [10]  # t0 = 10 leaves 14 future steps; 15 would leave only 9
    item = ds[0]
    assert item["future_valid"][0, :14].all() and not item["future_valid"][0, 14:].any()
    with pytest.raises(ValueError, match="min_future_steps"):
        SceneWindowDataset([short], CFG, min_future_steps=0)


def test_agent_centred_windows_put_each_vehicle_at_the_origin():
    """``centres="agents"``: every vehicle with 1 s of history and the future asked for centres
    a window, in its own frame; the ego-only index is a subset."""
    scene = _northbound_scene()
    ego_only = SceneWindowDataset([scene], CFG)
    ds = SceneWindowDataset([scene], CFG, centres="agents")
    assert set(ego_only.index) < set(ds.index)
    # Agent 2 appears at step 20: it centres windows only from t0 = 29 on (10 valid frames).
    assert min(t for _, t, r in ds.index if r == 2) == 30
    assert {r for _, t, r in ds.index if t == 10} == {0, 1, 3}
    row = ds.index.index((0, 30, 2))
    item = ds[row]
    np.testing.assert_allclose(item["history"][0, -1].numpy(), [0, 0, 0, 10], atol=1e-5)
    # The ego (5 m north, 3 m west of agent 2 heading north) is 5 m ahead, 3 m to the left.
    ego = int(np.flatnonzero(item["rows"].numpy() == 0)[0])
    np.testing.assert_allclose(item["history"][ego, -1, :2].numpy(), [5, 3], atol=1e-5)
    with pytest.raises(ValueError, match="centres"):
        SceneWindowDataset([scene], CFG, centres="everyone")
