"""Building a dataset directory: scenes in shards plus a ``manifest.json``, resumable, parallel.

Generated data (``counterscene generate --scenario S --scenes N --seed S0 --out DIR``): candidate
seeds are cut into blocks of ``shard_size`` consecutive seeds; block k tries seeds
``S0 + k * shard_size ...`` once each and writes the accepted scenes to ``shard-{k:05d}.npz``.
A rejected seed (unsafe factual log) is listed in the manifest with its reason and replaced by
the seeds after it, so the dataset is always "the first N safe seeds from S0", whatever the
number of workers, and no two scenes share a seed.

Real logs (``counterscene generate --from-scenarionet SRC --out DIR``, or
``--from-commonroad SRC``): the sorted ``.pkl`` (``.xml``) files are cut into blocks the same
way; a file that fails to load is listed with its error. CommonRoad files that repeat another
file's traffic (the same recording with another planning problem) are listed in the manifest's
``duplicates`` and not converted.

Resuming: the manifest is rewritten after every finished shard; a rerun of the same command
skips the shards it lists, so an interrupted run loses at most the shards in flight.
"""

from __future__ import annotations

import hashlib
import os
import signal
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from pathlib import Path

from counterscene_env.config import check_int, check_real
from counterscene_env.scene.blocks import (
    convert_commonroad_block,
    convert_scenarionet_block,
    generate_block,
)
from counterscene_env.scene.core import GENERATED_SOURCE
from counterscene_env.scene.manifest import (
    MANIFEST,
    open_manifest,
    refuse_shrinking,
    reusable_blocks,
    write_manifest,
)
from counterscene_env.scene.shards import load_scenes, save_scenes


def generate_dataset(
    out: str | os.PathLike,
    scenario: str,
    scenes: int,
    seed: int = 0,
    *,
    shard_size: int = 50,
    workers: int = 1,
    duration: float = 13.0,
    yielding: str = "highway-env",
    progress: bool = True,
) -> dict:
    """Generate ``scenes`` safe scenes of a highway-env scenario into ``out``; returns the
    manifest. ``yielding``: how intersection traffic gives way (``GeneratorConfig.yielding``)."""
    from counterscene_env.scene.highway import GENERATOR_VERSION, MIN_DURATION, check_yielding

    check_yielding(scenario, yielding)
    duration = check_real("duration", duration, ge=MIN_DURATION)  # before --out is made
    for key, value in (("scenes", scenes), ("shard_size", shard_size), ("workers", workers)):
        check_int(key, value, ge=1)
    check_int("seed", seed, ge=0)
    params = {
        "source": GENERATED_SOURCE,
        "scenario": scenario,
        "seed": int(seed),
        "shard_size": int(shard_size),
        "duration": float(duration),
        "generator_version": GENERATOR_VERSION,
        "yielding": yielding,
    }

    def block_args(k: int, limit: int) -> tuple:
        lo = seed + k * shard_size
        seeds = list(range(lo, lo + shard_size))
        return (generate_block, str(out), k, scenario, seeds, duration, limit, yielding)

    return _build(Path(out), params, scenes, block_args, None, workers, progress)


def convert_scenarionet(
    src: str | os.PathLike,
    out: str | os.PathLike,
    *,
    shard_size: int = 50,
    workers: int = 1,
    progress: bool = True,
) -> dict:
    """Convert every ScenarioNet ``.pkl`` under ``src`` into shards in ``out``; returns the manifest."""
    from counterscene_env.scene.scenarionet import scenarionet_files

    files = [str(p) for p in scenarionet_files(src)]
    params = {"source": "scenarionet"}
    return _convert_files(
        src, out, files, params, (convert_scenarionet_block,), shard_size, workers, progress
    )


def convert_commonroad(
    src: str | os.PathLike,
    out: str | os.PathLike,
    *,
    all_egos: bool = False,
    shard_size: int = 50,
    workers: int = 1,
    progress: bool = True,
) -> dict:
    """Convert the CommonRoad ``.xml`` files under ``src`` into shards in ``out``: one scene
    per distinct recording (files that repeat another's traffic are listed, not converted),
    or with ``all_egos`` one per ego choice. Returns the manifest."""
    from counterscene_env.scene.commonroad import commonroad_files, duplicate_files

    duplicates = duplicate_files(src)
    files = [str(p) for p in commonroad_files(src) if p.name not in duplicates]
    params = {"source": "commonroad", "all_egos": bool(all_egos), "duplicates": duplicates}
    worker = (convert_commonroad_block, bool(all_egos))
    return _convert_files(src, out, files, params, worker, shard_size, workers, progress)


