"""Behaviour snapshot for refactors: record what the public commands produce, then compare.

A refactor that "changes no behaviour" must give, for the same seeds and actions, the same
stress results, the same env rollout and the same open-loop evaluation, bit for bit; only
wall-clock timings may differ. This script records those outputs through the public
interfaces (the ``counterscene`` command and ``gym.make``), so it runs unchanged on the code
before and after a change::

    python tools/regression.py record runs/before        # on the old code
    python tools/regression.py record runs/after         # on the new code
    python tools/regression.py compare runs/before runs/after

``record`` runs (several minutes on 2 cores):

- ``counterscene stress --json --out`` for 16 episodes each of intersection (IDM ego,
  guidance ``full``), merge (IDM, ``none``) and roundabout (log replay, ``full``);
- a 200-step ``CounterScene-v0`` rollout with resets, seed 7, actions from a seeded generator;
- ``counterscene evaluate-model --json`` on 10 generated intersection scenes.

``compare`` prints each difference (file, key path, before, after) and exits 1 if there is any.
Only the result files are compared: the JSON and JSON-lines records and summaries
(:data:`RESULT_SUFFIXES`); the rest of a ``stress --out`` directory (``command.txt``, which
names the ``--out`` path, ``report.md``/``report.html``, ``plots/``, ``videos/``) is
presentation of those results and is left out. Timing fields (:data:`TIMING_KEYS`) are left
out of the comparison; ``--ignore-additions`` also leaves out files and keys that only the
new code writes (fields added on purpose).
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
from pathlib import Path

#: Keys whose values are wall-clock timings (never compared).
TIMING_KEYS = frozenset(
    {
        "seconds",
        "replan_seconds",
        "seconds_per_episode",
        "seconds_per_replan",
        "time_s",
        "load_seconds",
        "eval_seconds",
        "wall_seconds",  # timings.json: the run's wall clock, worker start-up included
        "wall_seconds_per_episode",
        "timings",  # `stress --json`: the run's wall-clock figures (timings.json)
    }
)

#: Suffixes of the result files (records and summaries) that ``compare`` reads.
RESULT_SUFFIXES = (".json", ".jsonl")

STRESS_RUNS = {
    "stress-intersection": ["--scenario", "intersection", "--planner", "idm", "--guidance", "full"],
    "stress-merge": ["--scenario", "merge", "--planner", "idm", "--guidance", "none"],
    "stress-roundabout": ["--scenario", "roundabout", "--planner", "log", "--guidance", "full"],
}


def _run(cmd: list[str], out: Path | None = None) -> None:
    print("$", " ".join(cmd), flush=True)
    result = subprocess.run(cmd, check=True, capture_output=True, text=True)
    if out is not None:
        out.write_text(result.stdout)


def record_rollout(path: Path, steps: int = 200, seed: int = 7) -> None:
    """``steps`` env steps of ``CounterScene-v0`` (intersection) with resets, as JSON lines."""
    import gymnasium as gym
    import numpy as np

    import counterscene_env  # noqa: F401  (registers the env)

    env = gym.make("CounterScene-v0", config={"scenario": "intersection"})
    rng = np.random.default_rng(seed)
    with open(path, "w") as f:
        obs, info = env.reset(seed=seed)
        f.write(json.dumps(_plain({"reset": 0, "obs": obs, "info": info})) + "\n")
        resets = 0
        for i in range(steps):
            action = rng.uniform(-1, 1, size=2).astype(np.float32)
            obs, reward, terminated, truncated, info = env.step(action)
            row = {"step": i, "action": action, "obs": obs, "reward": reward}
            row |= {"terminated": terminated, "truncated": truncated, "info": info}
            f.write(json.dumps(_plain(row)) + "\n")
            if terminated or truncated:
                resets += 1
                obs, info = env.reset()
                f.write(json.dumps(_plain({"reset": resets, "obs": obs, "info": info})) + "\n")
    env.close()


def _plain(x):
    """JSON-ready, exact: floats as their repr, so a bit-level change shows."""
    import numpy as np

    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return _plain(x.tolist())
    if isinstance(x, np.generic):
        return _plain(x.item())
    if isinstance(x, float):
        return repr(x)
    return x


def record(out: Path, episodes: int = 16) -> None:
    out.mkdir(parents=True, exist_ok=True)
    exe = [sys.executable, "-m", "counterscene_env.cli"]
    for name, args in STRESS_RUNS.items():
        cmd = [*exe, "stress", *args, "--episodes", str(episodes), "--seed", "100000"]
        _run([*cmd, "--json", "--quiet", "--out", str(out / name)])
    cmd = [*exe, "evaluate-model", "--scenario", "intersection", "--scenes", "10"]
    _run([*cmd, "--seed", "100000", "--json", "--quiet"], out / "evaluate-model.json")
    print("$ rollout: CounterScene-v0 intersection, 200 steps, seed 7", flush=True)
    record_rollout(out / "rollout.jsonl")


def _files(root: Path) -> list[Path]:
    """The result files under ``root`` (relative paths), see :data:`RESULT_SUFFIXES`."""
    return sorted(
        p.relative_to(root) for p in root.rglob("*") if p.is_file() and p.suffix in RESULT_SUFFIXES
    )


def _load(path: Path) -> list:
    text = path.read_text()
    if path.suffix == ".jsonl":
        return [json.loads(line) for line in text.splitlines() if line.strip()]
    return [json.loads(text)]


def diff(a, b, where: str = "", additions: bool = True) -> list[str]:
    """Differences between two JSON values, timing keys left out (``additions=False``: keys
    only in ``b`` too, for a change that adds fields on purpose)."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            if k in TIMING_KEYS or (k not in a and not additions):
                continue
            if k not in a or k not in b:
                out.append(f"{where}.{k}: only in {'after' if k in b else 'before'}")
            else:
                out += diff(a[k], b[k], f"{where}.{k}", additions)
        return out
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{where}: length {len(a)} != {len(b)}"]
        return [
            d
            for i, (x, y) in enumerate(zip(a, b, strict=True))
            for d in diff(x, y, f"{where}[{i}]", additions)
        ]
    same = a == b or (
        isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b)
    )
    return [] if same else [f"{where}: {a!r} != {b!r}"]


