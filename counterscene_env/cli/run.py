"""``counterscene stress``: closed-loop runs of a planner against guided traffic."""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

from counterscene_env.cli.common import (
    add_json_flag,
    add_model_flag,
    add_quiet_flag,
    add_seed_flag,
    int_at_least,
    json_safe,
    load_model,
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
        help="highway, merge, intersection, roundabout, scenarionet:DIR, commonroad:DIR, a "
        "dataset directory, or several of these separated by commas",
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
        "--like",
        metavar="ENV_ID",
        help=(
            "sb3 planners: the observation, action and policy frequency of highway-env's "
            "ENV_ID (its default config), e.g. intersection-v1, for a policy trained there "
            "without a PATH.env.json sidecar"
        ),
    )
    st.add_argument(
        "--env-config",
        help=(
            "sb3 planners: JSON object (or a .json file) of CounterScene-v0 config keys, e.g. "
            "the policy's observation and action, applied over PATH.env.json (the sidecar next "
            "to the zip) and --like"
        ),
    )
    _add_sim_flags(st)
    st.add_argument(
        "--batch",
        type=int,
        default=4,
        help="episodes advanced together, their replans in batched world-model calls (default 4)",
    )
    st.add_argument(
        "--egos",
        type=int,
        default=1,
        help="stored scenes cycled for more episodes than they hold: each pass seats the next "
        "moving vehicle as the ego (default 1: the recorded ego only)",
    )
    st.add_argument(
        "--min-future",
        type=float,
        default=0.0,
        metavar="S",
        help="stored scenes: seat only those with at least S s of log after their start "
        "(default 0: every scene; an episode ends with its log)",
    )
    st.add_argument(
        "--rollouts",
        type=int_at_least(1),
        default=1,
        metavar="K",
        help="candidate rollouts per episode (the paper's protocol: 16): each episode runs "
        "under K closed-loop seeds and the one most severe for the ego is kept (a collision "
        "first), at K times the cost (default 1)",
    )
    st.add_argument(
        "--workers",
        type=int,
        help="processes to run batches in, one torch thread each (default 1; --backend ray: "
        "batches at once, default every CPU Ray has); the results are those of the serial run",
    )
    st.add_argument(
        "--backend",
        choices=("local", "ray"),
        default="local",
        help="local processes (default), or Ray tasks (docs/scaling.md)",
    )
    st.add_argument(
        "--address",
        help="--backend ray: a Ray cluster's address (default: a local Ray of --workers CPUs)",
    )
    add_model_flag(st)
    add_json_flag(st, "print the summary as one JSON object (timings under 'timings')")
    st.add_argument(
        "--out",
        help="write DIR/episodes.jsonl and DIR/metrics.json as episodes finish "
        '(metrics.json says "complete": false until the last), DIR/timings.json and the '
        "report (report.html, report.md, plots/, videos/, command.txt; docs/reports.md) at "
        "the end",
    )
    st.add_argument(
        "--videos",
        type=int_at_least(0),
        metavar="K",
        help="with --out: re-simulate the K worst episodes as videos for the report "
        "(default 3; 0: none; needs the video extra)",
    )
    st.add_argument(
        "--resume",
        action="store_true",
        help="continue the run already in --out DIR (a stopped run, or a larger --episodes); "
        "without it, a DIR that holds episodes is refused",
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
    from counterscene_env.cli.flags import add_arguments
    from counterscene_env.sim.config import SimConfig

    group = parser.add_argument_group("closed-loop settings (SimConfig; unset: its default)")
    add_arguments(group, SimConfig, _SIM_ALIASES, _SIM_SWITCHES)


def _sim_config(args: argparse.Namespace):
    """The ``SimConfig`` of the given closed-loop flags (the rest at their defaults)."""
    from counterscene_env.cli.flags import parsed_fields
    from counterscene_env.sim.config import SimConfig

    return SimConfig(**parsed_fields(args, SimConfig))


def _cmd_stress(args: argparse.Namespace) -> int:
    from counterscene_env.stress import (
        EpisodeLog,
        StressConfig,
        run_identity,
        summarize,
        timings,
        write_summary,
        write_timings,
    )

    _check_backend(args)
    if args.videos is not None and not args.out:
        raise ValueError("--videos needs --out DIR: the videos are part of the run's report")
    if args.videos is None:
        args.videos = 3
    if args.resume and not args.out:
        raise ValueError("--resume needs --out DIR: the directory of the run to continue")
    config = StressConfig(
        scenario=args.scenario,
        episodes=args.episodes,
        seed=args.seed,
        planner=args.planner,
        sim=_sim_config(args),
        batch=args.batch,
        egos=args.egos,
        min_future=args.min_future,
        rollouts=args.rollouts,
    )
    env_config = _policy_env_config(args, config.is_sb3)
    model = None if config.is_sb3 else load_model(args.model)  # a bad --model fails here
    # Every check is done before the log: nothing is on disk until the first batch ends.
    log = None
    if args.out:
        identity = run_identity(config, args.model, env_config)
        n = config.episodes
        log = EpisodeLog(
            args.out, identity, args.resume, lambda r: summarize(r, config, args.model)
        )
        if len(log.records) > n:
            # Its summary would count n episodes and its report every recorded one.
            raise ValueError(
                f"--out {args.out} holds {len(log.records)} finished episodes of this run, "
                f"more than --episodes {n}: resume with --episodes {len(log.records)} or "
                "more, or pick another --out"
            )
    before = 0 if log is None else len(log.records)
    if args.resume and not before:  # a mistyped DIR would otherwise pass unnoticed
        print(
            f"--resume: {args.out} holds no episode of this run yet; starting it", file=sys.stderr
        )
    start = time.perf_counter()
    try:
        records = _run_stress(args, config, model, env_config, log)
    except KeyboardInterrupt:
        return _stress_stopped(args, config, log, time.perf_counter() - start, before)
    summary = summarize(records, config, args.model)
    times = timings(records, time.perf_counter() - start, len(records) - before, args.workers)
    if args.out:
        write_summary(args.out, summary)
        write_timings(args.out, times)
        _write_report(args)
    if args.json:
        print(json.dumps(json_safe({**summary, "timings": times})))
        return 0
    from counterscene_env.cli.stress_text import print_stress

    print_stress(config, summary, times, args.scenario, args.workers)
    return 0


def _write_report(args: argparse.Namespace, videos: int | None = None) -> None:
    """The run's report in --out (``counterscene_env.report.write_report``)."""
    from counterscene_env.report import write_report

    page = write_report(
        args.out, videos=args.videos if videos is None else videos, progress=not args.quiet
    )
    if not args.json:
        print(f"report: {page}", file=sys.stderr)


def _policy_env_config(args: argparse.Namespace, sb3: bool) -> dict | None:
    """The env-config keys ``--like`` and ``--env-config`` give an sb3 planner (None: none)."""
    if not sb3:
        for flag in ("like", "env_config"):
            if getattr(args, flag):
                raise ValueError(
                    f"--{flag.replace('_', '-')} applies to sb3:PATH.zip planners only"
                )
        return None
    out = {}
    if args.like:
        from counterscene_env.envs.like import config_like

        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                out.update(config_like(args.like))
        except ValueError as exc:
            raise ValueError(f"--like: {exc}") from None
        for w in caught:  # one line each, as the command's errors
            print(f"counterscene stress: warning: --like: {w.message}", file=sys.stderr)
    if args.env_config:
        out.update(_read_env_config(args.env_config))
    from counterscene_env.planners import sb3_sidecar  # torch: not at --help time

    if not out and not sb3_sidecar(args.planner.removeprefix("sb3:")).is_file():
        print(
            f"counterscene stress: note: {args.planner} has no .env.json sidecar and no --like "
            "or --env-config is given: the policy runs on CounterScene-v0's default "
            "observation, action and policy_frequency (10 Hz)",
            file=sys.stderr,
        )
    return out or None


def _read_env_config(text: str) -> dict:
    """``--env-config``: a JSON object, or the path of a ``.json`` file holding one."""
    if not text.lstrip().startswith("{"):
        path = Path(text)
        if not path.is_file():
            raise ValueError(f"--env-config: {text!r} is neither a JSON object nor a file")
        text = path.read_text()
    try:
        given = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"--env-config: not valid JSON ({exc})") from None
    if not isinstance(given, dict):
        raise ValueError(f"--env-config must be a JSON object, got {given!r}")
    return given


