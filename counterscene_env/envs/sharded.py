"""``workers=W``: a vector env's N envs in W processes, each one batched closed loop.

A :class:`~counterscene_env.envs.vector.CounterSceneVectorEnv` runs in one process: its
world-model calls use both cores, but the rest of a step (the envs' motion, the guidance's
and lane keeping's small tensor operations, highway-env's observations) runs on one. With
``workers=2`` the N envs are split into two contiguous shards, each a
``CounterSceneVectorEnv`` in its own process with one torch thread, stepped side by side:
on stored scenes 16 envs step 1.16x as fast as in one process at a 10 Hz policy and 1.25x at
2 Hz (docs/performance.md, "Vector env"). With fresh highway-env scenes the recordings
already keep the second core busy, and two workers gain nothing.

Env ``i`` is env ``i - first`` of the shard that holds it, and every env plays exactly the
episode of a single env with the same seed and actions, so the episodes do not depend on
``workers``. Every call is checked by all shards before any of them acts: a refused
``reset`` or ``step`` leaves every env as it was, and error messages name the env's index in
the whole vector env.
"""

from __future__ import annotations

import itertools
import multiprocessing as mp
import signal
import traceback
from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np
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
    unbatch_info,
)
from counterscene_env.envs.config import PER_ENV_OPTIONS, VECTOR_RESET_OPTIONS, reset_options
from counterscene_env.envs.vector import CounterSceneVectorEnv, check_batch_shape, ended_error

#: Errors a worker hands back as they are: bad input, named by its key or env.
USER_ERRORS = (ValueError, TypeError, RuntimeError, AttributeError)


def vector_env(num_envs: int = 1, workers: int = 1, **kwargs: Any) -> VectorEnv:
    """The vector env of ``gymnasium.make_vec("CounterScene-v0", num_envs=N, workers=W)``
    (Gymnasium passes keywords of a ``vector_entry_point`` through as they are): one
    :class:`CounterSceneVectorEnv` for ``workers=1`` (the default), else a
    :class:`ShardedVectorEnv`. ``kwargs``: the vector env's (``config``, ``render_mode``,
    ``scenario``, ``autoreset_mode``)."""
    if check_int("workers", workers, ge=1) == 1:
        return CounterSceneVectorEnv(num_envs, **kwargs)
    return ShardedVectorEnv(num_envs, workers, **kwargs)


