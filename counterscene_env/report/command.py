"""A run's command line, rebuilt from what the run recorded (``run.json``), for
``DIR/command.txt``.

Every closed-loop setting is spelled out, defaults included, so the command reruns the same
episodes even if a default changes later. Rerun as is, it finishes the run in the same
directory (``--resume``; nothing to do if it is complete); with another ``--out`` it
reproduces the run from scratch.
"""

from __future__ import annotations

import dataclasses
import json
import shlex
from pathlib import Path

from counterscene_env.report.rundir import Run
from counterscene_env.sim.config import SimConfig
from counterscene_env.stress import SB3_PREFIX
from counterscene_env.stress.log import PYTHON_PLANNER_PREFIX


def stress_argv(run: Run) -> list[str]:
    """``["counterscene", "stress", ...]``: the arguments that rerun ``run``.

    The episode count is the one the run was started for (``metrics.json``), else the
    number of finished episodes (a run killed before its summary).

    Raises:
        ValueError: ``run.json`` has no ``scenario`` (the message names the file).
    """
    ident = run.identity
    if "scenario" not in ident:
        raise ValueError(f"{run.directory / 'run.json'}: no 'scenario' field")
    episodes = run.planned_episodes or len(run.records)
    argv = ["counterscene", "stress", "--scenario", str(ident["scenario"])]
    argv += ["--episodes", str(episodes)]
    for key in ("seed", "planner", "batch", "egos", "min_future", "rollouts", "model"):
        if key in ident:
            argv += ["--" + key.replace("_", "-"), str(ident[key])]
    sim = ident.get("sim", {})
    for f in dataclasses.fields(SimConfig):
        if f.name not in sim or sim[f.name] is None:
            continue  # None: the model's own default, which the flag's absence keeps
        flag = "--" + f.name.replace("_", "-")
        value = sim[f.name]
        if isinstance(value, bool):
            argv.append(flag if value else "--no-" + flag[2:])
        else:
            argv += [flag, str(value)]
    if ident.get("env_config"):
        # --like and --env-config as the run merged them (over the policy's sidecar).
        argv += ["--env-config", json.dumps(ident["env_config"], sort_keys=True)]
    argv += ["--out", str(Path(run.directory)), "--resume"]
    return argv


def command_text(run: Run) -> str:
    """The contents of ``command.txt``: comments on how to use it, then one shell line."""
    lines = [
        "# Rerun of this stress run (rebuilt from run.json). As is, it finishes the run in",
        "# this directory (--resume); change --out to reproduce it from scratch.",
    ]
    if str(run.identity.get("planner", "")).startswith(PYTHON_PLANNER_PREFIX):
        lines.append(
            "# Its planner was given from Python (planner_factory): no --planner rebuilds it. "
            "Rerun it from your script; the line below names it for the record only."
        )
    if str(run.identity.get("planner", "")).startswith(SB3_PREFIX):
        lines.append(
            "# sb3 planner: the policy's PATH.env.json sidecar, if any, is read again; "
            "--env-config holds what --like and --env-config added."
        )
    unknown = sorted(
        set(run.identity.get("sim", {})) - {f.name for f in dataclasses.fields(SimConfig)}
    )
    if unknown:
        lines.append(f"# run.json has settings this version does not know: {', '.join(unknown)}")
    lines.append(shlex.join(stress_argv(run)))
    return "\n".join(lines) + "\n"