def _check_backend(args: argparse.Namespace) -> None:
    """``--backend``, ``--address`` and ``--workers`` fit, and Ray is installed if asked for
    (else a RuntimeError saying how). An unset ``--workers`` is 1 locally; Ray resolves it."""
    if args.workers is not None and args.workers < 1:
        raise ValueError(f"--workers must be >= 1, got {args.workers}")
    if args.address is not None and args.backend != "ray":
        raise ValueError("--address applies to --backend ray only")
    if args.backend == "ray":
        from counterscene_env.stress.ray_backend import import_ray

        import_ray()
    elif args.workers is None:
        args.workers = 1


def _run_stress(args: argparse.Namespace, config, model, env_config: dict | None, log):
    """Every episode of the run: serial, in ``--workers`` processes, or as Ray tasks."""
    from counterscene_env.stress import run_episodes, run_parallel, run_policy_episodes

    progress = not args.quiet
    if args.backend == "ray":
        from counterscene_env.stress.ray_backend import RayPool

        with RayPool(args.address, args.workers) as pool:
            args.workers = pool.workers  # what timings.json and the text report show
            return pool.run(config, args.model, env_config, progress=progress, log=log)
    if args.workers > 1:
        return run_parallel(
            config, args.workers, args.model, env_config, progress=progress, log=log
        )
    if config.is_sb3:
        return run_policy_episodes(config, args.model, env_config, progress=progress, log=log)
    return run_episodes(model, config, progress=progress, log=log)


#: Exit code of a run stopped by Ctrl-C (the shell's 128 + SIGINT).
STOPPED_EXIT_CODE = 130


def _stress_stopped(args: argparse.Namespace, config, log, wall: float, before: int) -> int:
    """Ctrl-C: the finished episodes' summary (``"complete": false``) and timings in --out,
    and how to go on."""
    from counterscene_env.stress import summarize, timings, write_summary, write_timings

    records = [] if log is None else log.reload()
    if log is None:
        msg = "without --out the finished episodes are not kept; pass --out DIR to keep them"
    elif not records:
        msg = f"no episode had finished: nothing was written to {log.dir}"
    else:
        write_summary(log.dir, summarize(records, config, args.model))
        ran = len(records) - before  # (--workers is unset if Ray was stopped as it started)
        write_timings(log.dir, timings(records, wall, ran, args.workers or 1))
        _write_report(args, videos=0)  # at once: the user is waiting; `report` adds videos
        msg = (
            f"{len(records)} of {config.episodes} episodes are in {log.dir} (metrics.json "
            'summarises them with "complete": false); rerun the same command with --resume '
            "to finish the run"
            if len(records) < config.episodes
            else f"every episode had finished: {log.dir}/metrics.json is complete"
        )
    print(f"counterscene stress: stopped. {msg}", file=sys.stderr)
    return STOPPED_EXIT_CODE
