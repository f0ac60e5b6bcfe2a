"""The traffic of the generated scenes: highway-env's environments and what we add to them.

:func:`make_env` gives the process's highway-env environment of a scenario (its road network
and its spawner); :class:`Traffic` replaces its controlled vehicles by IDM/MOBIL ones, adds
traffic where the stock env has too little, and does the per-frame housekeeping around
``road.act(); road.step(dt)``. ``highway.py`` records scenes from it, ``handover.py`` hands
vehicle states to it (why each addition: ``highway.py``'s module docstring, docs/scenes.md).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from highway_env.envs.highway_env import HighwayEnv
from highway_env.envs.intersection_env import IntersectionEnv
from highway_env.envs.merge_env import MergeEnv
from highway_env.envs.roundabout_env import RoundaboutEnv
from highway_env.road.lane import LineType, StraightLane

from counterscene_env.config import Yielding
from counterscene_env.scene.gap_acceptance import GapAcceptanceRoad, GapAcceptingVehicle
from counterscene_env.scene.highway_vehicle import (
    ForwardIDMVehicle,
    defer_lane_updates,
    update_lanes,
)

_ENV_CLASSES = {
    "highway": HighwayEnv,
    "merge": MergeEnv,
    "intersection": IntersectionEnv,
    "roundabout": RoundaboutEnv,
}

# Overrides of each env's default config. Frequencies are irrelevant here (we step the road
# ourselves); the counts shape the traffic.
_ENV_CONFIG = {
    "highway": {"lanes_count": 3, "vehicles_count": 24, "vehicles_density": 1.2},
    "merge": {},
    "intersection": {"initial_vehicle_count": 10, "spawn_probability": 0.6},
    "roundabout": {},
}
#: The recorded traffic's vehicle class per yielding rule.
VEHICLE_CLASSES = {
    Yielding.HIGHWAY_ENV.value: ForwardIDMVehicle,
    Yielding.GAP_ACCEPTANCE.value: GapAcceptingVehicle,
}


class _GapAcceptanceIntersectionEnv(IntersectionEnv):
    """highway-env's intersection on a :class:`GapAcceptanceRoad` (same network, same draws)."""

    def _make_road(self) -> None:
        super()._make_road()
        road = self.road
        self.road = GapAcceptanceRoad(
            network=road.network,
            np_random=road.np_random,
            record_history=road.record_history,
            neighbour_vehicles_connected_lanes=road.neighbour_vehicles_connected_lanes,
        )


#: One highway-env env per scenario and yielding rule, built on first use: building one (its
#: spaces, a first road) took a seventh of each scene's generation, and ``reset(seed=...)``
#: rebuilds the road and the traffic from the seed alone, so a reused env records exactly
#: what a new one would.
_ENVS: dict[tuple[str, str], Any] = {}


def make_env(scenario: str, yielding: str = Yielding.HIGHWAY_ENV.value):
    """The process's highway-env environment of ``scenario`` (one per scenario and yielding
    rule, made once; its class constants are only pristine inside
    ``idm_constants.pristine_idm_constants``)."""
    key = (scenario, yielding)
    if key not in _ENVS:
        vehicle = VEHICLE_CLASSES[yielding]
        config = {
            **_ENV_CONFIG[scenario],
            "other_vehicles_type": f"{vehicle.__module__}.{vehicle.__name__}",
        }
        cls = _ENV_CLASSES[scenario]
        if yielding == Yielding.GAP_ACCEPTANCE:
            cls = _GapAcceptanceIntersectionEnv
        _ENVS[key] = cls(config=config)
    return _ENVS[key]


class Traffic:
    """Per-scenario set-up and per-frame housekeeping around ``road.act(); road.step(dt)``."""

    def __init__(self, scenario: str, env, vehicle_class: type = ForwardIDMVehicle) -> None:
        self.scenario = scenario
        self.env = env
        self.vehicle_class = vehicle_class
        self.road = env.road
        self.rng = env.np_random
        self.time = 0.0
        self.next_spawn = 1.0
        defer_lane_updates(self.road)

    def setup(self):
        """Replace controlled vehicles by IDM/MOBIL ones, add traffic; return the ego vehicle."""
        ego = None
        for controlled in list(self.env.controlled_vehicles):
            idm = self.vehicle_class.create_from(controlled)
            self.road.vehicles[self.road.vehicles.index(controlled)] = idm
            ego = ego or idm
        if self.scenario == "merge":
            self._extend_merge_road()
            for lane, s_lo, s_hi in ((("a", "b", 0), 0, 200), (("a", "b", 1), 0, 200)):
                for _ in range(3):
                    self._spawn(lane, self.rng.uniform(s_lo, s_hi), self.rng.uniform(23, 30))
            for _ in range(2):
                self._spawn(("j", "k", 0), self.rng.uniform(20, 100), self.rng.uniform(18, 24))
        elif self.scenario == "roundabout":
            for _ in range(3):
                self._spawn_roundabout_entry()
        return ego

    def step(self, dt: float) -> None:
        self.road.act()
        self.road.step(dt)
        update_lanes(self.road)  # every vehicle's lane after its move, in one pass
        self.time += dt
        self._remove_finished()
        if self.time + 1e-9 >= self.next_spawn:
            # Spawn once per simulated second, as IntersectionEnv does once per (1 Hz) step.
            self.next_spawn += 1.0
            if self.scenario == "intersection":
                self.env._clear_vehicles()
                self.env._spawn_vehicle(spawn_probability=self.env.config["spawn_probability"])
            elif self.scenario == "roundabout" and self.rng.uniform() < 0.5:
                self._spawn_roundabout_entry()

    # -- helpers
    def _spawn(self, lane_index, longitudinal: float, speed: float, destination=None):
        """Put an IDM vehicle on a lane unless it would start within 15 m of another one."""
        lane = self.road.network.get_lane(lane_index)
        position = lane.position(longitudinal, 0.0)
        if any(np.linalg.norm(v.position - position) < 15.0 for v in self.road.vehicles):
            return None
        vehicle = self.vehicle_class.make_on_lane(self.road, lane_index, longitudinal, speed=speed)
        if destination is not None:
            vehicle.plan_route_to(destination)
        vehicle.randomize_behavior()
        self.road.vehicles.append(vehicle)
        return vehicle

    def _spawn_roundabout_entry(self) -> None:
        entries = [("ser", "ses", 0), ("eer", "ees", 0), ("ner", "nes", 0), ("wer", "wes", 0)]
        exits = ["sxr", "exr", "nxr", "wxr"]
        k = int(self.rng.integers(4))
        destination = exits[int(self.rng.choice([i for i in range(4) if i != k]))]
        self._spawn(
            entries[k], self.rng.uniform(0.0, 30.0), self.rng.uniform(7.0, 10.0), destination
        )

    def _remove_finished(self) -> None:
        """Vehicles at the end of a dead-end lane leave (their centre still on the lane)."""
        graph = self.road.network.graph
        keep = []
        for v in self.road.vehicles:
            lane = v.lane
            if lane is not None and not graph.get(v.lane_index[1]):
                s, _ = lane.local_coordinates(v.position)
                if s >= lane.length - 1.0:
                    continue
            keep.append(v)
        self.road.vehicles = keep

    def _extend_merge_road(self) -> None:
        net = self.road.network
        c, s, n = LineType.CONTINUOUS_LINE, LineType.STRIPED, LineType.NONE
        for i, line_types in enumerate(([c, s], [n, c])):
            end = net.get_lane(("c", "d", i)).end
            net.add_lane(
                "d", "e", StraightLane(end, end + np.array([400.0, 0.0]), line_types=line_types)
            )
