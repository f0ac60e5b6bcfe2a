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
``"scenes"``, a list of N :class:`Scene` (or None: draw one), ``"episode_seeds"``, a list
of N closed-loop seeds (or None), and ``"selection_seeds"``, a list of N seeds of a
``random`` selector's choice (or None), the per-env versions of ``"scene"``,
``"episode_seed"`` and ``"selection_seed"``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space, concatenate, create_empty_array, iterate

from counterscene_env.config import check_int
from counterscene_env.envs.batching import (
    add_info,
    attr_values,
    check_vector_modes,
    env_indices,
    expand_seeds,
    per_env_values,
    reset_mask,
)
from counterscene_env.envs.config import (
    PER_ENV_OPTIONS,
    VECTOR_RESET_OPTIONS,
    check_episode_inputs,
    reset_options,
)
from counterscene_env.envs.single_agent import CounterSceneEnv
from counterscene_env.scene.prefetch import one_thread_if
from counterscene_env.sim import ClosedLoop, SimConfig
from counterscene_env.world_model.checkpoint import shared_model

#: Config keys fixed for a vector env's life: its spaces and its shared closed loop.
FIXED_KEYS = ("observation", "action", "controlled_vehicles", "model")


def check_batch_shape(action_space: spaces.Space, actions: Any) -> None:
    """Raise unless a batch of ``Box`` actions has the batched space's shape (one row per
    env), named as a batch (e.g. one env's action given for all)."""
    if not isinstance(action_space, spaces.Box):
        return
    try:
        shape = np.shape(actions)
    except ValueError:  # ragged
        shape = "a ragged nesting"
    if shape != action_space.shape:
        raise ValueError(
            f"actions must have shape {action_space.shape} (one row per env), got {shape}"
        )


