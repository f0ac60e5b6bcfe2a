"""One source of configuration: choices, SimConfig fields as env keys, stress flags and SB3 runs."""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np
import pytest

from counterscene_env.cli.flags import add_arguments, field_docs, parsed_fields
from counterscene_env.config import GuidancePreset, Sampler, Selector, defaults
from counterscene_env.sim import SimConfig
from counterscene_env.world_model.config import ModelConfig
from counterscene_env.world_model.window import WindowConfig


def test_a_choice_takes_its_enum_or_its_string_and_stores_the_string():
    a = SimConfig(selector=Selector.TTC, guidance=GuidancePreset.NONE, sampler=Sampler.DDPM)
    b = SimConfig(selector="ttc", guidance="none", sampler="ddpm")
    assert a == b and type(a.selector) is str and a.selector == "ttc"
    assert dataclasses.asdict(a)["guidance"] == "none"


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("selector", "closest", r"unknown selector 'closest'; valid: \['causal', 'random'"),
        ("guidance", ["full"], r"unknown guidance preset \['full'\] for 'guidance'; valid"),
        ("selection_source", None, r"unknown selection source None; valid: \['log', 'model'\]"),
        ("sampler", "euler", r"unknown sampler 'euler'; valid: \['ddim', 'ddpm'\]"),
    ],
)
def test_a_bad_choice_names_the_value_and_lists_the_valid_ones(key, value, message):
    with pytest.raises(ValueError, match=message):
        SimConfig(**{key: value})


def test_field_docs_cover_every_sim_field():
    docs = field_docs(SimConfig)
    assert set(docs) == {f.name for f in dataclasses.fields(SimConfig)}
    assert docs["replan_every"] == "steps between world-model replans (5 = 0.5 s)."
    assert docs["eta"].startswith("noise scale of the strided sampler")


def test_flags_are_derived_from_fields_with_aliases_and_switches():
    parser = argparse.ArgumentParser()
    add_arguments(
        parser,
        SimConfig,
        aliases={"num_samples": ["--samples"]},
        switches={"traffic_yields": [("--no-yield", False, "no yielding")]},
    )
    given = parsed_fields(parser.parse_args([]), SimConfig)
    assert given == {}  # nothing given: the dataclass defaults apply
    args = parser.parse_args(
        ["--samples", "3", "--no-yield", "--sampler", "ddpm", "--eta", "0.5", "--no-strict-gates"]
    )
    assert parsed_fields(args, SimConfig) == {
        "num_samples": 3,
        "traffic_yields": False,
        "sampler": "ddpm",
        "eta": 0.5,
        "strict_gates": False,
    }
    with pytest.raises(SystemExit):
        parser.parse_args(["--selector", "closest"])


def test_every_window_setting_is_a_model_setting():
    """ModelConfig holds the window settings (the one source); ``window`` derives them."""
    shared = {f.name for f in dataclasses.fields(WindowConfig)} - {"stride"}
    assert shared <= {f.name for f in dataclasses.fields(ModelConfig)}
    config = ModelConfig(num_agents=7, num_lanes=5, lane_anchors="agents", agent_radius=33.0)
    window = config.window(stride=3)
    assert window.stride == 3
    assert all(getattr(window, name) == getattr(config, name) for name in shared)


def test_every_sim_field_is_an_env_config_key_with_its_default():
    from counterscene_env.envs.single_agent import CounterSceneEnv

    base = CounterSceneEnv.default_config()
    assert {k: base[k] for k in defaults(SimConfig)} == defaults(SimConfig)
    env = CounterSceneEnv(config={"sampling_steps": 3, "eta": 0.0, "realism_weight": 0.5})
    assert env.sim_config == SimConfig(sampling_steps=3, eta=0.0, realism_weight=0.5)
    with pytest.raises(ValueError, match="unknown sampler 'euler'"):
        env.configure({"sampler": "euler"})
    env.close()


