"""``CounterScene-v0``: one external ego against world-model traffic with a guided adversary.

The env is a highway-env ``AbstractEnv``: it takes highway-env's config dict, observation types
(``Kinematics`` by default, ``OccupancyGrid``, ``TimeToCollision``, ...), action types
(``ContinuousAction`` by default, ``DiscreteMetaAction``, ...) and renderer. What it replaces is
the traffic: instead of IDM/MOBIL vehicles, :class:`~counterscene_env.sim.ClosedLoop` moves every
other agent with the diffusion world model, and steers the causally selected adversary with
counterfactual guidance. The full spec sheet (spaces, rewards, config keys, info keys) is the
docstring of :class:`CounterSceneEnv` and ``docs/environment.md``.

The env class is assembled from two mixins: the frames of a policy step
(:class:`~counterscene_env.envs.frames.SimulationFrames`, ``envs/frames.py``) and each ego's
outcome of it, info, rewards and end (:class:`~counterscene_env.envs.outcome.EgoOutcomes`,
``envs/outcome.py``). This module holds the rest: construction, config, reset, the step's
checks and its order, rendering.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import numpy as np
from gymnasium import spaces
from highway_env.envs.common.abstract import AbstractEnv
from highway_env.vehicle.kinematics import Vehicle

from counterscene_env.envs.config import (
    UNUSED_BASE_KEYS,
    check_episode_inputs,
    counterscene_defaults,
    prepare,
    reset_options,
    sim_settings,
)
from counterscene_env.envs.egos import pick_egos
from counterscene_env.envs.frames import SimulationFrames
from counterscene_env.envs.mirror import Mirror, build_mirror, sync_mirror
from counterscene_env.envs.outcome import EgoOutcomes
from counterscene_env.envs.render import EpisodeView, render_frame, view_of
from counterscene_env.envs.spaces import (
    as_highway_action,
    capped_observation_space,
    check_action,
    kept_if_unchanged,
    reads_lanes,
)
from counterscene_env.scene.core import Scene
from counterscene_env.scene.sources import SceneSource
from counterscene_env.sim import ClosedLoop, SimConfig
from counterscene_env.sim.state import Episode
from counterscene_env.world_model.checkpoint import shared_model


def draw_episode_seed(rng: np.random.Generator) -> int:
    """An episode's closed-loop seed, drawn from the env's generator after its scene (the
    draws between two scene draws, which a recording ahead foresees: ``SceneSource.prefetch``)."""
    return int(rng.integers(2**31))


class CounterSceneEnv(EgoOutcomes, SimulationFrames, AbstractEnv):
    """Stress-test a driving policy against world-model traffic with a guided adversary.

    **Description.** Each episode starts from a factual scene (a fresh highway-env recording,
    or a real log) at 3 s of history. The ego (the scene's ego vehicle) follows your actions
    through highway-env's vehicle model; every other agent is driven by the diffusion world
    model, re-planned every ``replan_every`` steps from the simulated history. The agent whose
    behaviour keeps the scene safe (the causal adversary, by conflict mining on the factual
    future) has its spatial and temporal safety margins removed by counterfactual guidance
    during denoising; everyone else reacts through the learned dynamics.

    **Action space.** highway-env's ``config["action"]``. Default ``ContinuousAction``:
    ``Box(-1, 1, (2,), float32)``, (acceleration, steering) mapped linearly to [-5, 5] m/s^2
    and [-pi/4, pi/4] rad; values outside [-1, 1] are clipped (highway-env's ``clip``).
    ``DiscreteMetaAction`` gives ``Discrete(5)`` (or 3 with ``lateral: False``): the ego
    follows the lanes of its logged route at a target speed. A wrong shape, a NaN or an
    action outside a discrete space raises ``ValueError``.

    **Observation space.** highway-env's ``config["observation"]``. Default ``Kinematics``:
    ``Box(-1, 1, (10, 7), float32)``, the ego and up to 9 other agents within 200 m (nearest
    along the ego's lane first, behind it too), features ``presence, x, y, vx, vy, cos_h,
    sin_h``, x and y scaled from [-100, 100] m and vx, vy from [-20, 20] m/s to [-1, 1]
    (clipped), other agents relative to the ego.

    **Rewards.** A weighted sum of named terms, highway-env style (``info["rewards"]`` has
    each term): ``collision_reward`` (-5) x collision, ``off_road_reward`` (-1) x off road,
    ``hard_braking_reward`` (-0.5) x hard braking, ``high_speed_reward`` (1) x speed mapped
    from ``reward_speed_range`` [5, 15] m/s to [0, 1]. Collision and hard braking count if
    they happen at any simulation step of the policy step.

    **Starting state.** The scene's logged state at 3 s; the scene is drawn from
    ``scenario`` with the env's seed.

    **Episode end.** Terminated when the ego collides (``terminate_on_collision``) or leaves
    the drivable area (``terminate_on_off_road``); truncated after ``duration`` seconds or at
    the end of the log, never both. At the end, ``info["metrics"]`` holds the episode's
    metric summary (:func:`counterscene_env.metrics.evaluate_scene`).

    **Info** (every step): ``collision``, ``collided_with``, ``hard_braking``,
    ``ego_acceleration`` [m/s^2], ``ego_speed`` [m/s], ``off_road``, ``min_ttc`` [s],
    ``adversary``, ``conflict_type``, ``danger_score``, ``tier``, ``conflict_point`` [m],
    ``arrival_steps``, ``adversary_distance`` [m], ``fallback`` (why there is no adversary),
    ``replanned``, ``step``, ``time`` [s], ``rewards``, ``speed``, ``crashed``,
    ``scenario_id``.

    **Arguments.** ``gym.make("CounterScene-v0", config={...}, render_mode=None |
    "rgb_array" | "human")``; every key of :meth:`default_config`: highway-env's, the scene
    and reward keys, and every ``SimConfig`` field. Unknown keys raise; every value is checked
    by type and range before it is applied (``TypeError`` / ``ValueError`` naming the key),
    and a refused ``configure``, ``reset`` or ``step`` leaves the env as it was.
    ``gymnasium.make_vec("CounterScene-v0", num_envs=N)`` gives N of them in one closed loop
    (``envs/vector.py``).

    **Version history.** v0: first release.
    """

    metadata: ClassVar[dict] = {"render_modes": ["human", "rgb_array"], "render_fps": 10}

    def __init__(
        self,
        config: dict | None = None,
        render_mode: str | None = None,
        scenario: str | None = None,
    ) -> None:
        """``scenario``: the default scenario (the registered variants set it);
        ``config["scenario"]`` overrides it."""
        if scenario is not None:
            config = {"scenario": scenario, **(config or {})}
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode must be None or one of {self.metadata['render_modes']}, "
                f"got {render_mode!r}"
            )
        self.loop: ClosedLoop | None = None
        #: This env's episode in ``loop`` (0 unless a vector env shares one loop, :meth:`share`).
        self.slot = 0
        self.shared = False
        self.scene: Scene | None = None
        self.egos: list[int] = []
        self.mirror: Mirror | None = None  # highway-env's road and vehicles of the episode
        self.traffic: dict[int, Vehicle] = {}  # scene row -> its highway-env vehicle (not egos)
        #: Per frame of the last policy step, every ego's closed-loop info (envs/frames.py).
        self.frame_infos: list[list[dict]] = []
        self.ended: list[bool] = []  # per ego: its episode has ended (terminated)
        self._source: SceneSource | None = None
        self._reset_options: dict = {}
        self._failure: str | None = None  # why the env needs reset() (an unexpected failure)
        # highway-env's __init__ ends with a reset(); ours waits for the user's (Gymnasium
        # requires one before step), which saves a scene recording per env made.
        self._constructing = True
        super().__init__(config, render_mode)
        self._constructing = False

    def update_metadata(self, video_real_time_ratio: int = 1) -> None:
        """This instance's ``render_fps``: one frame per policy step (per simulation step
        while a ``RecordVideo`` wrapper records the intermediate frames), in real time."""
        fps = self.config[
            "simulation_frequency" if self._record_video_wrapper else "policy_frequency"
        ]
        self.metadata = {**type(self).metadata, "render_fps": video_real_time_ratio * fps}

    # ------------------------------------------------------------------ configuration
    @classmethod
    def default_config(cls) -> dict:
        config = super().default_config()
        for key in UNUSED_BASE_KEYS:
            config.pop(key)
        config.update(counterscene_defaults())
        return config

    def configure(self, config: Mapping | None) -> None:
        """Update the config. Every value is checked first (type and range, the observation
        and action types built on a scratch object, the replan's memory): a refused call
        raises ``TypeError`` or ``ValueError`` naming the key and changes nothing."""
        candidate, source = self._prepare(config)
        super().configure(candidate)
        self._source = source
        self.update_metadata()  # render_fps from construction on (RecordVideo reads it early)

    def check_config(self, config: Mapping | None) -> SimConfig:
        """Raise as ``configure(config)`` would, changing nothing; the closed-loop settings
        it would give."""
        candidate, _ = self._prepare(config)
        return SimConfig.from_mapping(sim_settings(candidate))

    def _prepare(self, config: Mapping | None) -> tuple[dict, SceneSource]:
        """The checked config that ``config``'s updates would give, and its scene source."""
        return prepare(self.config, config, self.default_config(), self._source, self)

    def define_spaces(self) -> None:
        """highway-env's spaces, with the ``Kinematics`` box bounded to [-1, 1] when every
        feature is normalised and clipped there (highway-env declares (-inf, inf)), and its
        observations kept to ``vehicles_count`` rows (:class:`RowCappedKinematics`). A space
        equal to the one before is kept, with its generator (``kept_if_unchanged``)."""
        before = self.__dict__.get("action_space"), self.__dict__.get("observation_space")
        super().define_spaces()
        self._needs_lanes = reads_lanes(self.config["observation"])
        space = capped_observation_space(self.observation_type, self.observation_space)
        self.action_space = kept_if_unchanged(before[0], self.action_space)
        self.observation_space = kept_if_unchanged(before[1], space)

    @property
    def sim_config(self) -> SimConfig:
        return SimConfig.from_mapping(sim_settings(self.config))

    def share(self, loop: ClosedLoop, slot: int) -> None:
        """Run this env's episodes in slot ``slot`` of ``loop``, a closed loop shared with
        other envs (the vector env, ``envs/vector.py``: one world-model call per replan for
        all of them). ``loop`` must have this env's model and closed-loop settings; the
        episode starts at the next ``reset``."""
        self.loop, self.slot, self.shared = loop, int(slot), True

    def close(self) -> None:
        """highway-env's ``close``; a scene being recorded ahead for this env is dropped."""
        self._source.drop_prefetch()
        super().close()

    @property
    def recording_ahead(self) -> bool:
        """Whether the scene of this env's next reset is being recorded in the background
        now (``prefetch_scenes``; ``scene/prefetch.py``)."""
        return self._source.recording_ahead

    @property
    def episode(self) -> Episode:
        """This env's current closed-loop episode (a public record of ``sim/``).

        Raises:
            RuntimeError: before the first ``reset()``."""
        if self.loop is None or self.slot >= len(self.loop.episodes):
            raise RuntimeError("no episode yet: call reset() first")
        return self.loop.episodes[self.slot]

    # ------------------------------------------------------------------ episode
    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[Any, dict]:
        """Start an episode (highway-env's ``reset``: its ``_reset`` builds the episode).

        ``options`` (all optional): ``"config"``: config updates, as highway-env;
        ``"scene"``: a :class:`Scene` to run instead of drawing one; ``"episode_seed"``: the
        closed loop's seed (world-model noise, adversary tie-breaks; at most 64 bits) instead
        of one drawn from the env's generator; ``counterscene stress`` passes its episode
        seeds so every planner meets the same traffic randomness; ``"selection_seed"``: the
        seed of a ``random`` selector's choice (the same range; default: the closed loop's
        own generator), which candidate rollouts share so that every candidate of an
        episode has the same adversary (``stress/rollouts.py``). Other keys are ignored
        with a warning (``envs.config.reset_options``). Bad input is refused before anything
        changes.
        """
        if self._constructing:
            # Stand-in egos (no road) give highway-env's per-ego spaces their length.
            n = self.config["controlled_vehicles"]
            self.controlled_vehicles = [Vehicle(None, np.zeros(2)) for _ in range(n)]
            self.define_spaces()
            return None, {}
        options = reset_options(options)
        candidate, source = self._prepare(options.pop("config", None))
        egos = candidate["controlled_vehicles"]
        check_episode_inputs(
            seed,
            options.get("scene"),
            options.get("episode_seed"),
            options.get("selection_seed"),
            egos,
        )
        seed = None if seed is None else int(seed)  # numpy's ints too; Gymnasium wants int
        super().configure(candidate)
        self._source, self._reset_options, self._failure = source, options, None
        try:
            return super().reset(seed=seed, options=options)
        except Exception as exc:
            self._fail("reset", exc)
            raise

    def _reset(self) -> None:
        config = self.config
        scene = self._reset_options.get("scene")
        drawn = scene is None
        if drawn:
            scene = self._source.draw(self.np_random, config["prefetch_scenes"])
        egos = pick_egos(scene, config["controlled_vehicles"])
        model = shared_model(config["model"])
        sim = self.sim_config
        if self.loop is None or self.loop.model is not model or self.loop.config != sim:
            if self.shared:
                raise ValueError(
                    "this env shares its closed loop (a vector env): its model and settings "
                    "cannot change at reset"
                )
            self.loop = ClosedLoop(model, sim)
        seed = self._reset_options.get("episode_seed")
        if seed is None:
            seed = draw_episode_seed(self.np_random)
        selection = self._reset_options.get("selection_seed")
        if self.shared:
            self.loop.start(self.slot, scene, seed, egos, selection_seed=selection)
        else:
            self.loop.reset([scene], [seed], [egos], selection_seeds=[selection])
        self.scene, self.egos = scene, egos
        self.frame_infos = [[dict(i) for i in self.loop.infos(self.slot)]]
        self.ended = [False] * len(egos)
        # The episode's clock is fixed here, as its closed-loop settings are: a configure()
        # mid-episode applies from the next reset on (docs/environment.md, "Config").
        self.frames_per_step = config["simulation_frequency"] // config["policy_frequency"]

        self.mirror = build_mirror(
            scene,
            egos,
            self.action_type.vehicle_class,
            self.np_random,
            record_history=config["show_trajectories"],
        )
        self.road = self.mirror.road
        self.road.neighbour_vehicles_connected_lanes = config["neighbour_vehicles_connected_lanes"]
        self.controlled_vehicles = self.mirror.egos
        self.traffic = self.mirror.traffic
        self.sync_road()
        if config["prefetch_scenes"] and drawn:  # the next reset's scene, if it draws too
            # Two draws ahead for one env that draws its episode seeds (the next reset is
            # taken to be like this one); one per env in a vector env, whose envs keep the
            # recorder's queue as many deep already (docs/performance.md).
            own_seed = self._reset_options.get("episode_seed") is None
            between = draw_episode_seed if own_seed and not self.shared else None
            self._source.prefetch(self.np_random, between=between)

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict]:
        """highway-env's step, after the action is checked: a refused action (wrong type,
        shape, NaN, not in a discrete space) raises and changes nothing."""
        action = self.check_step(action)
        try:
            self.begin_step(action)
            self._simulate()
            result = self.end_step(action)
        except Exception as exc:
            self._fail("step", exc)
        if self.render_mode == "human":
            self.render()
        return result

    # highway-env's step in three parts, public so that a vector env (envs/vector.py) checks
    # every env's action, then runs the frames of all its envs with one closed-loop step each.
    def check_step(self, action: Any) -> Any:
        """Raise unless ``step(action)`` can run (changes nothing); the action as stepped."""
        self._check_running()
        if isinstance(self.action_space, spaces.Tuple) and isinstance(action, list):
            action = tuple(action)  # one action per ego, as highway-env's MultiAgentAction
        check_action(self.action_space, action)
        return action

    def begin_step(self, action: Any) -> None:
        """Apply a checked action and start the policy step's frames."""
        self.time += self.frames_per_step / self.config["simulation_frequency"]
        if not self.config["manual_control"]:
            self.action_type.act(as_highway_action(action))
        self.begin_frames()

    def end_step(self, action: Any) -> tuple[Any, float, bool, bool, dict]:
        """The policy step's result once its frames are done (highway-env's ``step``)."""
        obs = self.observation_type.observe()
        reward = self._reward(action)
        terminated = self._is_terminated()
        truncated = self._is_truncated()
        return obs, reward, terminated, truncated, self._info(obs, action)

    def step_egos(self, actions: Mapping[int, Any]) -> Any:
        """One policy step with an action per ego (ego index -> action, already checked);
        egos without one (those done) keep their last controls. Returns every ego's
        observation. The PettingZoo env steps through this."""
        self._check_running(every_ego=False)
        try:
            types = self.action_type.agents_action_types
            for k, action in actions.items():
                types[k].act(as_highway_action(action))
            self.time += self.frames_per_step / self.config["simulation_frequency"]
            self.begin_frames()
            self._simulate()
            return self.observation_type.observe()
        except Exception as exc:
            self._fail("step", exc)

    def _check_running(self, every_ego: bool = True) -> None:
        """Raise unless a step can run (``every_ego``: and no ego's episode has ended)."""
        if self._failure is not None:
            raise RuntimeError(f"{self._failure}: the episode cannot go on, call reset()")
        if self.episode.done or (every_ego and any(self.ended)):
            raise RuntimeError("the episode is over (terminated or truncated): call reset()")

    def _fail(self, call: str, exc: Exception) -> None:
        """An unexpected failure inside ``call`` (a bug, not bad input, which is refused
        before anything changes): the env is marked as needing ``reset()``."""
        self._failure = f"the last {call}() failed ({type(exc).__name__}: {exc})"
        if call == "step":
            raise RuntimeError(f"{self._failure}: the episode cannot go on, call reset()") from exc

    # ------------------------------------------------------------------ frames
    # The frames themselves are SimulationFrames' (envs/frames.py); each ego's outcome of the
    # policy step is EgoOutcomes' (envs/outcome.py).
    def sync_road(self) -> None:
        """Write the closed loop's state into highway-env's road (observations, viewer)."""
        sync_mirror(self.mirror, self.loop.state(self.slot), lanes=self._needs_lanes)

    def episode_view(self) -> EpisodeView:
        """What the viewer draws on top of highway-env's frame (``envs/render.py``)."""
        hits = [
            v.crashed or self.ego_info(k)["collision"]
            for k, v in enumerate(self.controlled_vehicles)
        ]
        return view_of(self.episode, hits)

    # ------------------------------------------------------------------ rendering
    def render(self) -> np.ndarray | None:
        if self.render_mode is not None:
            self.episode  # noqa: B018 -- raises before the first reset, naming it
        return render_frame(self)