def ended_error(ended: list[int]) -> RuntimeError:
    """A step refused because envs ``ended`` have ended and autoreset is disabled."""
    return RuntimeError(
        f"envs {ended} ended: reset them with "
        "reset(options={'reset_mask': mask}) before stepping (autoreset disabled)"
    )


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
        check_int("num_envs", num_envs, ge=1)
        mode = check_vector_modes(render_mode, autoreset_mode, self.metadata["render_modes"])
        self.envs = [
            CounterSceneEnv(config=config, render_mode=render_mode, scenario=scenario)
            for _ in range(num_envs)
        ]
        first = self.envs[0]
        self._share(ClosedLoop(shared_model(first.config["model"]), first.sim_config))
        self.num_envs = num_envs
        self.render_mode = render_mode
        self.autoreset_mode = mode
        # One frame per policy step, as each env's (``render_fps``).
        self.metadata = {
            **self.metadata,
            "autoreset_mode": mode,
            "render_fps": first.metadata["render_fps"],
        }
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
        #: The index of env 0 in error messages (a worker of a sharded vector env holds envs
        #: ``first_index ..``, ``envs/sharded.py``).
        self.first_index = 0

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
        seeds, mask, per_env, options, sim = self._plan_reset(seed, options)
        if sim != self.loop.config:
            self._share(ClosedLoop(self.loop.model, sim))
        infos: dict = {}
        for i in np.flatnonzero(mask):
            env_options = dict(options)
            for key, per_env_key in PER_ENV_OPTIONS.items():
                if per_env[per_env_key][i] is not None:
                    env_options[key] = per_env[per_env_key][i]
            self._obs[i], info = self.envs[i].reset(seed=seeds[i], options=env_options)
            infos = self._add_info(infos, info, i)
        self._terminations[mask] = self._truncations[mask] = self._ended[mask] = False
        self._rewards[mask] = 0.0
        self._started = True
        self.metadata["render_fps"] = self.envs[0].metadata["render_fps"]  # policy_frequency
        return self._batch_obs(), infos

    def check_reset(
        self,
        *,
        seed: int | Sequence[int | None] | None = None,
        options: dict | None = None,
    ) -> None:
        """Raise what :meth:`reset` with these arguments would raise; change nothing."""
        self._plan_reset(seed, options)

    def _plan_reset(self, seed: Any, options: dict | None) -> tuple:
        """The checked inputs of a reset: ``(seeds, mask, per_env, options, sim)``, the
        options without the per-env keys, ``sim`` the closed-loop settings after it."""
        seeds = expand_seeds(seed, self.num_envs)
        # A single env's keys are kept, to be refused with the per-env key's name.
        options = reset_options(options, VECTOR_RESET_OPTIONS, tuple(PER_ENV_OPTIONS), 4)
        mask = reset_mask(options.pop("reset_mask", None), self.num_envs, self._started)
        per_env = {
            k: per_env_values(options.pop(k, None), k, self.num_envs)
            for k in PER_ENV_OPTIONS.values()
        }
        sim = self._check_reset(seeds, mask, per_env, options)
        if sim != self.loop.config and not mask.all():
            raise ValueError(
                "a reset of some envs (reset_mask) cannot change closed-loop settings: "
                "the envs share one closed loop"
            )
        return seeds, mask, per_env, options, sim

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
        for key, per_env_key in PER_ENV_OPTIONS.items():
            if key in options:
                raise ValueError(f"a vector env takes options[{per_env_key!r}], one per env")
        # Every env has the same config: one check for all.
        sim = self.envs[0].check_config(update)
        egos = {**self.config, **update}["controlled_vehicles"]
        for i in np.flatnonzero(mask):
            k = i + self.first_index
            names = (f"seed[{k}]", *(f"options[{key!r}][{k}]" for key in PER_ENV_OPTIONS.values()))
            # Scene, episode seed, selection seed: PER_ENV_OPTIONS' order, as the names'.
            inputs = (per_env[key][i] for key in PER_ENV_OPTIONS.values())
            check_episode_inputs(seeds[i], *inputs, egos, names)
        return sim

    # ------------------------------------------------------------------ step
    def step(self, actions: Any) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict]:
        """One policy step of every env: one closed-loop step per simulation frame for all
        envs still in their policy step, so each replan is one world-model call. Envs due an
        autoreset (``NEXT_STEP``) are reset instead and their action is ignored.

        Raises:
            RuntimeError: before ``reset``, or (``DISABLED``) an ended env was not reset.
            ValueError: a bad action (any env's): nothing changes.
        """
        actions, resetting = self._check_actions(actions)
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

    def check_step(self, actions: Any) -> None:
        """Raise what :meth:`step` with these actions would raise; change nothing."""
        actions, resetting = self._check_actions(actions)
        for i in np.flatnonzero(~resetting):
            self._check_env_step(i, actions[i])

    def _check_env_step(self, i: int, action: Any) -> Any:
        """Env ``i``'s ``check_step``; a refused action's message names the env."""
        try:
            return self.envs[i].check_step(action)
        except (TypeError, ValueError) as exc:
            kind = TypeError if isinstance(exc, TypeError) else ValueError
            raise kind(f"env {i + self.first_index}: {exc}") from exc

    def _check_actions(self, actions: Any) -> tuple[list, np.ndarray]:
        """The actions, one per env, and the envs due an autoreset (their action is ignored);
        raises before ``reset`` and, autoreset disabled, for an ended env."""
        if not self._started:
            raise RuntimeError("call reset() before step()")
        check_batch_shape(self.action_space, actions)
        actions = list(iterate(self.action_space, actions))
        if len(actions) != self.num_envs:
            raise ValueError(f"step needs {self.num_envs} actions, got {len(actions)}")
        resetting = self._ended.copy()  # NEXT_STEP: their autoreset; SAME_STEP: none
        if self.autoreset_mode is AutoresetMode.DISABLED and resetting.any():
            raise ended_error((np.flatnonzero(resetting) + self.first_index).tolist())
        return actions, resetting

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
        checked = [self._check_env_step(i, a) for i, a in zip(indices, actions, strict=True)]
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
    def call(self, name: str, *args: Any, **kwargs: Any) -> tuple:
        """Every env's ``name(*args, **kwargs)`` (or its attribute ``name``), as Gymnasium's
        ``SyncVectorEnv.call``."""
        return self.call_at(range(self.num_envs), name, args, kwargs)

    def call_at(
        self, indices: Sequence[int], name: str, args: tuple = (), kwargs: dict | None = None
    ) -> tuple:
        """:meth:`call` for the envs ``indices`` only (SB3's ``env_method``), in their order."""
        out = []
        for i in env_indices(indices, self.num_envs):
            attr = getattr(self.envs[i], name)
            out.append(attr(*args, **(kwargs or {})) if callable(attr) else attr)
        return tuple(out)

    def get_attr(self, name: str) -> tuple:
        """Every env's attribute ``name``."""
        return tuple(getattr(env, name) for env in self.envs)

    def set_attr(self, name: str, values: Any) -> None:
        """Set attribute ``name`` of every env: one value for all, or a list of one per env."""
        for env, value in zip(self.envs, attr_values(values, self.num_envs), strict=True):
            setattr(env, name, value)

    def render(self) -> tuple | None:
        """One ``[H, W, 3]`` uint8 frame per env (``render_mode="rgb_array"``)."""
        if self.render_mode is None:
            return None
        return tuple(env.render() for env in self.envs)

    def close_extras(self, **kwargs: Any) -> None:
        for env in self.envs:
            env.close()

    def _add_info(self, vector_infos: dict, env_info: dict, env_num: int) -> dict:
        """:func:`add_info` for this env's ``num_envs``."""
        return add_info(vector_infos, env_info, env_num, self.num_envs)
