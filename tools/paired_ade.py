"""Two or more world models on the same windows: one-sample ADE over 0-3 s against constant
velocity, and each model's difference from the first, paired by scene with a bootstrap interval
(docs/history/world_model.md, "Parked cars"):

    python tools/paired_ade.py scenarionet:path/to/nuscenes_mini_scenarionet runs/a runs/b default
    python tools/paired_ade.py data/ngsim_heldout default --by 'Peach|US101'   # per road
    python tools/paired_ade.py scenarionet:DIR runs/flagged runs/flagged@generated

A model named ``M@generated`` (or ``M@recorded``) reads every scene as highway-env's traffic
(or as a recording): the windows' ``recorded`` flag that a model trained with
``source_flag`` reads (docs/world_model_experiments.md, "Real driving and generated traffic
told apart").

Every second of each log where 3 s of history and 3 s of future exist, every agent the model
sees (as ``counterscene evaluate-model --every 1``, one sample per sampling call, the same seed
for every model). The ratio is the sum of the model's ADE over the sum of constant velocity's.
"""

from __future__ import annotations

import argparse
import re

import numpy as np
import torch

from counterscene_env.scene.core import GENERATED_SOURCE
from counterscene_env.scene.sources import stored_scenes
from counterscene_env.world_model.checkpoint import load_model
from counterscene_env.world_model.eval_windows import window_batches, window_jobs
from counterscene_env.world_model.evaluate import constant_velocity

HORIZON = 30  # steps (3 s at 10 Hz)
NO_INTERVAL = "[one scene: no interval]"  # as `counterscene evaluate-model` says it


def per_scene(model, scenes, seed: int) -> np.ndarray:
    """``[S, 2]``: each scene's summed ADE over 0-3 s, the model's and constant velocity's [m]."""
    jobs = window_jobs(scenes, model.config.history_steps, 10, HORIZON)
    g = torch.Generator().manual_seed(seed)
    sums = np.zeros((len(scenes), 2))
    for part, batch in window_batches(model, scenes, jobs):
        with torch.no_grad():
            pred = model.sample(batch, 1, g)
            state = model.current_state(batch).numpy()
        xy = pred.trajectory[:, 0, :, :HORIZON, :2].numpy()  # [B, K, H, 2]
        future = batch["future"].numpy()[..., :HORIZON, :2]
        ok = batch["future_valid"].numpy()[..., :HORIZON]
        cv = constant_velocity(state, HORIZON, model.config.dt)
        seen = model.agent_mask(batch).numpy()
        for b, (scene, _) in enumerate(part):
            for k in np.flatnonzero(seen[b] & ok[b].any(-1)):
                o = ok[b, k]
                sums[scene, 0] += np.linalg.norm(xy[b, k][o] - future[b, k][o], axis=-1).mean()
                sums[scene, 1] += np.linalg.norm(cv[b, k][o] - future[b, k][o], axis=-1).mean()
    return sums


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("source", help="scenario spec: scenarionet:DIR, commonroad:DIR or a dataset")
    ap.add_argument("models", nargs="+", help="model directories ('default': the shipped one)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--bootstrap", type=int, default=2000)
    ap.add_argument(
        "--by",
        metavar="REGEX",
        help="also give each model's ratio per group of scenes: the first match of REGEX in "
        "the scene's id (e.g. 'Peach|US101' for NGSIM's roads), with its bootstrap interval",
    )
    args = ap.parse_args()
    repeated = sorted({m for m in args.models if args.models.count(m) > 1})
    if repeated:  # results are per name: a repeated one would silently count once
        ap.error(f"model given more than once: {', '.join(repeated)} (name each model once)")
    scenes = list(stored_scenes(args.source))
    sums = {m: model_sums(m, scenes, args.seed) for m in args.models}
    rng = np.random.default_rng(0)
    draws = rng.integers(0, len(scenes), (args.bootstrap, len(scenes)))
    first = sums[args.models[0]]
    for name, s in sums.items():
        ratio = s[:, 0].sum() / s[:, 1].sum()
        line = f"{name}: ADE 0-3 s / constant velocity {ratio:.3f}"
        if name != args.models[0]:
            diff = [(s[i, 0].sum() - first[i, 0].sum()) / first[i, 1].sum() for i in draws]
            lo, hi = np.percentile(diff, [2.5, 97.5])
            line += (
                f", minus {args.models[0]}: {ratio - first[:, 0].sum() / first[:, 1].sum():+.3f}"
            )
            line += f" [{lo:+.3f}, {hi:+.3f}]" if len(scenes) > 1 else f" {NO_INTERVAL}"
        print(line)
        if args.by:
            for group, rows in groups(scenes, args.by).items():
                print("  " + group_line(group, s[rows], rng, args.bootstrap))


def model_sums(name: str, scenes, seed: int) -> np.ndarray:
    """:func:`per_scene` of model ``name`` (``DIR``, ``DIR@generated`` or ``DIR@recorded``)."""
    path, _, read_as = name.partition("@")
    if read_as not in ("", "generated", "recorded"):
        raise SystemExit(f"{name}: after '@' comes 'generated' or 'recorded', not {read_as!r}")
    if read_as:
        source = GENERATED_SOURCE if read_as == "generated" else "recording"
        scenes = [s.replace(metadata={**s.metadata, "source": source}) for s in scenes]
    return per_scene(load_model(path).eval(), scenes, seed)


def groups(scenes, pattern: str) -> dict[str, list[int]]:
    """Scene rows by the first match of ``pattern`` in their id (``"other"``: no match)."""
    out: dict[str, list[int]] = {}
    for i, scene in enumerate(scenes):
        m = re.search(pattern, scene.scenario_id)
        out.setdefault(m.group(0) if m else "other", []).append(i)
    return out


def group_line(group: str, sums: np.ndarray, rng, resamples: int) -> str:
    """``group: ratio [interval] (n scenes)`` over ``sums [S, 2]`` (bootstrap over scenes).

    A group of one scene has no interval (resampling one scene gives it back every time).
    """
    ratio = sums[:, 0].sum() / sums[:, 1].sum()
    # Drawn for one scene too, so that the groups after it keep their intervals.
    draws = rng.integers(0, len(sums), (resamples, len(sums)))
    if len(sums) < 2:
        return f"{group}: {ratio:.3f} {NO_INTERVAL} (1 scene)"
    boot = [sums[d, 0].sum() / max(sums[d, 1].sum(), 1e-9) for d in draws]
    lo, hi = np.percentile(boot, [2.5, 97.5])
    return f"{group}: {ratio:.3f} [{lo:.3f}, {hi:.3f}] ({len(sums)} scenes)"


if __name__ == "__main__":
    main()