@pytest.mark.usefixtures("one_torch_thread")
def test_sb3_planners_run_with_every_sim_setting(generated, tmp_path, monkeypatch):
    """``run_policy_episodes`` hands the whole SimConfig to the env (it used to drop sampler,
    sampling_steps, eta, map_guidance, realism_weight, cover_radius and max_windows)."""
    from stable_baselines3 import PPO

    from counterscene_env.envs.single_agent import CounterSceneEnv
    from counterscene_env.scene.shards import save_scenes
    from counterscene_env.sim import loop as loop_module
    from counterscene_env.stress import StressConfig, run_policy_episodes

    shard = tmp_path / "scenes.npz"
    save_scenes([generated["merge"]], shard)
    env = CounterSceneEnv(config={"scenario": str(shard)})
    PPO("MlpPolicy", env, n_steps=8, batch_size=8, device="cpu").save(tmp_path / "policy.zip")
    env.close()

    seen = []
    original = loop_module.ClosedLoop.__init__

    def spy(self, model, config=None):
        seen.append(config)
        original(self, model, config)

    monkeypatch.setattr(loop_module.ClosedLoop, "__init__", spy)
    sim = SimConfig(
        duration=0.3,
        num_samples=2,
        sampler="ddim",
        sampling_steps=2,
        eta=0.0,
        map_guidance=0.1,
        realism_weight=0.0,
        cover_radius=30.0,
        max_windows=2,
    )
    config = StressConfig(str(shard), episodes=1, planner=f"sb3:{tmp_path / 'policy.zip'}", sim=sim)
    records = run_policy_episodes(config, progress=False)
    assert seen == [sim]
    assert len(records) == 1 and np.isfinite(records[0]["rollout_s"])


def test_a_stress_runs_episode_seeds_must_fit_the_torch_generator():
    """Episode i runs under seed + i, which seeds a torch generator (64 bits): a run whose
    last episode would overflow it is refused when it is configured, not episodes in."""
    from counterscene_env.config import MAX_SEED
    from counterscene_env.stress import StressConfig

    assert StressConfig("merge", episodes=2, seed=MAX_SEED - 1).seed == MAX_SEED - 1
    with pytest.raises(ValueError, match=r"seed \d+ with 3 episodes"):
        StressConfig("merge", episodes=3, seed=MAX_SEED - 1)
    with pytest.raises(TypeError, match="seed must be an int"):
        StressConfig("merge", seed=1.5)


@pytest.mark.parametrize(
    ("values", "error", "words"),
    [
        ({"episodes": 1.5}, TypeError, "episodes must be an int"),
        ({"episodes": True}, TypeError, "episodes must be an int"),
        ({"batch": 0}, ValueError, "batch must be >= 1"),
        ({"rollouts": 2.0}, TypeError, "rollouts must be an int"),
        ({"min_future": "1"}, TypeError, "min_future must be a number"),
        ({"sim": {"duration": 1.0}}, TypeError, "sim must be a SimConfig"),
        ({"planner": None}, TypeError, "planner must be a str"),
        ({"scenario": None}, TypeError, "scenario must be a str"),
    ],
)
def test_a_stress_config_checks_its_fields_by_type_and_range(values, error, words):
    from counterscene_env.stress import StressConfig

    with pytest.raises(error, match=words):
        StressConfig(**{"scenario": "merge", **values})


def test_numpy_values_are_stored_as_plain_python_ones():
    """A count given as a numpy int (an index, a sweep) is stored as an int: the run's
    summary and records stay plain JSON."""
    from counterscene_env.stress import StressConfig

    config = StressConfig("merge", episodes=np.int64(3), seed=np.int64(5))
    assert type(config.episodes) is int and type(config.seed) is int
    sim = SimConfig(replan_every=np.int64(2), duration=np.float32(2.0))
    assert type(sim.replan_every) is int and type(sim.duration) is float
