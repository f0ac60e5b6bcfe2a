"""The training loss's overlap term: box penetration in torch (world_model/overlap.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from counterscene_env import geometry
from counterscene_env.world_model.overlap import new_overlaps, overlap_loss, penetration
from counterscene_env.world_model.train_config import TrainConfig

boxes = st.integers(0, 2**31 - 1)


@settings(max_examples=25, deadline=None)
@given(boxes)
def test_penetration_is_positive_exactly_where_the_boxes_overlap(seed):
    rng = np.random.default_rng(seed)
    K = 12
    xy = rng.uniform(-8, 8, (K, 2))
    yaw = rng.uniform(-np.pi, np.pi, K)
    ext = np.stack([rng.uniform(2, 12, K), rng.uniform(1, 3, K)], -1)
    p = penetration(torch.tensor(xy), torch.tensor(yaw), torch.tensor(ext)).numpy()
    want = geometry.boxes_overlap(
        xy[:, None], yaw[:, None], ext[:, None], xy[None], yaw[None], ext[None]
    )
    off = ~np.eye(K, dtype=bool)
    assert np.array_equal((p > 1e-9)[off], want[off])
    assert np.allclose(p, p.T)


def test_penetration_is_the_depth_along_the_best_axis():
    # Two 4 x 2 m boxes side by side along x, centres 3 m apart: 1 m deep; turned across
    # each other, the depth is along the smallest overlap.
    xy = torch.tensor([[0.0, 0.0], [3.0, 0.0]])
    ext = torch.tensor([[4.0, 2.0], [4.0, 2.0]])
    assert penetration(xy, torch.zeros(2), ext)[0, 1].item() == pytest.approx(1.0)
    assert penetration(xy, torch.tensor([0.0, np.pi / 2]), ext)[0, 1].item() == pytest.approx(0.0)
    xy = torch.tensor([[0.0, 0.0], [2.5, 0.0]])
    assert penetration(xy, torch.tensor([0.0, np.pi / 2]), ext)[0, 1].item() == pytest.approx(0.5)


def scene(pred_gap: float, log_gap: float, second_valid: bool = True):
    """Two 4 x 2 m cars in a row for 3 steps: predicted and logged centres ``gap`` m apart."""

    def states(gap):
        x = torch.tensor([[0.0, 0.0, 0.0], [gap, 0.0, 0.0]])  # x, y, course
        return x[:, None].expand(2, 3, 3)[None].clone()  # [1, 2, 3, 3]

    ok = torch.ones(1, 2, 3, dtype=torch.bool)
    ok[0, 1] = second_valid
    return states(pred_gap), states(log_gap), torch.tensor([[[4.0, 2.0], [4.0, 2.0]]]), ok


def test_the_overlap_loss_scores_predicted_overlaps_the_log_does_not_have():
    pred, log, ext, ok = scene(3.0, 10.0)  # 1 m deep at 3 steps, 2 agents x 3 steps valid
    assert overlap_loss(pred, log, ext, ok).item() == pytest.approx(3 * 1.0 / 6)
    assert overlap_loss(*scene(5.0, 10.0)).item() == 0.0  # apart
    assert overlap_loss(*scene(3.0, 3.5)).item() == 0.0  # the log's own overlap
    assert overlap_loss(*scene(3.0, 10.0, second_valid=False)).item() == 0.0


def test_its_gradient_moves_the_cars_apart():
    pred, log, ext, ok = scene(3.0, 10.0)
    pred.requires_grad_(True)
    overlap_loss(pred, log, ext, ok).backward()
    g = pred.grad[0, :, :, 0]  # d loss / d x
    assert (g[0] > 0).all() and (g[1] < 0).all()  # descending pulls car 0 back, car 1 on


@pytest.mark.parametrize("key", ["off_lane_weight", "overlap_weight"])
def test_a_negative_loss_weight_is_refused_by_name(key):
    with pytest.raises(ValueError, match=key):
        TrainConfig(data=("d",), out="o", **{key: -1.0})


def test_evaluation_counts_the_steps_a_prediction_overlaps_where_the_log_does_not():
    pred, log, ext, ok = scene(3.0, 10.0)
    pred[0, 1, 0, 0] = 10.0  # apart at the first step
    ext, ok = ext[0].numpy(), ok[0].numpy()
    clash = new_overlaps(pred[0].numpy(), log[0].numpy(), ext, ok)
    assert clash.tolist() == [False, True, True]
    assert not new_overlaps(log[0].numpy(), log[0].numpy(), ext, ok).any()
    own = scene(3.0, 3.5)  # the log overlaps too: not the model's
    assert not new_overlaps(own[0][0].numpy(), own[1][0].numpy(), ext, ok).any()
