"""One block of a dataset build: record or convert its seeds or files, save them as one shard.

``scene/datagen.py`` cuts a build into blocks and runs these in ``--workers`` processes (they
are module-level functions so that a process pool can pickle them by name). Each returns the
block's manifest entry: the shard's file, what it holds and what was rejected and why.
"""

from __future__ import annotations

import time
from pathlib import Path

from counterscene_env.scene.shards import save_scenes

__all__ = ["convert_commonroad_block", "convert_scenarionet_block", "generate_block", "save_block"]


def generate_block(
    out: str,
    k: int,
    scenario: str,
    seeds: list[int],
    duration: float,
    limit: int,
    yielding: str = "highway-env",
) -> dict:
    """Record the seeds of one block in order, stopping once ``limit`` scenes are safe."""
    from counterscene_env.scene.highway import GeneratorConfig, RejectedScene, record

    cfg = GeneratorConfig(duration=duration, yielding=yielding)
    scenes, rejected = [], []
    for s in seeds:
        if len(scenes) >= limit:
            break
        try:
            scenes.append(record(scenario, s, cfg))
        except RejectedScene as exc:
            rejected.append([s, str(exc)])
    entry = save_block(out, k, scenes, rejected, [int(sc.metadata["seed"]) for sc in scenes])
    # A block that stopped early does not cover its seeds: a larger rerun must redo it.
    entry["truncated"] = len(scenes) + len(rejected) < len(seeds)
    return entry


def convert_scenarionet_block(out: str, k: int, files: list[str]) -> dict:
    """Load one block of ScenarioNet files; a file that fails is listed with its error."""
    from counterscene_env.scene.core import SceneError
    from counterscene_env.scene.scenarionet import load_scenarionet

    scenes, rejected = [], []
    for f in files:
        start = time.perf_counter()
        try:
            scene = load_scenarionet(f)
        except SceneError as exc:
            rejected.append([Path(f).name, str(exc)])
            continue
        except Exception as exc:  # odd data in one file must not stop the whole conversion
            rejected.append([Path(f).name, f"{type(exc).__name__}: {exc}"])
            continue
        scene.metadata["generation_time_s"] = time.perf_counter() - start
        scenes.append(scene)
    return save_block(
        out, k, scenes, rejected, [Path(s.metadata.get("source_file", "")).name for s in scenes]
    )


def convert_commonroad_block(out: str, k: int, files: list[str], all_egos: bool) -> dict:
    """Load one block of CommonRoad files (every ego choice with ``all_egos``)."""
    from counterscene_env.scene.commonroad import iter_commonroad

    scenes, rejected = [], []
    for f in files:
        report: dict = {}
        start = time.perf_counter()
        got = list(iter_commonroad(f, all_egos, skip_duplicates=False, report=report))
        rejected += [[name, why] for name, why in report["skipped"].items()]
        for scene in got:
            scene.metadata["generation_time_s"] = (time.perf_counter() - start) / len(got)
        scenes += got
    return save_block(out, k, scenes, rejected, [s.scenario_id for s in scenes])


def save_block(out: str, k: int, scenes: list, rejected: list, ids: list) -> dict:
    """Write block ``k``'s scenes to ``shard-{k:05d}.npz`` in ``out``; its manifest entry."""
    name = f"shard-{k:05d}.npz"
    if scenes:
        save_scenes(scenes, Path(out) / name)
    return {
        "block": k,
        "file": name,
        "scenes": len(scenes),
        "seeds": ids,
        "rejected": rejected,
        "num_agents": [s.num_agents for s in scenes],
        "num_steps": [s.num_steps for s in scenes],
        "gen_time_s": [round(float(s.metadata.get("generation_time_s", 0.0)), 4) for s in scenes],
    }
