"""Cars parked off the street are held in place, out of the network's view
(``ModelConfig.hold_parked``; docs/world_model.md, "Cars parked off the street")."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import make_scene
from torch.utils.data import default_collate

from counterscene_env.world_model.config import HOLD_PARKED, preset
from counterscene_env.world_model.dataset import SceneWindowDataset
from counterscene_env.world_model.loss import training_loss
from counterscene_env.world_model.model import WorldModel
from counterscene_env.world_model.parked import KERB_OFFSET

pytestmark = pytest.mark.usefixtures("one_torch_thread")

TINY = preset("default").replace(
    d_model=32, num_heads=2, num_blocks=1, num_agents=6, num_lanes=8, sampling_steps=3
)
# Lanes 4 m wide on y = 0 and y = 4: the strips cover y in [-2, 6].
LOT, KERB = 12.0, 6.0 + KERB_OFFSET[0]  # a car 6 m beyond the strips; one at the kerb
# Rows: the ego (moving), stopped in a lot, stopped on a lane, moving through the lot,
# stopped at the kerb.
ROWS = [(10.0, 0.0, 0.0), (0.0, LOT, 30.0), (0.0, 4.0, 60.0), (5.0, LOT, -20.0), (0.0, KERB, 45.0)]
HELD = [False, True, False, False, False]


def _model(**changes) -> WorldModel:
    torch.manual_seed(0)
    return WorldModel(TINY.replace(**changes)).eval()


def _batch(model: WorldModel) -> dict[str, torch.Tensor]:
    T = 90
    t = np.arange(T) * 0.1
    pos = np.zeros((len(ROWS), T, 2))
    for i, (v, y, x0) in enumerate(ROWS):
        pos[i, :, 0] = 20.0 + x0 + v * t
        pos[i, :, 1] = y
    speeds = np.tile(np.array([r[0] for r in ROWS])[:, None], (1, T))
    ds = SceneWindowDataset([make_scene(pos, speeds=speeds)], model.window_config())
    return default_collate([ds[0]])


def _held_by_row(model, batch) -> list[bool]:
    """``held_agents`` in the order of ``ROWS`` (a window orders its agents by distance)."""
    held = model.held_agents(batch)[0].tolist()
    slots = batch["rows"][0].tolist()
    return [held[slots.index(i)] for i in range(len(ROWS))]


def test_only_a_stopped_car_off_every_lane_strip_is_held():
    assert HOLD_PARKED == KERB_OFFSET[1] == TINY.hold_parked
    model = _model()
    batch = _batch(model)
    assert _held_by_row(model, batch) == HELD
    # Off (checkpoints without the key): nobody is held.
    assert not _model(hold_parked=0.0).held_agents(batch).any()
    # A window without lanes has no street to be off.
    bare = {**batch, "map_valid": torch.zeros_like(batch["map_valid"])}
    assert not model.held_agents(bare).any()


def test_a_held_car_stays_put_and_the_others_plan_as_if_it_were_not_there():
    model = _model()
    batch = _batch(model)
    held = model.held_agents(batch)
    pred = model.sample(batch, 2, torch.Generator().manual_seed(0))
    assert pred.valid[0, :5].all()  # still a real agent with a plan (slot 5: padding)
    k = int(held[0].nonzero()[0, 0])
    now = batch["history"][0, k, -1, :2]
    moved = (pred.trajectory[0, :, k, :, :2] - now).norm(dim=-1)
    assert moved.max() < 1e-4 and (pred.trajectory[0, :, k, :, 3] == 0).all()
    # The same batch with that slot as padding: every other agent's sample is the same.
    gone = {**batch, "agent_valid": batch["agent_valid"] & ~held}
    ref = model.sample(gone, 2, torch.Generator().manual_seed(0))
    others = ~held[0]
    torch.testing.assert_close(
        pred.trajectory[:, :, others], ref.trajectory[:, :, others], rtol=0, atol=1e-5
    )
    # The training loss treats it as padding as well.
    g = torch.Generator().manual_seed(1)
    with_held = training_loss(model, batch, g)
    g = torch.Generator().manual_seed(1)
    without = training_loss(model, gone, g)
    torch.testing.assert_close(with_held["loss"], without["loss"])


def test_hold_passed_by_the_caller_wins():
    """The closed loop clears its guided adversary from the held agents: such a car is then
    planned by the network like any other (the sample of a model that holds nobody)."""
    model, free = _model(), _model(hold_parked=0.0)
    batch = _batch(model)
    none = torch.zeros_like(batch["agent_valid"])
    a = model.sample(batch, 2, torch.Generator().manual_seed(0), held=none)
    b = free.sample(batch, 2, torch.Generator().manual_seed(0))
    torch.testing.assert_close(a.trajectory, b.trajectory, rtol=0, atol=0)


def test_the_closed_loop_never_holds_its_guided_adversary(monkeypatch):
    """Even a car parked off the street is guided when the selection makes it the adversary
    (one that pulls out of a driveway in the log): the replan clears it from the held agents."""
    from test_sim import crossing_scene

    from counterscene_env.sim import ClosedLoop, SimConfig
    from counterscene_env.world_model.checkpoint import load_model

    model = load_model()
    seen = []
    sample = model.sample

    def every_agent_parked(batch, beyond=None):
        return model.agent_mask(batch)

    def spy(batch, *args, held=None, **kwargs):
        seen.append((batch["agent_valid"].clone(), None if held is None else held.clone()))
        return sample(batch, *args, held=held, **kwargs)

    monkeypatch.setattr(model, "held_agents", every_agent_parked)
    monkeypatch.setattr(model, "sample", spy)
    loop = ClosedLoop(model, SimConfig(duration=9.0, num_samples=2))
    loop.reset([crossing_scene()], [0])
    assert loop.selection(0).conflict.agent == 1
    for _ in range(12):  # three replans
        loop.step(np.zeros((1, 2)))
    assert len(seen) >= 2
    for valid, held in seen:  # the ego's window: the ego, then the adversary (row 1)
        assert held is not None and held[0, 0] and not held[0, 1]
        assert held[0, 2:].tolist() == valid[0, 2:].tolist()


@pytest.mark.parametrize("hold_parked", [None, 0.0, 4.0])
def test_the_closed_loop_setting_decides_how_far_off_the_lanes_a_car_is_held(
    monkeypatch, hold_parked
):
    """``SimConfig.hold_parked`` (a ``CounterScene-v0`` key and a ``stress`` flag) overrides
    the model's threshold: None keeps the model's 1.5 m, 0 holds nobody."""
    from test_sim import crossing_scene

    from counterscene_env.sim import ClosedLoop, SimConfig
    from counterscene_env.world_model import hold as hold_module
    from counterscene_env.world_model.checkpoint import load_model

    model = load_model()
    asked, seen = [], []
    sample = model.sample

    def everyone_off_the_lanes(batch, state, valid, beyond):
        asked.append(beyond)
        return valid

    def spy(batch, *args, held=None, **kwargs):
        seen.append(held.clone())
        return sample(batch, *args, held=held, **kwargs)

    monkeypatch.setattr(hold_module, "parked_off_lanes", everyone_off_the_lanes)
    monkeypatch.setattr(model, "sample", spy)
    loop = ClosedLoop(model, SimConfig(duration=9.0, num_samples=2, hold_parked=hold_parked))
    loop.reset([crossing_scene()], [0])
    for _ in range(6):
        loop.step(np.zeros((1, 2)))
    assert seen
    if hold_parked == 0.0:
        assert not asked and not any(h.any() for h in seen)
    else:
        assert asked and set(asked) == {model.config.hold_parked if hold_parked is None else 4.0}
        assert all(h[0, 0] for h in seen)  # the ego's window holds everyone but its adversary
