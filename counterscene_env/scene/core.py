"""The scene contract: one way to describe a driving scene, whatever its source.

A :class:`Scene` is a factual (or simulated) log of N agents over T steps at ``dt`` seconds,
plus the :class:`~counterscene_env.scene.road.RoadMap` they drive on. Every scenario source
(the highway-env generator, the ScenarioNet importer, the closed-loop simulator) produces one,
and everything downstream (selection, the world model, metrics) reads only this.

Conventions (docs/design.md, "Ego-centred frame"): SI units, world frame, ``yaw`` measured from +x counter-clockwise,
``speed`` the signed speed along the heading. Where ``valid[i, t]`` is False the state entries
of agent i at step t carry no meaning (they are zero after construction) and every consumer
must mask them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from counterscene_env.config import DEFAULT_DT, check_int, check_real
from counterscene_env.scene.road import RoadMap

#: Agent type labels. Vehicles are the agents the world model drives; the other types are kept
#: so that collision checks see pedestrians, cyclists and static objects too.
AGENT_TYPES = ("vehicle", "pedestrian", "cyclist", "other")

#: No road user moves faster than this between two valid steps [m/s] (360 km/h): a faster
#: "move" is a corrupt position (``Scene`` refuses it; importers repair the track).
MAX_SPEED = 100.0
DEFAULT_HISTORY_STEPS = 31  # 3 s of history including the current frame (paper: 31)
#: The least history a real log may start an episode with, steps before "now" (1 s).
MIN_HISTORY_STEPS = 10
#: The future a short log's "now" keeps where the log allows it, steps (1 s).
MIN_FUTURE_STEPS = 10
#: ``metadata["source"]`` of the scenes highway-env's traffic generates (``scene.highway``).
GENERATED_SOURCE = "highway-env"


class SceneError(ValueError):
    """A scene (in memory or on disk) breaks the contract; the message names the field."""


def _array(name: str, value: object, dtype: type) -> np.ndarray:
    """``value`` as a new array of ``dtype``; a value that is not numbers names the field."""
    try:
        return np.array(value, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise SceneError(f"{name} must be numbers: {exc}") from None


class SceneTooShort(SceneError):
    """A log too short for any episode (callers that read many logs skip and count these)."""


@dataclass(eq=False)
class Scene:
    """N agents over T steps of ``dt`` seconds on a road.

    Attributes:
        positions: ``[N, T, 2]`` float64, m, world frame (agent box centre).
        yaws: ``[N, T]`` float64, rad, heading from +x counter-clockwise.
        speeds: ``[N, T]`` float64, m/s, signed speed along the heading.
        extents: ``[N, 2]`` float64, m, (length, width) of each agent's box.
        valid: ``[N, T]`` bool, whether the agent exists at that step.
        agent_types: ``[N]`` str, one of :data:`AGENT_TYPES`.
        agent_ids: ``[N]`` str, stable ids (track ids for real logs).
        ego_index: row of the ego vehicle.
        road: the road map (highway-env network, drivable area, lane centre lines).
        dt: step length, s.
        scenario_id: a human-readable id (``"intersection/seed=17"``, a nuScenes scene name).
        current_index: the step that is "now": history is ``[:current_index + 1]``, the
            future ``[current_index + 1:]``. Defaults to 30 (3 s of history at 10 Hz).
        metadata: free-form JSON-serialisable facts about the source (seed, dataset, ...).
    """

    positions: np.ndarray
    yaws: np.ndarray
    speeds: np.ndarray
    extents: np.ndarray
    valid: np.ndarray
    agent_types: np.ndarray
    agent_ids: np.ndarray
    ego_index: int
    road: RoadMap
    dt: float = DEFAULT_DT
    scenario_id: str = ""
    current_index: int = DEFAULT_HISTORY_STEPS - 1
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        # Own copies: the scene zeroes invalid entries and must not alias the caller's arrays.
        for name in ("positions", "yaws", "speeds", "extents"):
            setattr(self, name, _array(name, getattr(self, name), np.float64))
        valid = np.asarray(self.valid)
        if valid.dtype != bool and not np.isin(valid, (0, 1)).all():
            raise SceneError(f"valid must be bools (or 0 and 1), got values {np.unique(valid)[:5]}")
        self.valid = np.array(valid, dtype=bool)
        self.agent_types = np.array(self.agent_types, dtype=str)
        self.agent_ids = np.array(self.agent_ids, dtype=str)
        try:  # a row and a step are ints (1.7 is not a row); dt a finite number of s
            self.ego_index = check_int("ego_index", self.ego_index)
            self.current_index = check_int("current_index", self.current_index)
            self.dt = check_real("dt", self.dt, gt=0)
        except (TypeError, ValueError) as exc:
            raise SceneError(str(exc)) from None
        self.metadata = dict(self.metadata)  # a slice's own top-level metadata
        self._validate()
        # Invalid entries carry no meaning; zero them so that NaNs from a source never leak.
        inv = ~self.valid
        self.positions[inv] = 0.0
        self.yaws[inv] = 0.0
        self.speeds[inv] = 0.0

    # ------------------------------------------------------------------ validation
    def _validate(self) -> None:
        """Raise :class:`SceneError` on the first broken field (shapes, indices, then values)."""
        n, t = self._validate_shapes()
        self._validate_indices(n, t)
        self._validate_values(n)

    def _validate_shapes(self) -> tuple[int, int]:
        """Check every array's shape against ``positions [N, T, 2]``; return ``(N, T)``."""
        if self.positions.ndim != 3 or self.positions.shape[2] != 2:
            raise SceneError(f"positions must be [N, T, 2], got {self.positions.shape}")
        n, t, _ = self.positions.shape
        expected = {
            "yaws": (self.yaws, (n, t)),
            "speeds": (self.speeds, (n, t)),
            "valid": (self.valid, (n, t)),
            "extents": (self.extents, (n, 2)),
            "agent_types": (self.agent_types, (n,)),
            "agent_ids": (self.agent_ids, (n,)),
        }
        for name, (arr, shape) in expected.items():
            if arr.shape != shape:
                raise SceneError(
                    f"{name} must have shape {shape} for N={n}, T={t}; got {arr.shape}"
                )
        if n == 0 or t == 0:
            raise SceneError(f"a scene needs at least one agent and one step, got N={n}, T={t}")
        return n, t

    def _validate_indices(self, n: int, t: int) -> None:
        """Check ``ego_index`` (a vehicle row of N), ``dt > 0`` s and ``current_index`` (of T)."""
        if not 0 <= self.ego_index < n:
            raise SceneError(f"ego_index {self.ego_index} out of range for {n} agents")
        if self.agent_types[self.ego_index] != "vehicle":
            raise SceneError(f"the ego must be a vehicle, got {self.agent_types[self.ego_index]!r}")
        if not self.dt > 0:
            raise SceneError(f"dt must be positive, got {self.dt}")
        if not 0 <= self.current_index < t:
            raise SceneError(f"current_index {self.current_index} out of range for T={t}")

    def _validate_values(self, n: int) -> None:
        """Check agent types and ids, finite states at valid steps, extents (m) and the road."""
        unknown = set(self.agent_types.tolist()) - set(AGENT_TYPES)
        if unknown:
            raise SceneError(f"unknown agent types {sorted(unknown)}; valid: {AGENT_TYPES}")
        if len(set(self.agent_ids.tolist())) != n:
            raise SceneError("agent_ids must be unique")
        for name in ("positions", "yaws", "speeds"):
            arr = getattr(self, name)
            if not np.isfinite(arr[self.valid]).all():
                raise SceneError(f"{name} has non-finite values at valid steps")
        self._validate_motion()
        if not np.isfinite(self.extents).all() or (self.extents <= 0).any():
            raise SceneError("extents must be finite and positive (length, width) in m")
        if not isinstance(self.road, RoadMap):
            raise SceneError(f"road must be a RoadMap, got {type(self.road).__name__}")

    def _validate_motion(self) -> None:
        """Refuse a track that moves faster than any road user can between two valid steps
        (:data:`MAX_SPEED`): a corrupt position, not a driver."""
        ok = self.valid[:, 1:] & self.valid[:, :-1]
        if not ok.any():
            return
        step = np.linalg.norm(np.diff(self.positions, axis=1), axis=-1)
        step = np.where(ok, step, 0.0)
        worst = np.unravel_index(np.argmax(step), step.shape)
        if step[worst] > MAX_SPEED * self.dt:
            agent, t = worst
            raise SceneError(
                f"agent {str(self.agent_ids[agent])!r} moves {step[worst]:.4g} m between steps {t} "
                f"and {t + 1} ({step[worst] / self.dt:.4g} m/s, above the {MAX_SPEED:g} m/s "
                "no road user reaches): a corrupt position"
            )

    # ------------------------------------------------------------------ basic facts
    @property
    def num_agents(self) -> int:
        return self.positions.shape[0]

    @property
    def num_steps(self) -> int:
        return self.positions.shape[1]

    @property
    def duration(self) -> float:
        """Length of the log in s (``(T - 1) * dt``)."""
        return (self.num_steps - 1) * self.dt

    @property
    def future_duration(self) -> float:
        """s of log after "now" (``current_index``): the longest episode the scene holds."""
        return (self.num_steps - 1 - self.current_index) * self.dt

    @property
    def vehicle_mask(self) -> np.ndarray:
        """``[N]`` bool, True for agents of type ``"vehicle"``."""
        return self.agent_types == "vehicle"

    @property
    def generated(self) -> bool:
        """Whether the scene is highway-env's generated traffic (``metadata["source"]``), not
        a recording of real driving (every imported log, and any scene that does not say)."""
        return self.metadata.get("source") == GENERATED_SOURCE

    @property
    def velocities(self) -> np.ndarray:
        """``[N, T, 2]`` m/s, world-frame velocity from speed and heading."""
        return self.speeds[..., None] * np.stack([np.cos(self.yaws), np.sin(self.yaws)], -1)

    # ------------------------------------------------------------------ slicing
    def replace(self, **changes) -> Scene:
        """A copy with some fields replaced (it owns copies of its arrays, like any Scene)."""
        return dataclasses.replace(self, **changes)

    def time_slice(self, start: int, stop: int) -> Scene:
        """Steps ``[start, stop)`` of the log.

        ``current_index`` moves with the slice and is clipped into it: a slice that starts after
        "now" (a future window) has ``current_index = 0``, its first frame.
        """
        if not 0 <= start < stop <= self.num_steps:
            raise SceneError(f"time slice [{start}, {stop}) outside [0, {self.num_steps})")
        return self.replace(
            positions=self.positions[:, start:stop].copy(),
            yaws=self.yaws[:, start:stop].copy(),
            speeds=self.speeds[:, start:stop].copy(),
            valid=self.valid[:, start:stop].copy(),
            current_index=int(np.clip(self.current_index - start, 0, stop - start - 1)),
        )

    def history(self, steps: int = DEFAULT_HISTORY_STEPS, t: int | None = None) -> Scene:
        """The ``steps`` frames ending at step ``t`` (inclusive; default ``current_index``).

        Frames before the start of the log are not invented: the window is shorter then.
        """
        t = self.current_index if t is None else int(t)
        return self.time_slice(max(0, t - steps + 1), t + 1)

    def future(self, steps: int | None = None, t: int | None = None) -> Scene:
        """The ``steps`` frames after step ``t`` (default: all frames after ``current_index``)."""
        t = self.current_index if t is None else int(t)
        stop = self.num_steps if steps is None else min(self.num_steps, t + 1 + int(steps))
        if t + 1 >= stop:
            raise SceneError(f"no future after step {t} in a log of {self.num_steps} steps")
        return self.time_slice(t + 1, stop)

    def select_agents(self, indices: np.ndarray | list[int]) -> Scene:
        """Keep the given agent rows, in that order. The ego must be among them."""
        idx = np.asarray(indices, dtype=np.int64)
        where = np.flatnonzero(idx == self.ego_index)
        if where.size != 1:
            raise SceneError("select_agents must keep the ego exactly once")
        return self.replace(
            positions=self.positions[idx].copy(),
            yaws=self.yaws[idx].copy(),
            speeds=self.speeds[idx].copy(),
            extents=self.extents[idx].copy(),
            valid=self.valid[idx].copy(),
            agent_types=self.agent_types[idx].copy(),
            agent_ids=self.agent_ids[idx].copy(),
            ego_index=int(where[0]),
        )

    def nearest_indices(
        self, k: int, t: int | None = None, types: tuple[str, ...] | None = None
    ) -> np.ndarray:
        """Indices of the ego and the ``k - 1`` agents nearest to it at step ``t``.

        The ego comes first, the others by increasing distance; agents not valid at ``t``
        (or not of one of ``types``) are left out, so fewer than ``k`` may come back.
        Ties break by row index, so the result is deterministic.
        """
        t = self.current_index if t is None else int(t)
        d = np.linalg.norm(self.positions[:, t] - self.positions[self.ego_index, t], axis=-1)
        ok = self.valid[:, t].copy()
        if types is not None:
            ok &= np.isin(self.agent_types, types)
        ok[self.ego_index] = False
        others = np.flatnonzero(ok)
        others = others[np.argsort(d[others], kind="stable")][: max(0, k - 1)]
        return np.concatenate([[self.ego_index], others]).astype(np.int64)

    def nearest(self, k: int, t: int | None = None, types: tuple[str, ...] | None = None) -> Scene:
        """The scene restricted to the ego and its ``k - 1`` nearest agents at step ``t``."""
        return self.select_agents(self.nearest_indices(k, t, types))

    def __repr__(self) -> str:
        return (
            f"Scene({self.scenario_id!r}, agents={self.num_agents}, steps={self.num_steps}, "
            f"dt={self.dt}, ego={self.ego_index}, lanes={len(self.road.lane_centerlines)})"
        )


