"""Stress runs: an ego planner against world-model traffic with a guided adversary, scored
as the paper's tables (``counterscene stress``).

Episode i of a run uses the i-th scene of its source (``scene.sources.scenes_for``: generated
scenarios, the i-th safe seed from ``seed``, as ``counterscene generate`` picks them;
``scenarionet:DIR``, the i-th ``.pkl`` file of DIR, sorted; a dataset directory, its i-th
scene; sources are cycled when there are more episodes than scenes) and seed ``seed + i`` for
its sampling noise. So every row of a comparison (guidance presets, selectors) sees the same
scenes and the same noise, and an episode's result does not depend on the batch it ran in.

The summary (:func:`summarize`) is the paper's table row: ADE, FDE, ORR, HBR, CR for the
horizon groups 1-4 s, 5-7 s, 8-10 s and per second (CR at second h counts episodes with an ego
collision at or before h), plus the whole-episode rates, ego-vs-adversary collisions, mean
min TTC, fallbacks and timing.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
import os
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from counterscene_env import metrics
from counterscene_env.config import Scenario
from counterscene_env.planners import Planner, make_planner
from counterscene_env.scene.core import Scene
from counterscene_env.scene.sources import SKIPPED, check_spec, scenes_for
from counterscene_env.sim import ClosedLoop, SimConfig
from counterscene_env.world_model.model import WorldModel

#: Prefix of a Stable-Baselines3 policy in ``--planner`` (``sb3:PATH.zip``).
SB3_PREFIX = "sb3:"


@dataclass(frozen=True)
class StressConfig:
    """One stress run.

    Attributes:
        scenario: ``highway``, ``merge``, ``intersection``, ``roundabout``,
            ``scenarionet:DIR``, or a dataset directory (``counterscene generate --out``).
        episodes: number of episodes.
        seed: seed of episode 0 (episode i: ``seed + i``).
        planner: ego planner name (``idm``, ``idm_yield``, ``constant_velocity``, ``log``),
            or ``sb3:PATH.zip``: a Stable-Baselines3 policy, run through ``CounterScene-v0``
            (:func:`run_policy_episodes`).
        sim: closed-loop settings (selector, guidance, samples, ...).
        batch: episodes advanced together (one world-model call per replan).
    """

    scenario: str
    episodes: int = 50
    seed: int = 0
    planner: str = "idm"
    sim: SimConfig = dataclasses.field(default_factory=SimConfig)
    batch: int = 4

    def __post_init__(self) -> None:
        if self.episodes < 1:
            raise ValueError(f"episodes must be >= 1, got {self.episodes}")
        if self.batch < 1:
            raise ValueError(f"batch must be >= 1, got {self.batch}")
        check_spec(self.scenario)
        if self.planner.startswith(SB3_PREFIX):
            path = Path(self.planner.removeprefix(SB3_PREFIX))
            if not path.is_file():
                raise ValueError(f"planner {self.planner!r}: no such SB3 policy file {path}")
        else:
            make_planner(self.planner)  # raises on an unknown name

    def to_dict(self) -> dict:
        out = dataclasses.asdict(self)
        out["sim"] = dataclasses.asdict(self.sim)
        return out


class EpisodeLog:
    """A stress run's durable record: ``DIR/episodes.jsonl``, one line per finished episode.

    Each batch's records are appended, flushed and synced to disk as the batch finishes, so a
    killed run (Ctrl-C, a crash, a lost machine) loses only the episodes in flight. Rerunning
    the same command resumes after the last recorded episode; a larger ``--episodes``
    extends the run. ``DIR/run.json`` holds what the run is (the config but its episode
    count, and the model): a rerun with anything else is refused, so one directory never
    mixes two runs.

    Args:
        directory: the run's output directory (created).
        identity: what the run is, as plain JSON values.

    Raises:
        ValueError: ``directory`` holds another run (the message names the differing keys).
    """

    def __init__(self, directory: str | os.PathLike, identity: dict) -> None:
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.path = self.dir / "episodes.jsonl"
        run = self.dir / "run.json"
        identity = json.loads(json.dumps(metrics.json_safe(identity)))
        if run.is_file():
            have = json.loads(run.read_text())
            if have != identity:
                keys = sorted(
                    k for k in set(have) | set(identity) if have.get(k) != identity.get(k)
                )
                raise ValueError(
                    f"{self.dir} holds a stress run with other settings ({', '.join(keys)}): "
                    "use another --out, or delete it to start over"
                )
        else:
            run.write_text(json.dumps(identity, indent=2) + "\n")
        self.records = self._read()

    def _read(self) -> list[dict]:
        """The finished episodes on disk, in order; a last line cut short by a kill is
        dropped (and removed from the file)."""
        if not self.path.is_file():
            return []
        text = self.path.read_text()
        lines = text.splitlines()
        records = []
        for n, line in enumerate(lines):
            try:
                records.append(json.loads(line))
            except json.JSONDecodeError:
                if n != len(lines) - 1:
                    raise ValueError(f"{self.path}: line {n + 1} is not JSON") from None
        if text and (len(records) < len(lines) or not text.endswith("\n")):
            # A kill mid-line: keep the whole records, each ended, so appends start afresh.
            self.path.write_text("".join(f"{x}\n" for x in lines[: len(records)]))
        for i, rec in enumerate(records):
            if rec.get("episode") != i:
                raise ValueError(f"{self.path}: line {i + 1} is not episode {i}")
        return [_from_json(rec) for rec in records]

    def append(self, records: Sequence[dict]) -> None:
        """Add finished episodes, on disk before this returns."""
        with open(self.path, "a") as f:
            for rec in records:
                f.write(json.dumps(metrics.json_safe(rec)) + "\n")
            f.flush()
            os.fsync(f.fileno())
        self.records += list(records)


def _from_json(record: dict) -> dict:
    """A record as written (``metrics.json_safe``: NaN and inf as null) back to its values:
    a null ``min_ttc`` is inf (no projected conflict), any other null metric NaN."""
    out = dict(record)
    for key in metrics.SCENE_KEYS:
        if out.get(key, 0) is None:
            out[key] = math.inf if key == "min_ttc" else math.nan
    out["per_second"] = {
        h: {k: math.nan if v is None else v for k, v in row.items()}
        for h, row in record.get("per_second", {}).items()
    }
    return out


def run_identity(config: StressConfig, model: str) -> dict:
    """What a stress run is, for :class:`EpisodeLog`: its config but the episode count, and
    its model."""
    out = config.to_dict()
    out.pop("episodes")
    return {**out, "model": model}


def _remaining_scenes(config: StressConfig, done: Sequence[dict]) -> Iterator[Scene]:
    """The scenes of episodes ``len(done)`` on: a generated road restarts from the seed after
    the last done scene's (no scene is generated twice), a stored source skips ahead."""
    k = len(done)
    if config.scenario in Scenario.values() and k:
        return scenes_for(config.scenario, config.episodes - k, done[-1]["scene_seed"] + 1)
    return itertools.islice(scenes_for(config.scenario, config.episodes, config.seed), k, None)


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
    from tqdm.auto import tqdm

    factory = planner_factory or (lambda: make_planner(config.planner))
    loop = ClosedLoop(model, config.sim)
    records: list[dict] = [] if log is None else log.records[: config.episodes]
    scenes = _remaining_scenes(config, records)
    bar = tqdm(total=config.episodes, desc="stress", unit="ep", disable=not progress)
    bar.update(len(records))
    index = len(records)
    while index < config.episodes:
        chunk = []
        for scene in scenes:
            chunk.append(scene)
            if len(chunk) == config.batch:
                break
        seeds = [config.seed + index + k for k in range(len(chunk))]
        batch = run_batch(loop, chunk, seeds, [factory() for _ in chunk], first=index)
        if log is not None:
            log.append(batch)
        records += batch
        index += len(chunk)
        bar.update(len(chunk))
        bar.set_postfix(cr=f"{np.mean([r['cr'] for r in records]):.2f}")
    bar.close()
    return records