def _convert_files(
    src: str | os.PathLike,
    out: str | os.PathLike,
    files: list[str],
    params: dict,
    worker: tuple,
    shard_size: int,
    workers: int,
    progress: bool,
) -> dict:
    """Convert sorted ``files`` in blocks of ``shard_size``: ``worker`` is the block function
    and its arguments after ``(out, k, block files)``; ``params`` name the source."""
    # Blocks are positions in the sorted file list: a resume over a changed folder would
    # duplicate some files and skip others, so the list itself is part of the parameters.
    params = {
        **params,
        "src": str(Path(src).resolve()),
        "shard_size": int(shard_size),
        "files": len(files),
        "file_list_sha256": hashlib.sha256("\n".join(files).encode()).hexdigest()[:16],
    }
    blocks = [files[i : i + shard_size] for i in range(0, len(files), shard_size)]
    fn, *extra = worker

    def block_args(k: int, limit: int) -> tuple:
        return (fn, str(out), k, blocks[k], *extra)

    return _build(Path(out), params, None, block_args, len(blocks), workers, progress)


# ---------------------------------------------------------------------- the build loop
def _build(
    out: Path,
    params: dict,
    target: int | None,
    block_args: Callable[[int, int], tuple],
    num_blocks: int | None,
    workers: int,
    progress: bool,
) -> dict:
    """Run blocks (in parallel) until ``target`` scenes (or all ``num_blocks``) are done."""
    from tqdm.auto import tqdm

    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is a file, not a directory")
    manifest = open_manifest(out, params)
    refuse_shrinking(out, manifest, target)
    out.mkdir(parents=True, exist_ok=True)  # every check is done: a refused run writes nothing
    done = reusable_blocks(out, manifest, target)
    bar = tqdm(
        total=target, disable=not progress, unit="scene", desc=params.get("scenario", "convert")
    )
    bar.update(sum(s["scenes"] for s in done.values()))
    pool = (
        ProcessPoolExecutor(max_workers=workers, initializer=_ignore_sigint)
        if workers > 1
        else None
    )
    loop = _BlockLoop(out, manifest, params, done, target, num_blocks, block_args, workers, pool)
    try:
        loop.run(bar)
    except BaseException:  # Ctrl-C or a failure: the blocks in hand are not wanted any more
        if pool is not None:
            _stop_workers(pool)
        raise
    finally:
        for fut in loop.pending:
            fut.cancel()
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
        bar.close()
    if target is not None:
        _truncate(out, manifest, done, target)
    return write_manifest(out, manifest, done, target)


