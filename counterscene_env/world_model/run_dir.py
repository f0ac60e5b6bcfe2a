"""A training run's directory (``counterscene train --out DIR``): what may start or resume
there, its resumable state and its log.

A run directory holds ``last.pt`` (the state to resume), ``model.safetensors`` +
``config.json`` (the EMA model) and ``log.jsonl`` (one record per checkpoint). A run resumes
when ``last.pt`` is there (:func:`check_resume`); a fresh run writes ``last.pt`` first (at
step 0), so a directory with a model but no ``last.pt`` holds someone else's model and is
refused (:func:`check_fresh_out`).
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from counterscene_env.world_model.checkpoint import CONFIG, WEIGHTS, model_dir
from counterscene_env.world_model.train_config import TrainConfig, plain_settings, same_path

STATE_FILE = "last.pt"
LOG_FILE = "log.jsonl"
#: The files of the EMA model a run writes.
MODEL_FILES = (WEIGHTS, CONFIG)
#: The settings that name datasets (``same_path`` compares them).
PATH_SETTINGS = ("data", "agent_centred", "smooth_tracks")


def start_over(out: str | os.PathLike) -> str:
    """How to start a run in ``out`` over (the end of a refusal's message)."""
    return (
        f"use another --out, or delete the run in {out} ({STATE_FILE}, {MODEL_FILES[0]}, "
        f"{MODEL_FILES[1]}, {LOG_FILE}) to start over"
    )


def _comparable(settings: Mapping[str, Any]) -> dict[str, Any]:
    """``settings`` (:func:`plain_settings`) with every dataset and ``init`` path in one
    spelling (:func:`same_path`, relative to the working directory): a resumed run may spell
    its paths another way. ``agent_centred`` and ``smooth_tracks`` are sets."""
    d = dict(settings)
    for key in PATH_SETTINGS:
        if key in d:
            paths = [same_path(p) for p in d[key]]
            d[key] = paths if key == "data" else sorted(paths)  # data's order sets the sources
    if d.get("init") not in (None, "default"):
        d["init"] = same_path(d["init"])
    return d


def data_fingerprint(data: Sequence[str]) -> list[list[list[Any]]]:
    """Per ``data`` entry, its files as ``[name, bytes]`` pairs: the shards of a dataset
    directory (as its manifest lists them) or the shard file itself; ``[]`` where there is
    none (loading then names the problem). Cheap (no file is read but the manifest), and it
    changes when a dataset gains or loses a shard or one changes size, which moves its
    validation split (the last scenes validate). Not the times: a copied dataset is the same
    one. A shard rewritten at the same size goes unnoticed."""
    from counterscene_env.scene.manifest import MANIFEST, shard_paths

    out = []
    for d in data:
        path = Path(d)
        if (path / MANIFEST).is_file():
            files = [(os.path.relpath(f, path), f) for f in shard_paths(path)]
        else:
            files = [(path.name, path)]
        ok = all(f.is_file() for _, f in files)
        out.append([[name, f.stat().st_size] for name, f in files] if ok else [])
    return out


def check_resume(
    state: Mapping[str, Any], cfg: TrainConfig, path: Path, fingerprint: list[Any]
) -> None:
    """Raise ``ValueError`` unless the run in ``state`` (read from ``path``, ``last.pt``) may go
    on with ``cfg``: the same settings (paths compared by :func:`same_path`), the same files in
    every dataset (``fingerprint``, :func:`data_fingerprint`; states from before it was stored
    are not checked) and no more steps done than ``cfg.steps``. Each message names what differs
    and what to do."""
    out = path.parent
    old, new = _comparable(state["config"]), _comparable(plain_settings(cfg))
    changed = sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k))
    if changed:
        raise ValueError(
            f"{path} belongs to a run with different settings ({', '.join(changed)}); "
            + start_over(out)
        )
    before = state.get("data_files")
    if before is not None:
        moved = [d for d, a, b in zip(cfg.data, before, fingerprint, strict=True) if a != b]
        if moved:
            raise ValueError(
                f"{path}: the files of --data {', '.join(moved)} changed since the run started "
                "(shards added, removed or resized), which moves the held-out validation "
                "scenes; restore them, or " + start_over(out)
            )
    if int(state["step"]) > cfg.steps:  # its record and weights are past --steps
        raise ValueError(
            f"{out} holds a run at step {state['step']}, more than --steps {cfg.steps}: "
            f"rerun with --steps {state['step']} or more, or use another --out"
        )


def check_fresh_out(out: Path, init: str | None) -> None:
    """Raise ``ValueError`` if ``out``, which holds no ``last.pt``, holds a model: a fresh run
    would overwrite it (a run writes ``last.pt`` before its first model, so the model is not
    this run's). The message names the directory, whether it is ``init``'s model, and what to
    do; nothing is written."""
    found = [name for name in MODEL_FILES if (out / name).exists()]
    if not found:
        return
    start = None if init is None else model_dir(init)
    its = (
        " (it is this run's --init)"
        if start is not None and same_path(start) == same_path(out)
        else ""
    )
    raise ValueError(
        f"{out} already holds a model{its} ({', '.join(found)}) and no {STATE_FILE} to resume "
        f"from: a new run would overwrite it. Use another --out, or move that model out of "
        f"{out} first"
    )


def read_state(path: Path, device: Any) -> dict[str, Any]:
    """The resumable state of a run in ``path`` (``last.pt``; plain containers only:
    ``weights_only``), its tensors on torch ``device``.

    Raises:
        ValueError: naming the file, when it is not a readable state (cut short, foreign)."""
    import torch

    try:
        return torch.load(path, weights_only=True, map_location=device)
    except Exception as exc:  # torch raises several kinds for a damaged or foreign file
        raise ValueError(
            f"{path} is not a readable training state ({type(exc).__name__}: {exc}); "
            + start_over(path.parent)
        ) from None


def save_state(out: Path, state: Mapping[str, Any]) -> None:
    """Write ``out/last.pt`` whole or not at all (a temporary file, renamed): a stop while
    writing leaves the previous state."""
    import torch

    tmp = out / (STATE_FILE + ".tmp")
    torch.save(dict(state), tmp)
    os.replace(tmp, out / STATE_FILE)


def trim_log(log: Path, step: int) -> None:
    """Keep in ``log`` (``log.jsonl``) one record per step up to ``step``, the step of the
    ``last.pt`` the run resumes from: a run stopped between writing a record and its
    ``last.pt`` reruns those steps, and would log them twice. Of a step logged twice the
    later record stays; a line cut short goes. The file is replaced at once (no half-written
    log), and left alone when nothing goes."""
    if not log.is_file():
        return
    lines = log.read_text().splitlines()
    kept: dict[int, str] = {}
    for line in lines:
        try:
            at = json.loads(line)["step"]
        except (json.JSONDecodeError, KeyError, TypeError):
            continue  # cut short by the stop
        if isinstance(at, int) and at <= step:
            kept[at] = line  # of a step logged twice, the later record
    keep = [kept[at] for at in sorted(kept)]
    if keep == lines:
        return
    tmp = log.with_name(log.name + ".tmp")
    tmp.write_text("".join(line + "\n" for line in keep))
    os.replace(tmp, log)
