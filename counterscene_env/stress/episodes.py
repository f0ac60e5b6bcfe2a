"""Running a stress run's episodes in this process: whole batches (:func:`chunks`), each run
by a runner (:class:`BatchRunner` for the reference planners, :class:`PolicyRunner` for an
sb3 policy), recorded in episode order (:class:`Progress`).

The parallel run (``stress.workers``) hands the same batches to the same runners in other
processes, so its records are those of the serial run.
"""

from __future__ import annotations

import dataclasses
import itertools
import os
import time
from collections.abc import Callable, Iterator, Sequence

import numpy as np

from counterscene_env.config import Scenario
from counterscene_env.planners import Planner, make_planner
from counterscene_env.scene.core import Scene
from counterscene_env.scene.sources import is_generated, scenes_for
from counterscene_env.sim import ClosedLoop
from counterscene_env.stress.batch import record, run_batch
from counterscene_env.stress.config import StressConfig
from counterscene_env.stress.log import PYTHON_PLANNER_KEY, EpisodeLog
from counterscene_env.stress.rollouts import keep_most_severe, rollout_seed
from counterscene_env.world_model.checkpoint import load_model
from counterscene_env.world_model.model import WorldModel


def _remaining_scenes(config: StressConfig, done: Sequence[dict], ahead: int) -> Iterator[Scene]:
    """The scenes of episodes ``len(done)`` on: a generated road restarts from the seed after
    the last done scene's (no scene is generated twice), a stored source skips ahead."""
    k = len(done)
    if config.scenario in Scenario.values() and k:
        seed = done[-1]["scene_seed"] + 1
        return scenes_for(config.scenario, config.episodes - k, seed, ahead=ahead)
    scenes = scenes_for(
        config.scenario, config.episodes, config.seed, config.egos, ahead, config.min_future
    )
    return itertools.islice(scenes, k, None)


def first_to_run(config: StressConfig, done: Sequence[dict]) -> int:
    """The first episode of the first batch :func:`chunks` runs after the ``done`` ones:
    the start of the batch ``len(done)`` falls in, or ``config.episodes`` when all are done."""
    if len(done) >= config.episodes:
        return config.episodes
    return len(done) - len(done) % config.batch


def chunks(
    config: StressConfig, done: Sequence[dict], ahead: int = 0
) -> Iterator[tuple[int, list[Scene]]]:
    """The batches still to run after the ``done`` episodes, in order: ``(first episode
    index, its scenes)``, each of ``config.batch`` episodes (the last may be
    shorter). Batch boundaries fall at the same episodes in every run of a config, so a batch
    cut short by a kill (some of its episodes recorded) is run again whole: the episodes still
    missing then come from a batch of the uninterrupted run's composition (the recorded ones
    are kept, :class:`Progress`). Never more scenes are drawn than the batches need; with
    ``ahead > 0``, up to ``ahead`` generated seeds are recorded in the background before they
    are (``scene.sources.scenes_for``)."""
    index = first_to_run(config, done)
    size = config.batch
    scenes = _remaining_scenes(config, done[:index], ahead)
    while index < config.episodes:
        chunk = list(itertools.islice(scenes, min(size, config.episodes - index)))
        if not chunk:
            return
        yield index, chunk
        index += len(chunk)


class Progress:
    """The finished episodes of a run: appended to its log in episode order, counted on a
    progress bar (with ETA) and in the running collision rate.

    Args:
        config: the run.
        log: its :class:`EpisodeLog` (its records of episodes ``< config.episodes`` count as
            done), or None.
        progress: show the bar.
    """

    def __init__(self, config: StressConfig, log: EpisodeLog | None, progress: bool) -> None:
        from tqdm.auto import tqdm

        self.log = log
        self.records: list[dict] = [] if log is None else log.records[: config.episodes]
        self.bar = tqdm(
            total=config.episodes,
            initial=len(self.records),  # the ETA counts only this invocation's episodes
            desc="stress",
            unit="ep",
            disable=not progress,
            dynamic_ncols=True,
        )

    def add(self, batch: list[dict]) -> None:
        """A finished batch, the next episodes in order (those already recorded, of a batch
        that a kill cut short and :func:`chunks` ran again, are left as recorded)."""
        batch = [r for r in batch if r["episode"] >= len(self.records)]
        if not batch:
            return
        if batch[0]["episode"] != len(self.records):
            raise RuntimeError(
                f"stress: episode {batch[0]['episode']} finished before episode "
                f"{len(self.records)} was recorded"
            )
        if self.log is not None:
            self.log.append(batch)
        self.records += batch
        self.bar.update(len(batch))
        self.bar.set_postfix(cr=f"{np.mean([r['cr'] for r in self.records]):.2f}")

    def close(self) -> None:
        self.bar.close()