class ShardedVectorEnv(VectorEnv):
    """N ``CounterScene-v0`` envs in ``workers`` processes (module doc).

    Args:
        num_envs: N (>= ``workers``).
        workers: processes (>= 2); shard ``w`` holds ``N // workers`` envs, one more for the
            first ``N % workers``.
        config, render_mode, scenario, autoreset_mode: as :class:`CounterSceneVectorEnv`.
    """

    metadata: ClassVar[dict] = CounterSceneVectorEnv.metadata

    def __init__(
        self,
        num_envs: int,
        workers: int,
        config: dict | None = None,
        render_mode: str | None = None,
        scenario: str | None = None,
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
    ) -> None:
        check_int("num_envs", num_envs, ge=1)
        check_int("workers", workers, ge=2)
        # Refused here, before any process starts (each worker's env checks them again).
        check_vector_modes(render_mode, autoreset_mode, self.metadata["render_modes"])
        if workers > num_envs:
            raise ValueError(f"workers ({workers}) cannot exceed num_envs ({num_envs})")
        sizes = [num_envs // workers + (w < num_envs % workers) for w in range(workers)]
        starts = np.cumsum([0, *sizes])
        self.shards = [slice(int(a), int(b)) for a, b in itertools.pairwise(starts)]
        self.num_envs = num_envs
        self.render_mode = render_mode
        self._pipes: list = []
        self._processes: list = []
        ctx = mp.get_context("spawn")
        kwargs = {
            "config": config,
            "render_mode": render_mode,
            "scenario": scenario,
            "autoreset_mode": autoreset_mode,
        }
        try:
            for shard in self.shards:
                parent, child = ctx.Pipe()
                # Daemonic: a worker ends with its parent even if close() was never called
                # (it then records fresh scenes itself, as in SB3's SubprocVecEnv).
                process = ctx.Process(
                    target=_serve,
                    args=(child, shard.stop - shard.start, shard.start, kwargs),
                    daemon=True,
                )
                process.start()
                child.close()
                self._pipes.append(parent)
                self._processes.append(process)
            spaces = self._gather(range(len(self.shards)))[0]
        except BaseException:
            self._stop()
            raise
        self.single_observation_space, self.single_action_space, mode, fps = spaces
        self.autoreset_mode = mode
        # One frame per policy step, as the workers' envs (``render_fps``).
        self.metadata = {**self.metadata, "autoreset_mode": mode, "render_fps": fps}
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._obs: list[Any] = [None] * num_envs
        self._started = False
        self._ended = np.zeros(num_envs, bool)  # autoreset disabled: ended, awaiting a reset

    @property
    def workers(self) -> int:
        """Processes."""
        return len(self.shards)

    # ------------------------------------------------------------------ reset and step
    def reset(
        self,
        *,
        seed: int | Sequence[int | None] | None = None,
        options: dict | None = None,
    ) -> tuple[Any, dict]:
        """:meth:`CounterSceneVectorEnv.reset`, every shard's envs at once (same arguments,
        same errors: nothing changes when any shard refuses)."""
        seeds = expand_seeds(seed, self.num_envs)
        # A single env's keys are kept, to be refused with the per-env key's name.
        options = reset_options(options, VECTOR_RESET_OPTIONS, tuple(PER_ENV_OPTIONS), 4)
        mask = reset_mask(options.pop("reset_mask", None), self.num_envs, self._started)
        per_env = {
            k: per_env_values(options.pop(k, None), k, self.num_envs)
            for k in PER_ENV_OPTIONS.values()
        }
        if "config" in options and not mask.all():
            # A shard whose envs are all reset would accept a change of closed-loop settings
            # that the others refuse: ask one shard whether it is one.
            self._send(0, "changes_sim", options["config"])
            if self._gather([0])[0]:
                raise ValueError(
                    "a reset of some envs (reset_mask) cannot change closed-loop settings: "
                    "the envs share one closed loop"
                )
        calls = {}
        for w, shard in enumerate(self.shards):
            if not mask[shard].any():
                continue
            local = {**options, **{k: v[shard] for k, v in per_env.items()}}
            if not mask.all():
                local["reset_mask"] = mask[shard].copy()
            calls[w] = {"seed": seeds[shard], "options": local}
        for name in ("check_reset", "reset"):
            for w, call in calls.items():
                self._send(w, name, call)
            results = self._gather(list(calls))
        infos: dict = {}
        for (w, call), (obs, shard_infos) in zip(calls.items(), results, strict=True):
            self._unpack(w, obs, shard_infos, infos, call["options"].get("reset_mask"))
        self._started = True
        self._ended[mask] = False
        if "config" in options:  # a new policy_frequency plays at its own speed
            self._send(0, "get_attr", "metadata")
            self.metadata["render_fps"] = self._gather([0])[0][0]["render_fps"]
        return self._batch_obs(), infos

    def step(self, actions: Any) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict]:
        """:meth:`CounterSceneVectorEnv.step`, every shard's envs side by side."""
        if not self._started:
            raise RuntimeError("call reset() before step()")
        check_batch_shape(self.action_space, actions)
        actions = list(iterate(self.action_space, actions))
        if len(actions) != self.num_envs:
            raise ValueError(f"step needs {self.num_envs} actions, got {len(actions)}")
        if self._ended.any():  # every ended env named at once, as one process names them
            raise ended_error(np.flatnonzero(self._ended).tolist())
        every = range(len(self.shards))
        for name in ("check_step", "step"):
            for w, shard in enumerate(self.shards):
                self._send(w, name, self._batch_actions(actions[shard]))
            results = self._gather(every)
        rewards, terminations, truncations = (
            np.zeros(self.num_envs, t) for t in (float, bool, bool)
        )
        infos: dict = {}
        for w, (obs, reward, terminated, truncated, shard_infos) in enumerate(results):
            shard = self.shards[w]
            rewards[shard], terminations[shard], truncations[shard] = reward, terminated, truncated
            self._unpack(w, obs, shard_infos, infos)
        if self.autoreset_mode is AutoresetMode.DISABLED:
            self._ended = terminations | truncations
        return self._batch_obs(), rewards, terminations, truncations, infos

    def _batch_actions(self, actions: list) -> Any:
        out = create_empty_array(self.single_action_space, len(actions))
        return concatenate(self.single_action_space, actions, out)

    def _unpack(
        self, w: int, obs: Any, shard_infos: dict, infos: dict, mask: np.ndarray | None = None
    ) -> None:
        """Shard ``w``'s batched obs and infos into this env's (only its envs of ``mask``)."""
        shard = self.shards[w]
        for j, o in enumerate(iterate(self._shard_space(w), obs)):
            if mask is None or mask[j]:
                self._obs[shard.start + j] = o
        for j in range(shard.stop - shard.start):
            if mask is None or mask[j]:
                add_info(infos, unbatch_info(shard_infos, j), shard.start + j, self.num_envs)

    def _shard_space(self, w: int):
        return batch_space(
            self.single_observation_space, self.shards[w].stop - self.shards[w].start
        )

    def _batch_obs(self) -> Any:
        out = create_empty_array(self.single_observation_space, self.num_envs)
        return concatenate(self.single_observation_space, self._obs, out)

    # ------------------------------------------------------------------ env access
    def call(self, name: str, *args: Any, **kwargs: Any) -> tuple:
        """Every env's ``name(*args, **kwargs)`` (or attribute ``name``), in env order."""
        return self.call_at(range(self.num_envs), name, args, kwargs)

    def call_at(
        self, indices: Sequence[int], name: str, args: tuple = (), kwargs: dict | None = None
    ) -> tuple:
        """:meth:`call` for the envs ``indices`` only, in their order."""
        indices = env_indices(indices, self.num_envs)
        asked = {}  # shard -> the global indices it is asked for
        for w, shard in enumerate(self.shards):
            mine = [i for i in indices if shard.start <= i < shard.stop]
            if mine:
                self._send(w, "call_at", ([i - shard.start for i in mine], name, args, kwargs))
                asked[w] = mine
        values = {}
        for mine, part in zip(asked.values(), self._gather(list(asked)), strict=True):
            values.update(zip(mine, part, strict=True))
        return tuple(values[i] for i in indices)

    def get_attr(self, name: str) -> tuple:
        """Every env's attribute ``name``."""
        for w in range(len(self.shards)):
            self._send(w, "get_attr", name)
        return tuple(x for part in self._gather(range(len(self.shards))) for x in part)

    def set_attr(self, name: str, values: Any) -> None:
        """Set attribute ``name`` of every env: one value for all, or a list of one per env."""
        values = attr_values(values, self.num_envs)
        for w, shard in enumerate(self.shards):
            self._send(w, "set_attr", (name, values[shard]))
        self._gather(range(len(self.shards)))

    def render(self) -> tuple | None:
        """One ``[H, W, 3]`` uint8 frame per env (``render_mode="rgb_array"``)."""
        if self.render_mode is None:
            return None
        return self.call("render")

    # ------------------------------------------------------------------ processes
    def _send(self, w: int, name: str, payload: Any = None) -> None:
        self._pipes[w].send((name, payload))

    def _gather(self, shards: Sequence[int]) -> list:
        """Every shard's answer, in order; the first error is raised after all answered."""
        answers = []
        for w in shards:
            try:
                answers.append(self._pipes[w].recv())
            except (EOFError, OSError) as exc:
                why = (
                    f"worker {w} stopped ({exc!r}). Workers are spawned processes: a script "
                    "that makes the env with workers > 1 must run its top-level code under "
                    "`if __name__ == '__main__':` (Python's multiprocessing)"
                )
                answers.append(("died", why))
        for status, value in answers:
            if status == "error":
                kind, message = value
                raise USER_ERRORS[kind](message)
            if status in ("failed", "died"):
                raise RuntimeError(f"a vector env worker failed:\n{value}")
        return [value for _, value in answers]

    def close_extras(self, **kwargs: Any) -> None:
        self._stop()

    def __del__(self) -> None:
        # As Gymnasium's AsyncVectorEnv: the workers go with the env (getattr: __init__ may
        # have failed before setting anything).
        if getattr(self, "_pipes", None) and not self.closed:
            self.close()

    def _stop(self) -> None:
        for pipe in self._pipes:
            try:
                pipe.send(("close", None))
            except (BrokenPipeError, OSError):
                pass
        for process in self._processes:
            process.join(timeout=10)
            if process.is_alive():
                process.terminate()
        for pipe in self._pipes:
            pipe.close()
        self._pipes, self._processes = [], []


