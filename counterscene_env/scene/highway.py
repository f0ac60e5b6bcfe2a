"""Source 1: factual scenes recorded from highway-env traffic.

highway-env builds the road (its ``highway``, ``merge``, ``intersection`` and ``roundabout``
networks) and drives every vehicle with its IDM (longitudinal) and MOBIL (lane change) models.
We only record: the simulation runs at ``sim_frequency`` Hz (a multiple of 10) and every
``sim_frequency / 10``-th frame is kept, so the 10 Hz log is exact, not resampled.

What we add to the stock environments, and why:

- The env's controlled vehicle is replaced by an IDM/MOBIL vehicle on the same route, so the
  factual log is pure traffic. It becomes the scene's ego (``highway``: the vehicle nearest the
  middle of the platoon, since highway-env puts its ego at the back).
- ``merge`` and ``roundabout`` come with four or five vehicles; we add traffic (more vehicles on
  the main road and the ramp; vehicles entering the roundabout over time) so scenes interact.
  ``intersection`` spawns over time with the env's own spawner. The merge road gets a 400 m
  continuation so that the ego does not run off its end within the log.
- Traffic is :class:`ForwardIDMVehicle` (``highway_vehicle.py``): highway-env's IDM/MOBIL
  vehicle whose speed never goes below 0 (the stock class allows -40 m/s, and yielding cars at
  the intersection roll back), with two of its searches made cheaper, same results.
- Vehicles at the end of a lane with no successor leave the scene (their ``valid`` ends), as
  the intersection env's own clean-up does; vehicles spawned later start invalid.
- Factual logs must be safe: a recording in which any two boxes overlap, or in which the ego is
  not present throughout, is rejected; :func:`generate` then tries the next seed.

Same ``(scenario, seed, duration)``, same scene: all randomness comes from the env's
``np_random`` seeded at reset, and the IDM class constants that ``IntersectionEnv`` overwrites
process-wide are restored after every recording (``scene/idm_constants.py``).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Any

import highway_env
import numpy as np
import shapely
from highway_env.envs.highway_env import HighwayEnv
from highway_env.envs.intersection_env import IntersectionEnv
from highway_env.envs.merge_env import MergeEnv
from highway_env.envs.roundabout_env import RoundaboutEnv
from highway_env.road.lane import LineType, StraightLane

from counterscene_env.config import Scenario, Yielding
from counterscene_env.geometry import overlaps_over_time, wrap_angle
from counterscene_env.scene.core import DEFAULT_DT, Scene
from counterscene_env.scene.gap_acceptance import GapAcceptanceRoad, GapAcceptingVehicle
from counterscene_env.scene.highway_vehicle import (
    ForwardIDMVehicle,
    defer_lane_updates,
    update_lanes,
)
from counterscene_env.scene.idm_constants import pristine_idm_constants
from counterscene_env.scene.road import RoadMap

SCENARIOS = Scenario.values()


GENERATOR_VERSION = 2

#: Shortest log, s: 3 s of history and 10 s of future.
MIN_DURATION = 13.0


@dataclass(frozen=True)
class GeneratorConfig:
    """How a scene is recorded.

    Attributes:
        duration: recorded length, s (history + future); at least 13 s (3 s + 10 s).
        warmup: simulated time discarded before recording starts, s; None: the scenario's
            default (:data:`WARMUP`). It lets highway-env's artificial initial placement settle.
        max_off_road: a recording in which a vehicle's centre is farther than this outside the
            drivable area is rejected, m (highway-env's steering controller occasionally drives
            a car into an intersection corner; such a log is not a sane factual one).
        sim_frequency: simulation rate, Hz; a multiple of 10 so that the 10 Hz log is exact.
        map_margin: the map is clipped to the recorded positions' bounding box plus this, m.
        yielding: how intersection traffic gives way: ``highway-env`` (its rule: target speed
            0, decided twice a second 3 s ahead) or ``gap-acceptance`` (a stop point before
            the crossing, chosen 6 s ahead; ``scene/gap_acceptance.py``). Only the
            intersection has crossing traffic: other roads refuse ``gap-acceptance``.
    """

    duration: float = 13.0
    warmup: float | None = None
    sim_frequency: int = 20
    map_margin: float = 60.0
    max_off_road: float = 1.0
    yielding: str = Yielding.HIGHWAY_ENV.value

    def __post_init__(self) -> None:
        object.__setattr__(self, "yielding", Yielding.parse(self.yielding, "yielding"))
        if self.duration < MIN_DURATION:
            raise ValueError(
                f"duration must be at least {MIN_DURATION} s (3 s history + 10 s future), "
                f"got {self.duration} s"
            )
        if self.sim_frequency % 10:
            raise ValueError(f"sim_frequency must be a multiple of 10 Hz, got {self.sim_frequency}")


#: Seeds :func:`generate` tries, by default, before it gives up.
MAX_ATTEMPTS = 20


class RejectedScene(RuntimeError):
    """A recording that may not serve as a factual log (collision, ego missing)."""


def generate(
    scenario: str,
    seed: int,
    duration: float | None = None,
    *,
    max_attempts: int = MAX_ATTEMPTS,
    config: GeneratorConfig | None = None,
) -> Scene:
    """Record one safe factual scene of a highway-env scenario.

    Args:
        scenario: one of :data:`SCENARIOS`.
        seed: the first seed tried; a rejected recording moves on to ``seed + 1`` and so on.
        duration: recorded length, s (the scene has ``round(duration / 0.1) + 1`` steps);
            None: ``config.duration`` (13 s by default).
        max_attempts: seeds tried before giving up.
        config: further recording settings (``duration`` here overrides it).

    Returns:
        The scene; ``scene.metadata["seed"]`` is the seed actually used and
        ``scene.metadata["rejected_seeds"]`` the ones skipped before it.
    """
    cfg = config or GeneratorConfig()
    if duration is not None:
        cfg = dataclasses.replace(cfg, duration=duration)
    rejected: list[int] = []
    for attempt in range(max_attempts):
        try:
            scene = record(scenario, seed + attempt, cfg)
        except RejectedScene:
            rejected.append(seed + attempt)
            continue
        scene.metadata["rejected_seeds"] = rejected
        return scene
    raise RuntimeError(
        f"{scenario}: no safe scene in seeds {seed}..{seed + max_attempts - 1}; "
        "raise max_attempts or change the seed"
    )


def record(scenario: str, seed: int, config: GeneratorConfig | None = None) -> Scene:
    """Record exactly one seed; raises :class:`RejectedScene` if it is not a safe log."""
    cfg = config or GeneratorConfig()
    check_yielding(scenario, cfg.yielding)
    start = time.perf_counter()
    log, ego, network, n_steps = _simulate(scenario, seed, cfg)
    scene = log.to_scene(ego, network, n_steps, cfg, scenario, seed)
    if scenario == "highway":
        scene = scene.replace(ego_index=_platoon_middle(scene))
    _reject_unsafe(scene, cfg)
    scene.metadata["generation_time_s"] = time.perf_counter() - start
    return scene


def check_yielding(scenario: str, yielding: str) -> None:
    """Refuse an unknown ``scenario``, or a ``yielding`` rule other than highway-env's on a
    road without crossing traffic."""
    if scenario not in SCENARIOS:
        raise ValueError(f"unknown scenario {scenario!r}; choose one of {SCENARIOS}")
    yielding = Yielding.parse(yielding, "yielding")
    if yielding != Yielding.HIGHWAY_ENV and scenario != Scenario.INTERSECTION:
        raise ValueError(
            f"yielding {yielding!r} applies to the intersection only (the one road with "
            f"crossing traffic), not to {scenario!r}"
        )


def _simulate(scenario: str, seed: int, cfg: GeneratorConfig) -> tuple[_Recorder, Any, Any, int]:
    """Warm up and run the env, logging every 10 Hz step: (log, ego vehicle, road network, T)."""
    with pristine_idm_constants():
        env = make_env(scenario, cfg.yielding)
        env.reset(seed=int(seed))  # a new road and traffic from this seed alone
        traffic = Traffic(scenario, env, _VEHICLE_CLASSES[cfg.yielding])
        ego = traffic.setup()
        frames_per_step = cfg.sim_frequency // 10
        warmup = WARMUP[scenario] if cfg.warmup is None else cfg.warmup
        for _ in range(round(warmup * cfg.sim_frequency)):
            traffic.step(1.0 / cfg.sim_frequency)
        if ego not in env.road.vehicles:
            raise RejectedScene("ego left the scene during warm-up")
        log = _Recorder()
        n_steps = round(cfg.duration / DEFAULT_DT) + 1
        for k in range(n_steps):
            log.snapshot(env.road.vehicles, k)
            _reject_early(log, ego, env.road.vehicles, k)
            if k < n_steps - 1:
                for _ in range(frames_per_step):
                    traffic.step(1.0 / cfg.sim_frequency)
        network = env.road.network
    return log, ego, network, n_steps


def _reject_early(log: _Recorder, ego, vehicles, k: int) -> None:
    """Stop a recording as soon as :func:`_reject_unsafe` is bound to refuse it: the ego has
    left, or this frame's boxes overlap. A rejected seed used to cost its whole 13 s; about
    one intersection seed in five is rejected (docs/performance.md). Overlaps are looked for
    only once highway-env has flagged a crash (a car stays ``crashed``), and with the same
    arithmetic as the final check, which still runs: the scenes kept are the same."""
    if ego not in vehicles:
        raise RejectedScene("the ego is not present for the whole log")
    if not any(v.crashed for v in vehicles):
        return
    rows = sorted(log.states[k])
    state = np.array([log.states[k][r] for r in rows])  # [V, 4]: x, y, heading, speed
    extents = np.array([[log.vehicles[r].LENGTH, log.vehicles[r].WIDTH] for r in rows])
    overlap = overlaps_over_time(
        state[:, None, :2], wrap_angle(state[:, None, 2]), extents, np.ones((len(rows), 1), bool)
    )
    if overlap.any():
        raise RejectedScene(f"boxes overlap at step {k}")


def _reject_unsafe(scene: Scene, cfg: GeneratorConfig) -> None:
    """Raise :class:`RejectedScene` for a missing ego, overlapping boxes or off-road driving."""
    if not scene.valid[scene.ego_index].all():
        raise RejectedScene("the ego is not present for the whole log")
    overlap = overlaps_over_time(scene.positions, scene.yaws, scene.extents, scene.valid)
    if overlap.any():
        raise RejectedScene(f"boxes overlap at {int(overlap.any(axis=(1, 2)).sum())} steps")
    centres = shapely.points(scene.positions[scene.valid])
    off = shapely.distance(scene.road.drivable_area, centres).max()
    if off > cfg.max_off_road:
        raise RejectedScene(f"a vehicle drove {off:.1f} m off the road")


# ---------------------------------------------------------------------- environments
_ENV_CLASSES = {
    "highway": HighwayEnv,
    "merge": MergeEnv,
    "intersection": IntersectionEnv,
    "roundabout": RoundaboutEnv,
}

#: Default warm-up per scenario, s. highway-env starts highway and merge traffic at 25-30 m/s on
#: 20 m/s lanes: everyone brakes hard for the first 1-2 s, an artefact we do not record. The
#: intersection env warms up for 3 s itself; the roundabout's first seconds are real yielding.
WARMUP = {"highway": 3.0, "merge": 3.0, "intersection": 1.0, "roundabout": 1.0}

# Overrides of each env's default config. Frequencies are irrelevant here (we step the road
# ourselves); the counts shape the traffic.
_ENV_CONFIG = {
    "highway": {"lanes_count": 3, "vehicles_count": 24, "vehicles_density": 1.2},
    "merge": {},
    "intersection": {"initial_vehicle_count": 10, "spawn_probability": 0.6},
    "roundabout": {},
}
#: The recorded traffic's vehicle class per yielding rule.
_VEHICLE_CLASSES = {
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
        vehicle = _VEHICLE_CLASSES[yielding]
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


# ---------------------------------------------------------------------- recording
class _Recorder:
    """Collects vehicle states per 10 Hz step, indexed by first appearance."""

    def __init__(self) -> None:
        self.rows: dict[int, int] = {}
        self.vehicles: list = []
        self.states: list[dict[int, tuple[float, float, float, float]]] = []

    def snapshot(self, vehicles, k: int) -> None:
        frame = {}
        for v in vehicles:
            key = id(v)
            if key not in self.rows:
                self.rows[key] = len(self.vehicles)
                self.vehicles.append(v)
            frame[self.rows[key]] = (
                float(v.position[0]),
                float(v.position[1]),
                float(v.heading),
                float(v.speed),
            )
        self.states.append(frame)

    def to_scene(
        self, ego, network, n_steps: int, cfg: GeneratorConfig, scenario: str, seed: int
    ) -> Scene:
        n = len(self.vehicles)
        state = np.zeros((n, n_steps, 4))
        valid = np.zeros((n, n_steps), dtype=bool)
        for k, frame in enumerate(self.states):
            for row, values in frame.items():
                state[row, k] = values
                valid[row, k] = True
        pos = state[..., :2]
        lo = pos[valid].min(axis=0) - cfg.map_margin
        hi = pos[valid].max(axis=0) + cfg.map_margin
        road = RoadMap.from_network(network, bounds=(lo[0], lo[1], hi[0], hi[1]))
        return Scene(
            positions=pos,
            yaws=wrap_angle(state[..., 2]),
            speeds=state[..., 3],
            extents=np.array([[v.LENGTH, v.WIDTH] for v in self.vehicles]),
            valid=valid,
            agent_types=np.full(n, "vehicle"),
            agent_ids=np.array([f"veh{i}" for i in range(n)]),
            ego_index=self.rows[id(ego)],
            road=road,
            dt=DEFAULT_DT,
            scenario_id=f"{scenario}/seed={seed}",
            metadata={
                "source": "highway-env",
                "scenario": scenario,
                "seed": int(seed),
                "generator_version": GENERATOR_VERSION,
                "highway_env_version": highway_env.__version__
                if hasattr(highway_env, "__version__")
                else "unknown",
                "sim_frequency": cfg.sim_frequency,
                "warmup_s": WARMUP[scenario] if cfg.warmup is None else cfg.warmup,
                "yielding": cfg.yielding,
            },
        )


def _platoon_middle(scene: Scene) -> int:
    """The vehicle present throughout that is nearest the platoon's median x at the current step."""
    t = scene.current_index
    always = np.flatnonzero(scene.valid.all(axis=1))
    if always.size == 0:
        return scene.ego_index
    median_x = np.median(scene.positions[scene.valid[:, t], t, 0])
    return int(always[np.argmin(np.abs(scene.positions[always, t, 0] - median_x))])
