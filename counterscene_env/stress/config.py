"""What a stress run is: :class:`StressConfig`, and its identity on disk (:func:`run_identity`)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from counterscene_env.config import (
    MAX_SEED,
    bounded,
    check_fields,
    check_seed,
    describe_value,
)
from counterscene_env.metrics.common import METRICS_VERSION
from counterscene_env.planners import make_planner
from counterscene_env.scene.sources import check_spec, is_generated
from counterscene_env.sim import SimConfig

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
            (:func:`~counterscene_env.stress.run_policy_episodes`).
        sim: closed-loop settings (selector, guidance, samples, ...).
        batch: episodes advanced together (one world-model call per replan; an sb3
            planner's in one vector env).
        egos: ego choices per stored scene when the run cycles a source with fewer scenes
            than episodes (``scene.sources.scenes_for``); 1 keeps every recorded ego.
        min_future: s of log after "now" a stored scene needs to be seated (shorter ones are
            skipped: an episode on them would end before anything could happen); 0 seats
            every scene. Generated roads always record a whole episode.
        rollouts: candidate rollouts per episode (the paper's protocol: 16): each episode is
            run under this many closed-loop seeds and the run most severe for the ego is kept
            (``stress.rollouts``; docs/closed_loop.md, "Candidate rollouts"). 1: the episode
            as its seed runs it.
    """

    scenario: str
    episodes: int = bounded(50, ge=1)
    seed: int = 0
    planner: str = "idm"
    sim: SimConfig = dataclasses.field(default_factory=SimConfig)
    batch: int = bounded(4, ge=1)
    egos: int = bounded(1, ge=1)
    min_future: float = bounded(0.0, ge=0)
    rollouts: int = bounded(1, ge=1)

    def __post_init__(self) -> None:
        for key in ("scenario", "planner"):
            if not isinstance(getattr(self, key), str):
                raise TypeError(f"{key} must be a str, {describe_value(getattr(self, key))}")
        if not isinstance(self.sim, SimConfig):
            raise TypeError(f"sim must be a SimConfig, {describe_value(self.sim)}")
        check_fields(self)  # counts, min_future: types and ranges, stored as plain values
        object.__setattr__(self, "seed", check_seed("seed", self.seed))
        if self.seed + self.episodes - 1 > MAX_SEED:  # the last episode's closed-loop seed
            raise ValueError(
                f"seed {self.seed} with {self.episodes} episodes: episode i's seed is seed + i, "
                f"and seeds must be <= {MAX_SEED} (torch's 64 bits)"
            )
        check_spec(self.scenario)
        if is_generated(self.scenario):
            object.__setattr__(self, "egos", 1)  # a new scene every episode: no ego choices
            object.__setattr__(self, "min_future", 0.0)  # and a whole episode's recording
        if self.is_sb3:
            path = self.policy_path
            if not path.is_file():
                raise ValueError(f"planner {self.planner!r}: no such SB3 policy file {path}")
        else:
            make_planner(self.planner)  # raises on an unknown name

    @property
    def is_sb3(self) -> bool:
        """The planner is a Stable-Baselines3 policy (``sb3:PATH.zip``)."""
        return self.planner.startswith(SB3_PREFIX)

    @property
    def policy_path(self) -> Path:
        """The ``.zip`` of an ``sb3:PATH.zip`` planner."""
        return Path(self.planner.removeprefix(SB3_PREFIX))

    def to_dict(self) -> dict:
        out = dataclasses.asdict(self)
        out["sim"] = dataclasses.asdict(self.sim)
        return out


#: Run-identity keys :func:`run_identity` leaves out at these, their defaults, so that runs
#: from before the key still resume; readers put them back (:func:`effective_identity`).
IDENTITY_DEFAULTS = {
    f.name: f.default
    for f in dataclasses.fields(StressConfig)
    if f.name in ("egos", "min_future", "rollouts")
}


def run_identity(config: StressConfig, model: str, env_config: dict | None = None) -> dict:
    """What a stress run is, for :class:`~counterscene_env.stress.EpisodeLog`: its config but
    the episode count, its model, the version of the metric definitions that score its
    episodes (``metrics.METRICS_VERSION``: a run scored by another is not this run), and
    (sb3 planners) the env-config keys given on top of the policy's sidecar (``--like``,
    ``--env-config``), which change what the policy sees. Keys of :data:`IDENTITY_DEFAULTS`
    at their default are left out (runs from before the key)."""
    out = config.to_dict()
    out.pop("episodes")
    for key, default in IDENTITY_DEFAULTS.items():
        if out[key] == default:
            out.pop(key)
    out["model"] = model
    out["metrics_version"] = METRICS_VERSION
    if env_config:
        out["env_config"] = env_config
    return out


def effective_identity(identity: dict) -> dict:
    """A run identity as ``run.json`` holds it, with every setting the run ran with: the keys
    :func:`run_identity` leaves out at their default (:data:`IDENTITY_DEFAULTS`; no
    ``env_config``: ``{}``) put back, and the closed-loop settings a run from before a
    ``SimConfig`` field did not record at today's default. A closed-loop setting of None stays
    None (``sim.config.NONE_MEANS`` says what it means)."""
    sim = {**dataclasses.asdict(SimConfig()), **identity.get("sim", {})}
    return {**IDENTITY_DEFAULTS, "env_config": {}, **identity, "sim": sim}


def model_identity(model: str) -> dict:
    """The world model of a run, for its summary: ``{"given": model as given (``--model``),
    "directory": the checkpoint directory it names, absolute}``; ``"default"`` is the
    shipped model's directory."""
    from counterscene_env.world_model.checkpoint import model_dir  # torch: lazily

    return {"given": model, "directory": str(model_dir(model).resolve())}