class BatchRunner:
    """Runs batches of episodes of a reference (or custom) planner in one closed loop:
    ``runner(first, scenes)`` runs episodes ``first ..`` with seeds ``config.seed + first ..``.

    Args:
        model: the world model.
        config: the run.
        planner_factory: a fresh planner per episode; default ``make_planner(config.planner)``.
    """

    def __init__(
        self,
        model: WorldModel,
        config: StressConfig,
        planner_factory: Callable[[], Planner] | None = None,
    ) -> None:
        self.config = config
        self.factory = planner_factory or (lambda: make_planner(config.planner))
        self.custom = planner_factory is not None
        self.loop = ClosedLoop(model, config.sim)

    def __call__(self, first: int, scenes: Sequence[Scene]) -> list[dict]:
        def run(seeds: list[int], selection_seeds: list[int]) -> list[dict]:
            planners = [self.factory() for _ in scenes]
            records = run_batch(self.loop, scenes, seeds, planners, first, selection_seeds)
            if self.custom:  # not config.planner: the record says which planner drove
                for rec, planner in zip(records, planners, strict=True):
                    rec[PYTHON_PLANNER_KEY] = str(getattr(planner, "name", type(planner).__name__))
            return records

        return candidate_rollouts(run, self.config, first, len(scenes))

    def close(self) -> None:
        pass


#: Env-config keys a stress run sets itself besides the closed-loop settings (``SIM_KEYS``):
#: its scenes, model and episode ends. A policy's sidecar or ``--env-config`` may set none.
RUN_KEYS = ("scenario", "model", "terminate_on_collision", "terminate_on_off_road")


class PolicyRunner:
    """Runs batches of episodes of an ``sb3:PATH.zip`` planner through ``CounterScene-v0``
    (see :func:`run_policy_episodes`); ``runner(first, scenes)`` as :class:`BatchRunner`. A
    batch's episodes run in one vector env (``envs/vector.py``: one world-model call per
    replan for all of them), each exactly as in a single env of its own.

    Args:
        config: the run.
        model: the world model's directory (``"default"``: the shipped one).
        env_config: env-config keys on top of the policy's ``PATH.env.json`` sidecar.
        policy: the policy's ``.zip`` (default ``config.policy_path``; a Ray worker passes
            its local copy).

    Raises:
        ValueError: the policy's spaces do not match the env's (the message names both).
    """

    def __init__(
        self,
        config: StressConfig,
        model: str = "default",
        env_config: dict | None = None,
        policy: str | os.PathLike | None = None,
    ) -> None:
        from counterscene_env.envs.config import SIM_KEYS
        from counterscene_env.envs.single_agent import CounterSceneEnv
        from counterscene_env.planners import SB3Policy

        self.config = config
        self.policy = SB3Policy(config.policy_path if policy is None else policy)
        for given, where in (
            (self.policy.env_config, f"{self.policy.path.name}'s .env.json sidecar"),
            (env_config or {}, "--env-config"),
        ):
            run_keys = sorted(set(given) & {*RUN_KEYS, *SIM_KEYS}, key=str)
            if run_keys:  # the run's own settings would overwrite them: refuse, never drop
                raise ValueError(
                    f"{where} sets {run_keys}, which the stress run sets itself: pass them as "
                    "its flags (--scenario, --model, --duration, --guidance, ...); the policy's "
                    "env config holds what it sees, does and when (observation, action, "
                    "policy_frequency, rewards)"
                )
        settings = {
            **self.policy.env_config,
            **(env_config or {}),
            "scenario": config.scenario if config.scenario in Scenario.values() else "merge",
            "model": model,
            **dataclasses.asdict(config.sim),  # every closed-loop setting
            "terminate_on_collision": False,
            "terminate_on_off_road": False,
        }
        self.settings = settings
        probe = CounterSceneEnv(config=settings)  # checks the settings; its spaces
        self.policy.bind(probe.observation_space, probe.action_space)
        probe.close()

    def __call__(self, first: int, scenes: Sequence[Scene]) -> list[dict]:
        return candidate_rollouts(
            lambda seeds, chosen: self._run(first, scenes, seeds, chosen),
            self.config,
            first,
            len(scenes),
        )

    def _run(
        self, first: int, scenes: Sequence[Scene], seeds: list[int], selection_seeds: list[int]
    ) -> list[dict]:
        """The batch's episodes with closed-loop seeds ``seeds`` and selection seeds
        ``selection_seeds``, one record each."""
        from gymnasium.vector import AutoresetMode
        from gymnasium.vector.utils import iterate

        from counterscene_env.envs.vector import CounterSceneVectorEnv

        B = len(scenes)
        start = time.perf_counter()
        venv = CounterSceneVectorEnv(B, self.settings, autoreset_mode=AutoresetMode.DISABLED)
        options = {
            "scenes": list(scenes),
            "episode_seeds": seeds,
            "selection_seeds": selection_seeds,
        }
        obs, _ = venv.reset(seed=seeds, options=options)
        current = list(iterate(venv.observation_space, obs))
        running = list(range(B))
        while running:  # each policy decision on its own observation, as in a single env
            results = venv.step_envs(running, [self.policy.predict(current[i]) for i in running])
            for i, (o, _, terminated, truncated, _) in zip(running, results, strict=True):
                current[i] = None if terminated or truncated else o
            running = [i for i in running if current[i] is not None]
        share = (time.perf_counter() - start) / B
        records = [
            record(venv.loop, b, scene, seeds[b], share, first + b)
            for b, scene in enumerate(scenes)
        ]
        venv.close()
        return records

    def close(self) -> None:
        pass


