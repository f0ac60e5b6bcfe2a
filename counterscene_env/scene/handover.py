"""Hand a moment of a scene to highway-env's traffic and record what it does next.

Used to give the world model's own closed-loop states an answer to learn from
(``tools/closed_loop_data.py``; docs/world_model_experiments.md, "The network's crossing
collisions"):
every vehicle becomes one of the recordings' IDM vehicles (``ForwardIDMVehicle``) at its
exact position, heading and speed, on highway-env's intersection road (which gives way by
lane priority), routed to a destination node, and the traffic runs at the recordings' 20 Hz
with no vehicle spawned. Only the intersection: its road is the same for every seed, so it
is the road of every stored intersection scene.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from counterscene_env.scene.core import DEFAULT_DT
from counterscene_env.scene.highway_traffic import Traffic, make_env
from counterscene_env.scene.highway_vehicle import ForwardIDMVehicle
from counterscene_env.scene.idm_constants import pristine_idm_constants

#: highway-env frames per 10 Hz step (20 Hz, as the recordings).
FRAMES_PER_STEP = 2


def drive_on(
    positions: np.ndarray,
    yaws: np.ndarray,
    speeds: np.ndarray,
    target_speeds: np.ndarray,
    destinations: Sequence[str | None],
    steps: int,
    scenario: str = "intersection",
) -> tuple[np.ndarray, np.ndarray]:
    """Drive ``N`` vehicles on with highway-env's traffic for ``steps`` 10 Hz steps.

    Args:
        positions: ``[N, 2]`` m, world frame of the scenario's road.
        yaws: ``[N]`` rad; ``speeds``, ``target_speeds``: ``[N]`` m/s (the IDM's desired speed).
        destinations: per vehicle, the road-network node its route leads to (None: highway-env
            routes it along its lane).
        steps: 10 Hz steps to record after the start.

    Returns:
        ``[N, steps, 4]`` states (x [m], y [m], heading [rad], speed [m/s]) and the ``[N,
        steps]`` validity (a vehicle that reaches the end of its last lane leaves, as in the
        recordings).

    Raises:
        ValueError: another scenario than the intersection, or arrays of other lengths.
    """
    if scenario != "intersection":
        raise ValueError(f"scenario: only 'intersection' can be handed over, got {scenario!r}")
    n = len(positions)
    if not (len(yaws) == len(speeds) == len(target_speeds) == len(destinations) == n):
        raise ValueError("positions, yaws, speeds, target_speeds and destinations must align")
    state = np.zeros((n, steps, 4))
    valid = np.zeros((n, steps), bool)
    with pristine_idm_constants():
        env = make_env(scenario)
        env.reset(seed=0)  # the road; its own traffic is replaced
        env.road.vehicles = []
        cars = []
        for i in range(n):
            car = ForwardIDMVehicle(
                env.road, np.array(positions[i], float), float(yaws[i]), float(speeds[i])
            )
            car.target_speed = float(target_speeds[i])
            if destinations[i] is not None:
                car.plan_route_to(destinations[i])
            env.road.vehicles.append(car)
            cars.append(car)
        traffic = Traffic(scenario, env)
        traffic.next_spawn = np.inf
        for k in range(steps):
            for _ in range(FRAMES_PER_STEP):
                traffic.step(DEFAULT_DT / FRAMES_PER_STEP)
            present = {id(v) for v in env.road.vehicles}
            for i, car in enumerate(cars):
                if id(car) in present:
                    state[i, k] = (*car.position, car.heading, car.speed)
                    valid[i, k] = True
    return state, valid
