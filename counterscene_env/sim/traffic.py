"""Background traffic: highway-env's IDM lane follower, for agents the world model no longer
sees.

An agent the model planned before but that has left every model window would otherwise run
on a stale open-loop plan and drift off the road; the closed loop drives it with
:class:`IDMLaneFollower` instead (``MotionSource.IDM``) until a window sees it again. The
reference ego planner ``planners.IDMPlanner`` wraps the same follower.
"""

from __future__ import annotations

import numpy as np
from highway_env.road.regulation import RegulatedRoad
from highway_env.road.road import Road
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.kinematics import Vehicle

from counterscene_env.scene.core import Scene
from counterscene_env.scene.idm_constants import idm_defaults
from counterscene_env.sim.state import WorldState


class IDMLaneFollower:
    """highway-env's IDM lane follower driving one agent of a scene.

    IDM on the vehicle ahead in its lane, lane-keeping steering, no lane changes, along the
    lanes of the agent's logged route (highway-env's own ``IDMVehicle`` logic).

    Args:
        target_speed: desired speed [m/s]; default: the fastest the agent drove in the 3 s
            before it started (at least ``min_target_speed``).
        min_target_speed: floor of the default target speed [m/s].
        yield_to_traffic: also apply highway-env's intersection rule (``RegulatedRoad``):
            when a conflict within 3 s is possible with a vehicle (constant-speed projection,
            ``is_conflict_possible``) and the lane priorities say the agent gives way
            (``respect_priorities``), its target speed is 0 for that step.
    """

    def __init__(
        self,
        target_speed: float | None = None,
        min_target_speed: float = 5.0,
        yield_to_traffic: bool = False,
    ) -> None:
        self.target_speed = target_speed
        self.min_target_speed = min_target_speed
        self.yield_to_traffic = yield_to_traffic

    def reset(
        self, scene: Scene, seed: int, agent: int | None = None, t: int | None = None
    ) -> None:
        """Start driving ``agent`` (default: the ego) from step ``t`` (default: "now") of
        ``scene``, along the lanes of its logged route."""
        self.scene = scene
        self.dt = scene.dt
        self.agent = e = scene.ego_index if agent is None else int(agent)
        t = scene.current_index if t is None else int(t)
        net = scene.road.network
        # Connected lanes: see the car ahead across a lane-segment boundary (junction entries).
        self.road = Road(
            network=net,
            vehicles=[],
            np_random=np.random.default_rng(seed),
            neighbour_vehicles_connected_lanes=True,
        )
        lo = max(0, t - 30)
        history = scene.speeds[e, lo : t + 1][scene.valid[e, lo : t + 1]]
        target = self.target_speed
        if target is None:
            target = max(float(history.max(initial=0.0)), self.min_target_speed)
        self.vehicle = IDMVehicle(
            self.road,
            scene.positions[e, t].copy(),
            float(scene.yaws[e, t]),
            float(scene.speeds[e, t]),
            target_speed=target,
            enable_lane_change=False,
        )
        self.vehicle.LENGTH, self.vehicle.WIDTH = (float(x) for x in scene.extents[e])
        # highway-env's own IDM constants on the instance: building an intersection env (ours
        # or a user's) changes the class's for the whole process, and an episode must not
        # depend on what ran before it.
        for name, value in idm_defaults().items():
            setattr(self.vehicle, name, value)
        # Follow the logged route: plan to the end node of the lane the agent's log ends on.
        last = np.flatnonzero(scene.valid[e])[-1]
        goal = net.get_closest_lane_index(scene.positions[e, last], scene.yaws[e, last])
        self.vehicle.plan_route_to(goal[1])
        self.others = {i: self._other(scene, i, t) for i in range(scene.num_agents) if i != e}
        self.road.vehicles = [self.vehicle]

    def _other(self, scene: Scene, i: int, t: int) -> Vehicle:
        """Agent ``i`` as a highway-env vehicle on this road, without its lane: highway-env
        would search every lane of the map for it, N times per follower, which on real maps
        (hundreds of lanes) was most of a real-log episode. The IDM reads only its position,
        heading and speed (``Road.neighbour_vehicles``). Within 40 m the yielding check
        (``_must_yield``) still costs searches: highway-env's conflict test predicts both
        vehicles by copying and stepping them, and the priority rule sets its lane."""
        other = Vehicle(None, scene.positions[i, t].copy(), float(scene.yaws[i, t]), 0.0)
        other.road = self.road
        return other

    def act(self, state: WorldState) -> np.ndarray:
        v, e = self.vehicle, self.agent
        v.position = np.array(state.positions[e], dtype=np.float64)
        v.heading, v.speed = float(state.yaws[e]), float(state.speeds[e])
        v.on_state_update()  # its lane, as highway-env would after a step
        present = []
        for i, other in self.others.items():
            if state.valid[i]:
                other.position = np.array(state.positions[i], dtype=np.float64)
                other.heading, other.speed = float(state.yaws[i]), float(state.speeds[i])
                present.append(other)
        self.road.vehicles = [v, *present]
        cruise = v.target_speed
        if self.yield_to_traffic and self._must_yield(v, present):
            v.target_speed = 0.0  # as RegulatedRoad.enforce_road_rules does
        v.act()
        v.target_speed = cruise
        acc, steer = float(v.action["acceleration"]), float(v.action["steering"])
        # IDM may ask a stopped car to "brake" further; a lane follower does not reverse.
        acc = max(acc, -v.speed / self.dt)
        return np.array([acc, steer])

    @staticmethod
    def _must_yield(v: IDMVehicle, others: list[Vehicle], radius: float = 40.0) -> bool:
        for other in others:
            if np.linalg.norm(other.position - v.position) > radius:
                continue
            if RegulatedRoad.is_conflict_possible(v, other):
                other.on_state_update()  # its lane, for the priority rule
                if RegulatedRoad.respect_priorities(v, other) is v:
                    return True
        return False

    def drive(self, state: WorldState) -> np.ndarray:
        """Act and advance the agent one step through highway-env's bicycle model; returns its
        next state (x m, y m, yaw rad, speed m/s). The closed loop drives background traffic
        (agents out of the world model's view) this way."""
        acc, steer = self.act(state)
        v = self.vehicle
        # Vehicle.act stores the (clipped) action; IDMVehicle.act would recompute its own.
        Vehicle.act(v, {"acceleration": acc, "steering": steer})
        v.step(self.dt)
        return np.array([*v.position, v.heading, v.speed])
