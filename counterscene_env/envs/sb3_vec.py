"""Stable-Baselines3 on the batched vector env: :class:`SB3VecEnv`.

SB3 algorithms take an SB3 ``VecEnv``, whose convention differs from Gymnasium 1.x's: an env
that ends is reset in the same step, ``done = terminated or truncated``, its last observation
is ``infos[i]["terminal_observation"]``, a time-limit end is flagged
``infos[i]["TimeLimit.truncated"]``, and infos are a list of one dict per env. This adapter
runs :class:`~counterscene_env.envs.vector.CounterSceneVectorEnv` in Gymnasium's
``SAME_STEP`` autoreset mode and translates; every replan stays one world-model call for all
envs (with ``workers=W``, for all envs of each of W processes: ``envs/sharded.py``). Wrap it in SB3's ``VecMonitor`` for episode returns in the training log::

    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecMonitor
    from counterscene_env.envs.sb3_vec import SB3VecEnv

    venv = VecMonitor(SB3VecEnv(num_envs=16, config={"policy_frequency": 2}))
    PPO("MlpPolicy", venv).learn(10_000)
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from gymnasium.vector import AutoresetMode
from stable_baselines3.common.vec_env import VecEnv

from counterscene_env.envs.batching import unbatch_info
from counterscene_env.envs.sharded import vector_env


class SB3VecEnv(VecEnv):
    """An SB3 ``VecEnv`` of N ``CounterScene-v0`` envs in one closed loop.

    Args:
        num_envs: N (>= 1).
        config: the single env's config keys, for every env (``docs/environment.md``).
        scenario: the default scenario.
        workers: processes the envs are split over (``envs/sharded.py``; 1: this process).
    """

    def __init__(
        self,
        num_envs: int,
        config: dict | None = None,
        scenario: str | None = None,
        workers: int = 1,
    ):
        self.venv = vector_env(
            num_envs,
            workers,
            config=config,
            scenario=scenario,
            autoreset_mode=AutoresetMode.SAME_STEP,
        )
        self._actions: np.ndarray | None = None
        super().__init__(
            num_envs, self.venv.single_observation_space, self.venv.single_action_space
        )

    def reset(self) -> Any:
        """Reset every env, with the seeds and options set by ``seed()`` / ``set_options()``
        (used once, SB3's convention)."""
        seeds = None if all(s is None for s in self._seeds) else list(self._seeds)
        options = self._options[0] if all(o == self._options[0] for o in self._options) else None
        if options is None:
            raise ValueError("SB3VecEnv takes the same options for every env")
        obs, infos = self.venv.reset(seed=seeds, options=options or None)
        self.reset_infos = [unbatch_info(infos, i) for i in range(self.num_envs)]
        self._reset_seeds()
        self._reset_options()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self) -> tuple[Any, np.ndarray, np.ndarray, list[dict]]:
        if self._actions is None:
            raise RuntimeError("step_wait() without step_async()")
        actions, self._actions = self._actions, None
        obs, rewards, terminated, truncated, infos = self.venv.step(actions)
        dones = terminated | truncated
        out = []
        for i in range(self.num_envs):
            if dones[i]:
                info = unbatch_info(infos["final_info"], i)
                info["terminal_observation"] = infos["final_obs"][i]
                info["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
                reset_info = unbatch_info(infos, i)
                for key in ("final_obs", "final_info"):
                    reset_info.pop(key)
                self.reset_infos[i] = reset_info
            else:
                info = unbatch_info(infos, i)
            out.append(info)
        return obs, rewards.astype(np.float32), dones, out

    def close(self) -> None:
        self.venv.close()

    # ------------------------------------------------------------------ SB3's env access
    def get_attr(self, attr_name: str, indices: Any = None) -> list[Any]:
        indices = list(self._get_indices(indices))
        return list(self.venv.call_at(indices, "__getattribute__", (attr_name,)))

    def set_attr(self, attr_name: str, value: Any, indices: Any = None) -> None:
        indices = list(self._get_indices(indices))
        self.venv.call_at(indices, "__setattr__", (attr_name, value))

    def env_method(
        self, method_name: str, *method_args: Any, indices: Any = None, **method_kwargs: Any
    ) -> list[Any]:
        indices = list(self._get_indices(indices))
        return list(self.venv.call_at(indices, method_name, method_args, method_kwargs))

    def env_is_wrapped(self, wrapper_class: type, indices: Any = None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]  # the envs are bare

    def get_images(self) -> Sequence[np.ndarray | None]:
        return list(self.venv.call("render"))
