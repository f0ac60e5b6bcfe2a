"""World-model configuration: one frozen, documented dataclass and its two presets.

``paper`` holds the reference constants of the CounterScene paper (hyper-parameter table): 31
history frames, 52 future steps, up to 21 agents within 50 m, width 128, 16 heads, 100 DDPM
steps. It is sized for a GPU. ``default`` keeps the method and shrinks the constants for a 2-core
CPU (docs/design.md, "CPU budget"): 12 agents, history and future tokens subsampled, width 96, a 10-step strided
sampler. Both build the same network class; only the sizes differ.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from counterscene_env.config import (
    DEFAULT_DT,
    LaneAnchors,
    PlanFeatures,
    PredictionTarget,
    Sampler,
    bounded,
    check_fields,
    check_int,
    check_real,
    choice_field,
)
from counterscene_env.world_model.parked import KERB_OFFSET
from counterscene_env.world_model.window import WindowConfig

#: The presets' ``hold_parked`` [m]: the farthest the training's parked cars stand outside a
#: lane strip, so that no stopped car the network was trained to plan is ever held.
HOLD_PARKED = KERB_OFFSET[1]


@dataclass(frozen=True)
class ModelConfig:
    """Architecture and sampling defaults of a world model.

    Attributes:
        history_steps: frames up to and including "now" that the model sees (10 Hz).
        future_steps: future steps it predicts (10 Hz); ``future_steps * dt`` is the horizon.
        history_stride: one history token every this many frames, ending at "now".
        action_stride: one action token every this many future steps (actions held in between);
            must divide ``future_steps``.
        num_agents: K, the ego plus its nearest vehicles.
        agent_radius: vehicles farther than this from the ego at "now" are left out [m].
        num_lanes: lane segments the model sees.
        lane_points: points per lane segment.
        lane_segment_length: length of a lane segment [m].
        map_radius: lane segments farther than this from every map anchor are left out [m].
        lane_anchors: ``"ego"``: the window's lanes are those nearest the ego (checkpoints
            without the key); ``"agents"``: those nearest where the window's agents are and
            where constant velocity would take them (``world_model.window.WindowConfig``).
        local_lanes: per agent, this many (at most ``num_lanes``) of the lane segments nearest
            to it, expressed in its own frame (position and course at "now"), form a second,
            agent-centric map that the agent's tokens attend to in every block; 0 disables it
            (the scene-frame map alone, as checkpoints without the key have it).
        local_radius: lane segments farther than this from the agent are masked out of its
            agent-centric map [m].
        lane_priority: every lane point also reads its lane's right of way
            (``RoadMap.lane_priorities``: highway-env's lane priority, by which the lower lane
            gives way at a crossing; 0 where the map gives none, as on every imported map).
            Without it (the default, and checkpoints without the key) the network cannot
            tell from the map who has the right of way at highway-env's intersection, whose
            four arms have the same shape. Measured in docs/world_model_experiments.md,
            "The network's crossing collisions".
        source_flag: every agent's tokens also read whether the scene is a recording of real
            driving or highway-env's generated traffic (the window's ``recorded``, from
            ``Scene.generated``), so that one model trained on both can keep highway-env's
            habits (exact speeds between manoeuvres, stop-and-go giving way) to highway-env's
            roads. Without it (the default, and checkpoints without the key) the network
            must tell them apart from the scene itself. Fine-tuned in, it was not taken up
            (docs/world_model_experiments.md, "Real driving and generated traffic told apart").
        d_model: token width.
        num_heads: attention heads (must divide ``d_model``).
        num_blocks: blocks of (temporal, social, map) attention + MLP.
        mlp_ratio: hidden width of the MLPs, as a multiple of ``d_model``.
        dropout: dropout inside the blocks during training.
        graph_dropout: probability of dropping one CIG edge bias during training (paper: 0.1).
        causal_temporal: causal instead of bidirectional temporal attention over future tokens.
        plan_features: what each future token reads of where its agent's plan goes:
            ``"none"`` (the paper's denoiser, and checkpoints without the key): the action
            alone, so two agents' paths meet only through what the network integrates from
            their action sequences; ``"noisy"``: the unicycle rollout of the noisy tokens at
            the token's last step (position, course, speed); ``"self"``: the rollout of the
            previous denoising step's clean prediction (self-conditioning, Chen et al. 2023;
            at the first step, or half of the training windows, none: a flag says which).
            With either, the social attention at each future token adds a learned per-head
            bias of the two agents' rolled-out relative position. Measured in
            docs/world_model_experiments.md, "The network's crossing collisions".
        prediction: what the network outputs: clean actions ``"x0"`` or the noise ``"epsilon"``.
        num_train_timesteps: K of the cosine schedule.
        sampler: default sampler, ``"ddim"`` (strided) or ``"ddpm"`` (all K steps).
        sampling_steps: steps of the strided sampler.
        eta: noise scale of the strided sampler (1 = ancestral DDPM posterior over each stride,
            0 = deterministic DDIM).
        clip_sample: clip the predicted clean actions to +-this (normalised units); 0 disables.
        map_guidance: weight of the map guidance while sampling (a gradient step on the
            posterior mean, clipped to the step's sigma; 0 disables); see ``map_guidance.py``.
            Off by default: measured on the held-out scenes it lowers the off-road rate but
            raises ADE more (docs/world_model.md).
        lane_steering: Adam steps of final-step lane keeping (``lane_steering.
            steer_onto_lanes``): the finished samples' yaw-rate tokens are corrected so that
            every agent that is on a lane now keeps its centre inside a lane strip; 0 disables
            (checkpoints without the key). Measured in docs/world_model.md.
        hold_parked: a vehicle stopped now (slower than ``metrics.realism.PARKED_SPEED``)
            whose centre lies more than this outside every lane strip of its window [m] is
            held in place: the network neither plans it nor sees it (a car parked in a lot or
            a driveway, off every street the map holds); 0 disables (checkpoints without the
            key). The presets take 1.5 m, the farthest that the training's parked cars stand
            outside a lane (``world_model.parked.KERB_OFFSET``): beyond it a stopped car is
            nothing the network has seen, and it braked the moving traffic near such cars on
            real streets (docs/world_model.md, "Cars parked off the street").
        yaw_gain: low-speed yaw-rate bound of the rollout, |w| <= yaw_gain * v [rad/m].
        lateral_limit: high-speed yaw-rate bound, |w| <= lateral_limit / v [m/s^2]. The
            reference values are 0.5 and 2 pi (docs/design.md, "Action space and unicycle
            dynamics"); the defaults are looser because the training traffic
            needs it (highway-env's roundabout corners above 2 pi m/s^2 in ~27 % of its steps,
            and yielding cars at the intersection turn in place faster than 0.5 v).
        dt: step length [s]: the scenes' step, ``config.DEFAULT_DT`` (0.1 s), and no other.
            Every count above is of 10 Hz frames cut from the scenes, and the rollout turns the
            actions into positions with ``dt``: any other value would move the predictions
            at the wrong speed.
    """

    history_steps: int = 31
    future_steps: int = 52
    history_stride: int = 5
    action_stride: int = 4
    num_agents: int = 12
    agent_radius: float = 50.0
    num_lanes: int = 32
    lane_points: int = 10
    lane_segment_length: float = 20.0
    map_radius: float = 60.0
    lane_anchors: str = choice_field(LaneAnchors, LaneAnchors.EGO)
    local_lanes: int = 0
    local_radius: float = 30.0
    lane_priority: bool = False
    source_flag: bool = False
    d_model: int = 96
    num_heads: int = 4
    num_blocks: int = 3
    mlp_ratio: int = 4
    dropout: float = 0.0
    graph_dropout: float = 0.1
    causal_temporal: bool = False
    plan_features: str = choice_field(PlanFeatures, PlanFeatures.NONE)
    prediction: str = choice_field(PredictionTarget, PredictionTarget.X0)
    num_train_timesteps: int = 100
    sampler: str = choice_field(Sampler, Sampler.DDIM)
    sampling_steps: int = 10
    eta: float = 1.0
    clip_sample: float = bounded(5.0, ge=0)
    map_guidance: float = bounded(0.0, ge=0)
    lane_steering: int = bounded(0, ge=0)
    hold_parked: float = 0.0
    yaw_gain: float = 1.0
    lateral_limit: float = 25.0
    dt: float = DEFAULT_DT

    def __post_init__(self) -> None:
        check_fields(self)  # types, ranges, finite numbers and the choices, each naming its key
        checks = [
            (self.history_steps >= 1, "history_steps must be >= 1"),
            (self.future_steps >= 1, "future_steps must be >= 1"),
            (self.history_stride >= 1, "history_stride must be >= 1"),
            (
                self.action_stride >= 1 and self.future_steps % self.action_stride == 0,
                "action_stride must divide future_steps",
            ),
            (self.num_agents >= 1, "num_agents must be >= 1"),
            (
                self.num_lanes >= 1 and self.lane_points >= 2,
                "need num_lanes >= 1, lane_points >= 2",
            ),
            (
                self.local_lanes >= 0 and self.local_radius > 0,
                "need local_lanes >= 0 and local_radius > 0",
            ),
            (self.d_model >= 2 and self.mlp_ratio >= 1, "need d_model >= 2 and mlp_ratio >= 1"),
            (
                self.num_heads >= 1 and self.d_model % self.num_heads == 0,
                "num_heads must divide d_model",
            ),
            (self.num_blocks >= 1, "num_blocks must be >= 1"),
            (
                1 <= self.sampling_steps <= self.num_train_timesteps,
                "sampling_steps must be in [1, num_train_timesteps]",
            ),
            (0.0 <= self.eta <= 1.0, "eta must be in [0, 1] (0: DDIM, 1: DDPM posterior)"),
            (0.0 <= self.graph_dropout < 1.0, "graph_dropout must be in [0, 1)"),
            (self.hold_parked >= 0.0, "hold_parked must be >= 0 (0 disables it)"),
            (
                math.isclose(self.dt, DEFAULT_DT, rel_tol=1e-9),
                f"dt must be {DEFAULT_DT} s (the scenes' step: the model reads 10 Hz frames), "
                f"got {self.dt!r}",
            ),
        ]
        for ok, message in checks:
            if not ok:
                raise ValueError(f"ModelConfig: {message}")

    @property
    def history_tokens(self) -> int:
        """History tokens per agent: frames now, now - stride, ... within the history."""
        return (self.history_steps - 1) // self.history_stride + 1

    @property
    def action_tokens(self) -> int:
        """Future action tokens per agent."""
        return self.future_steps // self.action_stride

    @property
    def horizon(self) -> float:
        """Prediction horizon [s]."""
        return self.future_steps * self.dt

    def window(self, stride: int = 10) -> WindowConfig:
        """The :class:`WindowConfig` of the windows this model reads: every window setting is
        the model's field of the same name (one source), ``stride`` aside (a dataset choice)."""
        shared = {f.name for f in dataclasses.fields(WindowConfig)} - {"stride"}
        return WindowConfig(**{name: getattr(self, name) for name in shared}, stride=stride)

    def replace(self, **changes: Any) -> ModelConfig:
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_mapping(cls, mapping: Mapping[str, Any]) -> ModelConfig:
        """Build from a mapping; an unknown key raises ``ValueError`` naming the valid ones."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(mapping) - names)
        if unknown:
            raise ValueError(
                f"unknown world-model config key(s) {unknown}; valid keys: {sorted(names)}"
            )
        return cls(**dict(mapping))


PRESETS: dict[str, ModelConfig] = {
    # CPU default: every number here was measured (docs/world_model.md, `counterscene bench`).
    "default": ModelConfig(
        num_lanes=48,
        lane_anchors="agents",
        local_lanes=10,
        lane_steering=20,
        hold_parked=HOLD_PARKED,
    ),
    # The paper's reference constants (hyper-parameter table of the CounterScene paper).
    "paper": ModelConfig(
        history_stride=1,
        action_stride=1,
        num_agents=21,
        d_model=128,
        num_heads=16,
        num_blocks=4,
        sampler="ddpm",
        sampling_steps=100,
        num_lanes=48,
        lane_anchors="agents",
        local_lanes=10,
        lane_steering=20,
        hold_parked=HOLD_PARKED,
    ),
}


def preset(name: str) -> ModelConfig:
    """The named preset (``"default"`` or ``"paper"``)."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown preset {name!r}; choose from {sorted(PRESETS)}") from None


def check_preset_name(key: str, value: Any) -> str | None:
    """``value`` if it names a preset, or None (a model saved without one, such as
    ``checkpoint.save_model``'s default): a checkpoint's ``"preset"``.

    Raises:
        ValueError: anything else, naming ``key``, the value and the valid names."""
    if value is None or (isinstance(value, str) and value in PRESETS):
        return value
    raise ValueError(f"{key} must be one of {sorted(PRESETS)} or null, got {value!r}")


def check_sampling(
    sampler: str,
    num_samples: int,
    steps: int | None,
    eta: float | None,
    map_guidance: float | None,
    lane_steering: int | None,
    init_steps: int,
) -> None:
    """Raise unless ``WorldModel.sample``'s numbers are in range (None: the config's),
    naming the argument, as the closed loop's settings are checked (``SimConfig``)."""
    if sampler not in ("ddim", "ddpm"):
        raise ValueError(f"sampler must be 'ddim' or 'ddpm', got {sampler!r}")
    check_int("num_samples", num_samples, ge=1)
    check_int("init_steps", init_steps, ge=0)
    if steps is not None:
        check_int("steps", steps, ge=1)
    if lane_steering is not None:
        check_int("lane_steering", lane_steering, ge=0)
    if eta is not None:
        check_real("eta", eta, ge=0, le=1)
    if map_guidance is not None:
        check_real("map_guidance", map_guidance, ge=0)
