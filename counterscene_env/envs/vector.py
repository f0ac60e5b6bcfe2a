"""``gymnasium.make_vec("CounterScene-v0", num_envs=N)``: N episodes in one closed loop.

Gymnasium's default vectorisation runs N separate envs, each replanning its traffic with its
own world-model call. Here the N envs share one :class:`~counterscene_env.sim.ClosedLoop`
(each env's episode is one slot of its batch), so every replan is one world-model call for
every env due to replan at that step. Each env is otherwise a full
:class:`~counterscene_env.envs.single_agent.CounterSceneEnv` (its own highway-env road, ego
vehicle, observation and action types, ``np_random`` and closed-loop seed), and a batched
world-model call gives each window the result it gets alone, so env ``i`` gives exactly the
episode of a single env with the same seed and actions (``tests/test_vector_env.py``).

**Autoreset.** Gymnasium 1.x's modes (``autoreset_mode=``): ``NEXT_STEP`` (the default): the
step after an env terminates or truncates resets it, ignores its action and returns its first
observation with reward 0; ``SAME_STEP``: the env is reset in the step that ends it, its last
observation and info are ``infos["final_obs"]`` and ``infos["final_info"]`` (what SB3 needs,
``envs/sb3_vec.py``); ``DISABLED``: reset ended envs yourself with
``reset(options={"reset_mask": mask})``.

**Seeds.** ``reset(seed=s)`` seeds env ``i`` with ``s + i``; ``seed=[s0, s1, ...]`` one per env.

**Infos.** Gymnasium's vector format: ``infos[key]`` is an array over envs and
``infos["_" + key]`` a mask of the envs that reported it; nested dicts (``rewards``,
``metrics``) likewise.

**Per-env options** (besides the single env's ``options``, which apply to every env):
``"scenes"``, a list of N :class:`Scene` (or None: draw one), and ``"episode_seeds"``, a list
of N closed-loop seeds (or None), the per-env versions of ``"scene"`` and ``"episode_seed"``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space, concatenate, create_empty_array, iterate

from counterscene_env.envs.config import check_episode_inputs
from counterscene_env.envs.single_agent import CounterSceneEnv
from counterscene_env.scene.prefetch import one_thread_if
from counterscene_env.sim import ClosedLoop, SimConfig
from counterscene_env.world_model.checkpoint import shared_model

#: Config keys fixed for a vector env's life: its spaces and its shared closed loop.
FIXED_KEYS = ("observation", "action", "controlled_vehicles", "model")


class CounterSceneVectorEnv(VectorEnv):
    """N ``CounterScene-v0`` envs whose traffic is replanned in one batched world-model call.

    Args:
        num_envs: N, the number of envs (>= 1).
        config: the single env's config keys (``docs/environment.md``), for every env.
        render_mode: None or ``"rgb_array"`` (``render()`` gives one frame per env).
        scenario: the default scenario (the registered variants set it).
        autoreset_mode: ``AutoresetMode.NEXT_STEP`` (default), ``SAME_STEP`` or ``DISABLED``
            (or their string values).
    """

    metadata: ClassVar[dict] = {
        "autoreset_mode": AutoresetMode.NEXT_STEP,
        "render_modes": ["rgb_array"],
        "render_fps": 10,
    }

    def __init__(
        self,
        num_envs: int = 1,
        config: dict | None = None,
        render_mode: str | None = None,
        scenario: str | None = None,
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
    ) -> None:
        if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"num_envs must be an int >= 1, got {num_envs!r}")
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        try:
            mode = AutoresetMode(autoreset_mode)
        except ValueError:
            modes = [m.value for m in AutoresetMode]
            raise ValueError(
                f"autoreset_mode must be one of {modes}, got {autoreset_mode!r}"
            ) from None
        self.envs = [
            CounterSceneEnv(config=config, render_mode=render_mode, scenario=scenario)
            for _ in range(num_envs)
        ]
        first = self.envs[0]
        self._share(ClosedLoop(shared_model(first.config["model"]), first.sim_config))
        self.num_envs = num_envs
        self.render_mode = render_mode
        self.autoreset_mode = mode
        self.metadata = {**self.metadata, "autoreset_mode": mode}
        self.single_observation_space = first.observation_space
        self.single_action_space = first.action_space
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._obs: list[Any] = [None] * num_envs
        self._rewards = np.zeros(num_envs, np.float64)
        self._terminations = np.zeros(num_envs, np.bool_)
        self._truncations = np.zeros(num_envs, np.bool_)
        self._ended = np.zeros(num_envs, np.bool_)  # terminated or truncated, not reset since
        self._started = False

    def _share(self, loop: ClosedLoop) -> None:
        """Run every env's episodes in ``loop`` (env ``i`` in slot ``i``)."""
        self.loop = loop
        for i, env in enumerate(self.envs):
            env.share(loop, i)

    @property
    def config(self) -> dict:
        """The envs' config (every env has the same)."""
        return self.envs[0].config

    # ------------------------------------------------------------------ reset
    def reset(
        self,
        *,
        seed: int | Sequence[int | None] | None = None,
        options: dict | None = None,
    ) -> tuple[Any, dict]:
        """Reset every env (or those of ``options["reset_mask"]``, a ``[N]`` bool array).

        Raises:
            ValueError, TypeError: bad seeds, mask, per-env options, or a config update of a
                fixed key (``FIXED_KEYS``); nothing changes.
        """
        seeds = self._seeds(seed)
        options = dict(options or {})
        mask = self._mask(options.pop("reset_mask", None))
        per_env = {k: self._per_env(options.pop(k, None), k) for k in ("scenes", "episode_seeds")}
        sim = self._check_reset(seeds, mask, per_env, options)
        if sim != self.loop.config:
            if not mask.all():
                raise ValueError(
                    "a reset of some envs (reset_mask) cannot change closed-loop settings: "
                    "the envs share one closed loop"
                )
            self._share(ClosedLoop(self.loop.model, sim))
        infos: dict = {}
        for i in np.flatnonzero(mask):
            env_options = dict(options)
            if per_env["scenes"][i] is not None:
                env_options["scene"] = per_env["scenes"][i]
            if per_env["episode_seeds"][i] is not None:
                env_options["episode_seed"] = per_env["episode_seeds"][i]
            self._obs[i], info = self.envs[i].reset(seed=seeds[i], options=env_options)
            infos = self._add_info(infos, info, i)
        self._terminations[mask] = self._truncations[mask] = self._ended[mask] = False
        self._rewards[mask] = 0.0
        self._started = True
        return self._batch_obs(), infos

    def _check_reset(
        self, seeds: list, mask: np.ndarray, per_env: dict[str, list], options: dict
    ) -> SimConfig:
        """Raise unless the reset can run for every env of ``mask`` (changes nothing); the
        closed-loop settings after its config update."""
        update = options.get("config") or {}
        fixed = sorted(set(FIXED_KEYS) & set(update))
        if fixed:
            raise ValueError(
                f"reset cannot change {fixed} of a vector env (its spaces and closed loop are "
                "fixed): make a new one with gymnasium.make_vec"
            )
        for key in ("scene", "episode_seed"):
            if key in options:
                raise ValueError(f"a vector env takes options[{key + 's'!r}], one per env")
        # Every env has the same config: one check for all.
        sim = self.envs[0].check_config(update)
        egos = {**self.config, **update}["controlled_vehicles"]
        for i in np.flatnonzero(mask):
            names = (f"seed[{i}]", f"options['scenes'][{i}]", f"options['episode_seeds'][{i}]")
            scene, episode_seed = per_env["scenes"][i], per_env["episode_seeds"][i]
            check_episode_inputs(seeds[i], scene, episode_seed, egos, names)
        return sim

    def _seeds(self, seed: int | Sequence[int | None] | None) -> list[int | None]:
        if seed is None:
            return [None] * self.num_envs
        if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
            return [int(seed) + i for i in range(self.num_envs)]
        if isinstance(seed, Sequence) and not isinstance(seed, str):
            if len(seed) != self.num_envs:
                raise ValueError(f"seed needs one entry per env ({self.num_envs}), got {seed!r}")
            return list(seed)
        raise TypeError(f"seed must be None, an int or a list of {self.num_envs}, got {seed!r}")

    def _mask(self, mask: Any) -> np.ndarray:
        if mask is None:
            return np.ones(self.num_envs, np.bool_)
        if not isinstance(mask, np.ndarray) or mask.dtype != np.bool_:
            raise TypeError(f"options['reset_mask'] must be a numpy bool array, got {mask!r}")
        if mask.shape != (self.num_envs,) or not mask.any():
            raise ValueError(
                f"options['reset_mask'] must have shape ({self.num_envs},) and a True entry, "
                f"got {mask!r}"
            )
        if not self._started and not mask.all():
            raise ValueError("the first reset resets every env (no reset_mask)")
        return mask

    def _per_env(self, values: Any, key: str) -> list:
        if values is None:
            return [None] * self.num_envs
        if not isinstance(values, Sequence) or len(values) != self.num_envs:
            raise ValueError(f"options[{key!r}] must be a list of {self.num_envs} (None: default)")
        return list(values)

    # ------------------------------------------------------------------ step
    def step(self, actions: Any) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict]:
        """One policy step of every env: one closed-loop step per simulation frame for all
        envs still in their policy step, so each replan is one world-model call. Envs due an
        autoreset (``NEXT_STEP``) are reset instead and their action is ignored.

        Raises:
            RuntimeError: before ``reset``, or (``DISABLED``) an ended env was not reset.
            ValueError: a bad action (any env's): nothing changes.
        """
        if not self._started:
            raise RuntimeError("call reset() before step()")
        actions = list(iterate(self.action_space, actions))
        if len(actions) != self.num_envs:
            raise ValueError(f"step needs {self.num_envs} actions, got {len(actions)}")
        resetting = self._ended.copy()  # NEXT_STEP: their autoreset; SAME_STEP: none
        if self.autoreset_mode is AutoresetMode.DISABLED and resetting.any():
            raise RuntimeError(
                f"envs {np.flatnonzero(resetting).tolist()} ended: reset them with "
                "reset(options={'reset_mask': mask}) before stepping (autoreset disabled)"
            )
        stepping = [i for i in range(self.num_envs) if not resetting[i]]
        stepped = self.step_envs(stepping, [actions[i] for i in stepping])
        results = dict(zip(stepping, stepped, strict=True))
        infos: dict = {}
        for i in range(self.num_envs):
            env = self.envs[i]
            if resetting[i]:
                self._obs[i], info = env.reset()
                self._rewards[i], self._terminations[i], self._truncations[i] = 0.0, False, False
            else:
                obs, reward, terminated, truncated, info = results[i]
                self._obs[i], self._rewards[i] = obs, reward
                self._terminations[i], self._truncations[i] = terminated, truncated
                if (terminated or truncated) and self.autoreset_mode is AutoresetMode.SAME_STEP:
                    final = {"final_obs": obs, "final_info": info}
                    infos = self._add_info(infos, final, i)
                    self._obs[i], info = env.reset()
                    terminated = truncated = False  # it goes on, reset
            infos = self._add_info(infos, info, i)
            self._ended[i] = not resetting[i] and (terminated or truncated)
        return (
            self._batch_obs(),
            self._rewards.copy(),
            self._terminations.copy(),
            self._truncations.copy(),
            infos,
        )

    def step_envs(self, indices: Sequence[int], actions: Sequence[Any]) -> list[tuple]:
        """Advance only the envs ``indices`` by one policy step, each with its action (the
        others stay as they are; no autoreset): each one's ``(obs, reward, terminated,
        truncated, info)``. Beyond Gymnasium's API: ``counterscene stress`` finishes a batch
        whose episodes end at different steps with it. Every action is checked before any env
        moves (``ValueError``: nothing changes)."""
        if not self._started:
            raise RuntimeError("call reset() before step()")
        indices = [int(i) for i in indices]
        if len(actions) != len(indices):
            raise ValueError(f"{len(indices)} envs but {len(actions)} actions")
        checked = [self.envs[i].check_step(a) for i, a in zip(indices, actions, strict=True)]
        self._run_frames(indices, checked)
        return [self.envs[i].end_step(a) for i, a in zip(indices, checked, strict=True)]

    def _run_frames(self, stepping: list[int], actions: list[Any]) -> None:
        """The frames of the envs in ``stepping``, each frame one closed-loop step for all
        of them: an env leaves when its policy step is over (its frames done, its episode
        over, or every ego ended)."""
        for i, action in zip(stepping, actions, strict=True):
            self.envs[i].begin_step(action)
        running = list(stepping)
        E = self.loop.num_egos
        while running:
            states = np.full((self.num_envs, E, 4), np.nan)
            only = np.zeros(self.num_envs, np.bool_)
            for i in running:
                states[i] = self.envs[i].advance_egos()
                only[i] = True
            with one_thread_if(any(env.recording_ahead for env in self.envs)):
                self.loop.step(ego_states=states, only=only)
            running = [i for i in running if not self.envs[i].end_frame()]

    def _batch_obs(self) -> Any:
        out = create_empty_array(self.single_observation_space, self.num_envs)
        return concatenate(self.single_observation_space, self._obs, out)

    # ------------------------------------------------------------------ the rest
    def render(self) -> tuple | None:
        """One ``[H, W, 3]`` uint8 frame per env (``render_mode="rgb_array"``)."""
        if self.render_mode is None:
            return None
        return tuple(env.render() for env in self.envs)

    def close_extras(self, **kwargs: Any) -> None:
        for env in self.envs:
            env.close()

    def _add_info(self, vector_infos: dict, env_info: dict, env_num: int) -> dict:
        """Gymnasium's vector info format (``VectorEnv._add_info``), where a key's values may
        differ in type between envs (a ``tier`` of 1 in one, None in another; an int and a
        float): the array widens to float or object instead of refusing or truncating."""
        for key, value in env_info.items():
            if isinstance(value, dict):
                vector_infos[key] = self._add_info(vector_infos.get(key, {}), value, env_num)
            else:
                array = vector_infos.get(key)
                if array is None:
                    array = _info_array(value, self.num_envs)
                array = _widened(array, value, vector_infos.get(f"_{key}"))
                array[env_num] = value
                vector_infos[key] = array
            mask = vector_infos.get(f"_{key}", np.zeros(self.num_envs, np.bool_))
            mask[env_num] = True
            vector_infos[f"_{key}"] = mask
        return vector_infos


