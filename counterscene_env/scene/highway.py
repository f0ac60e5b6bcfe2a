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

from counterscene_env.config import Scenario, Yielding, check_int
from counterscene_env.geometry import overlaps_over_time, wrap_angle
from counterscene_env.scene.core import DEFAULT_DT, GENERATED_SOURCE, Scene
from counterscene_env.scene.highway_traffic import VEHICLE_CLASSES, Traffic, make_env
from counterscene_env.scene.idm_constants import pristine_idm_constants
from counterscene_env.scene.road import RoadMap

SCENARIOS = Scenario.values()


GENERATOR_VERSION = 2

#: Shortest log, s: 3 s of history and 10 s of future.
MIN_DURATION = 13.0

#: Default warm-up per scenario, s. highway-env starts highway and merge traffic at 25-30 m/s on
#: 20 m/s lanes: everyone brakes hard for the first 1-2 s, an artefact we do not record. The
#: intersection env warms up for 3 s itself; the roundabout's first seconds are real yielding.
WARMUP = {"highway": 3.0, "merge": 3.0, "intersection": 1.0, "roundabout": 1.0}


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
    seed = check_int("seed", seed, ge=0)  # 1.5 would record seed 1, named "1.5"
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
        traffic = Traffic(scenario, env, VEHICLE_CLASSES[cfg.yielding])
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
                "source": GENERATED_SOURCE,
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
