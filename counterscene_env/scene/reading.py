"""Scenes from a path on disk: a dataset directory, a shard file, a ScenarioNet ``.pkl`` file
or a directory of them. One job: the reading side of ``scene/datagen.py`` (which writes
dataset directories) and of the ScenarioNet importer, for every command that takes a path.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from counterscene_env.scene.core import Scene, SceneTooShort
from counterscene_env.scene.manifest import MANIFEST, read_manifest, shard_paths
from counterscene_env.scene.shards import load_scenes

__all__ = ["iter_dataset", "iter_scenarionet", "iter_scenes"]


def iter_scenes(
    path: str | os.PathLike, on_short: Callable[[str], None] | None = None
) -> Iterator[tuple[Scene, float]]:
    """Yield (scene, seconds it took to produce) from a dataset directory, a shard file, a
    ScenarioNet ``.pkl`` file, or a directory of them (sorted, recursively).

    ``on_short(file name)`` is called for a ``.pkl`` log too short for any episode, which is
    then skipped; without it such a log raises :class:`SceneTooShort`.
    """
    path = Path(path)
    if (path.is_dir() and not (path / MANIFEST).is_file()) or path.suffix == ".pkl":
        yield from iter_scenarionet(path, on_short)
    elif path.is_file() and path.suffix != ".npz":
        hint = {
            ".xml": "CommonRoad scenarios are read by converting them: counterscene generate "
            "--from-commonroad DIR --out DATASET",
            ".json": "give the dataset directory that holds it",
        }.get(path.suffix, "give a dataset directory, a shard .npz or ScenarioNet .pkl files")
        raise ValueError(f"{path}: not a file of scenes; {hint}")
    else:
        yield from _iter_stored(path)


def iter_scenarionet(
    path: str | os.PathLike, on_short: Callable[[str], None] | None = None
) -> Iterator[tuple[Scene, float]]:
    """Yield (scene, seconds it took to import) from a ScenarioNet ``.pkl`` file or a directory
    of them only (``scenarionet:DIR``, ``--scenarionet DIR``): a CounterScene dataset
    directory or shard is refused by ``scenarionet_files``, naming it, not read as logs.
    ``on_short``: as :func:`iter_scenes`'s."""
    from counterscene_env.scene.scenarionet import load_scenarionet, scenarionet_files

    for f in scenarionet_files(path):  # raises if there are none
        start = time.perf_counter()
        try:
            scene = load_scenarionet(f)
        except SceneTooShort:
            if on_short is None:
                raise
            on_short(f.name)
            continue
        yield scene, time.perf_counter() - start


def iter_dataset(path: str | os.PathLike) -> Iterator[tuple[Scene, float]]:
    """Yield (scene, seconds it took to generate) from a dataset directory or one of its shard
    files only, as ``--data`` names them: a ScenarioNet ``.pkl`` or a directory of them is
    refused with a :class:`~counterscene_env.scene.shards.ShardError` naming the path, never
    read (its own flag reads it)."""
    yield from _iter_stored(Path(path))


def _iter_stored(path: Path) -> Iterator[tuple[Scene, float]]:
    """(scene, generation time) from a dataset directory or a shard file."""

    if path.is_dir():
        read_manifest(path)
        for shard in shard_paths(path):
            for scene in load_scenes(shard):
                yield scene, float(scene.metadata.get("generation_time_s", math.nan))
    elif path.is_file():
        for scene in load_scenes(path):
            yield scene, float(scene.metadata.get("generation_time_s", math.nan))
    else:
        raise FileNotFoundError(f"{path}: no such file or directory")