def _info_array(value: Any, n: int) -> np.ndarray:
    """An empty info array for ``n`` envs of ``value``'s kind (as Gymnasium makes them)."""
    if type(value) in (int, float, bool) or isinstance(value, np.number):
        return np.zeros(n, dtype=type(value))
    if isinstance(value, np.ndarray):
        return np.zeros((n, *value.shape), dtype=value.dtype)
    return np.full(n, None, dtype=object)


def _widened(array: np.ndarray, value: Any, mask: np.ndarray | None) -> np.ndarray:
    """``array``, widened if it cannot hold ``value``: int or bool to float for a float,
    anything to object for a value of another kind (envs not yet reported stay None)."""
    if array.dtype == object:
        return array
    if isinstance(value, (bool, np.bool_)):
        fits = array.dtype == np.bool_
    elif isinstance(value, (int, np.integer)):
        fits = array.dtype.kind in "iuf"
    elif isinstance(value, (float, np.floating)):
        if array.dtype.kind in "iub" and array.ndim == 1:
            return array.astype(np.float64)
        fits = array.dtype.kind == "f"
    else:
        fits = isinstance(value, np.ndarray) and value.shape == array.shape[1:]
    if fits:
        return array
    widened = np.full(len(array), None, dtype=object)
    reported = np.zeros(len(array), np.bool_) if mask is None else mask
    for i in np.flatnonzero(reported):
        widened[i] = array[i].item() if array.ndim == 1 else array[i]
    return widened