def _serve(pipe, num_envs: int, first: int, kwargs: dict) -> None:
    """A worker: one :class:`CounterSceneVectorEnv` of envs ``first ..``, driven by the
    parent's commands until ``close`` (or the parent's end)."""
    import torch

    # Ctrl-C reaches the parent, which closes the workers (a worker stopped mid-step would
    # leave its shard's envs in between).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    torch.set_num_threads(1)
    try:
        venv = CounterSceneVectorEnv(num_envs, **kwargs)
        venv.first_index = first
        pipe.send(
            (
                "ok",
                (
                    venv.single_observation_space,
                    venv.single_action_space,
                    venv.autoreset_mode,
                    venv.metadata["render_fps"],
                ),
            )
        )
    except Exception as exc:  # handed to the parent, which raises it
        pipe.send(_failure(exc))
        return
    while True:
        try:
            name, payload = pipe.recv()
        except (EOFError, OSError):
            break
        if name == "close":
            break
        try:
            pipe.send(("ok", _run(venv, name, payload)))
        except Exception as exc:
            pipe.send(_failure(exc))
    venv.close()
    pipe.close()


def _run(venv: CounterSceneVectorEnv, name: str, payload: Any) -> Any:
    if name == "check_reset":
        return venv.check_reset(**payload)
    if name == "reset":
        return venv.reset(**payload)
    if name == "check_step":
        return venv.check_step(payload)
    if name == "step":
        return venv.step(payload)
    if name == "changes_sim":
        return venv.envs[0].check_config(payload) != venv.loop.config
    if name == "call_at":
        return venv.call_at(*payload)
    if name == "get_attr":
        return venv.get_attr(payload)
    if name == "set_attr":
        return venv.set_attr(*payload)
    raise ValueError(f"unknown vector env worker command {name!r}")


def _failure(exc: Exception) -> tuple[str, Any]:
    """What a worker sends back: a user error as its built-in kind and message (a subclass
    need not unpickle in the parent), anything else as its traceback."""
    for kind, error in enumerate(USER_ERRORS):
        if isinstance(exc, error):
            return "error", (kind, str(exc))
    return "failed", "".join(traceback.format_exception(exc))
