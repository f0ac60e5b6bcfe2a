"""Shared fixtures: small scenes built by hand or generated once per test session."""

from __future__ import annotations

import os

import numpy as np
import pytest
from highway_env.road.road import RoadNetwork

from counterscene_env.scene import RoadMap, Scene

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")


def pytest_configure(config: pytest.Config) -> None:
    """Under pytest-xdist (``-n``, pyproject.toml) each worker is one of several processes
    on the machine's cores: one torch thread each, as two processes of two threads each on 2
    cores run many times slower."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        import torch

        torch.set_num_threads(1)


def straight_road(lanes: int = 2, length: float = 300.0) -> RoadMap:
    """A straight road along +x, lanes 4 m wide centred on y = 0, 4, ...; drivable y in [-2, 4 lanes - 2]."""
    return RoadMap.from_network(RoadNetwork.straight_road_network(lanes, length=length))


def make_scene(
    positions, yaws=None, speeds=None, extents=None, valid=None, ego_index=0, **kw
) -> Scene:
    """A vehicle-only scene from [N, T, 2] positions; other fields default sensibly."""
    positions = np.asarray(positions, dtype=float)
    n, t, _ = positions.shape
    return Scene(
        positions=positions,
        yaws=np.zeros((n, t)) if yaws is None else yaws,
        speeds=np.zeros((n, t)) if speeds is None else speeds,
        extents=np.tile([4.0, 2.0], (n, 1)) if extents is None else extents,
        valid=np.ones((n, t), bool) if valid is None else valid,
        agent_types=kw.pop("agent_types", np.full(n, "vehicle")),
        agent_ids=kw.pop("agent_ids", np.array([f"a{i}" for i in range(n)])),
        ego_index=ego_index,
        road=kw.pop("road", None) or straight_road(),
        current_index=kw.pop("current_index", 0),
        **kw,
    )


def crash_scene(T: int = 40) -> Scene:
    """Straight 2-lane road. Row 0 (the ego) drives east on y = 0 at 10 m/s from x = 50; row 2
    is parked 14 m ahead of it in its lane (in the log for 2 s only, so it is never picked as
    a second ego); row 1 drives beside it on y = 4, 30 m behind, with a clear lane. An ego at
    full throttle hits row 2 within a second."""
    t = np.arange(T) * 0.1
    ego = np.stack([50 + 10 * t, np.zeros(T)], -1)
    beside = np.stack([20 + 10 * t, np.full(T, 4.0)], -1)
    parked = np.tile([64.0, 0.0], (T, 1))
    valid = np.ones((3, T), bool)
    valid[2, 20:] = False
    speeds = np.array([np.full(T, 10.0), np.full(T, 10.0), np.zeros(T)])
    return make_scene(
        np.stack([ego, beside, parked]), speeds=speeds, valid=valid, scenario_id="planted-crash"
    )


@pytest.fixture(scope="module")
def one_torch_thread():
    """Tiny models on a shared 2-core machine: one torch thread is several times faster than
    two (no thread contention); the previous setting comes back after the module."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="session")
def generated():
    """One generated scene per highway-env scenario (seed 1), built once."""
    from counterscene_env.scene import generate

    return {sc: generate(sc, seed=1) for sc in ("highway", "merge", "intersection", "roundabout")}
