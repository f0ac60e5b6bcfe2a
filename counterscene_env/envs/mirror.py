"""highway-env's road as a mirror of the closed loop: built from an episode's scene, updated
from the loop's state every frame, so that highway-env's observation types and viewer see the
world-model traffic (``CounterScene-v0``, ``envs/single_agent.py``)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from highway_env.road.road import Road
from highway_env.vehicle.controller import ControlledVehicle
from highway_env.vehicle.kinematics import Vehicle

from counterscene_env.scene.core import Scene
from counterscene_env.sim.state import WorldState


@dataclass
class Mirror:
    """An episode's highway-env road.

    Attributes:
        road: highway-env's road on the scene's lane network.
        egos: the egos' vehicles, of the action type's class (they follow the policy).
        traffic: scene row -> highway-env vehicle of every other agent (written, never driven).
    """

    road: Road
    egos: list[Vehicle]
    traffic: dict[int, Vehicle]


def build_mirror(
    scene: Scene,
    egos: Sequence[int],
    vehicle_class: type[Vehicle],
    np_random: np.random.Generator,
    record_history: bool = False,
) -> Mirror:
    """The road and vehicles of ``scene`` at its "now" step: ``egos`` (scene rows) as
    ``vehicle_class`` vehicles at their logged states (lane-following classes routed to the
    lane where their log ends), every other agent as a plain vehicle."""
    t = scene.current_index
    road = Road(
        network=scene.road.network,
        vehicles=[],
        np_random=np_random,
        record_history=record_history,
    )
    ego_vehicles = []
    for e in egos:
        v = vehicle_class(
            road, scene.positions[e, t].copy(), float(scene.yaws[e, t]), float(scene.speeds[e, t])
        )
        v.LENGTH, v.WIDTH = (float(x) for x in scene.extents[e])
        if isinstance(v, ControlledVehicle):  # lane-following action types: the logged route
            last = np.flatnonzero(scene.valid[e])[-1]
            goal = scene.road.network.get_closest_lane_index(
                scene.positions[e, last], scene.yaws[e, last]
            )
            v.plan_route_to(goal[1])
        ego_vehicles.append(v)
    traffic = {}
    for i in range(scene.num_agents):
        if i in egos:
            continue
        v = Vehicle(road, scene.positions[i, t].copy(), float(scene.yaws[i, t]), 0.0)
        v.LENGTH, v.WIDTH = (float(x) for x in scene.extents[i])
        traffic[i] = v
    return Mirror(road, ego_vehicles, traffic)


def sync_mirror(mirror: Mirror, state: WorldState, lanes: bool) -> None:
    """Write the closed loop's ``state`` into the road: the egos and every agent present now
    (``lanes``: update each vehicle's lane too, for lane-based observation features; costly
    on big maps)."""
    present = []
    for i, v in mirror.traffic.items():
        if not state.valid[i]:
            continue
        v.position = np.array(state.positions[i], dtype=np.float64)
        v.heading, v.speed = float(state.yaws[i]), float(state.speeds[i])
        if lanes:
            v.on_state_update()
        present.append(v)
    mirror.road.vehicles = [*mirror.egos, *present]