def compare(before: Path, after: Path, additions: bool = True) -> int:
    names = sorted(set(_files(before)) | set(_files(after)))
    others = sum(p.is_file() for root in (before, after) for p in root.rglob("*")) - sum(
        len(_files(root)) for root in (before, after)
    )
    if others:
        print(f"({others} non-result files left out: commands, reports, plots, videos)")
    problems = 0
    for name in names:
        if not (before / name).exists() and not additions:
            print(f"{name}: only in after (an addition, ignored)")
            continue
        if not (before / name).exists() or not (after / name).exists():
            print(f"{name}: only in {'after' if (after / name).exists() else 'before'}")
            problems += 1
            continue
        found = diff(_load(before / name), _load(after / name), additions=additions)
        print(f"{name}: {'identical' if not found else f'{len(found)} differences'}")
        for line in found[:20]:
            print(f"  {line}")
        problems += bool(found)
    print("IDENTICAL (timings aside)" if not problems else f"{problems} files differ")
    return int(bool(problems))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    rec = sub.add_parser("record", help="record the outputs into DIR")
    rec.add_argument("out", type=Path)
    rec.add_argument("--episodes", type=int, default=16, help="episodes per stress run (16)")
    cmp_ = sub.add_parser("compare", help="compare two recordings")
    cmp_.add_argument("before", type=Path)
    cmp_.add_argument("after", type=Path)
    cmp_.add_argument(
        "--ignore-additions",
        action="store_true",
        help="ignore files and keys only in AFTER (a change that adds outputs on purpose)",
    )
    args = parser.parse_args()
    if args.command == "record":
        record(args.out, args.episodes)
        return 0
    return compare(args.before, args.after, additions=not args.ignore_additions)


if __name__ == "__main__":
    sys.exit(main())
