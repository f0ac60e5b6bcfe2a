"""``counterscene stress --backend ray``: a stress run's batches as Ray tasks, on a cluster
(``--address``) or on a Ray started here.

The driver forms the batches exactly as the serial run does (:func:`~.episodes.chunks`: the
same scenes, seeds and batch boundaries; scenes are read or generated here and travel as
data) and each task runs one whole batch with the serial run's runner
(:func:`~.episodes.make_runner`), because a batched world-model call's floating-point results
can depend on the batch's composition. Finished batches are recorded in episode order (a batch
that finishes early waits for the ones before it), so the records, ``episodes.jsonl`` and
``metrics.json`` are those of the serial run, and a stopped Ray run resumes like any other.

What a task needs travels with it, so a worker needs only this package installed: the world
model's checkpoint files (``config.json``, ``model.safetensors``) and, for an ``sb3:PATH.zip``
planner, the zip's bytes are put into Ray's object store once per run; a worker fetches them
once per run, writes them into a temporary directory, loads them with the usual checked
loaders (safetensors, and the SB3 zip without unpickling) and removes the directory.

Ctrl-C (``KeyboardInterrupt`` in the driver) cancels the tasks still running, with every batch
recorded before it on disk; :class:`RayPool` stops the local Ray it started.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import socket
import tempfile
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType, TracebackType
from typing import Any

from counterscene_env.planners import Planner, SB3Policy
from counterscene_env.scene.core import Scene
from counterscene_env.stress.config import StressConfig
from counterscene_env.stress.episodes import (
    BatchRunner,
    PolicyRunner,
    Progress,
    chunks,
    first_to_run,
    make_runner,
)
from counterscene_env.stress.log import EpisodeLog
from counterscene_env.stress.workers import BATCHES_AHEAD, USER_ERRORS
from counterscene_env.world_model.checkpoint import (
    CONFIG,
    DEFAULT_MODEL_DIR,
    WEIGHTS,
    CheckpointError,
    read_config,
    shared_model,
)

#: How to get Ray: the package's optional extra.
INSTALL_HINT = 'pip install "counterscene-env[ray]"'
#: Times Ray reruns a task whose worker process or node died (a batch is deterministic, so a
#: rerun gives the same records); an exception raised by the task itself is never retried.
TASK_RETRIES = 2
#: How long to wait for a cluster's address to accept a connection [s].
CONNECT_SECONDS = 5.0


class RayMissing(ImportError, RuntimeError):
    """Ray is not installed. An ``ImportError``, and a ``RuntimeError`` so that the command
    reports it in one line, as its other errors."""


def import_ray() -> ModuleType:
    """The ``ray`` module.

    Raises:
        RayMissing: Ray is not installed (the message says how to install it).
    """
    try:
        import ray
    except ImportError as exc:
        raise RayMissing(f"--backend ray needs Ray: {INSTALL_HINT} ({exc})") from None
    return ray


class RayPool:
    """Ray for stress runs: connects (or starts a local Ray) on construction; :meth:`close`
    disconnects from a cluster and stops a local Ray it started. A Ray already initialised in
    this process is used as it is and left so (``address`` is then only checked).

    Args:
        address: a running cluster's address (``ray start --head`` prints it; ``"auto"``: the
            one on this machine); None: a new local Ray.
        workers: batches run at once, one CPU each (>= 1); None: every CPU Ray has. A local
            Ray started here gets exactly ``workers`` CPUs.

    Attributes:
        workers: batches run at once.

    Raises:
        RayMissing: Ray is not installed.
        RuntimeError: Ray cannot be reached at ``address`` or cannot start.
    """

    def __init__(self, address: str | None = None, workers: int | None = None) -> None:
        if workers is not None and workers < 1:
            raise ValueError(f"--workers must be >= 1, got {workers}")
        self.ray = import_ray()
        if address is not None:
            _check_reachable(address)
        self.started = False
        if not self.ray.is_initialized():
            self._init(address, workers)
            self.started = True
        cpus = int(self.ray.cluster_resources().get("CPU", 1))
        self.workers = workers or max(1, cpus)

    def _init(self, address: str | None, workers: int | None) -> None:
        # Ray's own INFO lines would land between the progress bar and the table.
        quiet: dict[str, Any] = {"logging_level": logging.WARNING}
        try:
            if address is not None:  # a cluster's resources are its own: nothing to size
                self.ray.init(address=address, **quiet)
            else:
                # "local": a new Ray, even where `ray start` left a cluster (which Ray would
                # otherwise join, ignoring num_cpus).
                self.ray.init("local", num_cpus=workers, include_dashboard=False, **quiet)
        except (ConnectionError, ValueError, RuntimeError) as exc:
            where = f"at --address {address}" if address else "locally"
            # Ray's reason (e.g. a cluster that wants an auth token) is the exception's cause.
            why = f"{exc} ({exc.__cause__})" if exc.__cause__ else str(exc)
            raise RuntimeError(f"cannot start Ray {where}: {why}") from None

    def close(self) -> None:
        """Shut down the Ray this pool started."""
        if self.started and self.ray.is_initialized():
            self.ray.shutdown()
        self.started = False

    def __enter__(self) -> RayPool:
        return self

    def __exit__(
        self, kind: type | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def run(
        self,
        config: StressConfig,
        model: str = "default",
        env_config: dict | None = None,
        planner_factory: Callable[[], Planner] | None = None,
        progress: bool = True,
        log: EpisodeLog | None = None,
    ) -> list[dict]:
        """Run every episode as Ray tasks; the records of the serial run, in order (arguments
        as :func:`run_ray`). A stop (Ctrl-C) or failure cancels the tasks still running."""
        tally = Progress(config, log, progress)
        pending: dict[Any, int] = {}  # running tasks -> their first episode
        try:
            if first_to_run(config, tally.records) < config.episodes:
                payload = [self.ray.put(_payload(config, model, env_config, planner_factory))]
                self._collect(chunks(config, tally.records), payload, pending, tally)
        finally:
            tally.close()
            # Best effort: the run is stopping anyway. Not force: a running task gets a
            # KeyboardInterrupt, so its worker lives on and removes its temporary files.
            for ref in pending:
                with contextlib.suppress(Exception):
                    self.ray.cancel(ref)
        return tally.records

    def _collect(self, todo, payload: list, pending: dict[Any, int], tally: Progress) -> None:
        """Submit batches (at most ``BATCHES_AHEAD`` per worker unfinished, so scenes are
        drawn lazily) and record their results in episode order until none remain."""
        ray = self.ray
        task = ray.remote(_run_batch).options(num_cpus=1, max_retries=TASK_RETRIES)
        key = uuid.uuid4().hex  # this run's runner, in each worker process
        order: collections.deque[int] = collections.deque()  # submitted, not yet recorded
        done: dict[int, list[dict]] = {}  # finished, not yet recorded (an earlier one runs)

        def feed() -> None:
            while len(pending) < BATCHES_AHEAD * self.workers:
                nxt = next(todo, None)
                if nxt is None:
                    return
                # The payload travels inside a list so that Ray does not fetch it for every
                # task: a worker fetches it once, when it builds its runner.
                pending[task.remote(key, payload, *nxt)] = nxt[0]
                order.append(nxt[0])

        feed()
        while order:
            (ref,), _ = ray.wait(list(pending), num_returns=1)
            first = pending.pop(ref)
            done[first] = _result(ray, ref)
            while order and order[0] in done:
                tally.add(done.pop(order.popleft()))
            feed()


def _check_reachable(address: str) -> None:
    """Refuse a ``HOST:PORT`` address nothing listens on: Ray itself retries such an address
    for minutes before it gives up. Other forms (``auto``, ``ray://...``) are Ray's to check."""
    host, sep, port = address.rpartition(":")
    if not sep or not host or "/" in address or not port.isdigit():
        return
    try:  # an IPv6 host comes in brackets: [::1]:6379
        socket.create_connection((host.strip("[]"), int(port)), timeout=CONNECT_SECONDS).close()
    except OSError as exc:
        raise RuntimeError(f"cannot reach a Ray cluster at --address {address}: {exc}") from None


def run_ray(
    config: StressConfig,
    workers: int | None = None,
    address: str | None = None,
    model: str = "default",
    env_config: dict | None = None,
    planner_factory: Callable[[], Planner] | None = None,
    progress: bool = True,
    log: EpisodeLog | None = None,
) -> list[dict]:
    """Run every episode as Ray tasks; the records of the serial run
    (:func:`~.episodes.run_episodes`, or :func:`~.episodes.run_policy_episodes` for an sb3
    planner) for the same config, in order.

    Args:
        config: the run.
        workers: batches run at once (:class:`RayPool`).
        address: the Ray cluster (:class:`RayPool`).
        model: the world model's directory (``"default"``: the shipped one), read here and
            sent to the workers.
        env_config: sb3 planners: env-config keys on top of the policy's sidecar.
        planner_factory: a fresh planner per episode (default ``make_planner(config.planner)``);
            Ray sends it to the workers (a function or class importable there, or a closure
            cloudpickle can carry).
        progress: show a progress bar with ETA.
        log: as in :func:`~.episodes.run_episodes`.

    Raises:
        RayMissing: Ray is not installed.
        RuntimeError: Ray cannot start, or a task failed (the message holds its traceback).
    """
    with RayPool(address, workers) as pool:
        return pool.run(config, model, env_config, planner_factory, progress, log)


def checkpoint_files(model: str = "default") -> dict[str, bytes]:
    """The files of a world-model checkpoint directory (``"default"``: the shipped one) by
    name, to rebuild the model where the directory does not exist.

    Raises:
        CheckpointError: not a checkpoint directory (the message says why).
    """
    path = DEFAULT_MODEL_DIR if model == "default" else Path(model)
    read_config(path)  # a missing or foreign directory is named here, not on a worker
    out = {}
    for name in (CONFIG, WEIGHTS):
        if not (path / name).is_file():
            raise CheckpointError(f"{str(path)!r} has no {name}")
        out[name] = (path / name).read_bytes()
    return out


@dataclass(frozen=True)
class RunPayload:
    """What every task of a run needs, put into Ray's object store once.

    Attributes:
        config: the run.
        model: the world model's checkpoint files by name (:func:`checkpoint_files`).
        env_config: sb3 planners: every env-config key the policy runs with, its sidecar's
            included (the sidecar does not travel).
        planner_factory: as in :func:`run_ray`.
        policy_name: sb3 planners: the zip's file name (error messages name it).
        policy: sb3 planners: the zip's bytes.
    """

    config: StressConfig
    model: dict[str, bytes]
    env_config: dict | None = None
    planner_factory: Callable[[], Planner] | None = None
    policy_name: str | None = None
    policy: bytes | None = None

    def unpack(self, directory: Path) -> tuple[str, Path | None]:
        """Write the model (and the policy) under ``directory``; their paths."""
        model = directory / "model"
        model.mkdir()
        for name, data in self.model.items():
            (model / name).write_bytes(data)
        if self.policy is None or self.policy_name is None:
            return str(model), None
        policy = directory / "policy" / self.policy_name
        policy.parent.mkdir()
        policy.write_bytes(self.policy)
        return str(model), policy


def _payload(
    config: StressConfig,
    model: str,
    env_config: dict | None,
    planner_factory: Callable[[], Planner] | None,
) -> RunPayload:
    """The run's :class:`RunPayload`, read from this machine's files."""
    files = checkpoint_files(model)
    if not config.is_sb3:
        return RunPayload(config, files, env_config, planner_factory)
    path = config.policy_path
    # Read here: a bad zip is reported before any task runs, and the sidecar's keys travel
    # merged in the order PolicyRunner merges them (sidecar, then the given keys).
    sidecar = SB3Policy(path).env_config
    merged = {**sidecar, **(env_config or {})} or None
    return RunPayload(config, files, merged, planner_factory, path.name, path.read_bytes())


#: This worker process's runner: ``key`` (its run) and ``runner``.
_WORKER: dict[str, Any] = {}


def _run_batch(key: str, payload: list, first: int, scenes: list[Scene]) -> list[dict]:
    """A Ray task: episodes ``first ..`` on ``scenes``, one record each (the serial run's)."""
    import torch

    torch.set_num_threads(1)  # one thread per task: N tasks share N CPUs
    return _runner(key, payload)(first, scenes)


def _runner(key: str, payload: list) -> BatchRunner | PolicyRunner:
    """The runner of run ``key``, built once per worker process (Ray reuses its workers).

    The run's files exist only while it is built: Ray ends its workers without running
    ``atexit``, so files kept for the runner's life would be left behind in every worker."""
    if _WORKER.get("key") == key:
        return _WORKER["runner"]
    import ray

    _release()
    run: RunPayload = ray.get(payload[0])
    with tempfile.TemporaryDirectory(prefix="counterscene-ray-") as files:
        model, policy = run.unpack(Path(files))
        if run.config.is_sb3:
            # The env loads its model by name through shared_model (once per process and
            # name): loading it now keeps it for the env after the files are gone.
            shared_model(model)
        runner = make_runner(run.config, model, run.env_config, run.planner_factory, policy)
    _WORKER.update(key=key, runner=runner)
    return runner


def _release() -> None:
    """Close the previous run's runner in this worker."""
    if _WORKER:
        _WORKER.pop("runner").close()
        _WORKER.clear()


def _result(ray: ModuleType, ref: Any) -> list[dict]:
    """A finished task's records; its failure as the serial run would report it."""
    try:
        return ray.get(ref)
    except ray.exceptions.RayTaskError as exc:
        if isinstance(exc.cause, USER_ERRORS):
            raise exc.cause from None  # bad input (e.g. a policy whose spaces do not fit)
        raise RuntimeError(f"stress task failed:\n{exc}") from None
    except ray.exceptions.RayError as exc:  # a worker or node lost, retries spent
        raise RuntimeError(f"stress task failed: {exc}") from None