def run_batch(
    loop: ClosedLoop,
    scenes: Sequence[Scene],
    seeds: Sequence[int],
    planners: Sequence[Planner],
    first: int = 0,
) -> list[dict]:
    """Run B episodes together to their end (episode indices ``first ..``); one record each."""
    start = time.perf_counter()
    loop.reset(scenes, seeds)
    for planner, scene, seed in zip(planners, scenes, seeds, strict=True):
        planner.reset(scene, seed)
    B = len(scenes)
    while not loop.done.all():
        actions = np.zeros((B, 2))
        states = np.full((B, 4), np.nan)
        for b, planner in enumerate(planners):
            if loop.episodes[b].done:
                continue
            state = loop.state(b)
            if planner.replays_log:
                states[b] = planner.next_state(state)
            else:
                actions[b] = planner.act(state)
        loop.step(actions, states)
    wall = time.perf_counter() - start
    return [
        _record(loop, b, scene, seeds[b], wall / B, first + b) for b, scene in enumerate(scenes)
    ]


def _record(loop: ClosedLoop, b: int, scene: Scene, seed: int, seconds: float, index: int) -> dict:
    """Episode ``index``'s record: its metrics (:func:`metrics.evaluate_scene` of batch row
    ``b``), selection, seeds and timing."""
    ep = loop.episodes[b]
    sim = loop.scene(b)
    factual = scene.time_slice(0, sim.num_steps)
    rec = metrics.evaluate_scene(sim, factual, adversary=ep.adversary)
    conflict = ep.conflict
    scene_seed = scene.metadata.get("seed")
    rec.update(
        episode=int(index),
        seed=int(seed),
        scene_seed=None if scene_seed is None else int(scene_seed),
        adversary_type=None if conflict is None else conflict.subtype,
        adversary_tier=None if conflict is None else conflict.tier,
        danger_score=None if conflict is None else float(conflict.score),
        fallback=ep.selection.fallback,
        replans=ep.replans,
        replan_seconds=ep.replan_seconds,
        seconds=seconds,
    )
    return rec


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
    other planners' do (collisions and leaving the road do not end it). The env's
    observation and action config come from ``env_config``, else from the policy's
    ``PATH.env.json`` sidecar, else the env's defaults.

    Raises:
        ValueError: the policy's spaces do not match the env's (the message names both).
    """
    from tqdm.auto import tqdm

    from counterscene_env.envs.single_agent import CounterSceneEnv
    from counterscene_env.planners import SB3Policy

    policy = SB3Policy(config.planner.removeprefix(SB3_PREFIX))
    sim = config.sim
    settings = {
        **policy.env_config,
        **(env_config or {}),
        "scenario": config.scenario if config.scenario in Scenario.values() else "merge",
        "model": model,
        **dataclasses.asdict(sim),  # every closed-loop setting
        "terminate_on_collision": False,
        "terminate_on_off_road": False,
    }
    env = CounterSceneEnv(config=settings)
    policy.bind(env.observation_space, env.action_space)
    records: list[dict] = [] if log is None else log.records[: config.episodes]
    bar = tqdm(total=config.episodes, desc="stress", unit="ep", disable=not progress)
    bar.update(len(records))
    for i, scene in enumerate(_remaining_scenes(config, records), start=len(records)):
        seed = config.seed + i
        start = time.perf_counter()
        obs, _ = env.reset(seed=seed, options={"scene": scene, "episode_seed": seed})
        done = False
        while not done:
            obs, _, terminated, truncated, _ = env.step(policy.predict(obs))
            done = terminated or truncated
        record = _record(env.loop, 0, scene, seed, time.perf_counter() - start, i)
        if log is not None:
            log.append([record])
        records.append(record)
        bar.update(1)
        bar.set_postfix(cr=f"{np.mean([r['cr'] for r in records]):.2f}")
    bar.close()
    env.close()
    return records


def summarize(records: Sequence[dict], config: StressConfig) -> dict:
    """The paper's table row of a run (module docstring), JSON-ready."""
    agg = metrics.aggregate(records)
    ttc = np.array([r["min_ttc"] for r in records], float)
    finite = ttc[np.isfinite(ttc)]
    overall = agg["overall"]
    replans = sum(r["replans"] for r in records)
    seconds = sum(r["seconds"] for r in records)
    replan_seconds = sum(r["replan_seconds"] for r in records)
    return {
        "horizons": agg["groups"],
        "per_second": agg["per_second"],
        "episodes": len(records),
        "cr": overall["cr"],
        "cr_ego_adversary": overall["cr_ego_adversary"],
        "cr_non_ego": overall["cr_non_ego"],
        "hbr_ego": overall["hbr_ego"],
        "orr": overall["orr"],
        "orr_moving": overall["orr_moving"],
        "mean_min_ttc": float(finite.mean()) if finite.size else math.inf,
        "episodes_without_ttc_conflict": int((~np.isfinite(ttc)).sum()),
        "mean_min_clearance_adversary": overall["min_clearance_adversary"],
        "fallbacks": sum(r["fallback"] is not None for r in records),
        # Real logs: an episode ends with its log; a log with no future at all is skipped.
        "episodes_cut_at_log_end": sum(
            r["rollout_s"] < config.sim.duration - 1e-6 for r in records
        ),
        "scenes_too_short": SKIPPED.get(config.scenario, 0),
        "seconds_per_episode": seconds / len(records),
        "seconds_per_replan": replan_seconds / replans if replans else math.nan,
        "overall": overall,
        "config": config.to_dict(),
    }


def write_outputs(directory: str | os.PathLike, summary: dict, records: Sequence[dict]) -> None:
    """``DIR/metrics.json`` (the summary) and ``DIR/episodes.jsonl`` (one line per episode)."""
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    (out / "metrics.json").write_text(json.dumps(metrics.json_safe(summary), indent=2) + "\n")
    with open(out / "episodes.jsonl", "w") as f:
        for rec in records:
            f.write(json.dumps(metrics.json_safe(rec)) + "\n")


def write_summary(directory: str | os.PathLike, summary: dict) -> None:
    """``DIR/metrics.json``: the summary of a run whose episodes an :class:`EpisodeLog`
    keeps."""
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    (out / "metrics.json").write_text(json.dumps(metrics.json_safe(summary), indent=2) + "\n")
