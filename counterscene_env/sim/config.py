"""Closed-loop settings: :class:`SimConfig`, the one source of every simulation setting.

Each field is also a ``CounterScene-v0`` config key and a ``counterscene stress`` flag, both
derived from this dataclass (``counterscene_env.config``): add a field here, with its entry in
the docstring, and it is reachable from every front end.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from counterscene_env.config import (
    DEFAULT_DT,
    GuidancePreset,
    GuidanceProgress,
    Sampler,
    SelectionSource,
    Selector,
    bounded,
    check_fields,
    choice_field,
    from_mapping,
)


@dataclass(frozen=True)
class SimConfig:
    """Closed-loop settings.

    Attributes:
        duration: closed-loop length after "now" [s], at least one 0.1 s step; capped by
            the log's length.
        replan_every: steps between world-model replans (5 = 0.5 s).
        num_samples: samples per replan; the one with the lowest guidance loss plus
            realism cost is kept (paper protocol: 16). 2 samples with 2 warm steps were as
            good as 4 with 3 on the 100 quality episodes at about 60 % of the time
            (docs/history/performance.md, the third fast-replans session); with the final
            guidance step, no difference outside the noise on the 200-episode paper tables
            (docs/performance.md, "Two samples and two warm steps").
        selector: causal (the paper's conflict mining) or a baseline: random, distance
            (nearest), ttc (smallest time to collision).
        selection_source: log (mined once on the factual future) or model (mined at every
            replan on the world model's unguided prediction).
        strict_gates: the strict selection gates (d_min < 15 m, encounter neither on the
            last step nor with both on the first, adversary moving; docs/design.md, "Causal
            adversary selection"); off in the paper.
        yielders_first: the causal selector ranks a crossing conflict whose candidate
            reaches the conflict point before the ego after every other one: the adversary
            is the agent that leaves the ego the time to clear, as the paper describes it,
            which its score does not check (a departure; docs/closed_loop.md). False: the
            paper's ranking by tier and score.
        reachable_first: the causal selector ranks a conflict whose candidate cannot reach
            the conflict point by the ego's arrival (it arrives first, or it would need more
            than a passenger car's full-throttle 4 m/s^2) after every reachable one: the
            guidance's arrival-time compression can only act on a reachable conflict (a
            departure; docs/closed_loop.md). False: the ranking above.
        guidance: a guidance preset: full, no_jerk, no_conflict_aware, no_progressive,
            no_adaptive, minimal, none.
        final_step_guidance: the paper's final-step guidance (implementation table: one
            step of lr 0.3 on the finished sample at the last denoising step, unclipped;
            adversary/guidance.py). False: the guidance ends at the last noisy step, where
            its steps are clipped to that step's noise and barely move the adversary (our
            reference before 25 Nov 2026; docs/history/closed_loop.md, "Why the guidance did
            not bite harder").
        guidance_progress: what the guidance's progress p, which sets its stage multiplier
            and its arrival-time compression, measures: denoising (the paper's main text:
            every replan compresses the arrival gap by its last steps) or rollout (closed-loop
            step over the horizon, the paper's appendix and public code: no compression in
            the episode's first half; docs/closed_loop.md).
        sampler: the world model's sampler, ddim or ddpm (None: the model's default).
        sampling_steps: denoising steps of the strided sampler (None: the model's default).
        eta: noise scale of the strided sampler, 0 (DDIM) to 1 (DDPM posterior) (None: the
            model's default).
        map_guidance: step size of the world model's map guidance on every agent (None: the
            model's default).
        lane_steering: Adam steps of the world model's final-step lane keeping (None: the
            model's default; 0: off). 10, half the shipped model's 20: open loop on 200
            held-out generated scenes, 0.48 % of moving vehicles' predicted steps off the
            road against 0.32 % (intervals overlapping) at the same ADE; in the closed loop
            road keeping (``road_keeping``) takes what still leaves the road
            (docs/world_model.md, "Sampling").
        hold_parked: vehicles stopped now more than this far outside every lane strip of
            their window (cars in lots and driveways) are held in place, out of the world
            model's view [m] (None: the model's own ``hold_parked``, 1.5 for the shipped one;
            0: none held; docs/world_model.md, "Cars parked off the street"). The selected
            adversary is never held.
        warm_start_steps: denoising steps of a warm-started replan: after an episode's first
            replan, each window starts from the previous plan shifted to "now", noised to the
            level of the sampler's last ``warm_start_steps`` steps, and only those are run
            (docs/performance.md, "Warm start"); 0: every replan samples from pure noise.
            2 of the sampler's 10 steps do what 3 did (docs/performance.md).
        warm_first_replan: an episode's first replan starts warm too, from every agent's
            "keep speed and course" plan (what a warm replan gives an agent it has not planned
            before), instead of from pure noise with every denoising step. Needs
            ``warm_start_steps > 0``. Off: 6 % faster episodes for four times the off-road
            rate on development episodes (inside the noise; docs/performance.md).
        realism_weight: weight of the realism cost (agents overlapping or off their lanes,
            sim/realism.py) in the choice among samples; 0: guidance loss only.
        realism_horizon: how far ahead the realism cost counts each sample's overlaps [s]
            (None: the whole plan, 5.2 s for the shipped model; its off-lane distance counts
            over the first 2 s, sim/realism.py). A car crossing another's path must brake
            about 3 s before the crossing; a cost that read only the first 2 s (until 27 Nov
            2026) saw the world model's crossing collisions only once every sample had them
            (docs/world_model_experiments.md, "The network's crossing collisions").
        cover_radius: an agent is planned from a model window only if it is within this many
            metres of the window's centre [m]; farther agents get windows of their own.
        max_windows: model windows per episode and replan (the ego's plus extra ones).
        traffic_yields: ordinary traffic slows along its planned path rather than drive into
            another agent's box (sim/yielding.py); egos never yield. False: every plan is
            followed to the letter.
        adversary_yields_to_others: a guided adversary yields like ordinary traffic to
            everyone but the egos: the guidance removes its margins toward the ego, not its
            manners toward third parties (a departure from the paper, whose adversary has no
            reflexes; docs/design.md, "Where we depart"). False: it yields to no one.
            Needs ``traffic_yields``.
        road_keeping: a step that would take an agent other than an ego off the road is moved
            sideways onto its lane (sim/road_keeping.py). False: the plans' own off-road
            steps stand.
        memory_limit_gb: a replan whose estimated memory (sim/memory.py: samples x model
            windows x the model's size) exceeds this is refused before it starts [GB] (None:
            half of this machine's total memory, whatever is free).
    """

    duration: float = bounded(10.0, ge=DEFAULT_DT)  # a shorter one rounds to no step
    replan_every: int = bounded(5, ge=1)
    num_samples: int = bounded(2, ge=1)
    selector: str = choice_field(Selector, Selector.CAUSAL)
    selection_source: str = choice_field(SelectionSource, SelectionSource.LOG)
    strict_gates: bool = True
    yielders_first: bool = True
    reachable_first: bool = True
    guidance: str = choice_field(GuidancePreset, GuidancePreset.FULL)
    final_step_guidance: bool = True
    guidance_progress: str = choice_field(GuidanceProgress, GuidanceProgress.DENOISING)
    sampler: str | None = choice_field(Sampler, None)
    sampling_steps: int | None = bounded(None, ge=1)
    eta: float | None = bounded(None, ge=0, le=1)
    map_guidance: float | None = bounded(None, ge=0)
    lane_steering: int | None = bounded(10, ge=0)
    hold_parked: float | None = bounded(None, ge=0)
    warm_start_steps: int = bounded(2, ge=0)
    warm_first_replan: bool = False
    realism_weight: float = bounded(1.0, ge=0)
    realism_horizon: float | None = bounded(None, gt=0)
    cover_radius: float = bounded(25.0, gt=0)
    max_windows: int = bounded(1, ge=1)
    traffic_yields: bool = True
    adversary_yields_to_others: bool = True
    road_keeping: bool = True
    memory_limit_gb: float | None = bounded(None, gt=0)

    def __post_init__(self) -> None:
        check_fields(self)  # types, ranges and choices, each refusal naming its key
        if self.warm_first_replan and self.warm_start_steps == 0:
            raise ValueError(
                "warm_first_replan needs warm_start_steps > 0 (the steps a warm replan "
                "runs), got warm_start_steps = 0"
            )

    def check_model(self, num_train_timesteps: int) -> None:
        """Raise unless these settings fit a model trained on ``num_train_timesteps`` noise
        levels (``ModelConfig.num_train_timesteps``): the sampler strides over them, so
        ``sampling_steps`` is at most that."""
        steps = self.sampling_steps
        if steps is not None and steps > num_train_timesteps:
            raise ValueError(
                f"sampling_steps must be <= {num_train_timesteps} (the model's "
                f"num_train_timesteps), got {steps}"
            )

    @classmethod
    def from_mapping(cls, values: Mapping) -> SimConfig:
        """Build from a dict; unknown keys raise and name the valid ones."""
        return from_mapping(cls, values, "simulation")


#: What each setting of :class:`SimConfig` that may be None does then, in a few words (run
#: reports and ``compare`` labels show these, never "None"; the docstring above says more).
NONE_MEANS = {
    "sampler": "model default",
    "sampling_steps": "model default",
    "eta": "model default",
    "map_guidance": "model default",
    "hold_parked": "model default",
    "realism_horizon": "whole plan",
    "memory_limit_gb": "half of memory",
}


def shown_setting(key: str, value: object) -> object:
    """``value`` of setting ``key`` as reports show it: None as what it means (:data:`NONE_MEANS`)."""
    return NONE_MEANS.get(key, "None") if value is None else value