def drop_impossible_jumps(
    positions: np.ndarray, valid: np.ndarray, dt: float
) -> tuple[np.ndarray, dict[int, int]]:
    """Repair tracks with corrupt positions, one track at a time. A lone sample that jumps
    away and back (faster than :data:`MAX_SPEED`) is made invalid; where a track still
    "moves" faster than that between two valid steps, it is cut there and only its longest
    consistent piece stays valid.

    Args:
        positions: ``[N, T, 2]`` m; valid: ``[N, T]`` bool; dt: step [s].

    Returns:
        The repaired ``valid`` (a copy) and ``{row: steps made invalid}`` for the rows cut.
    """
    before = valid.sum(axis=1)
    valid = valid.copy()
    limit = MAX_SPEED * dt
    step = np.linalg.norm(np.diff(positions, axis=1), axis=-1)
    jumps = (step > limit) & valid[:, 1:] & valid[:, :-1]
    # A lone bad sample (a jump there and back, its neighbours consistent) loses that sample.
    skip = np.linalg.norm(positions[:, 2:] - positions[:, :-2], axis=-1) <= 2 * limit
    spike = jumps[:, :-1] & jumps[:, 1:] & skip
    valid[:, 1:-1] &= ~spike
    step = np.linalg.norm(np.diff(positions, axis=1), axis=-1)
    jumps = (step > limit) & valid[:, 1:] & valid[:, :-1]
    repaired = {int(r): int(before[r] - valid[r].sum()) for r in np.flatnonzero(spike.any(1))}
    for row in np.flatnonzero(jumps.any(axis=1)):
        # Piece index of every step: it grows by one after each jump.
        piece = np.concatenate([[0], np.cumsum(jumps[row])])
        sizes = np.bincount(piece, weights=valid[row])
        keep = valid[row] & (piece == int(np.argmax(sizes)))
        valid[row] = keep
        repaired[int(row)] = int(before[row] - keep.sum())
    return valid, repaired