def _ignore_sigint() -> None:
    """A worker's start: a Ctrl-C at the terminal is the parent's to handle (each worker
    printed a traceback, and the pool broke under the parent's shutdown)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _stop_workers(pool: ProcessPoolExecutor) -> None:
    """End the workers at once (their shards are written whole or not at all, and only the
    blocks collected are in the manifest), so the parent's shutdown does not wait for them.
    Python 3.14 has ``terminate_workers``; before it the pool's processes are reached
    directly."""
    terminate = getattr(pool, "terminate_workers", None)
    if terminate is not None:
        terminate()
        return
    for process in list((pool._processes or {}).values()):
        process.terminate()


class _BlockLoop:
    """The scheduling state of :func:`_build`: blocks done, futures in flight, the next block."""

    def __init__(
        self,
        out: Path,
        manifest: dict,
        params: dict,
        done: dict[int, dict],
        target: int | None,
        num_blocks: int | None,
        block_args: Callable[[int, int], tuple],
        workers: int,
        pool: ProcessPoolExecutor | None,
    ) -> None:
        self.out = out
        self.manifest = manifest
        self.params = params
        self.done = done  # shared with the caller: block -> manifest entry
        self.target = target
        self.num_blocks = num_blocks
        self.block_args = block_args
        self.workers = workers
        self.pool = pool
        self.pending: dict[Future, int] = {}
        self.next_block = 0
        self.empty_streak = 0

    def run(self, bar) -> None:
        """Schedule and collect blocks until :meth:`finished` or nothing is left to schedule."""
        while not self.finished():
            self.schedule()
            if not self.pending:
                break
            self.collect(bar)

    def contiguous_total(self) -> tuple[int, int]:
        """Scenes in the done blocks 0, 1, ... without a gap, and the first block missing."""
        total, k = 0, 0
        while k in self.done:
            total += self.done[k]["scenes"]
            k += 1
        return total, k

    def finished(self) -> bool:
        """Whether the gapless done blocks hold ``target`` scenes (or are all ``num_blocks``)."""
        total, k = self.contiguous_total()
        return total >= self.target if self.target is not None else k >= self.num_blocks

    def schedule(self) -> None:
        """Keep workers busy, but never schedule blocks that cannot be needed."""
        while len(self.pending) < self.workers:
            k = self._next_needed_block()
            if k is None:
                break
            self._submit(k, self._limit(k))

    def _next_needed_block(self) -> int | None:
        """The next block not done yet, or None if none may be scheduled now."""
        while self.next_block in self.done:
            self.next_block += 1
        if self.num_blocks is not None and self.next_block >= self.num_blocks:
            return None
        if self.target is not None:
            in_flight = self.params["shard_size"] * len(self.pending)  # scenes hoped for
            hoped = sum(s["scenes"] for s in self.done.values()) + in_flight
            if hoped >= self.target and self.pending:
                return None
        return self.next_block

    def _limit(self, k: int) -> int | None:
        """Scenes block ``k`` may accept: never more than are still missing before it."""
        before = [self.done[j]["scenes"] for j in range(k) if j in self.done]
        return (
            self.target - sum(before)
            if self.target is not None and len(before) == k
            else self.target
        )

    def _submit(self, k: int, limit: int | None) -> None:
        """Start block ``k`` (run inline without a pool) and track its future."""
        fn, *args = self.block_args(k, limit)
        if self.pool is None:
            fut: Future = Future()
            fut.set_result(fn(*args))
        else:
            fut = self.pool.submit(fn, *args)
        self.pending[fut] = k
        self.next_block = k + 1

    def collect(self, bar) -> None:
        """Wait for a block to finish; record it, advance ``bar`` and rewrite the manifest."""
        finished_now, _ = wait(self.pending, return_when=FIRST_COMPLETED)
        for fut in finished_now:
            self.pending.pop(fut)
            entry = fut.result()
            self.done[entry["block"]] = entry
            self.empty_streak = self.empty_streak + 1 if entry["scenes"] == 0 else 0
            bar.update(entry["scenes"])
            write_manifest(self.out, self.manifest, self.done, self.target)
        if self.target is not None and self.empty_streak >= 3:
            raise RuntimeError(
                f"{self.out}: three blocks in a row produced no scene; see {MANIFEST}"
            )


def _truncate(out: Path, manifest: dict, done: dict[int, dict], target: int) -> None:
    """Keep exactly the first ``target`` scenes (in seed order); drop blocks past them.

    The manifest is written before any shard is cut or deleted: if the run dies in between,
    the affected blocks are listed as truncated (or not at all) and a rerun redoes them.
    """
    total, cut, drop = 0, [], []
    for k in sorted(done):
        entry = done[k]
        if total >= target:
            drop.append(entry["file"])
            del done[k]
            continue
        keep = min(entry["scenes"], target - total)
        if keep < entry["scenes"]:
            last_seed = entry["seeds"][keep - 1]
            entry.update(
                scenes=keep,
                truncated=True,
                seeds=entry["seeds"][:keep],
                num_agents=entry["num_agents"][:keep],
                num_steps=entry["num_steps"][:keep],
                gen_time_s=entry["gen_time_s"][:keep],
                rejected=[r for r in entry["rejected"] if r[0] < last_seed],
            )
            cut.append((out / entry["file"], keep))
        total += keep
    if not (cut or drop):
        return
    write_manifest(out, manifest, done, target)
    for path, keep in cut:
        save_scenes(load_scenes(path)[:keep], path)
    for name in drop:
        (out / name).unlink(missing_ok=True)
