"""Parked cars added to training windows (``counterscene train --parked-cars``)."""

from __future__ import annotations

import pytest
import torch
from torch.utils.data import default_collate

from counterscene_env.geometry import boxes_overlap
from counterscene_env.world_model.config import preset
from counterscene_env.world_model.dataset import SceneWindowDataset
from counterscene_env.world_model.map_guidance import lane_excess
from counterscene_env.world_model.parked import KERB_OFFSET, MAX_CARS, add_parked_cars

AGENT_KEYS = ("history", "history_valid", "future", "future_valid", "extents", "agent_valid")


@pytest.fixture(scope="module")
def batch(generated):
    ds = SceneWindowDataset(list(generated.values()), preset("default").window())
    return default_collate([ds[i] for i in range(0, len(ds), max(1, len(ds) // 24))])


def _added(before, after):
    return after["agent_valid"] & ~before["agent_valid"]  # [B, K]


def test_parked_cars_stand_still_beside_a_lane_clear_of_the_traffic(batch):
    out = add_parked_cars(batch, 1.0, torch.Generator().manual_seed(0))
    new = _added(batch, out)
    assert new.any() and (new.sum(1) <= MAX_CARS).all()
    # The logged agents are untouched, and nothing else of the window changed.
    for key in AGENT_KEYS:
        assert torch.equal(out[key][batch["agent_valid"]], batch[key][batch["agent_valid"]])
    for key in ("map", "map_valid", "map_widths"):
        assert torch.equal(out[key], batch[key])
    nearest = []
    for b, k in new.nonzero().tolist():
        states = torch.cat([out["history"][b, k], out["future"][b, k]])  # [H + F, 4]
        assert (states == states[0]).all() and states[0, 3] == 0  # still, at speed 0
        assert out["history_valid"][b, k].all() and out["future_valid"][b, k].all()
        length, width = out["extents"][b, k].tolist()
        assert 4.0 < length < 5.1 and 1.7 < width < 2.1
        at = states[0, :2]
        lanes = (out["map"][b : b + 1], out["map_valid"][b : b + 1], out["map_widths"][b : b + 1])
        assert float(lane_excess(at[None, None, None], *lanes)) >= KERB_OFFSET[0] - 1e-5
        # No logged box (nor another parked car) ever touches it, though traffic may pass
        # close beside it.
        others = out["agent_valid"][b].clone()
        others[k] = False
        ok = torch.cat([out["history_valid"][b, others], out["future_valid"][b, others]], 1)
        boxes = torch.cat([out["history"][b, others], out["future"][b, others]], 1)[ok]
        sizes = out["extents"][b, others][:, None].expand(-1, ok.shape[1], 2)[ok]
        hit = boxes_overlap(
            at.numpy(),
            states[0, 2].numpy(),
            out["extents"][b, k].numpy(),
            boxes[:, :2].numpy(),
            boxes[:, 2].numpy(),
            sizes.numpy(),
        )
        assert not hit.any()
        nearest.append(float((boxes[:, :2] - at).norm(dim=-1).min()))
    assert min(nearest) < 4.0  # beside the traffic, as on a street


def test_parked_cars_follow_the_generator_and_the_share(batch):
    a = add_parked_cars(batch, 0.5, torch.Generator().manual_seed(3))
    b = add_parked_cars(batch, 0.5, torch.Generator().manual_seed(3))
    assert all(torch.equal(a[k], b[k]) for k in AGENT_KEYS)
    none = add_parked_cars(batch, 0.0, torch.Generator().manual_seed(3))
    assert none is batch
    full = _added(batch, add_parked_cars(batch, 1.0, torch.Generator().manual_seed(3)))
    half = _added(batch, a)
    assert half.any(1).sum() < full.any(1).sum()


def test_train_config_refuses_a_share_outside_0_1(tmp_path):
    from counterscene_env.world_model.train_config import TrainConfig

    with pytest.raises(ValueError, match="parked_cars"):
        TrainConfig(data=("x",), out=str(tmp_path), parked_cars=1.5)
