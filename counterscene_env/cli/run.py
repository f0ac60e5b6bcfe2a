"""``counterscene stress`` and ``counterscene bench-env``: closed-loop runs."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from counterscene_env.cli.common import (
    add_json_flag,
    add_model_flag,
    add_quiet_flag,
    add_seed_flag,
    fmt,
    json_safe,
    load_model,
    parse_overrides,
)


def add_stress(sub) -> None:
    """Register ``counterscene stress``."""
    st = sub.add_parser(
        "stress",
        help="stress-test an ego planner against guided world-model traffic",
        description=(
            "Run --episodes closed-loop episodes (scene and noise of episode i from seed "
            "--seed + i): the world model drives traffic, --planner drives the ego, and the "
            "adversary picked by --selector is steered by --guidance. Prints the paper's table "
            "row: ADE, FDE, ORR, HBR, CR for 1-4 s, 5-7 s, 8-10 s and per second."
        ),
    )
    st.add_argument(
        "--scenario",
        required=True,
        help="highway, merge, intersection, roundabout, or scenarionet:DIR",
    )
    st.add_argument("--episodes", type=int, default=50, help="episodes (default 50)")
    add_seed_flag(st, 100000, "seed of episode 0 (default 100000)")
    st.add_argument(
        "--planner",
        default="idm",
        help=(
            "ego planner: idm, idm_yield, constant_velocity, log, or sb3:PATH.zip (a "
            "Stable-Baselines3 policy, run through CounterScene-v0) (default idm)"
        ),
    )
    st.add_argument(
        "--env-config",
        help=(
            "sb3 planners: JSON object (or a .json file) of CounterScene-v0 config keys, e.g. "
            "the policy's observation and action; default: PATH.env.json next to the zip"
        ),
    )
    _add_sim_flags(st)
    st.add_argument(
        "--batch",
        type=int,
        default=4,
        help="episodes advanced together (4; sb3 planners run one at a time)",
    )
    add_model_flag(st)
    add_json_flag(st, "print the summary as one JSON object")
    st.add_argument(
        "--out",
        help="write DIR/episodes.jsonl as episodes finish and DIR/metrics.json at the end; "
        "rerun the same command to resume a stopped run",
    )
    add_quiet_flag(st)
    st.set_defaults(func=_cmd_stress)


#: Spellings of the closed-loop flags kept from before they were derived from SimConfig.
_SIM_ALIASES = {"num_samples": ["--samples"], "selection_source": ["--source"]}


_SIM_SWITCHES = {
    "strict_gates": [
        (
            "--paper-gates",
            False,
            "the paper's selection (no strict gates: parked or far adversaries allowed)",
        )
    ],
    "traffic_yields": [
        ("--no-yield", False, "traffic follows its plans to the letter (no yielding rule)")
    ],
}  # --no-road-keeping is the generated negation of --road-keeping


def _add_sim_flags(parser: argparse.ArgumentParser) -> None:
    """One flag per ``SimConfig`` field (``--field-name``, help from its docstring), plus the
    documented short spellings; :func:`_sim_config` turns them into a ``SimConfig``."""
    from counterscene_env.config import add_arguments
    from counterscene_env.sim.config import SimConfig

    group = parser.add_argument_group("closed-loop settings (SimConfig; unset: its default)")
    add_arguments(group, SimConfig, _SIM_ALIASES, _SIM_SWITCHES)


def _sim_config(args: argparse.Namespace):
    """The ``SimConfig`` of the given closed-loop flags (the rest at their defaults)."""
    from counterscene_env.config import parsed_fields
    from counterscene_env.sim.config import SimConfig

    return SimConfig(**parsed_fields(args, SimConfig))


def _cmd_stress(args: argparse.Namespace) -> int:
    from counterscene_env.stress import (
        SB3_PREFIX,
        EpisodeLog,
        StressConfig,
        run_episodes,
        run_identity,
        run_policy_episodes,
        summarize,
        write_summary,
    )

    sim = _sim_config(args)
    config = StressConfig(
        scenario=args.scenario,
        episodes=args.episodes,
        seed=args.seed,
        planner=args.planner,
        sim=sim,
        batch=args.batch,
    )
    # With --out, every finished episode is on disk at once, and a rerun resumes the run.
    log = EpisodeLog(args.out, run_identity(config, args.model)) if args.out else None
    if args.planner.startswith(SB3_PREFIX):
        env_config = None
        if args.env_config:
            text = args.env_config
            if not text.lstrip().startswith("{"):
                text = Path(text).read_text()
            env_config = json.loads(text)
        records = run_policy_episodes(
            config, args.model, env_config, progress=not args.quiet, log=log
        )
    else:
        if args.env_config:
            raise ValueError("--env-config applies to sb3:PATH.zip planners only")
        model = load_model(args.model)
        records = run_episodes(model, config, progress=not args.quiet, log=log)
    summary = summarize(records, config)
    if args.out:
        write_summary(args.out, summary)
    if args.json:
        print(json.dumps(json_safe(summary)))
        return 0
    print(
        f"{summary['episodes']} episodes of {args.scenario}, planner {args.planner}, selector "
        f"{sim.selector}, guidance {sim.guidance} (source {sim.selection_source}, "
        f"{sim.num_samples} samples)"
    )
    print(f"{'':8s}" + "".join(f"{k:>10s}" for k in ("ADE", "FDE", "ORR", "HBR", "CR")))
    for name, row in summary["horizons"].items():
        print(
            f"{name:8s}"
            + "".join(f"{fmt(row[k]):>10s}" for k in ("ADE", "FDE", "ORR", "HBR", "CR"))
        )
    print(
        f"episode CR {fmt(summary['cr'])}, ego-adversary CR {fmt(summary['cr_ego_adversary'])}, "
        f"non-ego CR {fmt(summary['cr_non_ego'])}, ORR {fmt(summary['orr'])}, "
        f"mean min TTC {fmt(summary['mean_min_ttc'])} s, min clearance to adversary "
        f"{fmt(summary['mean_min_clearance_adversary'])} m, fallbacks {summary['fallbacks']}"
    )
    if summary["episodes_cut_at_log_end"]:
        print(f"{summary['episodes_cut_at_log_end']} episodes ended with their log (short logs)")
    if summary["scenes_too_short"]:
        print(f"{summary['scenes_too_short']} logs too short for an episode were skipped")
    print(
        f"{fmt(summary['seconds_per_episode'])} s per episode, "
        f"{fmt(summary['seconds_per_replan'])} s per replan"
    )
    return 0


def add_bench_env(sub) -> None:
    """Register ``counterscene bench-env``."""
    bv = sub.add_parser(
        "bench-env",
        help="steps per second of CounterScene-v0",
        description=(
            "Step CounterScene-v0 --steps times with seeded random actions (resetting at "
            "episode ends) and report steps per second, with and without resets."
        ),
    )
    bv.add_argument("--scenario", default="intersection", help="scenario (default intersection)")
    bv.add_argument("--steps", type=int, default=500, help="env steps (default 500)")
    add_seed_flag(bv, 0, "seed (default 0)")
    bv.add_argument("--threads", type=int, help="torch threads (default: torch's choice)")
    bv.add_argument(
        "--policy",
        default="random",
        choices=("random", "hold"),
        help="random actions, or hold speed and course (default random)",
    )
    bv.add_argument(
        "--set",
        nargs="*",
        default=[],
        metavar="KEY=VALUE",
        help="other config keys (JSON values), e.g. policy_frequency=2 guidance=none",
    )
    add_json_flag(bv)
    bv.set_defaults(func=_cmd_bench_env)


def _cmd_bench_env(args: argparse.Namespace) -> int:
    from counterscene_env.envs.bench import bench_env

    config = {"scenario": args.scenario, **parse_overrides(args.set)}
    result = bench_env(
        config, steps=args.steps, seed=args.seed, threads=args.threads, policy=args.policy
    )
    if args.json:
        print(json.dumps(json_safe(result)))
        return 0
    c = result["config"]
    print(
        f"CounterScene-v0 {c['scenario']}, guidance {c['guidance']}, {c['num_samples']} samples, "
        f"policy {c['policy_frequency']} Hz, {result['threads']} torch threads, "
        f"{result['policy']} actions"
    )
    print(
        f"  {result['steps_per_second']:.1f} steps/s over {result['steps']} steps and "
        f"{result['episodes']} episodes (resets included)"
    )
    print(
        f"  step {1000 * result['step_seconds_mean']:.1f} ms mean ({100 * result['replan_share']:.0f} % "
        f"world-model replans), reset {result['reset_seconds_mean']:.2f} s mean"
    )
    return 0