def default_current_index(
    num_steps: int, where: str = "the log", preferred: int = DEFAULT_HISTORY_STEPS - 1
) -> int:
    """The "now" step of an imported log of ``num_steps`` steps.

    ``preferred`` (3 s of history) where the log holds :data:`MIN_FUTURE_STEPS` (1 s) after
    it; else the latest step that leaves 1 s of future, if that keeps
    :data:`MIN_HISTORY_STEPS` (1 s) of history; else the last step but one, if that does. An
    episode on a short log so gets a second of future wherever the log allows it.

    Raises:
        SceneTooShort: the log is too short for any episode (the message names ``where``).
    """
    if preferred + MIN_FUTURE_STEPS <= num_steps - 1:
        return preferred
    for now in (num_steps - 1 - MIN_FUTURE_STEPS, num_steps - 2):
        if now >= MIN_HISTORY_STEPS:
            return now
    raise SceneTooShort(
        f"{where}: recording too short: {num_steps} steps ({(num_steps - 1) * DEFAULT_DT:.1f} s)"
        f" leave no {MIN_HISTORY_STEPS} steps of history before a future step"
    )


#: Why a stored scene is not played (:func:`unplayable_reason`; also a log too short to
#: import at all).
TOO_SHORT = "too short for an episode"
EGO_ABSENT = "the ego is not in the log at 'now'"
NO_LANES = "its map has no lanes"


def unplayable_reason(scene: Scene) -> str | None:
    """Why an episode cannot start at the scene's "now" (None: it can): no step after it,
    the ego not valid then, or no lane to drive on (the ego's lane search needs one)."""
    if scene.current_index >= scene.num_steps - 1:
        return TOO_SHORT
    if not scene.valid[scene.ego_index, scene.current_index]:
        return EGO_ABSENT
    if not scene.road.lane_centerlines:
        return NO_LANES
    return None


def playable(scene: Scene) -> bool:
    """Whether an episode can start at the scene's "now" (:func:`unplayable_reason`)."""
    return unplayable_reason(scene) is None
