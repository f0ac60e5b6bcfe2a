"""A dataset directory's ``manifest.json``: what it holds, read, checked and written.

The manifest lists the directory's shards (one per block of seeds or files, with each
block's seeds, rejected seeds and their reasons), the parameters that made them and the
format version. ``counterscene_env/scene/datagen.py`` builds datasets with it; readers
(``scene/reading.py``, ``world_model/dataset.py``) find the shards through it. A rewrite
is atomic, so an interrupted build leaves the last complete manifest.
"""

from __future__ import annotations

import importlib.metadata
import json
import os
import re
from pathlib import Path

from counterscene_env.scene.shards import ShardError

MANIFEST = "manifest.json"
DATASET_FORMAT = "counterscene-dataset"
DATASET_VERSION = 1


def read_manifest(directory: str | os.PathLike) -> dict:
    """The manifest of a dataset directory, checked for format and version."""
    path = Path(directory) / MANIFEST
    if not path.is_file():
        raise ShardError(f"{directory}: no {MANIFEST}; not a CounterScene dataset directory")
    try:
        manifest = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ShardError(f"{path}: corrupt manifest ({exc})") from exc
    if manifest.get("format") != DATASET_FORMAT:
        raise ShardError(f"{path}: not a CounterScene dataset manifest")
    if int(manifest.get("version", -1)) > DATASET_VERSION:
        raise ShardError(
            f"{path}: dataset format version {manifest['version']} is newer than this "
            f"counterscene_env reads ({DATASET_VERSION}); upgrade counterscene-env"
        )
    return manifest


def shard_paths(directory: str | os.PathLike) -> list[Path]:
    """The shard files of a dataset directory, in order."""
    manifest = read_manifest(directory)
    return [Path(directory) / s["file"] for s in manifest["shards"] if s["scenes"] > 0]


def refuse_shrinking(out: Path, manifest: dict, target: int | None) -> None:
    """Raise ValueError if ``out`` already holds more scenes than the ``target`` asked for."""
    held = manifest.get("scenes_requested")
    if target is not None and held is not None and held > target:
        # Shrinking would delete scenes someone generated; never do that silently.
        raise ValueError(
            f"{out} already holds a dataset of {held} scenes; asked for {target}. "
            "Use another --out, or ask for at least as many scenes."
        )


def reusable_blocks(out: Path, manifest: dict, target: int | None) -> dict[int, dict]:
    """The manifest's block entries a rerun keeps (shard on disk, complete enough), by block."""
    done: dict[int, dict] = {}
    for entry in sorted(manifest["shards"], key=lambda e: e["block"]):
        if entry["scenes"] and not (out / entry["file"]).is_file():
            continue
        # A block that stopped early is complete only if the target needs nothing more from it.
        covered = sum(e["scenes"] for e in done.values()) + entry["scenes"]
        if entry.get("truncated") and (target is None or covered < target):
            continue
        done[entry["block"]] = entry
    return done


#: Dataset parameters added after datasets were first written, with the value those had.
_DEFAULTS_BEFORE = {"yielding": "highway-env"}


#: What a build leaves in its directory before its first manifest (a stop between the first
#: shard and the manifest naming it): the shard, or a shard or manifest half written.
_BUILD_LEFTOVER = re.compile(
    r"shard-\d{5,}\.npz|\.shard-\d{5,}\.npz\.\d+\.tmp|\.manifest\.json\.tmp"
)
#: Files of a world-model training run (``world_model/run_dir.py``), named in a refusal.
_MODEL_RUN_FILES = ("model.safetensors", "config.json", "last.pt", "log.jsonl")
#: Entries a refusal lists before "and N more".
_LISTED = 4


def refuse_foreign_out(out: Path) -> None:
    """Raise ``ValueError`` if ``out``, which holds no manifest, holds anything a build did not
    leave there (:data:`_BUILD_LEFTOVER`): a new dataset would mix its shards into someone
    else's files (a trained model, logs, another program's output). The message names the
    directory and what it holds; nothing is written. An empty directory, or one holding only
    the first shard of a build stopped before its manifest, is a dataset's to start."""
    if not out.is_dir():
        return
    foreign = sorted(p.name for p in out.iterdir() if not _BUILD_LEFTOVER.fullmatch(p.name))
    if not foreign:
        return
    model = [name for name in _MODEL_RUN_FILES if name in foreign]
    if model:
        what = f"a trained world model ({', '.join(model)})"
    else:
        more = len(foreign) - _LISTED
        what = ", ".join(foreign[:_LISTED]) + (f" and {more} more" if more > 0 else "")
    raise ValueError(
        f"--out {out} is not a dataset directory (no {MANIFEST}) and is not empty: it holds "
        f"{what}. Nothing was written; give a new or empty directory for the dataset"
    )


def open_manifest(out: Path, params: dict) -> dict:
    """The manifest in ``out`` (checked against ``params``), or a fresh one for a new dataset
    in a new, empty or :func:`refuse_foreign_out`-clean directory."""
    if (out / MANIFEST).is_file():
        manifest = read_manifest(out)
        # A key the manifest predates had its default then (datasets made before it resume).
        was = {**_DEFAULTS_BEFORE, **manifest}
        mismatch = {k: (was.get(k), v) for k, v in params.items() if was.get(k) != v}
        if mismatch:
            detail = ", ".join(f"{k}: {a!r} there, {b!r} asked" for k, (a, b) in mismatch.items())
            raise ValueError(f"{out} holds a different dataset ({detail}); use another --out")
        return manifest
    refuse_foreign_out(out)
    return {
        "format": DATASET_FORMAT,
        "version": DATASET_VERSION,
        **params,
        "counterscene_version": importlib.metadata.version("counterscene-env"),
        "scenes": 0,
        "shards": [],
    }


def write_manifest(out: Path, manifest: dict, done: dict[int, dict], target: int | None) -> dict:
    """Write the finished blocks ``done`` into ``out``'s manifest, atomically (a temporary file
    replaced in one step), and return it."""
    manifest["shards"] = [done[k] for k in sorted(done)]
    manifest["scenes"] = sum(s["scenes"] for s in manifest["shards"])
    manifest["scenes_requested"] = target
    manifest["rejected"] = sum(len(s["rejected"]) for s in manifest["shards"])
    tmp = out / f".{MANIFEST}.tmp"
    tmp.write_text(json.dumps(manifest, indent=1))
    os.replace(tmp, out / MANIFEST)
    return manifest