def candidate_rollouts(
    run: Callable[[list[int], list[int]], list[dict]],
    config: StressConfig,
    first: int,
    size: int,
) -> list[dict]:
    """The records of episodes ``first .. first + size``: ``run(seeds, selection_seeds)``
    plays the batch with those closed-loop seeds (the episodes' own, ``config.seed + i``)
    and seeds of a ``random`` selector's choice (the episodes' own too); with
    ``config.rollouts`` K > 1 it plays it K times, candidate k with closed-loop seeds
    ``rollouts.rollout_seed(seed, k)`` and the same selection seeds (every candidate of an
    episode has the same adversary: the protocol varies the noise, not the choice), and
    each episode keeps its most severe candidate for the ego (``rollouts.keep_most_severe``)."""
    seeds = [config.seed + first + b for b in range(size)]
    if config.rollouts == 1:
        return run(seeds, seeds)
    return keep_most_severe(
        [run([rollout_seed(s, k) for s in seeds], seeds) for k in range(config.rollouts)]
    )


def make_runner(
    config: StressConfig,
    model: str = "default",
    env_config: dict | None = None,
    planner_factory: Callable[[], Planner] | None = None,
    policy: str | os.PathLike | None = None,
) -> BatchRunner | PolicyRunner:
    """The serial run's runner for ``config``, built in this process (the parallel and Ray
    runs build theirs with it, so every run of a config runs its batches alike).

    Args:
        config: the run.
        model: the world model's directory (``"default"``: the shipped one), loaded here.
        env_config: sb3 planners: env-config keys on top of the policy's sidecar.
        planner_factory: a fresh planner per episode (default ``make_planner(config.planner)``).
        policy: sb3 planners: the policy's ``.zip`` (default ``config.policy_path``).
    """
    if config.is_sb3:
        return PolicyRunner(config, model, env_config, policy)
    return BatchRunner(load_model(model), config, planner_factory)


def drive(
    runner: Callable[[int, list[Scene]], list[dict]],
    config: StressConfig,
    progress: bool = True,
    log: EpisodeLog | None = None,
) -> list[dict]:
    """Every batch still to run (:func:`chunks`), one after the other, through ``runner``;
    the records of all episodes of the run, in order."""
    tally = Progress(config, log, progress)
    # The next batch's scenes are recorded in the background while this one runs
    # (scene/prefetch.py; batch.play_batch steps on one torch thread meanwhile).
    ahead = 2 * config.batch if is_generated(config.scenario) else 0  # scenes_for: if it can
    try:
        for first, scenes in chunks(config, tally.records, ahead):
            tally.add(runner(first, scenes))
    finally:
        tally.close()
    return tally.records


def run_episodes(
    model: WorldModel,
    config: StressConfig,
    planner_factory: Callable[[], Planner] | None = None,
    progress: bool = True,
    log: EpisodeLog | None = None,
) -> list[dict]:
    """Run every episode; one record per episode (:func:`metrics.evaluate_scene` plus the
    episode index, selection, seeds and timing). With a ``log``, episodes it holds are not
    run again and each finished batch is appended to it."""
    return drive(BatchRunner(model, config, planner_factory), config, progress, log)


def run_policy_episodes(
    config: StressConfig,
    model: str = "default",
    env_config: dict | None = None,
    progress: bool = True,
    log: EpisodeLog | None = None,
) -> list[dict]:
    """Run every episode of an ``sb3:PATH.zip`` planner through ``CounterScene-v0`` (a
    ``log`` as in :func:`run_episodes`).

    The policy sees the env's highway-env observations and acts through its action type.
    Episode i runs the same scene and closed-loop seed as :func:`run_episodes` would
    (``reset(options={"scene": ..., "episode_seed": seed + i})``) and runs to its end, as the
    other planners' do (collisions and leaving the road do not end it). A batch of
    ``config.batch`` episodes runs in one vector env and gives the records of single envs. The env's
    observation and action config come from ``env_config``, else from the policy's
    ``PATH.env.json`` sidecar, else the env's defaults.

    Raises:
        ValueError: the policy's spaces do not match the env's (the message names both).
    """
    runner = PolicyRunner(config, model, env_config)
    try:
        return drive(runner, config, progress, log)
    finally:
        runner.close()
